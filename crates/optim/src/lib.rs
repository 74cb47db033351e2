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
}

impl Default for AdamConfig {
    /// The NeRF paper's settings: β = (0.9, 0.999), ε = 1e-7.
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-7,
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
        }
    }
}

/// Moment estimates of one parameter group.
#[derive(Clone, Debug)]
struct GroupState {
    name: String,
    m: Vec<f32>,
    v: Vec<f32>,
}

/// Adam with bias correction and L2 weight decay added to the gradient (g += wd·p, as torch Adam weight_decay).
/// State (m, v per group, keyed by group name and length; step count) is created on first use and can be
/// exported/imported for checkpoints.
///
/// The bias correction uses one step count shared by all groups (the number of [`Adam::step`] calls),
/// so every group is expected to take part in every step. A group whose name is known but whose length
/// changed gets fresh (zero) moments.
#[derive(Clone, Debug)]
pub struct Adam {
    cfg: AdamConfig,
    step: u64,
    groups: Vec<GroupState>,
}

/// Exported optimiser state for checkpoints: the step count and `(name, m, v)` per group.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamState {
    /// Number of steps taken.
    pub step: u64,
    /// `(group name, first moments, second moments)`.
    pub groups: Vec<(String, Vec<f32>, Vec<f32>)>,
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
        }
    }

    /// The hyper-parameters.
    pub fn config(&self) -> &AdamConfig {
        &self.cfg
    }

    /// Takes one step with learning rate `lr` on every group: increments the step count, then for each
    /// element `g = grad + wd·p; m = β1·m + (1−β1)·g; v = β2·v + (1−β2)·g²;
    /// p −= lr·(m/(1−β1^t)) / (sqrt(v/(1−β2^t)) + ε)` (torch's formulation). Parallel over chunks for
    /// large groups; allocation-free once every group has state.
    ///
    /// Panics if a group's `params` and `grads` lengths differ (programmer error).
    pub fn step(&mut self, groups: &mut [ParamGroupMut<'_>], lr: f32) {
        self.step += 1;
        let t = self.step as f64;
        let (b1, b2, eps) = (self.cfg.beta1, self.cfg.beta2, self.cfg.eps);
        let bc1 = 1.0 - (b1 as f64).powf(t);
        let bc2 = 1.0 - (b2 as f64).powf(t);
        let step_size = (lr as f64 / bc1) as f32;
        let inv_sqrt_bc2 = (1.0 / bc2.sqrt()) as f32;
        for g in groups.iter_mut() {
            assert_eq!(
                g.params.len(),
                g.grads.len(),
                "Adam: group {:?} has {} params but {} grads",
                g.name,
                g.params.len(),
                g.grads.len()
            );
            let idx = self.state_index(g.name, g.params.len());
            let st = &mut self.groups[idx];
            let wd = g.weight_decay;
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

    /// Index of the state of group `name` with `len` parameters, creating (or resetting) it if needed.
    fn state_index(&mut self, name: &str, len: usize) -> usize {
        match self.groups.iter().position(|s| s.name == name) {
            Some(i) => {
                let s = &mut self.groups[i];
                if s.m.len() != len {
                    s.m = vec![0.0; len];
                    s.v = vec![0.0; len];
                }
                i
            }
            None => {
                self.groups.push(GroupState {
                    name: name.to_owned(),
                    m: vec![0.0; len],
                    v: vec![0.0; len],
                });
                self.groups.len() - 1
            }
        }
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
        self.step = s.step;
        self.groups = s
            .groups
            .into_iter()
            .map(|(name, m, v)| GroupState { name, m, v })
            .collect();
        Ok(())
    }
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
}

impl LrSchedule {
    /// The learning rate at (0-based) `step`.
    pub fn lr(&self, step: u64) -> f32 {
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

    #[test]
    fn first_and_second_step_match_hand_computation() {
        let cfg = AdamConfig {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
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
                sched.lr(step),
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
        };
        let e = adam.load_state(bad).unwrap_err();
        assert!(e.contains("\"w\""), "{e}");
        let dup = AdamState {
            step: 3,
            groups: vec![
                ("w".into(), vec![0.0], vec![0.0]),
                ("w".into(), vec![0.0], vec![0.0]),
            ],
        };
        assert!(adam.load_state(dup).is_err());
        let nan = AdamState {
            step: 3,
            groups: vec![("w".into(), vec![f32::NAN], vec![0.0])],
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
        assert_eq!(c.lr(0), 3e-3);
        assert_eq!(c.lr(1_000_000), 3e-3);
        let e = LrSchedule::Exponential {
            lr0: 5e-4,
            lr1: 5e-5,
            steps: 250_000,
        };
        assert!((e.lr(0) - 5e-4).abs() < 1e-10);
        assert!((e.lr(250_000) - 5e-5).abs() < 1e-10);
        assert!((e.lr(125_000) - (5e-4f64 * 5e-5).sqrt() as f32).abs() < 1e-9);
        assert!(e.lr(500_000) < e.lr(250_000));
        let s = LrSchedule::Step {
            lr0: 1e-2,
            gamma: 0.33,
            milestones: vec![15_000, 10_000, 20_000],
        };
        assert_eq!(s.lr(0), 1e-2);
        assert_eq!(s.lr(9_999), 1e-2);
        assert!((s.lr(10_000) - 3.3e-3).abs() < 1e-9);
        assert!((s.lr(15_000) - 1e-2 * 0.33 * 0.33).abs() < 1e-9);
        assert!((s.lr(1 << 40) - 1e-2 * 0.33f32.powi(3)).abs() < 1e-9);
        // Serde form used in config files.
        let parsed: LrSchedule = serde_json::from_str(
            r#"{"kind":"exponential","lr0":0.0005,"lr1":0.00005,"steps":250000}"#,
        )
        .unwrap();
        assert_eq!(parsed, e);
    }
}
