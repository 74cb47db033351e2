#![allow(clippy::needless_range_loop)]
//! Occupancy grid (fill, EMA updates, checkpoints) and ray marching with empty-space skipping.

use nerf_render::{composite_forward, CompositeOutputs};
use nerf_sampling::{march, OccupancyGrid, OccupancyGridConfig, RaySamples, Stepping, DENSITY_CHUNK, MAX_STEP_RATIO};
use rand::Rng;

const R: f32 = 0.5;

fn cfg(res: u32) -> OccupancyGridConfig {
    OccupancyGridConfig {
        resolution: res,
        ..Default::default()
    }
}

/// σ = `value` inside the ball of radius `radius` at the origin, 0 elsewhere.
fn ball(radius: f32, value: f32) -> impl FnMut(&[f32], &mut [f32]) {
    move |p: &[f32], s: &mut [f32]| {
        assert_eq!(p.len(), 3 * s.len());
        assert!(
            s.len() <= DENSITY_CHUNK,
            "density called with {} points",
            s.len()
        );
        for (i, s) in s.iter_mut().enumerate() {
            let r2 = p[3 * i].powi(2) + p[3 * i + 1].powi(2) + p[3 * i + 2].powi(2);
            *s = if r2 < radius * radius { value } else { 0.0 };
        }
    }
}

/// For every cell: (distance of its nearest point to the origin, distance of its centre).
fn cell_distances(g: &OccupancyGrid) -> Vec<(f64, f64)> {
    let res = g.resolution();
    let (lo, _) = g.aabb();
    let h = g.cell_size();
    let mut v = Vec::with_capacity(res * res * res);
    for k in 0..res {
        for j in 0..res {
            for i in 0..res {
                let ijk = [i, j, k];
                let (mut near2, mut c2) = (0f64, 0f64);
                for a in 0..3 {
                    let a0 = lo[a] as f64 + ijk[a] as f64 * h[a] as f64;
                    let a1 = a0 + h[a] as f64;
                    let nearest = 0f64.clamp(a0, a1);
                    near2 += nearest * nearest;
                    c2 += (0.5 * (a0 + a1)).powi(2);
                }
                v.push((near2.sqrt(), c2.sqrt()));
            }
        }
    }
    v
}

/// Checks the sphere classification; returns (#centre inside, #occupied, #cells touching the ball).
fn check_sphere(g: &OccupancyGrid) -> (usize, usize, usize) {
    let h = g.cell_size();
    let half_diag = 0.5 * ((h[0] * h[0] + h[1] * h[1] + h[2] * h[2]) as f64).sqrt();
    let (mut inside, mut occ, mut touching) = (0, 0, 0);
    for (idx, &(near, centre)) in cell_distances(g).iter().enumerate() {
        let o = g.is_cell_occupied(idx);
        occ += o as usize;
        if near > R as f64 + half_diag {
            assert!(!o, "cell {idx} entirely outside the ball is occupied");
        }
        if centre < R as f64 {
            inside += 1;
            assert!(o, "cell {idx} with its centre inside the ball is empty");
        }
        touching += (near < R as f64) as usize;
    }
    (inside, occ, touching)
}

fn ball_share() -> f64 {
    4.0 / 3.0 * std::f64::consts::PI * (R as f64).powi(3) / 27.0
}

#[test]
fn fill_from_marks_the_ball_and_only_the_ball() {
    let mut g = OccupancyGrid::new(cfg(32), [-1.5; 3], [1.5; 3]);
    assert_eq!(g.occupied_fraction(), 1.0, "a new grid is all occupied");
    let step = 3.0 * 3f32.sqrt() / 1024.0;
    g.fill_from(step, &mut ball(R, 50.0));
    let (inside, occ, _) = check_sphere(&g);
    // fill_from samples centres only: exactly the cells whose centre is inside.
    assert_eq!(occ, inside);
    let share = ball_share();
    let f = g.occupied_fraction() as f64;
    eprintln!("fill_from: occupied fraction {f:.5}, ball volume share {share:.5}");
    assert!(
        (f - share).abs() < 0.1 * share,
        "occupied fraction {f} vs ball volume share {share}"
    );
    assert!(g.is_occupied([0.0, 0.0, 0.0]));
    assert!(g.is_occupied([0.1, -0.2, 0.3]));
    assert!(!g.is_occupied([1.0, 1.0, 1.0]));
    assert!(!g.is_occupied([0.0, 0.0, 2.0]), "outside the box");
    assert!(!g.is_occupied([f32::NAN, 0.0, 0.0]));
    assert_eq!(g.step_size(), step);
}

#[test]
fn updates_past_warmup_mark_the_ball() {
    let c = cfg(32);
    let mut g = OccupancyGrid::new(c.clone(), [-1.5; 3], [1.5; 3]);
    let n = g.densities().len();
    let step = 3.0 * 3f32.sqrt() / 1024.0;
    let mut rng = nerf_core::rng(11, 0);
    let mut f = ball(R, 50.0);
    let n_updates = 2 * (c.warmup_steps / c.update_every) + 8;
    let mut updates = 0;
    for s in 0..n_updates * c.update_every {
        if !g.due(s) {
            continue;
        }
        updates += 1;
        let occ_before = (g.occupied_fraction() as f64 * n as f64).round() as usize;
        let mut calls = 0;
        let mut evaluated = 0;
        g.update(
            s,
            step,
            &mut |p: &[f32], out: &mut [f32]| {
                calls += 1;
                evaluated += out.len();
                f(p, out)
            },
            &mut rng,
        );
        let want = if s < c.warmup_steps {
            n
        } else {
            n / 4 + occ_before / 4
        };
        assert_eq!(evaluated, want, "points evaluated at step {s}");
        assert_eq!(calls, want.div_ceil(DENSITY_CHUNK));
    }
    assert_eq!(updates, n_updates);
    assert!(
        g.densities().iter().all(|d| d.is_finite()),
        "warm-up samples every cell"
    );
    let (inside, occ, touching) = check_sphere(&g);
    assert!(
        inside <= occ && occ <= touching,
        "{inside} <= {occ} <= {touching}"
    );
    let share = ball_share();
    let fr = g.occupied_fraction() as f64;
    eprintln!("updates: centre-inside {inside} <= occupied {occ} <= touching {touching}; fraction {fr:.5} vs share {share:.5}");
    assert!(
        fr > 0.9 * share && fr < 1.8 * share,
        "occupied fraction {fr} vs ball volume share {share}"
    );
}

#[test]
fn ema_decays_below_threshold_after_the_expected_number_of_updates() {
    // Left half (x < 0.5) keeps σ = 1000, so the mean opacity stays far above `threshold`
    // and the threshold in force is `threshold` itself. The right half starts at σ0 then drops to 0.
    let c = OccupancyGridConfig {
        resolution: 8,
        warmup_steps: 1_000_000,
        update_every: 1,
        ..Default::default()
    };
    let (sigma0, step) = (100.0f32, 0.01f32);
    let mut g = OccupancyGrid::new(c.clone(), [0.0; 3], [1.0; 3]);
    let mut rng = nerf_core::rng(5, 0);
    let mut phase_zero = false;
    let field = |p: &[f32], s: &mut [f32], zero: bool| {
        for i in 0..s.len() {
            s[i] = if p[3 * i] < 0.5 {
                1000.0
            } else if zero {
                0.0
            } else {
                sigma0
            };
        }
    };
    g.update(0, step, &mut |p, s| field(p, s, phase_zero), &mut rng);
    assert!(g.densities().iter().all(|&d| d == 1000.0 || d == sigma0));
    assert_eq!(g.occupied_fraction(), 1.0);
    // σ0·decay^k·step ≤ threshold  ⇔  k ≥ ln(threshold/(σ0·step))/ln(decay).
    let k_star = ((c.threshold as f64 / (sigma0 as f64 * step as f64)).ln() / (c.decay as f64).ln())
        .ceil() as usize;
    assert_eq!(k_star, 90, "σ0=100, step=0.01, threshold=0.01, decay=0.95");
    phase_zero = true;
    let right = |g: &OccupancyGrid| g.is_occupied([0.75, 0.5, 0.5]);
    for k in 1..=k_star + 2 {
        g.update(
            k as u64,
            step,
            &mut |p, s| field(p, s, phase_zero),
            &mut rng,
        );
        assert_eq!(
            right(&g),
            k < k_star,
            "after {k} zero updates (k* = {k_star})"
        );
        assert!(g.is_occupied([0.25, 0.5, 0.5]));
        let want = sigma0 as f64 * (c.decay as f64).powi(k as i32);
        let got = g.densities()[7] as f64; // cell (7,0,0): right half
        assert!((got - want).abs() <= 1e-4 * want, "k={k}: {got} vs {want}");
    }
    assert!((g.occupied_fraction() - 0.5).abs() < 1e-6);
}

#[test]
fn after_warmup_only_chosen_cells_decay() {
    let c = OccupancyGridConfig {
        resolution: 8,
        warmup_steps: 1,
        update_every: 1,
        ..Default::default()
    };
    let step = 0.01;
    let mut g = OccupancyGrid::new(c.clone(), [0.0; 3], [1.0; 3]);
    let mut rng = nerf_core::rng(6, 0);
    g.update(0, step, &mut |_, s| s.fill(100.0), &mut rng); // warm-up: every cell = 100
    assert!(g.densities().iter().all(|&d| d == 100.0));
    let mut decayed_total = 0usize;
    let rounds = 20;
    for s in 1..=rounds {
        let before = g.densities().to_vec();
        g.update(s, step, &mut |_, out| out.fill(0.0), &mut rng);
        let mut decayed = 0;
        for (b, a) in before.iter().zip(g.densities()) {
            if a != b {
                assert_eq!(*a, b * c.decay, "a chosen cell becomes max(decay·old, 0)");
                decayed += 1;
            }
        }
        decayed_total += decayed;
    }
    // All cells stay occupied (the mean decays with them), so each update draws n/4 + n/4 cells
    // with replacement: a cell is chosen with probability 1 − (1 − 1/n)^(n/2) ≈ 1 − e^(−1/2).
    let n = 512.0;
    let p = 1.0 - (1.0f64 - 1.0 / n).powf(n / 2.0);
    let frac = decayed_total as f64 / (rounds as f64 * n);
    let sd = (p * (1.0 - p) / (rounds as f64 * n)).sqrt();
    assert!((frac - p).abs() < 5.0 * sd, "chosen fraction {frac} vs {p}");
}

#[test]
fn due_config_and_checkpoints() {
    let c = cfg(16);
    let mut g = OccupancyGrid::new(c.clone(), [-1.0; 3], [1.0; 3]);
    assert!(g.due(0) && g.due(16) && g.due(32));
    assert!(!g.due(1) && !g.due(15) && !g.due(17));
    assert_eq!(g.config(), &c);

    let step = 2.0 * 3f32.sqrt() / 1024.0;
    assert_eq!(g.step_size(), step, "default step: diagonal / 1024");
    let mut rng = nerf_core::rng(1, 0);
    for s in 0..4 {
        g.update(s * 16, step, &mut ball(0.6, 20.0), &mut rng);
    }
    let saved = g.densities().to_vec();
    let mut h = OccupancyGrid::new(c.clone(), [-1.0; 3], [1.0; 3]);
    assert_eq!(h.occupied_fraction(), 1.0);
    h.set_densities(&saved, step).unwrap();
    assert_eq!(h.densities(), &saved[..]);
    assert_eq!(h.occupied_fraction(), g.occupied_fraction());
    assert!(h.occupied_fraction() > 0.0 && h.occupied_fraction() < 0.35);
    for i in 0..saved.len() {
        assert_eq!(h.is_cell_occupied(i), g.is_cell_occupied(i));
    }

    let e = h.set_densities(&saved[1..], step).unwrap_err();
    assert!(e.contains("4096") && e.contains("4095"), "{e}");
    let mut bad = saved.clone();
    bad[3] = f32::NAN;
    assert!(h.set_densities(&bad, step).unwrap_err().contains("cell 3"));
    bad[3] = -1.0;
    assert!(h.set_densities(&bad, step).is_err());
    assert_eq!(
        h.densities(),
        &saved[..],
        "a failed restore leaves the grid unchanged"
    );

    // Serde: defaults fill missing fields, unknown fields are rejected, round trip.
    let parsed: OccupancyGridConfig = serde_json::from_str(r#"{"resolution": 64}"#).unwrap();
    assert_eq!(
        parsed,
        OccupancyGridConfig {
            resolution: 64,
            ..Default::default()
        }
    );
    assert!(serde_json::from_str::<OccupancyGridConfig>(r#"{"resolutoin": 64}"#).is_err());
    let back: OccupancyGridConfig =
        serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
    assert_eq!(back, c);
    assert!(OccupancyGrid::try_new(cfg(0), [0.0; 3], [1.0; 3])
        .unwrap_err()
        .contains("resolution"));
    assert!(OccupancyGrid::try_new(c.clone(), [0.0; 3], [1.0, 0.0, 1.0])
        .unwrap_err()
        .contains("box"));
    let bad_decay = OccupancyGridConfig { decay: 1.5, ..c };
    assert!(bad_decay.validate().unwrap_err().contains("decay"));
}

/// Slab test in f64: (t_enter, t_exit).
fn slab64(o: &[f32], d: &[f32], lo: f32, hi: f32) -> (f64, f64) {
    let (mut a, mut b) = (f64::NEG_INFINITY, f64::INFINITY);
    for c in 0..3 {
        let (o, d) = (o[c] as f64, d[c] as f64);
        if d == 0.0 {
            if o < lo as f64 || o > hi as f64 {
                return (1.0, 0.0);
            }
        } else {
            let (x, y) = ((lo as f64 - o) / d, (hi as f64 - o) / d);
            a = a.max(x.min(y));
            b = b.min(x.max(y));
        }
    }
    (a, b)
}

/// Random rays, some starting inside the box, some missing it, some with far <= near.
fn random_rays(n: usize, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut g = nerf_core::rng(seed, 0);
    let (mut o, mut d, mut near, mut far) = (vec![], vec![], vec![], vec![]);
    for i in 0..n {
        let v: [f32; 3] = std::array::from_fn(|_| g.gen::<f32>() - 0.5);
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
        let mut dir: [f32; 3] = std::array::from_fn(|a| v[a] / l);
        if i % 17 == 0 {
            dir = [0.0, 0.0, 1.0]; // axis-aligned (zero components)
        }
        d.extend(dir);
        let scale = if i % 3 == 0 { 1.0 } else { 4.0 };
        o.extend((0..3).map(|_| (g.gen::<f32>() * 2.0 - 1.0) * scale));
        let a = g.gen::<f32>() * 0.5;
        near.push(a);
        far.push(if i % 11 == 0 {
            a
        } else {
            a + 1.0 + 8.0 * g.gen::<f32>()
        });
    }
    (o, d, near, far)
}

#[test]
fn marched_samples_obey_the_layout_and_the_grid() {
    let mut g = OccupancyGrid::new(cfg(24), [-1.5; 3], [1.5; 3]);
    g.fill_from(0.01, &mut ball(0.9, 50.0));
    let (o, d, near, far) = random_rays(3000, 2);
    let step = 0.013;
    let mut s = RaySamples::default();
    let mut capped = RaySamples::default();
    for use_rng in [false, true] {
        let mut rng = nerf_core::rng(9, 0);
        let max_samples = 1000;
        march(
            &g,
            &o,
            &d,
            &near,
            &far,
            step,
            max_samples,
            use_rng.then_some(&mut rng),
            &mut s,
        );
        let mut rng = nerf_core::rng(9, 0);
        march(
            &g,
            &o,
            &d,
            &near,
            &far,
            step,
            7,
            use_rng.then_some(&mut rng),
            &mut capped,
        );
        assert_eq!(s.n_rays, 3000);
        assert_eq!(s.ray_offsets.len(), 3001);
        assert_eq!(s.ray_offsets[0], 0);
        assert_eq!(*s.ray_offsets.last().unwrap() as usize, s.len());
        assert_eq!(
            (
                s.positions.len(),
                s.dirs.len(),
                s.dt.len(),
                s.ray_indices.len()
            ),
            (3 * s.len(), 3 * s.len(), s.len(), s.len())
        );
        let mut n_hit = 0;
        for r in 0..s.n_rays {
            let range = s.ray_range(r);
            let (o3, d3) = (&o[3 * r..3 * r + 3], &d[3 * r..3 * r + 3]);
            let (a, b) = slab64(o3, d3, -1.5, 1.5);
            let (t0, t1) = ((near[r] as f64).max(a), (far[r] as f64).min(b));
            if far[r] <= near[r] || t1 <= t0 {
                assert!(
                    range.is_empty(),
                    "ray {r} misses the box or has far <= near"
                );
                continue;
            }
            // The dense walk crosses the ball on rays that pass close to the centre.
            assert!(range.len() <= max_samples);
            n_hit += !range.is_empty() as usize;
            for k in range.clone() {
                let t = s.t[k] as f64;
                assert!(
                    t >= t0 - 1e-5 && t < t1 + 1e-5,
                    "ray {r}: t {t} outside [{t0}, {t1})"
                );
                if k + 1 < range.end {
                    assert!(s.t[k] < s.t[k + 1], "ray {r} not sorted");
                }
                assert_eq!(s.dt[k], step);
                assert_eq!(s.ray_indices[k] as usize, r);
                let mut p = [0f32; 3];
                for c in 0..3 {
                    p[c] = s.positions[3 * k + c];
                    let want = o3[c] as f64 + t * d3[c] as f64;
                    assert!((p[c] as f64 - want).abs() < 1e-5, "position = o + t·d");
                    assert!(p[c].abs() <= 1.5 + 1e-5, "inside the box");
                    assert_eq!(s.dirs[3 * k + c], d3[c]);
                }
                let pc = p.map(|x| x.clamp(-1.5, 1.5));
                assert!(g.is_occupied(pc), "ray {r}: sample {p:?} in an empty cell");
                if !use_rng {
                    // On the step grid t0 + (j + 0.5)·step.
                    let j = (t - t0) / step as f64 - 0.5;
                    assert!(
                        (j - j.round()).abs() < 2e-3,
                        "ray {r}: off the step grid ({j})"
                    );
                }
            }
            // The cap keeps the first 7 samples.
            let cr = capped.ray_range(r);
            assert_eq!(cr.len(), range.len().min(7));
            assert_eq!(
                &capped.t[cr],
                &s.t[range.start..range.start + range.len().min(7)]
            );
        }
        assert!(n_hit > 300, "only {n_hit} rays got samples");
    }
    // Rays straight through the centre from outside: t inside the ball.
    let o = [0.0, 0.0, -3.0, 3.0, 0.0, 0.0];
    let d = [0.0, 0.0, 1.0, -1.0, 0.0, 0.0];
    march(
        &g, &o, &d, &[0.0; 2], &[10.0; 2], 0.01, 10_000, None, &mut s,
    );
    for r in 0..2 {
        let range = s.ray_range(r);
        assert!(range.len() > 150, "ray {r}: {} samples", range.len());
        for k in range {
            assert!(
                (s.t[k] - 3.0).abs() < 0.9 + 0.2,
                "sample at {} far from the ball",
                s.t[k]
            );
        }
    }
    // Rays that miss the box entirely.
    let o = [0.0, 5.0, 0.0, 2.0, 2.0, 2.0];
    let d = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
    march(
        &g,
        &o,
        &d,
        &[0.0; 2],
        &[100.0; 2],
        0.01,
        10_000,
        None,
        &mut s,
    );
    assert_eq!(s.len(), 0);
    assert_eq!(s.ray_offsets, vec![0, 0, 0]);
}

#[test]
fn results_do_not_depend_on_the_thread_count() {
    let (o, d, near, far) = random_rays(5000, 4);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            // 48³ = 110592 cells: the warm-up update spans two density chunks.
            let mut g = OccupancyGrid::new(cfg(48), [-1.5; 3], [1.5; 3]);
            let mut rng = nerf_core::rng(77, 0);
            let c = g.config().clone();
            for s in (0..c.warmup_steps + 5 * c.update_every).step_by(c.update_every as usize) {
                g.update(s, 0.01, &mut ball(0.8, 30.0), &mut rng);
            }
            let mut out = RaySamples::default();
            march(&g, &o, &d, &near, &far, 0.01, 512, Some(&mut rng), &mut out);
            (g.densities().to_vec(), out)
        })
    };
    let (d1, s1) = run(1);
    let (d3, s3) = run(3);
    assert_eq!(d1, d3);
    assert!(s1.len() > 1000);
    assert_eq!(s1.ray_offsets, s3.ray_offsets);
    assert_eq!(s1.t, s3.t);
    assert_eq!(s1.dt, s3.dt);
    assert_eq!(s1.positions, s3.positions);
    assert_eq!(s1.dirs, s3.dirs);
    assert_eq!(s1.ray_indices, s3.ray_indices);
}

/// The analytic scene: a ball of σ = 30 and radius 0.8 whose colour varies with position.
fn scene(p: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
    for i in 0..sigma.len() {
        let q = [p[3 * i], p[3 * i + 1], p[3 * i + 2]];
        let r2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2];
        sigma[i] = if r2 < 0.64 { 30.0 } else { 0.0 };
        for c in 0..3 {
            rgb[3 * i + c] = 0.5 + 0.5 * (3.0 * q[c] + c as f32).sin();
        }
    }
}

fn render(s: &RaySamples, bg: &[f32]) -> CompositeOutputs<f32> {
    let mut sigma = vec![0.0; s.len()];
    let mut rgb = vec![0.0; 3 * s.len()];
    scene(&s.positions, &mut sigma, &mut rgb);
    let mut out = CompositeOutputs::new();
    composite_forward(
        &s.ray_offsets,
        &sigma,
        &rgb,
        &s.dt,
        &s.t,
        Some(bg),
        0.0,
        &mut out,
    );
    out
}

#[test]
fn marching_renders_the_dense_image_with_far_fewer_samples() {
    // 32×32 pinhole camera at (0, 0.5, 4) looking at the origin, 40° field of view.
    let (w, h) = (32usize, 32usize);
    let eye = [0.0f32, 0.5, 4.0];
    let fwd = {
        let l = (eye[0] * eye[0] + eye[1] * eye[1] + eye[2] * eye[2]).sqrt();
        eye.map(|x| -x / l)
    };
    let right = {
        let v = [-fwd[2], 0.0, fwd[0]]; // fwd × up(0,1,0)
        let l = (v[0] * v[0] + v[2] * v[2]).sqrt();
        v.map(|x| x / l)
    };
    let up = [
        right[1] * fwd[2] - right[2] * fwd[1],
        right[2] * fwd[0] - right[0] * fwd[2],
        right[0] * fwd[1] - right[1] * fwd[0],
    ];
    let tan = (20f32).to_radians().tan();
    let (mut o, mut d) = (vec![], vec![]);
    for j in 0..h {
        for i in 0..w {
            let x = ((i as f32 + 0.5) / w as f32 * 2.0 - 1.0) * tan;
            let y = (1.0 - (j as f32 + 0.5) / h as f32 * 2.0) * tan;
            let v: [f32; 3] = std::array::from_fn(|a| fwd[a] + x * right[a] + y * up[a]);
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            o.extend(eye);
            d.extend(v.map(|c| c / l));
        }
    }
    let n = w * h;
    let (near, far) = (vec![2.0f32; n], vec![6.0f32; n]);
    let bg: Vec<f32> = (0..n)
        .flat_map(|r| [1.0, 0.5 * (r % 2) as f32, 0.2])
        .collect();
    let step = 3.0 * 3f32.sqrt() / 512.0;

    // Dense: a fresh grid is all occupied, so `march` emits every step in [near, far] ∩ box.
    let dense_grid = OccupancyGrid::new(cfg(64), [-1.5; 3], [1.5; 3]);
    assert_eq!(dense_grid.occupied_fraction(), 1.0);
    // Marched: the grid filled from a conservative proxy of the scene's density — the ball dilated
    // by half a cell diagonal, so every cell that touches the ball (σ > 0) is occupied (the
    // centre of any cell that intersects the ball lies within r + half a diagonal).
    let mut grid = OccupancyGrid::new(cfg(64), [-1.5; 3], [1.5; 3]);
    let hd = 0.5 * 3f32.sqrt() * grid.cell_size()[0];
    grid.fill_from(step, &mut ball(0.8 + hd * 1.001, 30.0));

    let mut dense = RaySamples::default();
    let mut marched = RaySamples::default();
    let mut rng = nerf_core::rng(3, 0);
    march(
        &dense_grid,
        &o,
        &d,
        &near,
        &far,
        step,
        4096,
        Some(&mut rng),
        &mut dense,
    );
    let mut rng = nerf_core::rng(3, 0);
    march(
        &grid,
        &o,
        &d,
        &near,
        &far,
        step,
        4096,
        Some(&mut rng),
        &mut marched,
    );

    // Skipping never moves samples: the marched samples of each ray are exactly the dense ones
    // that lie in occupied cells.
    for r in 0..n {
        let kept: Vec<f32> = dense
            .ray_range(r)
            .filter(|&k| grid.is_occupied(std::array::from_fn(|c| dense.positions[3 * k + c])))
            .map(|k| dense.t[k])
            .collect();
        assert_eq!(&marched.t[marched.ray_range(r)], &kept[..], "ray {r}");
    }

    let a = render(&dense, &bg);
    let b = render(&marched, &bg);
    // The dropped samples lie in empty cells, which the proxy guarantees carry σ = 0: α = 0 there,
    // the transmittance is multiplied by exactly 1 and the sums gain exactly 0, so the images
    // agree to rounding (in practice bit-for-bit); 1e-6 leaves room for summation-order changes.
    let max_diff = a
        .rgb
        .iter()
        .zip(&b.rgb)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    eprintln!(
        "dense {} samples, marched {} samples, max |Δrgb| = {max_diff:e}",
        dense.len(),
        marched.len()
    );
    assert!(max_diff < 1e-6, "max |Δrgb| = {max_diff}");
    let opaque = a.opacity.iter().filter(|&&x| x > 0.9).count();
    let clear = a.opacity.iter().filter(|&&x| x == 0.0).count();
    assert!(
        opaque > 100 && clear > 100,
        "the image shows the ball ({opaque}) and background ({clear})"
    );
    assert!(
        3 * marched.len() < dense.len(),
        "marched {} vs dense {} samples",
        marched.len(),
        dense.len()
    );
}

#[test]
fn skipping_is_exact_on_a_scattered_grid() {
    // Cells occupied independently at random: many empty/occupied transitions per ray; the sparse
    // grids also have many all-empty 4³ blocks (skipped in one jump), including partial blocks at
    // the far faces when the resolution is not a multiple of 4. Rays include axis-aligned ones
    // lying exactly on cell faces and nearly face-parallel ones.
    for (res, frac) in [(16u32, 0.3f32), (18, 0.02), (32, 0.005)] {
        let mut g = OccupancyGrid::new(cfg(res), [-1.5; 3], [1.5; 3]);
        let mut rng = nerf_core::rng(21, res as u64);
        let n = (res * res * res) as usize;
        let dens: Vec<f32> = (0..n)
            .map(|_| if rng.gen::<f32>() < frac { 10.0 } else { 0.0 })
            .collect();
        let step = g.step_size();
        g.set_densities(&dens, step).unwrap();
        let f = g.occupied_fraction();
        assert!(
            (f - frac).abs() < 0.1 * frac + 3.0 / (n as f32).sqrt(),
            "occupied fraction {f}"
        );
        let all = OccupancyGrid::new(cfg(res), [-1.5; 3], [1.5; 3]);

        let (mut o, mut d, mut near, mut far) = random_rays(2000, 8);
        let h = 3.0 / res as f32;
        for i in 0..=res {
            let x = -1.5 + i as f32 * h; // on a face
            o.extend([x, 0.3, -4.0]);
            d.extend([0.0, 0.0, 1.0]);
            o.extend([-4.0, x, x]);
            d.extend([1.0, 0.0, 0.0]);
            let e = 1e-4f32 * (i as f32 - 8.0);
            let l = (1.0 + e * e).sqrt();
            o.extend([x, -4.0, 0.1]);
            d.extend([e / l, 1.0 / l, 0.0]);
            for _ in 0..3 {
                near.push(0.0);
                far.push(10.0);
            }
        }
        for step in [Stepping::from(0.0071), Stepping::new(0.002, 0.03)] {
        let (mut dense, mut marched) = (RaySamples::default(), RaySamples::default());
        let mut r1 = nerf_core::rng(2, 2);
        march(
            &all,
            &o,
            &d,
            &near,
            &far,
            step,
            100_000,
            Some(&mut r1),
            &mut dense,
        );
        let mut r2 = nerf_core::rng(2, 2);
        march(
            &g,
            &o,
            &d,
            &near,
            &far,
            step,
            100_000,
            Some(&mut r2),
            &mut marched,
        );
        let mut kept_total = 0;
        for r in 0..near.len() {
            let kept: Vec<f32> = dense
                .ray_range(r)
                .filter(|&k| {
                    let p: [f32; 3] = std::array::from_fn(|c| dense.positions[3 * k + c]);
                    g.is_occupied(p.map(|x| x.clamp(-1.5, 1.5)))
                })
                .map(|k| dense.t[k])
                .collect();
            kept_total += kept.len();
            assert_eq!(
                &marched.t[marched.ray_range(r)],
                &kept[..],
                "res {res}: ray {r} ({step:?})"
            );
        }
        assert_eq!(kept_total, marched.len());
        for k in 0..marched.len() {
            assert_eq!(marched.dt[k], step.dt(marched.t[k]));
        }
        let expect = frac * dense.len() as f32;
        assert!(
            (marched.len() as f32) > 0.5 * expect && (marched.len() as f32) < 1.5 * expect,
            "res {res}: {} marched of {} dense samples ({step:?})",
            marched.len(),
            dense.len()
        );
        }
    }
}

#[test]
fn cone_steps_grow_with_the_distance_as_instant_ngps() {
    // Knots inside the range: steps of `a` up to t_a = a/c, then t·c, then 1024·a from t_b.
    let (a, c) = (0.001f32, 0.05f32);
    let st = Stepping::new(a, c);
    let (ta, tb) = (a / c, MAX_STEP_RATIO * a / c);
    // The warp and its inverse.
    for i in 0..2000 {
        let t = 1e-3 * 1.01f32.powi(i);
        if t > 3.0 * tb {
            break;
        }
        let back = st.unwarp(st.warp(t));
        assert!((back - t).abs() <= 2e-6 * t.max(1.0), "t {t}: unwarp(warp(t)) = {back}");
    }
    // Continuous at the knots.
    for knot in [ta, tb] {
        let (lo, hi) = (st.warp(knot * (1.0 - 1e-6)), st.warp(knot * (1.0 + 1e-6)));
        assert!((hi - lo).abs() < 1e-4 * knot, "warp jumps at {knot}: {lo} .. {hi}");
    }
    // Uniform steps of `a` in the warped distance: the spacing in t is clamp(t·c, a, 1024·a).
    let mut s = 0.0f32;
    let mut seen = [false; 3];
    while st.unwarp(s) < 1.5 * tb {
        let (t0, t1) = (st.unwarp(s), st.unwarp(s + a));
        let want = (t0 * c).clamp(a, MAX_STEP_RATIO * a);
        // Between the knots the spacing is t·c at the step's start (t1 = t0·(1 + c)).
        let tol = if t0 > ta && t1 < tb { 1e-3 } else { 0.06 };
        assert!(((t1 - t0) - want).abs() <= tol * want, "t {t0}: step {} vs {want}", t1 - t0);
        assert_eq!(st.dt(t0), want);
        seen[if t0 < ta { 0 } else if t0 < tb { 1 } else { 2 }] = true;
        s += a;
    }
    assert_eq!(seen, [true; 3], "every regime visited");
    // No cone: the identity and constant steps.
    let flat = Stepping::from(a);
    assert!(!flat.is_cone());
    assert_eq!((flat.warp(3.7), flat.unwarp(3.7), flat.dt(123.0)), (3.7, 3.7, a));
}

#[test]
fn bad_density_values_are_sanitised() {
    let c = OccupancyGridConfig {
        resolution: 4,
        ..Default::default()
    };
    let mut g = OccupancyGrid::new(c, [0.0; 3], [1.0; 3]);
    let mut rng = nerf_core::rng(0, 0);
    // x-slab 0: NaN, 1: negative, 2: +inf, 3: 7.
    let mut f = |p: &[f32], s: &mut [f32]| {
        for i in 0..s.len() {
            s[i] = [f32::NAN, -5.0, f32::INFINITY, 7.0][(p[3 * i] * 4.0) as usize];
        }
    };
    g.update(0, 0.01, &mut f, &mut rng);
    for (idx, &v) in g.densities().iter().enumerate() {
        let want = [0.0, 0.0, f32::MAX, 7.0][idx % 4];
        assert_eq!(v, want, "cell {idx}");
    }
    g.fill_from(0.01, &mut f);
    for (idx, &v) in g.densities().iter().enumerate() {
        assert!(v >= 0.0, "cell {idx}: {v}");
        assert_eq!(g.is_cell_occupied(idx), idx % 4 >= 2);
    }
}

#[test]
fn a_march_taken_a_few_samples_at_a_time_emits_exactly_the_samples_of_march() {
    use nerf_sampling::RayMarch;
    let mut g = OccupancyGrid::new(cfg(24), [-1.5; 3], [1.5; 3]);
    g.fill_from(0.01, &mut ball(0.9, 50.0));
    let (o, d, near, far) = random_rays(2000, 7);
    let mut rng = nerf_core::rng(7, 1);
    for (step, max) in [(Stepping::from(0.013), 1024usize), (Stepping::from(0.03), 5), (Stepping::new(0.003, 0.05), 1024)] {
        let mut all = RaySamples::default();
        march(&g, &o, &d, &near, &far, step, max, None, &mut all);
        assert!(all.len() > 1000, "too few samples to be a test ({})", all.len());
        for r in 0..2000 {
            let ray = |v: &[f32]| [v[3 * r], v[3 * r + 1], v[3 * r + 2]];
            let mut m = RayMarch::new(&g, ray(&o), ray(&d), near[r], far[r]);
            let mut got = Vec::new();
            let mut calls = 0;
            while !m.is_done() {
                let budget = rng.gen_range(1..5);
                let n = m.advance(&g, step, max, budget, |t| got.push(t));
                assert!(n <= budget);
                calls += 1;
                assert!(calls <= max + 2, "ray {r}: the march does not end");
            }
            assert_eq!(got, all.t[all.ray_range(r)], "ray {r} ({step:?}, max {max})");
            assert_eq!(m.emitted(), got.len());
            assert_eq!(m.advance(&g, step, max, 4, |_| panic!("a finished march emitted")), 0);
        }
    }
}
