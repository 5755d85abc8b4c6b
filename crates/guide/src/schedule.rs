//! Training schedule, the weights that combine iteration images, and the path fallback's
//! rule (pure functions, doc section 5).
//!
//! Iteration k renders `2^k` passes of `spp_per_pass` samples per pixel. The last iteration
//! absorbs the remainder when the iteration after it could not get at least twice its passes
//! (so the final iteration always has at least about half the budget).

#[cfg(test)]
mod tests;

/// How iteration images become the final image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum SampleCombination {
    /// The final image is the last iteration only.
    Discard,
    /// Like `Discard`, but stop learning early when the extrapolated final variance gets worse
    /// (after 256 spp) or the next iteration cannot be afforded, and render the rest of the
    /// budget into the current iteration ([`automatic_should_stop`]).
    Automatic,
    /// Keep every iteration; combine the last (up to) 4 with inverse-variance weights (2019).
    #[default]
    InverseVar,
}

/// Render budget.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Budget {
    /// Samples per pixel (rounded up to whole passes).
    Spp(u32),
    /// Wall-clock seconds.
    Seconds(f64),
}

/// Total passes for an spp budget: `ceil(spp / spp_per_pass)`.
pub fn total_passes(spp: u32, spp_per_pass: u32) -> u32 {
    let s = spp_per_pass.max(1);
    spp.div_ceil(s)
}

/// Passes of iteration `k` given the passes still to render: `min(remaining, 2^k)`, extended to
/// all `remaining` if what would be left is less than twice that. Returns `(passes, is_last)`.
pub fn iteration_passes(k: u32, remaining_passes: u32) -> (u32, bool) {
    let base = if k >= 31 { u32::MAX } else { 1u32 << k };
    let mut p = remaining_passes.min(base);
    if (remaining_passes - p) < p.saturating_mul(2) {
        p = remaining_passes;
    }
    (p, p >= remaining_passes)
}

/// The whole spp-budget plan: passes per iteration, summing to `total_passes(spp, spp_per_pass)`.
pub fn plan_spp(spp: u32, spp_per_pass: u32) -> Vec<u32> {
    let mut remaining = total_passes(spp, spp_per_pass);
    let mut out = Vec::new();
    let mut k = 0;
    while remaining > 0 {
        let (p, _) = iteration_passes(k, remaining);
        out.push(p);
        remaining -= p;
        k += 1;
    }
    out
}

/// Time budget: whether iteration `k`, predicted to take `predicted_seconds` (e.g. twice the
/// previous iteration), should be the last one and run until the budget ends: true when the
/// time left after it would be less than twice its duration.
///
/// The same rule serves inverse-variance combination, where training samples are kept:
/// training longer did not pay (`docs/decisions/time-budget-last-iteration.md`).
pub fn time_iteration_is_last(remaining_seconds: f64, predicted_seconds: f64) -> bool {
    remaining_seconds - predicted_seconds < 2.0 * predicted_seconds
}

/// Length of an iteration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum IterationLength {
    /// Render this many passes.
    Passes(u32),
    /// Render passes (in chunks of the doubled size) until this total elapsed time (the budget).
    UntilSeconds(f64),
}

/// What the next iteration should do.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IterationPlan {
    /// How long it runs.
    pub length: IterationLength,
    /// Whether it is the final iteration (renders the image that is kept, records nothing).
    pub is_last: bool,
}

/// Plans iteration `k` for either budget kind, or `None` when the budget is used up.
///
/// * `Budget::Spp`: [`iteration_passes`] over `total_passes - passes_done`.
/// * `Budget::Seconds`: `2^k` passes, predicted to take twice `previous_iteration_seconds`;
///   if the time left after that would be less than twice the prediction
///   ([`time_iteration_is_last`]) the iteration is the last and runs until the budget.
///   Without a previous duration (k = 0) the iteration is not last.
pub fn plan_iteration(
    k: u32,
    budget: Budget,
    spp_per_pass: u32,
    passes_done: u32,
    elapsed_seconds: f64,
    previous_iteration_seconds: Option<f64>,
) -> Option<IterationPlan> {
    match budget {
        Budget::Spp(spp) => {
            let total = total_passes(spp, spp_per_pass);
            let remaining = total.saturating_sub(passes_done);
            if remaining == 0 {
                return None;
            }
            let (p, is_last) = iteration_passes(k, remaining);
            Some(IterationPlan {
                length: IterationLength::Passes(p),
                is_last,
            })
        }
        Budget::Seconds(s) => {
            let remaining = s - elapsed_seconds;
            if !(remaining > 0.0) {
                return None;
            }
            let passes = if k >= 31 { u32::MAX } else { 1u32 << k };
            match previous_iteration_seconds {
                Some(prev) if time_iteration_is_last(remaining, 2.0 * prev) => {
                    Some(IterationPlan {
                        length: IterationLength::UntilSeconds(s),
                        is_last: true,
                    })
                }
                _ => Some(IterationPlan {
                    length: IterationLength::Passes(passes),
                    is_last: false,
                }),
            }
        }
    }
}

/// Extrapolated variance of the final image if the rest of the budget were rendered with the
/// distribution of the iteration just finished: `V_k * cost_k / remaining`, where `cost_k` is
/// the iteration's cost (passes or seconds) and `remaining` the budget left *before* it,
/// in the same unit (as \[G\] computes it).
pub fn extrapolated_final_variance(variance: f64, cost: f64, remaining_before: f64) -> f64 {
    if remaining_before > 0.0 {
        variance * cost / remaining_before
    } else {
        f64::INFINITY
    }
}

/// One finished iteration, for [`automatic_should_stop`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IterationOutcome {
    /// Estimated variance of the iteration's image (the renderer's estimate, e.g. the mean
    /// over pixels of the variance of the pixel's mean).
    pub variance: f64,
    /// Cost of the iteration (passes or seconds).
    pub cost: f64,
    /// Budget left before the iteration (same unit).
    pub remaining_before: f64,
    /// Samples per pixel rendered before this iteration started.
    pub spp_before: u64,
}

/// `Automatic` combination: after iteration `history.last()`, whether to stop learning and
/// spend the rest of the budget on the current distribution. True when budget is left and
/// either the remainder is smaller than the iteration just done (the next cannot be afforded),
/// or more than 256 spp were rendered before it and its extrapolated final variance is worse
/// than the previous iteration's.
pub fn automatic_should_stop(history: &[IterationOutcome]) -> bool {
    let Some(cur) = history.last() else {
        return false;
    };
    let remaining_after = cur.remaining_before - cur.cost;
    if !(remaining_after > 0.0) {
        return false;
    }
    if remaining_after < cur.cost {
        return true;
    }
    let now = extrapolated_final_variance(cur.variance, cur.cost, cur.remaining_before);
    let last = if history.len() >= 2 {
        let p = &history[history.len() - 2];
        extrapolated_final_variance(p.variance, p.cost, p.remaining_before)
    } else {
        f64::INFINITY
    };
    cur.spp_before > 256 && now > last
}

/// Index of the iteration at which `Automatic` stops on a sequence of outcomes, if any.
pub fn automatic_stop_index(history: &[IterationOutcome]) -> Option<usize> {
    (1..=history.len())
        .find(|&n| automatic_should_stop(&history[..n]))
        .map(|n| n - 1)
}

/// What the path fallback concludes after a checked training iteration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GuidingVerdict {
    /// Guiding pays: keep training and stop checking.
    Keep,
    /// Guiding does not pay: render the rest of the budget as plain path tracing.
    FallBack,
    /// Not clear yet: check again after the next iteration.
    Undecided,
}

/// Guided sampling is kept once its efficiency cost is at most this fraction of path tracing's.
pub const GUIDING_KEEP_RATIO: f64 = 0.8;
/// Path tracing takes over once guided sampling's efficiency cost is at least this multiple of
/// path tracing's at two checks in a row (the guide still improves while it trains, so it
/// gets the benefit of the doubt). The measurements behind this and the other thresholds:
/// `docs/decisions/path-fallback.md`.
pub const GUIDING_FALLBACK_RATIO: f64 = 1.25;
/// Path tracing takes over at the first check already when guided sampling's efficiency cost
/// is at least this multiple of path tracing's: a loss this clear is not made up by a tree
/// trained on more samples, and on a short budget the second check's iteration alone costs a
/// tenth of the budget. The first check judges a tree trained on one spp, so it separates
/// scenes poorly and the threshold sits between those guiding loses (cornell-box) and those
/// it wins later (door-ajar), nearer the latter: falling back there costs far more than a
/// second check costs the former.
pub const GUIDING_FALLBACK_FIRST_RATIO: f64 = 2.4;
/// Path tracing also takes over at the first check when a guided sample is this much noisier
/// than a path sample (per-sample relative variance, guided over path) and guided sampling is
/// less efficient by at least [`GUIDING_FALLBACK_RATIO`]. Unlike the efficiency cost, the
/// variance ratio does not depend on the machine's speed (for a given seed it is the same
/// everywhere), and it separates the scenes far better: a scene that guiding will win already
/// has less noise per sample with the 1-spp tree.
pub const GUIDING_FALLBACK_FIRST_VARIANCE_RATIO: f64 = 1.2;
/// After this many checked iterations the verdict is final either way.
pub const GUIDING_LAST_DECISION: usize = 4;

/// The path fallback's rule. `guided_costs`: efficiency costs (per-sample variance x cost per
/// sample, in any unit shared with `path_cost`) of the checked guided iterations, oldest
/// first; `path_cost`: the same for unguided path tracing (its latest estimate);
/// `variance_ratio`: the latest guided iteration's per-sample relative variance over path
/// tracing's. Keep guiding once it is clearly more efficient ([`GUIDING_KEEP_RATIO`]); fall
/// back once it has been clearly less efficient at the last two checks
/// ([`GUIDING_FALLBACK_RATIO`], the earlier one against the path cost of now), or at the first
/// check when it is far less efficient ([`GUIDING_FALLBACK_FIRST_RATIO`]) or clearly less
/// efficient with noisier samples ([`GUIDING_FALLBACK_FIRST_VARIANCE_RATIO`]); at the
/// [`GUIDING_LAST_DECISION`]-th check keep guiding unless it is clearly less efficient.
pub fn guiding_verdict(
    guided_costs: &[f64],
    path_cost: f64,
    variance_ratio: f64,
) -> GuidingVerdict {
    let n = guided_costs.len();
    if n == 0 {
        return GuidingVerdict::Undecided;
    }
    if !(path_cost > 0.0 && path_cost.is_finite()) || guided_costs.iter().any(|c| !(*c >= 0.0)) {
        // No usable comparison (black image, NaN): guiding is the configured method.
        return if n >= GUIDING_LAST_DECISION {
            GuidingVerdict::Keep
        } else {
            GuidingVerdict::Undecided
        };
    }
    let ratio = |c: f64| c / path_cost;
    let last = ratio(guided_costs[n - 1]);
    if last <= GUIDING_KEEP_RATIO {
        GuidingVerdict::Keep
    } else if (n == 1
        && (last >= GUIDING_FALLBACK_FIRST_RATIO
            || (last >= GUIDING_FALLBACK_RATIO
                && variance_ratio >= GUIDING_FALLBACK_FIRST_VARIANCE_RATIO)))
        || (n >= 2
            && last >= GUIDING_FALLBACK_RATIO
            && ratio(guided_costs[n - 2]) >= GUIDING_FALLBACK_RATIO)
    {
        GuidingVerdict::FallBack
    } else if n >= GUIDING_LAST_DECISION {
        if last < GUIDING_FALLBACK_RATIO {
            GuidingVerdict::Keep
        } else {
            GuidingVerdict::FallBack
        }
    } else {
        GuidingVerdict::Undecided
    }
}

/// Inverse-variance weights for iterations with the given variances: the last (up to) 4 get
/// `(1 / V_i) / sum_j (1 / V_j)`, earlier ones 0. Non-finite or negative variances get weight
/// 0; if some of the last 4 have variance exactly 0 they share the weight equally. If none is
/// usable the last iteration gets weight 1.
pub fn inverse_variance_weights(variances: &[f64]) -> Vec<f64> {
    let n = variances.len();
    let mut w = vec![0.0; n];
    if n == 0 {
        return w;
    }
    let begin = n.saturating_sub(4);
    let zeros: Vec<usize> = (begin..n).filter(|&i| variances[i] == 0.0).collect();
    if !zeros.is_empty() {
        for &i in &zeros {
            w[i] = 1.0 / zeros.len() as f64;
        }
        return w;
    }
    let mut total = 0.0;
    for i in begin..n {
        let v = variances[i];
        if v > 0.0 && v.is_finite() {
            w[i] = 1.0 / v;
            total += w[i];
        }
    }
    if total > 0.0 {
        for x in &mut w {
            *x /= total;
        }
    } else {
        w[n - 1] = 1.0;
    }
    w
}
