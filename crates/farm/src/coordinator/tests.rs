//! Coordinator tests over real gRPC on a loopback port.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};

use pathfarm_proto::v1::jobs_client::JobsClient;
use pathfarm_proto::v1::workers_client::WorkersClient;
use pathfarm_proto::v1::{self};
use tokio::sync::oneshot;
use tonic::transport::Channel;
use tonic::{Code, Request};

use super::*;
use crate::bundle::digest_of;
use crate::driver::Coverage;

/// Job `id`'s EXR, downloaded.
async fn download_exr(jobs: &mut JobsClient<Channel>, id: &str) -> Vec<u8> {
    let mut s = jobs
        .download_result(v1::DownloadResultRequest {
            job_id: id.to_string(),
            kind: v1::ResultKind::Exr as i32,
        })
        .await
        .unwrap()
        .into_inner();
    let mut bytes = Vec::new();
    while let Some(c) = s.message().await.unwrap() {
        if let Some(v1::data_chunk::Part::Data(d)) = c.part {
            bytes.extend_from_slice(&d);
        }
    }
    bytes
}

/// Every job the coordinator lists.
async fn list_jobs(jobs: &mut JobsClient<Channel>) -> Vec<v1::JobStatus> {
    jobs.list_jobs(v1::ListJobsRequest::default())
        .await
        .unwrap()
        .into_inner()
        .jobs
}

/// A 16x16 guided_path scene at 8 spp: a floor lit by a small area light above it.
pub(super) const SCENE: &str = include_str!("testdata/lit-floor.xml");

pub(super) fn temp_dir(what: &str) -> PathBuf {
    static N: AtomicU64 = AtomicU64::new(0);
    let n = N.fetch_add(1, Ordering::Relaxed);
    let dir =
        std::env::temp_dir().join(format!("pathfarm-coord-{what}-{}-{n}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

pub(super) fn config(data: PathBuf, token: Option<&str>) -> CoordinatorConfig {
    CoordinatorConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: data,
        token: token.map(str::to_string),
        tls: None,
        metrics: None,
        http: None,
        viewer_token: None,
        limits: Limits::default(),
        bundle_limits: BundleLimits::default(),
        scheduler: SchedulerConfig::default(),
        resources: Resources::default(),
        job_logs: Default::default(),
        checkpoint_interval: Duration::ZERO,
        default_tile: Some(8),
    }
}

/// `msg` as a request carrying a worker's upload key (`Registered.upload_key`).
pub(super) fn keyed<T>(msg: T, key: &[u8]) -> Request<T> {
    let mut req = Request::new(msg);
    let hex: String = key.iter().map(|b| format!("{b:02x}")).collect();
    req.metadata_mut()
        .insert(pathfarm_proto::WORKER_KEY_HEADER, hex.parse().unwrap());
    req
}

pub(super) struct Running {
    addr: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<Result<(), CoordinatorError>>,
}

impl Running {
    pub(super) async fn start(cfg: CoordinatorConfig) -> Running {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(serve_with_listener(cfg, listener, async move {
            let _ = rx.await;
        }));
        Running {
            addr,
            stop: Some(tx),
            task,
        }
    }

    pub(super) async fn channel(&self) -> Channel {
        Channel::from_shared(format!("http://{}", self.addr))
            .unwrap()
            .connect()
            .await
            .unwrap()
    }

    pub(super) async fn stop(mut self) {
        let _ = self.stop.take().unwrap().send(());
        self.task.await.unwrap().unwrap();
    }
}

/// A coordinator without a token over a fresh data directory (named for `what`), and a
/// jobs client connected to it.
pub(super) async fn start_open(what: &str) -> (PathBuf, Running, JobsClient<Channel>) {
    let data = temp_dir(what);
    let c = Running::start(config(data.clone(), None)).await;
    let jobs = JobsClient::new(c.channel().await);
    (data, c, jobs)
}

/// Opens a control stream that sends what `rx` receives; returns it with the coordinator's
/// first answer (Registered or Refused).
async fn open_control(
    workers: &mut WorkersClient<Channel>,
    rx: tokio::sync::mpsc::Receiver<v1::WorkerMessage>,
) -> (
    tonic::Streaming<v1::CoordinatorMessage>,
    v1::CoordinatorMessage,
) {
    let mut inbound = workers
        .control(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let first = inbound.message().await.unwrap().unwrap();
    (inbound, first)
}

fn authed<T>(msg: T, token: Option<&str>) -> Request<T> {
    let mut req = Request::new(msg);
    if let Some(t) = token {
        req.metadata_mut()
            .insert("authorization", format!("Bearer {t}").parse().unwrap());
    }
    req
}

pub(super) async fn upload(
    jobs: &mut JobsClient<Channel>,
    bytes: &[u8],
    token: Option<&str>,
) -> v1::BundleFile {
    let digest = digest_of(bytes);
    let mut parts = vec![v1::BlobChunk {
        part: Some(v1::blob_chunk::Part::Header(v1::BlobHeader {
            digest: digest.0.to_vec(),
            size: bytes.len() as u64,
        })),
    }];
    for c in bytes.chunks(100) {
        parts.push(v1::BlobChunk {
            part: Some(v1::blob_chunk::Part::Data(c.to_vec())),
        });
    }
    let req = authed(tokio_stream::iter(parts), token);
    jobs.upload_blob(req).await.unwrap();
    v1::BundleFile {
        path: "scene.xml".into(),
        digest: digest.0.to_vec(),
        size: bytes.len() as u64,
    }
}

/// Uploads [`SCENE`] and submits it as [`submit_request`] does; returns the new job's id.
async fn submit_scene(jobs: &mut JobsClient<Channel>) -> String {
    let file = upload(jobs, SCENE.as_bytes(), None).await;
    jobs.submit_job(submit_request(file))
        .await
        .unwrap()
        .into_inner()
        .job_id
}

pub(super) fn submit_request(file: v1::BundleFile) -> v1::SubmitJobRequest {
    v1::SubmitJobRequest {
        bundle: Some(v1::Bundle {
            root: "scene.xml".into(),
            files: vec![file],
        }),
        settings: Some(v1::JobSettings {
            budget: Some(v1::job_settings::Budget::Spp(4)),
            ..Default::default()
        }),
        priority: 0,
        name: "test".into(),
        batch: String::new(),
    }
}

#[tokio::test]
async fn wrong_or_missing_token_is_unauthenticated() {
    let data = temp_dir("auth");
    let c = Running::start(config(data.clone(), Some("s3cret"))).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let list = || v1::ListJobsRequest::default();
    let e = jobs.list_jobs(authed(list(), None)).await.unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);
    assert!(e.message().contains("missing"), "{}", e.message());
    let e = jobs
        .list_jobs(authed(list(), Some("nope")))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);
    assert!(e.message().contains("wrong") && !e.message().contains("nope"));
    jobs.list_jobs(authed(list(), Some("s3cret")))
        .await
        .unwrap();
    let mut workers = WorkersClient::new(ch);
    let e = workers
        .fetch_blob(authed(
            v1::BlobRequest {
                digest: vec![0; 32],
            },
            Some("bad"),
        ))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn malformed_scene_is_invalid_argument_and_stores_nothing() {
    let (data, c, mut jobs) = start_open("bad").await;
    let file = upload(&mut jobs, b"<scene version=\"3.0.0\"><shape", None).await;
    let e = jobs.submit_job(submit_request(file)).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{}", e.message());
    assert!(e.message().contains("scene.xml"), "{}", e.message());
    // a path job is refused too
    let path_scene = SCENE.replace("guided_path", "path");
    let file = upload(&mut jobs, path_scene.as_bytes(), None).await;
    let e = jobs.submit_job(submit_request(file)).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(
        e.message().contains("guided_path jobs only"),
        "{}",
        e.message()
    );
    assert!(list_jobs(&mut jobs).await.is_empty());
    let tmp: Vec<_> = std::fs::read_dir(data.join("tmp")).unwrap().collect();
    assert!(tmp.is_empty(), "temporary files left: {tmp:?}");
    c.stop().await;
    // nothing persisted either
    let db = db::Db::open(&data.join("jobs.redb")).unwrap();
    assert!(db.all().unwrap().is_empty());
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn corrupt_blob_upload_is_rejected_and_not_stored() {
    let (data, c, mut jobs) = start_open("blob").await;
    let digest = digest_of(b"hello");
    let parts = vec![
        v1::BlobChunk {
            part: Some(v1::blob_chunk::Part::Header(v1::BlobHeader {
                digest: digest.0.to_vec(),
                size: 5,
            })),
        },
        v1::BlobChunk {
            part: Some(v1::blob_chunk::Part::Data(b"hellx".to_vec())),
        },
    ];
    let e = jobs
        .upload_blob(tokio_stream::iter(parts))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    let missing = jobs
        .find_missing_blobs(v1::FindMissingBlobsRequest {
            digests: vec![digest.0.to_vec()],
            bundle: None,
        })
        .await
        .unwrap()
        .into_inner()
        .missing;
    assert_eq!(missing.len(), 1);
    assert_eq!(std::fs::read_dir(data.join("blobs")).unwrap().count(), 0);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn worker_with_other_protocol_is_refused() {
    let data = temp_dir("refuse");
    let c = Running::start(config(data.clone(), None)).await;
    let mut workers = WorkersClient::new(c.channel().await);
    let register = v1::WorkerMessage {
        msg: Some(v1::worker_message::Msg::Register(v1::Register {
            protocol_version: pathfarm_proto::PROTOCOL_VERSION + 1,
            build_id: crate::build::build_id().to_string(),
            threads: 1,
            host_name: "test".into(),
            worker_name: String::new(),
        })),
    };
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(register).await.unwrap();
    let (mut inbound, first) = open_control(&mut workers, rx).await;
    let Some(v1::coordinator_message::Msg::Refused(r)) = first.msg else {
        panic!("expected Refused, got {first:?}");
    };
    assert!(
        r.reason.contains(&format!(
            "worker protocol {}",
            pathfarm_proto::PROTOCOL_VERSION + 1
        )) && r
            .reason
            .contains(&format!("coordinator {}", pathfarm_proto::PROTOCOL_VERSION)),
        "{}",
        r.reason
    );
    let end = inbound.message().await.unwrap_err();
    assert_eq!(end.code(), Code::FailedPrecondition);
    drop(tx);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn submitted_job_is_queued_persisted_and_restarted() {
    let (data, c, mut jobs) = start_open("submit").await;
    let id = submit_scene(&mut jobs).await;
    assert_eq!(id, "job-1");
    // The session is built in the background once the job is admitted.
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    let (got, status) = loop {
        let got = jobs
            .get_job(v1::GetJobRequest { job_id: id.clone() })
            .await
            .unwrap()
            .into_inner();
        let status = got.status.clone().unwrap();
        if status.tiles_total > 0 || std::time::Instant::now() > deadline {
            break (got, status);
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(status.state, v1::JobState::Queued as i32);
    assert_eq!(status.tiles_total, 4, "16x16 in 8-pixel tiles");
    assert_eq!(
        got.image,
        Some(v1::Resolution {
            width: 16,
            height: 16
        })
    );
    let e = jobs
        .download_result(v1::DownloadResultRequest {
            job_id: id.clone(),
            kind: v1::ResultKind::Exr as i32,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    let e = jobs
        .get_job(v1::GetJobRequest {
            job_id: "job-99".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    c.stop().await;

    // After a restart the queued job is back (restarted from the beginning); a second job
    // gets a fresh id.
    let c = Running::start(config(data.clone(), None)).await;
    let mut jobs = JobsClient::new(c.channel().await);
    let listed = list_jobs(&mut jobs).await;
    assert_eq!(listed.len(), 1);
    assert_eq!(listed[0].job_id, "job-1");
    assert_eq!(listed[0].state, v1::JobState::Queued as i32);
    let cancelled = jobs
        .cancel_job(v1::CancelJobRequest {
            job_id: "job-1".into(),
            reason: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(cancelled.cancelled);
    assert_eq!(
        cancelled.status.unwrap().state,
        v1::JobState::Cancelled as i32
    );
    c.stop().await;
    let c = Running::start(config(data.clone(), None)).await;
    let mut jobs = JobsClient::new(c.channel().await);
    let listed = list_jobs(&mut jobs).await;
    assert_eq!(listed[0].state, v1::JobState::Cancelled as i32);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

async fn fetch(workers: &mut WorkersClient<Channel>, digest: &[u8]) -> Vec<u8> {
    let mut s = workers
        .fetch_blob(v1::BlobRequest {
            digest: digest.to_vec(),
        })
        .await
        .unwrap()
        .into_inner();
    let mut out = Vec::new();
    let Some(v1::data_chunk::Part::Header(h)) = s.message().await.unwrap().unwrap().part else {
        panic!("header first");
    };
    while let Some(c) = s.message().await.unwrap() {
        let Some(v1::data_chunk::Part::Data(d)) = c.part else {
            panic!("data after the header");
        };
        out.extend_from_slice(&d);
    }
    assert_eq!(out.len() as u64, h.total_size);
    assert_eq!(digest_of(&out).0.as_slice(), digest);
    out
}

/// A minimal in-test worker over the real gRPC API renders a whole job with the real
/// `render_unit`; the downloaded EXR equals the one-process render's, bit for bit.
#[tokio::test]
async fn fake_worker_renders_a_job_bit_identical_to_one_process() {
    use pathfarm_render::pass::{render_unit, UnitInputs};
    let data = temp_dir("e2e");
    let c = Running::start(config(data.clone(), None)).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let mut workers = WorkersClient::new(ch);
    let id = submit_scene(&mut jobs).await;
    let mut watch = jobs
        .watch_job(v1::WatchJobRequest { job_id: id.clone() })
        .await
        .unwrap()
        .into_inner();
    let first = watch.message().await.unwrap().unwrap();
    assert_eq!(first.state, v1::JobState::Queued as i32);

    let send = |m| v1::WorkerMessage { msg: Some(m) };
    use v1::worker_message::Msg as W;
    let (tx, mut inbound, worker_id, key) = fake_worker(&mut workers, 2).await;
    // a registered worker makes the services SERVING
    let mut health = tonic_health::pb::health_client::HealthClient::new(c.channel().await);
    let check = tonic_health::pb::HealthCheckRequest {
        service: pathfarm_proto::JOBS_SERVICE.into(),
    };
    let serving = tonic_health::pb::health_check_response::ServingStatus::Serving as i32;
    let mut ok = false;
    for _ in 0..50 {
        if health
            .check(check.clone())
            .await
            .unwrap()
            .into_inner()
            .status
            == serving
        {
            ok = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(ok, "health SERVING once a worker registered");
    let dir = temp_dir("e2e-worker");
    let mut scene: Option<Scene> = None;
    let mut tiles = 0;
    let (mut saw_preview, mut saw_eta) = (false, false);
    // the quadtree records of hold_records leases, kept until FlushRecords
    // (and the leases they are of)
    let mut held: Option<(pathfarm_guide::IterationStats, Coverage)> = None;
    let mut flushes = 0;
    loop {
        let m = inbound.message().await.unwrap().unwrap();
        if let Some(v1::coordinator_message::Msg::FlushRecords(f)) = &m.msg {
            let (records, covered) = held.take().expect("records held when asked for");
            let (bytes, who) = (records.encode(), (worker_id, &key[..]));
            let ack = upload_records(&mut workers, who, f, (&bytes, &covered)).await;
            assert!(ack.accepted, "{ack:?}");
            flushes += 1;
            continue;
        }
        let Some(v1::coordinator_message::Msg::LeaseOffer(offer)) = m.msg else {
            continue;
        };
        let lease = offer.lease.unwrap();
        assert_eq!(lease.job_id, id);
        if scene.is_none() {
            let Some(v1::lease::Scene::Bundle(b)) = &lease.scene else {
                panic!("inline bundle");
            };
            for f in &b.files {
                std::fs::write(dir.join(&f.path), fetch(&mut workers, &f.digest).await).unwrap();
            }
            let settings = lease.settings.as_ref().unwrap();
            let defs: Vec<(String, String)> = settings
                .defines
                .iter()
                .map(|d| (d.name.clone(), d.value.clone()))
                .collect();
            let desc = pathfarm_scene::load_scene(&dir.join(&b.root), &defs).unwrap();
            scene = Some(Scene::build(&desc).unwrap());
        }
        let scene = scene.as_ref().unwrap();
        let params = scene.guided.clone().unwrap();
        let pass = lease.pass.clone().unwrap();
        let spec = codec::spec_from_proto(&pass).unwrap();
        let mut tree = if pass.tree_digest.is_empty() {
            let (lo, hi) = scene.world().accel.bounds();
            SdTree::new(lo, hi, guided::guide_config(&params, scene))
        } else {
            SdTree::decode(&fetch(&mut workers, &pass.tree_digest).await).unwrap()
        };
        if !pass.fractions_digest.is_empty() {
            let f = fetch(&mut workers, &pass.fractions_digest).await;
            tree.set_fraction_states(&codec::decode_fractions(&f).unwrap())
                .unwrap();
        }
        let region =
            codec::region_from_proto(lease.tile.as_ref().unwrap(), scene.width, scene.height)
                .unwrap();
        let size = (scene.width, scene.height);
        let estimate = if let Some(part) = &lease.estimate {
            codec::decode_tile_estimate(part, size, region).unwrap()
        } else if pass.estimate_digest.is_empty() {
            Vec::new()
        } else {
            codec::decode_estimate(&fetch(&mut workers, &pass.estimate_digest).await).unwrap()
        };
        let inputs = UnitInputs {
            scene,
            params: &params,
            tree: &tree,
            estimate: &estimate,
            seed: lease.settings.as_ref().unwrap().seed.unwrap(),
            tile_size: 4,
        };
        let out = render_unit(&inputs, &spec, region, &|_| {});
        let stats = match (spec.record(), pass.hold_records) {
            (false, _) => Vec::new(),
            (true, false) => tree.take_stats().encode(),
            (true, true) => {
                let gradients = tree.take_gradients();
                let records = tree.take_stats();
                match &mut held {
                    Some((h, covered)) => {
                        h.merge(&records).unwrap();
                        covered.add(lease.lease_id);
                    }
                    None => held = Some((records, Coverage::of([lease.lease_id]))),
                }
                gradients.encode()
            }
        };
        let pixels = codec::encode_tile_pixels(&out.pixels);
        let header = v1::TileHeader {
            job_id: lease.job_id.clone(),
            unit: pass.unit,
            stats_size: stats.len() as u64,
            stats_digest: digest_of(&stats).0.to_vec(),
            tiles: vec![v1::UploadedTile {
                lease_id: lease.lease_id,
                tile: lease.tile,
                counters: Some(codec::tile_counters(&out)),
                pixels_size: pixels.len() as u64,
                pixels_digest: digest_of(&pixels).0.to_vec(),
            }],
        };
        let mut parts = vec![v1::TileUpload {
            part: Some(v1::tile_upload::Part::Header(header)),
        }];
        let payload = [pixels, stats].concat();
        for c in payload.chunks(1000) {
            parts.push(v1::TileUpload {
                part: Some(v1::tile_upload::Part::Data(c.to_vec())),
            });
        }
        let ack = workers
            .upload_tile(keyed(tokio_stream::iter(parts), &key))
            .await
            .unwrap()
            .into_inner();
        assert!(ack.accepted, "{ack:?}");
        tiles += 1;
        let status = jobs
            .get_job(v1::GetJobRequest { job_id: id.clone() })
            .await
            .unwrap()
            .into_inner()
            .status
            .unwrap();
        assert_ne!(status.state, v1::JobState::Failed as i32, "{status:?}");
        saw_preview |= status.preview_available && status.state != v1::JobState::Done as i32;
        saw_eta |= status
            .eta_seconds
            .is_some_and(|e| e.is_finite() && e >= 0.0);
        // the last tile ends the job: its results are assembled in the background
        let ended = [v1::JobState::Assembling, v1::JobState::Done];
        if ended.iter().any(|&e| status.state == e as i32) {
            break;
        }
        tx.send(send(W::RequestWork(v1::RequestWork { slots: 1 })))
            .await
            .unwrap();
    }
    assert!(tiles >= 4);
    assert!(flushes >= 1, "records collected once an iteration");
    assert!(
        saw_preview,
        "a preview of the image so far while the job ran"
    );
    assert!(saw_eta, "an ETA while the job ran");
    // the watch stream ends with DONE
    let mut last = first;
    while let Some(s) = watch.message().await.unwrap() {
        last = s;
    }
    assert_eq!(last.state, v1::JobState::Done as i32);

    let exr = download_exr(&mut jobs, &id).await;
    let scene = scene.unwrap();
    let params = scene.guided.clone().unwrap();
    let settings = pathfarm_render::RenderSettings::new(Some(4), None, scene.seed);
    let (film, _, _) = guided::render_guided(
        &scene,
        &params,
        Budget::Spp(4),
        &settings,
        guided::GuidedOptions::default(),
    );
    let expected =
        pathfarm_render::output::encode_exr(&film, pathfarm_render::output::Aovs::No).unwrap();
    assert!(
        exr == expected,
        "the farm's EXR differs from the one-process render"
    );
    drop(tx);
    c.stop().await;
    // a finished job's results survive a restart
    let c = Running::start(config(data.clone(), None)).await;
    let mut jobs = JobsClient::new(c.channel().await);
    let again = download_exr(&mut jobs, &id).await;
    assert!(again == expected);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
    let _ = std::fs::remove_dir_all(&dir);
}

/// What `grpcurl list` asks: the coordinator's reflection service names every service it
/// serves, its own, health and reflection.
#[tokio::test]
async fn reflection_lists_every_service_the_coordinator_serves() {
    use refl::server_reflection_request::MessageRequest;
    use refl::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1 as refl;
    let (data, c, _) = start_open("reflection").await;
    let mut client = refl::server_reflection_client::ServerReflectionClient::new(c.channel().await);
    let req = refl::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut answers = client
        .server_reflection_info(tokio_stream::iter([req]))
        .await
        .unwrap()
        .into_inner();
    let answer = answers.message().await.unwrap().unwrap().message_response;
    let Some(MessageResponse::ListServicesResponse(list)) = answer else {
        panic!("expected a service list, got {answer:?}");
    };
    let mut names: Vec<_> = list.service.into_iter().map(|s| s.name).collect();
    names.sort();
    assert_eq!(
        names,
        [
            "grpc.health.v1.Health",
            "grpc.reflection.v1.ServerReflection",
            pathfarm_proto::JOBS_SERVICE,
            pathfarm_proto::WORKERS_SERVICE,
        ]
    );
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn metrics_report_jobs_by_state() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let data = temp_dir("metrics");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let mut cfg = config(data.clone(), None);
    cfg.metrics = Some(port);
    let c = Running::start(cfg).await;
    let mut jobs = JobsClient::new(c.channel().await);
    let file = upload(&mut jobs, SCENE.as_bytes(), None).await;
    jobs.submit_job(submit_request(file)).await.unwrap();
    let mut sock = tokio::net::TcpStream::connect(port).await.unwrap();
    sock.write_all(b"GET /metrics HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut text = String::new();
    sock.read_to_string(&mut text).await.unwrap();
    assert!(text.starts_with("HTTP/1.1 200"), "{text}");
    assert!(text.contains("pathfarm_jobs{state=\"queued\"} 1"), "{text}");
    assert!(text.contains("pathfarm_workers 0"), "{text}");
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

/// Registers a fake worker asking for `slots` leases; returns its sender, control stream,
/// worker id and upload key.
pub(super) async fn fake_worker(
    workers: &mut WorkersClient<Channel>,
    slots: u32,
) -> (
    tokio::sync::mpsc::Sender<v1::WorkerMessage>,
    tonic::Streaming<v1::CoordinatorMessage>,
    u64,
    Vec<u8>,
) {
    fake_worker_named(workers, slots, "fake").await
}

/// [`fake_worker`] named `name` (host "test").
pub(super) async fn fake_worker_named(
    workers: &mut WorkersClient<Channel>,
    slots: u32,
    name: &str,
) -> (
    tokio::sync::mpsc::Sender<v1::WorkerMessage>,
    tonic::Streaming<v1::CoordinatorMessage>,
    u64,
    Vec<u8>,
) {
    use v1::worker_message::Msg as W;
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let send = |m| v1::WorkerMessage { msg: Some(m) };
    let register = W::Register(v1::Register {
        protocol_version: pathfarm_proto::PROTOCOL_VERSION,
        build_id: crate::build::build_id().to_string(),
        threads: 1,
        host_name: "test".into(),
        worker_name: name.into(),
    });
    tx.send(send(register)).await.unwrap();
    let more = W::RequestWork(v1::RequestWork { slots });
    tx.send(send(more)).await.unwrap();
    let (inbound, m) = open_control(workers, rx).await;
    let Some(v1::coordinator_message::Msg::Registered(r)) = m.msg else {
        panic!("registered: {m:?}");
    };
    (tx, inbound, r.worker_id, r.upload_key)
}

/// Answers `FlushRecords` `f` with `records`.
async fn upload_records(
    workers: &mut WorkersClient<Channel>,
    (worker_id, key): (u64, &[u8]),
    f: &v1::FlushRecords,
    (records, covered): (&[u8], &Coverage),
) -> v1::RecordsAck {
    use v1::records_upload::Part;
    let header = v1::RecordsHeader {
        worker_id,
        job_id: f.job_id.clone(),
        tree_digest: f.tree_digest.clone(),
        records_epoch: f.records_epoch,
        lost: false,
        size: records.len() as u64,
        digest: digest_of(records).0.to_vec(),
        covered_leases: covered.leases(),
        covered_digest: covered.digest(),
    };
    let mut parts = vec![v1::RecordsUpload {
        part: Some(Part::Header(header)),
    }];
    for c in records.chunks(1000) {
        parts.push(v1::RecordsUpload {
            part: Some(Part::Data(c.to_vec())),
        });
    }
    workers
        .upload_records(keyed(tokio_stream::iter(parts), key))
        .await
        .unwrap()
        .into_inner()
}

/// The next lease offered on `inbound` (within 10 s).
pub(super) async fn next_offer(
    inbound: &mut tonic::Streaming<v1::CoordinatorMessage>,
) -> v1::Lease {
    let wait = Duration::from_secs(10);
    loop {
        let m = tokio::time::timeout(wait, inbound.message())
            .await
            .expect("an offer within 10 s")
            .unwrap()
            .unwrap();
        if let Some(v1::coordinator_message::Msg::LeaseOffer(o)) = m.msg {
            return o.lease.unwrap();
        }
    }
}

/// Uploads a header naming `leases` (each with one byte of "pixels", no statistics).
pub(super) async fn upload_named(
    workers: &mut WorkersClient<Channel>,
    key: &[u8],
    job: &str,
    unit: u64,
    leases: &[(u64, Option<v1::Rect>)],
) -> v1::TileAck {
    let pixel = [7u8];
    let tiles = leases
        .iter()
        .map(|(id, rect)| v1::UploadedTile {
            lease_id: *id,
            tile: *rect,
            counters: None,
            pixels_size: 1,
            pixels_digest: digest_of(&pixel).0.to_vec(),
        })
        .collect::<Vec<_>>();
    let header = v1::TileHeader {
        job_id: job.into(),
        unit,
        stats_size: 0,
        stats_digest: digest_of(&[]).0.to_vec(),
        tiles,
    };
    let mut parts = vec![v1::TileUpload {
        part: Some(v1::tile_upload::Part::Header(header)),
    }];
    parts.push(v1::TileUpload {
        part: Some(v1::tile_upload::Part::Data(vec![7; leases.len()])),
    });
    workers
        .upload_tile(keyed(tokio_stream::iter(parts), key))
        .await
        .unwrap()
        .into_inner()
}

#[tokio::test]
async fn malformed_joint_uploads_are_corrupt_and_a_rejected_one_returns_its_valid_leases() {
    let data = temp_dir("joint");
    let c = Running::start(config(data.clone(), None)).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let mut workers = WorkersClient::new(ch);
    let id = submit_scene(&mut jobs).await;
    let (tx, mut inbound, _, key) = fake_worker(&mut workers, 1).await;
    let lease = next_offer(&mut inbound).await;
    let unit = lease.pass.as_ref().unwrap().unit;
    let corrupt = v1::TileRejectReason::Corrupt as i32;
    // No tile, or one lease named twice: malformed.
    let ack = upload_named(&mut workers, &key, &id, unit, &[]).await;
    assert_eq!(
        (ack.accepted, ack.reject_reason),
        (false, corrupt),
        "{ack:?}"
    );
    let twice = [(lease.lease_id, lease.tile), (lease.lease_id, lease.tile)];
    let ack = upload_named(&mut workers, &key, &id, unit, &twice).await;
    assert_eq!(
        (ack.accepted, ack.reject_reason),
        (false, corrupt),
        "{ack:?}"
    );
    // An unknown lease spoils the upload; the valid lease it named goes back to the queue
    // at once, not counting an attempt, and is offered again.
    let ack = upload_named(
        &mut workers,
        &key,
        &id,
        unit,
        &[(999_999, None), (lease.lease_id, lease.tile)],
    )
    .await;
    let unknown = v1::TileRejectReason::UnknownLease as i32;
    assert_eq!(
        (ack.accepted, ack.reject_reason),
        (false, unknown),
        "{ack:?}"
    );
    let more = v1::worker_message::Msg::RequestWork(v1::RequestWork { slots: 1 });
    tx.send(v1::WorkerMessage { msg: Some(more) })
        .await
        .unwrap();
    let again = next_offer(&mut inbound).await;
    assert_ne!(again.lease_id, lease.lease_id);
    assert_eq!((again.tile, again.attempt), (lease.tile, lease.attempt));
    assert_eq!(again.pass.as_ref().unwrap().unit, unit);
    drop(tx);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

/// The messages of a chunked upload: `header`, then one data part per entry of `data`.
fn chunked<M>(header: M, data: &[Vec<u8>], part: impl Fn(Vec<u8>) -> M) -> Vec<M> {
    std::iter::once(header)
        .chain(data.iter().cloned().map(part))
        .collect()
}

#[tokio::test]
/// The reader itself is tested in `chunked`; tile and records headers are held to their
/// leases before any data is read (`hardening_tests`).
async fn chunked_blob_uploads_refuse_oversized_parts_and_wrong_lengths() {
    use v1::blob_chunk;
    let data = temp_dir("chunked");
    let c = Running::start(config(data.clone(), None)).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch);
    let over = vec![0u8; pathfarm_proto::MAX_CHUNK_BYTES + 1];
    // Each case: the data parts after a header announcing 3 bytes, and what the refusal
    // must name.
    let cases: [(Vec<Vec<u8>>, &str); 4] = [
        (vec![over.clone()], "a data part of"),
        (vec![vec![1, 2], vec![3, 4]], "more data than"),
        (vec![vec![1, 2]], "2 bytes of data, the header says 3"),
        (vec![], "0 bytes of data"),
    ];
    for (parts, names) in &cases {
        // A blob: InvalidArgument, nothing stored.
        let header = blob_chunk::Part::Header(v1::BlobHeader {
            digest: digest_of(&[1, 2, 3]).0.to_vec(),
            size: 3,
        });
        let msgs = chunked(v1::BlobChunk { part: Some(header) }, parts, |d| {
            v1::BlobChunk {
                part: Some(blob_chunk::Part::Data(d)),
            }
        });
        let e = jobs
            .upload_blob(tokio_stream::iter(msgs))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
        assert!(e.message().contains(names), "blob {names:?}: {e:?}");
    }
    assert_eq!(std::fs::read_dir(data.join("blobs")).unwrap().count(), 0);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}
