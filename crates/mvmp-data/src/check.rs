//! `mvmp data check --format mvmp`: validate a whole dataset tree and list every problem with its file.
//! A plain check reads image headers (presence, size, colour type) and validates every annotation; a deep
//! check also decodes every image to its last pixel, which finds files cut short after their header.
use std::path::{Path, PathBuf};

use crate::layout::{Annotation, DatasetIndex, SceneIndex};
use mvmp_geom::Rig;

/// One problem found by the check.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    pub path: PathBuf,
    pub what: String,
}

impl Problem {
    /// The problem an error describes, naming its file once: the error's own file where it names one
    /// (its message without it), else `fallback` with the whole message.
    pub fn from_error(fallback: &Path, e: &crate::DataError) -> Problem {
        let (path, what) = match e {
            crate::DataError::File { path, what } => (path.clone(), what.clone()),
            crate::DataError::Io { path, source } => (path.clone(), source.to_string()),
            _ => (fallback.into(), e.to_string()),
        };
        Problem { path, what }
    }
}

/// What the check found.
#[derive(Debug, Default, Clone)]
pub struct CheckReport {
    pub scenes: usize,
    pub frames: usize,
    pub views: usize,
    pub people: usize,
    pub images: usize,
    pub problems: Vec<Problem>,
}

fn problem(r: &mut CheckReport, path: &Path, what: impl Into<String>) {
    r.problems.push(Problem {
        path: path.to_path_buf(),
        what: what.into(),
    });
}

/// Decode a whole image; a JPEG must also end with its end-of-image marker (a JPEG cut short decodes
/// without complaint, its missing rows grey). The loaders read images through this.
pub fn open_image(path: &Path) -> Result<image::DynamicImage, String> {
    // Read once: the bytes are both decoded and checked for the end marker.
    let bytes = std::fs::read(path).map_err(|e| e.to_string())?;
    let format = image::ImageFormat::from_path(path)
        .or_else(|_| image::guess_format(&bytes))
        .map_err(|e| format!("does not decode: {e}"))?;
    let img = image::load_from_memory_with_format(&bytes, format)
        .map_err(|e| format!("does not decode: {e}"))?;
    if format == image::ImageFormat::Jpeg && !jpeg_complete(&bytes) {
        return Err("the JPEG ends before its end-of-image marker (cut short)".into());
    }
    Ok(img)
}

/// A view's image, decoded whole and checked against its camera's resolution: every loader and
/// `infer` read views through this, with one message for each failure.
pub fn read_view_image(
    path: &Path,
    cam: &mvmp_geom::Camera,
) -> Result<image::RgbImage, crate::DataError> {
    let img = open_image(path)
        .map_err(|e| crate::DataError::file(path, format!("unreadable image: {e}")))?
        .to_rgb8();
    if img.dimensions() != (cam.width, cam.height) {
        return Err(crate::DataError::file(
            path,
            format!(
                "the image is {}x{} but camera {:?} of the rig is {}x{}",
                img.width(),
                img.height(),
                cam.name,
                cam.width,
                cam.height
            ),
        ));
    }
    Ok(img)
}

/// Whether the last scan of a JPEG is followed by an end-of-image marker. Inside entropy-coded data
/// every 0xFF byte is stuffed (0xFF 0x00), so the markers cannot occur there; an EXIF thumbnail's own
/// markers come before the main image's scan, and data some cameras append after the end marker is
/// allowed.
fn jpeg_complete(bytes: &[u8]) -> bool {
    let marker = |m: u8| move |w: &[u8]| w == [0xFF, m];
    let Some(scan) = bytes.windows(2).rposition(marker(0xDA)) else {
        return false;
    };
    bytes[scan..].windows(2).any(marker(0xD9))
}

/// What is wrong with the image at `path` as a view of a camera of `size` (width, height): its header
/// ([`view_header_problem`]), or with `deep` the whole image decoded.
pub fn view_problem(path: &Path, size: (u32, u32), deep: bool) -> Option<String> {
    if !deep {
        return view_header_problem(path, size);
    }
    match open_image(path) {
        Err(e) => Some(format!("unreadable image: {e}")),
        Ok(img) if (img.width(), img.height()) != size => Some(format!(
            "image is {} x {}, the camera says {} x {}",
            img.width(),
            img.height(),
            size.0,
            size.1
        )),
        Ok(_) => None,
    }
}

/// What is wrong with the image at `path` as a view of a camera of `size` (width, height), reading its
/// header only: missing, not an image, or another size.
pub fn view_header_problem(path: &Path, size: (u32, u32)) -> Option<String> {
    use image::ImageDecoder;
    let reader = match image::ImageReader::open(path).and_then(|r| r.with_guessed_format()) {
        Ok(rd) => rd,
        Err(e) => return Some(format!("missing or unreadable image: {e}")),
    };
    match reader.into_decoder() {
        Err(e) => Some(format!("not a readable image: {e}")),
        Ok(dec) if dec.dimensions() != size => Some(format!(
            "image is {} x {}, the camera says {} x {}",
            dec.dimensions().0,
            dec.dimensions().1,
            size.0,
            size.1
        )),
        Ok(_) => None,
    }
}

/// Check an image file: present, a readable image header, the expected size and colour type; with
/// `deep`, decoded whole.
fn check_image(r: &mut CheckReport, path: &Path, size: (u32, u32), kind: &str, deep: bool) {
    let reader = match image::ImageReader::open(path).and_then(|r| r.with_guessed_format()) {
        Ok(rd) => rd,
        Err(e) => return problem(r, path, format!("{kind} is missing or unreadable: {e}")),
    };
    match reader.into_decoder() {
        Err(e) => problem(r, path, format!("{kind} is not a readable image: {e}")),
        Ok(dec) => {
            use image::ImageDecoder;
            let dims = dec.dimensions();
            if dims != size {
                problem(
                    r,
                    path,
                    format!(
                        "{kind} is {} x {}, the camera says {} x {}",
                        dims.0, dims.1, size.0, size.1
                    ),
                );
            }
            let ct = dec.color_type();
            let ok = match kind {
                "depth map" => ct == image::ColorType::L16,
                "mask" => ct == image::ColorType::L8,
                _ => true,
            };
            if !ok {
                problem(r, path, format!("{kind} has colour type {ct:?}"));
            }
            if deep && let Err(e) = open_image(path) {
                problem(r, path, format!("{kind} {e}"));
            }
        }
    }
    r.images += 1;
}

/// One scene of a dataset: its rig, its index and every frame. `joints`: what each person must hold (the
/// body model's output joints), when the body model could be read.
fn check_scene(r: &mut CheckReport, dir: &Path, joints: Option<usize>, body: &str, deep: bool) {
    let rig = match Rig::read(&dir.join("cameras.json")) {
        Ok(rig) => rig,
        Err(e) => return problem(r, &dir.join("cameras.json"), e.to_string()),
    };
    r.views = r.views.max(rig.len());
    let scene = match SceneIndex::read(dir) {
        Ok(s) => s,
        Err(e) => return problem(r, &dir.join("scene.json"), e.to_string()),
    };
    for f in &scene.frames {
        r.frames += 1;
        check_frame(r, &dir.join(f), &rig, joints, body, deep);
    }
}

/// One frame: its annotation against the rig and the body model's joints, and every view's image,
/// depth map and mask.
fn check_frame(
    r: &mut CheckReport,
    fdir: &Path,
    rig: &Rig,
    joints: Option<usize>,
    body: &str,
    deep: bool,
) {
    let apath = fdir.join("annotation.json");
    let ann = match Annotation::read_with_problems(&apath, rig.len()) {
        Ok((a, found)) if found.is_empty() => a,
        Ok((_, found)) => {
            for what in found {
                problem(r, &apath, what);
            }
            return;
        }
        Err(e) => {
            let what = e.to_string();
            let prefix = format!("{}: ", apath.display());
            return problem(r, &apath, what.trim_start_matches(&prefix).to_string());
        }
    };
    r.people += ann.people.len();
    if let Some(Err(what)) = joints.map(|n| ann.check_joints(n, body)) {
        problem(r, &apath, what);
    }
    for (v, cam) in rig.cameras.iter().enumerate() {
        let size = (cam.width, cam.height);
        check_image(r, &fdir.join(&ann.images[v]), size, "image", deep);
        if let Some(d) = &ann.depth {
            check_image(r, &fdir.join(&d[v]), size, "depth map", deep);
        }
        if let Some(m) = &ann.masks {
            let mpath = fdir.join(&m[v]);
            check_image(r, &mpath, size, "mask", deep);
            check_mask_people(r, &mpath, ann.people.len());
        }
    }
}

/// A mask's largest person index must be one of the frame's people.
fn check_mask_people(r: &mut CheckReport, mpath: &Path, people: usize) {
    if let Ok(img) = image::open(mpath) {
        let max = img.to_luma8().pixels().map(|p| p.0[0]).max().unwrap_or(0);
        if max as usize > people {
            problem(
                r,
                mpath,
                format!("mask holds person {max} but the frame has {people} people"),
            );
        }
    }
}

/// Validate the dataset at `root`; `deep` also decodes every image.
pub fn check_dataset(root: &Path, deep: bool) -> CheckReport {
    let mut r = CheckReport::default();
    let index = match DatasetIndex::read(root) {
        Ok(i) => i,
        Err(e) => {
            problem(&mut r, &root.join("dataset.json"), e.to_string());
            return r;
        }
    };
    // People must hold the joints the body model outputs: losses and metrics index them by its layout.
    let joints = match crate::layout::load_body_model(&index.body_model, root) {
        Ok(m) => Some(m.num_output_joints()),
        Err(e) => {
            problem(
                &mut r,
                &root.join("dataset.json"),
                format!("body model: {e}"),
            );
            None
        }
    };
    for name in &index.scenes {
        r.scenes += 1;
        check_scene(&mut r, &root.join(name), joints, &index.body_model, deep);
    }
    r
}

#[cfg(test)]
mod tests {
    use super::open_image;

    /// A JPEG as a camera writes it, with trailing bytes after its end marker, and cut in half.
    #[test]
    fn a_jpeg_is_complete_with_trailing_bytes_and_incomplete_when_cut() {
        let img =
            image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([x as u8 * 3, y as u8 * 5, 90]));
        let mut jpeg = Vec::new();
        image::DynamicImage::ImageRgb8(img)
            .write_to(
                &mut std::io::Cursor::new(&mut jpeg),
                image::ImageFormat::Jpeg,
            )
            .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, bytes: &[u8]| {
            let p = dir.path().join(name);
            std::fs::write(&p, bytes).unwrap();
            p
        };
        assert!(open_image(&write("whole.jpg", &jpeg)).is_ok());
        let mut trailing = jpeg.clone();
        trailing.extend_from_slice(b"vendor metadata after the end marker");
        assert!(open_image(&write("trailing.jpg", &trailing)).is_ok());
        let e = open_image(&write("cut.jpg", &jpeg[..jpeg.len() / 2])).unwrap_err();
        assert!(
            e.contains("cut short") || e.contains("does not decode"),
            "{e}"
        );
    }
}
