//! A calibrated pinhole camera with Brown-Conrady distortion, in OpenCV's convention.
use nalgebra::{Matrix3, Vector2, Vector3};

use crate::GeomError;
use crate::error::CameraPart;

/// Tolerance on `R^T R = I` (largest absolute entry of the difference) accepted by [`Camera::new`].
/// Calibration files print rotations with 6-10 digits; 1e-5 accepts those and rejects real errors.
pub const ROTATION_TOLERANCE: f64 = 1e-5;

/// Farthest a camera centre may be from the world origin (metres): 100 km. Capture rigs span metres to
/// hundreds of metres; a centre beyond this is a unit mistake or a broken file, and pictures and grids
/// sized to it would not fit in memory.
pub const MAX_CENTRE_DISTANCE: f64 = 1e5;

/// Widest and tallest image a camera may have (pixels): ten times the 4K a capture rig records, so that
/// a picture of the rig's frames stays within memory.
pub const MAX_IMAGE_SIDE: u32 = 40_000;

/// Largest magnitude of an entry of K (pixels): a telephoto lens on a large sensor has a focal length
/// of some 10^4 to 10^5 pixels.
pub const MAX_INTRINSIC: f64 = 1e7;

/// Largest magnitude of a lens distortion coefficient: real lenses' k1..k3, p1, p2 are well inside it.
pub const MAX_DISTORTION: f64 = 1e4;

/// A calibrated camera. `x_cam = R x_world + t` (metres); pixels follow
/// `u = fx*xd + skew*yd + cx`, `v = fy*yd + cy` with `(xd, yd)` the distorted normalised coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// A name for messages (for example "00_03" or "54138969").
    pub name: String,
    /// Intrinsics: `[[fx, skew, cx], [0, fy, cy], [0, 0, 1]]`.
    pub k: Matrix3<f64>,
    /// World-to-camera rotation.
    pub r: Matrix3<f64>,
    /// World-to-camera translation (metres).
    pub t: Vector3<f64>,
    /// Distortion `[k1, k2, p1, p2, k3]` (OpenCV order and tangential form).
    pub dist: [f64; 5],
    /// Image width and height in pixels.
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// Build and validate a camera: finite values, positive focal lengths, `K[1][0] = K[2][0] = K[2][1] = 0`
    /// and `K[2][2] = 1`, `R` orthonormal within [`ROTATION_TOLERANCE`] with determinant +1, non-zero size.
    pub fn new(
        name: impl Into<String>,
        k: Matrix3<f64>,
        r: Matrix3<f64>,
        t: Vector3<f64>,
        dist: [f64; 5],
        width: u32,
        height: u32,
    ) -> Result<Self, GeomError> {
        let cam = Camera {
            name: name.into(),
            k,
            r,
            t,
            dist,
            width,
            height,
        };
        cam.validate()?;
        Ok(cam)
    }

    fn invalid(&self, part: CameraPart, what: String) -> GeomError {
        GeomError::InvalidCamera {
            camera: self.name.clone(),
            part,
            what,
        }
    }

    /// Check the invariants listed on [`Camera::new`].
    pub fn validate(&self) -> Result<(), GeomError> {
        for (what, part, vals) in [
            ("K", CameraPart::Intrinsics, self.k.as_slice()),
            ("R", CameraPart::Rotation, self.r.as_slice()),
            ("t", CameraPart::Translation, self.t.as_slice()),
            ("dist", CameraPart::Distortion, &self.dist[..]),
        ] {
            if let Some(v) = vals.iter().find(|v| !v.is_finite()) {
                return Err(self.invalid(part, format!("{what} holds a non-finite value ({v})")));
            }
        }
        if let Some(v) = self.k.iter().find(|v| v.abs() > MAX_INTRINSIC) {
            return Err(self.invalid(CameraPart::Intrinsics, format!(
                "K holds {v:?}; focal lengths, skew and principal point are within +-{MAX_INTRINSIC:.0e} \
                 pixels"
            )));
        }
        let (fx, fy) = (self.k[(0, 0)], self.k[(1, 1)]);
        if fx <= 0.0 || fy <= 0.0 {
            return Err(self.invalid(
                CameraPart::Intrinsics,
                format!("K: focal lengths must be positive, got fx = {fx}, fy = {fy}"),
            ));
        }
        let bottom = [self.k[(1, 0)], self.k[(2, 0)], self.k[(2, 1)]];
        if bottom.iter().any(|v| *v != 0.0) || self.k[(2, 2)] != 1.0 {
            return Err(self.invalid(
                CameraPart::Intrinsics,
                format!(
                    "K must be upper triangular with K[2][2] = 1, got rows {:?}",
                    [
                        self.k.row(1).iter().collect::<Vec<_>>(),
                        self.k.row(2).iter().collect()
                    ]
                ),
            ));
        }
        let err = (self.r.transpose() * self.r - Matrix3::identity())
            .abs()
            .max();
        if err > ROTATION_TOLERANCE {
            return Err(self.invalid(CameraPart::Rotation, format!(
                "R is not orthonormal: max |R^T R - I| = {err:.3e} (tolerance {ROTATION_TOLERANCE:.0e})"
            )));
        }
        let det = self.r.determinant();
        if det <= 0.0 {
            return Err(self.invalid(
                CameraPart::Rotation,
                format!("R has determinant {det:.6}, expected +1"),
            ));
        }
        let side = 1..=MAX_IMAGE_SIDE;
        if !(side.contains(&self.width) && side.contains(&self.height)) {
            return Err(self.invalid(CameraPart::ImageSize, format!(
                "image size (resolution) must be 1 to {MAX_IMAGE_SIDE} pixels a side, got {} x {}",
                self.width, self.height
            )));
        }
        let centre = self.centre().norm();
        if centre > MAX_CENTRE_DISTANCE {
            return Err(self.invalid(CameraPart::Placement, format!(
                "R and t put the camera {centre:.3e} m from the origin; a rig's cameras are within \
                 {MAX_CENTRE_DISTANCE:.0e} m (metres expected)"
            )));
        }
        if let Some(k) = self.dist.iter().find(|k| k.abs() > MAX_DISTORTION) {
            return Err(self.invalid(CameraPart::Distortion, format!(
                "dist holds {k:?}; lens distortion coefficients are within +-{MAX_DISTORTION:.0e}"
            )));
        }
        Ok(())
    }

    pub fn fx(&self) -> f64 {
        self.k[(0, 0)]
    }
    pub fn fy(&self) -> f64 {
        self.k[(1, 1)]
    }
    pub fn cx(&self) -> f64 {
        self.k[(0, 2)]
    }
    pub fn cy(&self) -> f64 {
        self.k[(1, 2)]
    }
    pub fn skew(&self) -> f64 {
        self.k[(0, 1)]
    }

    /// The camera centre in world coordinates, `-R^T t`.
    pub fn centre(&self) -> Vector3<f64> {
        -(self.r.transpose() * self.t)
    }

    /// World point to camera coordinates.
    pub fn to_camera(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.r * x + self.t
    }

    /// Apply the distortion model to normalised coordinates `(x, y) = (X/Z, Y/Z)`.
    pub fn distort(&self, p: Vector2<f64>) -> Vector2<f64> {
        distort(&self.dist, p)
    }

    /// Distorted normalised coordinates to pixels (intrinsics with skew).
    pub fn normalised_to_pixel(&self, d: Vector2<f64>) -> Vector2<f64> {
        Vector2::new(
            self.fx() * d.x + self.skew() * d.y + self.cx(),
            self.fy() * d.y + self.cy(),
        )
    }

    /// Pixels to distorted normalised coordinates (inverse of [`Camera::normalised_to_pixel`]).
    pub fn pixel_to_normalised(&self, uv: Vector2<f64>) -> Vector2<f64> {
        let y = (uv.y - self.cy()) / self.fy();
        let x = (uv.x - self.cx() - self.skew() * y) / self.fx();
        Vector2::new(x, y)
    }

    /// Project a world point to pixels with distortion. Returns the pixel and the camera depth `z_cam`;
    /// the pixel is meaningless when the depth is not positive.
    pub fn project(&self, x: &Vector3<f64>) -> (Vector2<f64>, f64) {
        let c = self.to_camera(x);
        let n = Vector2::new(c.x / c.z, c.y / c.z);
        (self.normalised_to_pixel(self.distort(n)), c.z)
    }

    /// Whether a pixel lies in the image under the pixel-centre convention:
    /// `-0.5 <= u < W - 0.5` and `-0.5 <= v < H - 0.5`.
    pub fn contains(&self, uv: Vector2<f64>) -> bool {
        uv.x >= -0.5
            && uv.x < self.width as f64 - 0.5
            && uv.y >= -0.5
            && uv.y < self.height as f64 - 0.5
    }

    /// Undo the distortion of normalised coordinates by Newton's method on the forward model. Returns
    /// `None` when it does not converge (far outside the region where the model is invertible).
    pub fn undistort(&self, d: Vector2<f64>) -> Option<Vector2<f64>> {
        undistort(&self.dist, d)
    }

    /// Back-project a pixel to a world ray: the camera centre and a unit direction. The ray passes through
    /// every world point that projects to this pixel in front of the camera.
    pub fn back_project(&self, uv: Vector2<f64>) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let n = self.undistort(self.pixel_to_normalised(uv))?;
        let dir_cam = Vector3::new(n.x, n.y, 1.0);
        let dir = (self.r.transpose() * dir_cam).normalize();
        Some((self.centre(), dir))
    }
}

/// The OpenCV Brown-Conrady model on normalised coordinates.
pub fn distort(dist: &[f64; 5], p: Vector2<f64>) -> Vector2<f64> {
    let [k1, k2, p1, p2, k3] = *dist;
    let (x, y) = (p.x, p.y);
    let r2 = x * x + y * y;
    let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    Vector2::new(
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    )
}

/// Inverse of [`distort`] by Newton's method with the analytic Jacobian.
pub fn undistort(dist: &[f64; 5], d: Vector2<f64>) -> Option<Vector2<f64>> {
    let [k1, k2, p1, p2, k3] = *dist;
    let mut p = d;
    for _ in 0..50 {
        let f = distort(dist, p) - d;
        if f.norm() < 1e-14 {
            return Some(p);
        }
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        // d(radial)/d(r2)
        let dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
        let j00 = radial + x * dr * 2.0 * x + 2.0 * p1 * y + p2 * 6.0 * x;
        let j01 = x * dr * 2.0 * y + 2.0 * p1 * x + p2 * 2.0 * y;
        let j10 = y * dr * 2.0 * x + p1 * 2.0 * x + 2.0 * p2 * y;
        let j11 = radial + y * dr * 2.0 * y + p1 * 6.0 * y + 2.0 * p2 * x;
        let det = j00 * j11 - j01 * j10;
        if det.abs() < 1e-12 || !det.is_finite() {
            return None;
        }
        p -= Vector2::new(j11 * f.x - j01 * f.y, -j10 * f.x + j00 * f.y) / det;
    }
    let f = distort(dist, p) - d;
    (f.norm() < 1e-9).then_some(p)
}
