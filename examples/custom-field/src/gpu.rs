//! The Plenoxels field on a wgpu device, built outside nerf-rs from its public GPU parts and one
//! kernel file of its own: the density and coefficient grids are two
//! [`nerf::gpu::encoding::GpuDenseGrid`]s writing the columns of one row per sample
//! (`[s·d, s·k₀ … s·k_{3B−1}]`), the direction's spherical harmonics a
//! [`nerf::gpu::encoding::GpuSphericalHarmonics`], and `shaders/plenoxels.wgsl` (this crate's,
//! compiled with nerf-rs's `common.wgsl` by [`nerf::gpu::shaders::with_common`]) turns a row and
//! the SH values into σ and rgb, and back. Every kernel launches for the batch's device-side count
//! ([`DispatchArgs`]). Parameters start as the CPU field's, in two device buffers with the CPU
//! groups' names and layouts, so checkpoints are the same on both devices.

use crate::{Plenoxels, GROUP_NAMES, NAME};
use nerf::field::gpu::wgpu;
use nerf::field::{FieldError, GpuParamGroup, GpuRadianceField, GpuSamples};
use nerf::gpu::encoding::{AtomicMode, GpuDenseGrid, GpuSphericalHarmonics};
use nerf::gpu::{DispatchArgs, GpuContext, GpuError, Kernel, Launch};

/// The field's own kernels (σ and rgb from a row of grid values and the SH values, and back).
pub const SHADER: &str = include_str!("../shaders/plenoxels.wgsl");

/// Workgroup size of the kernels.
const WG: u32 = 128;

/// [`Plenoxels`] on the GPU.
pub struct GpuPlenoxels {
    groups: Vec<GpuParamGroup>,
    density_grid: GpuDenseGrid,
    sh_grid: GpuDenseGrid,
    sh: GpuSphericalHarmonics,
    density: Kernel,
    forward: Kernel,
    backward: Kernel,
    capacity: usize,
    args: DispatchArgs,
    /// Per sample: `s·d` (column 0) and the `3B` scaled coefficients.
    head: wgpu::Buffer,
    sh_values: wgpu::Buffer,
    d_head: wgpu::Buffer,
}

fn gpu_err(e: GpuError) -> FieldError {
    FieldError::Gpu { field: NAME.into(), source: e }
}

impl GpuPlenoxels {
    /// The GPU twin of `field` with buffers for `capacity` samples per launch.
    pub fn new(field: &Plenoxels<f32>, ctx: &GpuContext, capacity: usize) -> Result<Self, FieldError> {
        let capacity = capacity.max(1);
        let b = field.n_coef();
        let stride = 1 + 3 * b;
        let grid = |channels, col| {
            GpuDenseGrid::new(ctx, field.config.resolution, channels, field.aabb_min, field.inv_extent, field.scale, (stride, col), AtomicMode::Auto)
                .map_err(gpu_err)
        };
        let density_grid = grid(1, 0)?;
        let sh_grid = grid(3 * b, 1)?;
        let sh = GpuSphericalHarmonics::new(ctx, field.sh.config()).map_err(gpu_err)?;
        let module = ctx.shader_module("plenoxels", &nerf::gpu::shaders::with_common(SHADER));
        let constants = [("B", b as f64), ("WG", WG as f64), ("SHIFT", field.shift as f64), ("INV_VOXEL", field.inv_voxel as f64)];
        let kernel = |entry| Kernel::from_module(ctx, &module, entry, &constants);
        let values = [field.density_grid.params(), field.sh_grid.params()];
        let groups = GROUP_NAMES
            .iter()
            .zip(values)
            .map(|(name, v)| GpuParamGroup {
                name: name.to_string(),
                len: v.len(),
                weight_decay: 0.0,
                params: ctx.upload(name, v),
                grads: ctx.zeros(name, 4 * v.len()),
            })
            .collect();
        let [head, sh_values, d_head] = ctx
            .zeros_per_sample(capacity, [("plenoxels grids out", stride), ("plenoxels sh", b), ("d plenoxels grids out", stride)])
            .map_err(gpu_err)?;
        Ok(Self {
            groups,
            density_grid,
            sh_grid,
            sh,
            density: kernel("plen_density"),
            forward: kernel("plen_forward"),
            backward: kernel("plen_backward"),
            capacity,
            args: DispatchArgs::new(ctx, capacity),
            head,
            sh_values,
            d_head,
        })
    }

    /// The launch of the batch `s`: its dispatch arguments, recorded for its device-side count.
    fn launch<'a>(&'a self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: &GpuSamples<'_>) -> Launch<'a> {
        self.args.record(ctx, enc, s.counters, s.launch(self.capacity))
    }
}

impl GpuRadianceField for GpuPlenoxels {
    fn kind(&self) -> &'static str {
        NAME
    }

    fn capacity(&self) -> usize {
        self.capacity
    }

    fn groups(&self) -> &[GpuParamGroup] {
        &self.groups
    }

    fn record_density(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        self.density_grid.record_forward(ctx, enc, s.counters, s.positions, &self.groups[0].params, &self.head, l);
        l.record(&self.density, ctx, enc, &[(0, s.counters), (1, &self.head), (3, sigma)], 1, WG, 1);
    }

    fn record_query(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        self.record_forward(ctx, enc, s, sigma, rgb)
    }

    fn record_forward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        let g = &self.groups;
        self.density_grid.record_forward(ctx, enc, s.counters, s.positions, &g[0].params, &self.head, l);
        self.sh_grid.record_forward(ctx, enc, s.counters, s.positions, &g[1].params, &self.head, l);
        self.sh.record_forward(ctx, enc, s.counters, s.dirs, &self.sh_values, l);
        let b = [(0, s.counters), (1, &self.head), (2, &self.sh_values), (3, sigma), (4, rgb)];
        l.record(&self.forward, ctx, enc, &b, 1, WG, 1);
    }

    fn record_backward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, d_sigma: &wgpu::Buffer, d_rgb: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        let g = &self.groups;
        let b = [(0, s.counters), (1, &self.head), (2, &self.sh_values), (5, d_sigma), (6, d_rgb), (7, &self.d_head)];
        l.record(&self.backward, ctx, enc, &b, 1, WG, 1);
        self.density_grid.record_backward(ctx, enc, s.counters, s.positions, &self.d_head, &g[0].grads, l);
        self.sh_grid.record_backward(ctx, enc, s.counters, s.positions, &self.d_head, &g[1].grads, l);
    }
}
