//! The line chart: lines where values are finite, gaps where not, no
//! panic on empty, flat or non-positive (log scale) input, and the bundled
//! font draws its text.

use dm_view::chart::{ChartOptions, ChartSeries, ValueScale, colour_columns, line_chart};

const RED: [u8; 3] = [200, 40, 40];

fn coloured_columns(values: &[f64], scale: ValueScale) -> Vec<u32> {
    let chart = line_chart(
        &[ChartSeries {
            values,
            color: RED,
            label: "",
        }],
        &ChartOptions {
            scale,
            ..ChartOptions::default()
        },
    )
    .expect("chart");
    colour_columns(&chart, RED)
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

/// Dark pixels inside `rows` (text and axes are drawn in black/grey).
fn dark_pixels(chart: &image::RgbImage, rows: std::ops::Range<u32>) -> usize {
    chart
        .enumerate_pixels()
        .filter(|(_, y, p)| rows.contains(y) && p.0.iter().all(|&c| c < 100))
        .count()
}

#[test]
fn title_and_legend_are_drawn_with_the_bundled_font() {
    let values = [1.0, 2.0, 3.0];
    let series = [ChartSeries {
        values: &values,
        color: RED,
        label: "fitted model",
    }];
    let plain = line_chart(&series, &ChartOptions::default()).expect("chart");
    let titled = line_chart(
        &series,
        &ChartOptions {
            title: "Track error per frame".into(),
            x_label: "frame".into(),
            y_label: "track error (mm)".into(),
            ..ChartOptions::default()
        },
    )
    .expect("chart");
    // The title lives in the top 30 rows; without one they stay blank
    // but for the legend's text further down.
    assert!(
        dark_pixels(&titled, 0..30) > 100 + dark_pixels(&plain, 0..30),
        "title text drawn: {} vs {} dark pixels",
        dark_pixels(&titled, 0..30),
        dark_pixels(&plain, 0..30)
    );
    let unlabelled = line_chart(
        &[ChartSeries {
            values: &values,
            color: RED,
            label: "",
        }],
        &ChartOptions::default(),
    )
    .expect("chart");
    assert!(
        dark_pixels(&plain, 0..360) > dark_pixels(&unlabelled, 0..360) + 50,
        "the legend's text is drawn"
    );
}

#[test]
fn tick_labels_are_short_and_distinct() {
    use dm_view::chart::format_tick;
    assert_eq!(format_tick(-0.0), "0");
    assert_eq!(format_tick(-1e-12 * 0.0), "0");
    assert_eq!(format_tick(0.25), "0.25");
    assert_eq!(format_tick(20.0), "20");
    assert_eq!(format_tick(-0.1), "-0.1");
    // Neighbouring ticks of a log axis within one decade stay distinct.
    assert_ne!(format_tick(4.57e-4), format_tick(4.62e-4));
    assert_eq!(format_tick(4.62e-4), "4.62e-4");
}
