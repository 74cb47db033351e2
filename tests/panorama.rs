//! 360° panoramas end to end (`"camera_model": "EQUIRECTANGULAR"`, [`nerf::data::equirect`]): a
//! textured room photographed by a panoramic camera from four places inside it, rendered here
//! from the analytic scene, trains a field that renders the room from a fifth place (its
//! panorama's six faces are the test views), on the CPU and, where an adapter exists, on the GPU.
//! The same panoramas mirrored left to right (the longitude's sign lost, as a loader with the
//! wrong convention would read them) must not train it.

use std::path::Path;
use std::sync::Arc;

use nerf::data::{load_blender, LoadOptions, Split};
use nerf::gpu::GpuContext;
use nerf::rays::glam::{Mat3, Vec3};
use nerf::rays::Camera;
use serde_json::json;

mod common;
use common::{light_hash_config, sparse_psnr, train_on};

const W: u32 = 128;
const H: u32 = 64;
/// The room's walls, floor and ceiling: the cube of this half-extent.
const ROOM: f32 = 1.2;

/// The room's colour where the ray `(o, d)` from inside it meets a wall: smooth stripes that
/// differ from wall to wall.
fn room(o: Vec3, d: Vec3) -> [f32; 3] {
    let t = (0..3).map(|a| if d[a] > 0.0 { (ROOM - o[a]) / d[a] } else { (-ROOM - o[a]) / d[a] }).fold(f32::INFINITY, f32::min);
    let p = o + t * d;
    [0.5 + 0.4 * (3.0 * p.x + p.y).sin(), 0.5 + 0.4 * (2.5 * p.y - p.z + 1.0).sin(), 0.5 + 0.4 * (3.5 * p.z + 0.5 * p.x).sin()]
}

/// Panorama `i`'s camera: a place inside the room, turned about the vertical and tilted a little.
fn pose(i: usize) -> [[f32; 4]; 4] {
    let r = Mat3::from_rotation_y(1.3 * i as f32 + 0.2) * Mat3::from_rotation_x(0.15 * (i as f32 - 2.0));
    let c = Vec3::new(0.3 * (i as f32 * 2.1).cos(), 0.15 * (i as f32 - 2.0), 0.3 * (i as f32 * 2.1).sin());
    let mut m = [[0.0; 4]; 4];
    for row in 0..3 {
        for col in 0..3 {
            m[row][col] = r.col(col)[row];
        }
        m[row][3] = c[row];
    }
    m[3][3] = 1.0;
    m
}

/// Writes the panoramas (`mirror`: the training ones flipped left to right) and the split files:
/// panoramas 0–3 train, panorama 4 tests. The files carry instant-ngp's box (the cube of
/// half-extent 1.5, rays from 0.3) so that the cameras may stand inside the scene.
fn write_scene(dir: &Path, mirror: bool) {
    for i in 0..5 {
        let m = pose(i);
        let cam = Camera::from_c2w(nerf::data::equirect::face_intrinsics(1), &m[..3]).unwrap();
        let img = image::RgbaImage::from_fn(W, H, |u, v| {
            let u = if mirror && i < 4 { W - 1 - u } else { u };
            let d = cam.rotation * Camera::equirect_dir(W, H, u as f32 + 0.5, v as f32 + 0.5);
            let c = room(cam.position, d.normalize());
            image::Rgba([c[0], c[1], c[2], 1.0].map(|x| (x * 255.0).round() as u8))
        });
        img.save(dir.join(format!("pano{i}.png"))).unwrap();
    }
    for (split, range) in [("train", 0..4), ("test", 4..5)] {
        let frames: Vec<_> = range.map(|i| json!({"file_path": format!("pano{i}.png"), "transform_matrix": pose(i)})).collect();
        let t = json!({"camera_model": "EQUIRECTANGULAR", "aabb_scale": 1, "scale": 0.33, "offset": [0.5, 0.5, 0.5], "frames": frames});
        std::fs::write(dir.join(format!("transforms_{split}.json")), t.to_string()).unwrap();
    }
}


#[test]
fn panoramas_from_inside_a_room_train_a_field_that_renders_it_from_elsewhere() {
    let (good, bad) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    write_scene(good.path(), false);
    write_scene(bad.path(), true);
    let opts = LoadOptions::default();
    let (train_views, test) = (load_blender(good.path(), Split::Train, &opts).unwrap(), load_blender(good.path(), Split::Test, &opts).unwrap());
    let mirrored = load_blender(bad.path(), Split::Train, &opts).unwrap();
    assert_eq!((train_views.n_views(), test.n_views(), train_views.width), (24, 6, 40), "six 40×40 faces a panorama");
    assert!(train_views.near < 0.5, "rays start near the camera: {}", train_views.near);

    let config = light_hash_config(300);
    let mut psnr = Vec::new();
    for (name, data) in [("panoramas", &train_views), ("mirrored panoramas", &mirrored)] {
        let t0 = std::time::Instant::now();
        let p = sparse_psnr(&train_on(&config, data, None), &test, 1);
        println!("cpu, {name}: {p:.2} dB on the held-out panorama's faces ({:.1} s)", t0.elapsed().as_secs_f64());
        psnr.push(p);
    }
    // Measured: 19.14 dB, and 9.82 dB from the mirrored panoramas.
    assert!(psnr[0] > 16.0, "{:.2} dB", psnr[0]);
    assert!(psnr[0] > psnr[1] + 3.0, "panoramas {:.2} dB, mirrored {:.2} dB", psnr[0], psnr[1]);

    let Some(ctx) = GpuContext::for_tests().map(Arc::new) else { return };
    let short = light_hash_config(80);
    let cpu = sparse_psnr(&train_on(&short, &train_views, None), &test, 1);
    let gpu = sparse_psnr(&train_on(&short, &train_views, Some(ctx)), &test, 1);
    println!("{} steps: cpu {cpu:.2} dB, gpu {gpu:.2} dB", short.iters);
    assert!((gpu - cpu).abs() < 1.0, "cpu {cpu:.2} dB, gpu {gpu:.2} dB");
}
