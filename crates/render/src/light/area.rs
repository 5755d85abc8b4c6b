//! Area lights: uniform sampling of a shape's surface by area.

use glam::{Vec2, Vec3};
use std::f32::consts::PI;

use super::LightSample;
use crate::geometry::{Accel, Analytic, ShapeGeom};
use crate::sampling::{concentric_disk, uniform_sphere, uniform_triangle, Distribution1D};

/// A triangle of an emitting mesh, prepared for sampling.
#[derive(Clone, Copy)]
pub(super) struct EmitterTri {
    v0: Vec3,
    e1: Vec3,
    e2: Vec3,
    /// Normals at v0, v1, v2 (flip applied): the vertex normals, or the unit
    /// face normal three times for meshes without vertex normals.
    n: [Vec3; 3],
    /// The normal is the same everywhere on the triangle (no vertex normals,
    /// or equal ones, as on `rectangle` and `cube`): `n[0]`, unit length.
    pub flat: bool,
}

impl EmitterTri {
    /// The triangle for [`flat_triangle_sample`] (meaningful when `flat`).
    #[inline(always)]
    pub fn flat(&self) -> FlatTri {
        FlatTri {
            v0: self.v0.to_array(),
            e1: self.e1.to_array(),
            e2: self.e2.to_array(),
            n: self.n[0].to_array(),
        }
    }
}

/// An emitting shape, sampled uniformly by area; it emits constant radiance from the front side
/// of its shading normal only.
pub struct AreaLight {
    /// Index of the emitting shape in the scene's [`Accel`].
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
    /// Prepares shape `shape` of `accel` for sampling; `radiance` is its emitted radiance (linear
    /// RGB).
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
            ShapeGeom::Analytic(Analytic::Cylinder { to_world, .. }) => {
                // circular (the loader checks): 2 pi r h
                let r = to_world.transform_vector3(Vec3::X).length();
                let h = to_world.transform_vector3(Vec3::Z).length();
                (Distribution1D::default(), 2.0 * PI * r * h)
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

    /// A light sample seen from `p_ref`, uniform over the surface by area.
    #[inline]
    pub fn sample(&self, accel: &Accel, p_ref: Vec3, u: Vec2) -> Option<LightSample> {
        if !self.tri_data.is_empty() {
            let (tri, ux) = self.pick(u.x)?;
            return self.sample_triangle(tri, ux, u.y, p_ref);
        }
        let (p, n) = match accel.shape(self.shape) {
            // Meshes always have `tri_data`; an empty one has nothing to sample.
            ShapeGeom::Mesh(_) => return None,
            ShapeGeom::Analytic(Analytic::Sphere {
                center,
                radius,
                flip,
            }) => {
                let n = uniform_sphere(u);
                (*center + n * *radius, if *flip { -n } else { n })
            }
            ShapeGeom::Analytic(a @ Analytic::Disk { to_world, .. }) => {
                let d = concentric_disk(u);
                let p = to_world.transform_point3(Vec3::new(d.x, d.y, 0.0));
                let (_, n, _) = a.shade(p);
                (p, n)
            }
            ShapeGeom::Analytic(a @ Analytic::Cylinder { to_world, .. }) => {
                // uniform by area on a circular cylinder: uniform in angle and height
                let phi = 2.0 * PI * u.x;
                let local = Vec3::new(phi.cos(), phi.sin(), u.y);
                let p = to_world.transform_point3(local);
                let (_, n, _) = a.shade(p);
                (p, n)
            }
        };
        self.towards(p_ref, p, n)
    }

    /// An emitting mesh's triangle picked by area with `ux`, and `ux` rescaled within
    /// its bin; `None` for analytic shapes and meshes of no area.
    #[inline(always)]
    pub(super) fn pick(&self, ux: f32) -> Option<(&EmitterTri, f32)> {
        if self.tri_data.is_empty() || self.area <= 0.0 {
            return None;
        }
        let (t, ux) = self.tris.sample(ux);
        Some((&self.tri_data[t], ux))
    }

    /// A point uniform on triangle `tri` (by `ux`, `uy`) seen from `p_ref`.
    #[inline(always)]
    pub(super) fn sample_triangle(
        &self,
        tri: &EmitterTri,
        ux: f32,
        uy: f32,
        p_ref: Vec3,
    ) -> Option<LightSample> {
        if tri.flat {
            let s = flat_triangle_sample(&tri.flat(), self.area, p_ref.to_array(), ux, uy);
            return s.valid.then(|| self.light_sample(s.wi, s.point, s.pdf));
        }
        let b = uniform_triangle(Vec2::new(ux, uy));
        let n =
            (tri.n[0] * (1.0 - b.x - b.y) + tri.n[1] * b.x + tri.n[2] * b.y).normalize_or_zero();
        self.towards(p_ref, tri.v0 + tri.e1 * b.x + tri.e2 * b.y, n)
    }

    /// The sample of point `p` (shading normal `n`) seen from `p_ref`.
    #[inline(always)]
    fn towards(&self, p_ref: Vec3, p: Vec3, n: Vec3) -> Option<LightSample> {
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

    /// The light sample of direction `wi` to `point` with solid-angle density `pdf`
    /// (without the light-selection probability).
    #[inline(always)]
    pub(super) fn light_sample(&self, wi: [f32; 3], point: [f32; 3], pdf: f32) -> LightSample {
        LightSample {
            wi: Vec3::from_array(wi),
            point: Vec3::from_array(point),
            infinite: false,
            value: self.radiance,
            pdf,
            delta: false,
        }
    }

    /// Total surface area of the shape, in world units squared.
    pub fn area(&self) -> f32 {
        self.area
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

/// An emitting triangle with one normal everywhere, as plain numbers.
#[derive(Clone, Copy, Default)]
pub(super) struct FlatTri {
    pub v0: [f32; 3],
    pub e1: [f32; 3],
    pub e2: [f32; 3],
    /// Unit normal (the emitting side).
    pub n: [f32; 3],
}

/// A point sampled on a [`FlatTri`] seen from a reference point.
#[derive(Clone, Copy, Default)]
pub(super) struct FlatSample {
    /// False when the sample is void (the reference point on the light, the back
    /// side facing it, or a non-finite density).
    pub valid: bool,
    pub wi: [f32; 3],
    pub point: [f32; 3],
    /// Solid-angle pdf without the light-selection probability.
    pub pdf: f32,
}

/// Uniform sampling by area of a flat emitting triangle of a light of total area
/// `area`, seen from `p_ref`, with `(ux, uy)` uniform. Branch-free arithmetic on plain
/// numbers, so that a loop over many samples vectorises; the one implementation for
/// one sample ([`AreaLight::sample`]) and many ([`super::Lights::sample_many`]).
#[inline(always)]
pub(super) fn flat_triangle_sample(
    tri: &FlatTri,
    area: f32,
    p_ref: [f32; 3],
    ux: f32,
    uy: f32,
) -> FlatSample {
    // uniform_triangle: barycentrics (1 - sqrt(ux), uy sqrt(ux)).
    let s = ux.sqrt();
    let (b1, b2) = (1.0 - s, uy * s);
    let point: [f32; 3] = std::array::from_fn(|c| tri.v0[c] + tri.e1[c] * b1 + tri.e2[c] * b2);
    let v: [f32; 3] = std::array::from_fn(|c| point[c] - p_ref[c]);
    let d2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    let dist = d2.sqrt();
    let wi: [f32; 3] = std::array::from_fn(|c| v[c] / dist);
    let cos = tri.n[0] * -wi[0] + tri.n[1] * -wi[1] + tri.n[2] * -wi[2];
    let pdf = d2 / (cos * area);
    FlatSample {
        valid: (dist != 0.0) & (cos > 0.0) & pdf.is_finite(),
        wi,
        point,
        pdf,
    }
}
