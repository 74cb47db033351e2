//! Fully fused small MLPs on the GPU (tiny-cuda-nn's "fully fused MLP"), the device twin of
//! [`nerf_mlp::Mlp`]: one workgroup pushes a tile of [`TILE`] samples through every layer with the
//! activations kept in workgroup memory (`shaders/mlp_fused.wgsl` documents the kernels, the tape
//! layout and the fixed order in which the weight gradients are summed: no atomics).
//!
//! Parameters and gradients are caller-owned f32 storage buffers in exactly the CPU layout (layer by
//! layer: `W` `out × fan_in` row-major, then `b`), so [`nerf_mlp::Mlp::params`] uploads as is. The
//! number of samples of a call is read on the device from `counters[COUNTER_N_SAMPLES]` (slot 1);
//! launches cover either a host-known `capacity ≥ n` or, from a [`crate::DispatchArgs`] table,
//! exactly the tiles of n ([`Launch`]). Every `record_*` only records into the caller's
//! encoder (no submission, no read-back, no buffer creation besides its bind groups and the
//! weight-gradient workgroups' sums, made by the first backward and again only when a backward's
//! capacity asks for another number of workgroups).

use crate::dispatch::Launch;
use crate::kernel::{Bound, Kernel};
use crate::{shaders, GpuContext, GpuError};
use std::sync::Mutex;
use nerf_mlp::{Activation, MlpConfig};
pub use crate::layout::{MlpParams, MlpLayerDesc};

/// Samples per workgroup tile (the tape is tiled in blocks of this many samples).
pub const TILE: usize = 32;
/// Widest supported layer (input, hidden and output widths).
pub const MAX_WIDTH: usize = 64;
/// Samples per weight-gradient workgroup at full capacity (each workgroup stores one row of
/// `n_params` sums; H100, 2^18 samples, when these were atomic adds: 1024 was the fastest of
/// 256..4096).
const WGRAD_SAMPLES_PER_GROUP: usize = 1024;
/// Upper bound on weight-gradient workgroups per layer.
const MAX_WGRAD_GROUPS: usize = 4096;
/// Upper bound on the weight-gradient workgroups' sums (`[G][n_params]` f32; G is lowered to fit).
const MAX_PARTIAL_BYTES: u64 = 64 << 20;
/// Workgroup memory the largest kernel needs (`d_t`, `h_t` of mlp_wgrad: 2 × 32 × 68 floats).
const WORKGROUP_BYTES: u32 = 4 * (2 * 32 * 68);

/// Mode bit of [`MlpParams::mode`]: the forward stores the tape.
const MODE_TAPE: u32 = 1;
/// Mode bit of [`MlpParams::mode`]: the backward writes `d_input`.
const MODE_DX: u32 = 2;
/// Mode bit of [`MlpParams::mode`]: the forward stores the activations as rows, not the tape.
const MODE_ROWS: u32 = 4;

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

/// The shapes the fully fused kernels take (both paths): a valid config, no skips, every width ≤
/// [`MAX_WIDTH`]. `owner` starts the error message.
pub(crate) fn check_fused_shape(owner: &str, config: &MlpConfig) -> Result<(), GpuError> {
    config.validate().map_err(|e| GpuError::Unsupported(format!("{owner}: invalid config: {e}")))?;
    if !config.skips.is_empty() {
        return Err(GpuError::Unsupported(format!(
            "{owner}: skip connections ({:?}) are not supported by the fused kernels",
            config.skips
        )));
    }
    for (what, w) in [
        ("input_dim", config.input_dim),
        ("output_dim", config.output_dim),
        ("hidden_dim", if config.hidden_layers > 0 { config.hidden_dim } else { 0 }),
    ] {
        if w > MAX_WIDTH {
            return Err(GpuError::Unsupported(format!("{owner}: {what} = {w} exceeds the fused kernels' limit of {MAX_WIDTH}")));
        }
    }
    Ok(())
}

/// Panics (a caller bug) when `buf` holds fewer than `floats` f32 words.
pub(crate) fn check_buffer<'a>(owner: &str, what: &str, buf: impl Into<Bound<'a>>, floats: usize) {
    let buf: Bound<'a> = buf.into();
    assert!(
        buf.size() >= 4 * floats as u64,
        "{owner}: {what} buffer has {} bytes, needs {} (capacity × width)",
        buf.size(),
        4 * floats
    );
}

/// A small MLP (every width ≤ [`MAX_WIDTH`], any number of layers, no skips) as fused GPU kernels.
/// Built once per config; parameters, gradients and activations live in caller-owned buffers.
pub struct FusedMlp {
    config: MlpConfig,
    layers: Vec<MlpLayerDesc>,
    n_params: usize,
    fps: usize,
    layer_buf: wgpu::Buffer,
    /// Uniforms for mode 0 (inference, backward without d_input), MODE_TAPE, MODE_DX (with
    /// `dx_cols` columns) and the head inference (the first `head` outputs).
    u_plain: wgpu::Buffer,
    u_tape: wgpu::Buffer,
    u_dx: wgpu::Buffer,
    u_head: wgpu::Buffer,
    /// Uniform of the forward that stores activation rows ([`FusedMlp::record_forward_rows`]).
    u_rows: wgpu::Buffer,
    /// Outputs of [`FusedMlp::record_inference_head`] and columns of `d_input` the backward writes.
    head: usize,
    dx_cols: usize,
    /// Bound in place of the tape (inference) and of d_input (backward without it); never written.
    dummy: wgpu::Buffer,
    /// Bound as the vec4 view of a parameter buffer under 16 bytes (read-only, so not `dummy`).
    dummy4: wgpu::Buffer,
    /// Wᵀ per layer (`mlp_transpose` writes it from the parameters at the start of each backward).
    wt: wgpu::Buffer,
    transpose: Kernel,
    forward: Kernel,
    tape_gather: Kernel,
    backward: Kernel,
    wgrad: Kernel,
    wgrad_sum: Kernel,
    /// The weight-gradient workgroups' sums, `[G][n_params]` for the G of the last backward's
    /// capacity (made by the first backward, remade when a backward's capacity asks for another G).
    partials: Mutex<Option<wgpu::Buffer>>,
}

impl FusedMlp {
    /// Builds the kernels for `config` (no atomics: they run the same on every adapter).
    pub fn new(ctx: &GpuContext, config: &MlpConfig) -> Result<Self, GpuError> {
        check_fused_shape("fused MLP", config)?;
        let limit = ctx.device.limits().max_compute_workgroup_storage_size;
        if limit < WORKGROUP_BYTES {
            return Err(GpuError::Unsupported(format!(
                "fused MLP: needs {WORKGROUP_BYTES} bytes of workgroup memory, the adapter offers {limit}"
            )));
        }

        let nl = config.hidden_layers + 1;
        let widths: Vec<usize> =
            (0..nl).map(|i| if i + 1 == nl { config.output_dim } else { config.hidden_dim }).collect();
        let total: usize = widths.iter().sum();
        let mut layers = Vec::with_capacity(nl);
        let (mut off, mut prev, mut pre) = (0usize, config.input_dim, 0usize);
        for (i, &out) in widths.iter().enumerate() {
            let w_off = off;
            off += out * prev;
            let b_off = if config.bias {
                off += out;
                off - out
            } else {
                0
            };
            let act = if i + 1 == nl { config.output_activation } else { config.hidden_activation };
            layers.push(MlpLayerDesc {
                fan_in: prev as u32,
                out: out as u32,
                w_off: w_off as u32,
                b_off: b_off as u32,
                act: act_code(act),
                a_pre: pre as u32,
                d_pre: (total + pre) as u32,
                has_bias: config.bias as u32,
            });
            pre += out;
            prev = out;
        }
        let fps = 2 * total;
        let n_params = off;
        let params = |mode| Self::uniform_params(config, fps, n_params, mode, config.output_dim, config.input_dim);
        let module = ctx.shader_module("mlp_fused.wgsl", &shaders::with_common(shaders::MLP_FUSED));
        Ok(Self {
            config: config.clone(),
            n_params,
            fps,
            layer_buf: ctx.upload("mlp layers", &layers),
            layers,
            u_plain: ctx.uniform("mlp params", &params(0)),
            u_tape: ctx.uniform("mlp params (tape)", &params(MODE_TAPE)),
            u_dx: ctx.uniform("mlp params (d_input)", &params(MODE_DX)),
            u_head: ctx.uniform("mlp params (head)", &params(0)),
            u_rows: ctx.uniform("mlp params (rows)", &params(MODE_ROWS)),
            head: config.output_dim,
            dx_cols: config.input_dim,
            dummy: ctx.zeros("mlp dummy", 16),
            dummy4: ctx.zeros("mlp vec4 dummy", 16),
            wt: ctx.zeros("mlp transposed weights", (4 * off).max(16)),
            transpose: Kernel::from_module(ctx, &module, "mlp_transpose", &[]),
            forward: Kernel::from_module(ctx, &module, "mlp_forward", &[]),
            tape_gather: Kernel::from_module(ctx, &module, "mlp_tape_gather", &[]),
            backward: Kernel::from_module(ctx, &module, "mlp_backward", &[]),
            wgrad: Kernel::from_module(ctx, &module, "mlp_wgrad", &[]),
            wgrad_sum: Kernel::from_module(ctx, &module, "mlp_wgrad_sum", &[]),
            partials: Mutex::new(None),
        })
    }

    fn uniform_params(config: &MlpConfig, fps: usize, n_params: usize, mode: u32, out_rows: usize, dx_cols: usize) -> MlpParams {
        MlpParams {
            n_layers: (config.hidden_layers + 1) as u32,
            input_dim: config.input_dim as u32,
            output_dim: config.output_dim as u32,
            fps: fps as u32,
            mode,
            out_rows: out_rows as u32,
            dx_cols: dx_cols as u32,
            n_params: n_params as u32,
        }
    }

    /// Narrows the work to what the caller reads (set once, before recording):
    /// [`FusedMlp::record_inference_head`] computes and writes only the first `head` outputs (the
    /// last layer runs only the register blocks that hold them), and a backward with `d_input`
    /// only its first `d_input_cols` columns. Both are clamped to `1..=` the full width; columns
    /// and outputs past them are left as they were.
    pub fn set_partial(&mut self, ctx: &GpuContext, head: usize, d_input_cols: usize) {
        self.head = head.clamp(1, self.config.output_dim);
        self.dx_cols = d_input_cols.clamp(1, self.config.input_dim);
        let (c, fps, np) = (&self.config, self.fps, self.n_params);
        self.u_dx = ctx.uniform("mlp params (d_input)", &Self::uniform_params(c, fps, np, MODE_DX, c.output_dim, self.dx_cols));
        self.u_head = ctx.uniform("mlp params (head)", &Self::uniform_params(c, fps, np, 0, self.head, c.input_dim));
    }

    /// The outputs [`FusedMlp::record_inference_head`] writes and the `d_input` columns the
    /// backward writes ([`FusedMlp::set_partial`]; the full widths by default).
    pub fn partial(&self) -> (usize, usize) {
        (self.head, self.dx_cols)
    }

    /// The configuration.
    pub fn config(&self) -> &MlpConfig {
        &self.config
    }

    /// Number of parameters (equals [`nerf_mlp::Mlp::n_params`] for the same config).
    pub fn n_params(&self) -> usize {
        self.n_params
    }

    /// The layer table the kernels use (shapes, offsets, activation codes, tape offsets).
    pub fn layers(&self) -> &[MlpLayerDesc] {
        &self.layers
    }

    /// Floats of tape per sample: the caller allocates `capacity · tape_floats_per_sample()` floats.
    /// (Every layer's activated output and, written by the backward, its pre-activation gradient.)
    pub fn tape_floats_per_sample(&self) -> usize {
        self.fps
    }

    /// The buffer bound as the forward's vec4 view of the weights: `params` itself, or a dummy
    /// for a buffer under one vec4 (such a net has no 16-byte aligned row to read that way).
    fn params4<'a>(&'a self, params: &'a wgpu::Buffer) -> &'a wgpu::Buffer {
        if params.size() >= 16 {
            params
        } else {
            &self.dummy4
        }
    }

    fn check<'a>(&self, what: &str, buf: impl Into<Bound<'a>>, floats: usize) {
        check_buffer("FusedMlp", what, buf, floats);
    }

    fn check_common<'a>(&self, input: impl Into<Bound<'a>>, params: &wgpu::Buffer, capacity: usize) {
        self.check("input", input, capacity * self.config.input_dim);
        self.check("params", params, self.n_params);
    }

    /// Records inference: `output [n][output_dim] = mlp(input [n][input_dim])`, n = `counters[1]` ≤
    /// `launch.capacity()`. Writes only the first n rows of `output`.
    #[allow(clippy::too_many_arguments)]
    pub fn record_inference(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: &wgpu::Buffer,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        self.record_forward_with(&self.u_plain, ctx, enc, counters, input.into(), params, output, None, launch);
    }

    /// As [`FusedMlp::record_inference`] for the first `head` outputs of each row only
    /// ([`FusedMlp::set_partial`]; the others are left as they were): the density pass of a
    /// field reads σ alone.
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
        self.record_forward_with(&self.u_head, ctx, enc, counters, input.into(), params, output, None, launch);
    }

    /// `mlp_forward` with `uniform`'s mode; `tape` (written by the tape and rows modes) has been
    /// checked by the caller (`dummy` without one).
    #[allow(clippy::too_many_arguments)]
    fn record_forward_with(
        &self,
        uniform: &wgpu::Buffer,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: Bound<'_>,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        tape: Option<Bound<'_>>,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        self.check_common(input, params, capacity);
        self.check("output", output, capacity * self.config.output_dim);
        let params4 = self.params4(params);
        launch.record(
            &self.forward,
            ctx,
            enc,
            &[
                (0, uniform.into()),
                (1, (&self.layer_buf).into()),
                (2, counters.into()),
                (3, input),
                (4, params.into()),
                (5, output.into()),
                (6, tape.unwrap_or((&self.dummy).into())),
                (10, params4.into()),
            ],
            1,
            TILE as u32,
            1,
        );
    }

    /// Records the training forward: as [`FusedMlp::record_inference`] and stores what the backward
    /// needs in `tape` (at least `capacity · tape_floats_per_sample()` floats).
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
        self.check("tape", tape, launch.capacity() * self.fps);
        self.record_forward_with(&self.u_tape, ctx, enc, counters, input.into(), params, output, Some(tape.into()), launch);
    }

    /// Floats per sample of the rows [`FusedMlp::record_forward_rows`] stores: every layer's
    /// activated output, the tape's first half.
    pub fn activation_floats_per_sample(&self) -> usize {
        self.fps / 2
    }

    /// A training forward that stores each sample's activations as a row of `activations`
    /// (`[n][activation_floats_per_sample()]`, at least `capacity ·` that many floats) instead of
    /// the tiled tape, and writes every output. The density pass of a compacted step runs it over
    /// the marched samples, so the training forward of the kept ones is a gather
    /// ([`FusedMlp::record_gather_tape`]) instead of the net again.
    #[allow(clippy::too_many_arguments)]
    pub fn record_forward_rows<'a>(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: impl Into<Bound<'a>>,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        activations: impl Into<Bound<'a>>,
        launch: Launch<'_>,
    ) {
        let activations = activations.into();
        self.check("activations", activations, launch.capacity() * self.activation_floats_per_sample());
        self.record_forward_with(&self.u_rows, ctx, enc, counters, input.into(), params, output, Some(activations), launch);
    }

    /// What [`FusedMlp::record_forward`] would write to `output` and `tape` for `counters[1]`
    /// samples whose inputs are rows `rows[i]` of a batch that [`FusedMlp::record_forward_rows`]
    /// ran with the same parameters, copied from its `activations` (the same bits; the backward
    /// then runs as after a training forward, with the gathered inputs as `input`). `rows` holds
    /// at least `launch.capacity()` indices, each a row that `activations` holds.
    #[allow(clippy::too_many_arguments)]
    pub fn record_gather_tape(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        rows: &wgpu::Buffer,
        activations: &wgpu::Buffer,
        output: &wgpu::Buffer,
        tape: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        assert!(rows.size() >= 4 * capacity as u64, "FusedMlp: rows hold fewer than {capacity} entries");
        self.check("activations", activations, self.activation_floats_per_sample());
        self.check("output", output, capacity * self.config.output_dim);
        self.check("tape", tape, capacity * self.fps);
        launch.record(
            &self.tape_gather,
            ctx,
            enc,
            &[(0, &self.u_tape), (1, &self.layer_buf), (2, counters), (3, activations), (5, output), (6, tape), (14, rows)],
            1,
            64,
            1,
        );
    }

    /// Number of weight-gradient workgroups per layer for `capacity` samples: one per
    /// [`WGRAD_SAMPLES_PER_GROUP`], as many as their sums' buffer (`[G][n_params]`) allows.
    fn wgrad_groups(&self, ctx: &GpuContext, capacity: usize) -> usize {
        let row = 4 * self.n_params.max(1) as u64;
        let fit = (ctx.max_storage_bytes().min(MAX_PARTIAL_BYTES) / row).max(1) as usize;
        capacity.div_ceil(WGRAD_SAMPLES_PER_GROUP).clamp(1, MAX_WGRAD_GROUPS).min(fit)
    }

    /// Records the backward of the last [`FusedMlp::record_forward`] (same `counters`, `input`,
    /// `params`, `tape`): `d_output [n][output_dim]` is dL/d(activated output). ACCUMULATES dL/dparams
    /// into `grads` (+=, CPU layout) and writes dL/dinput `[n][input_dim]` into `d_input` when given
    /// (its first [`FusedMlp::partial`]`().1` columns; all by default). Four dispatches: Wᵀ from
    /// `params` (a few thousand floats), the fused backward (fills the tape's gradient half), the
    /// split-K weight gradients (one row of sums per workgroup) and their sum into `grads`, in a
    /// fixed order: the same inputs give the same gradient bits on every run.
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
        // Wᵀ from the current parameters (a few thousand floats), read by the backward as vec4.
        let max_w = self.layers.iter().map(|l| l.out * l.fan_in).max().unwrap_or(0);
        self.transpose.record(
            ctx,
            enc,
            &[(1, &self.layer_buf), (4, params), (11, &self.wt)],
            [max_w.div_ceil(64).max(1), self.layers.len() as u32, 1],
        );
        launch.record(
            &self.backward,
            ctx,
            enc,
            &[
                (0, uniform),
                (1, &self.layer_buf),
                (2, counters),
                (4, params),
                (6, tape),
                (7, d_output),
                (8, dx),
                (12, &self.wt),
            ],
            1,
            TILE as u32,
            1,
        );
        let groups = self.wgrad_groups(ctx, capacity);
        let mut slot = self.partials.lock().unwrap_or_else(|e| e.into_inner());
        let floats = groups * self.n_params.max(1);
        if slot.as_ref().is_none_or(|b| b.size() != 4 * floats as u64) {
            *slot = Some(ctx.zeros("mlp weight-gradient sums", 4 * floats));
        }
        let partials = slot.as_ref().expect("made above");
        self.wgrad.record(
            ctx,
            enc,
            &[(0, &self.u_plain), (1, &self.layer_buf), (2, counters), (3, input), (6, tape), (13, partials)],
            [groups as u32, self.layers.len() as u32, 1],
        );
        self.wgrad_sum.record(
            ctx,
            enc,
            &[(0, &self.u_plain), (2, counters), (9, grads), (13, partials)],
            [self.n_params.div_ceil(32).max(1) as u32, 1, 1],
        );
    }
}

/// Which implementation of the fully fused small MLPs a field runs on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FusedMlpPath {
    /// Plain WGSL ([`FusedMlp`]): every adapter.
    #[default]
    Plain,
    /// Cooperative matrices ([`crate::mlp_coop::FusedMlpCoop`], f16 in, f32 accumulate): adapters
    /// with `EXPERIMENTAL_COOPERATIVE_MATRIX` and f16 (an error elsewhere).
    Coop,
}

/// What a field needs of a fully fused MLP, whichever path runs it (the methods of
/// [`FusedMlp`] and [`crate::mlp_coop::FusedMlpCoop`], which share their semantics).
#[allow(clippy::too_many_arguments)]
pub trait FusedNet: Send + Sync {
    /// The configuration.
    fn config(&self) -> &MlpConfig;
    /// f32 words of tape per sample (the caller allocates `capacity ·` this).
    fn tape_floats_per_sample(&self) -> usize;
    /// Inference of `counters[1]` samples.
    fn record_inference(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: &wgpu::Buffer,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        launch: Launch<'_>,
    );
    /// Inference of the first [`FusedNet::partial`]`().0` outputs only (the rest of `output` is left
    /// as it was, or written too where a path has no narrower kernel). `input` may start at an
    /// offset ([`Bound`]): rows of a larger batch read in place.
    #[allow(clippy::too_many_arguments)]
    fn record_inference_head(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: Bound<'_>,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        launch: Launch<'_>,
    );
    /// Narrows the work to what the caller reads: the head inference's outputs and the backward's
    /// `d_input` columns (see [`FusedMlp::set_partial`]). A path without narrower kernels keeps
    /// computing everything (a superset), which is the default.
    fn set_partial(&mut self, _ctx: &GpuContext, _head: usize, _d_input_cols: usize) {}
    /// What [`FusedNet::set_partial`] left: (head outputs, `d_input` columns) the kernels compute.
    fn partial(&self) -> (usize, usize) {
        (self.config().output_dim, self.config().input_dim)
    }
    /// The plain-WGSL net, for what only it offers: keeping the activations of a density pass
    /// as rows and gathering the tape of the kept samples from them
    /// ([`FusedMlp::record_forward_rows`], [`FusedMlp::record_gather_tape`]). `None` on the
    /// cooperative-matrix path.
    fn as_plain(&self) -> Option<&FusedMlp> {
        None
    }
    /// Training forward (stores the tape).
    fn record_forward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: &wgpu::Buffer,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        tape: &wgpu::Buffer,
        launch: Launch<'_>,
    );
    /// Backward of the last training forward: gradients accumulated, `d_input` written.
    fn record_backward(
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
    );
}

macro_rules! impl_fused_net {
    (@common $t:ty) => {
        fn config(&self) -> &MlpConfig {
            <$t>::config(self)
        }
        fn tape_floats_per_sample(&self) -> usize {
            <$t>::tape_floats_per_sample(self)
        }
        fn record_inference(
            &self,
            ctx: &GpuContext,
            enc: &mut wgpu::CommandEncoder,
            counters: &wgpu::Buffer,
            input: &wgpu::Buffer,
            params: &wgpu::Buffer,
            output: &wgpu::Buffer,
            launch: Launch<'_>,
        ) {
            <$t>::record_inference(self, ctx, enc, counters, input, params, output, launch)
        }
        fn record_inference_head(
            &self,
            ctx: &GpuContext,
            enc: &mut wgpu::CommandEncoder,
            counters: &wgpu::Buffer,
            input: Bound<'_>,
            params: &wgpu::Buffer,
            output: &wgpu::Buffer,
            launch: Launch<'_>,
        ) {
            <$t>::record_inference_head(self, ctx, enc, counters, input, params, output, launch)
        }
        fn record_forward(
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
            <$t>::record_forward(self, ctx, enc, counters, input, params, output, tape, launch)
        }
        fn record_backward(
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
            <$t>::record_backward(self, ctx, enc, counters, input, params, tape, d_output, grads, d_input, launch)
        }
    };
    ($t:ty) => {
        impl FusedNet for $t {
            impl_fused_net!(@common $t);
        }
    };
    // The plain net: partial heads and input gradients, activation rows.
    ($t:ty, plain) => {
        impl FusedNet for $t {
            impl_fused_net!(@common $t);
            fn set_partial(&mut self, ctx: &GpuContext, head: usize, d_input_cols: usize) {
                <$t>::set_partial(self, ctx, head, d_input_cols)
            }
            fn partial(&self) -> (usize, usize) {
                <$t>::partial(self)
            }
            fn as_plain(&self) -> Option<&FusedMlp> {
                Some(self)
            }
        }
    };
}

impl_fused_net!(FusedMlp, plain);
impl_fused_net!(crate::mlp_coop::FusedMlpCoop);

/// A fully fused MLP for `config` on `path` (a clear [`GpuError::Unsupported`] where the adapter
/// or the config does not allow it).
pub fn fused_net(ctx: &GpuContext, config: &MlpConfig, path: FusedMlpPath) -> Result<Box<dyn FusedNet>, GpuError> {
    Ok(fused_nets(ctx, std::slice::from_ref(config), path)?.remove(0))
}

/// Fully fused MLPs for several configs on `path`; the cooperative-matrix nets share one shader
/// compilation ([`crate::mlp_coop::FusedMlpCoop::with_config`]).
pub fn fused_nets(ctx: &GpuContext, configs: &[MlpConfig], path: FusedMlpPath) -> Result<Vec<Box<dyn FusedNet>>, GpuError> {
    let mut nets: Vec<Box<dyn FusedNet>> = Vec::with_capacity(configs.len());
    match path {
        FusedMlpPath::Plain => {
            for c in configs {
                nets.push(Box::new(FusedMlp::new(ctx, c)?));
            }
        }
        FusedMlpPath::Coop => {
            let Some((first, rest)) = configs.split_first() else { return Ok(nets) };
            let base = crate::mlp_coop::FusedMlpCoop::new(ctx, first)?;
            for c in rest {
                nets.push(Box::new(base.with_config(ctx, c)?));
            }
            nets.insert(0, Box::new(base));
        }
    }
    Ok(nets)
}
