//! Launches from the device's count (`shaders/dispatch.wgsl`) against their CPU twin, and an
//! indirect launch that needs the second dimension (more than 65 535 workgroups).

use nerf_gpu::compact::GpuRowGather;
use nerf_gpu::dispatch::{entry_offset, groups_for, MAX_ITEMS, MAX_K, MAX_Z};
use nerf_gpu::{DispatchArgs, GpuContext};
use rand::Rng as _;

fn context() -> Option<GpuContext> {
    let ctx = GpuContext::for_tests()?;
    if !ctx.indirect_dispatch {
        eprintln!("NOTICE: NERF_NO_INDIRECT is set; the indirect launches are not tested");
        return None;
    }
    Some(ctx)
}

#[test]
fn dispatch_arguments_match_their_cpu_twin() {
    let Some(ctx) = context() else { return };
    let mut r = nerf_core::rng(41, 0);
    let mut cases: Vec<(u32, u32, usize)> = vec![
        // (count in the slot, the other slot's value, capacity)
        (0, 7, 100),
        (1, 0, 1),
        (64, 3, 64),
        (65, 3, 1000),
        (5000, 1, 4000), // more than the capacity: clamped
        (65_535 * 4 + 1, 9, 1 << 20),
        (u32::MAX, 2, MAX_ITEMS as usize), // the largest table, a count above it
    ];
    for _ in 0..8 {
        let cap = r.gen_range(1usize..(1 << 26));
        cases.push((r.gen_range(0..=cap as u32 + 100), r.gen(), cap));
    }
    for slot in [1usize, 0] {
        for &(n, other, cap) in &cases {
            let counters = if slot == 1 { [other, n, 11, 12] } else { [n, other, 11, 12] };
            let counters = ctx.upload("counters", &counters);
            let args = DispatchArgs::for_slot(&ctx, cap, slot);
            let entries = (MAX_Z * (MAX_K + 1)) as usize;
            ctx.queue.write_buffer(args.buffer(), 0, bytemuck::cast_slice(&vec![0xDEAD_BEEFu32; 3 * entries]));
            let mut enc = ctx.encoder("dispatch args");
            let launch = args.record(&ctx, &mut enc, &counters, cap);
            assert!(launch.is_indirect() && launch.capacity() == cap);
            ctx.queue.submit([enc.finish()]);
            let table = ctx.read_u32(args.buffer(), 3 * entries).unwrap();
            let m = n.min(cap as u32);
            for z in 1..=MAX_Z {
                for k in 0..=MAX_K {
                    let o = (entry_offset(1 << k, z).unwrap() / 4) as usize;
                    assert_eq!(table[o..o + 3], groups_for(m, 1 << k, z), "slot {slot}, n {n}, cap {cap}, 2^{k} per group, z {z}");
                }
            }
        }
    }
}

/// A row gather of 2 rows per workgroup over 140 001 rows: 70 001 workgroups, so the table splits
/// them over two rows of workgroups and the kernel's linear index must use the device's
/// `num_workgroups`.
#[test]
fn an_indirect_launch_past_65535_workgroups_covers_every_row() {
    let Some(ctx) = context() else { return };
    let (n, cap, width) = (140_001usize, 140_010usize, 32usize);
    assert!(groups_for(n as u32, 2, 1)[1] == 2);
    let mut r = nerf_core::rng(42, 0);
    let n_src = 1000usize;
    let src: Vec<f32> = (0..n_src * width).map(|_| r.gen_range(-1.0f32..1.0)).collect();
    let rows: Vec<u32> = (0..cap).map(|_| r.gen_range(0..n_src as u32)).collect();
    let counters = ctx.upload("counters", &[0u32, n as u32]);
    let (src_b, rows_b) = (ctx.upload("src", &src), ctx.upload("rows", &rows));
    let dst = ctx.upload("dst", &vec![f32::NAN; cap * width]);
    let gather = GpuRowGather::new(&ctx, width).unwrap();
    let args = DispatchArgs::new(&ctx, cap);
    let mut enc = ctx.encoder("gather");
    let launch = args.record(&ctx, &mut enc, &counters, cap);
    gather.record(&ctx, &mut enc, &counters, &rows_b, &src_b, &dst, launch);
    ctx.queue.submit([enc.finish()]);
    let got = ctx.read_f32(&dst, cap * width).unwrap();
    for b in 0..n {
        let want = &src[rows[b] as usize * width..][..width];
        assert_eq!(&got[b * width..][..width], want, "row {b}");
    }
    assert!(got[n * width..].iter().all(|v| v.is_nan()), "rows past n were written");
}
