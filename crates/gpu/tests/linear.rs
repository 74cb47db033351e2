//! `GpuMlp` (tiled linear layers, plain WGSL and cooperative matrices) against its CPU twin
//! `nerf_mlp::Mlp` on random inputs: forward (output and tape), inference, backward (gradients
//! accumulated onto random pre-filled values, d_input). Outputs start poisoned with NaN.

use nerf_gpu::linear::GpuMlp;
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
    })
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
) {
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
    }
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
    // The same f16 tolerances as the hardware comparison (coop_mlp_matches_its_cpu_twin). One
    // config (input and hidden blocks, a skip, biases: every kernel and operand layout) and two
    // sizes: lavapipe compiles and runs the emulation slowly.
    let cfgs = vec![configs().swap_remove(1)];
    compare_with(&ctx, cfgs, &[1, 77], true, 1e-2, 5e-2, &|cfg, capacity| GpuMlp::with_coop_source(&ctx, cfg, capacity, &src).unwrap());
}
