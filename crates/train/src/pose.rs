//! The trainer's side of camera pose refinement (`TrainConfig::camera_optimizer`,
//! `nerf_rays::pose`): the corrections on the CPU, the per-step buffers that carry the fields'
//! input gradients back to them, nerfstudio's regulariser, and their name in checkpoints
//! (`camera/…`, see [`crate::views`]).

use crate::config::CameraOptimizerConfig;
use crate::views::{CpuViews, ViewKind, ViewState};
use nerf_optim::AdamConfig;
use nerf_rays::pose::{pose_correct_backward, pose_correct_rays, pose_regulariser, Mat3x3, POSE_PARAMS_PER_VIEW};

/// The pose corrections' entries in checkpoints (`camera/params`: per training view a
/// translation then a rotation vector, `camera/m`, `camera/v`, `camera/step`) and their Adam
/// group.
pub const POSE_VIEWS: ViewKind = ViewKind {
    prefix: "camera/",
    group: "camera_optimizer",
    per_view: POSE_PARAMS_PER_VIEW,
    what: "camera pose refinement",
};

/// The pose corrections and their optimiser state, as a checkpoint holds them.
pub type PoseState = ViewState;

/// The CPU path's pose corrections and the buffers of a step.
pub(crate) struct CpuPose {
    pub views: CpuViews,
    pub config: CameraOptimizerConfig,
    /// The batch's ray directions before the correction (the backward reads them).
    pub base_dirs: Vec<f32>,
    /// ∂L/∂o' and ∂L/∂d' per ray, summed over the stages.
    pub d_origins: Vec<f32>,
    pub d_dirs: Vec<f32>,
    /// ∂L/∂x and ∂L/∂d per sample of one stage.
    pub d_positions: Vec<f32>,
    pub d_sample_dirs: Vec<f32>,
    rotations: Vec<Mat3x3<f32>>,
    acc: Vec<f32>,
}

impl CpuPose {
    pub fn new(n_views: usize, adam: &AdamConfig, config: &CameraOptimizerConfig) -> Self {
        Self {
            views: CpuViews::new(POSE_VIEWS, vec![0.0; POSE_PARAMS_PER_VIEW * n_views], adam),
            config: config.clone(),
            base_dirs: Vec::new(),
            d_origins: Vec::new(),
            d_dirs: Vec::new(),
            d_positions: Vec::new(),
            d_sample_dirs: Vec::new(),
            rotations: Vec::new(),
            acc: Vec::new(),
        }
    }

    /// Moves the batch's rays by their views' corrections (keeping the directions before it) and
    /// zeroes the per-ray gradients.
    pub fn correct(&mut self, view_ids: &[u32], origins: &mut [f32], dirs: &mut [f32]) {
        self.base_dirs.clear();
        self.base_dirs.extend_from_slice(dirs);
        pose_correct_rays(view_ids, &self.views.params, origins, dirs, &mut self.rotations);
        self.d_origins.clear();
        self.d_origins.resize(origins.len(), 0.0);
        self.d_dirs.clear();
        self.d_dirs.resize(dirs.len(), 0.0);
    }

    /// Per-sample input-gradient buffers sized for `n` samples.
    pub fn sample_buffers(&mut self, n: usize) -> (&mut [f32], &mut [f32]) {
        self.d_positions.resize(3 * n, 0.0);
        self.d_sample_dirs.resize(3 * n, 0.0);
        (&mut self.d_positions, &mut self.d_sample_dirs)
    }

    /// The corrections' gradients from the per-ray ones and the regulariser, then one Adam step
    /// at the schedule's rate for `step`. Returns the regulariser's value (added to the loss).
    pub fn step(&mut self, view_ids: &[u32], step: u64) -> f32 {
        let v = &mut self.views;
        pose_correct_backward(view_ids, &v.params, &self.base_dirs, &self.d_origins, &self.d_dirs, &mut self.acc, &mut v.grads);
        let reg = regulariser(&self.config, &v.params, &mut v.grads);
        v.step(self.config.lr_at(step));
        reg
    }
}

/// What a run learnt, as `camera_corrections.json` holds it: per training view (in the order the
/// scene lists them, with its name, `names[v]`: `nerf_data::Dataset::view_names`) the correction
/// `[τ, ω]`, its size (`|τ|`, `|ω|` in degrees) and the corrected camera-to-world matrix
/// ([`nerf_rays::pose::move_camera`]; row-major 4×4 in the scene's ray space, the frame
/// `cameras` are in), and the mean sizes. `nerf export-scene --camera-corrections` writes a scene
/// with these poses.
pub fn corrections_json(params: &[f32], cameras: &[nerf_rays::Camera], names: &[String]) -> serde_json::Value {
    let n = cameras.len().max(1) as f64;
    let (mut sum_t, mut sum_r) = (0.0, 0.0);
    let views: Vec<serde_json::Value> = params
        .chunks_exact(POSE_PARAMS_PER_VIEW)
        .zip(cameras)
        .enumerate()
        .map(|(v, (p, cam))| {
            let p: [f32; POSE_PARAMS_PER_VIEW] = p.try_into().expect("chunks of 6");
            let t = p[..3].iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
            let r = p[3..].iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt().to_degrees();
            (sum_t, sum_r) = (sum_t + t, sum_r + r);
            serde_json::json!({
                "view": v, "image": names.get(v), "correction": p, "translation": t, "rotation_degrees": r,
                "camera_to_world": nerf_rays::pose::move_camera(cam, &p).c2w(),
            })
        })
        .collect();
    serde_json::json!({
        "convention": "per training view: translation τ (scene units) then rotation vector ω (radians); rays o' = o + τ, d' = exp([ω]x) d (nerfstudio SO3xR3)",
        "mean_translation": sum_t / n,
        "mean_rotation_degrees": sum_r / n,
        "views": views,
    })
}

/// nerfstudio's `camera_opt_regularizer` with `config`'s weights
/// ([`nerf_rays::pose::pose_regulariser`]): adds its gradient to `grads`, returns its value.
pub fn regulariser(config: &CameraOptimizerConfig, params: &[f32], grads: &mut [f32]) -> f32 {
    pose_regulariser(config.trans_penalty, config.rot_penalty, params, grads)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regulariser_gradient_matches_finite_differences() {
        let config = CameraOptimizerConfig { trans_penalty: 0.3, rot_penalty: 0.7, ..Default::default() };
        let params = vec![0.1, -0.2, 0.3, 0.05, 0.0, -0.1, 0.0, 0.0, 0.0, 0.2, 0.1, 0.4];
        let mut grads = vec![0.0; 12];
        let value = regulariser(&config, &params, &mut grads);
        let want = 0.3 * (0.14f32.sqrt() + 0.0) / 2.0 + 0.7 * (0.0125f32.sqrt() + 0.21f32.sqrt()) / 2.0;
        assert!((value - want).abs() < 1e-6, "{value} vs {want}");
        let h = 1e-3;
        for i in [0, 1, 2, 3, 5, 9, 10, 11] {
            let (mut p, mut m) = (params.clone(), params.clone());
            p[i] += h;
            m[i] -= h;
            let fd = (regulariser(&config, &p, &mut [0.0; 12]) - regulariser(&config, &m, &mut [0.0; 12])) / (2.0 * h);
            assert!((fd - grads[i]).abs() < 2e-3, "[{i}]: {} vs fd {fd}", grads[i]);
        }
        assert_eq!(&grads[6..9], &[0.0; 3], "no gradient at a zero translation");
    }

    #[test]
    fn the_rate_decays_from_lr_to_lr_final_then_stays() {
        let c = CameraOptimizerConfig { lr: 1e-3, lr_final: 1e-4, ..Default::default() };
        assert!((c.lr_at(0) - 1e-3).abs() < 1e-9);
        assert!((c.lr_at(2500) - 1e-3 * 0.1f32.sqrt()).abs() < 1e-8);
        assert!((c.lr_at(5000) - 1e-4).abs() < 1e-9 && c.lr_at(9000) == c.lr_at(5000));
        // With a warm-up the corrections stay put until it ends, then follow the same schedule.
        let w = CameraOptimizerConfig { warmup_steps: 300, ..c.clone() };
        assert_eq!((w.lr_at(0), w.lr_at(299)), (0.0, 0.0));
        assert_eq!((w.lr_at(300), w.lr_at(2500)), (c.lr_at(300), c.lr_at(2500)));
    }
}
