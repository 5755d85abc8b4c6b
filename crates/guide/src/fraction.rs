//! Learned BSDF-sampling fraction (2019 improvement): one logit theta per spatial leaf,
//! `alpha = sigmoid(theta)`, trained with Adam on exactly accumulated gradients.
//!
//! Per record (not delta, product `F > 0`), with `q = alpha p_bsdf + (1 - alpha) p_guide`:
//! `dL/dalpha = -(F / q)^p * (p_bsdf - p_guide) / p_sample`, p = 1 (KL) or 2 (variance).
//!
//! \[G\] takes one Adam step per record, in whatever order the threads deliver them. Here the
//! steps happen at defined points ([`crate::SdTree::step_fractions`], e.g. every pass end),
//! and they are as many as \[G\] would take: the batch keeps the gradient as a *function* of
//! alpha, so every step reads the gradient at the alpha it is taken from.
//!
//! * A record adds `w * dL/dalpha` evaluated at each alpha of the fixed [`GRID`] (split into
//!   positive and negative fixed-point accumulators; one record's terms all have the sign of
//!   `p_guide - p_bsdf`) and `w` to the leaf's batch. The gradient is unbiased at every grid
//!   alpha whatever alpha the direction was sampled with (`p_sample` is the pdf actually used),
//!   so the batch holds every record since the sampling tree last changed: it is cleared when
//!   the tree is refined ([`GradAccum::clear`]), not when a step is taken.
//! * [`FractionState::step`] takes one Adam step per `min_batch_weight` of weight recorded
//!   since the last step (at most [`MAX_STEPS_PER_CALL`]), each on
//!   `g(alpha) * alpha (1 - alpha) + l2 * theta`, where `g(alpha)` interpolates the batch mean
//!   linearly between grid points (constant beyond the ends). Theta is clamped to [-20, 20].
//!
//! Nothing depends on record order, so the result is bit-identical for any thread count and
//! for statistics merged from many workers. Stepping once per pass (the first version) gave
//! each leaf about as many steps as passes, and at Adam's rate of 0.01 per step alpha never
//! left 0.46-0.54: the learned fraction did not learn.

use crate::config::{AdamConfig, FractionLoss};
use crate::stats::{add_counted, from_fixed, to_fixed, Acc128};
use std::sync::atomic::AtomicU64;

#[cfg(test)]
mod tests;

/// Logistic function.
#[inline]
pub fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// Bound on |theta|.
pub const THETA_LIMIT: f64 = 20.0;

/// Adam state of one leaf's logit.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct FractionState {
    /// The logit theta (alpha = sigmoid(theta)); 0 initially.
    pub theta: f64,
    /// Adam first moment.
    pub m: f64,
    /// Adam second moment.
    pub v: f64,
    /// Number of Adam steps taken.
    pub t: u64,
}

/// Alphas at which every record's gradient is evaluated. With linear interpolation between
/// them the learned optimum of the unit tests' 1-D toy is off by 0.004 (KL) and 0.008 (var).
pub const GRID: [f64; GRID_LEN] = [0.03, 0.1, 0.25, 0.4, 0.6, 0.75, 0.9, 0.97];
/// Number of grid points.
pub const GRID_LEN: usize = 8;
/// Bound on the Adam steps one [`FractionState::step`] takes.
pub const MAX_STEPS_PER_CALL: u64 = 256;

/// Exact per-leaf batch of fraction gradients: fixed point (see [`crate::stats`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct GradAccum {
    /// Per grid alpha, the sum of positive `w * dL/dalpha` contributions.
    pub pos: [Acc128; GRID_LEN],
    /// Per grid alpha, the sum of magnitudes of negative contributions.
    pub neg: [Acc128; GRID_LEN],
    /// Sum of weights of contributing records.
    pub weight: Acc128,
    /// The part of `weight` already turned into Adam steps (local bookkeeping: statistics
    /// that travel between machines do not carry it).
    pub stepped: Acc128,
}

impl GradAccum {
    /// Whether nothing has been accumulated.
    pub fn is_zero(&self) -> bool {
        self.weight.get() == 0
            && self.pos.iter().all(|a| a.get() == 0)
            && self.neg.iter().all(|a| a.get() == 0)
    }

    /// Zeroes the batch.
    pub fn clear(&self) {
        for a in self.pos.iter().chain(self.neg.iter()) {
            a.set(0);
        }
        self.weight.set(0);
        self.stepped.set(0);
    }

    /// Adds another batch (integer addition, counted overflow).
    pub fn add_from(
        &self,
        pos: &[u128; GRID_LEN],
        neg: &[u128; GRID_LEN],
        weight: u128,
        overflow: &mut u64,
    ) {
        for k in 0..GRID_LEN {
            self.pos[k].set(add_counted(self.pos[k].get(), pos[k], overflow));
            self.neg[k].set(add_counted(self.neg[k].get(), neg[k], overflow));
        }
        self.weight
            .set(add_counted(self.weight.get(), weight, overflow));
    }
}

/// A record's `(F, p_bsdf, p_guide, p_sample)` in f64 if they can give a gradient: `F > 0`,
/// both pdfs non-negative, `p_sample > 0`, all finite.
fn record_inputs(
    product: f32,
    pdf_bsdf: f32,
    pdf_guide: f32,
    pdf_sample: f32,
) -> Option<(f64, f64, f64, f64)> {
    let (f, pb, pg, ps) = (
        product as f64,
        pdf_bsdf as f64,
        pdf_guide as f64,
        pdf_sample as f64,
    );
    let ok = f > 0.0 && f.is_finite() && pb >= 0.0 && pb.is_finite() && pg >= 0.0;
    (ok && pg.is_finite() && ps > 0.0 && ps.is_finite()).then_some((f, pb, pg, ps))
}

/// The per-record derivative of the loss with respect to alpha (before the sigmoid chain rule),
/// or `None` when the record does not contribute (non-finite inputs, `F <= 0`, `q <= 0`,
/// `p_sample <= 0`).
pub fn dloss_dalpha(
    alpha: f64,
    loss: FractionLoss,
    product: f32,
    pdf_bsdf: f32,
    pdf_guide: f32,
    pdf_sample: f32,
) -> Option<f64> {
    let (f, pb, pg, ps) = record_inputs(product, pdf_bsdf, pdf_guide, pdf_sample)?;
    let q = alpha * pb + (1.0 - alpha) * pg;
    if !(q > 0.0) {
        return None;
    }
    let r = f / q;
    let rp = match loss.exponent() {
        1 => r,
        _ => r * r,
    };
    let g = -rp * (pb - pg) / ps;
    g.is_finite().then_some(g)
}

impl GradAccum {
    /// Accumulates one record: `w * dL/dalpha` at every grid alpha (each clamped to `+-clamp`)
    /// and its weight `w`. Records that do not contribute (invalid inputs, or both pdfs zero:
    /// [`dloss_dalpha`] is `None` at every alpha) add nothing, not even weight.
    #[allow(clippy::too_many_arguments)]
    pub fn accumulate(
        &self,
        w: f64,
        loss: FractionLoss,
        product: f32,
        pdf_bsdf: f32,
        pdf_guide: f32,
        pdf_sample: f32,
        clamp: f64,
        overflow: &AtomicU64,
    ) {
        let Some((f, pb, pg, ps)) = record_inputs(product, pdf_bsdf, pdf_guide, pdf_sample) else {
            return;
        };
        if !(pb + pg > 0.0) {
            return;
        }
        // dloss_dalpha at every grid alpha, with what does not depend on alpha taken out:
        // -(F / q)^p d / p_sample, d = p_bsdf - p_guide, q = p_guide + alpha d. All terms
        // share the sign of -d.
        let d = pb - pg;
        let mut bad = false;
        if d != 0.0 {
            let target = if d < 0.0 { &self.pos } else { &self.neg };
            let a = w * d.abs() / ps;
            for (k, &alpha) in GRID.iter().enumerate() {
                let q = pg + alpha * d;
                if !(q > 0.0) {
                    continue;
                }
                let r = f / q;
                let wg = match loss {
                    FractionLoss::Kl => a * r,
                    FractionLoss::Var => a * r * r,
                };
                if !wg.is_finite() {
                    continue;
                }
                let (x, o) = to_fixed(wg.min(clamp));
                bad |= o;
                target[k].add(x, overflow);
            }
        }
        let (qw, o) = to_fixed(w);
        if bad || o {
            overflow.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        self.weight.add(qw, overflow);
    }

    /// Mean gradient `(pos - neg) / weight` at grid point `k`, `None` if the weight is zero.
    pub fn mean_at_grid(&self, k: usize) -> Option<f64> {
        let w = self.weight.get();
        if w == 0 {
            return None;
        }
        let (p, n) = (self.pos[k].get(), self.neg[k].get());
        let num = if p >= n {
            from_fixed(p - n)
        } else {
            -from_fixed(n - p)
        };
        Some(num / from_fixed(w))
    }

    /// [`GradAccum::mean_at_grid`] at every grid point, `None` if the weight is zero.
    pub fn grid_means(&self) -> Option<[f64; GRID_LEN]> {
        (self.weight.get() != 0)
            .then(|| std::array::from_fn(|k| self.mean_at_grid(k).unwrap_or(0.0)))
    }

    /// The batch's mean `dL/dalpha` at `alpha`: linear between grid points, the end values
    /// beyond them. `None` if the weight is zero.
    pub fn mean(&self, alpha: f64) -> Option<f64> {
        self.grid_means().map(|m| interpolate(&m, alpha))
    }
}

/// Linear interpolation of values `m` given at [`GRID`], constant beyond its ends.
pub fn interpolate(m: &[f64; GRID_LEN], alpha: f64) -> f64 {
    if !(alpha > GRID[0]) {
        return m[0];
    }
    for k in 1..GRID_LEN {
        if alpha <= GRID[k] {
            let t = (alpha - GRID[k - 1]) / (GRID[k] - GRID[k - 1]);
            return (1.0 - t) * m[k - 1] + t * m[k];
        }
    }
    m[GRID_LEN - 1]
}

impl FractionState {
    /// Current (unclamped) alpha.
    #[inline]
    pub fn alpha(&self) -> f64 {
        sigmoid(self.theta)
    }

    /// One Adam step with gradient `g` with respect to theta; clamps theta to [-20, 20].
    pub fn adam_step(&mut self, g: f64, c: &AdamConfig) {
        if !g.is_finite() {
            return;
        }
        let t = (self.t + 1).min(i32::MAX as u64) as i32;
        self.adam_update(g, c, c.beta1.powi(t), c.beta2.powi(t));
    }

    /// The Adam update for a finite `g`, given `beta1^t` and `beta2^t` of this step's `t`.
    fn adam_update(&mut self, g: f64, c: &AdamConfig, beta1_t: f64, beta2_t: f64) {
        self.t += 1;
        self.m = c.beta1 * self.m + (1.0 - c.beta1) * g;
        self.v = c.beta2 * self.v + (1.0 - c.beta2) * g * g;
        let (mh, vh) = (self.m / (1.0 - beta1_t), self.v / (1.0 - beta2_t));
        self.theta -= c.learning_rate * mh / (vh.sqrt() + c.epsilon);
        self.theta = self.theta.clamp(-THETA_LIMIT, THETA_LIMIT);
    }

    /// Takes one Adam step per `c.min_batch_weight` of weight recorded into `batch` since
    /// the last call (at most [`MAX_STEPS_PER_CALL`]; none unless that weight exceeds
    /// `c.min_batch_weight`), each on `mean(alpha) * alpha (1 - alpha) + l2 * theta` at the
    /// current alpha. The batch is kept (see the module doc). Returns whether it stepped.
    pub fn step(&mut self, batch: &GradAccum, c: &AdamConfig) -> bool {
        let (w, done) = (batch.weight.get(), batch.stepped.get());
        let fresh = from_fixed(w.saturating_sub(done));
        if !(fresh > c.min_batch_weight) {
            return false;
        }
        let Some(m) = batch.grid_means() else {
            return false;
        };
        let n = ((fresh / c.min_batch_weight.max(1e-9)) as u64).clamp(1, MAX_STEPS_PER_CALL);
        // The bias-correction powers are carried from step to step (no powi per step).
        let t = self.t.min(i32::MAX as u64) as i32;
        let (mut p1, mut p2) = (c.beta1.powi(t), c.beta2.powi(t));
        for _ in 0..n {
            let a = self.alpha();
            let g = interpolate(&m, a) * a * (1.0 - a) + c.l2 * self.theta;
            if !g.is_finite() {
                break;
            }
            p1 *= c.beta1;
            p2 *= c.beta2;
            self.adam_update(g, c, p1, p2);
        }
        batch.stepped.set(w);
        true
    }
}
