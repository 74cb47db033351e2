//! The paper's field on a wgpu device: the same composition as the CPU [`FreqNerf`] — frequency
//! encodings of position and direction ([`GpuFrequencyEncoding`]), the 8×256 trunk with its skip
//! and the view branch as tiled layer-by-layer networks ([`GpuMlp`], on cooperative matrices
//! where the adapter offers them), joined by [`FieldGlue`] (σ = ReLU of the first trunk output,
//! colour input = [feature, γ(d)]). Parameters start as the CPU field's, one buffer per group.

use crate::{FreqNerf, GpuLinear, GROUP_NAMES};
use nerf_field::gpu::wgpu;
use nerf_field::{FieldError, GpuParamGroup, GpuRadianceField, GpuSamples};
use nerf_gpu::encoding::GpuFrequencyEncoding;
use nerf_gpu::glue::{FieldGlue, SigmaActivation};
use nerf_gpu::linear::{GpuMlp, LinearPath};
use nerf_gpu::{GpuContext, Launch};

/// [`FreqNerf`] on the GPU.
pub struct GpuFreqNerf {
    groups: Vec<GpuParamGroup>,
    pos_enc: GpuFrequencyEncoding,
    dir_enc: GpuFrequencyEncoding,
    trunk: GpuMlp,
    color: GpuMlp,
    glue: FieldGlue,
    capacity: usize,
    pos: wgpu::Buffer,
    dir: wgpu::Buffer,
    head: wgpu::Buffer,
    color_in: wgpu::Buffer,
    trunk_tape: wgpu::Buffer,
    color_tape: wgpu::Buffer,
    d_color_in: wgpu::Buffer,
    d_head: wgpu::Buffer,
    /// ∂L/∂γ(x), the trunk's input gradient, once
    /// [`GpuRadianceField::enable_input_gradients`] asked for input gradients.
    d_pos: Option<wgpu::Buffer>,
    /// Width of the trunk's feature (the colour input's direction columns start there).
    width: usize,
}

/// Whether the GPU twin drops its networks' hidden f32 tape (`gpu_hidden_tape`): as asked, or,
/// unset, wherever the GEMMs are cooperative-matrix ones (their f16 copies give the ReLU masks).
fn drops_hidden_tape(setting: Option<bool>, path: LinearPath) -> bool {
    match setting {
        Some(keep) => !keep,
        None => path != LinearPath::Plain,
    }
}

fn gpu_err(e: nerf_gpu::GpuError) -> FieldError {
    FieldError::Gpu { field: "freq".into(), source: e }
}

impl GpuFreqNerf {
    /// The GPU twin of `field` with buffers for `capacity` samples per launch. The networks run on
    /// the kernels `gpu_linear` names; `auto` uses cooperative matrices (f16 in, f32 accumulate)
    /// when the adapter has them, unless `NERF_NO_COOP` is set: the workgroup-tiled kernels where
    /// subgroups are exactly 32 wide, else the subgroup-tiled ones.
    pub fn new(field: &FreqNerf<f32>, ctx: &GpuContext, capacity: usize) -> Result<Self, FieldError> {
        let capacity = capacity.max(1);
        let coop = ctx.features.cooperative_matrix && ctx.features.shader_f16;
        let pos_enc = GpuFrequencyEncoding::new(ctx, 3, field.pos_enc.config()).map_err(gpu_err)?;
        let dir_enc = GpuFrequencyEncoding::new(ctx, 3, field.dir_enc.config()).map_err(gpu_err)?;
        // Auto: the workgroup-tiled kernels where subgroups are exactly 32 wide (1.09× the
        // subgroup-tiled ones in the paper field's step on the H100, docs/results.md), else the
        // subgroup-tiled ones, else plain WGSL.
        let sg32 = ctx.info.subgroup_min_size == 32 && ctx.info.subgroup_max_size == 32;
        let path = match field.config.gpu_linear {
            GpuLinear::Auto if coop && sg32 => LinearPath::CoopTiled,
            GpuLinear::Auto if coop => LinearPath::Coop,
            GpuLinear::Auto | GpuLinear::Plain => LinearPath::Plain,
            GpuLinear::Coop => LinearPath::Coop,
            GpuLinear::CoopTiled => LinearPath::CoopTiled,
            GpuLinear::CoopTiledWide => LinearPath::CoopTiledWide,
        };
        let linear_err = |e: nerf_gpu::GpuError| FieldError::InvalidConfig {
            field: "freq".into(),
            message: format!(
                "gpu_linear = {}: {e} (gpu_linear = \"plain\" runs on every adapter)",
                serde_json::to_value(field.config.gpu_linear).unwrap_or_default()
            ),
        };
        let mut trunk = GpuMlp::new_with(ctx, &field.trunk.config, capacity, path).map_err(linear_err)?;
        let mut color = GpuMlp::new_with(ctx, &field.color.config, capacity, path).map_err(linear_err)?;
        if drops_hidden_tape(field.config.gpu_hidden_tape, path) {
            let tape_err = |e: nerf_gpu::GpuError| FieldError::InvalidConfig {
                field: "freq".into(),
                message: format!("gpu_hidden_tape = false: {e} (the GEMMs here: {:?})", path),
            };
            trunk.drop_hidden_tape(ctx).map_err(tape_err)?;
            color.drop_hidden_tape(ctx).map_err(tape_err)?;
        }
        let (pd, dd, w) = (field.pos_dim(), field.dir_dim(), field.config.width);
        let glue = FieldGlue::new(ctx, 1 + w, dd, 1, SigmaActivation::Relu, capacity);
        let wd = field.config.weight_decay;
        let groups = GROUP_NAMES
            .iter()
            .zip([field.trunk.params(), field.color.params()])
            .map(|(name, v)| GpuParamGroup {
                name: name.to_string(),
                len: v.len(),
                weight_decay: wd,
                params: ctx.upload(name, v),
                grads: ctx.zeros(name, 4 * v.len()),
            })
            .collect();
        let [pos, dir, head, color_in, trunk_tape, color_tape, d_color_in, d_head] = ctx
            .zeros_per_sample(
                capacity,
                [
                    ("pos enc", pd),
                    ("dir enc", dd),
                    ("trunk out", 1 + w),
                    ("color in", glue.color_in_dim),
                    ("trunk tape", trunk.tape_floats_per_sample()),
                    ("color tape", color.tape_floats_per_sample()),
                    ("d color in", glue.color_in_dim),
                    ("d trunk out", 1 + w),
                ],
            )
            .map_err(gpu_err)?;
        Ok(Self {
            groups,
            pos,
            dir,
            head,
            color_in,
            trunk_tape,
            color_tape,
            d_color_in,
            d_head,
            d_pos: None,
            width: w,
            glue,
            pos_enc,
            dir_enc,
            trunk,
            color,
            capacity,
        })
    }
}

impl GpuRadianceField for GpuFreqNerf {
    fn kind(&self) -> &'static str {
        "freq"
    }

    fn capacity(&self) -> usize {
        self.capacity
    }

    fn groups(&self) -> &[GpuParamGroup] {
        &self.groups
    }

    fn record_density(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer) {
        let cap = s.launch(self.capacity);
        ctx.profile_part("frequency encoding");
        self.pos_enc.record_forward(ctx, enc, s.counters, s.positions, &self.pos, cap);
        ctx.profile_part("trunk MLP");
        self.trunk.record_inference(ctx, enc, s.counters, &self.pos, &self.groups[0].params, &self.head, cap);
        ctx.profile_part("glue");
        self.glue.record_density(ctx, enc, s.counters, &self.head, sigma, Launch::direct(cap));
    }

    fn record_query(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        let cap = s.launch(self.capacity);
        ctx.profile_part("frequency encoding");
        self.pos_enc.record_forward(ctx, enc, s.counters, s.positions, &self.pos, cap);
        ctx.profile_part("trunk MLP");
        self.trunk.record_inference(ctx, enc, s.counters, &self.pos, &self.groups[0].params, &self.head, cap);
        ctx.profile_part("frequency encoding + glue");
        self.dir_enc.record_forward(ctx, enc, s.counters, s.dirs, &self.dir, cap);
        self.glue.record_assemble(ctx, enc, s.counters, &self.head, &self.dir, sigma, &self.color_in, Launch::direct(cap));
        ctx.profile_part("view MLP");
        self.color.record_inference(ctx, enc, s.counters, &self.color_in, &self.groups[1].params, rgb, cap);
    }

    fn record_forward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        let cap = s.launch(self.capacity);
        ctx.profile_part("frequency encoding");
        self.pos_enc.record_forward(ctx, enc, s.counters, s.positions, &self.pos, cap);
        ctx.profile_part("trunk MLP");
        self.trunk.record_forward(ctx, enc, s.counters, &self.pos, &self.groups[0].params, &self.head, &self.trunk_tape, cap);
        ctx.profile_part("frequency encoding + glue");
        self.dir_enc.record_forward(ctx, enc, s.counters, s.dirs, &self.dir, cap);
        self.glue.record_assemble(ctx, enc, s.counters, &self.head, &self.dir, sigma, &self.color_in, Launch::direct(cap));
        ctx.profile_part("view MLP");
        self.color.record_forward(ctx, enc, s.counters, &self.color_in, &self.groups[1].params, rgb, &self.color_tape, cap);
    }

    fn record_backward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, d_sigma: &wgpu::Buffer, d_rgb: &wgpu::Buffer) {
        let cap = s.launch(self.capacity);
        let g = &self.groups;
        ctx.profile_part("view MLP");
        self.color.record_backward(ctx, enc, s.counters, &self.color_in, &g[1].params, &self.color_tape, d_rgb, &g[1].grads, Some(&self.d_color_in), cap);
        ctx.profile_part("glue");
        self.glue.record_backward(ctx, enc, s.counters, &self.head, &self.d_color_in, d_sigma, &self.d_head, Launch::direct(cap));
        ctx.profile_part("trunk MLP");
        self.trunk.record_backward(ctx, enc, s.counters, &self.pos, &g[0].params, &self.trunk_tape, &self.d_head, &g[0].grads, self.d_pos.as_ref(), cap);
    }

    fn enable_input_gradients(&mut self, ctx: &GpuContext) -> Result<(), FieldError> {
        // The trunk's backward also writes its input gradient (the skip's columns included); the
        // view net's already covers the direction encoding's columns.
        let [d_pos] = ctx.zeros_per_sample(self.capacity, [("d pos enc", self.pos_enc.output_dim())]).map_err(gpu_err)?;
        self.d_pos = Some(d_pos);
        Ok(())
    }

    fn record_input_gradients(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, d_positions: &wgpu::Buffer, d_dirs: &wgpu::Buffer) {
        let d_pos = self.d_pos.as_ref().expect("record_input_gradients before enable_input_gradients");
        let cap = s.launch(self.capacity);
        ctx.profile_part("frequency encoding (input gradient)");
        let pd = self.pos_enc.output_dim();
        self.pos_enc.record_input_gradient(ctx, enc, s.counters, s.positions, d_pos, pd, 0, d_positions, cap);
        self.dir_enc.record_input_gradient(ctx, enc, s.counters, s.dirs, &self.d_color_in, self.glue.color_in_dim, self.width, d_dirs, cap);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_hidden_tape_is_dropped_by_default_on_cooperative_matrices_only() {
        for path in [LinearPath::Coop, LinearPath::CoopTiled, LinearPath::CoopTiledWide] {
            assert!(drops_hidden_tape(None, path), "{path:?}");
            assert!(!drops_hidden_tape(Some(true), path), "{path:?}");
            assert!(drops_hidden_tape(Some(false), path), "{path:?}");
        }
        // The plain GEMMs need the tape: kept unless asked otherwise (which `drop_hidden_tape`
        // then refuses with an error naming the setting).
        assert!(!drops_hidden_tape(None, LinearPath::Plain));
        assert!(!drops_hidden_tape(Some(true), LinearPath::Plain));
        assert!(drops_hidden_tape(Some(false), LinearPath::Plain));
    }
}
