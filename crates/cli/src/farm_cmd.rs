//! The farm's subcommands: `coordinator`, `worker`, `submit`, `status`, `cancel`,
//! `priority`, `fetch` and `cluster` (a coordinator and N workers on this machine, for one job).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use pathfarm_farm::client::{self, Budget, Client, Remote, SubmitOptions};
use pathfarm_farm::coordinator::JobLogs;
use pathfarm_proto::v1;
use pathfarm_render::output;
use pathfarm_scene::Limits;
use tokio::signal::unix::{signal, Signal, SignalKind};

use crate::outfile::{self, OutputFile};
use crate::render_cmd::{parse_defines, BudgetArgs};

#[derive(Args)]
pub struct CoordinatorArgs {
    /// Address to serve the gRPC API on.
    #[arg(long, default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// Directory for blobs, results and the job database.
    #[arg(long = "data", value_name = "DIR")]
    pub data: PathBuf,
    /// Require `authorization: Bearer TOKEN` on every call.
    #[arg(long, env = "PATHFARM_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Prometheus metrics address (serves GET /metrics).
    #[arg(long, value_name = "ADDR")]
    pub metrics: Option<SocketAddr>,
    /// Serve the web dashboard on this address (e.g. 127.0.0.1:8080): jobs, workers, a
    /// job's preview; sign in with the token. Needs --token; over TLS with --tls-cert.
    #[arg(long, value_name = "ADDR")]
    pub http: Option<SocketAddr>,
    /// A second token for the dashboard: signing in with it may look but not act (no
    /// cancel, no priority change). Needs --http; not a token of the API.
    #[arg(
        long,
        env = "PATHFARM_VIEWER_TOKEN",
        value_name = "TOKEN",
        requires = "http"
    )]
    pub viewer_token: Option<String>,
    /// Serve TLS only, with this certificate chain (PEM); needs --tls-key.
    #[arg(long, value_name = "PEM", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert.
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Largest scene bundle accepted, all files together, in bytes (default 4 GiB).
    #[arg(long, value_name = "BYTES")]
    pub max_bundle_bytes: Option<u64>,
    /// Largest single file of a bundle, in bytes (default 1 GiB).
    #[arg(long, value_name = "BYTES")]
    pub max_file_bytes: Option<u64>,
    /// Memory the running jobs' sessions may take together, in MiB (default: half the
    /// machine's memory). Jobs wait QUEUED for room; a job that could never fit is refused.
    #[arg(long, value_name = "MIB")]
    pub job_memory_mb: Option<u64>,
    /// Jobs queued or running at once (default 1000); more submissions are refused.
    #[arg(long, value_name = "N")]
    pub max_jobs_waiting: Option<usize>,
    /// Upload payloads buffered at once, all workers together, in MiB (default 1024).
    #[arg(long, value_name = "MIB")]
    pub upload_memory_mb: Option<u64>,
    /// Seconds an uploaded blob that no job refers to is kept (default 3600).
    #[arg(long, value_name = "SECONDS")]
    pub blob_grace_s: Option<f64>,
    /// Seconds an upload stream may stay silent (default 60).
    #[arg(long, value_name = "SECONDS")]
    pub stream_idle_s: Option<f64>,
    /// Rejected uploads after which a worker gets no more leases of that job (default 3).
    #[arg(long, value_name = "N")]
    pub bad_uploads_per_job: Option<u32>,
    /// Seconds of silence after which a worker is declared lost (default 15).
    #[arg(long, value_name = "SECONDS")]
    pub heartbeat_timeout_s: Option<f64>,
    /// Seconds a lease lives without a heartbeat listing it (default 60).
    #[arg(long, value_name = "SECONDS")]
    pub lease_timeout_s: Option<f64>,
    /// Seconds between a running job's checkpoints on disk, taken at iterations' ends (0:
    /// at every iteration's end). A restarted coordinator resumes a job from its last one.
    #[arg(long, value_name = "SECONDS", default_value_t = 30.0)]
    pub checkpoint_interval_s: f64,
    /// Seconds a lease can live however often heartbeats list it (default 600).
    #[arg(long, value_name = "SECONDS")]
    pub max_lease_lifetime_s: Option<f64>,
}

#[derive(Args)]
pub struct WorkerArgs {
    /// The coordinator's URL, e.g. http://127.0.0.1:50051.
    #[arg(long, env = "PATHFARM_COORDINATOR")]
    pub coordinator: String,
    /// Render threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Bearer token for the coordinator.
    #[arg(long, env = "PATHFARM_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// CA certificate (PEM) that signed the coordinator's: connect with TLS (https:// URL).
    #[arg(long, env = "PATHFARM_TLS_CA", value_name = "PEM")]
    pub tls_ca: Option<PathBuf>,
    /// A name for this worker, shown by `pathfarm status`.
    #[arg(long)]
    pub name: Option<String>,
    /// Cache directory for blobs and scene bundles (default: $XDG_CACHE_HOME or
    /// ~/.cache, /pathfarm-worker-PID).
    #[arg(long = "cache", value_name = "DIR")]
    pub cache: Option<PathBuf>,
    /// Memory the built scenes of the jobs this worker serves may take together, in MiB
    /// (the least recently used scenes go beyond it; one scene is always kept).
    #[arg(long, value_name = "MIB", default_value_t = pathfarm_farm::worker::scenes::DEFAULT_BUDGET_BYTES >> 20)]
    pub scene_cache_mib: u64,
    /// Benchmarks only: instead of rendering, sleep this many seconds a sample and upload
    /// zero radiance (`bench/farm_swarm.py`: the coordinator's work at many workers).
    #[arg(long, value_name = "SECONDS", hide = true)]
    pub simulate_seconds_per_sample: Option<f64>,
    /// Benchmarks only: run this many workers in this process (each with its own cache
    /// folder, control stream and render thread pool), for simulated swarms.
    #[arg(long, default_value_t = 1, hide = true)]
    pub instances: usize,
}

/// Coordinator connection flags shared by the client subcommands.
#[derive(Args, Clone)]
pub struct ConnArgs {
    /// The coordinator's URL, e.g. http://127.0.0.1:50051.
    #[arg(long, env = "PATHFARM_COORDINATOR")]
    pub coordinator: String,
    /// Bearer token for the coordinator.
    #[arg(long, env = "PATHFARM_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// CA certificate (PEM) that signed the coordinator's: connect with TLS (https:// URL).
    #[arg(long, env = "PATHFARM_TLS_CA", value_name = "PEM")]
    pub tls_ca: Option<PathBuf>,
}

impl ConnArgs {
    /// The coordinator these flags name.
    fn remote(&self) -> Result<Remote> {
        remote(
            &self.coordinator,
            self.token.as_deref(),
            self.tls_ca.as_deref(),
        )
    }
}

fn remote(url: &str, token: Option<&str>, tls_ca: Option<&Path>) -> Result<Remote> {
    let tls_ca = match tls_ca {
        Some(p) => Some(std::fs::read(p).with_context(|| format!("--tls-ca {}", p.display()))?),
        None => None,
    };
    Ok(Remote {
        url: url.to_string(),
        token: token.map(str::to_string),
        tls_ca,
    })
}

/// Render settings shared by `submit` and `cluster`.
#[derive(Args, Clone)]
pub struct JobArgs {
    #[command(flatten)]
    pub budget: BudgetArgs,
    /// Render at this resolution instead of the scene film's, e.g. 1280x720.
    #[arg(long, value_name = "WxH", value_parser = parse_resolution)]
    pub resolution: Option<(u32, u32)>,
}

fn parse_resolution(s: &str) -> Result<(u32, u32), String> {
    let bad = || format!("{s:?} is not WIDTHxHEIGHT (e.g. 1280x720)");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    Ok((w.parse().map_err(|_| bad())?, h.parse().map_err(|_| bad())?))
}

#[derive(Args)]
pub struct SubmitArgs {
    /// The Mitsuba 3 XML scene; or several, the frames of a batch (each a job): files, or
    /// directories whose `*.xml` files are the frames, in name order. Files the frames share
    /// are uploaded once.
    #[arg(required = true, num_args = 1..)]
    pub scenes: Vec<PathBuf>,
    #[command(flatten)]
    pub conn: ConnArgs,
    /// Wait for the job (every frame of a batch) to finish (with a progress bar).
    #[arg(long)]
    pub wait: bool,
    /// With --wait: write the result here (EXR, plus a PNG preview beside it); for a batch,
    /// a directory that gets each frame's EXR and PNG, named after its scene file.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// The batch's name, which `pathfarm status` groups its frames by (default, for more
    /// than one frame: the first frame's directory name).
    #[arg(long)]
    pub batch: Option<String>,
    #[command(flatten)]
    pub job: JobArgs,
    /// Scheduling priority (higher first).
    #[arg(long, default_value_t = 0, allow_hyphen_values = true)]
    pub priority: i32,
    /// Tile edge in pixels (default: the coordinator's).
    #[arg(long = "tile")]
    pub tile: Option<u32>,
}

#[derive(Args)]
pub struct StatusArgs {
    /// One job to describe (default: every job and every worker).
    pub job: Option<String>,
    #[command(flatten)]
    pub conn: ConnArgs,
}

#[derive(Args)]
pub struct HealthArgs {
    /// The gRPC service to ask about: "" (default) = the farm (serving once a worker is
    /// registered), pathfarm.v1.Workers = the coordinator is up.
    #[arg(long, default_value = "")]
    pub service: String,
    /// The coordinator's URL, e.g. http://127.0.0.1:50051.
    #[arg(
        long,
        env = "PATHFARM_COORDINATOR",
        default_value = "http://127.0.0.1:50051"
    )]
    pub coordinator: String,
    /// CA certificate (PEM) that signed the coordinator's: connect with TLS (https:// URL).
    #[arg(long, env = "PATHFARM_TLS_CA", value_name = "PEM")]
    pub tls_ca: Option<PathBuf>,
}

#[derive(Args)]
pub struct CancelArgs {
    /// The job (`job-N`).
    #[arg(required_unless_present = "batch", conflicts_with = "batch")]
    pub job: Option<String>,
    /// Every frame of this batch (`pathfarm submit --batch`, or its default name) that has
    /// not ended, instead of one job.
    #[arg(long)]
    pub batch: Option<String>,
    #[command(flatten)]
    pub conn: ConnArgs,
}

#[derive(Args)]
pub struct PriorityArgs {
    /// JOB PRIORITY, or with --batch PRIORITY alone (higher first; negative numbers too).
    #[arg(num_args = 1..=2, required = true, allow_negative_numbers = true, value_names = ["JOB", "PRIORITY"])]
    pub args: Vec<String>,
    /// Every frame of this batch that has not ended, instead of one job.
    #[arg(long)]
    pub batch: Option<String>,
    #[command(flatten)]
    pub conn: ConnArgs,
}

/// Who a cancel or priority change is for.
enum Target {
    Job(String),
    Batch(String),
}

impl Target {
    /// The jobs it names now: the job, or the batch's frames that have not ended.
    async fn jobs(&self, client: &mut Client) -> Result<Vec<String>> {
        let name = match self {
            Target::Job(j) => return Ok(vec![j.clone()]),
            Target::Batch(b) => b,
        };
        let jobs = client.list_jobs().await?;
        let frames: Vec<&v1::JobStatus> = jobs.iter().filter(|s| &s.batch == name).collect();
        if frames.is_empty() {
            bail!("--batch {}: no such batch", bounded(name));
        }
        let open = frames.iter().filter(|s| !is_terminal(s.state));
        Ok(open.map(|s| s.job_id.clone()).collect())
    }
}

/// At most 64 characters of `s`, for echoing input in an error.
fn bounded(s: &str) -> String {
    pathfarm_scene::shown_bounded(s, 64)
}

#[derive(Args)]
pub struct FetchArgs {
    pub job: String,
    /// Output EXR (a PNG preview is written beside it).
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub conn: ConnArgs,
}

#[derive(Args)]
pub struct ClusterArgs {
    /// Worker processes to start.
    #[arg(long)]
    pub workers: usize,
    /// Render threads of each worker (default: cores / workers, at least 1).
    #[arg(long)]
    pub threads_per_worker: Option<usize>,
    /// The Mitsuba 3 XML scene.
    pub scene: PathBuf,
    /// Output EXR (a PNG preview is written beside it).
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub job: JobArgs,
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// SIGINT and SIGTERM, registered now (before any output file, so that the output files'
/// own signal handler stays out of the way and temporaries are dropped normally).
struct Signals {
    int: Signal,
    term: Signal,
}

impl Signals {
    fn new() -> Result<Self> {
        Ok(Signals {
            int: signal(SignalKind::interrupt()).context("installing the SIGINT handler")?,
            term: signal(SignalKind::terminate()).context("installing the SIGTERM handler")?,
        })
    }

    async fn recv(&mut self) {
        tokio::select! {
            _ = self.int.recv() => {}
            _ = self.term.recv() => {}
        }
    }
}

/// `pathfarm coordinator`; `job_logs` is fed by the process's log subscriber.
pub fn coordinator(args: CoordinatorArgs, job_logs: JobLogs) -> Result<()> {
    let rt = runtime()?;
    let r = rt.block_on(async move {
        let mut signals = Signals::new()?;
        let shutdown = async move { signals.recv().await };
        serve_coordinator(args, job_logs, shutdown).await
    });
    log_peak_memory("coordinator");
    r
}

/// Logs the process's peak resident memory (Linux: VmHWM), for operators and benchmarks.
fn log_peak_memory(what: &str) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kb = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok());
    if let Some(kb) = kb {
        tracing::info!(peak_rss_mb = kb as f64 / 1024.0, "{what} exiting");
    }
}

async fn serve_coordinator(
    args: CoordinatorArgs,
    job_logs: JobLogs,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<()> {
    use pathfarm_farm::coordinator::{self, CoordinatorConfig};
    let tls = match (&args.tls_cert, &args.tls_key) {
        (Some(c), Some(k)) => Some(coordinator::TlsIdentity {
            cert_pem: std::fs::read(c).with_context(|| format!("--tls-cert {}", c.display()))?,
            key_pem: std::fs::read(k).with_context(|| format!("--tls-key {}", k.display()))?,
        }),
        _ => None,
    };
    let mut bundle_limits = pathfarm_farm::bundle::BundleLimits::default();
    if let Some(b) = args.max_bundle_bytes {
        bundle_limits.max_total_bytes = b;
    }
    if let Some(b) = args.max_file_bytes {
        bundle_limits.max_file_bytes = b;
    }
    let cfg = CoordinatorConfig {
        scheduler: scheduler_config(&args)?,
        resources: resources(&args)?,
        listen: args.listen,
        data_dir: args.data,
        token: args.token,
        tls,
        metrics: args.metrics,
        http: args.http,
        viewer_token: args.viewer_token,
        limits: Limits::default(),
        bundle_limits,
        job_logs,
        checkpoint_interval: std::time::Duration::try_from_secs_f64(args.checkpoint_interval_s)
            .ok()
            .with_context(|| {
                format!(
                    "--checkpoint-interval-s {}: not a number of seconds",
                    args.checkpoint_interval_s
                )
            })?,
        default_tile: None,
    };
    if cfg.http.is_some() && cfg.token.is_none() {
        bail!(
            "--http: the dashboard needs the API token (--token or PATHFARM_TOKEN) to sign in with"
        );
    }
    if cfg.viewer_token.is_some() && cfg.viewer_token == cfg.token {
        bail!("--viewer-token: the same as --token, so it would act, not only look");
    }
    if cfg
        .viewer_token
        .as_ref()
        .is_some_and(|t| t.is_empty() || t.len() > 4096)
    {
        bail!("--viewer-token: empty or longer than 4096 bytes");
    }
    coordinator::serve(cfg, shutdown).await?;
    Ok(())
}

/// A duration flag in seconds, checked.
fn seconds(flag: &str, s: Option<f64>) -> Result<Option<std::time::Duration>> {
    s.map(|s| {
        std::time::Duration::try_from_secs_f64(s)
            .ok()
            .filter(|d| !d.is_zero())
            .with_context(|| format!("--{flag} {s}: not a positive number of seconds"))
    })
    .transpose()
}

fn scheduler_config(args: &CoordinatorArgs) -> Result<pathfarm_farm::scheduler::SchedulerConfig> {
    let mut c = pathfarm_farm::scheduler::SchedulerConfig::default();
    if let Some(d) = seconds("heartbeat-timeout-s", args.heartbeat_timeout_s)? {
        c.heartbeat_timeout = d;
    }
    if let Some(d) = seconds("lease-timeout-s", args.lease_timeout_s)? {
        c.lease_timeout = d;
    }
    if let Some(d) = seconds("max-lease-lifetime-s", args.max_lease_lifetime_s)? {
        c.max_lease_lifetime = d;
    }
    Ok(c)
}

fn resources(args: &CoordinatorArgs) -> Result<pathfarm_farm::coordinator::Resources> {
    let mut r = pathfarm_farm::coordinator::Resources::default();
    if let Some(m) = args.job_memory_mb {
        r.job_memory_bytes = m.saturating_mul(1 << 20);
    }
    if let Some(n) = args.max_jobs_waiting {
        r.max_jobs_waiting = n;
    }
    if let Some(m) = args.upload_memory_mb {
        r.upload_memory_bytes = m.saturating_mul(1 << 20).max(1 << 20);
    }
    if let Some(d) = seconds("blob-grace-s", args.blob_grace_s)? {
        r.blob_grace = d;
    }
    if let Some(d) = seconds("stream-idle-s", args.stream_idle_s)? {
        r.stream_idle = d;
    }
    if let Some(n) = args.bad_uploads_per_job {
        r.bad_uploads_per_job = n.max(1);
    }
    Ok(r)
}

fn default_cache() -> PathBuf {
    let name = format!("pathfarm-worker-{}", std::process::id());
    if let Some(x) = std::env::var_os("XDG_CACHE_HOME").filter(|x| !x.is_empty()) {
        return PathBuf::from(x).join(name);
    }
    if let Some(h) = std::env::var_os("HOME").filter(|x| !x.is_empty()) {
        return PathBuf::from(h).join(".cache").join(name);
    }
    std::env::temp_dir().join(name)
}

fn default_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

pub fn worker(args: WorkerArgs) -> Result<()> {
    let cfgs = worker_configs(args)?;
    let rt = runtime()?;
    let r = rt.block_on(run_workers(cfgs));
    log_peak_memory("worker");
    r
}

/// One configuration per `--instances` (one, but for benchmark swarms), each with its own
/// name and cache folder when there are several.
fn worker_configs(args: WorkerArgs) -> Result<Vec<pathfarm_farm::worker::WorkerConfig>> {
    let threads = args.threads.unwrap_or_else(default_threads);
    if threads == 0 {
        bail!("--threads must be at least 1");
    }
    if args.instances == 0 {
        bail!("--instances must be at least 1");
    }
    let rendering = match args.simulate_seconds_per_sample {
        None => pathfarm_farm::worker::Rendering::Real,
        Some(s) if s.is_finite() && s >= 0.0 => pathfarm_farm::worker::Rendering::Simulated {
            seconds_per_sample: s,
        },
        Some(s) => bail!("--simulate-seconds-per-sample {s}: not a duration"),
    };
    let cache = args.cache.clone().unwrap_or_else(default_cache);
    let config = |i: usize| -> Result<pathfarm_farm::worker::WorkerConfig> {
        let (name, cache_dir) = match args.instances {
            1 => (args.name.clone().unwrap_or_default(), cache.clone()),
            _ => {
                let name = args.name.as_deref().unwrap_or("sim");
                (format!("{name}-{i}"), cache.join(format!("instance-{i}")))
            }
        };
        Ok(pathfarm_farm::worker::WorkerConfig {
            coordinator: remote(
                &args.coordinator,
                args.token.as_deref(),
                args.tls_ca.as_deref(),
            )?,
            threads,
            name,
            cache_dir,
            scene_cache_bytes: args.scene_cache_mib.saturating_mul(1 << 20),
            rendering,
        })
    };
    (0..args.instances).map(config).collect()
}

/// Runs the workers until a signal (then each drains) or until one of them fails.
async fn run_workers(cfgs: Vec<pathfarm_farm::worker::WorkerConfig>) -> Result<()> {
    let mut signals = Signals::new()?;
    let (stop, _) = tokio::sync::broadcast::channel::<()>(1);
    let several = cfgs.len() > 1;
    let mut workers = tokio::task::JoinSet::new();
    for cfg in cfgs {
        let mut stopped = stop.subscribe();
        // Several instances log into one stream: each line of an instance's session names it.
        let span = match several {
            false => tracing::Span::none(),
            true => tracing::info_span!("worker", name = %cfg.name),
        };
        let run = pathfarm_farm::worker::run(cfg, async move {
            let _ = stopped.recv().await;
        });
        workers.spawn(tracing::Instrument::instrument(run, span));
    }
    tokio::select! {
        _ = signals.recv() => {}
        Some(r) = workers.join_next() => r??,
    }
    let _ = stop.send(());
    while let Some(r) = workers.join_next().await {
        r??;
    }
    Ok(())
}

/// With `--integrator`, says on stderr what the replacement replaces and drops in `scene`
/// (the coordinator and the workers load it replaced the same way).
fn report_integrator(job: &JobArgs, scene: &Path) -> Result<()> {
    let Some(name) = job.budget.integrator.as_deref() else {
        return Ok(());
    };
    let defines = parse_defines(&job.budget.defines)?;
    let limits = Limits::default();
    let desc = pathfarm_scene::scan_scene_as(scene, &defines, &limits, Some(name))?;
    for w in desc.warnings.iter().filter(|w| w.contains("--integrator")) {
        eprintln!("warning: {w}");
    }
    Ok(())
}

fn job_options(
    job: &JobArgs,
    scene: &Path,
    tile: Option<u32>,
    priority: i32,
) -> Result<SubmitOptions> {
    report_integrator(job, scene)?;
    job.budget.check(&Limits::default())?;
    if job.budget.spp.is_some() && job.budget.time.is_some() {
        bail!("--spp and --time: a farm job has one budget, give one of them");
    }
    if tile == Some(0) {
        bail!("--tile must be at least 1");
    }
    Ok(SubmitOptions {
        defines: parse_defines(&job.budget.defines)?,
        integrator: job.budget.integrator.clone(),
        resolution: job.resolution,
        budget: match (job.budget.spp, job.budget.time) {
            (Some(n), _) => Some(Budget::Spp(n)),
            (None, Some(t)) => Some(Budget::Seconds(t)),
            _ => None,
        },
        seed: job.budget.seed,
        tile_size: tile,
        priority,
        name: scene
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        batch: String::new(),
    })
}

/// The EXR output and its PNG preview beside it, opened (checked) before any work.
fn open_outputs(exr: &Path) -> Result<(OutputFile, OutputFile)> {
    let ext_ok = exr
        .extension()
        .map(|e| e.eq_ignore_ascii_case("exr"))
        .unwrap_or(false);
    if !ext_ok {
        bail!("{}: the output must be an .exr file", exr.display());
    }
    let exr_out = OutputFile::create(exr)?;
    let png_out = OutputFile::create_checked(&exr.with_extension("png"), |p| {
        if output::is_pathfarm_preview(p) {
            return Ok(());
        }
        bail!(
            "{}: exists and is not a preview written by pathfarm, so it is left alone",
            p.display()
        )
    })?;
    Ok((exr_out, png_out))
}

async fn write_results(
    client: &mut Client,
    job: &str,
    outs: (OutputFile, OutputFile),
) -> Result<()> {
    let exr = client.download(job, v1::ResultKind::Exr).await?;
    let png = client.download(job, v1::ResultKind::PngPreview).await?;
    outfile::commit_all(vec![(outs.0, exr.as_slice()), (outs.1, png.as_slice())])
}

/// Whether a job in state `s` has ended (done, failed or cancelled).
fn is_terminal(s: i32) -> bool {
    use v1::JobState::{Cancelled, Done, Failed};
    matches!(v1::JobState::try_from(s), Ok(Done | Failed | Cancelled))
}

fn state_name(s: i32) -> &'static str {
    match v1::JobState::try_from(s) {
        Ok(v1::JobState::Queued) => "queued",
        Ok(v1::JobState::Training) => "training",
        Ok(v1::JobState::FinalPass) => "final-pass",
        Ok(v1::JobState::Assembling) => "assembling",
        Ok(v1::JobState::Done) => "done",
        Ok(v1::JobState::Failed) => "failed",
        Ok(v1::JobState::Cancelled) => "cancelled",
        _ => "unknown",
    }
}

/// Watches `job` with a progress bar until it ends; errors unless it ended DONE.
/// Follows `job` with a progress bar until it ends; its last status if it is done.
async fn wait_for(client: &mut Client, job: &str) -> Result<v1::JobStatus> {
    let bar = ProgressBar::new(1);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {percent}% {msg} ({eta} left)",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let status = client
        .watch(job, |s| {
            if s.samples_total > 0 {
                bar.set_length(s.samples_total);
                bar.set_position(s.samples_done.min(s.samples_total));
            }
            bar.set_message(format!(
                "{} iteration {} tiles {}/{} samples {}",
                state_name(s.state),
                s.iteration,
                s.tiles_done,
                s.tiles_total,
                s.samples_done
            ));
        })
        .await;
    bar.finish_and_clear();
    let status = status?;
    match v1::JobState::try_from(status.state) {
        Ok(v1::JobState::Done) => Ok(status),
        Ok(v1::JobState::Failed) => bail!("job {job} failed: {}", status.failure_reason),
        Ok(v1::JobState::Cancelled) => bail!("job {job} was cancelled"),
        _ => bail!("job {job} ended in state {}", state_name(status.state)),
    }
}

pub fn submit(args: SubmitArgs) -> Result<()> {
    if args.output.is_some() && !args.wait {
        bail!("-o/--output needs --wait (or use `pathfarm fetch JOB -o OUT.exr` later)");
    }
    let frames = batch_frames(&args.scenes)?;
    let batch = match (&args.batch, frames.len()) {
        (Some(b), _) => b.clone(),
        (None, 1) => String::new(),
        (None, _) => default_batch_name(&frames[0]),
    };
    let outputs = frame_outputs(&frames, args.output.as_deref())?;
    let mut opts = Vec::with_capacity(frames.len());
    for frame in &frames {
        let mut o = job_options(&args.job, frame, args.tile, args.priority)?;
        o.batch = batch.clone();
        opts.push(o);
    }
    let rt = runtime()?;
    rt.block_on(async move {
        let mut signals = Signals::new()?;
        let mut outs = Vec::new();
        for o in &outputs {
            outs.push(o.as_deref().map(open_outputs).transpose()?);
        }
        let work = async {
            let mut client = client::connect(&args.conn.remote()?).await?;
            let mut jobs = Vec::with_capacity(frames.len());
            for (frame, o) in frames.iter().zip(&opts) {
                let job = client.submit(frame, o).await?;
                println!("{job}");
                jobs.push(job);
            }
            if !batch.is_empty() {
                eprintln!("batch {batch}: {} frames submitted", jobs.len());
            }
            if args.wait {
                for (job, outs) in jobs.iter().zip(outs) {
                    let status = wait_for(&mut client, job).await?;
                    if let Some(outs) = outs {
                        write_results(&mut client, job, outs).await?;
                    }
                    print_summary(&status);
                }
            }
            anyhow::Ok(())
        };
        tokio::select! {
            r = work => r,
            _ = signals.recv() => bail!("interrupted"),
        }
    })
}

/// The scene files of `paths`: each file as given, each directory's `*.xml` files in name
/// order.
fn batch_frames(paths: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut frames = Vec::new();
    for p in paths {
        if !p.is_dir() {
            frames.push(p.clone());
            continue;
        }
        let mut xml: Vec<PathBuf> = std::fs::read_dir(p)
            .with_context(|| format!("{}: reading the directory", p.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|f| f.is_file() && f.extension().is_some_and(|x| x.eq_ignore_ascii_case("xml")))
            .collect();
        if xml.is_empty() {
            bail!("{}: no .xml scene files in the directory", p.display());
        }
        xml.sort();
        frames.extend(xml);
    }
    Ok(frames)
}

/// A batch's default name: its first frame's directory.
fn default_batch_name(first: &Path) -> String {
    let dir = std::path::absolute(first).ok().and_then(|p| {
        p.parent()
            .and_then(|d| d.file_name())
            .map(|n| n.to_os_string())
    });
    dir.map_or_else(|| "batch".into(), |n| n.to_string_lossy().into_owned())
}

/// Where each frame's result goes: `output` itself for one frame; for several, the
/// directory `output` (created) with an EXR per frame named after its scene file (after its
/// directory and file where two files share a name).
fn frame_outputs(frames: &[PathBuf], output: Option<&Path>) -> Result<Vec<Option<PathBuf>>> {
    let Some(out) = output else {
        return Ok(vec![None; frames.len()]);
    };
    if frames.len() == 1 {
        return Ok(vec![Some(out.to_path_buf())]);
    }
    if out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"))
    {
        bail!(
            "{}: a batch of {} frames writes into a directory, not one .exr file",
            out.display(),
            frames.len()
        );
    }
    std::fs::create_dir_all(out).with_context(|| format!("{}: creating it", out.display()))?;
    let stem = |f: &Path| {
        f.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let stems: Vec<String> = frames.iter().map(|f| stem(f)).collect();
    let mut names = Vec::with_capacity(frames.len());
    for (f, s) in frames.iter().zip(&stems) {
        let unique = stems.iter().filter(|t| *t == s).count() == 1;
        let name = if unique {
            s.clone()
        } else {
            let parent = std::path::absolute(f)
                .ok()
                .and_then(|p| {
                    p.parent()
                        .and_then(|d| d.file_name())
                        .map(|n| n.to_string_lossy().into_owned())
                })
                .unwrap_or_default();
            format!("{parent}-{s}")
        };
        if names.contains(&name) {
            bail!("two frames would both write {name}.exr: name the scene files apart");
        }
        names.push(name);
    }
    Ok(names
        .into_iter()
        .map(|n| Some(out.join(format!("{n}.exr"))))
        .collect())
}

/// A line per batch of frames among `jobs` (in the order of their first frame): how many
/// frames are in each state.
fn print_batches(jobs: &[v1::JobStatus]) {
    let mut batches: Vec<(&str, Vec<&v1::JobStatus>)> = Vec::new();
    for s in jobs.iter().filter(|s| !s.batch.is_empty()) {
        match batches.iter_mut().find(|(b, _)| *b == s.batch) {
            Some((_, frames)) => frames.push(s),
            None => batches.push((&s.batch, vec![s])),
        }
    }
    if batches.is_empty() {
        return;
    }
    println!();
    for (batch, frames) in batches {
        let mut counts: Vec<(&str, usize)> = Vec::new();
        for s in &frames {
            let state = state_name(s.state);
            match counts.iter_mut().find(|(n, _)| *n == state) {
                Some((_, c)) => *c += 1,
                None => counts.push((state, 1)),
            }
        }
        let states: Vec<String> = counts.iter().map(|(n, c)| format!("{c} {n}")).collect();
        println!(
            "batch {batch}: {} frames ({})",
            frames.len(),
            states.join(", ")
        );
    }
}

/// A finished job's summary line, in the form of `pathfarm render`'s.
fn print_summary(s: &v1::JobStatus) {
    let wall = s.finished_unix_ms.saturating_sub(s.started_unix_ms) as f64 / 1000.0;
    println!(
        "summary: job={} spp={} wall_s={wall:.3} nonfinite={}",
        s.job_id, s.spp_done, s.nonfinite
    );
}

fn ms_ago(unix_ms: u64) -> String {
    if unix_ms == 0 {
        return "-".into();
    }
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64);
    format!("{:.1}s ago", now.saturating_sub(unix_ms) as f64 / 1000.0)
}

fn print_job_row(s: &v1::JobStatus) {
    let pct = if s.samples_total > 0 {
        format!(
            "{:.1}%",
            100.0 * s.samples_done as f64 / s.samples_total as f64
        )
    } else {
        "-".into()
    };
    let eta = s.eta_seconds.map_or("-".into(), |e| format!("{e:.0}s"));
    println!(
        "{:<24} {:<20} {:<11} {:>4} {:>11} {:>7} {:>6} {:>4}  {}",
        s.job_id,
        s.name,
        state_name(s.state),
        s.iteration,
        format!("{}/{}", s.tiles_done, s.tiles_total),
        pct,
        eta,
        s.priority,
        s.failure_reason
    );
}

pub fn status(args: StatusArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let mut client = client::connect(&args.conn.remote()?).await?;
        if let Some(job) = &args.job {
            let r = client.status(job).await?;
            let s = r.status.unwrap_or_default();
            println!("job:        {}", s.job_id);
            println!("name:       {}", s.name);
            println!("state:      {}", state_name(s.state));
            println!("scene:      {}", r.root);
            if let Some(img) = r.image {
                println!("image:      {}x{}", img.width, img.height);
            }
            println!("iteration:  {}", s.iteration);
            println!("unit:       {}", s.unit);
            println!("tiles:      {}/{}", s.tiles_done, s.tiles_total);
            println!("samples:    {}/{}", s.samples_done, s.samples_total);
            println!("spp done:   {}", s.spp_done);
            println!("nonfinite:  {}", s.nonfinite);
            if let Some(e) = s.eta_seconds {
                println!("eta:        {e:.0} s");
            }
            println!("priority:   {}", s.priority);
            println!("submitted:  {}", ms_ago(s.submitted_unix_ms));
            if !s.failure_reason.is_empty() {
                println!("failure:    {}", s.failure_reason);
            }
            return Ok(());
        }
        let jobs = client.list_jobs().await?;
        println!(
            "{:<24} {:<20} {:<11} {:>4} {:>11} {:>7} {:>6} {:>4}  REASON",
            "JOB", "NAME", "STATE", "ITER", "TILES", "SAMPLES", "ETA", "PRIO"
        );
        for s in &jobs {
            print_job_row(s);
        }
        print_batches(&jobs);
        let workers = client.list_workers().await?;
        println!();
        println!(
            "{:<6} {:<16} {:<20} {:>7} {:>7} {:<10} {:<12} LEASES",
            "WORKER", "NAME", "HOST", "THREADS", "TILES", "STATE", "HEARTBEAT"
        );
        for w in &workers {
            let state = if !w.connected && w.draining {
                "left"
            } else if !w.connected {
                "lost"
            } else if w.draining {
                "draining"
            } else {
                "connected"
            };
            println!(
                "{:<6} {:<16} {:<20} {:>7} {:>7} {:<10} {:<12} {:?}",
                w.worker_id,
                w.worker_name,
                w.host_name,
                w.threads,
                w.tiles_done,
                state,
                ms_ago(w.last_heartbeat_unix_ms),
                w.lease_ids
            );
        }
        Ok(())
    })
}

/// Exits 0 if the service is SERVING (a container health check), 1 otherwise.
pub fn health(args: HealthArgs) -> Result<()> {
    let r = remote(&args.coordinator, None, args.tls_ca.as_deref())?;
    let serving = runtime()?.block_on(client::health(&r, &args.service))?;
    let name = if args.service.is_empty() {
        "the farm"
    } else {
        &args.service
    };
    if serving {
        println!("{name}: SERVING");
        Ok(())
    } else {
        bail!("{name}: not serving")
    }
}

pub fn cancel(args: CancelArgs) -> Result<()> {
    let target = match (args.job, args.batch) {
        (_, Some(b)) => Target::Batch(b),
        (Some(j), None) => Target::Job(j),
        (None, None) => bail!("name a job, or a batch with --batch"),
    };
    runtime()?.block_on(async move {
        let mut client = client::connect(&args.conn.remote()?).await?;
        for job in target.jobs(&mut client).await? {
            let r = client.cancel(&job).await?;
            let state = r.status.map_or("unknown", |s| state_name(s.state));
            if r.cancelled {
                println!("{job}: cancelled");
            } else {
                println!("{job}: not cancelled (already {state})");
            }
        }
        Ok(())
    })
}

pub fn priority(args: PriorityArgs) -> Result<()> {
    let (target, p) = match (args.batch, args.args.as_slice()) {
        (Some(b), [p]) => (Target::Batch(b), p),
        (None, [j, p]) => (Target::Job(j.clone()), p),
        (Some(_), _) => bail!("with --batch, give the priority alone"),
        (None, _) => bail!("give a job and its priority (or --batch NAME and a priority)"),
    };
    let priority: i32 =
        (p.parse()).with_context(|| format!("priority {}: not a whole number", bounded(p)))?;
    runtime()?.block_on(async move {
        let mut client = client::connect(&args.conn.remote()?).await?;
        for job in target.jobs(&mut client).await? {
            let r = client.set_priority(&job, priority).await?;
            let state = r.status.map_or("unknown", |s| state_name(s.state));
            if r.changed {
                println!("{job}: priority {priority}");
            } else {
                println!("{job}: priority not changed (already {state})");
            }
        }
        Ok(())
    })
}

pub fn fetch(args: FetchArgs) -> Result<()> {
    runtime()?.block_on(async move {
        let mut signals = Signals::new()?;
        let outs = open_outputs(&args.output)?;
        let work = async {
            let mut client = client::connect(&args.conn.remote()?).await?;
            write_results(&mut client, &args.job, outs).await
        };
        tokio::select! {
            r = work => r,
            _ = signals.recv() => bail!("interrupted"),
        }
    })
}

// ----- cluster -----

/// The child processes and temporary directory of a local cluster; dropping it stops the
/// children (SIGTERM, then SIGKILL after 5 s) and removes the directory.
struct Cluster {
    children: Vec<(String, Child)>,
    dir: PathBuf,
}

impl Cluster {
    fn stop(&mut self) {
        for (_, c) in &self.children {
            // SAFETY: kill(2) on our own child's pid.
            unsafe {
                libc::kill(c.id() as libc::pid_t, libc::SIGTERM);
            }
        }
        let deadline = Instant::now() + Duration::from_secs(5);
        for (name, c) in &mut self.children {
            loop {
                match c.try_wait() {
                    Ok(Some(_)) => break,
                    Ok(None) if Instant::now() < deadline => {
                        std::thread::sleep(Duration::from_millis(20))
                    }
                    _ => {
                        tracing::warn!("{name} did not stop after SIGTERM: killing it");
                        let _ = c.kill();
                        let _ = c.wait();
                        break;
                    }
                }
            }
        }
        self.children.clear();
        let _ = std::fs::remove_dir_all(&self.dir);
    }

    /// An error if a child has exited.
    fn check_alive(&mut self) -> Result<()> {
        for (name, c) in &mut self.children {
            if let Some(st) = c.try_wait()? {
                bail!("{name} exited early ({st})");
            }
        }
        Ok(())
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        self.stop();
    }
}

fn random_hex(bytes: usize) -> String {
    let mut buf = vec![0u8; bytes];
    let ok = std::fs::File::open("/dev/urandom")
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut buf))
        .is_ok();
    if !ok {
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let h = blake3_like(format!("{t}-{}", std::process::id()).as_bytes());
        buf = h;
    }
    buf.iter().map(|b| format!("{b:02x}")).collect()
}

/// A weak fallback mix (only when /dev/urandom is unreadable).
fn blake3_like(data: &[u8]) -> Vec<u8> {
    let mut x: u64 = 0xcbf2_9ce4_8422_2325;
    let mut out = Vec::with_capacity(16);
    for round in 0..2u64 {
        for &b in data {
            x = (x ^ b as u64 ^ round).wrapping_mul(0x0100_0000_01b3);
        }
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

fn free_port() -> Result<u16> {
    let l = std::net::TcpListener::bind("127.0.0.1:0").context("finding a free port")?;
    Ok(l.local_addr()?.port())
}

pub fn cluster(args: ClusterArgs) -> Result<()> {
    if args.workers == 0 {
        bail!("--workers must be at least 1");
    }
    let threads = args
        .threads_per_worker
        .unwrap_or_else(|| (default_threads() / args.workers).max(1));
    if threads == 0 {
        bail!("--threads-per-worker must be at least 1");
    }
    let opts = job_options(&args.job, &args.scene, None, 0)?;
    let rt = runtime()?;
    rt.block_on(async move {
        let mut signals = Signals::new()?;
        let outs = open_outputs(&args.output)?;
        let exe = std::env::current_exe().context("finding the pathfarm executable")?;
        let dir = std::env::temp_dir().join(format!(
            "pathfarm-cluster-{}-{}",
            std::process::id(),
            random_hex(4)
        ));
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let mut cluster = Cluster {
            children: Vec::new(),
            dir: dir.clone(),
        };
        let token = random_hex(16);
        let port = free_port()?;
        let url = format!("http://127.0.0.1:{port}");
        let log = std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into());
        let spawn = |what: &str, argv: Vec<String>| -> Result<Child> {
            Command::new(&exe)
                .args(&argv)
                .env("PATHFARM_TOKEN", &token)
                .env("RUST_LOG", &log)
                .env_remove("PATHFARM_COORDINATOR")
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .spawn()
                .with_context(|| format!("starting {what}"))
        };
        let c = spawn(
            "the coordinator",
            vec![
                "coordinator".into(),
                "--listen".into(),
                format!("127.0.0.1:{port}"),
                "--data".into(),
                dir.join("coordinator").to_string_lossy().into_owned(),
            ],
        )?;
        cluster.children.push(("the coordinator".into(), c));
        // The scene is bundled (loaded to find its files) while the coordinator and the
        // workers start.
        let collecting = tokio::spawn(client::Collected::of_owned(
            args.scene.clone(),
            opts.defines.clone(),
            opts.integrator.clone(),
        ));
        let work = async {
            // Wait until the coordinator answers.
            let start = Instant::now();
            let mut client = loop {
                cluster.check_alive()?;
                let r = remote(&url, Some(&token), None)?;
                if let Ok(mut c) = client::connect(&r).await {
                    if c.list_workers().await.is_ok() {
                        break c;
                    }
                }
                if start.elapsed() > Duration::from_secs(60) {
                    bail!("the coordinator did not answer within 60 s");
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            };
            // Workers start once the coordinator answers: they connect at once instead of
            // backing off (and warning) while it starts, and start while the bundle uploads.
            for i in 0..args.workers {
                let c = spawn(
                    "a worker",
                    vec![
                        "worker".into(),
                        "--coordinator".into(),
                        url.clone(),
                        "--threads".into(),
                        threads.to_string(),
                        "--name".into(),
                        format!("cluster-{i}"),
                        "--cache".into(),
                        dir.join(format!("worker-{i}"))
                            .to_string_lossy()
                            .into_owned(),
                    ],
                )?;
                cluster.children.push((format!("worker {i}"), c));
            }
            let collected = collecting.await.context("bundling the scene")??;
            let job = client.submit_collected(&collected, &opts).await?;
            tracing::info!(
                "submitted job {job} to a cluster of {} workers",
                args.workers
            );
            let status = {
                let watch = wait_for(&mut client, &job);
                tokio::pin!(watch);
                let mut tick = tokio::time::interval(Duration::from_millis(500));
                loop {
                    tokio::select! {
                        r = &mut watch => break r?,
                        _ = tick.tick() => cluster.check_alive()?,
                    }
                }
            };
            write_results(&mut client, &job, outs).await?;
            print_summary(&status);
            anyhow::Ok(())
        };
        let r = tokio::select! {
            r = work => r,
            _ = signals.recv() => Err(anyhow::anyhow!("interrupted")),
        };
        cluster.stop();
        r
    })
}
