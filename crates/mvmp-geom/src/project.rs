//! Batched, differentiable projection of world points into many cameras (tensor op for the model).
//!
//! The same model as [`crate::Camera::project`]: `x_cam = R x + t`, normalised coordinates, OpenCV
//! distortion, intrinsics with skew, and optionally the letterbox affine into network pixels.
use burn::tensor::{Bool, Device, Tensor, TensorData};

use crate::{Camera, Letterbox};

/// Normalised coordinates beyond this magnitude (about 76 degrees off-axis) count as not seen: the
/// polynomial distortion model is meaningless there and can fold far-away points back into the image.
pub const MAX_NORMALISED: f32 = 4.0;
/// Points closer to the camera plane than this (metres) count as not seen.
pub const MIN_DEPTH: f32 = 1e-3;

/// Camera parameters of a rig as tensors: `C` cameras.
#[derive(Debug, Clone)]
pub struct CameraTensors {
    /// `[C, 3, 3]` world-to-camera rotations.
    pub r: Tensor<3>,
    /// `[C, 1, 3]` translations.
    pub t: Tensor<3>,
    /// `[C, 1, 5]` distortion `[k1, k2, p1, p2, k3]`.
    pub dist: Tensor<3>,
    /// `[C, 1, 5]` intrinsics `[fx, skew, cx, fy, cy]`.
    pub intr: Tensor<3>,
    /// `[C, 1, 4]` output affine `[a_u, b_u, a_v, b_v]` (identity without a letterbox).
    pub affine: Tensor<3>,
    /// `[C, 1, 2]` original image size `[W, H]`.
    pub size: Tensor<3>,
}

/// Output of [`CameraTensors::project`].
#[derive(Debug, Clone)]
pub struct Projection {
    /// `[C, P, 2]` pixel coordinates (network pixels when a letterbox was given).
    pub uv: Tensor<3>,
    /// `[C, P]` depth along the optical axis.
    pub depth: Tensor<2>,
    /// `[C, P]` in front of the camera, within [`MAX_NORMALISED`], and inside the original image
    /// (`-0.5 <= u < W - 0.5`, same for v).
    pub visible: Tensor<2, Bool>,
}

impl CameraTensors {
    /// Cameras as tensors; `letterboxes`, when given, holds one letterbox per camera.
    pub fn new(cameras: &[Camera], letterboxes: Option<&[Letterbox]>, device: &Device) -> Self {
        let c = cameras.len();
        let mut r = Vec::with_capacity(c * 9);
        let mut t = Vec::with_capacity(c * 3);
        let mut dist = Vec::with_capacity(c * 5);
        let mut intr = Vec::with_capacity(c * 5);
        let mut affine = Vec::with_capacity(c * 4);
        let mut size = Vec::with_capacity(c * 2);
        for (i, cam) in cameras.iter().enumerate() {
            for a in 0..3 {
                for b in 0..3 {
                    r.push(cam.r[(a, b)] as f32);
                }
                t.push(cam.t[a] as f32);
            }
            dist.extend(cam.dist.iter().map(|v| *v as f32));
            intr.extend([cam.fx(), cam.skew(), cam.cx(), cam.fy(), cam.cy()].map(|v| v as f32));
            let aff = match letterboxes {
                Some(lb) => {
                    let (au, bu, av, bv) = lb[i].affine();
                    [au, bu, av, bv]
                }
                None => [1.0, 0.0, 1.0, 0.0],
            };
            affine.extend(aff.map(|v| v as f32));
            size.extend([cam.width as f32, cam.height as f32]);
        }
        let mk =
            |v: Vec<f32>, shape: [usize; 3]| Tensor::from_data(TensorData::new(v, shape), device);
        CameraTensors {
            r: mk(r, [c, 3, 3]),
            t: mk(t, [c, 1, 3]),
            dist: mk(dist, [c, 1, 5]),
            intr: mk(intr, [c, 1, 5]),
            affine: mk(affine, [c, 1, 4]),
            size: mk(size, [c, 1, 2]),
        }
    }

    pub fn num_cameras(&self) -> usize {
        self.r.dims()[0]
    }

    /// Project world points `[P, 3]` into every camera. Differentiable in the points.
    pub fn project(&self, points: Tensor<2>) -> Projection {
        let p = points.dims()[0];
        let c = self.num_cameras();
        let e = |t: &Tensor<3>, i: usize| t.clone().narrow(2, i, 1); // [C, 1, 1]
        // [1, P, 3] x [C, 3, 3]^T -> [C, P, 3]
        let cam = points
            .unsqueeze_dim::<3>(0)
            .matmul(self.r.clone().swap_dims(1, 2))
            + self.t.clone();
        let x = cam.clone().narrow(2, 0, 1);
        let y = cam.clone().narrow(2, 1, 1);
        let z = cam.narrow(2, 2, 1); // [C, P, 1]
        let front = z.clone().greater_elem(MIN_DEPTH);
        let zs = z.clone().clamp_min(MIN_DEPTH);
        let xn = x / zs.clone();
        let yn = y / zs;
        let in_range = xn
            .clone()
            .abs()
            .lower_equal_elem(MAX_NORMALISED)
            .bool_and(yn.clone().abs().lower_equal_elem(MAX_NORMALISED));
        // Clamp so that points that are not seen still give finite values (and finite gradients).
        let xn = xn.clamp(-MAX_NORMALISED, MAX_NORMALISED);
        let yn = yn.clamp(-MAX_NORMALISED, MAX_NORMALISED);
        let (k1, k2, p1, p2, k3) = (
            e(&self.dist, 0),
            e(&self.dist, 1),
            e(&self.dist, 2),
            e(&self.dist, 3),
            e(&self.dist, 4),
        );
        let r2 = xn.clone().powi_scalar(2) + yn.clone().powi_scalar(2);
        let radial = (((k3 * r2.clone() + k2) * r2.clone() + k1) * r2.clone()) + 1.0;
        let xy = xn.clone() * yn.clone();
        let xd = xn.clone() * radial.clone()
            + p1.clone() * xy.clone() * 2.0
            + p2.clone() * (r2.clone() + xn.clone().powi_scalar(2) * 2.0);
        let yd = yn.clone() * radial + p1 * (r2 + yn.powi_scalar(2) * 2.0) + p2 * xy * 2.0;
        let u = e(&self.intr, 0) * xd + e(&self.intr, 1) * yd.clone() + e(&self.intr, 2);
        let v = e(&self.intr, 3) * yd + e(&self.intr, 4);
        let w = e(&self.size, 0);
        let h = e(&self.size, 1);
        let inside = u
            .clone()
            .greater_equal_elem(-0.5)
            .bool_and((u.clone() - w + 0.5).lower_elem(0.0))
            .bool_and(v.clone().greater_equal_elem(-0.5))
            .bool_and((v.clone() - h + 0.5).lower_elem(0.0));
        let visible = front.bool_and(in_range).bool_and(inside).reshape([c, p]);
        let u = u * e(&self.affine, 0) + e(&self.affine, 1);
        let v = v * e(&self.affine, 2) + e(&self.affine, 3);
        Projection {
            uv: Tensor::cat(vec![u, v], 2),
            depth: z.reshape([c, p]),
            visible,
        }
    }
}
