//! SMPL-X joint names, the kinematic tree, the vertex-based extra joints and the regression order,
//! in one place (smplx's `joint_names.py` and `vertex_ids.py`).

/// Number of joints driven by linear blend skinning.
pub const NUM_JOINTS: usize = 55;
/// Joints with a pose-corrective blend shape (all but the root).
pub const NUM_POSE_JOINTS: usize = NUM_JOINTS - 1;
/// Rotations the network regresses (docs/architecture.md, SMPL-X): global, 21 body, 15 left hand,
/// 15 right hand, jaw.
pub const NUM_REGRESSED: usize = 53;
/// Body joints (pelvis excluded) among them, right after the global orientation.
pub const NUM_BODY: usize = 21;
/// Body-model shape and expression components used by mvmp.
pub const NUM_BETAS: usize = 10;
pub const NUM_EXPRESSION: usize = 10;
/// Joints with the face landmarks: 55 + 21 vertex joints + 51 landmarks.
pub const NUM_JOINTS_WITH_LANDMARKS: usize = 127;
/// Vertices of the SMPL-X mesh (the stand-in body model has as many).
pub const NUM_VERTICES: usize = 10475;

/// The 55 LBS joints in model order.
pub const JOINT_NAMES: [&str; NUM_JOINTS] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "jaw",
    "left_eye_smplhf",
    "right_eye_smplhf",
    "left_index1",
    "left_index2",
    "left_index3",
    "left_middle1",
    "left_middle2",
    "left_middle3",
    "left_pinky1",
    "left_pinky2",
    "left_pinky3",
    "left_ring1",
    "left_ring2",
    "left_ring3",
    "left_thumb1",
    "left_thumb2",
    "left_thumb3",
    "right_index1",
    "right_index2",
    "right_index3",
    "right_middle1",
    "right_middle2",
    "right_middle3",
    "right_pinky1",
    "right_pinky2",
    "right_pinky3",
    "right_ring1",
    "right_ring2",
    "right_ring3",
    "right_thumb1",
    "right_thumb2",
    "right_thumb3",
];

/// Parent of each LBS joint; the root has none (-1).
pub const PARENTS: [i32; NUM_JOINTS] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15, 20, 25,
    26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38, 21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49,
    50, 21, 52, 53,
];

/// Joints 55..75: (name, vertex index) of the vertex-based extra joints, in smplx's order.
pub const EXTRA_VERTEX_JOINTS: [(&str, usize); 21] = [
    ("nose", 9120),
    ("right_eye", 9929),
    ("left_eye", 9448),
    ("right_ear", 616),
    ("left_ear", 6),
    ("left_big_toe", 5770),
    ("left_small_toe", 5780),
    ("left_heel", 8846),
    ("right_big_toe", 8463),
    ("right_small_toe", 8474),
    ("right_heel", 8635),
    ("left_thumb", 5361),
    ("left_index", 4933),
    ("left_middle", 5058),
    ("left_ring", 5169),
    ("left_pinky", 5286),
    ("right_thumb", 8079),
    ("right_index", 7669),
    ("right_middle", 7794),
    ("right_ring", 7905),
    ("right_pinky", 8022),
];

/// Joints 76..126: the 51 static face landmarks, in smplx's order.
pub const LANDMARK_NAMES: [&str; 51] = [
    "right_eye_brow1",
    "right_eye_brow2",
    "right_eye_brow3",
    "right_eye_brow4",
    "right_eye_brow5",
    "left_eye_brow5",
    "left_eye_brow4",
    "left_eye_brow3",
    "left_eye_brow2",
    "left_eye_brow1",
    "nose1",
    "nose2",
    "nose3",
    "nose4",
    "right_nose_2",
    "right_nose_1",
    "nose_middle",
    "left_nose_1",
    "left_nose_2",
    "right_eye1",
    "right_eye2",
    "right_eye3",
    "right_eye4",
    "right_eye5",
    "right_eye6",
    "left_eye4",
    "left_eye3",
    "left_eye2",
    "left_eye1",
    "left_eye6",
    "left_eye5",
    "right_mouth_1",
    "right_mouth_2",
    "right_mouth_3",
    "mouth_top",
    "left_mouth_3",
    "left_mouth_2",
    "left_mouth_1",
    "left_mouth_5",
    "left_mouth_4",
    "mouth_bottom",
    "right_mouth_4",
    "right_mouth_5",
    "right_lip_1",
    "right_lip_2",
    "lip_top",
    "left_lip_2",
    "left_lip_1",
    "left_lip_3",
    "lip_bottom",
    "right_lip_3",
];

/// Name of output joint `i` (LBS joints, then vertex joints, then landmarks).
pub fn joint_name(i: usize) -> Option<&'static str> {
    if i < NUM_JOINTS {
        Some(JOINT_NAMES[i])
    } else if i < NUM_JOINTS + EXTRA_VERTEX_JOINTS.len() {
        Some(EXTRA_VERTEX_JOINTS[i - NUM_JOINTS].0)
    } else {
        LANDMARK_NAMES
            .get(i - NUM_JOINTS - EXTRA_VERTEX_JOINTS.len())
            .copied()
    }
}

/// Index of a joint by name among all output joints.
pub fn joint_index(name: &str) -> Option<usize> {
    (0..NUM_JOINTS_WITH_LANDMARKS).find(|&i| joint_name(i) == Some(name))
}

/// For each of the 53 regressed rotations, the LBS joint it drives: global orientation (0), the 21 body
/// joints (1..=21), the 15 left-hand joints (25..=39), the 15 right-hand joints (40..=54), jaw (22).
pub const REGRESSED_TO_JOINT: [usize; NUM_REGRESSED] = {
    let mut out = [0usize; NUM_REGRESSED];
    let mut i = 0;
    while i < 22 {
        out[i] = i;
        i += 1;
    }
    while i < 52 {
        out[i] = i + 3;
        i += 1;
    }
    out[52] = 22;
    out
};

/// The standard smplx parameter keys and how many axis-angle values each holds.
pub const POSE_KEYS: [(&str, usize, usize); 7] = [
    // (key, first LBS joint, number of joints)
    ("global_orient", 0, 1),
    ("body_pose", 1, 21),
    ("jaw_pose", 22, 1),
    ("leye_pose", 23, 1),
    ("reye_pose", 24, 1),
    ("left_hand_pose", 25, 15),
    ("right_hand_pose", 40, 15),
];
