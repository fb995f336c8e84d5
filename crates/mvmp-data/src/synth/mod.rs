//! `mvmp data synth`: synthetic multiview multi-person scenes in the MVMP-HMR layout.
//!
//! Each scene draws a people count, a camera rig and a lighting; its first frame places people, later
//! frames move them. Scenes are generated in parallel, each from its own seed derived from the master seed,
//! so the output does not depend on the number of threads. The dataset is written into a temporary
//! directory beside the target and renamed into place at the end, so a failed run leaves nothing behind.
pub mod config;
pub mod people;
pub mod render;
pub mod scene;

use std::path::Path;

use image::ImageEncoder;
use nalgebra::{Matrix3, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

pub use config::SynthConfig;
use render::{Part, Scenery, ViewOutput, face_parts, render_view};
use scene::{Posed, Poser, next_frame, place_people};

use crate::DataError;
use crate::layout::*;
use mvmp_geom::{Camera, Rig};
use mvmp_io::write_atomic_with;

/// What a synthesis run made.
#[derive(Debug, Clone, Copy, Default)]
pub struct SynthSummary {
    pub scenes: usize,
    pub frames: usize,
    pub views: usize,
    pub people: usize,
}

fn scene_seed(seed: u64, scene: usize) -> u64 {
    seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (scene as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03)
}

/// A camera at `pos` looking at `target`, image y pointing down.
pub fn look_at(
    name: String,
    pos: Vector3<f64>,
    target: Vector3<f64>,
    fov_deg: f64,
    k1: f64,
    size: [u32; 2],
    principal_offset: [f64; 2],
) -> Result<Camera, DataError> {
    let z = (target - pos).normalize();
    let up = if z.cross(&Vector3::z()).norm() < 1e-6 {
        Vector3::y()
    } else {
        Vector3::z()
    };
    let x = z.cross(&up).normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let (w, h) = (size[0] as f64, size[1] as f64);
    let f = (w / 2.0) / (fov_deg.to_radians() / 2.0).tan();
    let k = Matrix3::new(
        f,
        0.0,
        w / 2.0 - 0.5 + principal_offset[0],
        0.0,
        f,
        h / 2.0 - 0.5 + principal_offset[1],
        0.0,
        0.0,
        1.0,
    );
    Ok(Camera::new(
        name,
        k,
        r,
        -(r * pos),
        [k1, -k1 / 4.0, 0.0, 0.0, 0.0],
        size[0],
        size[1],
    )?)
}

fn make_rig(cfg: &SynthConfig, rng: &mut ChaCha8Rng) -> Result<Rig, DataError> {
    let c = &cfg.cameras;
    let size = cfg.image_size;
    let mut cams = Vec::new();
    let pp = |rng: &mut ChaCha8Rng| {
        [
            rng.random_range(-0.01..=0.01) * size[0] as f64,
            rng.random_range(-0.01..=0.01) * size[1] as f64,
        ]
    };
    if !c.listed.is_empty() {
        for (i, l) in c.listed.iter().enumerate() {
            cams.push(look_at(
                format!("cam{i:02}"),
                Vector3::from(l.position),
                Vector3::from(l.look_at),
                l.fov_deg,
                l.k1,
                size,
                pp(rng),
            )?);
        }
        return Ok(Rig::new(cams));
    }
    let offset = rng.random_range(0.0..std::f64::consts::TAU);
    for i in 0..c.count {
        let ring = &c.rings[i % c.rings.len()];
        let a = offset
            + std::f64::consts::TAU * i as f64 / c.count as f64
            + rng.random_range(-0.15..0.15);
        let pos = Vector3::new(ring.radius * a.cos(), ring.radius * a.sin(), ring.height);
        let target = Vector3::new(
            rng.random_range(-1.0..=1.0) * cfg.area[0] / 8.0,
            rng.random_range(-1.0..=1.0) * cfg.area[1] / 8.0,
            c.look_at_height,
        );
        let fov = rng.random_range(c.fov_deg[0]..=c.fov_deg[1]);
        let k1 = rng.random_range(c.k1[0]..=c.k1[1]);
        cams.push(look_at(
            format!("cam{i:02}"),
            pos,
            target,
            fov,
            k1,
            size,
            pp(rng),
        )?);
    }
    Ok(Rig::new(cams))
}

fn write_png_rgb(path: &Path, w: u32, h: u32, rgb: &[u8], jpeg: bool) -> Result<(), DataError> {
    write_atomic_with(path, |out| {
        if jpeg {
            image::codecs::jpeg::JpegEncoder::new_with_quality(out, 92)
                .write_image(rgb, w, h, image::ExtendedColorType::Rgb8)
                .map_err(std::io::Error::other)
        } else {
            image::codecs::png::PngEncoder::new(out)
                .write_image(rgb, w, h, image::ExtendedColorType::Rgb8)
                .map_err(std::io::Error::other)
        }
    })?;
    Ok(())
}

fn write_png_gray(
    path: &Path,
    w: u32,
    h: u32,
    bytes: &[u8],
    sixteen: bool,
) -> Result<(), DataError> {
    write_atomic_with(path, |out| {
        let kind = if sixteen {
            image::ExtendedColorType::L16
        } else {
            image::ExtendedColorType::L8
        };
        image::codecs::png::PngEncoder::new(out)
            .write_image(bytes, w, h, kind)
            .map_err(std::io::Error::other)
    })?;
    Ok(())
}

/// Joint visibility and 2D positions of one person in one view.
fn person_view(cam: &Camera, p: &Posed, index: usize, view: &ViewOutput) -> PersonView {
    let joints_2d = p
        .joints
        .iter()
        .map(|j| {
            let (uv, z) = cam.project(&Vector3::from(*j));
            let mut vis = z > 1e-3 && cam.contains(uv);
            if vis {
                // Hidden when another person covers the pixel in front of the joint.
                let (x, y) = (uv.x.round() as u32, uv.y.round() as u32);
                let k = (y * view.width + x) as usize;
                let m = view.mask[k];
                let d = view.depth_mm[k] as f64 / 1000.0;
                if m != 0 && (m as usize) != index + 1 && d < z - 0.02 {
                    vis = false;
                }
            }
            // Behind the camera, or so close to its plane that the lens model sends it past any
            // image (the annotation bound, `MAX_PIXEL`): no position.
            let far = |x: f64| x.is_nan() || x.abs() > crate::layout::MAX_PIXEL;
            let uv = if z > 1e-3 && !far(uv.x) && !far(uv.y) {
                uv
            } else {
                Vector2::new(-1.0, -1.0)
            };
            [uv.x, uv.y, if vis { 1.0 } else { 0.0 }]
        })
        .collect();
    PersonView {
        joints_2d,
        bbox: view.bbox[index],
        silhouette_pixels: view.silhouette[index],
        visible_pixels: view.visible[index],
    }
}

struct SceneOut {
    frames: usize,
    views: usize,
    people: usize,
}

#[allow(clippy::too_many_arguments)]
fn make_scene(
    cfg: &SynthConfig,
    index: usize,
    root: &Path,
    poser: &Poser,
    faces: &[[u32; 3]],
    parts: &[Part],
    progress: &(dyn Fn() + Sync),
) -> Result<SceneOut, DataError> {
    let mut rng = ChaCha8Rng::seed_from_u64(scene_seed(cfg.seed, index));
    let name = format!("scene_{index:03}");
    let dir = root.join(&name);
    std::fs::create_dir_all(&dir).map_err(|e| DataError::io(&dir, e))?;
    let rig = make_rig(cfg, &mut rng)?;
    rig.write(&dir.join("cameras.json"))?;
    let scenery = make_scenery(cfg, &mut rng);
    let count = rng.random_range(cfg.people[0]..=cfg.people[1]);
    let mut people: Vec<Posed> = Vec::new();
    let mut frames = Vec::new();
    let ext = if cfg.image_format == "jpeg" {
        "jpg"
    } else {
        "png"
    };
    for f in 0..cfg.frames_per_scene {
        people = if f == 0 {
            place_people(poser, count, cfg.area, &mut rng)
        } else {
            next_frame(poser, &people, cfg.area, &mut rng)
        };
        let frame_name = format!("frame_{f:06}");
        let fdir = dir.join(&frame_name);
        std::fs::create_dir_all(&fdir).map_err(|e| DataError::io(&fdir, e))?;
        let views: Vec<ViewOutput> = rig
            .cameras
            .par_iter()
            .map(|cam| render_view(cam, &people, faces, parts, &scenery))
            .collect();
        let files = write_views(cfg, &fdir, &views, ext)?;
        let ann = frame_annotation(&rig, &people, &views, files);
        write_json(&fdir.join("annotation.json"), &ann)?;
        frames.push(frame_name);
        progress();
    }
    write_json(
        &dir.join("scene.json"),
        &SceneIndex {
            format: SCENE_FORMAT.into(),
            version: SCHEMA_VERSION,
            frames: frames.clone(),
            area: cfg.area,
        },
    )?;
    Ok(SceneOut {
        frames: frames.len(),
        views: rig.len(),
        people: people.len(),
    })
}

/// A scene's lighting and ground: night or day, the sun's direction, two ground tones and the texture's
/// seed, drawn in that order.
fn make_scenery(cfg: &SynthConfig, rng: &mut ChaCha8Rng) -> Scenery {
    let night = rng.random_bool(cfg.lighting.night_fraction);
    let elev = rng.random_range(0.5..1.2f64);
    let azim = rng.random_range(0.0..std::f64::consts::TAU);
    let tone = |rng: &mut ChaCha8Rng| -> [f32; 3] {
        let g = rng.random_range(0.25..0.6f32);
        [
            g * rng.random_range(0.9..1.1),
            g,
            g * rng.random_range(0.85..1.05),
        ]
    };
    Scenery {
        night,
        light_dir: [
            -(elev.cos() * azim.cos()) as f32,
            -(elev.cos() * azim.sin()) as f32,
            -elev.sin() as f32,
        ],
        ground: [tone(rng), tone(rng)],
        seed: rng.random(),
    }
}

/// The file names of one frame's views: images, and depth maps and masks where the config makes them.
struct ViewFiles {
    images: Vec<String>,
    depth: Option<Vec<String>>,
    masks: Option<Vec<String>>,
}

/// Write one frame's rendered views into `fdir`.
fn write_views(
    cfg: &SynthConfig,
    fdir: &Path,
    views: &[ViewOutput],
    ext: &str,
) -> Result<ViewFiles, DataError> {
    let mut images = Vec::new();
    let mut depth = Vec::new();
    let mut masks = Vec::new();
    for (v, out) in views.iter().enumerate() {
        let img = format!("view_{v:02}.{ext}");
        write_png_rgb(
            &fdir.join(&img),
            out.width,
            out.height,
            &out.rgb,
            ext == "jpg",
        )?;
        images.push(img);
        if cfg.depth {
            let d = format!("depth_{v:02}.png");
            // 16-bit PNG samples are big-endian in the file; the encoder takes native-endian u16 bytes.
            let bytes: Vec<u8> = out.depth_mm.iter().flat_map(|x| x.to_ne_bytes()).collect();
            write_png_gray(&fdir.join(&d), out.width, out.height, &bytes, true)?;
            depth.push(d);
        }
        if cfg.masks {
            let m = format!("mask_{v:02}.png");
            write_png_gray(&fdir.join(&m), out.width, out.height, &out.mask, false)?;
            masks.push(m);
        }
    }
    Ok(ViewFiles {
        images,
        depth: cfg.depth.then_some(depth),
        masks: cfg.masks.then_some(masks),
    })
}

/// One frame's annotation: its files and every person's parameters, joints and per-view boxes.
fn frame_annotation(
    rig: &Rig,
    people: &[Posed],
    views: &[ViewOutput],
    files: ViewFiles,
) -> Annotation {
    Annotation {
        format: ANNOTATION_FORMAT.into(),
        version: SCHEMA_VERSION,
        images: files.images,
        depth: files.depth,
        masks: files.masks,
        people: people
            .iter()
            .enumerate()
            .map(|(i, p)| Person {
                id: p.state.id,
                smplx: p.params(),
                pelvis: p.pelvis,
                joints_3d: p.joints.clone(),
                views: rig
                    .cameras
                    .iter()
                    .zip(views)
                    .map(|(cam, view)| person_view(cam, p, i, view))
                    .collect(),
            })
            .collect(),
    }
}

/// Generate a dataset into `out` (which must not exist or be empty). `progress` is called once per frame.
pub fn generate(
    cfg: &SynthConfig,
    out: &Path,
    config_dir: &Path,
    progress: &(dyn Fn() + Sync),
) -> Result<SynthSummary, DataError> {
    if out.exists() {
        let empty = std::fs::read_dir(out)
            .map_err(|e| DataError::io(out, e))?
            .next()
            .is_none();
        if !empty {
            return Err(DataError::file(
                out,
                "the output directory exists and is not empty",
            ));
        }
    }
    let model = load_body_model(&cfg.body_model, config_dir)?;
    let parts = face_parts(&model);
    let staged = mvmp_io::StagedDir::new(out)?;
    let results: Vec<Result<SceneOut, DataError>> = (0..cfg.scenes)
        .into_par_iter()
        .map(|s| {
            let poser = Poser::new(&model);
            make_scene(
                cfg,
                s,
                staged.path(),
                &poser,
                &model.faces,
                &parts,
                progress,
            )
        })
        .collect();
    let mut summary = SynthSummary {
        scenes: cfg.scenes,
        ..Default::default()
    };
    for r in results {
        let s = r?;
        summary.frames += s.frames;
        summary.views = summary.views.max(s.views);
        summary.people += s.people;
    }
    let index = DatasetIndex {
        format: DATASET_FORMAT.into(),
        version: SCHEMA_VERSION,
        name: cfg.name.clone(),
        body_model: if cfg.body_model.starts_with("standin:") {
            cfg.body_model.clone()
        } else {
            // Stored absolute so the dataset can be read from anywhere (a relative `--config` leaves
            // `config_dir` relative too).
            let joined = config_dir.join(&cfg.body_model);
            std::path::absolute(&joined)
                .unwrap_or(joined)
                .to_string_lossy()
                .into_owned()
        },
        scenes: (0..cfg.scenes).map(|s| format!("scene_{s:03}")).collect(),
    };
    write_json(&staged.path().join("dataset.json"), &index)?;
    // The synthesis config, resolved, for the record.
    let toml = toml::to_string_pretty(cfg).expect("config serialises");
    mvmp_io::write_atomic(&staged.path().join("synth.toml"), toml.as_bytes())?;
    staged.finish()?;
    Ok(summary)
}
