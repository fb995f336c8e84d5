//! Loader errors and layouts: missing keys, wrong shapes, truncated files, pickles, 400 components,
//! Fortran order, pickled entries that must be skipped.
mod common;
use std::io::{Read, Write};
use std::path::Path;

use burn::tensor::{Device, Tensor, TensorData};
use common::standin;
use mvmp_smplx::{BodyModel, SmplxError, SmplxLayer, Translation};
use npyz::WriterBuilder;
use npyz::zip;

/// Copy `src` to `dst`, dropping entries named in `drop` and adding `(name, bytes)` entries.
fn rewrite(src: &Path, dst: &Path, drop: &[&str], add: &[(&str, Vec<u8>)]) {
    let mut zin = zip::ZipArchive::new(std::fs::File::open(src).unwrap()).unwrap();
    let mut zout = zip::ZipWriter::new(std::fs::File::create(dst).unwrap());
    for i in 0..zin.len() {
        let f = zin.by_index_raw(i).unwrap();
        if drop.iter().any(|d| f.name() == format!("{d}.npy")) {
            continue;
        }
        zout.raw_copy_file(f).unwrap();
    }
    for (name, bytes) in add {
        zout.start_file(format!("{name}.npy"), zip::write::FileOptions::default())
            .unwrap();
        zout.write_all(bytes).unwrap();
    }
    zout.finish().unwrap();
}

fn npy_f64(shape: &[u64], data: &[f64], fortran: bool) -> Vec<u8> {
    let mut buf = Vec::new();
    {
        let order = if fortran {
            npyz::Order::Fortran
        } else {
            npyz::Order::C
        };
        let mut w = npyz::WriteOptions::new()
            .default_dtype()
            .shape(shape)
            .order(order)
            .writer(&mut buf)
            .begin_nd()
            .unwrap();
        w.extend(data.iter().copied()).unwrap();
        w.finish().unwrap();
    }
    buf
}

fn written() -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("model.npz");
    standin().write_npz(&p).unwrap();
    (dir, p)
}

#[test]
fn missing_key_is_named() {
    let (dir, p) = written();
    let q = dir.path().join("no_posedirs.npz");
    rewrite(&p, &q, &["posedirs"], &[]);
    let e = BodyModel::load(&q).unwrap_err();
    assert!(
        matches!(&e, SmplxError::MissingKey { key, .. } if key == "posedirs"),
        "{e}"
    );
    assert!(e.to_string().contains("no_posedirs.npz"));
}

#[test]
fn wrong_shape_names_key_expected_and_actual() {
    let (dir, p) = written();
    let q = dir.path().join("bad_shape.npz");
    rewrite(
        &p,
        &q,
        &["J_regressor"],
        &[(
            "J_regressor",
            npy_f64(&[54, 10475], &vec![0.0; 54 * 10475], false),
        )],
    );
    let e = BodyModel::load(&q).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("J_regressor") && msg.contains("(55, 10475)") && msg.contains("[54, 10475]"),
        "{msg}"
    );
}

#[test]
fn a_model_without_vertices_is_refused() {
    let (dir, p) = written();
    let q = dir.path().join("empty.npz");
    rewrite(
        &p,
        &q,
        &["v_template"],
        &[("v_template", npy_f64(&[0, 3], &[], false))],
    );
    let msg = BodyModel::load(&q).unwrap_err().to_string();
    assert!(
        msg.contains("empty.npz") && msg.contains("v_template") && msg.contains("0 vertices"),
        "{msg}"
    );
}

#[test]
fn truncated_file_is_an_error_not_a_panic() {
    let (dir, p) = written();
    let mut bytes = Vec::new();
    std::fs::File::open(&p)
        .unwrap()
        .read_to_end(&mut bytes)
        .unwrap();
    for cut in [bytes.len() / 2, bytes.len() - 10, 100] {
        let q = dir.path().join(format!("cut{cut}.npz"));
        std::fs::write(&q, &bytes[..cut]).unwrap();
        let e = BodyModel::load(&q).unwrap_err();
        assert!(e.to_string().contains(&format!("cut{cut}.npz")), "{e}");
    }
    let e = BodyModel::load(&dir.path().join("absent.npz")).unwrap_err();
    assert!(matches!(e, SmplxError::Io { .. }));
}

#[test]
fn pickle_path_explains_conversion() {
    let e = BodyModel::load(Path::new("models/SMPLX_NEUTRAL.pkl")).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("SMPLX_NEUTRAL.pkl") && msg.contains("npz") && msg.contains("pkl_to_npz.py"),
        "{msg}"
    );
}

#[test]
fn pickled_entries_are_skipped() {
    let (dir, p) = written();
    // A minimal object-dtype .npy like numpy writes for dict-valued keys (joint2num, part2num).
    let header = "{'descr': '|O', 'fortran_order': False, 'shape': (), }";
    let mut h = header.to_string();
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut obj = b"\x93NUMPY\x01\x00".to_vec();
    obj.extend((h.len() as u16).to_le_bytes());
    obj.extend(h.as_bytes());
    obj.extend(b"\x80\x02}q\x00.");
    let q = dir.path().join("with_pickles.npz");
    rewrite(
        &p,
        &q,
        &[],
        &[("joint2num", obj.clone()), ("part2num", obj)],
    );
    let m = BodyModel::load(&q).unwrap();
    assert_eq!(&m, standin());
    let keys = BodyModel::list_keys(&q).unwrap();
    assert!(keys.iter().any(|(n, pickled)| n == "joint2num" && *pickled));
}

#[test]
fn four_hundred_component_layout_and_fortran_order() {
    let (dir, p) = written();
    let m = standin();
    let v = m.num_vertices();
    // v1.1 layout: 300 shape + 100 expression components; expression starts at 300.
    let mut sd = vec![0.0f64; v * 3 * 400];
    for k in 0..v * 3 {
        for c in 0..10 {
            sd[k * 400 + c] = m.shapedirs[k * 20 + c] as f64;
            sd[k * 400 + 300 + c] = m.shapedirs[k * 20 + 10 + c] as f64;
        }
        // Components the layer must ignore.
        sd[k * 400 + 10] = 1.0;
        sd[k * 400 + 310] = 1.0;
    }
    // Store v_template Fortran-ordered, as numpy does for a transposed array.
    let mut vt_f = vec![0.0f64; v * 3];
    for i in 0..v {
        for a in 0..3 {
            vt_f[a * v + i] = m.v_template[i * 3 + a] as f64;
        }
    }
    let q = dir.path().join("v11.npz");
    rewrite(
        &p,
        &q,
        &["shapedirs", "v_template"],
        &[
            ("shapedirs", npy_f64(&[v as u64, 3, 400], &sd, false)),
            ("v_template", npy_f64(&[v as u64, 3], &vt_f, true)),
        ],
    );
    let m400 = BodyModel::load(&q).unwrap();
    assert_eq!(m400.num_shape_components, 400);
    assert_eq!(m400.expression_offset(), 300);
    assert_eq!(m400.v_template, m.v_template);
    let d = Device::flex();
    let run = |model: &BodyModel| -> Vec<f32> {
        let layer = SmplxLayer::new(model, &d);
        let b: Vec<f32> = (0..10).map(|k| (k as f32 * 0.7).sin()).collect();
        let e: Vec<f32> = (0..10).map(|k| (k as f32 * 0.3).cos()).collect();
        layer
            .forward_axis_angle(
                Tensor::zeros([1, 55, 3], &d),
                Tensor::from_data(TensorData::new(b, [1, 10]), &d),
                Tensor::from_data(TensorData::new(e, [1, 10]), &d),
                Tensor::zeros([1, 3], &d),
                Translation::Standard,
            )
            .vertices
            .into_data()
            .try_into_vec()
            .unwrap()
    };
    let (a, b) = (run(m), run(&m400));
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    assert!(worst < 1e-6, "{worst}");
}

#[test]
fn hand_means_are_not_applied() {
    // The stand-in stores non-zero hand means; a zero hand pose must still give the flat template hand.
    let m = standin();
    let (l, _) = m.hands_mean.as_ref().unwrap();
    assert!(l.iter().any(|&x| x.abs() > 0.01));
    let d = Device::flex();
    let out = SmplxLayer::new(m, &d).forward_axis_angle(
        Tensor::zeros([1, 55, 3], &d),
        Tensor::zeros([1, 10], &d),
        Tensor::zeros([1, 10], &d),
        Tensor::zeros([1, 3], &d),
        Translation::Standard,
    );
    let v: Vec<f32> = out.vertices.into_data().try_into_vec().unwrap();
    let worst = v
        .iter()
        .zip(&m.v_template)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(worst < 1e-6, "{worst}");
}

/// A `.npy` of float64 whose header claims `shape` (written by hand: no writer makes such a header)
/// followed by `values` zeros.
fn npy_claiming(shape: &str, values: usize) -> Vec<u8> {
    npy_claiming_in(shape, values, false)
}

/// [`npy_claiming`] in C or Fortran (column-major) order.
fn npy_claiming_in(shape: &str, values: usize, fortran: bool) -> Vec<u8> {
    let order = if fortran { "True" } else { "False" };
    let mut h = format!("{{'descr': '<f8', 'fortran_order': {order}, 'shape': {shape}, }}");
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend((h.len() as u16).to_le_bytes());
    npy.extend(h.as_bytes());
    npy.extend(std::iter::repeat_n(0u8, values * 8));
    npy
}

#[test]
fn a_header_whose_shape_overflows_is_refused_naming_the_key() {
    let (dir, p) = written();
    // 2^32 x 2^32 x 1 wraps to 0 values in 64 bits; 2^63 x 2 to 0 as well; the other claims
    // more values than the file holds.
    for (i, shape) in [
        "(4294967296, 4294967296, 1)",
        "(9223372036854775808, 2)",
        "(1099511627776, 3)",
        "(18446744073709551615,)",
    ]
    .into_iter()
    .enumerate()
    {
        let q = dir.path().join(format!("overflow{i}.npz"));
        rewrite(
            &p,
            &q,
            &["v_template"],
            &[("v_template", npy_claiming(shape, 2))],
        );
        let msg = BodyModel::load(&q).unwrap_err().to_string();
        assert!(
            msg.contains(&format!("overflow{i}.npz")) && msg.contains("v_template"),
            "{shape}: {msg}"
        );
    }
}

#[test]
fn a_people_file_whose_header_overflows_is_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("people.npz");
    let mut z = zip::ZipWriter::new(std::fs::File::create(&path).unwrap());
    // 6148914691236517206 x 3 wraps to 2 values in 64 bits.
    z.start_file("transl.npy", zip::write::FileOptions::default())
        .unwrap();
    z.write_all(&npy_claiming("(6148914691236517206, 3)", 2))
        .unwrap();
    z.finish().unwrap();
    let msg = mvmp_smplx::people::read_people_npz(&path)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("people.npz") && msg.contains("transl"),
        "{msg}"
    );
}

/// Headers whose shape wraps in 64 bits or claims billions of values, in either order, are refused
/// before any value is read or reordered (a column-major reorder once indexed past the values read).
#[test]
fn a_people_file_claiming_more_than_it_holds_is_refused_in_either_order() {
    let dir = tempfile::tempdir().unwrap();
    for (i, (shape, fortran)) in [
        ("(9223372036854775809, 2)", true),
        ("(9223372036854775809, 2)", false),
        ("(4000000000, 3)", false),
        ("(4000000000, 3)", true),
        ("(2, 3)", true),
    ]
    .into_iter()
    .enumerate()
    {
        let path = dir.path().join(format!("people{i}.npz"));
        let mut z = zip::ZipWriter::new(std::fs::File::create(&path).unwrap());
        z.start_file("transl.npy", zip::write::FileOptions::default())
            .unwrap();
        // One value where the header claims more (the last case: 6 claimed, 1 held).
        z.write_all(&npy_claiming_in(shape, 1, fortran)).unwrap();
        z.finish().unwrap();
        let msg = mvmp_smplx::people::read_people_npz(&path)
            .unwrap_err()
            .to_string();
        assert!(
            msg.contains(&format!("people{i}.npz")) && msg.contains("transl"),
            "{shape} fortran {fortran}: {msg}"
        );
    }
}

#[test]
fn index_arrays_stored_as_fractions_are_refused_naming_the_key() {
    let (dir, p) = written();
    let m = standin();
    // The kinematic tree as float64 with one parent 2.5; the faces with one index 0.5.
    let mut kt: Vec<f64> = (0..2 * 55).map(|i| (i % 55) as f64).collect();
    kt[0] = -1.0;
    for (j, parent) in m.parents.iter().enumerate().skip(1) {
        kt[j] = *parent as f64;
    }
    kt[5] = 2.5;
    let mut f: Vec<f64> = m.faces.iter().flatten().map(|&i| i as f64).collect();
    f[4] = 0.5;
    let nf = m.faces.len() as u64;
    for (key, arr) in [
        ("kintree_table", npy_f64(&[2, 55], &kt, false)),
        ("f", npy_f64(&[nf, 3], &f, false)),
    ] {
        let q = dir.path().join(format!("fraction_{key}.npz"));
        rewrite(&p, &q, &[key], &[(key, arr)]);
        let msg = BodyModel::load(&q).unwrap_err().to_string();
        assert!(
            msg.contains(&format!("fraction_{key}.npz")) && msg.contains(key),
            "{msg}"
        );
    }
}

#[test]
fn half_of_a_pair_of_keys_is_refused_naming_the_missing_one() {
    let (dir, p) = written();
    for (dropped, kept) in [
        ("lmk_bary_coords", "lmk_faces_idx"),
        ("lmk_faces_idx", "lmk_bary_coords"),
        ("hands_meanr", "hands_meanl"),
    ] {
        let q = dir.path().join(format!("without_{dropped}.npz"));
        rewrite(&p, &q, &[dropped], &[]);
        let msg = BodyModel::load(&q).unwrap_err().to_string();
        assert!(
            msg.contains(&format!("without_{dropped}.npz"))
                && msg.contains(dropped)
                && msg.contains(kept),
            "{msg}"
        );
    }
    // Both halves of a pair absent: a model without landmarks (or hand means), as before.
    let q = dir.path().join("no_landmarks.npz");
    rewrite(&p, &q, &["lmk_faces_idx", "lmk_bary_coords"], &[]);
    let m = BodyModel::load(&q).unwrap();
    assert!(m.landmarks.is_none());
}
