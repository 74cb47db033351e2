//! 360° panoramas as training photos (nerfstudio's `"camera_model": "EQUIRECTANGULAR"`): each
//! panorama is cut into the six faces of a cube map, six pinhole views of 90° from the same
//! centre that together see every direction once, as nerfstudio's `ns-process-data` cuts
//! panoramas into planar views. Everything after loading (rays, masks, the GPU's ray kernel,
//! evaluation) then sees pinhole cameras only.
//!
//! The panorama's mapping is [`nerf_rays::Camera::equirect_dir`]'s (nerfstudio's): longitude
//! across the width, the image's centre looking forward (−z), the top row up (+y). A face's pixel
//! takes the bilinear sample of the panorama at its ray's direction, wrapping around in
//! longitude. The face size is `W/π` rounded down to a multiple of the downscale factor: at a
//! face's centre one face pixel spans the angle of one panorama pixel at the equator (six faces
//! hold 1.2× the panorama's pixels).

use glam::{Mat3, Vec3};
use nerf_rays::Intrinsics;
use rayon::prelude::*;

/// The six faces, in the order a panorama's views are listed: front (−z, the panorama's centre),
/// right (+x), back (+z), left (−x), up (+y), down (−y).
pub const FACES: [&str; 6] = ["front", "right", "back", "left", "up", "down"];

/// Face `f`'s rotation in the panorama camera's axes (columns: the face camera's x, y, z axes;
/// OpenGL camera axes, looking down −z): the face camera's rotation in the world is the
/// panorama's times this.
pub fn face_rotation(f: usize) -> Mat3 {
    use std::f32::consts::{FRAC_PI_2, PI};
    match f {
        0 => Mat3::IDENTITY,
        1 => Mat3::from_rotation_y(-FRAC_PI_2),
        2 => Mat3::from_rotation_y(PI),
        3 => Mat3::from_rotation_y(FRAC_PI_2),
        4 => Mat3::from_rotation_x(FRAC_PI_2),
        5 => Mat3::from_rotation_x(-FRAC_PI_2),
        _ => panic!("a cube has six faces, not face {f}"),
    }
}

/// The side of the faces of a `width`-wide panorama loaded with downscale factor `k`, before
/// downscaling: `width/π` rounded down to a multiple of `k`; `None` when that is 0.
pub fn face_size(width: u32, k: u32) -> Option<u32> {
    let s = (width as f64 / std::f64::consts::PI / k as f64).floor() as u32 * k;
    (s > 0).then_some(s)
}

/// A face's pinhole intrinsics at side `s`: 90° across, the principal point at the centre.
pub fn face_intrinsics(s: u32) -> Intrinsics {
    let f = 0.5 * s as f32;
    Intrinsics { width: s, height: s, fx: f, fy: f, cx: f, cy: f }
}

/// The continuous image coordinates `(u, v)` (pixel `k`'s centre at `k + ½`) of the unit
/// direction `d` (panorama camera axes) in a `width × height` panorama: the inverse of
/// [`nerf_rays::Camera::equirect_dir`], `u` in `[0, W)`.
pub fn panorama_uv(width: u32, height: u32, d: Vec3) -> (f64, f64) {
    let (x, y, z) = (d.x as f64, d.y as f64, d.z as f64);
    let theta = (-x).atan2(-z);
    let phi = y.clamp(-1.0, 1.0).acos();
    let u = 0.5 * width as f64 * (1.0 - theta / std::f64::consts::PI);
    (u.rem_euclid(width as f64), height as f64 * phi / std::f64::consts::PI)
}

/// Face `f` (side `s`) of a panorama `px` (straight RGBA, `4·W·H`, row-major): each face pixel
/// the bilinear sample at its centre's direction, wrapping around in longitude and clamped at the
/// poles.
///
/// # Panics
/// If `px` is not `4·W·H` long.
pub fn face_rgba(px: &[f32], width: u32, height: u32, f: usize, s: u32) -> Vec<f32> {
    let (w, h) = (width as usize, height as usize);
    assert_eq!(px.len(), 4 * w * h, "face_rgba: the panorama is not 4·W·H long");
    let rot = face_rotation(f);
    let k = face_intrinsics(s);
    let mut out = vec![0.0f32; 4 * (s * s) as usize];
    out.par_chunks_exact_mut(4 * s as usize).enumerate().for_each(|(j, row)| {
        for (i, o) in row.chunks_exact_mut(4).enumerate() {
            let d = rot * Vec3::new((i as f32 + 0.5 - k.cx) / k.fx, -(j as f32 + 0.5 - k.cy) / k.fy, -1.0);
            let (u, v) = panorama_uv(width, height, d.normalize());
            // Pixel-index space (pixel k's centre at k): columns wrap, rows clamp.
            let sx = u - 0.5;
            let sy = (v - 0.5).clamp(0.0, (h - 1) as f64);
            let (x0f, y0) = (sx.floor(), sy.floor() as usize);
            let (fx, fy) = ((sx - x0f) as f32, (sy - y0 as f64) as f32);
            let x0 = (x0f as i64).rem_euclid(w as i64) as usize;
            let x1 = (x0 + 1) % w;
            let y1 = (y0 + 1).min(h - 1);
            for c in 0..4 {
                let p = |x: usize, y: usize| px[4 * (y * w + x) + c];
                let top = p(x0, y0) * (1.0 - fx) + p(x1, y0) * fx;
                let bottom = p(x0, y1) * (1.0 - fx) + p(x1, y1) * fx;
                o[c] = top * (1.0 - fy) + bottom * fy;
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nerf_rays::Camera;

    #[test]
    fn panorama_uv_inverts_equirect_dir() {
        let (w, h) = (64u32, 32u32);
        for (u, v) in [(0.5f32, 0.5f32), (31.5, 16.0), (10.25, 3.75), (63.9, 31.9), (48.0, 8.0)] {
            let d = Camera::equirect_dir(w, h, u, v);
            let (u2, v2) = panorama_uv(w, h, d);
            assert!((u2 - u as f64).abs() < 1e-4 && (v2 - v as f64).abs() < 1e-4, "({u}, {v}) -> ({u2}, {v2})");
        }
    }

    #[test]
    fn faces_look_where_their_names_say_and_cover_every_direction_once() {
        let want = [Vec3::NEG_Z, Vec3::X, Vec3::Z, Vec3::NEG_X, Vec3::Y, Vec3::NEG_Y];
        for (f, w) in want.iter().enumerate() {
            let r = face_rotation(f);
            assert!((r * Vec3::NEG_Z - *w).length() < 1e-6, "{}: looks along {}", FACES[f], r * Vec3::NEG_Z);
            assert!((r.determinant() - 1.0).abs() < 1e-6);
        }
        // A direction lies in the face whose axis it is closest to (|component| largest), and
        // projects inside that face's image.
        let mut rng = nerf_core::rng(3, 0);
        use rand::Rng;
        for _ in 0..1000 {
            let d = Vec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0)).normalize();
            let f = (0..6).max_by(|&a, &b| d.dot(want[a]).total_cmp(&d.dot(want[b]))).unwrap();
            let c = face_rotation(f).transpose() * d;
            assert!(c.z < 0.0 && (c.x / -c.z).abs() <= 1.0 + 1e-6 && (c.y / -c.z).abs() <= 1.0 + 1e-6, "{d} in {}", FACES[f]);
        }
    }

    #[test]
    fn a_face_samples_the_panorama_at_its_pixels_directions() {
        // A smooth panorama: colour = a function of the direction.
        let (w, h) = (256u32, 128u32);
        let colour = |d: Vec3| [0.5 + 0.4 * d.x, 0.5 + 0.4 * d.y, 0.5 + 0.4 * d.z, 1.0];
        let mut pano = Vec::with_capacity((4 * w * h) as usize);
        for v in 0..h {
            for u in 0..w {
                pano.extend(colour(Camera::equirect_dir(w, h, u as f32 + 0.5, v as f32 + 0.5)));
            }
        }
        let s = face_size(w, 1).unwrap();
        assert_eq!((s, face_size(w, 4), face_size(3, 1)), (81, Some(80), None));
        for f in 0..6 {
            let face = face_rgba(&pano, w, h, f, s);
            let k = face_intrinsics(s);
            let cam = Camera { intrinsics: k, rotation: face_rotation(f), position: Vec3::ZERO, distortion: nerf_rays::Distortion::NONE };
            let mut worst = 0.0f32;
            for j in 0..s {
                for i in 0..s {
                    let want = colour(cam.ray_at(i as f32 + 0.5, j as f32 + 0.5).dir);
                    let p = 4 * (j * s + i) as usize;
                    for c in 0..4 {
                        worst = worst.max((face[p + c] - want[c]).abs());
                    }
                }
            }
            // Bilinear interpolation of a function whose gradient is at most 0.4 per radian, over
            // pixels of 2π/256 rad: a fraction of a step, most near the poles.
            assert!(worst < 0.01, "{}: off by {worst}", FACES[f]);
        }
    }
}
