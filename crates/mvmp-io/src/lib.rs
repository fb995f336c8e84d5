//! File output for every crate: atomic writes (data goes to a temporary file beside the target, then is
//! renamed over it, so a crash or an error never leaves a half-written output; directories of outputs are
//! staged the same way, [`StagedDir`]), the sweep of temporaries a killed process left, JSON parsing that
//! names the offending key, and model checkpoints ([`checkpoint`]).
use std::io::Write;
use std::path::{Path, PathBuf};

pub mod checkpoint;
mod error;

pub use error::IoError;

/// Write `bytes` to `path` atomically (temporary file in the same directory, then rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// Write to `path` atomically through a closure that fills a writer.
pub fn write_atomic_with(
    path: &Path,
    fill: impl FnOnce(&mut std::io::BufWriter<&mut std::fs::File>) -> std::io::Result<()>,
) -> Result<(), IoError> {
    let io_err = |source| IoError::Io {
        path: path.to_path_buf(),
        source,
    };
    let dir = parent_dir(path);
    sweep_stale(dir);
    let mut tmp = tempfile::Builder::new()
        .prefix(&partial_prefix())
        .tempfile_in(dir)
        .map_err(io_err)?;
    let _live = Live::new(tmp.path());
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        fill(&mut w).map_err(io_err)?;
        w.flush().map_err(io_err)?;
    }
    readable(tmp.path()).map_err(io_err)?;
    tmp.persist(path).map_err(|e| io_err(e.error))?;
    Ok(())
}

/// [`write_atomic_with`] for a writer that opens the file itself, given a path (a checkpoint store, an
/// optimizer's recorder): `fill` writes a temporary dot-file beside `path`, removed if `fill` fails,
/// which then replaces `path`.
pub fn write_atomic_via<E: From<IoError>>(
    path: &Path,
    fill: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), E> {
    let io_err = |source| IoError::Io {
        path: path.to_path_buf(),
        source,
    };
    // The temporary name keeps the destination's extension: writers that add one to a path without
    // (burn's burnpack writer) would otherwise write beside it.
    let suffix = path
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    sweep_stale(parent_dir(path));
    let tmp = tempfile::Builder::new()
        .prefix(&partial_prefix())
        .suffix(&suffix)
        .tempfile_in(parent_dir(path))
        .map_err(io_err)?
        .into_temp_path();
    let _live = Live::new(&tmp);
    fill(&tmp)?;
    readable(&tmp).map_err(io_err)?;
    tmp.persist(path).map_err(|e| io_err(e.error))?;
    Ok(())
}

/// The temporary outputs this process is writing now (see [`remove_live_partials`]).
static LIVE: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

fn live() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    LIVE.lock().unwrap_or_else(|e| e.into_inner())
}

/// Registers a temporary output while it exists.
struct Live(PathBuf);

impl Live {
    fn new(path: &Path) -> Live {
        live().push(path.to_path_buf());
        Live(path.to_path_buf())
    }
}

impl Drop for Live {
    fn drop(&mut self) {
        live().retain(|p| p != &self.0);
    }
}

/// Remove every temporary output this process is writing now. For a process about to quit on a signal:
/// `exit` runs no destructors, so the temporaries would otherwise stay behind until the next output
/// in their directory sweeps them.
pub fn remove_live_partials() {
    for p in live().drain(..) {
        let _ = remove_path(&p);
    }
}

/// Remove a file, or a directory with everything in it (a link is removed, not followed).
pub fn remove_path(path: &Path) -> std::io::Result<()> {
    if path.symlink_metadata()?.is_dir() {
        std::fs::remove_dir_all(path)
    } else {
        std::fs::remove_file(path)
    }
}

/// Every temporary output starts with this, then `<process id>@<host>-` and a random part.
pub const PARTIAL_PREFIX: &str = ".mvmp-partial-";

/// This machine's name as it appears in temporary names (letters and digits only).
fn host() -> &'static str {
    static HOST: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    HOST.get_or_init(|| {
        std::fs::read_to_string("/proc/sys/kernel/hostname")
            .unwrap_or_default()
            .chars()
            .filter(char::is_ascii_alphanumeric)
            .collect()
    })
}

/// The start of the temporary names of process `pid` on this machine.
pub fn partial_prefix_of(pid: u32) -> String {
    format!("{PARTIAL_PREFIX}{pid}@{}-", host())
}

fn partial_prefix() -> String {
    partial_prefix_of(std::process::id())
}

/// Remove from `dir` the temporary outputs of processes that no longer run (a kill or a power cut
/// leaves them behind; an error or Ctrl-C removes its own). Only what is certainly stale goes: names
/// this module makes, of this machine (a directory shared with others may hold their live ones), owned
/// by this user (`/proc` may hide other users' processes), of a process `/proc` does not list.
/// Failures are ignored, since a leftover costs disk space, not correctness.
pub fn sweep_stale(dir: &Path) {
    #[cfg(unix)]
    sweep_stale_unix(dir);
    #[cfg(not(unix))]
    let _ = dir;
}

#[cfg(unix)]
fn sweep_stale_unix(dir: &Path) {
    use std::os::unix::fs::MetadataExt;
    let proc = Path::new("/proc");
    let Ok(me) = proc.join("self").metadata() else {
        return;
    };
    if host().is_empty() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(pid) = name.to_str().and_then(stale_pid) else {
            continue;
        };
        let mine = entry.metadata().is_ok_and(|m| m.uid() == me.uid());
        if !mine || pid == std::process::id() || proc.join(pid.to_string()).exists() {
            continue;
        }
        let path = entry.path();
        if remove_path(&path).is_ok() {
            tracing::warn!(
                "removed {} (left by an interrupted process)",
                path.display()
            );
        }
    }
}

/// The process id in a temporary output's name made on this machine.
fn stale_pid(name: &str) -> Option<u32> {
    let rest = name.strip_prefix(PARTIAL_PREFIX)?;
    let (pid, rest) = rest.split_once('@')?;
    let random = rest.strip_prefix(host())?.strip_prefix('-')?;
    (!random.is_empty()).then_some(())?;
    pid.parse().ok()
}

/// The directory a file is written in (`.` for a bare name).
fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    }
}

/// Temporary files are created private (0600); outputs get the usual 0644.
fn readable(path: &Path) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o644))?;
    }
    #[cfg(not(unix))]
    let _ = path;
    Ok(())
}

/// A message from a reader of file formats, shortened to `max` characters: some echo what they failed
/// to parse (a damaged header can be 64 KB), which buries the file name and the key around it.
pub fn brief(message: &str, max: usize) -> String {
    match message.char_indices().nth(max) {
        None => message.to_string(),
        Some((cut, _)) => format!(
            "{}... ({} more characters)",
            &message[..cut],
            message[cut..].chars().count()
        ),
    }
}

/// A directory of outputs filled under a temporary name beside its destination and moved into place only
/// by [`StagedDir::finish`]: a command that fails half-way leaves the destination as it was (the
/// temporary directory is removed when the value is dropped).
pub struct StagedDir {
    tmp: tempfile::TempDir,
    dest: PathBuf,
    /// The file names of the command's own outputs ([`StagedDir::owning`]).
    owned: Option<fn(&str) -> bool>,
    _live: Live,
}

impl StagedDir {
    /// Stage outputs for `dest` (a directory, created by `finish` if missing).
    pub fn new(dest: &Path) -> Result<Self, IoError> {
        // An existing destination by its real path: `.` or `out/..` would otherwise put the stage
        // inside the destination it is to replace.
        let real = dest.canonicalize().ok();
        let parent = match real.as_deref().unwrap_or(dest).parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            Some(_) => Path::new("."),
            None => {
                return Err(IoError::Io {
                    path: dest.to_path_buf(),
                    source: std::io::Error::other("an output directory cannot be the root"),
                });
            }
        };
        let io_err = |source| IoError::Io {
            path: parent.to_path_buf(),
            source,
        };
        std::fs::create_dir_all(parent).map_err(io_err)?;
        sweep_stale(parent);
        let tmp = tempfile::Builder::new()
            .prefix(&partial_prefix())
            .tempdir_in(parent)
            .map_err(io_err)?;
        // Temporary directories are created private (0700); outputs get the usual 0755.
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(tmp.path(), std::fs::Permissions::from_mode(0o755))
                .map_err(io_err)?;
        }
        Ok(StagedDir {
            _live: Live::new(tmp.path()),
            tmp,
            dest: real.unwrap_or_else(|| dest.to_path_buf()),
            owned: None,
        })
    }

    /// Name the command's own outputs (by file name, at any depth): those of an earlier run that
    /// this one does not write go with the merge instead of staying beside the new ones (three people's
    /// meshes after a run that found two would otherwise read as three).
    pub fn owning(mut self, owned: fn(&str) -> bool) -> Self {
        self.owned = Some(owned);
        self
    }

    /// Where to write: the staged counterpart of the destination.
    pub fn path(&self) -> &Path {
        self.tmp.path()
    }

    /// Put everything staged into the destination: a missing destination is renamed into place whole.
    /// An existing one gets the staged files in place of their namesakes and keeps its other files: those
    /// are linked into the stage first and the two directories then swap in one rename (Linux), so the
    /// destination is never seen half-merged.
    pub fn finish(self) -> Result<(), IoError> {
        if !self.dest.exists() {
            // Held across the rename: a signal's `remove_live_partials` waits rather than removing
            // the tree as it moves into place.
            let live = live();
            let tmp = self.tmp.keep();
            let moved = std::fs::rename(&tmp, &self.dest).map_err(|source| IoError::Io {
                path: self.dest.clone(),
                source,
            });
            drop(live);
            return moved;
        }
        if !self.dest.is_dir() {
            return Err(IoError::Io {
                path: self.dest.clone(),
                source: std::io::Error::other("exists and is not a directory"),
            });
        }
        keep_others(&self.dest, self.tmp.path(), self.owned)?;
        let perms = self
            .dest
            .metadata()
            .map_err(io_at(&self.dest))?
            .permissions();
        std::fs::set_permissions(self.tmp.path(), perms).map_err(io_at(self.tmp.path()))?;
        // As above; after the swap the stage holds the old tree, which may go.
        let _live = live();
        swap(self.tmp.path(), &self.dest)
        // The stage now holds the old tree, removed as the `TempDir` drops.
    }
}

fn io_at(path: &Path) -> impl FnOnce(std::io::Error) -> IoError + '_ {
    move |source| IoError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Link (or copy) into `stage` every entry of `dest` that the stage has no namesake of, recursing into
/// directories both hold.
fn keep_others(dest: &Path, stage: &Path, owned: Option<fn(&str) -> bool>) -> Result<(), IoError> {
    for entry in std::fs::read_dir(dest).map_err(io_at(dest))? {
        let entry = entry.map_err(io_at(dest))?;
        let (old, new) = (entry.path(), stage.join(entry.file_name()));
        if owned.is_some_and(|owned| entry.file_name().to_str().is_some_and(owned)) {
            continue; // an earlier run's output: the stage's outputs replace all of them
        }
        let is_dir = entry.file_type().map_err(io_at(&old))?.is_dir();
        match (is_dir, new.symlink_metadata().ok()) {
            (true, Some(m)) if m.is_dir() => keep_others(&old, &new, owned)?,
            (_, Some(_)) => {} // the staged namesake replaces it
            (true, None) => {
                std::fs::create_dir(&new).map_err(io_at(&new))?;
                keep_others(&old, &new, owned)?;
            }
            (false, None) => {
                if std::fs::hard_link(&old, &new).is_err() {
                    std::fs::copy(&old, &new).map_err(io_at(&new))?;
                }
            }
        }
    }
    Ok(())
}

/// Exchange two directories: one atomic rename on Linux; elsewhere two renames, the destination put back
/// if the second fails.
fn swap(stage: &Path, dest: &Path) -> Result<(), IoError> {
    #[cfg(target_os = "linux")]
    {
        use rustix::fs::{CWD, RenameFlags, renameat_with};
        renameat_with(CWD, stage, CWD, dest, RenameFlags::EXCHANGE)
            .map_err(|e| io_at(dest)(e.into()))
    }
    #[cfg(not(target_os = "linux"))]
    {
        let aside = stage.with_extension("old");
        std::fs::rename(dest, &aside).map_err(io_at(dest))?;
        if let Err(e) = std::fs::rename(stage, dest) {
            let _ = std::fs::rename(&aside, dest);
            return Err(io_at(dest)(e));
        }
        std::fs::rename(&aside, stage).map_err(io_at(stage))
    }
}

/// Parse JSON text into `T`; the error names the key path where it failed (`people[0].pelvis[2]`),
/// then serde's message with its line and column.
pub fn parse_json<T: serde::de::DeserializeOwned>(text: &str) -> Result<T, String> {
    let de = &mut serde_json::Deserializer::from_str(text);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let key = e.path().to_string();
        let inner = e.into_inner().to_string();
        match key.as_str() {
            "" | "." => inner,
            // serde_json's word for a fixed-length array given more elements than it holds.
            _ if inner.starts_with("trailing characters") => {
                format!("key `{key}`: more elements than it takes ({inner})")
            }
            _ => format!("key `{key}`: {inner}"),
        }
    })
}
