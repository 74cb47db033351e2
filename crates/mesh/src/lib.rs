//! Surfaces of a trained field (instant-ngp's "marching cubes" mesh export, `nerf export-mesh`):
//! sample the field's density σ on a [`Lattice`] over the scene box, then [`extract_mesh`] the
//! isosurface `σ = threshold` as a triangle mesh with outward normals.
//!
//! The isosurface comes from naive surface nets (Gibson 1998, the `fast-surface-nets` crate): one
//! vertex per lattice cell the surface crosses (the mean of the crossings on the cell's edges),
//! one quad (two triangles) per crossed lattice edge. It places the surface where marching cubes
//! would, to within a fraction of a cell. The lattice is padded with
//! empty space on every side, so the mesh is closed: where the field is dense up to the box, the
//! box's faces close it (its vertices are clamped into the box).
//!
//! Pure functions over flat arrays: the caller evaluates the field (any `RadianceField`, on any
//! device) at [`Lattice::points`] and hands the densities over.

use fast_surface_nets::ndshape::{RuntimeShape, Shape};
use fast_surface_nets::{surface_nets, SurfaceNetsBuffer};
use rayon::prelude::*;
use std::ops::Range;

/// A regular lattice of points over a box, `dims[a]` nodes along axis `a` from `min[a]` to
/// `max[a]` inclusive. Nodes are numbered x fastest, then y, then z: node `(i, j, k)` is number
/// `i + dims[0]·(j + dims[1]·k)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice {
    /// The box's minimum corner (the first node).
    pub min: [f32; 3],
    /// The box's maximum corner (the last node).
    pub max: [f32; 3],
    /// Nodes per axis, each at least 2.
    pub dims: [u32; 3],
}

impl Lattice {
    /// The lattice of `resolution` nodes along the box's longest side and as many per unit length
    /// along the others (instant-ngp's marching-cubes resolution; at least 2 per axis), so that
    /// cells are as near cubic as the box allows.
    ///
    /// # Panics
    /// If `resolution < 2` or the box is empty or not finite.
    pub fn over_box(min: [f32; 3], max: [f32; 3], resolution: u32) -> Self {
        assert!(resolution >= 2, "a lattice needs at least 2 nodes per axis");
        let size: [f32; 3] = std::array::from_fn(|a| max[a] - min[a]);
        assert!(size.iter().all(|s| s.is_finite() && *s > 0.0), "an empty or infinite box: {min:?} to {max:?}");
        let longest = size.iter().fold(0.0f32, |m, &s| m.max(s));
        let dims = std::array::from_fn(|a| (((resolution - 1) as f32 * size[a] / longest).round() as u32 + 1).max(2));
        Self { min, max, dims }
    }

    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.dims.iter().map(|&d| d as usize).product()
    }

    /// Whether the lattice has no node (never, for a lattice from [`Lattice::over_box`]).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The distance between neighbouring nodes along each axis.
    pub fn spacing(&self) -> [f32; 3] {
        std::array::from_fn(|a| (self.max[a] - self.min[a]) / (self.dims[a] - 1) as f32)
    }

    /// The position of node `(i, j, k)`; the last node of an axis is exactly `max`.
    pub fn node(&self, ijk: [u32; 3]) -> [f32; 3] {
        std::array::from_fn(|a| {
            if ijk[a] + 1 == self.dims[a] {
                self.max[a]
            } else {
                self.min[a] + (self.max[a] - self.min[a]) * ijk[a] as f32 / (self.dims[a] - 1) as f32
            }
        })
    }

    /// Writes the positions of nodes `range` (`3·range.len()` floats, x y z per node) into `out`,
    /// resized to fit: the field is evaluated in batches of nodes, never over the whole lattice
    /// at once.
    pub fn points(&self, range: Range<usize>, out: &mut Vec<f32>) {
        out.resize(3 * range.len(), 0.0);
        let [nx, ny, _] = self.dims.map(|d| d as usize);
        for (p, n) in out.chunks_exact_mut(3).zip(range) {
            let ijk = [(n % nx) as u32, ((n / nx) % ny) as u32, (n / (nx * ny)) as u32];
            p.copy_from_slice(&self.node(ijk));
        }
    }
}

/// A triangle mesh in world coordinates.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// Unit outward normals per vertex (towards lower density: the density's negative gradient,
    /// from central differences on the lattice).
    pub normals: Vec<[f32; 3]>,
    /// Triangles, three vertex indices each, counter-clockwise seen from outside.
    pub indices: Vec<u32>,
}

impl Mesh {
    /// Number of triangles.
    pub fn n_triangles(&self) -> usize {
        self.indices.len() / 3
    }
}

/// The isosurface `σ = threshold` of the densities `density` (one per node of `lattice`, in its
/// order) as a closed triangle mesh: the region `σ > threshold` is inside. NaN densities count as
/// empty space.
///
/// # Panics
/// If `density.len() != lattice.len()`, or the padded lattice has more than 2³² nodes.
pub fn extract_mesh(lattice: &Lattice, density: &[f32], threshold: f32) -> Mesh {
    assert_eq!(density.len(), lattice.len(), "extract_mesh: one density per lattice node");
    let [nx, ny, nz] = lattice.dims;
    // Empty space on every side closes the surface at the box: one node before the lattice, two
    // after it (surface nets makes no quad on the edges of its last plane of cells).
    let shape = RuntimeShape::<u32, 3>::new([nx + 3, ny + 3, nz + 3]);
    let padded = shape.usize();
    assert!(padded < u32::MAX as usize, "a lattice of {padded} padded nodes is too large for one mesh");
    // Signed distance as surface nets wants it: negative inside. Empty space is `threshold − 0`;
    // a threshold ≤ 0 would make everything inside, so the padding is kept strictly outside.
    let outside = threshold.max(0.0) + 1.0;
    let mut sdf = vec![outside; padded];
    let (nx_, ny_) = (nx as usize, ny as usize);
    sdf.par_chunks_mut(((nx + 3) * (ny + 3)) as usize).enumerate().skip(1).take(nz as usize).for_each(|(z, slab)| {
        for y in 0..ny_ {
            let src = &density[nx_ * (y + ny_ * (z - 1))..][..nx_];
            let dst = &mut slab[(nx_ + 3) * (y + 1) + 1..][..nx_];
            for (d, &s) in dst.iter_mut().zip(src) {
                *d = if s.is_nan() { outside } else { threshold - s };
            }
        }
    });
    let mut buf = SurfaceNetsBuffer::default();
    surface_nets(&sdf, &shape, [0; 3], [nx + 2, ny + 2, nz + 2], &mut buf);
    drop(sdf);
    let h = lattice.spacing();
    let positions = buf
        .positions
        .iter()
        .map(|p| std::array::from_fn(|a| (lattice.min[a] + (p[a] - 1.0) * h[a]).clamp(lattice.min[a], lattice.max[a])))
        .collect();
    let normals = buf
        .normals
        .iter()
        .map(|g| {
            // The gradient of `threshold − σ` per lattice step, to world units: outward.
            let w: [f32; 3] = std::array::from_fn(|a| g[a] / h[a]);
            let len = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
            if len > 0.0 && len.is_finite() {
                w.map(|v| v / len)
            } else {
                [0.0, 0.0, 0.0]
            }
        })
        .collect();
    Mesh { positions, normals, indices: buf.indices }
}
