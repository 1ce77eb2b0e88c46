//! The frame-0 appearance table of docs/RESULTS.md: for each bundle, the
//! untrained model (its first-frame particles are what dm-fit keeps), the
//! default fit holding out the last camera, PSNR per camera and the time.
//!
//!     cargo run --release -p dm-studies --example appearance_table -- [--iters N] BUNDLE...
//!
//! With `--out DIR` each scene's model directory (model.json and the
//! splats) is written to DIR/<bundle name>, ready for dm-render.

use dm_appearance::{AppearanceOptions, fit_appearance, save_appearance};
use dm_bundle::Bundle;
use dm_model::{ModelOptions, WorldModel};
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut iterations = None;
    let mut out: Option<PathBuf> = None;
    let mut bundles = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--iters" => iterations = Some(args.next().ok_or("--iters needs a value")?.parse()?),
            "--out" => out = Some(args.next().ok_or("--out needs a value")?.into()),
            _ => bundles.push(PathBuf::from(arg)),
        }
    }
    println!(
        "| scene | Gaussians | steps | train cameras | train PSNR (dB) | held-out camera | held-out PSNR (dB) | fit time (s) |"
    );
    println!("|---|---:|---:|---|---:|---|---:|---:|");
    for path in bundles {
        let bundle = Bundle::open(&path)?;
        let model = WorldModel::from_bundle(&bundle, &ModelOptions::default())?;
        let mut options = AppearanceOptions::for_cameras(bundle.meta.cameras.len());
        if let Some(n) = iterations {
            options.iterations = n;
        }
        let (gaussians, record) = fit_appearance(&model, &bundle, &options, &mut |_| {})?;
        let train: Vec<String> = record
            .psnr
            .iter()
            .filter(|p| p.train)
            .map(|p| format!("{} {:.2}", p.name, p.psnr_db))
            .collect();
        let held = record.psnr.iter().find(|p| !p.train);
        println!(
            "| {} | {} | {} | {} | {:.2} ({}) | {} | {} | {:.1} |",
            path.file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
            record.gaussian_count,
            record.iterations,
            record.train_cameras.len(),
            record.mean_train_psnr_db,
            train.join(", "),
            held.map_or("–".into(), |p| p.name.clone()),
            held.map_or("–".into(), |p| format!("{:.2}", p.psnr_db)),
            record.fit_seconds
        );
        if let Some(out) = &out {
            let dir = out.join(path.file_name().ok_or("bundle path has no name")?);
            std::fs::create_dir_all(&dir)?;
            dm_bundle::write_json_atomic(&dir.join("model.json"), &model)?;
            save_appearance(&dir, &gaussians, &record)?;
        }
    }
    Ok(())
}
