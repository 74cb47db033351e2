//! One training step and batched rendering, for any field behind the `RadianceField` trait.

use crate::config::{SamplerConfig, TrainConfig};
use crate::TrainError;
use nerf_data::{Dataset, RayBatch};
use nerf_field::{FieldContext, ParamGroupMut, RadianceField, Registry};
use nerf_optim::{Adam, AdamState, Ema, EmaState};
use crate::color::{ColorState, CpuColor, COLOR_VIEWS};
use crate::pose::{CpuPose, PoseState, POSE_VIEWS};
use crate::views::check_views;
use nerf_render::{
    color_correct_backward, color_correct_forward, composite_backward, composite_forward, composited_counts, depth_loss_grad, distortion_loss_grad,
    mean_color_correction, photometric_loss_grad, CompositeOutputs, COLOR_PARAMS_PER_VIEW,
};
use nerf_sampling::{hierarchical, march, stratified, OccupancyGrid, OccupancyGridConfig, RaySamples};
use nerf_core::ScratchPool;
use std::sync::{Mutex, MutexGuard};

/// instant-ngp's cone angle for boxes with `aabb_scale` > 1 (its `cone_angle_constant`).
pub const NGP_CONE_ANGLE: f32 = 1.0 / 256.0;

/// Where the scene lives: what fields and samplers need to know about it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneBounds {
    /// Scene box lower corner.
    pub aabb_min: [f32; 3],
    /// Scene box upper corner.
    pub aabb_max: [f32; 3],
    /// Near distance along unit rays.
    pub near: f32,
    /// Far distance along unit rays.
    pub far: f32,
    /// Stratified and hierarchical sampling take each ray's `[near, far] ∩ box`
    /// ([`nerf_sampling::clip_segments`]) instead of `[near, far]`: NDC scenes, where the box
    /// (`z' ∈ [−1, 1]`) gives every ray its NDC segment. The occupancy marcher always clips.
    pub clip_to_box: bool,
    /// Levels of the occupancy grid's cascade when the config leaves `cascades` out: 1, or for
    /// an instant-ngp box `1 + ⌈log₂ aabb_scale⌉` (at most 8), so that the finest level covers
    /// the unit cube of instant-ngp units, as instant-ngp's cascades do.
    pub cascades: u32,
    /// The cone steps' angle when the config leaves `cone_angle` out: instant-ngp's 1/256 in an
    /// instant-ngp box with `aabb_scale` > 1 (distant space in geometrically growing steps), 0
    /// (constant steps) otherwise.
    pub cone_angle: f32,
    /// The box against the scene's unit, for the fields ([`FieldContext::scene_scale`]):
    /// instant-ngp's `aabb_scale` for an instant-ngp scene, 1 otherwise.
    pub scene_scale: f32,
    /// Training views of the scene: what per-view state (`color_correction`) is sized for.
    pub n_views: usize,
}

impl SceneBounds {
    /// The bounds of a loaded dataset (clipped to the box in NDC scenes).
    pub fn of(ds: &Dataset) -> Self {
        let cascades = match ds.ngp {
            Some(b) if b.aabb_scale > 1.0 => 1 + (b.aabb_scale.log2().ceil() as u32).min(nerf_sampling::MAX_CASCADES - 1),
            _ => 1,
        };
        Self {
            aabb_min: ds.aabb.min,
            aabb_max: ds.aabb.max,
            near: ds.near,
            far: ds.far,
            clip_to_box: ds.clips_to_aabb(),
            cascades,
            cone_angle: if matches!(ds.ngp, Some(b) if b.aabb_scale > 1.0) { NGP_CONE_ANGLE } else { 0.0 },
            scene_scale: ds.ngp.map_or(1.0, |b| b.aabb_scale),
            n_views: ds.n_views(),
        }
    }

    /// The marcher's steps: `step_size` with the config's cone angle, or the scene's when left out.
    pub fn stepping(&self, step_size: f32, cone_angle: Option<f32>) -> nerf_sampling::Stepping {
        nerf_sampling::Stepping::new(step_size, cone_angle.unwrap_or(self.cone_angle))
    }

    /// The occupancy grid's settings with `cascades` filled in from the scene when absent.
    pub fn grid_config(&self, grid: &OccupancyGridConfig) -> OccupancyGridConfig {
        OccupancyGridConfig { cascades: Some(grid.cascades.unwrap_or(self.cascades)), ..grid.clone() }
    }

    /// The bounds for rendering a novel-view path from `path`'s cameras in a scene trained from
    /// `training`'s: `far` moved out by as much as the path's farthest camera lies farther from
    /// the box's centre than the farthest training camera, `near` in (to no less than 0) by as
    /// much as its nearest camera lies nearer than the nearest training camera. A path within
    /// the training cameras' distances keeps the bounds as they are; one that zooms out or flies
    /// in keeps the scene within its rays' segments (NeRF's Blender scenes march `[2, 6]`, which
    /// a camera 8 from the object would see nothing of). Not for NDC scenes, whose bounds are
    /// NDC's.
    pub fn for_path(self, training: &[nerf_rays::Camera], path: &[nerf_rays::Camera]) -> Self {
        let c = nerf_rays::glam::Vec3::from_array(std::array::from_fn(|i| 0.5 * (self.aabb_min[i] + self.aabb_max[i])));
        let range = |cams: &[nerf_rays::Camera]| {
            cams.iter().map(|k| (k.position - c).length()).fold((f32::INFINITY, 0.0f32), |(lo, hi), d| (lo.min(d), hi.max(d)))
        };
        let ((t_lo, t_hi), (p_lo, p_hi)) = (range(training), range(path));
        if training.is_empty() || path.is_empty() || !(t_hi.is_finite() && p_hi.is_finite()) {
            return self;
        }
        // Rounding (a path at the training cameras' own distance) moves nothing.
        let slack = 1e-4 * t_hi;
        let (closer, farther) = (t_lo - p_lo, p_hi - t_hi);
        Self {
            near: if closer > slack { (self.near - closer).max(0.0) } else { self.near },
            far: if farther > slack { self.far + farther } else { self.far },
            ..self
        }
    }

    /// Per-ray segments into `near`/`far` (resized to the rays): `[near, far]`, clipped to the
    /// box when [`SceneBounds::clip_to_box`].
    pub fn segments(&self, origins: &[f32], dirs: &[f32], near: &mut Vec<f32>, far: &mut Vec<f32>) {
        let n = origins.len() / 3;
        near.clear();
        near.resize(n, self.near);
        far.clear();
        far.resize(n, self.far);
        if self.clip_to_box {
            nerf_sampling::clip_segments(self.aabb_min, self.aabb_max, origins, dirs, self.near, self.far, near, far);
        }
    }
}

/// Per-field buffers of one sampling stage (reused every step).
#[derive(Default)]
struct Stage {
    samples: RaySamples,
    sigma: Vec<f32>,
    rgb: Vec<f32>,
    comp: CompositeOutputs<f32>,
    d_ray_rgb: Vec<f32>,
    d_sigma: Vec<f32>,
    d_rgb: Vec<f32>,
    /// The distortion loss per ray (`distortion_loss`).
    ray_loss: Vec<f32>,
    /// The depth loss's gradient per ray (`depth_loss`).
    d_depth: Vec<f32>,
}

/// What one step did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepStats {
    /// Step index (0-based) that was just taken.
    pub step: u64,
    /// Total loss (sum of the per-stage photometric losses, plus the distortion and depth losses
    /// when on).
    pub loss: f32,
    /// Photometric MSE of the final stage (the image the user sees).
    pub mse: f32,
    /// Field samples trained on in this step (all stages; with `compact_samples` those left after
    /// compaction, not the marched ones the density pass saw).
    pub n_samples: usize,
    /// Samples the first stage's sampler produced before compaction (`compact_samples`; the
    /// density pass saw them); without compaction the first stage's `n_samples`. On the GPU read
    /// back with the loss, as `n_samples`.
    pub n_marched: usize,
    /// Rays in the step's batch. On the GPU read back with the loss (0 in between).
    pub n_rays: usize,
    /// Rays of the final stage whose composited opacity is positive, i.e. that met at least one
    /// sample (nerfacc's `alive_ray_mask`); read back with the loss on the GPU.
    pub alive_rays: usize,
    /// Photometric MSE of the final stage over those rays alone: what nerfacc's training log
    /// prints as its loss. Rays that met no sample show the background they are composited on, so
    /// with random backgrounds they add exact zeros to [`mse`](Self::mse). NaN when not read (GPU,
    /// between reads) or when no ray is alive.
    pub mse_alive: f32,
    /// Learning rate used.
    pub lr: f32,
}

impl StepStats {
    /// PSNR of [`mse_alive`](Self::mse_alive), dB; `None` when it is NaN.
    pub fn psnr_alive(&self) -> Option<f64> {
        self.mse_alive.is_finite().then(|| nerf_metrics::mse_to_psnr(self.mse_alive as f64))
    }
}

/// `(rays with a positive opacity, the MSE over their 3 channels)` from per-ray opacities and
/// per-ray squared errors summed over the channels ([`StepStats::alive_rays`],
/// [`StepStats::mse_alive`]; NaN without such a ray).
pub(crate) fn alive_mse(opacity: &[f32], ray_sq_err: impl Fn(usize) -> f64) -> (usize, f32) {
    let (mut n, mut sum) = (0usize, 0.0f64);
    for (r, &a) in opacity.iter().enumerate() {
        if a > 0.0 {
            n += 1;
            sum += ray_sq_err(r);
        }
    }
    (n, if n > 0 { (sum / (3 * n) as f64) as f32 } else { f32::NAN })
}

/// Field instances that hold the EMA weights, for rendering on the CPU. Filled from the average
/// lazily (at the first render after the average changed), so training pays nothing for them.
struct EmaFields {
    /// Version of the average the fields hold (see `Trainer::ema_version`).
    synced: u64,
    fields: Vec<Box<dyn RadianceField>>,
}

/// RNG streams (see `nerf_core::rng`): field initialisation, per-step batches.
const STREAM_STEP: u64 = 1 << 40;

/// Trains one or more instances of a field with a field-agnostic sampler and compositor.
pub struct Trainer {
    config: TrainConfig,
    bounds: SceneBounds,
    fields: Vec<Box<dyn RadianceField>>,
    group_names: Vec<Vec<String>>,
    adam: Adam,
    step: u64,
    batch: RayBatch,
    near: Vec<f32>,
    far: Vec<f32>,
    stages: Vec<Stage>,
    /// With `compact_samples`: every marched sample and its density (the inference pass), and how
    /// many leading samples of each ray compositing reaches.
    marched: RaySamples,
    marched_sigma: Vec<f32>,
    keep: Vec<u32>,
    /// The row in `marched` of each compacted sample (the field reuses its density pass's work).
    kept_rows: Vec<u32>,
    /// The batch's measured depths (`depth_loss`; 0: none), one per ray.
    depth_target: Vec<f32>,
    /// The occupancy grid of the `Occupancy` sampler.
    grid: Option<OccupancyGrid>,
    /// Running mean of samples per ray (sizes batches when `target_samples_per_step` is set).
    samples_per_ray: f32,
    /// Field samples evaluated by this trainer's steps (not counting restored ones).
    samples_seen: u64,
    /// The GPU execution path, when the trainer runs on a device.
    gpu: Option<crate::gpu::GpuEngine>,
    /// The parameters' exponential moving average (CPU path, `config.ema_decay`).
    ema: Option<Ema>,
    /// Bumped whenever the average changes (updates, restores): `EmaFields::synced` compares to it.
    ema_version: u64,
    /// Rendering instances of the field holding the average (CPU path with `ema_decay`).
    ema_fields: Option<Mutex<EmaFields>>,
    /// What `new_on` changed in the config to fit the adapter's limits.
    device_note: Option<String>,
    /// Whether the occupancy grid's cells have been marked with the training cameras (at the
    /// first step, and again after a restore).
    seen_marked: bool,
    /// The per-view colour correction of the CPU path (`config.color_correction`).
    color: Option<CpuColor>,
    /// The training view whose colour correction renders use (`None`: the mean).
    render_appearance: Option<usize>,
    /// The render crop box ([`Trainer::set_render_crop`]).
    render_crop: Option<nerf_sampling::CropBox>,
    /// Camera pose refinement of the CPU path (`config.camera_optimizer`).
    pose: Option<CpuPose>,
    /// The fraction of the run done, as the caller last set it ([`Trainer::set_progress`]).
    progress: Option<f64>,
    /// Buffers of the CPU renders (`render_rays`), kept between calls: one set per chunk
    /// rendered at once with the occupancy grid's rounds, one per call otherwise.
    round_scratch: ScratchPool<crate::rounds::RoundScratch>,
    stage_scratch: ScratchPool<StageScratch>,
}

/// The per-chunk buffers of a CPU render without the occupancy grid: each field's stage and the
/// rays' near and far bounds.
#[derive(Default)]
struct StageScratch {
    stages: Vec<Stage>,
    near: Vec<f32>,
    far: Vec<f32>,
}

/// Bounds on the adaptive number of rays per step.
const MIN_BATCH_RAYS: usize = 64;
const MAX_BATCH_RAYS: usize = 1 << 20;

impl Trainer {
    /// Builds the field(s) named by `config.field` from the registry.
    pub fn new(config: TrainConfig, registry: &Registry, bounds: SceneBounds) -> Result<Self, TrainError> {
        config.validate().map_err(TrainError::Config)?;
        let n = config.sampler.n_fields();
        let build = || -> Result<Vec<Box<dyn RadianceField>>, TrainError> {
            (0..n)
                .map(|i| {
                    let ctx = FieldContext {
                        aabb_min: bounds.aabb_min,
                        aabb_max: bounds.aabb_max,
                        seed: config.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(i as u64),
                        scene_scale: bounds.scene_scale,
                    };
                    Ok(registry.build(&config.field, &config.field_config, &ctx)?)
                })
                .collect()
        };
        let mut fields = build()?;
        let (ema, ema_fields) = match config.ema_decay {
            Some(d) => (Some(Ema::new(d)), Some(Mutex::new(EmaFields { synced: 0, fields: build()? }))),
            None => (None, None),
        };
        let prefixes = group_prefixes(n);
        let group_names: Vec<Vec<String>> = fields
            .iter_mut()
            .zip(prefixes)
            .map(|(f, p)| f.param_groups().iter().map(|g| format!("{p}/{}", g.name)).collect())
            .collect();
        let names: Vec<&String> = group_names.iter().flatten().collect();
        for g in &config.adam.sparse_groups {
            if !names.iter().any(|n| nerf_optim::names_group(g, n)) {
                return Err(TrainError::Config(format!(
                    "adam.sparse_groups names {g:?}, but the parameter groups of this run are {names:?}"
                )));
            }
        }
        let adam = Adam::new(config.adam.clone());
        // Sized for the scene's views (at least one; a restore takes the checkpoint's count).
        let color = config.color_correction.as_ref().map(|c| CpuColor::new(bounds.n_views.max(1), &config.adam, c.lr));
        let pose = match &config.camera_optimizer {
            Some(c) => {
                if let Some(f) = fields.iter().find(|f| !f.has_input_gradients()) {
                    return Err(TrainError::Config(format!(
                        "camera_optimizer needs the field's gradients in its inputs; field `{}` does not provide them (use `freq` or `hash`)",
                        f.kind()
                    )));
                }
                Some(CpuPose::new(bounds.n_views.max(1), &config.adam, c))
            }
            None => None,
        };
        let grid = match &config.sampler {
            SamplerConfig::Occupancy { grid, .. } => Some(
                OccupancyGrid::try_new(bounds.grid_config(grid), bounds.aabb_min, bounds.aabb_max)
                    .map_err(|e| TrainError::Config(format!("sampler.grid: {e}")))?,
            ),
            _ => None,
        };
        Ok(Self {
            grid,
            samples_per_ray: 0.0,
            samples_seen: 0,
            gpu: None,
            ema,
            ema_version: 0,
            ema_fields,
            device_note: None,
            seen_marked: false,
            color,
            render_appearance: None,
            render_crop: None,
            progress: None,
            pose,
            round_scratch: ScratchPool::new(),
            stage_scratch: ScratchPool::new(),
            stages: (0..n).map(|_| Stage::default()).collect(),
            marched: RaySamples::default(),
            marched_sigma: Vec::new(),
            keep: Vec::new(),
            kept_rows: Vec::new(),
            depth_target: Vec::new(),
            config,
            bounds,
            fields,
            group_names,
            adam,
            step: 0,
            batch: RayBatch::default(),
            near: Vec::new(),
            far: Vec::new(),
        })
    }

    /// As [`Trainer::new`], on `device` when given: every field instance is moved to the GPU
    /// (its `to_gpu` twin, same initial parameters) and the whole step runs there. Errors when the
    /// field has no GPU implementation.
    ///
    /// Where a buffer sized per sample would exceed the adapter's storage binding limit (lavapipe
    /// and some other adapters allow 128 MiB), the step's samples are fitted to the adapter:
    /// `target_samples_per_step` or `batch_rays` is scaled down, a note on stderr says so, and
    /// [`Trainer::config`] and [`Trainer::device_note`] hold what was changed.
    pub fn new_on(
        config: TrainConfig,
        registry: &Registry,
        bounds: SceneBounds,
        device: Option<std::sync::Arc<nerf_gpu::GpuContext>>,
    ) -> Result<Self, TrainError> {
        let mut t = Self::new(config, registry, bounds)?;
        if let Some(ctx) = device {
            // Each fit scales the step by the overshoot of the buffer that failed; a few tries
            // cover buffers that do not scale exactly linearly (ray-sized ones, clamps) and the
            // fine stage of a hierarchical sampler (built after the coarse one).
            let mut config = t.config.clone();
            let mut first_overshoot = None;
            let engine = loop {
                match crate::gpu::GpuEngine::new(ctx.clone(), &config, bounds, &t.fields, &t.group_names) {
                    Err(TrainError::GpuCapacity { message, bytes, limit }) => {
                        let tries = first_overshoot.map_or(0, |(_, _, k)| k);
                        match crate::gpu::fit_to_binding_limit(&config, bytes, limit) {
                            Some(fitted) if tries < 6 => {
                                config = fitted;
                                let (b, l) = first_overshoot.map_or((bytes, limit), |(b, l, _)| (b, l));
                                first_overshoot = Some((b, l, tries + 1));
                            }
                            _ => return Err(TrainError::GpuCapacity { message, bytes, limit }),
                        }
                    }
                    other => break other?,
                }
            };
            if let Some((bytes, limit, _)) = first_overshoot {
                let note = crate::gpu::fit_note(&t.config, &config, bytes, limit);
                eprintln!("note: {note} ({})", ctx.describe());
                t.device_note = Some(note);
                t.config = config;
            }
            t.gpu = Some(engine);
            // The device keeps (and renders with) its own average.
            t.ema = None;
            t.ema_fields = None;
            // … and its own colour and pose corrections.
            t.color = None;
            t.pose = None;
        }
        Ok(t)
    }

    /// `"gpu"` when the step runs on a wgpu device, else `"cpu"`.
    pub fn device(&self) -> &'static str {
        if self.gpu.is_some() {
            "gpu"
        } else {
            "cpu"
        }
    }

    /// The adapter the GPU path runs on (name, backend, type, driver).
    pub fn adapter(&self) -> Option<String> {
        self.gpu.as_ref().map(|g| g.describe())
    }

    /// The GPU profile of `TrainConfig::gpu_profile` once its window of steps is complete (returned
    /// once), or with `partial` the steps of it that ran. Always `None` on the CPU path.
    pub fn take_gpu_profile(&mut self, partial: bool) -> Option<crate::GpuProfile> {
        self.gpu.as_mut().and_then(|g| g.take_profile(partial))
    }

    /// Waits until every queued GPU step has finished (no-op on the CPU).
    pub fn finish(&self) -> Result<(), TrainError> {
        match &self.gpu {
            Some(g) => g.finish(),
            None => Ok(()),
        }
    }

    /// Field samples evaluated by the steps of this trainer (restored steps not included). On the
    /// GPU this reads a device counter (a small read-back).
    pub fn samples_seen(&self) -> Result<u64, TrainError> {
        match &self.gpu {
            Some(g) => g.samples_seen(),
            None => Ok(self.samples_seen),
        }
    }

    /// The run's config (on the GPU, with the samples per step fitted to the adapter where
    /// [`Trainer::new_on`] had to).
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// What [`Trainer::new_on`] changed in the config to fit the adapter, if anything.
    pub fn device_note(&self) -> Option<&str> {
        self.device_note.as_deref()
    }

    /// Steps taken so far.
    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// Marching step of the renders from now on (`render_step_size`; `None` = the training
    /// step); an error (a step that is not positive, a sampler without a step) leaves the
    /// setting as it was. Training keeps its step.
    pub fn set_render_step_size(&mut self, step: Option<f32>) -> Result<(), TrainError> {
        let c = TrainConfig { render_step_size: step, ..self.config.clone() };
        c.validate().map_err(TrainError::Config)?;
        self.config.render_step_size = step;
        Ok(())
    }

    /// Rays per pixel of the evaluation's renders from now on (`eval_spp`, 1..=256; see
    /// [`crate::evaluate`]); an error names a count out of range and leaves the setting as it was.
    pub fn set_eval_spp(&mut self, spp: u32) -> Result<(), TrainError> {
        let c = TrainConfig { eval_spp: spp, ..self.config.clone() };
        c.validate().map_err(TrainError::Config)?;
        self.config.eval_spp = spp;
        Ok(())
    }

    /// Tells the trainer how much of its run is done, in `[0, 1]` (values outside are clamped):
    /// what a [`LrSchedule::Progress`](nerf_optim::LrSchedule::Progress) learning rate follows.
    /// A run with a time budget sets the larger of its step and time fractions before each step.
    /// Until this is called the progress is `step / config.iters`.
    pub fn set_progress(&mut self, progress: f64) {
        self.progress = Some(if progress.is_nan() { 0.0 } else { progress.clamp(0.0, 1.0) });
    }

    /// The learning rate of the next step.
    pub fn learning_rate(&self) -> f32 {
        let progress = self.progress.unwrap_or_else(|| crate::run_progress(self.step, self.config.iters, 0.0, f64::INFINITY));
        self.config.lr.lr(self.step, progress)
    }

    /// The CPU fields (coarse first when hierarchical; the last one renders the image). On the GPU
    /// path these hold the initial parameters; use [`Trainer::export_fields`] for the trained ones.
    pub fn fields(&self) -> &[Box<dyn RadianceField>] {
        &self.fields
    }

    /// Total trainable parameters over all field instances.
    pub fn n_params(&self) -> usize {
        self.fields.iter().map(|f| f.n_params()).sum()
    }

    /// Takes one optimisation step on a random batch of rays from `data`.
    ///
    /// On the GPU the step is recorded and submitted without waiting; the loss is read back only
    /// every `log_every` steps (and on the last step), otherwise [`StepStats::loss`] and
    /// [`StepStats::mse`] are NaN and [`StepStats::n_samples`] is the last value read.
    ///
    /// A loss that is computed (every CPU step; every read-back on the GPU) and not finite is
    /// [`TrainError::Diverged`]: NaN or infinite parameters never train on silently.
    pub fn step(&mut self, data: &Dataset) -> Result<StepStats, TrainError> {
        let corrections = match (&self.gpu, &self.color) {
            (Some(g), _) => g.color_views(),
            (None, c) => c.as_ref().map(|c| c.views.n_views()),
        };
        if let Some(n) = corrections {
            check_views(&COLOR_VIEWS, n, data.n_views())?;
        }
        let poses = match (&self.gpu, &self.pose) {
            (Some(g), _) => g.pose_views(),
            (None, p) => p.as_ref().map(|p| p.views.n_views()),
        };
        if let Some(n) = poses {
            check_views(&POSE_VIEWS, n, data.n_views())?;
            if data.ndc.is_some() {
                return Err(TrainError::Config(
                    "camera_optimizer needs Euclidean rays: train this LLFF scene with ndc = false (--no-ndc)".into(),
                ));
            }
        }
        if self.config.depth_loss.is_some() {
            match &data.depths {
                None => {
                    return Err(TrainError::Config(format!(
                        "depth_loss is set, but the scene {} has no depth maps (nerfstudio's depth_file_path, instant-ngp's depth_path, or a COLMAP folder's points3D)",
                        data.root.display()
                    )))
                }
                Some(_) => {
                    if let Some(reason) = data.depths_mismatch() {
                        return Err(TrainError::Config(reason));
                    }
                }
            }
        }
        if !self.seen_marked {
            self.mark_seen(data)?;
            self.seen_marked = true;
        }
        let lr = self.learning_rate();
        match self.gpu.as_mut() {
            Some(g) => {
                // The GPU path returns `Diverged` itself (a NaN loss there also means "not read").
                let r = g.step(data, &self.config, self.step, lr);
                if matches!(r, Ok(_) | Err(TrainError::Diverged { .. })) {
                    self.step += 1; // submitted
                }
                r
            }
            None => {
                let s = self.cpu_step(data);
                if s.loss.is_finite() {
                    Ok(s)
                } else {
                    Err(TrainError::Diverged { step: s.step + 1, loss: s.loss })
                }
            }
        }
    }

    /// Marks the occupancy-grid cells that no training camera of `data` sees (instant-ngp's
    /// untrained cells: never occupied, never refreshed; `OccupancyGrid::mark_seen` with
    /// `Frustum::sees_sphere`, through each camera's lens). Euclidean scenes only: an NDC grid is
    /// not in the cameras' space.
    fn mark_seen(&mut self, data: &Dataset) -> Result<(), TrainError> {
        if data.ndc.is_some() || data.cameras.is_empty() {
            return Ok(());
        }
        let frusta: Vec<nerf_rays::Frustum> = data.cameras.iter().map(|c| c.frustum()).collect();
        let visible = move |c: [f32; 3], r: f32| frusta.iter().any(|f| f.sees_sphere(c.into(), r));
        if let Some(g) = self.gpu.as_mut() {
            return g.mark_seen(&visible);
        }
        if let Some(g) = self.grid.as_mut() {
            g.mark_seen(&visible);
        }
        Ok(())
    }

    fn cpu_step(&mut self, data: &Dataset) -> StepStats {
        let cfg = &self.config;
        let mut rng = nerf_core::rng(cfg.seed, STREAM_STEP + self.step);
        let n_rays = match cfg.target_samples_per_step {
            Some(target) => {
                // Before any step, assume the most samples a ray can get, so that the first step
                // (an all-occupied grid) is not hundreds of times the target.
                let spr = if self.samples_per_ray > 0.0 { self.samples_per_ray } else { max_samples_per_ray(&cfg.sampler) as f32 };
                ((target as f32 / spr) as usize).clamp(MIN_BATCH_RAYS, MAX_BATCH_RAYS)
            }
            None => cfg.batch_rays,
        };
        data.sample_rays(n_rays, cfg.train_background, cfg.pixel_convention, cfg.pixel_jitter, &mut rng, &mut self.batch);
        let n_rays = self.batch.len();
        if let Some(p) = self.pose.as_mut() {
            let b = &mut self.batch;
            p.correct(&b.view_ids, &mut b.origins, &mut b.dirs);
        }
        self.bounds.segments(&self.batch.origins, &self.batch.dirs, &mut self.near, &mut self.far);
        for f in self.fields.iter_mut() {
            f.zero_grad();
        }
        let perturb = cfg.perturb;
        let thr = cfg.transmittance_threshold;
        let b = &self.batch;
        // Stage 0: stratified samples, or occupancy-grid marching (grid refreshed from the
        // field's density first when due).
        if let (Some(grid), SamplerConfig::Occupancy { step_size, .. }) = (self.grid.as_mut(), &cfg.sampler) {
            if grid.due(self.step) {
                let field = self.fields[0].as_ref();
                grid.update(self.step, *step_size, &mut |p, s| field.density(p, s), &mut rng);
            }
        }
        if cfg.compact_samples {
            // instant-ngp's compacted batch: density of every marched sample (inference), then
            // train on the samples compositing reaches before the transmittance threshold.
            let m = &mut self.marched;
            first_stage_samples(cfg, &self.bounds, self.grid.as_ref(), &b.origins, &b.dirs, &self.near, &self.far, perturb.then_some(&mut rng), m);
            self.marched_sigma.resize(m.len(), 0.0);
            self.fields[0].density_for_training(&m.positions, &mut self.marched_sigma);
            composited_counts(&m.ray_offsets, &self.marched_sigma, &m.dt, thr, &mut self.keep);
            m.compact_into(&self.keep, usize::MAX, &mut self.stages[0].samples);
            nerf_sampling::compacted_rows(&m.ray_offsets, &self.stages[0].samples.ray_offsets, &mut self.kept_rows);
            let rows = &self.kept_rows;
            let st = &mut self.stages[0];
            run_stage(st, &b.background, thr, |p, d, s, c| self.fields[0].forward_rows(rows, p, d, s, c));
        } else {
            first_stage_samples(
                cfg,
                &self.bounds,
                self.grid.as_ref(),
                &b.origins,
                &b.dirs,
                &self.near,
                &self.far,
                perturb.then_some(&mut rng),
                &mut self.stages[0].samples,
            );
            forward_stage(self.fields[0].as_mut(), &mut self.stages[0], &b.background, thr);
        }
        // Stage 1: importance samples from the coarse weights (detached, as in the paper).
        if let SamplerConfig::Hierarchical { n_fine, .. } = cfg.sampler {
            let (s0, s1) = self.stages.split_at_mut(1);
            hierarchical(
                &s0[0].samples,
                &s0[0].comp.weights,
                &b.origins,
                &b.dirs,
                &self.far,
                n_fine,
                perturb.then_some(&mut rng),
                &mut s1[0].samples,
            );
            forward_stage(self.fields[1].as_mut(), &mut s1[0], &b.background, thr);
        }
        // Loss on every stage, then backward through compositing into each field.
        let mut loss = 0.0;
        let mut mse = 0.0;
        let mut n_samples = 0;
        let (mut alive_rays, mut mse_alive) = (0, f32::NAN);
        let n_stages = self.stages.len();
        let depth_range = self.bounds.far - self.bounds.near;
        let depth_loss = cfg.depth_loss.zip(data.depths.as_ref());
        if let Some((_, maps)) = depth_loss {
            self.depth_target.clear();
            self.depth_target.extend(b.view_ids.iter().zip(&b.pixel_ids).map(|(&v, &p)| maps[v as usize][p as usize]));
        }
        for (i, (field, st)) in self.fields.iter_mut().zip(self.stages.iter_mut()).enumerate() {
            st.d_ray_rgb.resize(3 * n_rays, 0.0);
            // With colour correction the loss sees each view's corrected pixels, and compositing's
            // backward gets the gradient through the correction (with an opacity term).
            // `inspect` would hand the closure `&&mut`, which cannot resize the buffers.
            #[allow(clippy::manual_inspect)]
            let color = self.color.as_mut().map(|c| {
                c.out.resize(3 * n_rays, 0.0);
                color_correct_forward(Some(&b.view_ids), &c.views.params, &st.comp.rgb, &st.comp.opacity, &b.background, &mut c.out);
                c
            });
            let pred = color.as_ref().map_or(&st.comp.rgb, |c| &c.out);
            mse = photometric_loss_grad(pred, &b.target, cfg.loss.huber_delta(), &mut st.d_ray_rgb);
            if i + 1 == n_stages {
                let sq = |r: usize| (0..3).map(|c| ((pred[3 * r + c] - b.target[3 * r + c]) as f64).powi(2)).sum::<f64>();
                (alive_rays, mse_alive) = alive_mse(&st.comp.opacity[..n_rays], sq);
            }
            let (d_ray_rgb, d_opacity) = match color {
                Some(c) => {
                    c.d_rgb.resize(3 * n_rays, 0.0);
                    c.d_opacity.resize(n_rays, 0.0);
                    color_correct_backward(
                        Some(&b.view_ids),
                        &c.views.params,
                        &st.comp.rgb,
                        &st.comp.opacity,
                        &b.background,
                        &st.d_ray_rgb,
                        &mut c.d_rgb,
                        &mut c.d_opacity,
                        &mut c.views.grads,
                    );
                    (&c.d_rgb, Some(&c.d_opacity[..]))
                }
                None => (&st.d_ray_rgb, None),
            };
            loss += mse;
            n_samples += st.samples.len();
            let n = st.samples.len();
            st.d_sigma.resize(n, 0.0);
            st.d_rgb.resize(3 * n, 0.0);
            let d_depth = match depth_loss {
                Some((lambda, _)) => {
                    st.d_depth.resize(n_rays, 0.0);
                    loss += depth_loss_grad(&st.comp.depth, &self.depth_target, lambda, &mut st.d_depth);
                    Some(&st.d_depth[..])
                }
                None => None,
            };
            composite_backward(
                &st.samples.ray_offsets,
                &st.sigma,
                &st.rgb,
                &st.samples.dt,
                &st.samples.t,
                Some(&b.background),
                &st.comp,
                d_ray_rgb,
                d_opacity,
                d_depth,
                &mut st.d_sigma,
                &mut st.d_rgb,
            );
            if let (Some(lambda), true) = (cfg.distortion_loss, i + 1 == n_stages) {
                st.ray_loss.resize(n_rays, 0.0);
                let scale = if depth_range > 0.0 { 1.0 / depth_range } else { 1.0 };
                let s = &st.samples;
                loss += distortion_loss_grad(
                    &s.ray_offsets, &st.sigma, &s.dt, &s.t, &st.comp, scale, lambda / n_rays.max(1) as f32, &mut st.d_sigma, &mut st.ray_loss,
                );
            }
            match self.pose.as_mut() {
                None => field.backward(&st.d_sigma, &st.d_rgb),
                Some(p) => {
                    // Camera pose refinement: the field's input gradients, gathered per ray.
                    let (dp, dd) = p.sample_buffers(n);
                    if let Err(e) = field.backward_with_inputs(&st.d_sigma, &st.d_rgb, dp, dd) {
                        panic!("field said it has input gradients (checked when the trainer was built): {e}");
                    }
                    st.samples.backward_to_rays(&p.d_positions, &p.d_sample_dirs, &mut p.d_origins, &mut p.d_dirs);
                }
            }
        }
        let lr = self.learning_rate();
        let Self { fields, group_names, adam, ema, .. } = self;
        let mut groups: Vec<ParamGroupMut<'_>> = Vec::new();
        for (f, names) in fields.iter_mut().zip(group_names.iter()) {
            for (g, name) in f.param_groups().into_iter().zip(names) {
                groups.push(ParamGroupMut { name, ..g });
            }
        }
        adam.step(&mut groups, lr);
        if let Some(c) = self.color.as_mut() {
            c.views.step(c.lr);
        }
        if let Some(p) = self.pose.as_mut() {
            loss += p.step(&self.batch.view_ids, self.step);
        }
        if let Some(e) = ema.as_mut() {
            e.update(&groups);
            self.ema_version += 1;
        }
        drop(groups);
        for f in fields.iter_mut() {
            f.after_optimizer_step();
        }
        let spr = self.stages[0].samples.len() as f32 / n_rays.max(1) as f32;
        self.samples_per_ray = if self.samples_per_ray > 0.0 { 0.9 * self.samples_per_ray + 0.1 * spr } else { spr };
        let n_marched = if cfg.compact_samples { self.marched.len() } else { self.stages[0].samples.len() };
        let stats = StepStats { step: self.step, loss, mse, n_samples, n_marched, n_rays, alive_rays, mse_alive, lr };
        self.samples_seen += n_samples as u64;
        self.step += 1;
        stats
    }

    /// Renders rays (inference, deterministic sampling) in chunks of `render_chunk_rays`, on the
    /// trainer's device (on the CPU with the occupancy sampler, the chunks concurrently).
    /// Outputs: rgb `3·n`, opacity `n`, depth `n`. With `ema_decay` set (and at least one step
    /// taken or restored) the field renders with the parameters' moving average; the occupancy
    /// grid is the one training keeps (from the raw parameters).
    ///
    /// With `color_correction` the pixels get the mean of the training views' corrections
    /// (`nerf_render::mean_color_correction`): novel views have none of their own; or one view's
    /// ([`set_render_appearance`](Self::set_render_appearance)).
    pub fn render_rays(
        &self,
        origins: &[f32],
        dirs: &[f32],
        background: &[f32],
        rgb: &mut [f32],
        opacity: &mut [f32],
        depth: &mut [f32],
    ) -> Result<(), TrainError> {
        self.render_rays_uncorrected(origins, dirs, background, rgb, opacity, depth)?;
        if let Some(params) = self.color_params()? {
            let correction = match self.render_appearance {
                None => mean_color_correction(&params).map_err(TrainError::Config)?.to_vec(),
                Some(k) => params.get(COLOR_PARAMS_PER_VIEW * k..COLOR_PARAMS_PER_VIEW * (k + 1)).map(<[f32]>::to_vec).ok_or_else(|| {
                    TrainError::Config(format!("appearance of training view {k}: the run has {} views", params.len() / COLOR_PARAMS_PER_VIEW))
                })?,
            };
            let raw = rgb.to_vec();
            color_correct_forward(None, &correction, &raw, opacity, background, rgb);
        }
        Ok(())
    }

    /// Renders with training view `view`'s colour correction (how that photo was exposed;
    /// instant-ngp's "latent from training view") instead of the mean of all views' (`None`).
    /// Errors when the run has no `color_correction` or no such view.
    pub fn set_render_appearance(&mut self, view: Option<usize>) -> Result<(), TrainError> {
        if let Some(k) = view {
            let Some(params) = self.color_params()? else {
                return Err(TrainError::Config("the run has no colour correction to render a view's appearance with (train with [color_correction])".into()));
            };
            let n = params.len() / COLOR_PARAMS_PER_VIEW;
            if k >= n {
                return Err(TrainError::Config(format!("appearance of training view {k}: the run's colour correction has {n} views (0..{n})")));
            }
        }
        self.render_appearance = view;
        Ok(())
    }

    /// Crops what [`render_rays`](Self::render_rays) shows to `crop` (instant-ngp's
    /// `render_aabb`, nerfstudio's crop box): every ray's segment, or its march through the
    /// occupancy grid, is clipped to the box, so only what lies inside is rendered and the rest
    /// is background. `None` renders the whole scene. Training never crops. Errors when the box
    /// lies wholly outside the scene's box (it would render nothing) and for NDC scenes (whose
    /// rays are not in the scene's frame). Every sampler crops, on either device.
    pub fn set_render_crop(&mut self, crop: Option<nerf_sampling::CropBox>) -> Result<(), TrainError> {
        if let Some(c) = &crop {
            if self.bounds.clip_to_box {
                return Err(TrainError::Config("a crop box needs Euclidean rays: this scene's rays are in NDC (train with --no-ndc)".into()));
            }
            let (lo, hi) = c.bounds();
            let (blo, bhi) = (self.bounds.aabb_min, self.bounds.aabb_max);
            if (0..3).any(|a| hi[a] <= blo[a] || lo[a] >= bhi[a]) {
                return Err(TrainError::Config(format!(
                    "the crop box (bounds {lo:?}..{hi:?}) lies outside the scene's box {blo:?}..{bhi:?}: it would render nothing"
                )));
            }
        }
        if let Some(g) = self.gpu.as_mut() {
            g.set_render_crop(crop);
        }
        self.render_crop = crop;
        Ok(())
    }

    /// The render crop box ([`set_render_crop`](Self::set_render_crop)).
    pub fn render_crop(&self) -> Option<&nerf_sampling::CropBox> {
        self.render_crop.as_ref()
    }

    /// [`render_rays`](Self::render_rays) without the colour correction.
    fn render_rays_uncorrected(
        &self,
        origins: &[f32],
        dirs: &[f32],
        background: &[f32],
        rgb: &mut [f32],
        opacity: &mut [f32],
        depth: &mut [f32],
    ) -> Result<(), TrainError> {
        if let Some(g) = &self.gpu {
            return g.render_rays(&self.config, origins, dirs, background, rgb, opacity, depth);
        }
        let ema_fields = self.ema_render_fields();
        let fields = ema_fields.as_ref().map_or(&self.fields, |g| &g.fields);
        let n = origins.len() / 3;
        let chunk = self.config.render_chunk_rays;
        let sampler = self.config.render_sampler().map_err(TrainError::Config)?;
        if let (Some(grid), SamplerConfig::Occupancy { step_size, max_samples_per_ray, cone_angle, .. }) = (self.grid.as_ref(), &sampler) {
            // Occupancy grid: rounds that stop marching a ray once it is opaque (same image), at
            // the render step (`render_step_size`) through the grid training keeps.
            let p = crate::rounds::MarchParams {
                step: self.bounds.stepping(*step_size, *cone_angle),
                max_samples: *max_samples_per_ray,
                near: self.bounds.near,
                far: self.bounds.far,
                t_threshold: self.config.transmittance_threshold,
                crop: self.render_crop,
            };
            // Chunks render concurrently (each its own rounds), so the marching and the field's
            // serial parts overlap; the image does not depend on the thread count.
            use rayon::prelude::*;
            let field = fields[0].as_ref();
            let pool = &self.round_scratch;
            rgb.par_chunks_mut(3 * chunk)
                .zip(opacity.par_chunks_mut(chunk))
                .zip(depth.par_chunks_mut(chunk))
                .enumerate()
                .for_each(|(i, ((rgb, opacity), depth))| {
                    let (r0, r1) = (i * chunk, (i * chunk + chunk).min(n));
                    pool.with(|scratch| {
                        crate::rounds::render_in_rounds(
                            grid,
                            p,
                            &origins[3 * r0..3 * r1],
                            &dirs[3 * r0..3 * r1],
                            &background[3 * r0..3 * r1],
                            scratch,
                            |pos, dir, sigma, c| field.query(pos, dir, sigma, c),
                            rgb,
                            opacity,
                            depth,
                        )
                    });
                });
            return Ok(());
        }
        self.stage_scratch.with(|s| self.render_stages(fields, origins, dirs, background, s, rgb, opacity, depth));
        Ok(())
    }

    /// The CPU render of [`render_rays_uncorrected`](Self::render_rays_uncorrected) without the
    /// occupancy grid's rounds: `render_chunk_rays` rays at a time through each field's stage.
    #[allow(clippy::too_many_arguments)]
    fn render_stages(
        &self,
        fields: &[Box<dyn RadianceField>],
        origins: &[f32],
        dirs: &[f32],
        background: &[f32],
        scratch: &mut StageScratch,
        rgb: &mut [f32],
        opacity: &mut [f32],
        depth: &mut [f32],
    ) {
        let n = origins.len() / 3;
        let chunk = self.config.render_chunk_rays;
        let StageScratch { stages, near, far } = scratch;
        stages.resize_with(fields.len(), Stage::default);
        for r0 in (0..n).step_by(chunk) {
            let r1 = (r0 + chunk).min(n);
            let (o, d, bg) = (&origins[3 * r0..3 * r1], &dirs[3 * r0..3 * r1], &background[3 * r0..3 * r1]);
            self.bounds.segments(o, d, near, far);
            if let Some(c) = &self.render_crop {
                nerf_sampling::crop_segments(c, o, d, self.bounds.near, near, far);
            }
            first_stage_samples(&self.config, &self.bounds, self.grid.as_ref(), o, d, near, far, None, &mut stages[0].samples);
            query_stage(fields[0].as_ref(), &mut stages[0], bg, self.config.transmittance_threshold);
            if let SamplerConfig::Hierarchical { n_fine, .. } = self.config.sampler {
                let (s0, s1) = stages.split_at_mut(1);
                hierarchical(&s0[0].samples, &s0[0].comp.weights, o, d, far, n_fine, None, &mut s1[0].samples);
                query_stage(fields[1].as_ref(), &mut s1[0], bg, self.config.transmittance_threshold);
            }
            let last = stages.last().unwrap();
            rgb[3 * r0..3 * r1].copy_from_slice(&last.comp.rgb);
            opacity[r0..r1].copy_from_slice(&last.comp.opacity);
            depth[r0..r1].copy_from_slice(&last.comp.depth);
        }
    }

    /// Density σ of the rendering field (the last: NeRF's fine network) at `positions` (`3·n`
    /// into `sigma`, `n`), on the trainer's device, with the parameters' moving average when
    /// rendering uses it ([`render_rays`](Self::render_rays)). For meshes: the field sampled on a
    /// lattice (`nerf_mesh`).
    pub fn density_at(&self, positions: &[f32], sigma: &mut [f32]) -> Result<(), TrainError> {
        self.points(positions, None, sigma, None)
    }

    /// Density σ (`n`) and colour (`3·n`) of the rendering field at `positions` seen along the
    /// unit `dirs` (`3·n` each), as [`density_at`](Self::density_at). For the colours of a
    /// mesh's vertices.
    pub fn query_points(&self, positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]) -> Result<(), TrainError> {
        self.points(positions, Some(dirs), sigma, Some(rgb))
    }

    fn points(&self, positions: &[f32], dirs: Option<&[f32]>, sigma: &mut [f32], mut rgb: Option<&mut [f32]>) -> Result<(), TrainError> {
        let n = sigma.len();
        assert!(positions.len() == 3 * n && dirs.is_none_or(|d| d.len() == 3 * n), "points: 3 values per point");
        assert!(rgb.as_ref().is_none_or(|c| c.len() == 3 * n), "points: 3 colour values per point");
        if let Some(g) = &self.gpu {
            return g.query_points(positions, dirs, sigma, rgb);
        }
        let ema_fields = self.ema_render_fields();
        let fields = ema_fields.as_ref().map_or(&self.fields, |g| &g.fields);
        let field = fields.last().expect("a trainer has a field").as_ref();
        // Bounded batches: a field's query allocates its activations per call.
        const BATCH: usize = 1 << 16;
        for p0 in (0..n).step_by(BATCH) {
            let p1 = (p0 + BATCH).min(n);
            let pos = &positions[3 * p0..3 * p1];
            match (dirs, rgb.as_deref_mut()) {
                (Some(d), Some(c)) => field.query(pos, &d[3 * p0..3 * p1], &mut sigma[p0..p1], &mut c[3 * p0..3 * p1]),
                _ => field.density(pos, &mut sigma[p0..p1]),
            }
        }
        Ok(())
    }

    /// The rendering instances holding the moving average, filled from it if it changed since;
    /// `None` without an average (off, or no update yet): render with the raw parameters.
    fn ema_render_fields(&self) -> Option<MutexGuard<'_, EmaFields>> {
        let (ema, cell) = (self.ema.as_ref()?, self.ema_fields.as_ref()?);
        if ema.step_count() == 0 {
            return None;
        }
        let mut guard = cell.lock().unwrap_or_else(|e| e.into_inner());
        if guard.synced != self.ema_version {
            for (f, names) in guard.fields.iter_mut().zip(&self.group_names) {
                for (g, name) in f.param_groups().into_iter().zip(names) {
                    let v = ema.values(name).expect("every group has an average after an update or a restore");
                    g.params.copy_from_slice(v);
                }
                f.after_optimizer_step();
            }
            guard.synced = self.ema_version;
        }
        Some(guard)
    }

    /// The parameters' moving average (`None` when `ema_decay` is off; no groups before the first
    /// step). Read back from the device on the GPU.
    pub fn ema_state(&self) -> Result<Option<EmaState>, TrainError> {
        if let Some(g) = &self.gpu {
            return g.ema_state();
        }
        Ok(self.ema.as_ref().map(|e| e.state()))
    }

    /// Parameters of every field instance (for checkpoints; read back from the device on the GPU).
    pub fn export_fields(&self) -> Result<crate::FieldParams, TrainError> {
        if let Some(g) = &self.gpu {
            return g.export_fields();
        }
        Ok(self.fields.iter().map(|f| f.export_params()).collect())
    }

    /// State besides parameters and optimiser that a resumed run needs, as named tensors: the
    /// sampler's (occupancy-grid densities, batch sizing), with `ema_decay` once a step was
    /// taken the parameters' moving average (`ema/step` and `ema/<group>`, see
    /// [`ema_to_entries`]), and with `color_correction` the corrections (`color/…`, see
    /// [`crate::views`]), and with `camera_optimizer` the pose corrections (`camera/…`). Checkpoints store it as is, so [`Trainer::restore`] — resume, `nerf
    /// eval`, a move between devices — carries the average without a separate argument.
    pub fn sampler_state(&self) -> Result<Vec<(String, Vec<f32>)>, TrainError> {
        let mut v = match &self.gpu {
            Some(g) => g.sampler_state()?,
            None => {
                let mut v = vec![("samples_per_ray".to_string(), vec![self.samples_per_ray])];
                if let Some(g) = &self.grid {
                    v.push(("occupancy_density".to_string(), g.densities().to_vec()));
                    if let Some(w) = g.seen_words() {
                        v.push((SEEN_ENTRY.to_string(), seen_to_entry(&w)));
                    }
                }
                v
            }
        };
        if let Some(s) = self.ema_state()? {
            v.extend(ema_to_entries(&s));
        }
        if let Some(s) = self.color_state()? {
            v.extend(s.to_entries(&COLOR_VIEWS));
        }
        if let Some(s) = self.pose_state()? {
            v.extend(s.to_entries(&POSE_VIEWS));
        }
        Ok(v)
    }

    /// The occupancy grid of the CPU path, when the sampler has one.
    pub fn occupancy_grid(&self) -> Option<&OccupancyGrid> {
        self.grid.as_ref()
    }

    /// A copy of the occupancy grid as training left it, on either device (the cell densities and
    /// seen marks read back from the GPU); `None` without an occupancy sampler. For masks over
    /// the scene (`nerf export-mesh`).
    pub fn occupancy_grid_now(&self) -> Result<Option<OccupancyGrid>, TrainError> {
        let (Some(grid), SamplerConfig::Occupancy { step_size, .. }) = (&self.grid, &self.config.sampler) else {
            return Ok(None);
        };
        let mut grid = grid.clone();
        if let Some(g) = &self.gpu {
            let state = g.sampler_state()?;
            if let Some(w) = seen_from_state(&state)? {
                grid.set_seen_words(&w).map_err(|e| TrainError::Config(format!("occupancy grid: {e}")))?;
            }
            if let Some((_, d)) = state.iter().find(|(n, _)| n == "occupancy_density") {
                grid.set_densities(d, *step_size).map_err(TrainError::Config)?;
            }
        }
        Ok(Some(grid))
    }

    /// The per-view colour corrections with their optimiser state (`None` without
    /// `color_correction`; read back from the device on the GPU). Checkpoints carry it in
    /// [`Trainer::sampler_state`].
    pub fn color_state(&self) -> Result<Option<ColorState>, TrainError> {
        if let Some(g) = &self.gpu {
            return g.color_state();
        }
        Ok(self.color.as_ref().map(|c| c.views.state()))
    }

    /// The per-view colour corrections only (12 values per training view; `None` without
    /// `color_correction`).
    pub fn color_params(&self) -> Result<Option<Vec<f32>>, TrainError> {
        if let Some(g) = &self.gpu {
            return g.color_params();
        }
        Ok(self.color.as_ref().map(|c| c.views.params.clone()))
    }

    /// The camera pose corrections with their optimiser state (`None` without
    /// `camera_optimizer`; read back from the device on the GPU). Checkpoints carry it in
    /// [`Trainer::sampler_state`].
    pub fn pose_state(&self) -> Result<Option<PoseState>, TrainError> {
        if let Some(g) = &self.gpu {
            return g.pose_state();
        }
        Ok(self.pose.as_ref().map(|p| p.views.state()))
    }

    /// The camera pose corrections only: per training view a translation then a rotation vector
    /// (`nerf_rays::pose`; `None` without `camera_optimizer`).
    pub fn pose_params(&self) -> Result<Option<Vec<f32>>, TrainError> {
        if let Some(g) = &self.gpu {
            return g.pose_params();
        }
        Ok(self.pose.as_ref().map(|p| p.views.params.clone()))
    }

    /// Optimiser state (for checkpoints; read back from the device on the GPU).
    pub fn adam_state(&self) -> Result<AdamState, TrainError> {
        if let Some(g) = &self.gpu {
            return g.adam_state();
        }
        Ok(self.adam.state())
    }

    /// Restores parameters, optimiser state, sampler state (with the moving average, when the
    /// checkpoint has one: see [`Trainer::sampler_state`]) and the step counter from a checkpoint.
    /// With `ema_decay` set and no average in the checkpoint, the average starts afresh (the next
    /// step copies the parameters); an average in the checkpoint of a run without `ema_decay` is
    /// ignored. The colour corrections (`color_correction`) are treated alike: kept at the
    /// identity when the checkpoint has none, ignored when the config has none; they are taken
    /// for however many views they are (a trainer built on the test views renders with their
    /// mean), and a training step on a dataset with another number of views is an error.
    pub fn restore(
        &mut self,
        step: u64,
        fields: &[Vec<(String, Vec<f32>)>],
        adam: AdamState,
        sampler_state: &[(String, Vec<f32>)],
    ) -> Result<(), TrainError> {
        let (color, sampler_state) = ColorState::from_entries(sampler_state, &COLOR_VIEWS)?;
        let (pose, sampler_state) = PoseState::from_entries(&sampler_state, &POSE_VIEWS)?;
        let (ema, sampler_state) = ema_from_entries(&sampler_state)?;
        // A checkpoint without corrections leaves them at the identity; corrections in the
        // checkpoint of a run without them are ignored.
        let color = color.filter(|_| self.config.color_correction.is_some());
        let pose = pose.filter(|_| self.config.camera_optimizer.is_some());
        if let (Some(p), Some(s)) = (&pose, self.pose.as_mut()) {
            s.views.load(p.clone())?;
        }
        if let (Some(s), Some(_)) = (&ema, self.config.ema_decay) {
            check_ema_groups(s, &self.group_names, fields)?;
        }
        let ema = ema.unwrap_or(EmaState { step: 0, groups: Vec::new() });
        // Marks stored in the checkpoint come back with the densities (so that the threshold and
        // bits are the trained grid's); without them the cameras mark again at the next step.
        let seen = seen_from_state(&sampler_state)?;
        self.seen_marked = seen.is_some();
        if let Some(g) = self.gpu.as_mut() {
            let ema = self.config.ema_decay.is_some().then_some(&ema);
            g.restore(fields, &adam, &sampler_state, seen.as_deref(), ema)?;
            if let Some(c) = color {
                g.restore_color(c)?;
            }
            if let Some(p) = pose {
                g.restore_pose(p)?;
            }
            self.step = step;
            return Ok(());
        }
        if let (Some(w), Some(g)) = (&seen, self.grid.as_mut()) {
            g.set_seen_words(w).map_err(|e| TrainError::Config(format!("checkpoint: {e}")))?;
        }
        for (name, v) in &sampler_state {
            match (name.as_str(), self.grid.as_mut(), &self.config.sampler) {
                ("samples_per_ray", _, _) if v.len() == 1 => self.samples_per_ray = v[0],
                ("occupancy_density", Some(g), SamplerConfig::Occupancy { step_size, .. }) => {
                    g.set_densities(v, *step_size).map_err(TrainError::Config)?
                }
                (SEEN_ENTRY, Some(_), _) => {}
                _ => return Err(TrainError::Config(format!("unexpected sampler state `{name}` in checkpoint"))),
            }
        }
        if fields.len() != self.fields.len() {
            return Err(TrainError::Config(format!(
                "checkpoint holds {} field instances, this config needs {}",
                fields.len(),
                self.fields.len()
            )));
        }
        for (f, groups) in self.fields.iter_mut().zip(fields) {
            f.import_params(groups)?;
        }
        self.adam.load_state(adam).map_err(TrainError::Config)?;
        if let (Some(c), Some(s)) = (color, self.color.as_mut()) {
            s.views.load(c)?;
        }
        if let Some(e) = self.ema.as_mut() {
            e.load_state(ema).map_err(TrainError::Config)?;
            self.ema_version += 1;
        }
        for f in self.fields.iter_mut() {
            f.after_optimizer_step();
        }
        self.step = step;
        Ok(())
    }
}

/// Name of the occupancy grid's seen marks in [`Trainer::sampler_state`] (see [`seen_to_entry`]).
pub const SEEN_ENTRY: &str = "occupancy_seen";

/// The grid's seen marks (`OccupancyGrid::seen_words`) as checkpoint values: each 32-bit word as
/// two `f32`s holding its low and high 16 bits (integers, exact in `f32`).
pub fn seen_to_entry(words: &[u32]) -> Vec<f32> {
    words.iter().flat_map(|&w| [(w & 0xFFFF) as f32, (w >> 16) as f32]).collect()
}

/// The inverse of [`seen_to_entry`]; errors on an odd length or a value that is not an integer
/// in `0..65536`.
pub fn seen_from_entry(v: &[f32]) -> Result<Vec<u32>, TrainError> {
    let half = |x: f32| ((0.0..65536.0).contains(&x) && x.fract() == 0.0).then_some(x as u32);
    if !v.len().is_multiple_of(2) {
        return Err(TrainError::Config(format!("malformed `{SEEN_ENTRY}` in checkpoint: odd length {}", v.len())));
    }
    v.chunks(2)
        .map(|p| match (half(p[0]), half(p[1])) {
            (Some(lo), Some(hi)) => Ok(lo | hi << 16),
            _ => Err(TrainError::Config(format!("malformed `{SEEN_ENTRY}` in checkpoint: {p:?} are not 16-bit halves"))),
        })
        .collect()
}

/// The seen marks of a checkpoint's sampler state, when it has them.
fn seen_from_state(state: &[(String, Vec<f32>)]) -> Result<Option<Vec<u32>>, TrainError> {
    state.iter().find(|(n, _)| n == SEEN_ENTRY).map(|(_, v)| seen_from_entry(v)).transpose()
}

/// Name of the moving average's update count in [`Trainer::sampler_state`].
pub const EMA_STEP_ENTRY: &str = "ema/step";
/// The prefixes of the parameter groups' names (`<prefix>/<group>`, as Adam and the moving
/// average know them) of a run with `n` field instances: `field`, or `coarse` and `fine`.
pub(crate) fn group_prefixes(n: usize) -> &'static [&'static str] {
    if n == 1 {
        &["field"]
    } else {
        &["coarse", "fine"]
    }
}

/// Prefix of the moving average's per-group values in [`Trainer::sampler_state`].
pub const EMA_PREFIX: &str = "ema/";

/// The moving average as named tensors (nothing before its first update): `ema/step` holds the
/// update count as `[count mod 2^24, count / 2^24]` (both exact in `f32`), then `ema/<group>`
/// holds each group's values.
pub fn ema_to_entries(s: &EmaState) -> Vec<(String, Vec<f32>)> {
    if s.step == 0 {
        return Vec::new();
    }
    let step = vec![(s.step & 0xFF_FFFF) as f32, (s.step >> 24) as f32];
    std::iter::once((EMA_STEP_ENTRY.to_string(), step))
        .chain(s.groups.iter().map(|(n, v)| (format!("{EMA_PREFIX}{n}"), v.clone())))
        .collect()
}

/// Splits the moving average ([`ema_to_entries`]) off a list of state tensors: `(average if
/// present, the other tensors)`. Errors on group values without an update count or a malformed
/// count.
#[allow(clippy::type_complexity)]
pub fn ema_from_entries(
    state: &[(String, Vec<f32>)],
) -> Result<(Option<EmaState>, Vec<(String, Vec<f32>)>), TrainError> {
    let mut step = None;
    let mut groups = Vec::new();
    let mut rest = Vec::new();
    for (name, v) in state {
        if name == EMA_STEP_ENTRY {
            let ok = v.len() == 2 && v.iter().all(|x| *x >= 0.0 && x.fract() == 0.0 && *x < (1u64 << 24) as f32);
            if !ok {
                return Err(TrainError::Config(format!("malformed `{EMA_STEP_ENTRY}` in checkpoint: {v:?}")));
            }
            step = Some(v[0] as u64 | ((v[1] as u64) << 24));
        } else if let Some(g) = name.strip_prefix(EMA_PREFIX) {
            groups.push((g.to_string(), v.clone()));
        } else {
            rest.push((name.clone(), v.clone()));
        }
    }
    match step {
        Some(step) => Ok((Some(EmaState { step, groups }), rest)),
        None if groups.is_empty() => Ok((None, rest)),
        None => Err(TrainError::Config(format!("checkpoint has EMA values but no `{EMA_STEP_ENTRY}`"))),
    }
}

/// A restored average must cover every parameter group of the run, with the parameters' lengths.
pub(crate) fn check_ema_groups(s: &EmaState, group_names: &[Vec<String>], fields: &[Vec<(String, Vec<f32>)>]) -> Result<(), TrainError> {
    if s.step == 0 {
        return Ok(());
    }
    for (names, groups) in group_names.iter().zip(fields) {
        for (name, (_, v)) in names.iter().zip(groups) {
            match s.groups.iter().find(|(n, _)| n == name) {
                Some((_, e)) if e.len() == v.len() => {}
                Some((_, e)) => {
                    return Err(TrainError::Config(format!(
                        "checkpoint EMA of group `{name}` has {} values, the parameters {}",
                        e.len(),
                        v.len()
                    )))
                }
                None => return Err(TrainError::Config(format!("checkpoint EMA lacks group `{name}`"))),
            }
        }
    }
    Ok(())
}

/// Upper bound on the samples one ray can get from the sampler (all stages).
fn max_samples_per_ray(s: &SamplerConfig) -> usize {
    match *s {
        SamplerConfig::Stratified { n_samples } => n_samples,
        SamplerConfig::Hierarchical { n_coarse, n_fine } => n_coarse + n_fine,
        SamplerConfig::Occupancy { max_samples_per_ray, .. } => max_samples_per_ray,
    }
}

/// The samples the first (or only) field sees: stratified, or marched through the occupancy grid.
#[allow(clippy::too_many_arguments)]
fn first_stage_samples(
    cfg: &TrainConfig,
    bounds: &SceneBounds,
    grid: Option<&OccupancyGrid>,
    origins: &[f32],
    dirs: &[f32],
    near: &[f32],
    far: &[f32],
    rng: Option<&mut nerf_core::Rng>,
    out: &mut RaySamples,
) {
    match &cfg.sampler {
        SamplerConfig::Stratified { n_samples: n } | SamplerConfig::Hierarchical { n_coarse: n, .. } => {
            stratified(origins, dirs, near, far, *n, rng, out)
        }
        SamplerConfig::Occupancy { step_size, max_samples_per_ray, cone_angle, .. } => {
            let grid = grid.expect("occupancy sampler has a grid");
            let stepping = bounds.stepping(*step_size, *cone_angle);
            march(grid, origins, dirs, near, far, stepping, *max_samples_per_ray, rng, out)
        }
    }
}

fn forward_stage(field: &mut dyn RadianceField, st: &mut Stage, background: &[f32], thr: f32) {
    run_stage(st, background, thr, |p, d, s, c| field.forward(p, d, s, c));
}

fn query_stage(field: &dyn RadianceField, st: &mut Stage, background: &[f32], thr: f32) {
    run_stage(st, background, thr, |p, d, s, c| field.query(p, d, s, c));
}

/// Evaluates the field on the stage's samples (`eval`: training forward or inference) and
/// composites them.
fn run_stage(
    st: &mut Stage,
    background: &[f32],
    thr: f32,
    eval: impl FnOnce(&[f32], &[f32], &mut [f32], &mut [f32]),
) {
    let n = st.samples.len();
    st.sigma.resize(n, 0.0);
    st.rgb.resize(3 * n, 0.0);
    eval(&st.samples.positions, &st.samples.dirs, &mut st.sigma, &mut st.rgb);
    composite_forward(
        &st.samples.ray_offsets,
        &st.sigma,
        &st.rgb,
        &st.samples.dt,
        &st.samples.t,
        Some(background),
        thr,
        &mut st.comp,
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A path within the training cameras' distances keeps the bounds; one farther out moves
    /// `far` out by as much, one nearer moves `near` in (not below 0); the scene then lies
    /// within the rays' segments from those cameras.
    #[test]
    fn bounds_for_a_path_cover_the_scene_from_its_cameras() {
        use nerf_rays::glam::Vec3;
        use nerf_rays::{Camera, Intrinsics};
        let k = Intrinsics { width: 8, height: 8, fx: 8.0, fy: 8.0, cx: 4.0, cy: 4.0 };
        // Cameras on +x looking at the origin down −x (OpenGL axes: back = +x).
        let at = |x: f32| Camera::from_c2w(k, &[[0.0, 0.0, 1.0, x], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]).unwrap();
        let b = SceneBounds {
            aabb_min: [-1.5; 3],
            aabb_max: [1.5; 3],
            near: 2.0,
            far: 6.0,
            clip_to_box: false,
            cascades: 1,
            cone_angle: 0.0,
            scene_scale: 1.0,
            n_views: 2,
        };
        let training = [at(3.5), at(4.5)];
        assert_eq!(b.for_path(&training, &[at(4.0), at(3.5)]), b, "within the training distances");
        assert_eq!(b.for_path(&training, &[at(4.5001), at(3.4999)]), b, "rounding");
        let out = b.for_path(&training, &[at(4.0), at(8.0)]);
        assert_eq!((out.near, out.far), (2.0, 9.5));
        let inn = b.for_path(&training, &[at(2.0), at(0.5)]);
        assert_eq!((inn.near, inn.far), (0.0, 6.0));
        // From 8 away the box spans t ∈ [6.5, 9.5] along the axis: inside the new segment.
        let (mut near, mut far) = (Vec::new(), Vec::new());
        out.segments(&[8.0, 0.0, 0.0], &(-Vec3::X).to_array(), &mut near, &mut far);
        assert!(near[0] <= 6.5 && far[0] >= 9.5, "{near:?} {far:?}");
        assert_eq!(b.for_path(&[], &[at(8.0)]), b);
    }

    #[test]
    fn alive_mse_counts_only_rays_with_opacity() {
        let opacity = [0.0f32, 0.5, 1e-30, 0.0, 1.0];
        let sq = [9.0f64, 0.3, 0.6, 5.0, 0.0];
        let (n, m) = alive_mse(&opacity, |r| sq[r]);
        assert_eq!(n, 3);
        assert!((m as f64 - 0.9 / 9.0).abs() < 1e-7, "{m}");
        let (n, m) = alive_mse(&[0.0, 0.0], |_| 1.0);
        assert!(n == 0 && m.is_nan());
    }

    #[test]
    fn seen_marks_round_trip_through_checkpoint_values() {
        let words = vec![0u32, u32::MAX, 0x8000_0001, 0x1234_5678, 0xFFFF_0000];
        let v = seen_to_entry(&words);
        assert_eq!(v.len(), 2 * words.len());
        assert_eq!(seen_from_entry(&v).unwrap(), words);
        let state = vec![("samples_per_ray".to_string(), vec![3.0]), (SEEN_ENTRY.to_string(), v.clone())];
        assert_eq!(seen_from_state(&state).unwrap(), Some(words));
        assert_eq!(seen_from_state(&state[..1]).unwrap(), None);
        // A value that is not a 16-bit half, or an odd count, is a malformed checkpoint.
        for bad in [vec![1.5, 0.0], vec![65536.0, 0.0], vec![-1.0, 0.0], vec![f32::NAN, 0.0], vec![1.0]] {
            let e = seen_from_entry(&bad).unwrap_err().to_string();
            assert!(e.contains(SEEN_ENTRY), "{e}");
        }
    }

    #[test]
    fn the_scenes_cone_fills_in_only_what_the_config_leaves_out() {
        let b = SceneBounds {
            aabb_min: [-1.0; 3],
            aabb_max: [1.0; 3],
            near: 0.1,
            far: 5.0,
            clip_to_box: true,
            cascades: 3,
            cone_angle: NGP_CONE_ANGLE,
            scene_scale: 4.0,
            n_views: 1,
        };
        assert_eq!(b.stepping(0.01, None).cone_angle, 1.0 / 256.0);
        assert_eq!(b.stepping(0.01, Some(0.0)).cone_angle, 0.0);
        assert_eq!(b.stepping(0.01, Some(0.5)).cone_angle, 0.5);
        assert_eq!(b.stepping(0.01, None).step, 0.01);
    }
}
