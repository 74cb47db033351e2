//! Datasets: the Blender (NeRF synthetic), instant-ngp / nerfstudio (captured scenes, [`ngp`]),
//! COLMAP (a sparse model beside the photos, [`colmap`]) and LLFF (real forward-facing,
//! [`llff`]) formats, image loading and downscaling, backgrounds, random ray batches.
//! [`load_scene`] tells them apart.
//!
//! The Blender format is a scene folder with `transforms_{train,val,test}.json`, each holding
//! `camera_angle_x` (horizontal field of view, radians) and `frames[]` of
//! `{ "file_path": "./train/r_0", "transform_matrix": 4×4 camera-to-world }` (OpenGL axes);
//! `file_path` is relative to the scene folder and gets `.png` appended when it has no extension.
//! Images are RGBA PNGs; [`load_blender`] keeps them as straight (not premultiplied) RGBA `f32`
//! in `[0, 1]` and composites onto a background only when rays are drawn ([`Background`]).
//! The same loader reads what instant-ngp's `colmap2nerf.py` and nerfstudio's `ns-process-data`
//! write for captured photos: one `transforms.json`, intrinsics in pixels, lens distortion, the
//! scene box, JPEG images ([`ngp`]).
//!
//! Ray batches ([`RayBatch`]) are flat `f32` arrays (`3·n` per quantity) refilled in place, so the
//! training loop does not allocate: [`Dataset::sample_rays`] for training (uniform over all pixels
//! of all views, or over those the views' masks keep ([`mask`]); optional jitter and random
//! backgrounds), [`Dataset::view_rays`] for evaluation.
//! Forward-facing scenes give their rays in NDC ([`Dataset::ndc`], [`Dataset::warp`]).
//! Camera paths to render along are read and written in nerfstudio's format ([`camera_path`]),
//! and read in instant-ngp's ([`ngp_path`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nerf_rays::glam::{Mat3, Vec3};
use nerf_rays::lens::COEFFICIENT_NAMES;
use nerf_rays::{Aabb, Camera, Intrinsics, Ndc, PixelConvention, Ray};

pub mod camera_path;
pub mod colmap;
pub mod depth;
pub mod equirect;
pub use colmap::is_colmap;
pub use camera_path::{camera_path_json, equirect_intrinsics, load_camera_path, read_camera_path, CameraPath, CameraPathFile, PathCrop};
pub mod llff;
pub use llff::{is_llff, load_llff};
pub mod mask;
pub use mask::PixelMasks;
pub mod ngp;
pub mod ngp_path;
pub use ngp_path::{NgpCameraPath, NgpSpace};
pub mod pixels;
pub use ngp::{CenterMethod, Distortion, Focal, Lens, LensModel, NerfstudioNormalization, NerfstudioOptions, NgpBox, OrientationMethod};
pub use pixels::Pixels;
use rand::Rng as _;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::Value;

/// Errors of dataset loading and writing. Every message starts with the file it concerns.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// The split's `transforms_<split>.json` does not exist.
    #[error("{}: transforms file not found", .path.display())]
    MissingTransforms {
        /// The missing transforms file.
        path: PathBuf,
    },
    /// A file could not be read, created or written.
    #[error("{}: {source}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The transforms file is not valid JSON (the message gives line and column).
    #[error("{}: malformed JSON: {source}", .path.display())]
    Json {
        /// The transforms file.
        path: PathBuf,
        /// The parser error (with line and column).
        #[source]
        source: serde_json::Error,
    },
    /// A required key is absent, e.g. `camera_angle_x` or `frames[3].file_path`.
    #[error("{}: missing key `{key}`", .path.display())]
    MissingKey {
        /// The transforms file.
        path: PathBuf,
        /// The key, with its position (`frames[i].key`) for per-frame keys.
        key: String,
    },
    /// A key has a value of the wrong type or out of range.
    #[error("{}: invalid `{key}`: {reason}", .path.display())]
    InvalidValue {
        /// The transforms file.
        path: PathBuf,
        /// The key.
        key: String,
        /// What is wrong with it.
        reason: String,
    },
    /// A frame's image file does not exist.
    #[error("{}: image file of frame {frame} not found", .path.display())]
    MissingImage {
        /// The expected image path.
        path: PathBuf,
        /// Index of the frame in the transforms file.
        frame: usize,
    },
    /// An image file could not be decoded.
    #[error("{}: cannot decode image: {source}", .path.display())]
    Decode {
        /// The image file.
        path: PathBuf,
        /// The decoder error.
        #[source]
        source: image::ImageError,
    },
    /// An image could not be encoded or written.
    #[error("{}: cannot write image: {source}", .path.display())]
    Encode {
        /// The image file.
        path: PathBuf,
        /// The encoder error.
        #[source]
        source: image::ImageError,
    },
    /// An image's size differs from the first image's.
    #[error("{}: image is {width}x{height}, but the first image {} is {first_width}x{first_height}", .path.display(), .first.display())]
    SizeMismatch {
        /// The offending image.
        path: PathBuf,
        /// Its width.
        width: u32,
        /// Its height.
        height: u32,
        /// The first image of the split.
        first: PathBuf,
        /// The first image's width.
        first_width: u32,
        /// The first image's height.
        first_height: u32,
    },
    /// A frame's `transform_matrix` holds a value that is not finite (as `f32`).
    #[error("{}: frame {frame}: non-finite value in transform_matrix", .path.display())]
    NonFinitePose {
        /// The transforms file.
        path: PathBuf,
        /// Index of the frame in the transforms file.
        frame: usize,
    },
    /// A frame's pose cannot place a camera: its rotation block is degenerate
    /// ([`nerf_rays::RayError::DegeneratePose`]).
    #[error("{}: frame {frame}: {source}", .path.display())]
    BadPose {
        /// The transforms (or poses) file.
        path: PathBuf,
        /// Index of the frame in that file.
        frame: usize,
        /// What is wrong with the pose.
        #[source]
        source: nerf_rays::RayError,
    },
    /// A frame's `transform_matrix` is not a 4×4 or 3×4 array of numbers.
    #[error("{}: frame {frame}: transform_matrix must be a 4x4 or 3x4 array of numbers, got {shape}", .path.display())]
    BadMatrix {
        /// The transforms file.
        path: PathBuf,
        /// Index of the frame in the transforms file.
        frame: usize,
        /// What was found instead.
        shape: String,
    },
    /// The split has no frames, or the view selection leaves none.
    #[error("{}: empty split: {reason}", .path.display())]
    EmptySplit {
        /// The transforms file.
        path: PathBuf,
        /// Why it is empty.
        reason: String,
    },
    /// The view selection is invalid (`every:0`).
    #[error("{}: invalid view selection: {reason}", .path.display())]
    BadSelection {
        /// The transforms file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The downscale factor is 0 or does not divide the image size.
    #[error("{}: bad downscale factor {k}: {reason}", .path.display())]
    BadDownscale {
        /// The transforms file (factor 0) or the image whose size it does not divide.
        path: PathBuf,
        /// The factor.
        k: u32,
        /// What is wrong.
        reason: String,
    },
    /// A frame's training mask ([`mask`]) is missing or does not fit its image.
    #[error("{}: mask of frame {frame}: {reason}", .path.display())]
    BadMask {
        /// The mask image.
        path: PathBuf,
        /// Index of the frame in `frames`.
        frame: usize,
        /// What is wrong.
        reason: String,
    },
    /// A frame's depth map ([`depth`]) is missing, not an integer depth image, or does not fit
    /// its photo.
    #[error("{}: depth map of frame {frame}: {reason}", .path.display())]
    BadDepth {
        /// The depth image.
        path: PathBuf,
        /// Index of the frame in `frames`.
        frame: usize,
        /// What is wrong.
        reason: String,
    },
    /// A COLMAP model file ([`colmap`]) is truncated, malformed or names something unsupported.
    #[error("{}: COLMAP model: {reason}", .path.display())]
    Colmap {
        /// The model file (`cameras.bin`, `images.txt`, …) or folder.
        path: PathBuf,
        /// What is wrong, with the camera or image it concerns.
        reason: String,
    },
}

/// Background colour that transparent pixels are composited onto.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Background {
    /// White (1, 1, 1): the NeRF papers' evaluation convention.
    #[default]
    White,
    /// Black (0, 0, 0).
    Black,
    /// A uniform random colour per ray (instant-ngp training). Where a fixed colour is needed
    /// (evaluation: [`Dataset::view_rays`], [`Dataset::view_rgb`]) it is treated as white.
    Random,
}

impl Background {
    /// The fixed colour of this background (`Random` → white).
    pub fn fixed_rgb(self) -> [f32; 3] {
        match self {
            Background::Black => [0.0; 3],
            Background::White | Background::Random => [1.0; 3],
        }
    }
}

/// A dataset split.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    /// Training views.
    Train,
    /// Validation views.
    Val,
    /// Test views.
    Test,
}

impl Split {
    /// `"train"`, `"val"` or `"test"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }

    /// The split's transforms file name, `transforms_<split>.json`.
    pub fn transforms_file(self) -> String {
        format!("transforms_{}.json", self.as_str())
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Split {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "train" => Ok(Split::Train),
            "val" => Ok(Split::Val),
            "test" => Ok(Split::Test),
            _ => Err(format!("unknown split `{s}` (expected train, val or test)")),
        }
    }
}

/// Which views of a split to use: all, every k-th (k ≥ 1, starting at view 0), the first n, or
/// n spread evenly over the split. Serialised as its string form (`"all"`, `"every:8"`,
/// `"first:5"`, `"spread:4"`), as on the command line.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum ViewSelection {
    /// Every view.
    All,
    /// Views 0, k, 2k, … (k ≥ 1).
    Every(usize),
    /// Views 0 … n−1 (fewer if the split has fewer).
    First(usize),
    /// `n` views spread evenly over the split (n ≥ 1): of `N` views, views `⌊i·N/n⌋` for
    /// `i = 0 … n−1` (every view if the split has at most `n`).
    Spread(usize),
}

impl ViewSelection {
    /// The selected indices among `n` views; `Err` for `Every(0)` and `Spread(0)`.
    pub fn indices(&self, n: usize) -> Result<Vec<usize>, String> {
        match *self {
            ViewSelection::All => Ok((0..n).collect()),
            ViewSelection::Every(0) => Err("every:0 (k must be at least 1)".into()),
            ViewSelection::Every(k) => Ok((0..n).step_by(k).collect()),
            ViewSelection::First(m) => Ok((0..n.min(m)).collect()),
            ViewSelection::Spread(0) => Err("spread:0 (n must be at least 1)".into()),
            ViewSelection::Spread(m) if m >= n => Ok((0..n).collect()),
            ViewSelection::Spread(m) => Ok((0..m).map(|i| i * n / m).collect()),
        }
    }
}

impl std::fmt::Display for ViewSelection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ViewSelection::All => write!(f, "all"),
            ViewSelection::Every(k) => write!(f, "every:{k}"),
            ViewSelection::First(n) => write!(f, "first:{n}"),
            ViewSelection::Spread(n) => write!(f, "spread:{n}"),
        }
    }
}

impl std::str::FromStr for ViewSelection {
    type Err = String;
    /// Parses `"all"`, `"every:K"` (K ≥ 1), `"first:N"` or `"spread:N"` (N ≥ 1).
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || {
            format!("invalid view selection `{s}` (expected `all`, `every:K` with K >= 1, `first:N`, or `spread:N` with N >= 1)")
        };
        let t = s.trim();
        if t == "all" {
            return Ok(ViewSelection::All);
        }
        let (kind, num) = t.split_once(':').ok_or_else(bad)?;
        let num: usize = num.trim().parse().map_err(|_| bad())?;
        match kind.trim() {
            "every" if num >= 1 => Ok(ViewSelection::Every(num)),
            "first" => Ok(ViewSelection::First(num)),
            "spread" if num >= 1 => Ok(ViewSelection::Spread(num)),
            _ => Err(bad()),
        }
    }
}

impl TryFrom<String> for ViewSelection {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

impl From<ViewSelection> for String {
    fn from(v: ViewSelection) -> String {
        v.to_string()
    }
}

/// How a scene without split files (one `transforms.json`, a COLMAP folder, an LLFF scene)
/// holds views out for testing: nerfstudio's dataparser `eval_mode`. Serialised as its string
/// form (`"interval:8"`, `"fraction:0.9"`, `"all"`), as on the command line. The frames are
/// taken in the order of their images' names (nerfstudio sorts them so), and the split is:
/// - `interval:K` (K ≥ 2; nerfstudio's `interval` with `eval_interval = K`): views `0, K, 2K, …`
///   test, the others train;
/// - `fraction:F` (0 < F < 1; nerfstudio's default `fraction` with `train_split_fraction = F`):
///   `⌈N·F⌉` training views evenly spaced from the first to the last
///   (`linspace(0, N − 1, ⌈N·F⌉)` truncated), the others test;
/// - `all` (nerfstudio's `all`): every view both trains and tests;
/// - `filename` (nerfstudio's `filename`): views whose image's file name contains `train` train,
///   the others test, and each of those must contain `eval` (an error names one that does not).
///
/// Without one ([`LoadOptions::holdout`] `None`) a scene keeps every 8th view in the file's order
/// for testing, as nerf-pytorch and instant-ngp's scripts do. A file's own
/// `train_filenames` / `test_filenames` lists win over either.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum Holdout {
    /// Every K-th view tests (K ≥ 2).
    Interval(usize),
    /// This fraction of the views trains (0 < F < 1).
    Fraction(f64),
    /// Every view trains and tests.
    All,
    /// By the images' file names: `train` in a name trains, `eval` tests.
    Filename,
}

impl Holdout {
    /// The indices of `split` among the views whose images' file names are `names` (in the order
    /// the split is taken in: by name). Errors, for [`Holdout::Filename`], with the first name
    /// that holds neither `train` nor `eval`.
    pub fn split(&self, names: &[impl AsRef<str>], split: Split) -> Result<Vec<usize>, String> {
        let n = names.len();
        let train = split == Split::Train;
        Ok(match *self {
            Holdout::Interval(k) => (0..n).filter(|i| (i % k == 0) != train).collect(),
            Holdout::Fraction(f) => {
                let n_train = ((n as f64) * f).ceil() as usize;
                // numpy's linspace(0, n − 1, n_train, dtype=int): i·step with step = (n − 1)/(m − 1),
                // the last exactly n − 1, the floats truncated.
                let chosen: Vec<usize> = match n_train {
                    0 => vec![],
                    1 => vec![0],
                    m => {
                        let step = (n - 1) as f64 / (m - 1) as f64;
                        (0..m).map(|i| if i + 1 == m { n - 1 } else { (i as f64 * step) as usize }).collect()
                    }
                };
                (0..n).filter(|i| chosen.contains(i) == train).collect()
            }
            Holdout::All => (0..n).collect(),
            Holdout::Filename => {
                // nerfstudio's get_train_eval_split_filename: `train` first, then `eval`.
                let names: Vec<&str> = names.iter().map(AsRef::as_ref).collect();
                if let Some(n) = names.iter().find(|n| !n.contains("train") && !n.contains("eval")) {
                    return Err(format!("`{n}` holds neither `train` nor `eval` in its name: the filename holdout needs one in every image's"));
                }
                (0..n).filter(|&i| names[i].contains("train") == train).collect()
            }
        })
    }
}

impl std::fmt::Display for Holdout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Holdout::Interval(k) => write!(f, "interval:{k}"),
            Holdout::Fraction(x) => write!(f, "fraction:{x}"),
            Holdout::All => write!(f, "all"),
            Holdout::Filename => write!(f, "filename"),
        }
    }
}

impl std::str::FromStr for Holdout {
    type Err = String;
    /// Parses `"interval:K"` (K ≥ 2), `"fraction:F"` (0 < F < 1), `"all"` or `"filename"`.
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("invalid holdout `{s}` (expected `interval:K` with K >= 2, `fraction:F` with 0 < F < 1, `all` or `filename`)");
        let t = s.trim();
        match t {
            "all" => return Ok(Holdout::All),
            "filename" => return Ok(Holdout::Filename),
            _ => {}
        }
        let (kind, num) = t.split_once(':').ok_or_else(bad)?;
        match kind.trim() {
            "interval" => num.trim().parse::<usize>().ok().filter(|k| *k >= 2).map(Holdout::Interval).ok_or_else(bad),
            "fraction" => num.trim().parse::<f64>().ok().filter(|f| *f > 0.0 && *f < 1.0).map(Holdout::Fraction).ok_or_else(bad),
            _ => Err(bad()),
        }
    }
}

impl TryFrom<String> for Holdout {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

impl From<Holdout> for String {
    fn from(v: Holdout) -> String {
        v.to_string()
    }
}

/// The file name of `path` (lossy), for name-based rules.
fn file_name_of(path: &Path) -> String {
    path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned())
}

/// Options of [`load_blender`].
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LoadOptions {
    /// Integer downscale factor (≥ 1; must divide the image size): k×k box average. A nerfstudio
    /// capture or COLMAP folder whose selected frames all have `images_<k>/` copies reads those
    /// instead (nerfstudio's downscaled copies; see docs/formats.md).
    pub downscale: u32,
    /// Which views of the split to load.
    pub views: ViewSelection,
    /// Forward-facing (LLFF) scenes in NeRF's normalised device coordinates, as the paper trains
    /// them ([`Dataset::ndc`]); `false` gives Euclidean rays (nerf-pytorch's `--no_ndc`). Blender
    /// scenes ignore it.
    pub ndc: bool,
    /// Read only each image's size from its header, and leave every view's entry of
    /// [`Dataset::images`] empty: for what needs the cameras alone (rendering a trained run,
    /// exporting its mesh), which then neither decodes nor holds the photos (a nerfstudio capture
    /// of a few hundred 4K photos is several GB even in bytes). Sizes are checked as in a full load
    /// (the same errors, naming the file); lens undistortion, which only resamples pixels, is
    /// skipped. Methods that read pixels panic on such a dataset
    /// ([`Dataset::has_images`] says which it is).
    pub cameras_only: bool,
    /// COLMAP folders ([`load_colmap`]): sparse depth maps from the reconstruction's 3-D points
    /// (`points3D`, [`colmap::read_points`]) for depth supervision, DS-NeRF's idea and
    /// nerfstudio's `create_sfm_depth`: each view gets the distance to the points it observes
    /// (mean reprojection error ≤ 2.5 px, seen by at least two images), at the pixel each
    /// projects to ([`Dataset::depths`]). Ignored where a frame has a depth map of its own, in
    /// other formats, and with `cameras_only`.
    #[serde(default)]
    pub sfm_depth: bool,
    /// Photos taken through a lens with distortion (`k1` …, a fisheye) are resampled to the
    /// pinhole camera of the same intrinsics when they load ([`ngp::undistort_rgba`]), the
    /// pixels that camera sees past the photo left out of training ([`ngp::pixels_seen`]), and
    /// the cameras are pinholes. `false` (the default, as nerfstudio and instant-ngp): the photos
    /// are kept as taken and each camera carries its lens ([`nerf_rays::Camera::distortion`]),
    /// so that rays go through the photo's own pixels and a fisheye keeps its whole view.
    #[serde(default)]
    pub undistort: bool,
    /// instant-ngp's `aabb_scale` in place of the transforms file's (or of none): the side of the
    /// training cube in instant-ngp units for an instant-ngp or Blender file, the half-side of
    /// nerfstudio's box about its normalised cameras for a nerfstudio capture or a COLMAP folder;
    /// the poses are read as they would be without it. `None` (the default): the file's.
    /// LLFF scenes refuse it.
    #[serde(default)]
    pub aabb_scale: Option<f32>,
    /// How a nerfstudio capture's or a COLMAP folder's poses are turned, centred and scaled
    /// (nerfstudio's dataparser options; the defaults are its). Other formats ignore it.
    #[serde(default)]
    pub nerfstudio: NerfstudioOptions,
    /// How a scene without split files holds views out for testing ([`Holdout`]); `None` (the
    /// default): every 8th view in the file's order.
    #[serde(default)]
    pub holdout: Option<Holdout>,
    /// Which loader reads the folder ([`SceneFormat`]; [`load_scene`]); the default tells by
    /// what the folder holds.
    #[serde(default)]
    pub format: SceneFormat,
}

/// Which of the loaders reads a scene folder ([`load_scene`]), as nerfstudio's dataparser
/// names one. A folder may hold several descriptions of one capture: mip-NeRF 360's scenes hold
/// LLFF's `poses_bounds.npy` beside the COLMAP model it was made from, and `ns-process-data`
/// writes a `transforms.json` beside its COLMAP model. Serialised as `auto`, `transforms`,
/// `llff` or `colmap`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SceneFormat {
    /// By what the folder holds: LLFF where it holds `poses_bounds.npy`, COLMAP where it holds a
    /// sparse model and no transforms file, else the transforms files.
    #[default]
    Auto,
    /// Transforms files: Blender's `transforms_<split>.json`, instant-ngp's and nerfstudio's
    /// `transforms.json` ([`load_blender`]).
    Transforms,
    /// LLFF's `poses_bounds.npy` ([`load_llff`]).
    Llff,
    /// COLMAP's sparse model, in `sparse/0/` or `colmap/sparse/0/` ([`load_colmap`]), whatever
    /// else the folder holds.
    Colmap,
}

impl Default for LoadOptions {
    /// Full resolution, all views, NDC for forward-facing scenes, no depth from the SfM points.
    fn default() -> Self {
        Self {
            downscale: 1,
            views: ViewSelection::All,
            ndc: true,
            cameras_only: false,
            sfm_depth: false,
            undistort: false,
            aabb_scale: None,
            nerfstudio: NerfstudioOptions::default(),
            holdout: None,
            format: SceneFormat::Auto,
        }
    }
}

/// One split of a scene in memory.
#[derive(Clone)]
pub struct Dataset {
    /// The scene folder.
    pub root: PathBuf,
    /// Which split this is.
    pub split: Split,
    /// Image width (after downscaling). Views of different sizes (a capture with several
    /// cameras, portrait and landscape photos) are held on one canvas of the largest width and
    /// height: each view's own size is its camera's ([`Dataset::view_size`]), its pixels sit in
    /// the canvas's top-left corner, and the rest of its canvas is masked out of training
    /// ([`Dataset::masks`]).
    pub width: u32,
    /// Image height (after downscaling; the canvas's, see [`Dataset::width`]).
    pub height: u32,
    /// One camera per view.
    pub cameras: Vec<Camera>,
    /// Per view: RGBA, row-major at the canvas's stride (`4·W·H` values; past a smaller view's
    /// own width and height transparent black), straight (not premultiplied) alpha, values in
    /// `[0, 1]`, held in 8 bits a channel where they are exact 8-bit values, else 16
    /// ([`Pixels`]: a photo from an 8-bit file takes 4 bytes a pixel).
    pub images: Vec<Pixels>,
    /// Per view: the image file it was loaded from (a panorama's six faces, [`equirect`], share
    /// its file; [`Dataset::view_names`] tells them apart).
    pub file_paths: Vec<PathBuf>,
    /// The pixels training may draw, one mask per view ([`mask`]: nerfstudio's `mask_path`,
    /// instant-ngp's dynamic masks, and the pixels a lens's photo did not see,
    /// [`ngp::pixels_seen`]); `None`: every pixel. When set it holds one entry per view: a
    /// dataset made from a selection of another's views takes [`PixelMasks::select`] of its
    /// masks.
    pub masks: Option<PixelMasks>,
    /// Per view, per pixel (row-major, `W·H`): the measured distance along the pixel's unit ray
    /// from the camera centre to the surface, in the scene's units, 0 where there is none
    /// ([`depth`]: nerfstudio's `depth_file_path`, instant-ngp's `depth_path`; a view without a
    /// depth map is all 0). `None`: the scene has no depth maps. Training on them is
    /// `depth_loss`.
    pub depths: Option<Vec<Vec<f32>>>,
    /// Near bound of the ray segment (Blender: 2).
    pub near: f32,
    /// Far bound of the ray segment (Blender: 6).
    pub far: f32,
    /// Scene bounds (Blender scenes: the cube of half-extent 1.5).
    pub aabb: Aabb,
    /// The NDC warp of a forward-facing scene: when set, every ray this dataset gives out
    /// ([`Dataset::sample_rays`], [`Dataset::view_rays`], [`Dataset::warp_rays`]) is the unit NDC
    /// ray of the camera ray, `near`/`far`/`aabb` are in NDC space, and a ray's segment is its
    /// part inside `aabb` (`z' ∈ [−1, 1]`: near plane to infinite depth).
    pub ndc: Option<Ndc>,
    /// LLFF: the nearest and farthest depth bounds of `poses_bounds.npy`, in the scene's
    /// (scaled) world units (novel-view paths are focused from them); `None` for Blender scenes.
    pub depth_bounds: Option<[f32; 2]>,
    /// instant-ngp's placement of the scene in its unit cube ([`ngp`]): set for scenes stored as
    /// one `transforms.json` or whose transforms file has `aabb_scale`, `scale` or `offset`; then
    /// `aabb` is its training cube and `near`/`far` come from it. `None` for NeRF's Blender
    /// scenes and LLFF.
    pub ngp: Option<NgpBox>,
    /// nerfstudio's normalisation, applied to the poses of a nerfstudio capture ([`ngp`]):
    /// what maps the file's frame into the one of [`Dataset::cameras`]. `None` for other scenes.
    pub normalization: Option<NerfstudioNormalization>,
}

impl std::fmt::Debug for Dataset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dataset")
            .field("root", &self.root)
            .field("split", &self.split)
            .field("width", &self.width)
            .field("height", &self.height)
            .field("n_views", &self.cameras.len())
            .field("near", &self.near)
            .field("far", &self.far)
            .field("aabb", &self.aabb)
            .field("ndc", &self.ndc)
            .field("ngp", &self.ngp)
            .finish_non_exhaustive()
    }
}

/// A batch of rays with their targets. All arrays are flat, `3·n` long unless stated.
#[derive(Default, Clone, Debug)]
pub struct RayBatch {
    /// Ray origins.
    pub origins: Vec<f32>,
    /// Unit ray directions.
    pub dirs: Vec<f32>,
    /// Target RGB composited onto the ray's background.
    pub target: Vec<f32>,
    /// Background RGB of each ray (what the renderer must composite onto).
    pub background: Vec<f32>,
    /// Per ray (`n` long): index of the view the ray comes from.
    pub view_ids: Vec<u32>,
    /// Per ray (`n` long): pixel index `row·W + col` within its view.
    pub pixel_ids: Vec<u32>,
}

impl RayBatch {
    /// Number of rays.
    pub fn len(&self) -> usize {
        self.origins.len() / 3
    }

    /// Whether the batch holds no rays.
    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }

    /// Removes all rays, keeping the allocations.
    pub fn clear(&mut self) {
        self.origins.clear();
        self.dirs.clear();
        self.target.clear();
        self.background.clear();
        self.view_ids.clear();
        self.pixel_ids.clear();
    }

    /// Resizes every array for `n` rays (contents unspecified), reusing allocations.
    fn resize(&mut self, n: usize) {
        self.origins.resize(3 * n, 0.0);
        self.dirs.resize(3 * n, 0.0);
        self.target.resize(3 * n, 0.0);
        self.background.resize(3 * n, 0.0);
        self.view_ids.resize(n, 0);
        self.pixel_ids.resize(n, 0);
    }
}

/// Rays per parallel work item of [`Dataset::sample_rays`]; each chunk draws from its own
/// generator (`nerf_core::rng(seed, chunk)`), so results do not depend on the thread count.
pub const SAMPLE_CHUNK: usize = 4096;

#[inline]
fn composite(px: &[f32], bg: [f32; 3], out: &mut [f32]) {
    let a = px[3];
    for c in 0..3 {
        out[c] = px[c] * a + (1.0 - a) * bg[c];
    }
}

impl Dataset {
    /// Number of views.
    pub fn n_views(&self) -> usize {
        self.cameras.len()
    }

    /// What is wrong with [`Dataset::depths`] when its maps are not one per view of `W·H`
    /// values (`None`: they fit, or there are none).
    pub fn depths_mismatch(&self) -> Option<String> {
        let d = self.depths.as_ref()?;
        let n = (self.width * self.height) as usize;
        (d.len() != self.n_views() || d.iter().any(|v| v.len() != n))
            .then(|| format!("depth maps of {} views for {} views of {}x{}", d.len(), self.n_views(), self.width, self.height))
    }

    /// View `i`'s own width and height (its camera's): [`Dataset::width`] × [`Dataset::height`]
    /// unless the views differ in size.
    pub fn view_size(&self, i: usize) -> (u32, u32) {
        let k = &self.cameras[i].intrinsics;
        (k.width, k.height)
    }

    /// The dataset of views `views` of this one, in that order: their cameras, pixels, file
    /// paths, masks and depth maps, the rest (size, bounds, scene) the same.
    ///
    /// # Panics
    /// If an index is not below [`Dataset::n_views`].
    pub fn select_views(&self, views: &[usize]) -> Dataset {
        fn pick<T: Clone>(v: &[T], views: &[usize]) -> Vec<T> {
            if v.is_empty() { Vec::new() } else { views.iter().map(|&i| v[i].clone()).collect() }
        }
        Dataset {
            cameras: views.iter().map(|&i| self.cameras[i]).collect(),
            images: pick(&self.images, views),
            file_paths: if self.file_paths.is_empty() { Vec::new() } else { views.iter().map(|&i| self.file_paths[i].clone()).collect() },
            masks: self.masks.as_ref().map(|m| m.select(views)),
            depths: self.depths.as_ref().map(|d| pick(d, views)),
            ..self.clone_without_views()
        }
    }

    /// This dataset without its per-view contents (cameras, pixels, paths, masks, depth maps).
    fn clone_without_views(&self) -> Dataset {
        Dataset {
            root: self.root.clone(),
            split: self.split,
            width: self.width,
            height: self.height,
            cameras: Vec::new(),
            images: Vec::new(),
            file_paths: Vec::new(),
            masks: None,
            depths: None,
            near: self.near,
            far: self.far,
            aabb: self.aabb,
            ndc: self.ndc,
            depth_bounds: self.depth_bounds,
            ngp: self.ngp,
            normalization: self.normalization,
        }
    }

    /// A name per view for files written from it (evaluation renders): its image's file stem
    /// (`view_<i>` without a path), and where several views share a stem (a panorama's faces,
    /// photos of one name in two folders) the stem and the view's place among them,
    /// `<stem>_<k>` (a panorama's faces: `k` in [`equirect::FACES`] order).
    pub fn view_names(&self) -> Vec<String> {
        let stems: Vec<String> = (0..self.n_views())
            .map(|i| self.file_paths.get(i).and_then(|p| p.file_stem()).map_or_else(|| format!("view_{i:03}"), |s| s.to_string_lossy().into_owned()))
            .collect();
        let mut count: std::collections::HashMap<&str, usize> = std::collections::HashMap::new();
        for s in &stems {
            *count.entry(s).or_insert(0) += 1;
        }
        let mut seen: std::collections::HashMap<&str, usize> = std::collections::HashMap::new();
        stems
            .iter()
            .map(|s| {
                if count[s.as_str()] == 1 {
                    return s.clone();
                }
                let k = seen.entry(s).or_insert(0);
                *k += 1;
                format!("{s}_{}", *k - 1)
            })
            .collect()
    }

    /// The views' sizes for people: `WxH`, or the distinct sizes in order of first appearance
    /// (`300x400 and 400x300`; the first three and a count past them).
    pub fn size_label(&self) -> String {
        let mut sizes: Vec<(u32, u32)> = Vec::new();
        for i in 0..self.n_views() {
            if !sizes.contains(&self.view_size(i)) {
                sizes.push(self.view_size(i));
            }
        }
        let names: Vec<String> = sizes.iter().take(3).map(|(w, h)| format!("{w}x{h}")).collect();
        match sizes.len() {
            0 => format!("{}x{}", self.width, self.height),
            1 => names[0].clone(),
            2 => names.join(" and "),
            3 => format!("{}, {} and {}", names[0], names[1], names[2]),
            n => format!("{} and {} more sizes", names.join(", "), n - 3),
        }
    }

    /// The pixels of all views at their own sizes ([`Dataset::view_size`]).
    pub fn n_view_pixels(&self) -> u64 {
        (0..self.n_views()).map(|i| self.view_size(i)).map(|(w, h)| u64::from(w) * u64::from(h)).sum()
    }

    /// The part of a per-pixel canvas array of view `i` (`per_pixel` values per pixel, rows at
    /// the canvas's stride, e.g. [`Dataset::images`] with 4 or [`Dataset::depths`] with 1) that
    /// covers the view's own pixels ([`Dataset::view_size`]), row-major at its own width;
    /// borrowed when the view fills the canvas.
    ///
    /// # Panics
    /// If `values` is not `per_pixel·W·H` long.
    pub fn view_crop<'a, T: Clone>(&self, i: usize, per_pixel: usize, values: &'a [T]) -> std::borrow::Cow<'a, [T]> {
        let (cw, ch) = (self.width as usize, self.height as usize);
        assert_eq!(values.len(), per_pixel * cw * ch, "view_crop: not {per_pixel} values per pixel of a {cw}x{ch} canvas");
        let (w, h) = self.view_size(i);
        let (w, h) = (w as usize, h as usize);
        if w == cw {
            return std::borrow::Cow::Borrowed(&values[..per_pixel * w * h]);
        }
        std::borrow::Cow::Owned(values.chunks_exact(per_pixel * cw).take(h).flat_map(|r| r[..per_pixel * w].iter().cloned()).collect())
    }

    /// Whether the views' pixels were loaded (false after [`LoadOptions::cameras_only`]).
    pub fn has_images(&self) -> bool {
        self.images.first().is_some_and(|img| !img.is_empty())
    }

    /// Panics with what was asked of a dataset loaded without its pixels (a caller's bug).
    fn expect_pixels(&self, what: &str) {
        assert!(self.has_images(), "{what} reads pixels, but {} was loaded with cameras_only", self.root.display());
    }

    /// Multiplies view `v`'s colours by `gains[v]` (per channel; alpha and the cameras kept): a
    /// change of exposure and white balance between photographs, for experiments with
    /// per-view colour correction. Values past 1 are clipped, as a photo's would be.
    ///
    /// # Panics
    /// Unless there is one gain triple per view.
    pub fn scale_colors(&mut self, gains: &[[f32; 3]]) {
        self.expect_pixels("scale_colors");
        assert_eq!(gains.len(), self.n_views(), "one gain triple per view");
        self.images.par_iter_mut().zip(gains).for_each(|(img, g)| {
            let mut px = img.to_f32();
            for p in px.chunks_exact_mut(4) {
                for c in 0..3 {
                    p[c] *= g[c];
                }
            }
            *img = Pixels::from_f32(&px);
        });
    }

    /// Moves each view's camera by `noise[v] = [τ (3), ω (3)]` ([`pose_noise`]): the centre by
    /// `τ`, the orientation by the rotation `exp([ω]×)` in world axes (`rotation ← R(ω) ·
    /// rotation`), so that the view's rays become `o + τ`, `R(ω) d` — what the correction
    /// `[−τ, −ω]` of camera pose refinement (`nerf_rays::pose`) undoes exactly.
    ///
    /// # Panics
    /// Unless there is one entry per view.
    pub fn perturb_poses(&mut self, noise: &[[f32; 6]]) {
        assert_eq!(noise.len(), self.n_views(), "one pose change per view");
        for (cam, p) in self.cameras.iter_mut().zip(noise) {
            *cam = nerf_rays::pose::move_camera(cam, p);
        }
    }

    /// Whether samplers should keep each ray's `[near, far]` inside [`Dataset::aabb`]: NDC scenes
    /// (the box gives every ray its NDC segment) and instant-ngp scenes (trained inside their cube).
    pub fn clips_to_aabb(&self) -> bool {
        self.ndc.is_some() || self.ngp.is_some()
    }

    /// A camera ray in this dataset's ray space: unchanged, or its NDC ray ([`Dataset::ndc`]; a
    /// ray that cannot be warped becomes [`Ndc::MISS`], which renders as background).
    #[inline]
    pub fn warp(&self, ray: Ray) -> Ray {
        match &self.ndc {
            Some(n) => n.ray_or_miss(ray.origin, ray.dir),
            None => ray,
        }
    }

    /// Puts camera rays (flat `origins` / `dirs`, e.g. from [`Camera::rays_into`] for a novel
    /// view) into this dataset's ray space in place; a no-op without [`Dataset::ndc`].
    pub fn warp_rays(&self, origins: &mut [f32], dirs: &mut [f32]) {
        if self.ndc.is_none() {
            return;
        }
        origins.par_chunks_mut(3).zip(dirs.par_chunks_mut(3)).for_each(|(o, d)| {
            let r = self.warp(Ray { origin: Vec3::from_slice(o), dir: Vec3::from_slice(d) });
            o.copy_from_slice(&r.origin.to_array());
            d.copy_from_slice(&r.dir.to_array());
        });
    }

    /// Fills `out` (reusing its allocations) with `n` rays drawn uniformly over all pixels of all
    /// views (random view, random pixel), or over the pixels the views' masks keep when
    /// [`Dataset::masks`] is set (random kept pixel: [`PixelMasks::pick`]); optional sub-pixel
    /// jitter (`u, v` uniform over the
    /// pixel's square instead of its position under `conv`; with [`PixelConvention::Integer`]
    /// the square of pixel `i` is `[i − ½, i + ½)`); target = rgb·a + (1−a)·bg with bg from
    /// `background` (Random: uniform per ray). Draws one `u64` from `rng` and derives a
    /// generator per chunk of [`SAMPLE_CHUNK`] rays from it, so the batch is a deterministic
    /// function of `rng`'s state; runs in parallel over chunks.
    ///
    /// # Panics
    /// If the dataset has no views or was loaded without its pixels
    /// ([`LoadOptions::cameras_only`]), or if its masks are not one per view or keep no pixel.
    pub fn sample_rays(
        &self,
        n: usize,
        background: Background,
        conv: PixelConvention,
        jitter: bool,
        rng: &mut nerf_core::Rng,
        out: &mut RayBatch,
    ) {
        self.expect_pixels("sample_rays");
        self.draw_rays(n, background, conv, jitter, rng, out, true);
    }

    /// As [`Dataset::sample_rays`] without the photos: the same rays, backgrounds, view and pixel
    /// ids for the same `rng` state, with every `target` NaN (no pixel is read). Works on a
    /// dataset loaded with [`LoadOptions::cameras_only`] (e.g. to cast rays through a trained
    /// field from the training cameras).
    ///
    /// # Panics
    /// If the dataset has no views, or if its masks are not one per view or keep no pixel.
    pub fn sample_camera_rays(
        &self,
        n: usize,
        background: Background,
        conv: PixelConvention,
        jitter: bool,
        rng: &mut nerf_core::Rng,
        out: &mut RayBatch,
    ) {
        self.draw_rays(n, background, conv, jitter, rng, out, false);
    }

    /// The body of [`Dataset::sample_rays`] (`with_targets`) and [`Dataset::sample_camera_rays`].
    #[allow(clippy::too_many_arguments)]
    fn draw_rays(
        &self,
        n: usize,
        background: Background,
        conv: PixelConvention,
        jitter: bool,
        rng: &mut nerf_core::Rng,
        out: &mut RayBatch,
        with_targets: bool,
    ) {
        assert!(self.n_views() > 0, "sampling rays from a dataset without views");
        if let Some(m) = &self.masks {
            assert_eq!(m.n_views(), self.n_views(), "masks of {} views for a dataset of {}", m.n_views(), self.n_views());
            assert_eq!(m.n_pixels(), self.width * self.height, "masks of views of another size");
            assert!(m.total() > 0, "sampling rays where every pixel is masked out");
        }
        out.resize(n);
        let seed: u64 = rng.gen();
        let (w, h) = (self.width, self.height);
        let n_views = self.n_views() as u32;
        let off = conv.offset();
        let c3 = 3 * SAMPLE_CHUNK;
        (
            out.origins.par_chunks_mut(c3),
            out.dirs.par_chunks_mut(c3),
            out.target.par_chunks_mut(c3),
            out.background.par_chunks_mut(c3),
            out.view_ids.par_chunks_mut(SAMPLE_CHUNK),
            out.pixel_ids.par_chunks_mut(SAMPLE_CHUNK),
        )
            .into_par_iter()
            .enumerate()
            .for_each(|(chunk, (o, d, t, b, vi, pi))| {
                let mut r = nerf_core::rng(seed, chunk as u64);
                for k in 0..vi.len() {
                    let (view, col, row) = match &self.masks {
                        None => (r.gen_range(0..n_views), r.gen_range(0..w), r.gen_range(0..h)),
                        Some(m) => {
                            let (view, pix) = m.pick(r.gen_range(0..m.total()));
                            (view, pix % w, pix / w)
                        }
                    };
                    let (u, v) = if jitter {
                        (
                            col as f32 + off - 0.5 + r.gen::<f32>(),
                            row as f32 + off - 0.5 + r.gen::<f32>(),
                        )
                    } else {
                        (col as f32 + off, row as f32 + off)
                    };
                    let bg = match background {
                        Background::Random => [r.gen::<f32>(), r.gen::<f32>(), r.gen::<f32>()],
                        fixed => fixed.fixed_rgb(),
                    };
                    let cam = &self.cameras[view as usize];
                    let ray = self.warp(cam.ray_at(u, v));
                    let pix = row * w + col;
                    let s = 3 * k..3 * k + 3;
                    o[s.clone()].copy_from_slice(&ray.origin.to_array());
                    d[s.clone()].copy_from_slice(&ray.dir.to_array());
                    b[s.clone()].copy_from_slice(&bg);
                    if with_targets {
                        composite(&self.images[view as usize].rgba(pix as usize), bg, &mut t[s]);
                    } else {
                        t[s].fill(f32::NAN);
                    }
                    vi[k] = view;
                    pi[k] = pix;
                }
            });
    }

    /// Every pixel of view `i` (its own size, [`Dataset::view_size`]), row-major, composited on
    /// the given fixed background (White/Black; Random → treated as White). Fills `out` (reusing
    /// allocations; `pixel_ids` index the canvas, `row·W + col`); parallel over rows.
    ///
    /// # Panics
    /// If `i >= n_views()`, or if the dataset was loaded without its pixels.
    pub fn view_rays(
        &self,
        i: usize,
        background: Background,
        conv: PixelConvention,
        out: &mut RayBatch,
    ) {
        let o = conv.offset();
        self.view_rays_at(i, background, [o, o], out);
    }

    /// As [`view_rays`](Self::view_rays), each ray through the point `offset` of its pixel:
    /// pixel `(col, row)` → image coordinates `(col + offset[0], row + offset[1])` (one of
    /// [`PixelConvention::sample_offsets`] for supersampling).
    ///
    /// # Panics
    /// If `i >= n_views()`, or if the dataset was loaded without its pixels.
    pub fn view_rays_at(&self, i: usize, background: Background, offset: [f32; 2], out: &mut RayBatch) {
        assert!(i < self.n_views(), "view index {i} out of range");
        self.expect_pixels("view_rays");
        let (w, h) = self.view_size(i);
        let (w, h, cw) = (w as usize, h as usize, self.width as usize);
        out.resize(w * h);
        let bg = background.fixed_rgb();
        let cam = &self.cameras[i];
        let img = &self.images[i];
        (
            out.origins.par_chunks_mut(3 * w),
            out.dirs.par_chunks_mut(3 * w),
            out.target.par_chunks_mut(3 * w),
            out.background.par_chunks_mut(3 * w),
            out.view_ids.par_chunks_mut(w),
            out.pixel_ids.par_chunks_mut(w),
        )
            .into_par_iter()
            .enumerate()
            .for_each(|(row, (o, d, t, b, vi, pi))| {
                for col in 0..w {
                    let ray = self.warp(cam.ray_at(col as f32 + offset[0], row as f32 + offset[1]));
                    let pix = row * cw + col;
                    let s = 3 * col..3 * col + 3;
                    o[s.clone()].copy_from_slice(&ray.origin.to_array());
                    d[s.clone()].copy_from_slice(&ray.dir.to_array());
                    b[s.clone()].copy_from_slice(&bg);
                    composite(&img.rgba(pix), bg, &mut t[s]);
                    vi[col] = i as u32;
                    pi[col] = pix as u32;
                }
            });
    }

    /// The view's RGB image composited on `background` (Random → White), `3·w·h` long for its
    /// own size `(w, h)` ([`Dataset::view_size`]).
    ///
    /// # Panics
    /// If `i >= n_views()`, or if the dataset was loaded without its pixels.
    pub fn view_rgb(&self, i: usize, background: Background) -> Vec<f32> {
        self.expect_pixels("view_rgb");
        let bg = background.fixed_rgb();
        let px = self.images[i].to_f32();
        let img = self.view_crop(i, 4, &px);
        let mut out = vec![0.0f32; img.len() / 4 * 3];
        for (px, o) in img.chunks_exact(4).zip(out.chunks_exact_mut(3)) {
            composite(px, bg, o);
        }
        out
    }
}

// ---------------------------------------------------------------------------------------------
// Loading

#[derive(Clone)]
struct Frame {
    index: usize,
    image: PathBuf,
    /// A panorama's face ([`equirect::FACES`]): the frame is this face of its photo.
    face: Option<usize>,
    /// nerfstudio's `mask_path`, resolved as `file_path` is.
    mask: Option<PathBuf>,
    /// The depth map (`depth_file_path` or `depth_path`, resolved as `file_path` is) and world
    /// units per integer step of it ([`depth`]).
    depth: Option<(PathBuf, f64)>,
    c2w: Vec<[f32; 4]>,
    lens: ngp::Lens,
}

/// Where a frame's training mask comes from ([`mask`]).
#[derive(Clone, Copy)]
enum MaskSource<'a> {
    /// nerfstudio's `mask_path`: non-zero keeps a pixel.
    Keep(&'a Path),
    /// instant-ngp's `dynamic_mask_<name>.png` beside the photo: non-zero drops a pixel.
    Drop(&'a Path),
    /// No mask file (a frame without a dynamic mask among frames with one, or a scene whose
    /// only masks are its lenses'): every pixel kept.
    All,
}

/// instant-ngp's dynamic mask of the photo at `image`: `dynamic_mask_<file stem>.png` in its folder.
fn dynamic_mask_path(image: &Path) -> PathBuf {
    let stem = image.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    image.with_file_name(format!("dynamic_mask_{stem}.png"))
}

fn parse_matrix(path: &Path, frame: usize, v: &Value) -> Result<Vec<[f32; 4]>, DataError> {
    let bad = |shape: String| DataError::BadMatrix {
        path: path.to_path_buf(),
        frame,
        shape,
    };
    let rows = v
        .as_array()
        .ok_or_else(|| bad(format!("a non-array value {}", json_kind(v))))?;
    let mut m = Vec::with_capacity(rows.len());
    let mut shape = Vec::with_capacity(rows.len());
    let mut all_numbers = true;
    for r in rows {
        match r.as_array() {
            Some(r) => {
                shape.push(r.len());
                all_numbers &= r.iter().all(Value::is_number);
            }
            None => return Err(bad(format!("a row that is {}", json_kind(r)))),
        }
    }
    let desc = || {
        let cols: Vec<String> = shape.iter().map(|c| c.to_string()).collect();
        format!("{} rows of lengths [{}]", shape.len(), cols.join(", "))
    };
    if !(rows.len() == 3 || rows.len() == 4) || shape.iter().any(|&c| c != 4) {
        return Err(bad(desc()));
    }
    if !all_numbers {
        return Err(bad("a non-numeric entry".into()));
    }
    let mut finite = true;
    for r in rows {
        let r = r.as_array().unwrap();
        let row: [f32; 4] = std::array::from_fn(|c| r[c].as_f64().unwrap_or(f64::NAN) as f32);
        finite &= row.iter().all(|x| x.is_finite());
        m.push(row);
    }
    if !finite {
        return Err(DataError::NonFinitePose {
            path: path.to_path_buf(),
            frame,
        });
    }
    Ok(m)
}

impl DataError {
    /// The error for frame `frame` of `path` whose matrix [`Camera::from_c2w`] refused.
    pub(crate) fn pose(path: &Path, frame: usize, e: nerf_rays::RayError) -> Self {
        let path = path.to_path_buf();
        match e {
            nerf_rays::RayError::NonFinitePose => DataError::NonFinitePose { path, frame },
            source => DataError::BadPose { path, frame, source },
        }
    }
}

fn json_kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

fn image_path(root: &Path, file_path: &str) -> PathBuf {
    let rel = file_path.strip_prefix("./").unwrap_or(file_path);
    let mut p = root.join(rel);
    if p.extension().is_none() {
        p.set_extension("png");
    }
    p
}

/// The frames read from nerfstudio's downscaled copies of their files for `--downscale k`:
/// `images_<k>/<file name>` in the scene folder for each image, `masks_<k>/` for each mask and
/// `depths_<k>/` for each depth map, as `ns-process-data` writes them and nerfstudio's data parser
/// reads them, with the camera keys scaled ([`ngp::Lens::downscaled`]). `None` unless every
/// frame has all of its copies, and for a photo with an instant-ngp dynamic mask beside it
/// (which has no such copy).
fn downscaled_copies(root: &Path, frames: &[&Frame], k: u32) -> Option<Vec<Frame>> {
    if frames.iter().any(|f| f.mask.is_none() && dynamic_mask_path(&f.image).is_file()) {
        return None;
    }
    let copy = |dir: &str, p: &Path| -> Option<PathBuf> {
        let c = root.join(format!("{dir}_{k}")).join(p.file_name()?);
        c.is_file().then_some(c)
    };
    frames
        .iter()
        .map(|f| {
            let mut g = (*f).clone();
            g.image = copy("images", &f.image)?;
            if let Some(m) = &f.mask {
                g.mask = Some(copy("masks", m)?);
            }
            if let Some((d, scale)) = &f.depth {
                g.depth = Some((copy("depths", d)?, *scale));
            }
            g.lens = f.lens.downscaled(k);
            Some(g)
        })
        .collect()
}

/// A decoded image: width, height, straight RGBA f32 pixels.
type Decoded = (u32, u32, Vec<f32>);

/// Decodes an image to straight RGBA f32 in `[0, 1]`.
fn decode_rgba(path: &Path) -> Result<Decoded, DataError> {
    let img = open_image(path)?.decode().map_err(|source| DataError::Decode { path: path.to_path_buf(), source })?;
    let (w, h) = (img.width(), img.height());
    let lut8: [f32; 256] = std::array::from_fn(|i| i as f32 / 255.0);
    let px = match img {
        image::DynamicImage::ImageRgba8(b) => {
            b.as_raw().iter().map(|&v| lut8[v as usize]).collect()
        }
        image::DynamicImage::ImageRgb8(b) => b
            .as_raw()
            .chunks_exact(3)
            .flat_map(|p| {
                [
                    lut8[p[0] as usize],
                    lut8[p[1] as usize],
                    lut8[p[2] as usize],
                    1.0,
                ]
            })
            .collect(),
        image::DynamicImage::ImageRgba16(b) => {
            b.as_raw().iter().map(|&v| v as f32 / 65535.0).collect()
        }
        image::DynamicImage::ImageRgb16(b) => b
            .as_raw()
            .chunks_exact(3)
            .flat_map(|p| {
                [
                    p[0] as f32 / 65535.0,
                    p[1] as f32 / 65535.0,
                    p[2] as f32 / 65535.0,
                    1.0,
                ]
            })
            .collect(),
        // Grey, and float images (TIFF): values past [0, 1] (an HDR photo) are clipped, as an
        // 8-bit photo of the scene would clip them; a value that is not a number is an error.
        other => {
            let mut px = other.to_rgba32f().into_raw();
            if let Some(i) = px.iter().position(|v| !v.is_finite()) {
                return Err(DataError::InvalidValue {
                    path: path.to_path_buf(),
                    key: "pixels".into(),
                    reason: format!("pixel ({}, {}) holds {}: a photo's values must be numbers", (i / 4) as u32 % w, (i / 4) as u32 / w, px[i]),
                });
            }
            px.iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
            px
        }
    };
    Ok((w, h, px))
}

/// k×k box average of an RGBA image (`w`, `h` divisible by `k`).
fn downscale_rgba(px: &[f32], w: usize, h: usize, k: usize) -> Vec<f32> {
    if k == 1 {
        return px.to_vec();
    }
    let (ow, oh) = (w / k, h / k);
    let inv = 1.0 / (k * k) as f32;
    let mut out = vec![0.0f32; ow * oh * 4];
    for (oy, orow) in out.chunks_exact_mut(4 * ow).enumerate() {
        for (ox, o) in orow.chunks_exact_mut(4).enumerate() {
            let mut acc = [0.0f32; 4];
            for y in oy * k..oy * k + k {
                let row = &px[4 * (y * w + ox * k)..4 * (y * w + ox * k + k)];
                for p in row.chunks_exact(4) {
                    for c in 0..4 {
                        acc[c] += p[c];
                    }
                }
            }
            for c in 0..4 {
                o[c] = acc[c] * inv;
            }
        }
    }
    out
}

/// Decodes `paths` in parallel and downscales each by `k` (a k×k box average); all must have the
/// size of the first, and `k` must divide it. Returns that size (before downscaling) and the
/// images; an error names the first failing image in order.
fn decode_views(paths: &[&Path], k: u32, cameras_only: bool) -> Result<(u32, u32, Vec<Pixels>), DataError> {
    let decoded = decode_each(paths, k, &|_, _, w, h| Ok((w, h)), &|_, _, _, _, px| Ok(px), cameras_only)?;
    let (w, h) = decoded[0].0;
    let mut images = Vec::with_capacity(decoded.len());
    for (i, ((vw, vh), _, px)) in decoded.into_iter().enumerate() {
        if (vw, vh) != (w, h) {
            return Err(size_mismatch(paths[i], (vw, vh), paths[0], (w, h)));
        }
        images.push(px);
    }
    Ok((w, h, images))
}

/// The image at `path` is `size`, not the size of the first image `first`.
/// Checks that every camera's lens takes each point of its photo back to a direction
/// ([`nerf_rays::Distortion::undistort_dir`]), once per distinct lens and image size: every
/// pixel corner along the photo's border, where the distorted radius is largest and a fold shows
/// first, and every 8th one inside (a COLMAP model with a camera per photo has hundreds of
/// lenses). Coefficients that fold the lens's polynomial over inside the photo (a calibration
/// gone wrong, or coefficients meant for another image size) would give its outer pixels the
/// rays of inner ones.
fn check_lenses(tpath: &Path, frames: &[&Frame], cameras: &[Camera]) -> Result<(), DataError> {
    let mut checked: Vec<(Intrinsics, Distortion)> = Vec::new();
    for (f, cam) in frames.iter().zip(cameras) {
        let (k, d) = (cam.intrinsics, cam.distortion);
        if d.is_identity() || checked.contains(&(k, d)) {
            continue;
        }
        checked.push((k, d));
        let bad = (0..=k.height).into_par_iter().find_map_first(|j| {
            let edge = j == 0 || j == k.height;
            (0..=k.width).filter(|&i| edge || i == 0 || i == k.width || (i % 8 == 0 && j % 8 == 0)).find(|&i| {
                let (xd, yd) = ((i as f64 - k.cx as f64) / k.fx as f64, (j as f64 - k.cy as f64) / k.fy as f64);
                !d.undistort_iterate(xd, yd).1
            })
            .map(|i| (i, j))
        });
        if let Some((i, j)) = bad {
            return Err(DataError::InvalidValue {
                path: tpath.to_path_buf(),
                key: format!("frames[{}].k1", f.index),
                reason: format!(
                    "the lens ({d}) takes no direction to the point ({i}, {j}) of {} ({}x{} as loaded): \
                     its polynomial folds over inside the photo (are the coefficients for this image size?)",
                    f.image.display(), k.width, k.height
                ),
            });
        }
    }
    Ok(())
}

fn size_mismatch(path: &Path, size: (u32, u32), first: &Path, first_size: (u32, u32)) -> DataError {
    DataError::SizeMismatch {
        path: path.to_path_buf(),
        width: size.0,
        height: size.1,
        first: first.to_path_buf(),
        first_width: first_size.0,
        first_height: first_size.1,
    }
}

/// A step between decoding an image and downscaling it: `(index, path, width, height, pixels)` →
/// the view's pixels, of the size [`ViewSize`] gives (e.g. [`ngp::undistort_rgba`], the same
/// size; [`equirect::face_rgba`], a panorama's face).
type ImageFix<'a> = dyn Fn(usize, &Path, u32, u32, Vec<f32>) -> Result<Vec<f32>, DataError> + Sync + 'a;

/// The size of the view `index` makes of its image at `path` of `width × height` pixels (before
/// downscaling); an error where the image's size is not the one its frame states.
type ViewSize<'a> = dyn Fn(usize, &Path, u32, u32) -> Result<(u32, u32), DataError> + Sync + 'a;

/// An image's size and the size of the view made of it (both before downscaling).
type ImageAndViewSize = ((u32, u32), (u32, u32));

/// A decoded view: its image's size, the view's size (both before downscaling) and the view's
/// downscaled pixels.
type DecodedView = ((u32, u32), (u32, u32), Pixels);

/// A reader for the image at `path`: the format its first bytes show, else its extension's.
fn open_image(path: &Path) -> Result<image::ImageReader<std::io::BufReader<std::fs::File>>, DataError> {
    let io = |source| DataError::Io { path: path.to_path_buf(), source };
    image::ImageReader::open(path).map_err(io)?.with_guessed_format().map_err(io)
}

/// Width and height from an image's header, without decoding its pixels.
fn image_size(path: &Path) -> Result<(u32, u32), DataError> {
    open_image(path)?.into_dimensions().map_err(|source| DataError::Decode { path: path.to_path_buf(), source })
}

/// Decodes `paths` in parallel, makes each image its view (`size`, `fix`) and downscales that by
/// `k`, which must divide the view's size. With `cameras_only` ([`LoadOptions::cameras_only`])
/// each image's size comes from its header, the same checks run, and every view's pixels are
/// left empty (`fix` is not called). An error names the first failing image in order.
fn decode_each(paths: &[&Path], k: u32, size: &ViewSize, fix: &ImageFix, cameras_only: bool) -> Result<Vec<DecodedView>, DataError> {
    assert!(!paths.is_empty(), "decoding no images");
    paths
        .par_iter()
        .enumerate()
        .map(|(i, &path)| {
            let (w, h, px) = if cameras_only {
                let (w, h) = image_size(path)?;
                (w, h, Vec::new())
            } else {
                decode_rgba(path)?
            };
            // Each view as it will be held, before the next is decoded: the loader never holds
            // every view as f32.
            if w == 0 || h == 0 {
                return Err(DataError::BadDownscale { path: path.to_path_buf(), k, reason: "the image is empty".into() });
            }
            let (vw, vh) = size(i, path, w, h)?;
            if vw % k != 0 || vh % k != 0 {
                return Err(DataError::BadDownscale {
                    path: path.to_path_buf(),
                    k,
                    reason: format!("it does not divide the image size {vw}x{vh}"),
                });
            }
            if cameras_only {
                return Ok(((w, h), (vw, vh), Pixels::default()));
            }
            let px = fix(i, path, w, h, px)?;
            debug_assert_eq!(px.len(), 4 * (vw * vh) as usize, "the view's pixels");
            Ok(((w, h), (vw, vh), Pixels::from_f32(&downscale_rgba(&px, vw as usize, vh as usize, k as usize))))
        })
        .collect::<Vec<_>>()
        .into_iter()
        .collect()
}

/// Which pixels of a lens's pinhole images its photos saw ([`ngp::pixels_seen`]), shared by
/// the frames of that lens.
type Seen = Arc<Vec<bool>>;

/// The training masks of `frames` ([`mask`]) from `sources`: each mask must be the size of its
/// frame's image (`sizes[i].0`, before downscaling; `sizes[i].1` is its view's). A pixel is kept
/// where the mask's value (grey, or any colour channel) is not 0 (`mask_path`), or where it is 0
/// (instant-ngp's dynamic masks). The masks go through the images' resampling to their views
/// (`fix`: a lens, a panorama's face), then drop the pixels their photo
/// did not see (`seen`, one per frame or empty: [`ngp::pixels_seen`]), then `k`× downscaling,
/// and a resulting pixel is kept only where every mask pixel it draws on is: training never
/// reads a masked-out pixel, even in part. Per view, the ascending indices of its kept pixels in
/// its own downscaled image (`None`: every pixel; views whose only mask is their lens's share
/// one list). An error names the first failing mask in order.
fn decode_masks(
    frames: &[&Frame],
    sources: &[MaskSource],
    seen: &[Option<Seen>],
    sizes: &[ImageAndViewSize],
    k: u32,
    fix: &ImageFix,
) -> Result<Vec<Option<Arc<[u32]>>>, DataError> {
    for (f, src) in frames.iter().zip(sources) {
        if let MaskSource::Keep(p) | MaskSource::Drop(p) = src {
            if !p.is_file() {
                return Err(DataError::BadMask { path: p.to_path_buf(), frame: f.index, reason: "file not found".into() });
            }
        }
    }
    // A mask (1 kept, 0 dropped, in every channel) of a `(w, h)` image without the pixels its
    // photo did not see, downscaled, as the indices of its kept pixels (`None`: all of them).
    let kept_of = |mut px: Vec<f32>, (w, h): (u32, u32), seen: Option<&Vec<bool>>| -> Option<Arc<[u32]>> {
        if let Some(seen) = seen {
            px.chunks_exact_mut(4).zip(seen).filter(|(_, &s)| !s).for_each(|(p, _)| p.fill(0.0));
        }
        let px = downscale_rgba(&px, w as usize, h as usize, k as usize);
        // Bilinear resampling and box averages of 1s give 1 up to rounding; a value mixed with a
        // 0 is at most 1 − 1/k² (box) or 1 − w for the 0's bilinear weight w (kept only for
        // w < 10⁻⁶).
        let kept: Vec<u32> = px.chunks_exact(4).enumerate().filter(|(_, p)| p[0] >= 1.0 - 1e-6).map(|(j, _)| j as u32).collect();
        (kept.len() < px.len() / 4).then(|| Arc::from(kept))
    };
    // Views whose only mask is their lens's share one list per lens (a lens's pixels are those
    // of one image size).
    let mut by_lens: Vec<(&Seen, Option<Arc<[u32]>>)> = Vec::new();
    for ((src, s), &(_, size)) in sources.iter().zip(seen).zip(sizes) {
        if let (MaskSource::All, Some(s)) = (src, s) {
            if !by_lens.iter().any(|(l, _)| Arc::ptr_eq(l, s)) {
                by_lens.push((s, kept_of(vec![1.0; 4 * (size.0 * size.1) as usize], size, Some(s))));
            }
        }
    }
    // One mask at a time per thread, down to its kept indices: no view's mask is held as pixels.
    let kept: Vec<Result<Option<Arc<[u32]>>, DataError>> = sources
        .par_iter()
        .enumerate()
        .map(|(i, &src)| {
            let seen = seen.get(i).and_then(Option::as_ref);
            let ((w, h), view) = sizes[i];
            let px = match src {
                MaskSource::All => return Ok(seen.and_then(|s| by_lens.iter().find(|(l, _)| Arc::ptr_eq(l, s)).expect("listed above").1.clone())),
                MaskSource::Keep(path) | MaskSource::Drop(path) => {
                    let (mw, mh, mut px) = decode_rgba(path)?;
                    if (mw, mh) != (w, h) {
                        return Err(DataError::BadMask {
                            path: path.to_path_buf(),
                            frame: frames[i].index,
                            reason: format!("it is {mw}x{mh}, its image {} is {w}x{h}", frames[i].image.display()),
                        });
                    }
                    let drop = matches!(src, MaskSource::Drop(_));
                    for p in px.chunks_exact_mut(4) {
                        let keep = if p[..3].iter().any(|&v| v > 0.0) != drop { 1.0 } else { 0.0 };
                        p.fill(keep);
                    }
                    fix(i, path, w, h, px)?
                }
            };
            Ok(kept_of(px, view, seen.map(|s| &**s)))
        })
        .collect();
    kept.into_iter().collect()
}

/// Views of different sizes on one canvas ([`Dataset::width`] × [`Dataset::height`], the
/// largest width and height): `sizes` are the views' (loaded) sizes. Each view's pixels,
/// depth map and kept-pixel list are moved to the canvas's top-left corner, row by row; the
/// pixels past a view's own width or height are transparent black, have no depth, and are
/// dropped from its training mask. Returns the masks on the canvas: `masks` moved, or, where
/// there were none, masks that keep each view's own pixels (one list per size, shared by its
/// views).
fn to_canvas(
    sizes: &[(u32, u32)],
    canvas: (u32, u32),
    images: &mut [Pixels],
    depths: Option<&mut Vec<Vec<f32>>>,
    masks: Option<Vec<Option<Arc<[u32]>>>>,
) -> PixelMasks {
    let (cw, ch) = (canvas.0 as usize, canvas.1 as usize);
    // `values` per pixel of a `w`-wide image, its rows at the canvas's stride.
    fn widen<T: Copy + Default>(src: &[T], w: usize, per_pixel: usize, (cw, ch): (usize, usize)) -> Vec<T> {
        let mut out = vec![T::default(); per_pixel * cw * ch];
        for (row, r) in src.chunks_exact(per_pixel * w).enumerate() {
            out[per_pixel * row * cw..][..per_pixel * w].copy_from_slice(r);
        }
        out
    }
    let small = |v: usize| (sizes[v].0 as usize, sizes[v].1 as usize) != (cw, ch);
    for (v, img) in images.iter_mut().enumerate() {
        if small(v) && !img.is_empty() {
            *img = img.widened(sizes[v].0 as usize, (cw, ch));
        }
    }
    if let Some(d) = depths {
        for (v, map) in d.iter_mut().enumerate() {
            if small(v) {
                *map = widen(map, sizes[v].0 as usize, 1, (cw, ch));
            }
        }
    }
    // Lists moved once each (a shared list stays shared), and each size's list of every pixel.
    let mut moved: Vec<(*const [u32], Arc<[u32]>)> = Vec::new();
    type SizeList = ((u32, u32), Arc<[u32]>);
    let mut whole: Vec<SizeList> = Vec::new();
    let kept = (0..sizes.len())
        .map(|v| {
            let list = masks.as_ref().and_then(|m| m[v].clone());
            if !small(v) {
                return list;
            }
            let w = sizes[v].0;
            let to_canvas = |p: u32| (p / w) * canvas.0 + p % w;
            Some(match list {
                Some(l) => match moved.iter().find(|(p, _)| std::ptr::eq(*p, &*l)) {
                    Some((_, m)) => m.clone(),
                    None => {
                        let m: Arc<[u32]> = l.iter().map(|&p| to_canvas(p)).collect();
                        moved.push((Arc::as_ptr(&l), m.clone()));
                        m
                    }
                },
                None => match whole.iter().find(|(s, _)| *s == sizes[v]) {
                    Some((_, m)) => m.clone(),
                    None => {
                        let m: Arc<[u32]> = (0..sizes[v].0 * sizes[v].1).map(to_canvas).collect();
                        whole.push((sizes[v], m.clone()));
                        m
                    }
                },
            })
        })
        .collect();
    PixelMasks::with_shared_views(canvas.0 * canvas.1, kept)
}

/// Loads one split of a scene in any format, by [`LoadOptions::format`]; by default LLFF
/// ([`load_llff`]) where the folder holds `poses_bounds.npy`, COLMAP ([`load_colmap`]) where it
/// holds a sparse model and no transforms file, else Blender or instant-ngp / nerfstudio
/// ([`load_blender`]).
pub fn load_scene(root: &Path, split: Split, opts: &LoadOptions) -> Result<Dataset, DataError> {
    match opts.format {
        SceneFormat::Llff => load_llff(root, split, opts),
        SceneFormat::Colmap => load_colmap(root, split, opts),
        SceneFormat::Transforms => load_blender(root, split, opts),
        SceneFormat::Auto if is_llff(root) => load_llff(root, split, opts),
        SceneFormat::Auto if is_colmap(root) => load_colmap(root, split, opts),
        SceneFormat::Auto => load_blender(root, split, opts),
    }
}

/// Loads one split of a COLMAP scene folder ([`colmap`]: `images/` and a sparse model): the
/// model read as the nerfstudio `transforms.json` that `ns-process-data` would write for it
/// ([`colmap::transforms_json`]), then loaded as [`load_blender`] loads that file. Errors name
/// the model's files.
pub fn load_colmap(root: &Path, split: Split, opts: &LoadOptions) -> Result<Dataset, DataError> {
    let dir = colmap::find_model(root).ok_or_else(|| DataError::Colmap {
        path: root.to_path_buf(),
        reason: format!("no model in {}", colmap::MODEL_DIRS.join(", ")),
    })?;
    let model = colmap::read_model(&dir)?;
    let (cameras, images) = colmap::model_files(&dir).ok_or_else(|| DataError::Colmap { path: dir.clone(), reason: "the model files went away while it was read".into() })?;
    let json = colmap::transforms_json(&cameras, &model)?;
    // The SfM points each frame's image observes, in the frame of the transforms file.
    let sfm = match (opts.sfm_depth && !opts.cameras_only).then(|| colmap::read_points(&dir)).transpose()?.flatten() {
        None => None,
        Some(points) => {
            let mut by_image: std::collections::HashMap<u32, Vec<[f64; 3]>> = std::collections::HashMap::new();
            for p in points.iter().filter(|p| p.error <= colmap::SFM_MAX_ERROR && p.images.len() >= colmap::SFM_MIN_VIEWS) {
                let x: [f64; 3] = std::array::from_fn(|i| (0..3).map(|k| colmap::APPLIED_TRANSFORM[i][k] * p.xyz[k]).sum());
                for im in &p.images {
                    by_image.entry(*im).or_default().push(x);
                }
            }
            let frames = json["frames"].as_array().expect("transforms_json writes frames");
            Some(frames.iter().map(|f| f["colmap_im_id"].as_u64().and_then(|id| by_image.remove(&(id as u32))).unwrap_or_default()).collect::<Vec<_>>())
        }
    };
    load_transforms_with(root, split, opts, images, &json, true, sfm.as_deref())
}

/// Loads one split of a Blender-format scene, or of an instant-ngp / nerfstudio scene (the same
/// format with the extensions of [`ngp`]): reads `root/transforms_<split>.json`, or else
/// `root/transforms.json` and takes the split's frames from it (every 8th frame for test and val,
/// the rest for train, unless nerfstudio's `<split>_filenames` lists them); selects views; decodes their images in parallel (RGBA 8/16-bit or RGB PNG,
/// JPEG; alpha 1 when absent), resamples photos with lens distortion to pinhole images,
/// optionally downscales them by a k×k box average, and builds each view's camera from its
/// intrinsics ([`ngp::Lens::intrinsics`]; Blender: `Intrinsics::from_fov_x(W0, H0,
/// camera_angle_x)`) `.downscaled(k)`. Every frame's `transform_matrix` and camera keys are
/// validated, even for unselected views. NeRF's Blender scenes get `near = 2`, `far = 6` and
/// `aabb = Aabb::cube(1.5)`; instant-ngp scenes ([`Dataset::ngp`]) the cube of their
/// [`NgpBox`], `near = `[`NgpBox::near`] and a `far` past the cube's farthest corner from every
/// camera of the file (the same for every split). A nerfstudio file ([`ngp::is_nerfstudio`]) has
/// its poses normalised as nerfstudio does ([`NerfstudioNormalization`], from every frame of the
/// file) and trains in nerfstudio's box `[−1, 1]³`.
pub fn load_blender(root: &Path, split: Split, opts: &LoadOptions) -> Result<Dataset, DataError> {
    let split_path = root.join(split.transforms_file());
    let single_path = root.join(ngp::NGP_TRANSFORMS);
    let (tpath, one_file) = if split_path.is_file() {
        (split_path, false)
    } else if single_path.is_file() {
        (single_path, true)
    } else {
        return Err(DataError::MissingTransforms { path: split_path });
    };
    let text = std::fs::read_to_string(&tpath).map_err(|source| DataError::Io {
        path: tpath.clone(),
        source,
    })?;
    let json: Value = serde_json::from_str(&text).map_err(|source| DataError::Json {
        path: tpath.clone(),
        source,
    })?;
    load_transforms(root, split, opts, tpath, &json, one_file)
}

/// [`load_blender`] after reading the transforms file `tpath`: `json` is its content, `one_file`
/// whether it is a single `transforms.json` (its frames split by [`ngp::split_filenames`] or
/// every 8th) rather than a split's own file.
fn load_transforms(root: &Path, split: Split, opts: &LoadOptions, tpath: PathBuf, json: &Value, one_file: bool) -> Result<Dataset, DataError> {
    load_transforms_with(root, split, opts, tpath, json, one_file, None)
}

/// [`load_transforms`] with, per frame of the file, the SfM points its image observes (in the
/// file's frame), from which frames without a depth map get sparse ones
/// ([`LoadOptions::sfm_depth`]).
#[allow(clippy::too_many_arguments)]
fn load_transforms_with(
    root: &Path,
    split: Split,
    opts: &LoadOptions,
    tpath: PathBuf,
    json: &Value,
    one_file: bool,
    sfm: Option<&[Vec<[f64; 3]>]>,
) -> Result<Dataset, DataError> {
    let missing = |key: String| DataError::MissingKey {
        path: tpath.clone(),
        key,
    };
    let invalid = |key: String, reason: String| DataError::InvalidValue {
        path: tpath.clone(),
        key,
        reason,
    };
    if !json.is_object() {
        return Err(invalid(
            "<top level>".into(),
            format!("expected an object, got {}", json_kind(json)),
        ));
    }
    ngp::Lens::parse(&tpath, json, None)?;
    let parsed_box = ngp::NgpBox::parse(&tpath, json)?;
    // Whether the poses are nerfstudio's is the file's say, whatever box the options ask for.
    let nerfstudio = one_file && ngp::is_nerfstudio(json);
    let parsed_box = match opts.aabb_scale {
        Some(s) if !(s.is_finite() && s > 0.0) => {
            return Err(invalid("aabb_scale".into(), format!("{s} (asked for in place of the file's): must be finite and above 0")));
        }
        Some(s) => Some(NgpBox { aabb_scale: s, ..parsed_box.unwrap_or_default() }),
        None => parsed_box,
    };
    let frames_v = json.get("frames").ok_or_else(|| missing("frames".into()))?;
    let frames_json = frames_v.as_array().ok_or_else(|| {
        invalid(
            "frames".into(),
            format!("expected an array, got {}", json_kind(frames_v)),
        )
    })?;
    if frames_json.is_empty() {
        return Err(DataError::EmptySplit {
            path: tpath.clone(),
            reason: "`frames` is empty".into(),
        });
    }
    // Depth maps' units: nerfstudio's `depth_unit_scale_factor` (10⁻³ when absent), instant-ngp's
    // `integer_depth_scale` (required with `depth_path`).
    let depth_scale = |key: &str| -> Result<Option<f64>, DataError> {
        match json.get(key) {
            None => Ok(None),
            Some(v) => match v.as_f64() {
                Some(x) if x > 0.0 && x.is_finite() => Ok(Some(x)),
                _ => Err(invalid(key.into(), format!("expected a positive number, got {v}"))),
            },
        }
    };
    let nerfstudio_depth = depth_scale("depth_unit_scale_factor")?.unwrap_or(depth::NERFSTUDIO_DEPTH_SCALE);
    let ngp_depth = depth_scale("integer_depth_scale")?;
    let mut frames = Vec::with_capacity(frames_json.len());
    for (i, f) in frames_json.iter().enumerate() {
        let lens = ngp::Lens::parse(&tpath, json, Some((i, f)))?;
        if lens.focal_x.is_none() && !lens.equirectangular {
            return Err(missing("camera_angle_x` or `fl_x".into()));
        }
        let fp_v = f
            .get("file_path")
            .ok_or_else(|| missing(format!("frames[{i}].file_path")))?;
        let fp = fp_v.as_str().ok_or_else(|| {
            invalid(
                format!("frames[{i}].file_path"),
                format!("expected a string, got {}", json_kind(fp_v)),
            )
        })?;
        let m = f
            .get("transform_matrix")
            .ok_or_else(|| missing(format!("frames[{i}].transform_matrix")))?;
        let c2w = parse_matrix(&tpath, i, m)?;
        let mask = match f.get("mask_path") {
            None | Some(Value::Null) => None,
            Some(Value::String(p)) => Some(image_path(root, p)),
            Some(v) => return Err(invalid(format!("frames[{i}].mask_path"), format!("expected a string, got {}", json_kind(v)))),
        };
        let depth = match (f.get("depth_file_path"), f.get("depth_path")) {
            (None | Some(Value::Null), None | Some(Value::Null)) => None,
            (Some(Value::String(p)), _) => Some((image_path(root, p), nerfstudio_depth)),
            (None | Some(Value::Null), Some(Value::String(p))) => {
                Some((image_path(root, p), ngp_depth.ok_or_else(|| missing("integer_depth_scale` (the depth maps' units, beside `depth_path`".into()))?))
            }
            (Some(v), _) => return Err(invalid(format!("frames[{i}].depth_file_path"), format!("expected a string, got {}", json_kind(v)))),
            (_, Some(v)) => return Err(invalid(format!("frames[{i}].depth_path"), format!("expected a string, got {}", json_kind(v)))),
        };
        frames.push(Frame {
            index: i,
            image: image_path(root, fp),
            face: None,
            mask,
            depth,
            c2w,
            lens,
        });
    }
    // nerfstudio's rule: a mask for every frame or for none.
    if let Some(f) = frames.iter().find(|f| f.mask.is_some() != frames[0].mask.is_some()) {
        let (with, without) = if f.mask.is_some() { (f.index, 0) } else { (0, f.index) };
        return Err(invalid(
            format!("frames[{}].mask_path", f.index),
            format!("frame {with} has a mask_path and frame {without} none: give every frame a mask or none"),
        ));
    }
    // The split's frames: all of a split file; every 8th (test, val) or the others (train) of one file.
    let in_split: Vec<usize> = if one_file {
        match ngp::split_filenames(&tpath, json, split)? {
            // nerfstudio's explicit lists: the frames whose image is named there.
            Some(names) => {
                let wanted: Vec<PathBuf> = names.iter().map(|n| image_path(root, n)).collect();
                if let Some(n) = names.iter().zip(&wanted).find(|(_, w)| !frames.iter().any(|f| &f.image == *w)) {
                    return Err(invalid(format!("{split}_filenames"), format!("`{}` is not the image of any frame", n.0)));
                }
                (0..frames.len()).filter(|&i| wanted.contains(&frames[i].image)).collect()
            }
            None => match opts.holdout {
                None => llff::split_indices(frames.len(), split),
                // nerfstudio's eval modes take the frames in the order of their images' names
                // (and so does the split).
                Some(h) => {
                    let mut by_name: Vec<usize> = (0..frames.len()).collect();
                    by_name.sort_by(|&a, &b| frames[a].image.cmp(&frames[b].image));
                    let names: Vec<String> = by_name.iter().map(|&i| file_name_of(&frames[i].image)).collect();
                    h.split(&names, split).map_err(|e| invalid("holdout".into(), e))?.into_iter().map(|i| by_name[i]).collect()
                }
            },
        }
    } else {
        (0..frames.len()).collect()
    };
    if in_split.is_empty() {
        return Err(DataError::EmptySplit {
            path: tpath.clone(),
            reason: format!("{} frames leave none for the {split} split", frames.len()),
        });
    }
    let selected = opts
        .views
        .indices(in_split.len())
        .map_err(|reason| DataError::BadSelection {
            path: tpath.clone(),
            reason,
        })?;
    if selected.is_empty() {
        return Err(DataError::EmptySplit {
            path: tpath.clone(),
            reason: format!("view selection `{}` leaves no views", opts.views),
        });
    }
    let k = opts.downscale;
    if k == 0 {
        return Err(DataError::BadDownscale {
            path: tpath.clone(),
            k,
            reason: "the factor must be at least 1".into(),
        });
    }
    // nerfstudio's poses are COLMAP's: normalised here as nerfstudio does, from every frame of
    // the file (cameras that all sit at one point, e.g. a single view, cannot be: they keep
    // instant-ngp's placement).
    let normalization = if nerfstudio {
        opts.nerfstudio.validate().map_err(|reason| DataError::InvalidValue { path: tpath.clone(), key: "scale_factor".into(), reason })?;
        ngp::NerfstudioNormalization::with_options(&frames.iter().map(|f| &f.c2w[..]).collect::<Vec<_>>(), &opts.nerfstudio)
    } else {
        None
    };
    let ngp_box = match normalization {
        Some(n) => {
            frames.iter_mut().for_each(|f| n.apply(&mut f.c2w));
            Some(NgpBox { aabb_scale: parsed_box.map_or(1.0, |b| b.aabb_scale), ..ngp::NerfstudioNormalization::BOX })
        }
        None if one_file => Some(parsed_box.unwrap_or_default()),
        None => parsed_box,
    };
    // Every frame's camera centre (all splits: `far` must not depend on the split or selection).
    let centres: Vec<Vec3> = frames.iter().map(|f| Vec3::new(f.c2w[0][3], f.c2w[1][3], f.c2w[2][3])).collect();
    let frames: Vec<&Frame> = selected.iter().map(|&i| &frames[in_split[i]]).collect();
    // nerfstudio's downscaled copies, read in place of box-averaging the originals where every
    // selected frame has them.
    let copies = if nerfstudio && k > 1 { downscaled_copies(root, &frames, k) } else { None };
    let (frames, k): (Vec<&Frame>, u32) = match &copies {
        Some(c) => (c.iter().collect(), 1),
        None => (frames, k),
    };
    for f in &frames {
        if !f.image.is_file() {
            return Err(DataError::MissingImage {
                path: f.image.clone(),
                frame: f.index,
            });
        }
    }
    // A panorama is six views: the faces of a cube map, from its centre ([`equirect`]).
    let faces: Vec<Frame> = frames
        .iter()
        .flat_map(|&f| {
            let n = if f.lens.equirectangular { equirect::FACES.len() } else { 1 };
            (0..n).map(move |face| {
                let mut v = f.clone();
                if f.lens.equirectangular {
                    let r = Mat3::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|r| f.c2w[r][c]))) * equirect::face_rotation(face);
                    for (row, c2w_row) in v.c2w.iter_mut().take(3).enumerate() {
                        for col in 0..3 {
                            c2w_row[col] = r.col(col)[row];
                        }
                    }
                    v.face = Some(face);
                }
                v
            })
        })
        .collect();
    let frames: Vec<&Frame> = faces.iter().collect();

    let paths: Vec<&Path> = frames.iter().map(|f| f.image.as_path()).collect();
    // A view's size: its photo's, or a panorama's face's (the panorama checked against the
    // size its frame states).
    let view_size = |i: usize, path: &Path, w: u32, h: u32| -> Result<(u32, u32), DataError> {
        let f = &frames[i];
        match f.face {
            None => Ok((w, h)),
            Some(_) => {
                if let Some(stated) = f.lens.size.filter(|&s| s != (w, h)) {
                    return Err(DataError::InvalidValue {
                        path: tpath.clone(),
                        key: format!("frames[{}].w", f.index),
                        reason: format!("the panorama is stated as {}x{}, but {} is {w}x{h}", stated.0, stated.1, path.display()),
                    });
                }
                let s = equirect::face_size(w, k).ok_or_else(|| DataError::BadDownscale {
                    path: path.to_path_buf(),
                    k,
                    reason: format!("a {w}-pixel-wide panorama's faces would be empty"),
                })?;
                Ok((s, s))
            }
        }
    };
    // An image made its view: a lens resampled to its pinhole camera, a panorama's face cut out.
    let undistort = |i: usize, path: &Path, w: u32, h: u32, px: Vec<f32>| {
        let f = &frames[i];
        if let Some(face) = f.face {
            let (s, _) = view_size(i, path, w, h)?;
            return Ok(equirect::face_rgba(&px, w, h, face, s));
        }
        if !opts.undistort || f.lens.distortion.is_identity() {
            return Ok(px);
        }
        let intr = f.lens.intrinsics(&tpath, path, w, h)?;
        Ok(ngp::undistort_rgba(&px, &intr, &f.lens.distortion))
    };
    let decoded = decode_each(&paths, k, &view_size, &undistort, opts.cameras_only)?;
    // Views may differ in size where the file states each one's (`w`, `h`: a capture with
    // several cameras) and for panoramas' faces; another view has the first such view's size.
    let both: Vec<ImageAndViewSize> = decoded.iter().map(|&(src, view, _)| (src, view)).collect();
    let sizes: Vec<(u32, u32)> = both.iter().map(|&(_, view)| view).collect();
    let plain: Vec<usize> = (0..frames.len()).filter(|&i| frames[i].face.is_none()).collect();
    if let Some(&i) = plain.iter().find(|&&i| frames[i].lens.size.is_none() && sizes[i] != sizes[plain[0]]) {
        return Err(size_mismatch(paths[i], sizes[i], paths[plain[0]], sizes[plain[0]]));
    }
    let mut images: Vec<Pixels> = decoded.into_iter().map(|(_, _, px)| px).collect();
    // Each view's pinhole intrinsics at the stored size, and its camera at the loaded one.
    let intrinsics = frames
        .iter()
        .zip(&sizes)
        .map(|(f, &(w, h))| match f.face {
            Some(_) => Ok(equirect::face_intrinsics(w)),
            None => f.lens.intrinsics(&tpath, &f.image, w, h),
        })
        .collect::<Result<Vec<_>, _>>()?;
    // Each camera carries its lens, unless the photos are resampled to pinhole images.
    let cameras = frames
        .iter()
        .zip(&intrinsics)
        .map(|(f, intr)| {
            let cam = Camera::from_c2w(intr.downscaled(k), &f.c2w).map_err(|e| DataError::pose(&tpath, f.index, e))?;
            Ok(if opts.undistort { cam } else { cam.with_distortion(f.lens.distortion) })
        })
        .collect::<Result<Vec<_>, DataError>>()?;
    check_lenses(&tpath, &frames, &cameras)?;
    // nerfstudio's masks, else instant-ngp's dynamic masks where any of the split's photos has
    // one (looked for only where pixels are loaded).
    let dynamic: Vec<Option<PathBuf>> = match frames[0].mask {
        None if !opts.cameras_only => frames.iter().map(|f| Some(dynamic_mask_path(&f.image)).filter(|p| p.is_file())).collect(),
        _ => Vec::new(),
    };
    // Pixels of the pinhole images that their photos did not see (a lens whose pinhole image
    // reaches past the photo), and those past a fisheye's image circle (`fisheye_crop_radius`),
    // once per distinct lens.
    let mut lenses: Vec<(Intrinsics, Distortion, Option<f64>, Option<Seen>)> = Vec::new();
    let mut seen = Vec::new();
    if !opts.cameras_only {
        for (f, &intr) in frames.iter().zip(&intrinsics) {
            // Photos kept as taken are seen where they are; resampled ones through their lens.
            let d = if opts.undistort { f.lens.distortion } else { Distortion::NONE };
            let crop = f.lens.crop_radius;
            if d.is_identity() && crop.is_none() {
                seen.push(None);
                continue;
            }
            let s = match lenses.iter().find(|(i, l, c, _)| (*i, *l, *c) == (intr, d, crop)) {
                Some((_, _, _, s)) => s.clone(),
                None => {
                    let s = ngp::pixels_seen(&intr, &d, crop).map(Arc::new);
                    lenses.push((intr, d, crop, s.clone()));
                    s
                }
            };
            seen.push(s);
        }
    }
    let sources: Option<Vec<MaskSource>> = if frames[0].mask.is_some() {
        Some(frames.iter().map(|f| MaskSource::Keep(f.mask.as_deref().expect("every frame or none"))).collect())
    } else if dynamic.iter().any(Option::is_some) {
        Some(dynamic.iter().map(|p| p.as_deref().map_or(MaskSource::All, MaskSource::Drop)).collect())
    } else if seen.iter().any(Option::is_some) {
        Some(vec![MaskSource::All; frames.len()])
    } else {
        None
    };
    let masks = match sources {
        Some(sources) if !opts.cameras_only => Some(decode_masks(&frames, &sources, &seen, &both, k, &undistort)?),
        _ => None,
    };
    // Depth maps, through the photos' lens resampling and downscaling, as distances along the
    // rays in the scene's units.
    let depths = if opts.cameras_only || frames.iter().all(|f| f.depth.is_none()) {
        None
    } else {
        let units = normalization.map_or(1.0, |n| n.scale) as f32;
        let maps: Vec<Result<Vec<f32>, DataError>> = frames
            .par_iter()
            .enumerate()
            .map(|(i, f)| {
                let ((w0, h0), (vw, vh)) = both[i];
                let Some((path, scale)) = &f.depth else { return Ok(vec![0.0; ((vw / k) * (vh / k)) as usize]) };
                let px = depth::decode(depth::DepthSource { path, scale: *scale }, f.index, (w0, h0))?;
                let px = downscale_rgba(&undistort(i, path, w0, h0, px)?, vw as usize, vh as usize, k as usize);
                // A panorama's depth map holds distances along the rays already (nerfstudio's
                // rays of an equirectangular camera are unit: it reads them so).
                Ok(match f.face {
                    Some(_) => depth::ranges(&px, units),
                    None => depth::ray_distances(&px, &cameras[i], units),
                })
            })
            .collect();
        Some(maps.into_iter().collect::<Result<Vec<_>, _>>()?)
    };
    // Sparse depth maps from the SfM points (COLMAP folders, `sfm_depth`), where no frame has a
    // depth map of its own.
    let mut depths = match (depths, sfm) {
        (None, Some(points)) if !opts.cameras_only => Some(
            frames
                .iter()
                .zip(&cameras)
                .map(|(f, cam)| {
                    let pts = points.get(f.index).map_or(&[][..], Vec::as_slice);
                    depth::sfm_depths(cam, pts.iter().map(|&p| normalization.map_or(p, |n| n.apply_point(p))))
                })
                .collect(),
        ),
        (d, _) => d,
    };
    // Views of different sizes share the canvas of the largest width and height.
    let loaded: Vec<(u32, u32)> = cameras.iter().map(|c| (c.intrinsics.width, c.intrinsics.height)).collect();
    let canvas = loaded.iter().fold((0, 0), |(w, h), &(vw, vh)| (w.max(vw), h.max(vh)));
    let n_pixels = canvas.0 * canvas.1;
    let masks = if loaded.iter().any(|&s| s != canvas) {
        Some(to_canvas(&loaded, canvas, &mut images, depths.as_mut(), masks))
    } else {
        masks.map(|m| PixelMasks::with_shared_views(n_pixels, m))
    };
    if masks.as_ref().is_some_and(|m| m.total() == 0) {
        return Err(DataError::EmptySplit { path: tpath.clone(), reason: "the masks keep no pixel: nothing to train on".into() });
    }
    let (near, far, aabb) = match &ngp_box {
        None => (2.0, 6.0, Aabb::cube(1.5)),
        Some(b) => {
            let (min, max) = b.world_aabb();
            let aabb = Aabb { min, max };
            // Past the cube's farthest corner from every camera of the file (rays are clipped to
            // the cube), so that every split and view selection gets the same bounds.
            let far = centres
                .iter()
                .flat_map(|&o| {
                    (0..8).map(move |m| {
                        let corner = Vec3::from_array(std::array::from_fn(|a| if m >> a & 1 == 1 { max[a] } else { min[a] }));
                        (corner - o).length()
                    })
                })
                .fold(0.0f32, f32::max);
            let near = b.near();
            (near, far.max(near) * 1.001 + 1e-3, aabb)
        }
    };
    Ok(Dataset {
        root: root.to_path_buf(),
        split,
        width: canvas.0,
        height: canvas.1,
        cameras,
        images,
        file_paths: frames.iter().map(|f| f.image.clone()).collect(),
        masks,
        depths,
        near,
        far,
        aabb,
        ndc: None,
        depth_bounds: None,
        ngp: ngp_box,
        normalization,
    })
}

// ---------------------------------------------------------------------------------------------
// Writing

#[inline]
fn to_u8(v: f32) -> u8 {
    // NaN → 0 (the `as` cast saturates NaN to 0).
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    bytes: &[u8],
    color: image::ExtendedColorType,
) -> Result<(), DataError> {
    use image::ImageEncoder as _;
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| DataError::Io {
            path: parent.to_path_buf(),
            source,
        })?;
    }
    let file = std::fs::File::create(path).map_err(|source| DataError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut wr = std::io::BufWriter::new(file);
    image::codecs::png::PngEncoder::new(&mut wr)
        .write_image(bytes, width, height, color)
        .map_err(|source| DataError::Encode {
            path: path.to_path_buf(),
            source,
        })?;
    use std::io::Write as _;
    wr.flush().map_err(|source| DataError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Writes a coloured point cloud as a binary little-endian PLY file (`float x, y, z` and
/// `uchar red, green, blue` per vertex; what MeshLab, CloudCompare, Blender and Open3D read),
/// colours in `[0, 1]` clamped and rounded to u8. Written under a temporary name and renamed, so
/// the file is whole or absent; the error names the path. (The format is a few lines of header
/// and packed records: not worth a dependency.)
pub fn write_ply_points(path: &Path, points: &[([f32; 3], [f32; 3])]) -> Result<(), DataError> {
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by nerf-rs\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    )
    .into_bytes();
    bytes.reserve(15 * points.len());
    for (p, c) in points {
        p.iter().for_each(|v| bytes.extend_from_slice(&v.to_le_bytes()));
        bytes.extend(c.iter().map(|&v| to_u8(v)));
    }
    write_ply_bytes(path, &bytes)
}

/// Writes a triangle mesh as a binary little-endian PLY file: per vertex `float x, y, z`,
/// `float nx, ny, nz` and `uchar red, green, blue` (colours in `[0, 1]`, clamped and rounded), per
/// face `list uchar int vertex_indices` of 3 — what MeshLab, Blender and Open3D read, and the
/// layout of instant-ngp's mesh export. Written under a temporary name and renamed, so the file is
/// whole or absent; the error names the path.
///
/// # Panics
/// If `normals` or `colors` is not one per position, or an index is not below the vertex count.
pub fn write_ply_mesh(
    path: &Path,
    positions: &[[f32; 3]],
    normals: &[[f32; 3]],
    colors: &[[f32; 3]],
    indices: &[u32],
) -> Result<(), DataError> {
    check_mesh(positions, normals, colors, indices);
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by nerf-rs\nelement vertex {}\n\
         property float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        positions.len(),
        indices.len() / 3
    )
    .into_bytes();
    bytes.reserve(27 * positions.len() + 13 * (indices.len() / 3));
    for ((p, n), c) in positions.iter().zip(normals).zip(colors) {
        p.iter().chain(n).for_each(|v| bytes.extend_from_slice(&v.to_le_bytes()));
        bytes.extend(c.iter().map(|&v| to_u8(v)));
    }
    for t in indices.chunks_exact(3) {
        bytes.push(3);
        t.iter().for_each(|&i| bytes.extend_from_slice(&(i as i32).to_le_bytes()));
    }
    write_ply_bytes(path, &bytes)
}

/// Writes a triangle mesh as Wavefront OBJ text, as [`write_ply_mesh`] takes it: `v x y z r g b`
/// (the vertex-colour extension MeshLab, Blender and Open3D read; colours in `[0, 1]`, clamped),
/// `vn nx ny nz`, and `f a//a b//b c//c` (1-based, counter-clockwise seen from outside). Written
/// under a temporary name and renamed; the error names the path.
///
/// # Panics
/// As [`write_ply_mesh`].
pub fn write_obj_mesh(
    path: &Path,
    positions: &[[f32; 3]],
    normals: &[[f32; 3]],
    colors: &[[f32; 3]],
    indices: &[u32],
) -> Result<(), DataError> {
    use std::fmt::Write as _;
    check_mesh(positions, normals, colors, indices);
    let mut text = String::with_capacity(64 * positions.len() + 32 * (indices.len() / 3));
    text.push_str("# written by nerf-rs\n");
    for (p, c) in positions.iter().zip(colors) {
        let c = c.map(|v| if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) });
        let _ = writeln!(text, "v {} {} {} {:.4} {:.4} {:.4}", p[0], p[1], p[2], c[0], c[1], c[2]);
    }
    for n in normals {
        let _ = writeln!(text, "vn {} {} {}", n[0], n[1], n[2]);
    }
    for t in indices.chunks_exact(3) {
        let [a, b, c] = [t[0] + 1, t[1] + 1, t[2] + 1];
        let _ = writeln!(text, "f {a}//{a} {b}//{b} {c}//{c}");
    }
    let tmp = path.with_extension("obj.tmp");
    std::fs::write(&tmp, text).map_err(|source| DataError::Io { path: tmp.clone(), source })?;
    std::fs::rename(&tmp, path).map_err(|source| DataError::Io { path: path.to_path_buf(), source })
}

/// The mesh writers' contract: one normal and colour per vertex, whole triangles of valid indices.
fn check_mesh(positions: &[[f32; 3]], normals: &[[f32; 3]], colors: &[[f32; 3]], indices: &[u32]) {
    assert!(normals.len() == positions.len() && colors.len() == positions.len(), "a mesh needs one normal and colour per vertex");
    assert!(indices.len().is_multiple_of(3) && indices.iter().all(|&i| (i as usize) < positions.len()), "a mesh's triangles index its vertices");
}

fn write_ply_bytes(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    let tmp = path.with_extension("ply.tmp");
    std::fs::write(&tmp, bytes).map_err(|source| DataError::Io { path: tmp.clone(), source })?;
    std::fs::rename(&tmp, path).map_err(|source| DataError::Io { path: path.to_path_buf(), source })
}

/// Writes an RGB f32 image (`3·W·H` values, row-major; clamped to `[0, 1]`, rounded to u8) as PNG,
/// creating the parent folder if needed; the error names the path.
///
/// # Panics
/// If `rgb.len() != 3·width·height`.
pub fn save_png(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<(), DataError> {
    assert_eq!(
        rgb.len(),
        3 * width as usize * height as usize,
        "save_png: rgb is not 3·W·H long"
    );
    let bytes: Vec<u8> = rgb.iter().map(|&v| to_u8(v)).collect();
    write_png(path, width, height, &bytes, image::ExtendedColorType::Rgb8)
}

/// Writes an `f32` RGBA image (`4·W·H` values in `[0, 1]`, straight alpha, clamped) as an 8-bit
/// RGBA PNG (`nerf render --alpha`). Errors name the file.
///
/// # Panics
/// If `rgba` is not `4·width·height` long.
pub fn save_png_rgba(path: &Path, width: u32, height: u32, rgba: &[f32]) -> Result<(), DataError> {
    assert_eq!(rgba.len(), 4 * width as usize * height as usize, "save_png_rgba: rgba is not 4·W·H long");
    let bytes: Vec<u8> = rgba.iter().map(|&v| to_u8(v)).collect();
    write_png(path, width, height, &bytes, image::ExtendedColorType::Rgba8)
}

/// Reads back an RGBA image [`save_png_rgba`] wrote: `4·W·H` values in `[0, 1]` (an RGB file's
/// alpha is 1). Errors name the file: missing, undecodable, or not `width × height`.
pub fn load_png_rgba(path: &Path, width: u32, height: u32) -> Result<Vec<f32>, DataError> {
    let (w, h, px) = decode_rgba(path)?;
    if (w, h) != (width, height) {
        return Err(DataError::InvalidValue { path: path.to_path_buf(), key: "size".into(), reason: format!("{w}x{h}, expected {width}x{height}") });
    }
    Ok(px)
}

/// Reads back an RGB image [`save_png`] wrote (`nerf render --resume`): `3·W·H` values in
/// `[0, 1]`, the alpha of an RGBA file dropped. Errors name the file: missing, undecodable, or
/// not `width × height`.
pub fn load_png_rgb(path: &Path, width: u32, height: u32) -> Result<Vec<f32>, DataError> {
    let px = load_png_rgba(path, width, height)?;
    Ok(px.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect())
}

/// A looping animated GIF written frame by frame (`nerf render --gif`): each frame quantised to
/// its own 256-colour palette (NeuQuant, the `image` crate's GIF encoder), so it is a preview,
/// not a lossless copy. The file is written under a temporary name and renamed into place by
/// [`GifWriter::finish`], so an interrupted render never leaves a truncated GIF behind.
pub struct GifWriter {
    enc: Option<image::codecs::gif::GifEncoder<SharedFile>>,
    file: SharedFile,
    tmp: PathBuf,
    path: PathBuf,
    width: u32,
    height: u32,
    delay: image::Delay,
    done: bool,
}

impl GifWriter {
    /// Starts `path` for frames of `width × height` shown at `fps` frames per second (GIF delays
    /// are in hundredths of a second, so the rate is rounded to one of those). Errors on a rate
    /// that is not positive and finite (naming `path`) and on I/O errors.
    pub fn create(path: &Path, width: u32, height: u32, fps: f32) -> Result<Self, DataError> {
        if !(fps.is_finite() && fps > 0.0) || width == 0 || height == 0 || width > 65535 || height > 65535 {
            let reason = format!("{width}x{height} frames at {fps} frames/s (need a positive rate and 1..=65535 pixels a side)");
            return Err(DataError::Encode {
                path: path.to_path_buf(),
                source: image::ImageError::Parameter(image::error::ParameterError::from_kind(
                    image::error::ParameterErrorKind::Generic(reason),
                )),
            });
        }
        let tmp = path.with_extension("gif.tmp");
        let file = std::fs::File::create(&tmp).map_err(|source| DataError::Io { path: tmp.clone(), source })?;
        let file = SharedFile(std::rc::Rc::new(std::cell::RefCell::new(std::io::BufWriter::new(file))));
        let mut enc = image::codecs::gif::GifEncoder::new_with_speed(file.clone(), 10);
        let encode = |source| DataError::Encode { path: path.to_path_buf(), source };
        enc.set_repeat(image::codecs::gif::Repeat::Infinite).map_err(encode)?;
        // Hundredths of a second per frame, at least 1.
        let centis = (100.0 / fps).round().max(1.0) as u32;
        Ok(Self {
            enc: Some(enc),
            file,
            tmp,
            path: path.to_path_buf(),
            width,
            height,
            delay: image::Delay::from_numer_denom_ms(10 * centis, 1),
            done: false,
        })
    }

    /// Appends one frame (`3·W·H` RGB values in `[0, 1]`, clamped).
    pub fn push(&mut self, rgb: &[f32]) -> Result<(), DataError> {
        assert_eq!(rgb.len(), 3 * self.width as usize * self.height as usize, "GifWriter::push: rgb is not 3·W·H long");
        // The encoder takes the frame's buffer, so there is nothing to reuse between frames.
        let rgba = rgb.chunks_exact(3).flat_map(|p| [to_u8(p[0]), to_u8(p[1]), to_u8(p[2]), 255]).collect();
        let img = image::RgbaImage::from_raw(self.width, self.height, rgba).expect("4·W·H bytes");
        let frame = image::Frame::from_parts(img, 0, 0, self.delay);
        let enc = self.enc.as_mut().expect("not finished");
        enc.encode_frame(frame).map_err(|source| DataError::Encode { path: self.path.clone(), source })
    }

    /// Writes the GIF trailer, flushes and syncs the file, and renames it into place.
    pub fn finish(mut self) -> Result<(), DataError> {
        use std::io::Write as _;
        // Dropping the encoder writes the trailer (into the buffer); the flush and sync below
        // report what writing it to disk met.
        drop(self.enc.take());
        let io = |source| DataError::Io { path: self.tmp.clone(), source };
        let mut f = self.file.0.borrow_mut();
        f.flush().map_err(io)?;
        f.get_ref().sync_all().map_err(io)?;
        drop(f);
        std::fs::rename(&self.tmp, &self.path).map_err(|source| DataError::Io { path: self.path.clone(), source })?;
        self.done = true;
        Ok(())
    }
}

/// The GIF's file, shared between the encoder (which owns its writer) and [`GifWriter::finish`]
/// (which flushes it and reports errors the encoder's drop would swallow).
#[derive(Clone)]
struct SharedFile(std::rc::Rc<std::cell::RefCell<std::io::BufWriter<std::fs::File>>>);

impl std::io::Write for SharedFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.borrow_mut().write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.0.borrow_mut().flush()
    }
}

impl Drop for GifWriter {
    fn drop(&mut self) {
        // Not finished (an error in between): leave no partial file.
        drop(self.enc.take());
        if !self.done {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Per-view colour gains for [`Dataset::scale_colors`]: each view and channel drawn uniformly
/// from `[1 − amount, 1 + amount]` with `seed`, then divided by the channel's mean over the views,
/// so that the gains average exactly 1 (the colours of views without a change).
///
/// # Panics
/// Unless `0 ≤ amount < 1`.
pub fn exposure_gains(n_views: usize, amount: f32, seed: u64) -> Vec<[f32; 3]> {
    use rand::Rng as _;
    assert!((0.0..1.0).contains(&amount), "exposure amount must lie in [0, 1), got {amount}");
    let mut rng = nerf_core::rng(seed, 0x6578_706f_7375_7265); // "exposure"
    let raw: Vec<[f32; 3]> = (0..n_views).map(|_| std::array::from_fn(|_| 1.0 + amount * (2.0 * rng.gen::<f32>() - 1.0))).collect();
    let mean: [f32; 3] = std::array::from_fn(|c| raw.iter().map(|g| g[c]).sum::<f32>() / n_views.max(1) as f32);
    raw.iter().map(|g| std::array::from_fn(|c| g[c] / mean[c])).collect()
}

/// Per-view pose changes for camera-refinement experiments ([`Dataset::perturb_poses`]): for
/// each view a translation with each axis drawn uniformly from `[−trans, trans]` (scene units)
/// and a rotation vector with each axis drawn from `[−rot_deg, rot_deg]` degrees (stored in
/// radians), with `seed`; then each of the six components has its mean over the views taken
/// out, so that the cameras do not move as a whole (a shift of all views together is no error
/// any method could see).
///
/// # Panics
/// Unless both amounts are finite and not negative.
pub fn pose_noise(n_views: usize, rot_deg: f32, trans: f32, seed: u64) -> Vec<[f32; 6]> {
    use rand::Rng as _;
    assert!(rot_deg.is_finite() && rot_deg >= 0.0 && trans.is_finite() && trans >= 0.0, "pose noise must be finite and ≥ 0, got {rot_deg}° and {trans}");
    let mut rng = nerf_core::rng(seed, 0x706f_7365_6e6f_6973); // "posenois"
    let rot = rot_deg.to_radians();
    let raw: Vec<[f32; 6]> = (0..n_views)
        .map(|_| std::array::from_fn(|i| (2.0 * rng.gen::<f32>() - 1.0) * if i < 3 { trans } else { rot }))
        .collect();
    let mean: [f32; 6] = std::array::from_fn(|i| raw.iter().map(|p| p[i]).sum::<f32>() / n_views.max(1) as f32);
    raw.iter().map(|p| std::array::from_fn(|i| p[i] - mean[i])).collect()
}

/// Writes a dataset back out in the Blender format: `out_root/transforms_<split>.json` with
/// `camera_angle_x` recomputed for the dataset's width (from the first camera's `fx`),
/// `frames[k] = { "file_path": "./<split>/r_<k>", "transform_matrix": 4×4 }`, and RGBA 8-bit PNGs
/// `out_root/<split>/r_<k>.png` (written in parallel). `attribution`, when given, becomes a
/// top-level `"attribution"` key. Used to derive small in-repo scenes from larger ones. A
/// dataset with training masks ([`Dataset::masks`]) writes them too: `"mask_path":
/// "./<split>/mask_<k>.png"`, 8-bit grey, 255 kept and 0 masked out; one with depth maps
/// ([`Dataset::depths`]) writes them as nerfstudio reads them: `"depth_file_path":
/// "./<split>/depth_<k>.png"`, 16-bit grey z-depths (0: none) in steps of the top-level
/// `depth_unit_scale_factor` (the largest depth / 65535). Intrinsics that the field
/// of view does not capture (`fy != fx`, a principal point off the image centre, views that
/// differ) are written as instant-ngp's `fl_x`, `fl_y`, `cx`, `cy`, `w`,
/// `h` (top level: the first view's; a frame whose camera differs carries its own, and its `w`,
/// `h` where its size differs: views of several sizes are written at their own), and an
/// instant-ngp scene's box ([`Dataset::ngp`]) as `aabb_scale`, `scale`, `offset`; a scene with
/// other bounds than NeRF's Blender ones (LLFF with Euclidean rays) gets the instant-ngp box that
/// encloses its [`Dataset::aabb`] ([`NgpBox::enclosing`]; its rays then start at that box's
/// near distance). Cameras with a lens ([`nerf_rays::Camera::distortion`]) write it as
/// instant-ngp's `is_fisheye`, `k1`, `k2`, `k3`, `k4`, `p1`, `p2` (top level: the first view's; a
/// frame whose lens differs carries its own), and their photos as loaded, distorted; a dataset
/// loaded with [`LoadOptions::undistort`] has pinhole cameras and resampled photos, and writes no
/// lens keys. A dataset in NDC is refused.
pub fn write_blender(
    ds: &Dataset,
    out_root: &Path,
    attribution: Option<&str>,
) -> Result<(), DataError> {
    if !ds.has_images() {
        return Err(DataError::InvalidValue {
            path: ds.root.clone(),
            key: "images".into(),
            reason: "the scene was loaded without its pixels (cameras_only): there are no images to write".into(),
        });
    }
    let split = ds.split.as_str();
    let tpath = out_root.join(ds.split.transforms_file());
    if let Some(m) = ds.masks.as_ref().filter(|m| m.n_views() != ds.n_views() || m.n_pixels() != ds.width * ds.height) {
        return Err(DataError::InvalidValue {
            path: ds.root.clone(),
            key: "masks".into(),
            reason: format!("masks of {} views of {} pixels for {} views of {}x{}", m.n_views(), m.n_pixels(), ds.n_views(), ds.width, ds.height),
        });
    }
    if let Some(reason) = ds.depths_mismatch() {
        return Err(DataError::InvalidValue { path: ds.root.clone(), key: "depths".into(), reason });
    }
    if ds.ndc.is_some() {
        return Err(DataError::InvalidValue {
            path: tpath,
            key: "ndc".into(),
            reason: "a scene loaded in NDC cannot be written as transforms; load it with Euclidean rays (ndc = false)"
                .into(),
        });
    }
    // Bounds other than NeRF's Blender ones (near 2, far 6, cube 1.5) travel as instant-ngp's box.
    let blender_bounds = ds.near == 2.0 && ds.far == 6.0 && ds.aabb == Aabb::cube(1.5);
    let ngp_box = ds.ngp.or_else(|| (!blender_bounds).then(|| NgpBox::enclosing(&ds.aabb)));
    let Some(first) = ds.cameras.first() else {
        return Err(DataError::EmptySplit {
            path: tpath,
            reason: "the dataset has no views to write".into(),
        });
    };
    let img_dir = out_root.join(split);
    std::fs::create_dir_all(&img_dir).map_err(|source| DataError::Io {
        path: img_dir.clone(),
        source,
    })?;
    // Masks are written when one drops a pixel of its view (not only the canvas past a smaller
    // view, which the file's sizes already leave out).
    let write_masks = ds.masks.as_ref().is_some_and(|m| {
        (0..ds.n_views()).any(|v| {
            let (w, h) = ds.view_size(v);
            m.kept(v).filter(|p| p % ds.width < w && p / ds.width < h).count() < (w * h) as usize
        })
    });
    // `camera_angle_x` alone gives `fy = fx`, the principal point at the centre, one camera model.
    let pixel_intrinsics = ds.cameras.iter().any(|c| {
        let k = &c.intrinsics;
        k != &first.intrinsics || k.fy != k.fx || k.cx != k.width as f32 * 0.5 || k.cy != k.height as f32 * 0.5
    });
    let lenses = ds.cameras.iter().any(|c| !c.distortion.is_identity());
    // A lens instant-ngp's keys do not hold names its `camera_model` in every frame: at the top
    // level that key would mark a file from nerfstudio, whose poses are normalised on loading.
    let named_lenses = lenses && ds.cameras.iter().any(|c| !ngp_lens(&c.distortion));
    let frames: Vec<Value> = ds
        .cameras
        .iter()
        .enumerate()
        .map(|(k, cam)| {
            let m = cam.c2w();
            let rows: Vec<Value> = m
                .iter()
                .map(|r| Value::Array(r.iter().map(|&v| Value::from(v as f64)).collect()))
                .collect();
            let mut f = serde_json::json!({
                "file_path": format!("./{split}/r_{k}"),
                "transform_matrix": rows,
            });
            if write_masks {
                f.as_object_mut().expect("a JSON object").insert("mask_path".into(), Value::from(format!("./{split}/mask_{k}.png")));
            }
            if ds.depths.is_some() {
                f.as_object_mut().expect("a JSON object").insert("depth_file_path".into(), Value::from(format!("./{split}/depth_{k}.png")));
            }
            if lenses && (named_lenses || cam.distortion != first.distortion) {
                let o = f.as_object_mut().expect("a JSON object");
                o.extend(lens_keys(&cam.distortion).into_iter().map(|(key, v)| (key.to_string(), v)));
            }
            if pixel_intrinsics && cam.intrinsics != first.intrinsics {
                let o = f.as_object_mut().expect("a JSON object");
                for (key, v) in focal_keys(&cam.intrinsics) {
                    o.insert(key.into(), Value::from(v));
                }
                if (cam.intrinsics.width, cam.intrinsics.height) != (first.intrinsics.width, first.intrinsics.height) {
                    o.insert("w".into(), Value::from(cam.intrinsics.width));
                    o.insert("h".into(), Value::from(cam.intrinsics.height));
                }
            }
            f
        })
        .collect();
    let mut top = serde_json::Map::new();
    if let Some(a) = attribution {
        top.insert("attribution".into(), Value::from(a));
    }
    top.insert(
        "camera_angle_x".into(),
        Value::from(first.intrinsics.fov_x()),
    );
    if pixel_intrinsics {
        let k = &first.intrinsics;
        for (key, v) in focal_keys(k) {
            top.insert(key.into(), Value::from(v));
        }
        top.insert("w".into(), Value::from(k.width));
        top.insert("h".into(), Value::from(k.height));
    }
    if lenses && !named_lenses {
        top.extend(lens_keys(&first.distortion).into_iter().map(|(key, v)| (key.to_string(), v)));
    }
    if let Some(b) = &ngp_box {
        top.insert("aabb_scale".into(), Value::from(b.aabb_scale as f64));
        top.insert("scale".into(), Value::from(b.scale as f64));
        top.insert("offset".into(), Value::from(b.offset.map(|o| o as f64).to_vec()));
    }
    // Depth maps back to z-depths (the pixel ray's distance times its cosine to the axis),
    // in 16-bit steps of the largest.
    let z_depths: Option<Vec<Vec<f32>>> = ds.depths.as_ref().map(|d| {
        d.par_iter()
            .zip(&ds.cameras)
            .enumerate()
            .map(|(v, (t, cam))| depth::z_depths(&ds.view_crop(v, 1, t), cam))
            .collect()
    });
    let z_step = z_depths.as_ref().map(|z| z.iter().flatten().fold(0.0f32, |a, &b| a.max(b)) as f64 / 65535.0);
    if let Some(step) = z_step {
        top.insert("depth_unit_scale_factor".into(), Value::from(if step > 0.0 { step } else { 1.0 }));
    }
    top.insert("frames".into(), Value::Array(frames));
    let text = serde_json::to_string_pretty(&Value::Object(top))
        .expect("serialising a JSON value cannot fail");
    std::fs::write(&tpath, text + "\n").map_err(|source| DataError::Io {
        path: tpath.clone(),
        source,
    })?;
    ds.images
        .par_iter()
        .enumerate()
        .map(|(k, img)| {
            let (w, h) = ds.view_size(k);
            let bytes: Vec<u8> = ds.view_crop(k, 4, &img.to_f32()).iter().map(|&v| to_u8(v)).collect();
            write_png(
                &img_dir.join(format!("r_{k}.png")),
                w,
                h,
                &bytes,
                image::ExtendedColorType::Rgba8,
            )?;
            if let (Some(z), Some(step)) = (&z_depths, z_step) {
                // 16-bit samples in native order (the encoder writes PNG's big-endian); a measured
                // depth is at least 1 step.
                let bytes: Vec<u8> = z[k]
                    .iter()
                    .flat_map(|&v| (if v > 0.0 { ((v as f64 / step).round() as u16).max(1) } else { 0 }).to_ne_bytes())
                    .collect();
                write_png(&img_dir.join(format!("depth_{k}.png")), w, h, &bytes, image::ExtendedColorType::L16)?;
            }
            match ds.masks.as_ref().filter(|_| write_masks) {
                Some(m) => write_png(
                    &img_dir.join(format!("mask_{k}.png")),
                    w,
                    h,
                    &ds.view_crop(k, 1, &m.view_bytes(k)),
                    image::ExtendedColorType::L8,
                ),
                None => Ok(()),
            }
        })
        .collect::<Vec<_>>()
        .into_iter()
        .collect()
}

/// Whether instant-ngp's keys hold the lens `d` (`is_fisheye`, `k1`..`k4`, `p1`, `p2`): OpenCV's
/// radial–tangential model without rational or thin-prism terms, or its fisheye without
/// tangential ones.
fn ngp_lens(d: &Distortion) -> bool {
    let [_, _, _, k4, k5, k6, p1, p2, s1, s2, s3, s4] = d.coefficients();
    let thin_prism = [s1, s2, s3, s4].iter().any(|&s| s != 0.0);
    match d.model {
        LensModel::RadialTangential => [k4, k5, k6].iter().all(|&k| k == 0.0) && !thin_prism,
        LensModel::Fisheye => k5 == 0.0 && k6 == 0.0 && p1 == 0.0 && p2 == 0.0 && !thin_prism,
        LensModel::Fisheye624 | LensModel::Fov | LensModel::Division | LensModel::Eucm => false,
    }
}

/// The keys of the lens `d`, every one written (zeros too, so that a frame's keys replace all
/// of the top level's): instant-ngp's `is_fisheye` and six coefficients where they hold it
/// ([`ngp_lens`]), else `camera_model` (`FULL_OPENCV`, `THIN_PRISM_FISHEYE`, `FISHEYE624`,
/// `FOV`, `DIVISION` or `EUCM`) and its coefficients (`FISHEYE624`'s as nerfstudio's
/// `distortion_params`, `FOV`'s `omega`, `DIVISION`'s `k1`, `EUCM`'s `alpha` and `beta`).
fn lens_keys(d: &Distortion) -> Vec<(&'static str, Value)> {
    if ngp_lens(d) {
        return vec![
            ("is_fisheye", Value::from(d.model == LensModel::Fisheye)),
            ("k1", Value::from(d.k1)),
            ("k2", Value::from(d.k2)),
            ("k3", Value::from(d.k3)),
            ("k4", Value::from(d.k4)),
            ("p1", Value::from(d.p1)),
            ("p2", Value::from(d.p2)),
        ];
    }
    let c = d.coefficients();
    match d.model {
        LensModel::Fov => vec![("camera_model", Value::from("FOV")), ("omega", Value::from(d.omega))],
        LensModel::Division => vec![("camera_model", Value::from("DIVISION")), ("k1", Value::from(d.k1))],
        LensModel::Eucm => vec![("camera_model", Value::from("EUCM")), ("alpha", Value::from(d.alpha)), ("beta", Value::from(d.beta))],
        LensModel::Fisheye624 => {
            // nerfstudio's order: k0..k5, p0 (OpenCV's p2), p1, s0..s3.
            let list: Vec<f64> = c[..6].iter().chain(&[c[7], c[6]]).chain(&c[8..]).copied().collect();
            vec![("camera_model", Value::from("FISHEYE624")), ("distortion_params", Value::from(list))]
        }
        model => {
            let name = if model == LensModel::Fisheye { "THIN_PRISM_FISHEYE" } else { "FULL_OPENCV" };
            std::iter::once(("camera_model", Value::from(name))).chain(COEFFICIENT_NAMES.iter().zip(c).map(|(k, v)| (*k, Value::from(v)))).collect()
        }
    }
}

/// instant-ngp's `fl_x`, `fl_y`, `cx`, `cy` of `k` (exact: `f32` → `f64`).
fn focal_keys(k: &nerf_rays::Intrinsics) -> [(&'static str, f64); 4] {
    [("fl_x", k.fx as f64), ("fl_y", k.fy as f64), ("cx", k.cx as f64), ("cy", k.cy as f64)]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// nerfstudio's eval modes: `fraction` as numpy's `linspace(0, N − 1, ⌈N·F⌉, dtype=int)` leaves
    /// out (the held-out indices printed by numpy 1.24 for these N and F), `interval` every K-th,
    /// `all` everything in both splits; the string forms round-trip and bad ones are refused.
    #[test]
    fn holdouts_split_as_nerfstudio() {
        let by_count = |h: Holdout, n: usize, s: Split| h.split(&vec![""; n], s).unwrap();
        let eval = |n: usize, f: f64| by_count(Holdout::Fraction(f), n, Split::Test);
        assert_eq!(eval(10, 0.9), [8]);
        assert_eq!(eval(25, 0.9), [11, 23]);
        assert_eq!(eval(100, 0.9), [9, 19, 29, 39, 49, 59, 69, 79, 89, 98]);
        assert_eq!(eval(37, 0.5), (1..36).step_by(2).collect::<Vec<_>>());
        assert_eq!(eval(7, 0.3), [1, 2, 4, 5]);
        let e300 = eval(300, 0.9);
        assert_eq!((e300.len(), e300[0], e300[28], e300[29]), (30, 9, 289, 298));
        for (n, f) in [(10, 0.9), (37, 0.5), (300, 0.9)] {
            let (tr, te) = (by_count(Holdout::Fraction(f), n, Split::Train), eval(n, f));
            assert_eq!(tr.len(), (n as f64 * f).ceil() as usize);
            let mut all: Vec<usize> = tr.into_iter().chain(te).collect();
            all.sort_unstable();
            assert_eq!(all, (0..n).collect::<Vec<_>>(), "each view in one split");
        }
        assert_eq!(by_count(Holdout::Interval(8), 20, Split::Test), [0, 8, 16]);
        assert_eq!(by_count(Holdout::Interval(8), 20, Split::Train).len(), 17);
        assert_eq!(by_count(Holdout::All, 5, Split::Test), by_count(Holdout::All, 5, Split::Train));
        for s in ["interval:8", "fraction:0.9", "all", "filename"] {
            assert_eq!(s.parse::<Holdout>().unwrap().to_string(), s);
        }
        // By name: `train` first (a name with both trains), then `eval`; neither is an error.
        let names = ["a_train", "b_eval", "c_train_eval", "d_eval"];
        assert_eq!(Holdout::Filename.split(&names, Split::Train).unwrap(), [0, 2]);
        assert_eq!(Holdout::Filename.split(&names, Split::Test).unwrap(), [1, 3]);
        assert!(Holdout::Filename.split(&["a_train", "b"], Split::Test).unwrap_err().contains("`b`"));
        assert_eq!(Holdout::Interval(2).split(&names, Split::Test).unwrap(), [0, 2]);
        for s in ["interval:1", "fraction:1", "fraction:0", "every:8", "fraction:x"] {
            assert!(s.parse::<Holdout>().unwrap_err().contains("invalid holdout"), "{s}");
        }
    }

    #[test]
    fn view_selection_parse_and_indices() {
        assert_eq!("all".parse::<ViewSelection>(), Ok(ViewSelection::All));
        assert_eq!(
            "every:8".parse::<ViewSelection>(),
            Ok(ViewSelection::Every(8))
        );
        assert_eq!(
            "first:5".parse::<ViewSelection>(),
            Ok(ViewSelection::First(5))
        );
        assert_eq!("spread:4".parse::<ViewSelection>(), Ok(ViewSelection::Spread(4)));
        assert_eq!(ViewSelection::Spread(4).indices(200).unwrap(), vec![0, 50, 100, 150]);
        assert_eq!(ViewSelection::Spread(3).indices(7).unwrap(), vec![0, 2, 4]);
        assert_eq!(ViewSelection::Spread(9).indices(3).unwrap(), vec![0, 1, 2]);
        assert!(ViewSelection::Spread(0).indices(3).is_err());
        for bad in ["every:0", "every", "first:x", "some:3", "", "every:-1", "spread:0"] {
            let e = bad.parse::<ViewSelection>().unwrap_err();
            assert!(
                e.contains("invalid view selection") && e.contains(bad),
                "{e}"
            );
        }
        assert_eq!(
            ViewSelection::Every(3).indices(10).unwrap(),
            vec![0, 3, 6, 9]
        );
        assert_eq!(ViewSelection::First(3).indices(2).unwrap(), vec![0, 1]);
        assert_eq!(ViewSelection::All.indices(3).unwrap(), vec![0, 1, 2]);
        assert!(ViewSelection::Every(0).indices(3).is_err());
        for s in ["all", "every:8", "first:5", "spread:4"] {
            assert_eq!(s.parse::<ViewSelection>().unwrap().to_string(), s);
        }
        assert_eq!("val".parse::<Split>(), Ok(Split::Val));
        assert!("validation".parse::<Split>().is_err());
    }

    #[test]
    fn box_downscale_of_known_pattern() {
        // 4x2 RGBA image, channel c of pixel (x,y) = 10y + x + 100c.
        let (w, h) = (4, 2);
        let px: Vec<f32> = (0..w * h * 4)
            .map(|i| {
                let (p, c) = (i / 4, i % 4);
                (10 * (p / w) + p % w + 100 * c) as f32
            })
            .collect();
        let d = downscale_rgba(&px, w, h, 2);
        assert_eq!(d.len(), 2 * 4);
        for c in 0..4 {
            let base = 100.0 * c as f32;
            assert_eq!(d[c], base + (0.0 + 1.0 + 10.0 + 11.0) / 4.0);
            assert_eq!(d[4 + c], base + (2.0 + 3.0 + 12.0 + 13.0) / 4.0);
        }
    }

    #[test]
    fn image_path_appends_png_only_without_extension() {
        let r = Path::new("/scene");
        assert_eq!(
            image_path(r, "./train/r_0"),
            Path::new("/scene/train/r_0.png")
        );
        assert_eq!(
            image_path(r, "train/r_0.jpg"),
            Path::new("/scene/train/r_0.jpg")
        );
    }
}
