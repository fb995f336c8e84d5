//! Joint sets of datasets whose ground truth is 3D joints rather than SMPL-X, and the mapping from the
//! 127 SMPL-X output joints to each. The mapping picks the SMPL-X joint at the same anatomical place; it is
//! a definition, not a learned regressor, so joints whose definitions differ (Human3.6M's spine and head
//! top, Panoptic's neck) carry a systematic offset that every method scored this way shares. Reports name
//! the set used.

/// A joint set to score on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointSet {
    /// All 127 SMPL-X joints (55 LBS, 21 vertex joints, 51 face landmarks).
    Smplx127,
    /// CMU Panoptic's first 15 joints19 joints (as VoxelPose evaluates).
    Panoptic15,
    /// Human3.6M's 17 joints (pelvis, right leg, left leg, spine, thorax, neck/nose, head, left arm, right
    /// arm), the order of the common 17-joint subset.
    H36m17,
}

/// Panoptic joints19[0..15] and the SMPL-X joint taken for each.
pub const PANOPTIC15: [(&str, &str); 15] = [
    ("neck", "neck"),
    ("nose", "nose"),
    ("body_center", "pelvis"),
    ("l_shoulder", "left_shoulder"),
    ("l_elbow", "left_elbow"),
    ("l_wrist", "left_wrist"),
    ("l_hip", "left_hip"),
    ("l_knee", "left_knee"),
    ("l_ankle", "left_ankle"),
    ("r_shoulder", "right_shoulder"),
    ("r_elbow", "right_elbow"),
    ("r_wrist", "right_wrist"),
    ("r_hip", "right_hip"),
    ("r_knee", "right_knee"),
    ("r_ankle", "right_ankle"),
];

/// Human3.6M's 17 joints and the SMPL-X joint taken for each.
pub const H36M17: [(&str, &str); 17] = [
    ("pelvis", "pelvis"),
    ("r_hip", "right_hip"),
    ("r_knee", "right_knee"),
    ("r_ankle", "right_ankle"),
    ("l_hip", "left_hip"),
    ("l_knee", "left_knee"),
    ("l_ankle", "left_ankle"),
    ("spine", "spine2"),
    ("thorax", "neck"),
    ("neck_nose", "nose"),
    ("head", "head"),
    ("l_shoulder", "left_shoulder"),
    ("l_elbow", "left_elbow"),
    ("l_wrist", "left_wrist"),
    ("r_shoulder", "right_shoulder"),
    ("r_elbow", "right_elbow"),
    ("r_wrist", "right_wrist"),
];

impl std::str::FromStr for JointSet {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        JointSet::by_name(s)
            .ok_or_else(|| format!("{s:?}: expected smplx127, panoptic15 or h36m17"))
    }
}

impl JointSet {
    pub fn by_name(name: &str) -> Option<JointSet> {
        match name {
            "smplx127" => Some(JointSet::Smplx127),
            "panoptic15" => Some(JointSet::Panoptic15),
            "h36m17" => Some(JointSet::H36m17),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            JointSet::Smplx127 => "smplx127",
            JointSet::Panoptic15 => "panoptic15",
            JointSet::H36m17 => "h36m17",
        }
    }

    /// Indices into the 127 SMPL-X output joints, in the set's order.
    pub fn smplx_indices(self) -> Vec<usize> {
        let table: &[(&str, &str)] = match self {
            JointSet::Smplx127 => {
                return (0..crate::names::NUM_JOINTS_WITH_LANDMARKS).collect();
            }
            JointSet::Panoptic15 => &PANOPTIC15,
            JointSet::H36m17 => &H36M17,
        };
        table
            .iter()
            .map(|(_, s)| crate::names::joint_index(s).expect("a SMPL-X joint name"))
            .collect()
    }

    /// The set's joints picked from SMPL-X joints (127, world).
    pub fn select(self, smplx: &[[f64; 3]]) -> Vec<[f64; 3]> {
        self.smplx_indices().into_iter().map(|i| smplx[i]).collect()
    }

    /// The index of the root (pelvis / body centre) in the set, used for matching.
    pub fn root(self) -> usize {
        match self {
            JointSet::Panoptic15 => 2,
            _ => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::names::joint_name;

    #[test]
    fn mappings_point_at_the_named_smplx_joints() {
        let p = JointSet::Panoptic15.smplx_indices();
        assert_eq!(p.len(), 15);
        assert_eq!(p[2], 0, "body centre = pelvis");
        assert_eq!(joint_name(p[1]), Some("nose"));
        assert!(p[1] >= 55, "the nose is a vertex joint");
        let h = JointSet::H36m17.smplx_indices();
        assert_eq!(h.len(), 17);
        // Right leg first (indices 1-3), then the left leg, as the 17-joint order has it.
        assert_eq!(
            h[1..7]
                .iter()
                .map(|&i| joint_name(i).unwrap())
                .collect::<Vec<_>>(),
            [
                "right_hip",
                "right_knee",
                "right_ankle",
                "left_hip",
                "left_knee",
                "left_ankle"
            ]
        );
        assert_eq!(JointSet::Smplx127.smplx_indices().len(), 127);
        for s in [JointSet::Smplx127, JointSet::Panoptic15, JointSet::H36m17] {
            assert_eq!(JointSet::by_name(s.name()), Some(s));
            assert_eq!(
                s.smplx_indices()[s.root()],
                0,
                "{}: the root is the pelvis",
                s.name()
            );
        }
        let joints: Vec<[f64; 3]> = (0..127).map(|i| [i as f64, 0.0, 0.0]).collect();
        assert_eq!(
            JointSet::Panoptic15.select(&joints)[5],
            [20.0, 0.0, 0.0],
            "left wrist = 20"
        );
    }
}
