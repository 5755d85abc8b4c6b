//! Session checkpoints on disk, and the collection of blobs nothing refers to any more.
//!
//! Between iterations a job's session is checkpointed ([`Session::checkpoint`]) so that a
//! restarted coordinator resumes it. The parts are blobs: the state, each film, and the tree
//! (the very blob the next unit's workers fetch, so it is encoded once). A finished
//! iteration's film never changes, so each is written once for the whole job. The parts are
//! written and made durable off the job's critical path, in the background; the job record
//! names them only once they are all on disk, so a crash at any moment leaves the record
//! naming a complete checkpoint (the previous one until the new one is complete).
//!
//! Blobs a job stops referring to (the tree, fractions and estimate of a finished unit, the
//! parts of a replaced checkpoint) become garbage candidates, deleted at the next collection
//! unless some job (identical jobs share blobs) still refers to them.

use std::collections::HashSet;
use std::sync::Arc;
use std::time::Instant;

use pathfarm_render::checkpoint::{self, Checkpoint};
use pathfarm_render::guided::{FallbackPolicy, Session};
use pathfarm_render::Region;

use super::db::JobRecord;
use super::{job_name, Prepared, Shared, State};
use crate::bundle::Digest;

/// A checkpoint's parts as digests, as a job record names them.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Parts {
    pub(crate) state: Digest,
    pub(crate) films: Vec<Digest>,
    pub(crate) tree: Digest,
}

impl Parts {
    fn of(record: &JobRecord) -> Option<Parts> {
        let d = |b: &[u8]| <[u8; 32]>::try_from(b).ok().map(Digest);
        Some(Parts {
            state: d(&record.checkpoint)?,
            films: record
                .checkpoint_films
                .iter()
                .map(|f| d(f))
                .collect::<Option<_>>()?,
            tree: d(&record.checkpoint_tree)?,
        })
    }

    fn digests(&self) -> impl Iterator<Item = Digest> + '_ {
        [self.state, self.tree]
            .into_iter()
            .chain(self.films.iter().copied())
    }

    fn set(&self, record: &mut JobRecord) {
        record.checkpoint = self.state.0.to_vec();
        record.checkpoint_tree = self.tree.0.to_vec();
        record.checkpoint_films = self.films.iter().map(|f| f.0.to_vec()).collect();
    }
}

/// Removes the checkpoint a record names, returning its parts (garbage candidates).
pub(crate) fn take_parts(record: &mut JobRecord) -> Vec<Digest> {
    let parts = Parts::of(record);
    record.checkpoint.clear();
    record.checkpoint_tree.clear();
    record.checkpoint_films.clear();
    parts.map(|p| p.digests().collect()).unwrap_or_default()
}

impl Shared {
    /// Takes job `n`'s checkpoint if one can be taken now (between iterations). The tree blob
    /// is stored now (the next unit publishes it); the rest is written in the background and
    /// recorded when it is durable. Returns the seconds spent here, on the critical path.
    pub(crate) fn save_checkpoint(self: &Arc<Self>, st: &mut State, n: u64) -> f64 {
        let t0 = Instant::now();
        let Some(a) = st.jobs.get_mut(&n).and_then(|j| j.active.as_mut()) else {
            return 0.0;
        };
        let Some(cp) = a.session.checkpoint() else {
            return 0.0;
        };
        let version = a.session.tree_version();
        let tree = match a.tree_digest {
            Some((v, d)) if v == version => d,
            _ => match self.blobs.put_unsynced(&a.session.tree().encode()) {
                Ok(d) => {
                    if let Some((_, old)) = a.tree_digest.replace((version, d)) {
                        st.garbage.push(old);
                    }
                    d
                }
                Err(e) => {
                    tracing::error!(job = %job_name(n), "checkpoint not stored: {e}");
                    return t0.elapsed().as_secs_f64();
                }
            },
        };
        a.checkpoint_seq += 1;
        let seq = a.checkpoint_seq;
        let shared = self.clone();
        tokio::task::spawn_blocking(move || shared.write_checkpoint(n, seq, cp, tree));
        t0.elapsed().as_secs_f64()
    }

    /// Writes a checkpoint's parts durably and records them, unless the job has ended or a
    /// later checkpoint was recorded meanwhile.
    fn write_checkpoint(&self, n: u64, seq: u64, cp: Checkpoint, tree: Digest) {
        let t0 = Instant::now();
        let written = (|| -> std::io::Result<Parts> {
            let films = cp
                .films
                .iter()
                .map(|f| self.blobs.put(f))
                .collect::<std::io::Result<Vec<_>>>()?;
            self.blobs.sync(&tree)?;
            let state = self.blobs.put(&cp.state)?;
            Ok(Parts { state, films, tree })
        })();
        let mut st = self.lock();
        let parts = match written {
            Ok(p) => p,
            Err(e) => return tracing::error!(job = %job_name(n), "checkpoint not stored: {e}"),
        };
        let Some(job) = st.jobs.get_mut(&n) else {
            return;
        };
        let current = job.active.as_ref().is_some_and(|a| a.checkpoint_seq == seq);
        // A part equal to a blob in the garbage may have been collected since it was written
        // (collections run under the lock): such a checkpoint is not recorded.
        let complete = parts.digests().all(|d| self.blobs.has(&d));
        if !complete {
            tracing::warn!(job = %job_name(n), "checkpoint not recorded: a part was collected");
        }
        if !current || !complete {
            st.garbage.extend(parts.digests());
            self.collect_garbage(&mut st);
            return;
        }
        let old = take_parts(&mut job.record);
        parts.set(&mut job.record);
        if let Err(e) = self.db.put(n, &job.record) {
            tracing::error!(job = %job_name(n), "checkpoint not recorded: {e}");
        }
        tracing::info!(job = %job_name(n), seconds = t0.elapsed().as_secs_f64(), "checkpoint recorded");
        st.garbage.extend(old);
        self.collect_garbage(&mut st);
    }

    /// The session of job `n` restored from the checkpoint its record names, if it has one
    /// that reads back (a damaged one is logged and the job starts over: the same bits,
    /// later).
    pub(crate) fn resume(
        &self,
        n: u64,
        record: &JobRecord,
        p: &Prepared,
        tiles: &[Region],
    ) -> Option<Session> {
        let parts = Parts::of(record)?;
        let read = |d: &Digest| {
            std::fs::read(self.blobs.path(d)).map_err(|e| format!("blob {}: {e}", d.to_hex()))
        };
        let restored = (|| -> Result<Session, String> {
            let cp = Checkpoint {
                state: read(&parts.state)?,
                films: parts.films.iter().map(read).collect::<Result<_, _>>()?,
            };
            let tree = checkpoint::decode_tree(&read(&parts.tree)?).map_err(|e| e.to_string())?;
            Session::restore(
                &p.params,
                p.budget,
                tiles.to_vec(),
                FallbackPolicy::Rule,
                &cp,
                tree,
            )
            .map_err(|e| e.to_string())
        })();
        match restored {
            Ok(s) => {
                tracing::info!(
                    job = %job_name(n),
                    "resumed from its checkpoint after iteration {} ({} spp done)",
                    s.iteration(),
                    s.spp_done()
                );
                Some(s)
            }
            Err(e) => {
                tracing::warn!(job = %job_name(n), "checkpoint unusable, starting over: {e}");
                None
            }
        }
    }

    /// Deletes the garbage candidates no job refers to.
    pub(crate) fn collect_garbage(&self, st: &mut State) {
        if st.garbage.is_empty() {
            return;
        }
        let live = referenced(st);
        for d in std::mem::take(&mut st.garbage) {
            if !live.contains(&d) {
                let _ = std::fs::remove_file(self.blobs.path(&d));
            }
        }
    }
}

/// Every blob some job refers to: its bundle's files, its results, its checkpoint, and the
/// inputs its unit in flight publishes.
fn referenced(st: &State) -> HashSet<Digest> {
    let mut live = HashSet::new();
    let d = |b: &[u8]| <[u8; 32]>::try_from(b).ok().map(Digest);
    for job in st.jobs.values() {
        let r = &job.record;
        if let Some(b) = r.request.as_ref().and_then(|q| q.bundle.as_ref()) {
            live.extend(b.files.iter().filter_map(|f| d(&f.digest)));
        }
        live.extend([&r.exr, &r.png, &r.tree].into_iter().filter_map(|x| d(x)));
        if let Some(p) = Parts::of(r) {
            live.extend(p.digests());
        }
        live.extend(job.active.iter().flat_map(|a| a.blobs()));
    }
    live
}
