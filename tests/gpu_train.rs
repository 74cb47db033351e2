//! The GPU path end to end on the in-repo scene (lavapipe in CI, any adapter elsewhere): the same
//! config trained on the GPU and on the CPU reaches the same PSNR within a stated tolerance, and a
//! GPU checkpoint restored into a CPU trainer renders the same image. Prints a notice and returns
//! where no adapter exists.

use nerf::data::{Dataset, Split, ViewSelection};
use nerf::gpu::GpuContext;
use nerf::train::{evaluate, SamplerConfig, SceneBounds, TrainConfig, Trainer};
use std::sync::Arc;

mod common;
use common::{light_hash_config, load};

fn device() -> Option<Arc<GpuContext>> {
    GpuContext::for_tests().map(Arc::new)
}

/// GPU and CPU training of one config reach the same PSNR. The hash preset keeps the parameters'
/// average (`ema_decay = 0.95`, as instant-ngp) and the runs are scored with it, so the GPU's
/// average is checked over a whole training here too (tests/ema.rs checks it step by step against
/// the direct sum); the average only reads the trained parameters, so a broken training step
/// fails here all the same.
#[test]
fn gpu_and_cpu_training_reach_the_same_psnr() {
    let Some(ctx) = device() else { return };
    let train = load(Split::Train, ViewSelection::All);
    let test = load(Split::Test, ViewSelection::Every(10));
    let config = light_hash_config(150);
    assert_eq!(config.ema_decay, Some(0.95), "the hash preset's average");
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    let mut psnr = Vec::new();
    for dev in [None, Some(ctx)] {
        let t0 = std::time::Instant::now();
        let mut t = Trainer::new_on(config.clone(), &registry, bounds, dev).unwrap();
        for _ in 0..config.iters {
            t.step(&train).unwrap();
        }
        t.finish().unwrap();
        assert_eq!(t.ema_state().unwrap().unwrap().step, config.iters);
        eprintln!("{}: trained in {:.1} s", t.device(), t0.elapsed().as_secs_f64());
        let r = evaluate(&t, &test, None, |_, _| {}).unwrap();
        println!("{}: {:.2} dB, SSIM {:.3}, {} samples", t.device(), r.psnr, r.ssim, t.samples_seen().unwrap());
        psnr.push(r.psnr);
    }
    // The two paths draw different random rays and jitter (rayon's streams vs the kernels' PCG
    // hash) and sum in a different order, so they are two samples of the same training, not the
    // same numbers. Measured on lavapipe: CPU 16.60 dB, GPU 16.60 dB after 150 steps of this
    // light config on every 10th test view (after 250 steps: 19.08 and 19.25 dB, a test 1.4×
    // as long; the preset's 64-wide nets and 2^13 samples, 20.18 and 20.72 dB, twice as long
    // again). 1.5 dB of tolerance still catches a broken kernel, which stays near the 9.7 dB
    // background-only image.
    assert!(psnr[0] > 15.0, "CPU PSNR {:.2}", psnr[0]);
    assert!((psnr[1] - psnr[0]).abs() < 1.5, "GPU {:.2} dB vs CPU {:.2} dB", psnr[1], psnr[0]);
}

/// The first view of `test` rendered by `t`: colours, opacities and depths (the tests pass
/// [`common::thumbnails`]).
fn render_first_view(t: &Trainer, test: &Dataset, config: &TrainConfig) -> [Vec<f32>; 3] {
    let mut batch = nerf::data::RayBatch::default();
    test.view_rays(0, config.eval_background, config.pixel_convention, &mut batch);
    let n = batch.len();
    let (mut rgb, mut op, mut depth) = (vec![f32::NAN; 3 * n], vec![f32::NAN; n], vec![f32::NAN; n]);
    t.render_rays(&batch.origins, &batch.dirs, &batch.background, &mut rgb, &mut op, &mut depth).unwrap();
    [rgb, op, depth]
}

/// Trains `config` for its `iters` steps on the GPU, moves the checkpoint into a CPU trainer and
/// renders the first test view with both: same parameters (and occupancy grid), deterministic
/// sampling, so the images agree up to f32 summation order (and a marched sample whose cell test
/// flips at a cell face). Returns (max, mean) |Δ| of the colours.
fn gpu_checkpoint_renders_the_same_on_the_cpu(ctx: Arc<GpuContext>, config: &TrainConfig) -> (f32, f32) {
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    let mut gpu = Trainer::new_on(config.clone(), &registry, bounds, Some(ctx)).unwrap();
    assert_eq!(gpu.device(), "gpu");
    for _ in 0..config.iters {
        gpu.step(&train).unwrap();
    }
    let mut cpu = Trainer::new(config.clone(), &registry, bounds).unwrap();
    cpu.restore(gpu.step_count(), &gpu.export_fields().unwrap(), gpu.adam_state().unwrap(), &gpu.sampler_state().unwrap())
        .unwrap();
    // The optimiser state made the trip too (a resumed CPU run continues from the GPU's moments).
    assert_eq!(cpu.adam_state().unwrap().step, config.iters);
    let [g_rgb, g_op, _] = render_first_view(&gpu, &test, config);
    let [c_rgb, c_op, _] = render_first_view(&cpu, &test, config);
    let n = g_op.len();
    assert!(g_rgb.iter().chain(&g_op).all(|x| x.is_finite()));
    let max_diff = g_rgb.iter().zip(&c_rgb).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    let mean_diff = g_rgb.iter().zip(&c_rgb).map(|(a, b)| (a - b).abs()).sum::<f32>() / g_rgb.len() as f32;
    let op_diff = g_op.iter().zip(&c_op).map(|(a, b)| (a - b).abs()).sum::<f32>() / n as f32;
    assert!(op_diff < 1e-3, "opacity mean |Δ| {op_diff}");
    // The rendering field at random points (mesh export): density, and density with colour.
    let m = 3001;
    let mut rng = nerf::core::rng(config.seed ^ 0x6d65_7368, 7);
    use rand::Rng;
    let pos: Vec<f32> = (0..3 * m).map(|i| rng.gen_range(train.aabb.min[i % 3]..train.aabb.max[i % 3])).collect();
    let dirs: Vec<f32> = (0..m)
        .flat_map(|_| {
            let v: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.0f32..1.0));
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
            v.map(|x| x / l)
        })
        .collect();
    let points = |t: &Trainer| {
        let (mut s0, mut s, mut c) = (vec![f32::NAN; m], vec![f32::NAN; m], vec![f32::NAN; 3 * m]);
        t.density_at(&pos, &mut s0).unwrap();
        t.query_points(&pos, &dirs, &mut s, &mut c).unwrap();
        assert_eq!(s0, s, "{}: density_at and query_points disagree", t.device());
        (s, c)
    };
    let ((gs, gc), (cs, cc)) = (points(&gpu), points(&cpu));
    let (lo, hi) = cs.iter().fold((f32::MAX, f32::MIN), |(l, h), &x| (l.min(x), h.max(x)));
    assert!(hi - lo > 1e-3 && lo >= 0.0, "densities from {lo} to {hi}");
    for (k, (a, b)) in gs.iter().zip(&cs).enumerate() {
        assert!((a - b).abs() <= 1e-3 * (1.0 + b.abs()), "point {k}: σ {a} on the GPU, {b} on the CPU");
    }
    let c_diff = gc.iter().zip(&cc).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(c_diff < 1e-4, "colour max |Δ| {c_diff}");
    // The occupancy grid read back from the GPU is the one restored on the CPU.
    match (gpu.occupancy_grid_now().unwrap(), cpu.occupancy_grid_now().unwrap()) {
        (Some(g), Some(c)) => {
            assert_eq!(g.densities(), c.densities());
            assert!(g.occupied_fraction() > 0.0 && g.occupied_fraction() < 1.0, "occupied {}", g.occupied_fraction());
            assert!((0..c.densities().len()).all(|i| g.is_cell_occupied(i) == c.is_cell_occupied(i)));
        }
        (None, None) => assert!(!matches!(config.sampler, SamplerConfig::Occupancy { .. })),
        _ => panic!("a grid on one device only"),
    }
    // Renders at half the training step (`render_step_size`): both devices march the grid
    // training kept at it, and the GPU queues its training step back after the frame.
    if let SamplerConfig::Occupancy { step_size, .. } = config.sampler {
        let fine = step_size / 2.0;
        for t in [&mut gpu, &mut cpu] {
            t.set_render_step_size(Some(fine)).unwrap();
        }
        let [gf, gf_op, _] = render_first_view(&gpu, &test, config);
        let [cf, cf_op, _] = render_first_view(&cpu, &test, config);
        let diff = |a: &[f32], b: &[f32]| {
            let d = a.iter().zip(b).map(|(x, y)| (x - y).abs());
            (d.clone().fold(0.0f32, f32::max), d.sum::<f32>() / a.len() as f32)
        };
        let (max, mean) = diff(&gf, &cf);
        assert!(mean < 1e-3 && max < 0.05 && diff(&gf_op, &cf_op).1 < 1e-3, "half step: GPU vs CPU max {max}, mean {mean}");
        let (_, moved) = diff(&gf, &g_rgb);
        assert!(moved > 1e-5, "the half step renders other samples (mean |Δ| {moved})");
        gpu.set_render_step_size(None).unwrap();
        let [again, _, _] = render_first_view(&gpu, &test, config);
        assert!(diff(&again, &g_rgb).0 <= 1e-6, "back at the training step: max |Δ| {}", diff(&again, &g_rgb).0);
        assert!(cpu.set_render_step_size(Some(-1.0)).unwrap_err().to_string().contains("render_step_size"));
        assert_eq!(cpu.config().render_step_size, Some(fine), "a refused step leaves the setting");
        cpu.set_render_step_size(None).unwrap();
    }
    render_crops_the_same_on_both(&mut gpu, &mut cpu, &test, config, &g_rgb, &c_rgb);
    (max_diff, mean_diff)
}

/// A render crop box (`set_render_crop`) on both devices: a turned box that cuts through the
/// object renders the same on the GPU as on the CPU, changes the image, leaves every pixel whose
/// ray misses it empty (background, opacity 0); a box holding the whole scene box changes
/// nothing (bit for bit on the CPU); and `None` renders the whole scene again.
fn render_crops_the_same_on_both(gpu: &mut Trainer, cpu: &mut Trainer, test: &Dataset, config: &TrainConfig, g_rgb: &[f32], c_rgb: &[f32]) {
    use nerf::sampling::CropBox;
    let diff = |a: &[f32], b: &[f32]| {
        let d = a.iter().zip(b).map(|(x, y)| (x - y).abs());
        (d.clone().fold(0.0f32, f32::max), d.sum::<f32>() / a.len() as f32)
    };
    let whole = CropBox::aabb([-10.0; 3], [10.0; 3]).unwrap();
    cpu.set_render_crop(Some(whole)).unwrap();
    assert_eq!(render_first_view(cpu, test, config)[0], c_rgb, "a crop holding the scene box changes nothing");
    let crop = CropBox::oriented([0.25, 0.0, 0.1], [0.0, 0.2, 0.6], [1.4, 3.0, 2.0]).unwrap();
    for t in [&mut *gpu, &mut *cpu] {
        t.set_render_crop(Some(crop)).unwrap();
    }
    let [gc, gc_op, _] = render_first_view(gpu, test, config);
    let [cc, cc_op, _] = render_first_view(cpu, test, config);
    let (max, mean) = diff(&gc, &cc);
    assert!(mean < 1e-3 && max < 0.05 && diff(&gc_op, &cc_op).1 < 1e-3, "cropped: GPU vs CPU max {max}, mean {mean}");
    let (_, moved) = diff(&cc, c_rgb);
    assert!(moved > 1e-3, "the crop cuts the object (mean |Δ| {moved})");
    let mut batch = nerf::data::RayBatch::default();
    test.view_rays(0, config.eval_background, config.pixel_convention, &mut batch);
    let (near, far) = (test.near, test.far);
    let mut missed = 0;
    for r in 0..batch.len() {
        let (o, d) = (&batch.origins[3 * r..3 * r + 3], &batch.dirs[3 * r..3 * r + 3]);
        let (a, b) = crop.slab([o[0], o[1], o[2]], [d[0], d[1], d[2]]);
        if b.min(far) < a.max(near) {
            missed += 1;
            for (rgb, op) in [(&gc, &gc_op), (&cc, &cc_op)] {
                assert_eq!(op[r], 0.0, "pixel {r} misses the crop");
                assert_eq!(&rgb[3 * r..3 * r + 3], &batch.background[3 * r..3 * r + 3], "pixel {r} is background");
            }
        }
    }
    assert!(missed > batch.len() / 10, "{missed} of {} rays miss the crop", batch.len());
    gpu.set_render_crop(None).unwrap();
    assert!(diff(&render_first_view(gpu, test, config)[0], g_rgb).0 <= 1e-6, "uncropped again");
    cpu.set_render_crop(None).unwrap();
    // A box beside the scene would render nothing: refused, and the setting kept.
    let beside = CropBox::aabb([5.0; 3], [6.0; 3]).unwrap();
    assert!(cpu.set_render_crop(Some(beside)).unwrap_err().to_string().contains("outside the scene's box"));
    assert!(cpu.render_crop().is_none());
}

#[test]
fn gpu_checkpoints_render_the_same_on_the_cpu_with_every_sampler() {
    let Some(ctx) = device() else { return };
    // The hash field with occupancy marching.
    let (max, mean) = gpu_checkpoint_renders_the_same_on_the_cpu(ctx.clone(), &light_hash_config(20));
    println!("occupancy: max |Δ| {max:.2e}, mean {mean:.2e}");
    assert!(mean < 1e-3 && max < 0.05, "occupancy: max {max}, mean {mean}");
    // The paper's field (small) with stratified, then hierarchical sampling.
    let tiny = |sampler| TrainConfig {
        iters: 5,
        batch_rays: 128,
        field_config: serde_json::json!({"width": 32, "depth": 3, "skips": [1], "view_width": 16}),
        sampler,
        ..TrainConfig::default()
    };
    for (name, sampler) in [
        ("stratified", SamplerConfig::Stratified { n_samples: 24 }),
        ("hierarchical", SamplerConfig::Hierarchical { n_coarse: 16, n_fine: 16 }),
    ] {
        let (max, mean) = gpu_checkpoint_renders_the_same_on_the_cpu(ctx.clone(), &tiny(sampler));
        println!("{name}: max |Δ| {max:.2e}, mean {mean:.2e}");
        // No marching: only summation order differs (importance samples can jump a zero-weight
        // bin on rounding, see crates/gpu/tests/pdf.rs, hence the looser max).
        assert!(mean < 1e-4 && max < 0.05, "{name}: max {max}, mean {mean}");
    }
}

/// Training marches at its own step after a render at a finer one (`render_step_size`): the
/// GPU's occupancy marcher serves both, so a render that left its step behind would double the
/// next steps' samples per ray. Without compaction, whose own marcher training would use.
#[test]
fn training_marches_at_its_own_step_after_a_finer_render() {
    let Some(ctx) = device() else { return };
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let config = TrainConfig { log_every: 1, compact_samples: false, ..light_hash_config(6) };
    let mut gpu = Trainer::new_on(config.clone(), &nerf::registry(), SceneBounds::of(&train), Some(ctx)).unwrap();
    let per_ray = |s: nerf::train::StepStats| s.n_marched as f64 / s.n_rays.max(1) as f64;
    let before = (0..3).map(|_| per_ray(gpu.step(&train).unwrap())).last().unwrap();
    let SamplerConfig::Occupancy { step_size, .. } = config.sampler else { unreachable!() };
    gpu.set_render_step_size(Some(step_size / 2.0)).unwrap();
    render_first_view(&gpu, &test, &config);
    let after = per_ray(gpu.step(&train).unwrap());
    assert!(before > 10.0 && (after / before - 1.0).abs() < 0.25, "samples per ray {before:.1} before the render, {after:.1} after");
}

/// A frame of more rays than one part of the GPU renderer's buffers (as many rays as the adapter's
/// largest storage binding holds of the rounds' 48-byte state, at most 2^22: 2 796 202 rays on
/// lavapipe's 128 MiB) renders in parts, each ray as it renders alone: a part and 2^10 more rays
/// that miss the scene box (they leave in their first round) with rays of a test view placed at
/// the start and across the end of the first part. The step's sample capacity (the rounds'
/// window) is raised so that the missing rays take a few rounds, not hundreds.
#[test]
fn a_frame_larger_than_the_renderers_buffers_renders_in_parts() {
    let Some(ctx) = device() else { return };
    let part = (ctx.max_storage_bytes() / nerf::gpu::sampling::GpuMarcher::ROUND_BYTES_PER_RAY as u64).min(1 << 22) as usize;
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let config = TrainConfig { target_samples_per_step: Some(1 << 18), ..light_hash_config(0) };
    let gpu = Trainer::new_on(config.clone(), &nerf::registry(), SceneBounds::of(&train), Some(ctx)).unwrap();
    // 16 rays through the middle of the view.
    let mut batch = nerf::data::RayBatch::default();
    test.view_rays(0, config.eval_background, config.pixel_convention, &mut batch);
    let (w, h) = (test.width as usize, test.height as usize);
    let (k, first) = (16, (h / 2) * w + w / 2 - 8);
    let (vo, vd, vbg) = (&batch.origins[3 * first..3 * (first + k)], &batch.dirs[3 * first..3 * (first + k)], &batch.background[3 * first..3 * (first + k)]);
    let (mut view_rgb, mut view_op, mut view_depth) = (vec![f32::NAN; 3 * k], vec![f32::NAN; k], vec![f32::NAN; k]);
    gpu.render_rays(vo, vd, vbg, &mut view_rgb, &mut view_op, &mut view_depth).unwrap();
    assert!(view_op.iter().all(|&a| a > 0.0), "the view's rays cross the box: {view_op:?}");

    let n = part + (1 << 10);
    let (mut o, mut d) = (vec![0.0f32; 3 * n], vec![0.0f32; 3 * n]);
    for r in 0..n {
        o[3 * r..3 * r + 3].copy_from_slice(&[10.0, 10.0, 10.0]);
        d[3 * r..3 * r + 3].copy_from_slice(&[1.0, 0.0, 0.0]); // away from the box
    }
    let mut bg: Vec<f32> = [0.2f32, 0.4, 0.6].repeat(n);
    let starts = [0, part - k / 2];
    for &s in &starts {
        o[3 * s..3 * (s + k)].copy_from_slice(vo);
        d[3 * s..3 * (s + k)].copy_from_slice(vd);
        bg[3 * s..3 * (s + k)].copy_from_slice(vbg);
    }
    let (mut rgb, mut op, mut depth) = (vec![f32::NAN; 3 * n], vec![f32::NAN; n], vec![f32::NAN; n]);
    gpu.render_rays(&o, &d, &bg, &mut rgb, &mut op, &mut depth).unwrap();
    for &s in &starts {
        assert_eq!(&rgb[3 * s..3 * (s + k)], &view_rgb[..], "rays {s}..: colours");
        assert_eq!(&op[s..s + k], &view_op[..], "rays {s}..: opacities");
        assert_eq!(&depth[s..s + k], &view_depth[..], "rays {s}..: depths");
    }
    let in_view = |r: usize| starts.iter().any(|&s| (s..s + k).contains(&r));
    for r in (0..n).filter(|&r| !in_view(r)) {
        assert!(
            op[r] == 0.0 && rgb[3 * r..3 * r + 3] == [0.2, 0.4, 0.6],
            "ray {r} misses the box: opacity {}, colour {:?}",
            op[r],
            &rgb[3 * r..3 * r + 3]
        );
    }
}

/// `NERF_GPU_CHECKS=off` builds the kernels without wgpu's runtime checks (index clamps, loop
/// counters; `GpuContext::shader_module`). That must change no value: the fields trained on a
/// checked device, restored on an unchecked one, render the same first test view bit for bit
/// (marching, both encodings, the MLPs and compositing all run), and a few more training steps
/// on each (every kernel of a step) keep them together, for the hash field and for the paper's
/// field with hierarchical sampling.
#[test]
fn shader_runtime_checks_change_no_result() {
    let Some(mut checked) = GpuContext::for_tests() else { return };
    checked.shader_checks = true;
    let mut unchecked = GpuContext::for_tests().unwrap();
    unchecked.shader_checks = false;
    let (checked, unchecked) = (Arc::new(checked), Arc::new(unchecked));
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    let paper = TrainConfig {
        iters: 3,
        batch_rays: 128,
        field_config: serde_json::json!({"width": 32, "depth": 3, "skips": [1], "view_width": 16}),
        sampler: SamplerConfig::Hierarchical { n_coarse: 16, n_fine: 16 },
        ..TrainConfig::default()
    };
    for (name, config) in [("hash", light_hash_config(20)), ("paper", paper)] {
        let mut a = Trainer::new_on(config.clone(), &registry, bounds, Some(checked.clone())).unwrap();
        for _ in 0..config.iters {
            a.step(&train).unwrap();
        }
        let mut b = Trainer::new_on(config.clone(), &registry, bounds, Some(unchecked.clone())).unwrap();
        b.restore(a.step_count(), &a.export_fields().unwrap(), a.adam_state().unwrap(), &a.sampler_state().unwrap())
            .unwrap();
        let render = |t: &Trainer| render_first_view(t, &test, &config).map(|v| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>());
        let (ra, rb) = (render(&a), render(&b));
        let n = ra[1].len();
        let opacity: f32 = ra[1].iter().map(|&x| f32::from_bits(x)).sum::<f32>() / n as f32;
        // A trained field, not an empty one: some rays meet matter.
        assert!(opacity > 0.01 && ra.iter().flatten().all(|&x| f32::from_bits(x).is_finite()), "{name}: opacity {opacity}");
        for (what, (x, y)) in ["colour", "opacity", "depth"].iter().zip(ra.iter().zip(&rb)) {
            let differ = x.iter().zip(y).filter(|(p, q)| p != q).count();
            assert_eq!(differ, 0, "{name}: {differ} {what} values differ with the shader checks on and off");
        }
        println!("{name}: {n} rays, mean opacity {opacity:.3}, identical with and without the checks");
        for _ in 0..2 {
            a.step(&train).unwrap();
            b.step(&train).unwrap();
        }
        let (ra, rb) = (render(&a), render(&b));
        let max_diff = ra[0].iter().zip(&rb[0]).map(|(&p, &q)| (f32::from_bits(p) - f32::from_bits(q)).abs()).fold(0.0f32, f32::max);
        let moved = ra[0].iter().zip(&rb[0]).filter(|(p, q)| p != q).count();
        println!("{name}: after 2 more steps on each, colour max |Δ| {max_diff:.2e} ({moved} of {} values differ)", 3 * n);
        // The scatter-adds of the hash table's gradients may sum in another order; a kernel that
        // read past its tile would move the colours by far more.
        assert!(max_diff < 1e-3, "{name}: colour max |Δ| {max_diff} after training on and off");
    }
}

#[test]
fn a_gpu_run_resumes_from_a_gpu_or_a_cpu_checkpoint() {
    let Some(ctx) = device() else { return };
    let train = load(Split::Train, ViewSelection::First(10));
    let mut config = light_hash_config(30);
    config.log_every = 5;
    let registry = nerf::registry();
    let bounds = SceneBounds::of(&train);
    for source in [Some(ctx.clone()), None] {
        let mut first = Trainer::new_on(config.clone(), &registry, bounds, source).unwrap();
        for _ in 0..20 {
            first.step(&train).unwrap();
        }
        let (fields, adam, sampler) =
            (first.export_fields().unwrap(), first.adam_state().unwrap(), first.sampler_state().unwrap());
        assert_eq!(adam.step, 20);
        assert!(sampler.iter().any(|(n, v)| n == "occupancy_density" && v.iter().any(|x| x.is_finite())));
        let mut resumed = Trainer::new_on(config.clone(), &registry, bounds, Some(ctx.clone())).unwrap();
        resumed.restore(first.step_count(), &fields, adam.clone(), &sampler).unwrap();
        // Everything a checkpoint holds arrives on the device unchanged ...
        let from = first.device();
        assert_eq!(resumed.step_count(), 20);
        assert_eq!(resumed.export_fields().unwrap(), fields, "from {from}");
        assert_eq!(resumed.adam_state().unwrap(), adam, "from {from}");
        assert_eq!(resumed.sampler_state().unwrap(), sampler, "from {from}");
        // ... and training continues from it (the loss is read back on logging steps).
        let mut losses = Vec::new();
        for _ in 0..10 {
            let s = resumed.step(&train).unwrap();
            if s.loss.is_finite() {
                losses.push(s.loss);
            }
        }
        assert_eq!(resumed.step_count(), 30);
        assert_eq!(losses.len(), 2, "{losses:?}");
        // A resumed run trains on (the MSE of a 20-step-old field is far below the white-image 0.1).
        assert!(losses.iter().all(|&l| l > 0.0 && l < 0.1), "from {from}: {losses:?}");
    }
}

/// `gpu_profile`: a window of GPU steps is timed pass by pass and summed by stage and kernel into
/// `gpu_profile.json` and `metrics.json`; a run that stops inside the window keeps what it timed.
#[test]
fn a_gpu_run_writes_its_profile() {
    let Some(ctx) = device() else { return };
    if !ctx.features.timestamps {
        eprintln!("NOTICE: adapter {} has no timestamp queries; no profile to check", ctx.describe());
        return;
    }
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let registry = nerf::registry();
    for (iters, start, steps, expect) in [(20u64, 15u64, 3u64, 3u64), (17, 15, 5, 2)] {
        let dir = tempfile::tempdir().unwrap();
        let mut config = light_hash_config(iters);
        config.gpu_profile = Some(nerf::train::ProfileWindow { start, steps });
        let opts = nerf::train::RunOptions {
            progress: false,
            write_renders: false,
            device: nerf::gpu::DevicePreference::Gpu,
            ..nerf::train::RunOptions::new(dir.path())
        };
        let summary = nerf::train::run(config, &registry, &train, &test, &opts).unwrap();
        let text = std::fs::read_to_string(dir.path().join("gpu_profile.json")).unwrap();
        let p: nerf::train::GpuProfile = serde_json::from_str(&text).unwrap();
        assert_eq!((p.first_step, p.steps, p.untimed_passes), (start, expect, 0));
        let stages: Vec<&str> = p.stages.iter().map(|s| s.stage.as_str()).collect();
        // Step 16 refreshes the occupancy grid (every 16 steps): it is in both windows.
        for s in ["occupancy update", "rays", "sampling", "field forward", "composite forward", "loss", "composite backward", "field backward", "adam"] {
            assert!(stages.contains(&s), "stage {s} missing: {stages:?}");
        }
        for part in ["hash encoding", "density MLP", "colour MLP"] {
            assert!(p.kernels.iter().any(|k| k.stage == "field backward" && k.part == part), "{part}: {:?}", p.kernels);
        }
        let sum: f64 = p.kernels.iter().map(|k| k.ms_per_step).sum();
        assert!(p.busy_ms_per_step > 0.0 && (sum - p.busy_ms_per_step).abs() <= 1e-9 * sum.max(1.0));
        assert!(p.span_ms_per_step >= p.busy_ms_per_step * 0.999, "passes of one queue do not overlap: {p:?}");
        assert!(p.kernels.windows(2).all(|w| w[0].ms_per_step >= w[1].ms_per_step));
        assert_eq!(summary.metrics["gpu_profile"]["steps"], expect);
    }
}

/// A step whose per-sample buffers exceed the adapter's storage binding limit (lavapipe's is
/// 128 MiB) is fitted to it: fewer samples per step, said on stderr, in `Trainer::config`,
/// `Trainer::device_note` and `metrics.json` — where the presets used to stop with an error.
#[test]
fn a_step_larger_than_the_adapters_binding_limit_is_fitted_to_it() {
    let Some(ctx) = device() else { return };
    let train = load(Split::Train, ViewSelection::First(10));
    let test = common::thumbnails(Split::Test, 1);
    let registry = nerf::registry();
    // The preset's 64-wide nets, whose tapes this test sizes.
    let mut config = common::small_hash_config(2, 16, 64);
    // The colour network's tape holds `fps` floats for each of the 2·target samples a step has
    // room for (at least 64: one hidden layer); this target needs ≥ twice the limit.
    let limit = ctx.max_storage_bytes();
    let asked = (limit / (8 * 32)) as usize;
    config.target_samples_per_step = Some(asked);
    let cfg: nerf::field_hash::HashNerfConfig = serde_json::from_value(config.field_config.clone()).unwrap();
    let bounds = SceneBounds::of(&train);
    let fctx = nerf::field::FieldContext { aabb_min: bounds.aabb_min, aabb_max: bounds.aabb_max, seed: 1, scene_scale: 1.0 };
    let cpu = nerf::field_hash::HashNerf::<f32>::new(cfg, &fctx).unwrap();
    let fps = nerf::gpu::mlp::FusedMlp::new(&ctx, &cpu.mlps()[1].config).unwrap().tape_floats_per_sample() as u64;
    assert!(2 * asked as u64 * 4 * fps >= 2 * limit, "the test's step must not fit ({fps} floats per sample)");

    let mut t = Trainer::new_on(config.clone(), &registry, bounds, Some(ctx.clone())).unwrap();
    let fitted = t.config().target_samples_per_step.unwrap();
    // The colour tape (the largest per-sample buffer) fits, and the step did not shrink much
    // more than it had to.
    assert!(2 * fitted as u64 * 4 * fps <= limit, "{fitted} samples per step do not fit {limit} bytes");
    assert!(fitted as u64 * 8 * fps * 2 >= limit, "{fitted} samples per step: shrunk more than twice what was needed");
    assert_eq!(fitted % 1024, 0);
    let note = t.device_note().expect("a note says what was fitted").to_string();
    assert!(note.contains(&format!("target_samples_per_step = {fitted} instead of {asked}")) && note.contains("MiB"), "{note}");
    for _ in 0..2 {
        t.step(&train).unwrap();
    }
    t.finish().unwrap();
    assert!(t.samples_seen().unwrap() > 0);

    // A fixed batch (no target) is fitted through batch_rays; `run` records it in metrics.json.
    let dir = tempfile::tempdir().unwrap();
    config.target_samples_per_step = None;
    config.batch_rays = (limit / (4 * 32 * 512)) as usize * 2;
    config.iters = 1;
    let opts = nerf::train::RunOptions {
        progress: false,
        write_renders: false,
        device: nerf::gpu::DevicePreference::Gpu,
        ..nerf::train::RunOptions::new(dir.path())
    };
    let summary = nerf::train::run(config.clone(), &registry, &train, &test, &opts).unwrap();
    let rays = summary.metrics["config"]["batch_rays"].as_u64().unwrap();
    assert!(rays < config.batch_rays as u64 && rays * 512 * 4 * fps <= limit, "{rays} rays");
    let note = summary.metrics["device_note"].as_str().unwrap();
    assert!(note.contains(&format!("batch_rays = {rays} instead of {}", config.batch_rays)), "{note}");
}

/// A field without a GPU twin (the trait's default `to_gpu`): the voxel field behind a wrapper
/// that forwards everything else.
struct CpuOnly(Box<dyn nerf::field::RadianceField>);

impl nerf::field::RadianceField for CpuOnly {
    fn kind(&self) -> &'static str {
        "cpu_only"
    }
    fn config(&self) -> serde_json::Value {
        self.0.config()
    }
    fn n_params(&self) -> usize {
        self.0.n_params()
    }
    fn density(&self, positions: &[f32], sigma: &mut [f32]) {
        self.0.density(positions, sigma)
    }
    fn query(&self, positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
        self.0.query(positions, dirs, sigma, rgb)
    }
    fn forward(&mut self, positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
        self.0.forward(positions, dirs, sigma, rgb)
    }
    fn backward(&mut self, d_sigma: &[f32], d_rgb: &[f32]) {
        self.0.backward(d_sigma, d_rgb)
    }
    fn zero_grad(&mut self) {
        self.0.zero_grad()
    }
    fn param_groups(&mut self) -> Vec<nerf::field::ParamGroupMut<'_>> {
        self.0.param_groups()
    }
    fn export_params(&self) -> Vec<(String, Vec<f32>)> {
        self.0.export_params()
    }
}

/// `gpu` refuses a field without a twin with an error naming it and the way out; the CPU trains
/// it as before.
#[test]
fn a_field_without_a_gpu_twin_is_refused_on_the_gpu_and_trains_on_the_cpu() {
    let Some(ctx) = device() else { return };
    let mut registry = nerf::field::Registry::new();
    registry.register(nerf::field::RegistryEntry {
        name: "cpu_only",
        description: "the voxel field without its GPU twin",
        default_config: || serde_json::json!({"resolution": 16, "hidden": 16}),
        train_preset: nerf::field_voxel::train_preset,
        build: |cfg, ctx| Ok(Box::new(CpuOnly(nerf::field_voxel::build(cfg, ctx)?))),
    });
    let train = load(Split::Train, ViewSelection::First(5));
    let mut config = light_hash_config(2);
    config.field = "cpu_only".into();
    config.field_config = serde_json::json!({"resolution": 16, "hidden": 16});
    let bounds = SceneBounds::of(&train);
    let e = match Trainer::new_on(config.clone(), &registry, bounds, Some(ctx)) {
        Ok(_) => panic!("a field without a GPU twin trained on the GPU"),
        Err(e) => e.to_string(),
    };
    assert!(e.contains("cpu_only") && e.contains("no GPU implementation") && e.contains("--device cpu"), "{e}");
    let mut t = Trainer::new_on(config, &registry, bounds, None).unwrap();
    t.step(&train).unwrap();
    assert_eq!((t.device(), t.fields()[0].kind()), ("cpu", "cpu_only"));
}
