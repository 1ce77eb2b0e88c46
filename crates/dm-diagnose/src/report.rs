//! `report.md`: the answer first, then the evidence, readable in a minute.

use crate::analysis::Rollout;
use crate::candidates::Candidate;
use crate::plots::PlotFile;
use crate::{DiagnoseError, Diagnosis};
use dm_bundle::{Bundle, write_file_atomic};
use std::fmt::Write as _;
use std::path::Path;

fn mm(v: f64) -> String {
    if v.is_finite() {
        format!("{:.2} mm", 1e3 * v)
    } else {
        "—".into()
    }
}

pub(crate) fn write_report(
    out: &Path,
    d: &Diagnosis,
    plots: &[PlotFile],
    bundle: &Bundle,
    base: &Rollout,
) -> Result<(), DiagnoseError> {
    let mut s = String::new();
    let _ = writeln!(s, "# Diagnosis\n");
    let model_text = Candidate::ALL
        .iter()
        .find(|c| c.name() == d.cause)
        .map_or("", |c| c.model_text());
    if d.cause == "none" {
        let _ = writeln!(
            s,
            "**Cause: none** (confidence {:.2}). No candidate explains at least {:.0} % of the \
             held-out track error; the best explains {:.1} %.\n",
            d.confidence,
            100.0 * d.threshold,
            100.0 * d.candidates.first().map_or(0.0, |c| c.score)
        );
    } else {
        let params: Vec<String> = d
            .effect_parameters
            .iter()
            .filter(|(k, _)| !k.starts_with("axis_") && !k.starts_with("centre_"))
            .map(|(k, v)| format!("{k} = {v:.4}"))
            .collect();
        let _ = writeln!(
            s,
            "**Cause: `{}`** (confidence {:.2}) — {}; fitted {}.\n",
            d.cause,
            d.confidence,
            model_text,
            params.join(", ")
        );
        let rel = |a: f64, b: f64| 100.0 * (a - b) / a;
        let _ = writeln!(
            s,
            "Held-out (test split, frames {}–{}): track {} → {} ({:.0} % lower), Chamfer {} → {} \
             ({:.0} % lower). Extended model: `{}`.\n",
            bundle.meta.split.test[0],
            bundle.meta.split.test[1] - 1,
            mm(d.gain.track_before),
            mm(d.gain.track_after),
            rel(d.gain.track_before, d.gain.track_after),
            mm(d.gain.chamfer_before),
            mm(d.gain.chamfer_after),
            rel(d.gain.chamfer_before, d.gain.chamfer_after),
            d.extended_model.as_deref().unwrap_or("—")
        );
    }
    if let Some(t) = &d.truth {
        let _ = writeln!(
            s,
            "Truth file: hidden effect `{}` — name {}{}.\n",
            t.truth_effect,
            if t.name_correct { "correct" } else { "WRONG" },
            t.relative_error
                .map(|e| format!(", fitted parameter off by {:+.0} %", 100.0 * e))
                .unwrap_or_default()
        );
    }
    let _ = writeln!(s, "## Candidates\n");
    let how = if d.candidates_fitted {
        "Each effect's best trial (parameter chosen on the training frames with the fitted \
         model's material and gains) was then fitted from the start with the fitted model's own \
         dm-fit options (`--fit-candidates`), and that fit compared with the fitted model on the \
         training frames (train reduction) and the **held-out** test frames"
    } else {
        "Each effect was added to the fitted model (material and gains held), its parameter \
         chosen on the training frames (train reduction), and checked on the **held-out** \
         test frames"
    };
    let _ = writeln!(
        s,
        "{how}; score = the smaller of the two shares of track error removed.\n"
    );
    let _ = writeln!(
        s,
        "| candidate | score | held-out reduction | train reduction | parameters | signature |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|");
    for c in &d.candidates {
        let params: Vec<String> = c
            .parameters
            .iter()
            .filter(|(k, _)| !k.starts_with("axis_") && !k.starts_with("centre_"))
            .map(|(k, v)| format!("{k} {v:.3}"))
            .collect();
        let mark = match c.signature_agrees {
            Some(true) => " ✔",
            Some(false) => " ✘",
            None => "",
        };
        let _ = writeln!(
            s,
            "| {}{}{} | {:+.3} | {:+.3} | {:+.3} | {} | {}{} |",
            if c.name == d.cause { "**" } else { "" },
            c.name,
            if c.name == d.cause { "**" } else { "" },
            c.score,
            c.held_out_reduction,
            c.train_reduction,
            params.join(", "),
            c.signature,
            mark
        );
    }
    let _ = writeln!(s);
    for p in plots.iter().filter(|p| p.file == "candidates.png") {
        let _ = writeln!(s, "![{}]({})\n\n{}\n", p.file, p.file, p.caption);
    }
    let _ = writeln!(s, "## Where the fitted model is wrong\n");
    let _ = writeln!(s, "| region (frame-0 thirds) | test track error | points |");
    let _ = writeln!(s, "|---|---|---|");
    for r in &d.regions_test {
        let _ = writeln!(
            s,
            "| {} | {} | {} |",
            r.region,
            mm(r.mean_error_m),
            r.points
        );
    }
    let _ = writeln!(s);
    for p in plots.iter().filter(|p| p.file != "candidates.png") {
        let _ = writeln!(s, "![{}]({})\n\n{}\n", p.file, p.file, p.caption);
    }
    if base.residual_dv.is_empty() {
        let _ = writeln!(
            s,
            "The fitted model has no neural residual (physics only).\n"
        );
    }
    if let Some(r) = &d.refit {
        let _ = writeln!(
            s,
            "Refit: {} extra effect-parameter trials; {} material steps (train loss {:.3e} → \
             {:.3e}, {}). {}\n",
            r.effect_trials,
            r.material_iterations,
            r.train_loss_before,
            r.train_loss_after,
            if r.material_kept { "kept" } else { "not kept" },
            r.note
        );
    }
    let path = out.join("report.md");
    write_file_atomic(&path, |tmp| std::fs::write(tmp, s.as_bytes()))?;
    Ok(())
}
