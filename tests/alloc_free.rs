//! The CPU training step and the CPU render allocate nothing per sample: every buffer they use is
//! sized once and reused. A recording global allocator takes the call stack of each allocation
//! made during a few steps (after warm-up steps that size the buffers) or a second render of the
//! same rays; what the `gemm` crate allocates for its packing panels (it takes no caller-provided
//! workspace; bounded by its cache blocking, not by the batch) is set aside, and what remains must
//! be a few small per-step lists, not buffers.
//!
//! The work runs in a one-thread rayon pool so that every allocation happens on the thread that
//! makes it, in order, and the call stack says whose it is.

mod common;

use nerf::data::{Split, ViewSelection};
use nerf::train::{SamplerConfig, SceneBounds, TrainConfig, Trainer};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, Ordering::SeqCst};
use std::sync::Mutex;

struct Recording;

static RECORDING: AtomicBool = AtomicBool::new(false);
/// (bytes, call stack) of every allocation made while recording.
static SEEN: Mutex<Vec<(usize, String)>> = Mutex::new(Vec::new());
/// Held by each test for its whole run: the recording is process-wide.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

thread_local! {
    /// Set while the allocator records (capturing a stack allocates too).
    static INSIDE: Cell<bool> = const { Cell::new(false) };
}

fn record(bytes: usize) {
    if !RECORDING.load(SeqCst) {
        return;
    }
    INSIDE.with(|inside| {
        if inside.replace(true) {
            return;
        }
        let stack = std::backtrace::Backtrace::force_capture().to_string();
        SEEN.lock().unwrap().push((bytes, stack));
        inside.set(false);
    });
}

// SAFETY: forwards every call to the system allocator unchanged; the recording allocates only
// through the same allocator, guarded against re-entry.
unsafe impl GlobalAlloc for Recording {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Recording = Recording;

/// What a trainer does while the allocator records.
enum Work {
    /// `n` training steps.
    Steps(usize),
    /// A render of the first training view's rays (after one unrecorded render of them).
    Render,
}

/// Allocations outside gemm made by `work`, after `warmup` training steps of `config`; with
/// `masked`, the training views carry masks (every other pixel kept, the first view whole) and
/// depth maps (a depth on every third pixel).
fn allocations_not_in_gemm(config: TrainConfig, warmup: usize, work: Work, masked: bool) -> Vec<(usize, String)> {
    let _alone = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let mut train = common::load(Split::Train, ViewSelection::All);
    if masked {
        let n = train.width * train.height;
        let flags: Vec<Vec<bool>> = (0..train.n_views()).map(|v| (0..n).map(|p| v == 0 || p % 2 == 0).collect()).collect();
        train.masks = Some(nerf::data::PixelMasks::from_flags(n, flags.iter().map(|f| &f[..])));
        train.depths = Some((0..train.n_views()).map(|_| (0..n).map(|p| if p % 3 == 0 { 4.0 } else { 0.0 }).collect()).collect());
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    pool.install(|| {
        let mut t = Trainer::new(config, &nerf::registry(), SceneBounds::of(&train)).unwrap();
        for _ in 0..warmup {
            t.step(&train).unwrap();
        }
        match work {
            Work::Steps(n) => {
                SEEN.lock().unwrap().clear();
                RECORDING.store(true, SeqCst);
                for _ in 0..n {
                    t.step(&train).unwrap();
                }
            }
            Work::Render => {
                let mut rays = nerf::data::RayBatch::default();
                train.view_rays(0, nerf::data::Background::White, t.config().pixel_convention, &mut rays);
                let n = rays.len();
                let (mut rgb, mut opacity, mut depth) = (vec![0.0; 3 * n], vec![0.0; n], vec![0.0; n]);
                let bg = vec![1.0; 3 * n];
                t.render_rays(&rays.origins, &rays.dirs, &bg, &mut rgb, &mut opacity, &mut depth).unwrap();
                SEEN.lock().unwrap().clear();
                RECORDING.store(true, SeqCst);
                t.render_rays(&rays.origins, &rays.dirs, &bg, &mut rgb, &mut opacity, &mut depth).unwrap();
            }
        }
        RECORDING.store(false, SeqCst);
    });
    let seen = std::mem::take(&mut *SEEN.lock().unwrap());
    assert!(!seen.is_empty(), "nothing was recorded: is the allocator installed?");
    // Without symbols the call stacks could not tell gemm's allocations from ours.
    assert!(
        seen.iter().any(|(_, s)| in_gemm(s)),
        "no recorded stack names gemm, which every step calls: the test binary has no symbols ({})",
        seen[0].1
    );
    seen.into_iter().filter(|(_, s)| !in_gemm(s)).collect()
}

/// Whether a call stack passes through the gemm crates (`gemm`, `gemm_common`, `gemm_f32`, …).
fn in_gemm(stack: &str) -> bool {
    stack.lines().any(|l| {
        // "  12: gemm_common::gemm::gemm_basic_generic" or "  12: <gemm_f32::…>::…"
        let symbol = l.trim_start().split_once(": ").map_or("", |(_, s)| s).trim_start_matches('<');
        symbol.starts_with("gemm::") || symbol.starts_with("gemm_")
    })
}

/// The frames of `stack` from this workspace's crates, for the failure message.
fn our_frames(stack: &str) -> String {
    let frames: Vec<&str> = stack
        .lines()
        .map(str::trim)
        .filter(|l| l.contains("nerf") && !l.starts_with("at ") && !l.contains("alloc_free"))
        .take(8)
        .collect();
    frames.join("\n    ")
}

fn check(name: &str, config: TrainConfig) {
    check_with(name, config, false)
}

fn check_with(name: &str, config: TrainConfig, masked: bool) {
    const STEPS: usize = 3;
    let ours = allocations_not_in_gemm(config, 20, Work::Steps(STEPS), masked);
    let bytes: usize = ours.iter().map(|(b, _)| b).sum();
    let report: Vec<String> = ours.iter().map(|(b, s)| format!("  {b} bytes:\n    {}", our_frames(s))).collect();
    println!("{name}: {} allocations, {bytes} bytes outside gemm in {STEPS} steps", ours.len());
    // Per step: the list of parameter groups handed to Adam and the field's list behind it
    // (two small vectors of references). A buffer sized by the batch would be kilobytes.
    assert!(
        ours.len() <= 4 * STEPS && bytes <= 1024 * STEPS,
        "{name}: {} allocations, {bytes} bytes in {STEPS} steps outside gemm:\n{}",
        ours.len(),
        report.join("\n")
    );
}

/// A second render of the same rays allocates nothing outside gemm: the rounds' ray states and
/// sample buffers (occupancy grid) or the fields' stages (stratified + hierarchical) are kept.
fn check_render(name: &str, config: TrainConfig) {
    let ours = allocations_not_in_gemm(config, 4, Work::Render, false);
    let report: Vec<String> = ours.iter().map(|(b, s)| format!("  {b} bytes:\n    {}", our_frames(s))).collect();
    assert!(ours.is_empty(), "{name}: a render allocated outside gemm:\n{}", report.join("\n"));
}

fn paper_config() -> TrainConfig {
    TrainConfig {
        field: "freq".into(),
        batch_rays: 512,
        field_config: serde_json::json!({"width": 64, "depth": 4, "skips": [2], "view_width": 32}),
        sampler: SamplerConfig::Hierarchical { n_coarse: 16, n_fine: 16 },
        ..TrainConfig::default()
    }
}

#[test]
fn a_render_allocates_nothing() {
    // The hash preset renders in rounds through the occupancy grid; the paper's field by stages.
    check_render("hash", common::small_hash_config(100, 4, 8));
    check_render("freq", paper_config());
}

#[test]
fn a_hash_field_step_allocates_no_buffers() {
    // The preset's sampler (occupancy grid, refreshed every 4 steps so that the measured steps
    // include an update) and its moving average of the weights.
    let mut c = common::small_hash_config(100, 4, 8);
    c.target_samples_per_step = Some(1 << 14);
    assert!(c.ema_decay.is_some());
    check("hash", c);
}

#[test]
fn a_masked_depth_supervised_hash_field_step_allocates_no_buffers() {
    // Training masks: rays drawn from the kept pixels only; depth supervision on them.
    let mut c = common::small_hash_config(100, 4, 8);
    c.target_samples_per_step = Some(1 << 14);
    c.depth_loss = Some(0.1);
    check_with("hash, masked, depth-supervised", c, true);
}

#[test]
fn a_paper_field_step_allocates_no_buffers() {
    check("freq", paper_config());
}

#[test]
fn a_voxel_field_step_allocates_no_buffers() {
    let registry = nerf::registry();
    let mut v = serde_json::to_value(TrainConfig::default()).unwrap();
    nerf::field::merge_json(&mut v, &(registry.get("voxel").unwrap().train_preset)());
    let mut c: TrainConfig = serde_json::from_value(v).unwrap();
    c.field = "voxel".into();
    c.target_samples_per_step = Some(1 << 14);
    check("voxel", c);
}
