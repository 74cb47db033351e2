//! Launches sized by the device's count instead of the buffers' capacity.
//!
//! A training step's sample count is known only on the device (the marcher or the compaction
//! writes it to `counters[1]`), so the per-sample kernels used to be launched for the capacity —
//! twice the target for a step, and more for the density pass — and the extra invocations
//! returned at once. [`DispatchArgs`] records one small kernel (`shaders/dispatch.wgsl`) that
//! turns the count into indirect-dispatch arguments; the kernels that follow it are launched
//! with `dispatch_workgroups_indirect` for exactly the workgroups the count needs. A [`Launch`]
//! carries the choice into every kernel wrapper: [`Launch::direct`] (a host-known size: tests,
//! set-up, fixed batches) or the launch [`DispatchArgs::record`] returns.
//!
//! CPU twin of the argument kernel: [`groups_for`]. `NERF_NO_INDIRECT` (any value) makes every
//! [`DispatchArgs::record`] return a direct launch for the capacity, as before, for A/B timing.

use crate::kernel::{groups_1d, Kernel, MAX_GROUPS_PER_DIM};
use crate::{shaders, GpuContext};

/// Largest `log2` of the items per workgroup the table covers (1024 items).
pub const MAX_K: u32 = 10;
/// Largest third launch dimension the table covers.
pub const MAX_Z: u32 = 32;
const ENTRIES: u32 = MAX_Z * (MAX_K + 1);
/// Most items a [`DispatchArgs`] table launches: 65 535 × 65 535 workgroups of one item.
pub const MAX_ITEMS: u32 = MAX_GROUPS_PER_DIM * MAX_GROUPS_PER_DIM;

/// Workgroup counts `[x, y, z]` for `n` items at `per_group` (a power of two ≤ 1024) items per
/// workgroup and `z` workgroups along the third dimension: `shaders/dispatch.wgsl`'s CPU twin.
/// As [`groups_1d`] except that `n = 0` gives an empty launch. Within the per-dimension limit for
/// `n ≤` [`MAX_ITEMS`] (the most a table is made for).
pub fn groups_for(n: u32, per_group: u32, z: u32) -> [u32; 3] {
    assert!(per_group.is_power_of_two() && per_group <= 1 << MAX_K, "per_group {per_group}");
    let g = n.div_ceil(per_group);
    if g <= MAX_GROUPS_PER_DIM {
        [g, 1, z]
    } else {
        let y = g.div_ceil(MAX_GROUPS_PER_DIM);
        [g.div_ceil(y), y, z]
    }
}

/// Byte offset of entry (`per_group`, `z`) in a [`DispatchArgs`] table, or `None` when the table
/// has no such entry (`per_group` not a power of two ≤ 1024, or `z` outside `1..=32`).
pub fn entry_offset(per_group: u32, z: u32) -> Option<u64> {
    if !per_group.is_power_of_two() || per_group > 1 << MAX_K || z == 0 || z > MAX_Z {
        return None;
    }
    let k = per_group.trailing_zeros();
    Some(12 * ((z - 1) * (MAX_K + 1) + k) as u64)
}

/// How a per-sample kernel is launched: for `capacity` items (host-known), or from a table of
/// indirect arguments that a [`DispatchArgs`] wrote for the device's count.
#[derive(Clone, Copy, Debug)]
pub struct Launch<'a> {
    capacity: usize,
    args: Option<&'a wgpu::Buffer>,
}

impl Launch<'_> {
    /// A launch for `capacity` samples (the kernels still stop at the device's count).
    pub fn direct(capacity: usize) -> Launch<'static> {
        Launch { capacity, args: None }
    }

    /// The most samples the buffers hold (what wrappers check buffer sizes against).
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Whether the kernels are launched from device-written arguments.
    pub fn is_indirect(&self) -> bool {
        self.args.is_some()
    }

    /// Records `kernel` for the batch: `items_per_sample` invocations per sample in workgroups of
    /// `wg` invocations, `z` workgroups along the third dimension. Indirect when this launch has a
    /// table and it holds the shape (`wg / items_per_sample` a power of two ≤ 1024, `z ≤ 32`);
    /// otherwise direct, for the capacity.
    #[allow(clippy::too_many_arguments, clippy::manual_is_multiple_of)] // keeps the MSRV (1.85)
    pub fn record<'b, B: Into<crate::kernel::Bound<'b>> + Copy>(
        &self,
        kernel: &Kernel,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        bindings: &[(u32, B)],
        items_per_sample: u32,
        wg: u32,
        z: u32,
    ) {
        let entry = (items_per_sample > 0 && wg % items_per_sample == 0)
            .then(|| entry_offset(wg / items_per_sample, z))
            .flatten();
        match (self.args, entry) {
            (Some(args), Some(offset)) => kernel.record_indirect(ctx, enc, bindings, args, offset),
            _ => {
                let [x, y, _] = groups_1d(self.capacity * items_per_sample as usize, wg);
                kernel.record(ctx, enc, bindings, [x, y, z]);
            }
        }
    }
}

impl From<usize> for Launch<'static> {
    fn from(capacity: usize) -> Self {
        Launch::direct(capacity)
    }
}

/// The indirect-argument table of one batch and the kernel that fills it (one per field or
/// stage: the table is rewritten for each batch it launches, in submission order).
pub struct DispatchArgs {
    kernel: Kernel,
    capacity: usize,
    cap: wgpu::Buffer,
    args: wgpu::Buffer,
}

impl DispatchArgs {
    /// A table for batches of at most `capacity` items counted in `counters[1]`.
    pub fn new(ctx: &GpuContext, capacity: usize) -> Self {
        Self::for_slot(ctx, capacity, crate::layout::COUNTER_N_SAMPLES)
    }

    /// As [`DispatchArgs::new`] for the count in `counters[slot]`. Panics when `capacity` exceeds
    /// [`MAX_ITEMS`] (no launch of one item per workgroup could cover it; no storage binding holds
    /// that many samples either).
    pub fn for_slot(ctx: &GpuContext, capacity: usize, slot: usize) -> Self {
        assert!(capacity as u64 <= MAX_ITEMS as u64, "dispatch arguments for {capacity} items (at most {MAX_ITEMS})");
        Self {
            kernel: Kernel::new(ctx, &shaders::with_common(shaders::DISPATCH), "dispatch_args", &[("SLOT", slot as f64)]),
            capacity,
            cap: ctx.upload("dispatch cap", &[capacity as u32]),
            args: ctx.zeros("dispatch args", 12 * ENTRIES as usize),
        }
    }

    /// The table (12 bytes per entry; see [`entry_offset`]).
    pub fn buffer(&self) -> &wgpu::Buffer {
        &self.args
    }

    /// Records the table for the count in `counters` (at most the table's capacity) and returns
    /// the launch of a batch of up to `capacity` samples from it — or, under `NERF_NO_INDIRECT`,
    /// records nothing and returns [`Launch::direct`]`(capacity)`.
    pub fn record<'a>(&'a self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, counters: &wgpu::Buffer, capacity: usize) -> Launch<'a> {
        assert!(capacity <= self.capacity, "a batch of {capacity} samples for dispatch arguments made for {}", self.capacity);
        if !ctx.indirect_dispatch {
            return Launch::direct(capacity);
        }
        self.kernel.record(ctx, enc, &[(0, counters), (1, &self.cap), (2, &self.args)], groups_1d(ENTRIES as usize, 64));
        Launch { capacity, args: Some(&self.args) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_cover_the_count_within_the_per_dimension_limit() {
        for n in [0u32, 1, 2, 63, 64, 65, 65_535, 65_536, 64 * 65_535 + 1, 1 << 24, MAX_ITEMS - 1, MAX_ITEMS] {
            for k in 0..=MAX_K {
                let per = 1u32 << k;
                let [x, y, z] = groups_for(n, per, 3);
                assert_eq!(z, 3);
                assert!(x <= MAX_GROUPS_PER_DIM && y <= MAX_GROUPS_PER_DIM, "{n} {per}: {x} {y}");
                let covered = x as u64 * y as u64 * per as u64;
                assert!(covered >= n as u64, "{n} {per}: {x}×{y}");
                // Less than a row or column of workgroups more than needed.
                assert!(covered < n as u64 + (x as u64 + y as u64) * per as u64, "{n} {per}: {x}×{y}");
                if n > 0 {
                    assert_eq!([x, y, 1], groups_1d(n as usize, per), "{n} {per}");
                } else {
                    assert_eq!(x, 0);
                }
            }
        }
    }

    #[test]
    fn entries_are_distinct_and_inside_the_table() {
        let mut seen = std::collections::HashSet::new();
        for z in 1..=MAX_Z {
            for k in 0..=MAX_K {
                let o = entry_offset(1 << k, z).unwrap();
                assert!(o + 12 <= 12 * ENTRIES as u64);
                assert!(seen.insert(o));
            }
        }
        assert_eq!(entry_offset(3, 1), None);
        assert_eq!(entry_offset(2048, 1), None);
        assert_eq!(entry_offset(64, 0), None);
        assert_eq!(entry_offset(64, MAX_Z + 1), None);
    }
}
