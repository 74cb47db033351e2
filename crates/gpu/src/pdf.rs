//! Stratified and hierarchical (inverse-CDF) sampling on the device (`shaders/pdf.wgsl`), the
//! paper's coarse and fine passes, twins of [`nerf_sampling::stratified`] and
//! [`nerf_sampling::hierarchical`].
//!
//! Both write the packed layout of [`crate::sampling`]: `offsets [R+1]` u32, `positions [S][3]`,
//! `dirs [S][3]`, `t [S]`, `dt [S]` (δ_i = t_{i+1} − t_i, last δ = far − t_last). Rays come as
//! `origins [R][3]` and unit `dirs [R][3]`; near/far are scalars (the trainer's dataset bounds),
//! or with `clip_to_box` each ray's `[near, far] ∩ box` (twin: [`nerf_sampling::clip_segments`]).
//! The number of rays is read on the device from `counters[0]`.
//!
//! Random numbers are counter-based ([`crate::rng`]) so the host twins below reproduce them:
//! stratified jitter `u = rand_f32(seed, 0, r·N + k)`, hierarchical jitter
//! `ξ = rand_f32(seed, 1, r·n_fine + k)`. The per-call seed is written into a uniform with
//! [`GpuContext::write`]: record at most one call per sampler per submission.

use crate::kernel::{groups_1d, Kernel};
use crate::{shaders, GpuContext, GpuError};
use std::cell::Cell;

use crate::layout::{crop_rows, PdfParams};

const WG: u32 = 64;

/// The box fields of [`PdfParams`] (the rest zero).
fn clip_params(clip: Option<([f32; 3], [f32; 3])>) -> PdfParams {
    let Some((lo, hi)) = clip else { return PdfParams::default() };
    PdfParams { clip: 1, box_min: [lo[0], lo[1], lo[2], 0.0], box_max: [hi[0], hi[1], hi[2], 0.0], ..Default::default() }
}

fn module(ctx: &GpuContext) -> wgpu::ShaderModule {
    ctx.shader_module("pdf.wgsl", &shaders::with_common(shaders::PDF))
}

/// Output buffers of one packed sample batch (caller-owned, sized for the capacity).
pub struct PackedOut<'a> {
    /// `[R+1]` u32 CSR offsets.
    pub offsets: &'a wgpu::Buffer,
    /// `[S][3]` sample positions `o + t·d`.
    pub positions: &'a wgpu::Buffer,
    /// `[S][3]` the ray direction of each sample.
    pub dirs: &'a wgpu::Buffer,
    /// `[S]` distances along the ray.
    pub t: &'a wgpu::Buffer,
    /// `[S]` interval lengths.
    pub dt: &'a wgpu::Buffer,
}

/// `N` stratified samples per ray in `[near, far]` (the coarse pass).
pub struct GpuStratified {
    n_samples: usize,
    near: f32,
    far: f32,
    clip: Option<([f32; 3], [f32; 3])>,
    crop: Cell<Option<nerf_sampling::CropBox>>,
    uniform: wgpu::Buffer,
    kernel: Kernel,
}

impl GpuStratified {
    /// `n_samples ≥ 1` per ray between the scalars `near` and `far` (when `!(far ≥ near)` every
    /// ray gets no samples, as on the CPU; `far == near` gives zero-length samples). Errors on
    /// `n_samples == 0` or non-finite bounds.
    pub fn new(ctx: &GpuContext, n_samples: usize, near: f32, far: f32) -> Result<Self, GpuError> {
        if n_samples == 0 || n_samples > u32::MAX as usize || !near.is_finite() || !far.is_finite() {
            return Err(GpuError::Unsupported(format!(
                "stratified sampling needs n_samples ≥ 1 and finite near/far, got {n_samples}, {near}..{far}"
            )));
        }
        let p = PdfParams { n_per_ray: n_samples as u32, near, far, ..Default::default() };
        Ok(Self {
            n_samples,
            near,
            far,
            clip: None,
            crop: Cell::new(None),
            uniform: ctx.uniform("stratified.params", &p),
            kernel: Kernel::from_module(ctx, &module(ctx), "stratified", &[("WG", WG as f64)]),
        })
    }

    /// Samples each ray's `[near, far] ∩ box` instead (a miss: `[near, near]`, zero-length
    /// intervals), as [`nerf_sampling::clip_segments`]: NDC scenes.
    pub fn clip_to_box(mut self, aabb_min: [f32; 3], aabb_max: [f32; 3]) -> Self {
        self.clip = Some((aabb_min, aabb_max));
        self
    }

    /// Clips each ray's segment to a render crop box as well (`None`: none) for the records
    /// that follow, as the CPU's `nerf_sampling::CropBox::clip` (a miss: `[near, near]`).
    pub fn set_crop(&self, crop: Option<nerf_sampling::CropBox>) {
        self.crop.set(crop);
    }

    /// Samples per ray.
    pub fn n_samples(&self) -> usize {
        self.n_samples
    }

    /// Records the sampler for `n_rays = counters[0] ≤ capacity_rays` rays; writes
    /// `counters[1] = n_rays·N` and `out` (offsets `r·N`; `out` sized for `capacity_rays·N`
    /// samples). `jitter: Some(seed)` jitters within each bin, `None` takes the bin centres.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        origins: &wgpu::Buffer,
        dirs: &wgpu::Buffer,
        jitter: Option<u32>,
        out: &PackedOut<'_>,
        capacity_rays: usize,
    ) {
        let p = PdfParams {
            n_per_ray: self.n_samples as u32,
            near: self.near,
            far: self.far,
            jitter: jitter.is_some() as u32,
            seed: jitter.unwrap_or(0),
            crop: crop_rows(self.crop.get().as_ref()),
            ..clip_params(self.clip)
        };
        ctx.write(&self.uniform, 0, &[p]);
        let n = (capacity_rays * self.n_samples).max(capacity_rays + 1);
        self.kernel.record(
            ctx,
            enc,
            &[
                (0, &self.uniform),
                (1, counters),
                (3, origins),
                (4, dirs),
                (8, out.offsets),
                (9, out.positions),
                (10, out.dirs),
                (11, out.t),
                (12, out.dt),
            ],
            groups_1d(n, WG),
        );
    }
}

/// The hierarchical (fine) pass: `n_fine` samples per ray from the coarse weights with
/// nerf-pytorch's `sample_pdf`, merged with the coarse samples (sorted), as
/// [`nerf_sampling::hierarchical`].
pub struct GpuHierarchical {
    n_fine: usize,
    near: f32,
    far: f32,
    clip: Option<([f32; 3], [f32; 3])>,
    crop: Cell<Option<nerf_sampling::CropBox>>,
    uniform: wgpu::Buffer,
    offsets_kernel: Kernel,
    kernel: Kernel,
}

impl GpuHierarchical {
    /// `n_fine` importance samples per ray; `far` closes the last interval. Errors on a
    /// non-finite `far`.
    pub fn new(ctx: &GpuContext, n_fine: usize, far: f32) -> Result<Self, GpuError> {
        if n_fine > u32::MAX as usize || !far.is_finite() {
            return Err(GpuError::Unsupported(format!("hierarchical sampling: bad n_fine {n_fine} or far {far}")));
        }
        let m = module(ctx);
        let p = PdfParams { n_per_ray: n_fine as u32, far, ..Default::default() };
        Ok(Self {
            n_fine,
            near: 0.0,
            far,
            clip: None,
            crop: Cell::new(None),
            uniform: ctx.uniform("hierarchical.params", &p),
            offsets_kernel: Kernel::from_module(ctx, &m, "hier_offsets", &[("WG", 256.0)]),
            kernel: Kernel::from_module(ctx, &m, "hierarchical", &[("WG", WG as f64)]),
        })
    }

    /// Closes each ray's last interval at its `[near, far] ∩ box` end instead (`near` on a
    /// miss), as the CPU's hierarchical pass given [`nerf_sampling::clip_segments`]' far: the
    /// same box as the coarse pass's [`GpuStratified::clip_to_box`].
    pub fn clip_to_box(mut self, near: f32, aabb_min: [f32; 3], aabb_max: [f32; 3]) -> Self {
        self.near = near;
        self.clip = Some((aabb_min, aabb_max));
        self
    }

    /// Clips each ray's segment to a render crop box as well (`None`: none) for the records
    /// that follow, as the CPU's `nerf_sampling::CropBox::clip` (a miss: `[near, near]`).
    pub fn set_crop(&self, crop: Option<nerf_sampling::CropBox>) {
        self.crop.set(crop);
    }

    /// Fine samples per ray.
    pub fn n_fine(&self) -> usize {
        self.n_fine
    }

    /// Largest number of output samples for `capacity_coarse` coarse samples over
    /// `capacity_rays` rays (size the output buffers with it).
    pub fn capacity_samples(&self, capacity_rays: usize, capacity_coarse: usize) -> usize {
        capacity_coarse + capacity_rays * self.n_fine
    }

    /// Records the fine pass over the coarse batch (`n_rays = counters_in[0]`, coarse `offsets`,
    /// `t`, and the compositor's `weights`, one per coarse sample). Rays with ≥ 3 coarse samples
    /// get `n_fine` more (fewer keep their coarse samples). Writes `counters_out = [n_rays, S]`
    /// (a different buffer from `counters_in`: the coarse stage still needs its counts) and `out`.
    /// `jitter: Some(seed)` draws stratified `u`, `None` takes `linspace(0, 1, n_fine)`.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters_in: &wgpu::Buffer,
        coarse_offsets: &wgpu::Buffer,
        coarse_t: &wgpu::Buffer,
        coarse_weights: &wgpu::Buffer,
        origins: &wgpu::Buffer,
        dirs: &wgpu::Buffer,
        jitter: Option<u32>,
        counters_out: &wgpu::Buffer,
        out: &PackedOut<'_>,
        capacity_rays: usize,
    ) {
        let p = PdfParams {
            n_per_ray: self.n_fine as u32,
            near: self.near,
            far: self.far,
            jitter: jitter.is_some() as u32,
            seed: jitter.unwrap_or(0),
            crop: crop_rows(self.crop.get().as_ref()),
            ..clip_params(self.clip)
        };
        ctx.write(&self.uniform, 0, &[p]);
        self.offsets_kernel.record(
            ctx,
            enc,
            &[(0, &self.uniform), (2, counters_out), (5, coarse_offsets), (8, out.offsets), (13, counters_in)],
            [1, 1, 1],
        );
        self.kernel.record(
            ctx,
            enc,
            &[
                (0, &self.uniform),
                (3, origins),
                (4, dirs),
                (5, coarse_offsets),
                (6, coarse_t),
                (7, coarse_weights),
                (8, out.offsets),
                (9, out.positions),
                (10, out.dirs),
                (11, out.t),
                (12, out.dt),
                (13, counters_in),
            ],
            groups_1d(capacity_rays, WG),
        );
    }
}

/// Host twin of the stratified kernel's jitter: `u` of sample `k` of ray `r` for `n_samples`
/// per ray (what `nerf_sampling::stratified`'s rng would draw).
pub fn stratified_u(seed: u32, n_samples: usize, r: usize, k: usize) -> f32 {
    crate::rng::rand_f32(seed, 0, (r * n_samples + k) as u32)
}

/// Host twin of the hierarchical kernel's `u` for sample `k` of ray `r`: jittered
/// `min((k + ξ)/n_fine, 1)` with `Some(seed)`, else `linspace(0, 1, n_fine)[k]`.
pub fn hierarchical_u(jitter: Option<u32>, n_fine: usize, r: usize, k: usize) -> f32 {
    match jitter {
        Some(seed) => ((k as f32 + crate::rng::rand_f32(seed, 1, (r * n_fine + k) as u32)) * (1.0 / n_fine as f32)).min(1.0),
        None if n_fine <= 1 => 0.0,
        None => (k as f64 / (n_fine - 1) as f64) as f32,
    }
}
