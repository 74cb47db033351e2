//! Training masks: which pixels of each view training may draw (nerfstudio's per-frame
//! `mask_path`, or instant-ngp's `dynamic_mask_<name>.png` beside a photo, whose non-zero
//! pixels are the dropped ones; and the pixels of a resampled photo that its lens did not see,
//! [`crate::ngp::pixels_seen`]; see docs/formats.md). A masked-out pixel (a passer-by, the
//! photographer's shadow, a car that moved between photos) is never drawn as a training ray;
//! the others are drawn uniformly, as nerfstudio's pixel sampler does. Evaluation scores whole
//! images, and test views with masks also over the pixels they keep (`nerf_train::MaskedMetrics`).
//!
//! [`PixelMasks`] keeps, per view, the sorted indices (`row·W + col`) of its kept pixels — or
//! nothing for a view that keeps every pixel (a photo without a dynamic mask) — and the running
//! count across views, so that the `k`-th kept pixel of the whole dataset ([`PixelMasks::pick`])
//! is found by a binary search over views: 4 bytes per kept pixel of a masked view. Views may
//! share one list ([`PixelMasks::with_shared_views`]: the views of one lens whose only mask is
//! the lens's), and then it is held once, on the CPU and on the GPU.

use std::sync::Arc;

/// The kept pixels of every view of a dataset ([`crate::Dataset::masks`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PixelMasks {
    /// Pixels per view (`W·H`).
    n_pixels: u32,
    /// Per view: indices `row·W + col` of its kept pixels, ascending; `None`: every pixel.
    kept: Vec<Option<Arc<[u32]>>>,
    /// `starts[v]` = kept pixels of views `0..v`; `starts[n_views]` = all of them.
    starts: Vec<u64>,
}

impl PixelMasks {
    /// Masks of views of `n_pixels` pixels from each view's kept pixel indices (`row·W + col`);
    /// each list is sorted and deduplicated here, and one that holds every pixel is stored as
    /// "every pixel".
    ///
    /// # Panics
    /// If an index is not below `n_pixels`.
    pub fn new(n_pixels: u32, kept: Vec<Vec<u32>>) -> Self {
        Self::with_full_views(n_pixels, kept.into_iter().map(Some).collect())
    }

    /// As [`PixelMasks::new`], `None` standing for a view that keeps every pixel.
    ///
    /// # Panics
    /// If an index is not below `n_pixels`.
    pub fn with_full_views(n_pixels: u32, kept: Vec<Option<Vec<u32>>>) -> Self {
        let kept = kept
            .into_iter()
            .map(|k| {
                let mut k = k?;
                k.sort_unstable();
                k.dedup();
                assert!(k.last().is_none_or(|&p| p < n_pixels), "kept pixel {:?} of a view of {n_pixels}", k.last());
                (k.len() < n_pixels as usize).then(|| Arc::from(k))
            })
            .collect();
        Self::from_views(n_pixels, kept)
    }

    /// Masks of views that may share their lists (one `Arc` for several views, held once):
    /// each list strictly ascending and below `n_pixels`; `None` (or a list of every pixel) for
    /// a view that keeps every pixel.
    ///
    /// # Panics
    /// If a list is not strictly ascending or holds an index not below `n_pixels`.
    pub fn with_shared_views(n_pixels: u32, kept: Vec<Option<Arc<[u32]>>>) -> Self {
        let kept = kept
            .into_iter()
            .map(|k| {
                let k = k?;
                assert!(k.windows(2).all(|w| w[0] < w[1]), "a shared list of kept pixels is not strictly ascending");
                assert!(k.last().is_none_or(|&p| p < n_pixels), "kept pixel {:?} of a view of {n_pixels}", k.last());
                (k.len() < n_pixels as usize).then_some(k)
            })
            .collect();
        Self::from_views(n_pixels, kept)
    }

    /// Masks from one keep/drop flag per pixel per view (`row·W + col` order, `n_pixels` each).
    ///
    /// # Panics
    /// If a view's flags are not `n_pixels` long.
    pub fn from_flags<'a>(n_pixels: u32, views: impl IntoIterator<Item = &'a [bool]>) -> Self {
        let kept = views
            .into_iter()
            .map(|flags| {
                assert_eq!(flags.len(), n_pixels as usize, "a view's flags");
                flags.iter().enumerate().filter(|(_, &k)| k).map(|(i, _)| i as u32).collect()
            })
            .collect();
        Self::new(n_pixels, kept)
    }

    /// Per view: `None` (every pixel kept) or its sorted, distinct kept pixels.
    fn from_views(n_pixels: u32, kept: Vec<Option<Arc<[u32]>>>) -> Self {
        let mut starts = Vec::with_capacity(kept.len() + 1);
        let mut total = 0u64;
        starts.push(0);
        for k in &kept {
            total += k.as_ref().map_or(n_pixels as u64, |k| k.len() as u64);
            starts.push(total);
        }
        Self { n_pixels, kept, starts }
    }

    /// Number of views.
    pub fn n_views(&self) -> usize {
        self.kept.len()
    }

    /// Pixels per view (`W·H`).
    pub fn n_pixels(&self) -> u32 {
        self.n_pixels
    }

    /// View `v`'s kept pixels, ascending; `None` when it keeps every pixel. Views that share a
    /// list ([`PixelMasks::with_shared_views`]) give the same slice (`std::ptr::eq`).
    pub fn view(&self, v: usize) -> Option<&[u32]> {
        self.kept[v].as_deref()
    }

    /// View `v`'s kept pixels, ascending (every pixel for a view without a mask).
    pub fn kept(&self, v: usize) -> impl Iterator<Item = u32> + '_ {
        let all = self.kept[v].is_none().then_some(0..self.n_pixels);
        self.kept[v].iter().flat_map(|k| k.iter()).copied().chain(all.into_iter().flatten())
    }

    /// Kept pixels of view `v`.
    pub fn kept_in(&self, v: usize) -> u64 {
        self.starts[v + 1] - self.starts[v]
    }

    /// Kept pixels of all views.
    pub fn total(&self) -> u64 {
        self.starts[self.kept.len()]
    }

    /// Whether pixel `pix` (`row·W + col`) of view `v` is kept.
    pub fn is_kept(&self, v: usize, pix: u32) -> bool {
        match &self.kept[v] {
            None => pix < self.n_pixels,
            Some(k) => k.binary_search(&pix).is_ok(),
        }
    }

    /// The `k`-th kept pixel of the dataset, views in order (`k < total()`): `(view, pixel)`.
    ///
    /// # Panics
    /// If `k >= total()`.
    pub fn pick(&self, k: u64) -> (u32, u32) {
        assert!(k < self.total(), "kept pixel {k} of {}", self.total());
        // The last view whose start is ≤ k (views without kept pixels share their start with the next).
        let v = self.starts.partition_point(|&s| s <= k) - 1;
        let local = k - self.starts[v];
        (v as u32, self.kept[v].as_ref().map_or(local as u32, |kept| kept[local as usize]))
    }

    /// The masks of the views `views` (in that order), e.g. a selection of a dataset's views.
    pub fn select(&self, views: &[usize]) -> Self {
        Self::from_views(self.n_pixels, views.iter().map(|&v| self.kept[v].clone()).collect())
    }

    /// View `v`'s mask as one byte per pixel (255 kept, 0 masked out).
    pub fn view_bytes(&self, v: usize) -> Vec<u8> {
        let mut out = vec![0u8; self.n_pixels as usize];
        for p in self.kept(v) {
            out[p as usize] = 255;
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pick_walks_the_kept_pixels_in_order_across_views_with_none_or_all_kept() {
        let m = PixelMasks::new(8, vec![vec![5, 1], vec![], vec![3, 3, 0], vec![7], (0..8).rev().collect()]);
        assert_eq!(m.total(), 13);
        assert_eq!((m.view(4), m.kept_in(4), m.kept_in(1)), (None, 8, 0), "a full list is stored as every pixel");
        let all: Vec<(u32, u32)> = (0..m.total()).map(|k| m.pick(k)).collect();
        let want: Vec<(u32, u32)> = [(0, 1), (0, 5), (2, 0), (2, 3), (3, 7)].into_iter().chain((0..8).map(|p| (4, p))).collect();
        assert_eq!(all, want);
        assert!(m.is_kept(2, 3) && !m.is_kept(2, 1) && !m.is_kept(1, 0) && m.is_kept(4, 6) && !m.is_kept(4, 8));
        assert_eq!(m.select(&[3, 0]).view(1), Some(&[1, 5][..]));
        assert_eq!(m.view_bytes(0), [0, 255, 0, 0, 0, 255, 0, 0]);
        assert_eq!(m.view_bytes(4), [255; 8]);
        assert_eq!(m.kept(4).collect::<Vec<_>>(), (0..8).collect::<Vec<_>>());
        assert_eq!(PixelMasks::with_full_views(8, vec![None, Some(vec![2])]).kept(0).count(), 8);
        let f = PixelMasks::from_flags(3, [&[false, true, true][..], &[true, false, false][..], &[true; 3][..]]);
        assert_eq!((f.view(0), f.view(1), f.view(2)), (Some(&[1u32, 2][..]), Some(&[0u32][..]), None));
    }

    #[test]
    fn shared_lists_are_held_once_and_stay_shared_through_selections() {
        let lens: Arc<[u32]> = Arc::from(vec![1, 4, 6]);
        let m = PixelMasks::with_shared_views(8, vec![Some(lens.clone()), None, Some(Arc::from(vec![2])), Some(lens.clone()), Some(Arc::from((0..8).collect::<Vec<_>>()))]);
        assert_eq!(Arc::strong_count(&lens), 3, "one list for views 0 and 3");
        assert_eq!((m.total(), m.view(4)), (3 + 8 + 1 + 3 + 8, None));
        assert!(std::ptr::eq(m.view(0).unwrap(), m.view(3).unwrap()));
        assert_eq!(m.pick(12), (3, 1));
        let s = m.select(&[3, 2, 0]);
        assert!(std::ptr::eq(s.view(0).unwrap(), s.view(2).unwrap()) && std::ptr::eq(s.view(0).unwrap(), m.view(0).unwrap()));
        assert_eq!(s, PixelMasks::new(8, vec![vec![1, 4, 6], vec![2], vec![1, 4, 6]]), "equal to the unshared masks");
    }

    #[test]
    #[should_panic(expected = "not strictly ascending")]
    fn shared_lists_must_be_ascending() {
        PixelMasks::with_shared_views(8, vec![Some(Arc::from(vec![3, 3]))]);
    }

    #[test]
    #[should_panic(expected = "kept pixel 2 of 2")]
    fn pick_past_the_end_panics() {
        PixelMasks::new(4, vec![vec![0], vec![1]]).pick(2);
    }
}
