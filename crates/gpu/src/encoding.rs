//! Input encodings on the GPU: Instant-NGP's multiresolution hash grid (forward, parameter
//! backward and the gradient w.r.t. the positions), a dense trilinear grid (DVGO's voxel grids:
//! forward and parameter backward), the spherical-harmonics direction encoding (forward and the
//! gradient w.r.t. the directions) and NeRF's frequency encoding (forward only). Each matches its CPU twin in `nerf-encoding` (same layouts, formulas and summation
//! order; the tests compare them on random inputs).
//!
//! Every wrapper compiles its pipelines once in `new` and only RECORDS dispatches into the
//! caller's encoder (`record_*`): no submission, no read-back. The number of samples of a step is
//! read on the device from `counters[COUNTER_N_SAMPLES]` ([`crate::layout::COUNTER_N_SAMPLES`]);
//! launches cover a host-known `capacity` and the invocations past `n` return. All arrays are
//! row-major `f32`, laid out as on the CPU.

use crate::dispatch::Launch;
use crate::kernel::{groups_1d, Bound, Kernel};
use crate::{shaders, GpuContext, GpuError};
use nerf_encoding::{FrequencyEncodingConfig, HashGrid, HashGridConfig, Precision, ShConfig};
pub use crate::layout::{DenseGridParams, HashGridParams};

/// Largest number of levels the hash-grid uniform holds (`HashGridConfig::validate` allows 64).
pub const MAX_HASH_LEVELS: usize = 64;

/// How the hash-grid backward accumulates into the gradient buffer.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AtomicMode {
    /// `atomic<f32>` + `atomicAdd` when the adapter has `SHADER_FLOAT32_ATOMIC`, else the
    /// compare-and-swap loop.
    #[default]
    Auto,
    /// As `Auto`, and on an adapter with `SUBGROUP` as well the additions of the dense (coarse)
    /// levels are summed over each subgroup before the atomics (`hash_backward_subgroup`): fewer
    /// atomics on the slots that the neighbouring samples of a batch share. Opt-in until timed on
    /// hardware where atomics contend (on lavapipe it is slower).
    SubgroupSums,
    /// Always the compare-and-swap loop on `atomic<u32>` (bit casts); for adapters without float
    /// atomics, and for testing that path on adapters with them.
    CompareExchange,
}

/// The multiresolution hash encoding on the GPU (`shaders/hash_grid.wgsl`), twin of
/// [`nerf_encoding::HashGrid`].
///
/// The parameters live in a caller-owned storage buffer of `n_params()` `f32` in exactly the
/// layout of [`HashGrid::params`] (level by level, slot-major: feature `j` of slot `s` of level
/// `l` at `level_offsets()[l] + s·F + j`), so checkpoints move between the CPU and the GPU as they
/// are. Positions are in world units and normalised with the box given at construction as
/// `nerf-field-hash` does: `clamp((p − aabb_min)·(1/(aabb_max − aabb_min)), 0, 1)`, NaN → 0.
///
/// Work split: one invocation per (sample, level), the level in the workgroup's `z` index, so a
/// workgroup reads a single level's table (cache locality, as tiny-cuda-nn). The forward reads the
/// `F` features of a corner with one vector load (`f32`/`vec2`/`vec4`). With
/// [`nerf_encoding::Precision::F16`] in the config (F = 2 only) the forward reads an `f16` mirror
/// of the table instead (half the bytes per lookup; the f32 parameters stay the master that the
/// backward and the optimiser use): each [`GpuHashGrid::record_forward`] first rewrites the mirror
/// from the parameters it is given (one pass over the table), so the mirror can never be stale.
///
/// Measured on the H100 (wgpu 30, Vulkan; L = 16, F = 2, T = 2^19, 2^18–2^20 samples): forward
/// 700–980 M samples/s, backward with `atomic<f32>` 270–350 M samples/s, with the
/// compare-and-swap fallback 55–80 M samples/s (F = 4: 680–880 / 150–190 / 35–48).
pub struct GpuHashGrid {
    cfg: HashGridConfig,
    resolutions: Vec<u32>,
    offsets: Vec<usize>,
    dense: Vec<bool>,
    params: HashGridParams,
    uniform: wgpu::Buffer,
    forward: Kernel,
    backward: Kernel,
    input_grad: Kernel,
    float_atomics: bool,
    subgroup_sums: bool,
    mirror: Option<F16Mirror>,
}

/// The `f16` mirror of the table and its kernels (`storage = "f16"`).
struct F16Mirror {
    words: usize,
    buffer: wgpu::Buffer,
    sync: Kernel,
    forward: Kernel,
}

/// Workgroup size of the hash-grid kernels.
const HASH_WG: u32 = 128;

/// `1 / (max − min)` per axis in `f32`, or an error naming the bad axis.
fn inv_extent(aabb_min: [f32; 3], aabb_max: [f32; 3]) -> Result<[f32; 3], GpuError> {
    let mut inv = [0.0f32; 3];
    for a in 0..3 {
        let e = aabb_max[a] - aabb_min[a];
        if !(e.is_finite() && e > 0.0 && aabb_min[a].is_finite()) {
            return Err(GpuError::Unsupported(format!(
                "hash grid scene box [{:?}, {:?}] has extent {e} on axis {a} (need a finite box with max > min)",
                aabb_min, aabb_max
            )));
        }
        inv[a] = 1.0 / e;
    }
    Ok(inv)
}

/// `src` without the lines between `//#begin NAME` and `//#end NAME`.
fn strip_section(src: &str, name: &str) -> String {
    let (begin, end) = (format!("//#begin {name}"), format!("//#end {name}"));
    assert!(src.contains(&begin) && src.contains(&end), "a WGSL source lost its `{name}` section");
    let mut out = String::with_capacity(src.len());
    let mut skipping = false;
    for line in src.lines() {
        let t = line.trim();
        if t == begin {
            skipping = true;
        } else if t == end {
            skipping = false;
        } else if !skipping {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

/// The hash-grid WGSL for `f` features per level, with the `atomic<f32>` section kept or
/// stripped, the subgroup section (inside it) kept only with `subgroups` (and the f16-mirror
/// section, which needs F = 2, stripped for other F), and the number of `Feat` vectors per slot.
fn hash_grid_source(f: usize, float_atomics: bool, subgroups: bool) -> (String, u32) {
    const ALIAS: &str = "alias Feat = vec2<f32>;";
    let (ty, per_slot) = match f {
        1 => ("f32", 1),
        2 => ("vec2<f32>", 1),
        4 => ("vec4<f32>", 1),
        8 => ("vec4<f32>", 2),
        other => unreachable!("n_features_per_level {other} passed validation"),
    };
    assert!(shaders::HASH_GRID.contains(ALIAS), "hash_grid.wgsl lost its `{ALIAS}` line");
    let mut src = shaders::HASH_GRID.replacen(ALIAS, &format!("alias Feat = {ty};"), 1);
    if !float_atomics {
        src = strip_section(&src, "f32-atomics");
    } else if !subgroups {
        src = strip_section(&src, "subgroups");
    }
    if f != 2 {
        src = strip_section(&src, "f16-mirror");
    }
    (shaders::with_common(&src), per_slot)
}

impl GpuHashGrid {
    /// Builds the pipelines for `cfg` over the scene box `[aabb_min, aabb_max]` (world units), with
    /// float atomics in the backward when the adapter has them.
    pub fn new(ctx: &GpuContext, cfg: &HashGridConfig, aabb_min: [f32; 3], aabb_max: [f32; 3]) -> Result<Self, GpuError> {
        Self::with_atomics(ctx, cfg, aabb_min, aabb_max, AtomicMode::Auto)
    }

    /// As [`GpuHashGrid::new`], choosing how the backward accumulates.
    pub fn with_atomics(
        ctx: &GpuContext,
        cfg: &HashGridConfig,
        aabb_min: [f32; 3],
        aabb_max: [f32; 3],
        mode: AtomicMode,
    ) -> Result<Self, GpuError> {
        if let Some(s) = cfg.grad_f16_scale {
            return Err(GpuError::Unsupported(format!(
                "hash grid: grad_f16_scale = {s} (the table's gradient summed in f16) is implemented on the CPU only: leave it out to train on the GPU"
            )));
        }
        // Resolutions, offsets and dense flags from the CPU encoding itself: equal by construction.
        let grid = HashGrid::<f32>::zeros(cfg).map_err(|e| GpuError::Unsupported(e.to_string()))?;
        let l = grid.n_levels();
        if l > MAX_HASH_LEVELS {
            return Err(GpuError::Unsupported(format!("hash grid: {l} levels (at most {MAX_HASH_LEVELS})")));
        }
        let n_params = grid.level_offsets()[l];
        let max_binding = ctx.device.limits().max_storage_buffer_binding_size;
        if n_params as u64 * 4 > max_binding || n_params > u32::MAX as usize {
            return Err(GpuError::Unsupported(format!(
                "hash grid: {n_params} parameters ({} MiB) exceed the adapter's largest storage binding ({} MiB); lower log2_hashmap_size",
                (n_params * 4) >> 20,
                max_binding >> 20
            )));
        }
        let mask = ((1u64 << cfg.log2_hashmap_size) - 1) as u32;
        let mut levels = [[0u32; 4]; MAX_HASH_LEVELS];
        for (li, lv) in levels.iter_mut().enumerate().take(l) {
            *lv = [grid.resolutions()[li], grid.level_offsets()[li] as u32, grid.is_dense(li) as u32, mask];
        }
        let mut scales = [[0f32; 4]; MAX_HASH_LEVELS / 4];
        for (li, s) in cfg.level_scales().into_iter().enumerate() {
            scales[li / 4][li % 4] = s;
        }
        let params = HashGridParams {
            aabb_min,
            n_levels: l as u32,
            inv_extent: inv_extent(aabb_min, aabb_max)?,
            offset: cfg.level_offset(),
            levels,
            scales,
        };
        let float_atomics = mode != AtomicMode::CompareExchange && ctx.features.float32_atomics;
        let subgroup_sums = float_atomics && mode == AtomicMode::SubgroupSums && ctx.features.subgroups;
        let f = cfg.n_features_per_level;
        let (src, per_slot) = hash_grid_source(f, float_atomics, subgroup_sums);
        let module = ctx.shader_module("hash_grid.wgsl", &src);
        let constants = [("FEATS", f as f64), ("VEC_PER_SLOT", per_slot as f64), ("WG", HASH_WG as f64)];
        let forward = Kernel::from_module(ctx, &module, "hash_forward", &constants);
        let backward_entry = match (float_atomics, subgroup_sums) {
            (true, true) => "hash_backward_subgroup",
            (true, false) => "hash_backward_atomic",
            (false, _) => "hash_backward_cas",
        };
        let backward = Kernel::from_module(ctx, &module, backward_entry, &constants);
        let input_grad = Kernel::from_module(ctx, &module, "hash_input_grad", &constants);
        let mirror = match cfg.storage {
            Precision::F32 => None,
            Precision::F16 if f != 2 => {
                return Err(GpuError::Unsupported(format!(
                    "hash grid: storage = \"f16\" needs 2 features per level on the GPU (got {f}); use storage = \"f32\""
                )))
            }
            Precision::F16 => Some(F16Mirror {
                words: n_params / 2,
                buffer: ctx.zeros("hash table f16", 2 * n_params),
                sync: Kernel::from_module(ctx, &module, "hash_mirror_f16", &constants),
                forward: Kernel::from_module(ctx, &module, "hash_forward_f16", &constants),
            }),
        };
        Ok(Self {
            cfg: cfg.clone(),
            resolutions: grid.resolutions().to_vec(),
            offsets: grid.level_offsets().to_vec(),
            dense: (0..l).map(|li| grid.is_dense(li)).collect(),
            uniform: ctx.uniform("hash_grid_params", &params),
            params,
            forward,
            backward,
            input_grad,
            float_atomics,
            subgroup_sums,
            mirror,
        })
    }

    /// Moves the scene box (takes effect for dispatches submitted after this call).
    pub fn set_aabb(&mut self, ctx: &GpuContext, aabb_min: [f32; 3], aabb_max: [f32; 3]) -> Result<(), GpuError> {
        self.params.inv_extent = inv_extent(aabb_min, aabb_max)?;
        self.params.aabb_min = aabb_min;
        ctx.write(&self.uniform, 0, std::slice::from_ref(&self.params));
        Ok(())
    }

    /// The configuration.
    pub fn config(&self) -> &HashGridConfig {
        &self.cfg
    }

    /// Number of `f32` parameters (the length of the params and grads buffers).
    pub fn n_params(&self) -> usize {
        self.offsets[self.offsets.len() - 1]
    }

    /// Floats per encoded sample, `L·F`.
    pub fn output_dim(&self) -> usize {
        self.resolutions.len() * self.cfg.n_features_per_level
    }

    /// Number of levels L.
    pub fn n_levels(&self) -> usize {
        self.resolutions.len()
    }

    /// Resolution (cells per axis) of each level (as [`HashGrid::resolutions`]).
    pub fn resolutions(&self) -> &[u32] {
        &self.resolutions
    }

    /// Start of each level's parameters (length L + 1, as [`HashGrid::level_offsets`]).
    pub fn level_offsets(&self) -> &[usize] {
        &self.offsets
    }

    /// Whether `level` is stored densely (as [`HashGrid::is_dense`]).
    pub fn is_dense(&self, level: usize) -> bool {
        self.dense[level]
    }

    /// Whether the backward adds with `atomic<f32>` (else the compare-and-swap loop).
    pub fn uses_float_atomics(&self) -> bool {
        self.float_atomics
    }

    /// Whether the backward sums the dense levels' additions over each subgroup before the
    /// atomics ([`AtomicMode::SubgroupSums`] on an adapter with float atomics and subgroups).
    pub fn uses_subgroup_sums(&self) -> bool {
        self.subgroup_sums
    }

    /// Whether the forward reads an `f16` mirror of the table (`storage = "f16"`).
    pub fn uses_f16_mirror(&self) -> bool {
        self.mirror.is_some()
    }

    /// The `f16` mirror as the last forward wrote it (`u32` words, two features each), or `None`
    /// for `storage = "f32"` (tests compare it with the CPU's mirror).
    pub fn mirror_buffer(&self) -> Option<&wgpu::Buffer> {
        self.mirror.as_ref().map(|m| &m.buffer)
    }

    /// The scene box's lower corner and `1/extent` the kernels normalise with.
    pub fn params(&self) -> &HashGridParams {
        &self.params
    }

    /// Records the forward: `features[i][l·F + j]` for the `n = counters[1]` samples of
    /// `positions` (`[n][3]`, world units), reading `params` (`n_params()` f32). Buffers hold at
    /// least `launch.capacity()` samples; `n ≤` that.
    #[allow(clippy::too_many_arguments)]
    pub fn record_forward<'a>(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        positions: impl Into<Bound<'a>>,
        params: &wgpu::Buffer,
        features: impl Into<Bound<'a>>,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        let (positions, features): (Bound<'a>, Bound<'a>) = (positions.into(), features.into());
        assert!(positions.size() >= 12 * capacity as u64, "GpuHashGrid: positions hold fewer than {capacity} samples");
        assert!(
            features.size() >= 4 * (capacity * self.output_dim()) as u64,
            "GpuHashGrid: features hold fewer than {capacity}·{} floats",
            self.output_dim()
        );
        assert!(params.size() >= 4 * self.n_params() as u64, "GpuHashGrid: params hold fewer than {} floats", self.n_params());
        let z = self.n_levels() as u32;
        match &self.mirror {
            None => {
                let b = [(0, (&self.uniform).into()), (1, counters.into()), (2, positions), (3, params.into()), (4, features)];
                launch.record(&self.forward, ctx, enc, &b, 1, HASH_WG, z);
            }
            Some(m) => {
                m.sync.record(ctx, enc, &[(3, params), (9, &m.buffer)], groups_1d(m.words, HASH_WG));
                let b = [(0, (&self.uniform).into()), (1, counters.into()), (2, positions), (8, (&m.buffer).into()), (4, features)];
                launch.record(&m.forward, ctx, enc, &b, 1, HASH_WG, z);
            }
        }
    }

    /// Records the backward: ADDS dL/dparams to `grads` (`n_params()` f32, the params' layout)
    /// from `d_features` (`[n][L·F]`) for the `n = counters[1]` samples of `positions`. No
    /// gradient w.r.t. the positions. The order of the atomic additions is unspecified, so sums
    /// differ from the CPU's in the last bits.
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        d_features: &wgpu::Buffer,
        grads: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        assert!(positions.size() >= 12 * capacity as u64, "GpuHashGrid: positions hold fewer than {capacity} samples");
        assert!(
            d_features.size() >= 4 * (capacity * self.output_dim()) as u64,
            "GpuHashGrid: d_features hold fewer than {capacity}·{} floats",
            self.output_dim()
        );
        assert!(grads.size() >= 4 * self.n_params() as u64, "GpuHashGrid: grads hold fewer than {} floats", self.n_params());
        let slot = if self.float_atomics { 7 } else { 6 };
        let b = [(0, &self.uniform), (1, counters), (2, positions), (5, d_features), (slot, grads)];
        launch.record(&self.backward, ctx, enc, &b, 1, HASH_WG, self.n_levels() as u32);
    }

    /// Records the gradient w.r.t. the positions (camera pose refinement): for the
    /// `n = counters[1]` samples of `positions` (`[n][3]`, world units), OVERWRITES
    /// `d_positions[3i..3i + 3]` with dL/d(world position) given `d_enc` (`[n][L·F]`, dL/d(encoding),
    /// the layout [`GpuHashGrid::record_backward`] reads), reading the table from the f32
    /// `params` (`n_params()` floats; never the f16 mirror). Rows past `n` are left untouched; no
    /// parameter gradient is added.
    ///
    /// Twin of `HashGrid::backward(xn, d_enc, _, Some(d_input))` followed by the chain rule
    /// through `nerf-field-hash`'s normalisation `xn = clamp((p − aabb_min)·inv_extent, 0, 1)`:
    /// the interpolation's derivative summed over the levels (each times its resolution),
    /// multiplied by `inv_extent[a]`, and 0 on an axis where `xn[a]` is not strictly inside
    /// `(0, 1)` (on or outside the box's faces). One invocation per sample (no atomics, so the
    /// result does not depend on the launch); buffers hold at least `launch.capacity()` samples.
    #[allow(clippy::too_many_arguments)]
    pub fn record_input_gradient(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        params: &wgpu::Buffer,
        d_enc: &wgpu::Buffer,
        d_positions: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        assert!(positions.size() >= 12 * capacity as u64, "GpuHashGrid: positions hold fewer than {capacity} samples");
        assert!(d_positions.size() >= 12 * capacity as u64, "GpuHashGrid: d_positions hold fewer than {capacity} samples");
        assert!(
            d_enc.size() >= 4 * (capacity * self.output_dim()) as u64,
            "GpuHashGrid: d_enc holds fewer than {capacity}·{} floats",
            self.output_dim()
        );
        assert!(params.size() >= 4 * self.n_params() as u64, "GpuHashGrid: params hold fewer than {} floats", self.n_params());
        let b = [(0, &self.uniform), (1, counters), (2, positions), (5, d_enc), (10, params), (11, d_positions)];
        launch.record(&self.input_grad, ctx, enc, &b, 1, HASH_WG, 1);
    }
}

/// Workgroup size of the dense-grid kernels.
const DENSE_WG: u32 = 128;

/// A dense trilinear grid on the GPU (`shaders/dense_grid.wgsl`), twin of
/// [`nerf_encoding::DenseGrid`] read at world positions normalised to the scene box as
/// `nerf-field-voxel` does (`clamp((p − aabb_min)·inv_extent, 0, 1)`, NaN → 0). Its values, times
/// a constant `scale`, go to columns `col .. col + C` of output rows of `stride` floats, so the
/// grids of a field can fill the columns of one buffer; the backward reads its gradient from the
/// same columns and adds `scale ·` it to the parameters' gradient.
pub struct GpuDenseGrid {
    params: DenseGridParams,
    uniform: wgpu::Buffer,
    forward: Kernel,
    backward: Kernel,
    float_atomics: bool,
}

impl GpuDenseGrid {
    /// The pipelines for a grid of `resolution` cells per axis and `channels` values per vertex
    /// over the box at `aabb_min` with `1/extent` = `inv_extent`, writing `scale ·` its values to
    /// columns `col..col + channels` of rows of `stride` floats (`(stride, col)`). The backward adds
    /// with float atomics when the adapter has them (unless `mode` is
    /// [`AtomicMode::CompareExchange`]; there are no subgroup sums here, so `SubgroupSums` is
    /// `Auto`).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: &GpuContext,
        resolution: usize,
        channels: usize,
        aabb_min: [f32; 3],
        inv_extent: [f32; 3],
        scale: f32,
        (stride, col): (usize, usize),
        mode: AtomicMode,
    ) -> Result<Self, GpuError> {
        let bad = |m: String| Err(GpuError::Unsupported(format!("dense grid: {m}")));
        let grid = nerf_encoding::DenseGrid::<f32>::zeros(resolution, channels);
        if let Err(e) = grid {
            return bad(e.to_string());
        }
        if col + channels > stride {
            return bad(format!("columns {col}..{} do not fit rows of {stride} floats", col + channels));
        }
        if !(aabb_min.iter().chain(&inv_extent).all(|v| v.is_finite()) && inv_extent.iter().all(|&v| v > 0.0)) {
            return bad(format!("scene box at {aabb_min:?} with 1/extent {inv_extent:?} (need finite values and 1/extent > 0)"));
        }
        if !scale.is_finite() {
            return bad(format!("scale {scale} is not finite"));
        }
        let n_vertices = (resolution + 1).pow(3);
        let n_params = n_vertices * channels;
        let max_binding = ctx.device.limits().max_storage_buffer_binding_size;
        if n_params as u64 * 4 > max_binding || n_params > u32::MAX as usize {
            return bad(format!(
                "{n_params} parameters ({} MiB) exceed the adapter's largest storage binding ({} MiB); lower the resolution",
                (n_params * 4) >> 20,
                max_binding >> 20
            ));
        }
        let params = DenseGridParams {
            aabb_min,
            res: resolution as u32,
            inv_extent,
            channels: channels as u32,
            stride: stride as u32,
            col: col as u32,
            scale,
            n_vertices: n_vertices as u32,
        };
        let float_atomics = mode != AtomicMode::CompareExchange && ctx.features.float32_atomics;
        let mut src = shaders::DENSE_GRID.to_string();
        if !float_atomics {
            src = strip_section(&src, "f32-atomics");
        }
        let module = ctx.shader_module("dense_grid.wgsl", &shaders::with_common(&src));
        let constants = [("WG", DENSE_WG as f64)];
        let backward_entry = if float_atomics { "dense_backward_atomic" } else { "dense_backward_cas" };
        Ok(Self {
            uniform: ctx.uniform("dense_grid_params", &params),
            params,
            forward: Kernel::from_module(ctx, &module, "dense_forward", &constants),
            backward: Kernel::from_module(ctx, &module, backward_entry, &constants),
            float_atomics,
        })
    }

    /// The uniform the kernels read.
    pub fn params(&self) -> &DenseGridParams {
        &self.params
    }

    /// Number of `f32` parameters, `C·(R+1)³` (the length of the params and grads buffers).
    pub fn n_params(&self) -> usize {
        self.params.n_vertices as usize * self.params.channels as usize
    }

    /// Whether the backward adds with `atomic<f32>` (else the compare-and-swap loop).
    pub fn uses_float_atomics(&self) -> bool {
        self.float_atomics
    }

    fn check(&self, what: &str, positions: &wgpu::Buffer, rows: &wgpu::Buffer, params: &wgpu::Buffer, launch: &Launch<'_>) {
        let capacity = launch.capacity();
        let stride = self.params.stride as usize;
        assert!(positions.size() >= 12 * capacity as u64, "GpuDenseGrid: positions hold fewer than {capacity} samples");
        assert!(rows.size() >= 4 * (capacity * stride) as u64, "GpuDenseGrid: {what} holds fewer than {capacity}·{stride} floats");
        assert!(params.size() >= 4 * self.n_params() as u64, "GpuDenseGrid: params hold fewer than {} floats", self.n_params());
    }

    /// Records the forward for the `n = counters[1]` samples of `positions` (`[n][3]`, world
    /// units): `out[i·stride + col + c] = scale · (interpolation of channel c)`, reading `params`
    /// (`n_params()` f32, [`nerf_encoding::DenseGrid::params`]' layout); the rows' other columns
    /// are left as they are. Buffers hold at least `launch.capacity()` samples.
    #[allow(clippy::too_many_arguments)]
    pub fn record_forward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        params: &wgpu::Buffer,
        out: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        self.check("out", positions, out, params, &launch);
        let b = [(0, &self.uniform), (1, counters), (2, positions), (3, params), (4, out)];
        launch.record(&self.forward, ctx, enc, &b, 1, DENSE_WG, 1);
    }

    /// Records the backward: ADDS `scale · w · d_out[i·stride + col + c]` to the gradient of every
    /// corner `w` of sample `i`'s cell in channel `c` (`grads`: the params' layout) for the
    /// `n = counters[1]` samples of `positions`. No gradient w.r.t. the positions. The order of
    /// the atomic additions is unspecified, so sums differ from the CPU's in the last bits.
    #[allow(clippy::too_many_arguments)]
    pub fn record_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        d_out: &wgpu::Buffer,
        grads: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        self.check("d_out", positions, d_out, grads, &launch);
        let slot = if self.float_atomics { 7 } else { 6 };
        let b = [(0, &self.uniform), (1, counters), (2, positions), (5, d_out), (slot, grads)];
        launch.record(&self.backward, ctx, enc, &b, 1, DENSE_WG, 1);
    }
}

/// Workgroup size of the SH and frequency kernels.
const ENC_WG: u32 = 256;

/// The spherical-harmonics direction encoding on the GPU (`shaders/sh.wgsl`), twin of
/// [`nerf_encoding::SphericalHarmonics`]: `degree²` outputs per sample, and the gradient w.r.t.
/// the directions. One invocation per sample.
pub struct GpuSphericalHarmonics {
    degree: u32,
    kernel: Kernel,
    input_grad: Kernel,
    grad_layouts: GradLayouts,
}

/// Uniforms `[stride, offset, 0, 0]` saying where an input-gradient kernel finds a sample's
/// ∂L/∂(encoding) in a wider row, one per layout asked for (each written once, so launches with
/// different layouts can share a submission).
#[derive(Default)]
struct GradLayouts(std::sync::Mutex<Vec<([u32; 2], wgpu::Buffer)>>);

impl GradLayouts {
    /// The uniform of rows of `stride` floats whose encoding's gradient starts at column
    /// `offset`, checked to hold `width` columns from there for `capacity` rows in `d_out`.
    #[allow(clippy::too_many_arguments)]
    fn get(&self, ctx: &GpuContext, what: &str, d_out: &wgpu::Buffer, stride: usize, offset: usize, width: usize, capacity: usize) -> wgpu::Buffer {
        assert!(stride >= offset + width, "{what}: rows of {stride} floats cannot hold {width} gradients from column {offset}");
        let end = capacity.max(1) * stride;
        assert!(end <= u32::MAX as usize, "{what}: {capacity} rows of {stride} floats overflow u32");
        let need = if capacity == 0 { 0 } else { (capacity - 1) * stride + offset + width };
        assert!(d_out.size() >= 4 * need as u64, "{what}: the gradient rows hold fewer than {need} floats");
        let key = [stride as u32, offset as u32];
        let mut layouts = self.0.lock().unwrap_or_else(|e| e.into_inner());
        match layouts.iter().find(|(k, _)| *k == key) {
            Some((_, b)) => b.clone(),
            None => {
                let b = ctx.uniform("input gradient layout", &[key[0], key[1], 0u32, 0u32]);
                layouts.push((key, b.clone()));
                b
            }
        }
    }
}

impl GpuSphericalHarmonics {
    /// Builds the pipeline for `cfg.degree` bands (1..=4).
    pub fn new(ctx: &GpuContext, cfg: &ShConfig) -> Result<Self, GpuError> {
        cfg.validate().map_err(|e| GpuError::Unsupported(e.to_string()))?;
        let module = ctx.shader_module("sh.wgsl", &shaders::with_common(shaders::SH));
        let constants = [("DEGREE", cfg.degree as f64), ("WG", ENC_WG as f64)];
        let kernel = Kernel::from_module(ctx, &module, "sh_forward", &constants);
        let input_grad = Kernel::from_module(ctx, &module, "sh_input_grad", &constants);
        Ok(Self { degree: cfg.degree, kernel, input_grad, grad_layouts: Default::default() })
    }

    /// Floats per encoded sample (`degree²`).
    pub fn output_dim(&self) -> usize {
        (self.degree * self.degree) as usize
    }

    /// Records the encoding of the `n = counters[1]` directions of `dirs` (`[n][3]`) into `out`
    /// (`[n][degree²]`); both hold at least `launch.capacity()` samples.
    pub fn record_forward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        dirs: &wgpu::Buffer,
        out: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        assert!(dirs.size() >= 12 * capacity as u64, "GpuSphericalHarmonics: dirs hold fewer than {capacity} samples");
        assert!(
            out.size() >= 4 * (capacity * self.output_dim()) as u64,
            "GpuSphericalHarmonics: out holds fewer than {capacity}·{} floats",
            self.output_dim()
        );
        launch.record(&self.kernel, ctx, enc, &[(0, counters), (1, dirs), (2, out)], 1, ENC_WG, 1);
    }

    /// Records the gradient w.r.t. the directions (camera pose refinement): for the
    /// `n = counters[1]` directions of `dirs` (`[n][3]`, used as-is, as the forward does),
    /// OVERWRITES `d_dirs[3k..3k + 3]` with dL/d(direction) given dL/d(encoding), read for sample
    /// `k` at `d_sh[k·d_sh_stride + d_sh_offset + j]`, `j < degree²` — the SH columns of a wider
    /// row, e.g. the hash field's colour-net input gradient `[density features | SH]` (stride
    /// `FieldGlue::color_in_dim`, offset the density outputs); stride `degree²` and offset 0 for
    /// plain `[n][degree²]` rows. Twin of `SphericalHarmonics::backward(dirs, d_sh, &mut [],
    /// Some(d_dirs))` (the polynomials differentiated as written; zeros for degree 1). Rows past
    /// `n` are left untouched; buffers hold at least `launch.capacity()` samples.
    ///
    /// # Panics
    /// If `d_sh_stride < d_sh_offset + degree²`, a buffer is too small for the capacity, or the
    /// last row's index overflows `u32`.
    #[allow(clippy::too_many_arguments)]
    pub fn record_input_gradient(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        dirs: &wgpu::Buffer,
        d_sh: &wgpu::Buffer,
        d_sh_stride: usize,
        d_sh_offset: usize,
        d_dirs: &wgpu::Buffer,
        launch: Launch<'_>,
    ) {
        let capacity = launch.capacity();
        assert!(dirs.size() >= 12 * capacity as u64, "GpuSphericalHarmonics: dirs hold fewer than {capacity} samples");
        assert!(d_dirs.size() >= 12 * capacity as u64, "GpuSphericalHarmonics: d_dirs hold fewer than {capacity} samples");
        let layout = self.grad_layouts.get(ctx, "GpuSphericalHarmonics", d_sh, d_sh_stride, d_sh_offset, self.output_dim(), capacity);
        let b = [(0, counters), (1, dirs), (3, &layout), (4, d_sh), (5, d_dirs)];
        launch.record(&self.input_grad, ctx, enc, &b, 1, ENC_WG, 1);
    }
}

/// NeRF's frequency encoding on the GPU (`shaders/frequency.wgsl`), twin of
/// [`nerf_encoding::FrequencyEncoding`]: `[x, sin(2⁰x), cos(2⁰x), …, sin(2^(L−1)x), cos(2^(L−1)x)]`,
/// blocks of `input_dim`, no π; forward, and the gradient in its input. One invocation per
/// output element (per input element for the gradient); `sin`/`cos` arguments are reduced to
/// `[−π, π]` first (see the WGSL header).
pub struct GpuFrequencyEncoding {
    input_dim: usize,
    output_dim: usize,
    kernel: Kernel,
    input_grad: Kernel,
    grad_layouts: GradLayouts,
}

impl GpuFrequencyEncoding {
    /// Builds the pipeline for `input_dim`-dimensional inputs (3 for positions and directions).
    pub fn new(ctx: &GpuContext, input_dim: usize, cfg: &FrequencyEncodingConfig) -> Result<Self, GpuError> {
        if input_dim == 0 || input_dim > 64 {
            return Err(GpuError::Unsupported(format!("frequency encoding: input_dim {input_dim} (need 1..=64)")));
        }
        if cfg.n_frequencies > 127 {
            return Err(GpuError::Unsupported(format!(
                "frequency encoding: n_frequencies {} (2^k must be a finite f32: at most 127)",
                cfg.n_frequencies
            )));
        }
        let skip = if cfg.include_input { input_dim } else { 0 };
        let output_dim = skip + 2 * cfg.n_frequencies * input_dim;
        if output_dim == 0 {
            return Err(GpuError::Unsupported(
                "frequency encoding: no frequencies and include_input = false give an empty encoding".into(),
            ));
        }
        let module = ctx.shader_module("frequency.wgsl", &shaders::with_common(shaders::FREQUENCY));
        let constants =
            [("D", input_dim as f64), ("N_FREQ", cfg.n_frequencies as f64), ("SKIP", skip as f64), ("WG", ENC_WG as f64)];
        let kernel = Kernel::from_module(ctx, &module, "frequency_forward", &constants);
        let input_grad = Kernel::from_module(ctx, &module, "frequency_input_grad", &constants);
        Ok(Self { input_dim, output_dim, kernel, input_grad, grad_layouts: Default::default() })
    }

    /// Floats per input sample.
    pub fn input_dim(&self) -> usize {
        self.input_dim
    }

    /// Floats per encoded sample, `input_dim·(include_input + 2L)`.
    pub fn output_dim(&self) -> usize {
        self.output_dim
    }

    /// Records the encoding of the `n = counters[1]` samples of `x` (`[n][input_dim]`) into `out`
    /// (`[n][output_dim]`); both hold at least `capacity` samples (`capacity·output_dim < 2³²`).
    pub fn record_forward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        x: &wgpu::Buffer,
        out: &wgpu::Buffer,
        capacity: usize,
    ) {
        let total = capacity * self.output_dim;
        assert!(total <= u32::MAX as usize, "GpuFrequencyEncoding: capacity {capacity} × {} outputs overflow u32", self.output_dim);
        assert!(
            x.size() >= 4 * (capacity * self.input_dim) as u64,
            "GpuFrequencyEncoding: x holds fewer than {capacity}·{} floats",
            self.input_dim
        );
        assert!(out.size() >= 4 * total as u64, "GpuFrequencyEncoding: out holds fewer than {capacity}·{} floats", self.output_dim);
        self.kernel.record(ctx, enc, &[(0, counters), (1, x), (2, out)], groups_1d(total, ENC_WG));
    }

    /// Records ∂L/∂x (`[n][input_dim]`, written; rows past `n = counters[1]` untouched) of the
    /// samples `x` from ∂L/∂out, which for sample `k` starts at `d_out[k·d_out_stride +
    /// d_out_offset]` (the encoding may be a slice of a wider row, as a network's input
    /// gradient): the twin of `FrequencyEncoding::backward` with `d_input`. Buffers hold at least
    /// `capacity` samples.
    ///
    /// # Panics
    /// If `d_out_stride < d_out_offset + output_dim`, a buffer is too small for the capacity, or
    /// the last row's index overflows `u32`.
    #[allow(clippy::too_many_arguments)]
    pub fn record_input_gradient(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        x: &wgpu::Buffer,
        d_out: &wgpu::Buffer,
        d_out_stride: usize,
        d_out_offset: usize,
        d_x: &wgpu::Buffer,
        capacity: usize,
    ) {
        let d = self.input_dim;
        assert!(x.size() >= 4 * (capacity * d) as u64, "GpuFrequencyEncoding: x holds fewer than {capacity}·{d} floats");
        assert!(d_x.size() >= 4 * (capacity * d) as u64, "GpuFrequencyEncoding: d_x holds fewer than {capacity}·{d} floats");
        let layout = self.grad_layouts.get(ctx, "GpuFrequencyEncoding", d_out, d_out_stride, d_out_offset, self.output_dim, capacity);
        let b = [(0, counters), (1, x), (3, &layout), (4, d_out), (5, d_x)];
        self.input_grad.record(ctx, enc, &b, groups_1d(capacity * d, ENC_WG));
    }
}
