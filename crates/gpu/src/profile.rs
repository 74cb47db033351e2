//! Where a training step spends its GPU time: timestamp queries around every compute pass.
//!
//! Every dispatch of a [`crate::Kernel`] is its own compute pass. While a profile is being recorded
//! ([`GpuContext::profile_start`] … [`GpuContext::profile_finish`]), each pass gets a begin and an
//! end timestamp and is attributed to the current *stage* (set by the trainer: "march", "field
//! forward", …), the current *part* (set by a field: "hash encoding", "density MLP", …) and the
//! kernel's entry point. Off (the default) it costs one uncontended lock per dispatch and
//! allocates nothing. Needs the adapter's `TIMESTAMP_QUERY` feature (the H100 and lavapipe have
//! it).
//!
//! Timestamps measure the GPU executing each pass; the gaps between passes (barriers, launch
//! latency) show up as the difference between a step's span (first begin to last end) and the sum
//! of its passes.

use crate::{GpuContext, GpuError};

/// Passes one profile can time (two queries each; wgpu allows 4096 queries per set).
pub const MAX_PROFILED_PASSES: u32 = wgpu::QUERY_SET_MAX_QUERIES / 2;

/// One timed compute pass.
#[derive(Clone, Debug, PartialEq)]
pub struct PassTiming {
    /// The stage the trainer was recording ("" when none was set).
    pub stage: String,
    /// The part of the stage a field was recording ("" when none was set).
    pub part: String,
    /// The kernel's entry point.
    pub kernel: String,
    /// Start, nanoseconds after the first pass of the profile began.
    pub begin_ns: f64,
    /// End, nanoseconds after the first pass of the profile began.
    pub end_ns: f64,
}

impl PassTiming {
    /// Duration of the pass in nanoseconds.
    pub fn ns(&self) -> f64 {
        (self.end_ns - self.begin_ns).max(0.0)
    }
}

/// The recorder kept in the context (query set and resolve buffer made once, on first use).
pub(crate) struct Recorder {
    query_set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    active: bool,
    stage: String,
    part: String,
    /// (stage, part, kernel) of every timed pass, in recording order.
    passes: Vec<(String, String, String)>,
    /// Passes recorded past [`MAX_PROFILED_PASSES`] (not timed).
    dropped: usize,
}

/// A finished recording: read it back after the command buffer it was recorded into was submitted.
#[must_use = "read the timings back after submitting the encoder"]
pub struct ProfileReadback {
    resolve: wgpu::Buffer,
    passes: Vec<(String, String, String)>,
    dropped: usize,
}

impl ProfileReadback {
    /// Passes recorded beyond [`MAX_PROFILED_PASSES`] (not timed).
    pub fn dropped(&self) -> usize {
        self.dropped
    }

    /// Waits for the submission and returns every timed pass in recording order.
    pub fn read(self, ctx: &GpuContext) -> Result<Vec<PassTiming>, GpuError> {
        let n = self.passes.len();
        if n == 0 {
            return Ok(Vec::new());
        }
        let words = ctx.read_u32(&self.resolve, 4 * n)?;
        let tick = |q: usize| (words[2 * q] as u64) | ((words[2 * q + 1] as u64) << 32);
        let period = ctx.queue.get_timestamp_period() as f64;
        let t0 = (0..n).map(|i| tick(2 * i)).min().unwrap_or(0);
        let ns = |t: u64| t.saturating_sub(t0) as f64 * period;
        Ok(self
            .passes
            .into_iter()
            .enumerate()
            .map(|(i, (stage, part, kernel))| PassTiming {
                stage,
                part,
                kernel,
                begin_ns: ns(tick(2 * i)),
                end_ns: ns(tick(2 * i + 1)),
            })
            .collect())
    }
}

impl GpuContext {
    fn recorder(&self) -> std::sync::MutexGuard<'_, Option<Recorder>> {
        self.profiler.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Starts timing every compute pass recorded from now on, on any encoder, until
    /// [`GpuContext::profile_finish`]. An error when the adapter has no timestamp queries.
    pub fn profile_start(&self) -> Result<(), GpuError> {
        if !self.features.timestamps {
            return Err(GpuError::Unsupported(format!("GPU profiling needs timestamp queries, which the adapter {} lacks", self.describe())));
        }
        let mut r = self.recorder();
        let r = r.get_or_insert_with(|| Recorder {
            query_set: self.device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("profile"),
                ty: wgpu::QueryType::Timestamp,
                count: 2 * MAX_PROFILED_PASSES,
            }),
            resolve: self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("profile resolve"),
                size: (2 * MAX_PROFILED_PASSES * wgpu::QUERY_SIZE) as u64,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            active: false,
            stage: String::new(),
            part: String::new(),
            passes: Vec::new(),
            dropped: 0,
        });
        r.active = true;
        r.stage.clear();
        r.part.clear();
        r.passes.clear();
        r.dropped = 0;
        Ok(())
    }

    /// Whether a profile is being recorded.
    pub fn profiling(&self) -> bool {
        self.recorder().as_ref().is_some_and(|r| r.active)
    }

    /// Names the stage the following passes belong to (and clears the part); a no-op unless a
    /// profile is being recorded.
    pub fn profile_stage(&self, stage: &str) {
        if let Some(r) = self.recorder().as_mut().filter(|r| r.active) {
            r.stage.clear();
            r.stage.push_str(stage);
            r.part.clear();
        }
    }

    /// Names the part of the current stage the following passes belong to (fields use it to tell
    /// their encodings and networks apart); a no-op unless a profile is being recorded.
    pub fn profile_part(&self, part: &str) {
        if let Some(r) = self.recorder().as_mut().filter(|r| r.active) {
            r.part.clear();
            r.part.push_str(part);
        }
    }

    /// The timestamp writes for the next pass of `kernel`, or `None` when not profiling (or the
    /// query set is full).
    pub(crate) fn profile_pass(&self, kernel: &str) -> Option<(wgpu::QuerySet, u32)> {
        let mut g = self.recorder();
        let r = g.as_mut().filter(|r| r.active)?;
        if r.passes.len() as u32 >= MAX_PROFILED_PASSES {
            r.dropped += 1;
            return None;
        }
        let i = r.passes.len() as u32;
        r.passes.push((r.stage.clone(), r.part.clone(), kernel.to_string()));
        Some((r.query_set.clone(), 2 * i))
    }

    /// Stops recording and records the resolve of the timestamps into `enc` (which must be the
    /// last encoder that recorded profiled passes, submitted after the others). `None` when no
    /// profile was being recorded.
    pub fn profile_finish(&self, enc: &mut wgpu::CommandEncoder) -> Option<ProfileReadback> {
        let mut g = self.recorder();
        let r = g.as_mut().filter(|r| r.active)?;
        r.active = false;
        let n = r.passes.len() as u32;
        if n > 0 {
            enc.resolve_query_set(&r.query_set, 0..2 * n, &r.resolve, 0);
        }
        Some(ProfileReadback { resolve: r.resolve.clone(), passes: std::mem::take(&mut r.passes), dropped: r.dropped })
    }
}
