//! Inverse-CDF (importance) sampling: nerf-pytorch's `sample_pdf` and the hierarchical fine pass.

use crate::packed::{for_each_ray, intervals, ray_geometry, RaySamples};
use crate::stratified::GRAIN;
use nerf_core::Real;
use rand::Rng as _;

/// The core of `sample_pdf`, in place: `io` holds the `u` values on entry and the samples on exit.
///
/// `n_w` weights `weight(i)` over `n_w + 1` bin edges `bin(i)`. The cdf is built on the fly while
/// walking the (sorted) `u`, so nothing is allocated; an out-of-order `u` restarts the walk, so any
/// `u` gives the right answer (sorted `u` costs `O(n + n_w)`).
#[inline]
fn pdf_in_place<T: Real>(
    n_w: usize,
    bin: impl Fn(usize) -> T,
    weight: impl Fn(usize) -> T,
    io: &mut [T],
) {
    assert!(
        n_w >= 1,
        "sample_pdf needs at least one weight (two bin edges)"
    );
    let eps = T::c(1e-5);
    let mut total = T::zero();
    for i in 0..n_w {
        total += weight(i) + eps;
    }
    // Walk state: j = #{cdf entries <= u} (searchsorted right); c_cur = cdf[j] (if j <= n_w),
    // c_prev = cdf[j-1] (if j >= 1).
    let (mut j, mut c_prev, mut c_cur) = (0usize, T::zero(), T::zero());
    let mut u_last = T::neg_infinity();
    for x in io.iter_mut() {
        let u = *x;
        if u < u_last || u.is_nan() {
            (j, c_prev, c_cur) = (0, T::zero(), T::zero());
        }
        u_last = u;
        while j <= n_w && c_cur <= u {
            j += 1;
            c_prev = c_cur;
            if j <= n_w {
                c_cur = c_prev + (weight(j - 1) + eps) / total;
            }
        }
        let below = j.saturating_sub(1);
        let above = j.min(n_w);
        let cdf_below = if j == 0 { T::zero() } else { c_prev };
        let cdf_above = if j <= n_w { c_cur } else { c_prev };
        let mut denom = cdf_above - cdf_below;
        if denom < eps {
            denom = T::one();
        }
        let frac = (u - cdf_below) / denom;
        let (b0, b1) = (bin(below), bin(above));
        *x = b0 + frac * (b1 - b0);
    }
}

/// `torch.linspace(0, 1, n)[k]` (includes both ends; `[0]` when `n == 1`).
#[inline]
fn linspace01<T: Real>(k: usize, n: usize) -> T {
    if n <= 1 {
        T::zero()
    } else {
        T::c(k as f64 / (n - 1) as f64)
    }
}

/// nerf-pytorch's `sample_pdf` for **one** ray (`run_nerf_helpers.sample_pdf`), bit-for-bit in
/// its conventions: `w += 1e-5`, `cdf = [0, cumsum(w/Σw)]`, `searchsorted(cdf, u, right=True)`,
/// `below = max(0, i−1)`, `above = min(len(cdf)−1, i)`, a cdf step `< 1e-5` is replaced by 1, and
/// `sample = bins[below] + (u − cdf[below])/denom · (bins[above] − bins[below])`.
///
/// `bins` has `weights.len() + 1` edges (`weights` must not be empty). `u` is either empty, which
/// selects the deterministic branch `u = linspace(0, 1, out.len())` (both ends included), or holds
/// one value in `[0, 1]` per output sample (sorted `u` is fastest; any order is correct). Writes
/// `out.len()` samples in `u` order (not merged with the bins, not sorted). Allocation-free.
pub fn sample_pdf<T: Real>(bins: &[T], weights: &[T], u: &[T], out: &mut [T]) {
    assert_eq!(
        bins.len(),
        weights.len() + 1,
        "bins must have weights.len() + 1 edges"
    );
    let n = out.len();
    if u.is_empty() {
        for (k, x) in out.iter_mut().enumerate() {
            *x = linspace01(k, n);
        }
    } else {
        assert_eq!(
            u.len(),
            n,
            "u must be empty (deterministic) or have one value per output sample"
        );
        out.copy_from_slice(u);
    }
    pdf_in_place(weights.len(), |i| bins[i], |i| weights[i], out);
}

/// Sorts an almost-sorted slice (insertion sort: linear when already sorted; NaNs go last).
fn insertion_sort(v: &mut [f32]) {
    for i in 1..v.len() {
        let x = v[i];
        let mut j = i;
        while j > 0 && v[j - 1].total_cmp(&x).is_gt() {
            v[j] = v[j - 1];
            j -= 1;
        }
        v[j] = x;
    }
}

/// Hierarchical (coarse-to-fine) sampling over a packed coarse batch, as nerf-pytorch's
/// `render_rays` does it.
///
/// For each ray with `N ≥ 3` coarse samples: `bins` are the `N − 1` midpoints of its coarse `t`,
/// the weights are `coarse_weights[1..N−1]` (first and last dropped), and `n_fine` samples are drawn
/// with [`sample_pdf`]'s rules, using `u = linspace(0, 1, n_fine)` when `rng` is `None` and sorted
/// stratified-jittered `u_k = (k + ξ_k)/n_fine`, `ξ_k ~ U[0,1)`, when `rng` is `Some`. They are
/// merged with the coarse `t` (the output ray has `N + n_fine` sorted samples), `δ` is recomputed
/// with the [`RaySamples`] convention (last `δ = far[r] − t_last`), and positions/dirs are filled
/// from `origins`/`dirs` (`3·n_rays`). Rays with fewer than 3 coarse samples cannot form a pdf and
/// keep just their coarse samples.
///
/// `coarse_weights` (one per coarse sample) normally come from `nerf_render::composite_forward`.
/// With `rng`, one `u64` is drawn per call and ray `r` uses `nerf_core::rng(seed, r)`, so results
/// do not depend on the thread count. `out`'s allocations are reused; no per-ray allocation.
#[allow(clippy::too_many_arguments)]
pub fn hierarchical(
    coarse: &RaySamples,
    coarse_weights: &[f32],
    origins: &[f32],
    dirs: &[f32],
    far: &[f32],
    n_fine: usize,
    rng: Option<&mut nerf_core::Rng>,
    out: &mut RaySamples,
) {
    let n_rays = coarse.n_rays;
    assert_eq!(
        coarse.ray_offsets.len(),
        n_rays + 1,
        "coarse.ray_offsets must hold n_rays + 1 entries"
    );
    assert_eq!(
        coarse_weights.len(),
        coarse.len(),
        "one coarse weight per coarse sample"
    );
    assert_eq!(far.len(), n_rays, "far must have one value per ray");
    assert_eq!(
        origins.len(),
        3 * n_rays,
        "origins must hold 3·n_rays values"
    );
    assert_eq!(dirs.len(), 3 * n_rays, "dirs must hold 3·n_rays values");
    assert!(
        coarse.ray_offsets.windows(2).all(|w| w[0] <= w[1])
            && coarse.ray_offsets.last() == Some(&(coarse.len() as u32)),
        "coarse.ray_offsets must be non-decreasing and end at the sample count"
    );
    let seed = rng.map(|r| r.gen::<u64>());

    out.ray_offsets.clear();
    out.ray_offsets.push(0);
    let mut total = 0usize;
    for r in 0..n_rays {
        let n_c = coarse.ray_len(r);
        total += n_c + if n_c >= 3 { n_fine } else { 0 };
        assert!(
            total <= u32::MAX as usize,
            "too many samples for u32 offsets"
        );
        out.ray_offsets.push(total as u32);
    }
    out.resize_samples(n_rays, total);

    for_each_ray(out, GRAIN, |r, range, s| {
        let cr = coarse.ray_range(r);
        let ct = &coarse.t[cr.clone()];
        let cw = &coarse_weights[cr];
        let n_c = ct.len();
        let t_out = &mut s.t[range.clone()];
        if n_c >= 3 && n_fine > 0 {
            // The ray's dt slot (n_c + n_fine long) is scratch for the fine samples until δ is written.
            let fine = &mut s.dt[range.clone()][..n_fine];
            match seed {
                Some(seed) => {
                    let mut g = nerf_core::rng(seed, r as u64);
                    let inv = 1.0 / n_fine as f32;
                    for (k, x) in fine.iter_mut().enumerate() {
                        *x = ((k as f32 + g.gen::<f32>()) * inv).min(1.0);
                    }
                }
                None => {
                    for (k, x) in fine.iter_mut().enumerate() {
                        *x = linspace01(k, n_fine);
                    }
                }
            }
            pdf_in_place(n_c - 2, |i| 0.5 * (ct[i] + ct[i + 1]), |i| cw[i + 1], fine);
            // Monotone in u up to the `denom < 1e-5` guard; make it exactly sorted, then merge.
            insertion_sort(fine);
            let (mut a, mut b) = (0, 0);
            for x in t_out.iter_mut() {
                if b >= n_fine || (a < n_c && ct[a] <= fine[b]) {
                    *x = ct[a];
                    a += 1;
                } else {
                    *x = fine[b];
                    b += 1;
                }
            }
        } else {
            t_out.copy_from_slice(ct);
        }
        intervals(t_out, far[r], &mut s.dt[range.clone()]);
        ray_geometry(
            r,
            &origins[3 * r..3 * r + 3],
            &dirs[3 * r..3 * r + 3],
            t_out,
            &mut s.positions[3 * range.start..3 * range.end],
            &mut s.dirs[3 * range.start..3 * range.end],
            &mut s.ray_indices[range],
        );
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nan_u_does_not_poison_later_samples() {
        let bins = [0.0f64, 1.0, 3.0];
        let weights = [1.0, 1.0];
        let mut a = [0.0; 4];
        sample_pdf(&bins, &weights, &[0.25, f64::NAN, 0.5, 0.75], &mut a);
        let mut b = [0.0; 3];
        sample_pdf(&bins, &weights, &[0.25, 0.5, 0.75], &mut b);
        assert!(a[1].is_nan());
        assert_eq!([a[0], a[2], a[3]], b);
        // Half the (floored) mass in each bin: u = 0.5 maps to the shared edge, 0.75 to the middle of bin 1.
        assert!(
            (b[1] - 1.0).abs() < 1e-9 && (b[2] - 2.0).abs() < 1e-9 && (b[0] - 0.5).abs() < 1e-9
        );
    }

    #[test]
    fn insertion_sort_sorts() {
        let mut v = [3.0f32, 1.0, 2.0, 2.0, -1.0];
        insertion_sort(&mut v);
        assert_eq!(v, [-1.0, 1.0, 2.0, 2.0, 3.0]);
    }
}
