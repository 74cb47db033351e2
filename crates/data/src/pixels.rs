//! One view's RGBA pixels as a dataset holds them: 8 bits a channel where every value is
//! exactly `k/255` (photos read from 8-bit files, as they load), else 16 bits (16-bit photos,
//! and the values resampling, box averages and clipped float images make), as the GPU holds
//! them too (`nerf_gpu::sampling::PixelFormat`). A 4000-photo capture's 8-bit photos take a
//! quarter of the memory they would as `f32`.
//!
//! Reading a value back gives the `f32` it was made from exactly for 8-bit values (`k/255` and
//! `(257·k)/65535` round to the same `f32`), and within `1/131070` for the others.

/// A view's pixels, row-major RGBA (straight alpha), values in `[0, 1]`.
#[derive(Clone, Debug, PartialEq)]
pub enum Pixels {
    /// `value = byte / 255`.
    Rgba8(Vec<u8>),
    /// `value = word / 65535`.
    Rgba16(Vec<u16>),
}

impl Default for Pixels {
    fn default() -> Self {
        Pixels::Rgba8(Vec::new())
    }
}

/// The byte of an exact 8-bit value, `None` for any other value.
#[inline]
fn exact8(x: f32) -> Option<u8> {
    let q = (x.clamp(0.0, 1.0) * 255.0).round();
    (q / 255.0 == x).then_some(q as u8)
}

/// The nearest 16-bit value of `x` clipped to `[0, 1]` (NaN → 0).
#[inline]
fn q16(x: f32) -> u16 {
    (x.clamp(0.0, 1.0) * 65535.0).round() as u16
}

impl Pixels {
    /// The values `px` (4 per pixel), as 8 bits when each is exactly `k/255`, else as the nearest
    /// 16-bit values of the values clipped to `[0, 1]`.
    pub fn from_f32(px: &[f32]) -> Self {
        let bytes: Option<Vec<u8>> = px.iter().map(|&x| exact8(x)).collect();
        match bytes {
            Some(b) => Pixels::Rgba8(b),
            None => Pixels::Rgba16(px.iter().map(|&x| q16(x)).collect()),
        }
    }

    /// The number of values (4 per pixel; 0 for a view loaded without its pixels).
    pub fn len(&self) -> usize {
        match self {
            Pixels::Rgba8(v) => v.len(),
            Pixels::Rgba16(v) => v.len(),
        }
    }

    /// Whether there are no values (a dataset loaded with `cameras_only`).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes the values take.
    pub fn size_in_bytes(&self) -> usize {
        match self {
            Pixels::Rgba8(v) => v.len(),
            Pixels::Rgba16(v) => 2 * v.len(),
        }
    }

    /// Whether every value is an exact 8-bit one.
    pub fn is_rgba8(&self) -> bool {
        matches!(self, Pixels::Rgba8(_))
    }

    /// Value `i` (pixel `i / 4`, channel `i % 4`).
    #[inline]
    pub fn value(&self, i: usize) -> f32 {
        match self {
            Pixels::Rgba8(v) => v[i] as f32 / 255.0,
            Pixels::Rgba16(v) => v[i] as f32 / 65535.0,
        }
    }

    /// Pixel `p`'s RGBA.
    #[inline]
    pub fn rgba(&self, p: usize) -> [f32; 4] {
        std::array::from_fn(|c| self.value(4 * p + c))
    }

    /// Every value as `f32`.
    pub fn to_f32(&self) -> Vec<f32> {
        (0..self.len()).map(|i| self.value(i)).collect()
    }

    /// Each value as 16 bits (an 8-bit value `k` is `257·k`, the same value).
    pub fn to_u16(&self) -> Vec<u16> {
        match self {
            Pixels::Rgba8(v) => v.iter().map(|&b| 257 * b as u16).collect(),
            Pixels::Rgba16(v) => v.clone(),
        }
    }

    /// The pixels of a `w`-pixel-wide image moved to the top-left corner of a `cw × ch` canvas,
    /// row by row; the rest transparent black (0).
    pub fn widened(&self, w: usize, (cw, ch): (usize, usize)) -> Self {
        fn widen<T: Copy + Default>(src: &[T], w: usize, (cw, ch): (usize, usize)) -> Vec<T> {
            let mut out = vec![T::default(); 4 * cw * ch];
            for (row, r) in src.chunks_exact(4 * w).enumerate() {
                out[4 * row * cw..][..4 * w].copy_from_slice(r);
            }
            out
        }
        match self {
            Pixels::Rgba8(v) => Pixels::Rgba8(widen(v, w, (cw, ch))),
            Pixels::Rgba16(v) => Pixels::Rgba16(widen(v, w, (cw, ch))),
        }
    }
}

impl From<Vec<f32>> for Pixels {
    fn from(px: Vec<f32>) -> Self {
        Pixels::from_f32(&px)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 8-bit values are held as bytes and read back bit for bit; any other value makes the view
    /// 16-bit, read back within half a step; values past [0, 1] are clipped.
    #[test]
    fn values_are_kept_in_as_few_bits_as_hold_them() {
        let eight: Vec<f32> = (0..=255).map(|k| k as f32 / 255.0).collect();
        let p = Pixels::from_f32(&eight);
        assert!(p.is_rgba8() && p.size_in_bytes() == 256);
        assert_eq!(p.to_f32(), eight, "bit for bit");
        let sixteen = Pixels::Rgba16(p.to_u16());
        assert_eq!(sixteen.to_f32(), eight, "k/255 and 257k/65535 are the same f32");
        let mut other = eight.clone();
        other[7] = 0.123_456_7;
        other[8] = 1.5;
        other[9] = -0.25;
        let q = Pixels::from_f32(&other);
        assert!(!q.is_rgba8() && q.size_in_bytes() == 512);
        let back = q.to_f32();
        assert!((back[7] - 0.123_456_7).abs() <= 0.5 / 65535.0 + 1e-7);
        assert_eq!((back[8], back[9]), (1.0, 0.0), "clipped");
        assert!(back.iter().zip(&eight).enumerate().all(|(i, (a, b))| [7, 8, 9].contains(&i) || a == b));
        assert_eq!(q.rgba(2), [back[8], back[9], back[10], back[11]]);
        let w = Pixels::from_f32(&[0.2; 8]).widened(1, (3, 2));
        assert_eq!(w.len(), 24);
        assert_eq!(w.to_f32().iter().filter(|&&x| x != 0.0).count(), 8);
        assert_eq!(w.rgba(3), Pixels::from_f32(&[0.2; 4]).rgba(0), "row 1 starts at the canvas's stride");
    }
}
