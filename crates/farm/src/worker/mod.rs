//! A farm worker: registers with the coordinator on the control stream, takes leases,
//! renders their tiles bit-exactly (one lease at a time, one more prefetched) and uploads the
//! results. Reconnects with backoff when the coordinator goes away; drains on shutdown.
//!
//! Tiles of one unit that the worker renders one after the other record into its copy of
//! the tree without taking the statistics in between, and go up in one upload with the
//! statistics taken once ([`upload`]): a unit costs the coordinator one statistics decode and
//! merge per worker, not one per tile. The leases stay the worker's until that upload, so a
//! worker lost before it re-renders all of them, as for a single tile.

use std::collections::{HashMap, VecDeque};
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use pathfarm_guide::SdTree;
use pathfarm_proto::v1::{self, workers_client::WorkersClient};
use pathfarm_proto::PROTOCOL_VERSION;
use pathfarm_render::guided::guide_config;
use pathfarm_render::pass::{render_unit, UnitInputs};
use pathfarm_render::{Purpose, Scene};
use pathfarm_scene::{GuidedParams, Limits};
use prost::Message;
use tokio::sync::mpsc;
use tokio_stream::wrappers::UnboundedReceiverStream;

use crate::bundle::{self, Built, Digest, Manifest, ManifestEntry, SceneBuild, SceneOptions};
use crate::client::{endpoint, error_chain, Auth, AuthChannel, Backoff, Remote, WorkerKey};
use crate::codec;

mod prefetch;
mod records;
pub mod scenes;
mod simulated;
mod upload;
mod worlds;

pub use simulated::Rendering;

pub use upload::MAX_JOINT_TILES;
use upload::{
    spawn_upload, FlushEnd, Flushing, HeldKey, Joint, RenderedTile, Spoiled, UploadEnd, UploadOf,
    Uploads,
};

/// How a worker runs.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// The coordinator: URL, token, TLS.
    pub coordinator: Remote,
    /// Render threads (at least 1).
    pub threads: usize,
    /// Optional operator-chosen name (empty = none).
    pub name: String,
    /// Blob, bundle and scratch cache.
    pub cache_dir: PathBuf,
    /// The memory the built scenes of the jobs this worker serves may take together
    /// ([`scenes::DEFAULT_BUDGET_BYTES`] by default); the least recently used go beyond it.
    pub scene_cache_bytes: u64,
    /// The path tracer, or a simulation of its time for benchmarks.
    pub rendering: Rendering,
}

/// Why a worker stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// The coordinator refused the registration (not retried).
    #[error("the coordinator refused this worker: {0}")]
    Refused(String),
    /// Bad configuration (URL, token, threads, cache directory).
    #[error("{0}")]
    Config(String),
}

type Api = WorkersClient<AuthChannel>;

/// Runs the worker until `shutdown` resolves (then drains and returns `Ok`) or the
/// coordinator refuses it.
pub async fn run(cfg: WorkerConfig, shutdown: impl Future<Output = ()>) -> Result<(), WorkerError> {
    if cfg.threads == 0 {
        return Err(WorkerError::Config("threads must be at least 1".into()));
    }
    let key = WorkerKey::default();
    let auth = Auth::new(cfg.coordinator.token.as_deref())
        .map_err(|e| WorkerError::Config(e.to_string()))?
        .with_worker_key(key.clone());
    let ep = endpoint(&cfg.coordinator).map_err(|e| WorkerError::Config(e.to_string()))?;
    for d in ["blobs", "bundles"] {
        std::fs::create_dir_all(cfg.cache_dir.join(d)).map_err(|e| {
            WorkerError::Config(format!("{}: {e}", cfg.cache_dir.join(d).display()))
        })?;
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(cfg.threads)
        .thread_name(|i| format!("pathfarm-render-{i}"))
        .build()
        .map_err(|e| WorkerError::Config(format!("thread pool: {e}")))?;
    let shared = Arc::new(Shared {
        cache_dir: cfg.cache_dir.clone(),
        pool,
        caches: Mutex::new(Caches::new(cfg.scene_cache_bytes)),
        tmp_counter: AtomicU64::new(0),
        scene_builds: AtomicU64::new(0),
        worlds: Mutex::default(),
        rendering: cfg.rendering,
    });
    tokio::pin!(shutdown);
    let mut stop = false;
    let mut backoff = Backoff::new();
    loop {
        if stop {
            return Ok(());
        }
        let channel = tokio::select! {
            r = ep.connect() => r,
            _ = &mut shutdown => return Ok(()),
        };
        let channel = match channel {
            Ok(c) => c,
            Err(e) => {
                let d = backoff.next_delay();
                tracing::warn!(
                    "cannot reach the coordinator at {}: {}; retrying in {:?}",
                    cfg.coordinator.url,
                    error_chain(&e),
                    d
                );
                tokio::select! {
                    _ = tokio::time::sleep(d) => continue,
                    _ = &mut shutdown => return Ok(()),
                }
            }
        };
        let api = WorkersClient::with_interceptor(channel, auth.clone())
            .max_decoding_message_size(16 << 20);
        match session(
            &cfg,
            &shared,
            api,
            &key,
            &mut shutdown,
            &mut stop,
            &mut backoff,
        )
        .await
        {
            Ok(()) => {}
            Err(SessionEnd::Refused(r)) => return Err(WorkerError::Refused(r)),
            Err(SessionEnd::Lost(m)) => {
                if stop {
                    return Ok(());
                }
                let d = backoff.next_delay();
                tracing::warn!("lost the coordinator: {m}; reconnecting in {d:?}");
                tokio::select! {
                    _ = tokio::time::sleep(d) => {}
                    _ = &mut shutdown => return Ok(()),
                }
            }
        }
    }
}

enum SessionEnd {
    Refused(String),
    Lost(String),
}

/// What the worker keeps across leases and sessions.
struct Shared {
    cache_dir: PathBuf,
    pool: rayon::ThreadPool,
    caches: Mutex<Caches>,
    tmp_counter: AtomicU64,
    /// Scenes built since the worker started (for leases or ahead).
    scene_builds: AtomicU64,
    /// The worlds of the scenes the worker holds, which scenes of the same world share.
    worlds: Mutex<worlds::Worlds>,
    rendering: Rendering,
}

/// A job's built scene.
struct JobScene {
    scene: Scene,
    params: GuidedParams,
}

/// A job's tree copy: the tree of `tree_digest` with the fractions of `fractions_digest`.
struct JobTree {
    tree_digest: Vec<u8>,
    fractions_digest: Vec<u8>,
    tree: SdTree,
    /// The unit whose tiles' records are in the tree, not yet taken (see [`upload::Joint`]).
    recording: Option<u64>,
}

struct Caches {
    /// Built scenes within the memory budget, shared by the jobs of one scene.
    scenes: scenes::SceneCache,
    /// One tree per job, at most [`JOB_TREES`].
    trees: HashMap<String, JobTree>,
    /// The jobs of `trees`, most recently used last.
    tree_order: Vec<String>,
    /// One estimate per job: its digest and values.
    estimates: HashMap<String, (Vec<u8>, Arc<Vec<f32>>)>,
    /// The pass inputs (trees, fractions, estimates) fetched last, most recently used last
    /// (at most [`INPUT_CACHE`]): kept in memory, not in the disk cache, since each is
    /// decoded once and superseded within an iteration (writing a tree of tens of MB to
    /// disk and reading it back cost a worker more than fetching it).
    inputs: Vec<(Digest, Arc<Vec<u8>>)>,
    /// The scene the coordinator's last `Prefetch` asked for, built or being built.
    prefetched: Option<prefetch::Prefetched>,
}

const INPUT_CACHE: usize = 4;

/// Trees kept for this many jobs (the most recently used): a worker serving several jobs at
/// once keeps each one's tree version instead of fetching it again when it comes back to
/// the job.
const JOB_TREES: usize = 8;

impl Caches {
    fn new(scene_budget: u64) -> Self {
        Self {
            scenes: scenes::SceneCache::new(scene_budget),
            trees: HashMap::new(),
            tree_order: Vec::new(),
            estimates: HashMap::new(),
            inputs: Vec::new(),
            prefetched: None,
        }
    }

    /// Keeps `jt` as `job`'s tree, dropping the least recently used trees (and estimates)
    /// of other jobs beyond [`JOB_TREES`], except trees holding records not yet uploaded.
    fn keep_tree(&mut self, job: &str, jt: JobTree) {
        self.trees.insert(job.to_string(), jt);
        self.tree_order.retain(|j| j != job);
        self.tree_order.push(job.to_string());
        while self.tree_order.len() > JOB_TREES {
            let Some(i) = (self.tree_order.iter())
                .position(|j| self.trees.get(j).is_none_or(|t| t.recording.is_none()))
            else {
                break;
            };
            let old = self.tree_order.remove(i);
            self.trees.remove(&old);
            self.estimates.remove(&old);
        }
    }

    /// Keeps `js` as the scene of `key` and `job`; the jobs whose scenes the budget pushed
    /// out lose their trees and estimates too (unless a tree holds records not yet uploaded).
    fn keep_scene(&mut self, key: prefetch::SceneKey, job: &str, js: Arc<JobScene>) {
        for old in self.scenes.insert(key, job, js) {
            if self.trees.get(&old).is_none_or(|t| t.recording.is_none()) {
                self.trees.remove(&old);
                self.tree_order.retain(|j| j != &old);
            }
            self.estimates.remove(&old);
        }
    }
}

/// The value of `key` in a most-recently-used-last list, moved to the end (most recent).
fn most_recent<K: PartialEq, V: Clone>(list: &mut Vec<(K, V)>, key: &K) -> Option<V> {
    let i = list.iter().position(|(k, _)| k == key)?;
    let e = list.remove(i);
    let v = e.1.clone();
    list.push(e);
    Some(v)
}

/// The outcome of rendering one lease.
enum LeaseEnd {
    /// Rendered: it joins the tiles of its unit waiting for their joint upload.
    Rendered(RenderedTile),
    /// Cancelled after it rendered: its records are in the tree and must be discarded.
    CancelledRendered(RenderedTile),
    Cancelled,
    Failed(Fail),
}

struct Running {
    lease_id: u64,
    job_id: String,
    cancelled: Arc<AtomicBool>,
    handle: tokio::task::JoinHandle<LeaseEnd>,
}

/// Queues a message on the control stream. Unbounded, so nothing is dropped (a lost
/// `RequestWork` would leak a credit, a lost `LeaseFailed` leave a tile waiting for its
/// deadline); what the worker sends is bounded by its leases and its heartbeat interval.
/// Fails only once the stream is gone, which the session loop sees and reconnects.
fn send(tx: &mpsc::UnboundedSender<v1::WorkerMessage>, msg: v1::worker_message::Msg) {
    if tx.send(v1::WorkerMessage { msg: Some(msg) }).is_err() {
        tracing::debug!("control stream closed: a message to the coordinator was not sent");
    }
}

/// One control-stream session's leases: queued, rendering, rendered and waiting for the
/// rest of their unit, being serialised and uploading, and whether the worker is draining.
/// The session loop feeds it one event at a time.
struct Leases {
    tx: mpsc::UnboundedSender<v1::WorkerMessage>,
    queue: VecDeque<v1::Lease>,
    running: Option<Running>,
    /// Rendered tiles of one unit whose records are in the tree: uploaded together.
    joint: Option<Joint>,
    /// The joint tiles' statistics being taken and encoded (the tree is busy meanwhile).
    flushing: Option<Flushing>,
    /// Uploads in progress: (leases, job) -> outcome. The next lease renders meanwhile.
    uploads: Uploads,
    /// Leases being serialised or uploaded.
    uploading: Vec<u64>,
    /// The job of each upload in progress (a job's records are flushed after its uploads).
    upload_jobs: Vec<String>,
    /// Per job, the quadtree records of this connection's accepted recording uploads of
    /// one tree version and epoch, until the coordinator asks for them.
    held: HashMap<String, records::Held>,
    /// `FlushRecords` waiting for their job's renders and uploads to end.
    flushes: Vec<v1::FlushRecords>,
    /// This connection's worker id (`Registered.worker_id`).
    worker_id: u64,
    draining: bool,
}

impl Leases {
    fn send(&self, msg: v1::worker_message::Msg) {
        send(&self.tx, msg);
    }

    /// SIGTERM or Ctrl-C: stop taking leases and hand back the ones not started.
    fn on_shutdown(&mut self) {
        use v1::worker_message::Msg;
        self.draining = true;
        tracing::info!("shutting down: draining");
        self.send(Msg::Draining(v1::Draining {}));
        let ids: Vec<u64> = self.queue.drain(..).map(|l| l.lease_id).collect();
        if !ids.is_empty() {
            tracing::info!("handing back leases {ids:?}");
            self.send(Msg::HandBack(v1::HandBack { lease_ids: ids }));
        }
    }

    fn heartbeat(&self) {
        let mut ids: Vec<u64> = self.running.iter().map(|r| r.lease_id).collect();
        ids.extend(self.queue.iter().map(|l| l.lease_id));
        ids.extend(self.joint.iter().flat_map(Joint::lease_ids));
        ids.extend(self.uploading.iter().copied());
        let hb = v1::Heartbeat {
            active_lease_ids: ids,
        };
        self.send(v1::worker_message::Msg::Heartbeat(hb));
    }

    /// The running lease's render ended: it joins its unit's tiles, or is reported.
    fn on_rendered(&mut self, id: u64, job: String, end: LeaseEnd) {
        use v1::worker_message::Msg;
        match end {
            LeaseEnd::Rendered(tile) => self.join(tile, Spoiled::No),
            LeaseEnd::CancelledRendered(tile) => {
                tracing::info!("lease {id} (job {job}): cancelled, nothing uploaded");
                self.join(tile, Spoiled::Yes);
            }
            LeaseEnd::Cancelled => {
                tracing::info!("lease {id} (job {job}): cancelled, nothing uploaded");
            }
            LeaseEnd::Failed(Fail { reason, severity }) => {
                tracing::error!("lease {id} (job {job}) failed: {reason}");
                let failed = v1::LeaseFailed {
                    lease_id: id,
                    reason,
                    fatal: severity == Severity::Fatal,
                };
                self.send(Msg::LeaseFailed(failed));
            }
        }
        if !self.draining {
            self.send(Msg::RequestWork(v1::RequestWork { slots: 1 }));
        }
    }

    /// Adds a rendered tile to the tiles of its unit (the session loop flushes a joint of
    /// another unit before it starts a lease, so the joint is this tile's unit's).
    fn join(&mut self, tile: RenderedTile, spoiled: Spoiled) {
        let joint = self.joint.get_or_insert_with(|| Joint::new(&tile));
        debug_assert!(joint.holds(&tile.job_id, tile.unit));
        joint.push(tile, spoiled);
    }

    /// Whether the joint tiles must be uploaded before anything else starts: the next lease
    /// is of another unit, or there is none yet, or the joint is full or spoiled.
    fn joint_is_due(&self) -> bool {
        let Some(j) = &self.joint else {
            return false;
        };
        let next = self.queue.front();
        j.is_full_or_spoiled()
            || !next.is_some_and(|l| j.holds(&l.job_id, l.pass.as_ref().map_or(0, |p| p.unit)))
    }

    /// Starts taking and encoding the joint tiles' statistics.
    fn start_flush(&mut self, shared: &Arc<Shared>) {
        let joint = self.joint.take().expect("a joint is due");
        self.uploading.extend(joint.lease_ids());
        self.flushing = Some(Flushing::start(shared, joint));
    }

    /// The joint tiles are serialised: upload them, or give their leases back.
    fn on_flushed(&mut self, api: &Api, ids: Vec<u64>, job: String, end: FlushEnd) {
        use v1::worker_message::Msg;
        match end {
            FlushEnd::Ready(upload, held) => {
                self.upload_jobs.push(job.clone());
                let of = UploadOf { ids, job, held };
                spawn_upload(&mut self.uploads, api, of, upload)
            }
            FlushEnd::Discarded => {
                self.uploading.retain(|l| !ids.contains(l));
                self.send(Msg::HandBack(v1::HandBack { lease_ids: ids }));
            }
            FlushEnd::Failed(reason) => {
                self.uploading.retain(|l| !ids.contains(l));
                self.fail_all(ids, &job, reason);
            }
        }
    }

    /// Reports leases `ids` failed (retryable): their tiles are rendered again.
    fn fail_all(&self, ids: Vec<u64>, job: &str, reason: String) {
        tracing::error!("leases {ids:?} (job {job}) failed: {reason}");
        for lease_id in ids {
            let failed = v1::LeaseFailed {
                lease_id,
                reason: reason.clone(),
                fatal: false,
            };
            self.send(v1::worker_message::Msg::LeaseFailed(failed));
        }
    }

    fn on_uploaded(&mut self, of: UploadOf, end: UploadEnd) {
        if let Some(i) = self.upload_jobs.iter().position(|j| *j == of.job) {
            self.upload_jobs.remove(i);
        }
        self.uploading.retain(|l| !of.ids.contains(l));
        let UploadOf { ids, job, held } = of;
        match (&end, held) {
            // Kept only for tiles the coordinator took from this worker; a rejected
            // upload's records go with it (its tiles are rendered again elsewhere).
            (UploadEnd::Acked(ack), Some((key, stats))) if ack.accepted && !ack.duplicate => {
                records::keep(&mut self.held, (&job, &ids), key, stats)
            }
            // Whether the coordinator took it is unknown: the records kept cannot be
            // vouched for.
            (UploadEnd::Failed(_), Some((key, _))) => records::lose(&mut self.held, &job, key),
            _ => {}
        }
        match end {
            UploadEnd::Acked(ack) if ack.accepted => {
                let dup = if ack.duplicate { " (duplicate)" } else { "" };
                let n = ids.len();
                tracing::info!("leases {ids:?} (job {job}): {n} tiles accepted{dup}");
            }
            UploadEnd::Acked(ack) => {
                let reason = v1::TileRejectReason::try_from(ack.reject_reason)
                    .unwrap_or(v1::TileRejectReason::Unspecified);
                tracing::warn!(
                    "leases {ids:?} (job {job}): tiles rejected: {reason:?} {}",
                    ack.detail
                );
            }
            UploadEnd::Failed(reason) => self.fail_all(ids, &job, reason),
        }
    }

    fn on_message(&mut self, msg: v1::CoordinatorMessage) {
        use v1::coordinator_message::Msg as C;
        use v1::worker_message::Msg;
        match msg.msg {
            Some(C::LeaseOffer(o)) => {
                let Some(lease) = o.lease else { return };
                tracing::info!(
                    "lease {} (job {}): offered, unit {} tile {:?}",
                    lease.lease_id,
                    lease.job_id,
                    lease.pass.as_ref().map_or(0, |p| p.unit),
                    lease.tile.as_ref().map(|t| (t.x0, t.y0, t.x1, t.y1))
                );
                if self.draining {
                    let ids = vec![lease.lease_id];
                    self.send(Msg::HandBack(v1::HandBack { lease_ids: ids }));
                } else {
                    self.queue.push_back(lease);
                }
            }
            Some(C::CancelLease(c)) => self.on_cancel(c),
            Some(C::Drain(d)) => {
                if !self.draining {
                    tracing::info!("the coordinator asks to drain: {}", d.reason);
                    self.draining = true;
                    self.send(Msg::Draining(v1::Draining {}));
                }
            }
            Some(C::FlushRecords(f)) => {
                tracing::info!(
                    "job {}: the coordinator asks for the records held",
                    f.job_id
                );
                self.flushes.push(f);
            }
            // Prefetch is taken by the session loop, which has the API to fetch with.
            Some(C::Registered(_)) | Some(C::Refused(_)) | Some(C::Prefetch(_)) | None => {}
        }
    }

    fn on_cancel(&mut self, c: v1::CancelLease) {
        if let Some(i) = self.queue.iter().position(|l| l.lease_id == c.lease_id) {
            let l = self.queue.remove(i).expect("position");
            let (id, job) = (l.lease_id, l.job_id);
            tracing::info!(
                "lease {id} (job {job}): cancelled before start: {}",
                c.reason
            );
            if !self.draining {
                let more = v1::RequestWork { slots: 1 };
                self.send(v1::worker_message::Msg::RequestWork(more));
            }
        } else if let Some(r) = self.running.as_ref().filter(|r| r.lease_id == c.lease_id) {
            let (id, job) = (r.lease_id, &r.job_id);
            tracing::info!(
                "lease {id} (job {job}): cancelled while rendering: {}",
                c.reason
            );
            r.cancelled.store(true, Ordering::SeqCst);
        } else if let Some(j) = self.joint.as_mut().filter(|j| j.has_lease(c.lease_id)) {
            tracing::info!(
                "lease {} (job {}): cancelled while waiting for its unit's upload: {}",
                c.lease_id,
                j.job_id(),
                c.reason
            );
            j.cancel(c.lease_id);
        }
    }

    /// Starts answering the `FlushRecords` whose job has nothing rendering, waiting for a
    /// joint upload, being serialised or uploading here: every tile's outcome is known, so
    /// the records kept are those of exactly the tiles the coordinator took.
    fn start_due_flushes(&mut self, api: &Api) {
        let busy = |job: &str, l: &Leases| {
            l.running.as_ref().is_some_and(|r| r.job_id == job)
                || l.joint.as_ref().is_some_and(|j| j.job_id() == job)
                || l.flushing.as_ref().is_some_and(|f| f.job_id == job)
                || l.upload_jobs.iter().any(|j| j == job)
        };
        let (due, waiting): (Vec<_>, Vec<_>) = std::mem::take(&mut self.flushes)
            .into_iter()
            .partition(|f| !busy(&f.job_id, self));
        self.flushes = waiting;
        for f in due {
            let held = records::take(&mut self.held, &f);
            tokio::spawn(records::send(api.clone(), self.worker_id, f, held));
        }
    }

    /// An upload task panicked: which leases and job it was of is unknown, so no record
    /// kept here can be vouched for (a flush then answers `lost`, and the coordinator rolls
    /// those jobs back), and no flush waits for it.
    fn on_upload_task_lost(&mut self, e: tokio::task::JoinError) {
        tracing::error!("upload task: {e}");
        self.upload_jobs.clear();
        self.held.clear();
    }

    /// The stream broke (or the worker drained): leases not started are abandoned (the
    /// coordinator re-queues them); the one rendering is finished, and the rendered tiles
    /// are uploaded if they can be.
    async fn finish(mut self, shared: &Arc<Shared>, api: &Api, end: StreamEnd) {
        if let Some(r) = self.running.take() {
            if end == StreamEnd::Broke {
                let (id, job) = (r.lease_id, &r.job_id);
                tracing::info!("lease {id} (job {job}): finishing after the stream broke");
            }
            let end = r.handle.await.unwrap_or(LeaseEnd::Cancelled);
            self.on_rendered(r.lease_id, r.job_id, end);
        }
        if let Some(f) = self.flushing.take() {
            let (ids, job, end) = f.finish().await;
            self.on_flushed(api, ids, job, end);
        }
        if self.joint.is_some() {
            self.start_flush(shared);
            let (ids, job, end) = self.flushing.take().expect("started").finish().await;
            self.on_flushed(api, ids, job, end);
        }
        while self.uploads.join_next().await.is_some() {}
    }
}

/// How a control stream's session ended ([`Leases::finish`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum StreamEnd {
    /// The worker drained and closed it.
    Closed,
    /// It broke (the coordinator went away, or ended it).
    Broke,
}

fn lost(s: tonic::Status) -> SessionEnd {
    SessionEnd::Lost(format!("{} ({:?})", s.message(), s.code()))
}

/// Opens the control stream and registers: the coordinator's answer and the stream.
async fn register(
    cfg: &WorkerConfig,
    api: &mut Api,
    tx: &mpsc::UnboundedSender<v1::WorkerMessage>,
    rx: mpsc::UnboundedReceiver<v1::WorkerMessage>,
) -> Result<(v1::Registered, tonic::Streaming<v1::CoordinatorMessage>), SessionEnd> {
    let register = v1::Register {
        protocol_version: PROTOCOL_VERSION,
        build_id: crate::build::build_id().to_string(),
        threads: cfg.threads as u32,
        host_name: host_name(),
        worker_name: cfg.name.clone(),
    };
    send(tx, v1::worker_message::Msg::Register(register));
    let mut inbound = api
        .control(UnboundedReceiverStream::new(rx))
        .await
        .map_err(lost)?
        .into_inner();
    let first = inbound.message().await.map_err(lost)?;
    match first.and_then(|m| m.msg) {
        Some(v1::coordinator_message::Msg::Registered(r)) => Ok((r, inbound)),
        Some(v1::coordinator_message::Msg::Refused(r)) => Err(SessionEnd::Refused(r.reason)),
        _ => Err(SessionEnd::Lost(
            "the coordinator did not answer Register".into(),
        )),
    }
}

async fn session<S: Future<Output = ()>>(
    cfg: &WorkerConfig,
    shared: &Arc<Shared>,
    mut api: Api,
    key: &WorkerKey,
    shutdown: &mut std::pin::Pin<&mut S>,
    stop: &mut bool,
    backoff: &mut Backoff,
) -> Result<(), SessionEnd> {
    use v1::worker_message::Msg;
    let (tx, rx) = mpsc::unbounded_channel::<v1::WorkerMessage>();
    let (registered, mut inbound) = register(cfg, &mut api, &tx, rx).await?;
    // The uploads of this stream's leases name it by its key.
    key.set(&registered.upload_key);
    backoff.reset();
    tracing::info!(
        "registered with {} as worker {} (coordinator {})",
        cfg.coordinator.url,
        registered.worker_id,
        registered.build_id
    );
    let mut l = Leases {
        tx,
        queue: VecDeque::new(),
        running: None,
        joint: None,
        flushing: None,
        uploads: Uploads::new(),
        uploading: Vec::new(),
        upload_jobs: Vec::new(),
        held: HashMap::new(),
        flushes: Vec::new(),
        worker_id: registered.worker_id,
        draining: *stop,
    };
    if l.draining {
        l.send(Msg::Draining(v1::Draining {}));
    } else {
        l.send(Msg::RequestWork(v1::RequestWork { slots: 2 }));
    }
    let hb = Duration::from_millis(registered.heartbeat_interval_ms.max(50) as u64);
    let mut heartbeat = tokio::time::interval(hb);
    heartbeat.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut shutdown_seen = *stop;
    let lost: Option<String> = loop {
        if l.running.is_none() && l.flushing.is_none() {
            if l.joint_is_due() {
                l.start_flush(shared);
            } else if let Some(lease) = l.queue.pop_front() {
                l.running = Some(start_lease(shared, &api, lease));
            } else if l.draining && l.uploads.is_empty() && l.joint.is_none() {
                break None;
            }
        }
        if !l.flushes.is_empty() {
            l.start_due_flushes(&api);
        }
        tokio::select! {
            _ = shutdown.as_mut(), if !shutdown_seen => {
                shutdown_seen = true;
                *stop = true;
                l.on_shutdown();
            }
            _ = heartbeat.tick() => {
                l.heartbeat();
                prefetch::expire(shared);
            }
            end = async { (&mut l.running.as_mut().expect("guarded").handle).await }, if l.running.is_some() => {
                let r = l.running.take().expect("guarded");
                let end = end.unwrap_or_else(|e| {
                    LeaseEnd::Failed(retryable(format!("render task panicked: {e}")))
                });
                l.on_rendered(r.lease_id, r.job_id, end);
            }
            end = async { l.flushing.as_mut().expect("guarded").wait().await }, if l.flushing.is_some() => {
                let f = l.flushing.take().expect("guarded");
                l.on_flushed(&api, f.lease_ids, f.job_id, end);
            }
            Some(done) = l.uploads.join_next(), if !l.uploads.is_empty() => {
                match done {
                    Ok((of, end)) => l.on_uploaded(of, end),
                    Err(e) => l.on_upload_task_lost(e),
                }
            }
            msg = inbound.message() => match msg {
                Ok(Some(v1::CoordinatorMessage { msg: Some(v1::coordinator_message::Msg::Prefetch(p)) })) => {
                    if !l.draining {
                        prefetch::start(shared, &api, p);
                    }
                }
                Ok(Some(m)) => l.on_message(m),
                Ok(None) => break Some("the control stream ended".to_string()),
                Err(s) => break Some(format!("{} ({:?})", s.message(), s.code())),
            },
        }
    };
    let draining = l.draining;
    let end = match lost {
        Some(_) => StreamEnd::Broke,
        None => StreamEnd::Closed,
    };
    l.finish(shared, &api, end).await;
    match lost {
        Some(m) if !draining => Err(SessionEnd::Lost(m)),
        Some(_) if !*stop => Err(SessionEnd::Lost("drained by the coordinator".into())),
        _ => {
            tracing::info!("drained");
            Ok(())
        }
    }
}

fn host_name() -> String {
    std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "unknown".into())
}

fn start_lease(shared: &Arc<Shared>, api: &Api, lease: v1::Lease) -> Running {
    let cancelled = Arc::new(AtomicBool::new(false));
    let lease_id = lease.lease_id;
    let job_id = lease.job_id.clone();
    let shared = shared.clone();
    let api = api.clone();
    let flag = cancelled.clone();
    tracing::info!("lease {lease_id} (job {job_id}): starting");
    let handle = tokio::spawn(async move { do_lease(shared, api, lease, flag).await });
    Running {
        lease_id,
        job_id,
        cancelled,
        handle,
    }
}

/// Why a lease could not be rendered, and whether trying again could help.
struct Fail {
    reason: String,
    severity: Severity,
}

/// Whether a failure is this worker's bad luck or the job's (`LeaseFailed.fatal`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Severity {
    /// Another attempt (here or elsewhere) may succeed: a fetch, a panic, an upload.
    Retryable,
    /// The lease cannot be rendered (its scene does not build, its inputs do not decode).
    Fatal,
}

fn retryable(reason: impl std::fmt::Display) -> Fail {
    Fail {
        reason: reason.to_string(),
        severity: Severity::Retryable,
    }
}

fn fatal(reason: impl std::fmt::Display) -> Fail {
    Fail {
        reason: reason.to_string(),
        severity: Severity::Fatal,
    }
}

fn digest_of_field(bytes: &[u8], what: &str) -> Result<Digest, Fail> {
    <[u8; 32]>::try_from(bytes)
        .map(Digest)
        .map_err(|_| fatal(format!("{what}: a digest of {} bytes", bytes.len())))
}

async fn do_lease(
    shared: Arc<Shared>,
    mut api: Api,
    lease: v1::Lease,
    cancelled: Arc<AtomicBool>,
) -> LeaseEnd {
    let fetch_start = Instant::now();
    let prepared = match prepare(&shared, &mut api, &lease).await {
        Ok(mut p) => {
            p.fetch_seconds = fetch_start.elapsed().as_secs_f64();
            p
        }
        Err(f) => return LeaseEnd::Failed(f),
    };
    if cancelled.load(Ordering::SeqCst) {
        return LeaseEnd::Cancelled;
    }
    let sh = shared.clone();
    // On the render pool's threads, decoding included: glibc gives each thread an arena of
    // its own and frees memory into the arena it came from, so a tree decoded on whichever
    // blocking thread picked the task faulted in fresh pages while its predecessor's went
    // back to another arena.
    let rendered =
        tokio::task::spawn_blocking(move || sh.pool.install(|| render(&sh, prepared))).await;
    let tile = match rendered {
        Ok(Ok(t)) => t,
        Ok(Err(f)) => return LeaseEnd::Failed(f),
        Err(e) => return LeaseEnd::Failed(retryable(format!("render panicked: {e}"))),
    };
    if cancelled.load(Ordering::SeqCst) {
        return LeaseEnd::CancelledRendered(tile);
    }
    LeaseEnd::Rendered(tile)
}

/// Everything a lease's render needs, fetched.
struct Prepared {
    lease: v1::Lease,
    manifest: Manifest,
    /// The scene's cache key: its bundle and settings, seed aside.
    scene_key: prefetch::SceneKey,
    tree_blob: Option<Arc<Vec<u8>>>,
    fractions_blob: Option<Arc<Vec<u8>>>,
    estimate_blob: Option<Arc<Vec<u8>>>,
    /// Seconds spent fetching the blobs.
    fetch_seconds: f64,
}

fn blob_path(cache: &Path, d: &Digest) -> PathBuf {
    cache.join("blobs").join(d.to_hex())
}

/// Fetches the blob `d` into memory, checking its digest.
async fn fetch(api: &mut Api, d: &Digest) -> Result<Vec<u8>, Fail> {
    let mut stream = api
        .fetch_blob(v1::BlobRequest {
            digest: d.0.to_vec(),
        })
        .await
        .map_err(|s| retryable(format!("fetching blob {}: {}", d.to_hex(), s.message())))?
        .into_inner();
    let data = crate::client::read_data_stream(&mut stream)
        .await
        .map_err(|e| retryable(format!("fetching blob {}: {e}", d.to_hex())))?;
    if blake3::hash(&data).as_bytes() != &d.0 {
        return Err(retryable(format!("blob {}: digest mismatch", d.to_hex())));
    }
    Ok(data)
}

/// Fetches the blob `d` into the disk cache unless it is there; returns its path.
async fn ensure_blob(shared: &Shared, api: &mut Api, d: &Digest) -> Result<PathBuf, Fail> {
    let path = blob_path(&shared.cache_dir, d);
    if path.is_file() {
        return Ok(path);
    }
    let data = fetch(api, d).await?;
    let n = shared.tmp_counter.fetch_add(1, Ordering::Relaxed);
    let tmp = shared.cache_dir.join("blobs").join(format!(
        ".tmp-{}-{}-{n}",
        d.to_hex(),
        std::process::id()
    ));
    std::fs::write(&tmp, &data)
        .and_then(|_| std::fs::rename(&tmp, &path))
        .map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            retryable(format!("{}: {e}", path.display()))
        })?;
    Ok(path)
}

/// The pass input named by an optional digest field (empty = none), from memory or fetched.
async fn pass_input(
    shared: &Shared,
    api: &mut Api,
    bytes: &[u8],
    what: &str,
) -> Result<Option<Arc<Vec<u8>>>, Fail> {
    if bytes.is_empty() {
        return Ok(None);
    }
    let d = digest_of_field(bytes, what)?;
    let caches = || shared.caches.lock().expect("cache lock");
    if let Some(data) = most_recent(&mut caches().inputs, &d) {
        return Ok(Some(data));
    }
    let data = Arc::new(fetch(api, &d).await?);
    let mut c = caches();
    c.inputs.push((d, data.clone()));
    if c.inputs.len() > INPUT_CACHE {
        c.inputs.remove(0);
    }
    Ok(Some(data))
}

/// The manifest of a bundle message.
fn manifest_of(bundle: &v1::Bundle) -> Result<Manifest, Fail> {
    let mut files = Vec::with_capacity(bundle.files.len());
    for f in &bundle.files {
        files.push(ManifestEntry {
            path: f.path.clone(),
            digest: digest_of_field(&f.digest, &f.path)?,
            size: f.size,
        });
    }
    Ok(Manifest {
        root: bundle.root.clone(),
        files,
    })
}

async fn prepare(shared: &Shared, api: &mut Api, lease: &v1::Lease) -> Result<Prepared, Fail> {
    let bundle = match &lease.scene {
        Some(v1::lease::Scene::Bundle(b)) => b.clone(),
        Some(v1::lease::Scene::BundleDigest(d)) => {
            let d = digest_of_field(d, "bundle_digest")?;
            let p = ensure_blob(shared, api, &d).await?;
            let bytes =
                std::fs::read(&p).map_err(|e| retryable(format!("{}: {e}", p.display())))?;
            v1::Bundle::decode(bytes.as_slice())
                .map_err(|e| fatal(format!("bundle blob {}: {e}", d.to_hex())))?
        }
        None => return Err(fatal("the lease names no scene bundle")),
    };
    let manifest = manifest_of(&bundle)?;
    let job = &lease.job_id;
    let caches = || shared.caches.lock().expect("cache lock");
    let scene_key = prefetch::scene_key(&bundle, lease.settings.as_ref());
    let mut have_scene = caches().scenes.get(&scene_key, job).is_some();
    if !have_scene {
        if let Some(js) = prefetch::take(shared, &scene_key).await {
            tracing::info!(
                "lease {} (job {job}): its scene was built ahead",
                lease.lease_id
            );
            caches().keep_scene(scene_key, job, js);
            have_scene = true;
        }
    }
    if !have_scene {
        for e in &manifest.files {
            ensure_blob(shared, api, &e.digest).await?;
        }
    }
    let pass = lease
        .pass
        .as_ref()
        .ok_or_else(|| fatal("the lease has no pass"))?;
    let tree_blob = pass_input(shared, api, &pass.tree_digest, "tree_digest").await?;
    let fractions_blob =
        pass_input(shared, api, &pass.fractions_digest, "fractions_digest").await?;
    let estimate_blob = pass_input(shared, api, &pass.estimate_digest, "estimate_digest").await?;
    Ok(Prepared {
        lease: lease.clone(),
        manifest,
        scene_key,
        tree_blob,
        fractions_blob,
        estimate_blob,
        fetch_seconds: 0.0,
    })
}

/// A job id as a directory name.
fn job_dir_name(job: &str) -> String {
    if !job.is_empty()
        && job.len() <= 64
        && job
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    {
        job.to_string()
    } else {
        blake3::hash(job.as_bytes()).to_hex()[..32].to_string()
    }
}

/// The lease's job's scene: from the cache (built for this job or another job of the same
/// scene), or built and cached.
fn load_job_scene(shared: &Shared, p: &Prepared) -> Result<Arc<JobScene>, Fail> {
    let job = &p.lease.job_id;
    let caches = || shared.caches.lock().expect("cache lock");
    let cached = caches().scenes.get(&p.scene_key, job);
    let js = match cached {
        Some(js) => js,
        None => {
            let t0 = Instant::now();
            let settings = p.lease.settings.as_ref();
            let js = Arc::new(build_scene(
                shared,
                &p.manifest,
                settings,
                &job_dir_name(job),
            )?);
            caches().keep_scene(p.scene_key, job, js.clone());
            tracing::info!(
                "job {job}: scene built in {:.3} s ({} scene builds by this worker)",
                t0.elapsed().as_secs_f64(),
                shared.scene_builds.load(Ordering::Relaxed)
            );
            js
        }
    };
    if let Some(img) = &p.lease.image {
        if (img.width, img.height) != (js.scene.width, js.scene.height) {
            return Err(fatal(format!(
                "the scene built at {}x{}, the lease says {}x{}",
                js.scene.width, js.scene.height, img.width, img.height
            )));
        }
    }
    Ok(js)
}

/// Builds the scene of `manifest` with `settings` (integrator, defines, resolution; not the
/// seed) from the blobs in the disk cache, laid out in `bundles/<dir_name>` and removed again
/// once built (the scene holds everything it read).
fn build_scene(
    shared: &Shared,
    manifest: &Manifest,
    settings: Option<&v1::SceneSettings>,
    dir_name: &str,
) -> Result<JobScene, Fail> {
    let dest = shared.cache_dir.join("bundles").join(dir_name);
    if dest.exists() {
        std::fs::remove_dir_all(&dest)
            .map_err(|e| retryable(format!("{}: {e}", dest.display())))?;
    }
    let cache = shared.cache_dir.clone();
    shared.scene_builds.fetch_add(1, Ordering::Relaxed);
    let built = bundle::materialize(manifest, |d| blob_path(&cache, d), &dest)
        .map_err(|e| retryable(format!("materialising the bundle: {e}")))
        .and_then(|_| build_in(shared, &dest, manifest, settings));
    let _ = std::fs::remove_dir_all(&dest);
    built
}

/// Builds the scene materialised in `dest`: on the world of a scene this worker holds when
/// the two differ only in their camera and integrator (the frames of a shot), else from its
/// files.
fn build_in(
    shared: &Shared,
    dest: &Path,
    manifest: &Manifest,
    settings: Option<&v1::SceneSettings>,
) -> Result<JobScene, Fail> {
    let limits = Limits {
        confine_files: true,
        ..Default::default()
    };
    let defines: Vec<(String, String)> = settings
        .map(|s| {
            s.defines
                .iter()
                .map(|d| (d.name.clone(), d.value.clone()))
                .collect()
        })
        .unwrap_or_default();
    let options = SceneOptions {
        overrides: &defines,
        integrator: settings.and_then(|s| s.integrator.as_deref()),
        resolution: (settings.and_then(|s| s.resolution.as_ref())).map(|r| (r.width, r.height)),
    };
    let t0 = Instant::now();
    let held = |key: &Digest| shared.worlds.lock().expect("worlds lock").get(key);
    let local = |e: &dyn std::fmt::Display| bundle::in_bundle_paths(e, dest);
    let (scene, key, built) =
        bundle::build_scene(manifest, dest, &options, &limits, Purpose::Render, held).map_err(
            |e| match e {
                SceneBuild::Load(e) => fatal(format!("loading the scene: {}", local(&e))),
                SceneBuild::Resolution(m) => fatal(m),
                SceneBuild::Build(e) => fatal(format!("building the scene: {}", local(&e))),
            },
        )?;
    match built {
        Built::OnHeldWorld => {
            tracing::info!("{}: built on the world of a scene held", manifest.root)
        }
        Built::FromFiles => {
            let mut worlds = shared.worlds.lock().expect("worlds lock");
            worlds.insert(key, &scene.shared_world());
            tracing::info!(
                "{}: world built in {:.3} s",
                manifest.root,
                t0.elapsed().as_secs_f64()
            );
        }
    }
    let params = scene.guided.clone().unwrap_or_default();
    Ok(JobScene { scene, params })
}

/// The job's tree copy (from the cache), refreshed for the lease's tree version and
/// fractions: a tree blob is read only when the cached copy is another version (a tree is
/// tens of MB).
fn lease_tree(shared: &Shared, p: &Prepared, js: &JobScene) -> Result<JobTree, Fail> {
    let pass = p.lease.pass.as_ref().expect("checked in prepare");
    let cached = shared
        .caches
        .lock()
        .expect("cache lock")
        .trees
        .remove(&p.lease.job_id);
    let want_tree = &pass.tree_digest;
    let stale = cached.as_ref().is_none_or(|t| &t.tree_digest != want_tree)
        || (pass.fractions_digest.is_empty()
            && cached
                .as_ref()
                .is_some_and(|t| !t.fractions_digest.is_empty()));
    if let Some(t) = cached.as_ref().filter(|t| t.recording.is_some()) {
        if stale || t.recording != Some(pass.unit) {
            // Another unit's records wait in this tree for their upload (the session loop
            // uploads them before it starts another unit's lease; this is a guard).
            let unit = t.recording;
            let mut c = shared.caches.lock().expect("cache lock");
            c.trees
                .insert(p.lease.job_id.clone(), cached.expect("checked"));
            return Err(retryable(format!(
                "the tree still holds unit {unit:?}'s records"
            )));
        }
    }
    let mut jt = match cached {
        Some(t) if !stale => t,
        old => {
            // The old tree goes before the new one is decoded: the allocator reuses its
            // memory instead of faulting in a second tree's worth (a tenth of a second at
            // every iteration's start, on every worker).
            drop(old);
            let tree = match &p.tree_blob {
                Some(bytes) => {
                    SdTree::decode(bytes).map_err(|e| fatal(format!("tree blob: {e}")))?
                }
                None => {
                    let (lo, hi) = js.scene.world().accel.bounds();
                    SdTree::new(lo, hi, guide_config(&js.params, &js.scene))
                }
            };
            JobTree {
                tree_digest: want_tree.clone(),
                fractions_digest: Vec::new(),
                tree,
                recording: None,
            }
        }
    };
    if jt.fractions_digest != pass.fractions_digest {
        if let Some(bytes) = &p.fractions_blob {
            let states = codec::decode_fractions(bytes)
                .map_err(|e| fatal(format!("fractions blob: {e}")))?;
            jt.tree
                .set_fraction_states(&states)
                .map_err(|e| fatal(format!("fractions blob: {e}")))?;
        }
        jt.fractions_digest = pass.fractions_digest.clone();
    }
    Ok(jt)
}

/// The lease's pixel estimate (guided roulette) over a `size` frame: its tile's part from
/// the lease, or the whole estimate's blob, cached per job by digest.
fn lease_estimate(
    shared: &Shared,
    p: &Prepared,
    size: (u32, u32),
    region: pathfarm_render::Region,
) -> Result<Arc<Vec<f32>>, Fail> {
    if let Some(part) = &p.lease.estimate {
        let e = codec::decode_tile_estimate(part, size, region);
        return Ok(Arc::new(e.map_err(|e| fatal(format!("lease: {e}")))?));
    }
    let Some(bytes) = &p.estimate_blob else {
        return Ok(Arc::new(Vec::new()));
    };
    let pass = p.lease.pass.as_ref().expect("checked in prepare");
    let job = &p.lease.job_id;
    let caches = || shared.caches.lock().expect("cache lock");
    let cached = caches()
        .estimates
        .get(job)
        .filter(|(d, _)| d == &pass.estimate_digest)
        .map(|(_, e)| e.clone());
    if let Some(e) = cached {
        return Ok(e);
    }
    let e = codec::decode_estimate(bytes).map_err(|e| fatal(format!("estimate blob: {e}")))?;
    let e = Arc::new(e);
    caches()
        .estimates
        .insert(job.clone(), (pass.estimate_digest.clone(), e.clone()));
    Ok(e)
}

fn render(shared: &Shared, p: Prepared) -> Result<RenderedTile, Fail> {
    let start = Instant::now();
    let js = load_job_scene(shared, &p)?;
    let scene = &js.scene;
    let pass = p.lease.pass.as_ref().expect("checked in prepare");
    let spec = codec::spec_from_proto(pass).map_err(fatal)?;
    let rect = p
        .lease
        .tile
        .as_ref()
        .ok_or_else(|| fatal("the lease has no tile"))?;
    let region = codec::region_from_proto(rect, scene.width, scene.height).map_err(fatal)?;
    let job = p.lease.job_id.clone();
    let tree_start = Instant::now();
    let mut jt = lease_tree(shared, &p, &js)?;
    let tree_seconds = tree_start.elapsed().as_secs_f64();
    let estimate = lease_estimate(shared, &p, (scene.width, scene.height), region)?;
    let seed = p
        .lease
        .settings
        .as_ref()
        .and_then(|s| s.seed)
        .unwrap_or(scene.seed);
    let prepare_seconds = p.fetch_seconds + start.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let out = {
        let inputs = UnitInputs {
            scene,
            params: &js.params,
            tree: &jt.tree,
            estimate: &estimate,
            seed,
            tile_size: 8,
        };
        match shared.rendering {
            Rendering::Real => {
                (shared.pool).install(|| render_unit(&inputs, &spec, region, &|_| {}))
            }
            Rendering::Simulated { seconds_per_sample } => {
                simulated::simulate_unit(&spec, region, seconds_per_sample)
            }
        }
    };
    let seconds = t0.elapsed().as_secs_f64();
    let serialize_start = Instant::now();
    if spec.record() {
        // The statistics stay in the tree: taken once for this unit's joint upload.
        jt.recording = Some(spec.unit);
    }
    shared
        .caches
        .lock()
        .expect("cache lock")
        .keep_tree(&job, jt);
    let pixels = codec::encode_tile_pixels(&out.pixels);
    let pixels_digest = blake3::hash(&pixels).as_bytes().to_vec();
    let serialize_seconds = serialize_start.elapsed().as_secs_f64();
    tracing::info!(
        "lease {} (job {}): rendered unit {} in {:.3} s (inputs {:.3} s, serialising {:.3} s, {} bytes; fetching {:.3} s, tree {:.3} s)",
        p.lease.lease_id,
        job,
        spec.unit,
        seconds,
        prepare_seconds,
        serialize_seconds,
        pixels.len(),
        p.fetch_seconds,
        tree_seconds,
    );
    let part = v1::UploadedTile {
        lease_id: p.lease.lease_id,
        tile: Some(*rect),
        counters: Some(v1::TileCounters {
            render_seconds: seconds,
            prepare_seconds,
            serialize_seconds,
            ..codec::tile_counters(&out)
        }),
        pixels_size: pixels.len() as u64,
        pixels_digest,
    };
    Ok(RenderedTile {
        job_id: job,
        unit: pass.unit,
        record: spec.record(),
        hold: (spec.record() && pass.hold_records).then(|| HeldKey {
            tree_digest: pass.tree_digest.clone(),
            epoch: pass.records_epoch,
        }),
        part,
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn job_dir_names_are_safe() {
        assert_eq!(job_dir_name("job-12_a"), "job-12_a");
        let n = job_dir_name("../etc");
        assert_eq!(n.len(), 32);
        assert!(n.chars().all(|c| c.is_ascii_hexdigit()));
    }
}
