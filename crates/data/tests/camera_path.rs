//! nerfstudio camera paths: reading one written by hand, the round trip through the writer, and a
//! clear error for each kind of bad file.

use nerf_data::{camera_path_json, load_camera_path, DataError};
use nerf_rays::glam::{Mat3, Vec3};
use nerf_rays::{Camera, PixelConvention, Projection};

fn write(dir: &std::path::Path, name: &str, text: &str) -> std::path::PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn a_nerfstudio_path_gives_its_poses_and_vertical_field_of_view() {
    let d = tempfile::tempdir().unwrap();
    // Two cameras 4 units out on +z and +x, both looking at the origin; 90° and 60° vertical fov;
    // a 200×100 image; the keys nerfstudio's viewer adds beside them are ignored.
    let p = write(
        d.path(),
        "camera_path.json",
        r#"{"keyframes": [], "camera_type": "perspective", "render_height": 100, "render_width": 200,
            "fps": 24, "seconds": 2, "smoothness_value": 0.5, "is_cycle": false, "crop": null,
            "camera_path": [
              {"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1], "fov": 90, "aspect": 2},
              {"camera_to_world": [0,0,1,4, 0,1,0,0, -1,0,0,0, 0,0,0,1], "fov": 60, "aspect": 2}
            ]}"#,
    );
    let path = load_camera_path(&p).unwrap();
    assert_eq!(path.fps, Some(24.0));
    assert_eq!(path.cameras.len(), 2);
    let (a, b) = (&path.cameras[0], &path.cameras[1]);
    assert_eq!((a.intrinsics.width, a.intrinsics.height), (200, 100));
    // fy = ½·H / tan(½·fov): 50 at 90°, 50·√3 at 60°; square pixels, centred principal point.
    assert!((a.intrinsics.fy - 50.0).abs() < 1e-4 && a.intrinsics.fx == a.intrinsics.fy, "{:?}", a.intrinsics);
    assert!((b.intrinsics.fy - 50.0 * 3f32.sqrt()).abs() < 1e-3, "{:?}", b.intrinsics);
    assert_eq!((a.intrinsics.cx, a.intrinsics.cy), (100.0, 50.0));
    // The fourth column is the position (the matrix is row-major), and the centre pixel looks at
    // the origin from both.
    assert_eq!(a.position, Vec3::new(0.0, 0.0, 4.0));
    assert_eq!(b.position, Vec3::new(4.0, 0.0, 0.0));
    for cam in [a, b] {
        let r = cam.ray(100, 50, PixelConvention::Integer);
        let to_origin = -cam.position.normalize();
        assert!(r.dir.normalize().dot(to_origin) > 0.9999, "{:?} {:?}", r.dir, cam.position);
    }
    // The image's top edge at 90° is 45° above the axis: the corner ray of the top-centre pixel.
    let top = a.ray_at(100.0, 0.0).dir.normalize();
    assert!((top.y - (0.5f32).sqrt()).abs() < 1e-5, "{top:?}");
}

#[test]
fn written_paths_read_back_to_the_same_cameras() {
    let d = tempfile::tempdir().unwrap();
    let k = nerf_rays::Intrinsics::from_fov_x(64, 48, 0.6911112070083618);
    // Arbitrary rotations and positions: the exact f32 values must survive the JSON text.
    let cams: Vec<Camera> = (0..5)
        .map(|i| {
            let t = 0.37 * i as f32 + 0.1;
            let rotation = Mat3::from_euler(nerf_rays::glam::EulerRot::YXZ, t, -0.4 * t, 0.05 * t);
            Camera { intrinsics: k, rotation, position: Vec3::new(3.1 * t.cos(), 0.7 - t, 2.9 * t.sin()), distortion: nerf_rays::Distortion::NONE }
        })
        .collect();
    let text = serde_json::to_string_pretty(&camera_path_json(&cams, Projection::Perspective, 12.5, None)).unwrap();
    let p = write(d.path(), "path.json", &text);
    let back = load_camera_path(&p).unwrap();
    assert_eq!(back.fps, Some(12.5));
    assert_eq!(back.projection, Projection::Perspective);
    assert_eq!(back.cameras.len(), cams.len());
    for (a, b) in cams.iter().zip(&back.cameras) {
        assert_eq!(a.intrinsics, b.intrinsics, "square pixels and a centred principal point come back exactly");
        assert_eq!(a.c2w(), b.c2w());
    }
}

#[test]
fn bad_paths_name_the_file_and_the_key() {
    let d = tempfile::tempdir().unwrap();
    let cam = r#"{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1], "fov": 50}"#;
    let ok = format!(r#"{{"render_width": 8, "render_height": 6, "camera_path": [{cam}]}}"#);
    assert_eq!(load_camera_path(&write(d.path(), "ok.json", &ok)).unwrap().cameras.len(), 1);
    let cases: Vec<(String, &str)> = vec![
        ("{ not json".into(), "malformed JSON"),
        ("[]".into(), "JSON object"),
        (format!(r#"{{"render_height": 6, "camera_path": [{cam}]}}"#), "render_width"),
        (format!(r#"{{"render_width": 0, "render_height": 6, "camera_path": [{cam}]}}"#), "render_width"),
        (format!(r#"{{"render_width": 8.5, "render_height": 6, "camera_path": [{cam}]}}"#), "render_width"),
        (r#"{"render_width": 8, "render_height": 6}"#.into(), "camera_path"),
        (r#"{"render_width": 8, "render_height": 6, "camera_path": []}"#.into(), "no cameras"),
        (format!(r#"{{"camera_type": "vr180_l", "render_width": 8, "render_height": 6, "camera_path": [{cam}]}}"#), "equirectangular"),
        (format!(r#"{{"render_width": 8, "render_height": 6, "fps": -1, "camera_path": [{cam}]}}"#), "fps"),
        (
            format!(r#"{{"render_width": 8, "render_height": 6, "camera_path": [{cam}, {{"camera_to_world": [1,0,0], "fov": 50}}]}}"#),
            "camera_path[1].camera_to_world",
        ),
        (
            format!(r#"{{"render_width": 8, "render_height": 6, "camera_path": [{cam}, {{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,1e39, 0,0,0,1], "fov": 50}}]}}"#),
            "camera_path[1].camera_to_world",
        ),
        (r#"{"render_width": 8, "render_height": 6, "camera_path": [{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4]}]}"#.into(), "camera_path[0].fov"),
        (r#"{"render_width": 8, "render_height": 6, "camera_path": [{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4], "fov": 180}]}"#.into(), "camera_path[0].fov"),
    ];
    for (i, (text, needle)) in cases.iter().enumerate() {
        let p = write(d.path(), &format!("bad{i}.json"), text);
        let e = load_camera_path(&p).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains(&format!("bad{i}.json")) && msg.contains(needle), "case {i}: {msg}");
    }
    let e = load_camera_path(&d.path().join("missing.json")).unwrap_err();
    assert!(matches!(e, DataError::Io { .. }) && e.to_string().contains("missing.json"), "{e}");
}

#[test]
fn equirectangular_paths_need_no_field_of_view_and_read_back() {
    let d = tempfile::tempdir().unwrap();
    // nerfstudio writes a fov for panoramas too; it is not used, nor needed.
    let p = write(
        d.path(),
        "pano.json",
        r#"{"camera_type": "equirectangular", "render_width": 64, "render_height": 32, "fps": 10,
            "camera_path": [
              {"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1], "fov": 75},
              {"camera_to_world": [0,0,1,4, 0,1,0,0, -1,0,0,0, 0,0,0,1]}
            ]}"#,
    );
    let path = load_camera_path(&p).unwrap();
    assert_eq!(path.projection, Projection::Equirectangular);
    assert_eq!(path.cameras.len(), 2);
    for c in &path.cameras {
        assert_eq!(c.intrinsics, nerf_data::equirect_intrinsics(64, 32));
    }
    assert_eq!(path.cameras[1].position, Vec3::new(4.0, 0.0, 0.0));
    let text = serde_json::to_string(&camera_path_json(&path.cameras, path.projection, 10.0, path.crop.as_ref())).unwrap();
    assert!(text.contains(r#""camera_type":"equirectangular""#), "{text}");
    let back = load_camera_path(&write(d.path(), "again.json", &text)).unwrap();
    assert_eq!(back.projection, Projection::Equirectangular);
    for (a, b) in path.cameras.iter().zip(&back.cameras) {
        assert_eq!((a.intrinsics, a.c2w()), (b.intrinsics, b.c2w()));
    }
}

#[test]
fn fisheye_paths_take_their_focal_length_from_the_fov() {
    let d = tempfile::tempdir().unwrap();
    let p = write(
        d.path(),
        "fish.json",
        r#"{"camera_type": "fisheye", "render_width": 200, "render_height": 100,
            "camera_path": [{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1], "fov": 90}]}"#,
    );
    let path = load_camera_path(&p).unwrap();
    assert_eq!(path.projection, Projection::Fisheye);
    assert!((path.cameras[0].intrinsics.fy - 50.0).abs() < 1e-4, "{:?}", path.cameras[0].intrinsics);
    let text = serde_json::to_string(&camera_path_json(&path.cameras, path.projection, 24.0, None)).unwrap();
    assert!(text.contains(r#""camera_type":"fisheye""#), "{text}");
    let no_fov = write(
        d.path(),
        "nofov.json",
        r#"{"camera_type": "fisheye", "render_width": 8, "render_height": 6,
            "camera_path": [{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1]}]}"#,
    );
    let e = load_camera_path(&no_fov).unwrap_err().to_string();
    assert!(e.contains("nofov.json") && e.contains("camera_path[0].fov"), "{e}");
}

#[test]
fn a_nerfstudio_crop_reads_and_writes_back() {
    let d = tempfile::tempdir().unwrap();
    let cam = r#"{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1], "fov": 50}"#;
    let file = |crop: &str| format!(r#"{{"render_width": 8, "render_height": 8, "crop": {crop}, "camera_path": [{cam}]}}"#);
    // What nerfstudio's viewer exports: centre, full size, roll/pitch/yaw, a 0–255 colour.
    let p = write(
        d.path(),
        "crop.json",
        &file(r#"{"crop_center": [0.5, -1, 2], "crop_scale": [1, 2, 3], "crop_rot": [0, 0, 1.5], "crop_bg_color": {"r": 255, "g": 0, "b": 51}}"#),
    );
    let path = load_camera_path(&p).unwrap();
    let c = path.crop.expect("a crop");
    assert_eq!((c.center, c.scale, c.rotation), ([0.5, -1.0, 2.0], [1.0, 2.0, 3.0], [0.0, 0.0, 1.5]));
    assert_eq!(c.background, [1.0, 0.0, 0.2]);
    // Written back with the path, read back the same.
    let text = serde_json::to_string(&camera_path_json(&path.cameras, path.projection, 24.0, Some(&c))).unwrap();
    assert_eq!(load_camera_path(&write(d.path(), "again.json", &text)).unwrap().crop, Some(c));
    // No rotation and no colour: none and black; `null` (what the viewer writes without a crop): no crop.
    let p = write(d.path(), "plain.json", &file(r#"{"crop_center": [0, 0, 0], "crop_scale": [2, 2, 2]}"#));
    let c = load_camera_path(&p).unwrap().crop.unwrap();
    assert_eq!((c.rotation, c.background), ([0.0; 3], [0.0; 3]));
    assert!(load_camera_path(&write(d.path(), "none.json", &file("null"))).unwrap().crop.is_none());
    // Bad crops name the key.
    for (crop, key) in [
        (r#"{"crop_scale": [1, 1, 1]}"#, "crop.crop_center"),
        (r#"{"crop_center": [0, 0, 0], "crop_scale": [1, 0, 1]}"#, "crop.crop_scale"),
        (r#"{"crop_center": [0, 0], "crop_scale": [1, 1, 1]}"#, "crop.crop_center"),
        (r#"{"crop_center": [0, 0, 0], "crop_scale": [1, 1, 1], "crop_rot": [0, "x", 0]}"#, "crop.crop_rot"),
        (r#"{"crop_center": [0, 0, 0], "crop_scale": [1, 1, 1], "crop_bg_color": {"r": 300, "g": 0, "b": 0}}"#, "crop.crop_bg_color"),
    ] {
        let p = write(d.path(), "bad.json", &file(crop));
        match load_camera_path(&p) {
            Err(DataError::InvalidValue { path, key: k, .. }) => assert_eq!((path, k.as_str()), (p.clone(), key), "{crop}"),
            other => panic!("{crop}: expected an invalid {key}, got {other:?}"),
        }
    }
}
