//! The `nerf` command line as a library: [`main_with`] runs it with any field registry, so a
//! program that registers a field of its own gets every command of `nerf` (train, eval, render,
//! the exports, slim, fields, ablate) for that field without a fork of nerf-rs:
//!
//! ```no_run
//! // A program's `main`:
//! let mut registry = nerf::registry(); // the fields nerf-rs ships
//! // registry.register(my_field::registry_entry());
//! nerf_cli::main_with(&registry);
//! ```
//!
//! The `nerf` binary is exactly that with [`nerf::registry`]; `examples/custom-field` is a whole
//! program of this kind (docs/adding-a-field.md). Errors are reported at this edge with `anyhow`,
//! one line naming the file and the problem, exit code 1 (130 after Ctrl-C, with the checkpoint
//! saved, or a render's frames so far kept).

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use nerf::data::{load_scene, write_blender, CameraPathFile, LoadOptions, Split, ViewSelection};
use nerf::field::{merge_json, Registry};
use nerf::rays::Projection;
use nerf::train::{make_trainer, run, Checkpoint, RunOptions, SceneBounds, TrainConfig, TrainError};
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

#[derive(Parser)]
#[command(name = "nerf", version, about = "Neural radiance fields: train on posed images, render new views")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Train a field on a scene, evaluate it on held-out views, write metrics.json.
    Train(TrainArgs),
    /// Evaluate a trained run (its checkpoint) on a scene's test views.
    Eval(EvalArgs),
    /// Render novel views of a trained run along a path (an orbit around the scene, nerf-pytorch's
    /// spiral, a path through the test cameras, or a nerfstudio camera path), written as PNG frames.
    Render(RenderArgs),
    /// Write a reduced copy of a scene as transforms files (fewer views, lower resolution).
    ExportScene(ExportArgs),
    /// Export a coloured point cloud of a trained run as PLY (nerfstudio's `ns-export pointcloud`):
    /// where random training rays stop.
    ExportPoints(PointsArgs),
    /// Export the surface of a trained run as a coloured triangle mesh in PLY (instant-ngp's
    /// marching-cubes mesh): the isosurface of its density at a threshold, over the scene box.
    ExportMesh(MeshArgs),
    /// Write a render-only copy of a run's checkpoint into a new run folder: the weights renders
    /// use (the moving average for a run with `ema_decay`), the occupancy grid, no optimiser state.
    /// About a quarter of the checkpoint's size; `eval`, `render` and the exports read it as they
    /// read the run, training cannot resume from it.
    Slim(SlimArgs),
    /// List the registered fields and their default configs.
    Fields,
    /// Run an ablation file: a grid of runs with the same scenes, seeds and budget; writes
    /// results.csv, results.md and PSNR plots (finished runs are skipped on re-run).
    Ablate(AblateArgs),
}

#[derive(Args)]
struct AblateArgs {
    /// Ablation file (TOML; see examples/ablations/README.md).
    file: PathBuf,
    /// Output folder (default: `runs/ablate/NAME`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Where every run trains: auto (a hardware GPU when present), cpu, or gpu (any adapter,
    /// error without one). NERF_DEVICE overrides it.
    #[arg(long, default_value = "auto")]
    device: nerf::gpu::DevicePreference,
}

#[derive(Args)]
struct TrainArgs {
    /// Scene folder: Blender format (transforms_train.json, transforms_test.json), instant-ngp /
    /// nerfstudio (one transforms.json; every 8th frame is a test view), COLMAP (images/ and a
    /// sparse model in sparse/0/ or colmap/sparse/0/; every 8th image by name is a test view) or
    /// LLFF (poses_bounds.npy, images_K/; every 8th image is a test view).
    scene: PathBuf,
    /// Field to train (see `nerf fields`).
    #[arg(long)]
    field: Option<String>,
    /// Training config file (TOML or JSON): any key of the training config; flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Maximum training steps.
    #[arg(long)]
    iters: Option<u64>,
    /// Wall-clock budget for training, seconds.
    #[arg(long = "time-budget")]
    time_budget: Option<f64>,
    /// Image downscale factor (2 = half resolution; LLFF: picks images_K/, e.g. 8 for the
    /// NeRF paper's 504×378 fern; nerfstudio captures and COLMAP folders read their images_K/
    /// copies where every photo has one).
    #[arg(long)]
    downscale: Option<u32>,
    /// Forward-facing (LLFF) scenes: Euclidean rays instead of the paper's NDC (nerf-pytorch's
    /// --no_ndc); eval and render follow the run.
    #[arg(long = "no-ndc")]
    no_ndc: bool,
    /// Photos taken through a lens with distortion (k1 …, a fisheye): resample them to pinhole
    /// images when they load, instead of tracing rays through the lens; eval and render follow
    /// the run.
    #[arg(long)]
    undistort: bool,
    /// instant-ngp's `aabb_scale` in place of the scene file's: a box that reaches past the
    /// cameras, for captures of rooms and outdoor scenes (e.g. 16; a nerfstudio capture or a
    /// COLMAP folder trains in [-N, N]^3 about its normalised cameras), without editing the
    /// file; eval, render and the exports follow the run (config `aabb_scale`).
    #[arg(long = "aabb-scale", value_name = "N")]
    aabb_scale: Option<f32>,
    /// nerfstudio's dataparser `--orientation-method` for a nerfstudio capture or a COLMAP
    /// folder: `up` (the mean camera up vector onto +z, the default), `vertical` (the direction
    /// most nearly vertical in every image; cameras that look many ways) or `none` (the poses'
    /// own axes); eval, render and the exports follow the run (config `[nerfstudio]`).
    #[arg(long = "orientation-method", value_enum)]
    orientation_method: Option<OrientationArg>,
    /// nerfstudio's `--center-method`: `poses` (the mean camera centre at the origin, the
    /// default), `focus` (the point the cameras look at: inward-looking captures) or `none`.
    #[arg(long = "center-method", value_enum)]
    center_method: Option<CenterArg>,
    /// nerfstudio's `--auto-scale-poses False`: keep the poses' scale (times `--scale-factor`)
    /// instead of scaling the farthest camera coordinate to 1.
    #[arg(long = "no-auto-scale-poses")]
    no_auto_scale_poses: bool,
    /// nerfstudio's `--scale-factor`: a further scale of the poses [default: 1].
    #[arg(long = "scale-factor", value_name = "S")]
    scale_factor: Option<f64>,
    /// Which views of a scene without split files (one transforms.json, a COLMAP folder, an
    /// LLFF scene) are held out for testing, nerfstudio's `--eval-mode`: `interval:K` (every
    /// K-th), `fraction:F` (nerfstudio's default: the fraction F trains, evenly spread, e.g.
    /// `fraction:0.9`), `all` (every view trains and tests) or `filename` (images named with
    /// `train` train, those with `eval` test); frames taken in the order of their images' names
    /// [default: every 8th view in the file's order]. eval and render follow the run.
    #[arg(long, value_name = "interval:K|fraction:F|all|filename")]
    holdout: Option<nerf::data::Holdout>,
    /// Which loader reads the scene folder, as nerfstudio's dataparser names one: `transforms`
    /// (Blender, instant-ngp, nerfstudio), `llff` (poses_bounds.npy) or `colmap` (the sparse
    /// model, whatever else the folder holds: mip-NeRF 360's scenes, which hold LLFF's poses
    /// too) [default: auto, by what the folder holds]. eval and render follow the run.
    #[arg(long = "scene-format", value_enum)]
    scene_format: Option<FormatArg>,
    /// Output folder.
    #[arg(long, default_value = "runs/latest")]
    out: PathBuf,
    /// Master seed.
    #[arg(long)]
    seed: Option<u64>,
    /// Test views to evaluate: all, every:K, first:N, spread:N.
    #[arg(long = "test-views")]
    test_views: Option<ViewSelection>,
    /// Also score the field every N steps on a few test views (`--eval-views`; config
    /// `[eval_every]`): PSNR and SSIM to history.jsonl and the progress bar. Not counted as
    /// training time.
    #[arg(long = "eval-every", value_name = "N")]
    eval_every: Option<u64>,
    /// The test views `--eval-every` scores, among `--test-views` (default spread:4).
    #[arg(long = "eval-views", requires = "eval_every")]
    eval_views: Option<ViewSelection>,
    /// Also write the renders of each `--eval-every` evaluation, OUT/progress/step_NNNNNN/<view>.png
    /// (how the views looked at that step; config `[eval_every] renders = true`).
    #[arg(long = "eval-renders")]
    eval_renders: bool,
    /// Training views to use: all, every:K, first:N, spread:N.
    #[arg(long = "train-views", default_value = "all")]
    train_views: ViewSelection,
    /// Rays per training step.
    #[arg(long = "batch-rays")]
    batch_rays: Option<usize>,
    /// Continue from `OUT/checkpoint.bin`.
    #[arg(long)]
    resume: bool,
    /// Start over in an OUT that holds an interrupted run (by default that is an error, so that
    /// re-running a command after Ctrl-C does not discard the run; a finished run is replaced).
    #[arg(long, conflicts_with = "resume")]
    overwrite: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Do not write rendered test views.
    #[arg(long = "no-renders")]
    no_renders: bool,
    /// Where to train: auto (a hardware GPU when present and the field has a GPU twin, else the
    /// CPU), cpu, or gpu (any adapter, incl. a software one; error without one). NERF_DEVICE
    /// overrides it.
    #[arg(long, default_value = "auto")]
    device: nerf::gpu::DevicePreference,
}

#[derive(Args)]
struct SlimArgs {
    /// A run folder written by `nerf train` or `nerf ablate` (holds checkpoint.bin).
    run: PathBuf,
    /// The new run folder (created; it must not hold a checkpoint yet).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args)]
struct EvalArgs {
    /// A run folder written by `nerf train` (holds checkpoint.bin).
    run: PathBuf,
    /// Scene folder (Blender, instant-ngp / nerfstudio or LLFF format).
    scene: PathBuf,
    /// Views of the split to score: all, every:K, first:N, spread:N (default: the run's test views).
    #[arg(long = "test-views", visible_alias = "views")]
    test_views: Option<ViewSelection>,
    /// Which of the scene's splits to score: the held-out `test` views, or the `train` views the
    /// field was fitted to (rendered and scored the same way; the gap between the two separates
    /// fit from generalisation).
    #[arg(long, value_enum, default_value = "test")]
    split: EvalSplit,
    /// Where to write renders and eval.json (default: `RUN/eval`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Where to render: auto, cpu or gpu (as `train --device`).
    #[arg(long, default_value = "auto")]
    device: nerf::gpu::DevicePreference,
    /// Rays per pixel, averaged (supersampling; instant-ngp scores its test views with 8)
    /// [default: the run's `eval_spp`, 1 unless set].
    #[arg(long)]
    spp: Option<u32>,
    /// Pixel filter the `--spp` rays are placed by: `box` (the pixel's square), or
    /// `blackman-harris[:WIDTH]` (Blender Cycles' film filter, the ground truth's of the NeRF
    /// synthetic scenes; WIDTH is Cycles' filter width, 1.5 pixels by default, and the window
    /// spans ±WIDTH) [default: the run's `eval_filter`, box unless set].
    #[arg(long, value_parser = parse_pixel_filter)]
    filter: Option<nerf::rays::PixelFilter>,
    /// Background the renders and the ground truth are composited on: white (the NeRF paper's
    /// protocol) or black (instant-ngp's) [default: the run's `eval_background`, white unless set].
    #[arg(long)]
    background: Option<EvalBackground>,
    /// Marching step of the renders, in place of the run's `render_step_size` (itself the
    /// training step, `sampler.step_size`, unless set; occupancy sampler only): the sample cap
    /// per ray grows in proportion and the grid is the one the run trained.
    #[arg(long)]
    step_size: Option<f32>,
}

/// The colours of `nerf render --depth` maps (`--depth-colormap`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum DepthColormap {
    /// Near bright, far dark.
    Gray,
    /// Google's Turbo, near blue, far red (nerfstudio's).
    Turbo,
}

/// Where `nerf render --aperture` focuses (`--focus`).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Focus {
    /// On what the middle of each frame shows.
    Auto,
    /// This far in front of the camera.
    Distance(f32),
}

fn parse_focus(s: &str) -> Result<Focus, String> {
    match s {
        "auto" => Ok(Focus::Auto),
        _ => s.parse().map(Focus::Distance).map_err(|_| format!("`{s}` is neither a distance nor `auto`")),
    }
}

/// `nerf eval --filter`: `box`, `blackman-harris` or `blackman-harris:WIDTH`.
fn parse_pixel_filter(s: &str) -> Result<nerf::rays::PixelFilter, String> {
    use nerf::rays::PixelFilter;
    let f = match s.split_once(':') {
        None if s == "box" => PixelFilter::Box,
        None if s == "blackman-harris" => PixelFilter::BlackmanHarris { width: 1.5 },
        Some(("blackman-harris", w)) => {
            PixelFilter::BlackmanHarris { width: w.parse().map_err(|_| format!("`{w}` is not a width in pixels"))? }
        }
        _ => return Err(format!("`{s}` is not a pixel filter: box, blackman-harris or blackman-harris:WIDTH")),
    };
    f.validate()?;
    Ok(f)
}

/// The split `nerf eval` scores (`--split`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum EvalSplit {
    /// The held-out test views (the usual evaluation).
    Test,
    /// The training views.
    Train,
}

impl EvalSplit {
    fn split(self) -> Split {
        match self {
            EvalSplit::Test => Split::Test,
            EvalSplit::Train => Split::Train,
        }
    }

    fn name(self) -> &'static str {
        match self {
            EvalSplit::Test => "test",
            EvalSplit::Train => "train",
        }
    }
}

/// The fixed backgrounds a test view can be scored on (`nerf eval --background`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum EvalBackground {
    /// White (1, 1, 1): the NeRF paper's numbers.
    White,
    /// Black (0, 0, 0): instant-ngp's paper's numbers.
    Black,
}

impl From<EvalBackground> for nerf::data::Background {
    fn from(b: EvalBackground) -> Self {
        match b {
            EvalBackground::White => nerf::data::Background::White,
            EvalBackground::Black => nerf::data::Background::Black,
        }
    }
}

#[derive(Args)]
struct RenderArgs {
    /// A run folder written by `nerf train` (holds checkpoint.bin).
    run: PathBuf,
    /// The scene the run was trained on: its cameras define the path (see `--path`).
    scene: PathBuf,
    /// Frames of the path (evenly spaced) [default: 60; along an instant-ngp camera path, 60 a
    /// second of it].
    #[arg(long)]
    frames: Option<usize>,
    /// The path: `orbit` (a turntable at the training cameras' distance and elevation around
    /// the point they look at, or the scene box's centre), `spiral` (nerf-pytorch's, for LLFF scenes), `interpolate` (nerfstudio's: through
    /// the run's test views in order, positions lerped and rotations slerped), or `auto`:
    /// spiral for LLFF scenes, orbit otherwise.
    #[arg(long, value_enum, default_value = "auto", conflicts_with = "camera_path")]
    path: PathKind,
    /// Render along this camera path instead: a nerfstudio `camera_path.json` (what its viewer
    /// exports; poses in the frame of the scene's cameras, see docs/formats.md), or an
    /// instant-ngp `base_cam.json` (what its camera-path editor saves; keyframes in instant-ngp's
    /// space, splined as instant-ngp does, `--frames` frames or 60 a second of the path). Every
    /// render writes the path it took in nerfstudio's format and, where it can, instant-ngp's,
    /// to edit and render again.
    #[arg(long = "camera-path", value_name = "FILE")]
    camera_path: Option<PathBuf>,
    /// What a frame is: `perspective` (a pinhole camera with the training views' intrinsics),
    /// `fisheye` (nerfstudio's equidistant fisheye with those intrinsics: as wide in focal lengths,
    /// but in angle) or `equirectangular` (nerfstudio's 360° panorama from the path's camera,
    /// twice as wide as high: twice the training images' height unless `--width`). A camera path
    /// file names its own.
    #[arg(long = "camera-type", value_enum, default_value = "perspective", conflicts_with = "camera_path")]
    camera_type: CameraType,
    /// Frame width in pixels (default: the training images', or the camera path's); the height
    /// keeps the aspect.
    #[arg(long)]
    width: Option<u32>,
    /// Where to write frame_0000.png, …, render.json, camera_path.json and (perspective frames
    /// of a scene instant-ngp reads) base_cam.json (default: `RUN/render`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Also write depth_0000.png, …: expected depth, near bright and far dark (`--depth-colormap`),
    /// over the range of the first frame's surfaces (1st to 99th percentile; NDC scenes: NDC
    /// depth, i.e. disparity).
    #[arg(long)]
    depth: bool,
    /// Colours of the `--depth` maps: `gray` (near bright, far dark, black where nothing is) or
    /// `turbo` (nerfstudio's: Google's Turbo colormap, near blue, far red, over the background).
    #[arg(long = "depth-colormap", value_enum, default_value = "gray", requires = "depth")]
    depth_colormap: DepthColormap,
    /// The depths the `--depth` maps span, `NEAR,FAR` (scene units along the ray; NDC runs: NDC
    /// depth), as nerfstudio's `--depth-near-plane` and `--depth-far-plane`: nearer is drawn as
    /// NEAR, farther as FAR. By default the range of the first frame's surfaces.
    #[arg(long = "depth-range", value_name = "NEAR,FAR", value_parser = parse_range, requires = "depth", allow_hyphen_values = true)]
    depth_range: Option<(f32, f32)>,
    /// Continue a render that was interrupted (Ctrl-C) in `--out`: the frames its render.json
    /// counts are kept, and rendering goes on from the next. The command must be the one that
    /// started it (the same path, frame size, rays per pixel, lens and shutter); anything else is refused.
    #[arg(long)]
    resume: bool,
    /// Also write normal_0000.png, …: the surface normal where each pixel's ray stops, from the
    /// density's gradient (central differences a pixel's footprint there apart), as `(n + 1)/2`
    /// in world axes (x red, y green, z blue) over the background (instant-ngp's Normals view,
    /// nerfstudio's `normals` output). Not for NDC runs.
    #[arg(long)]
    normals: bool,
    /// Also write the frames as one looping animated GIF, `render.gif`, shown at FPS frames per
    /// second (each frame in 256 colours: a preview to share; the PNGs keep full colour).
    #[arg(long, value_name = "FPS")]
    gif: Option<f32>,
    /// Write the frames as RGBA PNGs with a transparent background (nerfstudio's `rgba`
    /// output, instant-ngp's screenshots): the field's own colour, with its opacity as alpha,
    /// to composite over anything (with `--crop`, a cut-out of the scene). The GIF, depth and
    /// normal images still show the background.
    #[arg(long)]
    alpha: bool,
    /// Where to render: auto, cpu or gpu (as `train --device`).
    #[arg(long, default_value = "auto")]
    device: nerf::gpu::DevicePreference,
    /// For a run trained with `[color_correction]`: render with training view N's colour
    /// correction (how that photo was exposed) instead of the mean of all views'.
    #[arg(long, value_name = "N")]
    appearance: Option<usize>,
    /// Marching step of the frames, in place of the run's `render_step_size` (itself the
    /// training step unless set; occupancy sampler only), as `nerf eval --step-size`.
    #[arg(long)]
    step_size: Option<f32>,
    /// Rays per pixel, averaged: anti-aliased frames (instant-ngp renders its videos with 8),
    /// at that many times the render time. The rays go through a lattice of points over each
    /// pixel, as `nerf eval --spp` places them [default: 1, the pixel's centre].
    #[arg(long, default_value_t = 1)]
    spp: u32,
    /// Pixel filter the `--spp` rays are placed by, as `nerf eval --filter` [default: the run's
    /// `eval_filter`, box unless set].
    #[arg(long, value_parser = parse_pixel_filter)]
    filter: Option<nerf::rays::PixelFilter>,
    /// Depth of field: the radius of a thin lens, in scene units (instant-ngp's
    /// `aperture_size`). Rays leave points of the lens and meet on the plane `--focus` in front
    /// of the camera; what lies off it blurs. Each pixel's `--spp` rays take their own lens
    /// points: use 8 or more, or the frames are noisy. An instant-ngp camera path's own lens is
    /// used unless this is given (`--aperture 0`: none).
    #[arg(long, value_name = "RADIUS")]
    aperture: Option<f32>,
    /// Distance of the plane in focus in front of the camera, in scene units, or `auto`: for each
    /// frame, what the middle of the frame shows (the median depth of its central 5x5 pixels'
    /// rays that reach a surface, as a camera's autofocus) [default: for each frame, how far in
    /// front of its camera the point the path looks at lies (the orbit's centre); for an LLFF
    /// scene, the focus depth of nerf-pytorch's spiral].
    #[arg(long, value_name = "DISTANCE|auto", requires = "aperture", value_parser = parse_focus)]
    focus: Option<Focus>,
    /// Motion blur: the fraction of a frame's time the shutter stays open, from the frame's
    /// camera towards the next frame's (instant-ngp's `run.py` renders with 0.5). Each pixel's
    /// `--spp` rays are cast at their own moments: use 8 or more [default: 0, no blur].
    #[arg(long, value_name = "FRACTION", default_value_t = 0.0)]
    shutter: f32,
    /// Render only what lies in this box, `x0,y0,z0,x1,y1,z1` in the scene's coordinates (as
    /// `export-mesh --box`): every ray is clipped to it, the rest is background (instant-ngp's
    /// render box, nerfstudio's viewer crop). A nerfstudio camera path's own `crop` (an oriented
    /// box and its background colour) is used unless this is given. Not for NDC runs.
    #[arg(long, value_parser = parse_box, allow_hyphen_values = true)]
    crop: Option<([f32; 3], [f32; 3])>,
}

#[derive(Args)]
struct PointsArgs {
    /// A run folder written by `nerf train` (holds checkpoint.bin).
    run: PathBuf,
    /// The scene the run was trained on (its training cameras cast the rays).
    scene: PathBuf,
    /// Points to export.
    #[arg(long, default_value_t = 1_000_000)]
    points: usize,
    /// Keep a ray's point only when its opacity is at least this (0 to 1).
    #[arg(long = "min-opacity", default_value_t = 0.5)]
    min_opacity: f32,
    /// Where to write the PLY file (default: `RUN/points.ply`).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Seed of the random rays.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Where to render: auto, cpu or gpu (as `train --device`).
    #[arg(long, default_value = "auto")]
    device: nerf::gpu::DevicePreference,
    /// Export only the part of the scene in this box, `x0,y0,z0,x1,y1,z1` in the scene's
    /// coordinates: the rays are rendered cropped to it (what lies outside neither shows nor
    /// hides anything) and only points inside are kept (nerfstudio's `--obb-*` crop).
    #[arg(long, value_parser = parse_box, allow_hyphen_values = true)]
    crop: Option<([f32; 3], [f32; 3])>,
}

#[derive(Args)]
struct MeshArgs {
    /// A run folder written by `nerf train` (holds checkpoint.bin).
    run: PathBuf,
    /// The scene the run was trained on (its box and units).
    scene: PathBuf,
    /// Lattice nodes along the box's longest side (as many per unit length along the others), at
    /// most 1024; memory is about 13 bytes per node (220 MB at 256, 1.7 GB at 512).
    #[arg(long, default_value_t = 256)]
    resolution: u32,
    /// Density at the surface, per instant-ngp scene unit (the scene's own unit for instant-ngp
    /// and nerfstudio scenes; the box's longest side otherwise, as instant-ngp's 0.33 scale
    /// makes it for Blender scenes). instant-ngp's default is 2.5.
    #[arg(long, default_value_t = 2.5)]
    threshold: f32,
    /// The box to mesh, `x0,y0,z0,x1,y1,z1` in the scene's coordinates (clipped to the scene's
    /// box). Default: the scene's box; for an instant-ngp box with `aabb_scale` > 1, its unit cube
    /// (where instant-ngp puts the object, its finest occupancy level).
    #[arg(long = "box", value_parser = parse_box, allow_hyphen_values = true)]
    mesh_box: Option<([f32; 3], [f32; 3])>,
    /// Where to write the mesh (default: `RUN/mesh.ply`): binary PLY for `.ply`, Wavefront OBJ
    /// for `.obj`.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Evaluate the density in the whole box. By default a run with an occupancy grid counts the
    /// cells its grid marks empty (never seen by a training camera, or empty at the last refresh)
    /// as empty space, which drops the floaters no camera constrained.
    #[arg(long = "no-grid-mask")]
    no_grid_mask: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Where to evaluate the field: auto, cpu or gpu (as `train --device`).
    #[arg(long, default_value = "auto")]
    device: nerf::gpu::DevicePreference,
}

/// `nerf train --orientation-method`.
#[derive(Clone, Copy, clap::ValueEnum)]
enum OrientationArg {
    Up,
    Vertical,
    None,
}

/// `--scene-format`: `nerf_data::SceneFormat`.
#[derive(Clone, Copy, clap::ValueEnum)]
enum FormatArg {
    Auto,
    Transforms,
    Llff,
    Colmap,
}

impl From<FormatArg> for nerf::data::SceneFormat {
    fn from(f: FormatArg) -> Self {
        match f {
            FormatArg::Auto => Self::Auto,
            FormatArg::Transforms => Self::Transforms,
            FormatArg::Llff => Self::Llff,
            FormatArg::Colmap => Self::Colmap,
        }
    }
}

/// `nerf train --center-method`.
#[derive(Clone, Copy, clap::ValueEnum)]
enum CenterArg {
    Poses,
    Focus,
    None,
}

/// `x0,y0,z0,x1,y1,z1`: a box with `x0 < x1`, `y0 < y1`, `z0 < z1`.
fn parse_box(s: &str) -> Result<([f32; 3], [f32; 3]), String> {
    let v: Vec<f32> = s.split(',').map(|x| x.trim().parse::<f32>().map_err(|e| format!("`{x}`: {e}"))).collect::<Result<_, _>>()?;
    if v.len() != 6 || v.iter().any(|x| !x.is_finite()) {
        return Err(format!("expected six finite numbers x0,y0,z0,x1,y1,z1, got `{s}`"));
    }
    let (lo, hi) = ([v[0], v[1], v[2]], [v[3], v[4], v[5]]);
    if (0..3).any(|a| lo[a] >= hi[a]) {
        return Err(format!("an empty box: {lo:?} to {hi:?}"));
    }
    Ok((lo, hi))
}

/// `near,far`: two finite numbers with `near < far`.
fn parse_range(s: &str) -> Result<(f32, f32), String> {
    let v: Vec<f32> = s.split(',').map(|x| x.trim().parse::<f32>().map_err(|e| format!("`{x}`: {e}"))).collect::<Result<_, _>>()?;
    match v[..] {
        [near, far] if near.is_finite() && far.is_finite() && near < far => Ok((near, far)),
        _ => Err(format!("expected two finite numbers NEAR,FAR with NEAR < FAR, got `{s}`")),
    }
}

/// The frames of `nerf render` (nerfstudio's camera types).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum CameraType {
    /// A pinhole camera.
    Perspective,
    /// An equidistant fisheye.
    Fisheye,
    /// A 360° panorama.
    Equirectangular,
}

/// The generated camera paths of `nerf render`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum PathKind {
    /// Spiral for LLFF scenes, orbit otherwise.
    Auto,
    /// A turntable orbit.
    Orbit,
    /// nerf-pytorch's spiral (LLFF scenes).
    Spiral,
    /// Through the test cameras (nerfstudio's `interpolate`).
    Interpolate,
}

#[derive(Args)]
struct ExportArgs {
    /// Source scene (Blender, instant-ngp / nerfstudio, COLMAP, or LLFF: written with Euclidean rays and
    /// the instant-ngp box around its scene bounds).
    src: PathBuf,
    /// Destination folder.
    dst: PathBuf,
    /// Downscale factor.
    #[arg(long, default_value_t = 8)]
    downscale: u32,
    /// Which loader reads SRC (as `train --scene-format`).
    #[arg(long = "scene-format", value_enum, default_value = "auto")]
    scene_format: FormatArg,
    /// Training views to keep.
    #[arg(long = "train-views", default_value = "all")]
    train_views: ViewSelection,
    /// Test views to keep.
    #[arg(long = "test-views", default_value = "every:8")]
    test_views: ViewSelection,
    /// Attribution text stored in the JSON files.
    #[arg(long)]
    attribution: Option<String>,
    /// Changes each training view's exposure and white balance, for experiments with
    /// `color_correction`: colours times per-view, per-channel gains drawn from [1 − X, 1 + X]
    /// and normalised to a mean of 1 (values over 1 clip in the 8-bit images). Test views are
    /// kept; the gains go to `exposure_gains.json`.
    #[arg(long = "exposure-jitter", value_name = "X")]
    exposure_jitter: Option<f32>,
    /// Moves each training view's camera by a rotation with each axis drawn from
    /// [−DEG, DEG] degrees (about the camera centre, in world axes), for experiments with
    /// `camera_optimizer`; with `--pose-noise-trans` also shifts it. Zero mean over the views;
    /// test views are kept; the changes go to `pose_noise.json`.
    #[arg(long = "pose-noise-rot", value_name = "DEG")]
    pose_noise_rot: Option<f32>,
    /// Shifts each training view's camera centre by up to UNITS (scene units) per axis (see
    /// `--pose-noise-rot`).
    #[arg(long = "pose-noise-trans", value_name = "UNITS")]
    pose_noise_trans: Option<f32>,
    /// Seed of the `--exposure-jitter` gains and the `--pose-noise-*` changes.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// A COLMAP folder's reconstruction points written as sparse depth maps
    /// (`depth_file_path`, as `depth_loss` trains on them; see docs/formats.md, "Depth maps"),
    /// for depth-nerfacto or a later `nerf train`.
    #[arg(long = "sfm-depth")]
    sfm_depth: bool,
    /// Photos taken through a lens with distortion are written resampled to pinhole images, with
    /// no lens keys (for tools that take only pinhole cameras); without it they are written as
    /// taken, with their lenses.
    #[arg(long)]
    undistort: bool,
    /// A run's `camera_corrections.json` (`[camera_optimizer]`): each training view is written
    /// with the pose the run refined for it (matched by image name), as nerfstudio's
    /// `ns-export cameras` exports optimised poses, for other tools to train on.
    #[arg(long = "camera-corrections", value_name = "FILE", conflicts_with_all = ["pose_noise_rot", "pose_noise_trans"])]
    camera_corrections: Option<PathBuf>,
}

/// Runs the command line on this process's arguments with `registry`'s fields, then returns; a
/// failed command prints one line (`error: …`) and exits with code 1, or 130 after Ctrl-C (the
/// checkpoint or the frames so far kept). Usage errors, `--help` and `--version` are clap's.
pub fn main_with(registry: &Registry) {
    let cli = Cli::parse();
    if let Err(e) = dispatch(cli, registry) {
        eprintln!("error: {}", error_line(&e));
        std::process::exit(if is_interrupted(&e) { 130 } else { 1 });
    }
}

/// Parses `args` (the program's name first, as `std::env::args_os` gives them) and runs the
/// command with `registry`'s fields, in this process: what [`main_with`] does, with the error
/// returned instead of printed (a usage error or `--help` as clap's error). For tests and for
/// programs that drive several commands. The first command that can be stopped by Ctrl-C (`train`,
/// `render`) installs the process's handler; from then on Ctrl-C stops such commands and no longer
/// ends the process.
pub fn run_with<I, T>(registry: &Registry, args: I) -> Result<()>
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    dispatch(Cli::try_parse_from(args)?, registry)
}

/// Whether `e` is a command stopped by Ctrl-C (exit code 130): a training run (its checkpoint
/// saved) or a render (its frames so far kept).
pub fn is_interrupted(e: &anyhow::Error) -> bool {
    e.downcast_ref::<TrainError>().is_some_and(|t| matches!(t, TrainError::Interrupted { .. }))
        || e.downcast_ref::<RenderInterrupted>().is_some()
}

fn dispatch(cli: Cli, registry: &Registry) -> Result<()> {
    match cli.command {
        Command::Train(a) => cmd_train(a, registry),
        Command::Eval(a) => cmd_eval(a, registry),
        Command::Render(a) => cmd_render(a, registry),
        Command::ExportScene(a) => cmd_export(a),
        Command::ExportPoints(a) => cmd_export_points(a, registry),
        Command::ExportMesh(a) => cmd_export_mesh(a, registry),
        Command::Slim(a) => cmd_slim(a),
        Command::Fields => cmd_fields(registry),
        Command::Ablate(a) => cmd_ablate(a, registry),
    }
}

/// The process's Ctrl-C flag, cleared for the command about to start. A process can install one
/// handler, so it is installed on the first call and every later command (of [`run_with`]) shares it.
fn ctrl_c_flag() -> Result<Arc<AtomicBool>> {
    static FLAG: Mutex<Option<Arc<AtomicBool>>> = Mutex::new(None);
    let mut slot = FLAG.lock().unwrap_or_else(|poisoned| poisoned.into_inner());
    let flag = match slot.as_ref() {
        Some(flag) => flag.clone(),
        None => {
            let flag = Arc::new(AtomicBool::new(false));
            let handler_flag = flag.clone();
            ctrlc::set_handler(move || handler_flag.store(true, Ordering::SeqCst)).context("installing the Ctrl-C handler")?;
            slot.insert(flag).clone()
        }
    };
    flag.store(false, Ordering::SeqCst);
    Ok(flag)
}

/// One line for an error and its causes, `outer: cause: …`, as `{e:#}` writes it, but without a
/// cause whose text the line already holds: the libraries' errors (thiserror) write their source
/// into their own message, e.g. "lego/transforms_train.json: malformed JSON: expected value at
/// line 1 column 5", where the plain chain would repeat the parser's message.
fn error_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if line.is_empty() {
            line = text;
        } else if !text.is_empty() && !line.contains(&text) {
            line.push_str(": ");
            line.push_str(&text);
        }
    }
    line
}

/// Reads a TOML or JSON file into a JSON value (TOML when the extension is .toml).
fn read_config_file(path: &Path) -> Result<serde_json::Value> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}: cannot read config", path.display()))?;
    if path.extension().is_some_and(|e| e == "toml") {
        toml::from_str(&text).with_context(|| format!("{}: malformed TOML", path.display()))
    } else {
        serde_json::from_str(&text).with_context(|| format!("{}: malformed JSON", path.display()))
    }
}

/// defaults ← field preset ← config file ← command-line flags.
fn build_config(a: &TrainArgs, registry: &Registry) -> Result<TrainConfig> {
    let file = match &a.config {
        Some(p) => read_config_file(p)?,
        None => serde_json::Value::Null,
    };
    let field = a
        .field
        .clone()
        .or_else(|| file.get("field").and_then(|f| f.as_str()).map(str::to_string))
        .unwrap_or_else(|| TrainConfig::default().field);
    let entry = registry.get(&field)?;
    let mut v = serde_json::to_value(TrainConfig::default())?;
    merge_json(&mut v, &(entry.train_preset)());
    merge_json(&mut v, &file);
    let mut c: TrainConfig = serde_json::from_value(v).with_context(|| match &a.config {
        Some(p) => format!("{}: invalid training config", p.display()),
        None => "invalid training config".to_string(),
    })?;
    c.field = field;
    if let Some(x) = a.iters {
        c.iters = x;
    }
    if a.time_budget.is_some() {
        c.time_budget_secs = a.time_budget;
    }
    if let Some(x) = a.downscale {
        c.downscale = x;
    }
    if a.no_ndc {
        c.ndc = false;
    }
    if let Some(s) = a.aabb_scale {
        c.aabb_scale = Some(s);
    }
    if let Some(m) = a.orientation_method {
        c.nerfstudio.orientation_method = match m {
            OrientationArg::Up => nerf::data::OrientationMethod::Up,
            OrientationArg::Vertical => nerf::data::OrientationMethod::Vertical,
            OrientationArg::None => nerf::data::OrientationMethod::None,
        };
    }
    if let Some(m) = a.center_method {
        c.nerfstudio.center_method = match m {
            CenterArg::Poses => nerf::data::CenterMethod::Poses,
            CenterArg::Focus => nerf::data::CenterMethod::Focus,
            CenterArg::None => nerf::data::CenterMethod::None,
        };
    }
    if a.no_auto_scale_poses {
        c.nerfstudio.auto_scale_poses = false;
    }
    if let Some(f) = a.scale_factor {
        c.nerfstudio.scale_factor = f;
    }
    if let Some(h) = a.holdout {
        c.holdout = Some(h);
    }
    if let Some(f) = a.scene_format {
        c.scene_format = f.into();
    }
    if a.undistort {
        c.undistort = true;
    }
    if let Some(x) = a.seed {
        c.seed = x;
    }
    if let Some(x) = &a.test_views {
        c.test_views = x.clone();
    }
    if let Some(x) = a.batch_rays {
        c.batch_rays = x;
    }
    if let Some(steps) = a.eval_every {
        let views = a.eval_views.clone().or_else(|| c.eval_every.as_ref().map(|e| e.views.clone())).unwrap_or(ViewSelection::Spread(4));
        let renders = c.eval_every.as_ref().is_some_and(|e| e.renders);
        c.eval_every = Some(nerf::train::config::PeriodicEval { steps, views, renders });
    }
    if a.eval_renders {
        match c.eval_every.as_mut() {
            Some(e) => e.renders = true,
            None => bail!("--eval-renders writes the renders of the evaluations during the run: it needs --eval-every N (or [eval_every] in the config)"),
        }
    }
    c.validate().map_err(|e| match &a.config {
        Some(p) => anyhow::anyhow!("invalid training config ({} and the command-line flags): {e}", p.display()),
        None => anyhow::anyhow!("invalid training config: {e}"),
    })?;
    Ok(c)
}

/// The longest side nerfstudio trains photos at unless told otherwise (its `MAX_AUTO_RESOLUTION`).
const LARGE_PHOTO: u32 = 1600;

/// A hint for training views past [`LARGE_PHOTO`] pixels on a side at `--downscale 1`: the
/// factor that brings them under it, as nerfstudio picks one (a power of two).
fn large_photos_note(train: &nerf::data::Dataset, downscale: u32) -> Option<String> {
    let side = (0..train.n_views()).map(|i| train.view_size(i)).map(|(w, h)| w.max(h)).max()?;
    if downscale != 1 || side <= LARGE_PHOTO {
        return None;
    }
    let k = (1..).map(|n| 1u32 << n).find(|k| side / k <= LARGE_PHOTO).expect("a power of two brings any side under it");
    // Held as loaded (`nerf_data::Pixels`: 4 bytes a pixel of an 8-bit photo, 8 of a 16-bit
    // one), and downscaled, as box averages, in 16 bits.
    let gb = train.images.iter().map(|p| p.size_in_bytes() as f64).sum::<f64>() / 1e9;
    let down = train.n_views() as f64 * train.width as f64 * train.height as f64 * 8.0 / 1e9 / (k * k) as f64;
    Some(format!(
        "the photos are up to {side} pixels on a side ({gb:.1} GB as loaded); nerfstudio trains such captures at \
         {LARGE_PHOTO} or less: --downscale {k} (or `downscale = {k}` in the config) would take {down:.2} GB and train faster"
    ))
}

/// What a run in an instant-ngp box with `aabb_scale` > 1 does about the box: cone steps and a
/// cascade of occupancy grids (picked by the scene unless the config sets them), or, with another
/// sampler, what instant-ngp would use. (A grid field scales its finest resolution with the box
/// itself: `FieldContext::scene_scale`.)
fn large_box_note(config: &nerf::train::TrainConfig, bounds: &SceneBounds) -> String {
    match &config.sampler {
        nerf::train::SamplerConfig::Occupancy { cone_angle, grid, step_size, .. } => {
            let cone = bounds.stepping(*step_size, *cone_angle).cone_angle;
            let levels = bounds.grid_config(grid).cascades.unwrap_or(1);
            let steps = if cone > 0.0 { format!("cone steps (cone_angle = {cone})") } else { "constant steps (cone_angle = 0)".into() };
            format!("marching with {steps} through a cascade of {levels} occupancy grids (see docs/architecture.md)")
        }
        _ => "instant-ngp marches such a box with an occupancy grid ([sampler] kind = \"occupancy\"), cone steps and \
              a cascade of grids (see docs/architecture.md)"
            .into(),
    }
}

fn cmd_train(a: TrainArgs, registry: &Registry) -> Result<()> {
    let config = build_config(&a, registry)?;
    let load = |split, views: &ViewSelection| {
        load_scene(&a.scene, split, &config.load_options(views.clone(), false, config.depth_loss.is_some()))
    };
    let train = load(Split::Train, &a.train_views)?;
    let test = load(Split::Test, &config.test_views)?;
    if let Some(n) = &train.normalization {
        let colmap = nerf::data::is_colmap(&a.scene);
        eprintln!(
            "note: {}: a {}: poses normalised as nerfstudio does (scale {:.4}; see docs/formats.md), \
             trained in the box [-{s}, {s}]^3 about the cameras{}",
            a.scene.display(),
            if colmap { "COLMAP model" } else { "nerfstudio capture" },
            n.scale,
            if train.ngp.is_some_and(|b| b.aabb_scale > 1.0) {
                ""
            } else {
                "; for content past the cameras, --aabb-scale 16 (instant-ngp's aabb_scale)"
            },
            s = train.ngp.map_or(1.0, |b| b.aabb_scale),
        );
    }
    if let Some(note) = large_photos_note(&train, config.downscale) {
        eprintln!("note: {}: {note}", a.scene.display());
    }
    if let Some(b) = train.ngp.filter(|b| b.aabb_scale > 1.0) {
        eprintln!("note: {}: aabb_scale {}: {}", a.scene.display(), b.aabb_scale, large_box_note(&config, &SceneBounds::of(&train)));
    }
    eprintln!(
        "training `{}` on {} ({} train views, {} test views, {}) -> {}",
        config.field,
        a.scene.display(),
        train.n_views(),
        test.n_views(),
        train.size_label(),
        a.out.display()
    );
    // Shares of the views' own pixels (views of several sizes: not of their canvas).
    let all = train.n_view_pixels() as f64;
    if let Some(m) = train.masks.as_ref().filter(|m| (m.total() as f64) < all) {
        eprintln!("training masks keep {:.1} % of the training views' pixels", 100.0 * m.total() as f64 / all);
    }
    if let Some(d) = &train.depths {
        let measured = d.iter().flatten().filter(|&&t| t > 0.0).count() as f64;
        match config.depth_loss {
            Some(l) => eprintln!("depth maps measure {:.1} % of the training views' pixels: trained on with depth_loss = {l}", 100.0 * measured / all),
            None => eprintln!(
                "note: the depth maps measure {:.1} % of the training views' pixels; set depth_loss (e.g. 0.1) in the config to train on them",
                100.0 * measured / all
            ),
        }
    }
    let mut opts = RunOptions::new(&a.out);
    opts.resume = a.resume;
    opts.overwrite = a.overwrite;
    opts.progress = !a.quiet;
    opts.write_renders = !a.no_renders;
    opts.scene = a.scene.display().to_string();
    opts.device = a.device;
    opts.stop = ctrl_c_flag()?;
    let s = run(config, registry, &train, &test, &opts)?;
    println!(
        "{} steps, {:.1} s, {:.1} ms/step, test PSNR {:.2} dB, SSIM {:.4} on {} views -> {}",
        s.iterations,
        s.metrics["wall_seconds"].as_f64().unwrap_or(0.0),
        s.metrics["ms_per_iter"].as_f64().unwrap_or(0.0),
        s.eval.psnr,
        s.eval.ssim,
        s.eval.views.len(),
        a.out.join("metrics.json").display()
    );
    if let Some(split) = &s.eval.alpha_split {
        println!("  by ground-truth alpha: {}", split.summary());
    }
    if let Some(d) = &s.eval.depth {
        println!("  {}", d.summary());
    }
    if let Some(m) = &s.eval.masked {
        println!("  {}", m.summary());
    }
    Ok(())
}

fn cmd_eval(a: EvalArgs, registry: &Registry) -> Result<()> {
    let ck_path = a.run.join("checkpoint.bin");
    let ck = Checkpoint::load(&ck_path)?;
    let views = a.test_views.clone().unwrap_or_else(|| ck.config.test_views.clone());
    let test = load_scene(&a.scene, a.split.split(), &ck.config.load_options(views, false, ck.config.depth_loss.is_some()))?;
    let mut config = ck.config.for_rendering();
    if let Some(spp) = a.spp {
        config.eval_spp = spp;
        config.validate().map_err(|e| anyhow::anyhow!("--spp {spp}: {e}"))?;
    }
    if let Some(f) = a.filter {
        config.eval_filter = f;
    }
    if let Some(bg) = a.background {
        config.eval_background = bg.into();
    }
    if let Some(s) = a.step_size {
        config.render_step_size = Some(s);
        config.validate().map_err(|e| anyhow::anyhow!("--step-size {s}: {e}"))?;
    }
    let mut trainer = make_trainer(&config, registry, SceneBounds::of(&test), a.device)?;
    trainer.restore(ck.step, &ck.fields, ck.adam, &ck.sampler).map_err(|e| e.in_checkpoint(&ck_path))?;
    let out = a.out.unwrap_or_else(|| a.run.join("eval"));
    let pb = progress(a.quiet, test.n_views(), "eval {bar:30} {pos}/{len} views");
    let report = nerf::train::evaluate(&trainer, &test, Some(&out), |i, _| pb.set_position(i as u64))?;
    pb.finish_and_clear();
    let text = serde_json::to_string_pretty(&serde_json::json!({
        "field": ck.config.field, "split": a.split.name(), "iterations": ck.step, "device": trainer.device(), "adapter": trainer.adapter(), "spp": config.eval_spp, "filter": config.eval_filter, "sampler": config.sampler, "render_step_size": config.render_step_size, "background": config.eval_background, "test_psnr": report.psnr, "test_ssim": report.ssim,
        "n_test_views": report.views.len(), "width": test.width, "height": test.height, "alpha_split": report.alpha_split, "test_depth": report.depth, "test_masked": report.masked, "per_view": report.views,
    }))?;
    nerf::train::run::write_atomic(&out.join("eval.json"), text.as_bytes())?;
    let spp = match (config.eval_spp, config.eval_filter) {
        (1, _) => String::new(),
        (n, nerf::rays::PixelFilter::Box) => format!(", {n} rays per pixel"),
        (n, nerf::rays::PixelFilter::BlackmanHarris { width }) => format!(", {n} rays per pixel (Blackman-Harris, filter width {width} px)"),
    };
    println!("{} PSNR {:.2} dB, SSIM {:.4} on {} views{spp} -> {}", a.split.name(), report.psnr, report.ssim, report.views.len(), out.display());
    if let Some(split) = &report.alpha_split {
        println!("  by ground-truth alpha: {}", split.summary());
    }
    if let Some(d) = &report.depth {
        println!("  {}", d.summary());
    }
    if let Some(m) = &report.masked {
        println!("  {}", m.summary());
    }
    Ok(())
}

/// [`resume_point`]: frames done, the seconds they took, their depth range.
type ResumePoint = (usize, f64, Option<(f32, f32)>);

/// Where `nerf render --resume` goes on in `out`: the frames its `render.json` counts (each
/// PNG present), with the seconds they took and their depth range. The earlier render must have
/// had the same path (every camera within 10⁻⁵), camera type, frame size and rays per pixel.
#[allow(clippy::too_many_arguments)]
fn resume_point(
    out: &Path,
    path: &[nerf::rays::Camera],
    camera_type: &str,
    spp: usize,
    shutter: f32,
    lenses: &serde_json::Value,
    crop: &serde_json::Value,
    alpha: bool,
) -> Result<ResumePoint> {
    let file = out.join("render.json");
    let text = std::fs::read_to_string(&file).with_context(|| format!("{}: nothing to resume", file.display()))?;
    let r: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", file.display()))?;
    let k = path[0].intrinsics;
    let same = |key: &str, want: serde_json::Value| -> Result<()> {
        match r.get(key) {
            Some(v) if *v == want => Ok(()),
            got => bail!("{}: `{key}` is {}, this render's is {want}: --resume continues the render that was started, with the same path and options", file.display(), got.map_or("missing".into(), |v| v.to_string())),
        }
    };
    same("path_frames", path.len().into())?;
    same("camera_type", camera_type.into())?;
    same("width", k.width.into())?;
    same("height", k.height.into())?;
    same("spp", spp.into())?;
    // Renders from before motion blur and depth of field had neither.
    let shutter = serde_json::json!(shutter);
    if r.get("shutter").unwrap_or(&serde_json::json!(0.0)).as_f64() != shutter.as_f64() {
        same("shutter", shutter)?;
    }
    if r.get("lenses").unwrap_or(&serde_json::Value::Null) != lenses {
        same("lenses", lenses.clone())?;
    }
    if r.get("crop").unwrap_or(&serde_json::Value::Null) != crop {
        same("crop", crop.clone())?;
    }
    if r.get("alpha").and_then(serde_json::Value::as_bool).unwrap_or(false) != alpha {
        same("alpha", alpha.into())?;
    }
    let done = r.get("frames").and_then(serde_json::Value::as_u64).with_context(|| format!("{}: no `frames`", file.display()))? as usize;
    let cams = r.get("camera_to_world").and_then(serde_json::Value::as_array).with_context(|| format!("{}: no `camera_to_world`", file.display()))?;
    if done > path.len() || cams.len() != done {
        bail!("{}: `frames` is {done} with {} cameras, for a path of {}", file.display(), cams.len(), path.len());
    }
    for (i, (c, cam)) in cams.iter().zip(path).enumerate() {
        let m = cam.c2w();
        let close = (0..3).all(|row| (0..4).all(|col| c[row][col].as_f64().is_some_and(|v| (v - f64::from(m[row][col])).abs() <= 1e-5)));
        if !close {
            bail!("{}: frame {i}'s camera is not this path's: --resume continues the render that was started, with the same path", file.display());
        }
        let png = out.join(format!("frame_{i:04}.png"));
        if !png.is_file() {
            bail!("{}: missing, though {} counts it", png.display(), file.display());
        }
    }
    let seconds = r.get("render_seconds").and_then(serde_json::Value::as_f64).unwrap_or(0.0);
    let range = r.get("depth_range").and_then(serde_json::Value::as_array).and_then(|v| Some((v.first()?.as_f64()? as f32, v.get(1)?.as_f64()? as f32)));
    Ok((done, seconds, range))
}

/// A render stopped by Ctrl-C after its current frame (exit code 130).
#[derive(Debug)]
struct RenderInterrupted {
    done: usize,
    total: usize,
    out: PathBuf,
}

impl std::fmt::Display for RenderInterrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let frames = match self.done {
            0 => String::new(),
            n => format!("frame_0000.png … frame_{:04}.png, ", n - 1),
        };
        write!(
            f,
            "interrupted after {} of {} frames: {frames}render.json and camera_path.json are in {} (no render.gif); the same command with --resume goes on from there",
            self.done,
            self.total,
            self.out.display()
        )
    }
}

impl std::error::Error for RenderInterrupted {}

/// A progress bar on stderr over `len` items (drawn only on a terminal; none with `--quiet`).
fn progress(quiet: bool, len: usize, template: &str) -> indicatif::ProgressBar {
    if quiet {
        return indicatif::ProgressBar::hidden();
    }
    let pb = indicatif::ProgressBar::new(len as u64);
    pb.set_style(indicatif::ProgressStyle::with_template(template).expect("a valid template"));
    pb
}

/// A trained run, ready to query ([`load_run`]).
struct LoadedRun {
    /// The run's config (from its checkpoint).
    config: TrainConfig,
    /// Steps it trained.
    step: u64,
    /// Its scene's training split (cameras, box).
    train: nerf::data::Dataset,
    /// A trainer holding the checkpoint's state.
    trainer: nerf::train::Trainer,
}

/// Loads a run's checkpoint and its scene's training split into a trainer on `device`. With
/// `euclidean_for`, an NDC run is refused, naming what needs the scene's own space. Without
/// `pixels` the split's photos are not decoded (its cameras and box are all that rendering and
/// mesh export need; [`LoadOptions::cameras_only`]).
fn load_run(registry: &Registry, run: &Path, scene: &Path, device: nerf::gpu::DevicePreference, euclidean_for: Option<&str>, pixels: bool) -> Result<LoadedRun> {
    let opened = open_run(run, scene, euclidean_for, pixels)?;
    let bounds = SceneBounds::of(&opened.train);
    opened.into_loaded(registry, device, bounds)
}

/// A run's checkpoint and its scene's training split, before a trainer holds them
/// ([`open_run`]; [`load_run`] does both).
struct OpenedRun {
    ck_path: PathBuf,
    ck: Checkpoint,
    /// The scene's training split (cameras, box).
    train: nerf::data::Dataset,
}

/// [`load_run`]'s first half: the checkpoint and the scene, checked as it checks them.
fn open_run(run: &Path, scene: &Path, euclidean_for: Option<&str>, pixels: bool) -> Result<OpenedRun> {
    let ck_path = run.join("checkpoint.bin");
    let ck = Checkpoint::load(&ck_path)?;
    let c = &ck.config;
    let opts = c.load_options(ViewSelection::All, !pixels, false);
    let train = load_scene(scene, Split::Train, &opts)?;
    if let (Some(what), Some(_)) = (euclidean_for, &train.ndc) {
        bail!("{}: the run was trained in NDC space, not the scene's: {what} needs a run trained with --no-ndc", run.display());
    }
    Ok(OpenedRun { ck_path, ck, train })
}

impl OpenedRun {
    /// [`load_run`]'s second half: a trainer on `device` for the scene within `bounds`, holding
    /// the checkpoint's state.
    fn into_loaded(self, registry: &Registry, device: nerf::gpu::DevicePreference, bounds: SceneBounds) -> Result<LoadedRun> {
        let Checkpoint { step, config, fields, adam, sampler, .. } = self.ck;
        let mut trainer = make_trainer(&config.for_rendering(), registry, bounds, device)?;
        trainer.restore(step, &fields, adam, &sampler).map_err(|e| e.in_checkpoint(&self.ck_path))?;
        Ok(LoadedRun { config, step, train: self.train, trainer })
    }
}

/// The most pixels `nerf render` renders in one frame (8192², e.g. an 8K panorama): a frame's
/// rays, colours and depths are held in memory at once, about 56 bytes a pixel (3.8 GB here;
/// 20 more with `--spp` above 1, for the sums).
const MAX_RENDER_PIXELS: u64 = 1 << 26;

/// The buffers of `nerf render --normals`, reused from frame to frame.
#[derive(Default)]
struct NormalBuffers {
    surface: Vec<f32>,
    steps: Vec<f32>,
    stencil: Vec<f32>,
    sigma: Vec<f32>,
    batch: Vec<f32>,
    normals: Vec<f32>,
    /// The frame's normal map, RGB.
    image: Vec<f32>,
}

impl NormalBuffers {
    /// The normal map of a frame whose rays (`origins`, `dirs`) rendered `depth` and `opacity`:
    /// the density at six points about each ray's surface point, `steps` away, in batches of
    /// 2^16 pixels (a frame may have 2^26).
    #[allow(clippy::too_many_arguments)]
    fn render(&mut self, trainer: &nerf::train::Trainer, origins: &[f32], dirs: &[f32], depth: &[f32], opacity: &[f32], steps: nerf::render::NormalSteps, background: [f32; 3]) -> Result<()> {
        use nerf::render::{gradient_stencil, normals_from_stencil, surface_points_of};
        const BATCH: usize = 1 << 16;
        surface_points_of(origins, dirs, depth, opacity, steps, &mut self.surface, &mut self.steps);
        self.normals.clear();
        for (p, h) in self.surface.chunks(3 * BATCH).zip(self.steps.chunks(BATCH)) {
            gradient_stencil(p, h, &mut self.stencil);
            self.sigma.resize(self.stencil.len() / 3, 0.0);
            trainer.density_at(&self.stencil, &mut self.sigma)?;
            normals_from_stencil(&self.sigma, &mut self.batch);
            self.normals.extend_from_slice(&self.batch);
        }
        nerf::render::normals_to_rgb(&self.normals, opacity, background, &mut self.image);
        Ok(())
    }
}

/// `nerf render --focus auto`: the distance along `cam`'s optical axis of what the middle of its
/// frame shows (`nerf_render::focus_distance` of the rays through a 5x5-pixel window about the
/// centre, a pixel being the frame's: its focal length's reciprocal, or a panorama's 2π over its
/// width); `None` when none of them reaches a surface.
fn autofocus(trainer: &nerf::train::Trainer, cam: &nerf::rays::Camera, projection: Projection, background: [f32; 3]) -> Result<Option<f32>> {
    let k = cam.intrinsics;
    let f = match projection {
        Projection::Equirectangular => k.width as f32 / std::f32::consts::TAU,
        _ => 0.5 * (k.fx + k.fy),
    };
    let window = nerf::rays::Camera {
        intrinsics: nerf::rays::Intrinsics { width: 5, height: 5, fx: f, fy: f, cx: 2.5, cy: 2.5 },
        distortion: nerf::rays::Distortion::NONE,
        ..*cam
    };
    let (mut o, mut d) = (Vec::new(), Vec::new());
    window.frame_rays_at(Projection::Perspective, [0.5, 0.5], &mut o, &mut d);
    let n = o.len() / 3;
    let (mut rgb, mut opacity, mut depth) = (vec![0.0; 3 * n], vec![0.0; n], vec![0.0; n]);
    trainer.render_rays(&o, &d, &background.repeat(n), &mut rgb, &mut opacity, &mut depth)?;
    let forward = -cam.rotation.z_axis.normalize();
    let axial: Vec<f32> = d.chunks_exact(3).map(|d| nerf::rays::glam::Vec3::from_slice(d).dot(forward)).collect();
    Ok(nerf::render::focus_distance(&depth, &opacity, &axial))
}

/// Where each frame's shutter closes towards (`nerf render --shutter`): the next frame's camera.
enum NextCamera {
    /// Closed paths (an orbit, the spiral): the first frame follows the last.
    Cyclic,
    /// Open paths: the last frame stands still.
    Clamped,
    /// The camera at each frame's end, given (an instant-ngp path at `(i + 1) / n`).
    Given(Vec<nerf::rays::Camera>),
}

impl NextCamera {
    /// The camera frame `i` of `path` moves towards.
    fn camera<'a>(&'a self, path: &'a [nerf::rays::Camera], i: usize) -> &'a nerf::rays::Camera {
        match self {
            NextCamera::Cyclic => &path[(i + 1) % path.len()],
            NextCamera::Clamped => &path[(i + 1).min(path.len() - 1)],
            NextCamera::Given(ends) => &ends[i],
        }
    }
}

/// Frames a second of an instant-ngp camera path: the frame rate of instant-ngp's video renders
/// (`run.py --video_fps`, its GUI's render settings).
const NGP_VIDEO_FPS: f64 = 60.0;

fn cmd_render(a: RenderArgs, registry: &Registry) -> Result<()> {
    if a.frames == Some(0) {
        bail!("--frames must be at least 1");
    }
    if !(1..=nerf::train::config::MAX_EVAL_SPP).contains(&a.spp) {
        bail!("--spp {}: must be 1..={} rays per pixel", a.spp, nerf::train::config::MAX_EVAL_SPP);
    }
    if !(0.0..=1.0).contains(&a.shutter) {
        bail!("--shutter {}: the fraction of a frame the shutter is open must be in [0, 1]", a.shutter);
    }
    if let Some(r) = a.aperture {
        let f = match a.focus {
            Some(Focus::Distance(f)) => f,
            _ => 1.0,
        };
        nerf::rays::ThinLens { aperture: r, focus_distance: f }.validate().map_err(|e| anyhow::anyhow!("--aperture / --focus: {e}"))?;
    }
    // A user's path is read before the checkpoint, so a typo there fails fast.
    let user_path = a.camera_path.as_deref().map(nerf::data::read_camera_path).transpose()?;
    if let (Some(CameraPathFile::Nerfstudio(_)), Some(_)) = (&user_path, a.frames) {
        bail!("--frames: {} is a nerfstudio camera path, which has one camera per frame", a.camera_path.as_deref().unwrap_or(Path::new("")).display());
    }
    // The path first: the trainer marches the depth range that covers the scene from its
    // cameras (SceneBounds::for_path).
    let opened = open_run(&a.run, &a.scene, None, false)?;
    let config = opened.ck.config.clone();
    let train = &opened.train;
    // --width scales the intrinsics; the height keeps the aspect.
    let sized = |k: nerf::rays::Intrinsics| -> Result<nerf::rays::Intrinsics> {
        let k = match a.width {
            Some(w) => {
                let s = w as f32 / k.width as f32;
                let h = (k.height as f32 * s).round().max(1.0) as u32;
                nerf::rays::Intrinsics { width: w, height: h, fx: k.fx * s, fy: k.fy * s, cx: k.cx * s, cy: k.cy * s }
            }
            None => k,
        };
        k.validate().map_err(|e| anyhow::anyhow!("--width {}: {e}", k.width))?;
        let pixels = u64::from(k.width) * u64::from(k.height);
        if pixels > MAX_RENDER_PIXELS {
            bail!(
                "a {}x{} frame is {pixels} pixels, more than the {MAX_RENDER_PIXELS} (8192x8192) a frame may have \
                 (each pixel holds its ray and colour in memory, about 56 bytes); lower --width or the camera path's size",
                k.width,
                k.height
            );
        }
        Ok(k)
    };
    let projection = match (&user_path, a.camera_type) {
        (Some(CameraPathFile::Nerfstudio(p)), _) => p.projection,
        (Some(CameraPathFile::InstantNgp(_)), _) => Projection::Perspective,
        (None, CameraType::Perspective) => Projection::Perspective,
        (None, CameraType::Fisheye) => Projection::Fisheye,
        (None, CameraType::Equirectangular) => Projection::Equirectangular,
    };
    if a.normals && train.ndc.is_some() {
        bail!("{}: the run was trained in NDC space, whose density gradient is not the scene's: --normals needs a run trained with --no-ndc", a.run.display());
    }
    if projection != Projection::Perspective && train.ndc.is_some() {
        bail!(
            "{}: the run was trained in NDC space, which holds only what lies in front of the cameras: a {} frame needs a run trained with --no-ndc",
            a.run.display(),
            projection.name()
        );
    }
    // The point the path looks at (the orbit's centre, and where frames focus by default): the
    // point the training cameras look at (a capture's object, wherever nerfstudio's
    // normalisation left it) when it lies in the scene box, else the box's centre.
    let center = nerf::rays::look_at_point(&train.cameras)
        .filter(|p| train.aabb.contains(p.to_array()))
        .unwrap_or_else(|| nerf::rays::glam::Vec3::from_array(train.aabb.center()));
    // The crop: `--crop`, else a nerfstudio path's own (with its background colour).
    let background = config.eval_background.fixed_rgb();
    let (crop, path_crop) = match (a.crop, &user_path) {
        (Some((lo, hi)), _) => {
            let b = nerf::sampling::CropBox::aabb(lo, hi).map_err(|e| anyhow::anyhow!("--crop: {e}"))?;
            (Some(b), Some(nerf::data::PathCrop { center: b.center, rotation: [0.0; 3], scale: b.size(), background }))
        }
        (None, Some(CameraPathFile::Nerfstudio(nerf::data::CameraPath { crop: Some(c), .. }))) => {
            let b = nerf::sampling::CropBox::oriented(c.center, c.rotation, c.scale)
                .map_err(|e| anyhow::anyhow!("{}: crop: {e}", a.camera_path.as_deref().unwrap_or(Path::new("")).display()))?;
            (Some(b), Some(*c))
        }
        _ => (None, None),
    };
    let background = path_crop.map_or(background, |c| c.background);
    let (path, path_fps, next, path_lenses) = match user_path {
        Some(CameraPathFile::Nerfstudio(p)) => {
            let mut cams = p.cameras;
            for c in &mut cams {
                c.intrinsics = sized(c.intrinsics)?;
            }
            (cams, p.fps, NextCamera::Clamped, None)
        }
        Some(CameraPathFile::InstantNgp(p)) => {
            let file = a.camera_path.as_deref().unwrap_or(Path::new(""));
            let space = nerf::data::NgpSpace::of(train).with_context(|| {
                format!(
                    "{}: an instant-ngp camera path needs a scene instant-ngp reads (transforms files or a COLMAP model); {} is an LLFF scene, \
                     whose cameras are in nerf-pytorch's recentred frame",
                    file.display(),
                    a.scene.display()
                )
            })?;
            // The frames are the size of the training images' (`--width` scales them), each
            // with its keyframes' field of view; instant-ngp renders 60 frames a second.
            let k = sized(train.cameras[0].intrinsics)?;
            let frames = a.frames.unwrap_or_else(|| (p.duration_seconds() * NGP_VIDEO_FPS).round().max(1.0) as usize);
            let cams = p.cameras(file, frames, k.width, k.height, &space)?;
            // The shutter closes towards the camera at the frame's end, `(i + 1) / n` of the
            // path (instant-ngp's `render_frame_end_camera`).
            let next = match a.shutter > 0.0 {
                true => NextCamera::Given(
                    (1..=frames)
                        .map(|i| p.camera_at(i as f64 / frames as f64, k.width, k.height, &space))
                        .collect::<Result<_, _>>()
                        .with_context(|| format!("{}: the camera at a frame's end", file.display()))?,
                ),
                false => NextCamera::Clamped,
            };
            (cams, Some(NGP_VIDEO_FPS), next, Some(p.lenses(file, frames, &space)?))
        }
        None => {
            let k = match projection {
                Projection::Perspective | Projection::Fisheye => train.cameras[0].intrinsics,
                Projection::Equirectangular => nerf::data::equirect_intrinsics(2 * train.height, train.height),
            };
            let k = sized(k)?;
            let frames = a.frames.unwrap_or(60);
            // Forward-facing captures get nerf-pytorch's spiral; object-centred ones a turntable orbit.
            let kind = match a.path {
                PathKind::Auto if nerf::data::is_llff(&a.scene) => PathKind::Spiral,
                PathKind::Auto => PathKind::Orbit,
                p => p,
            };
            let path = match kind {
                PathKind::Spiral => nerf::data::llff::render_path(train, k, frames).with_context(|| {
                    format!("{}: no spiral: it needs an LLFF scene (its depth bounds) and its cameras", a.scene.display())
                })?,
                PathKind::Interpolate => {
                    // The run's test views (what `nerf eval` loads), in the scene's order.
                    let opts = config.load_options(config.test_views.clone(), true, false);
                    let test = load_scene(&a.scene, Split::Test, &opts)?;
                    nerf::rays::interpolate(&test.cameras, k, frames).with_context(|| {
                        format!("{}: --path interpolate needs at least 2 test cameras and 2 frames", a.scene.display())
                    })?
                }
                _ => nerf::rays::orbit(&train.cameras, center, k, frames)
                    .with_context(|| format!("{}: the training cameras do not define an orbit", a.scene.display()))?,
            };
            // An orbit and the spiral come back to their first frame after their last.
            let next = match kind {
                PathKind::Interpolate => NextCamera::Clamped,
                _ => NextCamera::Cyclic,
            };
            (path, None, next, None)
        }
    };
    let bounds = match train.ndc {
        Some(_) => SceneBounds::of(train),
        None => SceneBounds::of(train).for_path(&train.cameras, &path),
    };
    let LoadedRun { step, train, mut trainer, .. } = opened.into_loaded(registry, a.device, bounds)?;
    trainer.set_render_appearance(a.appearance).with_context(|| format!("{}: --appearance", a.run.display()))?;
    if let Some(s) = a.step_size {
        trainer.set_render_step_size(Some(s)).with_context(|| format!("{}: --step-size {s}", a.run.display()))?;
    }
    trainer.set_render_crop(crop).with_context(|| format!("{}: crop box", a.run.display()))?;
    // Each frame's lens: `--aperture`, focused at `--focus` (what the frame's middle shows, with
    // `auto`) or where the path looks, else an instant-ngp path's own.
    let lenses: Vec<Option<nerf::rays::ThinLens>> = match (a.aperture, path_lenses) {
        (Some(r), _) if r > 0.0 => path
            .iter()
            .enumerate()
            .map(|(i, cam)| {
                let focus_distance = match (a.focus, nerf::data::llff::focus_depth(&train)) {
                    (Some(Focus::Distance(f)), _) => f,
                    (Some(Focus::Auto), _) => {
                        if train.ndc.is_some() {
                            bail!("--focus auto: the run was trained in NDC space, whose depths are not distances: give --focus DISTANCE");
                        }
                        autofocus(&trainer, cam, projection, background)?.with_context(|| {
                            format!("--focus auto: nothing in the middle of frame {i} to focus on (its central pixels' rays reach no surface): give --focus DISTANCE")
                        })?
                    }
                    (None, Some(f)) => f,
                    (None, None) => {
                        let forward = -cam.rotation.z_axis.normalize();
                        let depth = (center - cam.position).dot(forward);
                        if !(depth > 1e-6) {
                            bail!("--aperture: the point the path looks at, {center}, is not in front of frame {i}'s camera: give --focus");
                        }
                        depth
                    }
                };
                Ok(Some(nerf::rays::ThinLens { aperture: r, focus_distance }))
            })
            .collect::<Result<_>>()?,
        (Some(_), _) | (None, None) => vec![None; path.len()],
        (None, Some(l)) => l,
    };
    if a.spp < 4 && (a.shutter > 0.0 || lenses.iter().any(Option::is_some)) {
        eprintln!("note: depth of field and motion blur are averaged over each pixel's --spp rays; with {} the frames are noisy (8 or more smooths them)", a.spp);
    }
    let lenses_json = match lenses.iter().any(Option::is_some) {
        true => serde_json::json!(lenses.iter().map(|l| l.map(|l| [l.aperture, l.focus_distance])).collect::<Vec<_>>()),
        false => serde_json::Value::Null,
    };
    let k = path[0].intrinsics; // every camera of a path has the same size
    let n_frames = path.len();
    let video_fps = a.gif.map(f64::from).or(path_fps).unwrap_or(30.0);
    let out = a.out.unwrap_or_else(|| a.run.join("render"));
    std::fs::create_dir_all(&out).with_context(|| format!("{}: cannot create", out.display()))?;
    let n = k.width as usize * k.height as usize;
    let bg: Vec<f32> = background.repeat(n);
    let crop_json = serde_json::json!(path_crop.map(|c| c.to_json()));
    let (mut o, mut d) = (Vec::new(), Vec::new());
    let (mut rgb, mut opacity, mut depth) = (vec![0.0; 3 * n], vec![0.0; n], vec![0.0; n]);
    // Supersampling: each frame is the mean of its renders through these points of each pixel.
    let points = config.pixel_convention.sample_offsets_filtered(a.spp as usize, a.filter.unwrap_or(config.eval_filter));
    let mut mean = nerf::train::PassMean::new(points.len());
    // Normal maps: the density's gradient at each pixel's surface point, by central differences
    // a pixel's footprint there apart (at least 1/2048 of the scene box's longest side).
    let min_normal_step = {
        let b = &train.aabb;
        (0..3).map(|i| b.max[i] - b.min[i]).fold(0.0f32, f32::max) / 2048.0
    };
    let mut normal_bufs = NormalBuffers::default();
    let (mut gray, mut gif) = (Vec::new(), a.gif.map(|fps| nerf::data::GifWriter::create(&out.join("render.gif"), k.width, k.height, fps)).transpose()?);
    // An interrupted render goes on where it stopped: its frames so far are kept (read back
    // into the GIF), its time and depth range carried over.
    let (start, mut render_seconds, mut depth_range) = match a.resume {
        true => resume_point(&out, &path, projection.name(), points.len(), a.shutter, &lenses_json, &crop_json, a.alpha)?,
        false => (0, 0.0, None),
    };
    if let Some(want) = a.depth_range {
        // A resumed render's frames so far span the range it recorded.
        if let Some(got) = depth_range.filter(|&got| start > 0 && got != want) {
            bail!("{}: the depth maps so far span {got:?}, not --depth-range {want:?}: --resume continues the render that was started, with the same path and options", out.join("render.json").display());
        }
        depth_range = Some(want);
    }
    let mut rgba = Vec::new();
    if let Some(g) = gif.as_mut() {
        for i in 0..start {
            let frame = out.join(format!("frame_{i:04}.png"));
            if a.alpha {
                // The GIF shows the frames over the background.
                nerf::render::over_background(&nerf::data::load_png_rgba(&frame, k.width, k.height)?, background, &mut gray);
                g.push(&gray)?;
            } else {
                g.push(&nerf::data::load_png_rgb(&frame, k.width, k.height)?)?;
            }
        }
    }
    // Ctrl-C stops after the frame being rendered; the frames so far and the json files stay.
    let stop = ctrl_c_flag()?;
    let mut done = start;
    let pb = progress(a.quiet, n_frames, "render {bar:30} {pos}/{len} frames, {eta} left");
    for (i, cam) in path.iter().enumerate().skip(start) {
        if stop.load(Ordering::SeqCst) {
            break;
        }
        pb.set_position(i as u64);
        // The shutter closes a fraction of the way to the next frame's camera.
        let close = (a.shutter > 0.0).then(|| nerf::rays::exposure::camera_lerp(cam, next.camera(&path, i), a.shutter));
        let exposure = nerf::rays::Exposure { camera: cam, shutter_close: close.as_ref(), lens: lenses[i], projection };
        for (j, &point) in points.iter().enumerate() {
            cam.frame_rays_at(projection, point, &mut o, &mut d);
            exposure.apply(j, points.len(), i as u64, &mut o, &mut d);
            train.warp_rays(&mut o, &mut d);
            let t = std::time::Instant::now();
            trainer.render_rays(&o, &d, &bg, &mut rgb, &mut opacity, &mut depth)?;
            render_seconds += t.elapsed().as_secs_f64();
            mean.add(j, [&rgb, &opacity, &depth]);
        }
        mean.finish([&mut rgb, &mut opacity, &mut depth]);
        if a.alpha {
            nerf::render::to_rgba(&rgb, &opacity, &bg, &mut rgba);
            nerf::data::save_png_rgba(&out.join(format!("frame_{i:04}.png")), k.width, k.height, &rgba)?;
        } else {
            nerf::data::save_png(&out.join(format!("frame_{i:04}.png")), k.width, k.height, &rgb)?;
        }
        if a.normals {
            if points.len() > 1 {
                // The surface of the pixel centres' rays (depth and opacity: the mean of the passes).
                cam.frame_rays_into(projection, config.pixel_convention, &mut o, &mut d);
            }
            // A pixel's angle: its focal length's reciprocal, or a panorama's 2π over its width.
            let pixel_angle = match projection {
                Projection::Equirectangular => std::f32::consts::TAU / k.width as f32,
                _ => 2.0 / (cam.intrinsics.fx + cam.intrinsics.fy),
            };
            let steps = nerf::render::NormalSteps { pixel_angle, min: min_normal_step };
            normal_bufs.render(&trainer, &o, &d, &depth, &opacity, steps, background)?;
            nerf::data::save_png(&out.join(format!("normal_{i:04}.png")), k.width, k.height, &normal_bufs.image)?;
        }
        if let Some(g) = gif.as_mut() {
            g.push(&rgb)?;
        }
        if a.depth {
            // One range for the whole path (the first frame with surfaces), so frames compare.
            depth_range = depth_range.or_else(|| nerf::render::depth_range(&depth, &opacity));
            let range = depth_range.unwrap_or((0.0, 1.0));
            match a.depth_colormap {
                DepthColormap::Gray => nerf::render::depth_to_gray(&depth, &opacity, range, &mut gray),
                DepthColormap::Turbo => nerf::render::depth_to_turbo(&depth, &opacity, range, background, &mut gray),
            }
            nerf::data::save_png(&out.join(format!("depth_{i:04}.png")), k.width, k.height, &gray)?;
        }
        done = i + 1;
    }
    pb.finish_and_clear();
    let interrupted = done < n_frames;
    match gif {
        Some(g) if !interrupted => g.finish()?,
        g => drop(g), // an unfinished GIF leaves no file
    }
    let fps = done as f64 / render_seconds.max(1e-9);
    let cameras: Vec<_> = path[..done].iter().map(|c| c.c2w()).collect();
    let text = serde_json::to_string_pretty(&serde_json::json!({
        "field": config.field, "iterations": step, "device": trainer.device(), "adapter": trainer.adapter(),
        "render_step_size": trainer.config().render_step_size, "spp": points.len(), "shutter": a.shutter, "lenses": lenses_json, "crop": crop_json, "alpha": a.alpha, "near": bounds.near, "far": bounds.far, "frames": done, "path_frames": n_frames, "camera_type": projection.name(), "width": k.width, "height": k.height, "render_seconds": render_seconds, "frames_per_second": fps,
        "depth_range": depth_range.map(|(lo, hi)| [lo, hi]),
        "camera_to_world": cameras,
    }))?;
    nerf::train::run::write_atomic(&out.join("render.json"), text.as_bytes())?;
    // The path as nerfstudio's camera_path.json: `--camera-path` renders it again.
    let text = serde_json::to_string_pretty(&nerf::data::camera_path_json(&path, projection, video_fps, path_crop.as_ref()))?;
    nerf::train::run::write_atomic(&out.join("camera_path.json"), text.as_bytes())?;
    // And as instant-ngp's base_cam.json, for its GUI (and `--camera-path` again), where the
    // scene has an instant-ngp space and the frames are perspective: the same frames at 60 a
    // second.
    let ngp_path = (projection == Projection::Perspective)
        .then(|| nerf::data::NgpSpace::of(&train))
        .flatten()
        .and_then(|space| {
            let mut p = nerf::data::NgpCameraPath::from_cameras(&path, &space, NGP_VIDEO_FPS)?;
            // Each keyframe with its frame's lens (the last frame's twice).
            for (k, lens) in p.keyframes.iter_mut().zip(lenses.iter().chain(lenses.last())) {
                if let Some(l) = lens {
                    k.aperture = space.length_to_ngp(f64::from(l.aperture));
                    k.focus = space.length_to_ngp(f64::from(l.focus_distance));
                }
            }
            Some(p)
        });
    if let Some(p) = ngp_path {
        let text = serde_json::to_string_pretty(&p.to_json())?;
        nerf::train::run::write_atomic(&out.join("base_cam.json"), text.as_bytes())?;
    }
    if interrupted {
        return Err(RenderInterrupted { done, total: n_frames, out }.into());
    }
    println!("{n_frames} frames at {}x{} ({fps:.2} frames/s on {}) -> {}", k.width, k.height, trainer.device(), out.display());
    // A video at full colour is one ffmpeg call away (with --alpha, VP9 in WebM keeps the alpha).
    let (codec, video) = match a.alpha {
        true => ("-c:v libvpx-vp9 -pix_fmt yuva420p", "render.webm"),
        false => ("-pix_fmt yuv420p", "render.mp4"),
    };
    println!("video: ffmpeg -framerate {video_fps} -i {} {codec} {}", out.join("frame_%04d.png").display(), out.join(video).display());
    Ok(())
}

/// Random training rays (from the training cameras; no photo is decoded), rendered in batches,
/// until `--points` of them stop inside the scene box with enough opacity (or 20 times as many
/// rays as points were cast); their expected termination points and colours
/// (`nerf::render::surface_points`) as PLY.
fn cmd_export_points(a: PointsArgs, registry: &Registry) -> Result<()> {
    if a.points == 0 || !(0.0..=1.0).contains(&a.min_opacity) {
        bail!("--points must be at least 1 and --min-opacity in [0, 1]");
    }
    let LoadedRun { config, train, mut trainer, .. } = load_run(registry, &a.run, &a.scene, a.device, Some("a point cloud (its depths are distances)"), false)?;
    let out = a.out.unwrap_or_else(|| a.run.join("points.ply"));
    // Points are kept in the scene box, or in its part the crop box holds.
    let mut keep = (train.aabb.min, train.aabb.max);
    if let Some((lo, hi)) = a.crop {
        let c = nerf::sampling::CropBox::aabb(lo, hi).map_err(|e| anyhow::anyhow!("--crop: {e}"))?;
        trainer.set_render_crop(Some(c)).with_context(|| format!("{}: --crop", a.run.display()))?;
        keep = (std::array::from_fn(|i| keep.0[i].max(lo[i])), std::array::from_fn(|i| keep.1[i].min(hi[i])));
    }
    // Batches start at twice the points asked for (at least 1024 rays) and double up to 2^16
    // while too few rays stop: a small cloud does not render 65 536 rays.
    let max_batch = 1 << 16;
    let mut batch = a.points.saturating_mul(2).clamp(1 << 10, max_batch);
    let max_rays = a.points.max(max_batch).saturating_mul(20);
    let mut rng = nerf::core::rng(a.seed, 0x706f_696e_7473); // "points"
    let mut rays = nerf::data::RayBatch::default();
    let (mut rgb, mut opacity, mut depth) = (vec![0.0; 3 * max_batch], vec![0.0; max_batch], vec![0.0; max_batch]);
    let mut points = Vec::with_capacity(a.points);
    let pb = progress(a.quiet, a.points, "points {bar:30} {pos}/{len}");
    let mut cast = 0;
    while points.len() < a.points && cast < max_rays {
        train.sample_camera_rays(batch, config.eval_background, config.pixel_convention, false, &mut rng, &mut rays);
        let (rgb, opacity, depth) = (&mut rgb[..3 * batch], &mut opacity[..batch], &mut depth[..batch]);
        trainer.render_rays(&rays.origins, &rays.dirs, &rays.background, rgb, opacity, depth)?;
        nerf::render::surface_points(&rays.origins, &rays.dirs, rgb, opacity, depth, &rays.background, a.min_opacity, keep, &mut points);
        cast += batch;
        batch = (2 * batch).min(max_batch);
        pb.set_position(points.len().min(a.points) as u64);
    }
    pb.finish_and_clear();
    points.truncate(a.points);
    if points.is_empty() {
        bail!("{}: none of {cast} rays stopped in the scene box with opacity ≥ {}: nothing to export", a.run.display(), a.min_opacity);
    }
    let records: Vec<([f32; 3], [f32; 3])> = points.iter().map(|p| (p.position, p.color)).collect();
    nerf::data::write_ply_points(&out, &records)?;
    println!("{} points (of {cast} rays) -> {}", points.len(), out.display());
    Ok(())
}

fn cmd_export_mesh(a: MeshArgs, registry: &Registry) -> Result<()> {
    if !(2..=1024).contains(&a.resolution) || !a.threshold.is_finite() || a.threshold <= 0.0 {
        bail!("--resolution must be in 2..=1024 (about 13 bytes of memory per lattice node: 14 GB at 1024) and --threshold a positive number");
    }
    let out = a.out.unwrap_or_else(|| a.run.join("mesh.ply"));
    let obj = match out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
        Some("ply") => false,
        Some("obj") => true,
        _ => bail!("{}: the mesh is written as .ply or .obj, by the file's extension", out.display()),
    };
    let LoadedRun { train, trainer, .. } = load_run(registry, &a.run, &a.scene, a.device, Some("a mesh"), false)?;
    let scene_box = (train.aabb.min, train.aabb.max);
    // σ per scene unit from σ per instant-ngp unit (σ is an inverse length): an instant-ngp unit
    // is 1/scale scene units, or the box's longest side where the scene has no instant-ngp box.
    let ngp_unit = match train.ngp {
        Some(b) => 1.0 / b.scale,
        None => (0..3).map(|k| scene_box.1[k] - scene_box.0[k]).fold(0.0f32, f32::max),
    };
    let threshold = a.threshold / ngp_unit;
    let (want_lo, want_hi) = match (a.mesh_box, train.ngp) {
        (Some(b), _) => b,
        (None, Some(b)) if b.aabb_scale > 1.0 => nerf::data::NgpBox { aabb_scale: 1.0, ..b }.world_aabb(),
        _ => scene_box,
    };
    let (lo, hi): ([f32; 3], [f32; 3]) =
        (std::array::from_fn(|k| want_lo[k].max(scene_box.0[k])), std::array::from_fn(|k| want_hi[k].min(scene_box.1[k])));
    if (0..3).any(|k| !(lo[k] < hi[k])) {
        bail!("the box {want_lo:?} to {want_hi:?} (--box) misses the scene's box {:?} to {:?}", scene_box.0, scene_box.1);
    }
    println!("meshing the box {lo:?} to {hi:?} at σ = {threshold:.4} per scene unit");
    let lattice = nerf::mesh::Lattice::over_box(lo, hi, a.resolution);
    let n = lattice.len();
    let grid = if a.no_grid_mask { None } else { trainer.occupancy_grid_now()? };
    let mut density = vec![0.0f32; n];
    let batch = 1 << 18;
    let pb = progress(a.quiet, n, "density {bar:30} {pos}/{len} points");
    let (mut points, mut kept, mut rows, mut sigma) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for p0 in (0..n).step_by(batch) {
        let p1 = (p0 + batch).min(n);
        lattice.points(p0..p1, &mut points);
        // Only the nodes in occupied cells go to the field; the others stay empty (σ = 0).
        kept.clear();
        rows.clear();
        for (k, p) in points.chunks_exact(3).enumerate() {
            if grid.as_ref().is_none_or(|g| g.is_occupied([p[0], p[1], p[2]])) {
                kept.extend_from_slice(p);
                rows.push(p0 + k);
            }
        }
        sigma.resize(rows.len(), 0.0);
        trainer.density_at(&kept, &mut sigma)?;
        rows.iter().zip(&sigma).for_each(|(&r, &s)| density[r] = s);
        pb.set_position(p1 as u64);
    }
    pb.finish_and_clear();
    let inside = density.iter().filter(|&&s| s > threshold).count();
    if inside == 0 {
        let top = density.iter().copied().filter(|s| s.is_finite()).fold(0.0f32, f32::max);
        bail!(
            "{}: no density above the threshold {} (σ {threshold:.4} per scene unit) on the {:?} lattice; the highest is {:.4} ({:.3} per instant-ngp unit): try a lower --threshold",
            a.run.display(),
            a.threshold,
            lattice.dims,
            top,
            top * ngp_unit
        );
    }
    let mesh = nerf::mesh::extract_mesh(&lattice, &density, threshold);
    drop(density);
    // Vertex colours: the field seen head-on, looking along the inward normal.
    let nv = mesh.positions.len();
    let pos: Vec<f32> = mesh.positions.iter().flatten().copied().collect();
    let dirs: Vec<f32> = mesh.normals.iter().flat_map(|n| if *n == [0.0; 3] { [0.0, 0.0, -1.0] } else { n.map(|v| -v) }).collect();
    let (mut sigma, mut rgb) = (vec![0.0; nv], vec![0.0; 3 * nv]);
    trainer.query_points(&pos, &dirs, &mut sigma, &mut rgb)?;
    let colors: Vec<[f32; 3]> = rgb.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    let write = if obj { nerf::data::write_obj_mesh } else { nerf::data::write_ply_mesh };
    write(&out, &mesh.positions, &mesh.normals, &colors, &mesh.indices)?;
    println!(
        "{} vertices, {} triangles ({:?} lattice, {:.1} % of its nodes denser than {} per instant-ngp unit) -> {}",
        nv,
        mesh.n_triangles(),
        lattice.dims,
        100.0 * inside as f64 / n as f64,
        a.threshold,
        out.display()
    );
    Ok(())
}

fn cmd_export(a: ExportArgs) -> Result<()> {
    if a.src.canonicalize().ok() == a.dst.canonicalize().ok() {
        bail!("{}: destination must differ from the source", a.dst.display());
    }
    if a.sfm_depth {
        let forced = matches!(a.scene_format, FormatArg::Colmap);
        let model = nerf::data::colmap::find_model(&a.src).filter(|_| forced || nerf::data::is_colmap(&a.src));
        let Some(dir) = model else {
            bail!("{}: --sfm-depth needs a COLMAP folder (images/ and a sparse model, no transforms file)", a.src.display());
        };
        if !dir.join("points3D.bin").is_file() && !dir.join("points3D.txt").is_file() {
            bail!("{}: --sfm-depth: the model has no points3D.bin or points3D.txt", dir.display());
        }
    }
    if let Some(x) = a.exposure_jitter {
        if !(0.0..1.0).contains(&x) {
            bail!("--exposure-jitter must lie in [0, 1), got {x}");
        }
    }
    for (flag, x) in [("--pose-noise-rot", a.pose_noise_rot), ("--pose-noise-trans", a.pose_noise_trans)] {
        if x.is_some_and(|x| !(x.is_finite() && x >= 0.0)) {
            bail!("{flag} must be a finite amount ≥ 0, got {}", x.unwrap());
        }
    }
    // The amount as typed (its shortest f32 digits), not the f32's f64 expansion.
    let typed = |x: f32| -> Result<f64> { Ok(x.to_string().parse()?) };
    let write_json = |name: &str, json: serde_json::Value| -> Result<()> {
        std::fs::create_dir_all(&a.dst).with_context(|| format!("{}: cannot create", a.dst.display()))?;
        let path = a.dst.join(name);
        std::fs::write(&path, serde_json::to_string_pretty(&json)?).with_context(|| format!("{}: cannot write", path.display()))
    };
    for (split, views) in [(Split::Train, &a.train_views), (Split::Test, &a.test_views)] {
        let opts = LoadOptions { downscale: a.downscale, views: views.clone(), ndc: false, cameras_only: false, sfm_depth: a.sfm_depth, undistort: a.undistort, aabb_scale: None, nerfstudio: Default::default(), holdout: None, format: a.scene_format.into() };
        let mut ds = load_scene(&a.src, split, &opts)?;
        if split == Split::Train && (a.pose_noise_rot.is_some() || a.pose_noise_trans.is_some()) {
            let (rot, trans) = (a.pose_noise_rot.unwrap_or(0.0), a.pose_noise_trans.unwrap_or(0.0));
            let noise = nerf::data::pose_noise(ds.n_views(), rot, trans, a.seed);
            ds.perturb_poses(&noise);
            let json = serde_json::json!({
                "rot_degrees": typed(rot)?, "trans": typed(trans)?, "seed": a.seed,
                "convention": "per training view: translation τ (scene units) then rotation vector ω (radians) applied to the source camera: centre + τ, rotation exp([ω]x) · rotation; the camera_optimizer correction [−τ, −ω] undoes it",
                "noise": noise,
            });
            write_json("pose_noise.json", json)?;
        }
        if let (Some(file), Split::Train) = (&a.camera_corrections, split) {
            apply_camera_corrections(&mut ds, file)?;
        }
        if let (Some(x), Split::Train) = (a.exposure_jitter, split) {
            let gains = nerf::data::exposure_gains(ds.n_views(), x, a.seed);
            ds.scale_colors(&gains);
            write_json("exposure_gains.json", serde_json::json!({ "amount": typed(x)?, "seed": a.seed, "gains": gains }))?;
        }
        write_blender(&ds, &a.dst, a.attribution.as_deref())?;
        println!("{:?}: {} views at {} -> {}", split, ds.n_views(), ds.size_label(), a.dst.display());
    }
    Ok(())
}

/// `nerf export-scene --camera-corrections FILE`: each view of `ds` takes the refined pose that
/// `FILE` (a run's `camera_corrections.json`) holds under its name, keeping its intrinsics and
/// lens. Errors name the file: unreadable, not a run's corrections, a view it has no pose for,
/// or a pose that is no camera.
fn apply_camera_corrections(ds: &mut nerf::data::Dataset, file: &Path) -> Result<()> {
    let text = std::fs::read_to_string(file).with_context(|| format!("{}: cannot read", file.display()))?;
    let json: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}: not JSON", file.display()))?;
    let views = json.get("views").and_then(serde_json::Value::as_array).with_context(|| format!("{}: no `views`: not a run's camera_corrections.json", file.display()))?;
    let mut poses = std::collections::HashMap::new();
    for (i, v) in views.iter().enumerate() {
        let (Some(name), Some(m)) = (v.get("image").and_then(serde_json::Value::as_str), v.get("camera_to_world")) else {
            bail!("{}: views[{i}] has no `image` or `camera_to_world` (corrections written before nerf-rs named the views cannot be matched)", file.display());
        };
        let rows: Option<Vec<[f32; 4]>> = m.as_array().and_then(|r| r.iter().map(|row| serde_json::from_value::<[f32; 4]>(row.clone()).ok()).collect());
        poses.insert(name.to_string(), rows.with_context(|| format!("{}: views[{i}].camera_to_world is not rows of 4 numbers", file.display()))?);
    }
    for (i, name) in ds.view_names().into_iter().enumerate() {
        let c2w = poses.get(&name).with_context(|| format!("{}: no refined pose for training view `{name}` (the run trained on other views?)", file.display()))?;
        let cam = &ds.cameras[i];
        ds.cameras[i] = nerf::rays::Camera::from_c2w(cam.intrinsics, c2w)
            .map_err(|e| anyhow::anyhow!("{}: view `{name}`: {e}", file.display()))?
            .with_distortion(cam.distortion);
    }
    Ok(())
}

fn cmd_slim(a: SlimArgs) -> Result<()> {
    let ck_path = a.run.join("checkpoint.bin");
    let out = a.out.join("checkpoint.bin");
    // Refused before the (large) checkpoint is read.
    if out.exists() {
        bail!("{}: already exists; give --out a new folder", out.display());
    }
    let slim = Checkpoint::load(&ck_path)?.for_rendering().with_context(|| format!("{}", ck_path.display()))?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    slim.save(&out)?;
    let size = |p: &Path| std::fs::metadata(p).map(|m| m.len() as f64 / (1 << 20) as f64).unwrap_or(f64::NAN);
    println!("{} ({:.1} MiB) -> {} ({:.1} MiB, render-only: step {})", ck_path.display(), size(&ck_path), out.display(), size(&out), slim.step);
    Ok(())
}

fn cmd_fields(registry: &Registry) -> Result<()> {
    for e in registry.entries() {
        println!("{}: {}\n  default config: {}", e.name, e.description, (e.default_config)());
    }
    Ok(())
}

fn cmd_ablate(a: AblateArgs, registry: &Registry) -> Result<()> {
    let ablation = nerf::ablate::Ablation::load(&a.file)?;
    let out = a.out.unwrap_or_else(|| ablation.default_out_dir());
    let opts = nerf::ablate::AblateOptions { out_dir: out, verbose: true, device: a.device };
    let r = nerf::ablate::run_ablation(&ablation, registry, &opts)?;
    let skipped = r.runs.iter().filter(|o| o.skipped).count();
    println!(
        "{} runs ({} reused) -> {}, {}, {}, {}",
        r.runs.len(),
        skipped,
        r.results_csv.display(),
        r.results_md.display(),
        r.psnr_vs_time.display(),
        r.psnr_vs_iter.display()
    );
    Ok(())
}
