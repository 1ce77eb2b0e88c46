//! `report.md`: the answer first, then the evidence, readable in a minute.

use crate::analysis::Rollout;
use crate::candidates::Candidate;
use crate::discover::Discovered;
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
    if let Some(found) = &d.discovered
        && found.score >= d.threshold
    {
        let _ = writeln!(
            s,
            "**Outside the library:** a body force `{}` explains {:.0} % of the training and \
             {:.0} % of the held-out track error (section \"Discovered term\").\n",
            found.formula,
            100.0 * found.train_reduction,
            100.0 * found.held_out_reduction
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
    if let Some(found) = &d.discovered {
        write_discovered(&mut s, found, d.discovered_model.as_deref());
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

/// The "Discovered term" section: the body force fitted beside the
/// library, its terms with their standard deviations and its gains.
fn write_discovered(s: &mut String, found: &Discovered, model: Option<&str>) {
    let _ = writeln!(
        s,
        "## Discovered term
"
    );
    let _ = writeln!(
        s,
        "A body force on every grid node with mass (a push, a drag along each world axis, a \
         spring towards {:?} m) regressed on the simulator's response over the training frames \
         with the material held; terms moving the tracks by under {} mm or under {:.0} % of the \
         largest term dropped ({} round(s)), then each checked on the training split's last \
         quarter, then learnt with the material through the adjoint ({} steps).\n",
        found.fitted_about_m.map(|c| (c * 1e3).round() / 1e3),
        1e3 * crate::discover::MIN_TERM_EFFECT_M,
        100.0 * crate::discover::RELATIVE_TERM_EFFECT,
        found.rounds,
        found.adjoint_iterations
    );
    if found.terms.is_empty() {
        let _ = writeln!(s, "No term cleared the thresholds: nothing found.\n");
        return;
    }
    let _ = writeln!(s, "`{}`\n", found.formula);
    let _ = writeln!(s, "| term | coefficient | ± std |");
    let _ = writeln!(s, "|---|---|---|");
    for t in &found.terms {
        let std = t.std.map_or("—".into(), |v| format!("{v:.3} {}", t.unit));
        let _ = writeln!(
            s,
            "| {} | {:.3} {} | {} |",
            t.name, t.coefficient, t.unit, std
        );
    }
    let _ = writeln!(s);
    if let Some(f) = &found.force {
        let _ = writeln!(
            s,
            "As a force field: {:.3} m/s² towards ({:.2}, {:.2}, {:.2}){}.\n",
            f.magnitude_m_s2,
            f.direction[0],
            f.direction[1],
            f.direction[2],
            match (f.magnitude_std_m_s2, f.direction_std_deg) {
                (Some(m), Some(a)) => format!(" (± {m:.3} m/s², ± {a:.1}°)"),
                _ => String::new(),
            }
        );
    }
    if let Some(spring) = &found.spring {
        let p = spring.point_m;
        let _ = writeln!(
            s,
            "As a spring: κ = {:.2} /s² towards ({:.3}, {:.3}, {:.3}) m.\n",
            spring.stiffness_per_s2, p[0], p[1], p[2]
        );
    }
    let _ = writeln!(
        s,
        "Held-out track {} → {} ({:+.0} %); training {:+.0} %; the adjoint steps with the \
         material {}. Model: `{}`. Dropped: {}.\n",
        mm(found.track_test_before),
        mm(found.track_test_after),
        -100.0 * found.held_out_reduction,
        -100.0 * found.train_reduction,
        if found.material_refit_kept {
            "kept"
        } else {
            "not kept"
        },
        model.unwrap_or("—"),
        if found.dropped.is_empty() {
            "none".into()
        } else {
            found.dropped.join(", ")
        }
    );
}
