//! The commands' progress bars: one style, on stderr (indicatif hides them when stderr is not a terminal),
//! none at all when a command runs quietly.
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// A bar of `len` steps labelled `label`; its message, after the ETA, says how the last step went.
pub fn bar(len: u64, label: &str, quiet: bool) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let b = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
    b.set_style(
        ProgressStyle::with_template(
            "{prefix} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta_precise} {msg}",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    b.set_prefix(label.to_string());
    b
}

/// A bar made when the number of steps is first known (an evaluation learns it with its first frame).
pub struct LazyBar {
    label: &'static str,
    quiet: bool,
    bar: Option<ProgressBar>,
}

impl LazyBar {
    pub fn new(label: &'static str, quiet: bool) -> Self {
        LazyBar {
            label,
            quiet,
            bar: None,
        }
    }

    /// Step `i` (0-based) of `n` is done.
    pub fn done(&mut self, i: usize, n: usize) {
        let (label, quiet) = (self.label, self.quiet);
        let b = self.bar.get_or_insert_with(|| bar(n as u64, label, quiet));
        b.set_position(i as u64 + 1);
    }

    pub fn finish(self) {
        if let Some(b) = self.bar {
            b.finish_and_clear();
        }
    }
}
