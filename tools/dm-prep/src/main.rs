//! `dm-prep`: turns captures into scene bundles (docs/bundle.md).
//!
//! One subcommand per source format; `import-phystwin` reads a PhysTwin case
//! directory (method.md §10). `dm-prep VIDEO --out BUNDLE` (no subcommand)
//! prepares a monocular video with the ONNX models of `models_manifest/`;
//! `models verify` checks model files; `prior` poses a mesh in a frame.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use dm_prep::models::{Manifest, MonocularModels, VerifyStatus, default_models_dir, verify_dir};
use dm_prep::phystwin::{DEFAULT_CONTROLLER_LABEL, ImportOptions, MaskSource, import_phystwin};
use dm_prep::prior::{FitOptions, Intrinsics, Mesh, PnpOptions, fit_prior};
use nalgebra::Vector3;

#[derive(Parser, Debug)]
#[command(
    name = "dm-prep",
    version,
    about = "Turn captures into scene bundles",
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    video: VideoArgs,
}

/// `dm-prep VIDEO --out BUNDLE`: a monocular video.
#[derive(Args, Debug)]
struct VideoArgs {
    /// A monocular video (mp4).
    video: Option<PathBuf>,
    /// Output bundle directory.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Directory of the ONNX model files ($DM_MODELS_DIR, else ./models).
    #[arg(long)]
    models: Option<PathBuf>,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Import a PhysTwin case directory (final_data.pkl, calibrate.pkl,
    /// metadata.json, split.json, color/, depth/, optional mask/).
    ImportPhystwin(ImportPhystwinArgs),
    /// ONNX model files of models_manifest/.
    Models {
        #[command(subcommand)]
        command: ModelsCommand,
    },
    /// Shape prior: pose a mesh (OBJ, glTF, GLB) in a frame by ORB matches +
    /// PnP-RANSAC, then fit it to the first-frame points (ICP + ARAP).
    Prior(PriorArgs),
}

#[derive(Subcommand, Debug)]
enum ModelsCommand {
    /// Check the model files present in DIR: sha256 (where the manifest pins
    /// one) and the ONNX input/output signature. Absent files are listed.
    Verify {
        /// Models directory ($DM_MODELS_DIR, else ./models).
        dir: Option<PathBuf>,
        /// A manifest directory other than the built-in models_manifest/.
        #[arg(long)]
        manifest: Option<PathBuf>,
    },
}

#[derive(Args, Debug)]
struct PriorArgs {
    /// The object's mesh (.obj with vertex colours or materials, .gltf, .glb).
    #[arg(long)]
    mesh: PathBuf,
    /// The first frame (PNG).
    #[arg(long)]
    frame: PathBuf,
    /// The first frame's object mask (PNG, > 127 = object).
    #[arg(long)]
    mask: Option<PathBuf>,
    /// Pinhole intrinsics fx,fy,cx,cy (pixels).
    #[arg(long, value_delimiter = ',', num_args = 4)]
    intrinsics: Vec<f64>,
    /// First-frame object points, (N, 3) float32 .npy in the camera frame (metres).
    #[arg(long)]
    points: PathBuf,
    /// Output directory: prior.json, prior_vertices.npy, prior_triangles.npy.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args, Debug)]
struct ImportPhystwinArgs {
    /// The PhysTwin case directory (only read).
    case_dir: PathBuf,
    /// Output bundle directory; must not exist unless --overwrite.
    #[arg(long)]
    out: PathBuf,
    /// Object category (default: inferred from the first-frame points).
    #[arg(long, value_enum)]
    category: Option<CategoryArg>,
    /// Label of the hands in mask/mask_info_<c>.json.
    #[arg(long, default_value = DEFAULT_CONTROLLER_LABEL)]
    controller_label: String,
    /// Replace an existing bundle at --out once the new one is complete.
    #[arg(long)]
    overwrite: bool,
}

#[derive(ValueEnum, Clone, Copy, Debug)]
enum CategoryArg {
    Linear,
    Planar,
    Volumetric,
}

impl From<CategoryArg> for dm_bundle::Category {
    fn from(arg: CategoryArg) -> Self {
        match arg {
            CategoryArg::Linear => dm_bundle::Category::Linear,
            CategoryArg::Planar => dm_bundle::Category::Planar,
            CategoryArg::Volumetric => dm_bundle::Category::Volumetric,
        }
    }
}

fn import_phystwin_command(args: &ImportPhystwinArgs) -> Result<()> {
    let options = ImportOptions {
        category: args.category.map(Into::into),
        controller_label: args.controller_label.clone(),
        overwrite: args.overwrite,
    };
    let summary = import_phystwin(&args.case_dir, &args.out, &options).with_context(|| {
        format!(
            "importing PhysTwin case {} into {}",
            args.case_dir.display(),
            args.out.display()
        )
    })?;
    let meta = &summary.bundle.meta;
    println!(
        "wrote {}: {} frames, {} cameras, {} tracked points, {} controller points, category {:?}{}, masks {}",
        args.out.display(),
        meta.frame_count,
        meta.cameras.len(),
        summary.bundle.tracks.object_point_count(),
        summary.bundle.tracks.hand_anchor_count(),
        meta.category,
        if summary.category_inferred {
            " (inferred)"
        } else {
            ""
        },
        match summary.mask_source {
            MaskSource::Segmentation => "from the case's segmentation",
            MaskSource::ProjectedTracks => "projected from tracks (the case has no mask/)",
        }
    );
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Some(Command::ImportPhystwin(args)) => import_phystwin_command(args),
        Some(Command::Models {
            command: ModelsCommand::Verify { dir, manifest },
        }) => models_verify_command(dir.as_deref(), manifest.as_deref()),
        Some(Command::Prior(args)) => prior_command(args),
        None => video_command(&cli.video),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

fn load_manifest(dir: Option<&Path>) -> Result<Manifest> {
    match dir {
        Some(dir) => Manifest::load_dir(dir).with_context(|| format!("reading manifest {}", dir.display())),
        None => Manifest::builtin().context("reading the built-in models_manifest/"),
    }
}

fn models_verify_command(dir: Option<&Path>, manifest: Option<&Path>) -> Result<()> {
    let manifest = load_manifest(manifest)?;
    let dir = dir.map_or_else(default_models_dir, Path::to_path_buf);
    let reports = verify_dir(&manifest, &dir);
    let mut failed = 0;
    for report in &reports {
        match &report.status {
            VerifyStatus::Absent => println!("absent  {:<22} {}", report.id, report.path.display()),
            VerifyStatus::Ok { sha256, sha256_pinned } => println!(
                "ok      {:<22} {} sha256 {sha256}{}",
                report.id,
                report.path.display(),
                if *sha256_pinned { " (matches the manifest)" } else { " (not pinned in the manifest)" }
            ),
            VerifyStatus::Failed(message) => {
                failed += 1;
                println!("FAILED  {:<22} {message}", report.id);
            }
        }
    }
    if failed > 0 {
        bail!("{failed} of the model files in {} failed verification", dir.display());
    }
    Ok(())
}

fn video_command(args: &VideoArgs) -> Result<()> {
    let Some(video) = &args.video else {
        bail!("nothing to do: give a video (`dm-prep video.mp4 --out bundle/`) or a subcommand (`dm-prep --help`)");
    };
    let Some(out) = &args.out else {
        bail!("{}: --out BUNDLE is required", video.display());
    };
    if !video.is_file() {
        bail!("{}: no such video file", video.display());
    }
    let manifest = load_manifest(None)?;
    let models_dir = args.models.clone().unwrap_or_else(default_models_dir);
    // Classical fallbacks (issue 8, capture pipeline) go here: when a model
    // is missing, run the OpenCV fallback for that stage instead of failing.
    let _models = MonocularModels::load(&manifest, &models_dir, 1)
        .with_context(|| format!("preparing {} into {}", video.display(), out.display()))?;
    bail!(
        "{}: the models in {} load and match the manifest, but this build has no monocular lift/fill stage to assemble a bundle from their outputs (issue 8 capture pipeline)",
        video.display(),
        models_dir.display()
    )
}

fn prior_command(args: &PriorArgs) -> Result<()> {
    let [fx, fy, cx, cy] = args.intrinsics[..] else {
        bail!("--intrinsics: expected fx,fy,cx,cy");
    };
    let mesh = Mesh::load(&args.mesh)?;
    let frame = image::open(&args.frame)
        .with_context(|| format!("{}: reading the frame", args.frame.display()))?
        .to_rgb8();
    let mask = match &args.mask {
        Some(path) => Some(
            image::open(path)
                .with_context(|| format!("{}: reading the mask", path.display()))?
                .to_luma8(),
        ),
        None => None,
    };
    let points: ndarray::Array2<f32> = dm_bundle::read_npy_checked(&args.points)?;
    if points.ncols() != 3 {
        bail!("{}: shape {:?}, expected (N, 3)", args.points.display(), points.dim());
    }
    let points: Vec<Vector3<f64>> = points
        .rows()
        .into_iter()
        .map(|row| Vector3::new(f64::from(row[0]), f64::from(row[1]), f64::from(row[2])))
        .collect();
    let intrinsics = Intrinsics {
        fx,
        fy,
        cx,
        cy,
        width: frame.width(),
        height: frame.height(),
    };
    let result = fit_prior(
        &mesh,
        &frame,
        mask.as_ref(),
        &intrinsics,
        &points,
        &PnpOptions::default(),
        &FitOptions::default(),
    )
    .with_context(|| format!("fitting {} to {}", args.mesh.display(), args.frame.display()))?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let pose_json = |pose: &nalgebra::Isometry3<f64>| {
        let rotation = pose.rotation.to_rotation_matrix();
        serde_json::json!({
            "rotation": (0..3).map(|r| (0..3).map(|c| rotation[(r, c)]).collect::<Vec<_>>()).collect::<Vec<_>>(),
            "translation_m": pose.translation.vector.iter().copied().collect::<Vec<_>>(),
        })
    };
    let report = serde_json::json!({
        "mesh": args.mesh.display().to_string(),
        "pnp_mesh_to_camera": pose_json(&result.pnp.mesh_to_camera),
        "pnp_view": result.pnp.view,
        "pnp_matches": result.pnp.matches,
        "pnp_inliers": result.pnp.inliers,
        "icp_mesh_to_camera": pose_json(&result.fit.rigid_pose),
        "arap_mesh_to_camera": pose_json(&result.fit.deformed_pose),
        "median_distance_before_m": result.fit.median_distance_before_m,
        "median_distance_after_m": result.fit.median_distance_after_m,
    });
    let vertices = ndarray::Array2::from_shape_fn((result.fit.vertices.len(), 3), |(i, k)| result.fit.vertices[i][k] as f32);
    let triangles = ndarray::Array2::from_shape_fn((result.triangles.len(), 3), |(i, k)| result.triangles[i][k] as i32);
    dm_bundle::write_npy_file(&args.out.join("prior_vertices.npy"), &vertices)?;
    dm_bundle::write_npy_file(&args.out.join("prior_triangles.npy"), &triangles)?;
    dm_bundle::write_json_atomic(&args.out.join("prior.json"), &report)?;
    println!(
        "wrote {}: PnP {} inliers of {} matches (view {}), median point distance {:.2} mm -> {:.2} mm",
        args.out.display(),
        result.pnp.inliers,
        result.pnp.matches,
        result.pnp.view,
        1e3 * result.fit.median_distance_before_m,
        1e3 * result.fit.median_distance_after_m
    );
    Ok(())
}
