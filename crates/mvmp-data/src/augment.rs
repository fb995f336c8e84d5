//! Photometric augmentation of training samples: brightness, contrast, saturation and per-channel colour
//! gains drawn per view. Cameras of one rig expose differently and scenes are lit differently (the
//! synthetic night scenes are about 0.4 times as bright as the day ones and bluish); a network trained
//! without this sees the lighting of its training scenes only.
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use crate::loader::{FrameSample, IMAGENET_MEAN, IMAGENET_STD};
use mvmp_geom::Letterbox;

/// How strongly each view's colours are jittered. Each factor is drawn uniformly from `[1 - x, 1 + x]`
/// per view (`color` per channel); 0 turns that jitter off, and all 0 (the default) leaves images as
/// they are.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Photometric {
    /// Gain on every channel.
    pub brightness: f32,
    /// Scale of the deviation from the view's mean grey.
    pub contrast: f32,
    /// Scale of each pixel's deviation from its own grey.
    pub saturation: f32,
    /// A gain per channel (white balance).
    pub color: f32,
}

/// One view's drawn factors.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Factors {
    brightness: f32,
    contrast: f32,
    saturation: f32,
    color: [f32; 3],
}

impl Photometric {
    /// The first key (`brightness`, ...) whose value is not within [0, 1), with its value.
    pub fn invalid(&self) -> Option<(&'static str, f32)> {
        [
            ("brightness", self.brightness),
            ("contrast", self.contrast),
            ("saturation", self.saturation),
            ("color", self.color),
        ]
        .into_iter()
        .find(|(_, x)| !(0.0..1.0).contains(x))
    }

    pub fn is_off(&self) -> bool {
        *self == Photometric::default()
    }

    /// Jitter every view of `sample` with draws that depend on `seed` only (the caller mixes in the
    /// epoch and the sample's number, so that a resumed run draws the same).
    pub fn apply(&self, sample: &mut FrameSample, seed: u64) {
        if self.is_off() {
            return;
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let plane = 3 * sample.size * sample.size;
        for (v, lb) in sample.letterboxes.iter().enumerate() {
            let f = self.draw(&mut rng);
            jitter_view(&mut sample.images[v * plane..(v + 1) * plane], lb, &f);
        }
    }

    fn draw(&self, rng: &mut impl Rng) -> Factors {
        let mut factor = |x: f32| {
            if x > 0.0 {
                rng.random_range(1.0 - x..=1.0 + x)
            } else {
                1.0
            }
        };
        Factors {
            brightness: factor(self.brightness),
            contrast: factor(self.contrast),
            saturation: factor(self.saturation),
            color: [factor(self.color), factor(self.color), factor(self.color)],
        }
    }
}

/// Jitter the image content of one normalised `[3, S, S]` view in place; the letterbox padding stays 0.
fn jitter_view(view: &mut [f32], lb: &Letterbox, f: &Factors) {
    let s = lb.size as usize;
    let pixels = || {
        (lb.offset_y as usize..(lb.offset_y + lb.content_height) as usize).flat_map(move |y| {
            (lb.offset_x as usize..(lb.offset_x + lb.content_width) as usize)
                .map(move |x| y * s + x)
        })
    };
    let rgb = |view: &[f32], i: usize| {
        std::array::from_fn::<f32, 3, _>(|c| {
            view[c * s * s + i] * IMAGENET_STD[c] + IMAGENET_MEAN[c]
        })
    };
    let grey = |p: [f32; 3]| 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2];
    let count = (lb.content_width * lb.content_height).max(1) as f32;
    let mean_grey = f.brightness * pixels().map(|i| grey(rgb(view, i))).sum::<f32>() / count;
    for i in pixels() {
        let mut p = rgb(view, i).map(|x| x * f.brightness);
        p = p.map(|x| (x - mean_grey) * f.contrast + mean_grey);
        let g = grey(p);
        for c in 0..3 {
            let x = ((p[c] - g) * f.saturation + g) * f.color[c];
            view[c * s * s + i] = (x.clamp(0.0, 1.0) - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sample of two 4 x 4 views letterboxed into 6 x 6 (one padding row above and below, one column
    /// left and right), every content pixel at raw value `raw`.
    fn sample(raw: [f32; 3]) -> FrameSample {
        let lb = Letterbox {
            src_width: 4,
            src_height: 4,
            size: 6,
            content_width: 4,
            content_height: 4,
            offset_x: 1,
            offset_y: 1,
        };
        let s = 6;
        let mut images = vec![0f32; 2 * 3 * s * s];
        for v in 0..2 {
            for c in 0..3 {
                for y in 1..5 {
                    for x in 1..5 {
                        images[v * 3 * s * s + c * s * s + y * s + x] =
                            (raw[c] - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
                    }
                }
            }
        }
        FrameSample {
            scene: "s".into(),
            frame: "f".into(),
            images,
            size: s,
            cameras: vec![],
            letterboxes: vec![lb; 2],
            people: vec![],
            cover: vec![],
        }
    }

    fn raw_at(sample: &FrameSample, view: usize, c: usize, y: usize, x: usize) -> f32 {
        let s = sample.size;
        sample.images[view * 3 * s * s + c * s * s + y * s + x] * IMAGENET_STD[c] + IMAGENET_MEAN[c]
    }

    #[test]
    fn off_leaves_images_bit_for_bit() {
        let before = sample([0.2, 0.3, 0.4]);
        let mut after = before.clone();
        Photometric::default().apply(&mut after, 7);
        assert_eq!(before.images, after.images);
    }

    #[test]
    fn brightness_scales_every_channel_of_a_view_by_one_factor_within_bounds() {
        let mut s = sample([0.2, 0.3, 0.4]);
        let aug = Photometric {
            brightness: 0.5,
            ..Default::default()
        };
        aug.apply(&mut s, 3);
        let mut gains = Vec::new();
        for v in 0..2 {
            let g = raw_at(&s, v, 0, 2, 2) / 0.2;
            // Same factor on the other channels and pixels (1e-5: f32 normalisation round trip).
            assert!((raw_at(&s, v, 1, 3, 4) / 0.3 - g).abs() < 1e-5);
            assert!((raw_at(&s, v, 2, 1, 1) / 0.4 - g).abs() < 1e-5);
            assert!((0.5..=1.5).contains(&g), "gain {g}");
            gains.push(g);
        }
        assert_ne!(gains[0], gains[1], "each view draws its own factor");
        // Padding is what the network sees for "no image": it stays 0 after normalisation.
        let p = s.size;
        assert_eq!(s.images[0], 0.0);
        assert_eq!(s.images[3 * p * p + 2 * p * p + 5 * p + 5], 0.0);
    }

    #[test]
    fn draws_depend_on_the_seed_only() {
        let aug = Photometric {
            brightness: 0.3,
            contrast: 0.3,
            saturation: 0.3,
            color: 0.1,
        };
        let (mut a, mut b, mut c) = (sample([0.5; 3]), sample([0.5; 3]), sample([0.5; 3]));
        aug.apply(&mut a, 11);
        aug.apply(&mut b, 11);
        aug.apply(&mut c, 12);
        assert_eq!(a.images, b.images);
        assert_ne!(a.images, c.images);
    }

    #[test]
    fn contrast_and_saturation_keep_a_grey_flat_view_grey() {
        // A flat grey view is its own mean and its own grey: contrast and saturation leave it alone.
        let mut s = sample([0.5; 3]);
        let aug = Photometric {
            contrast: 0.9,
            saturation: 0.9,
            ..Default::default()
        };
        aug.apply(&mut s, 5);
        for c in 0..3 {
            assert!((raw_at(&s, 1, c, 2, 3) - 0.5).abs() < 1e-5);
        }
    }

    #[test]
    fn out_of_range_strengths_are_named() {
        let aug = Photometric {
            saturation: 1.0,
            ..Default::default()
        };
        assert_eq!(aug.invalid(), Some(("saturation", 1.0)));
        let nan = Photometric {
            brightness: f32::NAN,
            ..Default::default()
        };
        assert_eq!(nan.invalid().map(|(k, _)| k), Some("brightness"));
        assert_eq!(Photometric::default().invalid(), None);
    }
}
