//! What the part-timing examples (`hrnet_parts`, `rootnet_parts`) share.
use std::io::Write;
use std::time::Instant;

/// The median and the fastest of `runs` runs of `f`, in milliseconds.
pub fn median_and_fastest(runs: usize, mut f: impl FnMut()) -> (f64, f64) {
    let mut ts: Vec<f64> = (0..runs)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    ts.sort_by(f64::total_cmp);
    (ts[ts.len() / 2], ts[0])
}

/// Writes `line` to standard output: an error, not a panic, when the reader has gone (`| head`).
pub fn print(line: std::fmt::Arguments) -> std::io::Result<()> {
    writeln!(std::io::stdout(), "{line}")
}

/// Ends the program with `result`: on an error, its message on standard error and exit status 1.
pub fn finish(name: &str, result: std::io::Result<()>) {
    if let Err(e) = result {
        eprintln!("{name}: {e}");
        std::process::exit(1);
    }
}
