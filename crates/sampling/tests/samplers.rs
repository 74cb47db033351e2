#![allow(clippy::needless_range_loop)]
//! Stratified and hierarchical sampling: layout invariants, intervals, determinism, statistics.

use nerf_render::{composite_forward, CompositeOutputs};
use nerf_sampling::{hierarchical, sample_pdf, stratified, RaySamples};
use rand::Rng;

/// Random rays with unit directions and per-ray [near, far].
fn rays(n: usize, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut g = nerf_core::rng(seed, 100);
    let (mut o, mut d, mut near, mut far) = (vec![], vec![], vec![], vec![]);
    for _ in 0..n {
        let v: [f32; 3] = [
            g.gen::<f32>() - 0.5,
            g.gen::<f32>() - 0.5,
            g.gen::<f32>() - 0.5,
        ];
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
        d.extend(v.iter().map(|x| x / l));
        o.extend((0..3).map(|_| g.gen::<f32>() * 2.0 - 1.0));
        let a = 1.0 + g.gen::<f32>();
        near.push(a);
        far.push(a + 0.5 + 4.0 * g.gen::<f32>());
    }
    (o, d, near, far)
}

/// Layout invariants every sampler output must satisfy; `far` gives the last interval.
fn check_layout(s: &RaySamples, origins: &[f32], dirs: &[f32], far: &[f32]) {
    let n = s.len();
    assert_eq!(s.ray_offsets.len(), s.n_rays + 1);
    assert_eq!(s.ray_offsets[0], 0);
    assert_eq!(*s.ray_offsets.last().unwrap() as usize, n);
    assert_eq!(
        (
            s.positions.len(),
            s.dirs.len(),
            s.dt.len(),
            s.ray_indices.len()
        ),
        (3 * n, 3 * n, n, n)
    );
    for r in 0..s.n_rays {
        let range = s.ray_range(r);
        for k in range.clone() {
            assert_eq!(s.ray_indices[k] as usize, r);
            let last = k + 1 == range.end;
            if !last {
                assert!(s.t[k] <= s.t[k + 1], "ray {r} not sorted at {k}");
            }
            let want_dt = if last {
                far[r] - s.t[k]
            } else {
                s.t[k + 1] - s.t[k]
            };
            assert!(
                (s.dt[k] - want_dt).abs() <= 1e-6,
                "δ[{k}] = {} want {want_dt}",
                s.dt[k]
            );
            for c in 0..3 {
                let p = origins[3 * r + c] + s.t[k] * dirs[3 * r + c];
                assert!((s.positions[3 * k + c] - p).abs() <= 1e-5);
                assert_eq!(s.dirs[3 * k + c], dirs[3 * r + c]);
            }
        }
        if !range.is_empty() {
            let sum: f64 = s.dt[range.clone()].iter().map(|&x| x as f64).sum();
            assert!(
                (sum - (far[r] - s.t[range.start]) as f64).abs() < 1e-4,
                "Σδ of ray {r}"
            );
        }
    }
}

#[test]
fn stratified_deterministic_bin_centres() {
    let (o, d, near, far) = rays(50, 1);
    let mut s = RaySamples::default();
    stratified(&o, &d, &near, &far, 8, None, &mut s);
    assert_eq!(s.len(), 50 * 8);
    check_layout(&s, &o, &d, &far);
    for r in 0..50 {
        let step = (far[r] - near[r]) / 8.0;
        for (i, k) in s.ray_range(r).enumerate() {
            assert!((s.t[k] - (near[r] + (i as f32 + 0.5) * step)).abs() < 1e-5);
            let want = if i < 7 { step } else { 0.5 * step };
            assert!((s.dt[k] - want).abs() < 1e-5);
        }
    }
}

#[test]
fn stratified_jitter_stays_in_bins_and_is_uniform() {
    let (o, d, near, far) = rays(400, 2);
    let mut s = RaySamples::default();
    let mut g = nerf_core::rng(5, 0);
    stratified(&o, &d, &near, &far, 32, Some(&mut g), &mut s);
    check_layout(&s, &o, &d, &far);
    // Position within its bin, in [0, 1]: must stay inside and be ~U[0,1).
    let mut frac = vec![];
    for r in 0..400 {
        let step = (far[r] - near[r]) / 32.0;
        for (i, k) in s.ray_range(r).enumerate() {
            let (lo, hi) = (near[r] + i as f32 * step, near[r] + (i + 1) as f32 * step);
            assert!(
                s.t[k] >= lo - 1e-5 && s.t[k] <= hi + 1e-5,
                "sample outside its bin"
            );
            frac.push(((s.t[k] - lo) / step).clamp(0.0, 1.0) as f64);
        }
    }
    frac.sort_by(f64::total_cmp);
    let n = frac.len() as f64;
    let ks = frac
        .iter()
        .enumerate()
        .map(|(i, &x)| ((i + 1) as f64 / n - x).max(x - i as f64 / n))
        .fold(0.0, f64::max);
    let bound = ((2.0f64 / 1e-6).ln() / (2.0 * n)).sqrt(); // DKW, α = 1e-6
    assert!(ks < bound, "jitter not uniform: KS {ks} ≥ {bound}");
    // Same generator state ⇒ same samples; the generator advanced ⇒ different samples.
    let mut s2 = RaySamples::default();
    stratified(
        &o,
        &d,
        &near,
        &far,
        32,
        Some(&mut nerf_core::rng(5, 0)),
        &mut s2,
    );
    assert_eq!(s.t, s2.t);
    stratified(&o, &d, &near, &far, 32, Some(&mut g), &mut s2);
    assert_ne!(s.t, s2.t);
}

#[test]
fn stratified_skips_missed_rays() {
    let o = vec![0.0f32; 12];
    let d: Vec<f32> = (0..4).flat_map(|_| [1.0, 0.0, 0.0]).collect();
    let near = [2.0, 3.0, f32::NAN, 1.0];
    let far = [6.0, 3.0, 5.0, 0.5];
    let mut s = RaySamples::default();
    stratified(&o, &d, &near, &far, 4, None, &mut s);
    // Inverted and NaN bounds: no samples; an empty segment (a clipped miss): four of length 0.
    assert_eq!(s.ray_offsets, vec![0, 4, 8, 8, 8]);
    assert!(s.t[..4].iter().all(|&t| (2.0..6.0).contains(&t)));
    assert!(s.t[4..8].iter().all(|&t| t == 3.0) && s.dt[4..8].iter().all(|&dt| dt == 0.0));
    check_layout(&s, &o, &d, &far);
}

/// Results must not depend on the number of rayon threads, and a reused output equals a fresh one.
#[test]
fn results_independent_of_thread_count_and_reuse() {
    let (o, d, near, far) = rays(3000, 3);
    let run = |threads: usize, out: &mut RaySamples, fine: &mut RaySamples| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut g = nerf_core::rng(9, 0);
            stratified(&o, &d, &near, &far, 64, Some(&mut g), out);
            let w: Vec<f32> = out.t.iter().map(|t| (t * 7.0).sin().abs()).collect();
            hierarchical(out, &w, &o, &d, &far, 32, Some(&mut g), fine);
        });
    };
    let (mut a, mut fa) = (RaySamples::default(), RaySamples::default());
    run(1, &mut a, &mut fa);
    assert_eq!(fa.len(), 3000 * 96);
    // Reuse outputs that previously held a different (smaller) batch.
    let (mut b, mut fb) = (RaySamples::default(), RaySamples::default());
    stratified(&o[..30], &d[..30], &near[..10], &far[..10], 5, None, &mut b);
    hierarchical(
        &b.clone(),
        &vec![0.5; b.len()],
        &o[..30],
        &d[..30],
        &far[..10],
        3,
        None,
        &mut fb,
    );
    run(4, &mut b, &mut fb);
    for (x, y) in [(&a, &b), (&fa, &fb)] {
        assert_eq!(x.n_rays, y.n_rays);
        assert_eq!(x.ray_offsets, y.ray_offsets);
        assert_eq!(x.t, y.t);
        assert_eq!(x.dt, y.dt);
        assert_eq!(x.positions, y.positions);
        assert_eq!(x.dirs, y.dirs);
        assert_eq!(x.ray_indices, y.ray_indices);
    }
    check_layout(&fa, &o, &d, &far);
}

#[test]
fn fill_geometry_rebuilds_positions() {
    let (o, d, near, far) = rays(20, 4);
    let mut s = RaySamples::default();
    stratified(
        &o,
        &d,
        &near,
        &far,
        7,
        Some(&mut nerf_core::rng(1, 1)),
        &mut s,
    );
    let (pos, dirs) = (s.positions.clone(), s.dirs.clone());
    s.positions.clear();
    s.dirs = vec![9.0; 5];
    s.fill_geometry(&o, &d);
    assert_eq!(s.positions, pos);
    assert_eq!(s.dirs, dirs);
    s.clear();
    assert!(s.is_empty() && s.n_rays == 0 && s.ray_offsets == vec![0]);
}

/// `backward_to_rays` is the gradient of `fill_geometry` (t fixed) in the rays' origins and
/// directions: L = Σ a·x + Σ b·d against central differences (in f64 over the f32 positions),
/// on a batch where some rays kept no samples; it accumulates onto what is there.
#[test]
fn backward_to_rays_matches_finite_differences() {
    let n_rays = 300; // more than one parallel chunk
    let (o, d, near, far) = rays(n_rays, 5);
    let mut full = RaySamples::default();
    stratified(&o, &d, &near, &far, 6, Some(&mut nerf_core::rng(2, 1)), &mut full);
    let keep: Vec<u32> = (0..n_rays as u32).map(|r| r % 7).collect(); // ray 0, 7, … keep none
    let mut s = RaySamples::default();
    full.compact_into(&keep, usize::MAX, &mut s);
    let n = s.len();
    let mut g = nerf_core::rng(3, 1);
    let a: Vec<f32> = (0..3 * n).map(|_| g.gen::<f32>() - 0.5).collect();
    let b: Vec<f32> = (0..3 * n).map(|_| g.gen::<f32>() - 0.5).collect();
    let loss = |o: &[f32], d: &[f32]| {
        let mut s = s.clone();
        s.fill_geometry(o, d);
        let x: f64 = s.positions.iter().zip(&a).map(|(p, w)| *p as f64 * *w as f64).sum();
        x + s.dirs.iter().zip(&b).map(|(p, w)| *p as f64 * *w as f64).sum::<f64>()
    };
    let (mut go, mut gd) = (vec![1.0f32; 3 * n_rays], vec![-1.0f32; 3 * n_rays]);
    s.backward_to_rays(&a, &b, &mut go, &mut gd);
    let h = 1e-2;
    for r in (0..n_rays).step_by(13).chain([0, 7, n_rays - 1]) {
        for c in 0..3 {
            let i = 3 * r + c;
            for (dir, grad, base) in [(false, go[i], 1.0), (true, gd[i], -1.0)] {
                let (mut op, mut om, mut dp, mut dm) = (o.clone(), o.clone(), d.clone(), d.clone());
                if dir {
                    dp[i] += h;
                    dm[i] -= h;
                } else {
                    op[i] += h;
                    om[i] -= h;
                }
                let fd = (loss(&op, &dp) - loss(&om, &dm)) / (2.0 * h as f64);
                let an = (grad - base) as f64;
                assert!((an - fd).abs() < 2e-3 * (1.0 + fd.abs()), "ray {r} {} [{c}]: {an} vs fd {fd}", if dir { "d" } else { "o" });
                if r % 7 == 0 {
                    assert_eq!(an, 0.0, "a ray without samples gets no gradient");
                }
            }
        }
    }
}

/// Expected CDF of `sample_pdf`'s piecewise-uniform density (with its `+1e-5` weight floor).
fn pdf_cdf(bins: &[f64], weights: &[f64], x: f64) -> f64 {
    let w: Vec<f64> = weights.iter().map(|w| w + 1e-5).collect();
    let total: f64 = w.iter().sum();
    let mut c = 0.0;
    for i in 0..w.len() {
        if x >= bins[i + 1] {
            c += w[i] / total;
        } else if x > bins[i] {
            c += w[i] / total * (x - bins[i]) / (bins[i + 1] - bins[i]);
        }
    }
    c
}

/// Kolmogorov–Smirnov distance of sorted samples to a CDF.
fn ks(sorted: &[f64], cdf: impl Fn(f64) -> f64) -> f64 {
    let n = sorted.len() as f64;
    sorted
        .iter()
        .enumerate()
        .map(|(i, &x)| ((i + 1) as f64 / n - cdf(x)).max(cdf(x) - i as f64 / n))
        .fold(0.0, f64::max)
}

/// DKW bound: P(KS > ε) ≤ 2 exp(−2 n ε²); α = 1e-6.
fn dkw(n: usize) -> f64 {
    ((2.0f64 / 1e-6).ln() / (2.0 * n as f64)).sqrt()
}

#[test]
fn sample_pdf_iid_u_follows_the_histogram() {
    let bins = [2.0, 2.5, 3.0, 4.0, 4.2, 5.0, 6.0];
    let weights = [0.1, 0.0, 0.5, 2.0, 0.3, 1.0];
    let mut g = nerf_core::rng(17, 0);
    let n = 20_000;
    let u: Vec<f64> = (0..n).map(|_| g.gen()).collect();
    let mut x = vec![0.0; n];
    sample_pdf(&bins, &weights, &u, &mut x);
    x.sort_by(f64::total_cmp);
    let d = ks(&x, |v| pdf_cdf(&bins, &weights, v));
    assert!(d < dkw(n), "KS {d} ≥ {}", dkw(n));
    // Power: the same samples are far from a uniform density on [2, 6].
    assert!(ks(&x, |v| ((v - 2.0) / 4.0).clamp(0.0, 1.0)) > 5.0 * dkw(n));
    // No mass in the zero-weight bin (beyond the 1e-5 floor).
    let in_empty = x.iter().filter(|&&v| v > 2.5 && v < 3.0).count();
    assert!(in_empty < 5, "{in_empty} samples in a zero-weight bin");
}

/// Hierarchical fine samples follow the pdf of the coarse weights (first and last dropped), each
/// ray's samples are stratified, and the pooled samples pass a KS test.
#[test]
fn hierarchical_samples_follow_the_coarse_pdf() {
    let n_rays = 2000;
    let n_fine = 16;
    let ct: [f32; 9] = [2.0, 2.3, 2.9, 3.2, 3.8, 4.1, 4.9, 5.4, 5.8];
    let cw: [f32; 9] = [5.0, 0.05, 0.6, 0.0, 0.3, 1.2, 0.1, 0.4, 5.0];
    let mut coarse = RaySamples {
        n_rays,
        ..Default::default()
    };
    coarse.ray_offsets.push(0);
    for r in 0..n_rays {
        coarse.t.extend(ct);
        coarse.ray_indices.extend([r as u32; 9]);
        coarse.ray_offsets.push(coarse.t.len() as u32);
    }
    coarse.dt = vec![0.0; coarse.t.len()];
    let weights: Vec<f32> = (0..n_rays).flat_map(|_| cw).collect();
    let origins = vec![0.0f32; 3 * n_rays];
    let dirs: Vec<f32> = (0..n_rays).flat_map(|_| [0.0, 1.0, 0.0]).collect();
    let far = vec![6.0f32; n_rays];
    let mut out = RaySamples::default();
    hierarchical(
        &coarse,
        &weights,
        &origins,
        &dirs,
        &far,
        n_fine,
        Some(&mut nerf_core::rng(23, 0)),
        &mut out,
    );
    check_layout(&out, &origins, &dirs, &far);

    let bins: Vec<f64> = (0..8)
        .map(|i| 0.5 * (ct[i] as f64 + ct[i + 1] as f64))
        .collect();
    let wp: Vec<f64> = cw[1..8].iter().map(|&w| w as f64).collect();
    let cdf = |x: f64| pdf_cdf(&bins, &wp, x);
    let mut pooled = Vec::with_capacity(n_rays * n_fine);
    for r in 0..n_rays {
        let range = out.ray_range(r);
        assert_eq!(range.len(), 9 + n_fine);
        // Split the merged ray back into coarse and fine samples.
        let mut fine = vec![];
        let mut j = 0;
        for &t in &out.t[range] {
            if j < 9 && t == ct[j] {
                j += 1;
            } else {
                fine.push(t as f64);
            }
        }
        assert_eq!(
            (j, fine.len()),
            (9, n_fine),
            "ray {r}: coarse samples must all be kept"
        );
        // Stratified u: the k-th fine sample has F(x_k) in [k/n, (k+1)/n].
        for (k, &x) in fine.iter().enumerate() {
            let f = cdf(x);
            assert!(
                f >= k as f64 / n_fine as f64 - 1e-4 && f <= (k + 1) as f64 / n_fine as f64 + 1e-4,
                "ray {r}: F(x_{k}) = {f}"
            );
        }
        pooled.extend(fine);
    }
    pooled.sort_by(f64::total_cmp);
    let n = pooled.len();
    let d = ks(&pooled, cdf);
    assert!(d < dkw(n), "KS {d} ≥ {}", dkw(n));
    // Power: using all coarse weights except the last (an off-by-one) is rejected clearly.
    let wrong: Vec<f64> = cw[0..7].iter().map(|&w| w as f64).collect();
    assert!(ks(&pooled, |x| pdf_cdf(&bins, &wrong, x)) > 5.0 * dkw(n));
}

#[test]
fn hierarchical_counts_and_short_rays() {
    // Rays with 0, 1, 2 coarse samples keep them; rays with ≥ 3 get n_fine more.
    let counts = [0usize, 1, 2, 3, 10];
    let mut coarse = RaySamples {
        n_rays: counts.len(),
        ..Default::default()
    };
    coarse.ray_offsets.push(0);
    for (r, &c) in counts.iter().enumerate() {
        for i in 0..c {
            coarse.t.push(2.0 + 0.3 * i as f32);
            coarse.ray_indices.push(r as u32);
        }
        coarse.ray_offsets.push(coarse.t.len() as u32);
    }
    coarse.dt = vec![0.3; coarse.t.len()];
    let n_rays = counts.len();
    let (o, d) = (
        vec![0.5f32; 3 * n_rays],
        (0..n_rays)
            .flat_map(|_| [0.0f32, 0.0, 1.0])
            .collect::<Vec<_>>(),
    );
    let far = vec![5.5f32; n_rays];
    let w: Vec<f32> = (0..coarse.len()).map(|k| 0.1 + (k % 3) as f32).collect();
    let mut out = RaySamples::default();
    hierarchical(
        &coarse,
        &w,
        &o,
        &d,
        &far,
        5,
        Some(&mut nerf_core::rng(1, 2)),
        &mut out,
    );
    assert_eq!(out.ray_offsets, vec![0, 0, 1, 3, 11, 26]);
    check_layout(&out, &o, &d, &far);
    for r in 0..n_rays {
        let (cr, or) = (coarse.ray_range(r), out.ray_range(r));
        if counts[r] >= 3 {
            // Fine samples lie between the first and last bin edge (coarse midpoints).
            let (lo, hi) = (
                0.5 * (coarse.t[cr.start] + coarse.t[cr.start + 1]),
                0.5 * (coarse.t[cr.end - 2] + coarse.t[cr.end - 1]),
            );
            let inner = out.t[or.clone()]
                .iter()
                .filter(|&&t| t >= lo && t <= hi)
                .count();
            assert!(inner >= 5);
        } else {
            assert_eq!(out.t[or], coarse.t[cr]);
        }
    }
}

/// End to end with nerf-render: coarse weights of a density blob concentrate the fine samples.
#[test]
fn fine_samples_concentrate_where_the_coarse_weights_are() {
    let n_rays = 64;
    let (o, d, _, _) = rays(n_rays, 8);
    let (near, far) = (vec![2.0f32; n_rays], vec![6.0f32; n_rays]);
    let mut coarse = RaySamples::default();
    let mut g = nerf_core::rng(4, 4);
    stratified(&o, &d, &near, &far, 64, Some(&mut g), &mut coarse);
    // A thin shell of density at t ∈ [4.0, 4.3] along every ray.
    let sigma: Vec<f32> = coarse
        .t
        .iter()
        .map(|&t| if (4.0..4.3).contains(&t) { 8.0 } else { 0.01 })
        .collect();
    let rgb = vec![0.5f32; 3 * coarse.len()];
    let mut comp = CompositeOutputs::new();
    composite_forward(
        &coarse.ray_offsets,
        &sigma,
        &rgb,
        &coarse.dt,
        &coarse.t,
        None,
        0.0,
        &mut comp,
    );
    let mut fine = RaySamples::default();
    hierarchical(
        &coarse,
        &comp.weights,
        &o,
        &d,
        &far,
        128,
        Some(&mut g),
        &mut fine,
    );
    check_layout(&fine, &o, &d, &far);
    let frac = |s: &RaySamples| {
        s.t.iter().filter(|&&t| (3.9..4.4).contains(&t)).count() as f64 / s.len() as f64
    };
    let (fc, ff) = (frac(&coarse), frac(&fine));
    assert!(fc < 0.15, "coarse fraction {fc}");
    assert!(ff > 0.6, "fine fraction {ff} (coarse {fc})");
}

#[test]
fn clip_segments_intersects_near_far_with_the_box() {
    // Along +x from x = −3 through the box [−1, 1]³; along +x at y = 5 (a miss); from inside;
    // and one whose box exit lies beyond far.
    let o = [-3.0f32, 0.0, 0.0, -3.0, 5.0, 0.0, 0.5, 0.0, 0.0, -3.0, 0.0, 0.0];
    let d = [1.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0];
    let (mut near, mut far) = (vec![0.0; 4], vec![0.0; 4]);
    nerf_sampling::clip_segments([-1.0; 3], [1.0; 3], &o, &d, 0.5, 10.0, &mut near, &mut far);
    assert_eq!((near[0], far[0]), (2.0, 4.0));
    assert_eq!((near[1], far[1]), (0.5, 0.5), "a miss gets the empty segment at near");
    assert_eq!((near[2], far[2]), (0.5, 0.5), "from inside: near, then the exit at 0.5 is not past it");
    nerf_sampling::clip_segments([-1.0; 3], [1.0; 3], &o, &d, 0.0, 3.0, &mut near, &mut far);
    assert_eq!((near[2], far[2]), (0.0, 0.5));
    assert_eq!((near[3], far[3]), (2.0, 3.0), "far cuts the box segment");
}
