//! instant-ngp's and nerfstudio's extensions of the Blender transforms file, the format that
//! `colmap2nerf.py` (instant-ngp) and `ns-process-data` (nerfstudio) write for captured scenes.
//!
//! - **One file for all views.** A scene folder with `transforms.json` and no
//!   `transforms_<split>.json` holds every view in one list; as for LLFF scenes, every 8th frame
//!   (0, 8, 16, …, in file order) is a test (and val) view and the others are training views
//!   ([`crate::llff::split_indices`]), unless the file lists them as nerfstudio does
//!   (`train_filenames`, `val_filenames`, `test_filenames`: image paths as in `file_path`;
//!   [`split_filenames`]).
//! - **Intrinsics** ([`Lens`]): `fl_x`, `fl_y`, `cx`, `cy` (pixels of the stored image, pixel
//!   centres at `+0.5`), `w`, `h` (the stored images' size, checked), or the field of view
//!   `x_fov` / `y_fov` (degrees) or `camera_angle_x` / `camera_angle_y` (radians), in instant-ngp's
//!   order of precedence (`x_fov`, then `fl_x`, then `camera_angle_x`); each key may also sit in
//!   a frame, where it overrides the top level. Missing: `fl_y = fl_x` (or from `y_fov` /
//!   `camera_angle_y`), `cx = w/2`, `cy = h/2`.
//! - **Lens distortion** ([`Distortion`]): OpenCV's radial–tangential model (COLMAP's `OPENCV`,
//!   `RADIAL`, `SIMPLE_RADIAL`: `k1`, `k2`, `k3`, `p1`, `p2`) and OpenCV's fisheye model
//!   (nerfstudio's `camera_model: "OPENCV_FISHEYE"`, instant-ngp's `is_fisheye: true`: `k1` …
//!   `k4`). Each image is resampled to the pinhole camera of the same intrinsics when it is
//!   loaded ([`undistort_rgba`], bilinear), so rays stay pinhole rays on both devices. Output
//!   pixels whose source lies outside the photo ([`pixels_seen`]) take the nearest edge pixel in
//!   the image and are left out of training by its mask ([`crate::mask`]).
//! - **Scene box** ([`NgpBox`]): instant-ngp maps a world point `p` (the file's axes) to
//!   `p·scale + offset` and trains inside the cube `[0.5 − aabb_scale/2, 0.5 + aabb_scale/2]³` of
//!   that space (defaults `scale = 0.33`, `offset = [0.5, 0.5, 0.5]`, `aabb_scale = 1`: the
//!   NeRF-synthetic cube of half-extent 1.5; or `scale` and `offset` from an `aabb` key). A scene with any of these keys, or stored as one
//!   `transforms.json`, gets that cube as its [`Dataset::aabb`](crate::Dataset::aabb), rays that
//!   start [`NGP_NEAR`] (instant-ngp units) from the camera and end where they leave the cube;
//!   split Blender scenes without the keys keep NeRF's `near = 2`, `far = 6`.
//! - **nerfstudio's normalisation**: a file from nerfstudio's `ns-process-data` ([`is_nerfstudio`]:
//!   `applied_transform`, or `camera_model` without `aabb_scale`; no `scale` or `offset`) holds
//!   COLMAP's poses at
//!   COLMAP's arbitrary scale and orientation. The loader normalises them as nerfstudio's
//!   dataparser does ([`NerfstudioNormalization`]: mean up onto +z, mean centre to the origin,
//!   the farthest camera coordinate to 1), so the scene's cameras are in nerfstudio's frame (the
//!   frame of its viewer's camera paths) and it trains in nerfstudio's box `[−1, 1]³`, grown by
//!   `aabb_scale` when the file gives one.

use std::path::Path;

use nerf_rays::Intrinsics;
use rayon::prelude::*;
use serde_json::Value;

use crate::{json_kind, DataError};

/// The single transforms file of an instant-ngp / nerfstudio scene.
pub const NGP_TRANSFORMS: &str = "transforms.json";

/// Where rays start, in instant-ngp's units (`0.1 / scale` world units from the camera):
/// instant-ngp's training `near_distance`, closer than which it penalises density.
pub const NGP_NEAR: f32 = 0.1;

/// nerfstudio's explicit split: the `<split>_filenames` list of a transforms file, `None` when the
/// file has none of `train_filenames`, `val_filenames`, `test_filenames`. An error when it has
/// some but not this split's, or when the list is not an array of strings.
pub fn split_filenames(path: &Path, top: &Value, split: crate::Split) -> Result<Option<Vec<String>>, DataError> {
    if ["train", "val", "test"].iter().all(|s| top.get(format!("{s}_filenames")).is_none()) {
        return Ok(None);
    }
    let key = format!("{split}_filenames");
    let v = top.get(&key).ok_or_else(|| DataError::MissingKey { path: path.to_path_buf(), key: key.clone() })?;
    let bad = || DataError::InvalidValue { path: path.to_path_buf(), key: key.clone(), reason: format!("expected an array of strings, got {}", json_kind(v)) };
    let names = v.as_array().ok_or_else(bad)?;
    names.iter().map(|n| n.as_str().map(str::to_string).ok_or_else(bad)).collect::<Result<Vec<_>, _>>().map(Some)
}

pub use nerf_rays::lens::{Distortion, LensModel, COEFFICIENT_NAMES};

/// A focal length as a transforms file gives it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Focal {
    /// In pixels (`fl_x`, `fl_y`).
    Pixels(f64),
    /// As the full field of view along the axis, in radians (`camera_angle_x`, or `x_fov` in
    /// degrees).
    Angle(f64),
}

impl Focal {
    /// The focal length in pixels for an image `size` pixels along the axis:
    /// `0.5·size / tan(0.5·angle)` (in `f64`, as [`Intrinsics::from_fov_x`]).
    fn pixels(self, size: u32) -> f32 {
        match self {
            Focal::Pixels(f) => f as f32,
            Focal::Angle(a) => (0.5 * size as f64 / (0.5 * a).tan()) as f32,
        }
    }
}

/// The camera keys of one frame, after merging the frame's keys over the file's top level.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Lens {
    /// `w`, `h`: the size of the stored images the intrinsics refer to.
    pub size: Option<(u32, u32)>,
    /// The horizontal focal length: `x_fov`, else `fl_x`, else `camera_angle_x`.
    pub focal_x: Option<Focal>,
    /// The vertical focal length: `y_fov`, else `fl_y`, else `camera_angle_y` (`None`: `fx`).
    pub focal_y: Option<Focal>,
    /// `cx`.
    pub cx: Option<f64>,
    /// `cy`.
    pub cy: Option<f64>,
    /// The lens model (`camera_model`, `is_fisheye`) and its coefficients (`k1`..`k6`, `p1`,
    /// `p2`, `s1`..`s4`, or nerfstudio's `distortion_params`; `FOV`'s `omega`).
    pub distortion: Distortion,
    /// nerfstudio's `fisheye_crop_radius`, in pixels: only the disc of this radius about the
    /// principal point trains (a fisheye's image circle; the black beyond it is no scene).
    pub crop_radius: Option<f64>,
    /// nerfstudio's `"camera_model": "EQUIRECTANGULAR"`: the photo is a 360° panorama
    /// ([`crate::equirect`]; the focal keys and `cx`, `cy` are not used, distortion
    /// coefficients are refused).
    pub equirectangular: bool,
}

/// Reads `key` from the frame (when given) or else the top level; returns the value and the key's
/// name as an error should print it (`frames[3].fl_x` or `fl_x`).
fn lookup<'a>(top: &'a Value, frame: Option<(usize, &'a Value)>, key: &str) -> Option<(&'a Value, String)> {
    if let Some((i, f)) = frame {
        if let Some(v) = f.get(key) {
            return Some((v, format!("frames[{i}].{key}")));
        }
    }
    top.get(key).map(|v| (v, key.to_string()))
}

impl Lens {
    /// Parses and checks the camera keys of frame `frame` (`None`: the top level only) of the
    /// transforms file `path`.
    pub fn parse(path: &Path, top: &Value, frame: Option<(usize, &Value)>) -> Result<Self, DataError> {
        let invalid = |key: String, reason: String| DataError::InvalidValue { path: path.to_path_buf(), key, reason };
        let number = |key: &str| -> Result<Option<(f64, String)>, DataError> {
            match lookup(top, frame, key) {
                None | Some((Value::Null, _)) => Ok(None),
                Some((v, name)) => match v.as_f64() {
                    Some(x) if x.is_finite() => Ok(Some((x, name))),
                    Some(x) => Err(invalid(name, format!("{x} is not finite"))),
                    None => Err(invalid(name, format!("expected a number, got {}", json_kind(v)))),
                },
            }
        };
        let positive = |key: &str| -> Result<Option<f64>, DataError> {
            match number(key)? {
                Some((x, name)) if x <= 0.0 => Err(invalid(name, format!("{x} is not positive"))),
                v => Ok(v.map(|(x, _)| x)),
            }
        };
        let angle = |key: &str| -> Result<Option<f64>, DataError> {
            match number(key)? {
                Some((a, name)) if !(a > 0.0 && a < std::f64::consts::PI) => {
                    Err(invalid(name, format!("{a} is not in (0, pi)")))
                }
                v => Ok(v.map(|(a, _)| a)),
            }
        };
        let degrees = |key: &str| -> Result<Option<f64>, DataError> {
            match number(key)? {
                Some((a, name)) if !(a > 0.0 && a < 180.0) => Err(invalid(name, format!("{a} is not in (0, 180) degrees"))),
                v => Ok(v.map(|(a, _)| a.to_radians())),
            }
        };
        let focal = |fov: &str, fl: &str, angle_key: &str| -> Result<Option<Focal>, DataError> {
            let (fov, fl, a) = (degrees(fov)?, positive(fl)?, angle(angle_key)?);
            Ok(fov.map(Focal::Angle).or(fl.map(Focal::Pixels)).or(a.map(Focal::Angle)))
        };
        let pixels = |key: &str| -> Result<Option<u32>, DataError> {
            match number(key)? {
                None => Ok(None),
                Some((x, _)) if x >= 1.0 && x.fract() == 0.0 && x <= u32::MAX as f64 => Ok(Some(x as u32)),
                Some((x, name)) => Err(invalid(name, format!("{x} is not a positive whole number of pixels"))),
            }
        };
        // nerfstudio names the model (`camera_model`), instant-ngp flags a fisheye (`is_fisheye`).
        // `Named` says which coefficients the named model has (COLMAP's names; `FULL_OPENCV`'s
        // k4..k6 are its rational terms, a fisheye's k4 is its θ⁸ term).
        #[derive(Clone, Copy, PartialEq)]
        enum Named {
            /// OPENCV and its special cases: k1..k3, p1, p2.
            OpenCv,
            /// FULL_OPENCV: k1..k6 (k4..k6 rational), p1, p2, s1..s4.
            FullOpenCv,
            /// OPENCV_FISHEYE: k1..k4.
            Fisheye,
            /// THIN_PRISM_FISHEYE: k1..k4, p1, p2, s1..s4 (COLMAP's), and k5, k6 (θ¹⁰, θ¹²).
            ThinPrismFisheye,
            /// FISHEYE624: nerfstudio's `distortion_params` only.
            Fisheye624,
            /// FOV (COLMAP's): `omega` only.
            Fov,
            /// DIVISION and SIMPLE_DIVISION (COLMAP's): `k1` only.
            Division,
            /// EUCM (COLMAP's): `alpha` and `beta` only.
            Eucm,
            /// EQUIRECTANGULAR: none.
            Equirectangular,
        }
        let mut named: Option<(Named, String, String)> = None;
        if let Some((v, name)) = lookup(top, frame, "camera_model") {
            let model = v.as_str().ok_or_else(|| invalid(name.clone(), format!("expected a string, got {}", json_kind(v))))?;
            let m = match model {
                "OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE" | "RADIAL" | "SIMPLE_RADIAL" => Named::OpenCv,
                "FULL_OPENCV" => Named::FullOpenCv,
                "OPENCV_FISHEYE" => Named::Fisheye,
                "THIN_PRISM_FISHEYE" => Named::ThinPrismFisheye,
                "FISHEYE624" | "RAD_TAN_THIN_PRISM_FISHEYE" => Named::Fisheye624,
                "FOV" => Named::Fov,
                "DIVISION" | "SIMPLE_DIVISION" => Named::Division,
                "EUCM" => Named::Eucm,
                "EQUIRECTANGULAR" => Named::Equirectangular,
                _ => {
                    return Err(invalid(
                        name,
                        format!(
                            "camera model `{model}` is not supported (OPENCV, PINHOLE, SIMPLE_PINHOLE, RADIAL, SIMPLE_RADIAL, \
                             FULL_OPENCV, OPENCV_FISHEYE, THIN_PRISM_FISHEYE, FISHEYE624, FOV, DIVISION, EUCM and EQUIRECTANGULAR are)"
                        ),
                    ))
                }
            };
            named = Some((m, name, model.to_string()));
        }
        let mut kind = named.as_ref().map_or(Named::OpenCv, |(m, _, _)| *m);
        if let Some((v, name)) = lookup(top, frame, "is_fisheye") {
            let fisheye = v.as_bool().ok_or_else(|| invalid(name.clone(), format!("expected a boolean, got {}", json_kind(v))))?;
            if fisheye {
                match &named {
                    Some((Named::Equirectangular, model_key, _)) => {
                        return Err(invalid(name, format!("true, but `{model_key}` names an equirectangular camera")));
                    }
                    Some((Named::OpenCv | Named::FullOpenCv | Named::Fov | Named::Division | Named::Eucm, model_key, _)) => {
                        return Err(invalid(name, format!("true, but `{model_key}` names a camera model without a fisheye lens")));
                    }
                    Some(_) => {}
                    None => kind = Named::Fisheye,
                }
            }
        }
        let model_name = |default: &str| named.as_ref().map_or_else(|| default.to_string(), |(_, _, m)| m.clone());
        // nerfstudio's `distortion_params`: [k1, k2, k3, k4, p1, p2], or FISHEYE624's
        // [k0..k5, p0, p1, s0..s3].
        let mut c = [0.0f64; 12];
        let mut keys = Vec::new();
        for (i, key) in COEFFICIENT_NAMES.iter().enumerate() {
            if let Some((x, name)) = number(key)? {
                keys.push((i, x, name));
            }
        }
        // A frame's own keys replace the top level's, whichever form each takes; both forms
        // at one level are refused.
        let in_frame = |name: &str| name.starts_with("frames[");
        let listed = lookup(top, frame, "distortion_params").filter(|(_, n)| in_frame(n) || !keys.iter().any(|(_, _, k)| in_frame(k)));
        if let Some((_, list)) = &listed {
            if let Some((_, x, name)) = keys.iter().find(|(_, _, k)| in_frame(k) == in_frame(list)) {
                return Err(invalid(name.clone(), format!("{x}: the lens is given by `{list}` too")));
            }
            keys.clear();
        }
        if let Some((v, name)) = &listed {
            let wanted = if kind == Named::Fisheye624 { 12 } else { 6 };
            let values = v
                .as_array()
                .filter(|a| a.len() == wanted)
                .and_then(|a| a.iter().map(|x| x.as_f64().filter(|x| x.is_finite())).collect::<Option<Vec<f64>>>())
                .ok_or_else(|| {
                    invalid(
                        name.clone(),
                        format!(
                            "expected {wanted} finite numbers ({}), got {}",
                            if wanted == 12 { "FISHEYE624's k0..k5, p0, p1, s0..s3" } else { "k1, k2, k3, k4, p1, p2" },
                            v.as_array().map_or_else(|| json_kind(v).to_string(), |a| format!("{} values", a.len()))
                        ),
                    )
                })?;
            match kind {
                Named::Fisheye624 => {
                    // Aria's p0 goes with r² + 2x², as OpenCV's p2 does.
                    c[..6].copy_from_slice(&values[..6]);
                    (c[6], c[7]) = (values[7], values[6]);
                    c[8..].copy_from_slice(&values[8..]);
                }
                _ => {
                    c[..4].copy_from_slice(&values[..4]);
                    (c[6], c[7]) = (values[4], values[5]);
                }
            }
        }
        for (i, x, name) in keys {
            if kind == Named::Fisheye624 {
                return Err(invalid(name, format!("{x}: a {} lens's coefficients are read from `distortion_params` (k0..k5, p0, p1, s0..s3)", model_name(""))));
            }
            c[i] = x;
        }
        // Coefficients the model does not have would describe some other lens.
        let (model, has): (LensModel, &[&str]) = match kind {
            Named::OpenCv => (LensModel::RadialTangential, &["k1", "k2", "k3", "p1", "p2"]),
            Named::FullOpenCv => (LensModel::RadialTangential, &COEFFICIENT_NAMES),
            Named::Fisheye => (LensModel::Fisheye, &["k1", "k2", "k3", "k4"]),
            Named::ThinPrismFisheye => (LensModel::Fisheye, &COEFFICIENT_NAMES),
            Named::Fisheye624 => (LensModel::Fisheye624, &COEFFICIENT_NAMES),
            Named::Fov => (LensModel::Fov, &[]),
            Named::Division => (LensModel::Division, &["k1"]),
            Named::Eucm => (LensModel::Eucm, &[]),
            Named::Equirectangular => (LensModel::RadialTangential, &[]),
        };
        for (i, key) in COEFFICIENT_NAMES.iter().enumerate() {
            if c[i] == 0.0 || has.contains(key) {
                continue;
            }
            let name = listed.as_ref().map(|(_, n)| n.clone()).or_else(|| lookup(top, frame, key).map(|(_, n)| n)).unwrap_or_else(|| key.to_string());
            let reason = match (kind, *key) {
                (Named::Equirectangular, _) => {
                    let model_key = named.as_ref().map_or("camera_model", |(_, k, _)| k.as_str());
                    format!("{}: `{model_key}` names an equirectangular camera, which has no lens distortion", c[i])
                }
                (Named::OpenCv, "k4") => format!(
                    "{}: k4 belongs to the fisheye model (`\"camera_model\": \"OPENCV_FISHEYE\"` or `\"is_fisheye\": true`) \
                     or to FULL_OPENCV's rational terms, and this camera is neither",
                    c[i]
                ),
                (Named::Fisheye, "p1" | "p2") => format!("{}: the fisheye model has no tangential terms (THIN_PRISM_FISHEYE has)", c[i]),
                _ => format!("{}: the {} model has no coefficient `{key}`", c[i], model_name(if kind == Named::Fisheye { "fisheye" } else { "OPENCV" })),
            };
            return Err(invalid(name, reason));
        }
        let equirectangular = kind == Named::Equirectangular;
        // COLMAP's FOV lens: its field of view `omega` in radians, in (0, π).
        let omega = match number("omega")? {
            None if kind == Named::Fov => {
                let name = named.as_ref().map_or_else(|| "camera_model".to_string(), |(_, k, _)| k.clone());
                return Err(invalid(name, "FOV: the lens needs its field of view `omega` (radians)".into()));
            }
            None => 0.0,
            Some((w, name)) if kind != Named::Fov => {
                return Err(invalid(name, format!("{w}: omega belongs to the FOV model (`\"camera_model\": \"FOV\"`), and this camera is not one")));
            }
            Some((w, name)) if !(w > 0.0 && w < std::f64::consts::PI) => return Err(invalid(name, format!("{w} is not in (0, pi) radians"))),
            Some((w, _)) => w,
        };
        // COLMAP's EUCM lens: `alpha` in [0, 1] and `beta` above 0, both needed.
        let mut eucm = [0.0; 2];
        for (slot, key, valid, range) in [(0, "alpha", (|a: f64| (0.0..=1.0).contains(&a)) as fn(f64) -> bool, "in [0, 1]"), (1, "beta", |b: f64| b > 0.0, "above 0")] {
            eucm[slot] = match number(key)? {
                None if kind == Named::Eucm => {
                    let name = named.as_ref().map_or_else(|| "camera_model".to_string(), |(_, k, _)| k.clone());
                    return Err(invalid(name, format!("EUCM: the lens needs its `{key}`")));
                }
                None => 0.0,
                Some((x, name)) if kind != Named::Eucm => {
                    return Err(invalid(name, format!("{x}: {key} belongs to the EUCM model (`\"camera_model\": \"EUCM\"`), and this camera is not one")));
                }
                Some((x, name)) if !valid(x) => return Err(invalid(name, format!("{x} is not {range}"))),
                Some((x, _)) => x,
            };
        }
        let size = match (pixels("w")?, pixels("h")?) {
            (Some(w), Some(h)) => Some((w, h)),
            (None, None) => None,
            (Some(_), None) => return Err(DataError::MissingKey { path: path.to_path_buf(), key: "h".into() }),
            (None, Some(_)) => return Err(DataError::MissingKey { path: path.to_path_buf(), key: "w".into() }),
        };
        Ok(Self {
            size,
            focal_x: focal("x_fov", "fl_x", "camera_angle_x")?,
            focal_y: focal("y_fov", "fl_y", "camera_angle_y")?,
            cx: number("cx")?.map(|(x, _)| x),
            cy: number("cy")?.map(|(x, _)| x),
            distortion: Distortion { omega, alpha: eucm[0], beta: eucm[1], ..Distortion::from_coefficients(model, c) },
            crop_radius: positive("fisheye_crop_radius")?,
            equirectangular,
        })
    }

    /// The camera keys of the same camera's images downscaled by `k` (nerfstudio's
    /// `images_<k>/` copies): focal lengths in pixels and the principal point divided by `k`
    /// (a field of view stays as it is), the lens unchanged, no size to check (the tool that made
    /// the copies rounded theirs).
    pub fn downscaled(&self, k: u32) -> Lens {
        let k = k as f64;
        let focal = |f: Option<Focal>| {
            f.map(|f| match f {
                Focal::Pixels(p) => Focal::Pixels(p / k),
                angle => angle,
            })
        };
        Lens {
            size: None,
            focal_x: focal(self.focal_x),
            focal_y: focal(self.focal_y),
            cx: self.cx.map(|c| c / k),
            cy: self.cy.map(|c| c / k),
            distortion: self.distortion,
            crop_radius: self.crop_radius.map(|r| r / k),
            equirectangular: self.equirectangular,
        }
    }

    /// The pinhole intrinsics of an image of `width × height` pixels (before any downscaling):
    /// `0.5·W / tan(0.5·x_fov)` or `fl_x` or `0.5·W / tan(0.5·camera_angle_x)` (in `f64`, as
    /// [`Intrinsics::from_fov_x`]), likewise for `fy` or else `fx`, `cx` or `W/2`, `cy` or `H/2`. Errors:
    /// neither `fl_x` nor `camera_angle_x`, or `w`/`h` that differ from the image (`image` names it).
    pub fn intrinsics(&self, path: &Path, image: &Path, width: u32, height: u32) -> Result<Intrinsics, DataError> {
        if let Some((w, h)) = self.size {
            if (w, h) != (width, height) {
                return Err(DataError::InvalidValue {
                    path: path.to_path_buf(),
                    key: "w".into(),
                    reason: format!("the intrinsics are for {w}x{h} images, but {} is {width}x{height}", image.display()),
                });
            }
        }
        let Some(focal_x) = self.focal_x else {
            return Err(DataError::MissingKey { path: path.to_path_buf(), key: "camera_angle_x` or `fl_x".into() });
        };
        let fx = focal_x.pixels(width);
        let fy = self.focal_y.map_or(fx, |f| f.pixels(height));
        Ok(Intrinsics {
            width,
            height,
            fx,
            fy,
            cx: self.cx.map_or(width as f32 * 0.5, |c| c as f32),
            cy: self.cy.map_or(height as f32 * 0.5, |c| c as f32),
        })
    }
}

/// Resamples a photo taken through a lens with `distortion` to the pinhole camera `intr` (the
/// same intrinsics, no distortion): output pixel `(i, j)` (centre `(i + 0.5, j + 0.5)`, normalised
/// `x = (i + 0.5 − cx)/fx`, `y = (j + 0.5 − cy)/fy`) takes the bilinear sample of `px` at the
/// distorted position `(fx·x_d + cx, fy·y_d + cy)`, clamped to the image. `px`: straight RGBA,
/// `4·W·H`, row-major, `W × H` = `intr`'s size.
pub fn undistort_rgba(px: &[f32], intr: &Intrinsics, distortion: &Distortion) -> Vec<f32> {
    let (w, h) = (intr.width as usize, intr.height as usize);
    assert_eq!(px.len(), 4 * w * h, "undistort_rgba: the image is not 4·W·H long");
    let (fx, fy, cx, cy) = (intr.fx as f64, intr.fy as f64, intr.cx as f64, intr.cy as f64);
    let mut out = vec![0.0f32; 4 * w * h];
    out.par_chunks_exact_mut(4 * w).enumerate().for_each(|(j, row)| {
        let y = (j as f64 + 0.5 - cy) / fy;
        for (i, o) in row.chunks_exact_mut(4).enumerate() {
            let x = (i as f64 + 0.5 - cx) / fx;
            let (xd, yd) = distortion.distort(x, y);
            // Continuous position in pixel-index space (pixel k's centre at k).
            let sx = (fx * xd + cx - 0.5).clamp(0.0, (w - 1) as f64);
            let sy = (fy * yd + cy - 0.5).clamp(0.0, (h - 1) as f64);
            let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let (tx, ty) = ((sx - x0 as f64) as f32, (sy - y0 as f64) as f32);
            let at = |xx: usize, yy: usize| &px[4 * (yy * w + xx)..4 * (yy * w + xx) + 4];
            let (a, b, c, d) = (at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1));
            for k in 0..4 {
                let top = a[k] + (b[k] - a[k]) * tx;
                let bottom = c[k] + (d[k] - c[k]) * tx;
                o[k] = top + (bottom - top) * ty;
            }
        }
    });
    out
}

/// Which pixels of the pinhole image that [`undistort_rgba`] makes for `intr` and `distortion`
/// the photo saw: pixel `(i, j)` is seen when its distorted position `(fx·x_d + cx,
/// fy·y_d + cy)` lies in the photo, `[0, W] × [0, H]`, and, with a `crop` radius
/// (`fisheye_crop_radius`), within that many pixels of the principal point `(cx, cy)`. Without
/// distortion the position is the pixel's centre. `None` when every pixel is (always so without
/// distortion or crop). A pixel that is not seen took the photo's nearest edge pixel in the
/// resampled image, a colour from another direction, or lies past a fisheye's image circle: the
/// loader leaves it out of training ([`crate::Dataset::masks`]).
pub fn pixels_seen(intr: &Intrinsics, distortion: &Distortion, crop: Option<f64>) -> Option<Vec<bool>> {
    if distortion.is_identity() && crop.is_none() {
        return None;
    }
    let (w, h) = (intr.width as usize, intr.height as usize);
    let (fx, fy, cx, cy) = (intr.fx as f64, intr.fy as f64, intr.cx as f64, intr.cy as f64);
    let r2 = crop.map_or(f64::INFINITY, |r| r * r);
    let mut seen = vec![true; w * h];
    seen.par_chunks_exact_mut(w).enumerate().for_each(|(j, row)| {
        let y = (j as f64 + 0.5 - cy) / fy;
        for (i, s) in row.iter_mut().enumerate() {
            let (xd, yd) = distortion.distort((i as f64 + 0.5 - cx) / fx, y);
            let (sx, sy) = (fx * xd + cx, fy * yd + cy);
            *s = (0.0..=w as f64).contains(&sx) && (0.0..=h as f64).contains(&sy) && (sx - cx).powi(2) + (sy - cy).powi(2) <= r2;
        }
    });
    if seen.iter().all(|&s| s) {
        None
    } else {
        Some(seen)
    }
}

/// instant-ngp's placement of a scene in its unit cube: world point `p` ↦ `p·scale + offset`,
/// trained inside `[0.5 − aabb_scale/2, 0.5 + aabb_scale/2]³`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NgpBox {
    /// `scale` (0.33).
    pub scale: f32,
    /// `offset` (`[0.5, 0.5, 0.5]`), in the file's axis order.
    pub offset: [f32; 3],
    /// `aabb_scale` (1): the side of the training cube in instant-ngp units.
    pub aabb_scale: f32,
}

impl Default for NgpBox {
    fn default() -> Self {
        Self { scale: 0.33, offset: [0.5; 3], aabb_scale: 1.0 }
    }
}

impl NgpBox {
    /// Reads `scale`, `offset` and `aabb_scale` from the top level of a transforms file, or
    /// instead of `scale` and `offset` instant-ngp's `aabb` (`[[x0, y0, z0], [x1, y1, z1]]`, the
    /// scene's box in the file's units, as RGB-D capture tools write it): then, as instant-ngp
    /// does, `scale` = 1 / its longest side and `offset` = `0.5 − centre·scale`, which puts that
    /// box in the unit cube ([`NgpBox::enclosing`]; `aabb` wins over `scale` and `offset`).
    /// `None` when none of them is there.
    pub fn parse(path: &Path, top: &Value) -> Result<Option<Self>, DataError> {
        if ["scale", "offset", "aabb_scale", "aabb"].iter().all(|k| top.get(k).is_none()) {
            return Ok(None);
        }
        let invalid = |key: &str, reason: String| DataError::InvalidValue { path: path.to_path_buf(), key: key.into(), reason };
        let positive = |key: &str, default: f32| -> Result<f32, DataError> {
            match top.get(key) {
                None => Ok(default),
                Some(v) => match v.as_f64() {
                    Some(x) if x.is_finite() && x > 0.0 && (x as f32).is_normal() => Ok(x as f32),
                    Some(x) => Err(invalid(key, format!("{x} is not a positive finite number"))),
                    None => Err(invalid(key, format!("expected a number, got {}", json_kind(v)))),
                },
            }
        };
        let d = Self::default();
        let offset = match top.get("offset") {
            None => d.offset,
            Some(v) => {
                let bad = || invalid("offset", format!("expected an array of 3 finite numbers, got {}", v));
                let a = v.as_array().filter(|a| a.len() == 3).ok_or_else(bad)?;
                let o: Vec<f32> = a.iter().filter_map(Value::as_f64).map(|x| x as f32).filter(|x| x.is_finite()).collect();
                <[f32; 3]>::try_from(o).map_err(|_| bad())?
            }
        };
        let aabb_scale = positive("aabb_scale", d.aabb_scale)?;
        if let Some(v) = top.get("aabb") {
            let bad = || invalid("aabb", format!("expected [[x0, y0, z0], [x1, y1, z1]] of finite numbers, a box with a side, got {v}"));
            let corner = |c: &Value| -> Option<[f32; 3]> {
                let a = c.as_array().filter(|a| a.len() == 3)?;
                let x: Vec<f32> = a.iter().filter_map(Value::as_f64).map(|x| x as f32).filter(|x| x.is_finite()).collect();
                <[f32; 3]>::try_from(x).ok()
            };
            let corners = v.as_array().filter(|a| a.len() == 2).ok_or_else(bad)?;
            let (min, max) = (corner(&corners[0]).ok_or_else(bad)?, corner(&corners[1]).ok_or_else(bad)?);
            // instant-ngp takes the sides' absolute values; a box without extent has no scale.
            let lo: [f32; 3] = std::array::from_fn(|a| min[a].min(max[a]));
            let hi: [f32; 3] = std::array::from_fn(|a| min[a].max(max[a]));
            if (0..3).all(|a| hi[a] - lo[a] <= 0.0) {
                return Err(bad());
            }
            return Ok(Some(Self { aabb_scale, ..Self::enclosing(&nerf_rays::Aabb { min: lo, max: hi }) }));
        }
        Ok(Some(Self { scale: positive("scale", d.scale)?, offset, aabb_scale }))
    }

    /// The smallest box of this kind (`aabb_scale = 1`) that holds `aabb`: `scale` = 1 / its
    /// longest side, `offset` = `0.5 − centre·scale` (how a scene with other bounds, e.g. LLFF's
    /// Euclidean box, is written in this format).
    pub fn enclosing(aabb: &nerf_rays::Aabb) -> Self {
        let side = (0..3).map(|a| aabb.max[a] - aabb.min[a]).fold(0.0f32, f32::max);
        let scale = 1.0 / side;
        Self { scale, offset: std::array::from_fn(|a| 0.5 - 0.5 * (aabb.min[a] + aabb.max[a]) * scale), aabb_scale: 1.0 }
    }

    /// The training cube in world coordinates: `(min, max)` with
    /// `min = (0.5 − aabb_scale/2 − offset)/scale`, `max = (0.5 + aabb_scale/2 − offset)/scale`.
    pub fn world_aabb(&self) -> ([f32; 3], [f32; 3]) {
        let half = 0.5 * self.aabb_scale;
        (
            std::array::from_fn(|a| (0.5 - half - self.offset[a]) / self.scale),
            std::array::from_fn(|a| (0.5 + half - self.offset[a]) / self.scale),
        )
    }

    /// The distance along unit rays where rays start: [`NGP_NEAR`]` / scale`.
    pub fn near(&self) -> f32 {
        NGP_NEAR / self.scale
    }
}

/// Whether a transforms file is nerfstudio's (what `ns-process-data` writes): none of
/// instant-ngp's `scale`, `offset` and `aabb`, and either `applied_transform` (written only by nerfstudio)
/// or `camera_model` without `aabb_scale` (tools that write instant-ngp files with poses already
/// scaled, as `colmap2nerf.py` does, may add `camera_model`, but always write `aabb_scale`). Such a
/// scene gets nerfstudio's normalisation ([`NerfstudioNormalization`]) instead of instant-ngp's
/// default placement.
pub fn is_nerfstudio(top: &Value) -> bool {
    let has = |k: &str| top.get(k).is_some();
    !has("scale") && !has("offset") && !has("aabb") && (has("applied_transform") || (has("camera_model") && !has("aabb_scale")))
}

/// nerfstudio's normalisation of captured poses (its `nerfstudio` dataparser with the defaults
/// `orientation_method = "up"`, `center_method = "poses"`, `auto_scale_poses = true`,
/// `scene_scale = 1`; `camera_utils.auto_orient_and_center_poses`): rotate the mean camera up
/// vector onto +z, move the mean camera centre `c` to the origin, then scale by
/// `s = 1 / max |t'|` over every rotated, centred camera centre and axis. The scene then trains in
/// the cube `[−1, 1]³` ([`NerfstudioNormalization::BOX`]), which holds every camera. Its other
/// dataparser options ([`NerfstudioOptions`]) turn, centre and scale otherwise
/// ([`NerfstudioNormalization::with_options`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NerfstudioNormalization {
    /// The rotation (rows), applied after centring.
    pub rotation: [[f64; 3]; 3],
    /// The point moved to the origin, `c` (file coordinates): the mean camera centre unless
    /// `center_method` says otherwise.
    pub center: [f64; 3],
    /// The scale `s`.
    pub scale: f64,
}

impl NerfstudioNormalization {
    /// nerfstudio's scene box `[−1, 1]³` as an instant-ngp box (`p·0.5 + 0.5` in `[0, 1]`);
    /// an `aabb_scale` in the file grows it about the origin.
    pub const BOX: NgpBox = NgpBox { scale: 0.5, offset: [0.5; 3], aabb_scale: 1.0 };

    /// The normalisation of cameras with these camera-to-world matrices (3 or 4 rows), with
    /// nerfstudio's default options. `None` when there are none, their up vectors cancel out, or
    /// their centres all coincide (a single view: nothing to scale by).
    pub fn of(c2ws: &[&[[f32; 4]]]) -> Option<Self> {
        Self::with_options(c2ws, &NerfstudioOptions::default())
    }

    /// The normalisation of these cameras with nerfstudio's dataparser options `opts`
    /// ([`NerfstudioOptions`]). `None` as [`of`](Self::of), and also when `auto_scale_poses`
    /// is off and `scale_factor` is not positive and finite.
    pub fn with_options(c2ws: &[&[[f32; 4]]], opts: &NerfstudioOptions) -> Option<Self> {
        if c2ws.is_empty() || c2ws.iter().any(|m| m.len() < 3 || m.iter().flatten().any(|v| !v.is_finite())) {
            return None; // a bad pose is reported, with its frame, where the camera is built
        }
        let n = c2ws.len() as f64;
        let col = |m: &[[f32; 4]], c: usize| -> [f64; 3] { std::array::from_fn(|r| m[r][c] as f64) };
        let mean = |c: usize| -> [f64; 3] {
            let mut acc = [0.0; 3];
            for m in c2ws {
                let v = col(m, c);
                (0..3).for_each(|a| acc[a] += v[a] / n);
            }
            acc
        };
        let center = match opts.center_method {
            CenterMethod::Poses => mean(3),
            CenterMethod::Focus => focus_of_attention(c2ws, mean(3)),
            CenterMethod::None => [0.0; 3],
        };
        let rotation = match opts.orientation_method {
            OrientationMethod::Up => rotation_between(mean(1), [0.0, 0.0, 1.0])?,
            OrientationMethod::Vertical => rotation_between(vertical_up(c2ws, mean(1))?, [0.0, 0.0, 1.0])?,
            OrientationMethod::None => [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let scale = if opts.auto_scale_poses {
            let mut extent = 0.0f64;
            for m in c2ws {
                let t = col(m, 3);
                let d: [f64; 3] = std::array::from_fn(|a| t[a] - center[a]);
                for row in &rotation {
                    extent = extent.max((row[0] * d[0] + row[1] * d[1] + row[2] * d[2]).abs());
                }
            }
            opts.scale_factor / extent
        } else {
            opts.scale_factor
        };
        (scale.is_finite() && scale > 0.0).then_some(Self { rotation, center, scale })
    }

    /// nerfstudio's `dataparser_transforms.json` for it: `{"transform": 3×4 [R | −R·c],
    /// "scale": s}`, so a point `p` of the file's frame is `s·(R·p − R·c)` in the normalised one
    /// (and a normalised point `q` is `Rᵀ·q/s + c` in the file's).
    pub fn to_json(&self) -> Value {
        let r = &self.rotation;
        let t: [f64; 3] = std::array::from_fn(|i| -(0..3).map(|j| r[i][j] * self.center[j]).sum::<f64>());
        let rows: Vec<[f64; 4]> = (0..3).map(|i| [r[i][0], r[i][1], r[i][2], t[i]]).collect();
        serde_json::json!({ "transform": rows, "scale": self.scale })
    }

    /// A point of the file's frame in the normalised one: `s·R·(p − c)`.
    pub fn apply_point(&self, p: [f64; 3]) -> [f64; 3] {
        let d: [f64; 3] = std::array::from_fn(|a| p[a] - self.center[a]);
        std::array::from_fn(|i| self.scale * (0..3).map(|k| self.rotation[i][k] * d[k]).sum::<f64>())
    }

    /// A camera-to-world matrix (3 or 4 rows) in the normalised frame: `R·rotation_block`,
    /// `s·R·(t − c)`; the bottom row of a 4×4 matrix is left as it is.
    pub fn apply(&self, c2w: &mut [[f32; 4]]) {
        let r = &self.rotation;
        let m: [[f64; 4]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| c2w[i][j] as f64));
        for i in 0..3 {
            for j in 0..3 {
                c2w[i][j] = (r[i][0] * m[0][j] + r[i][1] * m[1][j] + r[i][2] * m[2][j]) as f32;
            }
            let d: [f64; 3] = std::array::from_fn(|a| m[a][3] - self.center[a]);
            c2w[i][3] = (self.scale * (r[i][0] * d[0] + r[i][1] * d[1] + r[i][2] * d[2])) as f32;
        }
    }

    /// The inverse of [`NerfstudioNormalization::apply`]: a camera-to-world matrix of the
    /// normalised frame in the file's, `Rᵀ·rotation_block`, `Rᵀ·t / s + c`.
    pub fn unapply(&self, c2w: &mut [[f32; 4]]) {
        let r = &self.rotation;
        let m: [[f64; 4]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| c2w[i][j] as f64));
        for i in 0..3 {
            for j in 0..3 {
                c2w[i][j] = (r[0][i] * m[0][j] + r[1][i] * m[1][j] + r[2][i] * m[2][j]) as f32;
            }
            c2w[i][3] = ((r[0][i] * m[0][3] + r[1][i] * m[1][3] + r[2][i] * m[2][3]) / self.scale + self.center[i]) as f32;
        }
    }
}

/// How nerfstudio's dataparser turns captured poses (`orientation_method`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OrientationMethod {
    /// The mean camera up vector onto +z (nerfstudio's default).
    #[default]
    Up,
    /// The direction that projects most nearly vertically in every image onto +z (for cameras
    /// that do not all look the same way; nerfstudio's `vertical`, its SVD of the cameras' x axes,
    /// signed by the mean up vector).
    Vertical,
    /// No turn.
    None,
}

/// Where nerfstudio's dataparser puts the origin (`center_method`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CenterMethod {
    /// The mean camera centre (nerfstudio's default).
    #[default]
    Poses,
    /// The focus of attention: the point nearest the optical axes of the cameras that have it in
    /// front of them (inward-looking captures).
    Focus,
    /// The file's origin.
    None,
}

/// nerfstudio's dataparser options for a capture's poses (`ns-train … nerfstudio-data
/// --orientation-method … --center-method … --auto-scale-poses … --scale-factor …`): how
/// [`NerfstudioNormalization::with_options`] turns, centres and scales them. The defaults are
/// nerfstudio's. Its `pca` orientation is not offered: the eigenvectors' signs it leaves to
/// LAPACK decide its frame.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NerfstudioOptions {
    /// How the poses are turned.
    pub orientation_method: OrientationMethod,
    /// Where the origin goes.
    pub center_method: CenterMethod,
    /// Scale the poses so that the farthest camera coordinate is 1 (then by `scale_factor`).
    pub auto_scale_poses: bool,
    /// A further scale of the poses (the only one without `auto_scale_poses`).
    pub scale_factor: f64,
}

impl Default for NerfstudioOptions {
    fn default() -> Self {
        Self { orientation_method: OrientationMethod::Up, center_method: CenterMethod::Poses, auto_scale_poses: true, scale_factor: 1.0 }
    }
}

impl NerfstudioOptions {
    /// Errors on a `scale_factor` that is not positive and finite.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.scale_factor.is_finite() && self.scale_factor > 0.0) {
            return Err(format!("scale_factor {}: must be finite and above 0", self.scale_factor));
        }
        Ok(())
    }
}

/// nerfstudio's `focus_of_attention`: starting from `initial`, the least-squares nearest point
/// to the optical axes (`−z`) of the cameras that have the current point in front of them,
/// repeated until that set of cameras stops changing; with fewer than two such cameras, the
/// point so far (`initial` when no camera looks towards it: outward-looking captures).
fn focus_of_attention(c2ws: &[&[[f32; 4]]], initial: [f64; 3]) -> [f64; 3] {
    use nerf_rays::glam::{DMat3, DVec3};
    let rays: Vec<(DVec3, DVec3)> =
        c2ws.iter().map(|m| (DVec3::new(m[0][3] as f64, m[1][3] as f64, m[2][3] as f64), -DVec3::new(m[0][2] as f64, m[1][2] as f64, m[2][2] as f64))).collect();
    let mut focus = DVec3::from_array(initial);
    let in_front = |f: DVec3, set: &[usize]| -> Vec<usize> { set.iter().copied().filter(|&i| rays[i].1.dot(f - rays[i].0) > 0.0).collect() };
    let mut active = in_front(focus, &(0..rays.len()).collect::<Vec<_>>());
    while active.len() > 1 {
        // Σ MᵀM and Σ MᵀM·o over the active cameras, M = I − d·dᵀ (a projection: MᵀM = M).
        let (mut a, mut b) = (DMat3::ZERO, DVec3::ZERO);
        for &i in &active {
            let (o, d) = rays[i];
            let m = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
            let mtm = m.transpose() * m;
            a += mtm;
            b += mtm * o;
        }
        if a.determinant().abs() < 1e-12 {
            break; // parallel axes: no single nearest point
        }
        focus = a.inverse() * b;
        let next = in_front(focus, &active);
        if next.len() == active.len() {
            break; // the set did not change
        }
        active = next;
    }
    focus.to_array()
}

/// nerfstudio's `vertical` up direction: the right singular vector of the stacked camera x axes
/// with the smallest singular value (the direction most nearly orthogonal to every x axis), signed
/// to agree with the mean up vector `up`; where the second singular value is at most
/// `0.17·√n` (cameras that all look one way: the direction is not determined), `up` with its
/// component along the first singular vector removed instead. `None` when that leaves nothing.
fn vertical_up(c2ws: &[&[[f32; 4]]], up: [f64; 3]) -> Option<[f64; 3]> {
    use nerf_rays::glam::DVec3;
    let up = DVec3::from_array(up).try_normalize()?;
    // XᵀX of the n×3 matrix of x axes: its eigenvectors are X's right singular vectors, its
    // eigenvalues the squared singular values.
    let mut xtx = [[0.0f64; 3]; 3];
    for m in c2ws {
        let x = [m[0][0] as f64, m[1][0] as f64, m[2][0] as f64];
        for i in 0..3 {
            for j in 0..3 {
                xtx[i][j] += x[i] * x[j];
            }
        }
    }
    let (values, vectors) = symmetric_eigen(xtx);
    // Descending singular values, as the SVD gives them.
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| values[j].total_cmp(&values[i]));
    let v = |k: usize| DVec3::from_array(vectors[order[k]]);
    let second = values[order[1]].max(0.0).sqrt();
    let dir = if second > 0.17 * (c2ws.len() as f64).sqrt() {
        let w = v(2);
        if w.dot(up) > 0.0 {
            w
        } else {
            -w
        }
    } else {
        (up - v(0) * up.dot(v(0))).try_normalize()?
    };
    Some(dir.to_array())
}

/// Eigenvalues and unit eigenvectors of a symmetric 3×3 matrix by cyclic Jacobi rotations
/// (converged to rounding: a few sweeps).
fn symmetric_eigen(mut a: [[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]; // columns: eigenvectors
    for _ in 0..50 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        if off <= 1e-300 || off <= 1e-15 * (a[0][0].abs() + a[1][1].abs() + a[2][2].abs()) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let (c, s) = (1.0 / (t * t + 1.0).sqrt(), t / (t * t + 1.0).sqrt());
            // A ← Jᵀ·A·J with J the rotation in the (p, q) plane.
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2]], std::array::from_fn(|k| [v[0][k], v[1][k], v[2][k]]))
}

/// nerfstudio's `rotation_matrix_between(a, b)`: the rotation about `a × b` taking the direction
/// of `a` onto that of `b` (Rodrigues' formula); for (anti)parallel vectors the axis is `a × x̂`
/// (or `a × ŷ` when `a` has no x part). `None` when `a` or `b` is zero or not finite.
fn rotation_between(a: [f64; 3], b: [f64; 3]) -> Option<[[f64; 3]; 3]> {
    use nerf_rays::glam::{DMat3, DQuat, DVec3};
    let (a, b) = (DVec3::from_array(a).try_normalize()?, DVec3::from_array(b).try_normalize()?);
    let q = if a.cross(b).abs().element_sum() < 1e-6 {
        // (Anti)parallel: nerfstudio's axis, turned by the angle between them (0 or π).
        let x = if a.x.abs() < 1e-6 { DVec3::X } else { DVec3::Y };
        DQuat::from_axis_angle(a.cross(x).normalize(), a.dot(b).clamp(-1.0, 1.0).acos())
    } else {
        DQuat::from_rotation_arc(a, b) // the rotation about a × b: Rodrigues' formula
    };
    let m = DMat3::from_quat(q);
    Some(std::array::from_fn(|i| std::array::from_fn(|j| m.col(j)[i])))
}

#[cfg(test)]
mod tests {
    use super::{rotation_between, symmetric_eigen, Distortion, LensModel};

    /// The Jacobi solver: A·v = λ·v with orthonormal v, for a generic, a diagonal and a
    /// degenerate symmetric matrix.
    #[test]
    fn symmetric_eigen_decomposes() {
        for a in [[[4.0, 1.0, -2.0], [1.0, 2.0, 0.5], [-2.0, 0.5, 3.0]], [[2.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 5.0]], [[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]] {
            let (values, vectors) = symmetric_eigen(a);
            for k in 0..3 {
                let v = vectors[k];
                for i in 0..3 {
                    let av: f64 = (0..3).map(|j| a[i][j] * v[j]).sum();
                    assert!((av - values[k] * v[i]).abs() < 1e-12, "{a:?}: λ {} v {v:?}", values[k]);
                }
                for (l, w) in vectors.iter().enumerate() {
                    let dot: f64 = (0..3).map(|i| v[i] * w[i]).sum();
                    assert!((dot - (k == l) as u8 as f64).abs() < 1e-12);
                }
            }
            let trace: f64 = values.iter().sum();
            assert!((trace - (a[0][0] + a[1][1] + a[2][2])).abs() < 1e-12);
        }
    }

    /// OpenCV's fisheye model: without terms it is the equidistant fisheye (a ray θ off the axis
    /// lands θ focal lengths from the principal point), the one `nerf render --camera-type
    /// fisheye` renders (`Camera::fisheye_dir` takes the pixel back to the ray); with terms,
    /// `θ_d = θ·(1 + k1·θ² + k2·θ⁴ + k3·θ⁶ + k4·θ⁸)` (the value worked out apart, in Python).
    #[test]
    fn the_fisheye_model_is_opencvs() {
        let equidistant = Distortion { model: LensModel::Fisheye, ..Default::default() };
        assert!(!equidistant.is_identity(), "a fisheye without terms is not a pinhole");
        let intr = nerf_rays::Intrinsics { width: 64, height: 48, fx: 20.0, fy: 21.0, cx: 31.0, cy: 24.5 };
        let cam = nerf_rays::Camera::from_c2w(intr, &[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]).unwrap();
        for theta in [0.05f64, 0.4, 1.0, 1.45] {
            for phi in [0.3f64, 2.0, -2.5] {
                // A ray in OpenCV's camera axes (z forward) and its pinhole coordinates.
                let d = [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()];
                let (xd, yd) = equidistant.distort(d[0] / d[2], d[1] / d[2]);
                assert!(((xd * xd + yd * yd).sqrt() - theta).abs() < 1e-12, "θ = {theta}");
                assert!((yd.atan2(xd) - phi).abs() < 1e-12, "the azimuth is kept");
                let back = cam.fisheye_dir((intr.fx as f64 * xd + intr.cx as f64) as f32, (intr.fy as f64 * yd + intr.cy as f64) as f32);
                // OpenGL's camera axes: y up, looking down −z.
                let want = [d[0] as f32, -d[1] as f32, -d[2] as f32];
                assert!((0..3).all(|a| (back[a] - want[a]).abs() < 1e-5), "{back:?} against {want:?}");
            }
        }
        assert_eq!(equidistant.distort(0.0, 0.0), (0.0, 0.0));
        let d = Distortion { model: LensModel::Fisheye, k1: 0.1, k2: -0.02, k3: 0.003, k4: -0.0004, ..Default::default() };
        let (xd, yd) = d.distort(0.3, -0.4);
        assert!((xd - 0.28391970170193026).abs() < 1e-14 && (yd + 0.37855960226924035).abs() < 1e-14, "({xd}, {yd})");
    }

    /// A rotation taking `a`'s direction onto `b`'s, for generic, parallel and opposite vectors.
    #[test]
    fn rotation_between_takes_a_onto_b() {
        let z = [0.0, 0.0, 1.0];
        for a in [[0.3, -1.2, 0.5], [0.0, 0.0, 2.0], [0.0, 0.0, -1.0], [1e-9, 0.0, -3.0], [0.0, 1.0, 0.0]] {
            let r = rotation_between(a, z).unwrap();
            let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
            let ra: Vec<f64> = (0..3).map(|i| (0..3).map(|j| r[i][j] * a[j] / n).sum()).collect();
            assert!((0..3).all(|i| (ra[i] - z[i]).abs() < 1e-9), "{a:?} → {ra:?}");
            for i in 0..3 {
                for j in 0..3 {
                    let dot: f64 = (0..3).map(|k| r[i][k] * r[j][k]).sum();
                    assert!((dot - (i == j) as u8 as f64).abs() < 1e-9, "orthonormal rows: {r:?}");
                }
            }
        }
        assert!(rotation_between([0.0; 3], z).is_none());
    }
}
