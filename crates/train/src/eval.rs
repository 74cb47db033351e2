//! Evaluation on held-out views: render, PSNR and SSIM against the ground truth, PNGs.

use crate::trainer::Trainer;
use crate::TrainError;
use nerf_data::{save_png, Dataset, RayBatch};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Metrics of one rendered view.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ViewMetrics {
    /// View index within the evaluated dataset.
    pub index: usize,
    /// Ground-truth image file.
    pub file: String,
    /// PSNR in dB (images in `[0, 1]`).
    pub psnr: f64,
    /// SSIM (Gaussian 11×11, σ = 1.5).
    pub ssim: f64,
}

/// Metrics over a set of views. `psnr` and `ssim` are means of the per-view values (the NeRF
/// papers' convention).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EvalReport {
    /// Per-view metrics.
    pub views: Vec<ViewMetrics>,
    /// Mean PSNR.
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// Seconds spent rendering and scoring.
    pub seconds: f64,
    /// Seconds spent rendering alone (ray generation excluded; on the GPU including the upload of
    /// the rays and the read-back of the image).
    #[serde(default)]
    pub render_seconds: f64,
}

/// Renders every view of `data` with the trainer's fields on `data`'s evaluation background,
/// scores it, and writes `<out_dir>/<stem>.png` renders when `out_dir` is given.
pub fn evaluate(
    trainer: &Trainer,
    data: &Dataset,
    out_dir: Option<&Path>,
    mut on_view: impl FnMut(usize, usize),
) -> Result<EvalReport, TrainError> {
    let t0 = std::time::Instant::now();
    if let Some(d) = out_dir {
        std::fs::create_dir_all(d).map_err(|e| TrainError::Io { path: d.to_path_buf(), source: e })?;
    }
    let bg = trainer.config().eval_background;
    let conv = trainer.config().pixel_convention;
    let (w, h) = (data.width as usize, data.height as usize);
    let mut batch = RayBatch::default();
    let mut rgb = vec![0.0f32; 3 * w * h];
    let mut opacity = vec![0.0f32; w * h];
    let mut depth = vec![0.0f32; w * h];
    let mut views = Vec::with_capacity(data.n_views());
    let mut render_seconds = 0.0;
    for i in 0..data.n_views() {
        data.view_rays(i, bg, conv, &mut batch);
        let t = std::time::Instant::now();
        trainer.render_rays(&batch.origins, &batch.dirs, &batch.background, &mut rgb, &mut opacity, &mut depth)?;
        render_seconds += t.elapsed().as_secs_f64();
        let gt = &batch.target;
        let psnr = nerf_metrics::psnr(&rgb, gt);
        let ssim = nerf_metrics::ssim(&rgb, gt, w, h);
        let file = data.file_paths[i].display().to_string();
        if let Some(d) = out_dir {
            let stem = data.file_paths[i].file_stem().map(|s| s.to_string_lossy().into_owned());
            let path = d.join(format!("{}.png", stem.unwrap_or_else(|| format!("view_{i:03}"))));
            save_png(&path, data.width, data.height, &rgb)?;
        }
        views.push(ViewMetrics { index: i, file, psnr, ssim });
        on_view(i + 1, data.n_views());
    }
    let n = views.len().max(1) as f64;
    Ok(EvalReport {
        psnr: views.iter().map(|v| v.psnr).sum::<f64>() / n,
        ssim: views.iter().map(|v| v.ssim).sum::<f64>() / n,
        views,
        seconds: t0.elapsed().as_secs_f64(),
        render_seconds,
    })
}
