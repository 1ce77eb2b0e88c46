//! `dm-prep`: turns captures into scene bundles (docs/bundle.md).
//!
//! One subcommand per source format; `import-phystwin` reads a PhysTwin case
//! directory (method.md §10). `dm-prep VIDEO --out BUNDLE` (no subcommand)
//! prepares a monocular video with the ONNX models of `models_manifest/`;
//! `models verify` checks model files.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use dm_prep::models::{Manifest, MonocularModels, VerifyStatus, default_models_dir, verify_dir};
use dm_prep::phystwin::{DEFAULT_CONTROLLER_LABEL, ImportOptions, MaskSource, import_phystwin};

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
