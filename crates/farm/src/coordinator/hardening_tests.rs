//! The coordinator under faults and hostile peers, over real gRPC on a loopback port: each
//! test is one way a peer could hang a job or take the coordinator's memory or disk, and
//! what the coordinator must do instead.

use std::time::{Duration, Instant};

use pathfarm_proto::v1;
use pathfarm_proto::v1::jobs_client::JobsClient;
use pathfarm_proto::v1::workers_client::WorkersClient;
use tonic::transport::Channel;
use tonic::Code;

use super::tests::{
    config, fake_worker, fake_worker_named, keyed, next_offer, submit_request, temp_dir, upload,
    upload_named, Running,
};
use super::*;
use crate::bundle::digest_of;

use v1::coordinator_message::Msg as C;
use v1::worker_message::Msg as W;

fn send(m: W) -> v1::WorkerMessage {
    v1::WorkerMessage { msg: Some(m) }
}

/// Waits (at most 10 s) until `ok` holds for the job's status.
async fn until_status(
    jobs: &mut JobsClient<Channel>,
    id: &str,
    ok: impl Fn(&v1::JobStatus) -> bool,
) -> v1::JobStatus {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let req = v1::GetJobRequest { job_id: id.into() };
        let s = jobs
            .get_job(req)
            .await
            .unwrap()
            .into_inner()
            .status
            .unwrap();
        if ok(&s) {
            return s;
        }
        assert!(Instant::now() < deadline, "status never came: {s:?}");
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

/// Submits the test scene; its job id.
async fn submit(jobs: &mut JobsClient<Channel>) -> String {
    let file = upload(jobs, super::tests::SCENE.as_bytes(), None).await;
    let r = jobs.submit_job(submit_request(file)).await.unwrap();
    r.into_inner().job_id
}

/// The first message on `inbound` that is not a lease offer (within 10 s), or its end.
async fn next_non_offer(
    inbound: &mut tonic::Streaming<v1::CoordinatorMessage>,
) -> Result<Option<v1::CoordinatorMessage>, tonic::Status> {
    loop {
        let m = tokio::time::timeout(Duration::from_secs(10), inbound.message())
            .await
            .expect("a message within 10 s")?;
        match m {
            Some(v1::CoordinatorMessage {
                msg: Some(C::LeaseOffer(_)),
            }) => continue,
            other => return Ok(other),
        }
    }
}

#[tokio::test]
async fn a_silent_worker_is_declared_lost_told_so_and_offered_work_when_it_registers_again() {
    let data = temp_dir("silent");
    let mut cfg = config(data.clone(), None);
    cfg.scheduler.heartbeat_timeout = Duration::from_millis(800);
    let c = Running::start(cfg).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let mut workers = WorkersClient::new(ch);
    submit(&mut jobs).await;
    // Asks for work, takes a lease, then says nothing (a stopped process, a partition).
    let (tx, mut inbound, _, _) = fake_worker(&mut workers, 1).await;
    let first = next_offer(&mut inbound).await;
    let t0 = Instant::now();
    let end = next_non_offer(&mut inbound).await;
    let e = end.expect_err("the stream ends with a status");
    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
    assert!(e.message().contains("declared lost"), "{e:?}");
    assert!(t0.elapsed() < Duration::from_secs(5));
    // Back again (as the worker does on a broken stream): registered anew, it gets the
    // tile it lost, its next attempt.
    let (tx2, mut inbound2, _, _) = fake_worker(&mut workers, 1).await;
    let again = next_offer(&mut inbound2).await;
    assert_eq!((again.tile, again.attempt), (first.tile, first.attempt + 1));
    drop((tx, tx2));
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn jobs_get_memory_when_they_start_and_one_that_can_never_fit_is_refused() {
    let data = temp_dir("memory");
    let mut cfg = config(data.clone(), None);
    // Room for one 16x16 session, not two.
    let one = pathfarm_render::scene::guided_session_bytes(16, 16);
    cfg.resources.job_memory_bytes = one + one / 2;
    let c = Running::start(cfg.clone()).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let a = submit(&mut jobs).await;
    let b = submit(&mut jobs).await;
    until_status(&mut jobs, &a, |s| s.tiles_total > 0).await;
    // b waits QUEUED, with no session, until a is gone.
    let sb = until_status(&mut jobs, &b, |_| true).await;
    assert_eq!((sb.state, sb.tiles_total), (v1::JobState::Queued as i32, 0));
    let cancel = v1::CancelJobRequest {
        job_id: a.clone(),
        reason: String::new(),
    };
    jobs.cancel_job(cancel).await.unwrap();
    until_status(&mut jobs, &b, |s| s.tiles_total > 0).await;
    // A job bigger than the whole budget is refused at once, with the numbers.
    let big = super::tests::SCENE.replace("value=\"16\"", "value=\"2048\"");
    assert_ne!(
        big,
        super::tests::SCENE,
        "the test scene's resolution is a default"
    );
    let file = upload(&mut jobs, big.as_bytes(), None).await;
    let e = jobs.submit_job(submit_request(file)).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("2048x2048"), "{e:?}");
    c.stop().await;
    // A restarted coordinator allocates nothing for queued jobs until it admits them.
    let shared = Shared::open(cfg).unwrap();
    let st = shared.lock();
    assert!(st
        .jobs
        .values()
        .all(|j| j.memory() == 0 && j.active().is_none()));
    let queued = (st.jobs.values())
        .filter(|j| matches!(j.phase, Phase::Queued(_)))
        .count();
    assert_eq!(queued, 1, "b restarts; a was cancelled");
    drop(st);
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn a_full_queue_refuses_submissions() {
    let data = temp_dir("queue");
    let mut cfg = config(data.clone(), None);
    cfg.resources.max_jobs_waiting = 2;
    let c = Running::start(cfg).await;
    let mut jobs = JobsClient::new(c.channel().await);
    submit(&mut jobs).await;
    submit(&mut jobs).await;
    let file = upload(&mut jobs, super::tests::SCENE.as_bytes(), None).await;
    let e = jobs.submit_job(submit_request(file)).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

/// An upload's header alone, on a stream left open: what is answered before any data.
async fn header_only<M: Send + 'static>(
    header: M,
    call: impl FnOnce(
        tonic::Request<tokio_stream::wrappers::ReceiverStream<M>>,
    ) -> tokio::task::JoinHandle<Result<tonic::Response<String>, tonic::Status>>,
    key: &[u8],
) -> (Result<String, tonic::Status>, tokio::sync::mpsc::Sender<M>) {
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(header).await.unwrap();
    let stream = tokio_stream::wrappers::ReceiverStream::new(rx);
    let answer = call(keyed(stream, key));
    let answer = tokio::time::timeout(Duration::from_secs(5), answer)
        .await
        .expect("answered before any data was sent")
        .unwrap();
    (answer.map(|r| r.into_inner()), tx)
}

#[tokio::test]
async fn uploads_announcing_more_than_their_lease_can_produce_are_refused_before_any_data() {
    let data = temp_dir("announce");
    let c = Running::start(config(data.clone(), None)).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let workers = WorkersClient::new(ch);
    let id = submit(&mut jobs).await;
    let (tx, mut inbound, worker_id, key) = fake_worker(&mut workers.clone(), 1).await;
    let lease = next_offer(&mut inbound).await;
    let unit = lease.pass.as_ref().unwrap().unit;
    let tile = |size| v1::UploadedTile {
        lease_id: lease.lease_id,
        tile: lease.tile,
        pixels_size: size,
        ..Default::default()
    };
    for (pixels, stats) in [(4 << 30, 0), (1 << 20, 0), (93, 3 << 30)] {
        let header = v1::TileUpload {
            part: Some(v1::tile_upload::Part::Header(v1::TileHeader {
                job_id: id.clone(),
                unit,
                stats_size: stats,
                tiles: vec![tile(pixels)],
                ..Default::default()
            })),
        };
        let mut w = workers.clone();
        let (answer, _open) = header_only(
            header,
            |req| {
                tokio::spawn(async move {
                    let r = w.upload_tile(req).await?;
                    Ok(r.map(|a| format!("{a:?}")))
                })
            },
            &key,
        )
        .await;
        let answer = answer.unwrap();
        assert!(answer.contains("accepted: false"), "{answer}");
    }
    // Records never asked for, of 4 GiB: refused at the header.
    let header = v1::RecordsUpload {
        part: Some(v1::records_upload::Part::Header(v1::RecordsHeader {
            worker_id,
            job_id: id.clone(),
            size: 4 << 30,
            ..Default::default()
        })),
    };
    let mut w = workers.clone();
    let (answer, _open) = header_only(
        header,
        |req| {
            tokio::spawn(async move {
                let r = w.upload_records(req).await?;
                Ok(r.map(|a| format!("{a:?}")))
            })
        },
        &key,
    )
    .await;
    assert!(answer.unwrap().contains("accepted: false"));
    drop(tx);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn uploads_are_taken_only_from_the_worker_holding_the_lease() {
    let data = temp_dir("holder");
    let c = Running::start(config(data.clone(), None)).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let mut workers = WorkersClient::new(ch);
    let id = submit(&mut jobs).await;
    let (ta, mut a, _, _) = fake_worker(&mut workers, 1).await;
    let lease = next_offer(&mut a).await;
    let unit = lease.pass.as_ref().unwrap().unit;
    let (tb, _b, _, key_b) = fake_worker(&mut workers, 0).await;
    // B names A's lease: refused, and A keeps it (nothing went back to the queue).
    let ack = upload_named(
        &mut workers,
        &key_b,
        &id,
        unit,
        &[(lease.lease_id, lease.tile)],
    )
    .await;
    assert!(
        !ack.accepted && ack.detail.contains("not the uploading worker's"),
        "{ack:?}"
    );
    let list = jobs
        .list_workers(v1::ListWorkersRequest::default())
        .await
        .unwrap();
    let held: Vec<u64> = list
        .into_inner()
        .workers
        .iter()
        .flat_map(|w| w.lease_ids.clone())
        .collect();
    assert_eq!(held, vec![lease.lease_id]);
    // No key, or a key of no worker.
    let e = workers
        .upload_tile(tokio_stream::iter(Vec::<v1::TileUpload>::new()))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated, "{e:?}");
    let e = workers
        .upload_tile(keyed(
            tokio_stream::iter(Vec::<v1::TileUpload>::new()),
            &[7; 32],
        ))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::PermissionDenied, "{e:?}");
    drop((ta, tb));
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn bad_uploads_cost_their_sender_and_never_fail_the_job() {
    let data = temp_dir("blame");
    let c = Running::start(config(data.clone(), None)).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let mut workers = WorkersClient::new(ch);
    let id = submit(&mut jobs).await;
    let (tx, mut bad, _, key) = fake_worker(&mut workers, 1).await;
    let (honest_tx, _honest, _, _) = fake_worker_named(&mut workers, 0, "honest").await;
    for k in 0..3 {
        let lease = next_offer(&mut bad).await;
        let unit = lease.pass.as_ref().unwrap().unit;
        // Garbage pixels of the right size: corrupt.
        let pass = lease.pass.clone().unwrap();
        let spec = codec::spec_from_proto(&pass).unwrap();
        let region = codec::region_from_proto(&lease.tile.unwrap(), 16, 16).unwrap();
        let size = codec::tile_pixels_bytes(&spec, region) as usize;
        let ack = upload_sized(&mut workers, &key, &id, unit, &lease, vec![0xff; size]).await;
        assert!(!ack.accepted, "upload {k}: {ack:?}");
        assert_eq!(ack.reject_reason, v1::TileRejectReason::Corrupt as i32);
        tx.send(send(W::RequestWork(v1::RequestWork { slots: 1 })))
            .await
            .unwrap();
        let s = until_status(&mut jobs, &id, |_| true).await;
        assert_ne!(s.state, v1::JobState::Failed as i32, "{s:?}");
    }
    // Blocked after three: named in the job's status, offered none of its tiles.
    let s = until_status(&mut jobs, &id, |s| !s.blocked_workers.is_empty()).await;
    assert!(s.blocked_workers[0].starts_with("test/fake: "), "{s:?}");
    assert_ne!(s.state, v1::JobState::Failed as i32);
    let got = tokio::time::timeout(Duration::from_millis(500), next_offer(&mut bad)).await;
    assert!(got.is_err(), "a blocked worker was offered {got:?}");
    drop((tx, honest_tx));
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

/// Uploads `pixels` as the whole payload of `lease` (no statistics).
async fn upload_sized(
    workers: &mut WorkersClient<Channel>,
    key: &[u8],
    job: &str,
    unit: u64,
    lease: &v1::Lease,
    pixels: Vec<u8>,
) -> v1::TileAck {
    let header = v1::TileHeader {
        job_id: job.into(),
        unit,
        stats_size: 0,
        stats_digest: digest_of(&[]).0.to_vec(),
        tiles: vec![v1::UploadedTile {
            lease_id: lease.lease_id,
            tile: lease.tile,
            counters: None,
            pixels_size: pixels.len() as u64,
            pixels_digest: digest_of(&pixels).0.to_vec(),
        }],
    };
    let msgs = crate::chunked::messages::<v1::TileUpload>(header, &[&pixels], 1 << 20);
    let r = workers
        .upload_tile(keyed(tokio_stream::iter(msgs), key))
        .await;
    r.unwrap().into_inner()
}

#[tokio::test]
async fn heartbeats_naming_made_up_leases_cost_nothing_and_floods_disconnect() {
    let data = temp_dir("heartbeat");
    let c = Running::start(config(data.clone(), None)).await;
    let ch = c.channel().await;
    let mut workers = WorkersClient::new(ch);
    let (tx, mut inbound, _, _) = fake_worker(&mut workers, 0).await;
    // Ids nobody was given: no CancelLease each.
    let made_up = v1::Heartbeat {
        active_lease_ids: (1_000_000..1_000_100).collect(),
    };
    tx.send(send(W::Heartbeat(made_up))).await.unwrap();
    let quiet = tokio::time::timeout(Duration::from_millis(500), inbound.message()).await;
    assert!(quiet.is_err(), "answered made-up leases with {quiet:?}");
    // More ids than any worker can hold: disconnected.
    let flood = v1::Heartbeat {
        active_lease_ids: (0..5_000).collect(),
    };
    tx.send(send(W::Heartbeat(flood))).await.unwrap();
    let e = next_non_offer(&mut inbound).await.unwrap_err();
    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
    drop(tx);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn a_refused_submission_deletes_no_blob_another_client_needs() {
    let data = temp_dir("refused");
    let c = Running::start(config(data.clone(), None)).await;
    let mut jobs = JobsClient::new(c.channel().await);
    // A uploads its scene; B submits the same file with settings that are refused.
    let file = upload(&mut jobs, super::tests::SCENE.as_bytes(), None).await;
    let mut refused = submit_request(file.clone());
    refused.settings.as_mut().unwrap().budget = Some(v1::job_settings::Budget::Spp(0));
    let e = jobs.submit_job(refused).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    // A's submission still finds its blob.
    jobs.submit_job(submit_request(file)).await.unwrap();
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn unreferenced_blobs_are_deleted_after_the_grace_period() {
    let data = temp_dir("grace");
    let mut cfg = config(data.clone(), None);
    cfg.resources.blob_grace = Duration::from_millis(600);
    let c = Running::start(cfg).await;
    let mut jobs = JobsClient::new(c.channel().await);
    let kept = submit(&mut jobs).await;
    let orphan = upload(&mut jobs, b"never submitted", None).await;
    let path = data
        .join("blobs")
        .join(crate::bundle::Digest(orphan.digest.clone().try_into().unwrap()).to_hex());
    assert!(path.is_file());
    let deadline = Instant::now() + Duration::from_secs(10);
    while path.is_file() {
        assert!(
            Instant::now() < deadline,
            "the orphan blob was never deleted"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The submitted job's scene stays.
    let req = v1::GetJobRequest { job_id: kept };
    let root = jobs.get_job(req).await.unwrap().into_inner();
    assert_eq!(root.root, "scene.xml");
    let scene = digest_of(super::tests::SCENE.as_bytes()).to_hex();
    assert!(data.join("blobs").join(scene).is_file());
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn disconnected_workers_are_forgotten_and_names_are_bounded() {
    let data = temp_dir("forget");
    let c = Running::start(config(data.clone(), None)).await;
    let ch = c.channel().await;
    let mut jobs = JobsClient::new(ch.clone());
    let mut workers = WorkersClient::new(ch);
    for _ in 0..20 {
        let (tx, inbound, _, _) = fake_worker(&mut workers, 0).await;
        drop((tx, inbound));
    }
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let register = W::Register(v1::Register {
        protocol_version: pathfarm_proto::PROTOCOL_VERSION,
        build_id: crate::build::build_id().to_string(),
        threads: 1,
        host_name: "h".repeat(900 << 10),
        worker_name: String::new(),
    });
    tx.send(send(register)).await.unwrap();
    let _inbound = workers
        .control(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let list = loop {
        let list = jobs
            .list_workers(v1::ListWorkersRequest::default())
            .await
            .unwrap()
            .into_inner();
        let connected = list.workers.iter().filter(|w| w.connected).count();
        if (connected == 1 && list.workers.len() > 1) || Instant::now() > deadline {
            break list;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    // The departed are kept a while, one per identity (the 20 share one) and bounded; the
    // connected one's name is bounded.
    let (connected, departed): (Vec<_>, Vec<_>) = list.workers.iter().partition(|w| w.connected);
    assert_eq!(connected.len(), 1, "{}", list.workers.len());
    assert!(connected[0].host_name.len() < 400);
    assert!(!departed.is_empty() && departed.len() <= super::departed::MAX_DEPARTED);
    assert!(departed
        .iter()
        .all(|w| w.lease_ids.is_empty() && w.departed_unix_ms > 0));
    assert!(departed
        .iter()
        .all(|w| w.departed_reason.contains("disconnected")));
    drop(tx);
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn the_token_is_checked_first_and_errors_echo_bounded_input() {
    let data = temp_dir("edge");
    let c = Running::start(config(data.clone(), Some("s3cret"))).await;
    let mut jobs = JobsClient::new(c.channel().await);
    let mut req = tonic::Request::new(v1::ListJobsRequest::default());
    req.metadata_mut()
        .insert(pathfarm_proto::PROTOCOL_HEADER, "999".parse().unwrap());
    let e = jobs.list_jobs(req).await.unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated, "{e:?}");
    c.stop().await;
    let (data2, c, mut jobs) = super::tests::start_open("edge-open").await;
    for id in ["job-01", "job-+1", "job-", &"9".repeat(100_000)] {
        let e = jobs
            .get_job(v1::GetJobRequest { job_id: id.into() })
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::NotFound, "{id:.20}");
        assert!(e.message().len() < 400, "{}", e.message().len());
    }
    // A false size for a blob already held.
    let file = upload(&mut jobs, b"twelve bytes", None).await;
    let lie = vec![
        v1::BlobChunk {
            part: Some(v1::blob_chunk::Part::Header(v1::BlobHeader {
                digest: file.digest.clone(),
                size: 13,
            })),
        },
        v1::BlobChunk {
            part: Some(v1::blob_chunk::Part::Data(b"twelve bytes!".to_vec())),
        },
    ];
    let e = jobs.upload_blob(tokio_stream::iter(lie)).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    // Defines with padding, a huge define, and a time budget of a denormal.
    let scene = upload(&mut jobs, super::tests::SCENE.as_bytes(), None).await;
    let define = |name: &str, value: String| {
        let mut r = submit_request(scene.clone());
        let s = r.settings.as_mut().unwrap();
        s.scene.get_or_insert_with(Default::default).defines = vec![v1::Define {
            name: name.into(),
            value,
        }];
        r
    };
    for r in [
        define("resx", " 64".into()),
        define("resx", "6".repeat(3 << 20)),
    ] {
        let e = jobs.submit_job(r).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
        assert!(e.message().len() < 600, "{}", e.message().len());
    }
    let mut tiny = submit_request(scene);
    tiny.settings.as_mut().unwrap().budget = Some(v1::job_settings::Budget::TimeSeconds(5e-324));
    let e = jobs.submit_job(tiny).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
    let _ = std::fs::remove_dir_all(&data2);
}

#[tokio::test]
async fn a_refused_worker_is_not_told_the_coordinators_build() {
    let data = temp_dir("build");
    let c = Running::start(config(data.clone(), None)).await;
    let mut workers = WorkersClient::new(c.channel().await);
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let register = W::Register(v1::Register {
        protocol_version: pathfarm_proto::PROTOCOL_VERSION,
        build_id: "other".into(),
        threads: 1,
        host_name: "h".into(),
        worker_name: String::new(),
    });
    tx.send(send(register)).await.unwrap();
    let mut inbound = workers
        .control(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let first = inbound.message().await.unwrap().unwrap();
    let Some(C::Refused(r)) = first.msg else {
        panic!("{first:?}")
    };
    let ours = crate::build::build_id();
    assert!(r.required_build_id.is_empty());
    assert!(
        !r.reason.contains(ours) && r.reason.contains("other"),
        "{}",
        r.reason
    );
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}

#[tokio::test]
async fn reflection_is_served_as_v1alpha_too() {
    use refl::server_reflection_request::MessageRequest;
    use refl::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1alpha as refl;
    let (data, c, _) = super::tests::start_open("reflection-alpha").await;
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
    let names: Vec<_> = list.service.into_iter().map(|s| s.name).collect();
    assert!(
        names.iter().any(|n| n == pathfarm_proto::JOBS_SERVICE),
        "{names:?}"
    );
    c.stop().await;
    let _ = std::fs::remove_dir_all(&data);
}
