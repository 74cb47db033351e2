//! Per-view affine colour correction of composited pixels on the device (`shaders/color.wgsl`;
//! CPU twins `nerf_render::color_correct_forward` and `color_correct_backward`). The corrections
//! (12 values per view) and their gradients live in buffers this type owns; the trainer steps
//! them with a [`GpuAdam`](crate::optim::GpuAdam).

use crate::kernel::{groups_1d, Kernel};
use crate::views::ViewSums;
use crate::layout::ColorParams;
use crate::{shaders, GpuContext, GpuError};

/// Values per view (a row-major 3×3 matrix, then an offset).
pub const PARAMS_PER_VIEW: usize = 12;
const WG: u32 = 64;

/// Device buffers of one batch's pixels as the correction reads them.
pub struct ColorInputs<'a> {
    /// `counters` (`[0]` = number of rays).
    pub counters: &'a wgpu::Buffer,
    /// View index per ray (u32).
    pub views: &'a wgpu::Buffer,
    /// Composited colour per ray (`3·n_rays`, background included).
    pub rgb: &'a wgpu::Buffer,
    /// Opacity per ray.
    pub opacity: &'a wgpu::Buffer,
    /// Background per ray (`3·n_rays`).
    pub background: &'a wgpu::Buffer,
}

/// The corrections of `n_views` views for batches of up to `capacity_rays` rays.
pub struct GpuColorCorrection {
    forward: Kernel,
    backward: Kernel,
    reduce: ViewSums,
    uniform: wgpu::Buffer,
    /// The corrections, `12·n_views` f32 (identity at creation).
    pub params: wgpu::Buffer,
    /// Their gradient, `12·n_views` f32 (zero at creation): [`record_backward`](Self::record_backward)
    /// adds to it; the optimiser's step zeroes it again (`GpuAdam::record_step`).
    pub grads: wgpu::Buffer,
    ray_grads: wgpu::Buffer,
    n_views: usize,
    capacity_rays: usize,
}

impl GpuColorCorrection {
    /// Compiles the kernels and sets every view's correction to the identity.
    pub fn new(ctx: &GpuContext, n_views: usize, capacity_rays: usize) -> Result<Self, GpuError> {
        if n_views == 0 {
            return Err(GpuError::Unsupported("colour correction without training views".into()));
        }
        let module = ctx.shader_module("color.wgsl", &shaders::with_common(shaders::COLOR));
        let identity: Vec<f32> = (0..n_views).flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]).collect();
        let params = ColorParams { n_views: n_views as u32, capacity_rays: capacity_rays as u32, _pad: [0; 2] };
        Ok(Self {
            forward: Kernel::from_module(ctx, &module, "color_forward", &[]),
            backward: Kernel::from_module(ctx, &module, "color_backward", &[]),
            reduce: ViewSums::new(ctx, n_views, capacity_rays),
            uniform: ctx.uniform("color params", &params),
            params: ctx.upload("color corrections", &identity),
            grads: ctx.zeros("color correction grads", 4 * PARAMS_PER_VIEW * n_views),
            ray_grads: ctx.zeros_checked("color correction ray grads", 4 * PARAMS_PER_VIEW * capacity_rays.max(1))?,
            n_views,
            capacity_rays,
        })
    }

    /// Views the corrections are for.
    pub fn n_views(&self) -> usize {
        self.n_views
    }

    /// Number of correction values (`12·n_views`).
    pub fn len(&self) -> usize {
        PARAMS_PER_VIEW * self.n_views
    }

    /// Always false: there is at least one view.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Records the corrected pixels of the `counters[0]` rays into `out` (`3·n_rays`).
    pub fn record_forward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, x: &ColorInputs<'_>, out: &wgpu::Buffer) {
        self.forward.record(
            ctx,
            enc,
            &[(0, &self.uniform), (1, x.counters), (2, x.views), (3, &self.params), (4, x.rgb), (5, x.opacity), (6, x.background), (7, out)],
            groups_1d(self.capacity_rays, WG),
        );
    }

    /// Records the backward pass: `d_ray` holds ∂L/∂(corrected pixels) and receives ∂L/∂rgb in
    /// its place, `d_opacity` (`n_rays`) receives ∂L/∂opacity, and each view's gradient is
    /// **added** to [`grads`](Self::grads).
    pub fn record_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        x: &ColorInputs<'_>,
        d_ray: &wgpu::Buffer,
        d_opacity: &wgpu::Buffer,
    ) {
        self.backward.record(
            ctx,
            enc,
            &[
                (0, &self.uniform),
                (1, x.counters),
                (2, x.views),
                (3, &self.params),
                (4, x.rgb),
                (5, x.opacity),
                (6, x.background),
                (8, d_ray),
                (9, d_opacity),
                (10, &self.ray_grads),
            ],
            groups_1d(self.capacity_rays, WG),
        );
        self.reduce.record(ctx, enc, x.counters, x.views, &self.ray_grads, &self.grads);
    }

    /// Sets the corrections (`12·n_views` values).
    pub fn set_params(&self, ctx: &GpuContext, params: &[f32]) -> Result<(), GpuError> {
        if params.len() != self.len() {
            return Err(GpuError::Unsupported(format!("{} colour-correction values for {} views", params.len(), self.n_views)));
        }
        ctx.write(&self.params, 0, params);
        Ok(())
    }

    /// The corrections, read back.
    pub fn read_params(&self, ctx: &GpuContext) -> Result<Vec<f32>, GpuError> {
        ctx.read_f32(&self.params, self.len())
    }

    fn upload(ctx: &GpuContext, views: &[u32], rgb: &[f32], opacity: &[f32], background: &[f32]) -> [wgpu::Buffer; 5] {
        [
            ctx.upload("counters", &[opacity.len() as u32, 0]),
            ctx.upload("views", views),
            ctx.upload("rgb", rgb),
            ctx.upload("opacity", opacity),
            ctx.upload("background", background),
        ]
    }

    /// The corrected pixels of host slices (tests and one-off use). Panics past the capacity.
    pub fn forward(&self, ctx: &GpuContext, views: &[u32], rgb: &[f32], opacity: &[f32], background: &[f32]) -> Result<Vec<f32>, GpuError> {
        let n = opacity.len();
        assert!(n <= self.capacity_rays, "{n} rays exceed the capacity");
        let [c, v, r, o, b] = Self::upload(ctx, views, rgb, opacity, background);
        let out = ctx.upload("out", &vec![f32::NAN; 3 * n]);
        let mut enc = ctx.encoder("color forward");
        self.record_forward(ctx, &mut enc, &ColorInputs { counters: &c, views: &v, rgb: &r, opacity: &o, background: &b }, &out);
        ctx.queue.submit([enc.finish()]);
        ctx.read_f32(&out, 3 * n)
    }

    /// The backward pass on host slices (tests): `grads` is what the gradient is added to;
    /// returns `(∂L/∂rgb, ∂L/∂opacity, grads after)`.
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    pub fn backward(
        &self,
        ctx: &GpuContext,
        views: &[u32],
        rgb: &[f32],
        opacity: &[f32],
        background: &[f32],
        d_out: &[f32],
        grads: &[f32],
    ) -> Result<(Vec<f32>, Vec<f32>, Vec<f32>), GpuError> {
        let n = opacity.len();
        assert!(n <= self.capacity_rays, "{n} rays exceed the capacity");
        assert_eq!(grads.len(), self.len(), "one gradient per correction value");
        let [c, v, r, o, b] = Self::upload(ctx, views, rgb, opacity, background);
        let d_ray = ctx.upload("d_ray", d_out);
        let d_op = ctx.upload("d_opacity", &vec![f32::NAN; n]);
        ctx.write(&self.grads, 0, grads);
        let mut enc = ctx.encoder("color backward");
        self.record_backward(ctx, &mut enc, &ColorInputs { counters: &c, views: &v, rgb: &r, opacity: &o, background: &b }, &d_ray, &d_op);
        ctx.queue.submit([enc.finish()]);
        Ok((ctx.read_f32(&d_ray, 3 * n)?, ctx.read_f32(&d_op, n)?, ctx.read_f32(&self.grads, self.len())?))
    }
}
