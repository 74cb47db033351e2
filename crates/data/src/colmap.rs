//! COLMAP's sparse reconstructions, read directly: a scene folder with `images/` and a model in
//! `sparse/0/` (COLMAP's own layout) or `colmap/sparse/0/` (what nerfstudio's `ns-process-data`
//! keeps), each model as `cameras.bin` + `images.bin` or `cameras.txt` + `images.txt`
//! (`points3D` only for sparse depth maps, [`read_points`]). It is what nerfstudio's `colmap`
//! dataparser reads.
//!
//! The model becomes the `transforms.json` that `ns-process-data` would write for it
//! ([`transforms_json`]; nerfstudio's `colmap_utils.colmap_to_json`): per image, the
//! camera-to-world matrix inverted from COLMAP's world-to-camera `(q, t)`, turned from OpenCV's
//! camera axes to OpenGL's (y and z negated) and with the world's y and z axes swapped and the new
//! z negated (`applied_transform`); per image its camera's intrinsics in pixels and OpenCV
//! distortion. The loader then takes it as any nerfstudio file ([`crate::load_blender`]): poses
//! normalised as nerfstudio does, every 8th image (by name) a test view, rays through each
//! camera's lens. Camera models: `SIMPLE_PINHOLE`, `PINHOLE`, `SIMPLE_RADIAL`, `RADIAL`,
//! `OPENCV`, `FULL_OPENCV` (with its rational terms `k4..k6`), the fisheyes `OPENCV_FISHEYE`,
//! `RADIAL_FISHEYE` and `SIMPLE_RADIAL_FISHEYE` (written as nerfstudio writes them,
//! `OPENCV_FISHEYE` with `k1..k4`), `THIN_PRISM_FISHEYE` (its `sx1`, `sy1` as OpenCV's `s1`,
//! `s3`) and `RAD_TAN_THIN_PRISM_FISHEYE` (Project Aria's Fisheye624, written as nerfstudio's
//! `FISHEYE624` with `distortion_params`), `FOV` (its `omega`), and those of COLMAP 3.12 on:
//! `SIMPLE_DIVISION` and `DIVISION` (Fitzgibbon's division model, written as `DIVISION` with its
//! `k` as `k1`), the plain equidistant fisheyes `SIMPLE_FISHEYE` and `FISHEYE` (written as
//! `OPENCV_FISHEYE` with zero coefficients) and `EQUIRECTANGULAR` (360° panoramas, written as
//! nerfstudio's `EQUIRECTANGULAR` camera, whose mapping is COLMAP's: the image's centre looks
//! forward, its top row up) and `EUCM` (its `alpha` and `beta`). Unknown models are an error
//! naming the camera.

use std::path::{Path, PathBuf};

use serde_json::{json, Value};

use crate::DataError;

/// Where a model may sit below the scene folder, first match wins.
pub const MODEL_DIRS: [&str; 3] = ["sparse/0", "colmap/sparse/0", "sparse"];

/// The folder of the images, below the scene folder (COLMAP's image names are relative to it).
pub const IMAGES_DIR: &str = "images";

/// A COLMAP camera: its model's name, the image size and the model's parameters in COLMAP's
/// order (e.g. `OPENCV`: `fx, fy, cx, cy, k1, k2, p1, p2`).
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    /// `CAMERA_ID`.
    pub id: u32,
    /// The model's name, e.g. `PINHOLE`.
    pub model: String,
    /// Image width in pixels.
    pub width: u64,
    /// Image height in pixels.
    pub height: u64,
    /// The model's parameters.
    pub params: Vec<f64>,
}

/// A registered COLMAP image: its world-to-camera pose `x_cam = R(q)·x_world + t` (OpenCV camera
/// axes: x right, y down, z forward), its camera and its file name (below [`IMAGES_DIR`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapImage {
    /// `IMAGE_ID`.
    pub id: u32,
    /// The rotation as a unit quaternion `(w, x, y, z)`.
    pub qvec: [f64; 4],
    /// The translation.
    pub tvec: [f64; 3],
    /// `CAMERA_ID` of its camera.
    pub camera_id: u32,
    /// The file name, relative to the images folder.
    pub name: String,
}

/// A 3-D point of the sparse reconstruction (`points3D`): where it is, its mean reprojection
/// error and the images that observe it.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapPoint {
    /// `X Y Z` in COLMAP's world.
    pub xyz: [f64; 3],
    /// Mean reprojection error in pixels.
    pub error: f64,
    /// `IMAGE_ID` of every observation (its track; an image may appear twice).
    pub images: Vec<u32>,
}

/// nerfstudio's `create_sfm_depth` defaults: the largest reprojection error (pixels) of a point
/// that makes depth ...
pub const SFM_MAX_ERROR: f64 = 2.5;
/// ... and the fewest images that must observe it.
pub const SFM_MIN_VIEWS: usize = 2;

/// A model's cameras and images, as read.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColmapModel {
    /// The cameras.
    pub cameras: Vec<ColmapCamera>,
    /// The registered images, in the file's order.
    pub images: Vec<ColmapImage>,
}

/// COLMAP's camera models: id, name, number of parameters (`colmap/src/colmap/sensor/models.h`).
const MODELS: [(i32, &str, usize); 18] = [
    (0, "SIMPLE_PINHOLE", 3),
    (1, "PINHOLE", 4),
    (2, "SIMPLE_RADIAL", 4),
    (3, "RADIAL", 5),
    (4, "OPENCV", 8),
    (5, "OPENCV_FISHEYE", 8),
    (6, "FULL_OPENCV", 12),
    (7, "FOV", 5),
    (8, "SIMPLE_RADIAL_FISHEYE", 4),
    (9, "RADIAL_FISHEYE", 5),
    (10, "THIN_PRISM_FISHEYE", 12),
    (11, "RAD_TAN_THIN_PRISM_FISHEYE", 16),
    (12, "SIMPLE_DIVISION", 4),
    (13, "DIVISION", 5),
    (14, "SIMPLE_FISHEYE", 3),
    (15, "FISHEYE", 4),
    (16, "EUCM", 6),
    (17, "EQUIRECTANGULAR", 2),
];

fn bad(path: &Path, reason: impl Into<String>) -> DataError {
    DataError::Colmap { path: path.to_path_buf(), reason: reason.into() }
}

/// The model folder of a scene folder: the first of [`MODEL_DIRS`] that holds `cameras` and
/// `images` files of one kind (`.bin` preferred), if any.
pub fn find_model(root: &Path) -> Option<PathBuf> {
    MODEL_DIRS.iter().map(|d| root.join(d)).find(|d| model_files(d).is_some())
}

/// Whether `root` is a COLMAP scene folder: no `transforms*.json` there and a model below it.
pub fn is_colmap(root: &Path) -> bool {
    use crate::Split;
    let split_files = [Split::Train, Split::Val, Split::Test].map(Split::transforms_file);
    let transforms = std::iter::once(crate::ngp::NGP_TRANSFORMS).chain(split_files.iter().map(String::as_str));
    !transforms.into_iter().any(|t| root.join(t).is_file()) && find_model(root).is_some()
}

/// `(cameras, images)` files of the model folder `dir`, binary if both exist, else text.
pub fn model_files(dir: &Path) -> Option<(PathBuf, PathBuf)> {
    ["bin", "txt"].iter().find_map(|ext| {
        let (c, i) = (dir.join(format!("cameras.{ext}")), dir.join(format!("images.{ext}")));
        (c.is_file() && i.is_file()).then_some((c, i))
    })
}

/// Reads the model in the folder `dir` (binary or text, as [`find_model`] chose).
pub fn read_model(dir: &Path) -> Result<ColmapModel, DataError> {
    let (cams, imgs) = model_files(dir).ok_or_else(|| bad(dir, "no cameras.bin + images.bin or cameras.txt + images.txt here"))?;
    let read = |p: &Path| std::fs::read(p).map_err(|source| DataError::Io { path: p.to_path_buf(), source });
    let binary = cams.extension().is_some_and(|e| e == "bin");
    let model = if binary {
        ColmapModel { cameras: read_cameras_bin(&cams, &read(&cams)?)?, images: read_images_bin(&imgs, &read(&imgs)?)? }
    } else {
        let text = |p: &Path| String::from_utf8(read(p)?).map_err(|_| bad(p, "not UTF-8 text"));
        ColmapModel { cameras: read_cameras_txt(&cams, &text(&cams)?)?, images: read_images_txt(&imgs, &text(&imgs)?)? }
    };
    check(&model, &cams, &imgs)?;
    Ok(model)
}

/// The 3-D points of the model folder `dir` (`points3D.bin`, else `points3D.txt`), or `None`
/// when it has neither. Errors name the file (truncated, malformed, non-finite coordinates).
pub fn read_points(dir: &Path) -> Result<Option<Vec<ColmapPoint>>, DataError> {
    let (bin, txt) = (dir.join("points3D.bin"), dir.join("points3D.txt"));
    let read = |p: &Path| std::fs::read(p).map_err(|source| DataError::Io { path: p.to_path_buf(), source });
    let points = if bin.is_file() {
        read_points_bin(&bin, &read(&bin)?)?
    } else if txt.is_file() {
        let text = String::from_utf8(read(&txt)?).map_err(|_| bad(&txt, "not UTF-8 text"))?;
        read_points_txt(&txt, &text)?
    } else {
        return Ok(None);
    };
    let path = if bin.is_file() { bin } else { txt };
    if let Some(p) = points.iter().find(|p| p.xyz.iter().any(|v| !v.is_finite())) {
        return Err(bad(&path, format!("a point at {:?}: coordinates must be finite", p.xyz)));
    }
    Ok(Some(points))
}

/// `points3D.bin`: `u64` count, then per point `u64` id, 3 `f64` of `X Y Z`, 3 `u8` of colour,
/// `f64` error, `u64` track length and per observation `i32` image id, `i32` 2-D point index.
pub fn read_points_bin(path: &Path, data: &[u8]) -> Result<Vec<ColmapPoint>, DataError> {
    let mut b = Bytes { path, data, at: 0 };
    let n = b.count(51, &|| "the number of points".into())?;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let what = |s: &str| format!("point {k}'s {s}");
        b.u64(&|| what("id"))?;
        let mut xyz = [0.0; 3];
        for v in &mut xyz {
            *v = b.f64(&|| what("position"))?;
        }
        b.take::<3>(&|| what("colour"))?;
        let error = b.f64(&|| what("error"))?;
        let len = b.count(8, &|| what("track length"))?;
        let mut images = Vec::with_capacity(len);
        for _ in 0..len {
            images.push(b.i32(&|| what("track"))? as u32);
            b.i32(&|| what("track"))?;
        }
        out.push(ColmapPoint { xyz, error, images });
    }
    if b.at != data.len() {
        return Err(bad(path, format!("{} bytes after the last of {n} points", data.len() - b.at)));
    }
    Ok(out)
}

/// `points3D.txt`: per line `POINT3D_ID X Y Z R G B ERROR` then `IMAGE_ID POINT2D_IDX` pairs;
/// `#` starts a comment line.
pub fn read_points_txt(path: &Path, text: &str) -> Result<Vec<ColmapPoint>, DataError> {
    let mut out = Vec::new();
    for (n, line, f) in data_lines(text) {
        if f.len() < 8 || !(f.len() - 8).is_multiple_of(2) {
            return Err(bad(path, format!("line {n}: expected POINT3D_ID X Y Z R G B ERROR and IMAGE_ID POINT2D_IDX pairs, got `{line}`")));
        }
        let v = numbers::<f64>(path, n, &f[1..4])?;
        let error = numbers::<f64>(path, n, &f[7..8])?[0];
        let track = numbers::<u32>(path, n, &f[8..])?;
        out.push(ColmapPoint { xyz: [v[0], v[1], v[2]], error, images: track.iter().step_by(2).copied().collect() });
    }
    Ok(out)
}

/// A cursor over a binary file that names the file and what it was reading when it runs out.
struct Bytes<'a> {
    path: &'a Path,
    data: &'a [u8],
    at: usize,
}

impl Bytes<'_> {
    fn take<const N: usize>(&mut self, what: &dyn Fn() -> String) -> Result<[u8; N], DataError> {
        let end = self.at + N;
        let s = self.data.get(self.at..end).ok_or_else(|| {
            bad(self.path, format!("truncated: {} needs {N} bytes at offset {}, the file has {}", what(), self.at, self.data.len()))
        })?;
        self.at = end;
        Ok(s.try_into().expect("N bytes"))
    }
    fn u64(&mut self, what: &dyn Fn() -> String) -> Result<u64, DataError> {
        self.take::<8>(what).map(u64::from_le_bytes)
    }
    fn i32(&mut self, what: &dyn Fn() -> String) -> Result<i32, DataError> {
        self.take::<4>(what).map(i32::from_le_bytes)
    }
    fn f64(&mut self, what: &dyn Fn() -> String) -> Result<f64, DataError> {
        self.take::<8>(what).map(f64::from_le_bytes)
    }
    /// A count read from the file, checked against the bytes left (`min_each` per item) so that a
    /// corrupt count is an error, not a huge allocation.
    fn count(&mut self, min_each: usize, what: &dyn Fn() -> String) -> Result<usize, DataError> {
        let n = self.u64(what)?;
        let left = (self.data.len() - self.at) as u64;
        if n.checked_mul(min_each as u64).is_none_or(|b| b > left) {
            return Err(bad(self.path, format!("truncated or corrupt: {} is {n}, which would need more than the {left} bytes left", what())));
        }
        Ok(n as usize)
    }
}

fn model_by_id(path: &Path, camera: u32, id: i32) -> Result<(&'static str, usize), DataError> {
    MODELS
        .iter()
        .find(|m| m.0 == id)
        .map(|m| (m.1, m.2))
        .ok_or_else(|| bad(path, format!("camera {camera}: unknown camera model id {id}")))
}

fn model_by_name(path: &Path, camera: u32, name: &str) -> Result<usize, DataError> {
    MODELS
        .iter()
        .find(|m| m.1 == name)
        .map(|m| m.2)
        .ok_or_else(|| bad(path, format!("camera {camera}: unknown camera model `{name}`")))
}

fn camera_id(path: &Path, v: i64, what: &str) -> Result<u32, DataError> {
    u32::try_from(v).map_err(|_| bad(path, format!("{what} {v} is not a valid id")))
}

/// `cameras.bin`: `u64` count, then per camera `i32` id, `i32` model id, `u64` width, `u64`
/// height and the model's `f64` parameters (little-endian).
pub fn read_cameras_bin(path: &Path, data: &[u8]) -> Result<Vec<ColmapCamera>, DataError> {
    let mut b = Bytes { path, data, at: 0 };
    let n = b.count(24, &|| "the number of cameras".into())?;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let what = |s: &str| format!("camera {k}'s {s}");
        let id = camera_id(path, b.i32(&|| what("id"))?.into(), "camera id")?;
        let model_id = b.i32(&|| what("model id"))?;
        let (model, n_params) = model_by_id(path, id, model_id)?;
        let width = b.u64(&|| what("width"))?;
        let height = b.u64(&|| what("height"))?;
        let params = (0..n_params).map(|_| b.f64(&|| what("parameters"))).collect::<Result<_, _>>()?;
        out.push(ColmapCamera { id, model: model.into(), width, height, params });
    }
    if b.at != data.len() {
        return Err(bad(path, format!("{} bytes after the last of {n} cameras", data.len() - b.at)));
    }
    Ok(out)
}

/// `images.bin`: `u64` count, then per image `i32` id, 4 `f64` of `q` (w, x, y, z), 3 of `t`,
/// `i32` camera id, the NUL-terminated name, `u64` number of 2-D points and per point `f64` x,
/// `f64` y, `i64` 3-D point id (skipped).
pub fn read_images_bin(path: &Path, data: &[u8]) -> Result<Vec<ColmapImage>, DataError> {
    let mut b = Bytes { path, data, at: 0 };
    let n = b.count(73, &|| "the number of images".into())?;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let what = |s: &str| format!("image {k}'s {s}");
        let id = camera_id(path, b.i32(&|| what("id"))?.into(), "image id")?;
        let mut q = [0.0; 4];
        for v in &mut q {
            *v = b.f64(&|| what("rotation"))?;
        }
        let mut t = [0.0; 3];
        for v in &mut t {
            *v = b.f64(&|| what("translation"))?;
        }
        let camera = camera_id(path, b.i32(&|| what("camera id"))?.into(), "camera id")?;
        let rest = &data[b.at..];
        let len = rest.iter().position(|&c| c == 0).ok_or_else(|| bad(path, format!("truncated: image {id}'s name has no end")))?;
        let name = std::str::from_utf8(&rest[..len]).map_err(|_| bad(path, format!("image {id}'s name is not UTF-8")))?.to_string();
        b.at += len + 1;
        let points = b.count(24, &|| format!("image {id}'s number of 2-D points"))?;
        b.at += 24 * points; // checked by `count`
        out.push(ColmapImage { id, qvec: q, tvec: t, camera_id: camera, name });
    }
    if b.at != data.len() {
        return Err(bad(path, format!("{} bytes after the last of {n} images", data.len() - b.at)));
    }
    Ok(out)
}

/// The fields of text line `line_no`, each parsed as a `T`.
fn numbers<T: std::str::FromStr>(path: &Path, line_no: usize, fields: &[&str]) -> Result<Vec<T>, DataError> {
    fields
        .iter()
        .map(|f| f.parse().map_err(|_| bad(path, format!("line {line_no}: `{f}` is not a number"))))
        .collect()
}

/// The data lines of a COLMAP text file: `(line number from 1, the trimmed line, its
/// whitespace-separated fields)`, skipping blank lines and `#` comments.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str, Vec<&str>)> {
    text.lines().enumerate().filter_map(|(i, line)| {
        let line = line.trim();
        (!line.is_empty() && !line.starts_with('#')).then(|| (i + 1, line, line.split_whitespace().collect()))
    })
}

/// `cameras.txt`: per line `CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`; `#` starts a comment line.
pub fn read_cameras_txt(path: &Path, text: &str) -> Result<Vec<ColmapCamera>, DataError> {
    let mut out = Vec::new();
    for (n, line, f) in data_lines(text) {
        if f.len() < 4 {
            return Err(bad(path, format!("line {n}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got `{line}`")));
        }
        let id = numbers::<i64>(path, n, &f[..1])?[0];
        let id = camera_id(path, id, "camera id")?;
        let n_params = model_by_name(path, id, f[1])?;
        let size = numbers::<u64>(path, n, &f[2..4])?;
        let params = numbers::<f64>(path, n, &f[4..])?;
        if params.len() != n_params {
            return Err(bad(path, format!("line {n}: camera {id}: {} takes {n_params} parameters, got {}", f[1], params.len())));
        }
        out.push(ColmapCamera { id, model: f[1].into(), width: size[0], height: size[1], params });
    }
    Ok(out)
}

/// `images.txt`: per image a line `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` (the name is
/// the rest of the line) and the next line its 2-D points as `X Y POINT3D_ID` triples (empty for
/// an image without any), as COLMAP's `read_write_model.py` reads them. Comment lines (`#`) and
/// blank lines are skipped where an image line is expected. A points line that is not triples of
/// numbers is an error: a file with one line per image would otherwise lose every other image.
pub fn read_images_txt(path: &Path, text: &str) -> Result<Vec<ColmapImage>, DataError> {
    let mut out = Vec::new();
    let mut lines = text.lines().enumerate();
    while let Some((i, line)) = lines.next() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        // Nine whitespace-separated fields, then the name.
        let (mut f, mut rest) = (Vec::with_capacity(9), line);
        for _ in 0..9 {
            rest = rest.trim_start();
            let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
            f.push(&rest[..end]);
            rest = &rest[end..];
        }
        let name = rest.trim();
        if name.is_empty() {
            return Err(bad(path, format!("line {}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got `{line}`", i + 1)));
        }
        let ids = numbers::<i64>(path, i + 1, &[f[0], f[8]])?;
        let v = numbers::<f64>(path, i + 1, &f[1..8])?;
        let id = camera_id(path, ids[0], "image id")?;
        if let Some((j, points)) = lines.next() {
            let p: Vec<&str> = points.split_whitespace().collect();
            if !p.len().is_multiple_of(3) || p.iter().any(|x| x.parse::<f64>().is_err()) {
                return Err(bad(
                    path,
                    format!("line {}: expected image {id}'s 2-D points (X Y POINT3D_ID triples, or an empty line) after its line", j + 1),
                ));
            }
        }
        out.push(ColmapImage {
            id,
            qvec: [v[0], v[1], v[2], v[3]],
            tvec: [v[4], v[5], v[6]],
            camera_id: camera_id(path, ids[1], "camera id")?,
            name: name.to_string(),
        });
    }
    Ok(out)
}

/// Checks what the conversion relies on: images present, each image's camera present, finite
/// poses with a non-zero quaternion, finite parameters, a positive size.
fn check(model: &ColmapModel, cams: &Path, imgs: &Path) -> Result<(), DataError> {
    if model.images.is_empty() {
        return Err(bad(imgs, "no registered images"));
    }
    for c in &model.cameras {
        if c.width == 0 || c.height == 0 || c.width > u32::MAX as u64 || c.height > u32::MAX as u64 {
            return Err(bad(cams, format!("camera {}: image size {}x{}", c.id, c.width, c.height)));
        }
        if c.params.iter().any(|p| !p.is_finite()) {
            return Err(bad(cams, format!("camera {}: non-finite parameter in {:?}", c.id, c.params)));
        }
    }
    for im in &model.images {
        if !model.cameras.iter().any(|c| c.id == im.camera_id) {
            return Err(bad(imgs, format!("image {} (`{}`): camera {} is not in {}", im.id, im.name, im.camera_id, cams.display())));
        }
        let n2: f64 = im.qvec.iter().map(|v| v * v).sum();
        if !(n2.is_finite() && n2 > 1e-12) || im.tvec.iter().any(|v| !v.is_finite()) {
            return Err(bad(imgs, format!("image {} (`{}`): invalid pose q = {:?}, t = {:?}", im.id, im.name, im.qvec, im.tvec)));
        }
    }
    Ok(())
}

/// The rotation matrix of the quaternion `(w, x, y, z)`, normalised first (COLMAP's
/// `qvec2rotmat` of a unit quaternion).
pub fn rotation(q: [f64; 4]) -> [[f64; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// nerfstudio's `applied_transform` of a COLMAP model: world `(x, y, z)` → `(x, z, −y)`.
pub const APPLIED_TRANSFORM: [[f64; 4]; 3] = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]];

/// The camera-to-world matrix (4×4, OpenGL camera axes, the world of [`APPLIED_TRANSFORM`]) of an
/// image, as nerfstudio's `colmap_to_json` computes it.
pub fn camera_to_world(im: &ColmapImage) -> [[f64; 4]; 4] {
    let r = rotation(im.qvec);
    // Inverse of [R | t]: [Rᵀ | −Rᵀ·t]; OpenCV → OpenGL camera axes: columns y and z negated.
    let mut c2w = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            c2w[i][j] = r[j][i] * if j == 0 { 1.0 } else { -1.0 };
        }
        c2w[i][3] = -(0..3).map(|k| r[k][i] * im.tvec[k]).sum::<f64>();
    }
    // World axes: rows reordered (x, z, y), then the new z negated.
    let m = c2w;
    for (i, row) in APPLIED_TRANSFORM.iter().enumerate() {
        for j in 0..4 {
            c2w[i][j] = (0..3).map(|k| row[k] * m[k][j]).sum();
        }
    }
    c2w[3] = [0.0, 0.0, 0.0, 1.0];
    c2w
}

/// The camera keys of `transforms.json` for a camera (`camera_model`, `w`, `h`, `fl_x`, `fl_y`,
/// `cx`, `cy`, and the distortion coefficients its model has), as nerfstudio writes them.
fn camera_keys(path: &Path, c: &ColmapCamera) -> Result<serde_json::Map<String, Value>, DataError> {
    let p = &c.params;
    if c.model == "EQUIRECTANGULAR" {
        // A panorama: its size is all there is (COLMAP's parameters repeat it).
        let mut m = serde_json::Map::new();
        m.insert("camera_model".into(), json!("EQUIRECTANGULAR"));
        m.insert("w".into(), json!(c.width));
        m.insert("h".into(), json!(c.height));
        return Ok(m);
    }
    let (f, rest, model): (_, &[f64], _) = match c.model.as_str() {
        "SIMPLE_PINHOLE" | "SIMPLE_RADIAL" | "RADIAL" => ([p[0], p[0], p[1], p[2]], &p[3..], c.model.as_str()),
        "PINHOLE" | "OPENCV" => ([p[0], p[1], p[2], p[3]], &p[4..], c.model.as_str()),
        "OPENCV_FISHEYE" | "FISHEYE" => ([p[0], p[1], p[2], p[3]], &p[4..], "OPENCV_FISHEYE"),
        "SIMPLE_RADIAL_FISHEYE" | "RADIAL_FISHEYE" | "SIMPLE_FISHEYE" => ([p[0], p[0], p[1], p[2]], &p[3..], "OPENCV_FISHEYE"),
        "SIMPLE_DIVISION" => ([p[0], p[0], p[1], p[2]], &p[3..], "DIVISION"),
        "DIVISION" => ([p[0], p[1], p[2], p[3]], &p[4..], "DIVISION"),
        "EUCM" => ([p[0], p[1], p[2], p[3]], &p[4..], "EUCM"),
        "FULL_OPENCV" | "THIN_PRISM_FISHEYE" | "RAD_TAN_THIN_PRISM_FISHEYE" | "FOV" => ([p[0], p[1], p[2], p[3]], &p[4..], c.model.as_str()),
        other => {
            return Err(bad(
                path,
                format!(
                    "camera {}: camera model {other} is not supported (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, \
                     FULL_OPENCV, OPENCV_FISHEYE, RADIAL_FISHEYE, SIMPLE_RADIAL_FISHEYE, FOV, THIN_PRISM_FISHEYE, \
                     RAD_TAN_THIN_PRISM_FISHEYE, SIMPLE_DIVISION, DIVISION, SIMPLE_FISHEYE, FISHEYE, EUCM and EQUIRECTANGULAR are)",
                    c.id
                ),
            ))
        }
    };
    let mut m = serde_json::Map::new();
    m.insert("camera_model".into(), json!(model));
    m.insert("w".into(), json!(c.width));
    m.insert("h".into(), json!(c.height));
    for (k, v) in ["fl_x", "fl_y", "cx", "cy"].iter().zip(f) {
        m.insert((*k).into(), json!(v));
    }
    if c.model == "RAD_TAN_THIN_PRISM_FISHEYE" {
        // Project Aria's Fisheye624, written as nerfstudio writes it.
        m.insert("camera_model".into(), json!("FISHEYE624"));
        m.insert("distortion_params".into(), json!(rest));
        return Ok(m);
    }
    let names: &[&str] = match c.model.as_str() {
        "SIMPLE_RADIAL" => &["k1"],
        "RADIAL" => &["k1", "k2"],
        "OPENCV" => &["k1", "k2", "p1", "p2"],
        // COLMAP's order; k4..k6 are the rational terms.
        "FULL_OPENCV" => &["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"],
        // COLMAP's sx1, sy1 are OpenCV's s1, s3.
        "THIN_PRISM_FISHEYE" => &["k1", "k2", "p1", "p2", "k3", "k4", "s1", "s3"],
        "FOV" => &["omega"],
        "SIMPLE_DIVISION" | "DIVISION" => &["k1"],
        "EUCM" => &["alpha", "beta"],
        "OPENCV_FISHEYE" | "RADIAL_FISHEYE" | "SIMPLE_RADIAL_FISHEYE" | "SIMPLE_FISHEYE" | "FISHEYE" => &["k1", "k2", "k3", "k4"],
        _ => &[],
    };
    // nerfstudio writes all four fisheye coefficients, zeros for those a model lacks.
    let zeros = [0.0; 4];
    for (k, v) in names.iter().zip(rest.iter().chain(&zeros)) {
        m.insert((*k).into(), json!(v));
    }
    Ok(m)
}

/// The nerfstudio `transforms.json` of a model (what `ns-process-data` writes for it): one frame
/// per image, sorted by name, `file_path` = `images/NAME`, the image's camera keys in the frame,
/// and `applied_transform`. `path` names the cameras file in errors (an unsupported camera model).
pub fn transforms_json(path: &Path, model: &ColmapModel) -> Result<Value, DataError> {
    let mut images: Vec<&ColmapImage> = model.images.iter().collect();
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let mut frames = Vec::with_capacity(images.len());
    for im in images {
        let cam = model.cameras.iter().find(|c| c.id == im.camera_id).expect("checked by read_model");
        let mut frame = camera_keys(path, cam)?;
        frame.insert("file_path".into(), json!(format!("{IMAGES_DIR}/{}", im.name)));
        frame.insert("transform_matrix".into(), json!(camera_to_world(im)));
        frame.insert("colmap_im_id".into(), json!(im.id));
        frames.push(Value::Object(frame));
    }
    Ok(json!({ "frames": frames, "applied_transform": APPLIED_TRANSFORM }))
}
