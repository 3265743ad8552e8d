use super::*;
use proptest::prelude::*;

const CAMERAS_TXT: &str = "\
# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
# Number of cameras: 3
1 PINHOLE 640 480 500.5 501.25 320.5 240.5
2 SIMPLE_PINHOLE 320 240 250 160 120

3 SIMPLE_RADIAL 640 480 500 320 240 0.01
";

// Image 2 has an empty keypoint line; CRLF line ends must not matter.
const IMAGES_TXT: &str = "# Image list with two lines of data per image:\r
#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\r
1 1 0 0 0 0 0 0 1 left.png\r
100.5 200.25 7 300 400 -1\r
2 0.9999 0 0.0141 0 -0.2 0.01 0.03 2 right.png\r
\r
";

const POINTS_TXT: &str = "\
# 3D point list with one line of data per point:
7 0.1 0.2 3.5 255 128 0 0.42 1 0
8 -1 0.5 4 1 2 3 -1 1 1
";

use crate::error::field_of;

fn text_model() -> ColmapModel {
    ColmapModel {
        cameras: text::parse_cameras(CAMERAS_TXT, "cameras.txt").unwrap(),
        images: text::parse_images(IMAGES_TXT, "images.txt").unwrap(),
        points: text::parse_points3d(POINTS_TXT, "points3D.txt").unwrap(),
    }
}

fn write_text_dir(dir: &Path) {
    std::fs::write(dir.join("cameras.txt"), CAMERAS_TXT).unwrap();
    std::fs::write(dir.join("images.txt"), IMAGES_TXT).unwrap();
    std::fs::write(dir.join("points3D.txt"), POINTS_TXT).unwrap();
}

#[test]
fn hand_written_text_model_loads() {
    let tmp = tempfile::tempdir().unwrap();
    write_text_dir(tmp.path());
    assert_eq!(detect_format(tmp.path()).unwrap(), ModelFormat::Text);
    let m = read_colmap_dir(tmp.path()).unwrap();
    assert_eq!(m, text_model());
    assert_eq!((m.cameras.len(), m.images.len(), m.points.len()), (3, 2, 2));

    let left = m.image_by_name("left.png").unwrap();
    assert_eq!((left.id, left.camera_id), (1, 1));
    assert_eq!(left.pose, Pose::identity());
    assert_eq!(
        left.points2d,
        vec![
            Point2D {
                xy: [100.5, 200.25],
                point3d_id: Some(7)
            },
            Point2D {
                xy: [300.0, 400.0],
                point3d_id: None
            },
        ]
    );
    let right = m.image_by_name("right.png").unwrap();
    assert!(right.points2d.is_empty());
    assert_eq!(right.tvec, [-0.2, 0.01, 0.03]);
    right.pose.validate().unwrap();
    assert!(m.image_by_name("missing.png").is_none());

    // COLMAP's (0.5, 0.5) top-left pixel centre becomes murk's (0, 0).
    let k = m.intrinsics_of(left).unwrap();
    assert_eq!(k, Intrinsics::new(500.5, 501.25, 320.0, 240.0));
    let k2 = m.intrinsics_of(right).unwrap();
    assert_eq!(k2, Intrinsics::new(250.0, 250.0, 159.5, 119.5));

    let p7 = &m.points[&7];
    assert_eq!(
        (p7.xyz, p7.rgb, p7.error),
        ([0.1, 0.2, 3.5], [255, 128, 0], 0.42)
    );
    assert_eq!(
        p7.track,
        vec![TrackElement {
            image_id: 1,
            point2d_idx: 0
        }]
    );
    assert_eq!(m.points[&8].error, -1.0);
}

#[test]
fn unsupported_model_says_to_undistort() {
    let m = text_model();
    let e = m.cameras[&3].intrinsics().unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("SIMPLE_RADIAL") && msg.contains("image_undistorter"),
        "{msg}"
    );
    assert_eq!(field_of(e), "model");
    let mut im = m.images[&1].clone();
    im.camera_id = 3;
    assert_eq!(
        field_of(m.intrinsics_of(&im).unwrap_err()),
        "colmap.cameras[3].model"
    );
    let mut bad = m.cameras[&1].clone();
    bad.params[0] = -1.0;
    assert_eq!(field_of(bad.intrinsics().unwrap_err()), "params.fx");
}

#[test]
fn text_binary_text_round_trip_is_exact() {
    let original = text_model();
    let bin_dir = tempfile::tempdir().unwrap();
    write_colmap_binary(bin_dir.path(), &original).unwrap();
    assert_eq!(detect_format(bin_dir.path()).unwrap(), ModelFormat::Binary);
    let from_bin = read_colmap_dir(bin_dir.path()).unwrap();
    assert_eq!(from_bin, original);

    let txt_dir = tempfile::tempdir().unwrap();
    write_colmap_text(txt_dir.path(), &from_bin).unwrap();
    assert_eq!(read_colmap_dir(txt_dir.path()).unwrap(), original);

    // With both present, binary wins (COLMAP's order); text can still be asked for.
    write_colmap_text(bin_dir.path(), &original).unwrap();
    assert_eq!(detect_format(bin_dir.path()).unwrap(), ModelFormat::Binary);
    assert_eq!(
        read_colmap(bin_dir.path(), ModelFormat::Text).unwrap(),
        original
    );
}

#[test]
fn written_model_from_murk_types_round_trips() {
    let k = Intrinsics::new(300.0, 310.0, 127.5, 95.5);
    let cam = ColmapCamera::from_intrinsics(4, &k, 256, 192).unwrap();
    assert_eq!(cam.intrinsics().unwrap(), k);
    let skewed = Intrinsics { skew: 1.0, ..k };
    assert_eq!(
        field_of(ColmapCamera::from_intrinsics(4, &skewed, 256, 192).unwrap_err()),
        "skew"
    );
    let pose = Pose::from_colmap([0.8, 0.2, -0.1, 0.3], [0.1, -0.2, 0.3]).unwrap();
    let im = ColmapImage::new(9, 4, "view 009.png", &pose, vec![]).unwrap();
    let mut m = ColmapModel::default();
    m.cameras.insert(4, cam);
    m.images.insert(9, im);
    m.points.insert(
        1 << 40,
        Point3D {
            id: 1 << 40,
            xyz: [1e-20, -3.0, 1e5],
            rgb: [1, 2, 3],
            error: 0.125,
            track: vec![],
        },
    );
    let dir = tempfile::tempdir().unwrap();
    write_colmap_text(dir.path(), &m).unwrap();
    let back = read_colmap_dir(dir.path()).unwrap();
    assert_eq!(back, m);
    let p = &back.images[&9].pose;
    assert!((p.rotation() - pose.rotation()).amax() < 1e-12);
}

#[test]
fn truncated_binary_files_fail_without_panicking() {
    let m = text_model();
    let files: [(&str, Vec<u8>); 3] = [
        ("cameras", binary::encode_cameras(&m.cameras)),
        ("images", binary::encode_images(&m.images).unwrap()),
        ("points3D", binary::encode_points3d(&m.points)),
    ];
    for (name, bytes) in &files {
        for len in 0..bytes.len() {
            let cut = &bytes[..len];
            let res = match *name {
                "cameras" => binary::parse_cameras(cut, "cameras.bin").map(|_| ()),
                "images" => binary::parse_images(cut, "images.bin").map(|_| ()),
                _ => binary::parse_points3d(cut, "points3D.bin").map(|_| ()),
            };
            let e = res.expect_err("truncated file must not parse");
            let f = field_of(e);
            assert_eq!(f, format!("colmap.{name}"), "{name} cut at {len}");
        }
    }
    // Trailing garbage is corruption too.
    let mut long = files[0].1.clone();
    long.push(0);
    assert!(binary::parse_cameras(&long, "cameras.bin").is_err());
}

#[test]
fn absurd_counts_and_unknown_models_fail() {
    let mut b = u64::MAX.to_le_bytes().to_vec();
    b.extend([0u8; 64]);
    let msg = binary::parse_points3d(&b, "points3D.bin")
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("points3D.bin") && msg.contains("cannot fit"),
        "{msg}"
    );
    assert!(binary::parse_images(&b, "images.bin").is_err());
    assert!(binary::parse_cameras(&b, "cameras.bin").is_err());

    let mut cams = binary::encode_cameras(&text_model().cameras);
    cams[8 + 4] = 77; // first camera's model id
    let msg = binary::parse_cameras(&cams, "cameras.bin")
        .unwrap_err()
        .to_string();
    assert!(msg.contains("unknown camera model id 77"), "{msg}");
}

#[test]
fn malformed_text_names_file_and_line() {
    let e = text::parse_cameras("1 PINHOLE 640 480 1 2 3\n", "c.txt").unwrap_err();
    assert!(e.to_string().contains("c.txt:1"), "{e}");
    assert_eq!(field_of(e), "colmap.cameras");
    let e = text::parse_cameras("\n1 FISHEYE_X 640 480 1 2 3\n", "c.txt").unwrap_err();
    assert!(e.to_string().contains("c.txt:2") && e.to_string().contains("FISHEYE_X"));
    assert!(text::parse_cameras("1 PINHOLE 640 480 1 2 3 x\n", "c").is_err());
    assert!(
        text::parse_cameras("1 PINHOLE 640 480 1 2 3 4\n1 PINHOLE 1 1 1 1 1 1\n", "c").is_err()
    );

    let e = text::parse_images("1 1 0 0 0 0 0 0 1 a.png\n1 2\n", "i.txt").unwrap_err();
    assert!(e.to_string().contains("i.txt:2"), "{e}");
    assert_eq!(field_of(e), "colmap.images");
    let e = text::parse_images("1 0 0 0 0 0 0 0 1 a.png\n\n", "i.txt").unwrap_err();
    assert!(e.to_string().contains("qvec"), "{e}");
    assert!(text::parse_images("1 1 0 0 0 0 0 0 1\n\n", "i").is_err());
    // A missing keypoint line at the very end means no keypoints (as COLMAP's own reader).
    assert_eq!(
        text::parse_images("1 1 0 0 0 0 0 0 1 a b.png", "i").unwrap()[&1].name,
        "a b.png"
    );

    let e = text::parse_points3d("1 0 0 1 255 0 0 0.5 1\n", "p.txt").unwrap_err();
    assert_eq!(field_of(e), "colmap.points3D");
    assert!(text::parse_points3d("1 0 0 1 256 0 0 0.5\n", "p").is_err());
    assert!(text::parse_points3d("1 0 nan 1 25 0 0 0.5\n", "p").is_err());
}

#[test]
fn directory_errors() {
    let tmp = tempfile::tempdir().unwrap();
    assert_eq!(field_of(read_colmap_dir(tmp.path()).unwrap_err()), "colmap");
    write_text_dir(tmp.path());
    // A track naming a keypoint that does not exist.
    std::fs::write(tmp.path().join("points3D.txt"), "7 0 0 1 0 0 0 0 2 0\n").unwrap();
    assert_eq!(
        field_of(read_colmap_dir(tmp.path()).unwrap_err()),
        "colmap.points3D"
    );
    write_text_dir(tmp.path());
    std::fs::write(tmp.path().join("cameras.txt"), "1 PINHOLE 1 1 1 1 0 0\n").unwrap();
    assert_eq!(
        field_of(read_colmap_dir(tmp.path()).unwrap_err()),
        "colmap.images"
    );
    std::fs::write(tmp.path().join("cameras.txt"), [0xffu8, 0xfe, 0x00]).unwrap();
    assert_eq!(
        field_of(read_colmap_dir(tmp.path()).unwrap_err()),
        "colmap.cameras"
    );
}

proptest! {
    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..256)) {
        let _ = binary::parse_cameras(&bytes, "c");
        let _ = binary::parse_images(&bytes, "i");
        let _ = binary::parse_points3d(&bytes, "p");
        let s = String::from_utf8_lossy(&bytes);
        let _ = text::parse_cameras(&s, "c");
        let _ = text::parse_images(&s, "i");
        let _ = text::parse_points3d(&s, "p");
    }

    #[test]
    fn corrupted_binary_never_panics(pos in 0usize..400, val in any::<u8>()) {
        let m = text_model();
        for mut b in [
            binary::encode_cameras(&m.cameras),
            binary::encode_images(&m.images).unwrap(),
            binary::encode_points3d(&m.points),
        ] {
            let n = b.len();
            b[pos % n] = val;
            let _ = binary::parse_cameras(&b, "c");
            let _ = binary::parse_images(&b, "i");
            let _ = binary::parse_points3d(&b, "p");
        }
    }
}
