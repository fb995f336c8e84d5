//! What inference writes for a frame, and reading it back (so `mvmp eval --predictions` can score any
//! method's results stored this way):
//!
//! ```text
//! FRAME_OUT/
//!   people.npz          per person the standard smplx keys, pelvis and score (`mvmp_smplx::people`)
//!   person_XX.obj/.ply  each mesh in world coordinates (metres, z up)
//!   overlay_VV.png      the meshes drawn over view VV
//!   topdown.png         the capture area from above: each person's position and heading, the cameras
//! ```
use std::path::Path;

use image::{Rgb, RgbImage};
use mvmp_geom::{Camera, VoxelGrid};
use mvmp_io::write_atomic_with;
use mvmp_render::{Frame, Light, MeshRef, draw};
pub use mvmp_smplx::people::{StoredPerson, read_people_npz};
use nalgebra::Vector3;

use crate::InferError;
use crate::predictor::PersonPrediction;

/// Person colours (linear RGB), shared by overlays and the top-down view.
pub const PALETTE: [[f32; 3]; 8] = [
    [0.90, 0.35, 0.25],
    [0.25, 0.55, 0.90],
    [0.35, 0.80, 0.35],
    [0.95, 0.75, 0.20],
    [0.70, 0.40, 0.85],
    [0.20, 0.80, 0.80],
    [0.95, 0.50, 0.70],
    [0.60, 0.60, 0.60],
];

/// Write `people.npz` (atomically) for predicted people.
pub fn write_people_npz(path: &Path, people: &[PersonPrediction]) -> Result<(), InferError> {
    let stored: Vec<StoredPerson> = people.iter().map(PersonPrediction::stored).collect();
    Ok(mvmp_smplx::people::write_people_npz(path, &stored)?)
}

/// Blend the people's meshes over an image seen by `camera` (same size as the camera's image).
pub fn overlay(
    image: &RgbImage,
    camera: &Camera,
    people: &[PersonPrediction],
    faces: &[[u32; 3]],
) -> RgbImage {
    let mut frame = Frame::new(camera.width, camera.height, [0.0; 3]);
    let meshes: Vec<MeshRef> = people
        .iter()
        .enumerate()
        .map(|(i, p)| MeshRef {
            vertices: &p.vertices,
            faces,
            color: PALETTE[i % PALETTE.len()],
            face_colors: None,
        })
        .collect();
    // Light from behind the camera, so what the camera sees is lit.
    let axis = camera.r.row(2).transpose();
    let light = Light {
        dir: [axis[0] as f32, axis[1] as f32, axis[2] as f32 - 0.5],
        ambient: 0.3,
        color: [1.0; 3],
    };
    draw(&mut frame, camera, &meshes, &light);
    let shaded = frame.to_rgb8();
    let mut out = image.clone();
    for (i, px) in out.pixels_mut().enumerate() {
        if frame.mesh[i] >= 0 {
            for c in 0..3 {
                let m = shaded[i * 3 + c] as f32;
                px.0[c] = (0.35 * px.0[c] as f32 + 0.65 * m).round() as u8;
            }
        }
    }
    out
}

/// The forward (facing) direction on the ground of a person from their joints: the orientation vector
/// `(J_lhip - J_rhip) x (J_spine1 - J_pelvis)` of the losses, projected to the xy-plane and normalised.
pub fn heading(joints: &[[f32; 3]]) -> Option<[f64; 2]> {
    let j = |i: usize| {
        Vector3::new(
            joints[i][0] as f64,
            joints[i][1] as f64,
            joints[i][2] as f64,
        )
    };
    let o = (j(1) - j(2)).cross(&(j(3) - j(0)));
    let n = (o.x * o.x + o.y * o.y).sqrt();
    (n > 1e-9).then(|| [o.x / n, o.y / n])
}

/// A top-down picture (`size` pixels square) of `grid`'s ground area: a 1 m grid (coarser when the
/// cameras stand more than 100 m apart), the cameras (grey squares), each person as a disc at the
/// pelvis with a heading stroke, in the overlay colours.
pub fn topdown(
    grid: &VoxelGrid,
    cameras: &[Camera],
    people: &[PersonPrediction],
    size: u32,
) -> RgbImage {
    let mut img = RgbImage::from_pixel(size, size, Rgb([248, 248, 245]));
    let view = TopView::fit(grid, cameras, size);
    view.draw_ground(&mut img);
    // The grid's area.
    let (x0, x1) = (
        grid.center[0] - grid.size[0] / 2.0,
        grid.center[0] + grid.size[0] / 2.0,
    );
    let (y0, y1) = (
        grid.center[1] - grid.size[1] / 2.0,
        grid.center[1] + grid.size[1] / 2.0,
    );
    let corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)].map(|(x, y)| view.to_px(x, y));
    for i in 0..4 {
        line(
            &mut img,
            corners[i],
            corners[(i + 1) % 4],
            2.0,
            Rgb([150, 150, 145]),
        );
    }
    for c in cameras {
        let p = c.centre();
        disc(&mut img, view.to_px(p.x, p.y), 5.0, Rgb([90, 90, 90]));
    }
    let r = (0.25 * view.scale).max(3.0);
    for (i, p) in people.iter().enumerate() {
        let col = PALETTE[i % PALETTE.len()].map(|c| (c.powf(1.0 / 2.2) * 255.0) as u8);
        let (u, v) = view.to_px(p.pelvis[0] as f64, p.pelvis[1] as f64);
        disc(&mut img, (u, v), r, Rgb(col));
        if let Some(h) = heading(&p.joints) {
            let tip = view.to_px(
                p.pelvis[0] as f64 + 0.6 * h[0],
                p.pelvis[1] as f64 + 0.6 * h[1],
            );
            line(&mut img, (u, v), tip, (r / 3.0).max(2.0), Rgb([30, 30, 30]));
        }
    }
    img
}

/// The ground area a top-down picture shows: the grid and the cameras with a margin, x to the right and
/// y up the picture.
struct TopView {
    lo: [f64; 2],
    hi: [f64; 2],
    span: f64,
    mid: [f64; 2],
    /// Pixels per metre.
    scale: f64,
    size: f64,
}

impl TopView {
    fn fit(grid: &VoxelGrid, cameras: &[Camera], size: u32) -> Self {
        let mut lo = [
            grid.center[0] - grid.size[0] / 2.0,
            grid.center[1] - grid.size[1] / 2.0,
        ];
        let mut hi = [
            grid.center[0] + grid.size[0] / 2.0,
            grid.center[1] + grid.size[1] / 2.0,
        ];
        for c in cameras {
            let p = c.centre();
            lo = [lo[0].min(p.x), lo[1].min(p.y)];
            hi = [hi[0].max(p.x), hi[1].max(p.y)];
        }
        let span = (hi[0] - lo[0]).max(hi[1] - lo[1]) * 1.1;
        TopView {
            lo,
            hi,
            span,
            mid: [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0],
            scale: size as f64 / span,
            size: size as f64,
        }
    }

    fn to_px(&self, x: f64, y: f64) -> (f64, f64) {
        (
            (x - self.mid[0]) * self.scale + self.size / 2.0,
            self.size / 2.0 - (y - self.mid[1]) * self.scale,
        )
    }

    /// A 1 m grid, or 10 m, 100 m, ... so that at most about 100 lines cross the picture.
    fn draw_ground(&self, img: &mut RgbImage) {
        let grey = Rgb([215, 215, 210]);
        let step = 10f64.powi((self.span / 100.0).log10().ceil().max(0.0) as i32);
        let (gx0, gx1) = (
            (self.lo[0] / step).floor() - 1.0,
            (self.hi[0] / step).ceil() + 1.0,
        );
        let (gy0, gy1) = (
            (self.lo[1] / step).floor() - 1.0,
            (self.hi[1] / step).ceil() + 1.0,
        );
        for i in 0..=(gx1 - gx0) as usize {
            let gx = (gx0 + i as f64) * step;
            let (a, b) = (self.to_px(gx, gy0 * step), self.to_px(gx, gy1 * step));
            line(img, a, b, 1.0, grey);
        }
        for i in 0..=(gy1 - gy0) as usize {
            let gy = (gy0 + i as f64) * step;
            let (a, b) = (self.to_px(gx0 * step, gy), self.to_px(gx1 * step, gy));
            line(img, a, b, 1.0, grey);
        }
    }
}

fn disc(img: &mut RgbImage, c: (f64, f64), r: f64, col: Rgb<u8>) {
    let (w, h) = (img.width() as i64, img.height() as i64);
    for y in (c.1 - r).floor() as i64..=(c.1 + r).ceil() as i64 {
        for x in (c.0 - r).floor() as i64..=(c.0 + r).ceil() as i64 {
            let d = ((x as f64 - c.0).powi(2) + (y as f64 - c.1).powi(2)).sqrt();
            if d <= r && x >= 0 && y >= 0 && x < w && y < h {
                img.put_pixel(x as u32, y as u32, col);
            }
        }
    }
}

fn line(img: &mut RgbImage, a: (f64, f64), b: (f64, f64), width: f64, col: Rgb<u8>) {
    let len = ((b.0 - a.0).powi(2) + (b.1 - a.1).powi(2)).sqrt();
    let steps = (len * 2.0).ceil().max(1.0) as usize;
    for i in 0..=steps {
        let t = i as f64 / steps as f64;
        disc(
            img,
            (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1)),
            width / 2.0,
            col,
        );
    }
}

/// Save a PNG atomically.
pub fn save_png(path: &Path, img: &RgbImage) -> Result<(), InferError> {
    write_atomic_with(path, |w| {
        img.write_to(w, image::ImageFormat::Png)
            .map_err(std::io::Error::other)
    })?;
    Ok(())
}

/// Whether a file name is one [`write_frame`] writes: a later frame written over an earlier one's
/// directory replaces all of them (fewer people leave no meshes of the earlier ones behind).
pub fn is_frame_output(name: &str) -> bool {
    let numbered = |prefix: &str, ext: &str| {
        name.strip_prefix(prefix)
            .and_then(|r| r.strip_suffix(ext))
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
    };
    matches!(name, "people.npz" | "topdown.png")
        || numbered("person_", ".obj")
        || numbered("person_", ".ply")
        || numbered("overlay_", ".png")
}

/// Write everything inference produces for one frame into `dir`: people.npz, meshes, overlays (when the
/// input images are given), topdown.png.
pub fn write_frame(
    dir: &Path,
    people: &[PersonPrediction],
    faces: &[[u32; 3]],
    cameras: &[Camera],
    images: Option<&[RgbImage]>,
    grid: &VoxelGrid,
) -> Result<(), InferError> {
    std::fs::create_dir_all(dir).map_err(|e| InferError::io(dir, e))?;
    write_people_npz(&dir.join("people.npz"), people)?;
    for (i, p) in people.iter().enumerate() {
        mvmp_smplx::export::write_obj(&dir.join(format!("person_{i:02}.obj")), &p.vertices, faces)?;
        mvmp_smplx::export::write_ply(&dir.join(format!("person_{i:02}.ply")), &p.vertices, faces)?;
    }
    if let Some(images) = images {
        for (v, (img, cam)) in images.iter().zip(cameras).enumerate() {
            save_png(
                &dir.join(format!("overlay_{v:02}.png")),
                &overlay(img, cam, people, faces),
            )?;
        }
    }
    save_png(
        &dir.join("topdown.png"),
        &topdown(grid, cameras, people, 640),
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::is_frame_output;

    #[test]
    fn a_frames_own_outputs_are_told_from_other_files() {
        for name in [
            "people.npz",
            "topdown.png",
            "person_00.obj",
            "person_123.ply",
            "overlay_03.png",
        ] {
            assert!(is_frame_output(name), "{name}");
        }
        for name in [
            "notes.txt",
            "person_.obj",
            "person_0a.obj",
            "overlay_01.jpg",
            "people.npz.bak",
            "my_person_00.obj",
        ] {
            assert!(!is_frame_output(name), "{name}");
        }
    }
}
