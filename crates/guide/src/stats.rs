//! Exact, order-independent fixed-point accumulation.
//!
//! Every statistic the guide learns (quadtree cell sums, statistical weights W, fraction
//! gradients) is accumulated as an **unsigned 128-bit fixed-point integer** with
//! [`FRAC_BITS`] = 48 fractional bits, i.e. one integer unit is `2^-48` (~3.6e-15) real units and
//! the largest representable sum is `2^80` (~1.2e24) real units.
//!
//! Each accumulator is a pair of `AtomicU64` words. An addition adds the low word with
//! `fetch_add` (wrapping), detects the carry from the returned old value, and adds
//! `high + carry` to the high word. Because integer addition modulo `2^128` is associative and
//! commutative, and the number of carries out of the low word is `floor(sum_lo / 2^64)`
//! whatever the order, the final 128-bit value is bit-identical for any thread count or
//! interleaving. Only the final value is meaningful: read accumulators when no thread is adding.
//!
//! Overflow is never silent: a single contribution that does not fit (`x * 2^48 >= 2^128`) is
//! saturated and counted, and a wrap of the high word is counted, in the `overflow` counter the
//! caller passes in (see [`crate::SdTree::overflow_events`]). Both counts are order independent
//! because all quantities are non-negative (signed gradients use separate positive and negative
//! accumulators).
//!
//! Quantisation: a real contribution `x >= 0` becomes `round(x * 2^48)`; contributions below
//! `2^-49` round to zero (they still count toward W when they are record values).

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

/// Number of fractional bits of the fixed-point format (one unit = `2^-FRAC_BITS`).
pub const FRAC_BITS: u32 = 48;
/// The fixed-point representation of the real number 1.
pub const FIXED_ONE: u128 = 1u128 << FRAC_BITS;

const SCALE: f64 = (1u64 << FRAC_BITS) as f64;

/// Converts a finite, non-negative real to fixed point, rounding to nearest.
///
/// Returns `(value, overflowed)`; a value too large for 128 bits saturates to `u128::MAX` and
/// sets `overflowed`. Non-finite or negative input returns `(0, false)`: callers filter those.
pub fn to_fixed(x: f64) -> (u128, bool) {
    if !(x > 0.0) || !x.is_finite() {
        return (0, false);
    }
    let s = (x * SCALE).round();
    if s < 18_446_744_073_709_551_616.0 {
        // Below 2^64 (x < 65536, nearly every value): the cheap conversion, same result.
        (s as u64 as u128, false)
    } else if s >= 3.402_823_669_209_385e38 {
        (u128::MAX, true)
    } else {
        (s as u128, false)
    }
}

/// Converts a fixed-point integer back to a real (`q * 2^-48`), correctly rounded to f64.
#[inline]
pub fn from_fixed(q: u128) -> f64 {
    (q as f64) / SCALE
}

/// A 128-bit unsigned fixed-point accumulator that many threads may add to concurrently.
#[derive(Default, Debug)]
pub struct Acc128 {
    lo: AtomicU64,
    hi: AtomicU64,
}

impl Clone for Acc128 {
    fn clone(&self) -> Self {
        Self::from_u128(self.get())
    }
}

impl PartialEq for Acc128 {
    fn eq(&self, other: &Self) -> bool {
        self.get() == other.get()
    }
}
impl Eq for Acc128 {}

impl Acc128 {
    /// An accumulator holding `v`.
    pub fn from_u128(v: u128) -> Self {
        Self {
            lo: AtomicU64::new(v as u64),
            hi: AtomicU64::new((v >> 64) as u64),
        }
    }

    /// Adds `v` (thread safe, order independent); a wrap of the 128-bit value increments `overflow`.
    #[inline]
    pub fn add(&self, v: u128, overflow: &AtomicU64) {
        if v == 0 {
            return;
        }
        let a_lo = v as u64;
        let a_hi = (v >> 64) as u64;
        let old_lo = self.lo.fetch_add(a_lo, Relaxed);
        let carry = old_lo.checked_add(a_lo).is_none() as u64;
        let add_hi = a_hi.wrapping_add(carry);
        // a_hi = u64::MAX with a carry wraps to 0 here, which is itself a 128-bit overflow.
        let hi_overflow_from_carry = add_hi < a_hi;
        if add_hi != 0 {
            let old_hi = self.hi.fetch_add(add_hi, Relaxed);
            if old_hi.checked_add(add_hi).is_none() {
                overflow.fetch_add(1, Relaxed);
            }
        }
        if hi_overflow_from_carry {
            overflow.fetch_add(1, Relaxed);
        }
    }

    /// Current value (meaningful once no thread is adding).
    #[inline]
    pub fn get(&self) -> u128 {
        (self.lo.load(Relaxed) as u128) | ((self.hi.load(Relaxed) as u128) << 64)
    }

    /// Current value as a real number.
    #[inline]
    pub fn get_f64(&self) -> f64 {
        from_fixed(self.get())
    }

    /// Overwrites the value (requires exclusive access in practice; used by build/reset).
    #[inline]
    pub fn set(&self, v: u128) {
        self.lo.store(v as u64, Relaxed);
        self.hi.store((v >> 64) as u64, Relaxed);
    }

    /// Takes the value and leaves zero.
    pub fn take(&self) -> u128 {
        let v = self.get();
        self.set(0);
        v
    }
}

/// Adds two fixed-point values, counting a wrap in `overflow` (non-atomic helper for merges).
#[inline]
pub fn add_counted(a: u128, b: u128, overflow: &mut u64) -> u128 {
    let (s, o) = a.overflowing_add(b);
    if o {
        *overflow += 1;
    }
    s
}

/// Splits the integer `q` into parts proportional to the non-negative real `weights`, exactly:
/// the parts always sum to `q` (mass conservation). Weights are quantised to 32 bits relative
/// to their maximum; each part is `floor(q * W_i / T)` and the remainder (fewer than
/// `weights.len()` units) goes to the first largest weight. Deterministic.
/// `out` is cleared and filled with one part per weight. An all-zero or empty weight list puts
/// everything in part 0 (if any).
pub fn split_exact(q: u128, weights: &[f64], out: &mut Vec<u128>) {
    out.clear();
    if weights.is_empty() {
        return;
    }
    let max = weights
        .iter()
        .cloned()
        .fold(0.0f64, |a, b| if b > a { b } else { a });
    out.resize(weights.len(), 0);
    if !(max > 0.0) || !max.is_finite() {
        out[0] = q;
        return;
    }
    // `out` holds the quantised weights (< 2^32 each) until each is replaced by its part: no
    // allocation per call.
    let mut t: u128 = 0;
    let mut imax = 0usize;
    for (i, &w) in weights.iter().enumerate() {
        let x = if w > 0.0 {
            ((w / max) * 4294967295.0).round() as u128
        } else {
            0
        };
        if x > out[imax] {
            imax = i;
        }
        out[i] = x;
        t += x;
    }
    let (qd, qr) = div_rem(q, t);
    let mut acc: u128 = 0;
    for o in out.iter_mut() {
        // qr < t, so (qr * x) / t < x < 2^32
        let x = *o;
        *o = qd * x + div_rem(qr * x, t).0;
        acc += *o;
    }
    out[imax] += q - acc;
}

/// `(a / b, a % b)`, in 64-bit arithmetic when both fit (the common case: a 128-bit division is
/// a library call).
#[inline]
fn div_rem(a: u128, b: u128) -> (u128, u128) {
    match (u64::try_from(a), u64::try_from(b)) {
        (Ok(a), Ok(b)) => ((a / b) as u128, (a % b) as u128),
        _ => (a / b, a % b),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::TestRng;

    #[test]
    fn acc128_carries_into_high_word_exactly_in_any_order() {
        let ov = AtomicU64::new(0);
        let vals: Vec<u128> = (0..1000u128)
            .map(|i| (u64::MAX as u128) - i * 12345 + (i << 70))
            .collect();
        let a = Acc128::default();
        for &v in &vals {
            a.add(v, &ov);
        }
        let b = Acc128::default();
        for &v in vals.iter().rev() {
            b.add(v, &ov);
        }
        let exact: u128 = vals.iter().sum();
        assert_eq!(a.get(), exact);
        assert_eq!(b.get(), exact);
        assert_eq!(ov.load(Relaxed), 0);
    }

    #[test]
    fn acc128_counts_wrap_as_overflow() {
        let ov = AtomicU64::new(0);
        let a = Acc128::from_u128(u128::MAX - 5);
        a.add(10, &ov);
        assert_eq!(a.get(), 4);
        assert_eq!(ov.load(Relaxed), 1);
        let (v, o) = to_fixed(1e40);
        assert!(o && v == u128::MAX);
        assert_eq!(to_fixed(f64::NAN), (0, false));
        assert_eq!(to_fixed(-1.0), (0, false));
        assert_eq!(to_fixed(1.0), (FIXED_ONE, false));
    }

    #[test]
    fn split_exact_conserves_every_unit() {
        let mut out = Vec::new();
        let mut s = 7u64;
        for n in 1..20 {
            let w: Vec<f64> = (0..n)
                .map(|_| {
                    s = s.wrapping_mul(6364136223846793005).wrapping_add(1);
                    ((s >> 11) as f64 / (1u64 << 53) as f64).powi(3)
                })
                .collect();
            for q in [0u128, 1, 7, 1 << 48, u128::MAX / 3, u128::MAX] {
                split_exact(q, &w, &mut out);
                let total = out.iter().fold(0u128, |a, b| a.wrapping_add(*b));
                assert_eq!(total, q);
                assert!(out.iter().all(|&p| p <= q));
            }
        }
    }

    /// `split_exact` as first written (quantised weights in a Vec, 128-bit divisions).
    fn split_exact_reference(q: u128, weights: &[f64]) -> Vec<u128> {
        let max = weights.iter().cloned().fold(0.0f64, f64::max);
        let mut out = vec![0u128; weights.len()];
        if !(max > 0.0) || !max.is_finite() {
            out[0] = q;
            return out;
        }
        let wi: Vec<u128> = weights
            .iter()
            .map(|&w| {
                if w > 0.0 {
                    ((w / max) * 4294967295.0).round() as u128
                } else {
                    0
                }
            })
            .collect();
        let t: u128 = wi.iter().sum();
        let imax = (0..wi.len()).fold(0, |m, i| if wi[i] > wi[m] { i } else { m });
        let mut acc = 0u128;
        for i in 0..wi.len() {
            out[i] = (q / t) * wi[i] + ((q % t) * wi[i]) / t;
            acc += out[i];
        }
        out[imax] += q - acc;
        out
    }

    #[test]
    fn split_exact_equals_the_128_bit_reference_bit_for_bit() {
        let mut rng = TestRng::new(8);
        let mut out = Vec::new();
        for n in 1..24 {
            for _ in 0..300 {
                let w: Vec<f64> = (0..n)
                    .map(|_| match rng.next_u32() % 4 {
                        0 => 0.0,
                        1 => rng.f32() as f64 * 1e-9,
                        _ => rng.f32() as f64,
                    })
                    .collect();
                let big = ((rng.next_u32() as u128) << 96) | ((rng.next_u32() as u128) << 40);
                for q in [
                    0u128,
                    1,
                    3,
                    (rng.next_u32() as u128) << 20,
                    u64::MAX as u128,
                    big,
                ] {
                    crate::stats::split_exact(q, &w, &mut out);
                    assert_eq!(out, split_exact_reference(q, &w), "q {q} weights {w:?}");
                }
            }
        }
    }
}
