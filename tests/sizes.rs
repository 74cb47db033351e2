//! Views of several sizes end to end ([`nerf::data::Dataset::view_size`]): the in-repo scene's
//! training views cropped, half to landscape 100×64 and half to portrait 64×100, each crop
//! written as its own photo with its own size and principal point (instant-ngp's per-frame `w`,
//! `h`, `cx`, `cy`), as a capture with portrait and landscape photos comes. Trained on, the crops
//! must teach the field what the whole views do, on the CPU and, where an adapter exists, on the
//! GPU; the same crops with the principal point left at their centre (the crop's offset lost:
//! rays through the wrong pixels) must not.

use std::path::Path;

use nerf::data::{load_blender, Dataset, LoadOptions, Split, ViewSelection};
use serde_json::json;

mod common;
use common::{gpu_matches_cpu, light_hash_config, load, sparse_psnr, train_on};

/// View `v`'s crop: `(x0, y0, w, h)` — landscape views keep the top 64 rows, portrait views the
/// right 64 columns (off-centre, so a lost offset moves every ray).
fn crop_of(v: usize) -> (u32, u32, u32, u32) {
    if v % 2 == 1 {
        (36, 0, 64, 100)
    } else {
        (0, 0, 100, 64)
    }
}

/// Writes the crops of `full`'s views into `dir` with `transforms_train.json`; `offset`: the
/// principal points moved with the crops (correct), else left at each crop's centre.
fn write_crops(full: &Dataset, dir: &Path, offset: bool) {
    std::fs::create_dir_all(dir.join("train")).unwrap();
    let frames: Vec<_> = (0..full.n_views())
        .map(|v| {
            let (x0, y0, w, h) = crop_of(v);
            let img = image::RgbaImage::from_fn(w, h, |x, y| {
                let p = ((y + y0) * full.width + x + x0) as usize;
                image::Rgba(std::array::from_fn(|c| (full.images[v].value(4 * p + c) * 255.0).round() as u8))
            });
            img.save(dir.join(format!("train/c_{v}.png"))).unwrap();
            let k = full.cameras[v].intrinsics;
            let (cx, cy) = if offset { (k.cx - x0 as f32, k.cy - y0 as f32) } else { (w as f32 / 2.0, h as f32 / 2.0) };
            json!({"file_path": format!("train/c_{v}.png"), "transform_matrix": full.cameras[v].c2w(),
                   "w": w, "h": h, "fl_x": k.fx, "fl_y": k.fy, "cx": cx, "cy": cy})
        })
        .collect();
    std::fs::write(dir.join("transforms_train.json"), json!({ "frames": frames }).to_string()).unwrap();
}


#[test]
fn portrait_and_landscape_crops_train_the_field_on_both_devices() {
    let full = load(Split::Train, ViewSelection::All);
    let test = load(Split::Test, ViewSelection::Every(10));
    let (good, bad) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    write_crops(&full, good.path(), true);
    write_crops(&full, bad.path(), false);
    let crops = load_blender(good.path(), Split::Train, &LoadOptions::default()).unwrap();
    let lost = load_blender(bad.path(), Split::Train, &LoadOptions::default()).unwrap();
    assert_eq!((crops.width, crops.height, crops.size_label()), (100, 100, "100x64 and 64x100".to_string()));
    // The crops hold exactly the whole views' pixels and rays there.
    let mut rays = nerf::data::RayBatch::default();
    let mut whole = nerf::data::RayBatch::default();
    crops.view_rays(1, nerf::data::Background::White, nerf::rays::PixelConvention::Center, &mut rays);
    full.view_rays(1, nerf::data::Background::White, nerf::rays::PixelConvention::Center, &mut whole);
    for r in (0..rays.len()).step_by(97) {
        let (col, row) = (r as u32 % 64 + 36, r as u32 / 64);
        let q = (row * 100 + col) as usize;
        assert_eq!(&rays.target[3 * r..3 * r + 3], &whole.target[3 * q..3 * q + 3], "pixel ({col}, {row})");
        for c in 0..3 {
            assert!((rays.dirs[3 * r + c] - whole.dirs[3 * q + c]).abs() < 1e-5, "pixel ({col}, {row})");
        }
    }

    let config = light_hash_config(300);
    let mut psnr = Vec::new();
    let mut trained = Vec::new();
    for (name, data) in [("whole views", &full), ("crops", &crops), ("crops, offset lost", &lost)] {
        let t0 = std::time::Instant::now();
        let t = train_on(&config, data, None);
        let p = sparse_psnr(&t, &test, 2);
        println!("cpu, {name}: {p:.2} dB on the test views ({:.1} s)", t0.elapsed().as_secs_f64());
        psnr.push(p);
        trained.push(t);
    }
    // Evaluation renders and scores each view at its own size: two crops, landscape and
    // portrait, the same score as their part of the whole views' renders.
    let two = |d: &Dataset| d.select_views(&[0, 1]);
    let out = tempfile::tempdir().unwrap();
    let report = nerf::train::evaluate(&trained[1], &two(&crops), Some(out.path()), |_, _| {}).unwrap();
    assert!(two(&crops).masks.is_some() && report.masked.is_none(), "views on a canvas keep all their own pixels: no masked scores");
    let whole = common::render_views(&trained[1], &two(&full));
    for (v, m) in report.views.iter().enumerate() {
        let (x0, y0, w, h) = crop_of(v);
        assert_eq!((m.width, m.height), (w, h));
        assert_eq!(image::image_dimensions(out.path().join(format!("c_{v}.png"))).unwrap(), (w, h));
        let part = |x: &[f32]| -> Vec<f32> { (y0..y0 + h).flat_map(|row| x[3 * (row * 100 + x0) as usize..3 * (row * 100 + x0 + w) as usize].to_vec()).collect() };
        let p = nerf::metrics::psnr(&part(&whole[v].rgb), &part(&whole[v].rays.target));
        assert!((m.psnr - p).abs() < 1e-3 && m.psnr > 10.0, "view {v}: {:.3} dB scored, {p:.3} dB over its part of the whole view", m.psnr);
    }
    assert!(psnr[1] > psnr[0] - 1.5, "crops {:.2} dB, whole views {:.2} dB", psnr[1], psnr[0]);
    assert!(psnr[1] > psnr[2] + 1.0, "crops {:.2} dB, with their offset lost {:.2} dB", psnr[1], psnr[2]);
    gpu_matches_cpu(80, &crops, &test, 2);
}
