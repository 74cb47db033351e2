//! The trainer's side of the per-view colour correction (`TrainConfig::color_correction`,
//! `nerf_render::color_correct_forward`): the corrections and their Adam state on the CPU, and
//! how both devices store them in checkpoints (named tensors beside the sampler state, as the
//! moving average is).

use crate::TrainError;
use nerf_optim::{Adam, AdamConfig, AdamState, ParamGroupMut};
use nerf_render::{identity_color_correction, COLOR_PARAMS_PER_VIEW};

/// Name of the corrections' Adam group (in [`AdamState`]s; not in the fields' optimiser).
pub const COLOR_GROUP: &str = "color_correction";
/// Prefix of the corrections' entries in [`Trainer::sampler_state`](crate::Trainer::sampler_state):
/// `color/params` (12 values per training view), `color/m`, `color/v` (Adam's moments) and
/// `color/step` (Adam's step count as `[count mod 2^24, count / 2^24]`).
pub const COLOR_PREFIX: &str = "color/";

/// The corrections and their optimiser state, as a checkpoint holds them.
#[derive(Clone, Debug, PartialEq)]
pub struct ColorState {
    /// `12·n_views` values (see `nerf_render::COLOR_PARAMS_PER_VIEW`).
    pub params: Vec<f32>,
    /// Adam's state of the single group [`COLOR_GROUP`] (no groups before the first step).
    pub adam: AdamState,
}

impl ColorState {
    /// Views the corrections are for.
    pub fn n_views(&self) -> usize {
        self.params.len() / COLOR_PARAMS_PER_VIEW
    }

    /// The state as named tensors (see [`COLOR_PREFIX`]).
    pub fn to_entries(&self) -> Vec<(String, Vec<f32>)> {
        let s = self.adam.step;
        let mut v = vec![
            (format!("{COLOR_PREFIX}params"), self.params.clone()),
            (format!("{COLOR_PREFIX}step"), vec![(s & 0xFF_FFFF) as f32, (s >> 24) as f32]),
        ];
        if let Some((_, m, vv)) = self.adam.groups.iter().find(|(n, _, _)| n == COLOR_GROUP) {
            v.push((format!("{COLOR_PREFIX}m"), m.clone()));
            v.push((format!("{COLOR_PREFIX}v"), vv.clone()));
        }
        v
    }

    /// Splits the corrections ([`ColorState::to_entries`]) off a list of state tensors:
    /// `(corrections if present, the other tensors)`. Errors on a partial or malformed set.
    #[allow(clippy::type_complexity)]
    pub fn from_entries(state: &[(String, Vec<f32>)]) -> Result<(Option<Self>, Vec<(String, Vec<f32>)>), TrainError> {
        let bad = |m: String| TrainError::Config(format!("colour correction in checkpoint: {m}"));
        let (mine, rest): (Vec<_>, Vec<_>) = state.iter().cloned().partition(|(n, _)| n.starts_with(COLOR_PREFIX));
        if mine.is_empty() {
            return Ok((None, rest));
        }
        let get = |k: &str| mine.iter().find(|(n, _)| n.strip_prefix(COLOR_PREFIX) == Some(k)).map(|(_, v)| v.clone());
        if let Some((n, _)) = mine.iter().find(|(n, _)| !matches!(n.strip_prefix(COLOR_PREFIX), Some("params" | "step" | "m" | "v"))) {
            return Err(bad(format!("unknown entry `{n}`")));
        }
        let params = get("params").ok_or_else(|| bad("no `color/params`".into()))?;
        if params.is_empty() || params.len() % COLOR_PARAMS_PER_VIEW != 0 || params.iter().any(|x| !x.is_finite()) {
            return Err(bad(format!("`color/params` must be finite values, {COLOR_PARAMS_PER_VIEW} per view, got {}", params.len())));
        }
        let step = match get("step").as_deref() {
            Some(&[lo, hi]) if lo >= 0.0 && hi >= 0.0 && lo.fract() == 0.0 && hi.fract() == 0.0 && lo < 16_777_216.0 => {
                lo as u64 | (hi as u64) << 24
            }
            other => return Err(bad(format!("malformed `color/step` {other:?}"))),
        };
        let groups = match (get("m"), get("v")) {
            (Some(m), Some(v)) if m.len() == params.len() && v.len() == params.len() => vec![(COLOR_GROUP.to_string(), m, v)],
            (None, None) if step == 0 => Vec::new(),
            _ => return Err(bad("`color/m` and `color/v` must both be there, one value per parameter, once a step was taken".into())),
        };
        Ok((Some(Self { params, adam: AdamState { step, groups, steps: Vec::new() } }), rest))
    }
}

/// The CPU path's corrections: parameters, gradients, Adam, and the per-step buffers.
pub(crate) struct CpuColor {
    pub params: Vec<f32>,
    pub grads: Vec<f32>,
    pub adam: Adam,
    pub lr: f32,
    /// Corrected pixels (`3·n_rays`), and what compositing's backward gets.
    pub out: Vec<f32>,
    pub d_rgb: Vec<f32>,
    pub d_opacity: Vec<f32>,
}

impl CpuColor {
    pub fn new(n_views: usize, adam: &AdamConfig, lr: f32) -> Self {
        let params = identity_color_correction(n_views);
        let cfg = AdamConfig { sparse_groups: Vec::new(), ..adam.clone() };
        Self { grads: vec![0.0; params.len()], params, adam: Adam::new(cfg), lr, out: Vec::new(), d_rgb: Vec::new(), d_opacity: Vec::new() }
    }

    pub fn state(&self) -> ColorState {
        ColorState { params: self.params.clone(), adam: self.adam.state() }
    }

    /// Takes the checkpoint's corrections, for however many views they are (a trainer built on
    /// the test views renders with their mean; a training step checks the count).
    pub fn load(&mut self, s: ColorState) -> Result<(), TrainError> {
        self.grads = vec![0.0; s.params.len()];
        self.params = s.params;
        self.adam = Adam::new(self.adam.config().clone());
        self.adam.load_state(s.adam).map_err(TrainError::Config)
    }

    pub fn n_views(&self) -> usize {
        self.params.len() / COLOR_PARAMS_PER_VIEW
    }

    /// One Adam step on the gradients gathered this step; zeroes them for the next.
    pub fn step(&mut self) {
        let mut g = [ParamGroupMut { name: COLOR_GROUP, params: &mut self.params, grads: &mut self.grads, weight_decay: 0.0 }];
        self.adam.step(&mut g, self.lr);
        self.grads.fill(0.0);
    }
}

/// Errors unless a training dataset has as many views as there are corrections.
pub(crate) fn check_views(corrections: usize, dataset: usize) -> Result<(), TrainError> {
    if corrections != dataset {
        return Err(TrainError::Config(format!(
            "the run's colour correction is for {corrections} training views; this dataset has {dataset} \
             (train on the views it was set up for)"
        )));
    }
    Ok(())
}
