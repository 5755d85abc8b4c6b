//! The gRPC services of the coordinator: `Jobs` and `Workers`, the auth interceptor, the
//! server itself and its periodic tick.

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::Arc;

use pathfarm_guide::IterationStats;
use pathfarm_proto::v1::{self, jobs_server::Jobs, workers_server::Workers};
use pathfarm_proto::MAX_CHUNK_BYTES;
use pathfarm_render::pass::TileOutput;
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::transport::server::TcpIncoming;
use tonic::{Request, Response, Status, Streaming};

mod uploads;

use super::ledger::TileTimes;
use super::*;
use crate::bundle::digest_of;
use crate::chunked::{self, UploadError};
use crate::scheduler::Rejection;

type ChunkStream = Pin<Box<dyn Stream<Item = Result<v1::DataChunk, Status>> + Send>>;

#[derive(Clone)]
struct Svc {
    shared: Arc<Shared>,
    health: tonic_health::server::HealthReporter,
}

pub(super) async fn run(
    shared: Arc<Shared>,
    listener: TcpListener,
    addr: Option<SocketAddr>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), CoordinatorError> {
    let (health, health_service) = tonic_health::server::health_reporter();
    for name in ["", pathfarm_proto::JOBS_SERVICE] {
        health
            .set_service_status(name, tonic_health::ServingStatus::NotServing)
            .await;
    }
    health
        .set_service_status(
            pathfarm_proto::WORKERS_SERVICE,
            tonic_health::ServingStatus::Serving,
        )
        .await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pathfarm_proto::FILE_DESCRIPTOR_SET)
        // so that a stock client can describe the health service as well as call it
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()
        .map_err(|e| CoordinatorError::Reflection(e.to_string()))?;
    // v1alpha too: Python's stock grpcio-reflection and older grpcurl speak only that.
    let reflection_alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pathfarm_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()
        .map_err(|e| CoordinatorError::Reflection(e.to_string()))?;
    let svc = Svc {
        shared: shared.clone(),
        health: health.clone(),
    };
    let auth = Auth {
        expected: shared.cfg.token.as_ref().map(|t| format!("Bearer {t}")),
    };
    let ticker = {
        let svc = svc.clone();
        tokio::spawn(async move {
            let mut interval = tokio::time::interval(TICK);
            loop {
                interval.tick().await;
                let shared = svc.shared.clone();
                let _ = tokio::task::spawn_blocking(move || shared.tick()).await;
                update_health(&svc.shared, &svc.health).await;
            }
        })
    };
    if let Some(addr) = addr {
        tracing::info!("coordinator listening on {addr}");
    }
    let metrics = match shared.cfg.metrics {
        Some(maddr) => {
            let l = TcpListener::bind(maddr)
                .await
                .map_err(|error| CoordinatorError::Bind { addr: maddr, error })?;
            tracing::info!(
                "metrics on http://{}/metrics",
                l.local_addr().unwrap_or(maddr)
            );
            Some(tokio::spawn(super::metrics::serve(shared.clone(), l)))
        }
        None => None,
    };
    let dashboard = match shared.cfg.http {
        Some(haddr) => {
            let l = TcpListener::bind(haddr)
                .await
                .map_err(|error| CoordinatorError::Bind { addr: haddr, error })?;
            let scheme = if shared.cfg.tls.is_some() {
                "https"
            } else {
                "http"
            };
            let at = l.local_addr().unwrap_or(haddr);
            tracing::info!("dashboard on {scheme}://{at}/");
            Some(tokio::spawn(super::dashboard::serve(shared.clone(), l)))
        }
        None => None,
    };
    let closer = shared.clone();
    let shutdown = async move {
        shutdown.await;
        tracing::info!("coordinator shutting down");
        // End the workers' control streams so the server can stop.
        let mut st = closer.lock();
        closer
            .keys
            .write()
            .unwrap_or_else(|e| e.into_inner())
            .clear();
        for w in std::mem::take(&mut st.workers).into_values() {
            w.post(v1::coordinator_message::Msg::Drain(v1::Drain {
                reason: "the coordinator is shutting down".into(),
            }));
        }
    };
    let mut builder = tonic::transport::Server::builder();
    if let Some(tls) = &shared.cfg.tls {
        let identity = tonic::transport::Identity::from_pem(&tls.cert_pem, &tls.key_pem);
        builder = builder
            .tls_config(tonic::transport::ServerTlsConfig::new().identity(identity))
            .map_err(|e| CoordinatorError::Tls(crate::client::error_chain(&e)))?;
    }
    let result = builder
        .initial_stream_window_size(crate::client::STREAM_WINDOW)
        .initial_connection_window_size(crate::client::CONNECTION_WINDOW)
        .add_service(health_service)
        .add_service(reflection)
        .add_service(reflection_alpha)
        .add_service(v1::jobs_server::JobsServer::with_interceptor(
            svc.clone(),
            auth.clone(),
        ))
        .add_service(v1::workers_server::WorkersServer::with_interceptor(
            svc, auth,
        ))
        // The builder's tcp_nodelay applies only to listeners tonic binds itself: without
        // it on the accepted sockets, a lease offer or an ack written while an earlier
        // segment is unacknowledged waits for the peer's delayed ACK (about 40 ms on Linux).
        .serve_with_incoming_shutdown(
            TcpIncoming::from(listener).with_nodelay(Some(true)),
            shutdown,
        )
        .await;
    ticker.abort();
    let _ = ticker.await;
    for server in [metrics, dashboard].into_iter().flatten() {
        server.abort();
        let _ = server.await;
    }
    released(shared).await;
    result.map_err(CoordinatorError::from)
}

/// Waits (a minute at most) for the background work that holds the state (a job's build,
/// its assembly, a checkpoint write) to finish, so that when `serve` returns the data
/// directory and its database are free for the next coordinator.
async fn released(shared: Arc<Shared>) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while Arc::strong_count(&shared) > 1 {
        if std::time::Instant::now() > deadline {
            return tracing::warn!("background work still running at shutdown");
        }
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
}

#[derive(Clone)]
struct Auth {
    expected: Option<String>,
}

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        // The token first: an unauthenticated caller learns nothing, not even the protocol.
        if let Some(expected) = &self.expected {
            match req.metadata().get("authorization") {
                None => {
                    return Err(Status::unauthenticated(
                        "missing token: send metadata \"authorization: Bearer <token>\"",
                    ))
                }
                Some(v) if constant_time_eq(v.as_bytes(), expected.as_bytes()) => {}
                Some(_) => return Err(Status::unauthenticated("wrong token")),
            }
        }
        // A pathfarm client names its protocol; stock gRPC clients (grpcurl) need not.
        if let Some(v) = req.metadata().get(pathfarm_proto::PROTOCOL_HEADER) {
            let ours = pathfarm_proto::PROTOCOL_VERSION.to_string();
            if v.as_bytes() != ours.as_bytes() {
                let theirs = resources::truncate(v.to_str().unwrap_or("?"), 64);
                return Err(Status::failed_precondition(format!(
                    "protocol version mismatch: client protocol {theirs}, coordinator {ours}"
                )));
            }
        }
        Ok(req)
    }
}

/// Whether `a == b`, in a time that does not depend on where they differ.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn chunk_stream(path: PathBuf, digest: Vec<u8>) -> Result<ChunkStream, Status> {
    let mut file = std::fs::File::open(&path)
        .map_err(|e| Status::internal(format!("cannot open blob: {e}")))?;
    let size = file
        .metadata()
        .map_err(|e| Status::internal(format!("cannot open blob: {e}")))?
        .len();
    let (tx, rx) = mpsc::channel(4);
    tokio::task::spawn_blocking(move || {
        use std::io::Read;
        let header = v1::DataChunk {
            part: Some(v1::data_chunk::Part::Header(v1::DataHeader {
                total_size: size,
                digest,
            })),
        };
        if tx.blocking_send(Ok(header)).is_err() {
            return;
        }
        let mut buf = vec![0u8; MAX_CHUNK_BYTES];
        loop {
            match file.read(&mut buf) {
                Ok(0) => return,
                Ok(k) => {
                    let part = v1::DataChunk {
                        part: Some(v1::data_chunk::Part::Data(buf[..k].to_vec())),
                    };
                    if tx.blocking_send(Ok(part)).is_err() {
                        return;
                    }
                }
                Err(e) => {
                    let _ =
                        tx.blocking_send(Err(Status::internal(format!("cannot read blob: {e}"))));
                    return;
                }
            }
        }
    });
    Ok(Box::pin(ReceiverStream::new(rx)))
}

impl Svc {
    /// Runs `f` on a blocking thread: whatever takes the state lock waits there, never on
    /// the async threads that answer heartbeats and status.
    async fn off<R: Send + 'static>(&self, f: impl FnOnce(&Svc) -> R + Send + 'static) -> R {
        let svc = self.clone();
        match tokio::task::spawn_blocking(move || f(&svc)).await {
            Ok(r) => r,
            Err(e) => std::panic::resume_unwind(e.into_panic()),
        }
    }

    fn job_number(&self, id: &str) -> Result<u64, Status> {
        let missing = || Status::not_found(format!("no job {}", resources::echo(id)));
        let n = parse_job(id).ok_or_else(missing)?;
        match self.shared.view(n) {
            Some(_) => Ok(n),
            None => Err(missing()),
        }
    }

    /// Refuses a submission while [`Resources::max_jobs_waiting`] jobs are queued or running.
    fn room_for_a_job(&self) -> Result<(), Status> {
        let max = self.shared.cfg.resources.max_jobs_waiting;
        let views = self.shared.views.read().unwrap_or_else(|e| e.into_inner());
        let waiting = (views.values())
            .filter(|v| !is_terminal(v.status.borrow().state))
            .count();
        if waiting >= max {
            return Err(Status::resource_exhausted(format!(
                "{waiting} jobs are queued or running, the most this coordinator takes \
                 (--max-jobs-waiting); submit again when some have finished"
            )));
        }
        Ok(())
    }

    fn idle(&self) -> std::time::Duration {
        self.shared.cfg.resources.stream_idle
    }
}

#[tonic::async_trait]
impl Jobs for Svc {
    async fn find_missing_blobs(
        &self,
        req: Request<v1::FindMissingBlobsRequest>,
    ) -> Result<Response<v1::FindMissingBlobsResponse>, Status> {
        let req = req.into_inner();
        if let Some(b) = &req.bundle {
            manifest_from_proto(b)?
                .validate(&self.shared.cfg.bundle_limits)
                .map_err(|e| bad(format!("bundle: {e}")))?;
        }
        let mut seen = std::collections::HashSet::new();
        let mut missing = Vec::new();
        for (i, d) in req.digests.into_iter().enumerate() {
            let digest = digest_from(&d, &format!("digests[{i}]"))?;
            if seen.insert(digest) && !self.shared.blobs.has_and_touch(&digest) {
                missing.push(d);
            }
        }
        Ok(Response::new(v1::FindMissingBlobsResponse { missing }))
    }

    async fn upload_blob(
        &self,
        req: Request<Streaming<v1::BlobChunk>>,
    ) -> Result<Response<v1::UploadBlobResponse>, Status> {
        let mut stream = req.into_inner();
        let header = chunked::header(&mut stream, "UploadBlob", self.idle())
            .await
            .map_err(UploadError::into_status)?;
        let digest = digest_from(&header.digest, "header.digest")?;
        let max = self.shared.cfg.bundle_limits.max_file_bytes;
        if header.size > max {
            return Err(bad(format!(
                "header.size: {} bytes is more than the limit of {max} bytes \
                 (BundleLimits::max_file_bytes)",
                header.size
            )));
        }
        let done = |already_present| {
            Ok(Response::new(v1::UploadBlobResponse {
                digest: header.digest.clone(),
                size: header.size,
                already_present,
            }))
        };
        if self.shared.blobs.has_and_touch(&digest) {
            // The same digest with another size is a false header, not a duplicate.
            let stored = self.shared.blobs.size(&digest);
            if stored != Some(header.size) {
                return Err(bad(format!(
                    "header.size: {} bytes, but the blob {} is {} bytes",
                    header.size,
                    digest.to_hex(),
                    stored.unwrap_or(0)
                )));
            }
            return done(true);
        }
        let mut upload = self
            .shared
            .blobs
            .begin(digest, header.size)
            .map_err(|e| Status::internal(format!("cannot store the blob: {e}")))?;
        chunked::data(&mut stream, header.size, self.idle(), |d| upload.write(d))
            .await
            .map_err(UploadError::into_status)?;
        upload.finish().map_err(super::bad)?;
        tracing::debug!(blob = %digest.to_hex(), size = header.size, "blob stored");
        done(false)
    }

    async fn submit_job(
        &self,
        req: Request<v1::SubmitJobRequest>,
    ) -> Result<Response<v1::SubmitJobResponse>, Status> {
        let req = req.into_inner();
        self.room_for_a_job()?;
        let shared = self.shared.clone();
        let (req, prepared) = tokio::task::spawn_blocking(move || {
            shared.advise_prefetch(&req);
            let t0 = std::time::Instant::now();
            let p = shared.prepare(&req);
            let seconds = t0.elapsed().as_secs_f64();
            let ok = p.is_ok();
            tracing::info!(ok, "submission validated in {seconds:.3} s");
            (req, p)
        })
        .await
        .map_err(|e| Status::internal(format!("job validation panicked: {e}")))?;
        // A refused submission's blobs stay until the grace period has passed (another
        // client may have uploaded the same files for a job of its own): `sweep`.
        let prepared = prepared?;
        let record = JobRecord {
            request: Some(req),
            state: v1::JobState::Queued as i32,
            submitted_unix_ms: unix_ms(),
            width: prepared.width,
            height: prepared.height,
            ..Default::default()
        };
        let need = session_memory(&record);
        let budget = self.shared.cfg.resources.job_memory_bytes;
        if need > budget {
            return Err(Status::resource_exhausted(format!(
                "the job's {}x{} image needs about {} MB of coordinator memory, more than \
                 its job memory budget of {} MB (--job-memory-mb)",
                record.width,
                record.height,
                need >> 20,
                budget >> 20
            )));
        }
        self.room_for_a_job()?;
        let n = self
            .off(move |svc| {
                let mut st = svc.shared.lock();
                let n = st.next_job;
                st.next_job += 1;
                svc.shared.db.put(n, &record).map_err(Status::internal)?;
                let queued = Phase::Queued(Some(Box::new(prepared)));
                svc.shared.add_job(
                    &mut st,
                    n,
                    Job::new(record, queued, n, &svc.shared.cfg.resources),
                );
                tracing::info!(job = %job_name(n), "job submitted");
                svc.shared.admit(&mut st);
                Ok::<u64, Status>(n)
            })
            .await?;
        Ok(Response::new(v1::SubmitJobResponse {
            job_id: job_name(n),
        }))
    }

    type WatchJobStream = ReceiverStream<Result<v1::JobStatus, Status>>;

    async fn watch_job(
        &self,
        req: Request<v1::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let n = self.job_number(&req.get_ref().job_id)?;
        let mut rx = self.shared.view(n).expect("checked").status;
        let (tx, out) = mpsc::channel(4);
        tokio::spawn(async move {
            loop {
                let status = rx.borrow_and_update().clone();
                let terminal = is_terminal(status.state);
                if tx.send(Ok(status)).await.is_err() || terminal {
                    return;
                }
                if rx.changed().await.is_err() {
                    return;
                }
                // coalesce bursts of changes
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
            }
        });
        Ok(Response::new(ReceiverStream::new(out)))
    }

    async fn get_job(
        &self,
        req: Request<v1::GetJobRequest>,
    ) -> Result<Response<v1::GetJobResponse>, Status> {
        let t0 = std::time::Instant::now();
        let n = self.job_number(&req.get_ref().job_id)?;
        let view = self.shared.view(n).expect("checked");
        let status = view.status.borrow().clone();
        self.shared.metrics.status_call(t0.elapsed().as_secs_f64());
        Ok(Response::new(v1::GetJobResponse {
            status: Some(status),
            settings: view.settings,
            root: view.root,
            image: view.image,
        }))
    }

    async fn list_jobs(
        &self,
        req: Request<v1::ListJobsRequest>,
    ) -> Result<Response<v1::ListJobsResponse>, Status> {
        // From the views: a merge or refinement holding the state lock never delays it.
        let t0 = std::time::Instant::now();
        let req = req.into_inner();
        let views = self.shared.views.read().unwrap_or_else(|e| e.into_inner());
        let mut jobs: Vec<v1::JobStatus> = (views.values())
            .map(|v| v.status.borrow().clone())
            .filter(|s| req.states.is_empty() || req.states.contains(&s.state))
            .collect();
        drop(views);
        if req.limit > 0 && jobs.len() > req.limit as usize {
            jobs.drain(..jobs.len() - req.limit as usize);
        }
        self.shared.metrics.status_call(t0.elapsed().as_secs_f64());
        Ok(Response::new(v1::ListJobsResponse { jobs }))
    }

    async fn cancel_job(
        &self,
        req: Request<v1::CancelJobRequest>,
    ) -> Result<Response<v1::CancelJobResponse>, Status> {
        let req = req.into_inner();
        let n = self.job_number(&req.job_id)?;
        let reason = if req.reason.is_empty() {
            "cancelled".to_string()
        } else {
            format!("cancelled: {}", resources::truncate(&req.reason, 1024))
        };
        let answer = self
            .off(move |svc| {
                let mut st = svc.shared.lock();
                let cancelled = svc
                    .shared
                    .end_job(&mut st, n, v1::JobState::Cancelled, reason);
                let status = st.jobs[&n].status(n);
                v1::CancelJobResponse {
                    cancelled,
                    status: Some(status),
                }
            })
            .await;
        Ok(Response::new(answer))
    }

    async fn set_job_priority(
        &self,
        req: Request<v1::SetJobPriorityRequest>,
    ) -> Result<Response<v1::SetJobPriorityResponse>, Status> {
        let req = req.into_inner();
        let n = self.job_number(&req.job_id)?;
        let answer = self
            .off(move |svc| {
                let mut st = svc.shared.lock();
                let changed = svc.shared.set_priority(&mut st, n, req.priority);
                let status = st.jobs[&n].status(n);
                v1::SetJobPriorityResponse {
                    changed,
                    status: Some(status),
                }
            })
            .await;
        Ok(Response::new(answer))
    }

    type DownloadResultStream = ChunkStream;

    async fn download_result(
        &self,
        req: Request<v1::DownloadResultRequest>,
    ) -> Result<Response<Self::DownloadResultStream>, Status> {
        let req = req.into_inner();
        let n = self.job_number(&req.job_id)?;
        let kind = v1::ResultKind::try_from(req.kind).unwrap_or(v1::ResultKind::Unspecified);
        let job_id = resources::truncate(&req.job_id, 64);
        if kind == v1::ResultKind::Unspecified {
            return Err(Status::invalid_argument("kind: unspecified"));
        }
        let digest = self
            .off(move |svc| svc.shared.result_blob(n, kind))
            .await
            .map_err(|why| Status::failed_precondition(format!("{job_id}: {why}")))?;
        let path = self.shared.blobs.path(&digest);
        self.count_fetch(&path);
        Ok(Response::new(chunk_stream(path, digest.0.to_vec())?))
    }

    async fn list_workers(
        &self,
        _req: Request<v1::ListWorkersRequest>,
    ) -> Result<Response<v1::ListWorkersResponse>, Status> {
        let t0 = std::time::Instant::now();
        let view = self
            .shared
            .workers_view
            .read()
            .unwrap_or_else(|e| e.into_inner());
        let workers = view.clone();
        drop(view);
        self.shared.metrics.status_call(t0.elapsed().as_secs_f64());
        Ok(Response::new(v1::ListWorkersResponse { workers }))
    }
}

fn msg(m: v1::coordinator_message::Msg) -> Result<v1::CoordinatorMessage, Status> {
    Ok(v1::CoordinatorMessage { msg: Some(m) })
}

impl Svc {
    /// Takes a heartbeat of worker `id` without the state lock (applied by its next holder,
    /// as of now); a heartbeat listing more leases than any worker holds goes the slow way
    /// and disconnects its sender. Returns the message if it was not taken.
    fn on_heartbeat(&self, id: u64, h: v1::Heartbeat) -> Option<v1::worker_message::Msg> {
        if h.active_lease_ids.len() > self.shared.cfg.resources.max_heartbeat_leases {
            return Some(v1::worker_message::Msg::Heartbeat(h));
        }
        self.shared.beat(Beat {
            worker: WorkerId(id),
            at: self.shared.now(),
            unix_ms: unix_ms(),
            leases: h.active_lease_ids.iter().map(|&l| LeaseId(l)).collect(),
        });
        None
    }

    /// Handles one control message of worker `id`.
    fn on_worker_message(&self, id: u64, m: v1::worker_message::Msg) {
        use v1::worker_message::Msg;
        let shared = &self.shared;
        let mut st = shared.lock();
        let now = shared.now();
        let worker = WorkerId(id);
        if let Some(w) = st.workers.get_mut(&id) {
            w.last_unix_ms = unix_ms();
        }
        match m {
            Msg::Register(_) => {
                tracing::warn!(worker = id, "second Register ignored");
            }
            Msg::Heartbeat(h) => {
                // Only a flood comes here ([`Svc::on_heartbeat`] takes the others).
                let n = h.active_lease_ids.len();
                tracing::warn!(worker = id, leases = n, "heartbeat lists too many leases");
                let events = st.sched.worker_lost(worker).unwrap_or_default();
                let max = shared.cfg.resources.max_heartbeat_leases;
                let why = format!("sent a heartbeat of {n} leases (at most {max})");
                shared.forget_worker(&mut st, id, &why);
                shared.handle_events(&mut st, events);
                shared.lost_holder(&mut st, worker);
                return;
            }
            Msg::RequestWork(r) => {
                if let Some(w) = st.workers.get_mut(&id) {
                    w.credits = w.credits.saturating_add(r.slots);
                }
            }
            Msg::LeaseFailed(f) => {
                tracing::warn!(
                    worker = id,
                    lease = f.lease_id,
                    fatal = f.fatal,
                    "lease failed: {}",
                    f.reason
                );
                let job = st.sched.lease(LeaseId(f.lease_id)).map(|l| l.key.job.0);
                match st
                    .sched
                    .fail_lease(worker, LeaseId(f.lease_id), &f.reason, now)
                {
                    Ok(events) => {
                        shared.handle_events(&mut st, events);
                        // One worker's word that the job cannot be rendered blocks that
                        // worker; the job fails when no worker is left to try it.
                        if let (true, Some(n)) = (f.fatal, job) {
                            let why = format!("failed lease {}: {}", f.lease_id, f.reason);
                            shared.blame(&mut st, n, id, &why, Blame::Unrenderable);
                        }
                    }
                    Err(r) => tracing::debug!(
                        worker = id,
                        lease = f.lease_id,
                        "failure report ignored: {r}"
                    ),
                }
            }
            Msg::Draining(_) => {
                if let Some(w) = st.workers.get_mut(&id) {
                    w.draining = true;
                    w.credits = 0;
                }
                let _ = st.sched.drain_worker(worker);
            }
            Msg::HandBack(h) => {
                let leases: Vec<LeaseId> = h.lease_ids.iter().map(|&l| LeaseId(l)).collect();
                let _ = st.sched.hand_back(worker, &leases, now);
            }
        }
        shared.dispatch(&mut st);
    }

    fn worker_gone(&self, id: u64) {
        let mut st = self.shared.lock();
        self.shared.forget_worker(&mut st, id, "disconnected");
        self.shared.refresh_workers_view(&st);
        tracing::info!(worker = id, "worker disconnected");
        match st.sched.worker_lost(WorkerId(id)) {
            Ok(events) => self.shared.handle_events(&mut st, events),
            // already declared lost (silent): its jobs rolled back then, if it held records
            Err(_) => self.shared.lost_holder(&mut st, WorkerId(id)),
        }
        self.shared.dispatch(&mut st);
    }
}

#[tonic::async_trait]
impl Workers for Svc {
    type ControlStream = ReceiverStream<Result<v1::CoordinatorMessage, Status>>;

    async fn control(
        &self,
        req: Request<Streaming<v1::WorkerMessage>>,
    ) -> Result<Response<Self::ControlStream>, Status> {
        use v1::coordinator_message::Msg;
        let mut inbound = req.into_inner();
        let first = inbound.message().await?.and_then(|m| m.msg);
        let Some(v1::worker_message::Msg::Register(register)) = first else {
            return Err(Status::failed_precondition(
                "the first message on the control stream must be Register",
            ));
        };
        let (tx, rx) = mpsc::channel(self.shared.cfg.resources.outbox_messages.max(8));
        let ours = crate::build::build_id();
        let refusal = if register.protocol_version != pathfarm_proto::PROTOCOL_VERSION {
            Some(format!(
                "protocol version mismatch: worker protocol {}, coordinator {}",
                register.protocol_version,
                pathfarm_proto::PROTOCOL_VERSION
            ))
        } else if register.build_id != ours {
            // The coordinator's own build id is not told: run the same release everywhere.
            Some(format!(
                "build mismatch: worker build {} is not the coordinator's (different builds \
                 may round differently, and tiles must be bit-exact)",
                resources::echo(&register.build_id)
            ))
        } else {
            None
        };
        if let Some(reason) = refusal {
            let host = resources::truncate(&register.host_name, resources::MAX_NAME_BYTES);
            tracing::warn!(host = %host, "worker refused: {reason}");
            let _ = tx.try_send(msg(Msg::Refused(v1::Refused {
                reason: reason.clone(),
                supported_protocol_versions: vec![pathfarm_proto::PROTOCOL_VERSION],
                required_build_id: String::new(),
            })));
            let _ = tx.try_send(Err(Status::failed_precondition(reason)));
            return Ok(Response::new(ReceiverStream::new(rx)));
        }
        let mut register = register;
        for name in [&mut register.host_name, &mut register.worker_name] {
            *name = resources::truncate(name, resources::MAX_NAME_BYTES);
        }
        let id = self
            .off(move |svc| {
                let mut st = svc.shared.lock();
                let id = st.next_worker;
                st.next_worker += 1;
                let now = svc.shared.now();
                if let Err(e) = st
                    .sched
                    .register_worker(WorkerId(id), register.threads.max(1), now)
                {
                    return Err(Status::internal(e.to_string()));
                }
                let sc = &svc.shared.cfg.scheduler;
                let heartbeat = (sc.heartbeat_timeout.as_millis() / 3).clamp(100, 5000) as u32;
                let upload_key = new_upload_key(id);
                let _ = tx.try_send(msg(Msg::Registered(v1::Registered {
                    worker_id: id,
                    heartbeat_interval_ms: heartbeat,
                    lease_timeout_ms: sc.lease_timeout.as_millis().min(u32::MAX as u128) as u32,
                    protocol_version: pathfarm_proto::PROTOCOL_VERSION,
                    build_id: ours.to_string(),
                    upload_key: upload_key.to_vec(),
                })));
                tracing::info!(
                    worker = id,
                    host = %register.host_name,
                    name = %register.worker_name,
                    threads = register.threads,
                    "worker registered"
                );
                let conn = WorkerConn {
                    tx,
                    credits: 0,
                    register,
                    registered_unix_ms: unix_ms(),
                    last_unix_ms: unix_ms(),
                    tiles_done: 0,
                    draining: false,
                    upload_key,
                    overflowed: AtomicBool::new(false),
                };
                // A worker blocked from a job stays blocked when it comes back.
                let who = conn.identity();
                let blocked: Vec<u64> = (st.jobs.iter())
                    .filter(|(_, j)| j.blocklist.is_blocked(&who))
                    .map(|(&n, _)| n)
                    .collect();
                for n in blocked {
                    let _ = st.sched.block(WorkerId(id), JobId(n));
                }
                svc.shared
                    .keys
                    .write()
                    .unwrap_or_else(|e| e.into_inner())
                    .insert(upload_key, id);
                st.departed
                    .returned(&conn.register.host_name, &conn.register.worker_name);
                st.workers.insert(id, conn);
                svc.shared.refresh_workers_view(&st);
                Ok::<u64, Status>(id)
            })
            .await?;
        update_health(&self.shared, &self.health).await;
        let svc = self.clone();
        tokio::spawn(async move {
            loop {
                match inbound.message().await {
                    Ok(Some(v1::WorkerMessage { msg: Some(m) })) => {
                        let t0 = std::time::Instant::now();
                        let kind = match &m {
                            v1::worker_message::Msg::Heartbeat(_) => "heartbeat",
                            _ => "other",
                        };
                        let rest = match m {
                            v1::worker_message::Msg::Heartbeat(h) => svc.on_heartbeat(id, h),
                            m => Some(m),
                        };
                        if let Some(m) = rest {
                            svc.off(move |svc| svc.on_worker_message(id, m)).await;
                        }
                        let seconds = t0.elapsed().as_secs_f64();
                        svc.shared.metrics.control_message(kind, seconds);
                    }
                    Ok(Some(_)) => {}
                    Ok(None) => break,
                    Err(e) => {
                        tracing::info!(worker = id, "control stream error: {e}");
                        break;
                    }
                }
            }
            svc.off(move |svc| svc.worker_gone(id)).await;
            update_health(&svc.shared, &svc.health).await;
        });
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    type FetchBlobStream = ChunkStream;

    async fn fetch_blob(
        &self,
        req: Request<v1::BlobRequest>,
    ) -> Result<Response<Self::FetchBlobStream>, Status> {
        let raw = req.into_inner().digest;
        let digest = digest_from(&raw, "digest")?;
        if !self.shared.blobs.has(&digest) {
            return Err(Status::not_found(format!("no blob {}", digest.to_hex())));
        }
        let path = self.shared.blobs.path(&digest);
        self.count_fetch(&path);
        Ok(Response::new(chunk_stream(path, raw)?))
    }

    async fn upload_tile(
        &self,
        req: Request<Streaming<v1::TileUpload>>,
    ) -> Result<Response<v1::TileAck>, Status> {
        let sender = self.sender(req.metadata())?;
        self.take_tile_upload(sender, req.into_inner()).await
    }

    async fn upload_records(
        &self,
        req: Request<Streaming<v1::RecordsUpload>>,
    ) -> Result<Response<v1::RecordsAck>, Status> {
        let sender = self.sender(req.metadata())?;
        self.take_records_upload(sender, req.into_inner()).await
    }
}

impl Svc {
    fn count_fetch(&self, path: &std::path::Path) {
        if let Ok(meta) = std::fs::metadata(path) {
            self.shared.metrics.blob_sent(meta.len());
        }
    }
}

/// A fresh `Registered.upload_key` for worker `id`: 32 bytes from the kernel's random
/// source, or, where there is none, a hash of what differs between registrations.
fn new_upload_key(id: u64) -> [u8; 32] {
    use std::io::Read;
    let mut key = [0u8; 32];
    let random = std::fs::File::open("/dev/urandom").and_then(|mut f| f.read_exact(&mut key));
    if random.is_err() {
        let mut h = blake3::Hasher::new();
        h.update(&id.to_le_bytes());
        h.update(&std::process::id().to_le_bytes());
        h.update(format!("{:?}", std::time::SystemTime::now()).as_bytes());
        h.update(format!("{:p}", &key).as_bytes());
        key = *h.finalize().as_bytes();
    }
    key
}
