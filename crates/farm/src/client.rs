//! The farm's client side: what the CLI calls to submit jobs, watch them, list jobs and
//! workers, cancel jobs and download results (service `pathfarm.v1.Jobs`), plus the pieces the
//! worker shares (bearer-token interceptor, reconnect backoff).

use std::fmt;
use std::path::Path;
use std::time::Duration;

use pathfarm_proto::v1::{self, jobs_client::JobsClient};
use pathfarm_proto::MAX_CHUNK_BYTES;
use pathfarm_scene::Limits;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};
use tonic::{Code, Request, Status};

use crate::bundle::{self, BundleError};

/// Adds `authorization: Bearer TOKEN` (nothing without a token) and the protocol version
/// ([`pathfarm_proto::PROTOCOL_HEADER`]) to every call.
/// A worker's calls also carry its control stream's upload key
/// ([`pathfarm_proto::WORKER_KEY_HEADER`]) once it has one ([`Auth::with_worker_key`]).
#[derive(Clone)]
pub struct Auth {
    bearer: Option<MetadataValue<Ascii>>,
    worker_key: Option<WorkerKey>,
}

/// The upload key a worker's calls carry: set at each registration.
#[derive(Clone, Default)]
pub struct WorkerKey(std::sync::Arc<std::sync::Mutex<Option<MetadataValue<Ascii>>>>);

impl WorkerKey {
    /// Sets the key (`Registered.upload_key`) the following calls carry.
    pub fn set(&self, key: &[u8]) {
        let key = <[u8; 32]>::try_from(key).ok().map(crate::bundle::Digest);
        let value = key.and_then(|k| k.to_hex().parse().ok());
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = value;
    }

    fn get(&self) -> Option<MetadataValue<Ascii>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

impl Auth {
    /// The interceptor for `token`; a token that is not valid header text is an error.
    pub fn new(token: Option<&str>) -> Result<Self, ClientError> {
        let bearer =
            match token {
                None => None,
                Some(t) => Some(format!("Bearer {t}").parse().map_err(|_| {
                    ClientError::Usage("the token is not valid header text".into())
                })?),
            };
        Ok(Auth {
            bearer,
            worker_key: None,
        })
    }

    /// This interceptor, adding the upload key that `key` holds to every call.
    pub fn with_worker_key(mut self, key: WorkerKey) -> Self {
        self.worker_key = Some(key);
        self
    }
}

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.bearer {
            req.metadata_mut().insert("authorization", v.clone());
        }
        if let Some(v) = self.worker_key.as_ref().and_then(WorkerKey::get) {
            req.metadata_mut()
                .insert(pathfarm_proto::WORKER_KEY_HEADER, v);
        }
        req.metadata_mut().insert(
            pathfarm_proto::PROTOCOL_HEADER,
            MetadataValue::from(pathfarm_proto::PROTOCOL_VERSION),
        );
        Ok(req)
    }
}

/// A channel with the bearer-token interceptor.
pub type AuthChannel = InterceptedService<Channel, Auth>;

/// Where the coordinator is and how to reach it.
#[derive(Clone, Debug, Default)]
pub struct Remote {
    /// `http://host:port`, or `https://host:port` with [`Remote::tls_ca`].
    pub url: String,
    /// Bearer token sent on every call.
    pub token: Option<String>,
    /// PEM certificate(s) of the CA that signed the coordinator's certificate: the
    /// connection is TLS (rustls) and the coordinator's name is checked against the URL's host.
    pub tls_ca: Option<Vec<u8>>,
}

impl Remote {
    /// A plain-text remote (no token, no TLS).
    pub fn plain(url: impl Into<String>) -> Self {
        Remote {
            url: url.into(),
            ..Default::default()
        }
    }
}

/// The endpoint of `r` (`http://host:port`, or `https://` with a CA certificate).
pub fn endpoint(r: &Remote) -> Result<Endpoint, ClientError> {
    let url = &r.url;
    let ep = Endpoint::from_shared(url.to_string())
        .map(|e| {
            e.connect_timeout(Duration::from_secs(5))
                .initial_stream_window_size(STREAM_WINDOW)
                .initial_connection_window_size(CONNECTION_WINDOW)
                .tcp_nodelay(true)
        })
        .map_err(|e| ClientError::Usage(format!("invalid coordinator URL {url:?}: {e}")))?;
    let https = ep.uri().scheme_str() == Some("https");
    match (&r.tls_ca, https) {
        (Some(ca), true) => {
            let tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(ca));
            ep.tls_config(tls)
                .map_err(|e| ClientError::Usage(format!("TLS for {url}: {}", error_chain(&e))))
        }
        (Some(_), false) => Err(ClientError::Usage(format!(
            "a TLS CA certificate was given but the coordinator URL {url:?} is not https://"
        ))),
        (None, true) => Err(ClientError::Usage(format!(
            "{url}: an https:// coordinator needs the CA certificate that signed its \
             certificate (--tls-ca or PATHFARM_TLS_CA)"
        ))),
        (None, false) => Ok(ep),
    }
}

/// HTTP/2 flow-control windows of the farm's connections. h2's default of 64 KiB caps a
/// stream at one window per round trip: a 7 MB tile upload took 60 ms on loopback, a 50 MB
/// tree download 0.4 s. Trees and tiles are tens of MB, so the windows are too.
pub const STREAM_WINDOW: u32 = 16 << 20;
/// See [`STREAM_WINDOW`].
pub const CONNECTION_WINDOW: u32 = 64 << 20;

/// Exponential backoff for reconnects: 100 ms, doubling, at most 5 s.
#[derive(Clone, Debug)]
pub struct Backoff {
    next: Duration,
}

impl Backoff {
    pub const FIRST: Duration = Duration::from_millis(100);
    pub const MAX: Duration = Duration::from_secs(5);

    pub fn new() -> Self {
        Backoff { next: Self::FIRST }
    }

    /// The delay to wait now; the following one doubles (up to [`Backoff::MAX`]).
    pub fn next_delay(&mut self) -> Duration {
        let d = self.next;
        self.next = (self.next * 2).min(Self::MAX);
        d
    }

    /// Back to the first delay (after a success).
    pub fn reset(&mut self) {
        self.next = Self::FIRST;
    }
}

impl Default for Backoff {
    fn default() -> Self {
        Self::new()
    }
}

/// What can go wrong talking to the coordinator. A [`ClientError::Status`] carries the
/// coordinator's own message (e.g. its validation error).
#[derive(Debug)]
pub enum ClientError {
    /// Could not reach the coordinator.
    Connect {
        url: String,
        message: String,
    },
    /// The coordinator answered with an error status.
    Status(Status),
    /// Collecting the scene bundle failed.
    Bundle(BundleError),
    /// A bad argument or a malformed answer.
    Usage(String),
    Io(std::io::Error),
}

impl fmt::Display for ClientError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ClientError::Connect { url, message } => {
                write!(f, "cannot connect to the coordinator at {url}: {message}")
            }
            ClientError::Status(s) => {
                write!(f, "coordinator: {} ({:?})", s.message(), s.code())
            }
            ClientError::Bundle(e) => write!(f, "{e}"),
            ClientError::Usage(m) => write!(f, "{m}"),
            ClientError::Io(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for ClientError {}

impl From<Status> for ClientError {
    fn from(s: Status) -> Self {
        ClientError::Status(s)
    }
}

impl From<BundleError> for ClientError {
    fn from(e: BundleError) -> Self {
        ClientError::Bundle(e)
    }
}

impl ClientError {
    /// True for errors a retry may cure (the coordinator is down or restarting).
    pub fn is_unavailable(&self) -> bool {
        match self {
            ClientError::Connect { .. } => true,
            ClientError::Status(s) => matches!(s.code(), Code::Unavailable | Code::Unknown),
            _ => false,
        }
    }
}

/// How much to render (the guided training schedule's budget type).
pub use pathfarm_render::guided::Budget;

/// What `submit` sends besides the scene.
#[derive(Clone, Debug, Default)]
pub struct SubmitOptions {
    pub defines: Vec<(String, String)>,
    /// Replaces the scene's integrator (`--integrator`; [`pathfarm_scene::load_scene_as`]).
    pub integrator: Option<String>,
    /// Film width and height instead of the scene's.
    pub resolution: Option<(u32, u32)>,
    pub budget: Option<Budget>,
    pub seed: Option<u64>,
    pub tile_size: Option<u32>,
    pub priority: i32,
    pub name: String,
    /// The batch the job is a frame of (empty: none).
    pub batch: String,
}

/// A connection to the coordinator's `Jobs` service.
#[derive(Clone)]
pub struct Client {
    jobs: JobsClient<AuthChannel>,
}

/// A connected channel to the coordinator `r`.
async fn dial(r: &Remote) -> Result<Channel, ClientError> {
    endpoint(r)?
        .connect()
        .await
        .map_err(|e| ClientError::Connect {
            url: r.url.clone(),
            message: error_chain(&e),
        })
}

/// Connects to the coordinator at `url` (`http://host:port`), with an optional bearer token.
pub async fn connect(r: &Remote) -> Result<Client, ClientError> {
    let auth = Auth::new(r.token.as_deref())?;
    let channel = dial(r).await?;
    Ok(Client {
        jobs: JobsClient::with_interceptor(channel, auth),
    })
}

/// Asks the coordinator's `grpc.health.v1.Health` whether `service` ("" = the farm as a
/// whole) is serving: `Ok(true)` if SERVING. No token needed (health checks are open).
pub async fn health(r: &Remote, service: &str) -> Result<bool, ClientError> {
    use tonic_health::pb::{health_check_response::ServingStatus, health_client::HealthClient};
    let channel = dial(r).await?;
    let status = HealthClient::new(channel)
        .check(tonic_health::pb::HealthCheckRequest {
            service: service.to_string(),
        })
        .await?
        .into_inner()
        .status;
    Ok(status == ServingStatus::Serving as i32)
}

/// A manifest's proto form.
fn bundle_proto(m: &bundle::Manifest) -> v1::Bundle {
    v1::Bundle {
        root: m.root.clone(),
        files: m
            .files
            .iter()
            .map(|e| v1::BundleFile {
                path: e.path.clone(),
                digest: e.digest.0.to_vec(),
                size: e.size,
            })
            .collect(),
    }
}

/// Connects lazily: the channel dials on first use and redials after failures.
pub fn connect_lazy(r: &Remote) -> Result<Client, ClientError> {
    let auth = Auth::new(r.token.as_deref())?;
    let channel = endpoint(r)?.connect_lazy();
    Ok(Client {
        jobs: JobsClient::with_interceptor(channel, auth),
    })
}

/// `e` and its sources, joined with ": ".
pub fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut src = e.source();
    while let Some(x) = src {
        s.push_str(": ");
        s.push_str(&x.to_string());
        src = x.source();
    }
    s
}

/// Splits `data` into parts of at most `max` bytes (none for empty data).
pub fn chunks(data: &[u8], max: usize) -> impl Iterator<Item = &[u8]> {
    data.chunks(max.max(1))
}

/// A scene bundled for submission ([`Collected::of`]): its manifest and the local file of
/// each entry.
#[derive(Clone, Debug)]
pub struct Collected {
    manifest: bundle::Manifest,
    locals: Vec<std::path::PathBuf>,
}

impl Collected {
    /// Bundles `scene` as loaded with `defines`: its XML is parsed and every file it names
    /// opened and digested, meshes and images not decoded ([`bundle::collect`]); a caller
    /// that can do this while it waits for something else, as `pathfarm cluster` does while
    /// the coordinator starts, should.
    pub async fn of(
        scene: &Path,
        defines: &[(String, String)],
        integrator: Option<&str>,
    ) -> Result<Collected, ClientError> {
        let scene_path = scene.to_path_buf();
        let defines = defines.to_vec();
        let integrator = integrator.map(str::to_string);
        let (manifest, locals) = tokio::task::spawn_blocking(move || {
            let t0 = std::time::Instant::now();
            let limits = Limits::default();
            let collected = bundle::collect(&scene_path, &defines, integrator.as_deref(), &limits);
            let seconds = t0.elapsed().as_secs_f64();
            tracing::debug!(seconds, "bundled {}", scene_path.display());
            collected
        })
        .await
        .map_err(|e| ClientError::Usage(format!("bundling task failed: {e}")))??;
        Ok(Collected { manifest, locals })
    }

    /// [`Collected::of`] taking its arguments, for a task of its own.
    pub async fn of_owned(
        scene: std::path::PathBuf,
        defines: Vec<(String, String)>,
        integrator: Option<String>,
    ) -> Result<Collected, ClientError> {
        Self::of(&scene, &defines, integrator.as_deref()).await
    }
}

impl Client {
    /// Bundles `scene`, uploads the blobs the coordinator lacks and submits the job; returns
    /// its id.
    pub async fn submit(
        &mut self,
        scene: &Path,
        opts: &SubmitOptions,
    ) -> Result<String, ClientError> {
        let collected = Collected::of(scene, &opts.defines, opts.integrator.as_deref()).await?;
        self.submit_collected(&collected, opts).await
    }

    /// [`Client::submit`] of a scene bundled already (with `opts.defines`).
    pub async fn submit_collected(
        &mut self,
        collected: &Collected,
        opts: &SubmitOptions,
    ) -> Result<String, ClientError> {
        let Collected { manifest, locals } = collected;
        let digests: Vec<Vec<u8>> = manifest.files.iter().map(|e| e.digest.0.to_vec()).collect();
        let bundle = bundle_proto(manifest);
        let mut missing = Vec::new();
        for (i, batch) in digests.chunks(50_000).enumerate() {
            // the first request carries the manifest: a bundle over the coordinator's limits
            // is refused before anything is uploaded
            let r = self
                .jobs
                .find_missing_blobs(v1::FindMissingBlobsRequest {
                    digests: batch.to_vec(),
                    bundle: (i == 0).then(|| bundle.clone()),
                })
                .await?
                .into_inner();
            missing.extend(r.missing);
        }
        for m in &missing {
            let Some(i) = manifest.files.iter().position(|e| e.digest.0[..] == m[..]) else {
                return Err(ClientError::Usage(
                    "the coordinator asked for a blob the bundle does not hold".into(),
                ));
            };
            self.upload_file(&locals[i], &manifest.files[i]).await?;
        }
        tracing::info!(
            "{}: uploaded {} of {} files (the coordinator had the others)",
            manifest.root,
            missing.len(),
            manifest.files.len()
        );
        let (spp, time) = match opts.budget {
            Some(Budget::Spp(n)) => (Some(n), None),
            Some(Budget::Seconds(t)) => (None, Some(t)),
            None => (None, None),
        };
        let budget = match (spp, time) {
            (Some(n), _) => Some(v1::job_settings::Budget::Spp(n)),
            (None, Some(t)) => Some(v1::job_settings::Budget::TimeSeconds(t)),
            _ => None,
        };
        let req = v1::SubmitJobRequest {
            bundle: Some(bundle),
            settings: Some(v1::JobSettings {
                scene: Some(v1::SceneSettings {
                    integrator: opts.integrator.clone(),
                    defines: opts
                        .defines
                        .iter()
                        .map(|(n, v)| v1::Define {
                            name: n.clone(),
                            value: v.clone(),
                        })
                        .collect(),
                    resolution: opts
                        .resolution
                        .map(|(width, height)| v1::Resolution { width, height }),
                    seed: opts.seed,
                }),
                budget,
                tile_size: opts.tile_size.unwrap_or(0),
            }),
            priority: opts.priority,
            name: opts.name.clone(),
            batch: opts.batch.clone(),
        };
        let r = self.jobs.submit_job(req).await?.into_inner();
        Ok(r.job_id)
    }

    /// Uploads one local file as a blob, streamed in parts of at most 1 MiB.
    async fn upload_file(
        &mut self,
        local: &Path,
        entry: &bundle::ManifestEntry,
    ) -> Result<(), ClientError> {
        let (tx, rx) = tokio::sync::mpsc::channel::<v1::BlobChunk>(4);
        let header = v1::BlobChunk {
            part: Some(v1::blob_chunk::Part::Header(v1::BlobHeader {
                digest: entry.digest.0.to_vec(),
                size: entry.size,
            })),
        };
        let path = local.to_path_buf();
        let reader = tokio::task::spawn_blocking(move || -> std::io::Result<()> {
            use std::io::Read;
            if tx.blocking_send(header).is_err() {
                return Ok(());
            }
            let mut f = std::fs::File::open(&path)?;
            loop {
                let mut buf = vec![0u8; MAX_CHUNK_BYTES];
                let mut n = 0;
                while n < buf.len() {
                    let k = f.read(&mut buf[n..])?;
                    if k == 0 {
                        break;
                    }
                    n += k;
                }
                if n == 0 {
                    return Ok(());
                }
                buf.truncate(n);
                let msg = v1::BlobChunk {
                    part: Some(v1::blob_chunk::Part::Data(buf)),
                };
                if tx.blocking_send(msg).is_err() {
                    return Ok(());
                }
            }
        });
        let result = self
            .jobs
            .upload_blob(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await;
        match reader.await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(ClientError::Io(e)),
            Err(e) => return Err(ClientError::Usage(format!("upload task failed: {e}"))),
        }
        result?;
        Ok(())
    }

    /// Watches `job` until a terminal state, calling `on_status` on every status; returns
    /// the terminal status. Rides through coordinator restarts: an unavailable coordinator
    /// is retried with backoff, forever.
    pub async fn watch(
        &mut self,
        job: &str,
        mut on_status: impl FnMut(&v1::JobStatus),
    ) -> Result<v1::JobStatus, ClientError> {
        let mut backoff = Backoff::new();
        loop {
            let attempt: Result<Option<v1::JobStatus>, ClientError> = async {
                let mut stream = self
                    .jobs
                    .watch_job(v1::WatchJobRequest {
                        job_id: job.to_string(),
                    })
                    .await?
                    .into_inner();
                let mut last = None;
                while let Some(s) = stream.message().await? {
                    backoff.reset();
                    on_status(&s);
                    if is_terminal(s.state) {
                        return Ok(Some(s));
                    }
                    last = Some(s);
                }
                let _ = last;
                Ok(None)
            }
            .await;
            match attempt {
                Ok(Some(s)) => return Ok(s),
                Ok(None) => {}
                Err(e) if e.is_unavailable() => {
                    tracing::debug!("watch {job}: {e}; retrying");
                }
                Err(e) => return Err(e),
            }
            tokio::time::sleep(backoff.next_delay()).await;
        }
    }

    /// One job's status and settings.
    pub async fn status(&mut self, job: &str) -> Result<v1::GetJobResponse, ClientError> {
        Ok(self
            .jobs
            .get_job(v1::GetJobRequest {
                job_id: job.to_string(),
            })
            .await?
            .into_inner())
    }

    /// Every job the coordinator knows, oldest first.
    pub async fn list_jobs(&mut self) -> Result<Vec<v1::JobStatus>, ClientError> {
        Ok(self
            .jobs
            .list_jobs(v1::ListJobsRequest::default())
            .await?
            .into_inner()
            .jobs)
    }

    /// The coordinator's workers.
    pub async fn list_workers(&mut self) -> Result<Vec<v1::WorkerInfo>, ClientError> {
        Ok(self
            .jobs
            .list_workers(v1::ListWorkersRequest {})
            .await?
            .into_inner()
            .workers)
    }

    /// Cancels `job`.
    pub async fn cancel(&mut self, job: &str) -> Result<v1::CancelJobResponse, ClientError> {
        Ok(self
            .jobs
            .cancel_job(v1::CancelJobRequest {
                job_id: job.to_string(),
                reason: "cancelled from the command line".into(),
            })
            .await?
            .into_inner())
    }

    /// Sets `job`'s priority (higher first).
    pub async fn set_priority(
        &mut self,
        job: &str,
        priority: i32,
    ) -> Result<v1::SetJobPriorityResponse, ClientError> {
        let req = v1::SetJobPriorityRequest {
            job_id: job.to_string(),
            priority,
        };
        Ok(self.jobs.set_job_priority(req).await?.into_inner())
    }

    /// Downloads one result of `job`, verified against the header's size and digest.
    pub async fn download(
        &mut self,
        job: &str,
        kind: v1::ResultKind,
    ) -> Result<Vec<u8>, ClientError> {
        let mut stream = self
            .jobs
            .download_result(v1::DownloadResultRequest {
                job_id: job.to_string(),
                kind: kind as i32,
            })
            .await?
            .into_inner();
        read_data_stream(&mut stream).await
    }
}

/// Reads a DataHeader-then-parts stream, checking size and digest.
pub async fn read_data_stream(
    stream: &mut tonic::Streaming<v1::DataChunk>,
) -> Result<Vec<u8>, ClientError> {
    let header = match stream.message().await? {
        Some(v1::DataChunk {
            part: Some(v1::data_chunk::Part::Header(h)),
        }) => h,
        _ => return Err(ClientError::Usage("download: no header first".into())),
    };
    let mut data = Vec::with_capacity(header.total_size.min(1 << 30) as usize);
    while let Some(c) = stream.message().await? {
        match c.part {
            Some(v1::data_chunk::Part::Data(d)) => data.extend_from_slice(&d),
            _ => return Err(ClientError::Usage("download: a second header".into())),
        }
        if data.len() as u64 > header.total_size {
            return Err(ClientError::Usage(
                "download: more bytes than announced".into(),
            ));
        }
    }
    if data.len() as u64 != header.total_size {
        return Err(ClientError::Usage(format!(
            "download: got {} bytes, expected {}",
            data.len(),
            header.total_size
        )));
    }
    if blake3::hash(&data).as_bytes()[..] != header.digest[..] {
        return Err(ClientError::Usage("download: digest mismatch".into()));
    }
    Ok(data)
}

/// DONE, FAILED or CANCELLED.
pub fn is_terminal(state: i32) -> bool {
    matches!(
        v1::JobState::try_from(state),
        Ok(v1::JobState::Done | v1::JobState::Failed | v1::JobState::Cancelled)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_to_five_seconds_and_resets() {
        let mut b = Backoff::new();
        let ms: Vec<u128> = (0..9).map(|_| b.next_delay().as_millis()).collect();
        assert_eq!(ms, [100, 200, 400, 800, 1600, 3200, 5000, 5000, 5000]);
        b.reset();
        assert_eq!(b.next_delay(), Duration::from_millis(100));
    }

    #[test]
    fn chunks_are_at_most_max() {
        let data = vec![7u8; 2 * MAX_CHUNK_BYTES + 5];
        let parts: Vec<usize> = chunks(&data, MAX_CHUNK_BYTES).map(|c| c.len()).collect();
        assert_eq!(parts, [MAX_CHUNK_BYTES, MAX_CHUNK_BYTES, 5]);
        assert_eq!(chunks(&[], MAX_CHUNK_BYTES).count(), 0);
    }

    #[test]
    fn auth_header() {
        use tonic::service::Interceptor;
        let mut a = Auth::new(Some("s3cret")).unwrap();
        let r = a.call(Request::new(())).unwrap();
        assert_eq!(r.metadata().get("authorization").unwrap(), "Bearer s3cret");
        let mut none = Auth::new(None).unwrap();
        assert!(none
            .call(Request::new(()))
            .unwrap()
            .metadata()
            .get("authorization")
            .is_none());
    }
}
