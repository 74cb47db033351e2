//! Depth maps (nerfstudio's `depth_file_path`, instant-ngp's `depth_path`): loaded as distances
//! along the pixels' rays in the scene's units, through downscaling and lens resampling, written
//! back by `write_blender`, and their errors.

use std::path::Path;

use nerf_data::{load_blender, write_blender, DataError, Dataset, LoadOptions, Split};
use serde_json::{json, Value};

const W: u32 = 12;
const H: u32 = 8;

fn write_json(path: &Path, v: &Value) {
    std::fs::write(path, serde_json::to_string_pretty(v).unwrap()).unwrap();
}

/// A photo and a 16-bit depth map of the plane z = 0 seen from `(0.3, −0.2, 3)` looking down −z
/// (z-depth 3 m everywhere, 3000 in millimetres), but for the pixel `(2, 1)`, which has none.
fn capture(dir: &Path, depth_key: &str, extra: Value) {
    image::RgbImage::from_pixel(W, H, image::Rgb([200, 100, 50])).save(dir.join("a.png")).unwrap();
    let depth = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(W, H, |i, j| image::Luma([if (i, j) == (2, 1) { 0 } else { 3000 }]));
    depth.save(dir.join("a_depth.png")).unwrap();
    // Frame 0 is the test view; frame 1, elsewhere over the plane, gives nerfstudio's
    // normalisation two cameras to work from.
    let frame = |x: f64| json!({"file_path": "a.png", depth_key: "a_depth.png", "transform_matrix": [[1, 0, 0, x], [0, 1, 0, -0.2], [0, 0, 1, 3], [0, 0, 0, 1]]});
    let mut top = json!({"fl_x": 10.0, "fl_y": 11.0, "cx": 5.5, "cy": 4.25, "w": W, "h": H, "frames": [frame(0.3), frame(1.9)]});
    top.as_object_mut().unwrap().extend(extra.as_object().unwrap().clone());
    write_json(&dir.join("transforms.json"), &top);
}

fn load(dir: &Path, k: u32) -> Result<Dataset, DataError> {
    load_blender(dir, Split::Test, &LoadOptions { downscale: k, ..Default::default() })
}

/// Every pixel's depth puts its ray's end on the plane z = 0 (of the file's frame, times
/// `units`), but the pixels `none`, which have no depth (0).
fn assert_on_the_plane(d: &Dataset, none: &[u32], units: f32) {
    let depths = d.depths.as_ref().expect("the depth maps are loaded");
    assert_eq!((depths.len(), depths[0].len()), (1, (d.width * d.height) as usize));
    let cam = &d.cameras[0];
    for (p, &t) in depths[0].iter().enumerate() {
        let p = p as u32;
        if none.contains(&p) {
            assert_eq!(t, 0.0, "pixel {p} has no depth");
            continue;
        }
        let ray = cam.ray_at((p % d.width) as f32 + 0.5, (p / d.width) as f32 + 0.5);
        let end = ray.origin + ray.dir * t;
        // The plane z = 0 of the file, in the dataset's frame: 3 m below the camera along its axis.
        let below = (end - ray.origin).dot(-cam.rotation.col(2));
        assert!((below - 3.0 * units).abs() < 1e-4 * units.max(1.0), "pixel {p}: the ray ends {below} below the camera, not {}", 3.0 * units);
    }
}

#[test]
fn depth_maps_load_as_distances_along_the_rays() {
    // instant-ngp: `depth_path` in steps of `integer_depth_scale`, the file's units.
    let dir = tempfile::tempdir().unwrap();
    capture(dir.path(), "depth_path", json!({"integer_depth_scale": 0.001}));
    let d = load(dir.path(), 1).unwrap();
    assert_on_the_plane(&d, &[W + 2], 1.0);
    // Downscaled: the 2×2 block holding the pixel without depth has none.
    let half = load(dir.path(), 2).unwrap();
    assert_on_the_plane(&half, &[1], 1.0);
    // Loads without pixels read no depth maps.
    let cams = load_blender(dir.path(), Split::Test, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap();
    assert!(cams.depths.is_none());

    // nerfstudio: `depth_file_path` in millimetres (its default), scaled with the poses.
    let ns = tempfile::tempdir().unwrap();
    capture(ns.path(), "depth_file_path", json!({"camera_model": "OPENCV"}));
    let d = load(ns.path(), 1).unwrap();
    let units = d.normalization.expect("a nerfstudio file is normalised").scale as f32;
    assert!((units - 1.0).abs() > 0.05, "the test needs a scale that shows: {units}");
    assert_on_the_plane(&d, &[W + 2], units);
    // A file's own `depth_unit_scale_factor` (here: centimetres stored as tenths of a step).
    capture(ns.path(), "depth_file_path", json!({"camera_model": "OPENCV", "depth_unit_scale_factor": 0.01}));
    assert_on_the_plane(&load(ns.path(), 1).unwrap(), &[W + 2], 10.0 * units);

    // Written back as nerfstudio reads them: the same depths to within a 16-bit step.
    let out = tempfile::tempdir().unwrap();
    let d = load(dir.path(), 1).unwrap();
    write_blender(&d, out.path(), None).unwrap();
    let back = load_blender(out.path(), Split::Test, &LoadOptions::default()).unwrap();
    let (a, b) = (&d.depths.as_ref().unwrap()[0], &back.depths.as_ref().unwrap()[0]);
    let step = a.iter().fold(0.0f32, |m, &v| m.max(v)) / 65535.0;
    assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() <= step && (*x == 0.0) == (*y == 0.0)), "{a:?}\n{b:?}");
    // Scenes without depth maps have none.
    let plain = tempfile::tempdir().unwrap();
    capture(plain.path(), "no_depth", json!({}));
    assert!(load(plain.path(), 1).unwrap().depths.is_none());
}

#[test]
fn depth_maps_go_through_the_lens_resampling() {
    // A barrel lens: the depth of the plane is the same at every pixel, so the resampled map
    // still ends every ray on the plane, and the pixels without depth stay without.
    let dir = tempfile::tempdir().unwrap();
    capture(dir.path(), "depth_path", json!({"integer_depth_scale": 0.001, "k1": -0.05}));
    let d = load(dir.path(), 1).unwrap();
    let t = &d.depths.as_ref().unwrap()[0];
    let none: Vec<u32> = (0..W * H).filter(|&p| t[p as usize] == 0.0).collect();
    assert!(!none.is_empty() && none.len() <= 4, "the pixel without depth spreads to its bilinear neighbours only: {none:?}");
    assert_on_the_plane(&d, &none, 1.0);
}

#[test]
fn bad_depth_maps_are_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let err = |extra: Value, edit: &dyn Fn(&Path)| -> String {
        capture(dir.path(), "depth_path", extra);
        edit(dir.path());
        load(dir.path(), 1).unwrap_err().to_string()
    };
    let e = err(json!({}), &|_| {});
    assert!(e.contains("transforms.json") && e.contains("integer_depth_scale"), "{e}");
    let e = err(json!({"integer_depth_scale": -1}), &|_| {});
    assert!(e.contains("integer_depth_scale") && e.contains("positive"), "{e}");
    let e = err(json!({"integer_depth_scale": 0.001}), &|d| std::fs::remove_file(d.join("a_depth.png")).unwrap());
    assert!(e.contains("a_depth.png: depth map of frame 0: file not found"), "{e}");
    let e = err(json!({"integer_depth_scale": 0.001}), &|d| image::RgbImage::new(W, H).save(d.join("a_depth.png")).unwrap());
    assert!(e.contains("a_depth.png") && e.contains("single-channel 8- or 16-bit"), "{e}");
    let e = err(json!({"integer_depth_scale": 0.001}), &|d| image::GrayImage::new(W, H / 2).save(d.join("a_depth.png")).unwrap());
    assert!(e.contains("a_depth.png") && e.contains("it is 12x4, its photo is 12x8: not the photo's shape"), "{e}");
    let e = err(json!({"integer_depth_scale": 0.001}), &|d| {
        let mut v: Value = serde_json::from_str(&std::fs::read_to_string(d.join("transforms.json")).unwrap()).unwrap();
        v["frames"][0]["depth_path"] = json!(7);
        write_json(&d.join("transforms.json"), &v);
    });
    assert!(e.contains("frames[0].depth_path") && e.contains("expected a string"), "{e}");
}

/// Downscaling keeps no depth where a block straddles a silhouette (foreground and background
/// averaged would put a surface where nothing is), and keeps it on either side.
#[test]
fn downscaled_depth_maps_drop_silhouettes() {
    let dir = tempfile::tempdir().unwrap();
    capture(dir.path(), "depth_path", json!({"integer_depth_scale": 0.001}));
    // 1 m on columns 0–4, 3 m from column 5: the 2×2 blocks of columns 4–5 straddle the edge.
    let edge = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(W, H, |i, _| image::Luma([if i < 5 { 1000 } else { 3000 }]));
    edge.save(dir.path().join("a_depth.png")).unwrap();
    let half = load(dir.path(), 2).unwrap();
    let t = &half.depths.as_ref().unwrap()[0];
    for (p, &d) in t.iter().enumerate() {
        let col = p as u32 % (W / 2);
        assert_eq!(d == 0.0, col == 2, "pixel {p} (column {col}): {d}");
    }
}

/// A depth map smaller than its photo (a phone's LiDAR beside its camera), of the photo's shape,
/// is enlarged to it by nearest neighbour: each photo pixel takes the depth of the map's pixel
/// that covers it.
#[test]
fn smaller_depth_maps_are_enlarged_to_the_photo() {
    let dir = tempfile::tempdir().unwrap();
    capture(dir.path(), "depth_path", json!({"integer_depth_scale": 0.001}));
    // 3×2 map of the 12×8 photo: each map pixel covers 4×4 photo pixels; distinct z per pixel.
    let small = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(3, 2, |i, j| image::Luma([1000 + 500 * (i + 3 * j) as u16]));
    small.save(dir.path().join("a_depth.png")).unwrap();
    let d = load(dir.path(), 1).unwrap();
    let k = d.cameras[0].intrinsics;
    let t = &d.depths.as_ref().unwrap()[0];
    for (p, &dist) in t.iter().enumerate() {
        let (i, j) = (p as u32 % W, p as u32 / W);
        let z = 1.0 + 0.5 * (i / 4 + 3 * (j / 4)) as f32;
        let (x, y) = ((i as f32 + 0.5 - k.cx) / k.fx, (j as f32 + 0.5 - k.cy) / k.fy);
        assert!((dist - z * (x * x + y * y + 1.0).sqrt()).abs() < 1e-5, "pixel ({i}, {j}): {dist} for z = {z}");
    }
}

/// A `.npy` array of float32 values, `h×w`, as NumPy's `np.save` writes it (format 1.0).
fn write_npy_f32(path: &Path, h: usize, w: usize, values: &[f32]) {
    let dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({h}, {w}), }}");
    let pad = (64 - (10 + dict.len() + 1) % 64) % 64;
    let header = format!("{dict}{}\n", " ".repeat(pad));
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend((header.len() as u16).to_le_bytes());
    bytes.extend(header.as_bytes());
    values.iter().for_each(|v| bytes.extend(v.to_le_bytes()));
    std::fs::write(path, bytes).unwrap();
}

/// nerfstudio's `.npy` depth maps: float values times `depth_unit_scale_factor`; NaN, 0 and
/// negative values are no measurement; a malformed array is named.
#[test]
fn npy_depth_maps_load_like_images() {
    let dir = tempfile::tempdir().unwrap();
    capture(dir.path(), "depth_path", json!({"integer_depth_scale": 0.001}));
    let mut z = vec![3.0f32; (W * H) as usize];
    z[(W + 2) as usize] = f32::NAN;
    write_npy_f32(&dir.path().join("a_depth.npy"), H as usize, W as usize, &z);
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(dir.path().join("transforms.json")).unwrap()).unwrap();
    v["frames"][0]["depth_path"] = json!("a_depth.npy");
    v["integer_depth_scale"] = json!(1.0);
    write_json(&dir.path().join("transforms.json"), &v);
    assert_on_the_plane(&load(dir.path(), 1).unwrap(), &[W + 2], 1.0);
    write_npy_f32(&dir.path().join("a_depth.npy"), 2, (W * H / 2) as usize, &z);
    let e = load(dir.path(), 1).unwrap_err().to_string();
    assert!(e.contains("a_depth.npy: depth map of frame 0") && e.contains("not the photo's shape"), "{e}");
    std::fs::write(dir.path().join("a_depth.npy"), b"not numpy").unwrap();
    let e = load(dir.path(), 1).unwrap_err().to_string();
    assert!(e.contains("a_depth.npy") && e.contains("not a .npy array"), "{e}");
}
