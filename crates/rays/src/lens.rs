//! Lens distortion: OpenCV's radial–tangential and fisheye models of how a lens moves the
//! normalised image coordinates of a pinhole camera, and their inverse, which turns a pixel of a
//! photo taken through the lens back into the direction it saw ([`Distortion::undistort_dir`]).
//!
//! A [`Camera`](crate::Camera) carries its lens: its rays go through the photo's own pixels, as
//! in nerfstudio and instant-ngp, so a photo is never resampled and a fisheye keeps its whole
//! field of view, past 180° where the lens has it.

/// The lens model a [`Distortion`]'s coefficients belong to.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LensModel {
    /// OpenCV's radial–tangential model (COLMAP's `OPENCV` and its special cases): a pinhole
    /// camera when every coefficient is zero.
    #[default]
    RadialTangential,
    /// OpenCV's fisheye model (`cv::fisheye`; COLMAP's `OPENCV_FISHEYE`, `RADIAL_FISHEYE`,
    /// `SIMPLE_RADIAL_FISHEYE`): an equidistant fisheye when every coefficient is zero.
    Fisheye,
}

/// A lens's distortion of normalised image coordinates `(x, y)` (the pinhole's `x/z`, `y/z` in
/// OpenCV's camera axes: x right, y down, z forward).
///
/// - [`LensModel::RadialTangential`], OpenCV's: `r² = x² + y²`,
///   `x_d = x·(1 + k1·r² + k2·r⁴ + k3·r⁶) + 2·p1·x·y + p2·(r² + 2x²)` and
///   `y_d = y·(1 + k1·r² + k2·r⁴ + k3·r⁶) + p1·(r² + 2y²) + 2·p2·x·y` (`k4` is 0).
/// - [`LensModel::Fisheye`], OpenCV's: `θ = atan(r)`,
///   `θ_d = θ·(1 + k1·θ² + k2·θ⁴ + k3·θ⁶ + k4·θ⁸)`, `(x_d, y_d) = (θ_d / r)·(x, y)` (`p1`, `p2`
///   are 0): the distance from the principal point grows with the angle off the axis, not with
///   its tangent.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Distortion {
    /// Which model the coefficients are for.
    pub model: LensModel,
    /// Radial coefficient of `r²` (fisheye: of `θ²`).
    pub k1: f64,
    /// Radial coefficient of `r⁴` (`θ⁴`).
    pub k2: f64,
    /// Radial coefficient of `r⁶` (`θ⁶`).
    pub k3: f64,
    /// The fisheye's coefficient of `θ⁸` (0 for the radial–tangential model).
    pub k4: f64,
    /// First tangential coefficient (radial–tangential only).
    pub p1: f64,
    /// Second tangential coefficient (radial–tangential only).
    pub p2: f64,
}

/// Newton iterations of [`Distortion::undistort_dir`] at most (it stops once a step no longer
/// moves the point in f64; `shaders/rays.wgsl` runs all of them in f32): from the distorted
/// point itself, a lens a real camera has converges in a handful.
pub const UNDISTORT_ITERATIONS: usize = 10;

/// How far, in normalised coordinates, the distorted position of [`Distortion::undistort_dir`]'s
/// answer may lie from the point it was given for the answer to count (about 10⁻⁵ pixels at a
/// focal length of 1000 pixels).
pub const UNDISTORT_TOLERANCE: f64 = 1e-8;

impl Distortion {
    /// The pinhole camera: no distortion.
    pub const NONE: Distortion = Distortion { model: LensModel::RadialTangential, k1: 0.0, k2: 0.0, k3: 0.0, k4: 0.0, p1: 0.0, p2: 0.0 };

    /// `true` for a pinhole camera: the radial–tangential model with every coefficient zero (a
    /// fisheye is never one).
    pub fn is_identity(&self) -> bool {
        self.model == LensModel::RadialTangential && [self.k1, self.k2, self.k3, self.k4, self.p1, self.p2].iter().all(|&c| c == 0.0)
    }

    /// Whether every coefficient is finite.
    pub fn is_finite(&self) -> bool {
        [self.k1, self.k2, self.k3, self.k4, self.p1, self.p2].iter().all(|c| c.is_finite())
    }

    /// The distorted position of the undistorted normalised coordinates `(x, y)`.
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        match self.model {
            LensModel::RadialTangential => {
                let r2 = x * x + y * y;
                let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
                let xy = x * y;
                (
                    x * radial + 2.0 * self.p1 * xy + self.p2 * (r2 + 2.0 * x * x),
                    y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * xy,
                )
            }
            LensModel::Fisheye => {
                let r = (x * x + y * y).sqrt();
                // θ_d / r → 1 on the axis (θ = atan r ≈ r there).
                if r < 1e-12 {
                    return (x, y);
                }
                let s = self.fisheye_theta_d(r.atan()) / r;
                (x * s, y * s)
            }
        }
    }

    /// The fisheye's `θ_d(θ) = θ·(1 + k1·θ² + k2·θ⁴ + k3·θ⁶ + k4·θ⁸)`.
    #[inline]
    fn fisheye_theta_d(&self, theta: f64) -> f64 {
        let t2 = theta * theta;
        theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))
    }

    /// The distorted normalised coordinates of a point `p` in OpenCV's camera axes (x right,
    /// y down, z forward), where the lens images it: the pinhole's `(x/z, y/z)` distorted, or for
    /// the fisheye the angle `θ` off the axis (to π, so a point beside or behind the camera too)
    /// through `θ_d`. `None` where the lens does not image the point: behind a
    /// radial–tangential lens (`z ≤ 0`), on a fisheye's backward axis, or non-finite.
    pub fn project(&self, p: [f64; 3]) -> Option<(f64, f64)> {
        let out = match self.model {
            LensModel::RadialTangential => {
                if !(p[2] > 0.0) {
                    return None;
                }
                self.distort(p[0] / p[2], p[1] / p[2])
            }
            LensModel::Fisheye => {
                let rho = (p[0] * p[0] + p[1] * p[1]).sqrt();
                let theta = rho.atan2(p[2]);
                if rho == 0.0 {
                    if !(p[2] > 0.0) {
                        return None;
                    }
                    (0.0, 0.0)
                } else {
                    let s = self.fisheye_theta_d(theta) / rho;
                    (p[0] * s, p[1] * s)
                }
            }
        };
        (out.0.is_finite() && out.1.is_finite()).then_some(out)
    }

    /// The direction a lens pixel at distorted normalised coordinates `(x_d, y_d)` saw, in
    /// OpenCV's camera axes (x right, y down, z forward): the radial–tangential model's
    /// undistorted `(x, y, 1)` (z = 1, so that distances along it are depths), the fisheye's unit
    /// `(sin θ·x_d/θ_d, sin θ·y_d/θ_d, cos θ)` (a direction up to θ = π off the axis). The
    /// inverse of [`distort`](Self::distort) is found by [`UNDISTORT_ITERATIONS`] Newton steps
    /// from `(x_d, y_d)`, as `shaders/rays.wgsl` does in f32 (nerfstudio's
    /// `radial_and_tangential_undistort` likewise). `None` where they do not reach a point the
    /// lens takes to within [`UNDISTORT_TOLERANCE`] of `(x_d, y_d)`: a position past the edge of
    /// what the coefficients can describe (their polynomial folds back there).
    pub fn undistort_dir(&self, xd: f64, yd: f64) -> Option<[f64; 3]> {
        let (d, converged) = self.undistort_iterate(xd, yd);
        converged.then_some(d)
    }

    /// [`undistort_dir`](Self::undistort_dir)'s direction after its Newton steps, and whether
    /// it counts: the direction rays take (the GPU's is the same), which a loader checks over
    /// the whole photo (`nerf_data` refuses a lens that does not invert over its image).
    pub fn undistort_iterate(&self, xd: f64, yd: f64) -> ([f64; 3], bool) {
        match self.model {
            LensModel::RadialTangential => {
                let (mut x, mut y) = (xd, yd);
                for _ in 0..UNDISTORT_ITERATIONS {
                    let (fx, fy, [[a, b], [c, d]]) = self.distort_jacobian(x, y);
                    let (ex, ey) = (fx - xd, fy - yd);
                    let det = a * d - b * c;
                    if !(det.abs() > 1e-12) {
                        break;
                    }
                    let (sx, sy) = ((d * ex - b * ey) / det, (a * ey - c * ex) / det);
                    x -= sx;
                    y -= sy;
                    // Converged to f64 precision: more steps would not move it.
                    if sx.abs() + sy.abs() <= 1e-15 * (1.0 + x.abs() + y.abs()) {
                        break;
                    }
                }
                let (fx, fy) = self.distort(x, y);
                ([x, y, 1.0], (fx - xd).hypot(fy - yd) <= UNDISTORT_TOLERANCE)
            }
            LensModel::Fisheye => {
                let theta_d = xd.hypot(yd);
                if theta_d < 1e-12 {
                    return ([0.0, 0.0, 1.0], true);
                }
                let mut theta = theta_d;
                for _ in 0..UNDISTORT_ITERATIONS {
                    let t2 = theta * theta;
                    let f = self.fisheye_theta_d(theta) - theta_d;
                    let df = 1.0 + t2 * (3.0 * self.k1 + t2 * (5.0 * self.k2 + t2 * (7.0 * self.k3 + t2 * 9.0 * self.k4)));
                    if !(df.abs() > 1e-12) {
                        break;
                    }
                    let step = f / df;
                    theta -= step;
                    if step.abs() <= 1e-15 * (1.0 + theta.abs()) {
                        break;
                    }
                }
                let ok = theta.is_finite()
                    && (0.0..std::f64::consts::PI).contains(&theta)
                    && (self.fisheye_theta_d(theta) - theta_d).abs() <= UNDISTORT_TOLERANCE;
                let s = theta.sin() / theta_d;
                ([xd * s, yd * s, theta.cos()], ok)
            }
        }
    }

    /// The radial–tangential model's distorted position of `(x, y)` and its Jacobian
    /// `[[∂x_d/∂x, ∂x_d/∂y], [∂y_d/∂x, ∂y_d/∂y]]`.
    fn distort_jacobian(&self, x: f64, y: f64) -> (f64, f64, [[f64; 2]; 2]) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // ∂radial/∂(r²).
        let dr = self.k1 + r2 * (2.0 * self.k2 + r2 * 3.0 * self.k3);
        let (fx, fy) = self.distort(x, y);
        let a = radial + 2.0 * x * x * dr + 2.0 * self.p1 * y + 6.0 * self.p2 * x;
        let b = 2.0 * x * y * dr + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let c = 2.0 * x * y * dr + 2.0 * self.p1 * x + 2.0 * self.p2 * y;
        let d = radial + 2.0 * y * y * dr + 6.0 * self.p1 * y + 2.0 * self.p2 * x;
        (fx, fy, [[a, b], [c, d]])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn lenses(rng: &mut impl Rng) -> Vec<Distortion> {
        (0..40)
            .map(|i| {
                let mut c = || rng.gen_range(-1.0..1.0);
                if i % 2 == 0 {
                    Distortion { k1: 0.2 * c(), k2: 0.05 * c(), k3: 0.01 * c(), p1: 0.01 * c(), p2: 0.01 * c(), ..Distortion::NONE }
                } else {
                    Distortion { model: LensModel::Fisheye, k1: 0.05 * c(), k2: 0.01 * c(), k3: 0.002 * c(), k4: 0.0005 * c(), ..Distortion::NONE }
                }
            })
            .collect()
    }

    /// `undistort_dir` inverts `distort` (and `project`) over the field of view such lenses have:
    /// the radial–tangential model out to 40° off the axis, the fisheye out to 100°, past a
    /// hemisphere.
    #[test]
    fn undistorting_inverts_the_lens() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for lens in lenses(&mut rng) {
            let max_theta: f64 = if lens.model == LensModel::Fisheye { 100f64.to_radians() } else { 40f64.to_radians() };
            for _ in 0..200 {
                let (theta, phi) = (rng.gen_range(0.0..max_theta), rng.gen_range(-3.2f64..3.2));
                let p = [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()];
                let (xd, yd) = lens.project(p).unwrap();
                if lens.model == LensModel::RadialTangential {
                    assert_eq!(lens.distort(p[0] / p[2], p[1] / p[2]), (xd, yd));
                }
                let d = lens.undistort_dir(xd, yd).unwrap_or_else(|| panic!("{lens:?} at θ {theta}"));
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                assert!((0..3).all(|a| (d[a] / n - p[a]).abs() < 1e-9), "{lens:?}: {d:?} against {p:?}");
                if lens.model == LensModel::RadialTangential {
                    assert_eq!(d[2], 1.0, "z = 1");
                }
            }
        }
    }

    /// A point the lens cannot reach is no direction: past where a strong barrel lens's
    /// polynomial turns back (`r·(1 − 0.5 r²)` peaks at `r_d ≈ 0.544`), or past θ = π for a
    /// fisheye; and the identity leaves the point as it is.
    #[test]
    fn points_past_the_lens_have_no_direction() {
        let barrel = Distortion { k1: -0.5, ..Distortion::NONE };
        assert!(barrel.undistort_dir(0.5, 0.0).is_some());
        assert!(barrel.undistort_dir(0.6, 0.0).is_none());
        let fish = Distortion { model: LensModel::Fisheye, ..Distortion::NONE };
        assert!(fish.undistort_dir(3.0, 0.0).is_some_and(|d| d[2] < -0.98), "θ = 3 looks almost backwards");
        assert!(fish.undistort_dir(3.2, 0.0).is_none(), "past π");
        assert_eq!(Distortion::NONE.undistort_dir(0.3, -0.7), Some([0.3, -0.7, 1.0]));
        assert!(fish.project([0.0, 0.0, -1.0]).is_none() && barrel.project([0.1, 0.0, 0.0]).is_none());
        assert_eq!(fish.project([1.0, 0.0, 0.0]).map(|(x, _)| x), Some(std::f64::consts::FRAC_PI_2));
    }

    /// The Jacobian of the radial–tangential model against central differences.
    #[test]
    fn the_jacobian_is_the_derivative() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for lens in lenses(&mut rng).into_iter().filter(|l| l.model == LensModel::RadialTangential) {
            let (x, y) = (rng.gen_range(-0.8..0.8), rng.gen_range(-0.8..0.8));
            let (_, _, j) = lens.distort_jacobian(x, y);
            let h = 1e-6;
            let dx = |f: (f64, f64), g: (f64, f64)| [(f.0 - g.0) / (2.0 * h), (f.1 - g.1) / (2.0 * h)];
            let cx = dx(lens.distort(x + h, y), lens.distort(x - h, y));
            let cy = dx(lens.distort(x, y + h), lens.distort(x, y - h));
            for (got, want) in [(j[0][0], cx[0]), (j[1][0], cx[1]), (j[0][1], cy[0]), (j[1][1], cy[1])] {
                assert!((got - want).abs() < 1e-7, "{got} against {want}");
            }
        }
    }
}
