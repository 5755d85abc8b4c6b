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

use crate::region::{CellMask, CellWeights, Restriction};
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

/// Requests the block starting at sampling node `i` of `frozen` (the node and up to 4 children,
/// at most 160 bytes: 3 cache lines). A hint only.
#[inline(always)]
pub(crate) fn prefetch_block(frozen: &[SampleNode], i: usize) {
    let p = frozen.as_ptr().wrapping_add(i).cast::<u8>();
    prefetch(p);
    prefetch(p.wrapping_add(64));
    prefetch(p.wrapping_add(128));
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
    #[inline]
    fn sums_f64(&self) -> [f64; 4] {
        [
            from_fixed(self.sums[0].get()),
            from_fixed(self.sums[1].get()),
            from_fixed(self.sums[2].get()),
            from_fixed(self.sums[3].get()),
        ]
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

/// What sampling and pdf evaluation need of one node, derived from its four sums in one place
/// ([`SampleNode::from_sums`]) so that the cached and the uncached paths agree bit for bit.
///
/// 32 bytes, aligned so that a node never straddles a cache line (two per line): sampling and
/// pdf evaluation walk one node per level, and the trees of a large scene do not fit in cache.
/// The column and row probabilities are derived from the factors when sampling
/// ([`SampleNode::p_col0`], [`SampleNode::p_row0`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct SampleNode {
    /// Density factor `4 s_q / sum` per quadrant (exactly 0 for a zero quadrant).
    factor: [f32; 4],
    /// Child node per quadrant (0 = leaf cell).
    children: [u32; 4],
}

impl SampleNode {
    #[inline]
    fn from_sums(s: [f64; 4], children: [u32; 4]) -> Self {
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

/// Directional quadtree with fixed-point sums and a statistical weight.
///
/// Equality compares the nodes (structure and sums) and W; the sampling cache is ignored.
#[derive(Clone, Debug)]
pub struct DTree {
    pub(crate) nodes: Vec<DNode>,
    pub(crate) weight: Acc128,
    /// Optional cache of what sampling and pdf read per node (see [`SampleNode`]); valid only
    /// when its length equals the node count (see [`DTree::freeze`]).
    pub(crate) frozen: Vec<SampleNode>,
    /// With `frozen`: the probability of each cell of the 4x4 grid ([`DTree::cell_masses`]).
    pub(crate) frozen_cells: [f32; 16],
}

impl PartialEq for DTree {
    fn eq(&self, o: &Self) -> bool {
        self.nodes == o.nodes && self.weight == o.weight
    }
}
impl Eq for DTree {}

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

impl DTree {
    /// A tree with only the root node (4 empty leaf cells), weight 0.
    pub fn new() -> Self {
        Self {
            nodes: vec![DNode::default()],
            weight: Acc128::default(),
            frozen: Vec::new(),
            frozen_cells: [0.0; 16],
        }
    }

    /// Caches the quadrant sums as f64 for fast sampling and pdf evaluation. Call it on a tree
    /// whose sums will not change any more (the SD-tree does this for every sampling tree); any
    /// later change of the sums must be followed by another `freeze` or an [`DTree::unfreeze`].
    /// Results are bit-identical with and without the cache.
    ///
    /// The cache is laid out in blocks (see [`DTree::block_order`]): a node and its inner
    /// children are adjacent, so a walk that reaches a block's first node can request the whole
    /// block at once ([`prefetch_block`]) and pays one cache miss per two levels.
    pub fn freeze(&mut self) {
        let order = self.block_order();
        let mut new_index = vec![0u32; self.nodes.len()];
        for (new, &old) in order.iter().enumerate() {
            new_index[old as usize] = new as u32;
        }
        self.frozen = order
            .iter()
            .map(|&old| {
                let mut n = self.compute_node(old as usize);
                for c in &mut n.children {
                    if *c != 0 {
                        *c = new_index[*c as usize];
                    }
                }
                n
            })
            .collect();
        self.frozen_cells = self.cell_masses_in(&|i| self.frozen[i]);
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

    /// Child indices of node `i` of the sampling cache (tests of its layout).
    #[cfg(test)]
    pub(crate) fn frozen_children(&self, i: usize) -> [u32; 4] {
        self.frozen[i].children
    }

    /// Drops the sampling cache.
    pub fn unfreeze(&mut self) {
        self.frozen = Vec::new();
    }

    /// Sampling node `i` of the cache, requesting the rest of its block on the way (the walks
    /// read nodes through this, so the next level's node is already on its way).
    #[inline(always)]
    fn frozen_block(&self, i: usize) -> SampleNode {
        prefetch_block(&self.frozen, i);
        self.frozen[i]
    }

    #[inline]
    fn compute_node(&self, idx: usize) -> SampleNode {
        let n = &self.nodes[idx];
        SampleNode::from_sums(n.sums_f64(), n.children)
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
        self.nodes.capacity() * std::mem::size_of::<DNode>()
            + self.frozen.capacity() * std::mem::size_of::<SampleNode>()
            + std::mem::size_of::<Self>()
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
        if self.frozen.len() == self.nodes.len() {
            // a node with mass has a quadrant of at least a quarter of it: factor >= 1
            return self.frozen[0].factor == [0.0; 4];
        }
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
        self.unfreeze();
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

    /// Density over `(u, v)` at `uv`: product of `4 s_i / sum` along the path, 0 as soon as a
    /// quadrant on the path is zero, 1 (uniform) for an empty tree. Divide by `4 pi` for solid angle.
    /// The factors are f32, multiplied root first, exactly as [`DTree::sample_with_pdf`] does.
    pub fn pdf(&self, uv: Vec2) -> f32 {
        if self.frozen.len() == self.nodes.len() {
            Self::pdf_in(&|i| self.frozen_block(i), uv)
        } else {
            Self::pdf_in(&|i| self.compute_node(i), uv)
        }
    }

    /// [`DTree::pdf`] over the nodes `node(i)` returns (the cache, or computed from the sums).
    #[inline(always)]
    fn pdf_in(node: &impl Fn(usize) -> SampleNode, uv: Vec2) -> f32 {
        let root = node(0);
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
            n = node(c as usize);
        }
    }

    /// Samples `(u, v)` proportionally to the quadtree density; see [`DTree::sample_with_pdf`].
    pub fn sample(&self, rng: &mut impl FnMut() -> f32) -> Vec2 {
        self.sample_with_pdf(rng).0
    }

    /// Samples `(u, v)` and returns it with its density over `(u, v)`.
    ///
    /// At each node the column (u half) is chosen with probability `(s1 + s3) / sum`, then the
    /// row within it, using two fresh random numbers per level; two more place the point
    /// uniformly in the leaf cell. `rng` must return numbers in `[0, 1)`. An empty tree
    /// samples uniformly with density 1. The density equals [`DTree::pdf`] of the returned
    /// point bit for bit.
    pub fn sample_with_pdf(&self, rng: &mut impl FnMut() -> f32) -> (Vec2, f32) {
        if self.frozen.len() == self.nodes.len() {
            Self::sample_in(&|i| self.frozen_block(i), rng)
        } else {
            Self::sample_in(&|i| self.compute_node(i), rng)
        }
    }

    /// [`DTree::sample_with_pdf`] over the nodes `node(i)` returns.
    #[inline(always)]
    fn sample_in(
        node: &impl Fn(usize) -> SampleNode,
        rng: &mut impl FnMut() -> f32,
    ) -> (Vec2, f32) {
        let root = node(0);
        if root.factor == [0.0; 4] {
            return (uniform_in([0.0, 0.0], 1.0, rng), 1.0);
        }
        Self::sample_below(node, root, [0.0, 0.0], 1.0, 1.0, rng)
    }

    /// Samples below node `n`, whose square has corner `origin` and side `size`, the density
    /// so far being `pdf`: per level a column then a row, then a point uniformly in the leaf
    /// cell.
    #[inline(always)]
    fn sample_below(
        node: &impl Fn(usize) -> SampleNode,
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
            n = node(c as usize);
        }
    }

    /// Probability of each cell of the 4x4 grid over `(u, v)` (index `iu + 4 iv`, see
    /// [`CellMask`]): the product of the two top levels' factors over 16, in f32 (an empty
    /// tree: 1/16 each). Cached by [`DTree::freeze`].
    pub fn cell_masses(&self) -> [f32; 16] {
        if self.frozen.len() == self.nodes.len() {
            self.frozen_cells
        } else {
            self.cell_masses_in(&|i| self.compute_node(i))
        }
    }

    fn cell_masses_in(&self, node: &impl Fn(usize) -> SampleNode) -> [f32; 16] {
        let root = node(0);
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
                node(c1 as usize).factor.map(|f| f * 0.25)
            };
            for q2 in 0..4usize {
                let iu = ((q1 & 1) << 1) | (q2 & 1);
                let iv = ((q1 >> 1) << 1) | (q2 >> 1);
                m[iu + 4 * iv] = f1 * f2[q2];
            }
        }
        m
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
        let m = self.cell_masses();
        let mut mass = 0.0f32;
        for (i, mi) in m.iter().enumerate() {
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

    /// [`DTree::sample_with_pdf`] from the density restricted by `r` (from [`DTree::restrict`]
    /// on this tree): a cell of the mask chosen by its weighted mass (one random number), then the
    /// usual descent from the cell's node. The density returned equals
    /// [`DTree::pdf_restricted`] of the point bit for bit.
    pub fn sample_restricted(&self, r: Restriction, rng: &mut impl FnMut() -> f32) -> (Vec2, f32) {
        if r.mask == CellMask::ALL && r.weight == [1.0; 16] {
            return self.sample_with_pdf(rng);
        }
        if self.frozen.len() == self.nodes.len() {
            Self::sample_cell_in(&|i| self.frozen_block(i), &self.frozen_cells, r, rng)
        } else {
            let m = self.cell_masses();
            Self::sample_cell_in(&|i| self.compute_node(i), &m, r, rng)
        }
    }

    #[inline(always)]
    fn sample_cell_in(
        node: &impl Fn(usize) -> SampleNode,
        masses: &[f32; 16],
        r: Restriction,
        rng: &mut impl FnMut() -> f32,
    ) -> (Vec2, f32) {
        // The cell: the first whose running mass exceeds u * mass (rounding guard: else the
        // last cell of the mask with mass).
        let target = unit_f32(rng) * r.mass;
        let mut acc = 0.0f32;
        let mut cell = usize::MAX;
        for (i, &m) in masses.iter().enumerate() {
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
        let root = node(0);
        let (uv, pdf) = if root.factor == [0.0; 4] {
            (uniform_in(origin, 0.25, rng), 1.0)
        } else {
            let q1 = (iu >> 1) | ((iv >> 1) << 1);
            let q2 = (iu & 1) | ((iv & 1) << 1);
            let pdf = root.factor[q1]; // pdf() multiplies from 1.0: the same bits
            match root.children[q1] {
                0 => (uniform_in(origin, 0.25, rng), pdf),
                c1 => {
                    let n1 = node(c1 as usize);
                    let pdf = pdf * n1.factor[q2];
                    match n1.children[q2] {
                        0 => (uniform_in(origin, 0.25, rng), pdf),
                        c2 => Self::sample_below(node, node(c2 as usize), origin, 0.25, pdf, rng),
                    }
                }
            }
        };
        (uv, pdf * r.weight[cell] / r.mass)
    }

    /// Density at `uv` of the tree restricted by `r` (from [`DTree::restrict`] on this tree):
    /// [`DTree::pdf`] times the cell's weight, divided by the weighted mass inside the mask; 0
    /// outside.
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

    /// Density over `(u, v)` of a given leaf cell (constant within the cell).
    pub fn cell_pdf(&self, cell: &Cell) -> f64 {
        let cx = cell.origin[0] + cell.size * 0.5;
        let cy = cell.origin[1] + cell.size * 0.5;
        self.pdf(Vec2::new(cx as f32, cy as f32)) as f64
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
    /// Zeroing is what the paper does. Keeping half of the old sums and W *in this tree* (an
    /// early attempt) made veach-ajar at 30 CPU-s worse, relMSE 0.107 vs 0.077 (pathfarm
    /// preset) and 0.138 vs 0.119 (2019), 4-6 seeds; there the old weight also counted towards
    /// spatial splits. Carry-over ([`crate::carry`]) keeps the old statistics apart as a
    /// prior, out of the split criterion, and measured 0.93x relMSE at 30 CPU-s.
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
        self.unfreeze();
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
