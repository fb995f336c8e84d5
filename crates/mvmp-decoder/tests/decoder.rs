//! Trilinear sampling, mean parameters, decoder shapes, masking of absent people and gradients.
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Bool, Device, Tensor, TensorData};
use mvmp_decoder::*;
use mvmp_geom::VoxelGrid;
use mvmp_geom::rotation::{rot6d_to_matrix, y_up_to_z_up};

fn vals<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec().unwrap()
}

#[test]
fn trilinear_sampling_reproduces_a_linear_field() {
    let d = Device::flex();
    let g = VoxelGrid::new([0.5, -1.0, 1.0], [4.0, 3.0, 2.0], [8, 6, 4]).unwrap();
    let f = |p: [f64; 3]| 2.0 * p[0] + 3.0 * p[1] - p[2] + 1.0;
    let field: Vec<f32> = g.centers().iter().map(|c| f(*c) as f32).collect();
    let mut two = field.clone();
    two.extend(field.iter().map(|v| -v));
    let vol = Tensor::<5>::from_data(TensorData::new(two, [1, 2, 8, 6, 4]), &d);
    // Points inside the hull of the voxel centres.
    let pts: Vec<[f64; 3]> = vec![
        [0.0, -1.0, 1.0],
        [2.2, 0.1, 0.3],
        [-1.2, -2.2, 1.7],
        [0.77, -0.33, 0.95],
    ];
    let flat: Vec<f32> = pts.iter().flatten().map(|&x| x as f32).collect();
    let out = vals(trilinear_sample(
        vol,
        Tensor::from_data(TensorData::new(flat, [1, 4, 3]), &d),
        &g,
    ));
    for (i, p) in pts.iter().enumerate() {
        assert!(
            (out[i * 2] as f64 - f(*p)).abs() < 1e-4,
            "{p:?}: {} vs {}",
            out[i * 2],
            f(*p)
        );
        assert!((out[i * 2 + 1] as f64 + f(*p)).abs() < 1e-4);
    }
}

/// The linear field both lattice tests sample: exact at any point inside the voxel centres.
fn f(p: [f64; 3]) -> f64 {
    2.0 * p[0] + 3.0 * p[1] - p[2] + 1.0
}

/// A one-channel volume holding [`f`] at its voxel centres, and its grid.
fn linear_field_volume(d: &Device) -> (VoxelGrid, Tensor<5>) {
    let g = VoxelGrid::new([0.5, -1.0, 1.0], [4.0, 3.0, 2.0], [8, 6, 4]).unwrap();
    let field: Vec<f32> = g.centers().iter().map(|c| f(*c) as f32).collect();
    (
        g,
        Tensor::<5>::from_data(TensorData::new(field, [1, 1, 8, 6, 4]), d),
    )
}

/// A query's lattice samples the volume at the root plus each offset (x slowest, z fastest, spanning
/// `query_span` from end to end): on a linear field every sample is the field's value there.
#[test]
fn the_query_lattice_samples_the_volume_around_each_root() {
    let d = Device::flex();
    let (g, vol) = linear_field_volume(&d);
    let dec = DecoderConfig::new(1)
        .with_options(DecoderOptions {
            dim: 8,
            heads: 2,
            query_lattice: [2, 1, 3],
            query_span: [1.0, 0.7, 0.5],
            ..Default::default()
        })
        .init(&d);
    let want_offsets = [
        [-0.5, 0.0, -0.25],
        [-0.5, 0.0, 0.0],
        [-0.5, 0.0, 0.25],
        [0.5, 0.0, -0.25],
        [0.5, 0.0, 0.0],
        [0.5, 0.0, 0.25],
    ];
    assert_eq!(dec.lattice, want_offsets);
    let roots = [[0.3, -0.8, 1.0], [1.1, 0.2, 0.9]];
    let flat: Vec<f32> = roots.iter().flatten().map(|&x| x as f32).collect();
    let roots_t = Tensor::<3>::from_data(TensorData::new(flat, [1, 2, 3]), &d);
    let out = dec.sample_lattice(vol, roots_t, &g);
    assert_eq!(out.dims(), [1, 2, 6]);
    let out = vals(out);
    for (k, r) in roots.iter().enumerate() {
        for (l, o) in want_offsets.iter().enumerate() {
            let p: [f64; 3] = std::array::from_fn(|a| r[a] + o[a] as f64);
            let got = out[k * 6 + l] as f64;
            assert!(
                (got - f(p)).abs() < 1e-4,
                "root {k} point {l}: {got} vs {}",
                f(p)
            );
        }
    }
}

/// A lattice turned with the heading: its x axis points where the person faces and its y axis to their
/// left, so on a linear field each sample is the field at the root plus the offset turned by the
/// heading's angle (hand-derived: facing +y, the lattice's +x is the world's +y and its +y the world's
/// -x); facing +x it is the plain lattice.
#[test]
fn a_heading_lattice_turns_with_each_person() {
    let d = Device::flex();
    let (g, vol) = linear_field_volume(&d);
    let dec = DecoderConfig::new(1)
        .with_options(DecoderOptions {
            dim: 8,
            heads: 2,
            query_lattice: [2, 2, 2],
            query_span: [0.8, 0.6, 0.5],
            heading_lattice: true,
            ..Default::default()
        })
        .init(&d);
    // Every point stays inside the voxel centres, where the field is exact.
    let roots = [[0.3, -0.8, 1.0], [1.1, -0.9, 0.9], [0.6, -0.5, 1.1]];
    let flat: Vec<f32> = roots.iter().flatten().map(|&x| x as f32).collect();
    let roots_t = Tensor::<3>::from_data(TensorData::new(flat, [1, 3, 3]), &d);
    let angle = 0.7f64;
    let headings = [[1.0, 0.0], [0.0, 1.0], [angle.cos(), angle.sin()]];
    let flat: Vec<f32> = headings.iter().flatten().map(|&x| x as f32).collect();
    let heading = Tensor::<3>::from_data(TensorData::new(flat, [1, 3, 2]), &d);
    let turned = vals(dec.sample_lattice_turned(vol.clone(), roots_t.clone(), heading, &g));
    let plain = vals(dec.sample_lattice(vol, roots_t, &g));
    for l in 0..8 {
        assert!((turned[l] - plain[l]).abs() < 1e-5, "facing +x, point {l}");
        let [ox, oy, oz] = dec.lattice[l].map(f64::from);
        let by_hand = [roots[1][0] - oy, roots[1][1] + ox, roots[1][2] + oz];
        assert!(
            (turned[8 + l] as f64 - f(by_hand)).abs() < 1e-4,
            "facing +y, point {l}"
        );
        let (c, s) = (angle.cos(), angle.sin());
        let r = roots[2];
        let p = [r[0] + c * ox - s * oy, r[1] + s * ox + c * oy, r[2] + oz];
        assert!(
            (turned[16 + l] as f64 - f(p)).abs() < 1e-4,
            "turned, point {l}"
        );
    }
}

/// A joint's centroid in the box around a root, by hand: a likelihood that is 1 in one voxel of the
/// box and 0 elsewhere puts the centroid of the lattice points around that voxel (weights: the squared
/// trilinear sample) at the voxel's offset; a joint absent from the box gives 0. Turned with a
/// heading, the offset is in the person's frame.
#[test]
fn joint_centroids_find_a_joint_in_the_box() {
    let d = Device::flex();
    let g = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [16, 16, 8]).unwrap();
    let dec = DecoderConfig::new(1)
        .with_options(DecoderOptions {
            dim: 8,
            heads: 2,
            joint_lattice: [9, 9, 9],
            joint_span: [2.0, 2.0, 2.0],
            ..Default::default()
        })
        .with_joint_channels(2)
        .init(&d);
    // Joint 0 at the centre of voxel (10, 6, 5): x 0.625, y -0.375, z 1.375; joint 1 nowhere.
    let mut vol = vec![0f32; 2 * 16 * 16 * 8];
    vol[(10 * 16 + 6) * 8 + 5] = 1.0;
    let vol = Tensor::<5>::from_data(TensorData::new(vol, [1, 2, 16, 16, 8]), &d);
    let root = [0.125f32, 0.125, 1.125];
    let roots = Tensor::<3>::from_data(TensorData::new(root.to_vec(), [1, 1, 3]), &d);
    let c = vals(dec.joint_centroids(vol.clone(), roots.clone(), None, &g));
    assert_eq!(c.len(), 6);
    // Offsets as fractions of the box's half side (1 m); the lattice (0.25 m apart) is symmetric about
    // the voxel's centre, so the weighted mean is that centre.
    let want = [0.625 - 0.125, -0.375 - 0.125, 1.375 - 1.125];
    for a in 0..3 {
        assert!(
            (c[a] - want[a]).abs() < 1e-4,
            "axis {a}: {} vs {}",
            c[a],
            want[a]
        );
        assert_eq!(c[3 + a], 0.0, "an absent joint");
    }
    // Facing +y, the box turns a quarter (onto its own points): forward is world y, left is world -x.
    let heading = Tensor::<3>::from_data(TensorData::new(vec![0f32, 1.0], [1, 1, 2]), &d);
    let c = vals(dec.joint_centroids(vol, roots, Some(heading), &g));
    let turned = [want[1], -want[0], want[2]];
    for a in 0..3 {
        assert!(
            (c[a] - turned[a]).abs() < 1e-4,
            "turned, axis {a}: {} vs {}",
            c[a],
            turned[a]
        );
    }
}

/// The joints' centroids widen the query's input by three numbers per joint and reach every head:
/// moving a joint within the box changes each present person's output.
#[test]
fn joint_centroids_join_every_query() {
    let d = Device::flex();
    let dec = DecoderConfig::new(8)
        .with_options(DecoderOptions {
            dim: 32,
            heads: 4,
            pool: 2,
            query_norm: true,
            ..Default::default()
        })
        .with_joint_channels(3)
        .init(&d);
    assert_eq!(dec.query_proj.weight.dims()[0], 8 + 3 * 3 + 53 * 6 + 20);
    let (vol, roots, present, g) = inputs(&d, [1.5, 1.5, 1.0]);
    let run = |shift: usize| {
        let joints: Vec<f32> = (0..2 * 3 * 8 * 8 * 4)
            .map(|i: usize| f32::from(u8::from((i + shift).is_multiple_of(7))))
            .collect();
        let joints = Tensor::<5>::from_data(TensorData::new(joints, [2, 3, 8, 8, 4]), &d);
        let inputs = QueryInputs {
            heading: None,
            joints: Some(joints),
        };
        vals(
            dec.forward_with(vol.clone(), inputs, &g, roots.clone(), present.clone())
                .betas,
        )
    };
    let (a, b) = (run(0), run(3));
    for slot in [0usize, 1, 3] {
        let change = (0..10)
            .map(|i| (a[slot * 10 + i] - b[slot * 10 + i]).abs())
            .fold(0.0, f32::max);
        assert!(change > 1e-6, "slot {slot}: the joints changed nothing");
    }
}

#[test]
fn mean_parameters_are_upright_identity_and_zero() {
    let d = Device::flex();
    let m = vals(mean_params(&d));
    assert_eq!(m.len(), 53 * 6 + 20);
    let g = vals(rot6d_to_matrix(Tensor::from_data(
        TensorData::new(m[..6].to_vec(), [1, 6]),
        &d,
    )));
    let want = y_up_to_z_up();
    for k in 0..9 {
        assert!((g[k] as f64 - want[(k / 3, k % 3)]).abs() < 1e-6);
    }
    assert_eq!(m[6..12], [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
    assert!(m[318..].iter().all(|&v| v == 0.0));
}

fn inputs(d: &Device, third_root: [f32; 3]) -> (Tensor<5>, Tensor<3>, Tensor<2, Bool>, VoxelGrid) {
    let g = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [8, 8, 4]).unwrap();
    let vol: Vec<f32> = (0..2 * 8 * 256)
        .map(|i| ((i * 37) % 101) as f32 / 101.0)
        .collect();
    let vol = Tensor::<5>::from_data(TensorData::new(vol, [2, 8, 8, 8, 4]), d);
    let mut roots = vec![0.1f32, 0.2, 0.9, -1.0, 0.5, 1.0];
    roots.extend(third_root);
    roots.extend([0.5f32, 0.5, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    let roots = Tensor::<3>::from_data(TensorData::new(roots, [2, 3, 3]), d);
    let present = Tensor::<2, Bool>::from_data(
        TensorData::new(vec![true, true, false, true, false, false], [2, 3]),
        d,
    );
    (vol, roots, present, g)
}

#[test]
fn shapes_and_masking_of_absent_people() {
    let d = Device::flex();
    let lattices = [([1, 1, 1], [0.0; 3]), ([3, 2, 2], [0.5, 0.5, 1.0])];
    for (use_htb, pool, (lattice, span)) in [
        (true, 1, lattices[0]),
        (true, 2, lattices[0]),
        (false, 1, lattices[0]),
        (true, 2, lattices[1]),
    ] {
        let dec = DecoderConfig::new(8)
            .with_options(DecoderOptions {
                dim: 32,
                heads: 4,
                pool,
                use_htb,
                query_lattice: lattice,
                query_span: span,
                ..Default::default()
            })
            .init(&d);
        let (vol, roots, present, g) = inputs(&d, [1.5, 1.5, 1.0]);
        let out = dec.forward(vol.clone(), &g, roots, present.clone());
        assert_eq!(out.rot6d.dims(), [2, 3, 53, 6]);
        assert_eq!(out.betas.dims(), [2, 3, 10]);
        assert_eq!(out.expression.dims(), [2, 3, 10]);
        assert_eq!(out.transl.dims(), [2, 3, 3]);
        // Moving an absent person's root changes nothing for the people present.
        let (_, roots2, _, _) = inputs(&d, [-1.7, 0.3, 0.4]);
        let out2 = dec.forward(vol, &g, roots2, present);
        let (a, b) = (vals(out.rot6d), vals(out2.rot6d));
        let per = 53 * 6;
        for slot in [0usize, 1, 3] {
            let worst = (0..per)
                .map(|k| (a[slot * per + k] - b[slot * per + k]).abs())
                .fold(0.0, f32::max);
            assert!(
                worst < 1e-6,
                "htb {use_htb} pool {pool} slot {slot}: {worst}"
            );
        }
    }
}

#[test]
fn every_parameter_gets_a_gradient() {
    let d = Device::flex().autodiff();
    let dec = DecoderConfig::new(8)
        .with_options(DecoderOptions {
            dim: 32,
            heads: 4,
            ..Default::default()
        })
        .init(&d);
    let (vol, roots, present, g) = inputs(&d, [1.5, 1.5, 1.0]);
    let out = dec.forward(vol, &g, roots, present);
    let loss = out.rot6d.powi_scalar(2).sum()
        + out.betas.sum()
        + out.expression.sum()
        + out.transl.powi_scalar(2).sum();
    let grads = loss.backward();
    struct Check<'a>(&'a burn::tensor::Gradients, Vec<Vec<usize>>, usize);
    impl ModuleVisitor for Check<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if !p.is_require_grad() {
                return;
            }
            self.2 += 1;
            let ok = p
                .val()
                .grad(self.0)
                .is_some_and(|g| g.abs().sum().into_scalar::<f32>() > 0.0);
            if !ok {
                self.1.push(p.val().dims().to_vec());
            }
        }
    }
    let mut c = Check(&grads, Vec::new(), 0);
    dec.visit(&mut c);
    assert!(
        c.2 > 40 && c.1.is_empty(),
        "{} params, without gradient: {:?}",
        c.2,
        c.1
    );
}

#[test]
fn root_encoding_matches_the_voxel_encoding_at_voxel_centres() {
    // The queries and the tokens share one encoding (both go through `pos_proj`): at a voxel centre a
    // root is encoded as that voxel's token is.
    let d = Device::flex();
    let grid = VoxelGrid::new([0.5, -1.0, 1.0], [4.0, 2.0, 2.0], [8, 4, 4]).unwrap();
    let centres = grid.centers();
    let pts: Vec<f32> = centres.iter().flat_map(|c| c.map(|x| x as f32)).collect();
    let n = centres.len();
    let enc = vals(point_encoding(
        Tensor::from_data(TensorData::new(pts, [1, n, 3]), &d),
        &grid,
    ));
    let lo = grid.min_corner();
    // Independent: per axis a, frequency f: sin and cos of pi 2^f (c_a - lo_a) / size_a.
    for (i, c) in centres.iter().enumerate() {
        for a in 0..3 {
            let x = (c[a] - lo[a]) / grid.size[a];
            for f in 0..8 {
                let w = std::f64::consts::PI * (1 << f) as f64 * x;
                let o = i * 48 + (a * 8 + f) * 2;
                assert!((enc[o] as f64 - w.sin()).abs() < 1e-4, "sin at {i} {a} {f}");
                assert!(
                    (enc[o + 1] as f64 - w.cos()).abs() < 1e-4,
                    "cos at {i} {a} {f}"
                );
            }
        }
    }
}

/// Every parameter's gradient, in visiting order.
fn param_grads<M: Module>(m: &M, grads: &burn::tensor::Gradients) -> Vec<Vec<f32>> {
    struct Collect<'a>(&'a burn::tensor::Gradients, Vec<Vec<f32>>);
    impl ModuleVisitor for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if let Some(g) = p.val().grad(self.0) {
                self.1.push(vals(g));
            }
        }
    }
    let mut c = Collect(grads, Vec::new());
    m.visit(&mut c);
    c.1
}

/// Cross-attention in tiles (`mvmp_kernels::attention`, 7 tiles of 40 over 256 tokens) gives burn's
/// multi-head attention: the same outputs and the same gradient of every parameter.
#[test]
fn tiled_cross_attention_equals_burns_attention() {
    let d = Device::flex().autodiff();
    let whole = DecoderConfig::new(8)
        .with_options(DecoderOptions {
            dim: 32,
            heads: 4,
            ..Default::default()
        })
        .with_attention_tile(0)
        .init(&d);
    let mut tiled = whole.clone();
    for b in &mut tiled.blocks {
        b.tile = 40;
    }
    let run = |dec: &Decoder| {
        let (vol, roots, present, g) = inputs(&d, [1.5, 1.5, 1.0]);
        let out = dec.forward(vol, &g, roots, present);
        let loss = out.rot6d.clone().powi_scalar(2).sum() + out.betas.clone().sum();
        let grads = loss.backward();
        (vals(out.rot6d.detach()), param_grads(dec, &grads))
    };
    let ((ra, ga), (rb, gb)) = (run(&whole), run(&tiled));
    let worst = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    };
    assert!(
        worst(&ra, &rb) < 1e-5,
        "rot6d differs by {}",
        worst(&ra, &rb)
    );
    assert_eq!(ga.len(), gb.len());
    for (i, (a, b)) in ga.iter().zip(&gb).enumerate() {
        assert!(
            worst(a, b) < 1e-5,
            "parameter {i}: gradient differs by {}",
            worst(a, b)
        );
    }
}

/// With `pose_trunk` only the body-pose rotations reach the shared query path: a loss on the global
/// orientation, hands and face, betas, expression and translation leaves the query projection without a
/// gradient, one on the body rotations gives it one; the output shapes are those of the shared heads.
#[test]
fn with_pose_trunk_only_the_body_pose_trains_the_query_path() {
    let d = Device::flex().autodiff();
    let g = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [8, 8, 4]).unwrap();
    let dec = DecoderConfig::new(4)
        .with_options(DecoderOptions {
            dim: 8,
            heads: 2,
            pose_trunk: true,
            ..Default::default()
        })
        .init(&d);
    let vol = Tensor::<5>::random([1, 4, 8, 8, 4], burn::tensor::Distribution::Default, &d);
    let roots = Tensor::<3>::from_data(TensorData::new(vec![0.3f32, -0.2, 0.9], [1, 1, 3]), &d);
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true], [1, 1]), &d);
    let grad_of = |pick: &dyn Fn(DecoderOutput) -> Tensor<1>| {
        let out = dec.forward(vol.clone(), &g, roots.clone(), present.clone());
        assert_eq!(out.rot6d.dims(), [1, 1, 53, 6]);
        let grads = pick(out).backward();
        (dec.query_proj.weight.grad(&grads)).map(|t| t.abs().sum().into_scalar::<f32>())
    };
    let rest = grad_of(&|o| {
        o.rot6d.clone().narrow(2, 0, 1).sum()
            + o.rot6d.narrow(2, 22, 31).sum()
            + o.betas.sum()
            + o.expression.sum()
            + o.transl.sum()
    });
    assert!(rest.is_none_or(|s| s == 0.0), "{rest:?}");
    let body = grad_of(&|o| o.rot6d.narrow(2, 1, 21).sum());
    assert!(body.is_some_and(|s| s > 0.0), "{body:?}");
}

/// Height features by hand: 7 centres over 0.2-1.4 m are 0.2 m apart, so a root 0.6 m high is 1 at the
/// third, exp(-1/2) at its neighbours and exp(-2) two centres away, whatever its x and y.
#[test]
fn height_features_are_gaussian_bumps_of_the_root_height() {
    let d = Device::flex();
    let roots = Tensor::<3>::from_data(TensorData::new(vec![3.0f32, -2.0, 0.6], [1, 1, 3]), &d);
    let f: Vec<f32> = mvmp_decoder::height_features(roots, 7)
        .into_data()
        .try_into_vec()
        .unwrap();
    let want = [
        (-2.0f32).exp(),
        (-0.5f32).exp(),
        1.0,
        (-0.5f32).exp(),
        (-2.0f32).exp(),
    ];
    for (i, w) in want.iter().enumerate() {
        assert!((f[i] - w).abs() < 1e-5, "{f:?}");
    }
    assert!(f[6] < 1e-3, "{f:?}");
}

/// With `sample_skip` the projected volume sample joins the heads' input after the final norm: a skip
/// whose projection is all zeros gives exactly the decoder without it (the same other weights), and with
/// its own weights the output follows the sample.
#[test]
fn a_sample_skip_adds_the_projected_sample_to_the_heads_input() {
    let d = Device::flex();
    let dec = DecoderConfig::new(8)
        .with_options(DecoderOptions {
            dim: 32,
            heads: 4,
            query_norm: true,
            query_lattice: [3, 2, 2],
            query_span: [0.5, 0.5, 1.0],
            sample_skip: true,
            ..Default::default()
        })
        .init(&d);
    let (vol, roots, present, g) = inputs(&d, [1.5, 1.5, 1.0]);
    let run = |dec: &Decoder| {
        vals(
            dec.forward(vol.clone(), &g, roots.clone(), present.clone())
                .rot6d,
        )
    };
    let mut silent = dec.clone();
    let proj = silent.sample_proj.take().unwrap();
    let without = run(&silent);
    silent.sample_proj = Some(burn::nn::Linear {
        weight: proj.weight.clone().map(|w| w.zeros_like()),
        bias: proj.bias.clone().map(|b| b.map(|b| b.zeros_like())),
    });
    let gap = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    };
    assert!(gap(&run(&silent), &without) < 1e-6);
    assert!(
        gap(&run(&dec), &without) > 1e-5,
        "{}",
        gap(&run(&dec), &without)
    );
}

/// With `volume_norm` each channel is standardised over the volume, so the decoder reads a channel the
/// same whatever its level and scale: every channel moved by its own shift and positive scale leaves the
/// output unchanged, which it does not without the option.
#[test]
fn a_standardised_volume_reads_every_channel_the_same_at_any_level_and_scale() {
    let d = Device::flex();
    let options = |volume_norm| DecoderOptions {
        dim: 32,
        heads: 4,
        pool: 2,
        query_norm: true,
        query_lattice: [3, 2, 2],
        query_span: [0.5, 0.5, 1.0],
        volume_norm,
        ..Default::default()
    };
    let (vol, roots, present, g) = inputs(&d, [1.5, 1.5, 1.0]);
    let shift: Vec<f32> = (0..8).map(|c| c as f32 * 0.7 - 2.0).collect();
    let scale: Vec<f32> = (0..8).map(|c| 0.05 + c as f32 * 0.9).collect();
    let moved = vol.clone()
        * Tensor::<1>::from_data(TensorData::new(scale, [8]), &d).reshape([1, 8, 1, 1, 1])
        + Tensor::<1>::from_data(TensorData::new(shift, [8]), &d).reshape([1, 8, 1, 1, 1]);
    for (norm, invariant) in [(true, true), (false, false)] {
        let dec = DecoderConfig::new(8).with_options(options(norm)).init(&d);
        let run = |v: Tensor<5>| vals(dec.forward(v, &g, roots.clone(), present.clone()).rot6d);
        let (a, b) = (run(vol.clone()), run(moved.clone()));
        let gap = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert_eq!(gap < 1e-6, invariant, "volume_norm {norm}: {gap}");
    }
    // The standardised channels: zero mean and unit variance over the voxels, by direct computation.
    let s = vals(standardise_channels(moved));
    for ch in s.chunks(256) {
        let mean = ch.iter().sum::<f32>() / 256.0;
        let var = ch.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / 256.0;
        assert!(
            mean.abs() < 1e-5 && (var - 1.0).abs() < 1e-4,
            "{mean} {var}"
        );
    }
}

/// With `joint_samples` a query reads the joint volume's samples on the joint lattice, turned with the
/// heading under `heading_lattice` and layer-normalised (over each person's samples: the norm's initial
/// gain 1 and bias 0): on a linear field they are the field at the hand-turned points, normalised by
/// hand. The query projection widens by one input per joint and lattice point.
#[test]
fn joint_samples_are_the_turned_lattice_normalised() {
    let d = Device::flex();
    let (g, vol) = linear_field_volume(&d);
    let lattice = [2, 2, 3];
    let dec = |turn: bool| {
        DecoderConfig::new(4)
            .with_options(DecoderOptions {
                dim: 8,
                heads: 2,
                query_joints: true,
                joint_samples: true,
                joint_lattice: lattice,
                joint_span: [0.8, 0.6, 0.5],
                heading_lattice: turn,
                ..Default::default()
            })
            .with_joint_channels(1)
            .with_heading(true)
            .init(&d)
    };
    assert_eq!(dec(true).query_proj.weight.dims()[0], 4 + 12 + 53 * 6 + 20);
    let roots = [[0.3f64, -0.8, 1.0], [1.1, -0.9, 0.9]];
    let flat: Vec<f32> = roots.iter().flatten().map(|&x| x as f32).collect();
    let roots_t = Tensor::<3>::from_data(TensorData::new(flat, [1, 2, 3]), &d);
    let heading = Tensor::<3>::from_data(TensorData::new(vec![1f32, 0.0, 0.0, 1.0], [1, 2, 2]), &d);
    let normalised = |x: Vec<f64>| {
        let mean = x.iter().sum::<f64>() / x.len() as f64;
        let var = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / x.len() as f64;
        x.iter()
            .map(|v| (v - mean) / (var + 1e-5).sqrt())
            .collect::<Vec<_>>()
    };
    for turn in [true, false] {
        let dec = dec(turn);
        let got = dec.joint_inputs(vol.clone(), roots_t.clone(), Some(heading.clone()), &g);
        assert_eq!(got.dims(), [1, 2, 12]);
        let got = vals(got);
        for (k, r) in roots.iter().enumerate() {
            // The second person faces +y: the lattice's x is the world's +y, its y the world's -x.
            let points = dec.joint_lattice.iter().map(|o| {
                let [ox, oy, oz] = o.map(f64::from);
                match (turn, k) {
                    (true, 1) => [r[0] - oy, r[1] + ox, r[2] + oz],
                    _ => [r[0] + ox, r[1] + oy, r[2] + oz],
                }
            });
            let want = normalised(points.map(f).collect());
            for (l, w) in want.iter().enumerate() {
                let v = got[k * 12 + l] as f64;
                assert!(
                    (v - w).abs() < 1e-3,
                    "turn {turn}, person {k}, point {l}: {v} vs {w}"
                );
            }
        }
    }
}

/// `pose_read` starts at zero (the decoder's output is bit for bit that without it) and adds its linear
/// read of the joint samples, divided by the square root of their number, to the 21 body rotations
/// alone (slots 1-21 of the 53; the global orientation and the hands and face stay).
#[test]
fn pose_read_adds_its_linear_read_to_the_body_rotations() {
    let d = Device::flex();
    let (g, joints) = linear_field_volume(&d);
    let volume = Tensor::cat(vec![joints.clone(); 4], 1);
    let mut dec = DecoderConfig::new(4)
        .with_options(DecoderOptions {
            dim: 8,
            heads: 2,
            query_joints: true,
            joint_samples: true,
            pose_read: true,
            joint_lattice: [2, 2, 3],
            joint_span: [0.8, 0.6, 0.5],
            ..Default::default()
        })
        .with_joint_channels(1)
        .init(&d);
    let roots = Tensor::<3>::from_data(
        TensorData::new(vec![0.3f32, -0.8, 1.0, 1.1, -0.9, 0.9], [1, 2, 3]),
        &d,
    );
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true, true], [1, 2]), &d);
    let run = |dec: &Decoder| {
        let inputs = QueryInputs {
            heading: None,
            joints: Some(joints.clone()),
        };
        vals(
            dec.forward_with(volume.clone(), inputs, &g, roots.clone(), present.clone())
                .rot6d,
        )
    };
    let at_zero = run(&dec);
    let mut without = dec.clone();
    without.pose_read = None;
    assert_eq!(at_zero, run(&without));
    let x = vals(dec.joint_inputs(joints.clone(), roots.clone(), None, &g));
    // The output hands back what the read took (the pose fit's rows), and nothing without a read.
    let inputs = |dec: &Decoder| {
        let q = QueryInputs {
            heading: None,
            joints: Some(joints.clone()),
        };
        (dec.forward_with(volume.clone(), q, &g, roots.clone(), present.clone()))
            .pose_inputs
            .map(vals)
    };
    assert_eq!(inputs(&dec), Some(x.clone()));
    assert_eq!(inputs(&without), None);
    let (n, out) = (12, 21 * 6);
    let w: Vec<f32> = (0..n * out)
        .map(|i| ((i * 7) % 11) as f32 * 0.1 - 0.5)
        .collect();
    let bias: Vec<f32> = (0..out).map(|o| o as f32 * 0.01).collect();
    let read = dec.pose_read.as_mut().unwrap();
    read.weight = Param::from_tensor(Tensor::from_data(TensorData::new(w.clone(), [n, out]), &d));
    read.bias = Some(Param::from_tensor(Tensor::from_data(
        TensorData::new(bias.clone(), [out]),
        &d,
    )));
    let got = run(&dec);
    for k in 0..2 {
        for slot in 0..53 * 6 {
            let delta = (got[k * 318 + slot] - at_zero[k * 318 + slot]) as f64;
            let want = match slot {
                6..132 => {
                    let o = slot - 6;
                    let dot: f64 = (0..n)
                        .map(|i| x[k * n + i] as f64 * w[i * out + o] as f64)
                        .sum();
                    (dot + bias[o] as f64) / (n as f64).sqrt()
                }
                _ => 0.0,
            };
            assert!(
                (delta - want).abs() < 1e-4,
                "person {k}, slot {slot}: {delta} vs {want}"
            );
        }
    }
}
