//! A loss curve as a PNG: log-scale loss per iteration, with the stage
//! boundary marked (dm-view's pixel line chart: no font needed).

use dm_view::chart::{ChartOptions, ChartSeries, ValueScale, line_chart};
use image::RgbImage;

/// Plots `losses` (one per iteration); a grey line marks where stage 2
/// starts (after `stage1_iterations`).
pub fn loss_curve(losses: &[f64], stage1_iterations: usize) -> RgbImage {
    line_chart(
        &[ChartSeries {
            values: losses,
            color: [200, 40, 40],
        }],
        &ChartOptions {
            scale: ValueScale::Log,
            markers: vec![stage1_iterations],
            ..ChartOptions::default()
        },
    )
}
