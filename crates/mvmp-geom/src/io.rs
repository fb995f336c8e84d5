//! Atomic file writes: data goes to a temporary file beside the target, then is renamed over it, so a
//! crash or an error never leaves a half-written output; directories of outputs are staged the same way
//! ([`StagedDir`]).
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::GeomError;

/// Write `bytes` to `path` atomically (temporary file in the same directory, then rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), GeomError> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// Write to `path` atomically through a closure that fills a writer.
pub fn write_atomic_with(
    path: &Path,
    fill: impl FnOnce(&mut std::io::BufWriter<&mut std::fs::File>) -> std::io::Result<()>,
) -> Result<(), GeomError> {
    let io_err = |source| GeomError::Io {
        path: path.to_path_buf(),
        source,
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(io_err)?;
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        fill(&mut w).map_err(io_err)?;
        w.flush().map_err(io_err)?;
    }
    // Temporary files are created private (0600); outputs get the usual 0644.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        tmp.as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644))
            .map_err(io_err)?;
    }
    tmp.persist(path).map_err(|e| io_err(e.error))?;
    Ok(())
}

/// A directory of outputs filled under a temporary name beside its destination and moved into place only
/// by [`StagedDir::finish`]: a command that fails half-way leaves the destination as it was (the
/// temporary directory is removed when the value is dropped).
pub struct StagedDir {
    tmp: tempfile::TempDir,
    dest: PathBuf,
}

impl StagedDir {
    /// Stage outputs for `dest` (a directory, created by `finish` if missing).
    pub fn new(dest: &Path) -> Result<Self, GeomError> {
        let parent = match dest.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        let io_err = |source| GeomError::Io {
            path: parent.to_path_buf(),
            source,
        };
        std::fs::create_dir_all(parent).map_err(io_err)?;
        let tmp = tempfile::Builder::new()
            .prefix(".mvmp-partial-")
            .tempdir_in(parent)
            .map_err(io_err)?;
        Ok(StagedDir {
            tmp,
            dest: dest.to_path_buf(),
        })
    }

    /// Where to write: the staged counterpart of the destination.
    pub fn path(&self) -> &Path {
        self.tmp.path()
    }

    /// Move everything staged into the destination: a missing destination is renamed into place whole;
    /// into an existing one each staged file replaces its namesake (other files there are kept).
    pub fn finish(self) -> Result<(), GeomError> {
        if !self.dest.exists() {
            let tmp = self.tmp.keep();
            return std::fs::rename(&tmp, &self.dest).map_err(|source| GeomError::Io {
                path: self.dest.clone(),
                source,
            });
        }
        merge_into(self.tmp.path(), &self.dest)
    }
}

/// Move the tree under `from` into `to`, file by file (renames within one file system).
fn merge_into(from: &Path, to: &Path) -> Result<(), GeomError> {
    let io_err = |path: &Path| {
        let path = path.to_path_buf();
        move |source| GeomError::Io { path, source }
    };
    if !to.is_dir() {
        return Err(GeomError::Io {
            path: to.to_path_buf(),
            source: std::io::Error::other("exists and is not a directory"),
        });
    }
    for entry in std::fs::read_dir(from).map_err(io_err(from))? {
        let entry = entry.map_err(io_err(from))?;
        let (src, dst) = (entry.path(), to.join(entry.file_name()));
        if src.is_dir() && dst.is_dir() {
            merge_into(&src, &dst)?;
        } else {
            std::fs::rename(&src, &dst).map_err(io_err(&dst))?;
        }
    }
    Ok(())
}
