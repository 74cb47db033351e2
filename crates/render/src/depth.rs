//! Depth maps for viewing: expected depth turned into a grey image (near bright, far dark).

/// The depth range to show: the 1st and 99th percentiles of `depth[i] / opacity[i]` over the
/// pixels whose opacity is at least ½ (the surfaces), or `None` when there are none or the range
/// is empty. `depth` is [`crate::CompositeOutputs::depth`], `Σ w_i t_i`, not normalised.
pub fn depth_range(depth: &[f32], opacity: &[f32]) -> Option<(f32, f32)> {
    let mut d: Vec<f32> = depth
        .iter()
        .zip(opacity)
        .filter(|(z, &a)| a >= 0.5 && z.is_finite())
        .map(|(&z, &a)| z / a)
        .collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f32::total_cmp);
    let at = |q: f64| d[((d.len() - 1) as f64 * q).round() as usize];
    let (lo, hi) = (at(0.01), at(0.99));
    (hi > lo).then_some((lo, hi))
}

/// A grey RGB image (`3·n` values in `[0, 1]`) of the normalised depth `depth[i] / opacity[i]`
/// over `range`: 1 at `range.0` (near), 0 at `range.1` and beyond, scaled by the opacity so that
/// empty space is black.
pub fn depth_to_gray(depth: &[f32], opacity: &[f32], range: (f32, f32), out: &mut Vec<f32>) {
    let (lo, hi) = range;
    out.clear();
    out.extend(depth.iter().zip(opacity).flat_map(|(&z, &a)| {
        let v = if a > 0.0 { (1.0 - (z / a - lo) / (hi - lo)).clamp(0.0, 1.0) * a.min(1.0) } else { 0.0 };
        let v = if v.is_finite() { v } else { 0.0 };
        [v; 3]
    }));
}

/// Google's Turbo colormap at `x` (clamped to `[0, 1]`), by Ruofei Du's polynomial fit to
/// Anton Mikhailov's table: dark blue at 0, green-yellow in the middle, dark red at 1. The depth
/// colormap of nerfstudio's renders.
pub fn turbo(x: f32) -> [f32; 3] {
    const R: [f32; 6] = [0.135_721_38, 4.615_392_6, -42.660_323, 132.131_08, -152.942_39, 59.286_38];
    const G: [f32; 6] = [0.091_402_61, 2.194_188_4, 4.842_966_6, -14.185_033, 4.277_298_6, 2.829_566];
    const B: [f32; 6] = [0.106_673_3, 12.641_946, -60.582_047, 110.362_77, -89.903_11, 27.348_25];
    let x = x.clamp(0.0, 1.0);
    let poly = |c: &[f32; 6]| c.iter().rev().fold(0.0, |acc, &k| acc * x + k);
    [poly(&R), poly(&G), poly(&B)].map(|v| v.clamp(0.0, 1.0))
}

/// The depth map of [`depth_to_gray`] in [`turbo`]'s colours, as nerfstudio draws depth: the
/// normalised depth `(depth[i]/opacity[i] − range.0) / (range.1 − range.0)` coloured near blue,
/// far red, over `background` by the opacity.
pub fn depth_to_turbo(depth: &[f32], opacity: &[f32], range: (f32, f32), background: [f32; 3], out: &mut Vec<f32>) {
    let (lo, hi) = range;
    out.clear();
    out.extend(depth.iter().zip(opacity).flat_map(|(&z, &a)| {
        let a = if a.is_finite() { a.clamp(0.0, 1.0) } else { 0.0 };
        let t = if a > 0.0 { (z / a - lo) / (hi - lo) } else { 0.0 };
        let c = turbo(if t.is_finite() { t } else { 0.0 });
        std::array::from_fn::<f32, 3, _>(|k| c[k] * a + background[k] * (1.0 - a))
    }));
}

/// The distance to focus a frame on from rays through its centre (`nerf render --focus auto`):
/// the median, over the rays whose opacity is at least ½, of their expected depth
/// `depth[i] / opacity[i]` times `axial[i]`, the cosine between the ray and the optical axis (so
/// a distance along the axis, what a thin lens focuses at). `None` when no ray is that opaque.
pub fn focus_distance(depth: &[f32], opacity: &[f32], axial: &[f32]) -> Option<f32> {
    let mut d: Vec<f32> = depth
        .iter()
        .zip(opacity)
        .zip(axial)
        .filter(|((z, &a), _)| a >= 0.5 && z.is_finite())
        .map(|((&z, &a), &c)| z / a * c)
        .collect();
    if d.is_empty() {
        return None;
    }
    d.sort_by(f32::total_cmp);
    Some(d[(d.len() - 1) / 2])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn near_is_bright_far_is_dark_and_empty_space_black() {
        // 100 opaque pixels at depths 2..=3 (normalised by their opacity), one empty.
        let mut depth: Vec<f32> = (0..100).map(|i| 0.8 * (2.0 + i as f32 / 99.0)).collect();
        let mut opacity = vec![0.8f32; 100];
        depth.push(0.0);
        opacity.push(0.0);
        let (lo, hi) = depth_range(&depth, &opacity).unwrap();
        assert!((lo - 2.01).abs() < 0.02 && (hi - 2.99).abs() < 0.02, "{lo} {hi}");
        let mut img = vec![];
        depth_to_gray(&depth, &opacity, (lo, hi), &mut img);
        assert_eq!(img.len(), 3 * 101);
        assert!((img[0] - 0.8).abs() < 1e-6, "nearest: full brightness times opacity, got {}", img[0]);
        assert_eq!(img[3 * 99], 0.0, "farthest: dark");
        assert!(img[3 * 30] > img[3 * 60], "monotone");
        assert_eq!(img[3 * 100], 0.0, "empty space: black");
        assert!(img.iter().all(|v| (0.0..=1.0).contains(v)));
        // No surface, or a flat one: no range.
        assert!(depth_range(&[1.0, 2.0], &[0.1, 0.2]).is_none());
        assert!(depth_range(&[1.0, 1.0], &[1.0, 1.0]).is_none());
    }

    #[test]
    fn focus_is_the_median_axial_depth_of_the_opaque_rays() {
        // Expected depths 2, 3, 4 and 10 (the last two halved by their opacity), a transparent
        // ray at 1; cosines 1 but for the second ray.
        let depth = [2.0, 3.0, 2.0, 5.0, 1.0];
        let opacity = [1.0, 1.0, 0.5, 0.5, 0.2];
        let axial = [1.0, 0.5, 1.0, 1.0, 1.0];
        // Axial depths 2, 1.5, 4, 10: the lower middle of four is 2.
        assert_eq!(focus_distance(&depth, &opacity, &axial), Some(2.0));
        assert_eq!(focus_distance(&depth[..3], &opacity[..3], &axial[..3]), Some(2.0));
        assert_eq!(focus_distance(&[1.0, f32::NAN], &[0.4, 1.0], &[1.0, 1.0]), None);
    }

    #[test]
    fn turbo_runs_from_dark_blue_through_green_to_dark_red() {
        // The polynomial's constant terms at 0, its sum at 1 (Du's coefficients).
        assert_eq!(turbo(0.0), [0.135_721_38, 0.091_402_61, 0.106_673_3]);
        assert_eq!(turbo(-1.0), turbo(0.0));
        let end = turbo(1.0);
        assert!(end[0] > 0.5 && end[1] < 0.1 && end[2] < 0.05, "{end:?}");
        let mid = turbo(0.5);
        assert!(mid[1] > 0.95 && mid[0] > 0.5 && mid[2] < 0.4, "{mid:?}");
        let quarter = turbo(0.25);
        assert!(quarter[2] > quarter[0], "blue before red: {quarter:?}");
        // Depth maps: near blue, far red, the background where nothing is.
        let mut out = Vec::new();
        depth_to_turbo(&[2.0, 3.0, 1.0], &[1.0, 0.5, 0.0], (2.0, 6.0), [1.0; 3], &mut out);
        assert_eq!(&out[..3], &turbo(0.0));
        let far = turbo(1.0);
        assert!((0..3).all(|k| (out[3 + k] - (0.5 * far[k] + 0.5)).abs() < 1e-6), "{out:?}");
        assert_eq!(&out[6..], &[1.0; 3]);
    }
}
