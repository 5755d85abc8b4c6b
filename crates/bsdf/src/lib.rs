//! Scattering models with Mitsuba 3 semantics, evaluated in the local shading
//! frame (z is the shading normal).
//!
//! Conventions (the same as Mitsuba's):
//! - `wi` points *away* from the surface toward where the light goes (the
//!   previous path vertex / the camera), `wo` points away from the surface
//!   toward where light comes from (the next vertex / the light).
//! - `eval` returns f(wi, wo) * |cos theta_o| (the cosine is included).
//! - `pdf` is the solid-angle density of `sample` producing `wo` (0 for delta
//!   lobes, which only `sample` can produce).
//! - `sample` returns the weight f * |cos| / pdf (for delta lobes, the ratio of
//!   the delta coefficients), the pdf, the sampled lobe and the relative index
//!   of refraction `eta` of the crossing (1 for reflection).
//! - One-sided models (everything but the dielectrics) return zero when
//!   `wi.z <= 0`; two-sidedness is handled by the caller flipping the frame.
//!   There is no `twosided` model here: for Mitsuba's `twosided` wrapper the
//!   caller flips the shading frame (`Frame::flipped`) when `wi` is below the
//!   surface and evaluates the front (or back) BSDF in that frame; the
//!   (rough) dielectrics and thin dielectric are two-sided by themselves and
//!   must see the unflipped frame.
//! - `eta` parameters of the dielectrics are relative, `int_ior / ext_ior`,
//!   with the normal pointing to the exterior; `wi.z < 0` means the ray is
//!   inside. Conductors take the complex IOR (`eta`, `k`) per RGB channel.
//! - Transport mode is always *radiance* (paths traced from the camera):
//!   refracted samples and the transmission part of `eval` carry Mitsuba's
//!   solid-angle compression factor `eta_ti^2 = 1 / eta_crossing^2`, where
//!   `eta_crossing` is the reported `BsdfSample::eta` (e.g. entering glass of
//!   eta 1.5 scales by 1/2.25, leaving it by 2.25).
//! - No function returns NaN or infinity; `sample` returns `None` instead of
//!   a zero-weight or invalid sample.
//!
//! Parameters are already evaluated (textures looked up by the caller), so a
//! `Bsdf` value is small, `Copy`, and built per shading point.

// `!(x > 0.0)` is used on purpose throughout: it also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use glam::{Vec2, Vec3};

/// Which kind of lobe a sample came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Lobe {
    /// Perfectly specular (a Dirac delta): no pdf, no MIS, no NEE.
    pub delta: bool,
    /// Transmission (crossed the surface) rather than reflection.
    pub transmission: bool,
}

/// A direction drawn by [`Bsdf::sample`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BsdfSample {
    pub wo: Vec3,
    /// Solid-angle pdf (for delta lobes: the discrete probability of picking
    /// the lobe).
    pub pdf: f32,
    /// f * |cos theta_o| / pdf.
    pub weight: Vec3,
    /// Relative IOR of the crossing (eta_t / eta_i), 1 for reflection.
    pub eta: f32,
    pub lobe: Lobe,
}

impl BsdfSample {
    /// A reflected direction of a smooth (non-delta) lobe: `eta` 1.
    #[inline]
    pub fn glossy_reflection(wo: Vec3, pdf: f32, weight: Vec3) -> Self {
        Self::reflection(wo, pdf, weight, false)
    }

    /// A mirror-reflected direction of a delta lobe picked with probability `pdf`: `eta` 1.
    #[inline]
    pub fn specular_reflection(wo: Vec3, pdf: f32, weight: Vec3) -> Self {
        Self::reflection(wo, pdf, weight, true)
    }

    /// An undeviated or refracted direction of a delta lobe picked with probability
    /// `pdf`, crossing into relative IOR `eta`.
    #[inline]
    pub fn specular_transmission(wo: Vec3, pdf: f32, weight: Vec3, eta: f32) -> Self {
        Self {
            wo,
            pdf,
            weight,
            eta,
            lobe: Lobe {
                delta: true,
                transmission: true,
            },
        }
    }

    /// The sample, unless its weight is NaN or infinite (a degenerate configuration): then
    /// `None`, the path is absorbed rather than carrying a non-finite value on.
    #[inline]
    pub fn if_finite(self) -> Option<Self> {
        if self.weight.is_finite() {
            Some(self)
        } else {
            None
        }
    }

    #[inline]
    fn reflection(wo: Vec3, pdf: f32, weight: Vec3, delta: bool) -> Self {
        Self {
            wo,
            pdf,
            weight,
            eta: 1.0,
            lobe: Lobe {
                delta,
                transmission: false,
            },
        }
    }
}

/// Static properties of a BSDF, known without a direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct BsdfFlags {
    /// Has at least one non-delta lobe (NEE and MIS make sense).
    pub smooth: bool,
    /// Has at least one delta lobe.
    pub delta: bool,
    /// Can transmit.
    pub transmission: bool,
}

// The flag sets several models share, named once.
impl BsdfFlags {
    /// Only smooth reflection (diffuse, rough conductor, rough plastic).
    pub const GLOSSY_REFLECTION: Self = Self {
        smooth: true,
        delta: false,
        transmission: false,
    };
    /// Only a delta reflection (smooth conductor).
    pub const DELTA_REFLECTION: Self = Self {
        smooth: false,
        delta: true,
        transmission: false,
    };
    /// Delta reflection and delta transmission (smooth and thin dielectric).
    pub const DELTA_TRANSMISSION: Self = Self {
        smooth: false,
        delta: true,
        transmission: true,
    };
}

pub mod conductor;
pub mod dielectric;
pub mod diffuse;
pub mod frame;
pub mod fresnel;
pub mod microfacet;
pub mod plastic;
pub mod roughconductor;
pub mod roughdielectric;
pub mod roughplastic;
pub mod thindielectric;
pub mod warp;

pub use conductor::Conductor;
pub use dielectric::Dielectric;
pub use diffuse::Diffuse;
pub use frame::Frame;
pub use microfacet::{Microfacet, MicrofacetType};
pub use plastic::{specular_sampling_weight, Plastic};
pub use roughconductor::RoughConductor;
pub use roughdielectric::RoughDielectric;
pub use roughplastic::{RoughPlastic, RoughPlasticTable};
pub use thindielectric::ThinDielectric;

/// True when every value is finite, branch-free: `x - x` is 0 for a finite
/// `x` and NaN for an infinity or NaN, and a NaN makes the sum NaN (chained
/// `is_finite` tests compile to a compare and branch per value).
#[inline]
#[allow(clippy::eq_op)] // `x - x` on purpose, see above
pub(crate) fn all_finite<const N: usize>(values: [f32; N]) -> bool {
    // x - x is +0 (all bits clear) for finite x and NaN otherwise; OR-ing the bits
    // keeps the check free of a serial chain of float additions.
    values.iter().fold(0u32, |acc, &x| acc | (x - x).to_bits()) == 0
}

#[inline]
pub(crate) fn finite_or_zero(v: Vec3) -> Vec3 {
    if all_finite(v.to_array()) {
        v
    } else {
        Vec3::ZERO
    }
}

/// A scattering model with its parameters evaluated at one shading point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Bsdf<'a> {
    Diffuse(Diffuse),
    Conductor(Conductor),
    RoughConductor(RoughConductor),
    Dielectric(Dielectric),
    RoughDielectric(RoughDielectric),
    ThinDielectric(ThinDielectric),
    Plastic(Plastic),
    RoughPlastic(RoughPlastic<'a>),
}

macro_rules! dispatch {
    ($self:expr, $b:ident => $e:expr) => {
        match $self {
            Bsdf::Diffuse($b) => $e,
            Bsdf::Conductor($b) => $e,
            Bsdf::RoughConductor($b) => $e,
            Bsdf::Dielectric($b) => $e,
            Bsdf::RoughDielectric($b) => $e,
            Bsdf::ThinDielectric($b) => $e,
            Bsdf::Plastic($b) => $e,
            Bsdf::RoughPlastic($b) => $e,
        }
    };
}

impl Bsdf<'_> {
    pub fn flags(&self) -> BsdfFlags {
        dispatch!(self, b => b.flags())
    }

    /// Samples `wo` given `wi` (local frame). `u_lobe` picks the lobe, `u`
    /// the direction. `None` means no valid sample (the path is absorbed).
    pub fn sample(&self, wi: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        let s = dispatch!(self, b => b.sample(wi, u_lobe, u))?;
        let (w, wo) = (s.weight, s.wo);
        if all_finite([w.x, w.y, w.z, s.pdf, wo.x, wo.y, wo.z])
            && s.pdf > 0.0
            && w.max_element() > 0.0
        {
            Some(s)
        } else {
            None
        }
    }

    /// f(wi, wo) |cos theta_o| (zero for delta lobes).
    pub fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        finite_or_zero(dispatch!(self, b => b.eval(wi, wo)))
    }

    /// Solid-angle density of `sample` producing `wo` (zero for delta lobes).
    pub fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        let p = dispatch!(self, b => b.pdf(wi, wo));
        if p.is_finite() && p > 0.0 {
            p
        } else {
            0.0
        }
    }
}

#[cfg(test)]
mod tests;
