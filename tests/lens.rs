//! Lenses end to end: a textured room photographed through a fisheye of about 200° (OpenCV's
//! fisheye model with terms) from six places inside it, rendered here from the analytic scene,
//! trains a field that renders pinhole views of the room from four other places. Rays through the
//! photos' own pixels (the default) use the whole of each photo; resampled to pinhole images
//! (`LoadOptions::undistort`) the photos keep only their middle 120°; read as pinhole photos (the
//! lens keys lost) they must not train it. On the CPU and, where an adapter exists, on the GPU.

use std::path::Path;

use nerf::data::{load_blender, Dataset, LoadOptions, Split};
use nerf::rays::glam::{Mat3, Vec3};
use serde_json::json;

mod common;
use common::{gpu_matches_cpu, light_hash_config, psnr_of_each, room, yaw_pitch_pose as pose};

/// The fisheye photos: 64 pixels square, a focal length of 18 pixels (32 pixels out from the
/// centre is ~100° off the axis), OpenCV's `k1`, `k2`.
const FISH: (u32, f64, f64, f64) = (64, 18.0, 0.03, -0.004);


/// The fisheye's angle off the axis at distorted radius `theta_d` (in focal lengths):
/// `θ·(1 + k1·θ² + k2·θ⁴) = θ_d` solved by bisection, apart from the loader's Newton steps.
fn fisheye_theta(theta_d: f64) -> f64 {
    let (_, _, k1, k2) = FISH;
    let (mut lo, mut hi) = (0.0f64, 2.2f64);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        let t2 = mid * mid;
        if mid * (1.0 + t2 * (k1 + t2 * k2)) < theta_d {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Writes the scene: six fisheye photos for training, four pinhole photos (48×48, 80° across)
/// for testing. `lens`: whether the training frames state their lens (a capture whose lens
/// keys were lost otherwise).
fn write_scene(dir: &Path, lens: bool) {
    let (size, f, k1, k2) = FISH;
    let mut train = Vec::new();
    for i in 0..6 {
        let m = pose(Vec3::new(0.3 * (i as f32 * 2.3).cos(), 0.1 * (i as f32 - 2.5), 0.3 * (i as f32 * 2.3).sin()), 1.05 * i as f32, 0.2 * ((i % 3) as f32 - 1.0));
        let (r, o) = (Mat3::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|row| m[row][c]))), Vec3::new(m[0][3], m[1][3], m[2][3]));
        let c = 0.5 * size as f64;
        let img = image::RgbaImage::from_fn(size, size, |u, v| {
            let (xd, yd) = ((u as f64 + 0.5 - c) / f, (v as f64 + 0.5 - c) / f);
            let theta_d = xd.hypot(yd);
            let theta = fisheye_theta(theta_d);
            let s = if theta_d > 0.0 { theta.sin() / theta_d } else { 1.0 };
            // OpenCV's axes (y down, z forward) to OpenGL's.
            let d = Vec3::new((xd * s) as f32, -(yd * s) as f32, -theta.cos() as f32);
            let col = room(o, (r * d).normalize());
            image::Rgba([col[0], col[1], col[2], 1.0].map(|x| (x * 255.0).round() as u8))
        });
        img.save(dir.join(format!("fish{i}.png"))).unwrap();
        train.push(json!({"file_path": format!("fish{i}.png"), "transform_matrix": m}));
    }
    let mut t = json!({"fl_x": f, "fl_y": f, "cx": c_of(size), "cy": c_of(size), "w": size, "h": size, "aabb_scale": 1, "scale": 0.33, "offset": [0.5, 0.5, 0.5], "frames": train});
    if lens {
        t.as_object_mut().unwrap().extend(json!({"camera_model": "OPENCV_FISHEYE", "k1": k1, "k2": k2}).as_object().unwrap().clone());
    }
    std::fs::write(dir.join("transforms_train.json"), t.to_string()).unwrap();
    let (w, fov) = (48u32, 80f32.to_radians());
    let ft = 0.5 * w as f32 / (0.5 * fov).tan();
    let mut test = Vec::new();
    for i in 0..4 {
        let m = pose(Vec3::new(-0.2 * (i as f32 * 1.7 + 0.5).sin(), 0.05 * i as f32, 0.25 * (i as f32 * 1.7).cos()), 0.5 + 1.6 * i as f32, 0.25 * (i as f32 - 1.5));
        let (r, o) = (Mat3::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|row| m[row][c]))), Vec3::new(m[0][3], m[1][3], m[2][3]));
        let img = image::RgbaImage::from_fn(w, w, |u, v| {
            let d = Vec3::new((u as f32 + 0.5 - 0.5 * w as f32) / ft, -(v as f32 + 0.5 - 0.5 * w as f32) / ft, -1.0);
            let col = room(o, (r * d).normalize());
            image::Rgba([col[0], col[1], col[2], 1.0].map(|x| (x * 255.0).round() as u8))
        });
        img.save(dir.join(format!("view{i}.png"))).unwrap();
        test.push(json!({"file_path": format!("view{i}.png"), "transform_matrix": m}));
    }
    let t = json!({"fl_x": ft, "fl_y": ft, "w": w, "h": w, "aabb_scale": 1, "scale": 0.33, "offset": [0.5, 0.5, 0.5], "frames": test});
    std::fs::write(dir.join("transforms_test.json"), t.to_string()).unwrap();
}

fn c_of(size: u32) -> f64 {
    0.5 * size as f64
}

fn load(dir: &Path, split: Split, undistort: bool) -> Dataset {
    load_blender(dir, split, &LoadOptions { undistort, ..LoadOptions::default() }).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn fisheye_photos_train_through_their_lens() {
    let (good, lost) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    write_scene(good.path(), true);
    write_scene(lost.path(), false);
    let native = load(good.path(), Split::Train, false);
    let resampled = load(good.path(), Split::Train, true);
    let pinhole = load(lost.path(), Split::Train, false);
    let test = load(good.path(), Split::Test, false);
    assert!(native.cameras.iter().all(|c| !c.distortion.is_identity()) && native.masks.is_none());
    assert!(resampled.cameras.iter().all(|c| c.distortion.is_identity()));
    assert!(test.cameras.iter().all(|c| c.distortion.is_identity()));
    // The fisheye's rays reach past 90° off its axis; the resampled pinhole's stop at 60°.
    let off_axis = |d: &Dataset| {
        let c = &d.cameras[0];
        (c.rotation.transpose() * c.ray_at(0.5, 32.0).dir).angle_between(Vec3::NEG_Z).to_degrees()
    };
    assert!(off_axis(&native) > 95.0 && off_axis(&resampled) < 61.0, "{} and {}", off_axis(&native), off_axis(&resampled));

    let runs = [("fisheye photos through the lens", &native), ("resampled to pinholes", &resampled), ("read as pinholes", &pinhole)];
    let psnr = psnr_of_each(&light_hash_config(300), &runs, &test);
    // Measured: 24.41 dB through the lens, 18.21 dB resampled, 12.78 dB read as pinholes.
    assert!(psnr[0] > 20.0, "{:.2} dB", psnr[0]);
    assert!(psnr[0] > psnr[1] + 3.0, "through the lens {:.2} dB, resampled {:.2} dB", psnr[0], psnr[1]);
    assert!(psnr[0] > psnr[2] + 6.0, "through the lens {:.2} dB, read as pinholes {:.2} dB", psnr[0], psnr[2]);
    gpu_matches_cpu(80, &native, &test, 1);
}
