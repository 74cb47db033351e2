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
}
