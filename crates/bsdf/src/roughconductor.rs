//! Rough conductor (Mitsuba `roughconductor`): Cook–Torrance with a
//! Beckmann/GGX distribution, separable Smith G and complex Fresnel.

use crate::fresnel::{fresnel_conductor_rgb, reflect_about};
use crate::microfacet::Microfacet;
use crate::{finite_or_zero, BsdfFlags, BsdfSample};
use glam::{Vec2, Vec3};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoughConductor {
    /// The microfacet distribution and its roughness; visible-normal sampling is Mitsuba's
    /// default.
    pub distr: Microfacet,
    pub eta: Vec3,
    pub k: Vec3,
    pub specular_reflectance: Vec3,
}

impl RoughConductor {
    pub fn new(distr: Microfacet, eta: Vec3, k: Vec3, specular_reflectance: Vec3) -> Self {
        Self {
            distr,
            eta,
            k,
            specular_reflectance,
        }
    }

    pub fn flags(&self) -> BsdfFlags {
        BsdfFlags::GLOSSY_REFLECTION
    }

    pub fn sample(&self, wi: Vec3, _u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        if !(wi.z > 0.0) {
            return None;
        }
        let distr = self.distr;
        let (m, pdf_m) = distr.sample(wi, u);
        let wo = reflect_about(wi, m);
        if !(pdf_m > 0.0) || !(wo.z > 0.0) {
            return None;
        }
        let weight = if distr.sample_visible {
            distr.smith_g1(wo, m)
        } else {
            distr.g(wi, wo, m) * wi.dot(m) / (wi.z * m.z)
        };
        let pdf = pdf_m / (4.0 * wo.dot(m));
        let f = fresnel_conductor_rgb(wi.dot(m), self.eta, self.k);
        let weight = f * self.specular_reflectance * weight;
        if !(pdf > 0.0) || !pdf.is_finite() || !weight.is_finite() || weight == Vec3::ZERO {
            return None;
        }
        Some(BsdfSample::glossy_reflection(wo, pdf, weight))
    }

    pub fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        if !(wi.z > 0.0 && wo.z > 0.0) {
            return Vec3::ZERO;
        }
        let h = (wi + wo).normalize();
        let distr = self.distr;
        let d = distr.eval(h);
        if d == 0.0 {
            return Vec3::ZERO;
        }
        let g = distr.g(wi, wo, h);
        let result = d * g / (4.0 * wi.z);
        let f = fresnel_conductor_rgb(wi.dot(h), self.eta, self.k);
        finite_or_zero(f * self.specular_reflectance * result)
    }

    pub fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        if !(wi.z > 0.0 && wo.z > 0.0) {
            return 0.0;
        }
        let m = (wi + wo).normalize();
        if !(wi.dot(m) > 0.0 && wo.dot(m) > 0.0) {
            return 0.0;
        }
        let distr = self.distr;
        let r = if distr.sample_visible {
            distr.eval(m) * distr.smith_g1(wi, m) / (4.0 * wi.z)
        } else {
            distr.pdf(wi, m) / (4.0 * wo.dot(m))
        };
        if r.is_finite() {
            r
        } else {
            0.0
        }
    }
}
