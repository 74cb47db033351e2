//! Parameters the trainer learns per training view beside the field — the colour corrections
//! (`color_correction`) and the camera pose corrections (`camera_optimizer`) — with their own
//! Adam, and how checkpoints store them: named tensors beside the sampler state (as the moving
//! average is), `PREFIX/params` (the values, a fixed number per view), `PREFIX/m`, `PREFIX/v`
//! (Adam's moments) and `PREFIX/step` (Adam's step count as `[count mod 2^24, count / 2^24]`).

use crate::TrainError;
use nerf_optim::{Adam, AdamConfig, AdamState, ParamGroupMut};

/// One kind of per-view parameters: its name in checkpoints and the optimiser, and its size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ViewKind {
    /// Entry prefix in [`Trainer::sampler_state`](crate::Trainer::sampler_state) (`"color/"`).
    pub prefix: &'static str,
    /// Name of its Adam group (in [`AdamState`]s; not in the fields' optimiser).
    pub group: &'static str,
    /// Values per view.
    pub per_view: usize,
    /// What it is, for messages (`"colour correction"`).
    pub what: &'static str,
}

/// Per-view parameters and their optimiser state, as a checkpoint holds them.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewState {
    /// `per_view · n_views` values.
    pub params: Vec<f32>,
    /// Adam's state of the kind's single group (no groups before the first step).
    pub adam: AdamState,
}

impl ViewState {
    /// Views the values are for.
    pub fn n_views(&self, kind: &ViewKind) -> usize {
        self.params.len() / kind.per_view
    }

    /// The state as named tensors (see the module's documentation).
    pub fn to_entries(&self, kind: &ViewKind) -> Vec<(String, Vec<f32>)> {
        let (p, s) = (kind.prefix, self.adam.step);
        let mut v = vec![(format!("{p}params"), self.params.clone()), (format!("{p}step"), vec![(s & 0xFF_FFFF) as f32, (s >> 24) as f32])];
        if let Some((_, m, vv)) = self.adam.groups.iter().find(|(n, _, _)| n == kind.group) {
            v.push((format!("{p}m"), m.clone()));
            v.push((format!("{p}v"), vv.clone()));
        }
        v
    }

    /// Splits the kind's entries ([`ViewState::to_entries`]) off a list of state tensors:
    /// `(the state if present, the other tensors)`. Errors on a partial or malformed set.
    #[allow(clippy::type_complexity)]
    pub fn from_entries(state: &[(String, Vec<f32>)], kind: &ViewKind) -> Result<(Option<Self>, Vec<(String, Vec<f32>)>), TrainError> {
        let (p, per_view) = (kind.prefix, kind.per_view);
        let bad = |m: String| TrainError::Config(format!("{} in checkpoint: {m}", kind.what));
        let (mine, rest): (Vec<_>, Vec<_>) = state.iter().cloned().partition(|(n, _)| n.starts_with(p));
        if mine.is_empty() {
            return Ok((None, rest));
        }
        let get = |k: &str| mine.iter().find(|(n, _)| n.strip_prefix(p) == Some(k)).map(|(_, v)| v.clone());
        if let Some((n, _)) = mine.iter().find(|(n, _)| !matches!(n.strip_prefix(p), Some("params" | "step" | "m" | "v"))) {
            return Err(bad(format!("unknown entry `{n}`")));
        }
        let params = get("params").ok_or_else(|| bad(format!("no `{p}params`")))?;
        if params.is_empty() || params.len() % per_view != 0 || params.iter().any(|x| !x.is_finite()) {
            return Err(bad(format!("`{p}params` must be finite values, {per_view} per view, got {}", params.len())));
        }
        let step = match get("step").as_deref() {
            Some(&[lo, hi]) if lo >= 0.0 && hi >= 0.0 && lo.fract() == 0.0 && hi.fract() == 0.0 && lo < 16_777_216.0 => {
                lo as u64 | (hi as u64) << 24
            }
            other => return Err(bad(format!("malformed `{p}step` {other:?}"))),
        };
        let groups = match (get("m"), get("v")) {
            (Some(m), Some(v)) if m.len() == params.len() && v.len() == params.len() => vec![(kind.group.to_string(), m, v)],
            (None, None) if step == 0 => Vec::new(),
            _ => return Err(bad(format!("`{p}m` and `{p}v` must both be there, one value per parameter, once a step was taken"))),
        };
        Ok((Some(Self { params, adam: AdamState { step, groups, steps: Vec::new() } }), rest))
    }
}

/// The CPU path's per-view parameters: values, gradients and Adam.
pub(crate) struct CpuViews {
    pub kind: ViewKind,
    pub params: Vec<f32>,
    pub grads: Vec<f32>,
    pub adam: Adam,
}

impl CpuViews {
    /// Starts from `params` (whole views of `kind`); Adam as the fields' but dense.
    pub fn new(kind: ViewKind, params: Vec<f32>, adam: &AdamConfig) -> Self {
        let cfg = AdamConfig { sparse_groups: Vec::new(), ..adam.clone() };
        Self { kind, grads: vec![0.0; params.len()], params, adam: Adam::new(cfg) }
    }

    pub fn state(&self) -> ViewState {
        ViewState { params: self.params.clone(), adam: self.adam.state() }
    }

    /// Takes the checkpoint's values, for however many views they are (a trainer built on the
    /// test views renders with them; a training step checks the count).
    pub fn load(&mut self, s: ViewState) -> Result<(), TrainError> {
        self.grads = vec![0.0; s.params.len()];
        self.params = s.params;
        self.adam = Adam::new(self.adam.config().clone());
        self.adam.load_state(s.adam).map_err(TrainError::Config)
    }

    pub fn n_views(&self) -> usize {
        self.params.len() / self.kind.per_view
    }

    /// One Adam step at `lr` on the gradients gathered this step; zeroes them for the next.
    pub fn step(&mut self, lr: f32) {
        let mut g = [ParamGroupMut { name: self.kind.group, params: &mut self.params, grads: &mut self.grads, weight_decay: 0.0 }];
        self.adam.step(&mut g, lr);
        self.grads.fill(0.0);
    }
}

/// Errors unless a training dataset has as many views as there are per-view parameters.
pub(crate) fn check_views(kind: &ViewKind, learnt: usize, dataset: usize) -> Result<(), TrainError> {
    if learnt != dataset {
        return Err(TrainError::Config(format!(
            "the run's {} is for {learnt} training views; this dataset has {dataset} \
             (train on the views it was set up for)",
            kind.what
        )));
    }
    Ok(())
}
