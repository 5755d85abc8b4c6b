//! Thin dielectric sheet (Mitsuba `thindielectric`): delta reflection plus
//! undeviated transmission, with the reflectance of a slab including all
//! internal bounces, R' = R + T^2 R / (1 - R^2) = 2R / (1 + R).

use crate::dielectric::{sample_delta_lobes, Dielectric};
use crate::fresnel::fresnel_dielectric;
use crate::{BsdfFlags, BsdfSample};
use glam::{Vec2, Vec3};

/// A slab of zero thickness whose two faces are the interface a [`Dielectric`] describes
/// (Mitsuba's `thindielectric` takes the same parameters as `dielectric`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ThinDielectric(pub Dielectric);

impl ThinDielectric {
    pub fn new(eta: f32, specular_reflectance: Vec3, specular_transmittance: Vec3) -> Self {
        Self(Dielectric::new(
            eta,
            specular_reflectance,
            specular_transmittance,
        ))
    }

    pub fn flags(&self) -> BsdfFlags {
        BsdfFlags::DELTA_TRANSMISSION
    }

    /// Slab reflectance 2R/(1+R) at |cos theta_i|.
    #[inline]
    pub fn reflectance(&self, cos_theta_i: f32) -> f32 {
        let r = fresnel_dielectric(cos_theta_i.abs(), self.0.eta).0;
        r * 2.0 / (1.0 + r)
    }

    /// Two-sided. The transmitted direction is `-wi` with `eta = 1` (Mitsuba
    /// reports it as a `Null` lobe; here it is a delta transmission).
    pub fn sample(&self, wi: Vec3, u_lobe: f32, _u: Vec2) -> Option<BsdfSample> {
        if wi.z == 0.0 || !wi.z.is_finite() {
            return None;
        }
        let r = self.reflectance(wi.z);
        sample_delta_lobes(wi, u_lobe, r, self.0.specular_reflectance, |t| {
            BsdfSample::specular_transmission(-wi, t, self.0.specular_transmittance, 1.0)
        })
    }

    pub fn eval(&self, _wi: Vec3, _wo: Vec3) -> Vec3 {
        Vec3::ZERO
    }

    pub fn pdf(&self, _wi: Vec3, _wo: Vec3) -> f32 {
        0.0
    }
}
