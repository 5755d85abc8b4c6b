//! The coordinator's Prometheus metrics (prometheus-client), served at `GET /metrics` on
//! `CoordinatorConfig::metrics` by axum.
//!
//! Counters are updated where things happen; the gauges (jobs by state, workers, tiles in
//! flight and ready) are read from the coordinator's state at each scrape, so they are
//! never stale.

use std::sync::atomic::AtomicU64;
use std::sync::Arc;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::{Metric, Registry};
use tokio::net::TcpListener;

use super::ledger::UnitLedger;
use super::Shared;
use pathfarm_proto::v1;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StateLabel {
    state: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct PhaseLabel {
    phase: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct OutcomeLabel {
    outcome: &'static str,
}

type Seconds = Counter<f64, AtomicU64>;

/// Every metric the coordinator exports.
pub(crate) struct Metrics {
    registry: Registry,
    jobs: Family<StateLabel, Gauge>,
    workers: Gauge,
    tiles_in_flight: Gauge,
    tiles_ready: Gauge,
    /// Bytes of blobs and results sent (the unit ledger reads it too).
    pub(crate) blob_bytes_sent: Counter,
    tile_bytes_uploaded: Counter,
    tiles: Family<OutcomeLabel, Counter>,
    units: Counter,
    unit_seconds: Family<PhaseLabel, Seconds>,
    records_seconds: Family<PhaseLabel, Seconds>,
    records_bytes: Counter,
    roll_backs: Counter,
    workers_blocked: Counter,
    blobs_expired: Counter,
    control_seconds: Family<KindLabel, Histogram>,
    status_seconds: Histogram,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct KindLabel {
    kind: &'static str,
}

impl Default for Metrics {
    fn default() -> Self {
        let mut r = Registry::with_prefix("pathfarm");
        let on = &mut r;
        let jobs = registered(on, "jobs", "Jobs by state");
        let workers = registered(on, "workers", "Connected workers");
        let tiles_in_flight = registered(on, "tiles_in_flight", IN_FLIGHT_HELP);
        let tiles_ready = registered(on, "tiles_ready", "Tiles waiting for a worker");
        let blob_bytes_sent = registered(on, "blob_bytes_sent", BLOB_BYTES_HELP);
        let tile_bytes_uploaded = registered(on, "tile_bytes_received", TILE_BYTES_HELP);
        let tiles = registered(on, "tiles", "Tile uploads by outcome (accepted, rejected)");
        let units = registered(on, "units", "Units (passes of a job) finished");
        let unit_seconds = registered(on, "unit_seconds", UNIT_SECONDS_HELP);
        let records_seconds = registered(on, "records_seconds", RECORDS_SECONDS_HELP);
        let records_bytes = registered(on, "records_bytes_received", RECORDS_BYTES_HELP);
        let roll_backs = registered(on, "roll_backs", ROLL_BACKS_HELP);
        let workers_blocked = registered(on, "workers_blocked", BLOCKED_HELP);
        let blobs_expired = registered(on, "blobs_expired", EXPIRED_HELP);
        // 50 us to about 3 s
        let control_seconds = Family::<KindLabel, Histogram>::new_with_constructor(
            (|| Histogram::new(exponential_buckets(5e-5, 2.0, 17))) as fn() -> Histogram,
        );
        on.register(
            "control_message_seconds",
            CONTROL_HELP,
            control_seconds.clone(),
        );
        let status_seconds = Histogram::new(exponential_buckets(5e-5, 2.0, 17));
        on.register("status_seconds", STATUS_HELP, status_seconds.clone());
        Metrics {
            registry: r,
            jobs,
            workers,
            tiles_in_flight,
            tiles_ready,
            blob_bytes_sent,
            tile_bytes_uploaded,
            tiles,
            units,
            unit_seconds,
            records_seconds,
            records_bytes,
            roll_backs,
            workers_blocked,
            blobs_expired,
            control_seconds,
            status_seconds,
        }
    }
}

const RECORDS_SECONDS_HELP: &str = "Seconds spent collecting iterations' quadtree records \
     by phase: wait (asking the holders to the last records in), decode, merge, end \
     (refinement), checkpoint";

const RECORDS_BYTES_HELP: &str =
    "Bytes of quadtree records received (once per worker and tree version)";
const ROLL_BACKS_HELP: &str =
    "Jobs rolled back to their last checkpoint: a worker holding records was lost";

const CONTROL_HELP: &str = "Seconds from receiving a worker's control message (heartbeat, \
     lease request, failure, hand-back) to having handled it, waiting for the state lock included, \
     by kind (heartbeat, other)";
const STATUS_HELP: &str = "Seconds the coordinator took to answer a status call (ListJobs, \
     GetJob, ListWorkers), from the handler's start";
const BLOCKED_HELP: &str =
    "Workers blocked from a job after sending it bad results (a worker and job counted once)";
const EXPIRED_HELP: &str =
    "Uploaded blobs deleted because no job referred to them within the grace period";

const IN_FLIGHT_HELP: &str = "Tiles leased to workers and not yet in";
const BLOB_BYTES_HELP: &str =
    "Bytes of blobs (scenes, trees, fractions, estimates) and results sent";
const TILE_BYTES_HELP: &str = "Bytes of tile uploads (pixel sums and guide statistics) received";
const UNIT_SECONDS_HELP: &str = "Seconds spent on finished units by phase: render, prepare and \
     serialize on the workers; receive, decode, merge, end (refinement), checkpoint and \
     publish (tree broadcast) on the coordinator; wall per unit";

/// A new metric, registered as `name` with `help` (the registry keeps a handle sharing its
/// value).
fn registered<M: Metric + Clone + Default>(registry: &mut Registry, name: &str, help: &str) -> M {
    let metric = M::default();
    registry.register(name, help, metric.clone());
    metric
}

impl Metrics {
    /// Counts `bytes` of blob or result sent.
    pub(crate) fn blob_sent(&self, bytes: u64) {
        self.blob_bytes_sent.inc_by(bytes);
    }

    /// Counts a tile upload of `bytes`, accepted or not.
    pub(crate) fn tile_upload(&self, bytes: u64, accepted: bool) {
        self.tile_bytes_uploaded.inc_by(bytes);
        let outcome = if accepted { "accepted" } else { "rejected" };
        self.tiles.get_or_create(&OutcomeLabel { outcome }).inc();
    }

    /// Counts a records upload of `bytes`.
    pub(crate) fn records_upload(&self, bytes: u64) {
        self.records_bytes.inc_by(bytes);
    }

    /// Observes how long a control message took to handle.
    pub(crate) fn control_message(&self, kind: &'static str, seconds: f64) {
        self.control_seconds
            .get_or_create(&KindLabel { kind })
            .observe(seconds);
    }

    /// Observes how long a status call took.
    pub(crate) fn status_call(&self, seconds: f64) {
        self.status_seconds.observe(seconds);
    }

    /// Counts a worker blocked from a job.
    pub(crate) fn worker_blocked(&self) {
        self.workers_blocked.inc();
    }

    /// Counts unreferenced blobs deleted after the grace period.
    pub(crate) fn blobs_expired(&self, n: u64) {
        self.blobs_expired.inc_by(n);
    }

    /// Counts a job rolled back to its checkpoint.
    pub(crate) fn roll_back(&self) {
        self.roll_backs.inc();
    }

    /// Adds an iteration's records collection, by phase.
    pub(crate) fn observe_records(&self, phases: &[(&'static str, f64)]) {
        for &(phase, s) in phases {
            self.records_seconds
                .get_or_create(&PhaseLabel { phase })
                .inc_by(s.max(0.0));
        }
    }

    /// Adds a finished unit's accounts.
    pub(crate) fn observe_unit(&self, l: &UnitLedger) {
        self.units.inc();
        let phases = [
            ("wall", l.started.elapsed().as_secs_f64()),
            ("render", l.render_s),
            ("prepare", l.prepare_s),
            ("serialize", l.serialize_s),
            ("receive", l.receive_s),
            ("decode", l.decode_s),
            ("merge", l.merge_s),
            ("end", l.end_s),
            ("checkpoint", l.checkpoint_s),
            ("publish", l.publish_s),
        ];
        for (phase, s) in phases {
            self.unit_seconds
                .get_or_create(&PhaseLabel { phase })
                .inc_by(s.max(0.0));
        }
    }
}

/// The metrics in the text exposition format, with the gauges read now.
pub(crate) fn render(shared: &Shared) -> String {
    let m = &shared.metrics;
    {
        let st = shared.lock();
        let mut counts = [0i64; 7];
        for (&n, j) in &st.jobs {
            let s = super::status_of(n, &j.record, j.active()).state;
            if let Some(i) = STATES.iter().position(|x| *x as i32 == s) {
                counts[i] += 1;
            }
        }
        for (state, count) in STATES.iter().zip(counts) {
            let label = StateLabel {
                state: state_label(*state),
            };
            m.jobs.get_or_create(&label).set(count);
        }
        let workers = st.workers.len();
        m.workers.set(workers as i64);
        m.tiles_in_flight.set(st.sched.in_flight_total() as i64);
        m.tiles_ready.set(st.sched.ready_total() as i64);
    }
    let mut out = String::new();
    if let Err(e) = prometheus_client::encoding::text::encode(&mut out, &m.registry) {
        tracing::error!("encoding metrics: {e}");
    }
    out
}

/// Every job state a job can be in (the metrics' and the dashboard's order).
pub(crate) const STATES: [v1::JobState; 7] = [
    v1::JobState::Queued,
    v1::JobState::Training,
    v1::JobState::FinalPass,
    v1::JobState::Assembling,
    v1::JobState::Done,
    v1::JobState::Failed,
    v1::JobState::Cancelled,
];

fn state_label(s: v1::JobState) -> &'static str {
    match s {
        v1::JobState::Queued => "queued",
        v1::JobState::Training => "training",
        v1::JobState::FinalPass => "final_pass",
        v1::JobState::Assembling => "assembling",
        v1::JobState::Done => "done",
        v1::JobState::Failed => "failed",
        v1::JobState::Cancelled => "cancelled",
        v1::JobState::Unspecified => "unspecified",
    }
}

/// Serves `GET /metrics` on `listener` until the task is aborted.
pub(crate) async fn serve(shared: Arc<Shared>, listener: TcpListener) {
    use axum::routing::get;
    let app = axum::Router::new().route(
        "/metrics",
        get(move || {
            let shared = shared.clone();
            async move {
                let body = tokio::task::spawn_blocking(move || render(&shared))
                    .await
                    .unwrap_or_default();
                (
                    [(
                        axum::http::header::CONTENT_TYPE,
                        "application/openmetrics-text; version=1.0.0; charset=utf-8",
                    )],
                    body,
                )
            }
        }),
    );
    if let Err(e) = axum::serve(listener, app).await {
        tracing::error!("metrics server: {e}");
    }
}
