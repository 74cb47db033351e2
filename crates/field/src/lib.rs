//! The `RadianceField` trait: the one seam between a scene representation (a "field") and the rest
//! of nerf-rs.
//!
//! Samplers, compositing, the trainer, the renderer, the benchmarks and the CLI only ever talk to a
//! `dyn RadianceField`. A field maps packed samples (flat `3·n` position and unit-direction arrays,
//! see `nerf-sampling`'s `RaySamples`) to a density `σ ≥ 0` and an `rgb ∈ [0,1]³` per sample,
//! keeps what its backward pass needs, and exposes its parameters as named flat `f32` groups for the
//! optimiser and for checkpoints. Fields are built by name through a [`Registry`] from a serde
//! (JSON/TOML) config, so an ablation is a config file rather than a code change.
//!
//! Adding a field = implementing this trait in its own crate and adding one [`RegistryEntry`] in the
//! facade crate (`nerf::registry()`); nothing in the shared crates changes.

use serde::{Deserialize, Serialize};

pub mod gpu;
pub use gpu::{ChunkedDensity, GpuParamGroup, GpuRadianceField, GpuSamples};
pub use nerf_gpu::{GpuContext, GpuError};
pub use nerf_optim::ParamGroupMut;

/// Scene information a field may need when it is built: the region it must represent and the seed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldContext {
    /// Axis-aligned box containing the scene (world units). Grid-based fields normalise positions
    /// with it; the paper's MLP ignores it.
    pub aabb_min: [f32; 3],
    /// Upper corner of the scene box.
    pub aabb_max: [f32; 3],
    /// Seed for parameter initialisation.
    pub seed: u64,
    /// How large the box is against the scene's own unit: instant-ngp's `aabb_scale` for an
    /// instant-ngp scene (a box of `aabb_scale` unit cubes per side), 1 for any other. A grid
    /// field whose config leaves its finest resolution out scales it by this, as instant-ngp does
    /// (2048 × `aabb_scale`), so that the resolution per unit of the scene stays the same.
    #[serde(default = "unit_scale")]
    pub scene_scale: f32,
}

fn unit_scale() -> f32 {
    1.0
}

/// Errors raised when a field is built or its parameters are loaded.
#[derive(Debug, thiserror::Error)]
pub enum FieldError {
    /// No registry entry has this name.
    #[error("unknown field `{name}` (known fields: {known})")]
    UnknownField {
        /// The name asked for.
        name: String,
        /// Comma-separated list of registered names.
        known: String,
    },
    /// The field's config did not deserialise or is inconsistent.
    #[error("invalid config for field `{field}`: {message}")]
    InvalidConfig {
        /// Field name.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// The field's GPU twin could not be built on this adapter (its kernels do not support the
    /// config, or a buffer exceeds the adapter's limits: [`GpuError::CapacityTooLarge`] says by
    /// how much, so the caller can launch fewer samples).
    #[error("field `{field}` on the GPU: {source}")]
    Gpu {
        /// Field name.
        field: String,
        /// What the GPU crate reported.
        source: GpuError,
    },
    /// The field does not offer something a run asks of it.
    #[error("field `{field}` does not provide {what}")]
    Unsupported {
        /// Field name.
        field: String,
        /// What was asked for.
        what: String,
    },
    /// Parameters loaded from a checkpoint do not match the field's layout.
    #[error("parameter group `{group}` mismatch: {message}")]
    ParamMismatch {
        /// Group name.
        group: String,
        /// What is wrong.
        message: String,
    },
}

/// A neural radiance field over packed samples (CPU execution path).
///
/// Buffers are flat and row-major: `positions` and `dirs` hold `3·n` floats, `sigma` `n`, `rgb`
/// `3·n`. Implementations are free to parallelise internally (rayon).
pub trait RadianceField: Send + Sync {
    /// The registry name of this field kind (`"freq"`, `"hash"`, …).
    fn kind(&self) -> &'static str;

    /// The full config the field was built with (serialised), recorded in metrics and checkpoints.
    fn config(&self) -> serde_json::Value;

    /// Number of trainable scalars.
    fn n_params(&self) -> usize;

    /// Density only (σ ≥ 0, already activated) at `positions`. Used by occupancy grids and by
    /// density-driven samplers. Takes `&self` so it can run while no training tape exists.
    fn density(&self, positions: &[f32], sigma: &mut [f32]);

    /// Inference: density and colour at the samples, no tape kept (rendering, evaluation).
    fn query(&self, positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]);

    /// Training forward: as [`query`](Self::query), and keeps what [`backward`](Self::backward)
    /// needs. Buffers are reused between steps (no allocation once warmed up).
    fn forward(&mut self, positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]);

    /// The density pass of a compacted training step (instant-ngp's: density of every marched
    /// sample, then training on those before each ray's early termination). Same σ as
    /// [`density`](Self::density); a field may also keep what it computed on the way (e.g. the
    /// position encodings) for the [`forward_rows`](Self::forward_rows) that follows. The default
    /// keeps nothing.
    fn density_for_training(&mut self, positions: &[f32], sigma: &mut [f32]) {
        self.density(positions, sigma)
    }

    /// Training forward on the samples `rows` (indices into the last
    /// [`density_for_training`](Self::density_for_training) call's samples) whose positions and
    /// directions are `positions` and `dirs` (`3·rows.len()` each, gathered by the caller). Must
    /// give what [`forward`](Self::forward) gives on the same samples; a field that kept work from
    /// the density pass reuses it here, provided no parameter changed in between. The default is
    /// [`forward`](Self::forward).
    fn forward_rows(&mut self, rows: &[u32], positions: &[f32], dirs: &[f32], sigma: &mut [f32], rgb: &mut [f32]) {
        let _ = rows;
        self.forward(positions, dirs, sigma, rgb)
    }

    /// Backward pass of the last [`forward`](Self::forward) (or
    /// [`forward_rows`](Self::forward_rows)): given dL/dσ (`n`) and dL/drgb (`3·n`),
    /// *accumulates* parameter gradients.
    fn backward(&mut self, d_sigma: &[f32], d_rgb: &[f32]);

    /// Whether [`backward_with_inputs`](Self::backward_with_inputs) is implemented: camera pose
    /// refinement (`nerf_rays::pose`) needs the field's gradients in its inputs. Default `false`.
    fn has_input_gradients(&self) -> bool {
        false
    }

    /// As [`backward`](Self::backward) (parameter gradients accumulated), and also *writes*
    /// dL/d(position) into `d_positions` and dL/d(direction) into `d_dirs` (`3·n` each) for every
    /// sample of the last forward. Where the field clamps a position (to its box) the gradient
    /// is that of the clamped function. The default returns [`FieldError::Unsupported`].
    fn backward_with_inputs(
        &mut self,
        d_sigma: &[f32],
        d_rgb: &[f32],
        d_positions: &mut [f32],
        d_dirs: &mut [f32],
    ) -> Result<(), FieldError> {
        let _ = (d_sigma, d_rgb, d_positions, d_dirs);
        Err(FieldError::Unsupported { field: self.kind().into(), what: "input gradients (camera pose refinement)".into() })
    }

    /// Sets all parameter gradients to zero.
    fn zero_grad(&mut self);

    /// Called after every optimiser step (and after parameters are loaded), for fields that keep
    /// state derived from their parameters — e.g. an f16 copy of a hash table used for lookups.
    fn after_optimizer_step(&mut self) {}

    /// A twin of this field on a wgpu device, starting from the current parameters, with buffers
    /// for `capacity` samples per launch; `None` when the field has no GPU implementation (the
    /// trainer then uses the CPU path, or reports it when the GPU was asked for).
    fn to_gpu(&self, ctx: &GpuContext, capacity: usize) -> Option<Result<Box<dyn GpuRadianceField>, FieldError>> {
        let _ = (ctx, capacity);
        None
    }

    /// Parameters and gradients as named groups, each with its own L2 weight decay, for the
    /// optimiser. Group names are stable (they key optimiser state and checkpoints).
    fn param_groups(&mut self) -> Vec<ParamGroupMut<'_>>;

    /// Copies of the parameters by group name (checkpoints).
    fn export_params(&self) -> Vec<(String, Vec<f32>)>;

    /// Restores parameters written by [`export_params`](Self::export_params).
    fn import_params(&mut self, groups: &[(String, Vec<f32>)]) -> Result<(), FieldError> {
        let mut mine = self.param_groups();
        if mine.len() != groups.len() {
            return Err(FieldError::ParamMismatch {
                group: "*".into(),
                message: format!("expected {} groups, got {}", mine.len(), groups.len()),
            });
        }
        for (g, (name, values)) in mine.iter_mut().zip(groups) {
            if g.name != name || g.params.len() != values.len() {
                return Err(FieldError::ParamMismatch {
                    group: name.clone(),
                    message: format!(
                        "expected `{}` with {} values, got `{}` with {}",
                        g.name,
                        g.params.len(),
                        name,
                        values.len()
                    ),
                });
            }
            g.params.copy_from_slice(values);
        }
        drop(mine);
        self.after_optimizer_step();
        Ok(())
    }
}

/// Builds a field from its (possibly partial) JSON config; missing keys take the field's defaults.
pub type FieldBuilder =
    fn(config: &serde_json::Value, ctx: &FieldContext) -> Result<Box<dyn RadianceField>, FieldError>;

/// One registered field kind.
#[derive(Clone, Copy)]
pub struct RegistryEntry {
    /// Name used on the command line and in config files (`--field freq`).
    pub name: &'static str,
    /// One-line description for `--help` and docs.
    pub description: &'static str,
    /// The field's default config, serialised.
    pub default_config: fn() -> serde_json::Value,
    /// Training settings this field is meant to be trained with (sampler, batch, learning rate…),
    /// as a JSON patch over the trainer's defaults; `null` = the trainer's defaults (the paper's).
    pub train_preset: fn() -> serde_json::Value,
    /// Constructor.
    pub build: FieldBuilder,
}

/// The set of field kinds a program knows, looked up by name.
#[derive(Clone, Default)]
pub struct Registry {
    entries: Vec<RegistryEntry>,
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds (or replaces) an entry.
    pub fn register(&mut self, entry: RegistryEntry) -> &mut Self {
        self.entries.retain(|e| e.name != entry.name);
        self.entries.push(entry);
        self
    }

    /// All registered entries in registration order.
    pub fn entries(&self) -> &[RegistryEntry] {
        &self.entries
    }

    /// The entry called `name`.
    pub fn get(&self, name: &str) -> Result<&RegistryEntry, FieldError> {
        self.entries.iter().find(|e| e.name == name).ok_or_else(|| FieldError::UnknownField {
            name: name.to_string(),
            known: self.entries.iter().map(|e| e.name).collect::<Vec<_>>().join(", "),
        })
    }

    /// Builds the field `name` from `config` (`null` = the defaults).
    pub fn build(
        &self,
        name: &str,
        config: &serde_json::Value,
        ctx: &FieldContext,
    ) -> Result<Box<dyn RadianceField>, FieldError> {
        (self.get(name)?.build)(config, ctx)
    }
}

/// Merges a partial JSON config over a field's defaults (objects merge key by key, recursively;
/// anything else replaces) and deserialises the result. Unknown keys are rejected by fields that
/// use `#[serde(deny_unknown_fields)]`.
pub fn config_from_json<C: serde::de::DeserializeOwned + Serialize + Default>(
    field: &str,
    partial: &serde_json::Value,
) -> Result<C, FieldError> {
    let mut base = serde_json::to_value(C::default()).expect("config serialises");
    merge_json(&mut base, partial);
    serde_json::from_value(base).map_err(|e| FieldError::InvalidConfig {
        field: field.to_string(),
        message: e.to_string(),
    })
}

/// The training recipe grid fields share, instant-ngp's adapted to a CPU, as a JSON patch over the
/// trainer's config (a field's [`RegistryEntry::train_preset`] returns it, or merges its own keys
/// over it with [`merge_json`]):
///
/// - occupancy-grid marching: a 128³ grid (EMA decay 0.95, threshold 0.01, updated every 16
///   steps, 256 warm-up steps), step √3·3/1024 ≈ 5e-3 for the 3-unit Blender box, at most 1024
///   samples per ray;
/// - rays per step adapted to 2^16 samples per step (instant-ngp takes 2^18 on a GPU; on 2 CPU
///   cores 2^16 gives ~4× more optimiser steps per minute, which matters more early on);
/// - a random background colour per training ray, white for evaluation;
/// - Adam lr 1e-2, β = (0.9, 0.99), ε = 1e-15; decay ×0.33 at 50 %, 75 % and 90 % of 20k steps;
/// - compositing stops once transmittance falls below 1e-4.
pub fn grid_field_preset() -> serde_json::Value {
    serde_json::json!({
        "sampler": {
            "kind": "occupancy",
            "grid": { "resolution": 128, "decay": 0.95, "threshold": 0.01, "update_every": 16, "warmup_steps": 256 },
            "step_size": 0.005,
            "max_samples_per_ray": 1024
        },
        "target_samples_per_step": 65536,
        "iters": 20000,
        "train_background": "random",
        "eval_background": "white",
        "transmittance_threshold": 1e-4,
        "adam": { "beta1": 0.9, "beta2": 0.99, "eps": 1e-15 },
        "lr": { "kind": "step", "lr0": 1e-2, "gamma": 0.33, "milestones": [10000, 15000, 18000] },
        "log_every": 100,
        "checkpoint_every": 2000
    })
}

/// Recursive JSON merge: keys of `patch` override those of `base`; `null` patches are ignored.
/// An object whose `"kind"` tag differs from the base's (a serde internally tagged enum, e.g. a
/// sampler or a learning-rate schedule) replaces the base object instead of merging into it.
pub fn merge_json(base: &mut serde_json::Value, patch: &serde_json::Value) {
    use serde_json::Value;
    match (base, patch) {
        (_, Value::Null) => {}
        (Value::Object(b), Value::Object(p))
            if p.get("kind").is_some_and(|k| b.get("kind").is_some_and(|bk| bk != k)) =>
        {
            *b = p.clone();
        }
        (Value::Object(b), Value::Object(p)) => {
            for (k, v) in p {
                match b.get_mut(k) {
                    Some(slot) => merge_json(slot, v),
                    None => {
                        b.insert(k.clone(), v.clone());
                    }
                }
            }
        }
        (b, p) => *b = p.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[derive(Serialize, Deserialize, Default, Debug, PartialEq)]
    #[serde(deny_unknown_fields)]
    struct Cfg {
        a: u32,
        b: Inner,
    }
    #[derive(Serialize, Deserialize, Default, Debug, PartialEq)]
    #[serde(deny_unknown_fields)]
    struct Inner {
        x: f32,
        y: Vec<u32>,
    }

    #[test]
    fn partial_configs_merge_over_defaults() {
        let c: Cfg = config_from_json("t", &json!({"b": {"x": 2.5}})).unwrap();
        assert_eq!(c, Cfg { a: 0, b: Inner { x: 2.5, y: vec![] } });
        let c: Cfg = config_from_json("t", &serde_json::Value::Null).unwrap();
        assert_eq!(c, Cfg::default());
    }

    #[test]
    fn a_different_enum_tag_replaces_instead_of_merging() {
        let mut base = json!({"s": {"kind": "a", "x": 1}, "t": {"kind": "a", "x": 1}});
        merge_json(&mut base, &json!({"s": {"kind": "b", "y": 2}, "t": {"kind": "a", "y": 2}}));
        assert_eq!(base, json!({"s": {"kind": "b", "y": 2}, "t": {"kind": "a", "x": 1, "y": 2}}));
    }

    #[test]
    fn unknown_keys_are_named_in_the_error() {
        let e = config_from_json::<Cfg>("t", &json!({"zz": 1})).unwrap_err();
        assert!(e.to_string().contains("zz"), "{e}");
    }

    #[test]
    fn unknown_field_lists_known_ones() {
        let mut r = Registry::new();
        r.register(RegistryEntry {
            name: "demo",
            description: "",
            default_config: || json!({}),
            train_preset: || json!(null),
            build: |_, _| Err(FieldError::InvalidConfig { field: "demo".into(), message: "x".into() }),
        });
        let ctx = FieldContext { aabb_min: [-1.0; 3], aabb_max: [1.0; 3], seed: 0, scene_scale: 1.0 };
        let e = r.build("nope", &json!(null), &ctx).err().unwrap();
        assert!(e.to_string().contains("demo"), "{e}");
        assert!(r.build("demo", &json!(null), &ctx).is_err());
    }
}
