//! `GpuMlp` (tiled linear layers, plain WGSL and cooperative matrices) against its CPU twin
//! `nerf_mlp::Mlp` on random inputs: forward (output and tape), inference, backward (gradients
//! accumulated onto random pre-filled values, d_input). Outputs start poisoned with NaN.
//! The cooperative-matrix kernels (both tilings) also run here without tensor cores through the
//! plain-WGSL emulation of `common/coop_emu.rs`, and the workgroup-tiled entry points are
//! translated to SPIR-V as wgpu's Vulkan backend does (where an H100 run once failed).

use nerf_gpu::linear::{CoopTiling, GpuMlp, LinearPath};
use nerf_gpu::{shaders, GpuContext};
use nerf_mlp::{Activation, Mlp, MlpConfig, MlpTape};
use rand::Rng as _;

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

#[test]
fn linear_shaders_validate_with_naga() {
    for (name, src) in [("linear.wgsl", shaders::LINEAR), ("linear_coop.wgsl", shaders::LINEAR_COOP)] {
        let src = &shaders::with_common(src);
        let module = naga::front::wgsl::parse_str(src).unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(src)));
        let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
        v.validate(&module).unwrap_or_else(|e| panic!("{name}: {e:?}"));
    }
}

/// nerf_trunk-like but small: input 15, 4 hidden layers of 32, skip at 2, bias.
fn small_trunk(out_act: Activation, output_dim: usize) -> MlpConfig {
    MlpConfig {
        input_dim: 15,
        output_dim,
        hidden_dim: 32,
        hidden_layers: 4,
        hidden_activation: Activation::Relu,
        output_activation: out_act,
        skips: vec![2],
        bias: true,
    }
}

fn configs() -> Vec<MlpConfig> {
    vec![
        small_trunk(Activation::None, 5),
        small_trunk(Activation::Sigmoid, 3),
        // No bias, tanh hidden, wide-ish hidden not a multiple of 16 or 64, two skips.
        MlpConfig {
            input_dim: 7,
            output_dim: 70,
            hidden_dim: 72,
            hidden_layers: 3,
            hidden_activation: Activation::Tanh,
            output_activation: Activation::Softplus,
            skips: vec![1, 2],
            bias: false,
        },
        // A single linear layer.
        MlpConfig {
            input_dim: 9,
            output_dim: 4,
            hidden_dim: 0,
            hidden_layers: 0,
            hidden_activation: Activation::Relu,
            output_activation: Activation::Exp,
            skips: vec![],
            bias: true,
        },
    ]
}

fn check(what: &str, gpu: &[f32], cpu: &[f32], tol: f32) {
    assert_eq!(gpu.len(), cpu.len(), "{what}: length");
    let scale = cpu.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-3);
    for (i, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(g.is_finite(), "{what}[{i}] not written (poison survived): {g}");
        assert!((g - c).abs() <= tol * (scale + c.abs()), "{what}[{i}]: gpu {g} vs cpu {c} (tol {tol}, scale {scale})");
    }
}

/// Runs every config at several n (incl. 0, 1 and sizes that are not multiples of the tiles)
/// through forward, inference and backward, against the CPU twin.
fn compare(ctx: &GpuContext, use_coop: bool, tol_fwd: f32, tol_bwd: f32) {
    compare_with(ctx, configs(), &[0, 1, 77, 300], use_coop, tol_fwd, tol_bwd, &|cfg, capacity| {
        GpuMlp::new(ctx, cfg, capacity, use_coop).unwrap()
    });
}

#[allow(clippy::too_many_arguments)]
fn compare_with(
    ctx: &GpuContext,
    configs: Vec<MlpConfig>,
    sizes: &[usize],
    use_coop: bool,
    tol_fwd: f32,
    tol_bwd: f32,
    make: &dyn Fn(&MlpConfig, usize) -> GpuMlp,
) -> Vec<GpuMlp> {
    let mut made = Vec::new();
    for (ci, mut cfg) in configs.into_iter().enumerate() {
        if use_coop && cfg.hidden_activation == Activation::Relu {
            // f16 forward values flip the sign of pre-activations near 0 relative to the CPU, and
            // a flipped ReLU mask changes a whole gradient term: compare with a smooth activation.
            cfg.hidden_activation = Activation::Softplus;
        }
        let capacity = 300;
        let mut rng = nerf_core::rng(40 + ci as u64, 0);
        let mut mlp = Mlp::<f32>::new(cfg.clone(), &mut rng);
        let g = make(&cfg, capacity);
        assert_eq!(g.n_params(), mlp.n_params());
        assert_eq!(g.tape_floats_per_sample(), cfg.hidden_layers * cfg.hidden_dim + cfg.output_dim);
        for (si, &n) in sizes.iter().enumerate() {
            let mut r = nerf_core::rng(1000 + 10 * ci as u64 + si as u64, 1);
            let input: Vec<f32> = (0..n * cfg.input_dim).map(|_| r.gen_range(-1.0f32..1.0)).collect();
            let d_out: Vec<f32> = (0..n * cfg.output_dim).map(|_| r.gen_range(-1.0f32..1.0)).collect();
            let prefill: Vec<f32> = (0..mlp.n_params()).map(|_| r.gen_range(-1.0f32..1.0)).collect();
            let tag = format!("config {ci} n {n} coop {use_coop}");

            let mut tape = MlpTape::default();
            let cpu_out = mlp.forward(n, &input, &mut tape).to_vec();
            let (out, gtape) = g.run_forward(ctx, &input, mlp.params(), n, true).unwrap();
            check(&format!("{tag}: forward output"), &out, &cpu_out, tol_fwd);
            // The tape's last block is the output again.
            let t = g.tape_floats_per_sample();
            let tape_out: Vec<f32> = (0..n).flat_map(|k| gtape[k * t + t - cfg.output_dim..(k + 1) * t].to_vec()).collect();
            check(&format!("{tag}: tape output block"), &tape_out, &cpu_out, tol_fwd);
            let (inf, _) = g.run_forward(ctx, &input, mlp.params(), n, false).unwrap();
            check(&format!("{tag}: inference"), &inf, &cpu_out, tol_fwd);

            mlp.grads_mut().copy_from_slice(&prefill);
            let mut cpu_dx = vec![0.0f32; n * cfg.input_dim];
            mlp.backward(n, &input, &mut tape, &d_out, Some(&mut cpu_dx));
            for want_dx in [true, false] {
                let mut grads = prefill.clone();
                let dx = g.run_backward(ctx, &input, mlp.params(), &d_out, &mut grads, n, want_dx).unwrap();
                // Compare the accumulated part (grads − prefill) so the prefill does not hide errors.
                let dg: Vec<f32> = grads.iter().zip(&prefill).map(|(a, b)| a - b).collect();
                let cg: Vec<f32> = mlp.grads().iter().zip(&prefill).map(|(a, b)| a - b).collect();
                check(&format!("{tag}: grads (d_input {want_dx})"), &dg, &cg, tol_bwd);
                if want_dx {
                    check(&format!("{tag}: d_input"), &dx.unwrap(), &cpu_dx, tol_bwd);
                } else {
                    assert!(dx.is_none());
                }
            }
        }
        made.push(g);
    }
    made
}

#[test]
fn plain_mlp_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    // f32 throughout; different summation orders over ≤ 300 samples / ≤ 87 inputs: ~1e-6 relative
    // to the largest entry.
    compare(&ctx, false, 2e-5, 1e-4);
}

#[test]
fn coop_mlp_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    if !ctx.features.cooperative_matrix {
        eprintln!("NOTICE: adapter {} has no cooperative matrices; coop path not compared", ctx.describe());
        assert!(GpuMlp::new(&ctx, &small_trunk(Activation::None, 4), 16, true).is_err());
        return;
    }
    assert_eq!(GpuMlp::new(&ctx, &small_trunk(Activation::None, 4), 16, true).unwrap().path(), LinearPath::Coop);
    // f16 operands (11-bit mantissa, ~5e-4 relative per rounding) accumulated in f32 over up to
    // ~90 products per output and 4 layers: 1e-2 of the largest entry forward; backward also
    // rounds dZ at every layer and d_input sums cancelling terms through all 5 layers: 5e-2.
    compare(&ctx, true, 1e-2, 5e-2);
}

#[test]
fn gradients_accumulate_over_two_backward_passes() {
    let Some(ctx) = context() else { return };
    let cfg = small_trunk(Activation::None, 5);
    let mut rng = nerf_core::rng(7, 0);
    let mlp = Mlp::<f32>::new(cfg.clone(), &mut rng);
    let g = GpuMlp::new(&ctx, &cfg, 64, false).unwrap();
    let n = 50;
    let input: Vec<f32> = (0..n * 15).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let d_out: Vec<f32> = (0..n * 5).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let mut once = vec![0.0f32; g.n_params()];
    g.run_backward(&ctx, &input, mlp.params(), &d_out, &mut once, n, false).unwrap();
    let mut twice = once.clone();
    g.run_backward(&ctx, &input, mlp.params(), &d_out, &mut twice, n, false).unwrap();
    assert!(once.iter().any(|v| v.abs() > 1e-3));
    for (i, (a, b)) in once.iter().zip(&twice).enumerate() {
        assert!((2.0 * a - b).abs() <= 1e-5 * (1.0 + a.abs()), "grad {i}: once {a}, twice {b}");
    }
}

#[path = "common/coop_emu.rs"]
mod coop_emu;
#[path = "common/spirv.rs"]
mod spirv;

/// `linear_coop.wgsl` — checked on an H100 (docs/gpu.md) — with its cooperative-matrix operations
/// emulated in plain WGSL, against the CPU twin: this pins the emulation's semantics (load/store
/// layouts, multiply-add) to those the hardware showed, which `tests/mlp_coop.rs` relies on to run
/// the fused cooperative-matrix kernels here.
#[test]
fn emulated_coop_mlp_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    if !ctx.features.shader_f16 {
        eprintln!("NOTICE: adapter {} has no SHADER_F16; the emulated kernels cannot run", ctx.describe());
        return;
    }
    let src = coop_emu::emulate(&shaders::with_common(shaders::LINEAR_COOP));
    // The same f16 tolerances, configs and sizes as the hardware comparison
    // (coop_mlp_matches_its_cpu_twin).
    compare_with(&ctx, configs(), &[0, 1, 77, 130, 300], true, 1e-2, 5e-2, &|cfg, capacity| {
        GpuMlp::with_coop_source(&ctx, cfg, capacity, &src, CoopTiling::Subgroup).unwrap()
    });
}

// ---------------------------------------------------------------------------------------------
// The workgroup-tiled cooperative-matrix kernels (LinearPath::CoopTiled).

/// Widths that are not multiples of the 64×64 blocks nor of the 32-deep K chunks: input 39
/// (xp 48: K 48 in layer 0, a half-filled chunk), hidden 80 (two column blocks, the second 16
/// wide), a skip layer (K = 48 + 80 = 128 from both sources), output 4 (np 16), biases (the bias
/// column of dW), softplus hidden (see compare_with), sigmoid output. Three layers: the emulation
/// is slow on lavapipe.
fn tiled_config() -> MlpConfig {
    MlpConfig {
        input_dim: 39,
        output_dim: 4,
        hidden_dim: 80,
        hidden_layers: 2,
        hidden_activation: Activation::Softplus,
        output_activation: Activation::Sigmoid,
        skips: vec![1],
        bias: true,
    }
}

const TILED_ENTRY_POINTS: [&str; 3] = ["forward_tiled", "backward_data_tiled", "backward_weight_tiled"];

/// SPIR-V opcodes of the KHR cooperative-matrix load, store and multiply-add.
const SPIRV_COOP_OPS: [u32; 3] = [4457, 4458, 4459];

/// Parses and validates `src`, then translates each of `entry_points` to SPIR-V the way
/// wgpu-hal 30's Vulkan backend does (process_overrides, spv::write_vec with the entry point's
/// pipeline options, SPIR-V 1.6, both buffer bounds-check policies; as in tests/mlp_coop.rs).
/// Returns per entry point (coop loads, stores, multiply-adds, bytes of workgroup memory used).
fn translate(src: &str, entry_points: [&'static str; 3]) -> Vec<(&'static str, [usize; 3], u32)> {
    use naga::back::spv;
    let module = naga::front::wgsl::parse_str(src).unwrap_or_else(|e| panic!("{}", e.emit_to_string(src)));
    let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
    let info = v.validate(&module).unwrap_or_else(|e| panic!("naga validation: {e:?}"));
    let mut out = Vec::new();
    for ep_name in entry_points {
        let idx = module.entry_points.iter().position(|e| e.name == ep_name).unwrap_or_else(|| panic!("entry point {ep_name} missing"));
        let ep = &module.entry_points[idx];
        assert_eq!(ep.workgroup_size, [128, 1, 1], "{ep_name}: 4 subgroups of 32");
        let fi = info.get_entry_point(idx);
        let wg_bytes: u32 = module
            .global_variables
            .iter()
            .filter(|(h, g)| g.space == naga::AddressSpace::WorkGroup && !fi[*h].is_empty())
            .map(|(_, g)| module.types[g.ty].inner.size(module.to_ctx()))
            .sum();
        let mut counts = [0usize; 3];
        for buffer in [naga::proc::BoundsCheckPolicy::Restrict, naga::proc::BoundsCheckPolicy::Unchecked] {
            let options = spirv::vulkan_options(buffer);
            let (m, i) = naga::back::pipeline_constants::process_overrides(&module, &info, Some((ep.stage, &ep.name)), &Default::default())
                .unwrap_or_else(|e| panic!("{ep_name}: process_overrides: {e}"));
            let po = spv::PipelineOptions { shader_stage: ep.stage, entry_point: ep.name.clone() };
            let words = spv::write_vec(&m, &i, &options, Some(&po)).unwrap_or_else(|e| panic!("{ep_name}: SPIR-V translation ({buffer:?}): {e}"));
            assert!(words.len() > 5 && words[0] == 0x0723_0203, "{ep_name}: not a SPIR-V module");
            counts = [0; 3];
            let mut w = 5;
            while w < words.len() {
                let (len, op) = ((words[w] >> 16) as usize, words[w] & 0xffff);
                assert!(len > 0, "{ep_name}: malformed SPIR-V at word {w}");
                if let Some(k) = SPIRV_COOP_OPS.iter().position(|&o| o == op) {
                    counts[k] += 1;
                }
                w += len;
            }
        }
        out.push((ep_name, counts, wg_bytes));
    }
    out
}

#[test]
fn tiled_coop_kernels_translate_to_spirv_within_16k_of_workgroup_memory() {
    for (ep, [loads, stores, muladds], wg_bytes) in translate(&shaders::with_common(shaders::LINEAR_COOP), TILED_ENTRY_POINTS) {
        eprintln!("linear_coop.wgsl {ep}: {loads} coop loads, {stores} coop stores, {muladds} multiply-adds, {wg_bytes} B workgroup memory");
        // Per K step 2 A + 2 B tiles and 2×2 products; 4 accumulators stored for the epilogue.
        assert!(loads >= 4 && muladds >= 4 && stores >= 4, "{ep}: coop ops missing from the SPIR-V");
        assert!(wg_bytes <= 16 * 1024, "{ep}: {wg_bytes} B of workgroup memory (budget 16 KiB)");
        assert!(wg_bytes >= 2 * 64 * 40 * 2, "{ep}: the staging arrays are not used ({wg_bytes} B)");
    }
}

/// Emulated tiled kernels against the CPU twin with the f16 tolerances of the hardware test, at
/// sizes with partial 64-row blocks, and against the emulated subgroup-tiled kernels (the same f16
/// operands; only the f32 summation order differs).
#[test]
fn emulated_tiled_coop_mlp_matches_its_cpu_twin_and_the_untiled_kernels() {
    let Some(ctx) = context() else { return };
    if !ctx.features.shader_f16 {
        eprintln!("NOTICE: adapter {} has no SHADER_F16; the emulated kernels cannot run", ctx.describe());
        return;
    }
    let src = coop_emu::emulate(&shaders::with_common(shaders::LINEAR_COOP));
    let t0 = std::time::Instant::now();
    let mut cfgs = configs();
    cfgs.push(tiled_config());
    let tiled = compare_with(&ctx, cfgs, &[0, 1, 77, 130, 300], true, 1e-2, 5e-2, &|cfg, capacity| {
        let g = GpuMlp::with_coop_source(&ctx, cfg, capacity, &src, CoopTiling::Workgroup).unwrap();
        assert_eq!(g.path(), LinearPath::CoopTiled);
        g
    })
    .pop()
    .expect("the tiled config");
    eprintln!("emulated tiled kernels vs the CPU twin: {:.1} s", t0.elapsed().as_secs_f64());

    // Tiled vs untiled on one input. Both round the same f32 values to f16 at the same places;
    // accumulation order differs (the bias gradient is a plain sum in the tiled kernel), which
    // can move an f16 rounding by one ulp (~5e-4 relative): 2e-3 of the largest entry, 5-25×
    // tighter than the comparison with the CPU twin.
    let cfg = tiled_config();
    let untiled = GpuMlp::with_coop_source(&ctx, &cfg, tiled.capacity(), &src, CoopTiling::Subgroup).unwrap();
    assert_eq!(untiled.path(), LinearPath::Coop);
    let n = 77;
    let mut r = nerf_core::rng(77, 3);
    let mlp = Mlp::<f32>::new(cfg.clone(), &mut r);
    let input: Vec<f32> = (0..n * cfg.input_dim).map(|_| r.gen_range(-1.0f32..1.0)).collect();
    let d_out: Vec<f32> = (0..n * cfg.output_dim).map(|_| r.gen_range(-1.0f32..1.0)).collect();
    let run = |g: &GpuMlp| {
        let (out, tape) = g.run_forward(&ctx, &input, mlp.params(), n, true).unwrap();
        let mut grads = vec![0.0f32; g.n_params()];
        let dx = g.run_backward(&ctx, &input, mlp.params(), &d_out, &mut grads, n, true).unwrap().unwrap();
        (out, tape, grads, dx)
    };
    let (a, b) = (run(&untiled), run(&tiled));
    eprintln!("emulated tiled kernels, CPU twin and untiled kernels: {:.1} s", t0.elapsed().as_secs_f64());
    check("tiled vs untiled: output", &b.0, &a.0, 2e-3);
    check("tiled vs untiled: tape", &b.1, &a.1, 2e-3);
    check("tiled vs untiled: grads", &b.2, &a.2, 2e-3);
    check("tiled vs untiled: d_input", &b.3, &a.3, 2e-3);
    assert!(a.2.iter().any(|v| v.abs() > 1e-3), "gradients all ~0: the comparison would be vacuous");
}

#[test]
fn coop_tiled_mlp_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    let sg32 = ctx.info.subgroup_min_size == 32 && ctx.info.subgroup_max_size == 32;
    if !(ctx.features.cooperative_matrix && ctx.features.shader_f16 && sg32) {
        eprintln!(
            "NOTICE: adapter {} has no cooperative matrices / f16 / subgroups of exactly 32 ({}..={}); tiled coop path not compared",
            ctx.describe(),
            ctx.info.subgroup_min_size,
            ctx.info.subgroup_max_size
        );
        assert!(GpuMlp::new_with(&ctx, &tiled_config(), 16, LinearPath::CoopTiled).is_err());
        return;
    }
    // The tolerances of coop_mlp_matches_its_cpu_twin (same f16 operands).
    let mut cfgs = configs();
    cfgs.push(tiled_config());
    compare_with(&ctx, cfgs, &[0, 1, 77, 130, 300], true, 1e-2, 5e-2, &|cfg, capacity| {
        let g = GpuMlp::new_with(&ctx, cfg, capacity, LinearPath::CoopTiled).unwrap();
        assert_eq!(g.path(), LinearPath::CoopTiled);
        g
    });
}

// ---------------------------------------------------------------------------------------------
// The 128×128 kernels (LinearPath::CoopTiledWide).

/// Every wide product and a 64×64 one beside it: input 39 (xp 48), hidden 128 (one 128 block),
/// a skip into layer 1 (K = 48 + 128 = 176, so its weight gradient stays on the 64×64 kernel and
/// its data gradient is wide without `d_input`, columns [48, 176), and tiled with it), layer 2
/// 128 → 128 (wide forward, data and weight gradients), output 4 (np 16: a 64×64 forward and
/// weight gradient, a wide data gradient), biases, softplus hidden, sigmoid output.
fn wide_config() -> MlpConfig {
    MlpConfig {
        input_dim: 39,
        output_dim: 4,
        hidden_dim: 128,
        hidden_layers: 3,
        hidden_activation: Activation::Softplus,
        output_activation: Activation::Sigmoid,
        skips: vec![1],
        bias: true,
    }
}

const WIDE_ENTRY_POINTS: [&str; 3] = ["forward_wide", "backward_data_wide", "backward_weight_wide"];

#[test]
fn wide_coop_kernels_translate_to_spirv_within_28k_of_workgroup_memory() {
    for (ep, [loads, stores, muladds], wg_bytes) in translate(&shaders::with_common(shaders::LINEAR_COOP), WIDE_ENTRY_POINTS) {
        eprintln!("linear_coop.wgsl {ep}: {loads} coop loads, {stores} coop stores, {muladds} multiply-adds, {wg_bytes} B workgroup memory");
        // Per K step 4 A + 4 B tiles and 4×4 products; 16 accumulators stored for the epilogue.
        assert!(loads >= 8 && muladds >= 16 && stores >= 16, "{ep}: coop ops missing from the SPIR-V");
        assert_eq!(wg_bytes, 2 * 5120 * 2 + 2048 * 4 + 4, "{ep}: workgroup memory (GpuMlp checks the adapter for this many bytes)");
    }
}

/// Emulated wide kernels against the CPU twin with the f16 tolerances of the hardware test (the
/// paper's trunk and `wide_config`; sizes with partial 128-row blocks and two weight-gradient
/// splits), and against the emulated 64×64
/// kernels (the same f16 operands; only the f32 summation order differs).
#[test]
fn emulated_wide_coop_mlp_matches_its_cpu_twin_and_the_tiled_kernels() {
    let Some(ctx) = context() else { return };
    if !ctx.features.shader_f16 {
        eprintln!("NOTICE: adapter {} has no SHADER_F16; the emulated kernels cannot run", ctx.describe());
        return;
    }
    let src = coop_emu::emulate(&shaders::with_common(shaders::LINEAR_COOP));
    let t0 = std::time::Instant::now();
    // The paper's trunk too (63 → 8×256 with its skip → 257): the shapes the path is for.
    let cfgs = vec![MlpConfig::nerf_trunk(63, 257), wide_config()];
    let wide = compare_with(&ctx, cfgs, &[1, 130, 300], true, 1e-2, 5e-2, &|cfg, capacity| {
        let g = GpuMlp::with_coop_source(&ctx, cfg, capacity, &src, CoopTiling::WorkgroupWide).unwrap();
        assert_eq!(g.path(), LinearPath::CoopTiledWide);
        if cfg.hidden_dim == 256 {
            // forward: the 8 hidden layers (the 257-wide output is not a whole block); data
            // gradient: layers 1-8 (the skip layer's hidden columns without d_input); weight
            // gradient: layers 1-4, 6 and 7 (layer 0 has K = 64, the skip layer 5 K = 64 + 256,
            // the output 272 rows).
            assert_eq!(g.wide_products(false), [8, 8, 6]);
        } else {
            // forward: layers 0-2; data gradient: layers 1 (without d_input), 2 and 3; weight
            // gradient: layer 2.
            assert_eq!(g.wide_products(false), [3, 3, 1]);
            assert_eq!(g.wide_products(true), [3, 2, 1]);
        }
        g
    })
    .pop()
    .expect("wide_config");
    eprintln!("emulated wide kernels vs the CPU twin: {:.1} s", t0.elapsed().as_secs_f64());

    let cfg = wide_config();
    let tiled = GpuMlp::with_coop_source(&ctx, &cfg, wide.capacity(), &src, CoopTiling::Workgroup).unwrap();
    assert_eq!(tiled.wide_products(true), [0; 3]);
    let n = 200;
    let mut r = nerf_core::rng(78, 3);
    let mlp = Mlp::<f32>::new(cfg.clone(), &mut r);
    let input: Vec<f32> = (0..n * cfg.input_dim).map(|_| r.gen_range(-1.0f32..1.0)).collect();
    let d_out: Vec<f32> = (0..n * cfg.output_dim).map(|_| r.gen_range(-1.0f32..1.0)).collect();
    let run = |g: &GpuMlp, want_dx: bool| {
        let (out, tape) = g.run_forward(&ctx, &input, mlp.params(), n, true).unwrap();
        let mut grads = vec![0.0f32; g.n_params()];
        let dx = g.run_backward(&ctx, &input, mlp.params(), &d_out, &mut grads, n, want_dx).unwrap();
        (out, tape, grads, dx)
    };
    for want_dx in [true, false] {
        let (a, b) = (run(&tiled, want_dx), run(&wide, want_dx));
        // As in the tiled-vs-untiled comparison: an f16 rounding may move by one ulp.
        check("wide vs tiled: output", &b.0, &a.0, 2e-3);
        check("wide vs tiled: tape", &b.1, &a.1, 2e-3);
        check(&format!("wide vs tiled: grads (d_input {want_dx})"), &b.2, &a.2, 2e-3);
        assert!(a.2.iter().any(|v| v.abs() > 1e-3), "gradients all ~0: the comparison would be vacuous");
        if want_dx {
            check("wide vs tiled: d_input", &b.3.unwrap(), &a.3.unwrap(), 2e-3);
        }
    }
    eprintln!("emulated wide kernels, CPU twin and tiled kernels: {:.1} s", t0.elapsed().as_secs_f64());
}

/// The wide kernels on hardware (the H100, through the device tool) against the CPU twin, with
/// the tolerances of the other cooperative-matrix paths; elsewhere the path is refused.
#[test]
fn coop_tiled_wide_mlp_matches_its_cpu_twin() {
    let Some(ctx) = context() else { return };
    let sg32 = ctx.info.subgroup_min_size == 32 && ctx.info.subgroup_max_size == 32;
    if !(ctx.features.cooperative_matrix && ctx.features.shader_f16 && sg32) {
        eprintln!("NOTICE: adapter {} cannot run the wide cooperative-matrix path; not compared", ctx.describe());
        assert!(GpuMlp::new_with(&ctx, &wide_config(), 16, LinearPath::CoopTiledWide).is_err());
        return;
    }
    let mut cfgs = configs();
    cfgs.push(wide_config());
    cfgs.push(MlpConfig::nerf_trunk(63, 257));
    compare_with(&ctx, cfgs, &[0, 1, 77, 130, 300], true, 1e-2, 5e-2, &|cfg, capacity| {
        let g = GpuMlp::new_with(&ctx, cfg, capacity, LinearPath::CoopTiledWide).unwrap();
        assert_eq!(g.path(), LinearPath::CoopTiledWide);
        g
    });
}

#[test]
fn linear_paths_map_to_tilings() {
    assert_eq!(LinearPath::default(), LinearPath::Plain);
    assert_eq!(LinearPath::Plain.coop_tiling(), None);
    assert_eq!(LinearPath::Coop.coop_tiling(), Some(CoopTiling::Subgroup));
    assert_eq!(LinearPath::CoopTiled.coop_tiling(), Some(CoopTiling::Workgroup));
    assert_eq!(LinearPath::CoopTiledWide.coop_tiling(), Some(CoopTiling::WorkgroupWide));
    let Some(ctx) = context() else { return };
    let g = GpuMlp::new_with(&ctx, &small_trunk(Activation::None, 4), 16, LinearPath::Plain).unwrap();
    assert_eq!((g.path(), g.uses_coop()), (LinearPath::Plain, false));
}

// ---------------------------------------------------------------------------------------------
// Training without the hidden layers' f32 tape (GpuMlp::drop_hidden_tape).

/// ReLU hidden layers (the only kind, with identity, that may drop the tape), sized as
/// `tiled_config`: partial 64-row and 64-column blocks, a skip, biases, a sigmoid output.
fn relu_tiled_config() -> MlpConfig {
    MlpConfig { hidden_activation: Activation::Relu, ..tiled_config() }
}

/// `make(cfg, capacity, drop)` builds the same kernels twice, the second time without the hidden
/// f32 tape. On the same inputs both must give the same output, tape output block, gradients and
/// input gradients: the kernels are the same, and a ReLU's act' from the f16 copy of its output
/// equals the one from the f32 tape wherever that output is not in (0, 3·10⁻⁸). The dropped
/// tape's hidden blocks stay unwritten (NaN poison).
fn hidden_tape_changes_nothing(ctx: &GpuContext, configs: &[MlpConfig], make: &dyn Fn(&MlpConfig, usize, bool) -> GpuMlp) {
    for (ci, cfg) in configs.iter().enumerate() {
        let capacity = 300;
        let (kept, dropped) = (make(cfg, capacity, false), make(cfg, capacity, true));
        assert!(kept.keeps_hidden_tape() && !dropped.keeps_hidden_tape());
        let mut r = nerf_core::rng(500 + ci as u64, 2);
        let mlp = Mlp::<f32>::new(cfg.clone(), &mut r);
        for n in [1, 77, 300] {
            let input: Vec<f32> = (0..n * cfg.input_dim).map(|_| r.gen_range(-1.0f32..1.0)).collect();
            let d_out: Vec<f32> = (0..n * cfg.output_dim).map(|_| r.gen_range(-1.0f32..1.0)).collect();
            let tag = format!("config {ci} n {n}");
            let run = |g: &GpuMlp| {
                let (out, tape) = g.run_forward(ctx, &input, mlp.params(), n, true).unwrap();
                let mut grads = vec![0.0f32; g.n_params()];
                let dx = g.run_backward(ctx, &input, mlp.params(), &d_out, &mut grads, n, true).unwrap().unwrap();
                (out, tape, grads, dx)
            };
            let (a, b) = (run(&kept), run(&dropped));
            check(&format!("{tag}: output"), &b.0, &a.0, 1e-6);
            let t = kept.tape_floats_per_sample();
            let hidden = t - cfg.output_dim;
            for k in 0..n {
                let row = |tape: &[f32]| tape[k * t..(k + 1) * t].to_vec();
                let (ra, rb) = (row(&a.1), row(&b.1));
                check(&format!("{tag}: tape output block of sample {k}"), &rb[hidden..], &ra[hidden..], 1e-6);
                assert!(ra[..hidden].iter().all(|v| v.is_finite()), "{tag}: the kept tape was not written");
                assert!(rb[..hidden].iter().all(|v| v.is_nan()), "{tag}: the hidden tape was written after drop_hidden_tape");
            }
            check(&format!("{tag}: grads"), &b.2, &a.2, 1e-6);
            check(&format!("{tag}: d_input"), &b.3, &a.3, 1e-6);
            assert!(a.2.iter().any(|v| v.abs() > 1e-3), "{tag}: gradients all ~0: the comparison would be vacuous");
        }
    }
}

/// The emulated subgroup- and workgroup-tiled kernels (lavapipe) without the hidden tape.
#[test]
fn emulated_coop_mlp_trains_the_same_without_its_hidden_tape() {
    let Some(ctx) = context() else { return };
    if !ctx.features.shader_f16 {
        eprintln!("NOTICE: adapter {} has no SHADER_F16; the emulated kernels cannot run", ctx.describe());
        return;
    }
    let src = coop_emu::emulate(&shaders::with_common(shaders::LINEAR_COOP));
    let cfgs = [small_trunk(Activation::None, 5), relu_tiled_config(), MlpConfig { hidden_activation: Activation::None, ..small_trunk(Activation::Sigmoid, 3) }];
    for tiling in [CoopTiling::Subgroup, CoopTiling::Workgroup] {
        hidden_tape_changes_nothing(&ctx, &cfgs, &|cfg, capacity, drop| {
            let mut g = GpuMlp::with_coop_source(&ctx, cfg, capacity, &src, tiling).unwrap();
            if drop {
                g.drop_hidden_tape(&ctx).unwrap();
            }
            g
        });
    }
}

/// The same on tensor cores (the H100), for every cooperative-matrix path the adapter runs.
#[test]
fn coop_mlp_trains_the_same_without_its_hidden_tape() {
    let Some(ctx) = context() else { return };
    if !(ctx.features.cooperative_matrix && ctx.features.shader_f16) {
        eprintln!("NOTICE: adapter {} has no cooperative matrices / f16; not compared on tensor cores", ctx.describe());
        return;
    }
    let sg32 = ctx.info.subgroup_min_size == 32 && ctx.info.subgroup_max_size == 32;
    let paths: &[LinearPath] = if sg32 { &[LinearPath::Coop, LinearPath::CoopTiled, LinearPath::CoopTiledWide] } else { &[LinearPath::Coop] };
    let cfgs = [relu_tiled_config(), MlpConfig { hidden_activation: Activation::Relu, ..wide_config() }];
    for &path in paths {
        hidden_tape_changes_nothing(&ctx, &cfgs, &|cfg, capacity, drop| {
            let mut g = GpuMlp::new_with(&ctx, cfg, capacity, path).unwrap();
            if drop {
                g.drop_hidden_tape(&ctx).unwrap();
            }
            g
        });
    }
}

/// Where the hidden tape cannot be dropped: on the plain path (which keeps it), and with hidden
/// layers whose act' needs the value (softplus, tanh, sigmoid).
#[test]
fn the_hidden_tape_stays_where_it_is_needed() {
    let Some(ctx) = context() else { return };
    let mut plain = GpuMlp::new_with(&ctx, &relu_tiled_config(), 16, LinearPath::Plain).unwrap();
    let e = plain.drop_hidden_tape(&ctx).unwrap_err().to_string();
    assert!(e.contains("cooperative-matrix"), "{e}");
    assert!(plain.keeps_hidden_tape());
    if ctx.features.shader_f16 {
        let src = coop_emu::emulate(&shaders::with_common(shaders::LINEAR_COOP));
        let mut soft = GpuMlp::with_coop_source(&ctx, &tiled_config(), 16, &src, CoopTiling::Subgroup).unwrap();
        let e = soft.drop_hidden_tape(&ctx).unwrap_err().to_string();
        assert!(e.contains("ReLU") && e.contains("Softplus"), "{e}");
        assert!(soft.keeps_hidden_tape());
    }
}
