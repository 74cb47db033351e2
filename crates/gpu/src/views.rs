//! Per-view sums of per-ray values on the device (`shaders/views.wgsl`): how the gradients of the
//! parameters a trainer keeps per training view (colour correction, camera pose refinement) are
//! gathered from their rays' shares — one workgroup per view, a fixed reduction order, no atomics,
//! so the sums are the same bits on every run.

use crate::kernel::{groups_1d, Kernel};
use crate::layout::ViewParams;
use crate::{shaders, GpuContext};

/// Values per ray (and per view) the sums take.
pub const VALUES_PER_RAY: usize = 12;
const WG: u32 = 256;

/// The sums over `n_views` views for batches of up to `capacity_rays` rays.
pub struct ViewSums {
    kernel: Kernel,
    uniform: wgpu::Buffer,
    n_views: usize,
}

impl ViewSums {
    /// Compiles the kernel for `n_views` views and batches of up to `capacity_rays` rays.
    pub fn new(ctx: &GpuContext, n_views: usize, capacity_rays: usize) -> Self {
        let params = ViewParams { n_views: n_views as u32, capacity_rays: capacity_rays as u32, _pad: [0; 2] };
        Self {
            kernel: Kernel::new(ctx, &shaders::with_common(shaders::VIEWS), "view_sums", &[]),
            uniform: ctx.uniform("view sums params", &params),
            n_views,
        }
    }

    /// Records `sums[12·v + k] += Σ_{rays r of view v} ray_vals[12·r + k]` over the `counters[0]`
    /// rays of the batch (`views`: the view of each ray).
    pub fn record(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, counters: &wgpu::Buffer, views: &wgpu::Buffer, ray_vals: &wgpu::Buffer, sums: &wgpu::Buffer) {
        self.kernel.record(
            ctx,
            enc,
            &[(0, &self.uniform), (1, counters), (2, views), (3, ray_vals), (4, sums)],
            groups_1d(self.n_views * WG as usize, WG),
        );
    }
}
