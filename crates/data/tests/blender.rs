//! Blender-format loading, writing, downscaling, ray sampling and error reporting, on tiny
//! synthetic scenes written into temporary folders (and on lego when shared/data has it).

use std::path::{Path, PathBuf};

use glam::{Mat3, Vec3};
use nerf_data::{
    load_blender, save_png, write_blender, Background, DataError, Dataset, LoadOptions, PixelMasks,
    RayBatch, Split, ViewSelection,
};
use nerf_rays::{Aabb, Camera, Intrinsics, PixelConvention};
use rand::{Rng, SeedableRng};
use serde_json::{json, Value};

const ANGLE: f64 = 0.6911112070083618;

/// A camera on a sphere of radius 4 looking at the origin (OpenGL axes).
fn look_at_origin(k: Intrinsics, theta: f32, phi: f32) -> Camera {
    let pos = 4.0 * Vec3::new(theta.cos() * phi.cos(), theta.sin() * phi.cos(), phi.sin());
    let back = pos.normalize(); // camera +z points away from the target
    let right = Vec3::Z.cross(back).normalize();
    let up = back.cross(right);
    Camera {
        intrinsics: k,
        rotation: Mat3::from_cols(right, up, back),
        position: pos,
        distortion: nerf_rays::Distortion::NONE,
    }
}

/// Random 8-bit RGBA images (values u8/255) with some fully transparent and opaque pixels.
fn random_images(n: usize, w: u32, h: u32, seed: u64) -> Vec<Vec<f32>> {
    let mut r = rand::rngs::StdRng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            (0..4 * w * h)
                .map(|i| {
                    let v: u8 = if i % 4 == 3 && r.gen_bool(0.3) {
                        [0u8, 255][r.gen_range(0..2)]
                    } else {
                        r.gen()
                    };
                    v as f32 / 255.0
                })
                .collect()
        })
        .collect()
}

fn synthetic(n: usize, w: u32, h: u32, seed: u64) -> Dataset {
    let k = Intrinsics::from_fov_x(w, h, ANGLE);
    Dataset {
        root: PathBuf::new(),
        split: Split::Train,
        width: w,
        height: h,
        cameras: (0..n)
            .map(|i| look_at_origin(k, 0.9 * i as f32 + 0.3, 0.2 + 0.1 * i as f32))
            .collect(),
        images: random_images(n, w, h, seed).into_iter().map(Into::into).collect(),
        file_paths: vec![],
        masks: None,
        depths: None,
        near: 2.0,
        far: 6.0,
        aabb: Aabb::cube(1.5),
        ndc: None,
        depth_bounds: None,
        ngp: None,
        normalization: None,
    }
}

fn opts(k: u32, views: ViewSelection) -> LoadOptions {
    LoadOptions {
        downscale: k,
        views,
        ..Default::default()
    }
}

/// The in-repo scene's 8-bit photos are held in bytes: 4 a pixel, a quarter of `f32` RGBA.
#[test]
fn eight_bit_photos_take_four_bytes_a_pixel() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/lego_100");
    let ds = load_blender(&root, Split::Train, &LoadOptions::default()).unwrap();
    assert!(ds.images.iter().all(|p| p.is_rgba8() && p.size_in_bytes() == 4 * 100 * 100));
}

#[test]
fn write_then_load_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let ds = synthetic(3, 8, 6, 1);
    write_blender(&ds, dir.path(), Some("test scene, CC0")).unwrap();
    let json: Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("transforms_train.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(json["attribution"], "test scene, CC0");
    assert_eq!(json["frames"][2]["file_path"], "./train/r_2");
    assert!((json["camera_angle_x"].as_f64().unwrap() - ANGLE).abs() < 1e-6);

    let back = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!((back.width, back.height, back.n_views()), (8, 6, 3));
    assert_eq!(back.split, Split::Train);
    assert_eq!(
        (back.near, back.far, back.aabb),
        (2.0, 6.0, Aabb::cube(1.5))
    );
    for i in 0..3 {
        assert_eq!(
            back.images[i], ds.images[i],
            "view {i} pixels differ after the round trip"
        );
        assert_eq!(back.cameras[i].rotation, ds.cameras[i].rotation);
        assert_eq!(back.cameras[i].position, ds.cameras[i].position);
        let (a, b) = (back.cameras[i].intrinsics, ds.cameras[i].intrinsics);
        assert!((a.fx - b.fx).abs() < 1e-5 * b.fx && (a.fy - b.fy).abs() < 1e-5 * b.fy);
        assert_eq!((a.cx, a.cy, a.width, a.height), (4.0, 3.0, 8, 6));
        assert_eq!(
            back.file_paths[i],
            dir.path().join(format!("train/r_{i}.png"))
        );
    }
    // No attribution key when none is given.
    let dir2 = tempfile::tempdir().unwrap();
    write_blender(&ds, dir2.path(), None).unwrap();
    let json: Value = serde_json::from_str(
        &std::fs::read_to_string(dir2.path().join("transforms_train.json")).unwrap(),
    )
    .unwrap();
    assert!(json.get("attribution").is_none());
    // View selections.
    let every = load_blender(dir.path(), Split::Train, &opts(1, ViewSelection::Every(2))).unwrap();
    assert_eq!(every.n_views(), 2);
    assert_eq!(every.images[1], ds.images[2]);
    let first = load_blender(dir.path(), Split::Train, &opts(1, ViewSelection::First(1))).unwrap();
    assert_eq!(first.n_views(), 1);
    assert_eq!(first.cameras[0].position, ds.cameras[0].position);
}

/// Writes `transforms_<split>.json` with the given JSON and the given images (RGBA8) beside it.
fn write_scene(root: &Path, split: &str, transforms: &Value, images: &[(&str, u32, u32)]) {
    std::fs::create_dir_all(root.join(split)).unwrap();
    std::fs::write(
        root.join(format!("transforms_{split}.json")),
        serde_json::to_string(transforms).unwrap(),
    )
    .unwrap();
    for &(name, w, h) in images {
        let img = image::RgbaImage::from_fn(w, h, |x, y| {
            image::Rgba([(x * 17) as u8, (y * 29) as u8, 7, 200])
        });
        img.save(root.join(name)).unwrap();
    }
}

fn ident() -> Value {
    json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]])
}

fn frames_json(n: usize) -> Value {
    Value::Array(
        (0..n)
            .map(|i| json!({"file_path": format!("./train/r_{i}"), "transform_matrix": ident()}))
            .collect(),
    )
}

fn good_scene(root: &Path, n: usize, w: u32, h: u32) {
    let names: Vec<String> = (0..n).map(|i| format!("train/r_{i}.png")).collect();
    let imgs: Vec<(&str, u32, u32)> = names.iter().map(|s| (s.as_str(), w, h)).collect();
    write_scene(
        root,
        "train",
        &json!({"camera_angle_x": ANGLE, "frames": frames_json(n)}),
        &imgs,
    );
}

fn load_err(root: &Path, o: &LoadOptions) -> DataError {
    match load_blender(root, Split::Train, o) {
        Ok(_) => panic!("expected an error"),
        Err(e) => e,
    }
}

fn set_transforms(root: &Path, v: &Value) {
    std::fs::write(
        root.join("transforms_train.json"),
        serde_json::to_string_pretty(v).unwrap(),
    )
    .unwrap();
}

#[test]
fn downscale_is_box_mean_and_halves_focal() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 2, 8, 4);
    let full = load_blender(dir.path(), Split::Train, &opts(1, ViewSelection::All)).unwrap();
    let half = load_blender(dir.path(), Split::Train, &opts(2, ViewSelection::All)).unwrap();
    assert_eq!((half.width, half.height), (4, 2));
    let (kf, kh) = (full.cameras[0].intrinsics, half.cameras[0].intrinsics);
    assert_eq!(kh.fx, kf.fx / 2.0);
    assert_eq!((kh.cx, kh.cy), (2.0, 1.0));
    assert!((kf.fx as f64 - 0.5 * 8.0 / (0.5 * ANGLE).tan()).abs() < 1e-5);
    for y in 0..2 {
        for x in 0..4 {
            for c in 0..4 {
                let p = |xx: usize, yy: usize| full.images[1].value(4 * (yy * 8 + xx) + c);
                let mean = (p(2 * x, 2 * y)
                    + p(2 * x + 1, 2 * y)
                    + p(2 * x, 2 * y + 1)
                    + p(2 * x + 1, 2 * y + 1))
                    / 4.0;
                let got = half.images[1].value(4 * (y * 4 + x) + c);
                // Held in 16 bits (a mean of 8-bit values is rarely one): within half a step.
                assert!((got - mean).abs() <= 0.5 / 65535.0 + 1e-7, "({x},{y}) c{c}: {got} vs {mean}");
            }
        }
    }
    // Known pattern: red = 17x/255, so the mean of columns 2x and 2x+1 is 17(2x+0.5)/255.
    assert!((half.images[0].value(4 * 3) - 17.0 * 6.5 / 255.0).abs() <= 0.5 / 65535.0 + 1e-7);
    assert!(full.images[1].is_rgba8() && !half.images[1].is_rgba8(), "8-bit photos in bytes, their means in 16 bits");
    // A factor that does not divide the size, and factor 0.
    let e = load_err(dir.path(), &opts(3, ViewSelection::All));
    assert!(matches!(e, DataError::BadDownscale { k: 3, .. }), "{e}");
    assert!(
        e.to_string().contains("r_0.png") && e.to_string().contains("8x4"),
        "{e}"
    );
    let e = load_err(dir.path(), &opts(0, ViewSelection::All));
    assert!(matches!(e, DataError::BadDownscale { k: 0, .. }), "{e}");
    assert!(e.to_string().contains("transforms_train.json"), "{e}");
}

#[test]
fn rgb_and_16_bit_pngs_are_accepted() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir_all(root.join("train")).unwrap();
    set_transforms(
        root,
        &json!({"camera_angle_x": ANGLE, "frames": frames_json(2)}),
    );
    let rgb = image::RgbImage::from_fn(4, 2, |x, y| image::Rgb([x as u8 * 60, y as u8 * 100, 255]));
    rgb.save(root.join("train/r_0.png")).unwrap();
    let rgba16 = image::ImageBuffer::<image::Rgba<u16>, Vec<u16>>::from_fn(4, 2, |x, y| {
        image::Rgba([x as u16 * 20000, 65535, y as u16 * 30000, 32768])
    });
    rgba16.save(root.join("train/r_1.png")).unwrap();
    let ds = load_blender(root, Split::Train, &LoadOptions::default()).unwrap();
    let px = |v: usize, x: usize, y: usize| ds.images[v].rgba(y * 4 + x);
    assert_eq!(px(0, 3, 1), [180.0 / 255.0, 100.0 / 255.0, 1.0, 1.0]);
    assert_eq!(
        px(1, 2, 1),
        [40000.0 / 65535.0, 1.0, 30000.0 / 65535.0, 32768.0 / 65535.0]
    );
}

/// WebP and TIFF photos (`file_path` with their extension) load as PNGs do; a float TIFF's values
/// past [0, 1] are clipped, and one that is not a number is an error naming the file.
#[test]
fn webp_and_tiff_photos_are_accepted() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir_all(root.join("train")).unwrap();
    let frames: Vec<Value> = ["r_0.png", "r_1.webp", "r_2.tif"]
        .iter()
        .map(|f| json!({"file_path": format!("train/{f}"), "transform_matrix": ident()}))
        .collect();
    set_transforms(root, &json!({"camera_angle_x": ANGLE, "frames": frames}));
    let img = image::RgbaImage::from_fn(4, 3, |x, y| image::Rgba([x as u8 * 60, y as u8 * 100, 7, if x == 0 { 0 } else { 255 }]));
    for f in ["r_0.png", "r_1.webp", "r_2.tif"] {
        img.save(root.join("train").join(f)).unwrap();
    }
    let ds = load_blender(root, Split::Train, &LoadOptions::default()).unwrap();
    assert!(ds.images[1] == ds.images[0] && ds.images[2] == ds.images[0], "lossless WebP and TIFF hold the PNG's pixels");
    // A float TIFF (what an HDR pipeline writes): clipped to [0, 1]; NaN refused.
    let float = |v: f32| image::DynamicImage::ImageRgb32F(image::ImageBuffer::from_fn(4, 3, |x, _| image::Rgb([if x == 1 { v } else { 0.25 }, 0.5, 1.0])));
    float(1.75).save(root.join("train/r_2.tif")).unwrap();
    let ds = load_blender(root, Split::Train, &LoadOptions::default()).unwrap();
    // Held in 16 bits: 0.25 and 0.5 within half a step.
    let near = |a: [f32; 4], b: [f32; 4]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= 0.5 / 65535.0);
    assert!(near(ds.images[2].rgba(0), [0.25, 0.5, 1.0, 1.0]) && near(ds.images[2].rgba(1), [1.0, 0.5, 1.0, 1.0]), "{:?}", ds.images[2].rgba(1));
    float(f32::NAN).save(root.join("train/r_2.tif")).unwrap();
    let e = load_blender(root, Split::Train, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("r_2.tif") && e.contains("pixel (1, 0)") && e.contains("NaN"), "{e}");
}

#[test]
fn sampled_rays_match_view_rays() {
    let ds = synthetic(4, 12, 10, 7);
    let mut rng = nerf_core::rng(3, 0);
    let mut batch = RayBatch::default();
    let mut view = RayBatch::default();
    let n = 20_000; // several parallel chunks
    for (bg, conv) in [
        (Background::White, PixelConvention::Center),
        (Background::Black, PixelConvention::Integer),
    ] {
        ds.sample_rays(n, bg, conv, false, &mut rng, &mut batch);
        assert_eq!(batch.len(), n);
        let mut seen = vec![false; ds.n_views()];
        for r in 0..n {
            let (v, p) = (batch.view_ids[r] as usize, batch.pixel_ids[r] as usize);
            seen[v] = true;
            ds.view_rays(v, bg, conv, &mut view);
            let s = 3 * r..3 * r + 3;
            let t = 3 * p..3 * p + 3;
            assert_eq!(&batch.origins[s.clone()], &view.origins[t.clone()]);
            assert_eq!(&batch.dirs[s.clone()], &view.dirs[t.clone()]);
            assert_eq!(&batch.target[s.clone()], &view.target[t.clone()]);
            assert_eq!(&batch.background[s], &view.background[t]);
            if r > 200 {
                break;
            }
        }
        assert!(seen.iter().filter(|&&s| s).count() >= 3);
    }
    // Random background + jitter: re-derive the pixel by projecting the ray into its camera
    // (found from the origin alone), check it lies inside that pixel and that the target is the
    // pixel composited onto the ray's own background.
    ds.sample_rays(
        n,
        Background::Random,
        PixelConvention::Center,
        true,
        &mut rng,
        &mut batch,
    );
    let mut black = RayBatch::default();
    let mut bg_sum = [0.0f64; 3];
    let mut frac_sum = 0.0f64;
    for r in 0..n {
        let o = Vec3::from_slice(&batch.origins[3 * r..]);
        let d = Vec3::from_slice(&batch.dirs[3 * r..]);
        assert!((d.length() - 1.0).abs() < 1e-5);
        let v = ds
            .cameras
            .iter()
            .position(|c| c.position == o)
            .expect("origin is a camera centre");
        assert_eq!(v, batch.view_ids[r] as usize);
        let cam = &ds.cameras[v];
        let k = cam.intrinsics;
        let dc = cam.rotation.transpose() * d;
        let u = k.cx + k.fx * dc.x / -dc.z;
        let vv = k.cy - k.fy * dc.y / -dc.z;
        let col = u.floor();
        // Allow for rounding right at a pixel edge.
        let p = batch.pixel_ids[r] as usize;
        let (pc, pr) = (p % 12, p / 12);
        assert!(
            (u - pc as f32 >= -1e-3) && (u - pc as f32 <= 1.0 + 1e-3),
            "u {u} outside pixel column {pc}"
        );
        assert!(
            (vv - pr as f32 >= -1e-3) && (vv - pr as f32 <= 1.0 + 1e-3),
            "v {vv} outside pixel row {pr}"
        );
        frac_sum += (u - col) as f64;
        let bg = &batch.background[3 * r..3 * r + 3];
        let a = ds.images[v].value(4 * p + 3);
        if r < 300 {
            ds.view_rays(v, Background::Black, PixelConvention::Center, &mut black);
            for (c, &b) in bg.iter().enumerate() {
                let want = black.target[3 * p + c] + (1.0 - a) * b;
                assert!((batch.target[3 * r + c] - want).abs() < 1e-6);
            }
        }
        for (s, &b) in bg_sum.iter_mut().zip(bg) {
            assert!((0.0..1.0).contains(&b));
            *s += b as f64;
        }
    }
    // Jitter spreads positions over the pixel (mean fraction ≈ 0.5, not all at the centre), and
    // the random backgrounds are uniform (mean ≈ 0.5).
    let mean_frac = frac_sum / n as f64;
    assert!((mean_frac - 0.5).abs() < 0.02, "{mean_frac}");
    for s in bg_sum {
        assert!((s / n as f64 - 0.5).abs() < 0.02, "{s}");
    }
    // Reproducible from the generator state; allocations reused for a smaller batch.
    let mut b1 = RayBatch::default();
    let mut b2 = RayBatch::default();
    ds.sample_rays(
        5000,
        Background::Random,
        PixelConvention::Center,
        true,
        &mut nerf_core::rng(9, 1),
        &mut b1,
    );
    ds.sample_rays(
        5000,
        Background::Random,
        PixelConvention::Center,
        true,
        &mut nerf_core::rng(9, 1),
        &mut b2,
    );
    assert_eq!(b1.dirs, b2.dirs);
    assert_eq!(b1.target, b2.target);
    ds.sample_rays(
        5000,
        Background::Random,
        PixelConvention::Center,
        true,
        &mut nerf_core::rng(9, 2),
        &mut b2,
    );
    assert_ne!(b1.dirs, b2.dirs);
    let cap = b1.origins.capacity();
    ds.sample_rays(
        10,
        Background::White,
        PixelConvention::Center,
        false,
        &mut rng,
        &mut b1,
    );
    assert_eq!((b1.len(), b1.target.len(), b1.view_ids.len()), (10, 30, 10));
    assert_eq!(b1.origins.capacity(), cap);
    b1.clear();
    assert!(b1.is_empty());
}

#[test]
fn view_rays_and_view_rgb_composite() {
    let ds = synthetic(2, 5, 3, 11);
    let mut b = RayBatch::default();
    ds.view_rays(1, Background::Random, PixelConvention::Integer, &mut b);
    assert_eq!(b.len(), 15);
    let white = ds.view_rgb(1, Background::White);
    let black = ds.view_rgb(1, Background::Black);
    assert_eq!(b.target, white, "Random is treated as white in view_rays");
    for p in 0..15 {
        let px = &ds.images[1].to_f32()[4 * p..4 * p + 4];
        for c in 0..3 {
            assert!((white[3 * p + c] - (px[c] * px[3] + 1.0 - px[3])).abs() < 1e-7);
            assert!((black[3 * p + c] - px[c] * px[3]).abs() < 1e-7);
        }
        let r = ds.cameras[1].ray((p % 5) as u32, (p / 5) as u32, PixelConvention::Integer);
        assert_eq!(&b.dirs[3 * p..3 * p + 3], &r.dir.to_array());
        assert_eq!(b.pixel_ids[p] as usize, p);
    }
}

#[test]
fn save_png_clamps_and_rounds() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sub/out.png");
    let rgb = [
        0.0f32,
        1.0,
        0.5,
        -0.3,
        1.7,
        0.2,
        f32::NAN,
        0.999,
        0.001,
        0.1,
        0.2,
        0.3,
        0.4,
        0.5,
        0.6,
        0.7,
        0.8,
        0.9,
    ];
    save_png(&path, 3, 2, &rgb).unwrap();
    let img = image::open(&path).unwrap().to_rgb8();
    assert_eq!((img.width(), img.height()), (3, 2));
    let want: Vec<u8> = vec![
        0, 255, 128, 0, 255, 51, 0, 255, 0, 26, 51, 77, 102, 128, 153, 179, 204, 230,
    ];
    assert_eq!(img.into_raw(), want);
    // Writing onto a directory fails with an error naming the path.
    let e = save_png(dir.path(), 3, 2, &rgb).unwrap_err();
    assert!(matches!(e, DataError::Io { .. }));
    assert!(
        e.to_string().contains(&dir.path().display().to_string()),
        "{e}"
    );
}

// --- Errors: each writes a small broken scene and checks the variant and that the message
// names the file.

#[test]
fn error_missing_transforms() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 1, 4, 4);
    let e = load_blender(dir.path(), Split::Val, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::MissingTransforms { .. }), "{e}");
    assert!(e.to_string().contains("transforms_val.json"), "{e}");
}

#[test]
fn error_malformed_json() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 1, 4, 4);
    std::fs::write(
        dir.path().join("transforms_train.json"),
        "{\n  \"camera_angle_x\": 0.5,\n  \"frames\": [,]\n}",
    )
    .unwrap();
    let e = load_err(dir.path(), &LoadOptions::default());
    assert!(matches!(e, DataError::Json { .. }), "{e}");
    let msg = e.to_string();
    assert!(
        msg.contains("transforms_train.json") && msg.contains("line 3"),
        "{msg}"
    );
}

#[test]
fn error_missing_keys() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 2, 4, 4);
    let cases = [
        (json!({"frames": frames_json(2)}), "camera_angle_x` or `fl_x"),
        (json!({"camera_angle_x": ANGLE}), "frames"),
        (
            json!({"camera_angle_x": ANGLE, "frames": [
                {"file_path": "./train/r_0", "transform_matrix": ident()},
                {"transform_matrix": ident()}]}),
            "frames[1].file_path",
        ),
        (
            json!({"camera_angle_x": ANGLE, "frames": [{"file_path": "./train/r_0"}]}),
            "frames[0].transform_matrix",
        ),
    ];
    for (t, key) in cases {
        set_transforms(dir.path(), &t);
        let e = load_err(dir.path(), &LoadOptions::default());
        match &e {
            DataError::MissingKey { key: k, .. } => assert_eq!(k, key),
            other => panic!("expected MissingKey({key}), got {other}"),
        }
        let msg = e.to_string();
        assert!(
            msg.contains("transforms_train.json") && msg.contains(key),
            "{msg}"
        );
    }
    // Wrong types are InvalidValue.
    set_transforms(
        dir.path(),
        &json!({"camera_angle_x": "wide", "frames": frames_json(2)}),
    );
    let e = load_err(dir.path(), &LoadOptions::default());
    assert!(
        matches!(e, DataError::InvalidValue { .. })
            && e.to_string().contains("transforms_train.json"),
        "{e}"
    );
}

#[test]
fn error_missing_image() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 2, 4, 4);
    std::fs::remove_file(dir.path().join("train/r_1.png")).unwrap();
    let e = load_err(dir.path(), &LoadOptions::default());
    assert!(matches!(e, DataError::MissingImage { frame: 1, .. }), "{e}");
    assert!(e.to_string().contains("r_1.png"), "{e}");
    // Not selected → not needed.
    assert!(load_blender(dir.path(), Split::Train, &opts(1, ViewSelection::First(1))).is_ok());
}

#[test]
fn error_undecodable_image() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 2, 4, 4);
    std::fs::write(
        dir.path().join("train/r_0.png"),
        b"\x89PNG\r\n\x1a\nthis is not a png",
    )
    .unwrap();
    let e = load_err(dir.path(), &LoadOptions::default());
    assert!(matches!(e, DataError::Decode { .. }), "{e}");
    assert!(e.to_string().contains("r_0.png"), "{e}");
}

#[test]
fn error_size_mismatch() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 3, 4, 4);
    image::RgbaImage::new(4, 6)
        .save(dir.path().join("train/r_2.png"))
        .unwrap();
    let e = load_err(dir.path(), &LoadOptions::default());
    assert!(
        matches!(
            e,
            DataError::SizeMismatch {
                width: 4,
                height: 6,
                first_width: 4,
                first_height: 4,
                ..
            }
        ),
        "{e}"
    );
    let msg = e.to_string();
    assert!(msg.contains("r_2.png") && msg.contains("r_0.png"), "{msg}");
}

#[test]
fn error_non_finite_pose() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 2, 4, 4);
    // 1e39 is a finite JSON number but overflows f32.
    let mut frames = frames_json(2);
    frames[1]["transform_matrix"][0][3] = json!(1e39);
    set_transforms(
        dir.path(),
        &json!({"camera_angle_x": ANGLE, "frames": frames}),
    );
    let e = load_err(dir.path(), &LoadOptions::default());
    assert!(
        matches!(e, DataError::NonFinitePose { frame: 1, .. }),
        "{e}"
    );
    let msg = e.to_string();
    assert!(
        msg.contains("transforms_train.json") && msg.contains("frame 1"),
        "{msg}"
    );
}

#[test]
fn error_degenerate_pose() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 2, 4, 4);
    // A zeroed rotation block: every pixel's ray would have no direction.
    let mut frames = frames_json(2);
    frames[1]["transform_matrix"] = json!([[0, 0, 0, 1], [0, 0, 0, 2], [0, 0, 0, 3], [0, 0, 0, 1]]);
    set_transforms(
        dir.path(),
        &json!({"camera_angle_x": ANGLE, "frames": frames}),
    );
    let e = load_err(dir.path(), &LoadOptions::default());
    assert!(
        matches!(e, DataError::BadPose { frame: 1, .. }),
        "{e}"
    );
    let msg = e.to_string();
    assert!(
        msg.contains("transforms_train.json") && msg.contains("frame 1") && msg.contains("degenerate"),
        "{msg}"
    );
}

#[test]
fn error_bad_matrix_shape() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 2, 4, 4);
    for bad in [
        json!([[1, 0, 0, 0], [0, 1, 0, 0]]),
        json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
        json!([
            [1, 0, 0, 0],
            [0, 1, 0, 0],
            [0, 0, 1, 4],
            [0, 0, 0, 1],
            [0, 0, 0, 1]
        ]),
        json!([[1, 0, 0, 0], [0, 1, "x", 0], [0, 0, 1, 4]]),
        json!("identity"),
    ] {
        let mut frames = frames_json(2);
        frames[1]["transform_matrix"] = bad.clone();
        set_transforms(
            dir.path(),
            &json!({"camera_angle_x": ANGLE, "frames": frames}),
        );
        let e = load_err(dir.path(), &LoadOptions::default());
        assert!(
            matches!(e, DataError::BadMatrix { frame: 1, .. }),
            "{bad}: {e}"
        );
        assert!(e.to_string().contains("transforms_train.json"), "{e}");
    }
    // 3x4 is accepted.
    let mut frames = frames_json(2);
    frames[1]["transform_matrix"] = json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4]]);
    set_transforms(
        dir.path(),
        &json!({"camera_angle_x": ANGLE, "frames": frames}),
    );
    let ds = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!(ds.cameras[1].position, Vec3::new(0.0, 0.0, 4.0));
}

#[test]
fn error_empty_split() {
    let dir = tempfile::tempdir().unwrap();
    good_scene(dir.path(), 2, 4, 4);
    let e = load_err(dir.path(), &opts(1, ViewSelection::First(0)));
    assert!(matches!(e, DataError::EmptySplit { .. }), "{e}");
    assert!(
        e.to_string().contains("transforms_train.json") && e.to_string().contains("first:0"),
        "{e}"
    );
    let e = load_err(dir.path(), &opts(1, ViewSelection::Every(0)));
    assert!(matches!(e, DataError::BadSelection { .. }), "{e}");
    set_transforms(dir.path(), &json!({"camera_angle_x": ANGLE, "frames": []}));
    let e = load_err(dir.path(), &LoadOptions::default());
    assert!(matches!(e, DataError::EmptySplit { .. }), "{e}");
    assert!(e.to_string().contains("transforms_train.json"), "{e}");
}

#[test]
fn lego_train_downscaled() {
    let Some(lego) = nerf_core::shared::data(env!("CARGO_MANIFEST_DIR"), "nerf_synthetic/lego")
    else {
        return;
    };
    let ds = load_blender(&lego, Split::Train, &opts(8, ViewSelection::First(2))).unwrap();
    assert_eq!((ds.width, ds.height, ds.n_views()), (100, 100, 2));
    let k = ds.cameras[0].intrinsics;
    assert!((k.fx - 1111.1111 / 8.0).abs() < 1e-2, "focal {}", k.fx);
    assert!((k.fx - 138.8889).abs() < 1e-3, "focal {}", k.fx);
    assert_eq!((k.cx, k.cy), (50.0, 50.0));
    assert_eq!(ds.images[0].len(), 4 * 100 * 100);
    assert!(ds.images[0].to_f32().iter().all(|v| (0.0..=1.0).contains(v)));
    // Frame 0 of lego: camera centre (-0.0538, 3.8455, 1.2081); it sees the object (lego fits the
    // AABB) and the centre ray of the view hits the box.
    assert!(
        (ds.cameras[0].position - Vec3::new(-0.05379832, 3.8454704, 1.2080823)).length() < 1e-6
    );
    let r = ds.cameras[0].ray_at(50.0, 50.0);
    assert!(ds
        .aabb
        .intersect(r.origin.to_array(), r.dir.to_array())
        .is_some());
    // Alpha: transparent corners, opaque somewhere in the middle.
    assert_eq!(ds.images[0].value(3), 0.0);
    assert!(ds.images[0].to_f32().chunks_exact(4).any(|p| p[3] == 1.0));
    // Downscaled pixels are the 8x8 box means of the full-resolution image.
    let full = load_blender(&lego, Split::Train, &opts(1, ViewSelection::First(1))).unwrap();
    assert_eq!(full.width, 800);
    let mut max_err = 0.0f32;
    for y in 0..100 {
        for x in 0..100 {
            for c in 0..4 {
                let mut s = 0.0f64;
                for yy in 0..8 {
                    for xx in 0..8 {
                        s += full.images[0].value(4 * ((8 * y + yy) * 800 + 8 * x + xx) + c) as f64;
                    }
                }
                max_err =
                    max_err.max((ds.images[0].value(4 * (y * 100 + x) + c) - (s / 64.0) as f32).abs());
            }
        }
    }
    assert!(max_err < 1e-5, "{max_err}");
    // lego has no val split.
    let e = load_blender(&lego, Split::Val, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::MissingTransforms { .. }));
}

#[test]
fn cameras_only_gives_the_full_loads_cameras_without_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let ds = synthetic(4, 8, 6, 5);
    write_blender(&ds, dir.path(), None).unwrap();
    for (k, views) in [(1, ViewSelection::All), (2, ViewSelection::Every(2))] {
        let full = load_blender(dir.path(), Split::Train, &opts(k, views.clone())).unwrap();
        let cams = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..opts(k, views) }).unwrap();
        assert!(full.has_images() && !cams.has_images());
        assert_eq!(cams.images.len(), cams.n_views());
        assert_eq!((cams.width, cams.height, cams.n_views()), (full.width, full.height, full.n_views()));
        assert_eq!(cams.file_paths, full.file_paths);
        for (a, b) in cams.cameras.iter().zip(&full.cameras) {
            assert_eq!((a.rotation, a.position, a.intrinsics), (b.rotation, b.position, b.intrinsics));
        }
        assert_eq!((cams.near, cams.far, cams.aabb), (full.near, full.far, full.aabb));
    }
    // The same size checks as a full load, naming the file; writing it back is refused.
    let cams = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap();
    let e = write_blender(&cams, &dir.path().join("copy"), None).unwrap_err().to_string();
    assert!(e.contains("cameras_only"), "{e}");
    let e = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..opts(3, ViewSelection::All) }).unwrap_err().to_string();
    assert!(e.contains("r_0.png") && e.contains("8x6"), "{e}");
    save_png(&dir.path().join("train/r_2.png"), 4, 6, &vec![0.5; 3 * 24]).unwrap();
    let e = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap_err().to_string();
    assert!(e.contains("r_2.png") && e.contains("r_0.png"), "{e}");
    std::fs::write(dir.path().join("train/r_1.png"), b"not a png").unwrap();
    let e = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap_err().to_string();
    assert!(e.contains("r_1.png"), "{e}");
}

/// `sample_camera_rays` on a cameras-only load draws the rays `sample_rays` draws on the full load
/// from the same generator state (random backgrounds, jitter), with NaN targets.
#[test]
fn camera_rays_of_a_cameras_only_load_are_the_full_loads_rays() {
    let dir = tempfile::tempdir().unwrap();
    write_blender(&synthetic(3, 8, 6, 9), dir.path(), None).unwrap();
    let full = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    let cams = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap();
    for (background, jitter) in [(Background::Random, true), (Background::White, false)] {
        let (mut a, mut b) = (RayBatch::default(), RayBatch::default());
        let (mut ra, mut rb) = (nerf_core::rng(5, 1), nerf_core::rng(5, 1));
        full.sample_rays(3000, background, PixelConvention::Center, jitter, &mut ra, &mut a);
        cams.sample_camera_rays(3000, background, PixelConvention::Center, jitter, &mut rb, &mut b);
        assert_eq!((a.origins, a.dirs, a.background), (b.origins, b.dirs, b.background));
        assert_eq!((a.view_ids, a.pixel_ids), (b.view_ids, b.pixel_ids));
        assert!(a.target.iter().all(|t| t.is_finite()) && b.target.iter().all(|t| t.is_nan()) && b.target.len() == 9000);
        // The generators advanced alike.
        assert_eq!(ra.gen::<u64>(), rb.gen::<u64>());
    }
}

#[test]
#[should_panic(expected = "cameras_only")]
fn reading_pixels_of_a_cameras_only_load_is_a_clear_panic() {
    let dir = tempfile::tempdir().unwrap();
    write_blender(&synthetic(2, 8, 6, 7), dir.path(), None).unwrap();
    let cams = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap();
    let mut rng = nerf_core::rng(1, 0);
    cams.sample_rays(4, Background::White, PixelConvention::Center, false, &mut rng, &mut RayBatch::default());
}

/// Random keep flags for `n` views of `w·h` pixels; view 1 keeps every pixel.
fn random_flags(n: usize, w: u32, h: u32, seed: u64) -> Vec<Vec<bool>> {
    let mut r = rand::rngs::StdRng::seed_from_u64(seed);
    (0..n).map(|v| (0..w * h).map(|_| v == 1 || r.gen_bool(0.4)).collect()).collect()
}

/// Training masks (nerfstudio's `mask_path`) are written beside the images, read back as they
/// were, and training rays come from kept pixels only, every kept pixel in turn.
#[test]
fn masks_round_trip_and_training_rays_draw_only_kept_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let mut ds = synthetic(3, 8, 6, 2);
    let flags = random_flags(3, 8, 6, 3);
    ds.masks = Some(PixelMasks::from_flags(8 * 6, flags.iter().map(|f| &f[..])));
    write_blender(&ds, dir.path(), None).unwrap();
    let json: Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("transforms_train.json")).unwrap()).unwrap();
    assert_eq!(json["frames"][2]["mask_path"], "./train/mask_2.png");
    let mask = image::open(dir.path().join("train/mask_0.png")).unwrap();
    assert_eq!(mask.color(), image::ColorType::L8);
    let back = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!(back.masks, ds.masks);
    let kept = back.masks.as_ref().unwrap().total() as usize;
    let mut rng = nerf_core::rng(5, 0);
    let mut batch = RayBatch::default();
    back.sample_rays(4000, Background::Black, PixelConvention::Center, false, &mut rng, &mut batch);
    let mut drawn = std::collections::HashSet::new();
    for (k, (&v, &p)) in batch.view_ids.iter().zip(&batch.pixel_ids).enumerate() {
        assert!(flags[v as usize][p as usize], "ray {k}: masked-out pixel {p} of view {v} drawn");
        let px = &back.images[v as usize].to_f32()[4 * p as usize..4 * p as usize + 4];
        let want: Vec<f32> = (0..3).map(|c| px[c] * px[3]).collect();
        assert_eq!(&batch.target[3 * k..3 * k + 3], &want[..], "ray {k}: target of another pixel");
        drawn.insert((v, p));
    }
    assert_eq!(drawn.len(), kept, "every kept pixel is drawn in 4000 rays of {kept}");
    // Uniform over kept pixels, not over views: view 1 keeps all 48 pixels, the others ~40 %.
    let from_1 = batch.view_ids.iter().filter(|&&v| v == 1).count() as f64 / 4000.0;
    let share_1 = 48.0 / kept as f64;
    assert!((from_1 - share_1).abs() < 0.04, "view 1 gave {from_1:.3} of the rays, keeps {share_1:.3} of the pixels");
    // A selection of views takes its views' masks.
    let sel = load_blender(dir.path(), Split::Train, &opts(1, ViewSelection::Every(2))).unwrap();
    assert_eq!(sel.masks, Some(ds.masks.as_ref().unwrap().select(&[0, 2])));
    // A load without pixels has no masks (its rays are cast from every pixel).
    let cams = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap();
    assert!(cams.masks.is_none());
    // Masks that do not match the views are not written.
    let bad = Dataset { masks: Some(ds.masks.as_ref().unwrap().select(&[0])), ..ds.clone() };
    let e = write_blender(&bad, &dir.path().join("bad"), None).unwrap_err().to_string();
    assert!(e.contains("masks of 1 views of 48 pixels for 3 views of 8x6"), "{e}");
}

/// Downscaled, a pixel is kept only where all the k×k mask pixels it averages are; any non-zero
/// grey (here 1 of 255) or colour keeps a pixel.
#[test]
fn downscaled_masks_keep_only_wholly_kept_blocks() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (8u32, 6u32);
    good_scene(dir.path(), 2, w, h);
    let flags = random_flags(2, w, h, 7);
    let mut frames = frames_json(2);
    for (i, f) in flags.iter().enumerate() {
        frames[i]["mask_path"] = json!(format!("masks/m{i}.png"));
        std::fs::create_dir_all(dir.path().join("masks")).unwrap();
        // View 0: grey 1 keeps; view 1: an RGB mask, kept where red or blue is non-zero.
        if i == 0 {
            image::GrayImage::from_fn(w, h, |x, y| image::Luma([f[(y * w + x) as usize] as u8])).save(dir.path().join("masks/m0.png")).unwrap();
        } else {
            image::RgbImage::from_fn(w, h, |x, y| {
                let k = f[(y * w + x) as usize];
                image::Rgb([(k && x % 2 == 0) as u8 * 200, 0, (k && x % 2 == 1) as u8 * 3])
            })
            .save(dir.path().join("masks/m1.png"))
            .unwrap();
        }
    }
    set_transforms(dir.path(), &json!({"camera_angle_x": ANGLE, "frames": frames}));
    let full = load_blender(dir.path(), Split::Train, &opts(1, ViewSelection::All)).unwrap();
    assert_eq!(full.masks, Some(PixelMasks::from_flags(w * h, flags.iter().map(|f| &f[..]))));
    let half = load_blender(dir.path(), Split::Train, &opts(2, ViewSelection::All)).unwrap();
    let m = half.masks.unwrap();
    for (v, f) in flags.iter().enumerate() {
        for (y, x) in (0..h / 2).flat_map(|y| (0..w / 2).map(move |x| (y, x))) {
            let all = (0..4).all(|d| f[((2 * y + d / 2) * w + 2 * x + d % 2) as usize]);
            assert_eq!(m.is_kept(v, y * (w / 2) + x), all, "view {v}, pixel ({x}, {y})");
        }
    }
}

#[test]
fn error_bad_masks() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    good_scene(root, 2, 4, 3);
    let with_masks = |paths: [Value; 2]| {
        let mut frames = frames_json(2);
        for (i, p) in paths.into_iter().enumerate() {
            if !p.is_null() {
                frames[i]["mask_path"] = p;
            }
        }
        set_transforms(root, &json!({"camera_angle_x": ANGLE, "frames": frames}));
    };
    let gray = |name: &str, w: u32, h: u32, v: u8| image::GrayImage::from_pixel(w, h, image::Luma([v])).save(root.join(name)).unwrap();
    gray("train/m0.png", 4, 3, 255);
    // A missing mask file: named, with its frame.
    with_masks([json!("train/m0.png"), json!("train/m1.png")]);
    let e = load_err(root, &LoadOptions::default());
    assert!(matches!(e, DataError::BadMask { frame: 1, .. }), "{e:?}");
    assert!(e.to_string().contains("m1.png") && e.to_string().contains("not found"), "{e}");
    // A mask of another size than its image.
    gray("train/m1.png", 3, 4, 255);
    let e = load_err(root, &LoadOptions::default()).to_string();
    assert!(e.contains("m1.png") && e.contains("mask of frame 1") && e.contains("3x4") && e.contains("4x3"), "{e}");
    // A mask for some frames only, or a mask_path that is not a string.
    with_masks([json!("train/m0.png"), Value::Null]);
    let e = load_err(root, &LoadOptions::default()).to_string();
    assert!(e.contains("frames[1].mask_path") && e.contains("every frame a mask or none"), "{e}");
    with_masks([json!("train/m0.png"), json!(7)]);
    let e = load_err(root, &LoadOptions::default()).to_string();
    assert!(e.contains("frames[1].mask_path") && e.contains("expected a string"), "{e}");
    // Masks that keep nothing.
    gray("train/m0.png", 4, 3, 0);
    gray("train/m1.png", 4, 3, 0);
    with_masks([json!("train/m0.png"), json!("train/m1.png")]);
    let e = load_err(root, &LoadOptions::default());
    assert!(matches!(e, DataError::EmptySplit { .. }) && e.to_string().contains("nothing to train on"), "{e}");
}

/// instant-ngp's dynamic masks (`dynamic_mask_<name>.png` beside a photo, non-zero where something
/// moved) drop their non-zero pixels; a photo without one keeps all of its pixels; `mask_path`
/// takes precedence over them.
#[test]
fn instant_ngp_dynamic_masks_drop_their_non_zero_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (w, h) = (6u32, 4u32);
    good_scene(root, 3, w, h);
    let moved = |x: u32, y: u32| x >= 2 && y >= 1;
    image::GrayImage::from_fn(w, h, |x, y| image::Luma([if moved(x, y) { 255 } else { 0 }])).save(root.join("train/dynamic_mask_r_0.png")).unwrap();
    image::GrayImage::from_pixel(w, h, image::Luma([0])).save(root.join("train/dynamic_mask_r_2.png")).unwrap();
    let ds = load_blender(root, Split::Train, &LoadOptions::default()).unwrap();
    let m = ds.masks.as_ref().expect("dynamic masks read");
    let want0: Vec<u32> = (0..w * h).filter(|&p| !moved(p % w, p / w)).collect();
    assert_eq!(m.view(0), Some(&want0[..]));
    assert_eq!((m.view(1), m.kept_in(1)), (None, (w * h) as u64), "a photo without a dynamic mask keeps every pixel");
    assert_eq!((m.view(2), m.kept_in(2)), (None, (w * h) as u64));
    // Downscaled by 2: a pixel is dropped where any of its four moved.
    let half = load_blender(root, Split::Train, &opts(2, ViewSelection::All)).unwrap();
    assert_eq!(half.masks.unwrap().view(0), Some(&[0, 3][..]));
    // nerfstudio's mask_path wins over them.
    let mut frames = frames_json(3);
    for i in 0..3 {
        frames[i]["mask_path"] = json!("train/keep.png");
    }
    image::GrayImage::from_pixel(w, h, image::Luma([255])).save(root.join("train/keep.png")).unwrap();
    set_transforms(root, &json!({"camera_angle_x": ANGLE, "frames": frames}));
    let ds = load_blender(root, Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!(ds.masks.unwrap().total(), 3 * (w * h) as u64);
}
