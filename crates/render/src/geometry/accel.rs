//! The scene's acceleration structure: one CWBVH (obvhs) over every triangle
//! of every mesh, plus the analytic shapes.

use std::sync::Arc;
use std::time::Duration;

use glam::{Vec2, Vec3, Vec3A};
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::rt_triangle::RtTriangle;
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;
use pathfarm_scene::TriangleMesh;

use super::triangle::{self, TriShade};
use super::{Analytic, Hit, Ray, SurfaceInteraction};

/// Geometry of one shape, as the renderer keeps it.
#[derive(Clone, Debug)]
pub enum ShapeGeom {
    /// A triangle mesh (shared with the scene description), in world space.
    Mesh(Arc<TriangleMesh>),
    /// A sphere or disk, intersected in closed form.
    Analytic(Analytic),
}

/// The scene's geometry, ready for ray queries: every mesh triangle in one BVH, the analytic
/// shapes beside it, and each shape's geometry by shape index.
pub struct Accel {
    /// The CWBVH's nodes, decoded for traversal.
    nodes: Vec<Node>,
    /// Triangles in BVH primitive order, for intersection in batches.
    tris: TriSoa,
    /// Shape, triangle within the shape and hit-independent shading data
    /// of each BVH primitive.
    prims: Vec<PrimInfo>,
    /// Analytic shapes with their shape index.
    analytic: Vec<(u32, Analytic)>,
    shapes: Vec<ShapeGeom>,
    bounds: (Vec3, Vec3),
    /// The scene's length scale for ray offsets, see [`super::offset_origin`].
    offset_floor: f32,
    /// So few triangles ([`FLAT_MAX`]) that testing them all beats walking the
    /// BVH: rays are tested against every triangle, in BVH primitive order.
    flat: bool,
}

/// Scenes with at most this many triangles are intersected without the BVH.
const FLAT_MAX: usize = 64;

/// Rays per group in [`Accel::intersect_many`] and [`Accel::unoccluded_many`]: 16 beat 8 by
/// 16 % samples/CPU-s on the Cornell box (AMD Zen 4, AVX-512), 32 were within noise of 16;
/// with AVX2 (Zen 3) 16 and 8 are within noise.
const STREAM: usize = 16;

/// Whether [`Accel::build_with`] builds the BVH.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bvh {
    /// Build it: rays can be traced.
    Build,
    /// Skip it: only the shapes and the scene's bounds are kept, and no ray hits a triangle.
    Skip,
}

impl Accel {
    /// Builds the BVH over every triangle of `shapes` and keeps the shapes, indexed as given (the
    /// scene description's shape order).
    pub fn build(shapes: Vec<ShapeGeom>) -> Self {
        Self::build_with(shapes, Bvh::Build)
    }

    /// [`Accel::build`], or with [`Bvh::Skip`] only the shapes and their bounds (the same
    /// bounds, bit for bit): an accelerator that no ray hits, for reading a scene's settings
    /// without the cost of its BVH.
    pub fn build_with(shapes: Vec<ShapeGeom>, bvh: Bvh) -> Self {
        let mut tris = Vec::new();
        let mut refs = Vec::new();
        let mut analytic = Vec::new();
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        for (s, shape) in shapes.iter().enumerate() {
            match shape {
                ShapeGeom::Mesh(m) => {
                    for (t, idx) in m.indices.iter().enumerate() {
                        let v = idx.map(|i| m.positions[i as usize]);
                        for p in v {
                            lo = lo.min(p);
                            hi = hi.max(p);
                        }
                        tris.push(Triangle {
                            v0: v[0].into(),
                            v1: v[1].into(),
                            v2: v[2].into(),
                        });
                        refs.push((s as u32, t as u32));
                    }
                }
                ShapeGeom::Analytic(a) => {
                    let (l, h) = a.bounds();
                    lo = lo.min(l);
                    hi = hi.max(h);
                    analytic.push((s as u32, a.clone()));
                }
            }
        }
        let (nodes, tris, prims) = if tris.is_empty() || matches!(bvh, Bvh::Skip) {
            (Vec::new(), TriSoa::default(), Vec::new())
        } else {
            let bvh = build_cwbvh_from_tris(
                &tris,
                BvhBuildParams::slow_build(),
                &mut Duration::default(),
            );
            let ordered = TriSoa::new(
                bvh.primitive_indices
                    .iter()
                    .map(|&i| RtTriangle::from(&tris[i as usize])),
            );
            let prims = bvh
                .primitive_indices
                .iter()
                .map(|&i| {
                    let (shape, tri) = refs[i as usize];
                    let ShapeGeom::Mesh(m) = &shapes[shape as usize] else {
                        unreachable!("BVH primitives are mesh triangles")
                    };
                    PrimInfo {
                        shape,
                        tri,
                        shade: TriShade::new(m, tri as usize),
                    }
                })
                .collect();
            (bvh.nodes.iter().map(Node::new).collect(), ordered, prims)
        };
        if lo.x > hi.x {
            lo = Vec3::ZERO;
            hi = Vec3::ZERO;
        }
        let flat = tris.len <= FLAT_MAX;
        Self {
            nodes,
            tris,
            prims,
            analytic,
            shapes,
            bounds: (lo, hi),
            offset_floor: offset_floor(lo, hi),
            flat,
        }
    }

    /// Axis-aligned bounds of the whole scene.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }

    /// The floor of spawned rays' offsets ([`super::offset_origin`]): 1 for scenes that reach at
    /// least 1 from the origin, the scene's extent for smaller ones.
    #[inline]
    pub fn offset_floor(&self) -> f32 {
        self.offset_floor
    }

    /// The geometry of shape `i` (its index in the scene description).
    pub fn shape(&self, i: u32) -> &ShapeGeom {
        &self.shapes[i as usize]
    }

    /// Closest hit along the ray. `ANALYTIC` is false for scenes without
    /// analytic shapes, removing their test from the hot loop.
    #[inline]
    pub fn intersect<const ANALYTIC: bool>(&self, ray: &Ray) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        let mut tmax = ray.tmax;
        if !self.tris.is_empty() {
            let mut r = TraceRay::new(ray, self.offset_floor);
            let (prim, bary) = self.traverse::<false>(&mut r);
            if prim != u32::MAX {
                best = Some(self.triangle_hit(prim, r.tmax, bary));
                tmax = r.tmax;
            }
        }
        if ANALYTIC {
            self.intersect_analytic(ray, tmax, &mut best);
        }
        best
    }

    #[inline(always)]
    fn triangle_hit(&self, prim: u32, t: f32, bary: Vec2) -> Hit {
        let info = &self.prims[prim as usize];
        Hit {
            t,
            shape: info.shape,
            prim: info.tri,
            bvh_prim: prim,
            bary,
        }
    }

    /// The analytic shapes' part of a closest-hit query whose triangles gave `best` at `tmax`.
    #[inline(always)]
    fn intersect_analytic(&self, ray: &Ray, tmax: f32, best: &mut Option<Hit>) {
        let mut r = *ray;
        r.tmax = tmax;
        for (s, a) in &self.analytic {
            let t = a.intersect(&r);
            if t < r.tmax {
                r.tmax = t;
                *best = Some(Hit {
                    t,
                    shape: *s,
                    prim: 0,
                    bvh_prim: u32::MAX,
                    bary: Vec2::ZERO,
                });
            }
        }
    }

    /// Whether nothing blocks the ray between `tmin` and `tmax`: an any-hit query, for shadow
    /// rays.
    /// `ANALYTIC` is false for scenes without analytic shapes, as in [`Accel::intersect`].
    #[inline]
    pub fn unoccluded<const ANALYTIC: bool>(&self, ray: &Ray) -> bool {
        if !self.tris.is_empty()
            && self
                .traverse::<true>(&mut TraceRay::new(ray, self.offset_floor))
                .0
                != u32::MAX
        {
            return false;
        }
        !ANALYTIC || self.analytic_unoccluded(ray)
    }

    #[inline(always)]
    fn analytic_unoccluded(&self, ray: &Ray) -> bool {
        !self
            .analytic
            .iter()
            .any(|(_, a)| a.intersect(ray) < ray.tmax)
    }

    /// [`Accel::intersect`] of every ray: `hits[i]` for `rays[i]`, the same hits as one
    /// query at a time. In scenes with few triangles, groups of rays are tested
    /// against each triangle side by side (vectorised across rays).
    pub fn intersect_many<const ANALYTIC: bool>(&self, rays: &[Ray], hits: &mut [Option<Hit>]) {
        if !self.flat || self.tris.is_empty() {
            for (ray, hit) in rays.iter().zip(hits.iter_mut()) {
                *hit = self.intersect::<ANALYTIC>(ray);
            }
            return;
        }
        for (group, out) in rays.chunks(STREAM).zip(hits.chunks_mut(STREAM)) {
            let g = RayGroup::new(group);
            let (prim, [t, u, v]) = self.stream_closest(&g);
            for (i, (ray, hit)) in group.iter().zip(out.iter_mut()).enumerate() {
                let mut best = None;
                let mut tmax = ray.tmax;
                if prim[i] != u32::MAX {
                    best = Some(self.triangle_hit(prim[i], t[i], Vec2::new(u[i], v[i])));
                    tmax = t[i];
                }
                if ANALYTIC {
                    self.intersect_analytic(ray, tmax, &mut best);
                }
                *hit = best;
            }
        }
    }

    /// [`Accel::unoccluded`] of every ray, vectorised across rays like
    /// [`Accel::intersect_many`].
    pub fn unoccluded_many<const ANALYTIC: bool>(&self, rays: &[Ray], out: &mut [bool]) {
        if !self.flat || self.tris.is_empty() {
            for (ray, o) in rays.iter().zip(out.iter_mut()) {
                *o = self.unoccluded::<ANALYTIC>(ray);
            }
            return;
        }
        for (group, out) in rays.chunks(STREAM).zip(out.chunks_mut(STREAM)) {
            let blocked = self.stream_any(&RayGroup::new(group));
            for (i, (ray, o)) in group.iter().zip(out.iter_mut()).enumerate() {
                *o = !blocked[i] && (!ANALYTIC || self.analytic_unoccluded(ray));
            }
        }
    }

    /// Every triangle against one ray, block by block ([`Accel::flat`] scenes): the
    /// closest hit, the lowest primitive index among equally close ones (as
    /// [`Accel::stream_closest`] decides).
    #[inline(always)]
    fn test_all<const ANY_HIT: bool>(&self, r: &mut TraceRay) -> (u32, Vec2) {
        let mut found = u32::MAX;
        let mut bary = Vec2::ZERO;
        let nb = self.tris.blocks.len();
        for block in 0..nb {
            let lanes = if block + 1 == nb {
                LANE_MASK >> (nb * LANES - self.tris.len)
            } else {
                LANE_MASK
            };
            if self.test_block::<ANY_HIT>(block, lanes, r, &mut found, &mut bary) {
                break;
            }
        }
        (found, bary)
    }

    /// The triangles `lanes` of block `block` against `r`. Any-hit: true at the first
    /// hit, with `found` its primitive. Closest hit: each hit strictly closer than
    /// `r.tmax`, lowest lane first, narrows `r.tmax` and becomes `found` (with `bary`).
    #[inline(always)]
    fn test_block<const ANY_HIT: bool>(
        &self,
        block: usize,
        lanes: u32,
        r: &mut TraceRay,
        found: &mut u32,
        bary: &mut Vec2,
    ) -> bool {
        let (mut hits, [t, u, v]) = self.tris.intersect_block(block, lanes, r);
        if ANY_HIT && hits != 0 {
            *found = (block * LANES) as u32 + hits.trailing_zeros();
            return true;
        }
        while hits != 0 {
            let i = hits.trailing_zeros() as usize;
            hits &= hits - 1;
            if t[i] < r.tmax {
                r.tmax = t[i];
                *found = (block * LANES + i) as u32;
                *bary = Vec2::new(u[i], v[i]);
            }
        }
        false
    }

    /// Closest hits of a group of rays against every triangle, in primitive order: a
    /// triangle replaces a lane's hit when strictly closer, as [`Accel::test_all`] does.
    #[inline(always)]
    fn stream_closest(&self, g: &RayGroup) -> ([u32; STREAM], [[f32; STREAM]; 3]) {
        let mut prim = [u32::MAX; STREAM];
        let (mut best, mut bu, mut bv) = (g.tmax, [0.0f32; STREAM], [0.0f32; STREAM]);
        for j in 0..self.tris.len {
            let tri = self.tris.get(j);
            for i in 0..STREAM {
                let (ok, t, u, v) = tri_test(&tri, g, i);
                let take = ok & (t < best[i]);
                // Blends by bit mask, not `if`: the compiler turns a conditional update
                // into a masked store, which is slow on AMD Zen.
                let m = 0u32.wrapping_sub(take as u32);
                let blend =
                    |old: f32, new: f32| f32::from_bits(old.to_bits() & !m | new.to_bits() & m);
                best[i] = blend(best[i], t);
                bu[i] = blend(bu[i], u);
                bv[i] = blend(bv[i], v);
                prim[i] = prim[i] & !m | j as u32 & m;
            }
        }
        (prim, [best, bu, bv])
    }

    /// Whether any triangle blocks each ray of a group.
    #[inline(always)]
    fn stream_any(&self, g: &RayGroup) -> [bool; STREAM] {
        // 32-bit lanes, not bools: bools would be packed to bytes and back at every triangle.
        let mut blocked = [0u32; STREAM];
        for j in 0..self.tris.len {
            let tri = self.tris.get(j);
            for (i, b) in blocked.iter_mut().enumerate() {
                let (ok, t, _, _) = tri_test(&tri, g, i);
                *b |= (ok & (t <= g.tmax[i])) as u32;
            }
        }
        blocked.map(|b| b != 0)
    }

    /// Walks the CWBVH for `r`: closest hit (narrowing `r.tmax`) or, with `ANY_HIT`,
    /// the first hit found. Returns the BVH primitive (`u32::MAX`: none) and its
    /// barycentrics.
    ///
    /// At each node the ray meets the eight child boxes at once; the triangles of the hit
    /// leaves are tested at once, and the hit inner children are visited nearest box
    /// first (closest hit), the others kept on a stack with their entry distance. A
    /// kept child whose box starts beyond the closest hit found meanwhile is dropped
    /// without being read, the main saving over obvhs' traversal, whose stack keeps
    /// groups of siblings in a fixed per-octant order and reads every one of them.
    #[inline(always)]
    fn traverse<const ANY_HIT: bool>(&self, r: &mut TraceRay) -> (u32, Vec2) {
        if self.flat {
            return self.test_all::<ANY_HIT>(r);
        }
        // Not zeroed (a memset of 1.8 KB per ray): entries below `sp` are always written.
        let mut stack = [std::mem::MaybeUninit::<(u32, f32)>::uninit(); STACK];
        let mut sp = 0usize;
        let mut node = 0u32;
        let mut found = u32::MAX;
        let mut bary = Vec2::ZERO;
        loop {
            let n = &self.nodes[node as usize];
            let (mask, near) = n.intersect(r);

            // Primitives of the hit leaves (bit j: BVH index base + j),
            // by blocks of LANES, lowest first.
            let mut prims = mask & 0x00ff_ffff;
            let base = n.prim_base;
            while prims != 0 {
                let j = prims.trailing_zeros();
                let first = base + j;
                let (block, lane) = (first / LANES as u32, first % LANES as u32);
                // Bits j.. of `prims` are lanes `lane`.. of the block.
                let in_block = LANE_MASK >> lane;
                let lanes = ((prims >> j) & in_block) << lane;
                prims &= !(in_block << j);
                if self.test_block::<ANY_HIT>(block as usize, lanes, r, &mut found, &mut bary) {
                    return (found, bary);
                }
            }

            // Hit inner children: slot s is bit s; child index from the node's inner mask.
            let mut inner = mask >> 24;
            let child = |s: u32| n.child_base + (n.imask & ((1u32 << s) - 1)).count_ones();
            match inner.count_ones() {
                0 => loop {
                    if sp == 0 {
                        return (found, bary);
                    }
                    sp -= 1;
                    // SAFETY: entries 0..sp were written by pushes (below).
                    let (c, t) = unsafe { stack[sp].assume_init() };
                    if t <= r.tmax {
                        node = c;
                        break;
                    }
                },
                1 => node = child(inner.trailing_zeros()),
                2 => {
                    let (s0, s1) = (inner.trailing_zeros(), 31 - inner.leading_zeros());
                    let (a, b) = (
                        (child(s0), near[s0 as usize]),
                        (child(s1), near[s1 as usize]),
                    );
                    // The nearer one next (on a tie, the lower slot), the other kept.
                    let (next, keep) = if ANY_HIT || a.1 <= b.1 {
                        (a, b)
                    } else {
                        (b, a)
                    };
                    stack[sp].write(keep);
                    sp += 1;
                    node = next.0;
                }
                k => {
                    // Push all but the nearest, farthest first, so the nearest kept
                    // child is popped first.
                    let mut hits = [(0u32, 0f32); 8];
                    for h in hits.iter_mut().take(k as usize) {
                        let s = inner.trailing_zeros();
                        inner &= inner - 1;
                        *h = (child(s), near[s as usize]);
                    }
                    let hits = &mut hits[..k as usize];
                    if !ANY_HIT {
                        // Insertion sort, farthest first (ties keep slot order).
                        for i in 1..hits.len() {
                            let mut j = i;
                            while j > 0 && hits[j - 1].1 < hits[j].1 {
                                hits.swap(j - 1, j);
                                j -= 1;
                            }
                        }
                    }
                    let (last, rest) = hits.split_last().expect("k >= 2");
                    for &e in rest {
                        stack[sp].write(e);
                        sp += 1;
                    }
                    node = last.0;
                }
            }
        }
    }

    /// Shading data at a hit.
    #[inline(always)]
    pub fn interaction(&self, ray: &Ray, hit: &Hit) -> SurfaceInteraction {
        let p = ray.o + ray.d * hit.t;
        let (ng, ns, uv) = match &self.shapes[hit.shape as usize] {
            ShapeGeom::Mesh(m) => {
                // The intersection test's barycentrics.
                let pre = &self.prims[hit.bvh_prim as usize].shade;
                triangle::shade(m, hit.prim as usize, hit.bary, pre)
            }
            ShapeGeom::Analytic(a) => a.shade(p),
        };
        SurfaceInteraction {
            p,
            t: hit.t,
            ng,
            ns,
            uv,
            shape: hit.shape,
        }
    }

    /// The surface's partial derivatives `(dp/du, dp/dv)` at `si` (on triangle `prim` of its
    /// shape, [`Hit::prim`]), in world space, as Mitsuba
    /// computes them: from a triangle's vertex uvs, from a sphere's parameterisation, else
    /// (no uvs, a degenerate uv triangle, disks and cylinders) any tangent frame of the
    /// geometric normal. Only bump and normal maps need them, so they are not part of every
    /// interaction.
    pub fn uv_tangents(&self, si: &SurfaceInteraction, prim: u32) -> (Vec3, Vec3) {
        let fallback = || {
            let f = pathfarm_bsdf::Frame::from_normal(si.ng);
            (f.s, f.t)
        };
        match &self.shapes[si.shape as usize] {
            ShapeGeom::Mesh(m) => triangle::uv_tangents(m, prim as usize).unwrap_or_else(fallback),
            ShapeGeom::Analytic(a) => a.uv_tangents(si.p).unwrap_or_else(fallback),
        }
    }
}

/// A CWBVH node decoded for traversal: the child boxes in world space as
/// f32 rows (no per-visit dequantisation) and each child's contribution to
/// the hit mask precomputed. Same topology, slot order and indices as the
/// obvhs node it comes from; 256 bytes.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Node {
    /// Child boxes by axis, then min/max, then slot. Empty slots hold a
    /// zero box (their `code` is 0, so a hit on it adds nothing).
    bounds: [[[f32; 8]; 2]; 3],
    /// Per slot, its bits of the hit mask:
    /// for a leaf its primitives (unary count shifted to its offset from
    /// `prim_base`, obvhs' encoding), `0xff00_0000` for an internal child
    /// (narrowed to its slot's bit by [`SLOT_ORDER`]), 0
    /// for an empty slot.
    code: [u32; 8],
    /// Index of the first internal child in `Accel::nodes`.
    child_base: u32,
    /// BVH index of the first leaf primitive.
    prim_base: u32,
    /// Bit per slot: the child is an internal node.
    imask: u32,
}

impl Node {
    fn new(n: &CwBvhNode) -> Self {
        let e = n.compute_extent();
        let q = [
            [n.child_min_x, n.child_max_x],
            [n.child_min_y, n.child_max_y],
            [n.child_min_z, n.child_max_z],
        ];
        let mut bounds = [[[0.0f32; 8]; 2]; 3];
        let mut code = [0u32; 8];
        for slot in 0..8 {
            let meta = n.child_meta[slot];
            if meta == 0 {
                continue;
            }
            code[slot] = if n.imask & (1 << slot) != 0 {
                0xff00_0000
            } else {
                ((meta >> 5) as u32) << (meta & 0x1f)
            };
            for axis in 0..3 {
                for side in 0..2 {
                    // q * e is exact (e is a power of two).
                    bounds[axis][side][slot] = n.p[axis] + q[axis][side][slot] as f32 * e[axis];
                }
            }
        }
        Self {
            bounds,
            code,
            child_base: n.child_base_idx,
            prim_base: n.primitive_base_idx,
            imask: n.imask as u32,
        }
    }

    /// Ray against the eight child boxes: the hit mask (leaf primitives in the low 24
    /// bits, obvhs' encoding; bit `24 + s` for a hit inner child in slot `s`) and each
    /// box's entry distance. Boxes are culled beyond `tmax` and before the ray's
    /// `box_floor` (obvhs' floor of 1e-4, scaled for scenes smaller than 1).
    ///
    /// Written over all eight slots at once so that it compiles to 8-wide
    /// vector code: per axis both planes' distances by one FMA each (near
    /// and far by min/max: no per-ray plane selection, so the loads have
    /// fixed offsets), then the hit lanes' codes ORed.
    #[inline(always)]
    fn intersect(&self, ray: &TraceRay) -> (u32, [f32; 8]) {
        // `if a > b { a } else { b }` rather than f32::max: no NaN fix-up,
        // one vmaxps (operands are finite: inv_dir is clamped).
        #[inline(always)]
        fn max(a: f32, b: f32) -> f32 {
            if a > b {
                a
            } else {
                b
            }
        }
        #[inline(always)]
        fn min(a: f32, b: f32) -> f32 {
            if a < b {
                a
            } else {
                b
            }
        }
        // One FMA where the target has it; a multiply and an add where it does not, since
        // `f32::mul_add` without the `fma` target feature is a call into a software fmaf
        // (measured: 24 % of a guided render on veach-ajar, 2x slower per sample, for a
        // build without `-C target-cpu=native`, e.g. one made outside the workspace).
        #[inline(always)]
        fn plane(a: f32, b: f32, c: f32) -> f32 {
            #[cfg(target_feature = "fma")]
            {
                a.mul_add(b, c)
            }
            #[cfg(not(target_feature = "fma"))]
            {
                a * b + c
            }
        }
        let [[lx, hx], [ly, hy], [lz, hz]] = &self.bounds;
        let (inv, org) = (ray.inv_dir, ray.neg_org_inv);
        let mut hit_mask = 0u32;
        let mut near = [0.0f32; 8];
        for i in 0..8 {
            let (ax, bx) = (plane(lx[i], inv.x, org.x), plane(hx[i], inv.x, org.x));
            let (ay, by) = (plane(ly[i], inv.y, org.y), plane(hy[i], inv.y, org.y));
            let (az, bz) = (plane(lz[i], inv.z, org.z), plane(hz[i], inv.z, org.z));
            let (t0x, t1x) = (min(ax, bx), max(ax, bx));
            let (t0y, t1y) = (min(ay, by), max(ay, by));
            let (t0z, t1z) = (min(az, bz), max(az, bz));
            let t0 = max(max(t0x, t0y), max(t0z, ray.box_floor));
            let t1 = min(min(t1x, t1y), min(t1z, ray.tmax));
            near[i] = t0;
            let bits = self.code[i] & SLOT_ORDER[i];
            hit_mask |= if t0 <= t1 { bits } else { 0 };
        }
        (hit_mask, near)
    }
}

/// Per slot `s`, the mask that narrows a node's `code` to its bits in the hit mask:
/// all leaf bits and, for an inner child, bit `24 + s`.
static SLOT_ORDER: [u32; 8] = {
    let mut row = [0u32; 8];
    let mut s = 0;
    while s < 8 {
        row[s] = 0x00ff_ffff | 1 << (24 + s);
        s += 1;
    }
    row
};

/// A ray as the traversal uses it, with what the node and triangle tests
/// need precomputed once per ray.
struct TraceRay {
    origin: Vec3A,
    direction: Vec3A,
    /// 1 / direction, clamped to +-2^23 where a component's magnitude is at
    /// most f32::EPSILON (obvhs' `safe_inverse`; keeps box distances finite).
    inv_dir: Vec3A,
    /// `-origin * inv_dir`: box planes become distances by one FMA.
    neg_org_inv: Vec3A,
    tmin: f32,
    /// End of the ray; shortened to the closest hit found so far.
    tmax: f32,
    /// Lower bound on the entry distance of a box: obvhs' 1e-4 times the scene's
    /// [`Accel::offset_floor`] (so 1e-4 at unit scale and above). A fixed 1e-4 culled
    /// every box within 1e-4 of the ray's origin, in a scene 1e-4 across nearly all of it.
    box_floor: f32,
}

impl TraceRay {
    #[inline(always)]
    fn new(ray: &Ray, offset_floor: f32) -> Self {
        let direction = Vec3A::from(ray.d);
        let tiny = direction.abs().cmple(Vec3A::splat(f32::EPSILON));
        let clamped = Vec3A::splat(1.0 / f32::EPSILON).copysign(direction);
        let inv_dir = Vec3A::select(tiny, clamped, Vec3A::ONE / direction);
        let origin = Vec3A::from(ray.o);
        Self {
            origin,
            direction,
            inv_dir,
            neg_org_inv: -origin * inv_dir,
            tmin: ray.tmin,
            tmax: ray.tmax,
            box_floor: 1e-4 * offset_floor,
        }
    }
}

/// Entries of the traversal stack: a node visit keeps at most 7 children, and
/// obvhs' CWBVH is at most 32 levels deep (checked by its validation).
const STACK: usize = 7 * 32;

/// A BVH primitive: its triangle and what shading needs of it.
struct PrimInfo {
    shape: u32,
    /// Triangle index within the shape's mesh.
    tri: u32,
    shade: TriShade,
}

/// Batch width of the triangle test (8: measured faster than 4 on both
/// benchmark scenes, with AVX2).
/// A group of up to [`STREAM`] rays in structure-of-arrays form; unused lanes have
/// an empty interval.
struct RayGroup {
    o: [[f32; STREAM]; 3],
    d: [[f32; STREAM]; 3],
    tmin: [f32; STREAM],
    tmax: [f32; STREAM],
}

impl RayGroup {
    #[inline(always)]
    fn new(rays: &[Ray]) -> Self {
        let mut g = RayGroup {
            o: [[0.0; STREAM]; 3],
            d: [[0.0; STREAM]; 3],
            tmin: [1.0; STREAM],
            tmax: [-1.0; STREAM],
        };
        for (i, r) in rays.iter().enumerate() {
            for a in 0..3 {
                g.o[a][i] = r.o[a];
                g.d[a][i] = r.d[a];
            }
            g.tmin[i] = r.tmin;
            g.tmax[i] = r.tmax;
        }
        g
    }
}

/// One triangle (vertex 0, the two edges from it, the unnormalised normal).
struct Tri {
    v0: [f32; 3],
    e1: [f32; 3],
    e2: [f32; 3],
    ng: [f32; 3],
}

/// Ray `i` of `g` against `tri`: [`tri_lane`].
#[inline(always)]
fn tri_test(tri: &Tri, g: &RayGroup, i: usize) -> (bool, f32, f32, f32) {
    let o = [g.o[0][i], g.o[1][i], g.o[2][i]];
    let d = [g.d[0][i], g.d[1][i], g.d[2][i]];
    tri_lane(o, d, g.tmin[i], tri)
}

/// The ray (`o`, `d`) against `tri`: whether it hits inside at a distance of at least
/// `tmin`, with that distance and the barycentrics (weights of vertices 1 and 2). The
/// arithmetic of obvhs' `RtTriangle::intersect` (Möller-Trumbore on its edge layout, the
/// same sign-bit inside test), on plain numbers and branch-free, so that loops over
/// triangles ([`TriSoa::intersect_block`]) or rays ([`Accel::intersect_many`]) vectorise;
/// the one implementation of both, so they find the same hits.
#[inline(always)]
fn tri_lane(o: [f32; 3], d: [f32; 3], tmin: f32, tri: &Tri) -> (bool, f32, f32, f32) {
    let [dx, dy, dz] = d;
    let (cx, cy, cz) = (tri.v0[0] - o[0], tri.v0[1] - o[1], tri.v0[2] - o[2]);
    // r = d x c
    let rx = dy * cz - dz * cy;
    let ry = dz * cx - dx * cz;
    let rz = dx * cy - dy * cx;
    let inv_det = 1.0 / (tri.ng[0] * dx + tri.ng[1] * dy + tri.ng[2] * dz);
    let u = (rx * tri.e2[0] + ry * tri.e2[1] + rz * tri.e2[2]) * inv_det;
    let v = (rx * tri.e1[0] + ry * tri.e1[1] + rz * tri.e1[2]) * inv_det;
    let w = 1.0 - u - v;
    let t = (tri.ng[0] * cx + tri.ng[1] * cy + tri.ng[2] * cz) * inv_det;
    let inside = (u.to_bits() | v.to_bits() | w.to_bits()) & 0x8000_0000 == 0;
    (inside & (inv_det != 0.0) & (t >= tmin), t, u, v)
}

const LANES: usize = 8;
const LANE_MASK: u32 = (1 << LANES) - 1;

/// Triangles in obvhs' `RtTriangle` form (`v0`, `e1 = v0 - v1`,
/// `e2 = v2 - v0`, `ng = e1 x e2`), in blocks of `LANES` consecutive BVH
/// primitives, each block as twelve component rows (v0.x, v0.y, ..., ng.z).
#[derive(Default)]
struct TriSoa {
    len: usize,
    blocks: Vec<TriBlock>,
}

/// One block of `LANES` triangles, aligned for vector loads.
#[derive(Clone, Copy, Default)]
#[repr(C, align(32))]
struct TriBlock([[f32; LANES]; 12]);

impl TriSoa {
    fn new(tris: impl ExactSizeIterator<Item = RtTriangle>) -> Self {
        let len = tris.len();
        let mut blocks = vec![TriBlock::default(); len.div_ceil(LANES)];
        for (i, t) in tris.enumerate() {
            let b = &mut blocks[i / LANES].0;
            for (k, v) in [t.v0, t.e1, t.e2, t.ng].into_iter().enumerate() {
                for (j, x) in v.to_array().into_iter().enumerate() {
                    b[3 * k + j][i % LANES] = x;
                }
            }
        }
        Self { len, blocks }
    }

    fn is_empty(&self) -> bool {
        self.len == 0
    }

    #[inline(always)]
    fn get(&self, j: usize) -> Tri {
        let b = &self.blocks[j / LANES].0;
        let l = j % LANES;
        let at = |k: usize| [b[k][l], b[k + 1][l], b[k + 2][l]];
        Tri {
            v0: at(0),
            e1: at(3),
            e2: at(6),
            ng: at(9),
        }
    }

    /// Tests the triangles of block `block` whose bit is set in `lanes`:
    /// the bits of those hit within [tmin, tmax] and every lane's distance
    /// and barycentrics (weights of vertices 1 and 2).
    /// Per lane the arithmetic of obvhs' `RtTriangle::intersect` (Möller-
    /// Trumbore on its edge layout, the same sign-bit inside test), written
    /// across lanes so that it compiles to vector code.
    #[inline(always)]
    fn intersect_block(&self, block: usize, lanes: u32, r: &TraceRay) -> (u32, [[f32; LANES]; 3]) {
        let (o, d) = (r.origin.to_array(), r.direction.to_array());
        let (mut t, mut bu, mut bv) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
        let mut hits = 0u32;
        for i in 0..LANES {
            let (ok, ti, u, v) = tri_lane(o, d, r.tmin, &self.get(block * LANES + i));
            (t[i], bu[i], bv[i]) = (ti, u, v);
            hits |= ((ok & (ti <= r.tmax)) as u32) << i;
        }
        (hits & lanes, [t, bu, bv])
    }
}

/// The offset floor of a scene with bounds `lo`..`hi`: its largest coordinate magnitude,
/// at most 1 (and 1 when that is not a positive finite number). Ray offsets grow with a
/// point's distance from the origin, but a fixed floor of 1 would make them 20 % of a
/// scene 1e-4 across (its rays would start inside thin objects and skip contact
/// shadows); a floor that shrinks with the scene makes the offset a fixed fraction of the
/// scene at every scale. Scenes reaching 1 or more keep 1 (their renders unchanged).
fn offset_floor(lo: Vec3, hi: Vec3) -> f32 {
    let extent = lo.abs().max(hi.abs()).max_element();
    if extent > 0.0 && extent < 1.0 {
        extent
    } else {
        1.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// A soup of `n` random triangles in the unit cube, as one mesh.
    fn soup(n: usize, rng: &mut Rng) -> Accel {
        let mut positions = Vec::new();
        let mut indices = Vec::new();
        for t in 0..n as u32 {
            let c = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
            for _ in 0..3 {
                let jitter = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - 0.5;
                positions.push(c + jitter * 0.4);
            }
            indices.push([3 * t, 3 * t + 1, 3 * t + 2]);
        }
        let mesh = TriangleMesh {
            positions,
            normals: None,
            uvs: None,
            indices,
            flip_normals: false,
        };
        Accel::build(vec![ShapeGeom::Mesh(Arc::new(mesh))])
    }

    #[test]
    fn an_accelerator_without_bvh_has_the_bounds_of_the_built_one_and_no_hits() {
        let mut rng = Rng::new(7, 1);
        let built = soup(300, &mut rng);
        let shapes = built.shapes.clone();
        let skipped = Accel::build_with(shapes, Bvh::Skip);
        assert_eq!(skipped.bounds(), built.bounds());
        assert_eq!(skipped.offset_floor(), built.offset_floor());
        let rays = random_rays(200, &mut rng);
        assert!(rays.iter().any(|r| built.intersect::<false>(r).is_some()));
        assert!(rays.iter().all(|r| skipped.intersect::<false>(r).is_none()));
    }

    fn random_rays(n: usize, rng: &mut Rng) -> Vec<Ray> {
        (0..n)
            .map(|i| {
                let o = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - 0.5;
                // Aimed into the cube, where the triangles are.
                let target = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
                let d = (target - o).normalize();
                // Every third ray is bounded, as shadow rays are.
                let tmax = if i % 3 == 0 {
                    rng.next_f32()
                } else {
                    f32::INFINITY
                };
                Ray {
                    o,
                    d,
                    tmin: 0.0,
                    tmax,
                }
            })
            .collect()
    }

    #[test]
    fn ray_streams_find_the_hits_of_one_ray_at_a_time() {
        let mut rng = Rng::for_sample(5, 0, 0);
        // Below FLAT_MAX the stream is vectorised across rays; above it, it walks the BVH.
        for n in [1, 13, FLAT_MAX, 300] {
            let accel = soup(n, &mut rng);
            assert_eq!(accel.flat, n <= FLAT_MAX);
            // 203 rays: groups of STREAM and a partial one.
            let rays = random_rays(203, &mut rng);
            let mut hits = vec![None; rays.len()];
            accel.intersect_many::<false>(&rays, &mut hits);
            let mut clear = vec![false; rays.len()];
            accel.unoccluded_many::<false>(&rays, &mut clear);
            let mut found = 0;
            for (i, ray) in rays.iter().enumerate() {
                let one = accel.intersect::<false>(ray);
                let key =
                    |h: Option<Hit>| h.map(|h| (h.t.to_bits(), h.bvh_prim, h.bary.to_array()));
                assert_eq!(key(hits[i]), key(one), "{n} triangles, ray {i}");
                assert_eq!(
                    clear[i],
                    accel.unoccluded::<false>(ray),
                    "{n} triangles, ray {i}"
                );
                assert_eq!(clear[i], one.is_none(), "{n} triangles, ray {i}");
                found += one.is_some() as usize;
            }
            assert!(found > n.min(50), "{n} triangles: only {found} rays hit");
        }
    }

    #[test]
    fn testing_every_triangle_agrees_with_the_bvh() {
        let mut rng = Rng::for_sample(9, 0, 0);
        let mut accel = soup(FLAT_MAX, &mut rng);
        let rays = random_rays(500, &mut rng);
        let flat: Vec<_> = rays.iter().map(|r| accel.intersect::<false>(r)).collect();
        accel.flat = false;
        let mut agree = 0;
        for (ray, f) in rays.iter().zip(&flat) {
            let b = accel.intersect::<false>(ray);
            assert_eq!(f.is_some(), b.is_some());
            if let (Some(f), Some(b)) = (f, b) {
                // The same triangle at the same distance (another one only on a tie).
                assert_eq!(f.t, b.t);
                agree += (f.bvh_prim == b.bvh_prim) as usize;
            }
        }
        assert!(agree > 150, "only {agree} of {} rays hit", rays.len());
    }
}
