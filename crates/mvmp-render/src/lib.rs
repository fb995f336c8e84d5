//! A z-buffered software rasterizer for triangle meshes seen by a [`Camera`]: Lambert shading from a
//! directional light, per-pixel depth and the index of the mesh that covers each pixel. Vertices are
//! projected with the full camera model (distortion included); triangles are filled in image space with
//! perspective-correct depth.
use nalgebra::{Vector2, Vector3};

use mvmp_geom::Camera;

/// How far outside a triangle (in barycentric terms) a pixel centre may lie and still be filled. A pixel
/// centre on an edge two triangles share can come out a hair outside both (rounding); without the
/// margin a square seen face-on lost 10 of the 51 pixels along its diagonal.
const EDGE: f64 = -1e-9;

/// One mesh to draw.
pub struct MeshRef<'a> {
    pub vertices: &'a [[f32; 3]],
    pub faces: &'a [[u32; 3]],
    /// Base colour (linear 0..1).
    pub color: [f32; 3],
    /// Optional per-face colours, overriding `color`.
    pub face_colors: Option<&'a [[f32; 3]]>,
}

/// A directional light plus an ambient term, with a colour.
#[derive(Debug, Clone, Copy)]
pub struct Light {
    /// Direction the light travels (world).
    pub dir: [f32; 3],
    /// Ambient fraction, 0..1.
    pub ambient: f32,
    /// Light colour and intensity.
    pub color: [f32; 3],
}

/// Rendered buffers, row-major `height x width`.
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// RGB, 0..1.
    pub rgb: Vec<[f32; 3]>,
    /// Depth along the optical axis (metres); `f32::INFINITY` where nothing was drawn.
    pub depth: Vec<f32>,
    /// Index of the mesh drawn at each pixel, or -1.
    pub mesh: Vec<i32>,
}

impl Frame {
    pub fn new(width: u32, height: u32, background: [f32; 3]) -> Self {
        let n = (width * height) as usize;
        Frame {
            width,
            height,
            rgb: vec![background; n],
            depth: vec![f32::INFINITY; n],
            mesh: vec![-1; n],
        }
    }

    /// 8-bit sRGB-ish bytes (gamma 2.2), row-major RGB.
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.rgb
            .iter()
            .flat_map(|c| c.map(|v| (v.clamp(0.0, 1.0).powf(1.0 / 2.2) * 255.0).round() as u8))
            .collect()
    }
}

/// Draw meshes into a frame (z-buffered against what the frame already holds).
pub fn draw(frame: &mut Frame, camera: &Camera, meshes: &[MeshRef], light: &Light) {
    let ld = light.dir;
    let l = Vector3::new(ld[0] as f64, ld[1] as f64, ld[2] as f64).normalize();
    let ambient = light.ambient as f64;
    let centre = camera.centre();
    let (w, h) = (frame.width as i64, frame.height as i64);
    for (mi, m) in meshes.iter().enumerate() {
        let proj: Vec<(Vector2<f64>, f64)> = m
            .vertices
            .iter()
            .map(|v| camera.project(&Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)))
            .collect();
        for (fi, f) in m.faces.iter().enumerate() {
            let idx = f.map(|i| i as usize);
            let [(p0, z0), (p1, z1), (p2, z2)] = idx.map(|i| proj[i]);
            if z0 <= 1e-3 || z1 <= 1e-3 || z2 <= 1e-3 {
                continue;
            }
            let wv = idx.map(|i| {
                let v = m.vertices[i];
                Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)
            });
            let mut n = (wv[1] - wv[0]).cross(&(wv[2] - wv[0]));
            if n.norm() == 0.0 {
                continue;
            }
            n = n.normalize();
            // Two-sided: light the side that faces the camera.
            if n.dot(&(centre - wv[0])) < 0.0 {
                n = -n;
            }
            let shade = (ambient + (1.0 - ambient) * (-n.dot(&l)).max(0.0)) as f32;
            let base = m.face_colors.map_or(m.color, |c| c[fi]);
            let color = std::array::from_fn(|k| base[k] * shade * light.color[k]);
            let area = (p1 - p0).perp(&(p2 - p0));
            if area.abs() < 1e-12 {
                continue;
            }
            let xmin = p0.x.min(p1.x).min(p2.x).floor().max(0.0) as i64;
            let xmax = (p0.x.max(p1.x).max(p2.x).ceil() as i64).min(w - 1);
            let ymin = p0.y.min(p1.y).min(p2.y).floor().max(0.0) as i64;
            let ymax = (p0.y.max(p1.y).max(p2.y).ceil() as i64).min(h - 1);
            for y in ymin..=ymax {
                for x in xmin..=xmax {
                    let p = Vector2::new(x as f64, y as f64);
                    let b0 = (p1 - p).perp(&(p2 - p)) / area;
                    let b1 = (p2 - p).perp(&(p0 - p)) / area;
                    let b2 = 1.0 - b0 - b1;
                    if b0 < EDGE || b1 < EDGE || b2 < EDGE {
                        continue;
                    }
                    // Perspective-correct depth: 1/z is affine in screen space.
                    let z = 1.0 / (b0 / z0 + b1 / z1 + b2 / z2);
                    let k = (y * w + x) as usize;
                    if (z as f32) < frame.depth[k] {
                        frame.depth[k] = z as f32;
                        frame.rgb[k] = color;
                        frame.mesh[k] = mi as i32;
                    }
                }
            }
        }
    }
}

/// Pixels covered by a mesh's projection (its whole silhouette, no depth test), counting only pixels inside
/// a `width x height` image. Triangles with a vertex behind the camera are skipped.
pub fn coverage(
    camera: &Camera,
    vertices: &[[f32; 3]],
    faces: &[[u32; 3]],
    width: u32,
    height: u32,
) -> u32 {
    let proj: Vec<(Vector2<f64>, f64)> = vertices
        .iter()
        .map(|v| camera.project(&Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)))
        .collect();
    // The bounding box of the visible projections bounds the buffer.
    let (mut x0, mut y0, mut x1, mut y1) = (i64::MAX, i64::MAX, i64::MIN, i64::MIN);
    for (p, z) in &proj {
        if *z > 1e-3 {
            x0 = x0.min(p.x.floor() as i64);
            y0 = y0.min(p.y.floor() as i64);
            x1 = x1.max(p.x.ceil() as i64);
            y1 = y1.max(p.y.ceil() as i64);
        }
    }
    let (x0, y0) = (x0.max(0), y0.max(0));
    let (x1, y1) = (x1.min(width as i64 - 1), y1.min(height as i64 - 1));
    if x0 > x1 || y0 > y1 {
        return 0;
    }
    let bw = (x1 - x0 + 1) as usize;
    let mut hit = vec![false; bw * (y1 - y0 + 1) as usize];
    for f in faces {
        let [(p0, z0), (p1, z1), (p2, z2)] = f.map(|i| proj[i as usize]);
        if z0 <= 1e-3 || z1 <= 1e-3 || z2 <= 1e-3 {
            continue;
        }
        let area = (p1 - p0).perp(&(p2 - p0));
        if area.abs() < 1e-12 {
            continue;
        }
        let xa = (p0.x.min(p1.x).min(p2.x).floor() as i64).max(x0);
        let xb = (p0.x.max(p1.x).max(p2.x).ceil() as i64).min(x1);
        let ya = (p0.y.min(p1.y).min(p2.y).floor() as i64).max(y0);
        let yb = (p0.y.max(p1.y).max(p2.y).ceil() as i64).min(y1);
        for y in ya..=yb {
            for x in xa..=xb {
                let p = Vector2::new(x as f64, y as f64);
                let b0 = (p1 - p).perp(&(p2 - p)) / area;
                let b1 = (p2 - p).perp(&(p0 - p)) / area;
                if b0 >= EDGE && b1 >= EDGE && 1.0 - b0 - b1 >= EDGE {
                    hit[(y - y0) as usize * bw + (x - x0) as usize] = true;
                }
            }
        }
    }
    hit.iter().filter(|h| **h).count() as u32
}
