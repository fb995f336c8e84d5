//! SMPL-X forward on the CPU backend (flex), float32, stand-in model (SMPL-X sized: 10475 vertices).
//! Run: `cargo bench --bench smplx`. The project's target: batch 30 <= 10.8 ms on 2 cores.
//! `smplx_forward` is the inference forward (the fused CPU pass); `smplx_forward_tensor_ops` is the
//! differentiable tensor-op path that training takes, measured here without autodiff.
use burn::tensor::{Device, Tensor, TensorData};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use mvmp::smplx::{SmplxLayer, Translation, standin_model};

// The allocator of the `mvmp` binary, so that the figures are the binary's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn bench(c: &mut Criterion) {
    let device = Device::flex();
    let layer = SmplxLayer::new(&standin_model(0), &device);
    let mut group = c.benchmark_group("smplx_forward");
    group.sample_size(20);
    for batch in [1usize, 30, 256] {
        let pose: Vec<f32> = (0..batch * 165)
            .map(|i| ((i as f32) * 0.37).sin() * 0.3)
            .collect();
        let betas: Vec<f32> = (0..batch * 10).map(|i| ((i as f32) * 0.11).cos()).collect();
        let pose = Tensor::<3>::from_data(TensorData::new(pose, [batch, 55, 3]), &device);
        let betas = Tensor::<2>::from_data(TensorData::new(betas, [batch, 10]), &device);
        let expr = Tensor::<2>::zeros([batch, 10], &device);
        let transl = Tensor::<2>::zeros([batch, 3], &device);
        group.bench_with_input(BenchmarkId::from_parameter(batch), &batch, |b, _| {
            b.iter(|| {
                let out = layer.forward_axis_angle(
                    pose.clone(),
                    betas.clone(),
                    expr.clone(),
                    transl.clone(),
                    Translation::Standard,
                );
                // Reading back forces the computation to finish.
                out.vertices.sum().into_scalar::<f32>()
            })
        });
    }
    group.finish();

    let mut group = c.benchmark_group("smplx_forward_tensor_ops");
    group.sample_size(10);
    let batch = 30;
    let rot = mvmp::geom::rotation::axis_angle_to_matrix(Tensor::<2>::from_data(
        TensorData::new(
            (0..batch * 165)
                .map(|i| ((i as f32) * 0.37).sin() * 0.3)
                .collect::<Vec<f32>>(),
            [batch * 55, 3],
        ),
        &device,
    ))
    .reshape([batch, 55, 3, 3]);
    let zeros = |w| Tensor::<2>::zeros([batch, w], &device);
    group.bench_with_input(BenchmarkId::from_parameter(batch), &batch, |b, _| {
        b.iter(|| {
            let out = layer.forward_tensor_ops(
                rot.clone(),
                zeros(10),
                zeros(10),
                zeros(3),
                Translation::Standard,
            );
            out.vertices.sum().into_scalar::<f32>()
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
