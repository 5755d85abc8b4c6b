//! Smooth plastic (Mitsuba `plastic`): a delta dielectric coating over a
//! diffuse substrate, with internal diffuse Fresnel reflectance Fdr.

use crate::fresnel::{fresnel_dielectric, fresnel_diffuse_reflectance, reflect};
use crate::warp::{square_to_cosine_hemisphere, square_to_cosine_hemisphere_pdf};
use crate::{finite_or_zero, BsdfFlags, BsdfSample};
use glam::{Vec2, Vec3};

/// Mitsuba's `specular_sampling_weight = s_mean / (d_mean + s_mean)`, where
/// the means are `Texture::mean()` of the (whole) diffuse and specular
/// reflectance textures (for a constant RGB: the average of its channels;
/// `s_mean = 1` when no specular reflectance was given).
pub fn specular_sampling_weight(diffuse_mean: f32, specular_mean: f32) -> f32 {
    specular_mean / (diffuse_mean + specular_mean)
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plastic {
    /// Relative IOR int_ior / ext_ior.
    pub eta: f32,
    pub diffuse_reflectance: Vec3,
    pub specular_reflectance: Vec3,
    pub nonlinear: bool,
    /// See [`specular_sampling_weight`].
    pub specular_sampling_weight: f32,
    /// Precomputed 1 / eta^2.
    pub inv_eta_2: f32,
    /// Precomputed internal diffuse Fresnel reflectance Fdr(1 / eta).
    pub fdr_int: f32,
}

impl Plastic {
    pub fn new(
        eta: f32,
        diffuse_reflectance: Vec3,
        specular_reflectance: Vec3,
        nonlinear: bool,
        specular_sampling_weight: f32,
    ) -> Self {
        Self {
            eta,
            diffuse_reflectance,
            specular_reflectance,
            nonlinear,
            specular_sampling_weight,
            inv_eta_2: 1.0 / (eta * eta),
            fdr_int: fresnel_diffuse_reflectance(1.0 / eta),
        }
    }

    pub fn flags(&self) -> BsdfFlags {
        BsdfFlags {
            smooth: true,
            delta: true,
            transmission: false,
        }
    }

    #[inline]
    fn substrate(&self) -> Vec3 {
        let d = self.diffuse_reflectance;
        let denom = if self.nonlinear {
            Vec3::ONE - d * self.fdr_int
        } else {
            Vec3::splat(1.0 - self.fdr_int)
        };
        d / denom
    }

    /// (probability of the specular lobe, Fresnel at wi)
    #[inline]
    fn lobe_probs(&self, cos_theta_i: f32) -> (f32, f32) {
        let f_i = fresnel_dielectric(cos_theta_i, self.eta).0;
        let ps = f_i * self.specular_sampling_weight;
        let pd = (1.0 - f_i) * (1.0 - self.specular_sampling_weight);
        let p = ps / (ps + pd);
        (if p.is_finite() { p } else { 0.0 }, f_i)
    }

    pub fn sample(&self, wi: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        if !(wi.z > 0.0) {
            return None;
        }
        let (prob_specular, f_i) = self.lobe_probs(wi.z);
        let prob_diffuse = 1.0 - prob_specular;
        if u_lobe < prob_specular {
            let weight = self.specular_reflectance * (f_i / prob_specular);
            BsdfSample::specular_reflection(reflect(wi), prob_specular, weight).if_finite()
        } else {
            let wo = square_to_cosine_hemisphere(u);
            let pdf = prob_diffuse * square_to_cosine_hemisphere_pdf(wo);
            if !(pdf > 0.0) {
                return None;
            }
            let f_o = fresnel_dielectric(wo.z, self.eta).0;
            let weight =
                self.substrate() * (self.inv_eta_2 * (1.0 - f_i) * (1.0 - f_o) / prob_diffuse);
            BsdfSample::glossy_reflection(wo, pdf, weight).if_finite()
        }
    }

    /// Diffuse part only (the specular lobe is a delta).
    pub fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        if !(wi.z > 0.0 && wo.z > 0.0) {
            return Vec3::ZERO;
        }
        let f_i = fresnel_dielectric(wi.z, self.eta).0;
        let f_o = fresnel_dielectric(wo.z, self.eta).0;
        let v = self.substrate()
            * (square_to_cosine_hemisphere_pdf(wo) * self.inv_eta_2 * (1.0 - f_i) * (1.0 - f_o));
        finite_or_zero(v)
    }

    pub fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        if !(wi.z > 0.0 && wo.z > 0.0) {
            return 0.0;
        }
        let (prob_specular, _) = self.lobe_probs(wi.z);
        square_to_cosine_hemisphere_pdf(wo) * (1.0 - prob_specular)
    }
}
