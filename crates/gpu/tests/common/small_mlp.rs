//! Helpers shared by the fused-MLP tests (`tests/mlp.rs`, `tests/mlp_coop.rs`).

use nerf_mlp::{Activation, MlpConfig};
use rand::Rng as _;

/// An MLP config without skips.
pub fn cfg(input: usize, hidden: usize, layers: usize, output: usize, ha: Activation, oa: Activation, bias: bool) -> MlpConfig {
    MlpConfig {
        input_dim: input,
        output_dim: output,
        hidden_dim: hidden,
        hidden_layers: layers,
        hidden_activation: ha,
        output_activation: oa,
        skips: vec![],
        bias,
    }
}

/// `len` uniform values in `[-scale, scale)`.
pub fn random(rng: &mut nerf_core::Rng, len: usize, scale: f32) -> Vec<f32> {
    (0..len).map(|_| (2.0 * rng.gen::<f32>() - 1.0) * scale).collect()
}
