//! The path-guiding training driver (doc sections 3 and 5).
//!
//! Iteration k renders `2^k` passes of `spp_per_pass` samples per pixel over
//! the whole image with [`crate::integrator::guided_path`], recording into the
//! SD-tree's building statistics (all but the final iteration); after every
//! pass the learned fractions take their Adam steps, one pass late (the
//! session pipelines passes for the farm: [`crate::session`];
//! [`SdTree::step_fractions`]),
//! after every training iteration the tree is refined ([`SdTree::refine`]).
//! The budget (spp or seconds) covers training and the final iteration
//! ([`pathfarm_guide::schedule`]). The final image:
//! * `discard`: the last iteration's film;
//! * `automatic`: training stops when the extrapolated final variance gets
//!   worse (or the next iteration cannot be afforded); the rest of the budget
//!   is rendered, without recording, into that iteration's film;
//! * `inversevar`: the inverse-variance weighted mean of the last (up to) 4
//!   iteration films.
//!
//! Determinism: each pass is one [`render_into`] call whose sample `s` uses
//! the stream of global sample index `spp_done + s`; recording into the tree is
//! exact integer arithmetic and fractions step at pass ends, so image and
//! tree are bit-identical for any thread count (spp budgets; time budgets
//! depend on the clock by nature).

use std::time::{Duration, Instant};

pub use pathfarm_guide::schedule::Budget;
pub use pathfarm_guide::schedule::GuidingVerdict;
pub use pathfarm_guide::SdTree;
use pathfarm_guide::{DirectionalFilter, FractionLoss, FractionMode, GuideConfig, SpatialFilter};
use pathfarm_scene::{
    GuidedBudgetType, GuidedDirectionalFilter, GuidedFractionLoss, GuidedParams,
    GuidedSpatialFilter,
};

use crate::film::{Film, PixelStats};
use crate::pass::{render_unit, UnitInputs};
use crate::render::{Progress, Region, RenderSettings};
use crate::scene::Scene;

pub use crate::pass::{KICKSTART_SPP, PATH_STREAM};
pub use crate::session::{FallbackPolicy, Next, Records, RecordsError, Session, Splatting};

/// One iteration of a guided render.
#[derive(Clone, Debug)]
pub struct GuidedIteration {
    /// 0-based iteration index.
    pub index: u32,
    /// Samples per pixel rendered in the iteration.
    pub spp: u32,
    /// Spatial nodes and leaves of the tree the iteration sampled from.
    pub nodes: usize,
    /// Spatial leaves of that tree (the part of `nodes` that hold a directional quadtree).
    pub leaves: usize,
    /// Image variance of the iteration's film (mean over pixels and channels of the
    /// per-pixel variance of the mean).
    pub variance: f64,
    /// Wall time of the iteration.
    pub seconds: f64,
    /// Rays traced per camera sample (camera, continuation and shadow rays): a measure of
    /// the iteration's cost that does not depend on the machine's load.
    pub rays_per_sample: f64,
    /// Training iteration (recorded into the tree) rather than final.
    pub training: bool,
}

/// Statistics of a guided render.
#[derive(Clone, Debug)]
pub struct GuidedStats {
    /// Every iteration rendered, in order (training and final).
    pub iterations: Vec<GuidedIteration>,
    /// Total samples per pixel (training + final).
    pub spp: u32,
    /// Fraction of the budget spent in training iterations (by spp).
    pub training_fraction: f64,
    /// Approximate heap memory of the final tree.
    pub tree_memory_bytes: usize,
    /// Weights of the iteration films in the final image (inversevar), else 1 for the kept one.
    pub weights: Vec<f64>,
    /// Wall-clock time from the job's start to its end, training included.
    pub wall: Duration,
    /// Camera samples that produced a non-finite value (counted as zero).
    pub invalid_samples: u64,
    /// Guide records and light samples rejected for a non-finite value.
    pub nonfinite_records: u64,
    /// Path fallback: the training iteration after which the rest of the budget was rendered
    /// as plain path tracing (guiding did not pay), if it happened.
    pub path_fallback_after: Option<u32>,
    /// Extra paths made by splitting (`splitting`), over all passes.
    pub split_paths: u64,
    /// Extra light samples taken by `light_splitting`, over all passes.
    pub extra_light_samples: u64,
}

/// The guide configuration of `params`.
pub fn guide_config(params: &GuidedParams, scene: &Scene) -> GuideConfig {
    let mut cfg = GuideConfig {
        s_tree_threshold: params.s_tree_threshold,
        d_tree_threshold: params.d_tree_threshold,
        spp_per_pass: params.spp_per_pass.max(1),
        spatial_filter: match params.spatial_filter {
            GuidedSpatialFilter::Nearest => SpatialFilter::Nearest,
            GuidedSpatialFilter::Stochastic => SpatialFilter::Stochastic,
            GuidedSpatialFilter::Box => SpatialFilter::Box,
        },
        directional_filter: match params.directional_filter {
            GuidedDirectionalFilter::Nearest => DirectionalFilter::Nearest,
            GuidedDirectionalFilter::Box => DirectionalFilter::Box,
        },
        bsdf_sampling_fraction: match params.bsdf_sampling_fraction_loss {
            GuidedFractionLoss::None => FractionMode::Fixed(params.bsdf_sampling_fraction),
            GuidedFractionLoss::Kl => FractionMode::Learned {
                loss: FractionLoss::Kl,
            },
            GuidedFractionLoss::Var => FractionMode::Learned {
                loss: FractionLoss::Var,
            },
        },
        max_nodes: params.max_nodes.map(|n| n as usize),
        carry_over: params.carry_over,
        ..GuideConfig::default()
    };
    // The tree's memory cap: the scene's `max_memory_mb`, never more than the limits allow.
    let limit = scene.limits.max_guide_memory_bytes as f64;
    let bytes = params
        .max_memory_mb
        .map_or(limit, |mb| (mb * 1048576.0).min(limit));
    let (lo, hi) = scene.world().accel.bounds();
    let fresh = SdTree::new(lo, hi, cfg.clone()).stats();
    if params.max_memory_mb.is_some() {
        // Approximate: a spatial leaf costs about twice a fresh tree's single leaf (its
        // quadtrees grow past the uniform depth-4 start), and nodes ~ 2 leaves. (Without
        // `max_memory_mb` the spatial tree is bounded by the records: a split needs the
        // threshold's weight; `max_nodes` is part of a saved tree, so it stays unset.)
        let per_leaf = (2 * fresh.memory_bytes).max(1) as f64;
        let nodes = ((2.0 * bytes / per_leaf) as usize).max(1);
        cfg.max_nodes = Some(cfg.max_nodes.map_or(nodes, |n| n.min(nodes)));
    }
    // Exact: the quadtrees' nodes (building, sampling and carried prior: three per building
    // node) may take half of it.
    let quad_nodes = (fresh.sampling_dtree_nodes + fresh.building_dtree_nodes).max(1);
    let per_node = (fresh.memory_bytes as f64 / quad_nodes as f64) * 1.5;
    cfg.max_dtree_nodes = Some(((0.5 * bytes / per_node) as usize).max(1));
    cfg
}

/// Checks a guided render's budget before anything is rendered: a pass renders
/// `spp_per_pass` samples per pixel, so an spp budget smaller than one pass would be
/// silently exceeded.
pub fn check_budget(params: &GuidedParams, budget: Budget) -> Result<(), String> {
    match budget {
        Budget::Spp(spp) if params.spp_per_pass > spp => Err(format!(
            "spp_per_pass={} is more than the budget of {spp} spp (a pass renders \
             spp_per_pass samples per pixel): lower spp_per_pass or raise the budget",
            params.spp_per_pass
        )),
        _ => Ok(()),
    }
}

/// The budget of `params` (`budget` in `budget_type` units; by default the scene's
/// sample_count spp, or 300 seconds).
pub fn params_budget(params: &GuidedParams, scene: &Scene) -> Budget {
    match params.budget_type {
        GuidedBudgetType::Spp => Budget::Spp(
            params
                .budget
                .map_or(scene.sample_count, |b| (b.ceil() as u32).max(1)),
        ),
        GuidedBudgetType::Seconds => Budget::Seconds(params.budget.unwrap_or(300.0)),
    }
}

/// Image variance: mean over pixels and channels of the per-pixel variance of the mean.
pub fn film_variance(film: &Film) -> f64 {
    let v = film.variance_rgb();
    if v.is_empty() {
        return 0.0;
    }
    v.iter()
        .map(|p| p.iter().map(|&x| x as f64).sum::<f64>())
        .sum::<f64>()
        / (3 * v.len()) as f64
}

/// Relative variance of a film, as relMSE weighs errors: the mean over pixels of the
/// per-pixel variance of the mean (mean over channels) divided by `e^2 + 0.01`, where `e` is
/// the pixel's value estimate ([`pixel_estimate`]; the offset is the usual relMSE one). The
/// path fallback compares guided and unguided sampling with it. 0 without an estimate.
pub fn film_relative_variance(film: &Film, estimate: &[f32]) -> f64 {
    if estimate.len() != film.pixels.len() || estimate.is_empty() {
        return 0.0;
    }
    film.pixels
        .iter()
        .zip(estimate)
        .map(|(p, &e)| {
            let v = p.variance_of_mean();
            (v[0] as f64 + v[1] as f64 + v[2] as f64) / 3.0 / (e as f64 * e as f64 + 1e-2)
        })
        .sum::<f64>()
        / estimate.len() as f64
}

/// Weighted combination of films: per pixel, film k's sample weights are scaled by
/// `weights[k] / sum_w_k`, so the mean is `sum_k weights[k] mean_k` and the variance
/// sums of the merged samples give the combined variance.
pub fn combine_films(films: &[&Film], weights: &[f64]) -> Film {
    use rayon::prelude::*;
    let first = films[0];
    let mut out = Film::new(first.width, first.height);
    // Rows over the pool, each pixel taking the films in order: the same sums however the
    // rows are shared out.
    let row = first.width.max(1) as usize;
    (out.pixels.par_chunks_mut(row).enumerate()).for_each(|(y, line)| {
        for (f, &wk) in films.iter().zip(weights) {
            if wk == 0.0 {
                continue;
            }
            let src = &f.pixels[y * row..y * row + line.len()];
            for (o, p) in line.iter_mut().zip(src) {
                combine_pixel(o, p, wk);
            }
        }
    });
    out
}

/// The pixel values ([`PixelStats::mean`]) of [`combine_films`]'s film, the same bits,
/// without the film: a frame of values (12 bytes a pixel) instead of a frame of sums (96).
pub fn combined_means(films: &[&Film], weights: &[f64]) -> Vec<[f32; 3]> {
    let pixels = films[0].pixels.len();
    (0..pixels)
        .map(|i| {
            let mut o = PixelStats::default();
            for (f, &wk) in films.iter().zip(weights) {
                if wk != 0.0 {
                    combine_pixel(&mut o, &f.pixels[i], wk);
                }
            }
            o.mean()
        })
        .collect()
}

/// Adds pixel `p` of a film of weight `wk` to the combined pixel `o`.
#[inline]
fn combine_pixel(o: &mut PixelStats, p: &PixelStats, wk: f64) {
    o.count += p.count;
    if p.sum_w <= 0.0 {
        return;
    }
    let l = wk / p.sum_w;
    let l2 = l * l;
    o.sum_w += l * p.sum_w;
    o.sum_w2 += l2 * p.sum_w2;
    for c in 0..3 {
        o.sum_wl[c] += l * p.sum_wl[c];
        o.sum_w2l[c] += l2 * p.sum_w2l[c];
        o.sum_w2l2[c] += l2 * p.sum_w2l2[c];
    }
}

/// What a guided render reports as it goes and how its path fallback decides, beyond what
/// it renders. The default reports nothing and applies [`FallbackPolicy::Rule`].
#[derive(Clone, Copy)]
pub struct GuidedOptions<'a> {
    /// Called with the samples done so far (and the estimated total) as the render goes.
    pub progress: &'a (dyn Fn(Progress) + Sync),
    /// Called as each iteration ends.
    pub on_iteration: &'a dyn Fn(&GuidedIteration),
    /// The path fallback's rule; tests and experiments force either outcome with it.
    pub policy: FallbackPolicy,
}

impl Default for GuidedOptions<'_> {
    fn default() -> Self {
        GuidedOptions {
            progress: &|_| {},
            on_iteration: &|_| {},
            policy: FallbackPolicy::Rule,
        }
    }
}

/// Renders `scene` with the guided path tracer within `budget`. Returns the final film,
/// the statistics and the tree (as it stands at the end).
///
/// The one-process driver of a [`Session`]: every unit is rendered over the whole image as
/// one tile, recording straight into the session's tree.
pub fn render_guided(
    scene: &Scene,
    params: &GuidedParams,
    budget: Budget,
    settings: &RenderSettings,
    options: GuidedOptions,
) -> (Film, GuidedStats, SdTree) {
    let GuidedOptions {
        progress,
        on_iteration,
        policy,
    } = options;
    // The budget's clock starts with the call (building the tree is part of the render).
    let start = Instant::now();
    let (lo, hi) = scene.world().accel.bounds();
    let tree = SdTree::new(lo, hi, guide_config(params, scene));
    let (w, h) = (scene.width, scene.height);
    let whole = Region::full(w, h);
    let splatting = Splatting {
        filter: scene.filter,
        seed: settings.seed,
    };
    let mut session = Session::new(params, budget, tree, (w, h), splatting, vec![whole], policy);
    let npix = whole.pixels() as u64;
    let mut reported = 0;
    while let Next::Render(spec) = session.next(start.elapsed().as_secs_f64()) {
        let inputs = UnitInputs {
            scene,
            params,
            tree: session.tree(),
            estimate: session.pass_estimate(),
            seed: settings.seed,
            tile_size: settings.tile_size,
        };
        let base = session.spp_done() * npix;
        let unit_progress = |p: Progress| {
            let d = base + p.samples_done;
            let total = match budget {
                Budget::Spp(s) => s as u64 * npix,
                Budget::Seconds(s) => {
                    (d as f64 * s / start.elapsed().as_secs_f64().max(1e-3)) as u64
                }
            };
            progress(Progress {
                samples_done: d,
                samples_total: total.max(d),
            })
        };
        let out = render_unit(&inputs, &spec, whole, &unit_progress);
        let now = start.elapsed().as_secs_f64();
        session
            .add_tile(spec.unit, 0, &out, None, now)
            .expect("the one tile of the unit in flight");
        for it in &session.iterations()[reported..] {
            on_iteration(it);
        }
        reported = session.iterations().len();
    }
    for it in &session.iterations()[reported..] {
        on_iteration(it);
    }
    session.finish()
}

/// The per-pixel value estimate used by guided Russian roulette: the spp-weighted mean of the
/// iterations so far (`sum / spp`), averaged over each pixel's 3x3 neighbourhood to tame the
/// noise of early iterations, and floored at 1e-3 of the image mean (and 1e-6) so that dark
/// pixels do not divide by zero.
pub fn pixel_estimate(sum: &[f64], spp: u64, width: u32, height: u32) -> Vec<f32> {
    let (w, h) = (width as usize, height as usize);
    if spp == 0 || sum.len() != w * h || sum.is_empty() {
        return Vec::new();
    }
    let inv = 1.0 / spp as f64;
    let mean = sum.iter().sum::<f64>() * inv / sum.len() as f64;
    let floor = (1e-3 * mean).max(1e-6);
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (mut s, mut n) = (0.0f64, 0u32);
            for yy in y.saturating_sub(1)..=(y + 1).min(h - 1) {
                for xx in x.saturating_sub(1)..=(x + 1).min(w - 1) {
                    let v = sum[yy * w + xx] * inv;
                    if v.is_finite() {
                        s += v;
                        n += 1;
                    }
                }
            }
            let v = if n > 0 { s / n as f64 } else { 0.0 };
            out[y * w + x] = v.max(floor) as f32;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn pixel_estimate_is_the_3x3_mean_per_spp_with_a_floor() {
        // Deterministic arithmetic (no significance level). 3x2 image, sums over 4 spp.
        let sum = [4.0, 8.0, 0.0, 0.0, 0.0, 12.0];
        let e = pixel_estimate(&sum, 4, 3, 2);
        assert_eq!(e.len(), 6);
        // corner (0, 0): neighbours (0,0) (1,0) (0,1) (1,1) -> (1 + 2 + 0 + 0) / 4
        assert!((e[0] - 0.75).abs() < 1e-6, "{e:?}");
        // (1, 0): all six pixels -> (1 + 2 + 0 + 0 + 0 + 3) / 6
        assert!((e[1] - 1.0).abs() < 1e-6, "{e:?}");
        // (2, 0): (2 + 0 + 0 + 3) / 4
        assert!((e[2] - 1.25).abs() < 1e-6, "{e:?}");
        // a black image still gets a positive floor
        let z = pixel_estimate(&[0.0; 6], 4, 3, 2);
        assert!(z.iter().all(|&v| v > 0.0 && v <= 1e-6), "{z:?}");
        // a dark pixel among bright ones: floored at 1e-3 of the image mean
        let mut big = vec![0.0; 25 * 25];
        big[0] = 625e6;
        let b = pixel_estimate(&big, 1, 25, 25);
        let mean = 625e6 / 625.0;
        assert!(
            (b[24 * 25 + 24] as f64 - 1e-3 * mean).abs() < 1e-3,
            "{}",
            b[624]
        );
        assert!(pixel_estimate(&sum, 0, 3, 2).is_empty());
        assert!(pixel_estimate(&sum, 4, 2, 2).is_empty(), "size mismatch");
    }

    #[test]
    fn combined_films_are_the_weighted_mean_of_the_films() {
        // Exact arithmetic check (no statistics): per pixel the combination is
        // sum_k w_k mean_k, whatever each film's filter-weight sum.
        let mut a = Film::new(2, 1);
        let mut b = Film::new(2, 1);
        a.pixels[0].add(1.0, Vec3::splat(1.0));
        a.pixels[0].add(1.0, Vec3::splat(3.0));
        a.pixels[1].add(0.5, Vec3::new(4.0, 2.0, 0.0));
        b.pixels[0].add(0.25, Vec3::splat(6.0));
        b.pixels[1].add(2.0, Vec3::new(0.0, 2.0, 8.0));
        b.pixels[1].add(2.0, Vec3::new(0.0, 2.0, 8.0));
        let c = combine_films(&[&a, &b], &[0.75, 0.25]);
        let m = c.mean_rgb();
        for (got, want) in m[0].iter().zip([0.75 * 2.0 + 0.25 * 6.0; 3]) {
            assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        }
        for (got, want) in m[1].iter().zip([3.0, 2.0, 2.0]) {
            assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        }
        assert_eq!(c.pixels[0].count, 0);
        // A weight of 1 on one film reproduces its mean.
        assert_eq!(
            combine_films(&[&a, &b], &[0.0, 1.0]).mean_rgb(),
            b.mean_rgb()
        );
    }
}
