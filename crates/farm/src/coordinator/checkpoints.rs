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
use std::sync::{Arc, Weak};
use std::time::Instant;

use pathfarm_render::checkpoint::{self, Checkpoint};
use pathfarm_render::film::Film;
use pathfarm_render::guided::{FallbackPolicy, Session};
use pathfarm_render::Region;

use super::db::JobRecord;
use super::store::BlobStore;
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

/// A checkpoint taken on the critical path, to be written in the background: the films are
/// the session's own (shared), encoded there unless an earlier checkpoint stored them.
struct Unwritten {
    state: Vec<u8>,
    films: Vec<FilmPart>,
    tree: Digest,
}

/// One film of an [`Unwritten`] checkpoint, with the digest it was stored under by an
/// earlier checkpoint of the job, if any.
struct FilmPart {
    film: Arc<Film>,
    stored: Option<Digest>,
}

impl FilmPart {
    /// Looks `film` up among the films earlier checkpoints stored. The cache holds `Weak`s:
    /// they keep an allocation from being reused while they exist, so the same address is
    /// the same film (a film the session changes moves to a new allocation,
    /// [`Arc::make_mut`]).
    fn of(film: Arc<Film>, stored: &[(Weak<Film>, Digest)]) -> FilmPart {
        let same = stored
            .iter()
            .find(|(w, _)| std::ptr::eq(w.as_ptr(), Arc::as_ptr(&film)));
        FilmPart {
            stored: same.map(|(_, d)| *d),
            film,
        }
    }

    /// The film's blob: the stored one if it is still there, else encoded and stored now.
    fn write(&self, blobs: &BlobStore) -> std::io::Result<Digest> {
        match self.stored {
            Some(d) if blobs.has(&d) => Ok(d),
            _ => blobs.put_written(|sink| checkpoint::write_film(&self.film, sink)),
        }
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
    /// Takes job `n`'s checkpoint if one can be taken now (between iterations) and is due
    /// ([`super::CoordinatorConfig::checkpoint_interval`]). The tree blob
    /// is stored now (the next unit publishes it); the rest is written in the background and
    /// recorded when it is durable. Returns the seconds spent here, on the critical path.
    pub(crate) fn save_checkpoint(self: &Arc<Self>, st: &mut State, n: u64) -> f64 {
        let t0 = Instant::now();
        let Some(a) = st.jobs.get_mut(&n).and_then(|j| j.active_mut()) else {
            return 0.0;
        };
        let now = self.now();
        if now < a.checkpoint_due {
            return 0.0;
        }
        let Some(cp) = a.session().checkpoint_parts() else {
            return 0.0;
        };
        a.checkpoint_due = now + self.cfg.checkpoint_interval;
        let version = a.session().tree_version();
        let tree = match a.tree_digest {
            Some((v, d)) if v == version => d,
            _ => match self.blobs.put_unsynced(&a.driver.encode_tree()) {
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
        let films = cp
            .films
            .into_iter()
            .map(|f| FilmPart::of(f, &a.film_digests));
        let parts = Unwritten {
            state: cp.state,
            films: films.collect(),
            tree,
        };
        let shared = self.clone();
        tokio::task::spawn_blocking(move || shared.write_checkpoint(n, seq, parts));
        t0.elapsed().as_secs_f64()
    }

    /// Writes a checkpoint's parts durably and records them, unless the job has ended or a
    /// later checkpoint was recorded meanwhile.
    fn write_checkpoint(&self, n: u64, seq: u64, cp: Unwritten) {
        let t0 = Instant::now();
        let written = (|| -> std::io::Result<Parts> {
            let films = cp
                .films
                .iter()
                .map(|f| f.write(&self.blobs))
                .collect::<std::io::Result<Vec<_>>>()?;
            self.blobs.sync(&cp.tree)?;
            let state = self.blobs.put(&cp.state)?;
            Ok(Parts {
                state,
                films,
                tree: cp.tree,
            })
        })();
        let mut st = self.lock();
        let parts = match written {
            Ok(p) => p,
            Err(e) => return tracing::error!(job = %job_name(n), "checkpoint not stored: {e}"),
        };
        let Some(job) = st.jobs.get_mut(&n) else {
            return;
        };
        let current = job.active().is_some_and(|a| a.checkpoint_seq == seq);
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
        if let Some(a) = job.active_mut() {
            let films = cp.films.iter().zip(&parts.films);
            a.film_digests = films.map(|(f, &d)| (Arc::downgrade(&f.film), d)).collect();
        }
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
                p.splatting,
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
pub(crate) fn referenced(st: &State) -> HashSet<Digest> {
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
        live.extend(job.active().into_iter().flat_map(|a| a.blobs()));
    }
    live
}

#[cfg(test)]
mod tests {
    use super::*;

    fn film_with(x: f32) -> Film {
        let mut f = Film::new(2, 1);
        f.pixels[0].add(1.0, glam::Vec3::splat(x));
        f
    }

    #[test]
    fn a_film_is_stored_again_only_when_it_is_another_allocation() {
        let dir = std::env::temp_dir().join(format!("pathfarm-cp-test-{}", std::process::id()));
        let blobs = BlobStore::open(&dir).unwrap();
        let kept = Arc::new(film_with(1.0));
        let d = FilmPart::of(kept.clone(), &[]).write(&blobs).unwrap();
        let stored = vec![(Arc::downgrade(&kept), d)];
        // The same allocation is known; an equal film elsewhere is not (it is encoded anew,
        // and the store finds the same digest).
        assert_eq!(FilmPart::of(kept.clone(), &stored).stored, Some(d));
        let twin = Arc::new(film_with(1.0));
        assert_eq!(FilmPart::of(twin.clone(), &stored).stored, None);
        assert_eq!(FilmPart::of(twin, &stored).write(&blobs).unwrap(), d);
        // A film changed in place moves to a new allocation while a checkpoint knows it.
        let mut changed = kept;
        Arc::make_mut(&mut changed).merge(&film_with(2.0));
        let part = FilmPart::of(changed.clone(), &stored);
        assert_eq!(part.stored, None);
        assert_ne!(part.write(&blobs).unwrap(), d);
        // A known film whose blob was collected since is written again.
        let held = Arc::new(film_with(3.0));
        let d3 = FilmPart::of(held.clone(), &[]).write(&blobs).unwrap();
        let stored = vec![(Arc::downgrade(&held), d3)];
        std::fs::remove_file(blobs.path(&d3)).unwrap();
        let again = FilmPart::of(held, &stored);
        assert_eq!(again.stored, Some(d3));
        assert_eq!(again.write(&blobs).unwrap(), d3);
        assert!(blobs.has(&d3));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_film_written_in_pieces_is_the_blob_of_its_encoding() {
        let dir = std::env::temp_dir().join(format!("pathfarm-cp-pieces-{}", std::process::id()));
        let blobs = BlobStore::open(&dir).unwrap();
        // more pixels than one piece holds, and not a whole number of pieces
        let mut film = Film::new(129, 67);
        for (i, p) in film.pixels.iter_mut().enumerate() {
            p.add(
                0.25 + (i % 7) as f32,
                glam::Vec3::new(i as f32, 1.0 / (1 + i) as f32, -2.0),
            );
        }
        let whole = checkpoint::encode_film(&film);
        let d = FilmPart::of(Arc::new(film.clone()), &[])
            .write(&blobs)
            .unwrap();
        assert_eq!(d, crate::bundle::digest_of(&whole));
        assert_eq!(std::fs::read(blobs.path(&d)).unwrap(), whole);
        let back = checkpoint::decode_film(&whole, 129, 67).unwrap();
        assert_eq!(back, film);
        // written again: the same blob, and no temporary file left behind
        assert_eq!(FilmPart::of(Arc::new(film), &[]).write(&blobs).unwrap(), d);
        assert_eq!(std::fs::read_dir(dir.join("tmp")).unwrap().count(), 0);
        // a sink that fails leaves nothing behind either
        let e = blobs.put_written(|sink| {
            sink(b"part")?;
            Err(std::io::Error::other("disk full"))
        });
        assert!(e.is_err());
        assert_eq!(std::fs::read_dir(dir.join("tmp")).unwrap().count(), 0);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
