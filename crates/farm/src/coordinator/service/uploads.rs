//! Tile and records uploads: who sent them, what they may announce, and validation before
//! anything is committed.
//!
//! * **Who**: the sender is the connected worker whose control stream's upload key the call
//!   carries ([`Svc::sender`]), never a field of the upload; it must hold every lease it
//!   names, and records are taken only from a worker asked for them.
//! * **What**: a header is held to what its leases can produce (each tile's pixel bytes
//!   exactly, statistics only for a recording unit and within
//!   [`Resources::max_stats_bytes`]) and its bytes are reserved from the upload memory
//!   budget ([`Resources::upload_memory_bytes`]) before any data is read.
//! * **Validate, then commit**: the scheduler is asked without committing
//!   ([`Scheduler::check_all`]), the session validates and adds the tiles atomically, and
//!   only then does the scheduler accept them. A bad upload is refused and its leases go
//!   back to the queue; it counts against its sender ([`Shared::blame`]), never the job.

use std::time::Instant;

use tokio::sync::OwnedSemaphorePermit;

use super::*;
use pathfarm_render::pass::TilePixels;
use pathfarm_render::{Region, SplatPlan};

use super::ledger::thread_cpu_seconds;
use crate::driver::{Coverage, TileIn};

/// Why an upload is refused, and whether its sender is to blame (a stale upload, whose
/// lease expired or whose unit is over, is nobody's fault).
struct Refusal {
    reason: v1::TileRejectReason,
    detail: String,
    fault: Fault,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Fault {
    None,
    Sender,
}

impl Refusal {
    fn stale(reason: v1::TileRejectReason, detail: impl Into<String>) -> Refusal {
        let detail = detail.into();
        let fault = Fault::None;
        Refusal {
            reason,
            detail,
            fault,
        }
    }

    fn corrupt(detail: impl Into<String>) -> Refusal {
        let detail = detail.into();
        let (reason, fault) = (v1::TileRejectReason::Corrupt, Fault::Sender);
        Refusal {
            reason,
            detail,
            fault,
        }
    }
}

/// A tile of an upload, checked against its lease and decoded.
struct Accepting {
    lease: LeaseId,
    index: usize,
    out: TileOutput,
    counters: v1::TileCounters,
}

/// What an upload's header was checked to name: one job, one unit of it in flight.
struct Named {
    job: u64,
    unit: u64,
    spec: pathfarm_render::pass::PassSpec,
}

impl Svc {
    /// The connected worker a call comes from: the control stream its upload key names.
    pub(super) fn sender(&self, meta: &tonic::metadata::MetadataMap) -> Result<WorkerId, Status> {
        let header = pathfarm_proto::WORKER_KEY_HEADER;
        let key = (meta.get(header))
            .and_then(|v| v.to_str().ok())
            .and_then(parse_key)
            .ok_or_else(|| {
                Status::unauthenticated(format!(
                    "an upload needs the metadata {header}: its worker's upload key \
                     (Registered.upload_key, 64 hex digits)"
                ))
            })?;
        let keys = self.shared.keys.read().unwrap_or_else(|e| e.into_inner());
        keys.get(&key).map(|&id| WorkerId(id)).ok_or_else(|| {
            Status::permission_denied(
                "the upload key names no connected worker (its control stream ended: \
                 register again)",
            )
        })
    }

    /// Reserves `bytes` of the upload memory budget, waiting at most the idle timeout.
    async fn reserve(&self, bytes: u64) -> Result<OwnedSemaphorePermit, Status> {
        let budget = self.shared.cfg.resources.upload_memory_bytes;
        let kib = (bytes >> 10) + 1;
        if bytes > budget || kib > u32::MAX as u64 {
            return Err(Status::resource_exhausted(format!(
                "an upload of {bytes} bytes is more than the upload memory budget of \
                 {budget} bytes (--upload-memory-mb)"
            )));
        }
        let permits = self
            .shared
            .upload_kib
            .clone()
            .acquire_many_owned(kib as u32);
        match tokio::time::timeout(self.idle(), permits).await {
            Ok(Ok(permit)) => Ok(permit),
            _ => Err(Status::resource_exhausted(
                "the coordinator's upload memory is in use: try again",
            )),
        }
    }

    /// `UploadTile`: a joint upload of tiles of one unit from `sender`.
    pub(super) async fn take_tile_upload(
        &self,
        sender: WorkerId,
        mut stream: Streaming<v1::TileUpload>,
    ) -> Result<Response<v1::TileAck>, Status> {
        let header = match chunked::header(&mut stream, "UploadTile", self.idle()).await {
            Ok(h) => h,
            Err(e) => return upload_refused(e, corrupt_ack),
        };
        let received = Instant::now();
        let (header, announced) = self
            .off(move |svc| {
                let announced = svc.announced(sender, &header);
                match announced {
                    Ok(total) => (header, Ok(total)),
                    Err(r) => {
                        let ack = svc.refuse(&mut svc.shared.lock(), sender, &header, r);
                        (header, Err(ack))
                    }
                }
            })
            .await;
        let total = match announced {
            Ok(t) => t,
            Err(ack) => return Ok(Response::new(ack)),
        };
        let _reserved = self.reserve(total).await?;
        let bytes = match chunked::data_to_vec(&mut stream, total, self.idle()).await {
            Ok(b) => b,
            Err(e) => return upload_refused(e, corrupt_ack),
        };
        let receive_s = received.elapsed().as_secs_f64();
        let ack = (self.off(move |svc| svc.take_tiles(sender, header, bytes, receive_s))).await;
        self.shared.metrics.tile_upload(total, ack.accepted);
        Ok(Response::new(ack))
    }

    /// Checks a tile header against the leases it names, before any data is read: the
    /// payload bytes it may carry, or why it is refused.
    fn announced(&self, sender: WorkerId, header: &v1::TileHeader) -> Result<u64, Refusal> {
        payload_size(header).map_err(Refusal::corrupt)?;
        let st = self.shared.lock();
        let named = named(&st, sender, header)?;
        let mut total = header.stats_size;
        if !named.spec.record() && header.stats_size > 0 {
            let detail = format!("statistics for unit {}, which records nothing", named.unit);
            return Err(Refusal::corrupt(detail));
        }
        let max_stats = self.shared.cfg.resources.max_stats_bytes;
        if header.stats_size > max_stats {
            let detail = format!(
                "{} bytes of statistics, more than {max_stats} (Resources::max_stats_bytes)",
                header.stats_size
            );
            return Err(Refusal::corrupt(detail));
        }
        let a = st.jobs[&named.job].active().expect("named");
        let tiles = a.session().tiles_of(named.unit).expect("named");
        for t in &header.tiles {
            let key = st.sched.lease(LeaseId(t.lease_id)).expect("named").key;
            let region = tiles[key.tile as usize];
            let expected = codec::tile_pixels_bytes(&named.spec, region);
            if t.pixels_size != expected {
                return Err(Refusal::corrupt(format!(
                    "lease {}: {} bytes of pixels, its tile has {expected}",
                    t.lease_id, t.pixels_size
                )));
            }
            total += t.pixels_size;
        }
        Ok(total)
    }

    /// Refuses an upload: `sender` keeps nothing of it, so the leases it names that it still
    /// validly holds go back to the queue now (without counting an attempt) instead of
    /// waiting out their deadlines; a fault of the sender's counts against it.
    fn refuse(
        &self,
        st: &mut State,
        sender: WorkerId,
        header: &v1::TileHeader,
        r: Refusal,
    ) -> v1::TileAck {
        let now = self.shared.now();
        let mine = |t: &&v1::UploadedTile| {
            (st.sched.lease(LeaseId(t.lease_id))).is_some_and(|l| l.worker == sender)
        };
        let ids: Vec<LeaseId> = (header.tiles.iter().filter(mine))
            .map(|t| LeaseId(t.lease_id))
            .collect();
        let job = (ids.first())
            .and_then(|&id| st.sched.lease(id))
            .map(|l| l.key.job.0);
        let returned = st.sched.hand_back(sender, &ids, now).map_or(0, |k| k.len());
        if returned > 0 {
            tracing::info!(job = %resources::truncate(&header.job_id, 64), returned, "valid leases of a refused upload returned");
        }
        if let (Fault::Sender, Some(n)) = (r.fault, job) {
            self.shared.blame(st, n, sender.0, &r.detail, Blame::Bad);
        }
        self.shared.dispatch(st);
        ack(false, r.reason, r.detail).into_inner()
    }

    /// Decodes an upload (off the lock), validates it, and commits it: the session takes
    /// the tiles, then the scheduler accepts them.
    fn take_tiles(
        &self,
        sender: WorkerId,
        header: v1::TileHeader,
        bytes: Vec<u8>,
        receive_s: f64,
    ) -> v1::TileAck {
        let cpu_start = thread_cpu_seconds();
        let total = bytes.len() as u64;
        let shared = &self.shared;
        // The lock is held only to look the tiles up: decoding and preparing their pixels
        // (most of a unit's splatting) runs beside other uploads.
        let checked = split_and_decode(&header, &bytes).and_then(|(parts, stats)| {
            let look = look_up(&shared.lock(), sender, &header)?;
            let tiles = decode_tiles(&look, &header, &parts)?;
            Ok((look, tiles, stats))
        });
        let mut st = shared.lock();
        let st = &mut *st;
        let (look, tiles, stats) = match checked {
            Ok(c) => c,
            Err(r) => return self.refuse(st, sender, &header, r),
        };
        // The lock was let go while the pixels were decoded: the upload must still name the
        // same tiles of the same unit in flight.
        match look_up(st, sender, &header) {
            Ok(again) if again.same_tiles(&look) => {}
            Ok(_) => {
                let r = Refusal::stale(
                    v1::TileRejectReason::Superseded,
                    "the unit was re-tiled while the upload was decoded",
                );
                return self.refuse(st, sender, &header, r);
            }
            Err(r) => return self.refuse(st, sender, &header, r),
        }
        let named = look.named;
        // (CPU, not time waiting for the lock: another upload's merge, a unit's end)
        let decode_s = thread_cpu_seconds() - cpu_start;
        let (n, unit, spec) = (named.job, named.unit, named.spec);
        let now = shared.now();
        let ids: Vec<LeaseId> = tiles.iter().map(|t| t.lease).collect();
        match st.sched.check_all(sender, &ids, now) {
            Ok(()) => {}
            Err(Rejection::Duplicate) => {
                let mut a = ack(true, v1::TileRejectReason::Unspecified, String::new());
                a.get_mut().duplicate = true;
                return a.into_inner();
            }
            Err(r) => {
                let reason = match r {
                    Rejection::UnknownLease => v1::TileRejectReason::UnknownLease,
                    Rejection::Expired => v1::TileRejectReason::Expired,
                    _ => v1::TileRejectReason::Superseded,
                };
                tracing::info!(job = %job_name(n), leases = ?ids, "tiles rejected: {r}");
                return self.refuse(st, sender, &header, Refusal::stale(reason, r.to_string()));
            }
        }
        let a = (st.jobs.get_mut(&n))
            .and_then(|j| j.active_mut())
            .expect("checked");
        let merge_start = Instant::now();
        let tiles_in: Vec<TileIn> = (tiles.iter())
            .map(|t| TileIn {
                index: t.index,
                lease: t.lease,
                out: &t.out,
                render_seconds: t.counters.render_seconds,
            })
            .collect();
        let ended = match a
            .driver
            .tiles_in(sender, unit, &tiles_in, stats.as_ref(), now)
        {
            Ok(ended) => ended,
            Err(e) => {
                let detail = format!("tiles {ids:?} refused by the session: {e}");
                return self.refuse(st, sender, &header, Refusal::corrupt(detail));
            }
        };
        (st.sched.complete_all(sender, &ids, now))
            .expect("checked under the same lock, at the same instant");
        let unit_done = ended.iter().any(|s| s.unit == unit);
        let merge_s = merge_start.elapsed().as_secs_f64();
        let times = TileTimes {
            receive_s,
            decode_s,
            bytes: total,
        };
        self.account(st, sender, n, &spec, &tiles, unit_done, (times, merge_s));
        tracing::debug!(job = %job_name(n), leases = ?ids, unit, "tiles accepted");
        if !ended.is_empty() {
            shared.end_units(st, n, &ended);
        }
        shared.publish_status(st, n);
        shared.dispatch(st);
        ack(true, v1::TileRejectReason::Unspecified, String::new()).into_inner()
    }

    /// Books accepted tiles: the unit's ledger, the samples done and the worker's count.
    #[allow(clippy::too_many_arguments)]
    fn account(
        &self,
        st: &mut State,
        sender: WorkerId,
        n: u64,
        spec: &pathfarm_render::pass::PassSpec,
        tiles: &[Accepting],
        unit_done: bool,
        (times, merge_s): (TileTimes, f64),
    ) {
        let job = st.jobs.get_mut(&n).expect("checked");
        let a = job.active_mut().expect("checked");
        let samples: u64 = (tiles.iter())
            .map(|t| t.out.region.pixels() as u64 * spec.unit_spp())
            .sum();
        let counters: Vec<&v1::TileCounters> = tiles.iter().map(|t| &t.counters).collect();
        if let Some(ledger) = a.ledger(spec.unit) {
            if unit_done {
                ledger.end_s = merge_s;
                ledger.upload(&counters, &times, 0.0);
            } else {
                ledger.upload(&counters, &times, merge_s);
            }
        }
        job.record.samples_done += samples;
        (self.shared.throughput.lock())
            .unwrap_or_else(|e| e.into_inner())
            .add(self.shared.now(), samples, tiles.len() as u64);
        if let Some(w) = st.workers.get_mut(&sender.0) {
            w.tiles_done += tiles.len() as u64;
        }
    }

    /// `UploadRecords`: a holder's answer to `FlushRecords`, checked against what was asked
    /// of `sender` before its data is read.
    pub(super) async fn take_records_upload(
        &self,
        sender: WorkerId,
        mut stream: Streaming<v1::RecordsUpload>,
    ) -> Result<Response<v1::RecordsAck>, Status> {
        let refused = |d: String| records_refused(d).into_inner();
        let header = match chunked::header(&mut stream, "UploadRecords", self.idle()).await {
            Ok(h) => h,
            Err(e) => return upload_refused(e, refused),
        };
        if header.worker_id != sender.0 {
            return Ok(records_refused(format!(
                "worker_id {} is not the uploading worker's ({})",
                header.worker_id, sender.0
            )));
        }
        let max = self.shared.cfg.resources.max_records_bytes;
        if header.size > max {
            let detail = format!("{} bytes of records, at most {max}", header.size);
            return Ok(records_refused(detail));
        }
        let (header, asked) = self
            .off(move |svc| {
                let asked = svc.asked(&header);
                (header, asked)
            })
            .await;
        if let Err(detail) = asked {
            return Ok(records_refused(detail));
        }
        let size = if header.lost { 0 } else { header.size };
        let _reserved = self.reserve(size).await?;
        let bytes = match chunked::data_to_vec(&mut stream, size, self.idle()).await {
            Ok(b) => b,
            Err(e) => return upload_refused(e, refused),
        };
        self.shared.metrics.records_upload(bytes.len() as u64);
        Ok(self.off(move |svc| svc.take_records(header, bytes)).await)
    }

    /// Whether the job named by `header` is collecting records from its worker for its
    /// tree version and epoch; the refusal's text if not.
    fn asked(&self, header: &v1::RecordsHeader) -> Result<u64, String> {
        self.asked_locked(&self.shared.lock(), header)
    }

    /// A holder's records added to the session (decoded off the lock), or, if it lost them
    /// or sent records the session refuses, the job rolled back (and a bad sender blamed).
    fn take_records(&self, header: v1::RecordsHeader, bytes: Vec<u8>) -> Response<v1::RecordsAck> {
        let decode_start = Instant::now();
        let records = match header.lost {
            true => Ok(None),
            false
                if bytes.len() as u64 != header.size
                    || digest_of(&bytes).0.as_slice() != header.digest.as_slice() =>
            {
                Err("size or digest does not match the records".to_string())
            }
            false => match (
                IterationStats::decode(&bytes),
                Coverage::from_wire(header.covered_leases, &header.covered_digest),
            ) {
                (Ok(records), Ok(covered)) => Ok(Some((records, covered))),
                (Err(e), _) => Err(format!("records: {e}")),
                (_, Err(e)) => Err(e.to_string()),
            },
        };
        // Decoding is timed apart from waiting for the state lock.
        let decode_s = decode_start.elapsed().as_secs_f64();
        let shared = &self.shared;
        let mut st = shared.lock();
        let st = &mut *st;
        let n = match self.asked_locked(st, &header) {
            Ok(n) => n,
            Err(detail) => return records_refused(detail),
        };
        let w = header.worker_id;
        let (records, covered) = match records {
            Ok(Some(r)) => r,
            Ok(None) => {
                shared.roll_back(st, n, &format!("worker {w} lost the records it held"));
                return records_taken();
            }
            Err(detail) => {
                shared.blame(st, n, w, &detail, Blame::Bad);
                shared.roll_back(st, n, &format!("worker {w} sent bad records: {detail}"));
                return records_refused(detail);
            }
        };
        let a = (st.jobs.get_mut(&n))
            .and_then(|j| j.active_mut())
            .expect("asked");
        let merge_start = Instant::now();
        let left = match a.driver.records_from(WorkerId(w), &records, &covered) {
            Ok(left) => left,
            Err(e) => {
                let detail = e.to_string();
                shared.blame(st, n, w, &detail, Blame::Bad);
                shared.roll_back(st, n, &format!("worker {w}'s {detail}"));
                return records_refused(detail);
            }
        };
        let merge_s = merge_start.elapsed().as_secs_f64();
        if let Some(ledger) = a.records_ledger.as_mut() {
            ledger.add(bytes.len() as u64, decode_s, merge_s);
        }
        tracing::debug!(job = %job_name(n), worker = w, bytes = bytes.len(), left, "records in");
        if left == 0 {
            shared.drive(st, n);
            shared.dispatch(st);
        }
        records_taken()
    }

    /// [`Svc::asked`] under a lock already held.
    fn asked_locked(&self, st: &State, header: &v1::RecordsHeader) -> Result<u64, String> {
        let no_job = || format!("no job {}", resources::echo(&header.job_id));
        let n = parse_job(&header.job_id).ok_or_else(no_job)?;
        let job = st.jobs.get(&n).ok_or_else(no_job)?;
        let a = (job.active()).ok_or_else(|| "the job is not running".to_string())?;
        let current = a.driver.records_epoch() == header.records_epoch
            && a.tree_digest.map(|(_, d)| d.0.to_vec()) == Some(header.tree_digest.clone());
        let asked = a.driver.is_asked(WorkerId(header.worker_id));
        if !current || !asked {
            return Err("records not asked for (another epoch, version or worker)".into());
        }
        Ok(n)
    }
}

/// An upload key from its hex form (written as a digest is).
fn parse_key(hex: &str) -> Option<[u8; 32]> {
    crate::bundle::Digest::from_hex(hex).ok().map(|d| d.0)
}

/// The job, unit and pass of the leases a header names, all `sender`'s and of one unit in
/// flight; or why not.
fn named(st: &State, sender: WorkerId, header: &v1::TileHeader) -> Result<Named, Refusal> {
    let mut first: Option<crate::scheduler::TaskKey> = None;
    for t in &header.tiles {
        let id = t.lease_id;
        let Some(l) = st.sched.lease(LeaseId(id)) else {
            let detail = format!("lease {id} is not known");
            return Err(Refusal::stale(v1::TileRejectReason::UnknownLease, detail));
        };
        if l.worker != sender {
            return Err(Refusal::corrupt(format!(
                "lease {id} is not the uploading worker's"
            )));
        }
        let key = *first.get_or_insert(l.key);
        if l.key.job != key.job
            || l.key.unit != key.unit
            || header.job_id != job_name(key.job.0)
            || header.unit != key.unit
        {
            return Err(Refusal::corrupt(format!(
                "lease {id} ({}) does not belong with the upload's job {} unit {} and first \
                 lease ({key})",
                l.key,
                resources::echo(&header.job_id),
                header.unit
            )));
        }
    }
    let key = first.expect("an upload names at least one tile");
    let n = key.job.0;
    let spec = (st.jobs.get(&n))
        .and_then(|j| j.active())
        .filter(|a| a.session().tiles_of(key.unit).is_some())
        .and_then(|a| a.driver.flight(key.unit))
        .copied();
    let Some(spec) = spec else {
        let detail = format!("unit {} of {} is over", key.unit, job_name(n));
        return Err(Refusal::stale(v1::TileRejectReason::Superseded, detail));
    };
    Ok(Named {
        job: n,
        unit: key.unit,
        spec,
    })
}

type Decoded<'a> = (Vec<&'a [u8]>, Option<IterationStats>);

/// Splits an upload's payload by its header (whose sizes [`Svc::announced`] checked) and
/// checks its digests and decodes its statistics.
fn split_and_decode<'a>(header: &v1::TileHeader, bytes: &'a [u8]) -> Result<Decoded<'a>, Refusal> {
    let total = bytes.len();
    let (mut pixels, stats_bytes) = bytes.split_at(total - header.stats_size as usize);
    let mut parts = Vec::with_capacity(header.tiles.len());
    for t in &header.tiles {
        let (mine, rest) = pixels.split_at(t.pixels_size as usize);
        if digest_of(mine).0.as_slice() != t.pixels_digest.as_slice() {
            let detail = format!("lease {}: pixels_digest does not match", t.lease_id);
            return Err(Refusal::corrupt(detail));
        }
        parts.push(mine);
        pixels = rest;
    }
    if digest_of(stats_bytes).0.as_slice() != header.stats_digest.as_slice() {
        let detail = "stats_digest does not match the statistics payload";
        return Err(Refusal::corrupt(detail));
    }
    let stats = match stats_bytes.is_empty() {
        true => None,
        false => Some(
            IterationStats::decode(stats_bytes)
                .map_err(|e| Refusal::corrupt(format!("statistics: {e}")))?,
        ),
    };
    Ok((parts, stats))
}

/// An upload's tiles, looked up under the lock: the unit they name, each one's lease, index
/// and region, and how the unit's samples are splatted (for a unit of samples).
struct Lookup {
    named: Named,
    tiles: Vec<(LeaseId, usize, Region)>,
    plan: Option<SplatPlan>,
}

impl Lookup {
    /// Whether `self` names the tiles `other` named (of the same unit).
    fn same_tiles(&self, other: &Lookup) -> bool {
        (self.named.job, self.named.unit) == (other.named.job, other.named.unit)
            && self.tiles == other.tiles
    }
}

/// Checks every tile of an upload against its lease (the sender's, of the header's job and
/// unit, still in flight, the lease's region).
fn look_up(st: &State, sender: WorkerId, header: &v1::TileHeader) -> Result<Lookup, Refusal> {
    let named = named(st, sender, header)?;
    let session = st.jobs[&named.job].active().expect("named").session();
    let regions = session.tiles_of(named.unit).expect("named");
    let mut tiles = Vec::with_capacity(header.tiles.len());
    for t in &header.tiles {
        let lease_id = t.lease_id;
        let key = st.sched.lease(LeaseId(lease_id)).expect("named").key;
        let region = *regions.get(key.tile as usize).ok_or_else(|| {
            Refusal::stale(v1::TileRejectReason::Superseded, "the unit was re-tiled")
        })?;
        if t.tile != Some(codec::region_to_proto(region)) {
            return Err(Refusal::corrupt(format!(
                "the tile of lease {lease_id} is not its lease's ({key})"
            )));
        }
        tiles.push((LeaseId(lease_id), key.tile as usize, region));
    }
    let plan = session.splat_plan(named.unit).cloned();
    Ok(Lookup { named, tiles, plan })
}

/// Decodes and checks the pixels of every tile `look` found, and prepares the samples of a
/// unit of samples by its plan (their film positions drawn, each tile's interior gathered):
/// the CPU of an upload, done off the lock.
fn decode_tiles(
    look: &Lookup,
    header: &v1::TileHeader,
    parts: &[&[u8]],
) -> Result<Vec<Accepting>, Refusal> {
    let mut out = Vec::with_capacity(parts.len());
    for ((&(lease, index, region), t), bytes) in look.tiles.iter().zip(&header.tiles).zip(parts) {
        let pixels = codec::decode_tile_pixels(bytes, &look.named.spec, region)
            .map_err(|e| Refusal::corrupt(format!("lease {}: pixels: {e}", lease.0)))?;
        let pixels = match (pixels, &look.plan) {
            (TilePixels::Samples(v), Some(plan)) if v.len() == plan.samples(region) => {
                TilePixels::Prepared(Box::new(plan.prepare(region, &v)))
            }
            (TilePixels::Samples(_), Some(_)) => {
                let detail = format!("lease {}: samples not of the unit's plan", lease.0);
                return Err(Refusal::corrupt(detail));
            }
            (pixels, _) => pixels,
        };
        let c = t.counters.unwrap_or_default();
        out.push(Accepting {
            lease,
            index,
            out: TileOutput {
                region,
                pixels,
                rays: c.rays,
                invalid_samples: c.invalid_samples,
                nonfinite_records: c.nonfinite_records,
                split_paths: c.split_paths,
                extra_light_samples: c.extra_light_samples,
            },
            counters: c,
        });
    }
    Ok(out)
}

/// The most tiles one upload may carry.
pub const MAX_UPLOAD_TILES: usize = 64;

/// The payload bytes `header` announces, or why it is malformed: no tile or too many, a
/// tile without pixels, a lease named twice, more than 4 GiB.
fn payload_size(header: &v1::TileHeader) -> Result<u64, String> {
    let n = header.tiles.len();
    if n == 0 || n > MAX_UPLOAD_TILES {
        return Err(format!("{n} tiles in one upload (1 to {MAX_UPLOAD_TILES})"));
    }
    let mut ids: Vec<u64> = header.tiles.iter().map(|t| t.lease_id).collect();
    ids.sort_unstable();
    if ids.windows(2).any(|w| w[0] == w[1]) {
        return Err("a lease named twice in one upload".into());
    }
    let mut total = header.stats_size;
    for t in &header.tiles {
        if t.pixels_size == 0 {
            return Err(format!("lease {}: no pixel sums", t.lease_id));
        }
        total = total.saturating_add(t.pixels_size);
    }
    if total > 1 << 32 {
        return Err(format!("payload of {total} bytes is over 4 GiB"));
    }
    Ok(total)
}

/// A records upload taken.
fn records_taken() -> Response<v1::RecordsAck> {
    Response::new(v1::RecordsAck {
        accepted: true,
        detail: String::new(),
    })
}

/// A records upload refused, and why.
fn records_refused(detail: impl Into<String>) -> Response<v1::RecordsAck> {
    Response::new(v1::RecordsAck {
        accepted: false,
        detail: detail.into(),
    })
}

/// A malformed upload answered in the RPC's own reply (`ack` makes it from the detail); a
/// broken or idle stream as its status.
fn upload_refused<T>(e: UploadError, ack: impl FnOnce(String) -> T) -> Result<Response<T>, Status> {
    match e {
        UploadError::Malformed(detail) => Ok(Response::new(ack(detail))),
        e => Err(e.into_status()),
    }
}

fn corrupt_ack(detail: String) -> v1::TileAck {
    ack(false, v1::TileRejectReason::Corrupt, detail).into_inner()
}

fn ack(accepted: bool, reason: v1::TileRejectReason, detail: String) -> Response<v1::TileAck> {
    Response::new(v1::TileAck {
        accepted,
        reject_reason: reason as i32,
        detail,
        duplicate: false,
    })
}
