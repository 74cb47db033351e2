//! Views of different sizes in one scene (portrait and landscape photos, a capture with several
//! cameras): each view keeps its own size and camera, all are held on one canvas of the largest
//! width and height, and the canvas past a smaller view is never trained on or scored.

use std::collections::HashSet;
use std::path::Path;

use nerf_data::{load_blender, write_blender, Background, DataError, Dataset, LoadOptions, RayBatch, Split};
use nerf_rays::PixelConvention;
use rand::{Rng, SeedableRng};
use serde_json::{json, Value};

/// The frames' sizes: landscape, portrait, landscape, portrait.
const SIZES: [(u32, u32); 4] = [(8, 6), (6, 8), (8, 6), (6, 8)];

/// A camera 4 units from the origin looking at it, turned by `a` about the vertical axis.
fn pose(a: f64) -> Value {
    let (s, c) = a.sin_cos();
    json!([[c, 0.0, s, 4.0 * s], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 4.0 * c], [0.0, 0.0, 0.0, 1.0]])
}

/// Random RGBA8 pixels of a `w×h` image, as loaded (u8/255), and the image.
fn random_png(w: u32, h: u32, rng: &mut rand::rngs::StdRng) -> (Vec<f32>, image::RgbaImage) {
    let img = image::RgbaImage::from_fn(w, h, |_, _| image::Rgba([rng.gen(), rng.gen(), rng.gen(), [0, 255, rng.gen()][rng.gen_range(0..3)]]));
    (img.as_raw().iter().map(|&v| v as f32 / 255.0).collect(), img)
}

/// A scene of `SIZES` frames with their own `w`, `h`, `fl_x`, `cx`, `cy` (instant-ngp's per-frame
/// keys) in `transforms_train.json`, and frame 1 alone in `transforms_test.json`; `extra` is
/// merged into every frame. Returns each frame's pixels.
fn scene(root: &Path, seed: u64, extra: impl Fn(usize) -> Value) -> Vec<Vec<f32>> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    std::fs::create_dir_all(root.join("images")).unwrap();
    let mut pixels = Vec::new();
    let frames: Vec<Value> = SIZES
        .iter()
        .enumerate()
        .map(|(i, &(w, h))| {
            let (px, img) = random_png(w, h, &mut rng);
            img.save(root.join(format!("images/f{i}.png"))).unwrap();
            pixels.push(px);
            let mut f = json!({
                "file_path": format!("images/f{i}.png"), "transform_matrix": pose(0.4 * i as f64),
                "w": w, "h": h, "fl_x": 7.0 + i as f64, "cx": w as f64 / 2.0 + 0.25, "cy": h as f64 / 2.0 - 0.5,
            });
            if let Value::Object(x) = extra(i) {
                f.as_object_mut().unwrap().extend(x);
            }
            f
        })
        .collect();
    let write = |name: &str, frames: &[Value]| std::fs::write(root.join(name), serde_json::to_string_pretty(&json!({ "frames": frames })).unwrap()).unwrap();
    write("transforms_train.json", &frames);
    write("transforms_test.json", &frames[1..2]);
    pixels
}

/// The canvas pixel `(col, row)` of view `v`.
fn canvas_pixel(ds: &Dataset, v: usize, col: u32, row: u32) -> [f32; 4] {
    let p = (row * ds.width + col) as usize;
    ds.images[v].rgba(p)
}

#[test]
fn views_of_several_sizes_sit_on_one_canvas_with_the_rest_masked_out() {
    let dir = tempfile::tempdir().unwrap();
    let pixels = scene(dir.path(), 1, |_| json!({}));
    let ds = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!((ds.width, ds.height), (8, 8), "the largest width and height");
    assert_eq!(ds.size_label(), "8x6 and 6x8");
    assert_eq!(ds.n_view_pixels(), 4 * 48);
    for (v, &(w, h)) in SIZES.iter().enumerate() {
        assert_eq!(ds.view_size(v), (w, h));
        let k = ds.cameras[v].intrinsics;
        assert_eq!((k.fx, k.cx, k.cy), (7.0 + v as f32, w as f32 / 2.0 + 0.25, h as f32 / 2.0 - 0.5), "view {v}: its own intrinsics");
        assert_eq!(ds.images[v].len(), 4 * 64);
        for row in 0..8 {
            for col in 0..8 {
                let px = canvas_pixel(&ds, v, col, row);
                if col < w && row < h {
                    let i = 4 * (row * w + col) as usize;
                    assert_eq!(px, &pixels[v][i..i + 4], "view {v} ({col}, {row})");
                } else {
                    assert_eq!(px, [0.0; 4], "view {v} ({col}, {row}): past the view");
                }
                assert_eq!(ds.masks.as_ref().unwrap().is_kept(v, row * 8 + col), col < w && row < h, "view {v} ({col}, {row})");
            }
        }
        assert_eq!(ds.view_crop(v, 4, &ds.images[v].to_f32()).as_ref(), &pixels[v][..], "view {v}: cropped back");
    }
    // Views of one size share one list of kept pixels; a view that fills the canvas would have none.
    let m = ds.masks.as_ref().unwrap();
    assert!(std::ptr::eq(m.view(0).unwrap(), m.view(2).unwrap()) && std::ptr::eq(m.view(1).unwrap(), m.view(3).unwrap()));
    assert_eq!(m.total(), 4 * 48);

    // A view's rays and colours are its own size's; the pixel ids index the canvas.
    let mut batch = RayBatch::default();
    ds.view_rays(1, Background::White, PixelConvention::Center, &mut batch);
    assert_eq!(batch.len(), 48);
    let rgb = ds.view_rgb(1, Background::White);
    assert_eq!(rgb.len(), 3 * 48);
    for row in 0..8u32 {
        for col in 0..6u32 {
            let r = (row * 6 + col) as usize;
            let ray = ds.cameras[1].ray_at(col as f32 + 0.5, row as f32 + 0.5);
            assert_eq!(&batch.origins[3 * r..3 * r + 3], &ray.origin.to_array());
            assert_eq!(&batch.dirs[3 * r..3 * r + 3], &ray.dir.to_array());
            assert_eq!(batch.pixel_ids[r], row * 8 + col);
            let p = &pixels[1][4 * r..4 * r + 4];
            let want: Vec<f32> = (0..3).map(|c| p[c] * p[3] + (1.0 - p[3])).collect();
            assert_eq!(&batch.target[3 * r..3 * r + 3], &want[..], "pixel ({col}, {row})");
            assert_eq!(&rgb[3 * r..3 * r + 3], &want[..]);
        }
    }

    // Training rays: only the views' own pixels, every one of them (4000 draws of 192), each
    // with its camera's ray and its photo's colour.
    let mut rng = nerf_core::rng(7, 0);
    ds.sample_rays(4000, Background::Black, PixelConvention::Center, false, &mut rng, &mut batch);
    let mut drawn = HashSet::new();
    for r in 0..batch.len() {
        let (v, p) = (batch.view_ids[r] as usize, batch.pixel_ids[r]);
        let (col, row) = (p % 8, p / 8);
        let (w, h) = SIZES[v];
        assert!(col < w && row < h, "view {v}: pixel ({col}, {row}) past its {w}x{h}");
        let ray = ds.cameras[v].ray_at(col as f32 + 0.5, row as f32 + 0.5);
        assert_eq!(&batch.dirs[3 * r..3 * r + 3], &ray.dir.to_array());
        let px = &pixels[v][4 * (row * w + col) as usize..][..4];
        let want: Vec<f32> = (0..3).map(|c| px[c] * px[3]).collect();
        assert_eq!(&batch.target[3 * r..3 * r + 3], &want[..]);
        drawn.insert((v, p));
    }
    assert_eq!(drawn.len(), 4 * 48, "every pixel of every view drawn");

    // A selection of views keeps their cameras, pixels, masks and the canvas.
    let two = ds.select_views(&[3, 0]);
    assert_eq!((two.n_views(), two.width, two.height, two.view_size(0), two.view_size(1)), (2, 8, 8, (6, 8), (8, 6)));
    assert_eq!((&two.images[0], &two.file_paths[1]), (&ds.images[3], &ds.file_paths[0]));
    assert_eq!(two.masks, Some(ds.masks.as_ref().unwrap().select(&[3, 0])));
    assert_eq!(two.cameras[0].position, ds.cameras[3].position);

    // Downscaled: each view by its own size, then the canvas of the largest.
    let (w8, h8) = (16, 12);
    std::fs::create_dir_all(dir.path().join("big")).unwrap();
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let frames: Vec<Value> = [(w8, h8), (h8, w8)]
        .iter()
        .enumerate()
        .map(|(i, &(w, h))| {
            random_png(w, h, &mut rng).1.save(dir.path().join(format!("big/b{i}.png"))).unwrap();
            json!({"file_path": format!("b{i}.png"), "transform_matrix": pose(i as f64), "w": w, "h": h, "fl_x": 9.0})
        })
        .collect();
    std::fs::write(dir.path().join("big/transforms_train.json"), json!({ "frames": frames }).to_string()).unwrap();
    let small = load_blender(&dir.path().join("big"), Split::Train, &LoadOptions { downscale: 2, ..Default::default() }).unwrap();
    assert_eq!((small.width, small.height, small.view_size(0), small.view_size(1)), (8, 8, (8, 6), (6, 8)));
    assert_eq!(small.cameras[1].intrinsics.fx, 4.5);
    assert_eq!(small.masks.as_ref().unwrap().total(), 2 * 48);
}

#[test]
fn a_cameras_only_load_has_the_same_canvas_cameras_and_masks() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), 2, |_| json!({}));
    let full = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    let cams = load_blender(dir.path(), Split::Train, &LoadOptions { cameras_only: true, ..Default::default() }).unwrap();
    assert_eq!((cams.width, cams.height), (full.width, full.height));
    for (a, b) in cams.cameras.iter().zip(&full.cameras) {
        assert_eq!((a.intrinsics, a.rotation, a.position), (b.intrinsics, b.rotation, b.position));
    }
    assert_eq!(cams.masks, full.masks, "rays cast from the training cameras stay in their views");
    let (mut a, mut b) = (RayBatch::default(), RayBatch::default());
    full.sample_camera_rays(500, Background::White, PixelConvention::Center, true, &mut nerf_core::rng(1, 0), &mut a);
    cams.sample_camera_rays(500, Background::White, PixelConvention::Center, true, &mut nerf_core::rng(1, 0), &mut b);
    assert_eq!((a.dirs, a.pixel_ids), (b.dirs, b.pixel_ids));
}

#[test]
fn masks_and_depth_maps_of_views_of_several_sizes_are_their_own_views_on_the_canvas() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    for (i, &(w, h)) in SIZES.iter().enumerate() {
        image::GrayImage::from_fn(w, h, |_, _| image::Luma([if rng.gen_bool(0.7) { 255 } else { 0 }])).save(dir.path().join(format!("m{i}.png"))).unwrap();
        let z = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |_, _| image::Luma([if rng.gen_bool(0.2) { 0 } else { rng.gen_range(2000..6000) }]));
        z.save(dir.path().join(format!("d{i}.png"))).unwrap();
    }
    scene(dir.path(), 4, |i| json!({"mask_path": format!("m{i}.png"), "depth_file_path": format!("d{i}.png")}));
    let ds = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    // Frame 1 alone (its own size, no canvas) is what the scene holds of it.
    let one = load_blender(dir.path(), Split::Test, &LoadOptions::default()).unwrap();
    assert_eq!((one.width, one.height), (6, 8));
    assert_eq!(ds.depths_mismatch(), None);
    let (m, m1) = (ds.masks.as_ref().unwrap(), one.masks.as_ref().unwrap());
    let depths = ds.depths.as_ref().unwrap();
    assert_eq!(ds.view_crop(1, 1, &m.view_bytes(1)).as_ref(), &m1.view_bytes(0)[..]);
    assert_eq!(ds.view_crop(1, 1, &depths[1]).as_ref(), &one.depths.as_ref().unwrap()[0][..]);
    assert!(depths[1].iter().filter(|&&t| t > 0.0).count() > 20);
    for v in 0..4 {
        let (w, h) = SIZES[v];
        for p in 0..64u32 {
            if p % 8 >= w || p / 8 >= h {
                assert!(!m.is_kept(v, p) && depths[v][p as usize] == 0.0, "view {v}: canvas pixel {p} past the view");
            }
        }
    }
    // A mask of another size than its own frame is refused, naming it.
    image::GrayImage::new(8, 6).save(dir.path().join("m1.png")).unwrap();
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::BadMask { frame: 1, .. }) && e.to_string().contains("m1.png") && e.to_string().contains("6x8"), "{e}");
}

/// A pincushion lens (`k1 > 0`), resampled to pinhole cameras (`undistort`): its pinhole images
/// reach past the photos at their corners, and those pixels, found at each view's own size, stay
/// dropped on the canvas. Kept as taken, only the canvas past each view is masked.
#[test]
fn a_lens_mask_of_views_of_several_sizes_is_each_sizes_own() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), 8, |_| json!({"k1": 1.0}));
    let native = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!(native.masks.as_ref().unwrap().total(), native.n_view_pixels(), "every pixel of every view");
    let ds = load_blender(dir.path(), Split::Train, &LoadOptions { undistort: true, ..LoadOptions::default() }).unwrap();
    let m = ds.masks.as_ref().unwrap();
    for v in 0..4 {
        let (w, h) = SIZES[v];
        let kept_inside = (0..64u32).filter(|&p| m.is_kept(v, p)).inspect(|&p| assert!(p % 8 < w && p / 8 < h, "view {v}: canvas pixel {p} past the view kept")).count();
        assert!(kept_inside < (w * h) as usize && kept_inside > (w * h) as usize / 2, "view {v}: {kept_inside} of {} kept", w * h);
    }
}

#[test]
fn sizes_must_be_stated_to_differ() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), 5, |_| json!({}));
    // Frame 2 without its own `w`, `h`: it must have the first image's size.
    let text = std::fs::read_to_string(dir.path().join("transforms_train.json")).unwrap();
    let mut v: Value = serde_json::from_str(&text).unwrap();
    v["frames"][1].as_object_mut().unwrap().retain(|k, _| k != "w" && k != "h");
    std::fs::write(dir.path().join("transforms_train.json"), v.to_string()).unwrap();
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(matches!(e, DataError::SizeMismatch { width: 6, height: 8, first_width: 8, first_height: 6, .. }), "{e}");
    assert!(e.to_string().contains("f1.png") && e.to_string().contains("f0.png"), "{e}");
    // A stated size that is not the image's.
    v["frames"][1]["w"] = json!(8);
    v["frames"][1]["h"] = json!(6);
    std::fs::write(dir.path().join("transforms_train.json"), v.to_string()).unwrap();
    let e = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap_err();
    assert!(e.to_string().contains("8x6") && e.to_string().contains("f1.png"), "{e}");
}

#[test]
fn writing_a_scene_of_several_sizes_keeps_each_view_at_its_own() {
    let dir = tempfile::tempdir().unwrap();
    scene(dir.path(), 6, |_| json!({}));
    let ds = load_blender(dir.path(), Split::Train, &LoadOptions::default()).unwrap();
    let out = tempfile::tempdir().unwrap();
    write_blender(&ds, out.path(), None).unwrap();
    let json: Value = serde_json::from_str(&std::fs::read_to_string(out.path().join("transforms_train.json")).unwrap()).unwrap();
    assert_eq!((json["w"].as_u64(), json["h"].as_u64()), (Some(8), Some(6)));
    assert_eq!((json["frames"][1]["w"].as_u64(), json["frames"][1]["h"].as_u64()), (Some(6), Some(8)));
    assert!(json["frames"][0].get("w").is_none() && json["frames"][0].get("mask_path").is_none(), "the canvas's padding is not a mask");
    assert_eq!(image::image_dimensions(out.path().join("train/r_1.png")).unwrap(), (6, 8));
    let back = load_blender(out.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!((back.width, back.height, back.images.clone(), back.masks.clone()), (ds.width, ds.height, ds.images.clone(), ds.masks.clone()));
    for (a, b) in back.cameras.iter().zip(&ds.cameras) {
        assert_eq!(a.intrinsics, b.intrinsics);
        assert!((a.position - b.position).length() < 1e-6);
    }
}
