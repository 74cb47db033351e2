//! LLFF loading (`poses_bounds.npy` + `images_<k>/`): axis conversion, bd_factor scaling and
//! recentring checked through what they must leave unchanged, the held-out split, the image
//! folder a downscale picks, error reporting; on tiny scenes written into temporary folders (and
//! on fern when shared/data has it).

use std::path::Path;

use glam::{DMat3, DVec3, Vec3};
use nerf_data::{load_llff, load_scene, save_png, Background, DataError, Dataset, LoadOptions, RayBatch, Split, ViewSelection};
use nerf_rays::PixelConvention;

/// Writes `rows` (each 17 values) as a C-ordered little-endian f64 `.npy` file (format 1.0).
fn write_npy(path: &Path, rows: &[[f64; 17]]) {
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, 17), }}", rows.len());
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in rows.iter().flatten() {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, bytes).unwrap();
}

/// An OpenGL camera-to-world pose (rotation columns right, up, back; centre) as LLFF's row:
/// columns `[down, right, back, t, (h, w, f)]`, then the bounds.
fn llff_row(r: DMat3, t: DVec3, hwf: [f64; 3], bounds: [f64; 2]) -> [f64; 17] {
    let cols = [-r.y_axis, r.x_axis, r.z_axis, t];
    let mut row = [0.0; 17];
    for i in 0..3 {
        for (c, col) in cols.iter().enumerate() {
            row[5 * i + c] = col[i];
        }
        row[5 * i + 4] = hwf[i];
    }
    row[15] = bounds[0];
    row[16] = bounds[1];
    row
}

/// A forward-facing rig: `n` cameras on a small grid in the plane z = 0, all looking down −z
/// with slightly different yaw, then moved by the rigid transform `(g, shift)` and scaled by `s`.
fn rig(n: usize, g: DMat3, shift: DVec3, s: f64) -> Vec<[f64; 17]> {
    (0..n)
        .map(|i| {
            let yaw = 0.05 * (i as f64 - 0.5 * n as f64);
            let r = DMat3::from_rotation_y(yaw);
            let t = DVec3::new(0.3 * (i % 3) as f64 - 0.3, 0.2 * (i / 3) as f64 - 0.2, 0.05 * i as f64);
            llff_row(g * r, s * (g * t) + shift, [48.0, 64.0, 60.0], [s * (2.0 + 0.1 * i as f64), s * 9.0])
        })
        .collect()
}

/// A scene folder with `rows` and, per factor in `factors`, `images_<k>/` of the poses' 64×48
/// images divided by k (factor 1: `images/`), each image a flat colour per index.
fn scene(dir: &Path, rows: &[[f64; 17]], factors: &[u32]) {
    write_npy(&dir.join("poses_bounds.npy"), rows);
    for &k in factors {
        let folder = dir.join(if k == 1 { "images".to_string() } else { format!("images_{k}") });
        let (w, h) = (64 / k, 48 / k);
        for i in 0..rows.len() {
            let c = i as f32 / rows.len() as f32;
            let rgb: Vec<f32> = (0..w * h).flat_map(|_| [c, 0.5, 1.0 - c]).collect();
            save_png(&folder.join(format!("IMG_{i:03}.png")), w, h, &rgb).unwrap();
        }
    }
}

/// Euclidean rays (`--no-ndc`): the loader's geometry checked in world units.
fn opts(k: u32) -> LoadOptions {
    LoadOptions { downscale: k, views: ViewSelection::All, ndc: false, cameras_only: false, sfm_depth: false, undistort: false, aabb_scale: None, nerfstudio: Default::default(), holdout: None, format: Default::default() }
}

/// The default: NDC rays.
fn ndc_opts(k: u32) -> LoadOptions {
    LoadOptions { downscale: k, views: ViewSelection::All, ndc: true, cameras_only: false, sfm_depth: false, undistort: false, aabb_scale: None, nerfstudio: Default::default(), holdout: None, format: Default::default() }
}

fn poses(ds: &Dataset) -> Vec<(glam::Mat3, Vec3)> {
    ds.cameras.iter().map(|c| (c.rotation, c.position)).collect()
}

fn assert_same_poses(a: &Dataset, b: &Dataset, tol: f32) {
    for (i, ((ra, ta), (rb, tb))) in poses(a).iter().zip(poses(b)).enumerate() {
        assert!(ra.abs_diff_eq(rb, tol) && ta.abs_diff_eq(tb, tol), "camera {i}: {ra:?} {ta} vs {rb:?} {tb}");
    }
    assert!((a.near - b.near).abs() < tol && (a.far - b.far).abs() < tol);
    assert!(Vec3::from(a.aabb.min).abs_diff_eq(Vec3::from(b.aabb.min), 10.0 * tol));
}

#[test]
fn poses_are_recentred_scaled_and_split_as_nerf_pytorch_does() {
    let n = 10;
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), &rig(n, DMat3::IDENTITY, DVec3::ZERO, 1.0), &[2]);
    let train = load_llff(dir.path(), Split::Train, &opts(2)).unwrap();
    let test = load_llff(dir.path(), Split::Test, &opts(2)).unwrap();
    // Every 8th image is held out: 0 and 8 of 10.
    let names = |d: &Dataset| -> Vec<String> {
        d.file_paths.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect()
    };
    assert_eq!(names(&test), ["IMG_000.png", "IMG_008.png"]);
    assert_eq!(names(&train).len(), 8);
    assert!(!names(&train).contains(&"IMG_008.png".to_string()));
    assert_eq!(names(&load_llff(dir.path(), Split::Val, &opts(2)).unwrap()), names(&test));
    // nerfstudio's fraction split (`LoadOptions::holdout`): ⌈0.9·10⌉ = 9 train views spread as
    // numpy's linspace(0, 9, 9) truncated, image 8 held out.
    let frac = LoadOptions { holdout: Some(nerf_data::Holdout::Fraction(0.9)), ..opts(2) };
    assert_eq!(names(&load_llff(dir.path(), Split::Test, &frac).unwrap()), ["IMG_008.png"]);
    assert_eq!(names(&load_llff(dir.path(), Split::Train, &frac).unwrap()).len(), 9);
    // Images of images_2 (32×24), the focal of the full-resolution poses halved.
    assert_eq!((train.width, train.height), (32, 24));
    let k = train.cameras[0].intrinsics;
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (30.0, 30.0, 16.0, 12.0));
    // bd_factor: the nearest bound (2.0) becomes 1/0.75; near = 0.9 of it; far = 9 · sc, stretched
    // to the image corner's ray length.
    let sc = 1.0 / (2.0 * 0.75);
    assert!((test.near - (0.9 * 2.0 * sc) as f32).abs() < 1e-5, "{}", test.near);
    let corner = (1.0f64 + (32.0 / 60.0f64).powi(2) + (24.0 / 60.0f64).powi(2)).sqrt();
    assert!((test.far - (9.0 * sc * corner) as f32).abs() < 1e-4, "{}", test.far);
    // Recentred: the mean camera centre is the origin and the summed axes are the world's.
    let all: Vec<(glam::Mat3, Vec3)> = poses(&train).into_iter().chain(poses(&test)).collect();
    let mean = all.iter().map(|p| p.1).sum::<Vec3>() / n as f32;
    assert!(mean.length() < 1e-5, "{mean}");
    let z = all.iter().map(|p| p.0.z_axis).sum::<Vec3>().normalize();
    assert!(z.abs_diff_eq(Vec3::Z, 1e-5), "{z}");
    assert!(all.iter().map(|p| p.0.y_axis).sum::<Vec3>().normalize().dot(Vec3::X).abs() < 1e-5);
    // Each camera sees the others where the rig put them (scaled by sc): the offset from train
    // image 1 (all[0]) to image 2 (all[1]) in image 1's camera axes. A wrong LLFF axis order
    // would survive recentring but not this.
    let rig_pose = |i: usize| {
        let t = DVec3::new(0.3 * (i % 3) as f64 - 0.3, 0.2 * (i / 3) as f64 - 0.2, 0.05 * i as f64);
        (DMat3::from_rotation_y(0.05 * (i as f64 - 0.5 * n as f64)), t)
    };
    let ((r1, t1), (_, t2)) = (rig_pose(1), rig_pose(2));
    let expect = (r1.transpose() * (t2 - t1) * sc).as_vec3();
    let got = all[0].0.transpose() * (all[1].1 - all[0].1);
    assert!(got.abs_diff_eq(expect, 1e-5), "{got} vs {expect}");
    // The scene box holds every camera and what it sees up to the far bound.
    for c in &test.cameras {
        for (u, v) in [(0.0, 0.0), (32.0, 24.0), (16.0, 12.0)] {
            let d = c.rotation * Vec3::new((u - 16.0) / 30.0, -(v - 12.0) / 30.0, -1.0);
            for p in [c.position, c.position + d * (9.0 * sc) as f32] {
                assert!(train.aabb.contains(p.to_array()), "{p} outside {:?}", train.aabb);
            }
        }
    }
    // load_scene picks the LLFF loader.
    assert_eq!(names(&load_scene(dir.path(), Split::Test, &opts(2)).unwrap()), names(&test));
}

#[test]
fn ndc_rays_are_nerf_pytorchs_and_the_box_holds_their_whole_segment() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), &rig(10, DMat3::IDENTITY, DVec3::ZERO, 1.0), &[2]);
    let euclid = load_llff(dir.path(), Split::Test, &opts(2)).unwrap();
    let ds = load_llff(dir.path(), Split::Test, &ndc_opts(2)).unwrap();
    assert!(euclid.ndc.is_none());
    let ndc = ds.ndc.expect("LLFF loads in NDC by default");
    // Same cameras; the near plane z = −1 of nerf-pytorch, scales 2f/W and 2f/H.
    assert_same_poses_only(&ds, &euclid);
    assert_eq!((ndc.near, ndc.scale_x, ndc.scale_y), (1.0, 2.0 * 30.0 / 32.0, 2.0 * 30.0 / 24.0));
    assert_eq!(ds.near, 0.0);
    assert_eq!((ds.aabb.min[2], ds.aabb.max[2]), (-1.0, 1.0));
    let sc = 1.0 / (2.0 * 0.75);
    let [lo, hi] = ds.depth_bounds.unwrap();
    assert!((lo - (2.0 * sc) as f32).abs() < 1e-6 && (hi - (9.0 * sc) as f32).abs() < 1e-5, "{lo} {hi}");
    // Every pixel's ray is the NDC ray of its camera ray, unit length, starting on z' = −1, and
    // its part inside the box is its whole NDC segment [0, |d'|] (near plane to infinity).
    let mut b = RayBatch::default();
    for v in 0..ds.n_views() {
        ds.view_rays(v, Background::White, PixelConvention::Center, &mut b);
        let cam = &ds.cameras[v];
        for r in 0..b.len() {
            let (o, d) = (Vec3::from_slice(&b.origins[3 * r..]), Vec3::from_slice(&b.dirs[3 * r..]));
            let world = cam.ray((r % 32) as u32, (r / 32) as u32, PixelConvention::Center);
            let (eo, ed) = ndc.ray_unnormalized(world.origin, world.dir).unwrap();
            assert!(o.abs_diff_eq(eo, 1e-5) && d.abs_diff_eq(ed.normalize(), 1e-5), "view {v} ray {r}");
            let (t0, t1) = ds.aabb.intersect(o.to_array(), d.to_array()).expect("in the box");
            assert!(t0 < 1e-5 && (t1 - ed.length()).abs() < 1e-4, "view {v} ray {r}: {t0}..{t1} vs {}", ed.length());
            // The scene's depth range lies on that segment: the far bound maps inside the box.
            let p = ndc.point(world.origin + world.dir * (hi / world.dir.dot(-cam.rotation.z_axis)));
            assert!(ds.aabb.contains(p.to_array()), "{p}");
        }
    }
    // A camera turned away from the others is not a forward-facing capture: NDC is refused with
    // a message naming the file and the way out; Euclidean rays still load.
    let mut rows = rig(10, DMat3::IDENTITY, DVec3::ZERO, 1.0);
    rows[3] = llff_row(DMat3::from_rotation_y(1.7), DVec3::ZERO, [48.0, 64.0, 60.0], [2.0, 9.0]);
    let bad = tempfile::tempdir().unwrap();
    scene(bad.path(), &rows, &[2]);
    let e = load_llff(bad.path(), Split::Train, &ndc_opts(2)).unwrap_err().to_string();
    assert!(e.contains("poses_bounds.npy") && e.contains("forward-facing") && e.contains("--no-ndc"), "{e}");
    assert!(!e.contains("--scene-format"), "{e}");
    assert!(load_llff(bad.path(), Split::Train, &opts(2)).is_ok());
    // With a COLMAP model beside the poses (mip-NeRF 360's scenes), the message points to it.
    std::fs::create_dir_all(bad.path().join("sparse/0")).unwrap();
    for f in ["cameras.txt", "images.txt"] {
        std::fs::write(bad.path().join("sparse/0").join(f), "").unwrap();
    }
    let e = load_llff(bad.path(), Split::Train, &ndc_opts(2)).unwrap_err().to_string();
    assert!(e.contains("--no-ndc") && e.contains("--scene-format colmap"), "{e}");
}

fn assert_same_poses_only(a: &Dataset, b: &Dataset) {
    for (i, ((ra, ta), (rb, tb))) in poses(a).iter().zip(poses(b)).enumerate() {
        assert!(ra.abs_diff_eq(rb, 1e-6) && ta.abs_diff_eq(tb, 1e-6), "camera {i}");
    }
}

#[test]
fn a_rigid_motion_or_a_scale_of_the_capture_changes_nothing() {
    let base = tempfile::tempdir().unwrap();
    scene(base.path(), &rig(9, DMat3::IDENTITY, DVec3::ZERO, 1.0), &[4]);
    let a = load_llff(base.path(), Split::Train, &opts(4)).unwrap();
    // LLFF's axis order is checked too: a wrong conversion would not cancel under recentring
    // for a rotated rig with its own roll.
    let g = DMat3::from_euler(glam::EulerRot::XYZ, 0.7, -1.1, 0.4);
    let moved = tempfile::tempdir().unwrap();
    scene(moved.path(), &rig(9, g, DVec3::new(3.0, -2.0, 5.0), 3.5), &[4]);
    let b = load_llff(moved.path(), Split::Train, &opts(4)).unwrap();
    assert_same_poses(&a, &b, 2e-5);
}

#[test]
fn a_downscale_uses_the_closest_image_folder_and_box_averages_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), &rig(9, DMat3::IDENTITY, DVec3::ZERO, 1.0), &[2, 4]);
    let k4 = load_llff(dir.path(), Split::Train, &opts(4)).unwrap();
    assert!(k4.file_paths[0].to_string_lossy().contains("images_4"));
    // 8 from images_4 (the largest divisor present), box-averaged by 2.
    let k8 = load_llff(dir.path(), Split::Train, &opts(8)).unwrap();
    assert!(k8.file_paths[0].to_string_lossy().contains("images_4"));
    assert_eq!((k8.width, k8.height), (8, 6));
    assert_eq!(k8.cameras[0].intrinsics.fx, 60.0 / 8.0);
    let px = k8.images[0].to_f32();
    assert!((px[0] - k4.images[0].value(0)).abs() < 1e-6 && px[3] == 1.0, "RGB images get alpha 1");
    // No folder for 3 (nor for 1): the error lists what the scene has.
    let e = load_llff(dir.path(), Split::Train, &opts(3)).unwrap_err().to_string();
    assert!(e.contains("images_3") && e.contains("images_2, images_4") && e.contains("--downscale"), "{e}");
}

#[test]
fn bad_llff_scenes_are_clear_errors_naming_the_file() {
    let rows = rig(9, DMat3::IDENTITY, DVec3::ZERO, 1.0);
    let check = |edit: &dyn Fn(&Path), needles: &[&str]| {
        let dir = tempfile::tempdir().unwrap();
        scene(dir.path(), &rows, &[2]);
        edit(dir.path());
        let e = match load_llff(dir.path(), Split::Train, &opts(2)) {
            Ok(_) => panic!("loaded a bad scene; expected {needles:?}"),
            Err(e) => e,
        };
        let text = e.to_string();
        for n in needles {
            assert!(text.contains(n), "{text:?} should mention {n:?}");
        }
        e
    };
    // Not N×17.
    check(&|d| write_npy(&d.join("poses_bounds.npy"), &[]), &["poses_bounds.npy", "N×17"]);
    // Not a .npy file at all.
    check(&|d| std::fs::write(d.join("poses_bounds.npy"), "x,y\n1,2\n").unwrap(), &["poses_bounds.npy", ".npy"]);
    // A NaN in a pose names the image.
    let e = check(
        &|d| {
            let mut r = rows.clone();
            r[3][7] = f64::NAN;
            write_npy(&d.join("poses_bounds.npy"), &r);
        },
        &["poses_bounds.npy", "frame 3", "non-finite"],
    );
    assert!(matches!(e, DataError::NonFinitePose { frame: 3, .. }));
    // Bounds out of order.
    check(
        &|d| {
            let mut r = rows.clone();
            r[2][15] = 10.0;
            write_npy(&d.join("poses_bounds.npy"), &r);
        },
        &["image 2", "depth bounds"],
    );
    // One image too few.
    check(&|d| std::fs::remove_file(d.join("images_2/IMG_004.png")).unwrap(), &["images_2", "8 image files", "9 poses"]);
    // Images of different sizes.
    check(
        &|d| save_png(&d.join("images_2/IMG_005.png"), 16, 12, &vec![0.5; 3 * 16 * 12]).unwrap(),
        &["IMG_005.png", "16x12", "32x24"],
    );
    // Images whose aspect ratio is not the poses'.
    check(
        &|d| {
            for i in 0..9 {
                save_png(&d.join(format!("images_2/IMG_{i:03}.png")), 32, 32, &vec![0.5; 3 * 32 * 32]).unwrap();
            }
        },
        &["IMG_001.png", "aspect ratio"],
    );
    // No poses file: the Blender loader's "not found" for the scene's marker file.
    let dir = tempfile::tempdir().unwrap();
    let e = load_llff(dir.path(), Split::Train, &opts(1)).unwrap_err().to_string();
    assert!(e.contains("poses_bounds.npy") && e.contains("not found"), "{e}");
}

#[test]
fn fern_loads_as_nerf_pytorch_splits_it() {
    let Some(fern) = nerf_core::shared::data(env!("CARGO_MANIFEST_DIR"), "nerf_llff_data/fern") else { return };
    let train = load_scene(&fern, Split::Train, &opts(8)).unwrap();
    let test = load_scene(&fern, Split::Test, &opts(8)).unwrap();
    assert_eq!((train.n_views(), test.n_views()), (17, 3));
    assert_eq!((train.width, train.height), (504, 378));
    // focal 3260.53 px at 4032 wide, divided by 8.
    assert!((train.cameras[0].intrinsics.fx - 3260.5264 / 8.0).abs() < 1e-3);
    // Bounds 16.99–80.0 scaled so that the nearest is 1/0.75.
    assert!((train.near - 1.2).abs() < 1e-5, "{}", train.near);
    let far_depth = 80.0021 / (16.9853 * 0.75);
    assert!(train.far > far_depth as f32 && train.far < 1.3 * far_depth as f32, "{}", train.far);
    // Forward-facing: every camera looks within 20° of −z, and the cameras are close together
    // compared with the depth of the scene.
    for c in train.cameras.iter().chain(&test.cameras) {
        assert!(c.rotation.z_axis.dot(Vec3::Z) > 20f32.to_radians().cos(), "{:?}", c.rotation);
        assert!(c.position.length() < 0.5 * train.near, "{}", c.position);
    }
    // In NDC (the default), every camera's frustum fits the box and the box is not much wider
    // than the image plane's [−1, 1]² (the cameras are close to the mean one).
    let ndc = load_scene(&fern, Split::Train, &ndc_opts(8)).unwrap();
    assert!(ndc.ndc.is_some() && ndc.near == 0.0);
    assert!(ndc.aabb.min[..2].iter().all(|&v| v > -1.6 && v < -0.9) && ndc.aabb.max[..2].iter().all(|&v| v < 1.6 && v > 0.9), "{:?}", ndc.aabb);
}

#[test]
fn cameras_only_gives_the_full_loads_cameras_without_decoding() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), &rig(9, DMat3::IDENTITY, DVec3::ZERO, 1.0), &[2, 4]);
    for (k, ndc) in [(4, false), (8, true)] {
        let full = load_llff(dir.path(), Split::Train, &LoadOptions { ndc, ..opts(k) }).unwrap();
        let cams = load_llff(dir.path(), Split::Train, &LoadOptions { ndc, cameras_only: true, ..opts(k) }).unwrap();
        assert!(full.has_images() && !cams.has_images());
        assert_eq!(cams.images.len(), cams.n_views());
        assert_eq!((cams.width, cams.height, cams.file_paths.clone()), (full.width, full.height, full.file_paths.clone()));
        assert_eq!(poses(&cams), poses(&full));
        assert_eq!(cams.cameras.iter().map(|c| c.intrinsics).collect::<Vec<_>>(), full.cameras.iter().map(|c| c.intrinsics).collect::<Vec<_>>());
        assert_eq!((cams.near, cams.far, cams.aabb, cams.depth_bounds, cams.ndc.is_some()), (full.near, full.far, full.aabb, full.depth_bounds, ndc));
    }
    // An LLFF scene has no instant-ngp box to grow.
    let e = load_llff(dir.path(), Split::Train, &LoadOptions { aabb_scale: Some(16.0), ..opts(4) }).unwrap_err().to_string();
    assert!(e.contains("poses_bounds.npy") && e.contains("aabb_scale") && e.contains("LLFF"), "{e}");
    // A folder whose images are not those of the poses' aspect is still refused without decoding.
    let bad = tempfile::tempdir().unwrap();
    scene(bad.path(), &rig(9, DMat3::IDENTITY, DVec3::ZERO, 1.0), &[]);
    for i in 0..9 {
        save_png(&bad.path().join(format!("images_4/IMG_{i:03}.png")), 16, 16, &vec![0.5; 3 * 256]).unwrap();
    }
    let e = load_llff(bad.path(), Split::Train, &LoadOptions { cameras_only: true, ..opts(4) }).unwrap_err().to_string();
    assert!(e.contains("aspect ratio") && e.contains("IMG_"), "{e}");
}
