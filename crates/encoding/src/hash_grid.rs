//! Instant-NGP's multiresolution hash encoding (Müller et al. 2022), with HashNeRF's level resolutions.
//!
//! `L` levels of 3-D grids with geometrically growing resolution `res_l = floor(N_min·b^l)`,
//! `b = exp((ln N_max − ln N_min)/(L−1))` (the paper's eq. 2, evaluated in `f32` as HashNeRF does). Each
//! level stores `F` trainable features per grid vertex in a table of `T_l` slots: coarse levels whose
//! `(res+1)³` vertices fit in `T` are stored densely (when [`HashGridConfig::dense_levels`]), the others
//! through the spatial hash `(x·1 ⊕ y·2654435761 ⊕ z·805459861) mod T` ([`spatial_hash`]). A sample's
//! encoding is, per level, the trilinear interpolation of the features of its cell's 8 corners;
//! levels are concatenated level-major (`n × L·F`, HashNeRF's order).
//!
//! Inputs are positions already normalised to `[0,1]³` (the field normalises with the scene AABB);
//! they are clamped to `[0,1]`. Vertex `v` of level `l` sits at `v / res_l` (no half-cell offset) and a
//! point on the far face `x = 1` lands in the last cell. [`GridAlign::Staggered`] places the levels
//! as tiny-cuda-nn does instead (`p = x·(N_min·b^l − 1) + ½`), staggered against each other.
//!
//! The parameters live in the encoding ([`HashGrid::params`]); [`Encoding::backward`] scatter-adds
//! `dL/d(params)` into a caller-owned buffer. The backward pass splits the work **by level** (levels
//! own disjoint parameter ranges), so it is race-free and bit-for-bit deterministic for any number
//! of threads, without per-thread copies of the table.
#![allow(clippy::needless_range_loop)] // index loops read clearer in the kernels

use crate::Encoding;
use half::f16;
use half::slice::HalfFloatSliceExt;
use nerf_core::{round_f16, Real};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// The primes of Instant-NGP's spatial hash (`π₁ = 1` keeps neighbouring x-coordinates in neighbouring
/// slots, which helps the caches).
pub const HASH_PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// The largest supported `log2_hashmap_size` (2^30 slots per level).
pub const MAX_LOG2_HASHMAP_SIZE: u32 = 30;

/// The largest supported level resolution (vertex coordinates stay exact in `f32`).
pub const MAX_RESOLUTION: u32 = 1 << 20;

/// Batches of at most this many samples run on the calling thread; larger ones are split into one
/// contiguous block per rayon thread (never smaller than this).
///
/// The forward pass loops levels outermost over a whole block: visiting one level's table for many
/// samples in a row keeps it warm in cache and TLB, which measured ~3× faster on a 2^18 batch than
/// interleaving levels every 512 samples (the hashed tables of all levels together exceed the L3).
const MIN_BLOCK: usize = 4096;

/// Levels whose table is at least this large (bytes) are gathered with software prefetching: about
/// half a core's L2, above which a random corner is usually a cache miss.
const PREFETCH_MIN_BYTES: usize = 512 << 10;

/// How many samples ahead the corners are prefetched: enough misses in flight to hide much of the
/// latency, few enough that the lines are still in L1 when read (8 measured faster than 4 and 16 on
/// the CI machine, docs/results.md).
const PREFETCH_DISTANCE: usize = 8;

/// Samples per block for a batch of `n` (≥ MIN_BLOCK): one block per rayon thread.
fn block_size(n: usize) -> usize {
    n.div_ceil(rayon::current_num_threads().max(1))
        .max(MIN_BLOCK)
}

/// Below this many samples × levels the backward pass runs its levels on the calling thread.
const SERIAL_WORK: usize = 1 << 14;

/// Instant-NGP's spatial hash of an integer grid vertex: `(x·1 ⊕ y·2654435761 ⊕ z·805459861) mod 2^log2_t`,
/// computed in wrapping `u32` arithmetic (equal to the low bits of HashNeRF's `int64` evaluation).
#[inline(always)]
pub fn spatial_hash(xyz: [u32; 3], log2_t: u32) -> u32 {
    let h = xyz[0].wrapping_mul(HASH_PRIMES[0])
        ^ xyz[1].wrapping_mul(HASH_PRIMES[1])
        ^ xyz[2].wrapping_mul(HASH_PRIMES[2]);
    if log2_t >= 32 {
        h
    } else {
        h & ((1u32 << log2_t) - 1)
    }
}

/// Storage precision of the table that lookups read.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// Lookups read the `f32` (or `f64`) parameters directly.
    #[default]
    F32,
    /// Lookups read an `f16` mirror of the parameters (half the bytes moved); the full-precision
    /// parameters stay the master copy for the optimiser. Call [`HashGrid::sync_storage`] after each
    /// parameter update. On the CPU this pays off only where `f16 → f32` conversion is cheap: measured
    /// ~1.1× faster forward than `F32` with `-C target-cpu=native` (F16C/AVX2), but ~0.6–0.8× on a
    /// baseline x86-64 build, where the conversion is scalar code. It also halves the table's memory.
    F16,
}

/// Where a level's grid vertices sit ([`HashGridConfig::align`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum GridAlign {
    /// HashNeRF's grids: vertex `v` of level `l` at `v / res_l`, `res_l = floor(N_min·b^l)`. Every
    /// level has vertices on the box's faces, and levels whose resolutions share a factor share
    /// the planes between: every even level has one through the box's centre.
    #[default]
    Corner,
    /// tiny-cuda-nn's grids (instant-ngp, nerfacc): a point `x ∈ [0,1]` sits at `x·s_l + ½` in
    /// level `l`'s vertex coordinates, `s_l = N_min·b^l − 1` (not rounded), so the levels are
    /// staggered against each other and no plane of vertices is shared by design (the
    /// instant-ngp paper, appendix A). Vertices `0 ..= floor(s_l + ½) + 1` per axis; tiny-cuda-nn
    /// wraps the last one of a dense level around, this grid stores it.
    Staggered,
}

/// Configuration of [`HashGrid`] (Instant-NGP's defaults).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HashGridConfig {
    /// Number of levels L (16).
    pub n_levels: usize,
    /// Features per level F (2); one of 1, 2, 4, 8.
    pub n_features_per_level: usize,
    /// log2 of the maximum table size T per level (19).
    pub log2_hashmap_size: u32,
    /// Coarsest resolution N_min (16).
    pub base_resolution: u32,
    /// Finest resolution N_max over the scene box (2048; Instant-NGP uses 2048 × `aabb_scale` over
    /// its training cube, so an instant-ngp scene with `aabb_scale > 1` wants the product here).
    /// Because `b^(L−1)` is evaluated in `f32`, the finest level can come out as N_max − 1.
    pub max_resolution: u32,
    /// `true`: a level whose `(res+1)³` vertices fit in T is stored densely (no hash, Instant-NGP);
    /// `false`: every level is hashed into T slots (HashNeRF).
    pub dense_levels: bool,
    /// Precision of the table the lookups read ([`Precision::F16`]: an `f16` mirror).
    pub storage: Precision,
    /// Parameters are initialised ~ U(−init_scale, init_scale) (1e-4).
    pub init_scale: f32,
    /// Where the levels' vertices sit: HashNeRF's `corner` (the default) or tiny-cuda-nn's
    /// `staggered` ([`GridAlign`]).
    pub align: GridAlign,
    /// Accumulate the table's gradient as tiny-cuda-nn does in half precision, with this loss
    /// scale `S`: each sample's gradient for the level's features is scaled by `S` and rounded to
    /// `f16` (tiny-cuda-nn's `dL/dy` buffer), each corner's share `f16(g·S)·w` is rounded to
    /// `f16`, and every addition into an entry rounds the running sum to `f16` (its `half2`
    /// atomics), the entry being read back divided by `S`. Contributions below `f16`'s smallest
    /// subnormal (2⁻²⁴ after scaling) vanish and small ones lose precision, as there. `None` (the
    /// default): `f32` sums. A power of two keeps the scaling exact. CPU only: the GPU grid
    /// refuses it. (Left out of the serialised config when `None`, so older configs keep their
    /// hashes.)
    #[serde(skip_serializing_if = "Option::is_none")]
    pub grad_f16_scale: Option<f32>,
}

impl Default for HashGridConfig {
    fn default() -> Self {
        Self {
            n_levels: 16,
            n_features_per_level: 2,
            log2_hashmap_size: 19,
            base_resolution: 16,
            max_resolution: 2048,
            dense_levels: true,
            storage: Precision::F32,
            init_scale: 1e-4,
            align: GridAlign::Corner,
            grad_f16_scale: None,
        }
    }
}

/// An invalid [`HashGridConfig`].
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum HashGridConfigError {
    /// `n_levels` is 0 or unreasonably large.
    #[error("hash grid config: n_levels must be in 1..=64, got {0}")]
    Levels(usize),
    /// `n_features_per_level` is not 1, 2, 4 or 8.
    #[error("hash grid config: n_features_per_level must be 1, 2, 4 or 8, got {0}")]
    Features(usize),
    /// `log2_hashmap_size` out of range.
    #[error("hash grid config: log2_hashmap_size must be in 1..={MAX_LOG2_HASHMAP_SIZE}, got {0}")]
    HashmapSize(u32),
    /// The resolutions are not `1 ≤ base_resolution ≤ max_resolution ≤ MAX_RESOLUTION`.
    #[error("hash grid config: need 1 <= base_resolution ({base}) <= max_resolution ({max}) <= {MAX_RESOLUTION}")]
    Resolution {
        /// The configured base resolution.
        base: u32,
        /// The configured max resolution.
        max: u32,
    },
    /// `init_scale` is negative or not finite.
    #[error("hash grid config: init_scale must be finite and >= 0, got {0}")]
    InitScale(f32),
    /// `grad_f16_scale` is not a finite positive number.
    #[error("hash grid config: grad_f16_scale must be finite and > 0, got {0}")]
    GradScale(f32),
}

impl HashGridConfig {
    /// Checks the configuration (call on user-supplied configs before [`HashGrid::new`], or use
    /// [`HashGrid::try_new`]).
    pub fn validate(&self) -> Result<(), HashGridConfigError> {
        if !(1..=64).contains(&self.n_levels) {
            return Err(HashGridConfigError::Levels(self.n_levels));
        }
        if ![1, 2, 4, 8].contains(&self.n_features_per_level) {
            return Err(HashGridConfigError::Features(self.n_features_per_level));
        }
        if !(1..=MAX_LOG2_HASHMAP_SIZE).contains(&self.log2_hashmap_size) {
            return Err(HashGridConfigError::HashmapSize(self.log2_hashmap_size));
        }
        if self.base_resolution < 1
            || self.max_resolution < self.base_resolution
            || self.max_resolution > MAX_RESOLUTION
        {
            return Err(HashGridConfigError::Resolution {
                base: self.base_resolution,
                max: self.max_resolution,
            });
        }
        if !(self.init_scale.is_finite() && self.init_scale >= 0.0) {
            return Err(HashGridConfigError::InitScale(self.init_scale));
        }
        if let Some(s) = self.grad_f16_scale.filter(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(HashGridConfigError::GradScale(s));
        }
        Ok(())
    }

    /// The per-level growth factor `b = exp((ln N_max − ln N_min)/(L−1))`, evaluated in `f32` like
    /// HashNeRF (1 when L = 1).
    pub fn growth_factor(&self) -> f32 {
        if self.n_levels <= 1 {
            return 1.0;
        }
        (((self.max_resolution as f32).ln() - (self.base_resolution as f32).ln())
            / (self.n_levels - 1) as f32)
            .exp()
    }

    /// The level resolutions `res_l = floor(N_min·b^l)`, with `b^l` and the product in `f32` (HashNeRF;
    /// `[16, 20, 25, 32, …, 512]` for N_min = 16, N_max = 512, L = 16).
    ///
    /// With [`GridAlign::Staggered`], the cells per axis a point can fall in:
    /// `floor(s_l + ½) + 1` ([`HashGridConfig::level_scales`]).
    pub fn level_resolutions(&self) -> Vec<u32> {
        match self.align {
            GridAlign::Corner => {
                let b = self.growth_factor();
                (0..self.n_levels)
                    .map(|l| {
                        let r = ((self.base_resolution as f32) * b.powf(l as f32)).floor() as u32;
                        r.clamp(1, MAX_RESOLUTION)
                    })
                    .collect()
            }
            GridAlign::Staggered => self
                .level_scales()
                .iter()
                .map(|&s| ((s + 0.5).floor() as u32 + 1).clamp(1, MAX_RESOLUTION))
                .collect(),
        }
    }

    /// Per level, the factor `s_l` and the offset `o` of `p = x·s_l + o`, the position of a point
    /// `x ∈ [0,1]` in the level's vertex coordinates: `(res_l, 0)` ([`GridAlign::Corner`]) or
    /// `(N_min·b^l − 1, ½)` ([`GridAlign::Staggered`], tiny-cuda-nn's `grid_scale`; at least 1).
    pub fn level_scales(&self) -> Vec<f32> {
        match self.align {
            GridAlign::Corner => self.level_resolutions().iter().map(|&r| r as f32).collect(),
            GridAlign::Staggered => {
                let b = self.growth_factor();
                (0..self.n_levels)
                    .map(|l| ((self.base_resolution as f32) * b.powf(l as f32) - 1.0).clamp(1.0, (MAX_RESOLUTION - 1) as f32))
                    .collect()
            }
        }
    }

    /// The offset `o` of [`HashGridConfig::level_scales`] (0 or ½).
    pub fn level_offset(&self) -> f32 {
        match self.align {
            GridAlign::Corner => 0.0,
            GridAlign::Staggered => 0.5,
        }
    }
}

/// Per-level constants of the lookup.
#[derive(Clone, Copy, Debug)]
struct Level {
    /// Resolution (cells per axis).
    res: u32,
    /// Dense storage (`x + y·(res+1) + z·(res+1)²`) instead of the hash.
    dense: bool,
    /// `res + 1` (vertices per axis), for dense levels.
    stride: usize,
    /// `T − 1` for hashed levels (T is a power of two).
    mask: u32,
    /// `s_l` of `p = x·s_l + offset` ([`HashGridConfig::level_scales`]).
    scale: f32,
    /// 0 or ½ ([`HashGridConfig::level_offset`]).
    offset: f32,
}

impl Level {
    /// `[s_l, offset]` in `T`.
    fn scale_offset<T: Real>(&self) -> [T; 2] {
        [T::c(self.scale as f64), T::c(self.offset as f64)]
    }
}

/// A multiresolution hash grid encoding of 3-D points, generic over the parameter type so that the same
/// code runs in `f32` (training, the default) and `f64` (gradient checks).
///
/// Parameters are laid out level by level ([`HashGrid::level_offsets`]), slot-major within a level:
/// feature `j` of slot `s` of level `l` is `params[level_offsets[l] + s·F + j]`.
#[derive(Clone, Debug)]
pub struct HashGrid<T: Real = f32> {
    cfg: HashGridConfig,
    levels: Vec<Level>,
    resolutions: Vec<u32>,
    offsets: Vec<usize>,
    params: Vec<T>,
    /// The `f16` mirror of `params` (empty unless `storage == F16`).
    half: Vec<f16>,
}

impl<T: Real> HashGrid<T> {
    /// A grid with parameters ~ U(−init_scale, init_scale) drawn from `rng` (as `f32` values, so `f32`
    /// and `f64` grids built from the same seed hold the same numbers).
    ///
    /// # Panics
    /// If the configuration is invalid (see [`HashGridConfig::validate`]; use [`HashGrid::try_new`]
    /// for configurations read from user files).
    pub fn new(cfg: &HashGridConfig, rng: &mut nerf_core::Rng) -> Self {
        match Self::try_new(cfg, rng) {
            Ok(g) => g,
            Err(e) => panic!("{e}"),
        }
    }

    /// Like [`HashGrid::new`], returning an error for an invalid configuration.
    pub fn try_new(
        cfg: &HashGridConfig,
        rng: &mut nerf_core::Rng,
    ) -> Result<Self, HashGridConfigError> {
        use rand::Rng as _;
        let mut g = Self::zeros(cfg)?;
        let s = cfg.init_scale;
        for p in g.params.iter_mut() {
            *p = T::c(((rng.gen::<f32>() * 2.0 - 1.0) * s) as f64);
        }
        g.sync_storage();
        Ok(g)
    }

    /// A grid whose parameters are all zero (no random numbers drawn).
    pub fn zeros(cfg: &HashGridConfig) -> Result<Self, HashGridConfigError> {
        cfg.validate()?;
        let t = 1usize << cfg.log2_hashmap_size;
        let resolutions = cfg.level_resolutions();
        let scales = cfg.level_scales();
        let mut offsets = Vec::with_capacity(resolutions.len() + 1);
        let mut levels = Vec::with_capacity(resolutions.len());
        let mut total = 0usize;
        for (&res, &scale) in resolutions.iter().zip(&scales) {
            let stride = res as usize + 1;
            let verts = (stride as u64).pow(3);
            let dense = cfg.dense_levels && verts <= t as u64;
            let size = if dense { verts as usize } else { t };
            offsets.push(total);
            total += size * cfg.n_features_per_level;
            levels.push(Level {
                res,
                dense,
                stride,
                mask: (t - 1) as u32,
                scale,
                offset: cfg.level_offset(),
            });
        }
        offsets.push(total);
        let half = if cfg.storage == Precision::F16 {
            vec![f16::ZERO; total]
        } else {
            Vec::new()
        };
        Ok(Self {
            cfg: cfg.clone(),
            levels,
            resolutions,
            offsets,
            params: vec![T::zero(); total],
            half,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &HashGridConfig {
        &self.cfg
    }

    /// The resolution (cells per axis) of each level.
    pub fn resolutions(&self) -> &[u32] {
        &self.resolutions
    }

    /// Whether `level` is stored densely (no hash).
    pub fn is_dense(&self, level: usize) -> bool {
        self.levels[level].dense
    }

    /// Number of table slots `T_l` of `level` (`(res+1)³` when dense, else T).
    pub fn level_size(&self, level: usize) -> usize {
        (self.offsets[level + 1] - self.offsets[level]) / self.cfg.n_features_per_level
    }

    /// Start of each level's parameters in the flat table (length L+1; the last entry is `n_params`).
    pub fn level_offsets(&self) -> &[usize] {
        &self.offsets
    }

    /// Number of levels L.
    pub fn n_levels(&self) -> usize {
        self.levels.len()
    }

    /// Features per level F.
    pub fn n_features_per_level(&self) -> usize {
        self.cfg.n_features_per_level
    }

    /// The master parameters (`n_params` values).
    pub fn params(&self) -> &[T] {
        &self.params
    }

    /// The master parameters, mutable (call [`HashGrid::sync_storage`] after changing them).
    pub fn params_mut(&mut self) -> &mut [T] {
        &mut self.params
    }

    /// Re-derives the `f16` mirror from the master params (call after every optimiser step; no-op for
    /// [`Precision::F32`]).
    pub fn sync_storage(&mut self) {
        if self.cfg.storage != Precision::F16 {
            return;
        }
        const BLOCK: usize = 1 << 16;
        let params = &self.params;
        if let Some(p32) = as_f32(params) {
            self.half
                .par_chunks_mut(BLOCK)
                .zip(p32.par_chunks(BLOCK))
                .for_each(|(h, p)| h.convert_from_f32_slice(p));
        } else {
            self.half
                .par_chunks_mut(BLOCK)
                .zip(params.par_chunks(BLOCK))
                .for_each(|(h, p)| {
                    for (h, p) in h.iter_mut().zip(p) {
                        *h = f16::from_f64(p.f64());
                    }
                });
        }
    }

    /// Table slot of integer vertex `(x, y, z)` at `level`: `x + y·(res+1) + z·(res+1)²` when the level is
    /// dense, else [`spatial_hash`] mod T. Coordinates must be ≤ res on a dense level.
    pub fn slot(&self, level: usize, xyz: [u32; 3]) -> usize {
        let lv = &self.levels[level];
        if lv.dense {
            debug_assert!(
                xyz.iter().all(|&c| c <= lv.res),
                "vertex {xyz:?} outside level {level}"
            );
            xyz[0] as usize + lv.stride * (xyz[1] as usize + lv.stride * xyz[2] as usize)
        } else {
            (spatial_hash(xyz, 32) & lv.mask) as usize
        }
    }

    /// Runs `f` with the table the lookups read (the `f16` mirror or the master params).
    #[inline]
    fn with_table<R>(&self, f: impl FnOnce(TableRef<'_, T>) -> R) -> R {
        if self.cfg.storage == Precision::F16 {
            f(TableRef::Half(&self.half))
        } else {
            f(TableRef::Full(&self.params))
        }
    }

    fn check_input(&self, what: &str, input: &[T], other: &[T]) -> usize {
        assert_eq!(
            input.len() % 3,
            0,
            "HashGrid: input length {} is not a multiple of 3",
            input.len()
        );
        let n = input.len() / 3;
        let od = self.levels.len() * self.cfg.n_features_per_level;
        assert_eq!(
            other.len(),
            n * od,
            "HashGrid: {what} length {} != {n}·{od}",
            other.len()
        );
        n
    }

    /// Whether level `li`'s lookups prefetch: its table (`elem_bytes` per value) is at least
    /// [`PREFETCH_MIN_BYTES`].
    fn is_prefetched(&self, li: usize, elem_bytes: usize) -> bool {
        (self.offsets[li + 1] - self.offsets[li]) * elem_bytes >= PREFETCH_MIN_BYTES
    }

    /// Forward over one chunk of samples, level by level.
    fn forward_chunk<G: Table<T>, const F: usize>(&self, table: &G, input: &[T], out: &mut [T]) {
        if input.is_empty() {
            return;
        }
        let od = self.levels.len() * F;
        let interpolate = |c: &Cell<T>, off: usize, o: &mut [T]| {
            let v: [[T; F]; 8] = table.corners(off, &c.idx);
            for j in 0..F {
                let mut acc = T::zero();
                for k in 0..8 {
                    acc += c.w[k] * v[k][j];
                }
                o[j] = acc;
            }
        };
        for (li, lv) in self.levels.iter().enumerate() {
            let off = self.offsets[li];
            let so = lv.scale_offset::<T>();
            let lo = li * F;
            // On a level larger than the caches the gathers are cache misses: prefetch the corners
            // of the sample PREFETCH_DISTANCE ahead, so that several misses are in flight at once.
            // The cells computed for the prefetch wait in a ring until their sample comes up.
            let n = input.len() / 3;
            let outs = out.chunks_exact_mut(od);
            if self.is_prefetched(li, std::mem::size_of::<G::Elem>()) {
                let at = |i: usize| cell::<T, F>(lv, so, &input[3 * i..3 * i + 3]);
                let mut ring: [Cell<T>; PREFETCH_DISTANCE] = std::array::from_fn(|i| at(i.min(n - 1)));
                for c in ring.iter().take(n) {
                    table.prefetch(off, &c.idx);
                }
                for (i, o) in outs.enumerate() {
                    let slot = &mut ring[i % PREFETCH_DISTANCE];
                    let c = *slot;
                    let ahead = i + PREFETCH_DISTANCE;
                    if ahead < n {
                        *slot = at(ahead);
                        table.prefetch(off, &slot.idx);
                    }
                    interpolate(&c, off, &mut o[lo..lo + F]);
                }
            } else {
                for (x, o) in input.chunks_exact(3).zip(outs) {
                    interpolate(&cell::<T, F>(lv, so, x), off, &mut o[lo..lo + F]);
                }
            }
        }
    }

    fn forward_impl<G: Table<T>, const F: usize>(&self, table: &G, input: &[T], out: &mut [T]) {
        let n = input.len() / 3;
        let od = self.levels.len() * F;
        if n <= MIN_BLOCK {
            self.forward_chunk::<G, F>(table, input, out);
        } else {
            let b = block_size(n);
            input
                .par_chunks(b * 3)
                .zip(out.par_chunks_mut(b * od))
                .for_each(|(x, o)| self.forward_chunk::<G, F>(table, x, o));
        }
    }

    /// Scatter-adds the parameter gradient of one level (`d` is that level's slice of `d_params`).
    fn level_backward<const F: usize>(&self, li: usize, input: &[T], d_out: &[T], d: &mut [T]) {
        let lv = &self.levels[li];
        let od = self.levels.len() * F;
        let so = lv.scale_offset::<T>();
        let n = input.len() / 3;
        // As in the forward pass: on a level larger than the caches, prefetch the corners of the
        // sample PREFETCH_DISTANCE ahead (the pointer is only a hint; `d` is not read through it).
        let f16_scale = self.cfg.grad_f16_scale;
        let scatter = |c: &Cell<T>, g: &[T; F], d: &mut [T]| match f16_scale {
            None => {
                for k in 0..8 {
                    let dst: &mut [T; F] = (&mut d[c.idx[k]..c.idx[k] + F]).try_into().unwrap();
                    for j in 0..F {
                        dst[j] += c.w[k] * g[j];
                    }
                }
            }
            // tiny-cuda-nn's half-precision accumulation (`HashGridConfig::grad_f16_scale`): the
            // scaled gradient, each corner's share and each running sum rounded to f16; the
            // entries hold the sums divided by the scale.
            Some(s) => {
                let gs: [f32; F] = std::array::from_fn(|j| round_f16(g[j].f32() * s));
                for k in 0..8 {
                    let w = c.w[k].f32();
                    let dst: &mut [T; F] = (&mut d[c.idx[k]..c.idx[k] + F]).try_into().unwrap();
                    for j in 0..F {
                        let sum = round_f16(dst[j].f32() * s + round_f16(gs[j] * w));
                        dst[j] = T::c((sum / s) as f64);
                    }
                }
            }
        };
        let grads = d_out.chunks_exact(od).map(|g| -> &[T; F] { g[li * F..li * F + F].try_into().unwrap() });
        let is_zero = |g: &[T; F]| g.iter().all(|v| *v == T::zero());
        if n > 0 && self.is_prefetched(li, std::mem::size_of::<T>()) {
            // As in the forward pass, the cells computed for the prefetch wait in a ring. (One
            // helper for both rings, with the loop bodies as closures, measured 6 % slower on the
            // CPU hash step: 2 interleaved pairs of 500 steps, 2026-11-23; hence the two loops.)
            let at = |i: usize| cell::<T, F>(lv, so, &input[3 * i..3 * i + 3]);
            let mut ring: [Cell<T>; PREFETCH_DISTANCE] = std::array::from_fn(|i| at(i.min(n - 1)));
            for c in ring.iter().take(n) {
                Full(&d[..]).prefetch(0, &c.idx);
            }
            for (i, g) in grads.enumerate() {
                let slot = &mut ring[i % PREFETCH_DISTANCE];
                let c = *slot;
                let ahead = i + PREFETCH_DISTANCE;
                if ahead < n {
                    *slot = at(ahead);
                    Full(&d[..]).prefetch(0, &slot.idx);
                }
                if !is_zero(g) {
                    scatter(&c, g, d);
                }
            }
        } else {
            for (x, g) in input.chunks_exact(3).zip(grads) {
                if !is_zero(g) {
                    scatter(&cell::<T, F>(lv, so, x), g, d);
                }
            }
        }
    }

    /// Levels `lo..hi` own `d` (= `d_params[offsets[lo]..offsets[hi]]`); split it and recurse in parallel.
    fn backward_levels<const F: usize>(
        &self,
        lo: usize,
        hi: usize,
        input: &[T],
        d_out: &[T],
        d: &mut [T],
        parallel: bool,
    ) {
        if hi - lo == 1 {
            self.level_backward::<F>(lo, input, d_out, d);
            return;
        }
        let mid = (lo + hi) / 2;
        let (a, b) = d.split_at_mut(self.offsets[mid] - self.offsets[lo]);
        if parallel {
            rayon::join(
                || self.backward_levels::<F>(lo, mid, input, d_out, a, true),
                || self.backward_levels::<F>(mid, hi, input, d_out, b, true),
            );
        } else {
            self.backward_levels::<F>(lo, mid, input, d_out, a, false);
            self.backward_levels::<F>(mid, hi, input, d_out, b, false);
        }
    }

    /// dL/d(input) of one chunk of samples.
    fn input_grad_chunk<G: Table<T>, const F: usize>(
        &self,
        table: &G,
        input: &[T],
        d_out: &[T],
        d_in: &mut [T],
    ) {
        let od = self.levels.len() * F;
        d_in.fill(T::zero());
        for (li, lv) in self.levels.iter().enumerate() {
            let off = self.offsets[li];
            let so = lv.scale_offset::<T>();
            for ((x, g), dx) in input
                .chunks_exact(3)
                .zip(d_out.chunks_exact(od))
                .zip(d_in.chunks_exact_mut(3))
            {
                let g: &[T; F] = g[li * F..li * F + F].try_into().unwrap();
                if g.iter().all(|v| *v == T::zero()) {
                    continue;
                }
                let c = cell::<T, F>(lv, so, x);
                let v: [[T; F]; 8] = table.corners(off, &c.idx);
                // s_k = Σ_j g_j · e_kj: the loss's sensitivity to corner k's weight.
                let mut s = [T::zero(); 8];
                for k in 0..8 {
                    for j in 0..F {
                        s[k] += g[j] * v[k][j];
                    }
                }
                let [wx, wy, wz] = c.frac;
                let one = T::one();
                let (ax, ay, az) = ([one - wx, wx], [one - wy, wy], [one - wz, wz]);
                let sign = [-one, one];
                let mut dw = [T::zero(); 3];
                for k in 0..8 {
                    let (bx, by, bz) = (k & 1, (k >> 1) & 1, k >> 2);
                    dw[0] += s[k] * sign[bx] * ay[by] * az[bz];
                    dw[1] += s[k] * ax[bx] * sign[by] * az[bz];
                    dw[2] += s[k] * ax[bx] * ay[by] * sign[bz];
                }
                for a in 0..3 {
                    // clamp(x, 0, 1) has zero derivative outside the unit cube.
                    if x[a] >= T::zero() && x[a] <= one {
                        dx[a] += dw[a] * so[0];
                    }
                }
            }
        }
    }

    fn backward_impl<G: Table<T>, const F: usize>(
        &self,
        table: &G,
        input: &[T],
        d_out: &[T],
        d_params: &mut [T],
        d_input: Option<&mut [T]>,
    ) {
        let n = input.len() / 3;
        let nl = self.levels.len();
        let parallel = n * nl > SERIAL_WORK;
        self.backward_levels::<F>(0, nl, input, d_out, d_params, parallel);
        if let Some(d_in) = d_input {
            let od = nl * F;
            if n <= MIN_BLOCK {
                self.input_grad_chunk::<G, F>(table, input, d_out, d_in);
            } else {
                let b = block_size(n);
                input
                    .par_chunks(b * 3)
                    .zip(d_out.par_chunks(b * od))
                    .zip(d_in.par_chunks_mut(b * 3))
                    .for_each(|((x, g), dx)| self.input_grad_chunk::<G, F>(table, x, g, dx));
            }
        }
    }
}

/// Dispatches on the table kind and the (validated) feature count to a monomorphised kernel.
macro_rules! dispatch {
    ($self:ident, $method:ident, $($arg:expr),*) => {
        $self.with_table(|t| match t {
            TableRef::Full(p) => dispatch!(@f $self, $method, &Full(p), $($arg),*),
            TableRef::Half(h) => dispatch!(@f $self, $method, &Half(h), $($arg),*),
        })
    };
    (@f $self:ident, $method:ident, $tab:expr, $($arg:expr),*) => {
        match $self.cfg.n_features_per_level {
            1 => $self.$method::<_, 1>($tab, $($arg),*),
            2 => $self.$method::<_, 2>($tab, $($arg),*),
            4 => $self.$method::<_, 4>($tab, $($arg),*),
            8 => $self.$method::<_, 8>($tab, $($arg),*),
            f => unreachable!("n_features_per_level {f} passed validation"),
        }
    };
}

impl<T: Real> Encoding<T> for HashGrid<T> {
    fn input_dim(&self) -> usize {
        3
    }
    fn output_dim(&self) -> usize {
        self.levels.len() * self.cfg.n_features_per_level
    }
    fn n_params(&self) -> usize {
        self.params.len()
    }
    fn params(&self) -> &[T] {
        &self.params
    }
    fn params_mut(&mut self) -> &mut [T] {
        &mut self.params
    }
    fn sync_storage(&mut self) {
        HashGrid::sync_storage(self)
    }
    fn forward(&self, input: &[T], out: &mut [T]) {
        self.check_input("output", input, out);
        dispatch!(self, forward_impl, input, out)
    }
    fn backward(&self, input: &[T], d_out: &[T], d_params: &mut [T], d_input: Option<&mut [T]>) {
        let n = self.check_input("d_out", input, d_out);
        assert_eq!(
            d_params.len(),
            self.params.len(),
            "HashGrid: d_params length {} != n_params {}",
            d_params.len(),
            self.params.len()
        );
        if let Some(d) = &d_input {
            assert_eq!(
                d.len(),
                3 * n,
                "HashGrid: d_input length {} != {n}·3",
                d.len()
            );
        }
        dispatch!(self, backward_impl, input, d_out, d_params, d_input)
    }
}

/// `params` viewed as `f32` when `T` is `f32`.
fn as_f32<T: Real>(params: &[T]) -> Option<&[f32]> {
    (std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>())
        .then(|| bytemuck::cast_slice(params))
}

/// The cell of one sample at one level: the 8 corners' offsets within the level's table (slot·F) and
/// their trilinear weights. Corner `k` has bit 0 = +x, bit 1 = +y, bit 2 = +z.
#[derive(Clone, Copy)]
struct Cell<T> {
    idx: [usize; 8],
    w: [T; 8],
    frac: [T; 3],
}

#[inline(always)]
fn cell<T: Real, const F: usize>(lv: &Level, [scale_t, off_t]: [T; 2], x: &[T]) -> Cell<T> {
    let one = T::one();
    let mut v = [0u32; 3];
    let mut frac = [T::zero(); 3];
    for a in 0..3 {
        // max/min map NaN to 0 (IEEE maxNum), so the index stays in range for any input.
        let xc = x[a].max(T::zero()).min(one);
        // + 0 (corner grids) leaves every p ≥ 0 as it is.
        let p = xc * scale_t + off_t;
        // p ≥ 0, so truncation is floor (and avoids a libm `floorf` call on baseline x86-64).
        let vi = p.to_u32().unwrap_or(0).min(lv.res - 1);
        v[a] = vi;
        frac[a] = p - T::c(vi as f64);
    }
    let mut idx = [0usize; 8];
    if lv.dense {
        let s = lv.stride;
        let base = v[0] as usize + s * (v[1] as usize + s * v[2] as usize);
        for (k, i) in idx.iter_mut().enumerate() {
            *i = (base + (k & 1) + ((k >> 1) & 1) * s + (k >> 2) * s * s) * F;
        }
    } else {
        let hx = [v[0], v[0] + 1];
        let hy = [
            v[1].wrapping_mul(HASH_PRIMES[1]),
            (v[1] + 1).wrapping_mul(HASH_PRIMES[1]),
        ];
        let hz = [
            v[2].wrapping_mul(HASH_PRIMES[2]),
            (v[2] + 1).wrapping_mul(HASH_PRIMES[2]),
        ];
        for (k, i) in idx.iter_mut().enumerate() {
            *i = ((hx[k & 1] ^ hy[(k >> 1) & 1] ^ hz[k >> 2]) & lv.mask) as usize * F;
        }
    }
    let [wx, wy, wz] = frac;
    let (ax, ay, az) = ([one - wx, wx], [one - wy, wy], [one - wz, wz]);
    let mut w = [T::zero(); 8];
    for (k, wk) in w.iter_mut().enumerate() {
        *wk = ax[k & 1] * ay[(k >> 1) & 1] * az[k >> 2];
    }
    Cell { idx, w, frac }
}

/// The table a lookup reads.
enum TableRef<'a, T> {
    Full(&'a [T]),
    Half(&'a [f16]),
}

/// Gathers the F features of 8 corners (`off` = the level's offset, `idx` = slot·F within the level).
trait Table<T>: Sync {
    /// The stored element (`T`, or `f16` for the mirror).
    type Elem;
    /// The whole table.
    fn data(&self) -> &[Self::Elem];
    fn corners<const F: usize>(&self, off: usize, idx: &[usize; 8]) -> [[T; F]; 8];
    /// Hints the CPU to load the corners' cache lines (no effect on the result). Corners 0, 2, 4, 6
    /// only: corner `k + 1` (x + 1) is the neighbouring slot, mostly in the same 64-byte line.
    #[inline(always)]
    fn prefetch(&self, off: usize, idx: &[usize; 8]) {
        for k in [0, 2, 4, 6] {
            prefetch_line(self.data().as_ptr().wrapping_add(off + idx[k]));
        }
    }
}

/// Issues a prefetch of the cache line holding `p` into all cache levels (x86-64; a no-op elsewhere).
#[inline(always)]
fn prefetch_line<U>(p: *const U) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch never faults and has no architectural effect, whatever the address.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p.cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// The full-precision parameters.
struct Full<'a, T>(&'a [T]);

impl<T: Real> Table<T> for Full<'_, T> {
    type Elem = T;
    fn data(&self) -> &[T] {
        self.0
    }
    #[inline(always)]
    fn corners<const F: usize>(&self, off: usize, idx: &[usize; 8]) -> [[T; F]; 8] {
        std::array::from_fn(|k| {
            let i = off + idx[k];
            let s: &[T; F] = self.0[i..i + F].try_into().unwrap();
            *s
        })
    }
}

/// The `f16` mirror.
struct Half<'a>(&'a [f16]);

impl<T: Real> Table<T> for Half<'_> {
    type Elem = f16;
    fn data(&self) -> &[f16] {
        self.0
    }
    #[inline(always)]
    fn corners<const F: usize>(&self, off: usize, idx: &[usize; 8]) -> [[T; F]; 8] {
        // Gather all 8·F halves first (independent loads), then convert them in one vectorisable loop.
        let h: [[f16; F]; 8] = std::array::from_fn(|k| {
            let i = off + idx[k];
            let s: &[f16; F] = self.0[i..i + F].try_into().unwrap();
            *s
        });
        let mut f = [[0.0f32; F]; 8];
        for (o, &x) in f.as_flattened_mut().iter_mut().zip(h.as_flattened()) {
            *o = f16_to_f32(x);
        }
        f.map(|r| r.map(|v| T::from_f32(v).unwrap_or_else(T::nan)))
    }
}

/// Exact `f16 → f32` conversion, branch-free and inlinable (no CPU-feature dispatch per call, no
/// arithmetic on subnormal floats). Equals `half::f16::to_f32` for every bit pattern (tested).
#[inline(always)]
fn f16_to_f32(h: f16) -> f32 {
    let h = h.to_bits() as u32;
    let sign = (h & 0x8000) << 16;
    let em = h & 0x7fff;
    // Normal numbers: move exponent and mantissa into place and rebias the exponent by 127 − 15.
    let normal = (em << 13) + ((127 - 15) << 23);
    // Subnormals: mantissa · 2^−24 is exact and a normal f32.
    let sub = (em as f32 * (1.0 / 16_777_216.0)).to_bits();
    // Infinities and NaNs: all-ones exponent, mantissa kept.
    let special = 0x7f80_0000 | ((em & 0x3ff) << 13);
    // Select with masks (vectorises without branches).
    let is_sub = ((em < 0x400) as u32).wrapping_neg();
    let is_special = ((em >= 0x7c00) as u32).wrapping_neg();
    let bits = (sub & is_sub) | (special & is_special) | (normal & !(is_sub | is_special));
    f32::from_bits(bits | sign)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;

    fn flat(v: &serde_json::Value) -> Vec<f64> {
        match v {
            serde_json::Value::Array(a) => a.iter().flat_map(flat).collect(),
            x => vec![x.as_f64().expect("number")],
        }
    }

    fn reference() -> Option<serde_json::Value> {
        let path = nerf_core::shared::reference(env!("CARGO_MANIFEST_DIR"), "hash_grid.json")?;
        Some(serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap())
    }

    /// The reference file's embedding configuration (HashNeRF: every level hashed).
    fn reference_config() -> HashGridConfig {
        HashGridConfig {
            n_levels: 16,
            n_features_per_level: 2,
            log2_hashmap_size: 19,
            base_resolution: 16,
            max_resolution: 512,
            dense_levels: false,
            storage: Precision::F32,
            init_scale: 1e-4,
            align: GridAlign::Corner,
            grad_f16_scale: None,
        }
    }

    /// A small config with both dense and hashed levels, for the gradient checks.
    fn small_config(f: usize, storage: Precision) -> HashGridConfig {
        HashGridConfig {
            n_levels: 6,
            n_features_per_level: f,
            log2_hashmap_size: 12,
            base_resolution: 4,
            max_resolution: 64,
            dense_levels: true,
            storage,
            init_scale: 1.0,
            align: GridAlign::Corner,
            grad_f16_scale: None,
        }
    }

    #[test]
    fn spatial_hash_matches_hashnerf_exactly() {
        let Some(j) = reference() else { return };
        let log2 = j["inputs"]["hash"]["log2_hashmap_size"].as_u64().unwrap() as u32;
        let coords = j["inputs"]["hash"]["coords"].as_array().unwrap();
        let expect = j["outputs"]["hash"].as_array().unwrap();
        assert_eq!(coords.len(), 20);
        for (c, e) in coords.iter().zip(expect) {
            let c: Vec<u32> = c
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_u64().unwrap() as u32)
                .collect();
            let h = spatial_hash([c[0], c[1], c[2]], log2);
            assert_eq!(h as u64, e.as_u64().unwrap(), "hash of {c:?}");
        }
        let primes = flat(&j["inputs"]["primes_all"]);
        assert_eq!(
            HASH_PRIMES.map(|p| p as f64),
            [primes[0], primes[1], primes[2]]
        );
    }

    #[test]
    fn reference_resolutions_are_exact() {
        let cfg = reference_config();
        let expect = [
            16, 20, 25, 32, 40, 50, 64, 80, 101, 128, 161, 203, 256, 322, 406, 512,
        ];
        assert_eq!(cfg.level_resolutions(), expect);
        let Some(j) = reference() else { return };
        let peer: Vec<u32> = flat(&j["outputs"]["level_resolution_peer"])
            .iter()
            .map(|&r| r as u32)
            .collect();
        assert_eq!(cfg.level_resolutions(), peer);
        assert_eq!(
            cfg.growth_factor() as f64,
            j["outputs"]["b_f32"].as_f64().unwrap()
        );
    }

    /// Default config: b = 128^(1/15) = 2^(7/15); res_l = floor(16·2^(7l/15)). A level is dense iff its
    /// (res+1)³ vertices fit in T = 2^19 = 524288 ⇔ res+1 ≤ 80.6 ⇔ res ≤ 79: levels 0..=4 (16, 22, 30, 42,
    /// 58: 59³ = 205379) are dense; level 5 has res 80 and 81³ = 531441 > 524288, so it and every finer
    /// level is hashed. (The finest level comes out as 2047, not 2048: 16·b^15 = 2047.9988 in f32.)
    #[test]
    fn default_config_levels_dense_and_hashed_by_hand() {
        let cfg = HashGridConfig::default();
        let g = HashGrid::<f32>::zeros(&cfg).unwrap();
        let expect = [
            16, 22, 30, 42, 58, 80, 111, 153, 212, 294, 406, 561, 776, 1072, 1482, 2047,
        ];
        assert_eq!(g.resolutions(), expect);
        for l in 0..16 {
            assert_eq!(g.is_dense(l), l < 5, "level {l} (res {})", expect[l]);
            let size = if l < 5 {
                (expect[l] as usize + 1).pow(3)
            } else {
                1 << 19
            };
            assert_eq!(g.level_size(l), size, "level {l}");
            assert_eq!(g.level_offsets()[l + 1] - g.level_offsets()[l], 2 * size);
        }
        // 17³ + 23³ + 31³ + 43³ + 59³ = 331757 dense slots, 11 hashed levels of 2^19.
        assert_eq!(
            Encoding::<f32>::n_params(&g),
            2 * (331_757 + 11 * (1 << 19))
        );
        assert_eq!(g.level_offsets()[16], g.params().len());
        assert_eq!(Encoding::<f32>::output_dim(&g), 32);
        // HashNeRF mode hashes every level, even the coarsest.
        let all_hashed = HashGrid::<f32>::zeros(&HashGridConfig {
            dense_levels: false,
            ..cfg
        })
        .unwrap();
        assert!((0..16).all(|l| !all_hashed.is_dense(l) && all_hashed.level_size(l) == 1 << 19));
    }

    #[test]
    fn slots_by_hand() {
        let g = HashGrid::<f32>::zeros(&HashGridConfig::default()).unwrap();
        // Level 2: res 30, dense with 31 vertices per axis.
        assert_eq!(g.slot(2, [3, 5, 7]), 3 + 5 * 31 + 7 * 31 * 31);
        assert_eq!(g.slot(2, [30, 30, 30]), 31 * 31 * 31 - 1);
        assert_eq!(g.slot(0, [1, 0, 0]), 1);
        assert_eq!(g.slot(0, [0, 1, 0]), 17);
        assert_eq!(g.slot(0, [0, 0, 1]), 289);
        // Level 10 (hashed): 2·2654435761 mod 2^32 = 1013904226, 3·805459861 = 2416379583,
        // 1 ⊕ 1013904226 ⊕ 2416379583 = 2892625372, mod 2^19 = 128476.
        assert_eq!(g.slot(10, [1, 2, 3]), 128_476);
        // 7·2654435761 mod 2^32 = 1401181143, 9·805459861 mod 2^32 = 2954171453; 5 ⊕ … ⊕ … mod 2^19 = 83951.
        assert_eq!(g.slot(7, [5, 7, 9]), 83_951);
        assert_eq!(g.slot(7, [0, 0, 0]), 0);
        assert_eq!(g.slot(15, [3, 0, 0]), 3);
    }

    fn fill_reference_table<T: Real>(g: &mut HashGrid<T>) {
        let off = g.level_offsets().to_vec();
        let p = g.params_mut();
        for l in 0..16 {
            for idx in 0..(off[l + 1] - off[l]) / 2 {
                for f in 0..2 {
                    let v = ((idx * 37 + f * 101 + l * 211) % 1000) as f64 / 1000.0 - 0.5;
                    p[off[l] + 2 * idx + f] = T::c(v as f32 as f64);
                }
            }
        }
        g.sync_storage();
    }

    /// The 6 reference points normalised into [0,1]³ with the reference bounding box (in f64).
    fn reference_points(j: &serde_json::Value) -> Vec<f64> {
        let e = &j["inputs"]["embedding"];
        let (lo, hi) = (flat(&e["bounding_box_min"]), flat(&e["bounding_box_max"]));
        let pts = flat(&e["points"]);
        pts.chunks(3)
            .flat_map(|p| {
                (0..3)
                    .map(|a| (p[a] - lo[a]) / (hi[a] - lo[a]))
                    .collect::<Vec<_>>()
            })
            .collect()
    }

    fn check_reference_embedding<T: Real>(tol: f64) {
        let Some(j) = reference() else { return };
        let mut g = HashGrid::<T>::zeros(&reference_config()).unwrap();
        fill_reference_table(&mut g);
        let x: Vec<T> = reference_points(&j).into_iter().map(T::c).collect();
        let mut y = vec![T::zero(); 6 * 32];
        g.forward(&x, &mut y);
        let expect = flat(&j["outputs"]["embedding"]);
        let keep = j["outputs"]["keep_mask"].as_array().unwrap();
        let mut max_err = 0.0f64;
        for i in 0..6 {
            let inside = keep[i].as_bool().unwrap();
            assert_eq!(inside, i < 5);
            if inside {
                for k in 0..32 {
                    let (a, b) = (y[i * 32 + k].f64(), expect[i * 32 + k]);
                    max_err = max_err.max((a - b).abs());
                    assert!(
                        (a - b).abs() < tol,
                        "point {i} dim {k}: {a} vs HashNeRF {b}"
                    );
                }
            } else {
                // Outside the box HashNeRF extrapolates with w < 0; we clamp to the face, so only finiteness
                // is asserted (the field masks such samples anyway).
                assert!(y[i * 32..i * 32 + 32].iter().all(|v| v.is_finite()));
            }
        }
        eprintln!(
            "reference embedding ({}): max error {max_err:.2e}",
            std::any::type_name::<T>()
        );
    }

    #[test]
    fn reference_embedding_f32() {
        check_reference_embedding::<f32>(2e-5);
    }

    #[test]
    fn reference_embedding_f64() {
        check_reference_embedding::<f64>(2e-5);
    }

    /// Cells and corner slots of the 5 inside points at every level, against HashNeRF's
    /// `bottom_left_idx` and `corner_hash_indices` (corner c = 4i + 2j + k with i the x offset).
    #[test]
    fn reference_cells_and_corner_slots() {
        let Some(j) = reference() else { return };
        let g = HashGrid::<f64>::zeros(&reference_config()).unwrap();
        let x = reference_points(&j);
        let per_level = j["outputs"]["per_level"].as_array().unwrap();
        for (l, pl) in per_level.iter().enumerate() {
            assert_eq!(
                pl["resolution"].as_f64().unwrap() as u32,
                g.resolutions()[l]
            );
            let bl = flat(&pl["bottom_left_idx"]);
            let ch = flat(&pl["corner_hash_indices"]);
            let lv = g.levels[l];
            for i in 0..5 {
                let c = cell::<f64, 2>(&lv, lv.scale_offset(), &x[3 * i..3 * i + 3]);
                let v0: [u32; 3] = std::array::from_fn(|a| bl[3 * i + a] as u32);
                for a in 0..3 {
                    let v = (x[3 * i + a] * lv.res as f64).floor() as u32;
                    assert_eq!(v, v0[a], "level {l} point {i} axis {a}");
                }
                for c_peer in 0..8 {
                    let (di, dj, dk) = (
                        (c_peer >> 2) as u32,
                        ((c_peer >> 1) & 1) as u32,
                        (c_peer & 1) as u32,
                    );
                    let s = g.slot(l, [v0[0] + di, v0[1] + dj, v0[2] + dk]);
                    assert_eq!(
                        s as f64,
                        ch[8 * i + c_peer],
                        "level {l} point {i} corner {c_peer}"
                    );
                    // Our corner numbering has bit 0 = x.
                    let ours = (di + 2 * dj + 4 * dk) as usize;
                    assert_eq!(c.idx[ours], 2 * s);
                }
            }
        }
    }

    /// tiny-cuda-nn's placement: `p = x·(N_min·b^l − 1) + ½`, worked out by hand for the default
    /// levels; the box's corners sit in the middle of a level's first and last cells.
    #[test]
    fn staggered_levels_by_hand() {
        let cfg = HashGridConfig { align: GridAlign::Staggered, ..HashGridConfig::default() };
        let b = cfg.growth_factor();
        let scales = cfg.level_scales();
        assert_eq!(scales[0], 15.0);
        assert_eq!(scales[1], 16.0 * b - 1.0);
        assert_eq!(cfg.level_offset(), 0.5);
        let res = cfg.level_resolutions();
        // Level 0: p ∈ [0.5, 15.5], cells 0..=15 (17 vertices per axis); the finest: s = 2047
        // (b^15 in f32 may land a hair below 128), p ≤ 2047.5, 2048 cells.
        assert_eq!(res[0], 16);
        assert_eq!(res[15], (scales[15] + 0.5).floor() as u32 + 1);
        assert!((2047..=2048).contains(&res[15]), "{res:?}");
        for (s, r) in scales.iter().zip(&res) {
            assert!(((s + 0.5).floor() as u32) < *r);
        }
        let small = HashGridConfig { n_levels: 2, log2_hashmap_size: 14, base_resolution: 4, max_resolution: 8, init_scale: 1.0, ..cfg };
        let g = HashGrid::<f64>::new(&small, &mut nerf_core::rng(3, 0));
        // Level 0 (s = 3, dense: 5³ ≤ 2^14): x = 0 → p = ½, the middle of cell 0 → equal weights.
        let c = cell::<f64, 2>(&g.levels[0], g.levels[0].scale_offset(), &[0.0, 0.0, 1.0]);
        assert!(c.w.iter().all(|w| (w - 0.125).abs() < 1e-15), "{:?}", c.w);
        // z = 1 → p = 3.5: cell 3, corners at z = 3 and 4.
        assert_eq!(c.idx[0], g.slot(0, [0, 0, 3]) * 2);
        assert_eq!(c.idx[7], g.slot(0, [1, 1, 4]) * 2);
        // x = 0.3 at level 1 (s = 7): p = 2.6 → cell 2, fraction 0.6.
        let c = cell::<f64, 2>(&g.levels[1], g.levels[1].scale_offset(), &[0.3, 0.0, 0.0]);
        assert!((c.frac[0] - 0.6).abs() < 1e-6 && c.frac[1] == 0.5);
        assert_eq!(c.idx[0], g.slot(1, [2, 0, 0]) * 2);
    }

    #[test]
    fn far_face_lands_in_last_cell_and_inputs_are_clamped() {
        let mut r = nerf_core::rng(3, 0);
        let g = HashGrid::<f32>::new(&HashGridConfig::default(), &mut r);
        let mut y = vec![0.0f32; 32];
        g.forward(&[1.0, 1.0, 1.0], &mut y);
        for l in 0..16 {
            let res = g.resolutions()[l];
            let s = g.level_offsets()[l] + 2 * g.slot(l, [res, res, res]);
            assert_eq!(&y[2 * l..2 * l + 2], &g.params()[s..s + 2], "level {l}");
        }
        g.forward(&[0.0, 0.0, 0.0], &mut y);
        for l in 0..16 {
            let s = g.level_offsets()[l] + 2 * g.slot(l, [0, 0, 0]);
            assert_eq!(&y[2 * l..2 * l + 2], &g.params()[s..s + 2], "level {l}");
        }
        let mut a = vec![0.0f32; 32];
        let mut b = vec![0.0f32; 32];
        g.forward(&[-0.5, 2.0, 0.3], &mut a);
        g.forward(&[0.0, 1.0, 0.3], &mut b);
        assert_eq!(a, b);
        g.forward(&[f32::NAN, f32::INFINITY, f32::NEG_INFINITY], &mut a);
        assert!(a.iter().all(|v| v.is_finite()));
    }

    /// Random points whose fractional cell coordinate is in [0.05, 0.95] on every axis at every level.
    fn interior_points(g: &HashGrid<f64>, n: usize, r: &mut nerf_core::Rng) -> Vec<f64> {
        let mut out = Vec::with_capacity(3 * n);
        let mut tries = 0;
        while out.len() < 3 * n {
            tries += 1;
            assert!(tries < 1_000_000, "could not find interior points");
            let p: [f64; 3] = std::array::from_fn(|_| r.gen::<f64>());
            let ok = g.levels.iter().all(|lv| {
                p.iter().all(|&x| {
                    let q = x * lv.scale as f64 + lv.offset as f64;
                    (0.05..=0.95).contains(&(q - q.floor()))
                })
            });
            if ok {
                out.extend_from_slice(&p);
            }
        }
        out
    }

    fn loss(g: &HashGrid<f64>, x: &[f64], w: &[f64]) -> f64 {
        let mut y = vec![0.0; w.len()];
        g.forward(x, &mut y);
        y.iter().zip(w).map(|(a, b)| a * b).sum()
    }

    #[test]
    fn backward_params_matches_finite_differences_f64() {
        for (f, align) in [(1, GridAlign::Corner), (2, GridAlign::Corner), (4, GridAlign::Corner), (2, GridAlign::Staggered)] {
            let cfg = HashGridConfig { align, ..small_config(f, Precision::F32) };
            let mut r = nerf_core::rng(4, f as u64);
            let mut g = HashGrid::<f64>::new(&cfg, &mut r);
            assert!((0..6).any(|l| g.is_dense(l)) && (0..6).any(|l| !g.is_dense(l)));
            let n = 5;
            let x = interior_points(&g, n, &mut r);
            let od = 6 * f;
            let w: Vec<f64> = (0..n * od).map(|_| r.gen::<f64>() - 0.5).collect();
            let mut dp = vec![0.0; g.params().len()];
            g.backward(&x, &w, &mut dp, None);
            // Every level receives gradient (8 corners × n samples each).
            for l in 0..6 {
                let o = g.level_offsets();
                assert!(
                    dp[o[l]..o[l + 1]].iter().any(|v| *v != 0.0),
                    "level {l} got no gradient"
                );
            }
            // The loss is linear in the params: central differences are exact up to rounding. Check all.
            let h = 1e-3;
            for i in 0..dp.len() {
                let p0 = g.params()[i];
                g.params_mut()[i] = p0 + h;
                let lp = loss(&g, &x, &w);
                g.params_mut()[i] = p0 - h;
                let lm = loss(&g, &x, &w);
                g.params_mut()[i] = p0;
                let fd = (lp - lm) / (2.0 * h);
                assert!(
                    (fd - dp[i]).abs() < 1e-9,
                    "F={f} d_params[{i}]: analytic {} vs fd {fd}",
                    dp[i]
                );
            }
            // backward accumulates.
            let mut dp2 = dp.clone();
            g.backward(&x, &w, &mut dp2, None);
            assert!(dp2
                .iter()
                .zip(&dp)
                .all(|(a, b)| (a - 2.0 * b).abs() < 1e-12));
        }
    }

    #[test]
    fn backward_input_matches_finite_differences_f64() {
        for (f, storage, align) in [
            (2, Precision::F32, GridAlign::Corner),
            (4, Precision::F32, GridAlign::Corner),
            (8, Precision::F16, GridAlign::Corner),
            (2, Precision::F16, GridAlign::Corner),
            (2, Precision::F32, GridAlign::Staggered),
            (4, Precision::F16, GridAlign::Staggered),
        ] {
            let cfg = HashGridConfig { align, ..small_config(f, storage) };
            let mut r = nerf_core::rng(5, f as u64);
            let g = HashGrid::<f64>::new(&cfg, &mut r);
            let n = 6;
            let x = interior_points(&g, n, &mut r);
            let w: Vec<f64> = (0..n * 6 * f).map(|_| r.gen::<f64>() - 0.5).collect();
            let mut dp = vec![0.0; g.params().len()];
            let mut dx = vec![f64::NAN; 3 * n];
            g.backward(&x, &w, &mut dp, Some(&mut dx));
            let h = 1e-6;
            for i in 0..3 * n {
                let mut xp = x.clone();
                xp[i] += h;
                let mut xm = x.clone();
                xm[i] -= h;
                let fd = (loss(&g, &xp, &w) - loss(&g, &xm, &w)) / (2.0 * h);
                let err = (fd - dx[i]).abs() / dx[i].abs().max(1.0);
                assert!(
                    err < 1e-6,
                    "F={f} {storage:?} {align:?} d_input[{i}]: analytic {} vs fd {fd}",
                    dx[i]
                );
                assert!(
                    dx[i].abs() > 1e-3,
                    "d_input[{i}] = {} is suspiciously small",
                    dx[i]
                );
            }
        }
        // Outside the unit cube the clamp makes the encoding constant: zero input gradient.
        let g = HashGrid::<f64>::new(&small_config(2, Precision::F32), &mut nerf_core::rng(6, 0));
        let mut dx = [f64::NAN; 3];
        let mut dp = vec![0.0; g.params().len()];
        g.backward(&[-0.2, 0.5, 1.3], &[1.0; 12], &mut dp, Some(&mut dx));
        assert_eq!(dx[0], 0.0);
        assert_eq!(dx[2], 0.0);
        assert!(dx[1] != 0.0);
    }

    #[test]
    fn f16_gradient_sums_match_f32_within_half_rounding() {
        // Gradients whose scaled shares lie in f16's normal range: the half-precision sums stay
        // within a few f16 roundings of the f32 sums, and do differ from them.
        let mut r = nerf_core::rng(21, 0);
        for f in [1, 2, 4] {
            let cfg = small_config(f, Precision::F32);
            let g32 = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(22, f as u64));
            let g16 = HashGrid::<f32>::new(&HashGridConfig { grad_f16_scale: Some(1024.0), ..cfg.clone() }, &mut nerf_core::rng(22, f as u64));
            let n = 400;
            let x: Vec<f32> = (0..3 * n).map(|_| r.gen::<f32>()).collect();
            let w: Vec<f32> = (0..n * 6 * f).map(|_| (r.gen::<f32>() - 0.5) * 1e-2).collect();
            let w_abs: Vec<f32> = w.iter().map(|v| v.abs()).collect();
            let (mut d32, mut d16, mut d_abs) = (vec![0.0; g32.params().len()], vec![0.0; g32.params().len()], vec![0.0; g32.params().len()]);
            g32.backward(&x, &w, &mut d32, None);
            g16.backward(&x, &w, &mut d16, None);
            // Σ w_k·|g| over an entry's contributions (trilinear weights are ≥ 0).
            g32.backward(&x, &w_abs, &mut d_abs, None);
            let mut differ = 0;
            for i in 0..d32.len() {
                // Each scaled gradient, share and running sum rounds once, by at most 2⁻¹¹ of
                // the absolute sum Σ; ~26 additions reach an entry of the coarsest level here
                // (400 samples × 8 corners over 5³ vertices), and their errors mostly cancel, so
                // 32 roundings' worth bounds the error in practice (the worst case is ~3× that).
                let tol = 4.0 * 2f32.powi(-11) * d_abs[i] * 8.0 + 1e-9;
                assert!((d16[i] - d32[i]).abs() <= tol, "F={f} entry {i}: f16 {} vs f32 {} (|Σ| {})", d16[i], d32[i], d_abs[i]);
                differ += (d16[i] != d32[i]) as usize;
            }
            assert!(differ > 0, "F={f}: the f16 sums equal the f32 ones everywhere");
            assert!(d16.iter().filter(|v| **v != 0.0).count() > 100, "F={f}: too few entries touched");
        }
    }

    #[test]
    fn f16_gradient_sums_round_each_share_and_drop_the_tiny_ones() {
        let cfg = HashGridConfig { grad_f16_scale: Some(16.0), ..small_config(2, Precision::F32) };
        let g = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(23, 0));
        let x = [0.3137f32, 0.7063, 0.5772];
        let nd = 6 * 2;
        let r16 = |v: f32| half::f16::from_f32(v).to_f32();
        // One sample: every entry holds f16(f16(g·S)·w)/S, its trilinear share rounded twice.
        let gv = 1.2345e-3f32;
        let mut d = vec![0.0f32; g.params().len()];
        g.backward(&x, &vec![gv; nd], &mut d, None);
        let mut d32 = vec![0.0f32; g.params().len()];
        HashGrid::<f32>::new(&HashGridConfig { grad_f16_scale: None, ..cfg.clone() }, &mut nerf_core::rng(23, 0)).backward(&x, &vec![gv; nd], &mut d32, None);
        let mut checked = 0;
        for (a, b) in d.iter().zip(&d32) {
            if *b != 0.0 {
                let w = b / gv; // the f32 share's trilinear weight
                let want = r16(r16(gv * 16.0) * w) / 16.0;
                assert!((a - want).abs() <= 1e-6 * want.abs(), "entry: {a} vs {want} (w {w})");
                checked += 1;
            }
        }
        assert!(checked >= 8 * 6, "only {checked} entries checked");
        // A gradient whose scaled shares fall below half of f16's smallest subnormal (2⁻²⁴) leaves
        // every entry at exactly zero, where f32 sums keep it.
        let tiny = 2f32.powi(-26) / 16.0;
        let mut d = vec![0.0f32; g.params().len()];
        g.backward(&x, &vec![tiny; nd], &mut d, None);
        assert!(d.iter().all(|v| *v == 0.0), "a tiny gradient survived the f16 sums");
        let mut d32 = vec![0.0f32; g.params().len()];
        HashGrid::<f32>::new(&HashGridConfig { grad_f16_scale: None, ..cfg.clone() }, &mut nerf_core::rng(23, 0)).backward(&x, &vec![tiny; nd], &mut d32, None);
        assert!(d32.iter().any(|v| *v != 0.0));
    }

    #[test]
    fn grad_f16_scale_is_validated_and_left_out_of_configs_without_it() {
        for bad in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let cfg = HashGridConfig { grad_f16_scale: Some(bad), ..HashGridConfig::default() };
            assert!(matches!(cfg.validate(), Err(HashGridConfigError::GradScale(_))), "{bad} passed");
        }
        assert!(HashGridConfig { grad_f16_scale: Some(128.0), ..HashGridConfig::default() }.validate().is_ok());
        let v = serde_json::to_value(HashGridConfig::default()).unwrap();
        assert!(v.get("grad_f16_scale").is_none(), "the default config serialises the key: {v}");
        let c: HashGridConfig = serde_json::from_str(r#"{"grad_f16_scale": 1024}"#).unwrap();
        assert_eq!(c.grad_f16_scale, Some(1024.0));
        assert_eq!(serde_json::from_value::<HashGridConfig>(serde_json::to_value(&c).unwrap()).unwrap(), c);
    }

    #[test]
    fn f16_storage_matches_f32_within_rounding_and_syncs() {
        let cfg = HashGridConfig {
            log2_hashmap_size: 14,
            ..HashGridConfig::default()
        };
        let g32 = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(7, 0));
        let mut g16 = HashGrid::<f32>::new(
            &HashGridConfig {
                storage: Precision::F16,
                ..cfg.clone()
            },
            &mut nerf_core::rng(7, 0),
        );
        assert_eq!(g32.params(), g16.params());
        let mut r = nerf_core::rng(7, 1);
        let n = 2000;
        let x: Vec<f32> = (0..3 * n).map(|_| r.gen::<f32>()).collect();
        let (mut a, mut b) = (vec![0.0f32; 32 * n], vec![0.0f32; 32 * n]);
        g32.forward(&x, &mut a);
        g16.forward(&x, &mut b);
        let diff = a
            .iter()
            .zip(&b)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0f32, f32::max);
        // f16 rounding: relative 2^-11 of the table magnitude (1e-4), and 2^-25 absolute in the subnormals.
        assert!(diff <= 1e-3 * cfg.init_scale, "f16 vs f32: {diff}");
        assert!(diff > 0.0, "the f16 mirror was not read");
        // Change the params: the mirror keeps the old values until sync_storage.
        for p in g16.params_mut() {
            *p = *p * 1000.0 + 0.25;
        }
        let mut c = vec![0.0f32; 32 * n];
        g16.forward(&x, &mut c);
        assert_eq!(b, c);
        g16.sync_storage();
        g16.forward(&x, &mut c);
        let mut g32b = g32.clone();
        for p in g32b.params_mut() {
            *p = *p * 1000.0 + 0.25;
        }
        g32b.forward(&x, &mut a);
        let diff = a
            .iter()
            .zip(&c)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0f32, f32::max);
        assert!(diff <= 1e-3 * 0.35, "after sync: {diff}");
        assert!(a
            .iter()
            .zip(&c)
            .any(|(p, q)| (p - 0.25).abs() > 1e-3 && (q - 0.25).abs() > 1e-3));
    }

    #[test]
    fn parallel_equals_serial_and_is_deterministic() {
        let cfg = HashGridConfig {
            log2_hashmap_size: 15,
            ..HashGridConfig::default()
        };
        let g = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(8, 0));
        let mut r = nerf_core::rng(8, 1);
        let n = 3 * MIN_BLOCK + 17;
        let x: Vec<f32> = (0..3 * n).map(|_| r.gen::<f32>()).collect();
        let d: Vec<f32> = (0..32 * n).map(|_| r.gen::<f32>() - 0.5).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut y = vec![0.0f32; 32 * n];
                g.forward(&x, &mut y);
                let mut dp = vec![0.0f32; g.params().len()];
                let mut dx = vec![0.0f32; 3 * n];
                g.backward(&x, &d, &mut dp, Some(&mut dx));
                (y, dp, dx)
            })
        };
        let (y1, dp1, dx1) = run(1);
        let (y4, dp4, dx4) = run(4);
        assert!(y1 == y4, "forward differs between 1 and 4 threads");
        assert!(dp1 == dp4, "d_params differ between 1 and 4 threads");
        assert!(dx1 == dx4, "d_input differs between 1 and 4 threads");
        assert!(dp1.iter().any(|v| *v != 0.0));
        // Single samples (the serial path) equal the batched results.
        let mut y1s = [0.0f32; 32];
        let mut dps = vec![0.0f32; g.params().len()];
        for k in [0, 1, MIN_BLOCK, 2 * MIN_BLOCK + 5, n - 1] {
            g.forward(&x[3 * k..3 * k + 3], &mut y1s);
            assert_eq!(&y1s[..], &y4[32 * k..32 * k + 32], "sample {k}");
            let mut dxs = [0.0f32; 3];
            g.backward(
                &x[3 * k..3 * k + 3],
                &d[32 * k..32 * k + 32],
                &mut dps,
                Some(&mut dxs),
            );
            assert_eq!(&dxs[..], &dx4[3 * k..3 * k + 3], "sample {k}");
        }
        // Accumulating two halves equals the whole batch, bit for bit (same per-level order).
        let h = n / 2;
        let mut dp = vec![0.0f32; g.params().len()];
        g.backward(&x[..3 * h], &d[..32 * h], &mut dp, None);
        g.backward(&x[3 * h..], &d[32 * h..], &mut dp, None);
        assert!(dp == dp1);
    }

    #[test]
    fn prefetched_levels_equal_single_samples() {
        // The default 2^19 table: its hashed levels (4 MiB each) take the prefetching loops.
        let g = HashGrid::<f32>::new(&HashGridConfig::default(), &mut nerf_core::rng(9, 0));
        assert!((0..g.n_levels()).any(|l| g.level_size(l) * 2 * 4 >= PREFETCH_MIN_BYTES));
        let mut r = nerf_core::rng(9, 1);
        for n in [PREFETCH_DISTANCE - 1, PREFETCH_DISTANCE + 1, 300, 3 * MIN_BLOCK + 17] {
            let x: Vec<f32> = (0..3 * n).map(|_| r.gen::<f32>()).collect();
            let d: Vec<f32> = (0..32 * n).map(|_| r.gen::<f32>() - 0.5).collect();
            let mut y = vec![f32::NAN; 32 * n];
            g.forward(&x, &mut y);
            let mut dp = vec![0.0f32; g.params().len()];
            g.backward(&x, &d, &mut dp, None);
            // One sample at a time (no look-ahead), in order: the same values, and the same per-slot
            // sums in the same order, so bit for bit.
            let mut ys = [0.0f32; 32];
            let mut dps = vec![0.0f32; g.params().len()];
            for k in 0..n.min(400) {
                g.forward(&x[3 * k..3 * k + 3], &mut ys);
                assert_eq!(&ys[..], &y[32 * k..32 * k + 32], "n {n}, sample {k}");
                g.backward(&x[3 * k..3 * k + 3], &d[32 * k..32 * k + 32], &mut dps, None);
            }
            if n <= 400 {
                assert!(dps == dp, "n {n}: d_params differ");
            }
        }
    }

    #[test]
    fn config_serde_and_validation() {
        let c: HashGridConfig =
            serde_json::from_str(r#"{"n_levels": 8, "storage": "f16"}"#).unwrap();
        assert_eq!(
            c,
            HashGridConfig {
                n_levels: 8,
                storage: Precision::F16,
                ..Default::default()
            }
        );
        assert!(serde_json::from_str::<HashGridConfig>(r#"{"n_level": 8}"#).is_err());
        let back: HashGridConfig =
            serde_json::from_str(&serde_json::to_string(&c).unwrap()).unwrap();
        assert_eq!(back, c);
        let d = HashGridConfig::default();
        let bad = [
            (
                HashGridConfig {
                    n_levels: 0,
                    ..d.clone()
                },
                "n_levels",
            ),
            (
                HashGridConfig {
                    n_features_per_level: 3,
                    ..d.clone()
                },
                "n_features_per_level",
            ),
            (
                HashGridConfig {
                    log2_hashmap_size: 31,
                    ..d.clone()
                },
                "log2_hashmap_size",
            ),
            (
                HashGridConfig {
                    max_resolution: 8,
                    ..d.clone()
                },
                "max_resolution",
            ),
            (
                HashGridConfig {
                    init_scale: f32::NAN,
                    ..d.clone()
                },
                "init_scale",
            ),
        ];
        for (cfg, word) in bad {
            let e = HashGrid::<f32>::try_new(&cfg, &mut nerf_core::rng(0, 0)).unwrap_err();
            assert!(e.to_string().contains(word), "{e}");
        }
        // One level: b = 1, the level has the base resolution.
        let one = HashGridConfig { n_levels: 1, ..d };
        assert_eq!(one.level_resolutions(), [16]);
    }

    #[test]
    fn trait_object_exposes_params() {
        let mut e: Box<dyn Encoding<f32>> = Box::new(HashGrid::<f32>::new(
            &small_config(2, Precision::F16),
            &mut nerf_core::rng(10, 0),
        ));
        assert_eq!(e.params().len(), e.n_params());
        assert_eq!(e.params_mut().len(), e.n_params());
        let x = [0.3f32, 0.6, 0.9];
        let mut before = [0.0f32; 12];
        e.forward(&x, &mut before);
        e.params_mut().iter_mut().for_each(|p| *p += 1.0);
        e.sync_storage();
        let mut after = [0.0f32; 12];
        e.forward(&x, &mut after);
        // The trilinear weights sum to 1, so adding 1 to every parameter adds 1 to every output.
        for (a, b) in after.iter().zip(&before) {
            assert!((a - b - 1.0).abs() < 2e-3, "{a} vs {b} + 1");
        }
        let freq: Box<dyn Encoding<f32>> = Box::new(crate::FrequencyEncoding::new(
            3,
            &crate::FrequencyEncodingConfig::nerf_direction(),
        ));
        assert!(freq.params().is_empty());
    }

    #[test]
    fn f16_conversion_is_exact_for_every_bit_pattern() {
        for b in 0..=u16::MAX {
            let h = f16::from_bits(b);
            let (ours, theirs) = (f16_to_f32(h), h.to_f32());
            if theirs.is_nan() {
                assert!(ours.is_nan(), "{b:#06x}");
            } else {
                assert_eq!(ours.to_bits(), theirs.to_bits(), "{b:#06x}");
            }
        }
    }

    #[test]
    fn init_is_uniform_in_scale() {
        let cfg = HashGridConfig {
            log2_hashmap_size: 12,
            init_scale: 0.5,
            ..HashGridConfig::default()
        };
        let g = HashGrid::<f32>::new(&cfg, &mut nerf_core::rng(9, 0));
        let p = g.params();
        assert!(p.iter().all(|v| v.abs() <= 0.5));
        let mean = p.iter().map(|v| *v as f64).sum::<f64>() / p.len() as f64;
        let var = p.iter().map(|v| (*v as f64).powi(2)).sum::<f64>() / p.len() as f64;
        assert!(
            mean.abs() < 0.01 && (var - 0.25 / 3.0).abs() < 0.005,
            "mean {mean} var {var}"
        );
        let g64 = HashGrid::<f64>::new(&cfg, &mut nerf_core::rng(9, 0));
        assert!(g64.params().iter().zip(p).all(|(a, b)| *a == *b as f64));
    }
}
