//! Host-side mirrors of the WGSL uniform structs: `#[repr(C)]` + `bytemuck::Pod`, in one place.

/// `Params` of `shaders/composite.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct CompositeParams {
    /// Number of rays (CSR offsets have `n_rays + 1` entries).
    pub n_rays: u32,
    /// Early-stop transmittance (0 disables).
    pub t_threshold: f32,
    /// 1 when a per-ray background is composited.
    pub has_background: u32,
    /// Padding to 16 bytes (uniform layout).
    pub _pad: u32,
}
/// Slot of the `counters` buffer holding the number of rays of the step.
pub const COUNTER_N_RAYS: usize = 0;
/// Slot of the `counters` buffer holding the number of packed samples of the step.
pub const COUNTER_N_SAMPLES: usize = 1;
