//! People for synthetic scenes: shape, appearance, a plausible pose from anatomical joint-angle ranges,
//! heading, and placement close enough to touch but not to interpenetrate.
//!
//! Angles are axis-angle in the body's rest frame (y up, facing +z, the person's left at +x): hip flexion
//! is a rotation about -x, knee flexion about +x, the left shoulder lowers the arm about -z and the right
//! about +z, elbows bend forward about -y (left) and +y (right).
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// What a person is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activity {
    Standing,
    Walking,
    Running,
    Gesturing,
    Crouching,
}

impl Activity {
    pub fn sample(rng: &mut ChaCha8Rng) -> Self {
        match rng.random_range(0..100) {
            0..30 => Activity::Standing,
            30..60 => Activity::Walking,
            60..70 => Activity::Running,
            70..88 => Activity::Gesturing,
            _ => Activity::Crouching,
        }
    }

    /// Metres moved per frame along the heading.
    pub fn speed(self) -> f64 {
        match self {
            Activity::Walking => 0.35,
            Activity::Running => 0.8,
            _ => 0.0,
        }
    }
}

/// Colours of one person (linear RGB).
#[derive(Debug, Clone, Copy)]
pub struct Appearance {
    pub skin: [f32; 3],
    pub shirt: [f32; 3],
    /// The torso's front (what the open jacket `shirt` shows), lighter than the jacket.
    pub shirt_front: [f32; 3],
    pub pants: [f32; 3],
    pub shoes: [f32; 3],
    pub hair: [f32; 3],
    pub long_sleeves: bool,
}

/// Black, dark brown, brown, auburn, blond, grey.
const HAIR: [[f32; 3]; 6] = [
    [0.03, 0.03, 0.03],
    [0.10, 0.06, 0.04],
    [0.25, 0.15, 0.08],
    [0.35, 0.12, 0.05],
    [0.75, 0.62, 0.35],
    [0.55, 0.55, 0.55],
];

const SKIN: [[f32; 3]; 6] = [
    [0.93, 0.76, 0.64],
    [0.85, 0.64, 0.50],
    [0.72, 0.52, 0.38],
    [0.55, 0.37, 0.25],
    [0.40, 0.26, 0.17],
    [0.28, 0.18, 0.12],
];

/// A hair colour picked from the clothes already drawn, not from the generator: a draw of its own would
/// move every later draw and so every scene made before hair existed.
fn hair_of(shirt: [f32; 3], pants: [f32; 3]) -> [f32; 3] {
    let mix = (shirt[0] * 7919.0 + shirt[2] * 104_729.0 + pants[1] * 1_299_709.0) as u64;
    HAIR[(mix % HAIR.len() as u64) as usize]
}

/// A jacket (the torso's back and the sleeves) and what it shows in front, from one drawn colour (no
/// draw of its own, as for hair): the front is always the lighter, by 0.1 to 0.7 in every channel, so that
/// "lighter here" means "the front" for every person, by day and at night.
pub(crate) fn jacket_and_front(drawn: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    (drawn.map(|c| 0.6 * c), drawn.map(|c| 0.7 + 0.3 * c))
}

impl Appearance {
    pub fn sample(rng: &mut ChaCha8Rng) -> Self {
        let mut colour =
            |lo: f32, hi: f32| -> [f32; 3] { std::array::from_fn(|_| rng.random_range(lo..hi)) };
        let (shirt, shirt_front) = jacket_and_front(colour(0.05, 0.95));
        let pants = colour(0.03, 0.45);
        let shoes = colour(0.02, 0.3);
        Appearance {
            skin: SKIN[rng.random_range(0..SKIN.len())],
            shirt,
            shirt_front,
            pants,
            shoes,
            long_sleeves: rng.random_bool(0.5),
            hair: hair_of(shirt, pants),
        }
    }
}

/// One person's state in a scene.
#[derive(Debug, Clone)]
pub struct PersonState {
    pub id: u32,
    pub activity: Activity,
    /// Facing direction in the world: `(sin h, -cos h)`.
    pub heading: f64,
    /// Ground position of the pelvis (x, y).
    pub position: [f64; 2],
    /// Gait phase (radians).
    pub phase: f64,
    pub betas: [f64; NUM_BETAS],
    pub expression: [f64; NUM_EXPRESSION],
    pub appearance: Appearance,
    /// Full pose: 55 x 3 axis-angle (joint 0 is the global orientation).
    pub pose: Vec<f64>,
}

fn set(pose: &mut [f64], joint: usize, aa: [f64; 3]) {
    pose[joint * 3..joint * 3 + 3].copy_from_slice(&aa);
}

fn u(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    rng.random_range(lo..hi)
}

/// The full pose for an activity and phase (global orientation from the heading). The draws from
/// `rng` follow one fixed order (arms and head at rest, the activity's, then hands and jaw), so that a
/// seed makes the same people.
pub fn sample_pose(activity: Activity, heading: f64, phase: f64, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let mut p = vec![0.0; mvmp_smplx::names::NUM_JOINTS * 3];
    // Global: y-up rest frame to z-up world, then the heading about world z.
    let r = nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), heading)
        * nalgebra::Rotation3::from_matrix_unchecked(mvmp_geom::rotation::y_up_to_z_up());
    let g = r.scaled_axis();
    set(&mut p, 0, [g.x, g.y, g.z]);
    // Arms at rest hang by the sides.
    let arm_down = u(rng, 1.15, 1.4);
    set(&mut p, 16, [0.0, u(rng, -0.15, 0.15), -arm_down]);
    set(&mut p, 17, [0.0, u(rng, -0.15, 0.15), arm_down]);
    set(&mut p, 18, [0.0, -u(rng, 0.05, 0.4), 0.0]);
    set(&mut p, 19, [0.0, u(rng, 0.05, 0.4), 0.0]);
    set(&mut p, 15, [u(rng, -0.2, 0.25), u(rng, -0.5, 0.5), 0.0]);
    set(&mut p, 12, [u(rng, -0.1, 0.15), 0.0, 0.0]);
    match activity {
        Activity::Standing => standing(&mut p, rng),
        Activity::Walking | Activity::Running => gait(&mut p, activity, phase, arm_down),
        Activity::Gesturing => gesturing(&mut p, rng),
        Activity::Crouching => crouching(&mut p, rng),
    }
    hands_and_jaw(&mut p, rng);
    p
}

fn standing(p: &mut [f64], rng: &mut ChaCha8Rng) {
    let splay = u(rng, 0.0, 0.15);
    set(p, 1, [u(rng, -0.1, 0.05), 0.0, splay]);
    set(p, 2, [u(rng, -0.1, 0.05), 0.0, -splay]);
    set(p, 4, [u(rng, 0.0, 0.15), 0.0, 0.0]);
    set(p, 5, [u(rng, 0.0, 0.15), 0.0, 0.0]);
    set(p, 3, [u(rng, -0.05, 0.1), u(rng, -0.2, 0.2), 0.0]);
}

/// Walking or running at `phase` of the stride: legs and arms swing opposite.
fn gait(p: &mut [f64], activity: Activity, phase: f64, arm_down: f64) {
    let amp = if activity == Activity::Running {
        0.75
    } else {
        0.4
    };
    let s = phase.sin();
    set(p, 1, [-amp * s, 0.0, 0.03]);
    set(p, 2, [amp * s, 0.0, -0.03]);
    let knee = if activity == Activity::Running {
        1.3
    } else {
        0.5
    };
    set(
        p,
        4,
        [knee * (0.5 + 0.5 * (phase + 1.2).sin()).max(0.05), 0.0, 0.0],
    );
    set(
        p,
        5,
        [knee * (0.5 - 0.5 * (phase + 1.2).sin()).max(0.05), 0.0, 0.0],
    );
    // Arms swing opposite to the legs (about the body's side axis, in the shoulder frame).
    set(p, 16, [0.0, amp * 0.8 * s, -arm_down]);
    set(p, 17, [0.0, amp * 0.8 * s, arm_down]);
    if activity == Activity::Running {
        set(p, 18, [0.0, -1.4, 0.0]);
        set(p, 19, [0.0, 1.4, 0.0]);
        set(p, 3, [0.25, 0.0, 0.0]);
    }
}

fn gesturing(p: &mut [f64], rng: &mut ChaCha8Rng) {
    set(p, 1, [u(rng, -0.1, 0.0), 0.0, 0.05]);
    set(p, 2, [u(rng, -0.1, 0.0), 0.0, -0.05]);
    // One or both arms raised: the upper arm anywhere from sideways to up, forearm bent.
    let both = rng.random_bool(0.3);
    let left = rng.random_bool(0.5);
    for (is_left, raise) in [(true, left || both), (false, !left || both)] {
        if !raise {
            continue;
        }
        let sgn = if is_left { 1.0 } else { -1.0 };
        let (sh, el) = if is_left { (16, 18) } else { (17, 19) };
        set(
            p,
            sh,
            [0.0, sgn * u(rng, -0.9, 0.2), sgn * u(rng, -0.6, 0.9)],
        );
        set(p, el, [0.0, 0.0, sgn * u(rng, 0.3, 1.8)]);
    }
    set(p, 3, [0.0, u(rng, -0.3, 0.3), 0.0]);
}

fn crouching(p: &mut [f64], rng: &mut ChaCha8Rng) {
    let hip = u(rng, 1.2, 1.7);
    let knee = u(rng, 1.8, 2.3);
    set(p, 1, [-hip, 0.0, 0.15]);
    set(p, 2, [-hip, 0.0, -0.15]);
    set(p, 4, [knee, 0.0, 0.0]);
    set(p, 5, [knee, 0.0, 0.0]);
    set(p, 7, [-(knee - hip) * 0.6, 0.0, 0.0]);
    set(p, 8, [-(knee - hip) * 0.6, 0.0, 0.0]);
    set(p, 3, [u(rng, 0.2, 0.5), 0.0, 0.0]);
    set(p, 6, [u(rng, 0.0, 0.2), 0.0, 0.0]);
    set(p, 16, [0.0, -0.6, -0.8]);
    set(p, 17, [0.0, 0.6, 0.8]);
}

/// Hands: a relaxed curl of every finger joint, thumbs slightly in; the jaw a little open.
fn hands_and_jaw(p: &mut [f64], rng: &mut ChaCha8Rng) {
    let curl = u(rng, 0.1, 0.7);
    for j in 25..37 {
        set(p, j, [0.0, 0.0, -curl * u(rng, 0.7, 1.0)]);
        set(p, j + 15, [0.0, 0.0, curl * u(rng, 0.7, 1.0)]);
    }
    for j in 37..40 {
        set(p, j, [u(rng, 0.0, 0.3), 0.0, 0.0]);
        set(p, j + 15, [u(rng, 0.0, 0.3), 0.0, 0.0]);
    }
    set(p, 22, [u(rng, 0.0, 0.25), 0.0, 0.0]);
}

/// A new person at a position.
pub fn new_person(id: u32, position: [f64; 2], rng: &mut ChaCha8Rng) -> PersonState {
    let activity = Activity::sample(rng);
    let heading = u(rng, -std::f64::consts::PI, std::f64::consts::PI);
    let phase = u(rng, 0.0, std::f64::consts::TAU);
    let normal = Normal::<f64>::new(0.0, 0.8).expect("valid normal");
    let betas = std::array::from_fn(|_| normal.sample(rng).clamp(-2.5, 2.5));
    let expression = std::array::from_fn(|_| normal.sample(rng).clamp(-1.5, 1.5) * 0.5);
    let appearance = Appearance::sample(rng);
    let pose = sample_pose(activity, heading, phase, rng);
    PersonState {
        id,
        activity,
        heading,
        position,
        phase,
        betas,
        expression,
        appearance,
        pose,
    }
}

/// The person one frame later: walkers move along their heading, everyone re-poses a little.
pub fn advance(p: &PersonState, rng: &mut ChaCha8Rng) -> PersonState {
    let mut n = p.clone();
    n.heading += u(rng, -0.15, 0.15);
    let step = p.activity.speed();
    n.position = [
        p.position[0] + step * n.heading.sin() + u(rng, -0.03, 0.03),
        p.position[1] - step * n.heading.cos() + u(rng, -0.03, 0.03),
    ];
    n.phase += if step > 0.0 { 1.3 } else { 0.3 };
    n.pose = sample_pose(n.activity, n.heading, n.phase, rng);
    n
}
