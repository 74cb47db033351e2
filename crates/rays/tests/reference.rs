//! Ray generation against nerf-pytorch `get_rays_np` (shared/reference/rays.json) and AABB
//! intersection checks.

use glam::Vec3;
use nerf_rays::{Aabb, Camera, Intrinsics, PixelConvention};
use serde_json::Value;

fn load(name: &str) -> Option<Value> {
    let p = nerf_core::shared::reference(env!("CARGO_MANIFEST_DIR"), name)?;
    Some(serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap())
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

fn reference_camera(j: &Value) -> Camera {
    let inp = &j["inputs"];
    let (w, h) = (
        inp["W"].as_u64().unwrap() as u32,
        inp["H"].as_u64().unwrap() as u32,
    );
    let k = Intrinsics::from_fov_x(w, h, f(&inp["camera_angle_x"]));
    assert!(
        (k.fx as f64 - f(&inp["focal"])).abs() < 1e-5,
        "focal {} vs {}",
        k.fx,
        inp["focal"]
    );
    let c2w: Vec<[f32; 4]> = inp["c2w"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| std::array::from_fn(|c| f(&r[c]) as f32))
        .collect();
    assert_eq!(c2w.len(), 3);
    Camera::from_c2w(k, &c2w).unwrap()
}

#[test]
fn matches_nerf_pytorch_get_rays() {
    let Some(j) = load("rays.json") else { return };
    let cam = reference_camera(&j);
    let (w, h) = (cam.intrinsics.width, cam.intrinsics.height);
    let out = &j["outputs"];
    let mut max_err = 0.0f64;
    for row in 0..h {
        for col in 0..w {
            let d_ref = &out["rays_d"][row as usize][col as usize];
            let o_ref = &out["rays_o"][row as usize][col as usize];
            let d = cam.pixel_dir_unnormalized(col, row, PixelConvention::Integer);
            let r = cam.ray(col, row, PixelConvention::Integer);
            for a in 0..3 {
                let e = (d[a] as f64 - f(&d_ref[a])).abs();
                max_err = max_err.max(e);
                assert!(
                    e < 1e-6,
                    "pixel ({col},{row}) axis {a}: {} vs {}",
                    d[a],
                    d_ref[a]
                );
                assert!((r.origin[a] as f64 - f(&o_ref[a])).abs() < 1e-6);
            }
            // The unit ray is the normalised reference direction.
            let dref = Vec3::new(
                f(&d_ref[0]) as f32,
                f(&d_ref[1]) as f32,
                f(&d_ref[2]) as f32,
            );
            assert!((r.dir - dref.normalize()).length() < 1e-6);
            assert!((r.dir.length() - 1.0).abs() < 1e-6);
        }
    }
    eprintln!("max |d - d_ref| = {max_err:e}");
}

#[test]
fn centre_convention_is_half_a_pixel_off() {
    let Some(j) = load("rays.json") else { return };
    let cam = reference_camera(&j);
    let k = cam.intrinsics;
    // Moving half a pixel in u changes the camera-space direction by 0.5/fx along camera +x, and
    // half a pixel in v by 0.5/fy along camera −y.
    let expected = cam.rotation * Vec3::new(0.5 / k.fx, -0.5 / k.fy, 0.0);
    for row in 0..k.height {
        for col in 0..k.width {
            let di = cam.pixel_dir_unnormalized(col, row, PixelConvention::Integer);
            let dc = cam.pixel_dir_unnormalized(col, row, PixelConvention::Center);
            assert!(
                ((dc - di) - expected).length() < 1e-6,
                "{:?} vs {:?}",
                dc - di,
                expected
            );
            // And the centre ray is the integer ray evaluated half a pixel further.
            let r = cam.ray_at(col as f32 + 0.5, row as f32 + 0.5);
            assert!((r.dir - cam.ray(col, row, PixelConvention::Center).dir).length() < 1e-7);
            assert!((dc - di).length() > 1e-3);
        }
    }
}

#[test]
fn aabb_hit_miss_inside() {
    let b = Aabb::cube(1.0);
    // Hit from outside along +x: enters at 2, exits at 4.
    let (t0, t1) = b.intersect([-3.0, 0.2, -0.3], [1.0, 0.0, 0.0]).unwrap();
    assert!(
        (t0 - 2.0).abs() < 1e-6 && (t1 - 4.0).abs() < 1e-6,
        "{t0} {t1}"
    );
    // Non-unit direction: t scales inversely.
    let (t0, t1) = b.intersect([-3.0, 0.0, 0.0], [2.0, 0.0, 0.0]).unwrap();
    assert!((t0 - 1.0).abs() < 1e-6 && (t1 - 2.0).abs() < 1e-6);
    // Diagonal hit through a corner region.
    let d = Vec3::new(1.0, 1.0, 1.0).normalize();
    let (t0, t1) = b.intersect([-2.0, -2.0, -2.0], d.to_array()).unwrap();
    let s3 = 3f32.sqrt();
    assert!(
        (t0 - s3).abs() < 1e-5 && (t1 - 3.0 * s3).abs() < 1e-5,
        "{t0} {t1}"
    );
    // Miss: passes beside the box, parallel to a slab outside it.
    assert!(b.intersect([-3.0, 1.5, 0.0], [1.0, 0.0, 0.0]).is_none());
    // Miss: oblique ray that passes the corner.
    assert!(b
        .intersect(
            [-3.0, 0.0, 0.0],
            Vec3::new(1.0, 1.2, 0.0).normalize().to_array()
        )
        .is_none());
    // Miss: box behind the origin.
    assert!(b.intersect([3.0, 0.0, 0.0], [1.0, 0.0, 0.0]).is_none());
    // Origin inside: t_enter clamps to 0, exit at the far face.
    let (t0, t1) = b.intersect([0.5, 0.0, 0.0], [-1.0, 0.0, 0.0]).unwrap();
    assert_eq!(t0, 0.0);
    assert!((t1 - 1.5).abs() < 1e-6);
    // NaN input never hits.
    assert!(b.intersect([f32::NAN, 0.0, 0.0], [1.0, 0.0, 0.0]).is_none());
    // Random rays: the interval endpoints lie on the box surface and its midpoint inside.
    let mut s = 12345u64;
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    };
    let bb = Aabb {
        min: [-0.5, -1.0, 0.0],
        max: [1.0, 0.5, 2.0],
    };
    let mut hits = 0;
    for _ in 0..2000 {
        let o = [3.0 * next(), 3.0 * next(), 3.0 * next()];
        let d = Vec3::new(next(), next(), next()).normalize().to_array();
        if let Some((t0, t1)) = bb.intersect(o, d) {
            hits += 1;
            let p = |t: f32| std::array::from_fn::<f32, 3, _>(|a| o[a] + t * d[a]);
            let mid = p(0.5 * (t0 + t1));
            assert!(bb.contains(mid), "{mid:?}");
            let grow = Aabb {
                min: bb.min.map(|v| v - 1e-4),
                max: bb.max.map(|v| v + 1e-4),
            };
            assert!(grow.contains(p(t0)) && grow.contains(p(t1)));
            // Just beyond the exit is outside.
            assert!(!bb.contains(p(t1 + 1e-3)));
        } else {
            // A miss: no point of a dense march along the ray is inside.
            for i in 0..400 {
                assert!(!bb.contains(std::array::from_fn(|a| o[a] + 0.02 * i as f32 * d[a])));
            }
        }
    }
    assert!(hits > 100 && hits < 1900, "{hits}");
}
