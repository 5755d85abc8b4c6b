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
//!
//! Parameters are already evaluated (textures looked up by the caller), so a
//! `Bsdf` value is small, `Copy`, and built per shading point.

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

pub mod frame;
