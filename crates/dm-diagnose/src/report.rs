//! `report.md`: the answer first, then the evidence, readable in a minute.

use crate::analysis::Rollout;
use crate::candidates::Candidate;
use crate::detectability::{Limit, Stronger};
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
             track error on both the frames that chose its parameter and the validation frames \
             after them; the best explains {:.1} %.\n",
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
    if !d.detectability.is_empty() {
        let _ = writeln!(s, "{}\n", ruled_out_line(d));
    }
    if let Some(found) = &d.discovered
        && found.score >= d.threshold
    {
        let _ = writeln!(
            s,
            "**Outside the library:** a body force `{}` explains {:.0} % of the fit frames' and \
             {:.0} % of the validation frames' track error, {:.0} % of the held-out test error \
             (section \"Discovered term\").\n",
            found.formula,
            100.0 * found.fit_reduction,
            100.0 * found.validation_reduction,
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
        "Each effect's best trial (parameter chosen on the fit frames with the fitted \
         model's material and gains) was then fitted from the start with the fitted model's own \
         dm-fit options (`--fit-candidates`), and that fit compared with the fitted model"
    } else {
        "Each effect was added to the fitted model (material and gains held) and its \
         parameter chosen on the fit frames"
    };
    let frames = crate::selection_frames(bundle.meta.split.train);
    let _ = writeln!(
        s,
        "{how}. Fit frames {}–{}, validation frames {}–{} (the training split's last \
         quarter, which no choice saw); score = the smaller of the two shares of track error \
         removed. The test frames ({}–{}) are only reported.\n",
        frames.fit[0],
        frames.fit[1].saturating_sub(1),
        frames.validation[0],
        frames.validation[1].saturating_sub(1),
        bundle.meta.split.test[0],
        bundle.meta.split.test[1].saturating_sub(1),
    );
    let _ = writeln!(
        s,
        "| candidate | score | fit | validation | test (reported) | parameters | signature |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|");
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
            "| {}{}{} | {:+.3} | {:+.3} | {:+.3} | {:+.3} | {} | {}{} |",
            if c.name == d.cause { "**" } else { "" },
            c.name,
            if c.name == d.cause { "**" } else { "" },
            c.score,
            c.fit_reduction,
            c.validation_reduction,
            c.held_out_reduction,
            params.join(", "),
            c.signature,
            mark
        );
    }
    let _ = writeln!(s);
    for p in plots.iter().filter(|p| p.file == "candidates.png") {
        let _ = writeln!(s, "![{}]({})\n\n{}\n", p.file, p.file, p.caption);
    }
    write_detectability(&mut s, d);
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

/// A magnitude with the digits its size needs.
fn magnitude_text(value: f64) -> String {
    if value >= 100.0 {
        format!("{value:.0}")
    } else if value >= 1.0 {
        format!("{value:.2}")
    } else {
        format!("{value:.3}")
    }
}

/// `≥`, or `≤` where smaller magnitudes are stronger effects.
fn stronger_sign(l: &Limit) -> &'static str {
    match l.stronger {
        Stronger::Above => "≥",
        Stronger::Below => "≤",
    }
}

/// The search range, weakest end first.
fn searched_text(l: &Limit) -> String {
    let [low, high] = l.searched.map(magnitude_text);
    match l.stronger {
        Stronger::Above => format!("{low}–{high} {}", l.unit),
        Stronger::Below => format!("{high} down to {low} {}", l.unit),
    }
}

/// One line for the answer: which effects this clip rules out above which
/// magnitude (for a named cause: which others it would have shown), and
/// which it cannot show at all.
fn ruled_out_line(d: &Diagnosis) -> String {
    let shown: Vec<String> = d
        .detectability
        .iter()
        .filter(|(name, _)| **name != d.cause)
        .filter_map(|(name, l)| {
            Some(format!(
                "`{name}` {} {} {}",
                stronger_sign(l),
                magnitude_text(l.min_magnitude?),
                l.unit
            ))
        })
        .collect();
    let hidden: Vec<String> = d
        .detectability
        .iter()
        .filter(|(_, l)| l.min_magnitude.is_none())
        .map(|(name, l)| {
            let next = l.next_action.as_ref().map_or(String::new(), |n| {
                format!(
                    "; to test it, film {}: it reveals {} {} {}",
                    n.action,
                    stronger_sign(l),
                    magnitude_text(n.min_magnitude),
                    l.unit
                )
            });
            format!("`{name}` ({}{next})", searched_text(l))
        })
        .collect();
    let mut line = if shown.is_empty() {
        "**Ruled out:** nothing; this clip would reveal none of the library's effects \
         at any magnitude tried."
            .to_string()
    } else {
        format!(
            "**Ruled out** at these magnitudes, which this clip would have revealed unless the \
             clip's own fit absorbed part of the effect: {}.",
            shown.join(", ")
        )
    };
    if !hidden.is_empty() {
        line.push_str(&format!(
            " **Not testable in this clip** at any magnitude tried: {}.",
            hidden.join("; ")
        ));
    }
    line
}

/// The "What this clip can show" section: each library effect's
/// detection limit (crate::detectability).
fn write_detectability(s: &mut String, d: &Diagnosis) {
    if d.detectability.is_empty() {
        return;
    }
    let _ = writeln!(s, "## What this clip can show\n");
    let _ = writeln!(
        s,
        "The weakest magnitude of each effect that this clip reveals: the effect injected \
         into the fitted model (the extended model when a cause is named), its displacement \
         added to the recorded tracks (their noise and the model's misfit stay in), and the \
         candidate's trials scored as above; scanned, then bisected on a log scale. Magnitudes \
         in the units of `dm-synth --effect NAME:MAGNITUDE`. The model absorbed none of the \
         injected effect, as a fit would absorb part of it, so an effect above its limit can \
         still go unnamed; a directed effect's limit is its less visible orientation's. For an \
         effect this clip cannot reveal, variants of the recorded hand action are simulated \
         with the model (observations: its rollout plus this clip's residual) and the one \
         revealing the weakest magnitude is the next experiment.\n"
    );
    let _ = writeln!(
        s,
        "| effect | weakest revealed | searched | score there | next experiment |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|");
    for (name, l) in &d.detectability {
        let _ = writeln!(
            s,
            "| {name} | {} | {} | {:+.3} | {} |",
            l.min_magnitude.map_or("not revealed".into(), |m| format!(
                "{} {} {}",
                stronger_sign(l),
                magnitude_text(m),
                l.unit
            )),
            searched_text(l),
            l.score,
            match (&l.next_action, l.min_magnitude) {
                (_, Some(_)) => "—".to_string(),
                (Some(n), None) => format!(
                    "{}: {} {} {}",
                    n.action,
                    stronger_sign(l),
                    magnitude_text(n.min_magnitude),
                    l.unit
                ),
                (None, None) => "no variant tried reveals it".to_string(),
            }
        );
    }
    let _ = writeln!(s);
}
