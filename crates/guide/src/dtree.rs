//! Directional quadtree (D-tree) over the cylindrical `(u, v)` square.
//!
//! Nodes live in one flat array; node 0 is the root (depth 1) and is never a child. Each node
//! stores 4 quadrant sums (fixed point, see [`crate::stats`]) and 4 child indices, 0 meaning
//! "this quadrant is a leaf cell". Quadrant index: bit 0 = (u >= 0.5), bit 1 = (v >= 0.5).
//! A quadrant of a node at depth `d` is a square cell of side `2^-d`. Children are always
//! stored after their parent, so [`DTree::build`] can propagate sums in one reverse sweep.
//!
//! Records add to the leaf cell only; [`DTree::build`] makes every inner quadrant the exact
//! integer sum of its child's four quadrants.
//!
//! A quadtree has two states with a type each: [`DTree`] is the one that records and is built
//! and refined (the SD-tree's `building` trees and carried priors); [`DTree::freeze`] turns a
//! built tree into a [`SamplingDTree`], which samples and evaluates the density from f32
//! factors derived from the sums once (the SD-tree's `sampling` trees).

mod sampling;
#[cfg(test)]
mod tests;

pub use sampling::SamplingDTree;
pub(crate) use sampling::{prefetch, prefetch_block};

use crate::stats::{from_fixed, split_exact, Acc128};
use glam::Vec2;
use std::sync::atomic::AtomicU64;

#[derive(Default)]
struct Scratch {
    cells: Vec<(u32, u8)>,
    areas: Vec<f64>,
    parts: Vec<u128>,
    stack: Vec<BoxStackEntry>,
}

/// A pending node of the box-overlap traversal: index, lower corner, side.
type BoxStackEntry = (u32, [f64; 2], f64);

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

/// Maximum quadtree depth (root = depth 1; cells at depth 20 have side `2^-20`).
pub const MAX_DEPTH: u32 = 20;

/// One quadtree node: four quadrant sums and four child indices (0 = leaf cell).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct DNode {
    /// Fixed-point sums of weighted estimates per quadrant.
    pub sums: [Acc128; 4],
    /// Child node index per quadrant, 0 if the quadrant is a leaf cell.
    pub children: [u32; 4],
}

impl DNode {
    /// Sum of the four quadrants (exact, wrapping).
    #[inline]
    pub fn total(&self) -> u128 {
        self.sums.iter().fold(0u128, |a, s| a.wrapping_add(s.get()))
    }
    /// The four quadrants' sums in fixed point.
    #[inline]
    pub(crate) fn sums_fixed(&self) -> [u128; 4] {
        self.sums.each_ref().map(|s| s.get())
    }
    #[inline]
    fn sums_f64(&self) -> [f64; 4] {
        self.sums_fixed().map(from_fixed)
    }
}

/// A leaf cell of a quadtree, as found by a point lookup or a traversal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cell {
    /// Index of the node owning the cell.
    pub node: u32,
    /// Quadrant of that node (0..4).
    pub quadrant: u8,
    /// Depth of the owning node (root = 1); the cell's side is `2^-depth`.
    pub depth: u32,
    /// Lower corner of the cell in `(u, v)`.
    pub origin: [f64; 2],
    /// Side length of the cell.
    pub size: f64,
}

/// Directional quadtree with fixed-point sums and a statistical weight: the state that
/// records, builds and refines. Sampling reads a frozen copy ([`DTree::freeze`]).
///
/// Equality compares the nodes (structure and sums) and W.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DTree {
    pub(crate) nodes: Vec<DNode>,
    pub(crate) weight: Acc128,
}

impl Default for DTree {
    fn default() -> Self {
        Self::new()
    }
}

#[inline]
fn quadrant_origin(origin: [f64; 2], size: f64, q: usize) -> [f64; 2] {
    let h = size * 0.5;
    [
        origin[0] + if q & 1 != 0 { h } else { 0.0 },
        origin[1] + if q & 2 != 0 { h } else { 0.0 },
    ]
}

impl DTree {
    /// A tree with only the root node (4 empty leaf cells), weight 0.
    pub fn new() -> Self {
        Self {
            nodes: vec![DNode::default()],
            weight: Acc128::default(),
        }
    }

    /// A complete tree of the given depth (`depth >= 1`, clamped to [`MAX_DEPTH`]), all sums 0.
    /// Depth 4 gives 85 nodes and 256 leaf cells.
    pub fn uniform(depth: u32) -> Self {
        let depth = depth.clamp(1, MAX_DEPTH);
        let mut t = Self::new();
        let mut frontier = vec![0u32];
        for _ in 1..depth {
            let mut next = Vec::with_capacity(frontier.len() * 4);
            for &n in &frontier {
                for q in 0..4 {
                    let c = t.nodes.len() as u32;
                    t.nodes.push(DNode::default());
                    t.nodes[n as usize].children[q] = c;
                    next.push(c);
                }
            }
            frontier = next;
        }
        t
    }

    /// The node array (node 0 is the root).
    pub fn nodes(&self) -> &[DNode] {
        &self.nodes
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Number of leaf cells (quadrants without a child).
    pub fn leaf_count(&self) -> usize {
        self.nodes
            .iter()
            .map(|n| n.children.iter().filter(|&&c| c == 0).count())
            .sum()
    }

    /// Depth of the deepest node (root = 1).
    pub fn depth(&self) -> u32 {
        let mut best = 1;
        let mut stack = vec![(0u32, 1u32)];
        while let Some((n, d)) = stack.pop() {
            best = best.max(d);
            for &c in &self.nodes[n as usize].children {
                if c != 0 {
                    stack.push((c, d + 1));
                }
            }
        }
        best
    }

    /// Approximate heap memory of the tree in bytes.
    pub fn memory_bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<DNode>() + std::mem::size_of::<Self>()
    }

    /// Total sum (the root's four quadrants) in fixed point. Equals the sum of all leaf cells
    /// after [`DTree::build`].
    pub fn total_fixed(&self) -> u128 {
        self.nodes[0].total()
    }

    /// Total sum as a real number.
    pub fn total(&self) -> f64 {
        from_fixed(self.total_fixed())
    }

    /// Statistical weight W in fixed point.
    pub fn weight_fixed(&self) -> u128 {
        self.weight.get()
    }

    /// Statistical weight W (number of records, weighted).
    pub fn weight(&self) -> f64 {
        self.weight.get_f64()
    }

    /// Sets W (fixed point).
    pub fn set_weight_fixed(&mut self, w: u128) {
        self.weight.set(w);
    }

    /// Mean radiance `total / (4 pi W)`, 0 when W = 0.
    pub fn mean(&self) -> f64 {
        let w = self.weight();
        if w > 0.0 {
            self.total() / (4.0 * std::f64::consts::PI * w)
        } else {
            0.0
        }
    }

    /// A tree is empty (samples uniformly) when its total sum is zero (mean <= 0).
    pub fn is_empty(&self) -> bool {
        self.total_fixed() == 0
    }

    /// The `(node, quadrant)` pairs from the root down to the leaf cell containing `uv`
    /// (coordinates clamped to `[0, 1]`). Exact in f32: each level doubles and subtracts 0 or 1.
    #[inline]
    fn descend(&self, uv: Vec2) -> impl Iterator<Item = (u32, usize)> + '_ {
        let mut x = uv.x.clamp(0.0, 1.0);
        let mut y = uv.y.clamp(0.0, 1.0);
        let mut next = Some(0u32);
        std::iter::from_fn(move || {
            let idx = next?;
            let bu = (x >= 0.5) as usize;
            let bv = (y >= 0.5) as usize;
            let q = bu | (bv << 1);
            x = x * 2.0 - bu as f32;
            y = y * 2.0 - bv as f32;
            let c = self.nodes[idx as usize].children[q];
            next = (c != 0).then_some(c);
            Some((idx, q))
        })
    }

    /// Finds the leaf cell containing `uv` (coordinates clamped to `[0, 1]`).
    pub fn leaf_cell(&self, uv: Vec2) -> Cell {
        let (mut origin, mut size, mut depth, mut last) = ([0.0f64; 2], 1.0f64, 0u32, (0, 0));
        for (node, q) in self.descend(uv) {
            origin = quadrant_origin(origin, size, q);
            size *= 0.5;
            depth += 1;
            last = (node, q);
        }
        Cell {
            node: last.0,
            quadrant: last.1 as u8,
            depth,
            origin,
            size,
        }
    }

    /// The leaf cell containing `uv` as (owning node, quadrant): [`DTree::leaf_cell`] without the
    /// cell's geometry.
    #[inline]
    pub fn leaf_slot(&self, uv: Vec2) -> (u32, usize) {
        self.descend(uv).last().unwrap_or((0, 0))
    }

    /// Adds `amount` (fixed point) to the leaf cell containing `uv` (thread safe).
    #[inline]
    pub fn deposit(&self, uv: Vec2, amount: u128, overflow: &AtomicU64) {
        if amount == 0 {
            return;
        }
        let (node, q) = self.leaf_slot(uv);
        self.nodes[node as usize].sums[q].add(amount, overflow);
    }

    /// Adds `amount` (fixed point) to W (thread safe).
    #[inline]
    pub fn add_weight(&self, amount: u128, overflow: &AtomicU64) {
        self.weight.add(amount, overflow);
    }

    /// Directional box splat: distributes `amount` over the leaf cells overlapped by the square of
    /// side `size` centred on `uv`, proportionally to overlap area. The square wraps across the
    /// `v` (phi) seam, and the parts beyond `u = 0` / `u = 1` go to the cells on that border (the
    /// same as clamping), so the integer amount is conserved exactly.
    pub fn splat_box(&self, uv: Vec2, size: f64, amount: u128, overflow: &AtomicU64) {
        if amount == 0 {
            return;
        }
        SCRATCH.with(|sc| {
            let mut sc = sc.borrow_mut();
            let Scratch {
                cells,
                areas,
                parts,
                stack,
            } = &mut *sc;
            self.box_overlaps_with(uv, size, cells, areas, stack);
            if cells.is_empty() {
                self.deposit(uv, amount, overflow);
                return;
            }
            split_exact(amount, areas, parts);
            for (c, &p) in cells.iter().zip(parts.iter()) {
                self.nodes[c.0 as usize].sums[c.1 as usize].add(p, overflow);
            }
        });
    }

    /// Leaf cells `(node, quadrant)` overlapped by the wrapped box of side `size` centred on
    /// `uv`, with their overlap areas (u extended at the borders, v periodic).
    pub fn box_overlaps(
        &self,
        uv: Vec2,
        size: f64,
        cells: &mut Vec<(u32, u8)>,
        areas: &mut Vec<f64>,
    ) {
        self.box_overlaps_with(uv, size, cells, areas, &mut Vec::new());
    }

    /// [`DTree::box_overlaps`] with a reusable traversal stack.
    fn box_overlaps_with(
        &self,
        uv: Vec2,
        size: f64,
        cells: &mut Vec<(u32, u8)>,
        areas: &mut Vec<f64>,
        stack: &mut Vec<BoxStackEntry>,
    ) {
        let h = (size * 0.5).clamp(0.0, 0.5);
        let (u, v) = ((uv.x as f64).clamp(0.0, 1.0), (uv.y as f64).clamp(0.0, 1.0));
        let (u0, u1) = (u - h, u + h);
        let (v0, v1) = (v - h, v + h);
        cells.clear();
        areas.clear();
        // Depth first.
        stack.clear();
        stack.push((0, [0.0, 0.0], 1.0));
        while let Some((n, o, s)) = stack.pop() {
            for q in 0..4usize {
                let co = quadrant_origin(o, s, q);
                let cs = s * 0.5;
                // u overlap with borders extended to infinity
                let lo = if co[0] <= 0.0 {
                    f64::NEG_INFINITY
                } else {
                    co[0]
                };
                let hi = if co[0] + cs >= 1.0 {
                    f64::INFINITY
                } else {
                    co[0] + cs
                };
                let ou = (u1.min(hi) - u0.max(lo)).max(0.0);
                if ou <= 0.0 {
                    continue;
                }
                // v overlap, periodic: test the box shifted by -1, 0, +1
                let mut ov = 0.0;
                for shift in [-1.0, 0.0, 1.0] {
                    ov += ((v1 + shift).min(co[1] + cs) - (v0 + shift).max(co[1])).max(0.0);
                }
                if ov <= 0.0 {
                    continue;
                }
                let c = self.nodes[n as usize].children[q];
                if c == 0 {
                    cells.push((n, q as u8));
                    areas.push(ou * ov);
                } else {
                    stack.push((c, co, cs));
                }
            }
        }
    }

    /// Bottom-up build: every inner quadrant becomes the exact sum of its child's quadrants.
    pub fn build(&mut self) {
        for i in (0..self.nodes.len()).rev() {
            for q in 0..4 {
                let c = self.nodes[i].children[q];
                if c != 0 {
                    let s = self.nodes[c as usize].total();
                    self.nodes[i].sums[q].set(s);
                }
            }
        }
    }
    /// All leaf cells with their geometry, in depth-first order.
    pub fn leaf_cells(&self) -> Vec<Cell> {
        let mut out = Vec::new();
        let mut stack = vec![(0u32, [0.0f64; 2], 1.0f64, 1u32)];
        while let Some((n, o, s, d)) = stack.pop() {
            for q in 0..4usize {
                let co = quadrant_origin(o, s, q);
                let c = self.nodes[n as usize].children[q];
                if c == 0 {
                    out.push(Cell {
                        node: n,
                        quadrant: q as u8,
                        depth: d,
                        origin: co,
                        size: s * 0.5,
                    });
                } else {
                    stack.push((c, co, s * 0.5, d + 1));
                }
            }
        }
        out
    }

    /// Refines the tree from its own (built) sums and zeroes all statistics (doc section 3).
    ///
    /// Walks the tree depth first. For a quadrant with sum `s_i`, `f = s_i / S_total`. If
    /// `depth < max_depth` and `f > rho` the quadrant gets a child: the old child if there
    /// was one, else a new node whose 4 quadrants are seeded with `s_i / 4` (so one reset can
    /// refine several levels). Quadrants with `f <= rho` become leaf cells (coarsening).
    /// Finally all sums and W are zero. An empty tree (S_total = 0) becomes the uniform depth-4
    /// tree (85 nodes, 256 cells). Call [`DTree::build`] first.
    ///
    /// Zeroing is what the paper does. Old statistics kept in this tree would also count
    /// towards spatial splits, and measured worse; carry-over ([`crate::carry`]) keeps them
    /// apart as a prior instead (`docs/decisions/carry-over.md`).
    pub fn reset(&mut self, rho: f64, max_depth: u32) {
        *self = self.refined(rho, max_depth);
    }

    /// The tree [`DTree::reset`] makes of this one (zero statistics, refined structure),
    /// leaving this one as it is (carry-over reads it afterwards).
    pub fn refined(&self, rho: f64, max_depth: u32) -> Self {
        if !(self.total() > 0.0) {
            return Self::uniform(4.min(max_depth.clamp(1, MAX_DEPTH)));
        }
        let mut nodes = vec![DNode::default()];
        self.walk_refined(rho, max_depth, |parent, q| {
            let c = nodes.len() as u32;
            nodes.push(DNode::default());
            nodes[parent as usize].children[q] = c;
            Some(c)
        });
        Self {
            nodes,
            ..Self::new()
        }
    }

    /// How many nodes [`DTree::refined`] would make with `rho` and `max_depth`, counted
    /// without building them; counting stops past `limit` (the result is then `limit + 1`), so
    /// a tiny `rho` costs no more than `limit` steps.
    pub fn refined_node_count(&self, rho: f64, max_depth: u32, limit: usize) -> usize {
        if !(self.total() > 0.0) {
            return Self::uniform(4.min(max_depth.clamp(1, MAX_DEPTH)))
                .nodes
                .len();
        }
        let mut count = 1usize;
        self.walk_refined(rho, max_depth, |_, _| {
            count += 1;
            (count <= limit).then_some(0)
        });
        count.min(limit.saturating_add(1))
    }

    /// The walk of refinement (a non-empty tree): depth first from the root, for a quadrant
    /// with `f = s_i / S_total > rho` below `max_depth` it calls `new_child(parent, q)`, which
    /// returns the new child's index (or `None` to stop the walk). The child descends into the
    /// old child if there was one, else into a node whose 4 quadrants are seeded with
    /// `s_i / 4` (so one refinement can add several levels).
    fn walk_refined(
        &self,
        rho: f64,
        max_depth: u32,
        mut new_child: impl FnMut(u32, usize) -> Option<u32>,
    ) {
        let max_depth = max_depth.clamp(1, MAX_DEPTH);
        let total = self.total();
        // (new index, old index or u32::MAX when seeded, seeded sums, depth)
        let mut stack: Vec<(u32, u32, [f64; 4], u32)> = vec![(0, 0, [0.0; 4], 1)];
        while let Some((ni, oi, seeded, depth)) = stack.pop() {
            let sums = if oi != u32::MAX {
                self.nodes[oi as usize].sums_f64()
            } else {
                seeded
            };
            for q in 0..4 {
                let f = sums[q] / total;
                if depth < max_depth && f > rho {
                    let Some(c) = new_child(ni, q) else {
                        return;
                    };
                    let oc = if oi != u32::MAX {
                        self.nodes[oi as usize].children[q]
                    } else {
                        0
                    };
                    if oc != 0 {
                        stack.push((c, oc, [0.0; 4], depth + 1));
                    } else {
                        let s4 = sums[q] * 0.25;
                        stack.push((c, u32::MAX, [s4; 4], depth + 1));
                    }
                }
            }
        }
    }

    /// Zeroes every sum and W, keeping the structure.
    pub fn clear_stats(&mut self) {
        for n in &self.nodes {
            for s in &n.sums {
                s.set(0);
            }
        }
        self.weight.set(0);
    }

    /// A 64-bit fingerprint of the structure (child arrays only).
    pub fn structure_hash(&self, h: &mut crate::hash::Hasher64) {
        h.write_u64(self.nodes.len() as u64);
        for n in &self.nodes {
            for &c in &n.children {
                h.write_u32(c);
            }
        }
    }
}
