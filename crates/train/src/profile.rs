//! Where the GPU training step spends its time: the per-pass timestamps of a window of profiled
//! steps (`TrainConfig::gpu_profile`), summed by stage and by kernel.
//!
//! Profiled steps are submitted and waited for one at a time (their timestamps are read back), so
//! they do not overlap host recording with device work; the timings are those of the GPU executing
//! each compute pass. A step's *span* (first pass begin to last pass end) minus its *busy* time
//! (the sum of its passes) is the time between passes: barriers and launch latency.

use nerf_gpu::profile::PassTiming;
use serde::{Deserialize, Serialize};

/// Which training steps to profile on the GPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProfileWindow {
    /// First profiled step (0-based; leave the first few hundred steps out so the occupancy grid
    /// and the batch size have settled).
    pub start: u64,
    /// Number of consecutive steps profiled.
    pub steps: u64,
}

impl ProfileWindow {
    /// Whether `step` lies in the window.
    pub fn contains(&self, step: u64) -> bool {
        step >= self.start && step - self.start < self.steps
    }

    /// Whether `step` is the window's last step.
    pub fn is_last(&self, step: u64) -> bool {
        self.steps > 0 && step == self.start + self.steps - 1
    }
}

/// Time of one (stage, part, kernel) over the profiled steps.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KernelTime {
    /// Stage of the step (set by the trainer).
    pub stage: String,
    /// Part of the stage (set by the field; empty for the trainer's own kernels).
    pub part: String,
    /// Kernel entry point.
    pub kernel: String,
    /// Passes per step.
    pub calls_per_step: f64,
    /// Milliseconds per step.
    pub ms_per_step: f64,
}

/// Time of one stage over the profiled steps.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StageTime {
    /// Stage name.
    pub stage: String,
    /// Milliseconds per step.
    pub ms_per_step: f64,
    /// Share of the step's busy time.
    pub share: f64,
}

/// The summary written to `gpu_profile.json` and into `metrics.json`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GpuProfile {
    /// The adapter.
    pub adapter: String,
    /// First profiled step.
    pub first_step: u64,
    /// Profiled steps.
    pub steps: u64,
    /// Compute passes per step.
    pub passes_per_step: f64,
    /// Sum of the pass durations, milliseconds per step.
    pub busy_ms_per_step: f64,
    /// First pass begin to last pass end, milliseconds per step.
    pub span_ms_per_step: f64,
    /// Passes that could not be timed (query set full).
    pub untimed_passes: u64,
    /// By stage, in step order.
    pub stages: Vec<StageTime>,
    /// By kernel, slowest first.
    pub kernels: Vec<KernelTime>,
}

/// Accumulates the passes of profiled steps.
#[derive(Clone, Debug, Default)]
pub(crate) struct ProfileAccumulator {
    first_step: Option<u64>,
    steps: u64,
    passes: u64,
    busy_ns: f64,
    span_ns: f64,
    untimed: u64,
    /// (stage, part, kernel) → (calls, ns), in first-seen order.
    kernels: Vec<((String, String, String), u64, f64)>,
}

impl ProfileAccumulator {
    /// Steps added so far.
    pub(crate) fn steps(&self) -> u64 {
        self.steps
    }

    /// Adds one step's passes.
    pub(crate) fn add_step(&mut self, step: u64, passes: &[PassTiming], untimed: usize) {
        self.first_step.get_or_insert(step);
        self.steps += 1;
        self.passes += passes.len() as u64;
        self.untimed += untimed as u64;
        let begin = passes.iter().map(|p| p.begin_ns).fold(f64::INFINITY, f64::min);
        let end = passes.iter().map(|p| p.end_ns).fold(f64::NEG_INFINITY, f64::max);
        if end >= begin {
            self.span_ns += end - begin;
        }
        for p in passes {
            self.busy_ns += p.ns();
            let key = (p.stage.as_str(), p.part.as_str(), p.kernel.as_str());
            match self.kernels.iter_mut().find(|(k, _, _)| (k.0.as_str(), k.1.as_str(), k.2.as_str()) == key) {
                Some((_, calls, ns)) => {
                    *calls += 1;
                    *ns += p.ns();
                }
                None => self.kernels.push(((p.stage.clone(), p.part.clone(), p.kernel.clone()), 1, p.ns())),
            }
        }
    }

    /// The summary (per-step means).
    pub(crate) fn summary(&self, adapter: &str) -> GpuProfile {
        let n = self.steps.max(1) as f64;
        let ms = |ns: f64| ns / n / 1e6;
        let mut stages: Vec<StageTime> = Vec::new();
        for ((stage, _, _), _, ns) in &self.kernels {
            match stages.iter_mut().find(|s| &s.stage == stage) {
                Some(s) => s.ms_per_step += ms(*ns),
                None => stages.push(StageTime { stage: stage.clone(), ms_per_step: ms(*ns), share: 0.0 }),
            }
        }
        let busy = ms(self.busy_ns);
        for s in &mut stages {
            s.share = if busy > 0.0 { s.ms_per_step / busy } else { 0.0 };
        }
        let mut kernels: Vec<KernelTime> = self
            .kernels
            .iter()
            .map(|((stage, part, kernel), calls, ns)| KernelTime {
                stage: stage.clone(),
                part: part.clone(),
                kernel: kernel.clone(),
                calls_per_step: *calls as f64 / n,
                ms_per_step: ms(*ns),
            })
            .collect();
        kernels.sort_by(|a, b| b.ms_per_step.total_cmp(&a.ms_per_step));
        GpuProfile {
            adapter: adapter.to_string(),
            first_step: self.first_step.unwrap_or(0),
            steps: self.steps,
            passes_per_step: self.passes as f64 / n,
            busy_ms_per_step: busy,
            span_ms_per_step: ms(self.span_ns),
            untimed_passes: self.untimed,
            stages,
            kernels,
        }
    }
}

impl GpuProfile {
    /// A Markdown report: stages, then the `top` slowest kernels.
    pub fn table(&self, top: usize) -> String {
        let mut s = format!(
            "GPU profile of {} steps from step {} on {}: {:.3} ms busy per step ({:.3} ms span, {:.0} passes)\n\n| stage | ms/step | share |\n|---|---|---|\n",
            self.steps, self.first_step, self.adapter, self.busy_ms_per_step, self.span_ms_per_step, self.passes_per_step
        );
        for st in &self.stages {
            s += &format!("| {} | {:.3} | {:.1} % |\n", st.stage, st.ms_per_step, 100.0 * st.share);
        }
        s += "\n| stage | part | kernel | calls/step | ms/step |\n|---|---|---|---|---|\n";
        for k in self.kernels.iter().take(top) {
            s += &format!("| {} | {} | {} | {:.1} | {:.3} |\n", k.stage, k.part, k.kernel, k.calls_per_step, k.ms_per_step);
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pass(stage: &str, part: &str, kernel: &str, b: f64, e: f64) -> PassTiming {
        PassTiming { stage: stage.into(), part: part.into(), kernel: kernel.into(), begin_ns: b, end_ns: e }
    }

    #[test]
    fn window_bounds() {
        let w = ProfileWindow { start: 10, steps: 3 };
        assert!(!w.contains(9) && w.contains(10) && w.contains(12) && !w.contains(13));
        assert!(w.is_last(12) && !w.is_last(11));
        assert!(!ProfileWindow { start: 0, steps: 0 }.contains(0));
    }

    #[test]
    fn summary_averages_per_step_and_sorts_kernels() {
        let mut acc = ProfileAccumulator::default();
        acc.add_step(5, &[pass("march", "", "march_fill", 0.0, 1e6), pass("field", "mlp", "fwd", 1.5e6, 4.5e6)], 0);
        acc.add_step(6, &[pass("march", "", "march_fill", 0.0, 3e6), pass("field", "mlp", "fwd", 3e6, 4e6), pass("field", "mlp", "fwd", 4e6, 5e6)], 1);
        let p = acc.summary("test adapter");
        assert_eq!((p.first_step, p.steps, p.untimed_passes), (5, 2, 1));
        assert!((p.passes_per_step - 2.5).abs() < 1e-12);
        // busy: (1 + 3) + (3 + 1 + 1) = 9 ms over 2 steps; span: 4.5 + 5 ms.
        assert!((p.busy_ms_per_step - 4.5).abs() < 1e-12, "{}", p.busy_ms_per_step);
        assert!((p.span_ms_per_step - 4.75).abs() < 1e-12);
        assert_eq!(p.stages.iter().map(|s| s.stage.as_str()).collect::<Vec<_>>(), ["march", "field"]);
        assert!((p.stages[0].ms_per_step - 2.0).abs() < 1e-12 && (p.stages[1].ms_per_step - 2.5).abs() < 1e-12);
        assert!((p.stages.iter().map(|s| s.share).sum::<f64>() - 1.0).abs() < 1e-12);
        assert_eq!(p.kernels[0].kernel, "fwd");
        assert!((p.kernels[0].calls_per_step - 1.5).abs() < 1e-12);
        let t = p.table(10);
        assert!(t.contains("| field | mlp | fwd | 1.5 | 2.500 |"), "{t}");
        let back: GpuProfile = serde_json::from_str(&serde_json::to_string(&p).unwrap()).unwrap();
        assert_eq!(back, p);
    }
}
