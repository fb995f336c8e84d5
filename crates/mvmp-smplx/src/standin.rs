//! The stand-in body model: a procedurally generated, human-shaped model in exactly the official SMPL-X
//! npz layout, so that everything runs without the licensed files.
//!
//! The body is built from closed generalized cylinders ("tubes") that follow the bones of the SMPL-X
//! kinematic tree: torso, head, two legs, two feet, two arms with palms, ten fingers (18 closed surfaces,
//! 10475 vertices and 20878 triangles, so memory and speed figures transfer to the real model). Every
//! tube ring sits at an arclength along its bone path; skinning weights follow the bone that owns that part
//! of the path and blend smoothly across each joint (they sum to 1). Each joint-regressor row is a convex
//! combination of the two rings that bracket the joint, so it regresses the joint's centre. The 10 shape
//! directions are central differences of the generator in 10 proportion parameters (stature, girth, leg
//! length, shoulder width, torso length, arm length, hip width, head size, belly, chest); the 10 expression
//! directions move regions of the face; pose correctives bulge the blend zone of each bent joint. The
//! vertex-based extra joints (nose, eyes, ears, toes, heels, fingertips) are placed at the real model's
//! vertex indices and the 51 face landmarks on the face, so the 127-joint output has the SMPL-X meaning.
//! Rest pose: y up, facing +z, the person's left at +x, T-pose, metres. Deterministic by seed: the seed
//! jitters the proportions by a few percent and sets the (unused) hand means.
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::BodyModel;
use crate::names::{EXTRA_VERTEX_JOINTS, NUM_JOINTS, NUM_POSE_JOINTS};

/// Vertex count of the stand-in (equal to SMPL-X).
pub const STANDIN_VERTICES: usize = crate::names::NUM_VERTICES;
const NUM_SHAPE: usize = 10;
const NUM_EXPR: usize = 10;

type V3 = [f64; 3];

fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}
fn normalize(a: V3) -> V3 {
    scale(a, 1.0 / norm(a).max(1e-12))
}
fn smoothstep(x: f64) -> f64 {
    let t = x.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// One tube: a path of control points with an elliptical section `[front, back, side]` at each.
#[derive(Clone)]
struct Tube {
    points: Vec<V3>,
    radii: Vec<V3>,
    /// Joint that owns the segment from point k to k + 1.
    owners: Vec<usize>,
    /// Joint located at control point k (regressed from the rings there).
    joints_at: Vec<(usize, usize)>,
    rings: usize,
    segs: usize,
    /// Reference direction for the section's first axis (the "front" radius).
    hint: V3,
}

/// A built mesh plus, per vertex, which tube and which arclength it came from.
struct Built {
    verts: Vec<V3>,
    faces: Vec<[u32; 3]>,
    /// (tube, arclength, ring index or usize::MAX for poles) per vertex.
    origin: Vec<(usize, f64, usize)>,
    /// Per tube: first vertex, ring arclengths, total length.
    tube_info: Vec<(usize, Vec<f64>, f64)>,
}

/// The proportion parameters the shape directions are derivatives of.
#[derive(Clone, Copy)]
struct Proportions {
    p: [f64; NUM_SHAPE],
    jitter: [f64; 6],
}

fn mirror(v: V3) -> V3 {
    [-v[0], v[1], v[2]]
}

fn tubes(pr: &Proportions) -> Vec<Tube> {
    let [
        stature,
        girth,
        leg,
        shoulder,
        torso,
        arm,
        hip,
        head,
        belly,
        chest,
    ] = pr.p;
    let j = &pr.jitter;
    let g = (1.0 + 0.10 * girth) * j[0];
    // Heights: legs below the pelvis stretch with `leg`; the torso above it with `torso`.
    let leg_s = (1.0 + 0.06 * leg) * j[1];
    let tor_s = (1.0 + 0.06 * torso) * j[2];
    let arm_s = (1.0 + 0.06 * arm) * j[3];
    let sh = 0.02 * shoulder;
    let hw = (1.0 + 0.10 * hip) * j[4];
    let hd = (1.0 + 0.08 * head) * j[5];
    let py = -0.35;
    let up = |y: f64| py + (y - py) * tor_s; // torso heights
    let down = |y: f64| py + (y - py) * leg_s; // leg heights
    let mut out = Vec::new();
    // Torso: crotch -> neck top.
    out.push(Tube {
        points: vec![
            [0.0, up(-0.47), 0.0],
            [0.0, up(-0.40), 0.0],
            [0.0, py, 0.0],
            [0.0, up(-0.24), -0.01],
            [0.0, up(-0.12), -0.005],
            [0.0, up(0.0), 0.0],
            [0.0, up(0.10), -0.01],
            [0.0, up(0.17), -0.01],
            [0.0, up(0.245), 0.0],
        ],
        radii: vec![
            [0.04 * g, 0.04 * g, 0.06 * g * hw],
            [0.105 * g, 0.12 * g, 0.165 * g * hw],
            [0.11 * g, 0.12 * g, 0.165 * g * hw],
            [(0.11 + 0.035 * belly) * g, 0.10 * g, 0.145 * g],
            [
                (0.12 + 0.025 * belly + 0.01 * chest) * g,
                0.10 * g,
                0.155 * g,
            ],
            [(0.12 + 0.03 * chest) * g, 0.105 * g, (0.17 + 0.5 * sh) * g],
            [(0.10 + 0.01 * chest) * g, 0.10 * g, (0.17 + sh) * g],
            [0.05 * g, 0.05 * g, 0.055 * g],
            [0.045 * g, 0.045 * g, 0.05 * g],
        ],
        owners: vec![0, 0, 0, 3, 6, 9, 9, 12],
        joints_at: vec![(0, 2), (3, 3), (6, 4), (9, 5), (12, 7)],
        rings: 44,
        segs: 48,
        hint: [0.0, 0.0, 1.0],
    });
    // Head: chin -> crown, centred above the neck.
    let hy = up(0.17);
    let h = |y: f64| hy + (y - 0.17) * hd + 0.0;
    out.push(Tube {
        points: vec![
            [0.0, h(0.215), 0.02],
            [0.0, h(0.25), 0.015],
            [0.0, h(0.30), 0.01],
            [0.0, h(0.35), 0.0],
            [0.0, h(0.40), -0.005],
            [0.0, h(0.445), -0.01],
        ],
        radii: vec![
            [0.02 * hd, 0.02 * hd, 0.02 * hd],
            [0.075 * hd, 0.06 * hd, 0.06 * hd],
            [0.095 * hd, 0.09 * hd, 0.075 * hd],
            [0.10 * hd, 0.10 * hd, 0.08 * hd],
            [0.085 * hd, 0.09 * hd, 0.075 * hd],
            [0.02 * hd, 0.02 * hd, 0.02 * hd],
        ],
        owners: vec![15; 5],
        joints_at: vec![(15, 1)],
        rings: 47,
        segs: 41,
        hint: [0.0, 0.0, 1.0],
    });
    for side in [0usize, 1] {
        let m = |v: V3| if side == 0 { v } else { mirror(v) };
        let o = |left: usize| left + side; // left/right joints are adjacent in the tree
        // Leg: inside the torso -> ankle.
        let lx = 0.09 * hw;
        out.push(Tube {
            points: vec![
                m([lx - 0.005, up(-0.33), 0.0]),
                m([lx, down(-0.43), 0.0]),
                m([lx + 0.005, down(-0.62), 0.01]),
                m([lx + 0.01, down(-0.82), 0.01]),
                m([lx + 0.01, down(-0.95), -0.01]),
                m([lx + 0.01, down(-1.20), -0.02]),
                m([lx + 0.01, down(-1.24), -0.02]),
            ],
            radii: vec![
                [0.085 * g, 0.085 * g, 0.085 * g],
                [0.09 * g, 0.095 * g, 0.09 * g],
                [0.07 * g, 0.072 * g, 0.07 * g],
                [0.052 * g, 0.05 * g, 0.052 * g],
                [0.048 * g, 0.06 * g, 0.05 * g],
                [0.034 * g, 0.034 * g, 0.034 * g],
                [0.03 * g, 0.03 * g, 0.03 * g],
            ],
            owners: vec![0, o(1), o(1), o(4), o(4), o(7)],
            joints_at: vec![(o(1), 1), (o(4), 3), (o(7), 5)],
            rings: 60,
            segs: 28,
            hint: [0.0, 0.0, 1.0],
        });
        // Foot: heel -> toes.
        let fy = down(-1.2) - 0.065;
        out.push(Tube {
            points: vec![
                m([lx + 0.01, fy + 0.01, -0.075]),
                m([lx + 0.01, fy + 0.02, -0.02]),
                m([lx + 0.02, fy + 0.0, 0.10]),
                m([lx + 0.025, fy - 0.005, 0.17]),
            ],
            radii: vec![
                [0.03, 0.03, 0.035],
                [0.045, 0.025, 0.045],
                [0.03, 0.02, 0.05],
                [0.015, 0.012, 0.04],
            ],
            owners: vec![o(7), o(7), o(10)],
            joints_at: vec![(o(10), 2)],
            rings: 16,
            segs: 14,
            hint: [0.0, 1.0, 0.0],
        });
        // Arm: inside the chest -> collar -> shoulder -> elbow -> wrist -> palm.
        let ay = up(0.115);
        let ax = |x: f64| 0.18 + sh + (x - 0.18) * arm_s;
        out.push(Tube {
            points: vec![
                m([0.03, ay - 0.005, -0.01]),
                m([0.07 + 0.5 * sh, ay, -0.01]),
                m([0.18 + sh, ay + 0.005, -0.02]),
                m([ax(0.31), ay + 0.005, -0.025]),
                m([ax(0.44), ay + 0.005, -0.03]),
                m([ax(0.56), ay + 0.005, -0.025]),
                m([ax(0.69), ay + 0.005, -0.02]),
                m([ax(0.69) + 0.05, ay + 0.005, -0.015]),
                m([ax(0.69) + 0.095, ay + 0.005, -0.015]),
                m([ax(0.69) + 0.11, ay + 0.005, -0.015]),
            ],
            radii: vec![
                [0.045 * g, 0.045 * g, 0.05 * g],
                [0.05 * g, 0.05 * g, 0.055 * g],
                [0.055 * g, 0.055 * g, 0.055 * g],
                [0.045 * g, 0.045 * g, 0.045 * g],
                [0.037 * g, 0.037 * g, 0.04 * g],
                [0.033 * g, 0.033 * g, 0.036 * g],
                [0.022 * g, 0.022 * g, 0.03 * g],
                [0.017, 0.015, 0.042],
                [0.013, 0.013, 0.04],
                [0.008, 0.008, 0.03],
            ],
            owners: vec![9, o(13), o(16), o(16), o(18), o(18), o(20), o(20), o(20)],
            joints_at: vec![(o(13), 1), (o(16), 2), (o(18), 4), (o(20), 6)],
            rings: 34,
            segs: 24,
            hint: [0.0, 1.0, 0.0],
        });
        // Fingers: index, middle, pinky, ring (model order), then the thumb.
        let kx = ax(0.69) + 0.095;
        let fingers: [(f64, [f64; 3], usize); 4] = [
            (0.012, [0.038, 0.024, 0.022], 25),
            (-0.006, [0.042, 0.027, 0.023], 28),
            (-0.041, [0.030, 0.020, 0.020], 31),
            (-0.024, [0.039, 0.026, 0.022], 34),
        ];
        let r_off = 15 * side;
        for (fz, len, j1) in fingers {
            let j1 = j1 + r_off;
            let y = ay + 0.005;
            let x1 = kx;
            let x2 = x1 + len[0] * arm_s.sqrt();
            let x3 = x2 + len[1] * arm_s.sqrt();
            let x4 = x3 + len[2] * arm_s.sqrt();
            out.push(Tube {
                points: vec![
                    m([x1 - 0.025, y, fz]),
                    m([x1, y, fz]),
                    m([x2, y, fz]),
                    m([x3, y - 0.002, fz]),
                    m([x4, y - 0.004, fz]),
                ],
                radii: vec![
                    [0.009, 0.009, 0.009],
                    [0.0095, 0.0095, 0.0095],
                    [0.0085, 0.0085, 0.0085],
                    [0.0075, 0.0075, 0.0075],
                    [0.006, 0.006, 0.006],
                ],
                owners: vec![o(20), j1, j1 + 1, j1 + 2],
                joints_at: vec![(j1, 1), (j1 + 1, 2), (j1 + 2, 3)],
                rings: 12,
                segs: 8,
                hint: [0.0, 1.0, 0.0],
            });
        }
        let wx = ax(0.69);
        let j1 = 37 + r_off;
        out.push(Tube {
            points: vec![
                m([wx + 0.015, ay, -0.005]),
                m([wx + 0.03, ay - 0.005, 0.02]),
                m([wx + 0.055, ay - 0.01, 0.045]),
                m([wx + 0.08, ay - 0.01, 0.06]),
                m([wx + 0.10, ay - 0.01, 0.07]),
            ],
            radii: vec![
                [0.013, 0.013, 0.013],
                [0.012, 0.012, 0.012],
                [0.0105, 0.0105, 0.0105],
                [0.009, 0.009, 0.009],
                [0.007, 0.007, 0.007],
            ],
            owners: vec![o(20), j1, j1 + 1, j1 + 2],
            joints_at: vec![(j1, 1), (j1 + 1, 2), (j1 + 2, 3)],
            rings: 12,
            segs: 8,
            hint: [0.0, 1.0, 0.0],
        });
    }
    // Stature scales everything about the pelvis.
    let s = 1.0 + 0.06 * stature;
    for t in &mut out {
        for p in &mut t.points {
            *p = add([0.0, py, 0.0], scale(sub(*p, [0.0, py, 0.0]), s));
        }
        for r in &mut t.radii {
            *r = scale(*r, s);
        }
    }
    out
}

/// Arclengths of the control points of a path.
fn cumulative(points: &[V3]) -> Vec<f64> {
    let mut s = vec![0.0];
    for w in points.windows(2) {
        s.push(s.last().unwrap() + norm(sub(w[1], w[0])));
    }
    s
}

/// Point and section radii at arclength `s` along a tube (linear between control points).
fn along(t: &Tube, cum: &[f64], s: f64) -> (V3, V3) {
    let k = (0..t.points.len() - 1)
        .find(|&k| s <= cum[k + 1])
        .unwrap_or(t.points.len() - 2);
    let a = ((s - cum[k]) / (cum[k + 1] - cum[k]).max(1e-12)).clamp(0.0, 1.0);
    let lerp = |p: V3, q: V3| add(scale(p, 1.0 - a), scale(q, a));
    (
        lerp(t.points[k], t.points[k + 1]),
        lerp(t.radii[k], t.radii[k + 1]),
    )
}

fn build(tubes: &[Tube]) -> Built {
    let mut verts = Vec::new();
    let mut faces = Vec::new();
    let mut origin = Vec::new();
    let mut tube_info = Vec::new();
    for (ti, t) in tubes.iter().enumerate() {
        let cum = cumulative(&t.points);
        let len = *cum.last().unwrap();
        let base = verts.len();
        let ring_s: Vec<f64> = (1..=t.rings)
            .map(|i| len * i as f64 / (t.rings + 1) as f64)
            .collect();
        // Rounded caps: within `cap` of an end the section shrinks like a half ellipse.
        let cap_start = t.radii[0].iter().cloned().fold(0.0, f64::max).max(0.01);
        let cap_end = t.radii[t.radii.len() - 1]
            .iter()
            .cloned()
            .fold(0.0, f64::max)
            .max(0.01);
        verts.push(t.points[0]);
        origin.push((ti, 0.0, usize::MAX));
        for (ri, &s) in ring_s.iter().enumerate() {
            let (c, r) = along(t, &cum, s);
            let h = 0.01_f64.min(len / 4.0);
            let (pa, _) = along(t, &cum, (s - h).max(0.0));
            let (pb, _) = along(t, &cum, (s + h).min(len));
            let tan = normalize(sub(pb, pa));
            let e1 = normalize(sub(t.hint, scale(tan, dot(t.hint, tan))));
            let e2 = cross(tan, e1);
            let taper = {
                let d0 = s / cap_start;
                let d1 = (len - s) / cap_end;
                let f = |d: f64| {
                    if d < 1.0 {
                        (1.0 - (1.0 - d) * (1.0 - d)).sqrt()
                    } else {
                        1.0
                    }
                };
                f(d0) * f(d1)
            };
            for j in 0..t.segs {
                let phi = 2.0 * std::f64::consts::PI * j as f64 / t.segs as f64;
                let (cs, sn) = (phi.cos(), phi.sin());
                let a = if cs >= 0.0 { r[0] } else { r[1] };
                let off = add(scale(e1, a * cs * taper), scale(e2, r[2] * sn * taper));
                verts.push(add(c, off));
                origin.push((ti, s, ri));
            }
        }
        verts.push(*t.points.last().unwrap());
        origin.push((ti, len, usize::MAX));
        let ring = |i: usize, j: usize| (base + 1 + i * t.segs + (j % t.segs)) as u32;
        let last = (base + 1 + t.rings * t.segs) as u32;
        let mut tf = Vec::new();
        for j in 0..t.segs {
            tf.push([base as u32, ring(0, j + 1), ring(0, j)]);
            tf.push([last, ring(t.rings - 1, j), ring(t.rings - 1, j + 1)]);
        }
        for i in 0..t.rings - 1 {
            for j in 0..t.segs {
                tf.push([ring(i, j), ring(i, j + 1), ring(i + 1, j + 1)]);
                tf.push([ring(i, j), ring(i + 1, j + 1), ring(i + 1, j)]);
            }
        }
        // Orient outward: positive signed volume.
        let vol: f64 = tf
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| verts[i as usize]);
                dot(a, cross(b, c))
            })
            .sum();
        if vol < 0.0 {
            for f in &mut tf {
                f.swap(1, 2);
            }
        }
        faces.extend(tf);
        tube_info.push((base, ring_s, len));
    }
    Built {
        verts,
        faces,
        origin,
        tube_info,
    }
}

/// Face points of the template (eyes, nose tip, ears, mouth), relative to the head tube.
struct Face {
    nose: V3,
    eyes: [V3; 2],
    ears: [V3; 2],
    mouth: V3,
    brow_y: f64,
    eye_y: f64,
}

fn face_points(tubes: &[Tube]) -> Face {
    let h = &tubes[1];
    let (y0, y3) = (h.points[0][1], h.points[3][1]);
    let hd = (y3 - y0) / (0.35 - 0.215);
    let y = |v: f64| y0 + (v - 0.215) * hd;
    let front = h.points[3][2] + h.radii[3][0];
    Face {
        nose: [0.0, y(0.315), front + 0.01],
        eyes: [
            [0.034 * hd, y(0.338), front - 0.012],
            [-0.034 * hd, y(0.338), front - 0.012],
        ],
        ears: [[0.085 * hd, y(0.33), -0.01], [-0.085 * hd, y(0.33), -0.01]],
        mouth: [0.0, y(0.272), front - 0.02],
        brow_y: y(0.362),
        eye_y: y(0.338),
    }
}

/// Nose and ear bumps on the head (part of the shape, so they scale with it).
fn sculpt_head(b: &mut Built, tubes: &[Tube]) {
    let f = face_points(tubes);
    let hb = b.tube_info[1].0;
    let hn = 2 + tubes[1].rings * tubes[1].segs;
    let centre = tubes[1].points[3];
    for v in &mut b.verts[hb..hb + hn] {
        let radial = normalize(sub(*v, [centre[0], v[1], centre[2]]));
        let dn = norm(sub(*v, [f.nose[0], f.nose[1], v[2]]));
        if v[2] > centre[2] {
            let bump = 0.022 * (-(dn * dn) / (2.0 * 0.011 * 0.011)).exp();
            *v = add(*v, [0.0, 0.0, bump]);
        }
        for e in f.ears {
            let d = norm(sub(*v, e));
            *v = add(
                *v,
                scale(radial, 0.014 * (-(d * d) / (2.0 * 0.014 * 0.014)).exp()),
            );
        }
    }
}

fn build_full(pr: &Proportions) -> (Vec<Tube>, Built) {
    let t = tubes(pr);
    let mut b = build(&t);
    sculpt_head(&mut b, &t);
    (t, b)
}

/// Generate the stand-in body model for a seed.
pub fn standin_model(seed: u64) -> BodyModel {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let jitter: [f64; 6] = std::array::from_fn(|_| 1.0 + rng.random_range(-0.03..0.03));
    let base = Proportions {
        p: [0.0; NUM_SHAPE],
        jitter,
    };
    let (tubes, built) = build_full(&base);
    let nv = built.verts.len();
    assert_eq!(nv, STANDIN_VERTICES, "stand-in vertex budget");
    let face = face_points(&tubes);
    let head = Head::new(&tubes, &built);
    let mut shapedirs = shape_directions(&base, nv);
    expression_directions(&mut shapedirs, &built, &head, &face);
    let weights = skin_weights(&tubes, &built, &head, &face);
    let jreg = joint_regressor(&tubes, &built, &head, &face);
    let posedirs = pose_correctives(&base, &weights);
    let lmk = landmarks(&built, &tubes, &face);
    let picks = vertex_joint_picks(&tubes, &built, &head, &face);
    let mut new_of_old: Vec<usize> = (0..nv).collect();
    let mut old_at_new: Vec<usize> = (0..nv).collect();
    // Place the vertex joints at the official vertex indices.
    for (&(_, target), &src) in EXTRA_VERTEX_JOINTS.iter().zip(&picks) {
        let cur = new_of_old[src];
        let displaced = old_at_new[target];
        old_at_new.swap(cur, target);
        new_of_old[src] = target;
        new_of_old[displaced] = cur;
    }
    let v_template: Vec<f32> = (0..nv)
        .flat_map(|n| built.verts[old_at_new[n]].map(|x| x as f32))
        .collect();
    let faces: Vec<[u32; 3]> = built
        .faces
        .iter()
        .map(|f| f.map(|i| new_of_old[i as usize] as u32))
        .collect();
    let per_vertex = |src: &[f64], width: usize| -> Vec<f32> {
        (0..nv)
            .flat_map(|n| {
                let o = old_at_new[n];
                src[o * width..(o + 1) * width]
                    .iter()
                    .map(|&x| x as f32)
                    .collect::<Vec<_>>()
            })
            .collect()
    };
    let j_regressor: Vec<f32> = (0..NUM_JOINTS)
        .flat_map(|j| (0..nv).map(move |n| (j, n)))
        .map(|(j, n)| jreg[j * nv + old_at_new[n]] as f32)
        .collect();
    // Landmark faces refer to face indices, which the permutation keeps.
    let hands_mean = (
        (0..45)
            .map(|_| rng.random_range(-0.15..0.15) as f32)
            .collect(),
        (0..45)
            .map(|_| rng.random_range(-0.15..0.15) as f32)
            .collect(),
    );
    let l = NUM_SHAPE + NUM_EXPR;
    BodyModel {
        v_template,
        faces,
        shapedirs: per_vertex(&shapedirs, 3 * l),
        num_shape_components: l,
        posedirs: per_vertex(&posedirs, 3 * NUM_POSE_JOINTS * 9),
        j_regressor,
        weights: per_vertex(&weights, NUM_JOINTS),
        parents: crate::names::PARENTS.to_vec(),
        landmarks: Some(lmk),
        hands_mean: Some(hands_mean),
    }
}

/// The head's vertices (tube 1, its rings and two poles) and its centre.
struct Head {
    range: std::ops::Range<usize>,
    centre: V3,
}

impl Head {
    fn new(tubes: &[Tube], built: &Built) -> Self {
        let start = built.tube_info[1].0;
        Head {
            range: start..start + 2 + tubes[1].rings * tubes[1].segs,
            centre: tubes[1].points[3],
        }
    }

    /// The `n` head vertices nearest `target`, inverse-distance weighted (weights sum to 1).
    fn nearest(&self, built: &Built, target: V3, n: usize) -> Vec<(usize, f64)> {
        let mut d: Vec<(usize, f64)> = self
            .range
            .clone()
            .map(|v| (v, norm(sub(built.verts[v], target))))
            .collect();
        d.sort_by(|a, b| a.1.total_cmp(&b.1));
        d.truncate(n);
        let tot: f64 = d.iter().map(|x| 1.0 / (x.1 + 1e-3)).sum();
        d.into_iter()
            .map(|(v, x)| (v, (1.0 / (x + 1e-3)) / tot))
            .collect()
    }
}

/// `[V][3][shape + expression]` with the shape columns filled: central differences in the proportion
/// parameters.
fn shape_directions(base: &Proportions, nv: usize) -> Vec<f64> {
    let delta = 1e-3;
    let l = NUM_SHAPE + NUM_EXPR;
    let mut shapedirs = vec![0f64; nv * 3 * l];
    for c in 0..NUM_SHAPE {
        let mut hi = *base;
        hi.p[c] += delta;
        let mut lo = *base;
        lo.p[c] -= delta;
        let (_, bh) = build_full(&hi);
        let (_, bl) = build_full(&lo);
        for v in 0..nv {
            for a in 0..3 {
                shapedirs[(v * 3 + a) * l + c] = (bh.verts[v][a] - bl.verts[v][a]) / (2.0 * delta);
            }
        }
    }
    shapedirs
}

/// The expression columns of `shapedirs`: ten local deformations of the front of the head.
fn expression_directions(shapedirs: &mut [f64], built: &Built, head: &Head, face: &Face) {
    let l = NUM_SHAPE + NUM_EXPR;
    let head_centre = head.centre;
    let gauss = |p: V3, c: V3, s: f64| (-dot(sub(p, c), sub(p, c)) / (2.0 * s * s)).exp();
    for v in head.range.clone() {
        let p = built.verts[v];
        if p[2] < head_centre[2] {
            continue;
        }
        let m = face.mouth;
        let below = smoothstep((m[1] + 0.01 - p[1]) / 0.03);
        let corners = [add(m, [0.025, 0.0, -0.01]), add(m, [-0.025, 0.0, -0.01])];
        let brow =
            gauss(p, [0.0, face.brow_y, p[2]], 0.012) * smoothstep((0.06 - p[0].abs()) / 0.02);
        let cheeks = gauss(p, [0.045, m[1] + 0.02, p[2]], 0.018)
            + gauss(p, [-0.045, m[1] + 0.02, p[2]], 0.018);
        let mouth = gauss(p, m, 0.018);
        let eyes = gauss(p, face.eyes[0], 0.012) + gauss(p, face.eyes[1], 0.012);
        let nose = gauss(p, face.nose, 0.015);
        let c0 = gauss(p, corners[0], 0.012);
        let c1 = gauss(p, corners[1], 0.012);
        let radial = normalize(sub(p, [head_centre[0], p[1], head_centre[2]]));
        let dirs: [V3; NUM_EXPR] = [
            scale([0.0, -1.0, 0.1], 0.012 * below), // jaw open
            add(
                scale([0.3, 1.0, 0.0], 0.006 * c0),
                scale([-0.3, 1.0, 0.0], 0.006 * c1),
            ), // smile
            scale([0.0, 1.0, 0.0], 0.006 * brow),   // brows up
            scale(radial, 0.006 * cheeks),          // cheek puff
            scale([0.0, 0.0, 1.0], 0.006 * mouth),  // pucker
            scale([-p[0].signum() * 0.3, -1.0, 0.0], 0.004 * brow), // frown
            scale([p[0].signum(), 0.0, 0.0], 0.006 * mouth), // mouth wide
            scale([0.0, face.eye_y - p[1], 0.0], 0.3 * eyes), // squint
            scale([0.0, 1.0, 0.0], 0.004 * nose),   // nose wrinkle
            scale([0.0, 1.0, 0.0], 0.008 * c0),     // smirk (left)
        ];
        for (e, d) in dirs.iter().enumerate() {
            for a in 0..3 {
                shapedirs[(v * 3 + a) * l + NUM_SHAPE + e] = d[a];
            }
        }
    }
}

/// `[V][joints]` skinning weights: each tube segment's owner, blended across shared control points; the
/// jaw carries the lower front of the head.
fn skin_weights(tubes: &[Tube], built: &Built, head: &Head, face: &Face) -> Vec<f64> {
    let nv = built.verts.len();
    let mut weights = vec![0f64; nv * NUM_JOINTS];
    for (v, &(ti, s, _)) in built.origin.iter().enumerate() {
        let t = &tubes[ti];
        let cum = cumulative(&t.points);
        let k = (0..t.owners.len())
            .find(|&k| s <= cum[k + 1])
            .unwrap_or(t.owners.len() - 1);
        let mut w = vec![(t.owners[k], 1.0)];
        // Blend with the neighbouring segment's owner near the shared control point.
        for (kk, other) in [(k, k.wrapping_sub(1)), (k + 1, k + 1)] {
            if other >= t.owners.len() || t.owners[other] == t.owners[k] || kk == 0 {
                continue;
            }
            let seg_len = |i: usize| cum[i + 1] - cum[i];
            let width = (0.35 * seg_len(k).min(seg_len(other))).min(0.05);
            let d = (s - cum[kk]).abs();
            if d < width {
                // 0.5 at the control point, fading to 0 at the window edge.
                let share = 0.5 * (1.0 - smoothstep(d / width));
                w[0].1 -= share;
                w.push((t.owners[other], share));
            }
        }
        for (j, x) in w {
            weights[v * NUM_JOINTS + j] += x;
        }
    }
    for v in head.range.clone() {
        let p = built.verts[v];
        let jw = smoothstep((face.mouth[1] + 0.005 - p[1]) / 0.02)
            * smoothstep((p[2] - head.centre[2]) / 0.05);
        if jw > 0.0 {
            weights[v * NUM_JOINTS + 15] -= jw;
            weights[v * NUM_JOINTS + 22] += jw;
        }
    }
    weights
}

/// `[joints][V]` joint regressor, rows convex combinations of vertices: body joints from the rings at
/// their control points, jaw and eyes from the nearest head vertices.
fn joint_regressor(tubes: &[Tube], built: &Built, head: &Head, face: &Face) -> Vec<f64> {
    let nv = built.verts.len();
    let mut jreg = vec![0f64; NUM_JOINTS * nv];
    for (ti, t) in tubes.iter().enumerate() {
        let (base_v, ring_s, _) = &built.tube_info[ti];
        let cum = cumulative(&t.points);
        for &(j, k) in &t.joints_at {
            let s = cum[k];
            let i = ring_s
                .iter()
                .rposition(|&r| r <= s)
                .unwrap_or(0)
                .min(ring_s.len() - 2);
            let a = ((s - ring_s[i]) / (ring_s[i + 1] - ring_s[i])).clamp(0.0, 1.0);
            for (ri, w) in [(i, 1.0 - a), (i + 1, a)] {
                for sj in 0..t.segs {
                    jreg[j * nv + base_v + 1 + ri * t.segs + sj] += w / t.segs as f64;
                }
            }
        }
    }
    let jaw_pt = add(face.mouth, [0.0, -0.01, -0.04]);
    for (j, target) in [(22, jaw_pt), (23, face.eyes[0]), (24, face.eyes[1])] {
        for (v, w) in head.nearest(built, target, 8) {
            jreg[j * nv + v] += w;
        }
    }
    jreg
}

/// `[V][3][pose joints * 9]` pose correctives: joints bulge outward in their blend zone as they bend.
fn pose_correctives(base: &Proportions, weights: &[f64]) -> Vec<f64> {
    let rest = build_full(base).1;
    let nv = rest.verts.len();
    let normals = vertex_normals(&rest.verts, &rest.faces);
    let mut posedirs = vec![0f64; nv * 3 * NUM_POSE_JOINTS * 9];
    for v in 0..nv {
        for j in 1..NUM_JOINTS {
            let wj = weights[v * NUM_JOINTS + j];
            if wj <= 0.0 || wj >= 1.0 {
                continue;
            }
            // Blend zone: 4 w (1 - w) peaks at the joint.
            let b = 4.0 * wj * (1.0 - wj);
            for (a, n) in normals[v].iter().enumerate() {
                for d in [0, 4, 8] {
                    posedirs[(v * 3 + a) * NUM_POSE_JOINTS * 9 + (j - 1) * 9 + d] -= 0.01 * b * n;
                }
            }
        }
    }
    posedirs
}

/// The vertices that stand for SMPL-X's vertex joints, in [`EXTRA_VERTEX_JOINTS`]' order: nose, eyes and
/// ears, each foot's big toe, small toe and heel, and the ten fingertips.
fn vertex_joint_picks(tubes: &[Tube], built: &Built, head: &Head, face: &Face) -> Vec<usize> {
    let pick_near = |t: V3| -> usize { head.nearest(built, t, 1)[0].0 };
    let mut picks = vec![
        pick_near(add(face.nose, [0.0, 0.0, 0.02])),
        pick_near(face.eyes[1]),
        pick_near(face.eyes[0]),
        pick_near(scale(face.ears[1], 1.3)),
        pick_near(scale(face.ears[0], 1.3)),
    ];
    // Feet: tubes 3 (left) and 3 + 8 (right, after leg, foot, arm, 5 fingers of the left side).
    for (foot_tube, medial_sign) in [(3usize, -1.0), (3 + 8, 1.0)] {
        let (b0, _, _) = built.tube_info[foot_tube];
        let n = 2 + tubes[foot_tube].rings * tubes[foot_tube].segs;
        let cx = tubes[foot_tube].points[2][0];
        let range = b0..b0 + n;
        let score = |v: usize, side: f64| built.verts[v][2] + 0.5 * side * (built.verts[v][0] - cx);
        let big = range
            .clone()
            .max_by(|&a, &b| score(a, medial_sign).total_cmp(&score(b, medial_sign)))
            .unwrap();
        let small = range
            .clone()
            .max_by(|&a, &b| score(a, -medial_sign).total_cmp(&score(b, -medial_sign)))
            .unwrap();
        let heel = range
            .clone()
            .min_by(|&a, &b| built.verts[a][2].total_cmp(&built.verts[b][2]))
            .unwrap();
        picks.extend([big, small, heel]);
    }
    // Fingertips: thumb, index, middle, ring, pinky of each hand (the tubes' end poles).
    for side in 0..2 {
        let first = 5 + side * 8; // index finger tube of this side
        let tip = |k: usize| {
            let (b0, _, _) = built.tube_info[first + k];
            b0 + 1 + tubes[first + k].rings * tubes[first + k].segs
        };
        // Tube order: index, middle, pinky, ring, thumb.
        picks.extend([tip(4), tip(0), tip(1), tip(3), tip(2)]);
    }
    picks
}

fn vertex_normals(verts: &[V3], faces: &[[u32; 3]]) -> Vec<V3> {
    let mut n = vec![[0.0; 3]; verts.len()];
    for f in faces {
        let [a, b, c] = f.map(|i| verts[i as usize]);
        let fnorm = cross(sub(b, a), sub(c, a));
        for &i in f {
            n[i as usize] = add(n[i as usize], fnorm);
        }
    }
    n.into_iter().map(normalize).collect()
}

/// The 51 face landmarks: for each target (x, y) on the face, the frontmost head triangle under it and the
/// barycentric coordinates of the point there.
fn landmarks(b: &Built, tubes: &[Tube], face: &Face) -> (Vec<u32>, Vec<f32>) {
    let (hb, _, _) = b.tube_info[1];
    let hn = 2 + tubes[1].rings * tubes[1].segs;
    let head_faces: Vec<usize> = (0..b.faces.len())
        .filter(|&f| {
            b.faces[f]
                .iter()
                .all(|&i| (i as usize) >= hb && (i as usize) < hb + hn)
        })
        .collect();
    let m = face.mouth;
    let (ey, by) = (face.eye_y, face.brow_y);
    let ex = face.eyes[0][0];
    let ny = face.nose[1];
    let mut targets: Vec<(f64, f64)> = Vec::new();
    for i in 0..5 {
        targets.push((-0.055 + 0.01 * i as f64, by)); // right brow 1..5
    }
    for i in 0..5 {
        targets.push((0.015 + 0.01 * i as f64, by)); // left brow 5..1
    }
    for i in 0..4 {
        targets.push((0.0, ey - 0.005 - 0.009 * i as f64)); // nose bridge
    }
    for i in 0..5 {
        targets.push((-0.014 + 0.007 * i as f64, ny - 0.012)); // lower nose
    }
    for c in [-ex, ex] {
        for k in 0..6 {
            let a = std::f64::consts::PI * k as f64 / 3.0;
            targets.push((c - 0.011 * a.cos(), ey + 0.004 * a.sin()));
        }
    }
    for k in 0..12 {
        let a = std::f64::consts::PI * k as f64 / 6.0;
        targets.push((-0.025 * a.cos(), m[1] + 0.01 * a.sin()));
    }
    for k in 0..8 {
        let a = std::f64::consts::PI * k as f64 / 4.0;
        targets.push((-0.015 * a.cos(), m[1] + 0.004 * a.sin()));
    }
    let mut fidx = Vec::new();
    let mut bary = Vec::new();
    for (x, y) in targets {
        let mut best: Option<(usize, [f64; 3], f64)> = None;
        for &f in &head_faces {
            let [a, bb, c] = b.faces[f].map(|i| b.verts[i as usize]);
            let det = (bb[1] - c[1]) * (a[0] - c[0]) + (c[0] - bb[0]) * (a[1] - c[1]);
            if det.abs() < 1e-14 {
                continue;
            }
            let l0 = ((bb[1] - c[1]) * (x - c[0]) + (c[0] - bb[0]) * (y - c[1])) / det;
            let l1 = ((c[1] - a[1]) * (x - c[0]) + (a[0] - c[0]) * (y - c[1])) / det;
            let l2 = 1.0 - l0 - l1;
            if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                continue;
            }
            let z = l0 * a[2] + l1 * bb[2] + l2 * c[2];
            if best.as_ref().is_none_or(|bz| z > bz.2) {
                best = Some((f, [l0, l1, l2], z));
            }
        }
        let (f, l, _) = best.expect("every landmark target lies on the face");
        fidx.push(f as u32);
        bary.extend(l.map(|v| v as f32));
    }
    (fidx, bary)
}
