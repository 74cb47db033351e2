//! `shaders/dense_grid.wgsl` (`nerf_gpu::encoding::GpuDenseGrid`) against its CPU twin
//! `nerf_encoding::DenseGrid` on random grids and positions (inside, outside and on the faces of
//! the box, NaN), with poisoned outputs: the forward must write exactly its columns of the first
//! `n` rows, the backward must add to the gradient (both the float-atomic and the
//! compare-and-swap paths), for direct and indirect launches. Lavapipe in CI; prints a notice and
//! returns where no adapter exists.

use nerf_encoding::DenseGrid;
use nerf_gpu::encoding::{AtomicMode, GpuDenseGrid};
use nerf_gpu::{DispatchArgs, GpuContext, Launch};
use rand::Rng as _;

const POISON: f32 = -7.25e7;

struct Case {
    res: usize,
    channels: usize,
    stride: usize,
    col: usize,
    scale: f32,
    capacity: usize,
    n: usize,
}

/// The voxel field's normalisation (`nerf-field-voxel`): clamp((p − min)·inv, 0, 1), NaN → 0.
#[allow(clippy::manual_clamp)] // `f32::clamp` keeps a NaN; max/min map it to 0, as the field does
fn normalise(p: &[f32], min: [f32; 3], inv: [f32; 3]) -> Vec<f32> {
    p.chunks_exact(3).flat_map(|q| [0, 1, 2].map(|a| ((q[a] - min[a]) * inv[a]).max(0.0).min(1.0))).collect()
}

fn check(ctx: &GpuContext, c: &Case, mode: AtomicMode, indirect: bool, seed: u64) {
    let mut rng = nerf_core::rng(seed, 0);
    let grid = DenseGrid::<f32>::uniform(c.res, c.channels, 1.0, &mut rng).unwrap();
    let (min, max) = ([-1.5f32, -0.7, 0.2], [1.5f32, 1.3, 2.2]);
    let inv: [f32; 3] = std::array::from_fn(|a| 1.0 / (max[a] - min[a]));
    // Positions: most inside, some outside the box, some on its faces, one NaN.
    let mut pos: Vec<f32> = (0..3 * c.capacity)
        .map(|i| {
            let a = i % 3;
            let e = max[a] - min[a];
            match rng.gen_range(0..10) {
                0 => min[a] - rng.gen_range(0.0..0.5) * e,
                1 => max[a] + rng.gen_range(0.0..0.5) * e,
                2 => max[a],
                3 => min[a],
                _ => min[a] + rng.gen::<f32>() * e,
            }
        })
        .collect();
    if c.capacity > 3 {
        pos[4] = f32::NAN;
    }
    let mut d_out: Vec<f32> = (0..c.capacity * c.stride).map(|_| rng.gen_range(-1.0..1.0)).collect();
    for i in (0..d_out.len()).step_by(7) {
        d_out[i] = 0.0;
    }
    let grads0: Vec<f32> = (0..grid.params().len()).map(|_| rng.gen_range(-0.5..0.5)).collect();

    // CPU: the first n samples.
    let xn = normalise(&pos[..3 * c.n], min, inv);
    let mut vals = vec![0.0f32; c.n * c.channels];
    grid.forward(&xn, &mut vals);
    let d_cols: Vec<f32> = (0..c.n * c.channels)
        .map(|e| c.scale * d_out[(e / c.channels) * c.stride + c.col + e % c.channels])
        .collect();
    let mut want_grads = grads0.clone();
    grid.backward(&xn, &d_cols, &mut want_grads, None);

    // GPU.
    let g = GpuDenseGrid::new(ctx, c.res, c.channels, min, inv, c.scale, (c.stride, c.col), mode).unwrap();
    assert_eq!(g.n_params(), grid.params().len());
    assert_eq!(g.uses_float_atomics(), mode != AtomicMode::CompareExchange && ctx.features.float32_atomics);
    let counters = ctx.upload("counters", &[0u32, c.n as u32]);
    let b_pos = ctx.upload("positions", &pos);
    let b_params = ctx.upload("params", grid.params());
    let b_out = ctx.upload("out", &vec![POISON; c.capacity * c.stride]);
    let b_dout = ctx.upload("d_out", &d_out);
    let b_grads = ctx.upload("grads", &grads0);
    let args = DispatchArgs::new(ctx, c.capacity);
    let mut enc = ctx.encoder("dense grid test");
    let launch = if indirect { args.record(ctx, &mut enc, &counters, c.capacity) } else { Launch::direct(c.capacity) };
    g.record_forward(ctx, &mut enc, &counters, &b_pos, &b_params, &b_out, launch);
    g.record_backward(ctx, &mut enc, &counters, &b_pos, &b_dout, &b_grads, launch);
    ctx.queue.submit([enc.finish()]);
    let out = ctx.read_f32(&b_out, c.capacity * c.stride).unwrap();
    let grads = ctx.read_f32(&b_grads, grads0.len()).unwrap();

    let what = format!("res {} C {} stride {} col {} n {}/{} {mode:?} indirect {indirect}", c.res, c.channels, c.stride, c.col, c.n, c.capacity);
    for k in 0..c.capacity {
        for j in 0..c.stride {
            let got = out[k * c.stride + j];
            let ch = j.wrapping_sub(c.col);
            if k < c.n && ch < c.channels {
                // The same weights and sum order as the CPU; only the scale's product may round
                // differently (none: one multiplication either way).
                let want = c.scale * vals[k * c.channels + ch];
                assert!((got - want).abs() <= 1e-6 * want.abs().max(1.0), "{what}: out[{k}][{j}] = {got}, expected {want}");
            } else {
                assert_eq!(got, POISON, "{what}: out[{k}][{j}] was written");
            }
        }
    }
    // The gradient: sums of up to 8·n terms in another order (atomics).
    let scale = want_grads.iter().fold(1.0f32, |m, v| m.max(v.abs()));
    let mut changed = 0;
    for (i, (&got, &want)) in grads.iter().zip(&want_grads).enumerate() {
        assert!((got - want).abs() <= 2e-5 * scale, "{what}: grads[{i}] = {got}, expected {want}");
        changed += (want != grads0[i]) as usize;
    }
    assert!(c.n == 0 || changed > 0, "{what}: the backward added nothing");
}

#[test]
fn dense_grid_kernels_match_their_cpu_twin() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let cases = [
        // The voxel field's two grids writing into one row of 1 + 12 floats.
        Case { res: 9, channels: 1, stride: 13, col: 0, scale: 30.0, capacity: 500, n: 500 },
        Case { res: 9, channels: 12, stride: 13, col: 1, scale: 30.0, capacity: 500, n: 437 },
        // One cell; a single channel mid-row; an empty batch; a count past a workgroup.
        Case { res: 1, channels: 2, stride: 2, col: 0, scale: 1.0, capacity: 64, n: 64 },
        Case { res: 4, channels: 1, stride: 5, col: 3, scale: -0.5, capacity: 300, n: 129 },
        Case { res: 6, channels: 3, stride: 3, col: 0, scale: 2.0, capacity: 200, n: 0 },
    ];
    let mut seed = 1;
    for c in &cases {
        for mode in [AtomicMode::Auto, AtomicMode::CompareExchange] {
            for indirect in [false, true] {
                seed += 1;
                check(&ctx, c, mode, indirect, seed);
            }
        }
    }
}

#[test]
fn dense_grid_rejects_bad_shapes_naming_the_problem() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let new = |res, ch, inv: [f32; 3], cols| GpuDenseGrid::new(&ctx, res, ch, [0.0; 3], inv, 1.0, cols, AtomicMode::Auto).err().map(|e| e.to_string());
    let e = new(0, 1, [1.0; 3], (1, 0)).expect("resolution 0");
    assert!(e.contains("resolution"), "{e}");
    let e = new(4, 0, [1.0; 3], (1, 0)).expect("no channels");
    assert!(e.contains("channels"), "{e}");
    let e = new(4, 3, [1.0; 3], (4, 2)).expect("columns past the row");
    assert!(e.contains("2..5") && e.contains("4 floats"), "{e}");
    let e = new(4, 1, [1.0, 0.0, 1.0], (1, 0)).expect("a flat box");
    assert!(e.contains("1/extent"), "{e}");
    assert!(new(4, 3, [1.0; 3], (4, 1)).is_none());
}
