//! 360° panoramas as training photos (nerfstudio's `"camera_model": "EQUIRECTANGULAR"`,
//! [`nerf_data::equirect`]): each loads as the six faces of a cube map, pinhole views whose rays
//! see what the panorama shows in their direction. The fixture is an environment panorama whose
//! colour is a smooth function of the direction, so every face pixel can be checked against it.

use std::path::Path;

use nerf_data::{equirect, load_blender, write_blender, DataError, Dataset, LoadOptions, Split};
use nerf_rays::glam::{Mat3, Vec3};
use nerf_rays::Camera;
use serde_json::{json, Value};

const W: u32 = 256;
const H: u32 = 128;

/// The environment's colour in direction `d` (the panorama camera's axes).
fn colour(d: Vec3) -> [f32; 3] {
    [0.5 + 0.4 * d.x, 0.5 + 0.4 * d.y, 0.5 + 0.2 * d.z + 0.2 * (3.0 * d.x).sin() * d.y]
}

/// A rotation about an arbitrary axis and a position: panorama `i`'s camera-to-world matrix.
fn pose(i: usize) -> [[f32; 4]; 4] {
    let r = Mat3::from_axis_angle(Vec3::new(0.3, 1.0, -0.2 * i as f32).normalize(), 0.7 + 1.1 * i as f32);
    let mut m = [[0.0; 4]; 4];
    for row in 0..3 {
        for col in 0..3 {
            m[row][col] = r.col(col)[row];
        }
        m[row][3] = 0.1 * (i + row) as f32;
    }
    m[3][3] = 1.0;
    m
}

/// Two panoramas (`pano0.png`, `pano1.png`) and a 20×10 pinhole photo between them, in
/// `transforms_train.json`; `extra(i)` is merged into frame `i`.
fn scene(root: &Path, extra: impl Fn(usize) -> Value) {
    let pano = image::RgbaImage::from_fn(W, H, |u, v| {
        let c = colour(Camera::equirect_dir(W, H, u as f32 + 0.5, v as f32 + 0.5));
        image::Rgba([c[0], c[1], c[2], 1.0].map(|x| (x * 255.0).round() as u8))
    });
    pano.save(root.join("pano0.png")).unwrap();
    pano.save(root.join("pano1.png")).unwrap();
    image::RgbaImage::from_pixel(20, 10, image::Rgba([9, 99, 199, 255])).save(root.join("photo.png")).unwrap();
    let mut frames = vec![
        json!({"file_path": "pano0.png", "transform_matrix": pose(0), "camera_model": "EQUIRECTANGULAR", "w": W, "h": H}),
        json!({"file_path": "photo.png", "transform_matrix": pose(2), "fl_x": 12.0, "w": 20, "h": 10}),
        json!({"file_path": "pano1.png", "transform_matrix": pose(1), "camera_model": "EQUIRECTANGULAR"}),
    ];
    for (i, f) in frames.iter_mut().enumerate() {
        if let Value::Object(x) = extra(i) {
            f.as_object_mut().unwrap().extend(x);
        }
    }
    std::fs::write(root.join("transforms_train.json"), json!({ "frames": frames }).to_string()).unwrap();
}

/// The largest difference between a face view's pixels and the environment seen along its rays.
fn face_error(ds: &Dataset, v: usize, pano_pose: [[f32; 4]; 4]) -> f32 {
    let r = Mat3::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|row| pano_pose[row][c])));
    let (w, h) = ds.view_size(v);
    let mut worst = 0.0f32;
    for row in 0..h {
        for col in 0..w {
            let ray = ds.cameras[v].ray_at(col as f32 + 0.5, row as f32 + 0.5);
            let want = colour(r.transpose() * ray.dir);
            let p = 4 * (row * ds.width + col) as usize;
            for c in 0..3 {
                worst = worst.max((ds.images[v].value(p + c) - want[c]).abs());
            }
        }
    }
    worst
}

#[test]
fn a_panorama_loads_as_six_pinhole_faces_that_see_what_it_shows() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), |_| json!({}));
    let ds = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!(ds.n_views(), 13, "6 faces, the photo, 6 faces");
    let s = equirect::face_size(W, 1).unwrap();
    assert_eq!((s, ds.width, ds.height), (81, 81, 81));
    assert_eq!((ds.view_size(6), ds.view_size(0)), ((20, 10), (81, 81)));
    let names = ds.view_names();
    assert_eq!((&names[0][..], &names[5][..], &names[6][..], &names[7][..], &names[12][..]), ("pano0_0", "pano0_5", "photo", "pano1_0", "pano1_5"));
    for (first, i) in [(0, 0), (7, 1)] {
        for f in 0..6 {
            let v = first + f;
            assert_eq!(ds.cameras[v].position, ds.cameras[first].position, "a panorama's faces share its centre");
            assert_eq!(ds.cameras[v].intrinsics, equirect::face_intrinsics(s));
            // Quantised to 8 bits and bilinearly resampled: within 1.5 steps of 1/255.
            let e = face_error(&ds, v, pose(i));
            assert!(e < 1.5 / 255.0, "panorama {i}, face {}: off by {e}", equirect::FACES[f]);
        }
    }
    // The photo between them is a photo; the faces' canvas past it is masked out.
    assert_eq!(&ds.images[6].to_f32()[..4], &[9.0 / 255.0, 99.0 / 255.0, 199.0 / 255.0, 1.0]);
    assert_eq!(ds.masks.as_ref().unwrap().total(), 12 * 81 * 81 + 200);

    // Downscaled: faces of a multiple of the factor, then box-averaged.
    let half = load_blender(dir.path(), Split::Train, &LoadOptions { downscale: 2, ..Default::default() }).unwrap();
    assert_eq!((half.view_size(0), half.cameras[0].intrinsics.fx), ((40, 40), 20.0));
    assert!(face_error(&half, 3, pose(0)) < 2.0 / 255.0);
    // Cameras only: the same cameras, no pixels.
    let cams = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap();
    for (a, b) in cams.cameras.iter().zip(&ds.cameras) {
        assert_eq!((a.intrinsics, a.rotation, a.position), (b.intrinsics, b.rotation, b.position));
    }
    assert!(!cams.has_images());

    // Written back, the faces are pinhole photos with their own intrinsics and poses.
    let out = tempfile::tempdir().unwrap();
    write_blender(&ds, out.path(), None).unwrap();
    let back = load_blender(out.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!(back.n_views(), 13);
    // The faces' resampled colours are written as 8-bit PNGs: within half a step.
    let off = back.images.iter().flat_map(|p| p.to_f32()).zip(ds.images.iter().flat_map(|p| p.to_f32())).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(off <= 0.5 / 255.0 + 1e-6, "written back off by {off}");
    for (a, b) in back.cameras.iter().zip(&ds.cameras) {
        assert_eq!(a.intrinsics, b.intrinsics);
        assert!((a.rotation - b.rotation).abs_diff_eq(Mat3::ZERO, 1e-6) && (a.position - b.position).length() < 1e-6);
    }
}

#[test]
fn a_panoramas_mask_is_cut_with_it() {
    let dir = tempfile::tempdir().unwrap();
    // Each panorama's mask drops its upper half (everything above the horizon).
    image::GrayImage::from_fn(W, H, |_, v| image::Luma([if v < H / 2 { 0 } else { 255 }])).save(dir.path().join("mask.png")).unwrap();
    image::GrayImage::from_pixel(20, 10, image::Luma([255])).save(dir.path().join("photo_mask.png")).unwrap();
    scene(dir.path(), |i| json!({"mask_path": if i == 1 { "photo_mask.png" } else { "mask.png" }}));
    let ds = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    let m = ds.masks.as_ref().unwrap();
    let s = 81u32;
    assert_eq!((m.kept_in(4), m.kept_in(11)), (0, 0), "the up faces look above the horizon");
    assert_eq!((m.kept_in(5), m.kept_in(12)), ((s * s) as u64, (s * s) as u64), "the down faces below it");
    assert_eq!(m.kept_in(6), 200, "the photo keeps its pixels");
    for v in [0, 1, 2, 3, 7, 8, 9, 10] {
        // A side face keeps its lower half: its rows below the middle, the middle row (on the
        // horizon, half drawn from above it) dropped.
        for row in 0..s {
            let kept = (0..s).filter(|&col| m.is_kept(v, row * ds.width + col)).count() as u32;
            assert_eq!(kept, if row > s / 2 { s } else { 0 }, "view {v}, row {row}");
        }
    }
}

#[test]
fn panorama_errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    // A stated size that is not the panorama's.
    scene(dir.path(), |i| if i == 0 { json!({"w": 128, "h": 64}) } else { json!({}) });
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::InvalidValue { .. }) && e.to_string().contains("128x64") && e.to_string().contains("pano0.png"), "{e}");
    // A panorama's depth map of another shape.
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::new(W, W).save(dir.path().join("d.png")).unwrap();
    scene(dir.path(), |i| if i == 2 { json!({"depth_file_path": "d.png"}) } else { json!({}) });
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::BadDepth { frame: 2, .. }) && e.to_string().contains("d.png"), "{e}");
    // Faces too small to hold a pixel.
    scene(dir.path(), |_| json!({}));
    image::RgbaImage::new(2, 1).save(dir.path().join("pano1.png")).unwrap();
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::BadDownscale { .. }) && e.to_string().contains("pano1.png"), "{e}");
}

/// A panorama's depth map holds the distance along each ray (a 16-bit PNG in millimetres, as
/// nerfstudio's `depth_file_path`): its faces' depths are those distances, the room's walls seen
/// along each face pixel's ray.
#[test]
fn a_panoramas_depth_map_gives_its_faces_the_distances_along_their_rays() {
    let dir = tempfile::tempdir().unwrap();
    // A room, the cube of half-extent 2 about the camera: the distance to its walls along `d`.
    let range = |d: Vec3| 2.0 / d.abs().max_element();
    let map = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(W, H, |u, v| {
        image::Luma([(1000.0 * range(Camera::equirect_dir(W, H, u as f32 + 0.5, v as f32 + 0.5).normalize())).round() as u16])
    });
    map.save(dir.path().join("d.png")).unwrap();
    scene(dir.path(), |i| if i == 0 { json!({"depth_file_path": "d.png"}) } else { json!({}) });
    let ds = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    let depths = ds.depths.as_ref().unwrap();
    let r = Mat3::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|row| pose(0)[row][c])));
    let (mut measured, mut worst, mut sum) = (0, 0.0f32, 0.0f64);
    for v in 0..6 {
        for p in 0..81 * 81u32 {
            let t = depths[v][p as usize];
            if t == 0.0 {
                continue;
            }
            measured += 1;
            let ray = ds.cameras[v].ray_at((p % 81) as f32 + 0.5, (p / 81) as f32 + 0.5);
            let e = (t / range(r.transpose() * ray.dir) - 1.0).abs();
            (worst, sum) = (worst.max(e), sum + e as f64);
        }
    }
    // Bilinear samples of millimetre steps, a little off where they straddle the room's edges
    // and corners (a z-depth taken for a distance would be off by up to √3 − 1 at a face's corner).
    let mean = sum / measured as f64;
    assert!(measured > 6 * 81 * 81 * 95 / 100 && worst < 0.02 && mean < 0.002, "{measured} measured, off by {worst} at worst, {mean} on average");
    assert!(depths[6].iter().all(|&t| t == 0.0), "the photo has no depth map");
}
