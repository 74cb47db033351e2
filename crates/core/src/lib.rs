//! Shared numeric foundations of nerf-rs.
//!
//! Every numeric kernel that has a backward pass (compositing, encodings, MLP layers) is written
//! once, generic over [`Real`], so that training runs in `f32` while finite-difference gradient
//! checks run the *same code* in `f64`. [`rng`] gives the one seeded generator used everywhere so
//! that runs are reproducible from a `u64` seed. [`par`] splits packed (CSR) ray batches across
//! rayon threads, shared by the samplers and the compositor. [`scratch`] keeps the hot paths'
//! buffers allocated once: [`grown`] and the [`ScratchPool`] of `&self` queries.

use num_traits::{Float, FromPrimitive, NumAssign, ToPrimitive};

pub mod par;
pub mod scratch;
pub use scratch::{grown, ScratchPool};

/// The scalar type of the numeric kernels: `f32` (training, rendering) or `f64` (gradient checks).
pub trait Real:
    Float
    + FromPrimitive
    + ToPrimitive
    + NumAssign
    + Default
    + Copy
    + Send
    + Sync
    + std::fmt::Debug
    + std::fmt::Display
    + std::iter::Sum
    + bytemuck::Pod
    + 'static
{
    /// Converts an `f64` constant (exact for `f64`, rounded for `f32`).
    #[inline(always)]
    fn c(x: f64) -> Self {
        <Self as FromPrimitive>::from_f64(x).unwrap()
    }
    /// Converts to `f64` (for metrics, logging).
    #[inline(always)]
    fn f64(self) -> f64 {
        <Self as ToPrimitive>::to_f64(&self).unwrap()
    }
    /// Converts to `f32`.
    #[inline(always)]
    fn f32(self) -> f32 {
        <Self as ToPrimitive>::to_f32(&self).unwrap()
    }
}

impl Real for f32 {}
impl Real for f64 {}

/// `x` rounded to the nearest f16 (ties to even; overflow to ±∞, as a cast to `__half` does):
/// what tiny-cuda-nn's half-precision arithmetic keeps, for the CPU's emulations of it.
#[inline(always)]
pub fn round_f16<T: Real>(x: T) -> T {
    if std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>() {
        // f32 → f16 in one rounding (the F16C instruction where the CPU has it; f64's goes
        // through software).
        bytemuck::cast(half::f16::from_f32(bytemuck::cast::<T, f32>(x)).to_f32())
    } else {
        T::c(half::f16::from_f64(x.f64()).to_f64())
    }
}

/// The project's seeded random generator (PCG-64, stable across platforms and releases).
pub type Rng = rand_pcg::Pcg64Mcg;

/// A generator for `seed`, decorrelated for each `stream` (e.g. one stream per network, per worker
/// or per training step) so that adding a consumer does not shift the numbers every other one sees.
pub fn rng(seed: u64, stream: u64) -> Rng {
    use rand::SeedableRng;
    // SplitMix64 finaliser mixes seed and stream into well-spread 128-bit state.
    let mix = |mut z: u64| {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let a = mix(seed ^ mix(stream));
    let b = mix(a ^ 0xD1B5_4A32_D192_ED03);
    Rng::from_seed(((a as u128) << 64 | b as u128).to_le_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;

    #[test]
    fn rng_is_reproducible_and_streams_differ() {
        let a: Vec<u32> = (0..8).map(|_| 0).scan(rng(7, 0), |r, _: i32| Some(r.gen())).collect();
        let b: Vec<u32> = (0..8).map(|_| 0).scan(rng(7, 0), |r, _: i32| Some(r.gen())).collect();
        let c: Vec<u32> = (0..8).map(|_| 0).scan(rng(7, 1), |r, _: i32| Some(r.gen())).collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn real_constants_round_trip() {
        assert_eq!(f32::c(0.5), 0.5f32);
        assert_eq!(1.25f64.f32(), 1.25f32);
        assert_eq!(<f64 as Real>::c(1e-300), 1e-300);
    }
}

/// Locating the shared data and reference vectors (`../shared` beside the repository).
pub mod shared {
    use std::path::{Path, PathBuf};

    /// The `shared/` folder beside the repository, if present: `$NERF_SHARED_DIR` when set,
    /// otherwise the first ancestor of `start` (pass `env!("CARGO_MANIFEST_DIR")`) that has a
    /// `shared/reference` or `shared/data` sub-folder.
    pub fn dir(start: &str) -> Option<PathBuf> {
        if let Some(p) = std::env::var_os("NERF_SHARED_DIR") {
            let p = PathBuf::from(p);
            return p.is_dir().then_some(p);
        }
        Path::new(start).ancestors().find_map(|a| {
            let s = a.join("shared");
            (s.join("reference").is_dir() || s.join("data").is_dir()).then_some(s)
        })
    }

    /// `shared/reference/<name>` if it exists; otherwise prints a notice (so a skipped check is
    /// visible in the test log) and returns `None`.
    pub fn reference(start: &str, name: &str) -> Option<PathBuf> {
        let p = dir(start).map(|d| d.join("reference").join(name)).filter(|p| p.is_file());
        if p.is_none() {
            eprintln!("NOTICE: shared/reference/{name} not found beside the repository; skipping this reference check");
        }
        p
    }

    /// `shared/data/<rel>` if it exists; otherwise prints a notice and returns `None`.
    pub fn data(start: &str, rel: &str) -> Option<PathBuf> {
        let p = dir(start).map(|d| d.join("data").join(rel)).filter(|p| p.exists());
        if p.is_none() {
            eprintln!("NOTICE: shared/data/{rel} not found beside the repository; skipping");
        }
        p
    }
}
