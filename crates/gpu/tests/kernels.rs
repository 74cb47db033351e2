//! Every WGSL file validates with naga (no GPU needed), and every kernel matches its CPU twin on
//! random inputs with poisoned outputs (runs on any adapter: lavapipe in CI; prints a notice and
//! skips the comparison where no adapter exists).

use nerf_gpu::{shaders, Compositor, DevicePreference, GpuContext};
use rand::Rng as _;

#[test]
fn every_shader_validates_with_naga() {
    for (name, src) in shaders::ALL {
        let src = &shaders::with_common(src);
        let module = naga::front::wgsl::parse_str(src).unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(src)));
        let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
        v.validate(&module).unwrap_or_else(|e| panic!("{name}: {e:?}"));
    }
    // Every .wgsl in shaders/ is listed (and so validated and compiled into the crate).
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shaders");
    for entry in std::fs::read_dir(dir).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        if name.ends_with(".wgsl") {
            assert!(name == "common.wgsl" || shaders::ALL.iter().any(|(n, _)| *n == name), "{name} is not in shaders::ALL");
        }
    }
}

#[test]
fn device_preference_parses_and_rejects_typos() {
    assert_eq!("GPU".parse::<DevicePreference>().unwrap(), DevicePreference::Gpu);
    assert_eq!("cpu".parse::<DevicePreference>().unwrap(), DevicePreference::Cpu);
    let e = "gpuu".parse::<DevicePreference>().unwrap_err().to_string();
    assert!(e.contains("gpuu"), "{e}");
    // The CPU preference never opens a device.
    if std::env::var_os("NERF_DEVICE").is_none() {
        assert!(GpuContext::open(DevicePreference::Cpu).unwrap().is_none());
    }
}

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

/// Per-sample buffers: an overshoot names the largest buffer (not the first) with its bytes and
/// the limit; within the limit every buffer holds `capacity` rows.
#[test]
fn per_sample_buffers_report_their_largest_overshoot() {
    let Some(ctx) = context() else { return };
    let limit = ctx.max_storage_bytes();
    let fits = (limit / (4 * 10)) as usize;
    let [a, b, c] = ctx.zeros_per_sample(fits, [("a", 3), ("b", 10), ("c", 7)]).unwrap();
    assert_eq!([a.size(), b.size(), c.size()], [12 * fits as u64, 40 * fits as u64, 28 * fits as u64]);
    drop((a, b, c));
    match ctx.zeros_per_sample(fits + 1, [("a", 3), ("b", 10), ("c", 7)]) {
        Err(nerf_gpu::GpuError::CapacityTooLarge { label, bytes, limit: l, .. }) => {
            assert_eq!((label.as_str(), bytes, l), ("b", 40 * (fits as u64 + 1), limit));
        }
        other => panic!("expected CapacityTooLarge, got {:?}", other.map(|_| ())),
    }
    let e = ctx.zeros_checked("big", limit as usize + 4).unwrap_err().to_string();
    assert!(e.contains("`big`") && e.contains("MiB") && e.contains("batch_rays"), "{e}");
}

/// A random packed batch: rays with 0..40 samples, sorted t, mixed densities.
#[allow(clippy::type_complexity)]
fn batch(seed: u64, n_rays: usize) -> (Vec<u32>, Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut rng = nerf_core::rng(seed, 0);
    let mut offsets = vec![0u32];
    let (mut sigma, mut rgb, mut dt, mut t) = (vec![], vec![], vec![], vec![]);
    for _ in 0..n_rays {
        let k = if rng.gen::<f32>() < 0.1 { rng.gen_range(0..2) } else { rng.gen_range(0..40) };
        let mut tt = 2.0f32;
        for _ in 0..k {
            let d = rng.gen_range(0.001f32..0.2);
            sigma.push(if rng.gen::<f32>() < 0.3 { 0.0 } else { rng.gen_range(0.0f32..30.0) });
            rgb.extend((0..3).map(|_| rng.gen::<f32>()));
            dt.push(d);
            t.push(tt);
            tt += d;
        }
        offsets.push(sigma.len() as u32);
    }
    let bg = (0..3 * n_rays).map(|_| rng.gen::<f32>()).collect();
    (offsets, sigma, rgb, dt, t, bg)
}

#[test]
fn composite_kernel_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    for (seed, thr, with_bg) in [(1u64, 0.0f32, true), (2, 1e-3, true), (3, 0.0, false), (4, 0.05, true)] {
        let (offsets, sigma, rgb, dt, t, bg) = batch(seed, 1000);
        let bg_opt = with_bg.then_some(&bg[..]);
        let k = Compositor::new(&ctx, 1000, thr, with_bg);
        let gpu = k.forward(&ctx, &offsets, &sigma, &rgb, &dt, &t, bg_opt).unwrap();
        let mut cpu = nerf_render::CompositeOutputs::<f32>::default();
        nerf_render::composite_forward(&offsets, &sigma, &rgb, &dt, &t, bg_opt, thr, &mut cpu);
        let close = |what: &str, a: &[f32], b: &[f32], tol: f32| {
            assert_eq!(a.len(), b.len(), "{what} length");
            for (i, (x, y)) in a.iter().zip(b).enumerate() {
                assert!(x.is_finite(), "{what}[{i}] not written (poison survived): {x}");
                assert!((x - y).abs() <= tol * (1.0 + y.abs()), "{what}[{i}]: gpu {x} vs cpu {y} (seed {seed})");
            }
        };
        // exp(x) − 1 on the GPU vs exp_m1 on the CPU: ~1e-7 relative per sample, summed over ≤ 40.
        close("rgb", &gpu.rgb, &cpu.rgb, 2e-5);
        close("opacity", &gpu.opacity, &cpu.opacity, 2e-5);
        close("depth", &gpu.depth, &cpu.depth, 2e-5);
        close("weights", &gpu.weights, &cpu.weights, 2e-5);
    }
}

/// Depth supervision's kernel against `nerf_render::depth_loss_grad`: random expected and
/// measured depths, a fifth of the rays without a measurement (0) and one that matches exactly,
/// outputs poisoned; fresh seeds.
#[test]
fn depth_loss_kernel_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    for (seed, n_rays, lambda) in [(41u64, 700usize, 0.1f32), (42, 1, 2.0), (43, 3000, 0.01)] {
        let mut rng = nerf_core::rng(seed, 3);
        let depth: Vec<f32> = (0..n_rays).map(|_| rng.gen_range(0.0f32..5.0)).collect();
        let mut target: Vec<f32> = (0..n_rays).map(|_| if rng.gen_bool(0.2) { 0.0 } else { rng.gen_range(0.5f32..5.0) }).collect();
        if n_rays > 10 {
            target[7] = depth[7];
        }
        let mut d = vec![f32::NAN; n_rays];
        let total = nerf_render::depth_loss_grad(&depth, &target, lambda, &mut d);
        let k = Compositor::new(&ctx, n_rays, 0.0, false);
        let (g_d, g_loss) = k.depth_loss(&ctx, &depth, &target, lambda).unwrap();
        assert_eq!(g_d, d, "seed {seed}: d_depth");
        let sum: f64 = g_loss.iter().map(|&x| x as f64).sum();
        assert!((sum - total as f64).abs() <= 1e-5 * (total as f64).abs() + 1e-9, "seed {seed}: loss {sum} vs {total}");
        assert!(g_loss.iter().zip(&target).all(|(l, t)| l.is_finite() && (*t > 0.0 || *l == 0.0)), "seed {seed}: a loss without a measurement");
        assert!(n_rays < 10 || d.iter().filter(|&&x| x != 0.0).count() > n_rays / 2, "seed {seed}: most rays pull");
    }
}

#[test]
fn distortion_kernel_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    // λ = c·N: a per-ray weight c, so the gradients are not lost against d_sigma's start values.
    for (seed, thr, scale, c) in [(31u64, 0.0f32, 0.25f32, 0.01f32), (32, 1e-3, 1.0, 0.5), (33, 0.05, 0.1, 2.0)] {
        let (offsets, sigma, rgb, dt, t, _) = batch(seed, 900);
        let (n_rays, n) = (offsets.len() - 1, sigma.len());
        let lambda = c * n_rays as f32;
        let mut cpu = nerf_render::CompositeOutputs::<f32>::default();
        nerf_render::composite_forward(&offsets, &sigma, &rgb, &dt, &t, None, thr, &mut cpu);
        // The kernel adds to d_sigma: start from random values (fresh per seed).
        let mut rng = nerf_core::rng(seed, 2);
        let start: Vec<f32> = (0..n).map(|_| rng.gen_range(-1e-3f32..1e-3)).collect();
        let (mut ds, mut rl) = (start.clone(), vec![f32::NAN; n_rays]);
        let total = nerf_render::distortion_loss_grad(&offsets, &sigma, &dt, &t, &cpu, scale, lambda / n_rays as f32, &mut ds, &mut rl);
        let k = Compositor::new(&ctx, n_rays, thr, false);
        let (g_ds, g_rl) = k.distortion(&ctx, &offsets, &sigma, &dt, &t, &cpu.weights, scale, lambda, &start).unwrap();
        assert!(total > 0.0 && rl.iter().all(|x| x.is_finite()));
        for (i, (x, y)) in g_rl.iter().zip(&rl).enumerate() {
            assert!(x.is_finite() && (x - y).abs() <= 1e-4 * y.abs() + 1e-9, "ray_loss[{i}]: gpu {x} vs cpu {y} (seed {seed})");
        }
        // Samples behind an opaque stretch have (almost) no gradient; plenty of others do.
        let moved = ds.iter().zip(&start).filter(|(a, b)| (*a - *b).abs() > 1e-6).count();
        assert!(moved > n / 10, "a gradient above 1e-6 at only {moved} of {n} samples");
        for (i, ((x, y), s0)) in g_ds.iter().zip(&ds).zip(&start).enumerate() {
            let (gx, gy) = (x - s0, y - s0);
            assert!(x.is_finite() && (gx - gy).abs() <= 1e-3 * gy.abs() + 1e-7, "d_sigma[{i}]: gpu +{gx} vs cpu +{gy} (seed {seed})");
        }
    }
}

#[test]
fn composite_kernel_handles_an_empty_batch() {
    let Some(ctx) = context() else { return };
    let k = Compositor::new(&ctx, 2, 0.0, true);
    let out = k.forward(&ctx, &[0, 0, 0], &[], &[], &[], &[], Some(&[0.5; 6])).unwrap();
    assert_eq!(out.rgb, vec![0.5; 6]);
    assert_eq!(out.opacity, vec![0.0; 2]);
}

#[test]
fn composite_backward_kernel_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    for (seed, thr, with_bg, all_grads) in [(5u64, 0.0f32, true, true), (6, 1e-3, true, true), (7, 0.0, false, false), (8, 0.05, true, true)] {
        let (offsets, sigma, rgb, dt, t, bg) = batch(seed, 800);
        let n_rays = offsets.len() - 1;
        let bg_opt = with_bg.then_some(&bg[..]);
        let mut rng = nerf_core::rng(seed, 1);
        let d_rgb: Vec<f32> = (0..3 * n_rays).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
        let d_op: Vec<f32> = (0..n_rays).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
        let d_depth: Vec<f32> = (0..n_rays).map(|_| rng.gen_range(-0.1f32..0.1)).collect();
        let (dop, ddep) = if all_grads { (Some(&d_op[..]), Some(&d_depth[..])) } else { (None, None) };
        let mut cpu = nerf_render::CompositeOutputs::<f32>::default();
        nerf_render::composite_forward(&offsets, &sigma, &rgb, &dt, &t, bg_opt, thr, &mut cpu);
        let n = sigma.len();
        let (mut ds, mut dc) = (vec![f32::NAN; n], vec![f32::NAN; 3 * n]);
        nerf_render::composite_backward(&offsets, &sigma, &rgb, &dt, &t, bg_opt, &cpu, &d_rgb, dop, ddep, &mut ds, &mut dc);
        let k = Compositor::new(&ctx, n_rays, thr, with_bg);
        let gpu = k
            .backward(&ctx, &offsets, &sigma, &rgb, &dt, &t, bg_opt, &cpu.weights, &d_rgb, dop, ddep)
            .unwrap();
        // The GPU sums prefix-wise (total − prefix) where the CPU keeps a suffix sum; with ≤ 40
        // samples of |w·g| ≤ ~4 the difference stays ~1e-6 absolute; δ ≤ 0.2 scales it down.
        for (what, a, b) in [("d_sigma", &gpu.d_sigma, &ds), ("d_rgb", &gpu.d_rgb, &dc)] {
            for (i, (x, y)) in a.iter().zip(b.iter()).enumerate() {
                assert!(x.is_finite(), "{what}[{i}] not written: {x}");
                assert!((x - y).abs() <= 5e-5 * (1.0 + y.abs()), "{what}[{i}]: gpu {x} vs cpu {y} (seed {seed})");
            }
        }
    }
}

#[test]
fn loss_kernel_matches_photometric_loss_grad() {
    let Some(ctx) = context() else { return };
    let glue = nerf_gpu::TrainGlue::new(&ctx, 5000, nerf_gpu::composite::BatchParams::default());
    // MSE, then instant-ngp's Huber loss (δ = 0.1: most random residuals lie beyond it), then MSE again.
    for (seed, n, huber) in [(11u64, 1usize, None), (12, 777, None), (13, 5000, None), (14, 777, Some(0.1f32)), (15, 5000, Some(0.3)), (16, 10, None)] {
        glue.set_huber_delta(&ctx, huber);
        let mut rng = nerf_core::rng(seed, 0);
        let pred: Vec<f32> = (0..3 * n).map(|_| rng.gen()).collect();
        let target: Vec<f32> = (0..3 * n).map(|_| rng.gen()).collect();
        let mut d_cpu = vec![0.0; 3 * n];
        let mse = nerf_render::photometric_loss_grad(&pred, &target, huber, &mut d_cpu);
        let (d_gpu, sq) = glue.loss(&ctx, &pred, &target).unwrap();
        for (i, (a, b)) in d_gpu.iter().zip(&d_cpu).enumerate() {
            assert!((a - b).abs() <= 1e-6 * (1.0 + b.abs()), "d_pred[{i}]: {a} vs {b}");
        }
        let gpu_mse = sq.iter().map(|&x| x as f64).sum::<f64>() / (3 * n) as f64;
        assert!((gpu_mse - mse as f64).abs() <= 1e-5 * mse as f64, "{gpu_mse} vs {mse}");
    }
}

#[test]
fn batch_sizing_kernel_follows_the_cpu_rule() {
    let Some(ctx) = context() else { return };
    let bp = nerf_gpu::composite::BatchParams { target_samples: 1 << 16, min_rays: 64, max_rays: 1 << 14, _pad: 0 };
    let glue = nerf_gpu::TrainGlue::new(&ctx, 1 << 14, bp);
    let counters = ctx.upload("counters", &[1000u32, 50_000]);
    let spr = ctx.upload("spr", &[0.0f32]);
    let mut mean = 0.0f32;
    for (n_rays, n_samples) in [(1000u32, 50_000u32), (1310, 20_000), (4000, 1_000), (16384, 0)] {
        ctx.write(&counters, 0, &[n_rays, n_samples]);
        let mut enc = ctx.encoder("batch");
        glue.record_next_batch(&ctx, &mut enc, &counters, &spr);
        ctx.queue.submit([enc.finish()]);
        let s = n_samples as f32 / n_rays as f32;
        mean = if mean > 0.0 { 0.9 * mean + 0.1 * s } else { s };
        let want = ((bp.target_samples as f32 / mean.max(1e-6)) as u32).clamp(bp.min_rays, bp.max_rays);
        let got = ctx.read_u32(&counters, 1).unwrap()[0];
        assert_eq!(got, want, "after ({n_rays}, {n_samples})");
        assert!((ctx.read_f32(&spr, 1).unwrap()[0] - mean).abs() <= 1e-5 * mean.max(1.0));
    }
}

#[test]
fn kernels_reuse_bind_groups_for_the_same_buffers() {
    let Some(ctx) = context() else { return };
    let glue = nerf_gpu::TrainGlue::new(&ctx, 64, nerf_gpu::composite::BatchParams::default());
    let (c, p, t, d, e) = (
        ctx.upload("c", &[3u32, 0]),
        ctx.upload("p", &[0.5f32; 9]),
        ctx.upload("t", &[0.25f32; 9]),
        ctx.zeros("d", 36),
        ctx.zeros("e", 12),
    );
    for _ in 0..3 {
        let mut enc = ctx.encoder("loss");
        glue.record_loss(&ctx, &mut enc, &c, &p, &t, &d, &e);
        ctx.queue.submit([enc.finish()]);
    }
    // Three recordings with the same buffers: one bind group; a different output buffer: two.
    let k = nerf_gpu::Kernel::new(&ctx, &shaders::with_common(shaders::TRAIN), "mse_loss", &[]);
    let lp = ctx.uniform("lp", &nerf_gpu::composite::LossParams { capacity_rays: 64, huber_delta: 0.0, _pad: [0; 2] });
    let e2 = ctx.zeros("e2", 12);
    for out in [&e, &e, &e2, &e] {
        let mut enc = ctx.encoder("loss");
        k.record(&ctx, &mut enc, &[(0, &lp), (1, &c), (2, &p), (3, &t), (4, &d), (5, out)], [1, 1, 1]);
        ctx.queue.submit([enc.finish()]);
    }
    assert_eq!(k.cached_bind_groups(), 2);
    // The cached groups bind the right buffers: the loss landed in both outputs.
    let (a, b) = (ctx.read_f32(&e, 3).unwrap(), ctx.read_f32(&e2, 3).unwrap());
    assert_eq!(a, b);
    assert!((a[0] - 3.0 * 0.0625).abs() < 1e-7, "{a:?}");
}

/// What in `function` (and the functions it calls) keeps an array in function memory: local
/// variables whose type holds an array, and array values indexed at run time (naga's SPIR-V
/// backend copies those into a function-local variable). Workgroup, uniform and storage arrays are
/// not counted.
fn function_memory_arrays(module: &naga::Module, info: &naga::valid::ModuleInfo, ep: usize) -> Vec<String> {
    fn holds_array(module: &naga::Module, ty: naga::Handle<naga::Type>) -> bool {
        match &module.types[ty].inner {
            naga::TypeInner::Array { .. } => true,
            naga::TypeInner::Struct { members, .. } => members.iter().any(|m| holds_array(module, m.ty)),
            _ => false,
        }
    }
    fn calls(block: &naga::Block, out: &mut Vec<naga::Handle<naga::Function>>) {
        for st in block.iter() {
            match st {
                naga::Statement::Block(b) => calls(b, out),
                naga::Statement::If { accept, reject, .. } => {
                    calls(accept, out);
                    calls(reject, out);
                }
                naga::Statement::Switch { cases, .. } => cases.iter().for_each(|c| calls(&c.body, out)),
                naga::Statement::Loop { body, continuing, .. } => {
                    calls(body, out);
                    calls(continuing, out);
                }
                naga::Statement::Call { function, .. } => out.push(*function),
                _ => {}
            }
        }
    }
    let mut found = Vec::new();
    let check = |name: &str, f: &naga::Function, fi: &naga::valid::FunctionInfo, found: &mut Vec<String>| {
        for (_, var) in f.local_variables.iter() {
            if holds_array(module, var.ty) {
                found.push(format!("{name}: local `{}`", var.name.as_deref().unwrap_or("?")));
            }
        }
        for (_, expr) in f.expressions.iter() {
            if let naga::Expression::Access { base, .. } = expr {
                if matches!(fi[*base].ty.inner_with(&module.types), naga::TypeInner::Array { .. }) {
                    found.push(format!("{name}: an array value indexed at run time"));
                }
            }
        }
    };
    let entry = &module.entry_points[ep];
    check(&entry.name, &entry.function, info.get_entry_point(ep), &mut found);
    let mut todo = Vec::new();
    calls(&entry.function.body, &mut todo);
    let mut seen = std::collections::HashSet::new();
    while let Some(h) = todo.pop() {
        if seen.insert(h) {
            let f = &module.functions[h];
            check(f.name.as_deref().unwrap_or("?"), f, &info[h], &mut found);
            calls(&f.body, &mut todo);
        }
    }
    found
}

/// No kernel keeps an array in function memory, except those listed with a reason. naga writes
/// every WGSL loop as `loop { if !cond { break } }`, which drivers may leave rolled; an array
/// indexed by the loop counter then lives in local memory (on the H100 the plain GEMM's
/// accumulators, an array indexed in loops, ran 22× slower than the same sums in named
/// registers), and naga's SPIR-V backend copies an array *value* indexed at run time into a
/// function-local variable first. The hash grid's corners and the fused MLP's weight-gradient
/// prefetch are written out by hand for this reason; this keeps new kernels honest too.
#[test]
fn kernels_keep_no_arrays_in_function_memory() {
    // (file, entry point, why an array there costs nothing that matters)
    let allowed = [
        ("linear.wgsl", "forward", "the epilogue reads its 16 sums once per output"),
        ("linear.wgsl", "backward_data", "the epilogue reads its 16 sums once per output"),
        ("linear.wgsl", "backward_weight", "the epilogue reads its 16 sums once per output"),
        ("pose.wgsl", "pose_view_grads", "camera pose refinement only, one invocation per view"),
        ("views.wgsl", "view_sums", "per-view sums of the refinements, once per step"),
    ];
    let mut found = Vec::new();
    let mut checked = 0;
    for (name, src) in shaders::ALL {
        let src = &shaders::with_common(src);
        let module = naga::front::wgsl::parse_str(src).unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(src)));
        let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
        let info = v.validate(&module).unwrap_or_else(|e| panic!("{name}: {e:?}"));
        for (i, ep) in module.entry_points.iter().enumerate() {
            let arrays = function_memory_arrays(&module, &info, i);
            let excused = allowed.iter().any(|(f, e, _)| f == name && *e == ep.name);
            assert!(!excused || !arrays.is_empty(), "{name} {}: allowed an array but holds none; drop it from the list", ep.name);
            if !excused && !arrays.is_empty() {
                found.push(format!("{name} {}: {arrays:?}", ep.name));
            }
            checked += 1;
        }
    }
    assert!(checked > 60, "only {checked} entry points checked");
    assert!(found.is_empty(), "arrays in function memory:\n{}", found.join("\n"));
}

/// The check above finds what it looks for: the old hash-grid corners (an array field of a
/// struct value indexed in a loop) and a loop-indexed local array.
#[test]
fn the_function_memory_check_finds_arrays() {
    let src = r#"
struct Cell { slot: array<u32, 8>, w: array<f32, 8> }
@group(0) @binding(0) var<storage, read_write> out: array<f32>;
fn cell(x: f32) -> Cell {
    var c: Cell;
    for (var k = 0u; k < 8u; k++) { c.slot[k] = k; c.w[k] = x; }
    return c;
}
@compute @workgroup_size(1)
fn by_value() {
    let c = cell(out[0]);
    var acc = 0.0;
    for (var k = 0u; k < 8u; k++) { acc += c.w[k] * out[c.slot[k]]; }
    out[1] = acc;
}
@compute @workgroup_size(1)
fn local_array() {
    var a: array<f32, 4>;
    for (var k = 0u; k < 4u; k++) { a[k] = out[k]; }
    out[0] = a[1];
}
@compute @workgroup_size(1)
fn vectors() {
    let a = vec4<f32>(out[0], out[1], out[2], out[3]);
    out[0] = a.x + a.w;
}
"#;
    let module = naga::front::wgsl::parse_str(src).unwrap();
    let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
    let info = v.validate(&module).unwrap();
    let found: Vec<Vec<String>> = (0..3).map(|i| function_memory_arrays(&module, &info, i)).collect();
    assert!(found[0].iter().any(|f| f.starts_with("by_value: an array value")), "{:?}", found[0]);
    assert!(found[0].iter().any(|f| f == "cell: local `c`"), "{:?}", found[0]);
    assert_eq!(found[1], vec!["local_array: local `a`".to_string()]);
    assert!(found[2].is_empty(), "{:?}", found[2]);
}
