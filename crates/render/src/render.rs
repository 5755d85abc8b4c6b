//! The render loop: tiles in parallel, passes of samples, a sample budget or
//! a time budget.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use glam::Vec2;
use rayon::prelude::*;

use crate::film::Film;
use crate::geometry::Ray;
use crate::integrator::wavefront::PathWavefront;
use crate::rng::Rng;
use crate::scene::Scene;
use crate::splat::{SampleRec, Splat};

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
    /// Settings with the given budget and seed, the default tile size and no `pass_spp`.
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
    /// Camera samples finished so far, counting the region's own pixels only (not its halo).
    pub samples_done: u64,
    /// Samples expected in all, for a progress bar; under a time budget an estimate from the
    /// rate so far, which changes as the render advances.
    pub samples_total: u64,
}

/// Summary of a finished render: what was done and what was dropped.
#[derive(Clone, Copy, Debug)]
pub struct RenderStats {
    /// Samples per pixel actually rendered: fewer than asked for when a time limit stopped
    /// the render.
    pub spp: u32,
    /// Wall-clock time of the whole render call.
    pub wall: Duration,
    /// Camera samples that produced a non-finite value (counted as zero).
    pub invalid_samples: u64,
    /// Guide records and light samples rejected for a non-finite value (guided renders).
    pub nonfinite_records: u64,
}

impl RenderStats {
    /// Everything the render dropped for being NaN or infinite: samples and guide records
    /// (the `nonfinite=` of the summary line).
    pub fn nonfinite(&self) -> u64 {
        self.invalid_samples + self.nonfinite_records
    }
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
    /// The primary ray, in world space, through the sample's film position.
    pub ray: Ray,
    /// Index `y * width + x` of the sample's pixel in the whole image (not in the region).
    pub pixel: usize,
    /// The sample's pixel belongs to the region being rendered (not only to its filter
    /// halo): only owned samples may have side effects such as guide records or counters.
    pub owned: bool,
}

/// What [`render_into`] runs for every camera sample: radiance estimates for a batch of
/// samples. `rngs[k]` is sample `k`'s own generator (after the two pixel-offset numbers);
/// an estimate may depend only on its own sample and generator, never on the batch, so
/// that images do not depend on how the work is split. Any
/// `Fn(Ray, &mut Rng, pixel) -> Vec3` is an estimator taking one sample at a time.
pub trait Estimator: Sync {
    /// Writes to `out[k]` the radiance estimate of `samples[k]`, drawing from `rngs[k]` only. All
    /// three slices have the same length.
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
        let run = Batch {
            scene,
            samples,
            rngs,
            out,
        };
        crate::integrator::specialised(scene, run);
    }
}

/// One batch of the path wavefront, for [`crate::integrator::specialised`].
struct Batch<'s, 'b> {
    scene: &'s Scene,
    samples: &'b [CameraSample],
    rngs: &'b mut [Rng],
    out: &'b mut [glam::Vec3],
}

impl crate::integrator::Specialise for Batch<'_, '_> {
    type Output = ();
    fn call<const ENV: bool, const ANALYTIC: bool>(self) {
        let wavefront = PathWavefront::<ENV, ANALYTIC> { scene: self.scene };
        wavefront.estimate(self.samples, self.rngs, self.out)
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
    let region = Region::full(scene.width, scene.height);
    render_region_into(
        scene,
        settings,
        progress,
        first_sample,
        region,
        film,
        estimator,
    )
}

/// A rectangle of pixels `[x0, x1) x [y0, y1)` of the image: a tile.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Region {
    /// First column (inclusive).
    pub x0: u32,
    /// First row (inclusive).
    pub y0: u32,
    /// End column (exclusive).
    pub x1: u32,
    /// End row (exclusive).
    pub y1: u32,
}

impl Region {
    /// The whole `width x height` image.
    pub fn full(width: u32, height: u32) -> Self {
        Self {
            x0: 0,
            y0: 0,
            x1: width,
            y1: height,
        }
    }

    /// Number of columns; 0 if the region is inverted.
    pub fn width(&self) -> u32 {
        self.x1.saturating_sub(self.x0)
    }

    /// Number of rows; 0 if the region is inverted.
    pub fn height(&self) -> u32 {
        self.y1.saturating_sub(self.y0)
    }

    /// Number of pixels, `width * height`.
    pub fn pixels(&self) -> usize {
        self.width() as usize * self.height() as usize
    }

    /// Whether `(x, y)` is inside.
    #[inline]
    pub fn contains(&self, x: u32, y: u32) -> bool {
        x >= self.x0 && x < self.x1 && y >= self.y0 && y < self.y1
    }

    /// Non-empty and inside a `width x height` image.
    pub fn is_valid_in(&self, width: u32, height: u32) -> bool {
        self.x0 < self.x1 && self.y0 < self.y1 && self.x1 <= width && self.y1 <= height
    }

    /// This region grown by `reach` pixels on every side, clipped to the image: the pixels
    /// whose samples a filter of that reach splats into this region (its halo).
    pub fn grown(&self, reach: u32, width: u32, height: u32) -> Self {
        Self {
            x0: self.x0.saturating_sub(reach),
            y0: self.y0.saturating_sub(reach),
            x1: (self.x1 + reach).min(width),
            y1: (self.y1 + reach).min(height),
        }
    }

    /// The tiles of a `width x height` image in row-major order, `tile` pixels square
    /// (smaller at the right and bottom edges).
    pub fn tiles(width: u32, height: u32, tile: u32) -> Vec<Region> {
        let t = tile.max(1);
        let mut out = Vec::new();
        for y0 in (0..height).step_by(t as usize) {
            for x0 in (0..width).step_by(t as usize) {
                out.push(Region {
                    x0,
                    y0,
                    x1: (x0 + t).min(width),
                    y1: (y0 + t).min(height),
                });
            }
        }
        out
    }
}

/// [`render_into`] for the pixels of `region` only, into `film` (`region`-sized: pixel
/// `(x, y)` of the image is `film.pixels[(y - y0) * width + (x - x0)]`).
///
/// A pixel gathers the samples of every pixel within its filter's reach, so the samples of
/// the region's halo ([`Region::grown`]) are rendered too, and splatted in the same order as
/// for the whole image: every pixel of `region` gets exactly the bits a whole-image render
/// gives it. The estimator is told which samples are the region's own
/// ([`CameraSample::owned`]): only those may leave side effects (guide records, counters),
/// so that tiles rendered apart add up to one whole-image render. Invalid samples are
/// counted for owned pixels only.
pub fn render_region_into<E>(
    scene: &Scene,
    settings: &RenderSettings,
    progress: &(dyn Fn(Progress) + Sync),
    first_sample: u64,
    region: Region,
    film: &mut Film,
    estimator: &E,
) -> RenderStats
where
    E: Estimator + ?Sized,
{
    assert!(region.is_valid_in(scene.width, scene.height), "{region:?}");
    assert_eq!((film.width, film.height), (region.width(), region.height()));
    let start = Instant::now();
    let target_spp = match (settings.spp, settings.time_limit) {
        (Some(s), _) => s,
        (None, Some(_)) => u32::MAX,
        (None, None) => scene.sample_count,
    };
    let reach = scene.filter.reach();
    let halo = region.grown(reach as u32, scene.width, scene.height);
    let npix = region.pixels();
    let max_pass = max_pass_spp(scene.width, scene.height);
    let mut ctx = PassCtx::new(scene, settings, progress, first_sample, (region, halo));
    let mut spp_done = 0u32;
    let mut pass = if settings.time_limit.is_some() {
        1
    } else {
        settings.pass_spp.unwrap_or(target_spp)
    };
    while spp_done < target_spp {
        let s0 = spp_done;
        let s1 = s0.saturating_add(pass.clamp(1, max_pass)).min(target_spp);
        let total = match (settings.time_limit, settings.spp) {
            (Some(limit), None) => {
                let rate = (ctx.done.load(Ordering::Relaxed) as f64
                    / start.elapsed().as_secs_f64().max(1e-3))
                .max(1.0);
                (rate * limit.as_secs_f64()) as u64
            }
            _ => npix as u64 * target_spp as u64,
        };
        ctx.sample(s0, s1, total, estimator);
        ctx.splat(s1 - s0, film);
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
        invalid_samples: ctx.invalid.load(Ordering::Relaxed),
        nonfinite_records: 0,
    }
}

/// The most samples per pixel one pass of [`render_region_into`] buffers before it splats
/// them. It depends on the image size only, never on the region: a pixel's additions then
/// come in the same order whichever tile it is rendered in.
pub(crate) fn max_pass_spp(width: u32, height: u32) -> u32 {
    let image_pixels = width as usize * height as usize;
    ((PASS_BUFFER_BYTES / (image_pixels.max(1) * std::mem::size_of::<SampleRec>())) as u32).max(1)
}

/// The sample ranges `s0..s1` in which [`render_region_into`] renders and splats `spp`
/// samples per pixel with `settings` (an spp budget, no time limit).
pub(crate) fn pass_ranges(
    width: u32,
    height: u32,
    settings: &RenderSettings,
    spp: u32,
) -> Vec<(u32, u32)> {
    let pass = settings
        .pass_spp
        .unwrap_or(spp)
        .clamp(1, max_pass_spp(width, height));
    (0..spp)
        .step_by(pass as usize)
        .map(|s0| (s0, s0.saturating_add(pass).min(spp)))
        .collect()
}

/// Phase 1 of [`render_region_into`] alone, without a halo: the radiance of samples
/// `0..settings.spp` of every pixel of `region` (all of them owned), row-major within the
/// region, a pixel's samples in index order. Handed to a [`crate::splat::UnitSplat`] with
/// every other region's, they give the film [`render_region_into`] gives the whole image,
/// bit for bit: a sample's value depends on its own random stream only. A tile's samples are fewer bytes than its pixel sums for a few
/// samples per pixel, and need no halo.
pub fn sample_region<E>(
    scene: &Scene,
    settings: &RenderSettings,
    progress: &(dyn Fn(Progress) + Sync),
    first_sample: u64,
    region: Region,
    estimator: &E,
) -> (Vec<glam::Vec3>, RenderStats)
where
    E: Estimator + ?Sized,
{
    assert!(region.is_valid_in(scene.width, scene.height), "{region:?}");
    let start = Instant::now();
    let spp = settings.spp.unwrap_or(scene.sample_count);
    let npix = region.pixels();
    let mut ctx = PassCtx::new(scene, settings, progress, first_sample, (region, region));
    let n = spp as usize;
    let mut values = vec![glam::Vec3::ZERO; npix * n];
    for (s0, s1) in pass_ranges(scene.width, scene.height, settings, spp) {
        ctx.sample(s0, s1, npix as u64 * spp as u64, estimator);
        let k = (s1 - s0) as usize;
        for (p, recs) in ctx.buffer.chunks_exact(k).enumerate() {
            let out = &mut values[p * n + s0 as usize..p * n + s1 as usize];
            out.iter_mut().zip(recs).for_each(|(o, r)| *o = r.value);
        }
    }
    let stats = RenderStats {
        spp,
        wall: start.elapsed(),
        invalid_samples: ctx.invalid.load(Ordering::Relaxed),
        nonfinite_records: 0,
    };
    (values, stats)
}

/// State of one [`render_region_into`] call: the sample buffer of the halo's pixels and
/// their precomputed filter weights.
struct PassCtx<'a> {
    scene: &'a Scene,
    settings: &'a RenderSettings,
    progress: &'a (dyn Fn(Progress) + Sync),
    first_sample: u64,
    region: Region,
    halo: Region,
    done: AtomicU64,
    invalid: AtomicU64,
    buffer: Vec<SampleRec>,
    weights: Vec<f32>,
}

impl<'a> PassCtx<'a> {
    /// A render call's state for the pixels of `region` from the samples of `halo` (the
    /// region grown by the filter's reach, or the region itself when it only samples).
    fn new(
        scene: &'a Scene,
        settings: &'a RenderSettings,
        progress: &'a (dyn Fn(Progress) + Sync),
        first_sample: u64,
        (region, halo): (Region, Region),
    ) -> Self {
        PassCtx {
            scene,
            settings,
            progress,
            first_sample,
            region,
            halo,
            done: AtomicU64::new(0),
            invalid: AtomicU64::new(0),
            buffer: Vec::new(),
            weights: Vec::new(),
        }
    }

    /// Phase 1: samples `s0..s1` of every halo pixel, in chunks of `tile` pixels.
    fn sample<E: Estimator + ?Sized>(&mut self, s0: u32, s1: u32, total: u64, estimator: &E) {
        let n = (s1 - s0) as usize;
        let tile = self.settings.tile_size.max(1) as usize;
        let (scene, halo, region) = (self.scene, self.halo, self.region);
        let hw = halo.width() as usize;
        let w = scene.width as usize;
        let (seed, first_sample) = (self.settings.seed, self.first_sample);
        let (done, invalid, progress) = (&self.done, &self.invalid, self.progress);
        self.buffer.clear();
        self.buffer.resize(halo.pixels() * n, SampleRec::default());
        self.buffer
            .par_chunks_mut(tile * n)
            .enumerate()
            .for_each_init(ChunkScratch::default, |scratch, (chunk, out)| {
                let first = chunk * tile;
                scratch.samples.clear();
                scratch.rngs.clear();
                for (i, recs) in out.chunks_mut(n).enumerate() {
                    let local = first + i;
                    let x = halo.x0 + (local % hw) as u32;
                    let y = halo.y0 + (local / hw) as u32;
                    let pixel = y as usize * w + x as usize;
                    let owned = region.contains(x, y);
                    for (k, rec) in recs.iter_mut().enumerate() {
                        let index = first_sample + (s0 as usize + k) as u64;
                        let mut rng = Rng::for_sample(seed, pixel as u64, index);
                        rec.offset = rng.next_2d();
                        let ray = scene.camera.ray(Vec2::new(x as f32, y as f32) + rec.offset);
                        scratch.samples.push(CameraSample { ray, pixel, owned });
                        scratch.rngs.push(rng);
                    }
                }
                scratch.values.clear();
                scratch.values.resize(out.len(), glam::Vec3::ZERO);
                estimator.estimate(&scratch.samples, &mut scratch.rngs, &mut scratch.values);
                let mut bad = 0u64;
                let mut owned = 0u64;
                for ((rec, &value), s) in out.iter_mut().zip(&scratch.values).zip(&scratch.samples)
                {
                    owned += s.owned as u64;
                    rec.value = if value.is_finite() {
                        value
                    } else {
                        bad += s.owned as u64;
                        glam::Vec3::ZERO
                    };
                }
                invalid.fetch_add(bad, Ordering::Relaxed);
                let d = done.fetch_add(owned, Ordering::Relaxed) + owned;
                progress(Progress {
                    samples_done: d,
                    samples_total: total.max(d),
                });
            });
    }

    /// Phase 2: splat by gathering. The filter is separable: each sample's weights along x
    /// and y towards the 2 reach + 1 pixel columns and rows it can reach are evaluated once
    /// (`axis_weights`), not once per target pixel (a gaussian's 5x5 footprint evaluated
    /// per pair cost 5x the exponentials; door-ajar path tracing spent about a quarter of
    /// its time here). Same operands as a per-pair evaluation, so the same bits.
    fn splat(&mut self, n: u32, film: &mut Film) {
        let pass = Splat {
            filter: &self.scene.filter,
            size: (self.scene.width, self.scene.height),
            region: self.region,
            halo: self.halo,
            tile: self.settings.tile_size.max(1) as usize,
            threads: crate::splat::Threads::Pool,
            buffer: &self.buffer,
        };
        pass.add_to(n as usize, &mut self.weights, film, self.region);
    }
}
