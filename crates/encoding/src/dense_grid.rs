//! [`DenseGrid`]: `channels` values on every vertex of a `(R+1)³` lattice over `[0,1]³`, read by
//! trilinear interpolation.
//!
//! Parameters are stored channel-major: channel `c` owns `params[c·V .. (c+1)·V]` with
//! `V = (R+1)³` and vertex `(x, y, z)` at `(z·(R+1) + y)·(R+1) + x`. The forward pass is parallel
//! over chunks of samples; the parameter backward is parallel over channels (disjoint ranges of
//! the gradient, so it is race-free and deterministic: each channel scatters its samples in
//! order, exactly as the serial pass does).

use nerf_core::Real;
use rayon::prelude::*;

/// Samples per parallel chunk of the forward and input-gradient passes.
const CHUNK: usize = 4096;

/// Errors raised when a [`DenseGrid`] is built.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum DenseGridError {
    /// The resolution is zero or the lattice would not fit in memory.
    #[error("dense grid: resolution must be in 1..=1024, got {0}")]
    Resolution(usize),
    /// No channels.
    #[error("dense grid: channels must be at least 1, got {0}")]
    Channels(usize),
}

/// A dense trilinear grid of `channels` values per lattice vertex over `[0,1]³`.
#[derive(Clone, Debug)]
pub struct DenseGrid<T: Real> {
    resolution: usize,
    channels: usize,
    params: Vec<T>,
}

/// The 8 corner vertex indices and trilinear weights of a point, plus the cell-local fractions
/// and whether each axis was clamped (for the input gradient).
#[derive(Clone, Copy)]
struct Cell<T> {
    idx: [usize; 8],
    w: [T; 8],
    frac: [T; 3],
    inside: [bool; 3],
}

impl<T: Real> DenseGrid<T> {
    /// A grid of `resolution` cells per axis (`resolution + 1` vertices) with every value zero.
    pub fn zeros(resolution: usize, channels: usize) -> Result<Self, DenseGridError> {
        if !(1..=1024).contains(&resolution) {
            return Err(DenseGridError::Resolution(resolution));
        }
        if channels == 0 {
            return Err(DenseGridError::Channels(channels));
        }
        let v = (resolution + 1).pow(3);
        Ok(Self { resolution, channels, params: vec![T::zero(); v * channels] })
    }

    /// A grid with values drawn from `U(−scale, scale)`.
    pub fn uniform(
        resolution: usize,
        channels: usize,
        scale: f64,
        rng: &mut nerf_core::Rng,
    ) -> Result<Self, DenseGridError> {
        use rand::Rng as _;
        let mut g = Self::zeros(resolution, channels)?;
        for p in &mut g.params {
            *p = T::c(scale * (2.0 * rng.gen::<f64>() - 1.0));
        }
        Ok(g)
    }

    /// Cells per axis `R`.
    pub fn resolution(&self) -> usize {
        self.resolution
    }

    /// Values per vertex.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Vertices `(R+1)³` (the length of one channel's range of the parameters).
    pub fn n_vertices(&self) -> usize {
        (self.resolution + 1).pow(3)
    }

    /// Flat index of channel `c` at vertex `(x, y, z)` in [`params`](Self::params).
    pub fn index(&self, c: usize, xyz: [usize; 3]) -> usize {
        let r1 = self.resolution + 1;
        assert!(c < self.channels && xyz.iter().all(|&v| v < r1), "DenseGrid::index out of range");
        c * self.n_vertices() + (xyz[2] * r1 + xyz[1]) * r1 + xyz[0]
    }

    /// The parameters (channel-major).
    pub fn params(&self) -> &[T] {
        &self.params
    }

    /// The parameters, mutable.
    pub fn params_mut(&mut self) -> &mut [T] {
        &mut self.params
    }

    #[inline(always)]
    fn cell(&self, p: &[T]) -> Cell<T> {
        let r = self.resolution;
        let rt = T::c(r as f64);
        let mut base = [0usize; 3];
        let mut frac = [T::zero(); 3];
        let mut inside = [true; 3];
        for a in 0..3 {
            let x = p[a];
            inside[a] = x >= T::zero() && x <= T::one();
            let s = x.max(T::zero()).min(T::one()) * rt;
            // The far face x = 1 lands in the last cell with fraction 1.
            let i = s.floor().to_usize().unwrap_or(0).min(r - 1);
            base[a] = i;
            frac[a] = s - T::c(i as f64);
        }
        let r1 = r + 1;
        let o = (base[2] * r1 + base[1]) * r1 + base[0];
        let mut idx = [0usize; 8];
        let mut w = [T::zero(); 8];
        for k in 0..8 {
            let (dx, dy, dz) = (k & 1, (k >> 1) & 1, (k >> 2) & 1);
            idx[k] = o + (dz * r1 + dy) * r1 + dx;
            let f = |d: usize, a: usize| if d == 1 { frac[a] } else { T::one() - frac[a] };
            w[k] = f(dx, 0) * f(dy, 1) * f(dz, 2);
        }
        Cell { idx, w, frac, inside }
    }

    fn check(&self, what: &str, input: &[T], other: &[T]) -> usize {
        assert_eq!(input.len() % 3, 0, "DenseGrid::{what}: input length {} is not a multiple of 3", input.len());
        let n = input.len() / 3;
        assert_eq!(
            other.len(),
            n * self.channels,
            "DenseGrid::{what}: buffer length {} != {n}·{}",
            other.len(),
            self.channels
        );
        n
    }

    fn forward_chunk(&self, input: &[T], out: &mut [T]) {
        let (c, v) = (self.channels, self.n_vertices());
        for (p, o) in input.chunks_exact(3).zip(out.chunks_exact_mut(c)) {
            let cell = self.cell(p);
            for (ch, slot) in o.iter_mut().enumerate() {
                let g = &self.params[ch * v..(ch + 1) * v];
                let mut s = T::zero();
                for k in 0..8 {
                    s += cell.w[k] * g[cell.idx[k]];
                }
                *slot = s;
            }
        }
    }

    /// Interpolates at `n = input.len()/3` points of `[0,1]³` (clamped); `out` is `n·channels`,
    /// row-major. Parallel over chunks of samples.
    pub fn forward(&self, input: &[T], out: &mut [T]) {
        let n = self.check("forward", input, out);
        let c = self.channels;
        if n <= CHUNK {
            self.forward_chunk(input, out);
        } else {
            input
                .par_chunks(3 * CHUNK)
                .zip(out.par_chunks_mut(c * CHUNK))
                .for_each(|(x, o)| self.forward_chunk(x, o));
        }
    }

    /// [`forward`](Self::forward) on the calling thread only (reference for tests).
    pub fn forward_serial(&self, input: &[T], out: &mut [T]) {
        self.check("forward", input, out);
        self.forward_chunk(input, out);
    }

    /// Scatter-adds one channel's gradient: `d_channel += Σ_k w_k · d_out[k·C + ch]`.
    fn backward_channel(&self, ch: usize, input: &[T], d_out: &[T], d_channel: &mut [T]) {
        let c = self.channels;
        for (k, p) in input.chunks_exact(3).enumerate() {
            let g = d_out[k * c + ch];
            if g == T::zero() {
                continue;
            }
            let cell = self.cell(p);
            for j in 0..8 {
                d_channel[cell.idx[j]] += cell.w[j] * g;
            }
        }
    }

    fn input_grad_chunk(&self, input: &[T], d_out: &[T], d_in: &mut [T]) {
        let (c, v) = (self.channels, self.n_vertices());
        let rt = T::c(self.resolution as f64);
        for ((p, g), dx) in input.chunks_exact(3).zip(d_out.chunks_exact(c)).zip(d_in.chunks_exact_mut(3)) {
            let cell = self.cell(p);
            let f = cell.frac;
            let mut acc = [T::zero(); 3];
            for (ch, &gc) in g.iter().enumerate() {
                let vals = &self.params[ch * v..(ch + 1) * v];
                for k in 0..8 {
                    let bits = [k & 1, (k >> 1) & 1, (k >> 2) & 1];
                    let val = vals[cell.idx[k]] * gc;
                    for a in 0..3 {
                        // ∂w_k/∂frac_a: the factor of axis a becomes ±1.
                        let mut dw = if bits[a] == 1 { T::one() } else { -T::one() };
                        for b in 0..3 {
                            if b != a {
                                dw *= if bits[b] == 1 { f[b] } else { T::one() - f[b] };
                            }
                        }
                        acc[a] += dw * val;
                    }
                }
            }
            for a in 0..3 {
                dx[a] = if cell.inside[a] { acc[a] * rt } else { T::zero() };
            }
        }
    }

    /// Given dL/d(out) (`n·channels`), accumulates dL/d(params) into `d_params` (same layout as
    /// [`params`](Self::params)) and, when `d_input` is Some, writes dL/d(input) (`3n`; zero on an
    /// axis where the point was clamped). Parallel over channels (and over sample chunks for the
    /// input gradient); the result is bit-identical to [`backward_serial`](Self::backward_serial).
    pub fn backward(&self, input: &[T], d_out: &[T], d_params: &mut [T], d_input: Option<&mut [T]>) {
        let n = self.check("backward", input, d_out);
        let v = self.n_vertices();
        assert_eq!(d_params.len(), self.params.len(), "DenseGrid::backward: d_params length");
        let params = |d_params: &mut [T]| {
            d_params
                .par_chunks_mut(v)
                .enumerate()
                .for_each(|(ch, d)| self.backward_channel(ch, input, d_out, d));
        };
        match d_input {
            None => params(d_params),
            Some(d_in) => {
                assert_eq!(d_in.len(), 3 * n, "DenseGrid::backward: d_input length");
                let c = self.channels;
                rayon::join(|| params(d_params), || {
                    input
                        .par_chunks(3 * CHUNK)
                        .zip(d_out.par_chunks(c * CHUNK))
                        .zip(d_in.par_chunks_mut(3 * CHUNK))
                        .for_each(|((x, g), d)| self.input_grad_chunk(x, g, d));
                });
            }
        }
    }

    /// [`backward`](Self::backward) on the calling thread only (reference for tests).
    pub fn backward_serial(&self, input: &[T], d_out: &[T], d_params: &mut [T], d_input: Option<&mut [T]>) {
        let n = self.check("backward", input, d_out);
        let v = self.n_vertices();
        assert_eq!(d_params.len(), self.params.len(), "DenseGrid::backward: d_params length");
        for (ch, d) in d_params.chunks_mut(v).enumerate() {
            self.backward_channel(ch, input, d_out, d);
        }
        if let Some(d_in) = d_input {
            assert_eq!(d_in.len(), 3 * n, "DenseGrid::backward: d_input length");
            self.input_grad_chunk(input, d_out, d_in);
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::needless_range_loop)] // index loops read best in finite-difference checks

    use super::*;
    use rand::Rng as _;

    /// Points in `[0,1]³` whose fractional cell coordinates stay ≥ 0.05 from every face, so a
    /// finite-difference step never crosses a cell boundary (where trilinear interpolation has a kink).
    fn interior_points(n: usize, res: usize, rng: &mut nerf_core::Rng) -> Vec<f64> {
        let mut out = Vec::new();
        while out.len() < 3 * n {
            let p: [f64; 3] = [rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0)];
            if p.iter().all(|&x| (0.05..0.95).contains(&(x * res as f64).fract())) {
                out.extend_from_slice(&p);
            }
        }
        out
    }

    fn check(fd: f64, g: f64, what: &str) {
        assert!((fd - g).abs() <= 1e-7 + 1e-5 * fd.abs().max(g.abs()), "{what}: fd {fd} vs analytic {g}");
    }

    #[test]
    fn grid_returns_stored_values_at_vertices_and_clamps() {
        let mut rng = nerf_core::rng(1, 0);
        let g = DenseGrid::<f64>::uniform(5, 3, 1.0, &mut rng).unwrap();
        let mut pts = Vec::new();
        let mut want = Vec::new();
        for z in 0..=5 {
            for y in [0, 2, 5] {
                for x in [0, 1, 4, 5] {
                    pts.extend([x as f64 / 5.0, y as f64 / 5.0, z as f64 / 5.0]);
                    want.extend((0..3).map(|c| g.params()[g.index(c, [x, y, z])]));
                }
            }
        }
        let mut out = vec![0.0; want.len()];
        g.forward(&pts, &mut out);
        for (o, w) in out.iter().zip(&want) {
            assert!((o - w).abs() < 1e-12, "{o} vs {w}");
        }
        // Outside the box the value of the nearest face point is returned.
        let (mut a, mut b) = ([0.0; 3], [0.0; 3]);
        g.forward(&[-0.5, 0.3, 1.7], &mut a);
        g.forward(&[0.0, 0.3, 1.0], &mut b);
        assert_eq!(a, b);
        // Midpoint of an edge = mean of its two vertices.
        let mut m = [0.0; 3];
        g.forward(&[0.3, 0.4, 0.6], &mut m);
        for c in 0..3 {
            let v = 0.5 * (g.params()[g.index(c, [1, 2, 3])] + g.params()[g.index(c, [2, 2, 3])]);
            assert!((m[c] - v).abs() < 1e-12);
        }
        assert!(DenseGrid::<f32>::zeros(0, 1).is_err() && DenseGrid::<f32>::zeros(4, 0).is_err());
    }

    #[test]
    fn grid_backward_matches_finite_differences_f64() {
        let mut rng = nerf_core::rng(2, 0);
        let (res, ch, n) = (3, 2, 6);
        let mut g = DenseGrid::<f64>::uniform(res, ch, 1.0, &mut rng).unwrap();
        let x = interior_points(n, res, &mut rng);
        let w: Vec<f64> = (0..n * ch).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let loss = |g: &DenseGrid<f64>, x: &[f64]| {
            let mut o = vec![0.0; n * ch];
            g.forward(x, &mut o);
            o.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
        };
        let mut dp = vec![0.0; g.params().len()];
        let mut dx = vec![0.0; 3 * n];
        g.backward(&x, &w, &mut dp, Some(&mut dx));
        let h = 1e-6;
        let mut touched = 0;
        for i in 0..dp.len() {
            let orig = g.params()[i];
            g.params_mut()[i] = orig + h;
            let lp = loss(&g, &x);
            g.params_mut()[i] = orig - h;
            let lm = loss(&g, &x);
            g.params_mut()[i] = orig;
            check((lp - lm) / (2.0 * h), dp[i], &format!("param {i}"));
            touched += (dp[i] != 0.0) as usize;
        }
        assert!(touched >= 16, "only {touched} vertices received gradient");
        for i in 0..3 * n {
            let mut xp = x.clone();
            xp[i] += h;
            let mut xm = x.clone();
            xm[i] -= h;
            check((loss(&g, &xp) - loss(&g, &xm)) / (2.0 * h), dx[i], &format!("input {i}"));
        }
        assert!(dx.iter().all(|v| v.abs() > 1e-9), "input gradient vanished");
    }

    #[test]
    fn grid_parallel_equals_serial_bit_identically() {
        let mut rng = nerf_core::rng(3, 0);
        let g = DenseGrid::<f32>::uniform(8, 5, 1.0, &mut rng).unwrap();
        let n = 20_000; // several parallel chunks
        let x: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-0.1..1.1)).collect();
        let d: Vec<f32> = (0..5 * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let (mut o1, mut o2) = (vec![0.0; 5 * n], vec![1.0; 5 * n]);
        g.forward(&x, &mut o1);
        g.forward_serial(&x, &mut o2);
        assert_eq!(o1, o2);
        let (mut p1, mut p2) = (vec![0.5f32; g.params().len()], vec![0.5f32; g.params().len()]);
        let (mut x1, mut x2) = (vec![0.0; 3 * n], vec![1.0; 3 * n]);
        g.backward(&x, &d, &mut p1, Some(&mut x1));
        g.backward_serial(&x, &d, &mut p2, Some(&mut x2));
        assert!(p1.iter().zip(&p2).all(|(a, b)| a.to_bits() == b.to_bits()), "parameter gradients differ");
        assert!(x1.iter().zip(&x2).all(|(a, b)| a.to_bits() == b.to_bits()), "input gradients differ");
        assert!(p1.iter().filter(|&&v| v != 0.5).count() > 1000, "backward accumulated nothing");
        // Accumulates: a second call doubles the increment.
        let mut p3 = p1.clone();
        g.backward(&x, &d, &mut p3, None);
        let i = p1.iter().position(|&v| (v - 0.5).abs() > 1e-2).unwrap();
        assert!(((p3[i] - 0.5) - 2.0 * (p1[i] - 0.5)).abs() < 1e-3 * (p1[i] - 0.5).abs().max(1.0));
    }
}
