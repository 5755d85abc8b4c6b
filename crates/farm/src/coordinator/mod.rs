//! The coordinator: the farm's gRPC server. It serves the client API (`pathfarm.v1.Jobs`:
//! blobs, jobs, results, workers) and the worker API (`pathfarm.v1.Workers`: the control
//! stream, blob fetches, tile uploads), plus gRPC health and reflection.
//!
//! Each guided job is driven by a [`Session`]: its units are split into tiles, offered to
//! the [`Scheduler`], leased to workers, and the uploaded tiles (pixel sums and guide
//! statistics) are handed back to the session, which trains the guide exactly as the
//! one-process render does (bit-identical results).
//!
//! # Persistence and restarts
//!
//! Blobs live in `DATA/blobs/<hex digest>`; job records in a redb database,
//! `DATA/jobs.redb`. After a restart, jobs that were DONE, FAILED or CANCELLED are listed as
//! they were (and a DONE job's results can still be downloaded). Jobs that were QUEUED or
//! running **resume from their last checkpoint**: between training iterations the session's
//! state ([`Session::checkpoint`]) is stored as a blob and named in the job record, and a
//! restarted coordinator restores the session from it; the units after it are those an
//! uninterrupted run renders, so the result has the same bits. (A job without a usable
//! checkpoint starts over, which gives the same bits too, later.) The work since the last
//! checkpoint, at most one iteration, is rendered again.
//!
//! Concurrency: one [`Mutex`] holds the scheduler, the jobs with their sessions and the
//! workers' channels; it is never held across an `.await`.

mod checkpoints;
mod dashboard;
mod db;
mod departed;
mod guide_view;
#[cfg(test)]
mod hardening_tests;
mod job_log;
mod ledger;
mod metrics;
mod resources;
mod service;
mod store;
mod sweep;
#[cfg(test)]
mod tests;
mod throughput;

pub use job_log::JobLogs;
pub use resources::Resources;

use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use pathfarm_guide::SdTree;
use pathfarm_proto::v1;
use pathfarm_render::film::Film;
use pathfarm_render::guided::{self, Budget, FallbackPolicy, Records, Session, Splatting};
use pathfarm_render::pass::{PassKind, PassSpec};
use pathfarm_render::{Purpose, Region, Scene, World};
use pathfarm_scene::{GuidedParams, Limits};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tonic::Status;

use crate::bundle::{
    self, Built, BundleLimits, Digest, Manifest, ManifestEntry, SceneBuild, SceneOptions,
};
use crate::client::is_terminal;
use crate::codec;
use crate::driver::{Blame, Blocklist, JobDriver, Offer, Standing, Step, Tiling};
use crate::scheduler::{Event, JobId, LeaseId, Millis, Scheduler, SchedulerConfig, WorkerId};
use crate::tiling::CostMap;

use db::{Db, JobRecord};
use ledger::{RecordsEnd, RecordsLedger, UnitLedger};
use metrics::Metrics;
use store::BlobStore;

/// How the coordinator runs.
#[derive(Clone, Debug)]
pub struct CoordinatorConfig {
    /// The gRPC address to listen on.
    pub listen: SocketAddr,
    /// Where blobs, temporary files and the job database live.
    pub data_dir: PathBuf,
    /// If set, every RPC of both services needs `authorization: Bearer <token>`.
    pub token: Option<String>,
    /// If set, the gRPC port speaks TLS only (rustls) with this certificate chain and key
    /// (PEM), so tokens and scenes never cross the network in clear.
    pub tls: Option<TlsIdentity>,
    /// If set, Prometheus metrics (text format) are served at `GET /metrics` on this address.
    pub metrics: Option<SocketAddr>,
    /// If set, the web dashboard is served on this address (it needs the token; over TLS
    /// with the same certificate when `tls` is set).
    pub http: Option<SocketAddr>,
    /// If set, signing in to the dashboard with this token gives a session that may look
    /// but not act (no cancel, no priority change). Not a token of the API.
    pub viewer_token: Option<String>,
    /// Scene loading limits (files are always confined to the bundle).
    pub limits: Limits,
    /// What a bundle may hold.
    pub bundle_limits: BundleLimits,
    /// Lease timeouts and attempts.
    pub scheduler: SchedulerConfig,
    /// What jobs, uploads and peers may take.
    pub resources: Resources,
    /// Each job's last log lines, shown on its dashboard page: fed by the process's
    /// `tracing` subscriber when it installs this as a layer (empty otherwise).
    pub job_logs: JobLogs,
    /// How often a running job's session is written to disk, at an iteration's end: a
    /// restarted coordinator, or a job rolled back after losing records, resumes from the
    /// last one written (the same bits; what was rendered since is rendered again). The
    /// first at the first iteration's end this long after the job started, each next this
    /// long after the one before; zero: at every iteration's end. A 1920x1080 session
    /// writes 190 MB a new iteration film, which on a job of seconds an iteration costs
    /// the coordinator more CPU than the splat (`docs/decisions/checkpoint-interval.md`).
    pub checkpoint_interval: Duration,
    /// Tile edge when a job does not set one; `None` (the default): a few tiles per
    /// worker thread, of equal cost as measured in the job's earlier units
    /// ([`crate::tiling`]).
    pub default_tile: Option<u32>,
}

/// The coordinator's TLS certificate chain and private key, PEM.
#[derive(Clone)]
pub struct TlsIdentity {
    pub cert_pem: Vec<u8>,
    pub key_pem: Vec<u8>,
}

impl std::fmt::Debug for TlsIdentity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // never print the key
        write!(
            f,
            "TlsIdentity {{ cert: {} bytes, key: .. }}",
            self.cert_pem.len()
        )
    }
}

/// Why the coordinator could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum CoordinatorError {
    #[error("cannot listen on {addr}: {error}")]
    Bind {
        addr: SocketAddr,
        error: std::io::Error,
    },
    #[error("data directory {}: {error}", dir.display())]
    DataDir { dir: PathBuf, error: std::io::Error },
    #[error("{0}")]
    Database(String),
    #[error("gRPC reflection: {0}")]
    Reflection(String),
    #[error("TLS certificate or key: {0}")]
    Tls(String),
    #[error("gRPC server: {0}")]
    Transport(#[from] tonic::transport::Error),
}

/// Binds `cfg.listen` and serves until `shutdown` completes.
pub async fn serve(
    cfg: CoordinatorConfig,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), CoordinatorError> {
    // The data directory first: accepting connections means ready.
    let shared = Shared::open(cfg)?;
    let addr = shared.cfg.listen;
    let listener = TcpListener::bind(addr)
        .await
        .map_err(|error| CoordinatorError::Bind { addr, error })?;
    service::run(shared, listener, Some(addr), shutdown).await
}

/// As [`serve`], on an already bound listener (`cfg.listen` is ignored).
pub async fn serve_with_listener(
    cfg: CoordinatorConfig,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), CoordinatorError> {
    let shared = Shared::open(cfg)?;
    let addr = listener.local_addr().ok();
    service::run(shared, listener, addr, shutdown).await
}

// ----- shared state -----

pub(crate) struct Shared {
    pub(crate) cfg: CoordinatorConfig,
    pub(crate) blobs: BlobStore,
    pub(crate) db: Db,
    pub(crate) state: Mutex<State>,
    pub(crate) epoch: Instant,
    pub(crate) serving: AtomicBool,
    pub(crate) metrics: Metrics,
    /// The next job session's records epoch: unique for the coordinator's data (seeded
    /// with the clock at start, so a restarted coordinator's epochs differ from its
    /// predecessor's).
    pub(crate) next_epoch: AtomicU64,
    /// Upload buffers, in KiB: an upload holds what its header announced while it is read
    /// and decoded ([`Resources::upload_memory_bytes`]).
    pub(crate) upload_kib: Arc<tokio::sync::Semaphore>,
    /// A blob sweep is running ([`sweep`]), and when the last one started.
    pub(crate) sweeping: AtomicBool,
    pub(crate) last_sweep_ms: AtomicU64,
    /// What clients read about jobs and workers without waiting for the state lock (a
    /// merge or a refinement may hold it for most of a second): see [`JobView`].
    pub(crate) views: std::sync::RwLock<BTreeMap<u64, JobView>>,
    pub(crate) workers_view: std::sync::RwLock<Vec<v1::WorkerInfo>>,
    /// The work accepted over the last minutes (its own lock: the dashboard reads it).
    pub(crate) throughput: Mutex<throughput::Throughput>,
    /// Connected workers by their upload key (`Registered.upload_key`): an upload's sender,
    /// found without the state lock.
    pub(crate) keys: std::sync::RwLock<HashMap<[u8; 32], u64>>,
    /// Heartbeats received and not yet applied to the scheduler: a heartbeat is taken at
    /// once with the instant it arrived, and applied by the next holder of the state lock
    /// before anything else ([`Shared::lock`]), so its handling never waits for the lock and
    /// its effect (the worker alive, its leases extended) is as of its arrival.
    pub(crate) beats: Mutex<Vec<Beat>>,
    /// The scene and tree the dashboard's last guide picture was drawn from.
    pub(crate) guide_cache: Mutex<guide_view::GuideCache>,
    /// The world of the last frame of a batch validated, by [`bundle::world_key`]: the next
    /// frames (the same world, the camera moved) are validated by a scan of their text
    /// against it, not by decoding the files it was checked from again. One world's meshes
    /// and textures (no BVH), within the scene limits; none after a lone job's validation.
    pub(crate) inspected: Mutex<Option<(bundle::Digest, Arc<World>)>>,
}

/// Why a stored bundle's scene did not load ([`Shared::load_bundle`]).
#[derive(Debug, thiserror::Error)]
pub(crate) enum BundleLoad {
    /// Its files could not be laid out.
    #[error("bundle: {0}")]
    Bundle(String),
    /// The scene did not load or build.
    #[error("{0}")]
    Scene(String),
    /// The resolution override is out of the limits.
    #[error("settings.scene.resolution: {0}")]
    Resolution(String),
}

/// A heartbeat waiting to be applied ([`Shared::beats`]).
pub(crate) struct Beat {
    pub(crate) worker: WorkerId,
    pub(crate) at: Millis,
    pub(crate) unix_ms: u64,
    pub(crate) leases: Vec<LeaseId>,
}

/// What a client reads about a job without the state lock: its status as of its last
/// change (the job's watch channel, which the coordinator updates at every change) and what
/// its submission fixed.
#[derive(Clone)]
pub(crate) struct JobView {
    pub(crate) status: watch::Receiver<v1::JobStatus>,
    pub(crate) settings: Option<v1::JobSettings>,
    pub(crate) root: String,
    pub(crate) image: Option<v1::Resolution>,
}

/// A worker's control stream, bounded ([`Resources::outbox_messages`]).
pub(crate) type Outbox = mpsc::Sender<Result<v1::CoordinatorMessage, Status>>;

/// A connected worker: one control stream. It is forgotten when the stream ends or the
/// scheduler declares it lost (its stream is then ended, and a worker that comes back
/// registers anew).
pub(crate) struct WorkerConn {
    pub(crate) tx: Outbox,
    pub(crate) credits: u32,
    pub(crate) register: v1::Register,
    pub(crate) registered_unix_ms: u64,
    pub(crate) last_unix_ms: u64,
    pub(crate) tiles_done: u64,
    pub(crate) draining: bool,
    /// `Registered.upload_key`: what its uploads name it by.
    pub(crate) upload_key: [u8; 32],
    /// Its outbox was full: it does not read its stream, and the next tick disconnects it.
    pub(crate) overflowed: AtomicBool,
}

impl WorkerConn {
    /// Queues `msg` on the worker's stream; a full outbox marks the worker for
    /// disconnection instead of growing (or blocking the state lock).
    pub(crate) fn post(&self, msg: v1::coordinator_message::Msg) {
        let m = v1::CoordinatorMessage { msg: Some(msg) };
        if let Err(mpsc::error::TrySendError::Full(_)) = self.tx.try_send(Ok(m)) {
            self.overflowed.store(true, Ordering::Relaxed);
        }
    }

    /// "host/name", as blocklists and logs name a worker across reconnections.
    pub(crate) fn identity(&self) -> String {
        format!("{}/{}", self.register.host_name, self.register.worker_name)
    }
}

/// A job being rendered: its driver (session, units in flight, records holders) and what
/// the coordinator keeps beside it (published blobs, accounts, checkpoints).
pub(crate) struct Active {
    pub(crate) driver: JobDriver,
    pub(crate) seed: u64,
    /// Where each unit in flight's time and bytes went, by unit.
    pub(crate) ledgers: Vec<(u64, UnitLedger)>,
    /// Checkpoints taken so far (a background write records its checkpoint only if no later
    /// one was taken meanwhile).
    pub(crate) checkpoint_seq: u64,
    /// When the next checkpoint is due ([`CoordinatorConfig::checkpoint_interval`]).
    pub(crate) checkpoint_due: Millis,
    /// The PNG preview of the image so far (updated at every iteration's end).
    pub(crate) preview: Option<Digest>,
    /// The films the last recorded checkpoint stored, so the next one stores only new films.
    pub(crate) film_digests: Vec<(Weak<Film>, Digest)>,
    /// The blob of the tree version last published (or checkpointed).
    pub(crate) tree_digest: Option<(u32, Digest)>,
    /// The fractions of the last two units issued (the units in flight are among them).
    pub(crate) fractions_digests: Vec<((u32, u32), Digest)>,
    /// The pixel estimate last published, once one was (`Some(None)`: the job has none
    /// yet).
    pub(crate) estimate_digest: Option<Option<Digest>>,
    pub(crate) samples_total: u64,
    /// What the job was started from: a roll back starts it again
    /// ([`Shared::roll_back`]).
    pub(crate) prepared: Prepared,
    /// The accounts of the records collection in progress.
    pub(crate) records_ledger: Option<RecordsLedger>,
    /// The memory reserved for the session ([`Resources::job_memory_bytes`]).
    pub(crate) memory: u64,
}

impl Active {
    /// The blobs the job's units in flight refer to: their published inputs (tree,
    /// fractions, pixel estimate) and the preview.
    pub(crate) fn blobs(&self) -> Vec<Digest> {
        let estimate = self.estimate_digest.flatten();
        let fractions = self.fractions_digests.iter().map(|x| x.1);
        [self.tree_digest.map(|x| x.1), estimate, self.preview]
            .into_iter()
            .flatten()
            .chain(fractions)
            .collect()
    }

    pub(crate) fn session(&self) -> &Session {
        self.driver.session()
    }

    /// The digest of the fractions `spec` samples with.
    fn fractions_of(&self, spec: &PassSpec) -> Option<Digest> {
        let v = (spec.tree_version, spec.fraction_version);
        let found = self.fractions_digests.iter().find(|x| x.0 == v);
        found.map(|x| x.1)
    }

    fn ledger(&mut self, unit: u64) -> Option<&mut UnitLedger> {
        self.ledgers
            .iter_mut()
            .find(|l| l.0 == unit)
            .map(|l| &mut l.1)
    }
}

/// Where a job is in its life on this coordinator. Each phase holds what the job has in
/// it, so a job cannot be both waiting and running; the job record's `state` is the
/// phase's proto form for clients and the database.
pub(crate) enum Phase {
    /// Waiting for memory, holding only its request; what its submission was validated
    /// into, if this coordinator validated it (a restarted coordinator validates it again
    /// when it starts).
    Queued(Option<Box<Prepared>>),
    /// Admitted with this much memory: its session is being built off the state lock.
    Building(u64),
    /// Rendering.
    Running(Box<Active>),
    /// Rendered: its results are being encoded and stored off the state lock.
    Assembling,
    /// DONE, FAILED or CANCELLED (the record says which).
    Ended,
}

pub(crate) struct Job {
    pub(crate) record: JobRecord,
    pub(crate) phase: Phase,
    pub(crate) watch: watch::Sender<v1::JobStatus>,
    /// Its bad results per worker identity ([`WorkerConn::identity`]), and the workers
    /// that get no more of its leases.
    pub(crate) blocklist: Blocklist,
}

impl Job {
    pub(crate) fn new(record: JobRecord, phase: Phase, n: u64, r: &Resources) -> Job {
        let (watch, _) = watch::channel(v1::JobStatus::default());
        let job = Job {
            record,
            phase,
            watch,
            blocklist: Blocklist::new(r.bad_uploads_per_job),
        };
        job.watch.send_replace(job.status(n));
        job
    }

    /// The memory the job holds now.
    pub(crate) fn memory(&self) -> u64 {
        match &self.phase {
            Phase::Building(m) => *m,
            Phase::Running(a) => a.memory,
            _ => 0,
        }
    }

    pub(crate) fn active(&self) -> Option<&Active> {
        match &self.phase {
            Phase::Running(a) => Some(a),
            _ => None,
        }
    }

    pub(crate) fn active_mut(&mut self) -> Option<&mut Active> {
        match &mut self.phase {
            Phase::Running(a) => Some(a),
            _ => None,
        }
    }

    /// Moves a running job to `next`, giving back what it ran with.
    pub(crate) fn stop_running(&mut self, next: Phase) -> Option<Active> {
        if !matches!(self.phase, Phase::Running(_)) {
            return None;
        }
        match std::mem::replace(&mut self.phase, next) {
            Phase::Running(a) => Some(*a),
            _ => unreachable!("checked"),
        }
    }

    pub(crate) fn is_ended(&self) -> bool {
        matches!(self.phase, Phase::Ended)
    }

    pub(crate) fn status(&self, n: u64) -> v1::JobStatus {
        let mut s = status_of(n, &self.record, self.active());
        s.blocked_workers = self.blocklist.reasons();
        s
    }
}

pub(crate) struct State {
    pub(crate) sched: Scheduler,
    pub(crate) jobs: BTreeMap<u64, Job>,
    pub(crate) workers: BTreeMap<u64, WorkerConn>,

    /// Workers that left recently, shown as lost or left.
    pub(crate) departed: departed::Departed,
    pub(crate) next_job: u64,
    pub(crate) next_worker: u64,
    /// Blobs that jobs stopped referring to, deleted by the next
    /// [`Shared::collect_garbage`] unless another job still refers to them.
    pub(crate) garbage: Vec<Digest>,
}

/// Render threads of the connected workers that take work (at least 1): what a unit's tiles
/// are shared among.
pub(crate) fn slots(workers: &BTreeMap<u64, WorkerConn>) -> usize {
    let n: u64 = workers
        .values()
        .filter(|w| !w.draining)
        .map(|w| w.register.threads.max(1) as u64)
        .sum();
    n.clamp(1, 1 << 16) as usize
}

/// The memory a job's session takes on the coordinator (its films and samples).
pub(crate) fn session_memory(record: &JobRecord) -> u64 {
    pathfarm_render::scene::guided_session_bytes(record.width, record.height)
}

/// What `ListWorkers` says of connected worker `id`.
fn worker_info(st: &State, id: u64, w: &WorkerConn) -> v1::WorkerInfo {
    let held = st.sched.held_by(WorkerId(id));
    v1::WorkerInfo {
        worker_id: id,
        host_name: w.register.host_name.clone(),
        worker_name: w.register.worker_name.clone(),
        threads: w.register.threads,
        tiles_done: w.tiles_done,
        last_heartbeat_unix_ms: w.last_unix_ms,
        lease_ids: held.into_iter().map(|l| l.0).collect(),
        build_id: w.register.build_id.clone(),
        protocol_version: w.register.protocol_version,
        draining: w.draining,
        registered_unix_ms: w.registered_unix_ms,
        connected: true,
        departed_reason: String::new(),
        departed_unix_ms: 0,
    }
}

pub(crate) fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

pub(crate) fn job_name(n: u64) -> String {
    format!("job-{n}")
}

/// The number of a job id `job-N` exactly as [`job_name`] writes it: no sign, no leading
/// zero, no other spelling of the same number.
pub(crate) fn parse_job(id: &str) -> Option<u64> {
    let digits = id.strip_prefix("job-")?;
    let canonical = !digits.is_empty()
        && digits.bytes().all(|b| b.is_ascii_digit())
        && (digits == "0" || !digits.starts_with('0'));
    canonical.then(|| digits.parse().ok())?
}

/// What SubmitJob (or a restart) derives from a job's request.
pub(crate) struct Prepared {
    params: GuidedParams,
    budget: Budget,
    seed: u64,
    width: u32,
    height: u32,
    /// What the session splats units of few samples per pixel with.
    splatting: Splatting,
    tree: SdTree,
    tile: Option<u32>,
}

impl Prepared {
    /// A copy (the tree through its wire form: a fresh tree is a few hundred bytes).
    fn duplicate(&self) -> Prepared {
        Prepared {
            params: self.params.clone(),
            budget: self.budget,
            seed: self.seed,
            width: self.width,
            height: self.height,
            splatting: self.splatting,
            tree: SdTree::decode(&self.tree.encode()).expect("a tree decodes its own encoding"),
            tile: self.tile,
        }
    }
}

impl Shared {
    fn open(cfg: CoordinatorConfig) -> Result<Arc<Shared>, CoordinatorError> {
        let dir = cfg.data_dir.clone();
        std::fs::create_dir_all(&dir).map_err(|error| CoordinatorError::DataDir {
            dir: dir.clone(),
            error,
        })?;
        let blobs = BlobStore::open(&dir).map_err(|error| CoordinatorError::DataDir {
            dir: dir.clone(),
            error,
        })?;
        let db = Db::open(&dir.join("jobs.redb")).map_err(CoordinatorError::Database)?;
        let records = db.all().map_err(CoordinatorError::Database)?;
        let state = State {
            sched: Scheduler::new(cfg.scheduler.clone()),
            jobs: BTreeMap::new(),
            workers: BTreeMap::new(),
            departed: Default::default(),
            next_job: 1,
            next_worker: 1,
            garbage: Vec::new(),
        };
        let upload_kib = (cfg.resources.upload_memory_bytes >> 10).clamp(1, u32::MAX as u64 >> 3);
        let shared = Arc::new(Shared {
            upload_kib: Arc::new(tokio::sync::Semaphore::new(upload_kib as usize)),
            sweeping: AtomicBool::new(false),
            last_sweep_ms: AtomicU64::new(0),
            views: Default::default(),
            keys: Default::default(),
            workers_view: Default::default(),
            throughput: Default::default(),
            beats: Mutex::new(Vec::new()),
            guide_cache: Mutex::new(Default::default()),
            inspected: Mutex::new(None),
            cfg,
            blobs,
            db,
            state: Mutex::new(state),
            epoch: Instant::now(),
            serving: AtomicBool::new(false),
            metrics: Metrics::default(),
            next_epoch: AtomicU64::new(unix_ms()),
        });
        {
            // Jobs that were queued or running wait to be admitted again: nothing is
            // validated or allocated here, so a restart with any number of big jobs queued
            // costs no memory until each job's turn ([`Shared::admit`]).
            let mut st = shared.lock();
            for (n, mut record) in records {
                st.next_job = st.next_job.max(n + 1);
                let phase = match is_terminal(record.state) {
                    true => Phase::Ended,
                    false => {
                        tracing::info!(job = %job_name(n), "the job waits to restart");
                        record.state = v1::JobState::Queued as i32;
                        record.started_unix_ms = 0;
                        Phase::Queued(None)
                    }
                };
                shared.add_job(
                    &mut st,
                    n,
                    Job::new(record, phase, n, &shared.cfg.resources),
                );
            }
        }
        Ok(shared)
    }

    /// The state, with the heartbeats received meanwhile applied first.
    pub(crate) fn lock(&self) -> MutexGuard<'_, State> {
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        self.apply_beats(&mut st);
        st
    }

    /// Takes a heartbeat without waiting for the state lock ([`Shared::beats`]).
    pub(crate) fn beat(&self, beat: Beat) {
        self.beats
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(beat);
    }

    fn apply_beats(&self, st: &mut State) {
        let beats = std::mem::take(&mut *self.beats.lock().unwrap_or_else(|e| e.into_inner()));
        for b in beats {
            if let Some(w) = st.workers.get_mut(&b.worker.0) {
                w.last_unix_ms = b.unix_ms;
            }
            let Ok(stale) = st.sched.heartbeat(b.worker, &b.leases, b.at) else {
                continue;
            };
            // Only leases this worker was given are worth a cancel: one for every id a peer
            // makes up would amplify its heartbeats into our memory.
            for lease in stale {
                if st.sched.lease(lease).is_some_and(|v| v.worker == b.worker) {
                    send_cancel(st, b.worker, lease, "not this worker's lease any more");
                }
            }
        }
    }

    /// Adds job `n` to the state and to the views clients read.
    pub(crate) fn add_job(&self, st: &mut State, n: u64, job: Job) {
        let r = &job.record;
        let request = r.request.clone().unwrap_or_default();
        let view = JobView {
            status: job.watch.subscribe(),
            settings: request.settings,
            root: request.bundle.map(|b| b.root).unwrap_or_default(),
            image: (r.width > 0).then_some(v1::Resolution {
                width: r.width,
                height: r.height,
            }),
        };
        self.views
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .insert(n, view);
        st.jobs.insert(n, job);
    }

    /// The job view of `n`, if there is such a job.
    /// The blob of job `n`'s result `kind` (the running job's preview for a PNG before it
    /// is done), or why there is none yet. Takes the state lock: call off the executor.
    pub(crate) fn result_blob(&self, n: u64, kind: v1::ResultKind) -> Result<Digest, String> {
        let st = self.lock();
        let job = st.jobs.get(&n).ok_or_else(|| "no such job".to_string())?;
        let r = &job.record;
        let done = r.state == v1::JobState::Done as i32;
        let running_preview = job.active().and_then(|a| a.preview);
        if let (v1::ResultKind::PngPreview, Some(p), false) = (kind, running_preview, done) {
            return Ok(p);
        }
        let d = match kind {
            v1::ResultKind::Unspecified => return Err("kind: unspecified".into()),
            v1::ResultKind::Exr => &r.exr,
            v1::ResultKind::PngPreview => &r.png,
            v1::ResultKind::SdTree => &r.tree,
        };
        if !done || d.is_empty() {
            return Err(format!(
                "the result {kind:?} is available once the job is DONE (a PNG preview once \
                 its first iteration is done)"
            ));
        }
        <[u8; 32]>::try_from(d.as_slice())
            .map(Digest)
            .map_err(|_| "a stored result digest is not 32 bytes".to_string())
    }

    pub(crate) fn view(&self, n: u64) -> Option<JobView> {
        let views = self.views.read().unwrap_or_else(|e| e.into_inner());
        views.get(&n).cloned()
    }

    /// Forgets connected worker `id` (if it still is): its stream ends with `why`, so a
    /// worker that is still running sees it and registers again.
    pub(crate) fn forget_worker(&self, st: &mut State, id: u64, why: &str) {
        if let Some(w) = st.workers.remove(&id) {
            let last = worker_info(st, id, &w);
            st.departed.record(last, why, unix_ms());
            let mut keys = self.keys.write().unwrap_or_else(|e| e.into_inner());
            keys.remove(&w.upload_key);
            let status = Status::unavailable(format!("worker {id} {why}; register again"));
            let _ = w.tx.try_send(Err(status));
        }
        self.refresh_workers_view(st);
    }

    /// Refreshes what `ListWorkers` answers: the connected workers in registration order,
    /// then the departed ones, newest first.
    pub(crate) fn refresh_workers_view(&self, st: &State) {
        let connected = (st.workers.iter()).map(|(&id, w)| worker_info(st, id, w));
        let workers = connected.chain(st.departed.iter().cloned()).collect();
        *self.workers_view.write().unwrap_or_else(|e| e.into_inner()) = workers;
    }

    pub(crate) fn now(&self) -> Millis {
        Millis(self.epoch.elapsed().as_millis() as u64)
    }

    /// Advises the workers to build a just-submitted job's scene while it is validated
    /// ([`v1::Prefetch`]; see the worker's `prefetch` module): only when no other job is
    /// under way or waiting (a worker idle at another job's iteration boundary must not be
    /// made busy with a scene that may wait its turn) and when the bundle passes the cheap
    /// checks, with every blob here. Nothing depends on it: a lease builds what it needs.
    pub(crate) fn advise_prefetch(&self, req: &v1::SubmitJobRequest) {
        let Some(bundle) = &req.bundle else { return };
        let complete = manifest_from_proto(bundle).is_ok_and(|m| {
            m.validate(&self.cfg.bundle_limits).is_ok()
                && m.files.iter().all(|e| self.blobs.has(&e.digest))
        });
        if !complete {
            return;
        }
        let scene = req.settings.as_ref().and_then(|s| s.scene.clone());
        let settings = v1::SceneSettings {
            seed: None,
            ..scene.unwrap_or_default()
        };
        let prefetch = v1::Prefetch {
            bundle: Some(bundle.clone()),
            settings: Some(settings),
        };
        let msg = v1::coordinator_message::Msg::Prefetch(prefetch);
        let st = self.lock();
        if st.jobs.values().any(|j| !j.is_ended()) {
            return;
        }
        for w in st.workers.values().filter(|w| !w.draining) {
            w.post(msg.clone());
        }
    }

    /// The world of the last scene validated if it is `key`'s.
    fn inspected_world(&self, key: &bundle::Digest) -> Option<Arc<World>> {
        let held = self.inspected.lock().expect("inspected lock");
        held.as_ref()
            .filter(|(k, _)| k == key)
            .map(|(_, w)| w.clone())
    }

    /// The scene of a bundle whose files are in the blob store, with `settings` (built for
    /// `purpose`), from a temporary materialisation that is removed again. Messages name
    /// files by their bundle paths. Slow: call off the executor. A
    /// validation ([`Purpose::Inspect`]) of a scene whose world was the last one validated
    /// reads only its text and checks its files against the manifest.
    pub(crate) fn load_bundle(
        &self,
        manifest: &Manifest,
        settings: &v1::SceneSettings,
        overrides: &[(String, String)],
        purpose: Purpose,
    ) -> Result<Scene, BundleLoad> {
        let dir = self.blobs.temp_path("bundle");
        let local = |e: &dyn std::fmt::Display| bundle::in_bundle_paths(e, &dir);
        let result = (|| {
            bundle::materialize(manifest, |d| self.blobs.path(d), &dir)
                .map_err(|e| BundleLoad::Bundle(e.to_string()))?;
            let limits = Limits {
                confine_files: true,
                ..self.cfg.limits.clone()
            };
            let options = SceneOptions {
                overrides,
                integrator: settings.integrator.as_deref(),
                resolution: settings.resolution.as_ref().map(|r| (r.width, r.height)),
            };
            let held = |key: &Digest| match purpose {
                Purpose::Inspect => self.inspected_world(key),
                Purpose::Render => None,
            };
            let (scene, key, built) = bundle::build_scene(
                manifest, &dir, &options, &limits, purpose, held,
            )
            .map_err(|e| match e {
                SceneBuild::Load(e) => BundleLoad::Scene(local(&e)),
                SceneBuild::Resolution(m) => BundleLoad::Resolution(m),
                SceneBuild::Build(e) => BundleLoad::Scene(local(&e)),
            })?;
            if built == Built::OnHeldWorld {
                tracing::info!("{}: validated on the world validated last", manifest.root);
            }
            if purpose == Purpose::Inspect {
                *self.inspected.lock().expect("inspected lock") = Some((key, scene.shared_world()));
            }
            Ok(scene)
        })();
        let _ = std::fs::remove_dir_all(&dir);
        result
    }

    /// Validates a submission and loads its scene (from a temporary materialisation that is
    /// removed again). Slow: call off the async executor.
    pub(crate) fn prepare(&self, req: &v1::SubmitJobRequest) -> Result<Prepared, Status> {
        let bundle = req.bundle.as_ref().ok_or_else(|| bad("bundle: missing"))?;
        let manifest = manifest_from_proto(bundle)?;
        manifest
            .validate(&self.cfg.bundle_limits)
            .map_err(|e| bad(format!("bundle: {e}")))?;
        for e in &manifest.files {
            if !self.blobs.has(&e.digest) {
                return Err(Status::failed_precondition(format!(
                    "bundle file {:?}: blob {} is not on the coordinator (upload it first)",
                    e.path,
                    e.digest.to_hex()
                )));
            }
        }
        if req.name.len() > 256 {
            return Err(bad("name: more than 256 bytes"));
        }
        if req.batch.len() > 256 {
            return Err(bad("batch: more than 256 bytes"));
        }
        let settings = req.settings.clone().unwrap_or_default();
        let scene_settings = settings.scene.clone().unwrap_or_default();
        let overrides = overrides_of(&scene_settings)?;
        // The client bundled the scene without decoding it: a bad mesh is found here, and
        // named by its bundle path, not by this coordinator's. Images are checked by their
        // headers only (nothing here renders them): a bad one fails the workers' leases, and
        // so the job, naming it by its bundle path too.
        let scene = (self.load_bundle(&manifest, &scene_settings, &overrides, Purpose::Inspect))
            .map_err(|e| match e {
                BundleLoad::Bundle(m) => bad(format!("bundle: {m}")),
                BundleLoad::Scene(m) => bad(format!("scene {:?}: {m}", manifest.root)),
                BundleLoad::Resolution(m) => bad(format!("settings.scene.resolution: {m}")),
            })?;
        if req.batch.is_empty() {
            // Only a batch's next frame is likely to share the world: a lone job's is not
            // kept in memory.
            *self.inspected.lock().expect("inspected lock") = None;
        }
        let Some(params) = scene.guided.clone() else {
            let integrator = (scene_settings.integrator.as_deref())
                .map_or_else(|| "of the scene".to_string(), resources::echo);
            return Err(bad(format!(
                "integrator {integrator}: the farm renders guided_path jobs only"
            )));
        };
        let limits = &self.cfg.limits;
        let budget = match settings.budget {
            Some(v1::job_settings::Budget::Spp(n)) => {
                if n == 0 || n as u64 > limits.max_spp {
                    return Err(bad(format!(
                        "settings.spp: {n} is not between 1 and {} (Limits::max_spp)",
                        limits.max_spp
                    )));
                }
                Budget::Spp(n)
            }
            Some(v1::job_settings::Budget::TimeSeconds(t)) => {
                if !(t.is_finite() && t >= MIN_TIME_SECONDS && t <= limits.max_time_seconds) {
                    return Err(bad(format!(
                        "settings.time_seconds: {t} is not between {MIN_TIME_SECONDS} and {} \
                         (Limits::max_time_seconds)",
                        limits.max_time_seconds
                    )));
                }
                Budget::Seconds(t)
            }
            None => guided::params_budget(&params, &scene),
        };
        guided::check_budget(&params, budget).map_err(|e| bad(format!("settings: {e}")))?;
        let seed = scene_settings.seed.unwrap_or(scene.seed);
        let (lo, hi) = scene.world().accel.bounds();
        let tree = SdTree::new(lo, hi, guided::guide_config(&params, &scene));
        let tile = match settings.tile_size {
            0 => self.cfg.default_tile.map(|t| t.max(1)),
            t => Some(t),
        };
        Ok(Prepared {
            params,
            budget,
            seed,
            width: scene.width,
            height: scene.height,
            splatting: Splatting {
                filter: scene.filter,
                seed,
            },
            tree,
            tile,
        })
    }

    /// Units of job `n` ended (their tiles, and those of the units before them, are all
    /// in): checkpoint the session (between iterations), log the units' accounts, and go on
    /// with the next units.
    pub(crate) fn end_units(self: &Arc<Self>, st: &mut State, n: u64, ended: &[PassSpec]) {
        let checkpoint_s = self.between_iterations(st, n);
        if let Some(a) = st.jobs.get_mut(&n).and_then(|j| j.active_mut()) {
            for spec in ended {
                let Some(i) = a.ledgers.iter().position(|l| l.0 == spec.unit) else {
                    continue;
                };
                let (_, mut ledger) = a.ledgers.remove(i);
                ledger.checkpoint_s = checkpoint_s;
                let kind = format!("{:?}", spec.kind);
                ledger.finish(&job_name(n), spec, &kind, &self.metrics);
            }
        }
        self.drive(st, n);
    }

    /// What is done between two iterations of job `n` (if it is between two now): the
    /// preview updated and, when due, a checkpoint taken. Returns the seconds the
    /// checkpoint took on the critical path.
    fn between_iterations(self: &Arc<Self>, st: &mut State, n: u64) -> f64 {
        let Some(a) = st.jobs.get(&n).and_then(|j| j.active()) else {
            return 0.0;
        };
        if !a.session().between_iterations() {
            return 0.0;
        }
        self.update_preview(st, n);
        self.save_checkpoint(st, n)
    }

    /// Renders job `n`'s image so far as its PNG preview, in the background.
    fn update_preview(self: &Arc<Self>, st: &mut State, n: u64) {
        let Some(preview) = st
            .jobs
            .get(&n)
            .and_then(|j| j.active())
            .and_then(|a| a.session().preview())
        else {
            return;
        };
        let shared = self.clone();
        tokio::task::spawn_blocking(move || {
            let (w, h) = preview.size();
            let png = match pathfarm_render::output::encode_png_of_means(w, h, &preview.mean_rgb())
            {
                Ok(p) => p,
                Err(e) => return tracing::warn!(job = %job_name(n), "preview: {e}"),
            };
            let digest = match shared.blobs.put_unsynced(&png) {
                Ok(d) => d,
                Err(e) => return tracing::warn!(job = %job_name(n), "preview: {e}"),
            };
            let mut st = shared.lock();
            let st = &mut *st;
            match st.jobs.get_mut(&n).and_then(|j| j.active_mut()) {
                Some(a) => {
                    if let Some(old) = a.preview.replace(digest).filter(|&o| o != digest) {
                        st.garbage.push(old);
                    }
                }
                None => st.garbage.push(digest),
            }
            shared.publish_status(st, n);
        });
    }

    /// Starts queued jobs while their memory fits [`Resources::job_memory_bytes`]: the
    /// highest priority first, then the oldest; a job that does not fit yet holds back the
    /// jobs behind it (so a big job is not starved by small ones). Each admitted job's
    /// session is validated, built (films allocated) and resumed from its checkpoint off
    /// the state lock ([`Shared::build`]).
    pub(crate) fn admit(self: &Arc<Self>, st: &mut State) {
        let budget = self.cfg.resources.job_memory_bytes;
        let mut used: u64 = st.jobs.values().map(Job::memory).sum();
        let mut queued: Vec<(std::cmp::Reverse<i32>, u64)> = (st.jobs.iter())
            .filter(|(_, j)| matches!(j.phase, Phase::Queued(_)))
            .map(|(&n, j)| {
                let priority = j.record.request.as_ref().map_or(0, |r| r.priority);
                (std::cmp::Reverse(priority), n)
            })
            .collect();
        queued.sort_unstable();
        for (_, n) in queued {
            let job = st.jobs.get_mut(&n).expect("listed");
            let need = session_memory(&job.record);
            if used.saturating_add(need) > budget {
                return;
            }
            used += need;
            let Phase::Queued(prepared) = std::mem::replace(&mut job.phase, Phase::Building(need))
            else {
                unreachable!("listed as queued")
            };
            let record = job.record.clone();
            let shared = self.clone();
            tracing::info!(job = %job_name(n), memory_mb = need >> 20, "starting the job");
            tokio::task::spawn_blocking(move || {
                let built = shared.build(n, &record, prepared.map(|p| *p));
                shared.install(n, need, built);
            });
        }
    }

    /// Job `n`'s session, from its validated submission (or validated again after a
    /// restart), resumed from its checkpoint if it has one. Slow (films, checkpoint reads):
    /// off the state lock and the async threads.
    fn build(
        &self,
        n: u64,
        record: &JobRecord,
        prepared: Option<Prepared>,
    ) -> Result<(Session, Prepared), String> {
        let p = match prepared {
            Some(p) => p,
            None => {
                let request = record.request.clone().unwrap_or_default();
                self.prepare(&request).map_err(|status| {
                    format!(
                        "cannot restart the job after a coordinator restart: {}",
                        status.message()
                    )
                })?
            }
        };
        // The session's default tiling; each unit is re-tiled as it is issued (`drive`).
        let tiles = Region::tiles(p.width, p.height, p.tile.unwrap_or(32));
        let prepared = p.duplicate();
        let mut session = match self.resume(n, record, &p, &tiles) {
            Some(s) => s,
            None => Session::new(
                &p.params,
                p.budget,
                p.tree,
                (p.width, p.height),
                p.splatting,
                tiles,
                FallbackPolicy::Rule,
            ),
        };
        // Workers keep a tree version's quadtree records and ship them once, before
        // refinement (`docs/decisions/records-per-iteration.md`).
        session.set_records(Records::PerIteration);
        Ok((session, prepared))
    }

    /// Installs job `n`'s built session (unless the job ended meanwhile) and offers its
    /// first units.
    fn install(self: &Arc<Self>, n: u64, memory: u64, built: Result<(Session, Prepared), String>) {
        let mut st = self.lock();
        let st = &mut *st;
        let Some(job) = st.jobs.get_mut(&n) else {
            return;
        };
        if !matches!(job.phase, Phase::Building(_)) {
            // cancelled while it was built: its memory is free again
            self.admit(st);
            return;
        }
        let (session, p) = match built {
            Ok(b) => b,
            Err(reason) => {
                self.fail_job(st, n, reason);
                self.admit(st);
                return;
            }
        };
        let priority = job.record.request.as_ref().map_or(0, |r| r.priority);
        if let Err(e) = st.sched.add_job(JobId(n), priority, self.now()) {
            self.fail_job(st, n, format!("scheduler: {e}"));
            return;
        }
        let samples_total = match p.budget {
            Budget::Spp(s) => s as u64 * p.width as u64 * p.height as u64,
            Budget::Seconds(_) => 0,
        };
        job.record.width = p.width;
        job.record.height = p.height;
        job.record.state = v1::JobState::Queued as i32;
        job.record.spp_done = session.spp_done();
        job.record.samples_done = session.spp_done() * p.width as u64 * p.height as u64;
        job.record.started_unix_ms = 0;
        let tiling = match p.tile {
            Some(edge) => Tiling::Fixed(edge),
            None => Tiling::ByCost(CostMap::new(p.width, p.height)),
        };
        let epoch = self.next_epoch.fetch_add(1, Ordering::Relaxed);
        job.phase = Phase::Running(Box::new(Active {
            driver: JobDriver::new(session, tiling, epoch, self.now()),
            seed: p.seed,
            ledgers: Vec::new(),
            checkpoint_seq: 0,
            checkpoint_due: self.now() + self.cfg.checkpoint_interval,
            preview: None,
            film_digests: Vec::new(),
            tree_digest: None,
            fractions_digests: Vec::new(),
            estimate_digest: None,
            samples_total,
            prepared: p,
            records_ledger: None,
            memory,
        }));
        self.drive(st, n);
        self.dispatch(st);
    }

    /// Starts job `n` again from its last durable checkpoint (or from the start): a worker
    /// holding quadtree records of the iteration in progress was lost, or lost them. The
    /// job is deterministic, so only time is lost; its leases are cancelled and the
    /// workers' records of the old epoch are never added.
    pub(crate) fn roll_back(self: &Arc<Self>, st: &mut State, n: u64, why: &str) {
        let queued = Phase::Queued(None);
        let Some(a) = st.jobs.get_mut(&n).and_then(|j| j.stop_running(queued)) else {
            return;
        };
        tracing::warn!(job = %job_name(n), iteration = a.session().iteration(), "rolling back to the last checkpoint: {why}");
        self.metrics.roll_back();
        st.garbage.extend(a.blobs());
        let leases = st.sched.remove_job(JobId(n)).unwrap_or_default();
        for (worker, id) in leases {
            send_cancel(st, worker, id, "the job rolls back to its checkpoint");
        }
        if let Some(job) = st.jobs.get_mut(&n) {
            job.phase = Phase::Queued(Some(Box::new(a.prepared)));
        }
        self.publish_status(st, n);
        self.admit(st);
    }

    /// Advances job `n`'s driver until it waits: offers the units its session issues (two
    /// at once when training passes overlap), asks for records, checkpoints at iterations'
    /// ends, or finishes the job.
    pub(crate) fn drive(self: &Arc<Self>, st: &mut State, n: u64) {
        // Each unit's leases go out as soon as it is issued: issuing the next one (a new
        // iteration's second unit, after its fraction step) took tens of milliseconds that
        // the workers spent waiting at every iteration's start.
        while self.drive_once(st, n) {
            self.dispatch(st);
        }
    }

    /// One [`JobDriver::step`] of job `n`; true if there may be more to do at once.
    fn drive_once(self: &Arc<Self>, st: &mut State, n: u64) -> bool {
        let slots = slots(&st.workers);
        let now = self.now();
        let Some(a) = st.jobs.get_mut(&n).and_then(|j| j.active_mut()) else {
            return false;
        };
        let started = Instant::now();
        match a.driver.step(now, slots) {
            Err(e) => {
                self.fail_job(st, n, e.to_string());
                false
            }
            Ok(Step::Wait) => false,
            Ok(Step::Offer(offer)) => self.offer_unit(st, n, offer, started, now),
            Ok(Step::Collect(holders)) => {
                self.ask_for_records(st, n, &holders);
                false
            }
            Ok(Step::IterationEnded { iteration }) => {
                let end_s = started.elapsed().as_secs_f64();
                self.iteration_ended(st, n, iteration, end_s);
                true
            }
            Ok(Step::Done) => {
                self.job_rendered(st, n);
                false
            }
        }
    }

    /// Publishes a unit's new inputs and offers its tiles. True if it did.
    fn offer_unit(
        self: &Arc<Self>,
        st: &mut State,
        n: u64,
        offer: Offer,
        started: Instant,
        now: Millis,
    ) -> bool {
        let a = st
            .jobs
            .get_mut(&n)
            .and_then(|j| j.active_mut())
            .expect("driven");
        match self.publish(a, &offer) {
            Ok(replaced) => st.garbage.extend(replaced),
            Err(e) => {
                self.fail_job(st, n, format!("cannot store the unit's blobs: {e}"));
                return false;
            }
        }
        let spec = offer.spec;
        let publish_s = started.elapsed().as_secs_f64();
        let ledger = UnitLedger::start(publish_s, a.driver.seconds(now), &self.metrics);
        a.ledgers.push((spec.unit, ledger));
        tracing::info!(
            job = %job_name(n),
            unit = spec.unit,
            iteration = spec.iteration,
            kind = ?spec.kind,
            tiles = offer.tiles,
            "offering unit"
        );
        if let Err(e) = st.sched.offer_unit(JobId(n), spec.unit, offer.tiles) {
            self.fail_job(st, n, format!("scheduler: {e}"));
            return false;
        }
        self.publish_status(st, n);
        true
    }

    /// Asks the holders of job `n`'s records for them (`FlushRecords`).
    fn ask_for_records(self: &Arc<Self>, st: &mut State, n: u64, holders: &[WorkerId]) {
        let a = st
            .jobs
            .get_mut(&n)
            .and_then(|j| j.active_mut())
            .expect("driven");
        let Some((_, tree)) = a.tree_digest else {
            return self.roll_back(st, n, "records held of no published tree");
        };
        let flush = v1::FlushRecords {
            job_id: job_name(n),
            tree_digest: tree.0.to_vec(),
            records_epoch: a.driver.records_epoch(),
        };
        tracing::debug!(job = %job_name(n), ?holders, "collecting records");
        a.records_ledger = Some(RecordsLedger::start(holders.len()));
        for w in holders {
            if let Some(w) = st.workers.get(&w.0) {
                w.post(v1::coordinator_message::Msg::FlushRecords(flush.clone()));
            }
        }
    }

    /// Job `n`'s iteration `iteration` ended (its tree refined in `end_s`): the checkpoint of the
    /// iteration's end is taken and the collection's accounts logged.
    fn iteration_ended(self: &Arc<Self>, st: &mut State, n: u64, iteration: u32, end_s: f64) {
        let a = st
            .jobs
            .get_mut(&n)
            .and_then(|j| j.active_mut())
            .expect("driven");
        let ledger = a
            .records_ledger
            .take()
            .unwrap_or_else(|| RecordsLedger::start(0));
        let checkpoint_s = self.between_iterations(st, n);
        let ended = RecordsEnd {
            end_s,
            checkpoint_s,
        };
        ledger.finish(&job_name(n), iteration, ended, &self.metrics);
    }

    /// Job `n` is rendered: its results are assembled off the state lock, and its memory
    /// given back once they are.
    fn job_rendered(self: &Arc<Self>, st: &mut State, n: u64) {
        let job = st.jobs.get_mut(&n).expect("driven");
        let a = job.stop_running(Phase::Assembling).expect("driven");
        job.record.state = v1::JobState::Assembling as i32;
        job.record.spp_done = a.session().spp_done();
        job.record.iteration = a.session().iteration();
        job.record.nonfinite = a.session().nonfinite();
        job.record.iterations = iterations_of(a.session());
        job.record.fell_back_after = a.session().fell_back_after();
        let released = a.blobs();
        let _ = st.sched.remove_job(JobId(n));
        self.publish_status(st, n);
        // its memory is the films `finish` combines: given back once assembled
        self.admit(st);
        let session = a.driver.into_session();
        let shared = self.clone();
        // Combining the iteration films reads every one of them (190 MB each at 1920x1080):
        // not under the state lock.
        tokio::task::spawn_blocking(move || {
            let (film, stats, tree) = session.finish();
            tracing::info!(
                job = %job_name(n),
                iterations = stats.iterations.len(),
                "assembling results"
            );
            shared.assemble(n, film, tree, released)
        });
    }

    /// Encodes and stores job `n`'s results (off the state lock: EXR and PNG encoding take
    /// a while) and marks it DONE, unless it was cancelled meanwhile. The session's blobs
    /// (`released`, and the checkpoint) become garbage once the results are durable.
    fn assemble(
        self: &Arc<Self>,
        n: u64,
        film: pathfarm_render::Film,
        tree: SdTree,
        released: Vec<Digest>,
    ) {
        let encoded = (|| -> Result<[Vec<u8>; 3], String> {
            let exr = pathfarm_render::output::encode_exr(&film, pathfarm_render::output::Aovs::No)
                .map_err(|e| e.to_string())?;
            let png = pathfarm_render::output::encode_png(&film).map_err(|e| e.to_string())?;
            Ok([exr, png, tree.encode()])
        })();
        let put = |b: &Vec<u8>| self.blobs.put(b).map_err(|e| e.to_string());
        let written = encoded.and_then(|e| {
            e.iter().map(put).collect::<Result<Vec<_>, _>>()?;
            Ok(e)
        });
        let mut st = self.lock();
        let st = &mut *st;
        // A result may equal a blob already waiting in the garbage (the last preview is the
        // final PNG of a one-iteration job; the final tree is the last one published), and a
        // collection may have run between the write above and this lock: stored again if so.
        // Collections run under the lock, so once recorded below the results are safe.
        let stored = written.and_then(|e| {
            let d = e.each_ref().map(|b| bundle::digest_of(b));
            for (digest, bytes) in d.iter().zip(&e) {
                if !self.blobs.has(digest) {
                    put(bytes)?;
                }
            }
            Ok(d)
        });
        st.garbage.extend(released);
        let assembling = st
            .jobs
            .get(&n)
            .is_some_and(|j| matches!(j.phase, Phase::Assembling));
        match stored {
            Err(e) => self.fail_job(st, n, format!("cannot store the results: {e}")),
            Ok(results) if !assembling => st.garbage.extend(results),
            Ok([exr, png, tree]) => {
                let job = st.jobs.get_mut(&n).expect("checked");
                job.phase = Phase::Ended;
                job.record.state = v1::JobState::Done as i32;
                job.record.exr = exr.0.to_vec();
                job.record.png = png.0.to_vec();
                job.record.tree = tree.0.to_vec();
                job.record.finished_unix_ms = unix_ms();
                let parts = checkpoints::take_parts(&mut job.record);
                tracing::info!(job = %job_name(n), exr = %exr.to_hex(), "job done");
                self.persist(st, n);
                st.garbage.extend(parts);
                self.publish_status(st, n);
            }
        }
        self.collect_garbage(st);
    }

    /// Stores the new inputs of a unit ([`Offer`]; not durably: a unit's inputs are
    /// derived from the session, which a checkpoint keeps). Returns the digests they
    /// replace (garbage candidates).
    fn publish(&self, a: &mut Active, offer: &Offer) -> std::io::Result<Vec<Digest>> {
        let spec = &offer.spec;
        let mut replaced = Vec::new();
        // The iteration's checkpoint may have stored this tree version already.
        if offer.new_tree && a.tree_digest.map(|x| x.0) != Some(spec.tree_version) {
            let d = self.blobs.put_unsynced(&a.driver.encode_tree())?;
            replaced.extend(a.tree_digest.replace((spec.tree_version, d)).map(|x| x.1));
        }
        if offer.new_fractions {
            let d = self.blobs.put_unsynced(&a.driver.encode_fractions())?;
            a.fractions_digests
                .push(((spec.tree_version, spec.fraction_version), d));
            if a.fractions_digests.len() > 2 {
                replaced.push(a.fractions_digests.remove(0).1);
            }
        }
        if offer.new_estimate {
            let bytes = a.driver.encode_estimate();
            let digest = match bytes.is_empty() {
                true => None,
                false => Some(self.blobs.put_unsynced(&bytes)?),
            };
            replaced.extend(a.estimate_digest.replace(digest).flatten());
        }
        // Content-addressed: an input equal to the one it replaces is still in use.
        let live = a.blobs();
        replaced.retain(|d| !live.contains(d));
        Ok(replaced)
    }

    /// The blobs an ending job's session referred to: its published inputs and checkpoint.
    fn release_session_blobs(&self, st: &mut State, n: u64) {
        let Some(job) = st.jobs.get_mut(&n) else {
            return;
        };
        let mut out = checkpoints::take_parts(&mut job.record);
        out.extend(job.active().into_iter().flat_map(Active::blobs));
        st.garbage.extend(out);
    }

    /// Marks job `n` FAILED (if not already terminal), cancelling its leases.
    pub(crate) fn fail_job(self: &Arc<Self>, st: &mut State, n: u64, reason: String) {
        self.end_job(st, n, v1::JobState::Failed, reason);
    }

    /// Ends job `n` in `state` (FAILED or CANCELLED) unless it is already terminal. Returns
    /// whether it did.
    pub(crate) fn end_job(
        self: &Arc<Self>,
        st: &mut State,
        n: u64,
        state: v1::JobState,
        reason: String,
    ) -> bool {
        let Some(job) = st.jobs.get_mut(&n) else {
            return false;
        };
        if job.is_ended() {
            return false;
        }
        tracing::warn!(job = %job_name(n), state = ?state, "job ended: {reason}");
        self.release_session_blobs(st, n);
        let job = st.jobs.get_mut(&n).expect("checked");
        job.phase = Phase::Ended;
        job.record.state = state as i32;
        if state == v1::JobState::Failed {
            job.record.failure_reason = reason.clone();
        }
        job.record.finished_unix_ms = unix_ms();
        let cancelled = st.sched.remove_job(JobId(n)).unwrap_or_default();
        for (worker, lease) in cancelled {
            send_cancel(st, worker, lease, &reason);
        }
        self.persist(st, n);
        self.publish_status(st, n);
        self.collect_garbage(st);
        self.admit(st);
        true
    }

    /// Job `n` (not ended) is now of `priority`: stored, and applied to its admission
    /// and its next leases. False if the job has ended.
    pub(crate) fn set_priority(self: &Arc<Self>, st: &mut State, n: u64, priority: i32) -> bool {
        let Some(job) = st.jobs.get_mut(&n).filter(|j| !j.is_ended()) else {
            return false;
        };
        if let Some(r) = job.record.request.as_mut() {
            r.priority = priority;
        }
        // (a job not yet admitted is not in the scheduler)
        let _ = st.sched.set_priority(JobId(n), priority);
        tracing::info!(job = %job_name(n), priority, "priority changed");
        self.persist(st, n);
        self.publish_status(st, n);
        self.admit(st);
        self.dispatch(st);
        true
    }

    pub(crate) fn persist(&self, st: &State, n: u64) {
        if let Some(job) = st.jobs.get(&n) {
            if let Err(e) = self.db.put(n, &job.record) {
                tracing::error!(job = %job_name(n), "{e}");
            }
        }
    }

    pub(crate) fn publish_status(&self, st: &State, n: u64) {
        if let Some(job) = st.jobs.get(&n) {
            job.watch.send_replace(job.status(n));
        }
    }

    /// Offers leases to every worker with credits while the scheduler has tiles.
    pub(crate) fn dispatch(&self, st: &mut State) {
        let now = self.now();
        let mut ids: Vec<u64> = st
            .workers
            .iter()
            .filter(|(_, w)| w.credits > 0 && !w.draining)
            .map(|(&id, _)| id)
            .collect();
        // One lease per worker per round, every other round in reverse: a unit's tiles come
        // most costly first, and filling one worker's slots before the next's gave the first
        // worker the two biggest tiles (one of two workers idle for a third of every training
        // pass); dealt out this way, the first worker's big tile pairs with a small one.
        let mut offered = true;
        while offered {
            offered = false;
            for &id in &ids {
                offered |= st.workers[&id].credits > 0 && self.offer_next(st, id, now);
            }
            ids.reverse();
        }
        self.refresh_workers_view(st);
    }

    /// Offers worker `id` its next lease, if the scheduler has one for it.
    fn offer_next(&self, st: &mut State, id: u64, now: Millis) -> bool {
        let Some(lease) = st.sched.next_lease(WorkerId(id), now) else {
            return false;
        };
        let n = lease.key.job.0;
        let offer = self.offer(st, &lease, now);
        let w = st.workers.get_mut(&id).expect("listed");
        w.credits -= 1;
        tracing::debug!(job = %job_name(n), lease = lease.id.0, worker = id, tile = lease.key.tile, unit = lease.key.unit, "lease offered");
        if let Some(offer) = offer {
            w.post(v1::coordinator_message::Msg::LeaseOffer(offer));
        }
        let job = st.jobs.get_mut(&n).expect("scheduled jobs exist");
        if job.record.started_unix_ms == 0 {
            job.record.started_unix_ms = unix_ms();
            job.record.state = v1::JobState::Training as i32;
            self.publish_status(st, n);
        }
        true
    }

    fn offer(
        &self,
        st: &State,
        lease: &crate::scheduler::Lease,
        now: Millis,
    ) -> Option<v1::LeaseOffer> {
        let job = st.jobs.get(&lease.key.job.0)?;
        let a = job.active()?;
        let spec = a.driver.flight(lease.key.unit)?;
        let request = job.record.request.as_ref()?;
        let tiles = a.session().tiles_of(lease.key.unit)?;
        let region = *tiles.get(lease.key.tile as usize)?;
        let mut pass = codec::spec_to_proto(spec);
        pass.hold_records = spec.record();
        pass.records_epoch = a.driver.records_epoch();
        if spec.guide() || spec.record() {
            pass.tree_digest = a.tree_digest.map(|(_, d)| d.0.to_vec()).unwrap_or_default();
            pass.fractions_digest = a
                .fractions_of(spec)
                .map(|d| d.0.to_vec())
                .unwrap_or_default();
        }
        let mut tile_estimate = None;
        if spec.kind != PassKind::Path {
            let estimate = a.session().pass_estimate();
            let size = (job.record.width, job.record.height);
            let read = spec.sampled_pixels(region, &a.prepared.splatting.filter, size);
            match codec::encode_tile_estimate(estimate, size.0, read) {
                Some(part) => tile_estimate = Some(part),
                None => {
                    let estimate = a.estimate_digest.flatten();
                    pass.estimate_digest = estimate.map(|d| d.0.to_vec()).unwrap_or_default();
                }
            }
        }
        let mut settings = request
            .settings
            .as_ref()
            .and_then(|s| s.scene.clone())
            .unwrap_or_default();
        settings.seed = Some(a.seed);
        let deadline = unix_ms() + lease.deadline.0.saturating_sub(now.0);
        Some(v1::LeaseOffer {
            lease: Some(v1::Lease {
                lease_id: lease.id.0,
                job_id: job_name(lease.key.job.0),
                deadline_unix_ms: deadline,
                attempt: lease.attempt,
                tile: Some(codec::region_to_proto(region)),
                scene: request.bundle.clone().map(v1::lease::Scene::Bundle),
                settings: Some(settings),
                image: Some(v1::Resolution {
                    width: job.record.width,
                    height: job.record.height,
                }),
                pass: Some(pass),
                estimate: tile_estimate,
            }),
        })
    }

    /// Acts on scheduler events.
    pub(crate) fn handle_events(self: &Arc<Self>, st: &mut State, events: Vec<Event>) {
        for e in events {
            match e {
                Event::LeaseExpired { worker, lease, key } => {
                    tracing::warn!(job = %job_name(key.job.0), lease = lease.0, worker = worker.0, "lease expired");
                    send_cancel(st, worker, lease, "lease expired");
                }
                Event::WorkerLost { worker, returned } => {
                    if returned.is_empty() {
                        tracing::info!(worker = worker.0, "worker gone (it held no leases)")
                    } else {
                        let returned = returned.len();
                        tracing::warn!(worker = worker.0, returned, "worker lost");
                    }
                    // Its stream (if still open) is ended: a worker that was only paused
                    // reconnects and registers anew, and is offered work again.
                    self.forget_worker(
                        st,
                        worker.0,
                        "declared lost (silent past the heartbeat timeout)",
                    );
                    self.lost_holder(st, worker);
                }
                Event::JobFailed { job, reason } => {
                    self.fail_job(st, job.0, reason.to_string());
                }
                Event::CancelLease { worker, lease, key } => {
                    tracing::info!(job = %job_name(key.job.0), lease = lease.0, worker = worker.0, "cancelling lease");
                    send_cancel(st, worker, lease, "lease cancelled");
                }
            }
        }
    }

    /// Worker `id` sent job `n` something bad (an upload that is corrupt, out of range or
    /// refused by the session; a report that the job cannot be rendered): it is counted
    /// against the worker, never the job. Past [`Resources::bad_uploads_per_job`] (at once
    /// for [`Blame::Unrenderable`]) the worker gets no more leases of the job, under its
    /// identity, across reconnections; a job that every connected worker is blocked from
    /// fails with the last reason (its scene, not a worker, is then at fault).
    pub(crate) fn blame(self: &Arc<Self>, st: &mut State, n: u64, id: u64, why: &str, b: Blame) {
        let Some(who) = st.workers.get(&id).map(WorkerConn::identity) else {
            return;
        };
        let Some(job) = st.jobs.get_mut(&n) else {
            return;
        };
        let reason = resources::truncate(why, 512);
        let already = job.blocklist.is_blocked(&who);
        let standing = job.blocklist.blame(&who, &reason, b);
        tracing::warn!(job = %job_name(n), worker = id, identity = %who, ?standing, "bad result: {reason}");
        if already || standing != Standing::Blocked {
            return;
        }
        let blocked: Vec<u64> = (st.workers.iter())
            .filter(|(_, w)| w.identity() == who)
            .map(|(&w, _)| w)
            .collect();
        for w in blocked {
            for lease in st.sched.block(WorkerId(w), JobId(n)).unwrap_or_default() {
                send_cancel(st, WorkerId(w), lease, "blocked from the job");
            }
        }
        self.metrics.worker_blocked();
        let usable = (st.workers.iter())
            .any(|(&w, c)| !c.draining && !st.sched.is_blocked(WorkerId(w), JobId(n)));
        if !usable {
            let reason =
                format!("every connected worker was blocked from the job; last: {who}: {reason}");
            self.fail_job(st, n, reason);
        } else {
            self.publish_status(st, n);
        }
    }

    /// Worker `worker` is gone: every job it held records for rolls back.
    pub(crate) fn lost_holder(self: &Arc<Self>, st: &mut State, worker: WorkerId) {
        let jobs: Vec<u64> = st
            .jobs
            .iter()
            .filter(|(_, j)| j.active().is_some_and(|a| a.driver.holds(worker)))
            .map(|(&n, _)| n)
            .collect();
        for n in jobs {
            let why = format!(
                "worker {} held records of the iteration and is gone",
                worker.0
            );
            self.roll_back(st, n, &why);
        }
    }

    /// The periodic tick: expiries, waiting sessions, dispatch.
    pub(crate) fn tick(self: &Arc<Self>) {
        let mut st = self.lock();
        let now = self.now();
        let events = st.sched.tick(now);
        self.handle_events(&mut st, events);
        // Workers that stopped reading their stream until their outbox filled.
        let deaf: Vec<u64> = (st.workers.iter())
            .filter(|(_, w)| w.overflowed.load(Ordering::Relaxed))
            .map(|(&id, _)| id)
            .collect();
        for id in deaf {
            tracing::warn!(
                worker = id,
                "worker disconnected: it does not read its stream"
            );
            let events = st.sched.worker_lost(WorkerId(id)).unwrap_or_default();
            self.forget_worker(&mut st, id, "did not read its stream");
            self.handle_events(&mut st, events);
            self.lost_holder(&mut st, WorkerId(id));
        }
        self.admit(&mut st);
        // A holder that heartbeats but never answers a flush (a bug, or a wedged worker)
        // must not stall its job: after a lease's lifetime the job rolls back.
        let timeout = self.cfg.scheduler.lease_timeout;
        let stalled: Vec<u64> = (st.jobs.iter())
            .filter(|(_, j)| (j.active()).is_some_and(|a| a.driver.stalled(now, timeout)))
            .map(|(&n, _)| n)
            .collect();
        for n in stalled {
            self.roll_back(
                &mut st,
                n,
                "a holder did not answer for its records in time",
            );
        }
        // a resumed session, or one that may overlap its next unit (its driver says what)
        let running: Vec<u64> = (st.jobs.iter())
            .filter(|(_, j)| j.active().is_some())
            .map(|(&n, _)| n)
            .collect();
        for n in running {
            self.drive(&mut st, n);
        }
        self.dispatch(&mut st);
        drop(st);
        self.maybe_sweep();
    }
}

pub(crate) fn send_cancel(st: &State, worker: WorkerId, lease: LeaseId, reason: &str) {
    if let Some(w) = st.workers.get(&worker.0) {
        w.post(v1::coordinator_message::Msg::CancelLease(v1::CancelLease {
            lease_id: lease.0,
            reason: resources::truncate(reason, 1024),
        }));
    }
}

pub(crate) fn bad(message: impl Into<String>) -> Status {
    Status::invalid_argument(message)
}

pub(crate) fn digest_from(bytes: &[u8], field: &str) -> Result<Digest, Status> {
    let arr: [u8; 32] = bytes.try_into().map_err(|_| {
        Status::invalid_argument(format!(
            "{field}: a digest is 32 bytes, got {}",
            bytes.len()
        ))
    })?;
    Ok(Digest(arr))
}

pub(crate) fn manifest_from_proto(b: &v1::Bundle) -> Result<Manifest, Status> {
    let mut files = Vec::with_capacity(b.files.len());
    for (i, f) in b.files.iter().enumerate() {
        files.push(ManifestEntry {
            path: f.path.clone(),
            digest: digest_from(
                &f.digest,
                &format!("bundle.files[{i}].digest ({:?})", f.path),
            )?,
            size: f.size,
        });
    }
    Ok(Manifest {
        root: b.root.clone(),
        files,
    })
}

/// The shortest time budget a job may have, in seconds.
const MIN_TIME_SECONDS: f64 = 0.01;

/// The most defines a job may set, and the longest name and value of one.
const MAX_DEFINES: usize = 256;
const MAX_DEFINE_NAME_BYTES: usize = 128;
const MAX_DEFINE_VALUE_BYTES: usize = 4096;

/// A job's `-D name=value` overrides, each checked: a name is an identifier, a value has
/// no surrounding whitespace or control characters (`resx=' 64'` is refused, not read as
/// 64), and both are bounded; an error echoes at most a bounded part of the input.
fn overrides_of(s: &v1::SceneSettings) -> Result<Vec<(String, String)>, Status> {
    if s.defines.len() > MAX_DEFINES {
        return Err(bad(format!(
            "settings.scene.defines: {} defines, at most {MAX_DEFINES}",
            s.defines.len()
        )));
    }
    let mut out = Vec::new();
    for (i, d) in s.defines.iter().enumerate() {
        let field = format!("settings.scene.defines[{i}]");
        let identifier =
            d.name.bytes().enumerate().all(|(k, b)| {
                b == b'_' || b.is_ascii_alphabetic() || (k > 0 && b.is_ascii_digit())
            });
        if d.name.is_empty() || d.name.len() > MAX_DEFINE_NAME_BYTES || !identifier {
            return Err(bad(format!(
                "{field}.name: {} is not an identifier of at most {MAX_DEFINE_NAME_BYTES} bytes",
                resources::echo(&d.name)
            )));
        }
        let v = &d.value;
        if v.len() > MAX_DEFINE_VALUE_BYTES {
            return Err(bad(format!(
                "{field}.value ({}): {} bytes, at most {MAX_DEFINE_VALUE_BYTES}",
                d.name,
                v.len()
            )));
        }
        if v.trim() != v || v.chars().any(char::is_control) {
            return Err(bad(format!(
                "{field}.value ({}): {} has surrounding whitespace or control characters",
                d.name,
                resources::echo(v)
            )));
        }
        out.push((d.name.clone(), d.value.clone()));
    }
    if let Some(integrator) = &s.integrator {
        if integrator.is_empty() || integrator.len() > MAX_DEFINE_NAME_BYTES {
            return Err(bad(format!(
                "settings.scene.integrator: {} is not an integrator name",
                resources::echo(integrator)
            )));
        }
    }
    Ok(out)
}

pub(crate) fn status_of(n: u64, r: &JobRecord, a: Option<&Active>) -> v1::JobStatus {
    let request = r.request.clone().unwrap_or_default();
    let mut s = v1::JobStatus {
        job_id: job_name(n),
        name: request.name.clone(),
        batch: request.batch.clone(),
        state: r.state,
        iteration: r.iteration,
        samples_done: r.samples_done,
        preview_available: r.state == v1::JobState::Done as i32
            || a.is_some_and(|a| a.preview.is_some()),
        failure_reason: r.failure_reason.clone(),
        submitted_unix_ms: r.submitted_unix_ms,
        finished_unix_ms: r.finished_unix_ms,
        spp_done: r.spp_done,
        priority: request.priority,
        started_unix_ms: r.started_unix_ms,
        nonfinite: r.nonfinite,
        iterations: r.iterations.clone(),
        fell_back_after: r.fell_back_after,
        ..Default::default()
    };
    if let Some(a) = a {
        let session = a.session();
        s.iterations = iterations_of(session);
        s.fell_back_after = session.fell_back_after();
        let (done, total) = session.tiles_done();
        s.iteration = session.iteration();
        s.tiles_done = done as u32;
        s.tiles_total = if a.driver.flights().is_empty() {
            0
        } else {
            total as u32
        };
        s.samples_total = a.samples_total;
        s.spp_done = session.spp_done();
        s.nonfinite = session.nonfinite();
        if let Some(spec) = a.driver.flights().first() {
            s.unit = spec.unit;
            s.pass_kind = codec::spec_to_proto(spec).kind;
        }
        s.eta_seconds = eta(r, a, &request);
        if r.started_unix_ms != 0 {
            s.state = if session.in_final_pass() {
                v1::JobState::FinalPass as i32
            } else {
                v1::JobState::Training as i32
            };
        }
    }
    s
}

/// The iterations a session has rendered, as `JobStatus` gives them.
fn iterations_of(session: &Session) -> Vec<v1::IterationInfo> {
    (session.iterations().iter())
        .map(|it| v1::IterationInfo {
            index: it.index,
            spp: it.spp,
            variance: it.variance,
            seconds: it.seconds,
            tree_nodes: it.nodes as u64,
            tree_leaves: it.leaves as u64,
            training: it.training,
            rays_per_sample: it.rays_per_sample,
        })
        .collect()
}

/// Seconds until the job is done: with an spp budget, the time so far scaled by the samples
/// left over the samples done; with a time budget, the budget left. `None` before the job
/// started rendering.
fn eta(r: &JobRecord, a: &Active, request: &v1::SubmitJobRequest) -> Option<f64> {
    if r.started_unix_ms == 0 {
        return None;
    }
    let elapsed = unix_ms().saturating_sub(r.started_unix_ms) as f64 * 1e-3;
    let budget = request.settings.as_ref().and_then(|s| s.budget);
    if let Some(v1::job_settings::Budget::TimeSeconds(t)) = budget {
        return Some((t - elapsed).max(0.0));
    }
    let (done, total) = (r.samples_done as f64, a.samples_total as f64);
    (done > 0.0 && total > 0.0).then(|| elapsed * (total - done).max(0.0) / done)
}

/// Sets the health status of every service.
pub(crate) async fn update_health(
    shared: &Shared,
    reporter: &tonic_health::server::HealthReporter,
) {
    let any = !(shared.workers_view.read())
        .unwrap_or_else(|e| e.into_inner())
        .is_empty();
    if shared.serving.swap(any, Ordering::SeqCst) == any {
        return;
    }
    let status = if any {
        tonic_health::ServingStatus::Serving
    } else {
        tonic_health::ServingStatus::NotServing
    };
    // The farm (and its job API) serves once a worker is registered; the worker API serves
    // from the start (`service::run`), so that a readiness probe on it does not keep the
    // first worker out.
    for name in ["", pathfarm_proto::JOBS_SERVICE] {
        reporter.set_service_status(name, status).await;
    }
}

const TICK: Duration = Duration::from_millis(200);
