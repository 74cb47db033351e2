//! instant-ngp / nerfstudio transforms files: one `transforms.json` for all views, intrinsics in
//! pixels, lens distortion, the scene box keys, JPEG images, and their errors. Fixtures are
//! written into temporary folders, from the in-repo scene `scenes/lego_100` or synthesised.

use std::path::{Path, PathBuf};

use nerf_data::ngp::{undistort_rgba, NGP_NEAR};
use nerf_data::ngp::pixels_seen;
use nerf_data::{load_blender, load_scene, DataError, Dataset, Distortion, LensModel, LoadOptions, NgpBox, Split, ViewSelection};
use nerf_rays::Intrinsics;
use serde_json::{json, Value};

fn lego_100() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/lego_100")
}

fn load(root: &Path, split: Split) -> Dataset {
    load_blender(root, split, &LoadOptions::default()).unwrap_or_else(|e| panic!("{e}"))
}

/// [`load`] with the photos of lenses resampled to pinhole cameras (`LoadOptions::undistort`).
fn load_undistorted(root: &Path, split: Split, downscale: u32) -> Dataset {
    load_blender(root, split, &LoadOptions { undistort: true, downscale, ..LoadOptions::default() }).unwrap_or_else(|e| panic!("{e}"))
}

fn write_json(path: &Path, v: &Value) {
    std::fs::write(path, serde_json::to_string_pretty(v).unwrap()).unwrap();
}

/// The frames of a Blender split file with absolute image paths (`root.join` keeps them).
fn frames_of(root: &Path, split: &str) -> Vec<Value> {
    let v: Value = serde_json::from_str(&std::fs::read_to_string(root.join(format!("transforms_{split}.json"))).unwrap()).unwrap();
    v["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            let rel = f["file_path"].as_str().unwrap().trim_start_matches("./");
            json!({"file_path": root.join(format!("{rel}.png")).to_str().unwrap(), "transform_matrix": f["transform_matrix"]})
        })
        .collect()
}

/// 4 test and 28 training frames of lego_100 interleaved so that every 8th frame is a test frame.
fn interleaved_lego() -> Vec<Value> {
    let (train, test) = (frames_of(&lego_100(), "train"), frames_of(&lego_100(), "test"));
    let (mut tr, mut te) = (train.into_iter(), test.into_iter());
    (0..32).map(|i| if i % 8 == 0 { te.next().unwrap() } else { tr.next().unwrap() }).collect()
}

fn assert_same_views(a: &Dataset, b: &Dataset) {
    assert_eq!(a.n_views(), b.n_views());
    assert_eq!((a.width, a.height), (b.width, b.height));
    for (ca, cb) in a.cameras.iter().zip(&b.cameras) {
        assert_eq!(ca.intrinsics, cb.intrinsics);
        assert_eq!(ca.position, cb.position);
        assert_eq!(ca.rotation, cb.rotation);
        assert_eq!(ca.distortion, cb.distortion);
    }
    assert!(a.images == b.images, "images differ");
}

#[test]
fn one_transforms_json_holds_both_splits_every_8th_frame_a_test_view() {
    let lego = lego_100();
    let (bl_train, bl_test) = (load(&lego, Split::Train), load(&lego, Split::Test));
    let k = bl_train.cameras[0].intrinsics;
    let dir = tempfile::tempdir().unwrap();
    // Intrinsics in pixels (instant-ngp / nerfstudio) and as Blender's field of view.
    for top in [
        json!({"fl_x": k.fx as f64, "fl_y": k.fy as f64, "cx": 50.0, "cy": 50.0, "w": 100, "h": 100}),
        json!({"camera_angle_x": serde_json::from_str::<Value>(&std::fs::read_to_string(lego.join("transforms_train.json")).unwrap()).unwrap()["camera_angle_x"]}),
    ] {
        let mut t = top.as_object().unwrap().clone();
        t.insert("frames".into(), Value::Array(interleaved_lego()));
        write_json(&dir.path().join("transforms.json"), &Value::Object(t));
        let train = load_scene(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
        let test = load_scene(dir.path(), Split::Test, &LoadOptions::default()).unwrap();
        let val = load_scene(dir.path(), Split::Val, &LoadOptions::default()).unwrap();
        let first = |d: &Dataset, n: usize| Dataset {
            cameras: d.cameras[..n].to_vec(),
            images: d.images[..n].to_vec(),
            ..d.clone()
        };
        assert_same_views(&train, &first(&bl_train, 28));
        assert_same_views(&test, &first(&bl_test, 4));
        assert_same_views(&val, &test);
        // One set of bounds for every split and selection (the trainer's come from the training split).
        let one = load_scene(dir.path(), Split::Test, &LoadOptions { views: ViewSelection::First(1), ..Default::default() }).unwrap();
        for d in [&test, &one] {
            assert_eq!((d.near, d.far, d.aabb), (train.near, train.far, train.aabb));
        }
        // The scene sits in instant-ngp's default cube (scale 0.33, offset 0.5, aabb_scale 1).
        for d in [&train, &test] {
            assert_eq!(d.ngp, Some(NgpBox::default()));
            assert!(d.clips_to_aabb());
            assert!((d.aabb.max[0] - 0.5 / 0.33).abs() < 1e-6 && (d.aabb.min[2] + 0.5 / 0.33).abs() < 1e-6, "{:?}", d.aabb);
            assert!((d.near - NGP_NEAR / 0.33).abs() < 1e-6);
        }
        // A view selection applies within the split.
        let o = LoadOptions { views: ViewSelection::Every(3), ..Default::default() };
        let sel = load_scene(dir.path(), Split::Train, &o).unwrap();
        assert_eq!(sel.n_views(), 10);
        assert_eq!(sel.cameras[1].position, train.cameras[3].position);
        // Downscaling halves the intrinsics as for Blender scenes.
        let o = LoadOptions { downscale: 2, ..Default::default() };
        let half = load_scene(dir.path(), Split::Test, &o).unwrap();
        assert_eq!(half.cameras[0].intrinsics, k.downscaled(2));
        assert_eq!(half.images[0].len(), 4 * 50 * 50);
    }
    // The split files win over transforms.json.
    std::fs::copy(lego.join("transforms_test.json"), dir.path().join("transforms_test.json")).unwrap();
    std::fs::create_dir_all(dir.path().join("test")).unwrap();
    for i in 0..25 {
        std::fs::copy(lego.join(format!("test/r_{i}.png")), dir.path().join(format!("test/r_{i}.png"))).unwrap();
    }
    let test = load(dir.path(), Split::Test);
    assert_eq!(test.n_views(), 25);
    assert_eq!((test.near, test.far, test.ngp), (2.0, 6.0, None));
    assert!(!test.clips_to_aabb());
}

/// A split scene of 2 grey 4×4 views with `top`'s keys and per-frame extras.
fn tiny_scene(root: &Path, top: Value, frame_extra: [Value; 2]) {
    let img = image::RgbaImage::from_pixel(4, 4, image::Rgba([100, 150, 200, 255]));
    std::fs::create_dir_all(root.join("train")).unwrap();
    let mut frames = vec![];
    for (i, extra) in frame_extra.into_iter().enumerate() {
        img.save(root.join(format!("train/r_{i}.png"))).unwrap();
        let mut f = json!({
            "file_path": format!("./train/r_{i}"),
            "transform_matrix": [[1, 0, 0, 0.1 * i as f64], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]],
        });
        f.as_object_mut().unwrap().extend(extra.as_object().unwrap().clone());
        frames.push(f);
    }
    let mut t = top;
    t.as_object_mut().unwrap().insert("frames".into(), Value::Array(frames));
    write_json(&root.join("transforms_train.json"), &t);
}

#[test]
fn intrinsics_keys_in_pixels_degrees_or_radians_and_per_frame() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(
        dir.path(),
        json!({"fl_x": 3.0, "fl_y": 5.0, "cx": 1.5, "cy": 2.25, "w": 4, "h": 4}),
        [json!({}), json!({"fl_x": 7.0, "cx": 2.5})],
    );
    let d = load(dir.path(), Split::Train);
    let k = |fx, fy, cx, cy| Intrinsics { width: 4, height: 4, fx, fy, cx, cy };
    assert_eq!(d.cameras[0].intrinsics, k(3.0, 5.0, 1.5, 2.25));
    assert_eq!(d.cameras[1].intrinsics, k(7.0, 5.0, 2.5, 2.25));
    assert_eq!(d.ngp, None, "no box keys in a split file: NeRF's Blender bounds");
    assert_eq!((d.near, d.far), (2.0, 6.0));
    // x_fov (degrees) wins over fl_x, which wins over camera_angle_x; no fl_y: fy = fx; no cx: W/2.
    tiny_scene(
        dir.path(),
        json!({"x_fov": 90.0, "fl_x": 3.0, "camera_angle_x": 1.0}),
        [json!({}), json!({"x_fov": null, "camera_angle_y": std::f64::consts::FRAC_PI_2})],
    );
    let d = load(dir.path(), Split::Train);
    let f90 = (0.5 * 4.0 / (0.25 * std::f64::consts::PI).tan()) as f32;
    assert_eq!(d.cameras[0].intrinsics, k(f90, f90, 2.0, 2.0));
    assert_eq!(d.cameras[1].intrinsics, k(3.0, f90, 2.0, 2.0), "a null x_fov in the frame falls back to fl_x");
}

#[test]
fn box_keys_place_instant_ngps_cube_and_rays_end_past_it() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(dir.path(), json!({"camera_angle_x": 0.8, "aabb_scale": 2, "scale": 0.5, "offset": [0.5, 0.25, 0.5]}), [json!({}), json!({})]);
    let d = load(dir.path(), Split::Train);
    let b = NgpBox { scale: 0.5, offset: [0.5, 0.25, 0.5], aabb_scale: 2.0 };
    assert_eq!(d.ngp, Some(b));
    // (0.5 ∓ aabb_scale/2 − offset) / scale
    assert_eq!(d.aabb.min, [-2.0, -1.5, -2.0]);
    assert_eq!(d.aabb.max, [2.0, 2.5, 2.0]);
    assert_eq!(d.near, NGP_NEAR / 0.5);
    // Every ray from every camera leaves the cube before `far`.
    for c in &d.cameras {
        for m in 0..8 {
            let corner = glam::Vec3::from_array(std::array::from_fn(|a| if m >> a & 1 == 1 { d.aabb.max[a] } else { d.aabb.min[a] }));
            assert!((corner - c.position).length() < d.far);
        }
    }
    assert!(d.far < 2.0 * 7.0, "far is the farthest corner, not arbitrarily large: {}", d.far);
    // instant-ngp's `aabb` (the scene's box, as RGB-D capture tools write it) instead of `scale`
    // and `offset`: scale = 1 / its longest side, its centre at 0.5; it wins over `scale`. The
    // training cube is then the smallest cube about the box's centre that holds it.
    for top in [
        json!({"camera_angle_x": 0.8, "aabb": [[-1, -2, 0], [3, 1, 1]]}),
        json!({"camera_angle_x": 0.8, "aabb": [[3, 1, 1], [-1, -2, 0]], "scale": 9.0, "applied_transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]}),
    ] {
        tiny_scene(dir.path(), top.clone(), [json!({}), json!({})]);
        let d = load(dir.path(), Split::Train);
        assert_eq!(d.ngp, Some(NgpBox { scale: 0.25, offset: [0.25, 0.625, 0.375], aabb_scale: 1.0 }), "{top}");
        assert_eq!((d.aabb.min, d.aabb.max), ([-1.0, -2.5, -1.5], [3.0, 1.5, 2.5]), "{top}");
        assert!(!nerf_data::ngp::is_nerfstudio(&top), "a file with `aabb` is instant-ngp's, not nerfstudio's");
    }
}

#[test]
fn camera_and_box_errors_name_the_file_and_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let cases: [(Value, [Value; 2], &str, &str); 30] = [
        (json!({"fl_x": 3.0, "aabb": [[0, 0, 0], [1, 1]]}), [json!({}), json!({})], "`aabb`", "finite numbers"),
        (json!({"fl_x": 3.0, "aabb": [[1, 1, 1], [1, 1, 1]]}), [json!({}), json!({})], "`aabb`", "a box with a side"),
        (json!({"fl_x": 3.0, "w": 8, "h": 4}), [json!({}), json!({})], "`w`", "r_0.png is 4x4"),
        (json!({"fl_x": 3.0, "w": 4}), [json!({}), json!({})], "`h`", "missing key"),
        (json!({"fl_x": -3.0}), [json!({}), json!({})], "`fl_x`", "not positive"),
        (json!({"fl_x": 3.0}), [json!({}), json!({"fl_y": "tall"})], "`frames[1].fl_y`", "expected a number"),
        (json!({"fl_x": 3.0, "camera_model": "VR180_L"}), [json!({}), json!({})], "`camera_model`", "not supported"),
        (json!({"fl_x": 3.0, "camera_model": "FOV"}), [json!({}), json!({})], "`camera_model`", "needs its field of view `omega`"),
        (json!({"fl_x": 3.0}), [json!({}), json!({"omega": 0.9})], "`frames[1].omega`", "belongs to the FOV model"),
        (json!({"fl_x": 3.0, "camera_model": "FOV", "omega": 3.5}), [json!({}), json!({})], "`omega`", "not in (0, pi)"),
        (json!({"fl_x": 3.0, "camera_model": "DIVISION", "k1": -0.1}), [json!({}), json!({"k2": 0.01})], "`frames[1].k2`", "the DIVISION model has no coefficient `k2`"),
        (json!({"fl_x": 3.0, "camera_model": "SIMPLE_DIVISION"}), [json!({}), json!({"is_fisheye": true})], "`frames[1].is_fisheye`", "without a fisheye lens"),
        (json!({"fl_x": 3.0, "camera_model": "EUCM", "alpha": 0.5}), [json!({}), json!({})], "`camera_model`", "EUCM: the lens needs its `beta`"),
        (json!({"fl_x": 3.0, "camera_model": "EUCM", "alpha": 1.5, "beta": 1.0}), [json!({}), json!({})], "`alpha`", "not in [0, 1]"),
        (json!({"fl_x": 3.0}), [json!({}), json!({"beta": 1.0})], "`frames[1].beta`", "belongs to the EUCM model"),
        (json!({"camera_model": "EQUIRECTANGULAR"}), [json!({}), json!({"k1": 0.1})], "`frames[1].k1`", "no lens distortion"),
        (json!({"camera_model": "EQUIRECTANGULAR"}), [json!({}), json!({"is_fisheye": true})], "`frames[1].is_fisheye`", "names an equirectangular camera"),
        (json!({"fl_x": 3.0, "camera_model": 5}), [json!({}), json!({})], "`camera_model`", "expected a string"),
        (json!({"fl_x": 3.0, "camera_model": "OPENCV"}), [json!({}), json!({"is_fisheye": true})], "`frames[1].is_fisheye`", "`camera_model` names a camera model without a fisheye"),
        (json!({"fl_x": 3.0}), [json!({}), json!({"is_fisheye": "yes"})], "`frames[1].is_fisheye`", "expected a boolean"),
        (json!({"fl_x": 3.0, "k4": 0.1}), [json!({}), json!({})], "`k4`", "belongs to the fisheye model"),
        (json!({"fl_x": 3.0, "camera_model": "OPENCV_FISHEYE"}), [json!({}), json!({"p2": 0.01})], "`frames[1].p2`", "no tangential terms"),
        (json!({"fl_x": 3.0, "camera_model": "FISHEYE624"}), [json!({}), json!({"k1": 0.1})], "`frames[1].k1`", "read from `distortion_params`"),
        (json!({"fl_x": 3.0, "distortion_params": [0.1, 0, 0]}), [json!({}), json!({})], "`distortion_params`", "expected 6 finite numbers (k1, k2, k3, k4, p1, p2), got 3 values"),
        (json!({"fl_x": 3.0, "camera_model": "FISHEYE624"}), [json!({}), json!({"distortion_params": [0.1, 0, 0, 0, 0, 0]})], "`frames[1].distortion_params`", "expected 12 finite numbers"),
        (json!({"fl_x": 3.0, "distortion_params": [0.1, 0, 0, 0, 0, 0], "k1": 0.1}), [json!({}), json!({})], "`k1`", "given by `distortion_params` too"),
        (json!({"fl_x": 3.0, "k5": 0.1}), [json!({}), json!({})], "`k5`", "the OPENCV model has no coefficient `k5`"),
        (json!({"fl_x": 3.0, "camera_model": "OPENCV_FISHEYE"}), [json!({}), json!({"s1": 0.01})], "`frames[1].s1`", "the OPENCV_FISHEYE model has no coefficient `s1`"),
        (json!({"fl_x": 3.0, "aabb_scale": 0}), [json!({}), json!({})], "`aabb_scale`", "positive"),
        (json!({"fl_x": 3.0, "offset": [0.5, 0.5]}), [json!({}), json!({})], "`offset`", "3 finite numbers"),
    ];
    for (top, frames, key, what) in cases {
        tiny_scene(dir.path(), top.clone(), frames);
        let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("transforms_train.json") && msg.contains(key) && msg.contains(what), "{top}: {msg}");
    }
    // Neither focal key.
    tiny_scene(dir.path(), json!({"cx": 2.0}), [json!({}), json!({})]);
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::MissingKey { .. }) && e.to_string().contains("fl_x"), "{e}");
    // One transforms.json whose frames leave the training split empty.
    let one = tempfile::tempdir().unwrap();
    write_json(&one.path().join("transforms.json"), &json!({"fl_x": 3.0, "frames": [interleaved_lego()[0]]}));
    let e = load_blender(one.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::EmptySplit { .. }) && e.to_string().contains("transforms.json"), "{e}");
    assert_eq!(load_blender(one.path(), Split::Test, &LoadOptions::default()).unwrap().n_views(), 1);
    // Neither file: the error names the split file.
    let none = tempfile::tempdir().unwrap();
    let e = load_blender(none.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::MissingTransforms { .. }) && e.to_string().contains("transforms_train.json"), "{e}");
}

/// A smooth test pattern over normalised image coordinates.
fn pattern(x: f64, y: f64) -> [f64; 3] {
    [0.5 + 0.4 * (8.0 * x).sin(), 0.5 + 0.4 * (6.0 * y + 2.0 * x).cos(), 0.5 + 0.3 * (x * y * 10.0).sin()]
}

/// The undistorted normalised coordinates of distorted ones (Newton's method, numerical Jacobian).
fn undistort_point(d: &Distortion, xd: f64, yd: f64) -> (f64, f64) {
    let (mut x, mut y) = (xd, yd);
    for _ in 0..50 {
        let (fx, fy) = d.distort(x, y);
        let (rx, ry) = (fx - xd, fy - yd);
        let h = 1e-7;
        let (ax, ay) = d.distort(x + h, y);
        let (bx, by) = d.distort(x, y + h);
        let (j00, j10, j01, j11) = ((ax - fx) / h, (ay - fy) / h, (bx - fx) / h, (by - fy) / h);
        let det = j00 * j11 - j01 * j10;
        x -= (j11 * rx - j01 * ry) / det;
        y -= (-j10 * rx + j00 * ry) / det;
    }
    (x, y)
}

/// A photo of [`pattern`] taken through `d`: pixel `(i, j)` sees the undistorted point of its
/// distorted normalised coordinates. RGBA, 16-bit-exact values.
fn distorted_photo(k: &Intrinsics, d: &Distortion) -> Vec<u16> {
    let mut out = vec![];
    for j in 0..k.height {
        for i in 0..k.width {
            let xd = (i as f64 + 0.5 - k.cx as f64) / k.fx as f64;
            let yd = (j as f64 + 0.5 - k.cy as f64) / k.fy as f64;
            let (x, y) = undistort_point(d, xd, yd);
            let c = pattern(x, y);
            out.extend(c.iter().map(|&v| (v * 65535.0).round() as u16));
            out.push(65535);
        }
    }
    out
}

/// Max error of `img` against [`pattern`] at the pixel centres of the pinhole camera `k`, over
/// the pixels at least `margin` from the border.
fn max_error(img: &[f32], k: &Intrinsics, margin: u32) -> f64 {
    let mut worst = 0.0f64;
    for j in margin..k.height - margin {
        for i in margin..k.width - margin {
            let x = (i as f64 + 0.5 - k.cx as f64) / k.fx as f64;
            let y = (j as f64 + 0.5 - k.cy as f64) / k.fy as f64;
            let p = pattern(x, y);
            let o = 4 * (j * k.width + i) as usize;
            for c in 0..3 {
                worst = worst.max((img[o + c] as f64 - p[c]).abs());
            }
        }
    }
    worst
}

/// Whether the pinhole pixel `(i, j)` of `k` looks at a point that the photo taken through `d`
/// saw: its distorted position lies in the photo (written out here, apart from the loader's).
fn seen_by_photo(k: &Intrinsics, d: &Distortion, i: u32, j: u32) -> bool {
    let x = (i as f64 + 0.5 - k.cx as f64) / k.fx as f64;
    let y = (j as f64 + 0.5 - k.cy as f64) / k.fy as f64;
    let (xd, yd) = d.distort(x, y);
    let (u, v) = (k.fx as f64 * xd + k.cx as f64, k.fy as f64 * yd + k.cy as f64);
    (0.0..=k.width as f64).contains(&u) && (0.0..=k.height as f64).contains(&v)
}

/// A photo through each lens loads as taken, its camera carrying the lens and its rays the
/// directions the lens saw; with `undistort`, resampled to the pinhole camera.
#[test]
fn distorted_photos_keep_their_lens_or_are_resampled_to_the_pinhole_camera() {
    let k = Intrinsics { width: 96, height: 64, fx: 80.0, fy: 82.0, cx: 47.0, cy: 33.5 };
    let rt = |k1, k2, k3, p1, p2| Distortion { k1, k2, k3, p1, p2, ..Default::default() };
    let fish = |k1, k2, k3, k4| Distortion { model: LensModel::Fisheye, k1, k2, k3, k4, ..Default::default() };
    // Each lens with the keys that name it: COLMAP's OPENCV as nerfstudio writes it, OPENCV_FISHEYE
    // as nerfstudio writes it, and instant-ngp's fisheye flag (an equidistant fisheye, no terms).
    let opencv = |d: &Distortion| json!({"camera_model": "OPENCV", "k1": d.k1, "k2": d.k2, "k3": d.k3, "p1": d.p1, "p2": d.p2});
    let cases = [
        (rt(-0.12, 0.03, 0.0, 0.002, -0.003), opencv(&rt(-0.12, 0.03, 0.0, 0.002, -0.003))),
        (rt(0.08, -0.01, 0.004, -0.001, 0.002), opencv(&rt(0.08, -0.01, 0.004, -0.001, 0.002))),
        (fish(0.05, -0.01, 0.002, -0.0005), json!({"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": -0.0005})),
        (fish(0.0, 0.0, 0.0, 0.0), json!({"is_fisheye": true})),
        // nerfstudio's list of the same barrel lens: k1, k2, k3, k4, p1, p2.
        (rt(-0.12, 0.03, 0.0, 0.002, -0.003), json!({"distortion_params": [-0.12, 0.03, 0.0, 0.0, 0.002, -0.003]})),
        // OpenCV's 12-coefficient model: rational, tangential and thin prism (COLMAP's FULL_OPENCV
        // has the first eight).
        (
            Distortion { k1: -0.1, k2: 0.02, k4: 0.05, k5: -0.01, k6: 0.002, p1: 0.002, p2: -0.001, s1: 0.003, s2: -0.001, s3: -0.002, s4: 0.0005, ..Default::default() },
            json!({"camera_model": "FULL_OPENCV", "k1": -0.1, "k2": 0.02, "k4": 0.05, "k5": -0.01, "k6": 0.002, "p1": 0.002, "p2": -0.001, "s1": 0.003, "s2": -0.001, "s3": -0.002, "s4": 0.0005}),
        ),
        // COLMAP's THIN_PRISM_FISHEYE (its sx1, sy1 as s1, s3).
        (
            Distortion { model: LensModel::Fisheye, k1: 0.03, k2: -0.01, k3: 0.002, k4: -0.0003, p1: 0.002, p2: -0.002, s1: 0.003, s3: -0.002, ..Default::default() },
            json!({"camera_model": "THIN_PRISM_FISHEYE", "k1": 0.03, "k2": -0.01, "k3": 0.002, "k4": -0.0003, "p1": 0.002, "p2": -0.002, "s1": 0.003, "s3": -0.002}),
        ),
        // COLMAP's FOV lens.
        (Distortion::fov(0.9), json!({"camera_model": "FOV", "omega": 0.9})),
        // COLMAP's division lens (barrel: k1 < 0).
        (Distortion { model: LensModel::Division, k1: -0.15, ..Default::default() }, json!({"camera_model": "DIVISION", "k1": -0.15})),
        // COLMAP's EUCM lens.
        (Distortion::eucm(0.55, 1.2), json!({"camera_model": "EUCM", "alpha": 0.55, "beta": 1.2})),
        // nerfstudio's FISHEYE624: k0..k5, p0 (OpenCV's p2), p1, s0..s3.
        (
            Distortion::from_coefficients(LensModel::Fisheye624, [0.04, -0.01, 0.002, -0.0003, 0.00005, -0.00001, 0.0015, -0.002, 0.002, -0.0005, -0.001, 0.0003]),
            json!({"camera_model": "FISHEYE624", "distortion_params": [0.04, -0.01, 0.002, -0.0003, 0.00005, -0.00001, -0.002, 0.0015, 0.002, -0.0005, -0.001, 0.0003]}),
        ),
    ];
    for (d, keys) in cases {
        let photo = distorted_photo(&k, &d);
        let photo_f: Vec<f32> = photo.iter().map(|&v| v as f32 / 65535.0).collect();
        // The photo itself is off by far more than interpolation error; resampled, it matches.
        let before = max_error(&photo_f, &k, 4);
        let after = max_error(&undistort_rgba(&photo_f, &k, &d), &k, 4);
        eprintln!("{:?}: max error against the pinhole image: photo {before:.4}, resampled {after:.5}", d.model);
        assert!(before > 0.02, "the distortion should be visible: {before}");
        assert!(after < 3e-3, "resampled photo off by {after} (before: {before})");
        // Identity distortion leaves the image as it is.
        assert_eq!(undistort_rgba(&photo_f, &k, &Distortion::default()), photo_f);

        // Through the loader: the lens keys, a 16-bit PNG, per-view undistortion before downscaling.
        let dir = tempfile::tempdir().unwrap();
        image::ImageBuffer::<image::Rgba<u16>, _>::from_raw(k.width, k.height, photo.clone())
            .unwrap()
            .save(dir.path().join("photo.png"))
            .unwrap();
        // Its mask, taken through the same lens: kept where the scene point lies right of x = 0.5.
        let edge = 0.5;
        let mask = image::GrayImage::from_fn(k.width, k.height, |i, j| {
            let xd = (i as f64 + 0.5 - k.cx as f64) / k.fx as f64;
            let yd = (j as f64 + 0.5 - k.cy as f64) / k.fy as f64;
            image::Luma([if undistort_point(&d, xd, yd).0 > edge { 255 } else { 0 }])
        });
        mask.save(dir.path().join("mask.png")).unwrap();
        let frame = json!({"file_path": "photo.png", "mask_path": "mask.png", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]});
        let mut top = json!({"fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height, "frames": [frame]});
        top.as_object_mut().unwrap().extend(keys.as_object().unwrap().clone());
        write_json(&dir.path().join("transforms.json"), &top);
        // As taken (the default): the photo's own pixels, each on the ray its lens saw, whose
        // normalised coordinates are those the photo shows the pattern at.
        let native = load(dir.path(), Split::Test);
        let cam = native.cameras[0];
        assert_eq!((cam.intrinsics, cam.distortion), (k, d));
        assert!(native.images[0].to_f32().iter().zip(&photo_f).all(|(a, b)| a == b), "the photo as taken");
        let mut worst = 0.0f64;
        for j in 0..k.height {
            for i in 0..k.width {
                let dir = cam.rotation.transpose() * cam.ray_at(i as f32 + 0.5, j as f32 + 0.5).dir;
                let (x, y) = (dir.x as f64 / -dir.z as f64, -dir.y as f64 / -dir.z as f64);
                let p = pattern(x, y);
                let o = 4 * (j * k.width + i) as usize;
                worst = (0..3).fold(worst, |w, c| w.max((native.images[0].value(o + c) as f64 - p[c]).abs()));
            }
        }
        assert!(worst < 1e-4, "{:?}: the rays miss the photo's pattern by {worst}", d.model);
        let m = native.masks.as_ref().expect("the mask is loaded");
        assert!((0..k.width * k.height).all(|p| m.is_kept(0, p) == (mask.as_raw()[p as usize] == 255)), "the mask as taken");

        let test = load_undistorted(dir.path(), Split::Test, 1);
        assert_eq!((test.cameras[0].intrinsics, test.cameras[0].distortion), (k, Distortion::NONE));
        assert!(max_error(&test.images[0].to_f32(), &k, 4) < 3e-3);
        // The mask is resampled with the photo: kept right of the edge where the photo saw the
        // pixel, dropped left of it (a pixel either side of the edge may go either way), and
        // dropped where the pinhole image reaches past the photo (the pincushion lens's corners).
        let masks = test.masks.as_ref().expect("the mask is loaded");
        let (mut kept, mut dropped, mut unseen) = (0, 0, 0);
        for j in 0..k.height {
            for i in 0..k.width {
                let x = (i as f64 + 0.5 - k.cx as f64) / k.fx as f64;
                let is = masks.is_kept(0, j * k.width + i);
                if !seen_by_photo(&k, &d, i, j) {
                    assert!(!is, "pixel ({i}, {j}), which the photo did not see, kept");
                    unseen += 1;
                } else if x > edge + 1.0 / k.fx as f64 {
                    assert!(is, "pixel ({i}, {j}) right of the edge dropped");
                    kept += 1;
                } else if x < edge - 1.0 / k.fx as f64 {
                    assert!(!is, "pixel ({i}, {j}) left of the edge kept");
                    dropped += 1;
                }
            }
        }
        eprintln!("{kept} kept, {dropped} dropped, {unseen} not seen");
        assert!(kept > 150 && dropped > 1000, "{kept} kept, {dropped} dropped");
        // The pincushion lens, and the FOV lens, which magnifies about its axis (its factor
        // there is 2·tan(ω/2)/ω > 1), reach past their photo's nearer edges.
        let reaches_past = (d.k1 > 0.0 && d.model == LensModel::RadialTangential) || d.model == LensModel::Fov;
        assert_eq!(unseen > 0, reaches_past, "{d}: {unseen} pixels not seen");
        let half = load_undistorted(dir.path(), Split::Test, 2);
        let k2 = k.downscaled(2);
        assert!(max_error(&half.images[0].to_f32(), &k2, 2) < 1e-2, "{}", max_error(&half.images[0].to_f32(), &k2, 2));
    }
}

/// Resampled (`undistort`), a lens whose pinhole image reaches past the photo gets training masks
/// of the pixels the photo saw even without mask files (downscaled: a pixel only where all it is made of was seen); a
/// lens that stays inside its photo gets none.
#[test]
fn pixels_the_photo_did_not_see_are_not_trained_on() {
    let k = Intrinsics { width: 40, height: 30, fx: 32.0, fy: 32.0, cx: 20.5, cy: 14.0 };
    let pincushion = Distortion { k1: 0.15, p1: 0.01, ..Default::default() };
    let barrel = Distortion { k1: -0.1, ..Default::default() };
    let seen = pixels_seen(&k, &pincushion, None).expect("the corners reach past the photo");
    let n_seen = seen.iter().filter(|&&s| s).count();
    assert!(n_seen > 600 && n_seen < 1150, "{n_seen} of 1200 seen");
    for (p, &s) in seen.iter().enumerate() {
        assert_eq!(s, seen_by_photo(&k, &pincushion, p as u32 % k.width, p as u32 / k.width), "pixel {p}");
    }
    assert_eq!(pixels_seen(&k, &barrel, None), None);
    assert_eq!(pixels_seen(&k, &Distortion::default(), None), None);

    let dir = tempfile::tempdir().unwrap();
    image::RgbImage::from_pixel(k.width, k.height, image::Rgb([90, 140, 30])).save(dir.path().join("a.png")).unwrap();
    let scene = |lens: &Distortion| {
        // Nine frames of one lens: the test split holds frames 0 and 8, the training split the others.
        let frame = json!({"file_path": "a.png", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]});
        let top = json!({"camera_model": "OPENCV", "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "k1": lens.k1, "p1": lens.p1, "frames": vec![frame; 9]});
        write_json(&dir.path().join("transforms.json"), &top);
    };
    scene(&pincushion);
    // Rays through the photo's own pixels see all of it: no masks.
    assert!(load(dir.path(), Split::Test).masks.is_none(), "every pixel of the photo is seen");
    let full = load_undistorted(dir.path(), Split::Test, 1);
    let m = full.masks.as_ref().expect("masks of the seen pixels");
    assert_eq!(m.total() as usize, 2 * n_seen);
    assert!((0..1200).all(|p| m.is_kept(0, p) == seen[p as usize] && m.is_kept(1, p) == seen[p as usize]));
    // The views of one lens share its list.
    let train = load_undistorted(dir.path(), Split::Train, 1);
    let m = train.masks.as_ref().unwrap();
    assert_eq!((m.n_views(), m.total() as usize), (7, 7 * n_seen));
    assert!((1..7).all(|v| std::ptr::eq(m.view(v).unwrap(), m.view(0).unwrap())), "one list for the lens");
    let half = load_undistorted(dir.path(), Split::Test, 2);
    let m = half.masks.as_ref().unwrap();
    for (j, i) in (0..15u32).flat_map(|j| (0..20u32).map(move |i| (j, i))) {
        let all = (0..4).all(|q| seen[((2 * j + q / 2) * k.width + 2 * i + q % 2) as usize]);
        assert_eq!(m.is_kept(0, j * 20 + i), all, "downscaled pixel ({i}, {j})");
    }
    // Camera-only loads read no pixels and make no masks.
    let cams = load_blender(dir.path(), Split::Test, &LoadOptions { cameras_only: true, undistort: true, ..Default::default() }).unwrap();
    assert!(cams.masks.is_none());
    scene(&barrel);
    assert!(load_undistorted(dir.path(), Split::Test, 1).masks.is_none(), "a barrel lens stays inside its photo");
}

/// nerfstudio's `fisheye_crop_radius` (what its Project Aria processing writes): only the disc
/// of that many pixels about the principal point trains, at the photo's own size, downscaled
/// (a pixel only where all it is made of lies in the disc), beside mask files (both must keep
/// a pixel), and through the resampling of `undistort` (where the pixel's source lies in it).
#[test]
fn pixels_past_the_fisheye_crop_radius_are_not_trained_on() {
    let k = Intrinsics { width: 40, height: 30, fx: 12.0, fy: 12.0, cx: 20.5, cy: 14.0 };
    let radius = 13.0;
    let in_disc = |x: f64, y: f64| (x - k.cx as f64).powi(2) + (y - k.cy as f64).powi(2) <= radius * radius;
    let dir = tempfile::tempdir().unwrap();
    image::RgbImage::from_pixel(k.width, k.height, image::Rgb([90, 140, 30])).save(dir.path().join("a.png")).unwrap();
    // The left half masked out.
    image::GrayImage::from_fn(k.width, k.height, |i, _| image::Luma([if i < 20 { 0 } else { 255 }])).save(dir.path().join("m.png")).unwrap();
    let lens = Distortion { model: LensModel::Fisheye, k1: 0.02, ..Distortion::NONE };
    let scene = |mask: bool| {
        let mut frame = json!({"file_path": "a.png", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]});
        if mask {
            frame["mask_path"] = json!("m.png");
        }
        let top = json!({"camera_model": "OPENCV_FISHEYE", "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "k1": lens.k1,
                         "fisheye_crop_radius": radius, "frames": vec![frame; 9]});
        write_json(&dir.path().join("transforms.json"), &top);
    };
    scene(false);
    let d = load(dir.path(), Split::Test);
    let m = d.masks.as_ref().expect("the disc is a mask");
    let mut kept = 0;
    for (j, i) in (0..k.height).flat_map(|j| (0..k.width).map(move |i| (j, i))) {
        let inside = in_disc(i as f64 + 0.5, j as f64 + 0.5);
        assert_eq!(m.is_kept(0, j * k.width + i), inside, "pixel ({i}, {j})");
        kept += inside as u32;
    }
    assert!(kept > 400 && kept < 1100, "{kept} of 1200 in the disc");
    let half = load_blender(dir.path(), Split::Test, &LoadOptions { downscale: 2, ..Default::default() }).unwrap();
    let m = half.masks.as_ref().unwrap();
    for (j, i) in (0..15u32).flat_map(|j| (0..20u32).map(move |i| (j, i))) {
        let all = (0..4).all(|q| in_disc((2 * i + q % 2) as f64 + 0.5, (2 * j + q / 2) as f64 + 0.5));
        assert_eq!(m.is_kept(0, j * 20 + i), all, "downscaled pixel ({i}, {j})");
    }
    // Resampled to the pinhole camera: a pixel trains where its source in the photo is in the disc.
    let resampled = load_undistorted(dir.path(), Split::Test, 1);
    let m = resampled.masks.as_ref().unwrap();
    for (j, i) in (0..k.height).flat_map(|j| (0..k.width).map(move |i| (j, i))) {
        let (xd, yd) = lens.distort((i as f64 + 0.5 - k.cx as f64) / k.fx as f64, (j as f64 + 0.5 - k.cy as f64) / k.fy as f64);
        let (u, v) = (k.fx as f64 * xd + k.cx as f64, k.fy as f64 * yd + k.cy as f64);
        let seen = (0.0..=40.0).contains(&u) && (0.0..=30.0).contains(&v) && in_disc(u, v);
        assert_eq!(m.is_kept(0, j * k.width + i), seen, "resampled pixel ({i}, {j})");
    }
    // With mask files: the disc's right half.
    scene(true);
    let m = load(dir.path(), Split::Test).masks.unwrap();
    for (j, i) in (0..k.height).flat_map(|j| (0..k.width).map(move |i| (j, i))) {
        assert_eq!(m.is_kept(1, j * k.width + i), i >= 20 && in_disc(i as f64 + 0.5, j as f64 + 0.5), "masked pixel ({i}, {j})");
    }
    tiny_scene(dir.path(), json!({"fl_x": 3.0, "fisheye_crop_radius": -2}), [json!({}), json!({})]);
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("fisheye_crop_radius") && e.contains("not positive"), "{e}");
}

/// Cameras keep their lenses through `write_blender` (a fisheye at the top level, a frame with a
/// radial–tangential lens of its own), and coefficients that fold over inside the photo are
/// refused, naming the frame and the photo.
#[test]
fn lenses_are_written_and_impossible_ones_refused() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(
        dir.path(),
        json!({"fl_x": 3.0, "fl_y": 3.5, "cx": 2.0, "cy": 2.0, "w": 4, "h": 4, "is_fisheye": true, "k1": 0.02, "k4": -0.001}),
        [json!({}), json!({"is_fisheye": false, "k1": -0.05, "k4": 0.0, "p2": 0.004})],
    );
    let d = load(dir.path(), Split::Train);
    assert_eq!(d.cameras[0].distortion, Distortion { model: LensModel::Fisheye, k1: 0.02, k4: -0.001, ..Distortion::NONE });
    assert_eq!(d.cameras[1].distortion, Distortion { k1: -0.05, p2: 0.004, ..Distortion::NONE });
    let out = tempfile::tempdir().unwrap();
    nerf_data::write_blender(&d, out.path(), None).unwrap();
    assert_same_views(&d, &load(out.path(), Split::Train));

    // The models instant-ngp's keys do not hold, each frame naming its own (a top-level
    // `camera_model` would mark a nerfstudio file): Fisheye624, OpenCV's rational model, a
    // thin-prism fisheye; and a frame's keys replace the top level's list, and the other way round.
    tiny_scene(
        dir.path(),
        json!({"fl_x": 3.0, "cx": 2.0, "cy": 2.0, "w": 4, "h": 4, "camera_model": "FISHEYE624", "distortion_params": [0.01, 0, 0, 0, 0, 0.0001, 0.001, 0, 0, 0, 0.002, 0]}),
        [json!({}), json!({"camera_model": "FULL_OPENCV", "k1": -0.02, "k4": 0.01, "s2": 0.001})],
    );
    let d = load(dir.path(), Split::Train);
    assert_eq!(d.cameras[0].distortion, Distortion { model: LensModel::Fisheye624, k1: 0.01, k6: 0.0001, p2: 0.001, s3: 0.002, ..Distortion::NONE });
    assert_eq!(d.cameras[1].distortion, Distortion { k1: -0.02, k4: 0.01, s2: 0.001, ..Distortion::NONE });
    let mut mixed = d.clone();
    mixed.cameras[1].distortion = Distortion { model: LensModel::Fisheye, k1: 0.01, p1: -0.001, s1: 0.002, ..Distortion::NONE };
    let mut fov = d.clone();
    fov.cameras[1].distortion = Distortion::fov(0.8);
    let mut division = d.clone();
    division.cameras[1].distortion = Distortion { model: LensModel::Division, k1: -0.04, ..Distortion::NONE };
    let mut eucm = d.clone();
    eucm.cameras[1].distortion = Distortion::eucm(0.3, 0.9);
    for ds in [d, mixed, fov, division, eucm] {
        let out = tempfile::tempdir().unwrap();
        nerf_data::write_blender(&ds, out.path(), None).unwrap();
        let written: Value = serde_json::from_str(&std::fs::read_to_string(out.path().join("transforms_train.json")).unwrap()).unwrap();
        assert!(written.get("camera_model").is_none() && written["frames"][0]["camera_model"] == "FISHEYE624", "{written}");
        assert_same_views(&ds, &load(out.path(), Split::Train));
    }
    tiny_scene(dir.path(), json!({"fl_x": 3.0, "k1": 0.01}), [json!({}), json!({"distortion_params": [0.02, 0, 0, 0, 0, 0.001]})]);
    let d = load(dir.path(), Split::Train);
    assert_eq!((d.cameras[0].distortion.k1, d.cameras[1].distortion), (0.01, Distortion { k1: 0.02, p2: 0.001, ..Distortion::NONE }));

    // r·(1 − 0.6 r²) turns back at r_d ≈ 0.50; the photo's corners lie 0.94 out.
    tiny_scene(dir.path(), json!({"fl_x": 3.0, "cx": 2.0, "cy": 2.0, "k1": -0.6}), [json!({}), json!({})]);
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains("frames[0].k1") && e.contains("r_0.png") && e.contains("folds over"), "{e}");
    // Resampled to the pinhole camera, the same lens loads (its photo's corners seen twice).
    assert!(load_undistorted(dir.path(), Split::Train, 1).cameras[0].distortion.is_identity());
}

#[test]
fn jpeg_images_load() {
    let dir = tempfile::tempdir().unwrap();
    let img = image::RgbImage::from_fn(16, 8, |x, y| image::Rgb([(16 * x) as u8, (30 * y) as u8, 128]));
    img.save(dir.path().join("a.jpg")).unwrap();
    let frame = json!({"file_path": "a.jpg", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]});
    write_json(&dir.path().join("transforms.json"), &json!({"fl_x": 10.0, "frames": [frame]}));
    let d = load(dir.path(), Split::Test);
    assert_eq!((d.width, d.height), (16, 8));
    let px = d.images[0].to_f32();
    for (p, (x, y, c)) in px.chunks_exact(4).zip(img.enumerate_pixels()) {
        let _ = (x, y);
        for ch in 0..3 {
            assert!((p[ch] - c[ch] as f32 / 255.0).abs() < 0.06, "JPEG decoded far from its source");
        }
        assert_eq!(p[3], 1.0);
    }
}

#[test]
fn writing_keeps_pixel_intrinsics_and_the_box() {
    let dir = tempfile::tempdir().unwrap();
    tiny_scene(
        dir.path(),
        json!({"fl_x": 3.0, "fl_y": 5.0, "cx": 1.5, "cy": 2.25, "w": 4, "h": 4, "aabb_scale": 4, "scale": 0.25, "offset": [0.5, 0.3, 0.6]}),
        [json!({}), json!({"fl_x": 7.0, "cx": 2.5})],
    );
    let d = load(dir.path(), Split::Train);
    let out = tempfile::tempdir().unwrap();
    nerf_data::write_blender(&d, out.path(), None).unwrap();
    let back = load(out.path(), Split::Train);
    assert_same_views(&d, &back);
    assert_eq!((back.ngp, back.aabb, back.near, back.far), (d.ngp, d.aabb, d.near, d.far));
    let t: Value = serde_json::from_str(&std::fs::read_to_string(out.path().join("transforms_train.json")).unwrap()).unwrap();
    assert_eq!(t["fl_y"], json!(5.0));
    assert_eq!(t["frames"][1]["fl_x"], json!(7.0));
    assert!(t["frames"][0].get("fl_x").is_none(), "the first view's intrinsics are the top level's");
    // A plain Blender scene is written as before: the field of view only.
    let lego = load(&lego_100(), Split::Test);
    let small = Dataset { cameras: lego.cameras[..2].to_vec(), images: lego.images[..2].to_vec(), ..lego };
    let out = tempfile::tempdir().unwrap();
    nerf_data::write_blender(&small, out.path(), None).unwrap();
    let t: Value = serde_json::from_str(&std::fs::read_to_string(out.path().join("transforms_test.json")).unwrap()).unwrap();
    let keys: Vec<&String> = t.as_object().unwrap().keys().collect();
    assert_eq!(keys, ["camera_angle_x", "frames"]);
}

#[test]
fn fern_stored_as_one_transforms_json_gives_the_llff_cameras() {
    let Some(fern) = nerf_core::shared::data(env!("CARGO_MANIFEST_DIR"), "nerf_llff_data/fern") else { return };
    // Euclidean rays at 504×378 (images_8), both splits, as the LLFF loader reads them.
    let o = LoadOptions { downscale: 8, views: ViewSelection::All, ndc: false, cameras_only: false, sfm_depth: false, undistort: false, aabb_scale: None, nerfstudio: Default::default(), holdout: None, format: Default::default() };
    let (train, test) = (load_scene(&fern, Split::Train, &o).unwrap(), load_scene(&fern, Split::Test, &o).unwrap());
    let n = train.n_views() + test.n_views();
    let (mut tr, mut te) = (train.cameras.iter().zip(&train.file_paths), test.cameras.iter().zip(&test.file_paths));
    // LLFF holds out every 8th image, as one transforms.json does: the same interleaving.
    let frames: Vec<Value> = (0..n)
        .map(|i| {
            let (cam, path) = if i % 8 == 0 { te.next() } else { tr.next() }.unwrap();
            let k = cam.intrinsics;
            json!({
                "file_path": path.to_str().unwrap(),
                "transform_matrix": cam.c2w().map(|r| r.map(|v| v as f64)),
                "fl_x": k.fx as f64, "fl_y": k.fy as f64, "cx": k.cx as f64, "cy": k.cy as f64,
            })
        })
        .collect();
    // A box around LLFF's scene bounds: scale = 1/longest side, offset = 0.5 − centre·scale.
    let (lo, hi) = (train.aabb.min, train.aabb.max);
    let scale = 1.0 / (0..3).map(|a| hi[a] - lo[a]).fold(0.0f32, f32::max);
    let offset: Vec<f64> = (0..3).map(|a| (0.5 - 0.5 * (lo[a] + hi[a]) * scale) as f64).collect();
    let dir = tempfile::tempdir().unwrap();
    write_json(
        &dir.path().join("transforms.json"),
        &json!({"w": train.width, "h": train.height, "scale": scale as f64, "offset": offset, "frames": frames}),
    );
    for (llff, split) in [(&train, Split::Train), (&test, Split::Test)] {
        let d = load(dir.path(), split);
        assert_same_views(&d, llff);
        for a in 0..3 {
            assert!(d.aabb.min[a] <= lo[a] + 1e-4 && d.aabb.max[a] >= hi[a] - 1e-4, "{:?} vs {:?}", d.aabb, llff.aabb);
        }
        // What `nerf export-scene` writes for it: the same views in the box around its bounds.
        let out = tempfile::tempdir().unwrap();
        nerf_data::write_blender(llff, out.path(), None).unwrap();
        let back = load(out.path(), split);
        assert_same_views(&back, llff);
        assert_eq!(back.ngp, Some(NgpBox::enclosing(&llff.aabb)));
        for a in 0..3 {
            assert!(back.aabb.min[a] <= lo[a] + 1e-4 && back.aabb.max[a] >= hi[a] - 1e-4, "{:?}", back.aabb);
        }
    }
    // A scene in NDC has no world box to write.
    let ndc = load_scene(&fern, Split::Test, &LoadOptions { downscale: 8, ..Default::default() }).unwrap();
    let e = nerf_data::write_blender(&ndc, dir.path(), None).unwrap_err();
    assert!(e.to_string().contains("NDC"), "{e}");
}

#[test]
fn nerfstudio_split_lists_pick_the_frames() {
    let dir = tempfile::tempdir().unwrap();
    let frames = interleaved_lego();
    let name = |i: usize| frames[i]["file_path"].as_str().unwrap().to_string();
    let lists = |train: Vec<String>, test: Vec<String>| {
        json!({"fl_x": 100.0, "frames": frames.clone(), "train_filenames": train, "test_filenames": test})
    };
    write_json(&dir.path().join("transforms.json"), &lists(vec![name(5), name(0), name(9)], vec![name(3)]));
    let train = load(dir.path(), Split::Train);
    let all = load_scene(dir.path(), Split::Test, &LoadOptions::default()).unwrap();
    assert_eq!(all.n_views(), 1);
    assert_eq!(train.n_views(), 3);
    // File order, not list order: frames 0, 5, 9.
    let expect: Vec<PathBuf> = [0, 5, 9].iter().map(|&i| PathBuf::from(name(i))).collect();
    assert_eq!(train.file_paths, expect);
    assert_eq!(all.file_paths, vec![PathBuf::from(name(3))]);
    // Lists for some splits but not this one; a name that is no frame's image.
    let e = load_blender(dir.path(), Split::Val, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::MissingKey { .. }) && e.to_string().contains("val_filenames"), "{e}");
    write_json(&dir.path().join("transforms.json"), &lists(vec!["images/nope.png".into()], vec![name(3)]));
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(e.to_string().contains("train_filenames") && e.to_string().contains("nope.png"), "{e}");
    write_json(&dir.path().join("transforms.json"), &json!({"fl_x": 100.0, "frames": frames.clone(), "train_filenames": "all"}));
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(e.to_string().contains("array of strings"), "{e}");
}

/// nerfstudio's `ns-process-data` keeps COLMAP's poses at COLMAP's scale and orientation; the
/// loader normalises them as nerfstudio's dataparser does, wherever the capture sits, however it
/// is turned and however large it is.
#[test]
fn nerfstudio_scenes_are_normalised_as_nerfstudio_does() {
    let dir = tempfile::tempdir().unwrap();
    let k = load(&lego_100(), Split::Train).cameras[0].intrinsics;
    // lego's cameras moved rigidly and scaled: p → s·Q·p + shift, camera axes turned by Q.
    let q = glam::Mat3::from_euler(glam::EulerRot::XYZ, 0.7, -0.4, 1.9);
    let moved = |frames: Vec<Value>, s: f32, shift: [f32; 3], q: glam::Mat3| -> Vec<Value> {
        frames
            .into_iter()
            .map(|mut f| {
                let m: Vec<Vec<f32>> = (0..4).map(|r| (0..4).map(|c| f["transform_matrix"][r][c].as_f64().unwrap() as f32).collect()).collect();
                let rot = glam::Mat3::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|r| m[r][c]))); // columns
                let t = glam::Vec3::new(m[0][3], m[1][3], m[2][3]);
                let (rot, t) = (q * rot, s * (q * t) + glam::Vec3::from_array(shift));
                let rows: Vec<Vec<f32>> = (0..3).map(|r| vec![rot.col(0)[r], rot.col(1)[r], rot.col(2)[r], t[r]]).chain([vec![0.0, 0.0, 0.0, 1.0]]).collect();
                f["transform_matrix"] = json!(rows);
                f
            })
            .collect()
    };
    let scene = |frames: Vec<Value>, extra: Value| {
        let mut t = json!({"camera_model": "OPENCV", "fl_x": k.fx as f64, "fl_y": k.fy as f64, "cx": 50.0, "cy": 50.0, "w": 100, "h": 100,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "applied_transform": [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]], "frames": frames});
        for (key, v) in extra.as_object().unwrap() {
            t[key] = v.clone();
        }
        write_json(&dir.path().join("transforms.json"), &t);
        (load(dir.path(), Split::Train), load(dir.path(), Split::Test))
    };
    let orig = interleaved_lego();
    let (train0, test0) = scene(orig.clone(), json!({}));
    // Moved and scaled: the same cameras (nerfstudio's frame does not depend on where the
    // capture sits or on its scale).
    let big = moved(orig.clone(), 7.0, [10.0, -3.0, 5.0], glam::Mat3::IDENTITY);
    let (train, test) = scene(big.clone(), json!({}));
    for (a, b) in train0.cameras.iter().chain(&test0.cameras).zip(train.cameras.iter().chain(&test.cameras)) {
        assert!((a.position - b.position).abs().max_element() < 1e-4, "{} vs {}", a.position, b.position);
        assert!((a.rotation - b.rotation).abs().to_cols_array().iter().all(|d| *d < 1e-4), "{:?} vs {:?}", a.rotation, b.rotation);
    }
    // Turned as well: the same rig up to a turn about the up axis (nerfstudio only levels it)
    // and so a scale (the farthest coordinate along the turned axes is 1).
    let (turned, turned_test) = scene(moved(orig.clone(), 7.0, [10.0, -3.0, 5.0], q), json!({}));
    let rig = |d: &Dataset, e: &Dataset| -> Vec<glam::Vec3> { d.cameras.iter().chain(&e.cameras).map(|c| c.position).collect() };
    let (p0, p1) = (rig(&train0, &test0), rig(&turned, &turned_test));
    let ratio = (p1[1] - p1[0]).length() / (p0[1] - p0[0]).length();
    assert!(ratio > 0.5 && ratio < 2.0, "{ratio}");
    for i in 0..p0.len() {
        assert!((ratio * p0[i].z - p1[i].z).abs() < 1e-4, "heights agree: {} vs {} (×{ratio})", p0[i], p1[i]);
        for j in 0..i {
            assert!((ratio * (p0[i] - p0[j]).length() - (p1[i] - p1[j]).length()).abs() < 1e-4, "distances agree");
        }
    }
    // In that frame: every camera (both splits) inside [−1, 1]³ and one on its surface, their
    // mean centre at the origin, their mean up vector along +z; the box is [−1, 1]³.
    for (tr, te) in [(&train, &test), (&turned, &turned_test)] {
        let all: Vec<_> = tr.cameras.iter().chain(&te.cameras).collect();
        let max = all.iter().map(|c| c.position.abs().max_element()).fold(0.0f32, f32::max);
        assert!((max - 1.0).abs() < 1e-5, "{max}");
        let mean = all.iter().map(|c| c.position).sum::<glam::Vec3>() / all.len() as f32;
        assert!(mean.abs().max_element() < 1e-5, "{mean}");
        let up = all.iter().map(|c| c.rotation.col(1)).sum::<glam::Vec3>().normalize();
        assert!((up - glam::Vec3::Z).length() < 1e-5, "{up}");
    }
    assert_eq!(train.ngp, Some(NgpBox { scale: 0.5, offset: [0.5; 3], aabb_scale: 1.0 }));
    assert_eq!((train.aabb.min, train.aabb.max), ([-1.0; 3], [1.0; 3]));
    assert_eq!((test.aabb, test.near, test.far), (train.aabb, train.near, train.far), "one box for every split");
    assert!((train.near - NGP_NEAR / 0.5).abs() < 1e-6);
    // The images are the frames' own: only the poses change.
    assert!(train.images == train0.images);
    // nerfstudio's dataparser_transforms.json of the normalisation maps the file's camera
    // centres onto the loaded ones: q = scale·(transform·[p; 1]).
    let n = train.normalization.expect("a nerfstudio capture keeps its normalisation");
    let dt = n.to_json();
    let (m, sc) = (&dt["transform"], dt["scale"].as_f64().unwrap());
    for (f, cam) in big.iter().enumerate().filter(|(i, _)| i % 8 != 0).map(|(_, f)| f).zip(&train.cameras) {
        let p: Vec<f64> = (0..3).map(|r| f["transform_matrix"][r][3].as_f64().unwrap()).chain([1.0]).collect();
        let q: Vec<f64> = (0..3).map(|i| sc * (0..4).map(|j| m[i][j].as_f64().unwrap() * p[j]).sum::<f64>()).collect();
        assert!((0..3).all(|a| (q[a] - cam.position[a] as f64).abs() < 1e-5), "{q:?} vs {}", cam.position);
    }
    assert!(train0.normalization.is_some() && load(&lego_100(), Split::Train).normalization.is_none());
    // `aabb_scale` grows the box about the origin.
    let (train4, _) = scene(big.clone(), json!({"aabb_scale": 4}));
    assert_eq!((train4.aabb.min, train4.aabb.max), ([-4.0; 3], [4.0; 3]));
    assert_eq!(train4.cameras[3].position, train.cameras[3].position);
    // Asked for by the load options instead (`nerf train --aabb-scale`): the same box and poses
    // as the file's key gives, and in place of a key the file has.
    let with = |s: f32| nerf_data::load_scene(dir.path(), Split::Train, &LoadOptions { aabb_scale: Some(s), ..LoadOptions::default() });
    scene(big.clone(), json!({}));
    let asked = with(4.0).unwrap();
    assert_eq!((asked.aabb.min, asked.aabb.max, asked.ngp), (train4.aabb.min, train4.aabb.max, train4.ngp));
    assert!(asked.cameras.iter().zip(&train4.cameras).all(|(a, b)| a.position == b.position && a.rotation == b.rotation));
    scene(big.clone(), json!({"aabb_scale": 4}));
    assert_eq!(with(2.0).unwrap().aabb.max, [2.0; 3]);
    let Err(e) = with(0.0).map(|_| ()) else { panic!("aabb_scale 0 accepted") };
    let e = e.to_string();
    assert!(e.contains("transforms.json") && e.contains("aabb_scale") && e.contains("above 0"), "{e}");
    // `camera_model` with `aabb_scale` but no `applied_transform`: an instant-ngp file that some
    // tool gave a camera model (its poses are taken as already scaled).
    write_json(&dir.path().join("transforms.json"), &json!({"camera_model": "OPENCV", "aabb_scale": 16, "fl_x": k.fx as f64, "w": 100, "h": 100, "frames": big.clone()}));
    let ngp16 = load(dir.path(), Split::Train);
    assert_eq!(ngp16.ngp, Some(NgpBox { aabb_scale: 16.0, ..NgpBox::default() }));
    assert!(ngp16.normalization.is_none());
    let ngp2 = with(2.0).unwrap();
    assert_eq!((ngp2.ngp, ngp2.normalization.is_none()), (Some(NgpBox { aabb_scale: 2.0, ..NgpBox::default() }), true));
    // instant-ngp's `scale` / `offset` keep their meaning: the file is then instant-ngp's, poses as written.
    let (ngp, _) = scene(big.clone(), json!({"scale": 0.5, "offset": [0.5, 0.5, 0.5]}));
    assert_eq!(ngp.ngp, Some(NgpBox { scale: 0.5, offset: [0.5; 3], aabb_scale: 1.0 }));
    let first_train = |frames: &[Value]| -> [f32; 3] { std::array::from_fn(|r| frames[1]["transform_matrix"][r][3].as_f64().unwrap() as f32) };
    assert_eq!(ngp.cameras[0].position.to_array(), first_train(&big));
    // Cameras that all sit at one point (a single view) cannot be normalised: instant-ngp's cube.
    let one_point: Vec<Value> = big.iter().map(|f| { let mut f = f.clone(); for r in 0..3 { f["transform_matrix"][r][3] = json!(1.0); } f }).collect();
    let (one, _) = scene(one_point, json!({}));
    assert_eq!(one.ngp, Some(NgpBox::default()));
    assert_eq!(one.cameras[0].position, glam::Vec3::ONE);
}

/// nerfstudio's dataparser options (`LoadOptions::nerfstudio`): `none` keeps the file's axes,
/// origin and scale; `focus` puts the origin where the cameras look; `vertical` levels the
/// cameras' x axes; a capture whose cameras all look one way gets the `up` turn from `vertical`
/// too (nerfstudio's fallback); a bad scale factor names the key.
#[test]
fn nerfstudio_dataparser_options_turn_centre_and_scale_as_asked() {
    use nerf_data::{CenterMethod, NerfstudioOptions, OrientationMethod};
    let dir = tempfile::tempdir().unwrap();
    let k = load(&lego_100(), Split::Train).cameras[0].intrinsics;
    // lego's cameras (they look at its origin) turned by q, scaled by 3 and moved to `shift`.
    let q = glam::Mat3::from_euler(glam::EulerRot::XYZ, 0.7, -0.4, 1.9);
    let shift = glam::Vec3::new(4.0, -2.0, 1.0);
    let frames: Vec<Value> = interleaved_lego()
        .into_iter()
        .map(|mut f| {
            let m: Vec<Vec<f32>> = (0..3).map(|r| (0..4).map(|c| f["transform_matrix"][r][c].as_f64().unwrap() as f32).collect()).collect();
            let rot = q * glam::Mat3::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|r| m[r][c])));
            let t = 3.0 * (q * glam::Vec3::new(m[0][3], m[1][3], m[2][3])) + shift;
            f["transform_matrix"] = json!((0..3).map(|r| vec![rot.col(0)[r], rot.col(1)[r], rot.col(2)[r], t[r]]).chain([vec![0.0, 0.0, 0.0, 1.0]]).collect::<Vec<_>>());
            f
        })
        .collect();
    write_json(&dir.path().join("transforms.json"), &json!({"camera_model": "OPENCV", "fl_x": k.fx as f64, "fl_y": k.fy as f64, "cx": 50.0, "cy": 50.0,
        "w": 100, "h": 100, "applied_transform": [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]], "frames": frames.clone()}));
    let with = |o: NerfstudioOptions| nerf_data::load_scene(dir.path(), Split::Train, &LoadOptions { nerfstudio: o, ..LoadOptions::default() });
    let file: Vec<(glam::Vec3, glam::Mat3)> = frames
        .iter()
        .enumerate()
        .filter(|(i, _)| i % 8 != 0)
        .map(|(_, f)| {
            let m = |r: usize, c: usize| f["transform_matrix"][r][c].as_f64().unwrap() as f32;
            (glam::Vec3::new(m(0, 3), m(1, 3), m(2, 3)), glam::Mat3::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|r| m(r, c)))))
        })
        .collect();
    // Nothing asked: the file's poses as they are (scale factor 1).
    let none = NerfstudioOptions { orientation_method: OrientationMethod::None, center_method: CenterMethod::None, auto_scale_poses: false, scale_factor: 1.0 };
    let ds = with(none).unwrap();
    for (c, (p, r)) in ds.cameras.iter().zip(&file) {
        assert!((c.position - *p).length() < 1e-5 && (c.rotation - *r).abs().to_cols_array().iter().all(|d| *d < 1e-6));
    }
    // The focus of attention: the cameras look at `shift`, which becomes the origin; scaled so
    // the farthest coordinate is 1, then by 0.5.
    let focus = with(NerfstudioOptions { center_method: CenterMethod::Focus, scale_factor: 0.5, ..none }.with_auto_scale()).unwrap();
    let n = focus.normalization.unwrap();
    assert!((0..3).all(|a| (n.center[a] - shift[a] as f64).abs() < 1e-3), "focus {:?} vs {shift}", n.center);
    let all = nerf_data::load_scene(dir.path(), Split::Test, &LoadOptions { nerfstudio: NerfstudioOptions { center_method: CenterMethod::Focus, scale_factor: 0.5, ..none }.with_auto_scale(), ..LoadOptions::default() }).unwrap();
    let max = focus.cameras.iter().chain(&all.cameras).map(|c| c.position.abs().max_element()).fold(0.0f32, f32::max);
    assert!((max - 0.5).abs() < 1e-5, "{max}");
    for (c, (p, _)) in focus.cameras.iter().zip(&file) {
        let want = (*p - shift) * n.scale as f32;
        assert!((c.position - want).length() < 1e-3, "{} vs {want}", c.position);
    }
    // Vertical: lego's x axes are level in its own frame, so q's turn is undone about the axes
    // that matter: every camera's x axis is horizontal afterwards.
    let vertical = with(NerfstudioOptions { orientation_method: OrientationMethod::Vertical, ..NerfstudioOptions::default() }).unwrap();
    for c in &vertical.cameras {
        assert!(c.rotation.col(0).z.abs() < 1e-4, "x axis {}", c.rotation.col(0));
    }
    // (The mean up vector, nerfstudio's default, does not level them: the views are not spread
    // evenly enough for their up vectors' tilts to cancel.)
    let up = with(NerfstudioOptions::default()).unwrap();
    let tilt = up.cameras.iter().map(|c| c.rotation.col(0).z.abs()).fold(0.0f32, f32::max);
    assert!(tilt > 1e-3, "up levels the x axes too ({tilt})");
    // All looking one way (a forward-facing rig): vertical falls back to the mean up vector.
    let rig: Vec<Value> = (0..9)
        .map(|i| {
            let (x, y) = ((i % 3) as f32 * 0.3, (i / 3) as f32 * 0.2);
            let t = q * glam::Vec3::new(x, y, 0.0);
            json!({"file_path": frames[i]["file_path"].clone(), "transform_matrix": (0..3).map(|r| vec![q.col(0)[r], q.col(1)[r], q.col(2)[r], t[r]]).chain([vec![0.0, 0.0, 0.0, 1.0]]).collect::<Vec<_>>()})
        })
        .collect();
    write_json(&dir.path().join("transforms.json"), &json!({"camera_model": "OPENCV", "fl_x": k.fx as f64, "w": 100, "h": 100, "applied_transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "frames": rig}));
    let (up, vert) = (with(NerfstudioOptions::default()).unwrap(), with(NerfstudioOptions { orientation_method: OrientationMethod::Vertical, ..NerfstudioOptions::default() }).unwrap());
    for (a, b) in up.cameras.iter().zip(&vert.cameras) {
        assert!((a.position - b.position).length() < 1e-5 && (a.rotation.col(1) - glam::Vec3::Z).length() < 1e-5);
    }
    let Err(e) = with(NerfstudioOptions { scale_factor: 0.0, ..NerfstudioOptions::default() }).map(|_| ()) else { panic!("scale factor 0 accepted") };
    assert!(e.to_string().contains("transforms.json") && e.to_string().contains("scale_factor"), "{e}");
}

trait WithAutoScale {
    fn with_auto_scale(self) -> Self;
}

impl WithAutoScale for nerf_data::NerfstudioOptions {
    fn with_auto_scale(self) -> Self {
        Self { auto_scale_poses: true, ..self }
    }
}

/// `LoadOptions::holdout` (nerfstudio's `eval_mode`): the frames are taken in the order of their
/// images' names, whatever the file's order, and split by the rule; without it every 8th frame
/// in the file's order tests; a file's own lists win over it.
#[test]
fn a_holdout_splits_the_frames_in_name_order() {
    use nerf_data::Holdout;
    let dir = tempfile::tempdir().unwrap();
    // lego's 32 interleaved frames, written in reverse name order.
    let mut frames = interleaved_lego();
    frames.sort_by(|a, b| b["file_path"].as_str().cmp(&a["file_path"].as_str()));
    let mut names: Vec<PathBuf> = frames.iter().map(|f| PathBuf::from(f["file_path"].as_str().unwrap())).collect();
    write_json(&dir.path().join("transforms.json"), &json!({"fl_x": 100.0, "frames": frames.clone()}));
    let split = |h: Option<Holdout>, s: Split| load_scene(dir.path(), s, &LoadOptions { holdout: h, cameras_only: true, ..LoadOptions::default() }).unwrap().file_paths;
    // Default: every 8th frame of the file.
    assert_eq!(split(None, Split::Test), [0, 8, 16, 24].map(|i| names[i].clone()));
    names.sort();
    // nerfstudio's fraction 0.9 of the 32 sorted names: 29 train (numpy's linspace), 3 test.
    let (train, test) = (split(Some(Holdout::Fraction(0.9)), Split::Train), split(Some(Holdout::Fraction(0.9)), Split::Test));
    assert_eq!(train.len(), 29);
    let want: Vec<PathBuf> = Holdout::Fraction(0.9).split(&[""; 32], Split::Test).unwrap().into_iter().map(|i| names[i].clone()).collect();
    assert_eq!((test.len(), &test), (3, &want));
    assert!(train.iter().all(|p| !test.contains(p)));
    assert_eq!(split(Some(Holdout::Interval(8)), Split::Test), [0, 8, 16, 24].map(|i| names[i].clone()));
    assert_eq!(split(Some(Holdout::All), Split::Test).len(), 32);
    // The file's lists win.
    write_json(&dir.path().join("transforms.json"), &json!({"fl_x": 100.0, "frames": frames, "train_filenames": [names[0]], "test_filenames": [names[1]]}));
    assert_eq!(split(Some(Holdout::Fraction(0.5)), Split::Test), [names[1].clone()]);
}

/// nerfstudio's `filename` eval mode: images named with `train` train, those with `eval` test
/// (by the file's name, not its folder's); a name with neither is an error naming it.
#[test]
fn the_filename_holdout_splits_by_the_images_names() {
    use nerf_data::Holdout;
    let dir = tempfile::tempdir().unwrap();
    let mut frames = frames_of(&lego_100(), "train");
    frames.truncate(6);
    std::fs::create_dir_all(dir.path().join("eval_shots")).unwrap();
    let mut names = Vec::new();
    for (i, f) in frames.iter_mut().enumerate() {
        // Views 1 and 4 test; the folder's name does not count.
        let name = if i % 3 == 1 { format!("eval_shots/{i:02}_eval.png") } else { format!("eval_shots/frame_train_{i:02}.png") };
        std::fs::copy(f["file_path"].as_str().unwrap(), dir.path().join(&name)).unwrap();
        f["file_path"] = json!(name);
        names.push(dir.path().join(&name));
    }
    write_json(&dir.path().join("transforms.json"), &json!({"fl_x": 100.0, "frames": frames.clone()}));
    let load = |s: Split| load_scene(dir.path(), s, &LoadOptions { holdout: Some(Holdout::Filename), cameras_only: true, ..LoadOptions::default() });
    // In name order: `01_eval`, `04_eval`, then the `frame_train_*`.
    assert_eq!(load(Split::Test).unwrap().file_paths, [names[1].clone(), names[4].clone()]);
    assert_eq!(load(Split::Train).unwrap().file_paths, [0, 2, 3, 5].map(|i| names[i].clone()));
    assert_eq!("filename".parse::<Holdout>().unwrap(), Holdout::Filename);
    // A frame named with neither.
    std::fs::copy(&names[2], dir.path().join("eval_shots/other.png")).unwrap();
    frames[2]["file_path"] = json!("eval_shots/other.png");
    write_json(&dir.path().join("transforms.json"), &json!({"fl_x": 100.0, "frames": frames}));
    let e = load(Split::Train).unwrap_err().to_string();
    assert!(e.contains("transforms.json") && e.contains("holdout") && e.contains("other.png") && e.contains("neither"), "{e}");
}
