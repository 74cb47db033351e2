//! Normal maps for viewing: each ray's expected surface point, oriented by the density's gradient
//! there (what instant-ngp's `Normals` render mode and nerfstudio's `normals` output show).
//!
//! The gradient is taken by central differences, so any field that gives densities gives
//! normals: [`gradient_stencil`] lays out six points about each surface point, the field's
//! density there goes to [`normals_from_stencil`], and [`normals_to_rgb`] makes the image.

/// How far apart a surface point's differences are taken: one pixel's footprint at the point's
/// distance `t`, `t·pixel_angle`, so that the normals resolve what the frame does, and at least
/// `min`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NormalSteps {
    /// The angle a pixel spans, radians (a pinhole's `1/f`).
    pub pixel_angle: f32,
    /// The least step.
    pub min: f32,
}

/// The surface points of rays: `o + d·t` at the expected termination distance
/// `t = depth/opacity` (`depth` being `Σ w_i t_i`, not normalised, as
/// [`crate::CompositeOutputs::depth`]), or the origin where the opacity is 0; and the step of
/// each one's differences ([`NormalSteps`]). `origins`, `dirs` (unit): `3·n`; `depth`,
/// `opacity`: `n`; `points`: `3·n`; `steps`: `n`.
pub fn surface_points_of(origins: &[f32], dirs: &[f32], depth: &[f32], opacity: &[f32], rule: NormalSteps, points: &mut Vec<f32>, steps: &mut Vec<f32>) {
    points.clear();
    steps.clear();
    for ((o, d), (&z, &a)) in origins.chunks_exact(3).zip(dirs.chunks_exact(3)).zip(depth.iter().zip(opacity)) {
        let t = if a > 0.0 && (z / a).is_finite() { z / a } else { 0.0 };
        points.extend_from_slice(&[o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]);
        steps.push((t * rule.pixel_angle).max(rule.min));
    }
}

/// For each point `p` (`3·n` values) and its step `h` (`n`), the six points `p + h·e_x,
/// p − h·e_x, p + h·e_y, p − h·e_y, p + h·e_z, p − h·e_z`, in that order: `18·n` values into
/// `out`.
pub fn gradient_stencil(points: &[f32], steps: &[f32], out: &mut Vec<f32>) {
    assert_eq!(points.len(), 3 * steps.len(), "gradient_stencil: one step per point");
    out.clear();
    out.reserve(6 * points.len());
    for (p, &h) in points.chunks_exact(3).zip(steps) {
        for axis in 0..3 {
            for s in [h, -h] {
                let mut q = [p[0], p[1], p[2]];
                q[axis] += s;
                out.extend_from_slice(&q);
            }
        }
    }
}

/// Unit normals (`3·n` into `out`) from the densities at [`gradient_stencil`]'s points (`6·n`):
/// `−∇σ / |∇σ|`, pointing to where the density falls (out of a surface), the gradient's
/// components `(σ(p + h·e) − σ(p − h·e)) / 2h`. A point whose gradient vanishes (or is not
/// finite) gets `(0, 0, 0)`.
pub fn normals_from_stencil(sigma: &[f32], out: &mut Vec<f32>) {
    out.clear();
    out.extend(sigma.chunks_exact(6).flat_map(|s| {
        // The common factor 1/2h leaves the direction alone.
        let g = [s[0] - s[1], s[2] - s[3], s[4] - s[5]];
        let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
        if len > 0.0 && len.is_finite() {
            [-g[0] / len, -g[1] / len, -g[2] / len]
        } else {
            [0.0; 3]
        }
    }));
}

/// A normal map (`3·n` RGB values in `[0, 1]` into `out`): each unit normal as `(n + 1)/2`
/// (x red, y green, z blue, in world axes), weighted by the pixel's opacity over `background`,
/// so empty space shows the background and a normal that vanished shows mid-grey.
pub fn normals_to_rgb(normals: &[f32], opacity: &[f32], background: [f32; 3], out: &mut Vec<f32>) {
    out.clear();
    out.extend(normals.chunks_exact(3).zip(opacity).flat_map(|(n, &a)| {
        let a = if a.is_finite() { a.clamp(0.0, 1.0) } else { 0.0 };
        std::array::from_fn::<f32, 3, _>(|c| a * 0.5 * (n[c] + 1.0) + (1.0 - a) * background[c])
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A blob of density `σ(p) = exp(−|p − c|²)` falls away from its centre: the normals on a
    /// shell about it point straight out, whatever the step.
    #[test]
    fn normals_of_a_blob_point_away_from_its_centre() {
        let c = [0.3f32, -0.2, 0.5];
        let sigma = |p: &[f32]| (-(0..3).map(|a| (p[a] - c[a]).powi(2)).sum::<f32>()).exp();
        let dirs: Vec<[f32; 3]> = vec![[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.6, 0.0, 0.8], [-0.48, 0.6, -0.64], [0.36, 0.48, 0.8]];
        let points: Vec<f32> = dirs.iter().flat_map(|d| (0..3).map(|a| c[a] + 0.7 * d[a]).collect::<Vec<_>>()).collect();
        let (mut stencil, mut normals) = (Vec::new(), Vec::new());
        for h in [1e-3, 1e-2] {
            gradient_stencil(&points, &vec![h; dirs.len()], &mut stencil);
            assert_eq!(stencil.len(), 18 * dirs.len());
            let s: Vec<f32> = stencil.chunks_exact(3).map(sigma).collect();
            normals_from_stencil(&s, &mut normals);
            for (n, d) in normals.chunks_exact(3).zip(&dirs) {
                let err = (0..3).map(|a| (n[a] - d[a]).abs()).fold(0.0f32, f32::max);
                assert!(err < 2e-3, "h = {h}: {n:?} against {d:?}");
            }
        }
        // A flat density has no normal.
        normals_from_stencil(&[1.0; 6], &mut normals);
        assert_eq!(normals, [0.0; 3]);
    }

    #[test]
    fn surface_points_and_colours() {
        let (mut p, mut h) = (Vec::new(), Vec::new());
        surface_points_of(&[1.0, 2.0, 3.0, 0.0, 0.0, 0.0], &[0.0, 0.0, -1.0, 1.0, 0.0, 0.0], &[1.0, 0.0], &[0.5, 0.0], NormalSteps { pixel_angle: 0.25, min: 0.1 }, &mut p, &mut h);
        assert_eq!(p, [1.0, 2.0, 1.0, 0.0, 0.0, 0.0], "depth 1 at opacity ½: 2 along the ray; no opacity: the origin");
        assert_eq!(h, [0.5, 0.1], "a pixel's footprint 2 away, or the least step");
        let mut rgb = Vec::new();
        normals_to_rgb(&[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, -1.0, 0.0], &[1.0, 0.0, 0.5], [1.0, 1.0, 1.0], &mut rgb);
        assert_eq!(rgb, [0.5, 0.5, 1.0, 1.0, 1.0, 1.0, 0.75, 0.5, 0.75]);
    }
}
