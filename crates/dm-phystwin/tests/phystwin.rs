//! Importing the committed tiny PhysTwin case (`fixtures/phystwin_tiny`, made by
//! `scripts/make_phystwin_fixture.py`): every value is checked against the
//! script's formulas, and malformed cases fail naming the file and key while
//! leaving no output behind and the input untouched.

use std::fs;
use std::path::{Path, PathBuf};

use dm_bundle::{Bundle, BundleError, Category, MaskKind, UpAxis};
use dm_phystwin::{ImportOptions, MaskSource, import_phystwin};

const FRAMES: usize = 5;
const CAMERAS: usize = 3;
const WIDTH: usize = 32;
const HEIGHT: usize = 24;
const OBJECT_POINTS: usize = 24;
const CONTROLLER_POINTS: usize = 30;
const SURFACE_POINTS: usize = 10;
const INTERIOR_POINTS: usize = 4;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures")
}

fn copy_tree(from: &Path, to: &Path) {
    fs::create_dir_all(to).expect("create dir");
    for entry in fs::read_dir(from).expect("read dir") {
        let entry = entry.expect("entry");
        let target = to.join(entry.file_name());
        if entry.path().is_dir() {
            copy_tree(&entry.path(), &target);
        } else {
            fs::copy(entry.path(), &target).expect("copy");
        }
    }
}

/// Every file under `root` with its bytes, sorted.
fn tree(root: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut files = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in fs::read_dir(&dir).expect("read dir") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let bytes = fs::read(&path).expect("read");
                files.push((path, bytes));
            }
        }
    }
    files.sort();
    files
}

/// A writable copy of the tiny case in a fresh temporary directory.
fn case_copy() -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().expect("temp dir");
    let case = dir.path().join("case");
    copy_tree(&fixtures().join("phystwin_tiny"), &case);
    (dir, case)
}

// The fixture script's formulas.
fn object_point(t: usize, n: usize) -> [f32; 3] {
    let (t, nf) = (t as f64, n as f64);
    [
        (-0.05 + 0.02 * (n % 6) as f64 + 0.0 * t) as f32,
        (-0.03 + 0.02 * (n / 6) as f64 + 0.0 * t) as f32,
        (-0.02 - 0.01 * t - 0.001 * nf) as f32,
    ]
}
fn object_color(t: usize, n: usize) -> [f32; 3] {
    [
        (n as f64 / OBJECT_POINTS as f64 + 0.0 * t as f64) as f32,
        (t as f64 / FRAMES as f64 + 0.0 * n as f64) as f32,
        0.5,
    ]
}
fn controller_point(t: usize, m: usize) -> [f32; 3] {
    let (t, m) = (t as f64, m as f64);
    [
        (0.1 + 0.001 * m + 0.0 * t) as f32,
        (0.002 * m + 0.0 * t) as f32,
        (-0.05 - 0.01 * t + 0.0 * m) as f32,
    ]
}

#[test]
fn tiny_case_imports_with_exact_values() {
    let out_dir = tempfile::tempdir().expect("temp dir");
    let out = out_dir.path().join("bundle");
    let case = fixtures().join("phystwin_tiny");
    let before = tree(&case);
    let summary = import_phystwin(&case, &out, &ImportOptions::default()).expect("import");
    assert_eq!(tree(&case), before, "the case must not be modified");
    assert_eq!(summary.mask_source, MaskSource::Segmentation);
    assert!(summary.category_inferred);

    let bundle = Bundle::open(&out).expect("valid bundle");
    bundle.validate_images().expect("valid images");
    let meta = &bundle.meta;
    assert_eq!(meta.frame_count, FRAMES);
    assert_eq!(meta.fps, 30.0);
    assert_eq!((meta.split.train, meta.split.test), ([0, 3], [3, 5]));
    assert_eq!((meta.up_axis, meta.floor_height_m), (UpAxis::NegZ, 0.0));
    // The fixture has interior points, which PhysTwin fills only for volumetric objects.
    assert_eq!(meta.category, Category::Volumetric);
    assert_eq!(meta.hands.len(), 1);
    assert_eq!(meta.hands[0].anchor_range, [0, CONTROLLER_POINTS]);

    let tracks = &bundle.tracks;
    for t in 0..FRAMES {
        for n in 0..OBJECT_POINTS {
            let p = object_point(t, n);
            for k in 0..3 {
                assert_eq!(
                    tracks.object_points[[t, n, k]],
                    p[k],
                    "object_points[{t},{n},{k}]"
                );
            }
            assert_eq!(tracks.object_visibility[[t, n]], (n + t) % 5 != 0);
            assert_eq!(tracks.object_motion_valid[[t, n]], (n * t) % 4 != 1);
        }
        for m in 0..CONTROLLER_POINTS {
            let p = controller_point(t, m);
            for k in 0..3 {
                assert_eq!(
                    tracks.hand_points[[t, m, k]],
                    p[k],
                    "hand_points[{t},{m},{k}]"
                );
            }
            assert!(tracks.hand_visibility[[t, m]]);
        }
    }

    let particles = &bundle.particles;
    assert_eq!(
        particles.surface_points.nrows(),
        OBJECT_POINTS + SURFACE_POINTS
    );
    for n in 0..OBJECT_POINTS {
        for k in 0..3 {
            assert_eq!(particles.surface_points[[n, k]], object_point(0, n)[k]);
            assert_eq!(particles.surface_colors[[n, k]], object_color(0, n)[k]);
        }
    }
    for s in 0..SURFACE_POINTS {
        let expected = [(-0.05 + 0.01 * s as f64) as f32, 0.05, -0.02];
        let row = OBJECT_POINTS + s;
        for k in 0..3 {
            assert_eq!(particles.surface_points[[row, k]], expected[k]);
        }
        // Prior points take the colour of the nearest tracked point at frame 0.
        let nearest = (0..OBJECT_POINTS)
            .min_by(|&a, &b| {
                let d = |n: usize| {
                    (0..3)
                        .map(|k| (object_point(0, n)[k] - expected[k]).powi(2))
                        .sum::<f32>()
                };
                d(a).total_cmp(&d(b))
            })
            .expect("points");
        for k in 0..3 {
            assert_eq!(
                particles.surface_colors[[row, k]],
                object_color(0, nearest)[k]
            );
        }
    }
    assert_eq!(particles.interior_points.nrows(), INTERIOR_POINTS);
    for i in 0..INTERIOR_POINTS {
        assert_eq!(particles.interior_points[[i, 0]], (0.01 * i as f64) as f32);
        assert_eq!(particles.interior_points[[i, 2]], -0.01);
    }

    for (c, camera) in meta.cameras.iter().enumerate() {
        assert_eq!(camera.name, format!("cam{c}"));
        assert_eq!((camera.width, camera.height), (WIDTH as u32, HEIGHT as u32));
        assert_eq!((camera.fx, camera.fy), (20.0 + c as f64, 21.0 + c as f64));
        assert_eq!((camera.cx, camera.cy), (16.0, 12.0));
        // world_to_camera is the inverse of the fixture's camera-to-world: the
        // camera centre maps to the origin and the look-at target to the image centre.
        let angle = 2.0 * std::f64::consts::PI * c as f64 / CAMERAS as f64;
        let centre = [0.3 * angle.cos(), 0.3 * angle.sin(), -0.6];
        let at_centre = camera.world_to_camera_point(centre);
        assert!(at_centre.iter().all(|v| v.abs() < 1e-12), "{at_centre:?}");
        let [u, v] = camera.project([0.0, 0.0, -0.03]).expect("in front");
        assert!(
            (u - 16.0).abs() < 1e-9 && (v - 12.0).abs() < 1e-9,
            "{u} {v}"
        );
    }

    for c in 0..CAMERAS {
        for t in 0..FRAMES {
            let rgb = bundle.load_rgb(c, t).expect("rgb");
            let depth = bundle.load_depth_mm(c, t).expect("depth");
            let object = bundle.load_mask(c, t, MaskKind::Object).expect("mask");
            let hand = bundle.load_mask(c, t, MaskKind::Hand).expect("mask");
            for y in 0..HEIGHT {
                for x in 0..WIDTH {
                    let pixel = rgb.get_pixel(x as u32, y as u32).0;
                    let expected = [
                        ((x * 7 + t * 11) % 256) as u8,
                        ((y * 9 + c * 40) % 256) as u8,
                        ((x + y + 3 * t + c) % 256) as u8,
                    ];
                    assert_eq!(pixel, expected, "rgb cam{c} frame {t} ({x},{y})");
                    let mm = if (x, y) == (0, 0) {
                        0
                    } else {
                        (500 + 10 * t + 100 * c + 3 * x + 5 * y) as u16
                    };
                    assert_eq!(
                        depth.get_pixel(x as u32, y as u32).0[0],
                        mm,
                        "depth ({x},{y})"
                    );
                    let in_object = x >= 8 + t && x < 20 + t && y >= 6 + c && y < 16;
                    let in_hand = x >= 24 && y >= 2 * t && y < 2 * t + 4 + c;
                    assert_eq!(
                        object.get_pixel(x as u32, y as u32).0[0],
                        255 * u8::from(in_object)
                    );
                    assert_eq!(
                        hand.get_pixel(x as u32, y as u32).0[0],
                        255 * u8::from(in_hand)
                    );
                }
            }
        }
    }
}

#[test]
fn case_without_masks_projects_tracks_and_category_can_be_given() {
    let (dir, case) = case_copy();
    fs::remove_dir_all(case.join("mask")).expect("remove masks");
    let out = dir.path().join("bundle");
    let options = ImportOptions {
        category: Some(Category::Planar),
        ..ImportOptions::default()
    };
    let summary = import_phystwin(&case, &out, &options).expect("import");
    assert_eq!(summary.mask_source, MaskSource::ProjectedTracks);
    assert!(!summary.category_inferred);
    let bundle = Bundle::open(&out).expect("valid");
    bundle.validate_images().expect("valid images");
    assert_eq!(bundle.meta.category, Category::Planar);
    assert!(bundle.meta.provenance.notes.contains("splatted"));
    // Every visible tracked point lands on the object mask, no invisible one is needed.
    for (c, camera) in bundle.meta.cameras.iter().enumerate() {
        let mask = bundle.load_mask(c, 1, MaskKind::Object).expect("mask");
        let mut covered = 0;
        for n in (0..OBJECT_POINTS).filter(|n| (n + 1) % 5 != 0) {
            let p = object_point(1, n).map(f64::from);
            let [u, v] = camera.project(p).expect("in front");
            if (0.0..WIDTH as f64).contains(&u) && (0.0..HEIGHT as f64).contains(&v) {
                assert_eq!(
                    mask.get_pixel(u as u32, v as u32).0[0],
                    255,
                    "cam{c} point {n}"
                );
                covered += 1;
            }
        }
        assert!(covered > 0, "cam{c} sees no tracked point");
    }
}

/// Runs an import that must fail; checks the error names `file` and `field`
/// and that nothing was left next to the output.
fn expect_failure(
    case: &Path,
    out_parent: &Path,
    file: &str,
    field: &str,
    words: &str,
) -> BundleError {
    let out = out_parent.join("bundle");
    let before = tree(case);
    let err = import_phystwin(case, &out, &ImportOptions::default()).expect_err("must fail");
    assert!(err.path.ends_with(file), "expected file {file}, got {err}");
    assert_eq!(err.field, field, "{err}");
    assert!(err.problem.contains(words), "expected '{words}' in: {err}");
    assert!(!out.exists(), "output must not exist after a failure");
    let leftovers: Vec<_> = fs::read_dir(out_parent)
        .expect("read")
        .map(|e| e.expect("entry").file_name())
        .filter(|name| name.to_string_lossy().starts_with("bundle"))
        .collect();
    assert!(leftovers.is_empty(), "leftovers: {leftovers:?}");
    assert_eq!(tree(case), before, "the case must not be modified");
    err
}

#[test]
fn malformed_final_data_names_file_and_key() {
    let cases = [
        ("missing_key.pkl", "object_visibilities", "missing"),
        (
            "int_points.pkl",
            "controller_points",
            "expected float32 or float64, found int64",
        ),
        (
            "wrong_shape.pkl",
            "object_points",
            "expected shape (T, N, 3), found (5, 24, 2)",
        ),
        (
            "frame_mismatch.pkl",
            "object_visibilities",
            "expected shape (5, 24), found (4, 24)",
        ),
        ("nan_point.pkl", "object_points[2,3,1]", "must be finite"),
        ("truncated.pkl", "(pickle)", "truncated"),
        (
            "wrong_dtype.pkl",
            "(pickle)",
            "numpy dtype 'c8' is not supported",
        ),
        (
            "not_a_dict.pkl",
            "(top level)",
            "expected a dict of numpy arrays, found list of 3",
        ),
    ];
    for (bad, field, words) in cases {
        let (dir, case) = case_copy();
        fs::copy(
            fixtures().join("phystwin_bad").join(bad),
            case.join("final_data.pkl"),
        )
        .expect("replace final_data.pkl");
        expect_failure(&case, dir.path(), "final_data.pkl", field, words);
    }
}

#[test]
fn missing_frames_and_bad_metadata_name_file_and_key() {
    let (dir, case) = case_copy();
    fs::remove_file(case.join("color/1/3.png")).expect("remove");
    expect_failure(&case, dir.path(), "color/1/3.png", "file", "reading failed");

    let (dir, case) = case_copy();
    fs::remove_file(case.join("depth/2/4.npy")).expect("remove");
    expect_failure(&case, dir.path(), "depth/2/4.npy", "file", "reading failed");

    let (dir, case) = case_copy();
    fs::remove_file(case.join("mask/0/1/2.png")).expect("remove");
    expect_failure(
        &case,
        dir.path(),
        "mask/0/1/2.png",
        "file",
        "reading failed",
    );

    let edit_json = |case: &Path, name: &str, edit: &dyn Fn(&mut serde_json::Value)| {
        let path = case.join(name);
        let mut value: serde_json::Value =
            serde_json::from_str(&fs::read_to_string(&path).expect("read")).expect("json");
        edit(&mut value);
        fs::write(&path, value.to_string()).expect("write");
    };
    let (dir, case) = case_copy();
    edit_json(&case, "metadata.json", &|m| m["frame_num"] = 7.into());
    expect_failure(&case, dir.path(), "metadata.json", "frame_num", "is 7 but");

    let (dir, case) = case_copy();
    edit_json(&case, "metadata.json", &|m| {
        m["intrinsics"].as_array_mut().expect("array").pop();
    });
    expect_failure(
        &case,
        dir.path(),
        "metadata.json",
        "intrinsics",
        "has 2 cameras",
    );

    let (dir, case) = case_copy();
    edit_json(&case, "metadata.json", &|m| {
        m.as_object_mut().expect("object").remove("WH");
    });
    expect_failure(&case, dir.path(), "metadata.json", "WH", "missing");

    let (dir, case) = case_copy();
    edit_json(&case, "metadata.json", &|m| {
        m["intrinsics"][1][0][1] = 0.5.into()
    });
    expect_failure(
        &case,
        dir.path(),
        "metadata.json",
        "intrinsics[1][0][1]",
        "without skew",
    );

    let (dir, case) = case_copy();
    edit_json(&case, "split.json", &|m| m["frame_len"] = 4.into());
    expect_failure(&case, dir.path(), "split.json", "frame_len", "is 4 but");

    let (dir, case) = case_copy();
    edit_json(&case, "split.json", &|m| {
        m["test"] = serde_json::json!([2, 6])
    });
    expect_failure(&case, dir.path(), "split.json", "test", "within [0, 5]");

    let (dir, case) = case_copy();
    fs::write(
        case.join("mask/mask_info_2.json"),
        r#"{"0": "toy", "1": "toy2"}"#,
    )
    .expect("write");
    expect_failure(
        &case,
        dir.path(),
        "mask/mask_info_2.json",
        "(top level)",
        "exactly one object",
    );

    let (dir, case) = case_copy();
    fs::copy(case.join("color/0/0.png"), case.join("depth/0/1.npy")).expect("copy");
    expect_failure(&case, dir.path(), "depth/0/1.npy", "header", "cannot parse");
}

#[test]
fn calibration_must_be_rigid() {
    let (dir, case) = case_copy();
    // A pickle of [2 * identity] (protocol 2), written by hand: not a rotation.
    let calibration = fs::read(case.join("calibrate.pkl")).expect("read");
    assert!(calibration.starts_with(b"\x80\x05"));
    let mut scaled = b"\x80\x02]q\x00cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85C\x01b\x87R".to_vec();
    scaled.extend(b"(K\x01K\x04K\x04\x86cnumpy\ndtype\nX\x02\x00\x00\x00f8\x85R(K\x03X\x01\x00\x00\x00<NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb\x89B\x80\x00\x00\x00");
    for r in 0..4 {
        for c in 0..4 {
            let v: f64 = if r == c {
                if r == 3 { 1.0 } else { 2.0 }
            } else {
                0.0
            };
            scaled.extend(v.to_le_bytes());
        }
    }
    scaled.extend(b"tba.");
    fs::write(case.join("calibrate.pkl"), &scaled).expect("write");
    let err = expect_failure(
        &case,
        dir.path(),
        "calibrate.pkl",
        "[0]",
        "not a proper rotation",
    );
    assert!(
        err.to_string().contains("calibrate.pkl: field `[0]`"),
        "{err}"
    );
}

#[test]
fn existing_output_is_refused_and_kept() {
    let (dir, case) = case_copy();
    let out = dir.path().join("bundle");
    fs::create_dir(&out).expect("mkdir");
    fs::write(out.join("keep.txt"), "mine").expect("write");
    let err = import_phystwin(&case, &out, &ImportOptions::default()).expect_err("refused");
    assert!(err.problem.contains("already exists"), "{err}");
    assert_eq!(
        fs::read_to_string(out.join("keep.txt")).expect("kept"),
        "mine"
    );
    let options = ImportOptions {
        overwrite: true,
        ..ImportOptions::default()
    };
    import_phystwin(&case, &out, &options).expect("overwrite");
    assert!(!out.join("keep.txt").exists());
    Bundle::open(&out).expect("valid");
}
