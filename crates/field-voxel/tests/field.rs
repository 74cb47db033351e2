//! Conformance checks of the voxel-grid field (its dense grids, `nerf_encoding::DenseGrid`, are
//! tested in their crate): the whole field (f64 finite
//! differences over every parameter group, inference = training forward, groups, configs) and
//! training on the in-repo scene through the trainer and a registry holding only this field.

#![allow(clippy::needless_range_loop)] // index loops read best in finite-difference checks

use nerf_field::{FieldContext, RadianceField};
use nerf_field_voxel::{VoxelNerf, VoxelNerfConfig};
use rand::Rng as _;

fn unit_ctx(seed: u64) -> FieldContext {
    FieldContext { aabb_min: [0.0; 3], aabb_max: [1.0; 3], seed, scene_scale: 1.0 }
}

/// Points in `[0,1]³` whose fractional cell coordinates stay ≥ 0.05 from every face, so a
/// finite-difference step never crosses a cell boundary (where trilinear interpolation has a kink).
fn interior_points(n: usize, res: usize, rng: &mut nerf_core::Rng) -> Vec<f64> {
    let mut out = Vec::new();
    while out.len() < 3 * n {
        let p: [f64; 3] = [rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0)];
        if p.iter().all(|&x| (0.05..0.95).contains(&(x * res as f64).fract())) {
            out.extend_from_slice(&p);
        }
    }
    out
}

fn check(fd: f64, g: f64, what: &str) {
    assert!((fd - g).abs() <= 1e-7 + 1e-5 * fd.abs().max(g.abs()), "{what}: fd {fd} vs analytic {g}");
}

fn small() -> VoxelNerfConfig {
    VoxelNerfConfig {
        resolution: 4,
        features: 3,
        alpha_init: 0.3,
        dir_frequencies: 2,
        hidden: 8,
        hidden_layers: 2,
        mlp_weight_decay: 0.0,
        grid_lr_scale: 3.0,
    }
}

fn loss(f: &VoxelNerf<f64>, pos: &[f64], dirs: &[f64], a: &[f64], b: &[f64]) -> f64 {
    let n = pos.len() / 3;
    let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
    f.query_t(pos, dirs, &mut s, &mut c);
    s.iter().zip(a).map(|(x, y)| x * y).sum::<f64>() + c.iter().zip(b).map(|(x, y)| x * y).sum::<f64>()
}

#[test]
fn whole_field_backward_matches_finite_differences_f64() {
    let ctx = FieldContext { aabb_min: [-1.0, -1.0, -2.0], aabb_max: [1.0, 1.0, 2.0], seed: 5, scene_scale: 1.0 };
    let mut f = VoxelNerf::<f64>::new(small(), &ctx).unwrap();
    let mut rng = nerf_core::rng(9, 0);
    // Non-trivial density and features (the init is 0 and ±1e-4).
    for g in f.grids_mut() {
        g.params_mut().iter_mut().for_each(|p| *p = rng.gen_range(-0.5..0.5));
    }
    let n = 9;
    let unit = interior_points(n, 4, &mut rng);
    let pos: Vec<f64> = unit
        .chunks(3)
        .flat_map(|p| [p[0] * 2.0 - 1.0, p[1] * 2.0 - 1.0, p[2] * 4.0 - 2.0])
        .collect();
    let mut dirs: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    for d in dirs.chunks_mut(3) {
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.iter_mut().for_each(|x| *x /= l);
    }
    let a: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let b: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
    f.forward_t(&pos, &dirs, &mut s, &mut c);
    f.backward_t(&a, &b);
    let grads: Vec<Vec<f64>> = f.grid_grads().iter().map(|g| g.to_vec()).collect();
    let g_mlp = f.mlp().grads().to_vec();
    let h = 1e-6;
    for (gi, gg) in grads.iter().enumerate() {
        let mut touched = 0;
        for i in 0..gg.len() {
            let orig = f.grids()[gi].params()[i];
            f.grids_mut()[gi].params_mut()[i] = orig + h;
            let lp = loss(&f, &pos, &dirs, &a, &b);
            f.grids_mut()[gi].params_mut()[i] = orig - h;
            let lm = loss(&f, &pos, &dirs, &a, &b);
            f.grids_mut()[gi].params_mut()[i] = orig;
            check((lp - lm) / (2.0 * h), gg[i], &format!("grid {gi} param {i}"));
            touched += (gg[i] != 0.0) as usize;
        }
        assert!(touched > 20, "grid {gi}: only {touched} entries received gradient");
    }
    let mut nonzero = 0;
    for i in 0..g_mlp.len() {
        let orig = f.mlp().params()[i];
        f.mlp_mut().params_mut()[i] = orig + h;
        let lp = loss(&f, &pos, &dirs, &a, &b);
        f.mlp_mut().params_mut()[i] = orig - h;
        let lm = loss(&f, &pos, &dirs, &a, &b);
        f.mlp_mut().params_mut()[i] = orig;
        check((lp - lm) / (2.0 * h), g_mlp[i], &format!("mlp param {i}"));
        nonzero += (g_mlp[i] != 0.0) as usize;
    }
    assert!(nonzero > g_mlp.len() / 2, "only {nonzero} MLP params received gradient");
}

#[test]
fn initial_field_is_almost_empty_with_alpha_init_per_voxel() {
    // σ·voxel_size = −ln(1 − alpha_init) at d = 0 (DVGO's act_shift); the init is d ∈ ±1e-4,
    // read as s·d ∈ ±3e-3, which moves σ by < 0.5 %.
    let ctx = FieldContext { aabb_min: [-1.5; 3], aabb_max: [1.5; 3], seed: 0, scene_scale: 1.0 };
    let cfg = VoxelNerfConfig { resolution: 16, ..Default::default() };
    let f = VoxelNerf::<f64>::new(cfg.clone(), &ctx).unwrap();
    let mut s = [0.0; 2];
    f.density_t(&[0.1, -0.7, 1.2, 3.0, 3.0, 3.0], &mut s);
    let voxel = 3.0 / 16.0;
    let want = -(1.0 - cfg.alpha_init).ln() / voxel;
    for v in s {
        assert!((v - want).abs() < 5e-3 * want, "σ {v} vs {want}");
    }
}

#[test]
fn query_density_and_forward_agree_and_groups_have_the_right_decay() {
    let ctx = FieldContext { aabb_min: [-1.5; 3], aabb_max: [1.5; 3], seed: 2, scene_scale: 1.0 };
    let cfg = serde_json::json!({"resolution": 32, "hidden": 32, "mlp_weight_decay": 1e-6});
    let mut f: Box<dyn RadianceField> = nerf_field_voxel::build(&cfg, &ctx).unwrap();
    assert_eq!(f.kind(), "voxel");
    assert_eq!(f.config()["resolution"], 32);
    let mut rng = nerf_core::rng(3, 0);
    // Random density so σ varies.
    for g in f.param_groups().into_iter().take(2) {
        g.params.iter_mut().for_each(|p| *p = rng.gen_range(-2.0..2.0));
    }
    let n = nerf_field_voxel::QUERY_CHUNK + 7_000; // > one inference chunk
    let pos: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.6..1.6)).collect();
    let dirs: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let (mut s1, mut c1) = (vec![0.0; n], vec![0.0; 3 * n]);
    let (mut s2, mut c2) = (vec![f32::NAN; n], vec![f32::NAN; 3 * n]);
    let mut s3 = vec![f32::NAN; n];
    f.forward(&pos, &dirs, &mut s1, &mut c1);
    f.query(&pos, &dirs, &mut s2, &mut c2);
    f.density(&pos, &mut s3);
    let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + x.abs()));
    assert!(close(&s1, &s2) && close(&c1, &c2) && close(&s2, &s3));
    let spread = s1.iter().cloned().fold(0f32, f32::max) - s1.iter().cloned().fold(f32::MAX, f32::min);
    assert!(spread > 1.0, "σ barely varies ({spread})");
    // Backward accumulates into every group; zero_grad clears them.
    f.backward(&vec![1.0; n], &vec![0.5; 3 * n]);
    for g in f.param_groups() {
        assert!(g.grads.iter().any(|&v| v != 0.0), "group {} got no gradient", g.name);
    }
    f.zero_grad();
    let groups = f.param_groups();
    assert!(groups.iter().all(|g| g.grads.iter().all(|&v| v == 0.0)));
    let names: Vec<_> = groups.iter().map(|g| (g.name, g.weight_decay)).collect();
    assert_eq!(names, vec![("density_grid", 0.0), ("feature_grid", 0.0), ("color_mlp", 1e-6)]);
    let lens: Vec<usize> = groups.iter().map(|g| g.params.len()).collect();
    drop(groups);
    assert_eq!(lens[0], 33usize.pow(3));
    assert_eq!(lens[1], 12 * 33usize.pow(3));
    assert_eq!(lens.iter().sum::<usize>(), f.n_params());
    // Checkpoint round trip.
    let saved = f.export_params();
    let mut g = nerf_field_voxel::build(&cfg, &FieldContext { seed: 99, ..ctx }).unwrap();
    g.import_params(&saved).unwrap();
    let mut s4 = vec![0.0; n];
    g.density(&pos, &mut s4);
    assert_eq!(s3, s4);
}

#[test]
fn default_dimensions() {
    let f = VoxelNerf::<f32>::new(VoxelNerfConfig::default(), &unit_ctx(0)).unwrap();
    // 12 features + 27 direction values → 128 → 128 → 3.
    assert_eq!(f.mlp().layer_shapes(), vec![(39, 128), (128, 128), (128, 3)]);
    assert_eq!(f.grids()[0].n_vertices(), 129usize.pow(3));
    assert!(f.grids()[0].params().iter().all(|&v| v.abs() <= 1e-4));
    assert!(f.grids()[0].params().iter().any(|&v| v != 0.0), "density init must not be uniform");
    assert!(f.grids()[1].params().iter().all(|&v| v.abs() <= 1e-4));
    assert!(f.grids()[1].params().iter().any(|&v| v != 0.0));
}

#[test]
fn bad_configs_are_rejected_naming_the_key() {
    let ctx = unit_ctx(0);
    for (cfg, key) in [
        (serde_json::json!({"resolution": 0}), "resolution"),
        (serde_json::json!({"features": 0}), "features"),
        (serde_json::json!({"alpha_init": 1.0}), "alpha_init"),
        (serde_json::json!({"alpha_init": 0.0}), "alpha_init"),
        (serde_json::json!({"hidden": 0}), "hidden"),
        (serde_json::json!({"grid_lr_scale": -1.0}), "grid_lr_scale"),
        (serde_json::json!({"mlp_weight_decay": -1.0}), "mlp_weight_decay"),
        (serde_json::json!({"resolutoin": 8}), "resolutoin"),
        (serde_json::json!({"features": "many"}), "many"),
    ] {
        let e = nerf_field_voxel::build(&cfg, &ctx).err().unwrap_or_else(|| panic!("{cfg} accepted"));
        assert!(e.to_string().contains(key), "{cfg}: {e}");
    }
    let flat = FieldContext { aabb_min: [0.0; 3], aabb_max: [1.0, 0.0, 1.0], seed: 0, scene_scale: 1.0 };
    assert!(nerf_field_voxel::build(&serde_json::Value::Null, &flat).is_err());
}
