//! `GpuOccupancyGrid` against its CPU twin `nerf_sampling::OccupancyGrid` (runs on any adapter:
//! lavapipe in CI; prints a notice and returns where no adapter exists).
//!
//! Warm-up updates choose every cell in order on both sides, so with a density that depends only
//! on the cell (not on the jittered point inside it) the densities must be bit-identical and the
//! bits equal. After warm-up the two draw different random cells: the test checks the choice's
//! invariants and statistics, and checks the EMA/threshold/bit rules exactly against a host
//! application of the GPU's own choice (bits through the CPU grid's `set_densities`).

#![allow(clippy::manual_is_multiple_of, clippy::needless_range_loop)] // MSRV 1.85; index loops mirror the CPU

use nerf_gpu::occupancy::GpuOccupancyGrid;
use nerf_gpu::GpuContext;
use nerf_sampling::{OccupancyGrid, OccupancyGridConfig};

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

const AABB: ([f32; 3], [f32; 3]) = ([-1.5, -0.5, 0.0], [1.5, 2.0, 1.25]);

/// A density per (cell, round) from a small discrete set (so no cell sits at the mean by
/// accident), with a few NaN, negative and infinite values.
fn sigma_of(cell: usize, round: u32) -> f32 {
    let h = nerf_gpu::rng::rand_u32(round, 77, cell as u32);
    match h % 97 {
        0 => f32::NAN,
        1 => -3.0,
        2 if cell % 5 == 0 && round == 1 => f32::INFINITY,
        _ => [0.0f32, 0.05, 0.4, 1.3, 7.0, 40.0][(h >> 8) as usize % 6] * (1.0 + (h >> 20) as f32 / 4096.0),
    }
}

/// The cell box of `idx` (CPU layout, levels of a cascade included) with a little slack for f32
/// rounding.
fn inside_cell(grid: &OccupancyGrid, idx: usize, p: &[f32]) -> bool {
    let r = grid.resolution();
    let (m, idx) = (idx / (r * r * r), idx % (r * r * r));
    let ijk = [idx % r, (idx / r) % r, idx / (r * r)];
    let (lo, _) = grid.level_box(m);
    let h = grid.level_cell_size(m);
    (0..3).all(|a| {
        let c0 = lo[a] + ijk[a] as f32 * h[a];
        let c1 = lo[a] + (ijk[a] + 1) as f32 * h[a];
        p[a] >= c0 - 1e-5 && p[a] <= c1 + 1e-5
    })
}

fn bit(words: &[u32], i: usize) -> bool {
    (words[i / 32] >> (i % 32)) & 1 != 0
}

struct Scratch {
    positions: wgpu::Buffer,
    cells: wgpu::Buffer,
    sigma: wgpu::Buffer,
    counters: wgpu::Buffer,
}

fn scratch(ctx: &GpuContext, n: usize) -> Scratch {
    Scratch {
        positions: ctx.upload("positions", &vec![f32::NAN; 3 * n]),
        cells: ctx.upload("cells", &vec![u32::MAX; n]),
        sigma: ctx.upload("sigma", &vec![f32::NAN; n]),
        counters: ctx.upload("counters", &[123u32, u32::MAX]),
    }
}

/// Runs stage 1, reads back (positions, cells, m).
fn choose(ctx: &GpuContext, g: &GpuOccupancyGrid, s: &Scratch, step: u64, seed: u32) -> (Vec<f32>, Vec<u32>, usize) {
    let mut enc = ctx.encoder("choose");
    g.record_choose(ctx, &mut enc, step, seed, &s.positions, &s.cells, &s.counters);
    ctx.queue.submit([enc.finish()]);
    let c = ctx.read_u32(&s.counters, 2).unwrap();
    assert_eq!(c[0], 123, "counters_out[0] must be left alone");
    let m = c[1] as usize;
    assert!(m <= g.n_cells());
    (ctx.read_f32(&s.positions, 3 * m).unwrap(), ctx.read_u32(&s.cells, m).unwrap(), m)
}

fn apply(ctx: &GpuContext, g: &GpuOccupancyGrid, s: &Scratch, sigma: &[f32], step_size: f32) {
    ctx.write(&s.sigma, 0, sigma);
    let mut enc = ctx.encoder("apply");
    g.record_apply(ctx, &mut enc, &s.cells, &s.sigma, step_size);
    ctx.queue.submit([enc.finish()]);
}

/// Densities bit-identical, bits equal, occupied list = ascending occupied cells.
fn assert_same_grid(ctx: &GpuContext, g: &GpuOccupancyGrid, cpu: &OccupancyGrid, what: &str) {
    let d = g.download(ctx).unwrap();
    let n = g.n_cells();
    for (i, (a, b)) in d.iter().zip(cpu.densities()).enumerate() {
        assert_eq!(a.to_bits(), b.to_bits(), "{what}: density of cell {i}: gpu {a} cpu {b}");
    }
    let words = g.download_bits(ctx).unwrap();
    let mut expect_list = vec![];
    for i in 0..n {
        assert_eq!(bit(&words, i), cpu.is_cell_occupied(i), "{what}: bit of cell {i} (density {})", d[i]);
        if cpu.is_cell_occupied(i) {
            expect_list.push(i as u32);
        }
    }
    // Bits past the last cell stay clear.
    if n % 32 != 0 {
        assert_eq!(words[n / 32] >> (n % 32), 0, "{what}: padding bits");
    }
    let st = g.download_stats(ctx).unwrap();
    assert_eq!(st.n_occupied, expect_list.len(), "{what}: n_occupied");
    assert!((cpu.occupied_fraction() - expect_list.len() as f32 / n as f32).abs() < 1e-6);
    let list = ctx.read_u32(g.occupied_list(), expect_list.len().max(1)).unwrap();
    assert_eq!(&list[..expect_list.len()], &expect_list[..], "{what}: occupied list");
}

#[test]
fn warm_up_updates_match_the_cpu_exactly() {
    let Some(ctx) = context() else { return };
    // Threshold 0.01 (mean above it) and threshold 10 (the mean decides), odd and even
    // resolutions, and cascades (the mean over the finest level, every level's cells chosen).
    for (res, threshold, step_size, cascades) in
        [(24u32, 0.01f32, 0.01f32, 1u32), (13, 10.0, 0.02, 1), (1, 0.01, 0.005, 1), (16, 10.0, 0.01, 3), (16, 0.01, 0.02, 2)]
    {
        let cfg = OccupancyGridConfig { resolution: res, threshold, warmup_steps: 1000, cascades: Some(cascades), ..Default::default() };
        let g = GpuOccupancyGrid::new(&ctx, &cfg, AABB).unwrap();
        let mut cpu = OccupancyGrid::new(cfg.clone(), AABB.0, AABB.1);
        assert_same_grid(&ctx, &g, &cpu, "initial");
        let n = g.n_cells();
        let s = scratch(&ctx, n);
        let mut rng = nerf_core::rng(res as u64, 0);
        for round in 0..4u32 {
            let (pos, cells, m) = choose(&ctx, &g, &s, round as u64 * 16, 1000 + round);
            assert_eq!(m, n, "warm-up chooses every cell");
            let sigma: Vec<f32> = cells.iter().enumerate().map(|(j, &c)| {
                assert_eq!(c as usize, j, "warm-up chooses the cells in order");
                assert!(inside_cell(&cpu, j, &pos[3 * j..3 * j + 3]), "point {:?} outside cell {j}", &pos[3 * j..3 * j + 3]);
                sigma_of(j, round)
            }).collect();
            apply(&ctx, &g, &s, &sigma, step_size);
            let mut k = 0usize;
            let cpu_ref = cpu.clone();
            cpu.update(round as u64 * 16, step_size, &mut |p, out| {
                for (i, o) in out.iter_mut().enumerate() {
                    assert!(inside_cell(&cpu_ref, k, &p[3 * i..3 * i + 3]));
                    *o = sigma_of(k, round);
                    k += 1;
                }
            }, &mut rng);
            assert_eq!(k, n);
            assert_same_grid(&ctx, &g, &cpu, &format!("res {res} × {cascades} round {round}"));
        }
        // Something is occupied and something is not (the test exercises both sides).
        let st = g.download_stats(&ctx).unwrap();
        if res > 1 {
            assert!(st.n_occupied > 0 && st.n_occupied < n, "{st:?}");
        }
    }
}

#[test]
fn post_warm_up_updates_follow_the_cpu_rules() {
    let Some(ctx) = context() else { return };
    let cfg = OccupancyGridConfig { resolution: 20, threshold: 0.01, warmup_steps: 32, decay: 0.9, ..Default::default() };
    let step_size = 0.01;
    let g = GpuOccupancyGrid::new(&ctx, &cfg, AABB).unwrap();
    let n = g.n_cells();
    let s = scratch(&ctx, n);
    // One warm-up update gives a mixed grid.
    let (_, cells, _) = choose(&ctx, &g, &s, 0, 5);
    let sigma: Vec<f32> = cells.iter().map(|&c| sigma_of(c as usize, 0)).collect();
    apply(&ctx, &g, &s, &sigma, step_size);
    for (round, step) in [(1u32, 32u64), (2, 48), (3, 64)] {
        let before = g.download(&ctx).unwrap();
        let words = g.download_bits(&ctx).unwrap();
        let n_occ = (0..n).filter(|&i| bit(&words, i)).count();
        let (pos, cells, m) = choose(&ctx, &g, &s, step, 40 + round);
        assert_eq!(m, n / 4 + n_occ / 4);
        let cpu_geom = OccupancyGrid::new(cfg.clone(), AABB.0, AABB.1);
        for (j, &c) in cells.iter().enumerate() {
            assert!((c as usize) < n);
            assert!(inside_cell(&cpu_geom, c as usize, &pos[3 * j..3 * j + 3]));
            if j >= n / 4 {
                assert!(bit(&words, c as usize), "choice {j} (occupied part) picked empty cell {c}");
            }
        }
        // With replacement: the expected number of distinct cells among k draws from N is
        // N·(1 − (1 − 1/N)^k); allow 10 %.
        let distinct = |v: &[u32]| {
            let mut v = v.to_vec();
            v.sort_unstable();
            v.dedup();
            v.len() as f64
        };
        let expect = |nn: usize, k: usize| nn as f64 * (1.0 - (1.0 - 1.0 / nn as f64).powi(k as i32));
        let (du, eu) = (distinct(&cells[..n / 4]), expect(n, n / 4));
        assert!((du - eu).abs() < 0.1 * eu, "uniform part: {du} distinct, expected {eu}");
        if n_occ >= 40 {
            let (dof, eo) = (distinct(&cells[n / 4..]), expect(n_occ, n_occ / 4));
            assert!((dof - eo).abs() < 0.1 * eo, "occupied part: {dof} distinct, expected {eo}");
        }
        // The same seed chooses the same cells.
        let (_, again, _) = choose(&ctx, &g, &s, step, 40 + round);
        assert_eq!(again, cells);
        // Apply, and check against the CPU rules applied to the GPU's choice.
        let sigma: Vec<f32> = cells.iter().map(|&c| sigma_of(c as usize, round)).collect();
        apply(&ctx, &g, &s, &sigma, step_size);
        let mut tmp = vec![-1.0f32; n];
        for (&c, &x) in cells.iter().zip(&sigma) {
            let x = if x > 0.0 { x.min(f32::MAX) } else { 0.0 };
            tmp[c as usize] = tmp[c as usize].max(x);
        }
        let expect_d: Vec<f32> = before
            .iter()
            .zip(&tmp)
            .map(|(&d, &t)| if t < 0.0 { d } else if d.is_finite() { (d * cfg.decay).max(t) } else { t })
            .collect();
        let mut cpu = OccupancyGrid::new(cfg.clone(), AABB.0, AABB.1);
        cpu.set_densities(&expect_d, step_size).unwrap();
        assert_same_grid(&ctx, &g, &cpu, &format!("post-warm-up round {round}"));
    }
}

#[test]
fn upload_and_download_round_trip_through_a_cpu_grid() {
    let Some(ctx) = context() else { return };
    let cfg = OccupancyGridConfig { resolution: 16, ..Default::default() };
    let mut cpu = OccupancyGrid::new(cfg.clone(), AABB.0, AABB.1);
    // A ball of density: the filled grid has occupied and empty cells.
    cpu.fill_from(0.004, &mut |p, out| {
        for (i, o) in out.iter_mut().enumerate() {
            let r2 = p[3 * i] * p[3 * i] + (p[3 * i + 1] - 0.7).powi(2) + (p[3 * i + 2] - 0.6).powi(2);
            *o = 30.0 * (-4.0 * r2).exp();
        }
    });
    let g = GpuOccupancyGrid::new(&ctx, &cfg, AABB).unwrap();
    g.upload_from(&ctx, &cpu).unwrap();
    assert_same_grid(&ctx, &g, &cpu, "uploaded");
    let mut back = OccupancyGrid::new(cfg.clone(), AABB.0, AABB.1);
    back.set_densities(&g.download(&ctx).unwrap(), cpu.step_size()).unwrap();
    assert_eq!(back.densities(), cpu.densities());
    // Mismatched grids are refused with a message naming both.
    let other = OccupancyGrid::new(OccupancyGridConfig { resolution: 8, ..cfg.clone() }, AABB.0, AABB.1);
    let e = g.upload_from(&ctx, &other).unwrap_err().to_string();
    assert!(e.contains("8³") && e.contains("16³"), "{e}");
    // Invalid settings are errors, not panics.
    assert!(GpuOccupancyGrid::new(&ctx, &OccupancyGridConfig { resolution: 0, ..cfg.clone() }, AABB).is_err());
    assert!(GpuOccupancyGrid::new(&ctx, &cfg, ([0.0; 3], [1.0, 0.0, 1.0])).is_err());
}

#[test]
fn a_whole_warm_up_update_in_one_submission_matches_the_cpu() {
    // The trainer's protocol: choose, density, apply recorded into one encoder. During warm-up the
    // chosen cells are known in advance (every cell, in order), so σ can be uploaded up front in
    // place of the field's density kernel.
    let Some(ctx) = context() else { return };
    let cfg = OccupancyGridConfig { resolution: 11, warmup_steps: 100, ..Default::default() };
    let g = GpuOccupancyGrid::new(&ctx, &cfg, AABB).unwrap();
    let mut cpu = OccupancyGrid::new(cfg.clone(), AABB.0, AABB.1);
    let n = g.n_cells();
    let s = scratch(&ctx, n);
    let mut rng = nerf_core::rng(3, 0);
    for (round, step_size) in [(5u32, 0.01f32), (6, 0.03)] {
        let sigma: Vec<f32> = (0..n).map(|j| sigma_of(j, round)).collect();
        ctx.write(&s.sigma, 0, &sigma);
        let mut enc = ctx.encoder("update");
        g.record_choose(&ctx, &mut enc, round as u64, round, &s.positions, &s.cells, &s.counters);
        g.record_apply(&ctx, &mut enc, &s.cells, &s.sigma, step_size);
        ctx.queue.submit([enc.finish()]);
        let mut k = 0;
        cpu.update(round as u64, step_size, &mut |_, out| {
            for o in out.iter_mut() {
                *o = sigma_of(k, round);
                k += 1;
            }
        }, &mut rng);
        assert_same_grid(&ctx, &g, &cpu, &format!("one-submission round {round}"));
        assert_eq!(g.download_stats(&ctx).unwrap().n_chosen, n);
    }
}

#[test]
fn cells_no_camera_sees_are_never_refreshed_on_the_gpu_either() {
    let Some(ctx) = context() else { return };
    let cfg = OccupancyGridConfig { resolution: 20, threshold: 0.01, warmup_steps: 1000, ..Default::default() };
    let step_size = 0.01;
    // Marks from a CPU grid (the trainer's path: mark on the CPU, upload with the densities).
    let mut cpu = OccupancyGrid::new(cfg.clone(), AABB.0, AABB.1);
    cpu.mark_seen(&|p, r| p[0] - r < 0.2 && p[2] + r > 0.4);
    let n_seen = (0..cpu.densities().len()).filter(|&i| cpu.is_cell_seen(i)).count();
    assert!(n_seen > 1000 && n_seen < 6000, "{n_seen} seen");
    let g = GpuOccupancyGrid::new(&ctx, &cfg, AABB).unwrap();
    g.upload_from(&ctx, &cpu).unwrap();
    assert_same_grid(&ctx, &g, &cpu, "marked");
    let n = g.n_cells();
    let s = scratch(&ctx, n);
    let r = cfg.resolution as usize;
    let h = cpu.cell_size();
    // The cell of a point strictly inside one (one level).
    let cell_of = |p: &[f32]| -> usize {
        let ijk: [usize; 3] = std::array::from_fn(|a| (((p[a] - AABB.0[a]) / h[a]) as usize).min(r - 1));
        ijk[0] + r * (ijk[1] + r * ijk[2])
    };
    let mut rng = nerf_core::rng(3, 0);
    for round in 0..3u32 {
        // The GPU evaluates every chosen cell; the refresh ignores the unseen ones.
        let (_, cells, m) = choose(&ctx, &g, &s, round as u64 * 16, 500 + round);
        assert_eq!(m, n);
        let sigma: Vec<f32> = cells.iter().map(|&c| sigma_of(c as usize, round)).collect();
        apply(&ctx, &g, &s, &sigma, step_size);
        // The CPU asks only for the seen cells' points.
        let mut asked = 0;
        cpu.update(round as u64 * 16, step_size, &mut |p, out| {
            for (i, o) in out.iter_mut().enumerate() {
                let c = cell_of(&p[3 * i..3 * i + 3]);
                *o = sigma_of(c, round);
                asked += 1;
            }
        }, &mut rng);
        assert_eq!(asked, n_seen);
        assert_same_grid(&ctx, &g, &cpu, &format!("round {round}"));
        let d = g.download(&ctx).unwrap();
        assert!((0..n).all(|i| cpu.is_cell_seen(i) || d[i] == 0.0), "an unseen cell was refreshed");
    }
}
