//! The hash-grid field on a wgpu device: the same composition as the CPU [`HashNerf`] — hash
//! encoding ([`GpuHashGrid`]), density MLP (a fully fused [`FusedNet`]: plain WGSL or cooperative
//! matrices, [`crate::HashNerfConfig::gpu_mlp`]), spherical harmonics
//! ([`GpuSphericalHarmonics`]), colour MLP — joined by [`FieldGlue`]. Parameters start as the CPU
//! field's and live in three device buffers with the CPU groups' layouts.

use crate::{HashNerf, GROUP_NAMES};
use nerf_field::gpu::wgpu;
use nerf_field::{FieldError, GpuParamGroup, GpuRadianceField, GpuSamples};
use nerf_gpu::compact::{GpuRowCopy, GpuRowGather, RowOffsets};
use nerf_gpu::encoding::{AtomicMode, GpuHashGrid, GpuSphericalHarmonics};
use nerf_gpu::glue::{FieldGlue, SigmaActivation};
use nerf_gpu::mlp::{fused_nets, FusedMlpPath, FusedNet};
use nerf_gpu::{Bound, DispatchArgs, GpuContext, Launch};

/// [`HashNerf`] on the GPU.
pub struct GpuHashNerf {
    groups: Vec<GpuParamGroup>,
    grid: GpuHashGrid,
    sh: GpuSphericalHarmonics,
    density: Box<dyn FusedNet>,
    color: Box<dyn FusedNet>,
    glue: FieldGlue,
    capacity: usize,
    /// Launches of a batch's kernels for its device-side count (rewritten by each entry point).
    args: DispatchArgs,
    enc: wgpu::Buffer,
    dout: wgpu::Buffer,
    sh_out: wgpu::Buffer,
    color_in: wgpu::Buffer,
    density_tape: wgpu::Buffer,
    color_tape: wgpu::Buffer,
    d_color_in: wgpu::Buffer,
    d_dout: wgpu::Buffer,
    d_enc: wgpu::Buffer,
    /// What the density pass of a step on compacted samples keeps
    /// ([`GpuRadianceField::keep_density_pass`]), gathered for the kept samples by
    /// `record_forward_rows` instead of being computed again.
    kept: Option<KeptPass>,
    /// [`crate::HashNerfConfig::gpu_keep_density_activations`].
    keep_activations: bool,
    /// [`crate::HashNerfConfig::gpu_density_in_place`].
    density_in_place: bool,
    /// Density features the colour net reads (`dd − feat_start`) and outputs of the colour net.
    dims: (usize, usize),
    /// Whether the colour net's backward writes its input gradient for the SH inputs too
    /// ([`GpuRadianceField::enable_input_gradients`]).
    input_gradients: bool,
}

/// The density pass's encodings (`rows` rows of the encoding's width) and, with the plain density
/// net and [`crate::HashNerfConfig::gpu_keep_density_activations`], its activations
/// (`rows` rows of [`nerf_gpu::mlp::FusedMlp::activation_floats_per_sample`]).
struct KeptPass {
    enc: wgpu::Buffer,
    rows: usize,
    gather: GpuRowGather,
    activations: Option<wgpu::Buffer>,
    /// The copies of a later chunk's encodings and activations to their rows, for the chunk's
    /// samples only (a buffer copy would move its whole capacity), and the copy offsets of each
    /// chunk that starts at a multiple of the field's capacity (`nerf_field::ChunkedDensity`'s
    /// chunks); a chunk elsewhere falls back to buffer copies.
    copy_enc: GpuRowCopy,
    copy_activations: Option<GpuRowCopy>,
    chunk_offsets: Vec<(usize, RowOffsets)>,
    /// Whether the chunks are read and written in place
    /// ([`GpuRadianceField::density_pass_in_place`]): every chunk's byte offsets in the marched
    /// buffers (positions, σ, encodings, activations: multiples of `4 · capacity`) are multiples
    /// of the device's storage offset alignment, so the kernels bind those buffers at the chunk,
    /// and nothing is copied.
    in_place: bool,
}

impl KeptPass {
    /// Copies the first `launch`'s count of rows (`counters[1]`) of `src` to rows `first_row..` of
    /// `dst`, through `copy` where the chunk's offsets were made, else the chunk's whole capacity
    /// by a buffer copy.
    #[allow(clippy::too_many_arguments)]
    fn copy_chunk(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        copy: &GpuRowCopy,
        row_floats: usize,
        counters: &wgpu::Buffer,
        (src, dst): (&wgpu::Buffer, &wgpu::Buffer),
        first_row: usize,
        launch: Launch<'_>,
    ) {
        match self.chunk_offsets.iter().find(|(r, _)| *r == first_row) {
            Some((_, offsets)) => copy.record(ctx, enc, counters, offsets, src, dst, launch),
            None => {
                let row = 4 * row_floats as u64;
                enc.copy_buffer_to_buffer(src, 0, dst, row * first_row as u64, row * launch.capacity() as u64);
            }
        }
    }
}

/// Whether the table's backward sums over subgroups first (`gpu_hash_subgroup_sums`): as asked,
/// or, unset, on hardware adapters (where the atomics of a batch's neighbouring samples contend)
/// and not on software ones (where they do not, and the sums cost more than they save).
fn subgroup_sums(setting: Option<bool>, software_adapter: bool) -> bool {
    setting.unwrap_or(!software_adapter)
}

fn gpu_err(e: nerf_gpu::GpuError) -> FieldError {
    FieldError::Gpu { field: "hash".into(), source: e }
}

impl GpuHashNerf {
    /// The GPU twin of `field` with buffers for `capacity` samples per launch.
    pub fn new(field: &HashNerf<f32>, ctx: &GpuContext, capacity: usize) -> Result<Self, FieldError> {
        let cfg = &field.config;
        if let Some(s) = cfg.mlp_f16_scale {
            return Err(FieldError::InvalidConfig {
                field: "hash".into(),
                message: format!("mlp_f16_scale = {s} (the MLPs in emulated f16 arithmetic) is implemented on the CPU only: leave it out to train on the GPU"),
            });
        }
        let capacity = capacity.max(1);
        let aabb_min = field.aabb_min;
        let atomics = if subgroup_sums(cfg.gpu_hash_subgroup_sums, ctx.is_software()) { AtomicMode::SubgroupSums } else { AtomicMode::Auto };
        let grid = GpuHashGrid::with_atomics(ctx, &cfg.grid, aabb_min, field.aabb_max, atomics).map_err(gpu_err)?;
        let sh = GpuSphericalHarmonics::new(ctx, field.sh.config()).map_err(gpu_err)?;
        let path = match cfg.gpu_mlp {
            crate::GpuMlp::Plain => FusedMlpPath::Plain,
            crate::GpuMlp::Coop => FusedMlpPath::Coop,
        };
        let mlp_err = |e: nerf_gpu::GpuError| match path {
            FusedMlpPath::Coop => FieldError::InvalidConfig {
                field: "hash".into(),
                message: format!("gpu_mlp = \"coop\": {e} (gpu_mlp = \"plain\" runs on every adapter)"),
            },
            FusedMlpPath::Plain => gpu_err(e),
        };
        let mut nets = fused_nets(ctx, &[field.density.config.clone(), field.color.config.clone()], path).map_err(mlp_err)?;
        let mut color = nets.pop().expect("two nets");
        let mut density = nets.pop().expect("two nets");
        let (dd, fs, enc_dim, sh_dim) = (field.dout_dim(), field.feat_start(), field.enc_dim(), field.sh_dim());
        // The density pass reads σ (the density net's first output) alone, and the glue's backward
        // reads the colour net's input gradient for the density features (its first dd − fs
        // columns) alone, not for the SH encoding.
        density.set_partial(ctx, 1, enc_dim);
        color.set_partial(ctx, field.color.config.output_dim, dd - fs);
        let glue = FieldGlue::new(ctx, dd, sh_dim, fs, SigmaActivation::TruncExp { bias: cfg.density_bias }, capacity);
        let values = [field.grid.params(), field.density.params(), field.color.params()];
        let groups = GROUP_NAMES
            .iter()
            .zip(values)
            .zip(cfg.group_weight_decays())
            .map(|((name, v), weight_decay)| GpuParamGroup {
                name: name.to_string(),
                len: v.len(),
                weight_decay,
                params: ctx.upload(name, v),
                grads: ctx.zeros(name, 4 * v.len()),
            })
            .collect();
        let [enc, dout, sh_out, color_in, density_tape, color_tape, d_color_in, d_dout, d_enc] = ctx
            .zeros_per_sample(
                capacity,
                [
                    ("hash enc", enc_dim),
                    ("density out", dd),
                    ("sh", sh_dim),
                    ("color in", glue.color_in_dim),
                    ("density tape", density.tape_floats_per_sample()),
                    ("color tape", color.tape_floats_per_sample()),
                    ("d color in", glue.color_in_dim),
                    ("d density out", dd),
                    ("d enc", enc_dim),
                ],
            )
            .map_err(gpu_err)?;
        Ok(Self {
            groups,
            enc,
            dout,
            sh_out,
            color_in,
            density_tape,
            color_tape,
            d_color_in,
            d_dout,
            d_enc,
            kept: None,
            keep_activations: cfg.gpu_keep_density_activations,
            density_in_place: cfg.gpu_density_in_place,
            dims: (dd - fs, field.color.config.output_dim),
            input_gradients: false,
            args: DispatchArgs::new(ctx, capacity),
            glue,
            grid,
            sh,
            density,
            color,
            capacity,
        })
    }

    /// The launch of the batch `s`: its dispatch arguments, recorded for its device-side count.
    fn launch<'a>(&'a self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: &GpuSamples<'_>) -> Launch<'a> {
        ctx.profile_part("dispatch arguments");
        self.args.record(ctx, enc, s.counters, s.launch(self.capacity))
    }

    /// The density query with the encodings written to `encodings` (the field's own buffer, or
    /// the kept encodings of a density pass).
    fn record_density_via(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, encodings: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        ctx.profile_part("hash encoding");
        self.grid.record_forward(ctx, enc, s.counters, s.positions, &self.groups[0].params, encodings, l);
        ctx.profile_part("density MLP");
        self.density.record_inference_head(ctx, enc, s.counters, encodings.into(), &self.groups[1].params, &self.dout, l);
        ctx.profile_part("glue");
        self.glue.record_density(ctx, enc, s.counters, &self.dout, sigma, l);
    }

    /// The training forward from the encodings already in the field's buffer.
    #[allow(clippy::too_many_arguments)]
    fn record_forward_from_encodings(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        sigma: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
        l: Launch<'_>,
    ) {
        ctx.profile_part("density MLP");
        self.density.record_forward(ctx, enc, s.counters, &self.enc, &self.groups[1].params, &self.dout, &self.density_tape, l);
        self.record_forward_after_density(ctx, enc, s, sigma, rgb, l);
    }

    /// The training forward from the density net's output and tape already in the field's buffers.
    #[allow(clippy::too_many_arguments)]
    fn record_forward_after_density(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        sigma: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
        l: Launch<'_>,
    ) {
        ctx.profile_part("SH + glue");
        self.sh.record_forward(ctx, enc, s.counters, s.dirs, &self.sh_out, l);
        self.glue.record_assemble(ctx, enc, s.counters, &self.dout, &self.sh_out, sigma, &self.color_in, l);
        ctx.profile_part("colour MLP");
        self.color.record_forward(ctx, enc, s.counters, &self.color_in, &self.groups[2].params, rgb, &self.color_tape, l);
    }
}

impl GpuRadianceField for GpuHashNerf {
    fn kind(&self) -> &'static str {
        "hash"
    }

    fn capacity(&self) -> usize {
        self.capacity
    }

    fn groups(&self) -> &[GpuParamGroup] {
        &self.groups
    }

    fn record_density(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer) {
        self.record_density_via(ctx, enc, s, sigma, &self.enc);
    }

    fn keep_density_pass(&mut self, ctx: &GpuContext, marched: usize) -> Result<(), FieldError> {
        let width = self.grid.output_dim();
        let rows = marched.max(1);
        let enc = ctx.zeros_checked("kept hash enc", 4 * rows * width).map_err(gpu_err)?;
        // The activations only where they fit one binding (otherwise the density net runs again
        // for the kept samples: the same bits, more work).
        let activations = match (self.keep_activations, self.density.as_plain()) {
            (true, Some(net)) => ctx.zeros_checked("kept density activations", 4 * rows * net.activation_floats_per_sample()).ok(),
            _ => None,
        };
        let copy_activations = match (&activations, self.density.as_plain()) {
            (Some(_), Some(net)) => Some(GpuRowCopy::new(ctx, net.activation_floats_per_sample()).map_err(gpu_err)?),
            _ => None,
        };
        let chunk_offsets = (self.capacity..rows).step_by(self.capacity).map(|r| (r, GpuRowCopy::offsets(ctx, 0, r))).collect();
        // Every chunk's offset is a multiple of `4 · capacity` bytes (σ; positions, encodings and
        // activations are whole multiples of that), so one check covers them all.
        #[allow(clippy::manual_is_multiple_of)] // keeps the MSRV (1.85)
        let in_place = self.density_in_place && (4 * self.capacity as u64) % ctx.storage_offset_alignment() == 0;
        self.kept = Some(KeptPass {
            enc,
            rows,
            gather: GpuRowGather::new(ctx, width).map_err(gpu_err)?,
            activations,
            copy_enc: GpuRowCopy::new(ctx, width).map_err(gpu_err)?,
            copy_activations,
            chunk_offsets,
            in_place,
        });
        Ok(())
    }

    fn density_pass_in_place(&self) -> bool {
        self.kept.as_ref().is_some_and(|k| k.in_place)
    }

    fn record_density_for_training(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, first_row: usize) {
        let Some(k) = &self.kept else { return self.record_density(ctx, enc, s, sigma) };
        let cap = s.launch(self.capacity);
        assert!(first_row + cap <= k.rows, "a density pass over rows {first_row}..{} keeps {} rows", first_row + cap, k.rows);
        if k.in_place || first_row == 0 {
            // The chunk's rows of the marched buffers (the first chunk's are always its own; the
            // others' are bound at their offset where the field reads in place): the encodings
            // and activations land in their rows of the kept buffers, σ in its rows of the batch's.
            let l = self.launch(ctx, enc, &s);
            let width = self.grid.output_dim();
            let (positions, encodings) = (Bound::rows(s.positions, 3, first_row), Bound::rows(&k.enc, width, first_row));
            ctx.profile_part("hash encoding");
            self.grid.record_forward(ctx, enc, s.counters, positions, &self.groups[0].params, encodings, l);
            ctx.profile_part("density MLP");
            match (&k.activations, self.density.as_plain()) {
                (Some(acts), Some(net)) => {
                    let rows = Bound::rows(acts, net.activation_floats_per_sample(), first_row);
                    net.record_forward_rows(ctx, enc, s.counters, encodings, &self.groups[1].params, &self.dout, rows, l);
                }
                _ => self.density.record_inference_head(ctx, enc, s.counters, encodings, &self.groups[1].params, &self.dout, l),
            }
            ctx.profile_part("glue");
            self.glue.record_density(ctx, enc, s.counters, &self.dout, Bound::rows(sigma, 1, first_row), l);
            return;
        }
        // A later chunk in chunk buffers of its own: computed into the field's buffers, then its
        // encodings (and activations) copied to their rows.
        if let (Some(acts), Some(net)) = (&k.activations, self.density.as_plain()) {
            let l = self.launch(ctx, enc, &s);
            ctx.profile_part("hash encoding");
            self.grid.record_forward(ctx, enc, s.counters, s.positions, &self.groups[0].params, &self.enc, l);
            ctx.profile_part("density MLP");
            net.record_forward_rows(ctx, enc, s.counters, &self.enc, &self.groups[1].params, &self.dout, &self.density_tape, l);
            ctx.profile_part("glue");
            self.glue.record_density(ctx, enc, s.counters, &self.dout, sigma, l);
            k.copy_chunk(ctx, enc, &k.copy_enc, self.grid.output_dim(), s.counters, (&self.enc, &k.enc), first_row, l);
            let copy = k.copy_activations.as_ref().expect("a copy for the kept activations");
            k.copy_chunk(ctx, enc, copy, net.activation_floats_per_sample(), s.counters, (&self.density_tape, acts), first_row, l);
        } else {
            self.record_density(ctx, enc, s, sigma);
            let l = self.launch(ctx, enc, &s);
            k.copy_chunk(ctx, enc, &k.copy_enc, self.grid.output_dim(), s.counters, (&self.enc, &k.enc), first_row, l);
        }
    }

    fn record_forward_rows(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, rows: &wgpu::Buffer, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        let Some(k) = &self.kept else { return self.record_forward(ctx, enc, s, sigma, rgb) };
        let l = self.launch(ctx, enc, &s);
        ctx.profile_part("hash encoding (gather)");
        k.gather.record(ctx, enc, s.counters, rows, &k.enc, &self.enc, l);
        match (&k.activations, self.density.as_plain()) {
            (Some(acts), Some(net)) => {
                ctx.profile_part("density MLP (gather)");
                net.record_gather_tape(ctx, enc, s.counters, rows, acts, &self.dout, &self.density_tape, l);
                self.record_forward_after_density(ctx, enc, s, sigma, rgb, l);
            }
            _ => self.record_forward_from_encodings(ctx, enc, s, sigma, rgb, l),
        }
    }

    fn enable_input_gradients(&mut self, ctx: &GpuContext) -> Result<(), FieldError> {
        // The colour net's input gradient for the SH inputs too (the direction's gradient).
        let (nf, out) = self.dims;
        self.color.set_partial(ctx, out, self.glue.color_in_dim);
        debug_assert_eq!(self.glue.color_in_dim, nf + self.sh.output_dim());
        self.input_gradients = true;
        Ok(())
    }

    fn record_input_gradients(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, d_positions: &wgpu::Buffer, d_dirs: &wgpu::Buffer) {
        assert!(self.input_gradients, "record_input_gradients before enable_input_gradients");
        let l = self.launch(ctx, enc, &s);
        ctx.profile_part("hash encoding (input gradient)");
        self.grid.record_input_gradient(ctx, enc, s.counters, s.positions, &self.groups[0].params, &self.d_enc, d_positions, l);
        ctx.profile_part("SH (input gradient)");
        let (nf, _) = self.dims;
        self.sh.record_input_gradient(ctx, enc, s.counters, s.dirs, &self.d_color_in, self.glue.color_in_dim, nf, d_dirs, l);
    }

    fn record_query(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        ctx.profile_part("hash encoding");
        self.grid.record_forward(ctx, enc, s.counters, s.positions, &self.groups[0].params, &self.enc, l);
        ctx.profile_part("density MLP");
        self.density.record_inference(ctx, enc, s.counters, &self.enc, &self.groups[1].params, &self.dout, l);
        ctx.profile_part("SH + glue");
        self.sh.record_forward(ctx, enc, s.counters, s.dirs, &self.sh_out, l);
        self.glue.record_assemble(ctx, enc, s.counters, &self.dout, &self.sh_out, sigma, &self.color_in, l);
        ctx.profile_part("colour MLP");
        self.color.record_inference(ctx, enc, s.counters, &self.color_in, &self.groups[2].params, rgb, l);
    }

    fn record_forward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        ctx.profile_part("hash encoding");
        self.grid.record_forward(ctx, enc, s.counters, s.positions, &self.groups[0].params, &self.enc, l);
        self.record_forward_from_encodings(ctx, enc, s, sigma, rgb, l);
    }

    fn record_backward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, d_sigma: &wgpu::Buffer, d_rgb: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        let g = &self.groups;
        ctx.profile_part("colour MLP");
        self.color.record_backward(ctx, enc, s.counters, &self.color_in, &g[2].params, &self.color_tape, d_rgb, &g[2].grads, Some(&self.d_color_in), l);
        ctx.profile_part("glue");
        self.glue.record_backward(ctx, enc, s.counters, &self.dout, &self.d_color_in, d_sigma, &self.d_dout, l);
        ctx.profile_part("density MLP");
        self.density.record_backward(ctx, enc, s.counters, &self.enc, &g[1].params, &self.density_tape, &self.d_dout, &g[1].grads, Some(&self.d_enc), l);
        ctx.profile_part("hash encoding");
        self.grid.record_backward(ctx, enc, s.counters, s.positions, &self.d_enc, &g[0].grads, l);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subgroup_sums_are_on_by_default_on_hardware_adapters_only() {
        assert!(subgroup_sums(None, false));
        assert!(!subgroup_sums(None, true));
        for software in [false, true] {
            assert!(subgroup_sums(Some(true), software));
            assert!(!subgroup_sums(Some(false), software));
        }
    }
}
