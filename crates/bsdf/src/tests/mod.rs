mod behaviour;
mod chi2;
mod mitsuba_values;
mod stats;
mod table;

use crate::{Bsdf, Conductor, Microfacet, MicrofacetType, RoughConductor, RoughDielectric};
use glam::Vec3;

// The tests build many rough models; these spell one in a line, naming the roughness
// pair as one value.

/// A white (unit specular reflectance) rough conductor of complex IOR `eta + i k`.
fn rough_conductor(
    kind: MicrofacetType,
    alpha: (f32, f32),
    vis: bool,
    eta: Vec3,
    k: Vec3,
) -> Bsdf<'static> {
    let distr = Microfacet::new(kind, alpha.0, alpha.1, vis);
    Bsdf::RoughConductor(RoughConductor::new(
        distr,
        Conductor::new(eta, k, Vec3::ONE),
    ))
}

/// A rough dielectric of relative IOR `eta`, reflectance `r` and transmittance `t`.
fn rough_dielectric(
    kind: MicrofacetType,
    alpha: (f32, f32),
    vis: bool,
    eta: f32,
    r: Vec3,
    t: Vec3,
) -> Bsdf<'static> {
    let distr = Microfacet::new(kind, alpha.0, alpha.1, vis);
    Bsdf::RoughDielectric(RoughDielectric::new(distr, eta, r, t))
}
