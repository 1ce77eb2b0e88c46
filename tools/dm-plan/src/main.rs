//! `dm-plan`: hand motions that bring an object to a goal, planned with
//! its fitted world model and carried out in the model or a truth world.

use std::io::IsTerminal;

use anyhow::{Context, Result};
use clap::Parser;
use dm_plan::run::{PlanOptions, plan, write_outputs};
use indicatif::{ProgressBar, ProgressStyle};

fn main() -> Result<()> {
    let options = PlanOptions::parse();
    if !cfg!(feature = "video") && !options.no_video {
        anyhow::bail!(
            "this dm-plan was built without the `video` feature (OpenCV): pass --no-video, or rebuild with it"
        );
    }
    // A bar on a terminal; in a log, a line per search step.
    let terminal = std::io::stderr().is_terminal();
    let bar = if terminal {
        ProgressBar::new(1)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template("{msg:>9} [{bar:40}] {pos}/{len} {elapsed}")?
            .progress_chars("=> "),
    );
    let clock = std::time::Instant::now();
    let result = plan(&options, &mut |stage, done, total| {
        bar.set_message(stage.to_string());
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        if !terminal && (stage != "execute" || done == total) {
            eprintln!(
                "dm-plan: {stage} {done}/{total} ({:.0} s)",
                clock.elapsed().as_secs_f64()
            );
        }
        std::ops::ControlFlow::Continue(())
    })
    .context("planning (nothing was written)")?;
    bar.finish_and_clear();
    write_outputs(&options.out, &result)
        .with_context(|| format!("writing {}", options.out.display()))?;
    if !options.no_video {
        let dir = dm_plan::video::write_frames(&options.out, options.camera, &result)
            .context("rendering the video frames")?;
        dm_appearance::clip::encode_mp4(&dir, 0..result.executed.len(), 1.0 / result.frame_dt)
            .context("encoding the video")?;
    }
    let r = &result.record;
    println!(
        "dm-plan: goal {} ({} points), {} rollouts, {:.0} s, {} re-plans",
        r.goal.name, r.goal.points, r.rollouts, r.seconds, r.replans
    );
    println!(
        "  Chamfer to the goal (mm): start {:.1}, planned {:.1}, executed in the {} {:.1}",
        1e3 * r.start.final_chamfer_m,
        1e3 * r.planned.final_chamfer_m,
        r.plant,
        1e3 * r.executed.final_chamfer_m
    );
    let video = if options.no_video {
        ""
    } else {
        ", video/render.mp4"
    };
    println!("  {}: plan.json{video}", options.out.display());
    Ok(())
}
