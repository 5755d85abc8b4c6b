//! pathfarm's public gRPC API, package `pathfarm.v1`, generated from the workspace's
//! `proto/pathfarm/v1/*.proto` (see `proto/README.md`).
//!
//! * [`v1`]: the prost messages and both stubs of each service:
//!   [`v1::jobs_server`] / [`v1::jobs_client`] (the client API: bundles, jobs, results,
//!   workers list) and [`v1::workers_server`] / [`v1::workers_client`] (the worker API:
//!   control stream, blob fetches, tile uploads).
//! * [`FILE_DESCRIPTOR_SET`]: the encoded descriptor set of the package, for
//!   `tonic_reflection::server::Builder::register_encoded_file_descriptor_set`.
//! * [`PROTOCOL_VERSION`], [`MAX_CHUNK_BYTES`]: the protocol's version and chunk limit.

/// The generated code of package `pathfarm.v1`: messages, enums, and the tonic client and
/// server of the `Jobs` and `Workers` services.
pub mod v1 {
    #![allow(clippy::all, missing_docs)]
    tonic::include_proto!("pathfarm.v1");
}

/// The encoded `google.protobuf.FileDescriptorSet` of `pathfarm.v1` (every file of the
/// package, with their imports and comments), including the service descriptors: what
/// server reflection serves.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/pathfarm_v1_descriptor.bin"));

/// The protocol version this build speaks: a worker sends it in `Register`, and the
/// coordinator refuses versions it does not speak. Bumped on any change that an older peer
/// would misread; adding fields or messages does not bump it (fields are never renumbered).
pub const PROTOCOL_VERSION: u32 = 6;

/// gRPC metadata key in which pathfarm's clients and workers send [`PROTOCOL_VERSION`] on
/// every call; the coordinator refuses a call naming another version (calls without it, from
/// stock gRPC tools, are served).
pub const PROTOCOL_HEADER: &str = "pathfarm-protocol";

/// gRPC metadata key in which a worker sends its control stream's `Registered.upload_key`
/// (hex) on its uploads: the coordinator takes an upload's sender from it, never from a field
/// of the upload.
pub const WORKER_KEY_HEADER: &str = "pathfarm-worker-key";

/// The most payload bytes one chunk message carries (`DataChunk`, `BlobChunk`, `TileUpload`
/// data parts): 1 MiB. Senders split payloads into parts of at most this size; receivers
/// reject larger parts.
pub const MAX_CHUNK_BYTES: usize = 1 << 20;

/// Fully qualified name of the client service.
pub const JOBS_SERVICE: &str = "pathfarm.v1.Jobs";

/// Fully qualified name of the worker service.
pub const WORKERS_SERVICE: &str = "pathfarm.v1.Workers";

/// Length of a blake3 digest in the protocol's `bytes` digest fields.
pub const DIGEST_BYTES: usize = 32;
