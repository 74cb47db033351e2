//! The fused-MLP kernels (`shaders/mlp_fused.wgsl`, `nerf_gpu::mlp::FusedMlp`) against their CPU twin
//! `nerf_mlp::Mlp<f32>` on random inputs and weights: inference, training forward, backward (gradients
//! accumulated onto random pre-filled grads, d_input), outputs poisoned with NaN so that a skipped
//! slot fails, slots past n left untouched, and weight gradients that are the same bits on every run.

use nerf_gpu::mlp::FusedMlp;
use nerf_gpu::{DispatchArgs, GpuContext, GpuError, Launch};
use nerf_mlp::{Activation, Mlp, MlpConfig, MlpTape};
use rand::Rng as _;

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

#[path = "common/small_mlp.rs"]
mod small_mlp;
use small_mlp::{cfg, random};

/// The configurations under test: instant-ngp's density and colour nets, odd sizes with bias and
/// every activation, a single linear layer, a deep narrow net, widths between the block sizes and a
/// net of one weight.
fn configs() -> Vec<(&'static str, MlpConfig)> {
    use Activation::*;
    vec![
        ("density 32→64→16", cfg(32, 64, 1, 16, Relu, None, false)),
        ("colour 32→64→64→3", cfg(32, 64, 2, 3, Relu, Sigmoid, false)),
        ("odd tanh/softplus", cfg(7, 16, 2, 5, Tanh, Softplus, true)),
        ("odd softplus/exp", cfg(7, 16, 1, 5, Softplus, Exp, true)),
        ("linear only", cfg(13, 0, 0, 9, Relu, Tanh, true)),
        ("deep 64 wide", cfg(64, 64, 4, 64, Sigmoid, None, true)),
        // Widths that leave 3 and 5 register blocks of 8 (the kernels' 4- and 8-block loops with
        // a block wholly past the width).
        ("odd 20→40→24", cfg(20, 40, 1, 24, Relu, Tanh, true)),
        // One weight: a parameter buffer smaller than the forward's vec4 view of it.
        ("a single weight", cfg(1, 0, 0, 1, Relu, Tanh, false)),
    ]
}

/// |gpu − cpu| ≤ rel·|cpu| + abs_frac·max|cpu| for every element (and both finite).
fn assert_close(what: &str, gpu: &[f32], cpu: &[f32], rel: f32, abs_frac: f32) {
    assert_eq!(gpu.len(), cpu.len(), "{what}: lengths");
    let scale = cpu.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
    for (i, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert!(g.is_finite(), "{what}[{i}]: gpu {g} (cpu {c})");
        let tol = rel * c.abs() + abs_frac * scale;
        assert!((g - c).abs() <= tol, "{what}[{i}]: gpu {g} vs cpu {c} (tol {tol})");
    }
}

struct Run {
    inference: Vec<f32>,
    /// `record_inference_head` into its own NaN-poisoned buffer (all of it, not only the head).
    head: Vec<f32>,
    forward: Vec<f32>,
    grads: Vec<f32>,
    d_input: Option<Vec<f32>>,
}

/// Runs inference, the training forward and the backward on the device for n samples in buffers of
/// `capacity`, launched for the capacity or (`indirect`) from a `DispatchArgs` table for n; checks
/// that nothing past n is written (poison stays NaN).
#[allow(clippy::too_many_arguments)]
fn run_gpu(
    ctx: &GpuContext,
    net: &FusedMlp,
    n: usize,
    capacity: usize,
    input: &[f32],
    params: &[f32],
    grads0: &[f32],
    d_output: &[f32],
    with_dx: bool,
    indirect: bool,
) -> Run {
    let c = net.config();
    let (din, dout) = (c.input_dim, c.output_dim);
    let nan = |len: usize| vec![f32::NAN; len];
    let mut inp = input.to_vec();
    inp.resize(capacity * din, 0.0);
    let mut dout_v = d_output.to_vec();
    dout_v.resize(capacity * dout, 0.0);
    let counters = ctx.upload("counters", &[0u32, n as u32]);
    let input_b = ctx.upload("input", &inp);
    let params_b = ctx.upload("params", params);
    let out_inf = ctx.upload("out inference", &nan(capacity * dout));
    let out_fwd = ctx.upload("out forward", &nan(capacity * dout));
    let out_head = ctx.upload("out head", &nan(capacity * dout));
    let tape = ctx.upload("tape", &nan(capacity * net.tape_floats_per_sample()));
    let d_out_b = ctx.upload("d_output", &dout_v);
    let grads_b = ctx.upload("grads", grads0);
    let d_in_b = ctx.upload("d_input", &nan(capacity * din));
    let mut enc = ctx.encoder("mlp test");
    let args = DispatchArgs::new(ctx, capacity);
    let launch = if indirect { args.record(ctx, &mut enc, &counters, capacity) } else { Launch::direct(capacity) };
    net.record_inference(ctx, &mut enc, &counters, &input_b, &params_b, &out_inf, launch);
    net.record_inference_head(ctx, &mut enc, &counters, &input_b, &params_b, &out_head, launch);
    net.record_forward(ctx, &mut enc, &counters, &input_b, &params_b, &out_fwd, &tape, launch);
    net.record_backward(
        ctx,
        &mut enc,
        &counters,
        &input_b,
        &params_b,
        &tape,
        &d_out_b,
        &grads_b,
        with_dx.then_some(&d_in_b),
        launch,
    );
    ctx.queue.submit([enc.finish()]);
    let read = |b, len| ctx.read_f32(b, len).unwrap();
    let (inference, forward) = (read(&out_inf, capacity * dout), read(&out_fwd, capacity * dout));
    let d_input = read(&d_in_b, capacity * din);
    let head = read(&out_head, capacity * dout);
    for (what, v, w) in [("inference", &inference, dout), ("forward", &forward, dout), ("head", &head, dout), ("d_input", &d_input, din)] {
        assert!(v[n * w..].iter().all(|x| x.is_nan()), "{what}: slots past n = {n} were written");
    }
    if !with_dx {
        assert!(d_input.iter().all(|x| x.is_nan()), "d_input written although not requested");
    }
    Run {
        inference: inference[..n * dout].to_vec(),
        head: head[..n * dout].to_vec(),
        forward: forward[..n * dout].to_vec(),
        grads: read(&grads_b, params.len()),
        d_input: with_dx.then(|| d_input[..n * din].to_vec()),
    }
}

/// Every config, several sizes (0, 1, not a multiple of the tile, several tiles per weight-gradient
/// workgroup, fewer tiles than weight-gradient workgroups), one net per config reused across the
/// sizes (its buffer of per-workgroup sums is remade when the number of workgroups changes).
#[test]
fn fused_mlp_matches_the_cpu_mlp() {
    let Some(ctx) = context() else { return };
    let mut seed = 100u64;
    for (name, config) in configs() {
        let net = FusedMlp::new(&ctx, &config).unwrap();
        // (2100, 300): 3 workgroups of 22 tiles; (8000, 192) then (100, 8092): 8 workgroups,
        // first all with tiles, then 4 tiles for the 8, whose other 4 rows of sums still hold the
        // run before's (the sum must read only the 4 written); (20000, 500): 21 rows of sums, more
        // than the 8 lanes of mlp_wgrad_sum.
        for (n, extra) in [(0usize, 5usize), (1, 0), (33, 7), (517, 0), (2100, 300), (8000, 192), (100, 8092), (20000, 500)] {
            seed += 1;
            let mut rng = nerf_core::rng(seed, 0);
            let mut cpu = Mlp::<f32>::new(config.clone(), &mut rng);
            assert_eq!(net.n_params(), cpu.n_params(), "{name}: n_params");
            let input = random(&mut rng, n * config.input_dim, 2.0);
            let d_output = random(&mut rng, n * config.output_dim, 1.0);
            let grads0 = random(&mut rng, cpu.n_params(), 1.0);
            let with_dx = n != 517;
            // Every other case launches from the device's count.
            let gpu = run_gpu(&ctx, &net, n, n + extra, &input, cpu.params(), &grads0, &d_output, with_dx, seed.is_multiple_of(2));
            let what = format!("{name} (n = {n})");
            if n == 8000 {
                // Summed in a fixed order: a second run gives the same gradient bits.
                let again = run_gpu(&ctx, &net, n, n + extra, &input, cpu.params(), &grads0, &d_output, with_dx, seed.is_multiple_of(2));
                assert_eq!(bits(&again.grads), bits(&gpu.grads), "{what}: gradients differ between two runs");
            }
            // Inference and the training forward run the same code: bit-identical.
            assert_eq!(
                gpu.inference.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                gpu.forward.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "{what}: inference != forward"
            );
            // Without set_partial the head inference is the whole inference.
            assert_eq!(bits(&gpu.head), bits(&gpu.inference), "{what}: head != inference");
            if n == 0 {
                assert_eq!(gpu.grads, grads0, "{what}: n = 0 changed the gradients");
                continue;
            }
            let mut tape = MlpTape::default();
            let out = cpu.forward(n, &input, &mut tape).to_vec();
            // f32 dot products of ≤ 64 terms summed in another order (and GPU exp/log/tanh).
            assert_close(&format!("{what}: output"), &gpu.forward, &out, 1e-4, 1e-5);
            cpu.grads_mut().copy_from_slice(&grads0);
            let mut d_in = vec![0.0f32; n * config.input_dim];
            cpu.backward(n, &input, &mut tape, &d_output, Some(&mut d_in));
            // Gradients are sums over up to 20000 samples in a different order (tiles, sample
            // splits, workgroups): relative 1e-3 plus 1e-4 of the largest entry.
            assert_close(&format!("{what}: grads"), &gpu.grads, cpu.grads(), 1e-3, 1e-4);
            if let Some(d) = &gpu.d_input {
                // Back-propagated through every layer: f32 rounding of each dot product compounds.
                assert_close(&format!("{what}: d_input"), d, &d_in, 1e-3, 1e-5);
            }
        }
    }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// `set_partial(head, cols)`: the head inference writes exactly the first `head` outputs of each
/// row (bit-identical to the full inference: the same arithmetic, fewer register blocks) and leaves
/// the others as they were; a backward with d_input writes exactly its first `cols` columns
/// (bit-identical to the full net's); the training forward and the weight gradients do not change.
#[test]
fn partial_heads_and_input_gradients_write_only_what_is_asked() {
    let Some(ctx) = context() else { return };
    let mut seed = 900u64;
    for (name, config) in configs() {
        let (din, dout) = (config.input_dim, config.output_dim);
        let full = FusedMlp::new(&ctx, &config).unwrap();
        assert_eq!(full.partial(), (dout, din), "{name}: defaults");
        let mut clamped = FusedMlp::new(&ctx, &config).unwrap();
        clamped.set_partial(&ctx, 0, din + 5);
        assert_eq!(clamped.partial(), (1, din), "{name}: clamped");
        // Several (head, cols) per config, the narrowest and a random one.
        for round in 0..2 {
            seed += 1;
            let mut rng = nerf_core::rng(seed, 0);
            let (head, cols) = match round {
                0 => (1, 1),
                _ => (1 + rng.gen_range(0..dout), 1 + rng.gen_range(0..din)),
            };
            let mut part = FusedMlp::new(&ctx, &config).unwrap();
            part.set_partial(&ctx, head, cols);
            assert_eq!(part.partial(), (head, cols));
            let n = 77;
            let cpu = Mlp::<f32>::new(config.clone(), &mut rng);
            let input = random(&mut rng, n * din, 2.0);
            let d_output = random(&mut rng, n * dout, 1.0);
            let grads0 = random(&mut rng, cpu.n_params(), 1.0);
            let indirect = seed.is_multiple_of(2);
            let a = run_gpu(&ctx, &full, n, n + 3, &input, cpu.params(), &grads0, &d_output, true, indirect);
            let b = run_gpu(&ctx, &part, n, n + 3, &input, cpu.params(), &grads0, &d_output, true, indirect);
            let what = format!("{name} (head {head}, cols {cols})");
            assert_eq!(bits(&b.forward), bits(&a.forward), "{what}: training forward");
            assert_eq!(bits(&b.inference), bits(&a.inference), "{what}: full inference");
            assert_eq!(bits(&b.grads), bits(&a.grads), "{what}: weight gradients");
            let (da, db) = (a.d_input.unwrap(), b.d_input.unwrap());
            for r in 0..n {
                for j in 0..dout {
                    let (x, y) = (b.head[r * dout + j], a.inference[r * dout + j]);
                    if j < head {
                        assert_eq!(x.to_bits(), y.to_bits(), "{what}: head [{r}][{j}]");
                    } else {
                        assert!(x.is_nan(), "{what}: head [{r}][{j}] past the head was written");
                    }
                }
                for k in 0..din {
                    let (x, y) = (db[r * din + k], da[r * din + k]);
                    if k < cols {
                        assert_eq!(x.to_bits(), y.to_bits(), "{what}: d_input [{r}][{k}]");
                    } else {
                        assert!(x.is_nan(), "{what}: d_input [{r}][{k}] past the columns was written");
                    }
                }
            }
        }
    }
}

/// The density pass of a compacted step keeps its activations as rows (`record_forward_rows`)
/// and the kept samples' tape is gathered from them (`record_gather_tape`): for random rows (in
/// random order, with repeats), the gathered output and tape are the same bits as the training
/// forward on the gathered inputs, including the tape's unwritten gradient half and every float
/// past n (poison stays), and each tape float sits where the tile layout puts it (host twin). The
/// rows' last layer is the forward's output, which matches the CPU net; nothing past the batch is
/// written.
#[test]
fn activation_rows_gather_into_the_training_forwards_tape() {
    let Some(ctx) = context() else { return };
    let mut seed = 1300u64;
    for (name, config) in configs() {
        let net = FusedMlp::new(&ctx, &config).unwrap();
        let (din, dout, fps, fa) = (config.input_dim, config.output_dim, net.tape_floats_per_sample(), net.activation_floats_per_sample());
        assert_eq!(2 * fa, fps, "{name}: the activations are half the tape");
        // (source rows, kept samples): a partial last tile, whole tiles, one sample, none.
        for (n_src, n) in [(150usize, 101usize), (70, 64), (9, 1), (40, 0)] {
            seed += 1;
            let mut rng = nerf_core::rng(seed, 0);
            let cpu = Mlp::<f32>::new(config.clone(), &mut rng);
            let (cap_src, cap) = (n_src + 5, n + 3);
            let input_src = random(&mut rng, cap_src * din, 2.0);
            let rows: Vec<u32> = (0..cap).map(|_| rng.gen_range(0..n_src as u32)).collect();
            let mut input = Vec::with_capacity(cap * din);
            for &r in &rows {
                input.extend_from_slice(&input_src[r as usize * din..(r as usize + 1) * din]);
            }
            let nan = |len: usize| vec![f32::NAN; len];
            let params = ctx.upload("params", cpu.params());
            let c_src = ctx.upload("counters src", &[0u32, n_src as u32]);
            let c = ctx.upload("counters", &[0u32, n as u32]);
            let (in_src_b, in_b, rows_b) = (ctx.upload("input src", &input_src), ctx.upload("input", &input), ctx.upload("rows", &rows));
            let acts = ctx.upload("activation rows", &nan(cap_src * fa));
            let out_src = ctx.upload("out src", &nan(cap_src * dout));
            let (out_ref, tape_ref) = (ctx.upload("out ref", &nan(cap * dout)), ctx.upload("tape ref", &nan(cap * fps)));
            let (out_g, tape_g) = (ctx.upload("out gathered", &nan(cap * dout)), ctx.upload("tape gathered", &nan(cap * fps)));
            let mut enc = ctx.encoder("rows test");
            let (args_src, args) = (DispatchArgs::new(&ctx, cap_src), DispatchArgs::new(&ctx, cap));
            let indirect = seed.is_multiple_of(2);
            let l_src = if indirect { args_src.record(&ctx, &mut enc, &c_src, cap_src) } else { Launch::direct(cap_src) };
            net.record_forward_rows(&ctx, &mut enc, &c_src, &in_src_b, &params, &out_src, &acts, l_src);
            let l = if indirect { args.record(&ctx, &mut enc, &c, cap) } else { Launch::direct(cap) };
            net.record_forward(&ctx, &mut enc, &c, &in_b, &params, &out_ref, &tape_ref, l);
            net.record_gather_tape(&ctx, &mut enc, &c, &rows_b, &acts, &out_g, &tape_g, l);
            ctx.queue.submit([enc.finish()]);
            let read = |b, len| ctx.read_f32(b, len).unwrap();
            let what = format!("{name} (n = {n} of {n_src})");
            let (acts_v, out_src_v) = (read(&acts, cap_src * fa), read(&out_src, cap_src * dout));
            assert!(acts_v[n_src * fa..].iter().all(|x| x.is_nan()), "{what}: activation rows past the batch written");
            assert!(acts_v[..n_src * fa].iter().all(|x| x.is_finite()), "{what}: an activation row left unwritten");
            assert!(out_src_v[n_src * dout..].iter().all(|x| x.is_nan()), "{what}: outputs past the batch written");
            // The rows end with the last layer's activations: the output, which is the CPU net's.
            for r in 0..n_src {
                assert_eq!(bits(&acts_v[r * fa + fa - dout..(r + 1) * fa]), bits(&out_src_v[r * dout..(r + 1) * dout]), "{what}: row {r}");
            }
            let cpu_out = cpu.forward(n_src, &input_src[..n_src * din], &mut MlpTape::default()).to_vec();
            assert_close(&format!("{what}: output"), &out_src_v[..n_src * dout], &cpu_out, 1e-4, 1e-5);
            let (tr, tg) = (read(&tape_ref, cap * fps), read(&tape_g, cap * fps));
            assert_eq!(bits(&read(&out_g, cap * dout)), bits(&read(&out_ref, cap * dout)), "{what}: output");
            assert_eq!(bits(&tg), bits(&tr), "{what}: tape");
            // Host twin of the layout: tile t0, m samples; feature f of sample t0 + i at t0·fps + m·f + i.
            for s in 0..n {
                let (t0, i) = (s - s % 32, s % 32);
                let m = (n - t0).min(32);
                for f in 0..fa {
                    let want = acts_v[rows[s] as usize * fa + f];
                    assert_eq!(tg[t0 * fps + m * f + i].to_bits(), want.to_bits(), "{what}: sample {s} feature {f}");
                }
            }
        }
    }
}

/// Large activations: tanh/sigmoid/exp saturate like the CPU (no NaN from exp overflow in tanh).
#[test]
fn saturating_activations_stay_finite() {
    let Some(ctx) = context() else { return };
    let config = cfg(4, 8, 1, 2, Activation::Tanh, Activation::Sigmoid, true);
    let net = FusedMlp::new(&ctx, &config).unwrap();
    let mut rng = nerf_core::rng(7, 0);
    let mut cpu = Mlp::<f32>::new(config.clone(), &mut rng);
    cpu.params_mut().iter_mut().for_each(|p| *p *= 200.0);
    let n = 40;
    let input = random(&mut rng, n * 4, 50.0);
    let d_output = random(&mut rng, n * 2, 1.0);
    let grads0 = vec![0.0f32; cpu.n_params()];
    let gpu = run_gpu(&ctx, &net, n, n, &input, cpu.params(), &grads0, &d_output, true, true);
    let mut tape = MlpTape::default();
    let out = cpu.forward(n, &input, &mut tape).to_vec();
    assert_close("saturated output", &gpu.forward, &out, 1e-4, 1e-5);
    cpu.backward(n, &input, &mut tape, &d_output, None);
    // Saturated units have derivatives ~0 in both; the rest as in the main test.
    assert_close("saturated grads", &gpu.grads, cpu.grads(), 1e-3, 1e-4);
}

/// Configs the fused kernels cannot run give `GpuError::Unsupported` naming the problem.
#[test]
fn unsupported_configs_are_rejected_with_a_clear_error() {
    let Some(ctx) = context() else { return };
    use Activation::*;
    let mut skip = cfg(32, 64, 3, 3, Relu, None, true);
    skip.skips = vec![2];
    for (config, needle) in [
        (cfg(32, 128, 2, 3, Relu, None, false), "hidden_dim = 128"),
        (cfg(65, 64, 1, 3, Relu, None, false), "input_dim = 65"),
        (cfg(32, 64, 1, 100, Relu, None, false), "output_dim = 100"),
        (skip, "skip"),
        (cfg(0, 64, 1, 3, Relu, None, false), "input_dim must be positive"),
    ] {
        match FusedMlp::new(&ctx, &config) {
            Err(GpuError::Unsupported(m)) => assert!(m.contains(needle), "{m:?} should mention {needle:?}"),
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("{config:?} was accepted"),
        }
    }
    // A hidden_dim beyond the limit is fine when there are no hidden layers (it is unused).
    assert!(FusedMlp::new(&ctx, &cfg(8, 500, 0, 4, Relu, None, true)).is_ok());
}
