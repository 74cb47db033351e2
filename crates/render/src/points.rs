//! Surface points from rendered rays: where each ray's expected termination lies (a point cloud
//! of the scene, nerfstudio's `ns-export pointcloud`).

/// A point of the scene's surface: position (world coordinates) and colour in `[0, 1]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// World position.
    pub position: [f32; 3],
    /// RGB in `[0, 1]`, the background taken out.
    pub color: [f32; 3],
}

/// Appends to `out` the expected termination point of every rendered ray whose opacity is at
/// least `min_opacity` (and positive) and whose point lies in the box `[lo, hi]`:
/// `origin + (depth / opacity)·dir`, with `depth = Σ w_i t_i` as the compositor returns it (so
/// `depth / opacity` is the expected distance along the ray given that it stops, nerfstudio's
/// `expected_depth`; `dir` unit). The colour takes the background out of the composited one:
/// `(rgb − (1 − opacity)·bg) / opacity`, clamped to `[0, 1]`. Flat arrays as the renderer gives
/// them: `origins`, `dirs`, `rgb`, `background` `3·n`; `opacity`, `depth` `n`.
#[allow(clippy::too_many_arguments)]
pub fn surface_points(
    origins: &[f32],
    dirs: &[f32],
    rgb: &[f32],
    opacity: &[f32],
    depth: &[f32],
    background: &[f32],
    min_opacity: f32,
    (lo, hi): ([f32; 3], [f32; 3]),
    out: &mut Vec<SurfacePoint>,
) {
    for r in 0..opacity.len() {
        let a = opacity[r];
        if !(a >= min_opacity && a > 0.0) {
            continue;
        }
        let t = depth[r] / a;
        let position: [f32; 3] = std::array::from_fn(|c| origins[3 * r + c] + t * dirs[3 * r + c]);
        if !(0..3).all(|c| position[c] >= lo[c] && position[c] <= hi[c]) {
            continue;
        }
        let color = std::array::from_fn(|c| ((rgb[3 * r + c] - (1.0 - a) * background[3 * r + c]) / a).clamp(0.0, 1.0));
        out.push(SurfacePoint { position, color });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_sit_at_the_expected_depth_with_the_background_taken_out() {
        // Four rays from (0, 0, 1) and (1, 0, 0): opaque, half opaque, too faint, and one whose
        // point leaves the box.
        let origins = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0];
        let dirs = [0.0, 0.0, -1.0, -1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 1.0];
        let opacity = [1.0, 0.5, 0.05, 1.0];
        let depth = [0.75, 0.4, 0.01, 2.0]; // Σ w t: expected distances 0.75, 0.8, 0.2, 2
        let bg = [1.0; 12];
        // Half opaque: 0.5·c + 0.5·white = (0.6, 0.5, 0.75) for c = (0.2, 0, 0.5).
        let rgb = [0.1, 0.2, 0.3, 0.6, 0.5, 0.75, 0.9, 0.9, 0.9, 0.0, 0.0, 0.0];
        let mut out = vec![];
        surface_points(&origins, &dirs, &rgb, &opacity, &depth, &bg, 0.1, ([-1.0; 3], [1.0; 3]), &mut out);
        assert_eq!(out.len(), 2, "{out:?}");
        let close = |a: [f32; 3], b: [f32; 3]| (0..3).all(|c| (a[c] - b[c]).abs() < 1e-6);
        assert!(close(out[0].position, [0.0, 0.0, 0.25]) && close(out[0].color, [0.1, 0.2, 0.3]), "{:?}", out[0]);
        assert!(close(out[1].position, [0.2, 0.0, 0.0]) && close(out[1].color, [0.2, 0.0, 0.5]), "{:?}", out[1]);
        // Appends; a zero threshold still skips rays that stop nowhere.
        surface_points(&origins[..3], &dirs[..3], &rgb[..3], &[0.0], &[0.0], &bg[..3], 0.0, ([-1.0; 3], [1.0; 3]), &mut out);
        assert_eq!(out.len(), 2);
    }
}
