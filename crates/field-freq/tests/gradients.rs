//! Whole-field finite-difference checks in f64, and the paper's dimensions.

use nerf_core::Real;
use nerf_field_freq::{FreqNerf, FreqNerfConfig};
use rand::Rng as _;

fn small() -> FreqNerfConfig {
    FreqNerfConfig {
        pos_frequencies: 3,
        dir_frequencies: 2,
        width: 12,
        depth: 4,
        skips: vec![1],
        view_width: 6,
        weight_decay: 0.0,
        gpu_linear: Default::default(),
        gpu_hidden_tape: None,
    }
}

/// L = Σ a_k σ_k + Σ b_k rgb_k for fixed random a, b; its gradient w.r.t. the parameters is what
/// `backward_t(a, b)` must accumulate.
fn loss(f: &mut FreqNerf<f64>, pos: &[f64], dirs: &[f64], a: &[f64], b: &[f64]) -> f64 {
    let n = pos.len() / 3;
    let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
    f.query_t(pos, dirs, &mut s, &mut c);
    s.iter().zip(a).map(|(x, y)| x * y).sum::<f64>() + c.iter().zip(b).map(|(x, y)| x * y).sum::<f64>()
}

#[test]
fn whole_field_backward_matches_finite_differences_f64() {
    let mut f = FreqNerf::<f64>::new(small(), 3).unwrap();
    let mut rng = nerf_core::rng(11, 0);
    let n = 9;
    let pos: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.2..1.2)).collect();
    let mut dirs: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    for d in dirs.chunks_mut(3) {
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.iter_mut().for_each(|x| *x /= l);
    }
    let a: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let b: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();

    // Make sure σ is active on most samples so the density path is exercised: shift the σ bias.
    {
        let [trunk, _] = f.networks_mut();
        let (p, _) = trunk.params_and_grads_mut();
        let last = p.len() - (1 + 12); // output bias block starts here (σ is its first entry)
        p[last] = 0.5;
    }
    let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
    f.forward_t(&pos, &dirs, &mut s, &mut c);
    assert!(s.iter().filter(|&&x| x > 0.0).count() >= n / 2, "σ mostly active: {s:?}");
    for m in f.networks_mut() {
        m.zero_grad();
    }
    f.backward_t(&a, &b);
    let grads: Vec<Vec<f64>> = f.networks().iter().map(|m| m.grads().to_vec()).collect();

    let h = 1e-6;
    let mut checked = 0;
    for net in 0..2 {
        let len = f.networks()[net].n_params();
        // every parameter of the small field
        for i in 0..len {
            let orig = f.networks()[net].params()[i];
            f.networks_mut()[net].params_mut()[i] = orig + h;
            let lp = loss(&mut f, &pos, &dirs, &a, &b);
            f.networks_mut()[net].params_mut()[i] = orig - h;
            let lm = loss(&mut f, &pos, &dirs, &a, &b);
            f.networks_mut()[net].params_mut()[i] = orig;
            let fd = (lp - lm) / (2.0 * h);
            let g = grads[net][i];
            assert!((fd - g).abs() <= 1e-6 + 1e-5 * g.abs().max(fd.abs()), "net {net} param {i}: fd {fd} vs analytic {g}");
            checked += 1;
        }
    }
    assert!(checked > 500, "checked {checked} parameters");
}

/// `backward_inputs_t`: the gradients in the samples' positions and directions (through the
/// trunk with its skip, the colour net and both frequency encodings) against central
/// differences in f64, and the parameter gradients equal to those of `backward_t`.
#[test]
fn input_gradients_match_finite_differences_f64() {
    let mut f = FreqNerf::<f64>::new(small(), 4).unwrap();
    let mut twin = FreqNerf::<f64>::new(small(), 4).unwrap();
    let mut rng = nerf_core::rng(12, 0);
    let n = 7;
    let pos: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.2..1.2)).collect();
    let mut dirs: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    for d in dirs.chunks_mut(3) {
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        d.iter_mut().for_each(|x| *x /= l);
    }
    let a: Vec<f64> = (0..n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let b: Vec<f64> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    for net in [&mut f, &mut twin] {
        let [trunk, _] = net.networks_mut();
        let (p, _) = trunk.params_and_grads_mut();
        let last = p.len() - (1 + 12);
        p[last] = 0.5; // σ active on most samples
    }
    let (mut s, mut c) = (vec![0.0; n], vec![0.0; 3 * n]);
    twin.forward_t(&pos, &dirs, &mut s, &mut c);
    twin.backward_t(&a, &b);
    f.forward_t(&pos, &dirs, &mut s, &mut c);
    let (mut dp, mut dd) = (vec![f64::NAN; 3 * n], vec![f64::NAN; 3 * n]);
    f.backward_inputs_t(&a, &b, Some((&mut dp, &mut dd)));
    for net in 0..2 {
        assert_eq!(f.networks()[net].grads(), twin.networks()[net].grads(), "net {net}: parameter gradients differ");
    }
    let h = 1e-6;
    for (which, grad) in [("position", &dp), ("direction", &dd)] {
        for i in 0..3 * n {
            let (mut pp, mut pm, mut dp_, mut dm) = (pos.clone(), pos.clone(), dirs.clone(), dirs.clone());
            if which == "position" {
                pp[i] += h;
                pm[i] -= h;
            } else {
                dp_[i] += h;
                dm[i] -= h;
            }
            let fd = (loss(&mut f, &pp, &dp_, &a, &b) - loss(&mut f, &pm, &dm, &a, &b)) / (2.0 * h);
            let g = grad[i];
            assert!((fd - g).abs() <= 1e-6 + 1e-5 * fd.abs().max(g.abs()), "{which}[{i}]: fd {fd} vs analytic {g}");
        }
        assert!(grad.iter().filter(|g| g.abs() > 1e-3).count() > n, "{which} gradients are suspiciously small");
    }
}

#[test]
fn paper_dimensions_and_parameter_count() {
    let f = FreqNerf::<f32>::new(FreqNerfConfig::default(), 0).unwrap();
    let [trunk, color] = f.networks();
    // nerf-pytorch NeRF(D=8, W=256, input_ch=63, input_ch_views=27, skips=[4], use_viewdirs=True)
    let expected_trunk = 63 * 256 + 256 + 3 * (256 * 256 + 256) + (256 * 256 + 256) // layers 0..4
        + (319 * 256 + 256)                                                           // layer 5 (skip)
        + 2 * (256 * 256 + 256)                                                       // layers 6, 7
        + (256 + 1) + (256 * 256 + 256); // alpha_linear + feature_linear (fused as 257 outputs)
    assert_eq!(trunk.n_params(), expected_trunk);
    let expected_color = (283 * 128 + 128) + (128 * 3 + 3);
    assert_eq!(color.n_params(), expected_color);
    // nerf-pytorch reports 595,844 parameters for this network.
    assert_eq!(f.n_params(), 595_844);
    assert_eq!(<f32 as Real>::c(1.0), 1.0);
}

#[test]
fn invalid_configs_are_rejected_with_a_message() {
    let c = FreqNerfConfig { skips: vec![7], ..FreqNerfConfig::default() };
    let e = FreqNerf::<f32>::new(c, 0).err().unwrap().to_string();
    assert!(e.contains("skip"), "{e}");
    let e = nerf_field_freq::build(&serde_json::json!({"widht": 3}), &nerf_field::FieldContext {
        aabb_min: [-1.0; 3],
        aabb_max: [1.0; 3],
        seed: 0,
        scene_scale: 1.0,
    })
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("widht"), "{e}");
}

#[test]
fn query_equals_forward_and_density_equals_query_sigma() {
    use nerf_field::RadianceField;
    let mut f = FreqNerf::<f32>::new(small(), 5).unwrap();
    let mut rng = nerf_core::rng(2, 0);
    let n = 40_000; // > one query chunk
    let pos: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.5..1.5)).collect();
    let dirs: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let (mut s1, mut c1) = (vec![0.0; n], vec![0.0; 3 * n]);
    let (mut s2, mut c2) = (vec![f32::NAN; n], vec![f32::NAN; 3 * n]);
    let mut s3 = vec![f32::NAN; n];
    RadianceField::forward(&mut f, &pos, &dirs, &mut s1, &mut c1);
    f.query(&pos, &dirs, &mut s2, &mut c2);
    f.density(&pos, &mut s3);
    let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + x.abs()));
    assert!(close(&s1, &s2) && close(&c1, &c2) && close(&s2, &s3));
}

#[test]
fn queries_reusing_their_buffers_equal_those_of_a_fresh_field() {
    use nerf_field::RadianceField;
    // `query` and `density` keep their inference buffers between calls: after larger and
    // smaller calls each answer must still be the bits of a field that never answered before.
    let mut rng = nerf_core::rng(8, 0);
    let n = 20_000; // > one query chunk
    let pos: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.5..1.5)).collect();
    let dirs: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let ask = |f: &FreqNerf<f32>, a: usize, b: usize| {
        let (mut s, mut c, mut d) = (vec![f32::NAN; b - a], vec![f32::NAN; 3 * (b - a)], vec![f32::NAN; b - a]);
        f.query(&pos[3 * a..3 * b], &dirs[3 * a..3 * b], &mut s, &mut c);
        f.density(&pos[3 * a..3 * b], &mut d);
        (s, c, d)
    };
    let f = FreqNerf::<f32>::new(small(), 6).unwrap();
    for (a, b) in [(0, n), (0, 50), (3, 4_003), (0, n), (n - 1, n)] {
        assert!(ask(&f, a, b) == ask(&FreqNerf::<f32>::new(small(), 6).unwrap(), a, b), "samples {a}..{b}");
    }
}
