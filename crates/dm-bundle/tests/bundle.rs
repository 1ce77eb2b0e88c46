//! Round trip and corruption tests for scene bundle v1.

use std::fs;
use std::path::{Path, PathBuf};

use dm_bundle::{
    Bundle, BundleError, BundleMeta, BundleWriter, CameraSpec, Category, FirstFrameParticles,
    HandSpec, MaskKind, Provenance, Split, Tracks, UpAxis, depth_m_to_png_mm, write_json_atomic,
    write_npy_file,
};
use image::{GrayImage, Luma, Rgb, RgbImage};
use ndarray::{Array2, Array3};
use serde_json::Value;

const T: usize = 5;
const N: usize = 7;
const M: usize = 3;
const WIDTH: u32 = 8;
const HEIGHT: u32 = 6;

type TestResult = Result<(), Box<dyn std::error::Error>>;
type JsonEdit = Box<dyn Fn(&mut Value)>;

fn camera(name: &str, angle: f64) -> CameraSpec {
    let (s, c) = angle.sin_cos();
    CameraSpec {
        name: name.to_owned(),
        width: WIDTH,
        height: HEIGHT,
        fx: 10.0,
        fy: 11.0,
        cx: 4.0,
        cy: 3.0,
        // Rotation about the camera's y axis plus a translation along z.
        world_to_camera: [
            [c, 0.0, s, 0.1],
            [0.0, 1.0, 0.0, -0.2],
            [-s, 0.0, c, 1.5],
            [0.0, 0.0, 0.0, 1.0],
        ],
        axes: "opencv".to_owned(),
    }
}

fn sample_meta() -> BundleMeta {
    let mut meta = BundleMeta::new(
        T,
        30.0,
        Category::Linear,
        vec![camera("cam0", 0.0), camera("cam1", 0.7)],
    );
    meta.hands = vec![
        HandSpec {
            name: "right".to_owned(),
            anchor_range: [0, 2],
        },
        HandSpec {
            name: "left".to_owned(),
            anchor_range: [2, 3],
        },
    ];
    meta.provenance = Provenance {
        tool: "dm-bundle tests".to_owned(),
        source: "synthetic".to_owned(),
        created_unix_s: 1_700_000_000,
        notes: "round trip".to_owned(),
    };
    meta.floor_height_m = -0.05;
    meta
}

fn sample_tracks() -> Tracks {
    Tracks {
        object_points: Array3::from_shape_fn((T, N, 3), |(t, n, c)| {
            (t as f32) * 0.01 + (n as f32) * 0.1 + c as f32
        }),
        object_visibility: Array2::from_shape_fn((T, N), |(t, n)| (t + n) % 3 != 0),
        object_motion_valid: Array2::from_shape_fn((T, N), |(t, n)| (t * n) % 2 == 0),
        hand_points: Array3::from_shape_fn((T, M, 3), |(t, m, c)| {
            -(t as f32) * 0.02 + (m as f32) * 0.5 - c as f32
        }),
        hand_visibility: Array2::from_shape_fn((T, M), |(t, m)| t != m),
    }
}

fn sample_particles() -> FirstFrameParticles {
    FirstFrameParticles {
        surface_points: Array2::from_shape_fn((10, 3), |(i, c)| i as f32 * 0.01 + c as f32),
        surface_colors: Array2::from_shape_fn((10, 3), |(i, c)| ((i + c) % 5) as f32 / 4.0),
        interior_points: Array2::from_shape_fn((4, 3), |(i, c)| i as f32 * 0.02 - c as f32),
        interior_colors: Array2::from_shape_fn((4, 3), |(i, c)| ((i * c) % 3) as f32 / 2.0),
    }
}

struct FrameImages {
    rgb: RgbImage,
    depth_m: Vec<f32>,
    mask_object: GrayImage,
    mask_hand: GrayImage,
}

fn sample_images(cam: usize, frame: usize) -> FrameImages {
    let rgb = RgbImage::from_fn(WIDTH, HEIGHT, |x, y| {
        Rgb([
            (x * 30) as u8,
            (y * 40) as u8,
            (cam * 100 + frame * 20) as u8,
        ])
    });
    let depth_m = (0..WIDTH * HEIGHT)
        .map(|i| match i % 7 {
            0 => f32::NAN,
            1 => 0.0,
            2 => -1.0,
            3 => 100.0, // beyond the u16 millimetre range: clamped
            _ => 0.5 + i as f32 * 0.0123 + frame as f32 * 0.001,
        })
        .collect();
    let mask_object = GrayImage::from_fn(WIDTH, HEIGHT, |x, y| {
        Luma([if (x + y + frame as u32).is_multiple_of(2) {
            255
        } else {
            0
        }])
    });
    let mask_hand = GrayImage::from_fn(WIDTH, HEIGHT, |x, _| {
        Luma([if x as usize == cam + frame { 255 } else { 0 }])
    });
    FrameImages {
        rgb,
        depth_m,
        mask_object,
        mask_hand,
    }
}

fn write_all_frames(writer: &mut BundleWriter) -> Result<(), BundleError> {
    for cam in 0..2 {
        for frame in 0..T {
            let images = sample_images(cam, frame);
            writer.write_frame_images(
                cam,
                frame,
                &images.rgb,
                &images.depth_m,
                &images.mask_object,
                &images.mask_hand,
            )?;
        }
    }
    Ok(())
}

fn write_sample_bundle(dir: &Path) -> Result<Bundle, BundleError> {
    let mut writer = BundleWriter::create(dir, sample_meta())?;
    write_all_frames(&mut writer)?;
    writer.write_tracks(&sample_tracks())?;
    writer.write_particles(&sample_particles())?;
    writer.write_mesh_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")?;
    writer.finish()
}

/// A fresh valid bundle at `<tmp>/bundle`.
fn fresh_bundle() -> Result<(tempfile::TempDir, PathBuf), Box<dyn std::error::Error>> {
    let tmp = tempfile::tempdir()?;
    let dir = tmp.path().join("bundle");
    write_sample_bundle(&dir)?;
    Ok((tmp, dir))
}

fn open_err(dir: &Path) -> BundleError {
    match Bundle::open(dir) {
        Ok(_) => panic!("expected Bundle::open({}) to fail", dir.display()),
        Err(e) => {
            // Shown with --nocapture, to eyeball message quality.
            eprintln!("{e}");
            e
        }
    }
}

fn edit_json(dir: &Path, edit: impl FnOnce(&mut Value)) -> TestResult {
    let path = dir.join("bundle.json");
    let mut value: Value = serde_json::from_str(&fs::read_to_string(&path)?)?;
    edit(&mut value);
    write_json_atomic(&path, &value)?;
    Ok(())
}

fn dir_entries(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = fs::read_dir(dir)
        .map(|entries| {
            entries
                .filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

#[test]
fn round_trip_preserves_everything() -> TestResult {
    let (tmp, dir) = fresh_bundle()?;
    // Nothing but the final directory is left next to it.
    assert_eq!(dir_entries(tmp.path()), vec!["bundle".to_owned()]);

    let bundle = Bundle::open(&dir)?;
    let mut expected_meta = sample_meta();
    expected_meta.mesh = Some("mesh/object.obj".to_owned());
    assert_eq!(bundle.meta, expected_meta);
    assert_eq!(bundle.tracks, sample_tracks());
    assert_eq!(bundle.particles, sample_particles());
    assert_eq!(bundle.root, dir);
    assert!(dir.join("mesh/object.obj").is_file());
    bundle.validate_images()?;

    for cam in 0..2 {
        for frame in 0..T {
            let images = sample_images(cam, frame);
            assert_eq!(bundle.load_rgb(cam, frame)?, images.rgb);
            assert_eq!(
                bundle.load_mask(cam, frame, MaskKind::Object)?,
                images.mask_object
            );
            assert_eq!(
                bundle.load_mask(cam, frame, MaskKind::Hand)?,
                images.mask_hand
            );
            let depth = bundle.load_depth_m(cam, frame)?;
            assert_eq!(depth.len(), images.depth_m.len());
            for (&written, &read) in images.depth_m.iter().zip(&depth) {
                match depth_m_to_png_mm(written) {
                    0 => assert!(
                        read.is_nan(),
                        "{written} should read back as NaN, got {read}"
                    ),
                    mm => assert_eq!(read, f32::from(mm) / 1000.0),
                }
            }
        }
    }
    // Out-of-range indices are errors, not panics.
    assert!(bundle.load_rgb(2, 0).is_err());
    assert!(bundle.load_rgb(0, T).is_err());
    Ok(())
}

#[test]
fn depth_encoding_rounds_and_clamps() {
    assert_eq!(depth_m_to_png_mm(f32::NAN), 0);
    assert_eq!(depth_m_to_png_mm(f32::INFINITY), 0);
    assert_eq!(depth_m_to_png_mm(0.0), 0);
    assert_eq!(depth_m_to_png_mm(-0.3), 0);
    assert_eq!(depth_m_to_png_mm(0.0001), 1);
    assert_eq!(depth_m_to_png_mm(1.2344), 1234);
    assert_eq!(depth_m_to_png_mm(1.2346), 1235);
    assert_eq!(depth_m_to_png_mm(70.0), u16::MAX);
}

#[test]
fn a_missing_or_file_path_says_which() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let missing = tmp.path().join("no_scene");
    let err = open_err(&missing);
    assert_eq!(err.path, missing);
    assert_eq!(err.problem, "no such folder");
    let file = tmp.path().join("bundle.json");
    fs::write(&file, "{}")?;
    let err = open_err(&file);
    assert_eq!(err.path, file);
    assert!(err.problem.starts_with("not a directory"), "{err}");
    Ok(())
}

#[test]
fn truncated_npy_names_the_file() -> TestResult {
    let (_tmp, dir) = fresh_bundle()?;
    let path = dir.join("tracks/object_points.npy");
    let bytes = fs::read(&path)?;
    fs::write(&path, &bytes[..bytes.len() - 10])?;
    let err = open_err(&dir);
    assert_eq!(err.path, path);
    assert_eq!(err.field, "data");
    assert!(err.problem.contains("truncated"), "{err}");

    // Cut inside the header too.
    fs::write(&path, &bytes[..20])?;
    let err = open_err(&dir);
    assert_eq!(err.path, path);
    assert_eq!(err.field, "header");
    Ok(())
}

#[test]
fn wrong_dtype_names_expected_dtype() -> TestResult {
    let (_tmp, dir) = fresh_bundle()?;
    let path = dir.join("tracks/object_points.npy");
    write_npy_file(&path, &sample_tracks().object_points.mapv(f64::from))?;
    let err = open_err(&dir);
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (path.as_path(), "dtype")
    );
    assert!(
        err.problem.contains("float32") && err.problem.contains("<f8"),
        "{err}"
    );

    let path = dir.join("tracks/object_visibility.npy");
    write_npy_file(&path, &sample_tracks().object_points)?;
    write_npy_file(
        &dir.join("tracks/object_points.npy"),
        &sample_tracks().object_points,
    )?;
    let err = open_err(&dir);
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (path.as_path(), "dtype")
    );
    assert!(err.problem.contains("bool"), "{err}");
    Ok(())
}

#[test]
fn shape_mismatch_names_file_and_field() -> TestResult {
    let (_tmp, dir) = fresh_bundle()?;
    let path = dir.join("tracks/object_visibility.npy");
    write_npy_file(&path, &Array2::<bool>::from_elem((T, N - 1), true))?;
    let err = open_err(&dir);
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (path.as_path(), "shape")
    );
    assert!(
        err.problem.contains("(5, 7)") && err.problem.contains("(5, 6)"),
        "{err}"
    );

    // Frame count disagreeing with bundle.json.
    write_npy_file(&path, &sample_tracks().object_visibility)?;
    let points_path = dir.join("tracks/object_points.npy");
    write_npy_file(&points_path, &Array3::<f32>::zeros((T - 1, N, 3)))?;
    let err = open_err(&dir);
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (points_path.as_path(), "shape")
    );

    // Colours need one row per particle.
    write_npy_file(&points_path, &sample_tracks().object_points)?;
    let colors_path = dir.join("particles/interior_colors.npy");
    write_npy_file(&colors_path, &Array2::<f32>::zeros((3, 3)))?;
    let err = open_err(&dir);
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (colors_path.as_path(), "shape")
    );
    Ok(())
}

#[test]
fn non_finite_and_out_of_range_values_name_the_index() -> TestResult {
    let (_tmp, dir) = fresh_bundle()?;
    let path = dir.join("tracks/object_points.npy");
    let mut points = sample_tracks().object_points;
    points[[2, 3, 1]] = f32::NAN;
    write_npy_file(&path, &points)?;
    let err = open_err(&dir);
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (path.as_path(), "object_points[2,3,1]")
    );

    write_npy_file(&path, &sample_tracks().object_points)?;
    let colors_path = dir.join("particles/surface_colors.npy");
    let mut colors = sample_particles().surface_colors;
    colors[[4, 2]] = 1.5;
    write_npy_file(&colors_path, &colors)?;
    let err = open_err(&dir);
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (colors_path.as_path(), "surface_colors[4,2]")
    );
    Ok(())
}

#[test]
fn bad_json_names_the_key() -> TestResult {
    let (_tmp, dir) = fresh_bundle()?;
    let json = dir.join("bundle.json");
    let original = fs::read_to_string(&json)?;
    let cases: Vec<(JsonEdit, &str)> = vec![
        (
            Box::new(|v| drop(v.as_object_mut().map(|o| o.remove("fps")))),
            "fps",
        ),
        (Box::new(|v| v["category"] = "rope".into()), "category"),
        (Box::new(|v| v["up_axis"] = "z".into()), "up_axis"),
        (
            Box::new(|v| drop(v["cameras"][1].as_object_mut().map(|o| o.remove("fx")))),
            "cameras[1].fx",
        ),
        (
            Box::new(|v| v["cameras"][1]["fy"] = "ten".into()),
            "cameras[1].fy",
        ),
        (
            Box::new(|v| v["cameras"][0]["fx"] = (-3.0).into()),
            "cameras[0].fx",
        ),
        (
            Box::new(|v| v["cameras"][1]["name"] = "cam0".into()),
            "cameras[1].name",
        ),
        (
            Box::new(|v| v["cameras"][1]["name"] = "../x".into()),
            "cameras[1].name",
        ),
        (Box::new(|v| v["cameras"] = Value::Array(vec![])), "cameras"),
        (Box::new(|v| v["fps"] = 0.0.into()), "fps"),
        (Box::new(|v| v["format"] = "other".into()), "format"),
        (Box::new(|v| v["version"] = 2.into()), "version"),
        (Box::new(|v| v["units"] = "millimetres".into()), "units"),
        (
            Box::new(|v| v["depth"]["unit"] = "metres".into()),
            "depth.unit",
        ),
        (
            Box::new(|v| drop(v["provenance"].as_object_mut().map(|o| o.remove("tool")))),
            "provenance.tool",
        ),
        (
            Box::new(|v| v["split"]["test"] = serde_json::json!([2, 5])),
            "split.test",
        ),
        (
            Box::new(|v| v["split"]["train"] = serde_json::json!([0, 0])),
            "split.train",
        ),
        (
            Box::new(|v| v["split"]["test"] = serde_json::json!([3, 6])),
            "split.test",
        ),
        (
            Box::new(|v| v["hands"][1]["anchor_range"] = serde_json::json!([1, 3])),
            "hands[1].anchor_range",
        ),
        (
            Box::new(|v| v["hands"][1]["anchor_range"] = serde_json::json!([2, 4])),
            "hands[1].anchor_range",
        ),
        (
            Box::new(|v| {
                v["hands"] = serde_json::json!([{"name": "right", "anchor_range": [0, 2]}])
            }),
            "hands",
        ),
        (Box::new(|v| v["mesh"] = "../outside.obj".into()), "mesh"),
        (Box::new(|v| v["mesh"] = "mesh/missing.obj".into()), "mesh"),
    ];
    for (edit, field) in cases {
        fs::write(&json, &original)?;
        edit_json(&dir, edit)?;
        let err = open_err(&dir);
        assert_eq!(err.path, json, "{err}");
        assert_eq!(err.field, field, "{err}");
    }

    fs::write(&json, "{ not json")?;
    let err = open_err(&dir);
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (json.as_path(), "(json syntax)")
    );

    // `mesh` may be absent or null.
    fs::write(&json, &original)?;
    edit_json(&dir, |v| drop(v.as_object_mut().map(|o| o.remove("mesh"))))?;
    assert_eq!(Bundle::open(&dir)?.meta.mesh, None);
    Ok(())
}

#[test]
fn bad_rotation_names_the_camera() -> TestResult {
    let (_tmp, dir) = fresh_bundle()?;
    let json = dir.join("bundle.json");
    let original = fs::read_to_string(&json)?;
    let cases: Vec<JsonEdit> = vec![
        Box::new(|v| v["cameras"][1]["world_to_camera"][0][0] = 1.1.into()),
        Box::new(|v| v["cameras"][1]["world_to_camera"][3][2] = 0.5.into()),
        // A reflection: orthonormal but left-handed.
        Box::new(|v| {
            v["cameras"][1]["world_to_camera"] =
                serde_json::json!([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
        }),
    ];
    for edit in cases {
        fs::write(&json, &original)?;
        edit_json(&dir, edit)?;
        let err = open_err(&dir);
        assert_eq!(
            (err.path.as_path(), err.field.as_str()),
            (json.as_path(), "cameras[1].world_to_camera")
        );
    }
    Ok(())
}

#[test]
fn validate_images_names_missing_or_wrong_image() -> TestResult {
    let (_tmp, dir) = fresh_bundle()?;
    let bundle = Bundle::open(&dir)?;

    let missing = dir.join("views/cam1/depth/00003.png");
    fs::remove_file(&missing)?;
    let err = bundle.validate_images().err().ok_or("expected an error")?;
    assert_eq!(err.path, missing, "{err}");
    assert!(bundle.load_depth_m(1, 3).is_err());

    // Wrong colour type: an RGB image where a mask belongs.
    fs::copy(dir.join("views/cam1/depth/00002.png"), &missing)?;
    let mask = dir.join("views/cam0/mask_hand/00001.png");
    fs::copy(dir.join("views/cam0/rgb/00001.png"), &mask)?;
    let err = bundle.validate_images().err().ok_or("expected an error")?;
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (mask.as_path(), "colour_type")
    );

    // Wrong size.
    GrayImage::new(WIDTH + 1, HEIGHT).save(&mask)?;
    let err = bundle.validate_images().err().ok_or("expected an error")?;
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (mask.as_path(), "size")
    );

    // Mask value other than 0 / 255.
    GrayImage::from_pixel(WIDTH, HEIGHT, Luma([7])).save(&mask)?;
    let err = bundle.validate_images().err().ok_or("expected an error")?;
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (mask.as_path(), "pixel[0,0]")
    );

    // Not a PNG at all.
    fs::write(&mask, b"garbage")?;
    let err = bundle.validate_images().err().ok_or("expected an error")?;
    assert_eq!(
        (err.path.as_path(), err.field.as_str()),
        (mask.as_path(), "png")
    );
    Ok(())
}

#[test]
fn writer_refuses_to_overwrite_existing_dir() -> TestResult {
    let (_tmp, dir) = fresh_bundle()?;
    let before = fs::read(dir.join("bundle.json"))?;
    let err = BundleWriter::create(&dir, sample_meta())
        .err()
        .ok_or("expected an error")?;
    assert_eq!(err.path, dir);
    assert!(err.problem.contains("already exists"), "{err}");
    assert_eq!(fs::read(dir.join("bundle.json"))?, before);

    // create_overwrite replaces it, only once the new bundle is complete.
    let mut meta = sample_meta();
    meta.fps = 60.0;
    let mut writer = BundleWriter::create_overwrite(&dir, meta)?;
    write_all_frames(&mut writer)?;
    writer.write_tracks(&sample_tracks())?;
    writer.write_particles(&sample_particles())?;
    assert_eq!(Bundle::open(&dir)?.meta.fps, 30.0);
    let bundle = writer.finish()?;
    assert_eq!(bundle.meta.fps, 60.0);
    assert_eq!(Bundle::open(&dir)?.meta.fps, 60.0);
    // The old mesh went away with the old bundle.
    assert!(!dir.join("mesh").exists());
    let parent = dir.parent().ok_or("no parent")?;
    assert_eq!(dir_entries(parent), vec!["bundle".to_owned()]);
    Ok(())
}

#[test]
fn failed_write_leaves_no_final_dir() -> TestResult {
    let tmp = tempfile::tempdir()?;
    let dir = tmp.path().join("bundle");

    // Invalid content is caught by the validation in `finish`.
    let mut writer = BundleWriter::create(&dir, sample_meta())?;
    write_all_frames(&mut writer)?;
    let mut tracks = sample_tracks();
    tracks.hand_points[[1, 1, 1]] = f32::INFINITY;
    writer.write_tracks(&tracks)?;
    writer.write_particles(&sample_particles())?;
    let err = writer.finish().err().ok_or("expected an error")?;
    assert!(err.path.ends_with("tracks/hand_points.npy"), "{err}");
    assert_eq!(err.field, "hand_points[1,1,1]");
    assert!(
        dir_entries(tmp.path()).is_empty(),
        "{:?}",
        dir_entries(tmp.path())
    );

    // Missing pieces are reported by name.
    let mut writer = BundleWriter::create(&dir, sample_meta())?;
    writer.write_tracks(&sample_tracks())?;
    writer.write_particles(&sample_particles())?;
    let err = writer.finish().err().ok_or("expected an error")?;
    assert!(err.path.ends_with("views/cam0/rgb/00000.png"), "{err}");
    assert!(dir_entries(tmp.path()).is_empty());

    // Wrong image size is rejected at write time.
    let mut writer = BundleWriter::create(&dir, sample_meta())?;
    let images = sample_images(0, 0);
    let small = GrayImage::new(2, 2);
    let err = writer
        .write_frame_images(
            0,
            0,
            &images.rgb,
            &images.depth_m,
            &small,
            &images.mask_hand,
        )
        .err()
        .ok_or("expected an error")?;
    assert_eq!(err.field, "size");
    assert!(
        writer
            .write_frame_images(
                0,
                T,
                &images.rgb,
                &images.depth_m,
                &images.mask_object,
                &images.mask_hand
            )
            .is_err()
    );
    assert!(
        writer
            .write_frame_images(
                2,
                0,
                &images.rgb,
                &images.depth_m,
                &images.mask_object,
                &images.mask_hand
            )
            .is_err()
    );
    // Abandoning a writer cleans up after it.
    drop(writer);
    assert!(dir_entries(tmp.path()).is_empty());

    // Invalid metadata is rejected before anything is created.
    let mut meta = sample_meta();
    meta.cameras[0].fx = f64::NAN;
    let err = BundleWriter::create(&dir, meta)
        .err()
        .ok_or("expected an error")?;
    assert_eq!(err.field, "cameras[0].fx");
    assert!(dir_entries(tmp.path()).is_empty());
    Ok(())
}

#[test]
fn default_split_and_up_axis() {
    assert_eq!(
        Split::default_for(60),
        Split {
            train: [0, 42],
            test: [42, 60]
        }
    );
    assert_eq!(
        Split::default_for(5),
        Split {
            train: [0, 3],
            test: [3, 5]
        }
    );
    assert_eq!(
        Split::default_for(2),
        Split {
            train: [0, 1],
            test: [1, 2]
        }
    );
    assert_eq!(
        Split::default_for(3),
        Split {
            train: [0, 2],
            test: [2, 3]
        }
    );
    assert_eq!(UpAxis::NegY.unit_vector(), [0.0, -1.0, 0.0]);
    assert_eq!(UpAxis::PosZ.unit_vector(), [0.0, 0.0, 1.0]);
}

#[test]
fn spec_example_json_parses() -> TestResult {
    let text = r#"{
      "format": "deformmaster-bundle", "version": 1, "units": "metres", "up_axis": "-y",
      "fps": 30.0, "frame_count": 60, "category": "planar",
      "split": {"train": [0, 42], "test": [42, 60]},
      "provenance": {"tool": "dm-synth 0.1.0", "source": "preset rope seed 1", "created_unix_s": 0, "notes": ""},
      "depth": {"encoding": "png_u16", "unit": "millimetres"},
      "cameras": [{"name": "cam0", "width": 320, "height": 240, "fx": 300, "fy": 300, "cx": 160, "cy": 120,
                   "world_to_camera": [[1,0,0,0],[0,1,0,0],[0,0,1,2],[0,0,0,1]], "axes": "opencv"}],
      "hands": [{"name": "right", "anchor_range": [0, 16]}],
      "floor_height_m": 0.0, "mesh": null
    }"#;
    let meta: BundleMeta = serde_json::from_str(text)?;
    meta.validate(Path::new("bundle.json"))?;
    meta.validate_hand_ranges(Path::new("bundle.json"), 16)?;
    assert_eq!(meta.up_axis, UpAxis::NegY);
    assert_eq!(meta.category, Category::Planar);
    let reserialised = serde_json::to_value(&meta)?;
    assert_eq!(reserialised["up_axis"], "-y");
    assert_eq!(reserialised["category"], "planar");
    assert_eq!(reserialised["mesh"], Value::Null);
    assert_eq!(
        meta.cameras[0].project([0.0, 0.0, 0.0]),
        Some([160.0, 120.0])
    );
    Ok(())
}

#[test]
fn error_display_names_path_and_field() {
    let err = BundleError::new("/b/tracks/object_points.npy", "shape", "bad");
    assert_eq!(
        err.to_string(),
        "/b/tracks/object_points.npy: field `shape`: bad"
    );
}
