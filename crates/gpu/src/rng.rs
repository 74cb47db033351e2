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
        assert_ne!(super::rand_u32(1, 0, 5), super::rand_u32(2, 0, 5));
        assert_ne!(super::rand_u32(1, 0, 5), super::rand_u32(1, 1, 5));
    }
}
