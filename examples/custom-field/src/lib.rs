//! A radiance field written outside nerf-rs, against its public API only: the worked example of
//! docs/adding-a-field.md for a field that lives in a crate of its own. It depends on the facade
//! `nerf` (the parts, the `RadianceField` trait, the registry) and on `nerf_cli`, whose
//! `main_with` gives its binary, `nerf-plenoxels`, every command of `nerf` for the new field.
//!
//! The field is in the style of Plenoxels (Fridovich-Keil et al. 2022, "Plenoxels: Radiance
//! Fields without Neural Networks"): a voxel grid holding a density and, per colour channel,
//! spherical-harmonics coefficients, trilinearly interpolated; no network at all.
//!
//! - density: `σ = softplus(s·d(x) + shift) / voxel_size`, DVGO's activation (as the `voxel`
//!   field): with `shift = ln(1/(1−alpha_init) − 1)` a one-voxel step starts with opacity
//!   `alpha_init`, so the field starts empty, and σ is smooth where Plenoxels' ReLU has a kink;
//! - colour: `rgb_c = sigmoid(s · Σ_l k_{c,l}(x) · Y_l(dir))` over the `degree²` real spherical
//!   harmonics `Y_l` of [`nerf::encoding::SphericalHarmonics`] (instant-ngp's convention; degree
//!   3 gives Plenoxels' 9 coefficients per channel);
//! - both grids are [`nerf::encoding::DenseGrid`]s read as `s ×` their stored values: under Adam
//!   that is a learning rate `s×` the trainer's (Plenoxels trains its grids with large rates).
//!
//! What it leaves out of Plenoxels: the sparse grid and its coarse-to-fine pruning (this grid is
//! dense, so memory grows as `resolution³`), the total-variation and sparsity losses, and RMSProp.
//!
//! It trains and renders on a GPU too: [`gpu::GpuPlenoxels`] composes nerf-rs's public GPU parts
//! with one WGSL file of this crate's (`shaders/plenoxels.wgsl`), returned by
//! [`RadianceField::to_gpu`].

pub mod gpu;

use nerf::core::Real;
use nerf::encoding::{DenseGrid, Encoding, ShConfig, SphericalHarmonics};
use nerf::field::{config_from_json, FieldContext, FieldError, ParamGroupMut, RadianceField, RegistryEntry};
use serde::{Deserialize, Serialize};

/// The registry name of the field.
pub const NAME: &str = "plenoxels";

/// Group names (stable: they key optimiser state and checkpoints).
pub const GROUP_NAMES: [&str; 2] = ["density_grid", "sh_grid"];

/// Configuration; every hyper-parameter is a key, so an ablation is a config file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PlenoxelsConfig {
    /// Cells per axis of both grids (`resolution + 1` vertices per axis), 1..=1024.
    pub resolution: usize,
    /// Spherical-harmonics bands, 1..=4: `degree²` coefficients per colour channel (1: colour
    /// independent of the view; 3: Plenoxels' 9).
    pub sh_degree: u32,
    /// Opacity of a one-voxel step at initialisation, in `(0, 1)`.
    pub alpha_init: f64,
    /// The scale `s` at which both grids' stored values are read (their learning-rate multiplier
    /// under Adam), `> 0`.
    pub grid_lr_scale: f64,
}

impl Default for PlenoxelsConfig {
    fn default() -> Self {
        // 65³ vertices × (1 + 3·4) channels: 3.6 M parameters. On the in-repo 100×100 scene a
        // grid of 128 cells scored 4.3 dB lower after 90 s (docs/results.md): without Plenoxels'
        // total-variation loss, voxels seen by few pixels are left free. Raise it for larger images.
        Self { resolution: 64, sh_degree: 2, alpha_init: 1e-6, grid_lr_scale: 30.0 }
    }
}

/// What the last training forward keeps for its backward.
#[derive(Default)]
struct Tape<T: Real> {
    xn: Vec<T>,
    dens: Vec<T>,
    coef: Vec<T>,
    sh: Vec<T>,
    rgb: Vec<T>,
    d_dens: Vec<T>,
    d_coef: Vec<T>,
}

/// The Plenoxels-style field, generic over the scalar so that its backward can be checked
/// against finite differences in `f64`; `Plenoxels<f32>` is the [`RadianceField`].
pub struct Plenoxels<T: Real> {
    config: PlenoxelsConfig,
    aabb_min: [T; 3],
    inv_extent: [T; 3],
    inv_voxel: T,
    shift: T,
    scale: T,
    sh: SphericalHarmonics,
    density_grid: DenseGrid<T>,
    density_grad: Vec<T>,
    sh_grid: DenseGrid<T>,
    sh_grad: Vec<T>,
    tape: Tape<T>,
    /// Tapes for `&self` queries (rendering calls them thousands of times per view).
    query_tapes: nerf::core::ScratchPool<Tape<T>>,
}

fn softplus<T: Real>(z: T) -> T {
    z.max(T::zero()) + (-z.abs()).exp().ln_1p()
}

fn sigmoid<T: Real>(z: T) -> T {
    T::one() / (T::one() + (-z).exp())
}

impl<T: Real> Plenoxels<T> {
    /// Builds the field over the context's scene box; a bad config is an error naming its key.
    pub fn new(config: PlenoxelsConfig, ctx: &FieldContext) -> Result<Self, FieldError> {
        let bad = |message: String| FieldError::InvalidConfig { field: NAME.into(), message };
        let c = &config;
        if !(c.alpha_init > 0.0 && c.alpha_init < 1.0) {
            return Err(bad(format!("alpha_init must be in (0, 1), got {}", c.alpha_init)));
        }
        if !(c.grid_lr_scale > 0.0 && c.grid_lr_scale.is_finite()) {
            return Err(bad(format!("grid_lr_scale must be finite and > 0, got {}", c.grid_lr_scale)));
        }
        let sh = SphericalHarmonics::try_new(&ShConfig { degree: c.sh_degree })
            .map_err(|_| bad(format!("sh_degree must be in 1..=4, got {}", c.sh_degree)))?;
        let mut inv_extent = [T::zero(); 3];
        let mut volume = 1.0f64;
        for a in 0..3 {
            let e = ctx.aabb_max[a] - ctx.aabb_min[a];
            if !(e.is_finite() && e > 0.0) {
                return Err(bad(format!("scene box has extent {e} on axis {a}")));
            }
            inv_extent[a] = T::one() / T::c(e as f64);
            volume *= e as f64;
        }
        let voxel_size = volume.cbrt() / c.resolution as f64;
        let mut rng = nerf::core::rng(ctx.seed, 0x706c_656e); // "plen"
        let grid = |channels, rng: &mut nerf::core::Rng| {
            // Small random values, not zeros: an exactly uniform density would leave every cell
            // of the trainer's occupancy grid at its mean, i.e. empty.
            DenseGrid::uniform(c.resolution, channels, 1e-4, rng).map_err(|e| bad(format!("resolution: {e}")))
        };
        let density_grid = grid(1, &mut rng)?;
        let sh_grid = grid(3 * Encoding::<T>::output_dim(&sh), &mut rng)?;
        Ok(Self {
            aabb_min: ctx.aabb_min.map(|v| T::c(v as f64)),
            inv_extent,
            inv_voxel: T::c(1.0 / voxel_size),
            shift: T::c((1.0 / (1.0 - c.alpha_init) - 1.0).ln()),
            scale: T::c(c.grid_lr_scale),
            sh,
            density_grad: vec![T::zero(); density_grid.params().len()],
            sh_grad: vec![T::zero(); sh_grid.params().len()],
            density_grid,
            sh_grid,
            tape: Tape::default(),
            query_tapes: nerf::core::ScratchPool::new(),
            config,
        })
    }

    /// The density grid (1 channel) and the coefficient grid (`3·degree²` channels, red's first).
    pub fn grids_mut(&mut self) -> [&mut DenseGrid<T>; 2] {
        [&mut self.density_grid, &mut self.sh_grid]
    }

    /// The gradients accumulated for the two grids.
    pub fn grid_grads(&self) -> [&[T]; 2] {
        [&self.density_grad, &self.sh_grad]
    }

    /// Coefficients per colour channel (`degree²`).
    fn n_coef(&self) -> usize {
        Encoding::<T>::output_dim(&self.sh)
    }

    /// Positions normalised to `[0, 1]³` by the scene box, clamped.
    fn normalise(&self, positions: &[T], xn: &mut Vec<T>) {
        xn.clear();
        xn.extend(positions.chunks_exact(3).flat_map(|p| {
            [0, 1, 2].map(|a| ((p[a] - self.aabb_min[a]) * self.inv_extent[a]).max(T::zero()).min(T::one()))
        }));
    }

    /// σ, and (with `dirs`) rgb, of `positions`, leaving what a backward needs in `t`.
    fn eval(&self, positions: &[T], dirs: Option<&[T]>, t: &mut Tape<T>, sigma: &mut [T], rgb: Option<&mut [T]>) {
        let n = positions.len() / 3;
        assert_eq!(sigma.len(), n, "Plenoxels: sigma length");
        self.normalise(positions, &mut t.xn);
        t.dens.resize(n, T::zero());
        self.density_grid.forward(&t.xn, &mut t.dens);
        for (s, &d) in sigma.iter_mut().zip(&t.dens) {
            *s = softplus(self.scale * d + self.shift) * self.inv_voxel;
        }
        let (Some(dirs), Some(rgb)) = (dirs, rgb) else { return };
        assert!(dirs.len() == 3 * n && rgb.len() == 3 * n, "Plenoxels: dirs / rgb length");
        let b = self.n_coef();
        t.coef.resize(n * 3 * b, T::zero());
        self.sh_grid.forward(&t.xn, &mut t.coef);
        t.sh.resize(n * b, T::zero());
        self.sh.forward(dirs, &mut t.sh);
        for ((out, k), y) in rgb.chunks_exact_mut(3).zip(t.coef.chunks_exact(3 * b)).zip(t.sh.chunks_exact(b)) {
            for (c, o) in out.iter_mut().enumerate() {
                let z = k[c * b..(c + 1) * b].iter().zip(y).fold(T::zero(), |acc, (&k, &y)| acc + k * y);
                *o = sigmoid(self.scale * z);
            }
        }
    }

    /// Training forward: σ and rgb, keeping the tape for [`Self::backward_t`].
    pub fn forward_t(&mut self, positions: &[T], dirs: &[T], sigma: &mut [T], rgb: &mut [T]) {
        let mut t = std::mem::take(&mut self.tape);
        self.eval(positions, Some(dirs), &mut t, sigma, Some(&mut *rgb));
        t.rgb.clear();
        t.rgb.extend_from_slice(rgb);
        self.tape = t;
    }

    /// Backward of the last training forward: accumulates both grids' gradients.
    pub fn backward_t(&mut self, d_sigma: &[T], d_rgb: &[T]) {
        let mut t = std::mem::take(&mut self.tape);
        let n = t.dens.len();
        assert!(d_sigma.len() == n && d_rgb.len() == 3 * n, "Plenoxels::backward: gradient lengths");
        let b = self.n_coef();
        t.d_dens.resize(n, T::zero());
        for ((o, &d), &g) in t.d_dens.iter_mut().zip(&t.dens).zip(d_sigma) {
            // softplus' = sigmoid.
            *o = g * self.scale * sigmoid(self.scale * d + self.shift) * self.inv_voxel;
        }
        t.d_coef.resize(n * 3 * b, T::zero());
        for (((dk, y), c), g) in
            t.d_coef.chunks_exact_mut(3 * b).zip(t.sh.chunks_exact(b)).zip(t.rgb.chunks_exact(3)).zip(d_rgb.chunks_exact(3))
        {
            for ch in 0..3 {
                // d rgb / d z = s · rgb (1 − rgb); d z / d k_l = Y_l.
                let dz = g[ch] * self.scale * c[ch] * (T::one() - c[ch]);
                for (o, &y) in dk[ch * b..(ch + 1) * b].iter_mut().zip(y) {
                    *o = dz * y;
                }
            }
        }
        self.density_grid.backward(&t.xn, &t.d_dens, &mut self.density_grad, None);
        self.sh_grid.backward(&t.xn, &t.d_coef, &mut self.sh_grad, None);
        self.tape = t;
    }

    /// Inference: σ and rgb, no tape kept.
    pub fn query_t(&self, positions: &[T], dirs: &[T], sigma: &mut [T], rgb: &mut [T]) {
        self.query_tapes.with(|t| self.eval(positions, Some(dirs), t, sigma, Some(rgb)));
    }

    /// Inference: σ only.
    pub fn density_t(&self, positions: &[T], sigma: &mut [T]) {
        self.query_tapes.with(|t| self.eval(positions, None, t, sigma, None));
    }
}

impl RadianceField for Plenoxels<f32> {
    fn kind(&self) -> &'static str {
        NAME
    }
    fn config(&self) -> serde_json::Value {
        serde_json::to_value(&self.config).expect("config serialises")
    }
    fn n_params(&self) -> usize {
        self.density_grad.len() + self.sh_grad.len()
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
    fn to_gpu(&self, ctx: &nerf::field::GpuContext, capacity: usize) -> Option<Result<Box<dyn nerf::field::GpuRadianceField>, FieldError>> {
        Some(gpu::GpuPlenoxels::new(self, ctx, capacity).map(|f| Box::new(f) as Box<dyn nerf::field::GpuRadianceField>))
    }
    fn zero_grad(&mut self) {
        self.density_grad.fill(0.0);
        self.sh_grad.fill(0.0);
    }
    fn param_groups(&mut self) -> Vec<ParamGroupMut<'_>> {
        vec![
            ParamGroupMut { name: GROUP_NAMES[0], params: self.density_grid.params_mut(), grads: &mut self.density_grad, weight_decay: 0.0 },
            ParamGroupMut { name: GROUP_NAMES[1], params: self.sh_grid.params_mut(), grads: &mut self.sh_grad, weight_decay: 0.0 },
        ]
    }
    fn export_params(&self) -> Vec<(String, Vec<f32>)> {
        vec![
            (GROUP_NAMES[0].into(), self.density_grid.params().to_vec()),
            (GROUP_NAMES[1].into(), self.sh_grid.params().to_vec()),
        ]
    }
}

/// Registry constructor: `config` is a (possibly partial) [`PlenoxelsConfig`] as JSON.
pub fn build(config: &serde_json::Value, ctx: &FieldContext) -> Result<Box<dyn RadianceField>, FieldError> {
    let config: PlenoxelsConfig = config_from_json(NAME, config)?;
    Ok(Box::new(Plenoxels::<f32>::new(config, ctx)?))
}

/// Registry default config.
pub fn default_config() -> serde_json::Value {
    serde_json::to_value(PlenoxelsConfig::default()).expect("config serialises")
}

/// The training recipe, a JSON patch over the trainer's config: the one nerf-rs's grid fields share
/// ([`nerf::field::grid_field_preset`]: occupancy-grid marching at step 5e-3, 2^16 samples per
/// step, random training backgrounds, Adam 1e-2 with β = (0.9, 0.99), ε = 1e-15, early ray
/// termination).
pub fn train_preset() -> serde_json::Value {
    nerf::field::grid_field_preset()
}

/// The registry entry: `registry.register(nerf_plenoxels::registry_entry())`.
pub fn registry_entry() -> RegistryEntry {
    RegistryEntry {
        name: NAME,
        description: "Plenoxels-style voxels: density + spherical-harmonics colour per vertex, no network (an out-of-tree example)",
        default_config,
        train_preset,
        build,
    }
}
