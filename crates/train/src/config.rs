//! Training configuration: plain serde data that round-trips to JSON and TOML.

use nerf_data::{Background, ViewSelection};
use nerf_optim::{AdamConfig, LrSchedule};
use nerf_rays::{PixelConvention, PixelFilter};
use nerf_sampling::OccupancyGridConfig;
use serde::{Deserialize, Serialize};

/// How rays are turned into samples. Field-agnostic: the hierarchical sampler's coarse (proposal)
/// network is simply a second instance of the same field, queried through the same trait.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum SamplerConfig {
    /// `n_samples` stratified samples per ray in [near, far], one field.
    Stratified {
        /// Samples per ray.
        n_samples: usize,
    },
    /// The paper's coarse-to-fine scheme: `n_coarse` stratified samples through a coarse field,
    /// then `n_fine` inverse-CDF samples from its weights; the fine field sees all of them.
    /// Both networks are trained, the loss is the sum of the two photometric losses.
    Hierarchical {
        /// Stratified samples per ray for the coarse field (paper: 64).
        n_coarse: usize,
        /// Importance samples per ray added for the fine field (paper: 128).
        n_fine: usize,
    },
    /// Instant-NGP: constant-step ray marching that skips cells an occupancy grid marks empty.
    /// The grid is kept up to date from the field's density query (every `grid.update_every` steps).
    Occupancy {
        /// The occupancy grid.
        #[serde(default)]
        grid: OccupancyGridConfig,
        /// Marching step along unit rays (world units); with a cone, the smallest step.
        step_size: f32,
        /// Upper bound on samples per ray.
        max_samples_per_ray: usize,
        /// instant-ngp's cone steps: the step at distance `t` is `clamp(t·cone_angle, step_size,
        /// 1024·step_size)` ([`nerf_sampling::Stepping`]); 0: constant steps. Left out, the scene
        /// picks it as instant-ngp does ([`SceneBounds::cone_angle`](crate::SceneBounds::cone_angle)):
        /// 1/256 in an instant-ngp box with `aabb_scale` > 1, 0 otherwise.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        cone_angle: Option<f32>,
    },
}

impl SamplerConfig {
    /// Number of field instances the sampler needs (hierarchical: coarse + fine).
    pub fn n_fields(&self) -> usize {
        match self {
            SamplerConfig::Stratified { .. } | SamplerConfig::Occupancy { .. } => 1,
            SamplerConfig::Hierarchical { .. } => 2,
        }
    }

    /// The occupancy sampler with its marching step set to `step` (for rendering a trained run
    /// with finer or coarser steps): the sample cap per ray grows in proportion to a finer step,
    /// so rays reach as far, and the grid's threshold scales with the step, so a restored grid
    /// marks the cells it marked in training (a cell is occupied when `σ·step` exceeds
    /// `min(threshold, mean σ·step)`). Errors for the other samplers and a step that is not
    /// positive and finite.
    pub fn with_step_size(&self, step: f32) -> Result<SamplerConfig, String> {
        if !(step.is_finite() && step > 0.0) {
            return Err(format!("the marching step must be positive, got {step}"));
        }
        match self {
            SamplerConfig::Occupancy { grid, step_size, max_samples_per_ray, cone_angle } => {
                let mut grid = grid.clone();
                grid.threshold *= step / step_size;
                let scale = (step_size / step).max(1.0);
                Ok(SamplerConfig::Occupancy {
                    grid,
                    step_size: step,
                    max_samples_per_ray: (*max_samples_per_ray as f32 * scale).ceil() as usize,
                    cone_angle: *cone_angle,
                })
            }
            _ => Err("only the occupancy sampler marches with a step".into()),
        }
    }
}

/// The photometric loss on the rendered colours ([`nerf_render::photometric_loss_grad`]). Logged
/// losses and PSNRs are the MSE's in either case.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum LossConfig {
    /// Mean squared error (the NeRF paper).
    #[default]
    Mse,
    /// instant-ngp's default for NeRF (`"loss": {"otype": "Huber"}`, its `huber_loss(·, 0.1) / 5`):
    /// the squared error for residuals up to `delta`, linear beyond.
    Huber {
        /// Residual where the loss turns linear (instant-ngp: 0.1).
        delta: f32,
    },
}

impl LossConfig {
    /// The Huber δ, `None` for the MSE.
    pub fn huber_delta(&self) -> Option<f32> {
        match self {
            LossConfig::Mse => None,
            LossConfig::Huber { delta } => Some(*delta),
        }
    }
}

/// Everything that defines a training run. Defaults are the paper's NeRF on Blender scenes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Registry name of the field (`freq`, …).
    pub field: String,
    /// The field's own config (partial JSON over its defaults; `null` = defaults).
    #[serde(skip_serializing_if = "serde_json::Value::is_null")]
    pub field_config: serde_json::Value,
    /// Sampling scheme.
    pub sampler: SamplerConfig,
    /// Rays per training step (paper: 1024). Ignored when `target_samples_per_step` is set.
    pub batch_rays: usize,
    /// Instant-NGP's batching: when set, the number of rays per step follows the running mean of
    /// samples per ray so that a step evaluates about this many samples (2^18 on a GPU); the
    /// first step assumes the sampler's maximum samples per ray.
    pub target_samples_per_step: Option<usize>,
    /// Maximum number of steps.
    pub iters: u64,
    /// Optional wall-clock budget for training, seconds (training stops at whichever comes first).
    pub time_budget_secs: Option<f64>,
    /// Learning-rate schedule (paper: 5e-4 → 5e-5 exponentially over 250k steps).
    pub lr: LrSchedule,
    /// Adam hyper-parameters.
    pub adam: AdamConfig,
    /// Photometric loss (default: MSE).
    pub loss: LossConfig,
    /// Exponential moving average of the parameters (instant-ngp / tiny-cuda-nn: `Ema` with decay
    /// 0.95 around Adam); `None` (the default) = off. When set, every Adam step also updates the
    /// debiased average of every parameter group ([`nerf_optim::Ema`]), and rendering (evaluation,
    /// novel views, `nerf eval`) uses the averaged weights, while training steps — and, unlike
    /// instant-ngp, whose grid update queries its inference network, the occupancy-grid density
    /// updates — keep using the raw weights. Must lie in (0, 1).
    pub ema_decay: Option<f32>,
    /// Weight λ of mip-NeRF 360's distortion loss on the last stage's weights (nerfacto: 0.002),
    /// added to the photometric loss as `λ · mean over rays of L_ray`, with distances normalised
    /// by the scene's depth range (`s = t / (far − near)`; `nerf_render::distortion_loss_grad`):
    /// it gathers each ray's weight into one short stretch, against floaters and haze. `None`
    /// (the default) = off. Must be positive.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion_loss: Option<f32>,
    /// Weight λ of depth supervision on every stage (`nerf_render::depth_loss_grad`): `λ · mean
    /// over rays of |expected depth − measured depth|`, the measured depth coming from the
    /// scene's depth maps (`Dataset::depths`: nerfstudio's `depth_file_path`, instant-ngp's
    /// `depth_path`, or a COLMAP folder's points, `LoadOptions::sfm_depth`) where a pixel has
    /// one. Distances are in the scene's units. `None` (the
    /// default) = off; set, the scene must have depth maps. Must be positive.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_loss: Option<f32>,
    /// Per-view affine colour correction (`[color_correction]`; `nerf_render::color_correct_forward`):
    /// a 3×3 matrix and an offset per training view, applied to what the field composited and
    /// learnt with the field, for captures whose exposure or white balance changes between photos
    /// (nerfstudio's appearance embeddings, instant-ngp's per-image exposure). Renders of novel
    /// views use the mean correction. `None` (the default) = off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub color_correction: Option<ColorCorrectionConfig>,
    /// Camera pose refinement (`[camera_optimizer]`; nerfstudio's camera optimizer in `SO3xR3`
    /// mode, `nerf_rays::pose`): a translation and a rotation per training view, applied to the
    /// view's rays and learnt with the field through its input gradients, for captures whose
    /// poses (from structure from motion) are a little off. Test views and novel views keep
    /// their poses. Needs a field with input gradients (`freq`, `hash`) and Euclidean
    /// rays (an LLFF scene with `ndc = false`). `None` (the default) = off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_optimizer: Option<CameraOptimizerConfig>,
    /// Background composited behind training rays (paper on Blender: white).
    pub train_background: Background,
    /// Background for evaluation (white, as the paper's numbers).
    pub eval_background: Background,
    /// Rays per pixel when the test views are rendered for evaluation: 1 (the default) through
    /// the pixel convention's point; `N > 1` averages `N` renders through fixed points spread
    /// over each pixel ([`nerf_rays::PixelConvention::sample_offsets`]), as instant-ngp scores its
    /// test views (8 per pixel). Pairs with `pixel_jitter`, whose field learns colours at points
    /// of the pixels, as the anti-aliased ground truth integrates them. Costs `N` renders per
    /// view; training is unchanged. (Left out of the serialised config at 1, so the configs of
    /// runs made before it existed keep their hashes.)
    #[serde(skip_serializing_if = "is_one")]
    pub eval_spp: u32,
    /// The pixel filter the `eval_spp` rays of a pixel are placed by
    /// ([`nerf_rays::PixelConvention::sample_offsets_filtered`]): the unit box (the default, left
    /// out of the serialised config) or the Blackman–Harris window of Blender's Cycles, the
    /// renderer of the NeRF synthetic scenes (`{ kind = "blackman_harris", width = 1.5 }`).
    /// Acts only with `eval_spp > 1`.
    #[serde(skip_serializing_if = "is_box")]
    pub eval_filter: PixelFilter,
    /// Marching step of every render of the run (the evaluations during and after training,
    /// `nerf eval`, `nerf render`), when it should differ from the training step (the occupancy
    /// sampler's `step_size`, which training keeps). Rendering at a finer step than the field was
    /// trained with resolves its surfaces better: rendered at half the trained step, the scaled
    /// lego runs of docs/results.md ("The marching step scaled with the pixels") gain 0.36–0.40 dB.
    /// The sample cap per ray grows with a finer step ([`SamplerConfig::with_step_size`]); the
    /// occupancy grid is the one training keeps. Needs the occupancy sampler. `None` (the
    /// default, left out of the serialised config) = the training step.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub render_step_size: Option<f32>,
    /// Pixel convention of ray generation.
    pub pixel_convention: PixelConvention,
    /// Training rays through a uniformly random point of their pixel instead of its centre, the
    /// target staying the pixel's colour (instant-ngp trains so, unless `snap_to_pixel_centers`):
    /// the field learns what the pixel integrates, as the anti-aliased ground truth does.
    /// Evaluation and rendering always use the pixel convention's point. Default off (the paper).
    pub pixel_jitter: bool,
    /// Jitter samples within their strata while training (paper: perturb = 1).
    pub perturb: bool,
    /// Train on compacted samples (instant-ngp): a density-only inference pass over every marched
    /// sample finds where each ray's transmittance falls below `transmittance_threshold`; the
    /// training forward and backward then run only on the samples before that point (those past
    /// it get zero weight and zero gradient anyway), and `target_samples_per_step` counts these
    /// trained samples, so a step takes more rays for the same backward work. Needs the
    /// occupancy sampler and a positive `transmittance_threshold`. Default off.
    pub compact_samples: bool,
    /// Stop compositing a ray once its transmittance falls below this (0 = never).
    pub transmittance_threshold: f32,
    /// Master seed: initialisation, ray batches and jitter all derive from it.
    pub seed: u64,
    /// Image downscale factor applied when loading (2 = nerf-pytorch half_res).
    pub downscale: u32,
    /// Forward-facing (LLFF) scenes are loaded in NeRF's normalised device coordinates (the
    /// paper's protocol, `nerf_data::LoadOptions::ndc`); `false` = Euclidean rays (nerf-pytorch's
    /// `--no_ndc`). Blender scenes ignore it. Serialised only when `false`, so the configs (and
    /// ablation hashes) of runs made before it existed are unchanged.
    #[serde(skip_serializing_if = "is_true")]
    pub ndc: bool,
    /// Photos taken through a lens with distortion are resampled to pinhole images when they
    /// load (`nerf_data::LoadOptions::undistort`); `false` (the default): they are kept as taken
    /// and their rays go through the lens. Serialised only when `true`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub undistort: bool,
    /// instant-ngp's `aabb_scale` for the scene in place of its transforms file's
    /// (`nerf_data::LoadOptions::aabb_scale`; `nerf train --aabb-scale`): the box of a capture
    /// whose content reaches past its cameras, without editing the file. Every later load of the
    /// run (evaluation, renders, exports) takes it too. `None` (the default, not serialised): the
    /// file's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aabb_scale: Option<f32>,
    /// nerfstudio's dataparser options for a capture's (or COLMAP folder's) poses
    /// (`nerf_data::LoadOptions::nerfstudio`; `[nerfstudio] orientation_method = "none"`, …;
    /// `nerf train --orientation-method …`): every later load of the run takes them too.
    /// nerfstudio's defaults (not serialised) unless set.
    #[serde(default, skip_serializing_if = "is_default_nerfstudio")]
    pub nerfstudio: nerf_data::NerfstudioOptions,
    /// How a scene without split files holds test views out (`nerf_data::Holdout`:
    /// `"interval:8"`, `"fraction:0.9"`, `"all"`, `"filename"`; `nerf train --holdout`), nerfstudio's
    /// `eval_mode`; every later load of the run takes it. `None` (the default, not serialised):
    /// every 8th view in the file's order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holdout: Option<nerf_data::Holdout>,
    /// Which loader reads the scene folder (`nerf_data::SceneFormat`: `"auto"`, `"transforms"`,
    /// `"llff"`, `"colmap"`; `nerf train --scene-format`); every later load of the run takes it.
    /// `"auto"` (the default, not serialised): by what the folder holds.
    #[serde(default, skip_serializing_if = "is_auto_format")]
    pub scene_format: nerf_data::SceneFormat,
    /// Which test views to evaluate on.
    pub test_views: ViewSelection,
    /// Log (and update the progress bar message) every this many steps.
    pub log_every: u64,
    /// Write a checkpoint every this many steps (0 = only at the end / on interrupt).
    pub checkpoint_every: u64,
    /// Score the field on a few test views during a run (nerfstudio's `steps_per_eval_image`),
    /// written to `history.jsonl` and the progress bar; `None` (the default): only at the end.
    /// Read by `nerf train` (the ablation runner has its own schedule, `[eval]`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub eval_every: Option<PeriodicEval>,
    /// Rays per rendering chunk during evaluation. On the CPU with the occupancy sampler the
    /// chunks render concurrently (each marched in rounds on one thread, the field's queries
    /// parallel inside); the image does not depend on the thread count.
    pub render_chunk_rays: usize,
    /// Time every compute pass of these training steps on the GPU (timestamp queries) and write
    /// the breakdown by stage and kernel to `gpu_profile.json` and `metrics.json`
    /// ([`crate::profile`]); `None` (the default) = off. Ignored, with a note, on the CPU path.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu_profile: Option<crate::profile::ProfileWindow>,
}

/// Evaluation during a run ([`TrainConfig::eval_every`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PeriodicEval {
    /// Score every this many steps (≥ 1). The time it takes is not training time: it counts
    /// neither against `time_budget_secs` nor in `wall_seconds`.
    pub steps: u64,
    /// Which of the run's test views ([`TrainConfig::test_views`]) to score (default
    /// `spread:4`: four, spread over them).
    #[serde(default = "default_eval_views")]
    pub views: ViewSelection,
    /// Also write each evaluation's renders, `<out>/progress/step_<step>/<view>.png` (the views
    /// as they looked at that step, as nerfstudio logs its evaluation images); default off.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub renders: bool,
}

fn default_eval_views() -> ViewSelection {
    ViewSelection::Spread(4)
}

/// Settings of the per-view colour correction ([`TrainConfig::color_correction`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ColorCorrectionConfig {
    /// Adam's learning rate for the corrections (constant; the field's schedule does not apply).
    #[serde(default = "default_color_lr")]
    pub lr: f32,
}

fn default_color_lr() -> f32 {
    1e-3
}

/// Settings of camera pose refinement ([`TrainConfig::camera_optimizer`]): nerfacto's schedule
/// shape and penalties, at a lower rate than its `1e-3 → 1e-4`. Measured on the in-repo lego
/// (docs/results.md, "Camera pose refinement"): each view's gradient comes from the few dozen
/// rays it has in a batch, and Adam turns that noise into steps of about a tenth of the rate;
/// at 10⁻³ the corrections wander by more than accurate poses are off, at 3·10⁻⁴ they still
/// undo moves of a degree or two within 1000 steps.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraOptimizerConfig {
    /// Adam's learning rate for the corrections at step 0 …
    pub lr: f32,
    /// … decaying exponentially to this at `decay_steps`, and constant after.
    pub lr_final: f32,
    /// Steps of the decay.
    pub decay_steps: u64,
    /// Weight of the mean over views of `‖τ_v‖` (the translations' length) added to the loss.
    pub trans_penalty: f32,
    /// Weight of the mean over views of `‖ω_v‖` (the rotations' angle) added to the loss.
    pub rot_penalty: f32,
    /// Steps before the corrections start to move (their learning rate is 0 until then, the
    /// schedule is not shifted): the first steps' field is too rough for its gradients to say
    /// where a camera is. Default 0.
    pub warmup_steps: u64,
}

impl Default for CameraOptimizerConfig {
    fn default() -> Self {
        Self { lr: 3e-4, lr_final: 3e-5, decay_steps: 5000, trans_penalty: 1e-2, rot_penalty: 1e-3, warmup_steps: 0 }
    }
}

impl CameraOptimizerConfig {
    /// The learning rate at `step`.
    pub fn lr_at(&self, step: u64) -> f32 {
        if step < self.warmup_steps {
            return 0.0;
        }
        let f = (step as f64 / self.decay_steps.max(1) as f64).min(1.0);
        (self.lr as f64 * (self.lr_final as f64 / self.lr as f64).powf(f)) as f32
    }
}

impl Default for ColorCorrectionConfig {
    fn default() -> Self {
        Self { lr: default_color_lr() }
    }
}

/// Whether the scene format is told by the folder (left out of a serialised config).
fn is_auto_format(f: &nerf_data::SceneFormat) -> bool {
    *f == nerf_data::SceneFormat::Auto
}

/// Whether the dataparser options are nerfstudio's defaults (left out of a serialised config).
fn is_default_nerfstudio(o: &nerf_data::NerfstudioOptions) -> bool {
    *o == nerf_data::NerfstudioOptions::default()
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            field: "freq".into(),
            field_config: serde_json::Value::Null,
            sampler: SamplerConfig::Hierarchical { n_coarse: 64, n_fine: 128 },
            batch_rays: 1024,
            target_samples_per_step: None,
            iters: 200_000,
            time_budget_secs: None,
            lr: LrSchedule::Exponential { lr0: 5e-4, lr1: 5e-5, steps: 250_000 },
            adam: AdamConfig::default(),
            loss: LossConfig::Mse,
            ema_decay: None,
            distortion_loss: None,
            depth_loss: None,
            color_correction: None,
            camera_optimizer: None,
            train_background: Background::White,
            eval_background: Background::White,
            eval_spp: 1,
            eval_filter: PixelFilter::Box,
            render_step_size: None,
            pixel_convention: PixelConvention::Center,
            pixel_jitter: false,
            perturb: true,
            compact_samples: false,
            transmittance_threshold: 0.0,
            seed: 0,
            downscale: 1,
            ndc: true,
            undistort: false,
            aabb_scale: None,
            nerfstudio: nerf_data::NerfstudioOptions::default(),
            holdout: None,
            scene_format: nerf_data::SceneFormat::Auto,
            test_views: ViewSelection::Every(8),
            log_every: 100,
            checkpoint_every: 1000,
            eval_every: None,
            render_chunk_rays: 4096,
            gpu_profile: None,
        }
    }
}

/// The most rays per pixel `eval_spp` allows.
pub const MAX_EVAL_SPP: u32 = 256;

fn is_box(f: &PixelFilter) -> bool {
    *f == PixelFilter::Box
}

fn is_one(n: &u32) -> bool {
    *n == 1
}

fn is_true(b: &bool) -> bool {
    *b
}

impl TrainConfig {
    /// How this run's scene loads: its downscale, ray space, lens handling and box, with `views`
    /// of the split, only the cameras where `cameras_only`, and the SfM points' depths where
    /// `sfm_depth`.
    pub fn load_options(&self, views: ViewSelection, cameras_only: bool, sfm_depth: bool) -> nerf_data::LoadOptions {
        nerf_data::LoadOptions {
            downscale: self.downscale,
            views,
            ndc: self.ndc,
            cameras_only,
            sfm_depth,
            undistort: self.undistort,
            aabb_scale: self.aabb_scale,
            nerfstudio: self.nerfstudio,
            holdout: self.holdout,
            format: self.scene_format,
        }
    }

    /// The config a trainer that only renders a run needs: without the parts that act on the
    /// training photos alone (`camera_optimizer`: the corrections belong to the training views
    /// and renders use the cameras as given, and its per-step buffers are not needed). Its
    /// checkpoint restores into such a trainer (the `camera/…` entries are skipped).
    pub fn for_rendering(&self) -> TrainConfig {
        TrainConfig { camera_optimizer: None, ..self.clone() }
    }

    /// The marching of renders: the occupancy sampler with its step set to
    /// [`render_step_size`](Self::render_step_size) when that is set
    /// ([`SamplerConfig::with_step_size`]), the training sampler otherwise.
    pub fn render_sampler(&self) -> Result<SamplerConfig, String> {
        match self.render_step_size {
            None => Ok(self.sampler.clone()),
            Some(s) => self.sampler.with_step_size(s).map_err(|e| format!("render_step_size = {s}: {e}")),
        }
    }

    /// Checks values that would make a run meaningless.
    pub fn validate(&self) -> Result<(), String> {
        self.lr.validate()?;
        if let Some(s) = self.aabb_scale.filter(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(format!("aabb_scale {s}: must be finite and above 0"));
        }
        self.nerfstudio.validate().map_err(|e| format!("nerfstudio.{e}"))?;
        if self.batch_rays == 0 {
            return Err("batch_rays must be positive".into());
        }
        match self.sampler {
            SamplerConfig::Stratified { n_samples: 0 } => {
                return Err("sampler.n_samples must be positive".into())
            }
            SamplerConfig::Hierarchical { n_coarse, .. } if n_coarse < 2 => {
                return Err("sampler.n_coarse must be at least 2".into())
            }
            SamplerConfig::Occupancy { step_size, max_samples_per_ray, cone_angle, .. } => {
                if let Some(cone_angle) = cone_angle.filter(|c| !(c.is_finite() && *c >= 0.0)) {
                    return Err(format!("sampler.cone_angle must be finite and not negative, got {cone_angle}"));
                }
                if !(step_size.is_finite() && step_size > 0.0) {
                    return Err(format!("sampler.step_size must be positive, got {step_size}"));
                }
                if max_samples_per_ray == 0 {
                    return Err("sampler.max_samples_per_ray must be positive".into());
                }
            }
            _ => {}
        }
        if self.target_samples_per_step == Some(0) {
            return Err("target_samples_per_step must be positive".into());
        }
        if self.downscale == 0 {
            return Err("downscale must be at least 1".into());
        }
        if self.render_chunk_rays == 0 {
            return Err("render_chunk_rays must be positive".into());
        }
        if let Some(e) = &self.eval_every {
            if e.steps == 0 {
                return Err("eval_every.steps must be at least 1".into());
            }
            e.views.indices(1).map_err(|r| format!("eval_every.views: {r}"))?;
        }
        if let Some(d) = self.ema_decay {
            if !(d > 0.0 && d < 1.0) {
                return Err(format!("ema_decay must lie strictly between 0 and 1 (instant-ngp: 0.95), got {d}"));
            }
        }
        if let Some(c) = &self.color_correction {
            if !(c.lr.is_finite() && c.lr > 0.0) {
                return Err(format!("color_correction.lr must be a positive number, got {}", c.lr));
            }
        }
        if let Some(c) = &self.camera_optimizer {
            if !(c.lr.is_finite() && c.lr > 0.0 && c.lr_final.is_finite() && c.lr_final > 0.0) {
                return Err(format!("camera_optimizer.lr and lr_final must be positive numbers, got {} and {}", c.lr, c.lr_final));
            }
            if !(c.trans_penalty.is_finite() && c.trans_penalty >= 0.0 && c.rot_penalty.is_finite() && c.rot_penalty >= 0.0) {
                return Err(format!(
                    "camera_optimizer.trans_penalty and rot_penalty must be numbers ≥ 0, got {} and {}",
                    c.trans_penalty, c.rot_penalty
                ));
            }
        }
        if let Some(l) = self.distortion_loss {
            if !(l.is_finite() && l > 0.0) {
                return Err(format!("distortion_loss must be a positive number (nerfacto: 0.002), got {l}"));
            }
        }
        if let Some(l) = self.depth_loss {
            if !(l.is_finite() && l > 0.0) {
                return Err(format!("depth_loss must be a positive number, got {l}"));
            }
        }
        if let Some(d) = self.loss.huber_delta() {
            if !(d.is_finite() && d > 0.0) {
                return Err(format!("loss.delta must be a positive number (instant-ngp: 0.1), got {d}"));
            }
        }
        if self.compact_samples {
            if !matches!(self.sampler, SamplerConfig::Occupancy { .. }) {
                return Err("compact_samples needs the occupancy sampler (sampler.kind = \"occupancy\")".into());
            }
            if self.transmittance_threshold.is_nan() || self.transmittance_threshold <= 0.0 {
                return Err(format!(
                    "compact_samples needs a positive transmittance_threshold (instant-ngp: 1e-4), got {}",
                    self.transmittance_threshold
                ));
            }
        }
        if !(1..=MAX_EVAL_SPP).contains(&self.eval_spp) {
            return Err(format!("eval_spp must be 1..={MAX_EVAL_SPP} rays per pixel, got {}", self.eval_spp));
        }
        self.eval_filter.validate().map_err(|e| format!("eval_filter: {e}"))?;
        if self.render_step_size.is_some() {
            self.render_sampler()?;
        }
        if self.gpu_profile.is_some_and(|w| w.steps == 0) {
            return Err("gpu_profile.steps must be positive".into());
        }
        if let Some(t) = self.time_budget_secs {
            if !(t.is_finite() && t > 0.0) {
                return Err(format!("time_budget_secs must be a positive number, got {t}"));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_new_marching_step_keeps_the_grids_cells_and_the_rays_reach() {
        use nerf_sampling::OccupancyGrid;
        let occ = SamplerConfig::Occupancy {
            grid: OccupancyGridConfig { resolution: 16, ..Default::default() },
            step_size: 0.005,
            max_samples_per_ray: 1024,
            cone_angle: None,
        };
        // Densities spread over four decades, so the threshold and the mean both matter.
        use rand::Rng as _;
        let mut rng = nerf_core::rng(7, 0);
        let d: Vec<f32> = (0..16 * 16 * 16).map(|_| 10f32.powf(rng.gen_range(-2.0f32..2.0))).collect();
        let bits = |c: &SamplerConfig| {
            let SamplerConfig::Occupancy { grid, step_size, .. } = c else { unreachable!() };
            let mut g = OccupancyGrid::new(grid.clone(), [-1.0; 3], [1.0; 3]);
            g.set_densities(&d, *step_size).unwrap();
            (0..d.len()).map(|i| g.is_cell_occupied(i)).collect::<Vec<bool>>()
        };
        let trained = bits(&occ);
        let n = trained.iter().filter(|&&b| b).count();
        assert!(n > 100 && n < d.len() - 100, "{n} of {} cells", d.len());
        for step in [0.00125, 0.0025, 0.01] {
            let c = occ.with_step_size(step).unwrap();
            assert_eq!(bits(&c), trained, "step {step}");
            let SamplerConfig::Occupancy { step_size, max_samples_per_ray, .. } = c else { unreachable!() };
            assert_eq!(step_size, step);
            assert!(max_samples_per_ray as f32 * step >= 1024.0 * 0.005 - 1e-4, "step {step}: {max_samples_per_ray}");
        }
        // Left as it was, the threshold would have pruned cells at the finer step.
        let SamplerConfig::Occupancy { grid, .. } = &occ else { unreachable!() };
        let plain = SamplerConfig::Occupancy { grid: grid.clone(), step_size: 0.00125, max_samples_per_ray: 4096, cone_angle: None };
        assert_ne!(bits(&plain), trained);
        assert!(occ.with_step_size(0.0).unwrap_err().contains("positive"));
        assert!(occ.with_step_size(f32::NAN).is_err());
        let e = SamplerConfig::Stratified { n_samples: 64 }.with_step_size(0.01).unwrap_err();
        assert!(e.contains("occupancy"), "{e}");
    }

    #[test]
    fn config_round_trips_json_and_toml() {
        let c = TrainConfig { field_config: serde_json::json!({"width": 64}), time_budget_secs: Some(12.5), ..TrainConfig::default() };
        let j = serde_json::to_string(&c).unwrap();
        assert_eq!(serde_json::from_str::<TrainConfig>(&j).unwrap(), c);
        let t = toml::to_string(&TrainConfig { time_budget_secs: Some(3.0), ..TrainConfig::default() })
            .unwrap();
        let back: TrainConfig = toml::from_str(&t).unwrap();
        assert_eq!(back.time_budget_secs, Some(3.0));
        assert_eq!(back.sampler, c.sampler);
    }

    #[test]
    fn partial_toml_takes_defaults_and_rejects_typos() {
        let c: TrainConfig = toml::from_str("iters = 5\n[sampler]\nkind = \"stratified\"\nn_samples = 8\n").unwrap();
        assert_eq!(c.iters, 5);
        assert_eq!(c.sampler, SamplerConfig::Stratified { n_samples: 8 });
        assert_eq!(c.batch_rays, 1024);
        assert!(toml::from_str::<TrainConfig>("iterz = 5").is_err());
        assert_eq!(c.ema_decay, None);
    }

    #[test]
    fn loss_parses_and_is_validated() {
        let c: TrainConfig = toml::from_str("[loss]\nkind = \"huber\"\ndelta = 0.1\n").unwrap();
        assert_eq!(c.loss, LossConfig::Huber { delta: 0.1 });
        assert_eq!(c.loss.huber_delta(), Some(0.1));
        assert!(c.validate().is_ok());
        assert_eq!(TrainConfig::default().loss.huber_delta(), None);
        for bad in [0.0f32, -0.1, f32::NAN, f32::INFINITY] {
            let c = TrainConfig { loss: LossConfig::Huber { delta: bad }, ..TrainConfig::default() };
            assert!(c.validate().unwrap_err().contains("loss.delta"));
        }
        assert!(toml::from_str::<TrainConfig>("[loss]\nkind = \"l1\"\n").is_err());
    }

    #[test]
    fn eval_spp_round_trips_and_is_validated() {
        // 1 (the default) stays out of the serialised config, so older runs keep their hashes.
        let json = serde_json::to_value(TrainConfig::default()).unwrap();
        assert!(json.get("eval_spp").is_none());
        let c: TrainConfig = toml::from_str("eval_spp = 8\n").unwrap();
        assert_eq!(c.eval_spp, 8);
        assert!(c.validate().is_ok());
        let back: TrainConfig = toml::from_str(&toml::to_string(&c).unwrap()).unwrap();
        assert_eq!(back.eval_spp, 8);
        for bad in [0, MAX_EVAL_SPP + 1] {
            let e = TrainConfig { eval_spp: bad, ..TrainConfig::default() }.validate().unwrap_err();
            assert!(e.contains("eval_spp"), "{e}");
        }
    }

    #[test]
    fn eval_every_round_trips_and_is_validated() {
        assert!(serde_json::to_value(TrainConfig::default()).unwrap().get("eval_every").is_none());
        let c: TrainConfig = toml::from_str("[eval_every]\nsteps = 500\n").unwrap();
        assert_eq!(c.eval_every, Some(PeriodicEval { steps: 500, views: ViewSelection::Spread(4), renders: false }));
        let c: TrainConfig = toml::from_str("[eval_every]\nsteps = 500\nrenders = true\n").unwrap();
        assert!(c.eval_every.as_ref().unwrap().renders);
        let back: TrainConfig = serde_json::from_value(serde_json::to_value(&c).unwrap()).unwrap();
        assert_eq!(back.eval_every, c.eval_every);
        assert!(c.validate().is_ok());
        let c: TrainConfig = toml::from_str("[eval_every]\nsteps = 500\nviews = \"first:2\"\n").unwrap();
        assert_eq!(toml::from_str::<TrainConfig>(&toml::to_string(&c).unwrap()).unwrap(), c);
        let e = TrainConfig { eval_every: Some(PeriodicEval { steps: 0, views: ViewSelection::All, renders: false }), ..TrainConfig::default() }.validate().unwrap_err();
        assert!(e.contains("eval_every.steps"), "{e}");
        let e = TrainConfig { eval_every: Some(PeriodicEval { steps: 5, views: ViewSelection::Spread(0), renders: false }), ..TrainConfig::default() }.validate().unwrap_err();
        assert!(e.contains("eval_every.views") && e.contains("spread:0"), "{e}");
        assert!(toml::from_str::<TrainConfig>("[eval_every]\nevery = 5\n").is_err());
    }

    #[test]
    fn eval_filter_round_trips_and_is_validated() {
        // The box (the default) stays out of the serialised config.
        let json = serde_json::to_value(TrainConfig::default()).unwrap();
        assert!(json.get("eval_filter").is_none());
        let c: TrainConfig = toml::from_str("eval_spp = 8\neval_filter = { kind = \"blackman_harris\", width = 1.5 }\n").unwrap();
        assert_eq!(c.eval_filter, PixelFilter::BlackmanHarris { width: 1.5 });
        assert!(c.validate().is_ok());
        let back: TrainConfig = toml::from_str(&toml::to_string(&c).unwrap()).unwrap();
        assert_eq!(back, c);
        let e = TrainConfig { eval_filter: PixelFilter::BlackmanHarris { width: -1.0 }, ..TrainConfig::default() }.validate().unwrap_err();
        assert!(e.contains("eval_filter") && e.contains("width"), "{e}");
        assert!(toml::from_str::<TrainConfig>("eval_filter = { kind = \"tent\" }\n").is_err());
    }

    #[test]
    fn render_step_size_round_trips_and_is_validated() {
        let occ = "[sampler]\nkind = \"occupancy\"\nstep_size = 0.005\nmax_samples_per_ray = 1024\n";
        // Left out (the default) it stays out of the serialised config, and renders march as training.
        let c: TrainConfig = toml::from_str(occ).unwrap();
        assert_eq!(c.render_step_size, None);
        assert!(serde_json::to_value(&c).unwrap().get("render_step_size").is_none());
        assert_eq!(c.render_sampler().unwrap(), c.sampler);
        let c: TrainConfig = toml::from_str(&format!("render_step_size = 0.0025\n{occ}")).unwrap();
        assert!(c.validate().is_ok());
        let back: TrainConfig = toml::from_str(&toml::to_string(&c).unwrap()).unwrap();
        assert_eq!(back.render_step_size, Some(0.0025));
        // The render sampler is the training one at the new step; training's is unchanged.
        assert_eq!(c.render_sampler().unwrap(), c.sampler.with_step_size(0.0025).unwrap());
        let SamplerConfig::Occupancy { step_size, max_samples_per_ray, .. } = c.render_sampler().unwrap() else { unreachable!() };
        assert_eq!((step_size, max_samples_per_ray), (0.0025, 2048));
        assert!(matches!(c.sampler, SamplerConfig::Occupancy { step_size, .. } if step_size == 0.005));
        for bad in [0.0f32, -0.01, f32::NAN, f32::INFINITY] {
            let e = TrainConfig { render_step_size: Some(bad), ..c.clone() }.validate().unwrap_err();
            assert!(e.contains("render_step_size") && e.contains("positive"), "{bad}: {e}");
        }
        // The samplers without a marching step refuse it.
        let e = TrainConfig { render_step_size: Some(0.0025), ..TrainConfig::default() }.validate().unwrap_err();
        assert!(e.contains("render_step_size") && e.contains("occupancy"), "{e}");
    }

    #[test]
    fn progress_schedule_round_trips_and_is_validated() {
        let c: TrainConfig = toml::from_str("[lr]\nkind = \"progress\"\nlr0 = 1e-2\ngamma = 0.33\nat = [0.5, 0.75, 0.9]\nwarmup_steps = 100\n").unwrap();
        assert!(c.validate().is_ok());
        let back: TrainConfig = toml::from_str(&toml::to_string(&c).unwrap()).unwrap();
        assert_eq!(back.lr, c.lr);
        let bad: TrainConfig = toml::from_str("[lr]\nkind = \"progress\"\nlr0 = 1e-2\ngamma = 0.33\nat = [0.5, 2.0]\n").unwrap();
        let e = bad.validate().unwrap_err();
        assert!(e.contains("lr.at") && e.contains('2'), "{e}");
        let e = TrainConfig { lr: LrSchedule::Constant { lr: f32::NAN }, ..TrainConfig::default() }.validate().unwrap_err();
        assert!(e.contains("lr.lr"), "{e}");
    }

    #[test]
    fn ema_decay_parses_and_is_validated() {
        let c: TrainConfig = toml::from_str("ema_decay = 0.95").unwrap();
        assert_eq!(c.ema_decay, Some(0.95));
        assert!(c.validate().is_ok());
        for bad in [0.0f32, 1.0, -0.5, 1.5, f32::NAN] {
            let c = TrainConfig { ema_decay: Some(bad), ..TrainConfig::default() };
            let e = c.validate().unwrap_err();
            assert!(e.contains("ema_decay"), "{e}");
        }
    }

    #[test]
    fn cone_angle_left_out_is_the_scenes_and_zero_is_kept() {
        let occ = |extra: &str| -> TrainConfig {
            toml::from_str(&format!("[sampler]\nkind = \"occupancy\"\nstep_size = 0.01\nmax_samples_per_ray = 8\n{extra}")).unwrap()
        };
        let cone = |c: &TrainConfig| match c.sampler {
            SamplerConfig::Occupancy { cone_angle, .. } => cone_angle,
            _ => unreachable!(),
        };
        // Left out: None (the scene picks), and written back without the key.
        let c = occ("");
        assert_eq!(cone(&c), None);
        assert!(!toml::to_string(&c).unwrap().contains("cone_angle"));
        // 0 (constant steps) is a choice that survives a round trip, so an explicit 0 is not
        // replaced by the scene's cone.
        for v in [0.0f32, 0.00390625] {
            let c = occ(&format!("cone_angle = {v:?}\n"));
            assert_eq!(cone(&c), Some(v));
            let back: TrainConfig = toml::from_str(&toml::to_string(&c).unwrap()).unwrap();
            assert_eq!(cone(&back), Some(v));
            assert!(c.validate().is_ok());
        }
        let e = occ("cone_angle = -0.1\n").validate().unwrap_err();
        assert!(e.contains("cone_angle") && e.contains("-0.1"), "{e}");
    }
}
