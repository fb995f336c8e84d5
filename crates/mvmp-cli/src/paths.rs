//! Outputs that would overwrite a command's own input are refused before anything is written.
use std::path::{Path, PathBuf};

use anyhow::{Result, bail};

/// `path` resolved through the links and `..` of its existing part (the file itself may not exist yet).
fn resolved(path: &Path) -> Option<PathBuf> {
    if let Ok(p) = path.canonicalize() {
        return Some(p);
    }
    let name = path.file_name()?;
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    Some(parent.canonicalize().ok()?.join(name))
}

/// Refuse an `--out` report whose directory does not exist: a report written at the end of a long
/// command says so before the work rather than after it.
pub fn out_dir_exists(out: Option<&Path>) -> Result<()> {
    let parent = out.and_then(Path::parent);
    if let Some(dir) = parent.filter(|d| !d.as_os_str().is_empty() && !d.is_dir()) {
        bail!("--out: {} is not a directory", dir.display());
    }
    Ok(())
}

/// Refuse an output (`flag`) that is the input file `input` or, for an input directory, lies inside it.
pub fn not_over_input(flag: &str, out: &Path, input: &Path) -> Result<()> {
    let (Some(o), Some(i)) = (resolved(out), resolved(input)) else {
        return Ok(());
    };
    let clash = if i.is_dir() {
        o.starts_with(&i)
    } else {
        o == i
    };
    if clash {
        bail!(
            "{flag} {}: would overwrite the input {}",
            out.display(),
            input.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::not_over_input;

    #[test]
    fn an_output_over_its_input_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("ds");
        std::fs::create_dir_all(data.join("scene")).unwrap();
        let weights = dir.path().join("w.pth");
        std::fs::write(&weights, "w").unwrap();
        let e = not_over_input("--sheet", &data.join("dataset.json"), &data).unwrap_err();
        assert!(
            e.to_string().contains("--sheet") && e.to_string().contains("ds"),
            "{e}"
        );
        assert!(not_over_input("--sheet", &data.join("scene/../x.png"), &data).is_err());
        assert!(not_over_input("--out", &weights, &weights).is_err());
        assert!(not_over_input("--out", &dir.path().join("./w.pth"), &weights).is_err());
        assert!(not_over_input("--sheet", &dir.path().join("sheet.png"), &data).is_ok());
        assert!(not_over_input("--out", &dir.path().join("w.bpk"), &weights).is_ok());
    }
}
