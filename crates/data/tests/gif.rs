//! The animated GIF of `nerf render --gif`: frames, timing and loop as written, and no file left
//! behind by a writer that did not finish.

use image::AnimationDecoder as _;
use nerf_data::GifWriter;

/// A `w × h` frame of one colour.
fn solid(w: u32, h: u32, c: [f32; 3]) -> Vec<f32> {
    c.repeat((w * h) as usize)
}

#[test]
fn frames_come_back_in_order_with_their_delay() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("render.gif");
    let (w, h) = (9, 7);
    let colours = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]];
    let mut g = GifWriter::create(&path, w, h, 25.0).unwrap();
    for c in colours {
        g.push(&solid(w, h, c)).unwrap();
    }
    assert!(!path.exists(), "the GIF appears only when finished");
    g.finish().unwrap();
    assert!(path.exists() && !d.path().join("render.gif.tmp").exists());
    let bytes = std::fs::read(&path).unwrap();
    // Loops for ever: the NETSCAPE2.0 application extension.
    assert!(bytes.windows(11).any(|x| x == b"NETSCAPE2.0"));
    let dec = image::codecs::gif::GifDecoder::new(std::io::Cursor::new(bytes)).unwrap();
    let frames = dec.into_frames().collect_frames().unwrap();
    assert_eq!(frames.len(), colours.len());
    for (f, c) in frames.iter().zip(colours) {
        // 25 frames/s: 4 hundredths of a second.
        assert_eq!(f.delay().numer_denom_ms(), (40, 1));
        let img = f.buffer();
        assert_eq!(img.dimensions(), (w, h));
        let want = c.map(|v| (v * 255.0) as i32);
        for p in img.pixels() {
            let got = [p[0] as i32, p[1] as i32, p[2] as i32];
            assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() <= 8), "{got:?} for {want:?}");
        }
    }
}

#[test]
fn a_bad_rate_names_the_file_and_an_unfinished_gif_leaves_nothing() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("out.gif");
    for fps in [0.0, -1.0, f32::NAN, f32::INFINITY] {
        let e = GifWriter::create(&path, 4, 4, fps).err().expect("a bad rate is refused").to_string();
        assert!(e.contains("out.gif") && e.contains("frames/s"), "{e}");
    }
    let mut g = GifWriter::create(&path, 4, 4, 30.0).unwrap();
    g.push(&solid(4, 4, [0.5; 3])).unwrap();
    drop(g);
    assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 0, "a writer dropped before finish leaves no file");
}
