//! Error of an image against a reference, as path-guiding papers measure it.

use anyhow::{bail, Result};

/// An RGB image: row-major pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<[f32; 3]>,
}

/// The offset in relMSE's denominator that keeps near-black pixels from dominating (Müller et
/// al. 2017 and later path-guiding papers use 0.01).
pub const RELMSE_EPSILON: f64 = 0.01;

/// The errors of one image against the reference.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Errors {
    /// Mean over pixels and channels of `(v - r)^2 / (r^2 + 0.01)`.
    pub relmse: f64,
    /// Mean over pixels and channels of `(v - r)^2`.
    pub mse: f64,
    /// Mean of the image's values (pixels and channels): a biased method shows here.
    pub mean: f64,
}

impl Image {
    /// Box-downsamples by the integer factor that takes this image to `width x height`
    /// (a reference rendered or supplied at a multiple of the resolution).
    pub fn downsample_to(&self, width: u32, height: u32) -> Result<Image> {
        if (self.width, self.height) == (width, height) {
            return Ok(self.clone());
        }
        let k = self.width / width.max(1);
        if k < 1 || self.width != k * width || self.height != k * height {
            bail!(
                "the reference is {}x{}, not {width}x{height} or an integer multiple of it",
                self.width,
                self.height
            );
        }
        let (k, w) = (k as usize, self.width as usize);
        let mut out = Vec::with_capacity((width * height) as usize);
        for y in 0..height as usize {
            for x in 0..width as usize {
                let mut acc = [0.0f64; 3];
                for dy in 0..k {
                    for dx in 0..k {
                        let p = self.pixels[(y * k + dy) * w + x * k + dx];
                        (0..3).for_each(|c| acc[c] += p[c] as f64);
                    }
                }
                out.push(acc.map(|a| (a / (k * k) as f64) as f32));
            }
        }
        Ok(Image {
            width,
            height,
            pixels: out,
        })
    }

    /// The per-pixel mean of two images of one size.
    pub fn average(a: &Image, b: &Image) -> Image {
        let pixels = a
            .pixels
            .iter()
            .zip(&b.pixels)
            .map(|(p, q)| [0, 1, 2].map(|c| ((p[c] as f64 + q[c] as f64) * 0.5) as f32))
            .collect();
        Image {
            width: a.width,
            height: a.height,
            pixels,
        }
    }
}

/// One pixel's relative squared error, averaged over its channels.
pub fn pixel_relse(v: [f32; 3], r: [f32; 3]) -> f64 {
    (0..3)
        .map(|c| {
            let d = v[c] as f64 - r[c] as f64;
            d * d / ((r[c] as f64).powi(2) + RELMSE_EPSILON)
        })
        .sum::<f64>()
        / 3.0
}

/// The errors of `img` against `reference` (same size).
pub fn errors(img: &Image, reference: &Image) -> Errors {
    let n = (img.pixels.len() * 3).max(1) as f64;
    let (mut rel, mut sq, mut sum) = (0.0f64, 0.0f64, 0.0f64);
    for (v, r) in img.pixels.iter().zip(&reference.pixels) {
        rel += pixel_relse(*v, *r) * 3.0;
        for c in 0..3 {
            let d = v[c] as f64 - r[c] as f64;
            sq += d * d;
            sum += v[c] as f64;
        }
    }
    Errors {
        relmse: rel / n,
        mse: sq / n,
        mean: sum / n,
    }
}

/// The relMSE floor of a reference made as the mean of two independent halves `a` and `b`:
/// each half's error has variance s^2, their difference 2 s^2, and the mean s^2 / 2, so the
/// reference's own relMSE is about a quarter of the halves' relMSE against each other. Curves
/// that reach this level measure the reference, not the method.
pub fn reference_floor(a: &Image, b: &Image) -> f64 {
    let mean = Image::average(a, b);
    let n = (a.pixels.len() * 3).max(1) as f64;
    let mut sum = 0.0;
    for ((p, q), r) in a.pixels.iter().zip(&b.pixels).zip(&mean.pixels) {
        for c in 0..3 {
            let d = p[c] as f64 - q[c] as f64;
            sum += d * d / ((r[c] as f64).powi(2) + RELMSE_EPSILON);
        }
    }
    sum / n / 4.0
}

/// The relMSE floor of a given reference, as `bench/floor.py` estimates it: for two
/// independent renders `a` and `b` of one expected image E, the mean of
/// `(a - ref)(b - ref) / (ref^2 + 0.01)` is an unbiased estimate of E's own relMSE against the
/// reference whatever the noise: for an unbiased method, the reference's error.
pub fn cross_floor(a: &Image, b: &Image, reference: &Image) -> f64 {
    let n = (a.pixels.len() * 3).max(1) as f64;
    let mut sum = 0.0;
    for ((p, q), r) in a.pixels.iter().zip(&b.pixels).zip(&reference.pixels) {
        for c in 0..3 {
            let rc = r[c] as f64;
            sum += (p[c] as f64 - rc) * (q[c] as f64 - rc) / (rc * rc + RELMSE_EPSILON);
        }
    }
    sum / n
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: u32, h: u32, f: impl Fn(u32, u32) -> [f32; 3]) -> Image {
        let pixels = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| f(x, y));
        Image {
            width: w,
            height: h,
            pixels: pixels.collect(),
        }
    }

    #[test]
    fn relmse_follows_the_papers_definition() {
        // Deterministic: one pixel off by 1 in one channel where the reference is 1.
        let r = img(2, 1, |_, _| [1.0, 1.0, 1.0]);
        let mut v = r.clone();
        v.pixels[0][0] = 2.0;
        let e = errors(&v, &r);
        assert!((e.relmse - 1.0 / 1.01 / 6.0).abs() < 1e-12, "{e:?}");
        assert!((e.mse - 1.0 / 6.0).abs() < 1e-12);
        assert!((e.mean - 7.0 / 6.0).abs() < 1e-12);
        assert_eq!(errors(&r, &r).relmse, 0.0);
    }

    #[test]
    fn downsampling_averages_blocks_and_refuses_other_sizes() {
        let big = img(4, 2, |x, y| [x as f32, y as f32, 1.0]);
        let small = big.downsample_to(2, 1).unwrap();
        assert_eq!(small.pixels, vec![[0.5, 0.5, 1.0], [2.5, 0.5, 1.0]]);
        assert!(big.downsample_to(3, 1).is_err());
        assert!(big.downsample_to(8, 4).is_err());
        assert_eq!(big.downsample_to(4, 2).unwrap(), big);
    }

    #[test]
    fn reference_floor_estimates_the_error_of_the_mean_of_two_halves() {
        // Two halves with independent noise of standard deviation s around a true image t:
        // the floor must estimate relMSE(mean of halves, t). Seeded; 64x64 pixels x 3
        // channels make the estimate's relative standard error about 2 %, and 15 % is
        // about 7 standard errors (significance far below 1e-6).
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut normal = move || {
            let mut u = || {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 11) as f64 / (1u64 << 53) as f64
            };
            let (a, b) = (u().max(1e-300), u());
            ((-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()) as f32
        };
        let truth = img(64, 64, |x, y| {
            [1.0 + (x % 7) as f32, 0.5, 2.0 + (y % 5) as f32]
        });
        let s = 0.1f32;
        let mut noisy = || Image {
            pixels: truth
                .pixels
                .iter()
                .map(|p| p.map(|v| v + s * normal()))
                .collect(),
            ..truth.clone()
        };
        let (a, b) = (noisy(), noisy());
        let floor = reference_floor(&a, &b);
        let actual = errors(&Image::average(&a, &b), &truth).relmse;
        assert!((floor / actual - 1.0).abs() < 0.15, "{floor} vs {actual}");
        // The same halves as two renders against a reference off by a known amount: the
        // cross term finds the offset's relMSE (noise s^2 = 0.01 per value averages out
        // to a standard error near 1e-4, against an offset relMSE above 4e-3).
        let off = Image {
            pixels: truth.pixels.iter().map(|p| p.map(|v| v + 0.2)).collect(),
            ..truth.clone()
        };
        let expected = errors(&truth, &off).relmse;
        let est = cross_floor(&a, &b, &off);
        assert!((est / expected - 1.0).abs() < 0.15, "{est} vs {expected}");
    }
}
