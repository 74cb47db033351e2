use super::*;

fn cfg(
    input_dim: usize,
    output_dim: usize,
    hidden_dim: usize,
    hidden_layers: usize,
    ha: Activation,
    oa: Activation,
) -> MlpConfig {
    MlpConfig {
        input_dim,
        output_dim,
        hidden_dim,
        hidden_layers,
        hidden_activation: ha,
        output_activation: oa,
        skips: vec![],
        bias: true,
    }
}

fn random(n: usize, seed: u64, scale: f64) -> Vec<f64> {
    let mut r = nerf_core::rng(seed, 99);
    (0..n)
        .map(|_| (2.0 * r.gen::<f64>() - 1.0) * scale)
        .collect()
}

/// L = Σ g·mlp(x). Checks every parameter gradient and d_input against central differences in f64.
fn fd_check(config: MlpConfig, n: usize, seed: u64) {
    let mut rng = nerf_core::rng(seed, 0);
    let mut mlp = Mlp::<f64>::new(config.clone(), &mut rng);
    let x = random(n * config.input_dim, seed + 1, 1.0);
    let g = random(n * config.output_dim, seed + 2, 1.0);
    let mut tape = MlpTape::default();
    mlp.forward(n, &x, &mut tape);
    let mut dx = vec![f64::NAN; x.len()];
    mlp.backward(n, &x, &mut tape, &g, Some(&mut dx));
    let loss = |m: &Mlp<f64>, x: &[f64]| {
        let mut out = vec![0.0; n * config.output_dim];
        m.infer(n, x, &mut MlpScratch::default(), &mut out);
        out.iter().zip(&g).map(|(a, b)| a * b).sum::<f64>()
    };
    let h = 1e-6;
    let close = |an: f64, fd: f64| (an - fd).abs() <= 1e-8 + 1e-6 * an.abs().max(fd.abs());
    let mut worst: f64 = 0.0;
    let mut probe = mlp.clone();
    for i in 0..mlp.n_params() {
        let p0 = probe.params()[i];
        probe.params_mut()[i] = p0 + h;
        let lp = loss(&probe, &x);
        probe.params_mut()[i] = p0 - h;
        let lm = loss(&probe, &x);
        probe.params_mut()[i] = p0;
        let fd = (lp - lm) / (2.0 * h);
        let an = mlp.grads()[i];
        worst = worst.max((an - fd).abs());
        assert!(
            close(an, fd),
            "param {i}: analytic {an} vs fd {fd} ({config:?})"
        );
    }
    for i in 0..x.len() {
        let mut xp = x.clone();
        xp[i] += h;
        let mut xm = x.clone();
        xm[i] -= h;
        let fd = (loss(&mlp, &xp) - loss(&mlp, &xm)) / (2.0 * h);
        assert!(
            close(dx[i], fd),
            "d_input[{i}]: analytic {} vs fd {fd} ({config:?})",
            dx[i]
        );
    }
    // The check must not pass vacuously.
    assert!(
        mlp.grads().iter().any(|v| v.abs() > 1e-3),
        "all gradients ~0"
    );
    assert!(dx.iter().any(|v| v.abs() > 1e-3), "d_input ~0");
    let _ = worst;
}

#[test]
fn fd_single_linear_layer() {
    fd_check(cfg(4, 3, 0, 0, Activation::Relu, Activation::None), 6, 1);
}

#[test]
fn fd_relu_layer() {
    fd_check(cfg(3, 2, 7, 1, Activation::Relu, Activation::None), 8, 2);
}

#[test]
fn fd_sigmoid_layers() {
    fd_check(
        cfg(3, 2, 5, 1, Activation::Sigmoid, Activation::Sigmoid),
        7,
        3,
    );
}

#[test]
fn fd_tanh_softplus_exp() {
    fd_check(cfg(2, 3, 5, 1, Activation::Tanh, Activation::Exp), 5, 4);
    fd_check(
        cfg(2, 3, 5, 1, Activation::Softplus, Activation::Softplus),
        5,
        5,
    );
}

#[test]
fn fd_skip_connection() {
    let mut c = cfg(3, 2, 6, 2, Activation::Relu, Activation::None);
    c.skips = vec![1];
    fd_check(c, 6, 6);
}

#[test]
fn fd_three_hidden_layers_with_skip_and_no_bias() {
    let mut c = cfg(5, 4, 8, 3, Activation::Relu, Activation::Sigmoid);
    c.skips = vec![2];
    fd_check(c.clone(), 9, 7);
    c.bias = false;
    c.skips = vec![1, 2];
    fd_check(c, 9, 8);
}

#[test]
fn fd_large_batch_exercises_parallel_paths() {
    // n·width above the element-wise chunk so the rayon paths run; check a sample of parameters.
    let mut c = cfg(4, 3, 32, 2, Activation::Sigmoid, Activation::None);
    c.skips = vec![1];
    let n = 1200;
    let mut mlp = Mlp::<f64>::new(c.clone(), &mut nerf_core::rng(9, 0));
    let x = random(n * 4, 10, 1.0);
    let g = random(n * 3, 11, 1e-2);
    let mut tape = MlpTape::default();
    mlp.forward(n, &x, &mut tape);
    mlp.backward(n, &x, &mut tape, &g, None);
    let loss = |m: &Mlp<f64>| {
        let mut out = vec![0.0; n * 3];
        m.infer(n, &x, &mut MlpScratch::default(), &mut out);
        out.iter().zip(&g).map(|(a, b)| a * b).sum::<f64>()
    };
    let h = 1e-6;
    let mut probe = mlp.clone();
    for i in (0..mlp.n_params()).step_by(13) {
        let p0 = probe.params()[i];
        probe.params_mut()[i] = p0 + h;
        let lp = loss(&probe);
        probe.params_mut()[i] = p0 - h;
        let lm = loss(&probe);
        probe.params_mut()[i] = p0;
        let fd = (lp - lm) / (2.0 * h);
        let an = mlp.grads()[i];
        assert!(
            (an - fd).abs() <= 1e-8 + 1e-6 * an.abs(),
            "param {i}: {an} vs {fd}"
        );
    }
}

#[test]
fn paper_trunk_shape() {
    let c = MlpConfig::nerf_trunk(63, 257);
    let mlp = Mlp::<f32>::new(c, &mut nerf_core::rng(0, 0));
    let shapes = mlp.layer_shapes();
    assert_eq!(shapes.len(), 9);
    assert_eq!(shapes[0], (63, 256));
    assert_eq!(
        shapes[5],
        (319, 256),
        "nerf-pytorch pts_linears[5] takes [input, h]"
    );
    assert_eq!(shapes[8], (256, 257));
    for (i, s) in shapes.iter().enumerate() {
        if ![0, 5, 8].contains(&i) {
            assert_eq!(*s, (256, 256));
        }
    }
    // nerf-pytorch parameter count of pts_linears + alpha_linear + feature_linear.
    let expect = (63 * 256 + 256) + 6 * (256 * 256 + 256) + (319 * 256 + 256) + (256 * 257 + 257);
    assert_eq!(mlp.n_params(), expect);
    assert_eq!(
        mlp.flops_per_sample(),
        2 * (63 * 256 + 6 * 256 * 256 + 319 * 256 + 256 * 257)
    );
}

#[test]
fn init_is_pytorch_linear_uniform() {
    let mut c = cfg(63, 4, 256, 2, Activation::Relu, Activation::None);
    c.skips = vec![1];
    let mlp = Mlp::<f32>::new(c.clone(), &mut nerf_core::rng(5, 0));
    for ((fan_in, out), (w, b)) in mlp.layer_shapes().into_iter().zip(mlp.layer_offsets()) {
        let bound = 1.0 / (fan_in as f32).sqrt();
        let ws = &mlp.params()[w..w + fan_in * out];
        let bs = &mlp.params()[b.unwrap()..b.unwrap() + out];
        for s in [ws, bs] {
            let max = s.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            assert!(
                max <= bound,
                "fan_in {fan_in}: max |p| {max} > bound {bound}"
            );
            // Enough draws to nearly reach the bound (a too-narrow init would fail here).
            if s.len() >= 64 {
                assert!(
                    max > 0.9 * bound,
                    "fan_in {fan_in}: max |p| {max}, bound {bound}"
                );
            }
        }
        let mean = ws.iter().sum::<f32>() / ws.len() as f32;
        assert!(mean.abs() < 0.1 * bound, "weights not centred: {mean}");
    }
    // Same seed → same parameters; f64 and f32 draw the same numbers.
    let again = Mlp::<f32>::new(c.clone(), &mut nerf_core::rng(5, 0));
    assert_eq!(mlp.params(), again.params());
    let wide = Mlp::<f64>::new(c, &mut nerf_core::rng(5, 0));
    assert!(mlp
        .params()
        .iter()
        .zip(wide.params())
        .all(|(a, b)| (*a as f64 - b).abs() < 1e-7));
    assert!(mlp.grads().iter().all(|g| *g == 0.0));
}

#[test]
fn infer_equals_forward_including_from_worker_threads() {
    let c = MlpConfig {
        hidden_dim: 64,
        ..MlpConfig::nerf_trunk(27, 5)
    };
    let mlp = Mlp::<f32>::new(c, &mut nerf_core::rng(6, 0));
    let n = 1000;
    let x: Vec<f32> = random(n * 27, 12, 1.0)
        .into_iter()
        .map(|v| v as f32)
        .collect();
    let mut tape = MlpTape::default();
    let y = mlp.forward(n, &x, &mut tape).to_vec();
    let mut out = vec![f32::NAN; n * 5];
    mlp.infer(n, &x, &mut MlpScratch::default(), &mut out);
    let close = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .all(|(p, q)| (p - q).abs() <= 1e-5 * (1.0 + q.abs()))
    };
    assert!(close(&out, &y));
    // Chunks of 100 from many threads at once.
    let mut out2 = vec![f32::NAN; n * 5];
    out2.par_chunks_mut(100 * 5)
        .zip(x.par_chunks(100 * 27))
        .for_each_init(MlpScratch::default, |s, (o, xi)| {
            mlp.infer(xi.len() / 27, xi, s, o)
        });
    assert!(close(&out2, &y));
    // Output really depends on the input (not a constant).
    assert!((y[0] - y[5]).abs() > 1e-6 || (y[1] - y[6]).abs() > 1e-6);
}

#[test]
fn grads_accumulate_over_two_backward_calls() {
    let mut c = cfg(6, 3, 16, 2, Activation::Relu, Activation::None);
    c.skips = vec![1];
    let mut mlp = Mlp::<f64>::new(c, &mut nerf_core::rng(7, 0));
    let n = 20;
    let x1 = random(n * 6, 13, 1.0);
    let x2 = random(n * 6, 14, 1.0);
    let g = random(n * 3, 15, 1.0);
    let mut tape = MlpTape::default();
    let grad_of = |m: &mut Mlp<f64>, x: &[f64], tape: &mut MlpTape<f64>| {
        m.zero_grad();
        m.forward(n, x, tape);
        m.backward(n, x, tape, &g, None);
        m.grads().to_vec()
    };
    let g1 = grad_of(&mut mlp, &x1, &mut tape);
    let g2 = grad_of(&mut mlp, &x2, &mut tape);
    // Without zero_grad in between: g1 + g2.
    mlp.zero_grad();
    mlp.forward(n, &x1, &mut tape);
    mlp.backward(n, &x1, &mut tape, &g, None);
    mlp.forward(n, &x2, &mut tape);
    mlp.backward(n, &x2, &mut tape, &g, None);
    for i in 0..mlp.n_params() {
        assert!(
            (mlp.grads()[i] - (g1[i] + g2[i])).abs() <= 1e-12 * (1.0 + g1[i].abs() + g2[i].abs())
        );
    }
    assert!(g1.iter().zip(&g2).any(|(a, b)| (a - b).abs() > 1e-6));
    mlp.zero_grad();
    assert!(mlp.grads().iter().all(|v| *v == 0.0));
}

#[test]
fn tape_and_scratch_are_reused_without_reallocation() {
    let mlp = Mlp::<f32>::new(
        MlpConfig {
            hidden_dim: 32,
            ..MlpConfig::nerf_trunk(9, 4)
        },
        &mut nerf_core::rng(8, 0),
    );
    let x: Vec<f32> = random(64 * 9, 16, 1.0)
        .into_iter()
        .map(|v| v as f32)
        .collect();
    let mut tape = MlpTape::default();
    let p1 = mlp.forward(64, &x, &mut tape).as_ptr();
    let p2 = mlp.forward(32, &x[..32 * 9], &mut tape).as_ptr();
    let p3 = mlp.forward(64, &x, &mut tape).as_ptr();
    assert_eq!(p1, p2);
    assert_eq!(p1, p3);
    let mut s = MlpScratch::default();
    let mut out = vec![0.0f32; 64 * 4];
    mlp.infer(64, &x, &mut s, &mut out);
    let (a, b) = (s.a.as_ptr(), s.b.as_ptr());
    mlp.infer(16, &x[..16 * 9], &mut s, &mut out[..16 * 4]);
    mlp.infer(64, &x, &mut s, &mut out);
    assert!((s.a.as_ptr(), s.b.as_ptr()) == (a, b) || (s.a.as_ptr(), s.b.as_ptr()) == (b, a));
}

#[test]
fn f32_gradients_agree_with_f64() {
    let mut c = cfg(8, 4, 32, 3, Activation::Relu, Activation::Sigmoid);
    c.skips = vec![2];
    let m64 = Mlp::<f64>::new(c.clone(), &mut nerf_core::rng(9, 0));
    let mut m64 = m64;
    let mut m32 = Mlp::<f32>::new(c, &mut nerf_core::rng(9, 0));
    m32.params_mut()
        .iter_mut()
        .zip(m64.params())
        .for_each(|(a, b)| *a = *b as f32);
    m64.params_mut()
        .iter_mut()
        .zip(m32.params().to_vec())
        .for_each(|(a, b)| *a = b as f64);
    let n = 50;
    let x = random(n * 8, 17, 1.0);
    let g = random(n * 4, 18, 1.0);
    let (x32, g32): (Vec<f32>, Vec<f32>) = (
        x.iter().map(|v| *v as f32).collect(),
        g.iter().map(|v| *v as f32).collect(),
    );
    let (mut t64, mut t32) = (MlpTape::default(), MlpTape::default());
    m64.forward(n, &x, &mut t64);
    m32.forward(n, &x32, &mut t32);
    let mut d64 = vec![0.0; n * 8];
    let mut d32 = vec![0.0f32; n * 8];
    m64.backward(n, &x, &mut t64, &g, Some(&mut d64));
    m32.backward(n, &x32, &mut t32, &g32, Some(&mut d32));
    let scale = m64.grads().iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let err = m32
        .grads()
        .iter()
        .zip(m64.grads())
        .map(|(a, b)| (*a as f64 - b).abs())
        .fold(0.0, f64::max);
    assert!(
        err < 1e-4 * scale,
        "f32 vs f64 grads: {err} (scale {scale})"
    );
    let err = d32
        .iter()
        .zip(&d64)
        .map(|(a, b)| (*a as f64 - b).abs())
        .fold(0.0, f64::max);
    assert!(err < 1e-4, "f32 vs f64 d_input: {err}");
}

#[test]
fn config_validation_and_serde() {
    let mut rng = nerf_core::rng(0, 0);
    let mut c = cfg(3, 1, 8, 2, Activation::Relu, Activation::None);
    c.skips = vec![2];
    assert_eq!(
        Mlp::<f32>::try_new(c.clone(), &mut rng).unwrap_err(),
        MlpError::SkipOutOfRange {
            index: 2,
            hidden_layers: 2
        }
    );
    c.skips = vec![0];
    assert!(Mlp::<f32>::try_new(c.clone(), &mut rng).is_err());
    c.skips = vec![1, 1];
    assert_eq!(
        Mlp::<f32>::try_new(c.clone(), &mut rng).unwrap_err(),
        MlpError::DuplicateSkip(1)
    );
    c.skips = vec![];
    c.hidden_dim = 0;
    assert!(Mlp::<f32>::try_new(c.clone(), &mut rng)
        .unwrap_err()
        .to_string()
        .contains("hidden_dim"));
    c.hidden_layers = 0;
    assert!(
        Mlp::<f32>::try_new(c, &mut rng).is_ok(),
        "hidden_dim is unused without hidden layers"
    );
    let t = MlpConfig::nerf_trunk(63, 257);
    let json = serde_json::to_string(&t).unwrap();
    assert!(
        json.contains("\"relu\"") && json.contains("\"none\""),
        "{json}"
    );
    assert_eq!(serde_json::from_str::<MlpConfig>(&json).unwrap(), t);
}

#[test]
fn activations_and_derivatives() {
    for act in [
        Activation::None,
        Activation::Relu,
        Activation::Sigmoid,
        Activation::Tanh,
        Activation::Softplus,
        Activation::Exp,
    ] {
        for z in [-3.0f64, -0.4, 0.3, 2.5] {
            let h = 1e-6;
            let fd = (act.apply(z + h) - act.apply(z - h)) / (2.0 * h);
            let an = act.derivative_from_output(act.apply(z));
            assert!((fd - an).abs() < 1e-8, "{act:?} at {z}: {an} vs {fd}");
        }
    }
    assert_eq!(Activation::Softplus.apply(-800.0f64), 0.0);
    assert_eq!(Activation::Softplus.apply(800.0f64), 800.0);
    assert_eq!(Activation::Sigmoid.apply(-800.0f32), 0.0);
}

/// `backward_cols` gives the gradients of `backward` bit for bit, the first `cols` columns of its
/// `d_input`, and leaves the other columns as they were — in f32 (the precision the fields train
/// in), with a skip layer (two blocks that add into d_input) and with the hash field's colour net.
/// (A narrower product may go through another blocking of `gemm`, so the columns agree to rounding,
/// not bit for bit.)
#[test]
fn partial_input_gradients_match_the_full_ones() {
    let mut skip = cfg(9, 5, 24, 3, Activation::Relu, Activation::Sigmoid);
    skip.skips = vec![2];
    let color = cfg(32, 3, 64, 2, Activation::Relu, Activation::Sigmoid);
    for (seed, config) in [(11u64, skip), (13, color)] {
        let (din, dout) = (config.input_dim, config.output_dim);
        let n = 300;
        let mut rng = nerf_core::rng(seed, 0);
        let mlp = Mlp::<f32>::new(config.clone(), &mut rng);
        let x: Vec<f32> = random(n * din, seed + 1, 1.0).iter().map(|&v| v as f32).collect();
        let g: Vec<f32> = random(n * dout, seed + 2, 1.0).iter().map(|&v| v as f32).collect();
        let close = |a: f32, b: f32| (a - b).abs() <= 1e-6 * (1.0 + b.abs());
        let mut a = mlp.clone();
        let mut tape = MlpTape::default();
        a.forward(n, &x, &mut tape);
        let mut dx_full = vec![f32::NAN; n * din];
        a.backward(n, &x, &mut tape, &g, Some(&mut dx_full));
        for cols in [1, din / 2, din] {
            let mut b = mlp.clone();
            let mut tape = MlpTape::default();
            b.forward(n, &x, &mut tape);
            let mut dx = vec![f32::NAN; n * din];
            b.backward_cols(n, &x, &mut tape, &g, Some(&mut dx), cols);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(b.grads()), bits(a.grads()), "seed {seed} cols {cols}: grads");
            for r in 0..n {
                for k in 0..din {
                    let v = dx[r * din + k];
                    if k < cols {
                        let w = dx_full[r * din + k];
                        assert!(close(v, w), "seed {seed} cols {cols} [{r}][{k}]: {v} vs {w}");
                    } else {
                        assert!(v.is_nan(), "seed {seed} cols {cols}: d_input [{r}][{k}] past the columns was written");
                    }
                }
            }
        }
    }
}

/// A naive f64 twin of [`Mlp::set_f16_arithmetic`], written from its doc comment: every value that
/// the forward reads or writes rounded to f16, the backward scaled by `s` and rounded at each
/// layer, each parameter gradient and `dL/d(input)` rounded while scaled. Returns (output, grads,
/// d_input).
fn f16_reference(m: &Mlp<f64>, n: usize, x: &[f64], g: &[f64], s: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let r = |v: f64| round_f16(v);
    let c = &m.config;
    let d_in = c.input_dim;
    let w16: Vec<f64> = m.params().iter().map(|&p| r(p)).collect();
    let x16: Vec<f64> = x.iter().map(|&v| r(v)).collect();
    let shapes = m.layer_shapes();
    let offs = m.layer_offsets();
    let nl = shapes.len();
    let act = |i: usize| if i + 1 == nl { c.output_activation } else { c.hidden_activation };
    // The input of layer i for sample k: [x, h] for a skip layer, x for layer 0, else h.
    let layer_in = |i: usize, k: usize, acts: &[Vec<f64>]| -> Vec<f64> {
        let xk = &x16[k * d_in..(k + 1) * d_in];
        if i == 0 {
            return xk.to_vec();
        }
        let w = shapes[i - 1].1;
        let h = &acts[i - 1][k * w..(k + 1) * w];
        if c.skips.contains(&i) { [xk, h].concat() } else { h.to_vec() }
    };
    let mut acts: Vec<Vec<f64>> = Vec::new();
    for i in 0..nl {
        let (fan_in, out) = shapes[i];
        let (wo, bo) = offs[i];
        let mut y = vec![0.0; n * out];
        for k in 0..n {
            let inp = layer_in(i, k, &acts);
            for o in 0..out {
                let mut z: f64 = (0..fan_in).map(|j| w16[wo + o * fan_in + j] * inp[j]).sum();
                if let Some(b) = bo {
                    z += w16[b + o];
                }
                y[k * out + o] = r(act(i).apply(z));
            }
        }
        acts.push(y);
    }
    let mut dw = vec![0.0; m.n_params()];
    let mut dx = vec![0.0; n * d_in];
    let out_l = shapes[nl - 1].1;
    let mut dz: Vec<f64> = (0..n * out_l)
        .map(|q| r(r(g[q] * s) * act(nl - 1).derivative_from_output(acts[nl - 1][q])))
        .collect();
    for i in (0..nl).rev() {
        let (fan_in, out) = shapes[i];
        let (wo, bo) = offs[i];
        let x_cols = if i == 0 || c.skips.contains(&i) { d_in } else { 0 };
        let mut dh = vec![0.0; if i > 0 { n * shapes[i - 1].1 } else { 0 }];
        for k in 0..n {
            let inp = layer_in(i, k, &acts);
            for o in 0..out {
                let d = dz[k * out + o];
                for j in 0..fan_in {
                    dw[wo + o * fan_in + j] += d * inp[j];
                }
                if let Some(b) = bo {
                    dw[b + o] += d;
                }
            }
            for j in 0..fan_in {
                let v: f64 = (0..out).map(|o| dz[k * out + o] * w16[wo + o * fan_in + j]).sum();
                if j < x_cols {
                    dx[k * d_in + j] += v;
                } else {
                    let hw = shapes[i - 1].1;
                    let jj = j - x_cols;
                    let y = acts[i - 1][k * hw + jj];
                    dh[k * hw + jj] = r(r(v) * act(i - 1).derivative_from_output(y));
                }
            }
        }
        dz = dh;
    }
    let out = acts.pop().unwrap();
    (out, dw.iter().map(|&v| r(v) / s).collect(), dx.iter().map(|&v| r(v) / s).collect())
}

#[test]
fn f16_arithmetic_matches_its_naive_twin() {
    // tiny-cuda-nn's shape (no biases, ReLU, a linear output) and one with biases, a skip layer
    // and a sigmoid output; n large enough for the parallel element-wise passes (> 2^14 values).
    let mut skip = cfg(7, 3, 24, 3, Activation::Relu, Activation::Sigmoid);
    skip.skips = vec![2];
    let mut plain = cfg(32, 16, 64, 1, Activation::Relu, Activation::None);
    plain.bias = false;
    for (case, (c, n, s)) in [(plain, 300, 128.0), (skip, 700, 1024.0)].into_iter().enumerate() {
        let mut m = Mlp::<f64>::new(c.clone(), &mut nerf_core::rng(40 + case as u64, 0));
        m.set_f16_arithmetic(Some(s as f32));
        let x = random(n * c.input_dim, 41 + case as u64, 1.0);
        // Gradients of the size a loss over many samples hands an MLP (~1e-4), so that some of
        // the scaled products reach f16's subnormals.
        let g = random(n * c.output_dim, 42 + case as u64, 1e-4);
        let (y_ref, gw_ref, dx_ref) = f16_reference(&m, n, &x, &g, s);
        let mut tape = MlpTape::default();
        let y = m.forward(n, &x, &mut tape).to_vec();
        let mut dx = vec![f64::NAN; x.len()];
        m.backward(n, &x, &mut tape, &g, Some(&mut dx));
        // f64 products that differ from the naive sums in the last bits round to the same f16.
        assert_eq!(y, y_ref, "case {case}: forward");
        assert_eq!(m.grads(), &gw_ref[..], "case {case}: parameter gradients");
        assert_eq!(dx, dx_ref, "case {case}: input gradients");
        // The rounding happened: every output is an f16, and not every one equals the full
        // precision output.
        assert!(y.iter().all(|&v| round_f16(v) == v));
        let mut full = m.clone();
        full.set_f16_arithmetic(None);
        let y_full = full.forward(n, &x, &mut MlpTape::default()).to_vec();
        let moved = y.iter().zip(&y_full).filter(|(a, b)| a != b).count();
        assert!(moved > y.len() / 2, "case {case}: only {moved} of {} outputs changed", y.len());
        let worst = y.iter().zip(&y_full).map(|(a, b)| (a - b).abs() / b.abs().max(0.1)).fold(0.0, f64::max);
        assert!(worst < 2e-2, "case {case}: f16 output {worst} from the f32 one (relative)");
        // Inference reads and rounds as the training forward does.
        let mut inf = vec![f64::NAN; y.len()];
        m.infer(n, &x, &mut MlpScratch::default(), &mut inf);
        assert_eq!(inf, y, "case {case}: infer");
    }
}

#[test]
fn f16_arithmetic_loses_gradients_below_its_range_unless_scaled() {
    let mut c = cfg(16, 4, 32, 2, Activation::Relu, Activation::None);
    c.bias = false;
    let n = 64;
    let x: Vec<f32> = random(n * 16, 51, 1.0).iter().map(|&v| v as f32).collect();
    let g: Vec<f32> = random(n * 4, 52, 1.0).iter().map(|&v| v as f32).collect();
    // The same gradients 2^30 times smaller (exactly): ~1e-9, below f16's smallest subnormal
    // (5.96e-8) unless scaled.
    let tiny = 2f32.powi(-30);
    let g_tiny: Vec<f32> = g.iter().map(|&v| v * tiny).collect();
    let grads = |g: &[f32], scale: Option<f32>| {
        let mut m = Mlp::<f32>::new(c.clone(), &mut nerf_core::rng(50, 0));
        m.set_f16_arithmetic(scale);
        let mut tape = MlpTape::default();
        m.forward(n, &x, &mut tape);
        let mut dx = vec![f32::NAN; x.len()];
        m.backward(n, &x, &mut tape, g, Some(&mut dx));
        (m.grads().to_vec(), dx)
    };
    let (g_lost, dx_lost) = grads(&g_tiny, Some(1.0));
    assert!(g_lost.iter().chain(&dx_lost).all(|&v| v == 0.0), "unscaled f16 kept a gradient of ~1e-9");
    // Scaled by 2^30 they are the unit-sized gradients' f16 sums bit for bit, scaled back.
    let (g_unit, dx_unit) = grads(&g, Some(1.0));
    let (g_kept, dx_kept) = grads(&g_tiny, Some(1.0 / tiny));
    let back = |v: &[f32]| v.iter().map(|&v| v * tiny).collect::<Vec<_>>();
    assert_eq!(g_kept, back(&g_unit));
    assert_eq!(dx_kept, back(&dx_unit));
    assert!(g_kept.iter().any(|&v| v != 0.0));
    // Near the f32 gradients: f16's rounding, and the few ReLUs whose sign the rounding of a
    // pre-activation near 0 flips (each drops or adds a whole sample's term; here 2.6 %).
    let (g_full, dx_full) = grads(&g, None);
    for (name, kept, full) in [("params", &g_unit, &g_full), ("input", &dx_unit, &dx_full)] {
        let norm = full.iter().map(|v| v * v).sum::<f32>().sqrt();
        let err = kept.iter().zip(full).map(|(a, b)| (a - b) * (a - b)).sum::<f32>().sqrt();
        assert!(norm > 0.0 && err < 5e-2 * norm, "{name}: f16 gradients {err} from the f32 ones (norm {norm})");
    }
}

#[test]
fn f16_arithmetic_turned_off_is_the_plain_mlp() {
    let c = cfg(8, 4, 16, 2, Activation::Relu, Activation::Sigmoid);
    let n = 40;
    let x: Vec<f32> = random(n * 8, 61, 1.0).iter().map(|&v| v as f32).collect();
    let g: Vec<f32> = random(n * 4, 62, 1.0).iter().map(|&v| v as f32).collect();
    let run = |m: &mut Mlp<f32>| {
        let mut tape = MlpTape::default();
        let y = m.forward(n, &x, &mut tape).to_vec();
        m.backward(n, &x, &mut tape, &g, None);
        (y, m.grads().to_vec())
    };
    let mut plain = Mlp::<f32>::new(c.clone(), &mut nerf_core::rng(60, 0));
    let mut toggled = plain.clone();
    toggled.set_f16_arithmetic(Some(128.0));
    assert_eq!(toggled.f16_arithmetic(), Some(128.0));
    let (y16, _) = run(&mut toggled);
    toggled.zero_grad();
    toggled.set_f16_arithmetic(None);
    let (y, gr) = run(&mut toggled);
    assert_eq!((y.clone(), gr), run(&mut plain), "off again, the MLP computes what it did before");
    assert_ne!(y, y16);
}

#[test]
#[should_panic(expected = "loss scale")]
fn f16_arithmetic_refuses_a_bad_loss_scale() {
    Mlp::<f32>::new(cfg(2, 1, 4, 1, Activation::Relu, Activation::None), &mut nerf_core::rng(0, 0)).set_f16_arithmetic(Some(0.0));
}

#[test]
fn f32_rounding_to_f16_is_the_f64_one() {
    let mut r = nerf_core::rng(70, 0);
    let mut xs: Vec<f32> = (0..20_000).map(|_| (2.0 * r.gen::<f32>() - 1.0) * 10f32.powi(r.gen_range(-9..6))).collect();
    // Ties (halfway between two f16s), f16's subnormals and its overflow.
    xs.extend([1.0 + 2f32.powi(-11), 1.0 + 3.0 * 2f32.powi(-11), 3e-8, 5.96e-8, 65504.0, 65520.0, 1e6, -1e6, 0.0, -0.0]);
    for x in xs {
        let (a, b) = (round_f16(x), round_f16(x as f64) as f32);
        assert!(a == b && a.is_sign_negative() == b.is_sign_negative(), "{x}: f32 path {a}, f64 path {b}");
    }
}
