//! The pixel line chart: lines where values are finite, gaps where not,
//! and no panic on empty, flat or non-positive (log scale) input.

use dm_view::chart::{ChartOptions, ChartSeries, ValueScale, line_chart};

const RED: [u8; 3] = [200, 40, 40];

fn coloured_columns(values: &[f64], scale: ValueScale) -> Vec<u32> {
    let chart = line_chart(
        &[ChartSeries { values, color: RED }],
        &ChartOptions {
            scale,
            ..ChartOptions::default()
        },
    );
    let mut columns: Vec<u32> = chart
        .enumerate_pixels()
        .filter(|(_, _, p)| p.0 == RED)
        .map(|(x, _, _)| x)
        .collect();
    columns.sort_unstable();
    columns.dedup();
    columns
}

#[test]
fn draws_finite_segments_and_leaves_gaps() {
    let full = coloured_columns(&[1.0, 2.0, 3.0, 2.0, 1.0], ValueScale::Linear);
    assert!(
        full.len() > 500,
        "a line across the plot: {} columns",
        full.len()
    );
    let gap = coloured_columns(&[1.0, 2.0, f64::NAN, 2.0, 1.0], ValueScale::Linear);
    assert!(
        gap.len() < full.len() * 3 / 5,
        "NaN leaves a gap: {} columns",
        gap.len()
    );
    let log_gap = coloured_columns(&[1.0, 10.0, -1.0, 10.0, 1.0], ValueScale::Log);
    assert!(log_gap.len() < full.len() * 3 / 5);
}

#[test]
fn degenerate_inputs_draw_axes_only_or_a_flat_line() {
    assert!(coloured_columns(&[], ValueScale::Linear).is_empty());
    assert!(coloured_columns(&[f64::NAN; 4], ValueScale::Linear).is_empty());
    assert!(coloured_columns(&[0.5], ValueScale::Linear).is_empty());
    assert!(!coloured_columns(&[0.5, 0.5, 0.5], ValueScale::Linear).is_empty());
}
