//! The scene's acceleration structure: one CWBVH (obvhs) over every triangle
//! of every mesh, plus the analytic shapes.

use std::sync::Arc;
use std::time::Duration;

use glam::{UVec2, Vec3, Vec3A};
use obvhs::cwbvh::node::{extract_byte64, CwBvhNode};
use obvhs::cwbvh::{builder::build_cwbvh_from_tris, CwBvh};
use obvhs::ray::Ray as BRay;
use obvhs::rt_triangle::RtTriangle;
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;
use pathfarm_scene::TriangleMesh;

use super::{triangle, Analytic, Hit, Ray, SurfaceInteraction};

/// Geometry of one shape, as the renderer keeps it.
#[derive(Clone, Debug)]
pub enum ShapeGeom {
    Mesh(Arc<TriangleMesh>),
    Analytic(Analytic),
}

pub struct Accel {
    bvh: CwBvh,
    /// Triangles in BVH primitive order.
    tris: Vec<RtTriangle>,
    /// (shape, triangle within shape) for each entry of `tris`.
    tri_ref: Vec<(u32, u32)>,
    /// Analytic shapes with their shape index.
    analytic: Vec<(u32, Analytic)>,
    shapes: Vec<ShapeGeom>,
    bounds: (Vec3, Vec3),
}

impl Accel {
    pub fn build(shapes: Vec<ShapeGeom>) -> Self {
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
        let (bvh, tris, tri_ref) = if tris.is_empty() {
            (CwBvh::default(), Vec::new(), Vec::new())
        } else {
            let bvh = build_cwbvh_from_tris(
                &tris,
                BvhBuildParams::slow_build(),
                &mut Duration::default(),
            );
            let ordered: Vec<RtTriangle> = bvh
                .primitive_indices
                .iter()
                .map(|&i| RtTriangle::from(&tris[i as usize]))
                .collect();
            let ordered_refs = bvh
                .primitive_indices
                .iter()
                .map(|&i| refs[i as usize])
                .collect();
            (bvh, ordered, ordered_refs)
        };
        if lo.x > hi.x {
            lo = Vec3::ZERO;
            hi = Vec3::ZERO;
        }
        Self {
            bvh,
            tris,
            tri_ref,
            analytic,
            shapes,
            bounds: (lo, hi),
        }
    }

    /// Axis-aligned bounds of the whole scene.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }

    pub fn shape(&self, i: u32) -> &ShapeGeom {
        &self.shapes[i as usize]
    }

    #[inline]
    fn bray(ray: &Ray) -> BRay {
        BRay::new(Vec3A::from(ray.o), Vec3A::from(ray.d), ray.tmin, ray.tmax)
    }

    /// Closest hit along the ray. `ANALYTIC` is false for scenes without
    /// analytic shapes, removing their test from the hot loop.
    #[inline]
    pub fn intersect<const ANALYTIC: bool>(&self, ray: &Ray) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        let mut tmax = ray.tmax;
        if !self.tris.is_empty() {
            let mut r = Self::bray(ray);
            let mut prim = u32::MAX;
            let mut state = self.bvh.new_traversal(r.direction);
            let mut node: &CwBvhNode;
            obvhs::traverse!(
                self.bvh,
                node,
                state,
                intersect_node(node, &r, state.oct_inv4),
                {
                    let t = self.tris[state.primitive_id as usize].intersect(&r);
                    if t < r.tmax {
                        prim = state.primitive_id;
                        r.tmax = t;
                    }
                }
            );
            if prim != u32::MAX {
                let (shape, tri) = self.tri_ref[prim as usize];
                best = Some(Hit {
                    t: r.tmax,
                    shape,
                    prim: tri,
                    bvh_prim: prim,
                });
                tmax = r.tmax;
            }
        }
        if ANALYTIC {
            let mut r = *ray;
            r.tmax = tmax;
            for (s, a) in &self.analytic {
                let t = a.intersect(&r);
                if t < r.tmax {
                    r.tmax = t;
                    best = Some(Hit {
                        t,
                        shape: *s,
                        prim: 0,
                        bvh_prim: u32::MAX,
                    });
                }
            }
        }
        best
    }

    /// True when nothing blocks the ray in (tmin, tmax).
    #[inline]
    pub fn unoccluded<const ANALYTIC: bool>(&self, ray: &Ray) -> bool {
        if !self.tris.is_empty() {
            let r = Self::bray(ray);
            let mut state = self.bvh.new_traversal(r.direction);
            let mut node: &CwBvhNode;
            let mut blocked = false;
            'any_hit: {
                obvhs::traverse!(
                    self.bvh,
                    node,
                    state,
                    intersect_node(node, &r, state.oct_inv4),
                    {
                        if self.tris[state.primitive_id as usize].intersect(&r) < r.tmax {
                            blocked = true;
                            break 'any_hit;
                        }
                    }
                );
            }
            if blocked {
                return false;
            }
        }
        if ANALYTIC {
            for (_, a) in &self.analytic {
                if a.intersect(ray) < ray.tmax {
                    return false;
                }
            }
        }
        true
    }

    /// Shading data at a hit.
    #[inline]
    pub fn interaction(&self, ray: &Ray, hit: &Hit) -> SurfaceInteraction {
        let p = ray.o + ray.d * hit.t;
        let (ng, ns, uv) = match &self.shapes[hit.shape as usize] {
            ShapeGeom::Mesh(m) => {
                // Barycentrics from the intersection's own edge data (obvhs
                // layout: e1 = v0 - v1, e2 = v2 - v0, ng = e1 x e2), which
                // gives the weights of v1 and v2.
                let t = &self.tris[hit.bvh_prim as usize];
                let r = Vec3A::from(ray.d).cross(t.v0 - Vec3A::from(ray.o));
                let inv = 1.0 / t.ng.dot(Vec3A::from(ray.d));
                let b = glam::Vec2::new(r.dot(t.e2) * inv, r.dot(t.e1) * inv);
                triangle::shade(m, hit.prim as usize, b, Vec3::from(-t.ng))
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
}

/// Ray against the eight quantised child boxes of a CWBVH node: the hit mask
/// that obvhs' `traverse!` expects (internal children in the high byte by
/// traversal priority, leaf primitives in the low 24 bits).
///
/// Same arithmetic as obvhs' `CwBvhNode::intersect_ray` (the box planes in
/// the node's quantised grid, mul then add, the same `tmin` floor of 1e-4),
/// but written over all eight children at once so that it compiles to 8-wide
/// vector code instead of two 4-wide halves with per-lane scalar int->float
/// conversions and a branch per child.
#[inline(always)]
fn intersect_node(node: &CwBvhNode, ray: &BRay, oct_inv4: u32) -> u32 {
    /// obvhs' lower bound on the entry distance of a box.
    const EPSILON: f32 = 0.0001;
    let scale = node.compute_extent() * ray.inv_direction;
    let orig = (Vec3A::from(node.p) - ray.origin) * ray.inv_direction;
    // Near and far planes per axis, by the sign of the direction.
    let near_far = |lo: &[u8; 8], hi: &[u8; 8], neg: bool| {
        if neg {
            (*hi, *lo)
        } else {
            (*lo, *hi)
        }
    };
    let (nx, fx) = near_far(&node.child_min_x, &node.child_max_x, ray.direction.x < 0.0);
    let (ny, fy) = near_far(&node.child_min_y, &node.child_max_y, ray.direction.y < 0.0);
    let (nz, fz) = near_far(&node.child_min_z, &node.child_max_z, ray.direction.z < 0.0);
    // `if a > b { a } else { b }` rather than f32::max: no NaN fix-up, one
    // vmaxps (operands are finite: inv_direction is clamped by obvhs).
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
    let mut hits = 0u32;
    for i in 0..8 {
        let t0x = nx[i] as f32 * scale.x + orig.x;
        let t1x = fx[i] as f32 * scale.x + orig.x;
        let t0y = ny[i] as f32 * scale.y + orig.y;
        let t1y = fy[i] as f32 * scale.y + orig.y;
        let t0z = nz[i] as f32 * scale.z + orig.z;
        let t1z = fz[i] as f32 * scale.z + orig.z;
        let tmin = max(max(t0x, max(t0y, t0z)), EPSILON);
        let tmax = min(min(t1x, min(t1y, t1z)), ray.tmax);
        hits |= ((tmin <= tmax) as u32) << i;
    }
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
    let mut hit_mask = 0u32;
    while hits != 0 {
        let i = hits.trailing_zeros() as usize;
        hits &= hits - 1;
        hit_mask |= extract_byte64(child_bits8, i) << extract_byte64(bit_index8, i);
    }
    hit_mask
}
