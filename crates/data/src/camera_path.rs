//! Camera paths in nerfstudio's `camera_path.json` format, read by `nerf render --camera-path`
//! and written beside every render so a path can be edited and rendered again.
//! [`read_camera_path`] also reads instant-ngp's ([`crate::ngp_path`]).
//!
//! The file (what nerfstudio's viewer exports and `ns-render camera-path` reads):
//!
//! ```json
//! { "camera_type": "perspective", "render_width": 800, "render_height": 800, "fps": 30,
//!   "camera_path": [ { "camera_to_world": [16 numbers, row-major 4×4], "fov": 50.0 }, … ] }
//! ```
//!
//! `fov` is the vertical field of view in degrees, so `fy = ½·H / tan(½·fov)`; pixels are square
//! (`fx = fy`) and the principal point is the image centre (as nerfstudio's
//! `get_path_from_json`). Poses use OpenGL axes (the camera looks down −z, +y up), as
//! `transform_matrix` in a transforms file, and are in the frame of the cameras the scene's loader
//! gives: a transforms file's own frame (Blender, instant-ngp, nerfstudio data), nerf-pytorch's
//! recentred and rescaled frame for LLFF. Other keys (`keyframes`, `seconds`, `aspect`, …) are
//! ignored. `camera_type` is `perspective` (also when absent), `fisheye` (an equidistant fisheye
//! with the focal length `fov` gives, `nerf_rays::Camera::fisheye_dir`) or `equirectangular`: a
//! 360° panorama per frame (`nerf_rays::Camera::equirect_dir`), whose `fov` is not needed.

use std::path::Path;

use nerf_rays::{Camera, Intrinsics, Projection};

use crate::{DataError, NgpCameraPath};

/// A camera path: one camera per frame and the frame rate the file asks for.
#[derive(Clone, Debug)]
pub struct CameraPath {
    /// One camera per frame, all of the file's `render_width × render_height`: pinhole
    /// intrinsics from `fov`, or (equirectangular) only the size.
    pub cameras: Vec<Camera>,
    /// `camera_type`: perspective (also when absent) or equirectangular.
    pub projection: Projection,
    /// `fps` of the file, if it gives one.
    pub fps: Option<f64>,
    /// The file's `crop` (nerfstudio's viewer crop), if it has one.
    pub crop: Option<PathCrop>,
}

/// The crop of a nerfstudio camera path (`"crop"`, what its viewer's crop box exports and
/// `ns-render` renders with): an oriented box in the cameras' frame and the background colour
/// of the cropped render.
///
/// ```json
/// "crop": { "crop_center": [0, 0, 0], "crop_scale": [2, 2, 2], "crop_rot": [0, 0, 0],
///           "crop_bg_color": { "r": 0, "g": 0, "b": 0 } }
/// ```
///
/// `crop_scale` is the box's full size along its axes, `crop_rot` its roll, pitch and yaw in
/// radians (`R = Rz(yaw)·Ry(pitch)·Rx(roll)`, nerfstudio's `OrientedBox.from_params`; absent:
/// none), `crop_bg_color` 0–255 per channel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathCrop {
    /// `crop_center`: the box's centre.
    pub center: [f32; 3],
    /// `crop_rot`: roll, pitch, yaw (radians).
    pub rotation: [f32; 3],
    /// `crop_scale`: the box's size along its axes (positive).
    pub scale: [f32; 3],
    /// `crop_bg_color` as 0–1 RGB.
    pub background: [f32; 3],
}

impl PathCrop {
    /// The `crop` object of a camera path file.
    pub fn to_json(&self) -> serde_json::Value {
        let c = |x: f32| (x * 255.0).round().clamp(0.0, 255.0) as u32;
        serde_json::json!({
            "crop_center": self.center,
            "crop_scale": self.scale,
            "crop_rot": self.rotation,
            "crop_bg_color": { "r": c(self.background[0]), "g": c(self.background[1]), "b": c(self.background[2]) },
        })
    }
}

/// Reads a nerfstudio camera path (see the module docs). Errors name the file and the key:
/// missing file, malformed JSON, a missing or invalid `render_width`, `render_height`,
/// `camera_path[i].camera_to_world` (12 or 16 finite numbers) or `camera_path[i].fov` (degrees in
/// (0, 180); not needed by equirectangular paths), a camera type other than perspective, fisheye
/// and equirectangular, an empty path.
pub fn load_camera_path(path: &Path) -> Result<CameraPath, DataError> {
    parse_camera_path(path, &read_json(path)?)
}

/// A camera path file in either format ([`read_camera_path`]).
#[derive(Clone, Debug)]
pub enum CameraPathFile {
    /// nerfstudio's `camera_path.json`: one camera per frame.
    Nerfstudio(CameraPath),
    /// instant-ngp's `base_cam.json`: keyframes in instant-ngp's space, to be placed in a
    /// scene's frame ([`crate::NgpSpace`]) and splined into frames ([`NgpCameraPath::cameras`]).
    InstantNgp(NgpCameraPath),
}

/// Reads a camera path in nerfstudio's format ([`load_camera_path`]) or instant-ngp's
/// ([`NgpCameraPath`]): a file with a `path` and no `camera_path` is instant-ngp's. Errors
/// as those readers'.
pub fn read_camera_path(path: &Path) -> Result<CameraPathFile, DataError> {
    let v = read_json(path)?;
    if v.get("camera_path").is_none() && v.get("path").is_some() {
        return NgpCameraPath::parse(path, &v).map(CameraPathFile::InstantNgp);
    }
    parse_camera_path(path, &v).map(CameraPathFile::Nerfstudio)
}

pub(crate) fn read_json(path: &Path) -> Result<serde_json::Value, DataError> {
    let text = std::fs::read_to_string(path).map_err(|source| DataError::Io { path: path.to_path_buf(), source })?;
    serde_json::from_str(&text).map_err(|source| DataError::Json { path: path.to_path_buf(), source })
}

/// [`load_camera_path`] of a file already parsed.
fn parse_camera_path(path: &Path, v: &serde_json::Value) -> Result<CameraPath, DataError> {
    let missing = |key: &str| DataError::MissingKey { path: path.to_path_buf(), key: key.into() };
    let invalid = |key: &str, reason: String| DataError::InvalidValue { path: path.to_path_buf(), key: key.into(), reason };
    if !v.is_object() {
        return Err(invalid("(top level)", "a camera path is a JSON object".into()));
    }
    let projection = match v.get("camera_type") {
        None => Projection::Perspective,
        Some(t) => match t.as_str() {
            Some("perspective") => Projection::Perspective,
            Some("equirectangular") => Projection::Equirectangular,
            Some("fisheye") => Projection::Fisheye,
            _ => {
                return Err(invalid("camera_type", format!("{t}: only \"perspective\", \"fisheye\" and \"equirectangular\" cameras can be rendered")))
            }
        },
    };
    let size = |key: &str| -> Result<u32, DataError> {
        let x = v.get(key).ok_or_else(|| missing(key))?;
        x.as_u64().filter(|&n| n > 0 && n <= 1 << 16).map(|n| n as u32).ok_or_else(|| {
            invalid(key, format!("{x}: must be a whole number of pixels in 1..=65536"))
        })
    };
    let (width, height) = (size("render_width")?, size("render_height")?);
    let fps = match v.get("fps") {
        None | Some(serde_json::Value::Null) => None,
        Some(x) => Some(x.as_f64().filter(|f| f.is_finite() && *f > 0.0).ok_or_else(|| invalid("fps", format!("{x}: must be a positive number")))?),
    };
    let frames = v.get("camera_path").ok_or_else(|| missing("camera_path"))?;
    let frames = frames.as_array().ok_or_else(|| invalid("camera_path", "must be an array of cameras".into()))?;
    if frames.is_empty() {
        return Err(invalid("camera_path", "has no cameras".into()));
    }
    let mut cameras = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        let key = |k: &str| format!("camera_path[{i}].{k}");
        let m = f.get("camera_to_world").ok_or_else(|| missing(&key("camera_to_world")))?;
        let values: Option<Vec<f64>> = m.as_array().and_then(|a| a.iter().map(|x| x.as_f64()).collect());
        let values = values
            .filter(|vals| vals.len() == 16 || vals.len() == 12)
            .ok_or_else(|| invalid(&key("camera_to_world"), "must be 16 numbers (a row-major 4×4 matrix) or 12 (its top 3 rows)".into()))?;
        let rows: Vec<[f32; 4]> = values.chunks(4).take(3).map(|r| std::array::from_fn(|c| r[c] as f32)).collect();
        let k = match projection {
            // A panorama sees everything: its `fov`, which nerfstudio writes anyway, is not used.
            Projection::Equirectangular => equirect_intrinsics(width, height),
            // A fisheye's focal length comes from `fov` as a pinhole's (nerfstudio's).
            Projection::Perspective | Projection::Fisheye => {
                let fov = f.get("fov").ok_or_else(|| missing(&key("fov")))?;
                let deg = fov.as_f64().filter(|d| *d > 0.0 && *d < 180.0).ok_or_else(|| {
                    invalid(&key("fov"), format!("{fov}: the vertical field of view must be in (0, 180) degrees"))
                })?;
                intrinsics_from_fov_y(width, height, deg)
            }
        };
        let cam = Camera::from_c2w(k, &rows)
            .map_err(|e| invalid(&key("camera_to_world"), e.to_string()))?;
        cameras.push(cam);
    }
    let crop = match v.get("crop") {
        None | Some(serde_json::Value::Null) => None,
        Some(c) => Some(parse_crop(c, &invalid)?),
    };
    Ok(CameraPath { cameras, projection, fps, crop })
}

/// The `crop` object ([`PathCrop`]).
fn parse_crop(c: &serde_json::Value, invalid: &dyn Fn(&str, String) -> DataError) -> Result<PathCrop, DataError> {
    let three = |key: &str, positive: bool| -> Result<Option<[f32; 3]>, DataError> {
        let Some(x) = c.get(key) else { return Ok(None) };
        let v: Option<Vec<f64>> = x.as_array().and_then(|a| a.iter().map(|x| x.as_f64()).collect());
        match v {
            Some(v) if v.len() == 3 && v.iter().all(|x| x.is_finite() && (!positive || *x > 0.0)) => Ok(Some([v[0] as f32, v[1] as f32, v[2] as f32])),
            _ => Err(invalid(
                &format!("crop.{key}"),
                format!("{x}: must be 3 finite numbers{}", if positive { ", each positive" } else { "" }),
            )),
        }
    };
    let need = |key: &str, positive: bool| three(key, positive)?.ok_or_else(|| invalid(&format!("crop.{key}"), "missing: a crop needs crop_center and crop_scale".into()));
    let center = need("crop_center", false)?;
    let scale = need("crop_scale", true)?;
    let rotation = three("crop_rot", false)?.unwrap_or([0.0; 3]);
    let background = match c.get("crop_bg_color") {
        None | Some(serde_json::Value::Null) => [0.0; 3],
        Some(b) => {
            let ch = |k: &str| b.get(k).and_then(|x| x.as_f64()).filter(|x| (0.0..=255.0).contains(x)).map(|x| (x / 255.0) as f32);
            match (ch("r"), ch("g"), ch("b")) {
                (Some(r), Some(g), Some(bl)) => [r, g, bl],
                _ => return Err(invalid("crop.crop_bg_color", format!("{b}: must be {{\"r\", \"g\", \"b\"}}, each 0 to 255"))),
            }
        }
    };
    Ok(PathCrop { center, rotation, scale, background })
}

/// Square-pixel intrinsics with the principal point at the image centre and vertical field of view
/// `fov_y_degrees`: `fx = fy = ½·H / tan(½·fov)` (computed in f64).
pub fn intrinsics_from_fov_y(width: u32, height: u32, fov_y_degrees: f64) -> Intrinsics {
    let f = (0.5 * height as f64 / (0.5 * fov_y_degrees.to_radians()).tan()) as f32;
    Intrinsics { width, height, fx: f, fy: f, cx: width as f32 * 0.5, cy: height as f32 * 0.5 }
}

/// The vertical field of view of `k` in degrees, `2·atan(½·H / fy)`: the inverse of
/// [`intrinsics_from_fov_y`] (computed in f64).
pub fn fov_y_degrees(k: &Intrinsics) -> f64 {
    (2.0 * (0.5 * f64::from(k.height) / f64::from(k.fy)).atan()).to_degrees()
}

/// The intrinsics nerfstudio gives a `width × height` equirectangular camera (`fx = W/2`,
/// `fy = H`, the principal point at the centre); only the size is used for its rays.
pub fn equirect_intrinsics(width: u32, height: u32) -> Intrinsics {
    Intrinsics { width, height, fx: 0.5 * width as f32, fy: height as f32, cx: 0.5 * width as f32, cy: 0.5 * height as f32 }
}

/// `cameras` as a nerfstudio camera path of `projection` (the inverse of [`load_camera_path`]):
/// the size of the first camera, each camera's vertical field of view from its `fy`, its pose
/// row-major. The format cannot hold non-square pixels or an off-centre principal point: such
/// cameras come back with `fx = fy` and the image centre.
///
/// # Panics
/// If `cameras` is empty.
pub fn camera_path_json(cameras: &[Camera], projection: Projection, fps: f64, crop: Option<&PathCrop>) -> serde_json::Value {
    let k = cameras[0].intrinsics;
    let path: Vec<serde_json::Value> = cameras
        .iter()
        .map(|c| {
            let m: Vec<f32> = c.c2w().iter().flatten().copied().collect();
            serde_json::json!({
                "camera_to_world": m,
                "fov": fov_y_degrees(&c.intrinsics),
                "aspect": c.intrinsics.width as f64 / c.intrinsics.height as f64,
            })
        })
        .collect();
    serde_json::json!({
        "camera_type": projection.name(),
        "render_width": k.width,
        "render_height": k.height,
        "fps": fps,
        "seconds": cameras.len() as f64 / fps,
        "crop": crop.map(PathCrop::to_json),
        "camera_path": path,
    })
}
