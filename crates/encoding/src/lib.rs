//! Input encodings as reusable parts: NeRF's frequency (positional) encoding, Instant-NGP's
//! multiresolution hash grid ([`HashGrid`]), the spherical-harmonics direction encoding
//! ([`SphericalHarmonics`]) and a dense trilinear grid ([`DenseGrid`], DVGO's voxel grids;
//! tiny-cuda-nn's `DenseGrid` encoding).
//!
//! An [`Encoding`] maps `input_dim` floats per sample to `output_dim` floats per sample, with a
//! hand-written backward pass. Batches are row-major: sample `k`'s input is
//! `input[k*input_dim..(k+1)*input_dim]` and its encoding `out[k*output_dim..(k+1)*output_dim]`.
//! Encodings are generic over [`nerf_core::Real`] so that finite-difference checks run the same code
//! in `f64`. A field composes an encoding with a `nerf_mlp::Mlp` (tiny-cuda-nn's Encoding + Network
//! split); [`EncodingConfig`] is the serde description that a field's config embeds.

use nerf_core::Real;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub mod dense_grid;
pub mod hash_grid;
pub mod sh;

pub use dense_grid::{DenseGrid, DenseGridError};
pub use hash_grid::{spatial_hash, GridAlign, HashGrid, HashGridConfig, HashGridConfigError, Precision};
pub use sh::{ShConfig, ShConfigError, SphericalHarmonics};

/// An input encoding: maps `input_dim` floats per sample to `output_dim` floats. Parameter-free encodings
/// have `n_params() == 0`; parametric ones (the hash grid) own their parameters.
pub trait Encoding<T: Real>: Send + Sync {
    /// Floats per input sample.
    fn input_dim(&self) -> usize;
    /// Floats per encoded sample.
    fn output_dim(&self) -> usize;
    /// Number of trainable parameters (0 for parameter-free encodings).
    fn n_params(&self) -> usize {
        0
    }
    /// Encodes `n = input.len() / input_dim` samples. out: n·output_dim
    fn forward(&self, input: &[T], out: &mut [T]);
    /// Given dL/d(out), accumulates dL/d(params) into `d_params` (len n_params) and, when `d_input` is Some,
    /// writes dL/d(input) (n·input_dim).
    fn backward(&self, input: &[T], d_out: &[T], d_params: &mut [T], d_input: Option<&mut [T]>);
    /// The trainable parameters (empty for parameter-free encodings), laid out as `backward`'s `d_params`.
    fn params(&self) -> &[T] {
        &[]
    }
    /// The trainable parameters, mutable (call [`Encoding::sync_storage`] after changing them).
    fn params_mut(&mut self) -> &mut [T] {
        &mut []
    }
    /// Re-derives any reduced-precision copy of the parameters that lookups read (the hash grid's
    /// `f16` mirror) after the parameters changed; a no-op by default.
    fn sync_storage(&mut self) {}
}

/// Serde description of an encoding, chosen by `otype` in config files
/// (e.g. `{"otype": "frequency", "n_frequencies": 10, "include_input": true}`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "otype", rename_all = "snake_case")]
pub enum EncodingConfig {
    /// The input unchanged ([`IdentityEncoding`]).
    Identity,
    /// NeRF's frequency encoding ([`FrequencyEncoding`]).
    Frequency(FrequencyEncodingConfig),
}

impl EncodingConfig {
    /// Builds the encoding for `input_dim`-dimensional inputs.
    pub fn build<T: Real>(&self, input_dim: usize) -> Box<dyn Encoding<T>> {
        match self {
            EncodingConfig::Identity => Box::new(IdentityEncoding::new(input_dim)),
            EncodingConfig::Frequency(c) => Box::new(FrequencyEncoding::new(input_dim, c)),
        }
    }
}

/// Number of samples per rayon task; batches of at most this many samples run on the calling thread.
const CHUNK: usize = 1024;

/// Checks the slice lengths of a forward call and returns the number of samples.
fn check_forward(
    name: &str,
    in_dim: usize,
    out_dim: usize,
    input: &[impl Copy],
    out: &[impl Copy],
) -> usize {
    assert!(in_dim > 0, "{name}: input_dim is 0");
    assert_eq!(
        input.len() % in_dim,
        0,
        "{name}: input length {} is not a multiple of {in_dim}",
        input.len()
    );
    let n = input.len() / in_dim;
    assert_eq!(
        out.len(),
        n * out_dim,
        "{name}: output length {} != {n}·{out_dim}",
        out.len()
    );
    n
}

/// The identity encoding: `out = input`. Useful as a placeholder and for raw-input networks.
#[derive(Clone, Debug)]
pub struct IdentityEncoding {
    dim: usize,
}

impl IdentityEncoding {
    /// Identity on `dim` floats per sample.
    pub fn new(dim: usize) -> Self {
        Self { dim }
    }
}

impl<T: Real> Encoding<T> for IdentityEncoding {
    fn input_dim(&self) -> usize {
        self.dim
    }
    fn output_dim(&self) -> usize {
        self.dim
    }
    fn forward(&self, input: &[T], out: &mut [T]) {
        check_forward("IdentityEncoding", self.dim, self.dim, input, out);
        out.copy_from_slice(input);
    }
    fn backward(&self, input: &[T], d_out: &[T], d_params: &mut [T], d_input: Option<&mut [T]>) {
        check_forward("IdentityEncoding", self.dim, self.dim, input, d_out);
        assert!(d_params.is_empty(), "IdentityEncoding has no parameters");
        if let Some(d) = d_input {
            d.copy_from_slice(d_out);
        }
    }
}

/// Configuration of [`FrequencyEncoding`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrequencyEncodingConfig {
    /// Number of frequency bands L (frequencies 2^0 … 2^(L−1)). The paper: 10 for positions, 4 for directions.
    pub n_frequencies: usize,
    /// Whether the raw input is the first block of the output (the paper and nerf-pytorch: true).
    pub include_input: bool,
}

impl FrequencyEncodingConfig {
    /// The paper's position encoding: L = 10 with the input included (63 dims for 3-D).
    pub fn nerf_position() -> Self {
        Self {
            n_frequencies: 10,
            include_input: true,
        }
    }
    /// The paper's direction encoding: L = 4 with the input included (27 dims for 3-D).
    pub fn nerf_direction() -> Self {
        Self {
            n_frequencies: 4,
            include_input: true,
        }
    }
}

/// NeRF's frequency (positional) encoding, laid out exactly as nerf-pytorch's `get_embedder`:
/// `[p, sin(2^0 p), cos(2^0 p), sin(2^1 p), cos(2^1 p), …]`, where each block holds all `input_dim`
/// coordinates and there is no π factor. Output size `input_dim·(include_input + 2L)`.
///
/// `sin`/`cos` of `2^k p` are evaluated directly for each `k` (scaling by a power of two is exact), never by
/// the double-angle recurrence, which loses accuracy in `f32` at arguments like 2^9·1.5.
#[derive(Clone, Debug)]
pub struct FrequencyEncoding {
    input_dim: usize,
    cfg: FrequencyEncodingConfig,
}

impl FrequencyEncoding {
    /// The encoding of `input_dim`-dimensional inputs.
    pub fn new(input_dim: usize, cfg: &FrequencyEncodingConfig) -> Self {
        Self {
            input_dim,
            cfg: cfg.clone(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &FrequencyEncodingConfig {
        &self.cfg
    }

    fn out_dim(&self) -> usize {
        self.input_dim * (self.cfg.include_input as usize + 2 * self.cfg.n_frequencies)
    }

    /// Encodes the samples of one chunk.
    fn forward_chunk<T: Real>(&self, input: &[T], out: &mut [T]) {
        let (d, od) = (self.input_dim, self.out_dim());
        let skip = if self.cfg.include_input { d } else { 0 };
        for (x, o) in input.chunks_exact(d).zip(out.chunks_exact_mut(od)) {
            o[..skip].copy_from_slice(&x[..skip]);
            let mut freq = T::one();
            for blk in o[skip..].chunks_exact_mut(2 * d) {
                let (s, c) = blk.split_at_mut(d);
                for j in 0..d {
                    let (sn, cs) = (freq * x[j]).sin_cos();
                    s[j] = sn;
                    c[j] = cs;
                }
                freq = freq + freq;
            }
        }
    }

    /// dL/d(input) of one chunk.
    fn backward_chunk<T: Real>(&self, input: &[T], d_out: &[T], d_in: &mut [T]) {
        let (d, od) = (self.input_dim, self.out_dim());
        let skip = if self.cfg.include_input { d } else { 0 };
        for ((x, g), dx) in input
            .chunks_exact(d)
            .zip(d_out.chunks_exact(od))
            .zip(d_in.chunks_exact_mut(d))
        {
            if skip > 0 {
                dx.copy_from_slice(&g[..d]);
            } else {
                dx.fill(T::zero());
            }
            let mut freq = T::one();
            for blk in g[skip..].chunks_exact(2 * d) {
                let (gs, gc) = blk.split_at(d);
                for j in 0..d {
                    let (sn, cs) = (freq * x[j]).sin_cos();
                    dx[j] += freq * (cs * gs[j] - sn * gc[j]);
                }
                freq = freq + freq;
            }
        }
    }
}

impl<T: Real> Encoding<T> for FrequencyEncoding {
    fn input_dim(&self) -> usize {
        self.input_dim
    }
    fn output_dim(&self) -> usize {
        self.out_dim()
    }
    fn forward(&self, input: &[T], out: &mut [T]) {
        let (d, od) = (self.input_dim, self.out_dim());
        let n = check_forward("FrequencyEncoding", d, od, input, out);
        if n <= CHUNK {
            self.forward_chunk(input, out);
        } else {
            input
                .par_chunks(CHUNK * d)
                .zip(out.par_chunks_mut(CHUNK * od))
                .for_each(|(x, o)| self.forward_chunk(x, o));
        }
    }
    fn backward(&self, input: &[T], d_out: &[T], d_params: &mut [T], d_input: Option<&mut [T]>) {
        let (d, od) = (self.input_dim, self.out_dim());
        let n = check_forward("FrequencyEncoding", d, od, input, d_out);
        assert!(d_params.is_empty(), "FrequencyEncoding has no parameters");
        let Some(d_in) = d_input else { return };
        assert_eq!(
            d_in.len(),
            n * d,
            "FrequencyEncoding: d_input length {} != {n}·{d}",
            d_in.len()
        );
        if n <= CHUNK {
            self.backward_chunk(input, d_out, d_in);
        } else {
            input
                .par_chunks(CHUNK * d)
                .zip(d_out.par_chunks(CHUNK * od))
                .zip(d_in.par_chunks_mut(CHUNK * d))
                .for_each(|((x, g), dx)| self.backward_chunk(x, g, dx));
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

    #[test]
    fn output_dims_match_the_paper() {
        let p = FrequencyEncoding::new(3, &FrequencyEncodingConfig::nerf_position());
        let d = FrequencyEncoding::new(3, &FrequencyEncodingConfig::nerf_direction());
        assert_eq!(Encoding::<f32>::output_dim(&p), 63);
        assert_eq!(Encoding::<f32>::output_dim(&d), 27);
        let no_in = FrequencyEncoding::new(
            3,
            &FrequencyEncodingConfig {
                n_frequencies: 4,
                include_input: false,
            },
        );
        assert_eq!(Encoding::<f32>::output_dim(&no_in), 24);
        assert_eq!(Encoding::<f32>::n_params(&p), 0);
    }

    fn check_reference<T: Real>(tol: f64) {
        let Some(path) =
            nerf_core::shared::reference(env!("CARGO_MANIFEST_DIR"), "positional_encoding.json")
        else {
            return;
        };
        let j: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        for (inp, out, cfg) in [
            (
                "points",
                "points_embedded_f64",
                FrequencyEncodingConfig::nerf_position(),
            ),
            (
                "dirs",
                "dirs_embedded_f64",
                FrequencyEncodingConfig::nerf_direction(),
            ),
        ] {
            let x: Vec<T> = flat(&j["inputs"][inp]).into_iter().map(T::c).collect();
            let expect = flat(&j["outputs"][out]);
            let enc = FrequencyEncoding::new(3, &cfg);
            let mut y = vec![T::zero(); expect.len()];
            enc.forward(&x, &mut y);
            let err = y
                .iter()
                .zip(&expect)
                .map(|(a, b)| (a.f64() - b).abs())
                .fold(0.0, f64::max);
            assert!(err < tol, "{inp}: max error {err} >= {tol}");
        }
    }

    #[test]
    fn matches_nerf_pytorch_reference_f32() {
        check_reference::<f32>(1e-6);
    }

    #[test]
    fn matches_nerf_pytorch_reference_f64() {
        check_reference::<f64>(1e-12);
    }

    #[test]
    fn layout_is_input_then_sin_cos_blocks() {
        let enc = FrequencyEncoding::new(
            2,
            &FrequencyEncodingConfig {
                n_frequencies: 3,
                include_input: true,
            },
        );
        let x = [0.3f64, -1.1];
        let mut y = [0.0f64; 14];
        enc.forward(&x, &mut y);
        assert_eq!(&y[..2], &x);
        for k in 0..3 {
            let f = (1u32 << k) as f64;
            for j in 0..2 {
                assert_eq!(y[2 + 4 * k + j], (f * x[j]).sin());
                assert_eq!(y[4 + 4 * k + j], (f * x[j]).cos());
            }
        }
    }

    #[test]
    fn parallel_path_equals_serial_path() {
        let enc = FrequencyEncoding::new(3, &FrequencyEncodingConfig::nerf_position());
        let mut r = nerf_core::rng(1, 0);
        let n = 3 * CHUNK + 7;
        let x: Vec<f32> = (0..3 * n).map(|_| r.gen::<f32>() * 3.0 - 1.5).collect();
        let mut y = vec![0.0f32; 63 * n];
        enc.forward(&x, &mut y);
        let mut y1 = vec![0.0f32; 63];
        let g: Vec<f32> = (0..63 * n).map(|_| r.gen::<f32>() - 0.5).collect();
        let mut dx = vec![0.0f32; 3 * n];
        enc.backward(&x, &g, &mut [], Some(&mut dx));
        for k in [0, CHUNK, n - 1] {
            enc.forward(&x[3 * k..3 * k + 3], &mut y1);
            assert_eq!(&y1[..], &y[63 * k..63 * k + 63]);
            let mut dx1 = [0.0f32; 3];
            enc.backward(
                &x[3 * k..3 * k + 3],
                &g[63 * k..63 * k + 63],
                &mut [],
                Some(&mut dx1),
            );
            assert_eq!(&dx1[..], &dx[3 * k..3 * k + 3]);
        }
    }

    /// Central finite differences of L = Σ g·enc(x) in f64 against backward.
    fn fd_check(enc: &FrequencyEncoding, n: usize) {
        let d = enc.input_dim;
        let od = Encoding::<f64>::output_dim(enc);
        let mut r = nerf_core::rng(2, d as u64);
        let x: Vec<f64> = (0..n * d).map(|_| r.gen::<f64>() * 3.0 - 1.5).collect();
        let g: Vec<f64> = (0..n * od).map(|_| r.gen::<f64>() - 0.5).collect();
        let mut dx = vec![f64::NAN; n * d];
        enc.backward(&x, &g, &mut [], Some(&mut dx));
        let loss = |x: &[f64]| {
            let mut y = vec![0.0; n * od];
            enc.forward(x, &mut y);
            y.iter().zip(&g).map(|(a, b)| a * b).sum::<f64>()
        };
        // Small step: the 2^9 band has third derivatives ~1e8, so truncation error needs h ≲ 1e-7.
        let h = 1e-7;
        for i in 0..n * d {
            let mut xp = x.clone();
            xp[i] += h;
            let mut xm = x.clone();
            xm[i] -= h;
            let fd = (loss(&xp) - loss(&xm)) / (2.0 * h);
            let rel = (fd - dx[i]).abs() / dx[i].abs().max(1.0);
            assert!(
                rel < 1e-6,
                "d_input[{i}]: analytic {} vs fd {fd} (rel {rel})",
                dx[i]
            );
        }
    }

    #[test]
    fn backward_matches_finite_differences_f64() {
        fd_check(
            &FrequencyEncoding::new(3, &FrequencyEncodingConfig::nerf_position()),
            5,
        );
        fd_check(
            &FrequencyEncoding::new(
                3,
                &FrequencyEncodingConfig {
                    n_frequencies: 4,
                    include_input: false,
                },
            ),
            4,
        );
        fd_check(
            &FrequencyEncoding::new(
                2,
                &FrequencyEncodingConfig {
                    n_frequencies: 0,
                    include_input: true,
                },
            ),
            3,
        );
    }

    #[test]
    fn config_builds_boxed_encodings() {
        let cfg: EncodingConfig =
            serde_json::from_str(r#"{"otype":"frequency","n_frequencies":4,"include_input":true}"#)
                .unwrap();
        assert_eq!(
            cfg,
            EncodingConfig::Frequency(FrequencyEncodingConfig::nerf_direction())
        );
        let e = cfg.build::<f32>(3);
        assert_eq!((e.input_dim(), e.output_dim()), (3, 27));
        let id = EncodingConfig::Identity.build::<f64>(4);
        let x = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0];
        let mut y = [0.0; 8];
        id.forward(&x, &mut y);
        assert_eq!(x, y);
        let mut dx = [0.0; 8];
        id.backward(&x, &y, &mut [], Some(&mut dx));
        assert_eq!(dx, x);
    }
}
