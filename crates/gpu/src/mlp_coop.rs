//! Fully fused small MLPs on cooperative matrices (tensor cores): the same networks, buffers and
//! API as the plain-WGSL [`crate::mlp::FusedMlp`], with every layer's product done on 16×16×16
//! f16 cooperative matrices with f32 accumulation (`shaders/mlp_fused_coop.wgsl` documents the
//! kernels and layouts). Needs an adapter with `EXPERIMENTAL_COOPERATIVE_MATRIX` and `SHADER_F16`
//! ([`crate::GpuFeatures::cooperative_matrix`]); elsewhere [`FusedMlpCoop::new`] returns
//! [`GpuError::Unsupported`] and callers use [`crate::mlp::FusedMlp`].
//!
//! Buffers (caller-owned, as for [`crate::mlp::FusedMlp`]):
//! - `input` `[capacity][input_dim]`, `output` / `d_output` `[capacity][output_dim]`, `d_input`
//!   `[capacity][input_dim]` — f32, row-major; `n = counters[COUNTER_N_SAMPLES]` (slot 1) rows are
//!   used and nothing past row `n` is written;
//! - `params` / `grads` `[n_params()]` f32 in the CPU layout of [`nerf_mlp::Mlp`] (layer by layer,
//!   `W` `out × fan_in` row-major then `b`); the backward ACCUMULATES into `grads`;
//! - `tape` `[capacity · tape_floats_per_sample()]` f32 words, used as f16 pairs: per sample every
//!   layer's activated output and scaled pre-activation gradient, each padded to a multiple of 16.
//!
//! Owned scratch (sized in [`FusedMlpCoop::new`], independent of the sample count): the f16 copy of
//! the weights, rewritten by a small kernel at the start of every `record_*` call, and the split-K
//! partial sums of the weight gradients (`splits()` × Σ padded `dW` sizes floats, ≤ 8 MiB).
//!
//! Precision: activations, weights and gradients are rounded to f16 (11-bit mantissa) before each
//! product; gradients are scaled by 128 before the rounding (so small ones are not flushed) and
//! unscaled in f32. Expect ~1e-3 relative agreement with the f32 CPU twin, not bit equality.

use crate::dispatch::Launch;
use crate::kernel::{groups_1d, Bound, Kernel};
use crate::{shaders, GpuContext, GpuError};
use nerf_mlp::{Activation, MlpConfig};
use std::sync::Arc;

/// Samples per workgroup tile of the forward and backward kernels.
pub const TILE: usize = 32;
/// Widest supported layer (input, hidden and output widths).
pub use crate::mlp::MAX_WIDTH;
/// Most linear layers (`hidden_layers + 1`) the uniform's layer table holds.
pub const MAX_LAYERS: usize = 16;
/// Most sample splits of the weight-gradient reduction.
const MAX_SPLITS: usize = 256;
/// Fewest samples per split (`MIN_CHUNK` in the shader).
const MIN_CHUNK: usize = 64;
/// Budget of the partial-sum buffer in floats (8 MiB); fewer splits for larger networks.
const PARTIAL_FLOATS: usize = 1 << 21;
/// Workgroup memory of the largest kernel: `tile` (32 × 72 f16) + `stg` (32 × 68 f32) + `wg_n`.
const WORKGROUP_BYTES: u32 = 2 * 32 * 72 + 4 * 32 * 68 + 4;
/// Workgroup size of the 1-D kernels (convert_weights, reduce_grads).
const WG: u32 = 256;

/// Mode bit of [`CoopMlpParams::mode`]: the forward stores the tape.
const MODE_TAPE: u32 = 1;
/// Mode bit of [`CoopMlpParams::mode`]: the backward writes `d_input`.
const MODE_DX: u32 = 2;

fn act_code(a: Activation) -> u32 {
    match a {
        Activation::None => 0,
        Activation::Relu => 1,
        Activation::Sigmoid => 2,
        Activation::Tanh => 3,
        Activation::Softplus => 4,
        Activation::Exp => 5,
    }
}

fn r16(x: usize) -> usize {
    x.next_multiple_of(16)
}

/// One linear layer in the uniform (`struct Layer` of `mlp_fused_coop.wgsl`; 64 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct CoopLayerDesc {
    /// Inputs of the layer.
    pub fan_in: u32,
    /// Outputs of the layer.
    pub out: u32,
    /// `fan_in` rounded up to 16.
    pub kp: u32,
    /// `out` rounded up to 16.
    pub np: u32,
    /// Offset of `W` in the parameter buffer.
    pub w_off: u32,
    /// Offset of `b` in the parameter buffer (0 without a bias).
    pub b_off: u32,
    /// 1 when the layer has a bias.
    pub has_bias: u32,
    /// Activation code (0 none, 1 relu, 2 sigmoid, 3 tanh, 4 softplus, 5 exp).
    pub act: u32,
    /// Offset of the layer's `[np][kp]` f16 weights in the f16 weight copy.
    pub w16_off: u32,
    /// Tape column (f16 units) of the activated output `A_l`.
    pub a_off: u32,
    /// Tape column (f16 units) of the scaled pre-activation gradient `D_l`.
    pub d_off: u32,
    /// Tape column of the layer's input `A_{l−1}` (0 for layer 0, whose input is `input`).
    pub h_off: u32,
    /// Padded columns of the weight-gradient product (`kp`, + 16 for the bias column of ones).
    pub kcp: u32,
    /// Offset of the layer's `[np][kcp]` block in one split of the partial sums.
    pub p_off: u32,
    /// Weight-gradient workgroups per 32-row block of `dW` (`kcp / 32` rounded up).
    pub nbc: u32,
    /// Weight-gradient workgroups of the layer (`np / 32` rounded up × `nbc`).
    pub nblk: u32,
}

/// The uniform `Params` of `mlp_fused_coop.wgsl` (static per network and mode; 1072 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct CoopMlpParams {
    /// Linear layers.
    pub n_layers: u32,
    /// Network input width.
    pub input_dim: u32,
    /// Network output width.
    pub output_dim: u32,
    /// `input_dim` rounded up to 16.
    pub xp: u32,
    /// Tape f16 values per sample (`2 · tape_floats_per_sample`).
    pub s16: u32,
    /// Bit 0: the forward stores the tape; bit 1: the backward writes `d_input`.
    pub mode: u32,
    /// Sample splits of the weight-gradient reduction.
    pub splits: u32,
    /// Floats of one split of the partial sums.
    pub ps: u32,
    /// Parameters of the network.
    pub n_params: u32,
    /// Elements of the f16 weight copy.
    pub w16_total: u32,
    /// Always 0 (the kernels' "runtime zero", see the shader).
    pub zero: u32,
    /// Padding.
    pub _pad: u32,
    /// The layers (first `n_layers` used).
    pub layers: [CoopLayerDesc; MAX_LAYERS],
}

/// The source of the cooperative-matrix fused-MLP kernels as compiled (with `common.wgsl`).
pub fn source() -> String {
    shaders::with_common(shaders::MLP_FUSED_COOP)
}

/// A small MLP (every width ≤ [`MAX_WIDTH`], at most [`MAX_LAYERS`] layers, no skips) as fused
/// kernels on cooperative matrices. Built once per config; parameters, gradients, activations and
/// the tape live in caller-owned buffers, the f16 weights and partial sums in the struct.
pub struct FusedMlpCoop {
    config: MlpConfig,
    layers: Vec<CoopLayerDesc>,
    n_params: usize,
    fps: usize,
    splits: usize,
    w16_total: usize,
    /// Weight-gradient workgroups of the layer with the most (the wgrad launch's x extent).
    max_blocks: usize,
    /// Uniforms for mode 0 (inference, backward without d_input), MODE_TAPE, MODE_DX.
    u_plain: wgpu::Buffer,
    u_tape: wgpu::Buffer,
    u_dx: wgpu::Buffer,
    /// Bound in place of the tape (inference) and of d_input (backward without it); never written.
    dummy: wgpu::Buffer,
    w16: wgpu::Buffer,
    partial: wgpu::Buffer,
    kernels: Arc<Kernels>,
}

/// The compiled entry points (independent of the config, which lives in the uniforms: shared by
/// every network made with [`FusedMlpCoop::with_config`]).
struct Kernels {
    convert: Kernel,
    forward: Kernel,
    backward: Kernel,
    wgrad: Kernel,
    reduce: Kernel,
}

impl FusedMlpCoop {
    /// Builds the kernels and scratch for `config`. [`GpuError::Unsupported`] when the adapter
    /// lacks cooperative matrices or f16, or the config is invalid, has skips, a width over
    /// [`MAX_WIDTH`] or more than [`MAX_LAYERS`] layers.
    pub fn new(ctx: &GpuContext, config: &MlpConfig) -> Result<Self, GpuError> {
        if !(ctx.features.cooperative_matrix && ctx.features.shader_f16) {
            return Err(GpuError::Unsupported(format!(
                "cooperative-matrix fused MLP: the adapter {} lacks cooperative matrices \
                 (EXPERIMENTAL_COOPERATIVE_MATRIX) or SHADER_F16; use nerf_gpu::mlp::FusedMlp",
                ctx.describe()
            )));
        }
        Self::with_source(ctx, config, &source())
    }

    /// For tests: as [`FusedMlpCoop::new`] from a given WGSL source (with the same entry points and
    /// bindings) and without the cooperative-matrix feature check. The tests pass a copy of
    /// [`source`] whose coop ops are rewritten as plain-WGSL emulations, so the kernels' indexing,
    /// layouts and host side also run (slowly) on adapters without cooperative matrices.
    #[doc(hidden)]
    pub fn with_source(ctx: &GpuContext, config: &MlpConfig, source: &str) -> Result<Self, GpuError> {
        Self::check_config(ctx, config)?;
        let module = ctx.shader_module("mlp_fused_coop.wgsl", source);
        let k = |e: &str| Kernel::from_module(ctx, &module, e, &[]);
        let kernels = Kernels {
            convert: k("convert_weights"),
            forward: k("forward"),
            backward: k("backward"),
            wgrad: k("wgrad"),
            reduce: k("reduce_grads"),
        };
        Ok(Self::assemble(ctx, config, Arc::new(kernels)))
    }

    /// Another network on the same compiled kernels (no shader compilation: the hash field's
    /// density and colour nets can share them), with its own uniforms and scratch. Errors as
    /// [`FusedMlpCoop::new`] for configs the kernels cannot run.
    pub fn with_config(&self, ctx: &GpuContext, config: &MlpConfig) -> Result<Self, GpuError> {
        Self::check_config(ctx, config)?;
        Ok(Self::assemble(ctx, config, self.kernels.clone()))
    }

    fn check_config(ctx: &GpuContext, config: &MlpConfig) -> Result<(), GpuError> {
        crate::mlp::check_fused_shape("cooperative-matrix fused MLP", config)?;
        let nl = config.hidden_layers + 1;
        if nl > MAX_LAYERS {
            return Err(GpuError::Unsupported(format!(
                "cooperative-matrix fused MLP: {nl} linear layers exceed the limit of {MAX_LAYERS}"
            )));
        }
        let limit = ctx.device.limits().max_compute_workgroup_storage_size;
        if limit < WORKGROUP_BYTES {
            return Err(GpuError::Unsupported(format!(
                "cooperative-matrix fused MLP: needs {WORKGROUP_BYTES} bytes of workgroup memory, the adapter offers {limit}"
            )));
        }
        Ok(())
    }

    fn assemble(ctx: &GpuContext, config: &MlpConfig, kernels: Arc<Kernels>) -> Self {
        let (params, layers) = Self::plan(config);
        let mut u = params;
        let uniform = |label: &str, mode: u32, u: &mut CoopMlpParams| {
            u.mode = mode;
            ctx.uniform(label, &*u)
        };
        let splits = params.splits as usize;
        let w16_total = params.w16_total as usize;
        Self {
            config: config.clone(),
            max_blocks: layers.iter().map(|l| l.nblk as usize).max().unwrap_or(1),
            layers,
            n_params: params.n_params as usize,
            fps: params.s16 as usize / 2,
            splits,
            w16_total,
            u_plain: uniform("mlp coop params", 0, &mut u),
            u_tape: uniform("mlp coop params (tape)", MODE_TAPE, &mut u),
            u_dx: uniform("mlp coop params (d_input)", MODE_DX, &mut u),
            dummy: ctx.zeros("mlp coop dummy", 16),
            w16: ctx.zeros("mlp coop w16", 2 * w16_total),
            partial: ctx.zeros("mlp coop dW partial", 4 * splits * params.ps as usize),
            kernels,
        }
    }

    /// The uniform (mode 0) and layer table for a validated config (host only, no device).
    pub fn plan(config: &MlpConfig) -> (CoopMlpParams, Vec<CoopLayerDesc>) {
        let nl = config.hidden_layers + 1;
        let mut layers = Vec::with_capacity(nl);
        let (mut off, mut prev, mut w16_off, mut col, mut p_off) = (0usize, config.input_dim, 0usize, 0usize, 0usize);
        for i in 0..nl {
            let last = i + 1 == nl;
            let out = if last { config.output_dim } else { config.hidden_dim };
            let (kp, np) = (r16(prev), r16(out));
            let w_off = off;
            off += out * prev;
            let b_off = if config.bias {
                off += out;
                off - out
            } else {
                0
            };
            let kcp = kp + if config.bias { 16 } else { 0 };
            let nbc = kcp.div_ceil(32);
            let h_off = layers.last().map_or(0, |p: &CoopLayerDesc| p.a_off);
            layers.push(CoopLayerDesc {
                fan_in: prev as u32,
                out: out as u32,
                kp: kp as u32,
                np: np as u32,
                w_off: w_off as u32,
                b_off: b_off as u32,
                has_bias: config.bias as u32,
                act: act_code(if last { config.output_activation } else { config.hidden_activation }),
                w16_off: w16_off as u32,
                a_off: col as u32,
                d_off: (col + np) as u32,
                h_off,
                kcp: kcp as u32,
                p_off: p_off as u32,
                nbc: nbc as u32,
                nblk: (np.div_ceil(32) * nbc) as u32,
            });
            w16_off += np * kp;
            col += 2 * np;
            p_off += np * kcp;
            prev = out;
        }
        let splits = (PARTIAL_FLOATS / p_off.max(1)).clamp(1, MAX_SPLITS);
        let mut table = [CoopLayerDesc::default(); MAX_LAYERS];
        table[..nl].copy_from_slice(&layers);
        let params = CoopMlpParams {
            n_layers: nl as u32,
            input_dim: config.input_dim as u32,
            output_dim: config.output_dim as u32,
            xp: r16(config.input_dim) as u32,
            s16: col as u32,
            mode: 0,
            splits: splits as u32,
            ps: p_off as u32,
            n_params: off as u32,
            w16_total: w16_off as u32,
            zero: 0,
            _pad: 0,
            layers: table,
        };
        (params, layers)
    }

    /// The configuration.
    pub fn config(&self) -> &MlpConfig {
        &self.config
    }

    /// Number of parameters (equals [`nerf_mlp::Mlp::n_params`] for the same config).
    pub fn n_params(&self) -> usize {
        self.n_params
    }

    /// The layer table the kernels use (shapes, offsets, tape columns, weight-gradient blocks).
    pub fn layers(&self) -> &[CoopLayerDesc] {
        &self.layers
    }

    /// Sample splits of the weight-gradient reduction (partial sums hold this many copies of `dW`).
    pub fn splits(&self) -> usize {
        self.splits
    }

    /// Floats (f32 words) of tape per sample: the caller allocates `capacity · tape_floats_per_sample()`
    /// floats. The tape holds f16 values: every layer's activated output and its scaled
    /// pre-activation gradient, each padded to a multiple of 16 (so `Σ 16·⌈w/16⌉` words).
    pub fn tape_floats_per_sample(&self) -> usize {
        self.fps
    }

    fn check<'a>(&self, what: &str, buf: impl Into<Bound<'a>>, floats: usize) {
        crate::mlp::check_buffer("FusedMlpCoop", what, buf, floats);
    }

    fn check_common<'a>(&self, input: impl Into<Bound<'a>>, params: &wgpu::Buffer, capacity: usize) {
        self.check("input", input, capacity * self.config.input_dim);
        self.check("params", params, self.n_params);
    }

    /// Splits worth launching for `capacity`: a split holds at least `MIN_CHUNK` = 64 samples (see
    /// `split_chunk` in the shader), so with n ≤ capacity no split past `capacity / 64` has work.
    fn launched_splits(&self, capacity: usize) -> usize {
        capacity.div_ceil(MIN_CHUNK).clamp(1, self.splits)
    }

    fn record_convert(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, params: &wgpu::Buffer) {
        self.kernels.convert
            .record(ctx, enc, &[(0, &self.u_plain), (2, params), (3, &self.w16)], groups_1d(self.w16_total, WG));
    }

    /// Records inference: `output [n][output_dim] = mlp(input [n][input_dim])`, n = `counters[1]` ≤
    /// `launch.capacity()`. Writes only the first n rows of `output`. (Two dispatches: the f16 weight copy,
    /// then the fused forward.)
    #[allow(clippy::too_many_arguments)]
    pub fn record_inference<'a>(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: impl Into<Bound<'a>>,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        let input: Bound<'a> = input.into();
        self.check_common(input, params, capacity);
        self.check("output", output, capacity * self.config.output_dim);
        self.record_convert(ctx, enc, params);
        launch.record(
            &self.kernels.forward,
            ctx,
            enc,
            &[
                (0, (&self.u_plain).into()),
                (1, counters.into()),
                (2, input),
                (3, params.into()),
                (4, (&self.w16).into()),
                (5, output.into()),
                (6, (&self.dummy).into()),
            ],
            1,
            TILE as u32,
            1,
        );
    }

    /// [`FusedMlpCoop::record_inference`]: this path has no narrower kernel for a partial head,
    /// so every output is written ([`crate::mlp::FusedNet::record_inference_head`]).
    #[allow(clippy::too_many_arguments)]
    pub fn record_inference_head<'a>(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: impl Into<Bound<'a>>,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        self.record_inference(ctx, enc, counters, input, params, output, launch)
    }

    /// Records the training forward: as [`FusedMlpCoop::record_inference`] and stores what the
    /// backward needs in `tape` (at least `capacity · tape_floats_per_sample()` floats).
    #[allow(clippy::too_many_arguments)]
    pub fn record_forward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: &wgpu::Buffer,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        tape: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        self.check_common(input, params, capacity);
        self.check("output", output, capacity * self.config.output_dim);
        self.check("tape", tape, capacity * self.fps);
        self.record_convert(ctx, enc, params);
        launch.record(
            &self.kernels.forward,
            ctx,
            enc,
            &[
                (0, &self.u_tape),
                (1, counters),
                (2, input),
                (3, params),
                (4, &self.w16),
                (5, output),
                (6, tape),
            ],
            1,
            TILE as u32,
            1,
        );
    }

    /// Records the backward of the last [`FusedMlpCoop::record_forward`] (same `counters`, `input`,
    /// `params`, `tape`): `d_output [n][output_dim]` is dL/d(activated output). ACCUMULATES
    /// dL/dparams into `grads` (+=, CPU layout) and writes (overwrites) dL/dinput `[n][input_dim]`
    /// into `d_input` when given. Four dispatches: the f16 weight copy, the fused backward (fills
    /// the tape's gradient half), the split-K weight gradients of every layer, their reduction.
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: &wgpu::Buffer,
        params: &wgpu::Buffer,
        tape: &wgpu::Buffer,
        d_output: &wgpu::Buffer,
        grads: &wgpu::Buffer,
        d_input: Option<&wgpu::Buffer>,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        self.check_common(input, params, capacity);
        self.check("tape", tape, capacity * self.fps);
        self.check("d_output", d_output, capacity * self.config.output_dim);
        self.check("grads", grads, self.n_params);
        if let Some(d) = d_input {
            self.check("d_input", d, capacity * self.config.input_dim);
        }
        let (uniform, dx) = match d_input {
            Some(d) => (&self.u_dx, d),
            None => (&self.u_plain, &self.dummy),
        };
        self.record_convert(ctx, enc, params);
        launch.record(
            &self.kernels.backward,
            ctx,
            enc,
            &[(0, uniform), (1, counters), (2, d_output), (4, &self.w16), (6, tape), (7, dx)],
            1,
            TILE as u32,
            1,
        );
        self.kernels.wgrad.record(
            ctx,
            enc,
            &[(0, &self.u_plain), (1, counters), (2, input), (6, tape), (8, &self.partial)],
            [self.max_blocks as u32, self.launched_splits(capacity) as u32, self.layers.len() as u32],
        );
        self.kernels.reduce.record(
            ctx,
            enc,
            &[(0, &self.u_plain), (1, counters), (8, &self.partial), (9, grads)],
            groups_1d(self.n_params, WG),
        );
    }
}
