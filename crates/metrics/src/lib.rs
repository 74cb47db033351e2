//! Image quality metrics: MSE, PSNR and SSIM (Gaussian 11×11, σ = 1.5).
//!
//! All metrics take flat `f32` slices (images in `[0, 1]`, data range 1) and accumulate in `f64`.
//! The conventions are those of the NeRF papers' evaluation code:
//! - PSNR = −10·log10(MSE), MSE over every value of the image (nerf-pytorch `mse2psnr(img2mse)`,
//!   skimage `peak_signal_noise_ratio` with `data_range = 1`).
//! - SSIM as skimage `structural_similarity(a, b, channel_axis=-1, data_range=1,
//!   gaussian_weights=True, sigma=1.5, use_sample_covariance=False)`.
//!
//! Sums are taken over fixed-size chunks in parallel and the chunk partials added in order, so
//! results are deterministic regardless of the number of threads.

use rayon::prelude::*;

/// Values per parallel chunk of the MSE reduction.
const MSE_CHUNK: usize = 1 << 16;

/// Mean squared error of two equally long slices, accumulated in `f64`. Empty slices give NaN.
///
/// # Panics
/// If the lengths differ.
pub fn mse(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "mse: slices of different lengths");
    let partial = |(x, y): (&[f32], &[f32])| -> f64 {
        x.iter()
            .zip(y)
            .map(|(&p, &q)| {
                let d = p as f64 - q as f64;
                d * d
            })
            .sum()
    };
    let sum: f64 = if a.len() <= MSE_CHUNK {
        partial((a, b))
    } else {
        let parts: Vec<f64> = a
            .par_chunks(MSE_CHUNK)
            .zip(b.par_chunks(MSE_CHUNK))
            .map(partial)
            .collect();
        parts.iter().sum()
    };
    sum / a.len() as f64
}

/// PSNR in dB for data range 1: `−10·log10(mse(a, b))`; `+∞` when the images are equal.
///
/// # Panics
/// If the lengths differ.
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    mse_to_psnr(mse(a, b))
}

/// Converts an MSE (data range 1) to PSNR in dB: `−10·log10(mse)` (`+∞` for 0).
pub fn mse_to_psnr(mse: f64) -> f64 {
    -10.0 * mse.log10()
}

/// Squared error of two images split by a per-pixel mask: where the error sits. `a` and `b` hold
/// `channels` values per pixel and `mask` one flag per pixel. Returns `(sse, count)`: index 0
/// sums the squared differences of the unmasked pixels' values, index 1 of the masked ones', in
/// `f64`; `count` holds the number of values in each. `sse[k] / count[k]` is that part's MSE and
/// `sse[1] / (sse[0] + sse[1])` the masked pixels' share of the image's squared error.
/// Evaluation splits a view by its ground truth's alpha this way, which tells floaters and haze in
/// empty space (masked: alpha = 0) apart from errors on the object.
///
/// # Panics
/// If the lengths differ or are not `channels·mask.len()`.
pub fn sse_split(a: &[f32], b: &[f32], channels: usize, mask: &[bool]) -> ([f64; 2], [usize; 2]) {
    assert_eq!(a.len(), b.len(), "sse_split: images of different lengths");
    assert_eq!(a.len(), channels * mask.len(), "sse_split: mask is not one flag per pixel");
    let mut sse = [0.0f64; 2];
    let mut count = [0usize; 2];
    for ((pa, pb), &m) in a.chunks_exact(channels).zip(b.chunks_exact(channels)).zip(mask) {
        let k = m as usize;
        for (&x, &y) in pa.iter().zip(pb) {
            let d = x as f64 - y as f64;
            sse[k] += d * d;
        }
        count[k] += channels;
    }
    (sse, count)
}

/// SSIM stabilising constant `K1`.
pub const SSIM_K1: f64 = 0.01;
/// SSIM stabilising constant `K2`.
pub const SSIM_K2: f64 = 0.03;
/// Standard deviation of the SSIM Gaussian window.
pub const SSIM_SIGMA: f64 = 1.5;
/// Radius of the SSIM window: `int(3.5·σ + 0.5)` = 5 (11 taps), scipy's `truncate = 3.5`.
pub const SSIM_RADIUS: usize = 5;

/// The normalised 11-tap Gaussian (σ = 1.5) used by SSIM.
pub fn ssim_window() -> [f64; 2 * SSIM_RADIUS + 1] {
    let mut w: [f64; 2 * SSIM_RADIUS + 1] = std::array::from_fn(|i| {
        let x = i as f64 - SSIM_RADIUS as f64;
        (-0.5 * x * x / (SSIM_SIGMA * SSIM_SIGMA)).exp()
    });
    let s: f64 = w.iter().sum();
    w.iter_mut().for_each(|v| *v /= s);
    w
}

/// SSIM of two `H×W×3` images (interleaved RGB, row-major) in `[0, 1]`: the mean over the three
/// channels of [`ssim_per_channel`]. NaN when `width` or `height` is below 11 (skimage refuses
/// such images).
///
/// # Panics
/// If a slice length differs from `3·width·height`.
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize) -> f64 {
    let s = ssim_per_channel(a, b, width, height);
    (s[0] + s[1] + s[2]) / 3.0
}

/// Per-channel SSIM of two `H×W×3` images (interleaved RGB, row-major) in `[0, 1]`, skimage's
/// convention: local statistics by a separable normalised Gaussian (11 taps, σ = 1.5), population
/// (co)variances, `C1 = (0.01·1)²`, `C2 = (0.03·1)²`, and the SSIM map averaged after cropping a
/// 5-pixel border. skimage filters with scipy's "reflect" boundary before cropping; since the
/// cropped map only contains positions whose whole window lies inside the image, the reflected
/// values never reach it, so this computes exactly those `(H−10)·(W−10)` "valid" positions.
/// Computed in `f64`, parallel over rows. NaN for images narrower or shorter than 11 pixels.
///
/// # Panics
/// If a slice length differs from `3·width·height`.
pub fn ssim_per_channel(a: &[f32], b: &[f32], width: usize, height: usize) -> [f64; 3] {
    ssim_map_mean(a, b, width, height, None)
}

/// SSIM over the kept pixels of an image: [`ssim`]'s map averaged over the windows that hold
/// kept pixels only (`keep`: one flag per pixel, row-major), so nothing a mask drops (a
/// passer-by, the black beyond a fisheye's image circle) enters the score, not even through a
/// neighbour's window. With every pixel kept it is [`ssim`] exactly. NaN when no 11×11 window
/// holds kept pixels only (or the image is smaller than the window).
///
/// # Panics
/// If a slice length differs from `3·width·height`, or `keep` from `width·height`.
pub fn ssim_masked(a: &[f32], b: &[f32], width: usize, height: usize, keep: &[bool]) -> f64 {
    assert_eq!(keep.len(), width * height, "ssim_masked: not one flag per pixel");
    let s = ssim_map_mean(a, b, width, height, Some(keep));
    (s[0] + s[1] + s[2]) / 3.0
}

/// The per-channel mean of the SSIM map over the valid positions whose window `keep` keeps
/// whole (all without a mask).
fn ssim_map_mean(a: &[f32], b: &[f32], width: usize, height: usize, keep: Option<&[bool]>) -> [f64; 3] {
    let n = 3 * width * height;
    assert_eq!(a.len(), n, "ssim: first image is not 3·width·height long");
    assert_eq!(b.len(), n, "ssim: second image is not 3·width·height long");
    let taps = 2 * SSIM_RADIUS + 1;
    if width < taps || height < taps {
        return [f64::NAN; 3];
    }
    let win = ssim_window();
    let (vw, vh) = (width - 2 * SSIM_RADIUS, height - 2 * SSIM_RADIUS);
    // With a mask: the summed-area table of dropped pixels, `(width + 1)·(height + 1)`, so that a
    // window's count of them is four lookups.
    let dropped: Option<Vec<u32>> = keep.map(|k| {
        let mut sat = vec![0u32; (width + 1) * (height + 1)];
        for y in 0..height {
            let mut row = 0u32;
            for x in 0..width {
                row += u32::from(!k[y * width + x]);
                sat[(y + 1) * (width + 1) + x + 1] = sat[y * (width + 1) + x + 1] + row;
            }
        }
        sat
    });
    let whole_window_kept = |x: usize, y: usize| {
        dropped.as_ref().is_none_or(|sat| {
            let at = |yy: usize, xx: usize| sat[yy * (width + 1) + xx];
            let (x1, y1) = (x + taps, y + taps);
            at(y1, x1) + at(y, x) == at(y, x1) + at(y1, x)
        })
    };
    let c1 = (SSIM_K1 * 1.0).powi(2);
    let c2 = (SSIM_K2 * 1.0).powi(2);

    // Horizontal pass: for every row and valid column, the five filtered moments per channel:
    // [μa, μb, E[a²], E[b²], E[ab]] × 3 channels.
    const M: usize = 15;
    let mut horiz = vec![0.0f64; height * vw * M];
    horiz
        .par_chunks_mut(vw * M)
        .enumerate()
        .for_each(|(row, out)| {
            let ra = &a[3 * width * row..3 * width * (row + 1)];
            let rb = &b[3 * width * row..3 * width * (row + 1)];
            for (x, o) in out.chunks_exact_mut(M).enumerate() {
                let mut acc = [0.0f64; M];
                for (t, &w) in win.iter().enumerate() {
                    let p = 3 * (x + t);
                    for c in 0..3 {
                        let (va, vb) = (ra[p + c] as f64, rb[p + c] as f64);
                        let m = &mut acc[5 * c..5 * c + 5];
                        m[0] += w * va;
                        m[1] += w * vb;
                        m[2] += w * va * va;
                        m[3] += w * vb * vb;
                        m[4] += w * va * vb;
                    }
                }
                o.copy_from_slice(&acc);
            }
        });

    // Vertical pass over valid rows, then the SSIM map, summed per output row.
    let row_sums: Vec<([f64; 3], usize)> = (0..vh)
        .into_par_iter()
        .map(|y| {
            let mut sums = [0.0f64; 3];
            let mut kept = 0usize;
            let mut acc = [0.0f64; M];
            for x in 0..vw {
                if !whole_window_kept(x, y) {
                    continue;
                }
                kept += 1;
                acc.iter_mut().for_each(|v| *v = 0.0);
                for (t, &w) in win.iter().enumerate() {
                    let h = &horiz[((y + t) * vw + x) * M..((y + t) * vw + x + 1) * M];
                    for (s, &v) in acc.iter_mut().zip(h) {
                        *s += w * v;
                    }
                }
                for (c, sum) in sums.iter_mut().enumerate() {
                    let m = &acc[5 * c..5 * c + 5];
                    let (ux, uy) = (m[0], m[1]);
                    let vx = m[2] - ux * ux;
                    let vy = m[3] - uy * uy;
                    let vxy = m[4] - ux * uy;
                    let num = (2.0 * ux * uy + c1) * (2.0 * vxy + c2);
                    let den = (ux * ux + uy * uy + c1) * (vx + vy + c2);
                    *sum += num / den;
                }
            }
            (sums, kept)
        })
        .collect();
    let count = row_sums.iter().map(|(_, k)| k).sum::<usize>() as f64;
    let mut out = [0.0f64; 3];
    for (s, _) in &row_sums {
        for c in 0..3 {
            out[c] += s[c];
        }
    }
    out.map(|v| v / count)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_is_normalised_and_symmetric() {
        let w = ssim_window();
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        for i in 0..5 {
            assert_eq!(w[i], w[10 - i]);
            assert!(w[i] < w[i + 1]);
        }
    }

    #[test]
    fn sse_split_adds_up_to_the_mse() {
        let a = [0.0, 0.5, 1.0, 0.2, 0.2, 0.2, 1.0, 1.0, 1.0];
        let b = [0.0, 0.0, 1.0, 0.2, 0.7, 0.2, 0.0, 1.0, 1.0];
        let (sse, count) = sse_split(&a, &b, 3, &[false, true, true]);
        assert_eq!(count, [3, 6]);
        assert!((sse[0] - 0.25).abs() < 1e-6);
        assert!((sse[1] - 1.25).abs() < 1e-6);
        assert!(((sse[0] + sse[1]) / 9.0 - mse(&a, &b)).abs() < 1e-12);
        let (sse, count) = sse_split(&a, &b, 3, &[false; 3]);
        assert_eq!((sse[1], count), (0.0, [9, 0]));
    }

    #[test]
    fn mse_known_values() {
        assert_eq!(mse(&[0.0, 1.0], &[1.0, 1.0]), 0.5);
        assert!((psnr(&[0.0, 0.1], &[0.1, 0.0]) - 20.0).abs() < 1e-6);
        assert_eq!(mse_to_psnr(0.01), 20.0);
        // The chunked parallel path agrees with a direct sum.
        let n = 3 * MSE_CHUNK + 17;
        let a: Vec<f32> = (0..n)
            .map(|i| ((i * 7919) % 1000) as f32 / 1000.0)
            .collect();
        let b: Vec<f32> = (0..n)
            .map(|i| ((i * 104729) % 997) as f32 / 997.0)
            .collect();
        let direct: f64 = a
            .iter()
            .zip(&b)
            .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
            .sum::<f64>()
            / n as f64;
        assert!((mse(&a, &b) - direct).abs() < 1e-12 * direct);
    }

    #[test]
    fn small_images_give_nan() {
        let a = vec![0.5f32; 3 * 10 * 20];
        assert!(ssim(&a, &a, 10, 20).is_nan());
    }
}
