//! Per-pixel accumulation of filtered samples.
//!
//! A pixel keeps weighted sums of the samples splatted into it: sum w,
//! sum w L, and the second-order sums needed for the variance of the
//! weight-normalised mean. The renderer adds a pixel's contributions in a
//! canonical order (source pixel, then sample index), so the sums do not
//! depend on threads or tiles.

use glam::Vec3;
use rayon::prelude::*;

/// The running sums of one pixel: everything needed for its filter-weighted mean and the variance
/// of that mean, in f64 so that long renders do not lose precision.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelStats {
    /// Sum of the filter weights w of the samples splatted into the pixel.
    pub sum_w: f64,
    /// Sum of w L per RGB channel (L: the sample's radiance).
    pub sum_wl: [f64; 3],
    /// Sum of w^2.
    pub sum_w2: f64,
    /// Sum of w^2 L per RGB channel.
    pub sum_w2l: [f64; 3],
    /// Sum of w^2 L^2 per RGB channel.
    pub sum_w2l2: [f64; 3],
    /// Camera samples generated in this pixel.
    pub count: u32,
}

impl PixelStats {
    /// Adds one sample `v` with filter weight `w`.
    #[inline]
    pub fn add(&mut self, w: f32, v: Vec3) {
        let w = w as f64;
        let w2 = w * w;
        self.sum_w += w;
        self.sum_w2 += w2;
        for (c, x) in [v.x, v.y, v.z].into_iter().enumerate() {
            let x = x as f64;
            self.sum_wl[c] += w * x;
            self.sum_w2l[c] += w2 * x;
            self.sum_w2l2[c] += w2 * x * x;
        }
    }

    /// The pixel value: the weighted mean sum w L / sum w per channel; black when no weight reached
    /// the pixel.
    pub fn mean(&self) -> [f32; 3] {
        if self.sum_w <= 0.0 {
            return [0.0; 3];
        }
        self.sum_wl.map(|s| (s / self.sum_w) as f32)
    }

    /// Variance of the pixel value (the weighted mean), estimated as
    /// sum w^2 (L - mean)^2 / (sum w)^2, with the small-sample correction
    /// n_eff / (n_eff - 1), n_eff = (sum w)^2 / sum w^2. For unit weights this
    /// is the sample variance divided by N.
    pub fn variance_of_mean(&self) -> [f32; 3] {
        if self.sum_w <= 0.0 || self.sum_w2 <= 0.0 {
            return [0.0; 3];
        }
        let n_eff = self.sum_w * self.sum_w / self.sum_w2;
        if n_eff <= 1.0 + 1e-9 {
            return [0.0; 3];
        }
        std::array::from_fn(|c| {
            let m = self.sum_wl[c] / self.sum_w;
            let ss = self.sum_w2l2[c] - 2.0 * m * self.sum_w2l[c] + m * m * self.sum_w2;
            ((ss.max(0.0) / (self.sum_w * self.sum_w)) * n_eff / (n_eff - 1.0)) as f32
        })
    }
}

impl PixelStats {
    /// Bytes of [`PixelStats::write_le`]: the 11 f64 sums and the u32 sample count.
    pub const BYTES: usize = 11 * 8 + 4;

    /// Appends the sums (raw bits, little-endian) and the count: the exact form in which
    /// tiles travel and checkpoints keep films.
    pub fn write_le(&self, out: &mut Vec<u8>) {
        let sums = [self.sum_w, self.sum_w2].into_iter().chain(self.sum_wl);
        for x in sums.chain(self.sum_w2l).chain(self.sum_w2l2) {
            out.extend_from_slice(&x.to_le_bytes());
        }
        out.extend_from_slice(&self.count.to_le_bytes());
    }

    /// Reads what [`PixelStats::write_le`] wrote (`b` holds [`PixelStats::BYTES`] bytes).
    pub fn read_le(b: &[u8; Self::BYTES]) -> Self {
        let f = |k: usize| f64::from_le_bytes(b[8 * k..8 * k + 8].try_into().unwrap());
        PixelStats {
            sum_w: f(0),
            sum_w2: f(1),
            sum_wl: [f(2), f(3), f(4)],
            sum_w2l: [f(5), f(6), f(7)],
            sum_w2l2: [f(8), f(9), f(10)],
            count: u32::from_le_bytes(b[88..92].try_into().unwrap()),
        }
    }
}

/// The image being rendered.
#[derive(Clone, Debug, PartialEq)]
pub struct Film {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// The pixels' sums, row-major, `width * height` of them: pixel (x, y) is at `y * width + x`
    /// (for a region's film, relative to the region's corner).
    pub pixels: Vec<PixelStats>,
}

impl Film {
    /// An empty (all-zero) film of `width x height` pixels.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: zeroed_pixels(width as usize * height as usize),
        }
    }

    /// Every pixel's value ([`PixelStats::mean`]), row-major.
    pub fn mean_rgb(&self) -> Vec<[f32; 3]> {
        self.pixels.iter().map(|p| p.mean()).collect()
    }

    /// Every pixel's variance of the mean ([`PixelStats::variance_of_mean`]), row-major.
    pub fn variance_rgb(&self) -> Vec<[f32; 3]> {
        self.pixels.iter().map(|p| p.variance_of_mean()).collect()
    }

    /// Adds `other`'s samples to this film's (same size), as if they had been rendered
    /// into it: the pixel sums add.
    pub fn merge(&mut self, other: &Film) {
        assert_eq!((self.width, self.height), (other.width, other.height));
        // Pixel by pixel, so the same sums however the pixels are shared among threads (a
        // farm coordinator merges a 1920x1080 unit, 190 MB, at every unit's end).
        (self.pixels.par_iter_mut().zip(&other.pixels))
            .with_min_len(1 << 14)
            .for_each(|(p, q)| p.merge(q));
    }
}

/// `n` pixels of [`PixelStats::default`], whose bits are all zero: from the allocator's
/// zeroed memory, which for a large film is fresh pages the kernel zeroes as they are first
/// touched, instead of a pass writing defaults over all of them at once (a 1920x1080 film is
/// 190 MB; a farm coordinator made one under its state lock at every iteration's start).
fn zeroed_pixels(n: usize) -> Vec<PixelStats> {
    if n == 0 {
        return Vec::new();
    }
    let layout = std::alloc::Layout::array::<PixelStats>(n).expect("a film's size");
    // SAFETY: `layout` has a nonzero size; the memory is allocated by the global allocator
    // with the layout of a `Vec<PixelStats>` of capacity `n`, and all-zero bytes are a
    // valid `PixelStats` (f64 0.0 and u32 0), so all `n` are initialised.
    unsafe {
        let ptr = std::alloc::alloc_zeroed(layout);
        if ptr.is_null() {
            std::alloc::handle_alloc_error(layout);
        }
        Vec::from_raw_parts(ptr.cast::<PixelStats>(), n, n)
    }
}

impl PixelStats {
    /// Adds `q`'s sums to these.
    #[inline]
    pub(crate) fn merge(&mut self, q: &PixelStats) {
        self.sum_w += q.sum_w;
        self.sum_w2 += q.sum_w2;
        for c in 0..3 {
            self.sum_wl[c] += q.sum_wl[c];
            self.sum_w2l[c] += q.sum_w2l[c];
            self.sum_w2l2[c] += q.sum_w2l2[c];
        }
        self.count += q.count;
    }
}

/// A pixel's sums while samples are added to it one after another: [`PixelStats::add`]'s
/// operations lane by lane in two arrays, which the compiler turns into a few vector
/// instructions (a coordinator gathers about twenty samples into every pixel of a unit).
/// The same operations on the same operands as `add` (`w * 1` is `w`), so the same bits.
#[derive(Clone, Copy, Default)]
pub(crate) struct Accumulator {
    /// sum w, sum w L (3), sum w^2, sum w^2 L (3).
    a: [f64; 8],
    /// (unused), sum w^2 L^2 (3).
    b: [f64; 4],
}

impl Accumulator {
    /// The sums of `p`, to add to.
    #[inline(always)]
    pub(crate) fn of(p: &PixelStats) -> Self {
        let (l, m, q) = (p.sum_wl, p.sum_w2l, p.sum_w2l2);
        Accumulator {
            a: [p.sum_w, l[0], l[1], l[2], p.sum_w2, m[0], m[1], m[2]],
            b: [0.0, q[0], q[1], q[2]],
        }
    }

    /// Adds one sample `v` with filter weight `w`, as [`PixelStats::add`] does.
    // (indexed loops over fixed-size arrays: the form the compiler puts in vector lanes)
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    pub(crate) fn add(&mut self, w: f32, v: Vec3) {
        let w = w as f64;
        let w2 = w * w;
        let x = [1.0, v.x as f64, v.y as f64, v.z as f64];
        let mut m = [0.0f64; 8];
        for k in 0..4 {
            m[k] = w * x[k];
            m[4 + k] = w2 * x[k];
        }
        for k in 0..8 {
            self.a[k] += m[k];
        }
        for k in 0..4 {
            self.b[k] += m[4 + k] * x[k];
        }
    }

    /// Writes the sums back into `p` (its count is the caller's).
    #[inline(always)]
    pub(crate) fn store(self, p: &mut PixelStats) {
        let a = self.a;
        p.sum_w = a[0];
        p.sum_wl = [a[1], a[2], a[3]];
        p.sum_w2 = a[4];
        p.sum_w2l = [a[5], a[6], a[7]];
        p.sum_w2l2 = [self.b[1], self.b[2], self.b[3]];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_accumulator_adds_the_bits_pixel_stats_add_adds() {
        // Deterministic identity (no significance level): long random runs of weights and
        // radiance over many magnitudes, from a pixel holding sums already.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        for run in 0..200 {
            let mut p = PixelStats::default();
            p.add(0.3, Vec3::new(1.0, 2.0, 3.0));
            let mut acc = Accumulator::of(&p);
            for _ in 0..(run % 40) {
                let w = if next() < 0.2 { 0.0 } else { next() };
                let scale = 10f32.powi((next() * 12.0) as i32 - 6);
                let v = Vec3::new(next(), next(), next()) * scale;
                p.add(w, v);
                acc.add(w, v);
            }
            let mut q = p;
            q.sum_w = -1.0;
            q.sum_w2l2 = [7.0; 3];
            acc.store(&mut q);
            let bits = |p: &PixelStats| {
                let mut out = Vec::new();
                p.write_le(&mut out);
                out
            };
            assert_eq!(bits(&q), bits(&p), "run {run}");
        }
    }

    #[test]
    fn unit_weights_give_mean_and_variance_of_the_mean() {
        let mut p = PixelStats::default();
        for x in [1.0f32, 2.0, 3.0, 4.0] {
            p.add(1.0, Vec3::splat(x));
        }
        assert_eq!(p.mean(), [2.5; 3]);
        // Sample variance 5/3, divided by N = 4.
        assert!((p.variance_of_mean()[0] - 5.0 / 12.0).abs() < 1e-6);
    }

    #[test]
    fn weighted_mean_normalises_by_the_weights() {
        let mut p = PixelStats::default();
        p.add(0.25, Vec3::splat(4.0));
        p.add(0.75, Vec3::splat(0.0));
        assert_eq!(p.mean(), [1.0; 3]);
    }

    #[test]
    fn merging_films_equals_adding_their_samples_to_one() {
        // dyadic values: every sum is exact, so the comparison can be bit for bit
        let samples = [(0.5f32, 1.0f32), (1.0, 2.0), (0.25, 8.0), (0.75, 0.5)];
        let mut one = Film::new(2, 1);
        let (mut a, mut b) = (Film::new(2, 1), Film::new(2, 1));
        for (i, &(w, x)) in samples.iter().enumerate() {
            let px = i % 2;
            one.pixels[px].add(w, Vec3::new(x, 2.0 * x, 0.0));
            one.pixels[px].count += 1;
            let f = if i < 2 { &mut a } else { &mut b };
            f.pixels[px].add(w, Vec3::new(x, 2.0 * x, 0.0));
            f.pixels[px].count += 1;
        }
        a.merge(&b);
        assert_eq!(a, one);
        assert_eq!(a.pixels[0].count, 2);
    }
}
