//! Smooth dielectric interface (Mitsuba `dielectric`): delta reflection and
//! refraction, chosen by Fresnel with `u_lobe`.

use crate::fresnel::{fresnel_dielectric, reflect, refract};
use crate::{BsdfFlags, BsdfSample};
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
        BsdfFlags::DELTA_TRANSMISSION
    }

    /// Works from both sides (`wi.z < 0` is inside). Transmitted samples carry
    /// Mitsuba's radiance-mode factor `eta_ti^2 = (1 / eta_crossing)^2`.
    pub fn sample(&self, wi: Vec3, u_lobe: f32, _u: Vec2) -> Option<BsdfSample> {
        let cos_theta_i = wi.z;
        if cos_theta_i == 0.0 || !cos_theta_i.is_finite() {
            return None;
        }
        let (r, cos_theta_t, eta_it, eta_ti) = fresnel_dielectric(cos_theta_i, self.eta);
        sample_delta_lobes(wi, u_lobe, r, self.specular_reflectance, |t| {
            BsdfSample::specular_transmission(
                refract(wi, cos_theta_t, eta_ti),
                t,
                self.specular_transmittance * (eta_ti * eta_ti),
                eta_it,
            )
        })
    }

    pub fn eval(&self, _wi: Vec3, _wo: Vec3) -> Vec3 {
        Vec3::ZERO
    }

    pub fn pdf(&self, _wi: Vec3, _wo: Vec3) -> f32 {
        0.0
    }
}

/// The lobe choice of the smooth and the thin dielectric: the mirror reflection
/// (weight `specular_reflectance`) with probability `r`, picked by `u_lobe` as
/// Mitsuba does, else the delta transmission `transmitted` builds from its
/// probability `1 - r` (built only when picked, so the refraction is not computed
/// for reflected samples). `None` when the picked lobe has probability 0.
#[inline]
pub(crate) fn sample_delta_lobes(
    wi: Vec3,
    u_lobe: f32,
    r: f32,
    specular_reflectance: Vec3,
    transmitted: impl FnOnce(f32) -> BsdfSample,
) -> Option<BsdfSample> {
    let t = 1.0 - r;
    if r > 0.0 && u_lobe <= r {
        Some(BsdfSample::specular_reflection(
            reflect(wi),
            r,
            specular_reflectance,
        ))
    } else {
        if !(t > 0.0) {
            return None;
        }
        Some(transmitted(t))
    }
}
