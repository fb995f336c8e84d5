//! Procrustes, the voxel grid and the rig file.
use mvmp_geom::rotation::axis_angle_to_matrix_f64;
use mvmp_geom::{Camera, GeomError, Rig, VoxelGrid, similarity_procrustes};
use nalgebra::{Matrix3, Vector3};

fn cloud() -> Vec<Vector3<f64>> {
    (0..30)
        .map(|i| {
            let t = i as f64;
            Vector3::new(
                (t * 0.9).sin(),
                (t * 1.7).cos() * 0.5,
                (t * 0.3).sin() * 2.0,
            )
        })
        .collect()
}

#[test]
fn procrustes_recovers_a_planted_similarity() {
    let src = cloud();
    let r = axis_angle_to_matrix_f64(Vector3::new(0.4, -1.2, 2.0));
    let (s, t) = (1.7, Vector3::new(3.0, -2.0, 0.5));
    let dst: Vec<_> = src.iter().map(|p| s * (r * p) + t).collect();
    let sim = similarity_procrustes(&src, &dst).unwrap();
    assert!((sim.scale - s).abs() < 1e-10);
    assert!((sim.rotation - r).abs().max() < 1e-10);
    assert!((sim.translation - t).norm() < 1e-10);
}

#[test]
fn procrustes_never_returns_a_reflection() {
    let src = cloud();
    // The best orthogonal map to a mirrored cloud is a reflection; the result must stay a rotation.
    let mirror = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
    let dst: Vec<_> = src.iter().map(|p| mirror * p).collect();
    let sim = similarity_procrustes(&src, &dst).unwrap();
    assert!((sim.rotation.determinant() - 1.0).abs() < 1e-10);
    assert!(
        (sim.rotation.transpose() * sim.rotation - Matrix3::identity())
            .abs()
            .max()
            < 1e-10
    );
    assert!(similarity_procrustes(&src[..2], &dst[..2]).is_err());
    assert!(similarity_procrustes(&src, &dst[..5]).is_err());
}

#[test]
fn paper_grid_has_exact_decimetre_voxels() {
    let g = VoxelGrid::new([0.0, 0.0, 1.0], [30.0, 30.0, 2.0], [300, 300, 20]).unwrap();
    assert_eq!(g.voxel_size(), [0.1, 0.1, 0.1]);
    // First and last voxel centres sit half a voxel inside the bounds.
    let first = g.index_to_world([0.0, 0.0, 0.0]);
    assert!((first[0] + 14.95).abs() < 1e-12 && (first[2] - 0.05).abs() < 1e-12);
    let last = g.index_to_world([299.0, 299.0, 19.0]);
    assert!((last[0] - 14.95).abs() < 1e-12 && (last[2] - 1.95).abs() < 1e-12);
    let idx = g.world_to_index([1.234, -5.678, 0.9]);
    let back = g.index_to_world(idx);
    assert!((back[0] - 1.234).abs() < 1e-12 && (back[1] + 5.678).abs() < 1e-12);
    let v = g.containing_voxel([0.01, 0.01, 0.01]).unwrap();
    assert_eq!(v, [150, 150, 0]);
    assert_eq!(g.unflatten(g.flat_index([12, 34, 5])), [12, 34, 5]);
    assert_eq!(g.flat_index([1, 0, 0]), 300 * 20);
    assert!(g.containing_voxel([16.0, 0.0, 1.0]).is_none());
    assert!(VoxelGrid::new([0.0; 3], [1.0, -1.0, 1.0], [2, 2, 2]).is_err());
    let centers = VoxelGrid::new([0.0; 3], [2.0; 3], [2, 3, 4])
        .unwrap()
        .centers();
    assert_eq!(centers.len(), 24);
    // Voxel (0, 0, 1) of a 2 x 3 x 4 grid over [-1, 1]^3: sizes 1, 2/3, 1/2.
    let want = [-0.5, -1.0 + 1.0 / 3.0, -1.0 + 0.75];
    assert!(
        centers[1]
            .iter()
            .zip(want)
            .all(|(a, b)| (a - b).abs() < 1e-12),
        "{:?}",
        centers[1]
    );
}

#[test]
fn rig_round_trip_and_errors() {
    let dir = tempfile::tempdir().unwrap();
    let k = Matrix3::new(1000.0, 0.5, 640.0, 0.0, 900.0, 360.0, 0.0, 0.0, 1.0);
    let r = axis_angle_to_matrix_f64(Vector3::new(0.1, 0.2, 0.3));
    let cams = vec![
        Camera::new(
            "a",
            k,
            r,
            Vector3::new(0.1, 0.2, 3.0),
            [0.1, -0.01, 1e-3, 2e-3, 0.0],
            1280,
            720,
        )
        .unwrap(),
        Camera::new(
            "b",
            k,
            Matrix3::identity(),
            Vector3::new(0.0, 0.0, 5.0),
            [0.0; 5],
            640,
            480,
        )
        .unwrap(),
    ];
    let rig = Rig::new(cams);
    let p = dir.path().join("cameras.json");
    rig.write(&p).unwrap();
    assert_eq!(Rig::read(&p).unwrap(), rig);

    // Units other than metres are converted.
    let text = rig
        .to_json_string()
        .replace("\"units\": \"m\"", "\"units\": \"mm\"");
    let mm = Rig::from_json_str(&text, &p).unwrap();
    assert!((mm.cameras[0].t - rig.cameras[0].t / 1000.0).norm() < 1e-15);

    let check = |text: String, needle: &str| {
        let e = Rig::from_json_str(&text, &p).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains("cameras.json") && msg.contains(needle),
            "{msg}"
        );
    };
    check(
        rig.to_json_string()
            .replace("\"units\": \"m\"", "\"units\": \"feet\""),
        "units",
    );
    check(
        rig.to_json_string()
            .replace("\"version\": 1", "\"version\": 7"),
        "version",
    );
    check(
        rig.to_json_string().replace("\"resolution\"", "\"res\""),
        "res",
    );
    check(
        rig.to_json_string().replacen("1000.0", "-1000.0", 1),
        "cameras[0]",
    );
    check("{ not json".into(), "not a valid rig file");
    // The same camera twice, by name or by pose, would count one view twice.
    check(
        rig.to_json_string()
            .replace("\"name\": \"b\"", "\"name\": \"a\""),
        "cameras[1] (\"a\") repeats cameras[0]",
    );
    let twice = Rig::new(vec![rig.cameras[0].clone(), rig.cameras[0].clone()]);
    check(
        twice
            .to_json_string()
            .replacen("\"name\": \"a\"", "\"name\": \"c\"", 1),
        "cameras[1] (\"a\") repeats cameras[0] (\"c\")",
    );
    // OpenCV's distortion vectors: four terms are k3 = 0; longer ones only with their extra terms zero.
    let dist =
        "[\n        0.1,\n        -0.01,\n        0.001,\n        0.002,\n        0.0\n      ]";
    let json = rig.to_json_string();
    assert!(json.contains(dist), "{json}");
    let four = json.replace(dist, "[0.1, -0.01, 0.001, 0.002]");
    assert_eq!(Rig::from_json_str(&four, &p).unwrap(), rig);
    let eight = json.replace(dist, "[0.1, -0.01, 0.001, 0.002, 0, 0, 0, 0]");
    assert_eq!(Rig::from_json_str(&eight, &p).unwrap(), rig);
    check(
        json.replace(dist, "[0.1, -0.01, 0.001, 0.002, 0, 0.5, 0, 0]"),
        "cameras[0] (\"a\"): `dist` term 5 is 0.5",
    );
    check(
        json.replace(dist, "[0.1, -0.01, 0.001]"),
        "`dist` has 3 values",
    );
    let e = Rig::read(&dir.path().join("missing.json")).unwrap_err();
    assert!(matches!(e, GeomError::Io { .. }) && e.to_string().contains("missing.json"));
}

/// A grid the float32 network could not place: centres and sides beyond `MAX_EXTENT` (1e300 is
/// finite in float64 and infinite in float32), as well as non-finite and non-positive ones.
#[test]
fn grids_beyond_float32_reach_are_refused() {
    let good = VoxelGrid {
        center: [0.0, 0.0, 1.0],
        size: [8.0, 8.0, 2.0],
        shape: [32, 32, 8],
    };
    assert!(good.validate().is_ok());
    for (center, size) in [
        ([1e300, 0.0, 1.0], [8.0, 8.0, 2.0]),
        ([0.0, -2e4, 1.0], [8.0, 8.0, 2.0]),
        ([0.0, 0.0, f64::NAN], [8.0, 8.0, 2.0]),
        ([0.0, 0.0, 1.0], [8.0, 1e300, 2.0]),
        ([0.0, 0.0, 1.0], [8.0, 8.0, 0.0]),
        ([0.0, 0.0, 1.0], [f64::INFINITY, 8.0, 2.0]),
    ] {
        let grid = VoxelGrid {
            center,
            size,
            ..good
        };
        let e = grid.validate().unwrap_err().to_string();
        assert!(e.contains("center") || e.contains("size"), "{e}");
    }
}
