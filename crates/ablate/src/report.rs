//! The summary of an ablation: `results.csv`, `results.md` and PNG plots of the PSNR curves.

use crate::exec::{io_err, write_atomic, AblationReport, RunMetrics, RunOutcome};
use crate::spec::value_label;
use crate::AblateError;
use plotters::prelude::*;
use plotters::style::FontStyle;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Font files tried, in order, for plot text.
pub const FONT_CANDIDATES: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu-sans-fonts/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/freefont/FreeSans.ttf",
    "/usr/share/fonts/noto/NotoSans-Regular.ttf",
    "/usr/share/fonts/truetype/noto/NotoSans-Regular.ttf",
    "/Library/Fonts/Arial.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
    "C:\\Windows\\Fonts\\arial.ttf",
];

/// Registers the first available font as plotters' "sans-serif" (once per process); `false` when
/// none could be loaded, in which case plots are drawn without text.
pub fn ensure_font() -> bool {
    static FONT: OnceLock<bool> = OnceLock::new();
    *FONT.get_or_init(|| {
        for p in FONT_CANDIDATES {
            if let Ok(bytes) = std::fs::read(p) {
                let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
                if plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok() {
                    return true;
                }
            }
        }
        eprintln!("warning: no TrueType font found ({}…): plots are drawn without text", FONT_CANDIDATES[0]);
        false
    })
}

/// Summary columns after `id, name, scene, seed, <grid keys…>`.
const COLUMNS: &[&str] = &[
    "field",
    "iterations",
    "wall_seconds",
    "ms_per_iter",
    "samples_per_sec",
    "n_params",
    "peak_memory_mib",
    "test_psnr",
    "test_ssim",
];

fn scene_name(m: &RunMetrics) -> String {
    Path::new(&m.scene).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| m.scene.clone())
}

fn grid_cell(m: &RunMetrics, k: &str) -> String {
    m.grid.get(k).map(value_label).unwrap_or_default()
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// `results.csv`: one row per run, full-precision numbers, empty cells for unknown memory.
pub fn results_csv(runs: &[RunMetrics], grid_keys: &[String]) -> String {
    let mut header: Vec<String> = ["id", "name", "scene", "seed"].iter().map(|s| s.to_string()).collect();
    header.extend(grid_keys.iter().cloned());
    header.extend(COLUMNS.iter().map(|s| s.to_string()));
    let mut out = header.iter().map(|h| csv_field(h)).collect::<Vec<_>>().join(",") + "\n";
    for m in runs {
        let mut row = vec![m.id.clone(), m.name.clone(), scene_name(m), m.seed.to_string()];
        row.extend(grid_keys.iter().map(|k| grid_cell(m, k)));
        row.extend([
            m.field.clone(),
            m.iterations.to_string(),
            m.wall_seconds.to_string(),
            m.ms_per_iter.to_string(),
            m.samples_per_sec.to_string(),
            m.n_params.to_string(),
            m.peak_memory_mib.map(|x| x.to_string()).unwrap_or_default(),
            m.test_psnr.to_string(),
            m.test_ssim.to_string(),
        ]);
        out += &(row.iter().map(|c| csv_field(c)).collect::<Vec<_>>().join(",") + "\n");
    }
    out
}

/// `results.md`: a markdown table of the same columns (PSNR 2, SSIM 4 decimals).
pub fn results_md(title: &str, runs: &[RunMetrics], grid_keys: &[String]) -> String {
    let esc = |s: &str| s.replace('|', "\\|");
    let mut header: Vec<String> = ["run", "scene", "seed"].iter().map(|s| s.to_string()).collect();
    header.extend(grid_keys.iter().map(|k| format!("`{}`", esc(k))));
    header.extend(
        ["field", "iters", "wall s", "ms/iter", "samples/s", "params", "peak MiB", "test PSNR", "test SSIM"]
            .iter()
            .map(|s| s.to_string()),
    );
    let mut out = format!("# Ablation: {}\n\n", esc(title));
    out += &format!("| {} |\n", header.join(" | "));
    out += &format!("|{}\n", header.iter().map(|_| "---|").collect::<String>());
    for m in runs {
        let mut row = vec![esc(&m.name), esc(&scene_name(m)), m.seed.to_string()];
        row.extend(grid_keys.iter().map(|k| esc(&grid_cell(m, k))));
        row.extend([
            esc(&m.field),
            m.iterations.to_string(),
            format!("{:.1}", m.wall_seconds),
            format!("{:.2}", m.ms_per_iter),
            format!("{:.0}", m.samples_per_sec),
            m.n_params.to_string(),
            m.peak_memory_mib.map(|x| format!("{x:.0}")).unwrap_or_else(|| "–".into()),
            format!("{:.2}", m.test_psnr),
            format!("{:.4}", m.test_ssim),
        ]);
        out += &format!("| {} |\n", row.join(" | "));
    }
    out
}

/// Draws PSNR curves (one line per run) against `x` into a PNG at `path`.
pub fn plot_curves(
    path: &Path,
    runs: &[RunMetrics],
    x_label: &str,
    x: impl Fn(&crate::CurvePoint) -> f64,
) -> Result<(), AblateError> {
    let perr = |e: &dyn std::fmt::Display| AblateError::Plot { path: path.to_path_buf(), message: e.to_string() };
    let text = ensure_font();
    let pts = runs.iter().flat_map(|m| m.curve.iter());
    let (mut x1, mut y0, mut y1) = (0.0f64, f64::INFINITY, f64::NEG_INFINITY);
    for p in pts {
        x1 = x1.max(x(p));
        if p.psnr.is_finite() {
            y0 = y0.min(p.psnr);
            y1 = y1.max(p.psnr);
        }
    }
    if !y0.is_finite() {
        (y0, y1) = (0.0, 1.0);
    }
    let x1 = if x1 > 0.0 { x1 * 1.02 } else { 1.0 };
    let pad = ((y1 - y0) * 0.05).max(0.25);
    {
        let root = BitMapBackend::new(path, (1000, 640)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| perr(&e))?;
        let mut b = ChartBuilder::on(&root);
        b.margin(16);
        if text {
            b.caption(format!("test PSNR vs {x_label}"), ("sans-serif", 24)).x_label_area_size(44).y_label_area_size(60);
        } else {
            b.x_label_area_size(8).y_label_area_size(8);
        }
        let mut chart = b.build_cartesian_2d(0.0..x1, (y0 - pad)..(y1 + pad)).map_err(|e| perr(&e))?;
        let mut mesh = chart.configure_mesh();
        if text {
            mesh.x_desc(x_label).y_desc("test PSNR (dB)").label_style(("sans-serif", 15));
        } else {
            mesh.x_labels(0).y_labels(0);
        }
        mesh.draw().map_err(|e| perr(&e))?;
        for (i, m) in runs.iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            // Markers at the evaluation points (a one-point curve is still visible).
            chart
                .draw_series(m.curve.iter().map(|p| Circle::new((x(p), p.psnr), 4, color.filled())))
                .map_err(|e| perr(&e))?;
            let series = LineSeries::new(m.curve.iter().map(|p| (x(p), p.psnr)), color.stroke_width(2));
            let ann = chart.draw_series(series).map_err(|e| perr(&e))?;
            if text {
                ann.label(m.id.clone())
                    .legend(move |(a, b)| PathElement::new(vec![(a, b), (a + 20, b)], color.stroke_width(2)));
            }
        }
        if text {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .label_font(("sans-serif", 13))
                .position(SeriesLabelPosition::LowerRight)
                .draw()
                .map_err(|e| perr(&e))?;
        }
        root.present().map_err(|e| perr(&e))?;
    }
    Ok(())
}

/// Rebuilds every summary file under `out` from `outcomes`.
pub(crate) fn write_summary(
    out: &Path,
    title: &str,
    grid_keys: &[String],
    outcomes: Vec<RunOutcome>,
    diverged: Vec<(String, u64)>,
) -> Result<AblationReport, AblateError> {
    std::fs::create_dir_all(out).map_err(io_err(out))?;
    let runs: Vec<RunMetrics> = outcomes.iter().map(|o| o.metrics.clone()).collect();
    let p = |n: &str| -> PathBuf { out.join(n) };
    let (csv, md, pt, pi) = (p("results.csv"), p("results.md"), p("psnr_vs_time.png"), p("psnr_vs_iter.png"));
    write_atomic(&csv, results_csv(&runs, grid_keys).as_bytes())?;
    let mut text = results_md(title, &runs, grid_keys);
    if !diverged.is_empty() {
        text.push_str("\nDiverged (the loss turned NaN or infinite; left out above):\n\n");
        for (id, step) in &diverged {
            text.push_str(&format!("- {id}: after step {step}\n"));
        }
    }
    let fitted: Vec<&RunMetrics> = runs.iter().filter(|r| r.device_note.is_some()).collect();
    if !fitted.is_empty() {
        text.push_str("\nFitted to the adapter (trained with fewer samples per step than configured):\n\n");
        for r in fitted {
            text.push_str(&format!("- {}: {}\n", r.id, r.device_note.as_deref().unwrap_or_default()));
        }
    }
    write_atomic(&md, text.as_bytes())?;
    plot_curves(&pt, &runs, "training time (s)", |q| q.seconds)?;
    plot_curves(&pi, &runs, "iteration", |q| q.iter as f64)?;
    Ok(AblationReport {
        out_dir: out.to_path_buf(),
        runs: outcomes,
        results_csv: csv,
        results_md: md,
        psnr_vs_time: pt,
        psnr_vs_iter: pi,
        diverged,
    })
}

/// Reads a PNG (e.g. a plot written here) as 8-bit RGB: `(width, height, pixels)`.
pub fn read_png_rgb(path: &Path) -> Result<(u32, u32, Vec<u8>), AblateError> {
    let img = image::open(path)
        .map_err(|e| AblateError::Plot { path: path.to_path_buf(), message: format!("cannot decode: {e}") })?
        .to_rgb8();
    Ok((img.width(), img.height(), img.into_raw()))
}
