//! An Instant-NGP style radiance field (Müller et al. 2022): a multiresolution hash encoding of
//! position, a density MLP (one hidden layer of 64 → 16 outputs, σ = exp of the first with a
//! truncated gradient), spherical harmonics (degree 4) of the view direction, and a colour MLP
//! (two hidden layers of 64 on the 16 density outputs + 16 SH values → sigmoid rgb).
//!
//! Like the paper's field it is a composition of reusable parts — [`HashGrid`],
//! [`SphericalHarmonics`] and two [`Mlp`]s — generic over [`Real`] so the whole field is
//! finite-difference checked in `f64`. Positions are normalised to `[0,1]³` with the scene box of
//! the [`FieldContext`]. Its registry entry asks the trainer for instant-ngp's recipe
//! (occupancy-grid marching, samples-per-step batching, random backgrounds, Adam 1e-2 with
//! β = (0.9, 0.99), ε = 1e-15, L2 1e-6 on the MLP weights only, step decay): see
//! [`train_preset`].

pub mod gpu;

use nerf_core::{grown, Real, ScratchPool};
use nerf_encoding::{Encoding, HashGrid, HashGridConfig, ShConfig, SphericalHarmonics};
use nerf_field::{config_from_json, FieldContext, FieldError, ParamGroupMut, RadianceField};
use nerf_mlp::{Activation, Mlp, MlpConfig, MlpScratch, MlpTape};
use serde::{Deserialize, Serialize};

/// Configuration of the hash-grid field; every hyper-parameter is a key. Defaults: instant-ngp.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HashNerfConfig {
    /// The multiresolution hash encoding (L = 16, F = 2, T = 2^19, N_min = 16, N_max = 2048).
    pub grid: HashGridConfig,
    /// Spherical-harmonics degree of the direction encoding (4 → 16 values).
    pub sh_degree: u32,
    /// Outputs of the density MLP besides log-density (instant-ngp: 15, so 16 in all).
    pub geo_features: usize,
    /// Hidden width of the density MLP.
    pub density_hidden: usize,
    /// Hidden layers of the density MLP.
    pub density_layers: usize,
    /// Hidden width of the colour MLP.
    pub color_hidden: usize,
    /// Hidden layers of the colour MLP.
    pub color_layers: usize,
    /// Biases in the MLPs (tiny-cuda-nn's fully fused MLPs have none).
    pub mlp_bias: bool,
    /// L2 weight decay on the MLP weights (instant-ngp: 1e-6, the MLPs only).
    pub mlp_weight_decay: f32,
    /// L2 weight decay on the hash table's features (`wd·p` added to their gradient before Adam's
    /// moments; 0, the default, as in instant-ngp). Zip-NeRF decays its grid values (0.1 × the
    /// mean of their squares per level: ~2e-7 per entry of a hashed level of 2^19 × 2 features
    /// on this trainer's loss scale). With a dense Adam and ε = 1e-15 an entry that no sample
    /// touches for a while is pulled towards zero at about the learning rate per step. On lego
    /// at 400×400 it lowered the PSNR after 2000 steps: −0.62 dB at 2e-7, −2.25 dB at 2e-6
    /// (docs/results.md).
    pub grid_weight_decay: f32,
    /// How the MLP weights start: `xavier` (tiny-cuda-nn's fully fused MLPs, which instant-ngp
    /// and nerfacc train; the default since 2026-11-27) or `torch` (PyTorch's `nn.Linear`,
    /// HashNeRF-pytorch's field, the default before).
    pub mlp_init: MlpInit,
    /// `b` of `σ = exp(x + b)`, `x` the density MLP's first output (instant-ngp: 0; nerfacc's
    /// example: −1, so that a fresh field starts at σ ≈ e⁻¹ rather than 1). The colour MLP still
    /// sees `x` itself.
    pub density_bias: f32,
    /// What the colour MLP reads of the density MLP's outputs besides the direction encoding:
    /// `all` of them, the density logit `x` included (instant-ngp's `NerfNetwork`; the default),
    /// or the geometry `features` alone (nerfacc's `NGPRadianceField`, whose colour head reads
    /// the 15 features and not the logit), so that σ is shaped by the compositing alone.
    pub color_input: ColorInput,
    /// Which fully fused MLP kernels the GPU twin runs (ignored on the CPU): `plain` WGSL (every
    /// adapter) or `coop`erative matrices (tensor cores; adapters that offer them).
    pub gpu_mlp: GpuMlp,
    /// GPU twin, training on compacted samples (`compact_samples`) with the plain MLP kernels
    /// (ignored elsewhere): the density pass keeps the density net's activations of every marched
    /// sample, and the training forward gathers the kept samples' from them instead of running
    /// the density net again. The same bits either way; this trades the density net's forward
    /// over the kept samples (and the density pass's head-only shortcut) for 4·Σ widths bytes
    /// per marched sample written and gathered. Off where that buffer would not fit a binding.
    /// Off by default: on the H100 running the density net again was faster (7.85 against
    /// 8.30 ms per step at 2^18 samples, docs/results.md); on lavapipe keeping them was.
    pub gpu_keep_density_activations: bool,
    /// GPU twin, training on compacted samples (ignored elsewhere): the density pass over the
    /// marched samples, which runs in chunks of the training batch's capacity, reads each chunk's
    /// positions and writes its σ, encodings (and activations) in place, its kernels binding the
    /// marched buffers at the chunk's offset, instead of copying every chunk after the first
    /// through buffers of its own (`copy_rows`: 12 B in, 4 + 128 B out per sample). On by
    /// default; it applies where the chunk's offsets meet the adapter's storage offset alignment
    /// (a capacity that is a multiple of 64 samples on every adapter). `false` keeps the copies
    /// (an A/B of the two, docs/gpu.md).
    pub gpu_density_in_place: bool,
    /// GPU twin (ignored on the CPU): the hash table's backward sums the additions of its dense
    /// (coarse) levels over each subgroup before the atomics, on adapters with subgroups and
    /// float atomics ([`nerf_gpu::encoding::AtomicMode::SubgroupSums`]). Unset (the default since
    /// 2026-11-27): on for hardware adapters, off for software ones. On the H100 the table's
    /// backward took 0.72 against 1.12 ms per step of 2^18 samples (42.0 against 39.4 M trained
    /// samples/s on the in-repo scene); on lavapipe, whose atomics do not contend, it is slower
    /// (docs/results.md). `true` or `false` chooses on every adapter.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu_hash_subgroup_sums: Option<bool>,
    /// CPU only: both MLPs compute as tiny-cuda-nn's half-precision fully fused MLPs do, with
    /// this loss scale ([`Mlp::set_f16_arithmetic`]: inputs, weights and every layer's output
    /// rounded to f16; the backward scaled, rounded at each layer and unscaled after). tiny-cuda-nn's
    /// PyTorch bindings scale by 128. Unset (the default): the MLPs compute in full precision. The
    /// GPU field refuses it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mlp_f16_scale: Option<f32>,
}

/// How the hash field's MLP weights start ([`HashNerfConfig::mlp_init`]). Biases, where
/// `mlp_bias` asks for them, keep PyTorch's bound either way.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MlpInit {
    /// U(±1/√fan_in), PyTorch's `nn.Linear`.
    Torch,
    /// U(±√(6 / (fan_in + fan_out))) with both widths rounded up to a multiple of 16, as
    /// tiny-cuda-nn pads its fully fused MLPs (Xavier-uniform on the padded matrices). For the
    /// default nets that is 1.4× (first layer), 1.7× (hidden) and 2.2× (output layer) PyTorch's
    /// bound. On lego at 400×400 it scored 0.13 and 0.59 dB above `Torch` after 2000 steps
    /// (seeds 0 and 1, docs/results.md).
    #[default]
    Xavier,
}

impl MlpInit {
    /// Draws the weights of every layer of `mlp` again under this rule (`Torch` leaves them).
    fn apply<T: Real>(self, mlp: &mut Mlp<T>, rng: &mut nerf_core::Rng) {
        if self == MlpInit::Torch {
            return;
        }
        use rand::Rng;
        let pad = |n: usize| n.div_ceil(16) * 16;
        for ((fan_in, out), (w, _)) in mlp.layer_shapes().into_iter().zip(mlp.layer_offsets()) {
            let bound = (6.0 / (pad(fan_in) + pad(out)) as f64).sqrt();
            for p in &mut mlp.params_mut()[w..w + fan_in * out] {
                *p = T::c((2.0 * rng.gen::<f64>() - 1.0) * bound);
            }
        }
    }
}

/// What the hash field's colour MLP reads of the density MLP's outputs
/// ([`HashNerfConfig::color_input`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ColorInput {
    /// All `1 + geo_features` outputs, the density logit first (instant-ngp).
    #[default]
    All,
    /// The `geo_features` outputs after the logit (nerfacc's example).
    Features,
}

impl ColorInput {
    /// The first density output that the colour MLP reads (0 or 1).
    pub fn feat_start(self) -> usize {
        match self {
            ColorInput::All => 0,
            ColorInput::Features => 1,
        }
    }
}

/// The fully fused MLP kernels of the hash field's GPU twin ([`HashNerfConfig::gpu_mlp`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GpuMlp {
    /// Plain WGSL, f32 (`shaders/mlp_fused.wgsl`).
    #[default]
    Plain,
    /// Cooperative matrices, f16 in, f32 accumulate (`shaders/mlp_fused_coop.wgsl`).
    Coop,
}

impl Default for HashNerfConfig {
    fn default() -> Self {
        Self {
            grid: HashGridConfig::default(),
            sh_degree: 4,
            geo_features: 15,
            density_hidden: 64,
            density_layers: 1,
            color_hidden: 64,
            color_layers: 2,
            mlp_bias: false,
            mlp_weight_decay: 1e-6,
            grid_weight_decay: 0.0,
            mlp_init: MlpInit::Xavier,
            density_bias: 0.0,
            color_input: ColorInput::All,
            gpu_mlp: GpuMlp::Plain,
            gpu_keep_density_activations: false,
            gpu_density_in_place: true,
            gpu_hash_subgroup_sums: None,
            mlp_f16_scale: None,
        }
    }
}

/// The gradient of σ = exp(x) is taken as exp(min(x, TRUNC)) (instant-ngp's `trunc_exp`), which
/// keeps early, very dense guesses from producing exploding updates.
const TRUNC: f64 = 15.0;
/// Forward clamp that keeps σ finite in f32.
const MAX_LOG_DENSITY: f64 = 80.0;

#[derive(Default)]
struct Tape<T: Real> {
    n: usize,
    xn: Vec<T>,
    enc: Vec<T>,
    sh: Vec<T>,
    /// The samples' directions (the SH backward of input gradients reads them).
    dirs: Vec<T>,
    color_in: Vec<T>,
    density: MlpTape<T>,
    color: MlpTape<T>,
    d_color_in: Vec<T>,
    d_sh: Vec<T>,
    d_density_out: Vec<T>,
    d_enc: Vec<T>,
}

/// The position encodings of the last [`HashNerf::density_for_training_t`], reused by
/// [`HashNerf::forward_rows_t`] while the parameters are unchanged.
#[derive(Default)]
struct DensityPass<T: Real> {
    enc: Vec<T>,
    n: usize,
    valid: bool,
    /// Kept between steps so the pass allocates nothing once warmed up.
    scratch: Scratch<T>,
}

#[derive(Default)]
struct Scratch<T: Real> {
    xn: Vec<T>,
    enc: Vec<T>,
    dout: Vec<T>,
    sh: Vec<T>,
    color_in: Vec<T>,
    mlp: MlpScratch<T>,
}

/// The Instant-NGP field.
pub struct HashNerf<T: Real> {
    config: HashNerfConfig,
    aabb_min: [T; 3],
    aabb_max: [f32; 3],
    inv_extent: [T; 3],
    grid: HashGrid<T>,
    grid_grad: Vec<T>,
    sh: SphericalHarmonics,
    density: Mlp<T>,
    color: Mlp<T>,
    tape: Tape<T>,
    density_pass: DensityPass<T>,
    /// Inference buffers of [`RadianceField::query`] / [`RadianceField::density`], which take
    /// `&self` and run on several threads at once while rendering: rendering's rounds allocate
    /// and zero nothing once every thread has had a set.
    query_scratch: ScratchPool<Scratch<T>>,
}

/// Samples per inference chunk of [`RadianceField::query`] / [`RadianceField::density`].
const QUERY_CHUNK: usize = 1 << 15;

impl<T: Real> HashNerf<T> {
    /// Builds the field over the context's scene box.
    pub fn new(config: HashNerfConfig, ctx: &FieldContext) -> Result<Self, FieldError> {
        let bad = |m: String| FieldError::InvalidConfig { field: "hash".into(), message: m };
        if !(1..=4).contains(&config.sh_degree) {
            return Err(bad(format!("sh_degree must be 1..=4, got {}", config.sh_degree)));
        }
        if !config.density_bias.is_finite() {
            return Err(bad(format!("density_bias must be finite, got {}", config.density_bias)));
        }
        for (key, wd) in [("mlp_weight_decay", config.mlp_weight_decay), ("grid_weight_decay", config.grid_weight_decay)] {
            if !(wd.is_finite() && wd >= 0.0) {
                return Err(bad(format!("{key} must be finite and >= 0, got {wd}")));
            }
        }
        if let Some(s) = config.mlp_f16_scale.filter(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(bad(format!("mlp_f16_scale must be finite and > 0, got {s}")));
        }
        if config.density_hidden == 0 || config.color_hidden == 0 {
            return Err(bad("MLP widths must be positive".into()));
        }
        let mut inv = [T::zero(); 3];
        for (a, inv_a) in inv.iter_mut().enumerate() {
            let e = ctx.aabb_max[a] - ctx.aabb_min[a];
            if !(e.is_finite() && e > 0.0) {
                return Err(bad(format!("scene box has extent {e} on axis {a}")));
            }
            *inv_a = T::one() / T::c(e as f64);
        }
        let mut rng = nerf_core::rng(ctx.seed, 0x4A54);
        let grid = HashGrid::<T>::try_new(&config.grid, &mut rng).map_err(|e| bad(e.to_string()))?;
        let sh = SphericalHarmonics::new(&ShConfig { degree: config.sh_degree });
        let enc_dim = Encoding::<T>::output_dim(&grid);
        let sh_dim = Encoding::<T>::output_dim(&sh);
        let dout = 1 + config.geo_features;
        let mlp = |input_dim, output_dim, hidden_dim, hidden_layers, output_activation| MlpConfig {
            input_dim,
            output_dim,
            hidden_dim,
            hidden_layers,
            hidden_activation: Activation::Relu,
            output_activation,
            skips: vec![],
            bias: config.mlp_bias,
        };
        let mut density = Mlp::try_new(
            mlp(enc_dim, dout, config.density_hidden, config.density_layers, Activation::None),
            &mut rng,
        )
        .map_err(|e| bad(e.to_string()))?;
        let mut color = Mlp::try_new(
            mlp(dout - config.color_input.feat_start() + sh_dim, 3, config.color_hidden, config.color_layers, Activation::Sigmoid),
            &mut rng,
        )
        .map_err(|e| bad(e.to_string()))?;
        // A stream of its own: `torch` keeps the draws it had before `xavier` existed.
        let mut init_rng = nerf_core::rng(ctx.seed, 0x4A55);
        config.mlp_init.apply(&mut density, &mut init_rng);
        config.mlp_init.apply(&mut color, &mut init_rng);
        density.set_f16_arithmetic(config.mlp_f16_scale);
        color.set_f16_arithmetic(config.mlp_f16_scale);
        let grid_grad = vec![T::zero(); Encoding::<T>::n_params(&grid)];
        Ok(Self {
            config,
            aabb_min: ctx.aabb_min.map(|v| T::c(v as f64)),
            aabb_max: ctx.aabb_max,
            inv_extent: inv,
            grid,
            grid_grad,
            sh,
            density,
            color,
            tape: Tape::default(),
            density_pass: DensityPass::default(),
            query_scratch: ScratchPool::new(),
        })
    }

    /// The config.
    pub fn config(&self) -> &HashNerfConfig {
        &self.config
    }

    /// The hash encoding.
    pub fn grid(&self) -> &HashGrid<T> {
        &self.grid
    }

    /// The hash encoding, mutable (tests, custom initialisation).
    pub fn grid_mut(&mut self) -> &mut HashGrid<T> {
        self.density_pass.valid = false;
        &mut self.grid
    }

    /// The density and colour MLPs.
    pub fn mlps(&self) -> [&Mlp<T>; 2] {
        [&self.density, &self.color]
    }

    /// The density and colour MLPs, mutable.
    pub fn mlps_mut(&mut self) -> [&mut Mlp<T>; 2] {
        self.density_pass.valid = false;
        [&mut self.density, &mut self.color]
    }

    /// Accumulated gradient of the hash table.
    pub fn grid_grad(&self) -> &[T] {
        &self.grid_grad
    }

    /// Trainable scalars.
    pub fn n_params(&self) -> usize {
        self.grid_grad.len() + self.density.n_params() + self.color.n_params()
    }

    fn normalise(&self, positions: &[T], xn: &mut Vec<T>) {
        xn.clear();
        xn.extend(positions.chunks_exact(3).flat_map(|p| {
            [0, 1, 2].map(|a| ((p[a] - self.aabb_min[a]) * self.inv_extent[a]).max(T::zero()).min(T::one()))
        }));
    }

    fn dout_dim(&self) -> usize {
        1 + self.config.geo_features
    }

    /// The first density output the colour MLP reads ([`HashNerfConfig::color_input`]).
    fn feat_start(&self) -> usize {
        self.config.color_input.feat_start()
    }

    /// Training forward; keeps the tape for [`Self::backward_t`].
    pub fn forward_t(&mut self, positions: &[T], dirs: &[T], sigma: &mut [T], rgb: &mut [T]) {
        let n = positions.len() / 3;
        let mut t = std::mem::take(&mut self.tape);
        self.normalise(positions, &mut t.xn);
        t.enc.resize(n * self.enc_dim(), T::zero());
        self.grid.forward(&t.xn, &mut t.enc);
        self.forward_from_encoding(t, dirs, sigma, rgb);
    }

    /// The density pass of a compacted step ([`RadianceField::density_for_training`]): σ as
    /// [`Self::density_t`], keeping every sample's position encoding for [`Self::forward_rows_t`].
    pub fn density_for_training_t(&mut self, positions: &[T], sigma: &mut [T]) {
        let mut pass = std::mem::take(&mut self.density_pass);
        pass.n = positions.len() / 3;
        pass.enc.resize(pass.n * self.enc_dim(), T::zero());
        // `density_t`'s code and chunks, so σ is the same bit for bit.
        self.infer(positions, None, sigma, None, Some(&mut pass.enc), &mut pass.scratch);
        pass.valid = true;
        self.density_pass = pass;
    }

    /// Training forward on samples `rows` of the last [`Self::density_for_training_t`]
    /// (`positions`, `dirs`: theirs, gathered): the encodings are gathered from that pass instead
    /// of recomputed. Falls back to [`Self::forward_t`] when the parameters changed since (an
    /// optimiser step, `param_groups`, `grid_mut`, `mlps_mut`). Panics on a row outside that pass.
    pub fn forward_rows_t(&mut self, rows: &[u32], positions: &[T], dirs: &[T], sigma: &mut [T], rgb: &mut [T]) {
        let n = positions.len() / 3;
        assert_eq!(rows.len(), n, "forward_rows: {} rows for {n} positions", rows.len());
        let pass = &self.density_pass;
        if !pass.valid {
            return self.forward_t(positions, dirs, sigma, rgb);
        }
        assert!(rows.iter().all(|&r| (r as usize) < pass.n), "forward_rows: a row beyond the density pass's {} samples", pass.n);
        let enc_dim = self.enc_dim();
        let mut t = std::mem::take(&mut self.tape);
        self.normalise(positions, &mut t.xn);
        t.enc.resize(n * enc_dim, T::zero());
        {
            use rayon::prelude::*;
            let src = &pass.enc;
            t.enc.par_chunks_mut(enc_dim * 1024).zip(rows.par_chunks(1024)).for_each(|(dst, rows)| {
                for (d, &r) in dst.chunks_exact_mut(enc_dim).zip(rows) {
                    d.copy_from_slice(&src[r as usize * enc_dim..(r as usize + 1) * enc_dim]);
                }
            });
        }
        self.forward_from_encoding(t, dirs, sigma, rgb);
    }

    /// The rest of a training forward once `t.xn` and `t.enc` hold the samples' normalised
    /// positions and encodings; stores the tape.
    fn forward_from_encoding(&mut self, mut t: Tape<T>, dirs: &[T], sigma: &mut [T], rgb: &mut [T]) {
        let bias = T::c(self.config.density_bias as f64);
        let n = t.xn.len() / 3;
        assert_eq!(dirs.len(), 3 * n);
        let (dd, fs, sh_dim) = (self.dout_dim(), self.feat_start(), self.sh_dim());
        let w = dd - fs + sh_dim;
        t.n = n;
        let dout = self.density.forward(n, &t.enc, &mut t.density);
        t.sh.resize(n * sh_dim, T::zero());
        self.sh.forward(dirs, &mut t.sh);
        t.dirs.clear();
        t.dirs.extend_from_slice(dirs);
        t.color_in.resize(n * w, T::zero());
        for k in 0..n {
            let row = &dout[k * dd..(k + 1) * dd];
            sigma[k] = (row[0] + bias).min(T::c(MAX_LOG_DENSITY)).exp();
            color_input_row(row, fs, &t.sh[k * sh_dim..(k + 1) * sh_dim], &mut t.color_in[k * w..(k + 1) * w]);
        }
        rgb.copy_from_slice(self.color.forward(n, &t.color_in, &mut t.color));
        self.tape = t;
    }

    /// Backward of the last forward: accumulates gradients of the table and both MLPs.
    pub fn backward_t(&mut self, d_sigma: &[T], d_rgb: &[T]) {
        self.backward_inputs_t(d_sigma, d_rgb, None)
    }

    /// As [`Self::backward_t`], and with `inputs = Some((d_positions, d_dirs))` also writes the
    /// gradients in every sample's world position and direction (`3·n` each;
    /// [`RadianceField::backward_with_inputs`]). A position outside the box is clamped to it
    /// before the encoding, so its gradient across the clamped axis is 0.
    pub fn backward_inputs_t(&mut self, d_sigma: &[T], d_rgb: &[T], inputs: Option<(&mut [T], &mut [T])>) {
        let bias = T::c(self.config.density_bias as f64);
        let mut t = std::mem::take(&mut self.tape);
        let n = t.n;
        assert_eq!(d_sigma.len(), n);
        let (dd, fs, enc_dim, sh_dim) = (self.dout_dim(), self.feat_start(), self.enc_dim(), self.sh_dim());
        let (nf, w) = (dd - fs, dd - fs + sh_dim);
        t.d_color_in.resize(n * w, T::zero());
        // Without input gradients only the density features' columns of the colour net's input
        // gradient are read (the SH encoding has no parameters).
        let cols = if inputs.is_some() { w } else { nf };
        self.color.backward_cols(n, &t.color_in, &mut t.color, d_rgb, Some(&mut t.d_color_in), cols);
        t.d_density_out.resize(n * dd, T::zero());
        for (k, &ds) in d_sigma.iter().enumerate() {
            let dr = &mut t.d_density_out[k * dd..(k + 1) * dd];
            dr[..fs].fill(T::zero());
            dr[fs..].copy_from_slice(&t.d_color_in[k * w..k * w + nf]);
            // σ = exp(x + b) with a truncated gradient: dσ/dx := exp(min(x + b, TRUNC)); x is the
            // density net's first output, still on its tape.
            let x = t.density.output()[k * dd] + bias;
            dr[0] += ds * x.min(T::c(TRUNC)).exp();
        }
        t.d_enc.resize(n * enc_dim, T::zero());
        self.density.backward(n, &t.enc, &mut t.density, &t.d_density_out, Some(&mut t.d_enc));
        match inputs {
            None => self.grid.backward(&t.xn, &t.d_enc, &mut self.grid_grad, None),
            Some((d_pos, d_dirs)) => {
                assert_eq!(d_pos.len(), 3 * n);
                assert_eq!(d_dirs.len(), 3 * n);
                self.grid.backward(&t.xn, &t.d_enc, &mut self.grid_grad, Some(&mut *d_pos));
                // x_n = clamp((p − min)·inv_extent, 0, 1): a coordinate on the box's faces is
                // taken as clamped.
                for (g, xn) in d_pos.chunks_exact_mut(3).zip(t.xn.chunks_exact(3)) {
                    for a in 0..3 {
                        let inside = xn[a] > T::zero() && xn[a] < T::one();
                        g[a] = if inside { g[a] * self.inv_extent[a] } else { T::zero() };
                    }
                }
                t.d_sh.resize(n * sh_dim, T::zero());
                for k in 0..n {
                    let row = &t.d_color_in[k * w + nf..(k + 1) * w];
                    t.d_sh[k * sh_dim..(k + 1) * sh_dim].copy_from_slice(row);
                }
                let mut no_params: [T; 0] = [];
                self.sh.backward(&t.dirs, &t.d_sh, &mut no_params, Some(d_dirs));
            }
        }
        self.tape = t;
    }

    fn enc_dim(&self) -> usize {
        Encoding::<T>::output_dim(&self.grid)
    }
    fn sh_dim(&self) -> usize {
        Encoding::<T>::output_dim(&self.sh)
    }

    /// Inference without a tape, chunked. `dirs = None` computes density only.
    /// `keep_enc` (`n·enc_dim`), when given, receives the position encodings (the density pass of
    /// a compacted step keeps them); otherwise they live in `s` one chunk at a time.
    fn infer(
        &self,
        positions: &[T],
        dirs: Option<&[T]>,
        sigma: &mut [T],
        mut rgb: Option<&mut [T]>,
        mut keep_enc: Option<&mut [T]>,
        s: &mut Scratch<T>,
    ) {
        let bias = T::c(self.config.density_bias as f64);
        let n = positions.len() / 3;
        let (dd, fs, enc_dim, sh_dim) = (self.dout_dim(), self.feat_start(), self.enc_dim(), self.sh_dim());
        let w = dd - fs + sh_dim;
        for c0 in (0..n).step_by(QUERY_CHUNK) {
            let c1 = (c0 + QUERY_CHUNK).min(n);
            let m = c1 - c0;
            self.normalise(&positions[3 * c0..3 * c1], &mut s.xn);
            let enc = match keep_enc.as_deref_mut() {
                Some(e) => &mut e[c0 * enc_dim..c1 * enc_dim],
                None => grown(&mut s.enc, m * enc_dim),
            };
            self.grid.forward(&s.xn, enc);
            let dout = grown(&mut s.dout, m * dd);
            self.density.infer(m, enc, &mut s.mlp, dout);
            for k in 0..m {
                sigma[c0 + k] = (dout[k * dd] + bias).min(T::c(MAX_LOG_DENSITY)).exp();
            }
            if let (Some(dirs), Some(rgb)) = (dirs, rgb.as_deref_mut()) {
                let sh = grown(&mut s.sh, m * sh_dim);
                self.sh.forward(&dirs[3 * c0..3 * c1], sh);
                let color_in = grown(&mut s.color_in, m * w);
                for k in 0..m {
                    color_input_row(&dout[k * dd..(k + 1) * dd], fs, &sh[k * sh_dim..(k + 1) * sh_dim], &mut color_in[k * w..(k + 1) * w]);
                }
                self.color.infer(m, color_in, &mut s.mlp, &mut rgb[3 * c0..3 * c1]);
            }
        }
    }

    /// Inference: σ and rgb.
    pub fn query_t(&self, positions: &[T], dirs: &[T], sigma: &mut [T], rgb: &mut [T]) {
        self.query_scratch.with(|s| self.infer(positions, Some(dirs), sigma, Some(rgb), None, s))
    }

    /// Density only.
    pub fn density_t(&self, positions: &[T], sigma: &mut [T]) {
        self.query_scratch.with(|s| self.infer(positions, None, sigma, None, None, s))
    }
}

/// One sample's colour-net input: the density net's outputs from `feat_start` on, then the
/// direction's SH encoding.
fn color_input_row<T: Copy>(dout: &[T], feat_start: usize, sh: &[T], out: &mut [T]) {
    let nf = dout.len() - feat_start;
    out[..nf].copy_from_slice(&dout[feat_start..]);
    out[nf..].copy_from_slice(sh);
}

/// Group names (stable: they key optimiser state and checkpoints).
pub const GROUP_NAMES: [&str; 3] = ["hash_grid", "density_mlp", "color_mlp"];

impl HashNerfConfig {
    /// L2 weight decay of each parameter group, in [`GROUP_NAMES`] order (the CPU field's groups
    /// and its GPU twin's).
    pub fn group_weight_decays(&self) -> [f32; 3] {
        [self.grid_weight_decay, self.mlp_weight_decay, self.mlp_weight_decay]
    }
}

impl RadianceField for HashNerf<f32> {
    fn kind(&self) -> &'static str {
        "hash"
    }
    fn config(&self) -> serde_json::Value {
        serde_json::to_value(&self.config).expect("config serialises")
    }
    fn n_params(&self) -> usize {
        HashNerf::n_params(self)
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
    fn density_for_training(&mut self, positions: &[f32], sigma: &mut [f32]) {
        self.density_for_training_t(positions, sigma)
    }
    fn forward_rows(&mut self, rows: &[u32], positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
        self.forward_rows_t(rows, positions, dirs, sigma, rgb)
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
    fn to_gpu(
        &self,
        ctx: &nerf_field::GpuContext,
        capacity: usize,
    ) -> Option<Result<Box<dyn nerf_field::GpuRadianceField>, FieldError>> {
        Some(gpu::GpuHashNerf::new(self, ctx, capacity).map(|f| Box::new(f) as Box<dyn nerf_field::GpuRadianceField>))
    }
    fn zero_grad(&mut self) {
        use rayon::prelude::*;
        self.grid_grad.par_chunks_mut(1 << 16).for_each(|c| c.fill(0.0));
        self.density.zero_grad();
        self.color.zero_grad();
    }
    fn after_optimizer_step(&mut self) {
        self.density_pass.valid = false;
        self.grid.sync_storage();
    }
    fn param_groups(&mut self) -> Vec<ParamGroupMut<'_>> {
        self.density_pass.valid = false; // the caller may change the parameters
        let wd = self.config.group_weight_decays();
        let (dp, dg) = self.density.params_and_grads_mut();
        let (cp, cg) = self.color.params_and_grads_mut();
        vec![
            ParamGroupMut { name: GROUP_NAMES[0], params: self.grid.params_mut(), grads: &mut self.grid_grad, weight_decay: wd[0] },
            ParamGroupMut { name: GROUP_NAMES[1], params: dp, grads: dg, weight_decay: wd[1] },
            ParamGroupMut { name: GROUP_NAMES[2], params: cp, grads: cg, weight_decay: wd[2] },
        ]
    }
    fn export_params(&self) -> Vec<(String, Vec<f32>)> {
        vec![
            (GROUP_NAMES[0].into(), self.grid.params().to_vec()),
            (GROUP_NAMES[1].into(), self.density.params().to_vec()),
            (GROUP_NAMES[2].into(), self.color.params().to_vec()),
        ]
    }
}

/// Registry constructor: `config` is a (possibly partial) [`HashNerfConfig`] as JSON.
///
/// A config that leaves `grid.max_resolution` out gets the default scaled with the scene's box
/// ([`FieldContext::scene_scale`], instant-ngp's `aabb_scale`): instant-ngp's 2048 × `aabb_scale`,
/// the same resolution per unit of the scene in a larger box. [`RadianceField::config`] reports
/// the resolution used.
pub fn build(config: &serde_json::Value, ctx: &FieldContext) -> Result<Box<dyn RadianceField>, FieldError> {
    let mut cfg: HashNerfConfig = config_from_json("hash", config)?;
    if config.pointer("/grid/max_resolution").is_none() && ctx.scene_scale > 1.0 {
        let scaled = (cfg.grid.max_resolution as f64 * ctx.scene_scale as f64).round();
        cfg.grid.max_resolution = scaled.min(nerf_encoding::hash_grid::MAX_RESOLUTION as f64) as u32;
    }
    Ok(Box::new(HashNerf::<f32>::new(cfg, ctx)?))
}

/// Registry default config.
pub fn default_config() -> serde_json::Value {
    serde_json::to_value(HashNerfConfig::default()).expect("config serialises")
}

/// The training recipe of instant-ngp, adapted to a CPU: a JSON patch over the trainer's config,
/// the grid fields' [`nerf_field::grid_field_preset`] (occupancy-grid marching, 2^16 samples per
/// step, random training backgrounds, Adam 1e-2 with instant-ngp's β and ε, step decay over 20k
/// steps, early ray termination) and two keys of its own:
///
/// - rendering with an exponential moving average of the weights (decay 0.95, tiny-cuda-nn's `Ema`:
///   +0.4 dB on the in-repo scene after ~800 CPU steps, docs/results.md);
/// - training on compacted samples (`compact_samples`: a density pass over every marched sample,
///   forward and backward only on those before the early stop at transmittance 1e-4, the 2^16
///   target counting these): +0.51 / +0.42 dB on lego at 400×400 after 5 CPU minutes (2 seeds,
///   docs/results.md).
///
/// The loss stays the MSE: instant-ngp's Huber loss (`loss = { kind = "huber", delta = 0.1 }`)
/// helped on the in-repo scene but cost 0.43 dB on lego at 400×400 after 5 CPU minutes
/// (docs/results.md).
pub fn train_preset() -> serde_json::Value {
    let mut preset = nerf_field::grid_field_preset();
    nerf_field::merge_json(&mut preset, &serde_json::json!({ "compact_samples": true, "ema_decay": 0.95 }));
    preset
}
