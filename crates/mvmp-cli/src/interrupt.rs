//! What Ctrl-C (or SIGTERM, SIGHUP) does. While a run trains, the first press asks it to stop after the
//! current step (it then writes a checkpoint to resume from). Otherwise, or on a second press, the process quits at once, after
//! removing its temporary outputs (staged directories, files being written) and the outputs it registered
//! as unfinished: a new run's directory that holds no checkpoint yet, the demo's output directory. Either
//! way the exit status is 128 + the signal's number (130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP).
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::{Arc, Mutex, Once};

/// An unfinished output and when quitting removes it.
enum Unfinished {
    /// Always (the demo's output directory); `keep_dir`: only its contents (it existed, empty, before).
    Output { dir: PathBuf, keep_dir: bool },
    /// While it holds no `state.json` (a new run's directory: nothing to resume).
    Run(PathBuf),
}

struct State {
    /// The stop flag of the run that trains now.
    training: Option<Arc<AtomicBool>>,
    unfinished: Vec<Unfinished>,
}

/// The number of the last signal handled (0: none).
static RECEIVED: AtomicI32 = AtomicI32::new(0);

/// The signal that asked a run to stop, if one did (the run then ended with a checkpoint).
pub fn received() -> Option<u8> {
    match RECEIVED.load(Ordering::SeqCst) {
        s @ 1..=127 => Some(s as u8),
        _ => None,
    }
}

static STATE: Mutex<State> = Mutex::new(State {
    training: None,
    unfinished: Vec::new(),
});

fn state() -> std::sync::MutexGuard<'static, State> {
    STATE.lock().unwrap_or_else(|e| e.into_inner())
}

/// Install the handler (once per process; a failure leaves the signals at their defaults, quitting at
/// once).
pub fn install() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        if let Err(e) = listen() {
            tracing::warn!("signals keep their default action: {e}");
        }
    });
}

/// A thread that handles SIGINT, SIGTERM and SIGHUP (unless SIGHUP is ignored: a process started under
/// `nohup` must outlive its terminal).
#[cfg(unix)]
fn listen() -> std::io::Result<()> {
    use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
    let mut wanted = vec![SIGINT, SIGTERM];
    if !hangup_ignored() {
        wanted.push(SIGHUP);
    }
    let mut signals = signal_hook::iterator::Signals::new(&wanted)?;
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            for signal in signals.forever() {
                on_signal(signal);
            }
        })?;
    Ok(())
}

/// Whether SIGHUP is ignored now.
#[cfg(unix)]
fn hangup_ignored() -> bool {
    // SAFETY: sigaction with a null new action only reads the current disposition into `old`.
    unsafe {
        let mut old: libc::sigaction = std::mem::zeroed();
        libc::sigaction(libc::SIGHUP, std::ptr::null(), &mut old) == 0
            && old.sa_sigaction == libc::SIG_IGN
    }
}

#[cfg(not(unix))]
fn listen() -> std::io::Result<()> {
    // Ctrl-C is the only interruption here; 2 is SIGINT's number, so the status is 130 as on Unix.
    ctrlc::set_handler(|| on_signal(2)).map_err(std::io::Error::other)
}

/// A line on standard error that cannot panic (after a hangup, writes to the terminal fail).
fn say(text: std::fmt::Arguments) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "{text}");
}

/// `signal`'s number makes the exit status (128 + it, as a shell reports a process the signal killed).
fn on_signal(signal: i32) {
    RECEIVED.store(signal, Ordering::SeqCst);
    let mut s = state();
    if let Some(stop) = s.training.as_ref()
        && !stop.swap(true, Ordering::SeqCst)
    {
        say(format_args!(
            "\ninterrupted: writing a checkpoint after this step (Ctrl-C again to quit now)"
        ));
        return;
    }
    say(format_args!("\ninterrupted"));
    mvmp_io::remove_live_partials();
    for u in s.unfinished.drain(..).rev() {
        remove(u);
    }
    std::process::exit(128 + signal);
}

fn remove(u: Unfinished) {
    let (dir, keep_dir, why) = match u {
        Unfinished::Output { dir, keep_dir } => (dir, keep_dir, "unfinished"),
        Unfinished::Run(dir) if !dir.join("state.json").exists() => {
            (dir, false, "no checkpoint was written")
        }
        Unfinished::Run(_) => return,
    };
    match clear(&dir, keep_dir) {
        Ok(()) => say(format_args!("{why}: removed {}", dir.display())),
        Err(e) => say(format_args!(
            "{why}; removing {} failed: {e}",
            dir.display()
        )),
    }
}

/// Remove `dir` (or, with `keep_dir`, everything in it); a missing `dir` is no error.
pub fn clear(dir: &Path, keep_dir: bool) -> std::io::Result<()> {
    if !dir.exists() {
        return Ok(());
    }
    if !keep_dir {
        return std::fs::remove_dir_all(dir);
    }
    for entry in std::fs::read_dir(dir)? {
        mvmp_io::remove_path(&entry?.path())?;
    }
    Ok(())
}

/// A stop flag for a run about to train: Ctrl-C sets it (once) until [`training_ended`].
pub fn training_started() -> Arc<AtomicBool> {
    install();
    let stop = Arc::new(AtomicBool::new(false));
    state().training = Some(stop.clone());
    stop
}

/// The run stopped training: Ctrl-C quits at once again.
pub fn training_ended() {
    state().training = None;
}

/// A new run's directory: removed on quitting while it has no checkpoint.
pub fn new_run(dir: &Path) {
    install();
    state().unfinished.push(Unfinished::Run(dir.to_path_buf()));
}

/// An output directory to remove on quitting, until [`finished`] is called with it.
pub fn unfinished_output(dir: &Path, keep_dir: bool) {
    install();
    state().unfinished.push(Unfinished::Output {
        dir: dir.to_path_buf(),
        keep_dir,
    });
}

/// `dir` is complete: quitting keeps it.
pub fn finished(dir: &Path) {
    state().unfinished.retain(|u| match u {
        Unfinished::Output { dir: d, .. } | Unfinished::Run(d) => d != dir,
    });
}

#[cfg(test)]
mod tests {
    use super::clear;

    #[test]
    fn clearing_an_output_removes_it_or_only_what_it_holds() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("demo");
        std::fs::create_dir_all(out.join("run/checkpoints")).unwrap();
        std::fs::write(out.join("eval.json"), "{}").unwrap();
        std::fs::write(out.join("run/checkpoints/x"), "x").unwrap();
        clear(&out, true).unwrap();
        assert!(out.is_dir(), "the directory that existed before stays");
        assert_eq!(std::fs::read_dir(&out).unwrap().count(), 0);
        std::fs::create_dir_all(out.join("data")).unwrap();
        clear(&out, false).unwrap();
        assert!(!out.exists());
        clear(&out, false).unwrap();
    }
}
