//! The letterbox transform: an image of W0 x H0 is resized with its aspect ratio kept to fit S x S and
//! padded with zeros, centred. The map from original pixels to network pixels is the affine
//! `u' = sx (u + 0.5) - 0.5 + ox`, `v' = sy (v + 0.5) - 0.5 + oy` (pixel centres kept), built from the integer
//! content size the resize really produces, so it mirrors the image pipeline exactly.
use nalgebra::Vector2;

use crate::GeomError;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Letterbox {
    /// Original image size.
    pub src_width: u32,
    pub src_height: u32,
    /// Network input size S.
    pub size: u32,
    /// Content size inside the S x S canvas.
    pub content_width: u32,
    pub content_height: u32,
    /// Integer offsets of the content in the canvas.
    pub offset_x: u32,
    pub offset_y: u32,
}

impl Letterbox {
    /// The letterbox of a `w0 x h0` image into `size x size`.
    pub fn new(w0: u32, h0: u32, size: u32) -> Result<Self, GeomError> {
        if w0 == 0 || h0 == 0 || size == 0 {
            return Err(GeomError::InvalidLetterbox(format!(
                "sizes must be positive, got image {w0} x {h0} and target {size}"
            )));
        }
        let scale = size as f64 / w0.max(h0) as f64;
        let cw = ((w0 as f64 * scale).round() as u32).clamp(1, size);
        let ch = ((h0 as f64 * scale).round() as u32).clamp(1, size);
        Ok(Letterbox {
            src_width: w0,
            src_height: h0,
            size,
            content_width: cw,
            content_height: ch,
            offset_x: (size - cw) / 2,
            offset_y: (size - ch) / 2,
        })
    }

    /// Horizontal and vertical scale factors `Wc / W0`, `Hc / H0`.
    pub fn scale(&self) -> (f64, f64) {
        (
            self.content_width as f64 / self.src_width as f64,
            self.content_height as f64 / self.src_height as f64,
        )
    }

    /// The affine as `(a_u, b_u, a_v, b_v)` with `u' = a_u u + b_u`, `v' = a_v v + b_v`.
    pub fn affine(&self) -> (f64, f64, f64, f64) {
        let (sx, sy) = self.scale();
        (
            sx,
            0.5 * sx - 0.5 + self.offset_x as f64,
            sy,
            0.5 * sy - 0.5 + self.offset_y as f64,
        )
    }

    /// Original pixel to network pixel.
    pub fn apply(&self, uv: Vector2<f64>) -> Vector2<f64> {
        let (au, bu, av, bv) = self.affine();
        Vector2::new(au * uv.x + bu, av * uv.y + bv)
    }

    /// Network pixel to original pixel.
    pub fn invert(&self, uv: Vector2<f64>) -> Vector2<f64> {
        let (au, bu, av, bv) = self.affine();
        Vector2::new((uv.x - bu) / au, (uv.y - bv) / av)
    }
}
