//! Per-view pose changes for camera-refinement experiments: the noise stays in its range, has
//! zero mean and follows the seed; `perturb_poses` moves each view's rays exactly as the
//! correction of `nerf_rays::pose` does, so the opposite correction gives the rays back.

use nerf_data::{load_blender, pose_noise, LoadOptions, Split, ViewSelection};
use nerf_rays::pose::pose_correct_rays;
use nerf_rays::PixelConvention;

#[test]
fn noise_has_zero_mean_stays_in_range_and_follows_the_seed() {
    let n = pose_noise(40, 2.0, 0.1, 3);
    assert_eq!(n.len(), 40);
    for i in 0..6 {
        let mean = n.iter().map(|p| p[i] as f64).sum::<f64>() / 40.0;
        assert!(mean.abs() < 1e-6, "component {i}: mean {mean}");
        let bound = if i < 3 { 0.2 } else { 4f32.to_radians() }; // drawn within ±a, less a mean within ±a
        assert!(n.iter().all(|p| p[i].abs() <= bound));
        let spread = n.iter().map(|p| p[i]).fold(f32::MIN, f32::max) - n.iter().map(|p| p[i]).fold(f32::MAX, f32::min);
        assert!(spread > bound / 2.0, "component {i}: spread {spread}");
    }
    assert_eq!(n, pose_noise(40, 2.0, 0.1, 3));
    assert_ne!(n, pose_noise(40, 2.0, 0.1, 4));
    assert!(pose_noise(5, 0.0, 0.0, 1).iter().flatten().all(|&x| x == 0.0));
}

#[test]
#[should_panic(expected = "finite and ≥ 0")]
fn negative_noise_is_refused() {
    pose_noise(3, -1.0, 0.0, 0);
}

#[test]
fn perturbed_rays_are_the_corrected_rays_and_the_opposite_correction_undoes_them() {
    let scene = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/lego_100");
    let opts = LoadOptions { downscale: 4, views: ViewSelection::First(3), ..Default::default() };
    let before = load_blender(&scene, Split::Train, &opts).unwrap();
    let noise = pose_noise(3, 3.0, 0.2, 9);
    let mut after = before.clone();
    after.perturb_poses(&noise);
    let params: Vec<f32> = noise.iter().flatten().copied().collect();
    let undo: Vec<f32> = params.iter().map(|x| -x).collect();
    let conv = PixelConvention::Center;
    for v in 0..3 {
        let (mut o0, mut d0, mut o1, mut d1) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        before.cameras[v].rays_into(conv, &mut o0, &mut d0);
        after.cameras[v].rays_into(conv, &mut o1, &mut d1);
        let views = vec![v as u32; o0.len() / 3];
        let (mut oc, mut dc) = (o0.clone(), d0.clone());
        pose_correct_rays(&views, &params, &mut oc, &mut dc, &mut Vec::new());
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 2e-5);
        assert!(close(&oc, &o1) && close(&dc, &d1), "view {v}: perturbed rays = corrected rays");
        assert!(!close(&d0, &d1), "view {v}: the rays moved");
        pose_correct_rays(&views, &undo, &mut o1, &mut d1, &mut Vec::new());
        assert!(close(&o1, &o0) && close(&d1, &d0), "view {v}: the opposite correction undoes it");
    }
}
