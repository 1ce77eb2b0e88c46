//! `dm-fit`: learn a scene's world model from its bundle (stages 1–2).

use anyhow::{Context, Result};
use clap::Parser;
use dm_bundle::Bundle;
use dm_fit::run::{FitOptions, FitOutcome, run_fit};
use indicatif::ProgressBar;
use std::path::PathBuf;
use std::time::Duration;

#[derive(Parser, Debug)]
#[command(name = "dm-fit", about = "Fit a world model to a scene bundle")]
struct Cli {
    /// Scene bundle directory.
    bundle: PathBuf,
    /// Model directory (created; holds checkpoints, the model and the report).
    #[arg(long)]
    out: PathBuf,
    /// Continue from OUT/checkpoint.json after an interruption.
    #[arg(long)]
    resume: bool,
    /// Pause after this many steps (time-boxed runs; continue with --resume).
    #[arg(long)]
    stop_after: Option<usize>,
    #[command(flatten)]
    options: FitOptions,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let bundle = Bundle::open(&cli.bundle)
        .with_context(|| format!("reading bundle {}", cli.bundle.display()))?;
    let spinner = ProgressBar::new_spinner();
    spinner.enable_steady_tick(Duration::from_millis(200));
    let outcome = run_fit(
        &bundle,
        &cli.options,
        &cli.out,
        cli.resume,
        cli.stop_after,
        &mut |message| {
            // A hidden spinner (stderr not a terminal: a log) prints nothing itself.
            if spinner.is_hidden() {
                eprintln!("{message}");
            } else {
                spinner.println(message);
            }
            spinner.set_message(message.to_string());
        },
    )
    .with_context(|| {
        format!(
            "fitting {} into {}",
            cli.bundle.display(),
            cli.out.display()
        )
    })?;
    spinner.finish_and_clear();
    let report = match outcome {
        FitOutcome::Finished(report) => report,
        FitOutcome::Paused { stage, iteration } => {
            println!("dm-fit: paused at {stage:?}, iteration {iteration}; continue with --resume");
            return Ok(());
        }
    };
    println!(
        "dm-fit: E {:.3e} Pa, nu {:.3}, kp {:.3e}, kd {:.3e}, grasp radius {:.1} mm; train loss {} -> {:.3e} m² in {:.1} s",
        report.material["E_median_pa"].as_f64().unwrap_or(f64::NAN),
        report.material["nu_median"].as_f64().unwrap_or(f64::NAN),
        report.dca["kp"].as_f64().unwrap_or(f64::NAN),
        report.dca["kd"].as_f64().unwrap_or(f64::NAN),
        1e3 * report.dca["grasp_radius_m"].as_f64().unwrap_or(f64::NAN),
        report.loss["initial"]
            .as_f64()
            .map_or("-".into(), |v| format!("{v:.3e}")),
        report.loss["final"].as_f64().unwrap_or(f64::NAN),
        report.seconds
    );
    let moved = &report.material["sensitivity"];
    let percent = |key: &str| {
        moved[key]
            .as_f64()
            .map_or("diverged".into(), |v| format!("{:+.1} %", 100.0 * v))
    };
    println!(
        "  train loss with E ×0.75 / ×1.25: {} / {}; with ν −0.05 / +0.05: {} / {} (a change near 0: the clip barely constrains it)",
        percent("E_x0.75"),
        percent("E_x1.25"),
        percent("nu_minus_0.05"),
        percent("nu_plus_0.05"),
    );
    let check = &report.residual["check"];
    if let (Some(gain), Some(min_gain)) = (check["gain"].as_f64(), check["min_gain"].as_f64()) {
        let verdict = if check["kept"].as_bool() == Some(true) {
            "kept".to_string()
        } else {
            format!(
                "dropped, below the {:.0} % threshold: the model is the fit without it (--residual-min-gain 0 keeps it)",
                100.0 * min_gain
            )
        };
        println!(
            "  residual network: train Track {:+.1} % against the fit without it; {verdict}",
            -100.0 * gain
        );
    }
    if let Some(rows) = report.material["identifiability"]["parameters"].as_array() {
        let bounds: Vec<String> = rows
            .iter()
            .map(|row| {
                let name = row["name"].as_str().unwrap_or("?");
                // JSON null: the parameter moves no track (rigid actuators' gains).
                let Some(sigma) = row["std_all_estimated"].as_f64() else {
                    return format!("{name}: not moved by the tracks");
                };
                match name.strip_prefix("ln_") {
                    Some(scale) => format!("{scale} ±{:.1} %", 100.0 * sigma.exp_m1()),
                    None => format!("{name} ±{sigma:.3}"),
                }
            })
            .collect();
        println!(
            "  Cramér–Rao bound of the tracks (1σ, all estimated): {} (no unbiased fit of this clip can be tighter)",
            bounds.join(", ")
        );
    }
    println!(
        "  wrote {}/{{model.json, youngs_pa.npy, poisson.npy, expert_weights.npy, fit_report.json, loss_curve.png}}",
        cli.out.display()
    );
    Ok(())
}
