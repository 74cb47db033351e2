//! Cameras (pinhole, or through a lens), camera-to-world poses (OpenGL convention),
//! pixel-to-ray generation and axis-aligned bounding boxes.
//!
//! Conventions (those of the Blender / NeRF-synthetic format, nerf-pytorch and nerfstudio):
//! - A [`Camera`] holds a camera-to-world rotation and the camera centre. Camera axes are OpenGL's:
//!   the camera looks down its local −z, +y is up, +x is right.
//! - Image coordinates `(u, v)`: `u` grows with the column (to the right), `v` with the row
//!   (downwards). The camera-space direction through `(u, v)` is
//!   `[(u − cx)/fx, −(v − cy)/fy, −1]`, exactly as nerf-pytorch's `get_rays`.
//! - [`PixelConvention`] says where pixel `(col, row)` sits: at its centre `(col + ½, row + ½)`
//!   (the default, as in instant-ngp and nerfstudio) or at the integer corner `(col, row)`
//!   (nerf-pytorch).
//! - [`Ndc`] warps the rays of a forward-facing scene into NeRF's normalised device coordinates.
//! - [`Ray::dir`] is always unit length; [`Camera::pixel_dir_unnormalized`] gives the
//!   nerf-pytorch direction whose camera-space z component is −1.
//! - [`pose`] refines the training cameras: a per-view translation and rotation applied to the
//!   view's rays, with its backward pass (nerfstudio's camera optimizer).
//! - A camera may carry a lens ([`lens`]: OpenCV's radial–tangential or fisheye distortion): its
//!   pixels' rays are then the directions the lens saw, found by inverting the distortion.

pub mod exposure;
pub mod lens;
mod ndc;
pub mod pose;

pub use exposure::{Exposure, ThinLens};
pub use lens::{Distortion, LensModel};

pub use glam;
pub use ndc::Ndc;
use glam::{Mat3, Vec3};
use serde::{Deserialize, Serialize};

/// Errors of camera construction.
#[derive(Debug, thiserror::Error)]
pub enum RayError {
    /// A value of the camera-to-world matrix is NaN or infinite.
    #[error("non-finite value in camera pose")]
    NonFinitePose,
    /// The camera-to-world matrix does not have 3 or 4 rows.
    #[error("camera pose must have 3 or 4 rows of 4 values, got {rows} rows")]
    BadPoseShape {
        /// Number of rows that were given.
        rows: usize,
    },
    /// The camera-to-world matrix's rotation block is degenerate: an axis of (near) zero length, or
    /// three axes that do not span 3-D space, so that pixels would have no ray direction.
    #[error(
        "degenerate camera pose: its rotation block has axis lengths {lengths:?} and determinant {det:.3e}; \
         the three axes must span 3-D space"
    )]
    DegeneratePose {
        /// Lengths of the three axes (columns of the rotation block).
        lengths: [f32; 3],
        /// Determinant of the rotation block.
        det: f32,
    },
    /// Intrinsics that cannot describe a pinhole camera (zero size, non-positive or non-finite focal).
    #[error("invalid camera intrinsics: {0}")]
    BadIntrinsics(String),
}

/// Pinhole intrinsics in pixels: image size, focal lengths and principal point.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Horizontal focal length in pixels.
    pub fx: f32,
    /// Vertical focal length in pixels.
    pub fy: f32,
    /// Principal point, horizontal (pixels from the left image edge).
    pub cx: f32,
    /// Principal point, vertical (pixels from the top image edge).
    pub cy: f32,
}

impl Intrinsics {
    /// Blender: `f = 0.5·W / tan(0.5·camera_angle_x)` computed in f64 (then rounded to f32),
    /// `fx = fy = f`, `cx = W/2`, `cy = H/2`.
    pub fn from_fov_x(width: u32, height: u32, camera_angle_x: f64) -> Self {
        let f = (0.5 * width as f64 / (0.5 * camera_angle_x).tan()) as f32;
        Self {
            width,
            height,
            fx: f,
            fy: f,
            cx: width as f32 * 0.5,
            cy: height as f32 * 0.5,
        }
    }

    /// Downscaled by an integer factor `k`: `W/k`, `H/k` (integer division), focal lengths and
    /// principal point divided by `k` — nerf-pytorch's `half_res` for `k = 2`.
    ///
    /// # Panics
    /// If `k == 0` (programmer error; validate user input before calling).
    pub fn downscaled(&self, k: u32) -> Self {
        assert!(k >= 1, "downscale factor must be at least 1");
        let kf = k as f32;
        Self {
            width: self.width / k,
            height: self.height / k,
            fx: self.fx / kf,
            fy: self.fy / kf,
            cx: self.cx / kf,
            cy: self.cy / kf,
        }
    }

    /// Horizontal field of view in radians, `2·atan(0.5·W / fx)` (computed in f64); the inverse
    /// of [`Intrinsics::from_fov_x`].
    pub fn fov_x(&self) -> f64 {
        2.0 * (0.5 * self.width as f64 / self.fx as f64).atan()
    }

    /// Checks that the size is non-zero and the focal lengths and principal point are finite
    /// (focal lengths positive).
    pub fn validate(&self) -> Result<(), RayError> {
        if self.width == 0 || self.height == 0 {
            return Err(RayError::BadIntrinsics(format!(
                "image size {}x{} is empty",
                self.width, self.height
            )));
        }
        if !(self.fx.is_finite() && self.fy.is_finite() && self.fx > 0.0 && self.fy > 0.0) {
            return Err(RayError::BadIntrinsics(format!(
                "focal lengths ({}, {}) must be finite and positive",
                self.fx, self.fy
            )));
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(RayError::BadIntrinsics(format!(
                "principal point ({}, {}) must be finite",
                self.cx, self.cy
            )));
        }
        Ok(())
    }
}

/// Where pixel `(col, row)` sits in continuous image coordinates.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PixelConvention {
    /// Pixel `(i, j)` → `(i + 0.5, j + 0.5)`: the pixel centre (instant-ngp, nerfstudio).
    #[default]
    Center,
    /// Pixel `(i, j)` → `(i, j)`: nerf-pytorch's `get_rays` (no half-pixel offset).
    Integer,
}

impl PixelConvention {
    /// The offset added to integer pixel indices: 0.5 for [`Center`](Self::Center), 0 for
    /// [`Integer`](Self::Integer).
    #[inline]
    pub fn offset(self) -> f32 {
        match self {
            PixelConvention::Center => 0.5,
            PixelConvention::Integer => 0.0,
        }
    }

    /// `spp` points of a pixel to render it with (supersampling), as offsets added to integer
    /// pixel indices. One point is the convention's ([`offset`](Self::offset) on both axes). More
    /// form a rank-1 lattice over the pixel's unit square around that point: point `k` of `n` at
    /// `((k + ½)/n, ((k·a mod n) + ½)/n)`, `a` the integer nearest `n/φ` that is coprime to `n`,
    /// so each axis has one point in each of its `n` strata (the mean is the pixel's centre
    /// exactly) and the points spread over the square (a Fibonacci lattice where `n` is a
    /// Fibonacci number). The same count always gives the same points. The mean of a pixel's
    /// renders at these points estimates the colour its area integrates, which the anti-aliased
    /// ground truth of synthetic scenes holds (instant-ngp scores test views with 8 samples per
    /// pixel).
    pub fn sample_offsets(self, spp: usize) -> Vec<[f32; 2]> {
        self.sample_offsets_filtered(spp, PixelFilter::Box)
    }

    /// [`sample_offsets`](Self::sample_offsets) placed by a pixel filter: each axis of the
    /// lattice is warped through the inverse of the filter's cumulative distribution, so the
    /// plain mean of the renders at these points estimates the filter-weighted integral of the
    /// image around the pixel's point (Cycles' film filter, which is separable in the same way).
    /// [`PixelFilter::Box`] gives the unit square of [`sample_offsets`](Self::sample_offsets).
    /// Every axis keeps one point in each of its `n` strata of filter weight, the points are
    /// symmetric about the pixel's point, and one point is that point whatever the filter.
    pub fn sample_offsets_filtered(self, spp: usize, filter: PixelFilter) -> Vec<[f32; 2]> {
        let o = self.offset();
        if spp <= 1 {
            return vec![[o, o]];
        }
        (0..spp)
            .map(|k| {
                let [x, y] = lattice_point(k, spp);
                [(o as f64 + filter.inverse_cdf(x)) as f32, (o as f64 + filter.inverse_cdf(y)) as f32]
            })
            .collect()
    }
}

/// Point `k` of the `n`-point rank-1 lattice over the unit square, `((k + ½)/n, ((k·a mod n) +
/// ½)/n)` with `a` the integer nearest `n/φ` that is coprime to `n` (a Fibonacci lattice where `n`
/// is a Fibonacci number): each axis has one point in each of its `n` strata, and the points
/// spread over the square ([`PixelConvention::sample_offsets`], [`exposure::pass_sample`]).
pub(crate) fn lattice_point(k: usize, n: usize) -> [f64; 2] {
    let gcd = |mut a: usize, mut b: usize| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    let target = n as f64 / 1.618_033_988_749_895;
    let a = (1..n).filter(|&a| gcd(a, n) == 1).min_by(|&x, &y| (x as f64 - target).abs().total_cmp(&(y as f64 - target).abs())).unwrap_or(1);
    [(k as f64 + 0.5) / n as f64, (((k * a) % n) as f64 + 0.5) / n as f64]
}

/// The filter a rendered pixel integrates the image plane with when it is supersampled
/// ([`PixelConvention::sample_offsets_filtered`]; `eval_filter` of the training config).
/// Separable: the 2-D weight is the product of one 1-D profile per axis, in pixels from the
/// pixel's point.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum PixelFilter {
    /// Equal weight over the pixel's unit square (the area the pixel covers; instant-ngp's
    /// supersampling).
    #[default]
    Box,
    /// The 4-term Blackman–Harris window, Blender Cycles' film filter by default, the renderer of
    /// the NeRF synthetic scenes' ground truth. `width` is Cycles' `filter_width` (1.5 pixels by
    /// default), which Cycles' filter table doubles for this window: it spans `±width` pixels
    /// around the pixel's point. At 1.5 its standard deviation is 0.42 px against the box's
    /// 0.29 px, and a pixel takes in part of its neighbours.
    BlackmanHarris {
        /// Cycles' `filter_width` in pixels (its default 1.5): the window's half-width.
        width: f32,
    },
}

/// The 4-term Blackman–Harris coefficients (Cycles' `filter_func_blackman_harris`).
const BLACKMAN_HARRIS: [f64; 4] = [0.35875, 0.48829, 0.14128, 0.01168];

impl PixelFilter {
    /// Checks the filter's parameters: a Blackman–Harris width must be finite and in (0, 8]
    /// pixels.
    pub fn validate(self) -> Result<(), String> {
        match self {
            PixelFilter::Box => Ok(()),
            PixelFilter::BlackmanHarris { width } => {
                if width.is_finite() && width > 0.0 && width <= 8.0 {
                    Ok(())
                } else {
                    Err(format!("a blackman_harris pixel filter's width must be in (0, 8] pixels, got {width}"))
                }
            }
        }
    }

    /// The filter's 1-D weight at `x` pixels from the pixel's point, normalised to integrate to
    /// one.
    pub fn weight(self, x: f64) -> f64 {
        match self {
            PixelFilter::Box => {
                if x.abs() < 0.5 {
                    1.0
                } else {
                    0.0
                }
            }
            PixelFilter::BlackmanHarris { width } => {
                // The window over [−width, width] (Cycles' table doubles `filter_width`).
                let w = 2.0 * width as f64;
                if x.abs() >= 0.5 * w {
                    return 0.0;
                }
                let v = std::f64::consts::TAU * (x / w + 0.5);
                let [a0, a1, a2, a3] = BLACKMAN_HARRIS;
                (a0 - a1 * v.cos() + a2 * (2.0 * v).cos() - a3 * (3.0 * v).cos()) / (a0 * w)
            }
        }
    }

    /// The offset in pixels below which a fraction `u` ∈ (0, 1) of the filter's 1-D weight lies.
    pub fn inverse_cdf(self, u: f64) -> f64 {
        match self {
            PixelFilter::Box => u - 0.5,
            PixelFilter::BlackmanHarris { width } => {
                // The CDF over s = x/(2·width) + ½ ∈ [0, 1] in closed form, inverted by
                // bisection (it is increasing; 60 halvings reach f64's resolution).
                let [a0, a1, a2, a3] = BLACKMAN_HARRIS;
                let tau = std::f64::consts::TAU;
                let cdf = |s: f64| {
                    (a0 * s - a1 * (tau * s).sin() / tau + a2 * (2.0 * tau * s).sin() / (2.0 * tau)
                        - a3 * (3.0 * tau * s).sin() / (3.0 * tau))
                        / a0
                };
                let (mut lo, mut hi) = (0.0f64, 1.0f64);
                for _ in 0..60 {
                    let mid = 0.5 * (lo + hi);
                    if cdf(mid) < u {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                (0.5 * (lo + hi) - 0.5) * 2.0 * width as f64
            }
        }
    }
}

/// How a rendered frame maps its pixels to directions (nerfstudio's `camera_type` of a camera
/// path). Training views are always [`Perspective`](Self::Perspective).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Projection {
    /// A pinhole camera with the camera's intrinsics ([`Camera::rays_into`]).
    #[default]
    Perspective,
    /// A 360° panorama ([`Camera::equirect_rays_into`]): longitude across the width, latitude
    /// down the height; the intrinsics give only the image size (usually `W = 2·H`).
    Equirectangular,
    /// An equidistant fisheye ([`Camera::fisheye_dir`]): the angle from the optical axis grows
    /// linearly with the distance from the principal point, in units of the focal length.
    Fisheye,
}

impl Projection {
    /// nerfstudio's name of the camera type: `"perspective"` or `"equirectangular"`.
    pub fn name(self) -> &'static str {
        match self {
            Projection::Perspective => "perspective",
            Projection::Equirectangular => "equirectangular",
            Projection::Fisheye => "fisheye",
        }
    }
}

/// A ray `origin + t·dir`; `dir` is unit length.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    /// Ray origin (the camera centre for camera rays).
    pub origin: Vec3,
    /// Unit direction.
    pub dir: Vec3,
}

impl Ray {
    /// The point at parameter `t`.
    #[inline]
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + t * self.dir
    }
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    /// Minimum corner.
    pub min: [f32; 3],
    /// Maximum corner.
    pub max: [f32; 3],
}

impl Aabb {
    /// The cube `[−half, half]³`.
    pub fn cube(half: f32) -> Self {
        Self {
            min: [-half; 3],
            max: [half; 3],
        }
    }

    /// The centre `(min + max)/2`.
    pub fn center(&self) -> [f32; 3] {
        std::array::from_fn(|a| 0.5 * (self.min[a] + self.max[a]))
    }

    /// The side lengths `max − min`.
    pub fn extent(&self) -> [f32; 3] {
        std::array::from_fn(|a| self.max[a] - self.min[a])
    }

    /// Whether `p` lies inside the closed box.
    pub fn contains(&self, p: [f32; 3]) -> bool {
        (0..3).all(|a| p[a] >= self.min[a] && p[a] <= self.max[a])
    }

    /// Slab test. If the ray `origin + t·dir` (t ≥ 0) hits the box, returns
    /// `(t_enter.max(0), t_exit)`; an origin inside the box gives `t_enter = 0`. `dir` need not be
    /// unit length (the `t` are in units of `dir`); zero components are handled (the ray is then
    /// parallel to that slab and hits only if the origin lies between its planes). A box entirely
    /// behind the origin, a miss, or NaN input gives `None`.
    pub fn intersect(&self, origin: [f32; 3], dir: [f32; 3]) -> Option<(f32, f32)> {
        if origin.iter().chain(dir.iter()).any(|v| v.is_nan()) {
            return None;
        }
        let mut t0 = 0.0f32;
        let mut t1 = f32::INFINITY;
        for a in 0..3 {
            let (o, d) = (origin[a], dir[a]);
            if d == 0.0 {
                // Parallel to the slab; `!(..)` also rejects NaN.
                if !(o >= self.min[a] && o <= self.max[a]) {
                    return None;
                }
                continue;
            }
            let inv = 1.0 / d;
            let ta = (self.min[a] - o) * inv;
            let tb = (self.max[a] - o) * inv;
            let (near, far) = if ta <= tb { (ta, tb) } else { (tb, ta) };
            t0 = t0.max(near);
            t1 = t1.min(far);
            if t0 > t1 {
                return None;
            }
        }
        Some((t0, t1))
    }
}

/// A camera: intrinsics, the lens's distortion (none for a pinhole camera) and the
/// camera-to-world pose (OpenGL axes: looks down −z, +y up).
#[derive(Clone, Copy, Debug)]
pub struct Camera {
    /// Pinhole intrinsics (of the photo as stored: a lens's distortion acts on the normalised
    /// coordinates between them and the ray, [`lens`]).
    pub intrinsics: Intrinsics,
    /// Camera-to-world rotation (columns: the camera's x, y, z axes in world coordinates).
    pub rotation: Mat3,
    /// Camera centre in world coordinates.
    pub position: Vec3,
    /// The lens ([`Distortion::NONE`]: a pinhole camera). A pixel's ray is the direction the
    /// lens saw at it ([`Camera::camera_dir`]).
    pub distortion: Distortion,
}

impl Camera {
    /// The smallest `|det R| / (|x|·|y|·|z|)` [`Camera::from_c2w`] accepts for a rotation block
    /// `R` with axes `x, y, z`: the volume spanned by the unit axes (1 when they are orthogonal,
    /// 0 when they are coplanar). 10⁻³ lets through any pose a real exporter writes (rounding,
    /// a uniform scale) and rejects a zero or collapsed block, whose rays would have no direction.
    pub const MIN_AXIS_VOLUME: f32 = 1e-3;

    /// From the Blender/nerfstudio 4×4 (or top 3×4) row-major camera-to-world matrix
    /// (`transform_matrix`): rotation = the top-left 3×3 block, position = the last column.
    /// `Err(RayError::NonFinitePose)` if any value is not finite, `Err(RayError::BadPoseShape)`
    /// if there are not 3 or 4 rows, `Err(RayError::DegeneratePose)` if the rotation block's axes
    /// do not span space (see [`Camera::MIN_AXIS_VOLUME`]). The bottom row of a 4×4 matrix is not
    /// used.
    pub fn from_c2w(intrinsics: Intrinsics, c2w: &[[f32; 4]]) -> Result<Self, RayError> {
        if c2w.len() != 3 && c2w.len() != 4 {
            return Err(RayError::BadPoseShape { rows: c2w.len() });
        }
        if c2w.iter().flatten().any(|v| !v.is_finite()) {
            return Err(RayError::NonFinitePose);
        }
        let m = |r: usize, c: usize| c2w[r][c];
        let rotation = Mat3::from_cols(
            Vec3::new(m(0, 0), m(1, 0), m(2, 0)),
            Vec3::new(m(0, 1), m(1, 1), m(2, 1)),
            Vec3::new(m(0, 2), m(1, 2), m(2, 2)),
        );
        let position = Vec3::new(m(0, 3), m(1, 3), m(2, 3));
        // A rotation may carry a uniform scale (some exporters write one); what must hold is
        // that the axes span space. |det| / (|x|·|y|·|z|) is the volume of the parallelepiped
        // of the unit axes: 1 for orthogonal axes, 0 for coplanar ones.
        let lengths = [rotation.x_axis.length(), rotation.y_axis.length(), rotation.z_axis.length()];
        let det = rotation.determinant();
        let volume = lengths.iter().product::<f32>();
        if !(volume > 0.0 && volume.is_finite() && det.abs() >= Self::MIN_AXIS_VOLUME * volume) {
            return Err(RayError::DegeneratePose { lengths, det });
        }
        Ok(Self {
            intrinsics,
            rotation,
            position,
            distortion: Distortion::NONE,
        })
    }

    /// The rotation of the camera's axes as a unit quaternion, from the rotation block
    /// orthonormalised (file poses carry rounding, or a uniform scale): the z axis kept, x made
    /// orthogonal to it and to y.
    pub fn orientation(&self) -> glam::Quat {
        let z = self.rotation.z_axis.try_normalize().unwrap_or(Vec3::Z);
        let x = self.rotation.y_axis.cross(z).try_normalize().unwrap_or(Vec3::X);
        glam::Quat::from_mat3(&Mat3::from_cols(x, z.cross(x), z))
    }

    /// The same camera with the lens `distortion`.
    pub fn with_distortion(self, distortion: Distortion) -> Self {
        Self { distortion, ..self }
    }

    /// The same camera without its lens: the pinhole camera of its intrinsics (what novel views
    /// along a path through the training cameras are rendered with).
    pub fn pinhole(self) -> Self {
        self.with_distortion(Distortion::NONE)
    }

    /// The direction, in camera axes (OpenGL: x right, y up, −z forward), of continuous image
    /// coordinates `(u, v)`, computed in f64: the pinhole's `[(u−cx)/fx, −(v−cy)/fy, −1]`, or
    /// through a lens the direction it saw there ([`Distortion::undistort_iterate`], with z = −1
    /// for the radial–tangential model, unit for the fisheye, whose z may be positive past 90°).
    pub fn camera_dir(&self, u: f64, v: f64) -> [f64; 3] {
        let k = &self.intrinsics;
        let (xd, yd) = ((u - k.cx as f64) / k.fx as f64, (v - k.cy as f64) / k.fy as f64);
        let [x, y, z] = if self.distortion.is_identity() { [xd, yd, 1.0] } else { self.distortion.undistort_iterate(xd, yd).0 };
        [x, -y, -z]
    }

    /// The point `p` (world coordinates) in OpenCV's camera axes (x right, y down, z forward).
    pub fn to_opencv(&self, p: Vec3) -> [f64; 3] {
        let d = p - self.position;
        let axis = |c: usize| self.rotation.col(c).dot(d) as f64;
        [axis(0), -axis(1), -axis(2)]
    }

    /// Continuous image coordinates `(u, v)` where the camera images the world point `p`
    /// (through its lens, [`Distortion::project`]), wherever that lands, in the image or not;
    /// `None` where it images nothing (behind a pinhole camera, or on a fisheye's backward
    /// axis).
    pub fn project(&self, p: Vec3) -> Option<(f64, f64)> {
        self.project_opencv(self.to_opencv(p))
    }

    /// [`Camera::project`] of a point already in OpenCV's camera axes ([`Camera::to_opencv`]).
    pub fn project_opencv(&self, c: [f64; 3]) -> Option<(f64, f64)> {
        let k = &self.intrinsics;
        let (xd, yd) = self.distortion.project(c)?;
        Some((k.fx as f64 * xd + k.cx as f64, k.fy as f64 * yd + k.cy as f64))
    }

    /// The row-major 4×4 camera-to-world matrix (bottom row `[0, 0, 0, 1]`), the inverse of
    /// [`Camera::from_c2w`].
    pub fn c2w(&self) -> [[f32; 4]; 4] {
        let r = &self.rotation;
        let p = self.position;
        [
            [r.x_axis.x, r.y_axis.x, r.z_axis.x, p.x],
            [r.x_axis.y, r.y_axis.y, r.z_axis.y, p.y],
            [r.x_axis.z, r.y_axis.z, r.z_axis.z, p.z],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }

    /// Whether the ball of radius `r` about `c` (world coordinates) may show in the image
    /// ([`Frustum::sees_sphere`]; for many balls, build the [`frustum`](Self::frustum) once).
    pub fn sees_sphere(&self, c: Vec3, r: f32) -> bool {
        self.frustum().sees_sphere(c, r)
    }

    /// The region of space the image shows, for [`Frustum::sees_sphere`]. A pinhole camera's is
    /// bounded by the four planes through its centre and the image edges. Through a lens, the
    /// image's border is traced back through the lens (a point a pixel along it): a
    /// radial–tangential lens gets the planes that bound those directions (the region the lens
    /// sees is bounded by its border's directions), a fisheye, or a lens that sees past 89°
    /// off its axis, the cone about the axis that holds them; both widened by a pixel.
    pub fn frustum(&self) -> Frustum {
        let k = &self.intrinsics;
        let (w, h) = (k.width as f64, k.height as f64);
        let mut shape = FrustumShape::Planes {
            x: [-k.cx / k.fx, (k.width as f32 - k.cx) / k.fx],
            y: [-(k.height as f32 - k.cy) / k.fy, k.cy / k.fy],
        };
        if !self.distortion.is_identity() {
            let border = (0..=k.width).flat_map(|i| [(i as f64, 0.0), (i as f64, h)]).chain((0..=k.height).flat_map(|j| [(0.0, j as f64), (w, j as f64)]));
            let (mut x, mut y, mut angle) = ([f64::INFINITY, f64::NEG_INFINITY], [f64::INFINITY, f64::NEG_INFINITY], 0.0f64);
            for (u, v) in border {
                let d = self.camera_dir(u, v);
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                angle = angle.max((-d[2] / n).clamp(-1.0, 1.0).acos());
                let (a, b) = (d[0] / -d[2], d[1] / -d[2]);
                x = [x[0].min(a), x[1].max(a)];
                y = [y[0].min(b), y[1].max(b)];
            }
            // A pixel's angle at the principal point; the planes widen by the slopes it makes there.
            let pixel = 1.0 / k.fx.min(k.fy) as f64;
            shape = if self.distortion.model.is_fisheye() || angle > 89f64.to_radians() {
                FrustumShape::Cone { half_angle: (angle + pixel) as f32 }
            } else {
                let widen = |[lo, hi]: [f64; 2]| [(lo - pixel * (1.0 + lo * lo)) as f32, (hi + pixel * (1.0 + hi * hi)) as f32];
                FrustumShape::Planes { x: widen(x), y: widen(y) }
            };
        }
        Frustum { to_camera: self.rotation.transpose(), position: self.position, shape }
    }

    /// World direction (not normalised) through continuous image coordinates `(u, v)`:
    /// `R·[(u−cx)/fx, −(v−cy)/fy, −1]` for a pinhole camera.
    /// Through a lens: `R·`[`camera_dir`](Self::camera_dir).
    #[inline]
    pub fn dir_at_unnormalized(&self, u: f32, v: f32) -> Vec3 {
        if !self.distortion.is_identity() {
            return self.rotation * Vec3::from_array(self.camera_dir(u as f64, v as f64).map(|c| c as f32));
        }
        let k = &self.intrinsics;
        let d = Vec3::new((u - k.cx) / k.fx, -(v - k.cy) / k.fy, -1.0);
        self.rotation * d
    }

    /// Unnormalised direction exactly as nerf-pytorch `get_rays`: `R·[(u−cx)/fx, −(v−cy)/fy, −1]`
    /// where `(u, v)` are the coordinates of pixel `(col, row)` under `conv`.
    #[inline]
    pub fn pixel_dir_unnormalized(&self, col: u32, row: u32, conv: PixelConvention) -> Vec3 {
        let o = conv.offset();
        self.dir_at_unnormalized(col as f32 + o, row as f32 + o)
    }

    /// Unit-direction ray through pixel `(col, row)` under `conv`.
    #[inline]
    pub fn ray(&self, col: u32, row: u32, conv: PixelConvention) -> Ray {
        let o = conv.offset();
        self.ray_at(col as f32 + o, row as f32 + o)
    }

    /// Unit-direction ray through continuous image coordinates `(u, v)` (`u` along columns, `v`
    /// along rows, `(0, 0)` the top-left corner of the image).
    #[inline]
    pub fn ray_at(&self, u: f32, v: f32) -> Ray {
        Ray {
            origin: self.position,
            dir: self.dir_at_unnormalized(u, v).normalize(),
        }
    }

    /// All rays, row-major (row 0 first), written into flat `origins` / `dirs` (unit) arrays,
    /// each resized to `3·W·H` (their allocations are reused).
    pub fn rays_into(&self, conv: PixelConvention, origins: &mut Vec<f32>, dirs: &mut Vec<f32>) {
        self.par_rays_into(origins, dirs, |col, row| self.ray(col, row, conv).dir);
    }

    /// Every pixel's ray, row-major, into `origins` (the camera centre) and `dirs` (`dir(col,
    /// row)`, already unit length), each resized to `3·W·H`; the rows in parallel.
    fn par_rays_into(&self, origins: &mut Vec<f32>, dirs: &mut Vec<f32>, dir: impl Fn(u32, u32) -> Vec3 + Sync) {
        use rayon::prelude::*;
        let w = self.intrinsics.width as usize;
        let n = w * self.intrinsics.height as usize;
        origins.clear();
        dirs.clear();
        origins.resize(3 * n, 0.0);
        dirs.resize(3 * n, 0.0);
        if n == 0 {
            return;
        }
        let p = self.position.to_array();
        origins.par_chunks_mut(3 * w).for_each(|row| row.chunks_exact_mut(3).for_each(|o| o.copy_from_slice(&p)));
        dirs.par_chunks_mut(3 * w).enumerate().for_each(|(row, out)| {
            for (col, d) in out.chunks_exact_mut(3).enumerate() {
                d.copy_from_slice(&dir(col as u32, row as u32).to_array());
            }
        });
    }
}

/// The region of space a camera's image shows ([`Camera::frustum`]).
#[derive(Clone, Copy, Debug)]
pub struct Frustum {
    to_camera: Mat3,
    position: Vec3,
    shape: FrustumShape,
}

#[derive(Clone, Copy, Debug)]
enum FrustumShape {
    /// `x/depth ∈ x`, `y/depth ∈ y` (camera axes: x right, y up, depth along −z).
    Planes { x: [f32; 2], y: [f32; 2] },
    /// Within `half_angle` of the optical axis (−z).
    Cone { half_angle: f32 },
}

impl Frustum {
    /// Whether the ball of radius `r` about `c` (world coordinates) may show in the image. Between
    /// planes: it lies in front of the camera (depth > −r) and within `r` of the inner side of
    /// each of the four planes. In a cone: it reaches within the cone's half-angle of the axis
    /// (or holds the camera centre). A ball that shows passes; one that passes may still miss
    /// the image near its corners (the test is conservative, as instant-ngp's
    /// `mark_untrained_density_grid`).
    pub fn sees_sphere(&self, c: Vec3, r: f32) -> bool {
        let p = self.to_camera * (c - self.position); // camera axes: x right, y up, −z forward
        let depth = -p.z;
        match self.shape {
            FrustumShape::Planes { x, y } => {
                if depth <= -r {
                    return false;
                }
                // The signed distance to the plane x = a·depth is (x − a·depth)/√(1 + a²).
                let inside = |v: f32, [lo, hi]: [f32; 2]| {
                    (v - hi * depth) / (1.0 + hi * hi).sqrt() <= r && (lo * depth - v) / (1.0 + lo * lo).sqrt() <= r
                };
                inside(p.x, x) && inside(p.y, y)
            }
            FrustumShape::Cone { half_angle } => {
                let dist = p.length();
                if dist <= r {
                    return true;
                }
                let off_axis = (depth / dist).clamp(-1.0, 1.0).acos();
                off_axis <= half_angle + (r / dist).asin()
            }
        }
    }
}

impl Camera {
    /// The unit direction, in camera axes (OpenGL: x right, y up, −z forward), of continuous
    /// image coordinates `(u, v)` of a `width × height` equirectangular panorama, as nerfstudio's
    /// `EQUIRECTANGULAR` camera: with `x = (u − W/2)/(W/2)` and `y = (H/2 − v)/H`, longitude
    /// `θ = −π·x` and polar angle `φ = π·(½ − y)`, the direction
    /// `(−sin θ sin φ, cos φ, −cos θ sin φ)`. The image's centre looks forward, its left and right
    /// edges backward, a quarter of the width from the left edge to the left, the top row up.
    pub fn equirect_dir(width: u32, height: u32, u: f32, v: f32) -> Vec3 {
        let x = (u - 0.5 * width as f32) / (0.5 * width as f32);
        let y = (0.5 * height as f32 - v) / height as f32;
        let (theta, phi) = (-std::f32::consts::PI * x, std::f32::consts::PI * (0.5 - y));
        Vec3::new(-theta.sin() * phi.sin(), phi.cos(), -theta.cos() * phi.sin())
    }

    /// All rays of an equirectangular panorama from this camera's position and orientation
    /// ([`Camera::equirect_dir`] rotated into the world), of the intrinsics' `width × height`,
    /// row-major as [`Camera::rays_into`] writes them.
    pub fn equirect_rays_into(&self, conv: PixelConvention, origins: &mut Vec<f32>, dirs: &mut Vec<f32>) {
        let (w, h) = (self.intrinsics.width, self.intrinsics.height);
        self.camera_rays_into(conv, origins, dirs, |u, v| Self::equirect_dir(w, h, u, v));
    }

    /// Every pixel's ray, row-major, from the camera-axes direction `dir(u, v)` of its point
    /// (rotated into the world and normalised).
    fn camera_rays_into(&self, conv: PixelConvention, origins: &mut Vec<f32>, dirs: &mut Vec<f32>, dir: impl Fn(f32, f32) -> Vec3 + Sync) {
        let off = conv.offset();
        self.world_rays_at(off, off, origins, dirs, |u, v| self.rotation * dir(u, v));
    }

    /// Every pixel's ray, row-major, through the point `(col + ox, row + oy)` of pixel
    /// `(col, row)`, from the world direction `dir(u, v)` there (normalised).
    fn world_rays_at(&self, ox: f32, oy: f32, origins: &mut Vec<f32>, dirs: &mut Vec<f32>, dir: impl Fn(f32, f32) -> Vec3 + Sync) {
        self.par_rays_into(origins, dirs, |col, row| dir(col as f32 + ox, row as f32 + oy).normalize());
    }

    /// The unit direction, in camera axes, of continuous image coordinates `(u, v)` through this
    /// camera's intrinsics as an equidistant fisheye, nerfstudio's `FISHEYE`: with
    /// `x = (u − cx)/fx`, `y = −(v − cy)/fy` and `θ = min(√(x² + y²), π)`, the direction
    /// `(x·sin θ/θ, y·sin θ/θ, −cos θ)` (the optical axis at the principal point; a point `π/2`
    /// focal lengths from it looks sideways).
    pub fn fisheye_dir(&self, u: f32, v: f32) -> Vec3 {
        let k = &self.intrinsics;
        let (x, y) = ((u - k.cx) / k.fx, -(v - k.cy) / k.fy);
        let r = (x * x + y * y).sqrt();
        if r == 0.0 {
            return Vec3::NEG_Z;
        }
        let theta = r.min(std::f32::consts::PI);
        let s = theta.sin() / r;
        Vec3::new(x * s, y * s, -theta.cos())
    }

    /// The rays of a frame of `projection` ([`rays_into`](Self::rays_into),
    /// [`equirect_rays_into`](Self::equirect_rays_into), or the fisheye's
    /// [`fisheye_dir`](Self::fisheye_dir)), row-major.
    pub fn frame_rays_into(&self, projection: Projection, conv: PixelConvention, origins: &mut Vec<f32>, dirs: &mut Vec<f32>) {
        match projection {
            Projection::Perspective => self.rays_into(conv, origins, dirs),
            Projection::Equirectangular => self.equirect_rays_into(conv, origins, dirs),
            Projection::Fisheye => self.camera_rays_into(conv, origins, dirs, |u, v| self.fisheye_dir(u, v)),
        }
    }

    /// [`frame_rays_into`](Self::frame_rays_into) through another point of each pixel: the
    /// point `offset` from its integer corner (`[0.5, 0.5]` is the centre; one of
    /// [`PixelConvention::sample_offsets`] for supersampling). At the convention's offset the
    /// rays are [`frame_rays_into`](Self::frame_rays_into)'s, bit for bit.
    pub fn frame_rays_at(&self, projection: Projection, offset: [f32; 2], origins: &mut Vec<f32>, dirs: &mut Vec<f32>) {
        let [ox, oy] = offset;
        match projection {
            Projection::Perspective => self.world_rays_at(ox, oy, origins, dirs, |u, v| self.dir_at_unnormalized(u, v)),
            Projection::Equirectangular => {
                let (w, h) = (self.intrinsics.width, self.intrinsics.height);
                self.world_rays_at(ox, oy, origins, dirs, |u, v| self.rotation * Self::equirect_dir(w, h, u, v))
            }
            Projection::Fisheye => self.world_rays_at(ox, oy, origins, dirs, |u, v| self.rotation * self.fisheye_dir(u, v)),
        }
    }
}

/// A camera path for novel views: `n` cameras on a circle around `center`, at the mean distance and
/// mean elevation of `cameras` (the training views) about their mean "up" direction, each looking
/// at `center`, evenly spaced in azimuth and starting at the first camera's azimuth; `intrinsics`
/// for every frame. For object-centred (360°) captures such as the NeRF synthetic scenes this is
/// the familiar turntable render. `None` when `cameras` is empty or degenerate (every camera at
/// `center`, or a zero mean up vector).
pub fn orbit(cameras: &[Camera], center: Vec3, intrinsics: Intrinsics, n: usize) -> Option<Vec<Camera>> {
    let k = cameras.len() as f32;
    if cameras.is_empty() {
        return None;
    }
    let up = (cameras.iter().map(|c| c.rotation.y_axis).sum::<Vec3>() / k).try_normalize()?;
    let radius = cameras.iter().map(|c| (c.position - center).length()).sum::<f32>() / k;
    if !(radius > 0.0 && radius.is_finite()) {
        return None;
    }
    let elevation = cameras
        .iter()
        .map(|c| {
            let v = c.position - center;
            (v.dot(up) / v.length().max(f32::MIN_POSITIVE)).clamp(-1.0, 1.0).asin()
        })
        .sum::<f32>()
        / k;
    // Azimuth basis: the first camera's horizontal direction (any horizontal one if it is vertical).
    let v0 = cameras[0].position - center;
    let e1 = (v0 - up * v0.dot(up)).try_normalize().unwrap_or_else(|| up.any_orthonormal_vector());
    let e2 = up.cross(e1);
    Some(
        (0..n)
            .map(|j| {
                let phi = std::f32::consts::TAU * j as f32 / n as f32;
                let horizontal = e1 * phi.cos() + e2 * phi.sin();
                let position = center + radius * (horizontal * elevation.cos() + up * elevation.sin());
                // OpenGL axes: the camera looks down −z, so z points from the centre to the camera.
                let z = (position - center).normalize();
                let x = up.cross(z).try_normalize().unwrap_or(e2);
                let y = z.cross(x);
                Camera { intrinsics, rotation: Mat3::from_cols(x, y, z), position, distortion: Distortion::NONE }
            })
            .collect(),
    )
}

/// The point the cameras look at: the least-squares closest point to their optical axes
/// (`argmin_p Σ |(I − d·dᵀ)(p − o)|²`, `o` a camera's centre, `d` its viewing direction). The
/// point instant-ngp's `colmap2nerf.py` centres a capture on is of this kind (it averages the
/// closest points of pairs of axes instead). For object-centred (360°) captures it
/// is the object's centre; `None` when the axes are (near) parallel, as in forward-facing
/// captures, or there are fewer than two cameras.
pub fn look_at_point(cameras: &[Camera]) -> Option<Vec3> {
    use glam::{DMat3, DVec3};
    if cameras.len() < 2 {
        return None;
    }
    let (mut a, mut b) = (DMat3::ZERO, DVec3::ZERO);
    for c in cameras {
        let d = (-c.rotation.z_axis).as_dvec3().try_normalize()?;
        let m = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += m;
        b += m * c.position.as_dvec3();
    }
    // Each term is a projection with eigenvalues (0, 1, 1), so `a / n` has eigenvalues in [0, 2];
    // near-parallel axes leave one of them near 0 (a determinant near 0).
    let n = cameras.len() as f64;
    if !((a * (1.0 / n)).determinant() > 1e-3) {
        return None;
    }
    let p = a.inverse() * b;
    p.is_finite().then(|| p.as_vec3())
}

/// The distance in front of the cameras that [`spiral`]'s frames look at, between depths `near`
/// and `far`: nerf-pytorch's `focal`, `1 / (0.25/near + 0.75/far)` (its "focus depth").
pub fn spiral_focus(near: f32, far: f32) -> f32 {
    1.0 / (0.25 / near + 0.75 / far)
}

/// nerf-pytorch's `render_path_spiral` for forward-facing captures (LLFF): `n` cameras on a
/// spiral of two turns about the mean camera, in its image plane with a depth swing of half the
/// rate, every one looking at a point `focus` in front of the mean camera; `intrinsics` for every
/// frame. The spiral's radii are the 90th percentile of `|position|` per axis of the mean
/// camera's frame (nerf-pytorch's `rads`); `focus` follows nerf-pytorch: `1 / (0.25 / near +
/// 0.75 / far)` for the nearest and farthest scene depths (it passes `0.9 · min bound` and
/// `5 · max bound`). `None` for no cameras or a degenerate mean.
pub fn spiral(cameras: &[Camera], near: f32, far: f32, intrinsics: Intrinsics, n: usize) -> Option<Vec<Camera>> {
    if cameras.is_empty() || !(near > 0.0 && far > near) {
        return None;
    }
    let k = cameras.len() as f32;
    // nerf-pytorch's poses_avg.
    let center = cameras.iter().map(|c| c.position).sum::<Vec3>() / k;
    let z = cameras.iter().map(|c| c.rotation.z_axis).sum::<Vec3>().try_normalize()?;
    let up = cameras.iter().map(|c| c.rotation.y_axis).sum::<Vec3>();
    let x = up.cross(z).try_normalize()?;
    let avg = Mat3::from_cols(x, z.cross(x), z);
    let percentile90 = |axis: usize| {
        let mut v: Vec<f32> = cameras.iter().map(|c| (avg.transpose() * (c.position - center))[axis].abs()).collect();
        v.sort_by(f32::total_cmp);
        // numpy's linear interpolation between order statistics.
        let r = 0.9 * (v.len() - 1) as f32;
        let (lo, hi) = (r.floor() as usize, r.ceil() as usize);
        v[lo] + (v[hi] - v[lo]) * (r - lo as f32)
    };
    let rads = Vec3::new(percentile90(0), percentile90(1), percentile90(2));
    let focus = spiral_focus(near, far);
    let target = center + avg * Vec3::new(0.0, 0.0, -focus);
    Some(
        (0..n)
            .map(|j| {
                let theta = 2.0 * std::f32::consts::TAU * j as f32 / n as f32;
                let local = Vec3::new(theta.cos(), -theta.sin(), -(0.5 * theta).sin()) * rads;
                let position = center + avg * local;
                // nerf-pytorch's viewmatrix(z, up, position): the camera looks at `target`.
                let z = (position - target).normalize();
                let x = up.cross(z).normalize();
                let y = z.cross(x);
                Camera { intrinsics, rotation: Mat3::from_cols(x, y, z), position, distortion: Distortion::NONE }
            })
            .collect(),
    )
}

/// nerfstudio's `interpolate` trajectory (`ns-render interpolate`, `get_interpolated_poses_many`):
/// `n` cameras along the path through `cameras` in their order, evenly spaced in the path's
/// parameter `u ∈ [0, cameras.len() − 1]` (the first frame is the first camera, the last frame the
/// last one). Between cameras `i` and `i + 1` the position is interpolated linearly and the
/// orientation by quaternion slerp; `intrinsics` for every frame. `None` for fewer than two cameras
/// or `n < 2`.
pub fn interpolate(cameras: &[Camera], intrinsics: Intrinsics, n: usize) -> Option<Vec<Camera>> {
    if cameras.len() < 2 || n < 2 {
        return None;
    }
    let quats: Vec<glam::Quat> = cameras.iter().map(Camera::orientation).collect();
    let last = (cameras.len() - 1) as f32;
    Some(
        (0..n)
            .map(|j| {
                let u = last * j as f32 / (n - 1) as f32;
                let i = (u.floor() as usize).min(cameras.len() - 2);
                let t = u - i as f32;
                let (a, b) = (&cameras[i], &cameras[i + 1]);
                // glam's slerp takes the shorter way round (q and −q are the same rotation).
                let q = quats[i].slerp(quats[i + 1], t).normalize();
                Camera { intrinsics, rotation: Mat3::from_quat(q), position: a.position.lerp(b.position, t), distortion: Distortion::NONE }
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn test_camera() -> Camera {
        let k = Intrinsics::from_fov_x(8, 6, 0.9);
        let c2w = [
            [0.0f32, 0.0, 1.0, 2.0],
            [1.0, 0.0, 0.0, -1.0],
            [0.0, 1.0, 0.0, 0.5],
            [0.0, 0.0, 0.0, 1.0],
        ];
        Camera::from_c2w(k, &c2w).unwrap()
    }

    #[test]
    fn supersampling_points_cover_the_pixel_evenly() {
        for conv in [PixelConvention::Center, PixelConvention::Integer] {
            let o = conv.offset();
            // One sample: the convention's point; zero asks for one too.
            assert_eq!(conv.sample_offsets(1), vec![[o, o]]);
            assert_eq!(conv.sample_offsets(0), vec![[o, o]]);
            for spp in [2usize, 3, 4, 6, 8, 13, 16, 64] {
                let pts = conv.sample_offsets(spp);
                assert_eq!(pts.len(), spp);
                // Inside the unit square around the convention's point (the pixel's area).
                assert!(pts.iter().flatten().all(|&x| x > o - 0.5 && x < o + 0.5), "{conv:?} {spp}: {pts:?}");
                // One point per stratum on each axis (so distinct points, the mean exactly the
                // convention's point).
                for axis in 0..2 {
                    let mut strata: Vec<usize> = pts.iter().map(|p| ((p[axis] - (o - 0.5)) * spp as f32).floor() as usize).collect();
                    strata.sort_unstable();
                    assert_eq!(strata, (0..spp).collect::<Vec<_>>(), "{conv:?} {spp}: axis {axis}");
                    let mean = pts.iter().map(|p| p[axis] as f64).sum::<f64>() / spp as f64;
                    assert!((mean - o as f64).abs() < 1e-6, "{conv:?} {spp}: mean {mean}");
                }
                // Spread over the square, not along its diagonal: from 8 points on, each quarter
                // of the pixel holds at least an eighth of them.
                if spp >= 8 {
                    for qx in [false, true] {
                        for qy in [false, true] {
                            let n = pts.iter().filter(|p| (p[0] >= o) == qx && (p[1] >= o) == qy).count();
                            assert!(n * 8 >= spp, "{conv:?} {spp}: quarter ({qx}, {qy}) has {n}");
                        }
                    }
                }
            }
            // The same count, the same points (a deterministic evaluation).
            assert_eq!(conv.sample_offsets(8), conv.sample_offsets(8));
        }
    }

    #[test]
    fn filtered_supersampling_points_follow_the_filter() {
        // Box: exactly the unfiltered points.
        for spp in [1usize, 8, 16] {
            assert_eq!(PixelConvention::Center.sample_offsets_filtered(spp, PixelFilter::Box), PixelConvention::Center.sample_offsets(spp));
        }
        for width in [1.0f32, 1.5, 3.0] {
            let f = PixelFilter::BlackmanHarris { width };
            assert!(f.validate().is_ok());
            // The weight integrates to one over ±width, and the inverse CDF inverts a numerical
            // CDF of it.
            let n = 20_000;
            let dx = 2.0 * width as f64 / n as f64;
            let xs = (0..n).map(|i| -(width as f64) + (i as f64 + 0.5) * dx);
            assert_eq!(f.weight(width as f64 * 1.0001), 0.0);
            assert!(f.weight(0.0) > f.weight(0.5 * width as f64) && f.weight(0.5 * width as f64) > f.weight(0.9 * width as f64));
            let total: f64 = xs.clone().map(|x| f.weight(x) * dx).sum();
            assert!((total - 1.0).abs() < 1e-6, "{width}: {total}");
            let mut acc = 0.0;
            for (i, x) in xs.enumerate() {
                acc += f.weight(x) * dx;
                if i % 997 == 0 && acc > 1e-6 && acc < 1.0 - 1e-6 {
                    let inv = f.inverse_cdf(acc);
                    assert!((inv - (x + 0.5 * dx)).abs() < 2.0 * dx, "{width}: F^-1({acc}) = {inv}, x = {x}");
                }
            }
            // Symmetric; the median at the pixel's point; inside the window.
            assert!(f.inverse_cdf(0.5).abs() < 1e-12);
            for u in [0.01, 0.2, 0.37] {
                assert!((f.inverse_cdf(u) + f.inverse_cdf(1.0 - u)).abs() < 1e-9);
                assert!(f.inverse_cdf(u) > -(width as f64));
            }
            for conv in [PixelConvention::Center, PixelConvention::Integer] {
                let o = conv.offset() as f64;
                assert_eq!(conv.sample_offsets_filtered(1, f), vec![[o as f32; 2]]);
                let pts = conv.sample_offsets_filtered(16, f);
                for axis in 0..2 {
                    // Mean at the pixel's point; the spread of the points is the filter's, not
                    // the box's (Cycles' 1.5: 0.42 px against the box's 0.29).
                    let mean = pts.iter().map(|p| p[axis] as f64).sum::<f64>() / 16.0;
                    assert!((mean - o).abs() < 1e-6);
                    let var_pts = pts.iter().map(|p| (p[axis] as f64 - o).powi(2)).sum::<f64>() / 16.0;
                    let var_f: f64 = (0..n).map(|i| -(width as f64) + (i as f64 + 0.5) * dx).map(|x| x * x * f.weight(x) * dx).sum();
                    assert!((var_pts.sqrt() - var_f.sqrt()).abs() < 0.1 * var_f.sqrt(), "{width}: {} against {}", var_pts.sqrt(), var_f.sqrt());
                }
            }
        }
        let s = PixelFilter::BlackmanHarris { width: 1.5 };
        let sd = (0..1000).map(|i| -1.5 + (i as f64 + 0.5) * 3e-3).map(|x| x * x * s.weight(x) * 3e-3).sum::<f64>().sqrt();
        assert!((sd - 0.4155).abs() < 1e-3, "{sd}");
        for bad in [0.0f32, -1.0, f32::NAN, f32::INFINITY, 9.0] {
            assert!(PixelFilter::BlackmanHarris { width: bad }.validate().unwrap_err().contains("width"), "{bad}");
        }
        // Serde: a tagged table, Box by default.
        let j = serde_json::to_string(&s).unwrap();
        assert_eq!(j, r#"{"kind":"blackman_harris","width":1.5}"#);
        assert_eq!(serde_json::from_str::<PixelFilter>(&j).unwrap(), s);
        assert_eq!(serde_json::from_str::<PixelFilter>(r#"{"kind":"box"}"#).unwrap(), PixelFilter::Box);
        assert!(serde_json::from_str::<PixelFilter>(r#"{"kind":"gauss"}"#).is_err());
    }

    #[test]
    fn panoramas_and_fisheyes_look_where_nerfstudio_does() {
        let (w, h) = (64u32, 32u32);
        let cam = Camera { intrinsics: Intrinsics { width: w, height: h, fx: 32.0, fy: 32.0, cx: 32.0, cy: 16.0 }, ..test_camera() };
        let axis = |v: Vec3| cam.rotation * v; // camera axes in the world
        let at = |u: f32, v: f32| cam.rotation * Camera::equirect_dir(w, h, u, v);
        let close = |a: Vec3, b: Vec3| (a - b).length() < 1e-5;
        let (wf, hf) = (w as f32, h as f32);
        // Centre: forward; a quarter in from the left: left; three quarters: right; edges: back.
        assert!(close(at(0.5 * wf, 0.5 * hf), axis(Vec3::NEG_Z)), "{}", at(0.5 * wf, 0.5 * hf));
        assert!(close(at(0.25 * wf, 0.5 * hf), axis(Vec3::NEG_X)));
        assert!(close(at(0.75 * wf, 0.5 * hf), axis(Vec3::X)));
        assert!(close(at(0.0, 0.5 * hf), axis(Vec3::Z)) && close(at(wf, 0.5 * hf), axis(Vec3::Z)));
        // Top edge up, bottom edge down, whatever the column; a quarter of the height: 45° up.
        for u in [0.0, 10.0, 0.5 * wf, 63.0] {
            assert!(close(at(u, 0.0), axis(Vec3::Y)) && close(at(u, hf), axis(Vec3::NEG_Y)));
        }
        let up45 = at(0.5 * wf, 0.25 * hf);
        assert!(close(up45, axis(Vec3::new(0.0, 1.0, -1.0).normalize())), "{up45}");
        // The frame: W·H unit rays from the camera's centre, row-major, pixel centres.
        let (mut o, mut d) = (Vec::new(), Vec::new());
        cam.frame_rays_into(Projection::Equirectangular, PixelConvention::Center, &mut o, &mut d);
        assert_eq!((o.len(), d.len()), (3 * 64 * 32, 3 * 64 * 32));
        assert!(o.chunks_exact(3).all(|p| p == cam.position.to_array()));
        assert!(d.chunks_exact(3).all(|v| (Vec3::from_slice(v).length() - 1.0).abs() < 1e-5));
        let k = (5 * w + 17) as usize; // row 5, column 17
        assert!(close(Vec3::from_slice(&d[3 * k..3 * k + 3]), at(17.5, 5.5)));
        // Directions cover the sphere evenly in longitude: their mean over a row is on the axis.
        let row: Vec3 = (0..w as usize).map(|c| Vec3::from_slice(&d[3 * (3 * w as usize + c)..][..3])).sum::<Vec3>() / wf;
        assert!(row.dot(axis(Vec3::X)).abs() < 1e-5 && row.dot(axis(Vec3::Z)).abs() < 1e-5, "{row}");
        // Fisheye: the principal point looks forward, π/2 focal lengths to its right looks
        // right, as far above it looks up, π away looks back; small angles agree with the
        // pinhole; frames are unit rays from the centre.
        let fish = Camera { intrinsics: Intrinsics { width: 40, height: 30, fx: 10.0, fy: 10.0, cx: 20.0, cy: 15.0 }, ..test_camera() };
        let f = |u: f32, v: f32| fish.rotation * fish.fisheye_dir(u, v);
        let half_pi = 10.0 * std::f32::consts::FRAC_PI_2;
        assert!(close(f(20.0, 15.0), axis(Vec3::NEG_Z)));
        assert!(close(f(20.0 + half_pi, 15.0), axis(Vec3::X)) && close(f(20.0, 15.0 - half_pi), axis(Vec3::Y)));
        assert!(close(f(20.0 - 10.0 * std::f32::consts::PI, 15.0), axis(Vec3::Z)));
        let near_axis = fish.ray_at(20.3, 14.8).dir;
        assert!((f(20.3, 14.8) - near_axis).length() < 1e-4, "small angles: fisheye ≈ pinhole");
        fish.frame_rays_into(Projection::Fisheye, PixelConvention::Center, &mut o, &mut d);
        assert_eq!(d.len(), 3 * 40 * 30);
        assert!(d.chunks_exact(3).all(|v| (Vec3::from_slice(v).length() - 1.0).abs() < 1e-5));
        assert!(close(Vec3::from_slice(&d[3 * (7 * 40 + 31)..][..3]), f(31.5, 7.5)));
        // Perspective frames are the pinhole rays.
        let (mut o2, mut d2) = (Vec::new(), Vec::new());
        cam.frame_rays_into(Projection::Perspective, PixelConvention::Center, &mut o2, &mut d2);
        cam.rays_into(PixelConvention::Center, &mut o, &mut d);
        assert_eq!((o, d), (o2, d2));
    }

    /// `frame_rays_at` at the convention's point is `frame_rays_into`, bit for bit, for every
    /// projection and either convention; elsewhere in the pixel it is the ray through that point.
    #[test]
    fn frame_rays_at_moves_the_point_in_the_pixel() {
        let cam = Camera { intrinsics: Intrinsics { width: 12, height: 9, fx: 10.0, fy: 11.0, cx: 6.5, cy: 4.0 }, ..test_camera() };
        let (mut o, mut d, mut o2, mut d2) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for projection in [Projection::Perspective, Projection::Equirectangular, Projection::Fisheye] {
            for conv in [PixelConvention::Center, PixelConvention::Integer] {
                cam.frame_rays_into(projection, conv, &mut o, &mut d);
                cam.frame_rays_at(projection, [conv.offset(); 2], &mut o2, &mut d2);
                assert_eq!((&o, &d), (&o2, &d2), "{projection:?} {conv:?}");
            }
        }
        cam.frame_rays_at(Projection::Perspective, [0.25, 0.875], &mut o, &mut d);
        let k = 4 * 12 + 7; // row 4, column 7
        assert_eq!(&d[3 * k..3 * k + 3], &cam.ray_at(7.25, 4.875).dir.to_array());
        let fish = cam.rotation * cam.fisheye_dir(7.25, 4.875);
        cam.frame_rays_at(Projection::Fisheye, [0.25, 0.875], &mut o, &mut d);
        assert!((Vec3::from_slice(&d[3 * k..3 * k + 3]) - fish.normalize()).length() < 1e-6);
    }

    #[test]
    fn sees_sphere_is_the_image_for_points_and_conservative_for_balls() {
        // An off-centre principal point, so the four planes differ.
        let k = Intrinsics { width: 80, height: 60, fx: 70.0, fy: 75.0, cx: 30.0, cy: 35.0 };
        let cam = Camera { intrinsics: k, ..test_camera() };
        let shows = |p: Vec3| {
            let q = cam.rotation.transpose() * (p - cam.position);
            let d = -q.z;
            let (u, v) = (k.cx + k.fx * q.x / d, k.cy - k.fy * q.y / d);
            d > 0.0 && (0.0..=k.width as f32).contains(&u) && (0.0..=k.height as f32).contains(&v)
        };
        let mut g = nerf_core::rng(17, 0);
        use rand::Rng as _;
        let (mut seen, mut unseen) = (0, 0);
        for _ in 0..4000 {
            let c = cam.position + Vec3::new(g.gen_range(-6.0..6.0), g.gen_range(-6.0..6.0), g.gen_range(-6.0..6.0));
            // A point: exactly the projection test.
            assert_eq!(cam.sees_sphere(c, 0.0), shows(c), "{c:?}");
            // A ball: any visible point of it makes it seen.
            let r = g.gen_range(0.05f32..1.0);
            let visible = (0..300).any(|_| {
                let v = Vec3::new(g.gen_range(-1.0..1.0), g.gen_range(-1.0..1.0), g.gen_range(-1.0..1.0));
                v.length() <= 1.0 && shows(c + v * r)
            });
            let s = cam.sees_sphere(c, r);
            if visible {
                assert!(s, "ball at {c:?} r {r} shows but is not seen");
            }
            seen += s as usize;
            unseen += !s as usize;
        }
        assert!(seen > 150 && unseen > 2000, "{seen} seen, {unseen} not");
        // Behind the camera by more than the radius.
        let back = cam.position + cam.rotation * Vec3::new(0.0, 0.0, 2.0);
        assert!(!cam.sees_sphere(back, 1.9) && cam.sees_sphere(back, 2.1));
    }

    /// Cameras with a lens: a pixel's ray leads back to the pixel ([`Camera::project`]), a
    /// fisheye's rays reach past 90° off the axis, and the frustum holds every point and ball the
    /// image shows while leaving out most of space.
    #[test]
    fn lens_cameras_see_through_their_lens() {
        use rand::Rng as _;
        let k = Intrinsics { width: 80, height: 60, fx: 40.0, fy: 42.0, cx: 38.0, cy: 31.0 };
        let barrel = Distortion { k1: -0.12, k2: 0.01, p1: 0.002, p2: -0.003, ..Distortion::NONE };
        let pincushion = Distortion { k1: 0.1, k2: 0.02, ..Distortion::NONE };
        // About 190° across the width.
        let fish = Distortion { model: LensModel::Fisheye, k1: -0.02, k2: 0.003, ..Distortion::NONE };
        let fish_k = Intrinsics { fx: 24.0, fy: 24.0, ..k };
        // OpenCV's rational model with thin-prism terms (its numerator of higher degree, so
        // that it does not fold far off the axis), and a Fisheye624.
        let rational = Distortion { k1: 0.05, k2: 0.002, k4: 0.02, p1: 0.001, s1: 0.003, s3: -0.002, ..Distortion::NONE };
        let aria = Distortion { model: LensModel::Fisheye624, k1: -0.03, k2: 0.003, k5: 1e-5, p1: 0.001, p2: -0.002, s1: 0.001, s4: 0.0005, ..Distortion::NONE };
        let mut g = nerf_core::rng(23, 0);
        for (lens, k) in [(barrel, k), (pincushion, k), (rational, k), (fish, fish_k), (aria, fish_k)] {
            let cam = Camera { intrinsics: k, ..test_camera() }.with_distortion(lens);
            assert!(cam.frustum().sees_sphere(cam.position + cam.rotation * Vec3::NEG_Z, 0.0));
            for _ in 0..500 {
                let (u, v) = (g.gen_range(0.0..k.width as f32), g.gen_range(0.0..k.height as f32));
                let p = cam.ray_at(u, v).at(g.gen_range(0.5..5.0));
                let (pu, pv) = cam.project(p).unwrap();
                assert!((pu - u as f64).abs() < 1e-3 && (pv - v as f64).abs() < 1e-3, "{lens:?}: ({u}, {v}) back at ({pu}, {pv})");
            }
            let edge = cam.rotation.transpose() * cam.ray_at(0.0, k.cy).dir;
            if lens.model.is_fisheye() {
                assert!(edge.z > 0.05, "the fisheye's left edge looks behind the camera: {edge:?}");
            }
            let shows = |p: Vec3| cam.project(p).is_some_and(|(u, v)| (0.0..=k.width as f64).contains(&u) && (0.0..=k.height as f64).contains(&v));
            let frustum = cam.frustum();
            let (mut seen, mut unseen) = (0, 0);
            for _ in 0..3000 {
                let c = cam.position + Vec3::new(g.gen_range(-6.0..6.0), g.gen_range(-6.0..6.0), g.gen_range(-6.0..6.0));
                if shows(c) {
                    assert!(frustum.sees_sphere(c, 0.0), "{lens:?}: {c:?} shows");
                }
                let r = g.gen_range(0.05f32..1.0);
                let visible = (0..200).any(|_| {
                    let v = Vec3::new(g.gen_range(-1.0..1.0), g.gen_range(-1.0..1.0), g.gen_range(-1.0..1.0));
                    v.length() <= 1.0 && shows(c + v * r)
                });
                let s = frustum.sees_sphere(c, r);
                assert!(s || !visible, "{lens:?}: ball at {c:?} r {r} shows but is not seen");
                seen += s as usize;
                unseen += !s as usize;
            }
            // The fisheye sees more than a hemisphere: fewer balls are out of its view.
            let out = if lens.model.is_fisheye() { 250 } else { 1000 };
            assert!(seen > 150 && unseen > out, "{lens:?}: {seen} seen, {unseen} not");
        }
    }

    #[test]
    fn fov_round_trip_and_downscale() {
        let k = Intrinsics::from_fov_x(800, 800, 0.6911112070083618);
        assert!((k.fx - 1111.111).abs() < 1e-2, "{}", k.fx);
        assert_eq!((k.cx, k.cy), (400.0, 400.0));
        assert!((k.fov_x() - 0.6911112070083618).abs() < 1e-6);
        let h = k.downscaled(2);
        assert_eq!((h.width, h.height), (400, 400));
        assert_eq!(
            (h.fx, h.fy, h.cx, h.cy),
            (k.fx / 2.0, k.fy / 2.0, 200.0, 200.0)
        );
        assert!(k.validate().is_ok());
        let bad = Intrinsics { fx: f32::NAN, ..k };
        assert!(matches!(bad.validate(), Err(RayError::BadIntrinsics(_))));
    }

    #[test]
    fn c2w_round_trip_and_errors() {
        let cam = test_camera();
        let m = cam.c2w();
        let cam2 = Camera::from_c2w(cam.intrinsics, &m[..3]).unwrap();
        assert_eq!(cam2.rotation, cam.rotation);
        assert_eq!(cam2.position, cam.position);
        let mut bad = m;
        bad[1][2] = f32::INFINITY;
        assert!(matches!(
            Camera::from_c2w(cam.intrinsics, &bad),
            Err(RayError::NonFinitePose)
        ));
        assert!(matches!(
            Camera::from_c2w(cam.intrinsics, &m[..2]),
            Err(RayError::BadPoseShape { rows: 2 })
        ));
        // A uniformly scaled rotation is a pose; a zeroed or collapsed rotation block is not.
        let mut scaled = m;
        for row in scaled.iter_mut().take(3) {
            for v in row.iter_mut().take(3) {
                *v *= 0.01;
            }
        }
        assert!(Camera::from_c2w(cam.intrinsics, &scaled).is_ok());
        let mut zero = m;
        for row in zero.iter_mut().take(3) {
            row[..3].fill(0.0);
        }
        assert!(matches!(
            Camera::from_c2w(cam.intrinsics, &zero),
            Err(RayError::DegeneratePose { det, .. }) if det == 0.0
        ));
        let mut coplanar = m; // third axis = first axis
        for row in coplanar.iter_mut().take(3) {
            row[2] = row[0];
        }
        let e = Camera::from_c2w(cam.intrinsics, &coplanar).unwrap_err();
        assert!(matches!(e, RayError::DegeneratePose { .. }), "{e}");
        assert!(e.to_string().contains("span 3-D space"), "{e}");
    }

    #[test]
    fn centre_pixel_looks_down_minus_z() {
        let cam = test_camera();
        // Centre convention: pixel (3,2) of 8x6 sits at (3.5,2.5); the principal point is (4,3),
        // so use ray_at for the exact centre: camera −z maps to world −(third column).
        let r = cam.ray_at(4.0, 3.0);
        assert!((r.dir - Vec3::new(-1.0, 0.0, 0.0)).length() < 1e-6);
        // +u moves along camera +x, +v along camera −y.
        let right = cam.dir_at_unnormalized(5.0, 3.0) - cam.dir_at_unnormalized(4.0, 3.0);
        let down = cam.dir_at_unnormalized(4.0, 4.0) - cam.dir_at_unnormalized(4.0, 3.0);
        assert!((right.normalize() - cam.rotation.x_axis).length() < 1e-6);
        assert!((down.normalize() + cam.rotation.y_axis).length() < 1e-6);
    }

    #[test]
    fn rays_into_matches_ray() {
        let cam = test_camera();
        let (mut o, mut d) = (vec![1.0; 5], Vec::new());
        cam.rays_into(PixelConvention::Center, &mut o, &mut d);
        assert_eq!(o.len(), 3 * 8 * 6);
        assert_eq!(d.len(), 3 * 8 * 6);
        for row in 0..6u32 {
            for col in 0..8u32 {
                let i = 3 * (row as usize * 8 + col as usize);
                let r = cam.ray(col, row, PixelConvention::Center);
                assert_eq!(&d[i..i + 3], &r.dir.to_array());
                assert_eq!(&o[i..i + 3], &cam.position.to_array());
                assert!((r.dir.length() - 1.0).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn aabb_basics() {
        let b = Aabb {
            min: [-1.0, 0.0, 2.0],
            max: [3.0, 2.0, 4.0],
        };
        assert_eq!(b.center(), [1.0, 1.0, 3.0]);
        assert_eq!(b.extent(), [4.0, 2.0, 2.0]);
        assert!(b.contains([0.0, 1.0, 3.0]));
        assert!(!b.contains([0.0, 1.0, 5.0]));
        assert_eq!(Aabb::cube(1.5).extent(), [3.0; 3]);
    }

    #[test]
    fn orbit_cameras_circle_the_centre_at_the_training_distance_and_look_at_it() {
        let k = Intrinsics::from_fov_x(40, 30, 0.7);
        // Training cameras on a ring of radius 4 at 30° elevation about +z, looking at the origin.
        let centre = Vec3::new(0.1, -0.2, 0.05);
        let ring: Vec<Camera> = (0..12)
            .map(|j| {
                let (phi, el) = (std::f32::consts::TAU * j as f32 / 12.0 + 0.3, 30f32.to_radians());
                let position = centre + 4.0 * Vec3::new(el.cos() * phi.cos(), el.cos() * phi.sin(), el.sin());
                let z = (position - centre).normalize();
                let x = Vec3::Z.cross(z).normalize();
                Camera { intrinsics: k, rotation: Mat3::from_cols(x, z.cross(x), z), position, distortion: Distortion::NONE }
            })
            .collect();
        let path = orbit(&ring, centre, k, 8).unwrap();
        assert_eq!(path.len(), 8);
        for (j, c) in path.iter().enumerate() {
            let v = c.position - centre;
            assert!((v.length() - 4.0).abs() < 1e-4, "frame {j}: radius {}", v.length());
            let el = (v.z / v.length()).asin().to_degrees();
            assert!((el - 30.0).abs() < 0.05, "frame {j}: elevation {el}");
            // The central ray passes through the centre; the rotation is orthonormal, right-handed.
            let ray = c.ray_at(20.0, 15.0);
            let to_centre = (centre - c.position).normalize();
            assert!(ray.dir.dot(to_centre) > 1.0 - 1e-6, "frame {j} does not look at the centre");
            assert!((c.rotation.determinant() - 1.0).abs() < 1e-5);
            assert!(c.rotation.y_axis.z > 0.0, "frame {j}: image up points down");
            // Evenly spaced: 45° between consecutive frames.
            let n = path[(j + 1) % 8].position - centre;
            let (a, b) = (Vec3::new(v.x, v.y, 0.0).normalize(), Vec3::new(n.x, n.y, 0.0).normalize());
            assert!((a.dot(b).clamp(-1.0, 1.0).acos().to_degrees() - 45.0).abs() < 0.05, "frame {j}: spacing");
        }
        // The first frame starts at the first training camera's azimuth.
        assert!((path[0].position - ring[0].position).length() < 1e-3);
        assert!(orbit(&[], centre, k, 8).is_none());
        let at_centre = Camera { position: centre, ..ring[0] };
        assert!(orbit(&[at_centre], centre, k, 8).is_none());
    }

    #[test]
    fn look_at_point_finds_where_the_axes_meet_and_refuses_parallel_axes() {
        let k = Intrinsics::from_fov_x(40, 30, 0.7);
        let target = Vec3::new(0.3, -1.2, 0.7);
        // Cameras on the upper half of a sphere about `target`, looking at it (the mean camera
        // centre lies above it), one axis nudged off.
        let look = |position: Vec3, at: Vec3| {
            let z = (position - at).normalize();
            let x = Vec3::Z.cross(z).normalize();
            Camera { intrinsics: k, rotation: Mat3::from_cols(x, z.cross(x), z), position, distortion: Distortion::NONE }
        };
        let cams: Vec<Camera> = (0..20)
            .map(|j| {
                let (phi, el) = (2.4 * j as f32, (10.0 + 3.5 * j as f32).to_radians());
                target + 3.0 * Vec3::new(el.cos() * phi.cos(), el.cos() * phi.sin(), el.sin())
            })
            .map(|p| look(p, target))
            .collect();
        let mean = cams.iter().map(|c| c.position).sum::<Vec3>() / cams.len() as f32;
        assert!((mean - target).length() > 1.0, "the mean centre is not the answer");
        let p = look_at_point(&cams).unwrap();
        assert!((p - target).length() < 1e-4, "{p} vs {target}");
        // One axis off by 0.1 moves the point by about 0.1 / 20.
        let mut off = cams.clone();
        off[3] = look(off[3].position, target + Vec3::new(0.1, 0.0, 0.0));
        let q = look_at_point(&off).unwrap();
        assert!((q - target).length() > 1e-4 && (q - target).length() < 0.02, "{q}");
        // Forward-facing (every camera looking down −z) and too few cameras: no point.
        let rig: Vec<Camera> = (0..9).map(|i| Camera { intrinsics: k, rotation: Mat3::IDENTITY, position: Vec3::new(i as f32 * 0.1, 0.0, 0.0), distortion: Distortion::NONE }).collect();
        assert!(look_at_point(&rig).is_none());
        assert!(look_at_point(&cams[..1]).is_none());
    }

    #[test]
    fn spiral_cameras_circle_the_mean_camera_twice_and_look_at_the_focus() {
        let k = Intrinsics::from_fov_x(40, 30, 0.9);
        // A forward-facing rig: 11 cameras in the plane z = 0, looking down −z; offsets up to
        // 0.5 in x, 0.25 in y, 0.05 in z, in the rig's frame (yawed by 0.3 about y, moved).
        let yaw = Mat3::from_rotation_y(0.3);
        let shift = Vec3::new(1.0, 2.0, -0.5);
        let rig: Vec<Camera> = (0..11)
            .map(|i| {
                let u = i as f32 / 10.0 * 2.0 - 1.0;
                let local = Vec3::new(0.5 * u, 0.25 * (3.0 * u).sin(), 0.05 * u * u);
                Camera { intrinsics: k, rotation: yaw, position: shift + yaw * local, distortion: Distortion::NONE }
            })
            .collect();
        let center = rig.iter().map(|c| c.position).sum::<Vec3>() / 11.0;
        let (near, far) = (1.0, 20.0);
        let focus = 1.0 / (0.25 / near + 0.75 / far);
        let target = center + yaw * Vec3::new(0.0, 0.0, -focus);
        let path = spiral(&rig, near, far, k, 8).unwrap();
        assert_eq!(path.len(), 8);
        for (j, c) in path.iter().enumerate() {
            // In the rig's frame, within the 90th-percentile radii (0.5, 0.24, 0.03 here) of its centre.
            let local = yaw.transpose() * (c.position - center);
            assert!(local.x.abs() <= 0.5 + 1e-5 && local.y.abs() <= 0.25 && local.z.abs() <= 0.05, "{local}");
            let ray = c.ray_at(20.0, 15.0);
            assert!(ray.dir.dot((target - c.position).normalize()) > 1.0 - 1e-6, "frame {j} does not look at the focus");
            assert!((c.rotation.determinant() - 1.0).abs() < 1e-5 && c.rotation.y_axis.y > 0.9);
        }
        // Two turns: frame 4 of 8 is back at the start; frame 1 is a quarter turn (−y).
        assert!((path[4].position - path[0].position).length() < 1e-5);
        let q = yaw.transpose() * (path[1].position - center);
        assert!(q.x.abs() < 1e-5 && q.y < -0.2, "{q}");
        assert!(spiral(&[], near, far, k, 8).is_none());
        assert!(spiral(&rig, far, near, k, 8).is_none());
    }

    #[test]
    fn interpolated_cameras_pass_through_the_given_ones_and_turn_evenly_between() {
        let k = Intrinsics::from_fov_x(40, 30, 0.9);
        let at = |yaw: f32, p: Vec3| Camera { intrinsics: k, rotation: Mat3::from_rotation_y(yaw) * Mat3::from_rotation_x(-0.2), position: p, distortion: Distortion::NONE };
        // Three cameras: the second turned 60° from the first, the third 100° from the second
        // (a turn written the long way round: −260° is +100°).
        let (d60, d100) = (60f32.to_radians(), 100f32.to_radians());
        let cams = [at(0.0, Vec3::ZERO), at(d60, Vec3::new(2.0, 0.0, 0.0)), at(d60 + d100 - std::f32::consts::TAU, Vec3::new(2.0, 4.0, 0.0))];
        let path = interpolate(&cams, k, 9).unwrap();
        assert_eq!(path.len(), 9);
        // u = 0, 0.25, …, 2: frames 0, 4 and 8 are the cameras themselves.
        for (f, c) in [(0, &cams[0]), (4, &cams[1]), (8, &cams[2])] {
            assert!((path[f].position - c.position).length() < 1e-5, "frame {f}");
            assert!((path[f].rotation - c.rotation).to_cols_array().iter().all(|d| d.abs() < 1e-5), "frame {f}");
        }
        // Positions on the segments, evenly spaced; rotations unit and evenly turned (15° steps,
        // then 25° steps: the shorter way round).
        assert!((path[1].position - Vec3::new(0.5, 0.0, 0.0)).length() < 1e-5);
        assert!((path[6].position - Vec3::new(2.0, 2.0, 0.0)).length() < 1e-5);
        let angle = |a: &Camera, b: &Camera| (a.rotation.transpose() * b.rotation).to_cols_array()[..].iter().step_by(4).sum::<f32>();
        let deg = |a: &Camera, b: &Camera| ((angle(a, b) - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees();
        for j in 0..8 {
            let want = if j < 4 { 15.0 } else { 25.0 };
            assert!((deg(&path[j], &path[j + 1]) - want).abs() < 0.05, "step {j}: {}", deg(&path[j], &path[j + 1]));
            assert!((path[j].rotation.determinant() - 1.0).abs() < 1e-5);
        }
        assert!(interpolate(&cams[..1], k, 9).is_none() && interpolate(&cams, k, 1).is_none());
    }
}
