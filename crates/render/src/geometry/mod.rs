//! Ray-scene intersection: triangle meshes in an obvhs CWBVH, analytic
//! spheres and disks beside it, and the surface interaction at a hit.

mod accel;
mod analytic;
mod triangle;

pub use accel::{Accel, Bvh, ShapeGeom};
pub use analytic::Analytic;

use glam::{Vec2, Vec3};

/// A ray segment `o + t d` for t between `tmin` and `tmax`, in world space.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    /// Origin.
    pub o: Vec3,
    /// Direction; unit length (the sphere test and the `t` distances rely on it).
    pub d: Vec3,
    /// Start of the segment: nearer hits are ignored (the near clip of camera rays, else 0).
    pub tmin: f32,
    /// End of the segment: farther hits are ignored (infinity for an unbounded ray).
    pub tmax: f32,
}

/// What a closest-hit query found, before shading data is computed.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    /// Ray parameter of the hit: its distance from the origin along the (unit) direction.
    pub t: f32,
    /// Index of the shape in the scene description.
    pub shape: u32,
    /// Triangle index within the shape (0 for analytic shapes).
    pub prim: u32,
    /// Index of the triangle in the BVH's order (u32::MAX for analytic shapes).
    pub bvh_prim: u32,
    /// Barycentric coordinates of the hit on the triangle (the weights of
    /// its vertices 1 and 2) as the intersection test found them; zero for
    /// analytic shapes.
    pub bary: Vec2,
}

/// Local geometry at a hit point.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceInteraction {
    /// The hit point, in world space.
    pub p: Vec3,
    /// Ray parameter (distance along the unit direction) of the hit.
    pub t: f32,
    /// Geometric normal (unit; `flip_normals` applied).
    pub ng: Vec3,
    /// Shading normal (unit; interpolated vertex normals or `ng`).
    pub ns: Vec3,
    /// Surface coordinates at the hit (interpolated mesh uvs, or the sphere's or disk's
    /// parameterisation), used for texture lookups.
    pub uv: Vec2,
    /// Index of the hit shape in the scene description.
    pub shape: u32,
}

/// Offset scale for spawned rays: relative to the magnitude of the point, so
/// that it works at any scene scale (a fixed epsilon fails far from the
/// origin), and never below `floor` times that fraction: `floor` is the scene's
/// [`Accel::offset_floor`] (1, or the extent of a scene smaller than 1).
#[inline]
pub fn offset_origin(p: Vec3, ng: Vec3, d: Vec3, floor: f32) -> Vec3 {
    let scale = (floor + p.abs().max_element()) * 2.0e-5;
    let n = if ng.dot(d) >= 0.0 { ng } else { -ng };
    p + n * scale
}

/// A ray leaving surface point `p` in direction `d` (`floor`: see [`offset_origin`]).
#[inline]
pub fn spawn_ray(p: Vec3, ng: Vec3, d: Vec3, floor: f32) -> Ray {
    Ray {
        o: offset_origin(p, ng, d, floor),
        d,
        tmin: 0.0,
        tmax: f32::INFINITY,
    }
}

/// A shadow ray from surface point `p` towards `target` (stopping just short
/// of it). Returns the ray; `d` is unit length.
#[inline]
pub fn spawn_ray_to(p: Vec3, ng: Vec3, target: Vec3, floor: f32) -> Ray {
    let o = offset_origin(p, ng, target - p, floor);
    let v = target - o;
    let dist = v.length();
    Ray {
        o,
        d: v / dist,
        tmin: 0.0,
        tmax: dist * (1.0 - 1.0e-4),
    }
}
