//! Real spherical-harmonics encoding of view directions (Instant-NGP's direction encoding), in the
//! order, signs and constants of HashNeRF's `SHEncoder`.
//!
//! Degree `d` (1..=4) means bands `l = 0..d−1`, i.e. `d²` outputs. Inputs are unit direction vectors
//! (components in `[−1, 1]`) used **as-is**: no renormalisation and no `2x − 1` rescaling (tiny-cuda-nn
//! expects `[0,1]` inputs instead). The polynomials are HashNeRF's (e.g. `C2₂·(2z² − x² − y²)` for
//! `Y₂⁰`), which equal tiny-cuda-nn's unit-norm-simplified forms only for exactly unit vectors; the
//! backward pass differentiates these polynomials as written.

use crate::Encoding;
use nerf_core::Real;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// `Y₀⁰ = 1/(2√π)`.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;
/// Band 1 constant `√3/(2√π)` (the outputs are `−C1·y, C1·z, −C1·x`).
pub const SH_C1: f64 = 0.488_602_511_902_919_9;
/// Band 2 constants (signs included).
pub const SH_C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
/// Band 3 constants (signs included).
pub const SH_C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// The largest supported degree (bands 0..=3).
pub const MAX_SH_DEGREE: u32 = 4;

/// Samples per rayon task.
const CHUNK: usize = 2048;

/// Configuration of [`SphericalHarmonics`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ShConfig {
    /// Number of bands (4 → bands 0..3 → 16 outputs); 1..=4.
    pub degree: u32,
}

impl Default for ShConfig {
    fn default() -> Self {
        Self { degree: 4 }
    }
}

/// An invalid [`ShConfig`].
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ShConfigError {
    /// The degree is outside 1..=4.
    #[error("spherical harmonics config: degree must be in 1..={MAX_SH_DEGREE}, got {0}")]
    Degree(u32),
}

impl ShConfig {
    /// Checks the configuration.
    pub fn validate(&self) -> Result<(), ShConfigError> {
        if (1..=MAX_SH_DEGREE).contains(&self.degree) {
            Ok(())
        } else {
            Err(ShConfigError::Degree(self.degree))
        }
    }
}

/// The spherical-harmonics encoding of 3-D unit directions: `degree²` outputs per sample, parameter-free.
#[derive(Clone, Debug)]
pub struct SphericalHarmonics {
    cfg: ShConfig,
}

/// The constants in output order: `k[i]` multiplies polynomial `i`.
fn constants<T: Real>() -> [T; 16] {
    let c = [
        SH_C0, -SH_C1, SH_C1, -SH_C1, SH_C2[0], SH_C2[1], SH_C2[2], SH_C2[3], SH_C2[4], SH_C3[0],
        SH_C3[1], SH_C3[2], SH_C3[3], SH_C3[4], SH_C3[5], SH_C3[6],
    ];
    c.map(T::c)
}

impl SphericalHarmonics {
    /// The encoding for `cfg`.
    ///
    /// # Panics
    /// If the degree is outside 1..=4 (use [`SphericalHarmonics::try_new`] for user configs).
    pub fn new(cfg: &ShConfig) -> Self {
        match Self::try_new(cfg) {
            Ok(s) => s,
            Err(e) => panic!("{e}"),
        }
    }

    /// Like [`SphericalHarmonics::new`], returning an error for an invalid configuration.
    pub fn try_new(cfg: &ShConfig) -> Result<Self, ShConfigError> {
        cfg.validate()?;
        Ok(Self { cfg: cfg.clone() })
    }

    /// The configuration.
    pub fn config(&self) -> &ShConfig {
        &self.cfg
    }

    fn n_out(&self) -> usize {
        (self.cfg.degree * self.cfg.degree) as usize
    }

    fn forward_chunk<T: Real>(&self, k: &[T; 16], input: &[T], out: &mut [T]) {
        let od = self.n_out();
        for (d, o) in input.chunks_exact(3).zip(out.chunks_exact_mut(od)) {
            let (x, y, z) = (d[0], d[1], d[2]);
            let mut v = [T::zero(); 16];
            v[0] = k[0];
            if od > 1 {
                v[1] = k[1] * y;
                v[2] = k[2] * z;
                v[3] = k[3] * x;
            }
            if od > 4 {
                let (xx, yy, zz) = (x * x, y * y, z * z);
                let two = T::c(2.0);
                v[4] = k[4] * x * y;
                v[5] = k[5] * y * z;
                v[6] = k[6] * (two * zz - xx - yy);
                v[7] = k[7] * x * z;
                v[8] = k[8] * (xx - yy);
                if od > 9 {
                    let (three, four) = (T::c(3.0), T::c(4.0));
                    v[9] = k[9] * y * (three * xx - yy);
                    v[10] = k[10] * x * y * z;
                    v[11] = k[11] * y * (four * zz - xx - yy);
                    v[12] = k[12] * z * (two * zz - three * xx - three * yy);
                    v[13] = k[13] * x * (four * zz - xx - yy);
                    v[14] = k[14] * z * (xx - yy);
                    v[15] = k[15] * x * (xx - three * yy);
                }
            }
            o.copy_from_slice(&v[..od]);
        }
    }

    fn backward_chunk<T: Real>(&self, k: &[T; 16], input: &[T], d_out: &[T], d_in: &mut [T]) {
        let od = self.n_out();
        for ((d, g), dd) in input
            .chunks_exact(3)
            .zip(d_out.chunks_exact(od))
            .zip(d_in.chunks_exact_mut(3))
        {
            let (x, y, z) = (d[0], d[1], d[2]);
            let mut gk = [T::zero(); 16];
            for i in 0..od {
                gk[i] = g[i] * k[i];
            }
            let (mut dx, mut dy, mut dz) = (T::zero(), T::zero(), T::zero());
            if od > 1 {
                dy += gk[1];
                dz += gk[2];
                dx += gk[3];
            }
            if od > 4 {
                let (xx, yy, zz) = (x * x, y * y, z * z);
                let (two, three, four, six, eight) =
                    (T::c(2.0), T::c(3.0), T::c(4.0), T::c(6.0), T::c(8.0));
                // xy
                dx += gk[4] * y;
                dy += gk[4] * x;
                // yz
                dy += gk[5] * z;
                dz += gk[5] * y;
                // 2zz − xx − yy
                dx -= gk[6] * two * x;
                dy -= gk[6] * two * y;
                dz += gk[6] * four * z;
                // xz
                dx += gk[7] * z;
                dz += gk[7] * x;
                // xx − yy
                dx += gk[8] * two * x;
                dy -= gk[8] * two * y;
                if od > 9 {
                    // y(3xx − yy)
                    dx += gk[9] * six * x * y;
                    dy += gk[9] * three * (xx - yy);
                    // xyz
                    dx += gk[10] * y * z;
                    dy += gk[10] * x * z;
                    dz += gk[10] * x * y;
                    // y(4zz − xx − yy)
                    dx -= gk[11] * two * x * y;
                    dy += gk[11] * (four * zz - xx - three * yy);
                    dz += gk[11] * eight * y * z;
                    // z(2zz − 3xx − 3yy)
                    dx -= gk[12] * six * x * z;
                    dy -= gk[12] * six * y * z;
                    dz += gk[12] * (six * zz - three * xx - three * yy);
                    // x(4zz − xx − yy)
                    dx += gk[13] * (four * zz - three * xx - yy);
                    dy -= gk[13] * two * x * y;
                    dz += gk[13] * eight * x * z;
                    // z(xx − yy)
                    dx += gk[14] * two * x * z;
                    dy -= gk[14] * two * y * z;
                    dz += gk[14] * (xx - yy);
                    // x(xx − 3yy)
                    dx += gk[15] * three * (xx - yy);
                    dy -= gk[15] * six * x * y;
                }
            }
            dd[0] = dx;
            dd[1] = dy;
            dd[2] = dz;
        }
    }
}

impl<T: Real> Encoding<T> for SphericalHarmonics {
    fn input_dim(&self) -> usize {
        3
    }
    fn output_dim(&self) -> usize {
        self.n_out()
    }
    fn forward(&self, input: &[T], out: &mut [T]) {
        let od = self.n_out();
        let n = crate::check_forward("SphericalHarmonics", 3, od, input, out);
        let k = constants::<T>();
        if n <= CHUNK {
            self.forward_chunk(&k, input, out);
        } else {
            input
                .par_chunks(CHUNK * 3)
                .zip(out.par_chunks_mut(CHUNK * od))
                .for_each(|(x, o)| self.forward_chunk(&k, x, o));
        }
    }
    fn backward(&self, input: &[T], d_out: &[T], d_params: &mut [T], d_input: Option<&mut [T]>) {
        let od = self.n_out();
        let n = crate::check_forward("SphericalHarmonics", 3, od, input, d_out);
        assert!(d_params.is_empty(), "SphericalHarmonics has no parameters");
        let Some(d_in) = d_input else { return };
        assert_eq!(
            d_in.len(),
            3 * n,
            "SphericalHarmonics: d_input length {} != {n}·3",
            d_in.len()
        );
        let k = constants::<T>();
        if n <= CHUNK {
            self.backward_chunk(&k, input, d_out, d_in);
        } else {
            input
                .par_chunks(CHUNK * 3)
                .zip(d_out.par_chunks(CHUNK * od))
                .zip(d_in.par_chunks_mut(CHUNK * 3))
                .for_each(|((x, g), dx)| self.backward_chunk(&k, x, g, dx));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;

    fn flat(v: &serde_json::Value) -> Vec<f64> {
        match v {
            serde_json::Value::Array(a) => a.iter().flat_map(flat).collect(),
            x => vec![x.as_f64().expect("number")],
        }
    }

    fn reference() -> Option<serde_json::Value> {
        let path = nerf_core::shared::reference(env!("CARGO_MANIFEST_DIR"), "sh_encoding.json")?;
        Some(serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap())
    }

    #[test]
    fn constants_equal_the_reference_coefficients() {
        let Some(j) = reference() else { return };
        let c = &j["inputs"]["coefficients"];
        assert_eq!(c["C0"].as_f64().unwrap(), SH_C0);
        assert_eq!(c["C1"].as_f64().unwrap(), SH_C1);
        assert_eq!(flat(&c["C2"]), SH_C2);
        assert_eq!(flat(&c["C3"]), SH_C3);
    }

    fn check_reference<T: Real>(tol: f64) {
        let Some(j) = reference() else { return };
        let x: Vec<T> = flat(&j["inputs"]["dirs"]).into_iter().map(T::c).collect();
        let expect = flat(&j["outputs"]["sh_f64"]);
        assert_eq!(expect.len(), 160);
        let sh = SphericalHarmonics::new(&ShConfig { degree: 4 });
        let mut y = vec![T::nan(); 160];
        sh.forward(&x, &mut y);
        let err = y
            .iter()
            .zip(&expect)
            .map(|(a, b)| (a.f64() - b).abs())
            .fold(0.0, f64::max);
        assert!(err < tol, "max error {err} >= {tol}");
        // Lower degrees are prefixes of the degree-4 encoding.
        for d in 1..4u32 {
            let od = (d * d) as usize;
            let sh = SphericalHarmonics::new(&ShConfig { degree: d });
            let mut yd = vec![T::nan(); 10 * od];
            sh.forward(&x, &mut yd);
            for i in 0..10 {
                assert_eq!(
                    &yd[i * od..(i + 1) * od],
                    &y[i * 16..i * 16 + od],
                    "degree {d} sample {i}"
                );
            }
        }
    }

    #[test]
    fn matches_hashnerf_reference_f32() {
        check_reference::<f32>(1e-6);
    }

    #[test]
    fn matches_hashnerf_reference_f64() {
        check_reference::<f64>(1e-12);
    }

    #[test]
    fn output_dims_per_degree_and_validation() {
        for d in 1..=4u32 {
            let sh = SphericalHarmonics::new(&ShConfig { degree: d });
            assert_eq!(Encoding::<f32>::output_dim(&sh), (d * d) as usize);
            assert_eq!(Encoding::<f32>::input_dim(&sh), 3);
            assert_eq!(Encoding::<f32>::n_params(&sh), 0);
        }
        for d in [0, 5] {
            let e = SphericalHarmonics::try_new(&ShConfig { degree: d }).unwrap_err();
            assert!(e.to_string().contains("degree"), "{e}");
        }
        assert_eq!(ShConfig::default().degree, 4);
        let c: ShConfig = serde_json::from_str("{}").unwrap();
        assert_eq!(c, ShConfig::default());
        assert!(serde_json::from_str::<ShConfig>(r#"{"degre": 3}"#).is_err());
        // +z: only the zonal harmonics are non-zero.
        let sh = SphericalHarmonics::new(&ShConfig::default());
        let mut y = [0.0f64; 16];
        sh.forward(&[0.0, 0.0, 1.0], &mut y);
        assert_eq!(y[0], SH_C0);
        assert_eq!(y[2], SH_C1);
        assert_eq!(y[6], 2.0 * SH_C2[2]);
        assert_eq!(y[12], 2.0 * SH_C3[3]);
        assert!(y
            .iter()
            .enumerate()
            .all(|(i, v)| [0, 2, 6, 12].contains(&i) || *v == 0.0));
    }

    #[test]
    fn backward_matches_finite_differences_f64() {
        let mut r = nerf_core::rng(11, 0);
        for d in 1..=4u32 {
            let sh = SphericalHarmonics::new(&ShConfig { degree: d });
            let od = (d * d) as usize;
            let n = 6;
            // Unit directions and (as the polynomials are used as-is) a few non-unit ones.
            let x: Vec<f64> = (0..n)
                .flat_map(|i| {
                    let v: [f64; 3] = std::array::from_fn(|_| r.gen::<f64>() * 2.0 - 1.0);
                    let s = if i < 4 {
                        1.0 / (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
                    } else {
                        1.0
                    };
                    v.map(|c| c * s)
                })
                .collect();
            let g: Vec<f64> = (0..n * od).map(|_| r.gen::<f64>() - 0.5).collect();
            let mut dx = vec![f64::NAN; 3 * n];
            sh.backward(&x, &g, &mut [], Some(&mut dx));
            let loss = |x: &[f64]| {
                let mut y = vec![0.0; n * od];
                sh.forward(x, &mut y);
                y.iter().zip(&g).map(|(a, b)| a * b).sum::<f64>()
            };
            let h = 1e-6;
            for i in 0..3 * n {
                let mut xp = x.clone();
                xp[i] += h;
                let mut xm = x.clone();
                xm[i] -= h;
                let fd = (loss(&xp) - loss(&xm)) / (2.0 * h);
                let err = (fd - dx[i]).abs() / dx[i].abs().max(1.0);
                assert!(
                    err < 1e-8,
                    "degree {d} d_input[{i}]: analytic {} vs fd {fd}",
                    dx[i]
                );
                if d == 1 {
                    assert_eq!(dx[i], 0.0);
                }
            }
            if d > 1 {
                assert!(dx.iter().any(|v| v.abs() > 1e-2));
            }
        }
    }

    #[test]
    fn parallel_path_equals_serial_path() {
        let sh = SphericalHarmonics::new(&ShConfig::default());
        let mut r = nerf_core::rng(12, 0);
        let n = 2 * CHUNK + 3;
        let x: Vec<f32> = (0..3 * n).map(|_| r.gen::<f32>() * 2.0 - 1.0).collect();
        let g: Vec<f32> = (0..16 * n).map(|_| r.gen::<f32>() - 0.5).collect();
        let mut y = vec![0.0f32; 16 * n];
        sh.forward(&x, &mut y);
        let mut dx = vec![0.0f32; 3 * n];
        sh.backward(&x, &g, &mut [], Some(&mut dx));
        for k in [0, CHUNK, n - 1] {
            let mut y1 = [0.0f32; 16];
            sh.forward(&x[3 * k..3 * k + 3], &mut y1);
            assert_eq!(&y1[..], &y[16 * k..16 * k + 16]);
            let mut d1 = [0.0f32; 3];
            sh.backward(
                &x[3 * k..3 * k + 3],
                &g[16 * k..16 * k + 16],
                &mut [],
                Some(&mut d1),
            );
            assert_eq!(&d1[..], &dx[3 * k..3 * k + 3]);
        }
    }
}
