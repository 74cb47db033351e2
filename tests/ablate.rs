//! End to end: a tiny ablation (two fields × two settings, a few steps) on a reduced copy of the
//! in-repo scene writes per-run curves and metrics, results.csv, results.md and both plots; a
//! second invocation skips every finished run and rebuilds the same outputs; changing the budget
//! makes the runs train again.

use nerf::ablate::{read_png_rgb, run_ablation, AblateOptions, Ablation};
use nerf::data::{load_blender, write_blender, LoadOptions, Split, ViewSelection};
use std::path::{Path, PathBuf};

/// Writes a small scene (3 training views, 1 test view, downscale 4) into `dir`.
fn tiny_scene(dir: &Path) -> PathBuf {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/lego_100");
    let dst = dir.join("lego_tiny");
    for (split, n) in [(Split::Train, 3), (Split::Test, 1)] {
        let ds = load_blender(&src, split, &LoadOptions { downscale: 4, views: ViewSelection::First(n), ..Default::default() }).unwrap();
        write_blender(&ds, &dst, None).unwrap();
    }
    dst
}

fn ablation_text(iters: u64) -> String {
    format!(
        r#"
name = "tiny"
scenes = ["lego_tiny"]
test_views = "all"
seeds = [0]
[budget]
iters = {iters}
[eval]
every_iters = 2
[base]
log_every = 3
[[runs]]
name = "freq"
config = {{ field = "freq", batch_rays = 64, field_config = {{ width = 16, depth = 2, skips = [], view_width = 8 }}, sampler = {{ kind = "hierarchical", n_coarse = 8, n_fine = 8 }} }}
[[runs]]
name = "hash"
config = {{ field = "hash", target_samples_per_step = 2048, field_config = {{ grid = {{ log2_hashmap_size = 12, n_levels = 4 }} }}, camera_optimizer = {{}} }}
[grid]
train_background = ["white", "black"]
"#
    )
}

fn read(p: &Path) -> String {
    std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

#[test]
fn tiny_ablation_end_to_end_and_skip_on_rerun() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_scene(tmp.path());
    let file = tmp.path().join("tiny.toml");
    std::fs::write(&file, ablation_text(4)).unwrap();
    let out = tmp.path().join("out");
    let opts = AblateOptions { out_dir: out.clone(), verbose: true, device: nerf::gpu::DevicePreference::Cpu };
    let registry = nerf::registry();

    let ab = Ablation::load(&file).unwrap();
    let report = run_ablation(&ab, &registry, &opts).unwrap();
    assert_eq!(report.runs.len(), 4);
    assert!(report.runs.iter().all(|r| !r.skipped));
    let ids: Vec<&str> = report.runs.iter().map(|r| r.plan.id.as_str()).collect();
    assert_eq!(
        ids,
        [
            "freq__train_background=white__lego_tiny__s0",
            "freq__train_background=black__lego_tiny__s0",
            "hash__train_background=white__lego_tiny__s0",
            "hash__train_background=black__lego_tiny__s0",
        ]
    );

    // Per-run outputs.
    let run_dirs: Vec<_> = std::fs::read_dir(out.join("runs")).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(run_dirs.len(), 4);
    for r in &report.runs {
        let dir = out.join("runs").join(&r.plan.id);
        let m: serde_json::Value = serde_json::from_str(&read(&dir.join("metrics.json"))).unwrap();
        for key in [
            "field", "device", "iterations", "wall_seconds", "ms_per_iter", "samples_per_sec", "test_psnr",
            "test_ssim", "n_test_views", "width", "height", "config", "n_params", "peak_memory_mib", "curve",
            "config_hash",
        ] {
            assert!(m.get(key).is_some(), "{}: metrics.json lacks `{key}`", r.plan.id);
        }
        assert_eq!(m["iterations"], 4);
        assert_eq!(m["field"], r.plan.config.field.as_str());
        assert_eq!(m["config"]["train_background"], r.plan.grid[0].1);
        assert!(m["n_params"].as_u64().unwrap() > 0);
        // The hash runs refine the cameras: their corrections' sizes, and every view's in a file.
        let pose = r.plan.config.camera_optimizer.is_some();
        assert_eq!(pose, r.plan.config.field == "hash");
        assert_eq!(m.get("camera_corrections").is_some(), pose, "{}", r.plan.id);
        assert_eq!(dir.join("camera_corrections.json").exists(), pose, "{}", r.plan.id);
        if pose {
            assert!(m["camera_corrections"]["mean_rotation_degrees"].as_f64().unwrap() > 0.0);
            let c: serde_json::Value = serde_json::from_str(&read(&dir.join("camera_corrections.json"))).unwrap();
            assert_eq!(c["views"].as_array().unwrap().len(), 3);
        }
        let curve = read(&dir.join("curve.csv"));
        let lines: Vec<&str> = curve.lines().collect();
        assert_eq!(lines[0], "iter,seconds,psnr,ssim");
        let pts: Vec<Vec<f64>> =
            lines[1..].iter().map(|l| l.split(',').map(|x| x.parse::<f64>().unwrap()).collect()).collect();
        assert!(pts.len() >= 2, "{}: {} curve points", r.plan.id, pts.len());
        assert_eq!(pts.iter().map(|p| p[0] as u64).collect::<Vec<_>>(), [2, 4]);
        assert!(pts.windows(2).all(|w| w[1][1] >= w[0][1]), "training time is monotone");
        assert!(pts.iter().all(|p| p[2].is_finite() && p[2] > 0.0 && p[3].is_finite()));
        assert!((r.metrics.test_psnr - pts.last().unwrap()[2]).abs() < 1e-9);
        // The training log: every `log_every` (3) steps and the last step, with `nerf train`'s keys.
        let log = m["train_log"].as_array().unwrap();
        assert_eq!(log.iter().map(|p| p["step"].as_u64().unwrap()).collect::<Vec<_>>(), [3, 4], "{}", r.plan.id);
        for p in log {
            for key in ["elapsed_secs", "loss", "train_psnr", "lr", "samples", "marched_samples", "rays", "alive_rays", "train_psnr_alive"] {
                assert!(p[key].as_f64().is_some_and(|x| x.is_finite() && x > 0.0), "{}: train_log {key}: {p}", r.plan.id);
            }
            // The alive rays are some of the batch.
            assert!(p["alive_rays"].as_u64() <= p["rays"].as_u64(), "{p}");
        }
        assert!(log[0]["elapsed_secs"].as_f64() <= log[1]["elapsed_secs"].as_f64());
    }
    // The hash runs honour their field_config and preset (occupancy sampler), the freq runs theirs.
    assert_ne!(report.runs[0].metrics.n_params, report.runs[2].metrics.n_params);
    assert!(matches!(report.runs[2].plan.config.sampler, nerf::train::SamplerConfig::Occupancy { .. }));

    // results.csv
    let csv = read(&out.join("results.csv"));
    let rows: Vec<Vec<&str>> = csv.lines().map(|l| l.split(',').collect()).collect();
    let header = &rows[0];
    assert_eq!(
        header,
        &[
            "id", "name", "scene", "seed", "train_background", "field", "iterations", "wall_seconds", "ms_per_iter",
            "samples_per_sec", "n_params", "peak_memory_mib", "test_psnr", "test_ssim"
        ]
    );
    assert_eq!(rows.len(), 5, "header + 4 runs:\n{csv}");
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    for (row, r) in rows[1..].iter().zip(&report.runs) {
        assert_eq!(row.len(), header.len());
        assert_eq!(row[col("id")], r.plan.id);
        assert_eq!(row[col("scene")], "lego_tiny");
        assert_eq!(row[col("iterations")], "4");
        assert_eq!(row[col("train_background")], r.plan.grid[0].1.as_str().unwrap());
        let psnr: f64 = row[col("test_psnr")].parse().unwrap();
        let ssim: f64 = row[col("test_ssim")].parse().unwrap();
        assert!(psnr.is_finite() && psnr > 0.0 && ssim.is_finite(), "{row:?}");
        assert!(row[col("ms_per_iter")].parse::<f64>().unwrap() > 0.0);
        assert!(row[col("samples_per_sec")].parse::<f64>().unwrap() > 0.0);
    }

    // results.md
    let md = read(&out.join("results.md"));
    let table: Vec<&str> = md.lines().filter(|l| l.starts_with('|')).collect();
    assert_eq!(table.len(), 2 + 4, "{md}");
    assert!(table[0].contains("test PSNR") && table[0].contains("ms/iter") && table[0].contains("params"));
    assert!(table[1].starts_with("|---|"));
    for (line, r) in table[2..].iter().zip(&report.runs) {
        assert!(line.contains(&format!("{:.2}", r.metrics.test_psnr)), "{line}");
        assert!(line.contains(&r.metrics.field), "{line}");
    }

    // Plots decode and are not blank.
    for p in [&report.psnr_vs_time, &report.psnr_vs_iter] {
        let (w, h, px) = read_png_rgb(p).unwrap_or_else(|e| panic!("{e}"));
        assert!(w > 0 && h > 0 && px.len() == 3 * (w * h) as usize);
        let non_white = px.chunks(3).filter(|c| *c != [255, 255, 255]).count();
        assert!(non_white > 1000, "{}: only {non_white} drawn pixels", p.display());
    }

    // Re-run: every run is skipped and the summary is rebuilt identically.
    let mtimes = |r: &nerf::ablate::AblationReport| -> Vec<_> {
        r.runs
            .iter()
            .map(|o| std::fs::metadata(out.join("runs").join(&o.plan.id).join("metrics.json")).unwrap().modified().unwrap())
            .collect()
    };
    let before = mtimes(&report);
    let summary = |names: &[&str]| -> Vec<Vec<u8>> { names.iter().map(|n| std::fs::read(out.join(n)).unwrap()).collect() };
    let files = ["results.csv", "results.md", "psnr_vs_time.png", "psnr_vs_iter.png"];
    let first = summary(&files);
    std::fs::remove_file(out.join("results.csv")).unwrap();
    let again = run_ablation(&Ablation::load(&file).unwrap(), &registry, &opts).unwrap();
    assert!(again.runs.iter().all(|r| r.skipped), "every finished run is skipped");
    assert_eq!(mtimes(&again), before);
    for ((name, a), b) in files.iter().zip(summary(&files)).zip(&first) {
        assert!(&a == b, "{name} is not rebuilt identically");
    }
    for (a, b) in again.runs.iter().zip(&report.runs) {
        assert_eq!(a.metrics, b.metrics);
    }

    // A different budget changes every config hash: the runs train again.
    std::fs::write(&file, ablation_text(2)).unwrap();
    let third = run_ablation(&Ablation::load(&file).unwrap(), &registry, &opts).unwrap();
    assert!(third.runs.iter().all(|r| !r.skipped));
    assert!(third.runs.iter().all(|r| r.metrics.iterations == 2 && r.metrics.curve.len() == 1));
    assert!(third.runs.iter().zip(&report.runs).all(|(a, b)| a.plan.config_hash != b.plan.config_hash));
}

#[test]
fn the_example_ablations_parse_and_plan() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/ablations");
    for name in ["fields.toml", "hash_sweep.toml"] {
        let a = Ablation::load(&dir.join(name)).unwrap();
        let plans = a.plan(&nerf::registry()).unwrap();
        assert!(!plans.is_empty(), "{name}");
        for p in &plans {
            assert!(p.scene.join("transforms_train.json").exists(), "{name}: {}", p.scene.display());
            assert!(p.config.time_budget_secs.is_some(), "{name}: examples use a time budget");
        }
    }
    // The device ablations (their scene is a copy of ../shared's lego in .data/, made on demand).
    // The variants of h100_lego.toml are checked against its plan.
    let preset = Ablation::load(&dir.join("h100_lego.toml")).unwrap().plan(&nerf::registry()).unwrap();
    // The preset with a batch of 2^19 samples per step, nothing else changed.
    let b19 = Ablation::load(&dir.join("h100_lego_batch19.toml")).unwrap();
    assert!(b19.spec.checkpoints);
    let b19 = b19.plan(&nerf::registry()).unwrap();
    assert_eq!(b19.len(), 1);
    let mut same = b19[0].config.clone();
    assert_eq!(same.target_samples_per_step, Some(1 << 19));
    same.target_samples_per_step = preset[0].config.target_samples_per_step;
    assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&preset[0].config).unwrap());
    // The doubled batch with the distortion loss: h100_lego_batch19.toml's plan but for the loss.
    let b19d = Ablation::load(&dir.join("h100_lego_batch19_distortion.toml")).unwrap();
    assert!(b19d.spec.checkpoints);
    let b19d = b19d.plan(&nerf::registry()).unwrap();
    assert_eq!(b19d.len(), 1);
    let mut same = b19d[0].config.clone();
    assert_eq!((same.distortion_loss, b19[0].config.distortion_loss), (Some(0.01), None));
    same.distortion_loss = None;
    assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&b19[0].config).unwrap());
    // The preset with its finest grid level at 1024 cells instead of 2048, nothing else changed.
    let res1024 = Ablation::load(&dir.join("h100_lego_res1024.toml")).unwrap();
    assert!(res1024.spec.checkpoints);
    let res1024 = res1024.plan(&nerf::registry()).unwrap();
    assert_eq!(res1024.len(), 1);
    let mut same = res1024[0].config.clone();
    let grid = same.field_config.as_object_mut().unwrap().remove("grid").unwrap();
    assert_eq!(grid, serde_json::json!({ "max_resolution": 1024 }));
    assert_eq!(same.field_config, serde_json::json!({}), "the grid is the only field key it sets");
    assert!(preset[0].config.field_config.get("grid").is_none(), "the preset leaves the grid at its defaults (2048)");
    assert_eq!(nerf::encoding::hash_grid::HashGridConfig::default().max_resolution, 2048);
    same.field_config = preset[0].config.field_config.clone();
    assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&preset[0].config).unwrap());
    // Both leads at once: the doubled batch's plan with the coarser finest level.
    let b19r = Ablation::load(&dir.join("h100_lego_batch19_res1024.toml")).unwrap();
    assert!(b19r.spec.checkpoints);
    let b19r = b19r.plan(&nerf::registry()).unwrap();
    assert_eq!(b19r.len(), 1);
    let mut same = b19r[0].config.clone();
    assert_eq!(same.target_samples_per_step, Some(1 << 19));
    assert_eq!(same.field_config, res1024[0].config.field_config, "the finest level of h100_lego_res1024.toml");
    same.field_config = b19[0].config.field_config.clone();
    assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&b19[0].config).unwrap());
    // The step-matched files for a lease on another GPU: their h100_*.toml counterparts stopped at
    // lease F's 5-minute step count (halved for the doubled batch), under the same 300-s cap,
    // evaluated at each fifth of the steps.
    for (name, twin, iters, every) in [
        ("h100eq_lego.toml", &preset, 43_664, 8_733),
        ("h100eq_lego_batch19.toml", &b19, 21_832, 4_367),
        ("h100eq_lego_batch19_distortion.toml", &b19d, 21_832, 4_367),
        ("h100eq_lego_res1024.toml", &res1024, 43_664, 8_733),
        ("h100eq_lego_batch19_res1024.toml", &b19r, 21_832, 4_367),
    ] {
        let a = Ablation::load(&dir.join(name)).unwrap();
        assert!(a.spec.checkpoints, "{name}");
        assert_eq!((a.spec.budget.iters, a.spec.budget.seconds), (Some(iters), Some(300.0)), "{name}");
        assert_eq!((a.spec.eval.every_iters, a.spec.eval.every_seconds), (Some(every), None), "{name}");
        assert_eq!(iters / every, 4, "{name}: four evaluations before the final one");
        let plans = a.plan(&nerf::registry()).unwrap();
        assert_eq!(plans.len(), 1, "{name}");
        let mut same = plans[0].config.clone();
        assert_eq!((same.iters, twin[0].config.iters), (iters, u64::MAX), "{name}");
        same.iters = twin[0].config.iters;
        assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&twin[0].config).unwrap(), "{name}");
    }
    // The step-matched pair with tiny-cuda-nn's sparse Adam on the table: only the Adam differs.
    let pair = Ablation::load(&dir.join("h100eq_lego_batch19_res1024.toml")).unwrap().plan(&nerf::registry()).unwrap();
    let sparse = Ablation::load(&dir.join("h100eq_lego_batch19_res1024_sparse.toml")).unwrap();
    assert!(sparse.spec.checkpoints);
    assert_eq!((sparse.spec.budget.iters, sparse.spec.budget.seconds, sparse.spec.eval.every_iters), (Some(21_832), Some(300.0), Some(4_367)));
    let sparse = sparse.plan(&nerf::registry()).unwrap();
    assert_eq!((sparse.len(), pair.len()), (1, 1));
    let mut same = sparse[0].config.clone();
    assert!(same.adam.is_sparse("field/hash_grid") && !same.adam.is_sparse("field/color_mlp"));
    same.adam.sparse_groups.clear();
    assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&pair[0].config).unwrap());
    // Its 5-minute file, for an H100: the twin's plan with no step cap, as the pair's files are.
    let sparse5 = Ablation::load(&dir.join("h100_lego_batch19_res1024_sparse.toml")).unwrap();
    assert!(sparse5.spec.checkpoints);
    assert_eq!((sparse5.spec.budget.iters, sparse5.spec.budget.seconds), (None, Some(300.0)));
    assert_eq!((sparse5.spec.eval.every_iters, sparse5.spec.eval.every_seconds), (None, Some(60.0)));
    let sparse5 = sparse5.plan(&nerf::registry()).unwrap();
    assert_eq!(sparse5.len(), 1);
    let mut same = sparse5[0].config.clone();
    assert_eq!((same.iters, sparse[0].config.iters), (u64::MAX, 21_832));
    same.iters = sparse[0].config.iters;
    assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&sparse[0].config).unwrap());
    // The density pass in place against its copies: the pair's field and batch, two runs that
    // differ in `gpu_density_in_place` alone (and each trains the field the pair trains).
    let ab = Ablation::load(&dir.join("h100_density_in_place.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(ab.len(), 2);
    assert!(ab.iter().all(|p| p.config.target_samples_per_step == Some(1 << 19) && p.config.gpu_profile.is_some()));
    assert_eq!(ab[1].config.field_config["gpu_density_in_place"], false);
    assert_eq!(ab[0].config.field_config["grid"], pair[0].config.field_config["grid"]);
    let mut copies = ab[1].config.clone();
    copies.field_config.as_object_mut().unwrap().remove("gpu_density_in_place");
    assert_eq!(serde_json::to_value(&copies).unwrap(), serde_json::to_value(&ab[0].config).unwrap());
    for (name, n_runs) in [("h100_lego.toml", 1), ("h100_lego_tcnn_grid.toml", 1), ("h100_lego_occ_threshold.toml", 1), ("h100_coop.toml", 2), ("h100_lego60.toml", 2), ("h100_lego_table20.toml", 1), ("h100_lego_table20_f16.toml", 1), ("h100_lego_table21.toml", 1), ("h100_lego_nerfacc.toml", 1), ("h100_lego_distortion.toml", 1), ("h100_lego_distortion_003.toml", 1), ("h100_lego_color_features.toml", 1), ("h100_lego_ema099.toml", 1), ("h100_lego_res1024.toml", 1)] {
        let a = Ablation::load(&dir.join(name)).unwrap();
        let plans = a.plan(&nerf::registry()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(plans.len(), n_runs, "{name}");
        assert!(plans.iter().all(|p| p.config.field == "hash" && p.config.target_samples_per_step == Some(1 << 18)), "{name}");
        if name == "h100_lego60.toml" {
            // The preset's minute, profiled after the marched samples' growth, against the
            // table's subgroup sums (benches/device/recheck.sh).
            assert!(plans.iter().all(|p| p.config.time_budget_secs == Some(60.0) && p.config.gpu_profile.is_some_and(|w| w.start == 6000)));
            assert_eq!(plans[1].config.field_config["gpu_hash_subgroup_sums"], true);
            continue;
        }
        if name.starts_with("h100_lego") {
            // configs/gpu_hash.toml's schedule: annealed over the 5 minutes, whatever the step rate.
            assert!(matches!(&plans[0].config.lr, nerf::optim::LrSchedule::Progress { at, warmup_steps: 100, .. } if at.len() == 3));
            assert!(plans[0].config.validate().is_ok());
            // Each keeps its checkpoint: device_session.sh's lego run (the preset, or a variant as
            // LEGO=FILE) is then scored on all 200 test views by eval_half.sh.
            assert!(a.spec.checkpoints, "{name}");
        }
        if name == "h100_lego_occ_threshold.toml" {
            // The preset's sampler but for the threshold.
            match (&plans[0].config.sampler, &preset[0].config.sampler) {
                (nerf::train::SamplerConfig::Occupancy { grid: g, .. }, nerf::train::SamplerConfig::Occupancy { grid: p, .. }) => {
                    assert_eq!((g.threshold, p.threshold), (0.05, 0.01));
                    assert_eq!(nerf::sampling::OccupancyGridConfig { threshold: p.threshold, ..g.clone() }, *p);
                }
                s => panic!("{name}: sampler {s:?}"),
            }
            assert_eq!(plans[0].config.field_config, preset[0].config.field_config);
        }
        if let Some(t) = name.strip_prefix("h100_lego_table").and_then(|r| r.strip_suffix(".toml")) {
            // The preset but for the table's size (and, for `_f16`, its lookups' storage).
            let (size, f16) = t.split_once("_f16").map_or((t, false), |(s, _)| (s, true));
            let grid = &plans[0].config.field_config["grid"];
            assert_eq!(grid["log2_hashmap_size"].as_u64(), size.parse().ok(), "{name}");
            assert_eq!(grid["storage"].as_str(), f16.then_some("f16"), "{name}");
            assert_eq!((&plans[0].config.sampler, plans[0].config.time_budget_secs), (&preset[0].config.sampler, preset[0].config.time_budget_secs));
        }
        if name == "h100_lego_tcnn_grid.toml" {
            let grid = &plans[0].config.field_config["grid"];
            assert_eq!((grid["max_resolution"].as_u64(), grid["align"].as_str()), (Some(4096), Some("staggered")));
        }
        if let Some(lambda) = [("h100_lego_distortion.toml", 0.01), ("h100_lego_distortion_003.toml", 0.03)].iter().find(|(n, _)| *n == name).map(|(_, l)| *l) {
            // The preset but for the distortion loss.
            let mut same = plans[0].config.clone();
            assert_eq!((same.distortion_loss, preset[0].config.distortion_loss), (Some(lambda), None), "{name}");
            same.distortion_loss = None;
            assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&preset[0].config).unwrap());
        }
        if name == "h100_lego_color_features.toml" {
            // The preset but for the colour MLP's input (nerfacc's head).
            let mut same = plans[0].config.clone();
            assert_eq!(same.field_config, serde_json::json!({ "color_input": "features" }), "{name}");
            same.field_config = preset[0].config.field_config.clone();
            assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&preset[0].config).unwrap());
        }
        if name == "h100_lego_ema099.toml" {
            // The preset but for the weights' moving average, which only the renders read.
            let mut same = plans[0].config.clone();
            assert_eq!((same.ema_decay, preset[0].config.ema_decay), (Some(0.99), Some(0.95)), "{name}");
            same.ema_decay = preset[0].config.ema_decay;
            assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(&preset[0].config).unwrap());
        }
        if name == "h100_lego_nerfacc.toml" {
            // The preset but for nerfacc's recipe: Adam's beta2, the training background, the
            // grid (tiny-cuda-nn's, as h100_lego_tcnn_grid.toml) and sigma = exp(x - 1).
            let (c, p) = (&plans[0].config, &preset[0].config);
            assert_eq!((c.adam.beta2, p.adam.beta2), (0.999, 0.99));
            assert_eq!((c.train_background, p.train_background), (nerf::data::Background::White, nerf::data::Background::Random));
            let grid = &c.field_config["grid"];
            assert_eq!((grid["max_resolution"].as_u64(), grid["align"].as_str()), (Some(4096), Some("staggered")));
            assert_eq!(c.field_config["density_bias"].as_f64(), Some(-1.0));
            let mut same = c.clone();
            (same.adam, same.train_background, same.field_config) = (p.adam.clone(), p.train_background, p.field_config.clone());
            assert_eq!(serde_json::to_value(&same).unwrap(), serde_json::to_value(p).unwrap());
        }
    }
    // Supersampled evaluation: the second run trains with jitter and scores with 8 rays per pixel,
    // the first as the preset; both keep their checkpoints for `nerf eval --spp`.
    let a = Ablation::load(&dir.join("supersample_lego400.toml")).unwrap();
    let ss = a.plan(&nerf::registry()).unwrap();
    assert!(a.spec.checkpoints && ss.len() == 2);
    assert_eq!((ss[0].config.pixel_jitter, ss[0].config.eval_spp), (false, 1));
    assert_eq!((ss[1].config.pixel_jitter, ss[1].config.eval_spp), (true, 8));
    assert!(ss.iter().all(|p| p.config.validate().is_ok()));
    // The GPU/CPU parity run trains the CPU's lego 400x400 preset row as it was (same config),
    // on two seeds.
    let parity = Ablation::load(&dir.join("h100_lego400_parity.toml")).unwrap().plan(&nerf::registry()).unwrap();
    let cpu = Ablation::load(&dir.join("nerfacc_lego400.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(parity.len(), 2);
    for p in &parity {
        let mut c = p.config.clone();
        c.seed = cpu[0].config.seed;
        assert_eq!(serde_json::to_value(&c).unwrap(), serde_json::to_value(&cpu[0].config).unwrap());
    }
    assert_ne!(parity[0].config.seed, parity[1].config.seed);
    // The same over 6000 steps: the preset row of the CPU's long occupancy-threshold run.
    let long = Ablation::load(&dir.join("h100_lego400_parity_long.toml")).unwrap().plan(&nerf::registry()).unwrap();
    let cpu_long = Ablation::load(&dir.join("occ_threshold_lego400_long.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(long.len(), 2);
    assert_ne!(long[0].config.seed, long[1].config.seed);
    for p in &long {
        let mut c = p.config.clone();
        c.seed = cpu_long[0].config.seed;
        assert_eq!(serde_json::to_value(&c).unwrap(), serde_json::to_value(&cpu_long[0].config).unwrap());
    }
    // nerfacc's colour head over the same 6000 steps: that preset row but for the colour input.
    let head = Ablation::load(&dir.join("color_input_lego400_long.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(head.len(), 1);
    let mut c = head[0].config.clone();
    assert_eq!(c.field_config, serde_json::json!({ "color_input": "features" }));
    c.field_config = cpu_long[0].config.field_config.clone();
    assert_eq!(serde_json::to_value(&c).unwrap(), serde_json::to_value(&cpu_long[0].config).unwrap());
    // The H100's lego run scaled down 16x: a sixteenth of the pixels and of the samples per
    // step, a quarter of the finest level, a sixteenth of the table; the H100 run's steps and
    // schedule.
    let mimic_spec = Ablation::load(&dir.join("h100_mimic_lego200.toml")).unwrap();
    assert!(mimic_spec.spec.checkpoints);
    let mimic = mimic_spec.plan(&nerf::registry()).unwrap();
    assert_eq!(mimic.len(), 6);
    for p in &mimic {
        let c = &p.config;
        assert_eq!((c.downscale, c.target_samples_per_step, c.iters), (4, Some((1 << 18) / 16), 43000));
        assert_eq!(c.lr, preset[0].config.lr);
        let grid = &c.field_config["grid"];
        assert_eq!(grid["max_resolution"].as_u64(), Some(2048 / 4));
        assert!(c.validate().is_ok());
    }
    let log2 = |i: usize| mimic[i].config.field_config["grid"]["log2_hashmap_size"].as_u64();
    assert_eq!((0..6).map(log2).collect::<Vec<_>>(), [15, 16, 15, 15, 15, 15].map(Some));
    assert_eq!(mimic.iter().map(|p| p.config.distortion_loss).collect::<Vec<_>>(), [None, None, Some(0.01), None, None, None]);
    // The generalisation runs: one setting each away from t15, and every run keeps its checkpoint
    // (for `nerf eval --split train`).
    assert_eq!(mimic[3].config.field_config["sh_degree"], 2);
    assert!(mimic[4].config.pixel_jitter && !mimic[0].config.pixel_jitter);
    assert_eq!((mimic[5].config.ema_decay, mimic[0].config.ema_decay), (Some(0.99), Some(0.95)));
    for i in 3..6 {
        let (mut c, t15) = (mimic[i].config.clone(), &mimic[0].config);
        (c.pixel_jitter, c.ema_decay, c.field_config) = (t15.pixel_jitter, t15.ema_decay, t15.field_config.clone());
        assert_eq!(serde_json::to_value(&c).unwrap(), serde_json::to_value(t15).unwrap(), "run {i}");
    }
    // tiny-cuda-nn's half precision in the table, in the same scaled-down run: t15 as above, and
    // t15 with the f16 mirror and f16 gradient sums, nothing else changed.
    let half = Ablation::load(&dir.join("f16_grad_mimic_lego200.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(half.len(), 4);
    assert_eq!(half.iter().map(|p| p.config.seed).collect::<Vec<_>>(), [0, 1, 0, 1]);
    let t15_s0 = serde_json::to_value(&mimic[0].config).unwrap();
    assert_eq!(serde_json::to_value(&half[0].config).unwrap(), t15_s0);
    let mut c = half[2].config.clone();
    let grid = c.field_config["grid"].as_object_mut().unwrap();
    assert_eq!((grid.remove("storage").unwrap(), grid.remove("grad_f16_scale").unwrap()), (serde_json::json!("f16"), serde_json::json!(16.0)));
    assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0);
    // nerfacc's recipe in the same scaled-down run: t15 but for nerfacc's settings (its finest
    // level scaled as the mimic scales the preset's), and t15 with its Adam alone.
    let nac = Ablation::load(&dir.join("nerfacc_mimic_lego200.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(nac.len(), 2);
    let mut c = nac[0].config.clone();
    assert_eq!((c.adam.beta2, c.train_background), (0.999, nerf::data::Background::White));
    assert_eq!((c.field_config["grid"]["max_resolution"].as_u64(), c.field_config["density_bias"].as_f64()), (Some(1024), Some(-1.0)));
    assert_eq!(c.field_config["grid"]["align"], "staggered");
    (c.adam, c.train_background, c.field_config) = (mimic[0].config.adam.clone(), mimic[0].config.train_background, mimic[0].config.field_config.clone());
    assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0);
    let mut c = nac[1].config.clone();
    assert_eq!(c.adam.beta2, 0.999);
    c.adam.beta2 = mimic[0].config.adam.beta2;
    assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0);
    // tiny-cuda-nn's precision in the MLPs and the table together: t15 but for the three keys.
    let all16 = Ablation::load(&dir.join("f16_mlp_mimic_lego200.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(all16.len(), 1);
    let mut c = all16[0].config.clone();
    assert_eq!(c.field_config.as_object_mut().unwrap().remove("mlp_f16_scale"), Some(serde_json::json!(2048.0)));
    let grid = c.field_config["grid"].as_object_mut().unwrap();
    assert_eq!((grid.remove("storage").unwrap(), grid.remove("grad_f16_scale").unwrap()), (serde_json::json!("f16"), serde_json::json!(2048.0)));
    assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0);
    // Batches of 2^19 and 2^20 samples scaled down: t15 with 2x and 4x the samples per step, for
    // the steps each would fit into the H100's 5 minutes (and 2x at t15's total samples),
    // evaluated at the fifths.
    for (file, log2, iters) in [
        ("batch19_mimic_lego200.toml", 15, 24_000),
        ("batch19eq_mimic_lego200.toml", 15, 21_500),
        ("batch20_mimic_lego200.toml", 16, 12_000),
    ] {
        let b = Ablation::load(&dir.join(file)).unwrap();
        assert_eq!((b.spec.budget.iters, b.spec.eval.every_iters), (Some(iters), Some(iters / 5)), "{file}");
        let b = b.plan(&nerf::registry()).unwrap();
        assert_eq!(b.len(), 1);
        let mut c = b[0].config.clone();
        assert_eq!((c.target_samples_per_step, mimic[0].config.target_samples_per_step), (Some(1 << log2), Some(1 << 14)), "{file}");
        (c.target_samples_per_step, c.iters) = (mimic[0].config.target_samples_per_step, mimic[0].config.iters);
        assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0, "{file}");
    }
    // A coarser finest level in the same scaled-down run: t15 but for the finest level (256 and
    // 128 cells, as 1024 and 512 at 800x800), over two seeds.
    let maxres = Ablation::load(&dir.join("maxres_mimic_lego200.toml")).unwrap();
    assert!(maxres.spec.checkpoints);
    assert_eq!((maxres.spec.budget.iters, maxres.spec.eval.every_iters), (Some(43_000), Some(8_600)));
    let maxres = maxres.plan(&nerf::registry()).unwrap();
    assert_eq!(maxres.len(), 4);
    let mut finest: Vec<(u64, u64)> = maxres.iter().map(|p| (p.config.field_config["grid"]["max_resolution"].as_u64().unwrap(), p.config.seed)).collect();
    finest.sort();
    assert_eq!(finest, [(128, 0), (128, 1), (256, 0), (256, 1)]);
    for p in &maxres {
        let mut c = p.config.clone();
        c.seed = mimic[0].config.seed;
        c.field_config["grid"]["max_resolution"] = mimic[0].config.field_config["grid"]["max_resolution"].clone();
        assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0, "{}", p.name);
    }
    // Both of the scaled-down run's leads: t15's copy with the doubled batch (24 000 steps of
    // 2^15 samples) and the finest level at 256 cells, over two seeds.
    let both = Ablation::load(&dir.join("batch19_maxres_mimic_lego200.toml")).unwrap();
    assert!(both.spec.checkpoints);
    assert_eq!((both.spec.budget.iters, both.spec.eval.every_iters), (Some(24_000), Some(4_800)));
    let both = both.plan(&nerf::registry()).unwrap();
    assert_eq!(both.iter().map(|p| p.config.seed).collect::<Vec<_>>(), [0, 1]);
    for p in &both {
        let mut c = p.config.clone();
        assert_eq!((c.target_samples_per_step, c.field_config["grid"]["max_resolution"].as_u64()), (Some(1 << 15), Some(256)), "{}", p.name);
        (c.target_samples_per_step, c.iters, c.seed) = (mimic[0].config.target_samples_per_step, mimic[0].config.iters, mimic[0].config.seed);
        c.field_config["grid"]["max_resolution"] = mimic[0].config.field_config["grid"]["max_resolution"].clone();
        assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0, "{}", p.name);
    }
    // The pair's finest level bracketed by half-octaves: 362 and 181 cells (as 1448 and 724).
    let bracket = Ablation::load(&dir.join("batch19_maxres_bracket_mimic_lego200.toml")).unwrap();
    assert!(bracket.spec.checkpoints);
    assert_eq!((bracket.spec.budget.iters, bracket.spec.eval.every_iters), (Some(24_000), Some(4_800)));
    let bracket = bracket.plan(&nerf::registry()).unwrap();
    let finest: Vec<_> = bracket.iter().map(|p| p.config.field_config["grid"]["max_resolution"].as_u64()).collect();
    assert_eq!(finest, [Some(362), Some(181)]);
    for p in &bracket {
        let mut c = p.config.clone();
        c.field_config["grid"]["max_resolution"] = both[0].config.field_config["grid"]["max_resolution"].clone();
        assert_eq!(serde_json::to_value(&c).unwrap(), serde_json::to_value(&both[0].config).unwrap(), "{}", p.name);
    }
    // The pair with tiny-cuda-nn's sparse Adam on the table, over two seeds: only the Adam differs.
    let sparse = Ablation::load(&dir.join("batch19_maxres_sparse_mimic_lego200.toml")).unwrap();
    assert!(sparse.spec.checkpoints);
    assert_eq!((sparse.spec.budget.iters, sparse.spec.eval.every_iters), (Some(24_000), Some(4_800)));
    let sparse = sparse.plan(&nerf::registry()).unwrap();
    assert_eq!(sparse.iter().map(|p| p.config.seed).collect::<Vec<_>>(), [0, 1]);
    for (p, dense) in sparse.iter().zip(&both) {
        let mut c = p.config.clone();
        assert!(c.adam.is_sparse("field/hash_grid") && !c.adam.is_sparse("field/density_mlp"), "{}", p.name);
        c.adam.sparse_groups.clear();
        assert_eq!(serde_json::to_value(&c).unwrap(), serde_json::to_value(&dense.config).unwrap(), "{}", p.name);
    }
    // The doubled batch combined: t15_b19 with the distortion loss, and with the rate x sqrt(2).
    let combo = Ablation::load(&dir.join("batch19_combo_mimic_lego200.toml")).unwrap();
    assert_eq!((combo.spec.budget.iters, combo.spec.eval.every_iters), (Some(24_000), Some(4_800)));
    let combo = combo.plan(&nerf::registry()).unwrap();
    assert_eq!(combo.len(), 2);
    // Back to t15's batch and steps (the loop above does the same for the batch-only files).
    let unbatched = |c: &nerf::train::TrainConfig| {
        let mut c = c.clone();
        assert_eq!(c.target_samples_per_step, Some(1 << 15));
        (c.target_samples_per_step, c.iters) = (mimic[0].config.target_samples_per_step, mimic[0].config.iters);
        c
    };
    let mut c = unbatched(&combo[0].config);
    assert_eq!(c.distortion_loss, Some(0.01));
    c.distortion_loss = mimic[0].config.distortion_loss;
    assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0);
    let mut c = unbatched(&combo[1].config);
    assert_eq!(serde_json::to_value(&c.lr).unwrap()["lr0"].as_f64().map(|x| (x * 1e4).round()), Some(141.0));
    c.lr = mimic[0].config.lr.clone();
    assert_eq!(serde_json::to_value(&c).unwrap(), t15_s0);
    // The profile ablation (in-repo scene) and the sparse-Adam comparison.
    let prof = Ablation::load(&dir.join("h100_profile.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert!(prof.iter().all(|p| p.config.gpu_profile.is_some() && p.scene.join("transforms_train.json").exists()));
    assert!(prof.iter().any(|p| p.config.adam.is_sparse("field/hash_grid")));
    assert!(prof.iter().any(|p| p.config.compact_samples && p.config.validate().is_ok()));
    assert!(prof.iter().any(|p| p.config.field == "hash" && !p.config.compact_samples));
    // The one-lease device checks: both fields, each GEMM / fused-MLP path, pose refinement.
    let quick = Ablation::load(&dir.join("device_quick.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(quick.len(), 6);
    assert!(quick.iter().all(|p| p.config.gpu_profile.is_some() && p.config.validate().is_ok()));
    assert_eq!(quick.iter().filter(|p| p.config.camera_optimizer.is_some()).count(), 1);
    let check = Ablation::load(&dir.join("device_check.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(check.iter().map(|p| p.config.field.as_str()).collect::<Vec<_>>(), ["hash", "freq", "freq"]);
    assert_eq!(check[2].config.field_config["gpu_linear"], "coop_tiled_wide");
    // The paper's field with and without its hidden f32 tape (benches/device/hidden_tape_ab.sh).
    let tape = Ablation::load(&dir.join("device_hidden_tape.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(tape.len(), 2);
    assert!(tape.iter().all(|p| p.config.field == "freq" && p.config.gpu_profile.is_some()));
    assert_eq!(tape[0].config.field_config["gpu_hidden_tape"], true);
    let f: nerf::field_freq::FreqNerfConfig = serde_json::from_value(tape[0].config.field_config.clone()).unwrap();
    assert_eq!(f.gpu_hidden_tape, Some(true));
    // The second run is the default (dropped on cooperative matrices).
    assert!(tape[1].config.field_config.get("gpu_hidden_tape").is_none());
    assert_eq!(nerf::field_freq::FreqNerfConfig::default().gpu_hidden_tape, None);
    assert!(check.iter().all(|p| p.config.gpu_profile == quick[0].config.gpu_profile && p.config.iters == quick[0].config.iters));
    let variants = Ablation::load(&dir.join("device_variants.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(variants.len(), 7);
    assert_eq!(variants[5].config.field_config["grid"]["n_levels"], 8);
    assert_eq!(variants[6].config.field_config["grid"]["n_features_per_level"], 8);
    assert!(variants.iter().all(|p| p.config.field == "hash" && p.config.validate().is_ok()));
    assert!(variants.iter().any(|p| !p.config.compact_samples) && variants.iter().any(|p| p.config.adam.is_sparse("field/hash_grid")));
    let sparse = Ablation::load(&dir.join("sparse_adam.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(sparse.iter().filter(|p| p.config.adam.is_sparse("field/hash_grid")).count(), 2);
    assert_eq!(sparse.len(), 4);
    // The grid-schedule comparison: its three runs keep the hash preset and change only the
    // refresh (the scene is ../shared's lego, absent without ../shared; planning does not read it).
    let sched = Ablation::load(&dir.join("grid_schedule_lego400.toml")).unwrap().plan(&nerf::registry()).unwrap();
    let every: Vec<_> = sched
        .iter()
        .map(|p| match &p.config.sampler {
            nerf::train::SamplerConfig::Occupancy { grid, step_size, .. } => {
                assert!(p.config.compact_samples && *step_size == 0.005, "the preset is kept");
                (grid.update_every, grid.warmup_steps)
            }
            s => panic!("grid_schedule_lego400: sampler {s:?}"),
        })
        .collect();
    assert_eq!(every, [(16, 256), (32, 512), (64, 1024)]);
    let coop = Ablation::load(&dir.join("h100_coop.toml")).unwrap().plan(&nerf::registry()).unwrap();
    let paths: Vec<_> = coop.iter().map(|p| p.config.field_config["gpu_mlp"].as_str().unwrap().to_string()).collect();
    assert_eq!(paths, ["plain", "coop"]);
    // The jitter comparison at 400×400: the preset with and without jittered training rays.
    let jit = Ablation::load(&dir.join("jitter_lego400.toml")).unwrap().plan(&nerf::registry()).unwrap();
    let jitter: Vec<_> = jit.iter().map(|p| (p.config.pixel_jitter, p.config.compact_samples, p.config.iters)).collect();
    assert_eq!(jitter, [(false, true, 2000), (true, true, 2000)]);
    // The colour-correction comparisons: off and on per scene, the preset otherwise (fern with
    // llff_hash.toml's step).
    for (name, scenes, step) in [("color_correction_lego200.toml", 2, 0.005), ("color_correction_fern.toml", 1, 0.02)] {
        let plans = Ablation::load(&dir.join(name)).unwrap().plan(&nerf::registry()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(plans.len(), 2 * scenes, "{name}");
        assert_eq!(plans.iter().filter(|p| p.config.color_correction.is_some()).count(), scenes, "{name}");
        for p in &plans {
            assert!(matches!(p.config.sampler, nerf::train::SamplerConfig::Occupancy { step_size, .. } if step_size == step), "{name}");
            assert!(p.config.field == "hash" && p.config.iters == 2000 && p.config.validate().is_ok(), "{name}");
        }
    }
    // The pose-refinement comparison: off and on (nerfacto's defaults) on the moved and the
    // unchanged scene.
    let pose = Ablation::load(&dir.join("camera_optimizer_lego200.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(pose.len(), 4);
    let on: Vec<_> = pose.iter().filter_map(|p| p.config.camera_optimizer.clone()).collect();
    assert_eq!(on, vec![nerf::train::config::CameraOptimizerConfig::default(); 2]);
    assert!(pose.iter().all(|p| p.config.field == "hash" && p.config.iters == 2000 && p.config.validate().is_ok()));
    // On fern: Euclidean rays (NDC is refused), llff_hash.toml's step.
    let fern = Ablation::load(&dir.join("camera_optimizer_fern.toml")).unwrap().plan(&nerf::registry()).unwrap();
    assert_eq!(fern.iter().map(|p| p.config.camera_optimizer.is_some()).collect::<Vec<_>>(), [false, true]);
    for p in &fern {
        assert!(!p.config.ndc && p.config.validate().is_ok());
        assert!(matches!(p.config.sampler, nerf::train::SamplerConfig::Occupancy { step_size, .. } if step_size == 0.02));
    }
}

/// A run whose loss turns NaN (a learning rate of 1e30) is reported as diverged and left out;
/// the ablation goes on with the others and writes its outputs, also when every run diverged.
#[test]
fn a_diverging_run_is_left_out_and_the_ablation_goes_on() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_scene(tmp.path());
    let registry = nerf::registry();
    let head = r#"
scenes = ["lego_tiny"]
test_views = "all"
[budget]
iters = 6
[eval]
every_iters = 3
[base]
field = "hash"
target_samples_per_step = 2048
field_config = { grid = { log2_hashmap_size = 12, n_levels = 4 } }
"#;
    let diverging = "[[runs]]\nname = \"huge_lr\"\nconfig = { lr = { kind = \"constant\", lr = 1e30 } }\n";
    let fine = "[[runs]]\nname = \"fine\"\nconfig = {}\n";
    for (name, runs, n_fine) in [("mixed", format!("{diverging}{fine}"), 1), ("all_diverge", diverging.to_string(), 0)] {
        let file = tmp.path().join(format!("{name}.toml"));
        std::fs::write(&file, format!("name = \"{name}\"\n{head}{runs}")).unwrap();
        let out = tmp.path().join(name);
        let opts = AblateOptions { out_dir: out.clone(), verbose: false, device: nerf::gpu::DevicePreference::Cpu };
        let report = run_ablation(&Ablation::load(&file).unwrap(), &registry, &opts).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(report.runs.len(), n_fine, "{name}");
        assert!(report.runs.iter().all(|r| r.metrics.test_psnr.is_finite() && r.metrics.iterations == 6), "{name}");
        assert_eq!(report.diverged.len(), 1, "{name}");
        let (id, step) = &report.diverged[0];
        assert!(id.contains("huge_lr") && (1..=6).contains(step), "{name}: {id} {step}");
        let md = read(&report.results_md);
        assert!(md.contains("Diverged") && md.contains(id.as_str()), "{name}: {md}");
        assert!(!out.join("runs").join(id).join("metrics.json").exists(), "{name}: a diverged run must not look finished");
        assert!(report.psnr_vs_time.exists() && report.psnr_vs_iter.exists(), "{name}");
    }
    // On the GPU the loss is read back every `log_every` steps (here only at the last step): an
    // evaluation point in between renders NaN parameters and reports the divergence there.
    if nerf::gpu::GpuContext::for_tests().is_none() {
        return;
    }
    let file = tmp.path().join("gpu.toml");
    let text = format!("name = \"gpu\"\n{head}log_every = 1000\n{diverging}").replace("every_iters = 3", "every_iters = 2");
    std::fs::write(&file, text).unwrap();
    let opts = AblateOptions { out_dir: tmp.path().join("gpu"), verbose: false, device: nerf::gpu::DevicePreference::Gpu };
    let report = run_ablation(&Ablation::load(&file).unwrap(), &registry, &opts).unwrap();
    assert_eq!(report.diverged.len(), 1);
    let step = report.diverged[0].1;
    assert!(step == 2 || step == 4, "caught at step {step}, not by an evaluation point");
}

/// A GPU run whose step does not fit the adapter's storage bindings trains with fewer samples per
/// step; the run's metrics and results.md say so (its config and hash stay as configured, so a
/// re-run still finds it finished).
#[test]
fn a_run_fitted_to_the_adapter_says_so_in_the_results() {
    let Some(ctx) = nerf::gpu::GpuContext::for_tests() else { return };
    let tmp = tempfile::tempdir().unwrap();
    tiny_scene(tmp.path());
    // ≥ 64 floats per sample in the colour network's tape, for 2 · target samples: ≥ 2 × the limit.
    let target = ctx.max_storage_bytes() / (8 * 32);
    drop(ctx);
    let text = format!(
        r#"name = "fit"
scenes = ["lego_tiny"]
test_views = "all"
[budget]
iters = 1
[base]
field = "hash"
field_config = {{ grid = {{ log2_hashmap_size = 12, n_levels = 4 }} }}
[[runs]]
name = "big"
config = {{ target_samples_per_step = {target} }}
"#
    );
    let file = tmp.path().join("fit.toml");
    std::fs::write(&file, text).unwrap();
    let registry = nerf::registry();
    let opts = AblateOptions { out_dir: tmp.path().join("fit"), verbose: false, device: nerf::gpu::DevicePreference::Gpu };
    let ablation = Ablation::load(&file).unwrap();
    let report = run_ablation(&ablation, &registry, &opts).unwrap();
    let m = &report.runs[0].metrics;
    assert_eq!(m.config.target_samples_per_step, Some(target as usize));
    let note = m.device_note.as_deref().expect("the fit is recorded");
    assert!(note.contains(&format!("instead of {target}")), "{note}");
    let md = read(&report.results_md);
    assert!(md.contains("Fitted to the adapter") && md.contains(note), "{md}");
    let again = run_ablation(&ablation, &registry, &opts).unwrap();
    assert!(again.runs[0].skipped && again.runs[0].metrics.device_note.as_deref() == Some(note));
}

#[test]
fn an_llff_ablation_sweeps_the_ray_space() {
    let Some(fern) = nerf::core::shared::data(env!("CARGO_MANIFEST_DIR"), "nerf_llff_data/fern") else {
        eprintln!("NOTICE: ../shared/data/nerf_llff_data/fern is absent; not checked");
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("fern.toml");
    // images_8 box-averaged by 6 (84×63), one held-out view, three small hash steps per space.
    let text = format!(
        r#"
scenes = [{:?}]
downscale = 48
test_views = "first:1"
[budget]
iters = 3
[[runs]]
name = "hash"
config = {{ field = "hash", target_samples_per_step = 4096, field_config = {{ grid = {{ log2_hashmap_size = 12, n_levels = 4 }} }} }}
[grid]
ndc = [true, false]
"#,
        fern.to_string_lossy()
    );
    std::fs::write(&file, text).unwrap();
    let opts = AblateOptions { out_dir: tmp.path().join("out"), verbose: false, device: nerf::gpu::DevicePreference::Cpu };
    let report = run_ablation(&Ablation::load(&file).unwrap(), &nerf::registry(), &opts).unwrap();
    let ids: Vec<&str> = report.runs.iter().map(|r| r.plan.id.as_str()).collect();
    assert_eq!(ids, ["hash__ndc=true__fern__s0", "hash__ndc=false__fern__s0"]);
    let psnr: Vec<f64> = report.runs.iter().map(|r| r.metrics.test_psnr).collect();
    assert!(psnr.iter().all(|p| p.is_finite() && *p > 5.0), "{psnr:?}");
    // Different ray spaces give the field different inputs: different results.
    assert_ne!(psnr[0], psnr[1]);
    let md = read(&tmp.path().join("out/results.md"));
    assert!(md.contains("| `ndc` |") && md.contains("| hash | fern | 0 | false |"), "{md}");
}

/// `checkpoints = true` keeps each run's trained fields; `nerf eval`'s path (load, a trainer for
/// rendering, restore, evaluate) scores them as the run's last evaluation did, and a finished run
/// whose checkpoint is missing trains again.
#[test]
fn a_kept_checkpoint_scores_as_the_run_did() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tiny_scene(tmp.path());
    // The test view with a mask that keeps its left 12 columns: the run keeps its masked scores.
    let test = load_blender(&scene, Split::Test, &LoadOptions::default()).unwrap();
    let (w, h) = (test.width, test.height);
    let keep: Vec<bool> = (0..w * h).map(|p| p % w < 12).collect();
    write_blender(&nerf::data::Dataset { masks: Some(nerf::data::PixelMasks::from_flags(w * h, [&keep[..]])), ..test }, &scene, None).unwrap();
    let registry = nerf::registry();
    let file = tmp.path().join("ck.toml");
    std::fs::write(
        &file,
        r#"
name = "ck"
scenes = ["lego_tiny"]
test_views = "all"
checkpoints = true
[budget]
iters = 5
[base]
field = "hash"
target_samples_per_step = 2048
field_config = { grid = { log2_hashmap_size = 12, n_levels = 4 } }
[[runs]]
name = "hash"
"#,
    )
    .unwrap();
    let opts = AblateOptions { out_dir: tmp.path().join("out"), verbose: false, device: nerf::gpu::DevicePreference::Cpu };
    let ab = Ablation::load(&file).unwrap();
    let report = run_ablation(&ab, &registry, &opts).unwrap();
    let run = &report.runs[0];
    let ck_path = opts.out_dir.join("runs").join(&run.plan.id).join("checkpoint.bin");
    let ck = nerf::train::Checkpoint::load(&ck_path).unwrap();
    assert_eq!(ck.step, 5);
    assert_eq!(ck.config, run.plan.config);

    let test = load_blender(&scene, Split::Test, &LoadOptions { downscale: ck.config.downscale, views: ck.config.test_views.clone(), ..Default::default() }).unwrap();
    let bounds = nerf::train::SceneBounds::of(&test);
    let mut t = nerf::train::make_trainer(&ck.config.for_rendering(), &registry, bounds, nerf::gpu::DevicePreference::Cpu).unwrap();
    t.restore(ck.step, &ck.fields, ck.adam, &ck.sampler).unwrap();
    let r = nerf::train::evaluate(&t, &test, None, |_, _| {}).unwrap();
    assert!((r.psnr - run.metrics.test_psnr).abs() < 1e-9, "{} against {}", r.psnr, run.metrics.test_psnr);
    // The run's metrics keep the last evaluation's per-view scores and error split.
    assert_eq!(run.metrics.per_view.len(), test.n_views());
    assert!((run.metrics.per_view[0].psnr - r.views[0].psnr).abs() < 1e-9);
    assert_eq!(run.metrics.alpha_split.is_some(), r.alpha_split.is_some());
    let (m, rm) = (run.metrics.test_masked.expect("the masked scores"), r.masked.expect("the masked scores"));
    assert!((m.psnr - rm.psnr).abs() < 1e-9 && (m.ssim - rm.ssim).abs() < 1e-9 && m.kept_fraction == 12.0 / w as f64, "{m:?} against {rm:?}");

    // Re-running skips the finished run; without its checkpoint it trains again.
    assert!(run_ablation(&ab, &registry, &opts).unwrap().runs[0].skipped);
    std::fs::remove_file(&ck_path).unwrap();
    assert!(!run_ablation(&ab, &registry, &opts).unwrap().runs[0].skipped);
    assert!(ck_path.is_file());
}

/// Runs whose configs load the scene differently (here instant-ngp's `aabb_scale`, which places
/// the scene in another box) each get their own load: the two runs train in different boxes
/// and score differently, where a load shared by both would have given the same run twice.
#[test]
fn runs_that_load_the_scene_differently_get_their_own_load() {
    let tmp = tempfile::tempdir().unwrap();
    tiny_scene(tmp.path());
    let file = tmp.path().join("box.toml");
    let text = r#"
scenes = ["lego_tiny"]
test_views = "all"
[budget]
iters = 3
[[runs]]
name = "box1"
config = { field = "freq", aabb_scale = 1.0, batch_rays = 64, field_config = { width = 16, depth = 2, skips = [], view_width = 8 }, sampler = { kind = "hierarchical", n_coarse = 8, n_fine = 8 } }
[[runs]]
name = "box4"
config = { field = "freq", aabb_scale = 4.0, batch_rays = 64, field_config = { width = 16, depth = 2, skips = [], view_width = 8 }, sampler = { kind = "hierarchical", n_coarse = 8, n_fine = 8 } }
"#;
    std::fs::write(&file, text).unwrap();
    let opts = AblateOptions { out_dir: tmp.path().join("out"), verbose: false, device: nerf::gpu::DevicePreference::Cpu };
    let report = run_ablation(&Ablation::load(&file).unwrap(), &nerf::registry(), &opts).unwrap();
    let psnr: Vec<f64> = report.runs.iter().map(|r| r.metrics.test_psnr).collect();
    assert_eq!(psnr.len(), 2);
    assert!(psnr.iter().all(|p| p.is_finite()), "{psnr:?}");
    assert_ne!(psnr[0], psnr[1], "each box its own load");
}
