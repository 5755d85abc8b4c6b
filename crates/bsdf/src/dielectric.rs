//! Smooth dielectric interface (Mitsuba `dielectric`): delta reflection and
//! refraction, chosen by Fresnel with `u_lobe`.

use crate::fresnel::{fresnel_dielectric, reflect, refract};
use crate::{BsdfFlags, BsdfSample, Lobe};
use glam::{Vec2, Vec3};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dielectric {
    /// Relative IOR int_ior / ext_ior (the normal points to the exterior).
    pub eta: f32,
    pub specular_reflectance: Vec3,
    pub specular_transmittance: Vec3,
}

impl Dielectric {
    pub fn new(eta: f32, specular_reflectance: Vec3, specular_transmittance: Vec3) -> Self {
        Self {
            eta,
            specular_reflectance,
            specular_transmittance,
        }
    }

    pub fn flags(&self) -> BsdfFlags {
        BsdfFlags {
            smooth: false,
            delta: true,
            transmission: true,
        }
    }

    /// Works from both sides (`wi.z < 0` is inside). Transmitted samples carry
    /// Mitsuba's radiance-mode factor `eta_ti^2 = (1 / eta_crossing)^2`.
    pub fn sample(&self, wi: Vec3, u_lobe: f32, _u: Vec2) -> Option<BsdfSample> {
        let cos_theta_i = wi.z;
        if cos_theta_i == 0.0 || !cos_theta_i.is_finite() {
            return None;
        }
        let (r, cos_theta_t, eta_it, eta_ti) = fresnel_dielectric(cos_theta_i, self.eta);
        let t = 1.0 - r;
        if r > 0.0 && u_lobe <= r {
            Some(BsdfSample::specular_reflection(
                reflect(wi),
                r,
                self.specular_reflectance,
            ))
        } else {
            if !(t > 0.0) {
                return None;
            }
            Some(BsdfSample {
                wo: refract(wi, cos_theta_t, eta_ti),
                pdf: t,
                weight: self.specular_transmittance * (eta_ti * eta_ti),
                eta: eta_it,
                lobe: Lobe {
                    delta: true,
                    transmission: true,
                },
            })
        }
    }

    pub fn eval(&self, _wi: Vec3, _wo: Vec3) -> Vec3 {
        Vec3::ZERO
    }

    pub fn pdf(&self, _wi: Vec3, _wo: Vec3) -> f32 {
        0.0
    }
}
