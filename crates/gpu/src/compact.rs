//! Training on compacted samples (instant-ngp): after an inference pass gives σ of every marched
//! sample, [`GpuCompactor`] keeps each ray's leading samples up to where compositing stops
//! (transmittance below the threshold) and packs them into a second sample buffer, on which the
//! training forward and backward run. Kernels in `shaders/compact.wgsl`; CPU twins
//! `nerf_render::composited_counts` and `nerf_sampling::RaySamples::compact_into`.

use crate::kernel::{groups_1d, Kernel};
use crate::layout::{CompactParams, COUNTER_N_RAYS};
use crate::sampling::{GpuSamples, GpuScan};
use crate::{shaders, GpuContext, GpuError};

const WG: u32 = 64;
/// Storage buffers `compact_fill` binds.
const COMPACT_STORAGE_BINDINGS: u32 = 13;

/// Compacts packed samples (count, scan, fill) of up to `capacity_rays` rays into at most
/// `capacity_out` samples. Buffers are sized once.
pub struct GpuCompactor {
    count: Kernel,
    fill: Kernel,
    scan: GpuScan,
    params: wgpu::Buffer,
    counts: wgpu::Buffer,
    raw_offsets: wgpu::Buffer,
    capacity_rays: usize,
    capacity_out: usize,
}

impl GpuCompactor {
    /// Kernels and buffers for `capacity_rays` rays and `capacity_out` kept samples; compositing's
    /// early stop at transmittance `t_threshold` (> 0; 0 keeps every sample).
    pub fn new(ctx: &GpuContext, capacity_rays: usize, capacity_out: usize, t_threshold: f32) -> Result<Self, GpuError> {
        if capacity_rays >= 1 << 30 || capacity_out >= u32::MAX as usize {
            return Err(GpuError::Unsupported(format!("compaction capacities too large ({capacity_rays} rays, {capacity_out} samples)")));
        }
        if !(t_threshold >= 0.0 && t_threshold.is_finite()) {
            return Err(GpuError::Unsupported(format!("compaction needs a finite threshold ≥ 0, got {t_threshold}")));
        }
        let have = ctx.device.limits().max_storage_buffers_per_shader_stage;
        if have < COMPACT_STORAGE_BINDINGS {
            return Err(GpuError::Unsupported(format!(
                "compaction binds {COMPACT_STORAGE_BINDINGS} storage buffers per stage, the adapter allows {have}"
            )));
        }
        let module = ctx.device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("compact.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::with_common(shaders::COMPACT).into()),
        });
        let p = CompactParams { cap_rays: capacity_rays as u32, cap_out: capacity_out as u32, t_threshold, _pad: 0 };
        Ok(Self {
            count: Kernel::from_module(ctx, &module, "compact_count", &[]),
            fill: Kernel::from_module(ctx, &module, "compact_fill", &[]),
            scan: GpuScan::new(ctx, capacity_rays),
            params: ctx.uniform("compact_params", &p),
            counts: ctx.zeros("compact_counts", 4 * capacity_rays.max(1)),
            raw_offsets: ctx.zeros("compact_raw_offsets", 4 * (capacity_rays + 1)),
            capacity_rays,
            capacity_out,
        })
    }

    /// Records the compaction of `src` (`min(src_counters[0], capacity_rays)` rays, σ of its
    /// samples in `sigma`) into `out`, whose counters become `[n_rays, kept samples]`
    /// (`out_counters` must not be `src_counters`). `out` must hold `capacity_out` samples and
    /// `capacity_rays + 1` offsets.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        src_counters: &wgpu::Buffer,
        src: &GpuSamples,
        sigma: &wgpu::Buffer,
        out_counters: &wgpu::Buffer,
        out: &GpuSamples,
    ) {
        assert!(
            out.capacity_samples >= self.capacity_out && out.capacity_rays >= self.capacity_rays && src.capacity_rays >= self.capacity_rays,
            "buffers smaller than the compactor's capacities"
        );
        self.count.record(
            ctx,
            enc,
            &[(0, &self.params), (1, src_counters), (2, &src.offsets), (3, sigma), (4, &src.dt), (5, &self.counts)],
            groups_1d(self.capacity_rays, WG),
        );
        self.scan.record(ctx, enc, &self.counts, &self.raw_offsets, Some((src_counters, COUNTER_N_RAYS)), None);
        self.fill.record(
            ctx,
            enc,
            &[
                (0, &self.params),
                (1, src_counters),
                (2, &src.offsets),
                (4, &src.dt),
                (6, &self.raw_offsets),
                (7, &src.positions),
                (8, &src.dirs),
                (9, &src.t),
                (10, out_counters),
                (11, &out.offsets),
                (12, &out.positions),
                (13, &out.dirs),
                (14, &out.t),
                (15, &out.dt),
            ],
            groups_1d(self.capacity_rays + 1, WG),
        );
    }

    /// Samples a compaction keeps at most.
    pub fn capacity_out(&self) -> usize {
        self.capacity_out
    }
}
