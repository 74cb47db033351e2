//! The SPIR-V options under which wgpu's Vulkan backend translates a compute module (the step
//! where `linear_coop.wgsl` once failed on the H100), so tests can run that translation here.

use naga::back::spv;

/// wgpu 30's Vulkan options for a compute pipeline: SPIR-V 1.6, index/image bounds `Restrict`,
/// buffer bounds `buffer` (`Restrict` or `Unchecked`, depending on robustBufferAccess2), no
/// workgroup zero-initialisation (as `Kernel` asks), bounded loops, 16-bit storage I/O.
pub fn vulkan_options(buffer: naga::proc::BoundsCheckPolicy) -> spv::Options<'static> {
    spv::Options {
        lang_version: (1, 6),
        bounds_check_policies: naga::proc::BoundsCheckPolicies {
            index: naga::proc::BoundsCheckPolicy::Restrict,
            buffer,
            image_load: naga::proc::BoundsCheckPolicy::Restrict,
            binding_array: naga::proc::BoundsCheckPolicy::Unchecked,
        },
        zero_initialize_workgroup_memory: spv::ZeroInitializeWorkgroupMemoryMode::None,
        force_loop_bounding: true,
        use_storage_input_output_16: true,
        ..Default::default()
    }
}
