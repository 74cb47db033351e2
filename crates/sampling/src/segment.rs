//! Per-ray segments clipped to the scene box, for the samplers that take `[near, far]` as given
//! (stratified, hierarchical).

use rayon::prelude::*;

/// Writes `[near, far] ∩ box` for every ray (`origins`, `dirs` flat, `3·n` long; `out_near`,
/// `out_far` `n` long). A ray that misses the box, or whose clipped segment is empty, gets
/// `[near, near]`: its samples then have zero-length intervals (no colour, no opacity). The slab
/// test is the occupancy marcher's (a zero direction component keeps the ray when its origin is
/// between that slab's planes). NDC scenes need it: the NDC box `z' ∈ [−1, 1]` makes the clipped
/// segment of every ray exactly its NDC segment (near plane to infinite depth), whose length
/// differs from ray to ray. GPU twin: `segment` in `shaders/pdf.wgsl`.
#[allow(clippy::too_many_arguments)]
pub fn clip_segments(
    aabb_min: [f32; 3],
    aabb_max: [f32; 3],
    origins: &[f32],
    dirs: &[f32],
    near: f32,
    far: f32,
    out_near: &mut [f32],
    out_far: &mut [f32],
) {
    let n = out_near.len();
    assert!(origins.len() == 3 * n && dirs.len() == 3 * n && out_far.len() == n, "clip_segments: 3·n origins and dirs, n outputs");
    out_near
        .par_chunks_mut(4096)
        .zip(out_far.par_chunks_mut(4096))
        .enumerate()
        .for_each(|(c, (a, b))| {
            for k in 0..a.len() {
                let r = c * 4096 + k;
                let o = [origins[3 * r], origins[3 * r + 1], origins[3 * r + 2]];
                let d = [dirs[3 * r], dirs[3 * r + 1], dirs[3 * r + 2]];
                (a[k], b[k]) = segment(o, d, aabb_min, aabb_max, near, far);
            }
        });
}

/// One ray's `[near, far] ∩ box` (see [`clip_segments`]).
#[inline]
pub fn segment(o: [f32; 3], d: [f32; 3], lo: [f32; 3], hi: [f32; 3], near: f32, far: f32) -> (f32, f32) {
    let (t0, t1) = crate::occupancy::slab(o, d, lo, hi);
    let (a, b) = (near.max(t0), far.min(t1));
    if b > a {
        (a, b)
    } else {
        (near, near)
    }
}
