//! Backend equivalence: the same computations on flex (the reference CPU backend), burn-ndarray and,
//! with the `wgpu` feature, wgpu (a GPU, or lavapipe's software Vulkan on a machine without one) give the
//! same numbers within float32 tolerances: the SMPL-X forward, HRNet (conv, batch norm, upsampling),
//! view projection and fusion (grid sampling), the RootNet (3D convolutions, pooling) and the ViT
//! (attention, layer norm, GELU).
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use mvmp::fusion::{FusionMode, RootNetConfig, SamplingGrid, fuse_views};
use mvmp::geom::{Camera, Letterbox, VoxelGrid};
use mvmp::smplx::{SmplxLayer, Translation, standin_model};
use nalgebra::{Matrix3, Vector3};

/// Deterministic pseudo-random values in [-a, a] (a hash, not a progression).
fn values(n: usize, seed: u64, a: f32) -> Vec<f32> {
    (0..n as u64)
        .map(|i| {
            let mut x =
                (i ^ seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            x ^= x >> 31;
            x = x.wrapping_mul(0x94D0_49BB_1331_11EB);
            x ^= x >> 29;
            ((x % 20001) as f32 / 10000.0 - 1.0) * a
        })
        .collect()
}

fn t<const D: usize>(v: Vec<f32>, shape: [usize; D], d: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), d)
}

fn host<const D: usize>(x: Tensor<D>) -> Vec<f32> {
    x.into_data().convert::<f32>().try_into_vec().unwrap()
}

/// Largest absolute difference relative to the reference's largest magnitude.
fn rel_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = a.iter().fold(0f32, |m, x| m.max(x.abs())).max(1e-6);
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max)
        / scale
}

fn rig() -> Vec<Camera> {
    (0..2)
        .map(|i| {
            let a = i as f64 * 1.9 + 0.3;
            let pos = Vector3::new(5.0 * a.cos(), 5.0 * a.sin(), 2.2);
            let z = (Vector3::new(0.0, 0.0, 1.0) - pos).normalize();
            let x = z.cross(&Vector3::z()).normalize();
            let y = z.cross(&x);
            let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
            let k = Matrix3::new(110.0, 0.0, 79.5, 0.0, 110.0, 59.5, 0.0, 0.0, 1.0);
            Camera::new(
                format!("{i}"),
                k,
                r,
                -(r * pos),
                [-0.05, 0.01, 0.0, 0.0, 0.0],
                160,
                120,
            )
            .unwrap()
        })
        .collect()
}

/// Run every check of the suite with `other` against flex; `tol` is the relative tolerance.
fn suite(other: &Device, tol: f32) {
    let flex = Device::flex();
    // SMPL-X forward: skinning GEMMs, the kinematic chain, pose correctives.
    let model = standin_model(0);
    let run = |d: &Device| {
        let layer = SmplxLayer::new(&model, d);
        let out = layer.forward_axis_angle(
            t(values(2 * 55 * 3, 1, 0.4), [2, 55, 3], d),
            t(values(20, 2, 1.0), [2, 10], d),
            t(values(20, 3, 1.0), [2, 10], d),
            t(values(6, 4, 2.0), [2, 3], d),
            Translation::Pelvis,
        );
        (host(out.vertices), host(out.joints))
    };
    let (va, ja) = run(&flex);
    let (vb, jb) = run(other);
    assert!(
        rel_diff(&va, &vb) < tol,
        "SMPL-X vertices: {}",
        rel_diff(&va, &vb)
    );
    assert!(
        rel_diff(&ja, &jb) < tol,
        "SMPL-X joints: {}",
        rel_diff(&ja, &jb)
    );

    // Modules: made once on flex, copied to the other device, run in inference mode on both.
    let image = values(2 * 3 * 64 * 64, 5, 1.0);
    let hr = mvmp::backbone::HRNetConfig::by_name("tiny", 4)
        .unwrap()
        .init(&flex)
        .valid();
    let a = host(hr.forward(t(image.clone(), [2, 3, 64, 64], &flex)));
    let b = host(
        hr.fork(other)
            .forward(t(image.clone(), [2, 3, 64, 64], other)),
    );
    assert!(rel_diff(&a, &b) < tol, "HRNet: {}", rel_diff(&a, &b));

    let vit = mvmp::backbone::ViTConfig::by_name("tiny")
        .unwrap()
        .init(&flex)
        .valid();
    let img = values(3 * 56 * 56, 6, 1.0);
    let a = host(vit.forward(t(img.clone(), [1, 3, 56, 56], &flex)));
    let b = host(vit.fork(other).forward(t(img, [1, 3, 56, 56], other)));
    assert!(rel_diff(&a, &b) < tol, "ViT: {}", rel_diff(&a, &b));

    // Projection and fusion: every voxel centre into every view, bilinear sampling, mean and max.
    let grid = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [16, 16, 8]).unwrap();
    let cams = rig();
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|c| Letterbox::new(c.width, c.height, 64).unwrap())
        .collect();
    let maps = values(2 * 4 * 16 * 16, 7, 1.0);
    for mode in [FusionMode::Mean, FusionMode::Max] {
        let fused = |d: &Device| {
            let g = SamplingGrid::new(&grid, &cams, &lbs, 4.0, [16, 16], d);
            host(fuse_views(
                t(maps.clone(), [1, 2, 4, 16, 16], d),
                &[g],
                mode,
            ))
        };
        let (a, b) = (fused(&flex), fused(other));
        assert!(
            rel_diff(&a, &b) < tol,
            "fusion {mode:?}: {}",
            rel_diff(&a, &b)
        );
    }

    // RootNet: 3D convolutions, batch norm, max pooling, transposed convolutions.
    let rn = RootNetConfig::new(4).with_width(0.25).init(&flex).valid();
    let vol = values(4 * 16 * 16 * 8, 8, 1.0);
    let (la, oa) = rn.forward(t(vol.clone(), [1, 4, 16, 16, 8], &flex));
    let (lb, ob) = rn.fork(other).forward(t(vol, [1, 4, 16, 16, 8], other));
    let (la, lb) = (host(la), host(lb));
    assert!(
        rel_diff(&la, &lb) < tol,
        "RootNet likelihood: {}",
        rel_diff(&la, &lb)
    );
    let (oa, ob) = (host(oa), host(ob));
    assert!(
        rel_diff(&oa, &ob) < tol,
        "RootNet offsets: {}",
        rel_diff(&oa, &ob)
    );
}

#[test]
#[allow(deprecated)]
fn ndarray_matches_flex() {
    suite(&Device::ndarray(), 1e-4);
}

#[cfg(feature = "wgpu")]
#[test]
fn wgpu_matches_flex() {
    suite(&Device::wgpu(burn::tensor::DeviceKind::DefaultDevice), 1e-3);
}
