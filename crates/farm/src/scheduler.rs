//! The lease scheduler: which worker renders which tile, and when a lease is void.
//!
//! A pure state machine: no sockets, threads, I/O or clock. The gRPC coordinator (the
//! *driver*) owns one [`Scheduler`] behind a mutex, calls it for every message and timer, and
//! acts on what it returns. Time is injected as [`Millis`] (milliseconds on the driver's
//! monotonic clock); the driver must pass non-decreasing instants.
//!
//! ## Model
//!
//! * A job's session emits **units** in order ([`Scheduler::offer_unit`]), at most
//!   [`MAX_UNITS_IN_FLIGHT`] incomplete at a time (training passes overlap: a pass starts
//!   while the last tiles of the one before it render); a unit is split into **tiles**, and
//!   the older unit's ready tiles are leased first. Every tile of a unit is accepted exactly
//!   once; the [`Completion`] that accepts a unit's last tile carries `unit_done: true`, and
//!   that is the only one that does, so the driver tells the session and offers what it
//!   issues next.
//! * Workers **lease** tiles ([`Scheduler::next_lease`]), at most
//!   [`SchedulerConfig::leases_per_worker`] at a time. A lease is valid while `now < deadline`;
//!   heartbeats that list it push the deadline to `now + lease_timeout`. A lease whose deadline
//!   has passed is expired whether or not [`Scheduler::tick`] has reclaimed it yet, so the
//!   outcome of a late message does not depend on how often the driver ticks.
//! * A tile whose lease expires, whose worker is lost, or whose worker reports a failure counts
//!   an attempt and is queued again, ahead of the unit's untouched tiles. When a tile has
//!   failed `max_attempts` times its job fails ([`Event::JobFailed`]) and the job's other leases
//!   are cancelled ([`Event::CancelLease`]).
//! * Every call that can fail a job returns the [`Event`]s it caused, so the driver cannot miss
//!   a failure by forgetting to poll.
//!
//! ## Driver contract
//!
//! Call [`Scheduler::tick`] at least at [`Scheduler::next_deadline`]; forward
//! [`Event::CancelLease`] to its worker; report [`Event::JobFailed`] to the client; when a
//! completion says `unit_done`, feed the session and [`Scheduler::offer_unit`] its next unit.
//! Any message from a worker (heartbeat, lease request, completion, failure, hand-back) counts
//! as a sign of life for the heartbeat timeout.
//!
//! ## Memory
//!
//! Bounded by the tiles of each job's offered units plus the leases issued for those units: a
//! lease's record stays until a unit offered after its complete unit drops it, or its job is
//! removed,
//! because exactly-once and the precise [`Rejection`] of a late message need it. After that a
//! message naming the lease gets [`Rejection::UnknownLease`].

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::ops::Add;
use std::time::Duration;

/// Units of one job that may be incomplete at once.
pub const MAX_UNITS_IN_FLIGHT: usize = 2;

/// An instant on the driver's clock: milliseconds since an epoch of the driver's choosing
/// (e.g. the coordinator's start, from a monotonic clock). Spans are [`Duration`]s.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Millis(pub u64);

impl Add<Duration> for Millis {
    type Output = Millis;

    /// Saturating, so a huge timeout means "never" instead of wrapping into the past.
    fn add(self, span: Duration) -> Millis {
        let ms = u64::try_from(span.as_millis()).unwrap_or(u64::MAX);
        Millis(self.0.saturating_add(ms))
    }
}

impl fmt::Display for Millis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}.{:03} s", self.0 / 1000, self.0 % 1000)
    }
}

macro_rules! id_type {
    ($(#[$doc:meta])* $name:ident, $label:literal) => {
        $(#[$doc])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
        pub struct $name(pub u64);

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                write!(f, concat!($label, " {}"), self.0)
            }
        }
    };
}

id_type!(
    /// A render job, named by the coordinator.
    JobId,
    "job"
);
id_type!(
    /// A worker process, named by the coordinator (a restarted process gets a new id).
    WorkerId,
    "worker"
);
id_type!(
    /// A lease, allocated by the scheduler: increasing, never reused.
    LeaseId,
    "lease"
);

/// One tile of one unit of one job: the thing rendered exactly once.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct TaskKey {
    pub job: JobId,
    pub unit: u64,
    pub tile: u32,
}

impl fmt::Display for TaskKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "tile {} of unit {} of {}",
            self.tile, self.unit, self.job
        )
    }
}

/// Tunables. All spans are measured on the driver's clock.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SchedulerConfig {
    /// How long a lease lives without a heartbeat listing it (default 60 s). Longer than the
    /// slowest tile between two heartbeats; shorter means a hung worker loses its tile sooner.
    pub lease_timeout: Duration,
    /// A worker silent this long is declared lost and its leases returned (default 15 s,
    /// a few heartbeat intervals).
    pub heartbeat_timeout: Duration,
    /// Counted failures (expiry, loss, reported failure) after which a tile fails its job
    /// (default 5; at least 1).
    pub max_attempts: u32,
    /// Leases a worker may hold at once (default 24, at least 1): a worker holds the tiles
    /// of a unit it has rendered until it uploads them together (at most
    /// [`crate::worker::MAX_JOINT_TILES`]), besides one rendering, one prefetched and an
    /// upload in flight. The coordinator's offers follow the worker's requests; this is
    /// the ceiling.
    pub leases_per_worker: u32,
    /// The longest a lease can live however often heartbeats list it (default 10 min): a
    /// worker that heartbeats its leases but never uploads them cannot hold a job forever.
    pub max_lease_lifetime: Duration,
}

impl Default for SchedulerConfig {
    fn default() -> Self {
        SchedulerConfig {
            lease_timeout: Duration::from_secs(60),
            heartbeat_timeout: Duration::from_secs(15),
            max_attempts: 5,
            leases_per_worker: 24,
            max_lease_lifetime: Duration::from_secs(600),
        }
    }
}

/// What the scheduler knows of a lease ([`Scheduler::lease`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LeaseView {
    pub worker: WorkerId,
    pub key: TaskKey,
    /// Not completed, reclaimed or cancelled yet.
    pub live: bool,
}

/// A tile handed to a worker.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Lease {
    pub id: LeaseId,
    pub key: TaskKey,
    /// Void from this instant unless a heartbeat extends it.
    pub deadline: Millis,
    /// 1 for the first try; one more per counted failure (hand-backs do not count).
    pub attempt: u32,
}

/// An accepted result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Completion {
    pub key: TaskKey,
    /// True on exactly one completion per unit: the one that accepted its last tile.
    pub unit_done: bool,
}

/// Why a completion (or failure report) was not taken. The driver discards the result in all
/// cases; the variants are for logs and metrics.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, thiserror::Error)]
pub enum Rejection {
    /// Never issued, or its unit's bookkeeping is gone (the next unit was offered, or the job
    /// was removed).
    #[error("unknown lease")]
    UnknownLease,
    /// The deadline passed, or the lease was returned (lost worker, reported failure,
    /// hand-back) and its tile waits to be leased again.
    #[error("lease expired")]
    Expired,
    /// The lease was returned and its tile has since been leased again or accepted through
    /// another lease.
    #[error("tile leased again or completed through another lease")]
    Superseded,
    /// The lease belongs to another worker.
    #[error("lease held by another worker")]
    WrongWorker,
    /// The job was cancelled or has failed (a removed job's leases are `UnknownLease`).
    #[error("job cancelled or failed")]
    JobGone,
    /// This lease's result was already accepted (a retransmission): the tile is safe.
    #[error("result already accepted")]
    Duplicate,
}

/// Misuse by the driver: unknown or duplicate ids, units out of turn.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SchedError {
    #[error("{0} already exists")]
    DuplicateJob(JobId),
    #[error("{0} is not known")]
    UnknownJob(JobId),
    #[error("{0} is already registered")]
    DuplicateWorker(WorkerId),
    #[error("{0} is not registered")]
    UnknownWorker(WorkerId),
    #[error("{0} is cancelled or failed and takes no more units")]
    JobNotActive(JobId),
    #[error("unit {unit} of {job} and the one after it still have tiles to render")]
    UnitInProgress { job: JobId, unit: u64 },
    #[error("unit {unit} of {job} does not follow unit {last}")]
    UnitOutOfOrder { job: JobId, unit: u64, last: u64 },
    #[error("unit {unit} of {job} has no tiles")]
    EmptyUnit { job: JobId, unit: u64 },
}

/// One counted failure of a tile.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Failure {
    Expired {
        worker: WorkerId,
        lease: LeaseId,
    },
    WorkerLost {
        worker: WorkerId,
        lease: LeaseId,
    },
    /// The worker said it could not render the tile (message truncated to 1 KiB).
    Reported {
        worker: WorkerId,
        lease: LeaseId,
        message: String,
    },
}

impl fmt::Display for Failure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Failure::Expired { worker, lease } => write!(f, "{lease} on {worker} expired"),
            Failure::WorkerLost { worker, lease } => {
                write!(f, "{worker} was lost holding {lease}")
            }
            Failure::Reported {
                worker,
                lease,
                message,
            } => {
                write!(f, "{worker} reported on {lease}: {message}")
            }
        }
    }
}

/// Why a job failed: the tile that ran out of attempts and its last failure.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FailureReason {
    pub key: TaskKey,
    pub attempts: u32,
    pub last: Failure,
}

impl fmt::Display for FailureReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (key, attempts, last) = (self.key, self.attempts, &self.last);
        write!(f, "{key} failed {attempts} times; last: {last}")
    }
}

/// What the driver must act on.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// A lease's deadline passed; its tile is queued again (an attempt counted). The driver
    /// may tell the worker to abandon it.
    LeaseExpired {
        worker: WorkerId,
        lease: LeaseId,
        key: TaskKey,
    },
    /// A worker was declared lost (silent, or [`Scheduler::worker_lost`]); it is forgotten and
    /// all its leases were returned, each counting an attempt.
    WorkerLost {
        worker: WorkerId,
        returned: Vec<TaskKey>,
    },
    /// A tile ran out of attempts. Followed by the job's `CancelLease`s.
    JobFailed { job: JobId, reason: FailureReason },
    /// Tell the worker to stop rendering this lease; its result will be rejected.
    CancelLease {
        worker: WorkerId,
        lease: LeaseId,
        key: TaskKey,
    },
}

/// Where a job stands.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum JobState {
    Active,
    Cancelled,
    Failed(FailureReason),
}

impl fmt::Display for JobState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            JobState::Active => f.write_str("active"),
            JobState::Cancelled => f.write_str("cancelled"),
            JobState::Failed(reason) => write!(f, "failed: {reason}"),
        }
    }
}

/// Status of a job, for metrics.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JobInfo {
    pub job: JobId,
    pub priority: i32,
    pub arrived: Millis,
    pub state: JobState,
    pub unit: Option<UnitProgress>,
}

/// Progress of a job's oldest incomplete unit (or its last one).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UnitProgress {
    pub unit: u64,
    pub tiles: u32,
    pub done: u32,
    pub in_flight: usize,
    pub ready: usize,
}

/// Status of a worker, for metrics.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WorkerInfo {
    pub worker: WorkerId,
    /// As registered; informational (a tile uses all of a worker's threads).
    pub threads: u32,
    pub draining: bool,
    pub leases_held: usize,
    pub tiles_done: u64,
    /// The last message of any kind from the worker.
    pub last_seen: Millis,
}

/// Cap on a worker-supplied failure message: it may outlive the lease in a failed job's
/// reason, and it comes from the network.
const MAX_MESSAGE_BYTES: usize = 1024;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum TileState {
    Ready,
    Leased(LeaseId),
    Done,
}

#[derive(Clone, Copy, Debug)]
struct Tile {
    state: TileState,
    /// Counted failures so far.
    failures: u32,
}

#[derive(Debug)]
struct Unit {
    number: u64,
    tiles: Vec<Tile>,
    /// Ready tiles that were leased before: they go first, lowest first, so a returned tile
    /// does not wait behind the rest of the unit (the unit finishes only when it is done).
    returned: BTreeSet<u32>,
    /// Tiles `next_fresh..` have never been leased; they are ready, in order.
    next_fresh: u32,
    live: BTreeSet<LeaseId>,
    /// Every lease issued for this unit: their records go when the unit does.
    issued: Vec<LeaseId>,
    remaining: u32,
}

impl Unit {
    fn new(number: u64, tiles: u32) -> Unit {
        let tile = Tile {
            state: TileState::Ready,
            failures: 0,
        };
        Unit {
            number,
            tiles: vec![tile; tiles as usize],
            returned: BTreeSet::new(),
            next_fresh: 0,
            live: BTreeSet::new(),
            issued: Vec::new(),
            remaining: tiles,
        }
    }

    fn ready(&self) -> usize {
        self.returned.len() + (self.tiles.len() - self.next_fresh as usize)
    }

    fn take_ready(&mut self) -> Option<u32> {
        if let Some(tile) = self.returned.pop_first() {
            return Some(tile);
        }
        let fresh = self.next_fresh;
        if fresh as usize == self.tiles.len() {
            return None;
        }
        self.next_fresh += 1;
        Some(fresh)
    }
}

#[derive(Debug)]
struct Job {
    priority: i32,
    /// Position in arrival order: the tie-break between equal priorities.
    arrival: u64,
    arrived: Millis,
    state: JobState,
    /// Offered units, oldest first: complete ones are dropped at the next offer.
    units: Vec<Unit>,
}

impl Job {
    fn is_active(&self) -> bool {
        self.state == JobState::Active
    }

    fn ready(&self) -> usize {
        if !self.is_active() {
            return 0;
        }
        self.units.iter().map(Unit::ready).sum()
    }

    fn in_flight(&self) -> usize {
        self.units.iter().map(|unit| unit.live.len()).sum()
    }

    fn unit(&self, number: u64) -> Option<&Unit> {
        self.units.iter().find(|unit| unit.number == number)
    }
}

#[derive(Debug)]
struct Worker {
    threads: u32,
    draining: bool,
    last_seen: Millis,
    held: BTreeSet<LeaseId>,
    tiles_done: u64,
    /// Jobs this worker gets no leases of (it sent them bad tiles).
    blocked: BTreeSet<JobId>,
    /// The jobs it was leased tiles of most recently (most recent last, at most
    /// [`AFFINITY_JOBS`]): it holds their scenes and trees, so it prefers them.
    served: Vec<JobId>,
}

/// Jobs a worker is taken to hold the scenes and trees of: the most recent it served, as
/// many as a worker keeps trees of (its scenes are kept within a memory budget, usually
/// more).
pub const AFFINITY_JOBS: usize = 8;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Ending {
    Completed,
    /// Expired, lost, failed or handed back: the tile went back to the queue.
    Reclaimed,
    /// Its job was cancelled or failed.
    Cancelled,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum LeaseState {
    Live { deadline: Millis },
    Ended(Ending),
}

#[derive(Debug)]
struct LeaseRec {
    key: TaskKey,
    worker: WorkerId,
    state: LeaseState,
    /// The latest deadline heartbeats can give it (issue + `max_lease_lifetime`).
    last_deadline: Millis,
}

/// The scheduler. See the module documentation.
#[derive(Debug)]
pub struct Scheduler {
    config: SchedulerConfig,
    jobs: BTreeMap<JobId, Job>,
    /// Scheduling order: highest priority first, then earliest arrival.
    order: BTreeSet<(Reverse<i32>, u64, JobId)>,
    workers: BTreeMap<WorkerId, Worker>,
    /// Live leases and the ended leases of current units.
    leases: BTreeMap<LeaseId, LeaseRec>,
    /// Live leases by deadline, so `tick` touches only what expires.
    deadlines: BTreeSet<(Millis, LeaseId)>,
    next_lease_id: u64,
    next_arrival: u64,
}

/// The unit a lease record belongs to. Records are dropped with their unit (an offer after
/// it completed, job removal), so a record's unit is always one of its job's offered units.
fn unit_of(jobs: &mut BTreeMap<JobId, Job>, key: TaskKey) -> &mut Unit {
    jobs.get_mut(&key.job)
        .and_then(|job| job.units.iter_mut().find(|unit| unit.number == key.unit))
        .expect("a lease record outlives neither its job nor its unit")
}

fn truncated(message: &str) -> String {
    if message.len() <= MAX_MESSAGE_BYTES {
        return message.to_owned();
    }
    let mut end = MAX_MESSAGE_BYTES;
    while !message.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}…", &message[..end])
}

impl Scheduler {
    /// # Panics
    /// If `max_attempts` or `leases_per_worker` is 0 (no tile could ever be rendered).
    pub fn new(config: SchedulerConfig) -> Scheduler {
        assert!(config.max_attempts >= 1, "max_attempts must be at least 1");
        assert!(
            config.leases_per_worker >= 1,
            "leases_per_worker must be at least 1"
        );
        Scheduler {
            config,
            jobs: BTreeMap::new(),
            order: BTreeSet::new(),
            workers: BTreeMap::new(),
            leases: BTreeMap::new(),
            deadlines: BTreeSet::new(),
            next_lease_id: 0,
            next_arrival: 0,
        }
    }

    pub fn config(&self) -> &SchedulerConfig {
        &self.config
    }

    // ----- jobs -----

    /// A new job, with no unit yet. Arrival order is the order of these calls.
    pub fn add_job(&mut self, job: JobId, priority: i32, now: Millis) -> Result<(), SchedError> {
        if self.jobs.contains_key(&job) {
            return Err(SchedError::DuplicateJob(job));
        }
        let arrival = self.next_arrival;
        self.next_arrival += 1;
        let state = JobState::Active;
        let record = Job {
            priority,
            arrival,
            arrived: now,
            state,
            units: Vec::new(),
        };
        self.jobs.insert(job, record);
        self.order.insert((Reverse(priority), arrival, job));
        Ok(())
    }

    /// Job `job` is now of `priority`: its place in the scheduling order moves (leases
    /// already out stay).
    pub fn set_priority(&mut self, job: JobId, priority: i32) -> Result<(), SchedError> {
        let record = self.jobs.get_mut(&job).ok_or(SchedError::UnknownJob(job))?;
        let arrival = record.arrival;
        self.order.remove(&(Reverse(record.priority), arrival, job));
        record.priority = priority;
        self.order.insert((Reverse(priority), arrival, job));
        Ok(())
    }

    /// Adds unit `unit` (`tiles` tiles, ready in tile order) to the job's units. It must be
    /// numbered above the units offered before, and fewer than [`MAX_UNITS_IN_FLIGHT`] of
    /// those may be incomplete; the complete ones' bookkeeping is dropped.
    pub fn offer_unit(&mut self, job: JobId, unit: u64, tiles: u32) -> Result<(), SchedError> {
        let record = self.jobs.get_mut(&job).ok_or(SchedError::UnknownJob(job))?;
        if !record.is_active() {
            return Err(SchedError::JobNotActive(job));
        }
        if let Some(last) = record.units.last().map(|u| u.number) {
            if unit <= last {
                return Err(SchedError::UnitOutOfOrder { job, unit, last });
            }
        }
        let mut incomplete = record.units.iter().filter(|u| u.remaining > 0);
        if let Some(oldest) = incomplete.next() {
            if incomplete.count() + 1 >= MAX_UNITS_IN_FLIGHT {
                let unit = oldest.number;
                return Err(SchedError::UnitInProgress { job, unit });
            }
        }
        if tiles == 0 {
            return Err(SchedError::EmptyUnit { job, unit });
        }
        let (done, kept) = std::mem::take(&mut record.units)
            .into_iter()
            .partition(|u| u.remaining == 0);
        record.units = kept;
        record.units.push(Unit::new(unit, tiles));
        for id in done.into_iter().flat_map(|u: Unit| u.issued) {
            self.leases.remove(&id);
        }
        Ok(())
    }

    /// Cancels the job: it leases nothing more and rejects results with `JobGone`. Returns
    /// the live leases the driver must cancel on their workers (none if already over).
    pub fn cancel_job(&mut self, job: JobId) -> Result<Vec<(WorkerId, LeaseId)>, SchedError> {
        let record = self.jobs.get_mut(&job).ok_or(SchedError::UnknownJob(job))?;
        if !record.is_active() {
            return Ok(Vec::new());
        }
        record.state = JobState::Cancelled;
        let cancelled = self.cancel_live(job);
        Ok(cancelled
            .into_iter()
            .map(|(worker, lease, _)| (worker, lease))
            .collect())
    }

    /// Forgets the job and all its bookkeeping (cancelling it first if it is still active:
    /// the leases to cancel are returned). Later messages about its leases get `UnknownLease`.
    pub fn remove_job(&mut self, job: JobId) -> Result<Vec<(WorkerId, LeaseId)>, SchedError> {
        let cancelled = self.cancel_job(job)?;
        let record = self.jobs.remove(&job).expect("cancel_job found it");
        self.order
            .remove(&(Reverse(record.priority), record.arrival, job));
        for id in record.units.into_iter().flat_map(|unit| unit.issued) {
            self.leases.remove(&id);
        }
        Ok(cancelled)
    }

    // ----- workers -----

    pub fn register_worker(
        &mut self,
        worker: WorkerId,
        threads: u32,
        now: Millis,
    ) -> Result<(), SchedError> {
        if self.workers.contains_key(&worker) {
            return Err(SchedError::DuplicateWorker(worker));
        }
        let held = BTreeSet::new();
        let record = Worker {
            threads,
            draining: false,
            last_seen: now,
            held,
            tiles_done: 0,
            blocked: BTreeSet::new(),
            served: Vec::new(),
        };
        self.workers.insert(worker, record);
        Ok(())
    }

    /// Extends the deadline of every listed lease the worker validly holds to
    /// `now + lease_timeout`. Returns the listed leases it does not (or no longer) validly
    /// hold, which the worker should abandon.
    ///
    /// A lease the worker holds but does not list is left alone, not returned: a heartbeat
    /// can cross a lease grant in flight, so absence is no evidence of loss, and the
    /// deadline bounds what a really forgotten lease costs.
    pub fn heartbeat(
        &mut self,
        worker: WorkerId,
        active: &[LeaseId],
        now: Millis,
    ) -> Result<Vec<LeaseId>, SchedError> {
        self.touch_known(worker, now)?;
        let stale = active
            .iter()
            .copied()
            .filter(|&id| !self.extend(worker, id, now));
        Ok(stale.collect())
    }

    /// Declares the worker lost and forgets it: its leases go back to the front of their
    /// queues, each counting an attempt. Returns [`Event::WorkerLost`] and, if that exhausted
    /// a tile, the job failures it caused.
    pub fn worker_lost(&mut self, worker: WorkerId) -> Result<Vec<Event>, SchedError> {
        if !self.workers.contains_key(&worker) {
            return Err(SchedError::UnknownWorker(worker));
        }
        let mut events = Vec::new();
        let exhausted = self.lose(worker, &mut events);
        self.settle(exhausted, &mut events);
        Ok(events)
    }

    /// The worker gets no new leases; those it holds stay valid. When it holds none it can
    /// leave ([`Scheduler::worker_lost`] then returns nothing to requeue).
    pub fn drain_worker(&mut self, worker: WorkerId) -> Result<(), SchedError> {
        let record = self
            .workers
            .get_mut(&worker)
            .ok_or(SchedError::UnknownWorker(worker))?;
        record.draining = true;
        Ok(())
    }

    /// The worker gives leases back unrendered (e.g. shutting down): their tiles go to the
    /// front of their queues without counting an attempt. Leases it does not validly hold are
    /// ignored (an expired one is counted by `tick` as usual). Returns the tiles requeued.
    pub fn hand_back(
        &mut self,
        worker: WorkerId,
        leases: &[LeaseId],
        now: Millis,
    ) -> Result<Vec<TaskKey>, SchedError> {
        self.touch_known(worker, now)?;
        let mut keys = Vec::new();
        for &id in leases {
            if self.check(worker, id, now).is_ok() {
                keys.push(self.leases[&id].key);
                let exhausted = self.reclaim(id, None);
                debug_assert!(exhausted.is_none(), "a hand-back counts no attempt");
            }
        }
        Ok(keys)
    }

    // ----- leases -----

    /// The next tile for this worker, if it is registered, not draining, below its lease
    /// limit, and some job it is not blocked from has a ready tile: the highest-priority
    /// such job (ties: earliest arrival), its returned tiles first (lowest first), then its
    /// untouched tiles in order.
    ///
    /// Not a sign of the worker's life: the driver offers, the worker has said nothing (a
    /// worker that stopped reading is declared lost after `heartbeat_timeout` however often
    /// it is offered work).
    pub fn next_lease(&mut self, worker: WorkerId, now: Millis) -> Option<Lease> {
        let record = self.workers.get(&worker)?;
        if record.draining || record.held.len() >= self.config.leases_per_worker as usize {
            return None;
        }
        let job = self.pick_job(record)?;
        let served = &mut self.workers.get_mut(&worker).expect("checked").served;
        served.retain(|&j| j != job);
        served.push(job);
        if served.len() > AFFINITY_JOBS {
            served.remove(0);
        }
        Some(self.issue(worker, job, now))
    }

    /// The worker gets no more leases of `job` (it sent bad tiles); the leases of the job
    /// it holds are returned to the queue without counting an attempt (their tiles are not
    /// at fault) and listed for the driver to cancel.
    pub fn block(&mut self, worker: WorkerId, job: JobId) -> Result<Vec<LeaseId>, SchedError> {
        let record = self
            .workers
            .get_mut(&worker)
            .ok_or(SchedError::UnknownWorker(worker))?;
        record.blocked.insert(job);
        let of_job: Vec<LeaseId> = (record.held.iter())
            .copied()
            .filter(|id| self.leases[id].key.job == job)
            .collect();
        for &id in &of_job {
            let exhausted = self.reclaim(id, None);
            debug_assert!(exhausted.is_none(), "a block counts no attempt");
        }
        Ok(of_job)
    }

    /// Whether `worker` is blocked from `job`.
    pub fn is_blocked(&self, worker: WorkerId, job: JobId) -> bool {
        self.workers
            .get(&worker)
            .is_some_and(|w| w.blocked.contains(&job))
    }

    /// Accepts the lease's result if the lease is live, this worker's, and before its
    /// deadline; otherwise says why not. A tile is accepted at most once.
    pub fn complete(
        &mut self,
        worker: WorkerId,
        lease: LeaseId,
        now: Millis,
    ) -> Result<Completion, Rejection> {
        self.touch(worker, now);
        self.check(worker, lease, now)?;
        let (key, _) = self
            .end_lease(lease, Ending::Completed)
            .expect("checked live");
        if let Some(record) = self.workers.get_mut(&worker) {
            record.tiles_done += 1;
        }
        let unit_done = unit_of(&mut self.jobs, key).remaining == 0;
        Ok(Completion { key, unit_done })
    }

    /// Accepts the results of several leases at once (a worker's joint upload of tiles of
    /// one unit), all or none: if any lease is not this worker's live lease, nothing is
    /// accepted and the first lease's rejection, in `leases` order, is returned (an upload
    /// whose every lease was already accepted is a [`Rejection::Duplicate`], one with only
    /// some accepted is [`Rejection::Superseded`]; a lease named twice is an
    /// [`Rejection::UnknownLease`]). On success the
    /// completions are in `leases` order; at most the last can have `unit_done`.
    pub fn complete_all(
        &mut self,
        worker: WorkerId,
        leases: &[LeaseId],
        now: Millis,
    ) -> Result<Vec<Completion>, Rejection> {
        self.touch(worker, now);
        self.check_all(worker, leases, now)?;
        Ok(leases
            .iter()
            .map(|&id| self.complete(worker, id, now).expect("checked live"))
            .collect())
    }

    /// What [`Scheduler::complete_all`] would answer, without accepting anything: a driver
    /// validates the results between the two, and commits only what passed.
    pub fn check_all(
        &self,
        worker: WorkerId,
        leases: &[LeaseId],
        now: Millis,
    ) -> Result<(), Rejection> {
        let checks: Vec<Result<(), Rejection>> = leases
            .iter()
            .map(|&id| self.check(worker, id, now))
            .collect();
        if !checks.is_empty() && checks.iter().all(|c| *c == Err(Rejection::Duplicate)) {
            return Err(Rejection::Duplicate);
        }
        if let Some(r) = checks.iter().find_map(|c| c.err()) {
            // Some accepted, some not: never a retry of one upload (a worker uploads a
            // joint set once, whole), so not a duplicate either.
            return Err(match r {
                Rejection::Duplicate => Rejection::Superseded,
                r => r,
            });
        }
        let mut seen = BTreeSet::new();
        if leases.iter().any(|id| !seen.insert(*id)) {
            return Err(Rejection::UnknownLease);
        }
        Ok(())
    }

    /// The worker could not render the lease: its tile is queued again, counting an attempt.
    /// Returns the job failure this caused, if the tile is out of attempts.
    pub fn fail_lease(
        &mut self,
        worker: WorkerId,
        lease: LeaseId,
        reason: &str,
        now: Millis,
    ) -> Result<Vec<Event>, Rejection> {
        self.touch(worker, now);
        self.check(worker, lease, now)?;
        let message = truncated(reason);
        let failure = Failure::Reported {
            worker,
            lease,
            message,
        };
        let exhausted = self.reclaim(lease, Some(failure));
        let mut events = Vec::new();
        self.settle(exhausted, &mut events);
        Ok(events)
    }

    /// Declares silent workers lost, then expires leases whose deadline has come, then fails
    /// the jobs whose tiles ran out of attempts. Events come in that order.
    pub fn tick(&mut self, now: Millis) -> Vec<Event> {
        let mut events = Vec::new();
        let mut exhausted = Vec::new();
        let timeout = self.config.heartbeat_timeout;
        let silent: Vec<WorkerId> = (self.workers.iter())
            .filter(|(_, record)| record.last_seen + timeout <= now)
            .map(|(&id, _)| id)
            .collect();
        for worker in silent {
            exhausted.extend(self.lose(worker, &mut events));
        }
        while let Some(&(deadline, id)) = self.deadlines.first() {
            if deadline > now {
                break;
            }
            let (worker, key) = (self.leases[&id].worker, self.leases[&id].key);
            events.push(Event::LeaseExpired {
                worker,
                lease: id,
                key,
            });
            exhausted.extend(self.reclaim(id, Some(Failure::Expired { worker, lease: id })));
        }
        self.settle(exhausted, &mut events);
        events
    }

    /// When `tick` next has something to do: the earliest lease deadline or worker timeout.
    pub fn next_deadline(&self) -> Option<Millis> {
        let timeout = self.config.heartbeat_timeout;
        let lease = self.deadlines.first().map(|&(deadline, _)| deadline);
        let worker = self
            .workers
            .values()
            .map(|record| record.last_seen + timeout)
            .min();
        lease.into_iter().chain(worker).min()
    }

    // ----- queries -----

    /// The worker and tile of a lease the scheduler still knows (live, or ended in a unit
    /// still offered), and whether it is live.
    pub fn lease(&self, id: LeaseId) -> Option<LeaseView> {
        let rec = self.leases.get(&id)?;
        Some(LeaseView {
            worker: rec.worker,
            key: rec.key,
            live: matches!(rec.state, LeaseState::Live { .. }),
        })
    }

    /// The live leases `worker` holds, in id order (empty if unknown).
    pub fn held_by(&self, worker: WorkerId) -> Vec<LeaseId> {
        self.workers
            .get(&worker)
            .map_or(Vec::new(), |w| w.held.iter().copied().collect())
    }

    /// Whether `unit` is one of the job's offered units and all its tiles are accepted.
    pub fn unit_complete(&self, job: JobId, unit: u64) -> bool {
        let offered = self.jobs.get(&job).and_then(|record| record.unit(unit));
        offered.is_some_and(|offered| offered.remaining == 0)
    }

    /// Live leases of the job (0 if unknown).
    pub fn in_flight(&self, job: JobId) -> usize {
        self.jobs.get(&job).map_or(0, Job::in_flight)
    }

    pub fn in_flight_total(&self) -> usize {
        self.deadlines.len()
    }

    /// Tiles of the job waiting for a worker (0 if unknown, cancelled or failed).
    pub fn ready(&self, job: JobId) -> usize {
        self.jobs.get(&job).map_or(0, Job::ready)
    }

    pub fn ready_total(&self) -> usize {
        self.jobs.values().map(Job::ready).sum()
    }

    pub fn job_info(&self, job: JobId) -> Option<JobInfo> {
        let record = self.jobs.get(&job)?;
        let oldest = record.units.iter().find(|unit| unit.remaining > 0);
        let unit = oldest.or(record.units.last()).map(|unit| UnitProgress {
            unit: unit.number,
            tiles: unit.tiles.len() as u32,
            done: unit.tiles.len() as u32 - unit.remaining,
            in_flight: unit.live.len(),
            ready: record.ready(),
        });
        let (priority, arrived, state) = (record.priority, record.arrived, record.state.clone());
        Some(JobInfo {
            job,
            priority,
            arrived,
            state,
            unit,
        })
    }

    /// Every known job, in scheduling order.
    pub fn jobs(&self) -> Vec<JobInfo> {
        let ids = self.order.iter().map(|&(_, _, job)| job);
        ids.filter_map(|job| self.job_info(job)).collect()
    }

    pub fn worker_info(&self, worker: WorkerId) -> Option<WorkerInfo> {
        let record = self.workers.get(&worker)?;
        Some(WorkerInfo {
            worker,
            threads: record.threads,
            draining: record.draining,
            leases_held: record.held.len(),
            tiles_done: record.tiles_done,
            last_seen: record.last_seen,
        })
    }

    /// Every registered worker, by id.
    pub fn workers(&self) -> Vec<WorkerInfo> {
        (self.workers.keys())
            .filter_map(|&id| self.worker_info(id))
            .collect()
    }

    // ----- internals -----

    /// Records a sign of life; false if the worker is not registered.
    fn touch(&mut self, worker: WorkerId, now: Millis) -> bool {
        let Some(record) = self.workers.get_mut(&worker) else {
            return false;
        };
        record.last_seen = record.last_seen.max(now);
        true
    }

    /// [`Self::touch`] for the calls only a registered worker may make.
    fn touch_known(&mut self, worker: WorkerId, now: Millis) -> Result<(), SchedError> {
        if self.touch(worker, now) {
            Ok(())
        } else {
            Err(SchedError::UnknownWorker(worker))
        }
    }

    /// The job `worker` gets its next tile of: among the ready jobs of the highest
    /// priority, one it served recently (it holds that scene: switching costs it nothing),
    /// else the oldest. Affinity never idles a worker and never passes a higher priority.
    fn pick_job(&self, worker: &Worker) -> Option<JobId> {
        let mut ready = (self.order.iter())
            .filter(|&&(_, _, job)| !worker.blocked.contains(&job) && self.jobs[&job].ready() > 0);
        let &(top, _, first) = ready.next()?;
        if worker.served.contains(&first) {
            return Some(first);
        }
        let held = ready
            .take_while(|&&(priority, _, _)| priority == top)
            .find(|&&(_, _, job)| worker.served.contains(&job));
        Some(held.map_or(first, |&(_, _, job)| job))
    }

    fn issue(&mut self, worker: WorkerId, job: JobId, now: Millis) -> Lease {
        let id = LeaseId(self.next_lease_id);
        self.next_lease_id += 1;
        let deadline = now + self.config.lease_timeout;
        let units = self.jobs.get_mut(&job).map(|record| &mut record.units);
        let unit = units.and_then(|units| units.iter_mut().find(|unit| unit.ready() > 0));
        let unit = unit.expect("a job with ready tiles has a unit with ready tiles");
        let tile = unit.take_ready().expect("the picked job has a ready tile");
        let slot = &mut unit.tiles[tile as usize];
        slot.state = TileState::Leased(id);
        let attempt = slot.failures + 1;
        unit.live.insert(id);
        unit.issued.push(id);
        let key = TaskKey {
            job,
            unit: unit.number,
            tile,
        };
        let state = LeaseState::Live { deadline };
        let last_deadline = now
            + self
                .config
                .max_lease_lifetime
                .max(self.config.lease_timeout);
        let rec = LeaseRec {
            key,
            worker,
            state,
            last_deadline,
        };
        self.leases.insert(id, rec);
        self.deadlines.insert((deadline, id));
        self.workers
            .get_mut(&worker)
            .expect("registered")
            .held
            .insert(id);
        Lease {
            id,
            key,
            deadline,
            attempt,
        }
    }

    /// Ok if `worker` validly holds `id` at `now`; otherwise the rejection, most specific
    /// first: ownership, then the job, then the lease's own fate.
    fn check(&self, worker: WorkerId, id: LeaseId, now: Millis) -> Result<(), Rejection> {
        let rec = self.leases.get(&id).ok_or(Rejection::UnknownLease)?;
        if rec.worker != worker {
            return Err(Rejection::WrongWorker);
        }
        let job = &self.jobs[&rec.key.job];
        if !job.is_active() {
            return Err(Rejection::JobGone);
        }
        match rec.state {
            LeaseState::Live { deadline } if now < deadline => Ok(()),
            LeaseState::Live { .. } => Err(Rejection::Expired),
            LeaseState::Ended(Ending::Completed) => Err(Rejection::Duplicate),
            LeaseState::Ended(Ending::Cancelled) => Err(Rejection::JobGone),
            LeaseState::Ended(Ending::Reclaimed) => {
                let unit = job.unit(rec.key.unit).expect("a record's unit is offered");
                match unit.tiles[rec.key.tile as usize].state {
                    TileState::Ready => Err(Rejection::Expired),
                    TileState::Leased(_) | TileState::Done => Err(Rejection::Superseded),
                }
            }
        }
    }

    /// Heartbeat for one lease: true if it was valid and now lives `lease_timeout` longer.
    fn extend(&mut self, worker: WorkerId, id: LeaseId, now: Millis) -> bool {
        if self.check(worker, id, now).is_err() {
            return false;
        }
        let rec = self.leases.get_mut(&id).expect("checked");
        let LeaseState::Live { deadline } = &mut rec.state else {
            unreachable!("checked live")
        };
        // Never shorten (tolerates a driver clock that steps back a little), never past
        // the lease's lifetime.
        let wanted = (now + self.config.lease_timeout).min(rec.last_deadline);
        let extended = (*deadline).max(wanted);
        self.deadlines.remove(&(*deadline, id));
        self.deadlines.insert((extended, id));
        *deadline = extended;
        true
    }

    /// Ends a live lease: detaches it from its worker, the deadline index and its unit, and
    /// moves its tile to the state `ending` implies. None if it was not live.
    fn end_lease(&mut self, id: LeaseId, ending: Ending) -> Option<(TaskKey, WorkerId)> {
        let rec = self.leases.get_mut(&id)?;
        let LeaseState::Live { deadline } = rec.state else {
            return None;
        };
        rec.state = LeaseState::Ended(ending);
        let (key, worker) = (rec.key, rec.worker);
        self.deadlines.remove(&(deadline, id));
        if let Some(record) = self.workers.get_mut(&worker) {
            record.held.remove(&id);
        }
        let unit = unit_of(&mut self.jobs, key);
        unit.live.remove(&id);
        let tile = &mut unit.tiles[key.tile as usize];
        debug_assert_eq!(tile.state, TileState::Leased(id));
        tile.state = match ending {
            Ending::Completed => {
                unit.remaining -= 1;
                TileState::Done
            }
            Ending::Reclaimed => {
                unit.returned.insert(key.tile);
                TileState::Ready
            }
            // The job is over: nothing will lease the tile again.
            Ending::Cancelled => TileState::Ready,
        };
        Some((key, worker))
    }

    /// Takes a live lease back and queues its tile again. A `failure` counts an attempt; if
    /// that exhausts the tile, the reason is returned for [`Scheduler::settle`], which runs
    /// after the whole batch so every lease of a batch is treated alike.
    fn reclaim(&mut self, id: LeaseId, failure: Option<Failure>) -> Option<FailureReason> {
        let (key, _) = self.end_lease(id, Ending::Reclaimed)?;
        let failure = failure?;
        let tile = &mut unit_of(&mut self.jobs, key).tiles[key.tile as usize];
        tile.failures += 1;
        let attempts = tile.failures;
        (attempts >= self.config.max_attempts).then_some(FailureReason {
            key,
            attempts,
            last: failure,
        })
    }

    /// Forgets a worker and reclaims all its leases (each a counted failure).
    fn lose(&mut self, worker: WorkerId, events: &mut Vec<Event>) -> Vec<FailureReason> {
        let Some(record) = self.workers.remove(&worker) else {
            return Vec::new();
        };
        let mut returned = Vec::new();
        let mut exhausted = Vec::new();
        for id in record.held {
            returned.push(self.leases[&id].key);
            exhausted.extend(self.reclaim(id, Some(Failure::WorkerLost { worker, lease: id })));
        }
        events.push(Event::WorkerLost { worker, returned });
        exhausted
    }

    /// Fails the job of each exhausted tile (the first reason per job wins).
    fn settle(&mut self, exhausted: impl IntoIterator<Item = FailureReason>, out: &mut Vec<Event>) {
        for reason in exhausted {
            let job = reason.key.job;
            let Some(record) = self.jobs.get_mut(&job).filter(|record| record.is_active()) else {
                continue;
            };
            record.state = JobState::Failed(reason.clone());
            out.push(Event::JobFailed { job, reason });
            for (worker, lease, key) in self.cancel_live(job) {
                out.push(Event::CancelLease { worker, lease, key });
            }
        }
    }

    /// Ends every live lease of the job as cancelled.
    fn cancel_live(&mut self, job: JobId) -> Vec<(WorkerId, LeaseId, TaskKey)> {
        let units = self
            .jobs
            .get(&job)
            .map_or(&[][..], |record| &record.units[..]);
        let ids: Vec<LeaseId> = units
            .iter()
            .flat_map(|unit| unit.live.iter().copied())
            .collect();
        let ended = ids.into_iter().filter_map(|id| {
            let (key, worker) = self.end_lease(id, Ending::Cancelled)?;
            Some((worker, id, key))
        });
        ended.collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const J1: JobId = JobId(1);
    const J2: JobId = JobId(2);
    const J3: JobId = JobId(3);
    const W1: WorkerId = WorkerId(1);
    const W2: WorkerId = WorkerId(2);
    const W3: WorkerId = WorkerId(3);

    fn secs(s: u64) -> Millis {
        Millis(s * 1000)
    }

    /// A scheduler with `workers` registered at t = 0 and job 1 (priority 0) offering unit 0.
    fn with_job(config: SchedulerConfig, workers: &[WorkerId], tiles: u32) -> Scheduler {
        let mut s = Scheduler::new(config);
        for &w in workers {
            s.register_worker(w, 8, Millis(0)).unwrap();
        }
        s.add_job(J1, 0, Millis(0)).unwrap();
        s.offer_unit(J1, 0, tiles).unwrap();
        s
    }

    /// A one-tile job whose tile may be tried only once, leased to W1 at t = 0: whatever
    /// ends that lease badly fails the job.
    fn single_attempt_lease() -> (Scheduler, Lease) {
        let config = SchedulerConfig {
            max_attempts: 1,
            ..SchedulerConfig::default()
        };
        let mut s = with_job(config, &[W1], 1);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        (s, a)
    }

    fn setup(workers: &[WorkerId], tiles: u32) -> Scheduler {
        with_job(SchedulerConfig::default(), workers, tiles)
    }

    fn wide() -> SchedulerConfig {
        SchedulerConfig {
            leases_per_worker: 100,
            ..SchedulerConfig::default()
        }
    }

    /// Heartbeats listing no lease every 10 s up to `until`: workers stay alive, leases are
    /// not extended.
    fn keep_alive(s: &mut Scheduler, workers: &[WorkerId], from: u64, until: u64) {
        for t in (from..=until).step_by(10) {
            for &w in workers {
                s.heartbeat(w, &[], secs(t)).unwrap();
            }
        }
    }

    fn key(job: JobId, unit: u64, tile: u32) -> TaskKey {
        TaskKey { job, unit, tile }
    }

    #[test]
    fn expired_lease_is_requeued_and_counts_an_attempt() {
        let mut s = setup(&[W1, W2], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        assert_eq!((a.key, a.attempt, a.deadline), (key(J1, 0, 0), 1, secs(60)));
        keep_alive(&mut s, &[W1, W2], 10, 60);
        assert_eq!(s.tick(Millis(59_999)), vec![]);
        let expired = Event::LeaseExpired {
            worker: W1,
            lease: a.id,
            key: a.key,
        };
        assert_eq!(s.tick(secs(60)), vec![expired]);
        assert_eq!((s.in_flight(J1), s.ready(J1)), (0, 2));
        let b = s.next_lease(W2, secs(60)).unwrap();
        assert_eq!((b.key, b.attempt), (a.key, 2));
        assert!(b.id > a.id);
    }

    #[test]
    fn stale_completion_after_expiry_is_rejected() {
        let mut s = setup(&[W1], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        keep_alive(&mut s, &[W1], 10, 60);
        assert_eq!(s.tick(secs(60)).len(), 1);
        assert_eq!(s.complete(W1, a.id, secs(61)), Err(Rejection::Expired));
        assert_eq!(s.job_info(J1).unwrap().unit.unwrap().done, 0);
        assert_eq!(s.ready(J1), 2);
    }

    #[test]
    fn completion_past_the_deadline_is_rejected_even_before_tick_reclaims_it() {
        let mut s = setup(&[W1], 1);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        keep_alive(&mut s, &[W1], 10, 60);
        assert_eq!(s.complete(W1, a.id, secs(60)), Err(Rejection::Expired));
        // Nor does a heartbeat revive it.
        assert_eq!(s.heartbeat(W1, &[a.id], secs(60)).unwrap(), vec![a.id]);
        let expired = Event::LeaseExpired {
            worker: W1,
            lease: a.id,
            key: a.key,
        };
        assert_eq!(s.tick(secs(60)), vec![expired]);
        assert_eq!(s.next_lease(W1, secs(60)).unwrap().attempt, 2);
    }

    #[test]
    fn completion_from_superseded_lease_is_rejected() {
        let mut s = setup(&[W1, W2], 1);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        keep_alive(&mut s, &[W1, W2], 10, 60);
        s.tick(secs(60));
        let b = s.next_lease(W2, secs(60)).unwrap();
        assert_eq!(b.key, a.key);
        assert_eq!(s.complete(W1, a.id, secs(61)), Err(Rejection::Superseded));
        let done = s.complete(W2, b.id, secs(62)).unwrap();
        assert_eq!(
            done,
            Completion {
                key: a.key,
                unit_done: true
            }
        );
        assert_eq!(s.complete(W1, a.id, secs(63)), Err(Rejection::Superseded));
        assert_eq!(s.worker_info(W2).unwrap().tiles_done, 1);
        assert_eq!(s.worker_info(W1).unwrap().tiles_done, 0);
    }

    #[test]
    fn attempts_exhausted_fails_the_job_with_the_tile_in_the_reason() {
        let config = SchedulerConfig {
            max_attempts: 2,
            ..SchedulerConfig::default()
        };
        let mut s = with_job(config, &[W1, W2], 3);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W2, Millis(0)).unwrap();
        assert_eq!(s.fail_lease(W1, a.id, "out of memory", secs(1)), Ok(vec![]));
        let a2 = s.next_lease(W1, secs(1)).unwrap();
        assert_eq!((a2.key, a2.attempt), (a.key, 2));
        let events = s
            .fail_lease(W1, a2.id, "out of memory again", secs(2))
            .unwrap();
        let last = Failure::Reported {
            worker: W1,
            lease: a2.id,
            message: "out of memory again".into(),
        };
        let reason = FailureReason {
            key: a.key,
            attempts: 2,
            last,
        };
        let text = reason.to_string();
        assert!(text.contains("tile 0 of unit 0 of job 1"), "{text}");
        assert!(text.contains("out of memory again"), "{text}");
        let cancel = Event::CancelLease {
            worker: W2,
            lease: b.id,
            key: b.key,
        };
        assert_eq!(
            events,
            vec![
                Event::JobFailed {
                    job: J1,
                    reason: reason.clone()
                },
                cancel
            ]
        );
        assert_eq!(s.job_info(J1).unwrap().state, JobState::Failed(reason));
        assert_eq!(s.complete(W2, b.id, secs(3)), Err(Rejection::JobGone));
        assert_eq!(s.next_lease(W1, secs(3)), None);
        assert_eq!((s.ready(J1), s.in_flight(J1)), (0, 0));
        assert_eq!(s.offer_unit(J1, 1, 3), Err(SchedError::JobNotActive(J1)));
    }

    #[test]
    fn expiries_count_towards_the_attempt_limit_and_tick_reports_the_failure() {
        let (mut s, a) = single_attempt_lease();
        keep_alive(&mut s, &[W1], 10, 60);
        let events = s.tick(secs(60));
        let last = Failure::Expired {
            worker: W1,
            lease: a.id,
        };
        let reason = FailureReason {
            key: a.key,
            attempts: 1,
            last,
        };
        let expired = Event::LeaseExpired {
            worker: W1,
            lease: a.id,
            key: a.key,
        };
        assert_eq!(events, vec![expired, Event::JobFailed { job: J1, reason }]);
    }

    #[test]
    fn lost_worker_returns_its_leases() {
        let mut s = with_job(wide(), &[W1, W2], 4);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W1, Millis(0)).unwrap();
        let c = s.next_lease(W2, Millis(0)).unwrap();
        let events = s.worker_lost(W1).unwrap();
        let returned = vec![a.key, b.key];
        assert_eq!(
            events,
            vec![Event::WorkerLost {
                worker: W1,
                returned
            }]
        );
        assert_eq!(s.worker_info(W1), None);
        assert_eq!(s.worker_lost(W1), Err(SchedError::UnknownWorker(W1)));
        assert_eq!(s.complete(W1, b.id, secs(1)), Err(Rejection::Expired));
        // Returned tiles go first (before untouched tile 3), with an attempt counted.
        let got: Vec<(u32, u32)> = (0..3)
            .map(|_| s.next_lease(W2, secs(1)).unwrap())
            .map(|lease| (lease.key.tile, lease.attempt))
            .collect();
        assert_eq!(got, vec![(0, 2), (1, 2), (3, 1)]);
        assert_eq!(s.complete(W1, a.id, secs(2)), Err(Rejection::Superseded));
        assert!(s.complete(W2, c.id, secs(2)).is_ok());
    }

    #[test]
    fn silent_worker_is_declared_lost_after_heartbeat_timeout() {
        let mut s = setup(&[W1, W2], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        s.heartbeat(W2, &[], secs(10)).unwrap();
        assert_eq!(s.next_deadline(), Some(secs(15)));
        assert_eq!(s.tick(Millis(14_999)), vec![]);
        let lost = Event::WorkerLost {
            worker: W1,
            returned: vec![a.key],
        };
        assert_eq!(s.tick(secs(15)), vec![lost]);
        assert_eq!(s.next_lease(W1, secs(15)), None);
        assert_eq!(
            s.heartbeat(W1, &[a.id], secs(15)),
            Err(SchedError::UnknownWorker(W1))
        );
        assert_eq!(s.next_lease(W2, secs(15)).unwrap().attempt, 2);
    }

    #[test]
    fn offering_leases_is_no_sign_of_life() {
        // A worker that asked for work and then fell silent (stopped, partitioned) is lost
        // after the heartbeat timeout even though the driver kept offering it leases.
        let mut s = setup(&[W1], 4);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W1, secs(14)).unwrap();
        let lost = Event::WorkerLost {
            worker: W1,
            returned: vec![a.key, b.key],
        };
        assert_eq!(s.tick(secs(15)), vec![lost]);
    }

    #[test]
    fn heartbeats_extend_a_lease_only_within_its_lifetime() {
        let config = SchedulerConfig {
            max_lease_lifetime: Duration::from_secs(100),
            ..SchedulerConfig::default()
        };
        let mut s = with_job(config, &[W1, W2], 1);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        for t in (10..=90).step_by(10) {
            assert_eq!(s.heartbeat(W1, &[a.id], secs(t)).unwrap(), vec![]);
            s.heartbeat(W2, &[], secs(t)).unwrap();
        }
        // listed every 10 s, it still ends at issue + 100 s, and the tile goes to W2
        assert_eq!(s.tick(Millis(99_999)), vec![]);
        let events = s.tick(secs(100));
        assert!(
            matches!(events[..], [Event::LeaseExpired { lease, .. }] if lease == a.id),
            "{events:?}"
        );
        s.heartbeat(W1, &[], secs(100)).unwrap();
        let again = s.next_lease(W2, secs(100)).unwrap();
        assert_eq!((again.key, again.attempt), (a.key, 2));
    }

    #[test]
    fn a_blocked_worker_gets_no_leases_of_the_job_and_returns_those_it_holds() {
        let mut s = with_job(wide(), &[W1, W2], 3);
        s.add_job(J2, 0, Millis(1)).unwrap();
        s.offer_unit(J2, 0, 1).unwrap();
        let a = s.next_lease(W1, Millis(0)).unwrap();
        assert_eq!(a.key.job, J1);
        assert_eq!(s.block(W1, J1), Ok(vec![a.id]));
        assert!(s.is_blocked(W1, J1) && !s.is_blocked(W2, J1));
        assert_eq!(s.complete(W1, a.id, Millis(1)), Err(Rejection::Expired));
        // W1 now gets J2's tile although J1 comes first; J1's returned tile goes to W2
        // without an attempt counted.
        assert_eq!(s.next_lease(W1, Millis(2)).unwrap().key.job, J2);
        assert_eq!(s.next_lease(W1, Millis(2)), None);
        let b = s.next_lease(W2, Millis(2)).unwrap();
        assert_eq!((b.key, b.attempt), (a.key, 1));
    }

    #[test]
    fn check_all_answers_as_complete_all_and_changes_nothing() {
        let mut s = setup(&[W1, W2], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W1, Millis(0)).unwrap();
        assert_eq!(
            s.check_all(W2, &[a.id], Millis(1)),
            Err(Rejection::WrongWorker)
        );
        assert_eq!(s.check_all(W1, &[a.id, b.id], Millis(1)), Ok(()));
        assert!(s.lease(a.id).unwrap().live && s.lease(b.id).unwrap().live);
        assert_eq!(s.held_by(W1), vec![a.id, b.id]);
        s.complete_all(W1, &[a.id, b.id], Millis(1)).unwrap();
        assert_eq!(
            s.check_all(W1, &[a.id, b.id], Millis(2)),
            Err(Rejection::Duplicate)
        );
        assert!(!s.lease(a.id).unwrap().live);
        assert_eq!(s.held_by(W1), vec![]);
    }

    #[test]
    fn any_message_from_a_worker_counts_as_a_sign_of_life() {
        let mut s = setup(&[W1], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        s.complete(W1, a.id, secs(10)).unwrap();
        assert_eq!(s.worker_info(W1).unwrap().last_seen, secs(10));
        assert_eq!(s.tick(secs(24)), vec![]);
        assert_eq!(s.tick(secs(25)).len(), 1);
    }

    #[test]
    fn heartbeat_extends_lease_deadlines() {
        let mut s = setup(&[W1], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W1, Millis(0)).unwrap();
        for t in (10..=100).step_by(10) {
            assert_eq!(s.heartbeat(W1, &[a.id], secs(t)).unwrap(), vec![]);
        }
        // b was never listed: it expires at its original deadline; a lives until 160 s.
        let events = s.tick(secs(100));
        assert_eq!(
            events,
            vec![Event::LeaseExpired {
                worker: W1,
                lease: b.id,
                key: b.key
            }]
        );
        assert_eq!(s.next_deadline(), Some(secs(115)));
        let done = s.complete(W1, a.id, secs(100)).unwrap();
        assert_eq!(
            done,
            Completion {
                key: a.key,
                unit_done: false
            }
        );
    }

    #[test]
    fn heartbeat_that_omits_a_lease_does_not_return_it() {
        let mut s = setup(&[W1, W2], 1);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        keep_alive(&mut s, &[W1, W2], 10, 50);
        assert_eq!(s.tick(secs(50)), vec![]);
        assert_eq!((s.in_flight(J1), s.ready(J1)), (1, 0));
        assert_eq!(s.next_lease(W2, secs(50)), None);
        assert!(s.complete(W1, a.id, secs(59)).unwrap().unit_done);
    }

    #[test]
    fn heartbeat_reports_leases_the_worker_does_not_validly_hold() {
        let mut s = setup(&[W1, W2], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W2, Millis(0)).unwrap();
        s.complete(W2, b.id, secs(1)).unwrap();
        let stale = s
            .heartbeat(W1, &[a.id, b.id, LeaseId(99)], secs(2))
            .unwrap();
        assert_eq!(stale, vec![b.id, LeaseId(99)]);
    }

    #[test]
    fn heartbeat_from_another_worker_does_not_extend_a_lease() {
        let mut s = setup(&[W1, W2], 1);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        for t in (10..=60).step_by(10) {
            s.heartbeat(W1, &[], secs(t)).unwrap();
            assert_eq!(s.heartbeat(W2, &[a.id], secs(t)).unwrap(), vec![a.id]);
        }
        assert_eq!(s.tick(secs(60)).len(), 1);
    }

    #[test]
    fn completion_from_another_worker_is_rejected() {
        let mut s = setup(&[W1, W2], 1);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        assert_eq!(s.complete(W2, a.id, secs(1)), Err(Rejection::WrongWorker));
        assert_eq!(
            s.fail_lease(W2, a.id, "x", secs(1)),
            Err(Rejection::WrongWorker)
        );
        assert!(s.complete(W1, a.id, secs(2)).is_ok());
    }

    #[test]
    fn unknown_lease_is_rejected() {
        let mut s = setup(&[W1], 1);
        assert_eq!(
            s.complete(W1, LeaseId(7), secs(1)),
            Err(Rejection::UnknownLease)
        );
        assert_eq!(
            s.fail_lease(W1, LeaseId(7), "x", secs(1)),
            Err(Rejection::UnknownLease)
        );
    }

    #[test]
    fn higher_priority_job_is_leased_first_then_arrival() {
        let mut s = Scheduler::new(wide());
        s.register_worker(W1, 8, Millis(0)).unwrap();
        for (job, priority, t) in [(J1, 0, 0), (J2, 5, 1), (J3, 5, 2)] {
            s.add_job(job, priority, secs(t)).unwrap();
            s.offer_unit(job, 0, 2).unwrap();
        }
        let order: Vec<(u64, u32)> = (0..6)
            .map(|_| s.next_lease(W1, secs(3)).unwrap().key)
            .map(|key| (key.job.0, key.tile))
            .collect();
        assert_eq!(order, vec![(2, 0), (2, 1), (3, 0), (3, 1), (1, 0), (1, 1)]);
        let listed: Vec<JobId> = s.jobs().iter().map(|info| info.job).collect();
        assert_eq!(listed, vec![J2, J3, J1]);
    }

    #[test]
    fn a_changed_priority_moves_the_job_for_the_next_leases() {
        let mut s = Scheduler::new(wide());
        s.register_worker(W1, 8, Millis(0)).unwrap();
        for (job, priority, t) in [(J1, 0, 0), (J2, 5, 1)] {
            s.add_job(job, priority, secs(t)).unwrap();
            s.offer_unit(job, 0, 2).unwrap();
        }
        assert_eq!(s.next_lease(W1, secs(3)).unwrap().key.job, J2);
        s.set_priority(J1, 9).unwrap();
        let next: Vec<JobId> = (0..3)
            .map(|_| s.next_lease(W1, secs(3)).unwrap().key.job)
            .collect();
        assert_eq!(next, vec![J1, J1, J2], "J1 first once raised above J2");
        let listed: Vec<JobId> = s.jobs().iter().map(|info| info.job).collect();
        assert_eq!(listed, vec![J1, J2]);
        assert_eq!(
            s.set_priority(JobId(77), 1),
            Err(SchedError::UnknownJob(JobId(77)))
        );
    }

    /// Affinity: among ready jobs of the highest priority a worker keeps to one it served
    /// (it holds the scene), a worker that served none of them takes the oldest, and a
    /// higher priority comes first whatever a worker served.
    #[test]
    fn a_worker_keeps_to_the_ready_job_it_served_among_equal_priorities() {
        let mut s = Scheduler::new(wide());
        for w in [W1, W2] {
            s.register_worker(w, 8, Millis(0)).unwrap();
        }
        s.add_job(J1, 0, secs(0)).unwrap();
        s.offer_unit(J1, 0, 1).unwrap();
        let job =
            |s: &mut Scheduler, w: WorkerId, t: u64| s.next_lease(w, secs(t)).unwrap().key.job;
        assert_eq!(job(&mut s, W1, 1), J1);
        s.add_job(J2, 0, secs(1)).unwrap();
        s.offer_unit(J2, 0, 4).unwrap();
        assert_eq!(job(&mut s, W2, 2), J2, "the only ready job");
        s.offer_unit(J1, 1, 4).unwrap();
        assert_eq!(job(&mut s, W2, 3), J2, "W2 holds J2's scene, not J1's");
        assert_eq!(job(&mut s, W1, 3), J1);
        s.register_worker(W3, 8, secs(3)).unwrap();
        assert_eq!(
            job(&mut s, W3, 3),
            J1,
            "a worker that served neither: the oldest"
        );
        s.add_job(J3, 5, secs(4)).unwrap();
        s.offer_unit(J3, 0, 4).unwrap();
        assert_eq!(job(&mut s, W2, 4), J3, "a higher priority first");
        assert_eq!(job(&mut s, W2, 4), J3, "and then kept to");
        let rest: Vec<JobId> = (0..6).map(|_| job(&mut s, W1, 5)).collect();
        assert_eq!(
            rest,
            vec![J3, J3, J1, J1, J2, J2],
            "priority, then served, then oldest"
        );
    }

    #[test]
    fn retried_tiles_go_before_untouched_tiles_lowest_first() {
        let mut s = with_job(wide(), &[W1], 5);
        let leases: Vec<Lease> = (0..3)
            .map(|_| s.next_lease(W1, Millis(0)).unwrap())
            .collect();
        s.fail_lease(W1, leases[2].id, "x", secs(1)).unwrap();
        s.fail_lease(W1, leases[0].id, "x", secs(1)).unwrap();
        let tiles: Vec<u32> = (0..4)
            .map(|_| s.next_lease(W1, secs(2)).unwrap().key.tile)
            .collect();
        assert_eq!(tiles, vec![0, 2, 3, 4]);
    }

    #[test]
    fn failed_lease_counts_an_attempt_and_requeues() {
        let mut s = setup(&[W1], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        assert_eq!(s.fail_lease(W1, a.id, "bad", secs(1)), Ok(vec![]));
        assert_eq!(
            s.fail_lease(W1, a.id, "bad", secs(1)),
            Err(Rejection::Expired)
        );
        assert_eq!(s.complete(W1, a.id, secs(1)), Err(Rejection::Expired));
        let b = s.next_lease(W1, secs(1)).unwrap();
        assert_eq!((b.key, b.attempt), (a.key, 2));
    }

    #[test]
    fn cancelled_job_rejects_completions_and_lists_leases_to_cancel() {
        let mut s = setup(&[W1, W2], 3);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W1, Millis(0)).unwrap();
        let c = s.next_lease(W2, Millis(0)).unwrap();
        let cancel = s.cancel_job(J1).unwrap();
        assert_eq!(cancel, vec![(W1, a.id), (W1, b.id), (W2, c.id)]);
        assert_eq!(s.complete(W1, a.id, secs(1)), Err(Rejection::JobGone));
        assert_eq!(s.next_lease(W2, secs(1)), None);
        assert_eq!(
            (s.in_flight(J1), s.ready(J1), s.in_flight_total()),
            (0, 0, 0)
        );
        assert_eq!(s.worker_info(W1).unwrap().leases_held, 0);
        assert_eq!(s.cancel_job(J1), Ok(vec![]));
        assert_eq!(s.job_info(J1).unwrap().state, JobState::Cancelled);
        assert_eq!(s.cancel_job(J2), Err(SchedError::UnknownJob(J2)));
    }

    #[test]
    fn removed_job_forgets_its_leases() {
        let mut s = setup(&[W1], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        assert_eq!(s.remove_job(J1), Ok(vec![(W1, a.id)]));
        assert_eq!(s.complete(W1, a.id, secs(1)), Err(Rejection::UnknownLease));
        assert_eq!(
            (s.job_info(J1), s.jobs().len(), s.in_flight_total()),
            (None, 0, 0)
        );
        // The rejected completion at 1 s was still a sign of life.
        assert_eq!(s.next_deadline(), Some(secs(16)));
        s.add_job(J1, 0, secs(2)).unwrap();
        s.offer_unit(J1, 0, 1).unwrap();
        assert!(s.next_lease(W1, secs(2)).unwrap().id > a.id);
    }

    #[test]
    fn draining_worker_gets_no_new_leases() {
        let mut s = setup(&[W1, W2], 3);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        s.drain_worker(W1).unwrap();
        assert_eq!(s.next_lease(W1, secs(1)), None);
        assert!(s.worker_info(W1).unwrap().draining);
        assert!(s.complete(W1, a.id, secs(2)).is_ok());
        assert_eq!(s.next_lease(W1, secs(2)), None);
        assert_eq!(s.next_lease(W2, secs(2)).unwrap().key.tile, 1);
        assert_eq!(
            s.worker_lost(W1),
            Ok(vec![Event::WorkerLost {
                worker: W1,
                returned: vec![]
            }])
        );
    }

    #[test]
    fn handed_back_lease_does_not_count_an_attempt() {
        let mut s = setup(&[W1, W2], 3);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W1, Millis(0)).unwrap();
        assert_eq!(
            s.hand_back(W1, &[a.id, LeaseId(42)], secs(1)),
            Ok(vec![a.key])
        );
        // Not W2's to hand back, and a is no longer held.
        assert_eq!(s.hand_back(W2, &[b.id], secs(1)), Ok(vec![]));
        assert_eq!(s.hand_back(W1, &[a.id], secs(1)), Ok(vec![]));
        let again = s.next_lease(W2, secs(1)).unwrap();
        assert_eq!((again.key, again.attempt), (a.key, 1));
        assert_eq!(s.complete(W1, a.id, secs(2)), Err(Rejection::Superseded));
        assert_eq!(
            s.hand_back(W3, &[b.id], secs(1)),
            Err(SchedError::UnknownWorker(W3))
        );
    }

    #[test]
    fn unit_done_is_reported_exactly_once() {
        let mut s = setup(&[W1], 2);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W1, Millis(0)).unwrap();
        assert!(!s.complete(W1, b.id, secs(1)).unwrap().unit_done);
        assert!(!s.unit_complete(J1, 0));
        assert_eq!(s.complete(W1, b.id, secs(1)), Err(Rejection::Duplicate));
        assert!(s.complete(W1, a.id, secs(2)).unwrap().unit_done);
        assert_eq!(s.complete(W1, a.id, secs(2)), Err(Rejection::Duplicate));
        assert!(s.unit_complete(J1, 0));
        s.offer_unit(J1, 1, 1).unwrap();
        assert!(!s.unit_complete(J1, 0));
        // The previous unit's records are gone with it.
        assert_eq!(s.complete(W1, a.id, secs(3)), Err(Rejection::UnknownLease));
        let c = s.next_lease(W1, secs(3)).unwrap();
        assert_eq!(c.key, key(J1, 1, 0));
        assert!(s.complete(W1, c.id, secs(4)).unwrap().unit_done);
    }

    #[test]
    fn joint_completion_accepts_all_or_none() {
        let mut s = setup(&[W1, W2], 4);
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W1, Millis(0)).unwrap();
        let c = s.next_lease(W2, Millis(0)).unwrap();
        let d = s.next_lease(W1, Millis(0)).unwrap();
        // One lease of another worker spoils the upload: nothing is accepted.
        assert_eq!(
            s.complete_all(W1, &[a.id, c.id], secs(1)),
            Err(Rejection::WrongWorker)
        );
        assert_eq!((s.in_flight(J1), s.ready(J1)), (4, 0));
        // A lease named twice is not a lease of this upload.
        assert_eq!(
            s.complete_all(W1, &[a.id, a.id], secs(1)),
            Err(Rejection::UnknownLease)
        );
        assert_eq!(s.in_flight(J1), 4);
        let done = s.complete_all(W1, &[b.id, a.id], secs(2)).unwrap();
        let keys: Vec<_> = done.iter().map(|c| (c.key, c.unit_done)).collect();
        assert_eq!(keys, vec![(b.key, false), (a.key, false)]);
        assert_eq!(
            s.complete_all(W1, &[a.id, b.id], secs(3)),
            Err(Rejection::Duplicate)
        );
        // Accepted leases with a live one are not a retry: rejected whole.
        assert_eq!(
            s.complete_all(W1, &[a.id, d.id], secs(3)),
            Err(Rejection::Superseded)
        );
        assert!(!s.complete(W2, c.id, secs(4)).unwrap().unit_done);
        let last = s.complete_all(W1, &[d.id], secs(5)).unwrap();
        assert!(last[0].unit_done);
        assert!(s.unit_complete(J1, 0));
    }

    #[test]
    fn offer_unit_takes_units_in_order_with_at_most_two_incomplete() {
        let mut s = setup(&[W1], 1);
        assert_eq!(
            s.offer_unit(J1, 1, 1),
            Ok(()),
            "a second unit overlaps the first"
        );
        let unit0 = SchedError::UnitInProgress { job: J1, unit: 0 };
        assert_eq!(s.offer_unit(J1, 2, 1), Err(unit0));
        let a = s.next_lease(W1, Millis(0)).unwrap();
        s.complete(W1, a.id, secs(1)).unwrap();
        let out_of_order = SchedError::UnitOutOfOrder {
            job: J1,
            unit: 1,
            last: 1,
        };
        assert_eq!(s.offer_unit(J1, 1, 1), Err(out_of_order));
        assert_eq!(
            s.offer_unit(J1, 2, 0),
            Err(SchedError::EmptyUnit { job: J1, unit: 2 })
        );
        assert_eq!(s.offer_unit(J2, 0, 1), Err(SchedError::UnknownJob(J2)));
        assert_eq!(s.add_job(J1, 0, secs(1)), Err(SchedError::DuplicateJob(J1)));
        assert_eq!(
            s.register_worker(W1, 1, secs(1)),
            Err(SchedError::DuplicateWorker(W1))
        );
        assert_eq!(s.offer_unit(J1, 7, 3), Ok(()));
        assert_eq!(s.ready(J1), 4, "unit 1's tile and unit 7's three");
    }

    #[test]
    fn overlapping_units_lease_the_older_units_tiles_first_and_complete_apart() {
        let mut s = setup(&[W1, W2], 2);
        s.offer_unit(J1, 1, 1).unwrap();
        let leases: Vec<Lease> = (0..3)
            .map(|i| s.next_lease([W1, W2][i % 2], Millis(0)).unwrap())
            .collect();
        let keys: Vec<(u64, u32)> = leases.iter().map(|l| (l.key.unit, l.key.tile)).collect();
        assert_eq!(keys, [(0, 0), (0, 1), (1, 0)]);
        // the later unit is in first: only its completion says so
        let done = s.complete(W1, leases[2].id, secs(1)).unwrap();
        assert!(done.unit_done);
        assert!(s.unit_complete(J1, 1) && !s.unit_complete(J1, 0));
        assert!(!s.complete(W1, leases[0].id, secs(1)).unwrap().unit_done);
        // a lost worker's tile of the older unit goes back to the queue
        let events = s.worker_lost(W2).unwrap();
        assert!(matches!(&events[..], [Event::WorkerLost { returned, .. }] if returned.len() == 1));
        assert_eq!(s.job_info(J1).unwrap().unit.unwrap().unit, 0);
        let again = s.next_lease(W1, secs(2)).unwrap();
        assert_eq!((again.key.unit, again.key.tile), (0, 1));
        assert!(s.complete(W1, again.id, secs(2)).unwrap().unit_done);
        assert!(s.unit_complete(J1, 0));
        // both complete: the next offer drops their bookkeeping
        s.offer_unit(J1, 2, 1).unwrap();
        assert_eq!(
            s.complete(W1, leases[2].id, secs(3)),
            Err(Rejection::UnknownLease)
        );
    }

    #[test]
    fn worker_lease_limit_is_respected() {
        let limit = SchedulerConfig::default().leases_per_worker;
        let mut s = setup(&[W1], limit + 2);
        let limit = s.config().leases_per_worker;
        let a = s.next_lease(W1, Millis(0)).unwrap();
        for _ in 1..limit {
            s.next_lease(W1, Millis(0)).unwrap();
        }
        assert_eq!(s.next_lease(W1, Millis(0)), None);
        s.complete(W1, a.id, secs(1)).unwrap();
        assert_eq!(s.next_lease(W1, secs(1)).unwrap().key.tile, limit);
        assert_eq!(s.worker_info(W1).unwrap().leases_held, limit as usize);
    }

    #[test]
    fn lease_ids_increase_and_are_never_reused() {
        let mut s = setup(&[W1], 3);
        let mut ids = Vec::new();
        for round in 0..4 {
            let lease = s.next_lease(W1, secs(round)).unwrap();
            ids.push(lease.id);
            s.hand_back(W1, &[lease.id], secs(round)).unwrap();
        }
        assert!(ids.windows(2).all(|pair| pair[0] < pair[1]), "{ids:?}");
    }

    #[test]
    fn counts_track_leases_and_completions() {
        let mut s = with_job(wide(), &[W1, W2], 3);
        s.add_job(J2, 1, Millis(0)).unwrap();
        s.offer_unit(J2, 0, 2).unwrap();
        assert_eq!((s.ready_total(), s.in_flight_total()), (5, 0));
        let a = s.next_lease(W1, Millis(0)).unwrap();
        let b = s.next_lease(W2, Millis(0)).unwrap();
        let c = s.next_lease(W2, Millis(0)).unwrap();
        assert_eq!((a.key.job, b.key.job, c.key.job), (J2, J2, J1));
        assert_eq!(
            (s.ready(J1), s.ready(J2), s.in_flight(J1), s.in_flight(J2)),
            (2, 0, 1, 2)
        );
        s.complete(W2, b.id, secs(1)).unwrap();
        let w2 = s.worker_info(W2).unwrap();
        assert_eq!(
            (w2.threads, w2.leases_held, w2.tiles_done, w2.last_seen),
            (8, 1, 1, secs(1))
        );
        let progress = s.job_info(J2).unwrap().unit.unwrap();
        let expected = UnitProgress {
            unit: 0,
            tiles: 2,
            done: 1,
            in_flight: 1,
            ready: 0,
        };
        assert_eq!(progress, expected);
        assert_eq!(
            (s.ready_total(), s.in_flight_total(), s.workers().len()),
            (2, 2, 2)
        );
    }

    #[test]
    fn next_deadline_is_the_earliest_lease_deadline_or_worker_timeout() {
        let mut s = Scheduler::new(SchedulerConfig::default());
        assert_eq!(s.next_deadline(), None);
        s.register_worker(W1, 1, secs(100)).unwrap();
        assert_eq!(s.next_deadline(), Some(secs(115)));
        s.add_job(J1, 0, secs(100)).unwrap();
        s.offer_unit(J1, 0, 1).unwrap();
        let a = s.next_lease(W1, secs(100)).unwrap();
        s.heartbeat(W1, &[a.id], secs(150)).unwrap();
        assert_eq!(s.next_deadline(), Some(secs(165)));
        s.heartbeat(W1, &[], secs(200)).unwrap();
        assert_eq!(s.next_deadline(), Some(secs(210)));
    }

    #[test]
    fn failure_messages_are_truncated() {
        let (mut s, a) = single_attempt_lease();
        let events = s.fail_lease(W1, a.id, &"é".repeat(5000), secs(1)).unwrap();
        let Event::JobFailed { reason, .. } = &events[0] else {
            panic!("{events:?}")
        };
        let Failure::Reported { message, .. } = &reason.last else {
            panic!("{reason:?}")
        };
        assert!(
            message.len() <= MAX_MESSAGE_BYTES + '…'.len_utf8(),
            "{}",
            message.len()
        );
    }

    // ----- seeded random simulation -----
    //
    // A driver, a session per job and a population of workers around one scheduler. The
    // simulation keeps its own model of every lease (its deadline as heartbeats pushed it, how
    // it ended) and predicts each answer of the scheduler from that model: which tile a lease
    // request gets and at which attempt, whether a completion is accepted or why not, which
    // leases a lost worker returns, when a job runs out of attempts. Accepted results are kept
    // per (unit, tile) and folded in tile order when the unit is done; at the end every job
    // that was neither cancelled nor failed must equal a straight sequential run.

    use std::collections::HashMap;

    const LEASE_TIMEOUT: Duration = Duration::from_secs(60);
    const SLOTS: usize = 2;
    const MAX_STEPS: usize = 200_000;

    use pathfarm_testkit::TestRng;

    fn mix(mut z: u64) -> u64 {
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// The fake render: a deterministic function of the tile.
    fn render(key: TaskKey) -> u64 {
        mix(key.job.0 ^ mix(key.unit ^ mix(u64::from(key.tile) + 1)))
    }

    /// Order-dependent accumulation: swapping two results changes the total.
    fn fold(acc: u64, result: u64) -> u64 {
        mix(acc.rotate_left(5) ^ result)
    }

    #[derive(Clone, Copy, Debug, PartialEq)]
    enum End {
        Completed,
        Reclaimed,
        Cancelled,
    }

    struct SimLease {
        key: TaskKey,
        worker: WorkerId,
        deadline: Millis,
        done_at: Millis,
        /// False for a hung render: the worker's heartbeats leave it out.
        listed: bool,
        /// The worker will report a failure instead of a result.
        fails: bool,
        end: Option<End>,
    }

    #[derive(Clone, Copy, Debug, PartialEq)]
    enum Mode {
        Alive,
        Draining,
        /// Sends nothing; once declared lost a zombie still delivers its late results.
        Silent {
            zombie: bool,
        },
        Zombie,
        Gone,
    }

    struct SimWorker {
        id: WorkerId,
        mode: Mode,
        /// Leases the worker is rendering (it does not know which of them are void).
        pending: Vec<LeaseId>,
        /// Leases the model says are live.
        live: BTreeSet<LeaseId>,
        /// Leases it sent a result for, to send again.
        sent: Vec<LeaseId>,
        /// The jobs of its last leases, most recent last, at most [`AFFINITY_JOBS`].
        served: Vec<JobId>,
        next_heartbeat: Millis,
    }

    struct SimJob {
        id: JobId,
        priority: i32,
        arrive_at: Millis,
        seq: Option<u64>,
        units: Vec<u32>,
        offered: u64,
        finished: bool,
        removed: bool,
        cancelled: bool,
        failed: bool,
        // Per tile of the offered unit:
        accepted: Vec<Option<u64>>,
        holder: Vec<Option<LeaseId>>,
        leased_before: Vec<bool>,
        failures: Vec<u32>,
        acc: u64,
    }

    impl SimJob {
        fn gone(&self) -> bool {
            self.cancelled || self.failed
        }

        fn running(&self) -> bool {
            self.seq.is_some() && !self.finished && !self.gone()
        }

        fn start(&mut self, unit: u64) {
            let tiles = self.units[unit as usize] as usize;
            self.offered = unit;
            self.accepted = vec![None; tiles];
            self.holder = vec![None; tiles];
            self.leased_before = vec![false; tiles];
            self.failures = vec![0; tiles];
        }

        fn ready(&self) -> Vec<u32> {
            if !self.running() {
                return Vec::new();
            }
            let waiting = |&t: &usize| self.accepted[t].is_none() && self.holder[t].is_none();
            (0..self.accepted.len())
                .filter(waiting)
                .map(|t| t as u32)
                .collect()
        }

        fn key(&self, tile: u32) -> TaskKey {
            key(self.id, self.offered, tile)
        }

        fn sequential(&self) -> u64 {
            let tiles = (self.units.iter().enumerate())
                .flat_map(|(unit, &n)| (0..n).map(move |tile| (unit as u64, tile)));
            tiles.fold(0, |acc, (unit, tile)| {
                fold(acc, render(key(self.id, unit, tile)))
            })
        }
    }

    #[derive(Default, Debug)]
    struct Stats {
        completed: u64,
        failed: u64,
        cancelled: u64,
        accepted: u64,
        lost: u64,
        expired: u64,
        rejected: BTreeMap<Rejection, u64>,
    }

    impl Stats {
        fn add(&mut self, other: Stats) {
            self.completed += other.completed;
            self.failed += other.failed;
            self.cancelled += other.cancelled;
            self.accepted += other.accepted;
            self.lost += other.lost;
            self.expired += other.expired;
            for (rejection, n) in other.rejected {
                *self.rejected.entry(rejection).or_default() += n;
            }
        }

        fn rejected(&self, rejection: Rejection) -> u64 {
            self.rejected.get(&rejection).copied().unwrap_or(0)
        }
    }

    struct Sim {
        s: Scheduler,
        rng: TestRng,
        now: Millis,
        max_attempts: u32,
        fail_per_mille: u64,
        jobs: Vec<SimJob>,
        workers: Vec<SimWorker>,
        leases: BTreeMap<LeaseId, SimLease>,
        accepts: HashMap<TaskKey, u32>,
        last_lease: Option<LeaseId>,
        next_seq: u64,
        cancelled_one: bool,
        stats: Stats,
    }

    fn job_index(job: JobId) -> usize {
        job.0 as usize - 1
    }

    fn worker_index(worker: WorkerId) -> usize {
        worker.0 as usize - 1
    }

    fn sim_job(id: JobId, rng: &mut TestRng) -> SimJob {
        let priority = rng.below(3) as i32;
        let arrive_at = Millis(rng.below(120_000));
        let units = (0..rng.range(1, 4))
            .map(|_| rng.range(1, 10) as u32)
            .collect();
        let (offered, acc) = (0, 0);
        let (finished, removed, cancelled, failed) = (false, false, false, false);
        let (accepted, holder, leased_before, failures) = (vec![], vec![], vec![], vec![]);
        SimJob {
            id,
            priority,
            arrive_at,
            seq: None,
            units,
            offered,
            finished,
            removed,
            cancelled,
            failed,
            accepted,
            holder,
            leased_before,
            failures,
            acc,
        }
    }

    impl Sim {
        fn new(seed: u64, max_attempts: u32, fail_per_mille: u64) -> Sim {
            let mut rng = TestRng::new(seed);
            let jobs = (1..=8).map(|i| sim_job(JobId(i), &mut rng)).collect();
            let config = SchedulerConfig {
                lease_timeout: LEASE_TIMEOUT,
                heartbeat_timeout: Duration::from_secs(15),
                max_attempts,
                leases_per_worker: SLOTS as u32,
                max_lease_lifetime: Duration::from_secs(1 << 30),
            };
            Sim {
                s: Scheduler::new(config),
                rng,
                now: Millis(0),
                max_attempts,
                fail_per_mille,
                jobs,
                workers: Vec::new(),
                leases: BTreeMap::new(),
                accepts: HashMap::new(),
                last_lease: None,
                next_seq: 0,
                cancelled_one: false,
                stats: Stats::default(),
            }
        }

        fn run(mut self) -> Stats {
            for _ in 0..MAX_STEPS {
                if self
                    .jobs
                    .iter()
                    .all(|job| job.seq.is_some() && !job.running())
                {
                    self.final_checks();
                    return self.stats;
                }
                self.now = self.now + Duration::from_millis(self.rng.range(1, 1500));
                self.arrivals();
                self.population();
                self.maybe_cancel();
                // Not every step: completions past a deadline must be rejected before the
                // tick reclaims the lease too.
                if self.rng.chance(0.6) {
                    let events = self.s.tick(self.now);
                    self.apply(events);
                }
                for wi in 0..self.workers.len() {
                    self.act(wi);
                }
                self.check_counts();
            }
            panic!("the simulation did not finish in {MAX_STEPS} steps");
        }

        fn arrivals(&mut self) {
            for job in &mut self.jobs {
                if job.seq.is_some() || job.arrive_at > self.now {
                    continue;
                }
                self.s.add_job(job.id, job.priority, self.now).unwrap();
                self.s.offer_unit(job.id, 0, job.units[0]).unwrap();
                job.seq = Some(self.next_seq);
                self.next_seq += 1;
                job.start(0);
            }
        }

        fn population(&mut self) {
            let alive: Vec<usize> = (0..self.workers.len())
                .filter(|&wi| self.workers[wi].mode == Mode::Alive)
                .collect();
            if alive.is_empty() || (alive.len() < 6 && self.rng.chance(0.015)) {
                self.spawn();
            }
            if alive.is_empty() || !self.rng.chance(0.008) {
                return;
            }
            let wi = alive[self.rng.below(alive.len() as u64) as usize];
            let zombie = self.rng.chance(0.5);
            match self.rng.below(3) {
                0 => self.lose_explicitly(wi, zombie),
                1 => self.workers[wi].mode = Mode::Silent { zombie },
                _ => self.drain(wi),
            }
        }

        fn spawn(&mut self) {
            let id = WorkerId(self.workers.len() as u64 + 1);
            self.s
                .register_worker(id, self.rng.range(1, 16) as u32, self.now)
                .unwrap();
            let next_heartbeat = self.now + Duration::from_millis(self.rng.range(2000, 6000));
            let (pending, live, sent) = (Vec::new(), BTreeSet::new(), Vec::new());
            let mode = Mode::Alive;
            self.workers.push(SimWorker {
                id,
                mode,
                pending,
                live,
                sent,
                served: Vec::new(),
                next_heartbeat,
            });
        }

        /// The driver saw the worker's connection drop (or a drained worker leave).
        fn lose_explicitly(&mut self, wi: usize, zombie: bool) {
            self.workers[wi].mode = Mode::Silent { zombie };
            let events = self.s.worker_lost(self.workers[wi].id).unwrap();
            self.apply(events);
            assert!(matches!(self.workers[wi].mode, Mode::Zombie | Mode::Gone));
        }

        fn drain(&mut self, wi: usize) {
            let id = self.workers[wi].id;
            self.s.drain_worker(id).unwrap();
            self.workers[wi].mode = Mode::Draining;
            if self.rng.chance(0.5) {
                return;
            }
            let offered: Vec<LeaseId> = self.workers[wi].live.iter().copied().collect();
            let valid: Vec<LeaseId> = (offered.iter().copied())
                .filter(|l| self.leases[l].deadline > self.now)
                .collect();
            let keys = self.s.hand_back(id, &offered, self.now).unwrap();
            let expected: Vec<TaskKey> = valid.iter().map(|l| self.leases[l].key).collect();
            assert_eq!(keys, expected, "hand-back by {id}");
            for lease in valid {
                self.end(lease, End::Reclaimed);
                self.workers[wi].pending.retain(|&p| p != lease);
            }
        }

        fn maybe_cancel(&mut self) {
            if self.cancelled_one || !self.rng.chance(0.003) {
                return;
            }
            let running: Vec<usize> = (0..self.jobs.len())
                .filter(|&ji| self.jobs[ji].running())
                .collect();
            if running.is_empty() {
                return;
            }
            let ji = running[self.rng.below(running.len() as u64) as usize];
            let cancel = self.s.cancel_job(self.jobs[ji].id).unwrap();
            let held: BTreeSet<LeaseId> = self.jobs[ji].holder.iter().flatten().copied().collect();
            let expected: Vec<(WorkerId, LeaseId)> = held
                .into_iter()
                .map(|l| (self.leases[&l].worker, l))
                .collect();
            assert_eq!(cancel, expected);
            for (_, lease) in cancel {
                self.end(lease, End::Cancelled);
            }
            self.jobs[ji].cancelled = true;
            self.cancelled_one = true;
            self.stats.cancelled += 1;
        }

        fn act(&mut self, wi: usize) {
            match self.workers[wi].mode {
                Mode::Gone | Mode::Silent { .. } => {}
                Mode::Zombie => {
                    self.finish_due(wi);
                    if self.workers[wi].pending.is_empty() {
                        self.workers[wi].mode = Mode::Gone;
                    }
                }
                Mode::Alive | Mode::Draining => {
                    if self.now >= self.workers[wi].next_heartbeat {
                        self.heartbeat(wi);
                    }
                    self.finish_due(wi);
                    if self.rng.chance(0.03) {
                        self.resend(wi);
                    }
                    if self.workers[wi].mode == Mode::Alive {
                        self.request(wi);
                    } else if self.workers[wi].pending.is_empty() {
                        self.lose_explicitly(wi, false);
                    }
                }
            }
        }

        fn heartbeat(&mut self, wi: usize) {
            let w = &self.workers[wi];
            let listed: Vec<LeaseId> = w
                .pending
                .iter()
                .copied()
                .filter(|l| self.leases[l].listed)
                .collect();
            let void = |l: &LeaseId| {
                let lease = &self.leases[l];
                lease.end.is_some() || lease.deadline <= self.now
            };
            let expected: Vec<LeaseId> = listed.iter().copied().filter(void).collect();
            let stale = self.s.heartbeat(w.id, &listed, self.now).unwrap();
            assert_eq!(stale, expected, "heartbeat of {} at {}", w.id, self.now);
            let extended = self.now + LEASE_TIMEOUT;
            for l in listed.iter().filter(|l| !stale.contains(l)) {
                let lease = self.leases.get_mut(l).unwrap();
                lease.deadline = lease.deadline.max(extended);
            }
            // Half the time the worker abandons what it was told is void; otherwise its late
            // results must be rejected.
            if self.rng.chance(0.5) {
                self.workers[wi].pending.retain(|l| !stale.contains(l));
            }
            let interval = Duration::from_millis(self.rng.range(2000, 6000));
            self.workers[wi].next_heartbeat = self.now + interval;
        }

        fn finish_due(&mut self, wi: usize) {
            let now = self.now;
            let (due, rest): (Vec<LeaseId>, Vec<LeaseId>) = self.workers[wi]
                .pending
                .iter()
                .partition(|l| self.leases[l].done_at <= now);
            self.workers[wi].pending = rest;
            for lease in due {
                if self.leases[&lease].fails {
                    self.fail(wi, lease);
                } else {
                    self.complete(wi, lease);
                }
            }
        }

        /// The answer the scheduler must give to a result for `lease` now.
        fn expect(&self, lease: LeaseId) -> Result<(), Rejection> {
            let record = &self.leases[&lease];
            let (key, tile) = (record.key, record.key.tile as usize);
            let job = &self.jobs[job_index(key.job)];
            if job.removed || key.unit != job.offered {
                return Err(Rejection::UnknownLease);
            }
            if job.gone() {
                return Err(Rejection::JobGone);
            }
            match record.end {
                Some(End::Completed) => Err(Rejection::Duplicate),
                Some(End::Cancelled) => Err(Rejection::JobGone),
                Some(End::Reclaimed) if job.accepted[tile].is_some() => Err(Rejection::Superseded),
                Some(End::Reclaimed) if job.holder[tile].is_some() => Err(Rejection::Superseded),
                Some(End::Reclaimed) => Err(Rejection::Expired),
                None if self.now >= record.deadline => Err(Rejection::Expired),
                None => Ok(()),
            }
        }

        fn complete(&mut self, wi: usize, lease: LeaseId) {
            let worker = self.workers[wi].id;
            let expected = self.expect(lease);
            let got = self.s.complete(worker, lease, self.now);
            self.workers[wi].sent.push(lease);
            match (expected, got) {
                (Ok(()), Ok(completion)) => self.accept(lease, completion),
                (Err(e), Err(g)) if e == g => *self.stats.rejected.entry(g).or_default() += 1,
                (e, g) => panic!(
                    "result for {lease} at {}: expected {e:?}, got {g:?}",
                    self.now
                ),
            }
        }

        fn accept(&mut self, lease: LeaseId, completion: Completion) {
            let key = self.leases[&lease].key;
            assert_eq!(completion.key, key);
            self.end(lease, End::Completed);
            let job = &mut self.jobs[job_index(key.job)];
            let slot = &mut job.accepted[key.tile as usize];
            assert!(slot.is_none(), "{key} accepted twice");
            *slot = Some(render(key));
            *self.accepts.entry(key).or_default() += 1;
            self.stats.accepted += 1;
            let all = job.accepted.iter().all(Option::is_some);
            assert_eq!(completion.unit_done, all, "unit_done on {key}");
            if all {
                self.unit_done(job_index(key.job));
            }
        }

        /// The session folds the unit in tile order and offers the next one.
        fn unit_done(&mut self, ji: usize) {
            let job = &mut self.jobs[ji];
            assert!(self.s.unit_complete(job.id, job.offered));
            job.acc = job
                .accepted
                .iter()
                .flatten()
                .fold(job.acc, |acc, &r| fold(acc, r));
            let next = job.offered + 1;
            if let Some(&tiles) = job.units.get(next as usize) {
                self.s.offer_unit(job.id, next, tiles).unwrap();
                job.start(next);
                return;
            }
            job.finished = true;
            self.stats.completed += 1;
            if self.rng.chance(0.5) {
                assert_eq!(self.s.remove_job(job.id), Ok(vec![]));
                job.removed = true;
            }
        }

        fn fail(&mut self, wi: usize, lease: LeaseId) {
            let worker = self.workers[wi].id;
            let expected = self.expect(lease);
            let got = self
                .s
                .fail_lease(worker, lease, "simulated failure", self.now);
            match (expected, got) {
                (Ok(()), Ok(events)) => {
                    let key = self.leases[&lease].key;
                    self.end(lease, End::Reclaimed);
                    self.count_failure(key);
                    self.apply(events);
                }
                (Err(e), Err(g)) if e == g => *self.stats.rejected.entry(g).or_default() += 1,
                (e, g) => panic!(
                    "failure of {lease} at {}: expected {e:?}, got {g:?}",
                    self.now
                ),
            }
        }

        /// A retransmitted result: never accepted again.
        fn resend(&mut self, wi: usize) {
            let sent = &self.workers[wi].sent;
            if sent.is_empty() {
                return;
            }
            let lease = sent[self.rng.below(sent.len() as u64) as usize];
            let expected = self
                .expect(lease)
                .expect_err("a resent result is never valid");
            let got = self.s.complete(self.workers[wi].id, lease, self.now);
            assert_eq!(got, Err(expected), "resent result for {lease}");
            *self.stats.rejected.entry(expected).or_default() += 1;
        }

        fn request(&mut self, wi: usize) {
            let worker = self.workers[wi].id;
            loop {
                let expected = self.expected_pick(wi);
                let got = self.s.next_lease(worker, self.now);
                assert_eq!(
                    got.map(|l| l.key),
                    expected,
                    "lease for {worker} at {}",
                    self.now
                );
                let Some(lease) = got else { return };
                self.record_lease(wi, lease);
            }
        }

        /// Highest priority; among those, a job the worker served of its last
        /// [`AFFINITY_JOBS`], else arrival; returned tiles (lowest first) before fresh ones.
        fn expected_pick(&self, wi: usize) -> Option<TaskKey> {
            if self.workers[wi].live.len() >= SLOTS {
                return None;
            }
            let candidates = self.jobs.iter().filter(|job| !job.ready().is_empty());
            let served = &self.workers[wi].served;
            let job = candidates
                .min_by_key(|job| (Reverse(job.priority), !served.contains(&job.id), job.seq))?;
            let ready = job.ready();
            let retried = ready
                .iter()
                .copied()
                .find(|&t| job.leased_before[t as usize]);
            Some(job.key(retried.unwrap_or(ready[0])))
        }

        fn record_lease(&mut self, wi: usize, lease: Lease) {
            assert!(
                self.last_lease.is_none_or(|last| lease.id > last),
                "lease ids must increase"
            );
            self.last_lease = Some(lease.id);
            assert_eq!(lease.deadline, self.now + LEASE_TIMEOUT);
            let (key, tile) = (lease.key, lease.key.tile as usize);
            let served = &mut self.workers[wi].served;
            served.retain(|&j| j != key.job);
            served.push(key.job);
            if served.len() > AFFINITY_JOBS {
                served.remove(0);
            }
            let job = &mut self.jobs[job_index(key.job)];
            assert_eq!(lease.attempt, job.failures[tile] + 1, "attempt of {key}");
            job.holder[tile] = Some(lease.id);
            job.leased_before[tile] = true;
            let hung = self.rng.chance(0.05);
            let ms = if hung {
                self.rng.range(30_000, 120_000)
            } else {
                self.rng.range(500, 20_000)
            };
            let done_at = self.now + Duration::from_millis(ms);
            let fails = self.rng.chance(self.fail_per_mille as f64 / 1000.0);
            let (worker, deadline, listed, end) =
                (self.workers[wi].id, lease.deadline, !hung, None);
            let record = SimLease {
                key,
                worker,
                deadline,
                done_at,
                listed,
                fails,
                end,
            };
            self.leases.insert(lease.id, record);
            self.workers[wi].pending.push(lease.id);
            self.workers[wi].live.insert(lease.id);
        }

        /// The model's side of a lease ending.
        fn end(&mut self, lease: LeaseId, end: End) {
            let record = self.leases.get_mut(&lease).unwrap();
            assert_eq!(record.end, None, "{lease} ended twice");
            record.end = Some(end);
            let (key, worker) = (record.key, record.worker);
            let job = &mut self.jobs[job_index(key.job)];
            let tile = key.tile as usize;
            assert_eq!((job.offered, job.holder[tile]), (key.unit, Some(lease)));
            job.holder[tile] = None;
            assert!(self.workers[worker_index(worker)].live.remove(&lease));
        }

        fn count_failure(&mut self, key: TaskKey) {
            self.jobs[job_index(key.job)].failures[key.tile as usize] += 1;
        }

        fn apply(&mut self, events: Vec<Event>) {
            for event in events {
                match event {
                    Event::LeaseExpired { worker, lease, key } => self.expired(worker, lease, key),
                    Event::WorkerLost { worker, returned } => self.lost(worker, returned),
                    Event::JobFailed { job, reason } => self.job_failed(job, reason),
                    Event::CancelLease { worker, lease, key } => {
                        let record = &self.leases[&lease];
                        assert_eq!((record.worker, record.key), (worker, key));
                        assert!(self.jobs[job_index(key.job)].failed, "{lease} cancelled");
                        self.end(lease, End::Cancelled);
                    }
                }
            }
            // Exhaustion is reported in the batch that causes it; a failed job keeps no lease.
            for job in &self.jobs {
                if job.running() {
                    let within = job.failures.iter().all(|&f| f < self.max_attempts);
                    assert!(within, "{} should have failed", job.id);
                }
                if job.failed {
                    assert!(job.holder.iter().all(Option::is_none));
                }
            }
        }

        fn expired(&mut self, worker: WorkerId, lease: LeaseId, key: TaskKey) {
            let record = &self.leases[&lease];
            assert_eq!((record.worker, record.key), (worker, key));
            assert!(
                record.deadline <= self.now,
                "{lease} expired before {}",
                record.deadline
            );
            self.end(lease, End::Reclaimed);
            self.count_failure(key);
            self.stats.expired += 1;
        }

        fn lost(&mut self, worker: WorkerId, returned: Vec<TaskKey>) {
            let wi = worker_index(worker);
            let mode = self.workers[wi].mode;
            let Mode::Silent { zombie } = mode else {
                panic!("{worker} lost while {mode:?}")
            };
            let held: Vec<LeaseId> = self.workers[wi].live.iter().copied().collect();
            let expected: Vec<TaskKey> = held.iter().map(|l| self.leases[l].key).collect();
            assert_eq!(returned, expected, "leases returned by {worker}");
            for lease in held {
                let key = self.leases[&lease].key;
                self.end(lease, End::Reclaimed);
                self.count_failure(key);
            }
            self.workers[wi].mode = if zombie { Mode::Zombie } else { Mode::Gone };
            if !zombie {
                self.workers[wi].pending.clear();
            }
            self.stats.lost += 1;
        }

        fn job_failed(&mut self, id: JobId, reason: FailureReason) {
            let job = &mut self.jobs[job_index(id)];
            assert!(job.running(), "{id} failed while not running");
            let key = reason.key;
            assert_eq!((key.job, key.unit), (id, job.offered));
            assert_eq!(reason.attempts, job.failures[key.tile as usize]);
            assert_eq!(reason.attempts, self.max_attempts);
            assert!(reason.to_string().contains(&key.to_string()), "{reason}");
            job.failed = true;
            self.stats.failed += 1;
        }

        fn check_counts(&self) {
            for job in self
                .jobs
                .iter()
                .filter(|job| job.seq.is_some() && !job.removed)
            {
                let got = (self.s.in_flight(job.id), self.s.ready(job.id));
                let in_flight = job.holder.iter().flatten().count();
                assert_eq!(
                    got,
                    (in_flight, job.ready().len()),
                    "{} at {}",
                    job.id,
                    self.now
                );
            }
            for w in &self.workers {
                let info = self
                    .s
                    .worker_info(w.id)
                    .map(|i| (i.leases_held, i.draining));
                match w.mode {
                    Mode::Alive | Mode::Draining | Mode::Silent { .. } => {
                        assert_eq!(info, Some((w.live.len(), w.mode == Mode::Draining)));
                    }
                    Mode::Zombie | Mode::Gone => assert_eq!((info, w.live.len()), (None, 0)),
                }
            }
        }

        fn final_checks(&self) {
            for job in self.jobs.iter().filter(|job| !job.gone()) {
                assert!(job.finished);
                assert_eq!(
                    job.acc,
                    job.sequential(),
                    "{} differs from a sequential run",
                    job.id
                );
                for (unit, &tiles) in job.units.iter().enumerate() {
                    for tile in 0..tiles {
                        let key = key(job.id, unit as u64, tile);
                        assert_eq!(self.accepts.get(&key), Some(&1), "{key}");
                    }
                }
            }
            assert!(self.accepts.values().all(|&n| n == 1));
            assert_eq!((self.s.in_flight_total(), self.s.ready_total()), (0, 0));
            let kept = self.jobs.iter().filter(|job| !job.removed).count();
            assert_eq!(self.s.jobs().len(), kept);
        }
    }

    #[test]
    fn simulation_accepts_every_tile_exactly_once_despite_lost_slow_and_repeating_workers() {
        let mut total = Stats::default();
        for seed in 1..=24 {
            total.add(Sim::new(seed, 5, 20).run());
        }
        // The runs must have exercised what they claim to.
        assert!(total.completed >= 120, "{total:?}");
        assert!(
            total.lost > 0 && total.expired > 0 && total.cancelled > 0,
            "{total:?}"
        );
        for rejection in [
            Rejection::Expired,
            Rejection::Superseded,
            Rejection::Duplicate,
            Rejection::UnknownLease,
            Rejection::JobGone,
        ] {
            assert!(total.rejected(rejection) > 0, "no {rejection:?}: {total:?}");
        }
    }

    #[test]
    fn simulation_with_scarce_attempts_fails_exactly_the_jobs_whose_tiles_ran_out() {
        let mut total = Stats::default();
        for seed in 101..=112 {
            total.add(Sim::new(seed, 2, 200).run());
        }
        assert!(total.failed > 0 && total.completed > 0, "{total:?}");
    }
}
