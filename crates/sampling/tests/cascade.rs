//! Occupancy grids with a cascade of levels (instant-ngp's density-grid cascades): geometry, the
//! finest-level lookup, updates, the mean of the threshold, and exact skipping while marching.

use nerf_sampling::{march, OccupancyGrid, OccupancyGridConfig, RayMarch, RaySamples, Stepping};
use rand::Rng;

const LO: [f32; 3] = [-3.0, -1.0, -2.5];
const HI: [f32; 3] = [5.0, 7.0, 5.5];

fn cfg(res: u32, cascades: u32) -> OccupancyGridConfig {
    OccupancyGridConfig { resolution: res, cascades: Some(cascades), ..Default::default() }
}

#[test]
fn levels_halve_about_the_centre_and_the_finest_level_answers() {
    let g = OccupancyGrid::new(cfg(16, 3), LO, HI);
    assert_eq!(g.cascades(), 3);
    assert_eq!(g.densities().len(), 3 * 16 * 16 * 16);
    assert_eq!(g.level_box(2), (LO, HI), "the outermost level is the box, bit for bit");
    assert_eq!(g.cell_size(), g.level_cell_size(2));
    for m in 0..3 {
        let (lo, hi) = g.level_box(m);
        let s = 0.5f32.powi(2 - m as i32);
        for a in 0..3 {
            let (c, h) = (0.5 * (LO[a] + HI[a]), 0.5 * (HI[a] - LO[a]));
            assert!((lo[a] - (c - h * s)).abs() < 1e-6 && (hi[a] - (c + h * s)).abs() < 1e-6, "level {m}");
            assert!((g.level_cell_size(m)[a] - (hi[a] - lo[a]) / 16.0).abs() < 1e-7);
        }
        if m > 0 {
            // The inner box lies on cell faces 4 and 12 of this level (and on block faces).
            let (ilo, ihi) = g.level_box(m - 1);
            for a in 0..3 {
                let h = g.level_cell_size(m)[a];
                assert!((ilo[a] - (lo[a] + 4.0 * h)).abs() < 1e-5 && (ihi[a] - (lo[a] + 12.0 * h)).abs() < 1e-5);
            }
        }
    }

    // Level 0 empty, levels 1 and 2 occupied: the centre is empty, the rest occupied.
    let mut g = g;
    let n = 16 * 16 * 16;
    let dens: Vec<f32> = (0..3 * n).map(|i| if i < n { 0.0 } else { 100.0 }).collect();
    g.set_densities(&dens, 0.01).unwrap();
    assert!((g.occupied_fraction() - 2.0 / 3.0).abs() < 1e-6);
    let (c0, c1) = g.level_box(0);
    let mid: [f32; 3] = std::array::from_fn(|a| 0.5 * (c0[a] + c1[a]));
    assert!(!g.is_occupied(mid));
    assert!(!g.is_occupied(c0), "the inner box's corner belongs to the inner level");
    assert!(g.is_occupied([c0[0] - 1e-3, mid[1], mid[2]]));
    assert!(g.is_occupied([HI[0], HI[1], HI[2]]));
    assert!(!g.is_occupied([HI[0] + 1e-3, HI[1], HI[2]]), "outside the box");
}

#[test]
fn validation_names_the_problem() {
    assert!(cfg(16, 0).validate().unwrap_err().contains("cascades"));
    assert!(cfg(16, 9).validate().unwrap_err().contains("cascades"));
    assert!(cfg(24, 2).validate().unwrap_err().contains("divisible by 16"));
    assert!(cfg(24, 1).validate().is_ok(), "one level takes any resolution");
    assert!(cfg(32, 8).validate().is_ok());
    assert_eq!(OccupancyGridConfig::default().levels(), 1, "absent: one level");
    let g = OccupancyGrid::try_new(cfg(16, 2), LO, HI).unwrap();
    let e = g.clone().set_densities(&vec![0.0; 16 * 16 * 16], 0.01).unwrap_err();
    assert!(e.contains("8192") && e.contains("2 × 16³"), "{e}");
    // Serde: absent stays absent (the trainer picks), a number round-trips.
    let parsed: OccupancyGridConfig = serde_json::from_str(r#"{"resolution": 64}"#).unwrap();
    assert_eq!(parsed.cascades, None);
    assert!(!serde_json::to_string(&parsed).unwrap().contains("cascades"));
    let c: OccupancyGridConfig = serde_json::from_str(r#"{"resolution": 64, "cascades": 3}"#).unwrap();
    assert_eq!(c, cfg(64, 3));
    assert_eq!(serde_json::from_str::<OccupancyGridConfig>(&serde_json::to_string(&c).unwrap()).unwrap(), c);
}

#[test]
fn the_threshold_takes_the_mean_of_the_finest_level() {
    // Level 0: half its cells at σ·step = 0.002 (mean 0.001); level 1: zero but one cell at
    // 0.0008. A mean over both levels (0.0005) would mark that cell; the finest level's does not.
    let mut g = OccupancyGrid::new(cfg(16, 2), LO, HI);
    let n = 16 * 16 * 16;
    let mut d: Vec<f32> = (0..2 * n).map(|i| if i < n && i % 2 == 0 { 0.002 } else { 0.0 }).collect();
    d[n + 5] = 0.0008;
    d[n + 6] = 0.0015;
    g.set_densities(&d, 1.0).unwrap();
    for i in 0..n {
        assert_eq!(g.is_cell_occupied(i), i % 2 == 0, "cell {i}");
    }
    assert!(!g.is_cell_occupied(n + 5), "0.0008 is below the finest level's mean 0.001");
    assert!(g.is_cell_occupied(n + 6));
    assert_eq!(g.occupied_fraction(), (n / 2 + 1) as f32 / (2 * n) as f32);
}

#[test]
fn updates_sample_every_level_inside_its_cells() {
    // σ = 1 inside a ball about the box centre that reaches past level 0's box: during warm-up
    // every cell of every level is sampled once inside itself, so a cell is occupied exactly when
    // its sampled point was in the ball — cells wholly inside are occupied, wholly outside empty.
    let c = OccupancyGridConfig { warmup_steps: 100, ..cfg(16, 3) };
    let mut g = OccupancyGrid::new(c, LO, HI);
    let centre: [f32; 3] = std::array::from_fn(|a| 0.5 * (LO[a] + HI[a]));
    let radius = 1.4f32; // level 0 is 2 × 2 × 2 about the centre
    let calls = std::cell::Cell::new(0);
    let mut ball = |p: &[f32], s: &mut [f32]| {
        calls.set(calls.get() + 1);
        for (i, s) in s.iter_mut().enumerate() {
            let r2: f32 = (0..3).map(|a| (p[3 * i + a] - centre[a]).powi(2)).sum();
            *s = if r2 < radius * radius { 1.0 } else { 0.0 };
        }
    };
    let mut rng = nerf_core::rng(3, 0);
    g.update(0, 0.05, &mut ball, &mut rng);
    assert!(calls.get() > 0);
    let n = 16 * 16 * 16;
    let (mut inside, mut outside) = (0, 0);
    for m in 0..3 {
        let (lo, _) = g.level_box(m);
        let h = g.level_cell_size(m);
        for idx in 0..n {
            let ijk = [idx % 16, (idx / 16) % 16, idx / 256];
            let (mut near2, mut far2) = (0f32, 0f32);
            for a in 0..3 {
                let a0 = lo[a] + ijk[a] as f32 * h[a] - centre[a];
                let a1 = a0 + h[a];
                near2 += 0f32.clamp(a0, a1).powi(2);
                far2 += a0.abs().max(a1.abs()).powi(2);
            }
            let occ = g.is_cell_occupied(m * n + idx);
            if far2.sqrt() < radius - 1e-4 {
                assert!(occ, "level {m} cell {idx} inside the ball is empty");
                inside += 1;
            }
            if near2.sqrt() > radius + 1e-4 {
                assert!(!occ, "level {m} cell {idx} outside the ball is occupied");
                outside += 1;
            }
        }
    }
    assert!(inside > 1000 && outside > 5000, "{inside} inside, {outside} outside");
    // Past warm-up: a quarter of all cells and of the occupied ones; densities stay in {0, 1}
    // or the decayed 0.95.
    g.update(200, 0.05, &mut ball, &mut rng);
    assert!(g.densities().iter().all(|&x| x == 0.0 || x == 1.0 || x == 0.95));
}

/// Rays from inside, outside, along the inner boxes' faces and nearly parallel to them.
fn rays(g: &OccupancyGrid, n: usize, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut r = nerf_core::rng(seed, 0);
    let (mut o, mut d, mut near, mut far) = (vec![], vec![], vec![], vec![]);
    let mut push = |o_: [f32; 3], d_: [f32; 3], near_: f32, far_: f32| {
        let l = (d_[0] * d_[0] + d_[1] * d_[1] + d_[2] * d_[2]).sqrt();
        o.extend(o_);
        d.extend(d_.map(|x| x / l));
        near.push(near_);
        far.push(far_);
    };
    let centre: [f32; 3] = std::array::from_fn(|a| 0.5 * (LO[a] + HI[a]));
    for i in 0..n {
        let v: [f32; 3] = std::array::from_fn(|_| r.gen::<f32>() - 0.5);
        // Origins about the centre (inside the inner levels) or anywhere up to past the box.
        let spread = if i % 2 == 0 { 2.0 } else { 14.0 };
        let p: [f32; 3] = std::array::from_fn(|a| centre[a] + (r.gen::<f32>() - 0.5) * spread);
        push(p, v, r.gen::<f32>() * 0.3, 2.0 + 15.0 * r.gen::<f32>());
    }
    for m in 0..g.cascades() - 1 {
        let (lo, hi) = g.level_box(m);
        for (x, e) in [(lo[0], 0.0), (hi[0], 0.0), (lo[0], 1e-4), (hi[0], -3e-5)] {
            // Along an inner box's face (and nearly so), crossing the levels.
            push([x, LO[1] - 1.0, centre[2] + 0.1], [e, 1.0, 0.0], 0.0, 30.0);
            push([x, centre[1] + 0.37, LO[2] - 1.0], [e, 0.0, 1.0], 0.0, 30.0);
            push([LO[0] - 1.0, lo[1], hi[2]], [1.0, e, -e], 0.0, 30.0);
        }
    }
    (o, d, near, far)
}

#[test]
fn skipping_through_a_cascade_is_exact() {
    // Cells occupied at random on every level (sparse: many empty blocks skipped at once); the
    // march must emit exactly the dense walk's samples: every step whose cell, in the finest
    // level holding the point, is occupied.
    for (levels, frac) in [(2u32, 0.05f32), (3, 0.01), (4, 0.2)] {
        let mut g = OccupancyGrid::new(cfg(16, levels), LO, HI);
        let mut rng = nerf_core::rng(5, levels as u64);
        let dens: Vec<f32> = (0..g.densities().len()).map(|_| if rng.gen::<f32>() < frac { 10.0 } else { 0.0 }).collect();
        let step = g.step_size();
        g.set_densities(&dens, step).unwrap();
        let all = OccupancyGrid::new(cfg(16, levels), LO, HI);
        let (o, d, near, far) = rays(&g, 3000, levels as u64);
        for stepping in [Stepping::from(0.0093), Stepping::new(0.002, 0.02)] {
            let (mut dense, mut marched) = (RaySamples::default(), RaySamples::default());
            march(&all, &o, &d, &near, &far, stepping, 1 << 20, Some(&mut nerf_core::rng(9, 1)), &mut dense);
            march(&g, &o, &d, &near, &far, stepping, 1 << 20, Some(&mut nerf_core::rng(9, 1)), &mut marched);
            assert!(dense.len() > 100_000, "{} dense samples", dense.len());
            let mut kept_total = 0;
            for r in 0..near.len() {
                let kept: Vec<f32> = dense
                    .ray_range(r)
                    .filter(|&k| {
                        let p: [f32; 3] = std::array::from_fn(|c| dense.positions[3 * k + c]);
                        g.is_occupied(std::array::from_fn(|a| p[a].clamp(LO[a], HI[a])))
                    })
                    .map(|k| dense.t[k])
                    .collect();
                kept_total += kept.len();
                assert_eq!(&marched.t[marched.ray_range(r)], &kept[..], "{levels} levels: ray {r} ({stepping:?})");
            }
            assert_eq!(kept_total, marched.len());
            assert!(marched.len() > 1000 && marched.len() < dense.len() / 2, "{} of {}", marched.len(), dense.len());
        }
    }
}

#[test]
fn a_cascade_march_in_rounds_emits_the_samples_of_march() {
    let mut g = OccupancyGrid::new(cfg(16, 3), LO, HI);
    let mut rng = nerf_core::rng(8, 0);
    let dens: Vec<f32> = (0..g.densities().len()).map(|_| if rng.gen::<f32>() < 0.05 { 10.0 } else { 0.0 }).collect();
    g.set_densities(&dens, 0.01).unwrap();
    let (o, d, near, far) = rays(&g, 500, 4);
    for (step, max) in [(Stepping::from(0.011), 4096usize), (Stepping::new(0.002, 0.02), 7)] {
        let mut all = RaySamples::default();
        march(&g, &o, &d, &near, &far, step, max, None, &mut all);
        assert!(all.len() > 1000);
        for r in 0..near.len() {
            let ray = |v: &[f32]| [v[3 * r], v[3 * r + 1], v[3 * r + 2]];
            let mut m = RayMarch::new(&g, ray(&o), ray(&d), near[r], far[r]);
            let mut got = Vec::new();
            while !m.is_done() {
                m.advance(&g, step, max, rng.gen_range(1..6), |t| got.push(t));
            }
            assert_eq!(got, all.t[all.ray_range(r)], "ray {r} ({step:?})");
        }
    }
}

#[test]
fn cells_no_camera_sees_are_never_occupied_nor_refreshed() {
    // "Seen": cells whose ball reaches x > 1 (a camera looking at that half of the box).
    let c = OccupancyGridConfig { warmup_steps: 32, ..cfg(16, 2) };
    let mut g = OccupancyGrid::new(c, LO, HI);
    assert_eq!(g.seen_fraction(), 1.0);
    g.mark_seen(&|p, r| p[0] + r > 1.0);
    let n = g.densities().len();
    let seen: Vec<bool> = (0..n).map(|i| g.is_cell_seen(i)).collect();
    let n_seen = seen.iter().filter(|&&s| s).count();
    assert!(n_seen > n / 4 && n_seen < 3 * n / 4, "{n_seen} of {n} seen");
    assert!((g.seen_fraction() - n_seen as f32 / n as f32).abs() < 1e-6);
    for (i, &s) in seen.iter().enumerate() {
        assert_eq!(g.densities()[i] == 0.0, !s, "cell {i}: unseen cells start at 0, seen ones at +inf");
        assert_eq!(g.is_cell_occupied(i), s);
    }
    // Warm-up asks the density of the seen cells only; afterwards of seen cells only too.
    let asked = std::cell::Cell::new(0usize);
    let mut everywhere = |p: &[f32], s: &mut [f32]| {
        asked.set(asked.get() + s.len());
        for (i, s) in s.iter_mut().enumerate() {
            assert!(p[3 * i] > 1.0 - 1.0, "an unseen point was asked: {:?}", &p[3 * i..3 * i + 3]);
            *s = 50.0;
        }
    };
    let mut rng = nerf_core::rng(1, 0);
    g.update(0, 0.01, &mut everywhere, &mut rng);
    assert_eq!(asked.get(), n_seen, "warm-up: every seen cell once");
    asked.set(0);
    g.update(100, 0.01, &mut everywhere, &mut rng);
    assert!(asked.get() > 0 && asked.get() < n / 4 + n_seen / 4, "{} asked after warm-up", asked.get());
    for (i, &s) in seen.iter().enumerate() {
        assert_eq!(g.is_cell_occupied(i), s, "cell {i}: a dense field everywhere occupies exactly the seen cells");
    }
    // Restored and filled grids keep unseen cells at 0.
    g.set_densities(&vec![50.0; n], 0.01).unwrap();
    assert!((0..n).all(|i| g.is_cell_occupied(i) == seen[i]));
    g.fill_from(0.01, &mut |_, s: &mut [f32]| s.fill(50.0));
    assert!((0..n).all(|i| (g.densities()[i] == 0.0) != seen[i]));
}

#[test]
fn the_threshold_mean_leaves_out_cells_no_camera_sees() {
    // Seen cells (x > 1) at σ·step = 0.004; unseen ones hold 0. The mean over the seen cells is
    // 0.004, so a seen cell at 0.003 is empty; a mean over every cell (lower) would mark it.
    let mut g = OccupancyGrid::new(cfg(16, 1), LO, HI);
    g.mark_seen(&|p, r| p[0] + r > 1.0);
    let n = g.densities().len();
    let seen: Vec<usize> = (0..n).filter(|&i| g.is_cell_seen(i)).collect();
    assert_eq!(g.mean_cells(), seen.len());
    let mut d = vec![0.004f32; n];
    d[seen[0]] = 0.003;
    g.set_densities(&d, 1.0).unwrap();
    assert!(!g.is_cell_occupied(seen[0]), "0.003 is below the seen cells' mean of ~0.004");
    assert!(g.is_cell_occupied(seen[1]));
    assert!(seen.len() < n * 3 / 4, "{} of {n} seen: the all-cell mean would be far lower", seen.len());
}

#[test]
fn seen_marks_set_from_words_give_the_marked_grid() {
    // A checkpoint's marks restored into a fresh grid give the same marks, densities and bits.
    let mut g = OccupancyGrid::new(cfg(16, 2), LO, HI);
    g.mark_seen(&|p, r| p[0] + r > 0.5);
    let n = g.densities().len();
    let d: Vec<f32> = (0..n).map(|i| 0.001 * (i % 13) as f32).collect();
    g.set_densities(&d, 1.0).unwrap();
    let mut h = OccupancyGrid::new(cfg(16, 2), LO, HI);
    h.set_seen_words(&g.seen_words().unwrap()).unwrap();
    h.set_densities(&d, 1.0).unwrap();
    assert_eq!(h.seen_words(), g.seen_words());
    assert_eq!(h.seen_fraction(), g.seen_fraction());
    assert_eq!(h.densities(), g.densities());
    assert!((0..n).all(|i| h.is_cell_occupied(i) == g.is_cell_occupied(i)));
    assert!(g.seen_fraction() > 0.1 && g.seen_fraction() < 0.9, "{}", g.seen_fraction());
    // The wrong number of words is an error naming both counts.
    let e = h.set_seen_words(&[0; 3]).unwrap_err();
    assert!(e.contains("3 words") && e.contains(&format!("{n} cells")), "{e}");
}
