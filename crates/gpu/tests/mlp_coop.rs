//! The cooperative-matrix fused MLP (`shaders/mlp_fused_coop.wgsl`, `nerf_gpu::mlp_coop::FusedMlpCoop`).
//!
//! Always (no device needed): the shader parses and validates with naga and translates to SPIR-V
//! with naga's spv-out backend per entry point, the way wgpu-hal's Vulkan backend compiles it
//! (`linear_coop.wgsl`, known to run on an H100, goes through the same harness as a control), and
//! the Rust uniform matches the shader's struct layout.
//!
//! Where the adapter has cooperative matrices (not lavapipe: a NOTICE and an early return there):
//! inference, training forward, backward (gradients accumulated onto random pre-filled values,
//! d_input) against (a) an f16-emulating f64 reference that rounds where the kernels round (tight
//! tolerances: catches any indexing/layout bug) and (b) the CPU twin `nerf_mlp::Mlp<f32>` (f16
//! tolerances), outputs poisoned with NaN, slots past n untouched; unsupported configs give clear
//! errors.

use half::f16;
use nerf_gpu::mlp_coop::{self, CoopMlpParams, FusedMlpCoop};
use nerf_gpu::{shaders, DispatchArgs, GpuContext, GpuError, Launch};
use nerf_mlp::{Activation, Mlp, MlpConfig, MlpTape};

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

// ------------------------------------------------------------------------------------------------
// No device: naga validation and SPIR-V translation.

/// SPIR-V opcodes of the KHR cooperative-matrix instructions.
const OP_COOP_LOAD: u32 = 4457;
const OP_COOP_STORE: u32 = 4458;
const OP_COOP_MULADD: u32 = 4459;

/// Counts of (loads, stores, multiply-adds) in a SPIR-V module.
fn count_coop_ops(words: &[u32]) -> (usize, usize, usize) {
    assert!(words.len() > 5 && words[0] == 0x0723_0203, "not a SPIR-V module");
    let (mut l, mut s, mut m) = (0, 0, 0);
    let mut i = 5;
    while i < words.len() {
        let (count, op) = ((words[i] >> 16) as usize, words[i] & 0xffff);
        assert!(count > 0, "malformed SPIR-V instruction at word {i}");
        match op {
            OP_COOP_LOAD => l += 1,
            OP_COOP_STORE => s += 1,
            OP_COOP_MULADD => m += 1,
            _ => {}
        }
        i += count;
    }
    assert_eq!(i, words.len(), "SPIR-V instruction stream overruns the module");
    (l, s, m)
}

/// Parses and validates `src` (all capabilities), then translates every entry point to SPIR-V as
/// wgpu-hal 30's Vulkan backend does (process_overrides, then spv::write_vec with the entry point's
/// pipeline options; SPIR-V 1.6; index bounds checks `Restrict`, buffer checks `Restrict` or
/// `Unchecked` depending on robustBufferAccess2; no workgroup zero-init as `Kernel` asks). Returns
/// per entry point the coop op counts.
fn translate(name: &str, src: &str) -> Vec<(String, (usize, usize, usize))> {
    use naga::back::spv;
    let module = naga::front::wgsl::parse_str(src).unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(src)));
    let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
    let info = v.validate(&module).unwrap_or_else(|e| panic!("{name}: naga validation: {e:?}"));
    let mut out = Vec::new();
    for buffer in [naga::proc::BoundsCheckPolicy::Restrict, naga::proc::BoundsCheckPolicy::Unchecked] {
        let options = spirv::vulkan_options(buffer);
        // The whole module at once, then entry point by entry point (what a pipeline compiles).
        spv::write_vec(&module, &info, &options, None)
            .unwrap_or_else(|e| panic!("{name}: SPIR-V translation of the whole module ({buffer:?}): {e}"));
        for ep in &module.entry_points {
            let (m, i) = naga::back::pipeline_constants::process_overrides(
                &module,
                &info,
                Some((ep.stage, &ep.name)),
                &Default::default(),
            )
            .unwrap_or_else(|e| panic!("{name}: {}: process_overrides: {e}", ep.name));
            let po = spv::PipelineOptions { shader_stage: ep.stage, entry_point: ep.name.clone() };
            let words = spv::write_vec(&m, &i, &options, Some(&po))
                .unwrap_or_else(|e| panic!("{name}: {}: SPIR-V translation ({buffer:?}): {e}", ep.name));
            let counts = count_coop_ops(&words);
            if buffer == naga::proc::BoundsCheckPolicy::Restrict {
                out.push((ep.name.clone(), counts));
            }
        }
    }
    out
}

#[test]
fn coop_shaders_validate_and_translate_to_spirv() {
    // Control: linear_coop.wgsl ran on an H100, so the harness must accept it.
    let control = translate("linear_coop.wgsl", &shaders::with_common(shaders::LINEAR_COOP));
    let fwd = control.iter().find(|(n, _)| n == "forward").expect("linear_coop forward");
    assert!(fwd.1 .2 > 0, "linear_coop forward has no coop multiply-add in its SPIR-V: {control:?}");

    let ops = translate("mlp_fused_coop.wgsl", &mlp_coop::source());
    let names: Vec<&str> = ops.iter().map(|(n, _)| n.as_str()).collect();
    for ep in ["convert_weights", "forward", "backward", "wgrad", "reduce_grads"] {
        assert!(names.contains(&ep), "entry point {ep} missing: {names:?}");
    }
    for (ep, (loads, stores, muladds)) in &ops {
        eprintln!("mlp_fused_coop.wgsl {ep}: {loads} coop loads, {stores} coop stores, {muladds} multiply-adds");
        let is_coop = matches!(ep.as_str(), "forward" | "backward" | "wgrad");
        assert_eq!(*muladds > 0, is_coop, "{ep}: coop multiply-adds {muladds}");
        assert_eq!(*loads > 0 && *stores > 0, is_coop, "{ep}: coop loads {loads}, stores {stores}");
    }
}

/// The Rust uniform (`CoopMlpParams`) has the size and member offsets naga computes for the
/// shader's `Params` / `Layer` structs, and the plan matches the CPU twin's parameter count.
#[test]
fn uniform_layout_and_plan_match_the_shader_and_the_cpu_twin() {
    let src = mlp_coop::source();
    let module = naga::front::wgsl::parse_str(&src).unwrap_or_else(|e| panic!("{}", e.emit_to_string(&src)));
    let find = |name: &str| {
        module
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some(name))
            .unwrap_or_else(|| panic!("struct {name} not in the shader"))
            .1
            .inner
            .clone()
    };
    let gctx = module.to_ctx();
    let params = find("Params");
    assert_eq!(params.size(gctx) as usize, std::mem::size_of::<CoopMlpParams>(), "Params size");
    let layer = find("Layer");
    assert_eq!(layer.size(gctx) as usize, std::mem::size_of::<mlp_coop::CoopLayerDesc>(), "Layer size");
    if let naga::TypeInner::Struct { members, .. } = &params {
        let layers = members.iter().find(|m| m.name.as_deref() == Some("layers")).expect("layers member");
        assert_eq!(layers.offset as usize, std::mem::offset_of!(CoopMlpParams, layers), "layers offset");
        let zero = members.iter().find(|m| m.name.as_deref() == Some("zero")).expect("zero member");
        assert_eq!(zero.offset as usize, std::mem::offset_of!(CoopMlpParams, zero), "zero offset");
    } else {
        panic!("Params is not a struct");
    }
    if let naga::TypeInner::Struct { members, .. } = &layer {
        let nblk = members.iter().find(|m| m.name.as_deref() == Some("nblk")).expect("nblk member");
        assert_eq!(nblk.offset as usize, std::mem::offset_of!(mlp_coop::CoopLayerDesc, nblk), "nblk offset");
    }
    for (name, config) in configs() {
        let (p, layers) = FusedMlpCoop::plan(&config);
        let mut rng = nerf_core::rng(3, 0);
        let cpu = Mlp::<f32>::new(config.clone(), &mut rng);
        assert_eq!(p.n_params as usize, cpu.n_params(), "{name}: n_params");
        assert_eq!(layers.len(), config.hidden_layers + 1, "{name}: layers");
        assert_eq!(p.zero, 0);
        let mut col = 0;
        for (l, (d, (cpu_w, cpu_b))) in layers.iter().zip(cpu.layer_offsets()).enumerate() {
            assert_eq!(d.w_off as usize, cpu_w, "{name}: layer {l} W offset");
            assert_eq!(cpu_b.map(|b| b as u32), (d.has_bias != 0).then_some(d.b_off), "{name}: layer {l} b offset");
            assert!(d.np % 16 == 0 && d.kp % 16 == 0 && d.np >= d.out && d.kp >= d.fan_in && d.np - d.out < 16);
            assert_eq!((d.a_off, d.d_off), (col, col + d.np), "{name}: layer {l} tape columns");
            col += 2 * d.np;
        }
        assert_eq!(p.s16, col, "{name}: tape row");
        assert!(p.splits >= 1 && (p.splits * p.ps) as usize <= 1 << 21, "{name}: partial buffer");
    }
}

// ------------------------------------------------------------------------------------------------
// A plain-WGSL emulation of the cooperative-matrix ops, so that the kernels' indexing, layouts,
// staging, reduction and the host side run on any adapter with f16 (lavapipe in CI).

/// `mlp_coop::source()` with every coop op replaced by plain WGSL (`common/coop_emu.rs`): each
/// 16×16 matrix spread over the subgroup's 32 lanes, 8 entries per lane; loads / stores read and
/// write the same elements with the same strides and layouts as the real ops, the multiply-add is
/// C + A·B in f32 (like the tensor cores' f32 accumulation). Relies on the shader naming every
/// coop pointer index and stride with a plain identifier (the "runtime zero" lets).
#[path = "common/coop_emu.rs"]
mod coop_emu;
#[path = "common/spirv.rs"]
mod spirv;

fn emulated_source() -> String {
    coop_emu::emulate(&mlp_coop::source())
}

#[test]
fn emulated_source_validates() {
    let src = emulated_source();
    let module = naga::front::wgsl::parse_str(&src).unwrap_or_else(|e| panic!("{}", e.emit_to_string(&src)));
    let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all());
    v.validate(&module).unwrap_or_else(|e| panic!("emulated mlp_fused_coop.wgsl: {e:?}"));
    // Every load / store of the real shader became a call (5 kinds of loads, 2 stores).
    assert_eq!(src.matches("fn emu_load_").count(), 5, "{src}");
    assert_eq!(src.matches("fn emu_store_").count(), 2);
}

/// The kernels with emulated coop ops against both references, on any adapter with f16.
#[test]
fn emulated_coop_kernels_match_their_references() {
    let Some(ctx) = context() else { return };
    if !ctx.features.shader_f16 {
        eprintln!("NOTICE: adapter {} has no SHADER_F16; the emulated kernels cannot run", ctx.describe());
        return;
    }
    // One compilation (slow on lavapipe) shared by every config.
    let base = FusedMlpCoop::with_source(&ctx, &configs()[0].1, &emulated_source()).unwrap();
    compare_all(&ctx, |c| base.with_config(&ctx, c), false);
}

// ------------------------------------------------------------------------------------------------
// Device: against the references.

#[path = "common/small_mlp.rs"]
mod small_mlp;
use small_mlp::{cfg, random};

/// instant-ngp's density and colour nets, odd sizes with biases and every activation, a single
/// linear layer, a deep 64-wide net (with bias: 80 columns in the weight-gradient product).
fn configs() -> Vec<(&'static str, MlpConfig)> {
    use Activation::*;
    vec![
        ("density 32→64→16", cfg(32, 64, 1, 16, Relu, None, false)),
        ("colour 32→64→64→3", cfg(32, 64, 2, 3, Relu, Sigmoid, false)),
        ("odd tanh/softplus", cfg(7, 16, 2, 5, Tanh, Softplus, true)),
        ("odd softplus/exp", cfg(20, 48, 1, 33, Softplus, Exp, true)),
        ("linear only", cfg(13, 0, 0, 9, Relu, Tanh, true)),
        ("deep 64 wide", cfg(64, 64, 4, 64, Sigmoid, None, true)),
    ]
}

/// Per element: |gpu − ref| ≤ tol·(max|ref| + |ref|). On failure reports the worst element, the
/// number of violations, the max abs / rel error and the scale.
fn check(what: &str, gpu: &[f32], reference: &[f32], tol: f64) {
    assert_eq!(gpu.len(), reference.len(), "{what}: lengths");
    let scale = reference.iter().fold(0.0f64, |m, v| m.max(v.abs() as f64)).max(1e-6);
    let (mut bad, mut worst, mut worst_i, mut max_abs, mut max_rel) = (0usize, 0.0f64, 0usize, 0.0f64, 0.0f64);
    for (i, (&g, &c)) in gpu.iter().zip(reference).enumerate() {
        assert!(g.is_finite(), "{what}[{i}]: gpu {g} (reference {c}): not written or overflow");
        let (g, c) = (g as f64, c as f64);
        let err = (g - c).abs();
        let ratio = err / (tol * (scale + c.abs()));
        max_abs = max_abs.max(err);
        max_rel = max_rel.max(err / c.abs().max(1e-30));
        if ratio > 1.0 {
            bad += 1;
        }
        if ratio > worst {
            worst = ratio;
            worst_i = i;
        }
    }
    assert!(
        bad == 0,
        "{what}: {bad} of {} elements out of tolerance {tol}·(scale + |ref|); worst [{worst_i}]: gpu {} vs ref {} \
         ({worst:.2}× the tolerance); max abs err {max_abs:.3e}, max rel err {max_rel:.3e}, scale {scale:.3e}",
        gpu.len(),
        gpu[worst_i],
        reference[worst_i]
    );
}

/// ‖gpu − ref‖₂ ≤ tol·‖ref‖₂ (robust to a few ReLU masks flipped by f16 rounding).
fn check_norm(what: &str, gpu: &[f32], reference: &[f32], tol: f64) {
    assert_eq!(gpu.len(), reference.len(), "{what}: lengths");
    assert!(gpu.iter().all(|v| v.is_finite()), "{what}: non-finite values");
    let diff: f64 = gpu.iter().zip(reference).map(|(&g, &c)| (g as f64 - c as f64).powi(2)).sum::<f64>().sqrt();
    let norm: f64 = reference.iter().map(|&c| (c as f64).powi(2)).sum::<f64>().sqrt().max(1e-12);
    assert!(diff <= tol * norm, "{what}: relative L2 error {:.3e} > {tol} (‖ref‖ = {norm:.3e})", diff / norm);
}

fn h(x: f64) -> f64 {
    f16::from_f64(x).to_f64()
}

/// Rounds where the kernels round (inputs, weights, hidden activations, the tape, GRAD_SCALE·dZ to
/// f16), accumulates in f64. Returns (output, grads accumulated onto `grads0`, d_input).
fn emulate(config: &MlpConfig, params: &[f32], input: &[f32], d_output: &[f32], grads0: &[f32], n: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    const GS: f64 = 128.0;
    let (p, layers) = FusedMlpCoop::plan(config);
    let nl = layers.len();
    let w16: Vec<f64> = params.iter().map(|&w| h(w as f64)).collect();
    let mut out = vec![0.0f32; n * config.output_dim];
    let mut grads: Vec<f64> = grads0.iter().map(|&g| g as f64).collect();
    let mut dsum = vec![0.0f64; p.n_params as usize];
    let mut d_in = vec![0.0f32; n * config.input_dim];
    for s in 0..n {
        // acts[0] = f16 input, acts[l + 1] = f16 A_l (the tape).
        let mut acts: Vec<Vec<f64>> = vec![input[s * config.input_dim..(s + 1) * config.input_dim].iter().map(|&x| h(x as f64)).collect()];
        for (l, d) in layers.iter().enumerate() {
            let (fi, o) = (d.fan_in as usize, d.out as usize);
            let act = if l + 1 == nl { config.output_activation } else { config.hidden_activation };
            let mut a = Vec::with_capacity(o);
            for j in 0..o {
                let w = &w16[d.w_off as usize + j * fi..][..fi];
                let mut z: f64 = w.iter().zip(&acts[l]).map(|(w, x)| w * x).sum();
                // Accumulated in f32 on the device, bias added in f32.
                z = z as f32 as f64;
                if d.has_bias != 0 {
                    z += params[d.b_off as usize + j] as f64;
                }
                let y = act.apply(z);
                if l + 1 == nl {
                    out[s * o + j] = y as f32;
                }
                a.push(h(y as f32 as f64));
            }
            acts.push(a);
        }
        // Backward.
        let dl = &layers[nl - 1];
        let mut dz: Vec<f64> = (0..dl.out as usize)
            .map(|j| {
                let y = acts[nl][j];
                h(GS * d_output[s * dl.out as usize + j] as f64 * config.output_activation.derivative_from_output(y))
            })
            .collect();
        for l in (0..nl).rev() {
            let d = &layers[l];
            let (fi, o) = (d.fan_in as usize, d.out as usize);
            for j in 0..o {
                for k in 0..fi {
                    dsum[d.w_off as usize + j * fi + k] += dz[j] * acts[l][k];
                }
                if d.has_bias != 0 {
                    dsum[d.b_off as usize + j] += dz[j];
                }
            }
            let dh: Vec<f64> = (0..fi).map(|k| (0..o).map(|j| dz[j] * w16[d.w_off as usize + j * fi + k]).sum::<f64>()).collect();
            if l > 0 {
                let act = config.hidden_activation;
                dz = dh.iter().zip(&acts[l]).map(|(g, &y)| h(g * act.derivative_from_output(y))).collect();
            } else {
                for k in 0..fi {
                    d_in[s * fi + k] = (dh[k] / GS) as f32;
                }
            }
        }
    }
    for (g, d) in grads.iter_mut().zip(&dsum) {
        *g += d / GS;
    }
    (out, grads.iter().map(|&g| g as f32).collect(), d_in)
}

struct Run {
    inference: Vec<f32>,
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
    net: &FusedMlpCoop,
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
    inp.resize(capacity * din, f32::NAN);
    let mut dout_v = d_output.to_vec();
    dout_v.resize(capacity * dout, f32::NAN);
    let counters = ctx.upload("counters", &[0u32, n as u32]);
    let input_b = ctx.upload("input", &inp);
    let params_b = ctx.upload("params", params);
    let out_inf = ctx.upload("out inference", &nan(capacity * dout));
    let out_fwd = ctx.upload("out forward", &nan(capacity * dout));
    let tape = ctx.upload("tape", &nan(capacity * net.tape_floats_per_sample()));
    let d_out_b = ctx.upload("d_output", &dout_v);
    let grads_b = ctx.upload("grads", grads0);
    let d_in_b = ctx.upload("d_input", &nan(capacity * din));
    let mut enc = ctx.encoder("mlp coop test");
    let args = DispatchArgs::new(ctx, capacity);
    let launch = if indirect { args.record(ctx, &mut enc, &counters, capacity) } else { Launch::direct(capacity) };
    net.record_inference(ctx, &mut enc, &counters, &input_b, &params_b, &out_inf, launch);
    net.record_forward(ctx, &mut enc, &counters, &input_b, &params_b, &out_fwd, &tape, launch);
    net.record_backward(ctx, &mut enc, &counters, &input_b, &params_b, &tape, &d_out_b, &grads_b, with_dx.then_some(&d_in_b), launch);
    ctx.queue.submit([enc.finish()]);
    let read = |b, len| ctx.read_f32(b, len).unwrap();
    let (inference, forward) = (read(&out_inf, capacity * dout), read(&out_fwd, capacity * dout));
    let d_input = read(&d_in_b, capacity * din);
    for (what, v, w) in [("inference", &inference, dout), ("forward", &forward, dout), ("d_input", &d_input, din)] {
        assert!(v[n * w..].iter().all(|x| x.is_nan()), "{what}: slots past n = {n} were written");
    }
    if !with_dx {
        assert!(d_input.iter().all(|x| x.is_nan()), "d_input written although not requested");
    }
    Run {
        inference: inference[..n * dout].to_vec(),
        forward: forward[..n * dout].to_vec(),
        grads: read(&grads_b, params.len()),
        d_input: with_dx.then(|| d_input[..n * din].to_vec()),
    }
}

/// Every config at several n (0, 1, not multiples of the tile, several weight-gradient splits; with
/// `big` (real coop ops) also 517 and 2100, and the density net at 40 000 samples: chunks of more
/// than 64 samples — the emulation on lavapipe is too slow for those), inputs past n poisoned.
fn compare_all(ctx: &GpuContext, make: impl Fn(&MlpConfig) -> Result<FusedMlpCoop, GpuError>, big: bool) {
    let mut seed = 500u64;
    for (name, config) in configs() {
        let net = make(&config).unwrap_or_else(|e| panic!("{name}: {e}"));
        let mut sizes = vec![(0usize, 5usize), (1, 0), (33, 7), (130, 30)];
        if big {
            sizes.extend([(517, 0), (2100, 300)]);
            if name.starts_with("density") {
                sizes.push((40_000, 17));
            }
        }
        for (n, extra) in sizes {
            seed += 1;
            let mut rng = nerf_core::rng(seed, 0);
            let mut cpu = Mlp::<f32>::new(config.clone(), &mut rng);
            assert_eq!(net.n_params(), cpu.n_params(), "{name}: n_params");
            let input = random(&mut rng, n * config.input_dim, 1.0);
            let d_output = random(&mut rng, n * config.output_dim, 1.0);
            let grads0 = random(&mut rng, cpu.n_params(), 1.0);
            let with_dx = n != 517 && n != 33;
            // Every other case launches from the device's count.
            let gpu = run_gpu(ctx, &net, n, n + extra, &input, cpu.params(), &grads0, &d_output, with_dx, seed.is_multiple_of(2));
            let what = format!("{name} (n = {n}, seed {seed})");
            // Inference and the training forward run the same code: bit-identical.
            assert_eq!(
                gpu.inference.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                gpu.forward.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "{what}: inference != forward"
            );
            if n == 0 {
                assert_eq!(gpu.grads, grads0, "{what}: n = 0 changed the gradients");
                continue;
            }
            // Accumulated parts (grads − prefill) so the prefill does not hide errors.
            let acc = |g: &[f32]| g.iter().zip(&grads0).map(|(a, b)| a - b).collect::<Vec<f32>>();

            // (a) The f16-emulating reference: same roundings, only the f32 accumulation order and
            // rare 1-ulp f16 rounding differences (≈5e-4 relative, propagated) differ.
            let (e_out, e_grads, e_dx) = emulate(&config, cpu.params(), &input, &d_output, &grads0, n);
            check(&format!("{what}: output vs f16 emulation"), &gpu.forward, &e_out, 2e-3);
            check(&format!("{what}: grads vs f16 emulation"), &acc(&gpu.grads), &acc(&e_grads), 5e-3);
            if let Some(d) = &gpu.d_input {
                check(&format!("{what}: d_input vs f16 emulation"), d, &e_dx, 5e-3);
            }

            // (b) The f32 CPU twin. f16 operands (2^-11 ≈ 4.9e-4 relative per rounding) summed in
            // f32 over ≤ 64 products per layer and ≤ 5 layers: 1e-2 of the largest output forward
            // (as for linear_coop); backward also rounds GRAD_SCALE·dZ at every layer.
            let mut tape = MlpTape::default();
            let out = cpu.forward(n, &input, &mut tape).to_vec();
            check(&format!("{what}: output vs CPU"), &gpu.forward, &out, 1e-2);
            cpu.grads_mut().copy_from_slice(&grads0);
            let mut d_in = vec![0.0f32; n * config.input_dim];
            cpu.backward(n, &input, &mut tape, &d_output, Some(&mut d_in));
            let smooth = config.hidden_activation != Activation::Relu || config.hidden_layers == 0;
            if smooth {
                // As linear_coop's test: 5e-2 of the largest entry.
                check(&format!("{what}: grads vs CPU"), &acc(&gpu.grads), &acc(cpu.grads()), 5e-2);
                if let Some(d) = &gpu.d_input {
                    check(&format!("{what}: d_input vs CPU"), d, &d_in, 5e-2);
                }
            } else {
                // A pre-activation within f16 rounding of 0 flips its ReLU mask relative to the CPU
                // and changes that sample's whole term: compare in L2 (a few flips cost ≪ 3 %).
                check_norm(&format!("{what}: grads vs CPU"), &acc(&gpu.grads), &acc(cpu.grads()), 3e-2);
                if let Some(d) = &gpu.d_input {
                    check_norm(&format!("{what}: d_input vs CPU"), d, &d_in, 3e-2);
                }
            }
        }
    }
}

/// The real cooperative-matrix kernels against both references (adapters with cooperative matrices).
#[test]
fn coop_fused_mlp_matches_its_references() {
    let Some(ctx) = context() else { return };
    if !ctx.features.cooperative_matrix {
        eprintln!("NOTICE: adapter {} has no cooperative matrices; FusedMlpCoop not compared", ctx.describe());
        return;
    }
    compare_all(&ctx, |c| FusedMlpCoop::new(&ctx, c), true);
}

/// Two backward passes accumulate twice the gradient of one (grads are +=, not =).
#[test]
fn coop_gradients_accumulate() {
    let Some(ctx) = context() else { return };
    if !ctx.features.cooperative_matrix {
        eprintln!("NOTICE: adapter {} has no cooperative matrices; accumulation not checked", ctx.describe());
        return;
    }
    let config = cfg(32, 64, 1, 16, Activation::Relu, Activation::None, false);
    let net = FusedMlpCoop::new(&ctx, &config).unwrap();
    let mut rng = nerf_core::rng(77, 0);
    let cpu = Mlp::<f32>::new(config.clone(), &mut rng);
    let n = 300;
    let input = random(&mut rng, n * 32, 1.0);
    let d_output = random(&mut rng, n * 16, 1.0);
    let zeros = vec![0.0f32; net.n_params()];
    let once = run_gpu(&ctx, &net, n, n, &input, cpu.params(), &zeros, &d_output, false, true).grads;
    let twice = run_gpu(&ctx, &net, n, n, &input, cpu.params(), &once, &d_output, false, false).grads;
    assert!(once.iter().any(|v| v.abs() > 1e-3), "gradients are all ~0");
    for (i, (a, b)) in once.iter().zip(&twice).enumerate() {
        assert!((2.0 * a - b).abs() <= 1e-5 * (1.0 + a.abs()), "grad {i}: once {a}, twice {b}");
    }
}

/// Adapters without cooperative matrices and configs the kernels cannot run give
/// `GpuError::Unsupported` naming the problem.
#[test]
fn unsupported_adapters_and_configs_are_rejected_with_a_clear_error() {
    let Some(ctx) = context() else { return };
    let ok = cfg(32, 64, 1, 16, Activation::Relu, Activation::None, false);
    if !ctx.features.cooperative_matrix {
        match FusedMlpCoop::new(&ctx, &ok) {
            Err(GpuError::Unsupported(m)) => assert!(m.contains("cooperative matri"), "{m:?}"),
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("FusedMlpCoop built on an adapter without cooperative matrices"),
        }
        eprintln!("NOTICE: adapter {} has no cooperative matrices; only the adapter check ran", ctx.describe());
        return;
    }
    use Activation::*;
    let mut skip = cfg(32, 64, 3, 3, Relu, None, true);
    skip.skips = vec![2];
    for (config, needle) in [
        (cfg(32, 128, 2, 3, Relu, None, false), "hidden_dim = 128"),
        (cfg(65, 64, 1, 3, Relu, None, false), "input_dim = 65"),
        (cfg(32, 64, 1, 100, Relu, None, false), "output_dim = 100"),
        (cfg(32, 64, 16, 3, Relu, None, false), "17 linear layers"),
        (skip, "skip"),
        (cfg(0, 64, 1, 3, Relu, None, false), "input_dim must be positive"),
    ] {
        match FusedMlpCoop::new(&ctx, &config) {
            Err(GpuError::Unsupported(m)) => assert!(m.contains(needle), "{m:?} should mention {needle:?}"),
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("{config:?} was accepted"),
        }
    }
    assert!(FusedMlpCoop::new(&ctx, &cfg(8, 500, 0, 4, Relu, None, true)).is_ok());
}
