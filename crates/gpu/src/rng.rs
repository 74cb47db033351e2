//! Host twin of the counter-based random numbers in `shaders/common.wgsl` (PCG hash). Kernels
//! draw `rand_f32(seed, stream, index)` without state; tests reproduce the same numbers here.

/// PCG-RXS-M-XS 32-bit hash (as `pcg_hash` in WGSL).
#[inline]
pub fn pcg_hash(x: u32) -> u32 {
    let state = x.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
    let word = ((state >> ((state >> 28) + 4)) ^ state).wrapping_mul(277_803_737);
    (word >> 22) ^ word
}

/// A random `u32` for `(seed, stream, i)`.
#[inline]
pub fn rand_u32(seed: u32, stream: u32, i: u32) -> u32 {
    pcg_hash(seed ^ pcg_hash(stream ^ pcg_hash(i)))
}

/// Uniform in `[0, 1)` with 24 bits, bit-identical to WGSL's `rand_f32`.
#[inline]
pub fn rand_f32(seed: u32, stream: u32, i: u32) -> f32 {
    (rand_u32(seed, stream, i) >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// A random index below `n` for `(seed, stream, i)`: `⌊rand_u32 · n / 2³²⌋` (Lemire's
/// multiply-high; WGSL's `rand_below`, which builds the 64-bit product from 16-bit halves).
#[inline]
pub fn rand_below(seed: u32, stream: u32, i: u32, n: u32) -> u32 {
    ((rand_u32(seed, stream, i) as u64 * n as u64) >> 32) as u32
}

#[cfg(test)]
mod tests {
    #[test]
    fn uniform_numbers_cover_the_unit_interval_evenly() {
        let n = 100_000u32;
        let mut bins = [0usize; 10];
        for i in 0..n {
            let u = super::rand_f32(7, 3, i);
            assert!((0.0..1.0).contains(&u));
            bins[(u * 10.0) as usize] += 1;
        }
        for b in bins {
            assert!((b as f64 - 10_000.0).abs() < 500.0, "{bins:?}");
        }
        // Indices below n, as even at the top of the range as at the bottom (modulo is not:
        // n = 3·2³⁰ gives indices below 2³⁰ twice the draws of the others).
        let n3 = 3u32 << 30;
        let (mut low, mut high) = (0, 0);
        for i in 0..n {
            let k = super::rand_below(7, 4, i, n3);
            assert!(k < n3);
            low += (k < 1 << 30) as u32;
            high += (k >= 2 << 30) as u32;
        }
        assert!((low as f64 - high as f64).abs() < 1500.0, "{low} draws in the first third, {high} in the last");
        assert_eq!(super::rand_below(7, 4, 9, 1), 0);
        assert_ne!(super::rand_u32(1, 0, 5), super::rand_u32(2, 0, 5));
        assert_ne!(super::rand_u32(1, 0, 5), super::rand_u32(1, 1, 5));
    }
}
