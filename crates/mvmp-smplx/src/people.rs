//! `people.npz`: SMPL-X parameters of the people of one frame, as inference writes them and as
//! `mvmp eval --predictions` and pseudo-ground-truth read them. Per person (N rows) the standard smplx
//! keys, axis-angle: global_orient [N,3], body_pose [N,63], jaw_pose, leye_pose, reye_pose [N,3],
//! left_hand_pose, right_hand_pose [N,45], betas [N,10], expression [N,10], transl [N,3] (smplx's meaning:
//! added to the model origin); and pelvis [N,3] (the pelvis in the world), scores [N].
use std::path::Path;

use mvmp_io::write_atomic_with;
use npyz::WriterBuilder;

use crate::SmplxError;
use crate::names::POSE_KEYS;
use crate::params::{MAX_TRANSLATION, SmplxParams};

fn npz_err(path: &Path, e: impl std::fmt::Display) -> SmplxError {
    SmplxError::File {
        path: path.to_path_buf(),
        what: mvmp_io::brief(&e.to_string(), 300),
    }
}

/// Columns of `v` as `width` f32 values, zero-padded (an empty vector is all zeros).
fn padded(v: &[f64], width: usize) -> impl Iterator<Item = f32> + '_ {
    (0..width).map(move |i| v.get(i).copied().unwrap_or(0.0) as f32)
}

/// Write `people.npz` (atomically). `pelvis` is written when every person has one.
pub fn write_people_npz(path: &Path, people: &[StoredPerson]) -> Result<(), SmplxError> {
    let n = people.len();
    write_atomic_with(path, |w| {
        let mut w = npyz::npz::NpzWriter::new(w);
        let mut put = |name: &str, width: usize, data: Vec<f32>| -> std::io::Result<()> {
            let opts = npyz::zip::write::FileOptions::default()
                .compression_method(npyz::zip::CompressionMethod::Deflated);
            let shape: Vec<u64> = if width == 0 {
                vec![n as u64]
            } else {
                vec![n as u64, width as u64]
            };
            let mut out = w
                .array::<f32>(name, opts)?
                .default_dtype()
                .shape(&shape)
                .begin_nd()?;
            out.extend(data)?;
            out.finish()
        };
        let poses: Vec<Vec<f64>> = people.iter().map(|p| p.params.full_pose()).collect();
        for (key, first, count) in POSE_KEYS {
            let data = poses
                .iter()
                .flat_map(|full| {
                    full[first * 3..(first + count) * 3]
                        .iter()
                        .map(|&x| x as f32)
                })
                .collect();
            put(key, count * 3, data)?;
        }
        let column = |f: fn(&SmplxParams) -> &Vec<f64>, width: usize| -> Vec<f32> {
            people
                .iter()
                .flat_map(|p| padded(f(&p.params), width).collect::<Vec<_>>())
                .collect()
        };
        put("betas", 10, column(|p| &p.betas, 10))?;
        put("expression", 10, column(|p| &p.expression, 10))?;
        put("transl", 3, column(|p| &p.transl, 3))?;
        if people.iter().all(|p| p.pelvis.is_some()) {
            let pelvis = people
                .iter()
                .flat_map(|p| p.pelvis.unwrap_or_default().map(|x| x as f32))
                .collect();
            put("pelvis", 3, pelvis)?;
        }
        put("scores", 0, people.iter().map(|p| p.score as f32).collect())?;
        w.zip_writer().finish()?;
        Ok(())
    })?;
    Ok(())
}

/// An npz array: shape and values.
type Array = (Vec<u64>, Vec<f64>);

/// One person read back from `people.npz`.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredPerson {
    pub params: SmplxParams,
    pub score: f64,
    /// The pelvis in the world, where the file has it (inference writes it; other methods may not).
    pub pelvis: Option<[f64; 3]>,
}

/// Most people one stored frame may hold (a model decodes at most 1000): they are posed at once.
pub const MAX_STORED_PEOPLE: usize = 10_000;

/// Most values one person has in one array (the full pose, 55 joints x 3, is the widest).
const MAX_ROW: usize = 165;
/// Most values one array of `people.npz` may hold.
const MAX_ARRAY_VALUES: usize = MAX_STORED_PEOPLE * MAX_ROW;

/// Read `people.npz`: the standard smplx keys (missing pose keys are zero; `betas` and `expression` may
/// have up to 10 columns), optional `scores` (default 1). Any float dtype.
pub fn read_people_npz(path: &Path) -> Result<Vec<StoredPerson>, SmplxError> {
    let mut npz = npyz::npz::NpzArchive::open(path).map_err(|e| npz_err(path, e))?;
    let mut read = |name: &str| read_array(&mut npz, path, name);
    let (shape, transl) = read("transl")?.ok_or_else(|| npz_err(path, "missing key `transl`"))?;
    if shape.len() != 2 || shape[1] != 3 {
        return Err(npz_err(
            path,
            format!("key `transl` has shape {shape:?}; expected [N, 3]"),
        ));
    }
    let n = shape[0] as usize;
    if n > MAX_STORED_PEOPLE {
        return Err(npz_err(
            path,
            format!("key `transl` holds {n} people; at most {MAX_STORED_PEOPLE} per frame"),
        ));
    }
    let mut people: Vec<StoredPerson> = (0..n)
        .map(|i| StoredPerson {
            params: SmplxParams {
                transl: transl[i * 3..i * 3 + 3].to_vec(),
                ..Default::default()
            },
            score: 1.0,
            pelvis: None,
        })
        .collect();
    let mut keys: Vec<(&str, usize)> = POSE_KEYS.iter().map(|k| (k.0, k.2 * 3)).collect();
    keys.push(("betas", 0));
    keys.push(("expression", 0));
    for (key, width) in keys {
        let Some((shape, data)) = read(key)? else {
            continue;
        };
        check_rows(path, key, &shape, n, width)?;
        let c = shape[1] as usize;
        for (i, p) in people.iter_mut().enumerate() {
            set_param(&mut p.params, key, data[i * c..(i + 1) * c].to_vec());
        }
    }
    if let Some((shape, data)) = read("scores")? {
        finite_rows(path, "scores", &shape, &[n as u64], &data, 1)?;
        for (p, s) in people.iter_mut().zip(data) {
            p.score = s;
        }
    }
    if let Some((shape, data)) = read("pelvis")? {
        finite_rows(path, "pelvis", &shape, &[n as u64, 3], &data, 3)?;
        if let Some(i) = data.iter().position(|c| c.abs() > MAX_TRANSLATION) {
            return Err(npz_err(
                path,
                format!(
                    "key `pelvis`[{}] = {:?}: beyond {MAX_TRANSLATION} metres",
                    i / 3,
                    data[i]
                ),
            ));
        }
        for (p, c) in people.iter_mut().zip(data.chunks(3)) {
            p.pelvis = Some([c[0], c[1], c[2]]);
        }
    }
    for (i, p) in people.iter().enumerate() {
        p.params
            .validate(&format!("person {i}"))
            .map_err(|e| npz_err(path, e))?;
    }
    Ok(people)
}

/// One array of the archive as float64 rows in C order, with its shape; `None` when absent.
fn read_array<R: std::io::Read + std::io::Seek>(
    npz: &mut npyz::npz::NpzArchive<R>,
    path: &Path,
    name: &str,
) -> Result<Option<Array>, SmplxError> {
    let Some(arr) = npz.by_name(name).map_err(|e| npz_err(path, e))? else {
        return Ok(None);
    };
    let shape = arr.shape().to_vec();
    // The header's shape is checked before any value is read (the reader allocates what it declares),
    // and again against what was read, which the column-major reordering below indexes by.
    let Some(count) = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(usize::try_from(d).ok()?))
        .filter(|&c| c <= MAX_ARRAY_VALUES)
    else {
        return Err(npz_err(
            path,
            format!(
                "key `{name}` has shape {shape:?}: more than {MAX_ARRAY_VALUES} values \
                 ({MAX_STORED_PEOPLE} people of at most {MAX_ROW} values each)"
            ),
        ));
    };
    let fortran = matches!(arr.order(), npyz::Order::Fortran);
    let data: Vec<f64> = match arr.dtype() {
        npyz::DType::Plain(t) if t.type_char() == npyz::TypeChar::Float && t.size_field() == 4 => {
            arr.into_vec::<f32>()
                .map_err(|e| npz_err(path, format!("key `{name}`: {e}")))?
                .into_iter()
                .map(|x| x as f64)
                .collect()
        }
        _ => arr.into_vec::<f64>().map_err(|e| {
            npz_err(
                path,
                format!("key `{name}`: {e} (expected float32 or float64)"),
            )
        })?,
    };
    if data.len() != count {
        return Err(npz_err(
            path,
            format!(
                "key `{name}` holds {} values; its shape {shape:?} needs {count}",
                data.len()
            ),
        ));
    }
    // numpy may store column-major arrays; rows are read in C order.
    let data = if fortran && shape.len() == 2 {
        let (r, c) = (shape[0] as usize, shape[1] as usize);
        (0..r * c).map(|i| data[(i % c) * r + i / c]).collect()
    } else {
        data
    };
    Ok(Some((shape, data)))
}

/// A parameter array is `[N, width]` (`width` 0: at most 10 coefficients) with N the rows of `transl`.
fn check_rows(
    path: &Path,
    key: &str,
    shape: &[u64],
    n: usize,
    width: usize,
) -> Result<(), SmplxError> {
    let ok = shape.len() == 2
        && shape[0] as usize == n
        && (if width == 0 {
            shape[1] <= 10
        } else {
            shape[1] as usize == width
        });
    if ok {
        return Ok(());
    }
    let want = if width == 0 {
        "[N, <=10]".to_string()
    } else {
        format!("[N, {width}]")
    };
    Err(npz_err(
        path,
        format!(
            "key `{key}` has shape {shape:?}; expected {want} with N = {n} (the rows of `transl`)"
        ),
    ))
}

/// Put one person's row of `key` into its parameters.
fn set_param(p: &mut SmplxParams, key: &str, row: Vec<f64>) {
    match key {
        "global_orient" => p.global_orient = row,
        "body_pose" => p.body_pose = row,
        "jaw_pose" => p.jaw_pose = row,
        "leye_pose" => p.leye_pose = row,
        "reye_pose" => p.reye_pose = row,
        "left_hand_pose" => p.left_hand_pose = row,
        "right_hand_pose" => p.right_hand_pose = row,
        "betas" => p.betas = row,
        _ => p.expression = row,
    }
}

/// An optional per-person array has shape `want` and finite values (`per` per person).
fn finite_rows(
    path: &Path,
    key: &str,
    shape: &[u64],
    want: &[u64],
    data: &[f64],
    per: usize,
) -> Result<(), SmplxError> {
    if shape != want {
        return Err(npz_err(
            path,
            format!("key `{key}` has shape {shape:?}; expected {want:?}"),
        ));
    }
    match data.iter().position(|s| !s.is_finite()) {
        Some(i) => Err(npz_err(
            path,
            format!("key `{key}`[{}] = {} is not finite", i / per, data[i]),
        )),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn person(pelvis: Option<[f64; 3]>) -> StoredPerson {
        let mut params = SmplxParams {
            global_orient: vec![0.5, -0.25, 0.125],
            betas: vec![1.0, -2.0],
            transl: vec![0.1, 0.2, 0.3],
            ..Default::default()
        };
        params.body_pose = (0..63).map(|i| i as f64 / 64.0).collect();
        StoredPerson {
            params,
            score: 0.75,
            pelvis,
        }
    }

    #[test]
    fn people_round_trip_and_a_bad_pelvis_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("people.npz");
        let people = [
            person(Some([1.0, -2.0, 0.5])),
            person(Some([0.0, 0.0, 1.0])),
        ];
        write_people_npz(&path, &people).unwrap();
        let back = read_people_npz(&path).unwrap();
        assert_eq!(back.len(), 2);
        assert_eq!(back[0].pelvis, Some([1.0, -2.0, 0.5]));
        assert_eq!(back[1].score, 0.75);
        // Written as float32: these values are exact in it; betas are padded to 10 columns.
        assert_eq!(back[0].params.global_orient, people[0].params.global_orient);
        assert_eq!(back[0].params.body_pose, people[0].params.body_pose);
        assert_eq!(&back[0].params.betas[..2], &[1.0, -2.0]);
        assert_eq!(back[0].params.betas.len(), 10);
        // Without a pelvis for every person, the key is left out and reads back as unknown.
        write_people_npz(&path, &[person(None), person(Some([0.0; 3]))]).unwrap();
        assert!(
            read_people_npz(&path)
                .unwrap()
                .iter()
                .all(|p| p.pelvis.is_none())
        );
        // A non-finite pelvis is an error naming the file, the key and the person.
        write_people_npz(
            &path,
            &[person(Some([0.0; 3])), person(Some([f64::NAN, 0.0, 0.0]))],
        )
        .unwrap();
        let e = read_people_npz(&path).unwrap_err().to_string();
        assert!(
            e.contains("people.npz") && e.contains("`pelvis`[1]") && e.contains("NaN"),
            "{e}"
        );
        // So is a pelvis kilometres away.
        write_people_npz(&path, &[person(Some([0.0, 1e30, 0.0]))]).unwrap();
        let e = read_people_npz(&path).unwrap_err().to_string();
        assert!(e.contains("`pelvis`[0] = 1") && e.contains("metres"), "{e}");
    }
}
