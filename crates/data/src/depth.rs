//! Depth maps for depth supervision: a per-frame image of each pixel's depth, as an RGB-D
//! capture (an iPhone's LiDAR through Polycam or Record3D, a Kinect, instant-ngp's NeRFCapture)
//! stores it beside the photo.
//!
//! - nerfstudio's `depth_file_path` (depth-nerfacto's input): integer values times
//!   `depth_unit_scale_factor` (a top-level key where the file has one, else nerfstudio's
//!   default 10⁻³: millimetres to metres).
//! - instant-ngp's `depth_path`: integer values times the top-level `integer_depth_scale`
//!   (required with it).
//!
//! Values are z-depths (the distance along the camera's optical axis, as both tools and every
//! RGB-D sensor store them) in the file's world units; 0 marks a pixel without a measurement. A
//! panorama's map ([`crate::equirect`]) holds distances along the rays instead (a panorama has no
//! optical axis; nerfstudio reads an equirectangular camera's depths so).
//! The maps are single-channel 8- or 16-bit PNGs or `.npy` arrays (nerfstudio reads both; an
//! array's values are scaled the same way), of the photo's size or of its shape (a
//! sensor's smaller map is enlarged by nearest neighbour, as nerfstudio does). Loading ([`crate::Dataset::depths`]) turns
//! them into the distance along each pixel's unit ray from the camera centre, in the scene's
//! units (nerfstudio's normalisation scales them with the poses), after the photo's lens
//! resampling and `--downscale`; a resulting pixel has a depth only where every pixel it is made
//! of has one and their depths agree ([`MAX_RELATIVE_SPREAD`]: not across a silhouette).

use std::path::Path;

use nerf_rays::Camera;

use crate::DataError;

/// Where a frame's depth map comes from and what one integer step of it measures.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthSource<'a> {
    /// The depth image.
    pub path: &'a Path,
    /// World units per integer step of the image's values.
    pub scale: f64,
}

/// nerfstudio's default `depth_unit_scale_factor`: millimetres to metres.
pub const NERFSTUDIO_DEPTH_SCALE: f64 = 1e-3;

/// How far the depths a resampled pixel is made of may spread: a standard deviation above this
/// share of their mean (a silhouette, foreground and background averaged into a depth where
/// nothing is) leaves the pixel without a depth.
pub const MAX_RELATIVE_SPREAD: f32 = 0.05;

/// Decodes the depth image at `path` (frame `frame`, whose photo is `size`) into an RGBA-shaped
/// buffer for the photo's resampling: per pixel `(z, 1, z², 1)` where it has a measurement (`z`
/// in world units) and `(0, 0, 0, 1)` where it has none. Resampling (bilinear, box) averages
/// every channel, so the third keeps the second moment of what a pixel is made of. A map smaller
/// or larger than the photo, of its shape (aspect ratios within 1 %), is first resized to it by
/// nearest neighbour. A `.npy` file holds the values as an array. An error names the file:
/// missing, not a single-channel 8- or 16-bit image or a 2-D array, or of another shape.
pub(crate) fn decode(src: DepthSource<'_>, frame: usize, size: (u32, u32)) -> Result<Vec<f32>, DataError> {
    let bad = |reason: String| DataError::BadDepth { path: src.path.to_path_buf(), frame, reason };
    if !src.path.is_file() {
        return Err(bad("file not found".into()));
    }
    let npy = src.path.extension().is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    // Raw values (0, or not finite: no measurement) and the map's size.
    let (dw, dh, values): (u32, u32, Vec<f64>) = if npy {
        read_npy(src.path).map_err(bad)?
    } else {
        let img = crate::open_image(src.path)?.decode().map_err(|source| DataError::Decode { path: src.path.to_path_buf(), source })?;
        let (dw, dh) = (img.width(), img.height());
        let values = match img {
            image::DynamicImage::ImageLuma16(b) => b.into_raw().into_iter().map(f64::from).collect(),
            image::DynamicImage::ImageLuma8(b) => b.into_raw().into_iter().map(f64::from).collect(),
            other => {
                return Err(bad(format!(
                    "a depth map must be a single-channel 8- or 16-bit image of integer depths (or a .npy array), this one is {:?}",
                    other.color()
                )))
            }
        };
        (dw, dh, values)
    };
    // A depth sensor's map is often smaller than the photo (an iPhone's LiDAR: 256×192 beside a
    // 1920×1440 photo, as Polycam and Record3D store them); of the photo's shape, it is enlarged.
    let aspect = |w: u32, h: u32| w as f64 / h as f64;
    if dw == 0 || dh == 0 || (aspect(dw, dh) / aspect(size.0, size.1) - 1.0).abs() > 0.01 {
        return Err(bad(format!("it is {dw}x{dh}, its photo is {}x{}: not the photo's shape", size.0, size.1)));
    }
    // Nearest neighbour to the photo's size (nerfstudio's resize of depth maps: OpenCV's
    // INTER_NEAREST, source index ⌊i·src/dst⌋), so no depth is blended across a silhouette.
    let values: Vec<f64> = if (dw, dh) == size {
        values
    } else {
        let (w, h) = (size.0 as u64, size.1 as u64);
        (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .map(|(i, j)| values[((j * dh as u64 / h) * dw as u64 + i * dw as u64 / w) as usize])
            .collect()
    };
    Ok(values
        .into_iter()
        .flat_map(|v| {
            let z = (v * src.scale) as f32;
            if z > 0.0 && z.is_finite() {
                [z, 1.0, z * z, 1.0]
            } else {
                [0.0, 0.0, 0.0, 1.0]
            }
        })
        .collect())
}

/// A depth map stored as a NumPy array (nerfstudio reads `.npy` depth files too): `H×W` or
/// `H×W×1`, C order, little-endian float32/float64 or unsigned 8/16/32-bit integers.
fn read_npy(path: &Path) -> Result<(u32, u32, Vec<f64>), String> {
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    let npy = npyz::NpyFile::new(&bytes[..]).map_err(|e| format!("not a .npy array: {e}"))?;
    let shape = npy.shape().to_vec();
    let (h, w) = match shape[..] {
        [h, w] | [h, w, 1] => (h, w),
        _ => return Err(format!("expected an H×W array, got shape {shape:?}")),
    };
    if npy.order() != npyz::Order::C {
        return Err("Fortran-ordered arrays are not supported".into());
    }
    let unreadable = |e: std::io::Error| format!("truncated or unreadable data: {e}");
    let values: Vec<f64> = match npy.dtype().descr().trim_matches(|c| c == '\'' || c == '"') {
        "<f4" => npy.into_vec::<f32>().map_err(unreadable)?.into_iter().map(f64::from).collect(),
        "<f8" => npy.into_vec::<f64>().map_err(unreadable)?,
        "<u2" => npy.into_vec::<u16>().map_err(unreadable)?.into_iter().map(f64::from).collect(),
        "|u1" => npy.into_vec::<u8>().map_err(unreadable)?.into_iter().map(f64::from).collect(),
        "<u4" => npy.into_vec::<u32>().map_err(unreadable)?.into_iter().map(f64::from).collect(),
        d => return Err(format!("expected float32/64 or unsigned integer depths, got dtype {d}")),
    };
    let (w, h) = (u32::try_from(w).map_err(|_| "too wide")?, u32::try_from(h).map_err(|_| "too high")?);
    Ok((w, h, values))
}

/// How much farther than its depth a point lies along the ray of image point `(u, v)`:
/// `|d| / (−d_z)` for the camera-axes direction `d` there ([`Camera::camera_dir`]; a pinhole
/// camera's `√(x² + y² + 1)`), `None` where the ray does not look forward (a fisheye past 90°).
pub fn depth_to_distance(cam: &Camera, u: f64, v: f64) -> Option<f64> {
    let d = cam.camera_dir(u, v);
    (d[2] < 0.0).then(|| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() / -d[2])
}

/// The depth map of a resampled, downscaled buffer from [`decode`] for `cam`: per pixel the
/// distance along its unit ray through the pixel's centre (`z·`[`depth_to_distance`], a pinhole
/// camera's `z·√(x² + y² + 1)`, through the camera's lens where it has one), times `scale` (the
/// poses' normalisation), or 0 where any of the pixels it was made of had no measurement (the
/// validity channel is below 1), where their depths spread by more than
/// [`MAX_RELATIVE_SPREAD`], or where the pixel's ray does not look forward (a fisheye past 90°:
/// a depth map holds depths along the optical axis).
pub(crate) fn ray_distances(px: &[f32], cam: &Camera, scale: f32) -> Vec<f32> {
    let w = cam.intrinsics.width as usize;
    px.chunks_exact(4)
        .enumerate()
        .map(|(p, d)| {
            let Some(z) = measured(d) else { return 0.0 };
            let Some(f) = depth_to_distance(cam, (p % w) as f64 + 0.5, (p / w) as f64 + 0.5) else { return 0.0 };
            (z as f64 * f) as f32 * scale
        })
        .collect()
}

/// As [`ray_distances`] for a buffer whose values are distances along the rays already (a
/// panorama's depth map, resampled to a face of its cube map): each measured value times `scale`.
pub(crate) fn ranges(px: &[f32], scale: f32) -> Vec<f32> {
    px.chunks_exact(4).map(|d| measured(d).map_or(0.0, |r| r * scale)).collect()
}

/// The value of a resampled pixel `(v, valid, v², 1)`, or `None` where any pixel it was made of
/// had no measurement or their values spread by more than [`MAX_RELATIVE_SPREAD`].
fn measured(d: &[f32]) -> Option<f32> {
    let variance = d[2] - d[0] * d[0];
    (d[1] >= 1.0 - 1e-6 && variance <= (MAX_RELATIVE_SPREAD * d[0]).powi(2)).then_some(d[0])
}

/// A sparse depth map of the camera `cam` from 3-D points (in its world): each point in front of
/// the camera that it images in its photo (through its lens, [`Camera::project`]) sets the pixel
/// it falls in to the distance along that pixel's ray through its centre at the point's depth
/// (`z·`[`depth_to_distance`], `z` the point's depth along the optical axis); of two points in
/// one pixel the nearer wins; every other pixel is 0.
pub fn sfm_depths(cam: &Camera, points: impl Iterator<Item = [f64; 3]>) -> Vec<f32> {
    let k = &cam.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let mut out = vec![0.0f32; w * h];
    for p in points {
        let q = nerf_rays::glam::Vec3::from_array(p.map(|c| c as f32));
        let c = cam.to_opencv(q);
        let z = c[2];
        let Some((u, v)) = cam.project_opencv(c).filter(|_| z > 0.0) else { continue };
        if !(u >= 0.0 && v >= 0.0 && u < w as f64 && v < h as f64) {
            continue;
        }
        let (col, row) = (u.floor() as usize, v.floor() as usize);
        let Some(f) = depth_to_distance(cam, col as f64 + 0.5, row as f64 + 0.5) else { continue };
        let t = (z * f) as f32;
        let o = &mut out[row * w + col];
        if *o == 0.0 || t < *o {
            *o = t;
        }
    }
    out
}

/// The inverse of the loader's conversion to ray distances (without its scale): per pixel of
/// `cam`, the z-depth `t / `[`depth_to_distance`] of a distance `t` along its ray (0 stays 0, as
/// does a pixel whose ray does not look forward).
pub fn z_depths(t: &[f32], cam: &Camera) -> Vec<f32> {
    let w = cam.intrinsics.width as usize;
    t.iter()
        .enumerate()
        .map(|(p, &d)| match depth_to_distance(cam, (p % w) as f64 + 0.5, (p / w) as f64 + 0.5) {
            Some(f) if d != 0.0 => (d as f64 / f) as f32,
            _ => 0.0,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nerf_rays::Intrinsics;

    #[test]
    fn z_depths_become_distances_along_the_pixels_rays() {
        let intr = Intrinsics { width: 3, height: 2, fx: 2.0, fy: 4.0, cx: 1.5, cy: 1.0 };
        // z = 2 everywhere but pixel 4, which a resampling mixed with a pixel without depth, and
        // pixels 3 and 5, which it made of z = 1 and z = 3 (3: ¾ and ¼; 5: 2 % spread).
        let mut px: Vec<f32> = (0..6).flat_map(|_| [2.0, 1.0, 4.0, 1.0]).collect();
        px[4 * 4 + 1] = 0.75;
        px[4 * 3..4 * 3 + 4].copy_from_slice(&[1.5, 1.0, 0.75 + 0.25 * 9.0, 1.0]);
        px[4 * 5..4 * 5 + 4].copy_from_slice(&[2.0, 1.0, 0.5 * (1.98f32 * 1.98 + 2.02 * 2.02), 1.0]);
        let cam = Camera::from_c2w(intr, &[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]).unwrap();
        let t = ray_distances(&px, &cam, 0.5);
        // Pixel (0, 0): x = (0.5 − 1.5)/2 = −0.5, y = (0.5 − 1)/4 = −0.125.
        assert!((t[0] - 2.0 * (0.25f32 + 0.015625 + 1.0).sqrt() * 0.5).abs() < 1e-6, "{}", t[0]);
        assert_eq!(t[4], 0.0, "no depth where a source had none");
        assert_eq!(t[3], 0.0, "no depth where the sources spread (a silhouette)");
        assert!(t[5] > 1.0, "a 1 % spread (a slanted surface) keeps its depth");
        // Pixel (1, 0): x = 0, y = −0.125.
        assert!((t[1] - (1.0f32 + 0.015625).sqrt()).abs() < 1e-6, "{}", t[1]);
        assert!(t.iter().enumerate().all(|(p, &v)| p == 4 || p == 3 || v >= 1.0), "{t:?}");
    }

    /// Through a lens, a depth becomes the distance along the ray the lens saw at the pixel, and
    /// back; a fisheye's pixels that look past 90° have no depth.
    #[test]
    fn depths_through_a_lens() {
        use nerf_rays::{Distortion, LensModel};
        let intr = Intrinsics { width: 40, height: 20, fx: 12.0, fy: 12.0, cx: 20.0, cy: 10.0 };
        let id = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]];
        let fish = Camera::from_c2w(intr, &id).unwrap().with_distortion(Distortion { model: LensModel::Fisheye, ..Distortion::NONE });
        let barrel = fish.with_distortion(Distortion { k1: -0.05, ..Distortion::NONE });
        let px: Vec<f32> = (0..800).flat_map(|_| [2.0, 1.0, 4.0, 1.0]).collect();
        for cam in [fish, barrel] {
            let t = ray_distances(&px, &cam, 1.0);
            for (p, &d) in t.iter().enumerate() {
                let ray = cam.ray_at((p % 40) as f32 + 0.5, (p / 40) as f32 + 0.5);
                let depth = -ray.dir.z; // the camera looks down −z
                if depth > 0.0 {
                    assert!((d * depth - 2.0).abs() < 1e-4, "pixel {p}: {d} along a ray of depth {depth} a unit");
                } else {
                    assert_eq!(d, 0.0, "pixel {p} looks sideways or back");
                }
            }
            let z = z_depths(&t, &cam);
            assert!(z.iter().zip(&t).all(|(&z, &t)| if t == 0.0 { z == 0.0 } else { (z - 2.0).abs() < 1e-5 }));
            assert_eq!(t.contains(&0.0), cam.distortion.model == LensModel::Fisheye, "the edges of a 190° fisheye look back");
        }
    }
}
