//! Criterion benches of the GPU kernels that dominate a training step, on the first adapter
//! (skipped without one): hash encoding forward/backward (L16 F2 T2^19; the backward also on samples along rays and with
//! the dense levels summed over subgroups first); the hash field's fused
//! MLPs forward, forward + backward and the density pass's σ-only inference (plain WGSL, and on
//! cooperative matrices where the adapter has them); the paper's 8×256 trunk forward + backward
//! (plain WGSL, and cooperative matrices where the adapter has them: subgroup-tiled and, with
//! subgroups of 32, workgroup-tiled); Adam over the hash field's 12 M parameters; camera pose
//! refinement's kernels (the hash grid's and the SH encoding's input gradients, and the per-ray
//! and per-view sums of a batch of rays of 32 samples over 100 views). Each iteration
//! records one launch sequence, submits it and waits, so the time is the device's. Sizes: 2^18
//! samples (2^12 with `NERF_BENCH_SMALL=1`), halved where a buffer would pass the adapter's
//! storage-binding limit (lavapipe's 128 MiB: 2^16 samples, the trunk's 2^13), so the bench runs
//! everywhere; each bench's name carries its size. `cargo bench -p nerf-gpu --bench kernels`.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use nerf_encoding::HashGridConfig;
use nerf_gpu::encoding::{AtomicMode, GpuHashGrid, GpuSphericalHarmonics};
use nerf_gpu::pose::{GpuPoseCorrection, PoseRays, PoseSampleGrads};
use nerf_gpu::linear::{GpuMlp, LinearPath};
use nerf_gpu::mlp::FusedMlp;
use nerf_gpu::mlp_coop::FusedMlpCoop;
use nerf_gpu::optim::{GpuAdam, GpuParamGroup};
use nerf_gpu::{wgpu, GpuContext};
use nerf_mlp::{Activation, MlpConfig};
use rand::Rng as _;

/// The largest power of two ≤ `n` whose `n · bytes_per_sample` fits one storage binding of `ctx`.
fn fit(ctx: &GpuContext, mut n: usize, bytes_per_sample: usize) -> usize {
    let limit = ctx.device.limits().max_storage_buffer_binding_size as usize;
    while n > 1 && n * bytes_per_sample > limit {
        n /= 2;
    }
    n
}

/// Samples per bench: 2^18 (2^12 with `NERF_BENCH_SMALL`), fitted to the largest per-sample buffer
/// of the fused MLPs (the colour net's tape).
fn n_samples(ctx: &GpuContext) -> usize {
    let n = if std::env::var_os("NERF_BENCH_SMALL").is_some() { 1 << 12 } else { 1 << 18 };
    let color = MlpConfig {
        input_dim: 32,
        output_dim: 3,
        hidden_dim: 64,
        hidden_layers: 2,
        hidden_activation: Activation::Relu,
        output_activation: Activation::Sigmoid,
        skips: vec![],
        bias: false,
    };
    let fps = FusedMlp::new(ctx, &color).expect("the colour net").tape_floats_per_sample();
    fit(ctx, n, 4 * fps)
}

fn random(n: usize, lo: f32, hi: f32, seed: u64) -> Vec<f32> {
    let mut rng = nerf_core::rng(seed, 0);
    (0..n).map(|_| rng.gen_range(lo..hi)).collect()
}

/// `n` positions in the box [-1.5, 1.5]³ as a training batch packs them: runs of 32 consecutive
/// samples along random rays, 0.005 apart (the hash preset's marching step).
fn ray_positions(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = nerf_core::rng(seed, 0);
    let mut p = Vec::with_capacity(3 * n);
    while p.len() < 3 * n {
        let o: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.3f32..1.3));
        let d: [f32; 3] = std::array::from_fn(|_| rng.gen_range(-1.0f32..1.0));
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
        for s in 0..32 {
            p.extend((0..3).map(|a| (o[a] + 0.005 * s as f32 * d[a] / len).clamp(-1.5, 1.5)));
        }
    }
    p.truncate(3 * n);
    p
}

/// Records with `f`, submits, waits.
fn run(ctx: &GpuContext, f: impl Fn(&mut wgpu::CommandEncoder)) {
    let mut enc = ctx.encoder("bench");
    f(&mut enc);
    ctx.queue.submit([enc.finish()]);
    ctx.wait().unwrap();
}

fn kernels(c: &mut Criterion) {
    let Some(ctx) = GpuContext::for_tests() else { return };
    let n = n_samples(&ctx);
    let counters = ctx.upload("counters", &[0u32, n as u32]);
    let mut g = c.benchmark_group(format!("gpu_kernels ({})", ctx.info.name));
    g.sample_size(20);
    g.throughput(Throughput::Elements(n as u64));

    // Hash encoding.
    let cfg = HashGridConfig::default();
    let grid = GpuHashGrid::new(&ctx, &cfg, [-1.5; 3], [1.5; 3]).unwrap();
    let params = ctx.upload("table", &random(grid.n_params(), -1e-4, 1e-4, 1));
    let grads = ctx.zeros("table grads", 4 * grid.n_params());
    let pos = ctx.upload("positions", &random(3 * n, -1.5, 1.5, 2));
    let feat = ctx.zeros("features", 4 * n * grid.output_dim());
    let d_feat = ctx.upload("d features", &random(n * grid.output_dim(), -1.0, 1.0, 3));
    g.bench_function(BenchmarkId::new("hash_grid_forward", n), |b| {
        b.iter(|| run(&ctx, |e| grid.record_forward(&ctx, e, &counters, &pos, &params, &feat, n.into())))
    });
    g.bench_function(BenchmarkId::new("hash_grid_backward", n), |b| {
        b.iter(|| run(&ctx, |e| grid.record_backward(&ctx, e, &counters, &pos, &d_feat, &grads, n.into())))
    });
    // The backward on samples along rays (neighbours share the coarse levels' cells, so their
    // atomics contend), with and without the subgroup sums of the dense levels.
    let rays = ctx.upload("ray positions", &ray_positions(n, 4));
    let grid_sg = GpuHashGrid::with_atomics(&ctx, &cfg, [-1.5; 3], [1.5; 3], AtomicMode::SubgroupSums).unwrap();
    for (name, gr, p) in [
        ("hash_grid_backward_subgroup_sums", &grid_sg, &pos),
        ("hash_grid_backward_rays", &grid, &rays),
        ("hash_grid_backward_rays_subgroup_sums", &grid_sg, &rays),
    ] {
        g.bench_function(BenchmarkId::new(name, n), |b| {
            b.iter(|| run(&ctx, |e| gr.record_backward(&ctx, e, &counters, p, &d_feat, &grads, n.into())))
        });
    }
    // The forward through the f16 mirror (`storage = "f16"`), the mirror's rewrite from the f32
    // table included (as every forward does it).
    let cfg16 = HashGridConfig { storage: nerf_encoding::Precision::F16, ..cfg.clone() };
    let grid16 = GpuHashGrid::new(&ctx, &cfg16, [-1.5; 3], [1.5; 3]).unwrap();
    g.bench_function(BenchmarkId::new("hash_grid_forward_f16_table", n), |b| {
        b.iter(|| run(&ctx, |e| grid16.record_forward(&ctx, e, &counters, &pos, &params, &feat, n.into())))
    });

    // Camera pose refinement: the field's input gradients (hash grid through its f32 table; SH of
    // degree 4 from the colour net's 32-wide input-gradient rows), then the pose kernels on rays
    // of 32 samples from 100 views (correction, per-ray sums, one workgroup per view).
    let d_pos = ctx.zeros("d positions", 12 * n);
    g.bench_function(BenchmarkId::new("hash_grid_input_gradient", n), |b| {
        b.iter(|| run(&ctx, |e| grid.record_input_gradient(&ctx, e, &counters, &rays, &params, &d_feat, &d_pos, n.into())))
    });
    let sh = GpuSphericalHarmonics::new(&ctx, &nerf_encoding::ShConfig { degree: 4 }).unwrap();
    let dirs = ctx.upload("dirs", &random(3 * n, -0.577, 0.577, 12));
    let d_rows = ctx.upload("d colour input", &random(32 * n, -1.0, 1.0, 13));
    let d_dirs = ctx.zeros("d dirs", 12 * n);
    g.bench_function(BenchmarkId::new("sh_input_gradient", n), |b| {
        b.iter(|| run(&ctx, |e| sh.record_input_gradient(&ctx, e, &counters, &dirs, &d_rows, 32, 16, &d_dirs, n.into())))
    });
    let n_rays = n / 32;
    let pose = GpuPoseCorrection::new(&ctx, 100, n_rays, 1e-2, 1e-3).unwrap();
    pose.set_params(&ctx, &random(6 * 100, -0.01, 0.01, 14)).unwrap();
    let ray_counters = ctx.upload("ray counters", &[n_rays as u32, n as u32]);
    let views = ctx.upload("views", &(0..n_rays as u32).map(|r| r % 100).collect::<Vec<u32>>());
    let (origins, ray_dirs) = (ctx.upload("origins", &random(3 * n_rays, -3.0, 3.0, 15)), ctx.upload("ray dirs", &random(3 * n_rays, -0.577, 0.577, 16)));
    let offsets = ctx.upload("offsets", &(0..=n_rays as u32).map(|r| 32 * r).collect::<Vec<u32>>());
    let t = ctx.upload("t", &random(n, 2.0, 6.0, 17));
    let rays_in = PoseRays { counters: &ray_counters, views: &views, origins: &origins, dirs: &ray_dirs };
    let grads_in = PoseSampleGrads { offsets: &offsets, t: &t, d_positions: &d_pos, d_dirs: &d_dirs };
    g.bench_function(BenchmarkId::new("pose_correct_backward_reduce", n), |b| {
        b.iter(|| {
            run(&ctx, |e| {
                pose.record_correct(&ctx, e, &rays_in);
                pose.record_rays_backward(&ctx, e, &ray_counters, &grads_in);
                pose.record_reduce(&ctx, e, &ray_counters, &views);
            })
        })
    });

    // The hash field's fused MLPs.
    let mlp = |input, output, layers, out_act| MlpConfig {
        input_dim: input,
        output_dim: output,
        hidden_dim: 64,
        hidden_layers: layers,
        hidden_activation: Activation::Relu,
        output_activation: out_act,
        skips: vec![],
        bias: false,
    };
    for (name, cfg) in [("density_32_64_16", mlp(32, 16, 1, Activation::None)), ("color_32_64_64_3", mlp(32, 3, 2, Activation::Sigmoid))] {
        let net = FusedMlp::new(&ctx, &cfg).unwrap();
        let p = ctx.upload("w", &random(net.n_params(), -0.1, 0.1, 4));
        let gr = ctx.zeros("dw", 4 * net.n_params());
        let x = ctx.upload("x", &random(n * cfg.input_dim, -1.0, 1.0, 5));
        let y = ctx.zeros("y", 4 * n * cfg.output_dim);
        let tape = ctx.zeros("tape", 4 * n * net.tape_floats_per_sample());
        let dy = ctx.upload("dy", &random(n * cfg.output_dim, -1.0, 1.0, 6));
        let dx = ctx.zeros("dx", 4 * n * cfg.input_dim);
        g.bench_function(BenchmarkId::new(format!("fused_mlp_{name}_forward"), n), |b| {
            b.iter(|| run(&ctx, |e| net.record_forward(&ctx, e, &counters, &x, &p, &y, &tape, n.into())))
        });
        if cfg.output_dim == 16 {
            // The density pass: σ (the first output) alone.
            let mut head = FusedMlp::new(&ctx, &cfg).unwrap();
            head.set_partial(&ctx, 1, cfg.input_dim);
            g.bench_function(BenchmarkId::new(format!("fused_mlp_{name}_inference_sigma"), n), |b| {
                b.iter(|| run(&ctx, |e| head.record_inference_head(&ctx, e, &counters, &x, &p, &y, n.into())))
            });
        }
        g.bench_function(BenchmarkId::new(format!("fused_mlp_{name}_forward_backward"), n), |b| {
            b.iter(|| {
                run(&ctx, |e| {
                    net.record_forward(&ctx, e, &counters, &x, &p, &y, &tape, n.into());
                    net.record_backward(&ctx, e, &counters, &x, &p, &tape, &dy, &gr, Some(&dx), n.into());
                })
            })
        });
    }

    // The same nets through the cooperative-matrix fused MLP (adapters with cooperative matrices).
    if ctx.features.cooperative_matrix {
        for (name, cfg) in [("density_32_64_16", mlp(32, 16, 1, Activation::None)), ("color_32_64_64_3", mlp(32, 3, 2, Activation::Sigmoid))] {
            let net = FusedMlpCoop::new(&ctx, &cfg).unwrap();
            let p = ctx.upload("w", &random(net.n_params(), -0.1, 0.1, 4));
            let gr = ctx.zeros("dw", 4 * net.n_params());
            let x = ctx.upload("x", &random(n * cfg.input_dim, -1.0, 1.0, 5));
            let y = ctx.zeros("y", 4 * n * cfg.output_dim);
            let tape = ctx.zeros("tape", 4 * n * net.tape_floats_per_sample());
            let dy = ctx.upload("dy", &random(n * cfg.output_dim, -1.0, 1.0, 6));
            let dx = ctx.zeros("dx", 4 * n * cfg.input_dim);
            g.bench_function(BenchmarkId::new(format!("fused_mlp_coop_{name}_forward"), n), |b| {
                b.iter(|| run(&ctx, |e| net.record_forward(&ctx, e, &counters, &x, &p, &y, &tape, n.into())))
            });
            g.bench_function(BenchmarkId::new(format!("fused_mlp_coop_{name}_forward_backward"), n), |b| {
                b.iter(|| {
                    run(&ctx, |e| {
                        net.record_forward(&ctx, e, &counters, &x, &p, &y, &tape, n.into());
                        net.record_backward(&ctx, e, &counters, &x, &p, &tape, &dy, &gr, Some(&dx), n.into());
                    })
                })
            });
        }
    }

    // The paper's trunk (63 → 8×256 with the skip → 257), plain and cooperative matrices.
    let trunk = MlpConfig::nerf_trunk(63, 257);
    let trunk_fps = GpuMlp::new_with(&ctx, &trunk, 64, LinearPath::Plain).expect("the trunk").tape_floats_per_sample();
    let m = fit(&ctx, n / 4, 4 * trunk_fps);
    let x = ctx.upload("x", &random(m * 63, -1.0, 1.0, 7));
    let dy = ctx.upload("dy", &random(m * 257, -1e-3, 1e-3, 8));
    let y = ctx.zeros("y", 4 * m * 257);
    let mut modes = vec![LinearPath::Plain];
    if ctx.features.cooperative_matrix {
        modes.push(LinearPath::Coop);
        // The workgroup-tiled kernels need subgroups of exactly 32 (GpuMlp::new_with says so).
        if ctx.info.subgroup_min_size == 32 && ctx.info.subgroup_max_size == 32 {
            modes.push(LinearPath::CoopTiled);
            modes.push(LinearPath::CoopTiledWide);
        }
    }
    // Each cooperative-matrix path also without the hidden layers' f32 tape (`drop_hidden_tape`).
    let runs = modes.iter().flat_map(|&p| [(p, true), (p, false)]).filter(|&(p, keep)| keep || p != LinearPath::Plain);
    for (path, keep_tape) in runs {
        let mut net = GpuMlp::new_with(&ctx, &trunk, m, path).unwrap();
        if !keep_tape {
            net.drop_hidden_tape(&ctx).unwrap();
        }
        let p = ctx.upload("w", &random(net.n_params(), -0.05, 0.05, 9));
        let gr = ctx.zeros("dw", 4 * net.n_params());
        let tape = ctx.zeros("tape", 4 * m * net.tape_floats_per_sample());
        let kernels = match path {
            LinearPath::Plain => "plain",
            LinearPath::Coop => "coop",
            LinearPath::CoopTiled => "coop_tiled",
            LinearPath::CoopTiledWide => "coop_tiled_wide",
        };
        let name = format!("trunk_8x256_{kernels}{}_forward_backward", if keep_tape { "" } else { "_no_hidden_tape" });
        g.throughput(Throughput::Elements(m as u64));
        g.bench_function(BenchmarkId::new(name, m), |b| {
            b.iter(|| {
                run(&ctx, |e| {
                    net.record_forward(&ctx, e, &counters, &x, &p, &y, &tape, m);
                    net.record_backward(&ctx, e, &counters, &x, &p, &tape, &dy, &gr, None, m);
                })
            })
        });
    }

    // Adam over the hash field's parameters.
    let total = grid.n_params() + 8192;
    let adam = GpuAdam::new(&ctx, &nerf_optim::AdamConfig::instant_ngp(), &[GpuParamGroup::new("all", 0, total, 0.0)]).unwrap();
    let (p, gr) = (ctx.upload("p", &random(total, -0.1, 0.1, 10)), ctx.upload("g", &random(total, -0.1, 0.1, 11)));
    g.throughput(Throughput::Elements(total as u64));
    g.bench_function(BenchmarkId::new("adam", total), |b| b.iter(|| run(&ctx, |e| adam.record_step(&ctx, e, &p, &gr, 1e-2))));
    g.finish();
}

criterion_group!(benches, kernels);
criterion_main!(benches);
