//! Training masks: which pixels of each view training may draw (nerfstudio's per-frame
//! `mask_path`, or instant-ngp's `dynamic_mask_<name>.png` beside a photo, whose non-zero
//! pixels are the dropped ones; see docs/formats.md). A masked-out pixel (a passer-by, the
//! photographer's shadow, a car that moved between photos) is never drawn as a training ray;
//! the others are drawn uniformly, as nerfstudio's pixel sampler does. Evaluation scores whole
//! images.
//!
//! [`PixelMasks`] keeps, per view, the sorted indices (`row·W + col`) of its kept pixels, and
//! the running count across views, so that the `k`-th kept pixel of the whole dataset
//! ([`PixelMasks::pick`]) is found by a binary search over views: 4 bytes per kept pixel.

/// The kept pixels of every view of a dataset ([`crate::Dataset::masks`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PixelMasks {
    /// Per view: indices `row·W + col` of its kept pixels, ascending.
    kept: Vec<Vec<u32>>,
    /// `starts[v]` = kept pixels of views `0..v`; `starts[n_views]` = all of them.
    starts: Vec<u64>,
}

impl PixelMasks {
    /// Masks from each view's kept pixel indices (`row·W + col`); each list is sorted and
    /// deduplicated here.
    pub fn new(mut kept: Vec<Vec<u32>>) -> Self {
        for k in &mut kept {
            k.sort_unstable();
            k.dedup();
        }
        let mut starts = Vec::with_capacity(kept.len() + 1);
        let mut total = 0u64;
        starts.push(0);
        for k in &kept {
            total += k.len() as u64;
            starts.push(total);
        }
        Self { kept, starts }
    }

    /// Masks from one keep/drop flag per pixel per view (`row·W + col` order).
    pub fn from_flags<'a>(views: impl IntoIterator<Item = &'a [bool]>) -> Self {
        Self::new(
            views
                .into_iter()
                .map(|flags| flags.iter().enumerate().filter(|(_, &k)| k).map(|(i, _)| i as u32).collect())
                .collect(),
        )
    }

    /// Number of views.
    pub fn n_views(&self) -> usize {
        self.kept.len()
    }

    /// The kept pixels of view `v`, ascending.
    pub fn view(&self, v: usize) -> &[u32] {
        &self.kept[v]
    }

    /// Kept pixels of all views.
    pub fn total(&self) -> u64 {
        self.starts[self.kept.len()]
    }

    /// Whether pixel `pix` (`row·W + col`) of view `v` is kept.
    pub fn is_kept(&self, v: usize, pix: u32) -> bool {
        self.kept[v].binary_search(&pix).is_ok()
    }

    /// The `k`-th kept pixel of the dataset, views in order (`k < total()`): `(view, pixel)`.
    ///
    /// # Panics
    /// If `k >= total()`.
    pub fn pick(&self, k: u64) -> (u32, u32) {
        assert!(k < self.total(), "kept pixel {k} of {}", self.total());
        // The last view whose start is ≤ k (views without kept pixels share their start with the next).
        let v = self.starts.partition_point(|&s| s <= k) - 1;
        (v as u32, self.kept[v][(k - self.starts[v]) as usize])
    }

    /// The masks of the views `views` (in that order), e.g. a selection of a dataset's views.
    pub fn select(&self, views: &[usize]) -> Self {
        Self::new(views.iter().map(|&v| self.kept[v].clone()).collect())
    }

    /// View `v`'s mask as one byte per pixel (255 kept, 0 masked out), for `n_pixels` pixels.
    pub fn view_bytes(&self, v: usize, n_pixels: usize) -> Vec<u8> {
        let mut out = vec![0u8; n_pixels];
        for &p in &self.kept[v] {
            out[p as usize] = 255;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pick_walks_the_kept_pixels_in_order_across_views_with_none_kept() {
        let m = PixelMasks::new(vec![vec![5, 1], vec![], vec![3, 3, 0], vec![7]]);
        assert_eq!(m.total(), 5);
        let all: Vec<(u32, u32)> = (0..m.total()).map(|k| m.pick(k)).collect();
        assert_eq!(all, [(0, 1), (0, 5), (2, 0), (2, 3), (3, 7)]);
        assert!(m.is_kept(2, 3) && !m.is_kept(2, 1) && !m.is_kept(1, 0));
        assert_eq!(m.select(&[3, 0]).view(1), &[1, 5]);
        assert_eq!(m.view_bytes(0, 6), [0, 255, 0, 0, 0, 255]);
        let f = PixelMasks::from_flags([&[false, true, true][..], &[true, false, false][..]]);
        assert_eq!((f.view(0), f.view(1)), (&[1u32, 2][..], &[0u32][..]));
    }

    #[test]
    #[should_panic(expected = "kept pixel 2 of 2")]
    fn pick_past_the_end_panics() {
        PixelMasks::new(vec![vec![0], vec![1]]).pick(2);
    }
}
