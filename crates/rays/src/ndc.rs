//! NeRF's normalised device coordinates (NDC) for forward-facing scenes.
//!
//! nerf-pytorch's `ndc_rays`: a forward-facing scene, in a world frame whose mean camera looks
//! down −z from near the origin, is warped by the projection of a pinhole camera with focal `f`
//! and image size `W × H` (the scene's intrinsics) and a near plane at `z = −n`:
//!
//! ```text
//! π(x, y, z) = ( −(2f/W)·x/z,  −(2f/H)·y/z,  1 + 2n/z )
//! ```
//!
//! The near plane maps to `z' = −1` and infinite depth to `z' = +1`; lines map to lines. A ray
//! `o + t·d` (`d_z < 0`) is first moved to the near plane, `o ← o + t_n·d` with
//! `t_n = −(n + o_z)/d_z`, and then becomes the NDC ray `o' + s·d'` with `o' = π(o)` and
//! `d' = π(o + ∞·d) − π(o)`:
//!
//! ```text
//! d' = ( −(2f/W)·(d_x/d_z − o_x/o_z),  −(2f/H)·(d_y/d_z − o_y/o_z),  −2n/o_z )
//! ```
//!
//! so that `s ∈ [0, 1]` covers near plane to infinity, linearly in disparity. This crate's
//! [`Ndc::ray`] returns the same ray with a unit direction (the project's convention: `t` is a
//! length), along which the segment is `[0, |d'|]`; that segment is exactly the part of the ray
//! inside the slab `−1 ≤ z' ≤ 1`. Intervals `δ` along it are nerf-pytorch's
//! `(s_{i+1} − s_i)·|d'|`.
//!
//! Two generalisations of nerf-pytorch's formula, both the identity for its cameras: separate
//! focal lengths `fx`, `fy` (its `focal` is both), and the principal point is assumed at the
//! image centre, as there.
//!
//! View directions: nerf-pytorch feeds the field the world direction of the ray; here the field
//! sees the unit NDC direction. At a given NDC point `p'`, the NDC direction of a world ray
//! through it is `normalize(π(∞·d) − p')`, a function of `p'` and the world direction `d` alone
//! (independent of the camera), and one-to-one in `d` over the half-space `d_z < 0`: the same
//! information, in other coordinates.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::{Aabb, Camera, Intrinsics, Ray};

/// The NDC warp of a forward-facing scene (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ndc {
    /// `2·fx / W` (nerf-pytorch: `1 / (W / (2·focal))`).
    pub scale_x: f32,
    /// `2·fy / H`.
    pub scale_y: f32,
    /// Distance `n` of the near plane `z = −n` (nerf-pytorch: 1).
    pub near: f32,
}

impl Ndc {
    /// nerf-pytorch's near plane (`ndc_rays(H, W, focal, 1., …)`).
    pub const NEAR_PLANE: f32 = 1.0;

    /// The warp of a scene whose images have intrinsics `k`, with the near plane at `z = −near`.
    /// The scales are resolution-independent (`f` scales with `W`), so any downscale of the
    /// scene's images gives the same warp.
    pub fn new(k: &Intrinsics, near: f32) -> Self {
        Self { scale_x: 2.0 * k.fx / k.width as f32, scale_y: 2.0 * k.fy / k.height as f32, near }
    }

    /// `π(p)` for a point in front of the camera plane (`p.z < 0`).
    pub fn point(&self, p: Vec3) -> Vec3 {
        Vec3::new(-self.scale_x * p.x / p.z, -self.scale_y * p.y / p.z, 1.0 + 2.0 * self.near / p.z)
    }

    /// The image at infinity of world direction `d` (`d.z < 0`): `π(o + ∞·d)` for any `o`.
    pub fn vanishing_point(&self, d: Vec3) -> Vec3 {
        Vec3::new(-self.scale_x * d.x / d.z, -self.scale_y * d.y / d.z, 1.0)
    }

    /// nerf-pytorch's `ndc_rays` for one ray, literally: the NDC origin (on `z' = −1`) and the
    /// unnormalised NDC direction (`s ∈ [0, 1]` reaches `z' = 1`). `None` unless the ray heads
    /// into the scene (`d.z < 0`, finite input) and its origin, moved to the near plane, stays
    /// finite.
    pub fn ray_unnormalized(&self, origin: Vec3, dir: Vec3) -> Option<(Vec3, Vec3)> {
        if !origin.is_finite() || !dir.is_finite() || dir.z >= 0.0 {
            return None;
        }
        let t = -(self.near + origin.z) / dir.z;
        let o = origin + t * dir;
        let (sx, sy, n) = (self.scale_x, self.scale_y, self.near);
        let o_ndc = Vec3::new(-sx * o.x / o.z, -sy * o.y / o.z, 1.0 + 2.0 * n / o.z);
        let d_ndc = Vec3::new(
            -sx * (dir.x / dir.z - o.x / o.z),
            -sy * (dir.y / dir.z - o.y / o.z),
            -2.0 * n / o.z,
        );
        (o_ndc.is_finite() && d_ndc.is_finite()).then_some((o_ndc, d_ndc))
    }

    /// The NDC ray with a unit direction: the ray the samplers march, between `t = 0` (the near
    /// plane) and `t = |d'|` (infinite depth, `z' = 1`). `None` as [`Ndc::ray_unnormalized`].
    pub fn ray(&self, origin: Vec3, dir: Vec3) -> Option<Ray> {
        let (o, d) = self.ray_unnormalized(origin, dir)?;
        Some(Ray { origin: o, dir: d.normalize() })
    }

    /// [`Ndc::ray`], or [`Ndc::MISS`] for a ray that cannot be warped (one that does not head
    /// into the scene): rendering gives it the background.
    pub fn ray_or_miss(&self, origin: Vec3, dir: Vec3) -> Ray {
        self.ray(origin, dir).unwrap_or(Self::MISS)
    }

    /// A ray that misses every NDC scene box (it starts beyond infinite depth, `z' = 2`, and
    /// points away).
    pub const MISS: Ray = Ray { origin: Vec3::new(0.0, 0.0, 2.0), dir: Vec3::Z };

    /// The NDC box that holds the frusta of `cameras` from the near plane to infinite depth:
    /// `z' ∈ [−1, 1]` exactly (so a ray's segment inside the box is its whole NDC segment), `x'`
    /// and `y'` the hull of the image corners' rays, padded by `pad` of their extent. `None`
    /// when a camera has a corner ray that does not head into the scene (`d.z ≥ 0`: not a
    /// forward-facing capture) or no camera is given.
    pub fn scene_box(&self, cameras: &[Camera], pad: f32) -> Option<Aabb> {
        if cameras.is_empty() {
            return None;
        }
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for cam in cameras {
            let k = &cam.intrinsics;
            for (u, v) in [(0.0, 0.0), (k.width as f32, 0.0), (0.0, k.height as f32), (k.width as f32, k.height as f32)] {
                let (o, d) = self.ray_unnormalized(cam.position, cam.dir_at_unnormalized(u, v))?;
                for p in [o, o + d] {
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
            }
        }
        let e = hi - lo;
        Some(Aabb {
            min: [lo.x - pad * e.x, lo.y - pad * e.y, -1.0],
            max: [hi.x + pad * e.x, hi.y + pad * e.y, 1.0],
        })
    }
}
