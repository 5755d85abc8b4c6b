//! The last lines of each job's log, for its page on the dashboard: every event the
//! coordinator logs with a `job` field (units finished, uploads refused, leases returned,
//! workers lost, the guiding check), kept per job in a bounded ring. A `tracing` layer
//! ([`JobLogs`] as a [`Layer`]) the process installs beside its log output feeds it.

use std::collections::{HashMap, VecDeque};
use std::fmt::Write as _;
use std::sync::{Arc, Mutex};

use tracing::field::{Field, Visit};
use tracing::{Event, Subscriber};
use tracing_subscriber::layer::{Context, Layer};

use super::resources;

/// Lines kept per job (the oldest dropped first).
pub const LINES_PER_JOB: usize = 200;
/// The longest line kept, in bytes.
const MAX_LINE: usize = 400;
/// Jobs whose lines are kept (the job written to least recently dropped first).
const MAX_JOBS: usize = 256;

/// Each job's last log lines, shared by the layer that writes them and the dashboard.
#[derive(Clone, Default)]
pub struct JobLogs {
    inner: Arc<Mutex<Logs>>,
}

impl std::fmt::Debug for JobLogs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let logs = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        f.debug_struct("JobLogs")
            .field("jobs", &logs.jobs.len())
            .finish()
    }
}

#[derive(Default)]
struct Logs {
    jobs: HashMap<String, VecDeque<String>>,
    /// Job names, the one written to most recently last.
    recent: VecDeque<String>,
}

impl JobLogs {
    /// Job `job`'s last lines, oldest first.
    pub fn lines(&self, job: &str) -> Vec<String> {
        let logs = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        logs.jobs
            .get(job)
            .map_or_else(Vec::new, |l| l.iter().cloned().collect())
    }

    fn push(&self, job: String, line: String) {
        let mut logs = self.inner.lock().unwrap_or_else(|e| e.into_inner());
        let logs = &mut *logs;
        if let Some(i) = logs.recent.iter().position(|j| *j == job) {
            logs.recent.remove(i);
        }
        logs.recent.push_back(job.clone());
        while logs.recent.len() > MAX_JOBS {
            let old = logs.recent.pop_front().expect("longer than MAX_JOBS");
            logs.jobs.remove(&old);
        }
        let lines = logs.jobs.entry(job).or_default();
        lines.push_back(line);
        while lines.len() > LINES_PER_JOB {
            lines.pop_front();
        }
    }
}

/// An event's message, its `job` field and its other fields as `k=v`.
#[derive(Default)]
struct Fields {
    message: String,
    job: Option<String>,
    rest: String,
}

impl Visit for Fields {
    fn record_str(&mut self, field: &Field, value: &str) {
        match field.name() {
            "message" => self.message = value.to_string(),
            "job" => self.job = Some(value.to_string()),
            name => {
                let _ = write!(self.rest, " {name}={value}");
            }
        }
    }

    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        match field.name() {
            "message" => self.message = format!("{value:?}"),
            "job" => self.job = Some(format!("{value:?}")),
            name => {
                let _ = write!(self.rest, " {name}={value:?}");
            }
        }
    }
}

/// Whether `name` is a job's name as the coordinator writes it (`job-` and digits): an
/// event naming anything else (a peer's bounded echo of a bad id) is not a job's line.
fn is_job_name(name: &str) -> bool {
    name.strip_prefix("job-")
        .is_some_and(|d| !d.is_empty() && d.len() <= 20 && d.bytes().all(|b| b.is_ascii_digit()))
}

/// The time of day (UTC) of `unix_ms`, as `HH:MM:SS`.
fn clock(unix_ms: u64) -> String {
    let s = unix_ms / 1000 % 86_400;
    format!("{:02}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
}

impl<S: Subscriber> Layer<S> for JobLogs {
    fn on_event(&self, event: &Event<'_>, _ctx: Context<'_, S>) {
        let mut f = Fields::default();
        event.record(&mut f);
        let Some(job) = f.job.filter(|j| is_job_name(j)) else {
            return;
        };
        let level = event.metadata().level();
        let line = format!(
            "{} {level:>5} {}{}",
            clock(super::unix_ms()),
            f.message,
            f.rest
        );
        self.push(job, resources::truncate(&line, MAX_LINE));
    }
}

#[cfg(test)]
mod tests {
    use tracing_subscriber::layer::SubscriberExt;

    use super::*;

    #[test]
    fn a_jobs_events_are_kept_bounded_and_other_events_are_not() {
        let logs = JobLogs::default();
        let subscriber = tracing_subscriber::registry().with(logs.clone());
        tracing::subscriber::with_default(subscriber, || {
            tracing::info!(job = %"job-7", unit = 3, "unit finished");
            tracing::warn!(job = "job-7", leases = ?[1, 2], "tiles rejected: expired");
            tracing::info!(worker = 4, "worker gone");
            tracing::info!(job = %"\"evil\"\n", "refused");
            for k in 0..(LINES_PER_JOB + 5) {
                tracing::info!(job = %"job-8", k, "{}", "x".repeat(1000));
            }
        });
        let seven = logs.lines("job-7");
        assert_eq!(seven.len(), 2, "{seven:?}");
        assert!(
            seven[0].ends_with(" INFO unit finished unit=3"),
            "{}",
            seven[0]
        );
        assert!(seven[1].contains(" WARN tiles rejected: expired leases=[1, 2]"));
        let eight = logs.lines("job-8");
        assert_eq!(eight.len(), LINES_PER_JOB);
        assert!(eight.iter().all(|l| l.len() <= MAX_LINE + 20));
        assert!(
            logs.inner.lock().unwrap().jobs.len() == 2,
            "only jobs' names are kept"
        );
        for n in 0..(MAX_JOBS + 10) {
            logs.push(format!("job-{}", 100 + n), "l".into());
        }
        assert_eq!(logs.inner.lock().unwrap().jobs.len(), MAX_JOBS);
        assert!(
            logs.lines("job-7").is_empty(),
            "the least recently written job dropped"
        );
    }
}
