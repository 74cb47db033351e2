//! `shaders/field_glue.wgsl` (`nerf_gpu::glue::FieldGlue`) against a CPU twin written here from
//! the shader's contract (the fields' own CPU forward / backward are compared with their GPU
//! twins in crates/field-*/tests/gpu.rs): random inputs, poisoned outputs, counts that end inside
//! a workgroup, below the capacity, and past one dimension of workgroups; direct and indirect
//! launches.

use nerf_gpu::glue::{FieldGlue, SigmaActivation};
use nerf_gpu::{DispatchArgs, GpuContext, Launch};
use rand::Rng as _;

const POISON: f32 = -7.25e7;

fn random(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = nerf_core::rng(seed, 0);
    (0..n).map(|_| rng.gen_range(-3.0f32..3.0)).collect()
}

struct Shape {
    dd: usize,
    dir_dim: usize,
    feat_start: usize,
    act: SigmaActivation,
}

fn sigma_of(act: SigmaActivation, x: f32) -> f32 {
    match act {
        SigmaActivation::TruncExp { bias } => (x + bias).min(80.0).exp(),
        SigmaActivation::Relu => x.max(0.0),
        // In f64: the reference for the kernel's ln(1 + e) series at small e.
        SigmaActivation::Softplus { shift, scale } => {
            let z = x as f64 + shift as f64;
            (scale as f64 * (z.max(0.0) + (-z.abs()).exp().ln_1p())) as f32
        }
    }
}

fn sigma_grad(act: SigmaActivation, x: f32) -> f32 {
    match act {
        SigmaActivation::TruncExp { bias } => (x + bias).min(15.0).exp(),
        SigmaActivation::Relu => (x > 0.0) as u32 as f32,
        SigmaActivation::Softplus { shift, scale } => scale / (1.0 + (-(x + shift)).exp()),
    }
}

/// Runs assemble and backward on `n` of `capacity` samples and checks every output element,
/// the poison past `n` included.
fn check(ctx: &GpuContext, s: &Shape, capacity: usize, n: usize, indirect: bool, seed: u64) {
    let w = s.dd - s.feat_start + s.dir_dim;
    let glue = FieldGlue::new(ctx, s.dd, s.dir_dim, s.feat_start, s.act, capacity);
    assert_eq!(glue.color_in_dim, w);
    let dout = random(capacity * s.dd, seed);
    let dir = random(capacity * s.dir_dim, seed + 1);
    let d_color_in = random(capacity * w, seed + 2);
    let d_sigma = random(capacity, seed + 3);
    let counters = ctx.upload("counters", &[0u32, n as u32]);
    let b_dout = ctx.upload("dout", &dout);
    let b_dir = ctx.upload("dir", &dir);
    let b_dci = ctx.upload("d color in", &d_color_in);
    let b_ds = ctx.upload("d sigma", &d_sigma);
    let b_sigma = ctx.upload("sigma", &vec![POISON; capacity]);
    let b_ci = ctx.upload("color in", &vec![POISON; capacity * w]);
    let b_dd = ctx.upload("d dout", &vec![POISON; capacity * s.dd]);
    let args = DispatchArgs::new(ctx, capacity);
    let mut enc = ctx.encoder("glue test");
    let launch = if indirect {
        args.record(ctx, &mut enc, &counters, capacity)
    } else {
        Launch::direct(capacity)
    };
    glue.record_assemble(
        ctx, &mut enc, &counters, &b_dout, &b_dir, &b_sigma, &b_ci, launch,
    );
    glue.record_backward(
        ctx, &mut enc, &counters, &b_dout, &b_dci, &b_ds, &b_dd, launch,
    );
    ctx.queue.submit([enc.finish()]);
    let sigma = ctx.read_f32(&b_sigma, capacity).unwrap();
    let color_in = ctx.read_f32(&b_ci, capacity * w).unwrap();
    let d_dout = ctx.read_f32(&b_dd, capacity * s.dd).unwrap();
    let what = format!(
        "dd {} dir {} feat_start {} n {n}/{capacity} indirect {indirect}",
        s.dd, s.dir_dim, s.feat_start
    );
    let expect = |got: f32, want: f32, name: &str, i: usize| {
        // Exact for the copies; the activations within f32 rounding of the host's.
        assert!(
            (got - want).abs() <= 1e-6 * want.abs().max(1.0),
            "{what}: {name}[{i}] = {got}, expected {want}"
        );
    };
    for k in 0..capacity {
        let live = k < n;
        let x = dout[k * s.dd];
        expect(
            sigma[k],
            if live { sigma_of(s.act, x) } else { POISON },
            "sigma",
            k,
        );
        if live && matches!(s.act, SigmaActivation::Softplus { .. }) {
            // Relative as well: the voxel field starts with σ ≈ 1e-5 everywhere, where an
            // absolute bound says nothing.
            let want = sigma_of(s.act, x);
            assert!((sigma[k] - want).abs() <= 1e-4 * want.abs(), "{what}: sigma[{k}] = {}, expected {want}", sigma[k]);
        }
        for j in 0..w {
            let want = match (live, j < s.dd - s.feat_start) {
                (false, _) => POISON,
                (true, true) => dout[k * s.dd + s.feat_start + j],
                (true, false) => dir[k * s.dir_dim + j - (s.dd - s.feat_start)],
            };
            expect(color_in[k * w + j], want, "color_in", k * w + j);
        }
        for j in 0..s.dd {
            let mut want = if j >= s.feat_start {
                d_color_in[k * w + j - s.feat_start]
            } else {
                0.0
            };
            if j == 0 {
                want += d_sigma[k] * sigma_grad(s.act, x);
            }
            expect(
                d_dout[k * s.dd + j],
                if live { want } else { POISON },
                "d_dout",
                k * s.dd + j,
            );
        }
    }
}

#[test]
fn glue_matches_its_cpu_twin() {
    let Some(ctx) = GpuContext::for_tests() else {
        return;
    };
    let shapes = [
        // The hash field: all 16 density outputs, then 16 SH coefficients.
        Shape {
            dd: 16,
            dir_dim: 16,
            feat_start: 0,
            act: SigmaActivation::TruncExp { bias: 0.0 },
        },
        // The paper's field: σ, 256 features, 27 direction encodings.
        Shape {
            dd: 257,
            dir_dim: 27,
            feat_start: 1,
            act: SigmaActivation::Relu,
        },
        // Odd widths.
        Shape {
            dd: 5,
            dir_dim: 3,
            feat_start: 2,
            act: SigmaActivation::Relu,
        },
        Shape {
            dd: 1,
            dir_dim: 7,
            feat_start: 0,
            act: SigmaActivation::TruncExp { bias: -1.0 },
        },
        // The voxel field: σ from its density grid (column 0), 12 features from its feature grid,
        // 27 direction encodings; DVGO's shift for alpha_init 1e-6 (σ ≈ 1e-5: the ln(1 + e)
        // series) and a shift near 0 (the log).
        Shape {
            dd: 13,
            dir_dim: 27,
            feat_start: 1,
            act: SigmaActivation::Softplus { shift: -13.8155, scale: 42.7 },
        },
        Shape {
            dd: 3,
            dir_dim: 2,
            feat_start: 1,
            act: SigmaActivation::Softplus { shift: 0.5, scale: 0.75 },
        },
    ];
    let mut seed = 10;
    for s in &shapes {
        for (capacity, n) in [
            (200, 200),
            (200, 131),
            (200, 64),
            (200, 1),
            (200, 0),
            (1000, 999),
        ] {
            for indirect in [false, true] {
                seed += 4;
                check(&ctx, s, capacity, n, indirect, seed);
            }
        }
    }
    // Past 65 535 workgroups of 64 (the launch takes a second dimension).
    let big = 64 * 65_535 + 300;
    let s = Shape {
        dd: 2,
        dir_dim: 1,
        feat_start: 1,
        act: SigmaActivation::Relu,
    };
    check(&ctx, &s, big, big - 77, false, 99);
    check(&ctx, &s, big, big - 77, true, 100);
}
