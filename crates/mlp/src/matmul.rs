//! A safe, dimension-checked wrapper around the `gemm` crate's strided matrix product.
//!
//! Matrices are described by strided views ([`MatRef`], [`MatMut`]): element `(i, j)` of a view lives at
//! `data[i·row_stride + j·col_stride]`. A transpose is a view with the strides swapped ([`MatRef::t`]),
//! so `Xᵀ·Y` and `X·Wᵀ` need no copies.

use nerf_core::Real;

pub use gemm::Parallelism;

/// Largest offset `(rows−1)·rs + (cols−1)·cs` a view touches, panicking on overflow; `None` for an empty view.
fn max_offset(rows: usize, cols: usize, rs: usize, cs: usize) -> Option<usize> {
    if rows == 0 || cols == 0 {
        return None;
    }
    let r = (rows - 1)
        .checked_mul(rs)
        .expect("matrix view: offset overflow");
    let c = (cols - 1)
        .checked_mul(cs)
        .expect("matrix view: offset overflow");
    Some(r.checked_add(c).expect("matrix view: offset overflow"))
}

/// A read-only strided view of a `rows × cols` matrix.
#[derive(Clone, Copy, Debug)]
pub struct MatRef<'a, T> {
    data: &'a [T],
    rows: usize,
    cols: usize,
    rs: usize,
    cs: usize,
}

impl<'a, T> MatRef<'a, T> {
    /// A view with explicit strides. Panics if an element would lie outside `data`.
    pub fn new(
        data: &'a [T],
        rows: usize,
        cols: usize,
        row_stride: usize,
        col_stride: usize,
    ) -> Self {
        if let Some(m) = max_offset(rows, cols, row_stride, col_stride) {
            assert!(
                m < data.len(),
                "MatRef {rows}×{cols} (strides {row_stride}, {col_stride}) exceeds slice of {}",
                data.len()
            );
        }
        Self {
            data,
            rows,
            cols,
            rs: row_stride,
            cs: col_stride,
        }
    }
    /// A dense row-major view (`row_stride = cols`, `col_stride = 1`).
    pub fn row_major(data: &'a [T], rows: usize, cols: usize) -> Self {
        Self::new(data, rows, cols, cols, 1)
    }
    /// The transpose (a `cols × rows` view of the same data).
    pub fn t(self) -> Self {
        Self {
            data: self.data,
            rows: self.cols,
            cols: self.rows,
            rs: self.cs,
            cs: self.rs,
        }
    }
    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.rows
    }
    /// Number of columns.
    pub fn cols(&self) -> usize {
        self.cols
    }
}

/// A mutable strided view of a `rows × cols` matrix whose elements are distinct memory locations.
#[derive(Debug)]
pub struct MatMut<'a, T> {
    data: &'a mut [T],
    rows: usize,
    cols: usize,
    rs: usize,
    cs: usize,
}

impl<'a, T> MatMut<'a, T> {
    /// A view with explicit strides. Panics if an element would lie outside `data` or if two elements
    /// would share a location (the strides must describe a row-major or column-major layout with padding).
    pub fn new(
        data: &'a mut [T],
        rows: usize,
        cols: usize,
        row_stride: usize,
        col_stride: usize,
    ) -> Self {
        if let Some(m) = max_offset(rows, cols, row_stride, col_stride) {
            assert!(
                m < data.len(),
                "MatMut {rows}×{cols} (strides {row_stride}, {col_stride}) exceeds slice of {}",
                data.len()
            );
            let distinct = match (rows > 1, cols > 1) {
                (false, false) => true,
                (true, false) => row_stride >= 1,
                (false, true) => col_stride >= 1,
                (true, true) => {
                    (col_stride >= 1 && row_stride >= cols * col_stride)
                        || (row_stride >= 1 && col_stride >= rows * row_stride)
                }
            };
            assert!(
                distinct,
                "MatMut {rows}×{cols}: strides ({row_stride}, {col_stride}) alias elements"
            );
        }
        Self {
            data,
            rows,
            cols,
            rs: row_stride,
            cs: col_stride,
        }
    }
    /// A dense row-major view (`row_stride = cols`, `col_stride = 1`).
    pub fn row_major(data: &'a mut [T], rows: usize, cols: usize) -> Self {
        Self::new(data, rows, cols, cols, 1)
    }
    /// The transpose (a `cols × rows` view of the same data).
    pub fn t(self) -> Self {
        Self {
            data: self.data,
            rows: self.cols,
            cols: self.rows,
            rs: self.cs,
            cs: self.rs,
        }
    }
}

/// `dst = a·b` (or `dst += a·b` when `accumulate`), with `a: m×k`, `b: k×n`, `dst: m×n`, computed by
/// `gemm` (AVX-512/AVX2/NEON micro-kernels, multithreaded with `Parallelism::Rayon(0)` above gemm's own
/// size threshold). Panics on mismatched dimensions. When `accumulate` is false the old contents of `dst`
/// are ignored (NaNs included).
pub fn matmul<T: Real>(
    dst: MatMut<'_, T>,
    accumulate: bool,
    a: MatRef<'_, T>,
    b: MatRef<'_, T>,
    par: Parallelism,
) {
    let (m, n, k) = (dst.rows, dst.cols, a.cols);
    assert_eq!(a.rows, m, "matmul: a has {} rows, dst has {m}", a.rows);
    assert_eq!(b.rows, k, "matmul: a is {m}×{k} but b has {} rows", b.rows);
    assert_eq!(b.cols, n, "matmul: b has {} cols, dst has {n}", b.cols);
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            for i in 0..m {
                for j in 0..n {
                    dst.data[i * dst.rs + j * dst.cs] = T::zero();
                }
            }
        }
        return;
    }
    // SAFETY: the views were bounds-checked at construction (every element index used by gemm,
    // i·rs + j·cs with i < rows, j < cols, is inside its slice); `dst` is a unique borrow whose elements
    // are pairwise distinct, so gemm's parallel writes do not race, and it cannot alias `a` or `b`
    // (shared borrows). gemm supports f32 and f64, the only `Real` types.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.data.as_mut_ptr(),
            dst.cs as isize,
            dst.rs as isize,
            accumulate,
            a.data.as_ptr(),
            a.cs as isize,
            a.rs as isize,
            b.data.as_ptr(),
            b.cs as isize,
            b.rs as isize,
            T::one(),
            T::one(),
            false,
            false,
            false,
            par,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;

    fn naive<T: Real>(
        m: usize,
        n: usize,
        k: usize,
        a: impl Fn(usize, usize) -> T,
        b: impl Fn(usize, usize) -> T,
    ) -> Vec<f64> {
        let mut out = vec![0.0; m * n];
        for i in 0..m {
            for j in 0..n {
                out[i * n + j] = (0..k).map(|p| a(i, p).f64() * b(p, j).f64()).sum();
            }
        }
        out
    }

    fn check<T: Real>(tol: f64) {
        let mut r = nerf_core::rng(3, 0);
        for &(m, n, k) in &[
            (1, 1, 1),
            (5, 7, 3),
            (33, 17, 65),
            (300, 256, 63),
            (257, 130, 319),
        ] {
            for par in [Parallelism::None, Parallelism::Rayon(0)] {
                for (ta, tb) in [(false, false), (true, false), (false, true), (true, true)] {
                    // a stored as (m×k) or as its transpose (k×m); likewise b.
                    let av: Vec<T> = (0..m * k).map(|_| T::c(r.gen::<f64>() - 0.5)).collect();
                    let bv: Vec<T> = (0..k * n).map(|_| T::c(r.gen::<f64>() - 0.5)).collect();
                    let a = if ta {
                        MatRef::row_major(&av, k, m).t()
                    } else {
                        MatRef::row_major(&av, m, k)
                    };
                    let b = if tb {
                        MatRef::row_major(&bv, n, k).t()
                    } else {
                        MatRef::row_major(&bv, k, n)
                    };
                    let aval = |i: usize, p: usize| if ta { av[p * m + i] } else { av[i * k + p] };
                    let bval = |p: usize, j: usize| if tb { bv[j * k + p] } else { bv[p * n + j] };
                    let expect = naive(m, n, k, aval, bval);
                    // Overwrite a NaN-filled destination, then accumulate a second product on top.
                    let mut d = vec![T::nan(); m * n];
                    matmul(MatMut::row_major(&mut d, m, n), false, a, b, par);
                    let err = d
                        .iter()
                        .zip(&expect)
                        .map(|(x, y)| (x.f64() - y).abs())
                        .fold(0.0, f64::max);
                    assert!(
                        err < tol * (k as f64).sqrt(),
                        "{m}×{n}×{k} ta={ta} tb={tb}: err {err}"
                    );
                    matmul(MatMut::row_major(&mut d, m, n), true, a, b, par);
                    let err = d
                        .iter()
                        .zip(&expect)
                        .map(|(x, y)| (x.f64() - 2.0 * y).abs())
                        .fold(0.0, f64::max);
                    assert!(
                        err < 2.0 * tol * (k as f64).sqrt(),
                        "accumulate {m}×{n}×{k}: err {err}"
                    );
                }
            }
        }
    }

    #[test]
    fn matches_naive_f32() {
        check::<f32>(1e-6);
    }

    #[test]
    fn matches_naive_f64() {
        check::<f64>(1e-14);
    }

    #[test]
    fn strided_sub_blocks_and_column_major_destination() {
        // dst is the column block [2, 2+n) of a wider row-major matrix; a is a column block too;
        // then the same product into a column-major destination.
        let (m, n, k, w) = (9, 4, 5, 11);
        let big: Vec<f64> = (0..m * w).map(|i| (i as f64 * 0.37).sin()).collect();
        let bv: Vec<f64> = (0..k * n).map(|i| (i as f64 * 0.91).cos()).collect();
        let a = MatRef::new(&big[3..], m, k, w, 1);
        let b = MatRef::row_major(&bv, k, n);
        let expect = naive(m, n, k, |i, p| big[3 + i * w + p], |p, j| bv[p * n + j]);
        let mut d = vec![-7.0f64; m * w];
        matmul(
            MatMut::new(&mut d[2..], m, n, w, 1),
            false,
            a,
            b,
            Parallelism::None,
        );
        for i in 0..m {
            for j in 0..w {
                let v = d[i * w + j];
                if (2..2 + n).contains(&j) {
                    assert!((v - expect[i * n + j - 2]).abs() < 1e-14);
                } else {
                    assert_eq!(v, -7.0, "element outside the block was written");
                }
            }
        }
        let mut c = vec![0.0f64; m * n];
        matmul(
            MatMut::row_major(&mut c, n, m).t(),
            false,
            a,
            b,
            Parallelism::None,
        );
        for i in 0..m {
            for j in 0..n {
                assert!((c[j * m + i] - expect[i * n + j]).abs() < 1e-14);
            }
        }
    }

    #[test]
    fn empty_inner_dimension_zeroes_or_keeps() {
        let a: [f32; 0] = [];
        let mut d = [5.0f32; 6];
        matmul(
            MatMut::row_major(&mut d, 2, 3),
            true,
            MatRef::row_major(&a, 2, 0),
            MatRef::row_major(&a, 0, 3),
            Parallelism::None,
        );
        assert_eq!(d, [5.0; 6]);
        matmul(
            MatMut::row_major(&mut d, 2, 3),
            false,
            MatRef::row_major(&a, 2, 0),
            MatRef::row_major(&a, 0, 3),
            Parallelism::None,
        );
        assert_eq!(d, [0.0; 6]);
    }

    #[test]
    #[should_panic(expected = "exceeds slice")]
    fn out_of_bounds_view_panics() {
        let v = [0.0f32; 5];
        let _ = MatRef::row_major(&v, 2, 3);
    }

    #[test]
    #[should_panic(expected = "alias")]
    fn aliasing_destination_panics() {
        let mut v = [0.0f32; 8];
        let _ = MatMut::new(&mut v, 2, 3, 1, 1);
    }

    #[test]
    #[should_panic(expected = "rows")]
    fn mismatched_dimensions_panic() {
        let v = [0.0f32; 12];
        let mut d = [0.0f32; 4];
        matmul(
            MatMut::row_major(&mut d, 2, 2),
            false,
            MatRef::row_major(&v, 2, 3),
            MatRef::row_major(&v, 4, 2),
            Parallelism::None,
        );
    }
}
