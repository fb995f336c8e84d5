//! `mvmp import dinov2|hrnet --variant V --from FILE --out FILE`.
use std::path::Path;

use anyhow::{Result, bail};
use burn::tensor::Device;
use mvmp_backbone::{HrnetVariant, VitVariant};

use mvmp_backbone::import::import_dinov2;
use mvmp_io::checkpoint;

pub fn dinov2(variant: VitVariant, from: &Path, out: &Path) -> Result<()> {
    crate::paths::not_over_input("--out", out, from)?;
    let cfg = variant.config();
    let device = Device::flex();
    let mut vit = cfg.init(&device);
    let rep = import_dinov2(&mut vit, from)?;
    report(from, &rep)?;
    checkpoint::save(&vit, out)?;
    println!("wrote {} (burnpack, mvmp {variant} weights)", out.display());
    Ok(())
}

pub fn hrnet(variant: HrnetVariant, joints: usize, from: &Path, out: &Path) -> Result<()> {
    crate::paths::not_over_input("--out", out, from)?;
    let cfg = variant.config(joints);
    if joints == 0 {
        bail!("--joints must be at least 1");
    }
    let mut net = cfg.init(&Device::flex());
    let rep = mvmp_backbone::import::import_hrnet(&mut net, from)?;
    report(from, &rep)?;
    checkpoint::save(&net, out)?;
    println!(
        "wrote {} (burnpack, mvmp {variant} weights, {joints} joints)",
        out.display()
    );
    Ok(())
}

fn report(from: &Path, rep: &mvmp_io::checkpoint::LoadReport) -> Result<()> {
    println!("{}: loaded {} tensors", from.display(), rep.loaded.len());
    if !rep.missing.is_empty() {
        println!(
            "missing ({}), left at their initial values:",
            rep.missing.len()
        );
        for k in &rep.missing {
            println!("  {k}");
        }
    }
    if !rep.unused.is_empty() {
        println!("unused ({}):", rep.unused.len());
        for k in &rep.unused {
            println!("  {k}");
        }
    }
    if !rep.errors.is_empty() {
        for e in &rep.errors {
            eprintln!("  {e}");
        }
        // A shape or dtype that differs points at the wrong variant; anything else at the file.
        let mismatched = rep
            .errors
            .iter()
            .filter(|e| e.starts_with("Shape mismatch") || e.starts_with("DType mismatch"))
            .count();
        if mismatched < rep.errors.len() {
            bail!(
                "{}: {} tensors could not be read (the file is damaged or incomplete)",
                from.display(),
                rep.errors.len() - mismatched
            );
        }
        bail!(
            "{}: {mismatched} tensors could not be applied (shape or dtype mismatch); are --variant and --joints right?",
            from.display()
        );
    }
    if rep.loaded.is_empty() {
        bail!("{}: no tensor matched a parameter", from.display());
    }
    Ok(())
}
