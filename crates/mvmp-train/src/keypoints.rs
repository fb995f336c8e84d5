//! How well 2D joint heatmaps place the joints: for each joint a person shows in a view, the distance
//! from the true 2D joint to its map's peak near it. `mvmp model probe` reports it beside the volumes'
//! pose read, since the heatmap volume can carry no more of the pose than the 2D maps place.

use mvmp_data::loader::PersonGt;

/// Radius (map pixels) of the window round each true 2D joint in which the map's peak is looked for:
/// a peak further off is another joint's or another person's.
pub const KEYPOINT_WINDOW: isize = 3;

/// For each view and heatmap joint (`joints`, SMPL-X indices, in the maps' channel order) that `person`
/// shows: the distance in network pixels from the true 2D joint to the peak of its map `[V][J][h][w]`
/// within [`KEYPOINT_WINDOW`] map pixels, refined by the centroid of the non-negative values round it.
/// Map pixel `x` covers network pixel `(x + 0.5) * stride - 0.5`, as the heatmap targets are drawn.
pub fn keypoint_errors(
    maps: &[f32],
    [h, w]: [usize; 2],
    person: &PersonGt,
    joints: &[usize],
    stride: f32,
) -> Vec<f32> {
    let j = joints.len();
    let mut out = Vec::new();
    for (vi, view) in person.joints_2d.iter().enumerate() {
        for (k, &ji) in joints.iter().enumerate() {
            let Some(&[u, v, vis]) = view.get(ji) else {
                continue;
            };
            let Some(map) = maps.get((vi * j + k) * h * w..(vi * j + k + 1) * h * w) else {
                continue;
            };
            if vis <= 0.5 {
                continue;
            }
            let centre = [(u + 0.5) / stride - 0.5, (v + 0.5) / stride - 0.5];
            if let Some([px, py]) = window_peak(map, [h, w], centre) {
                let (x, y) = ((px + 0.5) * stride - 0.5, (py + 0.5) * stride - 0.5);
                out.push(((x - u).powi(2) + (y - v).powi(2)).sqrt());
            }
        }
    }
    out
}

/// The largest value of `map` `[h][w]` within [`KEYPOINT_WINDOW`] of `centre` (map pixels, x then y),
/// refined by the centroid of the non-negative values in its 3 x 3 neighbourhood; `None` when the window
/// lies outside the map.
fn window_peak(map: &[f32], [h, w]: [usize; 2], [cx, cy]: [f32; 2]) -> Option<[f32; 2]> {
    let at = |x: isize, y: isize| {
        (x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h)
            .then(|| map[y as usize * w + x as usize])
    };
    let (x0, y0) = (cx.round() as isize, cy.round() as isize);
    let r = KEYPOINT_WINDOW;
    let (_, bx, by) = (-r..=r)
        .flat_map(|dy| (-r..=r).map(move |dx| (x0 + dx, y0 + dy)))
        .filter_map(|(x, y)| at(x, y).map(|val| (val, x, y)))
        .max_by(|a, b| a.0.total_cmp(&b.0))?;
    let (mut sw, mut sx, mut sy) = (0.0f32, 0.0f32, 0.0f32);
    for (x, y) in (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (bx + dx, by + dy))) {
        if let Some(val) = at(x, y) {
            let val = val.max(0.0);
            (sw, sx, sy) = (sw + val, sx + val * x as f32, sy + val * y as f32);
        }
    }
    Some(if sw > 0.0 {
        [sx / sw, sy / sw]
    } else {
        [bx as f32, by as f32]
    })
}

/// A summary of keypoint errors (network pixels).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct KeypointSummary {
    pub keypoints: usize,
    pub median_px: f32,
    /// Fractions within one and two map pixels (`stride` and twice it).
    pub within_one_map_pixel: f32,
    pub within_two_map_pixels: f32,
}

pub fn summarise(errors: &[f32], stride: f32) -> KeypointSummary {
    let mut e = errors.to_vec();
    e.sort_by(f32::total_cmp);
    let n = e.len();
    let frac = |d: f32| e.iter().filter(|&&x| x <= d).count() as f32 / n.max(1) as f32;
    KeypointSummary {
        keypoints: n,
        median_px: if n == 0 { f32::NAN } else { e[n / 2] },
        within_one_map_pixel: frac(stride),
        within_two_map_pixels: frac(2.0 * stride),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn person(views: Vec<Vec<[f32; 3]>>) -> PersonGt {
        PersonGt {
            id: 0,
            pose: Vec::new(),
            betas: [0.0; mvmp_smplx::names::NUM_BETAS],
            expression: [0.0; mvmp_smplx::names::NUM_EXPRESSION],
            pelvis: [0.0; 3],
            joints_3d: Vec::new(),
            joints_2d: views,
            joint_valid: Vec::new(),
            smplx: true,
        }
    }

    #[test]
    fn the_peak_near_the_true_joint_is_found_and_measured_in_network_pixels() {
        // One view, two heatmap joints (SMPL-X 0 and 4) on 8 x 8 maps at stride 4.
        let (h, w, stride) = (8, 8, 4.0);
        let mut maps = vec![0.0f32; 2 * h * w];
        // Joint 0's map peaks at map pixel (3, 2) alone: network pixel (13.5, 9.5).
        maps[2 * w + 3] = 1.0;
        // Joint 4's map: a far stronger peak 5 map pixels away (outside the window) and a weak one at
        // (5, 5) with a neighbour at (6, 5) of equal weight: the centroid is (5.5, 5).
        maps[h * w + 7 * w] = 9.0;
        maps[h * w + 5 * w + 5] = 0.5;
        maps[h * w + 5 * w + 6] = 0.5;
        let mut view = vec![[0.0f32; 3]; 5];
        view[0] = [13.5, 13.5, 1.0]; // 4 network pixels below the peak
        view[4] = [21.5, 21.5, 1.0]; // map (5.25, 5.25)
        let p = person(vec![view.clone()]);
        let e = keypoint_errors(&maps, [h, w], &p, &[0, 4], stride);
        assert_eq!(e.len(), 2);
        assert!((e[0] - 4.0).abs() < 1e-5, "{e:?}");
        // Peak (5.5, 5) -> network (23.5, 21.5): 2 pixels to the right of the joint.
        assert!((e[1] - 2.0).abs() < 1e-5, "{e:?}");
        // A hidden joint is not counted.
        view[4][2] = 0.0;
        assert_eq!(
            keypoint_errors(&maps, [h, w], &person(vec![view]), &[0, 4], stride).len(),
            1
        );
    }

    #[test]
    fn the_summary_counts_within_one_and_two_map_pixels() {
        let s = summarise(&[1.0, 3.0, 5.0, 9.0], 4.0);
        assert_eq!(s.keypoints, 4);
        assert_eq!(s.median_px, 5.0);
        assert_eq!(s.within_one_map_pixel, 0.5);
        assert_eq!(s.within_two_map_pixels, 0.75);
    }
}
