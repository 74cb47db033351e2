//! nerf-rs: neural radiance fields in Rust.
//!
//! This facade re-exports the workspace's crates under short names and owns the **field
//! registry** — the one place that lists the field kinds a program can build by name. Everything
//! else (sampling, compositing, the trainer, the CLI) drives fields only through
//! [`field::RadianceField`].
//!
//! | module | crate | what |
//! |---|---|---|
//! | [`core`] | nerf-core | `Real` scalar trait, seeded RNG |
//! | [`rays`] | nerf-rays | cameras, rays, AABB |
//! | [`data`] | nerf-data | Blender datasets, ray batches, PNG |
//! | [`sampling`] | nerf-sampling | packed samples: stratified, hierarchical, occupancy-grid marching |
//! | [`render`] | nerf-render | compositing forward/backward, loss |
//! | [`mesh`] | nerf-mesh | density lattice and isosurface mesh of a trained field |
//! | [`metrics`] | nerf-metrics | PSNR, SSIM |
//! | [`encoding`] | nerf-encoding | frequency, hash-grid and spherical-harmonics encodings |
//! | [`mlp`] | nerf-mlp | MLPs with backward (GEMM) |
//! | [`optim`] | nerf-optim | Adam, learning-rate schedules |
//! | [`field`] | nerf-field | the `RadianceField` trait, registry types |
//! | [`field_freq`] | nerf-field-freq | the paper's NeRF field |
//! | [`field_hash`] | nerf-field-hash | the Instant-NGP hash-grid field |
//! | [`field_voxel`] | nerf-field-voxel | a DVGO-style dense voxel-grid field (the plug-in example) |
//! | [`ablate`] | nerf-ablate | the ablation runner |
//! | [`train`] | nerf-train | trainer, evaluation, checkpoints, runs |

pub use nerf_ablate as ablate;
pub use nerf_core as core;
pub use nerf_data as data;
pub use nerf_encoding as encoding;
pub use nerf_field as field;
pub use nerf_field_freq as field_freq;
pub use nerf_field_hash as field_hash;
pub use nerf_field_voxel as field_voxel;
pub use nerf_gpu as gpu;
pub use nerf_mesh as mesh;
pub use nerf_metrics as metrics;
pub use nerf_mlp as mlp;
pub use nerf_optim as optim;
pub use nerf_rays as rays;
pub use nerf_render as render;
pub use nerf_sampling as sampling;
pub use nerf_train as train;

use nerf_field::{Registry, RegistryEntry};

/// Every field kind nerf-rs ships, by name. A new field adds one entry here.
pub fn registry() -> Registry {
    let mut r = Registry::new();
    r.register(RegistryEntry {
        name: "freq",
        description: "the paper's NeRF: frequency encoding + 8x256 MLP, coarse and fine networks",
        default_config: nerf_field_freq::default_config,
        train_preset: || serde_json::Value::Null,
        build: nerf_field_freq::build,
    });
    r.register(RegistryEntry {
        name: "hash",
        description: "Instant-NGP: multiresolution hash grid + SH + tiny MLPs, occupancy-grid marching",
        default_config: nerf_field_hash::default_config,
        train_preset: nerf_field_hash::train_preset,
        build: nerf_field_hash::build,
    });
    r.register(nerf_field_voxel::registry_entry());
    r
}
