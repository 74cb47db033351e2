#![allow(clippy::needless_range_loop)]
//! Training on compacted samples: `composited_counts` finds exactly where compositing stops, and
//! the compacted batch (`RaySamples::compact_into`) composites to the same colours, opacities,
//! depths and gradients as the full one.

use nerf_render::{composite_backward, composite_forward, composited_counts, CompositeOutputs};
use nerf_sampling::{stratified, RaySamples};
use rand::Rng;

/// Stratified samples of random rays, with densities that make about half the rays opaque early.
fn batch(n_rays: usize, n_per_ray: usize, seed: u64) -> (RaySamples, Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut g = nerf_core::rng(seed, 7);
    let mut o = Vec::new();
    let mut d = Vec::new();
    for _ in 0..n_rays {
        o.extend([g.gen_range(-1.0f32..1.0), g.gen_range(-1.0f32..1.0), -3.0]);
        let v = [g.gen_range(-0.3f32..0.3), g.gen_range(-0.3f32..0.3), 1.0];
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        d.extend(v.map(|x| x / l));
    }
    let near = vec![1.0; n_rays];
    let far = vec![5.0; n_rays];
    let mut s = RaySamples::default();
    // Some rays get no samples: stratified with n_per_ray, then drop a few rays' samples by
    // compacting with zero counts (exercises empty rays in the source too).
    stratified(&o, &d, &near, &far, n_per_ray, Some(&mut g), &mut s);
    let keep: Vec<u32> = (0..n_rays).map(|r| if r % 7 == 3 { 0 } else { n_per_ray as u32 }).collect();
    let mut src = RaySamples::default();
    s.compact_into(&keep, usize::MAX, &mut src);
    let n = src.len();
    let sigma: Vec<f32> = (0..n)
        .map(|k| {
            let r = src.ray_indices[k] as usize;
            // Ray-dependent scale: transparent rays, rays that turn opaque mid-way, opaque early.
            let scale = [0.0f32, 0.5, 4.0, 40.0][r % 4];
            scale * g.gen::<f32>()
        })
        .collect();
    let rgb: Vec<f32> = (0..3 * n).map(|_| g.gen::<f32>()).collect();
    let bg: Vec<f32> = (0..3 * n_rays).map(|_| g.gen::<f32>()).collect();
    (src, sigma, rgb, bg)
}

fn composite(s: &RaySamples, sigma: &[f32], rgb: &[f32], bg: &[f32], thr: f32) -> CompositeOutputs<f32> {
    let mut out = CompositeOutputs::default();
    composite_forward(&s.ray_offsets, sigma, rgb, &s.dt, &s.t, Some(bg), thr, &mut out);
    out
}

#[test]
fn counts_stop_where_compositing_stops() {
    for (seed, thr) in [(1u64, 1e-4f32), (2, 1e-2), (3, 0.5), (4, 0.0)] {
        let (s, sigma, rgb, bg) = batch(301, 48, seed);
        let comp = composite(&s, &sigma, &rgb, &bg, thr);
        let mut counts = vec![u32::MAX; 5];
        composited_counts(&s.ray_offsets, &sigma, &s.dt, thr, &mut counts);
        assert_eq!(counts.len(), s.n_rays);
        let (mut cut_rays, mut kept) = (0, 0);
        for r in 0..s.n_rays {
            let range = s.ray_range(r);
            let c = counts[r] as usize;
            assert!(c <= range.len(), "ray {r}: count {c} > {} samples", range.len());
            kept += c;
            if thr == 0.0 {
                assert_eq!(c, range.len(), "threshold 0 never stops");
                continue;
            }
            // The transmittance before sample c is below the threshold (or the ray ended), and
            // before every earlier sample it was not.
            let mut trans = 1.0f32;
            for k in range.start..range.start + c {
                assert!(trans >= thr, "ray {r}: sample {k} is past the stop");
                trans *= (-sigma[k] * s.dt[k]).exp();
            }
            if c < range.len() {
                cut_rays += 1;
                assert!(trans < thr * 1.0001, "ray {r} stopped at {c} with T = {trans}");
                assert!(comp.weights[range.start + c..range.end].iter().all(|&w| w == 0.0));
            }
        }
        if thr > 0.0 {
            assert!(cut_rays > 20 && kept < s.len(), "the batch must exercise early stops ({cut_rays} rays cut)");
        }
    }
}

#[test]
fn compacted_samples_composite_and_backpropagate_the_same() {
    let thr = 1e-3f32;
    let (s, sigma, rgb, bg) = batch(257, 64, 11);
    let full = composite(&s, &sigma, &rgb, &bg, thr);
    let mut counts = Vec::new();
    composited_counts(&s.ray_offsets, &sigma, &s.dt, thr, &mut counts);
    let mut c = RaySamples::default();
    s.compact_into(&counts, usize::MAX, &mut c);
    assert!(c.len() < s.len() * 3 / 4, "compaction keeps {} of {}", c.len(), s.len());
    // Gather the per-sample values the field would return on the compacted positions.
    let mut cs = Vec::new();
    let mut crgb = Vec::new();
    for r in 0..s.n_rays {
        let src = s.ray_range(r);
        assert_eq!(c.ray_len(r), counts[r] as usize);
        for (j, k) in c.ray_range(r).zip(src.clone()) {
            assert_eq!(c.ray_indices[j] as usize, r);
            assert_eq!((c.t[j], c.dt[j]), (s.t[k], s.dt[k]));
            assert_eq!(c.positions[3 * j..3 * j + 3], s.positions[3 * k..3 * k + 3]);
            assert_eq!(c.dirs[3 * j..3 * j + 3], s.dirs[3 * k..3 * k + 3]);
            cs.push(sigma[k]);
            crgb.extend_from_slice(&rgb[3 * k..3 * k + 3]);
        }
    }
    let part = composite(&c, &cs, &crgb, &bg, thr);
    assert_eq!(part.rgb, full.rgb);
    assert_eq!(part.opacity, full.opacity);
    assert_eq!(part.depth, full.depth);
    // Gradients: the compacted samples get those of the full batch; the dropped ones got zero.
    let mut g = nerf_core::rng(5, 0);
    let d_rgb: Vec<f32> = (0..3 * s.n_rays).map(|_| g.gen_range(-1.0f32..1.0)).collect();
    let grads = |s: &RaySamples, sigma: &[f32], rgb: &[f32], comp: &CompositeOutputs<f32>| {
        let (mut ds, mut dc) = (vec![0.0; s.len()], vec![0.0; 3 * s.len()]);
        composite_backward(&s.ray_offsets, sigma, rgb, &s.dt, &s.t, Some(&bg), comp, &d_rgb, None, None, &mut ds, &mut dc);
        (ds, dc)
    };
    let (fs, fc) = grads(&s, &sigma, &rgb, &full);
    let (ps, pc) = grads(&c, &cs, &crgb, &part);
    for r in 0..s.n_rays {
        let src = s.ray_range(r);
        let kept = src.start..src.start + counts[r] as usize;
        for (j, k) in c.ray_range(r).zip(kept.clone()) {
            assert!((ps[j] - fs[k]).abs() <= 1e-6 * (1.0 + fs[k].abs()), "dσ ray {r}: {} vs {}", ps[j], fs[k]);
            assert_eq!(pc[3 * j..3 * j + 3], fc[3 * k..3 * k + 3]);
        }
        for k in kept.end..src.end {
            assert_eq!((fs[k], fc[3 * k]), (0.0, 0.0), "a dropped sample had a gradient");
        }
    }
}

#[test]
fn compaction_clips_at_the_capacity() {
    let (s, _, _, _) = batch(40, 16, 3);
    let keep: Vec<u32> = (0..s.n_rays as u32).map(|r| (r * 5) % 23).collect(); // some > ray length
    let want: Vec<usize> = (0..s.n_rays).map(|r| (keep[r] as usize).min(s.ray_len(r))).collect();
    let total: usize = want.iter().sum();
    let cap = total / 2 + 3;
    let mut c = RaySamples::default();
    s.compact_into(&keep, cap, &mut c);
    assert_eq!(c.len(), cap);
    assert_eq!(c.n_rays, s.n_rays);
    let mut acc = 0usize;
    for r in 0..s.n_rays {
        let start = acc.min(cap);
        acc += want[r];
        assert_eq!(c.ray_range(r), start..acc.min(cap), "ray {r}");
        for (j, k) in c.ray_range(r).zip(s.ray_range(r)) {
            assert_eq!(c.t[j], s.t[k]);
        }
    }
    // The rows of the kept samples in the source batch (what a field gathers its kept values by).
    let mut rows = vec![7u32; 3];
    nerf_sampling::compacted_rows(&s.ray_offsets, &c.ray_offsets, &mut rows);
    assert_eq!(rows.len(), cap);
    for (j, &k) in rows.iter().enumerate() {
        assert_eq!(c.positions[3 * j..3 * j + 3], s.positions[3 * k as usize..3 * k as usize + 3], "row {j} ← {k}");
        assert_eq!((c.t[j], c.ray_indices[j]), (s.t[k as usize], s.ray_indices[k as usize]), "row {j} ← {k}");
    }
    // Everything kept when it fits; a second compaction reuses the output's allocations.
    s.compact_into(&keep, usize::MAX, &mut c);
    assert_eq!(c.len(), total);
}
