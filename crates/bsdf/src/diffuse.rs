//! Lambertian reflection (Mitsuba `diffuse`).

use crate::warp::{square_to_cosine_hemisphere, square_to_cosine_hemisphere_pdf};
use crate::{BsdfFlags, BsdfSample};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Diffuse {
    pub reflectance: Vec3,
}

impl Diffuse {
    pub fn new(reflectance: Vec3) -> Self {
        Self { reflectance }
    }

    pub fn flags(&self) -> BsdfFlags {
        BsdfFlags {
            smooth: true,
            delta: false,
            transmission: false,
        }
    }

    pub fn sample(&self, wi: Vec3, _u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        if !(wi.z > 0.0) {
            return None;
        }
        let wo = square_to_cosine_hemisphere(u);
        let pdf = square_to_cosine_hemisphere_pdf(wo);
        if !(pdf > 0.0) {
            return None;
        }
        Some(BsdfSample::glossy_reflection(wo, pdf, self.reflectance))
    }

    pub fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        if wi.z > 0.0 && wo.z > 0.0 {
            self.reflectance * (FRAC_1_PI * wo.z)
        } else {
            Vec3::ZERO
        }
    }

    pub fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        if wi.z > 0.0 && wo.z > 0.0 {
            square_to_cosine_hemisphere_pdf(wo)
        } else {
            0.0
        }
    }
}
