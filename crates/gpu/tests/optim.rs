//! `GpuAdam` against its CPU twin `nerf_optim::Adam` (runs on any adapter: lavapipe in CI; prints
//! a notice and returns where no adapter exists).

use nerf_gpu::optim::{GpuAdam, GpuParamGroup};
use nerf_gpu::GpuContext;
use nerf_optim::{Adam, AdamConfig, AdamState, Ema, ParamGroupMut};
use rand::Rng as _;

fn context() -> Option<GpuContext> {
    GpuContext::for_tests()
}

/// Largest |a − b| / max(|b|, 1e-3) over two slices.
fn max_rel(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(x, y)| (x - y).abs() / y.abs().max(1e-3)).fold(0.0, |m, e| if e.is_nan() { f32::INFINITY } else { m.max(e) })
}

/// Layout with a hole between groups (never touched) and groups given out of offset order.
fn layout(sizes: &[usize], wds: &[f32]) -> (Vec<GpuParamGroup>, usize) {
    let mut groups = vec![];
    let mut off = 3; // a few leading parameters that belong to no group
    for (i, (&n, &wd)) in sizes.iter().zip(wds).enumerate() {
        groups.push(GpuParamGroup::new(format!("g{i}"), off, n, wd));
        off += n + 5;
    }
    groups.reverse();
    (groups, off)
}

/// `steps` steps of `GpuAdam` (with an EMA of decay `ema` when given) against `Adam` (+ `Ema`).
#[allow(clippy::too_many_arguments)]
fn run_case(ctx: &GpuContext, seed: u64, cfg: AdamConfig, sizes: &[usize], wds: &[f32], steps: usize, ema: Option<f32>) {
    let mut rng = nerf_core::rng(seed, 0);
    let (groups, extent) = layout(sizes, wds);
    let adam = GpuAdam::with_ema(ctx, &cfg, &groups, ema).unwrap();
    assert_eq!(adam.ema_decay(), ema);
    assert_eq!(adam.ema_buffer().is_some(), ema.is_some());
    assert_eq!(adam.extent(), extent - 5);
    let extent = adam.extent();
    let mut p: Vec<f32> = (0..extent).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let p_buf = ctx.upload("params", &p);
    let g_buf = ctx.zeros("grads", 4 * extent);
    let mut cpu = Adam::new(cfg);
    let mut cpu_ema = ema.map(Ema::new);
    // Poisoned: the first update must not read the previous values (ema = p exactly).
    if let Some(buf) = adam.ema_buffer() {
        ctx.write(buf, 0, &vec![f32::NAN; extent]);
    }
    for step in 0..steps {
        // Random gradients, some tiny, some large, some exactly zero.
        let g: Vec<f32> = (0..extent)
            .map(|i| match (i + step) % 4 {
                0 => rng.gen_range(-1.0f32..1.0),
                1 => rng.gen_range(-1e-4f32..1e-4),
                2 => rng.gen_range(-50.0f32..50.0),
                _ => 0.0,
            })
            .collect();
        ctx.write(&g_buf, 0, &g);
        let lr = 1e-2 * (1.0 + step as f32);
        let mut enc = ctx.encoder("adam");
        adam.record_step(ctx, &mut enc, &p_buf, &g_buf, lr);
        ctx.queue.submit([enc.finish()]);
        // CPU: each group's slice of the flat buffers, in the groups' order.
        let mut g_cpu = g.clone();
        let mut order: Vec<&GpuParamGroup> = groups.iter().collect();
        order.sort_by_key(|g| g.offset);
        let mut cpu_groups: Vec<ParamGroupMut<'_>> = vec![];
        let (mut prest, mut grest) = (&mut p[..], &mut g_cpu[..]);
        let mut pos = 0;
        for grp in order {
            let (_, pr) = prest.split_at_mut(grp.offset - pos);
            let (_, gr) = grest.split_at_mut(grp.offset - pos);
            let (pg, pr) = pr.split_at_mut(grp.len);
            let (gg, gr) = gr.split_at_mut(grp.len);
            cpu_groups.push(ParamGroupMut { name: &grp.name, params: pg, grads: gg, weight_decay: grp.weight_decay });
            prest = pr;
            grest = gr;
            pos = grp.offset + grp.len;
        }
        cpu.step(&mut cpu_groups, lr);
        if let Some(e) = cpu_ema.as_mut() {
            e.update(&cpu_groups);
        }
        drop(cpu_groups);
        let p_gpu = ctx.read_f32(&p_buf, extent).unwrap();
        if let (Some(buf), Some(e)) = (adam.ema_buffer(), &cpu_ema) {
            let got = ctx.read_f32(buf, extent).unwrap();
            for grp in &groups {
                let got = &got[grp.offset..grp.offset + grp.len];
                if step == 0 {
                    assert_eq!(got, &p_gpu[grp.offset..grp.offset + grp.len], "first EMA of {} is not p", grp.name);
                }
                // The parameters' own error (≤ 1e-5 relative, below) plus FMA contraction of the
                // two-term average; relative to max(|·|, 1e-3) as for the parameters.
                let err = max_rel(got, e.values(&grp.name).unwrap());
                assert!(err < 2e-5, "seed {seed} step {step}: EMA of {} rel. error {err}", grp.name);
            }
            // Outside every group: never written (still the poison).
            assert!(got[..3].iter().all(|x| x.is_nan()));
            assert_eq!(adam.ema_step_count(), step as u64 + 1);
        }
        // Same f32 formula; only FMA contraction and the device's sqrt and division differ
        // (Vulkan allows 2.5 ulp for division and sqrt; the H100 measured 2.0e-6 relative after
        // one step), compounded over a few steps.
        let e = max_rel(&p_gpu, &p);
        assert!(e < 1e-5, "seed {seed} step {step}: params rel. error {e}");
        let g_gpu = ctx.read_f32(&g_buf, extent).unwrap();
        for grp in &groups {
            assert!(g_gpu[grp.offset..grp.offset + grp.len].iter().all(|&x| x == 0.0), "grads of {} not zeroed", grp.name);
        }
        // Parameters and gradients outside every group are untouched.
        assert_eq!(g_gpu[..3], g[..3]);
        for w in [&p_gpu[..3], &p[..3]] {
            assert!(w.iter().all(|x| x.is_finite()));
        }
        assert_eq!(p_gpu[..3], p[..3]);
    }
    assert_eq!(adam.step_count(), steps as u64);
    // Moments match the CPU state too.
    let s_gpu = adam.state(ctx).unwrap();
    let s_cpu = cpu.state();
    assert_eq!(s_gpu.step, s_cpu.step);
    for (name, m, v) in &s_cpu.groups {
        let (_, gm, gv) = s_gpu.groups.iter().find(|(n, _, _)| n == name).unwrap();
        assert!(max_rel(gm, m) < 1e-6 && max_rel(gv, v) < 1e-6, "moments of {name}");
    }
    // Per-entry step counts of sparse groups: exactly the CPU's.
    assert_eq!(s_gpu.steps.len(), s_cpu.steps.len());
    for (name, n) in &s_cpu.steps {
        let (_, gn) = s_gpu.steps.iter().find(|(g, _)| g == name).unwrap();
        assert_eq!(gn, n, "step counts of {name}");
        // Every entry's gradient is exactly zero one step in four (see the gradients above).
        assert!(n.iter().all(|&k| k > 0 && (k as usize) < steps), "{name}: zero gradients were not skipped");
    }
}

/// tiny-cuda-nn's sparse Adam on some groups (zero-gradient entries skipped, per-entry bias
/// correction from the host's f64 table) beside dense groups, with and without the EMA.
#[test]
fn sparse_groups_match_the_cpu_adam() {
    let Some(ctx) = context() else { return };
    let cfg = AdamConfig { sparse_groups: vec!["g0".into(), "g2".into()], ..AdamConfig::instant_ngp() };
    run_case(&ctx, 5, cfg.clone(), &[1000, 37, 70_000], &[0.0, 1e-2, 1e-3], 6, None);
    run_case(&ctx, 6, cfg, &[513, 300], &[0.0, 0.0], 4, Some(0.95));
}

#[test]
fn adam_matches_the_cpu_over_several_steps_with_weight_decay_groups() {
    let Some(ctx) = context() else { return };
    run_case(&ctx, 1, AdamConfig::default(), &[1000, 37, 4096], &[0.0, 1e-2, 1e-6], 5, None);
    run_case(&ctx, 2, AdamConfig::instant_ngp(), &[70_000, 1], &[0.0, 0.1], 4, None);
    run_case(&ctx, 3, AdamConfig { beta1: 0.5, beta2: 0.9, eps: 1e-3, sparse_groups: vec![] }, &[513, 0, 300], &[1e-3, 0.0, 0.0], 3, None);
}

#[test]
fn adam_with_ema_matches_the_cpu_adam_and_ema() {
    let Some(ctx) = context() else { return };
    run_case(&ctx, 11, AdamConfig::instant_ngp(), &[1000, 37, 4096], &[0.0, 1e-2, 1e-6], 6, Some(0.95));
    run_case(&ctx, 12, AdamConfig::instant_ngp(), &[70_000, 1], &[0.0, 0.1], 4, Some(0.5));
    run_case(&ctx, 13, AdamConfig::default(), &[513, 0, 300], &[1e-3, 0.0, 0.0], 5, Some(0.99));
}

#[test]
fn ema_state_round_trips_and_bad_ema_states_are_rejected() {
    let Some(ctx) = context() else { return };
    let mut rng = nerf_core::rng(21, 0);
    let cfg = AdamConfig::instant_ngp();
    let groups = vec![GpuParamGroup::new("a", 0, 100, 0.0), GpuParamGroup::new("b", 100, 30, 0.0)];
    let adam = GpuAdam::with_ema(&ctx, &cfg, &groups, Some(0.9)).unwrap();
    assert_eq!(adam.ema_state(&ctx).unwrap().unwrap().step, 0);
    let p: Vec<f32> = (0..130).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let p_buf = ctx.upload("p", &p);
    let g_buf = ctx.zeros("g", 4 * 130);
    for _ in 0..3 {
        let g: Vec<f32> = (0..130).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
        ctx.write(&g_buf, 0, &g);
        let mut enc = ctx.encoder("adam");
        adam.record_step(&ctx, &mut enc, &p_buf, &g_buf, 1e-2);
        ctx.queue.submit([enc.finish()]);
    }
    let s = adam.ema_state(&ctx).unwrap().unwrap();
    assert_eq!(s.step, 3);
    assert_eq!(s.groups.iter().map(|(n, v)| (n.as_str(), v.len())).collect::<Vec<_>>(), [("a", 100), ("b", 30)]);
    // Three steps of size ~1e-2 from p: the average moved, and lags the parameters.
    let p_now = ctx.read_f32(&p_buf, 130).unwrap();
    let all: Vec<f32> = s.groups.iter().flat_map(|(_, v)| v.clone()).collect();
    assert!(all.iter().zip(&p_now).any(|(e, x)| e != x));
    // Into a fresh optimiser: the same values come back; the next step continues from them.
    let other = GpuAdam::with_ema(&ctx, &cfg, &groups, Some(0.9)).unwrap();
    other.load_ema_state(&ctx, &s).unwrap();
    assert_eq!(other.ema_state(&ctx).unwrap().unwrap(), s);
    let mut cpu = Ema::new(0.9);
    cpu.load_state(s.clone()).unwrap();
    let p2 = ctx.upload("p2", &p_now);
    let g2 = ctx.zeros("g2", 4 * 130); // zero gradient: Adam leaves p (almost: m ≠ 0) — compare to the device p
    let mut enc = ctx.encoder("adam");
    other.record_step(&ctx, &mut enc, &p2, &g2, 1e-2);
    ctx.queue.submit([enc.finish()]);
    let mut p_after = ctx.read_f32(&p2, 130).unwrap();
    let mut gz = vec![0.0f32; 130];
    {
        let (pa, pb) = p_after.split_at_mut(100);
        let (ga, gb) = gz.split_at_mut(100);
        cpu.update(&[
            ParamGroupMut { name: "a", params: pa, grads: ga, weight_decay: 0.0 },
            ParamGroupMut { name: "b", params: pb, grads: gb, weight_decay: 0.0 },
        ]);
    }
    let got = other.ema_state(&ctx).unwrap().unwrap();
    assert_eq!(got.step, 4);
    for (name, v) in &got.groups {
        let e = max_rel(v, cpu.values(name).unwrap());
        assert!(e < 1e-6, "{name}: rel. error {e}");
    }
    // Bad states: a missing group, a wrong length, a NaN; an optimiser without an EMA.
    let missing = nerf_optim::EmaState { step: 2, groups: vec![("a".into(), vec![0.0; 100])] };
    assert!(other.load_ema_state(&ctx, &missing).unwrap_err().to_string().contains("\"b\""));
    let short = nerf_optim::EmaState { step: 2, groups: vec![("a".into(), vec![0.0; 99]), ("b".into(), vec![0.0; 30])] };
    assert!(other.load_ema_state(&ctx, &short).is_err());
    let nan = nerf_optim::EmaState { step: 2, groups: vec![("a".into(), vec![f32::NAN; 100]), ("b".into(), vec![0.0; 30])] };
    assert!(other.load_ema_state(&ctx, &nan).is_err());
    assert_eq!(other.ema_step_count(), 4);
    let plain = GpuAdam::new(&ctx, &cfg, &groups).unwrap();
    assert!(plain.load_ema_state(&ctx, &s).is_err());
    assert_eq!(plain.ema_state(&ctx).unwrap(), None);
    assert!(GpuAdam::with_ema(&ctx, &cfg, &groups, Some(1.0)).is_err());
}

#[test]
fn state_round_trips_through_the_cpu_optimiser() {
    let Some(ctx) = context() else { return };
    let mut rng = nerf_core::rng(9, 0);
    let cfg = AdamConfig::instant_ngp();
    let groups = vec![GpuParamGroup::new("a", 0, 100, 0.0), GpuParamGroup::new("b", 100, 30, 1e-2)];
    // A CPU optimiser takes 3 steps; its state is loaded into the GPU one.
    let mut p: Vec<f32> = (0..130).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let mut cpu = Adam::new(cfg.clone());
    for _ in 0..3 {
        let mut g: Vec<f32> = (0..130).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
        let (pa, pb) = p.split_at_mut(100);
        let (ga, gb) = g.split_at_mut(100);
        cpu.step(
            &mut [
                ParamGroupMut { name: "a", params: pa, grads: ga, weight_decay: 0.0 },
                ParamGroupMut { name: "b", params: pb, grads: gb, weight_decay: 1e-2 },
            ],
            1e-2,
        );
    }
    let adam = GpuAdam::new(&ctx, &cfg, &groups).unwrap();
    adam.load_state(&ctx, &cpu.state()).unwrap();
    assert_eq!(adam.step_count(), 3);
    let p_buf = ctx.upload("p", &p);
    let mut g: Vec<f32> = (0..130).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let g_buf = ctx.upload("g", &g);
    let mut enc = ctx.encoder("adam");
    adam.record_step(&ctx, &mut enc, &p_buf, &g_buf, 1e-2);
    ctx.queue.submit([enc.finish()]);
    {
        let (pa, pb) = p.split_at_mut(100);
        let (ga, gb) = g.split_at_mut(100);
        cpu.step(
            &mut [
                ParamGroupMut { name: "a", params: pa, grads: ga, weight_decay: 0.0 },
                ParamGroupMut { name: "b", params: pb, grads: gb, weight_decay: 1e-2 },
            ],
            1e-2,
        );
    }
    let e = max_rel(&ctx.read_f32(&p_buf, 130).unwrap(), &p);
    assert!(e < 1e-6, "after loading the CPU state: rel. error {e}");
    let s = adam.state(&ctx).unwrap();
    assert_eq!(s.step, 4);
    assert_eq!(s.groups.len(), 2);
    // A fresh GPU optimiser (no state) gives a different step: the loaded moments mattered.
    let fresh = GpuAdam::new(&ctx, &cfg, &groups).unwrap();
    let p2 = ctx.upload("p2", &p);
    let g2 = ctx.upload("g2", &vec![0.5f32; 130]);
    let p3 = ctx.upload("p3", &p);
    let g3 = ctx.upload("g3", &vec![0.5f32; 130]);
    let mut enc = ctx.encoder("adam");
    fresh.record_step(&ctx, &mut enc, &p2, &g2, 1e-2);
    ctx.queue.submit([enc.finish()]);
    let mut enc = ctx.encoder("adam");
    adam.record_step(&ctx, &mut enc, &p3, &g3, 1e-2);
    ctx.queue.submit([enc.finish()]);
    assert_ne!(ctx.read_f32(&p2, 130).unwrap(), ctx.read_f32(&p3, 130).unwrap());
}

#[test]
fn bad_groups_and_bad_states_are_rejected() {
    let Some(ctx) = context() else { return };
    let cfg = AdamConfig::default();
    let e = GpuAdam::new(&ctx, &cfg, &[GpuParamGroup::new("a", 0, 10, 0.0), GpuParamGroup::new("b", 9, 4, 0.0)]).err().unwrap();
    assert!(e.to_string().contains("overlap") && e.to_string().contains("\"a\""), "{e}");
    let e = GpuAdam::new(&ctx, &cfg, &[GpuParamGroup::new("a", 0, 10, f32::NAN)]).err().unwrap();
    assert!(e.to_string().contains("\"a\""), "{e}");
    let adam = GpuAdam::new(&ctx, &cfg, &[GpuParamGroup::new("w", 0, 3, 0.0)]).unwrap();
    let bad = nerf_optim::AdamState { step: 2, groups: vec![("w".into(), vec![0.0; 3], vec![0.0; 2])], steps: vec![] };
    assert!(adam.load_state(&ctx, &bad).unwrap_err().to_string().contains("\"w\""));
    let nan = nerf_optim::AdamState { step: 2, groups: vec![("w".into(), vec![f32::NAN; 3], vec![0.0; 3])], steps: vec![] };
    assert!(adam.load_state(&ctx, &nan).is_err());
    assert_eq!(adam.step_count(), 0);
}

/// Sparse groups' per-entry step counts travel through checkpoints on either device; a dense
/// run's state (no counts) continues with every entry counted as having taken every step.
#[test]
fn sparse_step_counts_round_trip_and_continue_a_dense_state() {
    let Some(ctx) = context() else { return };
    let cfg = AdamConfig { sparse_groups: vec!["t".into()], ..AdamConfig::instant_ngp() };
    let groups = [GpuParamGroup::new("t", 0, 64, 0.0)];
    let adam = GpuAdam::new(&ctx, &cfg, &groups).unwrap();
    let p = ctx.upload("p", &vec![0.5f32; 64]);
    let g = ctx.zeros("g", 4 * 64);
    for step in 0..3u32 {
        // Entry i has a gradient at step s when i % 3 != s, i.e. twice in three steps (0 < i).
        let grads: Vec<f32> = (0..64).map(|i| if i % 3 == step { 0.0 } else { 0.1 + i as f32 * 1e-3 }).collect();
        ctx.write(&g, 0, &grads);
        let mut enc = ctx.encoder("adam");
        adam.record_step(&ctx, &mut enc, &p, &g, 1e-2);
        ctx.queue.submit([enc.finish()]);
    }
    let st = adam.state(&ctx).unwrap();
    assert_eq!(st.steps.len(), 1);
    assert!(st.steps[0].1.iter().all(|&k| k == 2), "{:?}", st.steps);
    let mut cpu = Adam::new(cfg.clone());
    cpu.load_state(st.clone()).unwrap();
    assert_eq!(cpu.entry_steps("t").unwrap(), st.steps[0].1.as_slice());
    let again = GpuAdam::new(&ctx, &cfg, &groups).unwrap();
    again.load_state(&ctx, &st).unwrap();
    assert_eq!(again.state(&ctx).unwrap(), st);
    // Bad counts are refused.
    let mut bad = st.clone();
    bad.steps[0].1[0] = 9;
    assert!(again.load_state(&ctx, &bad).is_err());
    bad.steps[0].1.pop();
    assert!(again.load_state(&ctx, &bad).is_err());
    // A dense state: counts = its step count.
    let dense = AdamState { steps: vec![], ..st };
    again.load_state(&ctx, &dense).unwrap();
    assert!(again.state(&ctx).unwrap().steps[0].1.iter().all(|&k| k == 3));
}
