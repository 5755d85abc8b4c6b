//! Analytic shapes (Mitsuba `sphere`, `disk`, `cylinder`), intersected directly. They are
//! few in real scenes, so they are tested after the BVH without their own
//! acceleration structure; scenes without them skip this entirely.

use glam::{Mat4, Vec2, Vec3};

use super::Ray;

/// A shape intersected in closed form rather than through the triangle BVH.
#[derive(Clone, Debug)]
pub enum Analytic {
    /// A sphere (Mitsuba `sphere`), in world space.
    Sphere {
        /// Centre, in world space.
        center: Vec3,
        /// Radius, in world units.
        radius: f32,
        /// Normals point inwards (Mitsuba `flip_normals`).
        flip: bool,
    },
    /// The unit disk of the local xy plane, placed by a transform (Mitsuba `disk`); build it with
    /// [`Analytic::disk`], which derives the other fields from `to_world`.
    Disk {
        /// Object-to-world transform of the unit disk (may scale it into an ellipse).
        to_world: Mat4,
        /// Inverse of `to_world`.
        to_local: Mat4,
        /// Unit world-space normal of the disk's +z side, before `flip` (the inverse transpose of
        /// `to_world` applied to +z).
        normal: Vec3,
        /// Normals point to local -z (Mitsuba `flip_normals`).
        flip: bool,
    },
    /// The open unit cylinder around the local z axis (radius 1, z from 0 to 1), placed by a
    /// transform that keeps it circular (Mitsuba `cylinder`); build it with
    /// [`Analytic::cylinder`].
    Cylinder {
        /// Object-to-world transform of the unit cylinder.
        to_world: Mat4,
        /// Inverse of `to_world`.
        to_local: Mat4,
        /// Normals point inwards (Mitsuba `flip_normals`).
        flip: bool,
    },
}

impl Analytic {
    /// The disk placed by `to_world`, with its inverse and world normal precomputed.
    pub fn disk(to_world: Mat4, flip: bool) -> Self {
        let normal = to_world
            .inverse()
            .transpose()
            .transform_vector3(Vec3::Z)
            .normalize();
        Analytic::Disk {
            to_world,
            to_local: to_world.inverse(),
            normal,
            flip,
        }
    }

    /// The cylinder placed by `to_world`, with its inverse precomputed.
    pub fn cylinder(to_world: Mat4, flip: bool) -> Self {
        Analytic::Cylinder {
            to_world,
            to_local: to_world.inverse(),
            flip,
        }
    }

    /// Distance to the nearest intersection in (ray.tmin, ray.tmax), or infinity.
    #[inline]
    pub fn intersect(&self, ray: &Ray) -> f32 {
        match self {
            Analytic::Sphere { center, radius, .. } => {
                // Numerically robust quadratic (pbrt-v4 / Ray Tracing Gems ch. 7).
                let f = ray.o - *center;
                let b = -f.dot(ray.d);
                let perp = f + b * ray.d;
                let disc = radius * radius - perp.length_squared();
                if disc < 0.0 {
                    return f32::INFINITY;
                }
                let q = b + b.signum() * disc.sqrt();
                // The roots are c / q and q (a = 1 for a unit direction).
                let c = f.length_squared() - radius * radius;
                let r0 = if q == 0.0 { 0.0 } else { c / q };
                let (t0, t1) = if r0 < q { (r0, q) } else { (q, r0) };
                for t in [t0, t1] {
                    if t > ray.tmin && t < ray.tmax {
                        return t;
                    }
                }
                f32::INFINITY
            }
            Analytic::Disk { to_local, .. } => {
                let o = to_local.transform_point3(ray.o);
                let d = to_local.transform_vector3(ray.d);
                if d.z == 0.0 {
                    return f32::INFINITY;
                }
                let t = -o.z / d.z;
                let q = o + d * t;
                if q.x * q.x + q.y * q.y <= 1.0 && t > ray.tmin && t < ray.tmax {
                    t
                } else {
                    f32::INFINITY
                }
            }
            Analytic::Cylinder { to_local, .. } => {
                // In the local frame (an affine map keeps the ray parameter), solved in f64:
                // grazing rays and thin cylinders lose digits in f32.
                let o = to_local.transform_point3(ray.o).as_dvec3();
                let d = to_local.transform_vector3(ray.d).as_dvec3();
                let a = d.x * d.x + d.y * d.y;
                if a == 0.0 {
                    return f32::INFINITY;
                }
                let b = o.x * d.x + o.y * d.y;
                let c = o.x * o.x + o.y * o.y - 1.0;
                let disc = b * b - a * c;
                if disc < 0.0 {
                    return f32::INFINITY;
                }
                let q = -(b + b.signum() * disc.sqrt());
                let (r0, r1) = (q / a, if q == 0.0 { 0.0 } else { c / q });
                let (t0, t1) = if r0 < r1 { (r0, r1) } else { (r1, r0) };
                for t in [t0, t1] {
                    let z = o.z + t * d.z;
                    let t = t as f32;
                    if (0.0..=1.0).contains(&z) && t > ray.tmin && t < ray.tmax {
                        return t;
                    }
                }
                f32::INFINITY
            }
        }
    }

    /// `(dp/du, dp/dv)` at point `p` of a sphere (Mitsuba's parameterisation: `u` the
    /// longitude, `v` the colatitude); `None` for other shapes and at the poles.
    pub fn uv_tangents(&self, p: Vec3) -> Option<(Vec3, Vec3)> {
        let Analytic::Sphere { center, .. } = self else {
            return None;
        };
        let d = p - *center;
        let r_xy = (d.x * d.x + d.y * d.y).sqrt();
        if r_xy <= 0.0 || r_xy.is_nan() {
            return None;
        }
        let (cos_phi, sin_phi) = (d.x / r_xy, d.y / r_xy);
        let pi = std::f32::consts::PI;
        let dp_du = Vec3::new(-d.y, d.x, 0.0) * (2.0 * pi);
        let dp_dv = Vec3::new(d.z * cos_phi, d.z * sin_phi, -r_xy) * pi;
        Some((dp_du, dp_dv))
    }

    /// (geometric normal, shading normal, uv) at point `p` on the surface.
    pub fn shade(&self, p: Vec3) -> (Vec3, Vec3, Vec2) {
        match self {
            Analytic::Sphere { center, flip, .. } => {
                let n = (p - *center).normalize();
                let n = if *flip { -n } else { n };
                let l = (p - *center).normalize();
                let mut phi = l.y.atan2(l.x);
                if phi < 0.0 {
                    phi += 2.0 * std::f32::consts::PI;
                }
                let uv = Vec2::new(
                    phi / (2.0 * std::f32::consts::PI),
                    l.z.clamp(-1.0, 1.0).acos() / std::f32::consts::PI,
                );
                (n, n, uv)
            }
            Analytic::Disk {
                to_local,
                normal,
                flip,
                ..
            } => {
                let q = to_local.transform_point3(p);
                let n = if *flip { -*normal } else { *normal };
                let r = (q.x * q.x + q.y * q.y).sqrt();
                let mut phi = q.y.atan2(q.x);
                if phi < 0.0 {
                    phi += 2.0 * std::f32::consts::PI;
                }
                (n, n, Vec2::new(r, phi / (2.0 * std::f32::consts::PI)))
            }
            Analytic::Cylinder {
                to_world,
                to_local,
                flip,
            } => {
                let q = to_local.transform_point3(p);
                // The transform keeps the cylinder circular: the radial direction maps to the
                // world normal as it is.
                let radial = to_world.transform_vector3(Vec3::new(q.x, q.y, 0.0));
                let n = radial.normalize_or_zero();
                let n = if *flip { -n } else { n };
                let mut phi = q.y.atan2(q.x);
                if phi < 0.0 {
                    phi += 2.0 * std::f32::consts::PI;
                }
                (n, n, Vec2::new(phi / (2.0 * std::f32::consts::PI), q.z))
            }
        }
    }

    /// World-space axis-aligned bounding box `(min, max)`; conservative for a disk (the transformed
    /// square around it).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        match self {
            Analytic::Sphere { center, radius, .. } => (
                *center - Vec3::splat(*radius),
                *center + Vec3::splat(*radius),
            ),
            Analytic::Disk { to_world, .. } => {
                let mut lo = Vec3::splat(f32::INFINITY);
                let mut hi = Vec3::splat(f32::NEG_INFINITY);
                for (x, y) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                    let q = to_world.transform_point3(Vec3::new(x, y, 0.0));
                    lo = lo.min(q);
                    hi = hi.max(q);
                }
                (lo, hi)
            }
            Analytic::Cylinder { to_world, .. } => {
                let mut lo = Vec3::splat(f32::INFINITY);
                let mut hi = Vec3::splat(f32::NEG_INFINITY);
                for (x, y, z) in [-1.0f32, 1.0]
                    .into_iter()
                    .flat_map(|x| [(x, -1.0, 0.0), (x, 1.0, 0.0), (x, -1.0, 1.0), (x, 1.0, 1.0)])
                {
                    let q = to_world.transform_point3(Vec3::new(x, y, z));
                    lo = lo.min(q);
                    hi = hi.max(q);
                }
                (lo, hi)
            }
        }
    }
}
