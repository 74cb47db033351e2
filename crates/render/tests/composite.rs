#![allow(clippy::needless_range_loop)]
//! Closed-form, finite-difference and consistency checks of the compositor.

use nerf_core::Real;
use nerf_render::{composite_backward, composite_forward, mse_loss_grad, CompositeOutputs};
use rand::Rng;

/// A random packed batch (f64), with rays of 0 and 1 samples among others.
struct Batch {
    offsets: Vec<u32>,
    sigma: Vec<f64>,
    rgb: Vec<f64>,
    dt: Vec<f64>,
    t: Vec<f64>,
    bg: Vec<f64>,
}

fn batch(counts: &[usize], sigma_max: f64, seed: u64) -> Batch {
    let mut g = nerf_core::rng(seed, 0);
    let mut b = Batch {
        offsets: vec![0],
        sigma: vec![],
        rgb: vec![],
        dt: vec![],
        t: vec![],
        bg: vec![],
    };
    for &c in counts {
        let mut t = 2.0 + g.gen::<f64>();
        for _ in 0..c {
            let dt = 0.05 + 0.45 * g.gen::<f64>();
            b.t.push(t);
            b.dt.push(dt);
            t += dt;
            b.sigma.push(sigma_max * g.gen::<f64>());
            for _ in 0..3 {
                b.rgb.push(g.gen());
            }
        }
        for _ in 0..3 {
            b.bg.push(g.gen());
        }
        b.offsets.push(b.sigma.len() as u32);
    }
    b
}

/// L = Σ a·rgb + Σ b·opacity + Σ e·depth with fixed random coefficients.
struct Loss {
    a: Vec<f64>,
    b: Vec<f64>,
    e: Vec<f64>,
}

impl Loss {
    fn new(n_rays: usize, seed: u64) -> Self {
        let mut g = nerf_core::rng(seed, 1);
        let mut v = |n: usize| {
            (0..n)
                .map(|_| g.gen::<f64>() * 2.0 - 1.0)
                .collect::<Vec<_>>()
        };
        Loss {
            a: v(3 * n_rays),
            b: v(n_rays),
            e: v(n_rays),
        }
    }
    fn eval(&self, o: &CompositeOutputs<f64>) -> f64 {
        let dot = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>();
        dot(&self.a, &o.rgb) + dot(&self.b, &o.opacity) + dot(&self.e, &o.depth)
    }
}

fn forward(
    b: &Batch,
    sigma: &[f64],
    rgb: &[f64],
    bg: Option<&[f64]>,
    thr: f64,
) -> CompositeOutputs<f64> {
    let mut o = CompositeOutputs::new();
    composite_forward(&b.offsets, sigma, rgb, &b.dt, &b.t, bg, thr, &mut o);
    o
}

/// Compares composite_backward with central differences of the loss w.r.t. every σ and c
/// (and the background, whose gradient is d_rgb·(1 − opacity)). Returns #non-zero gradients seen.
fn fd_check(b: &Batch, use_bg: bool, thr: f64, seed: u64) -> usize {
    let n_rays = b.offsets.len() - 1;
    let n = b.sigma.len();
    let loss = Loss::new(n_rays, seed);
    let bg = use_bg.then_some(&b.bg[..]);
    let fwd = forward(b, &b.sigma, &b.rgb, bg, thr);
    let (mut ds, mut dc) = (vec![f64::NAN; n], vec![f64::NAN; 3 * n]);
    composite_backward(
        &b.offsets,
        &b.sigma,
        &b.rgb,
        &b.dt,
        &b.t,
        bg,
        &fwd,
        &loss.a,
        Some(&loss.b),
        Some(&loss.e),
        &mut ds,
        &mut dc,
    );
    let h = 1e-6;
    let tol = |fd: f64| 1e-7 + 1e-6 * fd.abs();
    let mut nonzero = 0;
    for k in 0..n {
        let (mut sp, mut sm) = (b.sigma.clone(), b.sigma.clone());
        sp[k] += h;
        sm[k] -= h;
        let fd = (loss.eval(&forward(b, &sp, &b.rgb, bg, thr))
            - loss.eval(&forward(b, &sm, &b.rgb, bg, thr)))
            / (2.0 * h);
        assert!(
            (ds[k] - fd).abs() <= tol(fd),
            "dσ[{k}]: analytic {} vs fd {fd}",
            ds[k]
        );
        nonzero += (fd.abs() > 1e-6) as usize;
    }
    for k in 0..3 * n {
        let (mut cp, mut cm) = (b.rgb.clone(), b.rgb.clone());
        cp[k] += h;
        cm[k] -= h;
        let fd = (loss.eval(&forward(b, &b.sigma, &cp, bg, thr))
            - loss.eval(&forward(b, &b.sigma, &cm, bg, thr)))
            / (2.0 * h);
        assert!(
            (dc[k] - fd).abs() <= tol(fd),
            "dc[{k}]: analytic {} vs fd {fd}",
            dc[k]
        );
        nonzero += (fd.abs() > 1e-6) as usize;
    }
    if use_bg {
        for k in 0..3 * n_rays {
            let (mut bp, mut bm) = (b.bg.clone(), b.bg.clone());
            bp[k] += h;
            bm[k] -= h;
            let fd = (loss.eval(&forward(b, &b.sigma, &b.rgb, Some(&bp), thr))
                - loss.eval(&forward(b, &b.sigma, &b.rgb, Some(&bm), thr)))
                / (2.0 * h);
            let analytic = loss.a[k] * (1.0 - fwd.opacity[k / 3]);
            assert!(
                (analytic - fd).abs() <= tol(fd),
                "dbg[{k}]: analytic {analytic} vs fd {fd}"
            );
        }
    }
    nonzero
}

const COUNTS: &[usize] = &[0, 1, 5, 2, 0, 12, 1, 8, 3, 20];

#[test]
fn backward_matches_finite_differences_with_background() {
    let b = batch(COUNTS, 3.0, 11);
    let nz = fd_check(&b, true, 0.0, 5);
    assert!(
        nz > 3 * b.sigma.len(),
        "too few non-zero gradients ({nz}) for the check to mean anything"
    );
}

#[test]
fn backward_matches_finite_differences_black_background() {
    let b = batch(COUNTS, 1.0, 12);
    let nz = fd_check(&b, false, 0.0, 6);
    assert!(nz > 3 * b.sigma.len());
}

/// Transmittance before each sample, recomputed independently of the library.
fn transmittances(b: &Batch, r: usize) -> Vec<f64> {
    let (s0, s1) = (b.offsets[r] as usize, b.offsets[r + 1] as usize);
    let mut acc = 0.0f64;
    (s0..s1)
        .map(|k| {
            let tr = (-acc).exp();
            acc += b.sigma[k] * b.dt[k];
            tr
        })
        .collect()
}

#[test]
fn early_stop_forward_and_backward_agree_with_fd() {
    let thr = 0.2;
    let b = batch(COUNTS, 4.0, 21);
    // The check is only meaningful (and FD only valid) if no transmittance sits at the threshold,
    // and if some ray actually stops with samples of positive density left.
    let mut stopped = 0;
    let fwd = forward(&b, &b.sigma, &b.rgb, Some(&b.bg), thr);
    for r in 0..COUNTS.len() {
        let tr = transmittances(&b, r);
        for (i, &ti) in tr.iter().enumerate() {
            assert!(
                (ti - thr).abs() > 1e-4,
                "data too close to the threshold; pick another seed"
            );
            let k = b.offsets[r] as usize + i;
            if ti < thr {
                assert_eq!(
                    fwd.weights[k], 0.0,
                    "sample {k} after the stop must have weight 0"
                );
                stopped += (b.sigma[k] > 0.0) as usize;
            } else {
                let alpha = 1.0 - (-b.sigma[k] * b.dt[k]).exp();
                assert!((fwd.weights[k] - ti * alpha).abs() < 1e-12);
            }
        }
    }
    assert!(
        stopped >= 5,
        "only {stopped} samples skipped; the test does not exercise early stop"
    );
    // Without early stop the same batch differs (the skipped samples matter).
    let full = forward(&b, &b.sigma, &b.rgb, Some(&b.bg), 0.0);
    assert!(full
        .opacity
        .iter()
        .zip(&fwd.opacity)
        .any(|(a, c)| (a - c).abs() > 1e-6));
    fd_check(&b, true, thr, 7);
}

#[test]
fn three_sample_closed_form() {
    // σ = [1, 2, 0.5], δ = [0.5, 0.25, 1] ⇒ σδ = 0.5 each: α = 1 − e^{−1/2}, T = [1, e^{−1/2}, e^{−1}].
    let offsets = [0u32, 3];
    let sigma = [1.0f64, 2.0, 0.5];
    let dt = [0.5, 0.25, 1.0];
    let t = [2.0, 2.5, 2.75];
    let rgb = [
        1.0, 0.0, 0.0, /**/ 0.0, 1.0, 0.0, /**/ 0.0, 0.0, 1.0,
    ];
    let bg = [0.5, 0.25, 1.0];
    let a = 1.0 - (-0.5f64).exp();
    let tr = [1.0, (-0.5f64).exp(), (-1.0f64).exp()];
    let w: Vec<f64> = tr.iter().map(|x| x * a).collect();
    let acc = w[0] + w[1] + w[2];
    assert!((acc - (1.0 - (-1.5f64).exp())).abs() < 1e-15); // Σw = 1 − T_3
    let mut o = CompositeOutputs::new();
    composite_forward(&offsets, &sigma, &rgb, &dt, &t, Some(&bg), 0.0, &mut o);
    for i in 0..3 {
        assert!((o.weights[i] - w[i]).abs() < 1e-14, "w[{i}]");
        assert!(
            (o.rgb[i] - (w[i] + (1.0 - acc) * bg[i])).abs() < 1e-14,
            "rgb[{i}]"
        );
    }
    assert!((o.opacity[0] - acc).abs() < 1e-14);
    assert!((o.depth[0] - (2.0 * w[0] + 2.5 * w[1] + 2.75 * w[2])).abs() < 1e-14);
    // f32 agrees with the same closed form.
    let f = |x: &[f64]| x.iter().map(|&v| v as f32).collect::<Vec<f32>>();
    let mut o32 = CompositeOutputs::new();
    composite_forward(
        &offsets,
        &f(&sigma),
        &f(&rgb),
        &f(&dt),
        &f(&t),
        Some(&f(&bg)),
        0.0,
        &mut o32,
    );
    for i in 0..3 {
        assert!((o32.weights[i] as f64 - w[i]).abs() < 1e-6);
    }
    // Early stop at 0.5: T_2 = e^{−1} < 0.5 ≤ T_1, so only two samples count.
    composite_forward(&offsets, &sigma, &rgb, &dt, &t, Some(&bg), 0.5, &mut o);
    assert_eq!(o.weights[2], 0.0);
    assert!((o.opacity[0] - (w[0] + w[1])).abs() < 1e-14);
    assert!((o.opacity[0] - (1.0 - (-1.0f64).exp())).abs() < 1e-14);
}

#[test]
fn empty_rays_and_empty_batch() {
    let mut o = CompositeOutputs::<f32>::new();
    composite_forward(
        &[0, 0, 0],
        &[],
        &[],
        &[],
        &[],
        Some(&[0.1, 0.2, 0.3, 0.4, 0.5, 0.6]),
        0.0,
        &mut o,
    );
    assert_eq!(o.rgb, vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6]);
    assert_eq!(o.opacity, vec![0.0, 0.0]);
    assert_eq!(o.depth, vec![0.0, 0.0]);
    assert!(o.weights.is_empty());
    composite_forward(&[0], &[], &[], &[], &[], None, 0.0, &mut o);
    assert!(o.rgb.is_empty() && o.opacity.is_empty());
}

/// A batch large enough to be split across threads gives bit-identical results to compositing
/// each ray on its own (the block splitting cannot mix rays up), forward and backward.
#[test]
fn parallel_blocks_equal_per_ray_results() {
    let mut g = nerf_core::rng(3, 0);
    let counts: Vec<usize> = (0..3000).map(|_| g.gen_range(0..40usize)).collect();
    let b64 = batch(&counts, 2.0, 31);
    let f = |x: &[f64]| x.iter().map(|&v| v as f32).collect::<Vec<f32>>();
    let (sigma, rgb, dt, t, bg) = (
        f(&b64.sigma),
        f(&b64.rgb),
        f(&b64.dt),
        f(&b64.t),
        f(&b64.bg),
    );
    let n_rays = counts.len();
    let d_rgb: Vec<f32> = (0..3 * n_rays).map(|_| g.gen::<f32>() - 0.5).collect();
    let d_dep: Vec<f32> = (0..n_rays).map(|_| g.gen::<f32>() - 0.5).collect();
    let mut o = CompositeOutputs::new();
    composite_forward(&b64.offsets, &sigma, &rgb, &dt, &t, Some(&bg), 1e-3, &mut o);
    let n = sigma.len();
    assert!(n > 40_000, "batch must exceed the parallel grain");
    let (mut ds, mut dc) = (vec![0.0; n], vec![0.0; 3 * n]);
    composite_backward(
        &b64.offsets,
        &sigma,
        &rgb,
        &dt,
        &t,
        Some(&bg),
        &o,
        &d_rgb,
        None,
        Some(&d_dep),
        &mut ds,
        &mut dc,
    );
    let mut o1 = CompositeOutputs::new();
    for r in 0..n_rays {
        let (s0, s1) = (b64.offsets[r] as usize, b64.offsets[r + 1] as usize);
        let off = [0, (s1 - s0) as u32];
        composite_forward(
            &off,
            &sigma[s0..s1],
            &rgb[3 * s0..3 * s1],
            &dt[s0..s1],
            &t[s0..s1],
            Some(&bg[3 * r..3 * r + 3]),
            1e-3,
            &mut o1,
        );
        assert_eq!(o1.rgb[..], o.rgb[3 * r..3 * r + 3]);
        assert_eq!(o1.opacity[0], o.opacity[r]);
        assert_eq!(o1.depth[0], o.depth[r]);
        assert_eq!(o1.weights[..], o.weights[s0..s1]);
        let (mut ds1, mut dc1) = (vec![0.0; s1 - s0], vec![0.0; 3 * (s1 - s0)]);
        composite_backward(
            &off,
            &sigma[s0..s1],
            &rgb[3 * s0..3 * s1],
            &dt[s0..s1],
            &t[s0..s1],
            Some(&bg[3 * r..3 * r + 3]),
            &o1,
            &d_rgb[3 * r..3 * r + 3],
            None,
            Some(&d_dep[r..r + 1]),
            &mut ds1,
            &mut dc1,
        );
        assert_eq!(ds1[..], ds[s0..s1]);
        assert_eq!(dc1[..], dc[3 * s0..3 * s1]);
    }
}

/// The f32 path agrees with the f64 path (same code, different precision).
#[test]
fn f32_matches_f64() {
    let b = batch(COUNTS, 3.0, 41);
    let f = |x: &[f64]| x.iter().map(|&v| v as f32).collect::<Vec<f32>>();
    let o64 = forward(&b, &b.sigma, &b.rgb, Some(&b.bg), 0.0);
    let mut o32 = CompositeOutputs::new();
    composite_forward(
        &b.offsets,
        &f(&b.sigma),
        &f(&b.rgb),
        &f(&b.dt),
        &f(&b.t),
        Some(&f(&b.bg)),
        0.0,
        &mut o32,
    );
    for (x, y) in o32
        .rgb
        .iter()
        .zip(&o64.rgb)
        .chain(o32.weights.iter().zip(&o64.weights))
    {
        assert!((x.f64() - y).abs() < 2e-6);
    }
}

#[test]
fn mse_loss_and_gradient() {
    let mut g = nerf_core::rng(9, 0);
    let pred: Vec<f32> = (0..300).map(|_| g.gen()).collect();
    let target: Vec<f32> = (0..300).map(|_| g.gen()).collect();
    let mut d = vec![0.0; 300];
    let l = mse_loss_grad(&pred, &target, &mut d);
    let want = pred
        .iter()
        .zip(&target)
        .map(|(p, t)| ((p - t) as f64).powi(2))
        .sum::<f64>()
        / 300.0;
    assert!((l as f64 - want).abs() < 1e-7);
    // Central differences of the loss (evaluated in f64) w.r.t. a few predictions.
    for k in [0, 17, 299] {
        let h = 1e-3f64;
        let eval = |dx: f64| {
            pred.iter()
                .enumerate()
                .zip(&target)
                .map(|((i, &p), &t)| (p as f64 + if i == k { dx } else { 0.0 } - t as f64).powi(2))
                .sum::<f64>()
                / 300.0
        };
        let fd = (eval(h) - eval(-h)) / (2.0 * h);
        assert!(
            (d[k] as f64 - fd).abs() < 1e-6,
            "d_pred[{k}] {} vs {fd}",
            d[k]
        );
    }
    assert_eq!(mse_loss_grad(&[], &[], &mut []), 0.0);
}

/// instant-ngp's Huber loss: the gradient is that of `mean(h(e))`, `h(e) = e²` for `|e| ≤ δ` and
/// `2δ|e| − δ²` beyond (central differences in f64 away from the kink), and the returned value is
/// still the MSE.
#[test]
fn huber_loss_gradient_and_reported_mse() {
    let mut g = nerf_core::rng(10, 0);
    let n = 400;
    let pred: Vec<f32> = (0..n).map(|_| g.gen()).collect();
    let target: Vec<f32> = (0..n).map(|_| g.gen()).collect();
    let delta = 0.1f32;
    let mut d = vec![f32::NAN; n];
    let l = nerf_render::photometric_loss_grad(&pred, &target, Some(delta), &mut d);
    let mut d_mse = vec![0.0; n];
    assert_eq!(l, mse_loss_grad(&pred, &target, &mut d_mse), "reports the MSE");
    let h = |e: f64| if e.abs() <= delta as f64 { e * e } else { 2.0 * delta as f64 * e.abs() - (delta as f64).powi(2) };
    let (mut inside, mut outside) = (0, 0);
    for k in 0..n {
        let e = (pred[k] - target[k]) as f64;
        let step = 1e-4f64;
        if (e.abs() - delta as f64).abs() < 2.0 * step {
            continue; // the kink
        }
        let fd = (h(e + step) - h(e - step)) / (2.0 * step) / n as f64;
        assert!((d[k] as f64 - fd).abs() < 1e-7, "d_pred[{k}] {} vs {fd} (e = {e})", d[k]);
        if e.abs() <= delta as f64 {
            inside += 1;
            assert_eq!(d[k], d_mse[k], "MSE gradient inside δ");
        } else {
            outside += 1;
        }
    }
    assert!(inside > 10 && outside > 100, "{inside} / {outside}");
}

/// Depth supervision's L1 loss: its value, its gradient against central differences (away from
/// the kink), and nothing from rays without a measurement.
#[test]
fn depth_loss_and_gradient() {
    let mut g = nerf_core::rng(11, 0);
    let n = 300;
    let pred: Vec<f32> = (0..n).map(|_| g.gen_range(0.0..4.0)).collect();
    // Every fifth ray has no measurement (0), one is negative (also none).
    let mut target: Vec<f32> = (0..n).map(|k| if k % 5 == 0 { 0.0 } else { g.gen_range(0.5..4.0) }).collect();
    target[1] = -1.0;
    let lambda = 0.3f32;
    let mut d = vec![f32::NAN; n];
    let l = nerf_render::depth_loss_grad(&pred, &target, lambda, &mut d);
    let loss = |p: &[f64]| -> f64 {
        p.iter().zip(&target).filter(|(_, &t)| t > 0.0).map(|(&p, &t)| (p - t as f64).abs()).sum::<f64>() * lambda as f64 / n as f64
    };
    let p64: Vec<f64> = pred.iter().map(|&p| p as f64).collect();
    assert!((l as f64 - loss(&p64)).abs() < 1e-6, "{l} vs {}", loss(&p64));
    for k in 0..n {
        if target[k] <= 0.0 {
            assert_eq!(d[k], 0.0, "ray {k} has no measurement");
            continue;
        }
        let step = 1e-4;
        let (mut a, mut b) = (p64.clone(), p64.clone());
        a[k] += step;
        b[k] -= step;
        let fd = (loss(&a) - loss(&b)) / (2.0 * step);
        assert!((d[k] as f64 - fd).abs() < 1e-7, "d_depth[{k}] {} vs {fd}", d[k]);
    }
    // Through compositing: a ray whose expected depth is short of its target is pushed to put
    // weight farther (its far sample's density up, its near one's down).
    let offsets = [0u32, 2];
    let (sigma, rgb, dt, t) = ([1.0f64, 1.0], [0.5f64; 6], [0.5f64, 0.5], [1.0f64, 3.0]);
    let mut o = CompositeOutputs::new();
    composite_forward(&offsets, &sigma, &rgb, &dt, &t, None, 0.0, &mut o);
    let mut dd = [0.0f32];
    nerf_render::depth_loss_grad(&[o.depth[0] as f32], &[3.0], 1.0, &mut dd);
    let (mut d_sigma, mut d_rgb) = (vec![0.0; 2], vec![0.0; 6]);
    composite_backward(&offsets, &sigma, &rgb, &dt, &t, None, &o, &[0.0; 3], None, Some(&[dd[0] as f64]), &mut d_sigma, &mut d_rgb);
    assert!(d_sigma[0] > 0.0 && d_sigma[1] < 0.0, "gradient descent raises the far density: {d_sigma:?}");
}
