//! Sampling building blocks: discrete distributions and warps.

use glam::{Vec2, Vec3};
use std::f32::consts::PI;

/// Distributions with at most this many bins pick theirs by counting (see
/// [`Distribution1D::sample`]).
const SMALL: usize = 8;

/// Piecewise-constant 1D distribution over `n` bins.
#[derive(Clone, Debug, Default)]
pub struct Distribution1D {
    /// Normalised CDF, `cdf[0] = 0`, `cdf[n] = 1`.
    cdf: Vec<f32>,
    /// Sum of the (unnormalised) weights.
    total: f64,
}

impl Distribution1D {
    /// The distribution proportional to `weights`; negative and non-finite weights count as zero.
    /// If every weight is zero, the last bin gets all the probability.
    pub fn new(weights: &[f32]) -> Self {
        let mut cdf = Vec::with_capacity(weights.len() + 1);
        let mut acc = 0.0f64;
        cdf.push(0.0);
        for &w in weights {
            acc += if w.is_finite() && w > 0.0 {
                w as f64
            } else {
                0.0
            };
            cdf.push(acc as f32);
        }
        if acc > 0.0 {
            for c in cdf.iter_mut() {
                *c = (*c as f64 / acc) as f32;
            }
        }
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        Self { cdf, total: acc }
    }

    /// Number of bins.
    pub fn len(&self) -> usize {
        self.cdf.len().saturating_sub(1)
    }

    /// Whether there are no bins (the default distribution); such a distribution cannot be sampled.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Sum of the valid weights (before normalisation), in f64.
    pub fn total(&self) -> f64 {
        self.total
    }

    /// Probability of bin `i`.
    #[inline]
    pub fn pmf(&self, i: usize) -> f32 {
        self.cdf[i + 1] - self.cdf[i]
    }

    /// Picks a bin; returns it with `u` rescaled to [0, 1) within the bin.
    #[inline]
    pub fn sample(&self, u: f32) -> (usize, f32) {
        let n = self.len();
        let i = if n <= SMALL {
            // Few bins (a rectangle light's two triangles): count the inner CDF
            // entries at or below `u` without branches, which the bisection's
            // unpredictable comparisons would cost. Same bin: the CDF is sorted.
            self.cdf[1..n]
                .iter()
                .map(|&c| (c <= u) as usize)
                .sum::<usize>()
        } else {
            (self.cdf.partition_point(|&c| c <= u).max(1) - 1).min(n - 1)
        };
        let (c0, c1) = (self.cdf[i], self.cdf[i + 1]);
        let r = if c1 > c0 {
            ((u - c0) / (c1 - c0)).clamp(0.0, 1.0 - f32::EPSILON)
        } else {
            0.5
        };
        (i, r)
    }
}

/// Uniform point on a triangle (as barycentrics b1, b2).
#[inline]
pub fn uniform_triangle(u: Vec2) -> Vec2 {
    let s = u.x.sqrt();
    Vec2::new(1.0 - s, u.y * s)
}

/// Uniform direction on the unit sphere from `u` in [0, 1)^2 (pdf 1 / (4 pi) per steradian).
#[inline]
pub fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Concentric map of the unit square to the unit disk (area-preserving).
#[inline]
pub fn concentric_disk(u: Vec2) -> Vec2 {
    let o = u * 2.0 - Vec2::ONE;
    if o.x == 0.0 && o.y == 0.0 {
        return Vec2::ZERO;
    }
    let (r, theta) = if o.x.abs() > o.y.abs() {
        (o.x, (PI / 4.0) * (o.y / o.x))
    } else {
        (o.y, PI / 2.0 - (PI / 4.0) * (o.x / o.y))
    };
    Vec2::new(r * theta.cos(), r * theta.sin())
}

/// Power heuristic (beta = 2) weight of strategy `a` against `b`.
#[inline]
pub fn power_heuristic(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 && (a2 + b2).is_finite() {
        a2 / (a2 + b2)
    } else if a.is_infinite() {
        1.0
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counting_few_bins_picks_the_bins_bisection_picks() {
        // Small distributions count CDF entries; larger ones bisect. Both must give the
        // same bin and rescaled number for any u, zero-weight bins and edges included.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        for n in 1..=SMALL {
            for _ in 0..50 {
                let w: Vec<f32> = (0..n)
                    .map(|_| if next() < 0.3 { 0.0 } else { next() })
                    .collect();
                let d = Distribution1D::new(&w);
                let mut us: Vec<f32> = (0..200).map(|_| next()).collect();
                us.extend(d.cdf.iter().copied());
                us.extend([0.0, 1.0 - f32::EPSILON / 2.0, -0.0, f32::NAN, 1.0, -1.0]);
                for u in us {
                    let i = (d.cdf.partition_point(|&c| c <= u).max(1) - 1).min(n - 1);
                    assert_eq!(d.sample(u).0, i, "n {n}, weights {w:?}, u {u}");
                }
            }
        }
    }

    #[test]
    fn distribution_picks_bins_in_proportion() {
        let d = Distribution1D::new(&[1.0, 0.0, 3.0]);
        assert!(
            (d.pmf(0) - 0.25).abs() < 1e-6 && d.pmf(1) == 0.0 && (d.pmf(2) - 0.75).abs() < 1e-6
        );
        assert_eq!(d.sample(0.1).0, 0);
        assert_eq!(d.sample(0.25).0, 2);
        assert_eq!(d.sample(0.999).0, 2);
        let (_, r) = d.sample(0.625);
        assert!((r - 0.5).abs() < 1e-5);
    }

    #[test]
    fn mis_weights_partition_unity() {
        for (a, b) in [(1.0, 2.0), (0.3, 0.0), (5.0, 1e-3)] {
            assert!((power_heuristic(a, b) + power_heuristic(b, a) - 1.0).abs() < 1e-6);
        }
    }
}
