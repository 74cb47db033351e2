#![allow(clippy::needless_range_loop)]
//! Compositing against nerf-pytorch `raw2outputs` (shared/reference/raw2outputs.json).

use nerf_core::Real;
use nerf_render::{composite_forward, CompositeOutputs};
use serde_json::Value;

fn load() -> Option<Value> {
    let p = nerf_core::shared::reference(env!("CARGO_MANIFEST_DIR"), "raw2outputs.json")?;
    Some(serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap())
}

fn flat(v: &Value) -> Vec<f64> {
    match v {
        Value::Array(a) => a.iter().flat_map(flat).collect(),
        Value::Number(n) => vec![n.as_f64().unwrap()],
        _ => panic!("unexpected JSON value {v}"),
    }
}

/// Packs the reference inputs as nerf-pytorch feeds them: σ = relu(raw σ), c = sigmoid(raw rgb),
/// δ = diff(z)·|d| with the last interval 1e10·|d|, t = z.
struct Packed<T> {
    offsets: Vec<u32>,
    sigma: Vec<T>,
    rgb: Vec<T>,
    dt: Vec<T>,
    t: Vec<T>,
}

fn pack<T: Real>(z: &[f64], rays_d: &[f64], raw: &[f64], n_rays: usize, n_s: usize) -> Packed<T> {
    let mut p = Packed {
        offsets: vec![0],
        sigma: vec![],
        rgb: vec![],
        dt: vec![],
        t: vec![],
    };
    for r in 0..n_rays {
        let d = &rays_d[3 * r..3 * r + 3];
        let norm = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        for i in 0..n_s {
            let k = r * n_s + i;
            let dz = if i + 1 < n_s { z[k + 1] - z[k] } else { 1e10 };
            p.dt.push(T::c(dz * norm));
            p.t.push(T::c(z[k]));
            p.sigma.push(T::c(raw[4 * k + 3].max(0.0)));
            for c in 0..3 {
                p.rgb.push(T::c(1.0 / (1.0 + (-raw[4 * k + c]).exp())));
            }
        }
        p.offsets.push(((r + 1) * n_s) as u32);
    }
    p
}

fn check<T: Real>(v: &Value) -> usize {
    let z = flat(&v["inputs"]["z_vals"]);
    let rays_d = flat(&v["inputs"]["rays_d"]);
    let (n_rays, n_s) = (4, 8);
    assert_eq!(z.len(), n_rays * n_s);
    let mut checked = 0;
    let mut out = CompositeOutputs::<T>::new();
    for (ci, case) in v["inputs"]["cases"].as_array().unwrap().iter().enumerate() {
        let raw = flat(&case["raw"]);
        let p = pack::<T>(&z, &rays_d, &raw, n_rays, n_s);
        let white = vec![T::one(); 3 * n_rays];
        let black = vec![T::zero(); 3 * n_rays];
        for (key, bg) in [
            ("white_bkgd_f64", Some(&white[..])),
            ("black_bkgd_f64", None),
            ("black_bkgd_f64", Some(&black[..])),
        ] {
            let exp = &v["outputs"]["cases"][ci][key];
            composite_forward(
                &p.offsets,
                &p.sigma,
                &p.rgb,
                &p.dt,
                &p.t,
                bg,
                T::zero(),
                &mut out,
            );
            let close = |name: &str, got: &[T], want: &[f64], rel: bool| {
                assert_eq!(got.len(), want.len(), "{name}");
                for (i, (g, w)) in got.iter().zip(want).enumerate() {
                    let tol = if rel { 1e-5 * w.abs() } else { 1e-5 };
                    assert!(
                        (g.f64() - w).abs() <= tol,
                        "case {ci} {key} {name}[{i}]: got {g}, want {w}"
                    );
                }
            };
            close("rgb_map", &out.rgb, &flat(&exp["rgb_map"]), false);
            close("acc_map", &out.opacity, &flat(&exp["acc_map"]), false);
            close("weights", &out.weights, &flat(&exp["weights"]), false);
            close("depth_map", &out.depth, &flat(&exp["depth_map"]), true);
            let disp: Vec<T> = (0..n_rays)
                .map(|r| T::one() / (out.depth[r] / out.opacity[r]).max(T::c(1e-10)))
                .collect();
            close("disp_map", &disp, &flat(&exp["disp_map"]), true);
            checked += 1;
        }
    }
    checked
}

#[test]
fn matches_nerf_pytorch_raw2outputs_f64() {
    let Some(v) = load() else { return };
    assert_eq!(check::<f64>(&v), 6);
}

#[test]
fn matches_nerf_pytorch_raw2outputs_f32() {
    let Some(v) = load() else { return };
    assert_eq!(check::<f32>(&v), 6);
}
