//! The sampling state of a quadtree: [`SamplingDTree`], a [`DTree`] whose sums no longer
//! change, with what sampling and pdf evaluation read per node derived once
//! ([`DTree::freeze`]).

use super::{quadrant_origin, Cell, DTree};
use crate::region::{CellMask, CellWeights, Restriction};
use glam::Vec2;

/// A cache-line prefetch hint (no-op where the target has none). Never faults, even for an
/// address outside any allocation.
#[inline(always)]
pub(crate) fn prefetch(p: *const u8) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: prefetch is a hint; it does not access memory architecturally and cannot fault.
    #[allow(unused_unsafe)]
    unsafe {
        std::arch::x86_64::_mm_prefetch(p.cast::<i8>(), std::arch::x86_64::_MM_HINT_T0);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Requests the block starting at sampling node `i` of `cache` (the node and up to 4 children,
/// at most 160 bytes: 3 cache lines). A hint only.
#[inline(always)]
pub(crate) fn prefetch_block(cache: &[SampleNode], i: usize) {
    let p = cache.as_ptr().wrapping_add(i).cast::<u8>();
    prefetch(p);
    prefetch(p.wrapping_add(64));
    prefetch(p.wrapping_add(128));
}

/// What sampling and pdf evaluation need of one node, derived from its four sums in one place
/// ([`SampleNode::from_sums`]).
///
/// 32 bytes, aligned so that a node never straddles a cache line (two per line): sampling and
/// pdf evaluation walk one node per level, and the trees of a large scene do not fit in cache.
/// The column and row probabilities are derived from the factors when sampling
/// ([`SampleNode::p_col0`], [`SampleNode::p_row0`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct SampleNode {
    /// Density factor `4 s_q / sum` per quadrant (exactly 0 for a zero quadrant).
    pub(super) factor: [f32; 4],
    /// Child node per quadrant (0 = leaf cell).
    pub(super) children: [u32; 4],
}

impl SampleNode {
    #[inline]
    pub(super) fn from_sums(s: [f64; 4], children: [u32; 4]) -> Self {
        let tot = s[0] + s[1] + s[2] + s[3];
        if !(tot > 0.0) {
            return Self {
                children,
                ..Self::default()
            };
        }
        let f = |x: f64| if x > 0.0 { (4.0 * x / tot) as f32 } else { 0.0 };
        Self {
            factor: [f(s[0]), f(s[1]), f(s[2]), f(s[3])],
            children,
        }
    }

    /// Probability of the left column, `(s0 + s2) / sum`.
    #[inline]
    fn p_col0(&self) -> f32 {
        (self.factor[0] + self.factor[2]) * 0.25
    }

    /// Probability of the lower row within column `c`, `s_c / (s_c + s_{c+2})` (0.5 for an
    /// empty column).
    #[inline]
    fn p_row0(&self, c: usize) -> f32 {
        let (a, b) = (self.factor[c], self.factor[c + 2]);
        if a + b > 0.0 {
            a / (a + b)
        } else {
            0.5
        }
    }
}

/// Puts `x` (computed in f64) into the f32 grid while keeping it inside `[lo, hi)`.
#[inline]
fn to_f32_inside(x: f64, lo: f64, hi: f64) -> f32 {
    let mut f = x as f32;
    if (f as f64) >= hi {
        f = f32::from_bits(f.to_bits() - 1);
    }
    if (f as f64) < lo {
        f = f32::from_bits(f.to_bits() + 1);
    }
    f
}

/// A random number in `[0, 1)` (NaN maps to 0).
#[inline(always)]
fn unit_f32(rng: &mut impl FnMut() -> f32) -> f32 {
    let r = rng();
    if r >= 0.0 {
        r.min(1.0 - f32::EPSILON / 2.0)
    } else {
        0.0
    }
}

#[inline(always)]
fn next_unit(rng: &mut impl FnMut() -> f32) -> f64 {
    let r = rng() as f64;
    if r.is_nan() {
        0.0
    } else {
        r.clamp(0.0, 1.0 - f64::EPSILON)
    }
}

/// A point uniformly in the square with corner `origin` and side `size` (two random numbers),
/// strictly inside it in f32.
#[inline(always)]
fn uniform_in(origin: [f64; 2], size: f64, rng: &mut impl FnMut() -> f32) -> Vec2 {
    let r3 = next_unit(rng);
    let r4 = next_unit(rng);
    let u = to_f32_inside(origin[0] + r3 * size, origin[0], origin[0] + size);
    let v = to_f32_inside(origin[1] + r4 * size, origin[1], origin[1] + size);
    Vec2::new(u, v)
}

/// Probability of each cell of the 4x4 grid over `(u, v)` from the sampling nodes (root
/// first): the product of the two top levels' factors over 16, in f32 (an empty tree: 1/16
/// each).
fn cell_masses_of(cache: &[SampleNode]) -> [f32; 16] {
    let root = cache[0];
    if root.factor == [0.0; 4] {
        return [1.0 / 16.0; 16];
    }
    let mut m = [0.0f32; 16];
    for q1 in 0..4usize {
        let f1 = root.factor[q1] * 0.25;
        let c1 = root.children[q1];
        let f2 = if c1 == 0 {
            [0.25; 4]
        } else {
            cache[c1 as usize].factor.map(|f| f * 0.25)
        };
        for q2 in 0..4usize {
            let iu = ((q1 & 1) << 1) | (q2 & 1);
            let iv = ((q1 >> 1) << 1) | (q2 >> 1);
            m[iu + 4 * iv] = f1 * f2[q2];
        }
    }
    m
}

/// A quadtree frozen for sampling: the tree (its sums and weight no longer change, except the
/// weight when a spatial leaf splits) with what sampling and pdf evaluation read, derived from
/// the sums once by [`DTree::freeze`].
///
/// Equality compares the trees ([`DTree`]'s equality); the derived data is ignored.
#[derive(Clone, Debug)]
pub struct SamplingDTree {
    tree: DTree,
    /// One [`SampleNode`] per node of `tree`, laid out in blocks ([`DTree::block_order`]);
    /// the root is first.
    pub(crate) cache: Vec<SampleNode>,
    /// The probability of each cell of the 4x4 grid ([`SamplingDTree::cell_masses`]).
    cells: [f32; 16],
}

impl PartialEq for SamplingDTree {
    fn eq(&self, o: &Self) -> bool {
        self.tree == o.tree
    }
}
impl Eq for SamplingDTree {}

impl DTree {
    /// The sampling state of this tree: its quadrant sums turned into the f32 density factors
    /// that sampling and pdf evaluation read. The tree's sums must not change afterwards (the
    /// SD-tree freezes a built copy of each building tree at every refinement).
    ///
    /// The factors are laid out in blocks (see `DTree::block_order`): a node and its inner
    /// children are adjacent, so a walk that reaches a block's first node can request the
    /// whole block at once (`prefetch_block`) and pays one cache miss per two levels.
    pub fn freeze(self) -> SamplingDTree {
        let order = self.block_order();
        let mut new_index = vec![0u32; self.nodes.len()];
        for (new, &old) in order.iter().enumerate() {
            new_index[old as usize] = new as u32;
        }
        let cache: Vec<SampleNode> = order
            .iter()
            .map(|&old| {
                let n = &self.nodes[old as usize];
                let mut s = SampleNode::from_sums(n.sums_f64(), n.children);
                for c in &mut s.children {
                    if *c != 0 {
                        *c = new_index[*c as usize];
                    }
                }
                s
            })
            .collect();
        SamplingDTree {
            cells: cell_masses_of(&cache),
            cache,
            tree: self,
        }
    }

    /// The nodes in block order (old indices, root first): each block is a node followed by its
    /// inner children in quadrant order; the grandchildren start blocks of their own, placed
    /// depth first. Descending from a block's first node to one of its children then needs no
    /// second trip to memory.
    fn block_order(&self) -> Vec<u32> {
        let mut order = Vec::with_capacity(self.nodes.len());
        let mut roots = vec![0u32];
        while let Some(r) = roots.pop() {
            order.push(r);
            let first = order.len();
            order.extend(self.nodes[r as usize].children.iter().filter(|&&c| c != 0));
            // Blocks of the grandchildren, the first quadrant's on top of the stack.
            for i in (first..order.len()).rev() {
                let c = order[i] as usize;
                roots.extend(self.nodes[c].children.iter().rev().filter(|&&g| g != 0));
            }
        }
        order
    }
}

impl SamplingDTree {
    /// The frozen tree: structure, sums and weight. Read it only; the density factors were
    /// derived from its sums when it was frozen.
    pub fn tree(&self) -> &DTree {
        &self.tree
    }

    /// Sets W (fixed point). The weight is not part of the density, so the tree stays frozen
    /// (a spatial leaf that splits halves it between its children).
    pub fn set_weight_fixed(&mut self, w: u128) {
        self.tree.set_weight_fixed(w);
    }

    /// Approximate heap memory of the tree and its sampling nodes in bytes.
    pub fn memory_bytes(&self) -> usize {
        self.tree.memory_bytes() - std::mem::size_of::<DTree>()
            + self.cache.capacity() * std::mem::size_of::<SampleNode>()
            + std::mem::size_of::<Self>()
    }

    /// A frozen tree with its sampling nodes in node order instead of block order: what
    /// sampling computed from the sums before the block layout (tests compare the two).
    #[cfg(test)]
    pub(crate) fn in_node_order(tree: DTree) -> Self {
        let cache: Vec<SampleNode> = tree
            .nodes
            .iter()
            .map(|n| SampleNode::from_sums(n.sums_f64(), n.children))
            .collect();
        Self {
            cells: cell_masses_of(&cache),
            cache,
            tree,
        }
    }

    /// Child indices of sampling node `i` (tests of the block layout).
    #[cfg(test)]
    pub(crate) fn cache_children(&self, i: usize) -> [u32; 4] {
        self.cache[i].children
    }

    /// Sampling node `i`, requesting the rest of its block on the way (the walks read nodes
    /// through this, so the next level's node is already on its way).
    #[inline(always)]
    fn block(&self, i: usize) -> SampleNode {
        prefetch_block(&self.cache, i);
        self.cache[i]
    }

    /// Density over `(u, v)` at `uv`: product of `4 s_i / sum` along the path, 0 as soon as a
    /// quadrant on the path is zero, 1 (uniform) for an empty tree. Divide by `4 pi` for solid
    /// angle. The factors are f32, multiplied root first, exactly as
    /// [`SamplingDTree::sample_with_pdf`] does.
    pub fn pdf(&self, uv: Vec2) -> f32 {
        let root = self.block(0);
        if root.factor == [0.0; 4] {
            return 1.0; // empty tree: uniform
        }
        let mut x = uv.x.clamp(0.0, 1.0);
        let mut y = uv.y.clamp(0.0, 1.0);
        let mut n = root;
        let mut pdf = 1.0f32;
        loop {
            let bu = (x >= 0.5) as usize;
            let bv = (y >= 0.5) as usize;
            let q = bu | (bv << 1);
            let f = n.factor[q];
            if !(f > 0.0) {
                return 0.0;
            }
            pdf *= f;
            let c = n.children[q];
            if c == 0 {
                return pdf;
            }
            // exact in f32: doubling and subtracting 0 or 1
            x = x * 2.0 - bu as f32;
            y = y * 2.0 - bv as f32;
            n = self.block(c as usize);
        }
    }

    /// Samples `(u, v)` proportionally to the quadtree density; see
    /// [`SamplingDTree::sample_with_pdf`].
    pub fn sample(&self, rng: &mut impl FnMut() -> f32) -> Vec2 {
        self.sample_with_pdf(rng).0
    }

    /// Samples `(u, v)` and returns it with its density over `(u, v)`.
    ///
    /// At each node the column (u half) is chosen with probability `(s1 + s3) / sum`, then the
    /// row within it, using two fresh random numbers per level; two more place the point
    /// uniformly in the leaf cell. `rng` must return numbers in `[0, 1)`. An empty tree
    /// samples uniformly with density 1. The density equals [`SamplingDTree::pdf`] of the
    /// returned point bit for bit.
    pub fn sample_with_pdf(&self, rng: &mut impl FnMut() -> f32) -> (Vec2, f32) {
        let root = self.block(0);
        if root.factor == [0.0; 4] {
            return (uniform_in([0.0, 0.0], 1.0, rng), 1.0);
        }
        self.sample_below(root, [0.0, 0.0], 1.0, 1.0, rng)
    }

    /// Samples below node `n`, whose square has corner `origin` and side `size`, the density
    /// so far being `pdf`: per level a column then a row, then a point uniformly in the leaf
    /// cell.
    #[inline(always)]
    fn sample_below(
        &self,
        mut n: SampleNode,
        mut origin: [f64; 2],
        mut size: f64,
        mut pdf: f32,
        rng: &mut impl FnMut() -> f32,
    ) -> (Vec2, f32) {
        loop {
            let mut col = (unit_f32(rng) >= n.p_col0()) as usize;
            if !(n.factor[col] > 0.0 || n.factor[col + 2] > 0.0) {
                col ^= 1; // rounding guard: never pick a zero-mass column
            }
            let mut row = (unit_f32(rng) >= n.p_row0(col)) as usize;
            if !(n.factor[col | (row << 1)] > 0.0) {
                row ^= 1;
            }
            let q = col | (row << 1);
            pdf *= n.factor[q];
            origin = quadrant_origin(origin, size, q);
            size *= 0.5;
            let c = n.children[q];
            if c == 0 {
                return (uniform_in(origin, size, rng), pdf);
            }
            n = self.block(c as usize);
        }
    }

    /// Probability of each cell of the 4x4 grid over `(u, v)` (index `iu + 4 iv`, see
    /// [`CellMask`]): the product of the two top levels' factors over 16, in f32 (an empty
    /// tree: 1/16 each).
    pub fn cell_masses(&self) -> [f32; 16] {
        self.cells
    }

    /// The tree's density restricted to the cells of a mask, each cell's density times its
    /// weight (a [`CellMask`] or [`CellWeights`]; see [`crate::region`]): their weighted mass,
    /// summed in cell order. No restriction (mass exactly 1) for all cells unweighted and when
    /// the cells hold no probability, so the result can always be sampled.
    #[inline]
    pub fn restrict(&self, region: impl Into<CellWeights>) -> Restriction {
        let CellWeights { mask, weight } = region.into();
        if mask == CellMask::ALL && weight == [1.0; 16] {
            return Restriction::NONE;
        }
        let mut mass = 0.0f32;
        for (i, mi) in self.cells.iter().enumerate() {
            if mask.0 & (1 << i) != 0 {
                mass += mi * weight[i];
            }
        }
        if mass > 0.0 {
            Restriction { mask, mass, weight }
        } else {
            Restriction::NONE
        }
    }

    /// [`SamplingDTree::sample_with_pdf`] from the density restricted by `r` (from
    /// [`SamplingDTree::restrict`] on this tree): a cell of the mask chosen by its weighted
    /// mass (one random number), then the usual descent from the cell's node. The density
    /// returned equals [`SamplingDTree::pdf_restricted`] of the point bit for bit.
    pub fn sample_restricted(&self, r: Restriction, rng: &mut impl FnMut() -> f32) -> (Vec2, f32) {
        if r.mask == CellMask::ALL && r.weight == [1.0; 16] {
            return self.sample_with_pdf(rng);
        }
        // The cell: the first whose running mass exceeds u * mass (rounding guard: else the
        // last cell of the mask with mass).
        let target = unit_f32(rng) * r.mass;
        let mut acc = 0.0f32;
        let mut cell = usize::MAX;
        for (i, &m) in self.cells.iter().enumerate() {
            if r.mask.0 & (1 << i) != 0 && m > 0.0 {
                acc += m * r.weight[i];
                cell = i;
                if acc > target {
                    break;
                }
            }
        }
        let (iu, iv) = (cell % 4, cell / 4);
        let origin = [iu as f64 * 0.25, iv as f64 * 0.25];
        let root = self.block(0);
        let (uv, pdf) = if root.factor == [0.0; 4] {
            (uniform_in(origin, 0.25, rng), 1.0)
        } else {
            let q1 = (iu >> 1) | ((iv >> 1) << 1);
            let q2 = (iu & 1) | ((iv & 1) << 1);
            let pdf = root.factor[q1]; // pdf() multiplies from 1.0: the same bits
            match root.children[q1] {
                0 => (uniform_in(origin, 0.25, rng), pdf),
                c1 => {
                    let n1 = self.block(c1 as usize);
                    let pdf = pdf * n1.factor[q2];
                    match n1.children[q2] {
                        0 => (uniform_in(origin, 0.25, rng), pdf),
                        c2 => self.sample_below(self.block(c2 as usize), origin, 0.25, pdf, rng),
                    }
                }
            }
        };
        (uv, pdf * r.weight[cell] / r.mass)
    }

    /// Density at `uv` of the tree restricted by `r` (from [`SamplingDTree::restrict`] on this
    /// tree): [`SamplingDTree::pdf`] times the cell's weight, divided by the weighted mass
    /// inside the mask; 0 outside.
    #[inline]
    pub fn pdf_restricted(&self, r: Restriction, uv: Vec2) -> f32 {
        if r.mask == CellMask::ALL && r.weight == [1.0; 16] {
            return self.pdf(uv);
        }
        let cell = CellMask::cell_of(uv);
        if r.mask.0 & (1 << cell) == 0 {
            return 0.0;
        }
        self.pdf(uv) * r.weight[cell as usize] / r.mass
    }

    /// Density over `(u, v)` of a given leaf cell of the tree (constant within the cell).
    pub fn cell_pdf(&self, cell: &Cell) -> f64 {
        let cx = cell.origin[0] + cell.size * 0.5;
        let cy = cell.origin[1] + cell.size * 0.5;
        self.pdf(Vec2::new(cx as f32, cy as f32)) as f64
    }
}
