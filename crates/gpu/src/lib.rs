//! The wgpu execution path of nerf-rs (first slice): adapter selection with a clear error when
//! none exists, feature detection, and WGSL kernels from `shaders/` — each with a CPU twin in the
//! shared crates that tests check it against on random inputs (lavapipe in CI).
//!
//! Device choice: [`DevicePreference`] (`auto | cpu | gpu`), overridable with the `NERF_DEVICE`
//! environment variable. `cpu` never touches wgpu; `auto` falls back to the CPU path when no
//! adapter exists; `gpu` makes a missing adapter an error ([`GpuError::NoAdapter`]).

pub mod encoding;
pub mod kernel;
pub mod layout;
pub mod linear;
pub mod mlp;
pub mod occupancy;
pub mod pdf;
pub mod optim;
pub mod rng;
pub mod sampling;
pub mod shaders;

pub use kernel::{groups_1d, Kernel};

use std::str::FromStr;

/// Errors of the GPU path.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter was found (and the GPU was asked for).
    #[error("no GPU adapter found (backends tried: {backends}); install a Vulkan/Metal/DX12 driver (e.g. Mesa's lavapipe: apt-get install mesa-vulkan-drivers) or use --device cpu")]
    NoAdapter {
        /// Backends that were searched.
        backends: String,
    },
    /// The device could not be created.
    #[error("could not open the GPU device `{adapter}`: {message}")]
    Device {
        /// Adapter name.
        adapter: String,
        /// wgpu's message.
        message: String,
    },
    /// `NERF_DEVICE` or `--device` holds an unknown value.
    #[error("unknown device `{0}` (expected auto, cpu or gpu)")]
    BadPreference(String),
    /// A configuration the GPU kernels do not support (the message says which limit).
    #[error("not supported on the GPU path: {0}")]
    Unsupported(String),
    /// A buffer could not be read back.
    #[error("GPU read-back failed: {0}")]
    ReadBack(String),
}

/// Which execution path to use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DevicePreference {
    /// The GPU when an adapter exists, else the CPU.
    #[default]
    Auto,
    /// Always the CPU path.
    Cpu,
    /// The GPU; an error when there is no adapter.
    Gpu,
}

impl FromStr for DevicePreference {
    type Err = GpuError;
    fn from_str(s: &str) -> Result<Self, GpuError> {
        match s.trim().to_ascii_lowercase().as_str() {
            "auto" => Ok(Self::Auto),
            "cpu" => Ok(Self::Cpu),
            "gpu" => Ok(Self::Gpu),
            other => Err(GpuError::BadPreference(other.to_string())),
        }
    }
}

impl DevicePreference {
    /// `NERF_DEVICE` when set, else `self`.
    pub fn with_env_override(self) -> Result<Self, GpuError> {
        match std::env::var("NERF_DEVICE") {
            Ok(v) if !v.trim().is_empty() => v.parse(),
            _ => Ok(self),
        }
    }
}

/// What the adapter offers that the kernels can use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GpuFeatures {
    /// `enable f16;` in WGSL.
    pub shader_f16: bool,
    /// `atomic<f32>` with `atomicAdd` (scatter-add of hash-table gradients).
    pub float32_atomics: bool,
    /// Subgroup builtins.
    pub subgroups: bool,
    /// Cooperative matrices (tensor cores from WGSL; experimental in wgpu 30).
    pub cooperative_matrix: bool,
}

/// An opened device with its queue and what it supports. Pipelines and buffers are built once
/// per run from it.
pub struct GpuContext {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// Adapter name, backend, type, driver.
    pub info: wgpu::AdapterInfo,
    /// Detected features (those requested from the device).
    pub features: GpuFeatures,
}

impl GpuContext {
    /// Opens the best adapter (high performance first), or `Ok(None)` for `Cpu`, or for `Auto`
    /// when no adapter exists.
    pub fn open(pref: DevicePreference) -> Result<Option<Self>, GpuError> {
        let pref = pref.with_env_override()?;
        if pref == DevicePreference::Cpu {
            return Ok(None);
        }
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            apply_limit_buckets: false,
        }));
        let adapter = match adapter {
            Ok(a) => a,
            Err(_) if pref == DevicePreference::Auto => return Ok(None),
            Err(_) => return Err(GpuError::NoAdapter { backends: "vulkan, metal, dx12".into() }),
        };
        let info = adapter.get_info();
        let have = adapter.features();
        let mut want = wgpu::Features::empty();
        let mut features = GpuFeatures::default();
        for (flag, slot) in [
            (wgpu::Features::SHADER_F16, &mut features.shader_f16),
            (wgpu::Features::SHADER_FLOAT32_ATOMIC, &mut features.float32_atomics),
            (wgpu::Features::SUBGROUP, &mut features.subgroups),
        ] {
            if have.contains(flag) {
                want |= flag;
                *slot = true;
            }
        }
        features.cooperative_matrix = have.contains(wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX)
            && std::env::var_os("NERF_NO_COOP").is_none();
        if features.cooperative_matrix {
            want |= wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX;
        }
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("nerf"),
            required_features: want,
            required_limits: adapter.limits(),
            // SAFETY: experimental features are only enabled to use cooperative matrices, whose
            // kernels are validated against the plain-WGSL path in the tests (docs/gpu.md).
            experimental_features: if features.cooperative_matrix {
                unsafe { wgpu::ExperimentalFeatures::enabled() }
            } else {
                wgpu::ExperimentalFeatures::disabled()
            },
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| GpuError::Device { adapter: info.name.clone(), message: e.to_string() })?;
        Ok(Some(Self { device, queue, info, features }))
    }

    /// One line describing the adapter (recorded in metrics.json by the GPU path).
    pub fn describe(&self) -> String {
        format!("{} ({:?}, {:?}, {})", self.info.name, self.info.backend, self.info.device_type, self.info.driver)
    }

    fn storage(&self, label: &str, data: &[u8], writable: bool) -> wgpu::Buffer {
        use wgpu::util::DeviceExt;
        let mut usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        if writable {
            usage |= wgpu::BufferUsages::COPY_SRC;
        }
        // Storage bindings must not be empty.
        let data = if data.is_empty() { &[0u8; 4][..] } else { data };
        self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor { label: Some(label), contents: data, usage })
    }

    fn read_back(&self, src: &wgpu::Buffer, len_f32: usize) -> Result<Vec<f32>, GpuError> {
        let size = (4 * len_f32.max(1)) as u64;
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("staging"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("read") });
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, size);
        let idx = self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::Wait { submission_index: Some(idx), timeout: None })
            .map_err(|e| GpuError::ReadBack(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::ReadBack(e.to_string()))?
            .map_err(|e| GpuError::ReadBack(e.to_string()))?;
        let view = staging.get_mapped_range(..).map_err(|e| GpuError::ReadBack(format!("{e:?}")))?;
        let out: Vec<f32> = bytemuck::cast_slice(&view[..]).to_vec();
        drop(view);
        staging.unmap();
        Ok(out[..len_f32].to_vec())
    }
}

/// Outputs of [`Compositor::forward`], read back to the host.
#[derive(Clone, Debug, Default)]
pub struct CompositeOutputs {
    /// `3·n_rays`.
    pub rgb: Vec<f32>,
    /// `n_rays`.
    pub opacity: Vec<f32>,
    /// `n_rays`.
    pub depth: Vec<f32>,
    /// `n` samples.
    pub weights: Vec<f32>,
}

/// Gradients of [`Compositor::backward`], read back to the host.
#[derive(Clone, Debug, Default)]
pub struct CompositeGrads {
    /// dL/dσ per sample (`n`).
    pub d_sigma: Vec<f32>,
    /// dL/dc per sample (`3·n`).
    pub d_rgb: Vec<f32>,
}

/// The compositing kernels (`shaders/composite.wgsl`), pipelines built once.
pub struct Compositor {
    pipeline: wgpu::ComputePipeline,
    backward: wgpu::ComputePipeline,
}

impl Compositor {
    /// Builds the pipeline.
    pub fn new(ctx: &GpuContext) -> Self {
        let module = ctx.device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("composite.wgsl"),
            source: wgpu::ShaderSource::Wgsl(shaders::with_common(shaders::COMPOSITE).into()),
        });
        let make = |entry: &str| {
            ctx.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(entry),
                layout: None,
                module: &module,
                entry_point: Some(entry),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                cache: None,
            })
        };
        Self { pipeline: make("composite_forward"), backward: make("composite_backward") }
    }

    /// Gradients w.r.t. σ and the sample colours from the ray gradients, given the forward's
    /// `weights` (as [`Compositor::forward`] returns them).
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        ctx: &GpuContext,
        ray_offsets: &[u32],
        sigma: &[f32],
        rgb: &[f32],
        dt: &[f32],
        t: &[f32],
        background: Option<&[f32]>,
        t_threshold: f32,
        weights: &[f32],
        d_ray_rgb: &[f32],
        d_opacity: Option<&[f32]>,
        d_depth: Option<&[f32]>,
    ) -> Result<CompositeGrads, GpuError> {
        let n_rays = ray_offsets.len().saturating_sub(1);
        let n = sigma.len();
        let zeros = vec![0.0f32; n_rays];
        let b = |label, data: &[f32]| ctx.storage(label, bytemuck::cast_slice(data), false);
        let inputs = [
            b("sigma", sigma),
            b("rgb", rgb),
            b("dt", dt),
            b("t", t),
            b("background", background.unwrap_or(&[])),
            b("weights", weights),
            b("d_ray_rgb", d_ray_rgb),
            b("d_opacity", d_opacity.unwrap_or(&zeros)),
            b("d_depth", d_depth.unwrap_or(&zeros)),
        ];
        let poison = |len: usize| vec![f32::NAN; len.max(1)];
        let d_s = ctx.storage("d_sigma", bytemuck::cast_slice(&poison(n)), true);
        let d_c = ctx.storage("d_sample_rgb", bytemuck::cast_slice(&poison(3 * n)), true);
        let uniform = params_buffer(ctx, n_rays, t_threshold, background.is_some());
        let offsets = ctx.storage("offsets", bytemuck::cast_slice(ray_offsets), false);
        let [s, c, d, tt, bg, w, drgb, dop, ddep] = &inputs;
        let bound: [(u32, &wgpu::Buffer); 13] = [
            (0, &uniform), (1, &offsets), (2, s), (3, c), (4, d), (5, tt), (6, bg), (10, w),
            (11, drgb), (12, dop), (13, ddep), (14, &d_s), (15, &d_c),
        ];
        let entries: Vec<wgpu::BindGroupEntry<'_>> = bound
            .iter()
            .map(|(i, buf)| wgpu::BindGroupEntry { binding: *i, resource: buf.as_entire_binding() })
            .collect();
        dispatch(ctx, &self.backward, &entries, n_rays);
        Ok(CompositeGrads { d_sigma: ctx.read_back(&d_s, n)?, d_rgb: ctx.read_back(&d_c, 3 * n)? })
    }

    /// Composites packed samples on the device (host slices in, host vectors out: the testing and
    /// fallback entry point; a GPU training step keeps these buffers on the device).
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &self,
        ctx: &GpuContext,
        ray_offsets: &[u32],
        sigma: &[f32],
        rgb: &[f32],
        dt: &[f32],
        t: &[f32],
        background: Option<&[f32]>,
        t_threshold: f32,
    ) -> Result<CompositeOutputs, GpuError> {
        let n_rays = ray_offsets.len().saturating_sub(1);
        let n = sigma.len();
        let uniform = params_buffer(ctx, n_rays, t_threshold, background.is_some());
        let b = |label, data: &[f32]| ctx.storage(label, bytemuck::cast_slice(data), false);
        let offsets = ctx.storage("offsets", bytemuck::cast_slice(ray_offsets), false);
        let (s, c, d, tt) = (b("sigma", sigma), b("rgb", rgb), b("dt", dt), b("t", t));
        let bg = b("background", background.unwrap_or(&[]));
        // Outputs start poisoned (NaN) so a kernel that skips a slot cannot pass the tests.
        let poison = |len: usize| vec![f32::NAN; len.max(1)];
        let o_rgb = ctx.storage("out_rgb", bytemuck::cast_slice(&poison(3 * n_rays)), true);
        let o_op = ctx.storage("out_opacity", bytemuck::cast_slice(&poison(n_rays)), true);
        let o_depth = ctx.storage("out_depth", bytemuck::cast_slice(&poison(n_rays)), true);
        let o_w = ctx.storage("weights", bytemuck::cast_slice(&poison(n)), true);
        let entries: Vec<wgpu::BindGroupEntry<'_>> = [&uniform, &offsets, &s, &c, &d, &tt, &bg, &o_rgb, &o_op, &o_depth, &o_w]
            .iter()
            .enumerate()
            .map(|(i, buf)| wgpu::BindGroupEntry { binding: i as u32, resource: buf.as_entire_binding() })
            .collect();
        dispatch(ctx, &self.pipeline, &entries, n_rays);
        Ok(CompositeOutputs {
            rgb: ctx.read_back(&o_rgb, 3 * n_rays)?,
            opacity: ctx.read_back(&o_op, n_rays)?,
            depth: ctx.read_back(&o_depth, n_rays)?,
            weights: ctx.read_back(&o_w, n)?,
        })
    }
}

fn params_buffer(ctx: &GpuContext, n_rays: usize, t_threshold: f32, has_background: bool) -> wgpu::Buffer {
    use wgpu::util::DeviceExt;
    let params = layout::CompositeParams {
        n_rays: n_rays as u32,
        t_threshold,
        has_background: has_background as u32,
        _pad: 0,
    };
    ctx.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("params"),
        contents: bytemuck::bytes_of(&params),
        usage: wgpu::BufferUsages::UNIFORM,
    })
}

/// One dispatch of `pipeline` over `n_rays` invocations (workgroups of 64) with group 0 bound.
fn dispatch(ctx: &GpuContext, pipeline: &wgpu::ComputePipeline, entries: &[wgpu::BindGroupEntry<'_>], n_rays: usize) {
    let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout: &pipeline.get_bind_group_layout(0),
        entries,
    });
    let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None });
    {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: None, timestamp_writes: None });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.dispatch_workgroups((n_rays as u32).div_ceil(64).max(1), 1, 1);
    }
    ctx.queue.submit([enc.finish()]);
}
