//! Rough dielectric interface (Mitsuba `roughdielectric`, Walter et al. 2007).

use crate::fresnel::{fresnel_dielectric, reflect_about, refract_about};
use crate::microfacet::Microfacet;
use crate::{finite_or_zero, BsdfFlags, BsdfSample, Lobe};
use glam::{Vec2, Vec3};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoughDielectric {
    /// The microfacet distribution and its roughness.
    pub distr: Microfacet,
    /// Relative IOR int_ior / ext_ior.
    pub eta: f32,
    pub specular_reflectance: Vec3,
    pub specular_transmittance: Vec3,
}

impl RoughDielectric {
    pub fn new(
        distr: Microfacet,
        eta: f32,
        specular_reflectance: Vec3,
        specular_transmittance: Vec3,
    ) -> Self {
        Self {
            distr,
            eta,
            specular_reflectance,
            specular_transmittance,
        }
    }

    /// The distribution used for sampling (Walter's roughness scaling trick
    /// when not sampling visible normals).
    #[inline]
    fn sample_distr(&self, cos_theta_i: f32) -> Microfacet {
        let mut d = self.distr;
        if !d.sample_visible {
            d.scale_alpha(1.2 - 0.2 * cos_theta_i.abs().sqrt());
        }
        d
    }

    /// Equal interior and exterior IOR: there is no interface. Every microfacet then
    /// refracts straight through with Fresnel 0, so the BSDF is a delta transmission
    /// `wo = -wi`; Walter's model degenerates there (the half vector `wi + eta wo` is 0 and
    /// `dwh/dwo` infinite), and sampling it would reject every direction: the object would
    /// absorb all light instead of vanishing.
    #[inline]
    fn index_matched(&self) -> bool {
        self.eta == 1.0
    }

    pub fn flags(&self) -> BsdfFlags {
        BsdfFlags {
            smooth: !self.index_matched(),
            delta: self.index_matched(),
            transmission: true,
        }
    }

    /// Two-sided; transmitted samples carry the radiance-mode factor
    /// `eta_ti^2` and report `eta = eta_it`.
    pub fn sample(&self, wi: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        let cos_theta_i = wi.z;
        if cos_theta_i == 0.0 || !cos_theta_i.is_finite() {
            return None;
        }
        if self.index_matched() {
            return Some(BsdfSample::specular_transmission(
                -wi,
                1.0,
                self.specular_transmittance,
                1.0,
            ));
        }
        let distr = self.distr;
        let sdistr = self.sample_distr(cos_theta_i);
        let wi_up = if cos_theta_i < 0.0 { -wi } else { wi };
        let (m, pdf_m) = sdistr.sample(wi_up, u);
        if !(pdf_m > 0.0) || !pdf_m.is_finite() {
            return None;
        }
        // A back-facing microfacet has G1(wi, m) = 0 (Mitsuba: zero weight).
        if !(wi.dot(m) * cos_theta_i > 0.0) {
            return None;
        }
        let (f, cos_theta_t, eta_it, eta_ti) = fresnel_dielectric(wi.dot(m), self.eta);
        let selected_r = u_lobe <= f && f > 0.0;
        let (wo, mut weight, pdf_lobe, eta, dwh_dwo);
        if selected_r {
            wo = reflect_about(wi, m);
            weight = self.specular_reflectance;
            pdf_lobe = f;
            eta = 1.0;
            dwh_dwo = 1.0 / (4.0 * wo.dot(m));
        } else {
            if !(f < 1.0) {
                return None;
            }
            wo = refract_about(wi, m, cos_theta_t, eta_ti);
            weight = self.specular_transmittance * (eta_ti * eta_ti);
            pdf_lobe = 1.0 - f;
            eta = eta_it;
            dwh_dwo = (eta * eta * wo.dot(m)) / sq(wi.dot(m) + eta * wo.dot(m));
        }
        // Reject directions on the wrong side for the chosen lobe.
        if selected_r == (wo.z * cos_theta_i <= 0.0) || wo.z == 0.0 {
            return None;
        }
        let pdf = pdf_m * pdf_lobe * dwh_dwo.abs();
        if distr.sample_visible {
            weight *= distr.smith_g1(wo, m);
        } else {
            // Mitsuba uses G (wi.m) / (cos_i cos_m) here, which is eval/pdf
            // only for the unscaled distribution; with Walter's roughness
            // scaling of the sampling distribution that weight is biased. We
            // use the exact ratio instead (deviation from Mitsuba, only for
            // sample_visible = false).
            let p = self.pdf(wi, wo);
            weight = if p > 0.0 {
                self.eval(wi, wo) / p
            } else {
                Vec3::ZERO
            };
        }
        if !(pdf > 0.0) || !pdf.is_finite() || !weight.is_finite() || !(weight.max_element() > 0.0)
        {
            return None;
        }
        Some(BsdfSample {
            wo,
            pdf,
            weight,
            eta,
            lobe: Lobe {
                delta: false,
                transmission: !selected_r,
            },
        })
    }

    /// Generalised half vector (upper hemisphere), whether the pair is a
    /// reflection, and the relative IOR seen from the `wi` side.
    #[inline]
    fn half_vector(&self, wi: Vec3, wo: Vec3) -> Option<(Vec3, bool, f32)> {
        let reflect = wi.z * wo.z > 0.0;
        let eta = if wi.z > 0.0 { self.eta } else { 1.0 / self.eta };
        let h = wi + wo * if reflect { 1.0 } else { eta };
        let len2 = h.length_squared();
        if !(len2 > 1e-12) || !len2.is_finite() {
            return None;
        }
        let mut m = h / len2.sqrt();
        if m.z < 0.0 {
            m = -m;
        }
        Some((m, reflect, eta))
    }

    pub fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        let cos_theta_i = wi.z;
        if cos_theta_i == 0.0 || wo.z == 0.0 || self.index_matched() {
            return Vec3::ZERO;
        }
        let Some((m, reflect, eta)) = self.half_vector(wi, wo) else {
            return Vec3::ZERO;
        };
        let distr = self.distr;
        let d = distr.eval(m);
        let f = fresnel_dielectric(wi.dot(m), self.eta).0;
        let g = distr.g(wi, wo, m);
        let v = if reflect {
            self.specular_reflectance * (f * d * g / (4.0 * cos_theta_i.abs()))
        } else {
            let inv_eta = 1.0 / eta;
            let scale = inv_eta * inv_eta;
            let val = (scale * (1.0 - f) * d * g * eta * eta * wi.dot(m) * wo.dot(m))
                / (cos_theta_i * sq(wi.dot(m) + eta * wo.dot(m)));
            self.specular_transmittance * val.abs()
        };
        finite_or_zero(v)
    }

    pub fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        let cos_theta_i = wi.z;
        if cos_theta_i == 0.0 || wo.z == 0.0 || self.index_matched() {
            return 0.0;
        }
        let Some((m, reflect, eta)) = self.half_vector(wi, wo) else {
            return 0.0;
        };
        if !(wi.dot(m) * wi.z > 0.0 && wo.dot(m) * wo.z > 0.0) {
            return 0.0;
        }
        let dwh_dwo = if reflect {
            1.0 / (4.0 * wo.dot(m))
        } else {
            (eta * eta * wo.dot(m)) / sq(wi.dot(m) + eta * wo.dot(m))
        };
        let sdistr = self.sample_distr(cos_theta_i);
        let wi_up = if cos_theta_i < 0.0 { -wi } else { wi };
        let mut prob = sdistr.pdf(wi_up, m);
        let f = fresnel_dielectric(wi.dot(m), self.eta).0;
        prob *= if reflect { f } else { 1.0 - f };
        let r = prob * dwh_dwo.abs();
        if r.is_finite() {
            r
        } else {
            0.0
        }
    }
}

#[inline]
fn sq(x: f32) -> f32 {
    x * x
}
