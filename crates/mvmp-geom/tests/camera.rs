//! Camera model, distortion, back-projection and the batched tensor projection.
use burn::tensor::{Device, Tensor, TensorData};
use mvmp_geom::{Camera, CameraTensors, GeomError, Letterbox};
use nalgebra::{Matrix3, Vector2, Vector3};

fn cam(dist: [f64; 5], skew: f64) -> Camera {
    let k = Matrix3::new(1000.0, skew, 640.0, 0.0, 900.0, 360.0, 0.0, 0.0, 1.0);
    Camera::new(
        "test",
        k,
        Matrix3::identity(),
        Vector3::zeros(),
        dist,
        1280,
        720,
    )
    .unwrap()
}

#[test]
fn pinhole_projection_by_hand() {
    let c = cam([0.0; 5], 0.0);
    // (0.2, -0.1, 2) -> normalised (0.1, -0.05) -> (1000*0.1 + 640, 900*-0.05 + 360).
    let (uv, z) = c.project(&Vector3::new(0.2, -0.1, 2.0));
    assert!((uv - Vector2::new(740.0, 315.0)).norm() < 1e-9);
    assert_eq!(z, 2.0);
}

#[test]
fn each_distortion_term_by_hand() {
    // Normalised point (x, y) = (0.1, 0.2): r2 = 0.05.
    let p = Vector3::new(0.1, 0.2, 1.0);
    let (x, y, r2): (f64, f64, f64) = (0.1, 0.2, 0.05);
    let cases: [([f64; 5], f64, f64); 5] = [
        // k1 = 0.1: both scaled by 1 + 0.1 r2.
        (
            [0.1, 0.0, 0.0, 0.0, 0.0],
            x * (1.0 + 0.1 * r2),
            y * (1.0 + 0.1 * r2),
        ),
        // k2 = 0.1: by 1 + 0.1 r2^2.
        (
            [0.0, 0.1, 0.0, 0.0, 0.0],
            x * (1.0 + 0.1 * r2 * r2),
            y * (1.0 + 0.1 * r2 * r2),
        ),
        // p1 = 0.01: x += 2 p1 x y, y += p1 (r2 + 2 y^2).
        (
            [0.0, 0.0, 0.01, 0.0, 0.0],
            x + 2.0 * 0.01 * x * y,
            y + 0.01 * (r2 + 2.0 * y * y),
        ),
        // p2 = 0.01: x += p2 (r2 + 2 x^2), y += 2 p2 x y.
        (
            [0.0, 0.0, 0.0, 0.01, 0.0],
            x + 0.01 * (r2 + 2.0 * x * x),
            y + 2.0 * 0.01 * x * y,
        ),
        // k3 = 0.1: by 1 + 0.1 r2^3.
        (
            [0.0, 0.0, 0.0, 0.0, 0.1],
            x * (1.0 + 0.1 * r2.powi(3)),
            y * (1.0 + 0.1 * r2.powi(3)),
        ),
    ];
    for (dist, xd, yd) in cases {
        let c = cam(dist, 0.0);
        let (uv, _) = c.project(&p);
        let want = Vector2::new(1000.0 * xd + 640.0, 900.0 * yd + 360.0);
        assert!((uv - want).norm() < 1e-9, "{dist:?}: {uv} vs {want}");
    }
    // Skew adds skew * yd to u.
    let c = cam([0.0; 5], 2.5);
    let (uv, _) = c.project(&p);
    assert!((uv.x - (1000.0 * x + 2.5 * y + 640.0)).abs() < 1e-9);
}

#[test]
fn back_projection_inverts_projection() {
    let k = Matrix3::new(1400.0, 0.67, 943.0, 0.0, 1394.6, 554.2, 0.0, 0.0, 1.0);
    let r = nalgebra::Rotation3::from_euler_angles(0.3, -0.5, 1.1).into_inner();
    let c = Camera::new(
        "c",
        k,
        r,
        Vector3::new(0.2, 1.2, 2.9),
        [-0.289, 0.193, -9.4e-5, 3.44e-4, -0.0578],
        1920,
        1080,
    )
    .unwrap();
    for uv in [
        Vector2::new(10.0, 20.0),
        Vector2::new(960.0, 540.0),
        Vector2::new(1900.0, 1070.0),
    ] {
        let (o, d) = c.back_project(uv).unwrap();
        let p = o + d * 4.0;
        let (uv2, z) = c.project(&p);
        assert!(z > 0.0);
        assert!((uv2 - uv).norm() < 1e-6, "{uv} -> {uv2}");
    }
}

#[test]
fn invalid_cameras_are_rejected() {
    let k = Matrix3::new(1000.0, 0.0, 640.0, 0.0, 900.0, 360.0, 0.0, 0.0, 1.0);
    let bad_r = Matrix3::new(1.0, 0.1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
    let e = Camera::new("a", k, bad_r, Vector3::zeros(), [0.0; 5], 10, 10).unwrap_err();
    assert!(matches!(e, GeomError::InvalidCamera { .. }) && e.to_string().contains("orthonormal"));
    let refl = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
    let e = Camera::new("b", k, refl, Vector3::zeros(), [0.0; 5], 10, 10).unwrap_err();
    assert!(e.to_string().contains("determinant"), "{e}");
    let mut k2 = k;
    k2[(1, 1)] = -5.0;
    let e = Camera::new(
        "c",
        k2,
        Matrix3::identity(),
        Vector3::zeros(),
        [0.0; 5],
        10,
        10,
    )
    .unwrap_err();
    assert!(e.to_string().contains("fy = -5"), "{e}");
    let e = Camera::new(
        "d",
        k,
        Matrix3::identity(),
        Vector3::new(f64::NAN, 0.0, 0.0),
        [0.0; 5],
        10,
        10,
    )
    .unwrap_err();
    assert!(e.to_string().contains("non-finite"), "{e}");
    let e = Camera::new(
        "e",
        k,
        Matrix3::identity(),
        Vector3::zeros(),
        [0.0; 5],
        0,
        10,
    )
    .unwrap_err();
    assert!(e.to_string().contains("image size"), "{e}");
    // Finite but absurd: a centre 1e30 m away (a unit mistake or a broken file), a lens coefficient of
    // 1e30. A centre 99 km away and k1 = -500 are still cameras.
    let at = |t: f64, k1: f64| {
        Camera::new(
            "f",
            k,
            Matrix3::identity(),
            Vector3::new(t, 0.0, 0.0),
            [k1, 0.0, 0.0, 0.0, 0.0],
            10,
            10,
        )
    };
    let e = at(1e30, 0.0).unwrap_err();
    assert!(e.to_string().contains("from the origin"), "{e}");
    let e = at(0.0, 1e30).unwrap_err();
    assert!(e.to_string().contains("dist"), "{e}");
    at(9.9e4, -500.0).unwrap();
    // A skew of -1e30 pixels once passed the reader and `infer` ran on it.
    let mut k3 = k;
    k3[(0, 1)] = -1e30;
    let e = Camera::new(
        "g",
        k3,
        Matrix3::identity(),
        Vector3::zeros(),
        [0.0; 5],
        10,
        10,
    )
    .unwrap_err();
    assert!(e.to_string().contains("K holds"), "{e}");
}

#[test]
fn tensor_projection_matches_f64_with_letterbox_and_visibility() {
    let device = Device::flex();
    let k = Matrix3::new(1400.0, 0.67, 943.0, 0.0, 1394.6, 554.2, 0.0, 0.0, 1.0);
    let cams: Vec<Camera> = (0..3)
        .map(|i| {
            let a = i as f64 * 2.0;
            let centre = Vector3::new(6.0 * a.sin(), -6.0 * a.cos(), 1.5);
            // Look at the origin: the optical axis points from the centre to it, image y points down.
            let z = (-centre).normalize();
            let x = z.cross(&Vector3::z()).normalize();
            let y = z.cross(&x);
            let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
            Camera::new(
                format!("c{i}"),
                k,
                r,
                -(r * centre),
                [-0.2, 0.1, 1e-3, -5e-4, 0.01],
                1920,
                1080,
            )
            .unwrap()
        })
        .collect();
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|_| Letterbox::new(1920, 1080, 518).unwrap())
        .collect();
    let pts: Vec<Vector3<f64>> = (0..40)
        .map(|i| {
            let t = i as f64;
            Vector3::new(
                (t * 0.37).sin() * 4.0,
                (t * 0.71).cos() * 4.0,
                (t * 0.13).sin() + 1.0,
            )
        })
        .collect();
    let flat: Vec<f32> = pts
        .iter()
        .flat_map(|p| [p.x as f32, p.y as f32, p.z as f32])
        .collect();
    let ct = CameraTensors::new(&cams, Some(&lbs), &device);
    let out = ct.project(Tensor::from_data(
        TensorData::new(flat, [pts.len(), 3]),
        &device,
    ));
    let uv: Vec<f32> = out.uv.into_data().try_into_vec().unwrap();
    let vis: Vec<bool> = out.visible.into_data().try_into_vec().unwrap();
    let mut seen = 0;
    for (ci, c) in cams.iter().enumerate() {
        for (pi, p) in pts.iter().enumerate() {
            let (px, z) = c.project(p);
            let want_vis = z > 1e-3 && c.contains(px) && {
                let n = c.to_camera(p);
                (n.x / n.z).abs() <= 4.0 && (n.y / n.z).abs() <= 4.0
            };
            let k = ci * pts.len() + pi;
            assert_eq!(vis[k], want_vis, "camera {ci} point {pi}");
            if want_vis {
                seen += 1;
                let want = lbs[ci].apply(px);
                let got = Vector2::new(uv[k * 2] as f64, uv[k * 2 + 1] as f64);
                // float32 arithmetic on coordinates of a few hundred pixels.
                assert!((got - want).norm() < 2e-3, "{got} vs {want}");
            }
        }
    }
    assert!(seen > 40, "the test rig should see most points, saw {seen}");
}

#[test]
fn letterbox_maps_corners_and_inverts() {
    let lb = Letterbox::new(1920, 1080, 512).unwrap();
    assert_eq!((lb.content_width, lb.content_height), (512, 288));
    assert_eq!((lb.offset_x, lb.offset_y), (0, 112));
    // The outer edges of the image map to the outer edges of the content.
    let tl = lb.apply(Vector2::new(-0.5, -0.5));
    assert!((tl - Vector2::new(-0.5, 111.5)).norm() < 1e-9);
    let br = lb.apply(Vector2::new(1919.5, 1079.5));
    assert!((br - Vector2::new(511.5, 399.5)).norm() < 1e-9);
    let p = Vector2::new(123.4, 987.6);
    assert!((lb.invert(lb.apply(p)) - p).norm() < 1e-9);
    assert!(Letterbox::new(0, 10, 10).is_err());
}
