//! The GPU side of the field seam: a field that can run on a wgpu device offers a
//! [`GpuRadianceField`] twin of itself through [`RadianceField::to_gpu`](crate::RadianceField::to_gpu).
//!
//! The twin starts from the CPU field's parameters (same initialisation, same seed) and keeps them
//! on the device as one buffer per parameter group, in exactly the layout of
//! [`RadianceField::export_params`](crate::RadianceField::export_params): checkpoints move between
//! devices unchanged. Its methods only *record* kernels into the caller's command encoder, so the
//! trainer can put a whole step (sampling, field, compositing, loss, backward, Adam) into one
//! submission with no host round trip. Batch sizes are only known on the device: the number of
//! samples is `counters[COUNTER_N_SAMPLES]`, and every kernel is launched for `capacity` samples.

pub use nerf_gpu::wgpu;
use nerf_gpu::GpuContext;

/// One parameter group on the device.
pub struct GpuParamGroup {
    /// Group name (as [`ParamGroupMut::name`](crate::ParamGroupMut)), keys optimiser state and checkpoints.
    pub name: String,
    /// Number of parameters.
    pub len: usize,
    /// L2 weight decay of the group.
    pub weight_decay: f32,
    /// The parameters (`len` f32).
    pub params: wgpu::Buffer,
    /// Their gradients (`len` f32), accumulated by `record_backward`, zeroed by the optimiser.
    pub grads: wgpu::Buffer,
}

/// Device buffers of a packed batch of samples as a field reads them.
#[derive(Clone, Copy)]
pub struct GpuSamples<'a> {
    /// `counters` (`[1]` = number of samples).
    pub counters: &'a wgpu::Buffer,
    /// Positions, `3·n` f32.
    pub positions: &'a wgpu::Buffer,
    /// Unit directions, `3·n` f32.
    pub dirs: &'a wgpu::Buffer,
    /// The most samples the buffers hold (the launch size).
    pub capacity: usize,
}

/// A radiance field on a wgpu device (the twin of a CPU [`RadianceField`](crate::RadianceField)).
/// Buffers are sized once, for the `capacity` given at creation.
pub trait GpuRadianceField: Send {
    /// The registry name of the field kind.
    fn kind(&self) -> &'static str;

    /// Most samples per launch.
    fn capacity(&self) -> usize;

    /// The parameter groups on the device, in `export_params` order.
    fn groups(&self) -> &[GpuParamGroup];

    /// Records the density query (σ ≥ 0 per sample) — occupancy-grid updates.
    fn record_density(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer);

    /// Records inference: σ and rgb per sample (rendering).
    fn record_query(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        sigma: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
    );

    /// Records the training forward (keeps what the backward needs in the field's own buffers).
    fn record_forward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        sigma: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
    );

    /// Records the backward of the last recorded forward: dL/dσ (`n`) and dL/drgb (`3·n`) in,
    /// parameter gradients *accumulated* into the groups' `grads`.
    fn record_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        d_sigma: &wgpu::Buffer,
        d_rgb: &wgpu::Buffer,
    );

    /// Reads the parameters back, as [`RadianceField::export_params`](crate::RadianceField::export_params).
    fn export_params(&self, ctx: &GpuContext) -> Result<Vec<(String, Vec<f32>)>, nerf_gpu::GpuError> {
        self.groups().iter().map(|g| Ok((g.name.clone(), ctx.read_f32(&g.params, g.len)?))).collect()
    }

    /// Uploads parameters written by `export_params` (either device's).
    fn import_params(&self, ctx: &GpuContext, groups: &[(String, Vec<f32>)]) -> Result<(), crate::FieldError> {
        let mine = self.groups();
        if mine.len() != groups.len() {
            return Err(crate::FieldError::ParamMismatch {
                group: "*".into(),
                message: format!("expected {} groups, got {}", mine.len(), groups.len()),
            });
        }
        for (g, (name, values)) in mine.iter().zip(groups) {
            if &g.name != name || g.len != values.len() {
                return Err(crate::FieldError::ParamMismatch {
                    group: name.clone(),
                    message: format!("expected `{}` with {} values, got `{}` with {}", g.name, g.len, name, values.len()),
                });
            }
            ctx.write(&g.params, 0, values);
        }
        Ok(())
    }
}
