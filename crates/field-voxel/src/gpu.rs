//! The voxel field on a wgpu device: the same composition as the CPU [`VoxelNerf`] from the GPU
//! parts library, with no kernel of its own — the density and feature grids as two
//! [`GpuDenseGrid`]s writing the columns of one row per sample (`[s·d, s·k₀ … s·k_{F−1}]`),
//! [`FieldGlue`] for DVGO's σ (`softplus(s·d + shift) / voxel_size`,
//! [`SigmaActivation::Softplus`]) and the colour input `[s·k, γ(dir)]`
//! ([`GpuFrequencyEncoding`] of the direction), and the colour MLP as a fully fused [`FusedMlp`]
//! where its widths allow (≤ 64: `hidden = 64` and the default 12 features), else as a
//! layer-by-layer [`GpuMlp`] (plain WGSL GEMMs; the default `hidden = 128`). Parameters start as
//! the CPU field's and live in three device buffers with the CPU groups' names and layouts. The
//! per-sample kernels (grids, glue, fused MLP) launch for the batch's device-side count; the
//! direction encoding and the layer-by-layer GEMMs for the capacity.

use crate::{VoxelNerf, GROUP_NAMES};
use nerf_field::gpu::wgpu;
use nerf_field::{FieldError, GpuParamGroup, GpuRadianceField, GpuSamples};
use nerf_gpu::encoding::{AtomicMode, GpuDenseGrid, GpuFrequencyEncoding};
use nerf_gpu::glue::{FieldGlue, SigmaActivation};
use nerf_gpu::linear::{GpuMlp, LinearPath};
use nerf_gpu::mlp::FusedMlp;
use nerf_gpu::{DispatchArgs, GpuContext, Launch};

/// The colour network: fully fused where every width is ≤ 64, else layer by layer.
enum ColorNet {
    Fused(Box<FusedMlp>),
    Wide(Box<GpuMlp>),
}

impl ColorNet {
    /// The net for `config`, whose backward gives the input gradient of its first `features`
    /// columns only (the grids' features; the direction encoding's are never read).
    fn new(ctx: &GpuContext, config: &nerf_mlp::MlpConfig, capacity: usize, features: usize) -> Result<Self, nerf_gpu::GpuError> {
        match FusedMlp::new(ctx, config) {
            Ok(mut f) => {
                f.set_partial(ctx, config.output_dim, features);
                Ok(Self::Fused(Box::new(f)))
            }
            // Too wide for the fused kernels (or too little workgroup memory): the GEMMs.
            Err(_) => GpuMlp::new_with(ctx, config, capacity, LinearPath::Plain).map(|w| Self::Wide(Box::new(w))),
        }
    }

    fn tape_floats_per_sample(&self) -> usize {
        match self {
            Self::Fused(f) => f.tape_floats_per_sample(),
            Self::Wide(w) => w.tape_floats_per_sample(),
        }
    }
}

/// [`VoxelNerf`] on the GPU.
pub struct GpuVoxelNerf {
    groups: Vec<GpuParamGroup>,
    density_grid: GpuDenseGrid,
    feature_grid: GpuDenseGrid,
    dir_enc: GpuFrequencyEncoding,
    color: ColorNet,
    glue: FieldGlue,
    capacity: usize,
    /// Launches of a batch's per-sample kernels for its device-side count.
    args: DispatchArgs,
    /// Per sample: `s·d` (column 0) and the `F` scaled features.
    head: wgpu::Buffer,
    dir: wgpu::Buffer,
    color_in: wgpu::Buffer,
    color_tape: wgpu::Buffer,
    d_color_in: wgpu::Buffer,
    d_head: wgpu::Buffer,
}

fn gpu_err(e: nerf_gpu::GpuError) -> FieldError {
    FieldError::Gpu { field: "voxel".into(), source: e }
}

impl GpuVoxelNerf {
    /// The GPU twin of `field` with buffers for `capacity` samples per launch.
    pub fn new(field: &VoxelNerf<f32>, ctx: &GpuContext, capacity: usize) -> Result<Self, FieldError> {
        let capacity = capacity.max(1);
        let c = &field.config;
        let f = c.features;
        let head_dim = 1 + f;
        let grid = |channels, col| {
            GpuDenseGrid::new(ctx, c.resolution, channels, field.aabb_min, field.inv_extent, field.scale, (head_dim, col), AtomicMode::Auto)
                .map_err(gpu_err)
        };
        let density_grid = grid(1, 0)?;
        let feature_grid = grid(f, 1)?;
        let dir_enc = GpuFrequencyEncoding::new(ctx, 3, field.dir_enc.config()).map_err(gpu_err)?;
        let color = ColorNet::new(ctx, &field.color.config, capacity, f).map_err(gpu_err)?;
        let act = SigmaActivation::Softplus { shift: field.shift, scale: field.inv_voxel };
        let glue = FieldGlue::new(ctx, head_dim, dir_enc.output_dim(), 1, act, capacity);
        let values = [field.density_grid.params(), field.feature_grid.params(), field.color.params()];
        let decays = [0.0, 0.0, c.mlp_weight_decay];
        let groups = GROUP_NAMES
            .iter()
            .zip(values)
            .zip(decays)
            .map(|((name, v), weight_decay)| GpuParamGroup {
                name: name.to_string(),
                len: v.len(),
                weight_decay,
                params: ctx.upload(name, v),
                grads: ctx.zeros(name, 4 * v.len()),
            })
            .collect();
        let [head, dir, color_in, color_tape, d_color_in, d_head] = ctx
            .zeros_per_sample(
                capacity,
                [
                    ("voxel grids out", head_dim),
                    ("dir enc", dir_enc.output_dim()),
                    ("color in", glue.color_in_dim),
                    ("color tape", color.tape_floats_per_sample()),
                    ("d color in", glue.color_in_dim),
                    ("d voxel grids out", head_dim),
                ],
            )
            .map_err(gpu_err)?;
        Ok(Self {
            groups,
            density_grid,
            feature_grid,
            dir_enc,
            color,
            glue,
            capacity,
            args: DispatchArgs::new(ctx, capacity),
            head,
            dir,
            color_in,
            color_tape,
            d_color_in,
            d_head,
        })
    }

    /// Whether the colour network is the fully fused one (else the layer-by-layer GEMMs).
    pub fn fused_color_net(&self) -> bool {
        matches!(self.color, ColorNet::Fused(_))
    }

    /// The launch of the batch `s`: its dispatch arguments, recorded for its device-side count.
    fn launch<'a>(&'a self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: &GpuSamples<'_>) -> Launch<'a> {
        ctx.profile_part("dispatch arguments");
        self.args.record(ctx, enc, s.counters, s.launch(self.capacity))
    }

    /// Both grids into `head`, σ into `sigma` and the colour input.
    fn record_inputs(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: &GpuSamples<'_>, sigma: &wgpu::Buffer, l: Launch<'_>) {
        let g = &self.groups;
        ctx.profile_part("dense grids");
        self.density_grid.record_forward(ctx, enc, s.counters, s.positions, &g[0].params, &self.head, l);
        self.feature_grid.record_forward(ctx, enc, s.counters, s.positions, &g[1].params, &self.head, l);
        ctx.profile_part("frequency encoding + glue");
        self.dir_enc.record_forward(ctx, enc, s.counters, s.dirs, &self.dir, l.capacity());
        self.glue.record_assemble(ctx, enc, s.counters, &self.head, &self.dir, sigma, &self.color_in, l);
    }
}

impl GpuRadianceField for GpuVoxelNerf {
    fn kind(&self) -> &'static str {
        "voxel"
    }

    fn capacity(&self) -> usize {
        self.capacity
    }

    fn groups(&self) -> &[GpuParamGroup] {
        &self.groups
    }

    fn record_density(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        ctx.profile_part("dense grids");
        self.density_grid.record_forward(ctx, enc, s.counters, s.positions, &self.groups[0].params, &self.head, l);
        ctx.profile_part("glue");
        self.glue.record_density(ctx, enc, s.counters, &self.head, sigma, l);
    }

    fn record_query(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        self.record_inputs(ctx, enc, &s, sigma, l);
        ctx.profile_part("colour MLP");
        let p = &self.groups[2].params;
        match &self.color {
            ColorNet::Fused(f) => f.record_inference(ctx, enc, s.counters, &self.color_in, p, rgb, l),
            ColorNet::Wide(w) => w.record_inference(ctx, enc, s.counters, &self.color_in, p, rgb, l.capacity()),
        }
    }

    fn record_forward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer, rgb: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        self.record_inputs(ctx, enc, &s, sigma, l);
        ctx.profile_part("colour MLP");
        let p = &self.groups[2].params;
        match &self.color {
            ColorNet::Fused(f) => f.record_forward(ctx, enc, s.counters, &self.color_in, p, rgb, &self.color_tape, l),
            ColorNet::Wide(w) => w.record_forward(ctx, enc, s.counters, &self.color_in, p, rgb, &self.color_tape, l.capacity()),
        }
    }

    fn record_backward(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, d_sigma: &wgpu::Buffer, d_rgb: &wgpu::Buffer) {
        let l = self.launch(ctx, enc, &s);
        let g = &self.groups;
        ctx.profile_part("colour MLP");
        let (ci, tape, dci) = (&self.color_in, &self.color_tape, Some(&self.d_color_in));
        match &self.color {
            ColorNet::Fused(f) => f.record_backward(ctx, enc, s.counters, ci, &g[2].params, tape, d_rgb, &g[2].grads, dci, l),
            ColorNet::Wide(w) => w.record_backward(ctx, enc, s.counters, ci, &g[2].params, tape, d_rgb, &g[2].grads, dci, l.capacity()),
        }
        ctx.profile_part("glue");
        // d_head = [dσ·σ'(s·d), ∂L/∂(s·k)]; each grid's backward multiplies its columns by s.
        self.glue.record_backward(ctx, enc, s.counters, &self.head, &self.d_color_in, d_sigma, &self.d_head, l);
        ctx.profile_part("dense grids");
        self.density_grid.record_backward(ctx, enc, s.counters, s.positions, &self.d_head, &g[0].grads, l);
        self.feature_grid.record_backward(ctx, enc, s.counters, s.positions, &self.d_head, &g[1].grads, l);
    }
}
