//! Adam on the device (`shaders/adam.wgsl`), matching [`nerf_optim::Adam`] step for step.
//!
//! The trainer concatenates every parameter group of every field into ONE flat `f32` parameter
//! buffer and one gradient buffer of the same layout; [`GpuAdam`] owns the first/second moment
//! buffers (same layout) and updates all groups in one dispatch, zeroing the gradients as it goes
//! (so the next step's backward can accumulate with `+=` without a clearing pass).
//!
//! The step count lives on the host: [`GpuAdam::record_step`] increments it and rewrites a small
//! uniform (with [`GpuContext::write`]) holding the learning rate and both bias corrections,
//! computed in `f64` exactly as the CPU does. Because queued writes land before the next
//! submission, record at most ONE step per submission.

use crate::kernel::{groups_1d, Kernel};
use crate::{shaders, GpuContext, GpuError};
use nerf_optim::{AdamConfig, AdamState, Ema, EmaState};
use std::sync::atomic::{AtomicU64, Ordering};
use crate::layout::{AdamParams, GroupDesc};

const WG: u32 = 256;

/// One parameter group inside the flat parameter buffer.
#[derive(Clone, Debug, PartialEq)]
pub struct GpuParamGroup {
    /// Name (the key of the group in [`AdamState`], as the CPU optimiser uses it).
    pub name: String,
    /// Index of the group's first parameter in the flat buffer.
    pub offset: usize,
    /// Number of parameters.
    pub len: usize,
    /// L2 weight decay added to the gradient (`g += wd·p`, torch's `weight_decay`).
    pub weight_decay: f32,
    /// Multiplies the learning rate of this group (1 matches the CPU optimiser).
    pub lr_scale: f32,
}

impl GpuParamGroup {
    /// A group with `lr_scale = 1`.
    pub fn new(name: impl Into<String>, offset: usize, len: usize, weight_decay: f32) -> Self {
        Self { name: name.into(), offset, len, weight_decay, lr_scale: 1.0 }
    }
}

/// Adam over one flat parameter buffer with named groups; owns the moment buffers.
pub struct GpuAdam {
    cfg: AdamConfig,
    groups: Vec<GpuParamGroup>,
    /// Length of the parameter buffer the moments cover (`max(offset + len)`).
    extent: usize,
    total: usize,
    step: AtomicU64,
    m: wgpu::Buffer,
    v: wgpu::Buffer,
    group_buf: wgpu::Buffer,
    uniform: wgpu::Buffer,
    kernel: Kernel,
    ema: Option<GpuEma>,
    /// Per-entry step counts (u32, parameter layout; one word when no group is sparse).
    counts: wgpu::Buffer,
    /// `(1/(1−β1^t), 1/sqrt(1−β2^t))` for t = 1, 2, … until both are 1 in f32 (sparse groups).
    bias: wgpu::Buffer,
}

/// The bias corrections of sparse entries by step count, `(1/(1−β1^t), 1/sqrt(1−β2^t))` for
/// t = 1 … T, computed in f64 as [`nerf_optim::Adam`] does and rounded to f32; T is the first t
/// where both round to 1 (at most 2^20 entries; β this close to 1 are not used in practice).
fn bias_table(cfg: &AdamConfig) -> Vec<[f32; 2]> {
    let (b1, b2) = (cfg.beta1 as f64, cfg.beta2 as f64);
    let mut out = Vec::new();
    for t in 1..=(1u32 << 20) {
        let e = [(1.0 / (1.0 - b1.powf(t as f64))) as f32, (1.0 / (1.0 - b2.powf(t as f64)).sqrt()) as f32];
        out.push(e);
        if e == [1.0, 1.0] {
            break;
        }
    }
    out
}

/// The EMA of a [`GpuAdam`]: decay, update count, values (parameter layout).
struct GpuEma {
    decay: f32,
    step: AtomicU64,
    values: wgpu::Buffer,
}

impl GpuAdam {
    /// Builds the optimiser for `groups` (non-empty groups must not overlap; any order; empty
    /// groups are kept for [`GpuAdam::state`] but cost nothing). Moments start at zero, step 0.
    /// Errors on overlapping groups, non-finite weight decay or learning-rate scale, or a buffer
    /// larger than `u32` indices allow.
    pub fn new(ctx: &GpuContext, cfg: &AdamConfig, groups: &[GpuParamGroup]) -> Result<Self, GpuError> {
        Self::with_ema(ctx, cfg, groups, None)
    }

    /// As [`GpuAdam::new`], and with `ema_decay` every step also updates the exponential moving
    /// average of the parameters (see the module docs), which starts empty (update count 0; the
    /// first update copies the parameters). Errors when the decay is not in (0, 1).
    pub fn with_ema(
        ctx: &GpuContext,
        cfg: &AdamConfig,
        groups: &[GpuParamGroup],
        ema_decay: Option<f32>,
    ) -> Result<Self, GpuError> {
        if let Some(d) = ema_decay {
            if !(d > 0.0 && d < 1.0) {
                return Err(GpuError::Unsupported(format!("Adam: EMA decay must lie in (0, 1), got {d}")));
            }
        }
        let mut order: Vec<usize> = (0..groups.len()).filter(|&i| groups[i].len > 0).collect();
        order.sort_by_key(|&i| groups[i].offset);
        for w in order.windows(2) {
            let (a, b) = (&groups[w[0]], &groups[w[1]]);
            if a.offset + a.len > b.offset {
                return Err(GpuError::Unsupported(format!(
                    "Adam: parameter groups {:?} ({}..{}) and {:?} ({}..{}) overlap",
                    a.name,
                    a.offset,
                    a.offset + a.len,
                    b.name,
                    b.offset,
                    b.offset + b.len
                )));
            }
        }
        for g in groups {
            if !(g.weight_decay.is_finite() && g.lr_scale.is_finite()) {
                return Err(GpuError::Unsupported(format!(
                    "Adam: group {:?} has a non-finite weight decay ({}) or lr scale ({})",
                    g.name, g.weight_decay, g.lr_scale
                )));
            }
        }
        let extent = groups.iter().map(|g| g.offset + g.len).max().unwrap_or(0);
        if extent > u32::MAX as usize {
            return Err(GpuError::Unsupported(format!("Adam: {extent} parameters exceed u32 indices")));
        }
        let mut descs = Vec::with_capacity(order.len());
        let mut start = 0usize;
        for &i in &order {
            let g = &groups[i];
            descs.push(GroupDesc {
                offset: g.offset as u32,
                len: g.len as u32,
                start: start as u32,
                weight_decay: g.weight_decay,
                lr_scale: g.lr_scale,
                sparse: cfg.is_sparse(&g.name) as u32,
                _pad: [0; 2],
            });
            start += g.len;
        }
        let total = start;
        let params = AdamParams {
            total: total as u32,
            n_groups: descs.len() as u32,
            beta1: cfg.beta1,
            beta2: cfg.beta2,
            one_minus_beta1: 1.0 - cfg.beta1,
            one_minus_beta2: 1.0 - cfg.beta2,
            eps: cfg.eps,
            ..Default::default()
        };
        let entry = if ema_decay.is_some() { "adam_step_ema" } else { "adam_step" };
        let kernel = Kernel::new(ctx, &shaders::with_common(shaders::ADAM), entry, &[("WG", WG as f64)]);
        Ok(Self {
            cfg: cfg.clone(),
            groups: groups.to_vec(),
            extent,
            total,
            step: AtomicU64::new(0),
            m: ctx.zeros("adam.m", 4 * extent),
            v: ctx.zeros("adam.v", 4 * extent),
            group_buf: ctx.upload("adam.groups", &descs),
            uniform: ctx.uniform("adam.params", &params),
            kernel,
            ema: ema_decay.map(|decay| GpuEma { decay, step: AtomicU64::new(0), values: ctx.zeros("adam.ema", 4 * extent) }),
            counts: ctx.zeros("adam.counts", 4 * if groups.iter().any(|g| cfg.is_sparse(&g.name)) { extent } else { 1 }),
            bias: if groups.iter().any(|g| cfg.is_sparse(&g.name)) {
                ctx.upload("adam.bias", &bias_table(cfg))
            } else {
                ctx.upload("adam.bias", &[[1.0f32; 2]])
            },
        })
    }

    /// The hyper-parameters.
    pub fn config(&self) -> &AdamConfig {
        &self.cfg
    }

    /// The groups as given to [`GpuAdam::new`].
    pub fn groups(&self) -> &[GpuParamGroup] {
        &self.groups
    }

    /// Length (in `f32`) the parameter, gradient and moment buffers must have at least.
    pub fn extent(&self) -> usize {
        self.extent
    }

    /// Steps recorded so far (or loaded with [`GpuAdam::load_state`]).
    pub fn step_count(&self) -> u64 {
        self.step.load(Ordering::Relaxed)
    }

    /// The first- and second-moment buffers (`extent` f32 each, parameter layout).
    pub fn moments(&self) -> (&wgpu::Buffer, &wgpu::Buffer) {
        (&self.m, &self.v)
    }

    /// Records one Adam step with learning rate `lr` on every group of `params` (updated in place)
    /// from `grads` (set to zero afterwards). Increments the step count and rewrites the step
    /// uniform, so at most one step may be recorded per submission.
    pub fn record_step(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, params: &wgpu::Buffer, grads: &wgpu::Buffer, lr: f32) {
        let step = self.step.fetch_add(1, Ordering::Relaxed) + 1;
        // Exactly nerf_optim::Adam::step's arithmetic (f64, then rounded to f32).
        let t = step as f64;
        let bc1 = 1.0 - (self.cfg.beta1 as f64).powf(t);
        let bc2 = 1.0 - (self.cfg.beta2 as f64).powf(t);
        let step_size = (lr as f64 / bc1) as f32;
        let inv_sqrt_bc2 = (1.0 / bc2.sqrt()) as f32;
        // `step_size`, `inv_sqrt_bc2`, `ema_old`, `ema_new`, `lr`: words 7..12 of AdamParams.
        let (ema_old, ema_new) = match &self.ema {
            Some(e) => Ema::coefficients(e.decay, e.step.fetch_add(1, Ordering::Relaxed) + 1),
            None => (0.0, 0.0),
        };
        ctx.write(&self.uniform, 7 * 4, &[step_size, inv_sqrt_bc2, ema_old, ema_new, lr]);
        if self.total == 0 {
            return;
        }
        let mut bindings = vec![(0, &self.uniform), (1, &self.group_buf), (2, params), (3, grads), (4, &self.m), (5, &self.v)];
        if let Some(e) = &self.ema {
            bindings.push((6, &e.values));
        }
        bindings.push((7, &self.counts));
        bindings.push((8, &self.bias));
        self.kernel.record(ctx, enc, &bindings, groups_1d(self.total, WG));
    }

    /// The EMA decay, when the optimiser keeps an average.
    pub fn ema_decay(&self) -> Option<f32> {
        self.ema.as_ref().map(|e| e.decay)
    }

    /// EMA updates recorded so far (or loaded); 0 without an EMA or before the first step.
    pub fn ema_step_count(&self) -> u64 {
        self.ema.as_ref().map_or(0, |e| e.step.load(Ordering::Relaxed))
    }

    /// The EMA values (`extent` f32, parameter layout), when the optimiser keeps an average.
    /// Meaningful once [`GpuAdam::ema_step_count`] is positive.
    pub fn ema_buffer(&self) -> Option<&wgpu::Buffer> {
        self.ema.as_ref().map(|e| &e.values)
    }

    /// Reads the EMA back into an [`EmaState`] (one entry per group, in the order given to
    /// [`GpuAdam::new`]; no groups before the first update), `None` without an EMA. Waits for the
    /// queue.
    pub fn ema_state(&self, ctx: &GpuContext) -> Result<Option<EmaState>, GpuError> {
        let Some(e) = &self.ema else { return Ok(None) };
        let step = e.step.load(Ordering::Relaxed);
        if step == 0 {
            return Ok(Some(EmaState { step, groups: Vec::new() }));
        }
        let values = ctx.read_f32(&e.values, self.extent)?;
        Ok(Some(EmaState {
            step,
            groups: self.groups.iter().map(|g| (g.name.clone(), values[g.offset..g.offset + g.len].to_vec())).collect(),
        }))
    }

    /// Loads an EMA (from [`GpuAdam::ema_state`] or [`nerf_optim::Ema::state`]): the update count
    /// and every group's values. Fails, leaving the optimiser unchanged, without an EMA, when the
    /// state has updates but lacks a group (or its length differs), or holds a non-finite value.
    pub fn load_ema_state(&self, ctx: &GpuContext, s: &EmaState) -> Result<(), GpuError> {
        let Some(e) = &self.ema else {
            return Err(GpuError::Unsupported("Adam: loading an EMA into an optimiser without one".into()));
        };
        let mut values = vec![0.0f32; self.extent];
        if s.step > 0 {
            for g in &self.groups {
                let Some((_, v)) = s.groups.iter().find(|(n, _)| *n == g.name) else {
                    return Err(GpuError::Unsupported(format!("EMA state: group {:?} is missing", g.name)));
                };
                if v.len() != g.len || v.iter().any(|x| !x.is_finite()) {
                    return Err(GpuError::Unsupported(format!(
                        "EMA state: group {:?} has {} values (expected {}) or non-finite ones",
                        g.name,
                        v.len(),
                        g.len
                    )));
                }
                values[g.offset..g.offset + g.len].copy_from_slice(v);
            }
        }
        if self.extent > 0 {
            ctx.write(&e.values, 0, &values);
        }
        e.step.store(s.step, Ordering::Relaxed);
        Ok(())
    }

    /// Reads the moments back into an [`AdamState`] (one entry per group, in the order given to
    /// [`GpuAdam::new`]) for a checkpoint. Waits for the queue.
    pub fn state(&self, ctx: &GpuContext) -> Result<AdamState, GpuError> {
        let m = ctx.read_f32(&self.m, self.extent)?;
        let v = ctx.read_f32(&self.v, self.extent)?;
        let sparse: Vec<&GpuParamGroup> = self.groups.iter().filter(|g| self.cfg.is_sparse(&g.name)).collect();
        let counts = if sparse.is_empty() { Vec::new() } else { ctx.read_u32(&self.counts, self.extent)? };
        Ok(AdamState {
            step: self.step_count(),
            groups: self
                .groups
                .iter()
                .map(|g| (g.name.clone(), m[g.offset..g.offset + g.len].to_vec(), v[g.offset..g.offset + g.len].to_vec()))
                .collect(),
            steps: sparse.iter().map(|g| (g.name.clone(), counts[g.offset..g.offset + g.len].to_vec())).collect(),
        })
    }

    /// Loads a checkpoint (from [`GpuAdam::state`] or [`nerf_optim::Adam::state`]): the step count,
    /// and the moments of every group whose name and length match; other groups get zero moments
    /// (as the CPU optimiser gives a group it has no state for). Fails, leaving the optimiser
    /// unchanged, when a group's `m` and `v` lengths differ, a name repeats, or a moment is not
    /// finite (or `v` negative), or per-entry step counts do not fit their group's moments — the
    /// CPU's rules. A sparse group's entries take their counts from `s.steps`, or, without them
    /// (a dense run's state), the step count when the group's moments were loaded and 0 otherwise.
    pub fn load_state(&self, ctx: &GpuContext, s: &AdamState) -> Result<(), GpuError> {
        for (name, n) in &s.steps {
            let bad = |what: String| Err(GpuError::Unsupported(format!("Adam state: group {name:?} {what}")));
            match s.groups.iter().find(|(g, _, _)| g == name) {
                None => return bad("has step counts but no moments".into()),
                Some((_, m, _)) if m.len() != n.len() => return bad(format!("has {} moments but {} step counts", m.len(), n.len())),
                _ => {}
            }
            if n.iter().any(|&k| k as u64 > s.step) {
                return bad(format!("has an entry step count above the step count {}", s.step));
            }
        }
        for (i, (name, m, v)) in s.groups.iter().enumerate() {
            let bad = |what: &str| Err(GpuError::Unsupported(format!("Adam state: group {name:?} {what}")));
            if m.len() != v.len() {
                return bad(&format!("has {} first moments but {} second moments", m.len(), v.len()));
            }
            if s.groups[..i].iter().any(|(n, _, _)| n == name) {
                return bad("appears more than once");
            }
            if m.iter().any(|x| !x.is_finite()) || v.iter().any(|x| !x.is_finite() || *x < 0.0) {
                return bad("has non-finite or negative moments");
            }
        }
        let mut m = vec![0.0f32; self.extent];
        let mut v = vec![0.0f32; self.extent];
        for g in &self.groups {
            if let Some((_, gm, gv)) = s.groups.iter().find(|(n, gm, _)| *n == g.name && gm.len() == g.len) {
                m[g.offset..g.offset + g.len].copy_from_slice(gm);
                v[g.offset..g.offset + g.len].copy_from_slice(gv);
            }
        }
        if self.extent > 0 {
            ctx.write(&self.m, 0, &m);
            ctx.write(&self.v, 0, &v);
        }
        if self.groups.iter().any(|g| self.cfg.is_sparse(&g.name)) {
            let mut counts = vec![0u32; self.extent];
            for g in self.groups.iter().filter(|g| self.cfg.is_sparse(&g.name)) {
                let dst = &mut counts[g.offset..g.offset + g.len];
                if let Some((_, n)) = s.steps.iter().find(|(n, k)| *n == g.name && k.len() == g.len) {
                    dst.copy_from_slice(n);
                } else if s.groups.iter().any(|(n, gm, _)| *n == g.name && gm.len() == g.len) {
                    dst.fill(s.step.min(u32::MAX as u64) as u32);
                }
            }
            ctx.write(&self.counts, 0, &counts);
        }
        self.step.store(s.step, Ordering::Relaxed);
        Ok(())
    }
}
