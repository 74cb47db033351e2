//! The GPU twin of the hash-grid field against the CPU field on random samples (density, query,
//! training forward, parameter gradients, export/import): lavapipe in CI; prints a notice and
//! returns where no adapter exists.

use nerf_field::gpu::{check_gpu_input_gradients, check_gpu_twin};
use nerf_field::{FieldContext, GpuContext};
use nerf_field_hash::{HashNerf, HashNerfConfig};

/// A small grid (dense and hashed levels) with the default MLP shapes, its table stored as
/// `storage`, checked against its GPU twin.
fn check_small_field(storage: nerf_encoding::Precision, seed: u64) {
    check_small_field_with(storage, seed, false);
}

fn check_small_field_with(storage: nerf_encoding::Precision, seed: u64, subgroup_sums: bool) {
    check_small_field_aligned(storage, seed, subgroup_sums, nerf_encoding::GridAlign::Corner);
}

fn check_small_field_aligned(storage: nerf_encoding::Precision, seed: u64, subgroup_sums: bool, align: nerf_encoding::GridAlign) {
    check_small_field_biased(storage, seed, subgroup_sums, align, 0.0);
}

fn check_small_field_biased(storage: nerf_encoding::Precision, seed: u64, subgroup_sums: bool, align: nerf_encoding::GridAlign, density_bias: f32) {
    let mut cfg = HashNerfConfig { gpu_hash_subgroup_sums: Some(subgroup_sums), density_bias, ..Default::default() };
    cfg.grid.align = align;
    cfg.grid.storage = storage;
    check_small_config(cfg, seed);
}

/// `cfg` on the small grid of [`check_small_field`] (its grid shape replaced).
fn check_small_config(mut cfg: HashNerfConfig, seed: u64) {
    let Some(ctx) = GpuContext::for_tests() else { return };
    cfg.grid.n_levels = 6;
    cfg.grid.log2_hashmap_size = 12;
    cfg.grid.base_resolution = 4;
    cfg.grid.max_resolution = 64;
    let aabb = ([-1.5, -1.2, -1.0], [1.5, 1.3, 1.1]);
    let fctx = FieldContext { aabb_min: aabb.0, aabb_max: aabb.1, seed, scene_scale: 1.0 };
    let mut cpu = HashNerf::<f32>::new(cfg, &fctx).unwrap();
    // Outputs: f32 sums in another order (trilinear interpolation, 64-wide dot products), exp of
    // σ. Gradients: sums over 700 samples in another order (atomics, split-K reductions).
    check_gpu_twin(&mut cpu, &ctx, aabb, 700, 3, 1e-4, 2e-3);
}

#[test]
fn gpu_hash_field_matches_the_cpu_field() {
    check_small_field(nerf_encoding::Precision::F32, 7);
}

/// The same with the table read through an f16 mirror (`grid.storage = "f16"`) on both devices
/// (the plumbing; `crates/gpu/tests/encoding.rs` checks the mirror's rounding itself).
#[test]
fn gpu_hash_field_with_an_f16_table_matches_the_cpu_field() {
    check_small_field(nerf_encoding::Precision::F16, 8);
}

/// The same with the table's backward summing its dense levels over subgroups first
/// (`gpu_hash_subgroup_sums`; where the adapter has no subgroups, the plain atomics again).
#[test]
fn gpu_hash_field_with_subgroup_sums_matches_the_cpu_field() {
    check_small_field_with(nerf_encoding::Precision::F32, 9, true);
}

/// The same with tiny-cuda-nn's staggered levels (`grid.align = "staggered"`), with plain atomics
/// and with subgroup sums.
#[test]
fn gpu_hash_field_with_staggered_levels_matches_the_cpu_field() {
    check_small_field_aligned(nerf_encoding::Precision::F32, 10, false, nerf_encoding::GridAlign::Staggered);
    check_small_field_aligned(nerf_encoding::Precision::F32, 13, true, nerf_encoding::GridAlign::Staggered);
}

/// The same with nerfacc's density bias (σ = exp(x − 1)).
#[test]
fn gpu_hash_field_with_a_density_bias_matches_the_cpu_field() {
    check_small_field_biased(nerf_encoding::Precision::F32, 14, false, nerf_encoding::GridAlign::Corner, -1.0);
}

/// The same with nerfacc's colour head (`color_input = "features"`: the glue hands the colour
/// net the density outputs after the logit).
#[test]
fn gpu_hash_field_with_the_features_colour_input_matches_the_cpu_field() {
    check_small_config(HashNerfConfig { color_input: nerf_field_hash::ColorInput::Features, ..Default::default() }, 15);
}

/// A decayed table (`grid_weight_decay`) and MLPs: the twin's parameter groups carry the CPU
/// field's decays (`check_gpu_twin` compares them), which the GPU's Adam applies as the CPU's
/// does (crates/gpu/tests/optim.rs).
#[test]
fn gpu_hash_field_with_a_decayed_table_matches_the_cpu_field() {
    check_small_config(HashNerfConfig { grid_weight_decay: 2e-6, mlp_weight_decay: 3e-6, ..Default::default() }, 5);
}

/// Camera pose refinement's input gradients (∂L/∂x through the hash encoding and the box's
/// normalisation, ∂L/∂dir through the SH encoding and the colour net's input gradient) against
/// the CPU field's `backward_with_inputs`, and the parameter gradients with them on.
#[test]
fn gpu_hash_field_input_gradients_match_the_cpu_field() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    use nerf_field_hash::ColorInput::{All, Features};
    for (seed, sh_degree, align, color_input) in [
        (11, 4, nerf_encoding::GridAlign::Corner, All),
        (12, 2, nerf_encoding::GridAlign::Corner, All),
        (14, 4, nerf_encoding::GridAlign::Staggered, All),
        // The SH columns start after the features alone.
        (16, 4, nerf_encoding::GridAlign::Corner, Features),
    ] {
        let mut cfg = HashNerfConfig { color_input, ..Default::default() };
        cfg.grid.align = align;
        cfg.grid.n_levels = 6;
        cfg.grid.log2_hashmap_size = 12;
        cfg.grid.base_resolution = 4;
        cfg.grid.max_resolution = 64;
        cfg.sh_degree = sh_degree;
        let aabb = ([-1.5, -1.2, -1.0], [1.5, 1.3, 1.1]);
        let fctx = FieldContext { aabb_min: aabb.0, aabb_max: aabb.1, seed, scene_scale: 1.0 };
        let mut cpu = HashNerf::<f32>::new(cfg, &fctx).unwrap();
        // Sums of products in another order (8 corners × 6 levels, 64-wide dot products).
        check_gpu_input_gradients(&mut cpu, &ctx, aabb, 500, seed, 1e-4, 2e-3);
    }
}

#[test]
fn a_capacity_beyond_the_devices_binding_limit_is_a_clear_error() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let mut cfg = HashNerfConfig::default();
    cfg.grid.n_levels = 2;
    cfg.grid.log2_hashmap_size = 10;
    let aabb = ([-1.5f32; 3], [1.5f32; 3]);
    let fctx = FieldContext { aabb_min: aabb.0, aabb_max: aabb.1, seed: 7, scene_scale: 1.0 };
    let cpu = HashNerf::<f32>::new(cfg, &fctx).unwrap();
    // The colour MLP's tape is the largest per-sample buffer: one sample more than the limit holds.
    let color_fps = nerf_gpu::mlp::FusedMlp::new(&ctx, &cpu.mlps()[1].config).unwrap().tape_floats_per_sample();
    let capacity = (ctx.max_storage_bytes() / (4 * color_fps as u64)) as usize + 1;
    let err = match nerf_field::RadianceField::to_gpu(&cpu, &ctx, capacity).expect("the hash field has a GPU twin") {
        Ok(_) => panic!("a {capacity}-sample capacity fitted a {}-byte binding limit", ctx.max_storage_bytes()),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("color tape") && err.contains("MiB") && err.contains("target_samples_per_step"), "{err}");
}

#[test]
fn cpu_only_precision_keys_are_refused_on_the_gpu() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let fctx = FieldContext { aabb_min: [-1.5; 3], aabb_max: [1.5; 3], seed: 7, scene_scale: 1.0 };
    // The table's gradient summed in f16, and the MLPs in emulated f16 arithmetic.
    for key in ["grad_f16_scale", "mlp_f16_scale"] {
        let mut cfg = HashNerfConfig::default();
        cfg.grid.n_levels = 2;
        cfg.grid.log2_hashmap_size = 10;
        match key {
            "grad_f16_scale" => cfg.grid.grad_f16_scale = Some(16.0),
            _ => cfg.mlp_f16_scale = Some(128.0),
        }
        let cpu = HashNerf::<f32>::new(cfg, &fctx).unwrap();
        let err = match nerf_field::RadianceField::to_gpu(&cpu, &ctx, 1024).expect("the hash field has a GPU twin") {
            Ok(_) => panic!("the GPU field took {key}"),
            Err(e) => e.to_string(),
        };
        assert!(err.contains(key) && err.contains("CPU only"), "{err}");
    }
}

#[test]
fn the_cooperative_matrix_mlps_match_the_cpu_field_where_the_adapter_has_them() {
    let cfg: HashNerfConfig = serde_json::from_value(serde_json::json!({
        "gpu_mlp": "coop",
        "grid": { "n_levels": 6, "log2_hashmap_size": 12, "base_resolution": 4, "max_resolution": 64 }
    }))
    .unwrap();
    assert_eq!(cfg.gpu_mlp, nerf_field_hash::GpuMlp::Coop);
    assert_eq!(serde_json::to_value(&cfg).unwrap()["gpu_mlp"], "coop");
    let Some(ctx) = GpuContext::for_tests() else { return };
    let aabb = ([-1.5, -1.2, -1.0], [1.5, 1.3, 1.1]);
    let fctx = FieldContext { aabb_min: aabb.0, aabb_max: aabb.1, seed: 7, scene_scale: 1.0 };
    let mut cpu = HashNerf::<f32>::new(cfg, &fctx).unwrap();
    if !(ctx.features.cooperative_matrix && ctx.features.shader_f16) {
        let err = match nerf_field::RadianceField::to_gpu(&cpu, &ctx, 1024).expect("a GPU twin") {
            Ok(_) => panic!("gpu_mlp = coop accepted on an adapter without cooperative matrices"),
            Err(e) => e.to_string(),
        };
        assert!(err.contains("gpu_mlp") && err.contains("cooperative matrices") && err.contains("plain"), "{err}");
        println!("NOTICE: {} has no cooperative matrices: only the error path was checked", ctx.describe());
        return;
    }
    // f16 activations, weights and scaled gradients (see crates/gpu/tests/mlp_coop.rs): outputs
    // within 2 % of the largest value, gradients within 5 %.
    check_gpu_twin(&mut cpu, &ctx, aabb, 700, 3, 2e-2, 5e-2);
}

#[test]
fn chunked_density_matches_the_cpu_field_beyond_the_fields_capacity() {
    use nerf_field::{ChunkedDensity, RadianceField};
    use rand::Rng as _;
    let Some(ctx) = GpuContext::for_tests() else { return };
    let mut cfg = HashNerfConfig::default();
    cfg.grid.n_levels = 4;
    cfg.grid.log2_hashmap_size = 12;
    let aabb = ([-1.5f32; 3], [1.5f32; 3]);
    let fctx = FieldContext { aabb_min: aabb.0, aabb_max: aabb.1, seed: 9, scene_scale: 1.0 };
    let cpu = HashNerf::<f32>::new(cfg, &fctx).unwrap();
    let (chunk, total) = (300, 1000); // chunks of 300, 300, 300, 100
    let gpu = cpu.to_gpu(&ctx, chunk).unwrap().unwrap();
    let chunked = ChunkedDensity::new(&ctx, chunk, total);
    let mut rng = nerf_core::rng(4, 0);
    let pos: Vec<f32> = (0..3 * total).map(|_| rng.gen_range(-1.5f32..1.5)).collect();
    let mut want = vec![0.0; total];
    cpu.density(&pos, &mut want);
    let positions = ctx.upload("positions", &pos);
    for n in [0usize, 1, 299, 300, 301, 777, 1000] {
        let sigma = ctx.upload("sigma", &vec![f32::NAN; total]);
        let counters = ctx.upload("counters", &[0u32, n as u32]);
        let mut enc = ctx.encoder("chunked density");
        chunked.record(&ctx, &mut enc, gpu.as_ref(), &counters, &positions, &sigma);
        ctx.queue.submit([enc.finish()]);
        let got = ctx.read_f32(&sigma, total).unwrap();
        let scale = want.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        for i in 0..n {
            assert!((got[i] - want[i]).abs() <= 1e-4 * scale, "n = {n}: σ[{i}] gpu {} vs cpu {}", got[i], want[i]);
        }
        // Past the count nothing is written: the first chunk writes its own count, and the later
        // ones copy out only theirs (`GpuRowCopy`), not their chunk buffer's capacity.
        for (i, g) in got.iter().enumerate().skip(n) {
            assert!(g.is_nan(), "n = {n}: σ[{i}] written past the count");
        }
    }
}

/// With the density net's activations kept by the density pass (the default) and without (the
/// density net runs again on the gathered encodings).
#[test]
fn forward_on_rows_of_the_density_pass_equals_a_fresh_forward() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    // Chunks of 301 samples are never at an aligned offset (4 · 301 bytes of σ is not a multiple
    // of 8): they go through the chunk buffers. Chunks of 320 are (1280 bytes, 5 · 256) on every
    // adapter: they are read and written in place, unless `gpu_density_in_place = false`.
    let align = ctx.storage_offset_alignment();
    assert!(align >= 8 && 1280 % align == 0, "storage offset alignment {align}");
    for (chunk, in_place) in [(301, true), (320, true), (320, false)] {
        for keep_activations in [true, false] {
            check_forward_on_rows(&ctx, chunk, in_place, keep_activations);
        }
    }
}

fn check_forward_on_rows(ctx: &GpuContext, chunk: usize, in_place: bool, keep_activations: bool) {
    use nerf_field::{ChunkedDensity, GpuRadianceField, GpuSamples, RadianceField};
    use rand::Rng as _;
    let mut cfg = HashNerfConfig { gpu_keep_density_activations: keep_activations, gpu_density_in_place: in_place, ..Default::default() };
    cfg.grid.n_levels = 5;
    cfg.grid.log2_hashmap_size = 12;
    cfg.grid.base_resolution = 4;
    cfg.grid.max_resolution = 64;
    let aabb = ([-1.5f32; 3], [1.5f32; 3]);
    let fctx = FieldContext { aabb_min: aabb.0, aabb_max: aabb.1, seed: 11, scene_scale: 1.0 };
    let cpu = HashNerf::<f32>::new(cfg, &fctx).unwrap();
    // A marched batch of up to 700 samples in chunks of `chunk` (the first in place, the others
    // through the chunk buffers or in place), n of them marched; m kept rows drawn from them
    // (repeats too).
    let (total, n, m) = (700, 650, 280);
    let mut rng = nerf_core::rng(5, 0);
    let pos: Vec<f32> = (0..3 * total).map(|_| rng.gen_range(-1.5f32..1.5)).collect();
    let dirs: Vec<f32> = (0..m)
        .flat_map(|_| {
            let d = [rng.gen_range(-1.0f32..1.0), rng.gen_range(-1.0f32..1.0), 0.5];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            d.map(|x| x / l)
        })
        .collect();
    let rows: Vec<u32> = (0..m).map(|b| if b % 7 == 3 { (n - 1) as u32 } else { rng.gen_range(0..n as u32) }).collect();
    let kept_pos: Vec<f32> = rows.iter().flat_map(|&r| pos[3 * r as usize..3 * r as usize + 3].to_vec()).collect();
    let pad = |v: &[f32], len: usize| {
        let mut p = v.to_vec();
        p.resize(len, f32::NAN);
        p
    };
    let marched_counters = ctx.upload("marched counters", &[0u32, n as u32]);
    let marched = ctx.upload("marched positions", &pos);
    let marched_sigma = ctx.upload("marched sigma", &vec![f32::NAN; total]);
    let counters = ctx.upload("counters", &[0u32, m as u32]);
    let positions = ctx.upload("positions", &pad(&kept_pos, 3 * chunk));
    let d = ctx.upload("dirs", &pad(&dirs, 3 * chunk));
    let mut padded_rows = rows.clone();
    padded_rows.resize(chunk, u32::MAX); // past the count: never read
    let rows_buf = ctx.upload("rows", &padded_rows);
    let s = GpuSamples { counters: &counters, positions: &positions, dirs: &d, capacity: chunk };
    let d_sigma: Vec<f32> = (0..m).map(|_| rng.gen_range(-0.1f32..0.1)).collect();
    let d_rgb: Vec<f32> = (0..3 * m).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let (dsb, drb) = (ctx.upload("d sigma", &pad(&d_sigma, chunk)), ctx.upload("d rgb", &pad(&d_rgb, 3 * chunk)));
    let chunked = ChunkedDensity::new(ctx, chunk, total);
    let outputs = || (ctx.upload("sigma", &vec![f32::NAN; chunk]), ctx.upload("rgb", &vec![f32::NAN; 3 * chunk]));
    let read = |g: &dyn GpuRadianceField, sigma: &nerf_field::gpu::wgpu::Buffer, rgb: &nerf_field::gpu::wgpu::Buffer| {
        let grads: Vec<Vec<f32>> = g.groups().iter().map(|p| ctx.read_f32(&p.grads, p.len).unwrap()).collect();
        (ctx.read_f32(sigma, m).unwrap(), ctx.read_f32(rgb, 3 * m).unwrap(), grads)
    };

    // The step on compacted samples: density pass (keeping the encodings), forward on the rows,
    // backward.
    let mut kept = cpu.to_gpu(ctx, chunk).unwrap().unwrap();
    assert!(!kept.density_pass_in_place(), "in place before keep_density_pass");
    kept.keep_density_pass(ctx, total).unwrap();
    assert_eq!(kept.density_pass_in_place(), in_place && chunk == 320, "chunks of {chunk}, gpu_density_in_place = {in_place}");
    let (sigma, rgb) = outputs();
    let mut enc = ctx.encoder("compacted");
    chunked.record_for_training(ctx, &mut enc, kept.as_ref(), &marched_counters, &marched, &marched_sigma);
    kept.record_forward_rows(ctx, &mut enc, s, &rows_buf, &sigma, &rgb);
    kept.record_backward(ctx, &mut enc, s, &dsb, &drb);
    ctx.queue.submit([enc.finish()]);
    let (ks, kc, kg) = read(kept.as_ref(), &sigma, &rgb);
    // σ of the density pass is the field's density.
    let mut want = vec![0.0; total];
    cpu.density(&pos, &mut want);
    let got = ctx.read_f32(&marched_sigma, n).unwrap();
    let scale = want.iter().fold(0.0f32, |a, x| a.max(x.abs()));
    for i in 0..n {
        assert!((got[i] - want[i]).abs() <= 1e-4 * scale, "chunks of {chunk}: density pass σ[{i}]: gpu {} vs cpu {}", got[i], want[i]);
    }
    // Past the marched count nothing is written (the last chunk writes its own count only).
    assert!(ctx.read_f32(&marched_sigma, total).unwrap()[n..].iter().all(|x| x.is_nan()), "chunks of {chunk}: σ written past the count");

    // The same samples through a fresh twin's plain forward.
    let fresh = cpu.to_gpu(ctx, chunk).unwrap().unwrap();
    let (sigma, rgb) = outputs();
    let mut enc = ctx.encoder("fresh");
    fresh.record_forward(ctx, &mut enc, s, &sigma, &rgb);
    fresh.record_backward(ctx, &mut enc, s, &dsb, &drb);
    ctx.queue.submit([enc.finish()]);
    let (fs, fc, fg) = read(fresh.as_ref(), &sigma, &rgb);
    // Same encodings, same kernels after them: outputs bit for bit; gradients up to the order of
    // the hash grid's atomic additions.
    assert_eq!(ks.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), fs.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), "σ");
    assert_eq!(kc.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), fc.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), "rgb");
    for (g, (a, b)) in kg.iter().zip(&fg).enumerate() {
        let scale = b.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        assert!(scale > 0.0, "group {g}: no gradient");
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!((x - y).abs() <= 1e-5 * scale, "group {g}[{i}]: rows {x} vs fresh {y}");
        }
    }

    // The forward on rows reads the pass's encodings, not fresh ones: with the table changed
    // after the pass, it still gives the σ of the old table (a fresh forward does not).
    let mut params = kept.export_params(ctx).unwrap();
    params[0].1.iter_mut().for_each(|x| *x += 0.5);
    let (sigma, rgb) = outputs();
    let mut enc = ctx.encoder("pass");
    chunked.record_for_training(ctx, &mut enc, kept.as_ref(), &marched_counters, &marched, &marched_sigma);
    ctx.queue.submit([enc.finish()]);
    kept.import_params(ctx, &params).unwrap();
    let mut enc = ctx.encoder("rows after a change");
    kept.record_forward_rows(ctx, &mut enc, s, &rows_buf, &sigma, &rgb);
    ctx.queue.submit([enc.finish()]);
    assert_eq!(ctx.read_f32(&sigma, m).unwrap(), ks, "forward_rows computed the encodings again");
    let mut enc = ctx.encoder("fresh after a change");
    kept.record_forward(ctx, &mut enc, s, &sigma, &rgb);
    ctx.queue.submit([enc.finish()]);
    assert_ne!(ctx.read_f32(&sigma, m).unwrap(), ks, "the change of the table must show in a fresh forward");

    // Likewise the density net's weights: with its activations kept, the forward on rows gives
    // the σ of the weights the pass saw; without, the net runs again with the new weights.
    let pass_then_rows = |new_params: Option<&[(String, Vec<f32>)]>| {
        let mut enc = ctx.encoder("pass");
        chunked.record_for_training(ctx, &mut enc, kept.as_ref(), &marched_counters, &marched, &marched_sigma);
        ctx.queue.submit([enc.finish()]);
        if let Some(p) = new_params {
            kept.import_params(ctx, p).unwrap();
        }
        let mut enc = ctx.encoder("rows");
        kept.record_forward_rows(ctx, &mut enc, s, &rows_buf, &sigma, &rgb);
        ctx.queue.submit([enc.finish()]);
        ctx.read_f32(&sigma, m).unwrap()
    };
    let want = pass_then_rows(None);
    let mut changed = kept.export_params(ctx).unwrap();
    changed[1].1.iter_mut().for_each(|x| *x *= 1.5);
    let got = pass_then_rows(Some(&changed));
    if keep_activations {
        assert_eq!(got, want, "forward_rows ran the density net again");
    } else {
        assert_ne!(got, want, "without kept activations the density net runs on the rows");
    }
}
