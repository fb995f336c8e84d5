//! Human3.6M cameras from the published parameters (when ../shared/data is present): a skeleton projected
//! by the reader's cameras lands on the pixels computed from the raw file in its own tool-chain form within
//! the stated bound, cameras sit above the floor around the capture area, and bad files are named.
use std::path::{Path, PathBuf};

use mvmp_data::h36m::{CAMERAS, TEST_SUBJECTS, TRAIN_SUBJECTS, read_cameras};
use nalgebra::Vector3;
use serde_json::Value;

fn shared(rel: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(rel);
    p.exists().then_some(p)
}

/// The Human3.6M tool-chain's projection (radial + its tangential form) from the raw file's numbers, mm.
fn raw_project(f: &Value, subject: &str, cam: &str, x: [f64; 3]) -> [f64; 2] {
    let g = |v: &Value| v.as_f64().unwrap();
    let e = &f["extrinsics"][subject][cam];
    let i = &f["intrinsics"][cam];
    let p: Vec<f64> = (0..3)
        .map(|r| (0..3).map(|c| g(&e["R"][r][c]) * x[c]).sum::<f64>() + g(&e["t"][r][0]))
        .collect();
    let (xn, yn) = (p[0] / p[2], p[1] / p[2]);
    let d: Vec<f64> = i["distortion"].as_array().unwrap().iter().map(g).collect();
    let r2 = xn * xn + yn * yn;
    let radial = 1.0 + d[0] * r2 + d[1] * r2 * r2 + d[4] * r2 * r2 * r2;
    // tan = p1 y + p2 x; x_d = x (radial + tan) + p2 r^2; y_d = y (radial + tan) + p1 r^2.
    let tan = d[2] * yn + d[3] * xn;
    let xd = xn * (radial + tan) + d[3] * r2;
    let yd = yn * (radial + tan) + d[2] * r2;
    let k = |r: usize, c: usize| g(&i["calibration_matrix"][r][c]);
    [k(0, 0) * xd + k(0, 2), k(1, 1) * yd + k(1, 2)]
}

#[test]
fn published_cameras_match_the_raw_numbers_within_the_stated_bound() {
    let Some(path) = shared("h36m/karfly_camera-parameters.json") else {
        eprintln!("../shared/data not present: skipped");
        return;
    };
    let raw: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let mut worst: f64 = 0.0;
    for subject in TRAIN_SUBJECTS.iter().chain(&TEST_SUBJECTS) {
        let rig = read_cameras(&path, subject).unwrap();
        assert_eq!(rig.len(), 4);
        for (cam, id) in rig.cameras.iter().zip(CAMERAS) {
            // Cameras stand around the capture area, 1.3-1.8 m above the floor (z up, metres).
            let c = cam.centre();
            assert!(c.z > 1.2 && c.z < 2.0, "{subject}/{id}: centre {c:?}");
            assert!(c.x.hypot(c.y) > 3.0, "{subject}/{id}: centre {c:?}");
            // A grid of points standing in the middle of the room (mm), projected both ways.
            for gx in -4..=4 {
                for gz in 0..=8 {
                    let x = [gx as f64 * 300.0, 500.0, gz as f64 * 230.0];
                    let want = raw_project(&raw, subject, id, x);
                    let (got, depth) = cam.project(&(Vector3::new(x[0], x[1], x[2]) / 1000.0));
                    assert!(depth > 0.0);
                    if cam.contains(got) {
                        let e = (got.x - want[0]).hypot(got.y - want[1]);
                        worst = worst.max(e);
                    }
                }
            }
        }
    }
    // The two tangential forms differ by less than half a pixel (the module's statement: 0.49 px).
    assert!(worst < 0.5, "worst difference {worst} px");
    assert!(worst > 1e-3, "the forms do differ: {worst} px");
}

#[test]
fn bad_camera_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("cams.json");
    std::fs::write(&p, r#"{"intrinsics": {}, "extrinsics": {"S1": {}}}"#).unwrap();
    let e = read_cameras(&p, "S2").unwrap_err().to_string();
    assert!(e.contains("cams.json") && e.contains("S2"), "{e}");
    let e = read_cameras(&p, "S1").unwrap_err().to_string();
    assert!(e.contains("54138969") && e.contains("intrinsics"), "{e}");
    std::fs::write(&p, "{").unwrap();
    let e = read_cameras(&p, "S1").unwrap_err().to_string();
    assert!(e.contains("not a Human3.6M"), "{e}");
}

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/h36m")
        .join(name)
}

/// Joint `j` of frame `f` in the fixtures (scripts/h36m_cdf_fixtures.py), millimetres.
fn fixture_joint(f: usize, j: usize) -> [f64; 3] {
    let (f, j) = (f as f64, j as f64);
    [
        1000.0 + 10.0 * j + 5.0 * f,
        -400.0 + 20.0 * (j % 3.0),
        900.0 - 25.0 * j + f,
    ]
}

#[test]
fn pose_files_written_by_cdflib_read_in_every_layout() {
    // One record of [frames, 96] as float and as GZIP-compressed double, column-major, one record per
    // frame as an rVariable: all the same 5 frames, in metres.
    for name in [
        "pose_float_one_record.cdf",
        "pose_double_gzip.cdf",
        "pose_double_column_major.cdf",
        "pose_double_rvariable.cdf",
    ] {
        let poses = mvmp_data::h36m::read_poses(&fixture(name)).unwrap();
        assert_eq!(poses.len(), 5, "{name}");
        for (f, pose) in poses.iter().enumerate() {
            for (j, p) in pose.iter().enumerate() {
                let want = fixture_joint(f, j);
                for a in 0..3 {
                    assert!(
                        (p[a] - want[a] / 1000.0).abs() < 1e-9,
                        "{name}: frame {f} joint {j}: {p:?} vs {want:?} mm"
                    );
                }
            }
        }
    }
}

#[test]
fn damaged_pose_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(fixture("pose_float_one_record.cdf")).unwrap();
    let cut = dir.path().join("Walking.cdf");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let e = mvmp_data::h36m::read_poses(&cut).unwrap_err().to_string();
    assert!(e.contains("Walking.cdf"), "{e}");
    let junk = dir.path().join("Eating.cdf");
    std::fs::write(&junk, b"not a cdf file at all").unwrap();
    let e = mvmp_data::h36m::read_poses(&junk).unwrap_err().to_string();
    assert!(e.contains("Eating.cdf") && e.contains("CDF"), "{e}");
    let e = mvmp_data::h36m::read_poses(&dir.path().join("Posing.cdf"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("Posing.cdf"), "{e}");
    // Records of [5, 0] values (the zVDR's second dimension, bytes 752-755, big-endian), and a NaN
    // written over the first pose value.
    for (name, at, patch) in [
        ("Zero.cdf", 752, 0i32.to_be_bytes()),
        ("Nan.cdf", 780, [0xff; 4]),
    ] {
        let mut b = bytes.clone();
        b[at..at + 4].copy_from_slice(&patch);
        let path = dir.path().join(name);
        std::fs::write(&path, b).unwrap();
        let e = mvmp_data::h36m::read_poses(&path).unwrap_err().to_string();
        assert!(e.contains(name) && e.contains("Pose"), "{e}");
    }
}

/// A camera-parameters.json in the published layout with made-up cameras (scripts/h36m_cdf_fixtures.py):
/// four cameras on a 4 m circle looking at the centre of the room from 1.5 m, for subjects S9 and S11.
fn camera_parameters() -> Value {
    serde_json::from_str(&std::fs::read_to_string(fixture("camera-parameters.json")).unwrap())
        .unwrap()
}

/// A tree: S9 with "Directions 1" (float file) and "Walking" (compressed double), S11 with the excluded
/// "Directions" and "Sitting 1"; images of every frame for cameras 54138969 and 55011271 of
/// "Directions 1", and none elsewhere.
fn tree(root: &Path) {
    std::fs::write(
        mvmp_data::h36m::camera_file(root),
        camera_parameters().to_string(),
    )
    .unwrap();
    for (s, a, f) in [
        ("S9", "Directions 1", "pose_float_one_record.cdf"),
        ("S9", "Walking", "pose_double_gzip.cdf"),
        ("S11", "Directions", "pose_double_rvariable.cdf"),
        ("S11", "Sitting 1", "pose_double_column_major.cdf"),
    ] {
        let p = mvmp_data::h36m::pose_file(root, s, a);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::copy(fixture(f), p).unwrap();
    }
    // A black JPEG of each camera's own size (`data check` reads the headers).
    let seq =
        mvmp_data::h36m::H36mSequence::open(root, "S9", "Directions 1", &CAMERAS[..2], 1).unwrap();
    for (cam, c) in CAMERAS[..2].iter().zip(&seq.rig.cameras) {
        let mut jpeg = Vec::new();
        image::RgbImage::new(c.width, c.height)
            .write_to(
                &mut std::io::Cursor::new(&mut jpeg),
                image::ImageFormat::Jpeg,
            )
            .unwrap();
        for row in 0..5 {
            let p = mvmp_data::h36m::image_file(root, "S9", "Directions 1", cam, row);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, &jpeg).unwrap();
        }
    }
}

/// Images that are there but are not a view of their camera (not an image, another size) are named
/// per camera, the first and the count, like missing ones.
#[test]
fn unreadable_images_are_named_with_their_camera() {
    use mvmp_data::h36m::{check_tree, image_file};
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    tree(root);
    let (a, b) = (CAMERAS[0], CAMERAS[1]);
    for row in [1, 3] {
        std::fs::write(image_file(root, "S9", "Directions 1", a, row), b"text").unwrap();
    }
    let mut small = Vec::new();
    image::RgbImage::new(8, 8)
        .write_to(
            &mut std::io::Cursor::new(&mut small),
            image::ImageFormat::Png,
        )
        .unwrap();
    std::fs::write(image_file(root, "S9", "Directions 1", b, 4), small).unwrap();
    let report = check_tree(root, &CAMERAS[..2]);
    assert_eq!(report.sequences[0].4, 2, "{:?}", report.sequences);
    let find = |cam: &str, row: usize| {
        let p = image_file(root, "S9", "Directions 1", cam, row);
        report.problems.iter().find(|q| q.path == p).cloned()
    };
    let bad = find(a, 1).expect("the first unreadable image of the first camera");
    assert!(
        bad.what.contains("2 of the 5") && bad.what.contains(a),
        "{}",
        bad.what
    );
    let sized = find(b, 4).expect("the image of another size");
    assert!(
        sized.what.contains("8 x 8") && sized.what.contains("1 of the 5"),
        "{}",
        sized.what
    );
    assert_eq!(report.problems.len(), 4 + 2, "{:?}", report.problems);
}

#[test]
fn a_tree_reads_in_place_with_units_axes_and_joint_order() {
    use mvmp_data::h36m::{H36mSequence, actions, check_tree};
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    tree(root);
    assert_eq!(actions(root, "S9").unwrap(), ["Directions 1", "Walking"]);
    // S11's damaged "Directions" is left out.
    assert_eq!(actions(root, "S11").unwrap(), ["Sitting 1"]);
    let seq = H36mSequence::open(root, "S9", "Directions 1", &CAMERAS[..2], 2).unwrap();
    assert_eq!(seq.name(), "S9/Directions 1");
    assert_eq!(seq.rig.len(), 2);
    assert_eq!(
        seq.frames.iter().map(|f| f.row).collect::<Vec<_>>(),
        [0, 2, 4]
    );
    assert_eq!(
        seq.frames[1].images[1],
        root.join("S9/Images/Directions 1.55011271/000003.jpg")
    );
    // Metres, the file's own z-up axes, and the 17 joints in their order: pelvis is joint 0 of the 32,
    // the right hip 1, the left hip 6, the thorax 13, the head 15, the right wrist 27.
    let j = &seq.joints[1]; // row 2
    let close = |p: [f64; 3], q: [f64; 3]| (0..3).all(|a| (p[a] - q[a]).abs() < 1e-9);
    assert!(close(j[0], [1.01, -0.4, 0.902]), "{:?}", j[0]);
    assert!(close(j[1], [1.02, -0.38, 0.877]), "{:?}", j[1]);
    assert!(close(j[4], [1.07, -0.4, 0.752]), "{:?}", j[4]);
    assert!(close(j[8], [1.14, -0.38, 0.577]), "{:?}", j[8]);
    assert!(close(j[10], [1.16, -0.4, 0.527]), "{:?}", j[10]);
    assert!(close(j[16], [1.28, -0.4, 0.227]), "{:?}", j[16]);
    // The subject's cameras in metres: 4 m from the room's centre, 1.5 m up.
    let c = seq.rig.cameras[0].centre();
    assert!((c.z - 1.5).abs() < 1e-9 && (c.x.hypot(c.y) - 4.0).abs() < 1e-9);

    let report = check_tree(root, &CAMERAS[..2]);
    let seqs: Vec<(String, String, usize, usize, usize)> = report.sequences.clone();
    assert_eq!(
        seqs,
        [
            ("S9".into(), "Directions 1".into(), 2, 5, 5),
            ("S9".into(), "Walking".into(), 2, 5, 0),
            ("S11".into(), "Sitting 1".into(), 2, 5, 0),
        ]
    );
    // One problem per camera directory without images, naming its first frame.
    assert_eq!(report.problems.len(), 4, "{:?}", report.problems);
    assert!(report.problems.iter().any(|p| {
        p.path.ends_with("S11/Images/Sitting 1.55011271/000001.jpg")
            && p.what.contains("5 of the 5")
    }));
}

#[test]
fn broken_trees_name_the_file_and_the_key() {
    use mvmp_data::h36m::{H36mSequence, camera_file};
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    tree(root);
    // A camera that the split names but the rig does not have.
    let e = H36mSequence::open(root, "S9", "Walking", &["54138969", "12345678"], 1)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("12345678") && e.contains("camera-parameters.json"),
        "{e}"
    );
    // A subject without extrinsics.
    let e = H36mSequence::open(root, "S5", "Walking", &CAMERAS, 1)
        .unwrap_err()
        .to_string();
    assert!(e.contains("\"S5\"") && e.contains("extrinsics"), "{e}");
    // An action without a pose file.
    let e = H36mSequence::open(root, "S9", "Eating", &CAMERAS, 1)
        .unwrap_err()
        .to_string();
    assert!(e.contains("D3_Positions/Eating.cdf"), "{e}");
    // A camera file that lost a key.
    let mut cams = camera_parameters();
    cams["intrinsics"]
        .as_object_mut()
        .unwrap()
        .remove("58860488");
    std::fs::write(camera_file(root), cams.to_string()).unwrap();
    let e = H36mSequence::open(root, "S9", "Walking", &CAMERAS, 1)
        .unwrap_err()
        .to_string();
    assert!(e.contains("58860488") && e.contains("intrinsics"), "{e}");
    std::fs::remove_file(camera_file(root)).unwrap();
    let e = H36mSequence::open(root, "S9", "Walking", &CAMERAS, 1)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("camera-parameters.json") && e.contains("missing"),
        "{e}"
    );
}
