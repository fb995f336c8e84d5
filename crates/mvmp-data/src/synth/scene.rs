//! Posing people in the world, keeping feet on the ground and bodies apart.
use std::collections::HashMap;

use burn::tensor::{Device, Tensor, TensorData};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::people::{PersonState, advance, new_person};
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS};
use mvmp_smplx::{SmplxLayer, SmplxParams, Translation};

/// Closest allowed distance between the surfaces of two people (metres).
const MIN_GAP: f32 = 0.03;
const CELL: f32 = 0.06;

/// A person posed in the world.
#[derive(Debug, Clone)]
pub struct Posed {
    pub state: PersonState,
    /// `[V]` vertices (world, metres).
    pub vertices: Vec<[f32; 3]>,
    /// The 127 joints (world, metres).
    pub joints: Vec<[f64; 3]>,
    pub pelvis: [f64; 3],
    /// smplx's standard translation for these parameters.
    pub transl: [f64; 3],
}

impl Posed {
    pub fn params(&self) -> SmplxParams {
        SmplxParams::from_full_pose(
            &self.state.pose,
            &self.state.betas,
            &self.state.expression,
            self.transl,
        )
    }
}

/// Runs the body model for scene people.
pub struct Poser {
    layer: SmplxLayer,
    device: Device,
}

impl Poser {
    pub fn new(model: &mvmp_smplx::BodyModel) -> Self {
        let device = Device::flex();
        Poser {
            layer: SmplxLayer::new(model, &device),
            device,
        }
    }

    /// Pose people: pelvis over their ground position, then lifted so the lowest vertex touches z = 0.
    pub fn pose(&self, states: &[PersonState]) -> Vec<Posed> {
        let n = states.len();
        if n == 0 {
            return Vec::new();
        }
        let d = &self.device;
        let f = |v: Vec<f64>, shape: &[usize]| -> TensorData {
            TensorData::new(
                v.into_iter().map(|x| x as f32).collect::<Vec<f32>>(),
                shape.to_vec(),
            )
        };
        let pose = f(
            states.iter().flat_map(|s| s.pose.clone()).collect(),
            &[n, NUM_JOINTS, 3],
        );
        let betas = f(
            states.iter().flat_map(|s| s.betas).collect(),
            &[n, NUM_BETAS],
        );
        let expr = f(
            states.iter().flat_map(|s| s.expression).collect(),
            &[n, NUM_EXPRESSION],
        );
        let transl = f(
            states
                .iter()
                .flat_map(|s| [s.position[0], s.position[1], 0.0])
                .collect(),
            &[n, 3],
        );
        let betas_t = Tensor::<2>::from_data(betas, d);
        let expr_t = Tensor::<2>::from_data(expr, d);
        let out = self.layer.forward_axis_angle(
            Tensor::from_data(pose, d),
            betas_t.clone(),
            expr_t.clone(),
            Tensor::from_data(transl, d),
            Translation::Pelvis,
        );
        let rest = self.layer.rest_joints(betas_t, expr_t);
        let verts: Vec<f32> = out
            .vertices
            .into_data()
            .try_into_vec()
            .expect("f32 vertices");
        let joints: Vec<f32> = out.joints.into_data().try_into_vec().expect("f32 joints");
        let rest: Vec<f32> = rest.into_data().try_into_vec().expect("f32 joints");
        let nv = self.layer.num_vertices();
        let nj = self.layer.num_joints();
        (0..n)
            .map(|i| {
                let mut v: Vec<[f32; 3]> = verts[i * nv * 3..(i + 1) * nv * 3]
                    .chunks_exact(3)
                    .map(|c| [c[0], c[1], c[2]])
                    .collect();
                let lift = -v.iter().map(|p| p[2]).fold(f32::MAX, f32::min);
                for p in &mut v {
                    p[2] += lift;
                }
                let j: Vec<[f64; 3]> = joints[i * nj * 3..(i + 1) * nj * 3]
                    .chunks_exact(3)
                    .map(|c| [c[0] as f64, c[1] as f64, (c[2] + lift) as f64])
                    .collect();
                let pelvis = j[0];
                let j0 = &rest[i * NUM_JOINTS * 3..i * NUM_JOINTS * 3 + 3];
                let transl = [
                    pelvis[0] - j0[0] as f64,
                    pelvis[1] - j0[1] as f64,
                    pelvis[2] - j0[2] as f64,
                ];
                Posed {
                    state: states[i].clone(),
                    vertices: v,
                    joints: j,
                    pelvis,
                    transl,
                }
            })
            .collect()
    }
}

/// A spatial hash of surface points of the people placed so far.
#[derive(Default)]
struct Occupancy {
    cells: HashMap<(i32, i32, i32), Vec<[f32; 3]>>,
}

impl Occupancy {
    fn key(p: &[f32; 3]) -> (i32, i32, i32) {
        (
            (p[0] / CELL).floor() as i32,
            (p[1] / CELL).floor() as i32,
            (p[2] / CELL).floor() as i32,
        )
    }

    fn add(&mut self, verts: &[[f32; 3]]) {
        for p in verts.iter().step_by(2) {
            self.cells.entry(Self::key(p)).or_default().push(*p);
        }
    }

    fn collides(&self, verts: &[[f32; 3]]) -> bool {
        verts.iter().step_by(2).any(|p| {
            let (x, y, z) = Self::key(p);
            (-1..=1).any(|dx| {
                (-1..=1).any(|dy| {
                    (-1..=1).any(|dz| {
                        self.cells.get(&(x + dx, y + dy, z + dz)).is_some_and(|c| {
                            c.iter().any(|q| {
                                let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
                                d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < MIN_GAP * MIN_GAP
                            })
                        })
                    })
                })
            })
        })
    }
}

fn inside(area: [f64; 2], p: [f64; 2], margin: f64) -> bool {
    p[0].abs() <= area[0] / 2.0 - margin && p[1].abs() <= area[1] / 2.0 - margin
}

/// The first frame: `count` people placed in the area, clustered (about half are put within touching
/// distance of someone already there), none interpenetrating. People that find no free spot after many
/// tries are left out, so the result can hold fewer than `count`.
pub fn place_people(
    poser: &Poser,
    count: usize,
    area: [f64; 2],
    rng: &mut ChaCha8Rng,
) -> Vec<Posed> {
    let mut placed: Vec<Posed> = Vec::new();
    let mut occ = Occupancy::default();
    for id in 0..count as u32 {
        for _attempt in 0..80 {
            let pos = if !placed.is_empty() && rng.random_bool(0.5) {
                let other = &placed[rng.random_range(0..placed.len())];
                let a = rng.random_range(0.0..std::f64::consts::TAU);
                let r = rng.random_range(0.45..1.1);
                [other.pelvis[0] + r * a.cos(), other.pelvis[1] + r * a.sin()]
            } else {
                [
                    rng.random_range(-area[0] / 2.0..area[0] / 2.0),
                    rng.random_range(-area[1] / 2.0..area[1] / 2.0),
                ]
            };
            if !inside(area, pos, 0.5) {
                continue;
            }
            let state = new_person(id, pos, rng);
            let posed = poser.pose(std::slice::from_ref(&state)).remove(0);
            if occ.collides(&posed.vertices) {
                continue;
            }
            occ.add(&posed.vertices);
            placed.push(posed);
            break;
        }
    }
    placed
}

/// The next frame: every person advances; a move that would leave the area or touch someone keeps the
/// person where they were (turning them around when they hit the edge).
pub fn next_frame(
    poser: &Poser,
    prev: &[Posed],
    area: [f64; 2],
    rng: &mut ChaCha8Rng,
) -> Vec<Posed> {
    let candidates: Vec<_> = prev.iter().map(|p| advance(&p.state, rng)).collect();
    let new_posed = poser.pose(&candidates);
    let mut out: Vec<Posed> = Vec::with_capacity(prev.len());
    for (i, cand) in new_posed.into_iter().enumerate() {
        // Check against people already moved and those not yet moved (their old place).
        let mut occ = Occupancy::default();
        for p in out.iter().chain(prev[i + 1..].iter()) {
            occ.add(&p.vertices);
        }
        if inside(area, cand.state.position, 0.5) && !occ.collides(&cand.vertices) {
            out.push(cand);
        } else {
            let mut stay = prev[i].clone();
            stay.state.heading += std::f64::consts::PI;
            out.push(stay);
        }
    }
    out
}
