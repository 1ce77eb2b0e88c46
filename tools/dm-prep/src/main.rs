//! `dm-prep`: turns captures into scene bundles (docs/bundle.md).
//!
//! One subcommand per source format; `import-phystwin` reads a PhysTwin case
//! directory (method.md §10).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};
use dm_prep::phystwin::{DEFAULT_CONTROLLER_LABEL, ImportOptions, MaskSource, import_phystwin};

#[derive(Parser, Debug)]
#[command(name = "dm-prep", version, about = "Turn captures into scene bundles")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Import a PhysTwin case directory (final_data.pkl, calibrate.pkl,
    /// metadata.json, split.json, color/, depth/, optional mask/).
    ImportPhystwin(ImportPhystwinArgs),
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
        Command::ImportPhystwin(args) => import_phystwin_command(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}
