//! COLMAP scene folders (`images/` + a sparse model): the model read in both of COLMAP's formats,
//! its cameras checked against COLMAP's own projection, and its errors. The fixture is the in-repo
//! scene `scenes/lego_100` written as a COLMAP model would hold it, in an arbitrary world frame
//! (COLMAP's reconstructions have no preferred position, orientation or scale).

use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};
use nerf_data::colmap::{self, ColmapCamera, ColmapImage, ColmapModel};
use nerf_data::{load_blender, load_scene, DataError, Dataset, Distortion, LensModel, LoadOptions, Split};

fn lego_100() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/lego_100")
}

/// A unit quaternion `(w, x, y, z)` of a rotation matrix (Shepperd's method).
fn quaternion(r: DMat3) -> [f64; 4] {
    let m = |i: usize, j: usize| r.col(j)[i];
    let tr = m(0, 0) + m(1, 1) + m(2, 2);
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [0.25 * s, (m(2, 1) - m(1, 2)) / s, (m(0, 2) - m(2, 0)) / s, (m(1, 0) - m(0, 1)) / s]
    } else if m(0, 0) > m(1, 1) && m(0, 0) > m(2, 2) {
        let s = (1.0 + m(0, 0) - m(1, 1) - m(2, 2)).sqrt() * 2.0;
        [(m(2, 1) - m(1, 2)) / s, 0.25 * s, (m(0, 1) + m(1, 0)) / s, (m(0, 2) + m(2, 0)) / s]
    } else if m(1, 1) > m(2, 2) {
        let s = (1.0 + m(1, 1) - m(0, 0) - m(2, 2)).sqrt() * 2.0;
        [(m(0, 2) - m(2, 0)) / s, (m(0, 1) + m(1, 0)) / s, 0.25 * s, (m(1, 2) + m(2, 1)) / s]
    } else {
        let s = (1.0 + m(2, 2) - m(0, 0) - m(1, 1)).sqrt() * 2.0;
        [(m(1, 0) - m(0, 1)) / s, (m(0, 2) + m(2, 0)) / s, (m(1, 2) + m(2, 1)) / s, 0.25 * s]
    };
    // COLMAP keeps w ≥ 0; either sign is the same rotation.
    if q[0] < 0.0 {
        q.map(|v| -v)
    } else {
        q
    }
}

/// The similarity from lego's (Blender) world into the fixture's COLMAP world: `s·Q·p + d`.
struct Similarity {
    s: f64,
    q: DMat3,
    d: DVec3,
}

impl Similarity {
    fn apply(&self, p: DVec3) -> DVec3 {
        self.s * (self.q * p) + self.d
    }
}

fn arbitrary_frame() -> Similarity {
    Similarity { s: 3.7, q: DMat3::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.4), d: DVec3::new(-5.0, 12.0, 0.5) }
}

/// lego_100's train and test frames as one COLMAP model (image `view_NNN.png`, the frames in the
/// order train then test), in the world `sim` maps lego's into; its images copied beside it.
fn lego_model(root: &Path, sim: &Similarity) -> ColmapModel {
    let lego = lego_100();
    let blender = load_blender(&lego, Split::Train, &LoadOptions::default()).unwrap();
    let f = blender.cameras[0].intrinsics.fx as f64;
    std::fs::create_dir_all(root.join("images")).unwrap();
    let mut images = Vec::new();
    for split in ["train", "test"] {
        let t: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(lego.join(format!("transforms_{split}.json"))).unwrap()).unwrap();
        for fr in t["frames"].as_array().unwrap() {
            let m = |r: usize, c: usize| fr["transform_matrix"][r][c].as_f64().unwrap();
            // OpenGL camera axes → OpenCV's (y and z negated), moved into COLMAP's world.
            let r_gl = DMat3::from_cols(DVec3::new(m(0, 0), m(1, 0), m(2, 0)), DVec3::new(m(0, 1), m(1, 1), m(2, 1)), DVec3::new(m(0, 2), m(1, 2), m(2, 2)));
            let c2w_cv = sim.q * r_gl * DMat3::from_diagonal(DVec3::new(1.0, -1.0, -1.0));
            let centre = sim.apply(DVec3::new(m(0, 3), m(1, 3), m(2, 3)));
            let r = c2w_cv.transpose();
            let t = -(r * centre);
            let id = images.len() as u32 + 1;
            let rel = fr["file_path"].as_str().unwrap().trim_start_matches("./");
            let name = format!("view_{id:03}.png");
            std::fs::copy(lego.join(format!("{rel}.png")), root.join("images").join(&name)).unwrap();
            images.push(ColmapImage { id, qvec: quaternion(r), tvec: t.to_array(), camera_id: 7, name });
        }
    }
    ColmapModel { cameras: vec![ColmapCamera { id: 7, model: "PINHOLE".into(), width: 100, height: 100, params: vec![f, f, 50.0, 50.0] }], images }
}

const MODEL_IDS: [(&str, i32); 18] = [
    ("SIMPLE_PINHOLE", 0),
    ("PINHOLE", 1),
    ("SIMPLE_RADIAL", 2),
    ("RADIAL", 3),
    ("OPENCV", 4),
    ("OPENCV_FISHEYE", 5),
    ("FULL_OPENCV", 6),
    ("FOV", 7),
    ("SIMPLE_RADIAL_FISHEYE", 8),
    ("RADIAL_FISHEYE", 9),
    ("THIN_PRISM_FISHEYE", 10),
    ("RAD_TAN_THIN_PRISM_FISHEYE", 11),
    ("SIMPLE_DIVISION", 12),
    ("DIVISION", 13),
    ("SIMPLE_FISHEYE", 14),
    ("FISHEYE", 15),
    ("EUCM", 16),
    ("EQUIRECTANGULAR", 17),
];

/// `cameras.bin` and `images.bin` as COLMAP writes them (`write_cameras_binary`,
/// `write_images_binary` of its `read_write_model.py`), each image with `points` 2-D points.
fn write_bin(dir: &Path, m: &ColmapModel, points: usize) {
    std::fs::create_dir_all(dir).unwrap();
    let mut c = (m.cameras.len() as u64).to_le_bytes().to_vec();
    for cam in &m.cameras {
        let id = MODEL_IDS.iter().find(|(n, _)| *n == cam.model).unwrap().1;
        c.extend((cam.id as i32).to_le_bytes());
        c.extend(id.to_le_bytes());
        c.extend(cam.width.to_le_bytes());
        c.extend(cam.height.to_le_bytes());
        cam.params.iter().for_each(|p| c.extend(p.to_le_bytes()));
    }
    std::fs::write(dir.join("cameras.bin"), c).unwrap();
    let mut b = (m.images.len() as u64).to_le_bytes().to_vec();
    for im in &m.images {
        b.extend((im.id as i32).to_le_bytes());
        im.qvec.iter().chain(&im.tvec).for_each(|v| b.extend(v.to_le_bytes()));
        b.extend((im.camera_id as i32).to_le_bytes());
        b.extend(im.name.as_bytes());
        b.push(0);
        b.extend((points as u64).to_le_bytes());
        for k in 0..points {
            b.extend((k as f64).to_le_bytes());
            b.extend((2.0 * k as f64).to_le_bytes());
            b.extend((-1i64).to_le_bytes());
        }
    }
    std::fs::write(dir.join("images.bin"), b).unwrap();
}

/// `cameras.txt` and `images.txt` as COLMAP writes them (header comments, each image's 2-D
/// points on the line after it, empty for the odd images).
fn write_txt(dir: &Path, m: &ColmapModel) {
    std::fs::create_dir_all(dir).unwrap();
    let mut c = String::from("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    for cam in &m.cameras {
        let p: Vec<String> = cam.params.iter().map(|v| format!("{v:?}")).collect();
        c += &format!("{} {} {} {} {}\n", cam.id, cam.model, cam.width, cam.height, p.join(" "));
    }
    std::fs::write(dir.join("cameras.txt"), c).unwrap();
    let mut s = String::from("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    for (k, im) in m.images.iter().enumerate() {
        let v: Vec<String> = im.qvec.iter().chain(&im.tvec).map(|v| format!("{v:?}")).collect();
        s += &format!("{} {} {} {}\n", im.id, v.join(" "), im.camera_id, im.name);
        s += if k % 2 == 0 { "12.5 33.0 -1 40.25 2.0 17\n" } else { "\n" };
    }
    std::fs::write(dir.join("images.txt"), s).unwrap();
}

fn load(root: &Path, split: Split) -> Dataset {
    load_scene(root, split, &LoadOptions::default()).unwrap_or_else(|e| panic!("{e}"))
}

/// COLMAP's projection `u = K·(R·X + t)` of a point of its world, against the loaded camera's ray
/// through `u`: the ray must pass through the point, moved as the loader moved the poses (the
/// `applied_transform` of nerfstudio, then its normalisation). Checked for every view of both
/// splits, from a binary model in `sparse/0` and a text one in `colmap/sparse/0`.
#[test]
fn colmap_models_load_with_cameras_that_reproject_colmaps_points() {
    let sim = arbitrary_frame();
    // The third model has a second camera: the odd images cropped to portrait 64×100 (their
    // right 64 columns), as a capture with photos of two sizes.
    for (layout, binary, portrait) in [("sparse/0", true, false), ("colmap/sparse/0", false, false), ("sparse/0", true, true)] {
        let dir = tempfile::tempdir().unwrap();
        let mut model = lego_model(dir.path(), &sim);
        if portrait {
            let f = model.cameras[0].params[0];
            model.cameras.push(ColmapCamera { id: 8, model: "PINHOLE".into(), width: 64, height: 100, params: vec![f, f, 14.0, 50.0] });
            for im in model.images.iter_mut().filter(|im| im.id % 2 == 1) {
                im.camera_id = 8;
                let path = dir.path().join("images").join(&im.name);
                let img = image::open(&path).unwrap().to_rgba8();
                image::imageops::crop_imm(&img, 36, 0, 64, 100).to_image().save(&path).unwrap();
            }
        }
        let mdir = dir.path().join(layout);
        if binary {
            write_bin(&mdir, &model, 3);
        } else {
            write_txt(&mdir, &model);
        }
        assert!(nerf_data::is_colmap(dir.path()) && !nerf_data::is_colmap(&lego_100()));
        assert_eq!(colmap::find_model(dir.path()).as_deref(), Some(mdir.as_path()));
        assert_eq!(colmap::read_model(&mdir).unwrap(), model, "{layout}: read back as written");
        let (train, test) = (load(dir.path(), Split::Train), load(dir.path(), Split::Test));
        let n = model.images.len();
        assert_eq!((train.n_views(), test.n_views()), (n - n.div_ceil(8), n.div_ceil(8)), "every 8th image by name is a test view");
        let norm = train.normalization.expect("nerfstudio's normalisation");
        let to_loaded = |x: DVec3| -> DVec3 {
            let a = DVec3::new(x.x, x.z, -x.y); // applied_transform
            let d = a - DVec3::from_array(norm.center);
            DVec3::from_array(std::array::from_fn(|i| norm.scale * DVec3::from_array(norm.rotation[i]).dot(d)))
        };
        let mut rng_state = 0x1234_5678u64;
        let mut rnd = || {
            rng_state = rng_state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (rng_state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut sorted: Vec<&ColmapImage> = model.images.iter().collect();
        sorted.sort_by(|a, b| a.name.cmp(&b.name));
        let (mut tr, mut te) = (train.cameras.iter(), test.cameras.iter());
        let mut checked = 0;
        for (i, im) in sorted.iter().enumerate() {
            let cam = if i % 8 == 0 { te.next() } else { tr.next() }.unwrap();
            let path = if i % 8 == 0 { &test.file_paths[i / 8] } else { &train.file_paths[i - i / 8 - 1] };
            assert!(path.ends_with(Path::new("images").join(&im.name)), "{path:?} is {}'s image", im.name);
            let r = colmap::rotation(im.qvec);
            let r = DMat3::from_cols(DVec3::new(r[0][0], r[1][0], r[2][0]), DVec3::new(r[0][1], r[1][1], r[2][1]), DVec3::new(r[0][2], r[1][2], r[2][2]));
            let c = model.cameras.iter().find(|c| c.id == im.camera_id).unwrap();
            let [fx, fy, cx, cy] = [c.params[0], c.params[1], c.params[2], c.params[3]];
            assert_eq!((cam.intrinsics.width, cam.intrinsics.height), (c.width as u32, c.height as u32), "{}", im.name);
            for _ in 0..20 {
                // A point near lego (within its box), in COLMAP's world.
                let x = sim.apply(DVec3::new(rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0));
                let xc = r * x + DVec3::from_array(im.tvec);
                assert!(xc.z > 0.0, "in front of the camera");
                let (u, v) = (fx * xc.x / xc.z + cx, fy * xc.y / xc.z + cy);
                let ray = cam.ray_at(u as f32, v as f32);
                let p = to_loaded(x);
                let o = ray.origin.as_dvec3();
                let d = ray.dir.as_dvec3();
                let along = (p - o).dot(d);
                let off = (p - o - along * d).length();
                assert!(along > 0.0 && off < 2e-5 * along.max(1.0), "{}: the ray misses the point by {off} at depth {along}", im.name);
                checked += 1;
            }
        }
        assert_eq!(checked, 20 * n);
        // lego's cameras look at its origin: after the normalisation, where `nerf render` centres
        // its orbit (nerfstudio's centring puts the mean camera centre, above the object, at 0).
        let cams: Vec<_> = train.cameras.iter().chain(&test.cameras).copied().collect();
        let focus = nerf_rays::look_at_point(&cams).unwrap().as_dvec3();
        let origin = to_loaded(sim.apply(DVec3::ZERO));
        assert!((focus - origin).length() < 1e-4 && origin.length() > 0.1, "{focus} vs {origin}");
        // The images are lego's own, pixel for pixel (a portrait one on the canvas's left).
        let lego_train = load_blender(&lego_100(), Split::Train, &LoadOptions::default()).unwrap();
        assert!(train.images[0] == lego_train.images[1], "view_002 is lego's second training view");
        if portrait {
            assert_eq!((train.width, train.height, train.view_size(1)), (100, 100, (64, 100)), "view_003 is a portrait");
            let whole = lego_train.images[2].to_f32();
            let crop: Vec<f32> = (0..100).flat_map(|row| whole[4 * (row * 100 + 36)..4 * (row * 100 + 100)].iter().copied()).collect();
            assert!(train.view_crop(1, 4, &train.images[1].to_f32()).as_ref() == &crop[..], "view_003 is lego's third training view's right part");
            assert_eq!(train.masks.as_ref().unwrap().total(), train.n_view_pixels());
        }
    }
}

/// The binary and text forms of one model give the same dataset; the camera models' parameters
/// become nerfstudio's keys (`SIMPLE_*` share one focal length; `FULL_OPENCV` without rational
/// terms is OPENCV with `k3`).
#[test]
fn binary_and_text_models_agree_and_camera_models_map_to_nerfstudio_keys() {
    let dir = tempfile::tempdir().unwrap();
    let model = lego_model(dir.path(), &arbitrary_frame());
    write_bin(&dir.path().join("sparse/0"), &model, 0);
    let a = load(dir.path(), Split::Train);
    std::fs::remove_dir_all(dir.path().join("sparse")).unwrap();
    write_txt(&dir.path().join("sparse/0"), &model);
    let b = load(dir.path(), Split::Train);
    for (ca, cb) in a.cameras.iter().zip(&b.cameras) {
        assert_eq!((ca.intrinsics, ca.position, ca.rotation), (cb.intrinsics, cb.position, cb.rotation));
    }
    assert!(a.images == b.images);
    // A fisheye camera of the same intrinsics: the same cameras with the fisheye lens, the photos
    // as they are; resampled to pinhole cameras with `undistort`.
    std::fs::remove_dir_all(dir.path().join("sparse")).unwrap();
    let mut fish = model.clone();
    fish.cameras[0].model = "OPENCV_FISHEYE".into();
    fish.cameras[0].params.extend([0.02, -0.01, 0.0, 0.0]);
    write_bin(&dir.path().join("sparse/0"), &fish, 0);
    let f = load(dir.path(), Split::Train);
    assert!(f.cameras.iter().zip(&a.cameras).all(|(x, y)| x.intrinsics == y.intrinsics && x.position == y.position));
    let lens = nerf_rays::Distortion { model: nerf_rays::LensModel::Fisheye, k1: 0.02, k2: -0.01, ..nerf_rays::Distortion::NONE };
    assert!(f.cameras.iter().all(|c| c.distortion == lens), "{:?}", f.cameras[0].distortion);
    assert!(f.images == a.images, "the fisheye photos are kept as taken");
    let resampled = load_scene(dir.path(), Split::Train, &LoadOptions { undistort: true, ..LoadOptions::default() }).unwrap();
    assert!(resampled.cameras.iter().all(|c| c.distortion.is_identity()));
    assert!(resampled.images != a.images, "the fisheye photos are resampled");
    std::fs::remove_dir_all(dir.path().join("sparse")).unwrap();
    write_txt(&dir.path().join("sparse/0"), &model);
    // instant-ngp's dynamic mask beside a photo in images/: everything there moved.
    assert!(a.masks.is_none());
    let photo = &a.file_paths[0];
    let dynamic = photo.with_file_name(format!("dynamic_mask_{}.png", photo.file_stem().unwrap().to_string_lossy()));
    image::GrayImage::from_pixel(a.width, a.height, image::Luma([255])).save(&dynamic).unwrap();
    let masks = load(dir.path(), Split::Train).masks.expect("the dynamic mask is read");
    let n_pix = (a.width * a.height) as usize;
    assert_eq!((masks.kept_in(0), masks.kept_in(1), masks.view(1)), (0, n_pix as u64, None));

    let keys = |model: &str, params: Vec<f64>| -> serde_json::Value {
        let m = ColmapModel {
            cameras: vec![ColmapCamera { id: 1, model: model.into(), width: 64, height: 48, params }],
            images: vec![ColmapImage { id: 1, qvec: [1.0, 0.0, 0.0, 0.0], tvec: [0.0; 3], camera_id: 1, name: "a.png".into() }],
        };
        colmap::transforms_json(Path::new("images.bin"), &m).unwrap()["frames"][0].clone()
    };
    let f = keys("SIMPLE_RADIAL", vec![40.0, 31.0, 23.0, 0.1]);
    assert_eq!((f["fl_x"].as_f64(), f["fl_y"].as_f64(), f["cx"].as_f64(), f["cy"].as_f64(), f["k1"].as_f64()), (Some(40.0), Some(40.0), Some(31.0), Some(23.0), Some(0.1)));
    assert!(f.get("k2").is_none() && f["w"] == 64 && f["h"] == 48 && f["file_path"] == "images/a.png");
    let f = keys("OPENCV", vec![40.0, 41.0, 31.0, 23.0, 0.1, -0.2, 0.01, 0.02]);
    assert_eq!(["k1", "k2", "p1", "p2"].map(|k| f[k].as_f64().unwrap()), [0.1, -0.2, 0.01, 0.02]);
    assert_eq!(f["fl_y"].as_f64(), Some(41.0));
    let f = keys("FULL_OPENCV", vec![40.0, 41.0, 31.0, 23.0, 0.1, -0.2, 0.01, 0.02, 0.003, 0.04, 0.005, 0.0006]);
    assert_eq!(f["camera_model"].as_str(), Some("FULL_OPENCV"));
    assert_eq!(["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"].map(|k| f[k].as_f64().unwrap()), [0.1, -0.2, 0.01, 0.02, 0.003, 0.04, 0.005, 0.0006]);
    // COLMAP's sx1, sy1 are OpenCV's s1, s3.
    let f = keys("THIN_PRISM_FISHEYE", vec![40.0, 41.0, 31.0, 23.0, 0.1, -0.2, 0.01, 0.02, 0.003, 0.0004, 0.005, 0.006]);
    assert_eq!(f["camera_model"].as_str(), Some("THIN_PRISM_FISHEYE"));
    assert_eq!(["k1", "k2", "p1", "p2", "k3", "k4", "s1", "s3"].map(|k| f[k].as_f64().unwrap()), [0.1, -0.2, 0.01, 0.02, 0.003, 0.0004, 0.005, 0.006]);
    // Project Aria's Fisheye624, as nerfstudio writes it: its 12 coefficients in COLMAP's order.
    let aria: Vec<f64> = (1..=12).map(|i| i as f64 * 1e-3).collect();
    let f = keys("RAD_TAN_THIN_PRISM_FISHEYE", [vec![40.0, 41.0, 31.0, 23.0], aria.clone()].concat());
    assert_eq!((f["camera_model"].as_str(), f["distortion_params"].clone()), (Some("FISHEYE624"), serde_json::json!(aria)));
    let f = keys("FOV", vec![40.0, 41.0, 31.0, 23.0, 0.9]);
    assert_eq!((f["camera_model"].as_str(), f["omega"].as_f64()), (Some("FOV"), Some(0.9)));
    // Each model loads as its lens (COLMAP's parameters in its order, taken to ours).
    std::fs::remove_dir_all(dir.path().join("sparse")).unwrap();
    let cases = [
        ("FULL_OPENCV", vec![-0.1, 0.02, 0.001, -0.002, 0.003, 0.05, -0.01, 0.002], Distortion { k1: -0.1, k2: 0.02, p1: 0.001, p2: -0.002, k3: 0.003, k4: 0.05, k5: -0.01, k6: 0.002, ..Distortion::NONE }),
        (
            "THIN_PRISM_FISHEYE",
            vec![0.02, -0.01, 0.001, -0.002, 0.003, -0.0004, 0.002, -0.001],
            Distortion { model: LensModel::Fisheye, k1: 0.02, k2: -0.01, p1: 0.001, p2: -0.002, k3: 0.003, k4: -0.0004, s1: 0.002, s3: -0.001, ..Distortion::NONE },
        ),
        (
            "RAD_TAN_THIN_PRISM_FISHEYE",
            vec![0.02, -0.01, 0.003, -0.0004, 0.0001, -0.00002, 0.001, -0.002, 0.002, -0.0005, -0.001, 0.0003],
            Distortion::from_coefficients(LensModel::Fisheye624, [0.02, -0.01, 0.003, -0.0004, 0.0001, -0.00002, -0.002, 0.001, 0.002, -0.0005, -0.001, 0.0003]),
        ),
        ("FOV", vec![0.9], Distortion::fov(0.9)),
        ("DIVISION", vec![-0.05], Distortion { model: LensModel::Division, k1: -0.05, ..Distortion::NONE }),
        ("FISHEYE", vec![], Distortion { model: LensModel::Fisheye, ..Distortion::NONE }),
        ("EUCM", vec![0.6, 1.1], Distortion::eucm(0.6, 1.1)),
    ];
    for (name, coefficients, lens) in cases {
        let mut m = model.clone();
        m.cameras[0].model = name.into();
        m.cameras[0].params.truncate(4);
        m.cameras[0].params.extend(coefficients);
        write_bin(&dir.path().join("sparse/0"), &m, 0);
        let d = load(dir.path(), Split::Train);
        assert!(d.cameras.iter().all(|c| c.distortion == lens), "{name}: {}", d.cameras[0].distortion);
        std::fs::remove_dir_all(dir.path().join("sparse")).unwrap();
    }
    // A panorama (COLMAP's EQUIRECTANGULAR) is six views, the faces of a cube map; the front
    // one looks where a pinhole camera of the same pose looks, as COLMAP's and nerfstudio's
    // mappings both put the image's centre forward and its top row up.
    let mut pano = model.clone();
    pano.cameras[0].model = "EQUIRECTANGULAR".into();
    pano.cameras[0].params = vec![100.0, 100.0];
    write_bin(&dir.path().join("sparse/0"), &pano, 0);
    let p = load(dir.path(), Split::Train);
    assert_eq!(p.n_views(), 6 * a.n_views());
    for (i, c) in a.cameras.iter().enumerate() {
        let front = &p.cameras[6 * i];
        assert!(front.rotation.abs_diff_eq(c.rotation, 1e-5) && (front.position - c.position).length() < 1e-5, "view {i}");
        assert!(front.distortion.is_identity() && front.intrinsics.fx * 2.0 == front.intrinsics.width as f32, "a 90° pinhole face");
    }
    std::fs::remove_dir_all(dir.path().join("sparse")).unwrap();
    write_txt(&dir.path().join("sparse/0"), &model);
    // The fisheyes, as nerfstudio writes them: OPENCV_FISHEYE with all four terms.
    let fisheye = |f: &serde_json::Value| (f["camera_model"].as_str().map(str::to_string), ["fl_x", "fl_y", "k1", "k2", "k3", "k4"].map(|k| f[k].as_f64().unwrap()));
    let f = keys("OPENCV_FISHEYE", vec![40.0, 41.0, 31.0, 23.0, 0.1, -0.2, 0.03, -0.004]);
    assert_eq!(fisheye(&f), (Some("OPENCV_FISHEYE".to_string()), [40.0, 41.0, 0.1, -0.2, 0.03, -0.004]));
    let f = keys("RADIAL_FISHEYE", vec![40.0, 31.0, 23.0, 0.1, -0.2]);
    assert_eq!(fisheye(&f), (Some("OPENCV_FISHEYE".to_string()), [40.0, 40.0, 0.1, -0.2, 0.0, 0.0]));
    let f = keys("SIMPLE_RADIAL_FISHEYE", vec![40.0, 31.0, 23.0, 0.1]);
    assert_eq!(fisheye(&f), (Some("OPENCV_FISHEYE".to_string()), [40.0, 40.0, 0.1, 0.0, 0.0, 0.0]));
    assert_eq!((f["cx"].as_f64(), f["cy"].as_f64(), f.get("p1")), (Some(31.0), Some(23.0), None));
    // COLMAP 3.12's: the plain equidistant fisheyes, the division model, EUCM, panoramas.
    let f = keys("SIMPLE_FISHEYE", vec![40.0, 31.0, 23.0]);
    assert_eq!(fisheye(&f), (Some("OPENCV_FISHEYE".to_string()), [40.0, 40.0, 0.0, 0.0, 0.0, 0.0]));
    let f = keys("FISHEYE", vec![40.0, 41.0, 31.0, 23.0]);
    assert_eq!(fisheye(&f), (Some("OPENCV_FISHEYE".to_string()), [40.0, 41.0, 0.0, 0.0, 0.0, 0.0]));
    let f = keys("SIMPLE_DIVISION", vec![40.0, 31.0, 23.0, -0.1]);
    assert_eq!((f["camera_model"].as_str(), f["fl_x"].as_f64(), f["fl_y"].as_f64(), f["k1"].as_f64()), (Some("DIVISION"), Some(40.0), Some(40.0), Some(-0.1)));
    let f = keys("DIVISION", vec![40.0, 41.0, 31.0, 23.0, 0.05]);
    assert_eq!((f["camera_model"].as_str(), f["fl_y"].as_f64(), f["cy"].as_f64(), f["k1"].as_f64()), (Some("DIVISION"), Some(41.0), Some(23.0), Some(0.05)));
    let f = keys("EQUIRECTANGULAR", vec![64.0, 48.0]);
    assert_eq!((f["camera_model"].as_str(), f["w"].as_u64(), f["h"].as_u64(), f.get("fl_x")), (Some("EQUIRECTANGULAR"), Some(64), Some(48), None));
    let f = keys("EUCM", vec![40.0, 41.0, 31.0, 23.0, 0.6, 1.1]);
    assert_eq!((f["camera_model"].as_str(), f["alpha"].as_f64(), f["beta"].as_f64(), f.get("k1")), (Some("EUCM"), Some(0.6), Some(1.1), None));
    // The identity pose: COLMAP's camera at the origin looking down +z (OpenCV) is, after
    // nerfstudio's axes, a camera at the origin looking along +y with +z up.
    let m = &f["transform_matrix"];
    let col = |c: usize| [0, 1, 2].map(|r| m[r][c].as_f64().unwrap());
    assert_eq!((col(1), col(2)), ([0.0, 0.0, 1.0], [0.0, -1.0, 0.0]), "up = +z, backwards = −y");
}

fn err_of(root: &Path) -> String {
    match load_scene(root, Split::Train, &LoadOptions::default()) {
        Ok(_) => panic!("{} loaded", root.display()),
        Err(e) => e.to_string(),
    }
}

/// Broken models are errors naming the file and the problem, never a panic or a huge allocation.
#[test]
fn broken_models_are_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let model = lego_model(dir.path(), &arbitrary_frame());
    let mdir = dir.path().join("sparse/0");
    write_bin(&mdir, &model, 2);
    let images = std::fs::read(mdir.join("images.bin")).unwrap();
    let cameras = std::fs::read(mdir.join("cameras.bin")).unwrap();
    let with = |file: &str, bytes: &[u8]| {
        std::fs::write(mdir.join(file), bytes).unwrap();
        let e = err_of(dir.path());
        std::fs::write(mdir.join("images.bin"), &images).unwrap();
        std::fs::write(mdir.join("cameras.bin"), &cameras).unwrap();
        e
    };
    let e = with("images.bin", &images[..images.len() - 5]);
    assert!(e.contains("images.bin") && e.contains("truncated"), "{e}");
    let e = with("images.bin", &[images.as_slice(), &[0u8; 3]].concat());
    assert!(e.contains("images.bin") && e.contains("3 bytes after"), "{e}");
    let mut huge = images.clone();
    huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
    let e = with("images.bin", &huge);
    assert!(e.contains("images.bin") && e.contains("number of images"), "{e}");
    let mut unknown = cameras.clone();
    unknown[12..16].copy_from_slice(&99i32.to_le_bytes()); // the first camera's model id
    let e = with("cameras.bin", &unknown);
    assert!(e.contains("cameras.bin") && e.contains("camera 7: unknown camera model id 99"), "{e}");

    // Valid files, unsupported or inconsistent content.
    let variant = |m: &ColmapModel| -> String {
        write_bin(&mdir, m, 0);
        let e = err_of(dir.path());
        write_bin(&mdir, &model, 2);
        e
    };
    // A rational lens whose denominator folds it inside the photo (r / (1 − 2 r²) has no
    // inverse past r = 1/√2, the photo's corners reach r = √2).
    let mut rational = model.clone();
    rational.cameras[0].model = "FULL_OPENCV".into();
    rational.cameras[0].params = vec![50.0, 50.0, 50.0, 50.0, 0.0, 0.0, 0.0, 0.0, 0.0, -2.0, 0.0, 0.0];
    let e = variant(&rational);
    assert!(e.contains("images.bin") && e.contains("].k1`") && e.contains("folds over") && e.contains("k4 -2"), "{e}");
    let mut orphan = model.clone();
    orphan.images[3].camera_id = 8;
    let e = variant(&orphan);
    assert!(e.contains("images.bin") && e.contains("image 4 (`view_004.png`): camera 8 is not in"), "{e}");
    let mut nan = model.clone();
    nan.images[5].tvec[1] = f64::NAN;
    let e = variant(&nan);
    assert!(e.contains("images.bin") && e.contains("image 6 (`view_006.png`): invalid pose"), "{e}");
    let mut zero_q = model.clone();
    zero_q.images[0].qvec = [0.0; 4];
    assert!(variant(&zero_q).contains("image 1 (`view_001.png`): invalid pose"));
    let e = variant(&ColmapModel { images: vec![], ..model.clone() });
    assert!(e.contains("images.bin") && e.contains("no registered images"), "{e}");

    // Text: a bad number names its line; a wrong parameter count names the camera.
    std::fs::remove_dir_all(&mdir).unwrap();
    write_txt(&mdir, &model);
    let text = std::fs::read_to_string(mdir.join("images.txt")).unwrap();
    std::fs::write(mdir.join("images.txt"), text.replacen(" 7 view_003.png", " seven view_003.png", 1)).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("images.txt") && e.contains("`seven` is not a number"), "{e}");
    // One line per image (no points lines): an error, not every other image lost.
    let one_line: String = text.lines().filter(|l| l.starts_with('#') || l.ends_with(".png")).map(|l| format!("{l}\n")).collect();
    std::fs::write(mdir.join("images.txt"), one_line).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("images.txt") && e.contains("line 5: expected image 1's 2-D points"), "{e}");
    // Names may hold spaces; fields may be separated by several.
    let spaced = text.replacen("view_001.png", "view 001.png", 1).replacen(" 7 view_002.png", "   7   view_002.png", 1);
    std::fs::write(mdir.join("images.txt"), spaced).unwrap();
    std::fs::rename(dir.path().join("images/view_001.png"), dir.path().join("images/view 001.png")).unwrap();
    let names: Vec<String> = colmap::read_model(&mdir).unwrap().images.iter().take(2).map(|i| i.name.clone()).collect();
    assert_eq!(names, ["view 001.png", "view_002.png"]);
    assert_eq!(load(dir.path(), Split::Train).n_views(), model.images.len() - model.images.len().div_ceil(8));
    std::fs::rename(dir.path().join("images/view 001.png"), dir.path().join("images/view_001.png")).unwrap();
    std::fs::write(mdir.join("images.txt"), &text).unwrap();
    std::fs::write(mdir.join("cameras.txt"), "7 PINHOLE 100 100 50 50 50\n").unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("cameras.txt") && e.contains("line 1: camera 7: PINHOLE takes 4 parameters, got 3"), "{e}");
    write_txt(&mdir, &model);

    // A missing image names the image file.
    std::fs::remove_file(dir.path().join("images/view_010.png")).unwrap();
    let e = err_of(dir.path());
    assert!(e.contains("view_010.png") && e.contains("not found"), "{e}");
    assert!(matches!(load_scene(dir.path(), Split::Train, &LoadOptions::default()), Err(DataError::MissingImage { .. })));
}

/// `points3D.bin` as COLMAP writes it: per point id, `X Y Z`, colour, error, track.
fn write_points_bin(dir: &Path, points: &[colmap::ColmapPoint]) {
    let mut b = (points.len() as u64).to_le_bytes().to_vec();
    for (k, p) in points.iter().enumerate() {
        b.extend((k as u64 + 1).to_le_bytes());
        p.xyz.iter().for_each(|v| b.extend(v.to_le_bytes()));
        b.extend([200u8, 100, 50]);
        b.extend(p.error.to_le_bytes());
        b.extend((p.images.len() as u64).to_le_bytes());
        for (j, im) in p.images.iter().enumerate() {
            b.extend((*im as i32).to_le_bytes());
            b.extend((j as i32).to_le_bytes());
        }
    }
    std::fs::write(dir.join("points3D.bin"), b).unwrap();
}

/// `points3D.txt` as COLMAP writes it.
fn write_points_txt(dir: &Path, points: &[colmap::ColmapPoint]) {
    let mut s = String::from("# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
    for (k, p) in points.iter().enumerate() {
        let track: Vec<String> = p.images.iter().enumerate().map(|(j, im)| format!("{im} {j}")).collect();
        s += &format!("{} {:?} {:?} {:?} 200 100 50 {:?} {}\n", k + 1, p.xyz[0], p.xyz[1], p.xyz[2], p.error, track.join(" "));
    }
    std::fs::write(dir.join("points3D.txt"), s).unwrap();
}

/// `sfm_depth`: the reconstruction's points become sparse depth maps. Each training view's map
/// holds, at the pixel each point it observes projects to (computed here in COLMAP's own camera
/// model), the distance along that pixel's ray in the loaded scene's units; points with a large
/// reprojection error or a single observation give none. Binary and text agree.
#[test]
fn sfm_points_give_sparse_depth_maps() {
    let sim = arbitrary_frame();
    let dir = tempfile::tempdir().unwrap();
    let model = lego_model(dir.path(), &sim);
    let mdir = dir.path().join("sparse/0");
    write_bin(&mdir, &model, 0);
    let f = model.cameras[0].params[0];
    // COLMAP's pixel coordinates of a point in an image.
    let uv = |im: &ColmapImage, x: DVec3| -> (f64, f64, f64) {
        let r = colmap::rotation(im.qvec);
        let xc: [f64; 3] = std::array::from_fn(|i| (0..3).map(|k| r[i][k] * x[k]).sum::<f64>() + im.tvec[i]);
        (f * xc[0] / xc[2] + 50.0, f * xc[1] / xc[2] + 50.0, xc[2])
    };
    let project = |im: &ColmapImage, x: DVec3| -> Option<(u32, u32, f64)> {
        let (u, v, z) = uv(im, x);
        let xc = [0.0, 0.0, z];
        (xc[2] > 0.0 && (0.0..100.0).contains(&u) && (0.0..100.0).contains(&v)).then(|| {
            let (col, row) = (u.floor(), v.floor());
            let (px, py) = ((col + 0.5 - 50.0) / f, (row + 0.5 - 50.0) / f);
            (col as u32, row as u32, xc[2] * (px * px + py * py + 1.0).sqrt())
        })
    };
    let mut state = 0x9e37_79b9u64;
    let mut rnd = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    // Points that land within 10⁻³ px of a pixel's edge in some image are left out: the loader's
    // f32 cameras may put them in the neighbouring pixel.
    let on_edge = |x: DVec3| {
        model.images.iter().any(|im| {
            let (u, v, _) = uv(im, x);
            [u, v].iter().any(|c| (c - c.round()).abs() < 1e-3)
        })
    };
    let points: Vec<colmap::ColmapPoint> = (0..600)
        .map(|_| sim.apply(DVec3::new(rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0, rnd() * 2.0 - 1.0)))
        .filter(|&x| !on_edge(x))
        .enumerate()
        .map(|(k, x)| {
            let mut images: Vec<u32> = model.images.iter().filter(|im| project(im, x).is_some()).map(|im| im.id).collect();
            if k % 7 == 0 {
                images.truncate(1); // seen once: no depth
            }
            colmap::ColmapPoint { xyz: x.to_array(), error: if k % 10 == 0 { 3.0 } else { 0.4 }, images }
        })
        .collect();
    let opts = LoadOptions { sfm_depth: true, ..LoadOptions::default() };
    write_points_bin(&mdir, &points);
    assert_eq!(colmap::read_points(&mdir).unwrap().as_ref(), Some(&points));
    let train = load_scene(dir.path(), Split::Train, &opts).unwrap();
    let scale = train.normalization.unwrap().scale;
    let maps = train.depths.as_ref().expect("sparse depth maps");
    // The expected maps, in COLMAP's camera model (nearest point per pixel).
    let mut sorted: Vec<&ColmapImage> = model.images.iter().collect();
    sorted.sort_by(|a, b| a.name.cmp(&b.name));
    let train_images: Vec<&ColmapImage> = sorted.iter().enumerate().filter(|(i, _)| i % 8 != 0).map(|(_, im)| *im).collect();
    let mut measured = 0;
    for (v, im) in train_images.iter().enumerate() {
        let mut want = vec![0.0f64; 100 * 100];
        for p in points.iter().filter(|p| p.error <= 2.5 && p.images.len() >= 2 && p.images.contains(&im.id)) {
            let (c, r, t) = project(im, DVec3::from_array(p.xyz)).unwrap();
            let w = &mut want[(r * 100 + c) as usize];
            if *w == 0.0 || t * scale < *w {
                *w = t * scale;
            }
        }
        for (p, (&got, &w)) in maps[v].iter().zip(&want).enumerate() {
            assert!((got as f64 - w).abs() <= 1e-4 * w.max(1e-3), "{}: pixel {p}: {got} against {w}", im.name);
            measured += (w > 0.0) as usize;
        }
    }
    assert!(measured > 1000, "{measured} measured pixels");
    // The text model gives the same maps; without `sfm_depth`, or without points, none.
    std::fs::remove_file(mdir.join("points3D.bin")).unwrap();
    write_points_txt(&mdir, &points);
    assert_eq!(load_scene(dir.path(), Split::Train, &opts).unwrap().depths.as_ref(), Some(maps));
    assert!(load_scene(dir.path(), Split::Train, &LoadOptions::default()).unwrap().depths.is_none());
    std::fs::remove_file(mdir.join("points3D.txt")).unwrap();
    assert!(load_scene(dir.path(), Split::Train, &opts).unwrap().depths.is_none());
    // A broken points file is named.
    std::fs::write(mdir.join("points3D.bin"), [1u8, 0, 0]).unwrap();
    let e = load_scene(dir.path(), Split::Train, &opts).unwrap_err().to_string();
    assert!(e.contains("points3D.bin") && e.contains("truncated"), "{e}");
}
