//! Projection + fusion at paper scale: a 300 x 300 x 20 grid (30 x 30 x 2 m at 0.1 m), 5 views of
//! 1920 x 1080 letterboxed to 1288 x 1288, 92 x 92 feature maps (stride 14), 32 channels; CPU flex backend.
//! Run: `cargo bench --bench fusion`. Targets (DESIGN.md): sampling + fusion from cached grids <= 140 ms.
use burn::tensor::{Device, Tensor, TensorData};
use criterion::{Criterion, criterion_group, criterion_main};
use mvmp::fusion::{FusionMode, SamplingGrid, fuse_views};
use mvmp::geom::{Camera, Letterbox, VoxelGrid};
use nalgebra::{Matrix3, Vector3};

fn rig() -> Vec<Camera> {
    (0..5)
        .map(|i| {
            let a = i as f64 / 5.0 * std::f64::consts::TAU;
            let pos = Vector3::new(22.0 * a.cos(), 22.0 * a.sin(), 6.0);
            let z = (Vector3::new(0.0, 0.0, 1.0) - pos).normalize();
            let x = z.cross(&Vector3::z()).normalize();
            let y = z.cross(&x);
            let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
            let k = Matrix3::new(1100.0, 0.0, 959.5, 0.0, 1100.0, 539.5, 0.0, 0.0, 1.0);
            Camera::new(
                format!("{i}"),
                k,
                r,
                -(r * pos),
                [-0.1, 0.02, 0.0, 0.0, 0.0],
                1920,
                1080,
            )
            .unwrap()
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let d = Device::flex();
    let grid = VoxelGrid::new([0.0, 0.0, 1.0], [30.0, 30.0, 2.0], [300, 300, 20]).unwrap();
    let cams = rig();
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|_| Letterbox::new(1920, 1080, 1288).unwrap())
        .collect();
    let mut g = c.benchmark_group("fusion_paper_scale");
    g.sample_size(10);
    g.bench_function("sampling_grid_5_views", |b| {
        b.iter(|| {
            SamplingGrid::new(&grid, &cams, &lbs, 14.0, [92, 92], &d)
                .visible
                .dims()[1]
        })
    });
    let sg = SamplingGrid::new(&grid, &cams, &lbs, 14.0, [92, 92], &d);
    let maps: Vec<f32> = (0..5 * 32 * 92 * 92)
        .map(|i| ((i % 97) as f32) / 97.0)
        .collect();
    let maps = Tensor::<5>::from_data(TensorData::new(maps, [1, 5, 32, 92, 92]), &d);
    g.bench_function("sample_and_mean_fuse_32ch", |b| {
        b.iter(|| {
            fuse_views(maps.clone(), std::slice::from_ref(&sg), FusionMode::Mean)
                .narrow(2, 0, 1)
                .sum()
                .into_scalar::<f32>()
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
