//! The GPU execution path of the [`Trainer`](crate::Trainer): the same step as the CPU path —
//! random rays from the training images, sampling, field forward, compositing, loss, backward,
//! Adam, occupancy-grid updates — recorded into one command buffer per step and submitted without
//! waiting. Nothing is read back during training except the loss every `log_every` steps.
//!
//! Device buffers are sized once, from the config: `capacity_rays` rays and `capacity_samples`
//! samples per stage. The number of rays and samples of a step live in a `counters` buffer
//! (`[n_rays, n_samples]`) written by the kernels themselves (batch sizing, marching).

use crate::config::{SamplerConfig, TrainConfig};
use crate::profile::{GpuProfile, ProfileAccumulator};
use crate::trainer::{SceneBounds, StepStats};
use crate::TrainError;
use nerf_data::Dataset;
use nerf_field::{ChunkedDensity, GpuRadianceField, GpuSamples, RadianceField};
use nerf_gpu::compact::GpuCompactor;
use nerf_gpu::composite::{BatchParams, CompositeTargets, PackedBuffers};
use nerf_gpu::occupancy::GpuOccupancyGrid;
use nerf_gpu::optim::{GpuAdam, GpuParamGroup};
use nerf_gpu::pdf::{GpuHierarchical, GpuStratified, PackedOut};
use crate::color::{ColorState, COLOR_GROUP, COLOR_VIEWS};
use nerf_gpu::color::{ColorInputs, GpuColorCorrection};
use crate::pose::{PoseState, POSE_VIEWS};
use nerf_gpu::pose::{GpuPoseCorrection, PoseRays, PoseSampleGrads};
use nerf_gpu::sampling::{GpuImages, GpuMarcher, GpuRayGen, GpuRays, GpuSamples as PackedSamples, MarchConfig};
use nerf_gpu::{wgpu, Compositor, GpuContext, TrainGlue};
use nerf_optim::{AdamState, EmaState};
use std::cell::Cell;
use std::sync::Arc;

fn gerr(e: nerf_gpu::GpuError) -> TrainError {
    match e {
        nerf_gpu::GpuError::CapacityTooLarge { bytes, limit, .. } => {
            TrainError::GpuCapacity { message: e.to_string(), bytes, limit }
        }
        e => TrainError::Gpu(e.to_string()),
    }
}

/// A field's GPU twin failed to build: [`TrainError::GpuCapacity`] where one of its per-sample
/// buffers exceeds the adapter's binding limit (the trainer then launches fewer samples).
fn field_err(kind: &str) -> impl FnOnce(nerf_field::FieldError) -> TrainError + '_ {
    use nerf_field::FieldError;
    move |e| {
        // `FieldError::Gpu` already names the field and the device.
        let message = match &e {
            FieldError::Gpu { .. } => e.to_string(),
            _ => format!("field `{kind}` on the GPU: {e}"),
        };
        match e {
            FieldError::Gpu { source: nerf_gpu::GpuError::CapacityTooLarge { bytes, limit, .. }, .. } => {
                TrainError::GpuCapacity { message, bytes, limit }
            }
            _ => TrainError::Gpu(message),
        }
    }
}

/// Bounds on the adaptive number of rays per step (as the CPU path).
const MIN_BATCH_RAYS: usize = 64;
const MAX_BATCH_RAYS: usize = 1 << 20;
/// Steps submitted but not yet waited for.
const MAX_IN_FLIGHT: usize = 3;
/// RNG streams of the device kernels (seeds are per step).
const SEED_MIX: u64 = 0x9E37_79B9_7F4A_7C15;

/// Buffers of one sampling stage (one field instance), sized for the capacities.
struct Stage {
    counters: wgpu::Buffer,
    /// The packed layout: offsets, positions, dirs, t, dt.
    packed: PackedSamples,
    sigma: wgpu::Buffer,
    rgb: wgpu::Buffer,
    weights: wgpu::Buffer,
    ray_rgb: wgpu::Buffer,
    opacity: wgpu::Buffer,
    depth: wgpu::Buffer,
    d_ray_rgb: wgpu::Buffer,
    sq_err: wgpu::Buffer,
    /// The distortion loss per ray (`distortion_loss`, last stage).
    ray_loss: wgpu::Buffer,
    /// The depth loss per ray and its gradient w.r.t. the expected depth (`depth_loss`).
    depth_loss: wgpu::Buffer,
    d_depth: wgpu::Buffer,
    d_sigma: wgpu::Buffer,
    d_rgb: wgpu::Buffer,
    /// `counters` as this step used them, copied before the next batch size overwrites
    /// `[n_rays]` (read back with the loss).
    logged: wgpu::Buffer,
}

impl Stage {
    fn new(ctx: &GpuContext, rays: usize, samples: usize) -> Self {
        let f = |label: &str, n: usize| ctx.zeros(label, 4 * n);
        Self {
            counters: f("counters", 4),
            packed: PackedSamples::new(ctx, rays, samples),
            sigma: f("sigma", samples),
            rgb: f("rgb", 3 * samples),
            weights: f("weights", samples),
            ray_rgb: f("ray rgb", 3 * rays),
            opacity: f("opacity", rays),
            depth: f("depth", rays),
            d_ray_rgb: f("d ray rgb", 3 * rays),
            sq_err: f("sq err", rays),
            ray_loss: f("ray loss", rays),
            depth_loss: f("depth loss", rays),
            d_depth: f("d depth", rays),
            d_sigma: f("d sigma", samples),
            d_rgb: f("d rgb", 3 * samples),
            logged: f("logged counters", 4),
        }
    }

    fn packed_out(&self) -> PackedOut<'_> {
        let p = &self.packed;
        PackedOut { offsets: &p.offsets, positions: &p.positions, dirs: &p.dirs, t: &p.t, dt: &p.dt }
    }

    fn samples(&self) -> GpuSamples<'_> {
        GpuSamples {
            counters: &self.counters,
            positions: &self.packed.positions,
            dirs: &self.packed.dirs,
            capacity: self.packed.capacity_samples,
        }
    }
}

/// Most marching steps per ray and rendering round (instant-ngp: 8 between compactions).
const ROUND_STEPS: u32 = 8;
/// Rendering rounds recorded per submission (the host reads the alive count in between).
const ROUNDS_PER_SUBMISSION: usize = 8;

/// Rays and image of one rendered frame.
struct Frame {
    n: usize,
    /// Ray states and alive lists of rendering in rounds (occupancy sampler).
    rounds: Option<nerf_gpu::sampling::RoundFrame>,
    origins: wgpu::Buffer,
    dirs: wgpu::Buffer,
    background: wgpu::Buffer,
    rgb: wgpu::Buffer,
    opacity: wgpu::Buffer,
    depth: wgpu::Buffer,
}

/// The most rays one frame's buffers hold, whatever the adapter allows: 2^22 (a 2048² frame,
/// ~330 MB of buffers; an 800×800 view is 640 000 rays).
pub(crate) const MAX_FRAME_RAYS: usize = 1 << 22;

/// The rays of one part of a GPU render on an adapter whose largest storage buffer (and binding)
/// is `max_storage_bytes`: as many as the rounds' per-ray state fits, at most
/// [`MAX_FRAME_RAYS`], at least 1.
fn frame_part_rays(max_storage_bytes: u64) -> usize {
    let rays = max_storage_bytes / nerf_gpu::sampling::GpuMarcher::ROUND_BYTES_PER_RAY as u64;
    (rays.min(MAX_FRAME_RAYS as u64) as usize).max(1)
}

impl Frame {
    fn new(ctx: &GpuContext, n: usize, sampler: &Sampler, capacity_samples: usize) -> Self {
        Self {
            n,
            rounds: match sampler {
                Sampler::Occupancy(o) => Some(o.marcher.round_frame(ctx, n, capacity_samples)),
                _ => None,
            },
            origins: ctx.zeros("frame origins", 12 * n),
            dirs: ctx.zeros("frame dirs", 12 * n),
            background: ctx.zeros("frame background", 12 * n),
            rgb: ctx.zeros("frame rgb", 12 * n),
            opacity: ctx.zeros("frame opacity", 4 * n),
            depth: ctx.zeros("frame depth", 4 * n),
        }
    }
}

/// The occupancy-grid sampler's state.
struct Occupancy {
    grid: GpuOccupancyGrid,
    marcher: GpuMarcher,
    step_size: f32,
    /// Buffers of the grid update (cell points, chosen cells, σ, counters).
    points: wgpu::Buffer,
    cells: wgpu::Buffer,
    sigma: wgpu::Buffer,
    counters: wgpu::Buffer,
    /// The density query at those points, in chunks of the field's capacity.
    density: ChunkedDensity,
    /// The cells a training camera sees, once marked (`OccupancyGrid::seen_words`), for
    /// checkpoints.
    seen: Option<Vec<u32>>,
}

/// Training on compacted samples (`compact_samples`): the marched samples of a step and their
/// density (the inference pass), compacted into stage 0's buffers before the training forward.
struct Compaction {
    /// A marcher sized for the marched samples (the occupancy sampler's own marcher keeps the
    /// stage's capacity for rendering).
    marcher: GpuMarcher,
    counters: wgpu::Buffer,
    packed: PackedSamples,
    sigma: wgpu::Buffer,
    compactor: GpuCompactor,
    /// The density pass, in chunks of the field's capacity (the stage's), so compaction does not
    /// enlarge the field's buffers.
    density: ChunkedDensity,
    /// Row in the marched samples of each kept one (`record_forward_rows`).
    rows: wgpu::Buffer,
}

enum Sampler {
    Occupancy(Box<Occupancy>),
    Stratified(GpuStratified),
    Hierarchical(GpuStratified, Box<GpuHierarchical>),
}

/// The GPU twin of the CPU trainer's state.
pub(crate) struct GpuEngine {
    ctx: Arc<GpuContext>,
    fields: Vec<Box<dyn GpuRadianceField>>,
    /// One optimiser per parameter group (the groups live in separate buffers); each keeps the
    /// group's moving average when `ema_decay` is set.
    adams: Vec<Vec<GpuAdam>>,
    /// With `ema_decay`: one buffer per parameter group that holds the raw parameters while a
    /// render runs with the average copied into the parameter buffers (so the fields' bind groups
    /// stay valid).
    ema_backup: Vec<Vec<wgpu::Buffer>>,
    group_names: Vec<Vec<String>>,
    /// The training images on the device, with the identity of the dataset they came from.
    images: Option<((usize, usize, u32, u32), GpuImages)>,
    raygen: GpuRayGen,
    sampler: Sampler,
    compositor: Compositor,
    glue: TrainGlue,
    rays: GpuRays,
    stages: Vec<Stage>,
    /// With `compact_samples`: the inference pass's buffers and the compaction kernels.
    compaction: Option<Compaction>,
    /// Running mean of samples per ray (`[0]`), device side.
    spr: wgpu::Buffer,
    /// Samples evaluated so far: `[lo, hi]` u32, device side.
    seen: wgpu::Buffer,
    capacity_rays: usize,
    capacity_samples: usize,
    /// Rays of the first step (before the running mean exists).
    first_rays: usize,
    adaptive: bool,
    /// Samples trained on and marched in the last step whose counters were read.
    last_n_samples: Cell<(usize, usize)>,
    /// Rays per rendering chunk that last fitted the sample capacity.
    render_chunk: Cell<usize>,
    /// The render crop box (`Trainer::set_render_crop`), queued for each render only.
    render_crop: Option<nerf_sampling::CropBox>,
    /// Frame-sized rendering buffers (rays in, image out), kept between frames.
    frame: std::cell::RefCell<Option<Frame>>,
    /// Submissions of the steps still running (at most `MAX_IN_FLIGHT`).
    in_flight: std::collections::VecDeque<wgpu::SubmissionIndex>,
    /// Pass timings of the steps of `TrainConfig::gpu_profile` so far.
    profile: ProfileAccumulator,
    /// Set once the profile window is complete; taken by [`GpuEngine::take_profile`].
    profile_done: Option<GpuProfile>,
    /// The per-view colour correction (`color_correction`).
    color: Option<GpuColor>,
    /// Camera pose refinement (`camera_optimizer`).
    pose: Option<GpuPose>,
}

/// Camera pose refinement on the device: the corrections and their kernels, their Adam, and the
/// fields' input gradients of one stage (reused by the stages, which run one after the other).
struct GpuPose {
    pc: GpuPoseCorrection,
    adam: GpuAdam,
    adam_config: nerf_optim::AdamConfig,
    config: crate::config::CameraOptimizerConfig,
    /// ∂L/∂x per sample of a stage, `3·capacity` of the largest stage.
    d_positions: wgpu::Buffer,
    /// ∂L/∂(view direction) per sample of a stage.
    d_dirs: wgpu::Buffer,
}

/// The colour correction on the device: corrections, their Adam, and the per-ray buffers
/// between compositing, loss and compositing's backward (shared by the stages, which run one
/// after the other in a step's encoder).
struct GpuColor {
    cc: GpuColorCorrection,
    adam: GpuAdam,
    adam_config: nerf_optim::AdamConfig,
    lr: f32,
    /// Corrected pixels (what the loss sees), `3·capacity_rays`.
    out: wgpu::Buffer,
    /// ∂L/∂opacity from the correction, `capacity_rays`.
    d_opacity: wgpu::Buffer,
}

impl GpuEngine {
    /// Moves the CPU fields to the device and builds every kernel and buffer of a step.
    pub(crate) fn new(
        ctx: Arc<GpuContext>,
        config: &TrainConfig,
        bounds: SceneBounds,
        cpu_fields: &[Box<dyn RadianceField>],
        group_names: &[Vec<String>],
    ) -> Result<Self, TrainError> {
        let (capacity_rays, capacity_samples) = capacities(config);
        // With compaction the marched samples get their own buffers. With an adaptive batch (which
        // targets the trained samples) they hold 8 × the target (4 × the stage's capacity): a
        // step marches trained / kept fraction samples, and lego at 800×800 keeps about a quarter
        // of them (on the H100 the 4 × of 2026-11-27 filled from step 7000 on, so the batch's
        // last rays went unmarched; instant-ngp sizes its buffer at 16 × the target). A fixed
        // batch's capacity already holds every sample its rays can get. The density pass over
        // them runs in chunks of the stage's capacity.
        let capacity_marched = match (config.compact_samples, config.target_samples_per_step) {
            (true, Some(_)) => 4 * capacity_samples,
            _ => capacity_samples,
        };
        if config.gpu_profile.is_some() && !ctx.features.timestamps {
            return Err(TrainError::Gpu(format!(
                "gpu_profile needs timestamp queries, which the adapter {} lacks",
                ctx.describe()
            )));
        }

        let stage_samples = |i: usize| match config.sampler {
            SamplerConfig::Hierarchical { n_coarse, n_fine } if i == 1 => capacity_rays * (n_coarse + n_fine),
            _ => capacity_samples,
        };
        let mut fields = Vec::with_capacity(cpu_fields.len());
        for (i, f) in cpu_fields.iter().enumerate() {
            match f.to_gpu(&ctx, stage_samples(i)) {
                Some(g) => fields.push(g.map_err(field_err(f.kind()))?),
                None => {
                    return Err(TrainError::Gpu(format!(
                        "field `{}` has no GPU implementation (use --device cpu)",
                        f.kind()
                    )))
                }
            }
        }
        let mut adams = Vec::with_capacity(fields.len());
        for (f, names) in fields.iter().zip(group_names) {
            let mut per = Vec::new();
            for (g, name) in f.groups().iter().zip(names) {
                let group = GpuParamGroup::new(name.clone(), 0, g.len, g.weight_decay);
                per.push(GpuAdam::with_ema(&ctx, &config.adam, &[group], config.ema_decay).map_err(gerr)?);
            }
            adams.push(per);
        }
        let ema_backup = match config.ema_decay {
            Some(_) => fields
                .iter()
                .map(|f| f.groups().iter().map(|g| ctx.zeros("ema backup", 4 * g.len.max(1))).collect())
                .collect(),
            None => Vec::new(),
        };
        let n_stages = config.sampler.n_fields();
        let stages: Vec<Stage> = (0..n_stages).map(|i| Stage::new(&ctx, capacity_rays, stage_samples(i))).collect();
        let mut compaction = None;
        let sampler = match &config.sampler {
            SamplerConfig::Occupancy { grid, step_size, max_samples_per_ray, cone_angle } => {
                let g = GpuOccupancyGrid::new(&ctx, &bounds.grid_config(grid), (bounds.aabb_min, bounds.aabb_max)).map_err(gerr)?;
                let n_cells = g.n_cells();
                let mc = MarchConfig {
                    aabb_min: bounds.aabb_min,
                    aabb_max: bounds.aabb_max,
                    resolution: g.resolution() as u32,
                    cascades: g.cascades() as u32,
                    step_size: *step_size,
                    near: bounds.near,
                    far: bounds.far,
                    max_samples_per_ray: *max_samples_per_ray as u32,
                    cone_angle: bounds.stepping(*step_size, *cone_angle).cone_angle,
                };
                let marcher = GpuMarcher::new(&ctx, mc, capacity_rays, capacity_samples).map_err(gerr)?;
                if config.compact_samples {
                    // The field may keep what its density pass computes for the kept samples.
                    fields[0]
                        .keep_density_pass(&ctx, capacity_marched)
                        .map_err(field_err(cpu_fields[0].kind()))?;
                    compaction = Some(Compaction {
                        marcher: GpuMarcher::new(&ctx, mc, capacity_rays, capacity_marched).map_err(gerr)?,
                        counters: ctx.zeros("marched counters", 16),
                        packed: PackedSamples::new(&ctx, capacity_rays, capacity_marched),
                        sigma: ctx.zeros("marched sigma", 4 * capacity_marched),
                        compactor: GpuCompactor::new(&ctx, capacity_rays, capacity_samples, config.transmittance_threshold)
                            .map_err(gerr)?,
                        density: ChunkedDensity::new(&ctx, capacity_samples, capacity_marched),
                        rows: ctx.zeros("compacted rows", 4 * capacity_samples.max(1)),
                    });
                }
                Sampler::Occupancy(Box::new(Occupancy {
                    marcher,
                    step_size: *step_size,
                    points: ctx.zeros("occupancy points", 12 * n_cells),
                    cells: ctx.zeros("occupancy cells", 4 * n_cells),
                    sigma: ctx.zeros("occupancy sigma", 4 * n_cells),
                    counters: ctx.zeros("occupancy counters", 16),
                    density: ChunkedDensity::new(&ctx, capacity_samples, n_cells),
                    grid: g,
                    seen: None,
                }))
            }
            SamplerConfig::Stratified { n_samples } => {
                Sampler::Stratified(clip_coarse(GpuStratified::new(&ctx, *n_samples, bounds.near, bounds.far).map_err(gerr)?, &bounds))
            }
            SamplerConfig::Hierarchical { n_coarse, n_fine } => Sampler::Hierarchical(
                clip_coarse(GpuStratified::new(&ctx, *n_coarse, bounds.near, bounds.far).map_err(gerr)?, &bounds),
                Box::new(clip_fine(GpuHierarchical::new(&ctx, *n_fine, bounds.far).map_err(gerr)?, &bounds)),
            ),
        };
        let max_rays = capacity_rays.min(MAX_BATCH_RAYS);
        let batch = BatchParams {
            target_samples: config.target_samples_per_step.unwrap_or(0) as u32,
            min_rays: MIN_BATCH_RAYS.min(max_rays) as u32,
            max_rays: max_rays as u32,
            _pad: 0,
        };
        let first_rays = match config.target_samples_per_step {
            Some(t) => (t / max_samples_per_ray(&config.sampler).max(1)).clamp(MIN_BATCH_RAYS, max_rays),
            None => capacity_rays,
        };
        for st in &stages {
            ctx.write(&st.counters, 0, &[first_rays as u32, 0u32]);
        }
        let glue = TrainGlue::new(&ctx, capacity_rays, batch);
        glue.set_huber_delta(&ctx, config.loss.huber_delta());
        let compositor = Compositor::new(&ctx, capacity_rays, config.transmittance_threshold, true);
        let color = match &config.color_correction {
            Some(c) => {
                let cc = GpuColorCorrection::new(&ctx, bounds.n_views.max(1), capacity_rays).map_err(gerr)?;
                let adam_config = nerf_optim::AdamConfig { sparse_groups: Vec::new(), ..config.adam.clone() };
                let adam = GpuAdam::new(&ctx, &adam_config, &[GpuParamGroup::new(COLOR_GROUP, 0, cc.len(), 0.0)]).map_err(gerr)?;
                Some(GpuColor {
                    adam,
                    adam_config,
                    lr: c.lr,
                    out: ctx.zeros("corrected rgb", 12 * capacity_rays),
                    d_opacity: ctx.zeros("d opacity", 4 * capacity_rays),
                    cc,
                })
            }
            None => None,
        };
        let pose = match &config.camera_optimizer {
            Some(c) => {
                for (f, cpu) in fields.iter_mut().zip(cpu_fields) {
                    f.enable_input_gradients(&ctx).map_err(field_err(cpu.kind()))?;
                }
                let pc = GpuPoseCorrection::new(&ctx, bounds.n_views.max(1), capacity_rays, c.trans_penalty, c.rot_penalty).map_err(gerr)?;
                let adam_config = nerf_optim::AdamConfig { sparse_groups: Vec::new(), ..config.adam.clone() };
                let adam = GpuAdam::new(&ctx, &adam_config, &[GpuParamGroup::new(POSE_VIEWS.group, 0, pc.len(), 0.0)]).map_err(gerr)?;
                let most = (0..n_stages).map(stage_samples).max().unwrap_or(1).max(1);
                Some(GpuPose {
                    d_positions: ctx.zeros_checked("d positions", 12 * most).map_err(gerr)?,
                    d_dirs: ctx.zeros_checked("d sample dirs", 12 * most).map_err(gerr)?,
                    pc,
                    adam,
                    adam_config,
                    config: c.clone(),
                })
            }
            None => None,
        };
        if let Some(lambda) = config.distortion_loss {
            let range = bounds.far - bounds.near;
            compositor.set_distortion(&ctx, if range > 0.0 { 1.0 / range } else { 1.0 }, lambda);
        }
        if let Some(lambda) = config.depth_loss {
            compositor.set_depth_loss(&ctx, lambda);
        }
        Ok(Self {
            first_rays,
            raygen: GpuRayGen::new(&ctx, config.train_background, config.pixel_convention, config.pixel_jitter),
            compositor,
            glue,
            rays: GpuRays::new(&ctx, capacity_rays),
            spr: ctx.upload("samples per ray", &[0.0f32]),
            seen: ctx.upload("samples seen", &[0u32, 0u32]),
            group_names: group_names.to_vec(),
            images: None,
            fields,
            adams,
            ema_backup,
            sampler,
            stages,
            compaction,
            capacity_rays,
            capacity_samples,
            adaptive: config.target_samples_per_step.is_some(),
            last_n_samples: Cell::new((0, 0)),
            render_chunk: Cell::new(capacity_rays),
            render_crop: None,
            in_flight: Default::default(),
            frame: Default::default(),
            profile: Default::default(),
            profile_done: None,
            color,
            pose,
            ctx,
        })
    }

    pub(crate) fn describe(&self) -> String {
        self.ctx.describe()
    }

    /// Records and submits one training step; reads the loss back when `step + 1` is a logging
    /// step or the last one.
    #[allow(clippy::manual_is_multiple_of)] // keeps the MSRV (1.85)
    pub(crate) fn step(&mut self, data: &Dataset, cfg: &TrainConfig, step: u64, lr: f32) -> Result<StepStats, TrainError> {
        // The training images go to the device once (again only if another dataset is passed).
        let key = (data as *const Dataset as usize, data.n_views(), data.width, data.height);
        if self.images.as_ref().map(|(k, _)| *k) != Some(key) {
            let imgs = GpuImages::new(&self.ctx, data).map_err(gerr)?;
            self.images = Some((key, imgs));
        }
        let ctx = self.ctx.clone();
        let ctx = &*ctx;
        let seed = |stream: u64| {
            let x = cfg.seed.wrapping_mul(SEED_MIX) ^ (step.wrapping_add(1)).wrapping_mul(0xD1B5_4A32_D192_ED03) ^ stream;
            (x ^ (x >> 32)) as u32
        };
        let profiled = cfg.gpu_profile.is_some_and(|w| w.contains(step));
        if profiled {
            ctx.profile_start().map_err(gerr)?;
        }
        let mut enc = ctx.encoder("train step");
        let (_, images) = self.images.as_ref().expect("uploaded above");
        let s0 = &self.stages[0];
        // Occupancy-grid refresh from the field's density when due.
        if let Sampler::Occupancy(o) = &self.sampler {
            if o.grid.due(step) {
                ctx.profile_stage("occupancy update");
                ctx.profile_part("grid");
                o.grid.record_choose(ctx, &mut enc, step, seed(1), &o.points, &o.cells, &o.counters);
                // σ at the chosen points, a field-capacity chunk at a time.
                o.density.record(ctx, &mut enc, self.fields[0].as_ref(), &o.counters, &o.points, &o.sigma);
                ctx.profile_part("grid");
                o.grid.record_apply(ctx, &mut enc, &o.cells, &o.sigma, o.step_size);
            }
        }
        self.raygen.set_seed(ctx, seed(2));
        ctx.profile_stage("rays");
        self.raygen.record(ctx, &mut enc, &s0.counters, images, &self.rays);
        if let Some(p) = &self.pose {
            // Each ray moved by its view's pose correction before anything samples it.
            ctx.profile_part("pose correction");
            let r = &self.rays;
            p.pc.record_correct(ctx, &mut enc, &PoseRays { counters: &s0.counters, views: &r.views, origins: &r.origins, dirs: &r.dirs });
        }
        let perturb = cfg.perturb;
        match (&self.sampler, &self.compaction) {
            (Sampler::Occupancy(o), Some(c)) => self.record_compacted(ctx, &mut enc, o, c, perturb.then(|| seed(3))),
            _ => self.record_first_stage(ctx, &mut enc, perturb.then(|| seed(3))),
        }
        self.record_stage_forward(ctx, &mut enc, 0, true);
        if let Sampler::Hierarchical(_, h) = &self.sampler {
            let (a, b) = self.stages.split_at(1);
            self.record_fine(ctx, &mut enc, h, &a[0], &b[0], perturb.then(|| seed(4)));
            self.record_stage_forward(ctx, &mut enc, 1, true);
        }
        // Loss on every stage, backward through compositing into each field, Adam (whose step
        // zeroes the gradients, the colour corrections' too).
        for (i, st) in self.stages.iter().enumerate() {
            ctx.profile_stage("loss");
            let color_in = ColorInputs {
                counters: &st.counters,
                views: &self.rays.views,
                rgb: &st.ray_rgb,
                opacity: &st.opacity,
                background: &self.rays.background,
            };
            // With colour correction the loss sees each view's corrected pixels; its backward
            // turns the loss gradient into compositing's (in place) and an opacity gradient.
            if let Some(c) = &self.color {
                c.cc.record_forward(ctx, &mut enc, &color_in, &c.out);
            }
            let pred = self.color.as_ref().map_or(&st.ray_rgb, |c| &c.out);
            self.glue.record_loss(ctx, &mut enc, &st.counters, pred, &self.rays.target, &st.d_ray_rgb, &st.sq_err);
            if let Some(c) = &self.color {
                c.cc.record_backward(ctx, &mut enc, &color_in, &st.d_ray_rgb, &c.d_opacity);
            }
            let d_opacity = self.color.as_ref().map(|c| &c.d_opacity);
            // Depth supervision: the expected depth against the rays' measured ones.
            let d_depth = cfg.depth_loss.map(|_| {
                self.compositor.record_depth_loss(ctx, &mut enc, &st.counters, &st.depth, &self.rays.depth_target, &st.d_depth, &st.depth_loss);
                &st.d_depth
            });
            let pb = self.packed(st);
            ctx.profile_stage("composite backward");
            self.compositor.record_backward(ctx, &mut enc, &pb, &st.weights, &st.d_ray_rgb, d_opacity, d_depth, &st.d_sigma, &st.d_rgb);
            if cfg.distortion_loss.is_some() && i + 1 == self.stages.len() {
                self.compositor.record_distortion(ctx, &mut enc, &pb, &st.weights, &st.d_sigma, &st.ray_loss);
            }
            ctx.profile_stage(if i == 0 { "field backward" } else { "fine field backward" });
            self.fields[i].record_backward(ctx, &mut enc, st.samples(), &st.d_sigma, &st.d_rgb);
            if let Some(p) = &self.pose {
                // Camera pose refinement: the field's input gradients, gathered per ray.
                ctx.profile_stage("pose backward");
                self.fields[i].record_input_gradients(ctx, &mut enc, st.samples(), &p.d_positions, &p.d_dirs);
                let g = PoseSampleGrads { offsets: &st.packed.offsets, t: &st.packed.t, d_positions: &p.d_positions, d_dirs: &p.d_dirs };
                p.pc.record_rays_backward(ctx, &mut enc, &st.counters, &g);
            }
        }
        if let Some(p) = &self.pose {
            ctx.profile_stage("pose backward");
            p.pc.record_reduce(ctx, &mut enc, &self.stages[0].counters, &self.rays.views);
        }
        ctx.profile_stage("adam");
        if let Some(p) = &self.pose {
            p.adam.record_step(ctx, &mut enc, &p.pc.params, &p.pc.grads, p.config.lr_at(step));
        }
        if let Some(c) = &self.color {
            c.adam.record_step(ctx, &mut enc, &c.cc.params, &c.cc.grads, c.lr);
        }
        for (f, adams) in self.fields.iter().zip(&self.adams) {
            for (g, adam) in f.groups().iter().zip(adams) {
                adam.record_step(ctx, &mut enc, &g.params, &g.grads, lr);
            }
        }
        // Samples seen, batch size of the next step (from this step's first stage).
        let last = self.stages.len() - 1;
        ctx.profile_stage("batch bookkeeping");
        let done = step + 1;
        let read = done % cfg.log_every.max(1) == 0 || done == cfg.iters;
        if read {
            for st in &self.stages {
                enc.copy_buffer_to_buffer(&st.counters, 0, &st.logged, 0, Some(8));
            }
            if let Some(c) = &self.compaction {
                enc.copy_buffer_to_buffer(&c.counters, 0, &self.stages[0].logged, 8, Some(8));
            }
        }
        for st in &self.stages {
            self.glue.record_count(ctx, &mut enc, &st.counters, &self.seen);
        }
        if self.adaptive {
            self.glue.record_next_batch(ctx, &mut enc, &self.stages[0].counters, &self.spr);
        }
        let timings = if profiled { ctx.profile_finish(&mut enc) } else { None };
        let idx = ctx.queue.submit([enc.finish()]);
        if let Some(t) = timings {
            let untimed = t.dropped();
            let passes = t.read(ctx).map_err(gerr)?;
            self.profile.add_step(step, &passes, untimed);
            if cfg.gpu_profile.is_some_and(|w| w.is_last(step)) {
                self.profile_done = Some(self.profile.summary(&ctx.describe()));
            }
        }
        // Keep at most MAX_IN_FLIGHT steps queued: the host stays a few steps ahead of the device
        // (recording overlaps execution) without queueing unbounded work, so time budgets and
        // Ctrl-C act within milliseconds.
        self.in_flight.push_back(idx);
        if self.in_flight.len() > MAX_IN_FLIGHT {
            let oldest = self.in_flight.pop_front().expect("non-empty");
            ctx.device
                .poll(wgpu::PollType::Wait { submission_index: Some(oldest), timeout: None })
                .map_err(|e| TrainError::Gpu(e.to_string()))?;
        }
        let (mut loss, mut mse) = (f32::NAN, f32::NAN);
        let (mut n_samples, mut n_marched) = self.last_n_samples.get();
        let (mut n_rays_read, mut alive_rays, mut mse_alive) = (0, 0, f32::NAN);
        if read {
            let (mut l, mut total) = (0.0f64, 0usize);
            for (i, st) in self.stages.iter().enumerate() {
                let c = ctx.read_u32(&st.logged, 4).map_err(gerr)?;
                if i == 0 {
                    n_marched = if self.compaction.is_some() { c[3] as usize } else { c[1] as usize };
                }
                let n_rays = (c[0] as usize).min(self.capacity_rays);
                let sq = ctx.read_f32(&st.sq_err, n_rays).map_err(gerr)?;
                let m = sq.iter().map(|&x| x as f64).sum::<f64>() / (3 * n_rays.max(1)) as f64;
                l += m;
                if cfg.distortion_loss.is_some() && i == last {
                    l += ctx.read_f32(&st.ray_loss, n_rays).map_err(gerr)?.iter().map(|&x| x as f64).sum::<f64>();
                }
                if cfg.depth_loss.is_some() {
                    l += ctx.read_f32(&st.depth_loss, n_rays).map_err(gerr)?.iter().map(|&x| x as f64).sum::<f64>();
                }
                total += c[1] as usize;
                if i == last {
                    mse = m as f32;
                    n_rays_read = n_rays;
                    let opacity = ctx.read_f32(&st.opacity, n_rays).map_err(gerr)?;
                    (alive_rays, mse_alive) = crate::trainer::alive_mse(&opacity, |r| sq[r] as f64);
                }
            }
            if let Some(p) = &self.pose {
                l += p.pc.read_regulariser(ctx).map_err(gerr)? as f64;
            }
            loss = l as f32;
            if !loss.is_finite() {
                return Err(TrainError::Diverged { step: done, loss });
            }
            n_samples = total;
            self.last_n_samples.set((total, n_marched));
        }
        Ok(StepStats { step, loss, mse, n_samples, n_marched, n_rays: n_rays_read, alive_rays, mse_alive, lr })
    }

    /// The profile of `TrainConfig::gpu_profile` once its window is complete (once), or with
    /// `partial` whatever steps of it ran (a run that stopped inside the window).
    pub(crate) fn take_profile(&mut self, partial: bool) -> Option<GpuProfile> {
        if let Some(p) = self.profile_done.take() {
            self.profile = Default::default();
            return Some(p);
        }
        if partial && self.profile.steps() > 0 {
            let p = self.profile.summary(&self.ctx.describe());
            self.profile = Default::default();
            return Some(p);
        }
        None
    }

    fn packed<'a>(&'a self, st: &'a Stage) -> PackedBuffers<'a> {
        PackedBuffers {
            counters: &st.counters,
            offsets: &st.packed.offsets,
            sigma: &st.sigma,
            rgb: &st.rgb,
            dt: &st.packed.dt,
            t: &st.packed.t,
            background: &self.rays.background,
        }
    }

    /// Samples of the first (or only) stage from the current rays.
    fn record_first_stage(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, jitter_seed: Option<u32>) {
        let s0 = &self.stages[0];
        ctx.profile_stage("sampling");
        match &self.sampler {
            Sampler::Occupancy(o) => {
                o.marcher.set_seed(ctx, jitter_seed.unwrap_or(0), jitter_seed.is_some());
                o.marcher.record(ctx, enc, &s0.counters, o.grid.bitfield(), &self.rays.origins, &self.rays.dirs, &s0.packed)
            }
            Sampler::Stratified(s) | Sampler::Hierarchical(s, _) => s.record(
                ctx,
                enc,
                &s0.counters,
                &self.rays.origins,
                &self.rays.dirs,
                jitter_seed,
                &s0.packed_out(),
                self.capacity_rays,
            ),
        }
    }

    /// Training on compacted samples: marches every ray into the compaction's buffers, evaluates
    /// the density there (inference), and keeps in stage 0 each ray's samples up to where its
    /// transmittance falls below the threshold.
    fn record_compacted(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, o: &Occupancy, c: &Compaction, jitter_seed: Option<u32>) {
        let s0 = &self.stages[0];
        ctx.profile_stage("sampling");
        enc.copy_buffer_to_buffer(&s0.counters, 0, &c.counters, 0, Some(4));
        c.marcher.set_seed(ctx, jitter_seed.unwrap_or(0), jitter_seed.is_some());
        c.marcher.record(ctx, enc, &c.counters, o.grid.bitfield(), &self.rays.origins, &self.rays.dirs, &c.packed);
        ctx.profile_stage("density inference");
        c.density.record_for_training(ctx, enc, self.fields[0].as_ref(), &c.counters, &c.packed.positions, &c.sigma);
        ctx.profile_stage("compaction");
        c.compactor.record(ctx, enc, &c.counters, &c.packed, &c.sigma, &s0.counters, &s0.packed, &c.rows);
    }

    /// The fine stage's samples from the coarse stage's weights (written to `fine.counters`).
    fn record_fine(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        h: &GpuHierarchical,
        coarse: &Stage,
        fine: &Stage,
        jitter_seed: Option<u32>,
    ) {
        ctx.profile_stage("fine sampling");
        h.record(
            ctx,
            enc,
            &coarse.counters,
            &coarse.packed.offsets,
            &coarse.packed.t,
            &coarse.weights,
            &self.rays.origins,
            &self.rays.dirs,
            jitter_seed,
            &fine.counters,
            &fine.packed_out(),
            self.capacity_rays,
        );
    }

    /// Field forward (training or inference) and compositing of stage `i`.
    fn record_stage_forward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, i: usize, train: bool) {
        let st = &self.stages[i];
        let s = st.samples();
        ctx.profile_stage(if i == 0 { "field forward" } else { "fine field forward" });
        if let (true, 0, Some(c)) = (train, i, &self.compaction) {
            // Stage 0 holds the compaction of the density pass recorded just before.
            self.fields[0].record_forward_rows(ctx, enc, s, &c.rows, &st.sigma, &st.rgb);
        } else if train {
            self.fields[i].record_forward(ctx, enc, s, &st.sigma, &st.rgb);
        } else {
            self.fields[i].record_query(ctx, enc, s, &st.sigma, &st.rgb);
        }
        let out = CompositeTargets { rgb: &st.ray_rgb, opacity: &st.opacity, depth: &st.depth, weights: &st.weights };
        ctx.profile_stage("composite forward");
        self.compositor.record_forward(ctx, enc, &self.packed(st), &out);
    }

    /// Renders host rays on the device (deterministic sampling, inference). The rays are uploaded
    /// once; every chunk of at most the ray capacity is recorded into one submission that copies
    /// its image part into frame-sized outputs, and one read-back returns the image and each
    /// chunk's sample count. A chunk whose samples overflowed the sample capacity (the marcher
    /// clips there) is split and rendered again; the chunk size that fits is kept for next time.
    ///
    /// With a moving average (`ema_decay`, at least one update) the fields render with it: the
    /// raw parameters are copied aside and the average into the parameter buffers before, and
    /// back after (recorded copies, also when rendering fails).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn render_rays(
        &self,
        cfg: &TrainConfig,
        origins: &[f32],
        dirs: &[f32],
        background: &[f32],
        rgb: &mut [f32],
        opacity: &mut [f32],
        depth: &mut [f32],
    ) -> Result<(), TrainError> {
        let swap = !self.ema_backup.is_empty() && self.adams.iter().flatten().any(|a| a.ema_step_count() > 0);
        if swap {
            self.record_ema_swap(true);
        }
        // A frame larger than the adapter's buffers hold (an 8192² render: 3 GiB of ray state)
        // renders in parts; rays are independent, so the image is the same.
        let n = origins.len() / 3;
        let part = self.max_frame_rays();
        let mut r = Ok(());
        for r0 in (0..n).step_by(part) {
            let r1 = (r0 + part).min(n);
            r = self.render_rays_with_current(
                cfg,
                &origins[3 * r0..3 * r1],
                &dirs[3 * r0..3 * r1],
                &background[3 * r0..3 * r1],
                &mut rgb[3 * r0..3 * r1],
                &mut opacity[r0..r1],
                &mut depth[r0..r1],
            );
            if r.is_err() {
                break;
            }
        }
        if swap {
            self.record_ema_swap(false);
        }
        r
    }

    /// Crops the renders that follow to `crop` (`None`: none); training never crops.
    pub(crate) fn set_render_crop(&mut self, crop: Option<nerf_sampling::CropBox>) {
        self.render_crop = crop;
    }

    /// Queues `crop` on the sampler for the submissions that follow (`None` puts training's
    /// uncropped sampling back).
    fn queue_crop(&self, crop: Option<&nerf_sampling::CropBox>) {
        match &self.sampler {
            Sampler::Occupancy(o) => o.marcher.queue_crop(&self.ctx, crop),
            Sampler::Stratified(s) => s.set_crop(crop.copied()),
            Sampler::Hierarchical(s, h) => {
                s.set_crop(crop.copied());
                h.set_crop(crop.copied());
            }
        }
    }

    /// The most rays [`render_rays`](Self::render_rays) gives one frame's buffers: as many as the
    /// adapter's largest buffer and storage binding hold of the rounds' per-ray state, and at most
    /// [`MAX_FRAME_RAYS`] (the frame's buffers are kept between calls).
    pub(crate) fn max_frame_rays(&self) -> usize {
        frame_part_rays(self.ctx.max_storage_bytes())
    }

    /// The rendering field's (the last) density, and colour when `dirs` and `rgb` are given, at
    /// points: in batches of its stage's sample capacity, with the moving average as rendering.
    pub(crate) fn query_points(
        &self,
        positions: &[f32],
        dirs: Option<&[f32]>,
        sigma: &mut [f32],
        mut rgb: Option<&mut [f32]>,
    ) -> Result<(), TrainError> {
        let swap = !self.ema_backup.is_empty() && self.adams.iter().flatten().any(|a| a.ema_step_count() > 0);
        if swap {
            self.record_ema_swap(true);
        }
        let ctx = &*self.ctx;
        let (field, st) = (self.fields.last().expect("a field"), self.stages.last().expect("a stage"));
        let batch = st.packed.capacity_samples.min(field.capacity()).max(1);
        let n = sigma.len();
        let mut r = Ok(());
        for p0 in (0..n).step_by(batch) {
            let p1 = (p0 + batch).min(n);
            let m = p1 - p0;
            ctx.write(&st.counters, 4, &[m as u32]);
            ctx.write(&st.packed.positions, 0, &positions[3 * p0..3 * p1]);
            let mut enc = ctx.encoder("query points");
            let out = match (dirs, rgb.as_deref_mut()) {
                (Some(d), Some(c)) => {
                    ctx.write(&st.packed.dirs, 0, &d[3 * p0..3 * p1]);
                    field.record_query(ctx, &mut enc, st.samples(), &st.sigma, &st.rgb);
                    Some(&mut c[3 * p0..3 * p1])
                }
                _ => {
                    field.record_density(ctx, &mut enc, st.samples(), &st.sigma);
                    None
                }
            };
            ctx.queue.submit([enc.finish()]);
            let parts: Vec<(&wgpu::Buffer, usize)> = if out.is_some() { vec![(&st.sigma, m), (&st.rgb, 3 * m)] } else { vec![(&st.sigma, m)] };
            match ctx.read_words(&parts) {
                Ok(got) => {
                    sigma[p0..p1].iter_mut().zip(&got[0]).for_each(|(d, &w)| *d = f32::from_bits(w));
                    if let Some(c) = out {
                        c.iter_mut().zip(&got[1]).for_each(|(d, &w)| *d = f32::from_bits(w));
                    }
                }
                Err(e) => {
                    r = Err(gerr(e));
                    break;
                }
            }
        }
        if swap {
            self.record_ema_swap(false);
        }
        self.reset_batch();
        r
    }

    /// Submits the copies that put the moving average into the fields' parameter buffers (raw
    /// parameters to the backup first; `to_ema`) or the raw parameters back (`!to_ema`).
    fn record_ema_swap(&self, to_ema: bool) {
        let ctx = &*self.ctx;
        let mut enc = ctx.encoder(if to_ema { "ema in" } else { "ema out" });
        for ((f, adams), backups) in self.fields.iter().zip(&self.adams).zip(&self.ema_backup) {
            for ((g, adam), backup) in f.groups().iter().zip(adams).zip(backups) {
                let (Some(ema), bytes) = (adam.ema_buffer(), 4 * g.len as u64) else { continue };
                if bytes == 0 {
                    continue;
                }
                if to_ema {
                    enc.copy_buffer_to_buffer(&g.params, 0, backup, 0, bytes);
                    enc.copy_buffer_to_buffer(ema, 0, &g.params, 0, bytes);
                } else {
                    enc.copy_buffer_to_buffer(backup, 0, &g.params, 0, bytes);
                }
            }
        }
        ctx.queue.submit([enc.finish()]);
    }

    #[allow(clippy::too_many_arguments)]
    fn render_rays_with_current(
        &self,
        cfg: &TrainConfig,
        origins: &[f32],
        dirs: &[f32],
        background: &[f32],
        rgb: &mut [f32],
        opacity: &mut [f32],
        depth: &mut [f32],
    ) -> Result<(), TrainError> {
        let ctx = &*self.ctx;
        let n = origins.len() / 3;
        if n == 0 {
            return Ok(());
        }
        // Frame-sized buffers, kept between calls (reallocated only for a larger frame).
        let mut frame = self.frame.borrow_mut();
        if frame.as_ref().is_none_or(|f| f.n < n) {
            *frame = Some(Frame::new(ctx, n, &self.sampler, self.capacity_samples));
        }
        let Frame { origins: f_o, dirs: f_d, background: f_bg, rgb: out_rgb, opacity: out_op, depth: out_depth, rounds, .. } =
            frame.as_ref().expect("allocated above");
        ctx.write(f_o, 0, origins);
        ctx.write(f_d, 0, dirs);
        ctx.write(f_bg, 0, background);
        // The crop box for this frame only: training's sampling is queued back after it.
        if self.render_crop.is_some() {
            self.queue_crop(self.render_crop.as_ref());
        }
        let r = self.render_frame(cfg, n, rounds.as_ref(), (f_o, f_d, f_bg), (out_rgb, out_op, out_depth));
        if self.render_crop.is_some() {
            self.queue_crop(None);
        }
        r?;
        let got = ctx.read_words(&[(out_rgb, 3 * n), (out_op, n), (out_depth, n)]).map_err(gerr)?;
        for (dst, src) in [(&mut rgb[..3 * n], &got[0]), (&mut opacity[..n], &got[1]), (&mut depth[..n], &got[2])] {
            for (d, &w) in dst.iter_mut().zip(src) {
                *d = f32::from_bits(w);
            }
        }
        self.reset_batch();
        Ok(())
    }

    /// One frame's render into the frame's buffers: in rounds with the occupancy grid (at the
    /// render step), else in chunks.
    fn render_frame(
        &self,
        cfg: &TrainConfig,
        n: usize,
        rounds: Option<&nerf_gpu::sampling::RoundFrame>,
        (f_o, f_d, f_bg): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
        (out_rgb, out_op, out_depth): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), TrainError> {
        let ctx = &*self.ctx;
        if let (Sampler::Occupancy(o), Some(rf)) = (&self.sampler, rounds) {
            // At the render step (`render_step_size`), training's queued back after the frame.
            let stepping = match cfg.render_sampler().map_err(TrainError::Config)? {
                SamplerConfig::Occupancy { step_size, max_samples_per_ray, .. } => (step_size, max_samples_per_ray as u32),
                _ => unreachable!("the occupancy sampler's render sampler is one"),
            };
            o.marcher.queue_stepping(ctx, stepping.0, stepping.1);
            let r = self.render_rounds(o, rf, n, cfg.transmittance_threshold, (f_o, f_d, f_bg), (out_rgb, out_op, out_depth));
            o.marcher.restore_stepping(ctx);
            r
        } else {
            self.render_chunks(n, (f_o, f_d, f_bg), (out_rgb, out_op, out_depth))
        }
    }

    /// Occupancy-grid rendering in rounds (`GpuMarcher::record_round_*`): every ray of the frame
    /// starts alive; a round marches the next few steps of (up to a sample capacity of) alive rays,
    /// evaluates the field there, composites into the rays' states and drops the rays whose
    /// transmittance fell below the threshold or whose march ended. Same image as marching every
    /// sample first, without evaluating the samples behind opaque surfaces.
    fn render_rounds(
        &self,
        o: &Occupancy,
        rf: &nerf_gpu::sampling::RoundFrame,
        n: usize,
        t_threshold: f32,
        (f_o, f_d, f_bg): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
        (out_rgb, out_op, out_depth): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), TrainError> {
        let ctx = &*self.ctx;
        let st = &self.stages[0];
        o.marcher.set_seed(ctx, 0, false);
        rf.set(ctx, n, t_threshold, ROUND_STEPS, true);
        let mut enc = ctx.encoder("render rounds");
        o.marcher.record_round_start(ctx, &mut enc, rf, o.grid.bitfield());
        let mut round = 0;
        loop {
            for _ in 0..ROUNDS_PER_SUBMISSION {
                o.marcher.record_round_march(ctx, &mut enc, rf, round, &st.counters, o.grid.bitfield(), f_o, f_d, &st.packed);
                self.fields[0].record_query(ctx, &mut enc, st.samples(), &st.sigma, &st.rgb);
                o.marcher.record_round_composite(ctx, &mut enc, rf, round, &st.counters, &st.sigma, &st.rgb, &st.packed);
                round += 1;
            }
            ctx.queue.submit([std::mem::replace(&mut enc, ctx.encoder("render rounds")).finish()]);
            let (alive, _) = rf.status(ctx).map_err(gerr)?;
            if alive == 0 {
                break;
            }
        }
        o.marcher.record_round_output(ctx, &mut enc, rf, f_bg, out_rgb, out_op, out_depth);
        ctx.queue.submit([enc.finish()]);
        Ok(())
    }

    /// Rendering in chunks of at most the ray capacity (stratified and hierarchical sampling).
    fn render_chunks(
        &self,
        n: usize,
        (f_o, f_d, f_bg): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
        (out_rgb, out_op, out_depth): (&wgpu::Buffer, &wgpu::Buffer, &wgpu::Buffer),
    ) -> Result<(), TrainError> {
        let ctx = &*self.ctx;
        let chunk = self.render_chunk.get().clamp(1, self.capacity_rays);
        let mut todo: Vec<(usize, usize)> = (0..n).step_by(chunk).map(|r0| (r0, (r0 + chunk).min(n))).collect();
        let last = self.stages.last().expect("a stage");
        while !todo.is_empty() {
            let sizes: Vec<u32> = todo.iter().flat_map(|&(a, b)| [(b - a) as u32, 0]).collect();
            let sizes = ctx.upload("chunk sizes", &sizes);
            let stats = ctx.zeros("chunk samples", 4 * todo.len());
            let mut enc = ctx.encoder("render");
            for (k, &(r0, r1)) in todo.iter().enumerate() {
                let (r0, m) = (r0 as u64, (r1 - r0) as u64);
                enc.copy_buffer_to_buffer(f_o, 12 * r0, &self.rays.origins, 0, 12 * m);
                enc.copy_buffer_to_buffer(f_d, 12 * r0, &self.rays.dirs, 0, 12 * m);
                enc.copy_buffer_to_buffer(f_bg, 12 * r0, &self.rays.background, 0, 12 * m);
                for st in &self.stages {
                    enc.copy_buffer_to_buffer(&sizes, 8 * k as u64, &st.counters, 0, 8);
                }
                self.record_first_stage(ctx, &mut enc, None);
                self.record_stage_forward(ctx, &mut enc, 0, false);
                if let Sampler::Hierarchical(_, h) = &self.sampler {
                    let (a, b) = self.stages.split_at(1);
                    self.record_fine(ctx, &mut enc, h, &a[0], &b[0], None);
                    self.record_stage_forward(ctx, &mut enc, 1, false);
                }
                enc.copy_buffer_to_buffer(&last.ray_rgb, 0, out_rgb, 12 * r0, 12 * m);
                enc.copy_buffer_to_buffer(&last.opacity, 0, out_op, 4 * r0, 4 * m);
                enc.copy_buffer_to_buffer(&last.depth, 0, out_depth, 4 * r0, 4 * m);
                enc.copy_buffer_to_buffer(&self.stages[0].counters, 4, &stats, 4 * k as u64, 4);
            }
            ctx.queue.submit([enc.finish()]);
            let counts = ctx.read_u32(&stats, todo.len()).map_err(gerr)?;
            let mut again = Vec::new();
            if matches!(self.sampler, Sampler::Occupancy(_)) {
                for (&(r0, r1), &c) in todo.iter().zip(&counts) {
                    if c as usize >= self.capacity_samples && r1 - r0 > 1 {
                        let mid = r0 + (r1 - r0) / 2;
                        again.extend([(r0, mid), (mid, r1)]);
                        self.render_chunk.set(self.render_chunk.get().min((mid - r0).max(1)));
                    }
                }
            }
            todo = again;
        }
        Ok(())
    }

    /// Puts the training batch size back into the counters (rendering and resuming reuse them):
    /// the first step's size, then — when batches are sized by samples — the size the running
    /// mean gives.
    fn reset_batch(&self) {
        let ctx = &*self.ctx;
        for st in &self.stages {
            ctx.write(&st.counters, 0, &[self.first_rays as u32, 0u32]);
        }
        if self.adaptive {
            let mut enc = ctx.encoder("batch from mean");
            self.glue.record_batch_from_mean(ctx, &mut enc, &self.stages[0].counters, &self.spr);
            ctx.queue.submit([enc.finish()]);
        }
    }

    pub(crate) fn finish(&self) -> Result<(), TrainError> {
        self.ctx.wait().map_err(gerr)
    }

    pub(crate) fn samples_seen(&self) -> Result<u64, TrainError> {
        let v = self.ctx.read_u32(&self.seen, 2).map_err(gerr)?;
        Ok(v[0] as u64 | ((v[1] as u64) << 32))
    }

    pub(crate) fn export_fields(&self) -> Result<crate::FieldParams, TrainError> {
        self.fields.iter().map(|f| f.export_params(&self.ctx).map_err(gerr)).collect()
    }

    pub(crate) fn adam_state(&self) -> Result<AdamState, TrainError> {
        let (mut groups, mut steps) = (Vec::new(), Vec::new());
        let mut step = 0;
        for adams in &self.adams {
            for a in adams {
                let s = a.state(&self.ctx).map_err(gerr)?;
                step = s.step;
                groups.extend(s.groups);
                steps.extend(s.steps);
            }
        }
        Ok(AdamState { step, groups, steps })
    }

    /// The moving average of every group (`None` without `ema_decay`; no groups before the first
    /// update).
    pub(crate) fn ema_state(&self) -> Result<Option<EmaState>, TrainError> {
        if self.ema_backup.is_empty() {
            return Ok(None);
        }
        let mut out = EmaState { step: 0, groups: Vec::new() };
        for a in self.adams.iter().flatten() {
            if let Some(s) = a.ema_state(&self.ctx).map_err(gerr)? {
                out.step = s.step;
                out.groups.extend(s.groups);
            }
        }
        if out.step == 0 {
            out.groups.clear();
        }
        Ok(Some(out))
    }

    /// The colour corrections and their Adam state (`None` without `color_correction`).
    pub(crate) fn color_state(&self) -> Result<Option<ColorState>, TrainError> {
        let Some(c) = &self.color else { return Ok(None) };
        Ok(Some(ColorState { params: c.cc.read_params(&self.ctx).map_err(gerr)?, adam: c.adam.state(&self.ctx).map_err(gerr)? }))
    }

    /// The colour corrections only.
    pub(crate) fn color_params(&self) -> Result<Option<Vec<f32>>, TrainError> {
        self.color.as_ref().map(|c| c.cc.read_params(&self.ctx).map_err(gerr)).transpose()
    }

    /// Views the corrections are for (`None` without `color_correction`).
    pub(crate) fn color_views(&self) -> Option<usize> {
        self.color.as_ref().map(|c| c.cc.n_views())
    }

    /// Loads checkpointed corrections, for however many views they are (the buffers are made
    /// anew for another count).
    pub(crate) fn restore_color(&mut self, s: ColorState) -> Result<(), TrainError> {
        let ctx = self.ctx.clone();
        let Some(c) = self.color.as_mut() else { return Ok(()) };
        if s.n_views(&COLOR_VIEWS) != c.cc.n_views() {
            c.cc = GpuColorCorrection::new(&ctx, s.n_views(&COLOR_VIEWS), self.capacity_rays).map_err(gerr)?;
            c.adam = GpuAdam::new(&ctx, &c.adam_config, &[GpuParamGroup::new(COLOR_GROUP, 0, c.cc.len(), 0.0)]).map_err(gerr)?;
        }
        c.cc.set_params(&ctx, &s.params).map_err(gerr)?;
        c.adam.load_state(&ctx, &s.adam).map_err(gerr)
    }

    /// The pose corrections and their Adam state (`None` without `camera_optimizer`).
    pub(crate) fn pose_state(&self) -> Result<Option<PoseState>, TrainError> {
        let Some(p) = &self.pose else { return Ok(None) };
        Ok(Some(PoseState { params: p.pc.read_params(&self.ctx).map_err(gerr)?, adam: p.adam.state(&self.ctx).map_err(gerr)? }))
    }

    /// The pose corrections only.
    pub(crate) fn pose_params(&self) -> Result<Option<Vec<f32>>, TrainError> {
        self.pose.as_ref().map(|p| p.pc.read_params(&self.ctx).map_err(gerr)).transpose()
    }

    /// Views the pose corrections are for (`None` without `camera_optimizer`).
    pub(crate) fn pose_views(&self) -> Option<usize> {
        self.pose.as_ref().map(|p| p.pc.n_views())
    }

    /// Loads checkpointed pose corrections, for however many views they are (the buffers are
    /// made anew for another count).
    pub(crate) fn restore_pose(&mut self, s: PoseState) -> Result<(), TrainError> {
        let ctx = self.ctx.clone();
        let Some(p) = self.pose.as_mut() else { return Ok(()) };
        if s.n_views(&POSE_VIEWS) != p.pc.n_views() {
            let c = &p.config;
            p.pc = GpuPoseCorrection::new(&ctx, s.n_views(&POSE_VIEWS), self.capacity_rays, c.trans_penalty, c.rot_penalty).map_err(gerr)?;
            p.adam = GpuAdam::new(&ctx, &p.adam_config, &[GpuParamGroup::new(POSE_VIEWS.group, 0, p.pc.len(), 0.0)]).map_err(gerr)?;
        }
        p.pc.set_params(&ctx, &s.params).map_err(gerr)?;
        p.adam.load_state(&ctx, &s.adam).map_err(gerr)
    }

    pub(crate) fn sampler_state(&self) -> Result<Vec<(String, Vec<f32>)>, TrainError> {
        let spr = self.ctx.read_f32(&self.spr, 1).map_err(gerr)?;
        let mut v = vec![("samples_per_ray".to_string(), spr)];
        if let Sampler::Occupancy(o) = &self.sampler {
            v.push(("occupancy_density".to_string(), o.grid.download(&self.ctx).map_err(gerr)?));
            if let Some(w) = &o.seen {
                v.push((crate::trainer::SEEN_ENTRY.to_string(), crate::trainer::seen_to_entry(w)));
            }
        }
        Ok(v)
    }

    /// Marks the grid's cells no training camera sees (`OccupancyGrid::mark_seen`) on a CPU copy
    /// of the device's densities, and uploads densities and marks.
    pub(crate) fn mark_seen(&mut self, visible: &(dyn Fn([f32; 3], f32) -> bool + Sync)) -> Result<(), TrainError> {
        if let Sampler::Occupancy(o) = &mut self.sampler {
            let (lo, hi) = o.grid.aabb();
            let mut g = nerf_sampling::OccupancyGrid::try_new(o.grid.config().clone(), lo, hi).map_err(TrainError::Config)?;
            g.set_densities(&o.grid.download(&self.ctx).map_err(gerr)?, o.step_size).map_err(TrainError::Config)?;
            g.mark_seen(visible);
            o.grid.upload_from(&self.ctx, &g).map_err(gerr)?;
            o.seen = g.seen_words();
        }
        Ok(())
    }

    pub(crate) fn restore(
        &mut self,
        fields: &[Vec<(String, Vec<f32>)>],
        adam: &AdamState,
        sampler_state: &[(String, Vec<f32>)],
        seen: Option<&[u32]>,
        ema: Option<&EmaState>,
    ) -> Result<(), TrainError> {
        if fields.len() != self.fields.len() {
            return Err(TrainError::Config(format!(
                "checkpoint holds {} field instances, this config needs {}",
                fields.len(),
                self.fields.len()
            )));
        }
        for (f, groups) in self.fields.iter().zip(fields) {
            f.import_params(&self.ctx, groups)?;
        }
        for (adams, names) in self.adams.iter().zip(&self.group_names) {
            for (a, name) in adams.iter().zip(names) {
                let groups = adam.groups.iter().filter(|(n, _, _)| n == name).cloned().collect();
                let steps = adam.steps.iter().filter(|(n, _)| n == name).cloned().collect();
                a.load_state(&self.ctx, &AdamState { step: adam.step, groups, steps }).map_err(gerr)?;
                if let Some(e) = ema {
                    let groups = e.groups.iter().filter(|(n, _)| n == name).cloned().collect();
                    a.load_ema_state(&self.ctx, &EmaState { step: e.step, groups }).map_err(gerr)?;
                }
            }
        }
        if let Sampler::Occupancy(o) = &mut self.sampler {
            o.seen = seen.map(|w| w.to_vec());
        }
        for (name, v) in sampler_state {
            match (name.as_str(), &self.sampler) {
                ("samples_per_ray", _) if v.len() == 1 => {
                    self.ctx.write(&self.spr, 0, v);
                    self.reset_batch();
                }
                ("occupancy_density", Sampler::Occupancy(o)) => {
                    let (lo, hi) = o.grid.aabb();
                    let mut g = nerf_sampling::OccupancyGrid::try_new(o.grid.config().clone(), lo, hi).map_err(TrainError::Config)?;
                    if let Some(w) = seen {
                        g.set_seen_words(w).map_err(|e| TrainError::Config(format!("checkpoint: {e}")))?;
                    }
                    g.set_densities(v, o.step_size).map_err(TrainError::Config)?;
                    o.grid.upload_from(&self.ctx, &g).map_err(gerr)?
                }
                (crate::trainer::SEEN_ENTRY, Sampler::Occupancy(_)) => {}
                _ => return Err(TrainError::Config(format!("unexpected sampler state `{name}` in checkpoint"))),
            }
        }
        Ok(())
    }
}

/// The coarse sampler of an NDC scene takes each ray's segment inside the box.
fn clip_coarse(s: GpuStratified, b: &SceneBounds) -> GpuStratified {
    if b.clip_to_box { s.clip_to_box(b.aabb_min, b.aabb_max) } else { s }
}

/// The fine sampler closes each ray's last interval where the coarse one's segment ends.
fn clip_fine(s: GpuHierarchical, b: &SceneBounds) -> GpuHierarchical {
    if b.clip_to_box { s.clip_to_box(b.near, b.aabb_min, b.aabb_max) } else { s }
}

/// Upper bound on the samples one ray can get from the first stage.
fn max_samples_per_ray(s: &SamplerConfig) -> usize {
    match *s {
        SamplerConfig::Stratified { n_samples } => n_samples,
        SamplerConfig::Hierarchical { n_coarse, .. } => n_coarse,
        SamplerConfig::Occupancy { max_samples_per_ray, .. } => max_samples_per_ray,
    }
}

/// `config` with fewer samples per step, so that a buffer sized per sample that needs `bytes`
/// fits the adapter's `limit` (such buffers scale linearly with the step's samples):
/// `target_samples_per_step` (rounded down to a multiple of 1024) or `batch_rays` (to a multiple
/// of 64) scaled by `limit / bytes`. `None` when nothing smaller can be trained.
pub(crate) fn fit_to_binding_limit(config: &TrainConfig, bytes: u64, limit: u64) -> Option<TrainConfig> {
    let scale = |n: usize, multiple: usize| -> usize {
        let fitted = (n as u128 * limit as u128 / bytes.max(1) as u128) as usize;
        let fitted = if fitted >= multiple { fitted / multiple * multiple } else { fitted };
        // A buffer that was just over the limit must still shrink.
        fitted.min(n.saturating_sub(1))
    };
    let mut fitted = config.clone();
    match config.target_samples_per_step {
        Some(target) => {
            let t = scale(target, 1024);
            if t < 4 * MIN_BATCH_RAYS {
                return None;
            }
            fitted.target_samples_per_step = Some(t);
        }
        None => {
            let b = scale(config.batch_rays, 64);
            if b == 0 {
                return None;
            }
            fitted.batch_rays = b;
        }
    }
    Some(fitted)
}

/// What [`fit_to_binding_limit`] changed, for the user: `bytes` and `limit` of the first buffer
/// that did not fit, the config asked for and the one trained.
pub(crate) fn fit_note(asked: &TrainConfig, fitted: &TrainConfig, bytes: u64, limit: u64) -> String {
    let change = match (asked.target_samples_per_step, fitted.target_samples_per_step) {
        (Some(from), Some(to)) => format!("target_samples_per_step = {to} instead of {from}"),
        _ => format!("batch_rays = {} instead of {}", fitted.batch_rays, asked.batch_rays),
    };
    format!(
        "a per-sample buffer needs {:.1} MiB, more than the adapter's {:.1} MiB storage binding limit: training with {change}",
        bytes as f64 / 1048576.0,
        limit as f64 / 1048576.0
    )
}

/// `(rays, samples per stage)` the buffers are sized for.
fn capacities(config: &TrainConfig) -> (usize, usize) {
    match (config.target_samples_per_step, &config.sampler) {
        (Some(target), _) => {
            // Rays: enough for ≥ 4 samples per ray on average; samples: twice the target, so a
            // step whose rays find more than the running mean predicted still fits.
            let rays = (target / 4).clamp(MIN_BATCH_RAYS, MAX_BATCH_RAYS);
            (rays, 2 * target)
        }
        (None, s) => {
            let rays = config.batch_rays.max(1);
            (rays, rays * max_samples_per_ray(s))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIB: u64 = 1 << 20;

    #[test]
    fn a_render_part_fits_the_adapters_largest_buffer() {
        let per_ray = nerf_gpu::sampling::GpuMarcher::ROUND_BYTES_PER_RAY as u64;
        // lavapipe's 2 GiB − 1 and WebGPU's default 128 MiB binding; an 8192² frame (2^26 rays)
        // needs 3 GiB of round state, which wgpu refused with a panic before frames were parted.
        for limit in [(1u64 << 31) - 1, 128 * MIB, 1000, 1] {
            let part = frame_part_rays(limit) as u64;
            assert!(part >= 1 && part <= MAX_FRAME_RAYS as u64, "{limit}: {part}");
            assert!(part * per_ray <= limit || part == 1, "{part} rays of {per_ray} bytes exceed {limit} bytes");
            assert!(part == MAX_FRAME_RAYS as u64 || (part + 1) * per_ray > limit || limit < per_ray, "{limit}: {part} rays is not the most that fit");
        }
        assert_eq!(frame_part_rays(128 * MIB), (128 * MIB / per_ray) as usize);
        assert_eq!(frame_part_rays(1 << 40), MAX_FRAME_RAYS);
    }

    #[test]
    fn a_step_is_fitted_by_the_overshoot_of_its_largest_buffer() {
        // An adaptive batch: 2^18 samples that need 3 × the limit → a third, to a multiple of 1024.
        let asked = TrainConfig { target_samples_per_step: Some(1 << 18), ..TrainConfig::default() };
        let fitted = fit_to_binding_limit(&asked, 384 * MIB, 128 * MIB).unwrap();
        assert_eq!(fitted.target_samples_per_step, Some(87040)); // ⌊262144 / 3 / 1024⌋ · 1024
        assert_eq!(fitted.batch_rays, asked.batch_rays);
        let note = fit_note(&asked, &fitted, 384 * MIB, 128 * MIB);
        assert!(note.contains("384.0 MiB") && note.contains("128.0 MiB"), "{note}");
        assert!(note.contains("target_samples_per_step = 87040 instead of 262144"), "{note}");

        // A fixed batch: rays scaled, to a multiple of 64; the rest of the config is kept.
        let asked = TrainConfig { batch_rays: 4096, iters: 77, ..TrainConfig::default() };
        let fitted = fit_to_binding_limit(&asked, 576 * MIB, 128 * MIB).unwrap();
        assert_eq!((fitted.batch_rays, fitted.iters, fitted.target_samples_per_step), (896, 77, None));
        assert!(fit_note(&asked, &fitted, 576 * MIB, 128 * MIB).contains("batch_rays = 896 instead of 4096"));

        // Just over the limit still shrinks (by one multiple, or by one below the multiple).
        let fitted = fit_to_binding_limit(&asked, 128 * MIB + 4, 128 * MIB).unwrap();
        assert_eq!(fitted.batch_rays, 4032);
        let few = TrainConfig { batch_rays: 40, ..TrainConfig::default() };
        assert_eq!(fit_to_binding_limit(&few, 41, 40).unwrap().batch_rays, 39);

        // Nothing smaller to train: one ray over the limit, or fewer samples than 4 · the minimum rays.
        let one = TrainConfig { batch_rays: 1, ..TrainConfig::default() };
        assert!(fit_to_binding_limit(&one, 2 * MIB, MIB).is_none());
        let small = TrainConfig { target_samples_per_step: Some(4096), ..TrainConfig::default() };
        assert!(fit_to_binding_limit(&small, 64 * MIB, MIB).is_none());
    }
}
