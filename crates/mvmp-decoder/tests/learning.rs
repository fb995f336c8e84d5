//! The decoder learns to tell people apart. Each person's body pose (three bends) is written into the
//! feature volume around their root; after 300 Adam steps the predicted poses must follow it, the held-out
//! bend error below half of what predicting no bend costs. It guards the path from the volume to the pose
//! heads, which twice failed without a test noticing. Measured with this test (L1 on the rotations, as the
//! parameter loss): with `query_norm` off the error stayed at 1.00 of the no-bend error at learning rates
//! 3e-5 to 1e-3, and after 1000 steps at 1e-4; with it, 0.21-0.27 over four initial seeds at 1e-4. With
//! ReLU heads it stayed at 1.00 at 3e-4 and 1e-3: their hidden units fell silent. GELU heads learn at
//! both rates (0.20 at 1e-4 and 0.28 at 1e-3, this seed), so the test runs at both.
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Bool, Device, Tensor, TensorData};
use mvmp_decoder::{DecoderConfig, DecoderOptions, QueryInputs};
use mvmp_geom::VoxelGrid;
use mvmp_geom::rotation::rot6d_to_matrix;

const PEOPLE: usize = 6;
/// Body joints (of the 21) whose bend about x each person draws, and how far (radians).
const JOINTS: [usize; 3] = [1, 4, 16];
const BEND: f32 = 0.6;

/// The same bends as offsets of three joints from the roots, in a joint volume `[1, 3, X, Y, Z]`: joint
/// `c` a Gaussian (0.15 m) at the root moved `0.4 * bend c` metres along x.
fn joint_volume(grid: &VoxelGrid, roots: &[f32], bends: &[[f32; 3]], d: &Device) -> Tensor<5> {
    let [nx, ny, nz] = grid.shape;
    let n = nx * ny * nz;
    let mut v = vec![0f32; 3 * n];
    for (p, b) in bends.iter().enumerate() {
        for (c, bend) in b.iter().enumerate() {
            let at = [
                roots[p * 3] + 0.4 * bend,
                roots[p * 3 + 1],
                roots[p * 3 + 2],
            ];
            for (i, centre) in grid.centers().iter().enumerate() {
                let d2: f32 = (0..3).map(|a| (centre[a] as f32 - at[a]).powi(2)).sum();
                v[c * n + i] = v[c * n + i].max((-d2 / (2.0 * 0.15 * 0.15)).exp());
            }
        }
    }
    Tensor::from_data(TensorData::new(v, [1, 3, nx, ny, nz]), d)
}

/// A frame: the volume `[1, 32, 32, 32, 8]`, roots `[1, K, 3]`, and each person's bends `[K][3]`.
fn frame(grid: &VoxelGrid, step: u64, d: &Device) -> (Tensor<5>, Tensor<3>, Vec<[f32; 3]>) {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(step);
    let [nx, ny, nz] = grid.shape;
    let mut vol: Vec<f32> = (0..32 * nx * ny * nz)
        .map(|_| rng.random_range(-0.1..0.1))
        .collect();
    let (mut roots, mut bends) = (Vec::new(), Vec::new());
    for p in 0..PEOPLE {
        // People on a ring of cells, so that their 3 x 3 x 3 neighbourhoods never overlap.
        let (ix, iy, iz) = (
            4 + 4 * (p % 3) + rng.random_range(0..2),
            6 + 12 * (p / 3),
            3,
        );
        let b: [f32; 3] = std::array::from_fn(|_| rng.random_range(-BEND..BEND));
        for (c, v) in b.iter().enumerate() {
            for (x, y, z) in neighbourhood(ix, iy, iz) {
                vol[((c * nx + x) * ny + y) * nz + z] = *v;
            }
        }
        let centre = grid.centers()[(ix * ny + iy) * nz + iz];
        roots.extend(centre.map(|x| x as f32));
        bends.push(b);
    }
    let vol = Tensor::from_data(TensorData::new(vol, [1, 32, nx, ny, nz]), d);
    let roots = Tensor::from_data(TensorData::new(roots, [1, PEOPLE, 3]), d);
    (vol, roots, bends)
}

fn neighbourhood(x: usize, y: usize, z: usize) -> Vec<(usize, usize, usize)> {
    let r = |c: usize| c - 1..=c + 1;
    r(x).flat_map(|a| r(y).flat_map(move |b| r(z).map(move |c| (a, b, c))))
        .collect()
}

/// Rotations about x by each bend, identity elsewhere: `[1, K, 21, 3, 3]`.
fn targets(bends: &[[f32; 3]], d: &Device) -> Tensor<5> {
    let mut m = Vec::new();
    for b in bends {
        for j in 0..21 {
            let a = JOINTS.iter().position(|&k| k == j).map_or(0.0, |i| b[i]);
            let (c, s) = (a.cos(), a.sin());
            m.extend([1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c]);
        }
    }
    Tensor::from_data(TensorData::new(m, [1, bends.len(), 21, 3, 3]), d)
}

/// A frame as the decoder reads it: with `via_joints` the bends leave the feature volume (its first three
/// channels zeroed) and come only as joint offsets ([`joint_volume`]).
fn inputs(
    grid: &VoxelGrid,
    step: u64,
    d: &Device,
    via_joints: bool,
) -> (Tensor<5>, Tensor<3>, Vec<[f32; 3]>, Option<Tensor<5>>) {
    let (vol, roots, bends) = frame(grid, step, d);
    if !via_joints {
        return (vol, roots, bends, None);
    }
    let [_, c, nx, ny, nz] = vol.dims();
    let vol = Tensor::cat(
        vec![
            Tensor::zeros([1, 3, nx, ny, nz], d),
            vol.narrow(1, 3, c - 3),
        ],
        1,
    );
    let r: Vec<f32> = roots.to_data().try_into_vec().unwrap();
    let joints = joint_volume(grid, &r, &bends, d);
    (vol, roots, bends, Some(joints))
}

/// How a [`bend_error`] run trains.
#[derive(Clone, Copy, Default)]
struct Setup {
    /// The bends reach the decoder only as joint centroids (`joint_channels`).
    via_joints: bool,
    /// The loss of a training step: the L1 on all 53 rotations (the global orientation and the hands
    /// and face identities beside the bent body) and on betas and expression drawn at random per
    /// person, which no input explains (as the parameter loss sees synthetic people); otherwise the
    /// L1 on the 21 body rotations alone.
    every_parameter: bool,
    /// `DecoderOptions::pose_trunk`.
    pose_trunk: bool,
}

/// The step's loss under `setup`: the decoder's output for the frame against its bends.
fn step_loss(
    out: mvmp_decoder::DecoderOutput,
    bends: &[[f32; 3]],
    setup: Setup,
    step: u64,
    d: &Device,
) -> Tensor<1> {
    use rand::{Rng, SeedableRng};
    let all = rot6d_to_matrix(out.rot6d.reshape([PEOPLE * 53, 6])).reshape([1, PEOPLE, 53, 3, 3]);
    if !setup.every_parameter {
        return (all.narrow(2, 1, 21) - targets(bends, d)).abs().mean() * 10.0;
    }
    let eye = Tensor::<2>::eye(3, d)
        .reshape([1, 1, 1, 3, 3])
        .repeat_dim(1, PEOPLE);
    let truth = Tensor::cat(
        vec![eye.clone(), targets(bends, d), eye.repeat_dim(2, 31)],
        2,
    );
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(step + 99);
    let mut drawn = || -> Tensor<3> {
        let v: Vec<f32> = (0..PEOPLE * 10)
            .map(|_| rng.random_range(-1.4f32..1.4))
            .collect();
        Tensor::from_data(TensorData::new(v, [1, PEOPLE, 10]), d)
    };
    let (betas, expression) = (drawn(), drawn());
    ((all - truth).abs().mean()
        + (out.betas - betas).abs().mean()
        + (out.expression - expression).abs().mean())
        * 10.0
}

/// The runs of this binary's tests take turns: the backend's seeded generator is one per process, so
/// runs side by side draw each other's numbers, and 300 steps carry that into the result.
static TURNS: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Trains a fresh decoder for 300 steps at `lr` and returns its held-out bend error and the error of
/// predicting no bend.
fn bend_error(lr: f64, setup: Setup) -> (f32, f32) {
    let _turn = TURNS.lock().unwrap_or_else(|e| e.into_inner());
    let via_joints = setup.via_joints;
    let d = Device::flex().autodiff();
    d.seed(7);
    let grid = VoxelGrid::new([0.0, 0.0, 1.0], [8.0, 8.0, 2.0], [32, 32, 8]).unwrap();
    let steps = 300;
    let mut dec = DecoderConfig::new(32)
        .with_options(DecoderOptions {
            dim: 128,
            heads: 4,
            pool: 2,
            query_norm: true,
            pose_trunk: setup.pose_trunk,
            ..Default::default()
        })
        .with_joint_channels(if via_joints { 3 } else { 0 })
        .init(&d);
    let mut optim = AdamConfig::new().init();
    let present =
        Tensor::<2, Bool>::from_data(TensorData::new(vec![true; PEOPLE], [1, PEOPLE]), &d);
    let body = |dec: &mvmp_decoder::Decoder, vol, roots, joints| {
        let q = QueryInputs {
            heading: None,
            joints,
        };
        let out = dec.forward_with(vol, q, &grid, roots, present.clone());
        rot6d_to_matrix(out.rot6d.reshape([PEOPLE * 53, 6]))
            .reshape([1, PEOPLE, 53, 3, 3])
            .narrow(2, 1, 21)
    };
    // The drawn bends are what the decoder samples at each root.
    let (vol, roots, bends) = frame(&grid, 0, &d);
    let at: Vec<f32> = mvmp_decoder::trilinear_sample(vol, roots, &grid)
        .narrow(2, 0, 3)
        .into_data()
        .try_into_vec()
        .unwrap();
    let drawn: Vec<f32> = bends.concat();
    assert!(
        at.iter().zip(&drawn).all(|(a, b)| (a - b).abs() < 1e-5),
        "{at:?} vs {drawn:?}"
    );
    for step in 0..steps {
        let (vol, roots, bends, joints) = inputs(&grid, step, &d, via_joints);
        let q = QueryInputs {
            heading: None,
            joints,
        };
        let out = dec.forward_with(vol, q, &grid, roots, present.clone());
        let loss = step_loss(out, &bends, setup, step, &d);
        let grads = GradientsParams::from_grads(loss.backward(), &dec);
        dec = optim.step(lr, dec, grads);
    }
    // Held-out frames: the bend read back from each predicted rotation against the drawn one.
    let (mut err, mut base) = (0.0, 0.0);
    for step in 10_000..10_010 {
        let (vol, roots, bends, joints) = inputs(&grid, step, &d, via_joints);
        let r: Vec<f32> = body(&dec, vol, roots, joints)
            .into_data()
            .try_into_vec()
            .unwrap();
        for (p, b) in bends.iter().enumerate() {
            for (i, &j) in JOINTS.iter().enumerate() {
                let m = &r[(p * 21 + j) * 9..(p * 21 + j) * 9 + 9];
                err += (m[7].atan2(m[4]) - b[i]).abs();
                base += b[i].abs();
            }
        }
    }
    (err, base)
}

#[test]
fn the_decoder_learns_each_persons_pose_from_the_volume() {
    // 1e-4 and the tiny config's stage-2 rate.
    for lr in [1e-4, 1e-3] {
        let (err, base) = bend_error(lr, Setup::default());
        eprintln!("lr {lr}: bend error {:.3} of predicting none", err / base);
        assert!(
            err < 0.5 * base,
            "lr {lr}: bend error {err} against {base} for predicting none"
        );
    }
}

/// The same bends given only as joint offsets from the roots (the heatmap joints' centroids,
/// `joint_channels`): raw, the centroids never steered the heads (1.00 of the no-bend error at 1e-3;
/// scaled by 20, 0.24); layer-normalised, as the decoder now takes them, 0.38 (0.392 on a 2-core AVX2
/// machine; 0.611 there while the binary's other tests ran beside it, before they took turns: see
/// [`TURNS`]).
#[test]
fn the_decoder_learns_each_persons_pose_from_joint_centroids() {
    let setup = Setup {
        via_joints: true,
        ..Default::default()
    };
    let (err, base) = bend_error(1e-3, setup);
    eprintln!(
        "joint centroids: bend error {:.3} of predicting none",
        err / base
    );
    assert!(
        err < 0.6 * base,
        "bend error {err} against {base} for predicting none"
    );
}

/// The loss on every parameter, as training has it (see [`Setup::every_parameter`]). With one shared
/// path the residuals no input explains drown the bends (measured: 1.00 of the no-bend error, as with
/// the loss on the 53 rotations alone, 0.997); with `pose_trunk` only the body's head trains that path.
/// The bound sits between the two: with `pose_trunk` this test measured 0.42 on an AVX-512 machine and
/// 0.62 on an AVX2 one (the kernels round differently and the 300 steps carry it apart), without it
/// 1.02.
#[test]
fn the_decoder_learns_the_pose_beside_residuals_no_input_explains() {
    let setup = Setup {
        via_joints: true,
        every_parameter: true,
        pose_trunk: true,
    };
    let (err, base) = bend_error(1e-3, setup);
    eprintln!(
        "pose_trunk: bend error {:.3} of predicting none",
        err / base
    );
    assert!(
        err < 0.8 * base,
        "bend error {err} against {base} for predicting none"
    );
}
