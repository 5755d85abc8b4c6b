//! The render loop: tiles in parallel, passes of samples, a sample budget or
//! a time budget.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use glam::Vec2;
use rayon::prelude::*;

use crate::film::Film;
use crate::filter::Filter;
use crate::geometry::Ray;
use crate::integrator::wavefront::PathWavefront;
use crate::rng::Rng;
use crate::scene::Scene;

/// Default edge length of a square tile, in pixels.
pub const DEFAULT_TILE: u32 = 16;

/// What to render.
#[derive(Clone, Debug)]
pub struct RenderSettings {
    /// Samples per pixel; `None` uses the scene's `sample_count`, or is
    /// unbounded when `time_limit` is set.
    pub spp: Option<u32>,
    /// Stop after this much wall time (at a pass boundary).
    pub time_limit: Option<Duration>,
    /// Seed of every random stream.
    pub seed: u64,
    /// Pixels per work item (default 16). Does not change the image.
    pub tile_size: u32,
    /// Samples per pass when rendering to a sample budget (default: all in
    /// one pass). Does not change the image.
    pub pass_spp: Option<u32>,
}

impl RenderSettings {
    pub fn new(spp: Option<u32>, time_limit: Option<Duration>, seed: u64) -> Self {
        Self {
            spp,
            time_limit,
            seed,
            tile_size: DEFAULT_TILE,
            pass_spp: None,
        }
    }
}

/// Reported as the render advances.
#[derive(Clone, Copy, Debug)]
pub struct Progress {
    /// Samples done / expected (the expectation grows with time budgets).
    pub samples_done: u64,
    pub samples_total: u64,
}

#[derive(Clone, Copy, Debug)]
pub struct RenderStats {
    pub spp: u32,
    pub wall: Duration,
    /// Camera samples that produced a non-finite value (counted as zero).
    pub invalid_samples: u64,
}

/// One camera sample, kept until it has been splatted: its film position
/// within its pixel and its radiance estimate.
#[derive(Clone, Copy, Default)]
struct SampleRec {
    offset: Vec2,
    value: glam::Vec3,
}

/// Upper bound on the sample buffer of one pass (bytes).
const PASS_BUFFER_BYTES: usize = 256 << 20;

/// Renders the scene into a film.
///
/// Each pass renders samples `s0..s1` of every pixel (phase 1, rows in
/// parallel), then splats them (phase 2): every pixel gathers, in a fixed
/// order (source pixel, then sample index), the samples within its filter's
/// support. Pixels only depend on their own gather, so the image is the same
/// for any thread count or tile size.
pub fn render(
    scene: &Scene,
    settings: &RenderSettings,
    progress: &(dyn Fn(Progress) + Sync),
) -> (Film, RenderStats) {
    let mut film = Film::new(scene.width, scene.height);
    let stats = render_into(
        scene,
        settings,
        progress,
        0,
        &mut film,
        &path_estimator(scene),
    );
    (film, stats)
}

/// One camera sample handed to an [`Estimator`]: its ray and the index `y * width + x` of
/// its pixel.
#[derive(Clone, Copy, Debug)]
pub struct CameraSample {
    pub ray: Ray,
    pub pixel: usize,
}

/// What [`render_into`] runs for every camera sample: radiance estimates for a batch of
/// samples. `rngs[k]` is sample `k`'s own generator (after the two pixel-offset numbers);
/// an estimate may depend only on its own sample and generator, never on the batch, so
/// that images do not depend on how the work is split. Any
/// `Fn(Ray, &mut Rng, pixel) -> Vec3` is an estimator taking one sample at a time.
pub trait Estimator: Sync {
    fn estimate(&self, samples: &[CameraSample], rngs: &mut [Rng], out: &mut [glam::Vec3]);
}

impl<F> Estimator for F
where
    F: Fn(Ray, &mut Rng, usize) -> glam::Vec3 + Sync,
{
    fn estimate(&self, samples: &[CameraSample], rngs: &mut [Rng], out: &mut [glam::Vec3]) {
        for ((s, rng), o) in samples.iter().zip(rngs.iter_mut()).zip(out.iter_mut()) {
            *o = self(s.ray, rng, s.pixel);
        }
    }
}

/// The `path` integrator as an [`Estimator`]: batches of paths side by side
/// ([`crate::integrator::wavefront`]), specialised for the effects the scene has.
pub fn path_estimator(scene: &Scene) -> PathEstimator<'_> {
    PathEstimator { scene }
}

/// See [`path_estimator`].
pub struct PathEstimator<'a> {
    scene: &'a Scene,
}

impl Estimator for PathEstimator<'_> {
    fn estimate(&self, samples: &[CameraSample], rngs: &mut [Rng], out: &mut [glam::Vec3]) {
        let scene = self.scene;
        match (scene.features.environment, scene.features.analytic_shapes) {
            (false, false) => PathWavefront::<false, false> { scene }.estimate(samples, rngs, out),
            (true, false) => PathWavefront::<true, false> { scene }.estimate(samples, rngs, out),
            (false, true) => PathWavefront::<false, true> { scene }.estimate(samples, rngs, out),
            (true, true) => PathWavefront::<true, true> { scene }.estimate(samples, rngs, out),
        }
    }
}

/// The filter weights of a sample at `offset` in its pixel `(qx, qy)` towards the pixels
/// `(qx - reach + k, ...)`: `out[k]` along x and `out[span + k]` along y, `span = 2 reach + 1`.
/// The offset from a target pixel's centre is `(qx - px) - 0.5 + offset`, which is exactly the
/// `q - (p + 0.5) + offset` of a per-pair evaluation (small integers and halves are exact in
/// f32), so the weights are the same bits.
#[inline]
fn axis_weights(filter: &Filter, reach: i32, offset: Vec2, out: &mut [f32]) {
    let span = 2 * reach as usize + 1;
    for k in 0..span {
        // target p = q - reach + k, so q - p = reach - k
        let base = (reach - k as i32) as f32 - 0.5;
        out[k] = filter.eval(base + offset.x);
        out[span + k] = filter.eval(base + offset.y);
    }
}

/// Per-thread buffers of one phase-1 chunk.
#[derive(Default)]
struct ChunkScratch {
    samples: Vec<CameraSample>,
    rngs: Vec<Rng>,
    values: Vec<glam::Vec3>,
}

/// The render loop of [`render`] with any [`Estimator`], accumulating into
/// `film`. Sample `k` of this call uses the random stream of sample index
/// `first_sample + k`, so successive calls (e.g. the passes of path-guiding
/// iterations) draw fresh, deterministic streams. The estimator gets each
/// tile's camera samples as one batch: rays, pixel indices `y * width + x`
/// and the samples' own generators (after the two pixel-offset numbers).
pub fn render_into<E>(
    scene: &Scene,
    settings: &RenderSettings,
    progress: &(dyn Fn(Progress) + Sync),
    first_sample: u64,
    film: &mut Film,
    estimator: &E,
) -> RenderStats
where
    E: Estimator + ?Sized,
{
    let (w, h) = (scene.width, scene.height);
    let start = Instant::now();
    let target_spp = match (settings.spp, settings.time_limit) {
        (Some(s), _) => s,
        (None, Some(_)) => u32::MAX,
        (None, None) => scene.sample_count,
    };
    let npix = (w as usize) * (h as usize);
    let max_pass =
        ((PASS_BUFFER_BYTES / (npix.max(1) * std::mem::size_of::<SampleRec>())) as u32).max(1);
    let tile = settings.tile_size.max(1) as usize;
    let done = AtomicU64::new(0);
    let invalid = AtomicU64::new(0);
    let mut spp_done = 0u32;
    let mut pass = if settings.time_limit.is_some() {
        1
    } else {
        settings.pass_spp.unwrap_or(target_spp)
    };
    let mut buffer: Vec<SampleRec> = Vec::new();
    let mut weights: Vec<f32> = Vec::new();
    while spp_done < target_spp {
        let s0 = spp_done;
        let s1 = s0.saturating_add(pass.clamp(1, max_pass)).min(target_spp);
        let n = (s1 - s0) as usize;
        let total = match (settings.time_limit, settings.spp) {
            (Some(limit), None) => {
                let rate = (done.load(Ordering::Relaxed) as f64
                    / start.elapsed().as_secs_f64().max(1e-3))
                .max(1.0);
                (rate * limit.as_secs_f64()) as u64
            }
            _ => npix as u64 * target_spp as u64,
        };
        // Phase 1: samples, in tiles of `tile` pixels along each row.
        buffer.clear();
        buffer.resize(npix * n, SampleRec::default());
        buffer.par_chunks_mut(tile * n).enumerate().for_each_init(
            ChunkScratch::default,
            |scratch, (chunk, out)| {
                let first = chunk * tile;
                scratch.samples.clear();
                scratch.rngs.clear();
                for (i, recs) in out.chunks_mut(n).enumerate() {
                    let pixel = first + i;
                    let (x, y) = ((pixel % w as usize) as u32, (pixel / w as usize) as u32);
                    for (k, rec) in recs.iter_mut().enumerate() {
                        let index = first_sample + (s0 as usize + k) as u64;
                        let mut rng = Rng::for_sample(settings.seed, pixel as u64, index);
                        rec.offset = rng.next_2d();
                        let ray = scene.camera.ray(Vec2::new(x as f32, y as f32) + rec.offset);
                        scratch.samples.push(CameraSample { ray, pixel });
                        scratch.rngs.push(rng);
                    }
                }
                scratch.values.clear();
                scratch.values.resize(out.len(), glam::Vec3::ZERO);
                estimator.estimate(&scratch.samples, &mut scratch.rngs, &mut scratch.values);
                let mut bad = 0u64;
                for (rec, &value) in out.iter_mut().zip(&scratch.values) {
                    rec.value = if value.is_finite() {
                        value
                    } else {
                        bad += 1;
                        glam::Vec3::ZERO
                    };
                }
                invalid.fetch_add(bad, Ordering::Relaxed);
                let m = (out.len()) as u64;
                let d = done.fetch_add(m, Ordering::Relaxed) + m;
                progress(Progress {
                    samples_done: d,
                    samples_total: total.max(d),
                });
            },
        );
        // Phase 2: splat by gathering. The filter is separable: each sample's weights along x
        // and y towards the 2 reach + 1 pixel columns and rows it can reach are evaluated once
        // (`axis_weights`), not once per target pixel (a gaussian's 5x5 footprint evaluated
        // per pair cost 5x the exponentials; door-ajar path tracing spent about a quarter of
        // its time here). Same operands as a per-pair evaluation, so the same bits.
        let filter = scene.filter;
        let reach = filter.reach();
        let span = 2 * reach as usize + 1;
        // (every entry is written below: resizing keeps old values instead of zeroing)
        weights.resize(npix * n * 2 * span, 0.0);
        weights
            .par_chunks_mut(tile * n * 2 * span)
            .zip(buffer.par_chunks(tile * n))
            .for_each(|(out, recs)| {
                for (wt, rec) in out.chunks_mut(2 * span).zip(recs) {
                    axis_weights(&filter, reach, rec.offset, wt);
                }
            });
        let (buf, wts) = (&buffer, &weights);
        film.pixels
            .par_chunks_mut(w as usize)
            .enumerate()
            .for_each(|(y, row)| {
                let y = y as i32;
                for (x, stats) in row.iter_mut().enumerate() {
                    let x = x as i32;
                    stats.count += n as u32;
                    for qy in (y - reach).max(0)..=(y + reach).min(h as i32 - 1) {
                        let ky = span + (y - qy + reach) as usize;
                        for qx in (x - reach).max(0)..=(x + reach).min(w as i32 - 1) {
                            let kx = (x - qx + reach) as usize;
                            let q = qy as usize * w as usize + qx as usize;
                            let recs = &buf[q * n..(q + 1) * n];
                            let ws = wts[q * n * 2 * span..(q + 1) * n * 2 * span]
                                .chunks_exact(2 * span);
                            for (rec, wt) in recs.iter().zip(ws) {
                                // Added even at weight zero (it adds exact zeros: the sums
                                // are unchanged), which is cheaper than a branch that the
                                // random sample positions make unpredictable.
                                stats.add(wt[kx] * wt[ky], rec.value);
                            }
                        }
                    }
                }
            });
        spp_done = s1;
        if let Some(limit) = settings.time_limit {
            let elapsed = start.elapsed();
            if elapsed >= limit {
                break;
            }
            // Size the next pass to about a second, or to what is left.
            let per_spp = elapsed.as_secs_f64() / spp_done as f64;
            let left = (limit - elapsed).as_secs_f64();
            if left < 0.5 * per_spp {
                break;
            }
            pass = ((left.min(1.0) / per_spp).floor() as u32).max(1);
        }
    }
    RenderStats {
        spp: spp_done,
        wall: start.elapsed(),
        invalid_samples: invalid.load(Ordering::Relaxed),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn separable_splat_weights_equal_the_per_pair_filter_bits() {
        // Deterministic identity (no significance level): for every filter, random sample
        // offsets and every (source, target) pixel pair in reach, the product of the
        // precomputed axis weights is bit for bit the per-pair `eval(d.x) * eval(d.y)`.
        let filters = [
            Filter::Box { radius: 0.5 },
            Filter::Box { radius: 1.5 },
            Filter::Tent { radius: 1.0 },
            Filter::Tent { radius: 2.5 },
            Filter::Gaussian { stddev: 0.5 },
            Filter::Gaussian { stddev: 0.8 },
        ];
        let mut rng = Rng::new(31, 7);
        let mut nonzero = 0;
        for filter in filters {
            let reach = filter.reach();
            let span = 2 * reach as usize + 1;
            let mut wt = vec![0.0f32; 2 * span];
            for _ in 0..500 {
                let offset = rng.next_2d();
                let (qx, qy) = (7i32, 9i32);
                axis_weights(&filter, reach, offset, &mut wt);
                for py in qy - reach..=qy + reach {
                    for px in qx - reach..=qx + reach {
                        let centre = Vec2::new(px as f32 + 0.5, py as f32 + 0.5);
                        let d = Vec2::new(qx as f32, qy as f32) - centre + offset;
                        let per_pair = filter.eval(d.x) * filter.eval(d.y);
                        let (kx, ky) = ((px - qx + reach) as usize, (py - qy + reach) as usize);
                        let separable = wt[kx] * wt[span + ky];
                        assert_eq!(separable.to_bits(), per_pair.to_bits(), "{filter:?}");
                        nonzero += (per_pair != 0.0) as u32;
                    }
                }
            }
        }
        assert!(nonzero > 10_000, "weights must not all vanish ({nonzero})");
    }
}
