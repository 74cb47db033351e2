//! Stratified sampling of `[near, far]` (the NeRF coarse pass).

use crate::packed::{for_each_ray, intervals, ray_geometry, RaySamples};
use rand::Rng as _;

/// Rays with at most this many samples + rays in total are processed on the calling thread.
pub(crate) const GRAIN: usize = 16 * 1024;

/// `N` stratified samples per ray in `[near, far]`.
///
/// Bin `i` is `[near + i·s, near + (i+1)·s]` with `s = (far − near)/N`, and
/// `t_i = near + (i + u_i)·s` with `u_i ~ U[0,1)` per sample when `rng` is `Some` (jitter), else
/// `u_i = 0.5` (bin centres). Intervals follow the [`RaySamples`] convention
/// (`δ_{N−1} = far − t_{N−1}`), so `Σ δ_i = far − t_0`.
///
/// `origins`/`dirs` hold `3·n_rays` values (unit directions), `near`/`far` one value per ray, so
/// AABB-clipped rays work too. A ray with `!(far ≥ near)` (inverted or NaN bounds) gets **no
/// samples**; an empty segment `far == near` (a miss of [`crate::clip_segments`]) gets `N`
/// samples of zero length, which composite to nothing (the GPU twin's fixed `N` per ray). With `rng`, one `u64` is drawn from it per call and ray `r` uses
/// `nerf_core::rng(seed, r)`, so the result does not depend on the number of threads.
/// `out`'s allocations are reused.
pub fn stratified(
    origins: &[f32],
    dirs: &[f32],
    near: &[f32],
    far: &[f32],
    n_samples: usize,
    rng: Option<&mut nerf_core::Rng>,
    out: &mut RaySamples,
) {
    let n_rays = crate::packed::check_rays(origins, dirs, near, far);
    let seed = rng.map(|r| r.gen::<u64>());

    out.ray_offsets.clear();
    out.ray_offsets.push(0);
    let mut total = 0usize;
    for r in 0..n_rays {
        if far[r] >= near[r] {
            total += n_samples;
        }
        assert!(
            total <= u32::MAX as usize,
            "too many samples for u32 offsets"
        );
        out.ray_offsets.push(total as u32);
    }
    out.resize_samples(n_rays, total);

    for_each_ray(out, GRAIN, |r, range, s| {
        if range.is_empty() {
            return;
        }
        let (a, b) = (near[r], far[r]);
        let step = (b - a) / n_samples as f32;
        let t = &mut s.t[range.clone()];
        match seed {
            Some(seed) => {
                let mut g = nerf_core::rng(seed, r as u64);
                for (i, ti) in t.iter_mut().enumerate() {
                    let u: f32 = g.gen();
                    // Clamp keeps f32 rounding from pushing a sample past the bin end.
                    *ti = (a + (i as f32 + u) * step).min(a + (i + 1) as f32 * step);
                }
            }
            None => {
                for (i, ti) in t.iter_mut().enumerate() {
                    *ti = a + (i as f32 + 0.5) * step;
                }
            }
        }
        intervals(t, b, &mut s.dt[range.clone()]);
        ray_geometry(
            r,
            &origins[3 * r..3 * r + 3],
            &dirs[3 * r..3 * r + 3],
            t,
            &mut s.positions[3 * range.start..3 * range.end],
            &mut s.dirs[3 * range.start..3 * range.end],
            &mut s.ray_indices[range],
        );
    });
}
