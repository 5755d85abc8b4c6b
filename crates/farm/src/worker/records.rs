//! The quadtree records a worker keeps for the coordinator (`PassSpec.hold_records`): the
//! sums over its accepted recording tiles of one tree version and records epoch, uploaded
//! once when the coordinator asks (`FlushRecords`), instead of with every unit.
//!
//! Invariant: what a worker uploads for a version and epoch is the merge of exactly the
//! records of its uploads the coordinator accepted, and it says which leases those were
//! ([`Coverage`]: the coordinator refuses records that cover others) (a joint's records leave the tree with
//! it and are kept only once its upload is acknowledged); when it cannot vouch for that (an
//! upload whose outcome it never learned, a lost upload task) it answers `lost`, and the
//! coordinator starts the job again from its checkpoint under a new epoch. The session loop
//! answers a flush only once every upload of the job has its outcome.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};

use pathfarm_guide::IterationStats;
use pathfarm_proto::v1;
use pathfarm_proto::MAX_CHUNK_BYTES;

use super::upload::HeldKey;
use super::Api;
use crate::chunked;
use crate::driver::Coverage;

/// One job's kept records.
pub(super) struct Held {
    key: HeldKey,
    /// `None`: lost (some of them cannot be vouched for).
    records: Option<Kept>,
}

/// Records kept, and the leases whose records they are the sums of.
pub(super) struct Kept {
    stats: IterationStats,
    covered: Coverage,
}

/// Adds an accepted upload's records to those kept for `job` (replacing records of an older
/// version or epoch, which the coordinator no longer wants). Uploads run side by side, so an
/// upload from before a roll back can be acknowledged after one of the new epoch: its
/// records are not wanted, and do not replace the new epoch's. `tests/it/farm_sim.rs` has
/// its own copy of this rule for the seeded simulation.
pub(super) fn keep(
    held: &mut HashMap<String, Held>,
    (job, leases): (&str, &[u64]),
    key: HeldKey,
    r: IterationStats,
) {
    match held.get_mut(job) {
        Some(h) if h.key == key => {
            if injected_forgetting() {
                tracing::warn!("job {job}: leases {leases:?}: records forgotten (fault injection)");
                return;
            }
            if let Some(mine) = &mut h.records {
                if mine.stats.merge(&r).is_err() {
                    tracing::error!("job {job}: records of another tree structure: lost");
                    h.records = None;
                } else {
                    leases.iter().for_each(|&id| mine.covered.add(id));
                }
            }
        }
        Some(h) if h.key.epoch > key.epoch => {}
        _ => {
            let kept = Kept {
                stats: r,
                covered: Coverage::of(leases.iter().copied()),
            };
            let h = Held {
                key,
                records: Some(kept),
            };
            held.insert(job.to_string(), h);
        }
    }
}

/// Marks `job`'s records of `key` lost (not those of a later epoch, as [`keep`]).
pub(super) fn lose(held: &mut HashMap<String, Held>, job: &str, key: HeldKey) {
    if held.get(job).is_some_and(|h| h.key.epoch > key.epoch) {
        return;
    }
    tracing::warn!("job {job}: an upload's outcome is unknown: the records kept are lost");
    held.insert(job.to_string(), Held { key, records: None });
}

/// The records `f` asks for, if kept and intact (they leave the worker either way). Records
/// of another version or epoch stay: a flush the coordinator sent before it rolled the job
/// back can be answered after this worker kept records of the new epoch, which the
/// coordinator will ask for next (taking them here would hand in the new epoch's records
/// without those of the uploads accepted before, and the guide would differ).
pub(super) fn take(held: &mut HashMap<String, Held>, f: &v1::FlushRecords) -> Option<Kept> {
    if injected_loss() {
        return None;
    }
    let wanted = HeldKey {
        tree_digest: f.tree_digest.clone(),
        epoch: f.records_epoch,
    };
    if held.get(&f.job_id)?.key != wanted {
        return None;
    }
    held.remove(&f.job_id)?.records
}

/// Fault injection for tests: with `PATHFARM_FAULT_LOSE_RECORDS=N` in its environment a
/// worker answers its first N flushes with `lost`, as one that cannot vouch for its records
/// would, so a test can make the coordinator roll a job back at a known point.
fn injected_loss() -> bool {
    static ASKED: AtomicU64 = AtomicU64::new(0);
    first_n("PATHFARM_FAULT_LOSE_RECORDS", &ASKED)
}

/// Fault injection for tests: with `PATHFARM_FAULT_FORGET_RECORDS=N` a worker forgets the
/// records of its first N accepted recording uploads that join records it already keeps,
/// and hands in the rest as if complete, as a worker with a bookkeeping slip would: the
/// coordinator must tell by their coverage.
fn injected_forgetting() -> bool {
    static KEPT: AtomicU64 = AtomicU64::new(0);
    first_n("PATHFARM_FAULT_FORGET_RECORDS", &KEPT)
}

/// Whether this is one of the first N calls counted by `calls`, N from the environment
/// variable `var` (0 when unset).
fn first_n(var: &str, calls: &AtomicU64) -> bool {
    let n: u64 = std::env::var(var)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    calls.fetch_add(1, Ordering::Relaxed) < n
}

/// Uploads `records` in answer to `f` (`None`: lost), encoding them on a blocking thread.
pub(super) async fn send(mut api: Api, worker_id: u64, f: v1::FlushRecords, records: Option<Kept>) {
    let job = f.job_id.clone();
    let lost = records.is_none();
    let covered = records.as_ref().map(|k| k.covered).unwrap_or_default();
    let encode = move || records.map(|k| k.stats.encode());
    let bytes = match tokio::task::spawn_blocking(encode).await {
        Ok(b) => b.unwrap_or_default(),
        Err(e) => return tracing::error!("job {job}: encoding the records: {e}"),
    };
    let header = v1::RecordsHeader {
        worker_id,
        job_id: f.job_id,
        tree_digest: f.tree_digest,
        records_epoch: f.records_epoch,
        lost,
        size: bytes.len() as u64,
        digest: blake3::hash(&bytes).as_bytes().to_vec(),
        covered_leases: covered.leases(),
        covered_digest: covered.digest(),
    };
    let size = bytes.len();
    let messages = chunked::messages::<v1::RecordsUpload>(header, &[&bytes], MAX_CHUNK_BYTES);
    match api.upload_records(tokio_stream::iter(messages)).await {
        Ok(ack) if ack.get_ref().accepted => match lost {
            true => tracing::warn!("job {job}: told the coordinator the records are lost"),
            false => tracing::info!("job {job}: records uploaded ({size} bytes)"),
        },
        Ok(ack) => tracing::warn!("job {job}: records refused: {}", ack.get_ref().detail),
        // The coordinator notices: the control stream breaks with the connection, or it
        // restarted; either way the job rolls back, or the holder times out.
        Err(s) => tracing::warn!("job {job}: records upload failed: {}", s.message()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(epoch: u64) -> HeldKey {
        HeldKey {
            tree_digest: vec![7; 32],
            epoch,
        }
    }

    fn flush(epoch: u64) -> v1::FlushRecords {
        v1::FlushRecords {
            job_id: "job-1".into(),
            tree_digest: vec![7; 32],
            records_epoch: epoch,
        }
    }

    #[test]
    fn a_late_flush_of_an_earlier_epoch_leaves_the_records_of_the_current_one() {
        let mut held = HashMap::new();
        keep(&mut held, ("job-1", &[]), key(0), IterationStats::default());
        // The job rolled back (epoch 1) and an upload of the new epoch was accepted before
        // the flush of epoch 0 was answered.
        keep(&mut held, ("job-1", &[]), key(1), IterationStats::default());
        assert!(take(&mut held, &flush(0)).is_none(), "epoch 0's are gone");
        assert!(take(&mut held, &flush(1)).is_some(), "epoch 1's are kept");
        assert!(held.is_empty(), "taken records leave the worker");
        assert!(take(&mut held, &flush(1)).is_none(), "and are taken once");
    }

    #[test]
    fn an_upload_from_before_a_roll_back_acknowledged_late_leaves_the_new_epochs_records() {
        let mut held = HashMap::new();
        keep(&mut held, ("job-1", &[]), key(1), IterationStats::default());
        keep(&mut held, ("job-1", &[]), key(0), IterationStats::default());
        lose(&mut held, "job-1", key(0));
        assert!(take(&mut held, &flush(1)).is_some(), "epoch 1's are kept");
    }

    #[test]
    fn kept_records_say_which_accepted_leases_they_cover() {
        let mut held = HashMap::new();
        keep(
            &mut held,
            ("job-1", &[4, 5]),
            key(0),
            IterationStats::default(),
        );
        // an upload of the earlier epoch acknowledged late is not covered
        keep(
            &mut held,
            ("job-1", &[1]),
            key(3),
            IterationStats::default(),
        );
        keep(
            &mut held,
            ("job-1", &[6]),
            key(3),
            IterationStats::default(),
        );
        keep(
            &mut held,
            ("job-1", &[2]),
            key(0),
            IterationStats::default(),
        );
        keep(
            &mut held,
            ("job-1", &[7, 8]),
            key(3),
            IterationStats::default(),
        );
        let kept = take(&mut held, &flush(3)).expect("kept");
        assert_eq!(kept.covered, Coverage::of([1, 6, 7, 8]));
    }

    #[test]
    fn lost_records_are_answered_lost_for_their_key() {
        let mut held = HashMap::new();
        keep(&mut held, ("job-1", &[]), key(2), IterationStats::default());
        lose(&mut held, "job-1", key(2));
        assert!(take(&mut held, &flush(2)).is_none());
        assert!(held.is_empty());
    }
}
