//! Where the time and the bytes of one unit went: rendering on the workers against the
//! farm's own work (fetching and decoding inputs, serialising, transferring, merging,
//! refining, publishing). Logged as one `unit finished` line per unit and added to the
//! metrics; the farm benchmark (`bench/farm.py`) reads the lines.

use std::time::Instant;

use pathfarm_proto::v1;
use pathfarm_render::pass::PassSpec;

use super::Metrics;

/// CPU seconds the calling thread has run (0 where the clock is missing).
pub(crate) fn thread_cpu_seconds() -> f64 {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime only writes the timespec we pass.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
    match rc {
        0 => t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9,
        _ => 0.0,
    }
}

/// The accounts of the unit in flight.
#[derive(Clone, Debug)]
pub(crate) struct UnitLedger {
    /// When its tiles were offered, and the same on the job's clock (seconds since the job
    /// started: units of one iteration overlap, so an iteration's wall time is the span of
    /// its units, not their sum).
    pub(crate) started: Instant,
    pub(crate) job_s: f64,
    /// Seconds to encode and store the unit's inputs (tree, fractions, estimate).
    pub(crate) publish_s: f64,
    /// Sums over its accepted tiles of the workers' seconds.
    pub(crate) render_s: f64,
    pub(crate) prepare_s: f64,
    pub(crate) serialize_s: f64,
    /// Sums over its accepted tiles of the coordinator's seconds: receiving the upload
    /// (first to last message), checking, decoding and preparing it (CPU seconds of its
    /// thread: uploads are decoded side by side, [`thread_cpu_seconds`]), handing it to the
    /// session.
    pub(crate) receive_s: f64,
    pub(crate) decode_s: f64,
    pub(crate) merge_s: f64,
    /// Seconds of the last tile's hand-over, which ends the unit (and, at an iteration's
    /// end, refines the tree and updates the pixel estimate), and of the checkpoint.
    pub(crate) end_s: f64,
    pub(crate) checkpoint_s: f64,
    /// Bytes of tile uploads accepted, and of blobs sent since the unit started.
    pub(crate) bytes_up: u64,
    blobs_sent_before: u64,
    pub(crate) tiles: u32,
    /// Uploads accepted (each one or more tiles).
    pub(crate) uploads: u32,
}

impl Default for UnitLedger {
    fn default() -> Self {
        Self {
            started: Instant::now(),
            job_s: 0.0,
            publish_s: 0.0,
            render_s: 0.0,
            prepare_s: 0.0,
            serialize_s: 0.0,
            receive_s: 0.0,
            decode_s: 0.0,
            merge_s: 0.0,
            end_s: 0.0,
            checkpoint_s: 0.0,
            bytes_up: 0,
            blobs_sent_before: 0,
            tiles: 0,
            uploads: 0,
        }
    }
}

/// What the coordinator measured of one accepted upload.
pub(crate) struct TileTimes {
    pub(crate) receive_s: f64,
    pub(crate) decode_s: f64,
    pub(crate) bytes: u64,
}

impl UnitLedger {
    /// A unit whose inputs took `publish_s` to publish starts now, `job_s` seconds into its job.
    pub(crate) fn start(publish_s: f64, job_s: f64, metrics: &Metrics) -> Self {
        Self {
            publish_s,
            job_s,
            blobs_sent_before: metrics.blob_bytes_sent.get(),
            ..Self::default()
        }
    }

    /// Adds an accepted upload of one or more tiles (`merge_s`: its hand-over to the session).
    pub(crate) fn upload(&mut self, tiles: &[&v1::TileCounters], t: &TileTimes, merge_s: f64) {
        for c in tiles {
            self.render_s += c.render_seconds.max(0.0);
            self.prepare_s += c.prepare_seconds.max(0.0);
            self.serialize_s += c.serialize_seconds.max(0.0);
        }
        self.receive_s += t.receive_s;
        self.decode_s += t.decode_s;
        self.merge_s += merge_s;
        self.bytes_up += t.bytes;
        self.tiles += tiles.len() as u32;
        self.uploads += 1;
    }

    /// Logs the finished unit and adds it to the metrics.
    pub(crate) fn finish(&self, job: &str, spec: &PassSpec, kind: &str, metrics: &Metrics) {
        let (unit, iteration) = (spec.unit, spec.iteration);
        let wall = self.started.elapsed().as_secs_f64();
        let sent = metrics
            .blob_bytes_sent
            .get()
            .saturating_sub(self.blobs_sent_before);
        tracing::info!(
            job,
            unit,
            iteration,
            kind,
            tiles = self.tiles,
            uploads = self.uploads,
            job_s = self.job_s,
            wall_s = wall,
            render_s = self.render_s,
            prepare_s = self.prepare_s,
            serialize_s = self.serialize_s,
            receive_s = self.receive_s,
            decode_s = self.decode_s,
            merge_s = self.merge_s,
            end_s = self.end_s,
            checkpoint_s = self.checkpoint_s,
            publish_s = self.publish_s,
            bytes_up = self.bytes_up,
            bytes_down = sent,
            "unit finished"
        );
        metrics.observe_unit(self);
    }
}

/// The accounts of one iteration's records collection, from asking the holders to the
/// refined and checkpointed tree: logged as one `records collected` line (read by
/// `bench/farm.py`) and added to the metrics. Refinement happens here, not at the unit's
/// end, when records come once an iteration.
#[derive(Clone, Debug)]
pub(crate) struct RecordsLedger {
    /// When the holders were asked, and how many.
    pub(crate) started: Instant,
    pub(crate) holders: usize,
    /// Bytes of records received; the coordinator's seconds decoding them (off the state
    /// lock) and adding them to the tree.
    pub(crate) bytes: u64,
    pub(crate) decode_s: f64,
    pub(crate) merge_s: f64,
}

impl RecordsLedger {
    pub(crate) fn start(holders: usize) -> Self {
        Self {
            started: Instant::now(),
            holders,
            bytes: 0,
            decode_s: 0.0,
            merge_s: 0.0,
        }
    }

    /// One holder's records are in.
    pub(crate) fn add(&mut self, bytes: u64, decode_s: f64, merge_s: f64) {
        self.bytes += bytes;
        self.decode_s += decode_s;
        self.merge_s += merge_s;
    }

    /// Logs the collection: `wait_s` from asking to the last records in, then the
    /// refinement (`end_s`) and the checkpoint.
    pub(crate) fn finish(&self, job: &str, iteration: u32, ended: RecordsEnd, metrics: &Metrics) {
        let wait_s = self.started.elapsed().as_secs_f64() - ended.end_s - ended.checkpoint_s;
        tracing::info!(
            job,
            iteration,
            holders = self.holders,
            bytes = self.bytes,
            wait_s,
            decode_s = self.decode_s,
            merge_s = self.merge_s,
            end_s = ended.end_s,
            checkpoint_s = ended.checkpoint_s,
            "records collected"
        );
        metrics.observe_records(&[
            ("wait", wait_s),
            ("decode", self.decode_s),
            ("merge", self.merge_s),
            ("end", ended.end_s),
            ("checkpoint", ended.checkpoint_s),
        ]);
    }
}

/// What followed the last records in: seconds refining and checkpointing.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RecordsEnd {
    pub(crate) end_s: f64,
    pub(crate) checkpoint_s: f64,
}
