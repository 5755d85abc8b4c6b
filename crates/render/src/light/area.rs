//! Area lights: uniform sampling of a shape's surface by area.

use glam::{Vec2, Vec3};
use std::f32::consts::PI;

use super::LightSample;
use crate::geometry::{Accel, Analytic, ShapeGeom};
use crate::sampling::{concentric_disk, uniform_sphere, uniform_triangle, Distribution1D};

/// A triangle of an emitting mesh, prepared for sampling.
#[derive(Clone, Copy)]
struct EmitterTri {
    v0: Vec3,
    e1: Vec3,
    e2: Vec3,
    /// Normals at v0, v1, v2 (flip applied): the vertex normals, or the unit
    /// face normal three times for meshes without vertex normals.
    n: [Vec3; 3],
    /// The normal is the same everywhere on the triangle (no vertex normals,
    /// or equal ones, as on `rectangle` and `cube`): `n[0]`, unit length.
    flat: bool,
}

pub struct AreaLight {
    pub shape: u32,
    /// Prepared triangles (meshes only).
    tri_data: Vec<EmitterTri>,
    /// Emitted radiance (front side only).
    pub radiance: Vec3,
    /// Triangle selection by area (meshes only).
    tris: Distribution1D,
    /// Total surface area.
    area: f32,
}

impl AreaLight {
    pub fn new(accel: &Accel, shape: u32, radiance: Vec3) -> Self {
        let (tris, area) = match accel.shape(shape) {
            ShapeGeom::Mesh(m) => {
                let areas: Vec<f32> = m
                    .indices
                    .iter()
                    .map(|t| {
                        let [a, b, c] = t.map(|i| m.positions[i as usize]);
                        0.5 * (b - a).cross(c - a).length()
                    })
                    .collect();
                let d = Distribution1D::new(&areas);
                let total = d.total() as f32;
                (d, total)
            }
            ShapeGeom::Analytic(Analytic::Sphere { radius, .. }) => {
                (Distribution1D::default(), 4.0 * PI * radius * radius)
            }
            ShapeGeom::Analytic(Analytic::Disk { to_world, .. }) => {
                let x = to_world.transform_vector3(Vec3::X);
                let y = to_world.transform_vector3(Vec3::Y);
                (Distribution1D::default(), PI * x.cross(y).length())
            }
        };
        let tri_data = match accel.shape(shape) {
            ShapeGeom::Mesh(m) => m
                .indices
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|i| m.positions[i as usize]);
                    let sign = if m.flip_normals { -1.0 } else { 1.0 };
                    let (n, flat) = match &m.normals {
                        Some(ns) => {
                            let n = t.map(|i| ns[i as usize] * sign);
                            if n[0] == n[1] && n[0] == n[2] {
                                ([n[0].normalize_or_zero(); 3], true)
                            } else {
                                (n, false)
                            }
                        }
                        None => ([(b - a).cross(c - a).normalize_or_zero() * sign; 3], true),
                    };
                    EmitterTri {
                        v0: a,
                        e1: b - a,
                        e2: c - a,
                        n,
                        flat,
                    }
                })
                .collect(),
            _ => Vec::new(),
        };
        Self {
            shape,
            tri_data,
            radiance,
            tris,
            area,
        }
    }

    /// A uniformly distributed point on the surface with its shading normal.
    #[inline]
    fn sample_point(&self, accel: &Accel, u: Vec2) -> Option<(Vec3, Vec3)> {
        if !self.tri_data.is_empty() {
            if self.area <= 0.0 {
                return None;
            }
            let (t, ux) = self.tris.sample(u.x);
            let b = uniform_triangle(Vec2::new(ux, u.y));
            let tri = &self.tri_data[t];
            let n = if tri.flat {
                tri.n[0]
            } else {
                (tri.n[0] * (1.0 - b.x - b.y) + tri.n[1] * b.x + tri.n[2] * b.y).normalize_or_zero()
            };
            return Some((tri.v0 + tri.e1 * b.x + tri.e2 * b.y, n));
        }
        match accel.shape(self.shape) {
            // Meshes always have `tri_data`; an empty one has nothing to sample.
            ShapeGeom::Mesh(_) => None,
            ShapeGeom::Analytic(Analytic::Sphere {
                center,
                radius,
                flip,
            }) => {
                let n = uniform_sphere(u);
                Some((*center + n * *radius, if *flip { -n } else { n }))
            }
            ShapeGeom::Analytic(a @ Analytic::Disk { to_world, .. }) => {
                let d = concentric_disk(u);
                let p = to_world.transform_point3(Vec3::new(d.x, d.y, 0.0));
                let (_, n, _) = a.shade(p);
                Some((p, n))
            }
        }
    }

    #[inline]
    pub fn sample(&self, accel: &Accel, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        let (p, n) = self.sample_point(accel, u)?;
        let v = p - p_ref;
        let d2 = v.length_squared();
        let dist = d2.sqrt();
        if dist == 0.0 {
            return None;
        }
        let wi = v / dist;
        let cos = n.dot(-wi);
        if cos <= 0.0 {
            // Back side: emits nothing. Mitsuba returns a zero sample too.
            return None;
        }
        let pdf = d2 / (cos * self.area);
        if !pdf.is_finite() {
            return None;
        }
        Some(LightSample {
            wi,
            point: p,
            infinite: false,
            value: self.radiance,
            pdf,
            delta: false,
        })
    }

    /// Solid-angle density of `sample` producing point `p` (normal `n`) seen
    /// from `p_ref` (without the light-selection probability).
    #[inline]
    pub fn pdf_solid_angle(&self, p_ref: Vec3, p: Vec3, n: Vec3) -> f32 {
        let v = p - p_ref;
        let d2 = v.length_squared();
        let cos = n.dot(v).abs() / d2.sqrt();
        if cos <= 0.0 || self.area <= 0.0 {
            return 0.0;
        }
        d2 / (cos * self.area)
    }
}
