//! `dm-prep`: turns captures into scene bundles (docs/bundle.md).
//!
//! One subcommand per source format; `import-phystwin` reads a PhysTwin case
//! directory (method.md §10). A multi-view RGB-D capture (docs/capture.md)
//! goes through the stages `segment`, `depth`, `track`, `lift`, `fill`
//! (each cached under the work directory) or `all`, which also writes the
//! bundle; `score` compares a bundle's tracks with a reference bundle's.
//! `dm-prep VIDEO --out BUNDLE` (no subcommand) prepares a monocular video:
//! its depth frames (`--depth`) or a depth network of `models_manifest/`
//! make it a one-camera capture for the same stages; `models verify` checks
//! model files.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use dm_phystwin::{DEFAULT_CONTROLLER_LABEL, ImportOptions, MaskSource, import_phystwin};
use dm_prep::monocular::{
    ClipCapture, ClipSource, MonocularOptions, parse_intrinsics, prepare_clip_capture,
};
use dm_prep::score::{ScoreFrame, score_tracks_in};
use dm_prep::stages::{Prep, PrepOptions, Stage, StageModels, StageOutcome};
use dm_prep_models::{Manifest, VerifyStatus, default_models_dir, verify_dir};
use dm_shape_prior::{FitOptions, Intrinsics, Mesh, PnpOptions, fit_prior};
use indicatif::{ProgressBar, ProgressStyle};

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
    /// Depth frames recorded with the clip (DIR/<frame>.png, 16-bit
    /// millimetres, e.g. a phone's LiDAR); without it the depth network of
    /// models_manifest/ estimates them.
    #[arg(long)]
    depth: Option<PathBuf>,
    #[command(flatten)]
    models: StageModels,
    #[command(flatten)]
    monocular: MonocularOptions,
    /// Object category (default: inferred from the first-frame points).
    #[arg(long, value_enum)]
    category: Option<CategoryArg>,
    /// Hand (skin or glove) colour as R,G,B in [0, 1].
    #[arg(long, value_parser = parse_color)]
    hand_color: Option<[f32; 3]>,
    /// Replace an existing bundle at --out once the new one is complete.
    #[arg(long)]
    overwrite: bool,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Import a PhysTwin case directory (final_data.pkl, calibrate.pkl,
    /// metadata.json, split.json, color/, depth/, optional mask/).
    ImportPhystwin(ImportPhystwinArgs),
    /// Object and hand masks of a capture (depth/colour model + GrabCut, or
    /// SAM 2 with --segment-model sam2).
    Segment(StageArgs),
    /// Sensor depth of a capture, checked and cached.
    Depth(StageArgs),
    /// 2D tracks per camera (Lucas-Kanade with a forward-backward check, or
    /// CoTracker3 with --track-model cotracker3).
    Track(StageArgs),
    /// 3D object and hand tracks (depth + calibration, multi-view fusion).
    Lift(StageArgs),
    /// First-frame particles (surface, interior or sheet).
    Fill(StageArgs),
    /// Every stage, then the scene bundle at --out.
    All(AllArgs),
    /// Median 3D track error of BUNDLE against --reference.
    Score(ScoreArgs),
    /// Shape prior: pose a mesh (OBJ, glTF, GLB) in a frame by ORB matches
    /// and PnP-RANSAC over rendered views, then ICP + ARAP onto the frame's
    /// object points.
    Prior(PriorArgs),
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
struct StageArgs {
    /// The capture directory (calibration.json, <camera>/color.mp4, <camera>/depth/).
    #[arg(long)]
    capture: PathBuf,
    /// Where stage outputs are cached (default: <out>.work, or <capture>.work).
    #[arg(long)]
    work: Option<PathBuf>,
    /// The bundle the stages prepare (names the default work directory).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Object category (default: inferred from the first-frame points).
    #[arg(long, value_enum)]
    category: Option<CategoryArg>,
    /// Hand (skin or glove) colour as R,G,B in [0, 1].
    #[arg(long, value_parser = parse_color)]
    hand_color: Option<[f32; 3]>,
    #[command(flatten)]
    models: StageModels,
}

#[derive(Args, Debug)]
struct AllArgs {
    #[command(flatten)]
    stage: StageArgs,
    /// Replace an existing bundle at --out once the new one is complete.
    #[arg(long)]
    overwrite: bool,
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
    #[arg(long, value_parser = parse_intrinsics)]
    intrinsics: [f64; 4],
    /// First-frame object points, (N, 3) float32 .npy in the camera frame (metres).
    #[arg(long)]
    points: PathBuf,
    /// Output directory: prior.json, prior_vertices.npy, prior_triangles.npy.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args, Debug)]
struct ScoreArgs {
    /// The prepared bundle.
    bundle: PathBuf,
    /// The reference bundle (e.g. dm-synth --exact-tracks).
    #[arg(long)]
    reference: PathBuf,
    /// Compare in each bundle's camera 0 frame instead of the world (a
    /// monocular clip's bundle has its own, floor-based world).
    #[arg(long)]
    camera0: bool,
}

fn parse_color(s: &str) -> Result<[f32; 3], String> {
    let values: Vec<f32> = s
        .split(',')
        .map(|v| v.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{s}`: {e}"))?;
    match values[..] {
        [r, g, b] if [r, g, b].iter().all(|v| (0.0..=1.0).contains(v)) => Ok([r, g, b]),
        _ => Err(format!("`{s}` is not R,G,B with each in [0, 1]")),
    }
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

fn prep_for(args: &StageArgs) -> Result<Prep> {
    let work = args.work.clone().unwrap_or_else(|| {
        sibling_with_suffix(args.out.as_ref().unwrap_or(&args.capture), ".work")
    });
    let mut options = PrepOptions {
        category: args.category.map(Into::into),
        models: args.models.clone(),
        ..PrepOptions::default()
    };
    if let Some(color) = args.hand_color {
        options.segment.hand_color = color;
    }
    Prep::new(&args.capture, &work, options)
        .with_context(|| format!("opening capture {}", args.capture.display()))
}

fn progress_bar() -> Result<ProgressBar> {
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("{msg:>10} [{bar:40}] {pos}/{len} {elapsed}")
            .context("progress template")?
            .progress_chars("=> "),
    );
    Ok(bar)
}

fn report(outcomes: &[StageOutcome]) {
    for o in outcomes {
        if o.ran {
            println!("stage {}: ran in {:.1} s", o.stage.name(), o.seconds);
        } else {
            println!("stage {}: up to date (cached)", o.stage.name());
        }
    }
}

fn stage_command(stage: Stage, args: &StageArgs) -> Result<()> {
    let prep = prep_for(args)?;
    let bar = progress_bar()?;
    let mut progress = |name: &str, done: usize, total: usize| {
        if bar.message() != name {
            bar.set_message(name.to_string());
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
    };
    let outcomes = prep
        .run(stage, &mut progress)
        .with_context(|| format!("stage {} on {}", stage.name(), args.capture.display()))?;
    bar.finish_and_clear();
    report(&outcomes);
    println!("work directory {}", prep.work.display());
    Ok(())
}

fn all_command(args: &AllArgs) -> Result<()> {
    let out = args.stage.out.clone().context("`all` needs --out BUNDLE")?;
    let prep = prep_for(&args.stage)?;
    let bar = progress_bar()?;
    let mut progress = |name: &str, done: usize, total: usize| {
        if bar.message() != name {
            bar.set_message(name.to_string());
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
    };
    let start = std::time::Instant::now();
    let bundle = prep
        .write_bundle(&out, args.overwrite, &mut progress)
        .with_context(|| {
            format!(
                "preparing {} into {}",
                args.stage.capture.display(),
                out.display()
            )
        })?;
    bar.finish_and_clear();
    for stage in Stage::ALL {
        if let Some(seconds) = prep.recorded_seconds(stage) {
            println!(
                "stage {}: {:.1} s (when it last ran)",
                stage.name(),
                seconds
            );
        }
    }
    println!(
        "wrote {}: {} frames, {} cameras, {} object tracks, {} hand anchors in {} hands, {} + {} particles, category {:?} ({:.1} s)",
        out.display(),
        bundle.meta.frame_count,
        bundle.meta.cameras.len(),
        bundle.tracks.object_point_count(),
        bundle.tracks.hand_anchor_count(),
        bundle.meta.hands.len(),
        bundle.particles.surface_points.nrows(),
        bundle.particles.interior_points.nrows(),
        bundle.meta.category,
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

fn prior_command(args: &PriorArgs) -> Result<()> {
    let [fx, fy, cx, cy] = args.intrinsics;
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
        bail!(
            "{}: shape {:?}, expected (N, 3)",
            args.points.display(),
            points.dim()
        );
    }
    let points: Vec<nalgebra::Vector3<f64>> = points
        .rows()
        .into_iter()
        .map(|row| nalgebra::Vector3::new(f64::from(row[0]), f64::from(row[1]), f64::from(row[2])))
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
    .with_context(|| {
        format!(
            "fitting {} to {}",
            args.mesh.display(),
            args.frame.display()
        )
    })?;
    result
        .write(&args.out, &args.mesh)
        .with_context(|| format!("writing the shape prior into {}", args.out.display()))?;
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

fn score_command(args: &ScoreArgs) -> Result<()> {
    let frame = if args.camera0 {
        ScoreFrame::Camera0
    } else {
        ScoreFrame::World
    };
    let score = score_tracks_in(&args.bundle, &args.reference, frame).with_context(|| {
        format!(
            "scoring {} against {}",
            args.bundle.display(),
            args.reference.display()
        )
    })?;
    print_to_reader(&format!(
        "track_error_median_m {:.6}\ntrack_error_mean_m {:.6}\ntrack_error_p90_m {:.6}\n\
         frame0_match_median_m {:.6}\nscored_entries {} tracks {}\n",
        score.median_m,
        score.mean_m,
        score.p90_m,
        score.match_median_m,
        score.entries,
        score.tracks
    ))
}

/// Writes `text` to stdout; a reader that has stopped reading (`dm-prep
/// score … | head -1`) is not an error.
fn print_to_reader(text: &str) -> Result<()> {
    use std::io::Write;
    match std::io::stdout().lock().write_all(text.as_bytes()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => Ok(other?),
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Some(Command::ImportPhystwin(args)) => import_phystwin_command(args),
        Some(Command::Segment(args)) => stage_command(Stage::Segment, args),
        Some(Command::Depth(args)) => stage_command(Stage::Depth, args),
        Some(Command::Track(args)) => stage_command(Stage::Track, args),
        Some(Command::Lift(args)) => stage_command(Stage::Lift, args),
        Some(Command::Fill(args)) => stage_command(Stage::Fill, args),
        Some(Command::All(args)) => all_command(args),
        Some(Command::Score(args)) => score_command(args),
        Some(Command::Prior(args)) => prior_command(args),
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
        Some(dir) => {
            Manifest::load_dir(dir).with_context(|| format!("reading manifest {}", dir.display()))
        }
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
            VerifyStatus::Ok {
                sha256,
                sha256_pinned,
            } => println!(
                "ok      {:<22} {} sha256 {sha256}{}",
                report.id,
                report.path.display(),
                if *sha256_pinned {
                    " (matches the manifest)"
                } else {
                    " (not pinned in the manifest)"
                }
            ),
            VerifyStatus::Failed(message) => {
                failed += 1;
                println!("FAILED  {:<22} {message}", report.id);
            }
        }
    }
    if failed > 0 {
        bail!(
            "{failed} of the model files in {} failed verification",
            dir.display()
        );
    }
    Ok(())
}

fn video_command(args: &VideoArgs) -> Result<()> {
    let Some(video) = &args.video else {
        bail!(
            "nothing to do: give a video (`dm-prep video.mp4 --out bundle/`) or a subcommand (`dm-prep --help`)"
        );
    };
    let Some(out) = &args.out else {
        bail!("{}: --out BUNDLE is required", video.display());
    };
    if !video.is_file() {
        bail!("{}: no such video file", video.display());
    }
    if let Some(dir) = &args.depth
        && !dir.is_dir()
    {
        bail!("{}: --depth: no such directory", dir.display());
    }
    let options = &args.monocular;
    if !(options.horizontal_fov_deg > 1.0 && options.horizontal_fov_deg < 179.0) {
        bail!(
            "--fov-deg {}: must be between 1 and 179 degrees",
            options.horizontal_fov_deg
        );
    }
    if !(options.network_depth_scale.is_finite() && options.network_depth_scale > 0.0) {
        bail!(
            "--depth-scale {}: must be a positive number",
            options.network_depth_scale
        );
    }
    if let Some(height) = options.camera_height_m
        && !(height.is_finite() && height > 0.0)
    {
        bail!("--camera-height-m {height}: must be a positive number of metres");
    }
    if let Some(fps) = options.fps
        && !(fps.is_finite() && fps > 0.0)
    {
        bail!("--fps {fps}: must be a positive number");
    }
    let work = sibling_with_suffix(out, ".work");
    let capture = work.join("capture");
    let source = ClipSource {
        video,
        depth_frames: args.depth.as_deref(),
        models_dir: args.models.models_dir.as_deref(),
        options,
    };
    let bar = progress_bar()?;
    bar.set_message("depth");
    let mut progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let built = prepare_clip_capture(&source, &capture, &work.join("capture.json"), &mut progress)
        .with_context(|| format!("preparing {} into {}", video.display(), capture.display()))?;
    bar.finish_and_clear();
    match built {
        ClipCapture::Cached => println!("capture {}: up to date (cached)", capture.display()),
        ClipCapture::Written { frames, fps, floor } => println!(
            "capture {}: {frames} frames at {fps} fps; floor {:.3} m below the camera ({:.0} % of frame 0 on it)",
            capture.display(),
            floor.offset_m,
            100.0 * floor.inlier_fraction
        ),
    }
    all_command(&AllArgs {
        stage: StageArgs {
            capture,
            work: Some(work),
            out: Some(out.clone()),
            category: args.category,
            hand_color: args.hand_color,
            models: args.models.clone(),
        },
        overwrite: args.overwrite,
    })
}

fn sibling_with_suffix(path: &Path, suffix: &str) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(suffix);
    path.with_file_name(name)
}
