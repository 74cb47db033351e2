//! Point clouds as binary PLY: the header and the packed records read back.

use nerf_data::write_ply_points;

#[test]
fn ply_points_read_back() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("points.ply");
    let points = [([0.5f32, -1.25, 3.0], [1.0f32, 0.0, 0.5]), ([1e-3, 2.0, -7.5], [0.2, 2.0, -1.0])];
    write_ply_points(&path, &points).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let end = b"end_header\n";
    let h = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..h]).unwrap();
    assert!(header.starts_with("ply\nformat binary_little_endian 1.0\n") && header.contains("element vertex 2\n"), "{header}");
    let props: Vec<&str> = header.lines().filter(|l| l.starts_with("property")).collect();
    assert_eq!(props, ["property float x", "property float y", "property float z", "property uchar red", "property uchar green", "property uchar blue"]);
    let body = &bytes[h..];
    assert_eq!(body.len(), 2 * 15);
    for (i, (p, _)) in points.iter().enumerate() {
        let r = &body[15 * i..15 * (i + 1)];
        let xyz: Vec<f32> = (0..3).map(|k| f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap())).collect();
        assert_eq!(xyz, p.to_vec());
    }
    // Colours rounded to u8 and clamped.
    assert_eq!(&body[12..15], &[255, 0, 128]);
    assert_eq!(&body[27..30], &[51, 255, 0]);
    assert!(!d.path().join("points.ply.tmp").exists());
    let e = write_ply_points(&d.path().join("nope/points.ply"), &points).unwrap_err();
    assert!(e.to_string().contains("nope"), "{e}");
}

#[test]
fn ply_meshes_read_back() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("mesh.ply");
    let positions = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let normals = [[-0.577f32, -0.577, -0.577], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let colors = [[1.0f32, 0.5, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.1, 0.2, 0.3]];
    let indices = [0u32, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3];
    nerf_data::write_ply_mesh(&path, &positions, &normals, &colors, &indices).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let end = b"end_header\n";
    let h = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&bytes[..h]).unwrap();
    assert!(header.contains("element vertex 4\n") && header.contains("element face 4\nproperty list uchar int vertex_indices\n"), "{header}");
    let props: Vec<&str> = header.lines().filter(|l| l.starts_with("property")).take(9).collect();
    assert_eq!(props[3..6], ["property float nx", "property float ny", "property float nz"]);
    let body = &bytes[h..];
    assert_eq!(body.len(), 4 * 27 + 4 * 13);
    let f = |o: usize| f32::from_le_bytes(body[o..o + 4].try_into().unwrap());
    for (i, (p, n)) in positions.iter().zip(&normals).enumerate() {
        let got: Vec<f32> = (0..6).map(|k| f(27 * i + 4 * k)).collect();
        assert_eq!(got, [p.as_slice(), n.as_slice()].concat());
    }
    assert_eq!(&body[24..27], &[255, 128, 0]);
    assert_eq!(&body[27 * 3 + 24..27 * 4], &[26, 51, 77]);
    let faces = &body[4 * 27..];
    for (k, t) in indices.chunks_exact(3).enumerate() {
        let r = &faces[13 * k..13 * (k + 1)];
        assert_eq!(r[0], 3);
        let got: Vec<u32> = (0..3).map(|j| i32::from_le_bytes(r[1 + 4 * j..5 + 4 * j].try_into().unwrap()) as u32).collect();
        assert_eq!(got, t);
    }
    assert!(!d.path().join("mesh.ply.tmp").exists());
    let e = nerf_data::write_ply_mesh(&d.path().join("nope/mesh.ply"), &positions, &normals, &colors, &indices).unwrap_err();
    assert!(e.to_string().contains("nope"), "{e}");
}

#[test]
fn obj_meshes_read_back() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("mesh.obj");
    let positions = [[0.0f32, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -2.25]];
    let normals = [[-0.6f32, -0.8, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let colors = [[1.0f32, 0.5, 0.0], [2.0, -1.0, 0.25], [1.0, 1.0, 1.0], [0.1, 0.2, 0.3]];
    let indices = [0u32, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3];
    nerf_data::write_obj_mesh(&path, &positions, &normals, &colors, &indices).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let nums = |l: &str| -> Vec<f32> { l.split_whitespace().skip(1).map(|x| x.parse().unwrap()).collect() };
    let v: Vec<Vec<f32>> = text.lines().filter(|l| l.starts_with("v ")).map(nums).collect();
    let vn: Vec<Vec<f32>> = text.lines().filter(|l| l.starts_with("vn ")).map(nums).collect();
    assert_eq!(v.len(), 4);
    for (k, p) in positions.iter().enumerate() {
        assert_eq!(v[k][..3], p[..]);
        assert_eq!(vn[k], normals[k].to_vec());
    }
    assert_eq!(v[0][3..], [1.0, 0.5, 0.0]);
    assert_eq!(v[1][3..], [1.0, 0.0, 0.25], "colours clamped to [0, 1]");
    let f: Vec<Vec<u32>> = text
        .lines()
        .filter(|l| l.starts_with("f "))
        .map(|l| l.split_whitespace().skip(1).map(|c| {
            let (a, b) = c.split_once("//").unwrap();
            assert_eq!(a, b, "normal index = vertex index");
            a.parse().unwrap()
        }).collect())
        .collect();
    assert_eq!(f.concat(), indices.iter().map(|i| i + 1).collect::<Vec<_>>(), "1-based, in order");
    assert!(!d.path().join("mesh.obj.tmp").exists());
    let e = nerf_data::write_obj_mesh(&d.path().join("nope/mesh.obj"), &positions, &normals, &colors, &indices).unwrap_err();
    assert!(e.to_string().contains("nope"), "{e}");
}
