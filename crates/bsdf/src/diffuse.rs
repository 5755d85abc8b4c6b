//! Lambertian reflection (Mitsuba `diffuse`).

use crate::all_finite;
use crate::warp::{square_to_cosine_hemisphere_lane, square_to_cosine_hemisphere_pdf};
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
        BsdfFlags::GLOSSY_REFLECTION
    }

    pub fn sample(&self, wi: Vec3, _u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        let s = sample_lane(self.reflectance.to_array(), wi.z, u.x, u.y);
        s.valid
            .then(|| BsdfSample::glossy_reflection(Vec3::from_array(s.wo), s.pdf, self.reflectance))
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

/// A cosine-weighted direction drawn by [`sample_lane`] (weight: the reflectance).
#[derive(Clone, Copy, Debug, Default)]
pub struct LaneSample {
    /// False where [`crate::Bsdf::sample`] gives no sample.
    pub valid: bool,
    pub wo: [f32; 3],
    pub pdf: f32,
}

/// [`Diffuse::sample`] (with [`crate::Bsdf::sample`]'s checks) on plain numbers and
/// without branches, so that a loop over many shading points vectorises; the one
/// implementation of both. `wi_z` is the incident direction's cosine.
#[inline(always)]
pub fn sample_lane(reflectance: [f32; 3], wi_z: f32, ux: f32, uy: f32) -> LaneSample {
    let wo = square_to_cosine_hemisphere_lane(ux, uy);
    let pdf = FRAC_1_PI * wo[2];
    let [r0, r1, r2] = reflectance;
    let valid = (wi_z > 0.0)
        & (pdf > 0.0)
        & all_finite([r0, r1, r2, pdf, wo[0], wo[1], wo[2]])
        & (r0.max(r1).max(r2) > 0.0);
    LaneSample { valid, wo, pdf }
}

/// [`crate::Bsdf::sample`] of many diffuse shading points at once: `out[i]` for
/// `queries[i]` = (reflectance, cos of the incident direction, 2D number), computed 16
/// side by side in structure-of-arrays form so that the loop vectorises; the same
/// samples as one at a time ([`sample_lane`] is the one implementation).
pub fn sample_many(queries: &[(Vec3, f32, Vec2)], out: &mut [Option<BsdfSample>]) {
    const GROUP: usize = 16;
    for (qs, outs) in queries.chunks(GROUP).zip(out.chunks_mut(GROUP)) {
        let (mut wi_z, mut ux, mut uy) = ([1.0f32; GROUP], [0.5f32; GROUP], [0.5f32; GROUP]);
        let mut r = [[1.0f32; GROUP]; 3];
        for (j, &(refl, z, u)) in qs.iter().enumerate() {
            (wi_z[j], ux[j], uy[j]) = (z, u.x, u.y);
            (r[0][j], r[1][j], r[2][j]) = (refl.x, refl.y, refl.z);
        }
        let (mut valid, mut pdf, mut wo) = ([false; GROUP], [0.0f32; GROUP], [[0.0f32; GROUP]; 3]);
        for j in 0..GROUP {
            let s = sample_lane([r[0][j], r[1][j], r[2][j]], wi_z[j], ux[j], uy[j]);
            (valid[j], pdf[j]) = (s.valid, s.pdf);
            (wo[0][j], wo[1][j], wo[2][j]) = (s.wo[0], s.wo[1], s.wo[2]);
        }
        for (j, (&(refl, _, _), o)) in qs.iter().zip(outs.iter_mut()).enumerate() {
            *o = valid[j].then(|| {
                let wo = Vec3::new(wo[0][j], wo[1][j], wo[2][j]);
                BsdfSample::glossy_reflection(wo, pdf[j], refl)
            });
        }
    }
}
