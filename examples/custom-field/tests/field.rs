//! The conformance checks of docs/adding-a-field.md for the out-of-tree field: its backward
//! against f64 finite differences, inference against the training forward, its parameter groups
//! and its config errors.

use nerf::field::{FieldContext, RadianceField};
use nerf_plenoxels::{Plenoxels, PlenoxelsConfig};
use rand::Rng as _;

fn small(sh_degree: u32) -> PlenoxelsConfig {
    PlenoxelsConfig { resolution: 4, sh_degree, alpha_init: 0.3, grid_lr_scale: 3.0 }
}

/// `n` positions in the box `[-1, 1] × [-1, 1] × [-2, 2]` whose cell coordinates stay ≥ 0.05 from
/// every face of a `res`-cell grid (a finite-difference step never crosses a kink), and unit
/// directions.
fn samples(n: usize, res: usize, rng: &mut nerf::core::Rng) -> (Vec<f64>, Vec<f64>) {
    let mut pos = Vec::new();
    while pos.len() < 3 * n {
        let u: [f64; 3] = [rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0)];
        if u.iter().all(|&x| (0.05..0.95).contains(&(x * res as f64).fract())) {
            pos.extend_from_slice(&[2.0 * u[0] - 1.0, 2.0 * u[1] - 1.0, 4.0 * u[2] - 2.0]);
        }
    }
    let mut dirs: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    for d in dirs.chunks_mut(3) {
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.iter_mut().for_each(|x| *x /= l);
    }
    (pos, dirs)
}

fn ctx() -> FieldContext {
    FieldContext { aabb_min: [-1.0, -1.0, -2.0], aabb_max: [1.0, 1.0, 2.0], seed: 5, scene_scale: 1.0 }
}

#[test]
fn backward_matches_finite_differences_f64() {
    for degree in [1, 3] {
        let mut f = Plenoxels::<f64>::new(small(degree), &ctx()).unwrap();
        let mut rng = nerf::core::rng(9, degree as u64);
        // Values away from the near-empty start, so both activations are far from flat.
        for g in f.grids_mut() {
            g.params_mut().iter_mut().for_each(|p| *p = rng.gen_range(-0.5..0.5));
        }
        let n = 9;
        let (pos, dirs) = samples(n, 4, &mut rng);
        let a: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let b: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let loss = |f: &Plenoxels<f64>| {
            let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
            f.query_t(&pos, &dirs, &mut s, &mut c);
            s.iter().zip(&a).map(|(x, y)| x * y).sum::<f64>() + c.iter().zip(&b).map(|(x, y)| x * y).sum::<f64>()
        };
        let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
        f.forward_t(&pos, &dirs, &mut s, &mut c);
        f.backward_t(&a, &b);
        let grads: Vec<Vec<f64>> = f.grid_grads().iter().map(|g| g.to_vec()).collect();
        let mut checked = [0usize; 2];
        for (gi, grad) in grads.iter().enumerate() {
            for i in 0..grad.len() {
                let h = 1e-6;
                let v = f.grids_mut()[gi].params()[i];
                f.grids_mut()[gi].params_mut()[i] = v + h;
                let lp = loss(&f);
                f.grids_mut()[gi].params_mut()[i] = v - h;
                let lm = loss(&f);
                f.grids_mut()[gi].params_mut()[i] = v;
                let fd = (lp - lm) / (2.0 * h);
                let g = grad[i];
                assert!((fd - g).abs() <= 1e-7 + 1e-5 * fd.abs().max(g.abs()), "degree {degree}, grid {gi}, param {i}: fd {fd} vs {g}");
                checked[gi] += (g != 0.0) as usize;
            }
        }
        // The samples reach parameters of both grids (a backward that wrote nothing would pass above).
        assert!(checked.iter().all(|&c| c > 10), "degree {degree}: nonzero gradients {checked:?}");
    }
}

#[test]
fn inference_equals_the_training_forward_and_density_equals_its_sigma() {
    let mut f = Plenoxels::<f32>::new(PlenoxelsConfig { resolution: 16, ..small(3) }, &ctx()).unwrap();
    let mut rng = nerf::core::rng(3, 0);
    for g in f.grids_mut() {
        g.params_mut().iter_mut().for_each(|p| *p = rng.gen_range(-0.3..0.3));
    }
    let n = 500;
    // Positions past the box too: they are clamped to its faces.
    let pos: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-2.5..2.5)).collect();
    let (_, dirs) = samples(n, 16, &mut rng);
    let dirs: Vec<f32> = dirs.iter().map(|&d| d as f32).collect();
    let (mut s1, mut c1) = (vec![0.0; n], vec![0.0; 3 * n]);
    let (mut s2, mut c2) = (vec![-1.0; n], vec![-1.0; 3 * n]);
    let mut s3 = vec![-1.0; n];
    f.forward(&pos, &dirs, &mut s1, &mut c1);
    f.query(&pos, &dirs, &mut s2, &mut c2);
    f.density(&pos, &mut s3);
    assert_eq!(s1, s2);
    assert_eq!(c1, c2);
    assert_eq!(s1, s3);
    // Queries reuse their scratch tapes: a smaller batch after a larger one reads no stale rows.
    let m = 37;
    let (mut s4, mut c4) = (vec![-1.0; m], vec![-1.0; 3 * m]);
    f.query(&pos[3 * (n - m)..], &dirs[3 * (n - m)..], &mut s4, &mut c4);
    assert_eq!(s4, s1[n - m..]);
    assert_eq!(c4, c1[3 * (n - m)..]);
    assert!(s1.iter().all(|&s| s.is_finite() && s >= 0.0));
    assert!(c1.iter().all(|&c| (0.0..=1.0).contains(&c)));
}

#[test]
fn groups_cover_the_parameters_and_round_trip() {
    let config = PlenoxelsConfig { resolution: 8, ..small(2) };
    let mut f = Plenoxels::<f32>::new(config.clone(), &ctx()).unwrap();
    let sizes: Vec<(String, usize)> = f.param_groups().iter().map(|g| (g.name.to_string(), g.params.len())).collect();
    assert_eq!(sizes, [("density_grid".to_string(), 9 * 9 * 9), ("sh_grid".to_string(), 9 * 9 * 9 * 3 * 4)]);
    assert_eq!(f.n_params(), sizes.iter().map(|s| s.1).sum::<usize>());
    let exported = f.export_params();
    let mut g = Plenoxels::<f32>::new(config, &FieldContext { seed: 6, ..ctx() }).unwrap();
    assert_ne!(g.export_params(), exported, "another seed starts elsewhere");
    g.import_params(&exported).unwrap();
    assert_eq!(g.export_params(), exported);
}

#[test]
fn bad_configs_name_the_key() {
    let registry = {
        let mut r = nerf::registry();
        r.register(nerf_plenoxels::registry_entry());
        r
    };
    for (patch, key) in [
        (serde_json::json!({ "sh_degree": 5 }), "sh_degree"),
        (serde_json::json!({ "alpha_init": 1.0 }), "alpha_init"),
        (serde_json::json!({ "grid_lr_scale": 0.0 }), "grid_lr_scale"),
        (serde_json::json!({ "resolution": 0 }), "resolution"),
        (serde_json::json!({ "resolutoin": 64 }), "resolutoin"),
    ] {
        let err = match registry.build("plenoxels", &patch, &ctx()) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("{patch} was accepted"),
        };
        assert!(err.contains(key), "{patch}: {err}");
    }
}
