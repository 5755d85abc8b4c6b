//! Deletion of uploaded blobs that no job refers to once they are older than the operator's
//! grace period ([`super::Resources::blob_grace`]): a client that uploads a bundle and never
//! submits it (or whose submission is refused) cannot fill the disk, and a refused
//! submission never deletes blobs another client uploaded for its own job (identical files
//! share one blob).
//!
//! A blob's age is its file's modification time, refreshed whenever a client is told the
//! blob is present (`FindMissingBlobs`, `UploadBlob` of a blob already held), so the grace
//! period runs from the last time a client could have counted on it.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use super::{checkpoints, Shared};

/// How often the blob directory is listed: every 30 s, or twice per grace period if that
/// is shorter.
fn sweep_every(grace: Duration) -> Duration {
    (grace / 2).clamp(Duration::from_millis(100), Duration::from_secs(30))
}

impl Shared {
    /// Starts a sweep in the background unless one is running or one started within
    /// [`sweep_every`].
    pub(crate) fn maybe_sweep(self: &Arc<Self>) {
        let now_ms = self.epoch.elapsed().as_millis() as u64;
        let last = self.last_sweep_ms.load(Ordering::Relaxed);
        let every = sweep_every(self.cfg.resources.blob_grace).as_millis() as u64;
        if last != 0 && now_ms < last + every {
            return;
        }
        if self.sweeping.swap(true, Ordering::AcqRel) {
            return;
        }
        self.last_sweep_ms.store(now_ms.max(1), Ordering::Relaxed);
        let shared = self.clone();
        tokio::task::spawn_blocking(move || {
            shared.sweep();
            shared.sweeping.store(false, Ordering::Release);
        });
    }

    /// Lists the blobs older than the grace period (off the state lock), then deletes those
    /// no job refers to, checking each one's age again under the lock. Returns how many
    /// were deleted.
    pub(crate) fn sweep(&self) -> u64 {
        let grace = self.cfg.resources.blob_grace;
        let old = self.blobs.older_than(grace);
        if old.is_empty() {
            return 0;
        }
        let st = self.lock();
        let live = checkpoints::referenced(&st);
        let mut deleted = 0;
        for d in old.into_iter().filter(|d| !live.contains(d)) {
            if self.blobs.age(&d).is_some_and(|age| age >= grace) && self.blobs.remove(&d) {
                deleted += 1;
            }
        }
        drop(st);
        if deleted > 0 {
            tracing::info!(deleted, "unreferenced blobs deleted after the grace period");
            self.metrics.blobs_expired(deleted);
        }
        deleted
    }
}

/// How long ago `modified` was (zero if in the future).
pub(crate) fn age_of(modified: SystemTime) -> Duration {
    SystemTime::now()
        .duration_since(modified)
        .unwrap_or(Duration::ZERO)
}
