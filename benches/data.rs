//! Data benchmarks: rendering throughput of the synthetic renderer (one 640 x 360 view with 20 people)
//! and loading throughput of the training loader (5 views letterboxed to 512 x 512).
//! Run: `cargo bench --bench data`.
use std::path::Path;

use burn::data::dataset::Dataset;
use criterion::{Criterion, criterion_group, criterion_main};
use mvmp::data::dataset::FrameDataset;
use mvmp::data::loader::{Split, ViewChoice};
use mvmp::data::synth::render::{Scenery, face_parts, render_view};
use mvmp::data::synth::scene::{Poser, place_people};
use mvmp::data::synth::{SynthConfig, generate, look_at};
use nalgebra::Vector3;
use rand::SeedableRng;

// The allocator of the `mvmp` binary, so that the figures are the binary's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn bench(c: &mut Criterion) {
    let model = mvmp::smplx::standin_model(0);
    let poser = Poser::new(&model);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let people = place_people(&poser, 20, [10.0, 10.0], &mut rng);
    assert!(people.len() >= 18, "placed {}", people.len());
    let parts = face_parts(&model);
    let cam = look_at(
        "bench".into(),
        Vector3::new(9.0, -6.0, 4.0),
        Vector3::new(0.0, 0.0, 0.9),
        60.0,
        -0.05,
        [640, 360],
        [0.0, 0.0],
    )
    .unwrap();
    let scenery = Scenery {
        night: false,
        light_dir: [-0.3, -0.4, -0.8],
        ground: [[0.4, 0.4, 0.38], [0.3, 0.3, 0.3]],
        seed: 1,
    };
    let mut g = c.benchmark_group("data");
    g.sample_size(10);
    g.bench_function("render_view_640x360_20_people", |b| {
        b.iter(|| {
            render_view(&cam, &people, &model.faces, &parts, &scenery)
                .visible
                .len()
        })
    });

    // A dataset with 5 views at 1280 x 720, read and letterboxed to 512 x 512.
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = SynthConfig {
        scenes: 1,
        frames_per_scene: 2,
        people: [6, 6],
        image_size: [1280, 720],
        ..Default::default()
    };
    cfg.cameras.count = 5;
    let root = dir.path().join("ds");
    generate(&cfg, &root, Path::new("."), &|| {}).unwrap();
    let ds = FrameDataset::open(
        &root,
        Split::All,
        ViewChoice::Fixed(vec![0, 1, 2, 3, 4]),
        512,
    )
    .unwrap();
    g.bench_function("load_sample_5_views_512", |b| {
        b.iter(|| ds.get(0).unwrap().images.len())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
