//! Samplers that turn rays into packed samples for volume rendering.
//!
//! * [`RaySamples`] — the packed (CSR, nerfacc-style) layout shared by every sampler, field and the
//!   compositor: flat per-sample arrays (`positions`, `dirs`, `t`, `dt`, `ray_indices`) plus
//!   `ray_offsets` so that ray `r` owns samples `ray_offsets[r]..ray_offsets[r+1]`.
//! * [`stratified`] — jittered (or bin-centre) samples in `[near, far]` per ray (NeRF's coarse pass).
//! * [`clip_segments`] — per-ray `[near, far] ∩ box` for those two (NDC scenes, where segments
//!   differ from ray to ray).
//! * [`CropBox`] — a render crop box (instant-ngp's `render_aabb`, nerfstudio's oriented crop):
//!   segments and marches clipped to it, so a render shows only what lies inside.
//! * [`sample_pdf`] — nerf-pytorch's inverse-CDF sampler for one ray, conventions included.
//! * [`hierarchical`] — the coarse-to-fine pass over a whole packed batch.
//! * [`OccupancyGrid`] and [`march`] — Instant-NGP's empty-space skipping: an EMA occupancy grid
//!   (one level or a cascade) fed by any density function, and ray marching (constant or cone
//!   steps) that emits samples only in occupied cells (with `dt` the step, see [`march`]).
//!
//! Interval convention: `δ_i = t_{i+1} − t_i`, and the last interval is `far − t_{N−1}` (finite;
//! nerf-pytorch uses `1e10`). All samplers reuse the output's allocations, allocate nothing per
//! ray, run in parallel over blocks of rays with rayon, and give results independent of the number
//! of threads (per-ray generators derived from one seed drawn per call).

mod crop;
mod occupancy;
mod packed;

mod pdf;
mod segment;
mod stratified;

pub use crop::{crop_segments, CropBox};
pub use occupancy::{
    cascade_box, march, OccupancyGrid, OccupancyGridConfig, RayMarch, Stepping, DENSITY_CHUNK, MAX_CASCADES, MAX_RESOLUTION,
    MAX_STEP_RATIO,
};
pub use packed::{compacted_rows, RaySamples};
pub use pdf::{hierarchical, sample_pdf};
pub use segment::{clip_segments, segment};
pub use stratified::stratified;
