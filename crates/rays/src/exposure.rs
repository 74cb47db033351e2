//! Depth of field and motion blur for rendered frames, as instant-ngp renders its videos: a thin
//! lens, and a shutter that stays open while the camera moves along its path. Both are
//! transforms of a frame's rays over flat arrays ([`Exposure::apply`]), made before the rays are
//! rendered, so every field and both devices draw them.
//!
//! - **Thin lens** ([`ThinLens`], instant-ngp's `aperture_size` and focus plane): a pixel's ray
//!   leaves a point of a disk of radius `aperture` about the camera centre, in the plane of the
//!   camera's x and y axes, and passes through the point where the pinhole ray of the same pixel
//!   meets the plane `focus_distance` in front of the camera (for panoramas and fisheyes, whose
//!   rays go sideways, the sphere of that radius). What lies at the focus distance stays sharp;
//!   the rest blurs by how far it lies from it.
//! - **Motion blur** (instant-ngp's `shutter_fraction`): the shutter opens at the frame's camera
//!   and closes at the camera a fraction of the way to the next frame's; each ray is cast from
//!   the camera at its own moment in between, position lerped and rotation slerped (instant-ngp
//!   interpolates in log space, which differs from this by second-order terms over a frame).
//!
//! A frame with either effect is the mean of several passes (`nerf render --spp`). In pass `j`
//! of `n` each pixel takes its own moment and lens point ([`pass_sample`]): a point of a lattice
//! of `n` (one moment in each `n`-th of the shutter's time, and a rank-1 lattice over the lens
//! square), shifted by a hash of the pixel and the frame (a Cranley–Patterson rotation). So a
//! pixel's `n` rays stay spread evenly over the lens and the shutter, and neighbouring pixels
//! take different ones: too few passes leave noise, not `n` ghost copies of the frame.

use crate::{Camera, Projection};
use glam::{Mat3, Vec3};
use rayon::prelude::*;

/// A thin lens: depth of field (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ThinLens {
    /// Radius of the aperture, in scene units (instant-ngp's `aperture_size`, in its space's).
    /// 0: a pinhole, sharp everywhere.
    pub aperture: f32,
    /// Distance from the camera centre of the plane in focus, along the optical axis, in scene
    /// units.
    pub focus_distance: f32,
}

impl ThinLens {
    /// Checks the lens: the aperture finite and at least 0, the focus distance finite and above 0.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.aperture.is_finite() && self.aperture >= 0.0) {
            return Err(format!("aperture {}: must be a finite radius of at least 0", self.aperture));
        }
        if !(self.focus_distance.is_finite() && self.focus_distance > 0.0) {
            return Err(format!("focus distance {}: must be finite and above 0", self.focus_distance));
        }
        Ok(())
    }
}

/// The camera a fraction `t` of the way from `a` (at 0) to `b` (at 1): the position lerped, the
/// orientation slerped the shorter way round, `a`'s intrinsics and lens.
pub fn camera_lerp(a: &Camera, b: &Camera, t: f32) -> Camera {
    // glam's slerp takes the shorter way round (q and −q are the same rotation).
    Camera { rotation: Mat3::from_quat(a.orientation().slerp(b.orientation(), t).normalize()), position: a.position.lerp(b.position, t), ..*a }
}

/// How one frame is exposed: its camera, and what blurs it.
#[derive(Clone, Copy, Debug)]
pub struct Exposure<'a> {
    /// The frame's camera, as the shutter opens: the one its rays were cast from.
    pub camera: &'a Camera,
    /// The camera as the shutter closes (a fraction of the way to the next frame's camera,
    /// [`camera_lerp`]): motion blur. `None`: the camera stands still.
    pub shutter_close: Option<&'a Camera>,
    /// The lens: depth of field. `None` (or an aperture of 0): a pinhole.
    pub lens: Option<ThinLens>,
    /// The frame's projection: the focus is a plane for perspective frames, a sphere otherwise.
    pub projection: Projection,
}

impl Exposure<'_> {
    /// Whether the exposure changes no ray: no motion and no aperture.
    pub fn is_sharp(&self) -> bool {
        self.shutter_close.is_none() && self.lens.is_none_or(|l| l.aperture == 0.0)
    }

    /// Moves the rays of pass `pass` of `passes` of this frame (row-major, one per pixel, as
    /// [`Camera::frame_rays_at`] casts them from [`camera`](Self::camera); `origins` and unit
    /// `dirs` of 3 floats each) to where the lens and the moving shutter put them
    /// ([`pass_sample`] with `seed`, which should differ from frame to frame). The directions stay
    /// unit length. A sharp exposure leaves the rays as they are.
    pub fn apply(&self, pass: usize, passes: usize, seed: u64, origins: &mut [f32], dirs: &mut [f32]) {
        if self.is_sharp() {
            return;
        }
        let q_open = self.camera.orientation();
        let to_camera = q_open.inverse();
        let close = self.shutter_close.map(|c| (c.orientation(), c.position));
        let lens = self.lens.filter(|l| l.aperture > 0.0);
        let point = pass_point(pass, passes);
        origins.par_chunks_exact_mut(3).zip(dirs.par_chunks_exact_mut(3)).enumerate().for_each(|(pixel, (o, d))| {
            let [time, lu, lv] = shifted(point, pixel as u64, seed);
            let dir_cam = to_camera * Vec3::from_slice(d);
            let (q, position) = match close {
                Some((qc, pc)) => (q_open.slerp(qc, time).normalize(), Vec3::from_slice(o).lerp(pc, time)),
                None => (q_open, Vec3::from_slice(o)),
            };
            let mut origin = position;
            let mut dir = q * dir_cam;
            if let Some(l) = lens {
                // Where the pinhole ray meets the surface in focus.
                let reach = match self.projection {
                    Projection::Perspective => match -dir_cam.z {
                        depth if depth > 1e-6 => l.focus_distance / depth,
                        _ => f32::NAN, // parallel to the focal plane: no point in focus
                    },
                    Projection::Equirectangular | Projection::Fisheye => l.focus_distance,
                };
                if reach.is_finite() {
                    let focus = origin + dir * reach;
                    let [bx, by] = concentric_disk([lu, lv]);
                    origin += q * Vec3::new(bx * l.aperture, by * l.aperture, 0.0);
                    dir = focus - origin;
                }
            }
            let dir = dir.normalize();
            o.copy_from_slice(&origin.to_array());
            d.copy_from_slice(&dir.to_array());
        });
    }
}

/// Pixel `pixel`'s sample of pass `pass` of `passes`: `[time, lens_u, lens_v]`, each in `[0, 1)`.
/// Over the `passes` passes, `time` takes one value in each `1/passes` of `[0, 1)` and
/// `(lens_u, lens_v)` the points of a rank-1 lattice over the unit square (the lattice of
/// [`PixelConvention::sample_offsets`](crate::PixelConvention::sample_offsets)), all shifted
/// modulo 1 by a hash of `pixel` and `seed`, so that each pixel takes its own.
pub fn pass_sample(pixel: u64, pass: usize, passes: usize, seed: u64) -> [f32; 3] {
    shifted(pass_point(pass, passes), pixel, seed)
}

/// The unshifted point of pass `pass` of `passes` (the same for every pixel).
fn pass_point(pass: usize, passes: usize) -> [f64; 3] {
    let n = passes.max(1);
    let [x, y] = crate::lattice_point(pass % n, n);
    [((pass % n) as f64 + 0.5) / n as f64, x, y]
}

/// `point` shifted modulo 1 by a hash of `pixel` and `seed` (21 bits a coordinate).
#[inline]
fn shifted(point: [f64; 3], pixel: u64, seed: u64) -> [f32; 3] {
    let h = mix64(seed ^ mix64(pixel.wrapping_add(0x9e37_79b9_7f4a_7c15)));
    let shift = |k: u32| ((h >> (k * 21)) & 0x1f_ffff) as f64 / (1u64 << 21) as f64;
    // Below 1 after rounding to f32 too (the largest f32 under 1 is 1 − ε/2).
    std::array::from_fn(|k| ((point[k] + shift(k as u32)).fract() as f32).min(1.0 - f32::EPSILON / 2.0))
}

/// splitmix64's finaliser: a well-mixed 64-bit hash of `x`.
fn mix64(mut x: u64) -> u64 {
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

/// Shirley and Chiu's concentric map of the unit square onto the unit disk (instant-ngp's
/// `square2disk_shirley`): area-preserving up to a constant, so uniform points stay uniform, and
/// strata of the square stay compact on the disk.
pub fn concentric_disk([u, v]: [f32; 2]) -> [f32; 2] {
    let (a, b) = (2.0 * u - 1.0, 2.0 * v - 1.0);
    if a == 0.0 && b == 0.0 {
        return [0.0, 0.0];
    }
    let quarter = std::f32::consts::FRAC_PI_4;
    let (r, phi) = if a.abs() > b.abs() { (a, quarter * (b / a)) } else { (b, 2.0 * quarter - quarter * (a / b)) };
    let (sin, cos) = phi.sin_cos();
    [r * cos, r * sin]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Intrinsics;

    fn camera(position: [f32; 3], yaw: f32) -> Camera {
        let k = Intrinsics::from_fov_x(12, 9, 0.9);
        let r = Mat3::from_rotation_z(yaw) * Mat3::from_cols(Vec3::X, Vec3::Z, -Vec3::Y); // looks down +y
        let c2w: Vec<[f32; 4]> = (0..3).map(|i| [r.row(i).x, r.row(i).y, r.row(i).z, position[i]]).collect();
        Camera::from_c2w(k, &c2w).unwrap()
    }

    fn rays(c: &Camera, projection: Projection) -> (Vec<f32>, Vec<f32>) {
        let (mut o, mut d) = (Vec::new(), Vec::new());
        c.frame_rays_at(projection, [0.5, 0.5], &mut o, &mut d);
        (o, d)
    }

    #[test]
    fn a_sharp_exposure_leaves_the_rays_bit_for_bit() {
        let c = camera([0.1, -2.0, 0.3], 0.2);
        let (o0, d0) = rays(&c, Projection::Perspective);
        for lens in [None, Some(ThinLens { aperture: 0.0, focus_distance: 2.0 })] {
            let e = Exposure { camera: &c, shutter_close: None, lens, projection: Projection::Perspective };
            assert!(e.is_sharp());
            let (mut o, mut d) = (o0.clone(), d0.clone());
            e.apply(3, 8, 7, &mut o, &mut d);
            assert_eq!((o, d), (o0.clone(), d0.clone()));
        }
    }

    /// Every ray of a pixel, whatever its lens point, goes through the pinhole ray's point on the
    /// focal plane (or sphere), leaves the lens disk in the camera's xy plane, and is unit length.
    #[test]
    fn lens_rays_meet_on_the_surface_in_focus() {
        let c = camera([0.4, -3.0, 0.2], -0.3);
        let fwd = -(c.orientation() * Vec3::Z);
        for projection in [Projection::Perspective, Projection::Fisheye, Projection::Equirectangular] {
            let lens = ThinLens { aperture: 0.15, focus_distance: 2.5 };
            let (o0, d0) = rays(&c, projection);
            let e = Exposure { camera: &c, shutter_close: None, lens: Some(lens), projection };
            let mut spread = 0.0f32;
            for pass in 0..8 {
                let (mut o, mut d) = (o0.clone(), d0.clone());
                e.apply(pass, 8, 11, &mut o, &mut d);
                for p in 0..o.len() / 3 {
                    let (origin, dir) = (Vec3::from_slice(&o[3 * p..]), Vec3::from_slice(&d[3 * p..]));
                    let pin = Vec3::from_slice(&d0[3 * p..]);
                    if projection == Projection::Perspective || pin.dot(fwd) > 0.05 {
                        // Off the lens plane by nothing, within the aperture.
                        let off = origin - c.position;
                        assert!(off.dot(fwd).abs() < 1e-5 && off.length() <= lens.aperture * (1.0 + 1e-5), "{projection:?} pixel {p}: {off}");
                        spread = spread.max(off.length());
                    }
                    assert!((dir.length() - 1.0).abs() < 1e-5);
                    let focus = match projection {
                        Projection::Perspective => c.position + pin * (lens.focus_distance / pin.dot(fwd)),
                        _ => c.position + pin * lens.focus_distance,
                    };
                    // The ray passes through the focus point: its offset from the ray is 0.
                    let to = focus - origin;
                    let miss = (to - dir * to.dot(dir)).length();
                    assert!(miss < 2e-5 * to.length().max(1.0), "{projection:?} pixel {p} pass {pass}: misses by {miss}");
                }
            }
            assert!(spread > 0.8 * lens.aperture, "{projection:?}: the lens points reach only {spread}");
        }
    }

    /// With the shutter open from one camera to another, each ray is the ray of the same pixel
    /// from the camera at its own moment, and over the passes a pixel's moments cover the
    /// shutter's time, one in each stratum.
    #[test]
    fn motion_blur_casts_each_ray_from_the_camera_at_its_moment() {
        let (a, b) = (camera([0.0, -3.0, 0.0], 0.0), camera([0.3, -2.8, 0.1], 0.25));
        let (o0, d0) = rays(&a, Projection::Perspective);
        let e = Exposure { camera: &a, shutter_close: Some(&b), lens: None, projection: Projection::Perspective };
        assert!(!e.is_sharp());
        let passes = 6;
        let mut moments = vec![Vec::new(); o0.len() / 3];
        for pass in 0..passes {
            let (mut o, mut d) = (o0.clone(), d0.clone());
            e.apply(pass, passes, 5, &mut o, &mut d);
            for p in 0..o.len() / 3 {
                let [t, _, _] = pass_sample(p as u64, pass, passes, 5);
                moments[p].push(t);
                let at = camera_lerp(&a, &b, t);
                let (mut oo, mut dd) = (Vec::new(), Vec::new());
                at.frame_rays_at(Projection::Perspective, [0.5, 0.5], &mut oo, &mut dd);
                for k in 0..3 {
                    assert!((o[3 * p + k] - oo[3 * p + k]).abs() < 1e-5, "pixel {p} pass {pass}: origin");
                    assert!((d[3 * p + k] - dd[3 * p + k]).abs() < 1e-5, "pixel {p} pass {pass}: direction");
                }
            }
        }
        for m in &moments {
            let mut strata: Vec<usize> = m.iter().map(|t| (t * passes as f32) as usize).collect();
            strata.sort_unstable();
            assert_eq!(strata, (0..passes).collect::<Vec<_>>());
        }
        // Different pixels take different moments.
        assert!(moments.iter().any(|m| m[0] != moments[0][0]));
        // camera_lerp's ends are the cameras.
        let (s, t) = (camera_lerp(&a, &b, 0.0), camera_lerp(&a, &b, 1.0));
        assert!((s.position - a.position).length() < 1e-6 && (t.position - b.position).length() < 1e-6);
        assert!(s.rotation.abs_diff_eq(a.rotation, 1e-6) && t.rotation.abs_diff_eq(b.rotation, 1e-6));
    }

    #[test]
    fn pass_samples_are_lattice_points_shifted_per_pixel() {
        for n in [1usize, 2, 5, 8, 16] {
            for pixel in [0u64, 1, 77, 1 << 40] {
                let s: Vec<[f32; 3]> = (0..n).map(|j| pass_sample(pixel, j, n, 9)).collect();
                assert!(s.iter().flatten().all(|&x| (0.0..1.0).contains(&x)));
                for axis in 0..3 {
                    // Shifted by one amount modulo 1, a lattice keeps one point in each stratum.
                    let mut strata: Vec<usize> = s.iter().map(|p| (p[axis] * n as f32) as usize).collect();
                    strata.sort_unstable();
                    assert_eq!(strata, (0..n).collect::<Vec<_>>(), "n {n} pixel {pixel} axis {axis}: {s:?}");
                }
            }
            // Deterministic, and the shift depends on the pixel and the seed.
            assert_eq!(pass_sample(3, 0, n, 1), pass_sample(3, 0, n, 1));
            assert_ne!(pass_sample(3, 0, n, 1), pass_sample(4, 0, n, 1));
            assert_ne!(pass_sample(3, 0, n, 1), pass_sample(3, 0, n, 2));
        }
    }

    /// The concentric map keeps the square's area fractions: uniform points stay uniform on the
    /// disk (equal counts in rings of equal area and in the four quadrants).
    #[test]
    fn the_concentric_map_is_uniform_on_the_disk() {
        let n = 1000;
        let (mut rings, mut quadrants) = ([0usize; 4], [0usize; 4]);
        for i in 0..n {
            for j in 0..n {
                let [x, y] = concentric_disk([(i as f32 + 0.5) / n as f32, (j as f32 + 0.5) / n as f32]);
                let r2 = x * x + y * y;
                assert!(r2 <= 1.0 + 1e-6);
                rings[((r2 * 4.0) as usize).min(3)] += 1;
                quadrants[usize::from(x < 0.0) * 2 + usize::from(y < 0.0)] += 1;
            }
        }
        let each = n * n / 4;
        for c in rings.iter().chain(&quadrants) {
            assert!((*c as f64 - each as f64).abs() < 0.01 * each as f64, "{rings:?} {quadrants:?}");
        }
        assert_eq!(concentric_disk([0.5, 0.5]), [0.0, 0.0]);
    }

    #[test]
    fn lenses_are_validated() {
        assert!(ThinLens { aperture: 0.1, focus_distance: 1.0 }.validate().is_ok());
        assert!(ThinLens { aperture: 0.0, focus_distance: 1.0 }.validate().is_ok());
        for (a, f) in [(-0.1, 1.0), (f32::NAN, 1.0), (0.1, 0.0), (0.1, f32::INFINITY), (0.1, -2.0)] {
            assert!(ThinLens { aperture: a, focus_distance: f }.validate().is_err(), "{a} {f}");
        }
    }
}
