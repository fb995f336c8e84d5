//! OBJ and PLY export parse back with independent readers (tobj, ply-rs).
mod common;
use common::standin;
use mvmp_smplx::export::{write_obj, write_ply};

fn mesh() -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let m = standin();
    let v = m
        .v_template
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    (v, m.faces.clone())
}

#[test]
fn obj_parses_back() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("body.obj");
    let (v, f) = mesh();
    write_obj(&p, &v, &f).unwrap();
    let (models, _) = tobj::load_obj(&p, &tobj::LoadOptions::default()).unwrap();
    assert_eq!(models.len(), 1);
    let mm = &models[0].mesh;
    assert_eq!(mm.positions.len(), v.len() * 3);
    assert_eq!(mm.indices.len(), f.len() * 3);
    // tobj renumbers vertices by first use; compare the geometry of every face corner instead.
    for (k, &i) in mm.indices.iter().enumerate() {
        let want = v[f[k / 3][k % 3] as usize];
        assert_eq!(
            mm.positions[i as usize * 3..i as usize * 3 + 3],
            want,
            "corner {k}"
        );
    }
}

#[test]
fn ply_parses_back() {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("body.ply");
    let (v, f) = mesh();
    write_ply(&p, &v, &f).unwrap();
    let mut file = std::fs::File::open(&p).unwrap();
    let ply = Parser::<DefaultElement>::new().read_ply(&mut file).unwrap();
    let verts = &ply.payload["vertex"];
    let faces = &ply.payload["face"];
    assert_eq!((verts.len(), faces.len()), (v.len(), f.len()));
    assert_eq!(verts[5]["y"], Property::Float(v[5][1]));
    assert_eq!(
        faces[7]["vertex_indices"],
        Property::ListInt(f[7].iter().map(|&i| i as i32).collect())
    );
}

#[test]
fn write_to_missing_directory_fails_cleanly() {
    let (v, f) = mesh();
    let e = write_obj(std::path::Path::new("/nonexistent-dir/x.obj"), &v, &f).unwrap_err();
    assert!(e.to_string().contains("/nonexistent-dir"), "{e}");
}
