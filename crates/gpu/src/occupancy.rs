//! Instant-NGP's occupancy grid on the device (`shaders/occupancy.wgsl`), twin of
//! [`nerf_sampling::OccupancyGrid`].
//!
//! Buffers the grid owns (pub accessors): the EMA density per cell (`n = cascades·res³` f32, `+∞`
//! = never sampled, cell index `level·res³ + x + res·(y + res·z)`, level 0 the finest), the
//! occupancy bitfield (`⌈n/32⌉` u32 words, bit `i mod 32` of word `i/32` = cell `i`, the layout
//! [`crate::sampling`]'s marcher reads) and the ascending list of occupied cell indices (what the
//! post-warm-up update samples from).
//!
//! One update is recorded in two stages so that the trainer can run the field's density kernel in
//! between, all in one submission:
//! 1. [`GpuOccupancyGrid::record_choose`] picks the cells and one jittered point in each
//!    (`positions_out [m][3]`, `cells_out [m]`, `m` written to `counters_out[1]`);
//! 2. the caller evaluates σ at the points into `sigma [m]`;
//! 3. [`GpuOccupancyGrid::record_apply`] applies the EMA max, recomputes the mean and the
//!    threshold exactly as the CPU does, and rebuilds the bitfield and the occupied list.
//!
//! Parity with the CPU: during warm-up (every cell chosen, in order) the update is the CPU's
//! exactly, except for the random jitter inside each cell (the GPU draws it with
//! [`crate::rng::rand_f32`]) and the mean (over the finest level; an `f32` tree + Kahan sum instead of the CPU's `f64`
//! sum: about 1e-7 relative, which can only flip a cell whose `σ·step_size` lies that close to
//! the mean). After warm-up the cells are chosen from the same distribution as the CPU's (uniform
//! cells and uniform occupied cells, with replacement) but with a different random stream, so
//! only statistics can match; the EMA, threshold and bit rules stay exact.
//!
//! The per-update values (seed, warm-up flag, step size) live in a uniform rewritten with
//! [`GpuContext::write`]: record at most one update per submission.

use crate::kernel::{groups_1d, Kernel};
use crate::{shaders, GpuContext, GpuError};
use nerf_sampling::{OccupancyGrid, OccupancyGridConfig, MAX_CASCADES};
use crate::layout::{OccParams};

const WG: u32 = 256;

/// Byte offsets of the per-update fields of [`OccParams`].
const SEED_OFFSET: u64 = 13 * 4;
const STEP_SIZE_OFFSET: u64 = 15 * 4;
/// Byte offset of `mean_cells` in [`OccParams`].
const MEAN_CELLS_OFFSET: u64 = 17 * 4;

struct Kernels {
    choose: Kernel,
    scatter_max: Kernel,
    ema: Kernel,
    reduce: Kernel,
    build_bits: Kernel,
    scan_blocks: Kernel,
    compact: Kernel,
}

/// The occupancy grid on the device; see the module docs for the update protocol.
pub struct GpuOccupancyGrid {
    cfg: OccupancyGridConfig,
    aabb_min: [f32; 3],
    aabb_max: [f32; 3],
    n_cells: usize,
    n_words: usize,
    density: wgpu::Buffer,
    bits: wgpu::Buffer,
    /// Cells a training camera sees (bits as `bits`; all set unless marked).
    seen: wgpu::Buffer,
    tmp: wgpu::Buffer,
    occupied: wgpu::Buffer,
    stats: wgpu::Buffer,
    partials: wgpu::Buffer,
    blocks: wgpu::Buffer,
    /// Per-update uniform (seed/warm from `record_choose`, step size from `record_apply`).
    uniform: wgpu::Buffer,
    /// Uniform of the set-up recomputation (`new`, `upload_from`), so that it never races with
    /// the per-update values.
    setup_uniform: wgpu::Buffer,
    base: OccParams,
    k: Kernels,
}

impl GpuOccupancyGrid {
    /// A grid over `aabb = (min, max)` with every density `+∞` (all cells occupied), like
    /// `OccupancyGrid::new`; the bits are computed with the CPU's initial step size (box diagonal
    /// / 1024). Errors on an invalid configuration or box (the CPU's messages) or a grid larger
    /// than the adapter's storage-buffer binding limit.
    pub fn new(ctx: &GpuContext, cfg: &OccupancyGridConfig, aabb: ([f32; 3], [f32; 3])) -> Result<Self, GpuError> {
        // The CPU grid validates the settings and gives the initial step size.
        let cpu = OccupancyGrid::try_new(cfg.clone(), aabb.0, aabb.1).map_err(GpuError::Unsupported)?;
        let res = cfg.resolution as usize;
        let level_cells = res * res * res;
        let n_cells = cpu.cascades() * level_cells;
        let limit = ctx.device.limits().max_storage_buffer_binding_size;
        // The largest buffer of an update is the caller's `positions_out` (12 bytes per cell).
        if 12 * n_cells as u64 > limit {
            return Err(GpuError::Unsupported(format!(
                "occupancy grid: {res}³ cells need {} MiB of update positions, over the adapter's storage binding limit of {} MiB",
                (12 * n_cells as u64) >> 20,
                limit >> 20
            )));
        }
        let n_words = n_cells.div_ceil(32);
        let n_blocks = n_words.div_ceil(WG as usize);
        let n_partials = n_cells.div_ceil(WG as usize);
        let mut lv_lo = [[0f32; 4]; MAX_CASCADES as usize];
        let mut lv_cell = [[0f32; 4]; MAX_CASCADES as usize];
        for m in 0..cpu.cascades() {
            let (lo, _) = cpu.level_box(m);
            let h = cpu.level_cell_size(m);
            lv_lo[m] = [lo[0], lo[1], lo[2], 0.0];
            lv_cell[m] = [h[0], h[1], h[2], 0.0];
        }
        let base = OccParams {
            aabb_min: aabb.0,
            res: res as u32,
            cell: cpu.cell_size(),
            n_cells: n_cells as u32,
            decay: cfg.decay,
            threshold: cfg.threshold,
            n_words: n_words as u32,
            n_blocks: n_blocks as u32,
            n_partials: n_partials as u32,
            seed: 0,
            warm: 1,
            step_size: cpu.step_size(),
            level_cells: level_cells as u32,
            mean_cells: level_cells as u32,
            _pad: [0; 2],
            lv_lo,
            lv_cell,
        };
        let module = ctx.shader_module("occupancy.wgsl", &shaders::with_common(shaders::OCCUPANCY));
        let mk = |e: &str| Kernel::from_module(ctx, &module, e, &[("WG", WG as f64)]);
        let k = Kernels {
            choose: mk("choose"),
            scatter_max: mk("scatter_max"),
            ema: mk("ema"),
            reduce: mk("reduce"),
            build_bits: mk("build_bits"),
            scan_blocks: mk("scan_blocks"),
            compact: mk("compact"),
        };
        let grid = Self {
            cfg: cfg.clone(),
            aabb_min: aabb.0,
            aabb_max: aabb.1,
            n_cells,
            n_words,
            density: ctx.upload("occupancy.density", &vec![f32::INFINITY; n_cells]),
            bits: ctx.zeros("occupancy.bits", 4 * n_words),
            seen: ctx.upload("occupancy.seen", &vec![u32::MAX; n_words]),
            tmp: ctx.zeros("occupancy.tmp", 4 * n_cells),
            occupied: ctx.zeros("occupancy.occupied", 4 * n_cells),
            stats: ctx.zeros("occupancy.stats", 16),
            partials: ctx.zeros("occupancy.partials", 4 * n_partials),
            blocks: ctx.zeros("occupancy.blocks", 4 * n_blocks),
            uniform: ctx.uniform("occupancy.params", &base),
            setup_uniform: ctx.uniform("occupancy.setup", &base),
            base,
            k,
        };
        grid.recompute(ctx, cpu.step_size(), level_cells as u32);
        Ok(grid)
    }

    /// The configuration.
    pub fn config(&self) -> &OccupancyGridConfig {
        &self.cfg
    }

    /// The box `(min, max)`.
    pub fn aabb(&self) -> ([f32; 3], [f32; 3]) {
        (self.aabb_min, self.aabb_max)
    }

    /// Cells per axis (of every level).
    pub fn resolution(&self) -> usize {
        self.cfg.resolution as usize
    }

    /// Levels of the cascade.
    pub fn cascades(&self) -> usize {
        self.cfg.levels() as usize
    }

    /// Number of cells (`cascades·res³`): also the capacity `positions_out`/`cells_out`/`sigma`
    /// need.
    pub fn n_cells(&self) -> usize {
        self.n_cells
    }

    /// EMA density per cell (`cascades·res³` f32, `+∞` = never sampled).
    pub fn density(&self) -> &wgpu::Buffer {
        &self.density
    }

    /// Occupancy bitfield (`⌈cascades·res³/32⌉` u32 words; bit `i mod 32` of word `i/32` = cell `i`).
    pub fn bitfield(&self) -> &wgpu::Buffer {
        &self.bits
    }

    /// Number of words of [`GpuOccupancyGrid::bitfield`].
    pub fn n_words(&self) -> usize {
        self.n_words
    }

    /// Ascending indices of the occupied cells (the first `n_occupied` of `cascades·res³` slots).
    pub fn occupied_list(&self) -> &wgpu::Buffer {
        &self.occupied
    }

    /// `[n_occupied, m of the last choose, threshold bits, mean bits]` (4 u32).
    pub fn stats(&self) -> &wgpu::Buffer {
        &self.stats
    }

    /// Is `step` a grid-update step? (the CPU's `OccupancyGrid::due`).
    #[allow(clippy::manual_is_multiple_of)]
    pub fn due(&self, step: u64) -> bool {
        self.cfg.update_every == 0 || step % self.cfg.update_every == 0
    }

    /// Stage 1 of an update at training step `step`: chooses the cells (all of them in order
    /// during warm-up, `step < warmup_steps`; else `⌊n/4⌋` uniform plus `⌊n_occupied/4⌋` occupied
    /// ones, with replacement) and one jittered point in each, drawn from `seed`.
    /// Writes `positions_out [m][3]`, `cells_out [m]` (both sized for [`GpuOccupancyGrid::n_cells`])
    /// and `counters_out[1] = m` (slot 0 untouched), the count the density kernel reads.
    #[allow(clippy::too_many_arguments)]
    pub fn record_choose(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        step: u64,
        seed: u32,
        positions_out: &wgpu::Buffer,
        cells_out: &wgpu::Buffer,
        counters_out: &wgpu::Buffer,
    ) {
        let warm = (step < self.cfg.warmup_steps) as u32;
        ctx.write(&self.uniform, SEED_OFFSET, &[seed, warm]);
        self.k.choose.record(
            ctx,
            enc,
            &[(0, &self.uniform), (4, &self.occupied), (5, &self.stats), (8, positions_out), (9, cells_out), (10, counters_out)],
            groups_1d(self.n_cells, WG),
        );
    }

    /// Stage 2 of an update: `sigma [m]` holds σ at the points of the last `record_choose` (same
    /// `cells`); applies `max(decay·old, σ)` per chosen cell (`σ` replaces `+∞`; NaN/negative σ
    /// count as 0, `+∞` as `f32::MAX`), then recomputes the mean, the threshold
    /// `min(threshold, mean·step_size)` (the mean over the finest level), the bitfield and the
    /// occupied list with `step_size`.
    pub fn record_apply(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, cells: &wgpu::Buffer, sigma: &wgpu::Buffer, step_size: f32) {
        ctx.write(&self.uniform, STEP_SIZE_OFFSET, &[step_size]);
        self.k.scatter_max.record(
            ctx,
            enc,
            &[(3, &self.tmp), (5, &self.stats), (9, cells), (11, sigma), (12, &self.seen)],
            groups_1d(self.n_cells, WG),
        );
        self.record_recompute(ctx, enc, &self.uniform);
    }

    /// EMA (a no-op when no cell was chosen), mean, threshold, bits, occupied list.
    fn record_recompute(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, uniform: &wgpu::Buffer) {
        self.k.ema.record(
            ctx,
            enc,
            &[(0, uniform), (1, &self.density), (3, &self.tmp), (6, &self.partials)],
            groups_1d(self.n_cells, WG),
        );
        self.k.reduce.record(ctx, enc, &[(0, uniform), (5, &self.stats), (6, &self.partials)], [1, 1, 1]);
        let words = groups_1d(self.n_words, WG);
        self.k.build_bits.record(
            ctx,
            enc,
            &[(0, uniform), (1, &self.density), (2, &self.bits), (5, &self.stats), (7, &self.blocks)],
            words,
        );
        self.k.scan_blocks.record(ctx, enc, &[(0, uniform), (5, &self.stats), (7, &self.blocks)], [1, 1, 1]);
        self.k.compact.record(ctx, enc, &[(0, uniform), (2, &self.bits), (4, &self.occupied), (7, &self.blocks)], words);
    }

    /// Recomputes bits and the occupied list from the current densities with `step_size` and
    /// submits (set-up path).
    fn recompute(&self, ctx: &GpuContext, step_size: f32, mean_cells: u32) {
        ctx.write(&self.setup_uniform, 0, &[OccParams { step_size, mean_cells, ..self.base }]);
        let mut enc = ctx.encoder("occupancy.recompute");
        self.record_recompute(ctx, &mut enc, &self.setup_uniform);
        ctx.queue.submit([enc.finish()]);
    }

    /// Copies a CPU grid's densities (a checkpoint) and its marks of the cells cameras see
    /// (`OccupancyGrid::mark_seen`: unseen cells are never refreshed; all cells without marks)
    /// and recomputes the bits with its step size.
    /// Errors when its resolution, levels or box differ from this grid's.
    pub fn upload_from(&self, ctx: &GpuContext, grid: &OccupancyGrid) -> Result<(), GpuError> {
        if grid.resolution() != self.resolution() || grid.cascades() != self.cascades() || grid.aabb() != self.aabb() {
            return Err(GpuError::Unsupported(format!(
                "occupancy grid: cannot load a {} × {}³ grid over {:?} into a {} × {}³ grid over {:?}",
                grid.cascades(),
                grid.resolution(),
                grid.aabb(),
                self.cascades(),
                self.resolution(),
                self.aabb()
            )));
        }
        ctx.write(&self.density, 0, grid.densities());
        // The mean's divisor (the cells cameras see), for the updates and the set-up below.
        let mc = grid.mean_cells() as u32;
        ctx.write(&self.uniform, MEAN_CELLS_OFFSET, &[mc]);
        ctx.write(&self.seen, 0, &grid.seen_words().unwrap_or_else(|| vec![u32::MAX; self.n_words]));
        ctx.write(&self.tmp, 0, &vec![0u32; self.n_cells]);
        self.recompute(ctx, grid.step_size(), mc);
        Ok(())
    }

    /// Reads the densities back (`cascades·res³`, for checkpoints: `OccupancyGrid::set_densities`).
    pub fn download(&self, ctx: &GpuContext) -> Result<Vec<f32>, GpuError> {
        ctx.read_f32(&self.density, self.n_cells)
    }

    /// Reads the bitfield back (`⌈cascades·res³/32⌉` words).
    pub fn download_bits(&self, ctx: &GpuContext) -> Result<Vec<u32>, GpuError> {
        ctx.read_u32(&self.bits, self.n_words)
    }

    /// Reads `[n_occupied, m, threshold, mean]` back.
    pub fn download_stats(&self, ctx: &GpuContext) -> Result<GridStats, GpuError> {
        let s = ctx.read_u32(&self.stats, 4)?;
        Ok(GridStats { n_occupied: s[0] as usize, n_chosen: s[1] as usize, threshold: f32::from_bits(s[2]), mean: f32::from_bits(s[3]) })
    }
}

/// Statistics of the last update, read back by [`GpuOccupancyGrid::download_stats`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridStats {
    /// Occupied cells.
    pub n_occupied: usize,
    /// Cells chosen by the last `record_choose`.
    pub n_chosen: usize,
    /// `min(threshold, mean)` the bits were computed with.
    pub threshold: f32,
    /// Mean of `density·step_size` over the cells of the finest level.
    pub mean: f32,
}
