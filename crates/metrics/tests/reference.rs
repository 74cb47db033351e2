//! SSIM and PSNR against skimage (shared/reference/ssim.json), plus identity, symmetry and an
//! independent brute-force implementation of skimage's reflect-filter-then-crop procedure.

use nerf_metrics::{mse, psnr, ssim, ssim_masked, ssim_per_channel, ssim_window};
use rand::{Rng, SeedableRng};
use serde_json::Value;

fn image(v: &Value) -> Vec<f32> {
    // [H][W][3] u8 → u8/255 (exactly representable input as float32 as in the reference).
    let mut out = Vec::new();
    for row in v.as_array().unwrap() {
        for px in row.as_array().unwrap() {
            for c in px.as_array().unwrap() {
                out.push((c.as_f64().unwrap() / 255.0) as f32);
            }
        }
    }
    out
}

#[test]
fn matches_skimage() {
    let Some(p) = nerf_core::shared::reference(env!("CARGO_MANIFEST_DIR"), "ssim.json") else {
        return;
    };
    let j: Value = serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap();
    let shape = j["inputs"]["shape"].as_array().unwrap();
    let (h, w) = (
        shape[0].as_u64().unwrap() as usize,
        shape[1].as_u64().unwrap() as usize,
    );
    let pairs_in = j["inputs"]["pairs"].as_array().unwrap();
    let pairs_out = j["outputs"]["pairs"].as_array().unwrap();
    assert_eq!(pairs_in.len(), 3);
    for (pi, po) in pairs_in.iter().zip(pairs_out) {
        let name = po["name"].as_str().unwrap();
        let (a, b) = (image(&pi["a_u8"]), image(&pi["b_u8"]));
        assert_eq!(a.len(), 3 * w * h);
        let s = ssim(&a, &b, w, h);
        let s_ref = po["ssim"].as_f64().unwrap();
        assert!((s - s_ref).abs() < 1e-5, "{name}: ssim {s} vs {s_ref}");
        let pc = ssim_per_channel(&a, &b, w, h);
        for c in 0..3 {
            let r = po["ssim_per_channel"][c].as_f64().unwrap();
            assert!(
                (pc[c] - r).abs() < 1e-5,
                "{name} channel {c}: {} vs {r}",
                pc[c]
            );
        }
        let p = psnr(&a, &b);
        let p_ref = po["psnr"].as_f64().unwrap();
        assert!((p - p_ref).abs() < 1e-4, "{name}: psnr {p} vs {p_ref}");
        let m_ref = po["mse"].as_f64().unwrap();
        assert!((mse(&a, &b) - m_ref).abs() < 1e-6 * m_ref, "{name}: mse");
        eprintln!(
            "{name}: ssim err {:e}, psnr err {:e}",
            (s - s_ref).abs(),
            (p - p_ref).abs()
        );
    }
}

fn random_pair(w: usize, h: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
    let mut r = rand::rngs::StdRng::seed_from_u64(seed);
    let a: Vec<f32> = (0..3 * w * h).map(|_| r.gen::<f32>()).collect();
    let b: Vec<f32> = a
        .iter()
        .map(|&v| (0.7 * v + 0.3 * r.gen::<f32>()).clamp(0.0, 1.0))
        .collect();
    (a, b)
}

#[test]
fn identity_and_symmetry() {
    let (w, h) = (37, 23);
    let (a, b) = random_pair(w, h, 1);
    assert!((ssim(&a, &a, w, h) - 1.0).abs() < 1e-12);
    assert_eq!(psnr(&a, &a), f64::INFINITY);
    assert_eq!(mse(&a, &a), 0.0);
    let (s1, s2) = (ssim(&a, &b, w, h), ssim(&b, &a, w, h));
    assert!((s1 - s2).abs() < 1e-12, "{s1} {s2}");
    assert!(s1 < 0.99 && s1 > 0.0, "{s1}");
    assert_eq!(psnr(&a, &b), psnr(&b, &a));
    // A constant shift lowers SSIM only through the luminance term; a constant image vs itself is 1.
    let c = vec![0.25f32; 3 * w * h];
    assert!((ssim(&c, &c, w, h) - 1.0).abs() < 1e-12);
}

/// skimage's procedure literally: filter the whole image with a separable Gaussian in scipy
/// "reflect" mode (d c b a | a b c d), compute the SSIM map, crop 5 pixels, mean.
fn brute_force(a: &[f32], b: &[f32], w: usize, h: usize, c: usize) -> f64 {
    brute_force_masked(a, b, w, h, c, &vec![true; w * h])
}

/// [`brute_force`] with the cropped map's mean taken over the positions whose 11×11 window
/// `keep` keeps whole.
fn brute_force_masked(a: &[f32], b: &[f32], w: usize, h: usize, c: usize, keep: &[bool]) -> f64 {
    let win = ssim_window();
    let refl = |i: isize, n: usize| -> usize {
        let n = n as isize;
        let mut i = i;
        loop {
            if i < 0 {
                i = -i - 1;
            } else if i >= n {
                i = 2 * n - 1 - i;
            } else {
                return i as usize;
            }
        }
    };
    let filt = |f: &dyn Fn(usize, usize) -> f64| -> Vec<f64> {
        let mut tmp = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                tmp[y * w + x] = (0..11)
                    .map(|t| win[t] * f(y, refl(x as isize + t as isize - 5, w)))
                    .sum();
            }
        }
        let mut out = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                out[y * w + x] = (0..11)
                    .map(|t| win[t] * tmp[refl(y as isize + t as isize - 5, h) * w + x])
                    .sum();
            }
        }
        out
    };
    let pa = |y: usize, x: usize| a[3 * (y * w + x) + c] as f64;
    let pb = |y: usize, x: usize| b[3 * (y * w + x) + c] as f64;
    let ux = filt(&pa);
    let uy = filt(&pb);
    let uxx = filt(&|y, x| pa(y, x) * pa(y, x));
    let uyy = filt(&|y, x| pb(y, x) * pb(y, x));
    let uxy = filt(&|y, x| pa(y, x) * pb(y, x));
    let (c1, c2) = (1e-4, 9e-4);
    let mut sum = 0.0;
    let mut n = 0;
    for y in 5..h - 5 {
        for x in 5..w - 5 {
            let i = y * w + x;
            if (y - 5..=y + 5).any(|yy| (x - 5..=x + 5).any(|xx| !keep[yy * w + xx])) {
                continue;
            }
            let vx = uxx[i] - ux[i] * ux[i];
            let vy = uyy[i] - uy[i] * uy[i];
            let vxy = uxy[i] - ux[i] * uy[i];
            sum += (2.0 * ux[i] * uy[i] + c1) * (2.0 * vxy + c2)
                / ((ux[i] * ux[i] + uy[i] * uy[i] + c1) * (vx + vy + c2));
            n += 1;
        }
    }
    sum / n as f64
}

#[test]
fn matches_brute_force_on_non_square_images() {
    for (w, h, seed) in [(37, 23, 2), (11, 19, 3), (64, 12, 4)] {
        let (a, b) = random_pair(w, h, seed);
        let pc = ssim_per_channel(&a, &b, w, h);
        for (c, &got) in pc.iter().enumerate() {
            let r = brute_force(&a, &b, w, h, c);
            assert!((got - r).abs() < 1e-12, "{w}x{h} channel {c}: {got} vs {r}");
        }
    }
    // Large image: exercises the parallel paths; still symmetric and ≤ 1.
    let (w, h) = (400, 300);
    let (a, b) = random_pair(w, h, 5);
    let s = ssim(&a, &b, w, h);
    assert!(s < 1.0 && (s - ssim(&b, &a, w, h)).abs() < 1e-12);
}

/// The masked SSIM is the map's mean over the windows of kept pixels only (against the brute
/// force), the plain SSIM with every pixel kept, blind to what it drops, and NaN when no
/// window is kept whole.
#[test]
fn masked_ssim_averages_the_kept_windows() {
    let (w, h) = (41, 29);
    let (a, mut b) = random_pair(w, h, 6);
    assert_eq!(ssim_masked(&a, &b, w, h, &vec![true; w * h]), ssim(&a, &b, w, h));
    // Drop a disc and a few random pixels; ruin the disc in `b` (a passer-by in the photo).
    let mut r = rand::rngs::StdRng::seed_from_u64(7);
    let in_disc = |i: usize| {
        let (x, y) = ((i % w) as f64 - 25.0, (i / w) as f64 - 14.0);
        x * x + y * y < 36.0
    };
    let keep: Vec<bool> = (0..w * h).map(|i| !in_disc(i) && r.gen::<f32>() > 0.005).collect();
    let clean = b.clone();
    for (i, p) in b.chunks_exact_mut(3).enumerate() {
        if in_disc(i) {
            p.copy_from_slice(&[1.0, 0.0, 1.0]);
        }
    }
    let got = ssim_masked(&a, &b, w, h, &keep);
    let want = (0..3).map(|c| brute_force_masked(&a, &b, w, h, c, &keep)).sum::<f64>() / 3.0;
    assert!(got.is_finite() && (got - want).abs() < 1e-12, "masked {got} vs brute force {want}");
    assert_eq!(got, ssim_masked(&a, &clean, w, h, &keep), "what the mask drops does not count");
    assert!(ssim(&a, &b, w, h) < ssim(&a, &clean, w, h));
    // A dropped pixel in every 11×11 window: none kept whole.
    let sparse: Vec<bool> = (0..w * h).map(|i| !(i % w % 10 == 0 && i / w % 10 == 0)).collect();
    assert!(ssim_masked(&a, &b, w, h, &sparse).is_nan());
}
