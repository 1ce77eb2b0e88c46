//! A loss curve as a PNG: log-scale loss per iteration, with the stage
//! boundary marked (dm-view's labelled line chart).

use dm_view::ViewError;
use dm_view::chart::{ChartOptions, ChartSeries, ValueScale, line_chart};
use image::RgbImage;

/// Plots `losses` (one per iteration); dashed lines mark where each later
/// stage starts (`stage_starts`, iteration indices). The residual stage
/// and stage 3 change the objective (network regulariser, + L_rgb), so a
/// step up at their start is not a divergence.
pub fn loss_curve(losses: &[f64], stage_starts: &[usize]) -> Result<RgbImage, ViewError> {
    line_chart(
        &[ChartSeries {
            values: losses,
            color: [200, 40, 40],
            label: "",
        }],
        &ChartOptions {
            scale: ValueScale::Log,
            markers: stage_starts.to_vec(),
            title: "Training loss (dashed: next stage; stage 3 adds L_rgb)".into(),
            x_label: "iteration".into(),
            y_label: "loss (m²)".into(),
            ..ChartOptions::default()
        },
    )
}
