//! Mesh export: Wavefront OBJ and binary PLY, written atomically.
use std::io::Write;
use std::path::Path;

use ply_rs_bw::ply::{
    Addable, DefaultElement, ElementDef, Encoding, Ply, Property, PropertyDef, PropertyType,
    ScalarType,
};
use ply_rs_bw::writer::Writer;

use crate::SmplxError;
use mvmp_io::write_atomic_with;

/// Write a triangle mesh as OBJ (`v x y z` lines, then 1-based `f a b c`).
pub fn write_obj(path: &Path, vertices: &[[f32; 3]], faces: &[[u32; 3]]) -> Result<(), SmplxError> {
    write_atomic_with(path, |w| {
        writeln!(
            w,
            "# mvmp mesh: {} vertices, {} faces, metres",
            vertices.len(),
            faces.len()
        )?;
        for v in vertices {
            writeln!(w, "v {} {} {}", v[0], v[1], v[2])?;
        }
        for f in faces {
            writeln!(w, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1)?;
        }
        Ok(())
    })
    .map_err(SmplxError::Output)
}

/// Write a triangle mesh as binary little-endian PLY (float vertices, `vertex_indices` as uchar/int lists).
pub fn write_ply(path: &Path, vertices: &[[f32; 3]], faces: &[[u32; 3]]) -> Result<(), SmplxError> {
    let mut ply = Ply::<DefaultElement>::new();
    ply.header.encoding = Encoding::BinaryLittleEndian;
    ply.header.comments.push("mvmp mesh, metres".into());
    let mut vdef = ElementDef::new("vertex".into());
    for n in ["x", "y", "z"] {
        vdef.properties.add(PropertyDef::new(
            n.into(),
            PropertyType::Scalar(ScalarType::Float),
        ));
    }
    ply.header.elements.add(vdef);
    let mut fdef = ElementDef::new("face".into());
    fdef.properties.add(PropertyDef::new(
        "vertex_indices".into(),
        PropertyType::List(ScalarType::UChar, ScalarType::Int),
    ));
    ply.header.elements.add(fdef);
    let verts: Vec<DefaultElement> = vertices
        .iter()
        .map(|v| {
            let mut e = DefaultElement::new();
            e.insert("x".into(), Property::Float(v[0]));
            e.insert("y".into(), Property::Float(v[1]));
            e.insert("z".into(), Property::Float(v[2]));
            e
        })
        .collect();
    let fcs: Vec<DefaultElement> = faces
        .iter()
        .map(|f| {
            let mut e = DefaultElement::new();
            e.insert(
                "vertex_indices".into(),
                Property::ListInt(f.iter().map(|&i| i as i32).collect()),
            );
            e
        })
        .collect();
    ply.payload.insert("vertex".into(), verts);
    ply.payload.insert("face".into(), fcs);
    write_atomic_with(path, |w| Writer::new().write_ply(w, &mut ply).map(|_| ()))
        .map_err(SmplxError::Output)
}
