//! The path-guiding training driver (doc sections 3 and 5).
//!
//! Iteration k renders `2^k` passes of `spp_per_pass` samples per pixel over
//! the whole image with [`crate::integrator::guided_path`], recording into the
//! SD-tree's building statistics (all but the final iteration); after every
//! pass the learned fractions take their Adam steps, one per record of the pass
//! ([`SdTree::step_fractions`]),
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
//! exact integer arithmetic and fractions step at pass boundaries, so image and
//! tree are bit-identical for any thread count (spp budgets; time budgets
//! depend on the clock by nature).

use std::time::{Duration, Instant};

pub use pathfarm_guide::schedule::Budget;
pub use pathfarm_guide::schedule::GuidingVerdict;
use pathfarm_guide::schedule::{self, IterationLength, IterationOutcome};
pub use pathfarm_guide::SdTree;
use pathfarm_guide::{DirectionalFilter, FractionLoss, FractionMode, GuideConfig, SpatialFilter};
use pathfarm_scene::{
    GuidedBudgetType, GuidedCombination, GuidedDirectionalFilter, GuidedFractionLoss, GuidedNee,
    GuidedParams, GuidedRoulette, GuidedSpatialFilter,
};

use crate::counter::ShardedCounter;
use crate::film::Film;
use crate::geometry::Ray;
use crate::integrator::guided_path::{self, GuideCtx};
use crate::render::{path_estimator, render_into, Progress, RenderSettings};
use crate::rng::Rng;
use crate::scene::Scene;

/// NEE "kickstart" does light sampling while fewer than this many spp have been rendered.
pub const KICKSTART_SPP: u64 = 128;

/// Random streams of the path fallback's unguided passes start at this sample index, apart
/// from the guided passes' (which count up from 0).
const PATH_STREAM: u64 = 1 << 40;

/// Bookkeeping of the path fallback (`path_fallback`): while `enabled`, every training
/// iteration that samples from a built tree is checked against an unguided probe.
struct FallbackState {
    enabled: bool,
    /// Film of the unguided passes (probes, then the fallback's rendering).
    path_film: Film,
    path_seconds: f64,
    /// Rays of the probe passes.
    path_rays: u64,
    /// Samples per pixel in `path_film`, and how many of them are probes.
    path_spp: u64,
    probe_spp: u64,
    /// Seconds of the current iteration's unrecorded first pass.
    guided_pass_seconds: f64,
    /// Efficiency costs of the checked guided iterations, oldest first.
    guided_costs: Vec<f64>,
    /// The training iteration after which the rest of the budget went to path tracing.
    fell_back_after: Option<u32>,
}

impl FallbackState {
    fn new(enabled: bool, width: u32, height: u32) -> Self {
        Self {
            enabled,
            path_film: Film::new(width, height),
            path_seconds: 0.0,
            path_rays: 0,
            path_spp: 0,
            probe_spp: 0,
            guided_pass_seconds: 0.0,
            guided_costs: Vec::new(),
            fell_back_after: None,
        }
    }

    /// Whether an iteration sampling from `tree` is checked (the render loop ends at a
    /// fallback, so `enabled` covers the rest).
    fn checks(&self, tree: &SdTree) -> bool {
        self.enabled && tree.is_built()
    }
}

/// One iteration of a guided render.
#[derive(Clone, Debug)]
pub struct GuidedIteration {
    /// 0-based iteration index.
    pub index: u32,
    /// Samples per pixel rendered in the iteration.
    pub spp: u32,
    /// Spatial nodes and leaves of the tree the iteration sampled from.
    pub nodes: usize,
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
    pub iterations: Vec<GuidedIteration>,
    /// Total samples per pixel (training + final).
    pub spp: u32,
    /// Fraction of the budget spent in training iterations (by spp).
    pub training_fraction: f64,
    /// Approximate heap memory of the final tree.
    pub tree_memory_bytes: usize,
    /// Weights of the iteration films in the final image (inversevar), else 1 for the kept one.
    pub weights: Vec<f64>,
    pub wall: Duration,
    /// Camera samples that produced a non-finite value (counted as zero).
    pub invalid_samples: u64,
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
    let (lo, hi) = scene.accel.bounds();
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
    let first = films[0];
    let mut out = Film::new(first.width, first.height);
    for (f, &wk) in films.iter().zip(weights) {
        if wk == 0.0 {
            continue;
        }
        for (o, p) in out.pixels.iter_mut().zip(&f.pixels) {
            o.count += p.count;
            if p.sum_w <= 0.0 {
                continue;
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
    }
    out
}

/// Renders `scene` with the guided path tracer within `budget`. Returns the final film,
/// the statistics and the tree (as it stands at the end).
pub fn render_guided(
    scene: &Scene,
    params: &GuidedParams,
    budget: Budget,
    settings: &RenderSettings,
    progress: &(dyn Fn(Progress) + Sync),
) -> (Film, GuidedStats, SdTree) {
    render_guided_with(scene, params, budget, settings, progress, &|_| {})
}

/// [`render_guided`], calling `on_iteration` as each iteration ends.
pub fn render_guided_with(
    scene: &Scene,
    params: &GuidedParams,
    budget: Budget,
    settings: &RenderSettings,
    progress: &(dyn Fn(Progress) + Sync),
    on_iteration: &dyn Fn(&GuidedIteration),
) -> (Film, GuidedStats, SdTree) {
    render_guided_with_policy(
        scene,
        params,
        budget,
        settings,
        progress,
        on_iteration,
        &schedule::guiding_verdict,
    )
}

/// [`render_guided_with`] with the path fallback's rule as a parameter (by default
/// [`schedule::guiding_verdict`]), so that tests and experiments can force either outcome. It
/// gets the efficiency costs of the checked guided iterations, path tracing's and the per-sample
/// variance ratio of the latest check (see [`schedule::guiding_verdict`]).
pub fn render_guided_with_policy(
    scene: &Scene,
    params: &GuidedParams,
    budget: Budget,
    settings: &RenderSettings,
    progress: &(dyn Fn(Progress) + Sync),
    on_iteration: &dyn Fn(&GuidedIteration),
    policy: &dyn Fn(&[f64], f64, f64) -> GuidingVerdict,
) -> (Film, GuidedStats, SdTree) {
    let cfg = guide_config(params, scene);
    let (lo, hi) = scene.accel.bounds();
    let mut tree = SdTree::new(lo, hi, cfg);
    let spp_per_pass = params.spp_per_pass.max(1);
    let npix = scene.width as u64 * scene.height as u64;
    let start = Instant::now();
    let pass_settings = RenderSettings {
        spp: Some(spp_per_pass),
        time_limit: None,
        seed: settings.seed,
        tile_size: settings.tile_size,
        pass_spp: None,
    };

    let mut spp_done = 0u64;
    let mut passes_done = 0u32;
    let mut invalid = 0u64;
    let mut iterations: Vec<GuidedIteration> = Vec::new();
    let mut films: Vec<Film> = Vec::new();
    let mut history: Vec<IterationOutcome> = Vec::new();
    let mut prev_secs: Option<f64> = None;
    let mut training_spp = 0u64;
    let mut kept: Option<usize> = None;
    // Films of iterations rendered before the tree was built: unguided, so on a fallback
    // their samples join the path tracer's film.
    let mut unguided: Vec<usize> = Vec::new();
    // Pixel estimates for guided Russian roulette: spp-weighted mean of the finished
    // iterations' films (sum and spp so far), then blurred; empty until an iteration ended.
    let roulette = params.russian_roulette == GuidedRoulette::Guided;
    let mut est_sum: Vec<f64> = Vec::new();
    let mut est_spp = 0u64;
    let mut estimate: Vec<f32> = Vec::new();
    // Path fallback: the unguided probe's film, seconds and rays; the guided iterations'
    // efficiency costs; the iteration after which the rest went to path tracing.
    let mut fallback = FallbackState::new(params.path_fallback, scene.width, scene.height);

    // Progress of a render call that starts after `spp_before` spp of the whole budget.
    let overall_progress = |spp_before: u64| {
        let base = spp_before * npix;
        move |p: Progress| {
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
        }
    };

    // One pass of spp_per_pass samples into `film`.
    let rays_counter = ShardedCounter::new();
    let rays = &rays_counter;
    let splits_counter = ShardedCounter::new();
    let light_splits_counter = ShardedCounter::new();
    let render_pass = |tree: &SdTree,
                       estimate: &[f32],
                       guide: bool,
                       record: bool,
                       split: bool,
                       film: &mut Film,
                       spp_done: u64,
                       stream: u64,
                       invalid: &mut u64| {
        let nee = match params.nee {
            GuidedNee::Never => false,
            GuidedNee::Always => true,
            GuidedNee::Kickstart => spp_done < KICKSTART_SPP,
        };
        let ctx = GuideCtx {
            tree,
            guide,
            nee,
            indirect_only: params.nee == GuidedNee::Always,
            kickstart: params.nee == GuidedNee::Kickstart && nee,
            record,
            ppg_roulette: guide && params.russian_roulette == GuidedRoulette::Ppg,
            guided_rr_depth: params.guided_rr_depth,
            hemisphere: params.guide_hemisphere,
            cosine: params.guide_cosine,
            split: params.splitting && split,
            light_split: params.light_splitting && split,
            splits: Some(&splits_counter),
            light_splits: Some(&light_splits_counter),
            rays: Some(rays),
            pixel_estimate: if guide && roulette && tree.is_built() && !estimate.is_empty() {
                Some(estimate)
            } else {
                None
            },
        };
        let ctx = &ctx;
        let est = |ray: Ray, rng: &mut Rng, pixel: usize| match (
            scene.features.environment,
            scene.features.analytic_shapes,
        ) {
            (false, false) => guided_path::li::<false, false>(scene, ctx, ray, rng, pixel),
            (true, false) => guided_path::li::<true, false>(scene, ctx, ray, rng, pixel),
            (false, true) => guided_path::li::<false, true>(scene, ctx, ray, rng, pixel),
            (true, true) => guided_path::li::<true, true>(scene, ctx, ray, rng, pixel),
        };
        let st = render_into(
            scene,
            &pass_settings,
            &overall_progress(spp_done),
            stream,
            film,
            &est,
        );
        *invalid += st.invalid_samples;
    };

    let mut k = 0u32;
    loop {
        let elapsed = start.elapsed().as_secs_f64();
        let Some(plan) =
            schedule::plan_iteration(k, budget, spp_per_pass, passes_done, elapsed, prev_secs)
        else {
            break;
        };
        let remaining_before = match budget {
            Budget::Spp(s) => (schedule::total_passes(s, spp_per_pass) - passes_done) as f64,
            Budget::Seconds(s) => s - elapsed,
        };
        let record = !plan.is_last;
        let stats_before = tree.stats();
        let t0 = Instant::now();
        let rays_before = rays_counter.total();
        let spp_before = spp_done;
        let mut film = Film::new(scene.width, scene.height);
        let mut passes = 0u32;
        let mut last_pass = 0.0f64;
        let mut until = plan.length;
        let mut stopped = false;
        loop {
            match until {
                IterationLength::Passes(p) if passes >= p => {}
                IterationLength::UntilSeconds(s)
                    if passes > 0 && start.elapsed().as_secs_f64() + 0.5 * last_pass >= s => {}
                _ => {
                    let tp = Instant::now();
                    // The first pass of a training iteration checked by the path fallback is
                    // not recorded: it times what a final, guided pass costs.
                    let probe = passes == 0 && record && fallback.checks(&tree);
                    let rec = record && !stopped && !probe;
                    // Splitting only in passes that sample as the final image does (not in
                    // the fallback's timed check pass: there it judged immature trees by
                    // split paths and made door-ajar fall back).
                    render_pass(
                        &tree,
                        &estimate,
                        true,
                        rec,
                        !rec && !probe,
                        &mut film,
                        spp_done,
                        spp_done,
                        &mut invalid,
                    );
                    if rec {
                        tree.step_fractions();
                    }
                    last_pass = tp.elapsed().as_secs_f64();
                    if probe {
                        fallback.guided_pass_seconds = last_pass;
                    }
                    passes += 1;
                    spp_done += spp_per_pass as u64;
                    continue;
                }
            }
            // The iteration's passes are done. Automatic combination may turn a training
            // iteration into the final one: render the rest of the budget into its film.
            if record && !stopped && params.sample_combination == GuidedCombination::Automatic {
                let cost = match budget {
                    Budget::Spp(_) => passes as f64,
                    Budget::Seconds(_) => t0.elapsed().as_secs_f64(),
                };
                history.push(IterationOutcome {
                    variance: film_variance(&film),
                    cost,
                    remaining_before,
                    spp_before,
                });
                if schedule::automatic_should_stop(&history) {
                    stopped = true;
                    training_spp += spp_done - spp_before;
                    until = match budget {
                        Budget::Spp(s) => IterationLength::Passes(
                            schedule::total_passes(s, spp_per_pass) - passes_done,
                        ),
                        Budget::Seconds(s) => IterationLength::UntilSeconds(s),
                    };
                    continue;
                }
            }
            break;
        }
        passes_done += passes;
        let secs = t0.elapsed().as_secs_f64();
        prev_secs = Some(secs);
        let variance = film_variance(&film);
        let training = record && !stopped;
        if training {
            training_spp += spp_done - spp_before;
        }
        tracing::debug!("guided iteration {k}: {passes} passes, training {training}");
        iterations.push(GuidedIteration {
            index: k,
            spp: (spp_done - spp_before) as u32,
            nodes: stats_before.spatial_nodes,
            leaves: stats_before.leaves,
            variance,
            seconds: secs,
            rays_per_sample: (rays_counter.total() - rays_before) as f64
                / ((spp_done - spp_before) as f64 * npix as f64).max(1.0),
            training,
        });
        on_iteration(iterations.last().unwrap());
        if roulette || fallback.enabled {
            let spp = spp_done - spp_before;
            let means = film.mean_rgb();
            est_sum.resize(means.len(), 0.0);
            for (s, m) in est_sum.iter_mut().zip(&means) {
                *s += spp as f64 * (m[0] as f64 + m[1] as f64 + m[2] as f64) / 3.0;
            }
            est_spp += spp;
            estimate = pixel_estimate(&est_sum, est_spp, scene.width, scene.height);
        }
        if !tree.is_built() {
            // sampled without a guide (iteration 0): plain path tracing
            unguided.push(films.len());
        }
        let checked = training && fallback.checks(&tree);
        films.push(film);
        if !training {
            kept = Some(films.len() - 1);
            break;
        }
        if checked {
            // One unguided pass into the probe film, then compare per-sample efficiencies.
            let r0 = rays_counter.total();
            let tp = Instant::now();
            render_pass(
                &tree,
                &estimate,
                false,
                false,
                false,
                &mut fallback.path_film,
                spp_done + fallback.path_spp,
                PATH_STREAM + fallback.path_spp,
                &mut invalid,
            );
            fallback.path_seconds += tp.elapsed().as_secs_f64();
            fallback.path_rays += rays_counter.total() - r0;
            fallback.path_spp += spp_per_pass as u64;
            fallback.probe_spp += spp_per_pass as u64;
            passes_done += 1;
            let it = iterations.last().unwrap();
            let guided_variance = film_relative_variance(films.last().unwrap(), &estimate);
            let guided_cost = match budget {
                // per-sample variance x seconds per spp of an unrecorded pass
                Budget::Seconds(_) => {
                    guided_variance * it.spp as f64 * fallback.guided_pass_seconds
                        / spp_per_pass as f64
                }
                // deterministic: per-sample variance x rays per spp
                Budget::Spp(_) => guided_variance * it.rays_per_sample * it.spp as f64,
            };
            let path_variance = film_relative_variance(&fallback.path_film, &estimate);
            let path_cost = match budget {
                Budget::Seconds(_) => path_variance * fallback.path_seconds,
                Budget::Spp(_) => path_variance * fallback.path_rays as f64 / npix.max(1) as f64,
            };
            // per-sample relative variances: film variances of the mean times their spp
            let variance_ratio =
                guided_variance * it.spp as f64 / (path_variance * fallback.path_spp as f64);
            fallback.guided_costs.push(guided_cost);
            let verdict = policy(&fallback.guided_costs, path_cost, variance_ratio);
            tracing::info!(
                "guiding check after iteration {k}: guided cost {guided_cost:.4e}, path cost \
                 {path_cost:.4e} (ratio {:.3}, per-sample variance ratio {variance_ratio:.3}): \
                 {verdict:?}",
                guided_cost / path_cost
            );
            match verdict {
                GuidingVerdict::Keep => fallback.enabled = false,
                GuidingVerdict::FallBack => {
                    fallback.fell_back_after = Some(k);
                    break;
                }
                GuidingVerdict::Undecided => {}
            }
        }
        tree.refine(k);
        if let Some(rho) = tree.raised_d_tree_threshold() {
            tracing::warn!(
                "iteration {k}: the quadtrees would exceed the guide's memory cap \
                 (max_memory_mb, or Limits::max_guide_memory_bytes): refined with \
                 d_tree_threshold {rho:.3e} instead of {:.3e}",
                params.d_tree_threshold
            );
        }
        k += 1;
    }

    // Path fallback: the rest of the budget is plain path tracing into the probe's film,
    // which becomes the final iteration.
    if let Some(after) = fallback.fell_back_after {
        let t0 = Instant::now();
        let path_est = path_estimator(scene);
        // The path integrator itself (no guide bookkeeping), into the probes' film: both are
        // unbiased path-tracing estimates (same NEE, MIS and roulette), on the next sample
        // streams. One render call for the rest of the budget, so that the renderer sizes
        // its passes (about a second each) instead of paying per-pass costs every spp.
        let rest = match budget {
            Budget::Spp(s) => {
                let passes = schedule::total_passes(s, spp_per_pass).saturating_sub(passes_done);
                RenderSettings {
                    spp: Some(passes * spp_per_pass),
                    time_limit: None,
                    ..pass_settings.clone()
                }
            }
            Budget::Seconds(s) => RenderSettings {
                spp: None,
                time_limit: Some(Duration::from_secs_f64(
                    (s - start.elapsed().as_secs_f64()).max(0.0),
                )),
                ..pass_settings.clone()
            },
        };
        if rest.spp != Some(0) && rest.time_limit != Some(Duration::ZERO) {
            let st = render_into(
                scene,
                &rest,
                &overall_progress(spp_done + fallback.path_spp),
                PATH_STREAM + fallback.path_spp,
                &mut fallback.path_film,
                &path_est,
            );
            invalid += st.invalid_samples;
            fallback.path_spp += st.spp as u64;
        }
        let path_spp = fallback.path_spp;
        spp_done += path_spp;
        // The unguided iterations' samples are path tracing's too (the same estimator up to
        // its random streams): they join the film instead of being weighed apart (a 1-spp
        // iteration has no variance estimate, so inverse-variance weighting drops it).
        for &i in &unguided {
            fallback.path_film.merge(&films[i]);
            films[i] = Film::new(scene.width, scene.height);
        }
        iterations.push(GuidedIteration {
            index: after + 1,
            spp: path_spp as u32,
            nodes: 0,
            leaves: 0,
            variance: film_variance(&fallback.path_film),
            seconds: t0.elapsed().as_secs_f64(),
            // measured on the probe passes (the path integrator does not count rays)
            rays_per_sample: fallback.path_rays as f64
                / (fallback.probe_spp as f64 * npix as f64).max(1.0),
            training: false,
        });
        on_iteration(iterations.last().unwrap());
        films.push(std::mem::replace(
            &mut fallback.path_film,
            Film::new(scene.width, scene.height),
        ));
        kept = Some(films.len() - 1);
    } else {
        // probe passes count toward the total spp
        spp_done += fallback.path_spp;
    }

    let n = films.len();
    let weights = match params.sample_combination {
        // An iteration of one sample per pixel has no usable variance estimate (with a box
        // filter it is exactly 0, which would claim a perfect image): it gets weight 0.
        GuidedCombination::InverseVar if n > 0 => schedule::inverse_variance_weights(
            &iterations
                .iter()
                .enumerate()
                .map(|(k, i)| {
                    let merged = fallback.fell_back_after.is_some() && unguided.contains(&k);
                    if i.spp < 2 || merged {
                        f64::INFINITY
                    } else {
                        i.variance
                    }
                })
                .collect::<Vec<_>>(),
        ),
        _ => {
            let mut w = vec![0.0; n];
            if n > 0 {
                w[kept.unwrap_or(n - 1)] = 1.0;
            }
            w
        }
    };
    let film = if n == 0 {
        Film::new(scene.width, scene.height)
    } else if params.sample_combination == GuidedCombination::InverseVar {
        let refs: Vec<&Film> = films.iter().collect();
        combine_films(&refs, &weights)
    } else {
        films.swap_remove(kept.unwrap_or(n - 1))
    };
    let stats = GuidedStats {
        iterations,
        spp: spp_done as u32,
        training_fraction: if spp_done > 0 {
            training_spp as f64 / spp_done as f64
        } else {
            0.0
        },
        tree_memory_bytes: tree.stats().memory_bytes,
        weights,
        wall: start.elapsed(),
        invalid_samples: invalid,
        path_fallback_after: fallback.fell_back_after,
        split_paths: splits_counter.total(),
        extra_light_samples: light_splits_counter.total(),
    };
    (film, stats, tree)
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
