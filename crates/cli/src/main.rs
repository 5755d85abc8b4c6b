//! `pathfarm`: the command line.

// Checks are written `!(x > 0.0)` on purpose: they also reject NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod converge;
mod cpu_time;
mod farm_cmd;
mod guide_cmd;
mod heap;
mod outfile;
mod render_cmd;

use anyhow::Result;
use clap::{Parser, Subcommand};
use tracing_subscriber::filter::LevelFilter;
use tracing_subscriber::layer::{Layer, SubscriberExt};
use tracing_subscriber::util::SubscriberInitExt;

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
    /// Run the farm's coordinator: the gRPC API that schedules jobs over workers.
    Coordinator(farm_cmd::CoordinatorArgs),
    /// Run a farm worker: render the tiles a coordinator leases to it.
    Worker(farm_cmd::WorkerArgs),
    /// Submit a scene to a coordinator as a job (prints the job id).
    Submit(farm_cmd::SubmitArgs),
    /// Show the coordinator's jobs and workers, or one job.
    Status(farm_cmd::StatusArgs),
    /// Cancel a job, or every frame of a batch that has not ended (--batch).
    Cancel(farm_cmd::CancelArgs),
    /// Change a queued or running job's priority, or every such frame's of a batch (--batch).
    Priority(farm_cmd::PriorityArgs),
    /// Download a finished job's image (EXR, plus a PNG preview beside it).
    Fetch(farm_cmd::FetchArgs),
    /// Render one scene on a local farm: a coordinator and N worker processes.
    Cluster(farm_cmd::ClusterArgs),
    /// Error against time: every method at every budget against a reference (CSV, charts,
    /// a noise figure, a summary).
    Converge(converge::ConvergeArgs),
    /// Ask a coordinator's gRPC health service (exit 0 if SERVING): container health checks.
    Health(farm_cmd::HealthArgs),
}

fn main() {
    heap::tune();
    let cli = Cli::parse();
    // converge renders dozens of times: each render's progress lines would bury its own
    // progress bar, so it logs warnings only unless RUST_LOG says otherwise.
    let level = match cli.command {
        Command::Converge(_) => "warn",
        _ => "info",
    };
    // Colour only for a person at a terminal: a log written to a file or a pipe stays plain
    // text, and NO_COLOR (https://no-color.org) turns it off anywhere.
    let colour = std::io::IsTerminal::is_terminal(&std::io::stderr())
        && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| level.into());
    let output = tracing_subscriber::fmt::layer()
        .with_writer(std::io::stderr)
        .with_ansi(colour)
        .with_target(false);
    // A coordinator also keeps each job's last lines for the job's dashboard page, at info
    // whatever RUST_LOG asks of the output.
    let job_logs = matches!(cli.command, Command::Coordinator(_))
        .then(pathfarm_farm::coordinator::JobLogs::default);
    let job_layer = (job_logs.clone()).map(|l| l.with_filter(LevelFilter::INFO));
    tracing_subscriber::registry()
        .with(output.with_filter(filter))
        .with(job_layer)
        .init();
    let result: Result<()> = match cli.command {
        Command::Render(a) => render_cmd::render(a),
        Command::Converge(a) => converge::converge(a),
        Command::Info(a) => render_cmd::info(a),
        Command::Guide(c) => guide_cmd::run(c),
        Command::Coordinator(a) => farm_cmd::coordinator(a, job_logs.unwrap_or_default()),
        Command::Worker(a) => farm_cmd::worker(a),
        Command::Submit(a) => farm_cmd::submit(a),
        Command::Status(a) => farm_cmd::status(a),
        Command::Cancel(a) => farm_cmd::cancel(a),
        Command::Priority(a) => farm_cmd::priority(a),
        Command::Fetch(a) => farm_cmd::fetch(a),
        Command::Cluster(a) => farm_cmd::cluster(a),
        Command::Health(a) => farm_cmd::health(a),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
