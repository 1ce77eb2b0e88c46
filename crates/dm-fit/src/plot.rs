//! A loss curve as a PNG: log-scale loss per iteration, with the stage
//! boundary marked (dm-view's labelled line chart).

use crate::residual_check::ResidualCheck;
use dm_view::ViewError;
use dm_view::chart::{ChartOptions, ChartSeries, ValueScale, line_chart};
use image::RgbImage;

/// Plots `losses` (one per iteration) and `late_losses` (the same steps'
/// L_dyn over the last 30 % of the training frames; NaN where absent);
/// dashed lines mark where each later stage starts (`stage_starts`,
/// iteration indices), and a dot marks `kept`, the iteration whose
/// residual network the fit kept (`--residual-keep late-frames`; it may be
/// one past the last iteration: the network after the last step). The
/// residual stage and stage 3 change the objective (the network's
/// regulariser, then L_rgb), so a step up at their start is not a
/// divergence. The title says the residual check's decision
/// ([`loss_curve_title`]).
pub fn loss_curve(
    losses: &[f64],
    late_losses: &[f64],
    stage_starts: &[usize],
    kept: Option<(usize, f64)>,
    check: Option<&ResidualCheck>,
) -> Result<RgbImage, ViewError> {
    let kept_marker: Vec<f64> = match kept {
        Some((at, value)) => (0..=at)
            .map(|i| if i == at { value } else { f64::NAN })
            .collect(),
        None => Vec::new(),
    };
    let mut series = vec![
        ChartSeries {
            values: losses,
            color: [200, 40, 40],
            label: "all training frames",
        },
        ChartSeries {
            values: late_losses,
            color: [40, 90, 200],
            label: "last 30 % of them",
        },
    ];
    if kept.is_some() {
        series.push(ChartSeries {
            values: &kept_marker,
            color: [20, 150, 60],
            label: "kept residual network",
        });
    }
    line_chart(
        &series,
        &ChartOptions {
            scale: ValueScale::Log,
            markers: stage_starts.to_vec(),
            title: loss_curve_title(check),
            x_label: "iteration".into(),
            y_label: "loss (m²)".into(),
            ..ChartOptions::default()
        },
    )
}

/// The loss curve's title. After a residual check it says whether the
/// network was kept: a dropped network leaves a curve that looks like
/// `--residual none`'s (the fit goes on as that fit), and the reader
/// should not have to open `fit_report.json` to learn why. One decimal,
/// as dm-fit prints it: a gain of 16.7 % against 17 % must not read
/// "17 % < 17 %".
pub fn loss_curve_title(check: Option<&ResidualCheck>) -> String {
    match check {
        None => "Training loss (dashed: next stage; stage 3 adds L_rgb)".into(),
        Some(check) => format!(
            "Training loss · residual network {} (train gain {:.1} % {} {:.1} %)",
            if check.kept { "kept" } else { "dropped" },
            100.0 * check.gain,
            if check.kept { "≥" } else { "<" },
            100.0 * check.min_gain
        ),
    }
}
