//! Ray generation, prefix sums and occupancy-grid marching on the device against their CPU twins
//! (`ray_batch_cpu`, a host running sum, `nerf_sampling::march`), outputs poisoned before each
//! kernel. Runs on any adapter (lavapipe in CI); prints a notice and returns where none exists.

use std::path::PathBuf;

use nerf_data::{Background, Dataset, PixelMasks, Split};
use nerf_gpu::rng::rand_f32;
use nerf_gpu::sampling::{
    ray_batch_cpu, GpuImages, GpuMarcher, GpuRayGen, GpuRays, GpuSamples, GpuScan, MarchConfig, PixelFormat, MARCH_STREAM_U,
};
use nerf_gpu::{shaders, GpuContext};
use nerf_rays::{Aabb, Camera, Intrinsics, Ndc, PixelConvention};
use nerf_sampling::{march, CropBox, OccupancyGrid, OccupancyGridConfig, RayMarch, RaySamples, Stepping};
use rand::Rng as _;

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

#[test]
fn sampling_shaders_validate_with_naga() {
    for (name, src) in [("rays", shaders::RAYS), ("march", shaders::MARCH), ("scan", shaders::SCAN)] {
        let src = &shaders::with_common(src);
        let module = naga::front::wgsl::parse_str(src).unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(src)));
        let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
        v.validate(&module).unwrap_or_else(|e| panic!("{name}: {e:?}"));
    }
}

fn submit(ctx: &GpuContext, enc: wgpu::CommandEncoder) {
    ctx.queue.submit([enc.finish()]);
}

// ---------------------------------------------------------------------------------------------
// Prefix sums

#[test]
fn scan_matches_a_host_running_sum() {
    let Some(ctx) = context() else { return };
    let mut rng = nerf_core::rng(11, 0);
    for (case, &len) in [0usize, 1, 255, 256, 257, 1023, 1024, 1025, 100_000, 1_100_000].iter().enumerate() {
        let scan = GpuScan::new(&ctx, len);
        assert_eq!(scan.len(), len);
        // Mostly small values, a few large ones (sums wrap like u32).
        let input: Vec<u32> = (0..len).map(|_| if rng.gen::<f32>() < 0.01 { rng.gen() } else { rng.gen_range(0..300) }).collect();
        let expect = |n: usize| {
            let mut out = Vec::with_capacity(len + 1);
            let mut acc = 0u32;
            out.push(0);
            for (i, &x) in input.iter().enumerate() {
                if i < n {
                    acc = acc.wrapping_add(x);
                }
                out.push(acc);
            }
            out
        };
        let inp = ctx.upload("in", &input);
        // Fixed length, total copied into counters[1].
        let out = ctx.upload("out", &vec![0xDEAD_BEEFu32; len + 1]);
        let counters = ctx.upload("counters", &[7u32, 0xDEAD_BEEF, 9, 9]);
        let mut enc = ctx.encoder("scan");
        scan.record(&ctx, &mut enc, &inp, &out, None, Some((&counters, 1)));
        submit(&ctx, enc);
        let got = ctx.read_u32(&out, len + 1).unwrap();
        let want = expect(len);
        assert_eq!(got, want, "len {len}");
        let c = ctx.read_u32(&counters, 4).unwrap();
        assert_eq!(c, vec![7, want[len], 9, 9], "len {len}: total slot");
        // Dynamic length: only counters[2] inputs are read.
        let n = [0, len / 2, len, len + 5][case % 4];
        let counters = ctx.upload("counters", &[0u32, 0, n as u32, 0]);
        let out = ctx.upload("out", &vec![0xDEAD_BEEFu32; len + 1]);
        let mut enc = ctx.encoder("scan");
        scan.record(&ctx, &mut enc, &inp, &out, Some((&counters, 2)), None);
        submit(&ctx, enc);
        assert_eq!(ctx.read_u32(&out, len + 1).unwrap(), expect(n.min(len)), "len {len}, dynamic n {n}");
    }
}

// ---------------------------------------------------------------------------------------------
// Ray generation

/// A synthetic dataset: cameras on a sphere looking at the origin, random RGBA images whose values
/// are k/255 (or k/65535 when `sixteen`), alpha 0, 1 or in between.
fn dataset(seed: u64, n_views: usize, w: u32, h: u32, sixteen: bool) -> Dataset {
    let mut rng = nerf_core::rng(seed, 0);
    let q = if sixteen { 65535.0f32 } else { 255.0 };
    let mut cameras = vec![];
    let mut images = vec![];
    for _ in 0..n_views {
        let p = loop {
            let v: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.0f32..1.0));
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if l > 0.2 && l < 1.0 {
                break v.map(|x| 4.0 * x / l);
            }
        };
        let norm = |v: [f32; 3]| {
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            v.map(|x| x / l)
        };
        let cross = |a: [f32; 3], b: [f32; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
        let z = norm(p);
        let x = norm(cross([0.0, 0.0, 1.0], z));
        let y = cross(z, x);
        let c2w = [[x[0], y[0], z[0], p[0]], [x[1], y[1], z[1], p[1]], [x[2], y[2], z[2], p[2]], [0.0, 0.0, 0.0, 1.0]];
        let k = Intrinsics::from_fov_x(w, h, rng.gen_range(0.5..1.0));
        cameras.push(Camera::from_c2w(k, &c2w).unwrap());
        let mut img = Vec::with_capacity(4 * (w * h) as usize);
        for _ in 0..w * h {
            for _ in 0..3 {
                img.push(rng.gen_range(0..=q as u32) as f32 / q);
            }
            let a = match rng.gen_range(0..3) {
                0 => 0.0,
                1 => 1.0,
                _ => rng.gen_range(0..=q as u32) as f32 / q,
            };
            img.push(a);
        }
        images.push(img.into());
    }
    Dataset {
        root: PathBuf::from("synthetic"),
        split: Split::Train,
        width: w,
        height: h,
        cameras,
        images,
        file_paths: vec![],
        masks: None,
        depths: None,
        near: 2.0,
        far: 6.0,
        aabb: Aabb::cube(1.5),
        ndc: None,
        depth_bounds: None,
        ngp: None,
        normalization: None,
    }
}

/// Ray buffers for `cap` rays filled with NaN, so a slot the kernel skips fails the comparison.
fn poisoned_rays(ctx: &GpuContext, cap: usize) -> GpuRays {
    let nan = vec![f32::NAN; 3 * cap];
    GpuRays {
        origins: ctx.upload("o", &nan),
        dirs: ctx.upload("d", &nan),
        target: ctx.upload("t", &nan),
        background: ctx.upload("b", &nan),
        views: ctx.upload("v", &vec![u32::MAX; cap]),
        depth_target: ctx.upload("dt", &vec![f32::NAN; cap]),
        capacity: cap,
    }
}

/// Rays drawn on the device: `n` asked for (the counter), `cap` slots poisoned beforehand.
#[allow(clippy::too_many_arguments)]
fn draw_on_device(ctx: &GpuContext, images: &GpuImages, bg: Background, conv: PixelConvention, jitter: bool, seed: u32, n: usize, cap: usize) -> GpuRays {
    let gen = GpuRayGen::new(ctx, bg, conv, jitter);
    let rays = poisoned_rays(ctx, cap);
    let counters = ctx.upload("counters", &[n as u32, 0]);
    gen.set_seed(ctx, seed);
    let mut enc = ctx.encoder("rays");
    gen.record(ctx, &mut enc, &counters, images, &rays);
    submit(ctx, enc);
    rays
}

#[test]
fn ray_generation_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    let cases = [
        (1u32, Background::Random, PixelConvention::Center, false, false, 777usize),
        (2, Background::White, PixelConvention::Center, false, true, 1000),
        (3, Background::Black, PixelConvention::Integer, true, false, 1),
        (4, Background::Random, PixelConvention::Integer, true, true, 5000), // n past the capacity
        (5, Background::White, PixelConvention::Center, true, false, 0),
    ];
    let cap = 1000;
    for (seed, bg, conv, jitter, sixteen, n) in cases {
        let ds = dataset(seed as u64, 3, 13, 7, sixteen);
        let images = GpuImages::new(&ctx, &ds).unwrap();
        assert_eq!(images.n_views(), 3);
        assert_eq!(images.format(), if sixteen { PixelFormat::Rgba16 } else { PixelFormat::Rgba8 });
        let rays = draw_on_device(&ctx, &images, bg, conv, jitter, seed * 7919, n, cap);
        let m = n.min(cap);
        let cpu = ray_batch_cpu(&ds, seed * 7919, m, bg, conv, jitter);
        let read = |b: &wgpu::Buffer| ctx.read_f32(b, 3 * cap).unwrap();
        let (o, d, t, b) = (read(&rays.origins), read(&rays.dirs), read(&rays.target), read(&rays.background));
        // The view of every ray (the colour correction's index), none past n.
        let views = ctx.read_u32(&rays.views, cap).unwrap();
        assert_eq!(&views[..m], &cpu.view_ids[..], "seed {seed}: view indices");
        assert!(views[m..].iter().all(|&v| v == u32::MAX), "seed {seed}: a view past n written");
        for i in 0..3 * cap {
            if i < 3 * m {
                // Origins are copied and random backgrounds use the same 24-bit numbers: exact.
                assert_eq!(o[i], cpu.origins[i], "seed {seed}: origin {i}");
                assert_eq!(b[i], cpu.background[i], "seed {seed}: background {i}");
                // Directions: division, 3×3 product and normalisation (a few f32 ulps, FMA).
                assert!((d[i] - cpu.dirs[i]).abs() <= 4e-6, "seed {seed}: dir {i}: {} vs {}", d[i], cpu.dirs[i]);
                // Targets: u8/255 or u16/65535 decoding and the compositing rule (a few ulps).
                assert!((t[i] - cpu.target[i]).abs() <= 2e-6, "seed {seed}: target {i}: {} vs {}", t[i], cpu.target[i]);
            } else {
                assert!(o[i].is_nan() && d[i].is_nan() && t[i].is_nan() && b[i].is_nan(), "seed {seed}: slot {i} past n written");
            }
        }
        if m > 100 {
            // The batch covers every view and differing pixels (a stuck index would pass the
            // comparison only if the twin were stuck too).
            for v in 0..3 {
                assert!(cpu.view_ids.contains(&v), "seed {seed}: view {v} never drawn");
            }
            let distinct: std::collections::HashSet<_> = cpu.pixel_ids.iter().collect();
            assert!(distinct.len() > 50, "seed {seed}: {} distinct pixels", distinct.len());
            if bg == Background::Random {
                assert!(b[..3 * m].iter().any(|&x| x < 0.5) && b[..3 * m].iter().any(|&x| x > 0.5));
            }
        }
    }
}

/// Cameras with lenses (random coefficients; a fisheye wide enough to look back past 90°):
/// seeds 1–2 OpenCV's radial–tangential and fisheye lenses, 3–4 with their rational and
/// thin-prism terms (OpenCV's 12-coefficient model, COLMAP's `THIN_PRISM_FISHEYE`), 5–6 a
/// rational lens and a Fisheye624 with all its terms, 7–8 a FOV lens beside the Fisheye624, 9–10
/// a division lens (COLMAP's `DIVISION`) beside it, 11–12 beside a wide EUCM lens.
/// The device's f32 Newton steps (the closed forms of FOV, the division and EUCM) find the
/// directions the CPU's f64 ones do, and those differ from the pinhole's.
#[test]
fn ray_generation_through_lenses_matches_its_cpu_twin() {
    use nerf_rays::{Distortion, LensModel};
    let Some(ctx) = context() else { return };
    let cap = 3000;
    for seed in 1..=12u32 {
        let mut ds = dataset(100 + seed as u64, 3, 13, 7, false);
        let mut rng = nerf_core::rng(seed as u64, 5);
        let mut c = |s: f64| rng.gen_range(-s..s);
        // 13 pixels across at a focal length of 3.5: the fisheye's edges are ~106° off its axis.
        ds.cameras[1].intrinsics = Intrinsics { fx: 3.5, fy: 3.5, ..ds.cameras[1].intrinsics };
        // Random lenses that take every point of the image back to a direction (as the loader
        // demands): coefficients drawn until they do.
        let inverts = |cam: &Camera| {
            let k = cam.intrinsics;
            (0..=k.width).all(|i| (0..=k.height).all(|j| cam.distortion.undistort_dir((i as f64 - k.cx as f64) / k.fx as f64, (j as f64 - k.cy as f64) / k.fy as f64).is_some()))
        };
        loop {
            ds.cameras[0].distortion = Distortion { k1: c(0.3), k2: c(0.05), k3: c(0.01), p1: c(0.01), p2: c(0.01), ..Distortion::NONE };
            ds.cameras[1].distortion = Distortion { model: LensModel::Fisheye, k1: c(0.05), k2: c(0.01), k3: c(0.002), k4: c(0.0005), ..Distortion::NONE };
            if seed > 2 {
                let d = &mut ds.cameras[0].distortion;
                (d.k4, d.k5, d.k6) = (c(0.2), c(0.04), c(0.01));
                if seed <= 4 {
                    (d.s1, d.s2, d.s3, d.s4) = (c(0.01), c(0.002), c(0.01), c(0.002));
                }
                let f = &mut ds.cameras[1].distortion;
                (f.p1, f.p2, f.s1, f.s3) = (c(0.005), c(0.005), c(0.005), c(0.005));
                if seed > 4 {
                    f.model = LensModel::Fisheye624;
                    (f.k5, f.k6, f.s2, f.s4) = (c(0.0001), c(0.00002), c(0.001), c(0.001));
                }
                if seed > 6 {
                    ds.cameras[0].distortion = Distortion::fov(1.0 + c(0.5));
                }
                if seed > 8 {
                    ds.cameras[0].distortion = Distortion { model: LensModel::Division, k1: c(0.3), ..Distortion::NONE };
                }
                if seed > 10 {
                    // Wide enough (α²·β·r² > 1 at the corners) to look back past 90°, its rim
                    // ((2α − 1)·β·r² = 1) past the corners.
                    ds.cameras[1].distortion = Distortion::eucm(0.6 + c(0.05), 1.0 + c(0.1));
                }
            }
            if inverts(&ds.cameras[0]) && inverts(&ds.cameras[1]) {
                break;
            }
        }
        let images = GpuImages::new(&ctx, &ds).unwrap();
        let jitter = seed % 2 == 0;
        let rays = draw_on_device(&ctx, &images, Background::White, PixelConvention::Center, jitter, seed, cap, cap);
        let cpu = ray_batch_cpu(&ds, seed, cap, Background::White, PixelConvention::Center, jitter);
        let pinhole = Dataset { cameras: ds.cameras.iter().map(|c| c.pinhole()).collect(), ..ds.clone() };
        let plain = ray_batch_cpu(&pinhole, seed, cap, Background::White, PixelConvention::Center, jitter);
        let d = ctx.read_f32(&rays.dirs, 3 * cap).unwrap();
        let (mut bent, mut behind) = ([0usize; 3], 0);
        for r in 0..cap {
            let v = cpu.view_ids[r] as usize;
            for a in 0..3 {
                let i = 3 * r + a;
                assert!((d[i] - cpu.dirs[i]).abs() <= 2e-5, "seed {seed}: view {v}, ray {r}: dir {:?} vs {:?}", &d[3 * r..3 * r + 3], &cpu.dirs[3 * r..3 * r + 3]);
            }
            bent[v] += (0..3).any(|a| (cpu.dirs[3 * r + a] - plain.dirs[3 * r + a]).abs() > 1e-3) as usize;
            let local = ds.cameras[v].rotation.transpose() * nerf_rays::glam::Vec3::from_slice(&cpu.dirs[3 * r..3 * r + 3]);
            behind += (v == 1 && local.z > 0.0) as usize;
        }
        assert!(bent[0] > 100 && bent[1] > 100 && bent[2] == 0, "seed {seed}: rays the lenses turned, per view: {bent:?}");
        assert!(behind > 10, "seed {seed}: {behind} fisheye rays look back past 90°");
    }
}

/// With depth maps each ray carries its pixel's measured distance, the same as its twin's pixel
/// (`Dataset::depths[view][pixel]`, 0 where there is none); without them the slot is left alone.
#[test]
fn rays_carry_their_pixels_depth() {
    let Some(ctx) = context() else { return };
    let cap = 1500;
    for (seed, jitter, masked) in [(51u32, false, false), (52, true, true)] {
        let mut ds = dataset(seed as u64, 3, 17, 9, false);
        let mut rng = nerf_core::rng(seed as u64, 4);
        let n_pix = (ds.width * ds.height) as usize;
        ds.depths = Some((0..3).map(|_| (0..n_pix).map(|_| if rng.gen_bool(0.1) { 0.0 } else { rng.gen_range(0.5f32..6.0) }).collect()).collect());
        if masked {
            let flags: Vec<Vec<bool>> = (0..3).map(|_| (0..n_pix).map(|_| rng.gen_bool(0.5)).collect()).collect();
            ds.masks = Some(PixelMasks::from_flags(ds.width * ds.height, flags.iter().map(|f| &f[..])));
        }
        let images = GpuImages::new(&ctx, &ds).unwrap();
        let rays = draw_on_device(&ctx, &images, Background::Random, PixelConvention::Center, jitter, seed, cap, cap);
        let cpu = ray_batch_cpu(&ds, seed, cap, Background::Random, PixelConvention::Center, jitter);
        let got = ctx.read_f32(&rays.depth_target, cap).unwrap();
        let maps = ds.depths.as_ref().unwrap();
        let want: Vec<f32> = cpu.view_ids.iter().zip(&cpu.pixel_ids).map(|(&v, &p)| maps[v as usize][p as usize]).collect();
        assert_eq!(got, want, "seed {seed}: depth targets");
        assert!(want.iter().filter(|&&t| t == 0.0).count() > 50 && want.iter().filter(|&&t| t > 0.0).count() > 1000, "seed {seed}");
    }
    // No depth maps: the slots stay as they were (poisoned here).
    let ds = dataset(53, 2, 5, 4, false);
    let rays = draw_on_device(&ctx, &GpuImages::new(&ctx, &ds).unwrap(), Background::White, PixelConvention::Center, false, 53, 100, 100);
    assert!(ctx.read_f32(&rays.depth_target, 100).unwrap().iter().all(|x| x.is_nan()));
    // Depth maps that do not fit the views are refused.
    let bad = Dataset { depths: Some(vec![vec![1.0; 20]]), ..ds };
    let e = GpuImages::new(&ctx, &bad).err().expect("depth maps of 1 view for 2 accepted").to_string();
    assert!(e.contains("depth maps of 1 views for 2 views of 5x4"), "{e}");
}

/// With training masks the kernel draws only kept pixels, the same ones as its twin: random masks
/// (a view keeping nothing, one keeping a single pixel, one keeping every pixel: stored without a
/// list), targets where the masked-out pixels of the images are NaN (a masked pixel read on
/// either side fails the comparison). The last case keeps ~123 k pixels (over 2¹⁶), so the
/// index's multiply-high (`rand_below`) uses every 16-bit partial product.
#[test]
fn masked_ray_generation_matches_its_cpu_twin_and_draws_only_kept_pixels() {
    let Some(ctx) = context() else { return };
    let cap = 3000;
    // The last case's views 0 and 4 share one list (a lens's mask), uploaded once.
    for (seed, jitter, w, h, keep, shared) in
        [(31u32, false, 19u32, 9u32, 0.3, false), (32, true, 19, 9, 0.3, false), (33, false, 320, 240, 0.6, false), (35, true, 23, 7, 0.4, true)]
    {
        let n_views = if shared { 5 } else { 4 };
        let mut ds = dataset(seed as u64, n_views, w, h, false);
        let mut rng = nerf_core::rng(seed as u64, 2);
        let n_pix = (w * h) as usize;
        let mut flags: Vec<Vec<bool>> = (0..4)
            .map(|v| match v {
                1 => vec![false; n_pix],
                2 => (0..n_pix).map(|p| p == 77).collect(),
                3 => vec![true; n_pix],
                _ => (0..n_pix).map(|_| rng.gen_bool(keep)).collect(),
            })
            .collect();
        let listed = if shared {
            flags.push(flags[0].clone());
            let list = |f: &[bool]| -> std::sync::Arc<[u32]> { (0..n_pix as u32).filter(|&p| f[p as usize]).collect() };
            let lens = list(&flags[0]);
            let views = vec![Some(lens.clone()), Some(list(&flags[1])), Some(list(&flags[2])), None, Some(lens.clone())];
            ds.masks = Some(PixelMasks::with_shared_views(w * h, views));
            lens.len() + 1
        } else {
            ds.masks = Some(PixelMasks::from_flags(w * h, flags.iter().map(|f| &f[..])));
            (0..3).map(|v| flags[v].iter().filter(|&&k| k).count()).sum()
        };
        let kept = ds.masks.as_ref().unwrap().total() as usize;
        let images = GpuImages::new(&ctx, &ds).unwrap();
        assert_eq!(images.masks.size() as usize, 4 * (2 * n_views + listed), "seed {seed}: each list once");
        // Change the twin's masked-out pixels after the upload (to the negative of their colour),
        // so that a masked-out pixel drawn on one side and not the other shows.
        for (img, f) in ds.images.iter_mut().zip(&flags) {
            let mut px = img.to_f32();
            for (p, &k) in px.chunks_exact_mut(4).zip(f) {
                if !k {
                    p.iter_mut().for_each(|x| *x = 1.0 - *x);
                }
            }
            *img = px.into();
        }
        let rays = draw_on_device(&ctx, &images, Background::Random, PixelConvention::Center, jitter, seed, cap, cap);
        let cpu = ray_batch_cpu(&ds, seed, cap, Background::Random, PixelConvention::Center, jitter);
        let (o, d, t) = (
            ctx.read_f32(&rays.origins, 3 * cap).unwrap(),
            ctx.read_f32(&rays.dirs, 3 * cap).unwrap(),
            ctx.read_f32(&rays.target, 3 * cap).unwrap(),
        );
        assert_eq!(ctx.read_u32(&rays.views, cap).unwrap(), cpu.view_ids, "seed {seed}: views");
        for i in 0..3 * cap {
            assert_eq!(o[i], cpu.origins[i], "seed {seed}: origin {i}");
            assert!((d[i] - cpu.dirs[i]).abs() <= 4e-6, "seed {seed}: dir {i}: {} vs {}", d[i], cpu.dirs[i]);
            assert!((t[i] - cpu.target[i]).abs() <= 2e-6, "seed {seed}: target {i}: {} vs {}", t[i], cpu.target[i]);
        }
        // Only kept pixels, and (3000 draws of ~220 kept pixels) every one of them; of ~123 k,
        // draws from each view in proportion to the pixels it keeps.
        let drawn: std::collections::HashSet<(u32, u32)> = cpu.view_ids.iter().copied().zip(cpu.pixel_ids.iter().copied()).collect();
        assert!(drawn.iter().all(|&(v, p)| flags[v as usize][p as usize]), "seed {seed}: a masked-out pixel drawn");
        if kept < 1000 {
            assert_eq!(drawn.len(), kept, "seed {seed}: kept pixels never drawn");
        } else {
            let m = ds.masks.as_ref().unwrap();
            let first = cpu.view_ids.iter().filter(|&&v| v == 0).count() as f64 / cap as f64;
            let share = m.kept_in(0) as f64 / kept as f64;
            assert!(kept > 1 << 16 && (first - share).abs() < 0.03, "seed {seed}: {kept} kept, {first:.3} of the draws from view 0, which keeps {share:.3}");
        }
    }
    // Masks that do not match the views are refused.
    let mut ds = dataset(34, 2, 5, 4, false);
    ds.masks = Some(PixelMasks::new(20, vec![vec![1]]));
    let e = GpuImages::new(&ctx, &ds).err().expect("masks of 1 view for 2 accepted").to_string();
    assert!(e.contains("masks of 1 views"), "{e}");
}

#[test]
fn ray_generation_in_ndc_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    let cap = 2000;
    for (seed, jitter) in [(21u32, false), (22, true)] {
        let mut ds = dataset(seed as u64, 4, 17, 11, false);
        // Forward-facing cameras near the origin looking down −z (small random turns), and one
        // that looks sideways: its rays that cannot be warped must become the miss ray on both.
        let mut rng = nerf_core::rng(seed as u64, 1);
        for (i, cam) in ds.cameras.iter_mut().enumerate() {
            let a = if i == 3 { 1.4f32 } else { rng.gen_range(-0.2f32..0.2) };
            let (c, s) = (a.cos(), a.sin());
            let p = [rng.gen_range(-0.3f32..0.3), rng.gen_range(-0.3f32..0.3), rng.gen_range(-0.2f32..0.2)];
            let c2w = [[c, 0.0, s, p[0]], [0.0, 1.0, 0.0, p[1]], [-s, 0.0, c, p[2]]];
            *cam = Camera::from_c2w(cam.intrinsics, &c2w).unwrap();
        }
        ds.ndc = Some(Ndc::new(&ds.cameras[0].intrinsics, Ndc::NEAR_PLANE));
        let images = GpuImages::new(&ctx, &ds).unwrap();
        let rays = draw_on_device(&ctx, &images, Background::White, PixelConvention::Center, jitter, seed, cap, cap);
        let cpu = ray_batch_cpu(&ds, seed, cap, Background::White, PixelConvention::Center, jitter);
        let (o, d) = (ctx.read_f32(&rays.origins, 3 * cap).unwrap(), ctx.read_f32(&rays.dirs, 3 * cap).unwrap());
        let (mut warped, mut missed) = (0, 0);
        for r in 0..cap {
            let (co, cd) = (&cpu.origins[3 * r..3 * r + 3], &cpu.dirs[3 * r..3 * r + 3]);
            if co == [0.0, 0.0, 2.0] {
                missed += 1;
            } else {
                warped += 1;
                assert!((co[2] + 1.0).abs() < 1e-5, "seed {seed}: ray {r} starts on the near plane z' = -1: {co:?}");
            }
            for c in 0..3 {
                // The warp divides by o_z and d_z: a few f32 ulps of values of order 1.
                assert!((o[3 * r + c] - co[c]).abs() <= 2e-5 * (1.0 + co[c].abs()), "seed {seed}: origin {r}: {:?} vs {co:?}", &o[3 * r..3 * r + 3]);
                assert!((d[3 * r + c] - cd[c]).abs() <= 2e-5, "seed {seed}: dir {r}: {:?} vs {cd:?}", &d[3 * r..3 * r + 3]);
            }
        }
        assert!(warped > cap / 2 && missed > 0, "seed {seed}: {warped} warped, {missed} missed");
    }
}

#[test]
fn image_upload_rejects_bad_datasets() {
    let Some(ctx) = context() else { return };
    let mut ds = dataset(9, 2, 4, 3, false);
    ds.images[1] = nerf_data::Pixels::from_f32(&ds.images[1].to_f32()[4..]);
    let e = GpuImages::new(&ctx, &ds).err().expect("short image accepted").to_string();
    assert!(e.contains("synthetic") && e.contains("image 1"), "{e}");
    ds.cameras.clear();
    ds.images.clear();
    let e = GpuImages::new(&ctx, &ds).err().expect("empty dataset accepted").to_string();
    assert!(e.contains("no training views"), "{e}");
}

// ---------------------------------------------------------------------------------------------
// Marching

/// A grid whose occupied cells are a ball plus random noise in the x < 0 half (so that the x > 0
/// half has empty 4³ blocks next to occupied ones).
fn grid(seed: u32, res: u32, min: [f32; 3], max: [f32; 3]) -> OccupancyGrid {
    let cfg = OccupancyGridConfig { resolution: res, ..Default::default() };
    let mut g = OccupancyGrid::new(cfg, min, max);
    g.fill_from(0.01, &mut |p, s| {
        for (k, s) in s.iter_mut().enumerate() {
            let q = &p[3 * k..3 * k + 3];
            let r2 = (q[0] - 0.3).powi(2) + (q[1] + 0.1).powi(2) + q[2].powi(2);
            let h = nerf_gpu::rng::rand_u32(seed, q[0].to_bits() ^ q[1].to_bits().rotate_left(11), q[2].to_bits());
            let noise = q[0] < 0.0 && h % 100 < 8;
            *s = if r2 < 0.36 || noise { 50.0 } else { 0.0 };
        }
    });
    let f = g.occupied_fraction();
    assert!(f > 0.02 && f < 0.5, "occupied fraction {f}");
    g
}

/// The grid's bits in the u32 layout the marcher reads.
fn bitfield(g: &OccupancyGrid) -> Vec<u32> {
    let n = g.densities().len();
    let mut w = vec![0u32; n.div_ceil(32)];
    for i in 0..n {
        if g.is_cell_occupied(i) {
            w[i / 32] |= 1 << (i % 32);
        }
    }
    w
}

/// Rays: most from outside towards points near the box, some that miss, some axis-parallel, some
/// starting inside the box.
fn rays(seed: u64, n: usize) -> (Vec<f32>, Vec<f32>) {
    let mut rng = nerf_core::rng(seed, 1);
    let (mut o, mut d) = (vec![], vec![]);
    for i in 0..n {
        let kind = i % 10;
        let mut orig: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.0f32..1.0));
        let dir: [f32; 3] = match kind {
            0 => {
                // Axis-parallel (two zero components), origin inside the slab of the others.
                let a = rng.gen_range(0..3);
                orig[a] = if rng.gen() { -3.0 } else { 3.0 };
                let mut v = [0.0; 3];
                v[a] = -orig[a].signum();
                v
            }
            1 | 2 => std::array::from_fn(|_| rng.gen_range(-1.0f32..1.0)), // origin inside the box
            _ => {
                let l = (orig.iter().map(|x| x * x).sum::<f32>()).sqrt().max(1e-3);
                let dist = rng.gen_range(2.5f32..4.0);
                orig = orig.map(|x| x / l * dist);
                let spread = if kind == 3 { 3.0 } else { 1.2 }; // kind 3 often misses
                let target: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-spread..spread));
                std::array::from_fn(|a| target[a] - orig[a])
            }
        };
        let l = dir.iter().map(|x| x * x).sum::<f32>().sqrt();
        o.extend(orig);
        d.extend(dir.map(|x| x / l));
    }
    (o, d)
}

/// Reference dense walk (every step looked up, the CPU's rule) with a given `u` per ray.
#[allow(clippy::too_many_arguments)]
fn dense_walk(g: &OccupancyGrid, o: &[f32], d: &[f32], near: f32, far: f32, step: impl Into<Stepping>, max: usize, u: &dyn Fn(usize) -> f32) -> (Vec<u32>, Vec<f32>) {
    let stepping: Stepping = step.into();
    let step = stepping.step;
    let (lo, hi) = g.aabb();
    let res = g.resolution();
    let inv: [f32; 3] = std::array::from_fn(|a| res as f32 / (hi[a] - lo[a]));
    let mut offsets = vec![0u32];
    let mut ts = vec![];
    for r in 0..o.len() / 3 {
        let (oo, dd) = (&o[3 * r..3 * r + 3], &d[3 * r..3 * r + 3]);
        let (mut a0, mut a1, mut hit) = (f32::NEG_INFINITY, f32::INFINITY, true);
        for a in 0..3 {
            if dd[a] == 0.0 {
                hit &= oo[a] >= lo[a] && oo[a] <= hi[a];
            } else {
                let iv = 1.0 / dd[a];
                let (x, y) = ((lo[a] - oo[a]) * iv, (hi[a] - oo[a]) * iv);
                a0 = a0.max(x.min(y));
                a1 = a1.min(x.max(y));
            }
        }
        let (t0, t1) = (near.max(a0), far.min(a1));
        if hit && far > near && t1 > t0 {
            let ur = u(r);
            let s0 = stepping.warp(t0);
            let mut k = 0;
            let mut n = 0;
            loop {
                let t = if stepping.is_cone() { stepping.unwarp(s0 + (k as f32 + ur) * step) } else { t0 + (k as f32 + ur) * step };
                if t >= t1 || n >= max {
                    break;
                }
                let mut idx = 0;
                for a in (0..3).rev() {
                    let gc = (oo[a] + t * dd[a] - lo[a]) * inv[a];
                    idx = idx * res + (gc as usize).min(res - 1);
                }
                if g.is_cell_occupied(idx) {
                    ts.push(t);
                    n += 1;
                }
                k += 1;
            }
        }
        offsets.push(ts.len() as u32);
    }
    (offsets, ts)
}

struct GpuOut {
    offsets: Vec<u32>,
    n_samples: u32,
    positions: Vec<f32>,
    dirs: Vec<f32>,
    t: Vec<f32>,
    dt: Vec<f32>,
}

/// Runs the marcher on `n` of `cap_rays` rays with poisoned outputs.
#[allow(clippy::too_many_arguments)]
fn run_gpu(ctx: &GpuContext, m: &GpuMarcher, bits: &[u32], o: &[f32], d: &[f32], n: usize, seed: u32, jitter: bool) -> GpuOut {
    let (cr, cs) = (m.capacity_rays(), m.capacity_samples());
    let nan = |k: usize| vec![f32::NAN; k];
    let out = GpuSamples {
        offsets: ctx.upload("offsets", &vec![u32::MAX; cr + 1]),
        positions: ctx.upload("positions", &nan(3 * cs)),
        dirs: ctx.upload("dirs", &nan(3 * cs)),
        t: ctx.upload("t", &nan(cs)),
        dt: ctx.upload("dt", &nan(cs)),
        capacity_rays: cr,
        capacity_samples: cs,
    };
    let counters = ctx.upload("counters", &[n as u32, u32::MAX]);
    let bits = ctx.upload("bits", bits);
    let (ob, db) = (ctx.upload("o", o), ctx.upload("d", d));
    m.set_seed(ctx, seed, jitter);
    let mut enc = ctx.encoder("march");
    m.record(ctx, &mut enc, &counters, &bits, &ob, &db, &out);
    submit(ctx, enc);
    GpuOut {
        offsets: ctx.read_u32(&out.offsets, cr + 1).unwrap(),
        n_samples: ctx.read_u32(&counters, 2).unwrap()[1],
        positions: ctx.read_f32(&out.positions, 3 * cs).unwrap(),
        dirs: ctx.read_f32(&out.dirs, 3 * cs).unwrap(),
        t: ctx.read_f32(&out.t, cs).unwrap(),
        dt: ctx.read_f32(&out.dt, cs).unwrap(),
    }
}

/// Compares the GPU's samples of rays `0..n` with reference offsets / t. A ray may differ only by
/// samples whose position lies within 1e-3 cells of a cell face (f32 rounding of `o + t·d`, where
/// the device may fuse the multiply-add, decides the cell there); at most 1 % of the rays.
/// Also checks positions, dirs and dt of every sample, and that nothing past the count is written.
#[allow(clippy::too_many_arguments)]
fn compare(g: &OccupancyGrid, gpu: &GpuOut, ref_off: &[u32], ref_t: &[f32], o: &[f32], d: &[f32], step: impl Into<Stepping>, n: usize, what: &str) {
    let stepping: Stepping = step.into();
    let res = g.resolution() as f32;
    // On a cell face of any level (the faces of a cascade's inner boxes are among them).
    let near_face = |t: f32, r: usize| {
        (0..g.cascades()).any(|m| {
            let (lo, hi) = g.level_box(m);
            (0..3).any(|a| {
                let gc = (o[3 * r + a] + t * d[3 * r + a] - lo[a]) * res / (hi[a] - lo[a]);
                (gc - gc.round()).abs() < 1e-3
            })
        })
    };
    let total = gpu.offsets[n] as usize;
    assert_eq!(gpu.n_samples as usize, total, "{what}: counters[1]");
    let mut mismatched = 0;
    for r in 0..n {
        let gr = gpu.offsets[r] as usize..gpu.offsets[r + 1] as usize;
        let cr = ref_off[r] as usize..ref_off[r + 1] as usize;
        let (gt, ct) = (&gpu.t[gr.clone()], &ref_t[cr]);
        let same = gt.len() == ct.len() && gt.iter().zip(ct).all(|(a, b)| (a - b).abs() <= 1e-5 * b.abs().max(1.0));
        if !same {
            mismatched += 1;
            // Every sample in only one of the lists must sit at a face.
            for (x, y) in [(gt, ct), (ct, gt)] {
                for &t in x {
                    if !y.iter().any(|&s| (s - t).abs() <= 1e-5 * t.abs().max(1.0)) {
                        assert!(near_face(t, r), "{what}: ray {r}: sample t = {t} not in the reference\n gpu {gt:?}\n ref {ct:?}");
                    }
                }
            }
        }
        for k in gr {
            let dt = stepping.dt(gpu.t[k]);
            assert!((gpu.dt[k] - dt).abs() <= 1e-5 * dt, "{what}: dt {} vs {dt} at t = {}", gpu.dt[k], gpu.t[k]);
            for a in 0..3 {
                assert_eq!(gpu.dirs[3 * k + a], d[3 * r + a], "{what}: dirs");
                let p = o[3 * r + a] + gpu.t[k] * d[3 * r + a];
                assert!((gpu.positions[3 * k + a] - p).abs() <= 1e-5 * p.abs().max(1.0), "{what}: position");
            }
        }
    }
    assert!(mismatched <= n / 100, "{what}: {mismatched} of {n} rays differ");
    if mismatched > 0 {
        eprintln!("{what}: {mismatched} rays differ at cell faces only");
    }
    for k in total..gpu.t.len() {
        assert!(gpu.t[k].is_nan() && gpu.dt[k].is_nan() && gpu.positions[3 * k].is_nan(), "{what}: sample {k} past the count written");
    }
}

#[test]
fn marching_without_jitter_matches_the_cpu_march() {
    let Some(ctx) = context() else { return };
    for (seed, res, n_rays, max_samples) in [(1u32, 32u32, 2000usize, 1024usize), (2, 30, 1500, 1024), (3, 16, 1000, 5), (4, 64, 500, 2)] {
        let (lo, hi) = ([-1.5f32, -1.2, -1.0], [1.5f32, 1.3, 1.1]);
        let g = grid(seed, res, lo, hi);
        let step = 3.0f32.sqrt() * 3.0 / [256.0, 200.0, 128.0, 512.0][seed as usize - 1];
        let (near, far) = (0.3f32, 6.0f32);
        let (o, d) = rays(seed as u64, n_rays);
        let mut cpu = RaySamples::default();
        march(&g, &o, &d, &vec![near; n_rays], &vec![far; n_rays], step, max_samples, None, &mut cpu);
        assert!(cpu.len() > n_rays, "seed {seed}: too few samples ({}) to be a test", cpu.len());
        let empty = (0..n_rays).filter(|&r| cpu.ray_len(r) == 0).count();
        assert!(empty > 0 && empty < n_rays / 2, "seed {seed}: {empty} empty rays");
        // The reference dense walk is the CPU march (checks the reference used with jitter below).
        let (ref_off, ref_t) = dense_walk(&g, &o, &d, near, far, step, max_samples, &|_| 0.5);
        assert_eq!(ref_off, cpu.ray_offsets, "seed {seed}: dense walk vs march");
        assert_eq!(ref_t, cpu.t, "seed {seed}: dense walk vs march");

        let cfg = MarchConfig { aabb_min: lo, aabb_max: hi, resolution: res, cascades: 1, step_size: step, near, far, max_samples_per_ray: max_samples as u32, cone_angle: 0.0 };
        // Capacity above what is needed; fewer rays than the capacity (the rest must get offsets = total).
        let cap_rays = n_rays + 37;
        let m = GpuMarcher::new(&ctx, cfg, cap_rays, cpu.len() + 100).unwrap();
        let gpu = run_gpu(&ctx, &m, &bitfield(&g), &[o.clone(), vec![0.0; 111]].concat(), &[d.clone(), vec![1.0; 111]].concat(), n_rays, 5, false);
        assert_eq!(gpu.offsets[0], 0);
        compare(&g, &gpu, &cpu.ray_offsets, &cpu.t, &o, &d, step, n_rays, &format!("seed {seed}"));
        for r in n_rays..=cap_rays {
            assert_eq!(gpu.offsets[r], gpu.offsets[n_rays], "seed {seed}: offsets past n_rays");
        }
    }
}

/// A render at another step than training's: `queue_stepping` marches at its step and sample
/// cap (the CPU march at those), `restore_stepping` at the configured ones again, and the
/// marcher's config never changes. The caps are small enough to cut rays short, so a cap that
/// was not queued would show.
#[test]
fn queued_stepping_marches_at_its_step_and_restores_the_configured_one() {
    let Some(ctx) = context() else { return };
    let (lo, hi) = ([-1.5f32; 3], [1.5f32; 3]);
    let g = grid(31, 32, lo, hi);
    let (near, far, n_rays) = (0.3f32, 6.0f32, 1500usize);
    let (o, d) = rays(31, n_rays);
    let (step, max) = (0.02f32, 24usize);
    let cpu = |step: f32, max: usize| {
        let mut s = RaySamples::default();
        march(&g, &o, &d, &vec![near; n_rays], &vec![far; n_rays], step, max, None, &mut s);
        s
    };
    let (coarse, fine) = (cpu(step, max), cpu(step / 2.0, 2 * max));
    let capped = |s: &RaySamples, m: usize| (0..n_rays).filter(|&r| s.ray_len(r) == m).count();
    assert!(capped(&coarse, max) > 10 && capped(&fine, 2 * max) > 10, "the caps cut rays short");
    assert!(fine.len() > coarse.len() * 3 / 2, "{} vs {} samples", fine.len(), coarse.len());
    let cfg = MarchConfig { aabb_min: lo, aabb_max: hi, resolution: 32, cascades: 1, step_size: step, near, far, max_samples_per_ray: max as u32, cone_angle: 0.0 };
    let m = GpuMarcher::new(&ctx, cfg, n_rays, fine.len() + 100).unwrap();
    let bits = bitfield(&g);
    m.queue_stepping(&ctx, step / 2.0, 2 * max as u32);
    let gpu = run_gpu(&ctx, &m, &bits, &o, &d, n_rays, 0, false);
    compare(&g, &gpu, &fine.ray_offsets, &fine.t, &o, &d, step / 2.0, n_rays, "queued half step");
    assert_eq!((m.config().step_size, m.config().max_samples_per_ray), (step, max as u32), "the config is kept");
    m.restore_stepping(&ctx);
    let gpu = run_gpu(&ctx, &m, &bits, &o, &d, n_rays, 0, false);
    compare(&g, &gpu, &coarse.ray_offsets, &coarse.t, &o, &d, step, n_rays, "restored step");
}

/// The CPU's cropped march of every ray (`RayMarch::cropped`, to the end): offsets and t.
#[allow(clippy::too_many_arguments)]
fn cropped_march(g: &OccupancyGrid, o: &[f32], d: &[f32], near: f32, far: f32, step: f32, max: usize, crop: Option<&CropBox>) -> (Vec<u32>, Vec<f32>) {
    let (mut off, mut ts) = (vec![0u32], vec![]);
    for r in 0..o.len() / 3 {
        let (or, dr) = ([o[3 * r], o[3 * r + 1], o[3 * r + 2]], [d[3 * r], d[3 * r + 1], d[3 * r + 2]]);
        let mut m = RayMarch::cropped(g, or, dr, near, far, crop);
        while !m.is_done() {
            m.advance(g, step, max, usize::MAX, |t| ts.push(t));
        }
        off.push(ts.len() as u32);
    }
    (off, ts)
}

/// A render crop box: `queue_crop` clips every ray's march to it as the CPU's
/// `RayMarch::cropped` (an axis-aligned box: the same samples; a turned one: the same up to
/// rounding at the ends), and `None` marches the whole box again.
#[test]
fn a_queued_crop_box_marches_as_the_cpu_and_is_taken_back() {
    let Some(ctx) = context() else { return };
    let (lo, hi) = ([-1.5f32, -1.2, -1.0], [1.5f32, 1.3, 1.1]);
    let g = grid(41, 32, lo, hi);
    let (near, far, n_rays, step, max) = (0.3f32, 6.0f32, 2000usize, 0.02f32, 1024usize);
    let (o, d) = rays(41, n_rays);
    let (plain_off, plain_t) = cropped_march(&g, &o, &d, near, far, step, max, None);
    let mut plain = RaySamples::default();
    march(&g, &o, &d, &vec![near; n_rays], &vec![far; n_rays], step, max, None, &mut plain);
    assert_eq!((&plain_off, &plain_t), (&plain.ray_offsets, &plain.t), "RayMarch::cropped(None) is the march");
    let cfg = MarchConfig { aabb_min: lo, aabb_max: hi, resolution: 32, cascades: 1, step_size: step, near, far, max_samples_per_ray: max as u32, cone_angle: 0.0 };
    let m = GpuMarcher::new(&ctx, cfg, n_rays, plain.len() + 100).unwrap();
    let bits = bitfield(&g);
    let aligned = CropBox::aabb([0.3, -0.9, -0.6], [1.1, 0.4, 0.5]).unwrap();
    let turned = CropBox::oriented([0.6, -0.1, 0.0], [0.3, 0.5, -0.8], [0.8, 0.6, 1.4]).unwrap();
    for (crop, what) in [(aligned, "axis-aligned crop"), (turned, "turned crop")] {
        let (off, ts) = cropped_march(&g, &o, &d, near, far, step, max, Some(&crop));
        let kept = (0..n_rays).filter(|&r| off[r + 1] > off[r]).count();
        assert!(off[n_rays] > 0 && (off[n_rays] as usize) < plain.len() / 2 && kept > n_rays / 10, "{what}: {} of {} samples", off[n_rays], plain.len());
        // Every sample in the crop.
        let grown = CropBox { half: crop.half.map(|h| h + 1e-4), ..crop };
        for r in 0..n_rays {
            for &t in &ts[off[r] as usize..off[r + 1] as usize] {
                assert!(grown.contains(std::array::from_fn(|a| o[3 * r + a] + t * d[3 * r + a])), "{what}: ray {r} t {t}");
            }
        }
        m.queue_crop(&ctx, Some(&crop));
        let gpu = run_gpu(&ctx, &m, &bits, &o, &d, n_rays, 0, false);
        if crop.is_axis_aligned() {
            compare(&g, &gpu, &off, &ts, &o, &d, step, n_rays, what);
        } else {
            // The box's frame is a rotation the device may round differently (FMA): a sample
            // within rounding of the crop's faces may be in one list only; at most 1 % of rays.
            let differ = (0..n_rays)
                .filter(|&r| {
                    let (a, b) = (&gpu.t[gpu.offsets[r] as usize..gpu.offsets[r + 1] as usize], &ts[off[r] as usize..off[r + 1] as usize]);
                    !(a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-4 * y.abs().max(1.0)))
                })
                .count();
            assert!(differ * 100 <= n_rays, "{what}: {differ} of {n_rays} rays differ");
        }
    }
    m.queue_crop(&ctx, None);
    let gpu = run_gpu(&ctx, &m, &bits, &o, &d, n_rays, 0, false);
    compare(&g, &gpu, &plain.ray_offsets, &plain.t, &o, &d, step, n_rays, "crop taken back");
}

#[test]
fn marching_with_jitter_matches_a_dense_walk_with_the_same_offsets() {
    let Some(ctx) = context() else { return };
    for (seed, res) in [(21u32, 32u32), (22, 24)] {
        let (lo, hi) = ([-1.5f32; 3], [1.5f32; 3]);
        let g = grid(seed, res, lo, hi);
        let step = 0.013f32;
        let (near, far) = (2.0f32, 6.0f32);
        let n_rays = 1500;
        let (o, d) = rays(seed as u64, n_rays);
        let useed = seed * 1_000_003;
        let (ref_off, ref_t) = dense_walk(&g, &o, &d, near, far, step, 1024, &|r| rand_f32(useed, MARCH_STREAM_U, r as u32));
        assert!(ref_t.len() > n_rays);
        let cfg = MarchConfig { aabb_min: lo, aabb_max: hi, resolution: res, cascades: 1, step_size: step, near, far, max_samples_per_ray: 1024, cone_angle: 0.0 };
        let m = GpuMarcher::new(&ctx, cfg, n_rays, ref_t.len()).unwrap();
        let gpu = run_gpu(&ctx, &m, &bitfield(&g), &o, &d, n_rays, useed, true);
        compare(&g, &gpu, &ref_off, &ref_t, &o, &d, step, n_rays, &format!("jitter seed {seed}"));
        // Jitter moves samples off the u = 0.5 grid: a different sample set than without it.
        let (_, t_half) = dense_walk(&g, &o, &d, near, far, step, 1024, &|_| 0.5);
        let shared = gpu.t[..gpu.n_samples as usize].iter().zip(&t_half).filter(|(a, b)| a == b).count();
        assert!(shared < t_half.len() / 10, "jittered samples coincide with unjittered ones ({shared})");
    }
}

#[test]
fn cone_steps_match_the_cpu_march() {
    let Some(ctx) = context() else { return };
    // Cones whose steps start growing inside the box's range of t (t_a = step/cone) and, for the
    // last, stop growing there too (t_b = 1024·t_a), with and without jitter.
    for (seed, res, step, cone, jitter) in [(51u32, 32u32, 0.004f32, 0.05f32, false), (52, 24, 0.0005, 0.1, false), (53, 32, 0.004, 0.05, true)] {
        let (lo, hi) = ([-1.5f32, -1.2, -1.0], [1.5f32, 1.3, 1.1]);
        let g = grid(seed, res, lo, hi);
        let stepping = Stepping::new(step, cone);
        let (near, far) = (0.05f32, 6.0f32);
        let n_rays = 1500;
        let (o, d) = rays(seed as u64, n_rays);
        let useed = seed * 7919;
        let u = |r: usize| if jitter { rand_f32(useed, MARCH_STREAM_U, r as u32) } else { 0.5 };
        let (ref_off, ref_t) = dense_walk(&g, &o, &d, near, far, stepping, 1024, &u);
        if !jitter {
            // The reference is the CPU march.
            let mut cpu = RaySamples::default();
            march(&g, &o, &d, &vec![near; n_rays], &vec![far; n_rays], stepping, 1024, None, &mut cpu);
            assert_eq!((&ref_off, &ref_t), (&cpu.ray_offsets, &cpu.t), "seed {seed}: dense walk vs march");
        }
        // Steps grow: far fewer samples than constant steps of `step` give.
        let (_, flat) = dense_walk(&g, &o, &d, near, far, step, 1024, &u);
        assert!(ref_t.len() > n_rays && 2 * ref_t.len() < flat.len(), "seed {seed}: {} cone samples, {} flat", ref_t.len(), flat.len());
        let cfg = MarchConfig { aabb_min: lo, aabb_max: hi, resolution: res, cascades: 1, step_size: step, near, far, max_samples_per_ray: 1024, cone_angle: cone };
        let m = GpuMarcher::new(&ctx, cfg, n_rays, ref_t.len() + 100).unwrap();
        let gpu = run_gpu(&ctx, &m, &bitfield(&g), &o, &d, n_rays, useed, jitter);
        compare(&g, &gpu, &ref_off, &ref_t, &o, &d, stepping, n_rays, &format!("cone seed {seed}"));
    }
}

#[test]
fn a_cascade_marches_as_the_cpu() {
    let Some(ctx) = context() else { return };
    // Cells occupied at random on every level of 2–4 levels; rays from about the centre (inside
    // the finest level) and from far out, through every level; constant and cone steps.
    let (lo, hi) = ([-3.0f32, -1.0, -2.5], [5.0f32, 7.0, 5.5]);
    let centre: [f32; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
    for (seed, levels, stepping) in [(61u32, 3u32, Stepping::from(0.011)), (62, 4, Stepping::new(0.002, 0.02)), (63, 2, Stepping::from(0.02))] {
        let cfg = OccupancyGridConfig { resolution: 16, cascades: Some(levels), ..Default::default() };
        let mut g = OccupancyGrid::new(cfg, lo, hi);
        let dens: Vec<f32> = (0..g.densities().len() as u32)
            .map(|i| if nerf_gpu::rng::rand_u32(seed, 5, i) % 100 < 6 { 10.0 } else { 0.0 })
            .collect();
        g.set_densities(&dens, 0.01).unwrap();
        let n_rays = 1500;
        let mut rng = nerf_core::rng(seed as u64, 3);
        let (mut o, mut d) = (vec![], vec![]);
        for i in 0..n_rays {
            let spread = if i % 2 == 0 { 2.0 } else { 14.0 };
            o.extend((0..3).map(|a| centre[a] + (rng.gen::<f32>() - 0.5) * spread));
            let v: [f32; 3] = std::array::from_fn(|_| rng.gen::<f32>() - 0.5);
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            d.extend(v.map(|x| x / l));
        }
        let (near, far) = (0.05f32, 20.0f32);
        let mut cpu = RaySamples::default();
        march(&g, &o, &d, &vec![near; n_rays], &vec![far; n_rays], stepping, 1024, None, &mut cpu);
        assert!(cpu.len() > 5 * n_rays, "seed {seed}: too few samples ({})", cpu.len());
        let mc = MarchConfig {
            aabb_min: lo,
            aabb_max: hi,
            resolution: 16,
            cascades: levels,
            step_size: stepping.step,
            near,
            far,
            max_samples_per_ray: 1024,
            cone_angle: stepping.cone_angle,
        };
        let m = GpuMarcher::new(&ctx, mc, n_rays, cpu.len() + 100).unwrap();
        let gpu = run_gpu(&ctx, &m, &bitfield(&g), &o, &d, n_rays, 5, false);
        compare(&g, &gpu, &cpu.ray_offsets, &cpu.t, &o, &d, stepping, n_rays, &format!("{levels} levels, seed {seed}"));
    }
}

#[test]
fn marching_clips_to_the_sample_capacity() {
    let Some(ctx) = context() else { return };
    let (lo, hi) = ([-1.5f32; 3], [1.5f32; 3]);
    let g = grid(31, 32, lo, hi);
    let step = 0.02f32;
    let n_rays = 800;
    let (o, d) = rays(31, n_rays);
    let (ref_off, ref_t) = dense_walk(&g, &o, &d, 0.0, 6.0, step, 1024, &|_| 0.5);
    let total = ref_t.len();
    let cfg = MarchConfig { aabb_min: lo, aabb_max: hi, resolution: 32, cascades: 1, step_size: step, near: 0.0, far: 6.0, max_samples_per_ray: 1024, cone_angle: 0.0 };
    let bits = bitfield(&g);
    // A capacity that ends inside a ray (at its second sample), one that ends exactly at a ray's
    // end, one sample short of everything, and one sample short of the first ray with samples.
    let long = (0..n_rays).find(|&r| ref_off[r + 1] - ref_off[r] >= 3).expect("a ray with 3 samples");
    let first = (0..n_rays).find(|&r| ref_off[r + 1] > 0).expect("a ray with samples");
    let one_short = (ref_off[first + 1] as usize - 1).max(1);
    for cap in [ref_off[long] as usize + 2, ref_off[long + 1] as usize, total / 3, total - 1, one_short] {
        let m = GpuMarcher::new(&ctx, cfg, n_rays, cap).unwrap();
        let gpu = run_gpu(&ctx, &m, &bits, &o, &d, n_rays, 0, false);
        // Whole rays only: every ray that fits entirely keeps its samples, the ray that would
        // cross the capacity and every later one get none.
        let end = *ref_off.iter().filter(|&&x| x as usize <= cap).max().unwrap();
        assert_eq!(gpu.n_samples, end, "cap {cap}: counters[1]");
        for (r, &x) in ref_off.iter().enumerate() {
            assert_eq!(gpu.offsets[r], x.min(end), "cap {cap}: offset {r}");
        }
        for (k, &t) in ref_t.iter().enumerate().take(end as usize) {
            assert!((gpu.t[k] - t).abs() <= 1e-5 * t.abs().max(1.0), "cap {cap}: t[{k}]");
            assert_eq!(gpu.dt[k], step);
        }
        // Nothing is written past them (the buffers start as NaN).
        assert!(gpu.t[end as usize..cap].iter().all(|x| x.is_nan()), "cap {cap}: samples past the whole rays");
    }
    // No rays at all: every offset 0, no samples.
    let m = GpuMarcher::new(&ctx, cfg, 64, 1000).unwrap();
    let gpu = run_gpu(&ctx, &m, &bits, &o[..192], &d[..192], 0, 0, false);
    assert_eq!(gpu.n_samples, 0);
    assert!(gpu.offsets.iter().all(|&x| x == 0));
    assert!(gpu.t.iter().all(|x| x.is_nan()));
}

#[test]
fn marcher_rejects_bad_configurations() {
    let Some(ctx) = context() else { return };
    let good = MarchConfig { aabb_min: [-1.0; 3], aabb_max: [1.0; 3], resolution: 16, cascades: 1, step_size: 0.01, near: 0.0, far: 5.0, max_samples_per_ray: 64, cone_angle: 0.0 };
    assert!(GpuMarcher::new(&ctx, good, 10, 10).is_ok());
    for (bad, word) in [
        (MarchConfig { resolution: 0, ..good }, "resolution"),
        (MarchConfig { step_size: 0.0, ..good }, "step"),
        (MarchConfig { cone_angle: -0.1, ..good }, "cone"),
        (MarchConfig { cone_angle: f32::NAN, ..good }, "cone"),
        (MarchConfig { cascades: 0, ..good }, "cascades"),
        (MarchConfig { cascades: 9, ..good }, "cascades"),
        (MarchConfig { cascades: 2, resolution: 24, ..good }, "divisible by 16"),
        (MarchConfig { aabb_max: [1.0, -1.0, 1.0], ..good }, "box"),
    ] {
        let e = GpuMarcher::new(&ctx, bad, 10, 10).err().expect("accepted").to_string();
        assert!(e.contains(word), "{e}");
    }
}

// ---------------------------------------------------------------------------------------------
// Rendering in rounds

/// A test "field" on the device: σ and rgb from the sample position (its CPU twin: `field_cpu`).
const TEST_FIELD: &str = "
@group(0) @binding(0) var<storage, read> counters: array<u32>;
@group(0) @binding(1) var<storage, read> positions: array<f32>;
@group(0) @binding(2) var<storage, read_write> sigma: array<f32>;
@group(0) @binding(3) var<storage, read_write> rgb: array<f32>;
@compute @workgroup_size(64)
fn field(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = linear_id(gid, nwg, 64u);
    if (i >= counters[1]) { return; }
    let p = vec3<f32>(positions[3u * i], positions[3u * i + 1u], positions[3u * i + 2u]);
    let q = p - vec3<f32>(0.3, -0.1, 0.0);
    sigma[i] = 60.0 * max(0.0, 0.6 - sqrt(dot(q, q)));
    rgb[3u * i] = fract(p.x * 3.0);
    rgb[3u * i + 1u] = fract(p.y * 5.0);
    rgb[3u * i + 2u] = fract(p.z * 7.0);
}
";

fn field_cpu(p: &[f32]) -> (f32, [f32; 3]) {
    let q = [p[0] - 0.3, p[1] + 0.1, p[2]];
    let s = 60.0 * (0.6 - (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt()).max(0.0);
    let fr = |x: f32| x - x.floor();
    (s, [fr(p[0] * 3.0), fr(p[1] * 5.0), fr(p[2] * 7.0)])
}

struct Image {
    rgb: Vec<f32>,
    opacity: Vec<f32>,
    depth: Vec<f32>,
}

#[test]
fn rendering_in_rounds_matches_marching_everything_then_compositing() {
    let Some(ctx) = context() else { return };
    let field = nerf_gpu::Kernel::new(&ctx, &shaders::with_common(TEST_FIELD), "field", &[]);
    let (lo, hi) = ([-1.5f32, -1.2, -1.0], [1.5f32, 1.3, 1.1]);
    let (near, far) = (0.3f32, 6.0f32);
    for (seed, res, n_rays, max_samples, step, cone) in
        [(41u32, 32u32, 1500usize, 1024usize, 0.012f32, 0.0f32), (42, 24, 700, 9, 0.02, 0.0), (43, 32, 1000, 1024, 0.004, 0.05)]
    {
        let g = grid(seed, res, lo, hi);
        let (o, d) = rays(seed as u64, n_rays);
        let mut rng = nerf_core::rng(seed as u64, 9);
        let bg: Vec<f32> = (0..3 * n_rays).map(|_| rng.gen()).collect();
        let cfg = MarchConfig { aabb_min: lo, aabb_max: hi, resolution: res, cascades: 1, step_size: step, near, far, max_samples_per_ray: max_samples as u32, cone_angle: cone };
        let mut cpu = RaySamples::default();
        march(&g, &o, &d, &vec![near; n_rays], &vec![far; n_rays], Stepping::new(step, cone), max_samples, None, &mut cpu);
        let total = cpu.len();
        let (bits, ob, db, bgb) = (ctx.upload("bits", &bitfield(&g)), ctx.upload("o", &o), ctx.upload("d", &d), ctx.upload("bg", &bg));
        for threshold in [0.0f32, 1e-2] {
            // Reference on the device: every sample marched, evaluated, then composited.
            let m = GpuMarcher::new(&ctx, cfg, n_rays, total + 64).unwrap();
            let gpu_ref = {
                let cs = m.capacity_samples();
                let out = GpuSamples::new(&ctx, n_rays, cs);
                let counters = ctx.upload("counters", &[n_rays as u32, 0]);
                let (sigma, rgb) = (ctx.zeros("sigma", 4 * cs), ctx.zeros("rgb", 12 * cs));
                let img = [ctx.zeros("rgb", 12 * n_rays), ctx.zeros("op", 4 * n_rays), ctx.zeros("depth", 4 * n_rays), ctx.zeros("w", 4 * cs)];
                let comp = nerf_gpu::Compositor::new(&ctx, n_rays, threshold, true);
                let mut enc = ctx.encoder("reference");
                m.record(&ctx, &mut enc, &counters, &bits, &ob, &db, &out);
                field.record(&ctx, &mut enc, &[(0, &counters), (1, &out.positions), (2, &sigma), (3, &rgb)], nerf_gpu::groups_1d(cs, 64));
                let pb = nerf_gpu::composite::PackedBuffers {
                    counters: &counters,
                    offsets: &out.offsets,
                    sigma: &sigma,
                    rgb: &rgb,
                    dt: &out.dt,
                    t: &out.t,
                    background: &bgb,
                };
                let tg = nerf_gpu::composite::CompositeTargets { rgb: &img[0], opacity: &img[1], depth: &img[2], weights: &img[3] };
                comp.record_forward(&ctx, &mut enc, &pb, &tg);
                submit(&ctx, enc);
                assert_eq!(ctx.read_u32(&counters, 2).unwrap()[1] as usize, total, "reference marched every sample");
                Image {
                    rgb: ctx.read_f32(&img[0], 3 * n_rays).unwrap(),
                    opacity: ctx.read_f32(&img[1], n_rays).unwrap(),
                    depth: ctx.read_f32(&img[2], n_rays).unwrap(),
                }
            };
            // CPU twin: nerf_sampling::march + nerf_render::composite_forward on the same field.
            let mut cpu_img = nerf_render::CompositeOutputs::default();
            {
                let (mut s, mut c) = (vec![0.0f32; total], vec![0.0f32; 3 * total]);
                for k in 0..total {
                    let (a, b) = field_cpu(&cpu.positions[3 * k..3 * k + 3]);
                    s[k] = a;
                    c[3 * k..3 * k + 3].copy_from_slice(&b);
                }
                nerf_render::composite_forward(&cpu.ray_offsets, &s, &c, &cpu.dt, &cpu.t, Some(&bg), threshold, &mut cpu_img);
            }
            // Rounds: small sample capacities and windows force many rounds, windows smaller than
            // the alive list (the tail goes first next round) and one step per round.
            for (cap_samples, window, kmax) in [(total + 64, usize::MAX, 8u32), (600, 250, 3), (97, 40, 1), (5000, 5000, 64)] {
                let m = GpuMarcher::new(&ctx, cfg, n_rays, cap_samples).unwrap();
                let frame = m.round_frame(&ctx, n_rays + 5, window);
                let nan = |k: usize| ctx.upload("poison", &vec![f32::NAN; k]);
                let out = GpuSamples::new(&ctx, 1, cap_samples);
                let counters = ctx.upload("counters", &[0u32, 0]);
                let (sigma, rgb) = (nan(cap_samples), nan(3 * cap_samples));
                let (o_rgb, o_op, o_depth) = (nan(3 * n_rays), nan(n_rays), nan(n_rays));
                frame.set(&ctx, n_rays, threshold, kmax, true);
                let mut round = 0;
                let mut enc = ctx.encoder("rounds");
                m.record_round_start(&ctx, &mut enc, &frame, &bits);
                let evaluated = loop {
                    for _ in 0..4 {
                        m.record_round_march(&ctx, &mut enc, &frame, round, &counters, &bits, &ob, &db, &out);
                        field.record(&ctx, &mut enc, &[(0, &counters), (1, &out.positions), (2, &sigma), (3, &rgb)], nerf_gpu::groups_1d(cap_samples, 64));
                        m.record_round_composite(&ctx, &mut enc, &frame, round, &counters, &sigma, &rgb, &out);
                        round += 1;
                    }
                    submit(&ctx, std::mem::replace(&mut enc, ctx.encoder("rounds")));
                    let (alive, evaluated) = frame.status(&ctx).unwrap();
                    // Every window ray emits a sample or dies each round: a bound on the rounds.
                    let bound = (total + n_rays) / frame.cap_window() + max_samples + 8;
                    assert!(round <= bound, "rounds do not terminate ({alive} rays alive after {round})");
                    if alive == 0 {
                        break evaluated as usize;
                    }
                };
                m.record_round_output(&ctx, &mut enc, &frame, &bgb, &o_rgb, &o_op, &o_depth);
                submit(&ctx, enc);
                let img = Image {
                    rgb: ctx.read_f32(&o_rgb, 3 * n_rays).unwrap(),
                    opacity: ctx.read_f32(&o_op, n_rays).unwrap(),
                    depth: ctx.read_f32(&o_depth, n_rays).unwrap(),
                };
                let what = format!("seed {seed}, threshold {threshold}, capacity {cap_samples}, window {window}, kmax {kmax}");
                // Same samples, same arithmetic, same order: the same image as the reference.
                for (name, a, b) in [("rgb", &img.rgb, &gpu_ref.rgb), ("opacity", &img.opacity, &gpu_ref.opacity), ("depth", &img.depth, &gpu_ref.depth)] {
                    for (i, (x, y)) in a.iter().zip(b.iter()).enumerate() {
                        assert!((x - y).abs() <= 1e-6 * y.abs().max(1.0), "{what}: {name}[{i}] rounds {x} vs reference {y}");
                    }
                }
                // And the CPU twin's, but for the rare ray whose samples differ at a cell face
                // (see `compare`): at most 1 % of the rays.
                let differ = (0..n_rays)
                    .filter(|&r| {
                        (0..3).any(|c| (img.rgb[3 * r + c] - cpu_img.rgb[3 * r + c]).abs() > 1e-4)
                            || (img.opacity[r] - cpu_img.opacity[r]).abs() > 1e-4
                            || (img.depth[r] - cpu_img.depth[r]).abs() > 1e-4 * cpu_img.depth[r].abs().max(1.0)
                    })
                    .count();
                assert!(differ <= n_rays / 100, "{what}: {differ} rays differ from the CPU twin");
                // Early termination is what saves work: without a threshold every sample is
                // evaluated; with one, the rays stopped inside the ball skip the rest.
                if threshold == 0.0 {
                    assert_eq!(evaluated, total, "{what}: evaluated samples");
                } else if max_samples > 100 && cone == 0.0 {
                    eprintln!("{what}: {evaluated} of {total} samples evaluated");
                    // (With 9 samples per ray at most, or the few of cone steps, few rays get
                    // opaque: nothing to save.)
                    assert!(evaluated < total * 9 / 10, "{what}: {evaluated} of {total} samples evaluated");
                    let stopped = (0..n_rays).filter(|&r| img.opacity[r] > 1.0 - threshold).count();
                    assert!(stopped > n_rays / 10, "{what}: only {stopped} rays stopped early");
                }
            }
        }
    }
}
