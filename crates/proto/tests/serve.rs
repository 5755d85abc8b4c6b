//! The descriptor set at work over loopback: a reflection server built from
//! `FILE_DESCRIPTOR_SET` lists both services and serves each file by symbol and by name, as
//! grpcurl asks for them. The generated stubs are exercised against the real coordinator (the
//! farm crate's coordinator tests and the integration tests).

use pathfarm_proto::{FILE_DESCRIPTOR_SET, JOBS_SERVICE, WORKERS_SERVICE};
use prost::Message;
use tonic_reflection::pb::v1 as refl;

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

/// Serves reflection from `FILE_DESCRIPTOR_SET` on an ephemeral loopback port; returns its
/// URL. (The real services are exercised against the real coordinator in the farm crate.)
async fn serve() -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(FILE_DESCRIPTOR_SET)
        .build_v1()
        .unwrap();
    let server = tonic::transport::Server::builder()
        .add_service(reflection)
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

/// The file descriptors reflection answers `request` with, decoded.
async fn files(
    url: &str,
    request: refl::server_reflection_request::MessageRequest,
) -> Vec<prost_types::FileDescriptorProto> {
    let refl::server_reflection_response::MessageResponse::FileDescriptorResponse(files) =
        reflect(url, request).await
    else {
        panic!("expected file descriptors");
    };
    files
        .file_descriptor_proto
        .iter()
        .map(|b| prost_types::FileDescriptorProto::decode(b.as_slice()).unwrap())
        .collect()
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

    let decoded = files(
        &url,
        MessageRequest::FileContainingSymbol("pathfarm.v1.Workers".into()),
    )
    .await;
    let workers = decoded
        .iter()
        .find(|f| f.name() == "pathfarm/v1/workers.proto")
        .expect("workers.proto served");
    let rpcs: Vec<_> = workers.service[0].method.iter().map(|m| m.name()).collect();
    assert_eq!(
        rpcs,
        ["Control", "FetchBlob", "UploadTile", "UploadRecords"]
    );
    // Its import is served by name (grpcurl asks for each dependency it lacks).
    assert_eq!(workers.dependency, ["pathfarm/v1/common.proto"]);
    let common = files(
        &url,
        MessageRequest::FileByFilename("pathfarm/v1/common.proto".into()),
    )
    .await;
    assert!(common.len() == 1);
    let common = &common[0];
    assert!(common.message_type.iter().any(|m| m.name() == "DataChunk"));
}
