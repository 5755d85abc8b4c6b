//! Rendered tiles on their way to the coordinator: held together while the worker renders
//! more of their unit, serialised once (their statistics taken from the tree in one go),
//! uploaded in one call.
//!
//! Invariant: the records in a job's tree copy ([`super::JobTree::recording`]) are exactly
//! those of the tiles held in the [`Joint`] (or being serialised from it). With held records
//! (`PassSpec.hold_records`) a joint's quadtree records leave the tree with it, as always,
//! and wait beside its upload: kept ([`super::records`]) only if the upload is accepted. The session loop
//! keeps it by serialising the joint before it starts any lease of another unit, and a tile
//! cancelled after it rendered spoils its joint (the records are taken and thrown away, the
//! other leases handed back) rather than leaving its records behind.

use std::sync::Arc;
use std::time::Instant;

use pathfarm_guide::IterationStats;
use pathfarm_proto::v1;
use pathfarm_proto::MAX_CHUNK_BYTES;

use super::{retryable, Api, Fail, Shared};
use crate::chunked;

/// The most tiles one upload carries (the coordinator takes up to
/// `coordinator::MAX_UPLOAD_TILES`): bounds what a worker holds in memory and what it
/// re-renders when lost.
pub const MAX_JOINT_TILES: usize = 12;

/// A rendered tile: its job and unit, its part of the upload header, its pixel sums.
pub(super) struct RenderedTile {
    pub(super) job_id: String,
    pub(super) unit: u64,
    /// Whether the unit records into the tree (the joint then carries statistics).
    pub(super) record: bool,
    /// With `PassSpec.hold_records`: the tree version and epoch whose quadtree records the
    /// worker keeps until `FlushRecords` (the joint then carries the fraction gradients).
    pub(super) hold: Option<HeldKey>,
    pub(super) part: v1::UploadedTile,
    pub(super) pixels: Vec<u8>,
}

/// Which records a worker keeps: those of one tree version (its blob's digest) under one
/// records epoch of the job.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(super) struct HeldKey {
    pub(super) tree_digest: Vec<u8>,
    pub(super) epoch: u64,
}

/// Whether a tile's lease was cancelled after it rendered.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Spoiled {
    No,
    Yes,
}

/// Rendered tiles of one unit whose records are in the job's tree, waiting to go up together.
pub(super) struct Joint {
    job_id: String,
    unit: u64,
    record: bool,
    hold: Option<HeldKey>,
    tiles: Vec<RenderedTile>,
    /// A lease of it was cancelled: nothing of it is uploaded.
    spoiled: bool,
}

impl Joint {
    pub(super) fn new(first: &RenderedTile) -> Joint {
        Joint {
            job_id: first.job_id.clone(),
            unit: first.unit,
            record: first.record,
            hold: first.hold.clone(),
            tiles: Vec::new(),
            spoiled: false,
        }
    }

    pub(super) fn job_id(&self) -> &str {
        &self.job_id
    }

    /// Whether a lease of (`job`, `unit`) belongs with these tiles.
    pub(super) fn holds(&self, job: &str, unit: u64) -> bool {
        self.job_id == job && self.unit == unit
    }

    pub(super) fn push(&mut self, tile: RenderedTile, spoiled: Spoiled) {
        self.spoiled |= spoiled == Spoiled::Yes;
        self.record |= tile.record;
        if self.hold.is_none() {
            self.hold = tile.hold.clone();
        }
        if spoiled == Spoiled::No {
            self.tiles.push(tile);
        }
    }

    pub(super) fn lease_ids(&self) -> impl Iterator<Item = u64> + '_ {
        self.tiles.iter().map(|t| t.part.lease_id)
    }

    pub(super) fn has_lease(&self, id: u64) -> bool {
        self.lease_ids().any(|l| l == id)
    }

    /// Lease `id` was cancelled: it leaves, and the rest is not uploaded.
    pub(super) fn cancel(&mut self, id: u64) {
        self.tiles.retain(|t| t.part.lease_id != id);
        self.spoiled = true;
    }

    pub(super) fn is_full_or_spoiled(&self) -> bool {
        self.spoiled || self.tiles.len() >= MAX_JOINT_TILES
    }
}

/// What serialising a joint came to.
pub(super) enum FlushEnd {
    /// The upload to send, and the quadtree records the worker keeps if the coordinator
    /// accepts it.
    Ready(Upload, Option<(HeldKey, IterationStats)>),
    /// The joint was spoiled: its records were thrown away; hand its leases back.
    Discarded,
    /// The statistics could not be taken: the leases failed.
    Failed(String),
}

/// A joint being serialised on a blocking thread.
pub(super) struct Flushing {
    pub(super) lease_ids: Vec<u64>,
    pub(super) job_id: String,
    handle: tokio::task::JoinHandle<FlushEnd>,
}

impl Flushing {
    pub(super) fn start(shared: &Arc<Shared>, joint: Joint) -> Flushing {
        let lease_ids = joint.lease_ids().collect();
        let job_id = joint.job_id.clone();
        let shared = shared.clone();
        let handle = tokio::task::spawn_blocking(move || flush(&shared, joint));
        Flushing {
            lease_ids,
            job_id,
            handle,
        }
    }

    pub(super) async fn wait(&mut self) -> FlushEnd {
        (&mut self.handle)
            .await
            .unwrap_or_else(|e| FlushEnd::Failed(format!("serialising panicked: {e}")))
    }

    pub(super) async fn finish(mut self) -> (Vec<u64>, String, FlushEnd) {
        let end = self.wait().await;
        (self.lease_ids, self.job_id, end)
    }
}

/// One upload: its header and payloads (each tile's pixel sums, then the statistics).
pub(super) struct Upload {
    header: v1::TileHeader,
    pixels: Vec<Vec<u8>>,
    stats: Vec<u8>,
}

/// Takes the joint's records out of its job's tree (once for all its tiles: exact sums) and
/// encodes the upload.
fn flush(shared: &Shared, joint: Joint) -> FlushEnd {
    let start = Instant::now();
    let taken = if joint.record {
        match take_stats(shared, &joint) {
            Ok(s) => Some(s),
            Err(f) => return FlushEnd::Failed(f.reason),
        }
    } else {
        None
    };
    if joint.spoiled {
        return FlushEnd::Discarded;
    }
    // With held records only the fraction gradients go up now; the rest waits for the
    // coordinator's acceptance of this upload and then for its FlushRecords.
    let (stats, held) = match (taken, joint.hold.clone()) {
        (None, _) => (Vec::new(), None),
        (Some(s), None) => (s.encode(), None),
        (Some(s), Some(key)) => {
            let (gradients, records) = s.split_gradients();
            (gradients.encode(), Some((key, records)))
        }
    };
    let mut tiles: Vec<v1::UploadedTile> = Vec::with_capacity(joint.tiles.len());
    let mut pixels = Vec::with_capacity(joint.tiles.len());
    for t in joint.tiles {
        tiles.push(t.part);
        pixels.push(t.pixels);
    }
    let stats_digest = blake3::hash(&stats).as_bytes().to_vec();
    if let Some(c) = tiles.first_mut().and_then(|t| t.counters.as_mut()) {
        c.serialize_seconds += start.elapsed().as_secs_f64();
    }
    tracing::info!(
        "leases {:?} (job {}): unit {}: {} tiles, statistics {} bytes",
        tiles.iter().map(|t| t.lease_id).collect::<Vec<_>>(),
        joint.job_id,
        joint.unit,
        tiles.len(),
        stats.len()
    );
    let header = v1::TileHeader {
        job_id: joint.job_id,
        unit: joint.unit,
        stats_size: stats.len() as u64,
        stats_digest,
        tiles,
    };
    FlushEnd::Ready(
        Upload {
            header,
            pixels,
            stats,
        },
        held,
    )
}

/// The statistics recorded into the job's tree by the joint's tiles; the tree records
/// nothing more of them afterwards.
fn take_stats(shared: &Shared, joint: &Joint) -> Result<IterationStats, Fail> {
    let taken = {
        let mut caches = shared.caches.lock().expect("cache lock");
        let jt = caches.trees.get_mut(&joint.job_id);
        let jt = jt.filter(|jt| jt.recording == Some(joint.unit));
        jt.map(|jt| {
            jt.recording = None;
            jt.tree.take_stats()
        })
    };
    taken.ok_or_else(|| {
        retryable(format!(
            "the tree holding unit {}'s records is gone",
            joint.unit
        ))
    })
}

/// The outcome of one upload.
pub(super) enum UploadEnd {
    Acked(v1::TileAck),
    Failed(String),
}

/// What an upload is of: its leases, its job, and the quadtree records the worker keeps if
/// it is accepted.
pub(super) struct UploadOf {
    pub(super) ids: Vec<u64>,
    pub(super) job: String,
    pub(super) held: Option<(HeldKey, IterationStats)>,
}

/// Uploads in progress: what each is of, and the outcome.
pub(super) type Uploads = tokio::task::JoinSet<(UploadOf, UploadEnd)>;

/// Uploads leases' tiles in the background; the outcome arrives on `uploads`.
pub(super) fn spawn_upload(uploads: &mut Uploads, api: &Api, of: UploadOf, upload: Upload) {
    let api = api.clone();
    uploads.spawn(async move {
        let end = send(api, upload).await;
        (of, end)
    });
}

async fn send(mut api: Api, u: Upload) -> UploadEnd {
    let mut payloads: Vec<&[u8]> = u.pixels.iter().map(Vec::as_slice).collect();
    payloads.push(&u.stats);
    let msgs = chunked::messages::<v1::TileUpload>(u.header, &payloads, MAX_CHUNK_BYTES);
    match api.upload_tile(tokio_stream::iter(msgs)).await {
        Ok(ack) => UploadEnd::Acked(ack.into_inner()),
        Err(s) => UploadEnd::Failed(format!("upload failed: {} ({:?})", s.message(), s.code())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::chunked::messages;

    fn data(m: &[v1::TileUpload]) -> Vec<Vec<u8>> {
        m[1..]
            .iter()
            .map(|u| match &u.part {
                Some(v1::tile_upload::Part::Data(d)) => d.clone(),
                _ => panic!("not data"),
            })
            .collect()
    }

    fn tile(lease_id: u64, unit: u64) -> RenderedTile {
        RenderedTile {
            job_id: "job-1".into(),
            unit,
            record: true,
            hold: None,
            part: v1::UploadedTile {
                lease_id,
                ..Default::default()
            },
            pixels: vec![1, 2, 3],
        }
    }

    #[test]
    fn a_joint_holds_one_unit_until_full_and_a_cancelled_lease_spoils_it() {
        let first = tile(1, 4);
        let mut j = Joint::new(&first);
        j.push(first, Spoiled::No);
        assert!(j.holds("job-1", 4) && !j.holds("job-1", 5) && !j.holds("job-2", 4));
        for id in 2..MAX_JOINT_TILES as u64 {
            j.push(tile(id, 4), Spoiled::No);
            assert!(!j.is_full_or_spoiled());
        }
        j.push(tile(99, 4), Spoiled::No);
        assert!(j.is_full_or_spoiled());
        assert_eq!(j.lease_ids().count(), MAX_JOINT_TILES);
        // a held lease cancelled: it leaves, and nothing of the joint is uploaded
        let mut k = Joint::new(&tile(7, 4));
        k.push(tile(7, 4), Spoiled::No);
        k.push(tile(8, 4), Spoiled::No);
        assert!(k.has_lease(8));
        k.cancel(8);
        assert!(!k.has_lease(8) && k.has_lease(7) && k.is_full_or_spoiled());
        // a lease cancelled after it rendered: its records are in the tree, it is not held
        let mut m = Joint::new(&tile(9, 4));
        m.push(tile(9, 4), Spoiled::Yes);
        assert!(m.is_full_or_spoiled() && m.lease_ids().count() == 0);
    }

    #[test]
    fn upload_is_header_then_parts_of_at_most_max() {
        let a: Vec<u8> = (0..10u8).collect();
        let b: Vec<u8> = (50..53u8).collect();
        let stats: Vec<u8> = (100..107u8).collect();
        let m = messages::<v1::TileUpload>(v1::TileHeader::default(), &[&a, &b, &stats], 4);
        assert!(matches!(m[0].part, Some(v1::tile_upload::Part::Header(_))));
        let parts = data(&m);
        assert!(parts.iter().all(|p| !p.is_empty() && p.len() <= 4));
        assert_eq!(
            parts.concat(),
            [a.clone(), b.clone(), stats.clone()].concat()
        );
        // parts span the ends of payloads
        assert_eq!(parts[2], vec![8, 9, 50, 51]);
        assert_eq!(parts[3], vec![52, 100, 101, 102]);
        let m = messages::<v1::TileUpload>(v1::TileHeader::default(), &[&a, &[]], MAX_CHUNK_BYTES);
        assert_eq!(data(&m), vec![a]);
        let big = vec![1u8; MAX_CHUNK_BYTES + 1];
        let m = messages::<v1::TileUpload>(
            v1::TileHeader::default(),
            &[&big, &[2, 3]],
            MAX_CHUNK_BYTES,
        );
        let lens: Vec<usize> = data(&m).iter().map(|p| p.len()).collect();
        assert_eq!(lens, [MAX_CHUNK_BYTES, 3]);
    }
}
