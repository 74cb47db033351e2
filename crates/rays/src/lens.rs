//! Lens distortion: how a lens moves the image of a pinhole (or an equidistant fisheye), in
//! OpenCV's models and those COLMAP, nerfstudio and Project Aria calibrate, and its inverse,
//! which turns a pixel of a photo taken through the lens back into the direction it saw
//! ([`Distortion::undistort_dir`]).
//!
//! A [`Camera`](crate::Camera) carries its lens: its rays go through the photo's own pixels, as
//! in nerfstudio and instant-ngp, so a photo is never resampled and a fisheye keeps its whole
//! field of view, past 180° where the lens has it.

/// The lens model a [`Distortion`]'s coefficients belong to: how a direction is projected
/// before the distortion, and where its tangential and thin-prism terms apply.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LensModel {
    /// OpenCV's model (`cv::projectPoints` with the rational and thin-prism terms; COLMAP's
    /// `OPENCV`, `FULL_OPENCV` and their special cases): the pinhole's `(x/z, y/z)`, a rational
    /// radial factor, then tangential and thin-prism terms. A pinhole camera when every
    /// coefficient is zero.
    #[default]
    RadialTangential,
    /// OpenCV's fisheye model (`cv::fisheye`, Kannala–Brandt; COLMAP's `OPENCV_FISHEYE`,
    /// `RADIAL_FISHEYE`, `SIMPLE_RADIAL_FISHEYE`, and with tangential and thin-prism terms
    /// `THIN_PRISM_FISHEYE`): the equidistant point (the angle `θ` off the axis), a polynomial
    /// radial factor in `θ`, tangential and thin-prism terms on the equidistant point. An
    /// equidistant fisheye when every coefficient is zero.
    Fisheye,
    /// Meta's `Fisheye624` (Project Aria's `FisheyeRadTanThinPrism`; nerfstudio's `FISHEYE624`,
    /// COLMAP's `RAD_TAN_THIN_PRISM_FISHEYE`): as [`Fisheye`](Self::Fisheye), but the
    /// tangential and thin-prism terms apply to the radially distorted point.
    Fisheye624,
    /// COLMAP's `FOV` model (Devernay and Faugeras's, the ATAN camera of PTAM and DSO): the
    /// pinhole's `(x/z, y/z)` at radius `ρ` moves to `atan(2ρ·tan(ω/2)) / ω` along its
    /// direction, with the field of view `ω` in [`Distortion::omega`]; no other coefficients.
    Fov,
    /// COLMAP's `DIVISION` and `SIMPLE_DIVISION` (Fitzgibbon's one-parameter division model):
    /// the pinhole's `(x/z, y/z)` is the distorted point `p_d` divided by `1 + k1·|p_d|²`. Its
    /// radial factor is `R = 2 / (1 + √(1 − 4·k1·ρ²))` (nothing is imaged where
    /// `4·k1·ρ² > 1`), and it inverts in closed form; `k1` is its only coefficient (to first
    /// order in `ρ²` it is OpenCV's `k1`).
    Division,
    /// COLMAP's `EUCM` (Khomutenko et al.'s enhanced unified camera model): a direction
    /// `(x, y, z)` lands at `(x, y) / (α·d + (1 − α)·z)`, `d = √(β·(x² + y²) + z²)`, with
    /// [`Distortion::alpha`] in `[0, 1]` and [`Distortion::beta`] above 0; `α = 0` is a pinhole.
    /// It sees past 90° off the axis, so its directions are unit vectors as a fisheye's, and it
    /// inverts in closed form; no other coefficients.
    Eucm,
}

impl LensModel {
    /// Whether the lens's directions ([`Distortion::undistort_dir`]) are unit vectors, as those
    /// of a lens that may see past 90° off its axis (the fisheyes, EUCM), not `(x, y, 1)`.
    pub fn unit_directions(self) -> bool {
        self.is_fisheye() || self == LensModel::Eucm
    }

    /// Whether the model projects a direction by its angle off the axis (a fisheye), not by
    /// its pinhole slope.
    pub fn is_fisheye(self) -> bool {
        matches!(self, LensModel::Fisheye | LensModel::Fisheye624)
    }
}

/// A lens's distortion of the projected coordinates `(a, b)` of a direction, in OpenCV's
/// camera axes (x right, y down, z forward): the pinhole's `(x/z, y/z)` for
/// [`LensModel::RadialTangential`], the equidistant `θ·(x, y)/√(x² + y²)` with
/// `θ = atan2(√(x² + y²), z)` for the fisheyes. With `ρ² = a² + b²`:
///
/// - the radial factor `R`: the rational `(1 + k1·ρ² + k2·ρ⁴ + k3·ρ⁶) / (1 + k4·ρ² + k5·ρ⁴ +
///   k6·ρ⁶)` for [`LensModel::RadialTangential`] (OpenCV's; `k4..k6` are zero but in
///   `FULL_OPENCV`), the polynomial `1 + k1·θ² + k2·θ⁴ + … + k6·θ¹²` for the fisheyes
///   (OpenCV's fisheye stops at `k4`), `atan(2ρ·tan(ω/2)) / (ρ·ω)` for [`LensModel::Fov`],
///   `2 / (1 + √(1 − 4·k1·ρ²))` for [`LensModel::Division`];
/// - the tangential and thin-prism terms of a point `(u, v)`, `r² = u² + v²`:
///   `T_x = 2·p1·u·v + p2·(r² + 2u²) + s1·r² + s2·r⁴` and
///   `T_y = p1·(r² + 2v²) + 2·p2·u·v + s3·r² + s4·r⁴` (OpenCV's names and order);
/// - the distorted point: `R·(a, b) + T(a, b)`, or for [`LensModel::Fisheye624`]
///   `q + T(q)` with `q = R·(a, b)`.
///
/// The photo's pixel `(u, v)` sits at `(fx·x_d + cx, fy·y_d + cy)` of the distorted point.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Distortion {
    /// Which model the coefficients are for.
    pub model: LensModel,
    /// Radial coefficient of `ρ²` (fisheye: of `θ²`).
    pub k1: f64,
    /// Radial coefficient of `ρ⁴` (`θ⁴`).
    pub k2: f64,
    /// Radial coefficient of `ρ⁶` (`θ⁶`).
    pub k3: f64,
    /// The rational model's denominator coefficient of `ρ²`; the fisheye's of `θ⁸`.
    pub k4: f64,
    /// The rational model's denominator coefficient of `ρ⁴`; the fisheye's of `θ¹⁰`.
    pub k5: f64,
    /// The rational model's denominator coefficient of `ρ⁶`; the fisheye's of `θ¹²`.
    pub k6: f64,
    /// First tangential coefficient (with `2uv` in `T_x`).
    pub p1: f64,
    /// Second tangential coefficient (with `r² + 2u²` in `T_x`).
    pub p2: f64,
    /// Thin prism: coefficient of `r²` in `T_x`.
    pub s1: f64,
    /// Thin prism: coefficient of `r⁴` in `T_x`.
    pub s2: f64,
    /// Thin prism: coefficient of `r²` in `T_y`.
    pub s3: f64,
    /// Thin prism: coefficient of `r⁴` in `T_y`.
    pub s4: f64,
    /// [`LensModel::Fov`]'s field of view `ω`, in radians (0 for the other models): its radial
    /// factor is `R = atan(2ρ·tan(ω/2)) / (ρ·ω)`, a pinhole's as `ω` → 0.
    pub omega: f64,
    /// [`LensModel::Eucm`]'s `α`, in `[0, 1]` (0 for the other models).
    pub alpha: f64,
    /// [`LensModel::Eucm`]'s `β`, above 0 (0 for the other models).
    pub beta: f64,
}

/// Newton iterations of [`Distortion::undistort_dir`] at most (it stops once a step no longer
/// moves the point in f64; `shaders/rays.wgsl` runs all of them in f32): from the distorted
/// point itself, a lens a real camera has converges in a handful. A
/// [`LensModel::Fisheye624`] lens runs them twice: for its tangential terms, then its radial
/// factor.
pub const UNDISTORT_ITERATIONS: usize = 10;

/// How far, in normalised coordinates, the distorted position of [`Distortion::undistort_dir`]'s
/// answer may lie from the point it was given for the answer to count (about 10⁻⁵ pixels at a
/// focal length of 1000 pixels).
pub const UNDISTORT_TOLERANCE: f64 = 1e-8;

/// The names of [`Distortion::coefficients`], in their order.
pub const COEFFICIENT_NAMES: [&str; 12] = ["k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "s1", "s2", "s3", "s4"];

impl Distortion {
    /// The pinhole camera: no distortion.
    pub const NONE: Distortion =
        Distortion { model: LensModel::RadialTangential, k1: 0.0, k2: 0.0, k3: 0.0, k4: 0.0, k5: 0.0, k6: 0.0, p1: 0.0, p2: 0.0, s1: 0.0, s2: 0.0, s3: 0.0, s4: 0.0, omega: 0.0, alpha: 0.0, beta: 0.0 };

    /// The lens of `model` with `coefficients` in [`COEFFICIENT_NAMES`]' order (`omega` 0).
    pub fn from_coefficients(model: LensModel, c: [f64; 12]) -> Self {
        let [k1, k2, k3, k4, k5, k6, p1, p2, s1, s2, s3, s4] = c;
        Distortion { model, k1, k2, k3, k4, k5, k6, p1, p2, s1, s2, s3, s4, omega: 0.0, alpha: 0.0, beta: 0.0 }
    }

    /// The coefficients in [`COEFFICIENT_NAMES`]' order: `k1..k6`, `p1`, `p2`, `s1..s4`.
    pub fn coefficients(&self) -> [f64; 12] {
        [self.k1, self.k2, self.k3, self.k4, self.k5, self.k6, self.p1, self.p2, self.s1, self.s2, self.s3, self.s4]
    }

    /// `true` for a pinhole camera: the radial–tangential model with every coefficient zero (a
    /// fisheye is never one).
    #[inline]
    pub fn is_identity(&self) -> bool {
        // Every coefficient ±0, without a branch per coefficient (it is asked once per ray).
        self.model == LensModel::RadialTangential && self.coefficients().iter().fold(0u64, |acc, c| acc | (c.to_bits() << 1)) == 0
    }

    /// Whether every coefficient is finite.
    pub fn is_finite(&self) -> bool {
        self.coefficients().iter().all(|c| c.is_finite()) && self.omega.is_finite() && self.alpha.is_finite() && self.beta.is_finite()
    }

    /// The [`LensModel::Eucm`] lens of `alpha` and `beta`.
    pub fn eucm(alpha: f64, beta: f64) -> Self {
        Distortion { model: LensModel::Eucm, alpha, beta, ..Distortion::NONE }
    }

    /// [`LensModel::Eucm`]'s image point of the direction `p` (OpenCV's camera axes): `None`
    /// outside what the lens sees, `z ≤ −w·d` with `w = α/(1 − α)` for `α ≤ ½` (where
    /// `α·d + (1 − α)·z` reaches 0) and `(1 − α)/α` above (where the image's rim is; past it
    /// the projection folds back onto the image, the backward axis onto its centre).
    fn eucm_project(&self, p: [f64; 3]) -> Option<(f64, f64)> {
        let a = self.alpha;
        let d = (self.beta * (p[0] * p[0] + p[1] * p[1]) + p[2] * p[2]).sqrt();
        let w = if a <= 0.5 { a / (1.0 - a) } else { (1.0 - a) / a };
        let den = a * d + (1.0 - a) * p[2];
        (p[2] > -w * d && den > 1e-12 * d).then(|| (p[0] / den, p[1] / den))
    }

    /// [`LensModel::Eucm`]'s closed-form inverse (COLMAP's `CamFromImg`, on the whole sphere):
    /// the unit direction of image point `m`, `(m_x, m_y, m_z)` normalised with
    /// `m_z = (1 − β·α²·r²) / (α·√(1 − (2α − 1)·β·r²) + 1 − α)`, and whether it counts: the
    /// square root's argument not below 0 (past it, for `α > ½`, the lens images nothing) and
    /// the direction's image `m` again.
    fn eucm_unproject(&self, xd: f64, yd: f64) -> ([f64; 3], bool) {
        let (a, b) = (self.alpha, self.beta);
        let r2 = xd * xd + yd * yd;
        let radicand = 1.0 - (2.0 * a - 1.0) * b * r2;
        let mz = (1.0 - b * a * a * r2) / (a * radicand.max(0.0).sqrt() + 1.0 - a);
        let n = (r2 + mz * mz).sqrt();
        let dir = [xd / n, yd / n, mz / n];
        let back = self.eucm_project(dir);
        let ok = radicand >= 0.0
            && dir.iter().all(|c| c.is_finite())
            && back.is_some_and(|(x, y)| ((x - xd) * (x - xd) + (y - yd) * (y - yd)).sqrt() <= UNDISTORT_TOLERANCE * (1.0 + r2.sqrt()));
        (dir, ok)
    }

    /// The [`LensModel::Fov`] lens of field of view `omega` (radians).
    pub fn fov(omega: f64) -> Self {
        Distortion { model: LensModel::Fov, omega, ..Distortion::NONE }
    }

    /// Whether any tangential or thin-prism coefficient is not zero.
    pub fn has_tangential(&self) -> bool {
        [self.p1, self.p2, self.s1, self.s2, self.s3, self.s4].iter().any(|&c| c != 0.0)
    }

    /// The radial factor `R` at `ρ²` and its derivative `dR/d(ρ²)`.
    #[inline]
    fn radial(&self, r2: f64) -> (f64, f64) {
        if self.model == LensModel::Fov {
            return self.fov_radial(r2);
        }
        if self.model == LensModel::Division {
            // R = 2/(1 + q), q = √(1 − 4k·ρ²): dR/d(ρ²) = 4k / (q·(1 + q)²). NaN where q² < 0.
            let q = (1.0 - 4.0 * self.k1 * r2).sqrt();
            return (2.0 / (1.0 + q), 4.0 * self.k1 / (q * (1.0 + q) * (1.0 + q)));
        }
        if self.model == LensModel::RadialTangential {
            let n = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
            let dn = self.k1 + r2 * (2.0 * self.k2 + r2 * 3.0 * self.k3);
            if self.k4 == 0.0 && self.k5 == 0.0 && self.k6 == 0.0 {
                return (n, dn);
            }
            let d = 1.0 + r2 * (self.k4 + r2 * (self.k5 + r2 * self.k6));
            let dd = self.k4 + r2 * (2.0 * self.k5 + r2 * 3.0 * self.k6);
            (n / d, (dn * d - n * dd) / (d * d))
        } else {
            let r = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * (self.k4 + r2 * (self.k5 + r2 * self.k6)))));
            let dr = self.k1 + r2 * (2.0 * self.k2 + r2 * (3.0 * self.k3 + r2 * (4.0 * self.k4 + r2 * (5.0 * self.k5 + r2 * 6.0 * self.k6))));
            (r, dr)
        }
    }

    /// [`LensModel::Fov`]'s constant `c = 2·tan(ω/2)`: a ray `ρ` off the axis (on the plane
    /// `z = 1`) lands `atan(c·ρ)/ω` from the centre.
    #[inline]
    fn fov_c(&self) -> f64 {
        2.0 * (0.5 * self.omega).tan()
    }

    /// [`LensModel::Fov`]'s radial factor `R = atan(c·ρ) / (ρ·ω)`, `c = 2·tan(ω/2)`, and
    /// `dR/d(ρ²)`; near the axis (`c²ρ² < 10⁻⁴`) from the series `atan(t)/t = 1 − t²/3 + t⁴/5 −
    /// t⁶/7`, which the closed form loses to cancellation there.
    #[inline]
    fn fov_radial(&self, r2: f64) -> (f64, f64) {
        if self.omega == 0.0 {
            return (1.0, 0.0);
        }
        let c = self.fov_c();
        let scale = c / self.omega;
        let t2 = c * c * r2;
        if t2 < 1e-4 {
            let r = scale * (1.0 + t2 * (-1.0 / 3.0 + t2 * (1.0 / 5.0 - t2 / 7.0)));
            let dr = scale * c * c * (-1.0 / 3.0 + t2 * (2.0 / 5.0 - t2 * 3.0 / 7.0));
            return (r, dr);
        }
        let rho = r2.sqrt();
        let t = c * rho;
        let r = t.atan() / (rho * self.omega);
        // dR/dρ = (t/(1 + t²) − atan t) / (ω·ρ²), and d(ρ²) = 2ρ·dρ.
        let dr = (t / (1.0 + t2) - t.atan()) / (self.omega * r2) / (2.0 * rho);
        (r, dr)
    }

    /// The tangential and thin-prism terms `T(u, v)` and their Jacobian.
    #[inline]
    fn tangential(&self, u: f64, v: f64) -> ((f64, f64), [[f64; 2]; 2]) {
        let r2 = u * u + v * v;
        let uv = u * v;
        let t = (
            2.0 * self.p1 * uv + self.p2 * (r2 + 2.0 * u * u) + r2 * (self.s1 + r2 * self.s2),
            self.p1 * (r2 + 2.0 * v * v) + 2.0 * self.p2 * uv + r2 * (self.s3 + r2 * self.s4),
        );
        // ∂(s·r² + s'·r⁴)/∂u = 2u·(s + 2s'·r²).
        let (sx, sy) = (2.0 * (self.s1 + 2.0 * self.s2 * r2), 2.0 * (self.s3 + 2.0 * self.s4 * r2));
        let j = [
            [2.0 * self.p1 * v + 6.0 * self.p2 * u + u * sx, 2.0 * self.p1 * u + 2.0 * self.p2 * v + v * sx],
            [2.0 * self.p1 * u + 2.0 * self.p2 * v + u * sy, 6.0 * self.p1 * v + 2.0 * self.p2 * u + v * sy],
        ];
        (t, j)
    }

    /// One stage of the lens on a point and its Jacobian: the radial factor (`RADIAL`), the
    /// tangential and thin-prism terms (`TANGENTIAL`), or both, as
    /// [`LensModel::RadialTangential`] and [`LensModel::Fisheye`] apply them.
    #[inline(always)]
    fn stage<const RADIAL: bool, const TANGENTIAL: bool>(&self, a: f64, b: f64) -> ((f64, f64), [[f64; 2]; 2]) {
        let (mut f, mut j) = ((a, b), [[1.0, 0.0], [0.0, 1.0]]);
        if RADIAL {
            let (r, dr) = self.radial(a * a + b * b);
            f = (a * r, b * r);
            j = [[r + 2.0 * a * a * dr, 2.0 * a * b * dr], [2.0 * a * b * dr, r + 2.0 * b * b * dr]];
        }
        if TANGENTIAL {
            let (t, jt) = self.tangential(a, b);
            f = (f.0 + t.0, f.1 + t.1);
            for (row, trow) in j.iter_mut().zip(jt) {
                row[0] += trow[0];
                row[1] += trow[1];
            }
        }
        (f, j)
    }

    /// The distorted point of the projected point `(a, b)` (the pinhole's `(x/z, y/z)`, or a
    /// fisheye's equidistant point).
    #[inline]
    pub fn distort_projected(&self, a: f64, b: f64) -> (f64, f64) {
        let tangential = self.has_tangential();
        match self.model {
            LensModel::Eucm => self.eucm_project([a, b, 1.0]).unwrap_or((f64::NAN, f64::NAN)),
            LensModel::Fisheye624 => {
                let (q, _) = self.stage::<true, false>(a, b);
                if tangential {
                    self.stage::<false, true>(q.0, q.1).0
                } else {
                    q
                }
            }
            _ if tangential => self.stage::<true, true>(a, b).0,
            _ => self.stage::<true, false>(a, b).0,
        }
    }

    /// The distorted position of the undistorted normalised coordinates `(x, y)` (the pinhole's
    /// `(x/z, y/z)`; a fisheye first takes them to its equidistant point, `θ = atan(r)`).
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        if !self.model.is_fisheye() {
            return self.distort_projected(x, y);
        }
        let r = (x * x + y * y).sqrt();
        // θ / r → 1 on the axis (θ = atan r ≈ r there).
        let s = if r < 1e-12 { 1.0 } else { r.atan() / r };
        self.distort_projected(x * s, y * s)
    }

    /// The distorted normalised coordinates of a point `p` in OpenCV's camera axes (x right,
    /// y down, z forward), where the lens images it: the pinhole's `(x/z, y/z)` distorted, or for
    /// a fisheye the angle `θ` off the axis (to π, so a point beside or behind the camera too)
    /// through its lens. `None` where the lens does not image the point: behind a
    /// radial–tangential lens (`z ≤ 0`), on a fisheye's backward axis, or non-finite.
    pub fn project(&self, p: [f64; 3]) -> Option<(f64, f64)> {
        let out = if self.model == LensModel::Eucm {
            self.eucm_project(p)?
        } else if self.model.is_fisheye() {
            let rho = (p[0] * p[0] + p[1] * p[1]).sqrt();
            if rho == 0.0 {
                if !(p[2] > 0.0) {
                    return None;
                }
                self.distort_projected(0.0, 0.0)
            } else {
                let s = rho.atan2(p[2]) / rho;
                self.distort_projected(p[0] * s, p[1] * s)
            }
        } else {
            if !(p[2] > 0.0) {
                return None;
            }
            self.distort(p[0] / p[2], p[1] / p[2])
        };
        (out.0.is_finite() && out.1.is_finite()).then_some(out)
    }

    /// The direction a lens pixel at distorted normalised coordinates `(x_d, y_d)` saw, in
    /// OpenCV's camera axes (x right, y down, z forward): the radial–tangential model's
    /// undistorted `(x, y, 1)` (z = 1, so that distances along it are depths), a fisheye's unit
    /// `(sin θ·a/θ, sin θ·b/θ, cos θ)` of its equidistant point `(a, b)` (a direction up to
    /// θ = π off the axis), EUCM's unit direction in closed form. The inverse of [`distort`](Self::distort) is found by
    /// [`UNDISTORT_ITERATIONS`] Newton steps from `(x_d, y_d)`, as `shaders/rays.wgsl` does in
    /// f32 (nerfstudio's `radial_and_tangential_undistort` and `fisheye624_unproject`
    /// likewise). `None` where they do not reach a point the lens takes to within
    /// [`UNDISTORT_TOLERANCE`] of `(x_d, y_d)`: a position past the edge of what the
    /// coefficients can describe (their polynomial folds back there).
    pub fn undistort_dir(&self, xd: f64, yd: f64) -> Option<[f64; 3]> {
        let (d, converged) = self.undistort_iterate(xd, yd);
        converged.then_some(d)
    }

    /// [`UNDISTORT_ITERATIONS`] Newton steps at most for the point `(a, b)` that the stage
    /// ([`stage`](Self::stage)) takes to `(x_d, y_d)`, from `(x_d, y_d)` itself (the stage's
    /// terms are type parameters, so that each loop is compiled without branches on them).
    fn newton<const RADIAL: bool, const TANGENTIAL: bool>(&self, xd: f64, yd: f64) -> (f64, f64) {
        let (mut x, mut y) = (xd, yd);
        for _ in 0..UNDISTORT_ITERATIONS {
            let ((fx, fy), [[a, b], [c, d]]) = self.stage::<RADIAL, TANGENTIAL>(x, y);
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
        (x, y)
    }

    /// A fisheye without tangential terms moves a point along its own direction: Newton on θ
    /// alone, `θ·R(θ²) = θ_d` (the steps the 2-D ones take, for less work), and the unit
    /// direction `(sin θ·x_d/θ_d, sin θ·y_d/θ_d, cos θ)`.
    fn undistort_theta(&self, xd: f64, yd: f64) -> ([f64; 3], bool) {
        let theta_d = (xd * xd + yd * yd).sqrt();
        if theta_d < 1e-12 {
            return ([0.0, 0.0, 1.0], true);
        }
        let mut theta = theta_d;
        for _ in 0..UNDISTORT_ITERATIONS {
            let (r, dr) = self.radial(theta * theta);
            let df = r + 2.0 * theta * theta * dr;
            if !(df.abs() > 1e-12) {
                break;
            }
            let step = (theta * r - theta_d) / df;
            theta -= step;
            if step.abs() <= 1e-15 * (1.0 + theta.abs()) {
                break;
            }
        }
        let ok = theta.is_finite()
            && (0.0..std::f64::consts::PI).contains(&theta)
            && (theta * self.radial(theta * theta).0 - theta_d).abs() <= UNDISTORT_TOLERANCE;
        let s = theta.sin() / theta_d;
        ([xd * s, yd * s, theta.cos()], ok)
    }

    /// [`undistort_dir`](Self::undistort_dir)'s direction after its Newton steps, and whether
    /// it counts: the direction rays take (the GPU's is the same), which a loader checks over
    /// the whole photo (`nerf_data` refuses a lens that does not invert over its image).
    pub fn undistort_iterate(&self, xd: f64, yd: f64) -> ([f64; 3], bool) {
        let tangential = self.has_tangential();
        if self.model.is_fisheye() && !tangential {
            return self.undistort_theta(xd, yd);
        }
        if self.model == LensModel::Fov && self.omega != 0.0 {
            // The closed form: ρ = tan(ρ_d·ω) / (2·tan(ω/2)), for ρ_d·ω below a right angle.
            let rho_d = (xd * xd + yd * yd).sqrt();
            if rho_d < 1e-12 {
                let s = 1.0 / self.fov_radial(0.0).0;
                return ([xd * s, yd * s, 1.0], true);
            }
            let angle = rho_d * self.omega;
            let s = angle.tan() / self.fov_c() / rho_d;
            let ok = angle.abs() < std::f64::consts::FRAC_PI_2 && s.is_finite() && s > 0.0;
            return ([xd * s, yd * s, 1.0], ok);
        }
        if self.model == LensModel::Eucm {
            return self.eucm_unproject(xd, yd);
        }
        if self.model == LensModel::Division {
            // The closed form: p = p_d / (1 + k1·ρ_d²), where the lens takes p back to p_d (past
            // the radius where the division folds back, it takes p elsewhere).
            let s = 1.0 / (1.0 + self.k1 * (xd * xd + yd * yd));
            let (a, b) = (xd * s, yd * s);
            let (fx, fy) = self.distort_projected(a, b);
            let close = ((fx - xd) * (fx - xd) + (fy - yd) * (fy - yd)).sqrt() <= UNDISTORT_TOLERANCE * (1.0 + (xd * xd + yd * yd).sqrt());
            return ([a, b, 1.0], close && s > 0.0 && s.is_finite());
        }
        let (a, b) = match self.model {
            // (A fisheye without tangential terms took the 1-D path above.)
            LensModel::Fisheye624 => {
                let (u, v) = self.newton::<false, true>(xd, yd);
                self.newton::<true, false>(u, v)
            }
            _ if tangential => self.newton::<true, true>(xd, yd),
            _ => self.newton::<true, false>(xd, yd),
        };
        let (fx, fy) = self.distort_projected(a, b);
        let close = ((fx - xd) * (fx - xd) + (fy - yd) * (fy - yd)).sqrt() <= UNDISTORT_TOLERANCE;
        if !self.model.is_fisheye() {
            return ([a, b, 1.0], close);
        }
        let theta = (a * a + b * b).sqrt();
        let ok = close && theta.is_finite() && theta < std::f64::consts::PI;
        // sin θ / θ → 1 on the axis.
        let s = if theta < 1e-12 { 1.0 } else { theta.sin() / theta };
        ([a * s, b * s, theta.cos()], ok)
    }
}

impl std::fmt::Display for Distortion {
    /// The model and its coefficients that are not zero: `Fisheye624: k1 0.1, p2 -0.002`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:?}:", self.model)?;
        let mut any = false;
        for (name, c) in COEFFICIENT_NAMES.iter().zip(self.coefficients()).filter(|(_, c)| *c != 0.0) {
            write!(f, "{} {name} {c}", if any { "," } else { "" })?;
            any = true;
        }
        if self.model == LensModel::Fov {
            write!(f, " omega {}", self.omega)?;
            any = true;
        }
        if self.model == LensModel::Eucm {
            write!(f, " alpha {}, beta {}", self.alpha, self.beta)?;
            any = true;
        }
        if !any {
            write!(f, " no coefficients")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Random lenses of every model, each with the terms real calibrations have: by index mod 7,
    /// radial–tangential (0: OpenCV's common five, 1: rational, with thin prism), fisheyes
    /// without and with tangential terms (2, 3), `Fisheye624`s (4, 5) and `FOV` lenses (6).
    fn lenses(rng: &mut impl Rng) -> Vec<Distortion> {
        (0..70)
            .map(|i| {
                let mut c = || rng.gen_range(-1.0..1.0);
                match i % 7 {
                    6 => Distortion::fov(0.9 + 0.6 * c()),
                    0 => Distortion { k1: 0.2 * c(), k2: 0.05 * c(), k3: 0.01 * c(), p1: 0.01 * c(), p2: 0.01 * c(), ..Distortion::NONE },
                    1 => Distortion {
                        k1: 0.2 * c(),
                        k2: 0.05 * c(),
                        k3: 0.01 * c(),
                        k4: 0.1 * c(),
                        k5: 0.02 * c(),
                        k6: 0.005 * c(),
                        p1: 0.01 * c(),
                        p2: 0.01 * c(),
                        s1: 0.005 * c(),
                        s2: 0.001 * c(),
                        s3: 0.005 * c(),
                        s4: 0.001 * c(),
                        ..Distortion::NONE
                    },
                    2 => Distortion { model: LensModel::Fisheye, k1: 0.05 * c(), k2: 0.01 * c(), k3: 0.002 * c(), k4: 0.0005 * c(), ..Distortion::NONE },
                    3 => Distortion {
                        model: LensModel::Fisheye,
                        k1: 0.05 * c(),
                        k2: 0.01 * c(),
                        k3: 0.002 * c(),
                        k4: 0.0005 * c(),
                        p1: 0.002 * c(),
                        p2: 0.002 * c(),
                        s1: 0.002 * c(),
                        s3: 0.002 * c(),
                        ..Distortion::NONE
                    },
                    _ => Distortion {
                        model: LensModel::Fisheye624,
                        k1: 0.05 * c(),
                        k2: 0.01 * c(),
                        k3: 0.002 * c(),
                        k4: 0.0005 * c(),
                        k5: 0.0001 * c(),
                        k6: 0.00002 * c(),
                        p1: 0.002 * c(),
                        p2: 0.002 * c(),
                        s1: 0.002 * c(),
                        s2: 0.0005 * c(),
                        s3: 0.002 * c(),
                        s4: 0.0005 * c(),
                        ..Distortion::NONE
                    },
                }
            })
            .collect::<Vec<_>>()
            .into_iter()
            // Drawn after the others, so that theirs stay the draws they were.
            .chain((0..10).map(|_| Distortion { model: LensModel::Division, k1: rng.gen_range(-0.2..0.2), ..Distortion::NONE }))
            .collect::<Vec<_>>()
            .into_iter()
            .chain((0..10).map(|_| Distortion::eucm(rng.gen_range(0.0..1.0), rng.gen_range(0.5..2.0))))
            .collect()
    }

    /// `undistort_dir` inverts `distort` (and `project`) over the field of view such lenses have:
    /// the radial–tangential model out to 40° off the axis, the fisheyes out to 100°, past a
    /// hemisphere.
    #[test]
    fn undistorting_inverts_the_lens() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for lens in lenses(&mut rng) {
            let max_theta: f64 = if lens.model.is_fisheye() { 100f64.to_radians() } else { 40f64.to_radians() };
            for _ in 0..200 {
                let (theta, phi) = (rng.gen_range(0.0..max_theta), rng.gen_range(-3.2f64..3.2));
                let p = [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()];
                let (xd, yd) = lens.project(p).unwrap();
                if theta < 80f64.to_radians() {
                    let (dx, dy) = lens.distort(p[0] / p[2], p[1] / p[2]);
                    assert!((dx - xd).abs() + (dy - yd).abs() < 1e-12, "{lens:?}: distort and project agree");
                }
                let d = lens.undistort_dir(xd, yd).unwrap_or_else(|| panic!("{lens:?} at θ {theta}"));
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                assert!((0..3).all(|a| (d[a] / n - p[a]).abs() < 1e-9), "{lens:?}: {d:?} against {p:?}");
                if !lens.model.unit_directions() {
                    assert_eq!(d[2], 1.0, "z = 1");
                } else {
                    assert!((n - 1.0).abs() < 1e-12, "a fisheye's direction is a unit vector");
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
        // The same fold from a rational lens's denominator: r / (1 + 0.5 r²) peaks at r = √2.
        let rational = Distortion { k4: 0.5, ..Distortion::NONE };
        assert!(rational.undistort_dir(0.6, 0.0).is_some() && rational.undistort_dir(0.8, 0.0).is_none());
        for model in [LensModel::Fisheye, LensModel::Fisheye624] {
            let fish = Distortion { model, ..Distortion::NONE };
            assert!(fish.undistort_dir(3.0, 0.0).is_some_and(|d| d[2] < -0.98), "θ = 3 looks almost backwards");
            assert!(fish.undistort_dir(3.2, 0.0).is_none(), "past π");
            assert!(fish.project([0.0, 0.0, -1.0]).is_none());
            assert_eq!(fish.project([1.0, 0.0, 0.0]).map(|(x, _)| x), Some(std::f64::consts::FRAC_PI_2));
        }
        assert_eq!(Distortion::NONE.undistort_dir(0.3, -0.7), Some([0.3, -0.7, 1.0]));
        assert!(barrel.project([0.1, 0.0, 0.0]).is_none());
        // The division model with k1 > 0 images nothing past ρ = 1/(2√k1) (1.118 for 0.2), and its
        // distorted radius peaks at 1/√k1 there (2.236): past it, no direction.
        let division = Distortion { model: LensModel::Division, k1: 0.2, ..Distortion::NONE };
        assert!(division.project([1.1, 0.0, 1.0]).is_some() && division.project([1.2, 0.0, 1.0]).is_none());
        assert!(division.undistort_dir(2.2, 0.0).is_some() && division.undistort_dir(2.3, 0.0).is_none());
        // With k1 < 0 (barrel) every point is imaged, and the closed form inverts up to
        // 1/√(−k1), where 1 + k1·ρ_d² reaches 0.
        let barrel_division = Distortion { model: LensModel::Division, k1: -0.25, ..Distortion::NONE };
        assert!(barrel_division.undistort_dir(1.9, 0.0).is_some() && barrel_division.undistort_dir(2.0, 0.0).is_none());
        // EUCM with α > ½ sees past 90°: a point 110° off its axis comes back from its image;
        // one straight behind the camera has none, nor has a point past the image's rim
        // (r² > 1/((2α − 1)·β)).
        let eucm = Distortion::eucm(0.6, 1.2);
        let p = [110f64.to_radians().sin(), 0.0, 110f64.to_radians().cos()];
        let (x, y) = eucm.project(p).unwrap();
        let d = eucm.undistort_dir(x, y).unwrap();
        assert!((0..3).all(|a| (d[a] - p[a]).abs() < 1e-9) && d[2] < 0.0, "{d:?}");
        assert!(eucm.project([0.0, 0.0, -1.0]).is_none());
        let rim = (1.0 / (0.2 * 1.2f64)).sqrt();
        assert!(eucm.undistort_dir(0.99 * rim, 0.0).is_some() && eucm.undistort_dir(1.01 * rim, 0.0).is_none());
        // α = 0 is a pinhole.
        let (x, y) = Distortion::eucm(0.0, 1.0).project([0.3, -0.2, 2.0]).unwrap();
        assert!((x - 0.15).abs() < 1e-15 && (y + 0.1).abs() < 1e-15);
        let (x, _) = barrel_division.project([40.0, 0.0, 1.0]).unwrap();
        assert!(x < 2.0 && (x / (1.0 - 0.25 * x * x) - 40.0).abs() < 1e-9, "{x}");
    }

    /// The FOV lens's radial factor near its axis, where it switches to the series, agrees with
    /// the closed form on either side, and both slopes with the factor's central differences.
    #[test]
    fn the_fov_series_meets_the_closed_form() {
        let lens = Distortion::fov(1.1);
        let c = 2.0 * 0.55f64.tan();
        let edge = 1e-4 / (c * c);
        for r2 in [0.5 * edge, 0.999 * edge, 1.001 * edge, 2.0 * edge] {
            let (r, dr) = lens.fov_radial(r2);
            let rho = r2.sqrt();
            let closed = (c * rho).atan() / (rho * 1.1);
            assert!((r - closed).abs() < 1e-13, "{r} against {closed} at ρ² {r2}");
            let h = 1e-3 * edge;
            let fd = (lens.fov_radial(r2 + h).0 - lens.fov_radial(r2 - h).0) / (2.0 * h);
            assert!((dr - fd).abs() < 1e-6 * dr.abs(), "{dr} against {fd} at ρ² {r2}");
        }
        assert_eq!(Distortion::fov(0.0).distort(0.3, 0.4), (0.3, 0.4), "ω → 0 is the pinhole");
        assert!(lens.undistort_dir(1.6 / 1.1, 0.0).is_none(), "ρ_d·ω past a right angle");
    }

    /// Each stage's Jacobian against central differences, for every model and each stage
    /// alone or both together.
    #[test]
    fn the_jacobian_is_the_derivative() {
        /// A stage: the distorted point and its Jacobian.
        type Stage = fn(&Distortion, f64, f64) -> ((f64, f64), [[f64; 2]; 2]);
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        for lens in lenses(&mut rng) {
            let stages: [Stage; 3] =
                [Distortion::stage::<true, false>, Distortion::stage::<false, true>, Distortion::stage::<true, true>];
            for stage in stages {
                let (x, y) = (rng.gen_range(-0.8..0.8), rng.gen_range(-0.8..0.8));
                let (_, j) = stage(&lens, x, y);
                let h = 1e-6;
                let f = |x, y| stage(&lens, x, y).0;
                let dx = |f: (f64, f64), g: (f64, f64)| [(f.0 - g.0) / (2.0 * h), (f.1 - g.1) / (2.0 * h)];
                let cx = dx(f(x + h, y), f(x - h, y));
                let cy = dx(f(x, y + h), f(x, y - h));
                for (got, want) in [(j[0][0], cx[0]), (j[1][0], cx[1]), (j[0][1], cy[0]), (j[1][1], cy[1])] {
                    assert!((got - want).abs() < 1e-7, "{lens:?}: {got} against {want}");
                }
            }
        }
    }

    /// The models against the formulas of the tools that calibrate them, written out here in
    /// their own names and orders: OpenCV's 12-coefficient model (`cv::projectPoints`),
    /// COLMAP's `THIN_PRISM_FISHEYE` (`ThinPrismFisheyeModel::Distortion`: tangential and
    /// thin-prism terms on the equidistant point, `sx1`, `sy1`), and nerfstudio's
    /// `fisheye624_project` (`k0..k5`, `p0` with `r² + 2x²`, `p1`, `s0..s3`, all on the
    /// radially distorted point).
    #[test]
    fn the_models_are_the_calibration_tools() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        for _ in 0..50 {
            let mut c = |s: f64| s * rng.gen_range(-1.0..1.0);
            let k: [f64; 12] = std::array::from_fn(|_| c(0.05));
            let (x, y) = (c(0.7), c(0.7));
            let close = |a: (f64, f64), b: (f64, f64)| (a.0 - b.0).abs() + (a.1 - b.1).abs() < 1e-13;

            // OpenCV: distCoeffs (k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4).
            let [k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4] = k;
            let r2 = x * x + y * y;
            let radial = (1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2) / (1.0 + k4 * r2 + k5 * r2 * r2 + k6 * r2 * r2 * r2);
            let opencv = (
                x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r2 * r2,
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r2 * r2,
            );
            let ours = Distortion { k1, k2, k3, k4, k5, k6, p1, p2, s1, s2, s3, s4, ..Distortion::NONE };
            assert!(close(ours.distort(x, y), opencv), "OpenCV's model");

            // COLMAP's THIN_PRISM_FISHEYE: params (k1, k2, p1, p2, k3, k4, sx1, sy1).
            let [k1, k2, p1, p2, k3, k4, sx1, sy1, ..] = k;
            let r = (x * x + y * y).sqrt();
            let theta = r.atan();
            let (uu, vv) = (theta * x / r, theta * y / r);
            let t2 = uu * uu + vv * vv;
            let radial = k1 * t2 + k2 * t2 * t2 + k3 * t2 * t2 * t2 + k4 * t2 * t2 * t2 * t2;
            let du = uu * radial + 2.0 * p1 * uu * vv + p2 * (t2 + 2.0 * uu * uu) + sx1 * t2;
            let dv = vv * radial + 2.0 * p2 * uu * vv + p1 * (t2 + 2.0 * vv * vv) + sy1 * t2;
            let ours = Distortion { model: LensModel::Fisheye, k1, k2, k3, k4, p1, p2, s1: sx1, s3: sy1, ..Distortion::NONE };
            assert!(close(ours.distort(x, y), (uu + du, vv + dv)), "COLMAP's THIN_PRISM_FISHEYE");

            // nerfstudio's fisheye624_project: params (k0..k5, p0, p1, s0..s3).
            let [k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3] = k;
            let th_k = theta + k0 * theta.powi(3) + k1 * theta.powi(5) + k2 * theta.powi(7) + k3 * theta.powi(9) + k4 * theta.powi(11) + k5 * theta.powi(13);
            let (xr, yr) = (th_k * x / r, th_k * y / r);
            let rd2 = xr * xr + yr * yr;
            let aria = (
                xr + (2.0 * xr * xr + rd2) * p0 + 2.0 * xr * yr * p1 + s0 * rd2 + s1 * rd2 * rd2,
                yr + (2.0 * yr * yr + rd2) * p1 + 2.0 * xr * yr * p0 + s2 * rd2 + s3 * rd2 * rd2,
            );
            let ours = Distortion::from_coefficients(LensModel::Fisheye624, [k0, k1, k2, k3, k4, k5, p1, p0, s0, s1, s2, s3]);
            assert!(close(ours.distort(x, y), aria), "nerfstudio's FISHEYE624");

            // COLMAP's FOV: factor atan(r·2·tan(ω/2)) / (r·ω), its closed form.
            let omega = 0.9 + c(0.6);
            let factor = (r * 2.0 * (omega / 2.0).tan()).atan() / (r * omega);
            assert!(close(Distortion::fov(omega).distort(x, y), (x * factor, y * factor)), "COLMAP's FOV");
        }
    }
}
