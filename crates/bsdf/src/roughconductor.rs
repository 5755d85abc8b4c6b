//! Rough conductor (Mitsuba `roughconductor`): Cook–Torrance with a
//! Beckmann/GGX distribution, separable Smith G and complex Fresnel.

use crate::conductor::Conductor;
use crate::fresnel::reflect_about;
use crate::microfacet::Microfacet;
use crate::{finite_or_zero, BsdfFlags, BsdfSample};
use glam::{Vec2, Vec3};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoughConductor {
    /// The microfacet distribution and its roughness; visible-normal sampling is Mitsuba's
    /// default.
    pub distr: Microfacet,
    /// Each microfacet's reflectance: the smooth conductor's (Mitsuba's `roughconductor` takes
    /// the same parameters as `conductor`).
    pub interface: Conductor,
}

impl RoughConductor {
    pub fn new(distr: Microfacet, interface: Conductor) -> Self {
        Self { distr, interface }
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
        let weight = self.interface.fresnel(wi.dot(m)) * weight;
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
        finite_or_zero(self.interface.fresnel(wi.dot(h)) * result)
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
