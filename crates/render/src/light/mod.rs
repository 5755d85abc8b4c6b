//! Emitters: area lights on shapes, point, directional, constant and
//! environment-map lights, with Mitsuba's selection rule (every emitter is
//! picked with equal probability for next-event estimation).

mod area;
mod envmap;
mod spot;

pub use area::AreaLight;
use area::{flat_triangle_sample, FlatTri};
pub use envmap::EnvMap;
pub use spot::Spot;

use glam::{Vec2, Vec3};
use std::f32::consts::PI;

use crate::geometry::{spawn_ray, spawn_ray_to, Accel, Ray};
use crate::sampling::uniform_sphere;

/// One light sample seen from a reference point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Unit direction from the reference point towards the light.
    pub wi: Vec3,
    /// Point on the light (for shadow rays); meaningless when `infinite`.
    pub point: Vec3,
    /// The light is at infinity (environment, directional).
    pub infinite: bool,
    /// Incident radiance (for delta lights: intensity / d^2 or irradiance),
    /// not yet divided by `pdf`.
    pub value: Vec3,
    /// Solid-angle pdf including the selection probability; for delta lights
    /// the selection probability alone.
    pub pdf: f32,
    /// From a delta light (point or directional): no BSDF-sampled path can hit it, so the
    /// sample takes the full weight (MIS weight 1).
    pub delta: bool,
}

impl LightSample {
    /// The shadow ray testing this sample from surface point `p` (geometric normal `ng`):
    /// unbounded towards an infinite light, else stopping just short of the sampled point.
    /// `floor`: the scene's [`Accel::offset_floor`].
    #[inline]
    pub fn shadow_ray(&self, p: Vec3, ng: Vec3, floor: f32) -> Ray {
        if self.infinite {
            spawn_ray(p, ng, self.wi, floor)
        } else {
            spawn_ray_to(p, ng, self.point, floor)
        }
    }
}

/// One emitter of the scene.
pub enum Light {
    /// An emitting shape.
    Area(AreaLight),
    /// An isotropic point light.
    Point {
        /// Position in world space.
        position: Vec3,
        /// Radiant intensity (linear RGB, per steradian): the irradiance at distance d is
        /// `intensity / d^2`.
        intensity: Vec3,
    },
    /// A spot light (Mitsuba's `spot`).
    Spot(Spot),
    /// A light at infinity from a single direction.
    Directional {
        /// Normalised world-space direction the light travels (from the light into the scene).
        direction: Vec3,
        /// Irradiance (linear RGB) on a surface perpendicular to `direction`.
        irradiance: Vec3,
    },
    /// Uniform radiance from every direction at infinity.
    Constant {
        /// Radiance (linear RGB) arriving from every direction.
        radiance: Vec3,
    },
    /// An environment map at infinity.
    EnvMap(EnvMap),
}

/// All the scene's lights and the maps from shapes to their area lights.
pub struct Lights {
    /// Every light: the shapes' area lights first, in shape order, then the other emitters.
    pub lights: Vec<Light>,
    /// The environment light (constant or envmap), if any.
    pub environment: Option<usize>,
    /// Probability of selecting any one light.
    select_pdf: f32,
}

impl Lights {
    /// Wraps `lights`, finding the environment light and each light's selection probability
    /// (one over the number of lights).
    pub fn new(lights: Vec<Light>) -> Self {
        let environment = lights
            .iter()
            .position(|l| matches!(l, Light::Constant { .. } | Light::EnvMap(_)));
        let select_pdf = if lights.is_empty() {
            0.0
        } else {
            1.0 / lights.len() as f32
        };
        Self {
            lights,
            environment,
            select_pdf,
        }
    }

    /// Whether the scene has no light at all.
    pub fn is_empty(&self) -> bool {
        self.lights.is_empty()
    }

    /// The light `u_select` picks, each with the same probability; `None` without lights.
    #[inline(always)]
    fn select(&self, u_select: f32) -> Option<usize> {
        let n = self.lights.len();
        match n {
            0 => None,
            // One light: skip the float-to-index conversion; same choice.
            1 => Some(0),
            _ => Some(((u_select * n as f32) as usize).min(n - 1)),
        }
    }

    /// Samples a light for next-event estimation from point `p`.
    #[inline]
    pub fn sample(&self, accel: &Accel, p: Vec3, u_select: f32, u: Vec2) -> Option<LightSample> {
        let mut s = match &self.lights[self.select(u_select)?] {
            Light::Area(a) => a.sample(accel, p, u)?,
            Light::Point {
                position,
                intensity,
            } => {
                let v = *position - p;
                let d2 = v.length_squared();
                if d2 == 0.0 {
                    return None;
                }
                let wi = v / d2.sqrt();
                LightSample {
                    wi,
                    point: *position,
                    infinite: false,
                    value: *intensity / d2,
                    pdf: 1.0,
                    delta: true,
                }
            }
            Light::Spot(spot) => spot.sample(p)?,
            Light::Directional {
                direction,
                irradiance,
            } => LightSample {
                wi: -*direction,
                point: Vec3::ZERO,
                infinite: true,
                value: *irradiance,
                pdf: 1.0,
                delta: true,
            },
            Light::Constant { radiance } => {
                let wi = uniform_sphere(u);
                LightSample {
                    wi,
                    point: Vec3::ZERO,
                    infinite: true,
                    value: *radiance,
                    pdf: 1.0 / (4.0 * PI),
                    delta: false,
                }
            }
            Light::EnvMap(e) => e.sample(u)?,
        };
        s.pdf *= self.select_pdf;
        Some(s)
    }

    /// [`Lights::sample`] for many reference points at once: `out[i]` for `queries[i]`
    /// (point, selection number, 2D number), the same samples as one at a time. Flat
    /// triangles of emitting meshes (the common case) are sampled in groups, vectorised
    /// across queries; anything else one at a time.
    pub fn sample_many(
        &self,
        accel: &Accel,
        queries: &[(Vec3, f32, Vec2)],
        out: &mut [Option<LightSample>],
    ) {
        const GROUP: usize = 8;
        for (qs, outs) in queries.chunks(GROUP).zip(out.chunks_mut(GROUP)) {
            // Structure of arrays, so that the sampling loop below vectorises.
            let mut tri = [[0.0f32; GROUP]; 12];
            let mut area = [1.0f32; GROUP];
            let mut p_ref = [[0.0f32; GROUP]; 3];
            let (mut ux, mut uy) = ([0.0f32; GROUP], [0.0f32; GROUP]);
            // The area light of each lane sampled in the group.
            let mut light: [Option<&AreaLight>; GROUP] = [None; GROUP];
            for (i, (&(p, u_select, u), o)) in qs.iter().zip(outs.iter_mut()).enumerate() {
                let Some(l) = self.select(u_select) else {
                    *o = None;
                    continue;
                };
                let Light::Area(a) = &self.lights[l] else {
                    *o = self.sample(accel, p, u_select, u);
                    continue;
                };
                match a.pick(u.x) {
                    Some((t, x)) if t.flat => {
                        let t = t.flat();
                        for c in 0..3 {
                            tri[c][i] = t.v0[c];
                            tri[3 + c][i] = t.e1[c];
                            tri[6 + c][i] = t.e2[c];
                            tri[9 + c][i] = t.n[c];
                            p_ref[c][i] = p[c];
                        }
                        (area[i], ux[i], uy[i], light[i]) = (a.area(), x, u.y, Some(a));
                    }
                    Some((t, x)) => {
                        *o = a.sample_triangle(t, x, u.y, p).map(|mut s| {
                            s.pdf *= self.select_pdf;
                            s
                        })
                    }
                    None => *o = self.sample(accel, p, u_select, u),
                }
            }
            let mut valid = [false; GROUP];
            let mut wi = [[0.0f32; GROUP]; 3];
            let mut point = [[0.0f32; GROUP]; 3];
            let mut pdf = [0.0f32; GROUP];
            for i in 0..GROUP {
                let t = FlatTri {
                    v0: [tri[0][i], tri[1][i], tri[2][i]],
                    e1: [tri[3][i], tri[4][i], tri[5][i]],
                    e2: [tri[6][i], tri[7][i], tri[8][i]],
                    n: [tri[9][i], tri[10][i], tri[11][i]],
                };
                let p = [p_ref[0][i], p_ref[1][i], p_ref[2][i]];
                let s = flat_triangle_sample(&t, area[i], p, ux[i], uy[i]);
                valid[i] = s.valid;
                pdf[i] = s.pdf;
                for c in 0..3 {
                    wi[c][i] = s.wi[c];
                    point[c][i] = s.point[c];
                }
            }
            for (i, o) in outs.iter_mut().enumerate() {
                if let Some(a) = light[i] {
                    *o = valid[i].then(|| {
                        let mut ls = a.light_sample(
                            [wi[0][i], wi[1][i], wi[2][i]],
                            [point[0][i], point[1][i], point[2][i]],
                            pdf[i],
                        );
                        ls.pdf *= self.select_pdf;
                        ls
                    });
                }
            }
        }
    }

    /// Radiance arriving from the environment along direction `d` (pointing
    /// away from the scene).
    #[inline]
    pub fn environment_radiance(&self, d: Vec3) -> Vec3 {
        match self.environment.map(|i| &self.lights[i]) {
            Some(Light::Constant { radiance }) => *radiance,
            Some(Light::EnvMap(e)) => e.eval(d),
            _ => Vec3::ZERO,
        }
    }

    /// Solid-angle pdf (with selection) that NEE would have produced `d`
    /// towards the environment.
    #[inline]
    pub fn environment_pdf(&self, d: Vec3) -> f32 {
        self.select_pdf
            * match self.environment.map(|i| &self.lights[i]) {
                Some(Light::Constant { .. }) => 1.0 / (4.0 * PI),
                Some(Light::EnvMap(e)) => e.pdf(d),
                _ => 0.0,
            }
    }

    /// Solid-angle pdf (with selection) that NEE from `p_ref` would have
    /// produced the point `p` with shading normal `n` on area light `light`.
    #[inline]
    pub fn area_pdf(&self, light: u32, p_ref: Vec3, p: Vec3, n: Vec3) -> f32 {
        match &self.lights[light as usize] {
            Light::Area(a) => self.select_pdf * a.pdf_solid_angle(p_ref, p, n),
            _ => 0.0,
        }
    }

    /// Radiance leaving area light `light` towards direction `w` (away from
    /// the surface) at a point with shading normal `n`.
    #[inline]
    pub fn area_radiance(&self, light: u32, n: Vec3, w: Vec3) -> Vec3 {
        match &self.lights[light as usize] {
            Light::Area(a) if n.dot(w) > 0.0 => a.radiance,
            _ => Vec3::ZERO,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Analytic, ShapeGeom};
    use crate::rng::Rng;
    use pathfarm_scene::TriangleMesh;
    use std::sync::Arc;

    fn mesh(normals: Option<Vec<Vec3>>, z: f32) -> ShapeGeom {
        ShapeGeom::Mesh(Arc::new(TriangleMesh {
            positions: vec![
                Vec3::new(0.0, 0.0, z),
                Vec3::new(1.0, 0.0, z),
                Vec3::new(1.0, 1.0, z),
                Vec3::new(0.0, 2.0, z),
            ],
            normals,
            uvs: None,
            indices: vec![[0, 1, 2], [0, 2, 3]],
            flip_normals: true,
        }))
    }

    #[test]
    fn many_light_samples_at_once_equal_one_at_a_time() {
        let bent = vec![
            Vec3::new(0.0, 0.3, -1.0).normalize(),
            Vec3::NEG_Z,
            Vec3::new(0.2, 0.0, -1.0).normalize(),
            Vec3::NEG_Z,
        ];
        let shapes = vec![
            mesh(None, 2.0),
            mesh(Some(bent), 2.5),
            ShapeGeom::Analytic(Analytic::Sphere {
                center: Vec3::new(0.5, 0.5, 3.0),
                radius: 0.3,
                flip: false,
            }),
        ];
        let accel = crate::geometry::Accel::build(shapes);
        let e = Vec3::new(3.0, 2.0, 1.0);
        let lights = Lights::new(vec![
            Light::Area(AreaLight::new(&accel, 0, e)),
            Light::Area(AreaLight::new(&accel, 1, e)),
            Light::Area(AreaLight::new(&accel, 2, e)),
            Light::Point {
                position: Vec3::new(0.2, 0.1, 1.5),
                intensity: e,
            },
        ]);
        let mut rng = Rng::for_sample(4, 0, 0);
        // Reference points below the lights, some above the first (its back side).
        let queries: Vec<(Vec3, f32, Vec2)> = (0..203)
            .map(|_| {
                let p = Vec3::new(rng.next_f32(), rng.next_f32(), 2.3 * rng.next_f32());
                (p, rng.next_f32(), rng.next_2d())
            })
            .collect();
        let mut many = vec![None; queries.len()];
        lights.sample_many(&accel, &queries, &mut many);
        let bits = |s: &Option<LightSample>| {
            s.map(|s| {
                let v = |v: Vec3| v.to_array().map(f32::to_bits);
                (v(s.wi), v(s.point), v(s.value), s.pdf.to_bits(), s.delta)
            })
        };
        let mut flat_valid = 0;
        for (q, m) in queries.iter().zip(&many) {
            let one = lights.sample(&accel, q.0, q.1, q.2);
            assert_eq!(bits(m), bits(&one), "query {q:?}");
            flat_valid += (q.1 < 0.25 && one.is_some()) as usize;
        }
        assert!(flat_valid > 20, "{flat_valid}");
    }
}
