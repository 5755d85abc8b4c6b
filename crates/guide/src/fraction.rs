//! Learned BSDF-sampling fraction (2019 improvement): one logit theta per spatial leaf,
//! `alpha = sigmoid(theta)`, trained with Adam on exactly accumulated gradients.
//!
//! Per record (not delta, product `F > 0`), with `q = alpha p_bsdf + (1 - alpha) p_guide` at
//! the current (unclamped) alpha:
//! `dL/dalpha = -(F / q)^p * (p_bsdf - p_guide) / p_sample`, p = 1 (KL) or 2 (variance).
//! The record adds `w * dL/dalpha` (split into positive and negative fixed-point accumulators)
//! and `w` to the leaf's batch. [`FractionState::step`] (called from
//! [`crate::SdTree::step_fractions`]) turns the batch into
//! `g = mean(dL/dalpha) * alpha (1 - alpha) + l2 * theta` and takes one Adam step; theta is
//! clamped to [-20, 20]. Theta does not change while records are taken, so the result is
//! independent of record order.

use crate::config::{AdamConfig, FractionLoss};
use crate::stats::{add_counted, from_fixed, to_fixed, Acc128};
use std::sync::atomic::AtomicU64;

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

/// Exact per-leaf batch of fraction gradients: fixed point (see [`crate::stats`]).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct GradAccum {
    /// Sum of positive `w * dL/dalpha` contributions.
    pub pos: Acc128,
    /// Sum of magnitudes of negative contributions.
    pub neg: Acc128,
    /// Sum of weights of contributing records.
    pub weight: Acc128,
}

impl GradAccum {
    /// Whether nothing has been accumulated.
    pub fn is_zero(&self) -> bool {
        self.pos.get() == 0 && self.neg.get() == 0 && self.weight.get() == 0
    }

    /// Zeroes the batch.
    pub fn clear(&self) {
        self.pos.set(0);
        self.neg.set(0);
        self.weight.set(0);
    }

    /// Adds another batch (integer addition, counted overflow).
    pub fn add_from(&self, pos: u128, neg: u128, weight: u128, overflow: &mut u64) {
        self.pos.set(add_counted(self.pos.get(), pos, overflow));
        self.neg.set(add_counted(self.neg.get(), neg, overflow));
        self.weight
            .set(add_counted(self.weight.get(), weight, overflow));
    }
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
    let (f, pb, pg, ps) = (
        product as f64,
        pdf_bsdf as f64,
        pdf_guide as f64,
        pdf_sample as f64,
    );
    if !(f > 0.0 && f.is_finite() && pb >= 0.0 && pb.is_finite() && pg >= 0.0 && pg.is_finite())
        || !(ps > 0.0 && ps.is_finite())
    {
        return None;
    }
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
    /// Accumulates one record's `w * dL/dalpha` (clamped to `+-clamp`) and its weight `w`.
    pub fn accumulate(&self, w: f64, g: f64, clamp: f64, overflow: &AtomicU64) {
        let wg = (w * g).clamp(-clamp, clamp);
        let (q, o1) = to_fixed(wg.abs());
        let (qw, o2) = to_fixed(w);
        if o1 || o2 {
            overflow.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        if wg > 0.0 {
            self.pos.add(q, overflow);
        } else if wg < 0.0 {
            self.neg.add(q, overflow);
        }
        self.weight.add(qw, overflow);
    }

    /// Mean gradient `(pos - neg) / weight` of the batch, `None` if the weight is zero.
    pub fn mean(&self) -> Option<f64> {
        let w = self.weight.get();
        if w == 0 {
            return None;
        }
        let (p, n) = (self.pos.get(), self.neg.get());
        let num = if p >= n {
            from_fixed(p - n)
        } else {
            -from_fixed(n - p)
        };
        Some(num / from_fixed(w))
    }
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
        self.t += 1;
        self.m = c.beta1 * self.m + (1.0 - c.beta1) * g;
        self.v = c.beta2 * self.v + (1.0 - c.beta2) * g * g;
        let mh = self.m / (1.0 - c.beta1.powi(self.t.min(i32::MAX as u64) as i32));
        let vh = self.v / (1.0 - c.beta2.powi(self.t.min(i32::MAX as u64) as i32));
        self.theta -= c.learning_rate * mh / (vh.sqrt() + c.epsilon);
        self.theta = self.theta.clamp(-THETA_LIMIT, THETA_LIMIT);
    }

    /// Consumes `batch` if its weight exceeds `c.min_batch_weight`: one Adam step on
    /// `mean(dL/dalpha) * alpha (1 - alpha) + l2 * theta`. Returns whether a step was taken.
    pub fn step(&mut self, batch: &GradAccum, c: &AdamConfig) -> bool {
        if !(from_fixed(batch.weight.get()) > c.min_batch_weight) {
            return false;
        }
        let Some(mean) = batch.mean() else {
            return false;
        };
        let a = self.alpha();
        let g = mean * a * (1.0 - a) + c.l2 * self.theta;
        self.adam_step(g, c);
        batch.clear();
        true
    }
}
