//! Training rays and occupancy-grid marching on the device, plus multi-level prefix sums
//! (`shaders/rays.wgsl`, `shaders/march.wgsl`, `shaders/scan.wgsl`).
//!
//! * [`GpuImages`]: every training image on the device once, with one [`GpuCamera`] per view.
//!   Pixels are RGBA8 (one `u32` per pixel, `r | g<<8 | b<<16 | a<<24`, value/255) when every
//!   value of the dataset is exactly `k/255` (8-bit PNGs, what `nerf_data` loads: lossless), else
//!   RGBA16 (two `u32` per pixel, `r | g<<16`, `b | a<<16`, value/65535: lossless for 16-bit PNGs,
//!   a 1/65535 quantisation for anything else).
//! * [`GpuRayGen`]: a batch of training rays ([`GpuRays`]) drawn on the device, over every pixel
//!   or over the pixels the training masks keep; CPU twin [`ray_batch_cpu`].
//! * [`GpuScan`]: exclusive prefix sum of `u32` (1024 values per workgroup, multi-level).
//! * [`GpuMarcher`]: Instant-NGP marching through an occupancy bitfield into the packed layout
//!   ([`GpuSamples`]); CPU twin [`nerf_sampling::march`].
//!
//! Dynamic sizes live in the `counters` buffer ([`crate::layout::COUNTER_N_RAYS`] = number of
//! rays of the step, [`crate::layout::COUNTER_N_SAMPLES`] = number of packed samples, written by
//! the marcher). Kernels are launched for the capacities and return early past the counts.
//! Every `record*` method only records into the caller's encoder; per-step values (seed, jitter)
//! are queued with [`GpuContext::write`] by `set_*` methods, so record at most one use of each
//! instance per submission.

use crate::kernel::{groups_1d, Kernel};
use crate::layout::COUNTER_N_RAYS;
use crate::{rng, shaders, GpuContext, GpuError};
use nerf_data::{Background, Dataset, Pixels, RayBatch};
use nerf_rays::{LensModel, PixelConvention};
pub use crate::layout::{GpuCamera};
use crate::layout::{ImagesInfo, MarchParams, RayGenParams, RoundParams, RoundRayState, ScanParams};

/// Random stream of the view index of ray `r` (`rand_u32(seed, stream, r) % n_views`).
pub const RAY_STREAM_VIEW: u32 = 0x5241_0001;
/// Random stream of the pixel column (`% width`).
pub const RAY_STREAM_COL: u32 = 0x5241_0002;
/// Random stream of the pixel row (`% height`).
pub const RAY_STREAM_ROW: u32 = 0x5241_0003;
/// Random stream of the horizontal sub-pixel jitter (`rand_f32`).
pub const RAY_STREAM_JITTER_U: u32 = 0x5241_0004;
/// Random stream of the vertical sub-pixel jitter (`rand_f32`).
pub const RAY_STREAM_JITTER_V: u32 = 0x5241_0005;
/// Random streams of the random background, `+ c` for channel `c` (`rand_f32`).
pub const RAY_STREAM_BACKGROUND: u32 = 0x5241_0006;
/// Random stream of the marching offset `u` of ray `r` (`rand_f32`) when jitter is on.
pub const MARCH_STREAM_U: u32 = 0x4d41_5243;

/// Invocations per workgroup of the ray and marching kernels.
const WG: u32 = 64;
/// Values per workgroup of the scan (256 invocations × 4).
const SCAN_BLOCK: usize = 1024;
/// Invocations per workgroup of the scan.
const SCAN_WG: u32 = 256;
/// Cells per axis of the coarse blocks the marcher skips in one jump.
const CBLOCK: u32 = 4;

// ---------------------------------------------------------------------------------------------
// Images

/// How [`GpuImages`] stores pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PixelFormat {
    /// One `u32` per pixel, 8 bits per channel (exact for 8-bit sources).
    Rgba8,
    /// Two `u32` per pixel, 16 bits per channel.
    Rgba16,
}

/// All training images and cameras of a dataset on the device (uploaded once).
pub struct GpuImages {
    /// Packed pixels (see the module docs for the two formats).
    pub pixels: wgpu::Buffer,
    /// One [`GpuCamera`] per view.
    pub cameras: wgpu::Buffer,
    /// The training masks: per view its first kept pixel's rank and the offset of its kept
    /// pixels in this buffer (`0xffffffff`: every pixel), then those lists (`shaders/rays.wgsl`);
    /// one unused word for a dataset without masks.
    pub masks: wgpu::Buffer,
    /// The depth maps ([`Dataset::depths`]): per pixel the measured distance along its ray (0:
    /// none), laid out as the pixels; one unused word for a dataset without depth maps.
    pub depths: wgpu::Buffer,
    info: wgpu::Buffer,
    n_views: usize,
    format: PixelFormat,
}

impl GpuImages {
    /// Uploads `dataset`'s images (RGBA8 when every value is exactly `k/255`, else RGBA16),
    /// cameras, training masks ([`Dataset::masks`]: 8 bytes per view and 4 per kept pixel of a
    /// view that does not keep every pixel) and depth maps ([`Dataset::depths`]: 4 bytes per
    /// pixel). Errors when the dataset has no views, an image does
    /// not hold `4·W·H` values, the masks do not match the views, or the pixels or masks exceed
    /// the device's largest storage binding.
    pub fn new(ctx: &GpuContext, dataset: &Dataset) -> Result<Self, GpuError> {
        let name = dataset.root.display();
        let n_views = dataset.n_views();
        if n_views == 0 {
            return Err(GpuError::Unsupported(format!("dataset {name}: no training views to upload")));
        }
        let (w, h) = (dataset.width as usize, dataset.height as usize);
        if w == 0 || h == 0 {
            return Err(GpuError::Unsupported(format!("dataset {name}: empty image size {w}x{h}")));
        }
        if dataset.images.len() != n_views {
            return Err(GpuError::Unsupported(format!(
                "dataset {name}: {} images for {n_views} cameras",
                dataset.images.len()
            )));
        }
        for (i, img) in dataset.images.iter().enumerate() {
            if img.len() != 4 * w * h {
                return Err(GpuError::Unsupported(format!(
                    "dataset {name}: image {i} ({}) holds {} values, expected 4·{w}·{h}",
                    dataset.file_paths.get(i).map(|p| p.display().to_string()).unwrap_or_default(),
                    img.len()
                )));
            }
        }
        // The views' own bits (`nerf_data::Pixels`): 8 where every view has them, else 16.
        let exact8 = dataset.images.iter().all(Pixels::is_rgba8);
        let format = if exact8 { PixelFormat::Rgba8 } else { PixelFormat::Rgba16 };
        let words_per_pixel = if exact8 { 1 } else { 2 };
        let n_words = n_views * w * h * words_per_pixel;
        let limit: u64 = ctx.device.limits().max_storage_buffer_binding_size;
        if 4 * n_words as u64 > limit {
            return Err(GpuError::Unsupported(format!(
                "dataset {name}: {n_views} images of {w}x{h} take {} MiB as {format:?}, more than the device's largest storage binding ({} MiB); downscale the images",
                (4 * n_words as u64) >> 20,
                limit >> 20
            )));
        }
        let mut words = Vec::with_capacity(n_words);
        for img in &dataset.images {
            match img {
                Pixels::Rgba8(b) if exact8 => words.extend(b.chunks_exact(4).map(|p| u32::from_le_bytes([p[0], p[1], p[2], p[3]]))),
                _ => words.extend(img.to_u16().chunks_exact(2).map(|p| p[0] as u32 | (p[1] as u32) << 16)),
            }
        }
        let cams: Vec<GpuCamera> = dataset
            .cameras
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let m = c.c2w();
                let k = &c.intrinsics;
                let d = &c.distortion;
                let lens = match d.model {
                    _ if d.is_identity() => GpuCamera::PINHOLE,
                    LensModel::RadialTangential => GpuCamera::RADIAL_TANGENTIAL,
                    LensModel::Fisheye => GpuCamera::FISHEYE,
                    LensModel::Fisheye624 => GpuCamera::FISHEYE624,
                    LensModel::Fov => GpuCamera::FOV,
                    LensModel::Division => GpuCamera::DIVISION,
                    LensModel::Eucm => GpuCamera::EUCM,
                };
                let mut coefficients = d.coefficients().map(|c| c as f32);
                if d.model == LensModel::Fov {
                    coefficients = [0.0; 12];
                    coefficients[0] = d.omega as f32;
                }
                if d.model == LensModel::Eucm {
                    coefficients = [0.0; 12];
                    (coefficients[0], coefficients[1]) = (d.alpha as f32, d.beta as f32);
                }
                GpuCamera {
                    c2w: [m[0], m[1], m[2]],
                    intrinsics: [k.fx, k.fy, k.cx, k.cy],
                    size: [w as u32, h as u32, (i * w * h) as u32, lens],
                    lens: coefficients,
                }
            })
            .collect();
        let masks: Vec<u32> = match &dataset.masks {
            None => vec![0],
            Some(m) => {
                if m.n_views() != n_views || m.n_pixels() as usize != w * h || m.total() == 0 {
                    return Err(GpuError::Unsupported(format!(
                        "dataset {name}: masks of {} views of {} pixels keep {} pixels, for {n_views} views of {w}x{h}",
                        m.n_views(),
                        m.n_pixels(),
                        m.total()
                    )));
                }
                // Views that share a list (`PixelMasks::with_shared_views`) share it here too:
                // each distinct list is uploaded once, at the offset of its first view.
                let mut lists: Vec<&[u32]> = Vec::new();
                let first: Vec<Option<usize>> = (0..n_views)
                    .map(|v| {
                        m.view(v).map(|l| match lists.iter().position(|&u| std::ptr::eq(u, l)) {
                            Some(i) => i,
                            None => {
                                lists.push(l);
                                lists.len() - 1
                            }
                        })
                    })
                    .collect();
                let listed: u64 = lists.iter().map(|l| l.len() as u64).sum();
                let words = 2 * n_views as u64 + listed;
                if m.total() >= u32::MAX as u64 || words > u32::MAX as u64 || 4 * words > limit {
                    return Err(GpuError::Unsupported(format!(
                        "dataset {name}: the masks of {n_views} images of {w}x{h} keep {} pixels, too many to index on the device; downscale the images",
                        m.total()
                    )));
                }
                let mut offsets = Vec::with_capacity(lists.len());
                let mut offset = 2 * n_views as u32;
                for l in &lists {
                    offsets.push(offset);
                    offset += l.len() as u32;
                }
                let mut table = Vec::with_capacity(words as usize);
                let mut start = 0u32;
                for (v, list) in first.iter().enumerate() {
                    table.push(start);
                    table.push(list.map_or(u32::MAX, |i| offsets[i]));
                    start += m.kept_in(v) as u32;
                }
                for l in &lists {
                    table.extend_from_slice(l);
                }
                table
            }
        };
        let depths: Vec<f32> = match &dataset.depths {
            None => vec![0.0],
            Some(d) => {
                if let Some(reason) = dataset.depths_mismatch() {
                    return Err(GpuError::Unsupported(format!("dataset {name}: {reason}")));
                }
                if 4 * (n_views * w * h) as u64 > limit {
                    return Err(GpuError::Unsupported(format!(
                        "dataset {name}: the depth maps of {n_views} images of {w}x{h} take {} MiB, more than the device's largest storage binding ({} MiB); downscale the images",
                        (4 * (n_views * w * h) as u64) >> 20,
                        limit >> 20
                    )));
                }
                d.concat()
            }
        };
        let ndc = dataset.ndc.unwrap_or(nerf_rays::Ndc { scale_x: 0.0, scale_y: 0.0, near: 0.0 });
        let info = ImagesInfo {
            n_views: n_views as u32,
            format: words_per_pixel as u32,
            ndc: dataset.ndc.is_some() as u32,
            ndc_near: ndc.near,
            ndc_scale_x: ndc.scale_x,
            ndc_scale_y: ndc.scale_y,
            n_kept: dataset.masks.as_ref().map_or(0, |m| m.total() as u32),
            has_depth: dataset.depths.is_some() as u32,
        };
        Ok(Self {
            pixels: ctx.upload("images", &words),
            cameras: ctx.upload("cameras", &cams),
            masks: ctx.upload("masks", &masks),
            depths: ctx.upload("depths", &depths),
            info: ctx.uniform("images_info", &info),
            n_views,
            format,
        })
    }

    /// Number of views.
    pub fn n_views(&self) -> usize {
        self.n_views
    }

    /// The pixel format chosen.
    pub fn format(&self) -> PixelFormat {
        self.format
    }
}

// ---------------------------------------------------------------------------------------------
// Ray generation

/// Device buffers of a batch of rays, `[capacity][3]` f32 (and one view index per ray).
pub struct GpuRays {
    /// Ray origins.
    pub origins: wgpu::Buffer,
    /// Unit directions.
    pub dirs: wgpu::Buffer,
    /// Target colour composited on the ray's background.
    pub target: wgpu::Buffer,
    /// The ray's background colour.
    pub background: wgpu::Buffer,
    /// The index of the view each ray comes from (`[capacity]` u32).
    pub views: wgpu::Buffer,
    /// The measured distance along each ray (`[capacity]` f32; 0: none), from the depth maps
    /// ([`GpuImages::depths`]); left as it is for images without depth maps.
    pub depth_target: wgpu::Buffer,
    /// Rays the buffers hold.
    pub capacity: usize,
}

impl GpuRays {
    /// Zeroed buffers for `capacity` rays.
    pub fn new(ctx: &GpuContext, capacity: usize) -> Self {
        let b = |label| ctx.zeros(label, 12 * capacity);
        Self {
            origins: b("ray_origins"),
            dirs: b("ray_dirs"),
            target: b("ray_target"),
            background: b("ray_background"),
            views: ctx.zeros("ray_views", 4 * capacity),
            depth_target: ctx.zeros("ray_depth_target", 4 * capacity),
            capacity,
        }
    }
}

/// Draws training rays from [`GpuImages`] on the device (`shaders/rays.wgsl`); CPU twin
/// [`ray_batch_cpu`] (same random streams, see the `RAY_STREAM_*` constants).
pub struct GpuRayGen {
    kernel: Kernel,
    params: wgpu::Buffer,
}

impl GpuRayGen {
    /// Compiles the kernel for a background mode (`Random`: one uniform colour per ray), a pixel
    /// convention and optional sub-pixel jitter (`TrainConfig::pixel_jitter`).
    pub fn new(ctx: &GpuContext, background: Background, conv: PixelConvention, jitter: bool) -> Self {
        let kernel = Kernel::new(ctx, &shaders::with_common(shaders::RAYS), "ray_gen", &[]);
        let params = RayGenParams {
            seed: 0,
            background: match background {
                Background::White => 0,
                Background::Black => 1,
                Background::Random => 2,
            },
            jitter: jitter as u32,
            pixel_offset: conv.offset(),
        };
        Self { kernel, params: ctx.uniform("ray_gen_params", &params) }
    }

    /// Queues the seed of the next batch (call once per step, before submitting it).
    pub fn set_seed(&self, ctx: &GpuContext, seed: u32) {
        ctx.write(&self.params, 0, &[seed]);
    }

    /// Records the generation of `n = min(counters[COUNTER_N_RAYS], rays.capacity)` rays into `rays`.
    pub fn record(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, counters: &wgpu::Buffer, images: &GpuImages, rays: &GpuRays) {
        self.kernel.record(
            ctx,
            enc,
            &[
                (0, &self.params),
                (1, &images.info),
                (2, counters),
                (3, &images.cameras),
                (4, &images.pixels),
                (5, &rays.origins),
                (6, &rays.dirs),
                (7, &rays.target),
                (8, &rays.background),
                (9, &rays.views),
                (10, &images.masks),
                (11, &images.depths),
                (12, &rays.depth_target),
            ],
            groups_1d(rays.capacity, WG),
        );
    }
}

/// CPU twin of [`GpuRayGen`]: `n_rays` rays drawn with [`crate::rng`] on the same streams (with
/// [`Dataset::masks`]: the `k`-th kept pixel, [`nerf_data::PixelMasks::pick`]), each
/// built with [`nerf_rays::Camera::ray_at`] (then [`Dataset::warp`]: NDC scenes) and composited with `nerf_data`'s rule
/// `rgb·a + (1 − a)·bg` (straight alpha). Fills `view_ids` and `pixel_ids` too.
///
/// # Panics
/// If the dataset has no views.
pub fn ray_batch_cpu(dataset: &Dataset, seed: u32, n_rays: usize, background: Background, conv: PixelConvention, jitter: bool) -> RayBatch {
    assert!(dataset.n_views() > 0, "ray_batch_cpu on a dataset without views");
    let (w, h) = (dataset.width, dataset.height);
    let off = conv.offset();
    let mut b = RayBatch::default();
    for r in 0..n_rays as u32 {
        let (view, col, row) = match &dataset.masks {
            None => (
                rng::rand_u32(seed, RAY_STREAM_VIEW, r) % dataset.n_views() as u32,
                rng::rand_u32(seed, RAY_STREAM_COL, r) % w,
                rng::rand_u32(seed, RAY_STREAM_ROW, r) % h,
            ),
            Some(m) => {
                let (view, pix) = m.pick(rng::rand_below(seed, RAY_STREAM_VIEW, r, m.total() as u32) as u64);
                (view, pix % w, pix / w)
            }
        };
        let (mut u, mut v) = (col as f32 + off, row as f32 + off);
        if jitter {
            u = u - 0.5 + rng::rand_f32(seed, RAY_STREAM_JITTER_U, r);
            v = v - 0.5 + rng::rand_f32(seed, RAY_STREAM_JITTER_V, r);
        }
        let bg = match background {
            Background::Random => std::array::from_fn(|c| rng::rand_f32(seed, RAY_STREAM_BACKGROUND + c as u32, r)),
            fixed => fixed.fixed_rgb(),
        };
        let ray = dataset.warp(dataset.cameras[view as usize].ray_at(u, v));
        let pix = row * w + col;
        let px = dataset.images[view as usize].rgba(pix as usize);
        let a = px[3];
        b.origins.extend_from_slice(&ray.origin.to_array());
        b.dirs.extend_from_slice(&ray.dir.to_array());
        b.target.extend((0..3).map(|c| px[c] * a + (1.0 - a) * bg[c]));
        b.background.extend_from_slice(&bg);
        b.view_ids.push(view);
        b.pixel_ids.push(pix);
    }
    b
}

// ---------------------------------------------------------------------------------------------
// Prefix sums

/// Number of dynamic-length slots [`GpuScan`] prepares uniforms for.
const SCAN_SLOTS: usize = 4;

/// Exclusive prefix sum of `len` `u32` values (fixed per instance): `out[i] = Σ_{j<i} in[j]` for
/// `i ≤ len`, so `out[len]` is the total. Optionally only the first `min(len, counters[slot])`
/// inputs are read (the rest count as 0) and the total is copied into a counters slot.
pub struct GpuScan {
    len: usize,
    block: Kernel,
    inplace: Kernel,
    add: Kernel,
    /// Level-0 uniforms: fixed length, then dynamic with slot 0..SCAN_SLOTS.
    level0: Vec<wgpu::Buffer>,
    /// Levels ≥ 1: (values at this level, uniform, buffer holding them).
    levels: Vec<(usize, wgpu::Buffer, wgpu::Buffer)>,
    /// Bound where a binding is unused (one for read-write, one for read-only slots).
    dummy: wgpu::Buffer,
    dummy_ro: wgpu::Buffer,
}

impl GpuScan {
    /// Prepares the scan of `len` values (any length up to 2³⁰; 0 gives `out = [0]`).
    pub fn new(ctx: &GpuContext, len: usize) -> Self {
        assert!(len < 1 << 30, "scan length {len} too large");
        let module = ctx.shader_module("scan.wgsl", &shaders::with_common(shaders::SCAN));
        let block = Kernel::from_module(ctx, &module, "scan_block", &[]);
        let inplace = Kernel::from_module(ctx, &module, "scan_inplace", &[]);
        let add = Kernel::from_module(ctx, &module, "scan_add", &[]);
        let n0 = len + 1;
        let mut sizes = vec![n0];
        while *sizes.last().unwrap() > SCAN_BLOCK {
            sizes.push(sizes.last().unwrap().div_ceil(SCAN_BLOCK));
        }
        let p0 = |dynamic: bool, slot: usize| ScanParams {
            n: n0 as u32,
            n_input: len as u32,
            dynamic_n: dynamic as u32,
            has_sums: (sizes.len() > 1) as u32,
            slot: slot as u32,
            _pad: [0; 3],
        };
        let mut level0 = vec![ctx.uniform("scan_params", &p0(false, 0))];
        level0.extend((0..SCAN_SLOTS).map(|s| ctx.uniform("scan_params", &p0(true, s))));
        let levels = (1..sizes.len())
            .map(|l| {
                let n = sizes[l];
                let p = ScanParams {
                    n: n as u32,
                    n_input: n as u32,
                    dynamic_n: 0,
                    has_sums: (l + 1 < sizes.len()) as u32,
                    slot: 0,
                    _pad: [0; 3],
                };
                (n, ctx.uniform("scan_params", &p), ctx.zeros("scan_sums", 4 * n))
            })
            .collect();
        Self { len, block, inplace, add, level0, levels, dummy: ctx.zeros("scan_dummy", 4), dummy_ro: ctx.zeros("scan_dummy_ro", 4) }
    }

    /// The number of values scanned.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the scan is over no values.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Records the scan of `input` (≥ `len` values) into `output` (≥ `len + 1` values).
    /// `count = Some((counters, slot))` reads only `min(len, counters[slot])` inputs (`slot < 4`);
    /// `total = Some((counters, slot))` also copies the total into `counters[slot]`.
    pub fn record(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        input: &wgpu::Buffer,
        output: &wgpu::Buffer,
        count: Option<(&wgpu::Buffer, usize)>,
        total: Option<(&wgpu::Buffer, usize)>,
    ) {
        let (params0, counters) = match count {
            None => (&self.level0[0], &self.dummy_ro),
            Some((c, slot)) => {
                assert!(slot < SCAN_SLOTS, "scan count slot {slot} out of range");
                (&self.level0[1 + slot], c)
            }
        };
        let sums1 = self.levels.first().map(|l| &l.2).unwrap_or(&self.dummy);
        let groups = |n: usize| groups_1d(n.div_ceil(SCAN_BLOCK), 1);
        self.block.record(ctx, enc, &[(0, params0), (1, input), (2, output), (3, sums1), (4, counters)], groups(self.len + 1));
        for (l, (n, p, data)) in self.levels.iter().enumerate() {
            let sums = self.levels.get(l + 1).map(|x| &x.2).unwrap_or(&self.dummy);
            self.inplace.record(ctx, enc, &[(0, p), (3, sums), (5, data)], groups(*n));
        }
        for l in (0..self.levels.len()).rev() {
            // Add the scanned sums of level l + 1 (self.levels[l]) into level l.
            let sums = &self.levels[l].2;
            let (n, p, data) = if l == 0 {
                (self.len + 1, params0, output)
            } else {
                let x = &self.levels[l - 1];
                (x.0, &x.1, &x.2)
            };
            self.add.record(ctx, enc, &[(0, p), (3, sums), (5, data)], groups_1d(n, SCAN_WG));
        }
        if let Some((c, slot)) = total {
            enc.copy_buffer_to_buffer(output, 4 * self.len as u64, c, 4 * slot as u64, Some(4));
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Marching

/// Geometry and limits of [`GpuMarcher`] (those of the CPU's `OccupancyGrid` and `march`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MarchConfig {
    /// Grid box lower corner.
    pub aabb_min: [f32; 3],
    /// Grid box upper corner.
    pub aabb_max: [f32; 3],
    /// Cells per axis (of every level).
    pub resolution: u32,
    /// Levels of the occupancy grid's cascade (`nerf_sampling::OccupancyGridConfig::cascades`;
    /// 1: one grid over the box).
    pub cascades: u32,
    /// Marching step along unit rays.
    pub step_size: f32,
    /// Near distance (one value for every ray, as the trainer passes).
    pub near: f32,
    /// Far distance.
    pub far: f32,
    /// Most samples per ray.
    pub max_samples_per_ray: u32,
    /// instant-ngp's cone steps (`nerf_sampling::Stepping`; 0: constant steps of `step_size`).
    pub cone_angle: f32,
}

/// Byte offset of `step` in [`MarchParams`].
const MARCH_STEP_OFFSET: u64 = std::mem::offset_of!(MarchParams, step) as u64;
/// Byte offset of `max_samples` in [`MarchParams`].
const MARCH_MAX_SAMPLES_OFFSET: u64 = std::mem::offset_of!(MarchParams, max_samples) as u64;
/// Byte offset of the crop box's rows in [`MarchParams`].
const MARCH_CROP_OFFSET: u64 = std::mem::offset_of!(MarchParams, crop) as u64;
/// Byte offset of `seed` (followed by `jitter`) in [`MarchParams`].
const MARCH_SEED_OFFSET: u64 = std::mem::offset_of!(MarchParams, seed) as u64;

/// Packed samples on the device (the CSR layout of `nerf_sampling::RaySamples`).
pub struct GpuSamples {
    /// `[capacity_rays + 1]` u32: ray `r` owns samples `offsets[r]..offsets[r+1]`.
    pub offsets: wgpu::Buffer,
    /// `[capacity_samples][3]` f32: `o + t·d`.
    pub positions: wgpu::Buffer,
    /// `[capacity_samples][3]` f32: the ray's unit direction.
    pub dirs: wgpu::Buffer,
    /// `[capacity_samples]` f32 distances along the ray.
    pub t: wgpu::Buffer,
    /// `[capacity_samples]` f32 interval lengths (the step size for marched samples).
    pub dt: wgpu::Buffer,
    /// Rays the offsets can describe.
    pub capacity_rays: usize,
    /// Samples the buffers hold.
    pub capacity_samples: usize,
}

impl GpuSamples {
    /// Zeroed buffers.
    pub fn new(ctx: &GpuContext, capacity_rays: usize, capacity_samples: usize) -> Self {
        Self {
            offsets: ctx.zeros("sample_offsets", 4 * (capacity_rays + 1)),
            positions: ctx.zeros("sample_positions", 12 * capacity_samples),
            dirs: ctx.zeros("sample_dirs", 12 * capacity_samples),
            t: ctx.zeros("sample_t", 4 * capacity_samples),
            dt: ctx.zeros("sample_dt", 4 * capacity_samples),
            capacity_rays,
            capacity_samples,
        }
    }
}

/// Occupancy-grid marching on the device (`shaders/march.wgsl`), the twin of
/// [`nerf_sampling::march`]: same sample positions `t_k = t_start + (k + u)·step` (or cone steps)
/// kept where the cell of `o + t_k·d` (in the finest level of the cascade that holds it) is
/// occupied, at most `max_samples_per_ray` per ray, `dt` the step at the sample.
///
/// Capacity: when the rays' samples exceed `capacity_samples`, the offsets are clamped to it
/// (`offsets[r] = min(Σ_{j<r} count_j, capacity)`): the ray that straddles the capacity keeps
/// its first samples and every later ray gets none; `counters[COUNTER_N_SAMPLES]` receives
/// `min(total, capacity)`. Rays past `counters[COUNTER_N_RAYS]` (up to `capacity_rays`) get
/// `offsets[r] = ` that clamped total.
pub struct GpuMarcher {
    cfg: MarchConfig,
    capacity_rays: usize,
    capacity_samples: usize,
    params: wgpu::Buffer,
    coarse_kernel: Kernel,
    count_kernel: Kernel,
    fill_kernel: Kernel,
    scan: GpuScan,
    coarse: wgpu::Buffer,
    n_blocks: usize,
    counts: wgpu::Buffer,
    raw_offsets: wgpu::Buffer,
    /// Rendering in rounds (`round_*` of march.wgsl).
    rounds: RoundKernels,
}

struct RoundKernels {
    init: Kernel,
    begin: Kernel,
    count: Kernel,
    fill: Kernel,
    composite: Kernel,
    tail: Kernel,
    end: Kernel,
    output: Kernel,
}

/// Storage buffers the kernels bind at once (round_fill).
const MARCH_STORAGE_BINDINGS: u32 = 12;

impl GpuMarcher {
    /// Compiles the kernels and allocates the scratch for `capacity_rays` rays and
    /// `capacity_samples` samples. Errors on an invalid configuration (box, resolution in
    /// `1..=1024`, step, `far > near`), or an adapter with fewer than 11 storage buffers per stage.
    pub fn new(ctx: &GpuContext, cfg: MarchConfig, capacity_rays: usize, capacity_samples: usize) -> Result<Self, GpuError> {
        let bad = |m: String| Err(GpuError::Unsupported(format!("march config: {m}")));
        for a in 0..3 {
            if !(cfg.aabb_min[a].is_finite() && cfg.aabb_max[a].is_finite() && cfg.aabb_max[a] > cfg.aabb_min[a]) {
                return bad(format!("the box must be finite with max > min, got {:?}..{:?}", cfg.aabb_min, cfg.aabb_max));
            }
        }
        if cfg.resolution == 0 || cfg.resolution > nerf_sampling::MAX_RESOLUTION {
            return bad(format!("resolution must be in 1..={}, got {}", nerf_sampling::MAX_RESOLUTION, cfg.resolution));
        }
        if cfg.cascades == 0 || cfg.cascades > nerf_sampling::MAX_CASCADES || (cfg.cascades > 1 && !cfg.resolution.is_multiple_of(16)) {
            return bad(format!(
                "cascades must be in 1..={} (more than one with a resolution divisible by 16), got {} at {}",
                nerf_sampling::MAX_CASCADES,
                cfg.cascades,
                cfg.resolution
            ));
        }
        if !(cfg.cone_angle.is_finite() && cfg.cone_angle >= 0.0) {
            return bad(format!("cone angle must be finite and not negative, got {}", cfg.cone_angle));
        }
        if !(cfg.step_size.is_finite() && cfg.step_size > 0.0) {
            return bad(format!("step size must be positive, got {}", cfg.step_size));
        }
        if !(cfg.near.is_finite() && cfg.far.is_finite()) {
            return bad(format!("near/far must be finite, got {}/{}", cfg.near, cfg.far));
        }
        if capacity_rays >= 1 << 30 || capacity_samples >= u32::MAX as usize {
            return bad(format!("capacities too large ({capacity_rays} rays, {capacity_samples} samples)"));
        }
        let have = ctx.device.limits().max_storage_buffers_per_shader_stage;
        if have < MARCH_STORAGE_BINDINGS {
            return Err(GpuError::Unsupported(format!(
                "marching binds {MARCH_STORAGE_BINDINGS} storage buffers per stage, the adapter allows {have}"
            )));
        }
        let res = cfg.resolution;
        let cres = res.div_ceil(CBLOCK);
        let module = ctx.shader_module("march.wgsl", &shaders::with_common(shaders::MARCH));
        let cell: [f32; 3] = std::array::from_fn(|a| (cfg.aabb_max[a] - cfg.aabb_min[a]) / res as f32);
        let inv_cell: [f32; 3] = std::array::from_fn(|a| res as f32 / (cfg.aabb_max[a] - cfg.aabb_min[a]));
        // The levels exactly as the CPU grid's (nerf_sampling::cascade_box); the margin of a level
        // is 10⁻² of its cell, and at least 10⁻³ of the outermost cell (rounding grows with the
        // coordinates, which the outermost level bounds).
        let n_levels = cfg.cascades as usize;
        let min3 = |v: [f32; 3]| v[0].min(v[1]).min(v[2]);
        let mut lv = [[[0f32; 4]; 8]; 4];
        for m in 0..n_levels {
            let (lo, hi) = nerf_sampling::cascade_box(cfg.aabb_min, cfg.aabb_max, n_levels, m);
            let c: [f32; 3] = std::array::from_fn(|a| (hi[a] - lo[a]) / res as f32);
            let inv: [f32; 3] = std::array::from_fn(|a| res as f32 / (hi[a] - lo[a]));
            let margin = (1e-2 * min3(c)).max(1e-3 * min3(cell));
            lv[0][m] = [lo[0], lo[1], lo[2], margin];
            lv[1][m] = [hi[0], hi[1], hi[2], 0.0];
            lv[2][m] = [c[0], c[1], c[2], 0.0];
            lv[3][m] = [inv[0], inv[1], inv[2], 0.0];
        }
        let params = MarchParams {
            aabb_min: cfg.aabb_min,
            step: cfg.step_size,
            aabb_max: cfg.aabb_max,
            near: cfg.near,
            cell,
            far: cfg.far,
            inv_cell,
            margin: 1e-2 * cell[0].min(cell[1]).min(cell[2]),
            res,
            cres,
            max_samples: cfg.max_samples_per_ray,
            cap_rays: capacity_rays as u32,
            cap_samples: capacity_samples as u32,
            seed: 0,
            jitter: 0,
            cone_angle: cfg.cone_angle,
            n_levels: n_levels as u32,
            level_cells: res * res * res,
            _pad: [0; 2],
            lv_lo: lv[0],
            lv_hi: lv[1],
            lv_cell: lv[2],
            lv_inv: lv[3],
            crop: [[0.0; 4]; 4],
        };
        let n_blocks = n_levels * (cres as usize).pow(3);
        Ok(Self {
            cfg,
            capacity_rays,
            capacity_samples,
            params: ctx.uniform("march_params", &params),
            coarse_kernel: Kernel::from_module(ctx, &module, "march_coarse", &[]),
            count_kernel: Kernel::from_module(ctx, &module, "march_count", &[]),
            fill_kernel: Kernel::from_module(ctx, &module, "march_fill", &[]),
            scan: GpuScan::new(ctx, capacity_rays),
            coarse: ctx.zeros("march_coarse", 4 * n_blocks.div_ceil(32)),
            n_blocks,
            counts: ctx.zeros("march_counts", 4 * capacity_rays),
            raw_offsets: ctx.zeros("march_raw_offsets", 4 * (capacity_rays + 1)),
            rounds: RoundKernels {
                init: Kernel::from_module(ctx, &module, "round_init", &[]),
                begin: Kernel::from_module(ctx, &module, "round_begin", &[]),
                count: Kernel::from_module(ctx, &module, "round_count", &[]),
                fill: Kernel::from_module(ctx, &module, "round_fill", &[]),
                composite: Kernel::from_module(ctx, &module, "round_composite", &[]),
                tail: Kernel::from_module(ctx, &module, "round_tail", &[]),
                end: Kernel::from_module(ctx, &module, "round_end", &[]),
                output: Kernel::from_module(ctx, &module, "round_output", &[]),
            },
        })
    }

    /// The configuration (step size as last set).
    pub fn config(&self) -> &MarchConfig {
        &self.cfg
    }

    /// Rays the marcher is sized for.
    pub fn capacity_rays(&self) -> usize {
        self.capacity_rays
    }

    /// Samples the marcher is sized for.
    pub fn capacity_samples(&self) -> usize {
        self.capacity_samples
    }

    /// Queues the per-step seed and whether `u` is jittered (`rand_f32(seed, MARCH_STREAM_U, r)`)
    /// or 0.5 (call before submitting the step).
    pub fn set_seed(&self, ctx: &GpuContext, seed: u32, jitter: bool) {
        ctx.write(&self.params, MARCH_SEED_OFFSET, &[seed, jitter as u32]);
    }

    /// Queues a new step size (the CPU sampler keeps it fixed; provided for schedules).
    ///
    /// # Panics
    /// If `step` is not positive and finite.
    pub fn set_step_size(&mut self, ctx: &GpuContext, step: f32) {
        assert!(step > 0.0 && step.is_finite(), "step size must be positive");
        self.cfg.step_size = step;
        ctx.write(&self.params, MARCH_STEP_OFFSET, &[step]);
    }

    /// Queues a step and a sample cap per ray for the submissions that follow, leaving
    /// [`config`](Self::config) as it is: a render at another step than training's (finer steps
    /// need a larger cap for rays to reach as far). [`restore_stepping`](Self::restore_stepping)
    /// queues the configured ones back. No buffer depends on either, so any values fit.
    ///
    /// # Panics
    /// If `step` is not positive and finite or `max_samples` is 0.
    pub fn queue_stepping(&self, ctx: &GpuContext, step: f32, max_samples: u32) {
        assert!(step > 0.0 && step.is_finite() && max_samples > 0, "step size must be positive, and the sample cap too");
        ctx.write(&self.params, MARCH_STEP_OFFSET, &[step]);
        ctx.write(&self.params, MARCH_MAX_SAMPLES_OFFSET, &[max_samples]);
    }

    /// Queues a render crop box for the submissions that follow (`None`: none, as configured):
    /// every ray's `[t0, t1)` is also clipped to it, as the CPU's
    /// `nerf_sampling::RayMarch::cropped`. Queue `None` back before training marches again.
    pub fn queue_crop(&self, ctx: &GpuContext, crop: Option<&nerf_sampling::CropBox>) {
        ctx.write(&self.params, MARCH_CROP_OFFSET, &crate::layout::crop_rows(crop));
    }

    /// Queues the configured step and sample cap back after [`queue_stepping`](Self::queue_stepping).
    pub fn restore_stepping(&self, ctx: &GpuContext) {
        self.queue_stepping(ctx, self.cfg.step_size, self.cfg.max_samples_per_ray);
    }

    /// Records the whole marching (coarse bits, count, scan, fill) of `min(counters[0],
    /// capacity_rays)` rays (`origins`, `dirs`: `[R][3]`, unit directions) through `bitfield`
    /// (`⌈cascades·res³/32⌉` u32, bit `i % 32` of word `i / 32` = cell `i`) into `out` (sized at least
    /// for the marcher's capacities); writes `counters[COUNTER_N_SAMPLES]`.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        bitfield: &wgpu::Buffer,
        origins: &wgpu::Buffer,
        dirs: &wgpu::Buffer,
        out: &GpuSamples,
    ) {
        assert!(
            out.capacity_rays >= self.capacity_rays && out.capacity_samples >= self.capacity_samples,
            "output buffers smaller than the marcher's capacities"
        );
        self.record_coarse(ctx, enc, bitfield);
        let base: [(u32, &wgpu::Buffer); 10] = [
            (0, &self.params),
            (1, counters),
            (2, bitfield),
            (3, &self.coarse),
            (4, origins),
            (5, dirs),
            (9, &out.positions),
            (10, &out.dirs),
            (11, &out.t),
            (12, &out.dt),
        ];
        let mut b = base.to_vec();
        b.push((6, &self.counts));
        self.count_kernel.record(ctx, enc, &b, groups_1d(self.capacity_rays, WG));
        self.scan.record(ctx, enc, &self.counts, &self.raw_offsets, Some((counters, COUNTER_N_RAYS)), None);
        let mut b = base.to_vec();
        b.push((7, &self.raw_offsets));
        b.push((8, &out.offsets));
        self.fill_kernel.record(ctx, enc, &b, groups_1d(self.capacity_rays + 1, WG));
    }

    fn record_coarse(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, bitfield: &wgpu::Buffer) {
        enc.clear_buffer(&self.coarse, 0, None);
        self.coarse_kernel.record(ctx, enc, &[(0, &self.params), (2, bitfield), (13, &self.coarse)], groups_1d(self.n_blocks, WG));
    }

    // ---- rendering in rounds ----------------------------------------------------------------

    /// Bytes of per-ray state a [`RoundFrame`] holds (its largest per-ray buffer): a frame of
    /// `max_rays` rays needs a buffer and a storage binding of `max_rays` times this.
    pub const ROUND_BYTES_PER_RAY: usize = std::mem::size_of::<RoundRayState>();

    /// Buffers for rendering frames of up to `max_rays` rays in rounds of at most `cap_window`
    /// rays (clamped to `1..=capacity_samples`: a round evaluates at most `capacity_samples`
    /// samples, the size of the [`GpuSamples`] the rounds write).
    pub fn round_frame(&self, ctx: &GpuContext, max_rays: usize, cap_window: usize) -> RoundFrame {
        let max_rays = max_rays.max(1);
        let cap_window = cap_window.clamp(1, self.capacity_samples.max(1));
        RoundFrame {
            max_rays,
            cap_window,
            n_rays: std::cell::Cell::new(0),
            params: ctx.uniform("round params", &RoundParams::default()),
            rc: ctx.zeros("round counters", 4 * 8),
            state: ctx.zeros("round ray state", std::mem::size_of::<RoundRayState>() * max_rays),
            alive: [ctx.zeros("round alive a", 4 * max_rays), ctx.zeros("round alive b", 4 * max_rays)],
            counts: ctx.zeros("round counts", 4 * cap_window),
            raw: ctx.zeros("round offsets", 4 * (cap_window + 1)),
            scan: GpuScan::new(ctx, cap_window),
        }
    }

    /// Records the start of a frame set up with [`RoundFrame::set`]: the coarse occupancy bits,
    /// every ray alive with a fresh state.
    pub fn record_round_start(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, frame: &RoundFrame, bitfield: &wgpu::Buffer) {
        self.record_coarse(ctx, enc, bitfield);
        let n = frame.n_rays.get();
        self.rounds.init.record(
            ctx,
            enc,
            &[(14, &frame.params), (15, &frame.rc), (16, &frame.state), (25, &frame.alive[0])],
            groups_1d(n.max(1), WG),
        );
    }

    /// Records the marching half of round `round` (0, 1, … within the frame): the window of alive
    /// rays, each ray's next samples into `out` (positions, dirs, t, dt; the offsets stay in
    /// the frame), `counters[COUNTER_N_SAMPLES]` = the round's samples. The caller then evaluates
    /// the field on them (`sigma [n]`, `rgb [n][3]`) and records [`GpuMarcher::record_round_composite`].
    #[allow(clippy::too_many_arguments)]
    pub fn record_round_march(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        frame: &RoundFrame,
        round: usize,
        counters: &wgpu::Buffer,
        bitfield: &wgpu::Buffer,
        origins: &wgpu::Buffer,
        dirs: &wgpu::Buffer,
        out: &GpuSamples,
    ) {
        assert!(out.capacity_samples >= self.capacity_samples, "output buffers smaller than the marcher's capacity");
        let alive = &frame.alive[round % 2];
        let k = &self.rounds;
        k.begin.record(ctx, enc, &[(0, &self.params), (1, counters), (14, &frame.params), (15, &frame.rc)], [1, 1, 1]);
        let base: [(u32, &wgpu::Buffer); 12] = [
            (0, &self.params),
            (2, bitfield),
            (3, &self.coarse),
            (4, origins),
            (5, dirs),
            (15, &frame.rc),
            (16, &frame.state),
            (17, alive),
            (9, &out.positions),
            (10, &out.dirs),
            (11, &out.t),
            (12, &out.dt),
        ];
        let groups = groups_1d(frame.cap_window, WG);
        let mut b = base.to_vec();
        b.push((6, &frame.counts));
        k.count.record(ctx, enc, &b, groups);
        frame.scan.record(ctx, enc, &frame.counts, &frame.raw, Some((&frame.rc, 1)), Some((counters, 1)));
        let mut b = base.to_vec();
        b.push((7, &frame.raw));
        k.fill.record(ctx, enc, &b, groups);
    }

    /// Records the compositing half of round `round`: accumulates the window rays' samples
    /// (`sigma`, `rgb` of the field on `out`) into their state and compacts the alive list.
    #[allow(clippy::too_many_arguments)]
    pub fn record_round_composite(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        frame: &RoundFrame,
        round: usize,
        counters: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
        out: &GpuSamples,
    ) {
        let (alive, next) = (&frame.alive[round % 2], &frame.alive[(round + 1) % 2]);
        let k = &self.rounds;
        k.composite.record(
            ctx,
            enc,
            &[
                (14, &frame.params),
                (15, &frame.rc),
                (16, &frame.state),
                (17, alive),
                (18, next),
                (7, &frame.raw),
                (19, sigma),
                (20, rgb),
                (11, &out.t),
                (12, &out.dt),
            ],
            groups_1d(frame.cap_window, WG),
        );
        let n = frame.n_rays.get().max(1);
        k.tail.record(ctx, enc, &[(15, &frame.rc), (17, alive), (18, next)], groups_1d(n, WG));
        k.end.record(ctx, enc, &[(1, counters), (15, &frame.rc)], [1, 1, 1]);
    }

    /// Records the frame's outputs from the ray states: `rgb [n][3]` (+ `(1 − opacity)·background`
    /// when the frame has one; `background [n][3]`), `opacity [n]`, `depth [n]`.
    #[allow(clippy::too_many_arguments)]
    pub fn record_round_output(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        frame: &RoundFrame,
        background: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
        opacity: &wgpu::Buffer,
        depth: &wgpu::Buffer,
    ) {
        let n = frame.n_rays.get().max(1);
        self.rounds.output.record(
            ctx,
            enc,
            &[(14, &frame.params), (16, &frame.state), (21, background), (22, rgb), (23, opacity), (24, depth)],
            groups_1d(n, WG),
        );
    }
}

/// Frame buffers of rendering in rounds ([`GpuMarcher::round_frame`]): per-ray state, the alive
/// lists (ping-pong), the round counters and one round's offsets.
pub struct RoundFrame {
    max_rays: usize,
    cap_window: usize,
    n_rays: std::cell::Cell<usize>,
    params: wgpu::Buffer,
    /// `[alive, window, steps, appended, evaluated]` u32.
    rc: wgpu::Buffer,
    state: wgpu::Buffer,
    alive: [wgpu::Buffer; 2],
    counts: wgpu::Buffer,
    raw: wgpu::Buffer,
    scan: GpuScan,
}

impl RoundFrame {
    /// Most rays of a frame.
    pub fn max_rays(&self) -> usize {
        self.max_rays
    }

    /// Most rays per round.
    pub fn cap_window(&self) -> usize {
        self.cap_window
    }

    /// Queues the frame's parameters (before the submission that records
    /// [`GpuMarcher::record_round_start`]): `n_rays ≤ max_rays` rays; a ray stops once its
    /// transmittance is below `t_threshold` (0: never); at most `kmax ≥ 1` steps per ray and
    /// round; whether the output composites a background.
    ///
    /// # Panics
    /// If `n_rays > max_rays` or `kmax == 0`.
    pub fn set(&self, ctx: &GpuContext, n_rays: usize, t_threshold: f32, kmax: u32, has_background: bool) {
        assert!(n_rays <= self.max_rays, "frame of {n_rays} rays exceeds the {} it was sized for", self.max_rays);
        assert!(kmax >= 1, "kmax must be at least 1");
        self.n_rays.set(n_rays);
        let p = RoundParams {
            n_frame: n_rays as u32,
            cap_window: self.cap_window as u32,
            kmax,
            has_background: has_background as u32,
            t_threshold,
            _pad: [0; 3],
        };
        ctx.write(&self.params, 0, &[p]);
    }

    /// Reads back `(rays still alive, samples evaluated so far in this frame)` (waits for the
    /// device).
    pub fn status(&self, ctx: &GpuContext) -> Result<(usize, u64), GpuError> {
        let v = ctx.read_u32(&self.rc, 5)?;
        Ok((v[0] as usize, v[4] as u64))
    }
}
