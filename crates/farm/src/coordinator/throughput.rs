//! The farm's throughput over the last minutes: samples and tiles accepted, in buckets of
//! [`BUCKET`] over [`SPAN`], for the dashboard's workers page. A pure state machine: the
//! caller passes the time (the coordinator's clock).

use std::time::Duration;

use crate::scheduler::Millis;

/// One bucket's span.
pub(crate) const BUCKET: Duration = Duration::from_secs(10);
/// How far back the series goes: 60 buckets.
pub(crate) const SPAN: Duration = Duration::from_secs(600);

const BUCKETS: usize = (SPAN.as_secs() / BUCKET.as_secs()) as usize;

/// What was accepted in one bucket.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Bucket {
    pub(crate) samples: u64,
    pub(crate) tiles: u64,
}

/// Accepted work by time: a ring of [`BUCKETS`] buckets (bounded memory however long the
/// coordinator runs).
#[derive(Debug)]
pub(crate) struct Throughput {
    ring: [Bucket; BUCKETS],
    /// The index (time / BUCKET) of the newest bucket written.
    newest: u64,
}

impl Default for Throughput {
    fn default() -> Self {
        Throughput {
            ring: [Bucket::default(); BUCKETS],
            newest: 0,
        }
    }
}

fn index(t: Millis) -> u64 {
    t.0 / BUCKET.as_millis() as u64
}

impl Throughput {
    /// Counts `samples` in `tiles` accepted at `now`.
    pub(crate) fn add(&mut self, now: Millis, samples: u64, tiles: u64) {
        self.advance(index(now));
        let b = &mut self.ring[(self.newest % BUCKETS as u64) as usize];
        b.samples = b.samples.saturating_add(samples);
        b.tiles = b.tiles.saturating_add(tiles);
    }

    /// Clears the buckets between the newest written and `i` (time moved on).
    fn advance(&mut self, i: u64) {
        if i <= self.newest {
            return;
        }
        let gap = (i - self.newest).min(BUCKETS as u64);
        for k in 1..=gap {
            self.ring[((self.newest + k) % BUCKETS as u64) as usize] = Bucket::default();
        }
        self.newest = i;
    }

    /// The last [`BUCKETS`] buckets up to the one holding `now`, oldest first (the last one
    /// still filling).
    pub(crate) fn series(&self, now: Millis) -> Vec<Bucket> {
        let i = index(now);
        (0..BUCKETS as u64)
            .map(|back| {
                let at = i.checked_sub(BUCKETS as u64 - 1 - back);
                match at {
                    Some(at) if at <= self.newest && self.newest - at < BUCKETS as u64 => {
                        self.ring[(at % BUCKETS as u64) as usize]
                    }
                    _ => Bucket::default(),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(seconds: u64) -> Millis {
        Millis(seconds * 1000)
    }

    #[test]
    fn work_lands_in_its_bucket_and_ages_out_after_the_span() {
        let mut t = Throughput::default();
        t.add(at(5), 100, 1);
        t.add(at(9), 50, 2);
        t.add(at(25), 7, 1);
        let s = t.series(at(25));
        assert_eq!(s.len(), 60);
        assert_eq!(
            s[59],
            Bucket {
                samples: 7,
                tiles: 1
            },
            "the bucket of 20-30 s"
        );
        assert_eq!(s[58], Bucket::default(), "10-20 s: nothing");
        assert_eq!(
            s[57],
            Bucket {
                samples: 150,
                tiles: 3
            },
            "0-10 s"
        );
        // Ten minutes on, the first bucket has left the series; the one of 20-30 s is the
        // oldest shown until it leaves too.
        let s = t.series(at(605));
        assert_eq!(s[0], Bucket::default());
        assert_eq!(
            s[1],
            Bucket {
                samples: 7,
                tiles: 1
            }
        );
        assert!(t.series(at(625)).iter().all(|b| *b == Bucket::default()));
        // Writing long after clears what the ring held, whatever its slot.
        t.add(at(2000), 1, 1);
        let s = t.series(at(2000));
        assert_eq!(s.iter().map(|b| b.samples).sum::<u64>(), 1);
        // A clock read before the newest bucket (threads racing) counts in the newest.
        t.add(at(1995), 2, 1);
        assert_eq!(
            t.series(at(2000))[59],
            Bucket {
                samples: 3,
                tiles: 2
            }
        );
    }
}
