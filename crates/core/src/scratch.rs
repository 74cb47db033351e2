//! Reusable scratch buffers for the hot paths: [`grown`] sizes a buffer without zeroing what a
//! later, larger call would overwrite anyway, and [`ScratchPool`] hands buffers to queries that
//! take `&self` and run on several threads at once (a field's inference while rendering).

use std::sync::Mutex;

/// The first `len` elements of `v`, which grows (zero-filled) when shorter and otherwise keeps
/// its length: for buffers reused across calls of varying size, always sliced to the size in
/// use and written before they are read, so they are zeroed once instead of on every call that
/// follows a smaller one.
pub fn grown<T: Copy + Default>(v: &mut Vec<T>, len: usize) -> &mut [T] {
    if v.len() < len {
        v.resize(len, T::default());
    }
    &mut v[..len]
}

/// A pool of scratch values (`S`, e.g. a struct of `Vec`s) for work that takes `&self` and may run
/// on several threads at once: [`ScratchPool::with`] takes one (or makes one with `S::default()`)
/// and puts it back after, so once every thread has had one nothing is allocated. The pool holds
/// at most as many values as calls ever ran at once.
#[derive(Debug, Default)]
pub struct ScratchPool<S>(Mutex<Vec<S>>);

impl<S: Default> ScratchPool<S> {
    /// An empty pool.
    pub fn new() -> Self {
        Self(Mutex::new(Vec::new()))
    }

    /// Runs `f` with a value from the pool and returns it to the pool afterwards. A panic in `f`
    /// drops the value; a poisoned pool only costs the reuse.
    pub fn with<R>(&self, f: impl FnOnce(&mut S) -> R) -> R {
        let mut s = self.0.lock().ok().and_then(|mut p| p.pop()).unwrap_or_default();
        let r = f(&mut s);
        if let Ok(mut p) = self.0.lock() {
            p.push(s);
        }
        r
    }

    /// Values in the pool now (not lent out).
    pub fn len(&self) -> usize {
        self.0.lock().map_or(0, |p| p.len())
    }

    /// Whether the pool holds no value now.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grown_grows_zero_filled_and_never_shrinks() {
        let mut v = vec![7.0f32; 3];
        assert_eq!(grown(&mut v, 5), &[7.0, 7.0, 7.0, 0.0, 0.0]);
        grown(&mut v, 5).fill(1.0);
        assert_eq!(grown(&mut v, 2), &[1.0, 1.0]);
        assert_eq!(v.len(), 5, "a smaller call keeps the buffer's length");
        assert_eq!(grown(&mut v, 5), &[1.0; 5], "and a larger one after it zeroes nothing");
    }

    #[test]
    fn the_pool_reuses_values_and_holds_one_per_concurrent_call() {
        let pool = ScratchPool::<Vec<u8>>::new();
        pool.with(|s| s.extend([1, 2, 3]));
        assert_eq!(pool.len(), 1);
        pool.with(|s| assert_eq!(s, &[1, 2, 3], "the value comes back"));
        pool.with(|a| {
            pool.with(|b| {
                assert!(b.is_empty(), "a nested call gets a value of its own");
                b.push(9);
            });
            assert_eq!(a, &[1, 2, 3]);
        });
        assert_eq!(pool.len(), 2);
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| pool.with(|_| panic!("in f"))));
        assert!(caught.is_err());
        assert_eq!(pool.len(), 1, "the value lent to a panicking call is dropped");
        pool.with(|s| s.clear());
    }
}
