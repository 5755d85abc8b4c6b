//! A job's record of the workers that sent it bad results: counted per worker identity
//! (host and name, so a worker that reconnects keeps its record), and blocked from the job
//! past a limit, as Flamenco and Deadline do. Pure: the coordinator applies a block to the
//! scheduler and shows the reasons in the job's status; the simulation runs the same rule.

use std::collections::BTreeMap;

/// How bad a worker's result was.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Blame {
    /// A bad upload: counted, blocked past the limit.
    Bad,
    /// The worker says the job cannot be rendered: blocked at once.
    Unrenderable,
}

/// Where a worker stands with the job after a blame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Standing {
    /// Counted; it may go on rendering the job.
    Counted(u32),
    /// Blocked from the job, now.
    Blocked,
}

/// Bad results per worker identity, and the blocked ones with the last reason.
#[derive(Clone, Debug, Default)]
pub struct Blocklist {
    limit: u32,
    bad: BTreeMap<String, u32>,
    blocked: BTreeMap<String, String>,
}

impl Blocklist {
    /// Blocks a worker at its `limit`-th bad result (at least 1).
    pub fn new(limit: u32) -> Self {
        Self {
            limit: limit.max(1),
            ..Self::default()
        }
    }

    /// Counts a bad result of `identity` (`why`: bounded by the caller).
    pub fn blame(&mut self, identity: &str, why: &str, blame: Blame) -> Standing {
        if self.blocked.contains_key(identity) {
            return Standing::Blocked;
        }
        let count = self.bad.entry(identity.to_string()).or_default();
        *count += 1;
        if blame == Blame::Bad && *count < self.limit {
            return Standing::Counted(*count);
        }
        self.blocked.insert(identity.to_string(), why.to_string());
        Standing::Blocked
    }

    pub fn is_blocked(&self, identity: &str) -> bool {
        self.blocked.contains_key(identity)
    }

    /// The blocked identities and why, as `identity: reason` lines.
    pub fn reasons(&self) -> Vec<String> {
        (self.blocked.iter())
            .map(|(who, why)| format!("{who}: {why}"))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_worker_is_blocked_at_the_limit_and_stays_blocked() {
        let mut b = Blocklist::new(3);
        assert_eq!(b.blame("h/w", "nan", Blame::Bad), Standing::Counted(1));
        assert_eq!(b.blame("h/x", "nan", Blame::Bad), Standing::Counted(1));
        assert_eq!(b.blame("h/w", "nan", Blame::Bad), Standing::Counted(2));
        assert!(!b.is_blocked("h/w"));
        assert_eq!(b.blame("h/w", "garbage", Blame::Bad), Standing::Blocked);
        assert!(b.is_blocked("h/w") && !b.is_blocked("h/x"));
        assert_eq!(b.blame("h/w", "more", Blame::Bad), Standing::Blocked);
        assert_eq!(b.reasons(), vec!["h/w: garbage".to_string()]);
    }

    #[test]
    fn an_unrenderable_report_blocks_at_once() {
        let mut b = Blocklist::new(3);
        assert_eq!(
            b.blame("h/w", "no scene", Blame::Unrenderable),
            Standing::Blocked
        );
        assert!(b.is_blocked("h/w"));
    }

    #[test]
    fn a_limit_of_zero_blocks_at_the_first_bad_result() {
        let mut b = Blocklist::new(0);
        assert_eq!(b.blame("h/w", "nan", Blame::Bad), Standing::Blocked);
    }
}
