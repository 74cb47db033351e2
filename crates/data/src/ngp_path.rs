//! instant-ngp's camera paths: the `base_cam.json` its GUI's camera-path editor saves and
//! `scripts/run.py --video_camera_path` renders, read by `nerf render --camera-path`.
//!
//! ```json
//! { "loop": false, "time": 0.0, "spline_order": 3, "duration_seconds": 3.0,
//!   "path": [ { "R": [x, y, z, w], "T": [x, y, z], "fov": 50.625, "timestamp": 1.0 }, … ] }
//! ```
//!
//! Each keyframe is a camera of instant-ngp's own space, not the transforms file's:
//! - `T` is the camera's position and `R` the rotation of its axes as a quaternion, in Eigen's
//!   coefficient order `(x, y, z, w)`, which instant-ngp keeps since it left Eigen. The camera's
//!   axes are right, down and forward (OpenCV's). A point `p` of the transforms file's frame is
//!   at `cycle(p·scale + offset)` in instant-ngp's space, where `cycle(x, y, z) = (y, z, x)`, and
//!   `scale` and `offset` are the file's (0.33 and `[0.5, 0.5, 0.5]` unless it says otherwise:
//!   [`NgpBox`]). This is instant-ngp's `nerf_matrix_to_ngp`; [`ngp_matrix_to_nerf`] undoes it.
//! - `fov` is the vertical field of view in degrees (instant-ngp's default `fov_axis`), with
//!   square pixels and the principal point at the frame's centre.
//! - `timestamp` paces the path: it starts at the first keyframe, and the keyframe after
//!   keyframe `i` is where it is at keyframe `i`'s timestamp, in seconds (instant-ngp's
//!   `get_pos`; a `loop` is back at its first keyframe at the last one's timestamp, an open path
//!   at its last keyframe at the next-to-last one's). Where the timestamps are missing (files
//!   from before instant-ngp had them) or do not increase from above 0, the keyframes are
//!   spread evenly over 3 seconds, as instant-ngp's `sanitize_keyframes` does.
//!
//! The path between keyframes is instant-ngp's `eval_camera_path`: a uniform B-spline of
//! `spline_order` (3, cubic, by default; 2 quadratic, 1 linear, 0 the nearest keyframe) over the
//! keyframes, the quaternions summed with their signs aligned and normalised. A cubic B-spline
//! passes near its keyframes, not through them. A `loop` path wraps around to its first
//! keyframe. Frame `i` of `n` is the camera at play time `i / n`, as in `run.py`, where the
//! frame's shutter opens then: `run.py` also blurs each frame over the next half frame of the
//! path (`nerf render --shutter 0.5`).
//!
//! Depth of field: a keyframe's `aperture_size` (`dof` in older files, which takes its place
//! where both are present) is the radius of its lens, and `slice + scale` the distance of the
//! plane in focus in front of it, both in instant-ngp's units (instant-ngp's `plane_z`). They are
//! splined with the rest; [`NgpCameraPath::lenses`] gives each frame's lens in scene units.
//!
//! Not used: `time` (the GUI's play head), `up_dir`, `glow_mode` and `glow_y_cutoff`.

use std::path::Path;

use nerf_rays::glam::{DMat3, DQuat, DVec3, DVec4};
use nerf_rays::{Camera, ThinLens};
use serde_json::Value;

use crate::camera_path::{fov_y_degrees, intrinsics_from_fov_y, read_json};
use crate::{DataError, Dataset, NerfstudioNormalization, NgpBox};

/// How long instant-ngp spreads keyframes without valid timestamps over (its
/// `default_duration_seconds`).
pub const DEFAULT_DURATION_SECONDS: f32 = 3.0;

/// One keyframe of an instant-ngp camera path, in instant-ngp's space (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NgpKeyframe {
    /// `R`: the rotation of the camera's axes (right, down, forward), a quaternion `(x, y, z, w)`
    /// as the file holds it (not necessarily of unit length).
    pub rotation: [f64; 4],
    /// `T`: the camera's position.
    pub position: [f64; 3],
    /// `fov`: vertical field of view, degrees.
    pub fov: f64,
    /// `timestamp`: the second at which the path reaches the next keyframe (module docs; 0 where
    /// the file has none).
    pub timestamp: f64,
    /// `aperture_size` (or `dof`): the lens's radius in instant-ngp's units; 0 (also where the
    /// file has none): a pinhole.
    pub aperture: f64,
    /// `slice + scale`: the distance of the plane in focus in front of the camera, in
    /// instant-ngp's units (its `plane_z`; [`NgpKeyframe::DEFAULT_FOCUS`] where the file has
    /// neither).
    pub focus: f64,
}

impl NgpKeyframe {
    /// The focus distance of a keyframe without `slice` or `scale`: instant-ngp's defaults (0 and
    /// 1.5, its camera's distance from the point it orbits).
    pub const DEFAULT_FOCUS: f64 = 1.5;

    /// instant-ngp's `CameraKeyframe::m()`: the 3×4 camera matrix (columns right, down, forward,
    /// position), row-major, from the normalised quaternion.
    pub fn matrix(&self) -> [[f64; 4]; 3] {
        let [x, y, z, w] = self.rotation;
        let r = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
        std::array::from_fn(|i| {
            let row = r.row(i);
            [row.x, row.y, row.z, self.position[i]]
        })
    }

    /// The keyframe of a camera matrix (columns right, down, forward, position; row-major):
    /// instant-ngp's `CameraKeyframe::from_m`.
    pub fn from_matrix(m: [[f64; 4]; 3], fov: f64, timestamp: f64) -> Self {
        let r = DMat3::from_cols(
            DVec3::new(m[0][0], m[1][0], m[2][0]),
            DVec3::new(m[0][1], m[1][1], m[2][1]),
            DVec3::new(m[0][2], m[1][2], m[2][2]),
        );
        let q = DQuat::from_mat3(&r);
        Self { rotation: [q.x, q.y, q.z, q.w], position: [m[0][3], m[1][3], m[2][3]], fov, timestamp, aperture: 0.0, focus: Self::DEFAULT_FOCUS }
    }
}

/// An instant-ngp camera path ([`NgpCameraPath::load`]).
#[derive(Clone, Debug, PartialEq)]
pub struct NgpCameraPath {
    /// The keyframes, in order, with valid timestamps (sanitised as instant-ngp does).
    pub keyframes: Vec<NgpKeyframe>,
    /// `loop`: the path returns from its last keyframe to its first.
    pub looped: bool,
    /// `spline_order`: 0 to 3 (3 when absent).
    pub spline_order: u32,
}

/// What a keyframe's terms add up to in a spline (f64; instant-ngp sums in f32).
#[derive(Clone, Copy)]
struct Sum {
    r: DVec4,
    t: DVec3,
    fov: f64,
    aperture: f64,
    focus: f64,
}

/// instant-ngp's weighted sum of keyframes `Σ wᵢ·kᵢ`, left to right, each quaternion's sign
/// aligned with the running sum's (`CameraKeyframe::operator+`), the quaternion normalised at
/// the end (`normalize(CameraKeyframe)`).
fn blend(terms: &[(&NgpKeyframe, f64)]) -> NgpKeyframe {
    let mut acc: Option<Sum> = None;
    for &(k, w) in terms {
        let term = Sum { r: DVec4::from_array(k.rotation) * w, t: DVec3::from_array(k.position) * w, fov: k.fov * w, aperture: k.aperture * w, focus: k.focus * w };
        acc = Some(match acc {
            None => term,
            Some(a) => {
                let r = if term.r.dot(a.r) < 0.0 { -term.r } else { term.r };
                Sum { r: a.r + r, t: a.t + term.t, fov: a.fov + term.fov, aperture: a.aperture + term.aperture, focus: a.focus + term.focus }
            }
        });
    }
    let a = acc.expect("a spline has terms");
    let r = a.r.try_normalize().unwrap_or(DVec4::W);
    NgpKeyframe { rotation: r.to_array(), position: a.t.to_array(), fov: a.fov, timestamp: 0.0, aperture: a.aperture, focus: a.focus }
}

impl NgpCameraPath {
    /// Reads an instant-ngp camera path. Errors name the file and the key: missing file,
    /// malformed JSON, no `path` or an empty one, a keyframe's `R` (4 finite numbers, not all 0),
    /// `T` (3 finite numbers) or `fov` (degrees in (0, 180)) missing or invalid, `loop` not a
    /// boolean, `spline_order` other than 0–3.
    pub fn load(path: &Path) -> Result<Self, DataError> {
        Self::parse(path, &read_json(path)?)
    }

    /// [`NgpCameraPath::load`] of a file already parsed (`path` names it in errors).
    pub fn parse(path: &Path, v: &Value) -> Result<Self, DataError> {
        let missing = |key: &str| DataError::MissingKey { path: path.to_path_buf(), key: key.into() };
        let invalid = |key: &str, reason: String| DataError::InvalidValue { path: path.to_path_buf(), key: key.into(), reason };
        if !v.is_object() {
            return Err(invalid("(top level)", "a camera path is a JSON object".into()));
        }
        let looped = match v.get("loop") {
            None | Some(Value::Null) => false,
            Some(l) => l.as_bool().ok_or_else(|| invalid("loop", format!("{l}: must be true or false")))?,
        };
        let spline_order = match v.get("spline_order") {
            None | Some(Value::Null) => 3,
            Some(s) => s.as_u64().filter(|&o| o <= 3).ok_or_else(|| {
                invalid("spline_order", format!("{s}: instant-ngp's splines are of order 0 (nearest), 1, 2 or 3 (cubic)"))
            })? as u32,
        };
        let frames = v.get("path").ok_or_else(|| missing("path"))?;
        let frames = frames.as_array().ok_or_else(|| invalid("path", "must be an array of keyframes".into()))?;
        if frames.is_empty() {
            return Err(invalid("path", "has no keyframes".into()));
        }
        let numbers = |f: &Value, i: usize, key: &str, n: usize| -> Result<Vec<f64>, DataError> {
            let k = format!("path[{i}].{key}");
            let x = f.get(key).ok_or_else(|| missing(&k))?;
            let vals: Option<Vec<f64>> = x.as_array().and_then(|a| a.iter().map(Value::as_f64).collect());
            vals.filter(|v| v.len() == n && v.iter().all(|x| x.is_finite()))
                .ok_or_else(|| invalid(&k, format!("{x}: must be {n} finite numbers")))
        };
        let mut keyframes = Vec::with_capacity(frames.len());
        for (i, f) in frames.iter().enumerate() {
            let r = numbers(f, i, "R", 4)?;
            if r.iter().all(|&x| x == 0.0) {
                return Err(invalid(&format!("path[{i}].R"), "[0, 0, 0, 0] is no rotation".into()));
            }
            let t = numbers(f, i, "T", 3)?;
            let key = format!("path[{i}].fov");
            let fov = f.get("fov").ok_or_else(|| missing(&key))?;
            let fov_deg = fov.as_f64().filter(|d| *d > 0.0 && *d < 180.0).ok_or_else(|| {
                invalid(&key, format!("{fov}: the vertical field of view must be in (0, 180) degrees"))
            })?;
            let timestamp = f.get("timestamp").and_then(Value::as_f64).unwrap_or(0.0);
            // The lens: `dof` where present (instant-ngp's `from_json`), else `aperture_size`.
            let number = |key: &str, default: f64| -> Result<f64, DataError> {
                match f.get(key) {
                    None | Some(Value::Null) => Ok(default),
                    Some(x) => x.as_f64().filter(|v| v.is_finite()).ok_or_else(|| invalid(&format!("path[{i}].{key}"), format!("{x}: must be a finite number"))),
                }
            };
            let aperture_key = if f.get("dof").is_some_and(|v| !v.is_null()) { "dof" } else { "aperture_size" };
            let aperture = number(aperture_key, 0.0)?;
            if aperture < 0.0 {
                return Err(invalid(&format!("path[{i}].{aperture_key}"), format!("{aperture}: the aperture's radius must be at least 0")));
            }
            let focus = number("slice", 0.0)? + number("scale", NgpKeyframe::DEFAULT_FOCUS)?;
            keyframes.push(NgpKeyframe { rotation: [r[0], r[1], r[2], r[3]], position: [t[0], t[1], t[2]], fov: fov_deg, timestamp, aperture, focus });
        }
        let mut p = Self { keyframes, looped, spline_order };
        p.sanitize_timestamps();
        Ok(p)
    }

    /// instant-ngp's `sanitize_keyframes`: unless the timestamps increase from above 0, the
    /// keyframes are spread evenly, keyframe `i` of `n` at `3·(i + 1)/n` seconds.
    fn sanitize_timestamps(&mut self) {
        let mut prev = 0.0;
        let valid = self.keyframes.iter().all(|k| {
            let ok = k.timestamp > prev; // also false for NaN
            prev = k.timestamp;
            ok
        });
        if !valid {
            let n = self.keyframes.len() as f64;
            for (i, k) in self.keyframes.iter_mut().enumerate() {
                k.timestamp = f64::from(DEFAULT_DURATION_SECONDS) * (i + 1) as f64 / n;
            }
        }
    }

    /// The path's length in seconds (its last keyframe's timestamp, instant-ngp's
    /// `duration_seconds`).
    pub fn duration_seconds(&self) -> f64 {
        self.keyframes.last().map_or(0.0, |k| k.timestamp)
    }

    /// instant-ngp's `get_keyframe`: index `i` wrapped around a loop, else clamped to the ends.
    fn keyframe(&self, i: i64) -> &NgpKeyframe {
        let n = self.keyframes.len() as i64;
        let i = if self.looped { i.rem_euclid(n) } else { i.clamp(0, n - 1) };
        &self.keyframes[i as usize]
    }

    /// instant-ngp's `get_pos`: the segment (keyframe index) and the fraction of it at play time
    /// `playtime` (0 to 1 over the path).
    fn position(&self, playtime: f64) -> (i64, f64) {
        let k = &self.keyframes;
        if k.len() == 1 {
            return (0, playtime);
        }
        let duration = if self.looped { k[k.len() - 1].timestamp } else { k[k.len() - 2].timestamp };
        let s = playtime * duration;
        let upper = k.partition_point(|kf| kf.timestamp <= s) as i64; // std::upper_bound
        let i = upper.clamp(0, k.len() as i64 - if self.looped { 1 } else { 2 });
        let prev = if i == 0 { 0.0 } else { k[i as usize - 1].timestamp };
        (i, (s - prev) / (k[i as usize].timestamp - prev))
    }

    /// The camera at play time `t` (0 to 1): instant-ngp's `eval_camera_path`.
    pub fn eval(&self, t: f64) -> NgpKeyframe {
        let (i, t) = self.position(t);
        let k = |j: i64| self.keyframe(i + j);
        match self.spline_order {
            0 => *k(t.round() as i64),
            1 => blend(&[(k(0), 1.0 - t), (k(1), t)]),
            2 => {
                let tt = t * t;
                blend(&[(k(-1), (1.0 - t) * (1.0 - t) * 0.5), (k(0), (-2.0 * tt + 2.0 * t + 1.0) * 0.5), (k(1), tt * 0.5)])
            }
            _ => {
                let (tt, ttt) = (t * t, t * t * t);
                blend(&[
                    (k(-1), (1.0 - t).powi(3) / 6.0),
                    (k(0), (3.0 * ttt - 6.0 * tt + 4.0) / 6.0),
                    (k(1), (-3.0 * ttt + 3.0 * tt + 3.0 * t + 1.0) / 6.0),
                    (k(2), ttt / 6.0),
                ])
            }
        }
    }

    /// `frames` cameras of `width × height` along the path, frame `i` at play time `i / frames`
    /// (see the module docs), in the frame of `space`'s scene. Errors name `path` if a keyframe
    /// gives no camera (a rotation that does not span space cannot come out of a normalised
    /// quaternion, so only non-finite values can).
    pub fn cameras(&self, path: &Path, frames: usize, width: u32, height: u32, space: &NgpSpace) -> Result<Vec<Camera>, DataError> {
        (0..frames)
            .map(|i| {
                self.camera_at(i as f64 / frames as f64, width, height, space).map_err(|e| DataError::InvalidValue {
                    path: path.to_path_buf(),
                    key: "path".into(),
                    reason: format!("frame {i}: {e}"),
                })
            })
            .collect()
    }

    /// The `width × height` camera at play time `t` (0 to 1), in the frame of `space`'s scene
    /// (what frame `i` of `n` is at `t = i / n`; `nerf render --shutter` also takes the
    /// camera at the frame's end, `(i + 1) / n`).
    pub fn camera_at(&self, t: f64, width: u32, height: u32, space: &NgpSpace) -> Result<Camera, nerf_rays::RayError> {
        let kf = self.eval(t);
        Camera::from_c2w(intrinsics_from_fov_y(width, height, kf.fov), &space.to_scene(kf.matrix()))
    }
}

impl NgpCameraPath {
    /// The lens of each of `frames` frames along the path (frame `i` at play time `i / frames`,
    /// as [`NgpCameraPath::cameras`]), in the scene units of `space`: `None` where the splined
    /// aperture is 0 (a pinhole). Errors name `path` where a frame with an aperture has its plane
    /// in focus at or behind the camera (`slice + scale` ≤ 0).
    pub fn lenses(&self, path: &Path, frames: usize, space: &NgpSpace) -> Result<Vec<Option<ThinLens>>, DataError> {
        (0..frames)
            .map(|i| {
                let kf = self.eval(i as f64 / frames as f64);
                if kf.aperture <= 0.0 {
                    return Ok(None);
                }
                let lens = ThinLens { aperture: space.length_to_scene(kf.aperture) as f32, focus_distance: space.length_to_scene(kf.focus) as f32 };
                lens.validate().map(|()| Some(lens)).map_err(|e| DataError::InvalidValue {
                    path: path.to_path_buf(),
                    key: "path".into(),
                    reason: format!("frame {i}'s lens (slice + scale {:.4}, aperture_size {:.4}): {e}", kf.focus, kf.aperture),
                })
            })
            .collect()
    }

    /// The path that replays `cameras` frame for frame when read back and rendered at
    /// `fps` frames a second, which [`NgpCameraPath::cameras`] does with `cameras.len()` frames
    /// (and `nerf render` by default): one keyframe per camera, in instant-ngp's space, its
    /// vertical field of view from `fy`, the last one twice (an open path ends at its last
    /// keyframe, which no frame reaches), linear (`spline_order` 1). For `n` cameras, keyframe
    /// `i` of the `n + 1` is timestamped `n·(i + 1) / ((n + 1)·fps)`: the path lasts `n / fps`
    /// seconds and frame `i` lands on keyframe `i`. `None` for no cameras.
    pub fn from_cameras(cameras: &[Camera], space: &NgpSpace, fps: f64) -> Option<Self> {
        let last = cameras.last()?;
        let n = cameras.len() as f64;
        let keyframes = cameras
            .iter()
            .chain(std::iter::once(last))
            .enumerate()
            .map(|(i, c)| NgpKeyframe::from_matrix(space.to_ngp(&c.c2w()), fov_y_degrees(&c.intrinsics), n * (i + 1) as f64 / ((n + 1.0) * fps)))
            .collect();
        Some(Self { keyframes, looped: false, spline_order: 1 })
    }

    /// The path as instant-ngp's `base_cam.json` (what its GUI's camera-path editor loads):
    /// `loop`, `time`, `spline_order`, `duration_seconds` and the keyframes' `R`, `T`, `fov`,
    /// `timestamp`, and each keyframe's lens: `aperture_size` (and `dof`, which older versions
    /// read), its focus distance as `scale` with `slice` 0.
    pub fn to_json(&self) -> Value {
        let path: Vec<Value> = self
            .keyframes
            .iter()
            .map(|k| {
                serde_json::json!({
                    "R": k.rotation, "T": k.position, "fov": k.fov, "timestamp": k.timestamp,
                    "scale": k.focus, "slice": 0.0, "aperture_size": k.aperture, "dof": k.aperture,
                })
            })
            .collect();
        serde_json::json!({
            "loop": self.looped, "time": 0.0, "spline_order": self.spline_order,
            "duration_seconds": self.duration_seconds(), "path": path,
        })
    }
}

/// instant-ngp's `ngp_matrix_to_nerf`: a camera matrix of instant-ngp's space (columns right,
/// down, forward, position; row-major) as a camera-to-world matrix of the transforms file's frame
/// (OpenGL axes: right, up, back) for a scene placed by `placement`: the rows cycled back
/// (`xyz → yzx`), the y and z axes flipped, the position `(q − offset) / scale`.
pub fn ngp_matrix_to_nerf(m: [[f64; 4]; 3], placement: &NgpBox) -> [[f64; 4]; 3] {
    let mut r = [m[2], m[0], m[1]];
    for (a, row) in r.iter_mut().enumerate() {
        row[1] = -row[1];
        row[2] = -row[2];
        row[3] = (row[3] - f64::from(placement.offset[a])) / f64::from(placement.scale);
    }
    r
}

/// instant-ngp's `nerf_matrix_to_ngp`, the inverse of [`ngp_matrix_to_nerf`]: a camera-to-world
/// matrix of the transforms file's frame in instant-ngp's space.
pub fn nerf_matrix_to_ngp(m: [[f64; 4]; 3], placement: &NgpBox) -> [[f64; 4]; 3] {
    let mut r = m;
    for (a, row) in r.iter_mut().enumerate() {
        row[1] = -row[1];
        row[2] = -row[2];
        row[3] = row[3] * f64::from(placement.scale) + f64::from(placement.offset[a]);
    }
    [r[1], r[2], r[0]]
}

/// Where instant-ngp puts a scene: how its space maps to the frame of [`Dataset::cameras`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NgpSpace {
    /// The transforms file's `scale` and `offset` (instant-ngp's defaults where it has none).
    pub placement: NgpBox,
    /// nerfstudio's normalisation, for a nerfstudio capture: instant-ngp reads the file's poses
    /// as they are, these cameras are normalised.
    pub normalization: Option<NerfstudioNormalization>,
}

impl NgpSpace {
    /// The space instant-ngp would load `ds` into: its file's placement, or instant-ngp's
    /// default (`scale` 0.33, `offset` 0.5) for NeRF's Blender scenes and nerfstudio captures
    /// (whose files have no `scale` or `offset`). `None` for LLFF scenes, which instant-ngp
    /// does not read (their cameras are in nerf-pytorch's recentred frame).
    pub fn of(ds: &Dataset) -> Option<Self> {
        if ds.depth_bounds.is_some() {
            return None;
        }
        let placement = match ds.normalization {
            Some(_) => NgpBox::default(),
            None => ds.ngp.unwrap_or_default(),
        };
        Some(Self { placement, normalization: ds.normalization })
    }

    /// A camera-to-world matrix (3 or 4 rows) of the dataset's frame as a camera matrix of
    /// instant-ngp's space: the inverse of [`NgpSpace::to_scene`].
    pub fn to_ngp(&self, c2w: &[[f32; 4]]) -> [[f64; 4]; 3] {
        let mut m: [[f32; 4]; 3] = [c2w[0], c2w[1], c2w[2]];
        if let Some(n) = &self.normalization {
            n.unapply(&mut m);
        }
        nerf_matrix_to_ngp(std::array::from_fn(|i| std::array::from_fn(|j| f64::from(m[i][j]))), &self.placement)
    }

    /// A length of instant-ngp's space in the dataset's frame: divided by the placement's
    /// `scale`, times nerfstudio's normalisation's.
    pub fn length_to_scene(&self, l: f64) -> f64 {
        let l = l / f64::from(self.placement.scale);
        match &self.normalization {
            Some(n) => l * n.scale,
            None => l,
        }
    }

    /// A length of the dataset's frame in instant-ngp's space: the inverse of
    /// [`NgpSpace::length_to_scene`].
    pub fn length_to_ngp(&self, l: f64) -> f64 {
        let l = match &self.normalization {
            Some(n) => l / n.scale,
            None => l,
        };
        l * f64::from(self.placement.scale)
    }

    /// A camera matrix of instant-ngp's space as a camera-to-world matrix (3 rows) of the
    /// dataset's frame.
    pub fn to_scene(&self, m: [[f64; 4]; 3]) -> [[f32; 4]; 3] {
        let m = ngp_matrix_to_nerf(m, &self.placement);
        let mut out: [[f32; 4]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| m[i][j] as f32));
        if let Some(n) = &self.normalization {
            n.apply(&mut out);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kf(rotation: [f64; 4], position: [f64; 3], fov: f64) -> NgpKeyframe {
        NgpKeyframe { rotation, position, fov, timestamp: 0.0, aperture: 0.0, focus: NgpKeyframe::DEFAULT_FOCUS }
    }

    fn path(keyframes: Vec<NgpKeyframe>, looped: bool, spline_order: u32) -> NgpCameraPath {
        let mut p = NgpCameraPath { keyframes, looped, spline_order };
        p.sanitize_timestamps();
        p
    }

    /// instant-ngp's default camera (`Testbed::reset_camera`: axes right, down, forward =
    /// `(1,0,0), (0,−1,0), (0,0,−1)`, 1.5 behind the unit cube's centre) sees a NeRF-synthetic
    /// scene from +x, `1.5 / 0.33` away, looking at the origin with +z up: worked out by hand
    /// from `ngp_matrix_to_nerf`.
    #[test]
    fn instant_ngps_default_camera_looks_at_the_origin_from_plus_x() {
        let m = [[1.0, 0.0, 0.0, 0.5], [0.0, -1.0, 0.0, 0.5], [0.0, 0.0, -1.0, 0.5 + 1.5]];
        let c = ngp_matrix_to_nerf(m, &NgpBox::default());
        let col = |j: usize| [c[0][j], c[1][j], c[2][j]];
        assert_eq!(col(0), [0.0, 1.0, 0.0], "right: +y");
        assert_eq!(col(1), [0.0, 0.0, 1.0], "up: +z");
        assert_eq!(col(2), [1.0, 0.0, 0.0], "back: +x, so it looks down −x");
        let p = col(3);
        assert!((p[0] - 1.5 / f64::from(0.33f32)).abs() < 1e-12 && p[1].abs() < 1e-12 && p[2].abs() < 1e-12, "{p:?}");
    }

    /// The two conversions undo each other for any placement; a keyframe made from a matrix
    /// gives the matrix back.
    #[test]
    fn conversions_round_trip() {
        let b = NgpBox { scale: 0.21, offset: [0.4, 0.6, 0.55], aabb_scale: 4.0 };
        let q = DQuat::from_euler(nerf_rays::glam::EulerRot::XYZ, 0.3, -1.1, 2.0);
        let r = DMat3::from_quat(q);
        let m: [[f64; 4]; 3] = std::array::from_fn(|i| {
            let row = r.row(i);
            [row.x, row.y, row.z, [1.5, -0.7, 3.2][i]]
        });
        let back = ngp_matrix_to_nerf(nerf_matrix_to_ngp(m, &b), &b);
        let k = NgpKeyframe::from_matrix(nerf_matrix_to_ngp(m, &b), 40.0, 0.0);
        let again = ngp_matrix_to_nerf(k.matrix(), &b);
        for i in 0..3 {
            for j in 0..4 {
                assert!((back[i][j] - m[i][j]).abs() < 1e-12, "{back:?} {m:?}");
                assert!((again[i][j] - m[i][j]).abs() < 1e-12, "{again:?} {m:?}");
            }
        }
    }

    /// A cubic B-spline reproduces straight lines: keyframes evenly along x give positions
    /// evenly along x inside the path, and at its start (where the first keyframe stands in for
    /// the one before it) 1/6 of the way to the second keyframe.
    #[test]
    fn the_cubic_spline_follows_instant_ngps() {
        let id = [0.0, 0.0, 0.0, 1.0];
        let p = path((0..6).map(|i| kf(id, [i as f64, 0.0, 0.0], 30.0 + i as f64)).collect(), false, 3);
        // Six keyframes spread over 3 s: the path is at keyframe i at 0.5·i s and ends at 2.5 s.
        assert_eq!(p.keyframes.iter().map(|k| k.timestamp).collect::<Vec<_>>(), vec![0.5, 1.0, 1.5, 2.0, 2.5, 3.0]);
        for (t, x) in [(0.3, 1.5), (0.5, 2.5), (0.62, 3.1)] {
            let k = p.eval(t);
            assert!((k.position[0] - x).abs() < 1e-12, "t = {t}: {k:?}");
            assert!((k.fov - (30.0 + x)).abs() < 1e-12, "the field of view is splined too: {k:?}");
            assert_eq!(k.rotation, id);
        }
        assert!((p.eval(0.0).position[0] - 1.0 / 6.0).abs() < 1e-12);
        // Linear: through the keyframes; nearest: the keyframes themselves.
        let lin = NgpCameraPath { spline_order: 1, ..p.clone() };
        assert!((lin.eval(0.0).position[0]).abs() < 1e-12 && (lin.eval(0.5).position[0] - 2.5).abs() < 1e-12);
        let near = NgpCameraPath { spline_order: 0, ..p.clone() };
        assert_eq!(near.eval(0.5).position[0], 3.0, "2.5 rounds to keyframe 3 (round half away from zero)");
        assert_eq!(near.eval(0.45).position[0], 2.0);
    }

    /// Quaternions are summed with their signs aligned (q and −q are one rotation) and
    /// normalised: halfway between two pairs of keyframes turned 0° and 90° about z, the camera
    /// is turned 45°, whichever sign the file wrote the second rotation with.
    #[test]
    fn rotations_blend_on_the_short_way() {
        let a = DQuat::IDENTITY;
        let b = DQuat::from_rotation_z(std::f64::consts::FRAC_PI_2);
        for sign in [1.0, -1.0] {
            let qb = [sign * b.x, sign * b.y, sign * b.z, sign * b.w];
            let ks = vec![kf(a.to_array(), [0.0; 3], 50.0), kf(a.to_array(), [0.0; 3], 50.0), kf(qb, [0.0; 3], 50.0), kf(qb, [0.0; 3], 50.0)];
            let p = path(ks, false, 3);
            let k = p.eval(0.5); // segment 1, halfway: weights 1/48, 23/48, 23/48, 1/48
            let [x, y, z, w] = k.rotation;
            let angle = DQuat::from_xyzw(x, y, z, w).angle_between(DQuat::from_rotation_z(std::f64::consts::FRAC_PI_4));
            assert!(angle < 1e-7, "sign {sign}: {k:?}");
        }
    }

    /// A loop wraps: its start blends the last keyframe in, and it runs over every keyframe's
    /// interval, the last one's included.
    #[test]
    fn a_loop_wraps_around() {
        let id = [0.0, 0.0, 0.0, 1.0];
        let ks: Vec<_> = [0.0, 1.0, 2.0, 3.0].iter().map(|&x| kf(id, [x, 0.0, 0.0], 50.0)).collect();
        let p = path(ks.clone(), true, 3);
        assert!((p.eval(0.0).position[0] - (3.0 + 4.0 * 0.0 + 1.0) / 6.0).abs() < 1e-12);
        // Play time 7/8: segment 3, halfway, between keyframes 3 and 0 (weights 1/48, 23/48, 23/48, 1/48 on 2, 3, 0, 1).
        let x = (2.0 + 23.0 * 3.0 + 23.0 * 0.0 + 1.0) / 48.0;
        assert!((p.eval(0.875).position[0] - x).abs() < 1e-12, "{:?}", p.eval(0.875));
        let open = path(ks, false, 1);
        assert!((open.eval(1.0).position[0] - 3.0).abs() < 1e-12, "an open path ends at its last keyframe");
    }

    /// Valid timestamps place the keyframes in time; invalid ones are spread evenly over 3 s.
    #[test]
    fn timestamps_set_the_pace() {
        let id = [0.0, 0.0, 0.0, 1.0];
        let mut ks: Vec<_> = [0.0, 1.0, 2.0].iter().map(|&x| kf(id, [x, 0.0, 0.0], 50.0)).collect();
        ks[0].timestamp = 1.0;
        ks[1].timestamp = 4.0;
        ks[2].timestamp = 5.0;
        let p = path(ks.clone(), false, 1);
        assert_eq!(p.keyframes[1].timestamp, 4.0, "increasing timestamps are kept");
        // Open path: at keyframe 0 at 0 s, keyframe 1 at 1 s, keyframe 2 at 4 s (the end). Play
        // time 0.5 is 2 s, a third of the way from keyframe 1 to 2.
        assert!((p.eval(0.5).position[0] - 4.0 / 3.0).abs() < 1e-12, "{:?}", p.eval(0.5));
        ks[2].timestamp = 3.0;
        let p = path(ks, false, 1);
        assert_eq!(p.keyframes.iter().map(|k| k.timestamp).collect::<Vec<_>>(), vec![1.0, 2.0, 3.0]);
        assert_eq!(p.duration_seconds(), 3.0);
    }

    /// A written path read back gives the cameras it was written from, frame for frame, in a
    /// file's placement and through nerfstudio's normalisation alike.
    #[test]
    fn written_paths_replay_their_cameras() {
        use nerf_rays::glam::{Mat3, Quat, Vec3};
        use nerf_rays::Intrinsics;
        let k = Intrinsics { width: 40, height: 30, fx: 35.0, fy: 35.0, cx: 20.0, cy: 15.0 };
        let cams: Vec<Camera> = (0..5)
            .map(|i| {
                let a = i as f32 * 0.4;
                let rot = Mat3::from_quat(Quat::from_euler(nerf_rays::glam::EulerRot::ZXY, a, 0.3 + 0.1 * a, -0.2));
                let pos = Vec3::new(2.0 * a.cos(), 2.0 * a.sin(), 0.5 + 0.1 * a);
                let mut c2w = [[0.0f32; 4]; 3];
                for r in 0..3 {
                    for col in 0..3 {
                        c2w[r][col] = rot.col(col)[r];
                    }
                    c2w[r][3] = pos[r];
                }
                Camera::from_c2w(k, &c2w).unwrap()
            })
            .collect();
        let normalization = NerfstudioNormalization::of(&cams.iter().map(|c| c.c2w()).collect::<Vec<_>>().iter().map(|m| &m[..]).collect::<Vec<_>>());
        assert!(normalization.is_some());
        for space in [
            NgpSpace { placement: NgpBox { scale: 0.2, offset: [0.4, 0.5, 0.6], aabb_scale: 2.0 }, normalization: None },
            NgpSpace { placement: NgpBox::default(), normalization },
        ] {
            let p = NgpCameraPath::from_cameras(&cams, &space, 60.0).unwrap();
            let back = NgpCameraPath::parse(Path::new("base_cam.json"), &p.to_json()).unwrap();
            assert_eq!(back.keyframes.len(), 6);
            assert!((back.duration_seconds() * 60.0 - 5.0).abs() < 1e-9, "5 frames at 60 a second");
            let again = back.cameras(Path::new("base_cam.json"), cams.len(), k.width, k.height, &space).unwrap();
            for (i, (a, b)) in cams.iter().zip(&again).enumerate() {
                let (ma, mb) = (a.c2w(), b.c2w());
                for r in 0..3 {
                    for c in 0..4 {
                        assert!((ma[r][c] - mb[r][c]).abs() < 2e-5, "frame {i} [{r}][{c}]: {ma:?} vs {mb:?}");
                    }
                }
                assert!((a.intrinsics.fy - b.intrinsics.fy).abs() < 1e-3 && b.intrinsics.cx == 20.0, "{:?}", b.intrinsics);
            }
        }
    }

    /// Errors name the file and the key.
    #[test]
    fn bad_files_are_refused_by_key() {
        let p = Path::new("base_cam.json");
        let err = |text: &str| NgpCameraPath::parse(p, &serde_json::from_str(text).unwrap()).unwrap_err().to_string();
        let good = r#"{"R": [0, 0, 0, 1], "T": [0.5, 0.5, 2], "fov": 50}"#;
        assert!(NgpCameraPath::parse(p, &serde_json::from_str(&format!(r#"{{"path": [{good}]}}"#)).unwrap()).is_ok());
        for (text, words) in [
            (r#"{"loop": true}"#.to_string(), &["base_cam.json", "path"][..]),
            (r#"{"path": []}"#.to_string(), &["path", "no keyframes"]),
            (format!(r#"{{"path": [{good}, {{"R": [0, 0, 1], "T": [0, 0, 0], "fov": 50}}]}}"#), &["path[1].R", "4 finite numbers"]),
            (r#"{"path": [{"R": [0, 0, 0, 0], "T": [0, 0, 0], "fov": 50}]}"#.to_string(), &["path[0].R", "no rotation"]),
            (r#"{"path": [{"R": [0, 0, 0, 1], "T": [0, "a", 0], "fov": 50}]}"#.to_string(), &["path[0].T"]),
            (r#"{"path": [{"R": [0, 0, 0, 1], "T": [0, 0, 0]}]}"#.to_string(), &["path[0].fov"]),
            (r#"{"path": [{"R": [0, 0, 0, 1], "T": [0, 0, 0], "fov": 180}]}"#.to_string(), &["path[0].fov", "(0, 180)"]),
            (format!(r#"{{"spline_order": 4, "path": [{good}]}}"#), &["spline_order"]),
            (format!(r#"{{"loop": 1, "path": [{good}]}}"#), &["loop"]),
            (r#"{"path": [{"R": [0, 0, 0, 1], "T": [0, 0, 0], "fov": 50, "aperture_size": -0.1}]}"#.to_string(), &["path[0].aperture_size", "at least 0"]),
            (r#"{"path": [{"R": [0, 0, 0, 1], "T": [0, 0, 0], "fov": 50, "dof": "wide"}]}"#.to_string(), &["path[0].dof", "finite number"]),
            (r#"{"path": [{"R": [0, 0, 0, 1], "T": [0, 0, 0], "fov": 50, "scale": null, "slice": [1]}]}"#.to_string(), &["path[0].slice"]),
        ] {
            let e = err(&text);
            assert!(words.iter().all(|w| e.contains(w)), "{text}: {e}");
        }
    }

    /// A keyframe's lens: `dof` in place of `aperture_size` where both are present, focus at
    /// `slice + scale` (1.5 by default), splined with the rest, converted to scene units by the
    /// placement's scale (and nerfstudio's), and written back.
    #[test]
    fn keyframes_carry_their_lens() {
        let p = Path::new("base_cam.json");
        let text = r#"{"spline_order": 1, "path": [
            {"R": [0, 0, 0, 1], "T": [0.5, 0.5, 2], "fov": 50, "timestamp": 1, "aperture_size": 0.9, "dof": 0.02, "slice": 0.1, "scale": 1.0},
            {"R": [0, 0, 0, 1], "T": [0.5, 0.5, 2], "fov": 50, "timestamp": 2, "aperture_size": 0.04, "slice": -0.1, "scale": 2.0},
            {"R": [0, 0, 0, 1], "T": [0.5, 0.5, 2], "fov": 50, "timestamp": 3}]}"#;
        let path = NgpCameraPath::parse(p, &serde_json::from_str(text).unwrap()).unwrap();
        let k: Vec<(f64, f64)> = path.keyframes.iter().map(|k| (k.aperture, k.focus)).collect();
        assert_eq!(k, vec![(0.02, 1.1), (0.04, 1.9), (0.0, NgpKeyframe::DEFAULT_FOCUS)]);
        // Linear between the first two: halfway through the first segment (play time 1/4).
        let mid = path.eval(0.25);
        assert!((mid.aperture - 0.03).abs() < 1e-12 && (mid.focus - 1.5).abs() < 1e-12, "{mid:?}");
        for (space, unit) in [
            (NgpSpace { placement: NgpBox { scale: 0.25, offset: [0.5; 3], aabb_scale: 1.0 }, normalization: None }, 4.0),
            (
                NgpSpace {
                    placement: NgpBox::default(),
                    normalization: Some(NerfstudioNormalization { rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], center: [0.0; 3], scale: 0.5 }),
                },
                0.5 / f64::from(0.33f32),
            ),
        ] {
            assert!((space.length_to_ngp(space.length_to_scene(0.7)) - 0.7).abs() < 1e-12);
            let lenses = path.lenses(p, 4, &space).unwrap();
            let l = lenses[1].expect("an aperture at play time 1/4");
            assert!((f64::from(l.aperture) - 0.03 * unit).abs() < 1e-6 && (f64::from(l.focus_distance) - 1.5 * unit).abs() < 1e-5, "{l:?}");
            // The first frame has the first keyframe's lens.
            let l = lenses[0].expect("the first keyframe's aperture");
            assert!((f64::from(l.aperture) - 0.02 * unit).abs() < 1e-6 && (f64::from(l.focus_distance) - 1.1 * unit).abs() < 1e-5, "{l:?}");
        }
        // Written and read back, the lens stays.
        let back = NgpCameraPath::parse(p, &path.to_json()).unwrap();
        for (a, b) in path.keyframes.iter().zip(&back.keyframes) {
            assert!((a.aperture - b.aperture).abs() < 1e-12 && (a.focus - b.focus).abs() < 1e-12);
        }
        // A lens focused behind the camera is refused by frame.
        let behind = r#"{"path": [{"R": [0, 0, 0, 1], "T": [0, 0, 0], "fov": 50, "aperture_size": 0.1, "slice": -2, "scale": 1}]}"#;
        let path = NgpCameraPath::parse(p, &serde_json::from_str(behind).unwrap()).unwrap();
        let e = path.lenses(p, 2, &NgpSpace { placement: NgpBox::default(), normalization: None }).unwrap_err().to_string();
        assert!(e.contains("base_cam.json") && e.contains("frame 0") && e.contains("focus"), "{e}");
    }
}
