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
use tokio_stream::wrappers::{ReceiverStream, UnboundedReceiverStream};
use tokio_stream::Stream;
use tonic::transport::server::TcpIncoming;
use tonic::{Request, Response, Status, Streaming};

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
                svc.shared.tick();
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
    let closer = shared.clone();
    let shutdown = async move {
        shutdown.await;
        tracing::info!("coordinator shutting down");
        // End the workers' control streams so the server can stop.
        let mut st = closer.lock();
        for w in st.workers.values_mut() {
            if let Some(tx) = w.tx.take() {
                let _ = tx.send(Ok(v1::CoordinatorMessage {
                    msg: Some(v1::coordinator_message::Msg::Drain(v1::Drain {
                        reason: "the coordinator is shutting down".into(),
                    })),
                }));
            }
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
    if let Some(m) = metrics {
        m.abort();
    }
    result.map_err(CoordinatorError::from)
}

#[derive(Clone)]
struct Auth {
    expected: Option<String>,
}

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        // A pathfarm client names its protocol; stock gRPC clients (grpcurl) need not.
        if let Some(v) = req.metadata().get(pathfarm_proto::PROTOCOL_HEADER) {
            let ours = pathfarm_proto::PROTOCOL_VERSION.to_string();
            if v.as_bytes() != ours.as_bytes() {
                return Err(Status::failed_precondition(format!(
                    "protocol version mismatch: client protocol {}, coordinator {ours}",
                    v.to_str().unwrap_or("?")
                )));
            }
        }
        let Some(expected) = &self.expected else {
            return Ok(req);
        };
        match req.metadata().get("authorization") {
            None => Err(Status::unauthenticated(
                "missing token: send metadata \"authorization: Bearer <token>\"",
            )),
            Some(v) if v.as_bytes() == expected.as_bytes() => Ok(req),
            Some(_) => Err(Status::unauthenticated("wrong token")),
        }
    }
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
    fn job_number(&self, id: &str) -> Result<u64, Status> {
        let n = parse_job(id).ok_or_else(|| Status::not_found(format!("no job {id:?}")))?;
        if self.shared.lock().jobs.contains_key(&n) {
            Ok(n)
        } else {
            Err(Status::not_found(format!("no job {id:?}")))
        }
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
            if seen.insert(digest) && !self.shared.blobs.has(&digest) {
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
        let header = chunked::header(&mut stream, "UploadBlob")
            .await
            .map_err(upload_status)?;
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
        if self.shared.blobs.has(&digest) {
            return done(true);
        }
        let mut upload = self
            .shared
            .blobs
            .begin(digest, header.size)
            .map_err(|e| Status::internal(format!("cannot store the blob: {e}")))?;
        chunked::data(&mut stream, header.size, |d| upload.write(d))
            .await
            .map_err(upload_status)?;
        upload.finish().map_err(super::bad)?;
        tracing::debug!(blob = %digest.to_hex(), size = header.size, "blob stored");
        done(false)
    }

    async fn submit_job(
        &self,
        req: Request<v1::SubmitJobRequest>,
    ) -> Result<Response<v1::SubmitJobResponse>, Status> {
        let req = req.into_inner();
        self.shared.advise_prefetch(&req);
        let shared = self.shared.clone();
        let (req, prepared) = tokio::task::spawn_blocking(move || {
            let p = shared.prepare(&req);
            (req, p)
        })
        .await
        .map_err(|e| Status::internal(format!("job validation panicked: {e}")))?;
        let prepared = match prepared {
            Ok(p) => p,
            Err(status) => {
                // Nothing of a refused submission is kept: its blobs go unless a job uses them.
                let mut st = self.shared.lock();
                let digests = req.bundle.iter().flat_map(|b| &b.files);
                let digests =
                    digests.filter_map(|f| <[u8; 32]>::try_from(f.digest.as_slice()).ok());
                st.garbage.extend(digests.map(crate::bundle::Digest));
                self.shared.collect_garbage(&mut st);
                return Err(status);
            }
        };
        let mut st = self.shared.lock();
        let n = st.next_job;
        st.next_job += 1;
        let record = JobRecord {
            request: Some(req),
            state: v1::JobState::Queued as i32,
            submitted_unix_ms: unix_ms(),
            width: prepared.width,
            height: prepared.height,
            ..Default::default()
        };
        if let Err(e) = self.shared.db.put(n, &record) {
            return Err(Status::internal(e));
        }
        let (watch, _) = watch::channel(status_of(n, &record, None));
        st.jobs.insert(
            n,
            Job {
                record,
                active: None,
                watch,
            },
        );
        tracing::info!(job = %job_name(n), "job submitted");
        self.shared.start_job(&mut st, n, prepared);
        self.shared.dispatch(&mut st);
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
        let mut rx = self.shared.lock().jobs[&n].watch.subscribe();
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
        let n = self.job_number(&req.get_ref().job_id)?;
        let st = self.shared.lock();
        let job = &st.jobs[&n];
        let request = job.record.request.clone().unwrap_or_default();
        Ok(Response::new(v1::GetJobResponse {
            status: Some(status_of(n, &job.record, job.active.as_ref())),
            settings: request.settings,
            root: request.bundle.map(|b| b.root).unwrap_or_default(),
            image: (job.record.width > 0).then_some(v1::Resolution {
                width: job.record.width,
                height: job.record.height,
            }),
        }))
    }

    async fn list_jobs(
        &self,
        req: Request<v1::ListJobsRequest>,
    ) -> Result<Response<v1::ListJobsResponse>, Status> {
        let req = req.into_inner();
        let st = self.shared.lock();
        let mut jobs: Vec<v1::JobStatus> = st
            .jobs
            .iter()
            .map(|(&n, j)| status_of(n, &j.record, j.active.as_ref()))
            .filter(|s| req.states.is_empty() || req.states.contains(&s.state))
            .collect();
        if req.limit > 0 && jobs.len() > req.limit as usize {
            jobs.drain(..jobs.len() - req.limit as usize);
        }
        Ok(Response::new(v1::ListJobsResponse { jobs }))
    }

    async fn cancel_job(
        &self,
        req: Request<v1::CancelJobRequest>,
    ) -> Result<Response<v1::CancelJobResponse>, Status> {
        let req = req.into_inner();
        let n = self.job_number(&req.job_id)?;
        let mut st = self.shared.lock();
        let reason = if req.reason.is_empty() {
            "cancelled".to_string()
        } else {
            format!("cancelled: {}", req.reason)
        };
        let cancelled = self
            .shared
            .end_job(&mut st, n, v1::JobState::Cancelled, reason);
        let job = &st.jobs[&n];
        Ok(Response::new(v1::CancelJobResponse {
            cancelled,
            status: Some(status_of(n, &job.record, job.active.as_ref())),
        }))
    }

    type DownloadResultStream = ChunkStream;

    async fn download_result(
        &self,
        req: Request<v1::DownloadResultRequest>,
    ) -> Result<Response<Self::DownloadResultStream>, Status> {
        let req = req.into_inner();
        let n = self.job_number(&req.job_id)?;
        let kind = v1::ResultKind::try_from(req.kind).unwrap_or(v1::ResultKind::Unspecified);
        let digest = {
            let st = self.shared.lock();
            let r = &st.jobs[&n].record;
            let d = match kind {
                v1::ResultKind::Unspecified => {
                    return Err(Status::invalid_argument("kind: unspecified"))
                }
                v1::ResultKind::Exr => r.exr.clone(),
                v1::ResultKind::PngPreview => r.png.clone(),
                v1::ResultKind::SdTree => r.tree.clone(),
            };
            // while the job runs, the preview of the image so far
            let running_preview = st.jobs[&n].active.as_ref().and_then(|a| a.preview);
            if let (v1::ResultKind::PngPreview, Some(p), false) =
                (kind, running_preview, r.state == v1::JobState::Done as i32)
            {
                p.0.to_vec()
            } else if r.state != v1::JobState::Done as i32 || d.is_empty() {
                return Err(Status::failed_precondition(format!(
                    "{}: the result {kind:?} is available once the job is DONE (a PNG \
                     preview once its first iteration is done)",
                    req.job_id
                )));
            } else {
                d
            }
        };
        let path = self.shared.blobs.path(&digest_from(&digest, "result")?);
        self.count_fetch(&path);
        Ok(Response::new(chunk_stream(path, digest)?))
    }

    async fn list_workers(
        &self,
        _req: Request<v1::ListWorkersRequest>,
    ) -> Result<Response<v1::ListWorkersResponse>, Status> {
        let st = self.shared.lock();
        let workers = st
            .workers
            .iter()
            .map(|(&id, w)| {
                let mut lease_ids: Vec<u64> = st
                    .leases
                    .iter()
                    .filter(|(_, l)| l.worker == WorkerId(id) && !l.done && w.tx.is_some())
                    .map(|(&lease, _)| lease)
                    .collect();
                lease_ids.sort_unstable();
                v1::WorkerInfo {
                    worker_id: id,
                    host_name: w.register.host_name.clone(),
                    worker_name: w.register.worker_name.clone(),
                    threads: w.register.threads,
                    tiles_done: w.tiles_done,
                    last_heartbeat_unix_ms: w.last_unix_ms,
                    lease_ids,
                    build_id: w.register.build_id.clone(),
                    protocol_version: w.register.protocol_version,
                    draining: w.draining,
                    registered_unix_ms: w.registered_unix_ms,
                    connected: w.tx.is_some(),
                }
            })
            .collect();
        Ok(Response::new(v1::ListWorkersResponse { workers }))
    }
}

fn msg(m: v1::coordinator_message::Msg) -> Result<v1::CoordinatorMessage, Status> {
    Ok(v1::CoordinatorMessage { msg: Some(m) })
}

fn ack(accepted: bool, reason: v1::TileRejectReason, detail: String) -> Response<v1::TileAck> {
    Response::new(v1::TileAck {
        accepted,
        reject_reason: reason as i32,
        detail,
        duplicate: false,
    })
}

fn corrupt(detail: impl Into<String>) -> Result<Response<v1::TileAck>, Status> {
    Ok(ack(false, v1::TileRejectReason::Corrupt, detail.into()))
}

impl Svc {
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
                let active: Vec<LeaseId> = h.active_lease_ids.iter().map(|&l| LeaseId(l)).collect();
                if let Ok(stale) = st.sched.heartbeat(worker, &active, now) {
                    for lease in stale {
                        send_cancel(&st, worker, lease, "not this worker's lease any more");
                    }
                }
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
                let job = st.leases.get(&f.lease_id).map(|l| l.key.job.0);
                match st
                    .sched
                    .fail_lease(worker, LeaseId(f.lease_id), &f.reason, now)
                {
                    Ok(events) => {
                        shared.handle_events(&mut st, events);
                        if let (true, Some(n)) = (f.fatal, job) {
                            shared.fail_job(
                                &mut st,
                                n,
                                format!("worker {id} failed lease {}: {}", f.lease_id, f.reason),
                            );
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
        if let Some(w) = st.workers.get_mut(&id) {
            w.tx = None;
            w.credits = 0;
        }
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
    type ControlStream = UnboundedReceiverStream<Result<v1::CoordinatorMessage, Status>>;

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
        let (tx, rx) = mpsc::unbounded_channel();
        let ours = crate::build::build_id();
        let refusal = if register.protocol_version != pathfarm_proto::PROTOCOL_VERSION {
            Some(format!(
                "protocol version mismatch: worker protocol {}, coordinator {}",
                register.protocol_version,
                pathfarm_proto::PROTOCOL_VERSION
            ))
        } else if register.build_id != ours {
            Some(format!(
                "build mismatch: worker build {}, coordinator build {ours} (different builds \
                 may round differently, and tiles must be bit-exact)",
                register.build_id
            ))
        } else {
            None
        };
        if let Some(reason) = refusal {
            tracing::warn!(host = %register.host_name, "worker refused: {reason}");
            let _ = tx.send(msg(Msg::Refused(v1::Refused {
                reason: reason.clone(),
                supported_protocol_versions: vec![pathfarm_proto::PROTOCOL_VERSION],
                required_build_id: ours.to_string(),
            })));
            let _ = tx.send(Err(Status::failed_precondition(reason)));
            return Ok(Response::new(UnboundedReceiverStream::new(rx)));
        }
        let id = {
            let mut st = self.shared.lock();
            let id = st.next_worker;
            st.next_worker += 1;
            let now = self.shared.now();
            if let Err(e) = st
                .sched
                .register_worker(WorkerId(id), register.threads.max(1), now)
            {
                return Err(Status::internal(e.to_string()));
            }
            let sc = &self.shared.cfg.scheduler;
            let heartbeat = (sc.heartbeat_timeout.as_millis() / 3).clamp(100, 5000) as u32;
            let _ = tx.send(msg(Msg::Registered(v1::Registered {
                worker_id: id,
                heartbeat_interval_ms: heartbeat,
                lease_timeout_ms: sc.lease_timeout.as_millis().min(u32::MAX as u128) as u32,
                protocol_version: pathfarm_proto::PROTOCOL_VERSION,
                build_id: ours.to_string(),
            })));
            tracing::info!(
                worker = id,
                host = %register.host_name,
                name = %register.worker_name,
                threads = register.threads,
                "worker registered"
            );
            st.workers.insert(
                id,
                WorkerConn {
                    tx: Some(tx),
                    credits: 0,
                    register,
                    registered_unix_ms: unix_ms(),
                    last_unix_ms: unix_ms(),
                    tiles_done: 0,
                    draining: false,
                },
            );
            id
        };
        update_health(&self.shared, &self.health).await;
        let svc = self.clone();
        tokio::spawn(async move {
            loop {
                match inbound.message().await {
                    Ok(Some(v1::WorkerMessage { msg: Some(m) })) => svc.on_worker_message(id, m),
                    Ok(Some(_)) => {}
                    Ok(None) => break,
                    Err(e) => {
                        tracing::info!(worker = id, "control stream error: {e}");
                        break;
                    }
                }
            }
            svc.worker_gone(id);
            update_health(&svc.shared, &svc.health).await;
        });
        Ok(Response::new(UnboundedReceiverStream::new(rx)))
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
        let mut stream = req.into_inner();
        let header = match chunked::header(&mut stream, "UploadTile").await {
            Ok(h) => h,
            Err(e) => return upload_refused(e, corrupt_ack),
        };
        let received = std::time::Instant::now();
        let total = match payload_size(&header) {
            Ok(t) => t,
            Err(detail) => return corrupt(detail),
        };
        let bytes = match chunked::data_to_vec(&mut stream, total).await {
            Ok(b) => b,
            Err(e) => return upload_refused(e, corrupt_ack),
        };
        let receive_s = received.elapsed().as_secs_f64();
        let ack = self.upload_tile_inner(header, bytes, receive_s);
        let accepted = matches!(&ack, Ok(a) if a.get_ref().accepted);
        self.shared.metrics.tile_upload(total, accepted);
        ack
    }

    async fn upload_records(
        &self,
        req: Request<Streaming<v1::RecordsUpload>>,
    ) -> Result<Response<v1::RecordsAck>, Status> {
        let mut stream = req.into_inner();
        let refused = |d: String| records_ack(false, d).into_inner();
        let header = match chunked::header(&mut stream, "UploadRecords").await {
            Ok(h) => h,
            Err(e) => return upload_refused(e, refused),
        };
        if header.size > 1 << 32 {
            return Ok(records_ack(false, "records of over 4 GiB"));
        }
        let bytes = match chunked::data_to_vec(&mut stream, header.size).await {
            Ok(b) => b,
            Err(e) => return upload_refused(e, refused),
        };
        self.shared.metrics.records_upload(bytes.len() as u64);
        Ok(self.take_records(header, bytes))
    }
}

fn records_ack(accepted: bool, detail: impl Into<String>) -> Response<v1::RecordsAck> {
    Response::new(v1::RecordsAck {
        accepted,
        detail: detail.into(),
    })
}

/// A malformed upload as an `InvalidArgument` status.
fn upload_status(e: UploadError) -> Status {
    match e {
        UploadError::Transport(s) => s,
        UploadError::Malformed(detail) => bad(detail),
    }
}

/// A malformed upload answered in the RPC's own reply (`ack` makes it from the detail); a
/// broken stream as its status.
fn upload_refused<T>(e: UploadError, ack: impl FnOnce(String) -> T) -> Result<Response<T>, Status> {
    match e {
        UploadError::Transport(s) => Err(s),
        UploadError::Malformed(detail) => Ok(Response::new(ack(detail))),
    }
}

impl Svc {
    /// A holder's answer to FlushRecords: its records added to the session (decoded off
    /// the lock), or, if it lost them, the job rolled back.
    fn take_records(&self, header: v1::RecordsHeader, bytes: Vec<u8>) -> Response<v1::RecordsAck> {
        let Some(n) = parse_job(&header.job_id) else {
            return records_ack(false, format!("no job {:?}", header.job_id));
        };
        let decode_start = std::time::Instant::now();
        let records = match header.lost {
            true => None,
            false => {
                if bytes.len() as u64 != header.size
                    || digest_of(&bytes).0.as_slice() != header.digest.as_slice()
                {
                    return records_ack(false, "size or digest does not match the records");
                }
                match IterationStats::decode(&bytes) {
                    Ok(r) => Some(r),
                    Err(e) => return records_ack(false, format!("records: {e}")),
                }
            }
        };
        // Decoding is timed apart from waiting for the state lock.
        let decode_s = decode_start.elapsed().as_secs_f64();
        let shared = &self.shared;
        let mut st = shared.lock();
        let st = &mut *st;
        let w = header.worker_id;
        let Some(a) = st.jobs.get_mut(&n).and_then(|j| j.active.as_mut()) else {
            return records_ack(false, "the job is not running");
        };
        let current = a.records_epoch == header.records_epoch
            && a.tree_digest.map(|(_, d)| d.0.to_vec()) == Some(header.tree_digest.clone());
        let asked = a.collecting.as_ref().is_some_and(|c| c.contains(&w));
        if !current || !asked {
            return records_ack(
                false,
                "records not asked for (another epoch, version or worker)",
            );
        }
        let Some(records) = records else {
            let why = format!("worker {w} lost the records it held");
            shared.roll_back(st, n, &why);
            return records_ack(true, "");
        };
        let merge_start = std::time::Instant::now();
        if let Err(e) = a.session.add_records(&records) {
            let reason = format!("worker {w}'s records were refused by the session: {e}");
            shared.fail_job(st, n, reason);
            return records_ack(false, e.to_string());
        }
        let merge_s = merge_start.elapsed().as_secs_f64();
        a.records_ledger.add(bytes.len() as u64, decode_s, merge_s);
        let left = a.collecting.as_mut().expect("asked");
        left.remove(&w);
        tracing::debug!(job = %job_name(n), worker = w, bytes = bytes.len(), left = left.len(), "records in");
        if left.is_empty() && shared.records_in(st, n) {
            shared.drive(st, n);
            shared.dispatch(st);
        }
        records_ack(true, "")
    }
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

/// A tile of an upload, checked against its lease and decoded.
struct Accepting {
    lease: LeaseId,
    index: usize,
    out: TileOutput,
    counters: v1::TileCounters,
}

impl Svc {
    fn count_fetch(&self, path: &std::path::Path) {
        if let Ok(meta) = std::fs::metadata(path) {
            self.shared.metrics.blob_sent(meta.len());
        }
    }

    fn upload_tile_inner(
        &self,
        header: v1::TileHeader,
        bytes: Vec<u8>,
        receive_s: f64,
    ) -> Result<Response<v1::TileAck>, Status> {
        let decode_start = std::time::Instant::now();
        let total = bytes.len() as u64;
        let (mut pixels, stats_bytes) = bytes.split_at(total as usize - header.stats_size as usize);
        let mut parts = Vec::with_capacity(header.tiles.len());
        for t in &header.tiles {
            let (mine, rest) = pixels.split_at(t.pixels_size as usize);
            if digest_of(mine).0.as_slice() != t.pixels_digest.as_slice() {
                return corrupt(format!(
                    "lease {}: pixels_digest does not match",
                    t.lease_id
                ));
            }
            parts.push(mine);
            pixels = rest;
        }
        if digest_of(stats_bytes).0.as_slice() != header.stats_digest.as_slice() {
            return corrupt("stats_digest does not match the statistics payload");
        }
        let stats = if stats_bytes.is_empty() {
            None
        } else {
            match IterationStats::decode(stats_bytes) {
                Ok(s) => Some(s),
                Err(e) => return corrupt(format!("statistics: {e}")),
            }
        };
        // Decoding is timed apart from waiting for the state lock (another upload's merge, a
        // unit's end, a checkpoint): the ledger's decode column is CPU, not queueing.
        let mut decode_s = decode_start.elapsed().as_secs_f64();
        let shared = &self.shared;
        let mut st = shared.lock();
        let pixels_start = std::time::Instant::now();
        let (n, worker, unit, tiles) = match self.check_tiles(&st, &header, &parts) {
            Ok(checked) => checked,
            Err(a) => return Ok(self.refuse(&mut st, &header, Response::new(a))),
        };
        decode_s += pixels_start.elapsed().as_secs_f64();
        let now = shared.now();
        let ids: Vec<LeaseId> = tiles.iter().map(|t| t.lease).collect();
        let completions = match st.sched.complete_all(worker, &ids, now) {
            Ok(c) => c,
            Err(Rejection::Duplicate) => {
                let mut a = ack(true, v1::TileRejectReason::Unspecified, String::new());
                a.get_mut().duplicate = true;
                return Ok(a);
            }
            Err(r) => {
                let reason = match r {
                    Rejection::UnknownLease => v1::TileRejectReason::UnknownLease,
                    Rejection::Expired => v1::TileRejectReason::Expired,
                    _ => v1::TileRejectReason::Superseded,
                };
                tracing::info!(job = %job_name(n), leases = ?ids, "tiles rejected: {r}");
                return Ok(self.refuse(&mut st, &header, ack(false, reason, r.to_string())));
            }
        };
        let unit_done = completions.last().is_some_and(|c| c.unit_done);
        let times = TileTimes {
            receive_s,
            decode_s,
            bytes: total,
        };
        let job = st.jobs.get_mut(&n).expect("checked");
        let a = job.active.as_mut().expect("checked");
        let secs = a.clock.elapsed().as_secs_f64();
        let merge_start = std::time::Instant::now();
        let spec = a.flight(unit).expect("checked").spec;
        let outs: Vec<(usize, &TileOutput)> = tiles.iter().map(|t| (t.index, &t.out)).collect();
        if let Err(e) = a.session.add_tiles(unit, &outs, stats.as_ref(), secs) {
            let reason = format!("tiles {ids:?} rejected by the session: {e}");
            shared.fail_job(&mut st, n, reason);
            return Ok(ack(false, v1::TileRejectReason::Superseded, e.to_string()));
        }
        if spec.record() {
            // The tiles' quadtree records stay in the worker's tree copy until asked for.
            a.holders.insert(worker.0);
        }
        let merge_s = merge_start.elapsed().as_secs_f64();
        let mut samples = 0;
        for t in &tiles {
            let s = t.out.region.pixels() as u64 * spec.unit_spp();
            a.cost
                .record(t.out.region, t.counters.render_seconds / s.max(1) as f64);
            samples += s;
        }
        let flight = a.flights.iter_mut().find(|f| f.spec.unit == spec.unit);
        let ledger = &mut flight.expect("checked").ledger;
        let counters: Vec<&v1::TileCounters> = tiles.iter().map(|t| &t.counters).collect();
        if unit_done {
            ledger.end_s = merge_s;
            ledger.upload(&counters, &times, 0.0);
        } else {
            ledger.upload(&counters, &times, merge_s);
        }
        job.record.samples_done += samples;
        if let Some(w) = st.workers.get_mut(&worker.0) {
            w.tiles_done += tiles.len() as u64;
        }
        tracing::debug!(job = %job_name(n), leases = ?ids, unit, "tiles accepted");
        for id in &ids {
            if let Some(l) = st.leases.get_mut(&id.0) {
                l.done = true;
            }
        }
        if unit_done {
            shared.end_unit(&mut st, n, spec.unit);
        }
        shared.publish_status(&st, n);
        shared.dispatch(&mut st);
        Ok(ack(true, v1::TileRejectReason::Unspecified, String::new()))
    }

    /// Checks every tile of an upload against its lease (one worker, the header's job and
    /// unit, a unit still in flight, the lease's region) and decodes its pixels; the answer
    /// to give when one does not pass.
    fn check_tiles(
        &self,
        st: &State,
        header: &v1::TileHeader,
        parts: &[&[u8]],
    ) -> Result<(u64, WorkerId, u64, Vec<Accepting>), v1::TileAck> {
        let mut out = Vec::with_capacity(parts.len());
        let mut owner: Option<(WorkerId, TaskKey)> = None;
        for (t, bytes) in header.tiles.iter().zip(parts) {
            let lease_id = t.lease_id;
            let Some(info) = st.leases.get(&lease_id).copied() else {
                return Err(ack(
                    false,
                    v1::TileRejectReason::UnknownLease,
                    format!("lease {lease_id} is not known"),
                )
                .into_inner());
            };
            let (worker, first) = *owner.get_or_insert((info.worker, info.key));
            let n = info.key.job.0;
            if info.worker != worker
                || info.key.job != first.job
                || info.key.unit != first.unit
                || header.job_id != job_name(n)
                || header.unit != info.key.unit
            {
                return Err(corrupt_ack(format!(
                    "lease {lease_id} ({}) does not belong with the upload's job {} unit {} \
                     and first lease ({first})",
                    info.key, header.job_id, header.unit
                )));
            }
            let current = st
                .jobs
                .get(&n)
                .and_then(|j| j.active.as_ref())
                .and_then(|a| Some((a.flight(info.key.unit)?.spec, a)))
                .and_then(|(spec, a)| Some((spec, a.session.tiles_of(info.key.unit)?)))
                .and_then(|(spec, tiles)| Some((spec, *tiles.get(info.key.tile as usize)?)));
            let Some((spec, region)) = current else {
                return Err(ack(
                    false,
                    v1::TileRejectReason::Superseded,
                    format!("unit {} of {} is over", info.key.unit, job_name(n)),
                )
                .into_inner());
            };
            if t.tile != Some(codec::region_to_proto(region)) {
                return Err(corrupt_ack(format!(
                    "the tile of lease {lease_id} is not its lease's ({})",
                    info.key
                )));
            }
            let pixels = codec::decode_tile_pixels(bytes, &spec, region)
                .map_err(|e| corrupt_ack(format!("lease {lease_id}: pixels: {e}")))?;
            let c = t.counters.unwrap_or_default();
            out.push(Accepting {
                lease: LeaseId(lease_id),
                index: info.key.tile as usize,
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
        let (worker, key) = owner.expect("an upload has at least one tile");
        Ok((key.job.0, worker, key.unit, out))
    }

    /// Answers a rejected upload: the worker keeps nothing of it, so the leases it names
    /// that were still valid go back to the queue now (without counting an attempt) instead
    /// of waiting out their deadlines.
    fn refuse(
        &self,
        st: &mut State,
        header: &v1::TileHeader,
        answer: Response<v1::TileAck>,
    ) -> Response<v1::TileAck> {
        let now = self.shared.now();
        let known = |t: &v1::UploadedTile| st.leases.get(&t.lease_id).map(|i| i.worker);
        // The upload's owner is the holder of its first known lease; another worker's
        // leases named in it (a corrupt upload) are left alone.
        let Some(owner) = header.tiles.iter().find_map(known) else {
            return answer;
        };
        let ids: Vec<LeaseId> = header
            .tiles
            .iter()
            .filter(|t| known(t) == Some(owner))
            .map(|t| LeaseId(t.lease_id))
            .collect();
        let returned = st.sched.hand_back(owner, &ids, now).map_or(0, |k| k.len());
        if returned > 0 {
            tracing::info!(job = %header.job_id, returned, "valid leases of a rejected upload returned");
            self.shared.dispatch(st);
        }
        answer
    }
}

fn corrupt_ack(detail: String) -> v1::TileAck {
    ack(false, v1::TileRejectReason::Corrupt, detail).into_inner()
}
