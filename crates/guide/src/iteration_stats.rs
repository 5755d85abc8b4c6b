//! One iteration's statistics as domain data: the sparse per-leaf sums a tree records, tied to
//! the structure they were taken on, and their exact merge (how worker results combine). Their
//! byte encoding is the serialization layer's business, not this module's.

use crate::fraction::GRID_LEN;
use crate::stats::add_counted;

#[cfg(test)]
mod tests;

/// Statistics of one spatial leaf for one iteration (fixed-point integers, see [`crate::stats`]).
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct LeafStats {
    /// Leaf index ([`crate::LeafHandle`]).
    pub leaf: u32,
    /// Building statistical weight W.
    pub weight: u128,
    /// Positive fraction-gradient sums, one per alpha of [`crate::fraction::GRID`].
    pub grad_pos: [u128; GRID_LEN],
    /// Negative fraction-gradient magnitude sums, one per alpha of [`crate::fraction::GRID`].
    pub grad_neg: [u128; GRID_LEN],
    /// Fraction-gradient weight sum.
    pub grad_weight: u128,
    /// Light-sample sums `[sum, sum of squares, count]` ([`crate::light::LightStats`]).
    pub light: [u128; 3],
    /// Touched building quadtree nodes `(node index, 4 quadrant sums)`, ascending by index.
    pub nodes: Vec<(u32, [u128; 4])>,
}

/// One iteration's statistics: sparse (only touched leaves and nodes), exactly mergeable.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct IterationStats {
    /// [`SdTree::structure_hash`](crate::SdTree::structure_hash) of the tree the statistics
    /// were taken on.
    pub structure_hash: u64,
    /// Overflow events counted while recording these statistics.
    pub overflow_events: u64,
    /// Touched leaves, ascending by index.
    pub leaves: Vec<LeafStats>,
}

/// Errors of merging or applying statistics.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum StatsError {
    /// The statistics were taken on a tree with a different structure.
    #[error("statistics refer to a different tree structure")]
    StructureMismatch,
    /// A leaf or node index does not exist in the tree.
    #[error("statistics index out of range")]
    IndexOutOfRange,
}

impl IterationStats {
    /// Adds `other` into `self` by exact integer addition. Merging the statistics of disjoint
    /// record sets gives, bit for bit, the statistics of recording them all in one tree.
    /// Fails if the two were taken on differently structured trees.
    pub fn merge(&mut self, other: &IterationStats) -> Result<(), StatsError> {
        if self.structure_hash != other.structure_hash {
            return Err(StatsError::StructureMismatch);
        }
        let mut of = 0u64;
        let a = std::mem::take(&mut self.leaves);
        let mut out = Vec::with_capacity(a.len().max(other.leaves.len()));
        let (mut i, mut j) = (0, 0);
        while i < a.len() || j < other.leaves.len() {
            let take_a =
                j >= other.leaves.len() || (i < a.len() && a[i].leaf < other.leaves[j].leaf);
            let take_b =
                i >= a.len() || (j < other.leaves.len() && other.leaves[j].leaf < a[i].leaf);
            if take_a {
                out.push(a[i].clone());
                i += 1;
            } else if take_b {
                out.push(other.leaves[j].clone());
                j += 1;
            } else {
                let (x, y) = (&a[i], &other.leaves[j]);
                out.push(LeafStats {
                    leaf: x.leaf,
                    weight: add_counted(x.weight, y.weight, &mut of),
                    grad_pos: std::array::from_fn(|k| {
                        add_counted(x.grad_pos[k], y.grad_pos[k], &mut of)
                    }),
                    grad_neg: std::array::from_fn(|k| {
                        add_counted(x.grad_neg[k], y.grad_neg[k], &mut of)
                    }),
                    grad_weight: add_counted(x.grad_weight, y.grad_weight, &mut of),
                    light: std::array::from_fn(|k| add_counted(x.light[k], y.light[k], &mut of)),
                    nodes: merge_nodes(&x.nodes, &y.nodes, &mut of),
                });
                i += 1;
                j += 1;
            }
        }
        self.leaves = out;
        self.overflow_events = self.overflow_events + other.overflow_events + of;
        Ok(())
    }

    /// Splits the statistics into the fraction gradients and the rest (W, light-sample sums,
    /// quadtree nodes, overflow events): what a pass end's Adam steps need, and what only
    /// refinement does. Merged again, the two are `self`.
    pub fn split_gradients(self) -> (IterationStats, IterationStats) {
        let empty = |overflow_events| IterationStats {
            structure_hash: self.structure_hash,
            overflow_events,
            leaves: Vec::new(),
        };
        let (mut grads, mut rest) = (empty(0), empty(self.overflow_events));
        for l in self.leaves {
            let has_grads =
                l.grad_weight != 0 || l.grad_pos.iter().chain(&l.grad_neg).any(|&x| x != 0);
            let has_rest = l.weight != 0 || l.light.iter().any(|&x| x != 0) || !l.nodes.is_empty();
            if has_grads {
                grads.leaves.push(LeafStats {
                    leaf: l.leaf,
                    grad_pos: l.grad_pos,
                    grad_neg: l.grad_neg,
                    grad_weight: l.grad_weight,
                    ..LeafStats::default()
                });
            }
            if has_rest {
                rest.leaves.push(LeafStats {
                    leaf: l.leaf,
                    weight: l.weight,
                    light: l.light,
                    nodes: l.nodes,
                    ..LeafStats::default()
                });
            }
        }
        (grads, rest)
    }

    /// Merges many statistics (e.g. one per worker) into one.
    pub fn merge_all<'a>(
        parts: impl IntoIterator<Item = &'a IterationStats>,
    ) -> Result<IterationStats, StatsError> {
        let mut it = parts.into_iter();
        let Some(first) = it.next() else {
            return Ok(IterationStats::default());
        };
        let mut acc = first.clone();
        for p in it {
            acc.merge(p)?;
        }
        Ok(acc)
    }
}

fn merge_nodes(
    a: &[(u32, [u128; 4])],
    b: &[(u32, [u128; 4])],
    of: &mut u64,
) -> Vec<(u32, [u128; 4])> {
    let mut out = Vec::with_capacity(a.len().max(b.len()));
    let (mut i, mut j) = (0, 0);
    while i < a.len() || j < b.len() {
        if j >= b.len() || (i < a.len() && a[i].0 < b[j].0) {
            out.push(a[i]);
            i += 1;
        } else if i >= a.len() || b[j].0 < a[i].0 {
            out.push(b[j]);
            j += 1;
        } else {
            let mut s = a[i].1;
            for q in 0..4 {
                s[q] = add_counted(s[q], b[j].1[q], of);
            }
            out.push((a[i].0, s));
            i += 1;
            j += 1;
        }
    }
    out
}
