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
