//! Per-view exposure changes for colour-correction experiments: the gains average 1 per channel,
//! stay in their range, follow the seed; `scale_colors` multiplies colours and keeps alpha.

use nerf_data::{exposure_gains, load_blender, LoadOptions, Split, ViewSelection};

#[test]
fn gains_average_one_and_follow_the_seed() {
    let g = exposure_gains(50, 0.3, 4);
    assert_eq!(g.len(), 50);
    for c in 0..3 {
        let mean = g.iter().map(|x| x[c] as f64).sum::<f64>() / 50.0;
        assert!((mean - 1.0).abs() < 1e-6, "channel {c}: {mean}");
        // Drawn in [0.7, 1.3], then divided by a mean that is itself in that range.
        assert!(g.iter().all(|x| x[c] > 0.7 / 1.3 && x[c] < 1.3 / 0.7));
        let spread = g.iter().map(|x| x[c]).fold(f32::MIN, f32::max) - g.iter().map(|x| x[c]).fold(f32::MAX, f32::min);
        assert!(spread > 0.3, "channel {c}: spread {spread}");
    }
    assert_eq!(g, exposure_gains(50, 0.3, 4));
    assert_ne!(g, exposure_gains(50, 0.3, 5));
    assert!(exposure_gains(7, 0.0, 1).iter().flatten().all(|&x| x == 1.0));
}

#[test]
#[should_panic(expected = "[0, 1)")]
fn an_amount_of_one_is_refused() {
    exposure_gains(3, 1.0, 0);
}

#[test]
fn scale_colors_multiplies_each_views_colours_and_keeps_alpha() {
    let scene = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/lego_100");
    let opts = LoadOptions { downscale: 4, views: ViewSelection::First(2), ..Default::default() };
    let before = load_blender(&scene, Split::Train, &opts).unwrap();
    let mut after = before.clone();
    let gains = [[2.0, 0.5, 1.5], [1.0, 1.0, 3.0]];
    after.scale_colors(&gains);
    for v in 0..2 {
        for (p, q) in before.images[v].to_f32().chunks_exact(4).zip(after.images[v].to_f32().chunks_exact(4)) {
            assert_eq!(p[3], q[3]);
            for c in 0..3 {
                // Clipped to 1, as a photo's values, and held in 16 bits: within half a step.
                let want = (p[c] * gains[v][c]).min(1.0);
                assert!((q[c] - want).abs() <= 0.5 / 65535.0 + 1e-7, "{} vs {want}", q[c]);
            }
        }
    }
    assert!(before.images[0].to_f32().iter().any(|&x| x > 0.6), "a scene with colour to scale");
}
