//! A loss curve as a PNG: log-scale loss per iteration, with the stage
//! boundary marked (dm-view's labelled line chart).

use dm_view::ViewError;
use dm_view::chart::{ChartOptions, ChartSeries, ValueScale, line_chart};
use image::RgbImage;

/// Plots `losses` (one per iteration); a grey line marks where stage 2
/// starts (after `stage1_iterations`).
pub fn loss_curve(losses: &[f64], stage1_iterations: usize) -> Result<RgbImage, ViewError> {
    line_chart(
        &[ChartSeries {
            values: losses,
            color: [200, 40, 40],
            label: "",
        }],
        &ChartOptions {
            scale: ValueScale::Log,
            markers: vec![stage1_iterations],
            title: "Training loss L_dyn (dashed: stage 2 starts)".into(),
            x_label: "iteration".into(),
            y_label: "loss (m²)".into(),
            ..ChartOptions::default()
        },
    )
}
