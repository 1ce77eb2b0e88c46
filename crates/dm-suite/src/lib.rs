//! The benchmark suite (docs/suite.md): synthetic scenes of the
//! three categories, each fitted by every `dm-fit` variant of a committed
//! suite file and scored with the benchmark's metrics; per-run results are
//! cached so an interrupted suite resumes, diverged runs are recorded as
//! such, and the overall and per-category tables are written in the
//! paper's layout (method.md §9).

use clap::Parser;
use dm_bundle::{Bundle, BundleError, Category, write_file_atomic, write_json_atomic};
use dm_eval::lpips::Lpips;
use dm_eval::report::{COLUMNS, cell};
use dm_eval::{EvalError, EvalOptions, SplitMetrics, evaluate};
use dm_fit::material_fit::FitError;
use dm_fit::run::{FitOptions, FitOutcome, run_fit};
use dm_model::ModelError;
use dm_mpm::SimError;
use dm_synth::{Action, EffectSpec, Preset, SynthConfig, SynthError, TRUTH_VERSION, TruthFile};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub const SUITE_JSON: &str = "suite.json";
pub const TABLES_MARKDOWN: &str = "tables.md";
pub const RESULT_JSON: &str = "result.json";
/// The markers of the generated section in docs/RESULTS.md.
pub const SECTION_BEGIN: &str = "<!-- dm-eval suite: begin (generated; reruns replace it) -->";
pub const SECTION_END: &str = "<!-- dm-eval suite: end -->";

/// The section markers of the tables under `heading`: the benchmark
/// suite's are [`SECTION_BEGIN`] / [`SECTION_END`], any other suite's name
/// its heading so several suites share one document.
fn section_markers(heading: &str) -> (String, String) {
    if heading == DEFAULT_RESULTS_HEADING {
        (SECTION_BEGIN.to_owned(), SECTION_END.to_owned())
    } else {
        let name = heading.trim_start_matches('#').trim();
        (
            format!("<!-- dm-eval suite \"{name}\": begin (generated; reruns replace it) -->"),
            format!("<!-- dm-eval suite \"{name}\": end -->"),
        )
    }
}

/// Why the suite could not run (a diverged fit or rollout is not an error:
/// it is recorded in the results).
#[derive(Debug, thiserror::Error)]
pub enum SuiteError {
    #[error(transparent)]
    File(#[from] BundleError),
    #[error("scene {scene}: {source}")]
    Synth { scene: String, source: SynthError },
    #[error("scene {scene}, variant {variant}: fitting: {source}")]
    Fit {
        scene: String,
        variant: String,
        source: Box<FitError>,
    },
    #[error("scene {scene}, variant {variant}: evaluating: {source}")]
    Eval {
        scene: String,
        variant: String,
        source: Box<EvalError>,
    },
}

/// The suite file (`benchmarks/suite.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SuiteFile {
    /// What the suite is for (shown in the tables).
    #[serde(default)]
    pub description: String,
    /// The recording of every scene.
    pub recording: Recording,
    pub scenes: Vec<SceneSpec>,
    /// `dm-fit` flags shared by every variant (before the variant's own).
    #[serde(default)]
    pub fit_args: Vec<String>,
    pub variants: Vec<VariantSpec>,
    /// Camera of the image metrics (the protocol's camera 0).
    #[serde(default)]
    pub camera: usize,
    /// The heading of the section `--results-md` replaces (or appends).
    #[serde(default = "default_results_heading")]
    pub results_heading: String,
}

/// The benchmark suite's section in docs/RESULTS.md.
pub const DEFAULT_RESULTS_HEADING: &str = "## Benchmark suite";

fn default_results_heading() -> String {
    DEFAULT_RESULTS_HEADING.to_owned()
}

/// `dm-synth`'s recording options shared by the scenes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recording {
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub truth_particles: usize,
    pub tracks: usize,
    pub bundle_particles: usize,
    /// Physics engine of the scenes' truth (`dm-synth --engine`; absent: mpm).
    #[serde(default)]
    pub engine: dm_synth::Engine,
}

/// One synthetic scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    pub preset: Preset,
    pub seed: u64,
    pub action: Action,
    #[serde(default)]
    pub two_hands: bool,
    /// Hidden effect, `NAME[:MAGNITUDE]` as `dm-synth --effect`.
    #[serde(default)]
    pub effect: Option<String>,
}

/// One `dm-fit` variant: a name (a table row) and its flags.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VariantSpec {
    pub name: String,
    #[serde(default)]
    pub fit_args: Vec<String>,
}

/// A scene ready to synthesise.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedScene {
    /// `PRESET-sSEED-ACTION` (plus `-EFFECT`, `-2h`): directory and row name.
    pub id: String,
    pub category: Category,
    pub config: SynthConfig,
}

/// A variant with its parsed fit options.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedVariant {
    pub name: String,
    /// The flags as given (shared ones first).
    pub fit_args: Vec<String>,
    pub options: FitOptions,
}

/// A validated suite file.
#[derive(Clone, Debug, PartialEq)]
pub struct Suite {
    pub path: PathBuf,
    pub file: SuiteFile,
    pub scenes: Vec<PlannedScene>,
    pub variants: Vec<PlannedVariant>,
}

/// `dm-fit`'s option parser, so a variant's flags mean what they mean on
/// the command line.
#[derive(Parser, Debug)]
#[command(name = "dm-fit", no_binary_name = true)]
struct FitFlags {
    #[command(flatten)]
    options: FitOptions,
}

/// Parses `dm-fit` flags (as on its command line, without the bundle and
/// `--out`) into its options.
pub fn parse_fit_args(args: &[String]) -> Result<FitOptions, String> {
    FitFlags::try_parse_from(args)
        .map(|flags| flags.options)
        .map_err(|e| {
            // clap's first line is the message; the rest is usage help.
            let text = e.to_string();
            let first = text.lines().next().unwrap_or("").trim();
            first.strip_prefix("error: ").unwrap_or(first).to_owned()
        })
}

fn category_name(category: Category) -> &'static str {
    match category {
        Category::Linear => "linear",
        Category::Planar => "planar",
        Category::Volumetric => "volumetric",
    }
}

impl Suite {
    /// Reads and checks a suite file; every error names the file and field.
    pub fn load(path: &Path) -> Result<Self, SuiteError> {
        let file: SuiteFile = dm_bundle::read_json(path)?;
        let bad = |field: String, problem: String| {
            SuiteError::File(BundleError::new(path, field, problem))
        };
        if file.scenes.is_empty() {
            return Err(bad("scenes".into(), "lists no scene".into()));
        }
        if file.variants.is_empty() {
            return Err(bad("variants".into(), "lists no variant".into()));
        }
        let mut scenes: Vec<PlannedScene> = Vec::new();
        for (i, spec) in file.scenes.iter().enumerate() {
            let effect = match &spec.effect {
                Some(text) => Some(
                    text.parse::<EffectSpec>()
                        .map_err(|e| bad(format!("scenes[{i}].effect"), e.to_string()))?,
                ),
                None => None,
            };
            let r = &file.recording;
            let config = SynthConfig {
                action: Some(spec.action),
                two_hands: spec.two_hands,
                effect,
                frames: r.frames,
                width: r.width,
                height: r.height,
                truth_particles: r.truth_particles,
                tracks: r.tracks,
                bundle_particles: r.bundle_particles,
                engine: r.engine,
                ..SynthConfig::new(spec.preset, spec.seed)
            };
            config
                .validate()
                .map_err(|e| bad("recording".into(), e.to_string()))?;
            let action = format!("{:?}", spec.action).to_lowercase();
            let mut id = format!("{}-s{}-{action}", spec.preset.name(), spec.seed);
            if let Some(effect) = &spec.effect {
                id.push('-');
                id.push_str(&effect.replace([':', '.'], "_"));
            }
            if spec.two_hands {
                id.push_str("-2h");
            }
            if scenes.iter().any(|s| s.id == id) {
                return Err(bad(
                    format!("scenes[{i}]"),
                    format!("scene `{id}` is listed twice"),
                ));
            }
            scenes.push(PlannedScene {
                id,
                category: spec.preset.category(),
                config,
            });
        }
        let mut variants: Vec<PlannedVariant> = Vec::new();
        parse_fit_args(&file.fit_args).map_err(|e| bad("fit_args".into(), e))?;
        for (i, spec) in file.variants.iter().enumerate() {
            let name_ok = !spec.name.is_empty()
                && spec
                    .name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
            if !name_ok {
                return Err(bad(
                    format!("variants[{i}].name"),
                    format!("`{}` must be letters, digits, `_` or `-`", spec.name),
                ));
            }
            if variants.iter().any(|v| v.name == spec.name) {
                return Err(bad(
                    format!("variants[{i}].name"),
                    format!("variant `{}` is listed twice", spec.name),
                ));
            }
            let fit_args: Vec<String> = file
                .fit_args
                .iter()
                .chain(&spec.fit_args)
                .cloned()
                .collect();
            let options =
                parse_fit_args(&fit_args).map_err(|e| bad(format!("variants[{i}].fit_args"), e))?;
            variants.push(PlannedVariant {
                name: spec.name.clone(),
                fit_args,
                options,
            });
        }
        Ok(Self {
            path: path.to_path_buf(),
            file,
            scenes,
            variants,
        })
    }
}

/// How one (scene, variant) run ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunStatus {
    Ok,
    /// The fit or the evaluation rollout diverged (NaN, det F ≤ 0).
    Diverged,
}

/// `DIR/runs/SCENE/VARIANT/result.json` and one entry of `suite.json`'s
/// `runs`. The inputs are stored so a cached result is reused only for the
/// same scene, fit options, camera and LPIPS choice.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunResult {
    pub scene: String,
    pub category: Category,
    pub variant: String,
    pub status: RunStatus,
    /// Where it diverged and the simulator's message.
    pub diverged: Option<String>,
    pub train: Option<SplitMetrics>,
    pub test: Option<SplitMetrics>,
    pub fit_seconds: f64,
    pub eval_seconds: f64,
    pub synth: SynthConfig,
    /// dm-synth's [`TRUTH_VERSION`] of the scene (absent: 1).
    #[serde(default = "dm_synth::first_truth_version")]
    pub truth_version: u32,
    pub fit: FitOptions,
    pub camera: usize,
    pub lpips: bool,
}

impl RunResult {
    fn same_inputs(&self, other: &RunResult) -> bool {
        self.synth == other.synth
            && self.truth_version == other.truth_version
            && self.fit == other.fit
            && self.camera == other.camera
            && self.lpips == other.lpips
    }
}

/// A table row: one variant over a group of scenes.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VariantSummary {
    pub variant: String,
    /// Runs in the group (finished or diverged).
    pub runs: usize,
    pub diverged: usize,
    /// Means over the runs that did not diverge (`None`: all diverged).
    pub test: Option<SplitMetrics>,
    pub train: Option<SplitMetrics>,
}

/// One table: all scenes, or one category.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GroupTable {
    /// `all`, `linear`, `planar` or `volumetric`.
    pub group: String,
    pub scenes: Vec<String>,
    pub rows: Vec<VariantSummary>,
}

/// `DIR/suite.json` (keys documented in docs/suite.md).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SuiteReport {
    pub suite: String,
    pub command: String,
    pub scenes: Vec<SceneRecord>,
    pub variants: Vec<VariantRecord>,
    pub runs: Vec<RunResult>,
    pub tables: Vec<GroupTable>,
    /// Runs taken from the cache of an earlier invocation.
    pub cached_runs: usize,
    pub seconds: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SceneRecord {
    pub id: String,
    pub category: Category,
    pub config: SynthConfig,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VariantRecord {
    pub name: String,
    pub fit_args: Vec<String>,
}

/// What the suite is doing, for a progress bar.
#[derive(Clone, Copy, Debug)]
pub enum SuiteProgress<'a> {
    /// Synthesising scene `index` of `total`.
    Scene {
        id: &'a str,
        index: usize,
        total: usize,
    },
    /// Run `index` of `total` started (`cached`: its result is reused).
    Run {
        scene: &'a str,
        variant: &'a str,
        index: usize,
        total: usize,
        cached: bool,
    },
    /// A line from the fit or the evaluation of the current run.
    Detail(&'a str),
}

/// The simulator's divergence inside a fit or evaluation error, if that is
/// what stopped it.
fn divergence_of_fit(error: &FitError) -> Option<&SimError> {
    match error {
        FitError::Simulation(e @ SimError::Diverged { .. })
        | FitError::Model(ModelError::Simulation(e @ SimError::Diverged { .. })) => Some(e),
        _ => None,
    }
}

fn divergence_of_eval(error: &EvalError) -> Option<&SimError> {
    match error {
        EvalError::Model(ModelError::Simulation(e @ SimError::Diverged { .. })) => Some(e),
        _ => None,
    }
}

fn io_error(path: &Path, action: &str, e: &std::io::Error) -> SuiteError {
    SuiteError::File(BundleError::io(path, action, e))
}

fn remove_dir_if_present(dir: &Path) -> Result<(), SuiteError> {
    match std::fs::remove_dir_all(dir) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io_error(dir, "removing", &e)),
        _ => Ok(()),
    }
}

/// The scene's bundle under `out/scenes/ID/`, synthesised unless a complete
/// one with the same configuration is there (the truth file is written
/// last, so its presence means the bundle is complete).
fn scene_bundle(
    scene: &PlannedScene,
    out: &Path,
    progress: &mut dyn FnMut(SuiteProgress<'_>),
) -> Result<Bundle, SuiteError> {
    let dir = out.join("scenes").join(&scene.id);
    let bundle_dir = dir.join("bundle");
    let truth_path = dir.join("truth.json");
    let cached = truth_path.is_file()
        && dm_bundle::read_json::<TruthFile>(&truth_path)
            .is_ok_and(|t| t.config == scene.config && t.is_current());
    if !cached {
        remove_dir_if_present(&dir)?;
        std::fs::create_dir_all(&dir).map_err(|e| io_error(&dir, "creating", &e))?;
        let mut detail = |stage: &str, done: usize, total: usize| {
            progress(SuiteProgress::Detail(&format!(
                "{}: {stage} {done}/{total}",
                scene.id
            )))
        };
        dm_synth::generate(&scene.config, &bundle_dir, &truth_path, &mut detail).map_err(
            |source| SuiteError::Synth {
                scene: scene.id.clone(),
                source,
            },
        )?;
    }
    Ok(Bundle::open(&bundle_dir)?)
}

/// Fits and scores one (scene, variant); a divergence becomes a
/// `diverged` result. The fit resumes from its checkpoint when interrupted.
fn run_one(
    scene: &PlannedScene,
    variant: &PlannedVariant,
    bundle: &Bundle,
    run_dir: &Path,
    mut template: RunResult,
    lpips: Option<&mut Lpips>,
    progress: &mut dyn FnMut(SuiteProgress<'_>),
) -> Result<RunResult, SuiteError> {
    let model_dir = run_dir.join("model");
    let fit_error = |source: FitError| SuiteError::Fit {
        scene: scene.id.clone(),
        variant: variant.name.clone(),
        source: Box::new(source),
    };
    let clock = Instant::now();
    let mut fit = |resume: bool| {
        run_fit(
            bundle,
            &variant.options,
            &model_dir,
            resume,
            None,
            &mut |line| progress(SuiteProgress::Detail(line)),
        )
    };
    let outcome = match fit(true) {
        // A checkpoint of other options (the suite file changed): start over.
        Err(FitError::InvalidOption { option, .. }) if option == "--resume" => {
            remove_dir_if_present(&model_dir)?;
            fit(false)
        }
        other => other,
    };
    template.fit_seconds = clock.elapsed().as_secs_f64();
    let model = match outcome {
        Ok(FitOutcome::Finished(_)) => dm_model::WorldModel::load(&model_dir.join("model.json"))
            .map_err(|e| fit_error(e.into()))?,
        Ok(FitOutcome::Paused { .. }) => unreachable!("run_fit pauses only with stop_after"),
        Err(e) => {
            return match divergence_of_fit(&e) {
                Some(sim) => Ok(RunResult {
                    status: RunStatus::Diverged,
                    diverged: Some(format!("fit: {sim}")),
                    ..template
                }),
                None => Err(fit_error(e)),
            };
        }
    };
    let clock = Instant::now();
    let options = EvalOptions {
        camera: template.camera,
        frames: None,
        splats: None,
        device: variant.options.device,
    };
    let evaluation = evaluate(&model, bundle, &options, lpips, &mut |stage, t| {
        progress(SuiteProgress::Detail(&format!("evaluating: {stage} {t}")))
    });
    template.eval_seconds = clock.elapsed().as_secs_f64();
    match evaluation {
        Ok(evaluation) => Ok(RunResult {
            status: RunStatus::Ok,
            train: Some(evaluation.metrics.train),
            test: Some(evaluation.metrics.test),
            ..template
        }),
        Err(e) => match divergence_of_eval(&e) {
            Some(sim) => Ok(RunResult {
                status: RunStatus::Diverged,
                diverged: Some(format!("rollout: {sim}")),
                ..template
            }),
            None => Err(SuiteError::Eval {
                scene: scene.id.clone(),
                variant: variant.name.clone(),
                source: Box::new(e),
            }),
        },
    }
}

/// Runs the whole suite into `out` (resuming from its cache), then writes
/// `suite.json` and `tables.md`. `command` is recorded with the tables.
pub fn run_suite(
    suite: &Suite,
    out: &Path,
    mut lpips: Option<&mut Lpips>,
    command: &str,
    progress: &mut dyn FnMut(SuiteProgress<'_>),
) -> Result<SuiteReport, SuiteError> {
    let clock = Instant::now();
    std::fs::create_dir_all(out).map_err(|e| io_error(out, "creating", &e))?;
    let total = suite.scenes.len() * suite.variants.len();
    let mut runs = Vec::with_capacity(total);
    let mut cached_runs = 0;
    for (s, scene) in suite.scenes.iter().enumerate() {
        progress(SuiteProgress::Scene {
            id: &scene.id,
            index: s,
            total: suite.scenes.len(),
        });
        let bundle = scene_bundle(scene, out, progress)?;
        for (v, variant) in suite.variants.iter().enumerate() {
            let run_dir = out.join("runs").join(&scene.id).join(&variant.name);
            let result_path = run_dir.join(RESULT_JSON);
            let template = RunResult {
                scene: scene.id.clone(),
                category: scene.category,
                variant: variant.name.clone(),
                status: RunStatus::Ok,
                diverged: None,
                train: None,
                test: None,
                fit_seconds: 0.0,
                eval_seconds: 0.0,
                synth: scene.config.clone(),
                truth_version: TRUTH_VERSION,
                fit: variant.options.clone(),
                camera: suite.file.camera,
                lpips: lpips.is_some(),
            };
            let cached = result_path
                .is_file()
                .then(|| dm_bundle::read_json::<RunResult>(&result_path).ok())
                .flatten()
                .filter(|r| r.same_inputs(&template));
            progress(SuiteProgress::Run {
                scene: &scene.id,
                variant: &variant.name,
                index: s * suite.variants.len() + v,
                total,
                cached: cached.is_some(),
            });
            let result = match cached {
                Some(result) => {
                    cached_runs += 1;
                    result
                }
                None => {
                    std::fs::create_dir_all(&run_dir)
                        .map_err(|e| io_error(&run_dir, "creating", &e))?;
                    let result = run_one(
                        scene,
                        variant,
                        &bundle,
                        &run_dir,
                        template,
                        lpips.as_deref_mut(),
                        progress,
                    )?;
                    write_json_atomic(&result_path, &result)?;
                    result
                }
            };
            runs.push(result);
        }
    }
    let report = SuiteReport {
        suite: suite.path.display().to_string(),
        command: command.to_owned(),
        scenes: suite
            .scenes
            .iter()
            .map(|s| SceneRecord {
                id: s.id.clone(),
                category: s.category,
                config: s.config.clone(),
            })
            .collect(),
        variants: suite
            .variants
            .iter()
            .map(|v| VariantRecord {
                name: v.name.clone(),
                fit_args: v.fit_args.clone(),
            })
            .collect(),
        tables: tables(suite, &runs),
        runs,
        cached_runs,
        seconds: clock.elapsed().as_secs_f64(),
    };
    write_file_atomic(&out.join(TABLES_MARKDOWN), |temp| {
        std::fs::write(temp, tables_markdown(&report))
    })?;
    write_json_atomic(&out.join(SUITE_JSON), &report)?;
    Ok(report)
}

/// Mean of the finite values (NaN when none).
fn finite_mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, count) = values
        .filter(|v| v.is_finite())
        .fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    }
}

/// Per-metric means over scenes (each scene's split mean counts once).
fn mean_of(splits: &[&SplitMetrics]) -> Option<SplitMetrics> {
    if splits.is_empty() {
        return None;
    }
    let column = |f: fn(&SplitMetrics) -> f64| finite_mean(splits.iter().map(|s| f(s)));
    let lpips_computed = splits.iter().all(|s| s.lpips.is_some());
    Some(SplitMetrics {
        chamfer: column(|s| s.chamfer),
        track: column(|s| s.track),
        iou: column(|s| s.iou),
        psnr: column(|s| s.psnr),
        ssim: column(|s| s.ssim),
        lpips: lpips_computed.then(|| column(|s| s.lpips.unwrap_or(f64::NAN))),
    })
}

/// Which scenes a table averages over.
#[derive(Clone, Debug, PartialEq)]
enum GroupKey {
    All,
    Category(Category),
    /// Scenes hiding this effect (`None`: scenes without one).
    Effect(Option<&'static str>),
}

impl GroupKey {
    fn admits(&self, category: Category, synth: &SynthConfig) -> bool {
        match self {
            GroupKey::All => true,
            GroupKey::Category(wanted) => *wanted == category,
            GroupKey::Effect(wanted) => synth.effect.map(|e| e.name.name()) == *wanted,
        }
    }
}

/// The overall table, then one per category present (in the order linear,
/// planar, volumetric), then — when any scene hides an effect — one per
/// hidden effect and one for the scenes without (the residual ablation
/// compares variants on each).
pub fn tables(suite: &Suite, runs: &[RunResult]) -> Vec<GroupTable> {
    let mut groups: Vec<(String, GroupKey)> = vec![("all".into(), GroupKey::All)];
    for category in [Category::Linear, Category::Planar, Category::Volumetric] {
        if suite.scenes.iter().any(|s| s.category == category) {
            groups.push((category_name(category).into(), GroupKey::Category(category)));
        }
    }
    if suite.scenes.iter().any(|s| s.config.effect.is_some()) {
        let mut effects: Vec<Option<&'static str>> = Vec::new();
        for scene in &suite.scenes {
            let effect = scene.config.effect.map(|e| e.name.name());
            if !effects.contains(&effect) {
                effects.push(effect);
            }
        }
        // Effects in suite order, the scenes without one last.
        effects.sort_by_key(|e| e.is_none());
        for effect in effects {
            let name = effect.map_or("no hidden effect".to_owned(), |e| {
                format!("hidden effect {e}")
            });
            groups.push((name, GroupKey::Effect(effect)));
        }
    }
    groups
        .into_iter()
        .map(|(group, key)| {
            let rows = suite
                .variants
                .iter()
                .map(|variant| {
                    let runs: Vec<&RunResult> = runs
                        .iter()
                        .filter(|r| r.variant == variant.name && key.admits(r.category, &r.synth))
                        .collect();
                    let finished = |split: fn(&RunResult) -> Option<&SplitMetrics>| {
                        mean_of(&runs.iter().filter_map(|r| split(r)).collect::<Vec<_>>())
                    };
                    VariantSummary {
                        variant: variant.name.clone(),
                        runs: runs.len(),
                        diverged: runs
                            .iter()
                            .filter(|r| r.status == RunStatus::Diverged)
                            .count(),
                        test: finished(|r| r.test.as_ref()),
                        train: finished(|r| r.train.as_ref()),
                    }
                })
                .collect();
            GroupTable {
                group,
                scenes: suite
                    .scenes
                    .iter()
                    .filter(|s| key.admits(s.category, &s.config))
                    .map(|s| s.id.clone())
                    .collect(),
                rows,
            }
        })
        .collect()
}

/// The tables in the paper's layout (method.md §9): rows = variants,
/// columns = IoU, Chamfer, Track, PSNR, SSIM, LPIPS on the test split
/// (future prediction; the paper shows no train columns), plus the count of
/// diverged runs. A variant whose runs all diverged shows `diverged`.
pub fn tables_markdown(report: &SuiteReport) -> String {
    let mut md = String::new();
    let any_diverged = report.runs.iter().any(|r| r.status == RunStatus::Diverged);
    for table in &report.tables {
        let title = match table.group.as_str() {
            "all" => "All scenes".to_owned(),
            group => format!("{}{}", group[..1].to_uppercase(), &group[1..]),
        };
        let _ = writeln!(
            md,
            "**{title}** ({} scene{}: {}), test split:\n",
            table.scenes.len(),
            if table.scenes.len() == 1 { "" } else { "s" },
            table.scenes.join(", ")
        );
        let _ = write!(md, "| variant |");
        for c in &COLUMNS {
            let _ = write!(md, " {} |", c.heading);
        }
        let _ = writeln!(md, " diverged |");
        let _ = write!(md, "|---|");
        for _ in &COLUMNS {
            let _ = write!(md, "---:|");
        }
        let _ = writeln!(md, "---:|");
        for row in &table.rows {
            let _ = write!(md, "| {} |", row.variant);
            for c in &COLUMNS {
                let value = match &row.test {
                    Some(test) => cell((c.split)(test), c.digits),
                    None => "diverged".into(),
                };
                let _ = write!(md, " {value} |");
            }
            let mark = if row.diverged > 0 { "¹" } else { "" };
            let _ = writeln!(md, " {}/{}{mark} |", row.diverged, row.runs);
        }
        md.push('\n');
    }
    if any_diverged {
        let _ = writeln!(
            md,
            "¹ Diverged runs (the fit or the rollout hit NaN or det F ≤ 0) are counted, not averaged: the metrics are means over the runs that finished, as the paper reports its diverging ablation.\n"
        );
        for run in report
            .runs
            .iter()
            .filter(|r| r.status == RunStatus::Diverged)
        {
            let _ = writeln!(
                md,
                "- {} / {}: {}",
                run.scene,
                run.variant,
                run.diverged.as_deref().unwrap_or("diverged")
            );
        }
        md.push('\n');
    }
    let _ = writeln!(
        md,
        "Means over scenes of each scene's test-split mean (Chamfer and Track in metres; `–`: undefined or not computed). Variants' `dm-fit` flags:\n"
    );
    for variant in &report.variants {
        let _ = writeln!(md, "- `{}`: `{}`", variant.name, variant.fit_args.join(" "));
    }
    let _ = writeln!(
        md,
        "\nSuite `{}`, {} runs ({} from the cache of an earlier invocation):\n\n    {}",
        report.suite,
        report.runs.len(),
        report.cached_runs,
        report.command
    );
    md
}

/// `document` with the text between [`SECTION_BEGIN`] and [`SECTION_END`]
/// replaced by `body` (the markers kept); without markers the section is
/// appended under `heading`. `path` names the document in errors.
pub fn replace_marked_section(
    document: &str,
    body: &str,
    heading: &str,
    path: &Path,
) -> Result<String, BundleError> {
    let (begin_marker, end_marker) = section_markers(heading);
    let section = format!("{begin_marker}\n\n{}\n{end_marker}", body.trim_end());
    match (document.find(&begin_marker), document.find(&end_marker)) {
        (Some(begin), Some(end)) if begin < end => Ok(format!(
            "{}{section}{}",
            &document[..begin],
            &document[end + end_marker.len()..]
        )),
        (None, None) => Ok(format!(
            "{}\n\n{heading}\n\n{section}\n",
            document.trim_end()
        )),
        _ => Err(BundleError::new(
            path,
            "(suite section markers)",
            format!("needs `{begin_marker}` followed by `{end_marker}`, each once"),
        )),
    }
}

/// Writes the tables into `results_md` between the markers (atomically).
pub fn update_results_markdown(
    results_md: &Path,
    heading: &str,
    tables: &str,
) -> Result<(), BundleError> {
    let document = match std::fs::read_to_string(results_md) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
        Err(e) => return Err(BundleError::io(results_md, "reading", &e)),
    };
    let updated = replace_marked_section(&document, tables, heading, results_md)?;
    write_file_atomic(results_md, |temp| std::fs::write(temp, &updated))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every suite file committed under benchmarks/ parses and plans, so a
    /// long benchmark is not first found broken when someone runs it.
    #[test]
    fn every_committed_suite_file_loads() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../benchmarks");
        let mut loaded = 0;
        for entry in std::fs::read_dir(&dir).expect("benchmarks/") {
            let path = entry.expect("entry").path();
            if path.extension().is_some_and(|e| e == "json") {
                let suite = Suite::load(&path).unwrap_or_else(|e| panic!("{e}"));
                assert!(!suite.scenes.is_empty() && !suite.variants.is_empty());
                loaded += 1;
            }
        }
        assert!(loaded >= 3, "{loaded} suite files");
        let foreign = Suite::load(&dir.join("foreign.json")).expect("foreign suite");
        assert!(
            foreign
                .scenes
                .iter()
                .all(|s| s.config.engine == dm_synth::Engine::Mujoco)
        );
    }

    #[test]
    fn marked_section_is_replaced_and_appended_once() {
        let path = Path::new("RESULTS.md");
        let suite = DEFAULT_RESULTS_HEADING;
        let first =
            replace_marked_section("# Results\n", "table 1\n", suite, path).expect("appends");
        assert!(first.contains(suite) && first.contains("table 1"));
        let second =
            replace_marked_section(&format!("{first}\n## After\n"), "table 2", suite, path)
                .expect("replaces");
        assert!(second.contains("table 2") && !second.contains("table 1"));
        assert_eq!(second.matches(SECTION_BEGIN).count(), 1);
        assert_eq!(second.matches(suite).count(), 1);
        assert!(
            second.contains("## After"),
            "text after the section is kept"
        );
        // Another suite's section (its own heading and markers) sits beside it.
        let ablation = "## Residual ablation";
        let third = replace_marked_section(&second, "ablation 1", ablation, path).expect("appends");
        let fourth =
            replace_marked_section(&third, "ablation 2", ablation, path).expect("replaces");
        assert!(fourth.contains("table 2") && fourth.contains("ablation 2"));
        assert!(!fourth.contains("ablation 1"));
        assert_eq!(fourth.matches(ablation).count(), 1);
        let broken = replace_marked_section(SECTION_END, "x", suite, path)
            .expect_err("an end marker without a begin marker is an error");
        assert!(broken.to_string().contains("RESULTS.md"), "{broken}");
    }

    #[test]
    fn diverged_runs_are_counted_and_marked_not_averaged() {
        let config = SynthConfig::tiny(Preset::Toy, 1);
        // toy-b hides an effect: the tables add one group per hidden
        // effect and one for the scenes without.
        let drag_config = SynthConfig {
            effect: Some("air_drag".parse().expect("effect")),
            ..config.clone()
        };
        let config_of = |scene: &str| {
            if scene == "toy-b" {
                drag_config.clone()
            } else {
                config.clone()
            }
        };
        let variant = |name: &str, args: &[&str]| {
            let fit_args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
            PlannedVariant {
                name: name.into(),
                options: parse_fit_args(&fit_args).expect("valid flags"),
                fit_args,
            }
        };
        let suite = Suite {
            path: "suite.json".into(),
            file: SuiteFile {
                description: String::new(),
                recording: Recording {
                    frames: 14,
                    width: 48,
                    height: 36,
                    truth_particles: 2000,
                    tracks: 60,
                    bundle_particles: 800,
                    engine: dm_synth::Engine::Mpm,
                },
                scenes: Vec::new(),
                fit_args: Vec::new(),
                variants: Vec::new(),
                camera: 0,
                results_heading: default_results_heading(),
            },
            scenes: ["toy-a", "toy-b"]
                .map(|id| PlannedScene {
                    id: id.into(),
                    category: Category::Volumetric,
                    config: config_of(id),
                })
                .to_vec(),
            variants: vec![
                variant("full", &[]),
                variant("rigid", &["--actuators", "rigid"]),
            ],
        };
        let metrics = |chamfer: f64| SplitMetrics {
            chamfer,
            track: 0.02,
            iou: 0.5,
            psnr: 20.0,
            ssim: 0.9,
            lpips: None,
        };
        let run = |scene: &str, variant: &PlannedVariant, chamfer: Option<f64>| RunResult {
            scene: scene.into(),
            category: Category::Volumetric,
            variant: variant.name.clone(),
            status: if chamfer.is_some() {
                RunStatus::Ok
            } else {
                RunStatus::Diverged
            },
            diverged: chamfer
                .is_none()
                .then(|| "fit: simulation diverged".to_owned()),
            train: chamfer.map(metrics),
            test: chamfer.map(metrics),
            fit_seconds: 1.0,
            eval_seconds: 1.0,
            synth: config_of(scene),
            truth_version: TRUTH_VERSION,
            fit: variant.options.clone(),
            camera: 0,
            lpips: false,
        };
        let (full, rigid) = (&suite.variants[0], &suite.variants[1]);
        let runs = vec![
            run("toy-a", full, Some(0.01)),
            run("toy-a", rigid, None),
            run("toy-b", full, None),
            run("toy-b", rigid, None),
        ];
        let tables = tables(&suite, &runs);
        let groups: Vec<&str> = tables.iter().map(|t| t.group.as_str()).collect();
        assert_eq!(
            groups,
            [
                "all",
                "volumetric",
                "hidden effect air_drag",
                "no hidden effect"
            ]
        );
        assert_eq!(tables[2].scenes, ["toy-b"]);
        assert!(tables[2].rows[0].test.is_none(), "toy-b / full diverged");
        assert_eq!(
            tables[3].rows[0].test.as_ref().map(|t| t.chamfer),
            Some(0.01)
        );
        let full_row = &tables[0].rows[0];
        assert_eq!((full_row.runs, full_row.diverged), (2, 1));
        assert_eq!(
            full_row.test.as_ref().map(|t| t.chamfer),
            Some(0.01),
            "the diverged run is not averaged"
        );
        assert!(tables[0].rows[1].test.is_none(), "all rigid runs diverged");
        let report = SuiteReport {
            suite: "suite.json".into(),
            command: "dm-eval --suite suite.json --out x".into(),
            scenes: Vec::new(),
            variants: Vec::new(),
            runs,
            tables,
            cached_runs: 0,
            seconds: 0.0,
        };
        let md = tables_markdown(&report);
        assert!(
            md.contains("| full | 0.500 | 0.0100 | 0.0200 | 20.00 | 0.900 | – | 1/2¹ |"),
            "{md}"
        );
        assert!(
            md.contains(
                "| rigid | diverged | diverged | diverged | diverged | diverged | diverged | 2/2¹ |"
            ),
            "{md}"
        );
        assert!(
            md.contains("- toy-b / full: fit: simulation diverged"),
            "{md}"
        );
    }

    #[test]
    fn only_the_simulators_divergence_counts_as_diverged() {
        let diverged = || SimError::Diverged {
            frame: 3,
            substep: 1,
            particle: 7,
            reason: "det F <= 0".into(),
        };
        assert!(divergence_of_fit(&FitError::Simulation(diverged())).is_some());
        assert!(
            divergence_of_eval(&EvalError::Model(ModelError::Simulation(diverged()))).is_some()
        );
        let invalid = SimError::InvalidInput("bad".into());
        assert!(divergence_of_fit(&FitError::Simulation(invalid)).is_none());
    }

    #[test]
    fn variant_flags_parse_like_dm_fit() {
        let options = parse_fit_args(&[
            "--residual".into(),
            "none".into(),
            "--iters".into(),
            "2".into(),
        ])
        .expect("valid flags");
        assert_eq!(options.iters, 2);
        assert_eq!(options.model.residual, dm_model::ResidualKind::None);
        let error = parse_fit_args(&["--itres".into(), "2".into()]).expect_err("unknown flag");
        assert!(error.contains("--itres"), "{error}");
    }
}
