//! The paper's NeRF field (Mildenhall et al. 2020): frequency (positional) encoding of position
//! (L = 10) and view direction (L = 4), an 8×256 ReLU trunk that re-concatenates the encoded input
//! after its 5th layer, a density head (σ = ReLU), a 256-wide feature layer and a 128-wide
//! view-dependent colour branch with a sigmoid.
//!
//! It is a composition of reusable parts — two [`FrequencyEncoding`]s and two [`Mlp`]s — and is
//! generic over [`Real`] so that the whole field's backward pass can be checked against finite
//! differences in `f64`. The `f32` instance implements [`RadianceField`].
//!
//! Layer layout (nerf-pytorch's `NeRF` with `use_viewdirs=True`):
//! ```text
//! γ(x) (63) ─► trunk: 8 × Linear(·,256)+ReLU, input re-concatenated [γ(x), h] before layer 6,
//!              then Linear(256, 1+256) (nerf-pytorch's alpha_linear and feature_linear fused)
//!              ─► σ = ReLU(out[0]),  feature = out[1..]
//! [feature, γ(d)] (256+27) ─► colour: Linear(283,128)+ReLU ─► Linear(128,3)+sigmoid ─► rgb
//! ```

pub mod gpu;

use nerf_core::{grown, Real, ScratchPool};
use nerf_encoding::{Encoding, FrequencyEncoding, FrequencyEncodingConfig};
use nerf_field::{config_from_json, FieldContext, FieldError, ParamGroupMut, RadianceField};
use nerf_mlp::{Activation, Mlp, MlpConfig, MlpScratch, MlpTape};
use serde::{Deserialize, Serialize};

/// Configuration of the paper's field. Defaults are the paper's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FreqNerfConfig {
    /// Frequency bands for position (paper: 10 → 63 dims with the raw input).
    pub pos_frequencies: usize,
    /// Frequency bands for the view direction (paper: 4 → 27 dims).
    pub dir_frequencies: usize,
    /// Trunk width (paper: 256).
    pub width: usize,
    /// Trunk depth in linear layers (paper: 8).
    pub depth: usize,
    /// Trunk layers (0-based) after which the encoded input is re-concatenated (paper: `[4]`).
    pub skips: Vec<usize>,
    /// Width of the view-direction branch (paper: 128 = width / 2).
    pub view_width: usize,
    /// L2 weight decay on all weights (paper: 0).
    pub weight_decay: f32,
    /// Which layer-by-layer GEMM kernels the GPU twin runs (ignored on the CPU).
    pub gpu_linear: GpuLinear,
    /// Whether the GPU twin's training forward keeps the f32 tape of the networks' hidden layers.
    /// Unset (the default since 2026-11-27): dropped where the GEMMs are cooperative-matrix ones
    /// (their ReLU masks then come from the f16 copies those GEMMs keep anyway, saving 8 KiB
    /// written and read per sample of the trunk, [`nerf_gpu::linear::GpuMlp::drop_hidden_tape`];
    /// on the H100 the step took 29.9 against 33.6 ms, docs/results.md), kept on the plain path,
    /// which needs it. `true` keeps it on every path; `false` drops it and is an error on the
    /// plain path. Ignored on the CPU.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu_hidden_tape: Option<bool>,
}

/// The GEMM kernels of the paper field's GPU twin ([`FreqNerfConfig::gpu_linear`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GpuLinear {
    /// Cooperative matrices where the adapter has them (and `NERF_NO_COOP` is unset), else plain:
    /// `coop_tiled` where subgroups are exactly 32 wide (NVIDIA), else `coop`.
    #[default]
    Auto,
    /// Plain WGSL, f32, 64×64 tiles (`shaders/linear.wgsl`).
    Plain,
    /// Cooperative matrices, one subgroup per 32×32 output block, operands from global memory
    /// (`shaders/linear_coop.wgsl`, the H100-verified kernels).
    Coop,
    /// Cooperative matrices, four subgroups per 64×64 output block with K chunks staged in
    /// workgroup memory (`*_tiled` entry points of `shaders/linear_coop.wgsl`); needs 32-wide
    /// subgroups.
    CoopTiled,
    /// As `coop_tiled`, with 128×128 output blocks for the trunk's 256-wide products
    /// (`*_wide` entry points, 4×4 accumulators per subgroup); needs 32-wide subgroups and
    /// 28 676 bytes of workgroup memory. Opt-in: slower than `coop_tiled` on the H100 (57 against
    /// 39 ms per step, docs/results.md).
    CoopTiledWide,
}

impl Default for FreqNerfConfig {
    fn default() -> Self {
        Self {
            pos_frequencies: 10,
            dir_frequencies: 4,
            width: 256,
            depth: 8,
            skips: vec![4],
            view_width: 128,
            weight_decay: 0.0,
            gpu_linear: GpuLinear::Auto,
            gpu_hidden_tape: None,
        }
    }
}

impl FreqNerfConfig {
    fn validate(&self) -> Result<(), FieldError> {
        let bad = |m: String| Err(FieldError::InvalidConfig { field: "freq".into(), message: m });
        if self.width == 0 || self.depth == 0 || self.view_width == 0 {
            return bad("width, depth and view_width must be positive".into());
        }
        if let Some(s) = self.skips.iter().find(|&&s| s + 1 >= self.depth) {
            return bad(format!("skip after layer {s} needs a later trunk layer (depth {})", self.depth));
        }
        if self.pos_frequencies > 24 || self.dir_frequencies > 24 {
            return bad("more than 24 frequency bands exceeds f32 precision".into());
        }
        Ok(())
    }
}

/// Buffers kept between forward and backward (reused across steps).
#[derive(Default)]
struct Tape<T: Real> {
    n: usize,
    pos_in: Vec<T>,
    dir_in: Vec<T>,
    pos_enc: Vec<T>,
    dir_enc: Vec<T>,
    color_in: Vec<T>,
    raw_sigma: Vec<T>,
    trunk: MlpTape<T>,
    color: MlpTape<T>,
    // backward scratch
    d_color_in: Vec<T>,
    d_trunk: Vec<T>,
    /// dL/d(encoding), of positions then of directions (input gradients only).
    d_enc: Vec<T>,
}

/// The paper's NeRF field.
pub struct FreqNerf<T: Real> {
    config: FreqNerfConfig,
    pos_enc: FrequencyEncoding,
    dir_enc: FrequencyEncoding,
    trunk: Mlp<T>,
    color: Mlp<T>,
    tape: Tape<T>,
    /// Inference buffers of [`RadianceField::query`] / [`RadianceField::density`] (`&self`, on
    /// several threads at once while rendering), kept between calls.
    query_scratch: ScratchPool<QueryScratch<T>>,
}

/// Samples per inference chunk: bounds the scratch memory of [`RadianceField::query`].
const QUERY_CHUNK: usize = 1 << 14;

impl<T: Real> FreqNerf<T> {
    /// Builds the field with PyTorch-style initialisation from `seed`.
    pub fn new(config: FreqNerfConfig, seed: u64) -> Result<Self, FieldError> {
        config.validate()?;
        let pos_enc = FrequencyEncoding::new(
            3,
            &FrequencyEncodingConfig { n_frequencies: config.pos_frequencies, include_input: true },
        );
        let dir_enc = FrequencyEncoding::new(
            3,
            &FrequencyEncodingConfig { n_frequencies: config.dir_frequencies, include_input: true },
        );
        let pin = Encoding::<T>::output_dim(&pos_enc);
        let din = Encoding::<T>::output_dim(&dir_enc);
        let w = config.width;
        let mut rng = nerf_core::rng(seed, 0xF1E1D);
        // nerf-pytorch's `skips=[4]` (concatenate after layer 4) = MlpConfig's "layer 5 takes [x, h]".
        let trunk = Mlp::new(
            MlpConfig {
                input_dim: pin,
                output_dim: 1 + w,
                hidden_dim: w,
                hidden_layers: config.depth,
                hidden_activation: Activation::Relu,
                output_activation: Activation::None,
                skips: config.skips.iter().map(|s| s + 1).collect(),
                bias: true,
            },
            &mut rng,
        );
        let color = Mlp::new(
            MlpConfig {
                input_dim: w + din,
                output_dim: 3,
                hidden_dim: config.view_width,
                hidden_layers: 1,
                hidden_activation: Activation::Relu,
                output_activation: Activation::Sigmoid,
                skips: vec![],
                bias: true,
            },
            &mut rng,
        );
        Ok(Self { config, pos_enc, dir_enc, trunk, color, tape: Tape::default(), query_scratch: ScratchPool::new() })
    }

    /// The config.
    pub fn config(&self) -> &FreqNerfConfig {
        &self.config
    }

    /// Trainable scalars.
    pub fn n_params(&self) -> usize {
        self.trunk.n_params() + self.color.n_params()
    }

    /// Forward FLOPs per sample (multiply-adds × 2 of the three MLPs).
    pub fn flops_per_sample(&self) -> usize {
        self.trunk.flops_per_sample() + self.color.flops_per_sample()
    }

    fn pos_dim(&self) -> usize {
        Encoding::<T>::output_dim(&self.pos_enc)
    }
    fn dir_dim(&self) -> usize {
        Encoding::<T>::output_dim(&self.dir_enc)
    }

    /// Training forward over `n = positions.len()/3` samples; keeps the tape for [`Self::backward`].
    pub fn forward_t(&mut self, positions: &[T], dirs: &[T], sigma: &mut [T], rgb: &mut [T]) {
        let n = positions.len() / 3;
        assert_eq!(dirs.len(), 3 * n);
        assert_eq!(sigma.len(), n);
        assert_eq!(rgb.len(), 3 * n);
        let (pd, dd, w) = (self.pos_dim(), self.dir_dim(), self.config.width);
        let t = &mut self.tape;
        t.n = n;
        t.pos_in.clear();
        t.pos_in.extend_from_slice(positions);
        t.dir_in.clear();
        t.dir_in.extend_from_slice(dirs);
        t.pos_enc.resize(n * pd, T::zero());
        self.pos_enc.forward(positions, &mut t.pos_enc);
        let head_out = self.trunk.forward(n, &t.pos_enc, &mut t.trunk);
        // colour input = [feature, γ(d)]
        t.color_in.resize(n * (w + dd), T::zero());
        t.raw_sigma.resize(n, T::zero());
        t.dir_enc.resize(n * dd, T::zero());
        self.dir_enc.forward(dirs, &mut t.dir_enc);
        for k in 0..n {
            let row = &head_out[k * (1 + w)..(k + 1) * (1 + w)];
            t.raw_sigma[k] = row[0];
            sigma[k] = row[0].max(T::zero());
            let ci = &mut t.color_in[k * (w + dd)..(k + 1) * (w + dd)];
            ci[..w].copy_from_slice(&row[1..]);
            ci[w..].copy_from_slice(&t.dir_enc[k * dd..(k + 1) * dd]);
        }
        let out = self.color.forward(n, &t.color_in, &mut t.color);
        rgb.copy_from_slice(out);
    }

    /// Backward of the last [`Self::forward_t`]: accumulates parameter gradients.
    pub fn backward_t(&mut self, d_sigma: &[T], d_rgb: &[T]) {
        self.backward_inputs_t(d_sigma, d_rgb, None)
    }

    /// As [`Self::backward_t`], and with `inputs = Some((d_positions, d_dirs))` also writes the
    /// gradients in every sample's position and direction (`3·n` each;
    /// [`RadianceField::backward_with_inputs`]), through both frequency encodings.
    pub fn backward_inputs_t(&mut self, d_sigma: &[T], d_rgb: &[T], inputs: Option<(&mut [T], &mut [T])>) {
        let t = &mut self.tape;
        let n = t.n;
        assert_eq!(d_sigma.len(), n);
        assert_eq!(d_rgb.len(), 3 * n);
        let (dd, w) = (Encoding::<T>::output_dim(&self.dir_enc), self.config.width);
        t.d_color_in.resize(n * (w + dd), T::zero());
        self.color.backward(n, &t.color_in, &mut t.color, d_rgb, Some(&mut t.d_color_in));
        t.d_trunk.resize(n * (1 + w), T::zero());
        for (k, &ds) in d_sigma.iter().enumerate() {
            let dh = &mut t.d_trunk[k * (1 + w)..(k + 1) * (1 + w)];
            // σ = ReLU(raw): the gradient passes where raw > 0.
            dh[0] = if t.raw_sigma[k] > T::zero() { ds } else { T::zero() };
            dh[1..].copy_from_slice(&t.d_color_in[k * (w + dd)..k * (w + dd) + w]);
        }
        let Some((d_pos, d_dirs)) = inputs else {
            self.trunk.backward(n, &t.pos_enc, &mut t.trunk, &t.d_trunk, None);
            return;
        };
        let pd = Encoding::<T>::output_dim(&self.pos_enc);
        t.d_enc.resize(n * pd.max(dd), T::zero());
        self.trunk.backward(n, &t.pos_enc, &mut t.trunk, &t.d_trunk, Some(&mut t.d_enc[..n * pd]));
        self.pos_enc.backward(&t.pos_in, &t.d_enc[..n * pd], &mut [], Some(d_pos));
        for k in 0..n {
            let src = &t.d_color_in[k * (w + dd) + w..(k + 1) * (w + dd)];
            t.d_enc[k * dd..(k + 1) * dd].copy_from_slice(src);
        }
        self.dir_enc.backward(&t.dir_in, &t.d_enc[..n * dd], &mut [], Some(d_dirs));
    }

    /// Inference without a tape, chunked to bound memory.
    pub fn query_t(&self, positions: &[T], dirs: &[T], sigma: &mut [T], rgb: &mut [T]) {
        let n = positions.len() / 3;
        let (dd, w) = (self.dir_dim(), self.config.width);
        self.query_scratch.with(|s| {
            for c0 in (0..n).step_by(QUERY_CHUNK) {
                let c1 = (c0 + QUERY_CHUNK).min(n);
                let m = c1 - c0;
                let head = self.trunk_head(&positions[3 * c0..3 * c1], &mut s.pos_enc, &mut s.head, &mut s.mlp);
                let dir_enc = grown(&mut s.dir_enc, m * dd);
                self.dir_enc.forward(&dirs[3 * c0..3 * c1], dir_enc);
                let color_in = grown(&mut s.color_in, m * (w + dd));
                for k in 0..m {
                    let row = &head[k * (1 + w)..(k + 1) * (1 + w)];
                    sigma[c0 + k] = row[0].max(T::zero());
                    let ci = &mut color_in[k * (w + dd)..(k + 1) * (w + dd)];
                    ci[..w].copy_from_slice(&row[1..]);
                    ci[w..].copy_from_slice(&dir_enc[k * dd..(k + 1) * dd]);
                }
                self.color.infer(m, color_in, &mut s.mlp, &mut rgb[3 * c0..3 * c1]);
            }
        })
    }

    /// The trunk's inference on one chunk of positions: `m·(1 + width)` rows of raw σ and
    /// features, in `head` (grown to fit).
    fn trunk_head<'h>(&self, positions: &[T], pos_enc: &mut Vec<T>, head: &'h mut Vec<T>, mlp: &mut MlpScratch<T>) -> &'h [T] {
        let m = positions.len() / 3;
        let pos_enc = grown(pos_enc, m * self.pos_dim());
        self.pos_enc.forward(positions, pos_enc);
        let head = grown(head, m * (1 + self.config.width));
        self.trunk.infer(m, pos_enc, mlp, head);
        head
    }

    /// Density only, chunked.
    pub fn density_t(&self, positions: &[T], sigma: &mut [T]) {
        let n = positions.len() / 3;
        let w = self.config.width;
        self.query_scratch.with(|s| {
            for c0 in (0..n).step_by(QUERY_CHUNK) {
                let c1 = (c0 + QUERY_CHUNK).min(n);
                let m = c1 - c0;
                let head = self.trunk_head(&positions[3 * c0..3 * c1], &mut s.pos_enc, &mut s.head, &mut s.mlp);
                for k in 0..m {
                    sigma[c0 + k] = head[k * (1 + w)].max(T::zero());
                }
            }
        })
    }

    /// The two networks (trunk with σ/feature head, colour branch), mutable.
    pub fn networks_mut(&mut self) -> [&mut Mlp<T>; 2] {
        [&mut self.trunk, &mut self.color]
    }

    /// The two networks (trunk with σ/feature head, colour branch).
    pub fn networks(&self) -> [&Mlp<T>; 2] {
        [&self.trunk, &self.color]
    }
}

#[derive(Default)]
struct QueryScratch<T: Real> {
    pos_enc: Vec<T>,
    dir_enc: Vec<T>,
    head: Vec<T>,
    color_in: Vec<T>,
    mlp: MlpScratch<T>,
}

/// Group names of the two networks (stable: they key optimiser state and checkpoints).
pub const GROUP_NAMES: [&str; 2] = ["trunk", "color"];

impl RadianceField for FreqNerf<f32> {
    fn kind(&self) -> &'static str {
        "freq"
    }
    fn config(&self) -> serde_json::Value {
        serde_json::to_value(&self.config).expect("config serialises")
    }
    fn n_params(&self) -> usize {
        FreqNerf::n_params(self)
    }
    fn density(&self, positions: &[f32], sigma: &mut [f32]) {
        self.density_t(positions, sigma)
    }
    fn query(&self, positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
        self.query_t(positions, dirs, sigma, rgb)
    }
    fn forward(&mut self, positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
        self.forward_t(positions, dirs, sigma, rgb)
    }
    fn backward(&mut self, d_sigma: &[f32], d_rgb: &[f32]) {
        self.backward_t(d_sigma, d_rgb)
    }
    fn has_input_gradients(&self) -> bool {
        true
    }
    fn backward_with_inputs(
        &mut self,
        d_sigma: &[f32],
        d_rgb: &[f32],
        d_positions: &mut [f32],
        d_dirs: &mut [f32],
    ) -> Result<(), FieldError> {
        self.backward_inputs_t(d_sigma, d_rgb, Some((d_positions, d_dirs)));
        Ok(())
    }
    fn zero_grad(&mut self) {
        for m in self.networks_mut() {
            m.zero_grad();
        }
    }
    fn to_gpu(
        &self,
        ctx: &nerf_field::GpuContext,
        capacity: usize,
    ) -> Option<Result<Box<dyn nerf_field::GpuRadianceField>, FieldError>> {
        Some(gpu::GpuFreqNerf::new(self, ctx, capacity).map(|f| Box::new(f) as Box<dyn nerf_field::GpuRadianceField>))
    }
    fn param_groups(&mut self) -> Vec<ParamGroupMut<'_>> {
        let wd = self.config.weight_decay;
        self.networks_mut()
            .into_iter()
            .zip(GROUP_NAMES)
            .map(|(m, name)| {
                let (params, grads) = m.params_and_grads_mut();
                ParamGroupMut { name, params, grads, weight_decay: wd }
            })
            .collect()
    }
    fn export_params(&self) -> Vec<(String, Vec<f32>)> {
        self.networks()
            .into_iter()
            .zip(GROUP_NAMES)
            .map(|(m, name)| (name.to_string(), m.params().to_vec()))
            .collect()
    }
}

/// Registry constructor: `config` is a (possibly partial) [`FreqNerfConfig`] as JSON.
pub fn build(
    config: &serde_json::Value,
    ctx: &FieldContext,
) -> Result<Box<dyn RadianceField>, FieldError> {
    let cfg: FreqNerfConfig = config_from_json("freq", config)?;
    Ok(Box::new(FreqNerf::<f32>::new(cfg, ctx.seed)?))
}

/// Registry default config.
pub fn default_config() -> serde_json::Value {
    serde_json::to_value(FreqNerfConfig::default()).expect("config serialises")
}
