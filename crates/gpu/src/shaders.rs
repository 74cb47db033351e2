//! WGSL sources, one file per kernel family, compiled into the crate with `include_str!`. Every
//! family is compiled with `common.wgsl` (random numbers, launch index) prepended by
//! [`with_common`]; the tests validate each assembled module with naga.

macro_rules! wgsl {
    ($name:literal) => {
        include_str!(concat!("../../../shaders/", $name))
    };
}

/// Helpers shared by every family (PCG random numbers, 1-D launch index).
pub const COMMON: &str = wgsl!("common.wgsl");
/// Volume-rendering quadrature forward/backward and the photometric loss; CPU twins in `nerf-render`.
pub const COMPOSITE: &str = wgsl!("composite.wgsl");
/// Training rays from on-device images; CPU twin [`crate::sampling`].
pub const RAYS: &str = wgsl!("rays.wgsl");
/// Occupancy-grid marching and stratified sampling into the packed layout.
pub const MARCH: &str = wgsl!("march.wgsl");
/// Compaction of packed samples to those compositing reaches (training on compacted samples).
pub const COMPACT: &str = wgsl!("compact.wgsl");
/// Exclusive prefix sums (packed-layout offsets).
pub const SCAN: &str = wgsl!("scan.wgsl");
/// Occupancy-grid update (EMA of densities, threshold, bitfield).
pub const OCCUPANCY: &str = wgsl!("occupancy.wgsl");
/// Multiresolution hash encoding forward/backward.
pub const HASH_GRID: &str = wgsl!("hash_grid.wgsl");
/// Dense trilinear grid (DVGO's voxel grids) forward/backward; CPU twin `nerf_encoding::DenseGrid`.
pub const DENSE_GRID: &str = wgsl!("dense_grid.wgsl");
/// Spherical-harmonics direction encoding.
pub const SH: &str = wgsl!("sh.wgsl");
/// Frequency (positional) encoding.
pub const FREQUENCY: &str = wgsl!("frequency.wgsl");
/// Fully fused small MLPs (activations in workgroup memory), forward and backward.
pub const MLP_FUSED: &str = wgsl!("mlp_fused.wgsl");
/// Tiled linear layers for wide MLPs (plain WGSL).
pub const LINEAR: &str = wgsl!("linear.wgsl");
/// Tiled linear layers on cooperative matrices (f16 in, f32 accumulate).
pub const LINEAR_COOP: &str = wgsl!("linear_coop.wgsl");
/// Fully fused small MLPs on cooperative matrices (f16 in, f32 accumulate), forward and backward.
pub const MLP_FUSED_COOP: &str = wgsl!("mlp_fused_coop.wgsl");
/// Training-step glue: photometric loss and adaptive batch size.
pub const TRAIN: &str = wgsl!("train.wgsl");
/// Glue between a field's density network, σ activation and colour network (hash and paper fields).
pub const FIELD_GLUE: &str = wgsl!("field_glue.wgsl");
/// Adam update.
pub const ADAM: &str = wgsl!("adam.wgsl");
/// Inverse-transform (hierarchical) sampling.
pub const PDF: &str = wgsl!("pdf.wgsl");
/// Per-view affine colour correction of composited pixels; CPU twins in `nerf-render`.
pub const COLOR: &str = wgsl!("color.wgsl");
/// Camera pose refinement: ray correction, its backward, per-view gradients; CPU twins in `nerf-rays`.
pub const POSE: &str = wgsl!("pose.wgsl");
/// Per-view sums of per-ray values (the per-view parameters' gradients, [`crate::views`]).
pub const VIEWS: &str = wgsl!("views.wgsl");
/// Indirect-dispatch arguments from a device-side count ([`crate::dispatch`]).
pub const DISPATCH: &str = wgsl!("dispatch.wgsl");

/// Every kernel family with its file name (`common.wgsl` is part of each).
pub const ALL: &[(&str, &str)] = &[
    ("composite.wgsl", COMPOSITE),
    ("rays.wgsl", RAYS),
    ("march.wgsl", MARCH),
    ("scan.wgsl", SCAN),
    ("compact.wgsl", COMPACT),
    ("occupancy.wgsl", OCCUPANCY),
    ("hash_grid.wgsl", HASH_GRID),
    ("dense_grid.wgsl", DENSE_GRID),
    ("sh.wgsl", SH),
    ("frequency.wgsl", FREQUENCY),
    ("mlp_fused.wgsl", MLP_FUSED),
    ("linear.wgsl", LINEAR),
    ("linear_coop.wgsl", LINEAR_COOP),
    ("mlp_fused_coop.wgsl", MLP_FUSED_COOP),
    ("adam.wgsl", ADAM),
    ("train.wgsl", TRAIN),
    ("field_glue.wgsl", FIELD_GLUE),
    ("pdf.wgsl", PDF),
    ("dispatch.wgsl", DISPATCH),
    ("color.wgsl", COLOR),
    ("pose.wgsl", POSE),
    ("views.wgsl", VIEWS),
];

/// `source` with `common.wgsl` inserted after its leading `enable …;` directives (which WGSL
/// requires first).
pub fn with_common(source: &str) -> String {
    let mut head = String::new();
    let mut rest = String::new();
    let mut in_head = true;
    for line in source.lines() {
        let t = line.trim_start();
        if in_head && (t.starts_with("enable ") || t.starts_with("//") || t.is_empty()) {
            if t.starts_with("enable ") {
                head.push_str(line);
                head.push('\n');
            } else {
                rest.push_str(line);
                rest.push('\n');
            }
            continue;
        }
        in_head = false;
        rest.push_str(line);
        rest.push('\n');
    }
    format!("{head}{COMMON}\n{rest}")
}
