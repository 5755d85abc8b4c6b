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
    // Old leaf cells with their quadrant paths from the root, depth first.
    let mut stack: Vec<(u32, Vec<u8>)> = vec![(0, Vec::new())];
    while let Some((n, path)) = stack.pop() {
        let node = &old.nodes[n as usize];
        for q4 in 0..4u8 {
            let mut p = path.clone();
            p.push(q4);
            match node.children[q4 as usize] {
                0 => {
                    let amount = scale(node.sums[q4 as usize].get(), q);
                    if amount != 0 {
                        deposit_path(&prior, &p, amount, &overflow);
                    }
                }
                c => stack.push((c, p)),
            }
        }
    }
    prior.weight.set(scale(old.weight.get(), q));
    prior
}

/// Adds `amount` to the cell of `t` at quadrant path `path`: into the leaf cell that contains
/// it (the path's cell or a coarser one), or shared equally among the leaf cells below it.
fn deposit_path(t: &DTree, path: &[u8], amount: u128, overflow: &AtomicU64) {
    let mut n = 0usize;
    for (i, &q) in path.iter().enumerate() {
        match t.nodes[n].children[q as usize] {
            0 => {
                t.nodes[n].sums[q as usize].add(amount, overflow);
                return;
            }
            c if i + 1 == path.len() => {
                spread(t, c as usize, amount, overflow);
                return;
            }
            c => n = c as usize,
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

/// Adds `prior`'s leaf-cell sums and weight into `building` (before it is built). Does
/// nothing when `prior` is empty or its structure is not `building`'s (a prior is made for
/// the structure it was carried into; see [`carry`]).
pub(crate) fn add_prior(building: &DTree, prior: &DTree, overflow: &AtomicU64) {
    if prior.weight.get() == 0 && prior.total_fixed() == 0 {
        return;
    }
    if prior.nodes.len() != building.nodes.len()
        || prior
            .nodes
            .iter()
            .zip(&building.nodes)
            .any(|(a, b)| a.children != b.children)
    {
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
