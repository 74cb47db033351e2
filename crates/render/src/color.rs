//! Per-view affine colour correction of composited pixels (Urban Radiance Fields' per-camera
//! affine exposure model; the role of nerfstudio's appearance embeddings and instant-ngp's
//! per-image exposure): photographs of one scene differ in exposure and white balance, which a
//! static field cannot explain and fits as view-dependent haze. Each training view `v` gets a
//! 3×3 matrix `A_v` and an offset `b_v` (12 values, row-major `A` then `b`), applied to what the
//! field composited *before* the background:
//!
//! ```text
//! fg  = rgb − (1 − α)·bg                 (= Σ w_i c_i, the field's part of the pixel)
//! out = A_v fg + α·b_v + (1 − α)·bg      (= Σ w_i (A_v c_i + b_v) + (1 − α)·bg)
//! ```
//!
//! so a transparent pixel keeps its background and the result is exactly a per-sample
//! correction `c ↦ A c + b` of the field's colours, done once per ray. Identity (`A = I`,
//! `b = 0`) leaves pixels unchanged. The backward pass, with `g = ∂L/∂out`:
//!
//! ```text
//! ∂L/∂rgb = A_vᵀ g      ∂L/∂α = g·(A_v bg + b_v − bg)      ∂L/∂A_v += g fgᵀ      ∂L/∂b_v += α g
//! ```
//!
//! Novel views have no correction of their own; renders use the mean of the training views'
//! ([`mean_color_correction`]), nerfstudio's "average appearance embedding". The GPU twin is
//! `shaders/color.wgsl`.

use nerf_core::Real;

/// Values per view: a row-major 3×3 matrix, then an offset.
pub const COLOR_PARAMS_PER_VIEW: usize = 12;

/// The identity correction of `n_views` views (`A = I`, `b = 0`).
pub fn identity_color_correction(n_views: usize) -> Vec<f32> {
    let one: [f32; COLOR_PARAMS_PER_VIEW] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0];
    one.repeat(n_views)
}

/// The mean of the views' corrections (all 12 values averaged): what novel views are rendered
/// with. Errors when `params` is empty or not whole views.
pub fn mean_color_correction(params: &[f32]) -> Result<[f32; COLOR_PARAMS_PER_VIEW], String> {
    if params.is_empty() || !params.len().is_multiple_of(COLOR_PARAMS_PER_VIEW) {
        return Err(format!("{} colour-correction values are not whole views of {COLOR_PARAMS_PER_VIEW}", params.len()));
    }
    let n = (params.len() / COLOR_PARAMS_PER_VIEW) as f64;
    let mut sum = [0f64; COLOR_PARAMS_PER_VIEW];
    for v in params.chunks_exact(COLOR_PARAMS_PER_VIEW) {
        for (s, &x) in sum.iter_mut().zip(v) {
            *s += x as f64;
        }
    }
    Ok(sum.map(|s| (s / n) as f32))
}

fn check<T>(n_rays: usize, views: Option<&[u32]>, params: &[T], rgb: &[T], opacity: &[T], background: &[T]) {
    assert!(params.len().is_multiple_of(COLOR_PARAMS_PER_VIEW) && !params.is_empty(), "params: {COLOR_PARAMS_PER_VIEW} values per view");
    assert!(rgb.len() == 3 * n_rays && background.len() == 3 * n_rays && opacity.len() == n_rays, "rgb/background: 3 per ray, opacity: 1");
    let n_views = params.len() / COLOR_PARAMS_PER_VIEW;
    if let Some(v) = views {
        assert_eq!(v.len(), n_rays, "one view index per ray");
        assert!(v.iter().all(|&i| (i as usize) < n_views), "a view index is past the {n_views} views' corrections");
    }
}

#[inline(always)]
fn view_params<'a, T: Real>(params: &'a [T], views: Option<&[u32]>, r: usize) -> &'a [T] {
    let v = views.map_or(0, |v| v[r] as usize);
    &params[COLOR_PARAMS_PER_VIEW * v..COLOR_PARAMS_PER_VIEW * (v + 1)]
}

/// Applies the correction of ray `r`'s view (`views[r]`; every ray the first view's when
/// `views` is `None`, e.g. a [`mean_color_correction`]) to the composited `rgb` (`3·n_rays`,
/// background included) with the rays' `opacity` and `background`, into `out` (`3·n_rays`).
///
/// # Panics
/// On mismatched lengths or a view index without a correction.
pub fn color_correct_forward<T: Real>(
    views: Option<&[u32]>,
    params: &[T],
    rgb: &[T],
    opacity: &[T],
    background: &[T],
    out: &mut [T],
) {
    let n_rays = opacity.len();
    check(n_rays, views, params, rgb, opacity, background);
    assert_eq!(out.len(), 3 * n_rays, "out: 3 values per ray");
    for r in 0..n_rays {
        let p = view_params(params, views, r);
        let a = opacity[r];
        let bg = &background[3 * r..3 * r + 3];
        let fg: [T; 3] = std::array::from_fn(|c| rgb[3 * r + c] - (T::one() - a) * bg[c]);
        for i in 0..3 {
            out[3 * r + i] = p[3 * i] * fg[0] + p[3 * i + 1] * fg[1] + p[3 * i + 2] * fg[2] + a * p[9 + i] + (T::one() - a) * bg[i];
        }
    }
}

/// The backward pass of [`color_correct_forward`] for `d_out = ∂L/∂out`: writes `d_rgb`
/// (`3·n_rays`) and `d_opacity` (`n_rays`) — what compositing's backward takes — and **adds**
/// each view's parameter gradient to `d_params` (same layout as `params`).
///
/// # Panics
/// On mismatched lengths or a view index without a correction.
#[allow(clippy::too_many_arguments)]
pub fn color_correct_backward<T: Real>(
    views: Option<&[u32]>,
    params: &[T],
    rgb: &[T],
    opacity: &[T],
    background: &[T],
    d_out: &[T],
    d_rgb: &mut [T],
    d_opacity: &mut [T],
    d_params: &mut [T],
) {
    let n_rays = opacity.len();
    check(n_rays, views, params, rgb, opacity, background);
    assert!(d_out.len() == 3 * n_rays && d_rgb.len() == 3 * n_rays && d_opacity.len() == n_rays, "d_out/d_rgb: 3 per ray, d_opacity: 1");
    assert_eq!(d_params.len(), params.len(), "d_params: the layout of params");
    for r in 0..n_rays {
        let v = views.map_or(0, |v| v[r] as usize);
        let p = view_params(params, views, r);
        let a = opacity[r];
        let bg = &background[3 * r..3 * r + 3];
        let g = &d_out[3 * r..3 * r + 3];
        let fg: [T; 3] = std::array::from_fn(|c| rgb[3 * r + c] - (T::one() - a) * bg[c]);
        let mut d_a = T::zero();
        for j in 0..3 {
            // (Aᵀ g)_j and g·(A bg)'s share of column j.
            let atg = p[j] * g[0] + p[3 + j] * g[1] + p[6 + j] * g[2];
            d_rgb[3 * r + j] = atg;
            d_a += atg * bg[j] + g[j] * (p[9 + j] - bg[j]);
        }
        d_opacity[r] = d_a;
        let dp = &mut d_params[COLOR_PARAMS_PER_VIEW * v..COLOR_PARAMS_PER_VIEW * (v + 1)];
        for i in 0..3 {
            for j in 0..3 {
                dp[3 * i + j] += g[i] * fg[j];
            }
            dp[9 + i] += a * g[i];
        }
    }
}
