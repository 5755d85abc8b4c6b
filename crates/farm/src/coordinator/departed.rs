//! Workers that left, kept a while so that the views show a lost worker as lost instead of
//! dropping it from the list: the most recent [`MAX_DEPARTED`], one entry per worker
//! identity (host and name), forgotten when that identity registers again.

use std::collections::VecDeque;

use pathfarm_proto::v1;

use super::resources;

/// Departed workers kept (the oldest is dropped first).
pub(crate) const MAX_DEPARTED: usize = 32;

/// The longest departure reason kept, in bytes.
const MAX_REASON: usize = 200;

/// The departed workers, newest first.
#[derive(Default)]
pub(crate) struct Departed {
    list: VecDeque<v1::WorkerInfo>,
}

impl Departed {
    /// Keeps `last`, the worker's view when it left (`why`, at `unix_ms`): not connected,
    /// holding no lease.
    pub(crate) fn record(&mut self, mut last: v1::WorkerInfo, why: &str, unix_ms: u64) {
        self.returned(&last.host_name, &last.worker_name);
        last.connected = false;
        last.lease_ids.clear();
        last.departed_reason = resources::truncate(why, MAX_REASON);
        last.departed_unix_ms = unix_ms;
        self.list.push_front(last);
        self.list.truncate(MAX_DEPARTED);
    }

    /// A worker of this identity registered again: its departure is history.
    pub(crate) fn returned(&mut self, host_name: &str, worker_name: &str) {
        self.list
            .retain(|w| (w.host_name.as_str(), w.worker_name.as_str()) != (host_name, worker_name));
    }

    /// The departed workers, newest first.
    pub(crate) fn iter(&self) -> impl Iterator<Item = &v1::WorkerInfo> {
        self.list.iter()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(host: &str, name: &str) -> v1::WorkerInfo {
        v1::WorkerInfo {
            host_name: host.into(),
            worker_name: name.into(),
            connected: true,
            lease_ids: vec![3, 4],
            ..Default::default()
        }
    }

    #[test]
    fn departures_are_bounded_one_per_identity_and_forgotten_on_return() {
        let mut d = Departed::default();
        for k in 0..100 {
            d.record(info(&format!("h{k}"), "w"), &"x".repeat(1000), k);
        }
        assert_eq!(d.iter().count(), MAX_DEPARTED);
        let newest = d.iter().next().unwrap();
        assert_eq!(
            (newest.host_name.as_str(), newest.departed_unix_ms),
            ("h99", 99)
        );
        assert!(!newest.connected && newest.lease_ids.is_empty());
        // (cut to MAX_REASON bytes, then "… (N bytes)")
        assert!(newest.departed_reason.len() <= MAX_REASON + 20);
        d.record(info("h99", "w"), "lost", 200);
        assert_eq!(d.iter().filter(|w| w.host_name == "h99").count(), 1);
        assert_eq!(d.iter().next().unwrap().departed_reason, "lost");
        d.returned("h99", "w");
        assert!(d.iter().all(|w| w.host_name != "h99"));
        assert_eq!(d.iter().count(), MAX_DEPARTED - 1);
    }
}
