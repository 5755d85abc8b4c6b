//! The stubs and the descriptor set at work over loopback: a reflection server built from
//! `FILE_DESCRIPTOR_SET` lists both services, and toy `Jobs` / `Workers` servers answer the
//! generated clients on unary, client-streaming, server-streaming and bidirectional rpcs.

use std::pin::Pin;
use std::sync::Mutex;

use pathfarm_proto::v1::{
    self, blob_chunk, coordinator_message, data_chunk,
    jobs_client::JobsClient,
    jobs_server::{Jobs, JobsServer},
    worker_message,
    workers_client::WorkersClient,
    workers_server::{Workers, WorkersServer},
};
use pathfarm_proto::{FILE_DESCRIPTOR_SET, JOBS_SERVICE, MAX_CHUNK_BYTES, WORKERS_SERVICE};
use prost::Message;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};
use tonic_reflection::pb::v1 as refl;

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

#[test]
fn reflection_server_builds_from_the_descriptor_set() {
    tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1()
        .expect("reflection v1 service builds");
    tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .with_service_name(JOBS_SERVICE)
        .with_service_name(WORKERS_SERVICE)
        .build_v1alpha()
        .expect("reflection v1alpha service builds");
    // A truncated set is refused: the check above means something.
    assert!(tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(&FILE_DESCRIPTOR_SET[..FILE_DESCRIPTOR_SET.len() / 2])
        .build_v1()
        .is_err());
}

/// A toy coordinator: holds blobs in memory; the rpcs the tests do not use are
/// unimplemented.
#[derive(Default)]
struct Toy {
    blobs: Mutex<Vec<(Vec<u8>, Vec<u8>)>>,
}

#[tonic::async_trait]
impl Jobs for Toy {
    async fn find_missing_blobs(
        &self,
        req: Request<v1::FindMissingBlobsRequest>,
    ) -> Result<Response<v1::FindMissingBlobsResponse>, Status> {
        let blobs = self.blobs.lock().unwrap();
        let missing = req
            .into_inner()
            .digests
            .into_iter()
            .filter(|d| !blobs.iter().any(|(have, _)| have == d))
            .collect();
        Ok(Response::new(v1::FindMissingBlobsResponse { missing }))
    }

    async fn upload_blob(
        &self,
        req: Request<Streaming<v1::BlobChunk>>,
    ) -> Result<Response<v1::UploadBlobResponse>, Status> {
        let mut stream = req.into_inner();
        let Some(blob_chunk::Part::Header(header)) = stream.message().await?.and_then(|c| c.part)
        else {
            return Err(Status::invalid_argument(
                "the first message must be a header",
            ));
        };
        let mut data = Vec::new();
        while let Some(chunk) = stream.message().await? {
            match chunk.part {
                Some(blob_chunk::Part::Data(d)) if !d.is_empty() && d.len() <= MAX_CHUNK_BYTES => {
                    data.extend_from_slice(&d)
                }
                _ => return Err(Status::invalid_argument("bad data part")),
            }
        }
        if data.len() as u64 != header.size {
            return Err(Status::invalid_argument("size differs from the header's"));
        }
        self.blobs
            .lock()
            .unwrap()
            .push((header.digest.clone(), data));
        Ok(Response::new(v1::UploadBlobResponse {
            digest: header.digest,
            size: header.size,
            already_present: false,
        }))
    }

    async fn submit_job(
        &self,
        _: Request<v1::SubmitJobRequest>,
    ) -> Result<Response<v1::SubmitJobResponse>, Status> {
        Err(Status::unimplemented("toy"))
    }

    type WatchJobStream = BoxStream<v1::JobStatus>;

    async fn watch_job(
        &self,
        req: Request<v1::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let job_id = req.into_inner().job_id;
        let states = [
            v1::JobState::Queued,
            v1::JobState::Training,
            v1::JobState::FinalPass,
            v1::JobState::Done,
        ];
        let updates = states.map(|s| {
            Ok(v1::JobStatus {
                job_id: job_id.clone(),
                state: s as i32,
                ..Default::default()
            })
        });
        Ok(Response::new(Box::pin(tokio_stream::iter(updates))))
    }

    async fn get_job(
        &self,
        _: Request<v1::GetJobRequest>,
    ) -> Result<Response<v1::GetJobResponse>, Status> {
        Err(Status::not_found("toy"))
    }

    async fn list_jobs(
        &self,
        _: Request<v1::ListJobsRequest>,
    ) -> Result<Response<v1::ListJobsResponse>, Status> {
        Err(Status::unimplemented("toy"))
    }

    async fn cancel_job(
        &self,
        _: Request<v1::CancelJobRequest>,
    ) -> Result<Response<v1::CancelJobResponse>, Status> {
        Err(Status::unimplemented("toy"))
    }

    type DownloadResultStream = BoxStream<v1::DataChunk>;

    async fn download_result(
        &self,
        _: Request<v1::DownloadResultRequest>,
    ) -> Result<Response<Self::DownloadResultStream>, Status> {
        Err(Status::unimplemented("toy"))
    }

    async fn list_workers(
        &self,
        _: Request<v1::ListWorkersRequest>,
    ) -> Result<Response<v1::ListWorkersResponse>, Status> {
        Err(Status::unimplemented("toy"))
    }
}

#[tonic::async_trait]
impl Workers for Toy {
    type ControlStream = BoxStream<v1::CoordinatorMessage>;

    /// Registered for protocol version 1, Refused otherwise; one LeaseOffer per
    /// requested slot.
    async fn control(
        &self,
        req: Request<Streaming<v1::WorkerMessage>>,
    ) -> Result<Response<Self::ControlStream>, Status> {
        use coordinator_message::Msg;
        let mut incoming = req.into_inner();
        let Some(worker_message::Msg::Register(reg)) =
            incoming.message().await?.and_then(|m| m.msg)
        else {
            return Err(Status::failed_precondition(
                "the first message must be Register",
            ));
        };
        let reply = |m: Msg| Ok(v1::CoordinatorMessage { msg: Some(m) });
        if reg.protocol_version != pathfarm_proto::PROTOCOL_VERSION {
            let refused = Msg::Refused(v1::Refused {
                reason: format!(
                    "protocol version {} not supported (coordinator speaks {})",
                    reg.protocol_version,
                    pathfarm_proto::PROTOCOL_VERSION
                ),
                supported_protocol_versions: vec![pathfarm_proto::PROTOCOL_VERSION],
                required_build_id: String::new(),
            });
            return Ok(Response::new(Box::pin(tokio_stream::iter([reply(
                refused,
            )]))));
        }
        let registered = Msg::Registered(v1::Registered {
            worker_id: 1,
            heartbeat_interval_ms: 1_000,
            lease_timeout_ms: 5_000,
            protocol_version: pathfarm_proto::PROTOCOL_VERSION,
            build_id: "toy".into(),
        });
        // The usual coordinator shape: a task reads the worker's messages and answers
        // through a channel whose receiver is the response stream.
        let (tx, rx) = tokio::sync::mpsc::channel(8);
        tx.send(reply(registered)).await.unwrap();
        tokio::spawn(async move {
            let mut next_lease = 100u64;
            while let Some(Ok(m)) = incoming.next().await {
                if let Some(worker_message::Msg::RequestWork(rw)) = m.msg {
                    for _ in 0..rw.slots {
                        next_lease += 1;
                        let offer = Msg::LeaseOffer(v1::LeaseOffer {
                            lease: Some(v1::Lease {
                                lease_id: next_lease,
                                job_id: "job-1".into(),
                                ..Default::default()
                            }),
                        });
                        if tx.send(reply(offer)).await.is_err() {
                            return;
                        }
                    }
                }
            }
        });
        Ok(Response::new(Box::pin(
            tokio_stream::wrappers::ReceiverStream::new(rx),
        )))
    }

    type FetchBlobStream = BoxStream<v1::DataChunk>;

    async fn fetch_blob(
        &self,
        req: Request<v1::BlobRequest>,
    ) -> Result<Response<Self::FetchBlobStream>, Status> {
        let digest = req.into_inner().digest;
        let data = self
            .blobs
            .lock()
            .unwrap()
            .iter()
            .find(|(d, _)| *d == digest)
            .map(|(_, data)| data.clone())
            .ok_or_else(|| Status::not_found("no such blob"))?;
        let mut chunks = vec![Ok(v1::DataChunk {
            part: Some(data_chunk::Part::Header(v1::DataHeader {
                total_size: data.len() as u64,
                digest,
            })),
        })];
        chunks.extend(data.chunks(MAX_CHUNK_BYTES).map(|c| {
            Ok(v1::DataChunk {
                part: Some(data_chunk::Part::Data(c.to_vec())),
            })
        }));
        Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
    }

    async fn upload_tile(
        &self,
        _: Request<Streaming<v1::TileUpload>>,
    ) -> Result<Response<v1::TileAck>, Status> {
        Err(Status::unimplemented("toy"))
    }
}

/// Serves reflection, Jobs and Workers on an ephemeral loopback port; returns its URL.
async fn serve() -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1()
        .unwrap();
    let toy = std::sync::Arc::new(Toy::default());
    let server = tonic::transport::Server::builder()
        .add_service(reflection)
        .add_service(JobsServer::from_arc(toy.clone()))
        .add_service(WorkersServer::from_arc(toy))
        .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener));
    tokio::spawn(server);
    format!("http://{addr}")
}

async fn reflect(
    url: &str,
    request: refl::server_reflection_request::MessageRequest,
) -> refl::server_reflection_response::MessageResponse {
    let mut client = refl::server_reflection_client::ServerReflectionClient::new(
        tonic::transport::Endpoint::from_shared(url.to_string())
            .unwrap()
            .connect()
            .await
            .unwrap(),
    );
    let req = refl::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(request),
    };
    let mut responses = client
        .server_reflection_info(tokio_stream::iter([req]))
        .await
        .unwrap()
        .into_inner();
    responses
        .message()
        .await
        .unwrap()
        .unwrap()
        .message_response
        .unwrap()
}

#[tokio::test]
async fn reflection_lists_and_describes_the_services() {
    let url = serve().await;
    use refl::server_reflection_request::MessageRequest;
    use refl::server_reflection_response::MessageResponse;

    let MessageResponse::ListServicesResponse(list) =
        reflect(&url, MessageRequest::ListServices(String::new())).await
    else {
        panic!("expected a service list");
    };
    let names: Vec<_> = list.service.iter().map(|s| s.name.as_str()).collect();
    for want in [
        JOBS_SERVICE,
        WORKERS_SERVICE,
        "grpc.reflection.v1.ServerReflection",
    ] {
        assert!(names.contains(&want), "{want} in {names:?}");
    }

    let MessageResponse::FileDescriptorResponse(files) = reflect(
        &url,
        MessageRequest::FileContainingSymbol("pathfarm.v1.Workers".into()),
    )
    .await
    else {
        panic!("expected file descriptors");
    };
    let decoded: Vec<_> = files
        .file_descriptor_proto
        .iter()
        .map(|b| prost_types::FileDescriptorProto::decode(b.as_slice()).unwrap())
        .collect();
    let workers = decoded
        .iter()
        .find(|f| f.name() == "pathfarm/v1/workers.proto")
        .expect("workers.proto served");
    let rpcs: Vec<_> = workers.service[0].method.iter().map(|m| m.name()).collect();
    assert_eq!(rpcs, ["Control", "FetchBlob", "UploadTile"]);
    // Its import is served by name (grpcurl asks for each dependency it lacks).
    assert_eq!(workers.dependency, ["pathfarm/v1/common.proto"]);
    let MessageResponse::FileDescriptorResponse(files) = reflect(
        &url,
        MessageRequest::FileByFilename("pathfarm/v1/common.proto".into()),
    )
    .await
    else {
        panic!("expected file descriptors");
    };
    let common =
        prost_types::FileDescriptorProto::decode(files.file_descriptor_proto[0].as_slice())
            .unwrap();
    assert!(common.message_type.iter().any(|m| m.name() == "DataChunk"));
}

#[tokio::test]
async fn stubs_talk_over_loopback() {
    let url = serve().await;
    let mut jobs = JobsClient::connect(url.clone()).await.unwrap();
    let mut workers = WorkersClient::connect(url).await.unwrap();

    // Unary, then client streaming: a blob of 2.5 MiB in three parts.
    let blob: Vec<u8> = (0..(5 * MAX_CHUNK_BYTES / 2))
        .map(|i| (i % 251) as u8)
        .collect();
    let digest = vec![7u8; 32];
    let missing = jobs
        .find_missing_blobs(v1::FindMissingBlobsRequest {
            digests: vec![digest.clone()],
            bundle: None,
        })
        .await
        .unwrap()
        .into_inner()
        .missing;
    assert_eq!(missing, [digest.as_slice()]);
    let mut parts = vec![v1::BlobChunk {
        part: Some(blob_chunk::Part::Header(v1::BlobHeader {
            digest: digest.clone(),
            size: blob.len() as u64,
        })),
    }];
    parts.extend(blob.chunks(MAX_CHUNK_BYTES).map(|c| v1::BlobChunk {
        part: Some(blob_chunk::Part::Data(c.to_vec())),
    }));
    assert_eq!(parts.len(), 4);
    let stored = jobs
        .upload_blob(tokio_stream::iter(parts))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(stored.size, blob.len() as u64);
    let missing = jobs
        .find_missing_blobs(v1::FindMissingBlobsRequest {
            digests: vec![digest.clone(), vec![8u8; 32]],
            bundle: None,
        })
        .await
        .unwrap()
        .into_inner()
        .missing;
    assert_eq!(missing, [vec![8u8; 32]]);

    // Server streaming: the blob comes back whole, and job states arrive in order.
    let mut fetched = workers
        .fetch_blob(v1::BlobRequest {
            digest: digest.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    let Some(data_chunk::Part::Header(header)) = fetched.message().await.unwrap().unwrap().part
    else {
        panic!("a header first");
    };
    assert_eq!(header.total_size, blob.len() as u64);
    let mut got = Vec::new();
    while let Some(c) = fetched.message().await.unwrap() {
        let Some(data_chunk::Part::Data(d)) = c.part else {
            panic!("data after the header");
        };
        assert!(d.len() <= MAX_CHUNK_BYTES);
        got.extend(d);
    }
    assert_eq!(got, blob);
    let err = workers
        .fetch_blob(v1::BlobRequest {
            digest: vec![9; 32],
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::NotFound);

    let states: Vec<_> = jobs
        .watch_job(v1::WatchJobRequest {
            job_id: "job-1".into(),
        })
        .await
        .unwrap()
        .into_inner()
        .map(|s| s.unwrap().state())
        .collect()
        .await;
    assert_eq!(
        states,
        [
            v1::JobState::Queued,
            v1::JobState::Training,
            v1::JobState::FinalPass,
            v1::JobState::Done
        ]
    );

    // Bidirectional: register, ask for two leases, get two offers.
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    let send = |m: worker_message::Msg| v1::WorkerMessage { msg: Some(m) };
    tx.send(send(worker_message::Msg::Register(v1::Register {
        protocol_version: pathfarm_proto::PROTOCOL_VERSION,
        build_id: "toy".into(),
        threads: 2,
        host_name: "localhost".into(),
        worker_name: String::new(),
    })))
    .await
    .unwrap();
    let mut control = workers
        .control(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let first = control.message().await.unwrap().unwrap().msg;
    assert!(
        matches!(first, Some(coordinator_message::Msg::Registered(ref r)) if r.worker_id == 1),
        "{first:?}"
    );
    tx.send(send(worker_message::Msg::RequestWork(v1::RequestWork {
        slots: 2,
    })))
    .await
    .unwrap();
    let mut leases = Vec::new();
    for _ in 0..2 {
        match control.message().await.unwrap().unwrap().msg {
            Some(coordinator_message::Msg::LeaseOffer(o)) => leases.push(o.lease.unwrap().lease_id),
            other => panic!("expected a lease offer, got {other:?}"),
        }
    }
    assert_eq!(leases, [101, 102]);
    drop(tx);
    assert!(
        control.message().await.unwrap().is_none(),
        "stream ends with the worker's"
    );

    // A worker of another protocol version is refused.
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    tx.send(send(worker_message::Msg::Register(v1::Register {
        protocol_version: 2,
        ..Default::default()
    })))
    .await
    .unwrap();
    let mut control = workers
        .control(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    match control.message().await.unwrap().unwrap().msg {
        Some(coordinator_message::Msg::Refused(r)) => {
            assert!(r.reason.contains("protocol version 2"), "{}", r.reason);
            assert_eq!(r.supported_protocol_versions, [1]);
        }
        other => panic!("expected Refused, got {other:?}"),
    }
}
