//! The `Pose` variable of Human3.6M's NASA CDF pose files (`D3_Positions/<action>.cdf`): 32 joints x
//! (x, y, z) per frame. The files are parsed by the `cdf` crate; this module finds the variable (a
//! zVariable or an rVariable), gathers its records from the index tree (plain or GZIP-compressed blocks),
//! puts column-major arrays into row-major order and returns one row of values per frame. The file's
//! structure is checked first ([`guard`]), so that the decoder never sizes a buffer beyond the file.
mod guard;

use std::io::Read;
use std::path::Path;

use cdf::decode::Decodable;
use cdf::record::vxr::{VariableIndexRecord, VariableIndexRecordChild};
use cdf::repr::Endian;
use cdf::types::CdfType;

use crate::DataError;

/// CDF data types that hold IEEE floats (CDF_REAL4, CDF_REAL8, CDF_FLOAT, CDF_DOUBLE).
fn float_width(data_type: i32) -> Option<usize> {
    match data_type {
        21 | 44 => Some(4),
        22 | 45 => Some(8),
        _ => None,
    }
}

thread_local! {
    static DECODING: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Whether this thread is inside the CDF decoder, whose panics on a damaged file are caught and
/// reported as that file's error: a panic hook can keep quiet about them.
pub fn decoding_on_this_thread() -> bool {
    DECODING.with(|d| d.get())
}

/// `f` with its panic caught, marked for [`decoding_on_this_thread`] while it runs.
fn quietly<R>(f: impl FnOnce() -> R) -> std::thread::Result<R> {
    DECODING.with(|d| d.set(true));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    DECODING.with(|d| d.set(false));
    r
}

/// The values of variable `name` as f64, every record in order, each record's array in row-major order;
/// with the per-record dimensions.
pub fn read_variable(path: &Path, name: &str) -> Result<(Vec<f64>, Vec<usize>), DataError> {
    if !path.is_file() {
        return Err(DataError::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        ));
    }
    let bad = |what: String| DataError::file(path, what);
    let bytes = std::fs::read(path).map_err(|e| DataError::io(path, e))?;
    // The decoder allocates what the file declares before reading it, and a failed allocation aborts
    // the process: the structure is checked first, on the very bytes then decoded. The check refuses
    // files compressed as a whole, which the decoder cannot read.
    guard::check(&bytes).map_err(|w| bad(format!("not a readable CDF file: {w}")))?;
    // The decoder indexes into buffers it reads; a damaged file must not take the process down.
    let decoded = quietly(|| decode(bytes))
        .map_err(|_| bad("not a readable CDF file (the decoder failed on its structure)".into()))?
        .map_err(|e| bad(format!("not a readable CDF file: {e}")))?;
    let cdr = &decoded.cdr;
    let gdr = &cdr.gdr;
    let little = match cdr.encoding.get_endian() {
        Ok(Endian::Little) => true,
        Ok(Endian::Big) => false,
        Err(e) => return Err(bad(format!("unsupported encoding: {e}"))),
    };
    let (data_type, dims, vxrs) = if let Some(z) = gdr.zvdr_vec.iter().find(|v| *v.name == name) {
        let dims = record_dims(z.size_z_dims.iter().map(|d| i64::from(**d)))
            .map_err(|w| bad(format!("variable `{name}`: {w}")))?;
        (*z.data_type, dims, &z.vxr_vec)
    } else if let Some(r) = gdr.rvdr_vec.iter().find(|v| *v.name == name) {
        let dims = record_dims(gdr.size_r_dims.iter().map(|d| i64::from(**d)))
            .map_err(|w| bad(format!("variable `{name}`: {w}")))?;
        (*r.data_type, dims, &r.vxr_vec)
    } else {
        let names: Vec<String> = gdr
            .zvdr_vec
            .iter()
            .map(|v| v.name.to_string())
            .chain(gdr.rvdr_vec.iter().map(|v| v.name.to_string()))
            .collect();
        return Err(bad(format!(
            "no variable `{name}` (the file has {names:?})"
        )));
    };
    let width = float_width(data_type).ok_or_else(|| {
        bad(format!(
            "variable `{name}` has CDF data type {data_type}, expected a float type (21, 22, 44 or 45)"
        ))
    })?;
    let mut values = Vec::new();
    for vxr in vxrs {
        collect(vxr, width, little, &mut values)
            .map_err(|w| bad(format!("variable `{name}`: {w}")))?;
    }
    let per_record: usize = dims.iter().product::<usize>().max(1);
    if values.len() % per_record != 0 {
        return Err(bad(format!(
            "variable `{name}` holds {} values, not whole records of {dims:?}",
            values.len()
        )));
    }
    if !cdr.flags.row_major && dims.len() > 1 {
        for rec in values.chunks_mut(per_record) {
            let col = rec.to_vec();
            for (i, v) in rec.iter_mut().enumerate() {
                *v = col[column_major_offset(i, &dims)];
            }
        }
    }
    Ok((values, dims))
}

/// The `cdf` crate's decoding of a whole file held in memory.
fn decode(bytes: Vec<u8>) -> Result<cdf::cdf::Cdf, cdf::error::CdfError> {
    let mut decoder = cdf::decode::Decoder::new(std::io::Cursor::new(bytes))?;
    cdf::cdf::Cdf::decode_be(&mut decoder)
}

/// Most values a variable may hold over all its records (a Human3.6M pose sequence: a few thousand
/// frames of 96).
pub const MAX_VALUES: usize = 1 << 24;

/// A record's dimensions as the file declares them: each at least 1, their product at most
/// [`MAX_VALUES`].
fn record_dims(dims: impl Iterator<Item = i64>) -> Result<Vec<usize>, String> {
    let dims: Vec<i64> = dims.collect();
    let ok: Option<Vec<usize>> = dims
        .iter()
        .map(|&d| usize::try_from(d).ok().filter(|&d| d >= 1))
        .collect();
    match ok {
        Some(d)
            if d.iter()
                .try_fold(1usize, |a, &x| a.checked_mul(x))
                .is_some_and(|n| n <= MAX_VALUES) =>
        {
            Ok(d)
        }
        _ => Err(format!(
            "record dimensions {dims:?}: each must be at least 1 and their product at most {MAX_VALUES}"
        )),
    }
}

/// Where the element at row-major position `i` of an array of `dims` sits in column-major order.
fn column_major_offset(mut i: usize, dims: &[usize]) -> usize {
    let mut index = vec![0; dims.len()];
    for (k, &d) in dims.iter().enumerate().rev() {
        index[k] = i % d;
        i /= d;
    }
    let (mut off, mut stride) = (0, 1);
    for (k, &d) in dims.iter().enumerate() {
        off += index[k] * stride;
        stride *= d;
    }
    off
}

fn collect(
    vxr: &VariableIndexRecord,
    width: usize,
    little: bool,
    out: &mut Vec<f64>,
) -> Result<(), String> {
    for child in vxr.children.iter().flatten() {
        match child {
            VariableIndexRecordChild::VXR(inner) => collect(inner, width, little, out)?,
            VariableIndexRecordChild::VVR(vvr) => {
                for rec in &vvr.records {
                    if out.len() + rec.data.len() > MAX_VALUES {
                        return Err(format!("more than {MAX_VALUES} values"));
                    }
                    for v in &rec.data {
                        out.push(match v {
                            CdfType::Real4(x) => **x as f64,
                            CdfType::Real8(x) => **x,
                            other => return Err(format!("a non-float value {other:?}")),
                        });
                    }
                }
            }
            VariableIndexRecordChild::CVVR(c) => {
                if c.data.get(..2) != Some(&[0x1f, 0x8b]) {
                    return Err(
                        "a compressed block that is not GZIP (only GZIP is supported)".into(),
                    );
                }
                // Bounded, so that a small block cannot inflate into more than a variable may hold.
                let cap = ((MAX_VALUES - out.len().min(MAX_VALUES)) * width) as u64;
                let mut raw = Vec::new();
                flate2::read::GzDecoder::new(&c.data[..])
                    .take(cap + 1)
                    .read_to_end(&mut raw)
                    .map_err(|e| format!("a damaged GZIP block: {e}"))?;
                if raw.len() as u64 > cap {
                    return Err(format!(
                        "a GZIP block that inflates beyond {MAX_VALUES} values"
                    ));
                }
                if raw.len() % width != 0 {
                    return Err(format!(
                        "a decompressed block of {} bytes, not whole {width}-byte values",
                        raw.len()
                    ));
                }
                for b in raw.chunks_exact(width) {
                    out.push(match (width, little) {
                        (4, true) => f32::from_le_bytes(b.try_into().unwrap()) as f64,
                        (4, false) => f32::from_be_bytes(b.try_into().unwrap()) as f64,
                        (_, true) => f64::from_le_bytes(b.try_into().unwrap()),
                        (_, false) => f64::from_be_bytes(b.try_into().unwrap()),
                    });
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::{MAX_VALUES, column_major_offset, record_dims};

    #[test]
    fn column_major_offsets_by_hand() {
        // A 2 x 3 array: row-major (r, c) -> column-major r + 2 c.
        let got: Vec<usize> = (0..6).map(|i| column_major_offset(i, &[2, 3])).collect();
        assert_eq!(got, [0, 2, 4, 1, 3, 5]);
        // 1-D arrays are the same in both orders.
        assert_eq!(column_major_offset(4, &[7]), 4);
    }

    /// Dimensions a file declares: zero, negative or overflowing ones are refused before anything is
    /// indexed by them; a Human3.6M pose record (96 values) is not.
    #[test]
    fn declared_dimensions_are_checked() {
        assert_eq!(record_dims([96].into_iter()), Ok(vec![96]));
        assert_eq!(record_dims([32, 3].into_iter()), Ok(vec![32, 3]));
        for bad in [
            vec![0],
            vec![32, 0],
            vec![-1],
            vec![i64::from(i32::MIN)],
            vec![1 << 20, 1 << 20],
            vec![MAX_VALUES as i64 + 1],
        ] {
            assert!(record_dims(bad.clone().into_iter()).is_err(), "{bad:?}");
        }
    }
}
