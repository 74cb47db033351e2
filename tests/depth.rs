//! Depth supervision end to end (`depth_loss`, [`nerf::data::depth`]): an RGB-D capture of a
//! textured ball — photos and 16-bit depth maps as instant-ngp's `depth_path` stores them,
//! written here from the analytic scene — trained from three views. With the depth maps the
//! field puts the ball's surface where it is in the held-out views, on the CPU and on the GPU;
//! from the photos alone, three views leave its depth loose.

use nerf::data::{load_blender, Dataset, LoadOptions, Split};
use nerf::rays::glam::Vec3;
use nerf::rays::{Camera, Intrinsics};
use nerf::train::{SceneBounds, TrainConfig, TrainError, Trainer};
use serde_json::json;
use std::path::Path;

mod common;
use common::light_hash_config;

const SIZE: u32 = 40;
const RADIUS: f32 = 1.0;

/// The camera at azimuth `az`, elevation `el` (radians) on the sphere of radius 3 about the
/// origin, looking at it, z up (OpenGL axes: x right, y up, looking down −z).
fn c2w(az: f32, el: f32) -> [[f32; 4]; 4] {
    let pos = 3.0 * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
    let back = pos.normalize();
    let right = Vec3::Z.cross(back).normalize();
    let up = back.cross(right);
    let mut m = [[0.0; 4]; 4];
    for (c, v) in [right, up, back, pos].iter().enumerate() {
        for r in 0..3 {
            m[r][c] = v[r];
        }
    }
    m[3][3] = 1.0;
    m
}

/// The distance along the unit ray `(o, d)` to the ball, if it hits.
fn hit(o: Vec3, d: Vec3) -> Option<f32> {
    let b = o.dot(d);
    let disc = b * b - (o.length_squared() - RADIUS * RADIUS);
    (disc >= 0.0).then(|| -b - disc.sqrt()).filter(|&t| t > 0.0)
}

/// The ball's colour at the unit normal `n`: smooth stripes that tell its sides apart.
fn texture(n: Vec3) -> [f32; 3] {
    [0.5 + 0.45 * (5.0 * n.x + 1.0).sin(), 0.5 + 0.45 * (6.0 * n.y + 2.0).sin(), 0.5 + 0.45 * (7.0 * n.z).sin()]
}

fn intrinsics() -> Intrinsics {
    Intrinsics { width: SIZE, height: SIZE, fx: 40.0, fy: 40.0, cx: 20.0, cy: 20.0 }
}

/// Writes the capture: three training views a third of a turn apart and three test views
/// between them, each an RGBA photo (transparent where the ray misses) and a z-depth map in
/// steps of 10⁻⁴ (0 where it misses).
fn write_capture(dir: &Path) {
    let k = intrinsics();
    let mut frames = Vec::new();
    let (mut train, mut test) = (Vec::new(), Vec::new());
    for i in 0..6 {
        let az = i as f32 * std::f32::consts::PI / 3.0 + 0.2;
        let el = if i % 2 == 0 { 0.35 } else { -0.15 };
        let m = c2w(az, el);
        let cam = Camera::from_c2w(k, &m[..3]).unwrap();
        let forward = -cam.rotation.col(2);
        let mut photo = image::RgbaImage::new(SIZE, SIZE);
        let mut depth = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::new(SIZE, SIZE);
        for (x, y, px) in photo.enumerate_pixels_mut() {
            let ray = cam.ray_at(x as f32 + 0.5, y as f32 + 0.5);
            if let Some(t) = hit(ray.origin, ray.dir) {
                let c = texture((ray.origin + t * ray.dir).normalize());
                *px = image::Rgba([c[0], c[1], c[2], 1.0].map(|v| (v * 255.0).round() as u8));
                depth.put_pixel(x, y, image::Luma([(t * ray.dir.dot(forward) / 1e-4).round() as u16]));
            }
        }
        let (name, dname) = (format!("v{i}.png"), format!("v{i}_depth.png"));
        photo.save(dir.join(&name)).unwrap();
        depth.save(dir.join(&dname)).unwrap();
        if i % 2 == 0 { &mut train } else { &mut test }.push(name.clone());
        frames.push(json!({"file_path": name, "depth_path": dname, "transform_matrix": m}));
    }
    let top = json!({
        "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": SIZE, "h": SIZE,
        "integer_depth_scale": 1e-4, "train_filenames": train, "test_filenames": test, "frames": frames,
    });
    std::fs::write(dir.join("transforms.json"), serde_json::to_string_pretty(&top).unwrap()).unwrap();
}

fn train(config: &TrainConfig, data: &Dataset) -> Trainer {
    common::train_on(config, data, None)
}


/// Mean |rendered depth − true distance| over the pixels of `ds`'s views that see the ball.
fn depth_error(t: &Trainer, ds: &Dataset) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for v in common::render_views(t, ds) {
        for (r, &d) in v.depth.iter().enumerate() {
            let (o, dir) = (Vec3::from_slice(&v.rays.origins[3 * r..]), Vec3::from_slice(&v.rays.dirs[3 * r..]));
            if let Some(truth) = hit(o, dir) {
                sum += (d - truth).abs() as f64;
                n += 1;
            }
        }
    }
    assert!(n > 1000, "the ball fills the test views");
    sum / n as f64
}

#[test]
fn depth_maps_put_the_surface_where_it_is() {
    let dir = tempfile::tempdir().unwrap();
    write_capture(dir.path());
    let o = LoadOptions::default();
    let (train_views, test_views) = (load_blender(dir.path(), Split::Train, &o).unwrap(), load_blender(dir.path(), Split::Test, &o).unwrap());
    assert_eq!((train_views.n_views(), test_views.n_views()), (3, 3));
    // The loaded depth maps are the ball's distances along the training rays (to 16-bit steps).
    let maps = train_views.depths.as_ref().expect("depth maps are loaded");
    let mut rays = nerf::data::RayBatch::default();
    train_views.view_rays(1, nerf::data::Background::White, nerf::rays::PixelConvention::Center, &mut rays);
    for (r, &t) in maps[1].iter().enumerate() {
        let truth = hit(Vec3::from_slice(&rays.origins[3 * r..]), Vec3::from_slice(&rays.dirs[3 * r..]));
        assert!(truth.map_or(t == 0.0, |d| (d - t).abs() < 2e-4), "pixel {r}: {t} against {truth:?}");
    }

    let plain = light_hash_config(300);
    let supervised = TrainConfig { depth_loss: Some(0.1), ..plain.clone() };
    let mut errors = Vec::new();
    for (name, config) in [("photos only", &plain), ("photos and depth maps", &supervised)] {
        let t0 = std::time::Instant::now();
        let t = train(config, &train_views);
        let e = depth_error(&t, &test_views);
        println!("{name}: mean depth error {e:.4} on the test views' ball pixels ({:.1} s)", t0.elapsed().as_secs_f64());
        // The evaluation scores the same against the test views' depth maps (the ball's pixels).
        let report = nerf::train::evaluate(&t, &test_views, None, |_, _| {}).unwrap();
        let d = report.depth.expect("the test views have depth maps");
        assert!((d.mean_abs - e).abs() < 0.02 * e.max(0.05) && d.measured_fraction > 0.3, "{d:?} against {e}");
        errors.push(e);
    }
    // Measured: 0.364 from the photos alone, 0.096 with the depth maps.
    assert!(errors[1] < 0.5 * errors[0], "depth error {:.4} with the depth maps, {:.4} without", errors[1], errors[0]);

    // The same on the GPU (lavapipe in CI), in fewer steps: the rays carry their pixels' depths
    // and the depth loss's kernel feeds compositing's backward.
    if let Some(ctx) = nerf::gpu::GpuContext::for_tests() {
        let short = TrainConfig { iters: GPU_STEPS, ..supervised.clone() };
        let t0 = std::time::Instant::now();
        let g = depth_error(&common::train_on(&short, &train_views, Some(std::sync::Arc::new(ctx))), &test_views);
        let secs = t0.elapsed().as_secs_f64();
        let c = depth_error(&train(&short, &train_views), &test_views);
        let p = depth_error(&train(&TrainConfig { iters: GPU_STEPS, ..plain.clone() }, &train_views), &test_views);
        println!("{GPU_STEPS} steps: depth error {g:.4} with the depth maps on the GPU ({secs:.1} s), {c:.4} on the CPU, {p:.4} from the photos alone (CPU)");
        // Measured: 0.203 on lavapipe, 0.162 on the CPU, 0.383 from the photos alone.
        assert!(g < 0.7 * p, "GPU with the depth maps {g:.4}, CPU {c:.4}, photos alone {p:.4}");
    }
}

/// Steps of the GPU run (lavapipe: ~0.4 s a step with the light preset).
const GPU_STEPS: u64 = 120;

/// `depth_loss` on a scene without depth maps is a configuration error naming the scene.
#[test]
fn depth_loss_needs_depth_maps() {
    let data = common::thumbnails(Split::Train, 2);
    let config = TrainConfig { depth_loss: Some(0.1), ..light_hash_config(1) };
    let mut t = Trainer::new_on(config, &nerf::registry(), SceneBounds::of(&data), None).unwrap();
    match t.step(&data) {
        Err(TrainError::Config(e)) => assert!(e.contains("depth_loss") && e.contains("lego_100") && e.contains("no depth maps"), "{e}"),
        other => panic!("expected a configuration error, got {other:?}"),
    }
}
