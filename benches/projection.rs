//! Batched projection of a body's 10475 vertices into 31 cameras (the Panoptic HD rig size), with
//! distortion and the letterbox, on the CPU backend (flex). Run: `cargo bench --bench projection`.
use burn::tensor::{Device, Tensor, TensorData};
use criterion::{Criterion, criterion_group, criterion_main};
use mvmp::geom::{Camera, CameraTensors, Letterbox};
use nalgebra::{Matrix3, Vector3};

// The allocator of the `mvmp` binary, so that the figures are the binary's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn rig(n: usize) -> Vec<Camera> {
    (0..n)
        .map(|i| {
            let a = i as f64 / n as f64 * std::f64::consts::TAU;
            let centre = Vector3::new(5.0 * a.cos(), 5.0 * a.sin(), 1.0 + (i % 3) as f64);
            let z = (Vector3::new(0.0, 0.0, 1.0) - centre).normalize();
            let x = z.cross(&Vector3::z()).normalize();
            let y = z.cross(&x);
            let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
            let k = Matrix3::new(1400.0, 0.6, 960.0, 0.0, 1400.0, 540.0, 0.0, 0.0, 1.0);
            Camera::new(
                format!("{i}"),
                k,
                r,
                -(r * centre),
                [-0.25, 0.2, 1e-4, 3e-4, -0.05],
                1920,
                1080,
            )
            .unwrap()
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let device = Device::flex();
    let cams = rig(31);
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|_| Letterbox::new(1920, 1080, 518).unwrap())
        .collect();
    let ct = CameraTensors::new(&cams, Some(&lbs), &device);
    let pts: Vec<f32> = (0..10475 * 3)
        .map(|i| ((i as f32) * 0.013).sin() * 0.8 + if i % 3 == 2 { 1.0 } else { 0.0 })
        .collect();
    let pts = Tensor::<2>::from_data(TensorData::new(pts, [10475, 3]), &device);
    c.bench_function("project_10475_points_31_cameras", |b| {
        b.iter(|| {
            let p = ct.project(pts.clone());
            p.uv.sum().into_scalar::<f32>()
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
