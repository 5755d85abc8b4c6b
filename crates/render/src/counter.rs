//! A counter that the render threads add to without sharing a cache line.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

/// One slot per cache line.
#[derive(Debug, Default)]
#[repr(align(64))]
struct Slot(AtomicU64);

/// Adds from rayon's threads go to a slot of their own (by rayon thread index), so a count
/// taken once per camera sample does not bounce one cache line between cores. The total is
/// an integer sum: it does not depend on which thread added what.
#[derive(Debug)]
pub struct ShardedCounter {
    slots: Box<[Slot]>,
}

impl Default for ShardedCounter {
    fn default() -> Self {
        Self::new()
    }
}

impl ShardedCounter {
    /// A zero counter with a slot per thread of the current rayon pool (plus one for
    /// callers outside it).
    pub fn new() -> Self {
        Self {
            slots: (0..rayon::current_num_threads() + 1)
                .map(|_| Slot::default())
                .collect(),
        }
    }

    /// Adds `v` (thread safe).
    #[inline]
    pub fn add(&self, v: u64) {
        let i = rayon::current_thread_index().map_or(0, |i| i + 1) % self.slots.len();
        self.slots[i].0.fetch_add(v, Relaxed);
    }

    /// The sum of all adds so far (exact once no thread is adding).
    pub fn total(&self) -> u64 {
        self.slots.iter().map(|s| s.0.load(Relaxed)).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    #[test]
    fn sharded_counter_totals_every_add_from_any_thread() {
        // Deterministic (no significance level): 10000 adds of 1..=10000 from rayon's
        // threads and the calling thread sum to n (n + 1) / 2.
        let c = ShardedCounter::new();
        (1..=9999u64).into_par_iter().for_each(|v| c.add(v));
        c.add(10000);
        assert_eq!(c.total(), 10000 * 10001 / 2);
    }
}
