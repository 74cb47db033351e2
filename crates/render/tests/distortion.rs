#![allow(clippy::needless_range_loop)]
//! The distortion loss: its value against the O(n²) definition, its σ gradient against central
//! finite differences in f64 (through compositing's weights), the early stop, accumulation, and
//! what it rewards.

use nerf_render::{composite_forward, distortion_loss_grad, CompositeOutputs};
use rand::Rng;

/// Random rays (f64): sorted distances with gaps between samples (as marching skips cells),
/// some zero densities, and rays of 0 and 1 samples.
struct Batch {
    offsets: Vec<u32>,
    sigma: Vec<f64>,
    rgb: Vec<f64>,
    dt: Vec<f64>,
    t: Vec<f64>,
}

fn batch(counts: &[usize], sigma_max: f64, seed: u64) -> Batch {
    let mut g = nerf_core::rng(seed, 0);
    let mut b = Batch { offsets: vec![0], sigma: vec![], rgb: vec![], dt: vec![], t: vec![] };
    for &c in counts {
        let mut t = 2.0 + g.gen::<f64>();
        for _ in 0..c {
            let dt = 0.02 + 0.2 * g.gen::<f64>();
            b.t.push(t);
            b.dt.push(dt);
            t += dt + if g.gen::<f64>() < 0.3 { g.gen::<f64>() } else { 0.0 };
            b.sigma.push(if g.gen::<f64>() < 0.15 { 0.0 } else { sigma_max * g.gen::<f64>() });
            b.rgb.extend([g.gen::<f64>(), g.gen(), g.gen()]);
        }
        b.offsets.push(b.sigma.len() as u32);
    }
    b
}

fn forward(b: &Batch, sigma: &[f64], thr: f64) -> CompositeOutputs<f64> {
    let mut out = CompositeOutputs::new();
    composite_forward(&b.offsets, sigma, &b.rgb, &b.dt, &b.t, None, thr, &mut out);
    out
}

/// The loss of the batch at `sigma` (the function's own value).
fn loss(b: &Batch, sigma: &[f64], scale: f64, weight: f64, thr: f64) -> f64 {
    let fwd = forward(b, sigma, thr);
    let mut ds = vec![0.0; sigma.len()];
    let mut rl = vec![0.0; b.offsets.len() - 1];
    distortion_loss_grad(&b.offsets, sigma, &b.dt, &b.t, &fwd, scale, weight, &mut ds, &mut rl)
}

#[test]
fn the_loss_is_the_double_sum_of_its_definition() {
    let b = batch(&[0, 1, 5, 17, 40], 8.0, 3);
    let (scale, weight) = (0.25, 0.7);
    let fwd = forward(&b, &b.sigma, 0.0);
    let mut ds = vec![0.0; b.sigma.len()];
    let mut rl = vec![f64::NAN; 5];
    let total = distortion_loss_grad(&b.offsets, &b.sigma, &b.dt, &b.t, &fwd, scale, weight, &mut ds, &mut rl);
    for r in 0..5 {
        let (s0, s1) = (b.offsets[r] as usize, b.offsets[r + 1] as usize);
        let w = &fwd.weights[s0..s1];
        let s: Vec<f64> = b.t[s0..s1].iter().map(|t| scale * t).collect();
        let mut want = 0.0;
        for i in 0..w.len() {
            for j in 0..w.len() {
                want += w[i] * w[j] * (s[i] - s[j]).abs();
            }
            want += w[i] * w[i] * scale * b.dt[s0 + i] / 3.0;
        }
        assert!((rl[r] - weight * want).abs() < 1e-12 * (1.0 + want), "ray {r}: {} vs {}", rl[r], weight * want);
    }
    assert!((total - rl.iter().sum::<f64>()).abs() < 1e-12);
    assert_eq!(rl[0], 0.0, "a ray without samples");
    assert!(rl[3] > 0.0 && rl[4] > 0.0);
}

#[test]
fn the_sigma_gradient_matches_finite_differences_in_f64() {
    let b = batch(&[0, 1, 2, 9, 30, 64], 6.0, 11);
    let (scale, weight) = (0.3, 1.9);
    let fwd = forward(&b, &b.sigma, 0.0);
    // The gradient is added to what d_sigma holds.
    let mut g = nerf_core::rng(5, 9);
    let start: Vec<f64> = (0..b.sigma.len()).map(|_| g.gen::<f64>() - 0.5).collect();
    let mut ds = start.clone();
    let mut rl = vec![0.0; 6];
    distortion_loss_grad(&b.offsets, &b.sigma, &b.dt, &b.t, &fwd, scale, weight, &mut ds, &mut rl);
    // Central differences in f64: truncation O(h²), rounding ~ε·L/h (L ~ 10 here: ~1e-9).
    let h = 1e-6;
    let mut worst = 0.0f64;
    for k in 0..b.sigma.len() {
        let (mut p, mut m) = (b.sigma.clone(), b.sigma.clone());
        p[k] += h;
        m[k] = (m[k] - h).max(0.0);
        let fd = (loss(&b, &p, scale, weight, 0.0) - loss(&b, &m, scale, weight, 0.0)) / (p[k] - m[k]);
        let got = ds[k] - start[k];
        let err = (got - fd).abs();
        worst = worst.max(err / (1e-9 + fd.abs()));
        assert!(err < 1e-5 * fd.abs().max(got.abs()) + 1e-8, "sample {k}: analytic {got:.9e}, finite differences {fd:.9e}");
    }
    let largest = ds.iter().zip(&start).map(|(d, s)| (d - s).abs()).fold(0.0, f64::max);
    assert!(largest > 1e-2, "a gradient this small checks nothing: {largest}");
    eprintln!("worst relative error {worst:.2e}, largest gradient {largest:.3}");
}

#[test]
fn samples_past_the_early_stop_get_no_gradient_and_no_loss() {
    // One dense ray: compositing stops once the transmittance falls below the threshold.
    let b = batch(&[48], 40.0, 21);
    let thr = 1e-3;
    let fwd = forward(&b, &b.sigma, thr);
    let mut ds = vec![0.0; 48];
    let mut rl = vec![0.0; 1];
    distortion_loss_grad(&b.offsets, &b.sigma, &b.dt, &b.t, &fwd, 0.5, 1.0, &mut ds, &mut rl);
    let stop = fwd.weights.iter().rposition(|&w| w > 0.0).unwrap() + 1;
    assert!(stop < 40, "the ray should stop early (at {stop})");
    assert!(ds[stop + 1..].iter().all(|&d| d == 0.0), "gradient past the stop");
    // The loss is that of the ray cut at the stop (compositing's weights are zero past it).
    let cut = Batch { offsets: vec![0, stop as u32 + 1], sigma: b.sigma[..=stop].to_vec(), rgb: b.rgb[..3 * (stop + 1)].to_vec(), dt: b.dt[..=stop].to_vec(), t: b.t[..=stop].to_vec() };
    assert!((loss(&cut, &cut.sigma, 0.5, 1.0, thr) - rl[0]).abs() < 1e-12);
    // Past the stop, changing σ changes nothing.
    let mut moved = b.sigma.clone();
    moved[stop + 3] += 5.0;
    assert_eq!(loss(&b, &moved, 0.5, 1.0, thr), rl[0]);
}

#[test]
fn weight_in_one_place_costs_less_than_weight_spread_out() {
    // Same total weight (opacity ~0.95), once in one short interval, once split in two far apart.
    let one = Batch { offsets: vec![0, 3], sigma: vec![0.0, 30.0, 0.0], rgb: vec![0.5; 9], dt: vec![0.1; 3], t: vec![2.0, 2.5, 3.0] };
    let split = Batch { offsets: vec![0, 3], sigma: vec![7.74, 0.0, 30.0], rgb: vec![0.5; 9], dt: vec![0.1; 3], t: vec![2.0, 2.5, 3.0] };
    let op = |b: &Batch| forward(b, &b.sigma, 0.0).opacity[0];
    assert!((op(&one) - op(&split)).abs() < 0.05, "{} vs {}", op(&one), op(&split));
    let (a, c) = (loss(&one, &one.sigma, 1.0, 1.0, 0.0), loss(&split, &split.sigma, 1.0, 1.0, 0.0));
    assert!(c > 5.0 * a, "concentrated {a}, split {c}");
}
