//! Training on compacted samples (instant-ngp): after an inference pass gives σ of every marched
//! sample, [`GpuCompactor`] keeps each ray's leading samples up to where compositing stops
//! (transmittance below the threshold) and packs them into a second sample buffer, on which the
//! training forward and backward run. Kernels in `shaders/compact.wgsl`; CPU twins
//! `nerf_render::composited_counts` and `nerf_sampling::RaySamples::compact_into`.

use crate::dispatch::Launch;
use crate::kernel::{groups_1d, Kernel};
use crate::layout::{CompactParams, RowCopyParams, COUNTER_N_RAYS};
use crate::sampling::{GpuSamples, GpuScan};
use crate::{shaders, GpuContext, GpuError};

const WG: u32 = 64;
/// Storage buffers `compact_fill` binds.
const COMPACT_STORAGE_BINDINGS: u32 = 14;

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
        let module = ctx.shader_module("compact.wgsl", &shaders::with_common(shaders::COMPACT));
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
    /// (`out_counters` must not be `src_counters`), and `out_rows` (u32 per kept sample) its row
    /// in `src` (`nerf_sampling::compacted_rows`). `out` and `out_rows` must hold `capacity_out`
    /// samples, `out` `capacity_rays + 1` offsets.
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
        out_rows: &wgpu::Buffer,
    ) {
        assert!(
            out.capacity_samples >= self.capacity_out && out.capacity_rays >= self.capacity_rays && src.capacity_rays >= self.capacity_rays,
            "buffers smaller than the compactor's capacities"
        );
        assert!(out_rows.size() >= 4 * self.capacity_out as u64, "GpuCompactor: out_rows hold fewer than {} rows", self.capacity_out);
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
                (16, out_rows),
            ],
            groups_1d(self.capacity_rays + 1, WG),
        );
    }

    /// Samples a compaction keeps at most.
    pub fn capacity_out(&self) -> usize {
        self.capacity_out
    }
}

/// A kernel of `compact.wgsl` that moves rows of `row_floats` (1..=65536) f32 (`entry`:
/// `compact_gather` or `copy_rows`; `what` names it in the error).
fn row_kernel(ctx: &GpuContext, entry: &str, what: &str, row_floats: usize) -> Result<Kernel, GpuError> {
    if row_floats == 0 || row_floats > 1 << 16 {
        return Err(GpuError::Unsupported(format!("{what} needs 1..=65536 floats per row, got {row_floats}")));
    }
    Ok(Kernel::new(ctx, &shaders::with_common(shaders::COMPACT), entry, &[("ROW_FLOATS", row_floats as f64)]))
}

/// Gathers per-sample rows of a batch for the samples a [`GpuCompactor`] kept
/// (`compact_gather`): `dst[b] = src[rows[b]]`, rows of `row_floats` f32, for the
/// `counters[1]` kept samples. Used by a field that keeps values of its density pass (the hash
/// field's encodings) so that the training forward does not compute them again.
pub struct GpuRowGather {
    kernel: Kernel,
    row_floats: usize,
}

impl GpuRowGather {
    /// The gather of rows of `row_floats` (≥ 1) f32.
    pub fn new(ctx: &GpuContext, row_floats: usize) -> Result<Self, GpuError> {
        Ok(Self { kernel: row_kernel(ctx, "compact_gather", "a row gather", row_floats)?, row_floats })
    }

    /// Records `dst[b][..] = src[rows[b]][..]` for `b < counters[1]` (counters as a compaction's
    /// `out_counters`); `rows` and `dst` hold `launch.capacity()` rows, every `rows[b]` indexes a
    /// row of `src`.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        rows: &wgpu::Buffer,
        src: &wgpu::Buffer,
        dst: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        let floats = capacity * self.row_floats;
        assert!(floats < u32::MAX as usize, "GpuRowGather: {capacity} rows of {} floats overflow u32 indices", self.row_floats);
        assert!(rows.size() >= 4 * capacity as u64, "GpuRowGather: rows hold fewer than {capacity} entries");
        assert!(dst.size() >= 4 * floats as u64, "GpuRowGather: dst holds fewer than {capacity} rows");
        let b = [(10, counters), (16, rows), (17, src), (18, dst)];
        launch.record(&self.kernel, ctx, enc, &b, self.row_floats as u32, WG, 1);
    }
}

/// Copies the rows of a batch between buffers at row offsets (`copy_rows`): `dst[dst_row + b] =
/// src[src_row + b]`, rows of `row_floats` f32, for the `counters[1]` rows of the batch. A
/// chunked pass (`nerf_field::ChunkedDensity`, the hash field's kept encodings) moves a chunk's
/// samples in and out of the field's buffers with it: a buffer copy would move the chunk's whole
/// capacity, filled or not, as the host does not know the device's count.
pub struct GpuRowCopy {
    kernel: Kernel,
    row_floats: usize,
}

impl GpuRowCopy {
    /// The copy of rows of `row_floats` (≥ 1) f32.
    pub fn new(ctx: &GpuContext, row_floats: usize) -> Result<Self, GpuError> {
        Ok(Self { kernel: row_kernel(ctx, "copy_rows", "a row copy", row_floats)?, row_floats })
    }

    /// The row offsets of one copy, for [`record`](Self::record) (made once per offset pair: a
    /// chunk's offsets do not change between steps).
    pub fn offsets(ctx: &GpuContext, src_row: usize, dst_row: usize) -> RowOffsets {
        let p = RowCopyParams { src_row: src_row as u32, dst_row: dst_row as u32, _pad: [0; 2] };
        RowOffsets { params: ctx.uniform("row copy offsets", &p), src_row, dst_row }
    }

    /// Records `dst[dst_row + b][..] = src[src_row + b][..]` for `b < counters[1]` (at most
    /// `launch.capacity()`); both buffers must hold their offset plus `launch.capacity()` rows.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        offsets: &RowOffsets,
        src: &wgpu::Buffer,
        dst: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let RowOffsets { params, src_row, dst_row } = offsets;
        let (src_row, dst_row) = (*src_row, *dst_row);
        let (capacity, row_bytes) = (launch.capacity(), 4 * self.row_floats as u64);
        assert!(
            ((src_row.max(dst_row) + capacity) * self.row_floats) < u32::MAX as usize,
            "GpuRowCopy: rows {src_row}/{dst_row} + {capacity} of {} floats overflow u32 indices",
            self.row_floats
        );
        assert!(src.size() >= row_bytes * (src_row + capacity) as u64, "GpuRowCopy: src holds fewer than {} rows", src_row + capacity);
        assert!(dst.size() >= row_bytes * (dst_row + capacity) as u64, "GpuRowCopy: dst holds fewer than {} rows", dst_row + capacity);
        let b = [(10, counters), (17, src), (18, dst), (19, params)];
        launch.record(&self.kernel, ctx, enc, &b, self.row_floats as u32, WG, 1);
    }
}

/// The row offsets of a [`GpuRowCopy`] (a uniform buffer and the offsets it holds).
pub struct RowOffsets {
    params: wgpu::Buffer,
    src_row: usize,
    dst_row: usize,
}
