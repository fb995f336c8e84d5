//! Projection + fusion at paper scale: a 300 x 300 x 20 grid (30 x 30 x 2 m at 0.1 m), views of 1920 x 1080
//! letterboxed to 1288 x 1288, 92 x 92 feature maps (stride 14), 32 channels; and the Human Transformer
//! Blocks with 30 queries over that volume. CPU flex backend. Run: `cargo bench --bench fusion`.
//! The project's targets: sampling + fusion from cached grids <= 140 ms; peak memory of the step <= 1.5x one
//! fused volume. `fuse_views` on flex is the fused CPU pass; `_tensor_ops` rows are the training path. Peak memory is measured with a counting allocator around one call, outside criterion.
use std::alloc::{GlobalAlloc, Layout};
use std::sync::atomic::{AtomicUsize, Ordering};

use burn::tensor::{Bool, Device, Tensor, TensorData};
use criterion::{Criterion, criterion_group, criterion_main};
use mvmp::decoder::{DecoderConfig, DecoderOptions};
use mvmp::fusion::{FusionMode, SamplingGrid, fuse_views, fuse_views_tensor_ops};
use mvmp::geom::{Camera, Letterbox, VoxelGrid};
use nalgebra::{Matrix3, Vector3};

/// Counts bytes over mimalloc, the allocator of the `mvmp` binary.
struct Counting;
static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let p = unsafe { mimalloc::MiMalloc.alloc(l) };
        if !p.is_null() {
            let now = CURRENT.fetch_add(l.size(), Ordering::Relaxed) + l.size();
            PEAK.fetch_max(now, Ordering::Relaxed);
        }
        p
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { mimalloc::MiMalloc.dealloc(p, l) };
        CURRENT.fetch_sub(l.size(), Ordering::Relaxed);
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Bytes allocated at the peak of `f` beyond what was live before it.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = CURRENT.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let out = f();
    (out, PEAK.load(Ordering::Relaxed) - base)
}

fn rig(n: usize) -> Vec<Camera> {
    (0..n)
        .map(|i| {
            let a = i as f64 / n as f64 * std::f64::consts::TAU;
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

fn maps(views: usize, d: &Device) -> Tensor<5> {
    let v: Vec<f32> = (0..views * 32 * 92 * 92)
        .map(|i| ((i % 97) as f32) / 97.0)
        .collect();
    Tensor::from_data(TensorData::new(v, [1, views, 32, 92, 92]), d)
}

fn bench(c: &mut Criterion) {
    let d = Device::flex();
    let grid = VoxelGrid::new([0.0, 0.0, 1.0], [30.0, 30.0, 2.0], [300, 300, 20]).unwrap();
    let fused_bytes = 32 * grid.num_voxels() * 4;
    let mut g = c.benchmark_group("fusion_paper_scale");
    g.sample_size(10);
    for views in [1usize, 5] {
        let cams = rig(views);
        let lbs: Vec<Letterbox> = cams
            .iter()
            .map(|_| Letterbox::new(1920, 1080, 1288).unwrap())
            .collect();
        g.bench_function(format!("sampling_grid_{views}_views"), |b| {
            b.iter(|| {
                SamplingGrid::new(&grid, &cams, &lbs, 14.0, [92, 92], &d)
                    .visible
                    .dims()[1]
            })
        });
        let sg = SamplingGrid::new(&grid, &cams, &lbs, 14.0, [92, 92], &d);
        let m = maps(views, &d);
        let (_, peak) = peak_of(|| {
            fuse_views(m.clone(), std::slice::from_ref(&sg), FusionMode::Mean)
                .narrow(2, 0, 1)
                .sum()
                .into_scalar::<f32>()
        });
        println!(
            "fusion of {views} view(s): peak extra memory {:.1} MB = {:.2} x one fused volume ({:.1} MB)",
            peak as f64 / 1e6,
            peak as f64 / fused_bytes as f64,
            fused_bytes as f64 / 1e6
        );
        g.bench_function(format!("sample_and_mean_fuse_32ch_{views}_views"), |b| {
            b.iter(|| {
                fuse_views(m.clone(), std::slice::from_ref(&sg), FusionMode::Mean)
                    .narrow(2, 0, 1)
                    .sum()
                    .into_scalar::<f32>()
            })
        });
        // The differentiable path that training takes (here without autodiff).
        g.bench_function(
            format!("sample_and_mean_fuse_32ch_{views}_views_tensor_ops"),
            |b| {
                b.iter(|| {
                    fuse_views_tensor_ops(m.clone(), std::slice::from_ref(&sg), FusionMode::Mean)
                        .narrow(2, 0, 1)
                        .sum()
                        .into_scalar::<f32>()
                })
            },
        );
    }
    // Two HTBs, 30 queries, cross-attention over the volume pooled by 4 (75 x 75 x 5 tokens).
    let dec = DecoderConfig::new(32)
        .with_options(DecoderOptions {
            dim: 256,
            heads: 8,
            pool: 4,
            ..Default::default()
        })
        .init(&d);
    let vol = Tensor::<5>::from_data(
        TensorData::new(
            (0..fused_bytes / 4)
                .map(|i| ((i % 89) as f32) / 89.0)
                .collect::<Vec<f32>>(),
            [1, 32, 300, 300, 20],
        ),
        &d,
    );
    let roots: Vec<f32> = (0..30)
        .flat_map(|i| [(i as f32) * 0.7 - 10.0, (i as f32 * 1.3) % 20.0 - 10.0, 0.9])
        .collect();
    let roots = Tensor::<3>::from_data(TensorData::new(roots, [1, 30, 3]), &d);
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true; 30], [1, 30]), &d);
    g.bench_function("htb_30_queries_300x300x20_pool4", |b| {
        b.iter(|| {
            dec.forward(vol.clone(), &grid, roots.clone(), present.clone())
                .transl
                .sum()
                .into_scalar::<f32>()
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
