//! The rasterizer against hand-derived images: a camera at the origin looking along +z with f = 100 px
//! and the principal point at (50, 50), so that a world point (x, y, z) lands on pixel
//! (50 + 100 x / z, 50 + 100 y / z).
use mvmp_geom::Camera;
use mvmp_render::{Frame, Light, MeshRef, coverage, draw};
use nalgebra::{Matrix3, Vector3};

const SIZE: u32 = 101;

fn camera() -> Camera {
    let k = Matrix3::new(100.0, 0.0, 50.0, 0.0, 100.0, 50.0, 0.0, 0.0, 1.0);
    Camera::new(
        "c",
        k,
        Matrix3::identity(),
        Vector3::zeros(),
        [0.0; 5],
        SIZE,
        SIZE,
    )
    .unwrap()
}

/// The square `[-h, h]^2` (two triangles) on the plane `z = z0 + slope * x`.
fn square(h: f32, z0: f32, slope: f32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let v = [[-h, -h], [h, -h], [h, h], [-h, h]]
        .map(|[x, y]| [x, y, z0 + slope * x])
        .to_vec();
    (v, vec![[0, 1, 2], [0, 2, 3]])
}

const LIGHT: Light = Light {
    dir: [0.0, 0.0, 1.0],
    ambient: 0.2,
    color: [1.0, 1.0, 1.0],
};

fn mesh<'a>(v: &'a [[f32; 3]], f: &'a [[u32; 3]], color: [f32; 3]) -> MeshRef<'a> {
    MeshRef {
        vertices: v,
        faces: f,
        color,
        face_colors: None,
    }
}

#[test]
fn a_square_facing_the_camera_covers_its_projection_at_its_depth() {
    // x, y in [-1, 1] at z = 4: pixels 25..=75 on both axes, 51 x 51 of them (edges count).
    let (v, f) = square(1.0, 4.0, 0.0);
    let mut frame = Frame::new(SIZE, SIZE, [0.0; 3]);
    draw(
        &mut frame,
        &camera(),
        &[mesh(&v, &f, [0.5, 0.25, 1.0])],
        &LIGHT,
    );
    let drawn: Vec<usize> = (0..frame.mesh.len())
        .filter(|&i| frame.mesh[i] == 0)
        .collect();
    assert_eq!(drawn.len(), 51 * 51);
    assert_eq!(coverage(&camera(), &v, &f, SIZE, SIZE), 51 * 51);
    for &i in &drawn {
        let (x, y) = (i % SIZE as usize, i / SIZE as usize);
        assert!(
            (25..=75).contains(&x) && (25..=75).contains(&y),
            "pixel ({x}, {y})"
        );
        assert!(
            (frame.depth[i] - 4.0).abs() < 1e-5,
            "depth {}",
            frame.depth[i]
        );
        // The light travels along the view: the lit side faces the camera, fully lit.
        assert_eq!(frame.rgb[i], [0.5, 0.25, 1.0]);
    }
    let outside = (0..frame.mesh.len()).find(|&i| frame.mesh[i] < 0).unwrap();
    assert_eq!(frame.depth[outside], f32::INFINITY);
    assert_eq!(frame.rgb[outside], [0.0; 3]);
}

#[test]
fn depth_on_a_slanted_plane_is_perspective_correct() {
    // On z = 4 + x / 2 the ray through column u meets the plane at z = 4 / (1 - (u - 50) / 200): not
    // the affine interpolation of the corners' depths.
    let (v, f) = square(1.0, 4.0, 0.5);
    let mut frame = Frame::new(SIZE, SIZE, [0.0; 3]);
    draw(&mut frame, &camera(), &[mesh(&v, &f, [1.0; 3])], &LIGHT);
    for u in [40usize, 50, 60, 65] {
        let want = 4.0 / (1.0 - (u as f32 - 50.0) / 200.0);
        let got = frame.depth[50 * SIZE as usize + u];
        assert!(
            (got - want).abs() < 1e-4,
            "column {u}: {got} against {want}"
        );
    }
}

#[test]
fn the_nearer_mesh_wins_whatever_the_drawing_order() {
    let (far_v, far_f) = square(1.0, 4.0, 0.0);
    let (near_v, near_f) = square(0.2, 2.0, 0.0);
    for near_first in [false, true] {
        let far = mesh(&far_v, &far_f, [1.0, 0.0, 0.0]);
        let near = mesh(&near_v, &near_f, [0.0, 1.0, 0.0]);
        let (meshes, near_index) = if near_first {
            (vec![near, far], 0)
        } else {
            (vec![far, near], 1)
        };
        let mut frame = Frame::new(SIZE, SIZE, [0.0; 3]);
        draw(&mut frame, &camera(), &meshes, &LIGHT);
        // The near square spans 50 +- 10 px; the far one 50 +- 25.
        let centre = 50 * SIZE as usize + 50;
        assert_eq!(frame.mesh[centre], near_index);
        assert!((frame.depth[centre] - 2.0).abs() < 1e-5);
        let ring = 50 * SIZE as usize + 70;
        assert_eq!(frame.mesh[ring], 1 - near_index);
        let near_pixels = frame.mesh.iter().filter(|&&m| m == near_index).count();
        assert_eq!(near_pixels, 21 * 21);
    }
}

#[test]
fn a_mesh_behind_the_camera_covers_nothing() {
    let (v, f) = square(1.0, -4.0, 0.0);
    let mut frame = Frame::new(SIZE, SIZE, [0.0; 3]);
    draw(&mut frame, &camera(), &[mesh(&v, &f, [1.0; 3])], &LIGHT);
    assert!(frame.mesh.iter().all(|&m| m < 0));
    assert_eq!(coverage(&camera(), &v, &f, SIZE, SIZE), 0);
}
