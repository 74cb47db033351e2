//! The GPU twin of the paper's field against the CPU field on random samples (density, query,
//! training forward, parameter gradients, export/import) with the plain-WGSL networks, and with
//! cooperative matrices where the adapter has them (the H100; f16 tolerances). Prints a notice
//! and returns where no adapter exists.

use nerf_field::gpu::{check_gpu_input_gradients, check_gpu_twin};
use nerf_field::GpuContext;
use nerf_field::RadianceField;
use nerf_field_freq::{FreqNerf, FreqNerfConfig, GpuLinear};

#[test]
fn gpu_paper_field_matches_the_cpu_field() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    // The paper's layout at a width lavapipe runs quickly (skip, feature head, view branch).
    let cfg = FreqNerfConfig { width: 64, depth: 4, skips: vec![2], view_width: 32, ..Default::default() };
    let mut cpu = FreqNerf::<f32>::new(cfg, 5).unwrap();
    let aabb = ([-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]);
    if ctx.features.cooperative_matrix {
        // f16 operands (~1e-3 relative each), and ReLU masks that flip near zero.
        eprintln!("cooperative matrices: checking the f16 path");
        check_gpu_twin(&mut cpu, &ctx, aabb, 500, 4, 2e-2, 1e-1);
    } else {
        check_gpu_twin(&mut cpu, &ctx, aabb, 500, 4, 1e-4, 2e-3);
    }
}

/// Camera pose refinement's input gradients on the GPU (∂L/∂x through the trunk, skip included,
/// and the position's frequency encoding; ∂L/∂dir through the view net and the direction's)
/// against the CPU field's `backward_with_inputs`, with the plain-WGSL networks.
#[test]
fn gpu_paper_field_input_gradients_match_the_cpu_field() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let cfg = FreqNerfConfig { width: 64, depth: 4, skips: vec![2], view_width: 32, gpu_linear: GpuLinear::Plain, ..Default::default() };
    let mut cpu = FreqNerf::<f32>::new(cfg, 6).unwrap();
    let aabb = ([-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]);
    // Position gradients sum 2^9-scaled terms of both signs: relative to the largest value.
    check_gpu_input_gradients(&mut cpu, &ctx, aabb, 300, 6, 2e-4, 2e-3);
}

/// `gpu_linear` picks the GEMM kernels: the workgroup-tiled cooperative-matrix paths where the
/// adapter has cooperative matrices (and 32-wide subgroups; f16 tolerances as above), and a clear
/// refusal naming the setting elsewhere (lavapipe); `plain` runs everywhere.
#[test]
fn gpu_linear_selects_the_kernels() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    // Width 128 for `coop_tiled_wide`, so that its 128×128 kernels run (they take only widths
    // that are whole numbers of 128s).
    let cfg = |gpu_linear| {
        let width = if gpu_linear == GpuLinear::CoopTiledWide { 128 } else { 64 };
        FreqNerfConfig { width, depth: 4, skips: vec![2], view_width: 32, gpu_linear, ..Default::default() }
    };
    let aabb = ([-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]);
    let mut plain = FreqNerf::<f32>::new(cfg(GpuLinear::Plain), 6).unwrap();
    check_gpu_twin(&mut plain, &ctx, aabb, 300, 4, 1e-4, 2e-3);
    for path in [GpuLinear::Coop, GpuLinear::CoopTiled, GpuLinear::CoopTiledWide] {
        let mut f = FreqNerf::<f32>::new(cfg(path), 7).unwrap();
        match f.to_gpu(&ctx, 300).expect("the paper field has a GPU twin") {
            Ok(_) => {
                eprintln!("cooperative matrices: checking gpu_linear = {path:?}");
                check_gpu_twin(&mut f, &ctx, aabb, 300, 4, 2e-2, 1e-1);
            }
            Err(e) => {
                eprintln!("NOTICE: gpu_linear = {path:?} is not available on {}: {e}", ctx.describe());
                assert!(!ctx.features.cooperative_matrix || path != GpuLinear::Coop, "{e}");
                assert!(e.to_string().contains("gpu_linear") && e.to_string().contains("plain"), "{e}");
            }
        }
    }
}

/// `gpu_hidden_tape = false` (no f32 tape of the hidden layers; ReLU masks from the f16 copies):
/// the GPU twin still matches the CPU field with the f16 tolerances where the adapter has
/// cooperative matrices; elsewhere (lavapipe, plain GEMMs) the field refuses, naming the setting.
#[test]
fn gpu_paper_field_without_its_hidden_tape_matches_the_cpu_field() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let cfg = FreqNerfConfig { width: 64, depth: 4, skips: vec![2], view_width: 32, gpu_hidden_tape: Some(false), ..Default::default() };
    let mut f = FreqNerf::<f32>::new(cfg, 8).unwrap();
    let aabb = ([-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]);
    match f.to_gpu(&ctx, 300).expect("the paper field has a GPU twin") {
        Ok(_) => check_gpu_twin(&mut f, &ctx, aabb, 300, 4, 2e-2, 1e-1),
        Err(e) => {
            eprintln!("NOTICE: gpu_hidden_tape = false is not available on {}: {e}", ctx.describe());
            assert!(!ctx.features.cooperative_matrix, "{e}");
            assert!(e.to_string().contains("gpu_hidden_tape") && e.to_string().contains("cooperative-matrix"), "{e}");
        }
    }
}
