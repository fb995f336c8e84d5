//! The synthetic-scene configuration (`configs/synth/*.toml`). Unknown keys are an error; every key has a
//! default; `validate` names the key path and the bad value.
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::DataError;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SynthConfig {
    /// Dataset name written into dataset.json.
    pub name: String,
    /// Master seed: the same seed gives byte-identical output.
    pub seed: u64,
    /// Number of scenes.
    pub scenes: usize,
    /// Frames per scene (people move between frames).
    pub frames_per_scene: usize,
    /// People per scene, inclusive range `[min, max]` (paper: 10-30).
    pub people: [usize; 2],
    /// Capture area `[x, y]` in metres, centred at the origin (paper: up to 30 x 30).
    pub area: [f64; 2],
    /// Image `[width, height]` in pixels.
    pub image_size: [u32; 2],
    /// Image file format: "png" or "jpeg".
    pub image_format: String,
    /// Write 16-bit depth maps.
    pub depth: bool,
    /// Write instance masks.
    pub masks: bool,
    /// Body model: `standin:SEED` or a path to an SMPLX_*.npz.
    pub body_model: String,
    pub cameras: CameraConfig,
    pub lighting: LightingConfig,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            name: "synthetic".into(),
            seed: 0,
            scenes: 3,
            frames_per_scene: 2,
            people: [4, 8],
            area: [8.0, 8.0],
            image_size: [256, 256],
            image_format: "png".into(),
            depth: true,
            masks: true,
            body_model: "standin:0".into(),
            cameras: CameraConfig::default(),
            lighting: LightingConfig::default(),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// Number of cameras, spread over the rings (ignored when `listed` is given). At most 50.
    pub count: usize,
    /// Rings of cameras around the area: height above the ground and distance from the centre (metres).
    pub rings: Vec<Ring>,
    /// Horizontal field of view range in degrees `[min, max]`, drawn per camera.
    pub fov_deg: [f64; 2],
    /// Range of the radial distortion k1 `[min, max]` (k2 = -k1/4; 0 for an ideal lens).
    pub k1: [f64; 2],
    /// Height the cameras look at (metres).
    pub look_at_height: f64,
    /// Explicit cameras instead of rings.
    pub listed: Vec<ListedCamera>,
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig {
            count: 4,
            rings: vec![Ring {
                height: 3.0,
                radius: 9.0,
            }],
            fov_deg: [55.0, 65.0],
            k1: [0.0, 0.0],
            look_at_height: 0.9,
            listed: Vec::new(),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ring {
    pub height: f64,
    pub radius: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListedCamera {
    pub position: [f64; 3],
    pub look_at: [f64; 3],
    pub fov_deg: f64,
    #[serde(default)]
    pub k1: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LightingConfig {
    /// Fraction of scenes lit as night (dim, bluish, a low light); the rest are day.
    pub night_fraction: f64,
}

impl Default for LightingConfig {
    fn default() -> Self {
        LightingConfig {
            night_fraction: 0.25,
        }
    }
}

impl SynthConfig {
    /// Read and validate a TOML config.
    pub fn read(path: &Path) -> Result<Self, DataError> {
        let text = std::fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
        let cfg: SynthConfig = toml::from_str(&text)
            .map_err(|e| DataError::file(path, format!("invalid config: {e}")))?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    pub fn validate(&self, path: &Path) -> Result<(), DataError> {
        self.check_scenes()
            .and_then(|()| self.cameras.check())
            .map_err(|(key, what)| DataError::Config {
                path: path.into(),
                key,
                what,
            })
    }

    /// Scene, frame and people counts, area, images and lighting: the offending key and why.
    fn check_scenes(&self) -> Result<(), (String, String)> {
        let bad = |key: &str, what: String| Err((key.to_string(), what));
        if let Err(what) = mvmp_smplx::check_reference(&self.body_model) {
            return bad("body_model", what);
        }
        for (key, n) in [
            ("scenes", self.scenes),
            ("frames_per_scene", self.frames_per_scene),
        ] {
            if !(1..=MAX_COUNT).contains(&n) {
                return bad(key, format!("{n}: expected 1 to {MAX_COUNT}"));
            }
        }
        if self.scenes * self.frames_per_scene > MAX_COUNT {
            return bad(
                "scenes, frames_per_scene",
                format!(
                    "{} x {}: at most {MAX_COUNT} frames in all",
                    self.scenes, self.frames_per_scene
                ),
            );
        }
        let [lo, hi] = self.people;
        if lo == 0 || lo > hi || hi > 254 {
            return bad(
                "people",
                format!("{:?}: expected 1 <= min <= max <= 254", self.people),
            );
        }
        if !self
            .area
            .iter()
            .all(|a| a.is_finite() && *a >= 2.0 && *a <= 100.0)
        {
            return bad(
                "area",
                format!("{:?}: each side must be 2 to 100 m", self.area),
            );
        }
        let [w, h] = self.image_size;
        if !(16..=8192).contains(&w) || !(16..=8192).contains(&h) {
            return bad(
                "image_size",
                format!("{:?}: 16 to 8192 pixels", self.image_size),
            );
        }
        if !["png", "jpeg"].contains(&self.image_format.as_str()) {
            return bad(
                "image_format",
                format!("{:?}: expected \"png\" or \"jpeg\"", self.image_format),
            );
        }
        if !(0.0..=1.0).contains(&self.lighting.night_fraction) {
            return bad(
                "lighting.night_fraction",
                format!("{}: expected 0 to 1", self.lighting.night_fraction),
            );
        }
        Ok(())
    }
}

/// Most scenes, frames per scene, and frames in all, of one synthetic set (a million frames of 4 views
/// at 256 pixels are about 500 GB).
pub const MAX_COUNT: usize = 1_000_000;

fn fov_ok(f: f64) -> bool {
    f.is_finite() && (10.0..=150.0).contains(&f)
}

impl CameraConfig {
    /// The cameras: their count and rings, or the listed ones; field of view, distortion and aim.
    fn check(&self) -> Result<(), (String, String)> {
        let bad = |key: &str, what: String| Err((key.to_string(), what));
        let c = self;
        if c.listed.is_empty() {
            c.check_rings()?;
        } else if c.listed.len() > 50 {
            return bad(
                "cameras.listed",
                format!("{} cameras: at most 50", c.listed.len()),
            );
        }
        if !(fov_ok(c.fov_deg[0]) && fov_ok(c.fov_deg[1]) && c.fov_deg[0] <= c.fov_deg[1]) {
            return bad(
                "cameras.fov_deg",
                format!("{:?}: expected 10 to 150 degrees, min <= max", c.fov_deg),
            );
        }
        if !(c.k1[0] <= c.k1[1] && c.k1.iter().all(|k| k.is_finite() && k.abs() <= 0.5)) {
            return bad(
                "cameras.k1",
                format!("{:?}: expected |k1| <= 0.5, min <= max", c.k1),
            );
        }
        if !(c.look_at_height.is_finite() && c.look_at_height.abs() <= 100.0) {
            return bad(
                "cameras.look_at_height",
                format!(
                    "{}: expected a finite height within 100 m",
                    c.look_at_height
                ),
            );
        }
        for (i, l) in c.listed.iter().enumerate() {
            let finite =
                (l.position.iter().chain(&l.look_at)).all(|v| v.is_finite() && v.abs() <= 1000.0);
            let k1_ok = l.k1.is_finite() && l.k1.abs() <= 0.5;
            if !finite || !fov_ok(l.fov_deg) || !k1_ok || l.position == l.look_at {
                return bad(
                    &format!("cameras.listed[{i}]"),
                    "position and look_at must be distinct and within 1000 m, fov_deg 10 to 150, |k1| <= 0.5".into(),
                );
            }
        }
        Ok(())
    }

    /// The camera count and rings of a generated rig.
    fn check_rings(&self) -> Result<(), (String, String)> {
        if self.count == 0 || self.count > 50 {
            return Err((
                "cameras.count".into(),
                format!("{}: expected 1 to 50", self.count),
            ));
        }
        if self.rings.is_empty() {
            return Err(("cameras.rings".into(), "at least one ring is needed".into()));
        }
        for (i, r) in self.rings.iter().enumerate() {
            let within = |x: f64, lo: f64| x.is_finite() && x > lo && x <= 1000.0;
            if !(within(r.height, 0.2) && within(r.radius, 1.0)) {
                return Err((
                    format!("cameras.rings[{i}]"),
                    format!(
                        "height {} and radius {}: expected 0.2 to 1000 m and 1 to 1000 m",
                        r.height, r.radius
                    ),
                ));
            }
        }
        Ok(())
    }
}
