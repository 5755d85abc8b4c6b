//! The coordinator's job records, persisted with redb in `DATA/jobs.redb`: job number ->
//! a protobuf-encoded [`JobRecord`].

use std::path::Path;

use pathfarm_proto::v1;
use prost::Message;
use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};

const JOBS: TableDefinition<u64, &[u8]> = TableDefinition::new("jobs");

/// What the coordinator keeps of a job across restarts.
#[derive(Clone, PartialEq, prost::Message)]
pub(crate) struct JobRecord {
    /// The submission, as received.
    #[prost(message, optional, tag = "1")]
    pub request: Option<v1::SubmitJobRequest>,
    /// A `v1::JobState`.
    #[prost(int32, tag = "2")]
    pub state: i32,
    #[prost(string, tag = "3")]
    pub failure_reason: String,
    /// Result blobs (digests; empty = none).
    #[prost(bytes = "vec", tag = "4")]
    pub exr: Vec<u8>,
    #[prost(bytes = "vec", tag = "5")]
    pub png: Vec<u8>,
    #[prost(bytes = "vec", tag = "6")]
    pub tree: Vec<u8>,
    #[prost(uint64, tag = "7")]
    pub submitted_unix_ms: u64,
    #[prost(uint64, tag = "8")]
    pub finished_unix_ms: u64,
    #[prost(uint32, tag = "9")]
    pub width: u32,
    #[prost(uint32, tag = "10")]
    pub height: u32,
    #[prost(uint64, tag = "11")]
    pub spp_done: u64,
    #[prost(uint64, tag = "12")]
    pub samples_done: u64,
    #[prost(uint32, tag = "13")]
    pub iteration: u32,
    #[prost(uint64, tag = "14")]
    pub started_unix_ms: u64,
    /// The job session's last checkpoint's state (a blob digest; empty = none): taken
    /// between iterations, so a restarted coordinator resumes the job from there.
    #[prost(bytes = "vec", tag = "15")]
    pub checkpoint: Vec<u8>,
    /// The checkpoint's tree (a blob digest), and its films in order ([`crate::coordinator`]'s
    /// checkpoints module).
    #[prost(bytes = "vec", tag = "16")]
    pub checkpoint_tree: Vec<u8>,
    #[prost(bytes = "vec", repeated, tag = "17")]
    pub checkpoint_films: Vec<Vec<u8>>,
    /// Samples and guide records dropped for a NaN or infinite value (final once done).
    #[prost(uint64, tag = "18")]
    pub nonfinite: u64,
    /// The iterations and the path fallback's verdict (kept once the session is gone).
    #[prost(message, repeated, tag = "19")]
    pub iterations: Vec<v1::IterationInfo>,
    #[prost(uint32, optional, tag = "20")]
    pub fell_back_after: Option<u32>,
}

pub(crate) struct Db {
    db: Database,
}

fn err(e: impl std::fmt::Display) -> String {
    format!("job database: {e}")
}

impl Db {
    /// Opens the database at `path`, creating it if it does not exist. A new database is
    /// made under a temporary name and renamed into place once it is complete, so a
    /// coordinator killed while creating it leaves no half-made file at `path`.
    pub(crate) fn open(path: &Path) -> Result<Db, String> {
        if !path.exists() {
            let tmp = path.with_extension("redb.new");
            let _ = std::fs::remove_file(&tmp);
            {
                let db = Database::create(&tmp).map_err(err)?;
                let tx = db.begin_write().map_err(err)?;
                tx.open_table(JOBS).map_err(err)?;
                tx.commit().map_err(err)?;
            }
            std::fs::rename(&tmp, path).map_err(err)?;
        }
        let db = Database::create(path).map_err(err)?;
        let tx = db.begin_write().map_err(err)?;
        tx.open_table(JOBS).map_err(err)?;
        tx.commit().map_err(err)?;
        Ok(Db { db })
    }

    pub(crate) fn put(&self, job: u64, record: &JobRecord) -> Result<(), String> {
        let bytes = record.encode_to_vec();
        let tx = self.db.begin_write().map_err(err)?;
        {
            let mut table = tx.open_table(JOBS).map_err(err)?;
            table.insert(job, bytes.as_slice()).map_err(err)?;
        }
        tx.commit().map_err(err)
    }

    /// Every record, by job number.
    pub(crate) fn all(&self) -> Result<Vec<(u64, JobRecord)>, String> {
        let tx = self.db.begin_read().map_err(err)?;
        let table = tx.open_table(JOBS).map_err(err)?;
        let mut out = Vec::new();
        for row in table.iter().map_err(err)? {
            let (k, v) = row.map_err(err)?;
            let record = JobRecord::decode(v.value()).map_err(err)?;
            out.push((k.value(), record));
        }
        Ok(out)
    }
}
