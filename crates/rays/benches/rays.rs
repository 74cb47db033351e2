//! A rendered frame's rays at 800×800 (640 000 pixels, 320×320 with `NERF_BENCH_SMALL=1`): casting
//! them through one point of each pixel (`Camera::frame_rays_at`), and moving them through a thin
//! lens, an open shutter, and both (`Exposure::apply`, what `nerf render --aperture / --shutter`
//! adds to each pass).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use nerf_rays::exposure::camera_lerp;
use nerf_rays::{Camera, Exposure, Intrinsics, Projection, ThinLens};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let side = if std::env::var_os("NERF_BENCH_SMALL").is_some() { 320 } else { 800 };
    let k = Intrinsics::from_fov_x(side, side, 0.69);
    let cam = |x: f32| Camera::from_c2w(k, &[[0.0, 0.0, 1.0, 4.0 + x], [1.0, 0.0, 0.0, x], [0.0, 1.0, 0.0, 0.5]]).unwrap();
    let (a, b) = (cam(0.0), cam(0.3));
    let close = camera_lerp(&a, &b, 0.5);
    let lens = Some(ThinLens { aperture: 0.1, focus_distance: 4.0 });
    let (mut o, mut d) = (Vec::new(), Vec::new());
    a.frame_rays_at(Projection::Perspective, [0.5, 0.5], &mut o, &mut d);
    let (o0, d0) = (o.clone(), d.clone());

    let mut g = c.benchmark_group(format!("frame_rays_{side}x{side}"));
    g.throughput(Throughput::Elements(u64::from(side) * u64::from(side)));
    g.bench_function("cast", |bch| bch.iter(|| a.frame_rays_at(Projection::Perspective, black_box([0.3, 0.7]), &mut o, &mut d)));
    for (name, shutter_close, lens) in [("lens", None, lens), ("shutter", Some(&close), None), ("lens_and_shutter", Some(&close), lens)] {
        let e = Exposure { camera: &a, shutter_close, lens, projection: Projection::Perspective };
        g.bench_function(name, |bch| {
            bch.iter(|| {
                o.copy_from_slice(&o0);
                d.copy_from_slice(&d0);
                e.apply(black_box(3), 8, 1, &mut o, &mut d);
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
