//! A render crop box: instant-ngp's `render_aabb` and nerfstudio's viewer crop (an oriented box,
//! `crop` in its `camera_path.json`). Rays are clipped to it before sampling, so a render shows
//! only what lies inside; the samplers' segments and the marcher's `[t0, t1)` are intersected
//! with [`CropBox::slab`]. GPU twin: `crop_slab` in `shaders/common.wgsl`.

use serde::{Deserialize, Serialize};

/// An oriented box: centre, the box's axes as rows of a rotation (world → box frame), and half
/// its size along each of them. A point `p` is inside when `|axes[i]·(p − centre)| ≤ half[i]`
/// for every axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CropBox {
    /// The box's centre (scene frame).
    pub center: [f32; 3],
    /// Rows: the box's x, y and z axes in the scene frame (orthonormal).
    pub axes: [[f32; 3]; 3],
    /// Half the box's size along each axis.
    pub half: [f32; 3],
}

impl CropBox {
    /// The axis-aligned box `[lo, hi]`. Errors unless every corner is finite with `hi > lo`.
    pub fn aabb(lo: [f32; 3], hi: [f32; 3]) -> Result<Self, String> {
        if !(0..3).all(|a| lo[a].is_finite() && hi[a].is_finite() && hi[a] > lo[a]) {
            return Err(format!("a crop box needs finite corners with max > min on every axis, got {lo:?}..{hi:?}"));
        }
        Ok(Self {
            center: std::array::from_fn(|a| 0.5 * (lo[a] + hi[a])),
            axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            half: std::array::from_fn(|a| 0.5 * (hi[a] - lo[a])),
        })
    }

    /// nerfstudio's oriented box (`OrientedBox.from_params`): centre `center`, full size `size`
    /// along its axes, turned by `rpy` (roll, pitch, yaw in radians: the rotation
    /// `R = Rz(yaw)·Ry(pitch)·Rx(roll)`, whose columns are the box's axes in the scene frame).
    /// Errors on non-finite values or a size that is not positive.
    pub fn oriented(center: [f32; 3], rpy: [f32; 3], size: [f32; 3]) -> Result<Self, String> {
        if !(center.iter().chain(&rpy).all(|v| v.is_finite()) && size.iter().all(|s| s.is_finite() && *s > 0.0)) {
            return Err(format!(
                "a crop box needs a finite centre and rotation and a positive size, got centre {center:?}, rotation {rpy:?}, size {size:?}"
            ));
        }
        let [r, p, y] = rpy.map(f64::from);
        let (sr, cr, sp, cp, sy, cy) = (r.sin(), r.cos(), p.sin(), p.cos(), y.sin(), y.cos());
        // R = Rz(y)·Ry(p)·Rx(r), row-major.
        let m = [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ];
        // The box's axes are R's columns: rows of Rᵀ.
        let axes = std::array::from_fn(|i| std::array::from_fn(|j| m[j][i] as f32));
        Ok(Self { center, axes, half: size.map(|s| 0.5 * s) })
    }

    /// Whether the box is axis-aligned (its axes are the scene's).
    pub fn is_axis_aligned(&self) -> bool {
        (0..3).all(|i| (0..3).all(|j| self.axes[i][j] == if i == j { 1.0 } else { 0.0 }))
    }

    /// Roll, pitch and yaw of the box's rotation ([`oriented`](Self::oriented)'s `rpy`).
    pub fn rpy(&self) -> [f32; 3] {
        // R[j][i] = axes[i][j]: R[2][0] = −sin p, R[2][1] = cos p sin r, R[2][2] = cos p cos r,
        // R[1][0] = sin y cos p, R[0][0] = cos y cos p.
        let r = |row: usize, col: usize| f64::from(self.axes[col][row]);
        let pitch = (-r(2, 0)).clamp(-1.0, 1.0).asin();
        let (roll, yaw) = if pitch.cos() > 1e-6 {
            (r(2, 1).atan2(r(2, 2)), r(1, 0).atan2(r(0, 0)))
        } else {
            // Gimbal lock: yaw taken as 0.
            ((-r(1, 2)).atan2(r(1, 1)), 0.0)
        };
        [roll as f32, pitch as f32, yaw as f32]
    }

    /// The box's full size along its axes.
    pub fn size(&self) -> [f32; 3] {
        self.half.map(|h| 2.0 * h)
    }

    /// `o` and `d` in the box's frame (`axes·(o − centre)`, `axes·d`).
    #[inline]
    fn in_box_frame(&self, o: [f32; 3], d: [f32; 3]) -> ([f32; 3], [f32; 3]) {
        let q = [o[0] - self.center[0], o[1] - self.center[1], o[2] - self.center[2]];
        let dot = |a: &[f32; 3], v: [f32; 3]| a[0] * v[0] + a[1] * v[1] + a[2] * v[2];
        (self.axes.map(|a| dot(&a, q)), self.axes.map(|a| dot(&a, d)))
    }

    /// The ray `o + t·d` against the box: `(t_enter, t_exit)`, empty (`!(exit > enter)`) on a
    /// miss (the occupancy marcher's slab test in the box's frame).
    #[inline]
    pub fn slab(&self, o: [f32; 3], d: [f32; 3]) -> (f32, f32) {
        let (ob, db) = self.in_box_frame(o, d);
        crate::occupancy::slab(ob, db, self.half.map(|h| -h), self.half)
    }

    /// Whether `p` lies in the box (faces included).
    pub fn contains(&self, p: [f32; 3]) -> bool {
        let (q, _) = self.in_box_frame(p, [0.0; 3]);
        (0..3).all(|a| q[a].abs() <= self.half[a])
    }

    /// The ray's segment `[a, b]` clipped to the box: `[max(a, enter), min(b, exit)]`, or
    /// `[near, near]` when that is empty (as [`crate::segment`] gives a ray that misses the
    /// scene box: zero-length intervals, no colour, no opacity).
    #[inline]
    pub fn clip(&self, o: [f32; 3], d: [f32; 3], (a, b): (f32, f32), near: f32) -> (f32, f32) {
        let (t0, t1) = self.slab(o, d);
        let (a, b) = (a.max(t0), b.min(t1));
        if b > a {
            (a, b)
        } else {
            (near, near)
        }
    }

    /// The smallest axis-aligned box that holds this one (its corners' bounds).
    pub fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let ext: [f32; 3] = std::array::from_fn(|j| (0..3).map(|i| self.axes[i][j].abs() * self.half[i]).sum());
        (std::array::from_fn(|j| self.center[j] - ext[j]), std::array::from_fn(|j| self.center[j] + ext[j]))
    }
}

/// Clips every ray's `[near[r], far[r]]` to `crop` in place ([`CropBox::clip`]); `near` is the
/// scalar a miss collapses to.
pub fn crop_segments(crop: &CropBox, origins: &[f32], dirs: &[f32], near_scalar: f32, near: &mut [f32], far: &mut [f32]) {
    let n = near.len();
    assert!(origins.len() == 3 * n && dirs.len() == 3 * n && far.len() == n, "crop_segments: 3·n origins and dirs, n segments");
    for r in 0..n {
        let o = [origins[3 * r], origins[3 * r + 1], origins[3 * r + 2]];
        let d = [dirs[3 * r], dirs[3 * r + 1], dirs[3 * r + 2]];
        (near[r], far[r]) = crop.clip(o, d, (near[r], far[r]), near_scalar);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn rot_apply(c: &CropBox, v: [f32; 3]) -> [f32; 3] {
        // R·v = Σ_i v_i · axes[i] (R's columns are the axes).
        std::array::from_fn(|j| (0..3).map(|i| v[i] * c.axes[i][j]).sum())
    }

    #[test]
    fn oriented_box_is_nerfstudios_rotation() {
        // Yaw of 90°: the box's x axis is the scene's y.
        let c = CropBox::oriented([0.0; 3], [0.0, 0.0, std::f32::consts::FRAC_PI_2], [2.0, 4.0, 6.0]).unwrap();
        let x = rot_apply(&c, [1.0, 0.0, 0.0]);
        assert!((x[0]).abs() < 1e-6 && (x[1] - 1.0).abs() < 1e-6 && x[2].abs() < 1e-6, "{x:?}");
        // Its long side (x: 2, y: 4) now lies along the scene's x.
        assert!(c.contains([1.9, 0.9, 2.9]) && !c.contains([0.0, 1.1, 0.0]) && !c.contains([2.1, 0.0, 0.0]));
        let (lo, hi) = c.bounds();
        for a in 0..3 {
            assert!((hi[a] - [2.0, 1.0, 3.0][a]).abs() < 1e-5 && (lo[a] + hi[a]).abs() < 1e-5, "{lo:?} {hi:?}");
        }
        // Roll, pitch and yaw come back.
        let rpy = [0.3, -0.7, 2.1];
        let c = CropBox::oriented([1.0, 2.0, 3.0], rpy, [1.0; 3]).unwrap();
        for (a, b) in c.rpy().iter().zip(rpy) {
            assert!((a - b).abs() < 1e-5, "{:?} vs {rpy:?}", c.rpy());
        }
        // Rz·Ry·Rx order: pitch then yaw applied to the x axis.
        let (p, y) = (0.4f32, 0.9f32);
        let c = CropBox::oriented([0.0; 3], [0.0, p, y], [1.0; 3]).unwrap();
        let x = rot_apply(&c, [1.0, 0.0, 0.0]);
        let want = [y.cos() * p.cos(), y.sin() * p.cos(), -p.sin()];
        assert!(x.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6), "{x:?} vs {want:?}");
    }

    #[test]
    fn slab_matches_points_inside() {
        // The segment a ray gets is exactly where its points lie in the box.
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for _ in 0..200 {
            let rpy = [rng.gen_range(-3.0..3.0), rng.gen_range(-1.5..1.5), rng.gen_range(-3.0..3.0)];
            let size = [rng.gen_range(0.2..2.0), rng.gen_range(0.2..2.0), rng.gen_range(0.2..2.0)];
            let c = CropBox::oriented([rng.gen_range(-0.5..0.5), 0.1, -0.2], rpy, size).unwrap();
            let o = [rng.gen_range(-3.0..3.0), rng.gen_range(-3.0..3.0), rng.gen_range(-3.0..3.0)];
            let d: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.0..1.0));
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let d = d.map(|x| x / l);
            let (t0, t1) = c.slab(o, d);
            for k in 0..400 {
                let t = -6.0 + 12.0 * k as f32 / 400.0;
                let p = std::array::from_fn(|a| o[a] + t * d[a]);
                let margin = 1e-4;
                if t > t0 + margin && t < t1 - margin {
                    assert!(c.contains(p), "t {t} in ({t0}, {t1}) but {p:?} outside");
                } else if t < t0 - margin || t > t1 + margin {
                    assert!(!c.contains(p), "t {t} outside ({t0}, {t1}) but {p:?} inside");
                }
            }
        }
    }

    #[test]
    fn a_cropped_march_starts_and_ends_at_the_crop() {
        use crate::{OccupancyGrid, OccupancyGridConfig, RayMarch};
        let mut g = OccupancyGrid::new(OccupancyGridConfig { resolution: 16, ..Default::default() }, [-1.0; 3], [1.0; 3]);
        g.fill_from(0.01, &mut |_, s| s.fill(10.0));
        let c = CropBox::oriented([0.2, 0.0, 0.0], [0.0, 0.0, 0.7], [0.6, 0.8, 0.5]).unwrap();
        let (o, d, step) = ([0.2, 0.0, -3.0], [0.0, 0.0, 1.0], 0.01);
        let march = |crop: Option<&CropBox>| {
            let mut m = RayMarch::cropped(&g, o, d, 0.5, 6.0, crop);
            let mut ts = vec![];
            while !m.is_done() {
                m.advance(&g, step, 10_000, 7, |t| ts.push(t));
            }
            ts
        };
        let (whole, cropped) = (march(None), march(Some(&c)));
        // The box's z faces (it turns about z): the crop's z range is 2.75..3.25 along the ray.
        assert_eq!(whole.len(), 200);
        assert!((cropped[0] - (2.75 + 0.5 * step)).abs() < 1e-5, "{:?}", &cropped[..3]);
        assert!(cropped.len() == 50 && cropped.iter().all(|&t| t < 3.25), "{} samples", cropped.len());
        // A ray that misses the crop gets nothing.
        let mut m = RayMarch::cropped(&g, [0.9, 0.9, -3.0], d, 0.5, 6.0, Some(&c));
        assert!(m.is_done() && m.advance(&g, step, 100, 100, |_| {}) == 0);
    }

    #[test]
    fn clip_intersects_segments() {
        let c = CropBox::aabb([-1.0; 3], [1.0; 3]).unwrap();
        let (o, d) = ([0.0, 0.0, -5.0], [0.0, 0.0, 1.0]);
        assert_eq!(c.clip(o, d, (2.0, 8.0), 2.0), (4.0, 6.0));
        assert_eq!(c.clip(o, d, (4.5, 5.5), 2.0), (4.5, 5.5));
        // A miss (or a segment ending before the box) collapses to the scalar near.
        assert_eq!(c.clip([3.0, 0.0, -5.0], d, (2.0, 8.0), 2.0), (2.0, 2.0));
        assert_eq!(c.clip(o, d, (2.0, 3.0), 2.0), (2.0, 2.0));
        let (mut n, mut f) = (vec![2.0, 2.0], vec![8.0, 8.0]);
        crop_segments(&c, &[0.0, 0.0, -5.0, 3.0, 0.0, -5.0], &[0.0, 0.0, 1.0, 0.0, 0.0, 1.0], 2.0, &mut n, &mut f);
        assert_eq!((n, f), (vec![4.0, 2.0], vec![6.0, 2.0]));
        assert!(c.is_axis_aligned() && c.rpy() == [0.0; 3] && c.size() == [2.0; 3]);
        assert!(CropBox::aabb([0.0; 3], [0.0, 1.0, 1.0]).is_err());
        assert!(CropBox::oriented([0.0; 3], [f32::NAN, 0.0, 0.0], [1.0; 3]).is_err());
        assert!(CropBox::oriented([0.0; 3], [0.0; 3], [1.0, -1.0, 1.0]).is_err());
    }
}
