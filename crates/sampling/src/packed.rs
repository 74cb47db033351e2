//! The packed (CSR) sample layout shared by samplers, fields and the compositor.

use nerf_core::par::{cut, for_ray_blocks, SplitAt};
use rayon::prelude::*;

/// All samples of a batch of rays, packed (nerfacc's layout).
///
/// Sample `k` belongs to ray `ray_indices[k]`; ray `r` owns the contiguous range
/// `ray_offsets[r]..ray_offsets[r+1]` (CSR, i.e. `(start, count)` per ray). Samples of a ray are
/// sorted by `t`. Per-sample vectors are structure-of-arrays, xyz interleaved (`[x0,y0,z0,x1,…]`).
///
/// **Interval convention** (the NeRF paper's): for a ray's sorted sample distances
/// `t_0 ≤ … ≤ t_{N-1}` in `[near, far]`, `δ_i = t_{i+1} − t_i` and the last interval is
/// `δ_{N-1} = far − t_{N-1}`. This is *finite*, unlike nerf-pytorch, which sets the last interval to
/// `1e10` (so that any positive last density makes the ray opaque); here the ray can stay partly
/// transparent and the background shows through. Ray directions are expected to be unit vectors,
/// so `t` and `δ` are metric distances.
#[derive(Clone, Debug, Default)]
pub struct RaySamples {
    /// Number of rays in the batch (`ray_offsets.len() == n_rays + 1`).
    pub n_rays: usize,
    /// `3·n` world-space sample positions `o + t·d`.
    pub positions: Vec<f32>,
    /// `3·n` unit view direction of the sample's ray.
    pub dirs: Vec<f32>,
    /// `n` distances along the (unit) ray, sorted within each ray.
    pub t: Vec<f32>,
    /// `n` interval lengths `δ` used by compositing (see the convention above).
    pub dt: Vec<f32>,
    /// `n` owning ray of each sample.
    pub ray_indices: Vec<u32>,
    /// `n_rays + 1` CSR offsets: ray `r` owns `ray_offsets[r]..ray_offsets[r+1]`.
    pub ray_offsets: Vec<u32>,
}

impl RaySamples {
    /// Total number of samples `n` over all rays.
    pub fn len(&self) -> usize {
        self.t.len()
    }

    /// `true` when the batch holds no samples (it may still hold rays, all empty).
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// Removes all rays and samples, keeping the allocations; leaves `ray_offsets == [0]`.
    pub fn clear(&mut self) {
        self.n_rays = 0;
        self.positions.clear();
        self.dirs.clear();
        self.t.clear();
        self.dt.clear();
        self.ray_indices.clear();
        self.ray_offsets.clear();
        self.ray_offsets.push(0);
    }

    /// The sample range owned by ray `r` (panics if `r >= n_rays`).
    pub fn ray_range(&self, r: usize) -> std::ops::Range<usize> {
        assert!(
            r < self.n_rays,
            "ray {r} out of range (n_rays = {})",
            self.n_rays
        );
        self.ray_offsets[r] as usize..self.ray_offsets[r + 1] as usize
    }

    /// Number of samples of ray `r`.
    pub fn ray_len(&self, r: usize) -> usize {
        self.ray_range(r).len()
    }

    /// Rebuilds `positions` (`o + t·d`) and `dirs` (copied from the ray) from the rays' `origins`
    /// and `dirs` (`3·n_rays` each), `t` and `ray_indices`, after `t`/`dt` were filled.
    pub fn fill_geometry(&mut self, origins: &[f32], dirs: &[f32]) {
        assert_eq!(
            origins.len(),
            3 * self.n_rays,
            "origins must hold 3·n_rays values"
        );
        assert_eq!(
            dirs.len(),
            3 * self.n_rays,
            "dirs must hold 3·n_rays values"
        );
        let n = self.len();
        assert_eq!(
            self.ray_indices.len(),
            n,
            "ray_indices must hold one entry per sample"
        );
        self.positions.clear();
        self.positions.resize(3 * n, 0.0);
        self.dirs.clear();
        self.dirs.resize(3 * n, 0.0);
        const CHUNK: usize = 4096;
        self.positions
            .par_chunks_mut(3 * CHUNK)
            .zip(self.dirs.par_chunks_mut(3 * CHUNK))
            .zip(
                self.t
                    .par_chunks(CHUNK)
                    .zip(self.ray_indices.par_chunks(CHUNK)),
            )
            .for_each(|((pos, dir), (t, ri))| {
                for k in 0..t.len() {
                    let r = ri[k] as usize;
                    let (o, d) = (&origins[3 * r..3 * r + 3], &dirs[3 * r..3 * r + 3]);
                    for c in 0..3 {
                        pos[3 * k + c] = o[c] + t[k] * d[c];
                        dir[3 * k + c] = d[c];
                    }
                }
            });
    }

    /// Backward of [`fill_geometry`](Self::fill_geometry) with `t` held fixed: given the field's
    /// input gradients `∂L/∂x` (`d_positions`) and `∂L/∂d` (`d_dirs`) of every sample (`3·n`
    /// each), *accumulates* (`+=`) each ray's `∂L/∂o = Σ_k ∂L/∂x_k` into `d_origins` and
    /// `∂L/∂d = Σ_k (t_k ∂L/∂x_k + ∂L/∂d_k)` into `d_ray_dirs` (`3·n_rays` each): what camera
    /// pose refinement (`nerf_rays::pose`) needs, summed over the stages of a step.
    pub fn backward_to_rays(&self, d_positions: &[f32], d_dirs: &[f32], d_origins: &mut [f32], d_ray_dirs: &mut [f32]) {
        let n = self.len();
        assert_eq!(d_positions.len(), 3 * n, "d_positions must hold 3·n values");
        assert_eq!(d_dirs.len(), 3 * n, "d_dirs must hold 3·n values");
        assert_eq!(d_origins.len(), 3 * self.n_rays, "d_origins must hold 3·n_rays values");
        assert_eq!(d_ray_dirs.len(), 3 * self.n_rays, "d_ray_dirs must hold 3·n_rays values");
        const RAYS: usize = 256;
        d_origins.par_chunks_mut(3 * RAYS).zip(d_ray_dirs.par_chunks_mut(3 * RAYS)).enumerate().for_each(|(c, (go, gd))| {
            for (i, (go, gd)) in go.chunks_exact_mut(3).zip(gd.chunks_exact_mut(3)).enumerate() {
                let r = c * RAYS + i;
                for k in self.ray_offsets[r] as usize..self.ray_offsets[r + 1] as usize {
                    let t = self.t[k];
                    for a in 0..3 {
                        let gx = d_positions[3 * k + a];
                        go[a] += gx;
                        gd[a] += t * gx + d_dirs[3 * k + a];
                    }
                }
            }
        });
    }

    /// Keeps the first `keep[r]` samples of each ray `r` (at most all of them) in `out`, in order:
    /// training on compacted samples, where `keep` counts the samples compositing reaches before
    /// early termination (`nerf_render::composited_counts` on an inference pass), so the
    /// compacted batch composites to the same colours. At most `capacity` samples are kept: the
    /// offsets are clipped there (`min(Σ_{j<r} keep_j, capacity)`), so the ray that crosses it
    /// keeps a prefix and the rays after it none — the GPU twin's rule
    /// (`nerf_gpu::compact`). `usize::MAX` keeps everything.
    pub fn compact_into(&self, keep: &[u32], capacity: usize, out: &mut RaySamples) {
        assert_eq!(keep.len(), self.n_rays, "keep must hold one count per ray");
        out.ray_offsets.clear();
        out.ray_offsets.push(0);
        let mut total = 0usize;
        for (r, &k) in keep.iter().enumerate() {
            total += (k as usize).min(self.ray_len(r));
            out.ray_offsets.push(total.min(capacity) as u32);
        }
        let n = total.min(capacity);
        out.resize_samples(self.n_rays, n);
        let src = self;
        for_each_ray(out, 4096, |r, range, s| {
            let from = src.ray_offsets[r] as usize;
            let len = range.len();
            let (a, b) = (range.start, range.end);
            s.positions[3 * a..3 * b].copy_from_slice(&src.positions[3 * from..3 * (from + len)]);
            s.dirs[3 * a..3 * b].copy_from_slice(&src.dirs[3 * from..3 * (from + len)]);
            s.t[a..b].copy_from_slice(&src.t[from..from + len]);
            s.dt[a..b].copy_from_slice(&src.dt[from..from + len]);
            s.ray_indices[a..b].fill(r as u32);
        });
    }

    /// Resizes every per-sample vector to `n` samples and sets `n_rays` (contents unspecified
    /// except `ray_offsets`, which the caller fills). Reuses the allocations.
    pub(crate) fn resize_samples(&mut self, n_rays: usize, n: usize) {
        self.n_rays = n_rays;
        for v in [&mut self.positions, &mut self.dirs] {
            v.clear();
            v.resize(3 * n, 0.0);
        }
        for v in [&mut self.t, &mut self.dt] {
            v.clear();
            v.resize(n, 0.0);
        }
        self.ray_indices.clear();
        self.ray_indices.resize(n, 0);
    }

    /// Mutable views of the per-sample arrays plus the (read-only) offsets, for the parallel writers.
    pub(crate) fn views(&mut self) -> (&[u32], SampleSlices<'_>) {
        (
            &self.ray_offsets,
            SampleSlices {
                positions: &mut self.positions,
                dirs: &mut self.dirs,
                t: &mut self.t,
                dt: &mut self.dt,
                ray_indices: &mut self.ray_indices,
            },
        )
    }
}

/// The per-sample output arrays of a block of rays (a contiguous sample range).
pub(crate) struct SampleSlices<'a> {
    pub positions: &'a mut [f32],
    pub dirs: &'a mut [f32],
    pub t: &'a mut [f32],
    pub dt: &'a mut [f32],
    pub ray_indices: &'a mut [u32],
}

impl SplitAt for SampleSlices<'_> {
    fn split_at(self, _rays: usize, s: usize) -> (Self, Self) {
        let (p0, p1) = cut(self.positions, s, 3);
        let (d0, d1) = cut(self.dirs, s, 3);
        let (t0, t1) = cut(self.t, s, 1);
        let (dt0, dt1) = cut(self.dt, s, 1);
        let (r0, r1) = cut(self.ray_indices, s, 1);
        (
            SampleSlices {
                positions: p0,
                dirs: d0,
                t: t0,
                dt: dt0,
                ray_indices: r0,
            },
            SampleSlices {
                positions: p1,
                dirs: d1,
                t: t1,
                dt: dt1,
                ray_indices: r1,
            },
        )
    }
}

/// Runs `f(ray, local_sample_range, slices_of_the_block)` for every ray, in parallel blocks.
/// `local_sample_range` indexes the block's slices.
pub(crate) fn for_each_ray<F>(samples: &mut RaySamples, grain: usize, f: F)
where
    F: Fn(usize, std::ops::Range<usize>, &mut SampleSlices<'_>) + Sync,
{
    let (offsets, views) = samples.views();
    for_ray_blocks(offsets, views, grain, &|lo, hi, mut s: SampleSlices<'_>| {
        let base = offsets[lo] as usize;
        for r in lo..hi {
            let range = offsets[r] as usize - base..offsets[r + 1] as usize - base;
            f(r, range, &mut s);
        }
    });
}

/// Writes `δ_i = t_{i+1} − t_i` and `δ_{N−1} = far − t_{N−1}` for one ray's sorted `t`
/// (clamped at 0, so a `far` below the last sample gives a zero-length last interval).
#[inline]
pub(crate) fn intervals(t: &[f32], far: f32, dt: &mut [f32]) {
    let n = t.len();
    for i in 0..n {
        let next = if i + 1 < n { t[i + 1] } else { far };
        dt[i] = (next - t[i]).max(0.0);
    }
}

/// Writes the geometry (`o + t·d`, `d`) and the ray index of one ray's samples.
#[inline]
pub(crate) fn ray_geometry(
    r: usize,
    o: &[f32],
    d: &[f32],
    t: &[f32],
    pos: &mut [f32],
    dir: &mut [f32],
    ri: &mut [u32],
) {
    for k in 0..t.len() {
        for c in 0..3 {
            pos[3 * k + c] = o[c] + t[k] * d[c];
            dir[3 * k + c] = d[c];
        }
        ri[k] = r as u32;
    }
}

/// Checks the per-ray inputs every sampler takes (`3·n` origins and directions, `n` near and far
/// distances) and returns the number of rays. Mismatched lengths are programmer errors: panics.
pub(crate) fn check_rays(origins: &[f32], dirs: &[f32], near: &[f32], far: &[f32]) -> usize {
    let n_rays = near.len();
    assert_eq!(far.len(), n_rays, "near and far must have one value per ray");
    assert_eq!(origins.len(), 3 * n_rays, "origins must hold 3·n_rays values");
    assert_eq!(dirs.len(), 3 * n_rays, "dirs must hold 3·n_rays values");
    n_rays
}


/// The row in the marched samples (offsets `marched`) of each sample of their compaction
/// (offsets `compacted`: a prefix of every ray, [`RaySamples::compact_into`]), into `rows`
/// (cleared first). A field that kept per-sample values of its pass over the marched samples
/// gathers them for the compacted ones with it (the GPU's twin: `compact_fill`'s `out_rows`).
pub fn compacted_rows(marched: &[u32], compacted: &[u32], rows: &mut Vec<u32>) {
    rows.clear();
    for (r, w) in compacted.windows(2).enumerate() {
        let from = marched[r];
        rows.extend(from..from + (w[1] - w[0]));
    }
}
