//! Parallel traversal of a packed (CSR) batch: rays are split recursively into blocks of roughly
//! equal sample counts and handed to rayon, each block receiving the disjoint `&mut` sub-slices of
//! the outputs it owns. No allocation, no `unsafe`; results do not depend on the thread count.

/// Output slices that can be cut at a ray boundary (`rays` rays / `samples` samples into the block).
pub trait SplitAt: Sized + Send {
    /// Splits into the outputs of the first `rays` rays (`samples` samples) and the rest.
    fn split_at(self, rays: usize, samples: usize) -> (Self, Self);
}

/// Splits a mutable slice holding `per` values per item at item `at`.
#[inline]
pub fn cut<T>(s: &mut [T], at: usize, per: usize) -> (&mut [T], &mut [T]) {
    s.split_at_mut(at * per)
}

/// Calls `f(first_ray, end_ray, outputs_of_those_rays)` over blocks covering `0..n_rays`, in
/// parallel when the batch is larger than `grain` (samples + rays).
pub fn for_ray_blocks<S, F>(offsets: &[u32], out: S, grain: usize, f: &F)
where
    S: SplitAt,
    F: Fn(usize, usize, S) + Sync,
{
    let n_rays = offsets.len().saturating_sub(1);
    rec(offsets, 0, n_rays, out, grain.max(1), f);
}

fn rec<S, F>(offsets: &[u32], lo: usize, hi: usize, out: S, grain: usize, f: &F)
where
    S: SplitAt,
    F: Fn(usize, usize, S) + Sync,
{
    let (s_lo, s_hi) = (offsets[lo] as usize, offsets[hi] as usize);
    if hi - lo <= 1 || (s_hi - s_lo) + (hi - lo) <= grain {
        f(lo, hi, out);
        return;
    }
    // Split at the ray boundary closest to the sample midpoint, keeping both halves non-empty.
    let target = (s_lo + s_hi) / 2;
    let mid = (lo + 1 + offsets[lo + 1..hi].partition_point(|&o| (o as usize) < target))
        .clamp(lo + 1, hi - 1);
    let mid = if (s_hi - s_lo) == 0 {
        (lo + hi) / 2
    } else {
        mid
    };
    let (a, b) = out.split_at(mid - lo, offsets[mid] as usize - s_lo);
    rayon::join(
        || rec(offsets, lo, mid, a, grain, f),
        || rec(offsets, mid, hi, b, grain, f),
    );
}
