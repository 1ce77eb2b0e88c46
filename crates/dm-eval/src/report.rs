//! The outputs of an evaluation: `metrics.json` (the contract of
//! docs/metrics.md), `metrics.md` (a Markdown table) and one per-frame plot
//! per metric under `plots/`. Every file is written atomically; the JSON is
//! written last, so its presence means the report is complete.

use crate::{EvalError, FrameMetrics, Metrics, SplitMetrics};
use dm_bundle::{BundleError, write_file_atomic, write_json_atomic};
use dm_view::chart::{ChartOptions, ChartSeries, line_chart};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub const METRICS_JSON: &str = "metrics.json";
pub const METRICS_MARKDOWN: &str = "metrics.md";
pub const PLOTS_DIR: &str = "plots";

/// How the numbers were made, saved beside them.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RunInfo {
    pub bundle: String,
    pub model: String,
    pub camera: usize,
    pub camera_name: String,
    pub frames: usize,
    pub split: dm_bundle::Split,
    /// The LPIPS network file, or why LPIPS was skipped.
    pub lpips: String,
    /// What drew the predicted images: `gaussian_splats` (the model's
    /// fitted splats, MODEL_DIR/gaussians.ply) or `particle_spheres`.
    pub renderer: String,
    /// Where the rollout ran: `cpu` or `cuda`.
    pub device: dm_model::device::Device,
    pub rollout_and_metrics_seconds: f64,
    pub lpips_ms_per_frame: Option<f64>,
}

#[derive(Serialize)]
struct MetricsFile<'a> {
    #[serde(flatten)]
    metrics: &'a Metrics,
    run: &'a RunInfo,
}

/// One metric's column: JSON key, heading, digits shown, better direction.
#[derive(Debug)]
pub struct Column {
    pub key: &'static str,
    pub heading: &'static str,
    pub digits: usize,
    per_frame: fn(&FrameMetrics) -> Option<f64>,
    pub split: fn(&SplitMetrics) -> Option<f64>,
}

/// The metrics' columns, in the order of every table (metrics.md and the
/// benchmark suite's tables).
pub const COLUMNS: [Column; 6] = [
    Column {
        key: "iou",
        heading: "IoU ↑",
        digits: 3,
        per_frame: |f| Some(f.iou),
        split: |s| Some(s.iou),
    },
    Column {
        key: "chamfer",
        heading: "Chamfer (m) ↓",
        digits: 4,
        per_frame: |f| Some(f.chamfer),
        split: |s| Some(s.chamfer),
    },
    Column {
        key: "track",
        heading: "Track (m) ↓",
        digits: 4,
        per_frame: |f| Some(f.track),
        split: |s| Some(s.track),
    },
    Column {
        key: "psnr",
        heading: "PSNR (dB) ↑",
        digits: 2,
        per_frame: |f| Some(f.psnr),
        split: |s| Some(s.psnr),
    },
    Column {
        key: "ssim",
        heading: "SSIM ↑",
        digits: 3,
        per_frame: |f| Some(f.ssim),
        split: |s| Some(s.ssim),
    },
    Column {
        key: "lpips",
        heading: "LPIPS ↓",
        digits: 3,
        per_frame: |f| f.lpips,
        split: |s| s.lpips,
    },
];

/// A table cell: the value with `digits` decimals, `∞` for +∞, `–` for
/// NaN, −∞ or no value.
pub fn cell(value: Option<f64>, digits: usize) -> String {
    match value {
        Some(v) if v.is_finite() => format!("{v:.digits$}"),
        Some(v) if v == f64::INFINITY => "∞".into(),
        _ => "–".into(),
    }
}

/// The Markdown report: the split table and the per-frame plots with their
/// vertical ranges (the plots carry no text).
pub fn markdown(metrics: &Metrics, run: &RunInfo) -> String {
    let mut md = String::new();
    let split = &run.split;
    let _ = writeln!(md, "# dm-eval: {}\n", run.bundle);
    let _ = writeln!(
        md,
        "Model `{}`; camera `{}` (index {}); {} frames, train [{}, {}), test [{}, {}); rollout on {}; renderer: {}; LPIPS: {}.\n",
        run.model,
        run.camera_name,
        run.camera,
        run.frames,
        split.train[0],
        split.train[1],
        split.test[0],
        split.test[1],
        run.device,
        run.renderer,
        run.lpips
    );
    let _ = write!(md, "| split |");
    for c in &COLUMNS {
        let _ = write!(md, " {} |", c.heading);
    }
    let _ = write!(md, "\n|---|");
    for _ in &COLUMNS {
        let _ = write!(md, "---:|");
    }
    md.push('\n');
    for (name, values) in [("train", &metrics.train), ("test", &metrics.test)] {
        let _ = write!(md, "| {name} |");
        for c in &COLUMNS {
            let _ = write!(md, " {} |", cell((c.split)(values), c.digits));
        }
        md.push('\n');
    }
    let _ = writeln!(
        md,
        "\nPer frame (x: frame 0 to {}; dashed line: first test frame; y: from min to max, labelled on each plot):\n",
        run.frames.saturating_sub(1)
    );
    let _ = writeln!(md, "| metric | plot | min | max |\n|---|---|---:|---:|");
    for c in &COLUMNS {
        let (lo, hi) = finite_range(metrics, c);
        let _ = writeln!(
            md,
            "| {} | ![{}]({PLOTS_DIR}/{}.png) | {} | {} |",
            c.heading,
            c.key,
            c.key,
            cell(lo, c.digits),
            cell(hi, c.digits)
        );
    }
    md
}

fn finite_range(metrics: &Metrics, column: &Column) -> (Option<f64>, Option<f64>) {
    let finite = metrics
        .frames
        .iter()
        .filter_map(column.per_frame)
        .filter(|v| v.is_finite());
    let (lo, hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    (lo.is_finite().then_some(lo), hi.is_finite().then_some(hi))
}

/// Paths of the files a report consists of.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReportPaths {
    pub json: PathBuf,
    pub markdown: PathBuf,
    pub plots: Vec<PathBuf>,
}

/// Writes the report into `out_dir` (created if needed).
pub fn write_report(
    out_dir: &Path,
    metrics: &Metrics,
    run: &RunInfo,
) -> Result<ReportPaths, EvalError> {
    let plots_dir = out_dir.join(PLOTS_DIR);
    std::fs::create_dir_all(&plots_dir)
        .map_err(|e| BundleError::io(&plots_dir, "creating the output directory", &e))?;
    let test_start = run.split.test[0];
    let mut plots = Vec::new();
    for c in &COLUMNS {
        let values: Vec<f64> = metrics
            .frames
            .iter()
            .map(|f| (c.per_frame)(f).unwrap_or(f64::NAN))
            .collect();
        let chart = line_chart(
            &[ChartSeries {
                values: &values,
                color: [40, 90, 200],
                label: "",
            }],
            &ChartOptions {
                markers: vec![test_start],
                title: format!("{} per frame (dashed: the test split starts)", c.heading),
                x_label: "frame".into(),
                y_label: c.heading.into(),
                ..ChartOptions::default()
            },
        )?;
        let path = plots_dir.join(format!("{}.png", c.key));
        write_file_atomic(&path, |temp| {
            chart
                .save_with_format(temp, image::ImageFormat::Png)
                .map_err(std::io::Error::other)
        })?;
        plots.push(path);
    }
    let markdown_path = out_dir.join(METRICS_MARKDOWN);
    let text = markdown(metrics, run);
    write_file_atomic(&markdown_path, |temp| std::fs::write(temp, text.as_bytes()))?;
    let json_path = out_dir.join(METRICS_JSON);
    write_json_atomic(&json_path, &MetricsFile { metrics, run })?;
    Ok(ReportPaths {
        json: json_path,
        markdown: markdown_path,
        plots,
    })
}
