//! 3DGS PLY export and import.

mod common;

use common::{random_gaussians, rng};
use dm_splat::ply::{SH_C0, read_ply, write_ply};
use dm_splat::{Gaussians, SplatError};

/// The file stores f32: a round trip of f32 Gaussians is exact except the
/// colour, which goes through `(rgb − 0.5) / C0` and back (two f32
/// roundings of an O(1) value, ≤ 2 ulp ≈ 2.4e-7).
const COLOR_ROUND_TRIP_TOL: f32 = 3e-7;

#[test]
fn round_trip_preserves_gaussians() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("splats.ply");
    let g = random_gaussians(&mut rng(4), 257, (0.05, 0.95)).cast::<f32>();
    write_ply(&path, &g).expect("write");
    let back: Gaussians<f32> = read_ply(&path).expect("read");
    assert_eq!(back.len(), g.len());
    assert_eq!(back.means, g.means);
    assert_eq!(back.log_scales, g.log_scales);
    assert_eq!(back.rotations, g.rotations);
    assert_eq!(back.opacity_logits, g.opacity_logits);
    for (a, b) in back.colors.iter().zip(&g.colors) {
        assert!((a - b).amax() <= COLOR_ROUND_TRIP_TOL, "{a} vs {b}");
    }
    // No temporary file left behind.
    assert_eq!(std::fs::read_dir(dir.path()).expect("dir").count(), 1);
}

#[test]
fn layout_is_the_3dgs_one() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("one.ply");
    let mut g = Gaussians::<f64>::default();
    g.push(
        nalgebra::Vector3::new(1.0, 2.0, 3.0),
        nalgebra::Vector3::new(-4.0, -5.0, -6.0),
        [0.5, 0.5, 0.5, 0.5],
        0.25,
        nalgebra::Vector3::new(0.5 + SH_C0, 0.5, 0.5 - SH_C0),
    );
    write_ply(&path, &g).expect("write");
    let bytes = std::fs::read(&path).expect("read");
    let text_end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("end_header")
        + 11;
    let header = std::str::from_utf8(&bytes[..text_end]).expect("ascii header");
    let expected = "ply\nformat binary_little_endian 1.0\nelement vertex 1\n\
        property float x\nproperty float y\nproperty float z\n\
        property float nx\nproperty float ny\nproperty float nz\n\
        property float f_dc_0\nproperty float f_dc_1\nproperty float f_dc_2\n\
        property float opacity\n\
        property float scale_0\nproperty float scale_1\nproperty float scale_2\n\
        property float rot_0\nproperty float rot_1\nproperty float rot_2\nproperty float rot_3\n\
        end_header\n";
    assert_eq!(header, expected);
    let values: Vec<f32> = bytes[text_end..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let want = [
        1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.25, -4.0, -5.0, -6.0, 0.5, 0.5, 0.5, 0.5,
    ];
    assert_eq!(values.len(), want.len());
    for (v, w) in values.iter().zip(want) {
        assert!((v - w).abs() < 1e-6, "{values:?}");
    }
}

#[test]
fn reads_files_with_extra_properties_and_rejects_bad_ones() {
    let dir = tempfile::tempdir().expect("tempdir");
    // A 3DGS-style file with f_rest coefficients and a different order.
    let names = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "f_rest_0", "f_rest_1", "opacity", "scale_0",
        "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\ncomment test\nelement vertex 2\n{}end_header\n",
        names
            .iter()
            .map(|n| format!("property float {n}\n"))
            .collect::<String>()
    )
    .into_bytes();
    for k in 0..2 {
        for (j, _) in names.iter().enumerate() {
            let v = if j >= 12 {
                if j == 12 { 1.0f32 } else { 0.0 }
            } else {
                (k * 20 + j) as f32 * 0.01
            };
            bytes.extend(v.to_le_bytes());
        }
    }
    let path = dir.path().join("extra.ply");
    std::fs::write(&path, &bytes).expect("write");
    let g: Gaussians<f64> = read_ply(&path).expect("read");
    assert_eq!(g.len(), 2);
    assert!((g.opacity_logits[1] - 0.28).abs() < 1e-6);
    assert!((g.log_scales[0].z - 0.11).abs() < 1e-6);

    // Truncated data.
    let short = dir.path().join("short.ply");
    std::fs::write(&short, &bytes[..bytes.len() - 3]).expect("write");
    assert!(matches!(
        read_ply::<f32>(&short),
        Err(SplatError::Ply { .. })
    ));
    // Missing property.
    let header_end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("end_header")
        + 11;
    let header = String::from_utf8_lossy(&bytes[..header_end]).replace("opacity", "opacitx");
    let missing = dir.path().join("missing.ply");
    let mut b2 = header.into_bytes();
    b2.extend(&bytes[header_end..]);
    std::fs::write(&missing, &b2).expect("write");
    let err = read_ply::<f32>(&missing).expect_err("missing property");
    assert!(
        err.to_string().contains("missing vertex property opacity"),
        "{err}"
    );
    // A header claiming far more vertices than the file holds.
    let huge = dir.path().join("huge.ply");
    let text =
        String::from_utf8_lossy(&bytes[..header_end]).replace("vertex 2", "vertex 1000000000000");
    let mut b3 = text.into_bytes();
    b3.extend(&bytes[header_end..]);
    std::fs::write(&huge, &b3).expect("write");
    let err = read_ply::<f32>(&huge).expect_err("huge count");
    assert!(err.to_string().contains("shorter"), "{err}");
    // ASCII format.
    let ascii = dir.path().join("ascii.ply");
    std::fs::write(
        &ascii,
        "ply\nformat ascii 1.0\nelement vertex 0\nend_header\n",
    )
    .expect("write");
    assert!(matches!(
        read_ply::<f32>(&ascii),
        Err(SplatError::Ply { .. })
    ));
    // Not there.
    assert!(matches!(
        read_ply::<f32>(&dir.path().join("absent.ply")),
        Err(SplatError::Io { .. })
    ));
}
