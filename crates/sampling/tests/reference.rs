#![allow(clippy::needless_range_loop)]
//! `sample_pdf` and `hierarchical` against nerf-pytorch (shared/reference/sample_pdf.json).

use nerf_core::Real;
use nerf_sampling::{hierarchical, sample_pdf, RaySamples};
use serde_json::Value;

fn load() -> Option<Value> {
    let p = nerf_core::shared::reference(env!("CARGO_MANIFEST_DIR"), "sample_pdf.json")?;
    Some(serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap())
}

fn rows(v: &Value) -> Vec<Vec<f64>> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect()
        })
        .collect()
}

fn conv<T: Real>(x: &[f64]) -> Vec<T> {
    x.iter().map(|&v| T::c(v)).collect()
}

fn assert_close<T: Real>(what: &str, got: &[T], want: &[f64]) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g.f64() - w).abs() <= 1e-5,
            "{what}[{i}]: got {g}, want {w}"
        );
    }
}

fn check_sample_pdf<T: Real>(v: &Value) {
    let bins = rows(&v["inputs"]["bins"]);
    let weights = rows(&v["inputs"]["weights_passed"]);
    let u = rows(&v["inputs"]["u"]);
    let det = rows(&v["outputs"]["samples_det_f64"]);
    let rnd = rows(&v["outputs"]["samples_u_f64"]);
    assert_eq!(bins.len(), 3);
    for r in 0..bins.len() {
        let mut out = vec![T::zero(); det[r].len()];
        sample_pdf(&conv::<T>(&bins[r]), &conv::<T>(&weights[r]), &[], &mut out);
        assert_close(&format!("ray {r} det"), &out, &det[r]);
        sample_pdf(
            &conv::<T>(&bins[r]),
            &conv::<T>(&weights[r]),
            &conv::<T>(&u[r]),
            &mut out,
        );
        assert_close(&format!("ray {r} u"), &out, &rnd[r]);
        // Any order of u gives the same samples, permuted the same way.
        let mut u_rev = conv::<T>(&u[r]);
        u_rev.reverse();
        sample_pdf(
            &conv::<T>(&bins[r]),
            &conv::<T>(&weights[r]),
            &u_rev,
            &mut out,
        );
        out.reverse();
        assert_close(&format!("ray {r} reversed u"), &out, &rnd[r]);
    }
}

#[test]
fn sample_pdf_matches_nerf_pytorch_f64() {
    let Some(v) = load() else { return };
    check_sample_pdf::<f64>(&v);
}

#[test]
fn sample_pdf_matches_nerf_pytorch_f32() {
    let Some(v) = load() else { return };
    check_sample_pdf::<f32>(&v);
}

/// The whole coarse-to-fine pass over the three reference rays packed together, deterministic:
/// the merged sorted t equals render_rays' `z_vals` after `torch.sort(cat(z_vals, samples))`.
#[test]
fn hierarchical_det_matches_merged_sorted_z_vals() {
    let Some(v) = load() else { return };
    let z = rows(&v["inputs"]["z_vals"]);
    let wf = rows(&v["inputs"]["weights_full"]);
    let merged = rows(&v["outputs"]["z_vals_merged_sorted_det_f64"]);
    let n_rays = z.len();
    let mut coarse = RaySamples {
        n_rays,
        ..Default::default()
    };
    coarse.ray_offsets.push(0);
    for zr in &z {
        coarse.t.extend(zr.iter().map(|&x| x as f32));
        coarse.ray_offsets.push(coarse.t.len() as u32);
        coarse.ray_indices.extend(std::iter::repeat_n(
            (coarse.ray_offsets.len() - 2) as u32,
            zr.len(),
        ));
    }
    coarse.dt = vec![0.0; coarse.t.len()];
    let origins = vec![0.0f32; 3 * n_rays];
    let dirs: Vec<f32> = (0..n_rays).flat_map(|_| [0.0, 0.0, -1.0]).collect();
    let far = vec![6.0f32; n_rays];
    let weights: Vec<f32> = wf.iter().flatten().map(|&x| x as f32).collect();
    let mut out = RaySamples::default();
    hierarchical(&coarse, &weights, &origins, &dirs, &far, 16, None, &mut out);
    assert_eq!(out.n_rays, n_rays);
    for r in 0..n_rays {
        let range = out.ray_range(r);
        assert_eq!(range.len(), 26);
        assert_close(
            &format!("ray {r} merged"),
            &out.t[range.clone()],
            &merged[r],
        );
        for k in range {
            assert_eq!(out.ray_indices[k] as usize, r);
            assert_eq!(out.positions[3 * k + 2], -out.t[k]);
        }
    }
}
