//! Evaluation on held-out views: render, PSNR and SSIM against the ground truth, PNGs.

use crate::trainer::Trainer;
use crate::TrainError;
use nerf_data::{save_png, Dataset, RayBatch};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Metrics of one rendered view.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewMetrics {
    /// View index within the evaluated dataset.
    pub index: usize,
    /// Ground-truth image file.
    pub file: String,
    /// The view's width and height (views of one scene may differ: `Dataset::view_size`); 0 in
    /// files written before they were recorded.
    #[serde(default)]
    pub width: u32,
    /// See [`ViewMetrics::width`].
    #[serde(default)]
    pub height: u32,
    /// PSNR in dB (images in `[0, 1]`).
    pub psnr: f64,
    /// SSIM (Gaussian 11×11, σ = 1.5).
    pub ssim: f64,
    /// Where the view's error sits, split by its ground truth's alpha; `None` unless the view has
    /// both empty (alpha = 0) and object pixels (Blender scenes have; LLFF's photos do not).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_split: Option<AlphaSplit>,
    /// The rendered depth against the view's depth map ([`DepthError`]); `None` unless the view
    /// has measured pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth: Option<DepthError>,
    /// The scores over the pixels the view's mask keeps ([`MaskedMetrics`]); `None` unless some
    /// view of the set has a mask that drops pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub masked: Option<MaskedMetrics>,
}

/// A view's PSNR and SSIM over the pixels its mask keeps ([`Dataset::masks`]: nerfstudio's
/// `mask_path`, instant-ngp's dynamic masks, the pixels past a fisheye's
/// `fisheye_crop_radius` or that a resampled photo did not see). A masked-out pixel holds
/// something the field is not asked to reproduce (a passer-by, the black beyond the image
/// circle), so these scores leave it out, while [`ViewMetrics::psnr`] and `ssim` score the
/// whole image as nerfstudio's and instant-ngp's evaluations do. A view without a mask in a set
/// with masks keeps every pixel and scores as the whole image. For a set of views, each value
/// is the mean of the views' values.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaskedMetrics {
    /// Share of the view's pixels the mask keeps.
    pub kept_fraction: f64,
    /// PSNR over the kept pixels (the MSE of their values).
    pub psnr: f64,
    /// SSIM over the windows of kept pixels ([`nerf_metrics::ssim_masked`]).
    pub ssim: f64,
}

impl MaskedMetrics {
    /// The scores of a rendered view `rgb` (`w × h`, RGB) against its ground truth `gt` over the
    /// pixels `keep` keeps (one flag per pixel); `None` when it keeps none.
    pub fn of(rgb: &[f32], gt: &[f32], w: usize, h: usize, keep: &[bool]) -> Option<Self> {
        let (sse, count) = nerf_metrics::sse_split(rgb, gt, 3, keep);
        (count[1] > 0).then(|| Self {
            kept_fraction: (count[1] / 3) as f64 / keep.len() as f64,
            psnr: nerf_metrics::mse_to_psnr(sse[1] / count[1] as f64),
            ssim: nerf_metrics::ssim_masked(rgb, gt, w, h, keep),
        })
    }

    /// The mean of the views' scores; `None` when no view has them.
    pub fn mean<'a>(views: impl Iterator<Item = &'a MaskedMetrics>) -> Option<Self> {
        let [kept_fraction, psnr, ssim] = mean_of(views, |m| [m.kept_fraction, m.psnr, m.ssim])?;
        Some(Self { kept_fraction, psnr, ssim })
    }

    /// One line for a report.
    pub fn summary(&self) -> String {
        format!("over the pixels the masks keep ({:.1} % of them): PSNR {:.2} dB, SSIM {:.4}", 100.0 * self.kept_fraction, self.psnr, self.ssim)
    }
}

/// The mean over `items` of each of the `N` values `values` reads from one; `None` without items.
fn mean_of<'a, T: 'a, const N: usize>(items: impl Iterator<Item = &'a T>, values: impl Fn(&T) -> [f64; N]) -> Option<[f64; N]> {
    let (mut acc, mut n) = ([0.0f64; N], 0usize);
    for item in items {
        acc.iter_mut().zip(values(item)).for_each(|(a, v)| *a += v);
        n += 1;
    }
    (n > 0).then(|| acc.map(|a| a / n as f64))
}

/// Which pixels of view `i` (its own `w × h`, row-major) its mask keeps; `None` for a dataset
/// without masks.
fn kept_flags(data: &Dataset, i: usize) -> Option<Vec<bool>> {
    let masks = data.masks.as_ref()?;
    // The kept pixels are the canvas's (`row·W + col` of the dataset's width).
    let mut canvas = vec![false; masks.n_pixels() as usize];
    masks.kept(i).for_each(|p| canvas[p as usize] = true);
    Some(data.view_crop(i, 1, &canvas).into_owned())
}

/// Rendered expected depth against a depth map (`Dataset::depths`: distances along the rays, in
/// the scene's units) over the pixels it measures, as nerfstudio's depth-nerfacto reports
/// `depth_mse`. For a set of views, each value is the mean of the views' values.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthError {
    /// Mean squared difference.
    pub mse: f64,
    /// Mean absolute difference.
    pub mean_abs: f64,
    /// Share of the view's pixels with a measurement.
    pub measured_fraction: f64,
}

impl DepthError {
    /// The error of a rendered `depth` against the measured `target` (0: none), one value per
    /// pixel; `None` when no pixel is measured.
    pub fn of(depth: &[f32], target: &[f32]) -> Option<Self> {
        let (mut sq, mut abs, mut n) = (0.0f64, 0.0f64, 0usize);
        for (&d, &t) in depth.iter().zip(target) {
            if t > 0.0 {
                let e = (d - t) as f64;
                sq += e * e;
                abs += e.abs();
                n += 1;
            }
        }
        (n > 0).then(|| Self { mse: sq / n as f64, mean_abs: abs / n as f64, measured_fraction: n as f64 / target.len().max(1) as f64 })
    }

    /// The mean of the views' errors; `None` when no view has one.
    pub fn mean<'a>(errors: impl Iterator<Item = &'a DepthError>) -> Option<Self> {
        let [mse, mean_abs, measured_fraction] = mean_of(errors, |e| [e.mse, e.mean_abs, e.measured_fraction])?;
        Some(Self { mse, mean_abs, measured_fraction })
    }

    /// One line for a report.
    pub fn summary(&self) -> String {
        format!(
            "depth against the depth maps: mean |error| {:.4}, MSE {:.5} (scene units, {:.0} % of the pixels measured)",
            self.mean_abs,
            self.mse,
            100.0 * self.measured_fraction
        )
    }
}

/// A view's error split by its ground truth's alpha ([`nerf_metrics::sse_split`]): pixels of
/// empty space (alpha = 0), where any error is a floater or haze the field put in front of the
/// background, against pixels on the object (alpha > 0, its anti-aliased edge included). For a
/// set of views, each value is the mean of the views' values.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AlphaSplit {
    /// Share of the pixels that are empty.
    pub empty_fraction: f64,
    /// MSE over the empty pixels.
    pub mse_empty: f64,
    /// MSE over the object's pixels.
    pub mse_object: f64,
    /// Share of the view's squared error in the empty pixels.
    pub empty_error_share: f64,
    /// Mean rendered opacity over the empty pixels (0 when the field leaves empty space empty).
    pub empty_opacity: f64,
}

impl AlphaSplit {
    /// The split of one rendered view (`rgb`, `opacity`) against its ground truth (`gt`, RGB)
    /// and alpha (`alpha`, one value per pixel).
    pub fn of(rgb: &[f32], opacity: &[f32], gt: &[f32], alpha: impl Iterator<Item = f32>) -> Option<Self> {
        let empty: Vec<bool> = alpha.map(|a| a == 0.0).collect();
        let (sse, count) = nerf_metrics::sse_split(rgb, gt, 3, &empty);
        if count[0] == 0 || count[1] == 0 {
            return None;
        }
        let n_empty = count[1] / 3;
        let opacity_sum: f64 = opacity.iter().zip(&empty).filter(|(_, &e)| e).map(|(&o, _)| o as f64).sum();
        let total = sse[0] + sse[1];
        Some(Self {
            empty_fraction: n_empty as f64 / empty.len() as f64,
            mse_empty: sse[1] / count[1] as f64,
            mse_object: sse[0] / count[0] as f64,
            empty_error_share: if total > 0.0 { sse[1] / total } else { 0.0 },
            empty_opacity: opacity_sum / n_empty as f64,
        })
    }

    /// The mean of the views' splits; `None` when no view has one.
    pub fn mean<'a>(splits: impl Iterator<Item = &'a AlphaSplit>) -> Option<Self> {
        let m = mean_of(splits, |s| [s.empty_fraction, s.mse_empty, s.mse_object, s.empty_error_share, s.empty_opacity])?;
        Some(Self { empty_fraction: m[0], mse_empty: m[1], mse_object: m[2], empty_error_share: m[3], empty_opacity: m[4] })
    }

    /// One line for a report: the two parts' PSNRs (of their MSEs), the empty pixels' share of
    /// the error and their mean opacity.
    pub fn summary(&self) -> String {
        format!(
            "object pixels {:.2} dB; empty pixels ({:.0} % of the image) {:.2} dB, {:.1} % of the squared error, mean opacity there {:.4}",
            nerf_metrics::mse_to_psnr(self.mse_object),
            100.0 * self.empty_fraction,
            nerf_metrics::mse_to_psnr(self.mse_empty),
            100.0 * self.empty_error_share,
            self.empty_opacity
        )
    }
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
    /// The mean of the views' error splits by ground-truth alpha ([`AlphaSplit`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_split: Option<AlphaSplit>,
    /// The mean of the views' depth errors against their depth maps ([`DepthError`]), over the
    /// views that have measured pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth: Option<DepthError>,
    /// The mean of the views' scores over the pixels their masks keep ([`MaskedMetrics`]);
    /// `None` unless some view has a mask that drops pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub masked: Option<MaskedMetrics>,
    /// Seconds spent rendering and scoring.
    pub seconds: f64,
    /// Seconds spent rendering alone (ray generation excluded; on the GPU including the upload of
    /// the rays and the read-back of the image).
    #[serde(default)]
    pub render_seconds: f64,
}

/// The mean of a supersampled render's passes, one per ray through each pixel: the colour,
/// opacity and depth buffers summed pass by pass, then divided by the count ([`evaluate`]'s
/// `eval_spp`, `nerf render --spp`). With one pass it holds nothing and leaves the buffers as
/// they are.
#[derive(Debug, Default)]
pub struct PassMean {
    sums: Option<[Vec<f32>; 3]>,
    passes: usize,
}

impl PassMean {
    /// For renders of `passes` passes.
    pub fn new(passes: usize) -> Self {
        Self { sums: (passes > 1).then(Default::default), passes }
    }

    /// Adds pass `j` (0 first, which starts the sums over, at its buffers' sizes) of the colour,
    /// opacity and depth buffers.
    pub fn add(&mut self, j: usize, passes: [&[f32]; 3]) {
        let Some(sums) = self.sums.as_mut() else { return };
        for (s, x) in sums.iter_mut().zip(passes) {
            if j == 0 {
                s.clear();
                s.extend_from_slice(x);
            } else {
                s.iter_mut().zip(x).for_each(|(s, x)| *s += x);
            }
        }
    }

    /// Writes the mean over the passes into the buffers, after the last pass.
    pub fn finish(&self, out: [&mut [f32]; 3]) {
        let Some(sums) = self.sums.as_ref() else { return };
        let k = 1.0 / self.passes as f32;
        for (x, s) in out.into_iter().zip(sums) {
            x.iter_mut().zip(s).for_each(|(x, s)| *x = s * k);
        }
    }
}

/// Renders every view of `data` with the trainer's fields on `data`'s evaluation background
/// (`eval_spp` rays per pixel placed by `eval_filter`, averaged), scores it, and writes `<out_dir>/<name>.png` renders ([`Dataset::view_names`]) when
/// `out_dir` is given.
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
    // Supersampling: the mean of the renders through these points of each pixel, placed by the
    // pixel filter.
    let points = conv.sample_offsets_filtered(trainer.config().eval_spp as usize, trainer.config().eval_filter);
    let mut batch = RayBatch::default();
    let (mut rgb, mut opacity, mut depth) = (Vec::new(), Vec::new(), Vec::new());
    let mut mean = PassMean::new(points.len());
    let mut views = Vec::with_capacity(data.n_views());
    let mut render_seconds = 0.0;
    let names = data.view_names();
    for i in 0..data.n_views() {
        // The view's own size (views of several sizes: [`Dataset::view_size`]).
        let (w, h) = data.view_size(i);
        let (w, h) = (w as usize, h as usize);
        for (x, n) in [(&mut rgb, 3 * w * h), (&mut opacity, w * h), (&mut depth, w * h)] {
            x.resize(n, 0.0);
        }
        for (j, &point) in points.iter().enumerate() {
            data.view_rays_at(i, bg, point, &mut batch);
            let t = std::time::Instant::now();
            trainer.render_rays(&batch.origins, &batch.dirs, &batch.background, &mut rgb, &mut opacity, &mut depth)?;
            render_seconds += t.elapsed().as_secs_f64();
            mean.add(j, [&rgb, &opacity, &depth]);
        }
        mean.finish([&mut rgb, &mut opacity, &mut depth]);
        let gt = &batch.target;
        let psnr = nerf_metrics::psnr(&rgb, gt);
        let ssim = nerf_metrics::ssim(&rgb, gt, w, h);
        let file = data.file_paths[i].display().to_string();
        if let Some(d) = out_dir {
            let path = d.join(format!("{}.png", names[i]));
            save_png(&path, w as u32, h as u32, &rgb)?;
        }
        let px = data.images[i].to_f32();
        let image = data.view_crop(i, 4, &px);
        let alpha = image.chunks_exact(4).map(|p| p[3]);
        let alpha_split = AlphaSplit::of(&rgb, &opacity, gt, alpha);
        let depth = data.depths.as_ref().and_then(|d| DepthError::of(&depth, &data.view_crop(i, 1, &d[i])));
        let masked = kept_flags(data, i).and_then(|keep| MaskedMetrics::of(&rgb, gt, w, h, &keep));
        views.push(ViewMetrics { index: i, file, width: w as u32, height: h as u32, psnr, ssim, alpha_split, depth, masked });
        on_view(i + 1, data.n_views());
    }
    // Masks that drop nothing (views of several sizes each keep their own pixels) add nothing.
    if views.iter().all(|v| v.masked.is_none_or(|m| m.kept_fraction == 1.0)) {
        views.iter_mut().for_each(|v| v.masked = None);
    }
    let n = views.len().max(1) as f64;
    Ok(EvalReport {
        psnr: views.iter().map(|v| v.psnr).sum::<f64>() / n,
        ssim: views.iter().map(|v| v.ssim).sum::<f64>() / n,
        alpha_split: AlphaSplit::mean(views.iter().filter_map(|v| v.alpha_split.as_ref())),
        depth: DepthError::mean(views.iter().filter_map(|v| v.depth.as_ref())),
        masked: MaskedMetrics::mean(views.iter().filter_map(|v| v.masked.as_ref())),
        views,
        seconds: t0.elapsed().as_secs_f64(),
        render_seconds,
    })
}

#[cfg(test)]
mod tests {
    use super::{AlphaSplit, DepthError, MaskedMetrics, PassMean};

    /// Over every pixel the masked scores are the whole view's; over some, the MSE of theirs;
    /// over none, none.
    #[test]
    fn masked_metrics_score_the_kept_pixels() {
        let (w, h) = (32, 16);
        let gt: Vec<f32> = (0..3 * w * h).map(|i| ((i * 37) % 101) as f32 / 100.0).collect();
        // The left half off by 0.1, the right half by 0.2.
        let rgb: Vec<f32> = gt.iter().enumerate().map(|(i, &g)| g + if (i / 3) % w < w / 2 { 0.1 } else { 0.2 }).collect();
        let all = MaskedMetrics::of(&rgb, &gt, w, h, &vec![true; w * h]).unwrap();
        assert_eq!((all.kept_fraction, all.psnr, all.ssim), (1.0, nerf_metrics::psnr(&rgb, &gt), nerf_metrics::ssim(&rgb, &gt, w, h)));
        let left: Vec<bool> = (0..w * h).map(|p| p % w < w / 2).collect();
        let m = MaskedMetrics::of(&rgb, &gt, w, h, &left).unwrap();
        assert_eq!(m.kept_fraction, 0.5);
        assert!((m.psnr - 20.0).abs() < 1e-4, "{m:?}");
        assert!(m.ssim.is_finite() && m.ssim != all.ssim, "{m:?}");
        assert!(MaskedMetrics::of(&rgb, &gt, w, h, &vec![false; w * h]).is_none());
        let mean = MaskedMetrics::mean([all, m].iter()).unwrap();
        assert_eq!(mean.kept_fraction, 0.75);
        assert!((mean.psnr - 0.5 * (all.psnr + m.psnr)).abs() < 1e-12);
        assert!(MaskedMetrics::mean(std::iter::empty()).is_none());
    }

    /// The mean of the passes lands in the buffers; a new first pass starts over at its size; one
    /// pass leaves the buffers alone.
    #[test]
    fn pass_mean_averages_the_passes() {
        let mut m = PassMean::new(2);
        let (mut a, mut b, mut c) = (vec![0.0f32; 3], vec![0.0f32; 1], vec![0.0f32; 1]);
        m.add(0, [&[1.0, 2.0, 3.0], &[0.5], &[4.0]]);
        m.add(1, [&[3.0, 2.0, 1.0], &[1.0], &[2.0]]);
        m.finish([&mut a, &mut b, &mut c]);
        assert_eq!((a.as_slice(), b[0], c[0]), ([2.0, 2.0, 2.0].as_slice(), 0.75, 3.0));
        let (mut a, mut b, mut c) = (vec![0.0f32; 6], vec![0.0f32; 2], vec![0.0f32; 2]);
        m.add(0, [&[2.0; 6], &[1.0; 2], &[1.0; 2]]);
        m.add(1, [&[4.0; 6], &[0.0; 2], &[3.0; 2]]);
        m.finish([&mut a, &mut b, &mut c]);
        assert_eq!((a, b, c), (vec![3.0; 6], vec![0.5; 2], vec![2.0; 2]));
        let one = PassMean::new(1);
        let mut x = vec![7.0f32];
        one.finish([&mut x, &mut [], &mut []]);
        assert_eq!(x, [7.0]);
    }

    #[test]
    fn depth_error_over_the_measured_pixels() {
        let e = DepthError::of(&[1.0, 2.0, 3.0, 9.0], &[1.5, 0.0, 2.0, 0.0]).unwrap();
        assert!((e.mse - (0.25 + 1.0) / 2.0).abs() < 1e-12 && (e.mean_abs - 0.75).abs() < 1e-12, "{e:?}");
        assert_eq!(e.measured_fraction, 0.5);
        assert!(DepthError::of(&[1.0], &[0.0]).is_none(), "no measurement, no error");
        let m = DepthError::mean([e, DepthError { mse: 0.0, mean_abs: 0.25, measured_fraction: 1.0 }].iter()).unwrap();
        assert!((m.mean_abs - 0.5).abs() < 1e-12 && (m.measured_fraction - 0.75).abs() < 1e-12);
        assert!(DepthError::mean(std::iter::empty()).is_none());
    }

    #[test]
    fn alpha_split_of_a_small_view() {
        // Four pixels: two empty (alpha 0) with errors 0.1 and 0 on one channel, two on the
        // object (alpha 1 and 0.5, its edge) with an error of 0.2 on one channel.
        let gt = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.2, 0.2, 0.2];
        let rgb = [0.9, 1.0, 1.0, 1.0, 1.0, 1.0, 0.5, 0.7, 0.5, 0.2, 0.2, 0.2];
        let opacity = [0.3, 0.1, 1.0, 1.0];
        let alpha = [0.0, 0.0, 1.0, 0.5];
        let s = AlphaSplit::of(&rgb, &opacity, &gt, alpha.into_iter()).unwrap();
        assert_eq!(s.empty_fraction, 0.5);
        assert!((s.mse_empty - 0.01 / 6.0).abs() < 1e-9, "{s:?}");
        assert!((s.mse_object - 0.04 / 6.0).abs() < 1e-9, "{s:?}");
        assert!((s.empty_error_share - 0.2).abs() < 1e-6, "{s:?}");
        assert!((s.empty_opacity - 0.2).abs() < 1e-7, "{s:?}");
        // No empty pixel (a photo) or no object pixel: no split.
        assert!(AlphaSplit::of(&rgb, &opacity, &gt, [1.0; 4].into_iter()).is_none());
        assert!(AlphaSplit::of(&rgb, &opacity, &gt, [0.0; 4].into_iter()).is_none());
        // The mean of two splits is the mean of each value; of none, none.
        let t = AlphaSplit { empty_fraction: 1.0, mse_empty: 0.0, mse_object: 0.0, empty_error_share: 0.0, empty_opacity: 0.0 };
        let m = AlphaSplit::mean([s, t].iter()).unwrap();
        assert!((m.empty_fraction - 0.75).abs() < 1e-12 && (m.empty_opacity - 0.1).abs() < 1e-7);
        assert!(AlphaSplit::mean(std::iter::empty()).is_none());
    }
}
