//! nerfstudio's downscaled copies (`images_<k>/`, `masks_<k>/`, `depths_<k>/` beside `images/`, as
//! `ns-process-data` writes them): `--downscale k` reads them in place of box-averaging the
//! originals, with the intrinsics scaled, where every selected frame has its copies.

use std::path::Path;

use nerf_data::{load_scene, LoadOptions, Split};
use serde_json::json;

const ORIGINAL: [u8; 4] = [200, 40, 40, 255];
const COPY: [u8; 4] = [40, 200, 40, 255];

/// A nerfstudio capture of three 8×6 photos (`images/f<i>.png`, colour `ORIGINAL`) with masks
/// that keep every pixel, and their halves in `images_2/` (colour `COPY`) and `masks_2/` (which
/// drop the top-left pixel).
fn capture(root: &Path) {
    for dir in ["images", "images_2", "masks", "masks_2"] {
        std::fs::create_dir_all(root.join(dir)).unwrap();
    }
    let frames: Vec<_> = (0..3)
        .map(|i| {
            image::RgbaImage::from_pixel(8, 6, image::Rgba(ORIGINAL)).save(root.join(format!("images/f{i}.png"))).unwrap();
            image::RgbaImage::from_pixel(4, 3, image::Rgba(COPY)).save(root.join(format!("images_2/f{i}.png"))).unwrap();
            image::GrayImage::from_pixel(8, 6, image::Luma([255])).save(root.join(format!("masks/m{i}.png"))).unwrap();
            image::GrayImage::from_fn(4, 3, |x, y| image::Luma([if (x, y) == (0, 0) { 0 } else { 255 }])).save(root.join(format!("masks_2/m{i}.png"))).unwrap();
            let a = 0.5 * i as f64;
            json!({"file_path": format!("images/f{i}.png"), "mask_path": format!("masks/m{i}.png"),
                   "transform_matrix": [[a.cos(), 0, a.sin(), 3.0 * a.sin()], [0, 1, 0, 0], [-a.sin(), 0, a.cos(), 3.0 * a.cos()], [0, 0, 0, 1]]})
        })
        .collect();
    let t = json!({"camera_model": "OPENCV", "w": 8, "h": 6, "fl_x": 10.0, "fl_y": 11.0, "cx": 4.5, "cy": 2.5,
                   "train_filenames": ["images/f0.png", "images/f1.png", "images/f2.png"], "test_filenames": ["images/f1.png"], "frames": frames});
    std::fs::write(root.join("transforms.json"), t.to_string()).unwrap();
}

fn load(root: &Path, k: u32) -> nerf_data::Dataset {
    load_scene(root, Split::Train, &LoadOptions { downscale: k, ..Default::default() }).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn downscaled_copies_are_read_in_place_of_the_originals() {
    let dir = tempfile::tempdir().unwrap();
    capture(dir.path());
    let colour = |ds: &nerf_data::Dataset| -> [u8; 4] { std::array::from_fn(|c| (ds.images[0].value(c) * 255.0).round() as u8) };
    // Full resolution: the originals.
    let full = load(dir.path(), 1);
    assert_eq!((full.width, full.height, colour(&full)), (8, 6, ORIGINAL));
    assert!(full.file_paths[0].ends_with("images/f0.png"));
    // Halved: the copies, the intrinsics halved (as box-averaging the originals halves them).
    let half = load(dir.path(), 2);
    assert_eq!((half.width, half.height, colour(&half)), (4, 3, COPY));
    assert!(half.file_paths[2].ends_with("images_2/f2.png"));
    let k = half.cameras[0].intrinsics;
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (5.0, 5.5, 2.25, 1.25));
    assert_eq!(k, full.cameras[0].intrinsics.downscaled(2));
    let m = half.masks.as_ref().expect("the copies' masks");
    assert!((0..3).all(|v| !m.is_kept(v, 0) && m.is_kept(v, 1)) && m.total() == 3 * 11);
    // The cameras where they are either way.
    for (a, b) in half.cameras.iter().zip(&full.cameras) {
        assert_eq!((a.rotation, a.position), (b.rotation, b.position));
    }
    // Cameras only: the copies' sizes.
    let cams = load_scene(dir.path(), Split::Train, &LoadOptions { downscale: 2, cameras_only: true, ..Default::default() }).unwrap();
    assert_eq!((cams.width, cams.height, cams.cameras[1].intrinsics), (4, 3, half.cameras[1].intrinsics));

    // One copy missing: every frame from its original, box-averaged (and its mask keeps all).
    std::fs::remove_file(dir.path().join("masks_2/m1.png")).unwrap();
    let boxed = load(dir.path(), 2);
    assert_eq!((boxed.width, boxed.height, colour(&boxed)), (4, 3, ORIGINAL));
    assert_eq!(boxed.cameras[0].intrinsics, k);
    assert!(boxed.file_paths[0].ends_with("images/f0.png"));
    assert_eq!(boxed.masks.as_ref().map_or(12 * 3, |m| m.total()), 12 * 3);
}

/// A photo with an instant-ngp dynamic mask beside it (no `mask_path`): the mask has no copy, so
/// every frame is read from its original and the mask applies.
#[test]
fn a_dynamic_mask_keeps_the_originals() {
    let dir = tempfile::tempdir().unwrap();
    capture(dir.path());
    let text = std::fs::read_to_string(dir.path().join("transforms.json")).unwrap();
    let mut t: serde_json::Value = serde_json::from_str(&text).unwrap();
    for f in t["frames"].as_array_mut().unwrap() {
        f.as_object_mut().unwrap().remove("mask_path");
    }
    std::fs::write(dir.path().join("transforms.json"), t.to_string()).unwrap();
    // Without a dynamic mask: the copies.
    assert!(load(dir.path(), 2).file_paths[0].ends_with("images_2/f0.png"));
    // Its non-zero pixels drop: the right half of f0.
    image::GrayImage::from_fn(8, 6, |x, _| image::Luma([if x >= 4 { 255 } else { 0 }])).save(dir.path().join("images/dynamic_mask_f0.png")).unwrap();
    let ds = load(dir.path(), 2);
    assert!(ds.file_paths[0].ends_with("images/f0.png"));
    let m = ds.masks.as_ref().expect("the dynamic mask");
    assert_eq!((m.kept_in(0), m.kept_in(1)), (6, 12));
}
