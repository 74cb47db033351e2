//! Compositing (`shaders/composite.wgsl`) and the training-step glue (`shaders/train.wgsl`: loss,
//! adaptive batch size). `record_*` methods only record into the caller's encoder (a training step
//! is one submission); `forward`/`backward`/`loss` upload host slices, run and read back (tests and
//! one-off use).

use crate::kernel::{groups_1d, Kernel};
use crate::{layout, shaders, GpuContext, GpuError};
pub use crate::layout::{BatchParams, DepthParams, DistortionParams, LossParams};

/// Outputs of [`Compositor::forward`], read back to the host.
#[derive(Clone, Debug, Default)]
pub struct CompositeOutputs {
    /// `3·n_rays`.
    pub rgb: Vec<f32>,
    /// `n_rays`.
    pub opacity: Vec<f32>,
    /// `n_rays`.
    pub depth: Vec<f32>,
    /// `n` samples.
    pub weights: Vec<f32>,
}

/// Gradients of [`Compositor::backward`], read back to the host.
#[derive(Clone, Debug, Default)]
pub struct CompositeGrads {
    /// dL/dσ per sample (`n`).
    pub d_sigma: Vec<f32>,
    /// dL/dc per sample (`3·n`).
    pub d_rgb: Vec<f32>,
}

/// Device buffers of a packed batch as the compositing kernels read them.
pub struct PackedBuffers<'a> {
    /// `counters` (`[0]` = number of rays).
    pub counters: &'a wgpu::Buffer,
    /// CSR offsets, `n_rays + 1` u32.
    pub offsets: &'a wgpu::Buffer,
    /// σ per sample.
    pub sigma: &'a wgpu::Buffer,
    /// rgb per sample (`3·n`).
    pub rgb: &'a wgpu::Buffer,
    /// Interval lengths per sample.
    pub dt: &'a wgpu::Buffer,
    /// Distances per sample.
    pub t: &'a wgpu::Buffer,
    /// Per-ray background (`3·n_rays`), or a dummy when the compositor has none.
    pub background: &'a wgpu::Buffer,
}

/// Forward outputs on the device.
pub struct CompositeTargets<'a> {
    /// `3·n_rays`.
    pub rgb: &'a wgpu::Buffer,
    /// `n_rays`.
    pub opacity: &'a wgpu::Buffer,
    /// `n_rays`.
    pub depth: &'a wgpu::Buffer,
    /// `n` samples.
    pub weights: &'a wgpu::Buffer,
}

/// The compositing kernels, pipelines built once for a ray capacity and an early-stop threshold.
pub struct Compositor {
    forward: Kernel,
    backward: Kernel,
    distortion: Kernel,
    depth: Kernel,
    params: wgpu::Buffer,
    distortion_params: wgpu::Buffer,
    depth_params: wgpu::Buffer,
    capacity_rays: usize,
    zeros: wgpu::Buffer,
}

impl Compositor {
    /// Builds the pipelines for at most `capacity_rays` rays per launch.
    pub fn new(ctx: &GpuContext, capacity_rays: usize, t_threshold: f32, has_background: bool) -> Self {
        let src = shaders::with_common(shaders::COMPOSITE);
        let module = ctx.shader_module("composite.wgsl", &src);
        let params = layout::CompositeParams {
            n_rays: capacity_rays as u32,
            t_threshold,
            has_background: has_background as u32,
            _pad: 0,
        };
        Self {
            forward: Kernel::from_module(ctx, &module, "composite_forward", &[]),
            backward: Kernel::from_module(ctx, &module, "composite_backward", &[]),
            distortion: Kernel::from_module(ctx, &module, "distortion_backward", &[]),
            depth: Kernel::from_module(ctx, &module, "depth_loss", &[]),
            params: ctx.uniform("composite params", &params),
            distortion_params: ctx.uniform("distortion params", &DistortionParams { scale: 1.0, lambda: 0.0, _pad: [0; 2] }),
            depth_params: ctx.uniform("depth params", &DepthParams { lambda: 0.0, _pad: [0; 3] }),
            capacity_rays,
            zeros: ctx.zeros("composite zeros", 4 * capacity_rays),
        }
    }

    /// Records the forward quadrature (rays from `b.counters[0]`).
    pub fn record_forward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, b: &PackedBuffers<'_>, out: &CompositeTargets<'_>) {
        self.forward.record(
            ctx,
            enc,
            &[
                (0, &self.params),
                (1, b.offsets),
                (2, b.sigma),
                (3, b.rgb),
                (4, b.dt),
                (5, b.t),
                (6, b.background),
                (7, out.rgb),
                (8, out.opacity),
                (9, out.depth),
                (10, out.weights),
                (16, b.counters),
            ],
            groups_1d(self.capacity_rays, 64),
        );
    }

    /// Records the backward pass: dL/dσ and dL/dc per sample from the ray gradient `d_ray_rgb`
    /// (and optional opacity/depth gradients), given the forward's `weights`.
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        b: &PackedBuffers<'_>,
        weights: &wgpu::Buffer,
        d_ray_rgb: &wgpu::Buffer,
        d_opacity: Option<&wgpu::Buffer>,
        d_depth: Option<&wgpu::Buffer>,
        d_sigma: &wgpu::Buffer,
        d_sample_rgb: &wgpu::Buffer,
    ) {
        self.backward.record(
            ctx,
            enc,
            &[
                (0, &self.params),
                (1, b.offsets),
                (2, b.sigma),
                (3, b.rgb),
                (4, b.dt),
                (5, b.t),
                (6, b.background),
                (10, weights),
                (11, d_ray_rgb),
                (12, d_opacity.unwrap_or(&self.zeros)),
                (13, d_depth.unwrap_or(&self.zeros)),
                (14, d_sigma),
                (15, d_sample_rgb),
                (16, b.counters),
            ],
            groups_1d(self.capacity_rays, 64),
        );
    }

    /// Sets the distortion loss of [`Compositor::record_distortion`]: distances to `s = scale·t`,
    /// weight λ (the loss is λ times the mean over the step's rays). A queued write: set it before
    /// the steps it applies to are submitted.
    pub fn set_distortion(&self, ctx: &GpuContext, scale: f32, lambda: f32) {
        ctx.write(&self.distortion_params, 0, &[DistortionParams { scale, lambda, _pad: [0; 2] }]);
    }

    /// Records mip-NeRF 360's distortion loss over the `counters[0]` rays (CPU twin:
    /// `nerf_render::distortion_loss_grad`): the loss per ray into `ray_loss` and its σ gradient
    /// **added** to `d_sigma`, from the forward's `weights`.
    pub fn record_distortion(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        b: &PackedBuffers<'_>,
        weights: &wgpu::Buffer,
        d_sigma: &wgpu::Buffer,
        ray_loss: &wgpu::Buffer,
    ) {
        self.distortion.record(
            ctx,
            enc,
            &[
                (0, &self.params),
                (1, b.offsets),
                (2, b.sigma),
                (4, b.dt),
                (5, b.t),
                (10, weights),
                (14, d_sigma),
                (16, b.counters),
                (17, &self.distortion_params),
                (18, ray_loss),
            ],
            groups_1d(self.capacity_rays, 64),
        );
    }

    /// Sets the weight λ of [`Compositor::record_depth_loss`] (a queued write: set it before the
    /// steps it applies to are submitted).
    pub fn set_depth_loss(&self, ctx: &GpuContext, lambda: f32) {
        ctx.write(&self.depth_params, 0, &[DepthParams { lambda, _pad: [0; 3] }]);
    }

    /// Records depth supervision over the `counters[0]` rays (CPU twin:
    /// `nerf_render::depth_loss_grad`): from the forward's expected `depth` and the measured
    /// `target` (0: none), the loss per ray into `ray_loss` and `d_depth = dL/dD̂`, which
    /// [`Compositor::record_backward`] takes.
    #[allow(clippy::too_many_arguments)]
    pub fn record_depth_loss(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        depth: &wgpu::Buffer,
        target: &wgpu::Buffer,
        d_depth: &wgpu::Buffer,
        ray_loss: &wgpu::Buffer,
    ) {
        self.depth.record(
            ctx,
            enc,
            &[(0, &self.params), (9, depth), (16, counters), (19, &self.depth_params), (20, target), (21, d_depth), (22, ray_loss)],
            groups_1d(self.capacity_rays, 64),
        );
    }

    /// Depth supervision on host slices (tests): expected `depth` and measured `target` per ray;
    /// returns `(d_depth, loss per ray)`.
    pub fn depth_loss(&self, ctx: &GpuContext, depth: &[f32], target: &[f32], lambda: f32) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let n_rays = depth.len();
        assert!(n_rays <= self.capacity_rays && target.len() == n_rays, "{n_rays} rays, {} targets", target.len());
        let c = ctx.upload("counters", &[n_rays as u32, 0]);
        let (d, t) = (ctx.upload("depth", depth), ctx.upload("target", target));
        let (dd, loss) = (ctx.upload("d_depth", &vec![f32::NAN; n_rays]), ctx.upload("ray loss", &vec![f32::NAN; n_rays]));
        self.set_depth_loss(ctx, lambda);
        let mut enc = ctx.encoder("depth loss");
        self.record_depth_loss(ctx, &mut enc, &c, &d, &t, &dd, &loss);
        ctx.queue.submit([enc.finish()]);
        Ok((ctx.read_f32(&dd, n_rays)?, ctx.read_f32(&loss, n_rays)?))
    }

    /// The distortion loss of a packed batch (host slices in and out: tests): `d_sigma` (`n`) is
    /// what the kernel adds the gradient to; returns `(d_sigma, loss per ray)`.
    #[allow(clippy::too_many_arguments)]
    pub fn distortion(
        &self,
        ctx: &GpuContext,
        ray_offsets: &[u32],
        sigma: &[f32],
        dt: &[f32],
        t: &[f32],
        weights: &[f32],
        scale: f32,
        lambda: f32,
        d_sigma: &[f32],
    ) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let n_rays = ray_offsets.len().saturating_sub(1);
        assert!(n_rays <= self.capacity_rays, "{n_rays} rays exceed the compositor's capacity");
        let n = sigma.len();
        let rgb = vec![0.0; 3 * n];
        let [c, o, s, col, d, tt, bg] = Self::upload_batch(ctx, ray_offsets, sigma, &rgb, dt, t, None);
        let w = ctx.upload("weights", weights);
        let d_s = ctx.upload("d_sigma", d_sigma);
        let loss = ctx.upload("ray loss", &vec![f32::NAN; n_rays]);
        self.set_distortion(ctx, scale, lambda);
        let b = PackedBuffers { counters: &c, offsets: &o, sigma: &s, rgb: &col, dt: &d, t: &tt, background: &bg };
        let mut enc = ctx.encoder("distortion");
        self.record_distortion(ctx, &mut enc, &b, &w, &d_s, &loss);
        ctx.queue.submit([enc.finish()]);
        Ok((ctx.read_f32(&d_s, n)?, ctx.read_f32(&loss, n_rays)?))
    }

    fn upload_batch(
        ctx: &GpuContext,
        ray_offsets: &[u32],
        sigma: &[f32],
        rgb: &[f32],
        dt: &[f32],
        t: &[f32],
        background: Option<&[f32]>,
    ) -> [wgpu::Buffer; 7] {
        let n_rays = ray_offsets.len().saturating_sub(1) as u32;
        [
            ctx.upload("counters", &[n_rays, sigma.len() as u32]),
            ctx.upload("offsets", ray_offsets),
            ctx.upload("sigma", sigma),
            ctx.upload("rgb", rgb),
            ctx.upload("dt", dt),
            ctx.upload("t", t),
            ctx.upload("background", background.unwrap_or(&[])),
        ]
    }

    /// Composites packed samples (host slices in, host vectors out: tests and one-off use).
    /// Panics when the batch has more rays than the capacity given to [`Compositor::new`].
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &self,
        ctx: &GpuContext,
        ray_offsets: &[u32],
        sigma: &[f32],
        rgb: &[f32],
        dt: &[f32],
        t: &[f32],
        background: Option<&[f32]>,
    ) -> Result<CompositeOutputs, GpuError> {
        let n_rays = ray_offsets.len().saturating_sub(1);
        assert!(n_rays <= self.capacity_rays, "{n_rays} rays exceed the compositor's capacity");
        let n = sigma.len();
        let [c, o, s, col, d, tt, bg] = Self::upload_batch(ctx, ray_offsets, sigma, rgb, dt, t, background);
        // Outputs start poisoned (NaN) so a kernel that skips a slot cannot pass the tests.
        let poison = |label, len: usize| ctx.upload(label, &vec![f32::NAN; len]);
        let (o_rgb, o_op, o_depth, o_w) = (poison("rgb", 3 * n_rays), poison("opacity", n_rays), poison("depth", n_rays), poison("weights", n));
        let b = PackedBuffers { counters: &c, offsets: &o, sigma: &s, rgb: &col, dt: &d, t: &tt, background: &bg };
        let mut enc = ctx.encoder("composite");
        self.record_forward(ctx, &mut enc, &b, &CompositeTargets { rgb: &o_rgb, opacity: &o_op, depth: &o_depth, weights: &o_w });
        ctx.queue.submit([enc.finish()]);
        Ok(CompositeOutputs {
            rgb: ctx.read_f32(&o_rgb, 3 * n_rays)?,
            opacity: ctx.read_f32(&o_op, n_rays)?,
            depth: ctx.read_f32(&o_depth, n_rays)?,
            weights: ctx.read_f32(&o_w, n)?,
        })
    }

    /// Gradients w.r.t. σ and the sample colours (host slices in and out: tests and one-off use).
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        ctx: &GpuContext,
        ray_offsets: &[u32],
        sigma: &[f32],
        rgb: &[f32],
        dt: &[f32],
        t: &[f32],
        background: Option<&[f32]>,
        weights: &[f32],
        d_ray_rgb: &[f32],
        d_opacity: Option<&[f32]>,
        d_depth: Option<&[f32]>,
    ) -> Result<CompositeGrads, GpuError> {
        let n_rays = ray_offsets.len().saturating_sub(1);
        assert!(n_rays <= self.capacity_rays, "{n_rays} rays exceed the compositor's capacity");
        let n = sigma.len();
        let [c, o, s, col, d, tt, bg] = Self::upload_batch(ctx, ray_offsets, sigma, rgb, dt, t, background);
        let w = ctx.upload("weights", weights);
        let drgb = ctx.upload("d_ray_rgb", d_ray_rgb);
        let dop = d_opacity.map(|v| ctx.upload("d_opacity", v));
        let ddep = d_depth.map(|v| ctx.upload("d_depth", v));
        let d_s = ctx.upload("d_sigma", &vec![f32::NAN; n]);
        let d_c = ctx.upload("d_rgb", &vec![f32::NAN; 3 * n]);
        let b = PackedBuffers { counters: &c, offsets: &o, sigma: &s, rgb: &col, dt: &d, t: &tt, background: &bg };
        let mut enc = ctx.encoder("composite backward");
        self.record_backward(ctx, &mut enc, &b, &w, &drgb, dop.as_ref(), ddep.as_ref(), &d_s, &d_c);
        ctx.queue.submit([enc.finish()]);
        Ok(CompositeGrads { d_sigma: ctx.read_f32(&d_s, n)?, d_rgb: ctx.read_f32(&d_c, 3 * n)? })
    }
}

/// The training-step glue kernels (`shaders/train.wgsl`): photometric MSE + gradient, and the
/// adaptive batch size.
pub struct TrainGlue {
    loss: Kernel,
    next_batch: Kernel,
    count: Kernel,
    from_mean: Kernel,
    chunk: Kernel,
    loss_params: wgpu::Buffer,
    batch_params: wgpu::Buffer,
    capacity_rays: usize,
}

impl TrainGlue {
    /// Pipelines for `capacity_rays` rays; `batch` sizes steps by samples (see `next_batch`).
    pub fn new(ctx: &GpuContext, capacity_rays: usize, batch: BatchParams) -> Self {
        let src = shaders::with_common(shaders::TRAIN);
        let module = ctx.shader_module("train.wgsl", &src);
        Self {
            loss: Kernel::from_module(ctx, &module, "mse_loss", &[]),
            next_batch: Kernel::from_module(ctx, &module, "next_batch", &[]),
            count: Kernel::from_module(ctx, &module, "count_samples", &[]),
            from_mean: Kernel::from_module(ctx, &module, "batch_from_mean", &[]),
            chunk: Kernel::from_module(ctx, &module, "chunk_count", &[]),
            loss_params: ctx.uniform("loss params", &LossParams { capacity_rays: capacity_rays as u32, huber_delta: 0.0, _pad: [0; 2] }),
            batch_params: ctx.uniform("batch params", &batch),
            capacity_rays,
        }
    }

    /// Selects the loss of [`TrainGlue::record_loss`]: the MSE (`None`, the default) or the Huber
    /// loss with this δ (CPU twin: `nerf_render::photometric_loss_grad`). A queued write: set it before
    /// the steps it applies to are submitted.
    pub fn set_huber_delta(&self, ctx: &GpuContext, delta: Option<f32>) {
        ctx.write(&self.loss_params, 4, &[delta.unwrap_or(0.0)]);
    }

    /// Records the loss over the `counters[0]` rays: `d_pred = 2(pred − target)/(3n)` (MSE; with a
    /// Huber δ the residual is clamped to ±δ first) and the per-ray squared error `ray_sq_err`
    /// (the host sums it when it wants the MSE).
    #[allow(clippy::too_many_arguments)]
    pub fn record_loss(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        pred: &wgpu::Buffer,
        target: &wgpu::Buffer,
        d_pred: &wgpu::Buffer,
        ray_sq_err: &wgpu::Buffer,
    ) {
        self.loss.record(
            ctx,
            enc,
            &[(0, &self.loss_params), (1, counters), (2, pred), (3, target), (4, d_pred), (5, ray_sq_err)],
            groups_1d(self.capacity_rays, 64),
        );
    }

    /// Records the batch-size update: from `counters[1]` samples over `counters[0]` rays, the
    /// running mean in `samples_per_ray[0]` and the next step's `counters[0]`.
    pub fn record_next_batch(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, counters: &wgpu::Buffer, samples_per_ray: &wgpu::Buffer) {
        self.next_batch.record(ctx, enc, &[(0, &self.batch_params), (1, counters), (2, samples_per_ray)], [1, 1, 1]);
    }

    /// Records `seen += counters[1]` (a 64-bit total in two u32: `[lo, hi]`).
    pub fn record_count(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, counters: &wgpu::Buffer, seen: &wgpu::Buffer) {
        self.count.record(ctx, enc, &[(1, counters), (3, seen)], [1, 1, 1]);
    }

    /// Records `counters[0] = clamp(target / samples_per_ray[0])` when the mean is set (after
    /// rendering reused the counters, or after a resume).
    pub fn record_batch_from_mean(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, counters: &wgpu::Buffer, samples_per_ray: &wgpu::Buffer) {
        self.from_mean.record(ctx, enc, &[(0, &self.batch_params), (1, counters), (2, samples_per_ray)], [1, 1, 1]);
    }

    /// A uniform for [`TrainGlue::record_chunk_count`]: the chunk `[offset, offset + size)`.
    pub fn chunk_uniform(ctx: &GpuContext, offset: usize, size: usize) -> wgpu::Buffer {
        ctx.uniform("chunk", &[offset as u32, size as u32, 0, 0])
    }

    /// Records `dst[1] = clamp(src[1] − offset, 0, size)` with the chunk of `chunk` (made by
    /// [`TrainGlue::chunk_uniform`]): the item count of one chunk of a chunked launch.
    pub fn record_chunk_count(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, chunk: &wgpu::Buffer, src: &wgpu::Buffer, dst: &wgpu::Buffer) {
        self.chunk.record(ctx, enc, &[(0, chunk), (1, dst), (6, src)], [1, 1, 1]);
    }

    /// Host convenience: the loss kernel on host slices; returns (`d_pred`, per-ray squared error).
    pub fn loss(&self, ctx: &GpuContext, pred: &[f32], target: &[f32]) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let n = pred.len() / 3;
        assert!(n <= self.capacity_rays);
        let c = ctx.upload("counters", &[n as u32, 0]);
        let (p, t) = (ctx.upload("pred", pred), ctx.upload("target", target));
        let d = ctx.upload("d_pred", &vec![f32::NAN; 3 * n]);
        let e = ctx.upload("sq", &vec![f32::NAN; n]);
        let mut enc = ctx.encoder("loss");
        self.record_loss(ctx, &mut enc, &c, &p, &t, &d, &e);
        ctx.queue.submit([enc.finish()]);
        Ok((ctx.read_f32(&d, 3 * n)?, ctx.read_f32(&e, n)?))
    }
}
