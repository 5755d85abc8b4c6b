//! `pathfarm`: the command line.

mod cpu_time;
mod guide_cmd;
mod outfile;
mod render_cmd;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "pathfarm",
    version,
    about = "A path-guiding render farm: renders Mitsuba 3 XML scenes"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a Mitsuba 3 XML scene to EXR (plus a PNG preview).
    Render(render_cmd::RenderArgs),
    /// Load a scene and print what it contains and which effects it uses.
    Info(render_cmd::InfoArgs),
    /// Path-guiding tools: train and save an SD-tree, its statistics, pictures.
    #[command(subcommand)]
    Guide(guide_cmd::GuideCommand),
}

fn main() {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_target(false)
        .init();
    let cli = Cli::parse();
    let result: Result<()> = match cli.command {
        Command::Render(a) => render_cmd::render(a),
        Command::Info(a) => render_cmd::info(a),
        Command::Guide(c) => guide_cmd::run(c),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
