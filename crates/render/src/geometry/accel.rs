//! The scene's acceleration structure: one CWBVH (obvhs) over every triangle
//! of every mesh, plus the analytic shapes.

use std::sync::Arc;
use std::time::Duration;

use glam::{Vec3, Vec3A};
use obvhs::cwbvh::{builder::build_cwbvh_from_tris, CwBvh};
use obvhs::ray::{Ray as BRay, RayHit};
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
            let mut hit = RayHit::none();
            if self.bvh.ray_traverse(Self::bray(ray), &mut hit, |r, id| {
                self.tris[id].intersect(r)
            }) {
                let (shape, prim) = self.tri_ref[hit.primitive_id as usize];
                best = Some(Hit {
                    t: hit.t,
                    shape,
                    prim,
                    bvh_prim: hit.primitive_id,
                });
                tmax = hit.t;
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
        if !self.tris.is_empty()
            && !self
                .bvh
                .ray_traverse_miss(Self::bray(ray), |r, id| self.tris[id].intersect(r))
        {
            return false;
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
