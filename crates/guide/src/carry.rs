//! Carrying the statistics of one iteration over into the next (`carry_over`).
//!
//! The 2017 paper's refinement throws every building quadtree's statistics away: iteration
//! `k + 1` learns from its own records alone, although iteration `k`'s records estimate the
//! same incident radiance. A record is an unbiased estimate whichever guide sampled it (it is
//! weighted by `1 / p_mix`), so older records are noisier, not wrong. With a carry-over
//! fraction `beta`, each new building quadtree starts from `beta` times the statistics the
//! previous one ended with (its records and, in turn, what it had carried), so the tree built
//! after iteration `k` has learned from all earlier records with weights `beta^j`.
//!
//! The carried statistics are deposited into the *new* structure: a leaf cell that the
//! refinement split shares its sum equally among the new cells below it, one it merged adds
//! into the coarser cell. They are kept apart from the building quadtree (the leaf's
//! `prior`, a quadtree of the building tree's structure) and added in only at the next
//! [`crate::SdTree::refine`], so the building quadtree holds exactly this iteration's records:
//! [`crate::SdTree::take_stats`], [`crate::SdTree::apply_stats`] and
//! [`crate::IterationStats::merge`] stay exact, and a farm merging workers' statistics still
//! gets the bits one machine gets. The spatial split criterion counts this iteration's records
//! only (the carried weight is left out), so the spatial tree refines on the same schedule as
//! without carry-over.
//!
//! Everything is integer arithmetic on the fixed-point sums: `beta` is quantised to
//! [`CARRY_ONE`]ths, and a split cell's sum is divided exactly (remainders to the first
//! quadrants), so carrying is deterministic and independent of threads and workers.

use crate::dtree::DTree;
use std::sync::atomic::AtomicU64;

#[cfg(test)]
mod tests;

/// The unit of the quantised carry-over fraction: `beta` is applied as `q / CARRY_ONE`.
pub const CARRY_ONE: u32 = 256;

/// `beta` in [0, 1] as the integer numerator over [`CARRY_ONE`] (NaN and negatives: 0).
pub fn quantise(beta: f64) -> u32 {
    if beta > 0.0 {
        (beta.min(1.0) * CARRY_ONE as f64).round() as u32
    } else {
        0
    }
}

/// `s * q / CARRY_ONE`, rounded down, without overflowing (`q <= CARRY_ONE`).
#[inline]
pub(crate) fn scale(s: u128, q: u32) -> u128 {
    let (one, q) = (CARRY_ONE as u128, q as u128);
    s / one * q + (s % one) * q / one
}

/// The prior of the new building quadtree `new` (freshly reset, its sums zero): `q /`
/// [`CARRY_ONE`] of every leaf cell of `old` (the built quadtree before the reset) deposited
/// into `new`'s structure, and the same fraction of `old`'s weight W.
pub(crate) fn carry(old: &DTree, new: &DTree, q: u32) -> DTree {
    let mut prior = new.clone();
    prior.clear_stats();
    let overflow = AtomicU64::new(0);
    carry_node(old, 0, &prior, Target::Node(0), q, &overflow);
    prior.weight.set(scale(old.weight.get(), q));
    prior
}

/// Where an old node's region lies in the new structure.
#[derive(Clone, Copy)]
enum Target {
    /// At a node of the new tree (the same region).
    Node(usize),
    /// Inside a leaf cell `(node, quadrant)` of the new tree (the region was merged).
    Cell(usize, usize),
}

/// Deposits the scaled leaf cells below old node `on` into `prior`, walking both trees
/// together: an old leaf cell goes into the new leaf cell holding it, or is shared among the
/// new cells below it.
fn carry_node(old: &DTree, on: usize, prior: &DTree, at: Target, q: u32, ov: &AtomicU64) {
    for q4 in 0..4 {
        let target = match at {
            Target::Node(nn) => match prior.nodes[nn].children[q4] {
                0 => Target::Cell(nn, q4),
                c => Target::Node(c as usize),
            },
            cell => cell,
        };
        match old.nodes[on].children[q4] {
            0 => {
                let amount = scale(old.nodes[on].sums[q4].get(), q);
                if amount != 0 {
                    match target {
                        Target::Cell(n, c) => prior.nodes[n].sums[c].add(amount, ov),
                        Target::Node(n) => spread(prior, n, amount, ov),
                    }
                }
            }
            c => carry_node(old, c as usize, prior, target, q, ov),
        }
    }
}

/// Shares `amount` equally among the four quadrants of node `n` (the remainder one unit each
/// to the first quadrants), recursively down to the leaf cells.
fn spread(t: &DTree, n: usize, amount: u128, overflow: &AtomicU64) {
    let part = amount / 4;
    let rem = amount % 4;
    for q in 0..4 {
        let a = part + u128::from((q as u128) < rem);
        if a == 0 {
            continue;
        }
        match t.nodes[n].children[q] {
            0 => t.nodes[n].sums[q].add(a, overflow),
            c => spread(t, c as usize, a, overflow),
        }
    }
}

/// Whether `prior` holds nothing (a one-node quadtree without sums or weight).
pub(crate) fn is_empty(prior: &DTree) -> bool {
    prior.nodes.len() == 1 && prior.weight.get() == 0 && prior.total_fixed() == 0
}

/// Whether `prior` can be added into `building`: it is empty or has `building`'s structure
/// (a prior is made for the structure it was carried into; see [`carry`]).
pub(crate) fn fits(prior: &DTree, building: &DTree) -> bool {
    is_empty(prior)
        || (prior.nodes.len() == building.nodes.len()
            && prior
                .nodes
                .iter()
                .zip(&building.nodes)
                .all(|(a, b)| a.children == b.children))
}

/// Adds `prior`'s leaf-cell sums and weight into `building` (before it is built). Does
/// nothing when `prior` is empty or does not [`fits`] `building`.
pub(crate) fn add_prior(building: &DTree, prior: &DTree, overflow: &AtomicU64) {
    if is_empty(prior) || !fits(prior, building) {
        return;
    }
    for (p, b) in prior.nodes.iter().zip(&building.nodes) {
        for q in 0..4 {
            if b.children[q] == 0 {
                let s = p.sums[q].get();
                if s != 0 {
                    b.sums[q].add(s, overflow);
                }
            }
        }
    }
    building.weight.add(prior.weight.get(), overflow);
}

/// Splits every sum of `a` between `a` and `b` (two copies of one quadtree, the two halves of
/// a spatial leaf that splits): `b` gets half, rounded down, `a` the rest, so that no unit is
/// lost or made. (The weights W are split by the caller.)
pub(crate) fn halve_sums_into(a: &DTree, b: &DTree) {
    for (na, nb) in a.nodes.iter().zip(&b.nodes) {
        for q in 0..4 {
            let s = na.sums[q].get();
            na.sums[q].set(s - s / 2);
            nb.sums[q].set(s / 2);
        }
    }
}
