//! The command line as a library (`nerf_cli::run_with`): commands run in this process with the
//! registry they are given, several in a row (one Ctrl-C handler for the process), and usage
//! errors come back as errors instead of ending the process.

use std::path::Path;

fn scene() -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/lego_100").display().to_string()
}

/// A registry with the voxel field alone.
fn voxel_only() -> nerf::field::Registry {
    let mut r = nerf::field::Registry::new();
    r.register(nerf::field_voxel::registry_entry());
    r
}

#[test]
fn commands_run_in_process_with_the_registry_they_are_given() {
    let registry = voxel_only();
    nerf_cli::run_with(&registry, ["nerf", "fields"]).unwrap();

    // A field the given registry lacks is unknown, and the error lists what it holds.
    let e = nerf_cli::run_with(&registry, ["nerf", "train", &scene(), "--field", "hash", "--iters", "1"]).unwrap_err();
    let text = format!("{e:#}");
    assert!(text.contains("hash") && text.contains("voxel") && !text.contains("freq"), "{text}");

    // Two training commands in one process: each installs nothing the other trips over (a
    // process can hold one Ctrl-C handler).
    let dir = tempfile::tempdir().unwrap();
    for i in 0..2 {
        let out = dir.path().join(format!("run{i}"));
        let args = ["nerf", "train", &scene(), "--field", "voxel", "--iters", "2", "--test-views", "first:1", "--quiet", "--no-renders"];
        nerf_cli::run_with(&registry, args.iter().map(|s| s.to_string()).chain([format!("--out={}", out.display())])).unwrap();
        let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
        assert_eq!(metrics["field"], "voxel");
        assert_eq!(metrics["iterations"], 2);
    }
}

#[test]
fn usage_errors_are_returned_not_exited() {
    let e = nerf_cli::run_with(&voxel_only(), ["nerf", "train"]).unwrap_err();
    assert!(format!("{e}").contains("SCENE"), "{e}");
    assert!(!nerf_cli::is_interrupted(&e));
    assert!(nerf_cli::run_with(&voxel_only(), ["nerf", "--no-such-flag"]).is_err());
}
