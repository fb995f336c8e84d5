//! Shared by the SMPL-X tests: an independent f64 LBS written with plain loops and nalgebra, following
//! smplx's `lbs.py` step by step (no code shared with the tensor layer).
#![allow(dead_code)]
use mvmp_smplx::BodyModel;
use mvmp_smplx::names::{EXTRA_VERTEX_JOINTS, NUM_JOINTS};
use nalgebra::{Matrix3, Rotation3, Vector3};
use std::sync::OnceLock;

pub fn standin() -> &'static BodyModel {
    static M: OnceLock<BodyModel> = OnceLock::new();
    M.get_or_init(|| mvmp_smplx::standin_model(0))
}

pub struct RefOut {
    pub vertices: Vec<Vector3<f64>>,
    pub joints: Vec<Vector3<f64>>,
}

/// `pose`: 55 x 3 axis-angle; standard smplx translation.
pub fn reference_forward(
    m: &BodyModel,
    pose: &[f64],
    betas: &[f64],
    expr: &[f64],
    transl: [f64; 3],
) -> RefOut {
    let v = m.num_vertices();
    let l = m.num_shape_components;
    let e0 = m.expression_offset();
    let mut shaped: Vec<Vector3<f64>> = (0..v)
        .map(|i| Vector3::from_fn(|a, _| m.v_template[i * 3 + a] as f64))
        .collect();
    for (i, p) in shaped.iter_mut().enumerate() {
        for a in 0..3 {
            let base = (i * 3 + a) * l;
            for (c, b) in betas.iter().enumerate() {
                p[a] += b * m.shapedirs[base + c] as f64;
            }
            for (c, e) in expr.iter().enumerate() {
                p[a] += e * m.shapedirs[base + e0 + c] as f64;
            }
        }
    }
    let joints: Vec<Vector3<f64>> = (0..NUM_JOINTS)
        .map(|j| {
            (0..v).fold(Vector3::zeros(), |acc, i| {
                acc + shaped[i] * m.j_regressor[j * v + i] as f64
            })
        })
        .collect();
    let rots: Vec<Matrix3<f64>> = (0..NUM_JOINTS)
        .map(|j| {
            Rotation3::from_scaled_axis(Vector3::new(pose[j * 3], pose[j * 3 + 1], pose[j * 3 + 2]))
                .into_inner()
        })
        .collect();
    let mut feat = Vec::with_capacity(54 * 9);
    for r in &rots[1..] {
        let d = r - Matrix3::identity();
        for a in 0..3 {
            for b in 0..3 {
                feat.push(d[(a, b)]);
            }
        }
    }
    let posed: Vec<Vector3<f64>> = (0..v)
        .map(|i| {
            let mut p = shaped[i];
            for a in 0..3 {
                let row = &m.posedirs[(i * 3 + a) * 486..(i * 3 + a + 1) * 486];
                p[a] += row
                    .iter()
                    .zip(&feat)
                    .map(|(d, f)| *d as f64 * f)
                    .sum::<f64>();
            }
            p
        })
        .collect();
    let mut g_r = vec![Matrix3::identity(); NUM_JOINTS];
    let mut g_t = vec![Vector3::zeros(); NUM_JOINTS];
    for j in 0..NUM_JOINTS {
        let p = m.parents[j];
        if p < 0 {
            g_r[j] = rots[j];
            g_t[j] = joints[j];
        } else {
            let p = p as usize;
            g_r[j] = g_r[p] * rots[j];
            g_t[j] = g_r[p] * (joints[j] - joints[p]) + g_t[p];
        }
    }
    let t = Vector3::from(transl);
    let vertices: Vec<Vector3<f64>> = (0..v)
        .map(|i| {
            let mut r = Matrix3::zeros();
            let mut tr = Vector3::zeros();
            for j in 0..NUM_JOINTS {
                let w = m.weights[i * NUM_JOINTS + j] as f64;
                if w != 0.0 {
                    r += g_r[j] * w;
                    tr += (g_t[j] - g_r[j] * joints[j]) * w;
                }
            }
            r * posed[i] + tr + t
        })
        .collect();
    let mut out_j: Vec<Vector3<f64>> = g_t.iter().map(|x| x + t).collect();
    for (_, vid) in EXTRA_VERTEX_JOINTS {
        out_j.push(vertices[vid]);
    }
    if let Some((fi, bary)) = &m.landmarks {
        for (k, &f) in fi.iter().enumerate() {
            let tri = m.faces[f as usize];
            out_j.push((0..3).fold(Vector3::zeros(), |acc, c| {
                acc + vertices[tri[c] as usize] * bary[k * 3 + c] as f64
            }));
        }
    }
    RefOut {
        vertices,
        joints: out_j,
    }
}

/// A deterministic test pose: moderate angles on every joint.
pub fn test_pose(seed: f64) -> Vec<f64> {
    (0..165)
        .map(|i| ((i as f64 * 0.731 + seed).sin()) * 0.45)
        .collect()
}
