//! Renders with a transparent background (nerfstudio's `rgba` output, instant-ngp's screenshots):
//! a render's colour over its background taken apart into the field's own colour and its
//! opacity as alpha, for compositing elsewhere.

/// The straight-alpha RGBA (`4·n` into `out`) of rendered pixels: `rgb` (`3·n`) is
/// `Σ w_i c_i + (1 − α)·bg` over `background` (`3·n`) with `α = opacity` (`n`), so the field's
/// colour is `(rgb − (1 − α)·bg) / α`, clamped to `[0, 1]`, and alpha is `α`. A pixel with no
/// opacity (or not finite) is transparent black. The mean of supersampled passes
/// (`PassMean`) takes apart the same way: both of its terms are means. Compositing the result
/// over `background` (`c·α + (1 − α)·bg`) gives `rgb` back.
pub fn to_rgba(rgb: &[f32], opacity: &[f32], background: &[f32], out: &mut Vec<f32>) {
    let n = opacity.len();
    assert!(rgb.len() == 3 * n && background.len() == 3 * n, "to_rgba: 3 colour and background values per pixel");
    out.clear();
    out.reserve(4 * n);
    for ((c, &a), bg) in rgb.chunks_exact(3).zip(opacity).zip(background.chunks_exact(3)) {
        let a = if a.is_finite() { a.clamp(0.0, 1.0) } else { 0.0 };
        if a > 0.0 {
            out.extend((0..3).map(|k| ((c[k] - (1.0 - a) * bg[k]) / a).clamp(0.0, 1.0)));
            out.push(a);
        } else {
            out.extend_from_slice(&[0.0; 4]);
        }
    }
}

/// `rgba` (`4·n`, straight alpha) over `background` (`3` values, one colour for every pixel):
/// `c·α + (1 − α)·bg`, `3·n` into `out`.
pub fn over_background(rgba: &[f32], background: [f32; 3], out: &mut Vec<f32>) {
    out.clear();
    out.extend(rgba.chunks_exact(4).flat_map(|p| (0..3).map(move |k| p[k] * p[3] + (1.0 - p[3]) * background[k])));
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;

    /// Colours composited by the forward pass come apart into the samples' colour mix and
    /// opacity, and go back together over the background.
    #[test]
    fn a_render_comes_apart_and_back() {
        let mut rng = nerf_core::rng(3, 0);
        let n = 500;
        let (mut rgb, mut opacity, mut straight) = (Vec::new(), Vec::new(), Vec::new());
        let bg = [0.9f32, 0.2, 0.5];
        for i in 0..n {
            // Opacity 0 for some pixels, 1 for some, between for the rest.
            let a: f32 = match i % 5 {
                0 => 0.0,
                1 => 1.0,
                _ => rng.gen_range(0.01..1.0),
            };
            let c: [f32; 3] = std::array::from_fn(|_| rng.gen());
            rgb.extend((0..3).map(|k| c[k] * a + (1.0 - a) * bg[k]));
            opacity.push(a);
            straight.push((c, a));
        }
        let background: Vec<f32> = (0..n).flat_map(|_| bg).collect();
        let mut rgba = vec![f32::NAN; 7];
        to_rgba(&rgb, &opacity, &background, &mut rgba);
        assert_eq!(rgba.len(), 4 * n);
        for (i, (c, a)) in straight.iter().enumerate() {
            let p = &rgba[4 * i..4 * i + 4];
            assert_eq!(p[3], *a);
            if *a == 0.0 {
                assert_eq!(p, [0.0; 4], "no opacity: transparent black");
            } else {
                for k in 0..3 {
                    assert!((p[k] - c[k]).abs() < 2e-4 / a.max(0.01), "pixel {i}: {p:?} vs {c:?} at alpha {a}");
                }
            }
        }
        let mut back = Vec::new();
        over_background(&rgba, bg, &mut back);
        for (x, y) in back.iter().zip(&rgb) {
            assert!((x - y).abs() < 1e-5, "{x} vs {y}");
        }
        // NaN opacity: transparent; opacity past 1 is 1.
        to_rgba(&[0.5; 6], &[f32::NAN, 1.5], &[1.0; 6], &mut rgba);
        assert_eq!(rgba, [0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 1.0]);
    }
}
