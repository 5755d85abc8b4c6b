//! Spatial binary tree (S-tree) over a cube made from the scene's bounding box.
//!
//! Nodes live in one flat array; node 0 is the root and splits on x, a child splits on
//! `(parent.axis + 1) % 3`, always at the midpoint. Leaves point into the payload array owned
//! by [`crate::SdTree`].

use glam::Vec3;

#[cfg(test)]
mod tests;

/// One S-tree node.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SNode {
    /// Axis this node splits on (0 = x, 1 = y, 2 = z); meaningful for inner nodes.
    pub axis: u8,
    /// Child node indices, `[0, 0]` for a leaf (the root is never a child).
    pub children: [u32; 2],
    /// Payload (leaf) index for leaves, `u32::MAX` for inner nodes.
    pub leaf: u32,
    /// Depth of the node (root = 0).
    pub depth: u32,
}

impl SNode {
    /// Whether this node is a leaf.
    #[inline]
    pub fn is_leaf(&self) -> bool {
        self.children[0] == 0
    }
}

/// Result of a point lookup.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SLookup {
    /// Payload index of the leaf.
    pub leaf: u32,
    /// Node index of the leaf.
    pub node: u32,
    /// World-space lower corner of the leaf's box.
    pub min: Vec3,
    /// World-space extent (size) of the leaf's box.
    pub extent: Vec3,
}

/// Splits per axis that [`STree`]'s jump table resolves at once (the top `3 * JUMP_LEVELS`
/// levels of the tree): a grid of `2^(3 * JUMP_LEVELS)` cells, 16 KB at 4.
const JUMP_LEVELS: u32 = 4;

/// The spatial binary tree: cube domain and node array.
///
/// Equality compares the domain and the nodes (the jump table is derived from them).
#[derive(Clone, Debug)]
pub struct STree {
    pub(crate) min: Vec3,
    pub(crate) size: f32,
    pub(crate) nodes: Vec<SNode>,
    /// Jump table ([`STree::index`]): per cell of the `2^JUMP_LEVELS`-per-axis grid (x in the
    /// low bits, then y, then z), the node where the descent through that cell reaches depth
    /// `3 * JUMP_LEVELS`, or the leaf where it ends above that depth. Empty when not built:
    /// a split clears it, and lookups take the plain descent until it is indexed again.
    jump: Vec<u32>,
}

impl PartialEq for STree {
    fn eq(&self, o: &Self) -> bool {
        self.min == o.min && self.size == o.size && self.nodes == o.nodes
    }
}

impl STree {
    /// A single-leaf tree (payload 0) over the cube that contains `[aabb_min, aabb_max]`: the
    /// box is extended symmetrically around its centre to its largest extent (a degenerate box
    /// gets side 1; a tiny relative margin keeps the original faces strictly inside).
    pub fn new(aabb_min: Vec3, aabb_max: Vec3) -> Self {
        let (lo, hi) = if aabb_min.is_finite() && aabb_max.is_finite() {
            (aabb_min.min(aabb_max), aabb_min.max(aabb_max))
        } else {
            (Vec3::splat(-1.0), Vec3::splat(1.0))
        };
        let centre = (lo + hi) * 0.5;
        let mut size = (hi - lo).max_element();
        if !(size > 0.0) {
            size = 1.0;
        }
        size *= 1.0 + 1e-5;
        Self::from_parts(
            centre - Vec3::splat(size * 0.5),
            size,
            vec![SNode {
                axis: 0,
                children: [0, 0],
                leaf: 0,
                depth: 0,
            }],
        )
    }

    /// A tree from its domain and nodes (as read from the wire format), indexed.
    pub(crate) fn from_parts(min: Vec3, size: f32, nodes: Vec<SNode>) -> Self {
        let mut t = Self {
            min,
            size,
            nodes,
            jump: Vec::new(),
        };
        t.index();
        t
    }

    /// A copy without the jump table (lookups take the plain descent), for tests.
    #[cfg(test)]
    pub(crate) fn without_index(&self) -> Self {
        Self {
            jump: Vec::new(),
            ..self.clone()
        }
    }

    /// Heap memory of the node array and the jump table, in bytes.
    pub(crate) fn memory_bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<SNode>()
            + self.jump.capacity() * std::mem::size_of::<u32>()
    }

    /// Builds the jump table that lets lookups skip the top `3 * JUMP_LEVELS` levels. Call it
    /// after a round of splits; results of lookups are the same with or without it.
    pub(crate) fn index(&mut self) {
        let cells = 1usize << (3 * JUMP_LEVELS);
        let mut jump = Vec::with_capacity(cells);
        for cell in 0..cells {
            let c = [
                cell & ((1 << JUMP_LEVELS) - 1),
                (cell >> JUMP_LEVELS) & ((1 << JUMP_LEVELS) - 1),
                cell >> (2 * JUMP_LEVELS),
            ];
            let mut idx = 0usize;
            // Level l splits on axis l % 3 and reads that axis' digit l / 3 (most significant
            // first), as lookup_normalised does.
            for level in 0..3 * JUMP_LEVELS {
                let n = &self.nodes[idx];
                if n.is_leaf() {
                    break;
                }
                let digit = (c[(level % 3) as usize] >> (JUMP_LEVELS - 1 - level / 3)) & 1;
                idx = n.children[digit] as usize;
            }
            jump.push(idx as u32);
        }
        self.jump = jump;
    }

    /// Lower corner of the cube domain.
    pub fn domain_min(&self) -> Vec3 {
        self.min
    }

    /// Side length of the cube domain.
    pub fn domain_size(&self) -> f32 {
        self.size
    }

    /// The node array.
    pub fn nodes(&self) -> &[SNode] {
        &self.nodes
    }

    /// Normalises a world point into `[0, 1]^3` (clamped; NaN maps to 0).
    #[inline]
    pub fn normalise(&self, p: Vec3) -> Vec3 {
        let x = (p - self.min) / self.size;
        let c = |v: f32| if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
        Vec3::new(c(x.x), c(x.y), c(x.z))
    }

    /// Finds the leaf containing `p` and its box. Points outside the domain are clamped onto it.
    #[inline]
    pub fn lookup(&self, p: Vec3) -> SLookup {
        self.lookup_normalised(self.normalise(p))
    }

    /// Lookup with a point already in normalised `[0, 1]^3` coordinates.
    ///
    /// Node `d` levels below the root splits on axis `d % 3` (the tree's invariant, checked
    /// when a tree is read), and a midpoint split of `[0, 1]` sends a coordinate to child 1
    /// exactly when its next binary digit is 1. So the descent reads the digits of each
    /// coordinate as a 32-bit fixed-point number, three levels (x, y, z) per round, with no
    /// data-dependent branch and no float arithmetic in the loop. At most 20 splits per axis
    /// ([`crate::sdtree`]'s depth limit) use only digits that the fixed-point form holds
    /// exactly (`1.0` saturates to all ones: the last child at every level); the leaf's box is
    /// its digit prefix, exact in f32.
    #[inline]
    pub fn lookup_normalised(&self, x: Vec3) -> SLookup {
        // `as` saturates: 1.0 becomes u32::MAX, the all-ones digit string.
        let fixed = |v: f32| (v * 4_294_967_296.0) as u32;
        let digits = [fixed(x.x), fixed(x.y), fixed(x.z)];
        let mut bits = digits;
        let mut idx = 0usize;
        let mut depth = 0u32;
        if !self.jump.is_empty() {
            // The top levels at once: the cell of the leading JUMP_LEVELS digits per axis.
            let s = 32 - JUMP_LEVELS;
            let cell = (digits[0] >> s) as usize
                | ((digits[1] >> s) as usize) << JUMP_LEVELS
                | ((digits[2] >> s) as usize) << (2 * JUMP_LEVELS);
            idx = self.jump[cell] as usize;
            depth = self.nodes[idx].depth;
            // An inner node here is at depth 3 * JUMP_LEVELS: those digits are used up, and
            // the next level splits on x again. (At a leaf the loop below stops at once.)
            bits = digits.map(|d| d << JUMP_LEVELS);
        }
        'descend: loop {
            for b in &mut bits {
                let n = &self.nodes[idx];
                if n.is_leaf() {
                    break 'descend;
                }
                idx = n.children[(*b >> 31) as usize] as usize;
                *b <<= 1;
                depth += 1;
            }
        }
        // Splits per axis: x takes levels 0, 3, 6, ..., y 1, 4, ..., z 2, 5, ...
        let k = [depth.div_ceil(3), (depth + 1) / 3, depth / 3];
        let mut org = [0.0f32; 3];
        let mut ext = [0.0f32; 3];
        for a in 0..3 {
            let prefix = if k[a] == 0 {
                0
            } else {
                digits[a] & (u32::MAX << (32 - k[a]))
            };
            org[a] = prefix as f32 * (1.0 / 4_294_967_296.0);
            ext[a] = f32::from_bits((127 - k[a]) << 23); // 2^-k
        }
        SLookup {
            leaf: self.nodes[idx].leaf,
            node: idx as u32,
            min: self.min + Vec3::from_array(org) * self.size,
            extent: Vec3::from_array(ext) * self.size,
        }
    }

    /// Normalised box (`min`, `extent`) of node `node`, by walking from the root.
    pub fn node_box_normalised(&self, node: u32) -> ([f32; 3], [f32; 3]) {
        // parent links are not stored; find the path by a DFS (used rarely: tests, splats use traversal)
        let mut stack = vec![(0u32, [0.0f32; 3], [1.0f32; 3])];
        while let Some((n, o, e)) = stack.pop() {
            if n == node {
                return (o, e);
            }
            let sn = &self.nodes[n as usize];
            if !sn.is_leaf() {
                let (o2, e2) = upper_half(o, e, sn.axis as usize);
                stack.push((sn.children[0], o, e2));
                stack.push((sn.children[1], o2, e2));
            }
        }
        ([0.0; 3], [1.0; 3])
    }

    /// Splits leaf node `node` at its midpoint: child 0 keeps payload `leaf0`, child 1 gets
    /// `leaf1`. Returns the two child node indices.
    pub(crate) fn split(&mut self, node: u32, leaf0: u32, leaf1: u32) -> [u32; 2] {
        // The jump table no longer describes the tree (see `jump`).
        self.jump.clear();
        let n = self.nodes.len() as u32;
        let parent = &self.nodes[node as usize];
        let axis = ((parent.axis as u32 + 1) % 3) as u8;
        let depth = parent.depth + 1;
        // `node` splits on its own `axis`; its children split on the next axis
        self.nodes.push(SNode {
            axis,
            children: [0, 0],
            leaf: leaf0,
            depth,
        });
        self.nodes.push(SNode {
            axis,
            children: [0, 0],
            leaf: leaf1,
            depth,
        });
        let p = &mut self.nodes[node as usize];
        p.children = [n, n + 1];
        p.leaf = u32::MAX;
        [n, n + 1]
    }

    /// Visits every leaf whose box (in normalised coordinates, with faces on the domain border
    /// extended to infinity) overlaps the normalised box `[lo, hi]`, calling `f(leaf, overlap
    /// volume)` for overlaps > 0.
    pub fn for_each_overlap(&self, lo: [f32; 3], hi: [f32; 3], mut f: impl FnMut(u32, f64)) {
        let (lo, hi) = (lo.map(f64::from), hi.map(f64::from));
        let mut ov = [0.0f64; 3];
        for (a, ov) in ov.iter_mut().enumerate() {
            *ov = axis_overlap(lo[a], hi[a], 0.0, 1.0);
        }
        if !ov.iter().all(|&x| x > 0.0) {
            return;
        }
        // While the box lies within one child, that child is the only one it overlaps, along
        // the split axis by exactly as much as along the parent's (`hi - lo`, the faces
        // outside the box): descend without computing overlaps. First the jump table's
        // levels when the box lies within one of its cells, then level by level.
        let (mut n, mut o, mut e) = (0u32, [0.0f64; 3], [1.0f64; 3]);
        let cells = (1u32 << JUMP_LEVELS) as f64;
        if !self.jump.is_empty() {
            let k = lo.map(|x| (x * cells).floor().clamp(0.0, cells - 1.0));
            if (0..3).all(|a| k[a] == cells - 1.0 || hi[a] <= (k[a] + 1.0) / cells) {
                let cell = k[0] as usize
                    | (k[1] as usize) << JUMP_LEVELS
                    | (k[2] as usize) << (2 * JUMP_LEVELS);
                n = self.jump[cell];
                // an inner node there is at depth 3 * JUMP_LEVELS: the cell itself (a leaf
                // above that depth contains the box and ends the descent at once)
                o = k.map(|x| x / cells);
                e = [1.0 / cells; 3];
            }
        }
        loop {
            let sn = &self.nodes[n as usize];
            if sn.is_leaf() {
                break;
            }
            let a = sn.axis as usize;
            let mid = o[a] + e[a] * 0.5;
            if hi[a] <= mid {
                n = sn.children[0];
            } else if lo[a] >= mid {
                n = sn.children[1];
                o[a] = mid;
            } else {
                break;
            }
            e[a] *= 0.5;
        }
        self.overlap_below(n, o, e, ov, lo, hi, &mut f);
    }

    /// [`STree::for_each_overlap`] below node `n` (box origin `o`, extent `e`), whose overlap
    /// with the query box along each axis is `ov` (all > 0). A child differs from its parent
    /// along the split axis only, so only that overlap is recomputed; the volume is the
    /// product of the three in axis order. The recursion is as deep as the tree (at most
    /// [`crate::sdtree::MAX_SPATIAL_DEPTH`]); children are visited 0 before 1.
    #[allow(clippy::too_many_arguments)]
    fn overlap_below(
        &self,
        n: u32,
        o: [f64; 3],
        e: [f64; 3],
        ov: [f64; 3],
        lo: [f64; 3],
        hi: [f64; 3],
        f: &mut impl FnMut(u32, f64),
    ) {
        let sn = &self.nodes[n as usize];
        if sn.is_leaf() {
            f(sn.leaf, 1.0 * ov[0] * ov[1] * ov[2]);
            return;
        }
        let a = sn.axis as usize;
        let (o1, e2) = upper_half(o, e, a);
        for (c, oc) in [(sn.children[0], o), (sn.children[1], o1)] {
            let mut ovc = ov;
            ovc[a] = axis_overlap(lo[a], hi[a], oc[a], e2[a]);
            if ovc[a] > 0.0 {
                self.overlap_below(c, oc, e2, ovc, lo, hi, f);
            }
        }
    }
}

/// The upper child of the box (`o`, `e`) split at its midpoint along `axis`, as (origin,
/// extent); the lower child keeps `o` with the same extent. One rule for every walk that
/// tracks node boxes (f32 in the normalised lookups, f64 in the overlap walks).
#[inline]
pub(crate) fn upper_half<T>(o: [T; 3], e: [T; 3], axis: usize) -> ([T; 3], [T; 3])
where
    T: Copy + std::ops::Add<Output = T> + std::ops::Mul<Output = T> + From<f32>,
{
    let mut e2 = e;
    e2[axis] = e[axis] * T::from(0.5);
    let mut o2 = o;
    o2[axis] = o[axis] + e2[axis];
    (o2, e2)
}

/// Overlap of `[lo, hi]` with a node's interval `[o, o + e]` along one axis, the node's faces
/// on the domain border (0 or 1) extended to infinity.
#[inline]
fn axis_overlap(lo: f64, hi: f64, o: f64, e: f64) -> f64 {
    let l = if o <= 0.0 { f64::NEG_INFINITY } else { o };
    let h = if o + e >= 1.0 { f64::INFINITY } else { o + e };
    (hi.min(h) - lo.max(l)).max(0.0)
}
