//! Rendering in rounds with the occupancy grid on the CPU — the twin of the GPU's `round_*`
//! kernels (`shaders/march.wgsl`): every ray starts alive; a round marches each alive ray's next
//! few steps ([`RayMarch::advance`]), evaluates the field on those samples in one batch,
//! composites them into the ray's running colour, transmittance, opacity and depth
//! ([`nerf_render::RayComposite`], the per-ray step of `composite_forward`), and drops
//! the rays whose transmittance fell below the threshold or whose march ended. The samples, their
//! order and the arithmetic are those of [`nerf_sampling::march`] followed by
//! [`nerf_render::composite_forward`], so the image is the same bit for bit; the samples behind
//! opaque surfaces are never evaluated.

use nerf_render::RayComposite;
use nerf_sampling::{OccupancyGrid, RayMarch, Stepping};

/// Steps per alive ray and round: about `ROUND_SAMPLES_PER_RAY × rays` samples per round (at
/// least [`MIN_STEPS`], at most [`MAX_STEPS`] per ray: more per ray once most rays have stopped,
/// so late rounds still evaluate the field in large batches).
const ROUND_SAMPLES_PER_RAY: usize = 4;
const MIN_STEPS: usize = 4;
const MAX_STEPS: usize = 16;

/// The sampler's marching parameters.
#[derive(Clone, Copy, Debug)]
pub(crate) struct MarchParams {
    pub step: Stepping,
    pub max_samples: usize,
    pub near: f32,
    pub far: f32,
    pub t_threshold: f32,
    /// The render crop box: marches clipped to it.
    pub crop: Option<nerf_sampling::CropBox>,
}

struct RayState {
    march: RayMarch,
    comp: RayComposite<f32>,
}

/// Reusable buffers of [`render_in_rounds`].
#[derive(Default)]
pub(crate) struct RoundScratch {
    states: Vec<RayState>,
    alive: Vec<u32>,
    /// Per alive ray of the round: its sample range end.
    ends: Vec<usize>,
    t: Vec<f32>,
    positions: Vec<f32>,
    dirs: Vec<f32>,
    sigma: Vec<f32>,
    rgb: Vec<f32>,
    /// Samples evaluated by the last call.
    pub evaluated: usize,
}

/// Renders rays (`origins`, `dirs`: `3·n`, unit directions; `background`: `3·n`) through `grid`
/// in rounds, `query(positions, dirs, sigma, rgb)` evaluating the field; writes `rgb` (`3·n`, with
/// `(1 − opacity)·background`), `opacity` and `depth` (`n`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn render_in_rounds(
    grid: &OccupancyGrid,
    p: MarchParams,
    origins: &[f32],
    dirs: &[f32],
    background: &[f32],
    s: &mut RoundScratch,
    mut query: impl FnMut(&[f32], &[f32], &mut [f32], &mut [f32]),
    rgb: &mut [f32],
    opacity: &mut [f32],
    depth: &mut [f32],
) {
    let n = origins.len() / 3;
    s.states.clear();
    s.states.extend((0..n).map(|r| RayState {
        march: RayMarch::cropped(grid, ray3(origins, r), ray3(dirs, r), p.near, p.far, p.crop.as_ref()),
        comp: RayComposite::default(),
    }));
    s.alive.clear();
    s.alive.extend((0..n as u32).filter(|&r| !s.states[r as usize].march.is_done()));
    s.evaluated = 0;
    while !s.alive.is_empty() {
        let k = (ROUND_SAMPLES_PER_RAY * n / s.alive.len()).clamp(MIN_STEPS, MAX_STEPS);
        // March: each alive ray's next ≤ k samples, packed ray after ray.
        s.t.clear();
        s.ends.clear();
        for &r in &s.alive {
            let st = &mut s.states[r as usize];
            let t = &mut s.t;
            st.march.advance(grid, p.step, p.max_samples, k, |x| t.push(x));
            s.ends.push(s.t.len());
        }
        let m = s.t.len();
        s.positions.clear();
        s.dirs.clear();
        let mut start = 0;
        for (&r, &end) in s.alive.iter().zip(&s.ends) {
            let (o, d) = (ray3(origins, r as usize), ray3(dirs, r as usize));
            for &t in &s.t[start..end] {
                for c in 0..3 {
                    s.positions.push(o[c] + t * d[c]);
                    s.dirs.push(d[c]);
                }
            }
            start = end;
        }
        s.sigma.clear();
        s.sigma.resize(m, 0.0);
        s.rgb.clear();
        s.rgb.resize(3 * m, 0.0);
        if m > 0 {
            query(&s.positions, &s.dirs, &mut s.sigma, &mut s.rgb);
        }
        s.evaluated += m;
        // Composite (nerf_render::composite_forward's arithmetic, resumed) and drop finished rays.
        let mut start = 0;
        let mut keep = 0;
        for i in 0..s.alive.len() {
            let (r, end) = (s.alive[i], s.ends[i]);
            let st = &mut s.states[r as usize];
            for j in start..end {
                if st.comp.stopped(p.t_threshold) {
                    break;
                }
                st.comp.add(s.sigma[j], ray3(&s.rgb, j), p.step.dt(s.t[j]), s.t[j]);
            }
            start = end;
            if !(st.comp.stopped(p.t_threshold) || st.march.is_done()) {
                s.alive[keep] = r;
                keep += 1;
            }
        }
        s.alive.truncate(keep);
    }
    for (r, st) in s.states.iter().enumerate() {
        rgb[3 * r..3 * r + 3].copy_from_slice(&st.comp.color(ray3(background, r)));
        opacity[r] = st.comp.opacity;
        depth[r] = st.comp.depth;
    }
}

fn ray3(v: &[f32], r: usize) -> [f32; 3] {
    [v[3 * r], v[3 * r + 1], v[3 * r + 2]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use nerf_render::{composite_forward, CompositeOutputs};
    use nerf_sampling::{march, OccupancyGridConfig, RaySamples};
    use rand::Rng as _;

    /// A field: a soft ball of density with position-dependent colours.
    fn field(p: &[f32], _d: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
        for k in 0..sigma.len() {
            let q = [p[3 * k] - 0.2, p[3 * k + 1] + 0.1, p[3 * k + 2]];
            sigma[k] = 400.0 * (0.7 - (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt()).max(0.0);
            for c in 0..3 {
                rgb[3 * k + c] = (p[3 * k + c] * (3.0 + c as f32)).sin() * 0.5 + 0.5;
            }
        }
    }

    #[test]
    fn rounds_render_exactly_what_marching_everything_renders() {
        let (lo, hi) = ([-1.5f32; 3], [1.5f32; 3]);
        let mut grid = OccupancyGrid::new(OccupancyGridConfig { resolution: 32, ..Default::default() }, lo, hi);
        grid.fill_from(0.01, &mut |p, s| {
            for (k, s) in s.iter_mut().enumerate() {
                let q = &p[3 * k..3 * k + 3];
                // The ball, plus a shell of occupied cells with no density (samples that cost work).
                let r = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
                *s = if r < 1.0 || (1.2..1.3).contains(&r) { 50.0 } else { 0.0 };
            }
        });
        let n = 1500;
        let mut rng = nerf_core::rng(5, 0);
        let (mut o, mut d, mut bg) = (vec![], vec![], vec![]);
        for _ in 0..n {
            let orig: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.0f32..1.0));
            let l = orig.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-3);
            let orig = orig.map(|x| x / l * 3.5);
            let target: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.6f32..1.6));
            let dir: [f32; 3] = std::array::from_fn(|a| target[a] - orig[a]);
            let l = dir.iter().map(|x| x * x).sum::<f32>().sqrt();
            o.extend(orig);
            d.extend(dir.map(|x| x / l));
            bg.extend([rng.gen::<f32>(), rng.gen(), rng.gen()]);
        }
        for (t_threshold, max_samples, step) in [(1e-4f32, 1024usize, 0.01f32), (0.0, 1024, 0.01), (1e-2, 7, 0.02)] {
            let p = MarchParams { step: step.into(), max_samples, near: 0.5, far: 8.0, t_threshold, crop: None };
            // Reference: march everything, evaluate everything, composite.
            let mut all = RaySamples::default();
            march(&grid, &o, &d, &vec![p.near; n], &vec![p.far; n], step, max_samples, None, &mut all);
            let m = all.len();
            let (mut s_all, mut c_all) = (vec![0.0; m], vec![0.0; 3 * m]);
            field(&all.positions, &all.dirs, &mut s_all, &mut c_all);
            let mut reference = CompositeOutputs::default();
            composite_forward(&all.ray_offsets, &s_all, &c_all, &all.dt, &all.t, Some(&bg), t_threshold, &mut reference);
            // Rounds.
            let mut scratch = RoundScratch::default();
            let (mut rgb, mut op, mut dep) = (vec![f32::NAN; 3 * n], vec![f32::NAN; n], vec![f32::NAN; n]);
            render_in_rounds(&grid, p, &o, &d, &bg, &mut scratch, field, &mut rgb, &mut op, &mut dep);
            let what = format!("threshold {t_threshold}, max {max_samples}");
            assert_eq!(rgb, reference.rgb, "{what}: rgb");
            assert_eq!(op, reference.opacity, "{what}: opacity");
            assert_eq!(dep, reference.depth, "{what}: depth");
            let opaque = op.iter().filter(|&&x| x > 0.99).count();
            if t_threshold == 0.0 {
                assert_eq!(scratch.evaluated, m, "{what}: every sample evaluated without a threshold");
            } else if max_samples > 100 {
                assert!(opaque > n / 10, "{what}: only {opaque} opaque rays");
                eprintln!("{what}: {} of {m} samples evaluated", scratch.evaluated);
                assert!(scratch.evaluated < m * 3 / 4, "{what}: {} of {m} samples evaluated", scratch.evaluated);
            }
        }
    }
}
