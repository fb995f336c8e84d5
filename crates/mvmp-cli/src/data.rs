//! `mvmp data ...`: synthesis, statistics and validation of datasets.
use std::path::Path;

use anyhow::{Context, Result};
use mvmp_data::sources::SourceFormat;

use mvmp_data::synth::{SynthConfig, generate};

pub fn synth(config: &Path, out: &Path) -> Result<()> {
    let cfg = SynthConfig::read(config)?;
    let config_dir = config.parent().unwrap_or(Path::new("."));
    let pb = crate::progress::bar((cfg.scenes * cfg.frames_per_scene) as u64, "synth", false);
    let t0 = std::time::Instant::now();
    let summary = generate(&cfg, out, config_dir, &|| pb.inc(1))
        .with_context(|| format!("synthesising {} into {}", config.display(), out.display()))?;
    pb.finish_and_clear();
    println!(
        "wrote {}: {} scenes, {} frames, {} views, {} people in last frames, {:.1} s",
        out.display(),
        summary.scenes,
        summary.frames,
        summary.views,
        summary.people,
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

pub fn stats(dir: &Path, json: bool, sheet: Option<&Path>) -> Result<()> {
    if let Some(path) = sheet {
        crate::paths::not_over_input("--sheet", path, dir)?;
    }
    let s = mvmp_data::stats::dataset_stats(dir)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        println!("dataset {}", dir.display());
        println!("  scenes               {}", s.scenes);
        println!("  frames               {}", s.frames);
        println!(
            "  views per scene      {} (min {}, mean {:.1})",
            s.views, s.views_per_scene.min, s.views_per_scene.mean
        );
        println!(
            "  area                 up to {:.0} m x {:.0} m (mean {:.0} m^2)",
            s.area_max[0], s.area_max[1], s.area_m2.mean
        );
        println!(
            "  people per frame     {}-{} (mean {:.1})",
            s.people_per_frame.min, s.people_per_frame.max, s.people_per_frame.mean
        );
        println!("  occlusion (mean)     {:.3}", s.occlusion_mean);
        println!("  visible views (mean) {:.2}", s.visible_views_mean);
        let total: usize = s.occlusion_histogram.iter().sum::<usize>().max(1);
        println!(
            "  occlusion histogram (person-views, fraction of the silhouette hidden by others):"
        );
        for (i, n) in s.occlusion_histogram.iter().enumerate() {
            let bar = "#".repeat((40 * n).div_ceil(total));
            println!(
                "    {:.1}-{:.1} {:>7} {bar}",
                i as f64 / 10.0,
                (i + 1) as f64 / 10.0,
                n
            );
        }
    }
    if let Some(path) = sheet {
        mvmp_data::stats::contact_sheet(dir, 0, 0, 400, path)?;
        if !json {
            println!("contact sheet of scene 0, frame 0: {}", path.display());
        }
    }
    Ok(())
}

pub fn check(format: SourceFormat, dir: &Path, deep: bool) -> Result<()> {
    match format {
        SourceFormat::Mvmp => {}
        SourceFormat::Panoptic => return check_panoptic(dir, deep),
        SourceFormat::H36m => return check_h36m(dir, deep),
    }
    let r = mvmp_data::check::check_dataset(dir, deep);
    println!(
        "checked {}: {} scenes, {} frames, up to {} views, {} person annotations, {} image files",
        dir.display(),
        r.scenes,
        r.frames,
        r.views,
        r.people,
        r.images
    );
    if deep {
        println!("every image decoded whole; every annotation validated");
    } else {
        println!(
            "image headers only (size, colour type): pass --deep to decode every image; every annotation validated"
        );
    }
    report_problems(&r.problems, dir)
}

/// What a check of a public dataset's tree read of its images.
fn images_note(deep: bool) -> &'static str {
    if deep {
        "every image decoded whole; every pose file parsed"
    } else {
        "image headers only (present, an image, the camera's size): pass --deep to decode every image; every pose file parsed"
    }
}

fn check_panoptic(dir: &Path, deep: bool) -> Result<()> {
    let cams = mvmp_data::panoptic::VOXELPOSE_CAMERAS;
    let r = mvmp_data::panoptic::check_tree_with(dir, &cams, deep);
    println!(
        "checked {} as CMU Panoptic (cameras {}):",
        dir.display(),
        cams.join(", ")
    );
    for (name, c, f, p) in &r.sequences {
        println!("  {name}: {c} cameras, {f} frames, {p} people with an annotated root");
    }
    println!("{}", images_note(deep));
    report_problems(&r.problems, dir)
}

fn check_h36m(dir: &Path, deep: bool) -> Result<()> {
    let cams = mvmp_data::h36m::CAMERAS;
    let r = mvmp_data::h36m::check_tree_with(dir, &cams, deep);
    println!(
        "checked {} as Human3.6M (cameras {}):",
        dir.display(),
        cams.join(", ")
    );
    let mut subject = "";
    for (s, action, c, f, complete) in &r.sequences {
        if s != subject {
            let n = r.sequences.iter().filter(|q| &q.0 == s).count();
            let frames: usize = r.sequences.iter().filter(|q| &q.0 == s).map(|q| q.3).sum();
            println!("  {s}: {n} actions, {frames} frames with poses (one person each)");
            subject = s;
        }
        println!("    {action}: {c} cameras, {f} frames, {complete} with every camera's image");
    }
    println!("{}", images_note(deep));
    report_problems(&r.problems, dir)
}

/// Print every problem with its file; an error (non-zero exit) when there are any.
fn report_problems(problems: &[mvmp_data::check::Problem], dir: &Path) -> Result<()> {
    if problems.is_empty() {
        println!("no problems found");
        return Ok(());
    }
    for p in problems {
        println!("{}: {}", p.path.display(), p.what);
    }
    anyhow::bail!("{} problem(s) found in {}", problems.len(), dir.display())
}
