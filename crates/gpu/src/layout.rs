//! Host-side mirrors of every WGSL uniform and storage struct: `#[repr(C)]` + `bytemuck::Pod`, in
//! one place (grouped by the module that uses them; the public ones are re-exported there).

/// `Params` of `shaders/composite.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct CompositeParams {
    /// Number of rays (CSR offsets have `n_rays + 1` entries).
    pub n_rays: u32,
    /// Early-stop transmittance (0 disables).
    pub t_threshold: f32,
    /// 1 when a per-ray background is composited.
    pub has_background: u32,
    /// Padding to 16 bytes (uniform layout).
    pub _pad: u32,
}
/// Uniform of the distortion-loss kernel (`composite.wgsl`, `distortion_backward`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct DistortionParams {
    /// Distances to the normalised `s = scale·t`.
    pub scale: f32,
    /// λ: the loss is λ times the mean over the step's rays.
    pub lambda: f32,
    /// Padding to 16 bytes (uniform layout).
    pub _pad: [u32; 2],
}

/// Uniform of the depth-loss kernel (`composite.wgsl`, `depth_loss`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct DepthParams {
    /// λ: the loss is λ times the mean over the step's rays of |expected − measured depth|.
    pub lambda: f32,
    /// Padding to 16 bytes (uniform layout).
    pub _pad: [u32; 3],
}

/// Slot of the `counters` buffer holding the number of rays of the step.
pub const COUNTER_N_RAYS: usize = 0;
/// Slot of the `counters` buffer holding the number of packed samples of the step.
pub const COUNTER_N_SAMPLES: usize = 1;

// ---- composite.rs ----
/// `LossParams` of `shaders/train.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub struct LossParams {
    /// Launch capacity in rays.
    pub capacity_rays: u32,
    /// δ of the Huber loss (0: MSE).
    pub huber_delta: f32,
    /// Padding.
    pub _pad: [u32; 2],
}

// ---- composite.rs ----
/// `BatchParams` of `shaders/train.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub struct BatchParams {
    /// Target field samples per step.
    pub target_samples: u32,
    /// Fewest rays per step.
    pub min_rays: u32,
    /// Most rays per step (≤ the ray capacity of the step's buffers).
    pub max_rays: u32,
    /// Padding.
    pub _pad: u32,
}

// ---- encoding.rs ----
/// `Params` of `shaders/hash_grid.wgsl` (uniform; 1312 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct HashGridParams {
    /// Lower corner of the scene box (world units).
    pub aabb_min: [f32; 3],
    /// Number of levels L.
    pub n_levels: u32,
    /// `1 / (aabb_max − aabb_min)` per axis, computed in `f32` as `nerf-field-hash` does.
    pub inv_extent: [f32; 3],
    /// `o` of `p = x·s_l + o` ([`nerf_encoding::HashGridConfig::level_offset`]: 0 or ½).
    pub offset: f32,
    /// Per level: resolution, offset of the level in the parameters (floats), 1 when dense, T − 1.
    pub levels: [[u32; 4]; crate::encoding::MAX_HASH_LEVELS],
    /// Per level `l`: `s_l` of `p = x·s_l + o` at `[l / 4][l % 4]`
    /// ([`nerf_encoding::HashGridConfig::level_scales`]).
    pub scales: [[f32; 4]; crate::encoding::MAX_HASH_LEVELS / 4],
}

/// `Params` of `shaders/dense_grid.wgsl` (uniform; 48 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct DenseGridParams {
    /// Lower corner of the scene box (world units).
    pub aabb_min: [f32; 3],
    /// Cells per axis `R`.
    pub res: u32,
    /// `1 / (aabb_max − aabb_min)` per axis (the field's own, as it normalises on the CPU).
    pub inv_extent: [f32; 3],
    /// Values per vertex `C`.
    pub channels: u32,
    /// Floats per row of the output (and of its gradient).
    pub stride: u32,
    /// Column of channel 0 in those rows.
    pub col: u32,
    /// Factor on the interpolated values and on their gradient.
    pub scale: f32,
    /// Vertices `(R+1)³` (one channel's length in the parameters).
    pub n_vertices: u32,
}

// ---- glue.rs ----
/// `GlueParams` of `shaders/field_glue.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GlueParams {
    /// Density-network outputs per sample.
    pub dd: u32,
    /// Direction-encoding values per sample.
    pub dir_dim: u32,
    /// Launch capacity (samples).
    pub capacity: u32,
    /// First density output that feeds the colour network (0: all of them, 1: all but σ's).
    pub feat_start: u32,
    /// 0 = truncated exp, 1 = ReLU, 2 = scaled softplus.
    pub act: u32,
    /// Added to the density output before the truncated exp or the softplus (0 for ReLU).
    pub bias: f32,
    /// Factor on the softplus (1 for the others, which do not read it).
    pub scale: f32,
    /// Padding.
    pub _pad: u32,
}

// ---- linear.rs ----
/// Uniform `Params` of `shaders/linear.wgsl` and `shaders/linear_coop.wgsl` (field meanings there).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct LinearParams {
    /// Fan-out of the layer.
    pub n_out: u32,
    /// Fan-in of the layer (including the skip input).
    pub k_in: u32,
    /// Leading input columns read from the network input.
    pub ka: u32,
    /// Activation code of the layer ([`act_code`](crate::linear::act_code)).
    pub act: u32,
    /// Row stride of the network input.
    pub a_stride: u32,
    /// Row stride of the hidden source.
    pub b_stride: u32,
    /// Column offset of the hidden source.
    pub b_off: u32,
    /// Row stride of the destination.
    pub dst_stride: u32,
    /// Column offset of the destination.
    pub dst_off: u32,
    /// Row stride of the second output / of `d_output`.
    pub out_stride: u32,
    /// Bit flags: 1 write work, 2 write out, 4 bias, 8 accumulate d_input.
    pub flags: u32,
    /// Offset of `W` in the parameter buffer.
    pub w_off: u32,
    /// Offset of `b` in the parameter buffer.
    pub bias_off: u32,
    /// Rows per split of the weight-gradient product.
    pub chunk: u32,
    /// First column computed by `backward_data`.
    pub c_lo: u32,
    /// Activation code of the previous layer.
    pub prev_act: u32,
}

// ---- mlp.rs ----
/// `MlpParams` of `shaders/mlp_fused.wgsl` (uniform, static per instance and mode).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct MlpParams {
    /// Number of linear layers (`hidden_layers + 1`).
    pub n_layers: u32,
    /// Floats per input sample.
    pub input_dim: u32,
    /// Floats per output sample.
    pub output_dim: u32,
    /// Tape floats per sample.
    pub fps: u32,
    /// Bit 0: the forward stores the tape; bit 1: the backward writes `d_input`; bit 2: the forward
    /// stores the activations as rows (`[n][fps / 2]`, for `mlp_tape_gather`).
    pub mode: u32,
    /// Outputs the forward computes and writes (≤ `output_dim`; the rest are left as they were).
    pub out_rows: u32,
    /// Columns of `d_input` the backward computes and writes (≤ `input_dim`; likewise).
    pub dx_cols: u32,
    /// Parameters of the net (the row length of `mlp_wgrad`'s sums).
    pub n_params: u32,
}

// ---- mlp.rs ----
/// `MlpLayer` of `shaders/mlp_fused.wgsl`: one linear layer (storage buffer, static).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct MlpLayerDesc {
    /// Fan-in.
    pub fan_in: u32,
    /// Fan-out.
    pub out: u32,
    /// Offset of `W` in the parameter buffer.
    pub w_off: u32,
    /// Offset of `b` (0 without bias).
    pub b_off: u32,
    /// Activation code (0 none, 1 relu, 2 sigmoid, 3 tanh, 4 softplus, 5 exp).
    pub act: u32,
    /// Tape floats per sample before this layer's activated output.
    pub a_pre: u32,
    /// Tape floats per sample before this layer's pre-activation gradient.
    pub d_pre: u32,
    /// 1 when the layer has a bias.
    pub has_bias: u32,
}

// ---- occupancy.rs ----
/// `OccParams` of `shaders/occupancy.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct OccParams {
    pub(crate) aabb_min: [f32; 3],
    pub(crate) res: u32,
    pub(crate) cell: [f32; 3],
    pub(crate) n_cells: u32,
    pub(crate) decay: f32,
    pub(crate) threshold: f32,
    pub(crate) n_words: u32,
    pub(crate) n_blocks: u32,
    pub(crate) n_partials: u32,
    pub(crate) seed: u32,
    pub(crate) warm: u32,
    pub(crate) step_size: f32,
    /// Cells per level (`res³`); the mean of the threshold is over the first (finest) level.
    pub(crate) level_cells: u32,
    /// The divisor of that mean: the finest level's cells a camera sees (`OccupancyGrid::mean_cells`).
    pub(crate) mean_cells: u32,
    pub(crate) _pad: [u32; 2],
    /// Per level of the cascade (finest first): the box's lower corner (w unused).
    pub(crate) lv_lo: [[f32; 4]; 8],
    /// Per level: the cell size (w unused).
    pub(crate) lv_cell: [[f32; 4]; 8],
}

// ---- optim.rs ----
/// `AdamParams` of `shaders/adam.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct AdamParams {
    pub(crate) total: u32,
    pub(crate) n_groups: u32,
    pub(crate) beta1: f32,
    pub(crate) beta2: f32,
    pub(crate) one_minus_beta1: f32,
    pub(crate) one_minus_beta2: f32,
    pub(crate) eps: f32,
    pub(crate) step_size: f32,
    pub(crate) inv_sqrt_bc2: f32,
    /// EMA weight of the previous average (`adam_step_ema`).
    pub(crate) ema_old: f32,
    /// EMA weight of the new parameter (`adam_step_ema`).
    pub(crate) ema_new: f32,
    /// The learning rate (sparse groups debias per entry on the device).
    pub(crate) lr: f32,
}

// ---- optim.rs ----
/// `Group` of `shaders/adam.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct GroupDesc {
    pub(crate) offset: u32,
    pub(crate) len: u32,
    pub(crate) start: u32,
    pub(crate) weight_decay: f32,
    pub(crate) lr_scale: f32,
    /// 1: sparse group (zero gradients skipped, per-entry step counts).
    pub(crate) sparse: u32,
    pub(crate) _pad: [u32; 2],
}

// ---- pdf.rs ----
/// `PdfParams` of `shaders/pdf.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct PdfParams {
    pub(crate) n_per_ray: u32,
    pub(crate) near: f32,
    pub(crate) far: f32,
    pub(crate) jitter: u32,
    pub(crate) seed: u32,
    /// 1: each ray's segment is `[near, far] ∩ box` (`nerf_sampling::clip_segments`).
    pub(crate) clip: u32,
    pub(crate) _pad: [u32; 2],
    /// Box corners (xyz, w unused).
    pub(crate) box_min: [f32; 4],
    pub(crate) box_max: [f32; 4],
    /// The render crop box ([`crop_rows`]).
    pub(crate) crop: [[f32; 4]; 4],
}

/// The render crop box as the shaders' `crop_x, crop_y, crop_z, crop_c` rows (`common.wgsl`'s
/// `crop_slab`): the box's axes with half its size in w, then its centre with w = 1; all zero
/// (w = 0: no crop) for `None`.
pub(crate) fn crop_rows(crop: Option<&nerf_sampling::CropBox>) -> [[f32; 4]; 4] {
    let Some(c) = crop else { return [[0.0; 4]; 4] };
    let row = |i: usize| [c.axes[i][0], c.axes[i][1], c.axes[i][2], c.half[i]];
    [row(0), row(1), row(2), [c.center[0], c.center[1], c.center[2], 1.0]]
}

/// `CompactParams` of `shaders/compact.wgsl` (16 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct CompactParams {
    pub(crate) cap_rays: u32,
    pub(crate) cap_out: u32,
    pub(crate) t_threshold: f32,
    pub(crate) _pad: u32,
}

/// `RowCopyParams` of `shaders/compact.wgsl` (`copy_rows`, 16 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct RowCopyParams {
    pub(crate) src_row: u32,
    pub(crate) dst_row: u32,
    pub(crate) _pad: [u32; 2],
}

// ---- color.rs ----
/// `ColorParams` of `shaders/color.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ColorParams {
    pub(crate) n_views: u32,
    pub(crate) capacity_rays: u32,
    pub(crate) _pad: [u32; 2],
}

// ---- views.rs ----
/// `ViewParams` of `shaders/views.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ViewParams {
    pub(crate) n_views: u32,
    pub(crate) capacity_rays: u32,
    pub(crate) _pad: [u32; 2],
}

// ---- pose.rs ----
/// `PoseParams` of `shaders/pose.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct PoseParams {
    pub(crate) n_views: u32,
    pub(crate) capacity_rays: u32,
    pub(crate) trans_penalty: f32,
    pub(crate) rot_penalty: f32,
}

// ---- sampling.rs ----
/// One view's camera as `shaders/rays.wgsl` reads it (128 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GpuCamera {
    /// Rows of the 3×4 camera-to-world matrix: `[R₀₀, R₀₁, R₀₂, px]`, …
    pub c2w: [[f32; 4]; 3],
    /// `[fx, fy, cx, cy]`.
    pub intrinsics: [f32; 4],
    /// `[width, height, first pixel of the view in the pixel buffer, lens]`, the lens one of
    /// [`GpuCamera::PINHOLE`], [`GpuCamera::RADIAL_TANGENTIAL`], [`GpuCamera::FISHEYE`],
    /// [`GpuCamera::FISHEYE624`], [`GpuCamera::FOV`], [`GpuCamera::DIVISION`], [`GpuCamera::EUCM`].
    pub size: [u32; 4],
    /// The lens's coefficients `[k1..k6, p1, p2, s1..s4]`
    /// (`nerf_rays::Distortion::coefficients`); for [`GpuCamera::FOV`], `[ω, 0, …]`; for
    /// [`GpuCamera::EUCM`], `[α, β, 0, …]`.
    pub lens: [f32; 12],
}

impl GpuCamera {
    /// `size[3]` of a camera without a lens.
    pub const PINHOLE: u32 = 0;
    /// `size[3]` of OpenCV's radial–tangential lens (`LensModel::RadialTangential`).
    pub const RADIAL_TANGENTIAL: u32 = 1;
    /// `size[3]` of OpenCV's fisheye lens (`LensModel::Fisheye`).
    pub const FISHEYE: u32 = 2;
    /// `size[3]` of Meta's Fisheye624 lens (`LensModel::Fisheye624`).
    pub const FISHEYE624: u32 = 3;
    /// `size[3]` of COLMAP's FOV lens (`LensModel::Fov`).
    pub const FOV: u32 = 4;
    /// `size[3]` of COLMAP's division lens (`LensModel::Division`; `k1` in `lens[0]`).
    pub const DIVISION: u32 = 5;
    /// `size[3]` of COLMAP's EUCM lens (`LensModel::Eucm`; `α`, `β` in `lens[0..2]`).
    pub const EUCM: u32 = 6;
}

// ---- sampling.rs ----
/// `ImagesInfo` of `shaders/rays.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ImagesInfo {
    pub(crate) n_views: u32,
    pub(crate) format: u32,
    /// 1: rays are warped to NDC (`nerf_rays::Ndc`) with the three fields below.
    pub(crate) ndc: u32,
    pub(crate) ndc_near: f32,
    pub(crate) ndc_scale_x: f32,
    pub(crate) ndc_scale_y: f32,
    /// Kept pixels of the training masks (0: no masks, every pixel is drawn).
    pub(crate) n_kept: u32,
    /// 1: the images have depth maps (`Dataset::depths`), one f32 per pixel.
    pub(crate) has_depth: u32,
}

// ---- sampling.rs ----
/// `RayGenParams` of `shaders/rays.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct RayGenParams {
    pub(crate) seed: u32,
    pub(crate) background: u32,
    pub(crate) jitter: u32,
    pub(crate) pixel_offset: f32,
}

// ---- sampling.rs ----
/// `ScanParams` of `shaders/scan.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ScanParams {
    pub(crate) n: u32,
    pub(crate) n_input: u32,
    pub(crate) dynamic_n: u32,
    pub(crate) has_sums: u32,
    pub(crate) slot: u32,
    pub(crate) _pad: [u32; 3],
}

// ---- sampling.rs ----
/// `MarchParams` of `shaders/march.wgsl` (96 + 16 + 4·128 + 64 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct MarchParams {
    pub(crate) aabb_min: [f32; 3],
    pub(crate) step: f32,
    pub(crate) aabb_max: [f32; 3],
    pub(crate) near: f32,
    pub(crate) cell: [f32; 3],
    pub(crate) far: f32,
    pub(crate) inv_cell: [f32; 3],
    pub(crate) margin: f32,
    pub(crate) res: u32,
    pub(crate) cres: u32,
    pub(crate) max_samples: u32,
    pub(crate) cap_rays: u32,
    pub(crate) cap_samples: u32,
    pub(crate) seed: u32,
    pub(crate) jitter: u32,
    pub(crate) cone_angle: f32,
    /// Levels of the cascade (1: one grid over the box).
    pub(crate) n_levels: u32,
    /// Cells per level (`res³`).
    pub(crate) level_cells: u32,
    pub(crate) _pad: [u32; 2],
    /// Per level (finest first, the last is the box): lower corner, w = the level's margin.
    pub(crate) lv_lo: [[f32; 4]; 8],
    /// Per level: upper corner (w unused).
    pub(crate) lv_hi: [[f32; 4]; 8],
    /// Per level: cell size (w unused).
    pub(crate) lv_cell: [[f32; 4]; 8],
    /// Per level: `res / (hi − lo)` (w unused).
    pub(crate) lv_inv: [[f32; 4]; 8],
    /// The render crop box ([`crop_rows`]; zero: none).
    pub(crate) crop: [[f32; 4]; 4],
}

/// `RoundParams` of `shaders/march.wgsl` (rendering in rounds, 32 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct RoundParams {
    pub(crate) n_frame: u32,
    pub(crate) cap_window: u32,
    pub(crate) kmax: u32,
    pub(crate) has_background: u32,
    pub(crate) t_threshold: f32,
    pub(crate) _pad: [u32; 3],
}

/// `RayState` of `shaders/march.wgsl` (per-ray state of rendering in rounds, 48 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct RoundRayState {
    pub(crate) k: u32,
    pub(crate) emitted: u32,
    pub(crate) done: u32,
    pub(crate) _pad: u32,
    pub(crate) acc: [f32; 4],
    pub(crate) od: [f32; 4],
}
