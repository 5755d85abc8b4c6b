//! Per-pixel accumulation of samples.
//!
//! Each pixel keeps the running sum and sum of squares of its samples (in
//! f64, added in sample-index order), so the mean and the variance of the mean
//! are available, and the result does not depend on how pixels were grouped
//! into tiles or passes.

use glam::Vec3;

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelStats {
    pub sum: [f64; 3],
    pub sum_sq: [f64; 3],
    pub count: u32,
}

impl PixelStats {
    #[inline]
    pub fn add(&mut self, v: Vec3) {
        for (c, x) in [v.x, v.y, v.z].into_iter().enumerate() {
            let x = x as f64;
            self.sum[c] += x;
            self.sum_sq[c] += x * x;
        }
        self.count += 1;
    }

    pub fn mean(&self) -> [f32; 3] {
        let n = self.count.max(1) as f64;
        self.sum.map(|s| (s / n) as f32)
    }

    /// Unbiased variance of the pixel mean: sample variance / N.
    pub fn variance_of_mean(&self) -> [f32; 3] {
        let n = self.count as f64;
        if n < 2.0 {
            return [0.0; 3];
        }
        std::array::from_fn(|c| {
            let m = self.sum[c] / n;
            let var = ((self.sum_sq[c] - n * m * m) / (n - 1.0)).max(0.0);
            (var / n) as f32
        })
    }
}

/// The image being rendered.
#[derive(Clone, Debug, PartialEq)]
pub struct Film {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<PixelStats>,
}

impl Film {
    pub fn new(width: u32, height: u32) -> Self {
        Self { width, height, pixels: vec![PixelStats::default(); (width * height) as usize] }
    }

    pub fn mean_rgb(&self) -> Vec<[f32; 3]> {
        self.pixels.iter().map(|p| p.mean()).collect()
    }

    pub fn variance_rgb(&self) -> Vec<[f32; 3]> {
        self.pixels.iter().map(|p| p.variance_of_mean()).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixel_stats_give_mean_and_variance_of_the_mean() {
        let mut p = PixelStats::default();
        for x in [1.0f32, 2.0, 3.0, 4.0] {
            p.add(Vec3::splat(x));
        }
        assert_eq!(p.mean(), [2.5; 3]);
        // Sample variance 5/3, divided by N = 4.
        assert!((p.variance_of_mean()[0] - 5.0 / 12.0).abs() < 1e-6);
    }
}
