//! Emitters: area lights on shapes, point, directional, constant and
//! environment-map lights, with Mitsuba's selection rule (every emitter is
//! picked with equal probability for next-event estimation).

mod area;
mod envmap;

pub use area::AreaLight;
pub use envmap::EnvMap;

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
    pub delta: bool,
}

impl LightSample {
    /// The shadow ray testing this sample from surface point `p` (geometric normal `ng`):
    /// unbounded towards an infinite light, else stopping just short of the sampled point.
    #[inline]
    pub fn shadow_ray(&self, p: Vec3, ng: Vec3) -> Ray {
        if self.infinite {
            spawn_ray(p, ng, self.wi)
        } else {
            spawn_ray_to(p, ng, self.point)
        }
    }
}

pub enum Light {
    Area(AreaLight),
    Point { position: Vec3, intensity: Vec3 },
    Directional { direction: Vec3, irradiance: Vec3 },
    Constant { radiance: Vec3 },
    EnvMap(EnvMap),
}

/// All the scene's lights and the maps from shapes to their area lights.
pub struct Lights {
    pub lights: Vec<Light>,
    /// The environment light (constant or envmap), if any.
    pub environment: Option<usize>,
    /// Probability of selecting any one light.
    select_pdf: f32,
}

impl Lights {
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

    pub fn is_empty(&self) -> bool {
        self.lights.is_empty()
    }

    /// Samples a light for next-event estimation from point `p`.
    #[inline]
    pub fn sample(&self, accel: &Accel, p: Vec3, u_select: f32, u: Vec2) -> Option<LightSample> {
        let n = self.lights.len();
        if n == 0 {
            return None;
        }
        // (One light: skip the float-to-index conversion; same choice.)
        let i = if n == 1 {
            0
        } else {
            ((u_select * n as f32) as usize).min(n - 1)
        };
        let mut s = match &self.lights[i] {
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
