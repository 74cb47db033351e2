//! mip-NeRF 360's distortion loss (Barron et al. 2022, eq. 15; nerfacto's `distortion_loss`,
//! nerfacc's `distortion`): per ray, with weights `w_i` from compositing, sample distances
//! normalised to `s_i = scale·t_i` and interval lengths `ℓ_i = scale·δ_i`,
//!
//! ```text
//! L_ray = Σ_{i,j} w_i w_j |s_i − s_j| + ⅓ Σ_i w_i² ℓ_i
//! ```
//!
//! which pulls a ray's weight together into one short stretch (fewer floaters and no
//! semi-transparent haze). Computed in `O(n)` per ray with prefix sums:
//! `Σ_{i,j} w_i w_j |s_i − s_j| = 2 Σ_i w_i (s_i W_{<i} − S_{<i})` (`W_{<i} = Σ_{j<i} w_j`,
//! `S_{<i} = Σ_{j<i} w_j s_j`; samples sorted by `t`), and
//! `∂L/∂w_k = 2 (s_k (2 W_{<k} − W) − 2 S_{<k} + S) + ⅔ ℓ_k w_k`, taken into σ as compositing's
//! backward does (`∂L/∂σ_k = δ_k (g_k T_{k+1} − Σ_{i>k} g_i w_i)`, `T_{k+1} = 1 − Σ_{j≤k} w_j`).

use crate::CompositeOutputs;
use nerf_core::par::{cut, for_ray_blocks, SplitAt};
use nerf_core::Real;

struct Slices<'a, T> {
    d_sigma: &'a mut [T],
    ray_loss: &'a mut [T],
}

impl<T: Send> SplitAt for Slices<'_, T> {
    fn split_at(self, r: usize, s: usize) -> (Self, Self) {
        let (a0, a1) = cut(self.d_sigma, s, 1);
        let (b0, b1) = cut(self.ray_loss, r, 1);
        (Slices { d_sigma: a0, ray_loss: b0 }, Slices { d_sigma: a1, ray_loss: b1 })
    }
}

/// The distortion loss of every ray times `weight` into `ray_loss` (`n_rays`), its gradient
/// with respect to σ **added** to `d_sigma` (`n`), and their sum returned. `fwd` holds the
/// compositing forward of these samples (its weights, and its early stop, replayed as
/// [`composite_backward`](crate::composite_backward) does: samples past it get no gradient);
/// `scale` maps distances to the normalised `s = scale·t` (the trainer: 1 / (far − near) of the
/// scene). A mean over rays passes `weight = λ / n_rays`. Allocation-free; rays in parallel.
#[allow(clippy::too_many_arguments)]
pub fn distortion_loss_grad<T: Real>(
    ray_offsets: &[u32],
    sigma: &[T],
    dt: &[T],
    t: &[T],
    fwd: &CompositeOutputs<T>,
    scale: T,
    weight: T,
    d_sigma: &mut [T],
    ray_loss: &mut [T],
) -> T {
    let n_rays = ray_offsets.len().saturating_sub(1);
    let n = ray_offsets.last().map_or(0, |&o| o as usize);
    assert!(sigma.len() == n && dt.len() == n && t.len() == n && fwd.weights.len() == n, "one σ, δ, t and weight per sample");
    assert!(d_sigma.len() == n && ray_loss.len() == n_rays, "d_sigma: one per sample; ray_loss: one per ray");
    let t_threshold = fwd.t_threshold;
    let two = T::one() + T::one();
    let third = T::one() / (two + T::one());
    for_ray_blocks(ray_offsets, Slices { d_sigma: &mut *d_sigma, ray_loss: &mut *ray_loss }, 16 * 1024, &|lo, hi, o: Slices<'_, T>| {
        let base = ray_offsets[lo] as usize;
        for r in lo..hi {
            let (s0, s1) = (ray_offsets[r] as usize, ray_offsets[r + 1] as usize);
            // The samples compositing reached (its early stop), and the totals W, S over them.
            let (mut trans, mut m) = (T::one(), s0);
            let (mut w_all, mut s_all) = (T::zero(), T::zero());
            for k in s0..s1 {
                if trans < t_threshold {
                    break;
                }
                trans *= T::one() + (-sigma[k] * dt[k]).exp_m1();
                w_all += fwd.weights[k];
                s_all += fwd.weights[k] * scale * t[k];
                m = k + 1;
            }
            // Back to front: W_{>k}, S_{>k} and the suffix Σ_{i>k} g_i w_i.
            let (mut w_after, mut s_after, mut suffix, mut loss) = (T::zero(), T::zero(), T::zero(), T::zero());
            for k in (s0..m).rev() {
                let (w, s, len) = (fwd.weights[k], scale * t[k], scale * dt[k]);
                let w_before = w_all - w_after - w;
                let s_before = s_all - s_after - w * s;
                loss += two * w * (s * w_before - s_before) + third * len * w * w;
                let g = weight * (two * (s * (two * w_before - w_all) - two * s_before + s_all) + two * third * len * w);
                let t_next = T::one() - (w_before + w);
                o.d_sigma[k - base] += dt[k] * (g * t_next - suffix);
                suffix += g * w;
                w_after += w;
                s_after += w * s;
            }
            o.ray_loss[r - lo] = weight * loss;
        }
    });
    ray_loss.iter().fold(T::zero(), |a, &b| a + b)
}
