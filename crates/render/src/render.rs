//! The render loop: tiles in parallel, passes of samples, a sample budget or
//! a time budget.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use glam::Vec2;
use rayon::prelude::*;

use crate::film::{Film, PixelStats};
use crate::integrator::path;
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
    /// Tile edge in pixels (default 16). Does not change the image.
    pub tile_size: u32,
    /// Samples per pass when rendering to a sample budget (default: all in
    /// one pass). Does not change the image.
    pub pass_spp: Option<u32>,
}

impl RenderSettings {
    pub fn new(spp: Option<u32>, time_limit: Option<Duration>, seed: u64) -> Self {
        Self { spp, time_limit, seed, tile_size: DEFAULT_TILE, pass_spp: None }
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

/// Renders the scene into a film.
pub fn render(scene: &Scene, settings: &RenderSettings, progress: &(dyn Fn(Progress) + Sync)) -> (Film, RenderStats) {
    let (w, h) = (scene.width, scene.height);
    let tile = settings.tile_size.max(1);
    let start = Instant::now();
    let target_spp = match (settings.spp, settings.time_limit) {
        (Some(s), _) => s,
        (None, Some(_)) => u32::MAX,
        (None, None) => scene.sample_count,
    };
    let tiles: Vec<(u32, u32)> = (0..h.div_ceil(tile)).flat_map(|ty| (0..w.div_ceil(tile)).map(move |tx| (tx * tile, ty * tile))).collect();
    let mut film = Film::new(w, h);
    let done = AtomicU64::new(0);
    let invalid = AtomicU64::new(0);
    let pixels = (w as u64) * (h as u64);
    let mut spp_done = 0u32;
    // Pass sizes: a time budget renders passes sized to about a second each.
    let mut pass = if settings.time_limit.is_some() { 1 } else { settings.pass_spp.unwrap_or(target_spp) };
    while spp_done < target_spp {
        let s0 = spp_done;
        let s1 = s0.saturating_add(pass.max(1)).min(target_spp);
        let total = if settings.time_limit.is_some() && settings.spp.is_none() {
            let rate = (done.load(Ordering::Relaxed) as f64 / start.elapsed().as_secs_f64().max(1e-3)).max(1.0);
            (rate * settings.time_limit.unwrap().as_secs_f64()) as u64
        } else {
            pixels * target_spp as u64
        };
        let results: Vec<Vec<PixelStats>> = tiles
            .par_iter()
            .map(|&(x0, y0)| {
                let x1 = (x0 + tile).min(w);
                let y1 = (y0 + tile).min(h);
                let mut out = Vec::with_capacity(((x1 - x0) * (y1 - y0)) as usize);
                let mut bad = 0u64;
                for y in y0..y1 {
                    for x in x0..x1 {
                        let pixel = (y * w + x) as usize;
                        let mut stats = film.pixels[pixel];
                        for s in s0..s1 {
                            let v = sample(scene, settings.seed, x, y, pixel as u64, s as u64);
                            if v.is_finite() {
                                stats.add(v);
                            } else {
                                bad += 1;
                                stats.add(glam::Vec3::ZERO);
                            }
                        }
                        out.push(stats);
                    }
                }
                invalid.fetch_add(bad, Ordering::Relaxed);
                let n = done.fetch_add(out.len() as u64 * (s1 - s0) as u64, Ordering::Relaxed) + out.len() as u64 * (s1 - s0) as u64;
                progress(Progress { samples_done: n, samples_total: total.max(n) });
                out
            })
            .collect();
        for (&(x0, y0), out) in tiles.iter().zip(results) {
            let x1 = (x0 + tile).min(w);
            let mut it = out.into_iter();
            for y in y0..(y0 + tile).min(h) {
                for x in x0..x1 {
                    film.pixels[(y * w + x) as usize] = it.next().unwrap_or_default();
                }
            }
        }
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
    let stats = RenderStats { spp: spp_done, wall: start.elapsed(), invalid_samples: invalid.load(Ordering::Relaxed) };
    (film, stats)
}

/// One camera sample of pixel (x, y): its own random stream, a film position
/// drawn from the reconstruction filter, and the integrator's estimate.
#[inline]
fn sample(scene: &Scene, seed: u64, x: u32, y: u32, pixel: u64, index: u64) -> glam::Vec3 {
    let mut rng = Rng::for_sample(seed, pixel, index);
    let centre = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
    let size = Vec2::new(scene.width as f32, scene.height as f32);
    // Like Mitsuba's film (no border sampling), a pixel only receives samples
    // from inside the image: the filter is truncated at the image edges.
    let mut pos = centre + scene.filter.sample(rng.next_2d());
    let mut tries = 0;
    while (pos.cmplt(Vec2::ZERO).any() || pos.cmpge(size).any()) && tries < 16 {
        pos = centre + scene.filter.sample(rng.next_2d());
        tries += 1;
    }
    let ray = scene.camera.ray(pos.clamp(Vec2::ZERO, size - Vec2::splat(1e-3)));
    match (scene.features.environment, scene.features.analytic_shapes) {
        (false, false) => path::li::<false, false>(scene, ray, &mut rng),
        (true, false) => path::li::<true, false>(scene, ray, &mut rng),
        (false, true) => path::li::<false, true>(scene, ray, &mut rng),
        (true, true) => path::li::<true, true>(scene, ray, &mut rng),
    }
}
