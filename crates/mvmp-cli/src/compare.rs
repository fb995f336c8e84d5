//! `mvmp compare`: several runs side by side, as the figures their evaluations stored
//! (`RUN/eval-<split>.json`, written by `mvmp eval --run`) and one picture of their validation curves.
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail, ensure};
use mvmp_eval::Metrics;
use mvmp_train::curves::{Curves, write_png};

use crate::run::table;

pub struct CompareArgs<'a> {
    pub runs: &'a [PathBuf],
    /// A name per run, in order (default: each run directory's own name).
    pub names: Option<&'a [String]>,
    /// The split whose stored evaluation is read.
    pub split: &'a str,
    /// The stage whose curves are drawn (1: detection, 2: the whole model).
    pub stage: u8,
    /// The validation error drawn, a `*_mm` key of the runs' logs (default: the stage's headline,
    /// `root_mm` or `mpjpe_mm`).
    pub error: Option<&'a str>,
    /// Where the picture goes (none: the table alone).
    pub plot: Option<&'a Path>,
}

/// The table of every run's stored figures (also printed), after writing the picture if asked.
pub fn compare(args: &CompareArgs) -> Result<String> {
    let names = names(args.runs, args.names)?;
    ensure!(
        matches!(args.stage, 1 | 2),
        "--stage {}: expected 1 (detection) or 2 (the whole model)",
        args.stage
    );
    let mut rows = Vec::new();
    for (dir, name) in args.runs.iter().zip(&names) {
        rows.push((name.clone(), stored_metrics(dir, args.split)?));
    }
    if let Some(plot) = args.plot {
        let (headline, recall) = match args.stage {
            1 => ("root_mm", "root_recall"),
            _ => ("mpjpe_mm", "recall_500"),
        };
        let error = args.error.unwrap_or(headline);
        let mut curves = Vec::new();
        for (dir, name) in args.runs.iter().zip(&names) {
            let log = dir.join("metrics.jsonl");
            let text = std::fs::read_to_string(&log)
                .with_context(|| format!("reading {}", log.display()))?;
            curves.push((name.clone(), Curves::from_log(&text)));
        }
        let s = args.stage;
        drawn(&curves, &format!("stage {s} {error}"))?;
        let picture = Curves::compare(
            &curves,
            &format!("stage {s} total"),
            &format!("stage {s} {error}"),
            &format!("stage {s} {recall}"),
        );
        write_png(&picture, plot)?;
        eprintln!("written: {}", plot.display());
    }
    let people: Vec<usize> = rows.iter().map(|r| r.1.ground_truth).collect();
    let mut s = with_parts(&table(&rows), &rows);
    if people.iter().any(|&p| p != people[0]) {
        s += &format!(
            "note: the runs were scored on sets of different sizes (people: {people:?}): their \
             figures do not compare\n"
        );
    }
    print!("{s}");
    Ok(s)
}

/// Refuses a validation error that no run logged, naming those they did.
fn drawn(curves: &[(String, Curves)], name: &str) -> Result<()> {
    let logged = |c: &Curves| c.errors.iter().map(|s| s.name.clone()).collect::<Vec<_>>();
    if curves
        .iter()
        .any(|(_, c)| logged(c).iter().any(|n| n == name))
    {
        return Ok(());
    }
    let mut known: Vec<String> = curves.iter().flat_map(|(_, c)| logged(c)).collect();
    known.sort();
    known.dedup();
    bail!("no run logged validation {name:?}; they logged {known:?}")
}

/// The runs' names: given (one per run) or their directories' own, each once.
fn names(runs: &[PathBuf], given: Option<&[String]>) -> Result<Vec<String>> {
    ensure!(!runs.is_empty(), "--run: no run given");
    let names: Vec<String> = match given {
        Some(n) if n.len() != runs.len() => bail!(
            "--names: {} names for {} runs (one per --run, in order)",
            n.len(),
            runs.len()
        ),
        Some(n) => n.to_vec(),
        None => runs
            .iter()
            .map(|r| {
                let abs = std::path::absolute(r).unwrap_or_else(|_| r.clone());
                abs.file_name()
                    .map_or_else(|| r.display().to_string(), |n| n.to_string_lossy().into())
            })
            .collect(),
    };
    for (i, n) in names.iter().enumerate() {
        if names[..i].contains(n) {
            bail!("two runs are named {n:?}: give each its own with --names");
        }
    }
    Ok(names)
}

/// The overall figures of `RUN/eval-<split>.json`.
fn stored_metrics(run: &Path, split: &str) -> Result<Metrics> {
    let path = run.join(format!("eval-{split}.json"));
    if !path.exists() {
        bail!(
            "{}: not found; score the run first (`mvmp eval --run {} --data DATA --split {split}`)",
            path.display(),
            run.display()
        );
    }
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let value: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: malformed", path.display()))?;
    if value["format"] != "mvmp-eval-report" {
        bail!(
            "{}: format {}, expected \"mvmp-eval-report\"",
            path.display(),
            value["format"]
        );
    }
    serde_json::from_value(value).with_context(|| format!("{}: malformed", path.display()))
}

/// `table`'s lines with the parts of each run's joint error after them.
fn with_parts(table: &str, rows: &[(String, Metrics)]) -> String {
    let mut lines = table.lines();
    let mut s = format!(
        "{}   root / root-relative / PA-MPJPE\n",
        lines.next().unwrap_or("")
    );
    for (line, (_, m)) in lines.zip(rows) {
        let parts = match (m.root_mm, m.rr_mpjpe_mm, m.pa_mpjpe_mm) {
            (Some(a), Some(b), Some(c)) => format!("{a:.1} / {b:.1} / {c:.1}"),
            _ => "-".into(),
        };
        s += &format!("{line}   {parts}\n");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(dir: &Path, mpjpe: f64, people: usize) {
        std::fs::create_dir_all(dir).unwrap();
        let report = serde_json::json!({
            "format": "mvmp-eval-report", "mpjpe_mm": mpjpe, "pve_mm": mpjpe - 20.0,
            "pa_pve_mm": 55.25, "root_mm": 50.0, "rr_mpjpe_mm": 90.0, "pa_mpjpe_mm": 66.0,
            "recall_500": 0.975, "ap": {"25": 0.0, "100": 0.5, "150": 0.75},
            "matched": people, "ground_truth": people, "predictions": people, "per_scene": {}
        });
        std::fs::write(dir.join("eval-test.json"), report.to_string()).unwrap();
        let mut log = String::new();
        for s in 1..=20 {
            log += &format!(
                "{{\"kind\":\"step\",\"stage\":2,\"global_step\":{s},\"total\":{mpjpe}}}\n"
            );
        }
        log += &format!(
            "{{\"kind\":\"val\",\"stage\":2,\"global_step\":20,\"mpjpe_mm\":{mpjpe},\"recall_500\":1.0}}\n"
        );
        std::fs::write(dir.join("metrics.jsonl"), log).unwrap();
    }

    #[test]
    fn runs_read_back_as_a_table_and_a_picture() {
        let tmp = tempfile::tempdir().unwrap();
        let (a, b) = (tmp.path().join("full"), tmp.path().join("max"));
        run(&a, 104.9, 10);
        run(&b, 111.5, 10);
        let plot = tmp.path().join("cmp.png");
        let runs = [a, b];
        let args = CompareArgs {
            runs: &runs,
            names: None,
            split: "test",
            stage: 2,
            error: None,
            plot: Some(&plot),
        };
        let s = compare(&args).unwrap();
        let lines: Vec<&str> = s.lines().collect();
        assert_eq!(lines.len(), 3, "{s}");
        assert!(
            lines[1].starts_with("full ") && lines[1].contains("104.9"),
            "{s}"
        );
        assert!(
            lines[2].starts_with("max ") && lines[2].contains("111.5"),
            "{s}"
        );
        assert!(lines[1].ends_with("50.0 / 90.0 / 66.0"), "{s}");
        assert!(
            lines[1].contains("55.2") && lines[1].contains("0.975"),
            "{s}"
        );
        let img = image::open(&plot).unwrap();
        assert!(img.width() > 100 && img.height() > 100);
    }

    #[test]
    fn bad_runs_are_named() {
        let tmp = tempfile::tempdir().unwrap();
        let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
        run(&a, 100.0, 10);
        run(&b, 100.0, 12);
        let runs = [a.clone(), b.clone()];
        let base = CompareArgs {
            runs: &runs,
            names: None,
            split: "test",
            stage: 2,
            error: None,
            plot: None,
        };
        let s = compare(&base).unwrap();
        assert!(s.contains("different sizes (people: [10, 12])"), "{s}");
        let err = |args: &CompareArgs| crate::report::message(&compare(args).unwrap_err());
        let e = err(&CompareArgs {
            split: "train",
            ..base
        });
        assert!(
            e.contains("eval-train.json: not found") && e.contains("--split train"),
            "{e}"
        );
        let one = ["x".to_string()];
        let e = err(&CompareArgs {
            names: Some(&one),
            ..base
        });
        assert!(e.contains("1 names for 2 runs"), "{e}");
        let same = [a.clone(), a.clone()];
        let e = err(&CompareArgs {
            runs: &same,
            ..base
        });
        assert!(e.contains("two runs are named \"a\""), "{e}");
        let e = err(&CompareArgs { stage: 3, ..base });
        assert!(e.contains("--stage 3"), "{e}");
        let plot = tmp.path().join("p.png");
        let e = err(&CompareArgs {
            error: Some("pve"),
            plot: Some(&plot),
            ..base
        });
        assert!(
            e.contains("no run logged validation \"stage 2 pve\"")
                && e.contains("stage 2 mpjpe_mm"),
            "{e}"
        );
        assert!(!plot.exists());
        std::fs::write(b.join("eval-test.json"), "{\"format\": \"other\"}").unwrap();
        let e = err(&base);
        assert!(e.contains("eval-test.json: format \"other\""), "{e}");
        std::fs::write(b.join("eval-test.json"), "{").unwrap();
        let e = err(&base);
        assert!(e.contains("eval-test.json: malformed"), "{e}");
    }
}
