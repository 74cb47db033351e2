//! The `nerf` binary end to end: bad input gives a clear error naming the file (exit code ≠ 0, no
//! panic), Ctrl-C saves a checkpoint that `--resume` continues from.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn nerf() -> Command {
    Command::new(env!("CARGO_BIN_EXE_nerf"))
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Fails unless the command failed cleanly (exit 1, no panic) with a message containing `needles`.
fn assert_clean_failure(o: &Output, needles: &[&str]) {
    let e = stderr(o);
    assert_eq!(o.status.code(), Some(1), "expected exit code 1, stderr: {e}");
    assert!(!e.contains("panicked"), "must not panic: {e}");
    for n in needles {
        assert!(e.contains(n), "stderr should mention `{n}`: {e}");
    }
}

/// A copy of the in-repo scene with only a few views, which tests may break.
fn small_scene(dir: &Path) -> PathBuf {
    let out = dir.join("scene");
    let o = nerf()
        .args(["export-scene"])
        .arg(repo().join("scenes/lego_100"))
        .arg(&out)
        .args(["--downscale", "2", "--train-views", "first:3", "--test-views", "first:1"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    out
}

/// [`small_scene`] and a two-step [`train_tiny`] run on it on the CPU, in `dir`: the scene and
/// the run folder.
fn tiny_cpu_run(dir: &Path) -> (PathBuf, PathBuf) {
    let s = small_scene(dir);
    let run = dir.join("run");
    let o = train_tiny(&s, &run, &["--iters", "2", "--device", "cpu"]);
    assert!(o.status.success(), "{}", stderr(&o));
    (s, run)
}

/// A tiny field and sampler so that steps take milliseconds.
fn write_tiny_config(cfg: &Path) {
    std::fs::write(
        cfg,
        "batch_rays = 64\ncheckpoint_every = 5\nlog_every = 1\n[field_config]\nwidth = 16\ndepth = 2\nskips = []\nview_width = 8\n\
         [sampler]\nkind = \"hierarchical\"\nn_coarse = 8\nn_fine = 8\n",
    )
    .unwrap();
}

fn train_tiny(scene: &Path, out: &Path, extra: &[&str]) -> Output {
    let cfg = out.with_extension("toml");
    write_tiny_config(&cfg);
    nerf()
        .arg("train")
        .arg(scene)
        .arg("--config")
        .arg(&cfg)
        .arg("--out")
        .arg(out)
        .args(["--quiet", "--no-renders"])
        .args(extra)
        .output()
        .unwrap()
}

#[test]
fn missing_scene_folder_names_the_transforms_file() {
    let d = tempfile::tempdir().unwrap();
    let o = train_tiny(&d.path().join("nope"), &d.path().join("run"), &["--iters", "1"]);
    assert_clean_failure(&o, &["transforms_train.json"]);
}

#[test]
fn malformed_json_names_the_file() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    std::fs::write(s.join("transforms_train.json"), "{ \"camera_angle_x\": 0.69, \"frames\": [ }").unwrap();
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "1"]);
    assert_clean_failure(&o, &["transforms_train.json", "malformed JSON", "line 1 column"]);
    // The parser's position once: the library's message holds its source already, and the
    // binary does not repeat it from the error's chain.
    assert_eq!(stderr(&o).matches("line 1 column").count(), 1, "{}", stderr(&o));
}

#[test]
fn malformed_config_names_the_file_and_the_parsers_message() {
    // An error with context added at the binary's edge (anyhow) keeps its cause on the line.
    let d = tempfile::tempdir().unwrap();
    let cfg = d.path().join("bad.toml");
    std::fs::write(&cfg, "batch_rays = = 3\n").unwrap();
    let o = nerf().arg("train").arg(repo().join("scenes/lego_100")).arg("--config").arg(&cfg).arg("--out").arg(d.path().join("run")).output().unwrap();
    assert_clean_failure(&o, &["bad.toml", "malformed TOML", "line 1"]);
}

#[test]
fn missing_image_names_the_image() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    std::fs::remove_file(s.join("train/r_1.png")).unwrap();
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "1"]);
    assert_clean_failure(&o, &["r_1.png"]);
}

/// A scene whose frames name training masks (nerfstudio's `mask_path`) trains, saying how much
/// the masks keep; a missing mask is named with its frame.
#[test]
fn a_scene_with_masks_trains_and_a_missing_mask_is_named() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let p = s.join("transforms_train.json");
    let mut t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    for (i, f) in t["frames"].as_array_mut().unwrap().iter_mut().enumerate() {
        f["mask_path"] = serde_json::json!(format!("masks/{i}.png"));
        std::fs::create_dir_all(s.join("masks")).unwrap();
        // The left half of each 50×50 view kept.
        image::GrayImage::from_fn(50, 50, |x, _| image::Luma([if x < 25 { 255 } else { 0 }])).save(s.join(format!("masks/{i}.png"))).unwrap();
    }
    std::fs::write(&p, serde_json::to_string(&t).unwrap()).unwrap();
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("training masks keep 50.0 % of the training views' pixels"), "{}", stderr(&o));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.path().join("run/metrics.json")).unwrap()).unwrap();
    assert!(metrics["test_masked"].is_null() && metrics["per_view"][0].get("masked").is_none(), "test views without masks score whole: {metrics}");
    std::fs::remove_file(s.join("masks/1.png")).unwrap();
    let o = train_tiny(&s, &d.path().join("run2"), &["--iters", "1"]);
    assert_clean_failure(&o, &["masks/1.png", "mask of frame 1", "not found"]);
}

/// Test views with masks are also scored over the pixels their masks keep (`test_masked` and
/// each view's `masked` in metrics.json and eval.json, printed by `nerf eval`): the scores agree
/// with the written render against the ground truth over the kept pixels.
#[test]
fn test_views_with_masks_are_scored_over_the_kept_pixels() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let p = s.join("transforms_test.json");
    let mut t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    std::fs::create_dir_all(s.join("masks")).unwrap();
    // The top 20 rows of each 50×50 test view kept (40 %).
    for (i, f) in t["frames"].as_array_mut().unwrap().iter_mut().enumerate() {
        f["mask_path"] = serde_json::json!(format!("masks/t{i}.png"));
        image::GrayImage::from_fn(50, 50, |_, y| image::Luma([if y < 20 { 255 } else { 0 }])).save(s.join(format!("masks/t{i}.png"))).unwrap();
    }
    std::fs::write(&p, serde_json::to_string(&t).unwrap()).unwrap();
    let run = d.path().join("run");
    let o = train_tiny(&s, &run, &["--iters", "3", "--device", "cpu"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["test_masked"]["kept_fraction"], 0.4, "{}", metrics["test_masked"]);
    assert_eq!(metrics["per_view"][0]["masked"]["kept_fraction"], 0.4);
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--quiet", "--device", "cpu"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(out.contains("over the pixels the masks keep (40.0 % of them): PSNR"), "{out}");
    let eval: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("eval/eval.json")).unwrap()).unwrap();
    let (psnr, masked) = (eval["test_psnr"].as_f64().unwrap(), eval["test_masked"]["psnr"].as_f64().unwrap());
    // The render as written against the ground truth on white, whole and over the kept rows.
    let render = std::fs::read_dir(run.join("eval")).unwrap().map(|e| e.unwrap().path()).find(|p| p.extension().is_some_and(|e| e == "png")).unwrap();
    let render = image::open(&render).unwrap().to_rgb8();
    let file = t["frames"][0]["file_path"].as_str().unwrap().trim_start_matches("./");
    let gt = image::open(s.join(format!("{file}.png"))).unwrap().to_rgba8();
    let (mut sse, mut sse_kept) = (0.0f64, 0.0f64);
    for (x, y, px) in gt.enumerate_pixels() {
        let a = px[3] as f64 / 255.0;
        for c in 0..3 {
            let g = px[c] as f64 / 255.0 * a + (1.0 - a);
            let e = (render.get_pixel(x, y)[c] as f64 / 255.0 - g).powi(2);
            sse += e;
            if y < 20 {
                sse_kept += e;
            }
        }
    }
    let (whole, kept) = (-10.0 * (sse / 7500.0).log10(), -10.0 * (sse_kept / 3000.0).log10());
    assert!((whole - psnr).abs() < 0.05, "whole view: {whole} from the PNG, {psnr} reported");
    assert!((kept - masked).abs() < 0.05, "kept rows: {kept} from the PNG, {masked} reported");
    assert!((masked - psnr).abs() > 0.1, "the kept rows score apart from the whole view: {masked} vs {psnr}");
}

/// A scene with depth maps (nerfstudio's `depth_file_path`, millimetres): `nerf train` says how
/// much of the views they measure and that `depth_loss` trains on them; with it in the config the
/// run trains on them (and says so); a missing depth map is named.
#[test]
fn a_scene_with_depth_maps_trains_on_them_and_a_missing_one_is_named() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let p = s.join("transforms_train.json");
    let mut t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    std::fs::create_dir_all(s.join("depth")).unwrap();
    for (i, f) in t["frames"].as_array_mut().unwrap().iter_mut().enumerate() {
        f["depth_file_path"] = serde_json::json!(format!("depth/{i}.png"));
        // 4 m on the top 10 rows of each 50×50 view, nothing below.
        let map = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(50, 50, |_, y| image::Luma([if y < 10 { 4000 } else { 0 }]));
        map.save(s.join(format!("depth/{i}.png"))).unwrap();
    }
    std::fs::write(&p, serde_json::to_string(&t).unwrap()).unwrap();
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("the depth maps measure 20.0 % of the training views' pixels; set depth_loss"), "{}", stderr(&o));
    let run = d.path().join("run2");
    let cfg = run.with_extension("toml");
    write_tiny_config(&cfg);
    let text = std::fs::read_to_string(&cfg).unwrap();
    std::fs::write(&cfg, format!("depth_loss = 0.1\n{text}")).unwrap();
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(&run).args(["--quiet", "--no-renders", "--iters", "3"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("depth maps measure 20.0 % of the training views' pixels: trained on with depth_loss = 0.1"), "{}", stderr(&o));
    std::fs::remove_file(s.join("depth/1.png")).unwrap();
    let o = train_tiny(&s, &d.path().join("run3"), &["--iters", "1"]);
    assert_clean_failure(&o, &["depth/1.png", "depth map of frame 1", "not found"]);
}

/// A COLMAP text model of lego_100's first 12 training views (PINHOLE, images copied beside
/// it) with 2000 points in lego's box, each observed by the views it projects into.
fn colmap_lego(dir: &Path) -> PathBuf {
    let lego = repo().join("scenes/lego_100");
    let t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(lego.join("transforms_train.json")).unwrap()).unwrap();
    let f = 50.0 / (0.5 * t["camera_angle_x"].as_f64().unwrap()).tan();
    let root = dir.join("colmap");
    std::fs::create_dir_all(root.join("images")).unwrap();
    std::fs::create_dir_all(root.join("sparse/0")).unwrap();
    std::fs::write(root.join("sparse/0/cameras.txt"), format!("1 PINHOLE 100 100 {f} {f} 50 50\n")).unwrap();
    // World-to-camera (OpenCV axes) of each view: R = (c2w_gl · diag(1, −1, −1))ᵀ, t = −R·c.
    let mut views = Vec::new();
    let mut images = String::new();
    for (i, fr) in t["frames"].as_array().unwrap()[..12].iter().enumerate() {
        let m = |r: usize, c: usize| fr["transform_matrix"][r][c].as_f64().unwrap();
        let r: [[f64; 3]; 3] = std::array::from_fn(|a| std::array::from_fn(|b| m(b, a) * if a == 0 { 1.0 } else { -1.0 }));
        let c = [m(0, 3), m(1, 3), m(2, 3)];
        let tr: [f64; 3] = std::array::from_fn(|a| -(0..3).map(|k| r[a][k] * c[k]).sum::<f64>());
        // The rotation's quaternion (w, x, y, z), w > 0: none of these views turns by a half turn,
        // where this formula would not hold.
        let w = (1.0 + r[0][0] + r[1][1] + r[2][2]).max(0.0).sqrt() / 2.0;
        assert!(w > 1e-3, "view {i}: a half-turn rotation");
        let q = [w, (r[2][1] - r[1][2]) / (4.0 * w), (r[0][2] - r[2][0]) / (4.0 * w), (r[1][0] - r[0][1]) / (4.0 * w)];
        let name = format!("view_{i:03}.png");
        let rel = fr["file_path"].as_str().unwrap().trim_start_matches("./");
        std::fs::copy(lego.join(format!("{rel}.png")), root.join("images").join(&name)).unwrap();
        images += &format!("{} {} {} {} {} {} {} {} 1 {name}\n\n", i + 1, q[0], q[1], q[2], q[3], tr[0], tr[1], tr[2]);
        views.push((r, tr));
    }
    std::fs::write(root.join("sparse/0/images.txt"), images).unwrap();
    let mut points = String::new();
    let mut state = 7u64;
    let mut rnd = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64 * 1.4 - 0.7
    };
    for k in 0..2000 {
        let x = [rnd(), rnd(), rnd()];
        let track: Vec<String> = views
            .iter()
            .enumerate()
            .filter(|(_, (r, tr))| {
                let xc: [f64; 3] = std::array::from_fn(|a| (0..3).map(|b| r[a][b] * x[b]).sum::<f64>() + tr[a]);
                let (u, v) = (f * xc[0] / xc[2] + 50.0, f * xc[1] / xc[2] + 50.0);
                xc[2] > 0.0 && (0.0..100.0).contains(&u) && (0.0..100.0).contains(&v)
            })
            .map(|(i, _)| format!("{} 0", i + 1))
            .collect();
        points += &format!("{} {} {} {} 128 128 128 0.5 {}\n", k + 1, x[0], x[1], x[2], track.join(" "));
    }
    std::fs::write(root.join("sparse/0/points3D.txt"), points).unwrap();
    root
}

/// `--scene-format colmap` reads a folder's COLMAP model whatever else it holds (mip-NeRF 360's
/// scenes hold LLFF's poses_bounds.npy beside it, which the default would read); the run records
/// it, so `nerf eval` loads the same; a format whose files are missing is named.
#[test]
fn scene_format_picks_the_loader_and_the_run_keeps_it() {
    let d = tempfile::tempdir().unwrap();
    let src = colmap_lego(d.path());
    // Poses the LLFF loader cannot read: the default loader reads them and fails.
    std::fs::write(src.join("poses_bounds.npy"), b"not an array").unwrap();
    let o = train_tiny(&src, &d.path().join("auto"), &["--iters", "1", "--device", "cpu"]);
    assert_clean_failure(&o, &["poses_bounds.npy"]);
    let run = d.path().join("run");
    let o = train_tiny(&src, &run, &["--iters", "2", "--device", "cpu", "--scene-format", "colmap"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["config"]["scene_format"], "colmap");
    let o = nerf().arg("eval").arg(&run).arg(&src).args(["--quiet", "--device", "cpu"]).output().unwrap();
    assert!(o.status.success(), "eval reads the model as the run did: {}", stderr(&o));
    // A format whose files the folder lacks.
    let o = train_tiny(&repo().join("scenes/lego_100"), &d.path().join("llff"), &["--iters", "1", "--scene-format", "llff"]);
    assert_clean_failure(&o, &["poses_bounds.npy"]);
    let o = train_tiny(&repo().join("scenes/lego_100"), &d.path().join("colmap"), &["--iters", "1", "--scene-format", "colmap"]);
    assert_clean_failure(&o, &["sparse/0"]);
}

/// `nerf export-scene --sfm-depth` writes a COLMAP folder's points as sparse depth maps beside
/// the images (what `nerf train` with `depth_loss` trains on, and depth-nerfacto reads); on a
/// scene that is not a COLMAP folder it says so.
#[test]
fn export_scene_writes_sfm_depth_maps_of_a_colmap_folder() {
    let d = tempfile::tempdir().unwrap();
    let src = colmap_lego(d.path());
    let dst = d.path().join("out");
    let o = nerf().arg("export-scene").arg(&src).arg(&dst).args(["--downscale", "1", "--test-views", "first:1", "--sfm-depth"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dst.join("transforms_train.json")).unwrap()).unwrap();
    assert!(t["depth_unit_scale_factor"].as_f64().is_some_and(|s| s > 0.0), "{t}");
    let frames = t["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 10, "12 views, every 8th a test view");
    let map = image::open(dst.join(frames[0]["depth_file_path"].as_str().unwrap())).unwrap().into_luma16();
    let measured = map.pixels().filter(|p| p[0] > 0).count();
    assert!(measured > 100 && measured < 5000, "{measured} measured pixels of 10 000: sparse");
    // Without --sfm-depth: no depth maps; on a scene that is not a COLMAP folder: an error.
    let plain = d.path().join("plain");
    let o = nerf().arg("export-scene").arg(&src).arg(&plain).args(["--downscale", "1", "--test-views", "first:1"]).output().unwrap();
    assert!(o.status.success() && !std::fs::read_to_string(plain.join("transforms_train.json")).unwrap().contains("depth_file_path"));
    let o = nerf().arg("export-scene").arg(repo().join("scenes/lego_100")).arg(d.path().join("x")).arg("--sfm-depth").output().unwrap();
    assert_clean_failure(&o, &["lego_100", "--sfm-depth needs a COLMAP folder"]);
}

#[test]
fn wrong_image_size_names_the_image() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    image::RgbaImage::new(7, 9).save(s.join("train/r_2.png")).unwrap();
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "1"]);
    assert_clean_failure(&o, &["r_2.png"]);
}

/// Photos past 1600 pixels on a side trained at full resolution: a note with the downscale
/// nerfstudio would train them at; none once it is given.
#[test]
fn large_photos_get_a_downscale_note() {
    let d = tempfile::tempdir().unwrap();
    let s = d.path().join("wide");
    std::fs::create_dir_all(&s).unwrap();
    image::RgbaImage::from_pixel(3400, 4, image::Rgba([200, 100, 50, 255])).save(s.join("p.png")).unwrap();
    let frames = serde_json::json!([{"file_path": "p.png", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}]);
    for split in ["train", "test"] {
        std::fs::write(s.join(format!("transforms_{split}.json")), serde_json::json!({"camera_angle_x": 0.7, "frames": frames}).to_string()).unwrap();
    }
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("up to 3400 pixels on a side") && stderr(&o).contains("--downscale 4"), "{}", stderr(&o));
    let o = train_tiny(&s, &d.path().join("run2"), &["--iters", "1", "--downscale", "2"]);
    assert!(o.status.success() && !stderr(&o).contains("pixels on a side"), "{}", stderr(&o));
}

#[test]
fn nan_pose_names_the_file_and_frame() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let p = s.join("transforms_train.json");
    let mut j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    // JSON has no NaN literal; an overflowing number is the way a non-finite pose arrives.
    j["frames"][1]["transform_matrix"][0][3] = serde_json::json!(1e300);
    std::fs::write(&p, serde_json::to_string(&j).unwrap()).unwrap();
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "1"]);
    assert_clean_failure(&o, &["transforms_train.json", "frame 1"]);
}

/// An LLFF scene (fern, from ../shared) is recognised by its poses_bounds.npy; a downscale with no
/// image folder says which factors the scene has.
#[test]
fn an_llff_scene_is_recognised_and_a_missing_image_folder_named() {
    let Some(fern) = nerf::core::shared::data(env!("CARGO_MANIFEST_DIR"), "nerf_llff_data/fern") else {
        eprintln!("NOTICE: ../shared/data/nerf_llff_data/fern is absent; not checked");
        return;
    };
    let d = tempfile::tempdir().unwrap();
    let o = nerf().arg("train").arg(&fern).args(["--field", "hash", "--iters", "1"]).arg("--out").arg(d.path()).output().unwrap();
    assert_clean_failure(&o, &["fern/images", "images_4, images_8", "--downscale 8"]);
}

#[test]
fn an_llff_run_keeps_its_ray_space_through_eval_and_render() {
    let Some(fern) = nerf::core::shared::data(env!("CARGO_MANIFEST_DIR"), "nerf_llff_data/fern") else {
        eprintln!("NOTICE: ../shared/data/nerf_llff_data/fern is absent; not checked");
        return;
    };
    let d = tempfile::tempdir().unwrap();
    // images_8 box-averaged by 6: 84×63; two small hash steps, one test view. The untrained field
    // is opaque nowhere, so every render marches whole rays: 0.02 steps on a 32³ grid (the
    // preset's 0.005 steps made this test 3× as long).
    let cfg = d.path().join("small.toml");
    std::fs::write(&cfg, "target_samples_per_step = 4096\n[sampler]\nkind = \"occupancy\"\nstep_size = 0.02\nmax_samples_per_ray = 256\n[sampler.grid]\nresolution = 32\n").unwrap();
    for (flag, space) in [(None, "ndc"), (Some("--no-ndc"), "euclidean")] {
        let run = d.path().join(space);
        let mut cmd = nerf();
        cmd.arg("train").arg(&fern).args(["--field", "hash", "--iters", "2", "--downscale", "48", "--test-views", "first:1", "--config"]).arg(&cfg);
        cmd.args(["--device", "cpu", "--quiet", "--no-renders"]).arg("--out").arg(&run).args(flag);
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
        assert_eq!(m["ray_space"], space, "{m}");
        assert_eq!(m["config"].get("ndc").and_then(|v| v.as_bool()).unwrap_or(true), space == "ndc");
        // eval loads the scene in the run's ray space: the same PSNR (the other space would give
        // the field rays it never saw).
        let o = nerf().arg("eval").arg(&run).arg(&fern).args(["--device", "cpu"]).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let e: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("eval/eval.json")).unwrap()).unwrap();
        let (a, b) = (m["test_psnr"].as_f64().unwrap(), e["test_psnr"].as_f64().unwrap());
        assert!((a - b).abs() < 1e-9, "{space}: eval must reproduce the run's PSNR: {a} vs {b}");
        let o = nerf().arg("render").arg(&run).arg(&fern).args(["--frames", "2", "--width", "32", "--device", "cpu", "--depth"]).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(run.join("render/frame_0001.png").is_file() && run.join("render/depth_0001.png").is_file());
        // Depth of field in either space (the lens moves the rays before NDC warps them), focused
        // by default at the depth nerf-pytorch's spiral looks at: one distance for every frame.
        let o = nerf().arg("render").arg(&run).arg(&fern).args(["--frames", "2", "--width", "16", "--spp", "2", "--aperture", "0.01", "--device", "cpu", "--quiet", "--out"]).arg(run.join("dof")).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("dof/render.json")).unwrap()).unwrap();
        let focus: Vec<f64> = (0..2).map(|i| r["lenses"][i][1].as_f64().unwrap()).collect();
        assert!(focus[0] > 0.0 && focus[0] == focus[1], "{r}");
        if space == "ndc" {
            let o = nerf().arg("render").arg(&run).arg(&fern).args(["--frames", "1", "--width", "16", "--aperture", "0.01", "--focus", "auto", "--device", "cpu"]).output().unwrap();
            assert_clean_failure(&o, &["--focus auto", "NDC"]);
        }
        // A point cloud needs distances: the Euclidean run gives one, the NDC run a clear error.
        let o = nerf().arg("export-points").arg(&run).arg(&fern).args(["--points", "50", "--min-opacity", "0", "--device", "cpu"]).output().unwrap();
        match space {
            "ndc" => assert_clean_failure(&o, &["NDC", "--no-ndc"]),
            _ => assert!(o.status.success() && run.join("points.ply").is_file(), "{}", stderr(&o)),
        }
        // An instant-ngp camera path: instant-ngp does not read LLFF scenes, so there is no
        // space its keyframes could be in.
        if space == "ndc" {
            let o = nerf().arg("render").arg(&run).arg(&fern).args(["--frames", "1", "--normals", "--device", "cpu"]).output().unwrap();
            assert_clean_failure(&o, &["NDC", "--normals", "--no-ndc"]);
        }
        let base_cam = d.path().join("base_cam.json");
        std::fs::write(&base_cam, r#"{"path": [{"R": [0, 0, 0, 1], "T": [0.5, 0.5, 0.5], "fov": 50}]}"#).unwrap();
        let o = nerf().arg("render").arg(&run).arg(&fern).arg("--camera-path").arg(&base_cam).args(["--frames", "1", "--device", "cpu"]).output().unwrap();
        assert_clean_failure(&o, &["base_cam.json", "instant-ngp", "LLFF"]);
        // And a panorama (NDC holds only what lies in front of the cameras).
        let o = nerf().arg("render").arg(&run).arg(&fern).args(["--camera-type", "equirectangular", "--frames", "1", "--width", "16", "--device", "cpu"]).output().unwrap();
        match space {
            "ndc" => assert_clean_failure(&o, &["NDC", "equirectangular", "--no-ndc"]),
            _ => assert!(o.status.success(), "{}", stderr(&o)),
        }
        // So does a mesh (the field lives in NDC space there).
        let o = nerf().arg("export-mesh").arg(&run).arg(&fern).args(["--resolution", "16", "--threshold", "1e-6", "--device", "cpu"]).output().unwrap();
        match space {
            "ndc" => assert_clean_failure(&o, &["NDC", "--no-ndc"]),
            _ => assert!(o.status.success() && run.join("mesh.ply").is_file(), "{}", stderr(&o)),
        }
    }
    // Resuming in the other ray space is refused, naming the checkpoint.
    let run = d.path().join("ndc");
    let o = nerf().arg("train").arg(&fern).args(["--field", "hash", "--iters", "3", "--downscale", "48", "--test-views", "first:1", "--config"]).arg(&cfg)
        .args(["--device", "cpu", "--quiet", "--no-renders", "--resume", "--no-ndc"]).arg("--out").arg(&run).output().unwrap();
    assert_clean_failure(&o, &["checkpoint.bin", "NDC rays", "without --no-ndc"]);
}

#[test]
fn empty_split_is_an_error() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    std::fs::write(s.join("transforms_test.json"), "{\"camera_angle_x\": 0.69, \"frames\": []}").unwrap();
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "1"]);
    assert_clean_failure(&o, &["transforms_test.json"]);
}

#[test]
fn unknown_field_and_bad_config_are_errors() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "1", "--field", "nope"]);
    assert_clean_failure(&o, &["nope", "freq"]);
    let cfg = d.path().join("bad.toml");
    std::fs::write(&cfg, "iterz = 3\n").unwrap();
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).output().unwrap();
    assert_clean_failure(&o, &["bad.toml", "iterz"]);
    // A value the config's own checks refuse: the message names the file it may come from.
    std::fs::write(&cfg, "batch_rays = 0\n").unwrap();
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).output().unwrap();
    assert_clean_failure(&o, &["bad.toml", "batch_rays must be positive"]);
}

/// A checkpoint with one flipped bit is refused by `eval` and by `train --resume`, naming the file
/// (it carries a CRC-32), instead of rendering or training on from wrong weights.
#[test]
fn a_corrupted_checkpoint_is_refused_by_name() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let ck = run.join("checkpoint.bin");
    let mut bytes = std::fs::read(&ck).unwrap();
    let at = bytes.len() / 2; // inside the tensors
    bytes[at] ^= 0x04;
    std::fs::write(&ck, &bytes).unwrap();
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--device", "cpu", "--quiet"]).output().unwrap();
    assert_clean_failure(&o, &["checkpoint.bin", "checksum mismatch", "corrupted"]);
    let o = train_tiny(&s, &run, &["--iters", "4", "--device", "cpu", "--resume"]);
    assert_clean_failure(&o, &["checkpoint.bin", "checksum mismatch"]);
}

#[test]
fn degenerate_pose_names_the_file_and_frame() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let p = s.join("transforms_train.json");
    let mut j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    // A zeroed rotation block: it used to train to NaN ("training diverged") instead.
    j["frames"][1]["transform_matrix"] = serde_json::json!([[0, 0, 0, 1], [0, 0, 0, 2], [0, 0, 0, 3], [0, 0, 0, 1]]);
    std::fs::write(&p, serde_json::to_string(&j).unwrap()).unwrap();
    let o = train_tiny(&s, &d.path().join("run"), &["--iters", "1"]);
    assert_clean_failure(&o, &["transforms_train.json", "frame 1", "degenerate camera pose"]);
}

#[test]
fn train_writes_metrics_with_the_stable_keys_and_eval_reproduces_them() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let run = d.path().join("run");
    let o = train_tiny(&s, &run, &["--iters", "3"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    for k in [
        "field", "device", "iterations", "wall_seconds", "ms_per_iter", "samples_per_sec", "test_psnr", "test_ssim",
        "n_test_views", "width", "height", "config",
    ] {
        assert!(m.get(k).is_some(), "metrics.json lacks `{k}`: {m}");
    }
    assert_eq!(m["field"], "freq");
    // `auto` never picks a software adapter (lavapipe), and this machine has no hardware GPU
    // unless it says so; either way the device is recorded with its adapter.
    let dev = m["device"].as_str().unwrap();
    assert!(dev == "cpu" || dev == "gpu", "{dev}");
    assert_eq!(m["adapter"].is_null(), dev == "cpu", "{m}");
    assert_eq!(m["iterations"], 3);
    assert_eq!(m["width"], 50);
    assert_eq!(m["n_test_views"], 1);
    assert!(m["samples_per_sec"].as_f64().unwrap() > 0.0);
    let o = nerf().arg("eval").arg(&run).arg(&s).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let e: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval/eval.json")).unwrap()).unwrap();
    let (a, b) = (m["test_psnr"].as_f64().unwrap(), e["test_psnr"].as_f64().unwrap());
    assert!((a - b).abs() < 1e-9, "eval of the checkpoint must reproduce the run's PSNR: {a} vs {b}");
    assert!(run.join("eval/r_0.png").is_file());
    assert_eq!(e["background"], "white");
    assert_eq!(e["split"], "test");
    // The training views, rendered and scored as the test views are: all three of them, read
    // from the scene's train/ folder, with their own score.
    let train = d.path().join("eval_train");
    let o = nerf().arg("eval").arg(&run).arg(&s).arg("--out").arg(&train).args(["--split", "train", "--views", "all"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).starts_with("train PSNR"), "{}", String::from_utf8_lossy(&o.stdout));
    let t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(train.join("eval.json")).unwrap()).unwrap();
    assert_eq!((&t["split"], &t["n_test_views"]), (&serde_json::json!("train"), &serde_json::json!(3)));
    let files: Vec<&str> = t["per_view"].as_array().unwrap().iter().map(|v| v["file"].as_str().unwrap()).collect();
    assert!(files.len() == 3 && files.iter().all(|f| f.contains("train")), "{files:?}");
    assert!((t["test_psnr"].as_f64().unwrap() - b).abs() > 1e-6, "train {} vs test {b}", t["test_psnr"]);
    // Scored on black (instant-ngp's protocol): the render and the ground truth both composited
    // on black. After 3 steps the field is nearly empty, so the render's corner is the background.
    let black = d.path().join("eval_black");
    let o = nerf().arg("eval").arg(&run).arg(&s).arg("--out").arg(&black).args(["--background", "black"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let k: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(black.join("eval.json")).unwrap()).unwrap();
    assert_eq!(k["background"], "black");
    assert!((k["test_psnr"].as_f64().unwrap() - b).abs() > 1e-3, "black {} vs white {b}", k["test_psnr"]);
    let corner = |p: &Path| image::open(p).unwrap().to_rgb8().get_pixel(0, 0).0;
    assert!(corner(&run.join("eval/r_0.png")).iter().all(|&c| c > 200), "{:?}", corner(&run.join("eval/r_0.png")));
    assert!(corner(&black.join("r_0.png")).iter().all(|&c| c < 55), "{:?}", corner(&black.join("r_0.png")));
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--background", "random"]).output().unwrap();
    // A random background has no fixed colour to score on: clap names the values it takes.
    assert!(!o.status.success() && stderr(&o).contains("random") && stderr(&o).contains("black"), "{}", stderr(&o));
    // This run's sampler is the hierarchical one: no marching step to change.
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--step-size", "0.0025"]).output().unwrap();
    assert_clean_failure(&o, &["--step-size", "occupancy"]);
    // Supersampled through Cycles' pixel filter: eval.json records the filter and the rays, the
    // score line names them; a filter that is not one, or a width out of range, is a clear error.
    let bh = d.path().join("eval_bh");
    let o = nerf().arg("eval").arg(&run).arg(&s).arg("--out").arg(&bh).args(["--spp", "4", "--filter", "blackman-harris:2"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("4 rays per pixel (Blackman-Harris, filter width 2 px)"), "{}", String::from_utf8_lossy(&o.stdout));
    let f: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(bh.join("eval.json")).unwrap()).unwrap();
    assert_eq!((&f["spp"], &f["filter"]), (&serde_json::json!(4), &serde_json::json!({"kind": "blackman_harris", "width": 2.0})));
    assert_eq!(e["filter"], serde_json::json!({"kind": "box"}));
    for (bad, needle) in [("gauss", "not a pixel filter"), ("blackman-harris:wide", "not a width"), ("blackman-harris:0", "(0, 8]")] {
        // (clap's usage error: exit code 2.)
        let o = nerf().arg("eval").arg(&run).arg(&s).args(["--filter", bad]).output().unwrap();
        let err = stderr(&o);
        assert!(o.status.code() == Some(2) && !err.contains("panicked") && err.contains("--filter") && err.contains(needle), "{bad}: {err}");
    }
}

/// `--eval-every N`: the run scores the test views every N steps (history.jsonl, not at the last
/// step, whose evaluation is metrics.json's), and ends exactly where the same run without it ends.
#[test]
fn eval_every_scores_during_the_run_and_leaves_it_unchanged() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let (plain, probed) = (d.path().join("plain"), d.path().join("probed"));
    let o = train_tiny(&s, &plain, &["--iters", "7"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = train_tiny(&s, &probed, &["--iters", "7", "--eval-every", "3", "--eval-views", "all"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let metrics = |run: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap() };
    let (a, b) = (metrics(&plain), metrics(&probed));
    assert_eq!(a["test_psnr"], b["test_psnr"], "scoring during the run changed it");
    assert_eq!(b["config"]["eval_every"], serde_json::json!({"steps": 3, "views": "all"}));
    assert!(a["config"].get("eval_every").is_none(), "absent from configs that do not set it");
    let history = std::fs::read_to_string(probed.join("history.jsonl")).unwrap();
    let scored: Vec<serde_json::Value> = history.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()).filter(|v| v.get("test_psnr").is_some()).collect();
    let steps: Vec<u64> = scored.iter().map(|v| v["step"].as_u64().unwrap()).collect();
    assert_eq!(steps, [3, 6]);
    assert!(scored.iter().all(|v| v["test_psnr"].as_f64().unwrap().is_finite() && v["test_views"] == 1), "{scored:?}");
    assert!(!std::fs::read_to_string(plain.join("history.jsonl")).unwrap().contains("test_psnr"));
    assert!(!probed.join("progress").exists(), "no renders unless asked for");
    // `--eval-renders`: each evaluation's renders, by step, the size of the test views; the
    // run still ends where it did.
    let drawn = d.path().join("drawn");
    let o = train_tiny(&s, &drawn, &["--iters", "7", "--eval-every", "3", "--eval-views", "all", "--eval-renders"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(metrics(&drawn)["test_psnr"], a["test_psnr"]);
    assert_eq!(metrics(&drawn)["config"]["eval_every"]["renders"], true);
    let mut steps: Vec<String> = std::fs::read_dir(drawn.join("progress")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    steps.sort();
    assert_eq!(steps, ["step_000003", "step_000006"]);
    for step in &steps {
        let pngs: Vec<_> = std::fs::read_dir(drawn.join("progress").join(step)).unwrap().map(|e| e.unwrap().path()).collect();
        assert_eq!(pngs.len(), 1, "{step}: one test view");
        assert_eq!(image::image_dimensions(&pngs[0]).unwrap(), (50, 50), "{step}");
    }
    let o = train_tiny(&s, &d.path().join("bad3"), &["--iters", "2", "--eval-renders"]);
    assert_clean_failure(&o, &["--eval-renders", "--eval-every"]);
    // Bad settings are clear errors.
    let o = train_tiny(&s, &d.path().join("bad"), &["--iters", "2", "--eval-every", "0"]);
    assert_clean_failure(&o, &["eval_every.steps"]);
    let o = train_tiny(&s, &d.path().join("bad2"), &["--iters", "2", "--eval-views", "all"]);
    assert!(o.status.code() == Some(2) && stderr(&o).contains("--eval-every"), "{}", stderr(&o));
}

/// `nerf train --aabb-scale N`: the scene trains in instant-ngp's box of that size without its
/// file being edited; the run's config keeps it, so `nerf eval` loads the same box and scores
/// what training scored, and the box differs from the file's own.
#[test]
fn aabb_scale_grows_the_box_and_eval_follows_the_run() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let run = d.path().join("run");
    let o = train_tiny(&s, &run, &["--iters", "3", "--device", "cpu", "--aabb-scale", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("aabb_scale 2"), "{}", stderr(&o));
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(m["config"]["aabb_scale"], 2.0);
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--device", "cpu", "--quiet"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let e: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("eval/eval.json")).unwrap()).unwrap();
    assert_eq!(e["test_psnr"], m["test_psnr"], "eval loads the run's box");
    // The box matters: the same run in the file's box scores otherwise.
    let plain = d.path().join("plain");
    let o = train_tiny(&s, &plain, &["--iters", "3", "--device", "cpu"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let p: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(plain.join("metrics.json")).unwrap()).unwrap();
    assert_ne!(p["test_psnr"], m["test_psnr"]);
    assert!(p["config"].get("aabb_scale").is_none());
    let o = train_tiny(&s, &d.path().join("bad"), &["--iters", "1", "--aabb-scale=-1"]);
    assert_clean_failure(&o, &["aabb_scale", "above 0"]);
}

/// `nerf eval --step-size`: a run of the occupancy sampler rendered with a finer marching step
/// records the step, scores differently from its own step, and a step that is not positive is a
/// clear error. A run whose config sets `render_step_size` trains as the plain run does and
/// scores, in its own evaluation and in `nerf eval`, what `--step-size` gives the plain run.
#[test]
fn eval_renders_an_occupancy_run_with_another_marching_step() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let base_cfg = "field = \"hash\"\nbatch_rays = 256\ntarget_samples_per_step = 4096\n[field_config.grid]\nlog2_hashmap_size = 12\n\
        [sampler]\nkind = \"occupancy\"\nstep_size = 0.02\nmax_samples_per_ray = 256\n";
    let train = |name: &str, cfg_text: &str| -> PathBuf {
        let (run, cfg) = (d.path().join(name), d.path().join(format!("{name}.toml")));
        std::fs::write(&cfg, cfg_text).unwrap();
        let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(&run)
            .args(["--quiet", "--no-renders", "--iters", "30", "--device", "cpu"]).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        run
    };
    let run = train("run", base_cfg);
    let json = |p: PathBuf| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap() };
    let base = json(run.join("metrics.json"))["test_psnr"].as_f64().unwrap();
    let fine = d.path().join("fine");
    let o = nerf().arg("eval").arg(&run).arg(&s).arg("--out").arg(&fine).args(["--device", "cpu", "--quiet", "--step-size", "0.005"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let e = json(fine.join("eval.json"));
    assert!((e["render_step_size"].as_f64().unwrap() - 0.005).abs() < 1e-9, "{}", e["render_step_size"]);
    assert!((e["sampler"]["step_size"].as_f64().unwrap() - 0.02).abs() < 1e-9, "the training sampler is recorded as trained: {}", e["sampler"]);
    let psnr = e["test_psnr"].as_f64().unwrap();
    assert!(psnr.is_finite() && (psnr - base).abs() > 1e-6, "the finer step renders other samples: {psnr} vs {base}");
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--device", "cpu", "--quiet", "--step-size", "0"]).output().unwrap();
    assert_clean_failure(&o, &["--step-size", "positive"]);

    // The config key: the same training, evaluated at the finer step.
    let keyed = train("keyed", &format!("render_step_size = 0.005\n{base_cfg}"));
    let m = json(keyed.join("metrics.json"));
    assert_eq!(m["final_train_loss"], json(run.join("metrics.json"))["final_train_loss"], "training ignores the render step");
    assert_eq!(m["test_psnr"].as_f64().unwrap(), psnr, "the run's evaluation at render_step_size is `nerf eval --step-size`'s");
    let o = nerf().arg("eval").arg(&keyed).arg(&s).arg("--out").arg(d.path().join("keyed_eval")).args(["--device", "cpu", "--quiet"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(json(d.path().join("keyed_eval/eval.json"))["test_psnr"].as_f64().unwrap(), psnr, "nerf eval keeps the run's render step");
    // nerf render: the run's render step, or --step-size's; a frame at another step differs.
    let frame = |run: &Path, name: &str, extra: &[&str]| {
        let out = d.path().join(name);
        let o = nerf().arg("render").arg(run).arg(&s).args(["--frames", "1", "--width", "24", "--device", "cpu", "--quiet", "--out"]).arg(&out).args(extra).output().unwrap();
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        (json(out.join("render.json"))["render_step_size"].as_f64(), image::open(out.join("frame_0000.png")).unwrap().to_rgb8().into_raw())
    };
    let (keyed_step, keyed_px) = frame(&keyed, "r_keyed", &[]);
    assert_eq!(keyed_step, Some(0.005f32 as f64));
    let (flag_step, flag_px) = frame(&run, "r_flag", &["--step-size", "0.005"]);
    assert_eq!((flag_step, &flag_px), (Some(0.005f32 as f64), &keyed_px), "--step-size renders what the key does");
    let (plain_step, plain_px) = frame(&run, "r_plain", &[]);
    assert!(plain_step.is_none() && plain_px != keyed_px, "the training step renders another frame");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--device", "cpu", "--step-size", "0"]).output().unwrap();
    assert_clean_failure(&o, &["--step-size", "positive"]);
    let bad = d.path().join("bad.toml");
    std::fs::write(&bad, "render_step_size = 0.005\nfield = \"freq\"\niters = 1\n[sampler]\nkind = \"stratified\"\nn_samples = 8\n").unwrap();
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&bad).arg("--out").arg(d.path().join("bad")).args(["--quiet", "--device", "cpu"]).output().unwrap();
    assert_clean_failure(&o, &["render_step_size", "occupancy"]);
}

/// `nerf slim`: the render-only copy of a hash run with a moving average is a fraction of the
/// checkpoint and scores exactly what the run scores (in `nerf eval`, on the CPU and, where an
/// adapter exists, on the GPU); a render-only copy cannot be resumed, an existing copy is not
/// overwritten, and a missing run is named.
#[test]
fn slim_writes_a_render_only_copy_that_scores_what_the_run_scores() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let (run, cfg) = (d.path().join("run"), d.path().join("run.toml"));
    // 16-wide nets, 0.05 steps and 4 096 samples a step: the GPU evaluations below (lavapipe in
    // CI) took 12 s each with the preset's 64-wide nets at 0.02 steps, 3 s with these.
    std::fs::write(&cfg, "field = \"hash\"\nbatch_rays = 256\ntarget_samples_per_step = 4096\nema_decay = 0.9\n\
        [field_config]\ndensity_hidden = 16\ncolor_hidden = 16\n[field_config.grid]\nlog2_hashmap_size = 12\n\
        [sampler]\nkind = \"occupancy\"\nstep_size = 0.05\nmax_samples_per_ray = 64\n").unwrap();
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(&run)
        .args(["--quiet", "--no-renders", "--iters", "20", "--device", "cpu"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let slim = d.path().join("slim");
    let o = nerf().arg("slim").arg(&run).arg("--out").arg(&slim).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let size = |p: &Path| std::fs::metadata(p.join("checkpoint.bin")).unwrap().len() as i64;
    let json = |p: PathBuf| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap() };
    // Parameters, Adam's two moments and the average before, the parameters alone after (the
    // occupancy grid in both): 3 × 4 bytes per parameter fewer, up to the headers' few bytes.
    let n_params = json(run.join("metrics.json"))["n_params"].as_i64().unwrap();
    let saved = size(&run) - size(&slim);
    assert!((saved - 12 * n_params).abs() < 4096, "{saved} bytes saved, {n_params} parameters");
    let eval = |r: &Path, device: &str| -> Option<f64> {
        let out = d.path().join(format!("eval_{}_{device}", r.file_name().unwrap().to_string_lossy()));
        let o = nerf().arg("eval").arg(r).arg(&s).arg("--out").arg(&out).args(["--device", device, "--quiet"]).output().unwrap();
        if device == "gpu" && stderr(&o).contains("no GPU adapter") {
            eprintln!("NOTICE: no GPU adapter; the render-only copy was scored on the CPU only");
            return None;
        }
        assert!(o.status.success(), "{}", stderr(&o));
        json(out.join("eval.json"))["test_psnr"].as_f64()
    };
    let full = eval(&run, "cpu").unwrap();
    assert_eq!(eval(&slim, "cpu"), Some(full), "the copy scores what the run scores");
    assert!((full - json(run.join("metrics.json"))["test_psnr"].as_f64().unwrap()).abs() < 1e-9);
    if let Some(g) = eval(&run, "gpu") {
        assert_eq!(eval(&slim, "gpu"), Some(g), "on the GPU too");
    }
    // It cannot be trained on.
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(&slim)
        .args(["--quiet", "--no-renders", "--iters", "30", "--device", "cpu", "--resume"]).output().unwrap();
    assert_clean_failure(&o, &["checkpoint.bin", "render-only"]);
    let o = nerf().arg("slim").arg(&run).arg("--out").arg(&slim).output().unwrap();
    assert_clean_failure(&o, &["already exists"]);
    let o = nerf().arg("slim").arg(d.path().join("nope")).arg("--out").arg(d.path().join("x")).output().unwrap();
    assert_clean_failure(&o, &["nope"]);
}

/// Starts a long tiny run into `run`, interrupts it (SIGINT) once it has logged a few steps, and
/// checks that it stopped cleanly and said how to resume; the checkpoint's step.
#[cfg(unix)]
fn interrupted_run(scene: &Path, run: &Path) -> u64 {
    let cfg = run.with_extension("toml");
    write_tiny_config(&cfg);
    let hist = run.join("history.jsonl");
    // An earlier run's log would end the wait below at once.
    let _ = std::fs::remove_file(&hist);
    let child = nerf()
        .arg("train")
        .arg(scene)
        .arg("--config")
        .arg(&cfg)
        .arg("--out")
        .arg(run)
        .args(["--quiet", "--no-renders", "--iters", "100000000"])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    while std::fs::read_to_string(&hist).map(|h| h.lines().count()).unwrap_or(0) < 3 {
        assert!(t0.elapsed().as_secs() < 120, "training did not start");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let ok = Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(ok.success());
    let o = child.wait_with_output().unwrap();
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(130), "{e}");
    assert!(e.contains("checkpoint") && e.contains("--resume"), "{e}");
    assert!(!e.contains("panicked"), "{e}");
    let ck = nerf_train_step(run);
    assert!(ck >= 3, "checkpoint holds step {ck}");
    ck
}

fn iterations(run: &Path) -> Option<u64> {
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).ok()?).unwrap();
    m["iterations"].as_u64()
}

#[cfg(unix)]
#[test]
fn ctrl_c_saves_a_checkpoint_and_resume_continues() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let run = d.path().join("run");
    let ck = interrupted_run(&s, &run);
    // The same command again, without --resume: refused, the interrupted run left as it was.
    let before = std::fs::read(run.join("checkpoint.bin")).unwrap();
    let o = train_tiny(&s, &run, &["--iters", "2"]);
    assert_clean_failure(&o, &["interrupted run", &format!("step {ck}"), "--resume", "--overwrite"]);
    assert_eq!(std::fs::read(run.join("checkpoint.bin")).unwrap(), before, "the checkpoint was touched");
    // Resume to a fixed total and finish normally.
    let target = ck + 4;
    let o = train_tiny(&s, &run, &["--resume", "--iters", &target.to_string()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(m["iterations"].as_u64(), Some(target));
    assert_eq!(m["steps_this_invocation"].as_u64(), Some(4));
    // A finished run is replaced by a new one.
    let o = train_tiny(&s, &run, &["--iters", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(iterations(&run), Some(2));
}

/// A new run that replaces a finished one and is interrupted leaves no stale metrics.json that
/// would make it look finished; `--overwrite` starts over in a folder with an interrupted run.
#[cfg(unix)]
#[test]
fn an_interrupted_run_is_never_taken_for_a_finished_one_and_overwrite_starts_over() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let run = d.path().join("run");
    let o = train_tiny(&s, &run, &["--iters", "2"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(iterations(&run), Some(2));
    let ck = interrupted_run(&s, &run);
    assert_eq!(iterations(&run), None, "the finished run's metrics.json survived a new run");
    let o = train_tiny(&s, &run, &["--iters", "2"]);
    assert_clean_failure(&o, &["interrupted run", &format!("step {ck}")]);
    let o = train_tiny(&s, &run, &["--iters", "2", "--overwrite", "--resume"]);
    assert!(!o.status.success() && stderr(&o).contains("--overwrite"), "{}", stderr(&o));
    let o = train_tiny(&s, &run, &["--iters", "2", "--overwrite"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(iterations(&run), Some(2));
    assert_eq!(nerf_train_step(&run), 2);
}

/// The step stored in a run's checkpoint.
fn nerf_train_step(run: &Path) -> u64 {
    nerf::train::Checkpoint::load(&run.join("checkpoint.bin")).unwrap().step
}

#[test]
fn device_flag_trains_on_the_gpu_and_the_cpu_evaluates_the_checkpoint() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let o = train_tiny(&s, &d.path().join("typo"), &["--iters", "1", "--device", "gpux"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("gpux") && !stderr(&o).contains("panicked"), "{}", stderr(&o));

    let run = d.path().join("gpu");
    let o = train_tiny(&s, &run, &["--iters", "4", "--device", "gpu"]);
    if !o.status.success() {
        // No adapter at all: a one-line error that says how to get one.
        assert_clean_failure(&o, &["no GPU adapter", "--device cpu"]);
        eprintln!("NOTICE: no GPU adapter; checked the error only");
        return;
    }
    // The third field trains there too, through its own twin (a small grid: lavapipe is slow).
    // (A field without a twin is refused by `gpu`: tests/gpu_train.rs.)
    let cfg = d.path().join("voxel.toml");
    std::fs::write(&cfg, "field_config = { resolution = 16, hidden = 16 }\ntarget_samples_per_step = 4096\n").unwrap();
    let o = nerf()
        .arg("train")
        .arg(&s)
        .args(["--field", "voxel", "--iters", "2", "--device", "gpu", "--quiet", "--no-renders", "--config"])
        .arg(&cfg)
        .arg("--out")
        .arg(d.path().join("voxel"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.path().join("voxel/metrics.json")).unwrap()).unwrap();
    assert_eq!((m["device"].as_str(), m["config"]["field"].as_str()), (Some("gpu"), Some("voxel")), "{m}");
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(m["device"], "gpu", "{m}");
    assert!(m["adapter"].as_str().is_some_and(|a| !a.is_empty()), "{m}");
    assert_eq!(m["iterations"], 4);
    // The GPU's checkpoint evaluated on the CPU gives the same PSNR (same parameters, same
    // deterministic sampling; f32 summation order only).
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--device", "cpu"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let e: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval/eval.json")).unwrap()).unwrap();
    assert_eq!(e["device"], "cpu");
    let (a, b) = (m["test_psnr"].as_f64().unwrap(), e["test_psnr"].as_f64().unwrap());
    assert!((a - b).abs() < 0.01, "GPU run {a} dB vs CPU eval {b} dB");
}

#[test]
fn without_an_adapter_gpu_is_a_clear_error_and_auto_runs_on_the_cpu() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    // Hide every Vulkan driver from the loader: no adapter exists.
    let hide = |c: &mut Command| {
        c.env("VK_ICD_FILENAMES", "/nonexistent.json").env("VK_DRIVER_FILES", "/nonexistent.json");
    };
    let cfg = d.path().join("tiny.toml");
    write_tiny_config(&cfg);
    let train = |out: &Path, device: &str| {
        let mut c = nerf();
        c.arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(out);
        c.args(["--quiet", "--no-renders", "--iters", "2", "--device", device]);
        hide(&mut c);
        c.output().unwrap()
    };
    let o = train(&d.path().join("gpu"), "gpu");
    assert_clean_failure(&o, &["no GPU adapter", "mesa-vulkan-drivers", "--device cpu"]);
    let run = d.path().join("auto");
    let o = train(&run, "auto");
    assert!(o.status.success(), "{}", stderr(&o));
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(m["device"], "cpu");
    assert!(m["adapter"].is_null());
}

#[test]
fn render_writes_an_orbit_of_novel_views() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let out = d.path().join("frames");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "3", "--width", "20", "--device", "cpu", "--gif", "10", "--out"]).arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    // The same frames as one looping GIF at 10 frames/s.
    {
        use image::AnimationDecoder as _;
        let f = std::fs::File::open(out.join("render.gif")).unwrap();
        let frames = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(f)).unwrap().into_frames().collect_frames().unwrap();
        assert_eq!(frames.len(), 3);
        assert!(frames.iter().all(|f| f.delay().numer_denom_ms() == (100, 1) && f.buffer().dimensions() == (20, 20)));
        let png = image::open(out.join("frame_0001.png")).unwrap().to_rgb8();
        let diff = png.pixels().zip(frames[1].buffer().pixels()).map(|(a, b)| (0..3).map(|c| (a[c] as i32 - b[c] as i32).abs()).sum::<i32>()).sum::<i32>();
        assert!((diff as f64) / (3.0 * 400.0) < 12.0, "the GIF frame is the PNG in 256 colours: mean error {diff}");
    }
    assert!(String::from_utf8_lossy(&o.stdout).contains("ffmpeg -framerate 10"), "{}", String::from_utf8_lossy(&o.stdout));
    for i in 0..3 {
        let img = image::open(out.join(format!("frame_{i:04}.png"))).unwrap();
        assert_eq!((img.width(), img.height()), (20, 20), "frame {i}: the training images are square");
    }
    assert!(!out.join("frame_0003.png").exists());
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("render.json")).unwrap()).unwrap();
    assert_eq!(r["frames"], 3);
    assert_eq!(r["device"], "cpu");
    assert!(r["frames_per_second"].as_f64().unwrap() > 0.0);
    // Three camera positions on one circle about the box centre (the origin), 120° apart.
    let pos: Vec<[f64; 3]> = r["camera_to_world"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| std::array::from_fn(|k| m[k][3].as_f64().unwrap()))
        .collect();
    let norm = |p: &[f64; 3]| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
    assert!(pos.iter().all(|p| (norm(p) - norm(&pos[0])).abs() < 1e-4 && norm(p) > 1.0), "{pos:?}");
    let dist = |a: &[f64; 3], b: &[f64; 3]| norm(&[a[0] - b[0], a[1] - b[1], a[2] - b[2]]);
    assert!((dist(&pos[0], &pos[1]) - dist(&pos[1], &pos[2])).abs() < 1e-4 && dist(&pos[0], &pos[1]) > 0.5, "{pos:?}");
    // The orbit's camera_path.json renders the same frames again; --width rescales it.
    let again = d.path().join("again");
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(out.join("camera_path.json"))
        .args(["--device", "cpu", "--out"]).arg(&again).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("ffmpeg -framerate 10"), "the path's fps: {}", String::from_utf8_lossy(&o.stdout));
    for i in 0..3 {
        let (a, b) = (image::open(out.join(format!("frame_{i:04}.png"))).unwrap(), image::open(again.join(format!("frame_{i:04}.png"))).unwrap());
        assert_eq!(a.to_rgb8().as_raw(), b.to_rgb8().as_raw(), "frame {i}");
    }
    assert!(!again.join("frame_0003.png").exists());
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(out.join("camera_path.json"))
        .args(["--device", "cpu", "--width", "10", "--out"]).arg(d.path().join("small")).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(image::open(d.path().join("small/frame_0002.png")).unwrap().width(), 10);
    // Bad arguments: a clear one-line error.
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(out.join("camera_path.json")).args(["--frames", "2"]).output().unwrap();
    assert_clean_failure(&o, &["--frames", "camera_path.json", "one camera per frame"]);
    std::fs::write(d.path().join("bad_path.json"), r#"{"render_width": 8, "camera_path": []}"#).unwrap();
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(d.path().join("bad_path.json")).output().unwrap();
    assert_clean_failure(&o, &["bad_path.json", "render_height"]);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "0"]).output().unwrap();
    assert_clean_failure(&o, &["--frames"]);
    // A frame too large to hold is refused before anything is allocated (100 000² pixels also
    // overflow a u32 count).
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--width", "100000", "--out"]).arg(d.path().join("huge")).output().unwrap();
    assert_clean_failure(&o, &["100000x100000", "--width"]);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--device", "cpu", "--gif", "0", "--out"]).arg(d.path().join("g")).output().unwrap();
    assert_clean_failure(&o, &["render.gif", "frames/s"]);
    let o = nerf().arg("render").arg(d.path().join("nope")).arg(&s).output().unwrap();
    assert_clean_failure(&o, &["checkpoint.bin"]);
}

/// instant-ngp's `nerf_matrix_to_ngp` written out for a Blender scene (instant-ngp's default
/// `scale` 0.33 and `offset` 0.5): the camera's axes right, down, forward; position
/// `p·0.33 + 0.5`; then the rows cycled (`xyz ← yzx`). Returns the keyframe's `R` (x, y, z, w)
/// and `T`.
fn ngp_keyframe(c2w: &[[f64; 4]]) -> ([f64; 4], [f64; 3]) {
    use nerf::rays::glam::{DMat3, DQuat, DVec3};
    let m: Vec<[f64; 4]> = c2w[..3].iter().map(|r| [r[0], -r[1], -r[2], r[3] * f64::from(0.33f32) + 0.5]).collect();
    let m = [m[1], m[2], m[0]];
    let r = DMat3::from_cols(DVec3::new(m[0][0], m[1][0], m[2][0]), DVec3::new(m[0][1], m[1][1], m[2][1]), DVec3::new(m[0][2], m[1][2], m[2][2]));
    let q = DQuat::from_mat3(&r);
    ([q.x, q.y, q.z, q.w], [m[0][3], m[1][3], m[2][3]])
}

/// `nerf render --camera-path` reads instant-ngp's `base_cam.json`: a keyframe made from one of
/// an orbit's cameras (put into instant-ngp's space by its formulas) renders that orbit frame
/// again; a path of two keyframes 0.1 s long is 6 frames at 60 a second, moving evenly from the
/// first camera to the second (a linear spline). The `base_cam.json` written beside the orbit
/// renders the orbit again.
#[test]
fn render_follows_an_instant_ngp_camera_path() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let orbit = d.path().join("orbit");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "3", "--width", "20", "--device", "cpu", "--quiet", "--out"]).arg(&orbit).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let json = |p: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap() };
    let (r, cp) = (json(&orbit.join("render.json")), json(&orbit.join("camera_path.json")));
    let c2w = |i: usize| -> Vec<[f64; 4]> { (0..4).map(|row| std::array::from_fn(|c| r["camera_to_world"][i][row][c].as_f64().unwrap())).collect() };
    let fov = cp["camera_path"][1]["fov"].as_f64().unwrap();
    let (rot, t) = ngp_keyframe(&c2w(1));
    // The shape of an older instant-ngp's file (no timestamps; slice, scale, aperture_size).
    let one = serde_json::json!({"loop": false, "time": 0.0, "path": [{"R": rot, "T": t, "fov": fov, "slice": 0.0, "scale": 1.5, "aperture_size": 0.0}]});
    std::fs::write(d.path().join("base_cam.json"), one.to_string()).unwrap();
    let out = d.path().join("ngp");
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(d.path().join("base_cam.json"))
        .args(["--frames", "1", "--width", "20", "--device", "cpu", "--quiet", "--out"]).arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let (a, b) = (image::open(orbit.join("frame_0001.png")).unwrap().to_rgb8(), image::open(out.join("frame_0000.png")).unwrap().to_rgb8());
    assert_eq!(a.dimensions(), b.dimensions());
    let diffs: Vec<i32> = a.as_raw().iter().zip(b.as_raw()).map(|(x, y)| (*x as i32 - *y as i32).abs()).collect();
    let mean = diffs.iter().sum::<i32>() as f64 / diffs.len() as f64;
    assert!(mean < 0.5 && diffs.iter().all(|&d| d <= 3), "the orbit's frame again (to rounding): mean {mean}, max {:?}", diffs.iter().max());
    let got = json(&out.join("render.json"));
    for row in 0..3 {
        for c in 0..4 {
            let (x, y) = (got["camera_to_world"][0][row][c].as_f64().unwrap(), c2w(1)[row][c]);
            assert!((x - y).abs() < 1e-5, "camera_to_world[{row}][{c}]: {x} vs {y}");
        }
    }
    // The orbit keeps the scene's depth range (Blender's [2, 6]); a camera twice as far out
    // moves its far end out by as much, so the scene stays within its rays.
    assert_eq!((r["near"].as_f64(), r["far"].as_f64()), (Some(2.0), Some(6.0)), "{r}");
    let mut far = c2w(1);
    let dist = (0..3).map(|i| far[i][3] * far[i][3]).sum::<f64>().sqrt();
    (0..3).for_each(|i| far[i][3] *= 2.0);
    let (rf, tf) = ngp_keyframe(&far);
    std::fs::write(d.path().join("far.json"), serde_json::json!({"path": [{"R": rf, "T": tf, "fov": fov}]}).to_string()).unwrap();
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(d.path().join("far.json"))
        .args(["--frames", "1", "--width", "8", "--device", "cpu", "--quiet", "--out"]).arg(d.path().join("far")).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let got = json(&d.path().join("far/render.json"));
    assert_eq!(got["near"].as_f64(), Some(2.0));
    assert!((got["far"].as_f64().unwrap() - (6.0 + dist)).abs() < 1e-3, "{got}: the training cameras are {dist} away");
    // Two keyframes, a linear spline, timestamps 0.05 and 0.1 s: the path takes 0.1 s, 6 frames.
    let (r0, t0) = ngp_keyframe(&c2w(0));
    let (r2, t2) = ngp_keyframe(&c2w(2));
    let two = serde_json::json!({"loop": false, "spline_order": 1, "path": [
        {"R": r0, "T": t0, "fov": fov, "timestamp": 0.05}, {"R": r2, "T": t2, "fov": fov, "timestamp": 0.1}]});
    std::fs::write(d.path().join("two.json"), two.to_string()).unwrap();
    let out = d.path().join("two");
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(d.path().join("two.json"))
        .args(["--width", "8", "--device", "cpu", "--quiet", "--out"]).arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("ffmpeg -framerate 60"), "{}", String::from_utf8_lossy(&o.stdout));
    let got = json(&out.join("render.json"));
    assert_eq!(got["frames"], 6);
    assert!(out.join("frame_0005.png").is_file() && !out.join("frame_0006.png").exists());
    for i in 0..6 {
        let f = i as f64 / 6.0;
        for row in 0..3 {
            let want = (1.0 - f) * c2w(0)[row][3] + f * c2w(2)[row][3];
            let x = got["camera_to_world"][i][row][3].as_f64().unwrap();
            assert!((x - want).abs() < 1e-4, "frame {i}, position {row}: {x} vs {want}");
        }
    }
    // The orbit's own base_cam.json replays it: 3 frames at 60 a second, the same cameras.
    let again = d.path().join("again");
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(orbit.join("base_cam.json"))
        .args(["--width", "20", "--device", "cpu", "--quiet", "--out"]).arg(&again).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let got = json(&again.join("render.json"));
    assert_eq!(got["frames"], 3);
    for i in 0..3 {
        for row in 0..3 {
            for c in 0..4 {
                let (x, y) = (got["camera_to_world"][i][row][c].as_f64().unwrap(), c2w(i)[row][c]);
                assert!((x - y).abs() < 1e-5, "frame {i}, camera_to_world[{row}][{c}]: {x} vs {y}");
            }
        }
    }
    // A panorama's path has no instant-ngp form.
    let pano = d.path().join("pano");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--camera-type", "equirectangular", "--frames", "1", "--width", "8", "--device", "cpu", "--quiet", "--out"]).arg(&pano).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(pano.join("camera_path.json").is_file() && !pano.join("base_cam.json").exists());
    // Bad files are refused by key.
    std::fs::write(d.path().join("bad.json"), r#"{"path": [{"R": [0, 0, 0, 1], "T": [0.5, 0.5]}]}"#).unwrap();
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(d.path().join("bad.json")).output().unwrap();
    assert_clean_failure(&o, &["bad.json", "path[0].T", "3 finite numbers"]);
}

/// `nerf render --spp N` averages N rays through each pixel: the frame moves a little from the
/// one-ray frame (which `--spp 1` keeps bit for bit), and render.json records the count.
#[test]
fn render_supersamples_with_spp() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let render = |name: &str, extra: &[&str]| -> image::RgbImage {
        let out = d.path().join(name);
        let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--width", "24", "--device", "cpu", "--quiet", "--out"]).arg(&out).args(extra).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("render.json")).unwrap()).unwrap();
        assert_eq!(r["spp"], extra.get(1).map_or(1, |n| n.parse::<u64>().unwrap()), "{r}");
        image::open(out.join("frame_0000.png")).unwrap().to_rgb8()
    };
    let (one, same, four) = (render("one", &[]), render("same", &["--spp", "1"]), render("four", &["--spp", "4"]));
    assert_eq!(one.as_raw(), same.as_raw());
    let diffs: Vec<i32> = one.as_raw().iter().zip(four.as_raw()).map(|(x, y)| (*x as i32 - *y as i32).abs()).collect();
    let mean = diffs.iter().sum::<i32>() as f64 / diffs.len() as f64;
    assert!(diffs.iter().any(|&d| d > 0) && mean < 3.0, "four rays a pixel: a little different, mean {mean}");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--spp", "0"]).output().unwrap();
    assert_clean_failure(&o, &["--spp 0", "rays per pixel"]);
}

/// `nerf render --aperture R [--focus D]` renders through a thin lens and `--shutter F` blurs
/// each frame over part of the way to the next: a zero aperture and a closed shutter leave the
/// frames bit for bit; by default every frame focuses on the orbit's centre; the lens goes into
/// render.json and, in instant-ngp's units, into base_cam.json, whose render has it again;
/// a resumed render must have the same lens and shutter; bad values are refused.
#[test]
fn render_blurs_with_a_lens_and_an_open_shutter() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let json = |p: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap() };
    let render = |name: &str, extra: &[&str]| -> (Vec<u8>, serde_json::Value) {
        let out = d.path().join(name);
        let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "3", "--width", "16", "--device", "cpu", "--quiet", "--out"]).arg(&out).args(extra).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        (image::open(out.join("frame_0001.png")).unwrap().to_rgb8().into_raw(), json(&out.join("render.json")))
    };
    let (sharp, r) = render("sharp", &["--spp", "2"]);
    assert_eq!((r["shutter"].as_f64(), r["lenses"].is_null()), (Some(0.0), true), "{r}");
    let (pinhole, _) = render("pinhole", &["--spp", "2", "--aperture", "0", "--shutter", "0"]);
    assert_eq!(sharp, pinhole, "no aperture and a closed shutter change nothing");
    let (lens, r) = render("lens", &["--spp", "2", "--aperture", "0.3"]);
    assert_ne!(sharp, lens, "a wide lens blurs");
    // Every frame is focused on one point: the orbit's centre, where its cameras look.
    let lenses = r["lenses"].as_array().unwrap();
    assert_eq!(lenses.len(), 3);
    let focus_point = |i: usize| -> [f64; 3] {
        let m = &r["camera_to_world"][i];
        let f = lenses[i][1].as_f64().unwrap();
        assert_eq!(lenses[i][0].as_f64(), Some(0.30000001192092896));
        std::array::from_fn(|a| m[a][3].as_f64().unwrap() - f * m[a][2].as_f64().unwrap())
    };
    let p0 = focus_point(0);
    for i in 1..3 {
        let p = focus_point(i);
        assert!((0..3).all(|a| (p[a] - p0[a]).abs() < 1e-4), "frame {i} focuses at {p:?}, frame 0 at {p0:?}");
    }
    // base_cam.json holds the lens in instant-ngp's units (lego's scale 0.33), and renders it again.
    let b = json(&d.path().join("lens/base_cam.json"));
    let kf = &b["path"][1];
    assert!((kf["aperture_size"].as_f64().unwrap() - 0.3 * 0.33).abs() < 1e-5, "{kf}");
    assert!((kf["scale"].as_f64().unwrap() + kf["slice"].as_f64().unwrap() - 0.33 * lenses[1][1].as_f64().unwrap()).abs() < 1e-4, "{kf}");
    let again = d.path().join("again");
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(d.path().join("lens/base_cam.json"))
        .args(["--width", "16", "--spp", "2", "--device", "cpu", "--quiet", "--out"]).arg(&again).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let back = json(&again.join("render.json"));
    for i in 0..3 {
        for k in 0..2 {
            let (x, y) = (back["lenses"][i][k].as_f64().unwrap(), lenses[i][k].as_f64().unwrap());
            assert!((x - y).abs() < 1e-4, "frame {i}: {back}");
        }
    }
    // An explicit focus is every frame's.
    let (_, r) = render("focus", &["--aperture", "0.1", "--focus", "2.5"]);
    assert!(r["lenses"].as_array().unwrap().iter().all(|l| l[1].as_f64() == Some(2.5)), "{r}");
    // Motion blur: the frame moves towards the next one's camera.
    let (moving, r) = render("moving", &["--spp", "2", "--shutter", "0.5"]);
    assert_ne!(sharp, moving, "an open shutter blurs");
    assert_eq!(r["shutter"].as_f64(), Some(0.5));
    // A render is resumed with the lens and shutter it was started with.
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "3", "--width", "16", "--spp", "2", "--device", "cpu", "--resume", "--out"]).arg(d.path().join("moving")).output().unwrap();
    assert_clean_failure(&o, &["render.json", "shutter", "--resume"]);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "3", "--width", "16", "--spp", "2", "--aperture", "0.2", "--device", "cpu", "--resume", "--out"]).arg(d.path().join("lens")).output().unwrap();
    assert_clean_failure(&o, &["render.json", "lenses", "--resume"]);
    // Bad values.
    for (args, words) in [
        (&["--shutter", "1.5"][..], &["--shutter 1.5", "[0, 1]"][..]),
        (&["--aperture=-1"], &["--aperture", "at least 0"]),
        (&["--aperture", "0.1", "--focus", "0"], &["--focus", "above 0"]),
    ] {
        let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1"]).args(args).output().unwrap();
        assert_clean_failure(&o, words);
    }
}

/// `nerf render --aperture R --focus auto` focuses each frame on what its middle shows: on a
/// hash field trained briefly on the in-repo lego, every orbit frame's focus lies between the
/// near bound and the object's centre (the lego's near surface); an untrained field, which shows
/// nothing there, is a clear error.
#[test]
fn render_autofocuses_on_the_middle_of_each_frame() {
    let d = tempfile::tempdir().unwrap();
    let (s, tiny) = tiny_cpu_run(d.path());
    let render = |run: &Path, out: &str| {
        nerf().arg("render").arg(run).arg(&s).args(["--frames", "3", "--width", "16", "--aperture", "0.1", "--focus", "auto", "--device", "cpu", "--quiet", "--out"]).arg(d.path().join(out)).output().unwrap()
    };
    let o = render(&tiny, "none");
    assert_clean_failure(&o, &["--focus auto", "nothing in the middle of frame 0"]);
    let cfg = d.path().join("hash.toml");
    std::fs::write(&cfg, "target_samples_per_step = 8192\n").unwrap();
    let run = d.path().join("hash");
    let o = nerf().arg("train").arg(&s).args(["--field", "hash", "--iters", "60", "--device", "cpu", "--quiet", "--no-renders", "--config"]).arg(&cfg).arg("--out").arg(&run).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let o = render(&run, "auto");
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.path().join("auto/render.json")).unwrap()).unwrap();
    for i in 0..3 {
        let m = &r["camera_to_world"][i];
        let dist = (0..3).map(|a| m[a][3].as_f64().unwrap().powi(2)).sum::<f64>().sqrt();
        let f = r["lenses"][i][1].as_f64().unwrap();
        assert!(f > r["near"].as_f64().unwrap() && f < dist, "frame {i}: focus {f}, the object's centre {dist} away: {r}");
    }
}

/// `nerf render --depth --depth-colormap turbo` draws the depth maps in colour (nerfstudio's
/// Turbo), where the default is grey; the colormap needs `--depth`.
#[test]
fn render_draws_depth_in_turbo_colours() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let depth = |name: &str, extra: &[&str]| -> image::RgbImage {
        let out = d.path().join(name);
        let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--width", "16", "--depth", "--device", "cpu", "--quiet", "--out"]).arg(&out).args(extra).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        image::open(out.join("depth_0000.png")).unwrap().to_rgb8()
    };
    let gray = depth("gray", &[]);
    assert!(gray.pixels().all(|p| p[0] == p[1] && p[1] == p[2]));
    let turbo = depth("turbo", &["--depth-colormap", "turbo"]);
    assert!(turbo.pixels().any(|p| p[0] != p[1] || p[1] != p[2]), "coloured");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--depth-colormap", "turbo"]).output().unwrap();
    assert!(o.status.code() == Some(2) && stderr(&o).contains("--depth"), "{}", stderr(&o));
}

/// `nerf render --depth --depth-range NEAR,FAR` draws the depth maps over that range
/// (nerfstudio's depth near and far planes): a farther far plane draws every pixel at least as
/// bright, the surfaces brighter; render.json records it, and `--resume` refuses another.
#[test]
fn render_draws_depth_over_a_given_range() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let render = |name: &str, extra: &[&str]| -> Output {
        nerf().arg("render").arg(&run).arg(&s).args(["--frames", "2", "--width", "24", "--depth", "--device", "cpu", "--quiet", "--out"]).arg(d.path().join(name)).args(extra).output().unwrap()
    };
    let maps = |name: &str| -> Vec<u8> { (0..2).flat_map(|i| image::open(d.path().join(format!("{name}/depth_{i:04}.png"))).unwrap().to_luma8().into_raw()).collect() };
    let json = |name: &str| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(d.path().join(format!("{name}/render.json"))).unwrap()).unwrap() };
    // Lego's cameras are 4 from its centre: its surfaces lie between 2 and 6.
    for (name, range) in [("near", "2,4"), ("wide", "2,8")] {
        let o = render(name, &["--depth-range", range]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    assert_eq!(json("near")["depth_range"], serde_json::json!([2.0, 4.0]));
    let (near, wide) = (maps("near"), maps("wide"));
    assert!(near.iter().zip(&wide).all(|(a, w)| w >= a), "a farther far plane: no pixel darker");
    assert!(near.iter().zip(&wide).filter(|(a, w)| w > a).count() > near.len() / 20, "and surfaces brighter");
    let o = render("near", &["--depth-range", "2,8", "--resume"]);
    assert_clean_failure(&o, &["render.json", "--depth-range", "--resume"]);
    let o = render("bad", &["--depth-range", "3,1"]);
    assert!(o.status.code() == Some(2) && stderr(&o).contains("NEAR < FAR"), "{}", stderr(&o));
}

/// `nerf render --normals` writes a normal map beside each frame, the size of the frame, each
/// pixel a blend of a unit normal's colour and the white background by the frame's opacity.
#[test]
fn render_writes_normal_maps() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let out = d.path().join("normals");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "2", "--width", "16", "--spp", "2", "--normals", "--device", "cpu", "--quiet", "--out"]).arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    for i in 0..2 {
        let n = image::open(out.join(format!("normal_{i:04}.png"))).unwrap().to_rgb8();
        assert_eq!(n.dimensions(), (16, 16));
        // Over white, a pixel of opacity a shows c = 1 − a·(1 − n)/2 per channel, so for a unit
        // normal n, Σ(1 − c)² = a²·(4 − 2·Σn)/4 ≤ a²·(1 + √3/2): no colour farther from white
        // (a gradient left unnormalised would saturate its channels).
        for p in n.pixels() {
            let dist2: f32 = p.0.iter().map(|&c| (1.0 - c as f32 / 255.0).powi(2)).sum();
            assert!(dist2 <= 1.0 + 0.75f32.sqrt() + 1e-2, "{p:?}");
        }
    }
    assert!(!out.join("normal_0002.png").exists());
    let plain = d.path().join("plain");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--width", "16", "--device", "cpu", "--quiet", "--out"]).arg(&plain).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!plain.join("normal_0000.png").exists(), "only with --normals");
}

/// Every config shipped in configs/ is accepted by `nerf train` (one step on the in-repo scene,
/// CPU): a renamed key or a typo there is an error the user would meet first.
#[test]
fn every_shipped_config_trains() {
    let dir = std::fs::read_dir(repo().join("configs")).unwrap();
    let mut n = 0;
    for entry in dir {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "toml") {
            continue;
        }
        let d = tempfile::tempdir().unwrap();
        let o = nerf()
            .arg("train")
            .arg(repo().join("scenes/lego_100"))
            .arg("--config")
            .arg(&path)
            .args(["--iters", "1", "--test-views", "first:1", "--device", "cpu", "--quiet", "--no-renders", "--out"])
            .arg(d.path())
            .output()
            .unwrap();
        assert!(o.status.success(), "{}: {}", path.display(), stderr(&o));
        n += 1;
    }
    assert!(n >= 3, "only {n} configs found");
}

#[test]
fn a_large_instant_ngp_box_gets_cone_steps_and_a_note() {
    let d = tempfile::tempdir().unwrap();
    let scene = small_scene(d.path());
    // The exported scene with instant-ngp's box keys, aabb_scale 2.
    for split in ["train", "test"] {
        let p = scene.join(format!("transforms_{split}.json"));
        let mut t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        t["aabb_scale"] = serde_json::json!(2);
        std::fs::write(&p, t.to_string()).unwrap();
    }
    // The paper's sampler: the note says what instant-ngp would use.
    let o = train_tiny(&scene, &d.path().join("run"), &["--iters", "1"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let e = stderr(&o);
    assert!(e.contains("aabb_scale 2") && e.contains("kind = \"occupancy\""), "{e}");
    // The hash field's occupancy sampler with the cone and cascade left out: the scene picks
    // instant-ngp's (cone 1/256, 1 + log2(2) = 2 levels).
    let hash = |name: &str| {
        let cfg = d.path().join(format!("{name}.toml"));
        std::fs::write(
            &cfg,
            format!(
                "field = \"hash\"\ntarget_samples_per_step = 1024\nlog_every = 1\n[field_config.grid]\nlog2_hashmap_size = 10\n\
                 [sampler]\nkind = \"occupancy\"\nstep_size = 0.05\nmax_samples_per_ray = 64\n{}[sampler.grid]\nresolution = 16\n",
                if name == "constant" { "cone_angle = 0.0\n" } else { "" }
            ),
        )
        .unwrap();
        let o = nerf()
            .arg("train")
            .arg(&scene)
            .arg("--config")
            .arg(&cfg)
            .arg("--out")
            .arg(d.path().join(name))
            .args(["--quiet", "--no-renders", "--iters", "2", "--device", "cpu"])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        stderr(&o)
    };
    let e = hash("auto");
    assert!(e.contains("cone steps (cone_angle = 0.00390625)") && e.contains("cascade of 2"), "{e}");
    // Set in the config: constant steps kept.
    let e = hash("constant");
    assert!(e.contains("constant steps (cone_angle = 0)"), "{e}");
}

/// A nerfstudio capture (COLMAP's poses, `applied_transform`) trains in nerfstudio's frame, and
/// the run records that frame's transform as nerfstudio does (`dataparser_transforms.json`); its
/// dataparser options (`--orientation-method`, `--center-method`, `--no-auto-scale-poses`,
/// `--scale-factor`) change that frame and stay with the run; a Blender scene's run has none.
#[test]
fn a_nerfstudio_capture_run_writes_its_dataparser_transforms() {
    let d = tempfile::tempdir().unwrap();
    let lego = repo().join("scenes/lego_100");
    let tr: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(lego.join("transforms_train.json")).unwrap()).unwrap();
    // Ten training views as one nerfstudio file, every camera centre at 5·p + (1, 2, 3).
    let frames: Vec<serde_json::Value> = tr["frames"].as_array().unwrap()[..10]
        .iter()
        .map(|f| {
            let mut m = f["transform_matrix"].clone();
            for r in 0..3 {
                m[r][3] = serde_json::json!(5.0 * m[r][3].as_f64().unwrap() + (r + 1) as f64);
            }
            let rel = f["file_path"].as_str().unwrap().trim_start_matches("./");
            serde_json::json!({"file_path": lego.join(format!("{rel}.png")), "transform_matrix": m})
        })
        .collect();
    let scene = d.path().join("capture");
    std::fs::create_dir_all(&scene).unwrap();
    let f = 0.5 * 100.0 / (0.5 * tr["camera_angle_x"].as_f64().unwrap()).tan();
    let t = serde_json::json!({"camera_model": "OPENCV", "fl_x": f, "fl_y": f, "cx": 50, "cy": 50, "w": 100, "h": 100,
        "applied_transform": [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]], "frames": frames});
    std::fs::write(scene.join("transforms.json"), t.to_string()).unwrap();
    let run = d.path().join("run");
    let o = train_tiny(&scene, &run, &["--iters", "1", "--device", "cpu"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("a nerfstudio capture") && stderr(&o).contains("aabb_scale"), "{}", stderr(&o));
    let dt: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("dataparser_transforms.json")).unwrap()).unwrap();
    let s = dt["scale"].as_f64().unwrap();
    assert!(s > 0.0 && s < 1.0 / 5.0, "the capture's cameras are 5× lego's (4 units away): {s}");
    let m: Vec<Vec<f64>> = dt["transform"].as_array().unwrap().iter().map(|r| r.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()).collect();
    assert_eq!((m.len(), m[0].len()), (3, 4));
    // nerfstudio's dataparser options: no turn, the origin at the cameras' focus (lego's
    // cameras look at its origin, here at (1, 2, 3)), the poses' own scale times 0.2.
    let opts = d.path().join("opts");
    let o = train_tiny(
        &scene,
        &opts,
        &["--iters", "1", "--device", "cpu", "--orientation-method", "none", "--center-method", "focus", "--no-auto-scale-poses", "--scale-factor", "0.2"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let dt: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(opts.join("dataparser_transforms.json")).unwrap()).unwrap();
    assert!((dt["scale"].as_f64().unwrap() - 0.2).abs() < 1e-12, "{dt}");
    for r in 0..3 {
        for c in 0..3 {
            assert_eq!(dt["transform"][r][c].as_f64(), Some((r == c) as u8 as f64), "no turn: {dt}");
        }
        assert!((dt["transform"][r][3].as_f64().unwrap() + (r + 1) as f64).abs() < 0.05, "the focus at (1, 2, 3): {dt}");
    }
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(opts.join("metrics.json")).unwrap()).unwrap();
    let n = &m["config"]["nerfstudio"];
    assert_eq!((n["orientation_method"].as_str(), n["center_method"].as_str(), n["auto_scale_poses"].as_bool()), (Some("none"), Some("focus"), Some(false)), "{n}");
    // eval loads the run's frame, so it scores what training scored.
    let o = nerf().arg("eval").arg(&opts).arg(&scene).args(["--device", "cpu", "--quiet"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let e: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(opts.join("eval/eval.json")).unwrap()).unwrap();
    assert_eq!(e["test_psnr"], m["test_psnr"]);
    let o = train_tiny(&scene, &d.path().join("bad"), &["--iters", "1", "--scale-factor", "0"]);
    assert_clean_failure(&o, &["scale_factor", "above 0"]);
    // nerfstudio's `--eval-mode fraction`: 9 of the 10 frames train, one tests (every 8th: two).
    let held = |name: &str, extra: &[&str]| -> serde_json::Value {
        let run = d.path().join(name);
        let o = train_tiny(&scene, &run, &[&["--iters", "1", "--device", "cpu", "--test-views", "all"], extra].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap()
    };
    let (every8, frac) = (held("every8", &[]), held("frac", &["--holdout", "fraction:0.9"]));
    assert_eq!((every8["n_test_views"].as_u64(), every8["config"].get("holdout")), (Some(2), None), "{every8}");
    assert_eq!((frac["n_test_views"].as_u64(), frac["config"]["holdout"].as_str()), (Some(1), Some("fraction:0.9")), "{frac}");
    let o = train_tiny(&scene, &d.path().join("bad"), &["--iters", "1", "--holdout", "fraction:1.5"]);
    assert!(o.status.code() == Some(2) && stderr(&o).contains("invalid holdout"), "{}", stderr(&o));
    let blender = d.path().join("blender_run");
    let o = train_tiny(&small_scene(d.path()), &blender, &["--iters", "1", "--device", "cpu"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(blender.join("metrics.json").is_file() && !blender.join("dataparser_transforms.json").exists());
}

/// A COLMAP scene folder (`images/` + `sparse/0/*.txt`) trains as nerfstudio's `colmap`
/// dataparser would (normalised poses, `dataparser_transforms.json`), says what it is, and
/// `export-scene` writes it as transforms files that load again.
#[test]
fn a_colmap_scene_trains_and_exports() {
    let d = tempfile::tempdir().unwrap();
    let lego = repo().join("scenes/lego_100");
    let tr: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(lego.join("transforms_train.json")).unwrap()).unwrap();
    let scene = d.path().join("capture");
    std::fs::create_dir_all(scene.join("images")).unwrap();
    std::fs::create_dir_all(scene.join("sparse/0")).unwrap();
    // Ten training views, COLMAP's world = lego's: R = (c2w·diag(1, −1, −1))ᵀ, t = −R·c. For
    // these rotations (w ≥ 1e-3) the quaternion is (w, (R21 − R12)/4w, (R02 − R20)/4w, (R10 − R01)/4w).
    let mut lines = String::from("# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n");
    for (i, f) in tr["frames"].as_array().unwrap()[..10].iter().enumerate() {
        let m = |r: usize, c: usize| f["transform_matrix"][r][c].as_f64().unwrap();
        let r: [[f64; 3]; 3] = std::array::from_fn(|a| std::array::from_fn(|b| m(b, a) * if a == 0 { 1.0 } else { -1.0 }));
        let t: [f64; 3] = std::array::from_fn(|a| -(0..3).map(|b| r[a][b] * m(b, 3)).sum::<f64>());
        let w = 0.5 * (1.0 + r[0][0] + r[1][1] + r[2][2]).max(0.0).sqrt();
        assert!(w > 1e-3, "view {i}: pick another formula");
        let q = [w, (r[2][1] - r[1][2]) / (4.0 * w), (r[0][2] - r[2][0]) / (4.0 * w), (r[1][0] - r[0][1]) / (4.0 * w)];
        let name = format!("{i:02}.png");
        let rel = f["file_path"].as_str().unwrap().trim_start_matches("./");
        std::fs::copy(lego.join(format!("{rel}.png")), scene.join("images").join(&name)).unwrap();
        lines += &format!("{} {} {} {} {} {} {} {} 1 {name}\n\n", i + 1, q[0], q[1], q[2], q[3], t[0], t[1], t[2]);
    }
    std::fs::write(scene.join("sparse/0/images.txt"), lines).unwrap();
    let f = 0.5 * 100.0 / (0.5 * tr["camera_angle_x"].as_f64().unwrap()).tan();
    std::fs::write(scene.join("sparse/0/cameras.txt"), format!("1 PINHOLE 100 100 {f} {f} 50 50\n")).unwrap();
    let run = d.path().join("run");
    let o = train_tiny(&scene, &run, &["--iters", "1", "--device", "cpu"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let e = stderr(&o);
    assert!(e.contains("a COLMAP model") && e.contains("--aabb-scale 16") && e.contains("(8 train views, 1 test views"), "{e}");
    assert!(run.join("dataparser_transforms.json").is_file());
    let out = d.path().join("exported");
    let o = nerf().arg("export-scene").arg(&scene).arg(&out).args(["--downscale", "1", "--test-views", "all"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let o = train_tiny(&out, &d.path().join("run2"), &["--iters", "1", "--device", "cpu"]);
    assert!(o.status.success() && stderr(&o).contains("(8 train views, 1 test views"), "{}", stderr(&o));
    // A broken model: the error names the file and the line.
    std::fs::write(scene.join("sparse/0/cameras.txt"), "1 PINHOLE 100 100 nope 1 50 50\n").unwrap();
    let o = train_tiny(&scene, &d.path().join("run3"), &["--iters", "1", "--device", "cpu"]);
    assert_clean_failure(&o, &["cameras.txt", "COLMAP model", "line 1: `nope` is not a number"]);
}

/// Ctrl-C stops a render after the frame being rendered: exit code 130, the frames so far and
/// the json files kept, render.json counting them, no GIF (not even a partial one).
#[cfg(unix)]
#[test]
fn ctrl_c_stops_a_render_and_keeps_its_frames() {
    let d = tempfile::tempdir().unwrap();
    let s = small_scene(d.path());
    let run = d.path().join("run");
    let o = train_tiny(&s, &run, &["--iters", "1", "--device", "cpu"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = d.path().join("frames");
    let child = nerf()
        .arg("render")
        .arg(&run)
        .arg(&s)
        .args(["--frames", "100000", "--width", "8", "--device", "cpu", "--gif", "10", "--out"])
        .arg(&out)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = std::time::Instant::now();
    while !out.join("frame_0002.png").exists() {
        assert!(t0.elapsed().as_secs() < 120, "rendering did not start");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    assert!(Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap().success());
    let o = child.wait_with_output().unwrap();
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(130), "{e}");
    assert!(e.contains("interrupted after") && e.contains("--resume") && !e.contains("panicked"), "{e}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("render.json")).unwrap()).unwrap();
    let done = r["frames"].as_u64().unwrap() as usize;
    assert!((3..100000).contains(&done) && r["path_frames"] == 100000, "{r}");
    let pngs = std::fs::read_dir(&out).unwrap().filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().starts_with("frame_")).count();
    assert_eq!(pngs, done, "render.json counts the frames written");
    assert!(out.join("camera_path.json").is_file());
    let gifs: Vec<_> = std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().file_name()).filter(|n| n.to_string_lossy().contains("gif")).collect();
    assert!(gifs.is_empty(), "{gifs:?}");
}

/// `nerf render --resume` goes on from where an interrupted render stopped: the frames its
/// render.json counts stay as they are, the rest are rendered as the whole render would have
/// rendered them, the GIF holds them all; a different path or size is refused, as is a folder
/// with nothing to resume.
#[test]
fn resume_finishes_an_interrupted_render() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let args = ["--frames", "4", "--width", "12", "--device", "cpu", "--quiet", "--depth", "--gif", "10", "--out"];
    let whole = d.path().join("whole");
    let o = nerf().arg("render").arg(&run).arg(&s).args(args).arg(&whole).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    // What Ctrl-C after frame 1 leaves: two frames, render.json counting them, no GIF.
    let part = d.path().join("part");
    std::fs::create_dir_all(&part).unwrap();
    let mut r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(whole.join("render.json")).unwrap()).unwrap();
    r["frames"] = 2.into();
    r["camera_to_world"].as_array_mut().unwrap().truncate(2);
    std::fs::write(part.join("render.json"), r.to_string()).unwrap();
    for f in ["frame_0000.png", "frame_0001.png", "depth_0000.png", "depth_0001.png"] {
        std::fs::copy(whole.join(f), part.join(f)).unwrap();
    }
    // The kept frames stay as they are: marked here so that re-rendering them would show.
    let marked = image::RgbImage::from_pixel(12, 12, image::Rgb([1, 2, 3]));
    marked.save(part.join("frame_0000.png")).unwrap();
    let o = nerf().arg("render").arg(&run).arg(&s).args(args).arg(&part).arg("--resume").output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let png = |dir: &Path, f: &str| image::open(dir.join(f)).unwrap().to_rgb8().into_raw();
    assert_eq!(png(&part, "frame_0000.png"), marked.into_raw(), "kept, not rendered again");
    for f in ["frame_0001.png", "frame_0002.png", "frame_0003.png", "depth_0002.png", "depth_0003.png"] {
        assert_eq!(png(&part, f), png(&whole, f), "{f}");
    }
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(part.join("render.json")).unwrap()).unwrap();
    assert_eq!((r["frames"].as_u64(), r["camera_to_world"].as_array().map(Vec::len)), (Some(4), Some(4)));
    {
        use image::AnimationDecoder as _;
        let f = std::fs::File::open(part.join("render.gif")).unwrap();
        let frames = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(f)).unwrap().into_frames().collect_frames().unwrap();
        assert_eq!(frames.len(), 4, "the GIF holds the kept frames and the new ones");
    }
    // Another size, or nothing to resume: refused.
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "4", "--width", "10", "--device", "cpu", "--out"]).arg(&part).arg("--resume").output().unwrap();
    assert_clean_failure(&o, &["render.json", "width", "--resume"]);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "5", "--width", "12", "--device", "cpu", "--out"]).arg(&part).arg("--resume").output().unwrap();
    assert_clean_failure(&o, &["render.json", "path_frames"]);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "4", "--device", "cpu", "--resume", "--out"]).arg(d.path().join("empty")).output().unwrap();
    assert_clean_failure(&o, &["render.json", "nothing to resume"]);
}

/// `--path interpolate` goes through the run's test cameras in order (nerfstudio's
/// `interpolate`); `--path spiral` needs an LLFF scene.
#[test]
fn render_paths_through_the_test_cameras() {
    let d = tempfile::tempdir().unwrap();
    let s = d.path().join("scene");
    let o = nerf().args(["export-scene"]).arg(repo().join("scenes/lego_100")).arg(&s)
        .args(["--downscale", "4", "--train-views", "first:3", "--test-views", "first:3"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let run = d.path().join("run");
    let o = train_tiny(&s, &run, &["--iters", "1", "--device", "cpu", "--test-views", "all"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = d.path().join("frames");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--path", "interpolate", "--frames", "5", "--device", "cpu", "--out"]).arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("render.json")).unwrap()).unwrap();
    let t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(s.join("transforms_test.json")).unwrap()).unwrap();
    let pos = |m: &serde_json::Value| -> [f64; 3] { std::array::from_fn(|i| m[i][3].as_f64().unwrap()) };
    // Frames 0, 2 and 4 of 5 are test cameras 0, 1 and 2.
    for (frame, cam) in [(0, 0), (2, 1), (4, 2)] {
        let (a, b) = (pos(&r["camera_to_world"][frame]), pos(&t["frames"][cam]["transform_matrix"]));
        assert!((0..3).all(|i| (a[i] - b[i]).abs() < 1e-4), "frame {frame}: {a:?} vs test camera {cam}: {b:?}");
    }
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--path", "spiral", "--device", "cpu"]).output().unwrap();
    assert_clean_failure(&o, &["spiral", "LLFF"]);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--path", "orbit", "--camera-path", "x.json"]).output().unwrap();
    assert_eq!(o.status.code(), Some(2), "a usage error: {}", stderr(&o));
}

/// `nerf export-points`: a binary PLY of where random training rays stop, every point inside the
/// scene box; bad arguments are clear errors.
#[test]
fn export_points_writes_a_ply_inside_the_scene_box() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    // A barely trained field: every ray that stops anywhere in the box counts.
    let o = nerf().arg("export-points").arg(&run).arg(&s).args(["--points", "300", "--min-opacity", "0", "--device", "cpu"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(run.join("points.ply")).unwrap();
    let end = b"end_header\n";
    let h = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    assert!(std::str::from_utf8(&bytes[..h]).unwrap().contains("element vertex 300\n"));
    assert_eq!(bytes.len() - h, 300 * 15);
    for r in bytes[h..].chunks_exact(15) {
        let p: Vec<f32> = (0..3).map(|k| f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap())).collect();
        assert!(p.iter().all(|v| v.abs() <= 1.5), "outside the Blender cube: {p:?}");
    }
    for (args, needle) in [(["--points", "0"], "--points"), (["--min-opacity", "2"], "--min-opacity")] {
        let o = nerf().arg("export-points").arg(&run).arg(&s).args(args).output().unwrap();
        assert_clean_failure(&o, &[needle]);
    }
    // `--crop`: only the part of the scene in the box.
    let out = d.path().join("cropped.ply");
    let o = nerf().arg("export-points").arg(&run).arg(&s).args(["--points", "100", "--min-opacity", "0", "--device", "cpu", "--crop", "-0.5,-1.5,-0.2,1.5,0.3,1.5", "--out"]).arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(&out).unwrap();
    let h = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    assert_eq!(bytes.len() - h, 100 * 15);
    for r in bytes[h..].chunks_exact(15) {
        let p: Vec<f32> = (0..3).map(|k| f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap())).collect();
        assert!(p[0] >= -0.5 && p[1] <= 0.3 && p[2] >= -0.2, "outside the crop: {p:?}");
    }
}

/// `nerf render --crop BOX` renders only what lies in the box (instant-ngp's render box): rays
/// that miss it show the background; render.json and camera_path.json hold the crop (in
/// nerfstudio's form), and rendering that camera_path.json again gives the same frame; a
/// resumed render must have the same crop; a box beside the scene is a clear error.
#[test]
fn render_crops_to_a_box() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let json = |p: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap() };
    let render = |name: &str, extra: &[&str]| -> Vec<[u8; 3]> {
        let out = d.path().join(name);
        let o = nerf().arg("render").arg(&run).arg(&s).args(["--width", "24", "--device", "cpu", "--quiet", "--out"]).arg(&out).args(extra).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        image::open(out.join("frame_0000.png")).unwrap().to_rgb8().pixels().map(|p| p.0).collect()
    };
    // The share of pixels that are exactly the background (the run's: white).
    let bg = |f: &[[u8; 3]]| f.iter().filter(|p| **p == [255, 255, 255]).count() as f64 / f.len() as f64;
    let whole = render("whole", &["--frames", "2"]);
    // A slab at the box's +x face: almost every ray misses it.
    let cropped = render("cropped", &["--frames", "2", "--crop", "1.2,-1.5,-1.5,1.5,1.5,1.5"]);
    assert!(bg(&cropped) > 0.7 && bg(&cropped) > bg(&whole) + 0.2, "background: {} cropped, {} whole", bg(&cropped), bg(&whole));
    let r = json(&d.path().join("cropped/render.json"));
    let c = &r["crop"];
    let num = |v: &serde_json::Value| v.as_f64().unwrap();
    assert!((num(&c["crop_center"][0]) - 1.35).abs() < 1e-6 && (num(&c["crop_scale"][0]) - 0.3).abs() < 1e-6 && num(&c["crop_scale"][1]) == 3.0, "{r}");
    assert_eq!(c["crop_rot"], serde_json::json!([0.0, 0.0, 0.0]));
    assert!(json(&d.path().join("whole/render.json"))["crop"].is_null());
    // The path it wrote holds the crop: rendering it again gives the same frame.
    let path = d.path().join("cropped/camera_path.json");
    assert_eq!(json(&path)["crop"], *c);
    let again = render("again", &["--camera-path", path.to_str().unwrap()]);
    assert_eq!(again, cropped);
    // A resumed render keeps its crop.
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "2", "--width", "24", "--device", "cpu", "--resume", "--out"]).arg(d.path().join("cropped")).output().unwrap();
    assert_clean_failure(&o, &["render.json", "crop", "--resume"]);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--crop", "4,4,4,5,5,5", "--device", "cpu"]).output().unwrap();
    assert_clean_failure(&o, &["crop box", "outside the scene's box"]);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--crop", "1,1,1,0,0,0"]).output().unwrap();
    assert_eq!(o.status.code(), Some(2), "a usage error: {}", stderr(&o));
}

/// `nerf render --alpha`: RGBA frames whose colour over the background is the plain render
/// (to 8-bit rounding), transparent where the rays miss the crop box; render.json records it,
/// `--resume` keeps it (and rebuilds the GIF over the background from the frames so far).
#[test]
fn render_alpha_writes_frames_without_their_background() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let render = |name: &str, extra: &[&str]| -> Output {
        nerf().arg("render").arg(&run).arg(&s).args(["--width", "24", "--frames", "2", "--device", "cpu", "--quiet", "--crop", "-0.3,-1.5,-1.5,1.5,1.5,1.5", "--out"]).arg(d.path().join(name)).args(extra).output().unwrap()
    };
    let o = render("plain", &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = render("alpha", &["--alpha", "--gif", "10"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("-pix_fmt yuva420p"), "a video that keeps the alpha: {}", String::from_utf8_lossy(&o.stdout));
    let frame = |name: &str, i: usize| image::open(d.path().join(format!("{name}/frame_{i:04}.png"))).unwrap();
    for i in 0..2 {
        let (plain, alpha) = (frame("plain", i), frame("alpha", i));
        assert!(!plain.color().has_alpha() && alpha.color().has_alpha());
        let (plain, alpha) = (plain.to_rgb8(), alpha.to_rgba8());
        let (mut clear, mut seen) = (0, 0);
        for (p, q) in plain.pixels().zip(alpha.pixels()) {
            let a = q[3] as f64 / 255.0;
            for c in 0..3 {
                // Over the run's white background.
                let over = q[c] as f64 / 255.0 * a + (1.0 - a);
                assert!((over - p[c] as f64 / 255.0).abs() < 2.0 / 255.0, "frame {i}: {q:?} over white is not {p:?}");
            }
            if p.0 == [255, 255, 255] {
                clear += usize::from(q[3] == 0);
            }
            seen += usize::from(q[3] > 0);
        }
        let n = (plain.width() * plain.height()) as usize;
        assert!(clear > n / 4 && seen > 0, "frame {i}: {clear} transparent, {seen} with opacity, of {n}");
    }
    let json = |p: &str| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(d.path().join(p)).unwrap()).unwrap() };
    assert_eq!((json("alpha/render.json")["alpha"].clone(), json("plain/render.json")["alpha"].clone()), (true.into(), false.into()));
    assert!(d.path().join("alpha/render.gif").is_file());
    // Resumed after its first frame: the second is rendered again, the GIF made anew.
    let first = std::fs::read(d.path().join("alpha/frame_0001.png")).unwrap();
    let mut r = json("alpha/render.json");
    r["frames"] = 1.into();
    r["camera_to_world"] = serde_json::json!([r["camera_to_world"][0].clone()]);
    std::fs::write(d.path().join("alpha/render.json"), r.to_string()).unwrap();
    std::fs::remove_file(d.path().join("alpha/frame_0001.png")).unwrap();
    std::fs::remove_file(d.path().join("alpha/render.gif")).unwrap();
    let o = render("alpha", &["--resume"]);
    assert_clean_failure(&o, &["render.json", "alpha", "--resume"]);
    let o = render("alpha", &["--alpha", "--gif", "10", "--resume"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read(d.path().join("alpha/frame_0001.png")).unwrap(), first);
    assert!(d.path().join("alpha/render.gif").is_file());
}

/// `nerf export-mesh`: a binary PLY triangle mesh inside the scene box with unit normals; a
/// threshold above every density is a clear error that names the highest one, which then gives a
/// mesh; bad arguments are clear errors.
#[test]
fn export_mesh_writes_a_ply_mesh_inside_the_scene_box() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let mesh = |threshold: &str| {
        nerf().arg("export-mesh").arg(&run).arg(&s).args(["--resolution", "24", "--threshold", threshold, "--device", "cpu"]).output().unwrap()
    };
    // The highest density on a lattice, from the error a threshold above it gives.
    let highest = |o: Output| -> f32 {
        assert_clean_failure(&o, &["--threshold", "highest"]);
        let e = stderr(&o);
        let top: f32 = e.split('(').filter_map(|p| p.split(" per instant-ngp unit)").next()?.parse().ok()).next().unwrap_or_else(|| panic!("{e}"));
        assert!(top > 0.0, "{e}");
        top
    };
    let top = highest(mesh("1e9"));
    assert!(!run.join("mesh.ply").exists());
    let o = mesh(&format!("{}", 0.5 * top));
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(run.join("mesh.ply")).unwrap();
    let end = b"end_header\n";
    let h = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..h]).unwrap();
    let count = |e: &str| -> usize { header.split(&format!("element {e} ")).nth(1).unwrap().lines().next().unwrap().parse().unwrap() };
    let (nv, nf) = (count("vertex"), count("face"));
    assert!(nv > 0 && nf > 0 && bytes.len() - h == 27 * nv + 13 * nf, "{header}");
    assert!(String::from_utf8_lossy(&o.stdout).contains(&format!("{nv} vertices, {nf} triangles")));
    let f = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
    for v in 0..nv {
        let r = h + 27 * v;
        let (p, n): (Vec<f32>, Vec<f32>) = ((0..3).map(|k| f(r + 4 * k)).collect(), (3..6).map(|k| f(r + 4 * k)).collect());
        assert!(p.iter().all(|x| x.abs() <= 1.5), "vertex outside the Blender cube: {p:?}");
        let len = n.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!(len == 0.0 || (len - 1.0).abs() < 1e-4, "normal {n:?}");
    }
    for t in bytes[h + 27 * nv..].chunks_exact(13) {
        assert_eq!(t[0], 3);
        assert!((0..3).all(|j| (i32::from_le_bytes(t[1 + 4 * j..5 + 4 * j].try_into().unwrap()) as usize) < nv));
    }
    for (args, needle) in [(["--resolution", "1"], "--resolution"), (["--threshold", "0"], "--threshold"), (["--box", "5,5,5,6,6,6"], "misses")] {
        let o = nerf().arg("export-mesh").arg(&run).arg(&s).args(args).output().unwrap();
        assert_clean_failure(&o, &[needle]);
    }
    let o = nerf().arg("export-mesh").arg(&run).arg(&s).args(["--out", "mesh.stl"]).output().unwrap();
    assert_clean_failure(&o, &["mesh.stl", ".ply or .obj"]);
    // The same mesh as OBJ text: as many vertices and faces.
    let o = nerf().arg("export-mesh").arg(&run).arg(&s).args(["--resolution", "24", "--threshold", &format!("{}", 0.5 * top)])
        .args(["--device", "cpu", "--out"]).arg(d.path().join("mesh.obj")).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let obj = std::fs::read_to_string(d.path().join("mesh.obj")).unwrap();
    let lines = |p: &str| obj.lines().filter(|l| l.starts_with(p)).count();
    assert_eq!((lines("v "), lines("vn "), lines("f ")), (nv, nv, nf));
    let o = nerf().arg("export-mesh").arg(&run).arg(&s).args(["--box", "1,1,1,0,0,0"]).output().unwrap();
    assert!(o.status.code() == Some(2) && stderr(&o).contains("empty box"), "{}", stderr(&o));
    // A smaller box: every vertex inside it.
    let part = |threshold: f32| {
        nerf().arg("export-mesh").arg(&run).arg(&s).args(["--box=-0.5,-0.25,-0.5,0.5,0.5,0.75", "--resolution", "16"])
            .args(["--threshold", &format!("{threshold}"), "--device", "cpu", "--out"]).arg(d.path().join("part.ply")).output().unwrap()
    };
    let o = part(0.5 * highest(part(1e9)));
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(d.path().join("part.ply")).unwrap();
    let h = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..h]).unwrap();
    let nv: usize = header.split("element vertex ").nth(1).unwrap().lines().next().unwrap().parse().unwrap();
    assert!(nv > 0);
    for v in 0..nv {
        let p: Vec<f32> = (0..3).map(|k| f32::from_le_bytes(bytes[h + 27 * v + 4 * k..][..4].try_into().unwrap())).collect();
        assert!(p[0].abs() <= 0.5 && (-0.25..=0.5).contains(&p[1]) && (-0.5..=0.75).contains(&p[2]), "vertex outside --box: {p:?}");
    }
}

/// `nerf render --camera-type equirectangular|fisheye`: 360° panoramas twice as wide as high and
/// fisheye frames, camera paths that say so and render the same frames again; an NDC run is
/// refused (see the LLFF test).
#[test]
fn render_writes_panoramas_and_fisheye_frames() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let out = d.path().join("pano");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--camera-type", "equirectangular", "--frames", "2", "--width", "24", "--device", "cpu", "--out"])
        .arg(&out).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    for i in 0..2 {
        let img = image::open(out.join(format!("frame_{i:04}.png"))).unwrap();
        assert_eq!((img.width(), img.height()), (24, 12), "frame {i}");
    }
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("render.json")).unwrap()).unwrap();
    assert_eq!(r["camera_type"], "equirectangular");
    let p: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("camera_path.json")).unwrap()).unwrap();
    assert_eq!((p["camera_type"].as_str(), p["render_width"].as_u64(), p["render_height"].as_u64()), (Some("equirectangular"), Some(24), Some(12)));
    let again = d.path().join("again");
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(out.join("camera_path.json"))
        .args(["--device", "cpu", "--out"]).arg(&again).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    for i in 0..2 {
        let (a, b) = (image::open(out.join(format!("frame_{i:04}.png"))).unwrap(), image::open(again.join(format!("frame_{i:04}.png"))).unwrap());
        assert_eq!(a.to_rgb8().as_raw(), b.to_rgb8().as_raw(), "frame {i}");
    }
    // A perspective render of the same path differs (another projection, another size).
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "2", "--device", "cpu", "--out"]).arg(d.path().join("persp")).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(image::open(d.path().join("persp/frame_0000.png")).unwrap().width(), 50);
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--camera-type", "equirectangular", "--camera-path"]).arg(out.join("camera_path.json")).output().unwrap();
    assert!(o.status.code() == Some(2) && stderr(&o).contains("--camera-type"), "a usage error: {}", stderr(&o));
    // A fisheye: the training images' size, a path that says so and renders the same again,
    // frames unlike the pinhole's.
    let fish = d.path().join("fish");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--camera-type", "fisheye", "--frames", "2", "--device", "cpu", "--out"]).arg(&fish).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let p: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(fish.join("camera_path.json")).unwrap()).unwrap();
    assert_eq!(p["camera_type"], "fisheye");
    let again = d.path().join("fish_again");
    let o = nerf().arg("render").arg(&run).arg(&s).arg("--camera-path").arg(fish.join("camera_path.json")).args(["--device", "cpu", "--out"]).arg(&again).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let (f, g, q) = (image::open(fish.join("frame_0001.png")).unwrap().to_rgb8(), image::open(again.join("frame_0001.png")).unwrap().to_rgb8(), image::open(d.path().join("persp/frame_0001.png")).unwrap().to_rgb8());
    assert_eq!(f.dimensions(), (50, 50));
    assert_eq!(f.as_raw(), g.as_raw());
    assert_ne!(f.as_raw(), q.as_raw(), "the fisheye frame is the pinhole's");
}

/// `nerf export-scene --exposure-jitter`: the training views' colours are the unchanged export's
/// times the gains written to `exposure_gains.json` (mean 1 per channel; clipped at 1 in the
/// PNGs), test views are unchanged; a run with `[color_correction]` trains, checkpoints and
/// evaluates on it; an amount outside [0, 1) is a clear error.
#[test]
fn export_scene_changes_exposures_and_color_correction_trains_on_it() {
    let d = tempfile::tempdir().unwrap();
    let plain = small_scene(d.path());
    let s = d.path().join("exposed");
    let o = nerf().args(["export-scene"]).arg(repo().join("scenes/lego_100")).arg(&s)
        .args(["--downscale", "2", "--train-views", "first:3", "--test-views", "first:1", "--exposure-jitter", "0.3", "--seed", "5"])
        .output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(s.join("exposure_gains.json")).unwrap()).unwrap();
    assert_eq!(j["amount"], 0.3);
    assert_eq!(j["seed"], 5);
    let gains: Vec<[f64; 3]> = serde_json::from_value(j["gains"].clone()).unwrap();
    assert_eq!(gains.len(), 3);
    for c in 0..3 {
        let mean = gains.iter().map(|g| g[c]).sum::<f64>() / 3.0;
        assert!((mean - 1.0).abs() < 1e-6, "channel {c}: mean gain {mean}");
    }
    assert!(gains.iter().flatten().any(|&g| (g - 1.0).abs() > 0.02), "{gains:?}");
    let png = |p: PathBuf| image::open(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display())).to_rgba8();
    for (v, g) in gains.iter().enumerate() {
        let (a, b) = (png(plain.join(format!("train/r_{v}.png"))), png(s.join(format!("train/r_{v}.png"))));
        let mut checked = 0;
        for (pa, pb) in a.pixels().zip(b.pixels()) {
            assert_eq!(pa[3], pb[3], "view {v}: alpha kept");
            for c in 0..3 {
                let want = (pa[c] as f64 * g[c]).min(255.0);
                // Both PNGs round to 8 bits: the product is within a gain's worth of one level.
                assert!((pb[c] as f64 - want).abs() <= 1.0 + g[c], "view {v} channel {c}: {} vs {want}", pb[c]);
                checked += 1;
            }
        }
        assert!(checked > 1000);
    }
    assert_eq!(png(plain.join("test/r_0.png")), png(s.join("test/r_0.png")), "test views are unchanged");
    // A run with the correction on this scene: trains, checkpoints, evaluates.
    let cfg = d.path().join("cc.toml");
    std::fs::write(&cfg, "batch_rays = 64\ncheckpoint_every = 3\n[color_correction]\nlr = 0.01\n[field_config]\nwidth = 16\ndepth = 2\nskips = []\n\
        view_width = 8\n[sampler]\nkind = \"hierarchical\"\nn_coarse = 8\nn_fine = 8\n").unwrap();
    let run = d.path().join("run");
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(&run)
        .args(["--quiet", "--no-renders", "--iters", "3", "--device", "cpu"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--device", "cpu", "--quiet"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let eval: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("eval/eval.json")).unwrap()).unwrap();
    assert!(eval["test_psnr"].as_f64().unwrap().is_finite());
    // Rendering with one training view's appearance; a view past the run's is a clear error.
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--width", "16", "--device", "cpu", "--quiet", "--appearance", "2"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--device", "cpu", "--quiet", "--appearance", "3"]).output().unwrap();
    assert_clean_failure(&o, &["--appearance", "3 views"]);
    // The checkpoint's corrections are for 3 views: resuming on 2 is refused.
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(&run)
        .args(["--quiet", "--no-renders", "--iters", "6", "--device", "cpu", "--resume", "--train-views", "first:2"]).output().unwrap();
    assert_clean_failure(&o, &["3 training views", "has 2"]);
    let o = nerf().args(["export-scene"]).arg(repo().join("scenes/lego_100")).arg(d.path().join("x")).args(["--exposure-jitter", "1.5"]).output().unwrap();
    assert_clean_failure(&o, &["--exposure-jitter", "1.5"]);
}

/// `nerf export-scene --pose-noise-rot/--pose-noise-trans`: the training cameras are the
/// unchanged export's moved by the changes written to `pose_noise.json` (zero mean over the
/// views), test cameras are unchanged; a run with `[camera_optimizer]` trains on it and writes
/// its corrected poses to `camera_corrections.json` (and their mean size to metrics.json); a
/// negative amount is a clear error, and so is the optimizer on a field without input gradients.
#[test]
fn export_scene_moves_cameras_and_camera_optimizer_trains_on_it() {
    let d = tempfile::tempdir().unwrap();
    let plain = small_scene(d.path());
    let s = d.path().join("moved");
    let o = nerf().args(["export-scene"]).arg(repo().join("scenes/lego_100")).arg(&s)
        .args(["--downscale", "2", "--train-views", "first:3", "--test-views", "first:1", "--pose-noise-rot", "2", "--pose-noise-trans", "0.05", "--seed", "3"])
        .output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let json = |p: PathBuf| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap() };
    let j = json(s.join("pose_noise.json"));
    assert_eq!((j["rot_degrees"].as_f64(), j["trans"].as_f64(), j["seed"].as_u64()), (Some(2.0), Some(0.05), Some(3)));
    let noise: Vec<[f64; 6]> = serde_json::from_value(j["noise"].clone()).unwrap();
    assert_eq!(noise.len(), 3);
    for i in 0..6 {
        assert!(noise.iter().map(|p| p[i]).sum::<f64>().abs() < 1e-6, "component {i} has zero mean");
        let bound = if i < 3 { 0.1 } else { 4f64.to_radians() }; // twice the amount: the mean was taken out
        assert!(noise.iter().all(|p| p[i].abs() <= bound), "{noise:?}");
    }
    assert!(noise.iter().any(|p| p[3..].iter().any(|w| w.abs() > 1e-3)), "the cameras turned: {noise:?}");
    let frames = |p: PathBuf| -> Vec<[[f64; 4]; 4]> {
        json(p)["frames"].as_array().unwrap().iter().map(|f| serde_json::from_value(f["transform_matrix"].clone()).unwrap()).collect()
    };
    let (a, b) = (frames(plain.join("transforms_train.json")), frames(s.join("transforms_train.json")));
    for (v, ((ma, mb), p)) in a.iter().zip(&b).zip(&noise).enumerate() {
        for r in 0..3 {
            assert!((mb[r][3] - ma[r][3] - p[r]).abs() < 1e-5, "view {v}: the centre moved by τ");
        }
        // The rotation turned by |ω|: the angle between the optical axes is at most |ω|.
        let cos = (0..3).map(|r| ma[r][2] * mb[r][2]).sum::<f64>();
        let w = (p[3] * p[3] + p[4] * p[4] + p[5] * p[5]).sqrt();
        assert!(cos.min(1.0).acos() <= w + 1e-5, "view {v}");
    }
    assert_eq!(frames(plain.join("transforms_test.json")), frames(s.join("transforms_test.json")), "test cameras are unchanged");
    // A run with the optimizer on this scene writes the corrected poses.
    let cfg = d.path().join("pose.toml");
    // 1 024 samples a step (the preset's 2^16 made the 4 GPU steps 25 s on lavapipe, 2 s now).
    std::fs::write(&cfg, "field = \"hash\"\nbatch_rays = 64\ntarget_samples_per_step = 1024\ncompact_samples = false\n[camera_optimizer]\nlr = 0.001\n[field_config.grid]\nlog2_hashmap_size = 12\n\
        [sampler]\nkind = \"stratified\"\nn_samples = 16\n").unwrap();
    let run = d.path().join("run");
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(&run)
        .args(["--quiet", "--no-renders", "--iters", "4", "--device", "cpu"]).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let c = json(run.join("camera_corrections.json"));
    let views = c["views"].as_array().unwrap();
    assert_eq!(views.len(), 3);
    let moved = frames(s.join("transforms_train.json"));
    for (v, e) in views.iter().enumerate() {
        let p: [f64; 6] = serde_json::from_value(e["correction"].clone()).unwrap();
        assert!(p.iter().any(|x| *x != 0.0), "view {v} was corrected");
        let m: [[f64; 4]; 4] = serde_json::from_value(e["camera_to_world"].clone()).unwrap();
        for r in 0..3 {
            assert!((m[r][3] - moved[v][r][3] - p[r]).abs() < 1e-5, "view {v}: the corrected centre is the camera's + τ");
        }
    }
    let metrics = json(run.join("metrics.json"));
    assert!(metrics["camera_corrections"]["mean_rotation_degrees"].as_f64().unwrap() > 0.0);
    assert!((metrics["config"]["camera_optimizer"]["lr"].as_f64().unwrap() - 0.001).abs() < 1e-9, "the config as trained");
    let o = nerf().arg("eval").arg(&run).arg(&s).args(["--device", "cpu", "--quiet"]).output().unwrap();
    assert!(o.status.success(), "the run evaluates again from its checkpoint: {}", stderr(&o));
    // `export-scene --camera-corrections`: the scene again, its training views at the refined
    // poses (matched by name), its test views as they were.
    assert!(views.iter().all(|v| v["image"].is_string()), "{c}");
    let refined = d.path().join("refined");
    let o = nerf().args(["export-scene"]).arg(&s).arg(&refined).args(["--downscale", "1", "--test-views", "all", "--camera-corrections"]).arg(run.join("camera_corrections.json")).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let written = frames(refined.join("transforms_train.json"));
    for (v, e) in views.iter().enumerate() {
        let m: [[f64; 4]; 4] = serde_json::from_value(e["camera_to_world"].clone()).unwrap();
        assert!((0..3).all(|r| (0..4).all(|c| (written[v][r][c] - m[r][c]).abs() < 1e-5)), "view {v}: {:?} vs {m:?}", written[v]);
    }
    assert_eq!(frames(refined.join("transforms_test.json")), frames(s.join("transforms_test.json")));
    // A view the run did not train on has no refined pose.
    let o = nerf().args(["export-scene"]).arg(repo().join("scenes/lego_100")).arg(d.path().join("other")).args(["--downscale", "2", "--train-views", "first:4", "--camera-corrections"]).arg(run.join("camera_corrections.json")).output().unwrap();
    assert_clean_failure(&o, &["camera_corrections.json", "no refined pose for training view", "r_3"]);
    // On a GPU adapter (lavapipe here) it trains too, and writes the corrections the same way;
    // `eval` and `render` of the CPU run run there (the corrections are the training photos').
    let gpu_run = d.path().join("gpu");
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(&gpu_run)
        .args(["--quiet", "--no-renders", "--iters", "4", "--device", "gpu"]).output().unwrap();
    if stderr(&o).contains("no GPU adapter") {
        eprintln!("NOTICE: no GPU adapter; GPU training and rendering of the run not checked");
    } else {
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(json(gpu_run.join("metrics.json"))["device"].as_str(), Some("gpu"));
        let c = json(gpu_run.join("camera_corrections.json"));
        assert_eq!(c["views"].as_array().unwrap().len(), 3);
        assert!(c["mean_rotation_degrees"].as_f64().unwrap() > 0.0, "the GPU run corrected the cameras: {c}");
        let o = nerf().arg("eval").arg(&run).arg(&s).args(["--device", "gpu", "--quiet"]).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let gpu_eval = json(run.join("eval/eval.json"));
        assert_eq!(gpu_eval["device"].as_str(), Some("gpu"), "{gpu_eval}");
        let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "1", "--width", "16", "--device", "gpu", "--quiet"]).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
    }
    // What it cannot take.
    let o = nerf().args(["export-scene"]).arg(repo().join("scenes/lego_100")).arg(d.path().join("x")).arg("--pose-noise-rot=-1").output().unwrap();
    assert_clean_failure(&o, &["--pose-noise-rot", "-1"]);
    std::fs::write(&cfg, "field = \"voxel\"\n[camera_optimizer]\n").unwrap();
    let o = nerf().arg("train").arg(&s).arg("--config").arg(&cfg).arg("--out").arg(d.path().join("voxel"))
        .args(["--quiet", "--iters", "1", "--device", "cpu"]).output().unwrap();
    assert_clean_failure(&o, &["camera_optimizer", "voxel"]);
}

#[test]
fn render_and_exports_read_only_the_cameras_of_the_training_photos() {
    let d = tempfile::tempdir().unwrap();
    let (s, run) = tiny_cpu_run(d.path());
    let mesh = || nerf().arg("export-mesh").arg(&run).arg(&s).args(["--resolution", "16", "--threshold", "0.001", "--device", "cpu"]).output().unwrap();
    let before = mesh();
    let points = || {
        let o = nerf().arg("export-points").arg(&run).arg(&s).args(["--points", "10", "--min-opacity", "0", "--device", "cpu"]).output().unwrap();
        assert!(o.status.success(), "export-points: {}", stderr(&o));
        std::fs::read(run.join("points.ply")).unwrap()
    };
    let points_before = points();
    // Cut every training photo inside its pixel data: the header (size) still reads, the pixels
    // no longer decode.
    for e in std::fs::read_dir(s.join("train")).unwrap() {
        let p = e.unwrap().path();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    }
    let out = d.path().join("frames");
    let o = nerf().arg("render").arg(&run).arg(&s).args(["--frames", "2", "--width", "16", "--device", "cpu", "--out"]).arg(&out).output().unwrap();
    assert!(o.status.success(), "render decodes no training photo: {}", stderr(&o));
    assert!(out.join("frame_0001.png").exists());
    let after = mesh();
    assert_eq!((after.status.code(), &after.stdout), (before.status.code(), &before.stdout), "export-mesh decodes no training photo: {}", stderr(&after));
    // Exporting points casts rays from the training cameras, decoding no photo either: the same
    // points.
    assert!(points() == points_before, "export-points gave other points without the photos' pixels");
}

#[test]
fn ablate_shows_each_runs_progress() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = small_scene(tmp.path());
    let file = tmp.path().join("tiny.toml");
    std::fs::write(
        &file,
        format!(
            "name = \"tiny\"\nscenes = [{:?}]\ndownscale = 1\ntrain_views = \"all\"\ntest_views = \"all\"\nseeds = [0]\n\
             [budget]\niters = 6\n[eval]\nevery_iters = 3\n\
             [base]\nfield = \"freq\"\nbatch_rays = 64\nlog_every = 2\n\
             field_config = {{ width = 16, depth = 2, skips = [], view_width = 8 }}\n\
             sampler = {{ kind = \"hierarchical\", n_coarse = 8, n_fine = 8 }}\n\
             [[runs]]\nname = \"a\"\nconfig = {{}}\n",
            scene.display().to_string()
        ),
    )
    .unwrap();
    let o = nerf().arg("ablate").arg(&file).args(["--device", "cpu", "--out"]).arg(tmp.path().join("out")).output().unwrap();
    let e = stderr(&o);
    assert!(o.status.success(), "{e}");
    // The training log every 2 steps and the test PSNR at steps 3 and 6, as they happen.
    for step in [2, 4, 6] {
        assert!(e.contains(&format!("[1] a__scene__s0: step {step}, ")) && e.contains("training PSNR"), "step {step}: {e}");
    }
    for step in [3, 6] {
        let line = e.lines().find(|l| l.starts_with(&format!("[1] a__scene__s0: step {step}, ")) && l.contains("test PSNR"));
        assert!(line.is_some(), "no evaluation at step {step}: {e}");
    }
}

/// A scene whose photos were taken through a lens: `nerf train` traces rays through it, or with
/// `--undistort` resamples the photos (the choice kept in metrics.json, which `nerf eval`
/// follows); `nerf export-scene` writes the lens, or pinhole images with `--undistort`; a lens
/// that folds over inside its photo is refused by name.
#[test]
fn lens_scenes_train_through_their_lens_or_undistorted() {
    let d = tempfile::tempdir().unwrap();
    let scene = small_scene(d.path());
    let set_lens = |keys: serde_json::Value| {
        for split in ["train", "test"] {
            let p = scene.join(format!("transforms_{split}.json"));
            let mut t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
            t.as_object_mut().unwrap().extend(keys.as_object().unwrap().clone());
            std::fs::write(&p, t.to_string()).unwrap();
        }
    };
    set_lens(serde_json::json!({"is_fisheye": true, "k1": 0.02}));
    for (name, extra) in [("native", &[][..]), ("undistorted", &["--undistort"][..])] {
        let run = d.path().join(name);
        let o = train_tiny(&scene, &run, &[&["--iters", "2", "--device", "cpu"], extra].concat());
        assert!(o.status.success(), "{}", stderr(&o));
        let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).unwrap()).unwrap();
        assert_eq!(m["config"]["undistort"].as_bool().unwrap_or(false), !extra.is_empty(), "{name}");
        let o = nerf().arg("eval").arg(&run).arg(&scene).args(["--device", "cpu"]).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let e: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("eval/eval.json")).unwrap()).unwrap();
        let (a, b) = (m["test_psnr"].as_f64().unwrap(), e["test_psnr"].as_f64().unwrap());
        assert!((a - b).abs() < 1e-9, "{name}: eval loads the test views as the run did: {a} vs {b}");
    }
    for (name, extra) in [("with_lens", &[][..]), ("pinhole", &["--undistort"][..])] {
        let out = d.path().join(name);
        let o = nerf().arg("export-scene").arg(&scene).arg(&out).args(["--downscale", "1"]).args(extra).output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("transforms_train.json")).unwrap()).unwrap();
        assert_eq!(t["is_fisheye"].as_bool(), extra.is_empty().then_some(true), "{name}: {t}");
    }
    set_lens(serde_json::json!({"is_fisheye": false, "k1": -0.9}));
    let o = train_tiny(&scene, &d.path().join("folded"), &["--iters", "1", "--device", "cpu"]);
    assert_clean_failure(&o, &["transforms_train.json", "frames[0].k1", "folds over"]);
}
