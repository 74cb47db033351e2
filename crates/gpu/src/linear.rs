//! Wide MLPs on the GPU (the NeRF paper's 8×256 trunk and any other [`MlpConfig`]), layer by layer.
//!
//! [`GpuMlp`] is the device twin of [`nerf_mlp::Mlp`]: the same parameter layout (layer by layer,
//! `W` `out × fan_in` row-major then `b`), the same skip semantics (layer `i ∈ skips` reads
//! `[input, h_{i−1}]`; `W`'s first `input_dim` columns multiply the input) and the same activations.
//! Two implementations of every product:
//! - plain WGSL (`shaders/linear.wgsl`): 64×64 output tiles through workgroup memory, 16-deep K
//!   steps, 4×4 outputs per invocation, bias + activation (forward) and `act'` (backward) fused
//!   into the epilogues; `dW += dZᵀ·X` split over the samples into a partial buffer reduced by a
//!   second kernel (deterministic, no atomics); the skip concatenation is read from two sources.
//! - cooperative matrices (`shaders/linear_coop.wgsl`, tensor cores): 16×16×16 f16 products with
//!   f32 accumulation, on f16 copies of the activations and weights padded to multiples of 16
//!   (owned by the [`GpuMlp`]); the f32 tape and outputs keep the same layout as the plain path.
//!   Two tilings of its products ([`CoopTiling`]): one subgroup per workgroup owning a 32×32
//!   block with every operand tile loaded from global memory ([`LinearPath::Coop`], the path
//!   verified on an H100), or four subgroups sharing a 64×64 block with each 32-deep K chunk of
//!   both operands staged once in workgroup memory by coalesced loads ([`LinearPath::CoopTiled`]).
//!
//! Buffers (all `f32`, row-major, caller-owned unless noted):
//! - `input` `[capacity][input_dim]`, `output` `[capacity][output_dim]`, `d_output` like `output`,
//!   `d_input` like `input`;
//! - `params` / `grads` `[n_params()]` in the CPU layout; backward ACCUMULATES into `grads`;
//! - `tape` `[capacity][tape_floats_per_sample()]`: per sample, the post-activations of every layer
//!   (hidden layers, then the output) side by side; after [`GpuMlp::drop_hidden_tape`] the
//!   training forward writes only the output block;
//! - `counters` (`array<u32>`): slot [`crate::layout::COUNTER_N_SAMPLES`] holds `n`, the number of
//!   samples of the step (`n ≤ capacity`).

use crate::kernel::{groups_1d, Kernel};
use crate::{shaders, GpuContext, GpuError};
use nerf_mlp::{Activation, MlpConfig};
pub use crate::layout::{LinearParams};

const FLAG_WORK: u32 = 1;
const FLAG_OUT: u32 = 2;
const FLAG_BIAS: u32 = 4;
const FLAG_DINPUT: u32 = 8;
/// Output tile edge of the plain kernels.
const TILE: usize = 64;
/// Workgroup size of the 1-D kernels.
const WG: u32 = 256;

/// The WGSL code of an activation (`act_apply` / `act_grad` in the shaders).
pub fn act_code(a: Activation) -> u32 {
    match a {
        Activation::None => 0,
        Activation::Relu => 1,
        Activation::Sigmoid => 2,
        Activation::Tanh => 3,
        Activation::Softplus => 4,
        Activation::Exp => 5,
    }
}

/// Which implementation of the products a [`GpuMlp`] runs (chosen in [`GpuMlp::new_with`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum LinearPath {
    /// Plain WGSL, f32 throughout (`shaders/linear.wgsl`); runs on every adapter.
    #[default]
    Plain,
    /// Cooperative matrices, one subgroup of 32 per workgroup owning a 32×32 output block,
    /// operand tiles loaded straight from global memory ([`CoopTiling::Subgroup`]).
    Coop,
    /// Cooperative matrices, four subgroups of 32 per workgroup sharing a 64×64 output block,
    /// K staged through workgroup memory ([`CoopTiling::Workgroup`]). Needs a subgroup size of
    /// exactly 32 (NVIDIA); the f16 scratch gets 64-row padding.
    CoopTiled,
    /// As [`LinearPath::CoopTiled`], with 128×128 output blocks (4×4 accumulators per subgroup)
    /// for the products whose block width is a multiple of 128 ([`CoopTiling::WorkgroupWide`]).
    /// Needs 32-wide subgroups and 28 676 bytes of workgroup memory; 128-row padding.
    CoopTiledWide,
}

impl LinearPath {
    /// The cooperative-matrix tiling of this path (`None` for [`LinearPath::Plain`]).
    pub fn coop_tiling(self) -> Option<CoopTiling> {
        match self {
            LinearPath::Plain => None,
            LinearPath::Coop => Some(CoopTiling::Subgroup),
            LinearPath::CoopTiled => Some(CoopTiling::Workgroup),
            LinearPath::CoopTiledWide => Some(CoopTiling::WorkgroupWide),
        }
    }
}

/// How the cooperative-matrix GEMMs (`forward`, `backward_data`, `backward_weight` of
/// `shaders/linear_coop.wgsl`) split their work; the results agree up to f32 summation order.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum CoopTiling {
    /// One subgroup (32 lanes) per workgroup, a 32×32 block of C (2×2 accumulators); every 16×16
    /// f16 operand tile is loaded from global memory by the subgroup that uses it.
    #[default]
    Subgroup,
    /// The `*_tiled` entry points: 4 subgroups per workgroup (128 lanes), a 64×64 block of C;
    /// each K chunk of 32 is copied once into workgroup memory (8-byte coalesced loads, the next
    /// chunk prefetched into registers) and the subgroups load their tiles from there. 14 340
    /// bytes of workgroup memory per entry point.
    Workgroup,
    /// The `*_wide` entry points where a product's block width is a whole number of 128s (the
    /// 8×256 trunk's hidden layers), the `*_tiled` ones elsewhere: 4 subgroups per workgroup, a
    /// 128×128 block of C, each subgroup a 64×64 quarter as 4×4 accumulators (4 + 4 tile loads
    /// from workgroup memory per 16 products, against 2 + 2 per 4), K chunks of 32 staged as in
    /// [`CoopTiling::Workgroup`]. 28 676 bytes of workgroup memory.
    WorkgroupWide,
}

/// Workgroup memory of the `*_wide` entry points (ua, ub, Cw, wg_n of `linear_coop.wgsl`).
const WIDE_WORKGROUP_BYTES: u32 = 2 * 5120 * 2 + 2048 * 4 + 4;

impl CoopTiling {
    /// Rows of an output block, and the row padding of the f16 scratch.
    fn rows(self) -> usize {
        match self {
            CoopTiling::Subgroup => 32,
            CoopTiling::Workgroup => 64,
            CoopTiling::WorkgroupWide => 128,
        }
    }
}

/// One linear layer's shape and parameter offsets (the CPU twin's layout).
#[derive(Clone, Debug)]
struct LayerInfo {
    fan_in: usize,
    out: usize,
    /// Leading input columns from the network input (`input_dim` for layer 0 and skip layers).
    ka: usize,
    w_off: usize,
    b_off: Option<usize>,
    act: Activation,
    /// Column offset of this layer's output in a tape row.
    tape_off: usize,
}

/// Per-layer uniforms of the plain path.
struct PlainLayer {
    fwd: wgpu::Buffer,
    inf: wgpu::Buffer,
    /// Backward uniforms `[without d_input, with d_input]`.
    bwd: [wgpu::Buffer; 2],
}

/// Plain-path kernels and scratch.
struct Plain {
    forward: Kernel,
    backward_data: Kernel,
    backward_weight: Kernel,
    reduce: Kernel,
    output_grad: Kernel,
    layers: Vec<PlainLayer>,
    out_grad_u: wgpu::Buffer,
    /// Inference ping-pong `[capacity][2·hidden]`.
    scratch: wgpu::Buffer,
    dz: [wgpu::Buffer; 2],
    partial: wgpu::Buffer,
}

/// A multilayer perceptron on the GPU: kernels compiled and scratch sized for `capacity` samples
/// once in [`GpuMlp::new`]; `record_*` only record into the caller's encoder.
pub struct GpuMlp {
    config: MlpConfig,
    layers: Vec<LayerInfo>,
    n_params: usize,
    capacity: usize,
    tape_stride: usize,
    n_splits: usize,
    chunk: usize,
    plain: Option<Plain>,
    coop: Option<coop::Coop>,
    dummy: wgpu::Buffer,
}

/// Rows per split of the weight-gradient product for a capacity (≥ 64 splits on large batches).
fn split_chunk(capacity: usize) -> usize {
    (capacity.div_ceil(64)).next_multiple_of(16).max(256)
}

impl GpuMlp {
    /// Builds the kernels for `config` and scratch for up to `capacity` samples per call.
    /// `use_coop` selects the cooperative-matrix path ([`LinearPath::Coop`]; needs
    /// `ctx.features.cooperative_matrix` and `shader_f16`; an error otherwise), else
    /// [`LinearPath::Plain`].
    pub fn new(ctx: &GpuContext, config: &MlpConfig, capacity: usize, use_coop: bool) -> Result<Self, GpuError> {
        Self::new_with(ctx, config, capacity, if use_coop { LinearPath::Coop } else { LinearPath::Plain })
    }

    /// As [`GpuMlp::new`] with the implementation chosen by `path`. The cooperative-matrix paths
    /// need `ctx.features.cooperative_matrix` and `shader_f16`, and [`LinearPath::CoopTiled`] a
    /// subgroup size of exactly 32 (its kernels take `local_invocation_index / 32` as the
    /// subgroup); an [`GpuError::Unsupported`] otherwise.
    pub fn new_with(ctx: &GpuContext, config: &MlpConfig, capacity: usize, path: LinearPath) -> Result<Self, GpuError> {
        let Some(tiling) = path.coop_tiling() else {
            return Self::build(ctx, config, capacity, None);
        };
        if !(ctx.features.cooperative_matrix && ctx.features.shader_f16) {
            return Err(GpuError::Unsupported(format!(
                "cooperative-matrix MLP asked for, but the adapter {} lacks cooperative matrices or f16",
                ctx.describe()
            )));
        }
        if tiling != CoopTiling::Subgroup && !(ctx.info.subgroup_min_size == 32 && ctx.info.subgroup_max_size == 32) {
            return Err(GpuError::Unsupported(format!(
                "workgroup-tiled cooperative-matrix MLP needs a subgroup size of 32, but the adapter {} has {}..={}",
                ctx.describe(),
                ctx.info.subgroup_min_size,
                ctx.info.subgroup_max_size
            )));
        }
        let limit = ctx.device.limits().max_compute_workgroup_storage_size;
        if tiling == CoopTiling::WorkgroupWide && limit < WIDE_WORKGROUP_BYTES {
            return Err(GpuError::Unsupported(format!(
                "wide cooperative-matrix MLP needs {WIDE_WORKGROUP_BYTES} bytes of workgroup memory, the adapter {} offers {limit}",
                ctx.describe()
            )));
        }
        let src = shaders::with_common(shaders::LINEAR_COOP);
        Self::build(ctx, config, capacity, Some((&src, tiling)))
    }

    /// For tests: the cooperative-matrix path with `tiling`, compiled from `source` (a copy of
    /// `linear_coop.wgsl` with the same entry points and bindings, e.g. with its cooperative-matrix
    /// operations emulated in plain WGSL) and without the feature checks.
    #[doc(hidden)]
    pub fn with_coop_source(ctx: &GpuContext, config: &MlpConfig, capacity: usize, source: &str, tiling: CoopTiling) -> Result<Self, GpuError> {
        Self::build(ctx, config, capacity, Some((source, tiling)))
    }

    fn build(ctx: &GpuContext, config: &MlpConfig, capacity: usize, coop_source: Option<(&str, CoopTiling)>) -> Result<Self, GpuError> {
        config.validate().map_err(|e| GpuError::Unsupported(e.to_string()))?;
        let mut layers = Vec::with_capacity(config.hidden_layers + 1);
        let (mut off, mut prev, mut tape_off) = (0usize, config.input_dim, 0usize);
        for i in 0..=config.hidden_layers {
            let last = i == config.hidden_layers;
            let skip = config.skips.contains(&i);
            let fan_in = if i == 0 { config.input_dim } else { prev + if skip { config.input_dim } else { 0 } };
            let out = if last { config.output_dim } else { config.hidden_dim };
            let w_off = off;
            off += out * fan_in;
            let b_off = config.bias.then(|| {
                off += out;
                off - out
            });
            let act = if last { config.output_activation } else { config.hidden_activation };
            let ka = if i == 0 || skip { config.input_dim } else { 0 };
            layers.push(LayerInfo { fan_in, out, ka, w_off, b_off, act, tape_off });
            tape_off += out;
            prev = out;
        }
        let tape_stride = tape_off;
        let max_words = u32::MAX as usize / 4;
        if off > max_words || capacity.saturating_mul(tape_stride) > max_words {
            return Err(GpuError::Unsupported(format!(
                "MLP of {off} parameters with a tape of {capacity}×{tape_stride} floats exceeds 32-bit indexing"
            )));
        }
        let chunk = split_chunk(capacity);
        let n_splits = capacity.div_ceil(chunk).max(1);
        let mut me = Self {
            config: config.clone(),
            layers,
            n_params: off,
            capacity,
            tape_stride,
            n_splits,
            chunk,
            plain: None,
            coop: None,
            dummy: ctx.zeros("linear dummy", 4),
        };
        if let Some((src, tiling)) = coop_source {
            me.coop = Some(coop::Coop::new(ctx, &me, src, tiling)?);
        } else {
            me.plain = Some(me.build_plain(ctx));
        }
        Ok(me)
    }

    fn build_plain(&self, ctx: &GpuContext) -> Plain {
        let src = shaders::with_common(shaders::LINEAR);
        let module = ctx.shader_module("linear.wgsl", &src);
        let k = |e: &str| Kernel::from_module(ctx, &module, e, &[]);
        let cfg = &self.config;
        let h = cfg.hidden_dim;
        let nl = self.layers.len();
        let mut ls = Vec::with_capacity(nl);
        for (i, l) in self.layers.iter().enumerate() {
            let last = i + 1 == nl;
            let bias = if l.b_off.is_some() { FLAG_BIAS } else { 0 };
            let prev = (i > 0).then(|| &self.layers[i - 1]);
            let base = LinearParams {
                n_out: l.out as u32,
                k_in: l.fan_in as u32,
                ka: l.ka as u32,
                act: act_code(l.act),
                a_stride: cfg.input_dim as u32,
                w_off: l.w_off as u32,
                bias_off: l.b_off.unwrap_or(0) as u32,
                chunk: self.chunk as u32,
                ..Default::default()
            };
            let fwd = LinearParams {
                b_stride: self.tape_stride as u32,
                b_off: prev.map_or(0, |p| p.tape_off) as u32,
                dst_stride: self.tape_stride as u32,
                dst_off: l.tape_off as u32,
                out_stride: cfg.output_dim as u32,
                flags: bias | FLAG_WORK | if last { FLAG_OUT } else { 0 },
                ..base
            };
            let inf = LinearParams {
                b_stride: (2 * h) as u32,
                b_off: if i == 0 { 0 } else { ((i - 1) % 2 * h) as u32 },
                dst_stride: (2 * h) as u32,
                dst_off: (i % 2 * h) as u32,
                out_stride: cfg.output_dim as u32,
                flags: bias | if last { FLAG_OUT } else { FLAG_WORK },
                ..base
            };
            let bwd = |with_dinput: bool| LinearParams {
                b_stride: self.tape_stride as u32,
                b_off: prev.map_or(0, |p| p.tape_off) as u32,
                dst_stride: (l.fan_in - l.ka) as u32,
                flags: bias | if with_dinput { FLAG_DINPUT } else { 0 },
                c_lo: if with_dinput { 0 } else { l.ka as u32 },
                prev_act: prev.map_or(0, |p| act_code(p.act)),
                ..base
            };
            ls.push(PlainLayer {
                fwd: ctx.uniform("linear fwd", &fwd),
                inf: ctx.uniform("linear inf", &inf),
                bwd: [ctx.uniform("linear bwd", &bwd(false)), ctx.uniform("linear bwd+dx", &bwd(true))],
            });
        }
        let lastl = &self.layers[nl - 1];
        let og = LinearParams {
            n_out: lastl.out as u32,
            act: act_code(lastl.act),
            b_stride: self.tape_stride as u32,
            b_off: lastl.tape_off as u32,
            out_stride: cfg.output_dim as u32,
            ..Default::default()
        };
        let maxw = self.layers.iter().map(|l| l.out).max().unwrap_or(1);
        let max_partial = self.layers.iter().map(|l| l.out * (l.fan_in + 1)).max().unwrap_or(1);
        let cap = self.capacity.max(1);
        Plain {
            forward: k("forward"),
            backward_data: k("backward_data"),
            backward_weight: k("backward_weight"),
            reduce: k("reduce_grads"),
            output_grad: k("output_grad"),
            layers: ls,
            out_grad_u: ctx.uniform("linear output_grad", &og),
            scratch: ctx.zeros("linear inference scratch", 4 * cap * 2 * h.max(1)),
            dz: [ctx.zeros("linear dz a", 4 * cap * maxw), ctx.zeros("linear dz b", 4 * cap * maxw)],
            partial: ctx.zeros("linear dW partial", 4 * self.n_splits * max_partial),
        }
    }

    /// Number of parameters (length of the params / grads buffers).
    pub fn n_params(&self) -> usize {
        self.n_params
    }

    /// Floats per sample of the tape (Σ of the layer widths).
    pub fn tape_floats_per_sample(&self) -> usize {
        self.tape_stride
    }

    /// The sample capacity given to [`GpuMlp::new`].
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// The configuration.
    pub fn config(&self) -> &MlpConfig {
        &self.config
    }

    /// Whether the training forward writes the f32 tape of the hidden layers (true unless
    /// [`GpuMlp::drop_hidden_tape`] was called).
    pub fn keeps_hidden_tape(&self) -> bool {
        self.coop.as_ref().is_none_or(|c| c.hidden_tape)
    }

    /// Stops the training forward from writing the hidden layers' f32 tape (cooperative-matrix
    /// paths). The backward then takes a hidden layer's `act'` from the f16 copy of its output,
    /// which the next layer's products read anyway; only the output block of the tape is still
    /// written. That saves 4 bytes written and 4 read per hidden activation and sample: 8 KiB per
    /// sample for the paper's 8×256 trunk. Needs ReLU or identity hidden layers, whose `act'`
    /// depends only on the sign (the f16 copy rounds `0 < y < 3·10⁻⁸` to zero, a value the next
    /// layer's product already saw as zero); an [`GpuError::Unsupported`] on the plain path or
    /// with another hidden activation.
    pub fn drop_hidden_tape(&mut self, ctx: &GpuContext) -> Result<(), GpuError> {
        let act = self.config.hidden_activation;
        if !matches!(act, Activation::Relu | Activation::None) {
            return Err(GpuError::Unsupported(format!(
                "an MLP without its hidden f32 tape needs ReLU or identity hidden layers, not {act:?}"
            )));
        }
        match self.coop.as_mut() {
            Some(c) => {
                c.drop_hidden_tape(ctx);
                Ok(())
            }
            None => Err(GpuError::Unsupported("only the cooperative-matrix GEMMs can train without the hidden f32 tape".into())),
        }
    }

    /// Whether this instance runs on cooperative matrices.
    pub fn uses_coop(&self) -> bool {
        self.coop.is_some()
    }

    /// The implementation this instance runs.
    pub fn path(&self) -> LinearPath {
        match self.coop.as_ref().map(|c| c.tiling) {
            None => LinearPath::Plain,
            Some(CoopTiling::Subgroup) => LinearPath::Coop,
            Some(CoopTiling::Workgroup) => LinearPath::CoopTiled,
            Some(CoopTiling::WorkgroupWide) => LinearPath::CoopTiledWide,
        }
    }

    /// For tests: how many layers run their forward, backward_data (with or without `d_input`)
    /// and backward_weight products on the `*_wide` kernels ([`LinearPath::CoopTiledWide`]).
    #[doc(hidden)]
    pub fn wide_products(&self, with_d_input: bool) -> [usize; 3] {
        self.coop.as_ref().map_or([0; 3], |c| c.wide_products(with_d_input))
    }

    fn check_capacity(&self, capacity: usize) {
        assert!(
            capacity <= self.capacity,
            "GpuMlp: launch capacity {capacity} exceeds the capacity {} given to new",
            self.capacity
        );
    }

    /// Groups of a row-tiled product: rows over x/y, `col_tiles` over z.
    fn row_groups(capacity: usize, rows_per_tile: usize, col_tiles: usize) -> [u32; 3] {
        let g = groups_1d(capacity, rows_per_tile as u32);
        [g[0], g[1], col_tiles.max(1) as u32]
    }

    /// Records the forward of `n = counters[1]` samples: `output = mlp(input)` and the tape that
    /// [`GpuMlp::record_backward`] needs. Launched for `capacity` (≤ the capacity of `new`).
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
        capacity: usize,
    ) {
        self.check_capacity(capacity);
        if let Some(c) = &self.coop {
            return c.record_forward(self, ctx, enc, counters, input, params, output, Some(tape), capacity);
        }
        let p = self.plain.as_ref().expect("plain path");
        for (l, u) in self.layers.iter().zip(&p.layers) {
            p.forward.record(
                ctx,
                enc,
                &[(0, &u.fwd), (1, counters), (2, input), (3, tape), (4, params), (5, output)],
                Self::row_groups(capacity, TILE, l.out.div_ceil(TILE)),
            );
        }
    }

    /// Records inference only (no tape; the [`GpuMlp`] owns the scratch): `output = mlp(input)`.
    #[allow(clippy::too_many_arguments)]
    pub fn record_inference(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        input: &wgpu::Buffer,
        params: &wgpu::Buffer,
        output: &wgpu::Buffer,
        capacity: usize,
    ) {
        self.check_capacity(capacity);
        if let Some(c) = &self.coop {
            return c.record_forward(self, ctx, enc, counters, input, params, output, None, capacity);
        }
        let p = self.plain.as_ref().expect("plain path");
        for (l, u) in self.layers.iter().zip(&p.layers) {
            p.forward.record(
                ctx,
                enc,
                &[(0, &u.inf), (1, counters), (2, input), (3, &p.scratch), (4, params), (5, output)],
                Self::row_groups(capacity, TILE, l.out.div_ceil(TILE)),
            );
        }
    }

    /// Records the backward from `d_output`: ACCUMULATES the parameter gradients into `grads` and,
    /// when `d_input` is given, OVERWRITES it with dL/d(input). `input`, `params` and `tape` must
    /// be those of the forward.
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
        capacity: usize,
    ) {
        self.check_capacity(capacity);
        if let Some(d) = d_input {
            enc.clear_buffer(d, 0, None);
        }
        if let Some(c) = &self.coop {
            return c.record_backward(self, ctx, enc, counters, input, params, tape, d_output, grads, d_input, capacity);
        }
        let p = self.plain.as_ref().expect("plain path");
        let nl = self.layers.len();
        let last = &self.layers[nl - 1];
        p.output_grad.record(
            ctx,
            enc,
            &[(0, &p.out_grad_u), (1, counters), (2, d_output), (3, tape), (4, &p.dz[0])],
            groups_1d(capacity * last.out, WG),
        );
        let mut cur = 0;
        for i in (0..nl).rev() {
            let l = &self.layers[i];
            let u = &p.layers[i].bwd[d_input.is_some() as usize];
            let kc = l.fan_in + l.b_off.is_some() as usize;
            p.backward_weight.record(
                ctx,
                enc,
                &[(0, u), (1, counters), (2, &p.dz[cur]), (3, input), (4, tape), (5, &p.partial)],
                [kc.div_ceil(TILE) as u32, l.out.div_ceil(TILE) as u32, capacity.div_ceil(self.chunk).max(1) as u32],
            );
            p.reduce.record(ctx, enc, &[(0, u), (1, counters), (2, &p.partial), (3, grads)], groups_1d(l.out * kc, WG));
            let c_lo = if d_input.is_some() { 0 } else { l.ka };
            if c_lo < l.fan_in {
                let dx = d_input.unwrap_or(&self.dummy);
                p.backward_data.record(
                    ctx,
                    enc,
                    &[(0, u), (1, counters), (2, &p.dz[cur]), (3, params), (4, &p.dz[1 - cur]), (5, tape), (6, dx)],
                    Self::row_groups(capacity, TILE, (l.fan_in - c_lo).div_ceil(TILE)),
                );
            }
            cur = 1 - cur;
        }
    }

    /// Host convenience for tests: uploads, runs forward (with a tape) or inference for `n`
    /// samples and reads back `(output, tape)` (tape empty for inference).
    pub fn run_forward(&self, ctx: &GpuContext, input: &[f32], params: &[f32], n: usize, with_tape: bool) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        assert_eq!(input.len(), n * self.config.input_dim, "GpuMlp::run_forward: input length");
        assert_eq!(params.len(), self.n_params, "GpuMlp::run_forward: params length");
        let counters = ctx.upload("counters", &[n as u32, n as u32]);
        let inp = ctx.upload("input", input);
        let par = ctx.upload("params", params);
        let out = ctx.upload("output", &vec![f32::NAN; n * self.config.output_dim]);
        let tape = ctx.upload("tape", &vec![f32::NAN; n * self.tape_stride]);
        let mut enc = ctx.encoder("run_forward");
        if with_tape {
            self.record_forward(ctx, &mut enc, &counters, &inp, &par, &out, &tape, n);
        } else {
            self.record_inference(ctx, &mut enc, &counters, &inp, &par, &out, n);
        }
        ctx.queue.submit([enc.finish()]);
        let o = ctx.read_f32(&out, n * self.config.output_dim)?;
        let t = if with_tape { ctx.read_f32(&tape, n * self.tape_stride)? } else { Vec::new() };
        Ok((o, t))
    }

    /// Host convenience for tests: forward then backward for `n` samples; `grads` is accumulated
    /// in place; returns `d_input` when `want_d_input`.
    #[allow(clippy::too_many_arguments)]
    pub fn run_backward(
        &self,
        ctx: &GpuContext,
        input: &[f32],
        params: &[f32],
        d_output: &[f32],
        grads: &mut [f32],
        n: usize,
        want_d_input: bool,
    ) -> Result<Option<Vec<f32>>, GpuError> {
        assert_eq!(d_output.len(), n * self.config.output_dim, "GpuMlp::run_backward: d_output length");
        assert_eq!(grads.len(), self.n_params, "GpuMlp::run_backward: grads length");
        let counters = ctx.upload("counters", &[n as u32, n as u32]);
        let inp = ctx.upload("input", input);
        let par = ctx.upload("params", params);
        let out = ctx.zeros("output", 4 * n * self.config.output_dim);
        let tape = ctx.zeros("tape", 4 * n * self.tape_stride);
        let dout = ctx.upload("d_output", d_output);
        let g = ctx.upload("grads", grads);
        let dx = ctx.upload("d_input", &vec![f32::NAN; n * self.config.input_dim]);
        let mut enc = ctx.encoder("run_backward");
        self.record_forward(ctx, &mut enc, &counters, &inp, &par, &out, &tape, n);
        self.record_backward(ctx, &mut enc, &counters, &inp, &par, &tape, &dout, &g, want_d_input.then_some(&dx), n);
        ctx.queue.submit([enc.finish()]);
        grads.copy_from_slice(&ctx.read_f32(&g, self.n_params)?);
        Ok(if want_d_input { Some(ctx.read_f32(&dx, n * self.config.input_dim)?) } else { None })
    }
}

/// The cooperative-matrix implementation (`shaders/linear_coop.wgsl`).
mod coop {
    use super::{act_code, CoopTiling, GpuMlp, FLAG_BIAS, FLAG_DINPUT, FLAG_OUT, FLAG_WORK, WG};
    use crate::kernel::{groups_1d, Kernel};
    use crate::{GpuContext, GpuError};

    /// Writes the f16 copy of the hidden activations.
    const FLAG_H16: u32 = 16;
    /// backward_data takes the previous layer's activation for `act'` from h16, not the f32 tape.
    const FLAG_PREV_H16: u32 = 32;
    /// Block edge of the `*_wide` entry points.
    const WIDE: usize = 128;

    /// Uniform `CP` of `shaders/linear_coop.wgsl`.
    #[repr(C)]
    #[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
    struct CoopParams {
        n_out: u32,
        k_in: u32,
        ka: u32,
        act: u32,
        np: u32,
        kp: u32,
        xp: u32,
        hp: u32,
        w16_off: u32,
        h_src: u32,
        h_dst: u32,
        flags: u32,
        t_stride: u32,
        t_off: u32,
        t_prev_off: u32,
        out_dim: u32,
        w_off: u32,
        bias_off: u32,
        chunk: u32,
        c_lo: u32,
        prev_act: u32,
        kcp: u32,
        in_dim: u32,
        _pad: u32,
    }

    fn r16(x: usize) -> usize {
        x.next_multiple_of(16)
    }

    struct CoopLayer {
        np: usize,
        kp: usize,
        kcp: usize,
        xp: usize,
        w16: wgpu::Buffer,
        fwd: wgpu::Buffer,
        inf: wgpu::Buffer,
        bwd: [wgpu::Buffer; 2],
        /// The contents of `fwd` and `bwd` as built (before [`Coop::drop_hidden_tape`]).
        fwd_p: CoopParams,
        bwd_p: [CoopParams; 2],
    }

    pub(super) struct Coop {
        pub(super) tiling: CoopTiling,
        /// Whether the training forward writes the hidden layers' f32 tape.
        pub(super) hidden_tape: bool,
        convert_input: Kernel,
        convert_weights: Kernel,
        forward: Kernel,
        output_grad: Kernel,
        backward_data: Kernel,
        backward_weight: Kernel,
        reduce: Kernel,
        /// The `*_wide` entry points ([`CoopTiling::WorkgroupWide`] only): forward, backward_data,
        /// backward_weight.
        wide: Option<[Kernel; 3]>,
        layers: Vec<CoopLayer>,
        xp: usize,
        in_u: wgpu::Buffer,
        out_grad_u: wgpu::Buffer,
        x16: wgpu::Buffer,
        x16_inf: wgpu::Buffer,
        h16: wgpu::Buffer,
        h16_inf: wgpu::Buffer,
        w16: wgpu::Buffer,
        dz16: [wgpu::Buffer; 2],
        partial: wgpu::Buffer,
        ones: wgpu::Buffer,
    }

    impl Coop {
        /// Memory (f16 scratch, bytes): x16 and its inference copy `2·rows·xp` each, h16
        /// `hidden_layers·rows·hp` (+ `2·rows·hp` for inference), dz16 `2·rows·max_np`, with
        /// `rows = capacity` rounded up to 32 ([`CoopTiling::Subgroup`]), 64
        /// ([`CoopTiling::Workgroup`], whose epilogues write whole 64-row blocks) or 128
        /// ([`CoopTiling::WorkgroupWide`]); w16 and the f32
        /// partials do not depend on the tiling.
        pub(super) fn new(ctx: &GpuContext, m: &GpuMlp, src: &str, tiling: CoopTiling) -> Result<Self, GpuError> {
            let module = ctx.shader_module("linear_coop.wgsl", src);
            let k = |e: &str| Kernel::from_module(ctx, &module, e, &[]);
            let cfg = &m.config;
            let xp = r16(cfg.input_dim);
            let hp = r16(cfg.hidden_dim);
            let rows = m.capacity.next_multiple_of(tiling.rows()).max(tiling.rows());
            let nl = m.layers.len();
            let mut layers = Vec::with_capacity(nl);
            let mut w16_off = 0usize;
            for (i, l) in m.layers.iter().enumerate() {
                let last = i + 1 == nl;
                let lxp = if l.ka > 0 { xp } else { 0 };
                let np = r16(l.out);
                let kp = lxp + if i > 0 { hp } else { 0 };
                let kcp = kp + if l.b_off.is_some() { 16 } else { 0 };
                let bias = if l.b_off.is_some() { FLAG_BIAS } else { 0 };
                let prev = (i > 0).then(|| &m.layers[i - 1]);
                let base = CoopParams {
                    n_out: l.out as u32,
                    k_in: l.fan_in as u32,
                    ka: l.ka as u32,
                    act: act_code(l.act),
                    np: np as u32,
                    kp: kp as u32,
                    xp: lxp as u32,
                    hp: hp as u32,
                    w16_off: w16_off as u32,
                    t_stride: m.tape_stride as u32,
                    t_off: l.tape_off as u32,
                    t_prev_off: prev.map_or(0, |p| p.tape_off) as u32,
                    out_dim: cfg.output_dim as u32,
                    w_off: l.w_off as u32,
                    bias_off: l.b_off.unwrap_or(0) as u32,
                    chunk: m.chunk as u32,
                    prev_act: prev.map_or(0, |p| act_code(p.act)),
                    kcp: kcp as u32,
                    in_dim: cfg.input_dim as u32,
                    ..Default::default()
                };
                let layer_h = |j: usize| (j * rows * hp) as u32;
                let fwd = CoopParams {
                    h_src: if i > 0 { layer_h(i - 1) } else { 0 },
                    h_dst: if last { 0 } else { layer_h(i) },
                    flags: bias | FLAG_WORK | if last { FLAG_OUT } else { FLAG_H16 },
                    ..base
                };
                let inf = CoopParams {
                    h_src: if i > 0 { layer_h((i - 1) % 2) } else { 0 },
                    h_dst: layer_h(i % 2),
                    flags: bias | if last { FLAG_OUT } else { FLAG_H16 },
                    ..base
                };
                let bwd = |dx: bool| CoopParams {
                    h_src: if i > 0 { layer_h(i - 1) } else { 0 },
                    flags: bias | if dx { FLAG_DINPUT } else { 0 },
                    c_lo: if dx { 0 } else { lxp as u32 },
                    ..base
                };
                layers.push(CoopLayer {
                    np,
                    kp,
                    kcp,
                    xp: lxp,
                    w16: ctx.uniform("coop w16", &CoopParams { ..base }),
                    fwd: ctx.uniform("coop fwd", &fwd),
                    inf: ctx.uniform("coop inf", &inf),
                    bwd: [ctx.uniform("coop bwd", &bwd(false)), ctx.uniform("coop bwd+dx", &bwd(true))],
                    fwd_p: fwd,
                    bwd_p: [bwd(false), bwd(true)],
                });
                w16_off += np * kp;
            }
            let lastl = &m.layers[nl - 1];
            let og = CoopParams {
                n_out: lastl.out as u32,
                act: act_code(lastl.act),
                np: r16(lastl.out) as u32,
                t_stride: m.tape_stride as u32,
                t_off: lastl.tape_off as u32,
                out_dim: cfg.output_dim as u32,
                ..Default::default()
            };
            let inp = CoopParams { xp: xp as u32, in_dim: cfg.input_dim as u32, ..Default::default() };
            let max_np = layers.iter().map(|l| l.np).max().unwrap_or(16);
            let max_partial = layers.iter().map(|l| l.np * l.kcp).max().unwrap_or(16);
            let mut ones = [half::f16::ZERO; 256];
            for r in 0..16 {
                ones[r * 16] = half::f16::ONE;
            }
            // At least 16 bytes: the tiled kernels view some of these buffers as vec4<f16> (a
            // binding of at least 8 bytes), and a net without hidden layers has an empty h16.
            let f16b = |n: usize| (2 * n).max(16);
            let tiled = |e: &str| match tiling {
                CoopTiling::Subgroup => k(e),
                CoopTiling::Workgroup | CoopTiling::WorkgroupWide => k(&format!("{e}_tiled")),
            };
            let wide = (tiling == CoopTiling::WorkgroupWide)
                .then(|| ["forward", "backward_data", "backward_weight"].map(|e| k(&format!("{e}_wide"))));
            Ok(Self {
                tiling,
                hidden_tape: true,
                convert_input: k("convert_input"),
                convert_weights: k("convert_weights"),
                forward: tiled("forward"),
                output_grad: k("output_grad"),
                backward_data: tiled("backward_data"),
                backward_weight: tiled("backward_weight"),
                reduce: k("reduce_grads"),
                wide,
                layers,
                xp,
                in_u: ctx.uniform("coop input", &inp),
                out_grad_u: ctx.uniform("coop output_grad", &og),
                x16: ctx.zeros("coop x16", f16b(rows * xp)),
                x16_inf: ctx.zeros("coop x16 inference", f16b(rows * xp)),
                h16: ctx.zeros("coop h16", f16b(cfg.hidden_layers.max(1) * rows * hp)),
                h16_inf: ctx.zeros("coop h16 inference", f16b(2 * rows * hp)),
                w16: ctx.zeros("coop w16", f16b(w16_off)),
                dz16: [ctx.zeros("coop dz16 a", f16b(rows * max_np)), ctx.zeros("coop dz16 b", f16b(rows * max_np))],
                partial: ctx.zeros("coop dW partial", 4 * m.n_splits * max_partial),
                ones: ctx.upload("coop ones", &ones),
            })
        }

        /// The wide kernels, where this instance has them and a product's block width `cols` is a
        /// whole number of [`WIDE`] blocks.
        fn wide(&self, cols: usize) -> Option<&[Kernel; 3]> {
            self.wide.as_ref().filter(|_| cols > 0 && cols.is_multiple_of(WIDE))
        }

        /// See [`GpuMlp::wide_products`]; the same predicates as the record functions.
        pub(super) fn wide_products(&self, with_d_input: bool) -> [usize; 3] {
            let mut n = [0; 3];
            for l in &self.layers {
                let c_lo = if with_d_input { 0 } else { l.xp };
                n[0] += self.wide(l.np).is_some() as usize;
                n[1] += (c_lo < l.kp && self.wide(l.kp - c_lo).is_some()) as usize;
                n[2] += self.wide(l.np).and(self.wide(l.kp)).is_some() as usize;
            }
            n
        }

        /// See [`GpuMlp::drop_hidden_tape`]: the hidden layers' forward without `FLAG_WORK`, and
        /// every backward that reaches a hidden layer with `FLAG_PREV_H16`.
        pub(super) fn drop_hidden_tape(&mut self, ctx: &GpuContext) {
            let nl = self.layers.len();
            for (i, l) in self.layers.iter().enumerate() {
                if i + 1 < nl {
                    ctx.write(&l.fwd, 0, &[CoopParams { flags: l.fwd_p.flags & !FLAG_WORK, ..l.fwd_p }]);
                }
                if i > 0 {
                    for (u, p) in l.bwd.iter().zip(&l.bwd_p) {
                        ctx.write(u, 0, &[CoopParams { flags: p.flags | FLAG_PREV_H16, ..*p }]);
                    }
                }
            }
            self.hidden_tape = false;
        }

        fn record_weights(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, params: &wgpu::Buffer) {
            for l in &self.layers {
                self.convert_weights.record(ctx, enc, &[(0, &l.w16), (2, params), (3, &self.w16)], groups_1d(l.np * l.kp, WG));
            }
        }

        #[allow(clippy::too_many_arguments)]
        pub(super) fn record_forward(
            &self,
            m: &GpuMlp,
            ctx: &GpuContext,
            enc: &mut wgpu::CommandEncoder,
            counters: &wgpu::Buffer,
            input: &wgpu::Buffer,
            params: &wgpu::Buffer,
            output: &wgpu::Buffer,
            tape: Option<&wgpu::Buffer>,
            capacity: usize,
        ) {
            let rows = capacity.next_multiple_of(32).max(32);
            let (x16, h16) = if tape.is_some() { (&self.x16, &self.h16) } else { (&self.x16_inf, &self.h16_inf) };
            self.record_weights(ctx, enc, params);
            self.convert_input.record(ctx, enc, &[(0, &self.in_u), (1, counters), (2, input), (3, x16)], groups_1d(rows * self.xp, WG));
            let dst = tape.unwrap_or(&m.dummy);
            let t = self.tiling.rows();
            for l in &self.layers {
                let u = if tape.is_some() { &l.fwd } else { &l.inf };
                let b = [(0, u), (1, counters), (2, x16), (3, h16), (4, &self.w16), (5, params), (6, dst), (7, output), (8, h16)];
                match (self.tiling, self.wide(l.np)) {
                    (_, Some([forward, ..])) => forward.record(ctx, enc, &b, GpuMlp::row_groups(capacity, WIDE, l.np / WIDE)),
                    (CoopTiling::Subgroup, _) => self.forward.record(ctx, enc, &b[..8], GpuMlp::row_groups(capacity, t, l.np.div_ceil(t))),
                    // Binding 8: h16 again, as vec4s for the staging loads.
                    _ => self.forward.record(ctx, enc, &b, GpuMlp::row_groups(capacity, 64, l.np.div_ceil(64))),
                }
            }
        }

        #[allow(clippy::too_many_arguments)]
        pub(super) fn record_backward(
            &self,
            m: &GpuMlp,
            ctx: &GpuContext,
            enc: &mut wgpu::CommandEncoder,
            counters: &wgpu::Buffer,
            _input: &wgpu::Buffer,
            params: &wgpu::Buffer,
            tape: &wgpu::Buffer,
            d_output: &wgpu::Buffer,
            grads: &wgpu::Buffer,
            d_input: Option<&wgpu::Buffer>,
            capacity: usize,
        ) {
            let rows = capacity.next_multiple_of(32).max(32);
            let t = self.tiling.rows();
            self.record_weights(ctx, enc, params);
            let nl = self.layers.len();
            self.output_grad.record(
                ctx,
                enc,
                &[(0, &self.out_grad_u), (1, counters), (2, d_output), (3, tape), (4, &self.dz16[0])],
                groups_1d(rows * self.layers[nl - 1].np, WG),
            );
            let mut cur = 0;
            for i in (0..nl).rev() {
                let l = &self.layers[i];
                let ml = &m.layers[i];
                let u = &l.bwd[d_input.is_some() as usize];
                let splits = capacity.div_ceil(m.chunk).max(1) as u32;
                let wide_w = self.wide(l.np).and(self.wide(l.kp));
                match self.tiling {
                    _ if wide_w.is_some() => wide_w.expect("checked")[2].record(
                        ctx,
                        enc,
                        &[(0, u), (1, counters), (2, &self.dz16[cur]), (3, &self.x16), (4, &self.h16), (6, &self.partial)],
                        [(l.kp / WIDE) as u32, (l.np / WIDE) as u32, splits],
                    ),
                    CoopTiling::Subgroup => self.backward_weight.record(
                        ctx,
                        enc,
                        &[(0, u), (1, counters), (2, &self.dz16[cur]), (3, &self.x16), (4, &self.h16), (5, &self.ones), (6, &self.partial)],
                        [l.kcp.div_ceil(32) as u32, l.np.div_ceil(32) as u32, splits],
                    ),
                    // Blocks over the kp columns only: the bias column is summed without the ones.
                    CoopTiling::Workgroup | CoopTiling::WorkgroupWide => self.backward_weight.record(
                        ctx,
                        enc,
                        &[(0, u), (1, counters), (2, &self.dz16[cur]), (3, &self.x16), (4, &self.h16), (6, &self.partial)],
                        [l.kp.div_ceil(64) as u32, l.np.div_ceil(64) as u32, splits],
                    ),
                }
                let kc = ml.fan_in + ml.b_off.is_some() as usize;
                self.reduce.record(ctx, enc, &[(0, u), (1, counters), (2, &self.partial), (3, grads)], groups_1d(ml.out * kc, WG));
                let c_lo = if d_input.is_some() { 0 } else { l.xp };
                if c_lo < l.kp {
                    let dx = d_input.unwrap_or(&m.dummy);
                    // Binding 7: h16, the previous layer's activations for act' under FLAG_PREV_H16.
                    let b = [(0, u), (1, counters), (2, &self.dz16[cur]), (3, &self.w16), (4, &self.dz16[1 - cur]), (5, tape), (6, dx), (7, &self.h16)];
                    let cols = l.kp - c_lo;
                    match self.wide(cols) {
                        Some([_, backward_data, _]) => backward_data.record(ctx, enc, &b, GpuMlp::row_groups(capacity, WIDE, cols / WIDE)),
                        None => self.backward_data.record(ctx, enc, &b, GpuMlp::row_groups(capacity, t.min(64), cols.div_ceil(t.min(64)))),
                    }
                }
                cur = 1 - cur;
            }
        }
    }
}
