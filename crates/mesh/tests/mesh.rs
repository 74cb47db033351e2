//! Isosurfaces of analytic densities: where the vertices lie, which way normals and faces turn,
//! and that the meshes are closed.

use nerf_mesh::{extract_mesh, Lattice, Mesh};
use std::collections::HashMap;

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn norm(a: [f32; 3]) -> f32 {
    dot(a, a).sqrt()
}

/// Densities of `f` at every node of the lattice, through `Lattice::points` in batches.
fn sample(l: &Lattice, f: impl Fn([f32; 3]) -> f32) -> Vec<f32> {
    let mut out = Vec::with_capacity(l.len());
    let mut pts = Vec::new();
    for r0 in (0..l.len()).step_by(1000) {
        l.points(r0..(r0 + 1000).min(l.len()), &mut pts);
        out.extend(pts.chunks_exact(3).map(|p| f([p[0], p[1], p[2]])));
    }
    out
}

/// Every edge is shared by exactly two triangles, in opposite directions (closed and
/// consistently oriented), and V − E + F = 2 (a sphere's topology). Returns the face count.
fn assert_closed_sphere_topology(m: &Mesh) -> usize {
    let mut edges: HashMap<(u32, u32), i32> = HashMap::new();
    for t in m.indices.chunks_exact(3) {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            assert_ne!(a, b, "a degenerate triangle {t:?}");
            *edges.entry((a.min(b), a.max(b))).or_default() += if a < b { 1 } else { -1 };
        }
    }
    let mut count: HashMap<(u32, u32), usize> = HashMap::new();
    for t in m.indices.chunks_exact(3) {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            *count.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    assert!(count.values().all(|&c| c == 2), "an edge not shared by exactly two triangles");
    assert!(edges.values().all(|&s| s == 0), "two triangles run along an edge the same way");
    let (v, e, f) = (m.positions.len() as i64, count.len() as i64, m.n_triangles() as i64);
    assert_eq!(v - e + f, 2, "Euler characteristic of V={v} E={e} F={f}");
    f as usize
}

/// Faces turn away from `centre` (a convex shape around it) and normals point away from it.
fn assert_outward(m: &Mesh, centre: [f32; 3], min_normal_dot: f32) {
    for t in m.indices.chunks_exact(3) {
        let [a, b, c] = [0, 1, 2].map(|k| m.positions[t[k] as usize]);
        let g: [f32; 3] = std::array::from_fn(|i| (a[i] + b[i] + c[i]) / 3.0);
        let n = cross(sub(b, a), sub(c, a));
        assert!(dot(n, sub(g, centre)) > 0.0, "triangle {t:?} faces inwards");
    }
    for (p, n) in m.positions.iter().zip(&m.normals) {
        assert!((norm(*n) - 1.0).abs() < 1e-4, "normal {n:?} is not unit");
        let r = sub(*p, centre);
        assert!(dot(*n, r) / norm(r) > min_normal_dot, "normal {n:?} at {p:?} is not outward");
    }
}

fn smooth_ball(centre: [f32; 3], radius: f32, peak: f32) -> impl Fn([f32; 3]) -> f32 {
    move |p| peak / (1.0 + ((norm(sub(p, centre)) - radius) / 0.03).exp())
}

#[test]
fn a_ball_gives_a_closed_outward_sphere_at_its_radius() {
    let l = Lattice::over_box([-1.0; 3], [1.0; 3], 48);
    assert_eq!(l.dims, [48; 3]);
    let (c, r) = ([0.1, -0.05, 0.02], 0.6);
    // Density 20 inside falling to 0 across the radius: the threshold 10 is the sphere |p − c| = r.
    let m = extract_mesh(&l, &sample(&l, smooth_ball(c, r, 20.0)), 10.0);
    let h = l.spacing()[0];
    assert!(m.positions.len() > 1000, "{} vertices", m.positions.len());
    for p in &m.positions {
        let d = norm(sub(*p, c));
        assert!((d - r).abs() < 0.25 * h, "vertex at distance {d} from the centre, radius {r}, cell {h}");
    }
    assert_closed_sphere_topology(&m);
    assert_outward(&m, c, 0.98);
    // A higher threshold is a smaller sphere: denser inside.
    let inner = extract_mesh(&l, &sample(&l, smooth_ball(c, r, 20.0)), 19.0);
    let mean = |m: &Mesh| m.positions.iter().map(|p| norm(sub(*p, c))).sum::<f32>() / m.positions.len() as f32;
    assert!(mean(&inner) < mean(&m) - 0.05, "{} vs {}", mean(&inner), mean(&m));
}

#[test]
fn a_field_dense_up_to_the_box_is_closed_by_the_box() {
    let (lo, hi) = ([-0.5, 0.0, 1.0], [0.5, 2.0, 1.5]);
    let l = Lattice::over_box(lo, hi, 21);
    assert_eq!(l.dims, [11, 21, 6]);
    let m = extract_mesh(&l, &vec![3.0; l.len()], 1.0);
    assert_closed_sphere_topology(&m);
    let centre = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
    assert_outward(&m, centre, 0.0);
    for p in &m.positions {
        let on_a_face = (0..3).any(|a| p[a] == lo[a] || p[a] == hi[a]);
        let inside = (0..3).all(|a| p[a] >= lo[a] && p[a] <= hi[a]);
        assert!(on_a_face && inside, "vertex {p:?} off the box's surface");
    }
}

#[test]
fn a_box_that_is_not_a_cube_keeps_cells_cubic_and_the_ball_round() {
    let l = Lattice::over_box([0.0, 0.0, 0.0], [2.0, 1.0, 0.5], 81);
    assert_eq!(l.dims, [81, 41, 21]);
    let h = l.spacing();
    assert!((h[0] - h[1]).abs() < 1e-6 && (h[0] - h[2]).abs() < 1e-6, "cells {h:?}");
    let (c, r) = ([1.2, 0.5, 0.25], 0.18);
    let m = extract_mesh(&l, &sample(&l, smooth_ball(c, r, 5.0)), 2.5);
    for p in &m.positions {
        let d = norm(sub(*p, c));
        assert!((d - r).abs() < 0.25 * h[0], "vertex at distance {d}, radius {r}");
    }
    assert_closed_sphere_topology(&m);
    assert_outward(&m, c, 0.95);
}

#[test]
fn empty_space_and_nan_give_no_triangles() {
    let l = Lattice::over_box([0.0; 3], [1.0; 3], 8);
    assert_eq!(extract_mesh(&l, &vec![0.5; l.len()], 1.0), Mesh::default());
    assert_eq!(extract_mesh(&l, &vec![f32::NAN; l.len()], 1.0), Mesh::default());
    // One NaN node inside a dense block: a hole, with its own small surface around it.
    let mut d = vec![3.0; l.len()];
    d[3 + 8 * (3 + 8 * 3)] = f32::NAN;
    let m = extract_mesh(&l, &d, 1.0);
    assert!(m.n_triangles() > 0);
    assert!(m.indices.iter().all(|&i| (i as usize) < m.positions.len()));
}

#[test]
fn lattice_nodes_run_x_fastest_and_end_on_the_box() {
    let l = Lattice::over_box([1.0, -2.0, 0.0], [2.0, -1.5, 0.25], 5);
    assert_eq!(l.dims, [5, 3, 2]);
    assert_eq!(l.len(), 30);
    let mut all = Vec::new();
    l.points(0..l.len(), &mut all);
    assert_eq!(&all[..3], &[1.0, -2.0, 0.0]);
    assert_eq!(&all[3..6], &[1.25, -2.0, 0.0]);
    assert_eq!(&all[3 * 5..3 * 6], &[1.0, -1.75, 0.0]);
    assert_eq!(&all[3 * 29..], &[2.0, -1.5, 0.25]);
    let mut part = Vec::new();
    l.points(7..19, &mut part);
    assert_eq!(part, all[3 * 7..3 * 19]);
}
