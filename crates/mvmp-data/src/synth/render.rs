//! Rendering one view of a synthetic frame: textured ground and sky by ray casting, people by the
//! z-buffered rasterizer with per-part colours, then depth, instance masks, per-person silhouettes.
use nalgebra::{Vector2, Vector3};

use super::people::Appearance;
use super::scene::Posed;
use mvmp_geom::Camera;
use mvmp_render::{Frame, Light, MeshRef, coverage, draw};

/// Which garment (or skin, or hair) covers a face of the body mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    Skin,
    Hair,
    Shirt,
    /// The front of the torso: what an open jacket shows, lighter than the jacket.
    ShirtFront,
    Sleeve,
    Pants,
    Shoes,
}

const HEAD: usize = 15;

/// The part of each face, from the joint that dominates its first vertex's skinning weights. The head
/// is skin in front below the forehead and hair elsewhere: with a head of one colour all round, and
/// clothes alike front and back, nothing in an image told which way a person faces. The head alone was
/// not enough: at the demo's scale it is ~7 pixels high, and the detector's left and right joint heatmaps
/// came out the same (the fused heatmaps' left-minus-right centroids pointed at random). So the torso's
/// front differs from its back too, as most clothes do (an open jacket, a print, buttons).
pub fn face_parts(model: &mvmp_smplx::BodyModel) -> Vec<Part> {
    let nj = mvmp_smplx::names::NUM_JOINTS;
    let dominant = |v: usize| {
        let row = &model.weights[v * nj..(v + 1) * nj];
        (0..nj)
            .max_by(|&a, &b| row[a].total_cmp(&row[b]))
            .unwrap_or(0)
    };
    let head = PartBox::new(model, |v| dominant(v) == HEAD);
    let chest = PartBox::new(model, |v| matches!(dominant(v), 3 | 6 | 9));
    let part_of_joint = |j: usize| match j {
        0 | 1 | 2 | 4 | 5 => Part::Pants,
        7 | 8 | 10 | 11 => Part::Shoes,
        3 | 6 | 9 | 13 | 14 | 16 | 17 => Part::Shirt,
        18 | 19 => Part::Sleeve,
        _ => Part::Skin,
    };
    model
        .faces
        .iter()
        .map(|f| match dominant(f[0] as usize) {
            HEAD if head.is_hair(model, f) => Part::Hair,
            j => match part_of_joint(j) {
                Part::Shirt if chest.is_front(model, f) => Part::ShirtFront,
                p => p,
            },
        })
        .collect()
}

/// The bounds of some of the body's vertices (the head's, the chest's) in the rest pose (y up, z forward).
struct PartBox {
    lo: [f32; 3],
    hi: [f32; 3],
}

impl PartBox {
    fn new(model: &mvmp_smplx::BodyModel, member: impl Fn(usize) -> bool) -> Self {
        let mut b = PartBox {
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
        };
        for v in (0..model.v_template.len() / 3).filter(|&v| member(v)) {
            for k in 0..3 {
                b.lo[k] = b.lo[k].min(model.v_template[v * 3 + k]);
                b.hi[k] = b.hi[k].max(model.v_template[v * 3 + k]);
            }
        }
        b
    }

    /// Where a face's centre lies within the box along axis `k` (0 at `lo`, 1 at `hi`).
    fn relative(&self, model: &mvmp_smplx::BodyModel, face: &[u32; 3], k: usize) -> f32 {
        let mean = face
            .iter()
            .map(|&v| model.v_template[v as usize * 3 + k])
            .sum::<f32>()
            / 3.0;
        (mean - self.lo[k]) / (self.hi[k] - self.lo[k]).max(1e-6)
    }

    /// The front half (z forward).
    fn is_front(&self, model: &mvmp_smplx::BodyModel, face: &[u32; 3]) -> bool {
        self.relative(model, face, 2) > 0.5
    }

    /// Hair: the back half of the head and its top above the forehead.
    fn is_hair(&self, model: &mvmp_smplx::BodyModel, face: &[u32; 3]) -> bool {
        self.relative(model, face, 2) < 0.5 || self.relative(model, face, 1) > 0.8
    }
}

/// Lighting and ground of a scene.
#[derive(Debug, Clone, Copy)]
pub struct Scenery {
    pub night: bool,
    /// Direction the sun (or moon) light travels.
    pub light_dir: [f32; 3],
    /// Ground tile colours.
    pub ground: [[f32; 3]; 2],
    pub seed: u64,
}

impl Scenery {
    fn light(&self) -> Light {
        if self.night {
            Light {
                dir: self.light_dir,
                ambient: 0.3,
                color: [0.30, 0.33, 0.45],
            }
        } else {
            Light {
                dir: self.light_dir,
                ambient: 0.35,
                color: [1.0, 0.97, 0.92],
            }
        }
    }
}

/// What rendering one view produces.
pub struct ViewOutput {
    pub width: u32,
    pub height: u32,
    /// RGB bytes, row-major.
    pub rgb: Vec<u8>,
    /// Depth along the optical axis in millimetres (0 = sky).
    pub depth_mm: Vec<u16>,
    /// Person index + 1, 0 where no person.
    pub mask: Vec<u8>,
    /// Per person: visible pixels, whole-silhouette pixels, bounding box of the visible pixels.
    pub visible: Vec<u32>,
    pub silhouette: Vec<u32>,
    pub bbox: Vec<Option<[f64; 4]>>,
}

fn hash(x: i64, y: i64, seed: u64) -> f32 {
    let mut h = (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ seed.wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 33;
    h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
    h ^= h >> 29;
    (h >> 40) as f32 / (1u64 << 24) as f32
}

fn ground_colour(p: &Vector3<f64>, s: &Scenery) -> [f32; 3] {
    // 1 m paving tiles in two tones, varied per tile, with a fine grain and darker joints.
    let (tx, ty) = (p.x.floor() as i64, p.y.floor() as i64);
    let tone = s.ground[((tx + ty).rem_euclid(2)) as usize];
    let vary = 0.85 + 0.3 * hash(tx, ty, s.seed);
    let grain = 0.9
        + 0.2
            * hash(
                (p.x * 40.0).floor() as i64,
                (p.y * 40.0).floor() as i64,
                s.seed ^ 7,
            );
    let fx = p.x - p.x.floor();
    let fy = p.y - p.y.floor();
    let joint = if fx < 0.02 || fy < 0.02 { 0.6 } else { 1.0 };
    tone.map(|c| c * vary * grain * joint)
}

/// Render one view.
pub fn render_view(
    cam: &Camera,
    people: &[Posed],
    faces: &[[u32; 3]],
    parts: &[Part],
    scenery: &Scenery,
) -> ViewOutput {
    let (w, h) = (cam.width, cam.height);
    let light = scenery.light();
    let mut frame = Frame::new(w, h, [0.0; 3]);
    draw_background(&mut frame, cam, scenery, &light);
    let colours: Vec<Vec<[f32; 3]>> = people
        .iter()
        .map(|p| part_colours(&p.state.appearance, parts))
        .collect();
    let meshes: Vec<MeshRef> = people
        .iter()
        .zip(&colours)
        .map(|(p, c)| MeshRef {
            vertices: &p.vertices,
            faces,
            color: [1.0; 3],
            face_colors: Some(c),
        })
        .collect();
    draw(&mut frame, cam, &meshes, &light);
    let (mask, visible, bbox) = instances(&frame, people.len());
    let silhouette: Vec<u32> = people
        .iter()
        .zip(&visible)
        .map(|(p, v)| coverage(cam, &p.vertices, faces, w, h).max(*v))
        .collect();
    let depth_mm = frame
        .depth
        .iter()
        .map(|&z| {
            if z.is_finite() {
                (z * 1000.0).round().clamp(1.0, 65535.0) as u16
            } else {
                0
            }
        })
        .collect();
    ViewOutput {
        width: w,
        height: h,
        rgb: frame.to_rgb8(),
        depth_mm,
        mask,
        visible,
        silhouette,
        bbox,
    }
}

/// Ground and sky by casting every pixel's ray: the textured, sunlit ground (with a lamp's pool of
/// light at night) where the ray meets it, with its depth, and a sky gradient elsewhere.
fn draw_background(frame: &mut Frame, cam: &Camera, scenery: &Scenery, light: &Light) {
    let (w, h) = (cam.width, cam.height);
    let sun = Vector3::new(
        light.dir[0] as f64,
        light.dir[1] as f64,
        light.dir[2] as f64,
    )
    .normalize();
    let ground_lit = (light.ambient + (1.0 - light.ambient) * (-sun.z).max(0.0) as f32).min(1.0);
    for y in 0..h {
        for x in 0..w {
            let k = (y * w + x) as usize;
            let Some((o, d)) = cam.back_project(Vector2::new(x as f64, y as f64)) else {
                continue;
            };
            if d.z < -1e-6 && o.z > 0.0 {
                let t = -o.z / d.z;
                let p = o + d * t;
                let z_cam = cam.to_camera(&p).z;
                let mut c = ground_colour(&p, scenery);
                if scenery.night {
                    // A pool of lamp light around the middle of the scene.
                    let lamp = (-(p.x * p.x + p.y * p.y) / (2.0 * 6.0 * 6.0)).exp() as f32;
                    c = c.map(|v| v * (0.25 + 1.2 * lamp));
                }
                frame.rgb[k] = std::array::from_fn(|i| c[i] * ground_lit * light.color[i]);
                frame.depth[k] = z_cam as f32;
            } else {
                let up = d.z.clamp(0.0, 1.0) as f32;
                frame.rgb[k] = if scenery.night {
                    [0.01 + 0.02 * up, 0.015 + 0.03 * up, 0.04 + 0.06 * up]
                } else {
                    [0.75 - 0.35 * up, 0.85 - 0.3 * up, 0.98 - 0.1 * up]
                };
            }
        }
    }
}

/// Each face's colour for one person's appearance.
fn part_colours(a: &Appearance, parts: &[Part]) -> Vec<[f32; 3]> {
    parts
        .iter()
        .map(|part| match part {
            Part::Skin => a.skin,
            Part::Hair => a.hair,
            Part::Shirt => a.shirt,
            Part::ShirtFront => a.shirt_front,
            Part::Sleeve if a.long_sleeves => a.shirt,
            Part::Sleeve => a.skin,
            Part::Pants => a.pants,
            Part::Shoes => a.shoes,
        })
        .collect()
}

/// Per-pixel instance mask (person index + 1, 0 for none), each person's visible pixel count and the box
/// of their visible pixels, from the rasterizer's per-pixel mesh index.
type Instances = (Vec<u8>, Vec<u32>, Vec<Option<[f64; 4]>>);

fn instances(frame: &Frame, n: usize) -> Instances {
    let w = frame.width;
    let mut visible = vec![0u32; n];
    let mut bbox: Vec<Option<[f64; 4]>> = vec![None; n];
    let mut mask = vec![0u8; frame.mesh.len()];
    for (k, &m) in frame.mesh.iter().enumerate() {
        if m >= 0 {
            let i = m as usize;
            mask[k] = (i + 1) as u8;
            visible[i] += 1;
            let (x, y) = ((k as u32 % w) as f64, (k as u32 / w) as f64);
            let b = bbox[i].get_or_insert([x, y, x, y]);
            *b = [b[0].min(x), b[1].min(y), b[2].max(x), b[3].max(y)];
        }
    }
    (mask, visible, bbox)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The mean rest-pose z (forward) and the number of the faces of part `want` that `keep` accepts.
    fn mean_z(
        model: &mvmp_smplx::BodyModel,
        parts: &[Part],
        want: Part,
        keep: impl Fn(&[u32; 3]) -> bool,
    ) -> (f64, usize) {
        let z = |f: &[u32; 3]| {
            f.iter()
                .map(|&v| model.v_template[v as usize * 3 + 2] as f64)
                .sum::<f64>()
                / 3.0
        };
        let zs: Vec<f64> = model
            .faces
            .iter()
            .zip(parts)
            .filter(|(f, p)| **p == want && keep(f))
            .map(|(f, _)| z(f))
            .collect();
        (zs.iter().sum::<f64>() / zs.len().max(1) as f64, zs.len())
    }

    /// The stand-in's head: hair behind and on top, skin on the face, so the face points forward (+z in
    /// the rest pose) by more than the nose alone.
    #[test]
    fn the_head_is_hair_behind_and_skin_in_front() {
        let model = mvmp_smplx::standin_model(0);
        let parts = face_parts(&model);
        let nj = mvmp_smplx::names::NUM_JOINTS;
        let on_head = |f: &[u32; 3]| {
            let row = &model.weights[f[0] as usize * nj..(f[0] as usize + 1) * nj];
            (0..nj).max_by(|&a, &b| row[a].total_cmp(&row[b])) == Some(HEAD)
        };
        let (hair_z, hair_n) = mean_z(&model, &parts, Part::Hair, on_head);
        let (face_z, face_n) = mean_z(&model, &parts, Part::Skin, on_head);
        assert!(
            hair_n > face_n && face_n > 20,
            "{hair_n} hair, {face_n} skin faces"
        );
        assert!(
            face_z - hair_z > 0.05,
            "face at z {face_z}, hair at {hair_z}"
        );
        // Hair only on the head.
        let off_head = model
            .faces
            .iter()
            .zip(&parts)
            .filter(|(f, p)| **p == Part::Hair && !on_head(f))
            .count();
        assert_eq!(off_head, 0);
    }

    /// The torso's front is its own part, in front of the back (+z in the rest pose), and drawn lighter.
    #[test]
    fn the_torso_front_differs_from_its_back() {
        let model = mvmp_smplx::standin_model(0);
        let parts = face_parts(&model);
        let all = |_: &[u32; 3]| true;
        let (front_z, front_n) = mean_z(&model, &parts, Part::ShirtFront, all);
        let (back_z, back_n) = mean_z(&model, &parts, Part::Shirt, all);
        assert!(
            front_n > 20 && back_n > 20,
            "{front_n} front, {back_n} back faces"
        );
        assert!(
            front_z - back_z > 0.05,
            "front at z {front_z}, back at {back_z}"
        );
        for drawn in [[0.95f32, 0.9, 0.85], [0.05, 0.2, 0.1], [0.5, 0.45, 0.4]] {
            let (jacket, front) = super::super::people::jacket_and_front(drawn);
            for c in 0..3 {
                assert!(
                    front[c] - jacket[c] >= 0.1,
                    "{drawn:?}: {jacket:?} vs {front:?}"
                );
            }
        }
    }
}
