//! Volume rendering for nerf-rs: the NeRF quadrature over packed samples (compositing), its
//! analytic backward pass, and the photometric loss.
//!
//! Samples are packed as in `nerf_sampling::RaySamples`: ray `r` owns samples
//! `ray_offsets[r]..ray_offsets[r+1]`, sorted by `t`. Per sample `i` of a ray, with density
//! `σ_i ≥ 0`, colour `c_i` (3 values), interval `δ_i` and distance `t_i`:
//!
//! ```text
//! α_i = 1 − exp(−σ_i δ_i)          T_i = Π_{j<i} (1 − α_j) = exp(−Σ_{j<i} σ_j δ_j)
//! w_i = T_i α_i
//! rgb = Σ w_i c_i + (1 − Σ w_i)·bg     opacity = Σ w_i     depth = Σ w_i t_i  (not normalised)
//! ```
//!
//! Optional early stop: when `T_i < t_threshold` the ray ends *before* sample `i`; the weights of
//! the skipped samples are 0 and the backward pass differentiates exactly that truncated sum.
//!
//! The kernels are generic over [`nerf_core::Real`] so that finite-difference gradient checks run
//! the same code in `f64`. They are allocation-free (outputs are caller-owned and reused), `O(n)`
//! per ray, and run in parallel over blocks of rays with rayon for large batches.
//!
//! [`depth_range`] and [`depth_to_gray`] turn the expected depth into a viewable image;
//! [`surface_points`] into a point cloud; [`surface_points_of`], [`gradient_stencil`],
//! [`normals_from_stencil`] and [`normals_to_rgb`] the density's gradient at each ray's surface
//! point into a normal map. [`distortion_loss_grad`] is mip-NeRF 360's
//! regulariser on the weights; [`color_correct_forward`] the per-view affine colour correction
//! of real captures (exposure, white balance). [`to_rgba`] takes a render apart from its
//! background (transparent renders).

mod alpha;
mod color;
mod depth;
mod distortion;
mod normals;
mod points;

pub use alpha::{over_background, to_rgba};
pub use color::{
    color_correct_backward, color_correct_forward, identity_color_correction, mean_color_correction, COLOR_PARAMS_PER_VIEW,
};
pub use depth::{depth_range, depth_to_gray, depth_to_turbo, focus_distance, turbo};
pub use distortion::distortion_loss_grad;
pub use normals::{gradient_stencil, normals_from_stencil, normals_to_rgb, surface_points_of, NormalSteps};
pub use points::{surface_points, SurfacePoint};
use nerf_core::Real;
use nerf_core::par::{cut, for_ray_blocks, SplitAt};
use rayon::prelude::*;

/// Rays whose samples + rays total at most this many are composited on the calling thread.
const GRAIN: usize = 16 * 1024;

/// Per-ray outputs of [`composite_forward`] plus the per-sample weights that
/// [`composite_backward`] needs. Reusable: the forward resizes the vectors, keeping allocations.
#[derive(Clone, Debug, Default)]
pub struct CompositeOutputs<T> {
    /// `3·n_rays` composited colour, background included.
    pub rgb: Vec<T>,
    /// `n_rays` accumulated opacity `Σ w_i`.
    pub opacity: Vec<T>,
    /// `n_rays` expected depth `Σ w_i t_i` (not divided by the opacity, like nerf-pytorch).
    pub depth: Vec<T>,
    /// `n` per-sample weights `w_i = T_i α_i` (0 for samples skipped by early stop).
    pub weights: Vec<T>,
    /// The early-stop threshold the forward used (0 = none); the backward replays it to find
    /// exactly the samples the forward composited.
    pub t_threshold: T,
}

impl<T: Real> CompositeOutputs<T> {
    /// Empty outputs (no allocation until the first forward).
    pub fn new() -> Self {
        Self::default()
    }
}

/// Per-ray and per-sample output slices of a block of rays.
struct FwdSlices<'a, T> {
    rgb: &'a mut [T],
    opacity: &'a mut [T],
    depth: &'a mut [T],
    weights: &'a mut [T],
}

impl<T: Send> SplitAt for FwdSlices<'_, T> {
    fn split_at(self, r: usize, s: usize) -> (Self, Self) {
        let (c0, c1) = cut(self.rgb, r, 3);
        let (o0, o1) = cut(self.opacity, r, 1);
        let (d0, d1) = cut(self.depth, r, 1);
        let (w0, w1) = cut(self.weights, s, 1);
        (
            FwdSlices {
                rgb: c0,
                opacity: o0,
                depth: d0,
                weights: w0,
            },
            FwdSlices {
                rgb: c1,
                opacity: o1,
                depth: d1,
                weights: w1,
            },
        )
    }
}

/// Per-sample gradient slices of a block of rays.
struct BwdSlices<'a, T> {
    d_sigma: &'a mut [T],
    d_rgb: &'a mut [T],
}

impl<T: Send> SplitAt for BwdSlices<'_, T> {
    fn split_at(self, _r: usize, s: usize) -> (Self, Self) {
        let (a0, a1) = cut(self.d_sigma, s, 1);
        let (b0, b1) = cut(self.d_rgb, s, 3);
        (
            BwdSlices {
                d_sigma: a0,
                d_rgb: b0,
            },
            BwdSlices {
                d_sigma: a1,
                d_rgb: b1,
            },
        )
    }
}

/// Checks the packed layout against the per-sample arrays (programmer errors panic).
fn check_layout<T>(
    ray_offsets: &[u32],
    sigma: &[T],
    rgb: &[T],
    dt: &[T],
    t: &[T],
    background: Option<&[T]>,
) -> (usize, usize) {
    assert!(
        !ray_offsets.is_empty(),
        "ray_offsets must hold n_rays + 1 entries"
    );
    let n_rays = ray_offsets.len() - 1;
    let n = sigma.len();
    assert!(
        ray_offsets[0] == 0
            && ray_offsets.windows(2).all(|w| w[0] <= w[1])
            && ray_offsets[n_rays] as usize == n,
        "ray_offsets must start at 0, be non-decreasing and end at the sample count"
    );
    assert_eq!(rgb.len(), 3 * n, "rgb must hold 3 values per sample");
    assert_eq!(dt.len(), n, "dt must hold one value per sample");
    assert_eq!(t.len(), n, "t must hold one value per sample");
    if let Some(bg) = background {
        assert_eq!(
            bg.len(),
            3 * n_rays,
            "background must hold 3 values per ray"
        );
    }
    (n_rays, n)
}

#[inline(always)]
fn bg_of<T: Real>(background: Option<&[T]>, r: usize) -> [T; 3] {
    match background {
        Some(b) => [b[3 * r], b[3 * r + 1], b[3 * r + 2]],
        None => [T::zero(); 3],
    }
}

/// One ray's compositing in progress: transmittance and the accumulated colour, opacity and
/// depth. [`composite_forward`] runs it over each ray's samples; renderers that evaluate a ray's
/// samples a few at a time (rendering in rounds) keep it between batches — same arithmetic, same
/// result.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayComposite<T> {
    /// Transmittance before the next sample.
    pub trans: T,
    /// Σ wᵢ cᵢ so far.
    pub rgb: [T; 3],
    /// Σ wᵢ so far.
    pub opacity: T,
    /// Σ wᵢ tᵢ so far.
    pub depth: T,
}

impl<T: Real> Default for RayComposite<T> {
    fn default() -> Self {
        Self { trans: T::one(), rgb: [T::zero(); 3], opacity: T::zero(), depth: T::zero() }
    }
}

impl<T: Real> RayComposite<T> {
    /// Whether compositing has stopped: transmittance below `t_threshold` (0 = never).
    #[inline]
    pub fn stopped(&self, t_threshold: T) -> bool {
        self.trans < t_threshold
    }

    /// Adds a sample (density, colour, interval length, distance) and returns its weight
    /// `w = T·(1 − exp(−σδ))`. Call only while not [`stopped`](Self::stopped).
    #[inline]
    pub fn add(&mut self, sigma: T, rgb: [T; 3], dt: T, t: T) -> T {
        let em = (-sigma * dt).exp_m1(); // exp(−σδ) − 1 = −α, accurate for small σδ
        let w = self.trans * -em;
        for (a, c) in self.rgb.iter_mut().zip(rgb) {
            *a += w * c;
        }
        self.opacity += w;
        self.depth += w * t;
        self.trans *= T::one() + em;
        w
    }

    /// The ray's colour over `background`: `Σ wᵢ cᵢ + (1 − Σ wᵢ)·bg`.
    #[inline]
    pub fn color(&self, background: [T; 3]) -> [T; 3] {
        std::array::from_fn(|c| self.rgb[c] + (T::one() - self.opacity) * background[c])
    }
}

/// Per ray, the number of its leading samples that [`composite_forward`] composites with the
/// same `t_threshold`: those reached before the transmittance falls below it (all of them when
/// the threshold is 0). The samples after them get zero weight and zero gradient, so training
/// on only these (instant-ngp's compacted batch, after an inference pass over every marched
/// sample) composites to the same colours and gradients. Uses [`RayComposite`]'s arithmetic, so
/// the count is exactly where `composite_forward` stops. `out` gets `n_rays` counts.
pub fn composited_counts<T: Real>(ray_offsets: &[u32], sigma: &[T], dt: &[T], t_threshold: T, out: &mut Vec<u32>) {
    let n_rays = ray_offsets.len().saturating_sub(1);
    let n = ray_offsets.last().copied().unwrap_or(0) as usize;
    assert!(sigma.len() >= n && dt.len() >= n, "sigma and dt must hold the {n} samples the offsets describe");
    out.clear();
    out.resize(n_rays, 0);
    out.par_iter_mut().with_min_len(256).enumerate().for_each(|(r, c)| {
        let (s0, s1) = (ray_offsets[r] as usize, ray_offsets[r + 1] as usize);
        let mut ray = RayComposite::default();
        let mut k = s0;
        while k < s1 && !ray.stopped(t_threshold) {
            ray.add(sigma[k], [T::zero(); 3], dt[k], T::zero());
            k += 1;
        }
        *c = (k - s0) as u32;
    });
}

/// Composites packed samples into per-ray colour, opacity and depth (see the crate docs).
///
/// * `ray_offsets`: `n_rays + 1` CSR offsets; `sigma`, `dt`, `t`: `n` values; `rgb`: `3·n`.
/// * `background`: `3·n_rays` colours blended with weight `1 − opacity`; `None` = black.
/// * `t_threshold`: early stop when the transmittance before a sample drops below it (`0` disables).
///
/// `out` is resized (allocations reused) and fully overwritten. A ray without samples gets
/// `rgb = background`, `opacity = depth = 0`.
#[allow(clippy::too_many_arguments)]
pub fn composite_forward<T: Real>(
    ray_offsets: &[u32],
    sigma: &[T],
    rgb: &[T],
    dt: &[T],
    t: &[T],
    background: Option<&[T]>,
    t_threshold: T,
    out: &mut CompositeOutputs<T>,
) {
    let (n_rays, n) = check_layout(ray_offsets, sigma, rgb, dt, t, background);
    out.t_threshold = t_threshold;
    for (v, len) in [
        (&mut out.rgb, 3 * n_rays),
        (&mut out.opacity, n_rays),
        (&mut out.depth, n_rays),
        (&mut out.weights, n),
    ] {
        v.clear();
        v.resize(len, T::zero());
    }
    let slices = FwdSlices {
        rgb: &mut out.rgb,
        opacity: &mut out.opacity,
        depth: &mut out.depth,
        weights: &mut out.weights,
    };
    for_ray_blocks(
        ray_offsets,
        slices,
        GRAIN,
        &|lo, hi, o: FwdSlices<'_, T>| {
            let base = ray_offsets[lo] as usize;
            for r in lo..hi {
                let (s0, s1) = (ray_offsets[r] as usize, ray_offsets[r + 1] as usize);
                let mut ray = RayComposite::default();
                for k in s0..s1 {
                    if ray.stopped(t_threshold) {
                        break; // the remaining weights stay 0 (the slice was zero-filled)
                    }
                    let c = [rgb[3 * k], rgb[3 * k + 1], rgb[3 * k + 2]];
                    o.weights[k - base] = ray.add(sigma[k], c, dt[k], t[k]);
                }
                let i = r - lo;
                o.rgb[3 * i..3 * i + 3].copy_from_slice(&ray.color(bg_of(background, r)));
                o.opacity[i] = ray.opacity;
                o.depth[i] = ray.depth;
            }
        },
    );
}

/// The analytic backward of [`composite_forward`] (same inputs, `fwd` its outputs).
///
/// Given `d_rgb = dL/d(rgb_ray)` (`3·n_rays`) and optionally `dL/d(opacity)` and `dL/d(depth)`
/// (`n_rays` each; `None` = zero), writes `d_sigma = dL/dσ` (`n`) and `d_sample_rgb = dL/dc`
/// (`3·n`) for every sample (0 for samples skipped by early stop, which is replayed from
/// `fwd.t_threshold`). With
/// `g_i = d_rgb·(c_i − bg) + d_opacity + d_depth·t_i = dL/dw_i`:
///
/// ```text
/// dL/dc_i = d_rgb · w_i
/// dL/dσ_k = δ_k · ( g_k T_{k+1} − Σ_{i>k} g_i w_i )
/// ```
///
/// computed in `O(n)` per ray with a suffix sum (no autodiff, no allocation: `d_sample_rgb`
/// doubles as scratch for `T_{k+1}`). The gradient w.r.t. the background colour, if needed, is
/// `d_rgb · (1 − opacity)` per ray.
#[allow(clippy::too_many_arguments)]
pub fn composite_backward<T: Real>(
    ray_offsets: &[u32],
    sigma: &[T],
    rgb: &[T],
    dt: &[T],
    t: &[T],
    background: Option<&[T]>,
    fwd: &CompositeOutputs<T>,
    d_rgb: &[T],
    d_opacity: Option<&[T]>,
    d_depth: Option<&[T]>,
    d_sigma: &mut [T],
    d_sample_rgb: &mut [T],
) {
    let (n_rays, n) = check_layout(ray_offsets, sigma, rgb, dt, t, background);
    assert_eq!(
        fwd.weights.len(),
        n,
        "fwd must be the forward outputs of this batch"
    );
    assert_eq!(d_rgb.len(), 3 * n_rays, "d_rgb must hold 3 values per ray");
    if let Some(d) = d_opacity {
        assert_eq!(d.len(), n_rays, "d_opacity must hold one value per ray");
    }
    if let Some(d) = d_depth {
        assert_eq!(d.len(), n_rays, "d_depth must hold one value per ray");
    }
    assert_eq!(d_sigma.len(), n, "d_sigma must hold one value per sample");
    assert_eq!(
        d_sample_rgb.len(),
        3 * n,
        "d_sample_rgb must hold 3 values per sample"
    );
    let t_threshold = fwd.t_threshold;
    let slices = BwdSlices {
        d_sigma,
        d_rgb: d_sample_rgb,
    };
    for_ray_blocks(
        ray_offsets,
        slices,
        GRAIN,
        &|lo, hi, o: BwdSlices<'_, T>| {
            let base = ray_offsets[lo] as usize;
            for r in lo..hi {
                let (s0, s1) = (ray_offsets[r] as usize, ray_offsets[r + 1] as usize);
                let bg = bg_of(background, r);
                let dc = [d_rgb[3 * r], d_rgb[3 * r + 1], d_rgb[3 * r + 2]];
                let d_op = d_opacity.map_or(T::zero(), |d| d[r]);
                let d_dep = d_depth.map_or(T::zero(), |d| d[r]);
                // Pass 1 (front to back): recompute T_{k+1} exactly as the forward did, find the stop.
                let mut trans = T::one();
                let mut m = s0;
                for k in s0..s1 {
                    if trans < t_threshold {
                        break;
                    }
                    trans *= T::one() + (-sigma[k] * dt[k]).exp_m1();
                    o.d_rgb[3 * (k - base)] = trans;
                    m = k + 1;
                }
                for k in m..s1 {
                    o.d_sigma[k - base] = T::zero();
                    o.d_rgb[3 * (k - base)..3 * (k - base) + 3].fill(T::zero());
                }
                // Pass 2 (back to front): suffix sum S = Σ_{i>k} g_i w_i.
                let mut suffix = T::zero();
                for k in (s0..m).rev() {
                    let j = k - base;
                    let w = fwd.weights[k];
                    let g = dc[0] * (rgb[3 * k] - bg[0])
                        + dc[1] * (rgb[3 * k + 1] - bg[1])
                        + dc[2] * (rgb[3 * k + 2] - bg[2])
                        + d_op
                        + d_dep * t[k];
                    let t_next = o.d_rgb[3 * j];
                    o.d_sigma[j] = dt[k] * (g * t_next - suffix);
                    suffix += g * w;
                    for (d, &g_c) in o.d_rgb[3 * j..3 * j + 3].iter_mut().zip(&dc) {
                        *d = g_c * w;
                    }
                }
            }
        },
    );
}

/// Depth supervision: the loss `λ · (1/n) · Σ_r |D̂_r − D_r|` over the `n` rays of a batch, where
/// `D̂_r = Σ w_i t_i` is ray `r`'s expected depth ([`CompositeOutputs::depth`]) and `D_r` its
/// measured distance along the ray (`target`, from a depth map; rays whose target is not
/// positive have no measurement and add nothing). Writes `d_depth = dL/dD̂` (`λ·sign(D̂ − D)/n`,
/// 0 without a measurement), which [`composite_backward`] takes, and returns the loss. L1: a
/// sensor's outliers (flying pixels at silhouettes, missed returns) pull no harder than any
/// other error. Accumulates in `f64`.
pub fn depth_loss_grad(pred: &[f32], target: &[f32], lambda: f32, d_depth: &mut [f32]) -> f32 {
    assert_eq!(pred.len(), target.len(), "pred and target must have the same length");
    assert_eq!(d_depth.len(), pred.len(), "d_depth must have the same length as pred");
    let scale = lambda / pred.len().max(1) as f32;
    let mut sum = 0.0f64;
    for ((d, &p), &t) in d_depth.iter_mut().zip(pred).zip(target) {
        *d = if t > 0.0 {
            sum += (p - t).abs() as f64;
            // sign(0) = 0: a ray that already matches gets no push.
            scale * if p > t { 1.0 } else if p < t { -1.0 } else { 0.0 }
        } else {
            0.0
        };
    }
    (sum * scale as f64) as f32
}

/// Mean squared error over all values and its gradient: returns `mean((pred − target)²)` and writes
/// `d_pred = 2 (pred − target) / len`. Accumulates in `f64`.
pub fn mse_loss_grad(pred: &[f32], target: &[f32], d_pred: &mut [f32]) -> f32 {
    photometric_loss_grad(pred, target, None, d_pred)
}

/// The photometric loss `mean(h(pred − target))` over all values and its gradient, where `h(e) = e²`
/// (MSE, `huber_delta = None`) or instant-ngp's Huber loss `h(e) = e²` for `|e| ≤ δ`,
/// `2δ|e| − δ²` beyond (its `huber_loss(·, 0.1) / 5`: the MSE for small residuals, linear for large
/// ones, so outliers — edges, early training — pull with a bounded gradient). Writes
/// `d_pred = h'(e) / len` and returns the MSE `mean(e²)` in either case (what PSNR reports).
/// Accumulates in `f64`.
pub fn photometric_loss_grad(pred: &[f32], target: &[f32], huber_delta: Option<f32>, d_pred: &mut [f32]) -> f32 {
    assert_eq!(
        pred.len(),
        target.len(),
        "pred and target must have the same length"
    );
    assert_eq!(
        d_pred.len(),
        pred.len(),
        "d_pred must have the same length as pred"
    );
    if pred.is_empty() {
        return 0.0;
    }
    let scale = 2.0 / pred.len() as f32;
    let delta = huber_delta.unwrap_or(f32::INFINITY);
    let mut sum = 0.0f64;
    for ((d, &p), &y) in d_pred.iter_mut().zip(pred).zip(target) {
        let e = p - y;
        sum += (e as f64) * (e as f64);
        *d = scale * e.clamp(-delta, delta);
    }
    (sum / pred.len() as f64) as f32
}
