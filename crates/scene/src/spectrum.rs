//! Spectra given as `wavelength:value` pairs, turned into the linear sRGB colour Mitsuba 3's
//! RGB variants give them (`spectrum_list_to_srgb`): the piecewise-linear spectrum is
//! integrated against the CIE 1931 matching functions (times the D65 illuminant, unless it
//! is an emitter's), at 1000 wavelengths from 360 to 830 nm, and the XYZ result converted to
//! sRGB. A reflectance is then clamped to [0, 1], anything else to >= 0.

use glam::{DVec3, Vec3};

use crate::cie::{D65, XYZ, Y_NORMALIZATION};

const MIN: f64 = 360.0;
const MAX: f64 = 830.0;
const STEPS: usize = 1000;

/// XYZ to linear sRGB (D65 white).
fn xyz_to_srgb(c: DVec3) -> DVec3 {
    DVec3::new(
        3.240479 * c.x - 1.537150 * c.y - 0.498535 * c.z,
        -0.969256 * c.x + 1.875991 * c.y + 0.041556 * c.z,
        0.055648 * c.x - 0.204043 * c.y + 1.057311 * c.z,
    )
}

/// Linear interpolation in a table sampled every 5 nm from 360 nm.
fn table<T: Copy>(t: &[T], w: f64, get: impl Fn(T) -> DVec3) -> DVec3 {
    let x = (w - MIN) * ((t.len() - 1) as f64 / (MAX - MIN));
    let i = (x.max(0.0) as usize).min(t.len() - 2);
    let f = x - i as f64;
    get(t[i]) * (1.0 - f) + get(t[i + 1]) * f
}

/// How a spectrum is used, which decides its conversion.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Use {
    /// A reflectance or other colour in [0, 1]: against D65, clamped to [0, 1].
    Reflectance,
    /// A quantity that may exceed 1 (an index of refraction): against D65, clamped to >= 0.
    Unbounded,
    /// An emitter's radiance: not weighted by D65, clamped to >= 0.
    Emission,
}

/// The sRGB colour of the spectrum `pairs` (wavelengths in nm, strictly increasing, at
/// least two).
pub(crate) fn to_srgb(pairs: &[(f32, f32)], usage: Use) -> Vec3 {
    let d65 = usage != Use::Emission;
    let (first, last) = (pairs[0].0 as f64, pairs[pairs.len() - 1].0 as f64);
    let mut xyz = DVec3::ZERO;
    for i in 0..STEPS {
        let w = MIN + i as f64 / (STEPS - 1) as f64 * (MAX - MIN);
        if w < first || w > last {
            continue;
        }
        let k = pairs
            .partition_point(|p| p.0 as f64 <= w)
            .clamp(1, pairs.len() - 1)
            - 1;
        let ((w0, v0), (w1, v1)) = (pairs[k], pairs[k + 1]);
        let (w0, v0, w1, v1) = (w0 as f64, v0 as f64, w1 as f64, v1 as f64);
        let v = ((w - w1) * v0 + (w0 - w) * v1) / (w0 - w1);
        let weight = match d65 {
            true => table(&D65, w, |d| DVec3::splat(d as f64)).x,
            false => 1.0,
        };
        xyz += table(&XYZ, w, |c| {
            DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64)
        }) * v
            * weight;
    }
    xyz *= (MAX - MIN) * Y_NORMALIZATION / STEPS as f64;
    let rgb = xyz_to_srgb(xyz);
    let rgb = match usage {
        Use::Reflectance => rgb.clamp(DVec3::ZERO, DVec3::ONE),
        _ => rgb.max(DVec3::ZERO),
    };
    rgb.as_vec3()
}

/// The colour of a uniform spectrum of `value` on an emitter: Mitsuba 3's RGB variants give
/// it the sRGB of XYZ (1, 1, 1) times the value (white in XYZ is not white in sRGB), so that
/// they match its spectral variants.
pub(crate) fn uniform_emission(value: f32) -> Vec3 {
    (xyz_to_srgb(DVec3::ONE) * value as f64).as_vec3()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: Vec3, b: [f32; 3]) -> bool {
        (a - Vec3::from(b)).abs().max_element() < 2e-5
    }

    /// Expected values: Mitsuba 3.9.1, `mi.spectrum_list_to_srgb(w, v, bounded, d65)` and
    /// `mi.xyz_to_srgb`.
    #[test]
    fn spectra_turn_into_the_colours_mitsuba_3_gives_them() {
        let r = [(400.0, 0.1), (500.0, 0.5), (600.0, 0.8), (700.0, 0.3)];
        let got = to_srgb(&r, Use::Reflectance);
        assert!(close(got, [0.752186, 0.64527, 0.271707]), "{got}");
        let got = to_srgb(&r, Use::Emission);
        assert!(close(got, [0.883847, 0.618319, 0.236324]), "{got}");
        let got = to_srgb(&[(400.0, 1.0), (700.0, 2.0)], Use::Emission);
        assert!(close(got, [2.14, 1.40424, 1.01714]), "{got}");
        let got = uniform_emission(2.0);
        assert!(close(got, [2.40959, 1.89658, 1.81783]), "{got}");
    }

    #[test]
    fn a_reflectance_out_of_gamut_is_clamped_and_an_emission_is_not_capped() {
        let saturated = [(600.0, 0.0), (640.0, 50.0), (680.0, 0.0)];
        let r = to_srgb(&saturated, Use::Reflectance);
        assert!(r.min_element() >= 0.0 && r.max_element() <= 1.0, "{r}");
        let e = to_srgb(&saturated, Use::Emission);
        assert!(e.min_element() >= 0.0 && e.x > 1.0, "{e}");
    }
}
