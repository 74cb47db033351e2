//! Optimisers and learning-rate schedules: Adam over named parameter groups with per-group weight decay.
//!
//! A field hands the optimiser its parameters as a list of [`ParamGroupMut`]s (flat `f32` buffers
//! with their gradients, a name and an L2 weight decay). [`Adam`] keeps its moment estimates per
//! group, keyed by the group's name and length, creates them on first use, and can export and import
//! them ([`AdamState`]) for checkpoints. [`LrSchedule`] gives the learning rate of each step.
//! [`Ema`] keeps an exponential moving average of the parameters (tiny-cuda-nn's `Ema` optimiser
//! wrapper, which instant-ngp renders with), updated after every optimiser step.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// A named, flat parameter group handed to the optimiser by a field.
pub struct ParamGroupMut<'a> {
    /// Name of the group (the key of the optimiser state, e.g. `"mlp.weights"`).
    pub name: &'a str,
    /// The parameters, updated in place by [`Adam::step`].
    pub params: &'a mut [f32],
    /// dL/d(params), same length as `params`. Read, never modified, by [`Adam::step`] (zero them yourself).
    pub grads: &'a mut [f32],
    /// L2 weight decay: `wd·p` is added to the gradient before the moment updates (torch `Adam(weight_decay=…)`).
    pub weight_decay: f32,
}

/// Hyper-parameters of [`Adam`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    /// Decay rate of the first-moment estimate.
    pub beta1: f32,
    /// Decay rate of the second-moment estimate.
    pub beta2: f32,
    /// Added to `sqrt(v̂)` in the denominator.
    pub eps: f32,
    /// Names of the parameter groups updated *sparsely*, as tiny-cuda-nn's Adam updates its
    /// "non-matrix" parameters (instant-ngp's hash tables): an entry whose gradient is exactly zero
    /// in a step is skipped — parameter, moments and its own step count unchanged — and the bias
    /// correction of an entry uses its own step count (the number of steps in which it had a
    /// gradient). Groups are named as [`AdamConfig::is_sparse`] says. Empty (the default): every
    /// group is dense.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sparse_groups: Vec<String>,
}

impl Default for AdamConfig {
    /// The NeRF paper's settings: β = (0.9, 0.999), ε = 1e-7.
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-7,
            sparse_groups: Vec::new(),
        }
    }
}

impl AdamConfig {
    /// Instant-NGP's settings: β = (0.9, 0.99), ε = 1e-15.
    pub fn instant_ngp() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-15,
            sparse_groups: Vec::new(),
        }
    }

    /// Whether group `name` is updated sparsely (see [`AdamConfig::sparse_groups`]): an entry of
    /// `sparse_groups` names a group by its full name (`field/hash_grid`, `fine/hash_grid`) or by
    /// the part after the last `/` (the field's own group name, `hash_grid`).
    pub fn is_sparse(&self, name: &str) -> bool {
        self.sparse_groups.iter().any(|g| names_group(g, name))
    }
}

/// Whether `entry` (of [`AdamConfig::sparse_groups`]) names the parameter group `name`: by its full
/// name (`field/hash_grid`) or by the part after the last `/` (`hash_grid`).
pub fn names_group(entry: &str, name: &str) -> bool {
    entry == name || name.rsplit('/').next() == Some(entry)
}

/// Moment estimates of one parameter group.
#[derive(Clone, Debug)]
struct GroupState {
    name: String,
    m: Vec<f32>,
    v: Vec<f32>,
    /// Per-entry step counts of a sparse group (empty for a dense one).
    steps: Vec<u32>,
}

/// Adam with bias correction and L2 weight decay added to the gradient (g += wd·p, as torch Adam weight_decay).
/// State (m, v per group, keyed by group name and length; step count) is created on first use and can be
/// exported/imported for checkpoints.
///
/// The bias correction of a dense group uses one step count shared by all groups (the number of
/// [`Adam::step`] calls), so every group is expected to take part in every step; a sparse group
/// ([`AdamConfig::sparse_groups`]) counts steps per entry. A group whose name is known but whose
/// length changed gets fresh (zero) moments.
#[derive(Clone, Debug)]
pub struct Adam {
    cfg: AdamConfig,
    step: u64,
    groups: Vec<GroupState>,
    /// `(1 − β1^t, 1/sqrt(1 − β2^t))` for t = 1, 2, … (f64, as the dense update computes them),
    /// extended one entry per step: the bias corrections of sparse entries with their own counts.
    bias: Vec<(f64, f64)>,
}

/// Exported optimiser state for checkpoints: the step count and `(name, m, v)` per group.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamState {
    /// Number of steps taken.
    pub step: u64,
    /// `(group name, first moments, second moments)`.
    pub groups: Vec<(String, Vec<f32>, Vec<f32>)>,
    /// `(group name, per-entry step counts)` of the sparse groups ([`AdamConfig::sparse_groups`]).
    /// A sparse group missing here (a state written by a dense run) counts every entry as having
    /// taken all `step` steps, which is what its moments went through.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub steps: Vec<(String, Vec<u32>)>,
}

/// Groups longer than this are updated in parallel chunks of this many elements.
const PAR_CHUNK: usize = 1 << 14;

impl Adam {
    /// A new optimiser with no state yet (step count 0).
    pub fn new(cfg: AdamConfig) -> Self {
        Self {
            cfg,
            step: 0,
            groups: Vec::new(),
            bias: Vec::new(),
        }
    }

    /// The hyper-parameters.
    pub fn config(&self) -> &AdamConfig {
        &self.cfg
    }

    /// Takes one step with learning rate `lr` on every group: increments the step count, then for each
    /// element `g = grad + wd·p; m = β1·m + (1−β1)·g; v = β2·v + (1−β2)·g²;
    /// p −= lr·(m/(1−β1^t)) / (sqrt(v/(1−β2^t)) + ε)` (torch's formulation). In a sparse group an
    /// element whose gradient is exactly zero is skipped and `t` is the element's own step count.
    /// Parallel over chunks for large groups; allocation-free once every group has state (the
    /// bias-correction table grows by one entry per step).
    ///
    /// Panics if a group's `params` and `grads` lengths differ (programmer error).
    pub fn step(&mut self, groups: &mut [ParamGroupMut<'_>], lr: f32) {
        self.step += 1;
        let (b1, b2, eps) = (self.cfg.beta1, self.cfg.beta2, self.cfg.eps);
        while (self.bias.len() as u64) < self.step {
            let t = (self.bias.len() + 1) as f64;
            self.bias.push((1.0 - (b1 as f64).powf(t), 1.0 / (1.0 - (b2 as f64).powf(t)).sqrt()));
        }
        let (bc1, inv_sqrt_bc2) = self.bias[self.step as usize - 1];
        let step_size = (lr as f64 / bc1) as f32;
        let inv_sqrt_bc2 = inv_sqrt_bc2 as f32;
        let bias = &self.bias;
        for g in groups.iter_mut() {
            assert_eq!(
                g.params.len(),
                g.grads.len(),
                "Adam: group {:?} has {} params but {} grads",
                g.name,
                g.params.len(),
                g.grads.len()
            );
            let sparse = self.cfg.is_sparse(g.name);
            let idx = state_index(&mut self.groups, self.step - 1, sparse, g.name, g.params.len());
            let st = &mut self.groups[idx];
            let wd = g.weight_decay;
            if sparse {
                let sparse_kernel = |p: &mut [f32], gr: &[f32], m: &mut [f32], v: &mut [f32], n: &mut [u32]| {
                    for i in 0..p.len() {
                        if gr[i] == 0.0 {
                            continue;
                        }
                        n[i] += 1;
                        let (bc1, ib2) = bias[n[i] as usize - 1];
                        let gi = gr[i] + wd * p[i];
                        let mi = b1 * m[i] + (1.0 - b1) * gi;
                        let vi = b2 * v[i] + (1.0 - b2) * gi * gi;
                        m[i] = mi;
                        v[i] = vi;
                        p[i] -= (lr as f64 / bc1) as f32 * mi / (vi.sqrt() * ib2 as f32 + eps);
                    }
                };
                if g.params.len() > PAR_CHUNK {
                    g.params
                        .par_chunks_mut(PAR_CHUNK)
                        .zip(g.grads.par_chunks(PAR_CHUNK))
                        .zip(st.m.par_chunks_mut(PAR_CHUNK))
                        .zip(st.v.par_chunks_mut(PAR_CHUNK))
                        .zip(st.steps.par_chunks_mut(PAR_CHUNK))
                        .for_each(|((((p, gr), m), v), n)| sparse_kernel(p, gr, m, v, n));
                } else {
                    sparse_kernel(g.params, g.grads, &mut st.m, &mut st.v, &mut st.steps);
                }
                continue;
            }
            let kernel = |p: &mut [f32], gr: &[f32], m: &mut [f32], v: &mut [f32]| {
                for i in 0..p.len() {
                    let gi = gr[i] + wd * p[i];
                    let mi = b1 * m[i] + (1.0 - b1) * gi;
                    let vi = b2 * v[i] + (1.0 - b2) * gi * gi;
                    m[i] = mi;
                    v[i] = vi;
                    p[i] -= step_size * mi / (vi.sqrt() * inv_sqrt_bc2 + eps);
                }
            };
            if g.params.len() > PAR_CHUNK {
                g.params
                    .par_chunks_mut(PAR_CHUNK)
                    .zip(g.grads.par_chunks(PAR_CHUNK))
                    .zip(st.m.par_chunks_mut(PAR_CHUNK))
                    .zip(st.v.par_chunks_mut(PAR_CHUNK))
                    .for_each(|(((p, gr), m), v)| kernel(p, gr, m, v));
            } else {
                kernel(g.params, g.grads, &mut st.m, &mut st.v);
            }
        }
    }


    /// The per-entry step counts of sparse group `name` (`None` for a dense or unknown group).
    pub fn entry_steps(&self, name: &str) -> Option<&[u32]> {
        self.groups.iter().find(|g| g.name == name && !g.steps.is_empty()).map(|g| g.steps.as_slice())
    }

    /// Number of steps taken so far.
    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// Exports the state (a copy) for a checkpoint.
    pub fn state(&self) -> AdamState {
        AdamState {
            step: self.step,
            groups: self
                .groups
                .iter()
                .map(|g| (g.name.clone(), g.m.clone(), g.v.clone()))
                .collect(),
            steps: self.groups.iter().filter(|g| !g.steps.is_empty()).map(|g| (g.name.clone(), g.steps.clone())).collect(),
        }
    }

    /// Replaces the state with `s` (from [`Adam::state`]). Fails, leaving the optimiser unchanged, when a
    /// group's `m` and `v` lengths differ, a group name repeats, or a moment is not finite (or `v` negative).
    pub fn load_state(&mut self, s: AdamState) -> Result<(), String> {
        for (i, (name, m, v)) in s.groups.iter().enumerate() {
            if m.len() != v.len() {
                return Err(format!(
                    "Adam state: group {name:?} has {} first moments but {} second moments",
                    m.len(),
                    v.len()
                ));
            }
            if s.groups[..i].iter().any(|(n, _, _)| n == name) {
                return Err(format!("Adam state: group {name:?} appears more than once"));
            }
            if m.iter().any(|x| !x.is_finite()) || v.iter().any(|x| !x.is_finite() || *x < 0.0) {
                return Err(format!(
                    "Adam state: group {name:?} has non-finite or negative moments"
                ));
            }
        }
        for (name, n) in &s.steps {
            let Some((_, m, _)) = s.groups.iter().find(|(g, _, _)| g == name) else {
                return Err(format!("Adam state: step counts for {name:?}, which has no moments"));
            };
            if n.len() != m.len() {
                return Err(format!("Adam state: group {name:?} has {} moments but {} step counts", m.len(), n.len()));
            }
            if n.iter().any(|&k| k as u64 > s.step) {
                return Err(format!("Adam state: group {name:?} has an entry step count above the step count {}", s.step));
            }
        }
        self.step = s.step;
        let mut steps = s.steps;
        self.groups = s
            .groups
            .into_iter()
            .map(|(name, m, v)| {
                let steps = steps.iter_mut().find(|(n, _)| *n == name).map(|(_, k)| std::mem::take(k)).unwrap_or_default();
                GroupState { name, m, v, steps }
            })
            .collect();
        Ok(())
    }
}

/// Index of the state of group `name` with `len` parameters, creating (or resetting) it if needed.
/// A sparse group without per-entry step counts gets them: `dense_steps` (the steps its moments
/// went through) when it has moments, 0 for fresh ones.
fn state_index(groups: &mut Vec<GroupState>, dense_steps: u64, sparse: bool, name: &str, len: usize) -> usize {
    let i = match groups.iter().position(|s| s.name == name) {
        Some(i) => {
            let s = &mut groups[i];
            if s.m.len() != len {
                s.m = vec![0.0; len];
                s.v = vec![0.0; len];
                s.steps.clear();
                if sparse {
                    s.steps = vec![0; len];
                }
            }
            i
        }
        None => {
            groups.push(GroupState { name: name.to_owned(), m: vec![0.0; len], v: vec![0.0; len], steps: if sparse { vec![0; len] } else { Vec::new() } });
            groups.len() - 1
        }
    };
    let s = &mut groups[i];
    if sparse && s.steps.len() != len {
        s.steps = vec![dense_steps.min(u32::MAX as u64) as u32; len];
    } else if !sparse && !s.steps.is_empty() {
        s.steps.clear();
    }
    i
}

/// Exponential moving average of parameter groups, debiased as tiny-cuda-nn's `Ema` optimiser
/// stores it (instant-ngp trains with `Ema(decay 0.95) ∘ ExponentialDecay ∘ Adam` and renders with
/// the average, while the optimiser keeps stepping the raw parameters).
///
/// With zero initialisation the plain average after `t` updates is
/// `s_t = d·s_{t−1} + (1−d)·p_t = (1−d)·Σ_{k≤t} d^(t−k)·p_k`, whose weights sum to `1 − d^t`;
/// the debiased average `e_t = s_t / (1 − d^t)` is what is stored. Substituting
/// `s_{t−1} = (1 − d^(t−1))·e_{t−1}` gives the recursion
/// `e_t = (d·(1 − d^(t−1))·e_{t−1} + (1 − d)·p_t) / (1 − d^t) = a_t·e_{t−1} + b_t·p_t`
/// (see [`Ema::coefficients`]); `a_1 = 0`, `b_1 = 1`, so the first update copies the parameters.
///
/// Values are kept per group, keyed by the group's name like [`Adam`]'s moments. A group seen for
/// the first time (or whose length changed) starts as a copy of its parameters, as if they had
/// always had these values. Allocation-free once every group has values.
#[derive(Clone, Debug)]
pub struct Ema {
    decay: f32,
    step: u64,
    groups: Vec<(String, Vec<f32>)>,
}

/// Exported [`Ema`] state for checkpoints: the number of updates and `(name, values)` per group.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EmaState {
    /// Number of updates taken (0: no average yet).
    pub step: u64,
    /// `(group name, averaged values)`.
    pub groups: Vec<(String, Vec<f32>)>,
}

/// One EMA update on a slice: `ema = a·ema + b·p` element-wise, and `ema = b·p` when `a == 0`
/// (the first update, which must not read the previous values). The CPU twin of the EMA part of
/// `shaders/adam.wgsl`.
pub fn ema_update(a: f32, b: f32, ema: &mut [f32], p: &[f32]) {
    assert_eq!(ema.len(), p.len(), "ema_update: {} values but {} parameters", ema.len(), p.len());
    if a == 0.0 {
        for (e, &x) in ema.iter_mut().zip(p) {
            *e = b * x;
        }
    } else {
        for (e, &x) in ema.iter_mut().zip(p) {
            *e = a * *e + b * x;
        }
    }
}

impl Ema {
    /// A new average with no values yet. Panics unless `0 < decay < 1` (configs validate it).
    pub fn new(decay: f32) -> Self {
        assert!(decay > 0.0 && decay < 1.0, "Ema: decay must lie in (0, 1), got {decay}");
        Self { decay, step: 0, groups: Vec::new() }
    }

    /// The decay `d`.
    pub fn decay(&self) -> f32 {
        self.decay
    }

    /// Updates taken so far (0: no average yet).
    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// `(a_t, b_t)` of the `t`-th update (`t ≥ 1`) in `f64`: `e_t = a_t·e_{t−1} + b_t·p_t` with
    /// `a_t = d·(1 − d^(t−1)) / (1 − d^t)` and `b_t = (1 − d) / (1 − d^t)`.
    pub fn coefficients_f64(decay: f64, t: u64) -> (f64, f64) {
        assert!(t >= 1, "Ema: updates are numbered from 1");
        let t = t as f64;
        let denom = 1.0 - decay.powf(t);
        (decay * (1.0 - decay.powf(t - 1.0)) / denom, (1.0 - decay) / denom)
    }

    /// [`Ema::coefficients_f64`] rounded to `f32` (what both devices use: computed once per step on
    /// the host, exactly as [`Adam`]'s bias corrections are). `a_1 = 0` and `b_1 = 1` exactly.
    pub fn coefficients(decay: f32, t: u64) -> (f32, f32) {
        let (a, b) = Self::coefficients_f64(decay as f64, t);
        (a as f32, b as f32)
    }

    /// Folds the current parameters of every group into the average (call after each optimiser
    /// step). Parallel over chunks for large groups.
    pub fn update(&mut self, groups: &[ParamGroupMut<'_>]) {
        self.step += 1;
        let (a, b) = Self::coefficients(self.decay, self.step);
        for g in groups {
            let p: &[f32] = g.params;
            let known = self.groups.iter().position(|(n, _)| n == g.name);
            let values = match known {
                Some(i) if self.groups[i].1.len() == p.len() => &mut self.groups[i].1,
                _ => {
                    // First sight (or a new length): the average starts at the parameters.
                    match known {
                        Some(i) => self.groups[i].1 = p.to_vec(),
                        None => self.groups.push((g.name.to_owned(), p.to_vec())),
                    }
                    continue;
                }
            };
            if p.len() > PAR_CHUNK {
                values
                    .par_chunks_mut(PAR_CHUNK)
                    .zip(p.par_chunks(PAR_CHUNK))
                    .for_each(|(e, x)| ema_update(a, b, e, x));
            } else {
                ema_update(a, b, values, p);
            }
        }
    }

    /// The averaged values of group `name`, if it has any.
    pub fn values(&self, name: &str) -> Option<&[f32]> {
        self.groups.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }

    /// Exports the state (a copy) for a checkpoint.
    pub fn state(&self) -> EmaState {
        EmaState { step: self.step, groups: self.groups.clone() }
    }

    /// Replaces the state with `s` (from [`Ema::state`]). Fails, leaving the average unchanged,
    /// when a group name repeats or a value is not finite.
    pub fn load_state(&mut self, s: EmaState) -> Result<(), String> {
        for (i, (name, v)) in s.groups.iter().enumerate() {
            if s.groups[..i].iter().any(|(n, _)| n == name) {
                return Err(format!("EMA state: group {name:?} appears more than once"));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(format!("EMA state: group {name:?} has non-finite values"));
            }
        }
        self.step = s.step;
        self.groups = s.groups;
        Ok(())
    }
}

/// A learning-rate schedule, chosen by `kind` in config files
/// (e.g. `{"kind": "exponential", "lr0": 5e-4, "lr1": 5e-5, "steps": 250000}`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum LrSchedule {
    /// The same rate at every step.
    Constant {
        /// The learning rate.
        lr: f32,
    },
    /// The paper: lr = lr0 · (lr1/lr0)^(step/steps)  (5e-4 → 5e-5 over 250k steps in the paper; `steps` configurable).
    /// Past `steps` it keeps decaying at the same rate (as nerf-pytorch does).
    Exponential {
        /// Rate at step 0.
        lr0: f32,
        /// Rate at step `steps`.
        lr1: f32,
        /// Steps over which the rate goes from `lr0` to `lr1`.
        steps: u64,
    },
    /// instant-ngp style: lr0 · gamma^(number of milestones ≤ step).
    Step {
        /// Rate before the first milestone.
        lr0: f32,
        /// Factor applied at each milestone.
        gamma: f32,
        /// Steps at which the rate is multiplied by `gamma` (any order).
        milestones: Vec<u64>,
    },
    /// nerfacc's schedule for Instant-NGP, over the run's progress rather than its step count:
    /// lr0 · gamma^(number of fractions in `at` ≤ progress), where progress is the fraction of
    /// the run done (of its steps, or of its time budget when that ends it first). A
    /// time-budgeted run thus anneals before its end whatever its step rate.
    Progress {
        /// Rate before the first fraction.
        lr0: f32,
        /// Factor applied at each fraction.
        gamma: f32,
        /// Fractions of the run, in `(0, 1)`, at which the rate is multiplied by `gamma`
        /// (nerfacc: `[0.5, 0.75, 0.9]`).
        at: Vec<f64>,
        /// Steps of linear warm-up from `lr0 / 100` (nerfacc: 100); 0 (the default) for none.
        #[serde(default)]
        warmup_steps: u64,
    },
}

impl LrSchedule {
    /// The learning rate at (0-based) `step`, with `progress` the fraction of the run done
    /// (in `[0, 1]`; only [`LrSchedule::Progress`] reads it).
    pub fn lr(&self, step: u64, progress: f64) -> f32 {
        match self {
            LrSchedule::Constant { lr } => *lr,
            LrSchedule::Exponential { lr0, lr1, steps } => {
                if *steps == 0 {
                    return *lr1;
                }
                let (a, b) = (*lr0 as f64, *lr1 as f64);
                (a * (b / a).powf(step as f64 / *steps as f64)) as f32
            }
            LrSchedule::Step {
                lr0,
                gamma,
                milestones,
            } => {
                let k = milestones.iter().filter(|&&m| m <= step).count();
                (*lr0 as f64 * (*gamma as f64).powi(k as i32)) as f32
            }
            LrSchedule::Progress { lr0, gamma, at, warmup_steps } => {
                let k = at.iter().filter(|&&f| f <= progress).count();
                let warm = if step < *warmup_steps { 0.01 + 0.99 * step as f64 / *warmup_steps as f64 } else { 1.0 };
                (*lr0 as f64 * (*gamma as f64).powi(k as i32) * warm) as f32
            }
        }
    }

    /// Checks the numbers: rates positive and finite, factors positive, progress fractions
    /// inside `(0, 1)`. The message names the field at fault.
    pub fn validate(&self) -> Result<(), String> {
        let positive = |name: &str, x: f32| {
            if x.is_finite() && x > 0.0 {
                Ok(())
            } else {
                Err(format!("lr.{name} must be a positive number, got {x}"))
            }
        };
        match self {
            LrSchedule::Constant { lr } => positive("lr", *lr),
            LrSchedule::Exponential { lr0, lr1, .. } => positive("lr0", *lr0).and(positive("lr1", *lr1)),
            LrSchedule::Step { lr0, gamma, .. } => positive("lr0", *lr0).and(positive("gamma", *gamma)),
            LrSchedule::Progress { lr0, gamma, at, .. } => {
                positive("lr0", *lr0)?;
                positive("gamma", *gamma)?;
                match at.iter().find(|f| !(**f > 0.0 && **f < 1.0)) {
                    Some(f) => Err(format!("lr.at holds fractions of the run, each strictly between 0 and 1, got {f}")),
                    None => Ok(()),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn group<'a>(name: &'a str, p: &'a mut [f32], g: &'a mut [f32], wd: f32) -> ParamGroupMut<'a> {
        ParamGroupMut {
            name,
            params: p,
            grads: g,
            weight_decay: wd,
        }
    }

    fn sparse_cfg() -> AdamConfig {
        AdamConfig { sparse_groups: vec!["table".into()], ..AdamConfig::instant_ngp() }
    }

    #[test]
    fn sparse_group_with_every_gradient_nonzero_is_dense_adam() {
        // Large enough for the parallel chunks; gradients never exactly zero.
        let n = 3 * PAR_CHUNK + 17;
        let mut rng = nerf_core_free_rng(11);
        let p0: Vec<f32> = (0..n).map(|_| rng() * 2.0 - 1.0).collect();
        let (mut pd, mut ps) = (p0.clone(), p0.clone());
        let mut dense = Adam::new(AdamConfig::instant_ngp());
        let mut sparse = Adam::new(sparse_cfg());
        for step in 0..5 {
            let g: Vec<f32> = (0..n).map(|_| rng() + 0.01).collect();
            let lr = 1e-2 / (1 + step) as f32;
            dense.step(&mut [group("table", &mut pd, &mut g.clone(), 1e-3)], lr);
            sparse.step(&mut [group("table", &mut ps, &mut g.clone(), 1e-3)], lr);
        }
        assert_eq!(pd, ps);
        assert!(sparse.entry_steps("table").unwrap().iter().all(|&k| k == 5));
        assert!(dense.entry_steps("table").is_none());
    }

    #[test]
    fn sparse_entries_skip_zero_gradients_and_debias_with_their_own_count() {
        let mut p = vec![0.5f32, -0.25, 1.0];
        let mut mlp = vec![0.3f32];
        let mut adam = Adam::new(sparse_cfg());
        // Entry 0 has a gradient at steps 1 and 3, entry 1 at step 2, entry 2 never.
        let grads = [[0.2f32, 0.0, 0.0], [0.0, -0.7, 0.0], [0.4, 0.0, 0.0]];
        for (k, g) in grads.iter().enumerate() {
            let mut g = g.to_vec();
            let mut gm = vec![0.0f32];
            let before = (p.clone(), adam.state());
            adam.step(&mut [group("table", &mut p, &mut g, 0.0), group("mlp", &mut mlp, &mut gm, 0.0)], 1e-2);
            // Skipped entries: parameter, moments and count unchanged.
            let after = adam.state();
            for i in 0..3 {
                if grads[k][i] == 0.0 {
                    assert_eq!(p[i], before.0[i]);
                    if let Some((_, m, v)) = before.1.groups.iter().find(|(n, _, _)| n == "table") {
                        assert_eq!((after.groups[0].1[i], after.groups[0].2[i]), (m[i], v[i]));
                    }
                }
            }
        }
        assert_eq!(adam.entry_steps("table").unwrap(), &[2, 1, 0]);
        assert_eq!(p[2], 1.0);
        // The dense "mlp" group moved on its zero gradients (its moments decay), sparse entries did not.
        assert!(adam.entry_steps("mlp").is_none());
        // Entry 0 took exactly the steps of a dense Adam that saw only its two gradients.
        let mut q = vec![0.5f32];
        let mut solo = Adam::new(AdamConfig::instant_ngp());
        for g in [0.2f32, 0.4] {
            solo.step(&mut [group("x", &mut q, &mut [g], 0.0)], 1e-2);
        }
        assert_eq!(p[0], q[0]);
        let mut q1 = vec![-0.25f32];
        Adam::new(AdamConfig::instant_ngp()).step(&mut [group("x", &mut q1, &mut [-0.7], 0.0)], 1e-2);
        assert_eq!(p[1], q1[0]);
    }

    #[test]
    fn sparse_state_round_trips_and_is_validated() {
        let mut p = vec![0.5f32, -0.25];
        let mut adam = Adam::new(sparse_cfg());
        adam.step(&mut [group("table", &mut p, &mut [0.1, 0.0], 0.0)], 1e-2);
        adam.step(&mut [group("table", &mut p, &mut [0.1, 0.3], 0.0)], 1e-2);
        let st = adam.state();
        assert_eq!(st.steps, vec![("table".to_string(), vec![2, 1])]);
        let json = serde_json::to_string(&st).unwrap();
        assert_eq!(serde_json::from_str::<AdamState>(&json).unwrap(), st);
        let mut back = Adam::new(sparse_cfg());
        back.load_state(st.clone()).unwrap();
        assert_eq!(back.state(), st);
        let bad = |f: &dyn Fn(&mut AdamState)| {
            let mut s = st.clone();
            f(&mut s);
            Adam::new(sparse_cfg()).load_state(s).unwrap_err()
        };
        assert!(bad(&|s| s.steps[0].1.push(0)).contains("step counts"));
        assert!(bad(&|s| s.steps[0].0 = "other".into()).contains("no moments"));
        assert!(bad(&|s| s.steps[0].1[0] = 3).contains("above"));
        // A dense run's state continues sparsely with every entry counted as having taken every step.
        let mut dense = Adam::new(AdamConfig::instant_ngp());
        let mut pd = vec![0.5f32, -0.25];
        for _ in 0..3 {
            dense.step(&mut [group("table", &mut pd, &mut [0.1, 0.2], 0.0)], 1e-2);
        }
        let mut cont = Adam::new(sparse_cfg());
        cont.load_state(dense.state()).unwrap();
        let (mut a, mut b) = (pd.clone(), pd.clone());
        cont.step(&mut [group("table", &mut a, &mut [0.1, 0.2], 0.0)], 1e-2);
        dense.step(&mut [group("table", &mut b, &mut [0.1, 0.2], 0.0)], 1e-2);
        assert_eq!(a, b);
        assert_eq!(cont.entry_steps("table").unwrap(), &[4, 4]);
    }

    #[test]
    fn sparse_group_entries_name_full_or_local_group_names() {
        assert!(names_group("field/hash_grid", "field/hash_grid"));
        assert!(names_group("hash_grid", "field/hash_grid") && names_group("hash_grid", "fine/hash_grid"));
        assert!(names_group("hash_grid", "hash_grid"));
        assert!(!names_group("field", "field/hash_grid") && !names_group("hash", "field/hash_grid"));
        assert!(!names_group("coarse/hash_grid", "fine/hash_grid"));
        let cfg = AdamConfig { sparse_groups: vec!["coarse/hash_grid".into()], ..AdamConfig::default() };
        assert!(cfg.is_sparse("coarse/hash_grid") && !cfg.is_sparse("fine/hash_grid"));
    }

    /// A tiny deterministic generator in [0, 1) for these tests.
    fn nerf_core_free_rng(seed: u64) -> impl FnMut() -> f32 {
        let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    #[test]
    fn first_and_second_step_match_hand_computation() {
        let cfg = AdamConfig {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            sparse_groups: vec![],
        };
        let mut adam = Adam::new(cfg);
        let mut p = vec![1.0f32, -2.0];
        let mut g = vec![0.5f32, -0.1];
        let lr = 0.01;
        adam.step(&mut [group("w", &mut p, &mut g, 0.0)], lr);
        // Step 1: m̂ = g, v̂ = g², so the update is lr·g/(|g|+eps) ≈ lr·sign(g).
        let e0 = 1.0 - 0.01 * 0.5 / (0.5 + 1e-8);
        let e1 = -2.0 + 0.01 * 0.1 / (0.1 + 1e-8);
        assert!((p[0] as f64 - e0).abs() < 1e-7, "{} vs {e0}", p[0]);
        assert!((p[1] as f64 - e1).abs() < 1e-7, "{} vs {e1}", p[1]);
        // Step 2 with a new gradient, computed by hand in f64.
        let g2 = [0.2f64, 0.3];
        g.copy_from_slice(&[0.2, 0.3]);
        let before = [p[0] as f64, p[1] as f64];
        adam.step(&mut [group("w", &mut p, &mut g, 0.0)], lr);
        let g1 = [0.5f64, -0.1];
        for i in 0..2 {
            let m = 0.9 * (0.1 * g1[i]) + 0.1 * g2[i];
            let v = 0.999 * (0.001 * g1[i] * g1[i]) + 0.001 * g2[i] * g2[i];
            let mh = m / (1.0 - 0.9f64.powi(2));
            let vh = v / (1.0 - 0.999f64.powi(2));
            let expect = before[i] - 0.01 * mh / (vh.sqrt() + 1e-8);
            assert!(
                (p[i] as f64 - expect).abs() < 1e-6,
                "param {i}: {} vs {expect}",
                p[i]
            );
        }
        assert_eq!(adam.step_count(), 2);
    }

    #[test]
    fn converges_on_a_quadratic() {
        // L = ½ Σ a_i (p_i − c_i)², a large and parallel-chunked group plus a small one.
        let n = 3 * PAR_CHUNK + 17;
        let a: Vec<f32> = (0..n).map(|i| 0.5 + (i % 7) as f32).collect();
        let c: Vec<f32> = (0..n)
            .map(|i| ((i * 37) % 101) as f32 / 50.0 - 1.0)
            .collect();
        let mut p = vec![0.0f32; n];
        let mut g = vec![0.0f32; n];
        let mut q = vec![3.0f32, -4.0];
        let mut gq = vec![0.0f32; 2];
        let mut adam = Adam::new(AdamConfig::default());
        let sched = LrSchedule::Exponential {
            lr0: 0.05,
            lr1: 0.0005,
            steps: 2000,
        };
        for step in 0..2000 {
            for i in 0..n {
                g[i] = a[i] * (p[i] - c[i]);
            }
            gq[0] = q[0] - 1.0;
            gq[1] = q[1] - 1.0;
            adam.step(
                &mut [
                    group("big", &mut p, &mut g, 0.0),
                    group("small", &mut q, &mut gq, 0.0),
                ],
                sched.lr(step, 0.0),
            );
        }
        let err = p
            .iter()
            .zip(&c)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(err < 1e-3, "max error {err}");
        assert!(
            (q[0] - 1.0).abs() < 1e-3 && (q[1] - 1.0).abs() < 1e-3,
            "{q:?}"
        );
    }

    #[test]
    fn weight_decay_is_added_to_the_gradient() {
        // With zero gradient, weight decay alone drives the parameter towards zero, and one step with
        // (g, wd) equals one step with gradient g + wd·p and no decay.
        let cfg = AdamConfig::default();
        let (mut a, mut b) = (Adam::new(cfg.clone()), Adam::new(cfg));
        let mut pa = vec![2.0f32, -1.0, 0.5];
        let mut ga = vec![0.3f32, 0.0, -0.2];
        let mut pb = pa.clone();
        let mut gb: Vec<f32> = pa.iter().zip(&ga).map(|(p, g)| g + 0.1 * p).collect();
        a.step(&mut [group("w", &mut pa, &mut ga, 0.1)], 1e-2);
        b.step(&mut [group("w", &mut pb, &mut gb, 0.0)], 1e-2);
        assert_eq!(pa, pb);
        let mut p = vec![1.0f32];
        let mut g = vec![0.0f32];
        let mut c = Adam::new(AdamConfig::default());
        for _ in 0..500 {
            c.step(&mut [group("w", &mut p, &mut g, 0.5)], 1e-2);
        }
        assert!(p[0].abs() < 0.1, "{}", p[0]);
        // Without decay nothing moves.
        let mut p = vec![1.0f32];
        let mut c = Adam::new(AdamConfig::default());
        c.step(&mut [group("w", &mut p, &mut g, 0.0)], 1e-2);
        assert_eq!(p[0], 1.0);
    }

    #[test]
    fn state_round_trip_gives_identical_steps() {
        let mk = |n: usize, s: f32| {
            (0..n)
                .map(|i| (i as f32 * 0.37 + s).sin())
                .collect::<Vec<f32>>()
        };
        let mut p1 = mk(PAR_CHUNK + 5, 0.0);
        let mut p2 = mk(3, 1.0);
        let mut adam = Adam::new(AdamConfig::instant_ngp());
        for k in 0..5 {
            let mut g1 = mk(p1.len(), k as f32);
            let mut g2 = mk(p2.len(), 2.0 * k as f32);
            adam.step(
                &mut [
                    group("a", &mut p1, &mut g1, 1e-3),
                    group("b", &mut p2, &mut g2, 0.0),
                ],
                1e-2,
            );
        }
        // Export through JSON (as a checkpoint would) and import into a fresh optimiser.
        let json = serde_json::to_string(&adam.state()).unwrap();
        let mut restored = Adam::new(AdamConfig::instant_ngp());
        restored
            .load_state(serde_json::from_str(&json).unwrap())
            .unwrap();
        assert_eq!(restored.step_count(), 5);
        let (mut q1, mut q2) = (p1.clone(), p2.clone());
        for k in 5..8 {
            let mut g1 = mk(p1.len(), k as f32);
            let mut g2 = mk(p2.len(), 2.0 * k as f32);
            adam.step(
                &mut [
                    group("a", &mut p1, &mut g1, 1e-3),
                    group("b", &mut p2, &mut g2, 0.0),
                ],
                1e-2,
            );
            let mut g1 = mk(q1.len(), k as f32);
            let mut g2 = mk(q2.len(), 2.0 * k as f32);
            restored.step(
                &mut [
                    group("a", &mut q1, &mut g1, 1e-3),
                    group("b", &mut q2, &mut g2, 0.0),
                ],
                1e-2,
            );
        }
        assert_eq!(p1, q1);
        assert_eq!(p2, q2);
        // A fresh optimiser (no state) would have produced different parameters.
        let mut fresh = Adam::new(AdamConfig::instant_ngp());
        let mut r = p2.clone();
        let mut g = mk(3, 0.0);
        let mut r2 = p2.clone();
        let mut g2 = mk(3, 0.0);
        fresh.step(&mut [group("b", &mut r, &mut g, 0.0)], 1e-2);
        adam.step(&mut [group("b", &mut r2, &mut g2, 0.0)], 1e-2);
        assert_ne!(r, r2);
    }

    #[test]
    fn load_state_rejects_bad_state() {
        let mut adam = Adam::new(AdamConfig::default());
        let bad = AdamState {
            step: 3,
            groups: vec![("w".into(), vec![0.0; 3], vec![0.0; 2])],
            steps: vec![],
        };
        let e = adam.load_state(bad).unwrap_err();
        assert!(e.contains("\"w\""), "{e}");
        let dup = AdamState {
            step: 3,
            groups: vec![
                ("w".into(), vec![0.0], vec![0.0]),
                ("w".into(), vec![0.0], vec![0.0]),
            ],
            steps: vec![],
        };
        assert!(adam.load_state(dup).is_err());
        let nan = AdamState {
            step: 3,
            groups: vec![("w".into(), vec![f32::NAN], vec![0.0])],
            steps: vec![],
        };
        assert!(adam.load_state(nan).is_err());
        assert_eq!(adam.step_count(), 0);
    }

    #[test]
    fn group_with_changed_length_gets_fresh_state() {
        let mut adam = Adam::new(AdamConfig::default());
        let mut p = vec![0.0f32; 4];
        let mut g = vec![1.0f32; 4];
        adam.step(&mut [group("w", &mut p, &mut g, 0.0)], 0.1);
        let mut p = vec![0.0f32; 6];
        let mut g = vec![1.0f32; 6];
        adam.step(&mut [group("w", &mut p, &mut g, 0.0)], 0.1);
        let s = adam.state();
        assert_eq!(s.groups.len(), 1);
        assert_eq!(s.groups[0].1.len(), 6);
        // Fresh moments: m = (1−β1)·g at the second step, not β1·m_old + …
        assert!(
            (s.groups[0].1[0] - 0.1).abs() < 1e-7,
            "{}",
            s.groups[0].1[0]
        );
    }

    /// The debiased average written as a weighted sum: `Σ_k (1−d)·d^(t−k)·p_k / (1 − d^t)`.
    fn direct_ema(decay: f64, ps: &[Vec<f64>]) -> Vec<f64> {
        let t = ps.len() as i32;
        let norm = 1.0 - decay.powi(t);
        let mut out = vec![0.0; ps[0].len()];
        for (k, p) in ps.iter().enumerate() {
            let w = (1.0 - decay) * decay.powi(t - 1 - k as i32) / norm;
            for (o, x) in out.iter_mut().zip(p) {
                *o += w * x;
            }
        }
        out
    }

    #[test]
    fn ema_recursion_equals_the_debiased_weighted_sum() {
        use rand::{Rng as _, SeedableRng as _};
        let mut rng = rand::rngs::StdRng::seed_from_u64(17);
        for &decay in &[0.95f64, 0.5, 0.99, 0.1] {
            // The recursion in f64 against the direct sum, after every step.
            let n = 7;
            let mut ps: Vec<Vec<f64>> = Vec::new();
            let mut e = vec![f64::NAN; n];
            for t in 1..=60u64 {
                let p: Vec<f64> = (0..n).map(|_| rng.gen_range(-2.0..2.0)).collect();
                let (a, b) = Ema::coefficients_f64(decay, t);
                if t == 1 {
                    assert_eq!((a, b), (0.0, 1.0), "the first update copies the parameters");
                }
                assert!((a + b - 1.0).abs() < 1e-12, "weights sum to one: {a} + {b}");
                for (ei, &pi) in e.iter_mut().zip(&p) {
                    *ei = if a == 0.0 { b * pi } else { a * *ei + b * pi };
                }
                ps.push(p);
                let direct = direct_ema(decay, &ps);
                for (x, y) in e.iter().zip(&direct) {
                    assert!((x - y).abs() < 1e-12, "decay {decay} step {t}: {x} vs {y}");
                }
            }
        }
    }

    #[test]
    fn ema_matches_the_direct_sum_over_groups_and_round_trips() {
        use rand::{Rng as _, SeedableRng as _};
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let decay = 0.95f32;
        let sizes = [PAR_CHUNK + 9, 5];
        let mut ema = Ema::new(decay);
        let mut hist: Vec<Vec<Vec<f64>>> = vec![Vec::new(); 2];
        let mut params: Vec<Vec<f32>> = sizes.iter().map(|&n| vec![0.0; n]).collect();
        let mut grads: Vec<Vec<f32>> = sizes.iter().map(|&n| vec![0.0; n]).collect();
        let mut json = String::new();
        for t in 1..=30u64 {
            for (i, p) in params.iter_mut().enumerate() {
                for x in p.iter_mut() {
                    *x = rng.gen_range(-1.0f32..1.0);
                }
                hist[i].push(p.iter().map(|&x| x as f64).collect());
            }
            let (p0, p1) = params.split_at_mut(1);
            let (g0, g1) = grads.split_at_mut(1);
            ema.update(&[group("big", &mut p0[0], &mut g0[0], 0.0), group("small", &mut p1[0], &mut g1[0], 0.0)]);
            assert_eq!(ema.step_count(), t);
            for (i, name) in ["big", "small"].iter().enumerate() {
                let direct = direct_ema(decay as f64, &hist[i]);
                let got = ema.values(name).unwrap();
                if t == 1 {
                    assert_eq!(got, &params[i][..], "the first update copies the parameters");
                }
                // f32 recursion: a few ulp per step, not compounding (|a|, |b| ≤ 1).
                let err = got.iter().zip(&direct).map(|(&x, y)| (x as f64 - y).abs()).fold(0.0, f64::max);
                assert!(err < 1e-5, "{name} step {t}: max error {err}");
            }
            if t == 10 {
                json = serde_json::to_string(&ema.state()).unwrap();
            }
        }
        // A restored average continues exactly as the original did.
        let mut back = Ema::new(decay);
        back.load_state(serde_json::from_str(&json).unwrap()).unwrap();
        assert_eq!(back.step_count(), 10);
        let mut again = back.clone();
        let mut p = vec![0.25f32; 5];
        let mut g = vec![0.0f32; 5];
        again.update(&[group("small", &mut p, &mut g, 0.0)]);
        let (a, b) = Ema::coefficients(decay, 11);
        let before = back.values("small").unwrap();
        for (x, y) in again.values("small").unwrap().iter().zip(before) {
            assert_eq!(*x, a * y + b * 0.25);
        }
        // A group seen for the first time starts at its parameters.
        let mut q = vec![3.0f32; 4];
        let mut gq = vec![0.0f32; 4];
        again.update(&[group("new", &mut q, &mut gq, 0.0)]);
        assert_eq!(again.values("new").unwrap(), &[3.0f32; 4][..]);
        // Bad states are rejected and leave the average unchanged.
        let dup = EmaState { step: 2, groups: vec![("w".into(), vec![0.0]), ("w".into(), vec![1.0])] };
        assert!(back.load_state(dup).unwrap_err().contains("\"w\""));
        let nan = EmaState { step: 2, groups: vec![("w".into(), vec![f32::NAN])] };
        assert!(back.load_state(nan).is_err());
        assert_eq!(back.step_count(), 10);
    }

    #[test]
    fn schedules_at_endpoints() {
        let c = LrSchedule::Constant { lr: 3e-3 };
        assert_eq!(c.lr(0, 0.0), 3e-3);
        assert_eq!(c.lr(1_000_000, 0.0), 3e-3);
        let e = LrSchedule::Exponential {
            lr0: 5e-4,
            lr1: 5e-5,
            steps: 250_000,
        };
        assert!((e.lr(0, 0.0) - 5e-4).abs() < 1e-10);
        assert!((e.lr(250_000, 0.0) - 5e-5).abs() < 1e-10);
        assert!((e.lr(125_000, 0.0) - (5e-4f64 * 5e-5).sqrt() as f32).abs() < 1e-9);
        assert!(e.lr(500_000, 0.0) < e.lr(250_000, 0.0));
        let s = LrSchedule::Step {
            lr0: 1e-2,
            gamma: 0.33,
            milestones: vec![15_000, 10_000, 20_000],
        };
        assert_eq!(s.lr(0, 0.0), 1e-2);
        assert_eq!(s.lr(9_999, 0.0), 1e-2);
        assert!((s.lr(10_000, 0.0) - 3.3e-3).abs() < 1e-9);
        assert!((s.lr(15_000, 0.0) - 1e-2 * 0.33 * 0.33).abs() < 1e-9);
        assert!((s.lr(1 << 40, 0.0) - 1e-2 * 0.33f32.powi(3)).abs() < 1e-9);
        // Serde form used in config files.
        let parsed: LrSchedule = serde_json::from_str(
            r#"{"kind":"exponential","lr0":0.0005,"lr1":0.00005,"steps":250000}"#,
        )
        .unwrap();
        assert_eq!(parsed, e);
    }

    #[test]
    fn progress_schedule_follows_the_run_not_the_step() {
        let p = LrSchedule::Progress { lr0: 1e-2, gamma: 0.33, at: vec![0.75, 0.5, 0.9], warmup_steps: 0 };
        // The step count does not matter, the fraction of the run does.
        assert_eq!(p.lr(0, 0.0), 1e-2);
        assert_eq!(p.lr(1 << 40, 0.4999), 1e-2);
        assert!((p.lr(7, 0.5) - 3.3e-3).abs() < 1e-9);
        assert!((p.lr(7, 0.8) - 1e-2 * 0.33 * 0.33).abs() < 1e-9);
        assert!((p.lr(7, 1.0) - 1e-2 * 0.33f32.powi(3)).abs() < 1e-9);
        // nerfacc's warm-up: from lr0/100, linear, lr0 at `warmup_steps`.
        let w = LrSchedule::Progress { lr0: 1e-2, gamma: 0.33, at: vec![0.5], warmup_steps: 100 };
        assert!((w.lr(0, 0.0) - 1e-4).abs() < 1e-10);
        assert!((w.lr(50, 0.0) - 1e-2 * 0.505).abs() < 1e-9);
        assert_eq!(w.lr(100, 0.0), 1e-2);
        // TOML form; the warm-up may be left out.
        let parsed: LrSchedule = toml::from_str("kind = \"progress\"\nlr0 = 0.01\ngamma = 0.33\nat = [0.75, 0.5, 0.9]\n").unwrap();
        assert_eq!(parsed, p);
        assert_eq!(p.validate(), Ok(()));
        // Bad numbers name the field.
        let bad = LrSchedule::Progress { lr0: 1e-2, gamma: 0.33, at: vec![0.5, 1.0], warmup_steps: 0 };
        assert!(bad.validate().unwrap_err().contains("lr.at"));
        let bad = LrSchedule::Progress { lr0: 1e-2, gamma: f32::NAN, at: vec![], warmup_steps: 0 };
        assert!(bad.validate().unwrap_err().contains("lr.gamma"));
        assert!(LrSchedule::Constant { lr: 0.0 }.validate().unwrap_err().contains("lr.lr"));
        assert!(LrSchedule::Exponential { lr0: 5e-4, lr1: -1.0, steps: 10 }.validate().unwrap_err().contains("lr.lr1"));
    }
}
