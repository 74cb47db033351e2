#![allow(clippy::needless_range_loop)]
//! Per-view colour correction: it is the per-sample correction `c ↦ A c + b` composited (and the
//! identity changes nothing), and its backward pass matches central finite differences in f64,
//! alone and through compositing.

use nerf_render::{
    color_correct_backward, color_correct_forward, composite_backward, composite_forward, identity_color_correction, mean_color_correction,
    CompositeOutputs, COLOR_PARAMS_PER_VIEW,
};
use rand::Rng;

const P: usize = COLOR_PARAMS_PER_VIEW;

/// Packed samples of rays with 0..12 samples, sorted distances, densities up to 6.
struct Batch {
    offsets: Vec<u32>,
    sigma: Vec<f64>,
    rgb: Vec<f64>,
    dt: Vec<f64>,
    t: Vec<f64>,
    background: Vec<f64>,
    views: Vec<u32>,
    params: Vec<f64>,
}

fn batch(n_rays: usize, n_views: usize, seed: u64) -> Batch {
    let mut g = nerf_core::rng(seed, 0);
    let mut b = Batch { offsets: vec![0], sigma: vec![], rgb: vec![], dt: vec![], t: vec![], background: vec![], views: vec![], params: vec![] };
    for r in 0..n_rays {
        let c = if r == 0 { 0 } else { g.gen_range(1..12) };
        let mut t = 2.0 + g.gen::<f64>();
        for _ in 0..c {
            let dt = 0.02 + 0.2 * g.gen::<f64>();
            b.t.push(t);
            b.dt.push(dt);
            t += dt;
            b.sigma.push(6.0 * g.gen::<f64>());
            b.rgb.extend([g.gen::<f64>(), g.gen(), g.gen()]);
        }
        b.offsets.push(b.sigma.len() as u32);
        b.background.extend([g.gen::<f64>(), g.gen(), g.gen()]);
        b.views.push(g.gen_range(0..n_views as u32));
    }
    // Corrections near the identity, as training keeps them.
    b.params = identity_color_correction(n_views).iter().map(|&x| x as f64 + 0.3 * (g.gen::<f64>() - 0.5)).collect();
    b
}

fn composite(b: &Batch, rgb: &[f64], sigma: &[f64]) -> CompositeOutputs<f64> {
    let mut out = CompositeOutputs::new();
    composite_forward(&b.offsets, sigma, rgb, &b.dt, &b.t, Some(&b.background), 0.0, &mut out);
    out
}

fn correct(b: &Batch, params: &[f64], rgb: &[f64], opacity: &[f64]) -> Vec<f64> {
    let mut out = vec![f64::NAN; rgb.len()];
    color_correct_forward(Some(&b.views), params, rgb, opacity, &b.background, &mut out);
    out
}

#[test]
fn correcting_the_pixel_is_correcting_every_sample() {
    let b = batch(40, 5, 1);
    let fwd = composite(&b, &b.rgb, &b.sigma);
    let out = correct(&b, &b.params, &fwd.rgb, &fwd.opacity);
    // c ↦ A_v c + b_v on every sample of a ray of view v, then compositing.
    let mut per_sample = b.rgb.clone();
    for r in 0..40 {
        let p = &b.params[P * b.views[r] as usize..][..P];
        for s in b.offsets[r] as usize..b.offsets[r + 1] as usize {
            let c = &b.rgb[3 * s..3 * s + 3];
            for i in 0..3 {
                per_sample[3 * s + i] = p[3 * i] * c[0] + p[3 * i + 1] * c[1] + p[3 * i + 2] * c[2] + p[9 + i];
            }
        }
    }
    let want = composite(&b, &per_sample, &b.sigma).rgb;
    for (k, (x, y)) in out.iter().zip(&want).enumerate() {
        assert!((x - y).abs() < 1e-12, "ray {} channel {}: {x} vs {y}", k / 3, k % 3);
    }
    // The empty ray keeps its background under any correction.
    assert_eq!(&out[..3], &b.background[..3]);
}

#[test]
fn the_identity_and_the_mean_of_identities_change_nothing() {
    let b = batch(30, 4, 2);
    let fwd = composite(&b, &b.rgb, &b.sigma);
    let id: Vec<f64> = identity_color_correction(4).iter().map(|&x| x as f64).collect();
    let out = correct(&b, &id, &fwd.rgb, &fwd.opacity);
    for (x, y) in out.iter().zip(&fwd.rgb) {
        assert!((x - y).abs() < 1e-15);
    }
    let mean = mean_color_correction(&identity_color_correction(7)).unwrap();
    assert_eq!(&mean[..], &identity_color_correction(1)[..]);
    // `None` applies the first (here: the only) view's correction to every ray.
    let p: Vec<f64> = b.params[..P].to_vec();
    let mut all = vec![0.0; fwd.rgb.len()];
    color_correct_forward(None, &p, &fwd.rgb, &fwd.opacity, &b.background, &mut all);
    let zero = vec![0u32; 30];
    let mut want = vec![0.0; fwd.rgb.len()];
    color_correct_forward(Some(&zero), &b.params, &fwd.rgb, &fwd.opacity, &b.background, &mut want);
    assert_eq!(all, want);
}

#[test]
fn the_mean_averages_each_value_and_rejects_partial_views() {
    let mut p = identity_color_correction(2);
    p[0] = 3.0; // A₀₀ of view 0
    p[P + 11] = 0.5; // b₂ of view 1
    let m = mean_color_correction(&p).unwrap();
    assert_eq!(m[0], 2.0);
    assert_eq!(m[11], 0.25);
    assert_eq!(m[4], 1.0);
    assert!(mean_color_correction(&p[..13]).unwrap_err().contains("13"));
    assert!(mean_color_correction(&[]).is_err());
}

/// L = Σ W ⊙ out for fixed random weights W.
fn loss(b: &Batch, w: &[f64], params: &[f64], rgb: &[f64], opacity: &[f64]) -> f64 {
    correct(b, params, rgb, opacity).iter().zip(w).map(|(o, w)| o * w).sum()
}

#[test]
fn the_backward_matches_finite_differences() {
    let b = batch(25, 3, 3);
    let mut g = nerf_core::rng(3, 1);
    let fwd = composite(&b, &b.rgb, &b.sigma);
    let (rgb, op) = (fwd.rgb.clone(), fwd.opacity.clone());
    let w: Vec<f64> = (0..75).map(|_| g.gen::<f64>() - 0.5).collect();
    let (mut d_rgb, mut d_op) = (vec![f64::NAN; 75], vec![f64::NAN; 25]);
    let mut d_params = vec![0.5; b.params.len()]; // added to
    color_correct_backward(Some(&b.views), &b.params, &rgb, &op, &b.background, &w, &mut d_rgb, &mut d_op, &mut d_params);
    let h = 1e-6;
    let fd = |f: &dyn Fn(f64) -> f64| (f(h) - f(-h)) / (2.0 * h);
    for k in 0..75 {
        let n = fd(&|e| {
            let mut x = rgb.clone();
            x[k] += e;
            loss(&b, &w, &b.params, &x, &op)
        });
        assert!((n - d_rgb[k]).abs() < 1e-8, "d_rgb[{k}]: {} vs {n}", d_rgb[k]);
    }
    for r in 0..25 {
        let n = fd(&|e| {
            let mut x = op.clone();
            x[r] += e;
            loss(&b, &w, &b.params, &rgb, &x)
        });
        assert!((n - d_op[r]).abs() < 1e-8, "d_opacity[{r}]: {} vs {n}", d_op[r]);
    }
    for k in 0..b.params.len() {
        let n = fd(&|e| {
            let mut x = b.params.clone();
            x[k] += e;
            loss(&b, &w, &x, &rgb, &op)
        });
        assert!((n + 0.5 - d_params[k]).abs() < 1e-8, "d_params[{k}]: {} vs {n} + 0.5", d_params[k]);
    }
}

/// Through compositing: the corrected pixel's gradient with respect to every σ and sample colour,
/// taken by compositing's backward from `d_rgb` and `d_opacity`, against finite differences of
/// the whole chain.
#[test]
fn the_chain_through_compositing_matches_finite_differences() {
    let b = batch(20, 2, 4);
    let mut g = nerf_core::rng(4, 1);
    let w: Vec<f64> = (0..60).map(|_| g.gen::<f64>() - 0.5).collect();
    let chain = |sigma: &[f64], rgb: &[f64]| {
        let f = composite(&b, rgb, sigma);
        loss(&b, &w, &b.params, &f.rgb, &f.opacity)
    };
    let fwd = composite(&b, &b.rgb, &b.sigma);
    let (mut d_rgb, mut d_op, mut d_params) = (vec![0.0; 60], vec![0.0; 20], vec![0.0; b.params.len()]);
    color_correct_backward(Some(&b.views), &b.params, &fwd.rgb, &fwd.opacity, &b.background, &w, &mut d_rgb, &mut d_op, &mut d_params);
    let n = b.sigma.len();
    let (mut d_sigma, mut d_c) = (vec![f64::NAN; n], vec![f64::NAN; 3 * n]);
    composite_backward(&b.offsets, &b.sigma, &b.rgb, &b.dt, &b.t, Some(&b.background), &fwd, &d_rgb, Some(&d_op), None, &mut d_sigma, &mut d_c);
    let h = 1e-6;
    for k in 0..n {
        let (mut p, mut m) = (b.sigma.clone(), b.sigma.clone());
        p[k] += h;
        m[k] -= h;
        let fd = (chain(&p, &b.rgb) - chain(&m, &b.rgb)) / (2.0 * h);
        assert!((fd - d_sigma[k]).abs() < 1e-7 * (1.0 + fd.abs()), "d_sigma[{k}]: {} vs {fd}", d_sigma[k]);
    }
    for k in 0..3 * n {
        let (mut p, mut m) = (b.rgb.clone(), b.rgb.clone());
        p[k] += h;
        m[k] -= h;
        let fd = (chain(&b.sigma, &p) - chain(&b.sigma, &m)) / (2.0 * h);
        assert!((fd - d_c[k]).abs() < 1e-8, "d_sample_rgb[{k}]: {} vs {fd}", d_c[k]);
    }
}

#[test]
#[should_panic(expected = "past the 2 views")]
fn a_view_without_a_correction_is_refused() {
    let b = batch(3, 2, 5);
    let fwd = composite(&b, &b.rgb, &b.sigma);
    let mut out = vec![0.0; 9];
    color_correct_forward(Some(&[0, 1, 2]), &b.params, &fwd.rgb, &fwd.opacity, &b.background, &mut out);
}
