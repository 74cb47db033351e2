//! `GpuStratified` / `GpuHierarchical` against their CPU twins `nerf_sampling::{stratified,
//! hierarchical}` (runs on any adapter: lavapipe in CI; prints a notice and returns where no
//! adapter exists). Without jitter the CPU functions are compared directly; with jitter the CPU
//! cannot be handed the kernels' `u`, so a host twin below (the CPU's formulas, and the CPU's own
//! `sample_pdf`, fed the same `u` as the kernels) is compared, after checking that the twin equals
//! the CPU function when both take deterministic `u`.

use nerf_gpu::pdf::{hierarchical_u, stratified_u, GpuHierarchical, GpuStratified, PackedOut};
use nerf_gpu::GpuContext;
use nerf_sampling::{hierarchical, sample_pdf, stratified, RaySamples};
use rand::Rng as _;

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

fn rays(seed: u64, n: usize) -> (Vec<f32>, Vec<f32>) {
    let mut rng = nerf_core::rng(seed, 0);
    let o: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-2.0f32..2.0)).collect();
    let mut d = vec![0.0f32; 3 * n];
    for r in 0..n {
        let v: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.0f32..1.0));
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
        for c in 0..3 {
            d[3 * r + c] = v[c] / l;
        }
    }
    (o, d)
}

struct Out {
    offsets: wgpu::Buffer,
    positions: wgpu::Buffer,
    dirs: wgpu::Buffer,
    t: wgpu::Buffer,
    dt: wgpu::Buffer,
}

/// Output buffers poisoned with NaN (and u32::MAX offsets) so a skipped slot fails.
fn out_buffers(ctx: &GpuContext, rays: usize, samples: usize) -> Out {
    let nan = |k: usize| ctx.upload("out", &vec![f32::NAN; k.max(1)]);
    Out { offsets: ctx.upload("offsets", &vec![u32::MAX; rays + 1]), positions: nan(3 * samples), dirs: nan(3 * samples), t: nan(samples), dt: nan(samples) }
}

impl Out {
    fn packed(&self) -> PackedOut<'_> {
        PackedOut { offsets: &self.offsets, positions: &self.positions, dirs: &self.dirs, t: &self.t, dt: &self.dt }
    }
    fn read(&self, ctx: &GpuContext, n_rays: usize) -> RaySamples {
        let offsets = ctx.read_u32(&self.offsets, n_rays + 1).unwrap();
        let s = *offsets.last().unwrap() as usize;
        RaySamples {
            n_rays,
            positions: ctx.read_f32(&self.positions, 3 * s).unwrap(),
            dirs: ctx.read_f32(&self.dirs, 3 * s).unwrap(),
            t: ctx.read_f32(&self.t, s).unwrap(),
            dt: ctx.read_f32(&self.dt, s).unwrap(),
            ray_indices: vec![],
            ray_offsets: offsets,
        }
    }
}

/// |a − b| ≤ tol·(1 + |b|) everywhere (NaN fails).
fn close(what: &str, a: &[f32], b: &[f32], tol: f32) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= tol * (1.0 + y.abs()), "{what}[{i}]: gpu {x} cpu {y}");
    }
}

/// Offsets equal; t, dt, positions, dirs within `tol` (f32 rounding of the same formulas: the
/// device may contract a·b + c into an FMA and its division is within 2.5 ulp).
fn same_samples(what: &str, g: &RaySamples, c: &RaySamples, tol: f32) {
    assert_eq!(g.ray_offsets, c.ray_offsets, "{what}: offsets");
    close(&format!("{what} t"), &g.t, &c.t, tol);
    close(&format!("{what} dt"), &g.dt, &c.dt, 4.0 * tol);
    close(&format!("{what} positions"), &g.positions, &c.positions, tol);
    assert_eq!(g.dirs, c.dirs, "{what}: dirs are copies");
}

/// As [`same_samples`] for importance samples, where a few may legitimately differ: where `u`
/// lands (within rounding) on a cdf value at the edge of a zero-weight bin, the inverse cdf jumps
/// across that bin, and which side it takes depends on the last bit of the cdf (the H100's FMA
/// contraction moved one sample of 4 800 by 0.2). Such rays must stay rare (≤ 1 % of rays); all
/// other rays must match to `tol`.
fn same_fine_samples(what: &str, g: &RaySamples, c: &RaySamples, tol: f32) {
    assert_eq!(g.ray_offsets, c.ray_offsets, "{what}: offsets");
    assert_eq!(g.dirs, c.dirs, "{what}: dirs are copies");
    let ok = |x: f32, y: f32, tol: f32| (x - y).abs() <= tol * (1.0 + y.abs());
    let mut jumped = 0;
    for r in 0..c.n_rays {
        let range = c.ray_range(r);
        let same_t = range.clone().all(|i| ok(g.t[i], c.t[i], tol));
        if !same_t {
            jumped += 1;
            assert!(g.t[range.clone()].iter().all(|t| t.is_finite()), "{what}: ray {r} not written");
            continue;
        }
        for i in range {
            assert!(ok(g.dt[i], c.dt[i], 4.0 * tol), "{what} dt[{i}]: gpu {} cpu {}", g.dt[i], c.dt[i]);
            for a in 0..3 {
                let (x, y) = (g.positions[3 * i + a], c.positions[3 * i + a]);
                assert!(ok(x, y, tol), "{what} positions[{}]: gpu {x} cpu {y}", 3 * i + a);
            }
        }
    }
    assert!(jumped * 100 <= c.n_rays.max(1), "{what}: {jumped} of {} rays differ", c.n_rays);
}

/// The CPU `stratified` for given `u(r, k)` (its formulas, in its order).
fn stratified_twin(o: &[f32], d: &[f32], near: f32, far: f32, n: usize, u: impl Fn(usize, usize) -> f32) -> RaySamples {
    let n_rays = o.len() / 3;
    let mut s = RaySamples { n_rays, ray_offsets: vec![0], ..Default::default() };
    for r in 0..n_rays {
        let step = (far - near) / n as f32;
        let ts: Vec<f32> = (0..n).map(|i| (near + (i as f32 + u(r, i)) * step).min(near + (i + 1) as f32 * step)).collect();
        push_ray(&mut s, o, d, r, &ts, far);
    }
    s
}

fn push_ray(s: &mut RaySamples, o: &[f32], d: &[f32], r: usize, ts: &[f32], far: f32) {
    for (i, &t) in ts.iter().enumerate() {
        let next = if i + 1 < ts.len() { ts[i + 1] } else { far };
        s.t.push(t);
        s.dt.push((next - t).max(0.0));
        for c in 0..3 {
            s.positions.push(o[3 * r + c] + t * d[3 * r + c]);
            s.dirs.push(d[3 * r + c]);
        }
        s.ray_indices.push(r as u32);
    }
    s.ray_offsets.push(s.t.len() as u32);
}

fn run_stratified(ctx: &GpuContext, k: &GpuStratified, o: &[f32], d: &[f32], jitter: Option<u32>) -> (RaySamples, u32) {
    let n_rays = o.len() / 3;
    let cap = n_rays + 3; // capacity above n_rays: the extra invocations must do nothing
    let out = out_buffers(ctx, cap, cap * k.n_samples());
    let counters = ctx.upload("counters", &[n_rays as u32, u32::MAX]);
    let (ob, db) = (ctx.upload("o", o), ctx.upload("d", d));
    let mut enc = ctx.encoder("stratified");
    k.record(ctx, &mut enc, &counters, &ob, &db, jitter, &out.packed(), cap);
    ctx.queue.submit([enc.finish()]);
    (out.read(ctx, n_rays), ctx.read_u32(&counters, 2).unwrap()[1])
}

#[test]
fn stratified_matches_the_cpu() {
    let Some(ctx) = context() else { return };
    for (seed, n_rays, n) in [(1u64, 257usize, 64usize), (2, 1, 1), (3, 0, 8), (4, 600, 7)] {
        let (o, d) = rays(seed, n_rays);
        let (near, far) = (2.0f32, 6.0f32);
        let k = GpuStratified::new(&ctx, n, near, far).unwrap();
        // Bin centres: the CPU function itself.
        let mut cpu = RaySamples::default();
        stratified(&o, &d, &vec![near; n_rays], &vec![far; n_rays], n, None, &mut cpu);
        let (gpu, count) = run_stratified(&ctx, &k, &o, &d, None);
        assert_eq!(count as usize, n_rays * n);
        same_samples("centres", &gpu, &cpu, 2e-6);
        // The twin reproduces the CPU with u = 0.5 ...
        let twin = stratified_twin(&o, &d, near, far, n, |_, _| 0.5);
        assert_eq!(twin.t, cpu.t);
        assert_eq!(twin.dt, cpu.dt);
        // ... and, with the kernel's u, the jittered kernel.
        let s = 100 + seed as u32;
        let (gpu, _) = run_stratified(&ctx, &k, &o, &d, Some(s));
        let twin = stratified_twin(&o, &d, near, far, n, |r, i| stratified_u(s, n, r, i));
        same_samples("jittered", &gpu, &twin, 2e-6);
        if n_rays > 0 && n > 1 {
            assert_ne!(gpu.t, cpu.t, "jitter moved the samples");
        }
    }
    // An inverted interval gives no samples (as the CPU); an empty one zero-length samples.
    let (o, d) = rays(5, 10);
    let k = GpuStratified::new(&ctx, 4, 3.0, 3.0).unwrap();
    let (gpu, count) = run_stratified(&ctx, &k, &o, &d, Some(1));
    assert_eq!(count, 40);
    assert!(gpu.t.iter().all(|&t| t == 3.0) && gpu.dt.iter().all(|&dt| dt == 0.0));
    let k = GpuStratified::new(&ctx, 4, 3.0, 2.5).unwrap();
    let (gpu, count) = run_stratified(&ctx, &k, &o, &d, Some(1));
    assert_eq!(count, 0);
    assert_eq!(gpu.ray_offsets, vec![0; 11]);
    assert!(GpuStratified::new(&ctx, 0, 2.0, 6.0).is_err());
}

/// A random coarse batch: per ray 0..=max_n sorted t in [2, 6] and weights (some rays all zero).
fn coarse(seed: u64, n_rays: usize, max_n: usize) -> (RaySamples, Vec<f32>) {
    let mut rng = nerf_core::rng(seed, 1);
    let mut s = RaySamples { n_rays, ray_offsets: vec![0], ..Default::default() };
    let mut w = vec![];
    for _ in 0..n_rays {
        let k = if rng.gen::<f32>() < 0.15 { rng.gen_range(0..4) } else { rng.gen_range(0..=max_n) };
        let mut ts: Vec<f32> = (0..k).map(|_| rng.gen_range(2.0f32..6.0)).collect();
        ts.sort_by(f32::total_cmp);
        let zero = rng.gen::<f32>() < 0.1;
        for t in ts {
            s.t.push(t);
            w.push(if zero || rng.gen::<f32>() < 0.3 { 0.0 } else { rng.gen::<f32>().powi(3) });
        }
        s.ray_offsets.push(s.t.len() as u32);
    }
    (s, w)
}

/// The CPU `hierarchical` for given u (its steps, with the CPU's own `sample_pdf`).
fn hierarchical_twin(c: &RaySamples, w: &[f32], o: &[f32], d: &[f32], far: f32, n_fine: usize, jitter: Option<u32>) -> RaySamples {
    let mut s = RaySamples { n_rays: c.n_rays, ray_offsets: vec![0], ..Default::default() };
    for r in 0..c.n_rays {
        let range = c.ray_range(r);
        let (ct, cw) = (&c.t[range.clone()], &w[range]);
        let n_c = ct.len();
        let mut ts = ct.to_vec();
        if n_c >= 3 && n_fine > 0 {
            let bins: Vec<f32> = (0..n_c - 1).map(|i| 0.5 * (ct[i] + ct[i + 1])).collect();
            let u: Vec<f32> = (0..n_fine).map(|k| hierarchical_u(jitter, n_fine, r, k)).collect();
            let mut fine = vec![0.0f32; n_fine];
            sample_pdf(&bins, &cw[1..n_c - 1], &u, &mut fine);
            fine.sort_by(f32::total_cmp);
            ts.extend_from_slice(&fine);
            ts.sort_by(f32::total_cmp); // coarse-first on ties is the same multiset of values
        }
        push_ray(&mut s, o, d, r, &ts, far);
    }
    s
}

/// Runs the fine pass over the coarse batch `(c, w)` of rays `(o, d)` with output buffers
/// poisoned and sized for `cap_rays` rays; checks the counters it writes.
#[allow(clippy::too_many_arguments)]
fn run_hierarchical(
    ctx: &GpuContext,
    k: &GpuHierarchical,
    c: &RaySamples,
    w: &[f32],
    o: &[f32],
    d: &[f32],
    jitter: Option<u32>,
    cap_rays: usize,
) -> RaySamples {
    let n_rays = c.n_rays;
    let out = out_buffers(ctx, cap_rays, k.capacity_samples(cap_rays, c.len()));
    let counters_out = ctx.upload("counters_out", &[u32::MAX; 2]);
    let counters_in = ctx.upload("counters_in", &[n_rays as u32, c.len() as u32]);
    let (c_off, c_t, c_w) = (ctx.upload("c_off", &c.ray_offsets), ctx.upload("c_t", &c.t), ctx.upload("c_w", w));
    let (ob, db) = (ctx.upload("o", o), ctx.upload("d", d));
    let mut enc = ctx.encoder("hierarchical");
    k.record(ctx, &mut enc, &counters_in, &c_off, &c_t, &c_w, &ob, &db, jitter, &counters_out, &out.packed(), cap_rays);
    ctx.queue.submit([enc.finish()]);
    let s = out.read(ctx, n_rays);
    assert_eq!(ctx.read_u32(&counters_out, 2).unwrap(), vec![n_rays as u32, s.len() as u32]);
    s
}

#[test]
fn hierarchical_matches_the_cpu() {
    let Some(ctx) = context() else { return };
    let far = 6.0f32;
    for (seed, n_rays, max_n, n_fine) in [(1u64, 300usize, 40usize, 16usize), (2, 1, 5, 1), (3, 0, 4, 8), (4, 64, 64, 128), (5, 50, 10, 0)] {
        let (c, w) = coarse(seed, n_rays, max_n);
        let (o, d) = rays(seed + 10, n_rays);
        let k = GpuHierarchical::new(&ctx, n_fine, far).unwrap();
        let run = |jitter: Option<u32>| run_hierarchical(&ctx, &k, &c, &w, &o, &d, jitter, n_rays + 2);
        // Deterministic u: the CPU function itself.
        let mut cpu = RaySamples::default();
        hierarchical(&c, &w, &o, &d, &vec![far; n_rays], n_fine, None, &mut cpu);
        let gpu = run(None);
        same_fine_samples(&format!("seed {seed} linspace"), &gpu, &cpu, 1e-5);
        // The twin equals the CPU with linspace u ...
        let twin = hierarchical_twin(&c, &w, &o, &d, far, n_fine, None);
        assert_eq!(twin.ray_offsets, cpu.ray_offsets);
        close("twin", &twin.t, &cpu.t, 1e-6);
        // ... and matches the jittered kernel.
        let s = 7 + seed as u32;
        let gpu = run(Some(s));
        let twin = hierarchical_twin(&c, &w, &o, &d, far, n_fine, Some(s));
        same_fine_samples(&format!("seed {seed} jittered"), &gpu, &twin, 1e-5);
        // Sorted within each ray.
        for r in 0..n_rays {
            let t = &gpu.t[gpu.ray_range(r)];
            assert!(t.windows(2).all(|p| p[0] <= p[1]), "ray {r} not sorted");
        }
    }
}

#[test]
fn samplers_clipped_to_a_box_match_the_cpu_given_clip_segments() {
    let Some(ctx) = context() else { return };
    let (lo, hi) = ([-1.0f32, -0.8, -1.0], [1.2f32, 1.0, 1.0]);
    let (near, far) = (0.0f32, 10.0f32);
    for (seed, n_rays, n) in [(31u64, 400usize, 32usize), (32, 3, 5)] {
        let (o, d) = rays(seed, n_rays);
        let (mut sn, mut sf) = (vec![0.0; n_rays], vec![0.0; n_rays]);
        nerf_sampling::clip_segments(lo, hi, &o, &d, near, far, &mut sn, &mut sf);
        if n_rays > 100 {
            let hits = sn.iter().zip(&sf).filter(|(a, b)| b > a).count();
            assert!(hits > n_rays / 10 && hits < n_rays, "{hits} of {n_rays} rays cross the box: both cases are covered");
        }
        // Coarse: each ray's [near, far] ∩ box.
        let k = GpuStratified::new(&ctx, n, near, far).unwrap().clip_to_box(lo, hi);
        let mut cpu = RaySamples::default();
        stratified(&o, &d, &sn, &sf, n, None, &mut cpu);
        let (gpu, count) = run_stratified(&ctx, &k, &o, &d, None);
        assert_eq!(count as usize, n_rays * n);
        same_samples("clipped centres", &gpu, &cpu, 2e-5);
        // Samples lie in the box (or, for a miss, are zero-length intervals at near).
        for r in 0..n_rays {
            for i in cpu.ray_range(r) {
                if sf[r] > sn[r] {
                    assert!((0..3).all(|a| cpu.positions[3 * i + a] >= lo[a] - 1e-4 && cpu.positions[3 * i + a] <= hi[a] + 1e-4));
                } else {
                    assert_eq!(cpu.dt[i], 0.0);
                }
            }
        }
        // Fine: the last interval closes at each ray's clipped far.
        let (c, w) = coarse(seed, n_rays, 24);
        let h = GpuHierarchical::new(&ctx, 8, far).unwrap().clip_to_box(near, lo, hi);
        let gpu = run_hierarchical(&ctx, &h, &c, &w, &o, &d, None, n_rays);
        let mut cpu = RaySamples::default();
        hierarchical(&c, &w, &o, &d, &sf, 8, None, &mut cpu);
        same_fine_samples("clipped fine", &gpu, &cpu, 2e-5);
    }
}

#[test]
fn samplers_cropped_to_an_oriented_box_match_the_cpu_given_crop_segments() {
    let Some(ctx) = context() else { return };
    // A turned crop box inside a larger scene box (the NDC clip on, as for NDC scenes), and the
    // same box with no scene clip (Blender scenes: [near, far] ∩ crop).
    let crop = nerf_sampling::CropBox::oriented([0.1, -0.2, 0.05], [0.4, -0.3, 1.1], [2.2, 1.6, 2.4]).unwrap();
    let (lo, hi) = ([-1.0f32, -0.8, -1.0], [1.2f32, 1.0, 1.0]);
    let (near, far) = (0.0f32, 10.0f32);
    for (seed, n_rays, n, clip) in [(41u64, 400usize, 32usize, true), (42, 400, 16, false), (43, 3, 5, false)] {
        let (o, d) = rays(seed, n_rays);
        let (mut sn, mut sf) = (vec![near; n_rays], vec![far; n_rays]);
        if clip {
            nerf_sampling::clip_segments(lo, hi, &o, &d, near, far, &mut sn, &mut sf);
        }
        nerf_sampling::crop_segments(&crop, &o, &d, near, &mut sn, &mut sf);
        if n_rays > 100 {
            let hits = sn.iter().zip(&sf).filter(|(a, b)| b > a).count();
            assert!(hits > n_rays / 10 && hits < n_rays, "{hits} of {n_rays} rays cross the crop: both cases are covered");
        }
        let k = GpuStratified::new(&ctx, n, near, far).unwrap();
        let k = if clip { k.clip_to_box(lo, hi) } else { k };
        k.set_crop(Some(crop));
        let mut cpu = RaySamples::default();
        stratified(&o, &d, &sn, &sf, n, None, &mut cpu);
        let (gpu, _) = run_stratified(&ctx, &k, &o, &d, None);
        same_samples("cropped centres", &gpu, &cpu, 2e-5);
        // Every sample of a ray that crosses the crop lies in it; the others are empty.
        for r in 0..n_rays {
            for i in cpu.ray_range(r) {
                if sf[r] > sn[r] {
                    let p = [cpu.positions[3 * i], cpu.positions[3 * i + 1], cpu.positions[3 * i + 2]];
                    let grown = nerf_sampling::CropBox { half: crop.half.map(|h| h + 1e-4), ..crop };
                    assert!(grown.contains(p), "ray {r}: {p:?} outside the crop");
                } else {
                    assert_eq!(cpu.dt[i], 0.0);
                }
            }
        }
        // The crop off again: the plain samples.
        k.set_crop(None);
        let (sn0, sf0) = if clip {
            let (mut a, mut b) = (vec![0.0; n_rays], vec![0.0; n_rays]);
            nerf_sampling::clip_segments(lo, hi, &o, &d, near, far, &mut a, &mut b);
            (a, b)
        } else {
            (vec![near; n_rays], vec![far; n_rays])
        };
        let mut plain = RaySamples::default();
        stratified(&o, &d, &sn0, &sf0, n, None, &mut plain);
        same_samples("uncropped again", &run_stratified(&ctx, &k, &o, &d, None).0, &plain, 2e-5);
        // Fine: the last interval closes at each ray's cropped far.
        let (c, w) = coarse(seed, n_rays, 24);
        let h = GpuHierarchical::new(&ctx, 8, far).unwrap();
        let h = if clip { h.clip_to_box(near, lo, hi) } else { h };
        h.set_crop(Some(crop));
        let gpu = run_hierarchical(&ctx, &h, &c, &w, &o, &d, None, n_rays);
        let mut cpu = RaySamples::default();
        hierarchical(&c, &w, &o, &d, &sf, 8, None, &mut cpu);
        same_fine_samples("cropped fine", &gpu, &cpu, 2e-5);
    }
}
