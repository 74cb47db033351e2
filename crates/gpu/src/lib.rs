//! The wgpu execution path of nerf-rs (first slice): adapter selection with a clear error when
//! none exists, feature detection, and WGSL kernels from `shaders/` — each with a CPU twin in the
//! shared crates that tests check it against on random inputs (lavapipe in CI).
//!
//! Device choice: [`DevicePreference`] (`auto | cpu | gpu`), overridable with the `NERF_DEVICE`
//! environment variable. `cpu` never touches wgpu; `auto` falls back to the CPU path when no
//! adapter exists; `gpu` makes a missing adapter an error ([`GpuError::NoAdapter`]).

pub mod color;
pub mod compact;
pub mod composite;
pub mod dispatch;
pub mod encoding;
pub mod glue;
pub mod kernel;
pub mod layout;
pub mod linear;
pub mod mlp;
pub mod mlp_coop;
pub mod occupancy;
pub mod pdf;
pub mod pose;
pub mod optim;
pub mod profile;
pub mod rng;
pub mod sampling;
pub mod shaders;
pub mod views;

pub use composite::{CompositeGrads, CompositeOutputs, Compositor, TrainGlue};
pub use dispatch::{DispatchArgs, Launch};
pub use kernel::{groups_1d, Bound, Kernel};

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
    /// `NERF_GPU_CHECKS` holds an unknown value.
    #[error("NERF_GPU_CHECKS=`{0}` is not understood (expected on or off; unset, the adapter decides)")]
    BadChecks(String),
    /// A configuration the GPU kernels do not support (the message says which limit).
    #[error("not supported on the GPU path: {0}")]
    Unsupported(String),
    /// A buffer whose size follows the samples per launch is larger than one storage binding may
    /// be on this adapter. Buffers sized per sample scale linearly with the capacity, so
    /// `limit / bytes` of it fits (the trainer fits its batch with it).
    #[error(
        "the `{label}` buffer needs {:.1} MiB, more than the {:.1} MiB one storage binding may hold on {adapter} \
         (lower target_samples_per_step or batch_rays)",
        *bytes as f64 / 1048576.0,
        *limit as f64 / 1048576.0
    )]
    CapacityTooLarge {
        /// The buffer.
        label: String,
        /// Bytes it needs.
        bytes: u64,
        /// The adapter's largest storage binding in bytes.
        limit: u64,
        /// Adapter name.
        adapter: String,
    },
    /// A buffer could not be read back.
    #[error("GPU read-back failed: {0}")]
    ReadBack(String),
}

/// Which execution path to use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DevicePreference {
    /// The GPU when an adapter exists, else the CPU. (The trainer's `auto` also skips software
    /// adapters such as lavapipe, which are slower than its CPU path.)
    #[default]
    Auto,
    /// Always the CPU path.
    Cpu,
    /// The GPU (any adapter, software ones included); an error when there is none.
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
    /// Timestamp queries around compute passes (the [`profile`] of a training step).
    pub timestamps: bool,
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
    /// Whether per-sample kernels are launched from device-written arguments
    /// ([`dispatch::DispatchArgs`]); off under `NERF_NO_INDIRECT` (for A/B timing).
    pub indirect_dispatch: bool,
    /// Whether the shader modules built from this context keep wgpu's runtime checks (index
    /// clamps on fixed-size arrays, loop counters). By default off on hardware adapters and on
    /// on software ones (lavapipe), where each is the faster (see [`GpuContext::shader_module`]);
    /// `NERF_GPU_CHECKS=on|off` overrides that. Set it before building the kernels it should
    /// apply to.
    pub shader_checks: bool,
    /// The pass timer of [`profile`] (made on first use).
    profiler: std::sync::Mutex<Option<profile::Recorder>>,
}

impl GpuContext {
    /// Opens the best adapter (high performance first), or `Ok(None)` for `Cpu`, or for `Auto`
    /// when no adapter exists.
    pub fn open(pref: DevicePreference) -> Result<Option<Self>, GpuError> {
        Self::open_with(pref.with_env_override()?)
    }

    /// As [`GpuContext::open`] without the `NERF_DEVICE` override.
    pub fn open_with(pref: DevicePreference) -> Result<Option<Self>, GpuError> {
        if pref == DevicePreference::Cpu {
            return Ok(None);
        }
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        // wgpu checks the arguments of every indirect dispatch with a dispatch of its own (and two
        // barriers) unless told not to; ours come from `shaders/dispatch.wgsl`, which keeps them
        // within the per-dimension limit (tested against its CPU twin). WGPU_VALIDATION_INDIRECT_CALL
        // turns the check back on.
        if std::env::var_os("WGPU_VALIDATION_INDIRECT_CALL").is_none() {
            desc.flags.remove(wgpu::InstanceFlags::VALIDATION_INDIRECT_CALL);
        }
        let instance = wgpu::Instance::new(desc);
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
            (wgpu::Features::TIMESTAMP_QUERY, &mut features.timestamps),
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
        let indirect_dispatch = std::env::var_os("NERF_NO_INDIRECT").is_none();
        let software = info.device_type == wgpu::DeviceType::Cpu;
        let shader_checks = shader_checks_from(std::env::var("NERF_GPU_CHECKS").ok().as_deref(), software)?;
        Ok(Some(Self { device, queue, info, features, indirect_dispatch, shader_checks, profiler: Default::default() }))
    }

    /// For tests and benches: any adapter (software ones such as lavapipe included, the
    /// `NERF_DEVICE` override ignored), or `None` with a NOTICE on stderr when there is none, so
    /// that a test can skip its GPU comparison. Panics when a device exists but cannot be opened.
    pub fn for_tests() -> Option<Self> {
        match Self::open_with(DevicePreference::Gpu) {
            Ok(Some(c)) => {
                eprintln!("GPU tests on {}", c.describe());
                Some(c)
            }
            Ok(None) | Err(GpuError::NoAdapter { .. }) => {
                eprintln!("NOTICE: no GPU adapter (install mesa-vulkan-drivers for lavapipe); skipping the GPU comparison");
                None
            }
            Err(e) => panic!("{e}"),
        }
    }

    /// The device's `min_storage_buffer_offset_alignment`: a [`Bound`] binding's offset must be
    /// a multiple of it.
    pub fn storage_offset_alignment(&self) -> u64 {
        self.device.limits().min_storage_buffer_offset_alignment as u64
    }

    /// Whether the adapter is a software rasteriser running on the CPU (lavapipe, WARP, …).
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Compiles one WGSL file (every kernel is built through here).
    ///
    /// With [`GpuContext::shader_checks`] off, the module is built without the checks that naga
    /// otherwise adds to the SPIR-V it hands the driver: a clamp on every index into a fixed-size
    /// array (the workgroup tiles of the fused MLPs and GEMMs, read and written in their innermost
    /// loops) and an iteration counter on every loop. Divisions keep their guard, and storage
    /// buffers stay bounds-checked by the driver's robust buffer access, which wgpu enables
    /// wherever the adapter offers it. Whether this is faster depends on the driver's compiler.
    /// On the H100 both fields train 14–16 % more samples per second without the checks; on
    /// lavapipe the fused MLPs gain ~5 % but the plain GEMM loses ~40 % (docs/results.md). Hence
    /// the default: off on hardware, on on software adapters. `tests/gpu_train.rs` checks that
    /// turning them off changes no rendered value and trains the same.
    pub fn shader_module(&self, label: &str, source: &str) -> wgpu::ShaderModule {
        let desc = wgpu::ShaderModuleDescriptor { label: Some(label), source: wgpu::ShaderSource::Wgsl(source.into()) };
        if self.shader_checks {
            return self.device.create_shader_module(desc);
        }
        let checks = wgpu::ShaderRuntimeChecks {
            bounds_checks: false,
            force_loop_bounding: false,
            // Kept: a guarded division by a runtime value costs one select, none sits in a hot
            // loop, and a zero divisor from a bad parameter stays defined.
            int_div_checks: true,
            ..wgpu::ShaderRuntimeChecks::checked()
        };
        // SAFETY: the kernels index their fixed-size arrays within bounds (each is tested against
        // its CPU twin on random inputs; rendering and training with the checks off are compared
        // with the checks on), every loop is bounded by its parameters, and buffer accesses stay
        // checked by the driver's robust buffer access.
        unsafe { self.device.create_shader_module_trusted(desc, checks) }
    }

    /// One line describing the adapter (recorded in metrics.json by the GPU path), with
    /// "shader checks off" when the kernels are built without wgpu's runtime checks.
    pub fn describe(&self) -> String {
        let checks = if self.shader_checks { "" } else { ", shader checks off" };
        format!("{} ({:?}, {:?}, {}{checks})", self.info.name, self.info.backend, self.info.device_type, self.info.driver)
    }
}

/// wgpu's shader runtime checks from `NERF_GPU_CHECKS`: `on`, `1`, `true` or `yes` keep them,
/// `off`, `0`, `false` or `no` drop them (any case); unset or empty, they are kept only on a
/// `software` adapter (the faster choice on each, measured on lavapipe and the H100).
fn shader_checks_from(value: Option<&str>, software: bool) -> Result<bool, GpuError> {
    match value.map(|v| v.trim().to_ascii_lowercase()).as_deref() {
        None | Some("") => Ok(software),
        Some("on" | "1" | "true" | "yes") => Ok(true),
        Some("off" | "0" | "false" | "no") => Ok(false),
        Some(_) => Err(GpuError::BadChecks(value.unwrap_or_default().to_string())),
    }
}

/// The wgpu version the kernels are written against, re-exported so fields and the trainer name
/// the same types.
pub use wgpu;

#[cfg(test)]
mod tests {
    #[test]
    fn shader_checks_follow_the_adapter_unless_set() {
        use super::shader_checks_from as f;
        for software in [false, true] {
            // Unset or empty: the adapter's default (on only for software adapters).
            assert_eq!(f(None, software).unwrap(), software);
            assert_eq!(f(Some(" "), software).unwrap(), software);
            for on in ["on", "1", "TRUE", " yes "] {
                assert!(f(Some(on), software).unwrap(), "{on}");
            }
            for off in ["off", " OFF ", "0", "false", "no"] {
                assert!(!f(Some(off), software).unwrap(), "{off}");
            }
            let e = f(Some("maybe"), software).unwrap_err().to_string();
            assert!(e.contains("NERF_GPU_CHECKS") && e.contains("maybe"), "{e}");
        }
    }
}
