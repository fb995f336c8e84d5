//! How different the predicted people are from each other. A decoder that has not learned to read its
//! input predicts one body for everyone (the mean): its errors look like those of a poor model, but its
//! spread across people is ~0 while the ground truth's is tens of degrees. Training logs both spreads of
//! its predictions at every validation.
use nalgebra::{Rotation3, Vector3};

/// The facing direction of a body in the z-up world, degrees in (-180, 180]: its model-frame forward axis
/// (+z of SMPL-X) turned by the global orientation (axis-angle), projected on the ground.
pub fn heading_deg(global_orient: [f64; 3]) -> f64 {
    let forward = Rotation3::from_scaled_axis(Vector3::from(global_orient)) * Vector3::z();
    forward.y.atan2(forward.x).to_degrees()
}

/// The angular deviation of headings (degrees): sqrt(2 (1 - R)) with R the length of their mean unit
/// vector, in degrees. 0 when every person faces one way, about 81 for headings spread evenly. `None`
/// for fewer than two people.
pub fn heading_spread_deg(headings_deg: &[f64]) -> Option<f64> {
    if headings_deg.len() < 2 {
        return None;
    }
    let n = headings_deg.len() as f64;
    let (c, s) = headings_deg.iter().fold((0.0, 0.0), |(c, s), h| {
        let r = h.to_radians();
        (c + r.cos(), s + r.sin())
    });
    let r = (c * c + s * s).sqrt() / n;
    Some((2.0 * (1.0 - r).max(0.0)).sqrt().to_degrees())
}

/// The spread of articulations (degrees): the root mean square over the axis-angle components of the
/// poses (each person one equal-length vector, radians) of their standard deviation across people.
/// `None` for fewer than two people.
pub fn pose_spread_deg(poses: &[Vec<f64>]) -> Option<f64> {
    let first = poses.first()?;
    if poses.len() < 2 || first.is_empty() {
        return None;
    }
    let n = poses.len() as f64;
    let var_sum: f64 = (0..first.len())
        .map(|c| {
            let mean = poses.iter().map(|p| p[c]).sum::<f64>() / n;
            poses.iter().map(|p| (p[c] - mean).powi(2)).sum::<f64>() / n
        })
        .sum();
    Some((var_sum / first.len() as f64).sqrt().to_degrees())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heading_of_a_turn_about_the_vertical() {
        // A body turned by a about the world's z axis after the y-up to z-up turn (+90 deg about x), whose
        // forward +z then points along -y: heading -90 + a.
        for a in [0.0f64, 30.0, 135.0] {
            let up = Rotation3::from_scaled_axis(Vector3::x() * std::f64::consts::FRAC_PI_2);
            let turn = Rotation3::from_scaled_axis(Vector3::z() * a.to_radians());
            let aa = (turn * up).scaled_axis();
            let h = heading_deg([aa.x, aa.y, aa.z]);
            assert!((h - (a - 90.0)).abs() < 1e-9, "{a}: {h}");
        }
    }

    #[test]
    fn spreads_of_hand_derived_cases() {
        // One heading for all: 0. Two at +-60 deg around any mean: R = cos 60 = 0.5, sqrt(2 * 0.5) = 1 rad.
        // (sqrt(2 (1 - R)) turns rounding of R near 1 into ~1e-6 degrees.)
        assert!(heading_spread_deg(&[-94.0, -94.0, -94.0]).unwrap() < 1e-5);
        let s = heading_spread_deg(&[10.0 + 60.0, 10.0 - 60.0]).unwrap();
        assert!((s - 1f64.to_degrees()).abs() < 1e-9, "{s}");
        // Opposite headings: R = 0, sqrt(2) rad.
        let s = heading_spread_deg(&[0.0, 180.0]).unwrap();
        assert!((s - 2f64.sqrt().to_degrees()).abs() < 1e-9, "{s}");
        assert_eq!(heading_spread_deg(&[5.0]), None);
        // Two people differing by 2a in one of two components: std a in it, 0 in the other; RMS a / sqrt 2.
        let a = 0.3;
        let s = pose_spread_deg(&[vec![0.1 - a, 0.5], vec![0.1 + a, 0.5]]).unwrap();
        assert!((s - (a / 2f64.sqrt()).to_degrees()).abs() < 1e-9, "{s}");
        assert_eq!(pose_spread_deg(&[vec![0.2; 63], vec![0.2; 63]]), Some(0.0));
        assert_eq!(pose_spread_deg(&[vec![0.2; 63]]), None);
    }
}
