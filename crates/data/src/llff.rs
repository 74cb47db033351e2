//! LLFF scenes: the NeRF paper's real forward-facing captures (`nerf_llff_data/fern`, …).
//!
//! A scene folder holds `poses_bounds.npy` (N×17 little-endian f64: per image a 3×5 matrix
//! `[R | t | (h, w, f)]` in LLFF's axis order `[down, right, back]`, then the near and far depth
//! bounds) and the images in `images/` (full resolution) and/or `images_<k>/` (downscaled by k),
//! sorted by name. [`load_llff`] follows nerf-pytorch's `load_llff_data` with its defaults:
//! - axes to OpenGL's `[right, up, back]` (what [`Camera`] expects);
//! - `bd_factor = 0.75`: translations and bounds scaled by `1 / (0.75 · min near bound)`;
//! - poses recentred on their average (`recenter_poses`): the mean camera becomes the identity;
//! - held-out views: every 8th image (`llffhold = 8`) is the test split (and the validation
//!   split, as in nerf-pytorch); the others are the training split.
//!
//! Rays are in NeRF's normalised device coordinates by default (`LoadOptions::ndc`, the paper's
//! protocol; [`nerf_rays::Ndc`] with the near plane at `z = −1` and the images' intrinsics):
//! `near = 0`, the scene box is the NDC hull of every camera's frustum with `z' ∈ [−1, 1]`, and a
//! ray's segment is its part inside that box (near plane to infinite depth, linear in
//! disparity). Without NDC (nerf-pytorch's `--no_ndc`) rays are Euclidean: `near = 0.9 · min
//! bound`, `far = max bound` stretched by the largest `|d|` of a camera-space pixel direction
//! `(x, y, −1)`, so that every pixel's ray reaches the far depth bound; the scene box covers
//! every camera's frustum between those.

use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};
use nerf_rays::{Aabb, Camera, Intrinsics, Ndc};

use crate::{DataError, Dataset, LoadOptions, Split};

/// The file that marks an LLFF scene.
pub const POSES_FILE: &str = "poses_bounds.npy";

/// nerf-pytorch's `llffhold`: every 8th image is held out for testing.
pub const LLFF_HOLD: usize = 8;

/// nerf-pytorch's `bd_factor`: the nearest depth bound is scaled to `1 / 0.75`.
pub const BD_FACTOR: f64 = 0.75;

/// True when `root` holds an LLFF scene (`poses_bounds.npy`).
pub fn is_llff(root: &Path) -> bool {
    root.join(POSES_FILE).is_file()
}

/// One row of `poses_bounds.npy`, in f64.
struct Row {
    /// LLFF's 3×5 matrix, row-major: `[down, right, back, t, (h, w, f)]` columns.
    m: [[f64; 5]; 3],
    /// Near and far depth bounds.
    bounds: [f64; 2],
}

fn bad_poses(path: &Path, reason: impl Into<String>) -> DataError {
    DataError::InvalidValue { path: path.to_path_buf(), key: "poses_bounds".into(), reason: reason.into() }
}

/// Reads `poses_bounds.npy`: an N×17 float array (f64 or f32, C order), every value finite.
fn read_rows(path: &Path) -> Result<Vec<Row>, DataError> {
    let bytes = std::fs::read(path).map_err(|source| DataError::Io { path: path.to_path_buf(), source })?;
    let npy = npyz::NpyFile::new(&bytes[..]).map_err(|e| bad_poses(path, format!("not a .npy array: {e}")))?;
    let shape = npy.shape().to_vec();
    if shape.len() != 2 || shape[1] != 17 || shape[0] == 0 {
        return Err(bad_poses(path, format!("expected an N×17 array (N ≥ 1), got shape {shape:?}")));
    }
    if npy.order() != npyz::Order::C {
        return Err(bad_poses(path, "Fortran-ordered arrays are not supported"));
    }
    let values: Vec<f64> = match npy.dtype().descr().trim_matches(|c| c == '\'' || c == '"') {
        "<f8" => npy.into_vec::<f64>(),
        "<f4" => npy.into_vec::<f32>().map(|v| v.into_iter().map(f64::from).collect()),
        d => return Err(bad_poses(path, format!("expected little-endian float64 or float32 values, got dtype {d}"))),
    }
    .map_err(|e| bad_poses(path, format!("truncated or unreadable data: {e}")))?;
    values
        .chunks_exact(17)
        .enumerate()
        .map(|(i, r)| {
            if r.iter().any(|v| !v.is_finite()) {
                return Err(DataError::NonFinitePose { path: path.to_path_buf(), frame: i });
            }
            let m = std::array::from_fn(|row| std::array::from_fn(|c| r[5 * row + c]));
            let bounds = [r[15], r[16]];
            if !(bounds[0] > 0.0 && bounds[1] > bounds[0]) {
                return Err(bad_poses(path, format!("image {i}: depth bounds {bounds:?} are not 0 < near < far")));
            }
            let (h, w, f) = (r[4], r[9], r[14]);
            if !(h >= 1.0 && w >= 1.0 && f > 0.0) {
                return Err(bad_poses(path, format!("image {i}: (h, w, focal) = ({h}, {w}, {f}) must be positive")));
            }
            Ok(Row { m, bounds })
        })
        .collect()
}

/// A camera-to-world pose in f64: rotation columns (camera x, y, z in the world) and centre.
#[derive(Clone, Copy, Debug)]
struct Pose {
    r: DMat3,
    t: DVec3,
}

impl Pose {
    /// LLFF's `[down, right, back, t]` columns → OpenGL's `[right, up, back, t]`
    /// (nerf-pytorch: `poses[:, 1:2], -poses[:, 0:1], poses[:, 2:]`).
    fn from_llff(m: &[[f64; 5]; 3]) -> Self {
        let col = |c: usize| DVec3::new(m[0][c], m[1][c], m[2][c]);
        Pose { r: DMat3::from_cols(col(1), -col(0), col(2)), t: col(3) }
    }

    /// nerf-pytorch's `poses_avg`: centre = mean position, z = normalised sum of the z axes,
    /// up = sum of the y axes, then `viewmatrix(z, up, centre)`.
    fn average(poses: &[Pose]) -> Pose {
        let n = poses.len() as f64;
        let center = poses.iter().map(|p| p.t).sum::<DVec3>() / n;
        let z = poses.iter().map(|p| p.r.z_axis).sum::<DVec3>().normalize();
        let up = poses.iter().map(|p| p.r.y_axis).sum::<DVec3>();
        let x = up.cross(z).normalize();
        let y = z.cross(x).normalize();
        Pose { r: DMat3::from_cols(x, y, z), t: center }
    }

    /// `self⁻¹ · other` for rigid poses.
    fn relative(&self, other: &Pose) -> Pose {
        let rt = self.r.transpose();
        Pose { r: rt * other.r, t: rt * (other.t - self.t) }
    }
}

/// The image folder for downscale `k`: `images_<k>` (or `images` for 1) when present, else the
/// most downscaled `images_<j>` with `j` dividing `k` (then box-averaged by `k / j`). Returns
/// the folder and `j`.
fn image_folder(root: &Path, k: u32) -> Result<(PathBuf, u32), DataError> {
    let name = |j: u32| if j == 1 { "images".to_string() } else { format!("images_{j}") };
    #[allow(clippy::manual_is_multiple_of)] // keeps the MSRV (1.85)
    for j in (1..=k).rev().filter(|j| k % j == 0) {
        let dir = root.join(name(j));
        if dir.is_dir() {
            return Ok((dir, j));
        }
    }
    let mut present: Vec<String> = std::fs::read_dir(root)
        .map(|it| {
            it.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n == "images" || n.strip_prefix("images_").is_some_and(|s| s.parse::<u32>().is_ok()))
                .collect()
        })
        .unwrap_or_default();
    present.sort();
    Err(DataError::BadDownscale {
        path: root.join(name(k)),
        k,
        reason: if present.is_empty() {
            "the scene has no images/ or images_<k>/ folder".into()
        } else {
            format!(
                "no image folder for this factor or a divisor of it; the scene has {} (e.g. --downscale {})",
                present.join(", "),
                present.last().and_then(|n| n.strip_prefix("images_")).unwrap_or("1")
            )
        },
    })
}

/// Image files of a folder, sorted by name (`.png`, `.jpg`, `.jpeg`, any case), as nerf-pytorch
/// lists them.
fn image_files(dir: &Path) -> Result<Vec<PathBuf>, DataError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|source| DataError::Io { path: dir.to_path_buf(), source })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let ext = p.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
            matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg"))
        })
        .collect();
    files.sort();
    Ok(files)
}

/// Indices of `split` among `n` images: every [`LLFF_HOLD`]th for test (and val), the rest for train.
pub fn split_indices(n: usize, split: Split) -> Vec<usize> {
    (0..n).filter(|i| (i % LLFF_HOLD == 0) != (split == Split::Train)).collect()
}

/// Loads one split of an LLFF scene (see the module docs for the conventions). `opts.downscale`
/// picks the image folder (`images_<k>`, or a folder of a divisor of `k` box-averaged to it);
/// `opts.views` selects among the split's views. Errors name the file: a missing or malformed
/// `poses_bounds.npy`, a non-finite pose, an image count that does not match the poses, images of
/// different sizes, or a size that does not match the poses' aspect ratio.
pub fn load_llff(root: &Path, split: Split, opts: &LoadOptions) -> Result<Dataset, DataError> {
    let poses_path = root.join(POSES_FILE);
    if !poses_path.is_file() {
        return Err(DataError::MissingTransforms { path: poses_path });
    }
    if let Some(s) = opts.aabb_scale {
        return Err(DataError::InvalidValue {
            path: poses_path,
            key: "aabb_scale".into(),
            reason: format!("{s}: an LLFF scene has no instant-ngp box (its rays are bounded by its depths, or by NDC)"),
        });
    }
    let rows = read_rows(&poses_path)?;
    let k = opts.downscale;
    if k == 0 {
        return Err(DataError::BadDownscale { path: poses_path, k, reason: "the factor must be at least 1".into() });
    }
    let (dir, j) = image_folder(root, k)?;
    let files = image_files(&dir)?;
    if files.len() != rows.len() {
        return Err(DataError::InvalidValue {
            path: dir.clone(),
            key: "images".into(),
            reason: format!("{} image files, but {} poses in {POSES_FILE}", files.len(), rows.len()),
        });
    }

    // Scale (bd_factor), axes, recentring: over all images, so both splits share one world.
    let sc = 1.0 / (rows.iter().map(|r| r.bounds[0]).fold(f64::INFINITY, f64::min) * BD_FACTOR);
    let poses: Vec<Pose> = rows
        .iter()
        .map(|r| {
            let p = Pose::from_llff(&r.m);
            Pose { t: p.t * sc, ..p }
        })
        .collect();
    let avg = Pose::average(&poses);
    let poses: Vec<Pose> = poses.iter().map(|p| avg.relative(p)).collect();
    let near_bound = sc * rows.iter().map(|r| r.bounds[0]).fold(f64::INFINITY, f64::min);
    let far_bound = sc * rows.iter().map(|r| r.bounds[1]).fold(0.0, f64::max);

    // The images are in the order of their names.
    let selected_split = match opts.holdout {
        Some(h) => {
            let names: Vec<String> = files.iter().map(|f| crate::file_name_of(f)).collect();
            h.split(&names, split).map_err(|reason| DataError::InvalidValue { path: dir.clone(), key: "holdout".into(), reason })?
        }
        None => split_indices(rows.len(), split),
    };
    let selected: Vec<usize> = opts
        .views
        .indices(selected_split.len())
        .map_err(|reason| DataError::BadSelection { path: poses_path.clone(), reason })?
        .into_iter()
        .map(|i| selected_split[i])
        .collect();
    if selected.is_empty() {
        return Err(DataError::EmptySplit {
            path: poses_path.clone(),
            reason: format!(
                "{} of the {} images are in the {} split; view selection `{}` leaves none",
                selected_split.len(),
                rows.len(),
                split.as_str(),
                opts.views
            ),
        });
    }

    let sub = k / j;
    let paths: Vec<&Path> = selected.iter().map(|&i| files[i].as_path()).collect();
    let (w, h, images) = crate::decode_views(&paths, sub, opts.cameras_only)?;
    let first = files[selected[0]].clone();

    // Intrinsics: the poses hold the full-resolution (h, w, focal); the folder's images are that
    // divided by their factor, so the focal scales with the image width (nerf-pytorch takes the
    // factor from the folder's name; the images' size is checked against the poses' aspect ratio).
    let (h0, w0, f0) = (rows[0].m[0][4], rows[0].m[1][4], rows[0].m[2][4]);
    let (wj, hj) = (w as f64, h as f64);
    if ((wj / hj) - (w0 / h0)).abs() > 0.01 * (w0 / h0) {
        return Err(DataError::InvalidValue {
            path: first,
            key: "image size".into(),
            reason: format!("{wj}x{hj} does not have the aspect ratio of the poses' {w0}x{h0}"),
        });
    }
    let f = (f0 * wj / w0) as f32;
    let intr =
        Intrinsics { width: wj as u32, height: hj as u32, fx: f, fy: f, cx: wj as f32 * 0.5, cy: hj as f32 * 0.5 }
            .downscaled(sub);

    let all_cameras = poses
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let c2w: Vec<[f32; 4]> = (0..3)
                .map(|r| [p.r.x_axis[r] as f32, p.r.y_axis[r] as f32, p.r.z_axis[r] as f32, p.t[r] as f32])
                .collect();
            Camera::from_c2w(intr, &c2w).map_err(|e| DataError::pose(&poses_path, i, e))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let cameras: Vec<Camera> = selected.iter().map(|&i| all_cameras[i]).collect();

    let (near, far, aabb, ndc) = if opts.ndc {
        // NDC (the paper): near plane z = −1 in the recentred, bd_factor-scaled world; every
        // ray's segment is its part inside the box, z' ∈ [−1, 1].
        let ndc = Ndc::new(&intr, Ndc::NEAR_PLANE);
        let aabb = ndc.scene_box(&all_cameras, 0.05).ok_or_else(|| {
            let colmap = crate::colmap::find_model(root).map_or("", |_| ", or read the folder's COLMAP model with --scene-format colmap, as for mip-NeRF 360's scenes");
            bad_poses(&poses_path, format!("a camera looks away from the scene's mean viewing direction: not a forward-facing capture, so NDC does not apply (train with --no-ndc{colmap})"))
        })?;
        // Any segment inside the box is shorter than its diagonal: a far bound the clip reaches.
        let far = aabb.extent().iter().map(|e| e * e).sum::<f32>().sqrt();
        (0.0f32, far, aabb, Some(ndc))
    } else {
        // The farthest pixel ray: |(x, y, −1)| at an image corner.
        let corner = DVec3::new(0.5 * intr.width as f64 / intr.fx as f64, 0.5 * intr.height as f64 / intr.fy as f64, 1.0);
        let near = 0.9 * near_bound;
        let far = far_bound * corner.length();
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for p in &poses {
            lo = lo.min(p.t);
            hi = hi.max(p.t);
            for (sx, sy) in [(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)] {
                let d = p.r * DVec3::new(sx * corner.x, sy * corner.y, -1.0);
                for depth in [near_bound * 0.9, far_bound] {
                    let q = p.t + d * depth;
                    lo = lo.min(q);
                    hi = hi.max(q);
                }
            }
        }
        let pad = (hi - lo) * 0.02;
        let (lo, hi) = ((lo - pad).as_vec3(), (hi + pad).as_vec3());
        (near as f32, far as f32, Aabb { min: lo.to_array(), max: hi.to_array() }, None)
    };

    Ok(Dataset {
        root: root.to_path_buf(),
        split,
        width: intr.width,
        height: intr.height,
        cameras,
        images,
        file_paths: selected.iter().map(|&i| files[i].clone()).collect(),
        masks: None,
        depths: None,
        near,
        far,
        aabb,
        ndc,
        depth_bounds: Some([near_bound as f32, far_bound as f32]),
        ngp: None,
        normalization: None,
    })
}

/// The novel-view path nerf-pytorch renders for an LLFF scene: [`nerf_rays::spiral`] about the
/// cameras of `ds` (its training split), focused as nerf-pytorch does from the depth bounds
/// (`0.9 · min bound` and `5 · max bound`, [`Dataset::depth_bounds`]), with `intrinsics` for
/// every frame. `None` for a scene without depth bounds (not LLFF) or cameras.
pub fn render_path(ds: &Dataset, intrinsics: Intrinsics, n: usize) -> Option<Vec<Camera>> {
    let [lo, hi] = ds.depth_bounds?;
    nerf_rays::spiral(&ds.cameras, 0.9 * lo, 5.0 * hi, intrinsics, n)
}

/// How far in front of its cameras [`render_path`]'s spiral looks ([`nerf_rays::spiral_focus`]
/// of its depths). `None` for a scene without depth bounds.
pub fn focus_depth(ds: &Dataset) -> Option<f32> {
    let [lo, hi] = ds.depth_bounds?;
    Some(nerf_rays::spiral_focus(0.9 * lo, 5.0 * hi))
}
