//! The answer to `FlushRecords`: the quadtree records a job's tree copy kept for a tree
//! version (`PassSpec.hold_records` leases), uploaded once, or word that they are lost.
//!
//! Invariant: the records a worker uploads are the sums over exactly the tiles the
//! coordinator accepted from it in the flushed version and epoch. Records of any other
//! tile that rendered into the copy (rejected, failed, cancelled after rendering) poison it
//! ([`super::JobTree::poisoned`]), and the session loop answers a flush only once every
//! upload of the job has its outcome.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use pathfarm_proto::v1;
use pathfarm_proto::MAX_CHUNK_BYTES;

use super::{Api, Shared};

/// Takes the records asked for by `f` (on a blocking thread) and uploads them.
pub(super) async fn send(shared: Arc<Shared>, mut api: Api, worker_id: u64, f: v1::FlushRecords) {
    let job = f.job_id.clone();
    let sh = shared.clone();
    let (header, bytes) = match tokio::task::spawn_blocking(move || take(&sh, worker_id, f)).await {
        Ok(taken) => taken,
        Err(e) => return tracing::error!("job {job}: taking the records: {e}"),
    };
    let lost = header.lost;
    let size = bytes.len();
    let msgs = messages(header, &bytes);
    match api.upload_records(tokio_stream::iter(msgs)).await {
        Ok(ack) if ack.get_ref().accepted => match lost {
            true => tracing::warn!("job {job}: told the coordinator the records are lost"),
            false => tracing::info!("job {job}: records uploaded ({size} bytes)"),
        },
        Ok(ack) => tracing::warn!("job {job}: records refused: {}", ack.get_ref().detail),
        // The coordinator notices: the control stream breaks with the connection, or it
        // was restarted; either way the job rolls back.
        Err(s) => tracing::warn!("job {job}: records upload failed: {}", s.message()),
    }
}

/// Fault injection for tests: with `PATHFARM_FAULT_LOSE_RECORDS=N` in its environment a
/// worker answers its first N flushes with `lost`, as one whose records were spoiled would,
/// so a test can make the coordinator roll a job back at a known point.
fn injected_loss() -> bool {
    static ASKED: AtomicU64 = AtomicU64::new(0);
    let n: u64 = std::env::var("PATHFARM_FAULT_LOSE_RECORDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    ASKED.fetch_add(1, Ordering::Relaxed) < n
}

/// The header and bytes answering `f`: the copy's records if it holds them for `f`'s tree
/// version and epoch, unpoisoned, with no joint upload's records in it; else `lost`.
fn take(shared: &Shared, worker_id: u64, f: v1::FlushRecords) -> (v1::RecordsHeader, Vec<u8>) {
    let taken = if injected_loss() {
        None
    } else {
        let mut c = shared.caches.lock().expect("cache lock");
        c.trees
            .get_mut(&f.job_id)
            .filter(|t| {
                t.tree_digest == f.tree_digest
                    && t.epoch == f.records_epoch
                    && t.holds
                    && !t.poisoned
                    && t.recording.is_none()
            })
            .map(|t| {
                t.holds = false;
                t.tree.take_stats()
            })
    };
    let bytes = taken.as_ref().map(|r| r.encode()).unwrap_or_default();
    let header = v1::RecordsHeader {
        worker_id,
        job_id: f.job_id,
        tree_digest: f.tree_digest,
        records_epoch: f.records_epoch,
        lost: taken.is_none(),
        size: bytes.len() as u64,
        digest: blake3::hash(&bytes).as_bytes().to_vec(),
    };
    (header, bytes)
}

/// The header, then `bytes` in data parts of at most [`MAX_CHUNK_BYTES`].
fn messages(header: v1::RecordsHeader, bytes: &[u8]) -> Vec<v1::RecordsUpload> {
    use v1::records_upload::Part;
    let mut out = vec![v1::RecordsUpload {
        part: Some(Part::Header(header)),
    }];
    out.extend(bytes.chunks(MAX_CHUNK_BYTES).map(|c| v1::RecordsUpload {
        part: Some(Part::Data(c.to_vec())),
    }));
    out
}
