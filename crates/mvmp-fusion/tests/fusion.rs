//! Projection and fusion against values computed independently with the f64 camera model; pooling, NMS
//! and root extraction on planted cases; the RootNet's shapes and gradients.
use burn::tensor::{Device, Tensor, TensorData};
use mvmp_fusion::pool::{max_filter3d_3, max_pool3d_2, nms3d};
use mvmp_fusion::roots::root_voxel_and_offset;
use mvmp_fusion::*;
use mvmp_geom::{Camera, Letterbox, VoxelGrid};
use nalgebra::{Matrix3, Vector2, Vector3};

const S: u32 = 64;
const STRIDE: f64 = 4.0;
const MAP: usize = 16;

fn camera(name: &str, pos: [f64; 3], target: [f64; 3], k1: f64) -> Camera {
    let pos = Vector3::from(pos);
    let z = (Vector3::from(target) - pos).normalize();
    let x = z.cross(&Vector3::z()).normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let k = Matrix3::new(150.0, 0.0, 79.5, 0.0, 150.0, 59.5, 0.0, 0.0, 1.0);
    Camera::new(name, k, r, -(r * pos), [k1, 0.0, 0.0, 0.0, 0.0], 160, 120).unwrap()
}

fn rig() -> Vec<Camera> {
    vec![
        camera("a", [5.0, 0.5, 2.0], [0.0, 0.0, 0.8], -0.05),
        // Close to the grid: parts of it are outside this view or behind it.
        camera("b", [0.5, -1.2, 1.5], [0.3, 3.0, 0.8], 0.0),
    ]
}

fn grid() -> VoxelGrid {
    VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [12, 12, 6]).unwrap()
}

fn vals<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec().unwrap()
}

/// Independent expectation: the feature-map coordinate of a voxel in a view, and whether the view sees it.
fn expected_sample(cam: &Camera, lb: &Letterbox, p: [f64; 3]) -> Option<Vector2<f64>> {
    let (uv, z) = cam.project(&Vector3::from(p));
    let n = cam.to_camera(&Vector3::from(p));
    let seen = z > 1e-3 && cam.contains(uv) && (n.x / n.z).abs() <= 4.0 && (n.y / n.z).abs() <= 4.0;
    seen.then(|| {
        let q = lb.apply(uv);
        Vector2::new((q.x + 0.5) / STRIDE - 0.5, (q.y + 0.5) / STRIDE - 0.5)
    })
}

fn setup(device: &Device) -> (Vec<Camera>, Vec<Letterbox>, SamplingGrid) {
    setup_with(device, grid())
}

fn setup_with(device: &Device, voxels: VoxelGrid) -> (Vec<Camera>, Vec<Letterbox>, SamplingGrid) {
    let cams = rig();
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|c| Letterbox::new(c.width, c.height, S).unwrap())
        .collect();
    let g = SamplingGrid::new(&voxels, &cams, &lbs, STRIDE, [MAP, MAP], device);
    (cams, lbs, g)
}

#[test]
fn a_painted_pixel_lands_in_exactly_the_voxels_that_project_there() {
    let d = Device::flex();
    let (cams, lbs, g) = setup(&d);
    let (pi, pj) = (7usize, 9usize); // row, column of the painted feature pixel in view 0
    let mut maps = vec![0f32; 2 * MAP * MAP];
    maps[pi * MAP + pj] = 1.0;
    let maps = Tensor::<5>::from_data(TensorData::new(maps, [1, 2, 1, MAP, MAP]), &d);
    let fused = vals(fuse_views(maps, std::slice::from_ref(&g), FusionMode::Mean));
    let gr = grid();
    let (mut hits, mut seen0) = (0, 0);
    for (k, c) in gr.centers().iter().enumerate() {
        let s0 = expected_sample(&cams[0], &lbs[0], *c);
        let s1 = expected_sample(&cams[1], &lbs[1], *c);
        let count = s0.is_some() as usize + s1.is_some() as usize;
        let want = match s0 {
            Some(f) => {
                seen0 += 1;
                // Bilinear weight of the painted pixel after border clamping.
                let fx = f.x.clamp(0.0, (MAP - 1) as f64);
                let fy = f.y.clamp(0.0, (MAP - 1) as f64);
                let w = (1.0 - (fx - pj as f64).abs()).max(0.0)
                    * (1.0 - (fy - pi as f64).abs()).max(0.0);
                w / count as f64
            }
            None => 0.0,
        };
        if want > 0.0 {
            hits += 1;
        }
        assert!(
            (fused[k] as f64 - want).abs() < 1e-4,
            "voxel {k}: {} vs {want}",
            fused[k]
        );
    }
    assert!(
        hits >= 3 && seen0 > 100,
        "hits {hits}, seen by view 0: {seen0}"
    );
}

#[test]
fn mean_ignores_views_that_do_not_see_a_voxel_and_max_takes_the_largest() {
    check_mean_and_max(grid());
}

#[test]
fn fusion_on_a_finer_grid_matches_the_per_voxel_expectation() {
    let fine = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [72, 72, 16]).unwrap();
    check_mean_and_max(fine);
}

fn check_mean_and_max(voxels: VoxelGrid) {
    let d = Device::flex();
    let (cams, lbs, g) = setup_with(&d, voxels);
    let mut maps = vec![1f32; MAP * MAP];
    maps.extend(vec![3f32; MAP * MAP]);
    let maps = Tensor::<5>::from_data(TensorData::new(maps, [1, 2, 1, MAP, MAP]), &d);
    let mean = vals(fuse_views(
        maps.clone(),
        std::slice::from_ref(&g),
        FusionMode::Mean,
    ));
    let max = vals(fuse_views(maps, std::slice::from_ref(&g), FusionMode::Max));
    let mut cases = [0usize; 4];
    for (k, c) in voxels.centers().iter().enumerate() {
        let s0 = expected_sample(&cams[0], &lbs[0], *c).is_some();
        let s1 = expected_sample(&cams[1], &lbs[1], *c).is_some();
        let (wm, wx) = match (s0, s1) {
            (true, true) => (2.0, 3.0),
            (true, false) => (1.0, 1.0),
            (false, true) => (3.0, 3.0),
            (false, false) => (0.0, 0.0),
        };
        cases[s0 as usize * 2 + s1 as usize] += 1;
        assert!(
            (mean[k] - wm).abs() < 1e-5 && (max[k] - wx).abs() < 1e-5,
            "voxel {k}: {} {}",
            mean[k],
            max[k]
        );
    }
    // The rig was chosen so that every case occurs.
    assert!(
        cases.iter().all(|&n| n > 0),
        "cases (none, only b, only a, both): {cases:?}"
    );
}

#[test]
fn pooling_and_filters_match_naive_loops() {
    let d = Device::flex();
    let (b, c, x, y, z) = (1, 2, 4, 6, 4);
    let v: Vec<f32> = (0..b * c * x * y * z)
        .map(|i| ((i * 7919) % 113) as f32)
        .collect();
    let t = Tensor::<5>::from_data(TensorData::new(v.clone(), [b, c, x, y, z]), &d);
    let at = |ci: usize, i: usize, j: usize, k: usize| v[((ci * x + i) * y + j) * z + k];
    let pooled = vals(max_pool3d_2(t.clone()));
    let filt = vals(max_filter3d_3(t.clone()));
    for ci in 0..c {
        for i in 0..x / 2 {
            for j in 0..y / 2 {
                for k in 0..z / 2 {
                    let mut m = f32::MIN;
                    for (di, dj, dk) in (0..8).map(|q| (q >> 2, (q >> 1) & 1, q & 1)) {
                        m = m.max(at(ci, 2 * i + di, 2 * j + dj, 2 * k + dk));
                    }
                    assert_eq!(pooled[((ci * x / 2 + i) * (y / 2) + j) * (z / 2) + k], m);
                }
            }
        }
        for i in 0..x {
            for j in 0..y {
                for k in 0..z {
                    let mut m = f32::MIN;
                    for di in -1i64..=1 {
                        for dj in -1i64..=1 {
                            for dk in -1i64..=1 {
                                let (a, bb, cc) = (i as i64 + di, j as i64 + dj, k as i64 + dk);
                                if a >= 0
                                    && bb >= 0
                                    && cc >= 0
                                    && a < x as i64
                                    && bb < y as i64
                                    && cc < z as i64
                                {
                                    m = m.max(at(ci, a as usize, bb as usize, cc as usize));
                                }
                            }
                        }
                    }
                    assert_eq!(filt[((ci * x + i) * y + j) * z + k], m);
                }
            }
        }
    }
    // NMS keeps exactly the local maxima.
    let kept = vals(nms3d(t));
    for (k, (&a, &f)) in v.iter().zip(&filt).enumerate() {
        assert_eq!(kept[k], if a == f { a } else { 0.0 });
    }
}

#[test]
fn nms_finds_planted_gaussians_at_their_world_positions() {
    let d = Device::flex();
    let g = VoxelGrid::new([1.0, -2.0, 1.0], [8.0, 8.0, 2.0], [40, 40, 10]).unwrap();
    let roots = vec![[0.33, -1.07, 0.91], [3.02, 0.71, 1.13], [-1.5, -4.63, 0.55]];
    let target = gaussian_target(&g, std::slice::from_ref(&roots), 0.2, &d);
    // The offset volume holds each root's sub-voxel offset at its voxel (what the offset head learns).
    let mut off = vec![0f32; 3 * g.num_voxels()];
    for r in &roots {
        let (v, o) = root_voxel_and_offset(&g, *r).unwrap();
        for a in 0..3 {
            off[a * g.num_voxels() + g.flat_index(v)] = o[a] as f32;
        }
    }
    let off = Tensor::<5>::from_data(TensorData::new(off, [1, 3, 40, 40, 10]), &d);
    // Each planted root has a detection within `tol` metres.
    let all_found = |found: &[Vec<Root>], tol: f64, how: &str| {
        assert_eq!(found[0].len(), 3, "{how}: {:?}", found[0]);
        for r in &roots {
            let best = found[0]
                .iter()
                .map(|f| {
                    (0..3)
                        .map(|a| (f.position[a] - r[a]).powi(2))
                        .sum::<f64>()
                        .sqrt()
                })
                .fold(f64::MAX, f64::min);
            assert!(
                best < tol,
                "{how}: root {r:?}: nearest detection {best} m away"
            );
        }
    };
    let offsets = Subvoxel::Offset(Box::new(off));
    all_found(
        &extract_roots(target.clone(), offsets, &g, 10, 0.3),
        1e-5,
        "offsets",
    );
    // The Gaussian's own peak finds each root as exactly as the offsets (the targets are Gaussians; 1e-4:
    // the logarithms of f32 values).
    let peaks = extract_roots(target.clone(), Subvoxel::Peak, &g, 10, 0.3);
    all_found(&peaks, 1e-4, "peak");
    // Without offsets, the peak is the voxel centre nearest to the root (within half a voxel per axis).
    let coarse = extract_roots(target.clone(), Subvoxel::Centre, &g, 10, 0.3);
    for f in &coarse[0] {
        assert!(
            roots
                .iter()
                .any(|r| (0..3).all(|a| (f.position[a] - r[a]).abs() <= 0.1 + 1e-9))
        );
        assert!(f.score > 0.7 && f.score <= 1.0);
    }
}

#[test]
fn rootnet_shapes_and_gradients() {
    for norm in [VolumeNorm::Batch, VolumeNorm::Group] {
        rootnet_shapes_and_gradients_with(norm);
    }
}

fn rootnet_shapes_and_gradients_with(norm: VolumeNorm) {
    let d = Device::flex().autodiff();
    let net = RootNetConfig::new(3)
        .with_width(0.25)
        .with_norm(norm)
        .init(&d);
    let x = Tensor::<5>::from_data(
        TensorData::new(
            (0..2 * 3 * 8 * 8 * 4)
                .map(|i| ((i % 17) as f32) / 17.0)
                .collect::<Vec<f32>>(),
            [2, 3, 8, 8, 4],
        ),
        &d,
    );
    let (l, o) = net.forward(x);
    assert_eq!(l.dims(), [2, 1, 8, 8, 4]);
    assert_eq!(o.dims(), [2, 3, 8, 8, 4]);
    let loss = (l.powi_scalar(2).sum() + o.abs().sum()) * 1e3;
    let grads = loss.backward();
    use burn::module::{Module, ModuleVisitor, Param};
    struct Check<'a> {
        grads: &'a burn::tensor::Gradients,
        zero: Vec<String>,
        n: usize,
    }
    impl ModuleVisitor for Check<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            // Batch-norm running statistics are visited too, but are not trained.
            if !p.is_require_grad() {
                return;
            }
            self.n += 1;
            match p.val().grad(self.grads) {
                Some(g) if g.clone().abs().sum().into_scalar::<f32>() > 0.0 => {}
                Some(_) => self.zero.push(format!("{:?} zero", p.val().dims())),
                None => self.zero.push(format!("{:?} none", p.val().dims())),
            }
        }
    }
    let mut c = Check {
        grads: &grads,
        zero: Vec::new(),
        n: 0,
    };
    net.visit(&mut c);
    assert!(c.n > 30);
    assert!(
        c.zero.is_empty(),
        "{norm:?}: {} of {} parameters without gradient: {:?}",
        c.zero.len(),
        c.n,
        c.zero
    );
}

#[test]
fn deformable_fusion_starts_as_mean_fusion_and_learns() {
    use mvmp_fusion::DeformableFusionConfig;
    let d = Device::flex();
    let (_, _, g) = setup(&d);
    let maps: Vec<f32> = (0..2 * 3 * MAP * MAP)
        .map(|i| ((i * 37) % 101) as f32 / 101.0)
        .collect();
    let maps = Tensor::<5>::from_data(TensorData::new(maps, [1, 2, 3, MAP, MAP]), &d);
    let def = DeformableFusionConfig::new().init(&d);
    let a = vals(def.forward(maps.clone(), std::slice::from_ref(&g)));
    let b = vals(fuse_views(maps, std::slice::from_ref(&g), FusionMode::Mean));
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    assert!(
        worst < 1e-5,
        "deformable at initialisation vs mean: {worst}"
    );
    // Its offsets and weights receive gradients.
    let ad = Device::flex().autodiff();
    let (_, _, g) = setup(&ad);
    let def = DeformableFusionConfig::new().init(&ad);
    let maps: Vec<f32> = (0..2 * 3 * MAP * MAP)
        .map(|i| ((i * 37) % 101) as f32 / 101.0)
        .collect();
    let maps = Tensor::<5>::from_data(TensorData::new(maps, [1, 2, 3, MAP, MAP]), &ad);
    let target = Tensor::<5>::ones([1, 3, 12, 12, 6], &ad);
    let loss = (def.forward(maps, std::slice::from_ref(&g)) - target)
        .powi_scalar(2)
        .sum();
    let grads = loss.backward();
    let gw: f32 = def
        .proj
        .weight
        .val()
        .grad(&grads)
        .unwrap()
        .abs()
        .sum()
        .into_scalar();
    assert!(gw > 0.0);
}

/// Sampling grids of a 7 x 9 x 5 voxel grid (not a multiple of the fused pass's block) for two batch
/// items with different rigs, each leaving some voxels unseen and some seen by one view only.
fn two_rigs(d: &Device) -> [SamplingGrid; 2] {
    let voxels = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [7, 9, 5]).unwrap();
    let (_, _, g0) = setup_with(d, voxels);
    let cams: Vec<Camera> = vec![
        camera("c", [-4.0, 2.0, 2.5], [0.0, 0.0, 1.0], 0.03),
        camera("d", [1.0, 1.0, 1.2], [3.0, 3.0, 1.0], -0.02),
    ];
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|c| Letterbox::new(c.width, c.height, S).unwrap())
        .collect();
    let g1 = SamplingGrid::new(&voxels, &cams, &lbs, STRIDE, [MAP, MAP], d);
    [g0, g1]
}

/// The fused CPU pass (`fuse_views` on plain flex) and the tensor ops compute the same volumes: two
/// batch items with different rigs, channel counts that are not a multiple of the vector width, a voxel
/// count that is not a multiple of the block, voxels outside or behind a view.
#[test]
fn fused_pass_matches_the_tensor_ops() {
    let d = Device::flex();
    let grids = two_rigs(&d);
    assert!(grids.iter().all(|g| g.is_fused()));
    // Training on flex takes the fused pass too; other backends keep no host copy (burn-ndarray is
    // deprecated upstream but still a backend here).
    #[allow(deprecated)]
    let other = Device::ndarray();
    assert!(!setup(&other).2.is_fused());
    assert!(setup(&Device::flex().autodiff()).2.is_fused());
    for c in [1usize, 5, 33] {
        let n = 2 * 2 * c * MAP * MAP;
        let maps: Vec<f32> = (0..n)
            .map(|i| ((i * 7919) % 1009) as f32 / 1009.0 - 0.3)
            .collect();
        let maps = Tensor::<5>::from_data(TensorData::new(maps, [2, 2, c, MAP, MAP]), &d);
        for mode in [FusionMode::Mean, FusionMode::Max] {
            let a = fuse_views(maps.clone(), &grids, mode);
            let b = fuse_views_tensor_ops(maps.clone(), &grids, mode);
            assert_eq!(a.dims(), [2, c, 7, 9, 5]);
            assert_eq!(a.dims(), b.dims());
            let (a, b) = (vals(a), vals(b));
            let worst = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max);
            // Same bilinear weights from coordinates computed along two routes: float32 rounding.
            assert!(worst < 1e-5, "{c} channels, {mode:?}: max diff {worst}");
            // The rigs leave some voxels unseen and some seen by one view only.
            assert!(a.iter().filter(|&&x| x == 0.0).count() > 0, "{mode:?}");
        }
    }
}

/// Under autodiff on flex the fused pass's scatter backward gives the maps the gradient the tensor
/// ops' `grid_sample` backward gives, for the mean and the maximum: two batch items with different
/// rigs, a voxel count that is not a multiple of the block, voxels unseen or seen by one view.
#[test]
fn fused_backward_matches_the_tensor_ops() {
    let d = Device::flex().autodiff();
    let grids = two_rigs(&d);
    let c = 5;
    let n = 2 * 2 * c * MAP * MAP;
    let maps: Vec<f32> = (0..n)
        .map(|i| ((i * 7919) % 1009) as f32 / 1009.0 - 0.3)
        .collect();
    let maps = TensorData::new(maps, [2, 2, c, MAP, MAP]);
    // The volume's gradient: distinct per element, so a misplaced scatter shows.
    let p = 7 * 9 * 5;
    let weights: Vec<f32> = (0..2 * c * p)
        .map(|i| ((i * 613) % 499) as f32 / 499.0 - 0.5)
        .collect();
    let weights = Tensor::<5>::from_data(TensorData::new(weights, [2, c, 7, 9, 5]), &d);
    for mode in [FusionMode::Mean, FusionMode::Max] {
        let grad_of = |fused: bool| {
            let m = Tensor::<5>::from_data(maps.clone(), &d).require_grad();
            let vol = if fused {
                fuse_views(m.clone(), &grids, mode)
            } else {
                fuse_views_tensor_ops(m.clone(), &grids, mode)
            };
            let grads = (vol * weights.clone()).sum().backward();
            vals(m.grad(&grads).expect("the maps' gradient"))
        };
        let (a, b) = (grad_of(true), grad_of(false));
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        // Same bilinear weights from coordinates computed along two routes: float32 rounding.
        assert!(worst < 1e-5, "{mode:?}: max diff {worst}");
        assert!(
            b.iter().any(|&x| x != 0.0),
            "{mode:?}: a gradient reaches the maps"
        );
    }
}

/// A `[1, 3, 8, 8, 4]` input with structure (not constant per channel).
fn rootnet_input(d: &Device) -> Tensor<5> {
    Tensor::<5>::from_data(
        TensorData::new(
            (0..3 * 8 * 8 * 4)
                .map(|i| ((i * 7 % 23) as f32) / 23.0)
                .collect::<Vec<f32>>(),
            [1, 3, 8, 8, 4],
        ),
        d,
    )
}

#[test]
fn group_normalised_rootnet_scores_alike_in_training_and_inference() {
    // Training (autodiff) normalises with the batch's statistics; inference with running averages. At
    // batch 1 those differ, which is what made the batch-normalised detector find people in training and
    // miss them in validation; a group-normalised RootNet has no running statistics.
    use burn::module::Module;
    let ad = Device::flex().autodiff();
    let plain = Device::flex();
    for (norm, alike) in [(VolumeNorm::Group, true), (VolumeNorm::Batch, false)] {
        let net = RootNetConfig::new(3)
            .with_width(0.25)
            .with_norm(norm)
            .init(&ad);
        let (train, _) = net.forward(rootnet_input(&ad));
        let (infer, _) = net.valid().forward(rootnet_input(&plain));
        let a: Vec<f32> = train.into_data().convert::<f32>().try_into_vec().unwrap();
        let b: Vec<f32> = infer.into_data().convert::<f32>().try_into_vec().unwrap();
        let diff = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        let scale = a.iter().map(|x| x.abs()).fold(0f32, f32::max);
        assert!(scale > 0.0, "{norm:?}: zero output");
        assert_eq!(
            diff <= 1e-5 * scale.max(1e-3),
            alike,
            "{norm:?}: {diff} of {scale}"
        );
    }
}
