//! The loss curve marks the residual network the fit kept
//! (`--residual-keep late-frames`), also when it is the network after the
//! last step, one iteration past the recorded history; its title says
//! whether the residual check kept the network.

use dm_fit::plot::{loss_curve, loss_curve_title};
use dm_fit::residual_check::ResidualCheck;
use dm_view::chart::colour_columns;

const KEPT_GREEN: [u8; 3] = [20, 150, 60];

fn green_columns(image: &image::RgbImage) -> Vec<u32> {
    colour_columns(image, KEPT_GREEN)
}

#[test]
fn loss_curve_marks_the_kept_residual_network() {
    let losses: Vec<f64> = (0..10).map(|i| 1e-4 / (1.0 + i as f64)).collect();
    let late: Vec<f64> = losses.iter().map(|l| 0.9 * l).collect();
    let plain = loss_curve(&losses, &late, &[3, 5], None, None).expect("chart");
    assert!(
        green_columns(&plain).is_empty(),
        "nothing is marked without a kept network"
    );

    let inside = loss_curve(&losses, &late, &[3, 5], Some((7, late[7])), None).expect("chart");
    let past_end = loss_curve(&losses, &late, &[3, 5], Some((10, 8e-6)), None).expect("chart");
    let dot_inside = green_columns(&inside);
    let dot_past = green_columns(&past_end);
    // The legend's swatch is at the left; the rightmost green is the dot,
    // and the one past the history sits right of the one at iteration 7.
    assert!(!dot_inside.is_empty() && !dot_past.is_empty());
    assert!(dot_past.last() > dot_inside.last());
}

#[test]
fn loss_curve_title_says_whether_the_check_kept_the_network() {
    let check = |gain: f64| ResidualCheck {
        track_with: 1e-2 * (1.0 - gain),
        track_without: 1e-2,
        gain,
        min_gain: 0.17,
        kept: gain >= 0.17,
    };
    // A gain just under the threshold (a real fit's 16.7 %) must not read
    // as equal to it.
    let (dropped, kept) = (check(0.167), check(0.24));
    assert_eq!(
        loss_curve_title(Some(&dropped)),
        "Training loss · residual network dropped (train gain 16.7 % < 17.0 %)"
    );
    assert_eq!(
        loss_curve_title(Some(&kept)),
        "Training loss · residual network kept (train gain 24.0 % ≥ 17.0 %)"
    );
    // The title reaches the picture.
    let losses: Vec<f64> = (0..10).map(|i| 1e-4 / (1.0 + i as f64)).collect();
    let plain = loss_curve(&losses, &losses, &[3, 5], None, None).expect("chart");
    let with_drop = loss_curve(&losses, &losses, &[3, 5], None, Some(&dropped)).expect("chart");
    assert_ne!(plain, with_drop);
}
