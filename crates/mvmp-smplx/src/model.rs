//! SMPL-X body-model files in the official `SMPLX_*.npz` layout (the keys smplx loads), read and written.
//!
//! Required keys: `v_template` (V, 3), `f` (F, 3), `shapedirs` (V, 3, L) with L >= 20 (20: 10 shape + 10
//! expression, v1.0; 400: 300 + 100, v1.1), `posedirs` (V, 3, 486), `J_regressor` (55, V), `weights` (V, 55),
//! `kintree_table` (2, 55). Optional: `lmk_faces_idx` (51,), `lmk_bary_coords` (51, 3) (giving the 51 face
//! landmarks), `hands_meanl`, `hands_meanr` (45,) (read but not applied: hands are relative to a flat hand).
//! Keys holding pickled objects (`joint2num`, `part2num`, ...) are skipped. Any float or integer dtype
//! loads; Fortran-ordered arrays are reordered.
use std::collections::BTreeSet;
use std::io::{Read, Seek};
use std::path::Path;

use npyz::{TypeChar, WriterBuilder};

use crate::SmplxError;
use crate::names::{NUM_EXPRESSION, NUM_JOINTS, NUM_POSE_JOINTS, PARENTS};
use mvmp_io::{brief, write_atomic_with};

/// Largest magnitude of any float in a body model: SMPL-X's template spans about 1.8 m, its shape and
/// pose directions move vertices by centimetres per unit, and its weights, regressor rows and landmark
/// coordinates lie in [0, 1]. A model in millimetres, or a broken file, exceeds it.
pub const MAX_MODEL_VALUE: f64 = 10.0;

/// A body model held on the CPU, as in the file (float32).
#[derive(Debug, Clone, PartialEq)]
pub struct BodyModel {
    /// `[V, 3]` rest-pose template (metres, y up).
    pub v_template: Vec<f32>,
    /// `[F, 3]` triangles.
    pub faces: Vec<[u32; 3]>,
    /// `[V, 3, L]` shape (and expression) directions.
    pub shapedirs: Vec<f32>,
    /// L, the number of components in `shapedirs`.
    pub num_shape_components: usize,
    /// `[V, 3, 486]` pose-corrective directions.
    pub posedirs: Vec<f32>,
    /// `[55, V]` joint regressor.
    pub j_regressor: Vec<f32>,
    /// `[V, 55]` skinning weights.
    pub weights: Vec<f32>,
    /// Parent of each joint (-1 for the root).
    pub parents: Vec<i32>,
    /// `[51]` faces of the static face landmarks and `[51, 3]` their barycentric coordinates.
    pub landmarks: Option<(Vec<u32>, Vec<f32>)>,
    /// `[45]` each: the file's mean hand poses (kept for round trips; not applied).
    pub hands_mean: Option<(Vec<f32>, Vec<f32>)>,
}

/// One array read from an npz: values as f64 in C order, and its shape.
struct Array {
    data: Vec<f64>,
    shape: Vec<usize>,
}

/// Most values one array of a body-model file may hold: about twice SMPL-X's largest (posedirs, 10475 x 3 x
/// 486), so that a header declaring billions is refused before anything is allocated.
pub const MAX_ARRAY_VALUES: usize = 1 << 25;

fn read_array<R: Read + Seek>(
    npz: &mut npyz::npz::NpzArchive<R>,
    path: &Path,
    key: &str,
) -> Result<Option<Array>, SmplxError> {
    let bad = |what: String| SmplxError::Value {
        path: path.to_path_buf(),
        key: key.into(),
        what,
    };
    let Some(npy) = npz
        .by_name(key)
        .map_err(|e| bad(format!("unreadable: {}", brief(&e.to_string(), 200))))?
    else {
        return Ok(None);
    };
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let fortran = matches!(npy.order(), npyz::Order::Fortran);
    let dtype = npy.dtype();
    let npyz::DType::Plain(ts) = &dtype else {
        return Err(SmplxError::Dtype {
            path: path.into(),
            key: key.into(),
            dtype: dtype.descr(),
            expected: "a numeric array",
        });
    };
    // The header's shape is checked before any value is read: the reader allocates what it declares.
    let Some(n) = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .filter(|&n| n <= MAX_ARRAY_VALUES)
    else {
        return Err(bad(format!(
            "has shape {shape:?}: more than {MAX_ARRAY_VALUES} values (SMPL-X's largest array, \
             posedirs, holds 15.3 million)"
        )));
    };
    let read_err = |e: std::io::Error| bad(format!("truncated or corrupt data: {e}"));
    let data: Vec<f64> = match (ts.type_char(), ts.size_field()) {
        (TypeChar::Float, 8) => npy.into_vec::<f64>().map_err(read_err)?,
        (TypeChar::Float, 4) => npy
            .into_vec::<f32>()
            .map_err(read_err)?
            .into_iter()
            .map(f64::from)
            .collect(),
        (TypeChar::Int, 8) => conv(npy.into_vec::<i64>().map_err(read_err)?),
        (TypeChar::Int, 4) => conv(npy.into_vec::<i32>().map_err(read_err)?),
        (TypeChar::Uint, 8) => conv(npy.into_vec::<u64>().map_err(read_err)?),
        (TypeChar::Uint, 4) => conv(npy.into_vec::<u32>().map_err(read_err)?),
        (TypeChar::Object, _) => {
            return Err(bad(
                "holds pickled Python objects, not a numeric array".into()
            ));
        }
        _ => {
            return Err(SmplxError::Dtype {
                path: path.into(),
                key: key.into(),
                dtype: dtype.descr(),
                expected: "float32/64 or int32/64",
            });
        }
    };
    if data.len() != n {
        return Err(bad(format!(
            "holds {} values, its shape {shape:?} needs {n}",
            data.len()
        )));
    }
    let data = if fortran && shape.len() > 1 {
        fortran_to_c(&data, &shape)
    } else {
        data
    };
    Ok(Some(Array { data, shape }))
}

fn conv<T: Copy + TryInto<i64>>(v: Vec<T>) -> Vec<f64> {
    // Unsigned root markers (4294967295) become large positive numbers; callers only use in-range indices.
    v.into_iter()
        .map(|x| x.try_into().map(|i: i64| i as f64).unwrap_or(f64::MAX))
        .collect()
}

/// Reorder column-major data of the given shape into row-major order.
fn fortran_to_c(data: &[f64], shape: &[usize]) -> Vec<f64> {
    let n = data.len();
    let mut out = vec![0.0; n];
    let nd = shape.len();
    let mut idx = vec![0usize; nd];
    for (c_pos, slot) in out.iter_mut().enumerate() {
        // Unravel c_pos in C order, ravel in Fortran order.
        let mut rem = c_pos;
        for d in (0..nd).rev() {
            idx[d] = rem % shape[d];
            rem /= shape[d];
        }
        let mut f_pos = 0;
        let mut stride = 1;
        for d in 0..nd {
            f_pos += idx[d] * stride;
            stride *= shape[d];
        }
        *slot = data[f_pos];
    }
    out
}

struct Reader<'a, R: Read + Seek> {
    npz: npyz::npz::NpzArchive<R>,
    path: &'a Path,
}

impl<R: Read + Seek> Reader<'_, R> {
    fn optional(
        &mut self,
        key: &str,
        expected: &[Option<usize>],
    ) -> Result<Option<Array>, SmplxError> {
        let Some(a) = read_array(&mut self.npz, self.path, key)? else {
            return Ok(None);
        };
        let ok = a.shape.len() == expected.len()
            && a.shape
                .iter()
                .zip(expected)
                .all(|(s, e)| e.is_none_or(|e| e == *s));
        if !ok {
            let exp: Vec<String> = expected
                .iter()
                .map(|e| e.map_or("*".to_string(), |v| v.to_string()))
                .collect();
            return Err(SmplxError::Shape {
                path: self.path.into(),
                key: key.into(),
                expected: format!("({})", exp.join(", ")),
                actual: a.shape,
            });
        }
        Ok(Some(a))
    }

    fn required(&mut self, key: &str, expected: &[Option<usize>]) -> Result<Array, SmplxError> {
        self.optional(key, expected)?
            .ok_or_else(|| SmplxError::MissingKey {
                path: self.path.into(),
                key: key.into(),
            })
    }
}

fn f32s(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

/// How far a skinning-weight or regressor row may stray from summing to 1 (and a weight below 0): the
/// official files hold float32 rows within 1e-6 of it.
const ROW_TOLERANCE: f32 = 1e-2;

fn value_err(path: &Path, key: &str, what: String) -> SmplxError {
    SmplxError::Value {
        path: path.into(),
        key: key.into(),
        what,
    }
}

/// The triangles of `f`, every index below the `v` vertices.
fn faces_of(f: &Array, v: usize, path: &Path) -> Result<Vec<[u32; 3]>, SmplxError> {
    if let Some((i, bad)) = f
        .data
        .iter()
        .enumerate()
        .find(|(_, x)| !(**x >= 0.0 && (**x as usize) < v && x.fract() == 0.0))
    {
        return Err(value_err(
            path,
            "f",
            format!("entry {i} = {bad} is not a vertex index below {v}"),
        ));
    }
    Ok(f.data
        .chunks_exact(3)
        .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
        .collect())
}

/// The parents of `kintree_table`'s first row (the root's set to -1), each before its child.
fn parents_of(kt: &Array, path: &Path) -> Result<Vec<i32>, SmplxError> {
    // The root's entry is a marker (-1, or 4294967295 unsigned); every other one an index.
    if let Some((j, p)) = kt.data[1..NUM_JOINTS]
        .iter()
        .enumerate()
        .find(|(_, p)| p.fract() != 0.0 || !p.is_finite())
    {
        return Err(value_err(
            path,
            "kintree_table",
            format!("joint {} has parent {p}, not a joint index", j + 1),
        ));
    }
    let mut parents: Vec<i32> = kt.data[..NUM_JOINTS].iter().map(|&p| p as i32).collect();
    parents[0] = -1;
    for (j, &p) in parents.iter().enumerate().skip(1) {
        if p < 0 || p as usize >= j {
            return Err(value_err(
                path,
                "kintree_table",
                format!("joint {j} has parent {p}; parents must precede their children"),
            ));
        }
    }
    Ok(parents)
}

/// The landmarks' face indices, each below the `nf` faces.
fn landmark_faces(fi: &Array, nf: usize, path: &Path) -> Result<Vec<u32>, SmplxError> {
    if let Some(bad) = fi
        .data
        .iter()
        .find(|x| !(**x >= 0.0 && (**x as usize) < nf && x.fract() == 0.0))
    {
        return Err(value_err(
            path,
            "lmk_faces_idx",
            format!("{bad} is not a face index below {nf}"),
        ));
    }
    Ok(fi.data.iter().map(|&x| x as u32).collect())
}

impl BodyModel {
    pub fn num_vertices(&self) -> usize {
        self.v_template.len() / 3
    }

    pub fn num_faces(&self) -> usize {
        self.faces.len()
    }

    /// Joints the body layer outputs for this model: 55, plus the vertex joints when the model has
    /// SMPL-X's vertices (76), plus the face landmarks when it has them (127).
    pub fn num_output_joints(&self) -> usize {
        let v = self.num_vertices();
        if crate::names::EXTRA_VERTEX_JOINTS
            .iter()
            .any(|&(_, vid)| vid >= v)
        {
            return NUM_JOINTS;
        }
        let landmarks = self.landmarks.as_ref().map_or(0, |(faces, _)| faces.len());
        NUM_JOINTS + crate::names::EXTRA_VERTEX_JOINTS.len() + landmarks
    }

    /// Load an `SMPLX_*.npz` file.
    pub fn load(path: &Path) -> Result<Self, SmplxError> {
        if path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("pkl"))
        {
            return Err(SmplxError::Pickle { path: path.into() });
        }
        let file = std::fs::File::open(path).map_err(|source| SmplxError::Io {
            path: path.into(),
            source,
        })?;
        let npz = npyz::npz::NpzArchive::new(std::io::BufReader::new(file)).map_err(|e| {
            SmplxError::NotNpz {
                path: path.into(),
                what: brief(&e.to_string(), 200),
            }
        })?;
        let mut r = Reader { npz, path };
        let vt = r.required("v_template", &[None, Some(3)])?;
        let v = vt.shape[0];
        if v == 0 {
            return Err(SmplxError::Value {
                path: path.into(),
                key: "v_template".into(),
                what: "has 0 vertices".into(),
            });
        }
        let f = r.required("f", &[None, Some(3)])?;
        let sd = r.required("shapedirs", &[Some(v), Some(3), None])?;
        let l = sd.shape[2];
        if l < 10 + NUM_EXPRESSION {
            return Err(SmplxError::Shape {
                path: path.into(),
                key: "shapedirs".into(),
                expected: format!("({v}, 3, L) with L >= 20"),
                actual: sd.shape,
            });
        }
        let pd = r.required("posedirs", &[Some(v), Some(3), Some(NUM_POSE_JOINTS * 9)])?;
        let jr = r.required("J_regressor", &[Some(NUM_JOINTS), Some(v)])?;
        let w = r.required("weights", &[Some(v), Some(NUM_JOINTS)])?;
        let kt = r.required("kintree_table", &[Some(2), Some(NUM_JOINTS)])?;
        let lmk_f = r.optional("lmk_faces_idx", &[Some(51)])?;
        let lmk_b = r.optional("lmk_bary_coords", &[Some(51), Some(3)])?;
        let hml = r.optional("hands_meanl", &[Some(45)])?;
        let hmr = r.optional("hands_meanr", &[Some(45)])?;

        // Keys that only work in pairs: one without the other is a damaged file, not a model without
        // landmarks (its output would silently lose 51 joints) or without hand means.
        for (a, b, has_a, has_b) in [
            (
                "lmk_faces_idx",
                "lmk_bary_coords",
                lmk_f.is_some(),
                lmk_b.is_some(),
            ),
            ("hands_meanl", "hands_meanr", hml.is_some(), hmr.is_some()),
        ] {
            if has_a != has_b {
                let (present, absent) = if has_a { (a, b) } else { (b, a) };
                return Err(value_err(
                    path,
                    absent,
                    format!("missing, while `{present}` is present (they come as a pair)"),
                ));
            }
        }
        let faces = faces_of(&f, v, path)?;
        let parents = parents_of(&kt, path)?;
        let landmarks = match (lmk_f, lmk_b) {
            (Some(fi), Some(b)) => Some((landmark_faces(&fi, faces.len(), path)?, f32s(&b.data))),
            _ => None,
        };
        let model = BodyModel {
            v_template: f32s(&vt.data),
            faces,
            shapedirs: f32s(&sd.data),
            num_shape_components: l,
            posedirs: f32s(&pd.data),
            j_regressor: f32s(&jr.data),
            weights: f32s(&w.data),
            parents,
            landmarks,
            hands_mean: hml.zip(hmr).map(|(a, b)| (f32s(&a.data), f32s(&b.data))),
        };
        model.check_values(path)?;
        model.check_rows(path)?;
        Ok(model)
    }

    /// Each vertex's skinning weights are a convex blend (no negative share, summing to 1) and each
    /// joint's regressor row sums to 1: a row of zeros puts its vertex or joint at the origin whatever
    /// the pose, which is a damaged file, not a body.
    fn check_rows(&self, path: &Path) -> Result<(), SmplxError> {
        let v = self.v_template.len() / 3;
        let rows = |vals: &[f32], n: usize| -> Vec<(f32, f32)> {
            vals.chunks(n)
                .map(|r| {
                    (
                        r.iter().sum(),
                        r.iter().copied().fold(f32::INFINITY, f32::min),
                    )
                })
                .collect()
        };
        for (i, (sum, min)) in rows(&self.weights, NUM_JOINTS).into_iter().enumerate() {
            if min < -ROW_TOLERANCE || (sum - 1.0).abs() > ROW_TOLERANCE {
                let what = format!(
                    "vertex {i}'s weights sum to {sum:?} with least {min:?}: skinning weights are \
                     shares of 1, none negative"
                );
                return Err(value_err(path, "weights", what));
            }
        }
        for (j, (sum, _)) in rows(&self.j_regressor, v).into_iter().enumerate() {
            if (sum - 1.0).abs() > ROW_TOLERANCE {
                let what =
                    format!("joint {j}'s row sums to {sum:?}, where a regressor's rows sum to 1");
                return Err(value_err(path, "J_regressor", what));
            }
        }
        Ok(())
    }

    /// Every float array finite and within [`MAX_MODEL_VALUE`].
    fn check_values(&self, path: &Path) -> Result<(), SmplxError> {
        let empty = Vec::new();
        let (hands_l, hands_r) = self
            .hands_mean
            .as_ref()
            .map_or((&empty, &empty), |(l, r)| (l, r));
        let bary = self.landmarks.as_ref().map_or(&empty, |(_, b)| b);
        for (key, vals) in [
            ("v_template", &self.v_template),
            ("shapedirs", &self.shapedirs),
            ("posedirs", &self.posedirs),
            ("J_regressor", &self.j_regressor),
            ("weights", &self.weights),
            ("lmk_bary_coords", bary),
            ("hands_meanl", hands_l),
            ("hands_meanr", hands_r),
        ] {
            if let Some(i) = vals.iter().position(|x| !x.is_finite()) {
                return Err(value_err(
                    path,
                    key,
                    format!("entry {i} is not finite ({})", vals[i]),
                ));
            }
            if let Some(i) = vals
                .iter()
                .position(|x| f64::from(x.abs()) > MAX_MODEL_VALUE)
            {
                return Err(value_err(
                    path,
                    key,
                    format!(
                        "entry {i} is {:?}: beyond +-{MAX_MODEL_VALUE}, which no body model in metres \
                         holds",
                        vals[i]
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Index of the first expression component in `shapedirs`: 10 for the 20-component (v1.0) layout,
    /// 300 for the 400-component (v1.1) layout, as smplx does.
    pub fn expression_offset(&self) -> usize {
        if self.num_shape_components >= 400 {
            300
        } else {
            10
        }
    }

    /// Whether the joints of the kinematic tree equal the SMPL-X tree.
    pub fn has_smplx_tree(&self) -> bool {
        self.parents == PARENTS
    }

    /// Names of the arrays in an npz file, with the ones that hold pickled objects marked.
    pub fn list_keys(path: &Path) -> Result<Vec<(String, bool)>, SmplxError> {
        let mut npz = npyz::npz::NpzArchive::open(path).map_err(|e| SmplxError::NotNpz {
            path: path.into(),
            what: brief(&e.to_string(), 200),
        })?;
        let names: BTreeSet<String> = npz.array_names().map(str::to_string).collect();
        let mut out = Vec::new();
        for n in names {
            let pickled = npz
                .by_name(&n)
                .ok()
                .flatten()
                .is_some_and(|a| a.uses_pickled_array());
            out.push((n, pickled));
        }
        Ok(out)
    }

    /// Write the model in the official npz layout (float64 arrays, `f` as uint32, `kintree_table` as int64
    /// with -1 for the root's parent), atomically.
    pub fn write_npz(&self, path: &Path) -> Result<(), SmplxError> {
        write_atomic_with(path, |w| {
            let mut w = npyz::npz::NpzWriter::new(w);
            let v = self.num_vertices();
            let l = self.num_shape_components;
            let f64s = |x: &[f32]| x.iter().map(|&a| a as f64).collect::<Vec<_>>();
            write_arr(&mut w, "v_template", &[v, 3], &f64s(&self.v_template))?;
            let f: Vec<u32> = self.faces.iter().flatten().copied().collect();
            write_arr(&mut w, "f", &[self.faces.len(), 3], &f)?;
            write_arr(&mut w, "shapedirs", &[v, 3, l], &f64s(&self.shapedirs))?;
            let pd = f64s(&self.posedirs);
            write_arr(&mut w, "posedirs", &[v, 3, NUM_POSE_JOINTS * 9], &pd)?;
            let jr = f64s(&self.j_regressor);
            write_arr(&mut w, "J_regressor", &[NUM_JOINTS, v], &jr)?;
            write_arr(&mut w, "weights", &[v, NUM_JOINTS], &f64s(&self.weights))?;
            let kt: Vec<i64> = self
                .parents
                .iter()
                .map(|&p| p as i64)
                .chain(0..NUM_JOINTS as i64)
                .collect();
            write_arr(&mut w, "kintree_table", &[2, NUM_JOINTS], &kt)?;
            if let Some((fi, b)) = &self.landmarks {
                let fi: Vec<i64> = fi.iter().map(|&x| x as i64).collect();
                write_arr(&mut w, "lmk_faces_idx", &[51], &fi)?;
                write_arr(&mut w, "lmk_bary_coords", &[51, 3], &f64s(b))?;
            }
            if let Some((l, r)) = &self.hands_mean {
                write_arr(&mut w, "hands_meanl", &[45], &f64s(l))?;
                write_arr(&mut w, "hands_meanr", &[45], &f64s(r))?;
                // The PCA hand bases of the official files; identity (full axis-angle) here.
                let eye: Vec<f64> = (0..45 * 45)
                    .map(|i| if i % 46 == 0 { 1.0 } else { 0.0 })
                    .collect();
                write_arr(&mut w, "hands_componentsl", &[45, 45], &eye)?;
                write_arr(&mut w, "hands_componentsr", &[45, 45], &eye)?;
            }
            w.zip_writer().finish()?;
            Ok(())
        })
        .map_err(SmplxError::Output)
    }
}

fn write_arr<W, T>(
    w: &mut npyz::npz::NpzWriter<W>,
    name: &str,
    shape: &[usize],
    data: &[T],
) -> std::io::Result<()>
where
    W: std::io::Write + std::io::Seek,
    T: npyz::AutoSerialize + Copy,
{
    let shape: Vec<u64> = shape.iter().map(|&s| s as u64).collect();
    let opts = npyz::zip::write::FileOptions::default()
        .compression_method(npyz::zip::CompressionMethod::Deflated);
    let mut out = w
        .array::<T>(name, opts)?
        .default_dtype()
        .shape(&shape)
        .begin_nd()?;
    out.extend(data.iter().copied())?;
    out.finish()
}
