#![allow(clippy::needless_range_loop)]
//! Compaction to the samples compositing reaches (`shaders/compact.wgsl`) against its CPU twins
//! (`nerf_render::composited_counts`, `RaySamples::compact_into`) on random packed batches, outputs
//! poisoned before each run. Runs on any adapter (lavapipe in CI); prints a notice and returns
//! where none exists.

use nerf_gpu::compact::{GpuCompactor, GpuRowCopy, GpuRowGather};
use nerf_gpu::wgpu;
use nerf_gpu::sampling::GpuSamples;
use nerf_gpu::{DispatchArgs, GpuContext};
use nerf_render::composited_counts;
use nerf_sampling::RaySamples;
use rand::Rng as _;

/// A random packed batch: `n_rays` rays of 0–60 samples (a few empty), sorted `t`, positive `dt`,
/// densities from transparent to opaque-at-once depending on the ray.
fn batch(n_rays: usize, seed: u64) -> (RaySamples, Vec<f32>) {
    let mut g = nerf_core::rng(seed, 3);
    let mut s = RaySamples { n_rays, ray_offsets: vec![0], ..Default::default() };
    let mut sigma = Vec::new();
    for r in 0..n_rays {
        let len = if r % 9 == 4 { 0 } else { g.gen_range(1..60) };
        let scale = [0.0f32, 0.3, 3.0, 30.0, 300.0][g.gen_range(0..5)];
        let mut t = g.gen_range(0.5f32..1.0);
        for _ in 0..len {
            let dt = g.gen_range(0.001f32..0.05);
            s.t.push(t);
            s.dt.push(dt);
            t += dt;
            s.positions.extend((0..3).map(|_| g.gen_range(-1.0f32..1.0)));
            s.dirs.extend((0..3).map(|_| g.gen_range(-1.0f32..1.0)));
            s.ray_indices.push(r as u32);
            sigma.push(scale * g.gen::<f32>());
        }
        s.ray_offsets.push(s.t.len() as u32);
    }
    (s, sigma)
}

fn pad<T: Copy>(v: &[T], len: usize, fill: T) -> Vec<T> {
    let mut p = v.to_vec();
    p.resize(len.max(1), fill);
    p
}

struct Case {
    n_rays: usize,
    cap_rays: usize,
    /// Output capacity as a fraction of the kept total (≥ 1: no clipping).
    cap_frac: f32,
    thr: f32,
    seed: u64,
}

fn run(ctx: &GpuContext, c: &Case) {
    let (s, sigma) = batch(c.n_rays, c.seed);
    let n = s.len();
    let cap_src = n + 13;
    // CPU twin: counts, then the kept total decides the output capacity of the case.
    let mut want_counts = Vec::new();
    composited_counts(&s.ray_offsets, &sigma, &s.dt, c.thr, &mut want_counts);
    let kept: usize = want_counts.iter().map(|&k| k as usize).sum();
    let cap_out = ((kept as f32 * c.cap_frac) as usize).max(1);

    let src = GpuSamples::new(ctx, c.cap_rays, cap_src);
    ctx.write(&src.offsets, 0, &pad(&s.ray_offsets, c.cap_rays + 1, n as u32));
    ctx.write(&src.positions, 0, &pad(&s.positions, 3 * cap_src, f32::NAN));
    ctx.write(&src.dirs, 0, &pad(&s.dirs, 3 * cap_src, f32::NAN));
    ctx.write(&src.t, 0, &pad(&s.t, cap_src, f32::NAN));
    ctx.write(&src.dt, 0, &pad(&s.dt, cap_src, f32::NAN));
    let sig = ctx.upload("sigma", &pad(&sigma, cap_src, f32::NAN));
    let src_counters = ctx.upload("src counters", &[c.n_rays as u32, n as u32]);
    let out = GpuSamples::new(ctx, c.cap_rays, cap_out);
    ctx.write(&out.offsets, 0, &vec![u32::MAX; c.cap_rays + 1]);
    for (b, len) in [(&out.positions, 3 * cap_out), (&out.dirs, 3 * cap_out), (&out.t, cap_out), (&out.dt, cap_out)] {
        ctx.write(b, 0, &vec![f32::NAN; len]);
    }
    let out_counters = ctx.upload("out counters", &[u32::MAX, u32::MAX]);
    let out_rows = ctx.upload("out rows", &vec![u32::MAX; cap_out]);
    let k = GpuCompactor::new(ctx, c.cap_rays, cap_out, c.thr).unwrap();
    let mut enc = ctx.encoder("compact");
    k.record(ctx, &mut enc, &src_counters, &src, &sig, &out_counters, &out, &out_rows);
    ctx.queue.submit([enc.finish()]);

    // Counts: the GPU's offsets give them (before clipping: compare on unclipped cases below).
    let counters = ctx.read_u32(&out_counters, 2).unwrap();
    assert_eq!(counters[0] as usize, c.n_rays, "n_rays copied");
    assert_eq!(counters[1] as usize, kept.min(cap_out), "kept samples");
    let off = ctx.read_u32(&out.offsets, c.cap_rays + 1).unwrap();
    // The GPU's per-ray counts, recovered from its offsets where they are not clipped.
    let mut gpu_counts = Vec::with_capacity(c.n_rays);
    let mut acc = 0usize;
    let mut borderline = 0;
    for r in 0..c.n_rays {
        let got = (off[r + 1] - off[r]) as usize;
        assert_eq!(off[r] as usize, acc.min(cap_out), "offset of ray {r}");
        let w = want_counts[r] as usize;
        let clipped = acc + w > cap_out;
        if !clipped && got != w {
            // exp(−σδ) − 1 on the GPU vs exp_m1 on the CPU: allowed only a step off, at a
            // transmittance within rounding of the threshold.
            let range = s.ray_range(r);
            let mut trans = 1.0f64;
            for k in range.start..range.start + got.min(w) {
                trans *= (-(sigma[k] as f64) * s.dt[k] as f64).exp();
            }
            assert!(got.abs_diff(w) == 1 && (trans / c.thr as f64 - 1.0).abs() < 1e-3, "ray {r}: GPU keeps {got}, CPU {w} (T = {trans})");
            borderline += 1;
        }
        gpu_counts.push(if clipped { w } else { got } as u32);
        acc += if clipped { w } else { got };
    }
    assert!(borderline * 100 <= c.n_rays.max(100), "{borderline} borderline rays");
    for (r, &o) in off.iter().enumerate().skip(c.n_rays + 1) {
        assert_eq!(o as usize, acc.min(cap_out), "offset past the rays ({r})");
    }
    // The copy: exactly RaySamples::compact_into with the same counts and capacity.
    let mut want = RaySamples::default();
    s.compact_into(&gpu_counts, cap_out, &mut want);
    assert_eq!(off[..=c.n_rays], want.ray_offsets[..], "offsets");
    let m = want.len();
    let same = |what: &str, got: Vec<f32>, want: &[f32]| {
        assert_eq!(got.len(), want.len(), "{what}");
        if let Some(i) = (0..got.len()).find(|&i| got[i].to_bits() != want[i].to_bits()) {
            panic!("{what}[{i}]: GPU {} vs CPU {}", got[i], want[i]);
        }
    };
    same("positions", ctx.read_f32(&out.positions, 3 * m).unwrap(), &want.positions);
    same("dirs", ctx.read_f32(&out.dirs, 3 * m).unwrap(), &want.dirs);
    same("t", ctx.read_f32(&out.t, m).unwrap(), &want.t);
    same("dt", ctx.read_f32(&out.dt, m).unwrap(), &want.dt);
    let mut want_rows = Vec::new();
    nerf_sampling::compacted_rows(&s.ray_offsets, &want.ray_offsets, &mut want_rows);
    assert_eq!(ctx.read_u32(&out_rows, m).unwrap(), want_rows, "rows");
    gather_rows(ctx, &out_counters, &out_rows, &want_rows, n, c.seed);
    if c.thr > 0.0 && c.n_rays > 100 {
        assert!(kept < n * 9 / 10, "the case must drop samples ({kept} of {n} kept)");
    }
}

/// `GpuRowGather` after a compaction against the CPU gather by the same rows, for a few row
/// widths (a field's encoding is 32 floats), destination poisoned.
fn gather_rows(ctx: &GpuContext, counters: &wgpu::Buffer, rows: &wgpu::Buffer, want_rows: &[u32], n_src: usize, seed: u64) {
    let m = want_rows.len();
    let cap = m + 5;
    let mut g = nerf_core::rng(seed, 9);
    for width in [1usize, 3, 32] {
        let src: Vec<f32> = (0..(n_src.max(1)) * width).map(|_| g.gen_range(-1.0f32..1.0)).collect();
        let src_buf = ctx.upload("gather src", &src);
        let dst = ctx.upload("gather dst", &vec![f32::NAN; cap * width]);
        let gather = GpuRowGather::new(ctx, width).unwrap();
        // Rows buffers hold the compactor's capacity (≥ m); a batch of m + 5 rows: the extra ones
        // stay. Launched from the device's count (rows of 1 and 32 floats: 64 and 2 rows per
        // workgroup) or, where the table has no entry (3 floats), for the capacity.
        let rows_cap = (rows.size() / 4) as usize;
        let mut enc = ctx.encoder("gather");
        let args = DispatchArgs::new(ctx, cap.min(rows_cap));
        let launch = args.record(ctx, &mut enc, counters, cap.min(rows_cap));
        gather.record(ctx, &mut enc, counters, rows, &src_buf, &dst, launch);
        ctx.queue.submit([enc.finish()]);
        let got = ctx.read_f32(&dst, cap * width).unwrap();
        for (b, &r) in want_rows.iter().enumerate() {
            let want = &src[r as usize * width..(r as usize + 1) * width];
            assert_eq!(&got[b * width..(b + 1) * width], want, "width {width}: row {b} ← {r}");
        }
        assert!(got[m * width..].iter().all(|x| x.is_nan()), "width {width}: written past the kept samples");
    }
    assert!(GpuRowGather::new(ctx, 0).is_err());
}

#[test]
fn compaction_matches_its_cpu_twins() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let cases = [
        Case { n_rays: 1000, cap_rays: 1000, cap_frac: 1.0, thr: 1e-4, seed: 1 },
        Case { n_rays: 777, cap_rays: 1300, cap_frac: 1.5, thr: 1e-2, seed: 2 },
        Case { n_rays: 1500, cap_rays: 1500, cap_frac: 0.6, thr: 1e-4, seed: 3 },
        Case { n_rays: 64, cap_rays: 64, cap_frac: 1.0, thr: 0.0, seed: 4 },
        Case { n_rays: 1, cap_rays: 5, cap_frac: 1.0, thr: 0.5, seed: 5 },
        Case { n_rays: 0, cap_rays: 70, cap_frac: 1.0, thr: 1e-4, seed: 6 },
        Case { n_rays: 3000, cap_rays: 3000, cap_frac: 0.05, thr: 1e-3, seed: 7 },
    ];
    for c in &cases {
        run(&ctx, c);
    }
}

#[test]
fn compactor_rejects_bad_thresholds() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    assert!(GpuCompactor::new(&ctx, 10, 10, f32::NAN).is_err());
    assert!(GpuCompactor::new(&ctx, 10, 10, -1.0).is_err());
}

/// `GpuRowCopy` against the CPU's slice copy: random rows at random offsets, counts from empty to
/// the launch's capacity, launched from the device's count (rows of 1 and 32 floats) or for the
/// capacity (3 and 80 floats); the destination is poisoned, and no row past the count is written.
#[test]
fn row_copy_moves_the_counted_rows_only() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let mut g = nerf_core::rng(0x0c09, 1);
    for width in [1usize, 3, 32, 80] {
        let copy = GpuRowCopy::new(&ctx, width).unwrap();
        for trial in 0..4 {
            let cap = g.gen_range(1..400usize);
            let count = match trial {
                0 => 0,
                1 => cap,
                _ => g.gen_range(0..=cap),
            };
            let (src_row, dst_row) = (g.gen_range(0..300usize), g.gen_range(0..300usize));
            let (n_src, n_dst) = (src_row + cap + g.gen_range(0..5), dst_row + cap + g.gen_range(0..5));
            let src: Vec<f32> = (0..n_src * width).map(|_| g.gen_range(-1.0f32..1.0)).collect();
            let (src_buf, dst) = (ctx.upload("copy src", &src), ctx.upload("copy dst", &vec![f32::NAN; n_dst * width]));
            let counters = ctx.upload("copy counters", &[7u32, count as u32]);
            let offsets = GpuRowCopy::offsets(&ctx, src_row, dst_row);
            let args = DispatchArgs::new(&ctx, cap);
            let mut enc = ctx.encoder("row copy");
            let launch = args.record(&ctx, &mut enc, &counters, cap);
            copy.record(&ctx, &mut enc, &counters, &offsets, &src_buf, &dst, launch);
            ctx.queue.submit([enc.finish()]);
            let got = ctx.read_f32(&dst, n_dst * width).unwrap();
            let (d0, d1) = (dst_row * width, (dst_row + count) * width);
            assert_eq!(&got[d0..d1], &src[src_row * width..(src_row + count) * width], "width {width}, count {count} of {cap}");
            assert!(got[..d0].iter().chain(&got[d1..]).all(|x| x.is_nan()), "width {width}: written outside rows {dst_row}..+{count}");
        }
    }
    assert!(GpuRowCopy::new(&ctx, 0).is_err());
}
