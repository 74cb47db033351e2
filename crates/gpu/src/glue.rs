//! [`FieldGlue`]: the kernels of `shaders/field_glue.wgsl` that join a field's density network, its
//! σ activation and its colour network (used by the hash-grid, the paper's and the voxel field).

use crate::dispatch::Launch;
use crate::kernel::{Bound, Kernel};
use crate::{shaders, GpuContext};
pub use crate::layout::{GlueParams};

/// How σ is made from the density network's first output `x`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SigmaActivation {
    /// `σ = exp(min(x + bias, 80))`, gradient `exp(min(x + bias, 15))` (Instant-NGP's truncated
    /// exp; nerfacc's example shifts it by `bias = −1`).
    TruncExp {
        /// Added to `x` before the exponential.
        bias: f32,
    },
    /// `σ = max(x, 0)` (the paper).
    Relu,
    /// `σ = scale · softplus(x + shift)`, gradient `scale · sigmoid(x + shift)` (DVGO's density
    /// activation; the voxel field's `shift` starts it almost empty, its `scale` is
    /// `1 / voxel_size`).
    Softplus {
        /// Added to `x` before the softplus.
        shift: f32,
        /// Factor on the softplus.
        scale: f32,
    },
}

/// The glue kernels for one field shape.
pub struct FieldGlue {
    assemble: Kernel,
    density_only: Kernel,
    backward: Kernel,
    params: wgpu::Buffer,
    capacity: usize,
    /// Width of the colour network's input (`dd − feat_start + dir_dim`).
    pub color_in_dim: usize,
}

impl FieldGlue {
    /// Kernels for `dd` density outputs, `dir_dim` direction features, colour input from output
    /// `feat_start` on.
    pub fn new(ctx: &GpuContext, dd: usize, dir_dim: usize, feat_start: usize, act: SigmaActivation, capacity: usize) -> Self {
        assert!(feat_start < dd.max(1) || dd == 0);
        let module = ctx.shader_module("field_glue.wgsl", &shaders::with_common(shaders::FIELD_GLUE));
        let (act, bias, scale) = match act {
            SigmaActivation::TruncExp { bias } => (0, bias, 1.0),
            SigmaActivation::Relu => (1, 0.0, 1.0),
            SigmaActivation::Softplus { shift, scale } => (2, shift, scale),
        };
        let p = GlueParams {
            dd: dd as u32,
            dir_dim: dir_dim as u32,
            capacity: capacity as u32,
            feat_start: feat_start as u32,
            act,
            bias,
            scale,
            _pad: 0,
        };
        Self {
            assemble: Kernel::from_module(ctx, &module, "assemble", &[]),
            density_only: Kernel::from_module(ctx, &module, "density_only", &[]),
            backward: Kernel::from_module(ctx, &module, "backward_glue", &[]),
            params: ctx.uniform("glue", &p),
            capacity,
            color_in_dim: dd - feat_start + dir_dim,
        }
    }

    /// Panics when a batch holds more samples than the glue was made for.
    fn check(&self, launch: &Launch<'_>) {
        assert!(launch.capacity() <= self.capacity, "FieldGlue: a batch of {} samples for a glue made for {}", launch.capacity(), self.capacity);
    }

    /// σ and the colour input from the density outputs and the direction encoding.
    #[allow(clippy::too_many_arguments)]
    pub fn record_assemble(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        dout: &wgpu::Buffer,
        dir_enc: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
        color_in: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        self.check(&launch);
        let b = [(0, &self.params), (1, counters), (2, dout), (3, dir_enc), (4, sigma), (5, color_in)];
        launch.record(&self.assemble, ctx, enc, &b, 1, 64, 1);
    }

    /// σ only.
    pub fn record_density<'a>(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        dout: &wgpu::Buffer,
        sigma: impl Into<Bound<'a>>,
        launch: Launch<'_>,
    ) {
        self.check(&launch);
        let b = [(0, (&self.params).into()), (1, counters.into()), (2, dout.into()), (4, sigma.into())];
        launch.record(&self.density_only, ctx, enc, &b, 1, 64, 1);
    }

    /// dL/d(density outputs) from dL/dσ and dL/d(colour input); `dout` is the forward's.
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        dout: &wgpu::Buffer,
        d_color_in: &wgpu::Buffer,
        d_sigma: &wgpu::Buffer,
        d_dout: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        self.check(&launch);
        let b = [(0, &self.params), (1, counters), (2, dout), (6, d_color_in), (7, d_sigma), (8, d_dout)];
        launch.record(&self.backward, ctx, enc, &b, 1, 64, 1);
    }
}
