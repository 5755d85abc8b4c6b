//! What the coordinator lets jobs, uploads and peers take: its counterpart of the scene's
//! [`pathfarm_scene::Limits`]. Every size a peer announces is held to these before anything
//! is allocated; every default is documented in `docs/farm.md` ("Resource policy").

use std::time::Duration;

/// The coordinator's resource policy.
#[derive(Clone, Debug)]
pub struct Resources {
    /// Memory the sessions of running jobs may take together (films, samples: estimated by
    /// [`pathfarm_render::scene::guided_session_bytes`]). A job is given its memory when it
    /// starts, never at submission: a queued job holds only its request. A job that fits
    /// the budget waits QUEUED until the running jobs leave it room; one that could never
    /// fit is refused at submission (`RESOURCE_EXHAUSTED`). Default: half the machine's
    /// memory.
    pub job_memory_bytes: u64,
    /// Jobs queued or running at once (default 1000); a submission past it is refused
    /// (`RESOURCE_EXHAUSTED`).
    pub max_jobs_waiting: usize,
    /// Upload payloads (tiles, statistics, records) buffered at once, all peers together
    /// (default 1 GiB). An upload reserves what its header announces before it reads any
    /// data, and waits for room.
    pub upload_memory_bytes: u64,
    /// The guide statistics one tile upload may carry (default 256 MiB).
    pub max_stats_bytes: u64,
    /// The quadtree records one worker may send for a tree version (default 1 GiB).
    pub max_records_bytes: u64,
    /// Messages queued for one worker's control stream (default 4096). A worker that does
    /// not read its stream until this fills is disconnected.
    pub outbox_messages: usize,
    /// Lease ids one heartbeat may list (default 1024): a worker holds at most
    /// `SchedulerConfig::leases_per_worker`.
    pub max_heartbeat_leases: usize,
    /// The longest an upload stream may stay silent between two messages (default 60 s).
    pub stream_idle: Duration,
    /// How long an uploaded blob that no job refers to is kept before it is deleted
    /// (default 1 h): the time a client has between uploading a bundle and submitting it.
    pub blob_grace: Duration,
    /// Rejected uploads (corrupt, out of range, refused by the session) after which a worker
    /// gets no more leases of that job (default 3).
    pub bad_uploads_per_job: u32,
}

impl Default for Resources {
    fn default() -> Self {
        let memory = pathfarm_scene::Limits::default().max_memory_bytes;
        Resources {
            job_memory_bytes: memory / 2,
            max_jobs_waiting: 1000,
            upload_memory_bytes: 1 << 30,
            max_stats_bytes: 256 << 20,
            max_records_bytes: 1 << 30,
            outbox_messages: 4096,
            max_heartbeat_leases: 1024,
            stream_idle: Duration::from_secs(60),
            blob_grace: Duration::from_secs(3600),
            bad_uploads_per_job: 3,
        }
    }
}

/// The longest a host or worker name is kept (it is echoed by `ListWorkers`).
pub(crate) const MAX_NAME_BYTES: usize = 256;

/// The most of a peer's input an error message echoes.
pub(crate) const MAX_ECHO_BYTES: usize = 200;

/// `text` cut to at most `max` bytes on a character boundary, with "…" when cut.
pub(crate) fn truncate(text: &str, max: usize) -> String {
    if text.len() <= max {
        return text.to_string();
    }
    let mut end = max;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}… ({} bytes)", &text[..end], text.len())
}

/// A peer's value as an error message may echo it: bounded, debug-quoted.
pub(crate) fn echo(text: &str) -> String {
    format!("{:?}", truncate(text, MAX_ECHO_BYTES))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn truncation_keeps_short_text_and_cuts_long_text_on_a_character_boundary() {
        assert_eq!(truncate("abc", 3), "abc");
        let long = "é".repeat(100);
        let cut = truncate(&long, 5);
        assert!(cut.starts_with("éé…"), "{cut}");
        assert!(cut.ends_with("(200 bytes)"), "{cut}");
        assert!(echo(&"x".repeat(10_000)).len() < MAX_ECHO_BYTES + 40);
    }
}
