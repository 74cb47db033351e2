//! The NDC warp against nerf-pytorch's `ndc_rays` formula (evaluated here in f64) and against the
//! geometry it must have: world points of a ray land on its NDC ray, in depth order; the segment
//! `[0, |d'|]` is the part of the ray inside the scene box; infinite depth is the vanishing point.

use glam::{DVec3, Mat3, Vec3};
use nerf_rays::{Camera, Intrinsics, Ndc};
use rand::{Rng, SeedableRng};

/// nerf-pytorch `ndc_rays(H, W, focal, near, rays_o, rays_d)` for one ray, in f64.
fn ndc_rays_f64(h: f64, w: f64, focal: f64, near: f64, o: DVec3, d: DVec3) -> (DVec3, DVec3) {
    let t = -(near + o.z) / d.z;
    let o = o + t * d;
    let o0 = -1.0 / (w / (2.0 * focal)) * o.x / o.z;
    let o1 = -1.0 / (h / (2.0 * focal)) * o.y / o.z;
    let o2 = 1.0 + 2.0 * near / o.z;
    let d0 = -1.0 / (w / (2.0 * focal)) * (d.x / d.z - o.x / o.z);
    let d1 = -1.0 / (h / (2.0 * focal)) * (d.y / d.z - o.y / o.z);
    let d2 = -2.0 * near / o.z;
    (DVec3::new(o0, o1, o2), DVec3::new(d0, d1, d2))
}

fn intrinsics() -> Intrinsics {
    Intrinsics { width: 504, height: 378, fx: 407.6, fy: 407.6, cx: 252.0, cy: 189.0 }
}

/// A forward-facing camera: near the origin, looking roughly down −z.
fn camera(r: &mut impl Rng) -> Camera {
    let axis = Vec3::new(r.gen_range(-1.0..1.0), r.gen_range(-1.0..1.0), r.gen_range(-1.0..1.0)).normalize();
    let rot = Mat3::from_axis_angle(axis, r.gen_range(-0.15..0.15));
    let pos = Vec3::new(r.gen_range(-0.3..0.3), r.gen_range(-0.3..0.3), r.gen_range(-0.2..0.2));
    let c2w: Vec<[f32; 4]> = (0..3).map(|i| [rot.x_axis[i], rot.y_axis[i], rot.z_axis[i], pos[i]]).collect();
    Camera::from_c2w(intrinsics(), &c2w).unwrap()
}

fn random_ray(r: &mut impl Rng, cam: &Camera) -> (Vec3, Vec3) {
    let k = cam.intrinsics;
    let d = cam.dir_at_unnormalized(r.gen_range(0.0..k.width as f32), r.gen_range(0.0..k.height as f32));
    (cam.position, d.normalize())
}

#[test]
fn matches_nerf_pytorch_ndc_rays() {
    let mut r = rand::rngs::StdRng::seed_from_u64(11);
    let k = intrinsics();
    let ndc = Ndc::new(&k, Ndc::NEAR_PLANE);
    for _ in 0..500 {
        let cam = camera(&mut r);
        let (o, d) = random_ray(&mut r, &cam);
        let (eo, ed) = ndc_rays_f64(k.height as f64, k.width as f64, k.fx as f64, 1.0, o.as_dvec3(), d.as_dvec3());
        let (go, gd) = ndc.ray_unnormalized(o, d).expect("a forward ray");
        assert!((go.as_dvec3() - eo).abs().max_element() < 1e-5, "origin {go} vs {eo}");
        assert!((gd.as_dvec3() - ed).abs().max_element() < 1e-5, "direction {gd} vs {ed}");
        assert!((go.z + 1.0).abs() < 1e-5, "the origin lies on the near plane z' = −1: {go}");
        let unit = ndc.ray(o, d).unwrap();
        assert!((unit.dir.length() - 1.0).abs() < 1e-6);
        assert!((unit.dir.as_dvec3() - ed.normalize()).length() < 1e-5);
    }
}

#[test]
fn world_points_land_on_the_ndc_ray_in_depth_order_and_infinity_at_the_vanishing_point() {
    let mut r = rand::rngs::StdRng::seed_from_u64(12);
    let ndc = Ndc::new(&intrinsics(), Ndc::NEAR_PLANE);
    for _ in 0..200 {
        let cam = camera(&mut r);
        let (o, d) = random_ray(&mut r, &cam);
        let (on, dn) = ndc.ray_unnormalized(o, d).unwrap();
        let t_near = -(1.0 + o.z) / d.z;
        let mut last = -1.0f32;
        for t in [t_near + 1e-3, t_near + 0.1, t_near + 1.0, t_near + 5.0, t_near + 50.0] {
            let p = ndc.point(o + t * d);
            // On the NDC ray: p = o' + s·d' with s ∈ [0, 1], increasing with depth.
            let s = (p - on).dot(dn) / dn.length_squared();
            assert!((on + s * dn - p).length() < 1e-4, "{p} is off the NDC ray");
            assert!((0.0..=1.0).contains(&s) && s > last, "s = {s} after {last}");
            last = s;
        }
        assert!((on + dn - ndc.vanishing_point(d)).length() < 1e-4);
    }
}

#[test]
fn the_scene_box_holds_exactly_the_ndc_segment_of_every_camera_ray() {
    let mut r = rand::rngs::StdRng::seed_from_u64(13);
    let ndc = Ndc::new(&intrinsics(), Ndc::NEAR_PLANE);
    let cams: Vec<Camera> = (0..6).map(|_| camera(&mut r)).collect();
    let aabb = ndc.scene_box(&cams, 0.02).expect("forward-facing cameras");
    assert_eq!((aabb.min[2], aabb.max[2]), (-1.0, 1.0));
    for cam in &cams {
        for _ in 0..200 {
            let (o, d) = random_ray(&mut r, cam);
            let (_, dn) = ndc.ray_unnormalized(o, d).unwrap();
            let ray = ndc.ray(o, d).unwrap();
            let (t0, t1) = aabb.intersect(ray.origin.to_array(), ray.dir.to_array()).expect("inside the box");
            assert!(t0.abs() < 1e-5 && (t1 - dn.length()).abs() < 1e-4 * dn.length(), "segment {t0}..{t1}, |d'| = {}", dn.length());
        }
    }
}

#[test]
fn rays_that_do_not_head_into_the_scene_are_refused_or_miss() {
    let ndc = Ndc::new(&intrinsics(), Ndc::NEAR_PLANE);
    assert!(ndc.ray(Vec3::ZERO, Vec3::new(0.0, 0.0, 1.0)).is_none());
    assert!(ndc.ray(Vec3::ZERO, Vec3::new(1.0, 0.0, 0.0)).is_none());
    assert!(ndc.ray(Vec3::new(f32::NAN, 0.0, 0.0), -Vec3::Z).is_none());
    let miss = ndc.ray_or_miss(Vec3::ZERO, Vec3::Z);
    let cams = [camera(&mut rand::rngs::StdRng::seed_from_u64(14))];
    let aabb = ndc.scene_box(&cams, 0.02).unwrap();
    assert!(aabb.intersect(miss.origin.to_array(), miss.dir.to_array()).is_none());
    // A camera that looks sideways is not forward-facing: no NDC box.
    let side = Camera::from_c2w(intrinsics(), &[[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0]]).unwrap();
    assert!(ndc.scene_box(&[side], 0.02).is_none());
    // The optical axis of the identity camera maps to the z' axis.
    let axis = ndc.ray(Vec3::ZERO, -Vec3::Z).unwrap();
    assert!((axis.origin - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6 && (axis.dir - Vec3::Z).length() < 1e-6);
}
