//! `curves.png` of a run: the weighted loss terms over steps (log scale, each stage) beside the
//! validation figures over steps, drawn from `metrics.jsonl`.
use std::path::Path;

use plotters::prelude::*;
use serde_json::Value;

use crate::TrainError;
use mvmp_io::write_atomic_with;

const WIDTH: u32 = 1400;
const HEIGHT: u32 = 520;
/// Steps averaged per plotted loss point: single steps of batch 1 are too noisy to read.
const SMOOTH: usize = 10;
const COLORS: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// One named series of (global step, value) points.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// The series of a metrics log: loss terms per stage (smoothed) and validation figures.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Curves {
    pub losses: Vec<Series>,
    /// Errors in mm (validation `*_mm` keys).
    pub errors: Vec<Series>,
    /// Fractions in [0, 1] (validation recall keys).
    pub recalls: Vec<Series>,
}

const STEP_KEYS: [&str; 11] = [
    "kind",
    "stage",
    "epoch",
    "step",
    "global_step",
    "lr",
    "seconds",
    "queries",
    "root_peak",
    "root_at_gt",
    "root_background",
];

fn push(list: &mut Vec<Series>, name: String, x: f64, y: f64) {
    match list.iter_mut().find(|s| s.name == name) {
        Some(s) => s.points.push((x, y)),
        None => list.push(Series {
            name,
            points: vec![(x, y)],
        }),
    }
}

impl Curves {
    /// Collect the series of `metrics.jsonl` lines (unparseable lines are skipped: the log's own reader
    /// reports them).
    pub fn from_log(text: &str) -> Curves {
        let mut raw: Vec<Series> = Vec::new();
        let mut c = Curves::default();
        for v in text
            .lines()
            .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        {
            let Some(obj) = v.as_object() else { continue };
            let x = obj
                .get("global_step")
                .and_then(Value::as_f64)
                .unwrap_or(0.0);
            let stage = obj.get("stage").and_then(Value::as_u64).unwrap_or(0);
            let kind = obj.get("kind").and_then(Value::as_str).unwrap_or("");
            for (k, val) in obj {
                let Some(y) = val.as_f64().filter(|y| y.is_finite()) else {
                    continue;
                };
                match kind {
                    "step" if !STEP_KEYS.contains(&k.as_str()) => {
                        push(&mut raw, format!("stage {stage} {k}"), x, y)
                    }
                    "val" if k.ends_with("_mm") => {
                        push(&mut c.errors, format!("stage {stage} {k}"), x, y)
                    }
                    "val" if k.contains("recall") => {
                        push(&mut c.recalls, format!("stage {stage} {k}"), x, y)
                    }
                    _ => {}
                }
            }
        }
        c.losses = raw.into_iter().map(smooth).collect();
        c
    }
}

/// Means of consecutive chunks of `SMOOTH` points, at the chunk's last step.
fn smooth(s: Series) -> Series {
    let points = s
        .points
        .chunks(SMOOTH)
        .map(|c| {
            let y = c.iter().map(|p| p.1).sum::<f64>() / c.len() as f64;
            (c[c.len() - 1].0, y)
        })
        .collect();
    Series { points, ..s }
}

/// The steps the series span: from 0, or from their first step when they start late (a comparison of
/// stage-2 curves), so that the curves fill the panel.
fn x_range(sets: &[&[Series]]) -> std::ops::Range<f64> {
    let steps = || {
        sets.iter()
            .flat_map(|s| s.iter())
            .flat_map(|s| s.points.iter().map(|p| p.0))
    };
    let max = steps().fold(1.0f64, f64::max);
    let min = steps().fold(f64::INFINITY, f64::min);
    let lo = if min.is_finite() && min > 0.25 * max {
        min - 0.02 * (max - min)
    } else {
        0.0
    };
    lo..max + 0.02 * (max - lo)
}

type DrawErr = Box<dyn std::error::Error>;

/// The legend box of both panels.
fn draw_legend<'a, 'b: 'a, CT: plotters::coord::CoordTranslate>(
    chart: &mut ChartContext<'a, BitMapBackend<'b>, CT>,
    at: SeriesLabelPosition,
) -> Result<(), DrawErr> {
    chart
        .configure_series_labels()
        .position(at)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .draw()?;
    Ok(())
}

fn draw_losses(
    area: &DrawingArea<BitMapBackend, plotters::coord::Shift>,
    c: &Curves,
) -> Result<(), DrawErr> {
    let ys = c.losses.iter().flat_map(|s| s.points.iter().map(|p| p.1));
    let lo = ys
        .clone()
        .filter(|&y| y > 0.0)
        .fold(f64::INFINITY, f64::min);
    let hi = ys.fold(0.0f64, f64::max);
    let (lo, hi) = if lo.is_finite() && hi > lo {
        (lo * 0.8, hi * 1.25)
    } else {
        (1e-3, 1.0)
    };
    let mut chart = ChartBuilder::on(area)
        .caption("weighted loss terms (mean of 10 steps)", ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .build_cartesian_2d(x_range(&[&c.losses]), (lo..hi).log_scale())?;
    chart
        .configure_mesh()
        .x_desc("step")
        .x_label_formatter(&|x| format!("{x:.0}"))
        .draw()?;
    for (i, s) in c.losses.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        let pts = s.points.iter().copied().filter(|p| p.1 > 0.0);
        chart
            .draw_series(LineSeries::new(pts, color.stroke_width(2)))?
            .label(s.name.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    draw_legend(&mut chart, SeriesLabelPosition::UpperRight)
}

fn draw_validation(
    area: &DrawingArea<BitMapBackend, plotters::coord::Shift>,
    c: &Curves,
) -> Result<(), DrawErr> {
    let hi = c
        .errors
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.1))
        .fold(100.0f64, f64::max);
    let mut chart = ChartBuilder::on(area)
        .caption(
            "validation (lines: mm, left; dashed: recall, right)",
            ("sans-serif", 18),
        )
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(56)
        .right_y_label_area_size(48)
        .build_cartesian_2d(x_range(&[&c.errors, &c.recalls]), 0.0..hi * 1.05)?
        .set_secondary_coord(x_range(&[&c.errors, &c.recalls]), 0.0..1.05);
    chart
        .configure_mesh()
        .x_desc("step")
        .y_desc("mm")
        .x_label_formatter(&|x| format!("{x:.0}"))
        .y_label_formatter(&|y| format!("{y:.0}"))
        .draw()?;
    chart.configure_secondary_axes().y_desc("recall").draw()?;
    for (i, s) in c.errors.iter().enumerate() {
        let color = COLORS[i % COLORS.len()];
        chart
            .draw_series(LineSeries::new(s.points.clone(), color.stroke_width(2)).point_size(3))?
            .label(s.name.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    for (i, s) in c.recalls.iter().enumerate() {
        let color = COLORS[(i + c.errors.len()) % COLORS.len()];
        chart
            .draw_secondary_series(DashedLineSeries::new(
                s.points.clone(),
                6,
                4,
                color.stroke_width(2),
            ))?
            .label(s.name.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    draw_legend(&mut chart, SeriesLabelPosition::LowerLeft)
}

/// Register the embedded font once (plotters' text needs one; no system fonts are assumed).
fn ensure_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // The font is embedded and valid; a failure would only leave the labels blank.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        );
    });
}

/// Draw the curves as RGB pixels `[HEIGHT][WIDTH][3]`.
pub fn render(c: &Curves) -> Result<Vec<u8>, String> {
    ensure_font();
    let mut buf = vec![255u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, HEIGHT)).into_drawing_area();
        let (left, right) = root.split_horizontally(WIDTH / 2);
        draw_losses(&left, c).map_err(|e| e.to_string())?;
        draw_validation(&right, c).map_err(|e| e.to_string())?;
        root.present().map_err(|e| e.to_string())?;
    }
    Ok(buf)
}

impl Curves {
    /// Several runs in one picture: each run's series named `loss`, `error` and `recall` (as
    /// [`Curves::from_log`] names them, e.g. "stage 2 total"), labelled by the run's name.
    pub fn compare(runs: &[(String, Curves)], loss: &str, error: &str, recall: &str) -> Curves {
        let pick = |list: &[Series], name: &str, run: &str| {
            list.iter().find(|s| s.name == name).map(|s| Series {
                name: run.to_string(),
                points: s.points.clone(),
            })
        };
        let mut c = Curves::default();
        for (run, curves) in runs {
            c.losses.extend(pick(&curves.losses, loss, run));
            c.errors.extend(pick(&curves.errors, error, run));
            c.recalls
                .extend(pick(&curves.recalls, recall, &format!("{run} (recall)")));
        }
        c
    }
}

/// Redraw `out` (a PNG) from the metrics log at `log`, atomically.
pub fn write_curves(log: &Path, out: &Path) -> Result<(), TrainError> {
    let text = std::fs::read_to_string(log).map_err(|e| TrainError::io(log, e))?;
    write_png(&Curves::from_log(&text), out)
}

/// Draw `c` into the PNG `out`, atomically.
pub fn write_png(c: &Curves, out: &Path) -> Result<(), TrainError> {
    let pixels = render(c).map_err(|e| TrainError::file(out, e))?;
    let img = image::RgbImage::from_raw(WIDTH, HEIGHT, pixels)
        .ok_or_else(|| TrainError::file(out, "curve buffer of the wrong size"))?;
    write_atomic_with(out, |w| {
        img.write_to(w, image::ImageFormat::Png)
            .map_err(std::io::Error::other)
    })?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn series_come_from_step_and_validation_lines() {
        let mut log = String::new();
        for s in 1..=25u64 {
            log.push_str(&format!(
                "{{\"kind\":\"step\",\"stage\":1,\"global_step\":{s},\"lr\":0.001,\"detection\":{}}}\n",
                s as f64
            ));
        }
        log.push_str("{\"kind\":\"val\",\"stage\":1,\"global_step\":25,\"root_mm\":80.0,\"root_recall\":0.5}\n");
        log.push_str("{\"kind\":\"step\",\"stage\":2,\"glob"); // a torn last line
        let c = Curves::from_log(&log);
        assert_eq!(c.losses.len(), 1);
        assert_eq!(c.losses[0].name, "stage 1 detection");
        // Chunks of 10: means 5.5, 15.5 and (21..=25) 23 at steps 10, 20, 25.
        assert_eq!(
            c.losses[0].points,
            vec![(10.0, 5.5), (20.0, 15.5), (25.0, 23.0)]
        );
        assert_eq!(c.errors[0].points, vec![(25.0, 80.0)]);
        assert_eq!(c.recalls[0].name, "stage 1 root_recall");
        let px = render(&c).expect("drawn");
        assert_eq!(px.len(), (WIDTH * HEIGHT * 3) as usize);
        // Something other than the white background was drawn.
        assert!(px.iter().filter(|&&b| b < 128).count() > 1000);
    }

    #[test]
    fn a_comparison_takes_one_series_of_each_kind_per_run() {
        let log = |mm: f64| {
            format!(
                "{{\"kind\":\"step\",\"stage\":2,\"global_step\":1,\"total\":3.0,\"mesh\":2.0}}\n\
                 {{\"kind\":\"val\",\"stage\":2,\"global_step\":1,\"mpjpe_mm\":{mm},\"pve_mm\":1.0,\"recall_500\":0.5}}\n"
            )
        };
        let runs = vec![
            ("full".to_string(), Curves::from_log(&log(100.0))),
            ("max".to_string(), Curves::from_log(&log(120.0))),
        ];
        let c = Curves::compare(
            &runs,
            "stage 2 total",
            "stage 2 mpjpe_mm",
            "stage 2 recall_500",
        );
        let names = |l: &[Series]| l.iter().map(|s| s.name.clone()).collect::<Vec<_>>();
        assert_eq!(names(&c.losses), ["full", "max"]);
        assert_eq!(names(&c.errors), ["full", "max"]);
        assert_eq!(names(&c.recalls), ["full (recall)", "max (recall)"]);
        assert_eq!(c.errors[1].points, vec![(1.0, 120.0)]);
    }
}
