use dm_view::{Frame, add_sensor_noise, side_by_side};
use image::{Rgb, RgbImage};

#[test]
fn side_by_side_concatenates_with_gap() {
    let a = RgbImage::from_pixel(3, 2, Rgb([255, 0, 0]));
    let b = RgbImage::from_pixel(5, 4, Rgb([0, 255, 0]));
    let strip = side_by_side(&[a, b], &["a", "b"]);
    assert_eq!(strip.dimensions(), (3 + 4 + 5, 4));
    assert_eq!(strip.get_pixel(0, 0), &Rgb([255, 0, 0]));
    assert_eq!(strip.get_pixel(4, 0), &Rgb([0, 0, 0]));
    assert_eq!(strip.get_pixel(0, 3), &Rgb([0, 0, 0]));
    assert_eq!(strip.get_pixel(7, 3), &Rgb([0, 255, 0]));
    assert_eq!(side_by_side(&[], &[]).dimensions(), (0, 0));
}

#[test]
fn sensor_noise_is_deterministic_and_bounded() {
    let mut a = Frame::with_background(17, 9, [0.5; 3]);
    let mut b = a.clone();
    add_sensor_noise(&mut a, 0.05, 42);
    add_sensor_noise(&mut b, 0.05, 42);
    assert_eq!(a, b);
    assert!(
        a.rgb
            .iter()
            .flatten()
            .all(|&c| (c - 0.5).abs() <= 0.05 + 1e-6)
    );
    assert!(a.rgb.iter().flatten().any(|&c| c != 0.5));
    let mut c = Frame::with_background(17, 9, [0.5; 3]);
    add_sensor_noise(&mut c, 0.05, 43);
    assert_ne!(a.rgb, c.rgb);
}

#[test]
fn depth_u16_conversion() {
    let mut frame = Frame::empty(3, 1);
    frame.depth = vec![1.2345, f32::INFINITY, 100.0];
    let depth = frame.depth_to_u16_mm();
    assert_eq!(depth.as_raw(), &vec![1235, 0, u16::MAX]);
}
