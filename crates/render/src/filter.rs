//! Reconstruction filters by importance sampling.
//!
//! Each camera sample picks its film offset from the (normalised) filter and
//! contributes to exactly one pixel with weight 1. The expected pixel value is
//! the same filtered, weight-normalised value that Mitsuba's splatting
//! computes, and a pixel depends only on its own samples: that keeps images
//! independent of tiling.

use glam::Vec2;
use pathfarm_scene::RFilter;

#[derive(Clone, Copy, Debug)]
pub enum Filter {
    Box { radius: f32 },
    Tent { radius: f32 },
    /// Truncated at 4 standard deviations, as Mitsuba does.
    Gaussian { stddev: f32 },
}

impl Filter {
    pub fn new(desc: RFilter) -> Self {
        match desc {
            RFilter::Box { radius } => Filter::Box { radius },
            RFilter::Tent { radius } => Filter::Tent { radius },
            RFilter::Gaussian { stddev } => Filter::Gaussian { stddev },
        }
    }

    /// Offset from the pixel centre for the uniform sample `u`.
    #[inline]
    pub fn sample(&self, u: Vec2) -> Vec2 {
        match *self {
            Filter::Box { radius } => (u * 2.0 - Vec2::ONE) * radius,
            Filter::Tent { radius } => Vec2::new(sample_tent(u.x), sample_tent(u.y)) * radius,
            Filter::Gaussian { stddev } => Vec2::new(sample_truncated_gaussian(u.x, stddev), sample_truncated_gaussian(u.y, stddev)),
        }
    }
}

/// Inverse CDF of the unit tent on [-1, 1].
#[inline]
fn sample_tent(u: f32) -> f32 {
    if u < 0.5 {
        (2.0 * u).sqrt() - 1.0
    } else {
        1.0 - (2.0 - 2.0 * u).sqrt()
    }
}

/// Mitsuba's gaussian filter: exp(-x^2 / (2 s^2)) minus its value at the
/// radius 4s, clamped at 0. Sampled by inverting a tabulated CDF.
fn sample_truncated_gaussian(u: f32, stddev: f32) -> f32 {
    const N: usize = 256;
    thread_local! {
        static CDF: Vec<f32> = {
            // Table for stddev = 1 over [-4, 4].
            let f = |x: f32| ((-0.5 * x * x).exp() - (-0.5f32 * 16.0).exp()).max(0.0);
            let mut cdf = vec![0.0f32; N + 1];
            for i in 0..N {
                let x0 = -4.0 + 8.0 * i as f32 / N as f32;
                let x1 = -4.0 + 8.0 * (i + 1) as f32 / N as f32;
                cdf[i + 1] = cdf[i] + 0.5 * (f(x0) + f(x1)) * (x1 - x0);
            }
            let total = cdf[N];
            cdf.iter_mut().for_each(|c| *c /= total);
            cdf
        };
    }
    CDF.with(|cdf| {
        let i = cdf.partition_point(|&c| c <= u).clamp(1, N) - 1;
        let (c0, c1) = (cdf[i], cdf[i + 1]);
        let t = if c1 > c0 { (u - c0) / (c1 - c0) } else { 0.5 };
        (-4.0 + 8.0 * (i as f32 + t) / N as f32) * stddev
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tent_samples_follow_the_tent_density() {
        // Histogram of 10 bins on [-1, 1] against the tent's bin masses.
        let n = 100_000;
        let mut bins = [0usize; 10];
        for i in 0..n {
            let x = sample_tent((i as f32 + 0.5) / n as f32);
            bins[((x + 1.0) * 5.0).clamp(0.0, 9.999) as usize] += 1;
        }
        for (b, &count) in bins.iter().enumerate() {
            let (a, c) = (-1.0 + 0.2 * b as f64, -1.0 + 0.2 * (b + 1) as f64);
            let cdf = |x: f64| if x < 0.0 { 0.5 * (1.0 + x) * (1.0 + x) } else { 1.0 - 0.5 * (1.0 - x) * (1.0 - x) };
            let expected = (cdf(c) - cdf(a)) * n as f64;
            assert!((count as f64 - expected).abs() < 0.01 * n as f64, "bin {b}: {count} vs {expected}");
        }
    }

    #[test]
    fn gaussian_samples_are_centred_with_the_right_spread() {
        let n = 100_000;
        let (mut m1, mut m2) = (0.0f64, 0.0f64);
        for i in 0..n {
            let x = sample_truncated_gaussian((i as f32 + 0.5) / n as f32, 0.5) as f64;
            assert!(x.abs() <= 2.0 + 1e-4);
            m1 += x;
            m2 += x * x;
        }
        m1 /= n as f64;
        m2 /= n as f64;
        assert!(m1.abs() < 1e-3);
        // Variance of the truncated, offset gaussian with s = 0.5 is a little below 0.25.
        assert!(m2 > 0.2 && m2 < 0.25, "{m2}");
    }
}
