//! The pass timer (`nerf_gpu::profile`): every dispatch recorded between `profile_start` and
//! `profile_finish` is timed and attributed to the stage and part current when it was recorded,
//! and timing a step does not change what it computes. Runs on any adapter with timestamp queries
//! (lavapipe in CI); prints a notice and returns elsewhere.

use nerf_gpu::optim::{GpuAdam, GpuParamGroup};
use nerf_gpu::GpuContext;
use nerf_optim::AdamConfig;

/// `n` Adam steps over one buffer, the first `n_a` in stage "a", the rest in stage "b" / part "p".
fn run(ctx: &GpuContext, profile: bool, n: usize, n_a: usize) -> (Vec<f32>, Option<Vec<nerf_gpu::profile::PassTiming>>) {
    let len = 5000;
    let adam = GpuAdam::new(ctx, &AdamConfig::instant_ngp(), &[GpuParamGroup::new("all", 0, len, 0.0)]).unwrap();
    let p0: Vec<f32> = (0..len).map(|i| ((i * 37 % 101) as f32 - 50.0) / 50.0).collect();
    let g: Vec<f32> = (0..len).map(|i| ((i * 53 % 97) as f32 - 48.0) / 10.0).collect();
    let (p, gr) = (ctx.upload("p", &p0), ctx.upload("g", &g));
    if profile {
        ctx.profile_start().unwrap();
        assert!(ctx.profiling());
    }
    let mut enc = ctx.encoder("profiled");
    ctx.profile_stage("a");
    for i in 0..n {
        if i == n_a {
            ctx.profile_stage("b");
            ctx.profile_part("p");
        }
        adam.record_step(ctx, &mut enc, &p, &gr, 1e-2);
    }
    let timings = ctx.profile_finish(&mut enc);
    assert_eq!(timings.is_some(), profile);
    assert!(!ctx.profiling());
    ctx.queue.submit([enc.finish()]);
    let passes = timings.map(|t| {
        assert_eq!(t.dropped(), 0);
        t.read(ctx).unwrap()
    });
    (ctx.read_f32(&p, len).unwrap(), passes)
}

#[test]
fn passes_are_timed_and_attributed_without_changing_results() {
    let Some(ctx) = GpuContext::for_tests() else { return };
    if !ctx.features.timestamps {
        eprintln!("NOTICE: adapter {} has no timestamp queries; nothing to profile", ctx.describe());
        assert!(ctx.profile_start().is_err());
        return;
    }
    let (plain, none) = run(&ctx, false, 5, 2);
    assert!(none.is_none());
    let (timed, passes) = run(&ctx, true, 5, 2);
    assert_eq!(plain, timed, "profiling changed the results");
    let passes = passes.unwrap();
    // Adam records a fixed number of passes per step: 2 steps in "a", 3 in "b".
    let a: Vec<_> = passes.iter().filter(|p| p.stage == "a").collect();
    let b: Vec<_> = passes.iter().filter(|p| p.stage == "b").collect();
    assert!(!a.is_empty());
    assert_eq!(a.len() + b.len(), passes.len());
    assert_eq!(2 * b.len(), 3 * a.len(), "{passes:?}");
    assert!(a.iter().all(|p| p.part.is_empty()) && b.iter().all(|p| p.part == "p"));
    let pos = |s: &str| passes.iter().position(|p| p.stage == s).unwrap();
    assert!(passes[..pos("b")].iter().all(|p| p.stage == "a"), "recording order kept");
    assert!(passes.iter().all(|p| p.kernel.starts_with("adam")), "{passes:?}");
    for p in &passes {
        assert!(p.begin_ns.is_finite() && p.end_ns.is_finite() && p.begin_ns >= 0.0 && p.end_ns >= p.begin_ns, "{p:?}");
    }
    assert_eq!(passes.iter().map(|p| p.begin_ns).fold(f64::INFINITY, f64::min), 0.0);
    // Passes run in order on one queue: the last one cannot end before the first began.
    assert!(passes.last().unwrap().end_ns >= passes[0].begin_ns);
    // A second profile starts empty.
    let (_, again) = run(&ctx, true, 1, 1);
    assert_eq!(again.unwrap().len(), a.len() / 2);
    // Outside a profile nothing is recorded.
    let mut enc = ctx.encoder("unprofiled");
    assert!(ctx.profile_finish(&mut enc).is_none());
}
