//! `dm-play`: the interactive playground of a fitted model in the browser.

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Parser;
use dm_play::{PlayOptions, Playground, open_session, serve};

#[derive(Parser, Debug)]
#[command(
    name = "dm-play",
    about = "Grab, pull and re-material a fitted world model live in a browser page"
)]
struct Args {
    /// Fitted model directory (dm-fit's output; dm-appearance's splats are used when present).
    model_dir: PathBuf,
    /// Port (0: pick a free one; the URL is printed).
    #[arg(long, default_value_t = 0)]
    port: u16,
    /// Address to listen on (only this machine by default).
    #[arg(long, default_value = "127.0.0.1")]
    bind: IpAddr,
    #[command(flatten)]
    simulation: PlayOptions,
    /// Where recorded sessions are written as scene bundles.
    #[arg(long, default_value = "dm-play-recordings")]
    record_dir: PathBuf,
}

#[tokio::main]
async fn main() -> Result<()> {
    let args = Args::parse();
    let session = open_session(&args.model_dir, &args.simulation)
        .with_context(|| format!("opening the model in {}", args.model_dir.display()))?;
    let state = session.state();
    let sprites = session.sprites();
    let addr = SocketAddr::new(args.bind, args.port);
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .with_context(|| format!("listening on {addr}"))?;
    let bound = listener.local_addr().context("reading the bound address")?;
    println!(
        "dm-play: {} particles, {} {} drawn, grid {}^3, {} substeps per {:.1} ms frame",
        state.particle_count,
        sprites.count,
        sprites.kind,
        state.grid,
        state.substeps_per_frame,
        1e3 * state.frame_dt
    );
    println!("  recordings go to {}", args.record_dir.display());
    println!("  open http://{bound}/   (Ctrl+C to stop)");
    let playground = Playground::start(session, args.record_dir);
    serve(listener, playground)
        .await
        .context("serving the playground")
}
