//! Light-sample statistics of a spatial leaf: what one next-event (light) sample taken in the
//! leaf contributes per unit path throughput, learned like everything else in the tree.
//!
//! In the usual "NEE always" setup the quadtrees learn *indirect* light only (the light
//! samples account for the direct part), so the leaf's quadtree flux says nothing about how
//! much a vertex's light sample is worth, or how noisy it is. These statistics fill that gap:
//! a renderer records every light sample's value (`f cos Le w / p_light`, averaged over colour
//! channels; 0 for an occluded or failed sample) in training passes, and reads back the mean
//! and standard deviation frozen at the end of the iteration, e.g. to take several light
//! samples at vertices whose light sample is noisy compared with the pixel's value (Vorba and
//! Křivánek 2016's weight window, applied to the light sample; see the renderer's
//! `light_splitting`).
//!
//! The sums are exact fixed-point integers ([`crate::stats`]), so they are bit-identical for
//! any thread count and merge exactly across workers ([`crate::IterationStats`]).

use crate::stats::{from_fixed, to_fixed, Acc128, FIXED_ONE};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

#[cfg(test)]
mod tests;

/// One leaf's light-sample statistics: this iteration's sums (building) and the mean and
/// standard deviation frozen from the previous iteration's sums (read by the renderer).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LightStats {
    /// Sum of the recorded values (fixed point).
    pub sum: Acc128,
    /// Sum of the squared recorded values (fixed point).
    pub sum_sq: Acc128,
    /// Number of recorded samples (fixed point, one unit per sample).
    pub count: Acc128,
    /// Mean value of a light sample, frozen by [`LightStats::freeze`] (0 without samples).
    pub mean: f32,
    /// Standard deviation of a light sample's value, frozen by [`LightStats::freeze`] (0
    /// without samples).
    pub std_dev: f32,
}

impl LightStats {
    /// Records one light sample's value (thread safe, order independent). Negative or
    /// non-finite values are ignored; a value whose square does not fit the fixed-point format
    /// (above about 1e12) saturates and counts an overflow event.
    #[inline]
    pub fn record(&self, value: f32, overflow: &AtomicU64) {
        if !(value >= 0.0) || !value.is_finite() {
            return;
        }
        let v = value as f64;
        let (q, o1) = to_fixed(v);
        let (q2, o2) = to_fixed(v * v);
        if o1 || o2 {
            overflow.fetch_add(1, Relaxed);
        }
        self.sum.add(q, overflow);
        self.sum_sq.add(q2, overflow);
        self.count.add(FIXED_ONE, overflow);
    }

    /// Freezes the mean and standard deviation of the samples recorded so far (keeps the
    /// previous ones when there are none). The sums are left as they are.
    pub fn freeze(&mut self) {
        let n = from_fixed(self.count.get());
        if n > 0.0 {
            let mean = from_fixed(self.sum.get()) / n;
            let second = from_fixed(self.sum_sq.get()) / n;
            self.mean = mean as f32;
            self.std_dev = (second - mean * mean).max(0.0).sqrt() as f32;
        }
    }

    /// Zeroes the sums (the frozen mean and deviation stay).
    pub fn clear(&self) {
        self.sum.set(0);
        self.sum_sq.set(0);
        self.count.set(0);
    }

    /// Moves the sums out as `[sum, sum_sq, count]`, leaving zeros (see
    /// [`crate::SdTree::take_stats`]).
    pub fn take(&self) -> [u128; 3] {
        [self.sum.take(), self.sum_sq.take(), self.count.take()]
    }

    /// The sums as `[sum, sum_sq, count]`.
    pub fn sums(&self) -> [u128; 3] {
        [self.sum.get(), self.sum_sq.get(), self.count.get()]
    }

    /// Sets the sums from `[sum, sum_sq, count]`.
    pub fn set_sums(&self, s: [u128; 3]) {
        self.sum.set(s[0]);
        self.sum_sq.set(s[1]);
        self.count.set(s[2]);
    }
}
