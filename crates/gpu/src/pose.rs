//! Camera pose refinement on the device (`shaders/pose.wgsl`; CPU twins
//! `nerf_rays::pose::{pose_correct_rays, pose_correct_backward, pose_regulariser}` and
//! `nerf_sampling::RaySamples::backward_to_rays`). Each training view's correction (6 values: a
//! translation, then a rotation vector, nerfstudio's `SO3xR3`), its gradient and the per-ray
//! buffers live in this type; the trainer steps the corrections with a
//! [`GpuAdam`](crate::optim::GpuAdam).
//!
//! A step records [`record_correct`](GpuPoseCorrection::record_correct) right after ray
//! generation (rays moved in place), [`record_rays_backward`](GpuPoseCorrection::record_rays_backward)
//! after each stage's field backward (the field's input gradients gathered per ray), and
//! [`record_reduce`](GpuPoseCorrection::record_reduce) before the optimiser (the views' sums
//! through [`ViewSums`], shared with the colour correction, then one invocation per view).

use crate::kernel::{groups_1d, Kernel};
use crate::layout::PoseParams;
use crate::views::ViewSums;
use crate::{shaders, GpuContext, GpuError};

/// Values per view (a translation, then a rotation vector).
pub const PARAMS_PER_VIEW: usize = 6;
const WG: u32 = 64;

/// The rays of a batch as the correction reads and moves them.
#[derive(Clone, Copy)]
pub struct PoseRays<'a> {
    /// `counters` (`[0]` = number of rays).
    pub counters: &'a wgpu::Buffer,
    /// View index per ray (u32).
    pub views: &'a wgpu::Buffer,
    /// Ray origins (`3·n_rays`).
    pub origins: &'a wgpu::Buffer,
    /// Unit ray directions (`3·n_rays`).
    pub dirs: &'a wgpu::Buffer,
}

/// One stage's packed samples and the field's input gradients on them.
#[derive(Clone, Copy)]
pub struct PoseSampleGrads<'a> {
    /// CSR offsets, `n_rays + 1` u32.
    pub offsets: &'a wgpu::Buffer,
    /// Distance of each sample along its ray.
    pub t: &'a wgpu::Buffer,
    /// ∂L/∂x per sample (`3·n`).
    pub d_positions: &'a wgpu::Buffer,
    /// ∂L/∂(view direction) per sample (`3·n`).
    pub d_dirs: &'a wgpu::Buffer,
}

/// The pose corrections of `n_views` views for batches of up to `capacity_rays` rays.
pub struct GpuPoseCorrection {
    correct: Kernel,
    rays_backward: Kernel,
    sums: ViewSums,
    view_grads: Kernel,
    uniform: wgpu::Buffer,
    /// The corrections, `6·n_views` f32 (zero at creation).
    pub params: wgpu::Buffer,
    /// Their gradient, `6·n_views` f32 (zero at creation): [`record_reduce`](Self::record_reduce)
    /// adds to it; the optimiser's step zeroes it again (`GpuAdam::record_step`).
    pub grads: wgpu::Buffer,
    /// The regulariser's term of each view at the last reduction (`n_views` f32; their sum is
    /// the value added to the loss).
    pub reg_terms: wgpu::Buffer,
    base_dirs: wgpu::Buffer,
    ray_grads: wgpu::Buffer,
    /// The views' sums of their rays' `ray_grads` (`12·n_views`).
    view_acc: wgpu::Buffer,
    n_views: usize,
    capacity_rays: usize,
}

impl GpuPoseCorrection {
    /// Compiles the kernels; every view's correction starts at zero. `trans_penalty` and
    /// `rot_penalty` weigh nerfstudio's regulariser (mean over views of `‖τ‖` and `‖ω‖`).
    pub fn new(ctx: &GpuContext, n_views: usize, capacity_rays: usize, trans_penalty: f32, rot_penalty: f32) -> Result<Self, GpuError> {
        if n_views == 0 {
            return Err(GpuError::Unsupported("camera pose refinement without training views".into()));
        }
        let module = ctx.shader_module("pose.wgsl", &shaders::with_common(shaders::POSE));
        let params = PoseParams { n_views: n_views as u32, capacity_rays: capacity_rays as u32, trans_penalty, rot_penalty };
        let cap = capacity_rays.max(1);
        Ok(Self {
            correct: Kernel::from_module(ctx, &module, "pose_correct", &[]),
            rays_backward: Kernel::from_module(ctx, &module, "pose_rays_backward", &[]),
            sums: ViewSums::new(ctx, n_views, capacity_rays),
            view_grads: Kernel::from_module(ctx, &module, "pose_view_grads", &[]),
            uniform: ctx.uniform("pose params", &params),
            params: ctx.zeros("pose corrections", 4 * PARAMS_PER_VIEW * n_views),
            grads: ctx.zeros("pose correction grads", 4 * PARAMS_PER_VIEW * n_views),
            reg_terms: ctx.zeros("pose regulariser terms", 4 * n_views),
            base_dirs: ctx.zeros_checked("pose base dirs", 12 * cap)?,
            ray_grads: ctx.zeros_checked("pose ray grads", 48 * cap)?,
            view_acc: ctx.zeros("pose view sums", 48 * n_views),
            n_views,
            capacity_rays,
        })
    }

    /// Views the corrections are for.
    pub fn n_views(&self) -> usize {
        self.n_views
    }

    /// Number of correction values (`6·n_views`).
    pub fn len(&self) -> usize {
        PARAMS_PER_VIEW * self.n_views
    }

    /// Always false: there is at least one view.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Records the correction of the `counters[0]` rays in place (`o += τ_v`, `d ← R(ω_v) d`),
    /// keeping their directions before it and zeroing their gradient sums for the step.
    pub fn record_correct(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, rays: &PoseRays<'_>) {
        self.correct.record(
            ctx,
            enc,
            &[(0, &self.uniform), (1, rays.counters), (2, rays.views), (3, &self.params), (4, rays.origins), (5, rays.dirs), (6, &self.base_dirs), (11, &self.ray_grads)],
            groups_1d(self.capacity_rays, WG),
        );
    }

    /// Records, for one stage, the sums over each ray's samples of the field's input gradients
    /// (`∂L/∂o' += Σ ∂L/∂x`, `∂L/∂d' += Σ t ∂L/∂x + ∂L/∂dir`), added to the ray's sums since
    /// [`record_correct`](Self::record_correct).
    pub fn record_rays_backward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, counters: &wgpu::Buffer, s: &PoseSampleGrads<'_>) {
        self.rays_backward.record(
            ctx,
            enc,
            &[
                (0, &self.uniform),
                (1, counters),
                (6, &self.base_dirs),
                (7, s.offsets),
                (8, s.t),
                (9, s.d_positions),
                (10, s.d_dirs),
                (11, &self.ray_grads),
            ],
            groups_1d(self.capacity_rays, WG),
        );
    }

    /// Records each view's gradient from its rays' sums plus the regulariser's, **added** to
    /// [`grads`](Self::grads), and the regulariser's terms into [`reg_terms`](Self::reg_terms).
    pub fn record_reduce(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, counters: &wgpu::Buffer, views: &wgpu::Buffer) {
        enc.clear_buffer(&self.view_acc, 0, None);
        self.sums.record(ctx, enc, counters, views, &self.ray_grads, &self.view_acc);
        self.view_grads.record(
            ctx,
            enc,
            &[(0, &self.uniform), (3, &self.params), (12, &self.grads), (13, &self.reg_terms), (14, &self.view_acc)],
            groups_1d(self.n_views, WG),
        );
    }

    /// Sets the corrections (`6·n_views` values).
    pub fn set_params(&self, ctx: &GpuContext, params: &[f32]) -> Result<(), GpuError> {
        if params.len() != self.len() {
            return Err(GpuError::Unsupported(format!("{} pose-correction values for {} views", params.len(), self.n_views)));
        }
        ctx.write(&self.params, 0, params);
        Ok(())
    }

    /// The corrections, read back.
    pub fn read_params(&self, ctx: &GpuContext) -> Result<Vec<f32>, GpuError> {
        ctx.read_f32(&self.params, self.len())
    }

    /// The regulariser's value at the last reduction (the sum of [`reg_terms`](Self::reg_terms)).
    pub fn read_regulariser(&self, ctx: &GpuContext) -> Result<f32, GpuError> {
        Ok(ctx.read_f32(&self.reg_terms, self.n_views)?.iter().map(|&x| x as f64).sum::<f64>() as f32)
    }

    /// The corrected rays of host slices (tests and one-off use): `(origins, dirs)`. Panics past
    /// the capacity.
    pub fn correct(&self, ctx: &GpuContext, views: &[u32], origins: &[f32], dirs: &[f32]) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let n = views.len();
        assert!(n <= self.capacity_rays, "{n} rays exceed the capacity");
        let (c, v, o, d) = upload_rays(ctx, views, origins, dirs);
        let mut enc = ctx.encoder("pose correct");
        self.record_correct(ctx, &mut enc, &PoseRays { counters: &c, views: &v, origins: &o, dirs: &d });
        ctx.queue.submit([enc.finish()]);
        Ok((ctx.read_f32(&o, 3 * n)?, ctx.read_f32(&d, 3 * n)?))
    }

    /// A whole step's pose backward on host slices (tests): the rays (before the correction) are
    /// corrected, then each stage's `(ray offsets, t, ∂L/∂x, ∂L/∂dir)` is gathered per ray, then
    /// reduced per view onto `grads` (what the gradient is added to). Returns
    /// `(grads after, regulariser value)`.
    #[allow(clippy::type_complexity)]
    pub fn backward(
        &self,
        ctx: &GpuContext,
        views: &[u32],
        origins: &[f32],
        dirs: &[f32],
        stages: &[(&[u32], &[f32], &[f32], &[f32])],
        grads: &[f32],
    ) -> Result<(Vec<f32>, f32), GpuError> {
        let n = views.len();
        assert!(n <= self.capacity_rays, "{n} rays exceed the capacity");
        assert_eq!(grads.len(), self.len(), "one gradient per correction value");
        let (c, v, o, d) = upload_rays(ctx, views, origins, dirs);
        ctx.write(&self.grads, 0, grads);
        ctx.write(&self.reg_terms, 0, &vec![f32::NAN; self.n_views]);
        let mut enc = ctx.encoder("pose backward");
        self.record_correct(ctx, &mut enc, &PoseRays { counters: &c, views: &v, origins: &o, dirs: &d });
        let bufs: Vec<_> = stages
            .iter()
            .map(|(offsets, t, dx, dd)| {
                assert_eq!(offsets.len(), n + 1, "one offset per ray and one more");
                [ctx.upload("offsets", offsets), ctx.upload("t", t), ctx.upload("d positions", dx), ctx.upload("d dirs", dd)]
            })
            .collect();
        for [offsets, t, d_positions, d_dirs] in &bufs {
            self.record_rays_backward(ctx, &mut enc, &c, &PoseSampleGrads { offsets, t, d_positions, d_dirs });
        }
        self.record_reduce(ctx, &mut enc, &c, &v);
        ctx.queue.submit([enc.finish()]);
        Ok((ctx.read_f32(&self.grads, self.len())?, self.read_regulariser(ctx)?))
    }
}

fn upload_rays(ctx: &GpuContext, views: &[u32], origins: &[f32], dirs: &[f32]) -> (wgpu::Buffer, wgpu::Buffer, wgpu::Buffer, wgpu::Buffer) {
    let n = views.len();
    assert_eq!(origins.len(), 3 * n, "3 values per origin");
    assert_eq!(dirs.len(), 3 * n, "3 values per direction");
    // Storage buffers may not be empty.
    let pad = |x: &[f32]| if x.is_empty() { vec![0.0] } else { x.to_vec() };
    (
        ctx.upload("counters", &[n as u32, 0]),
        ctx.upload("views", &if n == 0 { vec![0] } else { views.to_vec() }),
        ctx.upload("origins", &pad(origins)),
        ctx.upload("dirs", &pad(dirs)),
    )
}
