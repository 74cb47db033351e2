//! Multilayer perceptrons with hand-written backward passes over batched, row-major activations (GEMM-backed).
//!
//! An [`Mlp`] is tiny-cuda-nn's "Network" part: a stack of fully connected layers configured by plain
//! serde data ([`MlpConfig`]), composed with an encoding by a field. Batches are row-major: sample `k`'s
//! vector is `x[k*dim..(k+1)*dim]`. Each layer computes `y = act(x·Wᵀ + b)` with `W` stored `out × in`
//! row-major; every product (forward, `dW += dZᵀ·X`, `dX = dZ·W`) goes through [`matmul()`], a safe
//! wrapper of the multithreaded `gemm` crate. Everything is generic over [`nerf_core::Real`], so the
//! finite-difference checks run the same code in `f64`.
//!
//! Parameters are one flat buffer (layer by layer: `W` row-major, then `b`), gradients another of the
//! same layout, so an optimiser sees a single group ([`Mlp::params_and_grads_mut`]).

pub mod matmul;

pub use matmul::{matmul, MatMut, MatRef, Parallelism};

pub use nerf_core::round_f16;
use nerf_core::Real;
use rand::Rng as _;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Errors in an [`MlpConfig`] (which usually comes from a config file).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MlpError {
    /// A dimension that must be positive is zero.
    #[error("MLP config: {0} must be positive")]
    ZeroDim(&'static str),
    /// A skip index outside `1..hidden_layers`.
    #[error("MLP config: skip index {index} is not a hidden layer in 1..{hidden_layers} (layer 0 already takes the input)")]
    SkipOutOfRange {
        /// The offending index.
        index: usize,
        /// The number of hidden layers.
        hidden_layers: usize,
    },
    /// A skip index listed twice.
    #[error("MLP config: skip index {0} is listed twice")]
    DuplicateSkip(usize),
}

/// Element-wise activation. Backward uses the derivative expressed through the saved *output* `y`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Activation {
    /// Identity: `y = z`, `dy/dz = 1`.
    None,
    /// `y = max(z, 0)`, `dy/dz = [y > 0]`.
    Relu,
    /// `y = 1/(1+e^−z)`, `dy/dz = y(1−y)`.
    Sigmoid,
    /// `y = tanh z`, `dy/dz = 1−y²`.
    Tanh,
    /// `y = ln(1+e^z)`, `dy/dz = sigmoid(z) = 1−e^−y`.
    Softplus,
    /// `y = e^z`, `dy/dz = y`.
    Exp,
}

impl Activation {
    /// The activation of a pre-activation `z`.
    #[inline(always)]
    pub fn apply<T: Real>(self, z: T) -> T {
        match self {
            Activation::None => z,
            Activation::Relu => z.max(T::zero()),
            Activation::Sigmoid => T::one() / (T::one() + (-z).exp()),
            Activation::Tanh => z.tanh(),
            Activation::Softplus => z.max(T::zero()) + (-z.abs()).exp().ln_1p(),
            Activation::Exp => z.exp(),
        }
    }

    /// `dy/dz` from the output `y = apply(z)`.
    #[inline(always)]
    pub fn derivative_from_output<T: Real>(self, y: T) -> T {
        match self {
            Activation::None => T::one(),
            Activation::Relu => {
                if y > T::zero() {
                    T::one()
                } else {
                    T::zero()
                }
            }
            Activation::Sigmoid => y * (T::one() - y),
            Activation::Tanh => T::one() - y * y,
            Activation::Softplus => -(-y).exp_m1(),
            Activation::Exp => y,
        }
    }
}

/// Configuration of an [`Mlp`].
///
/// The network has `hidden_layers + 1` linear layers: hidden layers `0..hidden_layers` of width
/// `hidden_dim` followed by `hidden_activation`, then the output layer (`output_dim`, `output_activation`).
/// With `hidden_layers == 0` it is a single linear layer `input_dim → output_dim`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MlpConfig {
    /// Floats per input sample.
    pub input_dim: usize,
    /// Floats per output sample.
    pub output_dim: usize,
    /// Width of every hidden layer.
    pub hidden_dim: usize,
    /// Number of hidden layers (0 = a single linear layer).
    pub hidden_layers: usize,
    /// Activation after every hidden layer.
    pub hidden_activation: Activation,
    /// Activation after the output layer.
    pub output_activation: Activation,
    /// Hidden layer indices `i` (0-based, counted over the hidden layers, each in `1..hidden_layers`) whose
    /// INPUT is the network input concatenated with the previous hidden activation, as `[input, h_{i−1}]`
    /// (fan-in `input_dim + hidden_dim`; `W`'s first `input_dim` columns multiply the input).
    ///
    /// nerf-pytorch's `skips=[4]` (`if i in skips: h = cat([input_pts, h])` *after* layer 4) is `skips: vec![5]`
    /// here: the 6th linear layer (index 5) has fan-in 63+256 = 319, exactly nerf-pytorch's `pts_linears[5]`.
    /// See [`MlpConfig::nerf_trunk`].
    pub skips: Vec<usize>,
    /// Whether the layers have biases.
    pub bias: bool,
}

impl MlpConfig {
    /// The NeRF paper's trunk as nerf-pytorch builds it: 8 hidden ReLU layers of 256, the input re-concatenated
    /// after the 5th (index 4, so `skips = [5]`), and a linear output layer of `output_dim`
    /// (e.g. 1 + 256: σ and the feature vector, nerf-pytorch's `alpha_linear` and `feature_linear` fused).
    pub fn nerf_trunk(input_dim: usize, output_dim: usize) -> Self {
        Self {
            input_dim,
            output_dim,
            hidden_dim: 256,
            hidden_layers: 8,
            hidden_activation: Activation::Relu,
            output_activation: Activation::None,
            skips: vec![5],
            bias: true,
        }
    }

    /// Checks the dimensions and skip indices.
    pub fn validate(&self) -> Result<(), MlpError> {
        if self.input_dim == 0 {
            return Err(MlpError::ZeroDim("input_dim"));
        }
        if self.output_dim == 0 {
            return Err(MlpError::ZeroDim("output_dim"));
        }
        if self.hidden_layers > 0 && self.hidden_dim == 0 {
            return Err(MlpError::ZeroDim("hidden_dim"));
        }
        for (k, &s) in self.skips.iter().enumerate() {
            if s == 0 || s >= self.hidden_layers {
                return Err(MlpError::SkipOutOfRange {
                    index: s,
                    hidden_layers: self.hidden_layers,
                });
            }
            if self.skips[..k].contains(&s) {
                return Err(MlpError::DuplicateSkip(s));
            }
        }
        Ok(())
    }
}

/// One linear layer's shape and where its parameters live in the flat buffer.
#[derive(Clone, Debug)]
struct Layer {
    /// Fan-in (including the concatenated input for a skip layer).
    fan_in: usize,
    /// Fan-out.
    out: usize,
    /// Whether the input is `[x, h]` (a skip layer).
    skip: bool,
    /// Offset of `W` (`out × fan_in`, row-major).
    w_off: usize,
    /// Offset of `b` (`out`), when the layer has a bias.
    b_off: Option<usize>,
    act: Activation,
}

/// What [`Mlp::forward`] keeps for [`Mlp::backward`]: the post-activations of every layer, plus backward's
/// scratch. Buffers only grow, so reusing one tape makes forward/backward allocation-free once warmed up.
#[derive(Debug)]
pub struct MlpTape<T> {
    n: usize,
    acts: Vec<Vec<T>>,
    dz: Vec<T>,
    dh: Vec<T>,
    /// Under [`Mlp::set_f16_arithmetic`]: the weights and the input as the forward read them
    /// (rounded to f16), and backward's scaled parameter gradients before their rounding.
    w16: Vec<T>,
    x16: Vec<T>,
    dw: Vec<T>,
}

impl<T> Default for MlpTape<T> {
    fn default() -> Self {
        Self {
            n: 0,
            acts: Vec::new(),
            dz: Vec::new(),
            dh: Vec::new(),
            w16: Vec::new(),
            x16: Vec::new(),
            dw: Vec::new(),
        }
    }
}

impl<T> MlpTape<T> {
    /// Number of samples of the last forward.
    pub fn n(&self) -> usize {
        self.n
    }

    /// The last forward's output (`n·output_dim`, what [`Mlp::forward`] returned; empty before
    /// any forward).
    pub fn output(&self) -> &[T] {
        self.acts.last().map_or(&[], |a| &a[..])
    }
}

/// Scratch of [`Mlp::infer`] (two ping-pong activation buffers). One per thread.
#[derive(Debug)]
pub struct MlpScratch<T> {
    a: Vec<T>,
    b: Vec<T>,
    w16: Vec<T>,
    x16: Vec<T>,
}

impl<T> Default for MlpScratch<T> {
    fn default() -> Self {
        Self {
            a: Vec::new(),
            b: Vec::new(),
            w16: Vec::new(),
            x16: Vec::new(),
        }
    }
}

/// `v` rounded to f16 in place.
fn round_all<T: Real>(v: &mut [T], parallel: bool) {
    if parallel && v.len() > EW_CHUNK {
        v.par_chunks_mut(EW_CHUNK).for_each(|c| c.iter_mut().for_each(|x| *x = round_f16(*x)));
    } else {
        v.iter_mut().for_each(|x| *x = round_f16(*x));
    }
}

/// `dst` := `src` rounded to f16 (`dst` grows only past its capacity).
fn round_into<T: Real>(dst: &mut Vec<T>, src: &[T]) {
    dst.clear();
    dst.extend(src.iter().map(|&x| round_f16(x)));
}

/// Resizes `v` to `len` (allocates only when it grows past its capacity).
fn ensure<T: Real>(v: &mut Vec<T>, len: usize) {
    if v.len() < len {
        v.resize(len, T::zero());
    } else {
        v.truncate(len);
    }
}

/// Elements per rayon task in the element-wise passes; smaller passes run on the calling thread.
const EW_CHUNK: usize = 1 << 14;

/// `z[r, j] = act(z[r, j] + b[j])` over the rows of `z` (width `w`).
fn bias_act<T: Real>(z: &mut [T], w: usize, bias: Option<&[T]>, act: Activation, parallel: bool) {
    let kernel = |z: &mut [T]| {
        for row in z.chunks_exact_mut(w) {
            if let Some(b) = bias {
                for (v, &bj) in row.iter_mut().zip(b) {
                    *v += bj;
                }
            }
            match act {
                Activation::None => {}
                Activation::Relu => row.iter_mut().for_each(|v| *v = v.max(T::zero())),
                _ => row.iter_mut().for_each(|v| *v = act.apply(*v)),
            }
        }
    };
    let rows_per = (EW_CHUNK / w).max(1);
    if parallel && z.len() > EW_CHUNK {
        z.par_chunks_mut(rows_per * w).for_each(kernel);
    } else {
        kernel(z);
    }
}

/// `d[i] *= act'(y[i])` element-wise.
fn mul_act_derivative<T: Real>(d: &mut [T], y: &[T], act: Activation, parallel: bool) {
    assert_eq!(d.len(), y.len());
    let kernel = |d: &mut [T], y: &[T]| match act {
        Activation::None => {}
        Activation::Relu => d.iter_mut().zip(y).for_each(|(g, &y)| {
            if y <= T::zero() {
                *g = T::zero()
            }
        }),
        _ => d
            .iter_mut()
            .zip(y)
            .for_each(|(g, &y)| *g *= act.derivative_from_output(y)),
    };
    if parallel && d.len() > EW_CHUNK {
        d.par_chunks_mut(EW_CHUNK)
            .zip(y.par_chunks(EW_CHUNK))
            .for_each(|(d, y)| kernel(d, y));
    } else {
        kernel(d, y);
    }
}

/// `db[j] += Σ_r dz[r, j]` (width `w`), parallel over column blocks.
fn add_col_sums<T: Real>(db: &mut [T], dz: &[T], w: usize, parallel: bool) {
    const COLS: usize = 16;
    let kernel = |c0: usize, db: &mut [T]| {
        let mut acc = [T::zero(); COLS];
        let acc = &mut acc[..db.len()];
        for row in dz.chunks_exact(w) {
            for (a, &g) in acc.iter_mut().zip(&row[c0..c0 + db.len()]) {
                *a += g;
            }
        }
        for (d, a) in db.iter_mut().zip(acc.iter()) {
            *d += *a;
        }
    };
    if parallel && dz.len() > EW_CHUNK {
        db.par_chunks_mut(COLS)
            .enumerate()
            .for_each(|(i, d)| kernel(i * COLS, d));
    } else {
        db.chunks_mut(COLS)
            .enumerate()
            .for_each(|(i, d)| kernel(i * COLS, d));
    }
}

/// A multilayer perceptron with its parameters and accumulated gradients.
#[derive(Clone, Debug)]
pub struct Mlp<T: Real> {
    /// The configuration it was built from (read-only in practice: changing it does not rebuild the layers).
    pub config: MlpConfig,
    params: Vec<T>,
    grads: Vec<T>,
    layers: Vec<Layer>,
    /// [`Mlp::set_f16_arithmetic`]'s loss scale.
    f16: Option<f32>,
}

impl<T: Real> Mlp<T> {
    /// Init like PyTorch nn.Linear (U(−1/√fan_in, 1/√fan_in) for W and b) from `rng`.
    ///
    /// Panics with the [`MlpError`] message if the config is invalid; use [`Mlp::try_new`] for configs
    /// that come from users.
    pub fn new(config: MlpConfig, rng: &mut nerf_core::Rng) -> Self {
        match Self::try_new(config, rng) {
            Ok(m) => m,
            Err(e) => panic!("{e}"),
        }
    }

    /// Like [`Mlp::new`], but returns an error for an invalid config.
    pub fn try_new(config: MlpConfig, rng: &mut nerf_core::Rng) -> Result<Self, MlpError> {
        config.validate()?;
        let mut layers = Vec::with_capacity(config.hidden_layers + 1);
        let mut off = 0;
        let mut prev = config.input_dim;
        for i in 0..=config.hidden_layers {
            let last = i == config.hidden_layers;
            let skip = config.skips.contains(&i);
            let fan_in = prev + if skip { config.input_dim } else { 0 };
            let out = if last {
                config.output_dim
            } else {
                config.hidden_dim
            };
            let w_off = off;
            off += out * fan_in;
            let b_off = config.bias.then(|| {
                off += out;
                off - out
            });
            let act = if last {
                config.output_activation
            } else {
                config.hidden_activation
            };
            layers.push(Layer {
                fan_in,
                out,
                skip,
                w_off,
                b_off,
                act,
            });
            prev = out;
        }
        let mut params = vec![T::zero(); off];
        for l in &layers {
            let bound = 1.0 / (l.fan_in as f64).sqrt();
            let mut init = |s: &mut [T]| {
                s.iter_mut()
                    .for_each(|p| *p = T::c((2.0 * rng.gen::<f64>() - 1.0) * bound))
            };
            init(&mut params[l.w_off..l.w_off + l.out * l.fan_in]);
            if let Some(b) = l.b_off {
                init(&mut params[b..b + l.out]);
            }
        }
        Ok(Self {
            config,
            grads: vec![T::zero(); off],
            params,
            layers,
            f16: None,
        })
    }

    /// Emulates tiny-cuda-nn's half-precision fully fused MLPs (on the CPU: the products still
    /// run in `T` and every value they read or write is rounded to f16): with `Some(S)`,
    /// - the forward reads the input and the weights rounded to f16 and rounds every layer's
    ///   output (after its bias and activation) to f16: what tiny-cuda-nn keeps in shared memory
    ///   between layers and hands on, [`Mlp::infer`] included;
    /// - the backward multiplies `dL/d(output)` by the loss scale `S` (tiny-cuda-nn's PyTorch
    ///   bindings use 128) and rounds it, and each layer's `dL/dz` and `dL/dh`, to f16; the
    ///   products read the rounded weights and inputs; each call's parameter gradients and
    ///   `dL/d(input)` are rounded to f16 while scaled, then divided by `S`, so that a gradient
    ///   below f16's smallest subnormal over `S` is lost, as in the original.
    ///
    /// What this leaves out: tiny-cuda-nn's tensor cores also sum the products in f16 (each
    /// partial sum rounded), which these f32/f64 products do not. The parameters themselves, and
    /// the optimiser, stay in `T` (tiny-cuda-nn's f32 master copy). `None` (the default) turns it
    /// off. Panics unless `S` is finite and positive.
    pub fn set_f16_arithmetic(&mut self, loss_scale: Option<f32>) {
        if let Some(s) = loss_scale {
            assert!(s.is_finite() && s > 0.0, "Mlp::set_f16_arithmetic: loss scale {s} is not finite and > 0");
        }
        self.f16 = loss_scale;
    }

    /// The loss scale of [`Mlp::set_f16_arithmetic`], `None` when it is off.
    pub fn f16_arithmetic(&self) -> Option<f32> {
        self.f16
    }

    /// Total number of parameters.
    pub fn n_params(&self) -> usize {
        self.params.len()
    }
    /// The flat parameters (layer by layer: `W` row-major `out × fan_in`, then `b`).
    pub fn params(&self) -> &[T] {
        &self.params
    }
    /// The flat parameters, mutable (e.g. to load a checkpoint).
    pub fn params_mut(&mut self) -> &mut [T] {
        &mut self.params
    }
    /// The accumulated gradients (same layout as the parameters).
    pub fn grads(&self) -> &[T] {
        &self.grads
    }
    /// The accumulated gradients, mutable.
    pub fn grads_mut(&mut self) -> &mut [T] {
        &mut self.grads
    }
    /// Sets every gradient to zero.
    pub fn zero_grad(&mut self) {
        self.grads.fill(T::zero());
    }
    /// Both at once for the optimiser (disjoint borrows).
    pub fn params_and_grads_mut(&mut self) -> (&mut [T], &mut [T]) {
        (&mut self.params, &mut self.grads)
    }
    /// `(fan_in, fan_out)` of each linear layer, input to output.
    pub fn layer_shapes(&self) -> Vec<(usize, usize)> {
        self.layers.iter().map(|l| (l.fan_in, l.out)).collect()
    }
    /// Offsets in the flat buffer of each layer's `W` and (if any) `b`, e.g. to give weights and biases
    /// different weight decay.
    pub fn layer_offsets(&self) -> Vec<(usize, Option<usize>)> {
        self.layers.iter().map(|l| (l.w_off, l.b_off)).collect()
    }

    /// FLOPs of one forward per sample (2·Σ fan_in·fan_out) — for GFLOP/s reporting.
    pub fn flops_per_sample(&self) -> usize {
        self.layers.iter().map(|l| 2 * l.fan_in * l.out).sum()
    }

    /// Widest activation (for scratch sizes).
    fn max_width(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.out)
            .max()
            .unwrap_or(0)
            .max(self.config.input_dim)
    }

    /// The column block `[c0, c0+cols)` of layer `l`'s `W` as an `out × cols` view.
    fn w_block<'a>(params: &'a [T], l: &Layer, c0: usize, cols: usize) -> MatRef<'a, T> {
        MatRef::new(&params[l.w_off + c0..], l.out, cols, l.fan_in, 1)
    }

    /// `z = act([x,] h · Wᵀ + b)` for layer `i`; `h` is the previous activation (None for layer 0).
    #[allow(clippy::too_many_arguments)]
    fn layer_forward(
        &self,
        params: &[T],
        i: usize,
        n: usize,
        x: &[T],
        h: Option<&[T]>,
        z: &mut [T],
        par: Parallelism,
    ) {
        let l = &self.layers[i];
        let d_in = self.config.input_dim;
        let out = l.out;
        match h {
            None => {
                matmul(
                    MatMut::row_major(z, n, out),
                    false,
                    MatRef::row_major(x, n, d_in),
                    Self::w_block(params, l, 0, d_in).t(),
                    par,
                );
            }
            Some(h) => {
                let (c0, hw) = if l.skip {
                    (d_in, l.fan_in - d_in)
                } else {
                    (0, l.fan_in)
                };
                matmul(
                    MatMut::row_major(z, n, out),
                    false,
                    MatRef::row_major(h, n, hw),
                    Self::w_block(params, l, c0, hw).t(),
                    par,
                );
                if l.skip {
                    matmul(
                        MatMut::row_major(z, n, out),
                        true,
                        MatRef::row_major(x, n, d_in),
                        Self::w_block(params, l, 0, d_in).t(),
                        par,
                    );
                }
            }
        }
        let bias = l.b_off.map(|b| &params[b..b + out]);
        let parallel = matches!(par, Parallelism::Rayon(_));
        bias_act(z, out, bias, l.act, parallel);
        if self.f16.is_some() {
            round_all(z, parallel);
        }
    }

    fn check_input(&self, n: usize, input: &[T]) {
        assert_eq!(
            input.len(),
            n * self.config.input_dim,
            "Mlp: input length {} != {n}·{}",
            input.len(),
            self.config.input_dim
        );
    }

    /// The weights and the input a forward reads: as they are, or under f16 arithmetic rounded
    /// into `w16` and `x16`.
    fn operands<'a>(&'a self, input: &'a [T], w16: &'a mut Vec<T>, x16: &'a mut Vec<T>) -> (&'a [T], &'a [T]) {
        if self.f16.is_none() {
            return (&self.params, input);
        }
        round_into(w16, &self.params);
        round_into(x16, input);
        (w16, x16)
    }

    /// Forward for n samples keeping what backward needs in `tape` (buffers reused across calls: no allocation
    /// once warmed up). Returns the output (n·output_dim), which lives in the tape.
    pub fn forward<'t>(&self, n: usize, input: &[T], tape: &'t mut MlpTape<T>) -> &'t [T] {
        self.check_input(n, input);
        let nl = self.layers.len();
        tape.n = n;
        tape.acts.resize_with(nl, Vec::new);
        let par = Parallelism::Rayon(0);
        let (params, input) = self.operands(input, &mut tape.w16, &mut tape.x16);
        for i in 0..nl {
            let (done, rest) = tape.acts.split_at_mut(i);
            let z = &mut rest[0];
            ensure(z, n * self.layers[i].out);
            let h = if i == 0 { None } else { Some(&done[i - 1][..]) };
            self.layer_forward(params, i, n, input, h, z, par);
        }
        &tape.acts[nl - 1]
    }

    /// Inference only (no tape kept beyond `scratch`), for rendering/density queries; may be called from many
    /// threads at once on different chunks (takes &self). Writes `out` (n·output_dim).
    ///
    /// Called from a rayon worker thread (e.g. inside `par_chunks`), its products run single-threaded, since the
    /// caller already parallelises; otherwise they use all rayon threads.
    pub fn infer(&self, n: usize, input: &[T], scratch: &mut MlpScratch<T>, out: &mut [T]) {
        self.check_input(n, input);
        assert_eq!(
            out.len(),
            n * self.config.output_dim,
            "Mlp::infer: out length {} != {n}·{}",
            out.len(),
            self.config.output_dim
        );
        let par = if rayon::current_thread_index().is_some() {
            Parallelism::None
        } else {
            Parallelism::Rayon(0)
        };
        let nl = self.layers.len();
        let w = self.max_width();
        let (mut a, mut b) = (
            std::mem::take(&mut scratch.a),
            std::mem::take(&mut scratch.b),
        );
        let (params, input) = self.operands(input, &mut scratch.w16, &mut scratch.x16);
        if nl > 1 {
            nerf_core::grown(&mut a, n * w);
            nerf_core::grown(&mut b, n * w);
        }
        for i in 0..nl {
            let width = self.layers[i].out;
            if i + 1 == nl {
                let h = if i == 0 {
                    None
                } else {
                    Some(&a[..n * self.layers[i - 1].out])
                };
                self.layer_forward(params, i, n, input, h, out, par);
            } else {
                let h = if i == 0 {
                    None
                } else {
                    Some(&a[..n * self.layers[i - 1].out])
                };
                self.layer_forward(params, i, n, input, h, &mut b[..n * width], par);
                std::mem::swap(&mut a, &mut b);
            }
        }
        scratch.a = a;
        scratch.b = b;
    }

    /// Backward from dL/d(output) (n·output_dim): ACCUMULATES parameter grads into self.grads, and writes
    /// dL/d(input) when d_input is Some. `input` must be the same slice passed to forward.
    pub fn backward(
        &mut self,
        n: usize,
        input: &[T],
        tape: &mut MlpTape<T>,
        d_output: &[T],
        d_input: Option<&mut [T]>,
    ) {
        self.backward_cols(n, input, tape, d_output, d_input, self.config.input_dim)
    }

    /// As [`Mlp::backward`], writing only the first `cols` columns of `d_input` (`1 ≤ cols ≤
    /// input_dim`; the others are left as they were): a field whose input mixes features with an
    /// encoding that has no parameters (the hash field's SH inputs) asks for the features' columns.
    /// The parameter gradients are those of [`Mlp::backward`] bit for bit, the columns written up to
    /// rounding.
    pub fn backward_cols(
        &mut self,
        n: usize,
        input: &[T],
        tape: &mut MlpTape<T>,
        d_output: &[T],
        d_input: Option<&mut [T]>,
        cols: usize,
    ) {
        self.check_input(n, input);
        assert!(
            (1..=self.config.input_dim).contains(&cols),
            "Mlp::backward_cols: cols {cols} outside 1..={}",
            self.config.input_dim
        );
        let nl = self.layers.len();
        assert!(
            tape.n == n && tape.acts.len() == nl,
            "Mlp::backward: the tape holds a forward of {} samples, not {n}",
            tape.n
        );
        assert_eq!(
            d_output.len(),
            n * self.config.output_dim,
            "Mlp::backward: d_output length {} != {n}·{}",
            d_output.len(),
            self.config.output_dim
        );
        let d_in = self.config.input_dim;
        let mut d_input = d_input;
        if let Some(d) = d_input.as_deref_mut() {
            assert_eq!(
                d.len(),
                n * d_in,
                "Mlp::backward: d_input length {} != {n}·{d_in}",
                d.len()
            );
            if cols == d_in {
                d.fill(T::zero());
            } else {
                d.chunks_exact_mut(d_in).for_each(|row| row[..cols].fill(T::zero()));
            }
        }
        let par = Parallelism::Rayon(0);
        let w = self.max_width();
        let (mut dz, mut dh) = (std::mem::take(&mut tape.dz), std::mem::take(&mut tape.dh));
        nerf_core::grown(&mut dz, n * w);
        nerf_core::grown(&mut dh, n * w);
        // Under f16 arithmetic the products read the weights and the input as the forward did, and
        // the parameter gradients go to `dw` (scaled by S) to be rounded before they are added.
        let (w16, x16, mut dw) = (std::mem::take(&mut tape.w16), std::mem::take(&mut tape.x16), std::mem::take(&mut tape.dw));
        let f16 = self.f16.map(|s| T::c(s as f64));
        let (params, input) = match f16 {
            Some(_) => {
                assert!(
                    w16.len() == self.params.len() && x16.len() == input.len(),
                    "Mlp::backward: f16 arithmetic was turned on after the forward"
                );
                dw.clear();
                dw.resize(self.params.len(), T::zero());
                (&w16[..], &x16[..])
            }
            None => (&self.params[..], input),
        };
        let grads = if f16.is_some() { &mut dw[..] } else { &mut self.grads[..] };
        // dZ of the output layer.
        let last = &self.layers[nl - 1];
        match f16 {
            Some(s) => dz[..n * last.out].iter_mut().zip(d_output).for_each(|(z, &g)| *z = round_f16(g * s)),
            None => dz[..n * last.out].copy_from_slice(d_output),
        }
        mul_act_derivative(&mut dz[..n * last.out], &tape.acts[nl - 1], last.act, true);
        if f16.is_some() {
            round_all(&mut dz[..n * last.out], true);
        }
        for i in (0..nl).rev() {
            let l = self.layers[i].clone();
            let g = &dz[..n * l.out];
            let dzt = MatRef::row_major(g, n, l.out).t();
            // Column blocks of W: the input block [0, d_in) (layer 0 or a skip layer), the hidden block after it.
            let x_block = i == 0 || l.skip;
            let hw = if i == 0 {
                0
            } else {
                l.fan_in - if l.skip { d_in } else { 0 }
            };
            let hc0 = l.fan_in - hw;
            if i > 0 {
                let h = &tape.acts[i - 1];
                let dw = MatMut::new(&mut grads[l.w_off + hc0..], l.out, hw, l.fan_in, 1);
                matmul(dw, true, dzt, MatRef::row_major(h, n, hw), par);
            }
            if x_block {
                let dw = MatMut::new(&mut grads[l.w_off..], l.out, d_in, l.fan_in, 1);
                matmul(dw, true, dzt, MatRef::row_major(input, n, d_in), par);
                if let Some(d) = d_input.as_deref_mut() {
                    let wx = MatRef::new(&params[l.w_off..], l.out, cols, l.fan_in, 1);
                    matmul(
                        MatMut::new(d, n, cols, d_in, 1),
                        true,
                        MatRef::row_major(g, n, l.out),
                        wx,
                        par,
                    );
                }
            }
            if let Some(b) = l.b_off {
                add_col_sums(&mut grads[b..b + l.out], g, l.out, true);
            }
            if i > 0 {
                let wh = MatRef::new(&params[l.w_off + hc0..], l.out, hw, l.fan_in, 1);
                let dhs = &mut dh[..n * hw];
                matmul(
                    MatMut::row_major(dhs, n, hw),
                    false,
                    MatRef::row_major(g, n, l.out),
                    wh,
                    par,
                );
                if f16.is_some() {
                    round_all(dhs, true);
                }
                mul_act_derivative(dhs, &tape.acts[i - 1], self.layers[i - 1].act, true);
                if f16.is_some() {
                    round_all(dhs, true);
                }
                std::mem::swap(&mut dz, &mut dh);
            }
        }
        if let Some(s) = f16 {
            let inv = T::one() / s;
            self.grads.iter_mut().zip(&dw).for_each(|(g, &d)| *g += round_f16(d) * inv);
            if let Some(d) = d_input {
                d.chunks_exact_mut(d_in).for_each(|row| row[..cols].iter_mut().for_each(|v| *v = round_f16(*v) * inv));
            }
        }
        tape.dz = dz;
        tape.dh = dh;
        tape.w16 = w16;
        tape.x16 = x16;
        tape.dw = dw;
    }
}

#[cfg(test)]
mod tests;
