//! The GPU encodings (hash grid forward/backward, spherical harmonics, frequency) against their
//! CPU twins in `nerf-encoding` on random inputs, outputs poisoned with NaN so that a skipped slot
//! fails, launches with `capacity > n` so that the device-side sample count is honoured. Runs on
//! any adapter (lavapipe in CI); prints a notice and skips where no adapter exists.

use nerf_encoding::{
    Encoding, FrequencyEncoding, FrequencyEncodingConfig, HashGrid, GridAlign, HashGridConfig, Precision, ShConfig,
    SphericalHarmonics,
};
use nerf_gpu::encoding::{AtomicMode, GpuFrequencyEncoding, GpuHashGrid, GpuSphericalHarmonics};
use nerf_gpu::layout::COUNTER_N_SAMPLES;
use nerf_gpu::{DispatchArgs, GpuContext, Launch};
use rand::Rng as _;

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

/// A counters buffer with `n` samples (and a different ray count, which the encodings must ignore).
fn counters(ctx: &GpuContext, n: usize) -> wgpu::Buffer {
    let mut c = [0u32; 4];
    c[COUNTER_N_SAMPLES] = n as u32;
    c[1 - COUNTER_N_SAMPLES] = 7_777;
    ctx.upload("counters", &c)
}

fn poisoned(ctx: &GpuContext, len: usize) -> wgpu::Buffer {
    ctx.upload("poisoned", &vec![f32::NAN; len])
}

/// Runs `record` in its own submission and reads `len` floats of `out`.
fn run_and_read(ctx: &GpuContext, out: &wgpu::Buffer, len: usize, record: impl FnOnce(&mut wgpu::CommandEncoder)) -> Vec<f32> {
    let mut enc = ctx.encoder("test");
    record(&mut enc);
    ctx.queue.submit([enc.finish()]);
    ctx.read_f32(out, len).unwrap()
}

/// The launch of a batch of `cap` samples counted in `cnt`: recorded from `args` (the device's
/// count) when `indirect`, else for the capacity.
fn launch<'a>(ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, args: &'a DispatchArgs, cnt: &wgpu::Buffer, cap: usize, indirect: bool) -> Launch<'a> {
    if indirect {
        args.record(ctx, enc, cnt, cap)
    } else {
        Launch::direct(cap)
    }
}

/// `out[..n·dim]` matches `cpu` within `tol(i)` and `out[n·dim..]` kept its NaN poison.
fn check(what: &str, gpu: &[f32], cpu: &[f32], tol: impl Fn(usize) -> f32) {
    assert!(gpu.len() >= cpu.len());
    let (mut worst, mut worst_rel) = (0.0f32, 0.0f32);
    for (i, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        worst = worst.max((g - c).abs());
        worst_rel = worst_rel.max((g - c).abs() / tol(i));
        assert!(g.is_finite(), "{what}[{i}] not written (poison survived): {g}");
        assert!((g - c).abs() <= tol(i), "{what}[{i}]: gpu {g} vs cpu {c}");
    }
    eprintln!("{what}: max |gpu − cpu| = {worst:e} ({worst_rel:.3} of the tolerance)");
    for (i, g) in gpu.iter().enumerate().skip(cpu.len()) {
        assert!(g.is_nan(), "{what}[{i}] beyond n was written: {g}");
    }
}

/// Small grids covering dense and hashed levels and F = 1, 2, 4, 8 (init U(−1, 1) so that every
/// parameter matters at f32 resolution).
fn grid_configs() -> Vec<HashGridConfig> {
    let c = |n_levels, f, log2, base, max, dense| HashGridConfig {
        n_levels,
        n_features_per_level: f,
        log2_hashmap_size: log2,
        base_resolution: base,
        max_resolution: max,
        dense_levels: dense,
        storage: Precision::F32,
        init_scale: 1.0,
        ..Default::default()
    };
    let staggered = |c: HashGridConfig| HashGridConfig { align: GridAlign::Staggered, ..c };
    vec![
        c(6, 2, 12, 4, 64, true),
        c(5, 1, 10, 3, 40, false),
        c(4, 4, 13, 6, 96, true),
        c(3, 8, 9, 2, 30, true),
        // tiny-cuda-nn's staggered levels: dense and hashed, F = 2 and 4.
        staggered(c(6, 2, 12, 4, 64, true)),
        staggered(c(4, 4, 13, 6, 96, false)),
    ]
}

const AABB_MIN: [f32; 3] = [-1.5, -0.25, 2.0];
const AABB_MAX: [f32; 3] = [1.5, 2.75, 2.5];

/// `n` world positions: uniform in (and a little beyond) the box, on its faces, on the grid's
/// cell boundaries, and a few non-finite ones.
fn positions(seed: u64, n: usize, res: &[u32]) -> Vec<f32> {
    let mut r = nerf_core::rng(seed, 0);
    let mut p = Vec::with_capacity(3 * n);
    for i in 0..n {
        for a in 0..3 {
            let (lo, hi) = (AABB_MIN[a], AABB_MAX[a]);
            let e = hi - lo;
            let v = match (i + a) % 6 {
                0 | 1 => lo + r.gen::<f32>() * e,
                2 => lo + (r.gen::<f32>() * 1.2 - 0.1) * e,
                3 => {
                    let l = r.gen_range(0..res.len());
                    lo + (r.gen_range(0..=res[l]) as f32 / res[l] as f32) * e
                }
                4 => [lo, hi][r.gen_range(0..2)],
                _ => lo + r.gen::<f32>() * e,
            };
            p.push(v);
        }
    }
    // Non-finite inputs map like the CPU's clamp (NaN → 0, ±∞ → the faces).
    if n > 10 {
        p[3] = f32::NAN;
        p[7] = f32::INFINITY;
        p[11] = f32::NEG_INFINITY;
    }
    p
}

/// Normalisation of nerf-field-hash: ((p − min)·(1/extent)).max(0).min(1) in f32 (max/min, not
/// clamp: NaN must map to 0 as in the field).
#[allow(clippy::manual_clamp)]
fn normalise(p: &[f32]) -> Vec<f32> {
    let inv: [f32; 3] = std::array::from_fn(|a| 1.0 / (AABB_MAX[a] - AABB_MIN[a]));
    p.chunks_exact(3)
        .flat_map(|q| [0, 1, 2].map(|a| ((q[a] - AABB_MIN[a]) * inv[a]).max(0.0).min(1.0)))
        .collect()
}

#[test]
fn hash_grid_mirrors_the_cpu_layout_and_rejects_bad_input() {
    let Some(ctx) = context() else { return };
    for cfg in grid_configs() {
        let cpu = HashGrid::<f32>::zeros(&cfg).unwrap();
        let gpu = GpuHashGrid::new(&ctx, &cfg, AABB_MIN, AABB_MAX).unwrap();
        assert_eq!(gpu.n_params(), cpu.n_params());
        assert_eq!(gpu.output_dim(), Encoding::<f32>::output_dim(&cpu));
        assert_eq!(gpu.level_offsets(), cpu.level_offsets());
        assert_eq!(gpu.resolutions(), cpu.resolutions());
        assert!((0..cpu.n_levels()).all(|l| gpu.is_dense(l) == cpu.is_dense(l)));
    }
    let bad = HashGridConfig { n_features_per_level: 3, ..HashGridConfig::default() };
    let e = GpuHashGrid::new(&ctx, &bad, AABB_MIN, AABB_MAX).err().unwrap().to_string();
    assert!(e.contains("n_features_per_level"), "{e}");
    let cfg = &grid_configs()[0];
    let e = GpuHashGrid::new(&ctx, cfg, [0.0; 3], [1.0, 0.0, 1.0]).err().unwrap().to_string();
    assert!(e.contains("axis 1"), "{e}");
    let mut g = GpuHashGrid::new(&ctx, cfg, [0.0; 3], [1.0; 3]).unwrap();
    let e = g.set_aabb(&ctx, [0.0; 3], [1.0, 1.0, f32::NAN]).unwrap_err().to_string();
    assert!(e.contains("axis 2"), "{e}");
    let e = GpuSphericalHarmonics::new(&ctx, &ShConfig { degree: 5 }).err().unwrap().to_string();
    assert!(e.contains("degree"), "{e}");
    let big = FrequencyEncodingConfig { n_frequencies: 200, include_input: true };
    let e = GpuFrequencyEncoding::new(&ctx, 3, &big).err().unwrap().to_string();
    assert!(e.contains("n_frequencies"), "{e}");
}

#[test]
fn hash_grid_forward_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    for (ci, cfg) in grid_configs().into_iter().enumerate() {
        let grid = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(100 + ci as u64, 0));
        let l = grid.n_levels();
        assert!((0..l).any(|k| !grid.is_dense(k)), "config {ci} has no hashed level");
        // Start with a unit box and move it: set_aabb must take effect.
        let mut gpu = GpuHashGrid::new(&ctx, &cfg, [0.0; 3], [1.0; 3]).unwrap();
        gpu.set_aabb(&ctx, AABB_MIN, AABB_MAX).unwrap();
        let od = gpu.output_dim();
        let params = ctx.upload("params", grid.params());
        for (n, extra) in [(1500usize, 37usize), (1, 0), (0, 5)] {
            let cap = n + extra;
            let pos = positions(200 + ci as u64 + n as u64, cap, grid.resolutions());
            let mut cpu = vec![0.0f32; n * od];
            grid.forward(&normalise(&pos[..3 * n]), &mut cpu);
            let (cnt, pos_b, out) = (counters(&ctx, n), ctx.upload("positions", &pos), poisoned(&ctx, cap * od));
            // Launched for the capacity (n = 1) and from the device's count (the others).
            let args = DispatchArgs::new(&ctx, cap);
            let got = run_and_read(&ctx, &out, cap * od, |enc| {
                let l = launch(&ctx, enc, &args, &cnt, cap, n != 1);
                gpu.record_forward(&ctx, enc, &cnt, &pos_b, &params, &out, l)
            });
            // The cell, slots and weights are computed with the same f32 operations; only the
            // 8-term weighted sum may be contracted to FMAs (|params| ≤ 1: a few ulp of 1).
            check(&format!("config {ci} n {n} features"), &got, &cpu, |_| 2e-6);
        }
    }
}

/// `storage = "f16"`: the mirror the forward writes against the CPU's `sync_storage` (f32 → f16,
/// round to nearest: at most one f16 ulp apart), and the forward that reads it against the CPU
/// forward on its own mirror. F ≠ 2 is refused with a clear error.
#[test]
fn hash_grid_f16_mirror_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    for (ci, mut cfg) in grid_configs().into_iter().enumerate() {
        cfg.storage = Precision::F16;
        if cfg.n_features_per_level != 2 {
            let e = GpuHashGrid::new(&ctx, &cfg, AABB_MIN, AABB_MAX).err().expect("F ≠ 2 with an f16 mirror").to_string();
            assert!(e.contains("f16") && e.contains("2 features"), "{e}");
            continue;
        }
        let mut grid = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(700 + ci as u64, 0));
        // Values across f16's range, including ones that round (f32 mantissa bits below f16's).
        let mut r = nerf_core::rng(701 + ci as u64, 0);
        grid.params_mut().iter_mut().for_each(|p| *p = r.gen_range(-1.0f32..1.0) * [1.0, 1e-3, 30.0][r.gen_range(0..3)]);
        grid.sync_storage();
        let gpu = GpuHashGrid::new(&ctx, &cfg, AABB_MIN, AABB_MAX).unwrap();
        assert!(gpu.uses_f16_mirror());
        let od = gpu.output_dim();
        let params = ctx.upload("params", grid.params());
        let (n, cap) = (1500usize, 1537usize);
        let pos = positions(702 + ci as u64, cap, grid.resolutions());
        let mut cpu = vec![0.0f32; n * od];
        grid.forward(&normalise(&pos[..3 * n]), &mut cpu);
        let (cnt, pos_b, out) = (counters(&ctx, n), ctx.upload("positions", &pos), poisoned(&ctx, cap * od));
        let args = DispatchArgs::new(&ctx, cap);
        let got = run_and_read(&ctx, &out, cap * od, |enc| {
            let l = launch(&ctx, enc, &args, &cnt, cap, true);
            gpu.record_forward(&ctx, enc, &cnt, &pos_b, &params, &out, l)
        });
        let words = ctx.read_u32(gpu.mirror_buffer().unwrap(), grid.n_params() / 2).unwrap();
        let mut exact = 0;
        for (i, w) in words.iter().enumerate() {
            for (j, bits) in [(w & 0xffff) as u16, (w >> 16) as u16].into_iter().enumerate() {
                let want = half::f16::from_f32(grid.params()[2 * i + j]);
                let ulps = (bits as i32 - want.to_bits() as i32).abs();
                assert!(ulps <= 1, "config {ci}: mirror word {i}.{j}: {bits:#06x}, CPU {:#06x}", want.to_bits());
                exact += (ulps == 0) as usize;
            }
        }
        eprintln!("config {ci}: {exact} of {} mirror values bit-equal to the CPU's", grid.n_params());
        // The same f16 values weighted in f32. Where the adapter rounded every value as the CPU
        // did (lavapipe), only FMA contraction of the 8-term sum may differ: a few f32 ulp of the
        // largest corner value (|p| ≤ 30), far below the f16 rounding the forward must show
        // (reading the f32 table instead is off by up to 2^-11 relative). Elsewhere one f16 ulp of
        // the largest corner value (2^-6) per lookup.
        let tol = if exact == grid.n_params() { 4e-5 } else { 2e-2 };
        check(&format!("config {ci} f16 features"), &got, &cpu, |_| tol);
    }
}

/// `n` world positions as a training batch packs them: runs of consecutive samples along rays
/// (random origins and directions in the box, 1 to 40 samples per ray, steps of 0.4 % of the box),
/// so that neighbouring samples share cells at the coarse levels.
fn ray_positions(seed: u64, n: usize) -> Vec<f32> {
    let mut r = nerf_core::rng(seed, 0);
    let mut p = Vec::with_capacity(3 * n);
    while p.len() < 3 * n {
        let o: [f32; 3] = std::array::from_fn(|_| r.gen::<f32>());
        let d: [f32; 3] = std::array::from_fn(|_| r.gen_range(-1.0f32..1.0));
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
        for s in 0..r.gen_range(1..=40) {
            for a in 0..3 {
                let u = o[a] + 0.004 * s as f32 * d[a] / len;
                p.push(AABB_MIN[a] + u * (AABB_MAX[a] - AABB_MIN[a]));
            }
        }
    }
    p.truncate(3 * n);
    p
}

/// Every accumulation path (compare-and-swap, `atomic<f32>`, and `atomic<f32>` with the dense
/// levels' additions summed over subgroups first) against the CPU, on scattered positions and on
/// rays of consecutive samples (which share coarse cells, the case the subgroup sums are for).
#[test]
fn hash_grid_backward_matches_its_cpu_twin_with_every_atomic_path() {
    let Some(ctx) = context() else { return };
    if !ctx.features.float32_atomics {
        eprintln!("NOTICE: adapter without SHADER_FLOAT32_ATOMIC: only the compare-and-swap path runs");
    } else if !ctx.features.subgroups {
        eprintln!("NOTICE: adapter without SUBGROUP: the subgroup sums are not tested");
    }
    for (ci, cfg) in grid_configs().into_iter().flat_map(|c| [(c.clone(), false), (c, true)]).enumerate() {
        let (cfg, along_rays) = cfg;
        let grid = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(300 + ci as u64, 0));
        let np = grid.n_params();
        let od = Encoding::<f32>::output_dim(&grid);
        let (n, cap) = (1200usize, 1300usize);
        let pos = if along_rays { ray_positions(450 + ci as u64, cap) } else { positions(400 + ci as u64, cap, grid.resolutions()) };
        let mut r = nerf_core::rng(500 + ci as u64, 1);
        // Random upstream gradients (every 7th sample all zero), also in the rows past n that the
        // kernel must not read.
        let d: Vec<f32> = (0..cap * od)
            .map(|k| if (k / od) % 7 == 3 { 0.0 } else { r.gen_range(-1.0f32..1.0) })
            .collect();
        let prefill: Vec<f32> = (0..np).map(|_| r.gen_range(-1.0f32..1.0)).collect();
        let xn = normalise(&pos[..3 * n]);
        let mut cpu = prefill.clone();
        grid.backward(&xn, &d[..n * od], &mut cpu, None);
        // Scale of each sum: |prefill| + Σ w·|d| (the CPU backward of |d|; weights are ≥ 0).
        let mut mag: Vec<f32> = prefill.iter().map(|v| v.abs()).collect();
        let d_abs: Vec<f32> = d[..n * od].iter().map(|v| v.abs()).collect();
        grid.backward(&xn, &d_abs, &mut mag, None);
        let touched = cpu.iter().zip(&prefill).filter(|(a, b)| a != b).count();
        assert!(touched > np / 20 && touched > 100, "config {ci}: only {touched} of {np} slots get gradient");
        let mut modes = vec![AtomicMode::CompareExchange];
        if ctx.features.float32_atomics {
            modes.extend([AtomicMode::Auto, AtomicMode::SubgroupSums]);
        }
        for mode in modes {
            let gpu = GpuHashGrid::with_atomics(&ctx, &cfg, AABB_MIN, AABB_MAX, mode).unwrap();
            assert_eq!(gpu.uses_float_atomics(), mode != AtomicMode::CompareExchange);
            assert_eq!(gpu.uses_subgroup_sums(), mode == AtomicMode::SubgroupSums && ctx.features.subgroups);
            let (cnt, pos_b, d_b) = (counters(&ctx, n), ctx.upload("positions", &pos), ctx.upload("d_features", &d));
            let grads = ctx.upload("grads", &prefill);
            // The compare-and-swap path launched from the device's count, atomic<f32> for the capacity.
            let args = DispatchArgs::new(&ctx, cap);
            let got = run_and_read(&ctx, &grads, np, |enc| {
                let l = launch(&ctx, enc, &args, &cnt, cap, mode == AtomicMode::CompareExchange);
                gpu.record_backward(&ctx, enc, &cnt, &pos_b, &d_b, &grads, l)
            });
            // f32 sums in another (atomic) order on both sides: ≤ (terms per slot ≲ 40)·2^-24·scale.
            check(&format!("config {ci} {mode:?} grads"), &got, &cpu, |i| 4e-6 * mag[i]);
        }
    }
}

#[test]
fn spherical_harmonics_match_their_cpu_twin() {
    let Some(ctx) = context() else { return };
    let mut r = nerf_core::rng(600, 0);
    let (n, cap) = (2000usize, 2100usize);
    // Unit directions (the field's input), plus non-unit ones for the polynomials as written.
    let dirs: Vec<f32> = (0..cap)
        .flat_map(|i| {
            let v: [f32; 3] = std::array::from_fn(|_| r.gen_range(-1.5f32..1.5));
            let s = if i % 3 == 0 { 1.0 } else { 1.0 / (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3) };
            v.map(|c| c * s)
        })
        .collect();
    for degree in 1..=4 {
        let cfg = ShConfig { degree };
        let cpu_enc = SphericalHarmonics::new(&cfg);
        let gpu = GpuSphericalHarmonics::new(&ctx, &cfg).unwrap();
        let od = gpu.output_dim();
        assert_eq!(od, (degree * degree) as usize);
        let mut cpu = vec![0.0f32; n * od];
        cpu_enc.forward(&dirs[..3 * n], &mut cpu);
        let (cnt, d_b, out) = (counters(&ctx, n), ctx.upload("dirs", &dirs), poisoned(&ctx, cap * od));
        let args = DispatchArgs::new(&ctx, cap);
        let got = run_and_read(&ctx, &out, cap * od, |enc| {
            let l = launch(&ctx, enc, &args, &cnt, cap, degree % 2 == 0);
            gpu.record_forward(&ctx, enc, &cnt, &d_b, &out, l)
        });
        // Same products in the same order; FMA contraction of the sums of squares: a few ulp of
        // the largest term (|terms| ≲ 3·1.5³).
        check(&format!("sh degree {degree}"), &got, &cpu, |i| 1e-6 * (1.0 + 4.0 * cpu[i].abs().max(1.0)));
    }
}

#[test]
fn frequency_encoding_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    let mut r = nerf_core::rng(700, 0);
    let cases = [
        (3usize, FrequencyEncodingConfig::nerf_position()),
        (3, FrequencyEncodingConfig::nerf_direction()),
        (3, FrequencyEncodingConfig { n_frequencies: 6, include_input: false }),
        (2, FrequencyEncodingConfig { n_frequencies: 12, include_input: true }),
    ];
    for (ci, (d, cfg)) in cases.into_iter().enumerate() {
        let (n, cap) = (700usize, 750usize);
        // World-scale inputs (|x| ≤ 4, so 2^11·x reaches 8192) with exact special values.
        let specials = [0.0f32, 1.5, -1.5, 1.0, -4.0, std::f32::consts::PI];
        let x: Vec<f32> = (0..cap * d)
            .map(|k| if k % 17 == 0 { specials[(k / 17) % specials.len()] } else { r.gen_range(-4.0f32..4.0) })
            .collect();
        let cpu_enc = FrequencyEncoding::new(d, &cfg);
        let gpu = GpuFrequencyEncoding::new(&ctx, d, &cfg).unwrap();
        let od = gpu.output_dim();
        assert_eq!(od, Encoding::<f32>::output_dim(&cpu_enc));
        let mut cpu = vec![0.0f32; n * od];
        cpu_enc.forward(&x[..n * d], &mut cpu);
        let (cnt, x_b, out) = (counters(&ctx, n), ctx.upload("x", &x), poisoned(&ctx, cap * od));
        let got = run_and_read(&ctx, &out, cap * od, |enc| gpu.record_forward(&ctx, enc, &cnt, &x_b, &out, cap));
        // The reduced argument is within ~1e-7 of the exact one (Cody–Waite, |k| ≤ 1304) and the
        // GPU's sin/cos on [−π, π] within ~4e-7 (NVIDIA's hardware approximation): 2e-6 absolute.
        check(&format!("frequency case {ci}"), &got, &cpu, |_| 2e-6);
    }
}

/// The frequency encoding's input gradient (camera pose refinement) against
/// `FrequencyEncoding::backward` with `d_input`, with ∂L/∂out read from a slice of wider rows (as
/// the paper field's view net hands it over) and from plain rows; poisoned outputs, rows past
/// the count untouched, two layouts in one submission.
#[test]
fn frequency_encoding_input_gradient_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    let mut r = nerf_core::rng(701, 0);
    let cases = [
        (3usize, FrequencyEncodingConfig::nerf_position()),
        (3, FrequencyEncodingConfig::nerf_direction()),
        (3, FrequencyEncodingConfig { n_frequencies: 6, include_input: false }),
        (2, FrequencyEncodingConfig { n_frequencies: 12, include_input: true }),
    ];
    for (ci, (d, cfg)) in cases.into_iter().enumerate() {
        let (n, cap) = (600usize, 650usize);
        let x: Vec<f32> = (0..cap * d).map(|_| r.gen_range(-4.0f32..4.0)).collect();
        let cpu_enc = FrequencyEncoding::new(d, &cfg);
        let gpu = GpuFrequencyEncoding::new(&ctx, d, &cfg).unwrap();
        let od = gpu.output_dim();
        // Layouts: (stride, offset) of a wider row, and plain rows.
        let layouts = [(od + 37, 29), (od, 0)];
        let g: Vec<f32> = (0..cap * od).map(|_| r.gen_range(-1.0f32..1.0)).collect();
        let mut want = vec![0.0f32; n * d];
        cpu_enc.backward(&x[..n * d], &g[..n * od], &mut [], Some(&mut want));
        // Each term: 2^k (cos·g_s − sin·g_c), the GPU's sin/cos within ~4e-7 of the CPU's.
        let tol: Vec<f32> = (0..n * d)
            .map(|i| {
                let (k, j) = (i / d, i % d);
                let skip = if cfg.include_input { d } else { 0 };
                let sum: f32 = (0..cfg.n_frequencies)
                    .map(|b| (1u32 << b) as f32 * (g[k * od + skip + 2 * b * d + j].abs() + g[k * od + skip + 2 * b * d + d + j].abs()))
                    .sum();
                1e-6 + 2e-6 * sum
            })
            .collect();
        let (cnt, x_b) = (counters(&ctx, n), ctx.upload("x", &x));
        let outs: Vec<wgpu::Buffer> = layouts.iter().map(|_| poisoned(&ctx, cap * d)).collect();
        let rows: Vec<wgpu::Buffer> = layouts
            .iter()
            .map(|&(stride, offset)| {
                let mut wide = vec![1e30f32; cap * stride];
                for k in 0..cap {
                    wide[k * stride + offset..k * stride + offset + od].copy_from_slice(&g[k * od..(k + 1) * od]);
                }
                ctx.upload("d_out rows", &wide)
            })
            .collect();
        let mut enc = ctx.encoder("frequency input gradient");
        for ((&(stride, offset), rows), out) in layouts.iter().zip(&rows).zip(&outs) {
            gpu.record_input_gradient(&ctx, &mut enc, &cnt, &x_b, rows, stride, offset, out, cap);
        }
        ctx.queue.submit([enc.finish()]);
        for ((stride, offset), out) in layouts.iter().zip(&outs) {
            let got = ctx.read_f32(out, cap * d).unwrap();
            check(&format!("frequency input gradient case {ci} layout ({stride}, {offset})"), &got, &want, |i| tol[i]);
        }
    }
}

/// dL/d(world position) as the hash field's CPU path computes it (`backward_inputs_t` of
/// `nerf-field-hash`): `HashGrid::backward(xn, d_enc, _, Some(d_pos))`, then the chain rule
/// through `xn = clamp((p − min)·inv_extent, 0, 1)`: times `inv_extent[a]` where `xn[a]` is
/// strictly inside (0, 1), else 0.
fn cpu_position_gradient(grid: &HashGrid<f32>, xn: &[f32], d_enc: &[f32]) -> Vec<f32> {
    let inv: [f32; 3] = std::array::from_fn(|a| 1.0 / (AABB_MAX[a] - AABB_MIN[a]));
    let mut scratch = vec![0.0f32; grid.n_params()];
    let mut d_pos = vec![f32::NAN; xn.len()];
    grid.backward(xn, d_enc, &mut scratch, Some(&mut d_pos));
    for (g, x) in d_pos.chunks_exact_mut(3).zip(xn.chunks_exact(3)) {
        for a in 0..3 {
            g[a] = if x[a] > 0.0 && x[a] < 1.0 { g[a] * inv[a] } else { 0.0 };
        }
    }
    d_pos
}

/// `GpuHashGrid::record_input_gradient` against the CPU field's position gradient on every grid
/// config (dense and hashed levels; F = 1, 2, 4, 8), at scattered positions that include cell
/// boundaries, the box's faces, points outside it and non-finite ones (the clamp rule), with
/// upstream gradients that are zero for whole samples and for single levels (skipped as on the
/// CPU). The output is poisoned with NaN (so an accumulating or skipping kernel fails) and launched
/// for a capacity above the device's count (the rows past it must keep their poison), from the
/// device's count and for the capacity.
#[test]
fn hash_grid_input_gradient_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    let inv: [f32; 3] = std::array::from_fn(|a| 1.0 / (AABB_MAX[a] - AABB_MIN[a]));
    let mut dense_levels = 0;
    for (ci, cfg) in grid_configs().into_iter().enumerate() {
        let grid = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(800 + ci as u64, 0));
        let nl = grid.n_levels();
        assert!((0..nl).any(|l| !grid.is_dense(l)), "config {ci} has no hashed level");
        dense_levels += (0..nl).filter(|l| grid.is_dense(*l)).count();
        let f = cfg.n_features_per_level;
        let od = nl * f;
        let pmax = grid.params().iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let gpu = GpuHashGrid::new(&ctx, &cfg, AABB_MIN, AABB_MAX).unwrap();
        let params = ctx.upload("params", grid.params());
        for (n, extra, indirect) in [(1200usize, 91usize, true), (1000, 33, false), (1, 4, true), (0, 6, true)] {
            let cap = n + extra;
            let seed = 810 + 10 * ci as u64 + n as u64;
            let pos = positions(seed, cap, grid.resolutions());
            let mut r = nerf_core::rng(seed, 1);
            // Upstream gradients: every 7th sample all zero, every 5th (sample, level) zero.
            let d: Vec<f32> = (0..cap * od)
                .map(|k| if (k / od) % 7 == 3 || (k / f) % 5 == 2 { 0.0 } else { r.gen_range(-1.0f32..1.0) })
                .collect();
            let xn = normalise(&pos[..3 * n]);
            let cpu = cpu_position_gradient(&grid, &xn, &d[..n * od]);
            // Σ |terms| per output: per level, Σ_k |∂w_k/∂x_a| = 2 times |s_k| ≤ pmax·Σ_j |g_j|,
            // times the resolution, times inv_extent.
            let mag: Vec<f32> = (0..3 * n)
                .map(|e| {
                    let (i, a) = (e / 3, e % 3);
                    let per_level = (0..nl).map(|l| {
                        let g: f32 = d[i * od + l * f..i * od + l * f + f].iter().map(|v| v.abs()).sum();
                        2.0 * pmax * g * grid.resolutions()[l] as f32
                    });
                    inv[a] * per_level.sum::<f32>()
                })
                .collect();
            if n > 100 {
                let zeros = cpu.iter().filter(|v| **v == 0.0).count();
                let clamped = xn.iter().filter(|v| **v == 0.0 || **v == 1.0).count();
                assert!(clamped > n / 10, "config {ci}: only {clamped} coordinates on or outside the faces");
                assert!(zeros < 3 * n / 2, "config {ci}: {zeros} of {} gradients are zero", 3 * n);
                assert!(cpu.iter().any(|v| v.abs() > 1.0), "config {ci}: gradients suspiciously small");
            }
            let (cnt, pos_b, d_b, out) =
                (counters(&ctx, n), ctx.upload("positions", &pos), ctx.upload("d_enc", &d), poisoned(&ctx, 3 * cap));
            let args = DispatchArgs::new(&ctx, cap);
            let got = run_and_read(&ctx, &out, 3 * cap, |enc| {
                let l = launch(&ctx, enc, &args, &cnt, cap, indirect);
                gpu.record_input_gradient(&ctx, enc, &cnt, &pos_b, &params, &d_b, &out, l)
            });
            // The same f32 operations in the same order; only FMA contraction may differ: a few
            // ulp of the sum of the terms' magnitudes (≈ 40 terms per level).
            check(&format!("config {ci} n {n} d_positions"), &got, &cpu, |e| 1e-30 + 4e-6 * mag[e]);
        }
    }
    assert!(dense_levels > 0, "no config has a dense level");
}

/// `GpuSphericalHarmonics::record_input_gradient` against `SphericalHarmonics::backward` for
/// degrees 1..=4, with the SH gradient read from wider rows (the hash field's colour-net input
/// gradient `[16 density features | SH]`, a padded row with the SH block in the middle, and the
/// plain layout), the other columns filled with values the kernel must not read. The output is
/// poisoned with NaN and launched for a capacity above the device's count.
#[test]
fn spherical_harmonics_input_gradient_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    let (n, cap) = (1700usize, 1789usize);
    for degree in 1..=4u32 {
        let cfg = ShConfig { degree };
        let cpu_enc = SphericalHarmonics::new(&cfg);
        let gpu = GpuSphericalHarmonics::new(&ctx, &cfg).unwrap();
        let od = gpu.output_dim();
        for (li, (stride, offset)) in [(16 + od, 16usize), (od + 7, 3), (od, 0)].into_iter().enumerate() {
            let seed = 900 + 10 * degree as u64 + li as u64;
            let mut r = nerf_core::rng(seed, 0);
            // Unit directions (the field's input), plus non-unit ones for the polynomials as written.
            let dirs: Vec<f32> = (0..cap)
                .flat_map(|i| {
                    let v: [f32; 3] = std::array::from_fn(|_| r.gen_range(-1.5f32..1.5));
                    let s = if i % 3 == 0 { 1.0 } else { 1.0 / (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3) };
                    v.map(|c| c * s)
                })
                .collect();
            let rows: Vec<f32> = (0..cap * stride).map(|_| r.gen_range(-1.0f32..1.0)).collect();
            let d_sh: Vec<f32> = (0..n).flat_map(|k| rows[k * stride + offset..k * stride + offset + od].to_vec()).collect();
            let mut cpu = vec![f32::NAN; 3 * n];
            cpu_enc.backward(&dirs[..3 * n], &d_sh, &mut [], Some(&mut cpu));
            if degree > 1 {
                assert!(cpu.iter().any(|v| v.abs() > 0.1), "degree {degree}: gradients suspiciously small");
            }
            // Σ |terms| per sample: each SH gradient times at most ≈ 5·max(|x|, |y|, |z|, 1)².
            let mag: Vec<f32> = (0..n)
                .map(|k| {
                    let m = dirs[3 * k..3 * k + 3].iter().fold(1.0f32, |m, v| m.max(v.abs()));
                    8.0 * m * m * d_sh[k * od..(k + 1) * od].iter().map(|v| v.abs()).sum::<f32>()
                })
                .collect();
            let (cnt, dirs_b, rows_b, out) =
                (counters(&ctx, n), ctx.upload("dirs", &dirs), ctx.upload("d_color_in", &rows), poisoned(&ctx, 3 * cap));
            let args = DispatchArgs::new(&ctx, cap);
            let got = run_and_read(&ctx, &out, 3 * cap, |enc| {
                let l = launch(&ctx, enc, &args, &cnt, cap, li != 1);
                gpu.record_input_gradient(&ctx, enc, &cnt, &dirs_b, &rows_b, stride, offset, &out, l)
            });
            // The same products and sums in the same order; FMA contraction: a few ulp of Σ |terms|.
            check(&format!("sh degree {degree} stride {stride} offset {offset} d_dirs"), &got, &cpu, |e| 1e-30 + 1e-6 * mag[e / 3]);
        }
    }
}

/// Two SH layouts recorded into one submission each read their own stride and offset (the
/// layout uniform is per layout, not rewritten per call).
#[test]
fn spherical_harmonics_input_gradient_layouts_share_a_submission() {
    let Some(ctx) = context() else { return };
    let cfg = ShConfig { degree: 4 };
    let (cpu_enc, gpu) = (SphericalHarmonics::new(&cfg), GpuSphericalHarmonics::new(&ctx, &cfg).unwrap());
    let (n, od) = (300usize, 16usize);
    let mut r = nerf_core::rng(950, 0);
    let dirs: Vec<f32> = (0..3 * n).map(|_| r.gen_range(-1.0f32..1.0)).collect();
    let layouts = [(od + 16, 16usize), (od + 2, 1)];
    let rows: Vec<Vec<f32>> = layouts.iter().map(|(s, _)| (0..n * s).map(|_| r.gen_range(-1.0f32..1.0)).collect()).collect();
    let (cnt, dirs_b) = (counters(&ctx, n), ctx.upload("dirs", &dirs));
    let rows_b: Vec<wgpu::Buffer> = rows.iter().map(|v| ctx.upload("rows", v)).collect();
    let outs: Vec<wgpu::Buffer> = (0..2).map(|_| poisoned(&ctx, 3 * n)).collect();
    let mut enc = ctx.encoder("two layouts");
    for (li, (s, o)) in layouts.iter().enumerate() {
        gpu.record_input_gradient(&ctx, &mut enc, &cnt, &dirs_b, &rows_b[li], *s, *o, &outs[li], Launch::direct(n));
    }
    ctx.queue.submit([enc.finish()]);
    for (li, (s, o)) in layouts.iter().enumerate() {
        let d_sh: Vec<f32> = (0..n).flat_map(|k| rows[li][k * s + o..k * s + o + od].to_vec()).collect();
        let mut cpu = vec![0.0f32; 3 * n];
        cpu_enc.backward(&dirs, &d_sh, &mut [], Some(&mut cpu));
        let got = ctx.read_f32(&outs[li], 3 * n).unwrap();
        check(&format!("layout {li} d_dirs"), &got, &cpu, |_| 1e-4);
    }
}
