//! Smooth conductor: a delta mirror with complex-IOR Fresnel (Mitsuba `conductor`).

use crate::fresnel::{fresnel_conductor_rgb, reflect};
use crate::{BsdfFlags, BsdfSample};
use glam::{Vec2, Vec3};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Conductor {
    /// Real part of the complex IOR per channel (relative to the exterior).
    pub eta: Vec3,
    /// Imaginary part (absorption coefficient) per channel.
    pub k: Vec3,
    pub specular_reflectance: Vec3,
}

impl Conductor {
    pub fn new(eta: Vec3, k: Vec3, specular_reflectance: Vec3) -> Self {
        Self {
            eta,
            k,
            specular_reflectance,
        }
    }

    /// The reflectance at incidence cosine `cos_theta_i` (Fresnel times
    /// `specular_reflectance`).
    #[inline]
    pub fn fresnel(&self, cos_theta_i: f32) -> Vec3 {
        fresnel_conductor_rgb(cos_theta_i, self.eta, self.k) * self.specular_reflectance
    }

    pub fn flags(&self) -> BsdfFlags {
        BsdfFlags::DELTA_REFLECTION
    }

    pub fn sample(&self, wi: Vec3, _u_lobe: f32, _u: Vec2) -> Option<BsdfSample> {
        if !(wi.z > 0.0) {
            return None;
        }
        Some(BsdfSample::specular_reflection(
            reflect(wi),
            1.0,
            self.fresnel(wi.z),
        ))
    }

    pub fn eval(&self, _wi: Vec3, _wo: Vec3) -> Vec3 {
        Vec3::ZERO
    }

    pub fn pdf(&self, _wi: Vec3, _wo: Vec3) -> f32 {
        0.0
    }
}
