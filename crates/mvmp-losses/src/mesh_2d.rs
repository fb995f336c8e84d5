//! The 2D mesh loss over every view in one pass on flex, with its own backward under autodiff.
//!
//! As tensor ops ([`crate::mesh_2d_loss_weighted`] once per view), each view projects the true and the
//! predicted points through some forty elementwise operations on `[B, K * N]` tensors, and autodiff keeps
//! their intermediates for a backward of as many again. Here one pass over the points projects each
//! into every view, sums the weighted L1 per view and, under autodiff, forms each point's gradient at the
//! same time: the loss is a sum over points, so a point's gradient is its own terms' alone, and the
//! backward only scales it by the loss's gradient. The true points' projections, what counts and each
//! view's normaliser are constants made once per call ([`Mesh2dPlan`]). [`set_fused_mesh_2d`] turns the
//! pass off under autodiff, so that the tensor-op path can be timed beside it.
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use mvmp_geom::project::{MAX_NORMALISED, MIN_DEPTH};
use mvmp_geom::{Camera, Letterbox};
use mvmp_kernels::host::{HostF32, dims};

static FUSED: AtomicBool = AtomicBool::new(true);

/// Whether training (autodiff on flex) takes the one-pass 2D mesh loss (the default) or tensor ops;
/// process-wide. Without autodiff, flex always takes the pass.
pub fn set_fused_mesh_2d(on: bool) {
    FUSED.store(on, Ordering::Relaxed);
}

/// See [`set_fused_mesh_2d`].
pub fn fused_mesh_2d() -> bool {
    FUSED.load(Ordering::Relaxed)
}

/// Whether [`crate::mesh_2d_loss_views`] takes the one pass on `device`.
pub(crate) fn applies(device: &Device) -> bool {
    *device == Device::flex() && (!device.is_autodiff() || fused_mesh_2d())
}

/// One camera and its letterbox on the host, in float32 as [`mvmp_geom::CameraTensors`] holds them.
#[derive(Debug, Clone, Copy)]
pub struct HostCamera {
    r: [f32; 9],
    t: [f32; 3],
    dist: [f32; 5],
    /// `[fx, skew, cx, fy, cy]`.
    intr: [f32; 5],
    /// `[a_u, b_u, a_v, b_v]` into network pixels.
    affine: [f32; 4],
}

/// A point's network pixel and what its backward needs.
struct Projected {
    uv: [f32; 2],
    /// `d(u, v) / d(xn, yn)`, zero along a clamped normalised coordinate.
    d_norm: [[f32; 2]; 2],
    /// The unclamped normalised coordinates and the depth divided by.
    raw: [f32; 2],
    zs: f32,
    /// 1 where the depth is not clamped.
    dz: f32,
}

impl HostCamera {
    pub fn new(cam: &Camera, letterbox: Option<&Letterbox>) -> Self {
        let r = std::array::from_fn(|i| cam.r[(i / 3, i % 3)] as f32);
        let (au, bu, av, bv) = letterbox.map_or((1.0, 0.0, 1.0, 0.0), Letterbox::affine);
        HostCamera {
            r,
            t: std::array::from_fn(|i| cam.t[i] as f32),
            dist: cam.dist.map(|v| v as f32),
            intr: [cam.fx(), cam.skew(), cam.cx(), cam.fy(), cam.cy()].map(|v| v as f32),
            affine: [au, bu, av, bv].map(|v| v as f32),
        }
    }

    /// The model of `CameraTensors::project`: depth clamped to [`MIN_DEPTH`], normalised coordinates
    /// clamped to [`MAX_NORMALISED`], OpenCV distortion, intrinsics with skew, the letterbox.
    fn project(&self, p: &[f32]) -> Projected {
        let (r, t) = (&self.r, &self.t);
        let c: [f32; 3] = std::array::from_fn(|i| {
            r[3 * i] * p[0] + r[3 * i + 1] * p[1] + r[3 * i + 2] * p[2] + t[i]
        });
        let zs = c[2].max(MIN_DEPTH);
        let raw = [c[0] / zs, c[1] / zs];
        let kept = raw.map(|x| if x.abs() <= MAX_NORMALISED { 1.0 } else { 0.0 });
        let [xn, yn] = raw.map(|x| x.clamp(-MAX_NORMALISED, MAX_NORMALISED));
        let [k1, k2, p1, p2, k3] = self.dist;
        let r2 = xn * xn + yn * yn;
        let radial = ((k3 * r2 + k2) * r2 + k1) * r2 + 1.0;
        let d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
        let xd = xn * radial + p1 * xn * yn * 2.0 + p2 * (r2 + xn * xn * 2.0);
        let yd = yn * radial + p1 * (r2 + yn * yn * 2.0) + p2 * xn * yn * 2.0;
        // d(xd, yd) / d(xn, yn); the two cross terms are equal.
        let cross = 2.0 * xn * yn * d_radial + 2.0 * p1 * xn + 2.0 * p2 * yn;
        let dxd = [
            radial + 2.0 * xn * xn * d_radial + 2.0 * p1 * yn + 6.0 * p2 * xn,
            cross,
        ];
        let dyd = [
            cross,
            radial + 2.0 * yn * yn * d_radial + 6.0 * p1 * yn + 2.0 * p2 * xn,
        ];
        let [fx, s, cx, fy, cy] = self.intr;
        let [au, bu, av, bv] = self.affine;
        let u = (fx * xd + s * yd + cx) * au + bu;
        let v = (fy * yd + cy) * av + bv;
        let d_norm = [
            std::array::from_fn(|i| au * (fx * dxd[i] + s * dyd[i]) * kept[i]),
            std::array::from_fn(|i| av * fy * dyd[i] * kept[i]),
        ];
        Projected {
            uv: [u, v],
            d_norm,
            raw,
            zs,
            dz: if c[2] > MIN_DEPTH { 1.0 } else { 0.0 },
        }
    }
}

impl Projected {
    /// The gradient in the world point of `g` on `(u, v)`.
    fn pull(&self, r: &[f32; 9], g: [f32; 2]) -> [f32; 3] {
        let gn: [f32; 2] =
            std::array::from_fn(|i| g[0] * self.d_norm[0][i] + g[1] * self.d_norm[1][i]);
        let gc = [
            gn[0] / self.zs,
            gn[1] / self.zs,
            -(gn[0] * self.raw[0] + gn[1] * self.raw[1]) / self.zs * self.dz,
        ];
        std::array::from_fn(|j| r[j] * gc[0] + r[3 + j] * gc[1] + r[6 + j] * gc[2])
    }
}

/// What the pass needs besides the predicted points: every batch item's cameras, the true points'
/// pixels in each view and each point's weight there, divided by that view's normaliser (0 where the
/// true pixel is outside the image).
#[derive(Debug)]
pub struct Mesh2dPlan {
    /// `[B][V]`.
    cameras: Vec<Vec<HostCamera>>,
    /// Points per batch item.
    per_item: usize,
    /// `[V][B * per_item][2]`.
    truth: Vec<Vec<[f32; 2]>>,
    /// `[V][B * per_item]`.
    coeff: Vec<Vec<f32>>,
}

/// Points per task of the pass.
const CHUNK: usize = 2048;

impl Mesh2dPlan {
    /// `truth` and `weight` hold `[B, per_item, 3]` and `[B, per_item]` values; `cameras[b]` batch item
    /// `b`'s views; `size` the network input's side.
    pub fn new(cameras: Vec<Vec<HostCamera>>, truth: &[f32], weight: &[f32], size: f32) -> Self {
        let per_item = weight.len() / cameras.len().max(1);
        let views = cameras.first().map_or(0, Vec::len);
        let (truth, coeff) = (0..views)
            .map(|v| view(&cameras, v, per_item, truth, weight, size))
            .unzip();
        Mesh2dPlan {
            cameras,
            per_item,
            truth,
            coeff,
        }
    }

    /// The loss of `points` (`[B, per_item, 3]` values) and, with `grad`, its gradient in them.
    fn run(&self, points: &[f32], grad: bool) -> (f32, Option<Vec<f32>>) {
        let n = points.len() / 3;
        let mut g = grad.then(|| vec![0f32; n * 3]);
        let sums: Vec<f64> = match &mut g {
            Some(g) => g
                .par_chunks_mut(CHUNK * 3)
                .enumerate()
                .map(|(i, gc)| self.chunk(points, i, Some(gc)))
                .collect(),
            None => (0..n.div_ceil(CHUNK))
                .into_par_iter()
                .map(|i| self.chunk(points, i, None))
                .collect(),
        };
        // Summed in the chunks' order: the same value on any number of threads.
        (sums.iter().sum::<f64>() as f32, g)
    }

    /// The loss of chunk `i` of the points, its gradient written to `g` where given.
    fn chunk(&self, points: &[f32], i: usize, mut g: Option<&mut [f32]>) -> f64 {
        let start = i * CHUNK;
        let end = (start + CHUNK).min(points.len() / 3);
        let mut sum = 0f64;
        for m in start..end {
            let p = &points[3 * m..3 * m + 3];
            for (v, cam) in self.cameras[m / self.per_item].iter().enumerate() {
                let c = self.coeff[v][m];
                if c == 0.0 {
                    continue;
                }
                let q = cam.project(p);
                let d = [q.uv[0] - self.truth[v][m][0], q.uv[1] - self.truth[v][m][1]];
                sum += (c * (d[0].abs() + d[1].abs())) as f64;
                if let Some(g) = g.as_deref_mut() {
                    let sign = d.map(|x| if x == 0.0 { 0.0 } else { c * x.signum() });
                    let gp = q.pull(&cam.r, sign);
                    let o = 3 * (m - start);
                    (0..3).for_each(|j| g[o + j] += gp[j]);
                }
            }
        }
        sum
    }
}

/// View `v`'s true pixels and each point's weight divided by the view's normaliser.
fn view(
    cameras: &[Vec<HostCamera>],
    v: usize,
    per_item: usize,
    truth: &[f32],
    weight: &[f32],
    size: f32,
) -> (Vec<[f32; 2]>, Vec<f32>) {
    let inside = |x: f32| (0.0..size).contains(&x);
    let (pix, mut w): (Vec<[f32; 2]>, Vec<f32>) = truth
        .chunks_exact(3)
        .zip(weight)
        .enumerate()
        .map(|(m, (p, &w))| {
            let q = cameras[m / per_item][v].project(p).uv;
            (q, if q.iter().all(|&x| inside(x)) { w } else { 0.0 })
        })
        .unzip();
    let norm = (w.iter().map(|&x| x as f64).sum::<f64>() * 2.0).max(1.0);
    w.iter_mut().for_each(|x| *x = (*x as f64 / norm) as f32);
    (pix, w)
}

/// The loss of `points [B, K, N, 3]` with the pass (see [`crate::mesh_2d_loss_views`]).
pub(crate) fn loss(points: Tensor<4>, plan: Mesh2dPlan) -> Tensor<1> {
    Tensor::from_dispatch(<Dispatch as Mesh2dBackend>::mesh_2d_views(
        points.into_dispatch(),
        Arc::new(plan),
    ))
}

/// The backend side of [`loss`]: flex runs the pass; autodiff keeps its gradient for the backward.
#[backend_extension(Flex, Autodiff)]
pub trait Mesh2dBackend: Backend {
    fn mesh_2d_views(points: FloatTensor<Self>, plan: Arc<Mesh2dPlan>) -> FloatTensor<Self> {
        let device = points.device();
        let (loss, _) = plan.run(&HostF32::read::<Self>(points), false);
        Self::float_from_data(TensorData::new(vec![loss], [1]), &device)
    }
}

impl Mesh2dBackend for Flex {}

impl<B: Backend + Mesh2dBackend, C: CheckpointStrategy> Mesh2dBackend for Autodiff<B, C> {
    fn mesh_2d_views(points: FloatTensor<Self>, plan: Arc<Mesh2dPlan>) -> FloatTensor<Self> {
        let guards = [points.node()];
        let points = points.into_primitive();
        let device = points.device();
        let shape: [usize; 4] = dims(&points);
        let tracked = Mesh2dBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful();
        let track = matches!(tracked, OpsKind::Tracked(_));
        let (loss, grad) = plan.run(&HostF32::read::<B>(points), track);
        let out = B::float_from_data(TensorData::new(vec![loss], [1]), &device);
        match tracked {
            OpsKind::Tracked(prep) => {
                let grad = grad.expect("computed when tracked");
                prep.finish(Saved { grad, shape }, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

#[derive(Debug)]
struct Mesh2dBackward;

/// The loss's gradient in the points, formed by the forward.
#[derive(Debug, Clone)]
struct Saved {
    grad: Vec<f32>,
    shape: [usize; 4],
}

impl<B: Backend> Backward<B, 1> for Mesh2dBackward {
    type State = Saved;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let upstream = grads.consume::<B>(&ops.node);
        let [parent] = ops.parents;
        let Some(node) = parent else { return };
        let Saved { mut grad, shape } = ops.state;
        let device = upstream.device();
        let scale = HostF32::read::<B>(upstream)[0];
        grad.par_iter_mut().for_each(|x| *x *= scale);
        let out = B::float_from_data(TensorData::new(grad, shape), &device);
        grads.register::<B>(node.id, out);
    }
}
