//! Whole-field checks of the hash-grid field: finite differences in f64 over every parameter
//! group, inference = training forward, config validation, parameter groups and decay.

use nerf_encoding::{HashGridConfig, Precision};
use nerf_field::{FieldContext, RadianceField};
use nerf_field_hash::{ColorInput, GpuMlp, HashNerf, HashNerfConfig, MlpInit};
use rand::Rng as _;

fn unit_ctx(seed: u64) -> FieldContext {
    FieldContext { aabb_min: [0.0; 3], aabb_max: [1.0; 3], seed, scene_scale: 1.0 }
}

fn small() -> HashNerfConfig {
    HashNerfConfig {
        grid: HashGridConfig {
            n_levels: 3,
            n_features_per_level: 2,
            log2_hashmap_size: 6, // 64 slots: levels with (res+1)^3 > 64 are hashed
            base_resolution: 2,
            max_resolution: 8,
            dense_levels: true,
            storage: Precision::F32,
            init_scale: 0.5,
            ..Default::default()
        },
        sh_degree: 3,
        geo_features: 3,
        density_hidden: 8,
        density_layers: 1,
        color_hidden: 8,
        color_layers: 2,
        mlp_bias: true,
        mlp_weight_decay: 1e-6,
        grid_weight_decay: 0.0,
        mlp_init: MlpInit::Torch,
        density_bias: 0.0,
        color_input: ColorInput::All,
        gpu_mlp: GpuMlp::Plain,
        gpu_keep_density_activations: true,
        gpu_density_in_place: true,
        gpu_hash_subgroup_sums: None,
        mlp_f16_scale: None,
    }
}

/// Points whose fractional cell coordinates stay ≥ 0.05 from every face at every level, so a
/// finite-difference step never crosses a cell boundary (where trilinear interpolation has a kink).
fn interior_points(n: usize, res: &[u32], rng: &mut nerf_core::Rng) -> Vec<f64> {
    let mut out = Vec::new();
    while out.len() < 3 * n {
        let p: [f64; 3] = [rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0)];
        let ok = res.iter().all(|&r| {
            p.iter().all(|&x| {
                let f = (x * r as f64).fract();
                (0.05..0.95).contains(&f)
            })
        });
        if ok {
            out.extend_from_slice(&p);
        }
    }
    out
}

fn loss(f: &HashNerf<f64>, pos: &[f64], dirs: &[f64], a: &[f64], b: &[f64]) -> f64 {
    let n = pos.len() / 3;
    let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
    f.query_t(pos, dirs, &mut s, &mut c);
    s.iter().zip(a).map(|(x, y)| x * y).sum::<f64>() + c.iter().zip(b).map(|(x, y)| x * y).sum::<f64>()
}

#[test]
fn whole_field_backward_matches_finite_differences_f64() {
    backward_matches_finite_differences(small());
}

/// The same with nerfacc's density bias (σ = exp(x − 1)).
#[test]
fn whole_field_backward_with_a_density_bias_matches_finite_differences_f64() {
    backward_matches_finite_differences(HashNerfConfig { density_bias: -1.0, ..small() });
}

/// The same with nerfacc's colour head (`color_input = "features"`: the colour net reads the
/// geometry features, not the density logit), with a density bias besides.
#[test]
fn whole_field_backward_with_the_features_colour_input_matches_finite_differences_f64() {
    backward_matches_finite_differences(HashNerfConfig { color_input: ColorInput::Features, ..small() });
    backward_matches_finite_differences(HashNerfConfig { color_input: ColorInput::Features, density_bias: -1.0, ..small() });
}

fn backward_matches_finite_differences(cfg: HashNerfConfig) {
    let mut f = HashNerf::<f64>::new(cfg, &unit_ctx(4)).unwrap();
    let mut rng = nerf_core::rng(9, 0);
    let n = 7;
    let res = f.grid().resolutions().to_vec();
    assert!((0..3).any(|l| !f.grid().is_dense(l)) && (0..3).any(|l| f.grid().is_dense(l)), "both kinds of level");
    let pos = interior_points(n, &res, &mut rng);
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
    let g_grid = f.grid_grad().to_vec();
    let g_mlp: Vec<Vec<f64>> = f.mlps().iter().map(|m| m.grads().to_vec()).collect();

    let h = 1e-6;
    let check = |fd: f64, g: f64, what: &str| {
        assert!((fd - g).abs() <= 1e-7 + 1e-5 * fd.abs().max(g.abs()), "{what}: fd {fd} vs analytic {g}");
    };
    let mut touched = 0;
    for i in 0..g_grid.len() {
        let orig = f.grid().params()[i];
        f.grid_mut().params_mut()[i] = orig + h;
        let lp = loss(&f, &pos, &dirs, &a, &b);
        f.grid_mut().params_mut()[i] = orig - h;
        let lm = loss(&f, &pos, &dirs, &a, &b);
        f.grid_mut().params_mut()[i] = orig;
        let fd = (lp - lm) / (2.0 * h);
        check(fd, g_grid[i], &format!("table entry {i}"));
        touched += (g_grid[i] != 0.0) as usize;
    }
    assert!(touched > 20, "only {touched} table entries received gradient");
    for m in 0..2 {
        for i in 0..g_mlp[m].len() {
            let orig = f.mlps()[m].params()[i];
            f.mlps_mut()[m].params_mut()[i] = orig + h;
            let lp = loss(&f, &pos, &dirs, &a, &b);
            f.mlps_mut()[m].params_mut()[i] = orig - h;
            let lm = loss(&f, &pos, &dirs, &a, &b);
            f.mlps_mut()[m].params_mut()[i] = orig;
            check((lp - lm) / (2.0 * h), g_mlp[m][i], &format!("mlp {m} param {i}"));
        }
    }
}

/// `backward_with_inputs`: the gradients in the samples' world positions (through the box's
/// normalisation, in a box that is not the unit cube) and directions (through the SH encoding)
/// against central differences in f64; the parameter gradients are those of `backward`; a point
/// outside the box gets none across the clamped axis.
#[test]
fn input_gradients_match_finite_differences_f64() {
    let ctx = FieldContext { aabb_min: [-1.0, -2.0, 0.5], aabb_max: [1.0, 2.0, 3.5], seed: 5, scene_scale: 1.0 };
    let mut f = HashNerf::<f64>::new(small(), &ctx).unwrap();
    let mut rng = nerf_core::rng(10, 0);
    let n = 6;
    let res = f.grid().resolutions().to_vec();
    let mut pos = interior_points(n, &res, &mut rng);
    for p in pos.chunks_mut(3) {
        for a in 0..3 {
            p[a] = ctx.aabb_min[a] as f64 + p[a] * (ctx.aabb_max[a] - ctx.aabb_min[a]) as f64;
        }
    }
    pos[0] = 1.5; // sample 0 lies beyond the box in x
    let mut dirs: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    for d in dirs.chunks_mut(3) {
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.iter_mut().for_each(|x| *x /= l);
    }
    let a: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let b: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
    let mut twin = HashNerf::<f64>::new(small(), &ctx).unwrap();
    twin.forward_t(&pos, &dirs, &mut s, &mut c);
    twin.backward_t(&a, &b);
    let plain: Vec<f64> = twin.grid_grad().iter().chain(twin.mlps().iter().flat_map(|m| m.grads().iter())).copied().collect();
    f.forward_t(&pos, &dirs, &mut s, &mut c);
    let (mut dp, mut dd) = (vec![f64::NAN; 3 * n], vec![f64::NAN; 3 * n]);
    f.backward_inputs_t(&a, &b, Some((&mut dp, &mut dd)));
    let with: Vec<f64> = f.grid_grad().iter().chain(f.mlps().iter().flat_map(|m| m.grads().iter())).copied().collect();
    assert_eq!(plain, with, "parameter gradients change when input gradients are asked for");
    assert_eq!(dp[0], 0.0, "clamped axis");
    let h = 1e-7;
    for (which, grad) in [("position", &dp), ("direction", &dd)] {
        for i in 0..3 * n {
            let (mut pp, mut pm, mut dp_, mut dm) = (pos.clone(), pos.clone(), dirs.clone(), dirs.clone());
            if which == "position" {
                pp[i] += h;
                pm[i] -= h;
            } else {
                dp_[i] += h;
                dm[i] -= h;
            }
            let fd = (loss(&f, &pp, &dp_, &a, &b) - loss(&f, &pm, &dm, &a, &b)) / (2.0 * h);
            let g = grad[i];
            assert!((fd - g).abs() <= 1e-6 + 1e-5 * fd.abs().max(g.abs()), "{which}[{i}]: fd {fd} vs analytic {g}");
        }
        assert!(grad.iter().filter(|g| g.abs() > 1e-3).count() > n, "{which} gradients are suspiciously small");
    }
}

#[test]
fn density_gradient_is_truncated_for_large_log_density() {
    // σ = exp(x); for x > 15 the backward uses exp(15) (instant-ngp's trunc_exp).
    let mut cfg = small();
    cfg.density_layers = 0;
    cfg.mlp_bias = true;
    let mut f = HashNerf::<f64>::new(cfg, &unit_ctx(1)).unwrap();
    {
        let [d, _] = f.mlps_mut();
        let p = d.params_mut();
        p.iter_mut().for_each(|x| *x = 0.0);
        let n_out = 4; // 1 + geo_features
        let bias0 = p.len() - n_out;
        p[bias0] = 20.0; // x = 20 for every sample
    }
    let pos = [0.3, 0.4, 0.6];
    let dirs = [0.0, 0.0, 1.0];
    let (mut s, mut c) = ([0.0], [0.0; 3]);
    f.forward_t(&pos, &dirs, &mut s, &mut c);
    assert!((s[0] - 20f64.exp()).abs() < 1e-6 * 20f64.exp());
    f.backward_t(&[1.0], &[0.0; 3]);
    let [d, _] = f.mlps();
    let g = d.grads();
    let bias_grad = g[g.len() - 4];
    assert!((bias_grad - 15f64.exp()).abs() < 1e-6 * 15f64.exp(), "truncated gradient {bias_grad}");
}

/// `density_bias = b` scales σ by e^b and leaves the colours alone (the colour net sees the
/// unbiased output), and the truncation of the gradient applies to `x + b`.
#[test]
fn density_bias_scales_sigma_and_moves_the_truncation() {
    let mut cfg = small();
    cfg.density_layers = 0;
    cfg.mlp_bias = true;
    let run = |bias: f64, x: f64| {
        let mut f = HashNerf::<f64>::new(HashNerfConfig { density_bias: bias as f32, ..cfg.clone() }, &unit_ctx(1)).unwrap();
        {
            let [d, _] = f.mlps_mut();
            let p = d.params_mut();
            p.iter_mut().for_each(|v| *v = 0.0);
            let bias0 = p.len() - 4; // 1 + geo_features outputs
            p[bias0] = x;
        }
        let (mut s, mut c) = ([0.0], [0.0; 3]);
        f.forward_t(&[0.3, 0.4, 0.6], &[0.0, 0.0, 1.0], &mut s, &mut c);
        f.backward_t(&[1.0], &[0.0; 3]);
        let [d, _] = f.mlps();
        let g = d.grads();
        (s[0], c, g[g.len() - 4])
    };
    let (s0, c0, g0) = run(0.0, 0.7);
    let (s1, c1, g1) = run(-1.0, 0.7);
    assert!((s1 - s0 * (-1f64).exp()).abs() < 1e-12 * s0, "{s1} vs {s0}");
    assert_eq!(c0, c1, "the colour net sees x, not x + b");
    assert!((g1 - g0 * (-1f64).exp()).abs() < 1e-12 * g0, "{g1} vs {g0}");
    // x = 15.5: truncated without a bias, not with b = −1 (x + b = 14.5).
    let (_, _, g) = run(0.0, 15.5);
    assert!((g - 15f64.exp()).abs() < 1e-9 * g);
    let (s, _, g) = run(-1.0, 15.5);
    assert!((s - 14.5f64.exp()).abs() < 1e-9 * s && (g - 14.5f64.exp()).abs() < 1e-9 * g, "{g}");
}

/// `color_input = "features"`: the colour net has `geo_features + SH` inputs, the density logit
/// moves σ and not the colour, and the colour's gradient does not reach the logit. With `all`
/// (instant-ngp's) the logit moves the colour and receives its gradient.
#[test]
fn the_features_colour_input_keeps_the_logit_out_of_the_colour() {
    let mut cfg = small();
    cfg.density_layers = 0;
    let run = |color_input: ColorInput, x: f64| {
        let mut f = HashNerf::<f64>::new(HashNerfConfig { color_input, ..cfg.clone() }, &unit_ctx(1)).unwrap();
        {
            let [d, _] = f.mlps_mut();
            let p = d.params_mut();
            let bias0 = p.len() - 4; // 1 + geo_features outputs
            p[bias0] = x;
        }
        let (mut s, mut c) = ([0.0], [0.0; 3]);
        f.forward_t(&[0.3, 0.4, 0.6], &[0.0, 0.0, 1.0], &mut s, &mut c);
        // A loss on the colour alone.
        f.backward_t(&[0.0], &[1.0, -0.5, 0.25]);
        let [d, c_net] = f.mlps();
        let g = d.grads();
        (s[0], c, g[g.len() - 4], c_net.config.input_dim)
    };
    let sh = 9; // degree 3
    let (s0, c0, g0, w) = run(ColorInput::Features, 0.2);
    let (s1, c1, _, _) = run(ColorInput::Features, 1.3);
    assert_eq!(w, 3 + sh, "the features and the SH encoding");
    assert!((s1 / s0 - 1.1f64.exp()).abs() < 1e-9, "σ follows the logit: {s0} → {s1}");
    assert_eq!(c0, c1, "the colour does not");
    assert_eq!(g0, 0.0, "no colour gradient reaches the logit");
    let (_, a0, ga, wa) = run(ColorInput::All, 0.2);
    let (_, a1, _, _) = run(ColorInput::All, 1.3);
    assert_eq!(wa, 1 + 3 + sh);
    assert_ne!(a0, a1, "instant-ngp's colour net reads the logit");
    assert!(ga != 0.0, "and passes it the colour's gradient");
    let j: HashNerfConfig = serde_json::from_value(serde_json::json!({"color_input": "features"})).unwrap();
    assert_eq!(j.color_input, ColorInput::Features);
    assert_eq!(HashNerfConfig::default().color_input, ColorInput::All);
}

#[test]
fn query_density_and_forward_agree_and_groups_have_the_right_decay() {
    let ctx = FieldContext { aabb_min: [-1.5; 3], aabb_max: [1.5; 3], seed: 2, scene_scale: 1.0 };
    let mut f: Box<dyn RadianceField> = nerf_field_hash::build(&serde_json::json!({"grid": {"log2_hashmap_size": 14}}), &ctx).unwrap();
    let mut rng = nerf_core::rng(3, 0);
    let n = 40_000; // > one inference chunk
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
    let groups = f.param_groups();
    let names: Vec<_> = groups.iter().map(|g| (g.name, g.weight_decay)).collect();
    assert_eq!(names, vec![("hash_grid", 0.0), ("density_mlp", 1e-6), ("color_mlp", 1e-6)]);
    let total: usize = groups.iter().map(|g| g.params.len()).sum();
    drop(groups);
    assert_eq!(total, f.n_params());
    // With `grid_weight_decay` the table's group carries its own decay.
    let cfg = serde_json::json!({"grid": {"log2_hashmap_size": 14}, "grid_weight_decay": 2e-6, "mlp_weight_decay": 3e-6});
    let mut f = nerf_field_hash::build(&cfg, &ctx).unwrap();
    let names: Vec<_> = f.param_groups().iter().map(|g| (g.name, g.weight_decay)).collect();
    assert_eq!(names, vec![("hash_grid", 2e-6), ("density_mlp", 3e-6), ("color_mlp", 3e-6)]);
}

#[test]
fn queries_reusing_their_buffers_equal_those_of_a_fresh_field() {
    use rayon::prelude::*;
    // `query` and `density` keep their inference buffers in a pool between calls (rendering's
    // rounds call them with ever-changing sizes, from several threads at once). Each answer must
    // be the bits a field with an empty pool gives for the same input.
    let ctx = FieldContext { aabb_min: [-1.5; 3], aabb_max: [1.5; 3], seed: 4, scene_scale: 1.0 };
    let cfg = serde_json::json!({"grid": {"log2_hashmap_size": 14}});
    let mut rng = nerf_core::rng(11, 0);
    let n = 40_000; // > one inference chunk
    let pos: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.6..1.6)).collect();
    let dirs: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let fresh = |a: usize, b: usize| {
        let f = nerf_field_hash::build(&cfg, &ctx).unwrap();
        let (mut s, mut c, mut d) = (vec![f32::NAN; b - a], vec![f32::NAN; 3 * (b - a)], vec![f32::NAN; b - a]);
        f.query(&pos[3 * a..3 * b], &dirs[3 * a..3 * b], &mut s, &mut c);
        f.density(&pos[3 * a..3 * b], &mut d);
        (s, c, d)
    };
    let f = nerf_field_hash::build(&cfg, &ctx).unwrap();
    let ask = |a: usize, b: usize| {
        let (mut s, mut c, mut d) = (vec![f32::NAN; b - a], vec![f32::NAN; 3 * (b - a)], vec![f32::NAN; b - a]);
        f.query(&pos[3 * a..3 * b], &dirs[3 * a..3 * b], &mut s, &mut c);
        f.density(&pos[3 * a..3 * b], &mut d);
        (s, c, d)
    };
    // Large, small, large again, and a range whose buffers were last filled by other samples.
    for (a, b) in [(0, n), (0, 100), (5, 5_005), (0, n), (7_000, 7_300), (n - 1, n)] {
        assert!(ask(a, b) == fresh(a, b), "samples {a}..{b}");
    }
    // Several threads at once, each chunk its own size.
    let bounds: Vec<(usize, usize)> = (0..24).map(|i| (i * 1_500, i * 1_500 + 97 * (i + 1))).collect();
    let pooled: Vec<_> = bounds.par_iter().map(|&(a, b)| ask(a, b)).collect();
    for (&(a, b), got) in bounds.iter().zip(&pooled) {
        assert!(*got == fresh(a, b), "concurrent samples {a}..{b}");
    }
}

/// σ, rgb and gradients of a field's training forward and backward on `pos`/`dirs`, run either
/// directly or as rows of an earlier density pass over `all` (`rows` index `all`).
fn train_pass(f: &mut dyn RadianceField, rows: Option<(&[u32], &[f32])>, pos: &[f32], dirs: &[f32], d: &[f32]) -> Vec<Vec<f32>> {
    let n = pos.len() / 3;
    let (mut s, mut c) = (vec![f32::NAN; n], vec![f32::NAN; 3 * n]);
    f.zero_grad();
    match rows {
        Some((rows, all)) => {
            let mut s_all = vec![f32::NAN; all.len() / 3];
            f.density_for_training(all, &mut s_all);
            let mut s_ref = vec![f32::NAN; all.len() / 3];
            f.density(all, &mut s_ref);
            assert_eq!(s_all, s_ref, "the density pass's σ is density()'s");
            f.forward_rows(rows, pos, dirs, &mut s, &mut c);
        }
        None => f.forward(pos, dirs, &mut s, &mut c),
    }
    f.backward(&d[..n], &d[n..4 * n]);
    let mut out = vec![s, c];
    out.extend(f.param_groups().into_iter().map(|g| g.grads.to_vec()));
    out
}

#[test]
fn forward_on_rows_of_the_density_pass_equals_a_fresh_forward() {
    let ctx = FieldContext { aabb_min: [-1.5; 3], aabb_max: [1.5; 3], seed: 4, scene_scale: 1.0 };
    let mut f = nerf_field_hash::build(&serde_json::json!({"grid": {"log2_hashmap_size": 14}}), &ctx).unwrap();
    let mut rng = nerf_core::rng(5, 0);
    let n_all = 40_000; // > one inference chunk
    let all: Vec<f32> = (0..3 * n_all).map(|_| rng.gen_range(-1.6..1.6)).collect();
    let rows: Vec<u32> = (0..n_all as u32).filter(|_| rng.gen_bool(0.6)).collect();
    let gather = |v: &[f32]| rows.iter().flat_map(|&r| v[3 * r as usize..3 * r as usize + 3].to_vec()).collect::<Vec<_>>();
    let pos = gather(&all);
    let dirs: Vec<f32> = (0..pos.len()).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let d: Vec<f32> = (0..4 * rows.len()).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let fresh = train_pass(f.as_mut(), None, &pos, &dirs, &d);
    let reused = train_pass(f.as_mut(), Some((&rows, &all)), &pos, &dirs, &d);
    assert!(fresh[2].iter().any(|&g| g != 0.0), "the table gets gradients");
    for (k, (a, b)) in fresh.iter().zip(&reused).enumerate() {
        assert!(a == b, "output {k} differs between forward and forward_rows");
    }
    // Parameters changed after the density pass: its encodings are stale and must not be used.
    let mut s_all = vec![0.0; n_all];
    f.density_for_training(&all, &mut s_all);
    for g in f.param_groups() {
        g.params.iter_mut().for_each(|p| *p += 0.25);
    }
    let n = rows.len();
    let (mut s1, mut c1, mut s2, mut c2) = (vec![0.0; n], vec![0.0; 3 * n], vec![1.0; n], vec![1.0; 3 * n]);
    f.forward_rows(&rows, &pos, &dirs, &mut s1, &mut c1);
    f.forward(&pos, &dirs, &mut s2, &mut c2);
    assert!(s1 == s2 && c1 == c2, "forward_rows used encodings from before a parameter change");
}

#[test]
fn default_dimensions_follow_instant_ngp() {
    let f = HashNerf::<f32>::new(HashNerfConfig::default(), &unit_ctx(0)).unwrap();
    let [d, c] = f.mlps();
    assert_eq!(d.layer_shapes(), vec![(32, 64), (64, 16)], "density MLP: 32 → 64 → 16");
    assert_eq!(c.layer_shapes(), vec![(32, 64), (64, 64), (64, 3)], "colour MLP: 16+16 → 64 → 64 → 3");
    assert_eq!(d.n_params() + c.n_params(), 32 * 64 + 64 * 16 + 32 * 64 + 64 * 64 + 64 * 3);
}

/// `mlp_init = "xavier"` (the default) draws tiny-cuda-nn's bounds, √(6 / (fan_in + fan_out))
/// over widths padded to 16, `torch` PyTorch's 1/√fan_in, and the choice touches nothing else.
#[test]
fn xavier_init_draws_tiny_cuda_nns_bounds_and_only_the_mlp_weights() {
    let ctx = unit_ctx(3);
    let cfg: HashNerfConfig = serde_json::from_value(serde_json::json!({"mlp_init": "torch"})).unwrap();
    let torch = HashNerf::<f32>::new(cfg, &ctx).unwrap();
    let xavier = HashNerf::<f32>::new(HashNerfConfig::default(), &ctx).unwrap();
    assert_eq!(torch.grid().params(), xavier.grid().params(), "the table does not depend on the MLP init");
    let explicit: HashNerfConfig = serde_json::from_value(serde_json::json!({"mlp_init": "xavier"})).unwrap();
    assert_eq!(explicit, HashNerfConfig::default(), "xavier is the default");
    let pad = |n: usize| n.div_ceil(16) * 16;
    for (t, x) in torch.mlps().into_iter().zip(xavier.mlps()) {
        for ((fan_in, out), (w, _)) in x.layer_shapes().into_iter().zip(x.layer_offsets()) {
            let max = |m: &nerf_mlp::Mlp<f32>| m.params()[w..w + fan_in * out].iter().fold(0.0f32, |a, v| a.max(v.abs()));
            let (bt, bx) = (1.0 / (fan_in as f32).sqrt(), (6.0 / (pad(fan_in) + pad(out)) as f32).sqrt());
            // Each bound nearly reached and never passed (the layers hold ≥ 192 weights).
            assert!(max(t) <= bt && max(t) > 0.9 * bt, "torch {fan_in}→{out}: max {} against {bt}", max(t));
            assert!(max(x) <= bx && max(x) > 0.9 * bx, "xavier {fan_in}→{out}: max {} against {bx}", max(x));
            assert!(bx > 1.3 * bt, "{fan_in}→{out}: {bx} against {bt}");
        }
    }
    assert!(serde_json::from_value::<HashNerfConfig>(serde_json::json!({"mlp_init": "he"})).is_err());
}

#[test]
fn bad_configs_are_rejected() {
    assert!(nerf_field_hash::build(&serde_json::json!({"sh_degree": 7}), &unit_ctx(0)).is_err());
    let e = nerf_field_hash::build(&serde_json::json!({"grid": {"levls": 3}}), &unit_ctx(0)).err().unwrap();
    assert!(e.to_string().contains("levls"), "{e}");
    let flat = FieldContext { aabb_min: [0.0; 3], aabb_max: [1.0, 0.0, 1.0], seed: 0, scene_scale: 1.0 };
    assert!(nerf_field_hash::build(&serde_json::Value::Null, &flat).is_err());
    let e = HashNerf::<f32>::new(HashNerfConfig { density_bias: f32::NAN, ..small() }, &unit_ctx(0)).err().unwrap();
    assert!(e.to_string().contains("density_bias"), "{e}");
    for (cfg, key) in [
        (HashNerfConfig { grid_weight_decay: -1e-6, ..small() }, "grid_weight_decay"),
        (HashNerfConfig { grid_weight_decay: f32::INFINITY, ..small() }, "grid_weight_decay"),
        (HashNerfConfig { mlp_weight_decay: f32::NAN, ..small() }, "mlp_weight_decay"),
        (HashNerfConfig { mlp_f16_scale: Some(0.0), ..small() }, "mlp_f16_scale"),
        (HashNerfConfig { mlp_f16_scale: Some(f32::INFINITY), ..small() }, "mlp_f16_scale"),
    ] {
        let e = HashNerf::<f32>::new(cfg, &unit_ctx(0)).err().unwrap();
        assert!(e.to_string().contains(key), "{e}");
    }
}

#[test]
fn the_finest_resolution_left_out_grows_with_the_scenes_box() {
    // instant-ngp: 2048 × aabb_scale over the box. A resolution the config sets is kept, and a
    // scene of scale 1 keeps the default.
    let res = |config: serde_json::Value, scene_scale: f32| -> u64 {
        let ctx = FieldContext { aabb_min: [-6.0; 3], aabb_max: [6.0; 3], seed: 0, scene_scale };
        let f = nerf_field_hash::build(&config, &ctx).unwrap();
        f.config()["grid"]["max_resolution"].as_u64().unwrap()
    };
    let small = serde_json::json!({"grid": {"log2_hashmap_size": 12}});
    let default = HashNerfConfig::default().grid.max_resolution as u64;
    assert_eq!(default, 2048);
    assert_eq!(res(small.clone(), 1.0), default);
    assert_eq!(res(small.clone(), 4.0), 4 * default);
    assert_eq!(res(small.clone(), 2.5), 5120);
    assert_eq!(res(serde_json::json!({"grid": {"log2_hashmap_size": 12, "max_resolution": 1024}}), 4.0), 1024);
    assert_eq!(res(serde_json::Value::Null, 16.0), 16 * default);
}

#[test]
fn f16_mlp_arithmetic_reaches_both_mlps_from_the_config_file() {
    let ctx = FieldContext { aabb_min: [-1.5; 3], aabb_max: [1.5; 3], seed: 4, scene_scale: 1.0 };
    // Table entries of O(1) (a fresh table's ~1e-4 would give logits in f16's subnormals).
    let cfg = serde_json::json!({"grid": {"log2_hashmap_size": 12, "init_scale": 1.0}, "mlp_f16_scale": 128.0});
    let parsed: HashNerfConfig = serde_json::from_value(cfg.clone()).unwrap();
    assert_eq!(parsed.mlp_f16_scale, Some(128.0));
    let back: HashNerfConfig = serde_json::from_str(&serde_json::to_string(&parsed).unwrap()).unwrap();
    assert_eq!(back, parsed);
    // Unset, it is left out of the written config (older readers keep reading it).
    assert!(!serde_json::to_string(&HashNerfConfig::default()).unwrap().contains("mlp_f16_scale"));
    let f16 = HashNerf::<f32>::new(parsed, &ctx).unwrap();
    assert!(f16.mlps().iter().all(|m| m.f16_arithmetic() == Some(128.0)));
    let full = HashNerf::<f32>::new(serde_json::from_value(serde_json::json!({"grid": {"log2_hashmap_size": 12, "init_scale": 1.0}})).unwrap(), &ctx).unwrap();
    assert!(full.mlps().iter().all(|m| m.f16_arithmetic().is_none()));
    // The same parameters, the density and the colour in f16: σ = exp(x) of an f16 x, and every
    // colour an f16 (the sigmoid's output is rounded as the net's last layer).
    let mut rng = nerf_core::rng(5, 0);
    let n = 500;
    let pos: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let dirs: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let (mut s16, mut c16) = (vec![f32::NAN; n], vec![f32::NAN; 3 * n]);
    let (mut s32, mut c32) = (vec![f32::NAN; n], vec![f32::NAN; 3 * n]);
    f16.query(&pos, &dirs, &mut s16, &mut c16);
    full.query(&pos, &dirs, &mut s32, &mut c32);
    let r = nerf_mlp::round_f16::<f32>;
    assert!(c16.iter().all(|&c| r(c) == c));
    // ln σ is the f16 logit up to the rounding of exp and ln in f32 (f16's spacing near 1: 1e-3).
    assert!(s16.iter().all(|&s| (s.ln() - r(s.ln())).abs() <= 1e-5 * (1.0 + s.ln().abs())));
    assert!(s32.iter().filter(|&&s| (s.ln() - r(s.ln())).abs() > 1e-5 * (1.0 + s.ln().abs())).count() > n / 2);
    assert!(c16.iter().zip(&c32).any(|(a, b)| a != b));
    assert!(c16.iter().zip(&c32).all(|(a, b)| (a - b).abs() < 1e-2), "f16 colours far from the f32 ones");
}
