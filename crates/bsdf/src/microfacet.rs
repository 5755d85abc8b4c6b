//! Microfacet distributions (Beckmann and GGX / Trowbridge–Reitz) with the
//! same conventions as Mitsuba's `microfacet.h`: anisotropic roughness
//! `alpha_u`/`alpha_v` (clamped to >= 1e-4), Smith shadowing-masking (the
//! Beckmann one via Mitsuba's rational approximation), and either
//! visible-normal sampling (Heitz & d'Eon 2014, default) or sampling of
//! D(m) cos(theta_m).

use crate::warp::square_to_uniform_disk_concentric;
use glam::{Vec2, Vec3};
use std::f32::consts::PI;

/// Which normal distribution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MicrofacetType {
    Beckmann,
    Ggx,
}

/// A microfacet distribution with (possibly anisotropic) roughness.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Microfacet {
    pub kind: MicrofacetType,
    pub alpha_u: f32,
    pub alpha_v: f32,
    pub sample_visible: bool,
}

impl Microfacet {
    /// Roughness values are clamped to at least 1e-4 (as Mitsuba).
    pub fn new(kind: MicrofacetType, alpha_u: f32, alpha_v: f32, sample_visible: bool) -> Self {
        Self {
            kind,
            alpha_u: alpha_u.max(1e-4),
            alpha_v: alpha_v.max(1e-4),
            sample_visible,
        }
    }

    #[inline]
    pub fn is_isotropic(&self) -> bool {
        self.alpha_u == self.alpha_v
    }

    /// Multiplies both roughness values (Walter et al.'s sampling trick).
    #[inline]
    pub fn scale_alpha(&mut self, s: f32) {
        self.alpha_u *= s;
        self.alpha_v *= s;
    }

    /// Normal distribution function D(m).
    #[inline]
    pub fn eval(&self, m: Vec3) -> f32 {
        let alpha_uv = self.alpha_u * self.alpha_v;
        let cos2 = m.z * m.z;
        let result = match self.kind {
            MicrofacetType::Beckmann => {
                let e = (sq(m.x / self.alpha_u) + sq(m.y / self.alpha_v)) / cos2;
                (-e).exp() / (PI * alpha_uv * cos2 * cos2)
            }
            MicrofacetType::Ggx => {
                1.0 / (PI
                    * alpha_uv
                    * sq(sq(m.x / self.alpha_u) + sq(m.y / self.alpha_v) + m.z * m.z))
            }
        };
        // Also rejects NaN (m.z == 0) and the lower hemisphere.
        if result * m.z > 1e-20 && result.is_finite() {
            result
        } else {
            0.0
        }
    }

    /// Density of [`Self::sample`] producing the microfacet normal `m`.
    #[inline]
    pub fn pdf(&self, wi: Vec3, m: Vec3) -> f32 {
        let d = self.eval(m);
        let r = if self.sample_visible {
            d * self.smith_g1(wi, m) * wi.dot(m).abs() / wi.z
        } else {
            d * m.z
        };
        if r.is_finite() {
            r
        } else {
            0.0
        }
    }

    /// Samples a microfacet normal; returns `(m, pdf)` (pdf as [`Self::pdf`]).
    /// `wi` must be in the upper hemisphere when sampling visible normals.
    pub fn sample(&self, wi: Vec3, u: Vec2) -> (Vec3, f32) {
        if !self.sample_visible {
            let (sin_phi, cos_phi, alpha_2);
            if self.is_isotropic() {
                let (s, c) = (2.0 * PI * u.y).sin_cos();
                sin_phi = s;
                cos_phi = c;
                alpha_2 = self.alpha_u * self.alpha_u;
            } else {
                let ratio = self.alpha_v / self.alpha_u;
                let tmp = ratio * (2.0 * PI * u.y).tan();
                let c = (1.0 / (tmp * tmp + 1.0).sqrt()).copysign((u.y - 0.5).abs() - 0.25);
                cos_phi = c;
                sin_phi = c * tmp;
                alpha_2 = 1.0 / (sq(cos_phi / self.alpha_u) + sq(sin_phi / self.alpha_v));
            }
            let (cos_theta, pdf);
            match self.kind {
                MicrofacetType::Beckmann => {
                    cos_theta = 1.0 / (1.0 - alpha_2 * (1.0 - u.x).ln()).sqrt();
                    let c3 = (cos_theta * cos_theta * cos_theta).max(1e-20);
                    pdf = (1.0 - u.x) / (PI * self.alpha_u * self.alpha_v * c3);
                }
                MicrofacetType::Ggx => {
                    let tan2 = alpha_2 * u.x / (1.0 - u.x);
                    cos_theta = 1.0 / (1.0 + tan2).sqrt();
                    let temp = 1.0 + tan2 / alpha_2;
                    let c3 = (cos_theta * cos_theta * cos_theta).max(1e-20);
                    pdf = 1.0 / (PI * self.alpha_u * self.alpha_v * c3 * temp * temp);
                }
            }
            let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
            (
                Vec3::new(cos_phi * sin_theta, sin_phi * sin_theta, cos_theta),
                pdf,
            )
        } else {
            // Stretch wi to the unit-roughness configuration.
            let wi_p = Vec3::new(self.alpha_u * wi.x, self.alpha_v * wi.y, wi.z).normalize();
            let (sin_phi, cos_phi) = sincos_phi(wi_p);
            let slope = self.sample_visible_11(wi_p.z, u);
            let sx = (cos_phi * slope.x - sin_phi * slope.y) * self.alpha_u;
            let sy = (sin_phi * slope.x + cos_phi * slope.y) * self.alpha_v;
            let m = Vec3::new(-sx, -sy, 1.0).normalize();
            let pdf = self.eval(m) * self.smith_g1(wi, m) * wi.dot(m).abs() / wi.z;
            (m, pdf)
        }
    }

    /// [`Self::sample`] for visible normals without computing the pdf
    /// (used to build the rough plastic tables).
    #[inline]
    pub(crate) fn sample_visible_normal(&self, wi: Vec3, u: Vec2) -> Vec3 {
        let wi_p = Vec3::new(self.alpha_u * wi.x, self.alpha_v * wi.y, wi.z).normalize();
        let (sin_phi, cos_phi) = sincos_phi(wi_p);
        let slope = self.sample_visible_11(wi_p.z, u);
        let sx = (cos_phi * slope.x - sin_phi * slope.y) * self.alpha_u;
        let sy = (sin_phi * slope.x + cos_phi * slope.y) * self.alpha_v;
        Vec3::new(-sx, -sy, 1.0).normalize()
    }

    /// Smith's separable shadowing-masking G(wi, wo, m) = G1(wi, m) G1(wo, m).
    #[inline]
    pub fn g(&self, wi: Vec3, wo: Vec3, m: Vec3) -> f32 {
        self.smith_g1(wi, m) * self.smith_g1(wo, m)
    }

    /// Smith's shadowing function G1(v, m); zero when v sees the back of m.
    #[inline]
    pub fn smith_g1(&self, v: Vec3, m: Vec3) -> f32 {
        let xy_alpha_2 = sq(self.alpha_u * v.x) + sq(self.alpha_v * v.y);
        if v.dot(m) * v.z <= 0.0 {
            return 0.0;
        }
        if xy_alpha_2 == 0.0 {
            return 1.0;
        }
        let tan_theta_alpha_2 = xy_alpha_2 / (v.z * v.z);
        match self.kind {
            MicrofacetType::Beckmann => {
                let a = 1.0 / tan_theta_alpha_2.sqrt();
                if a >= 1.6 {
                    1.0
                } else {
                    let a2 = a * a;
                    (3.535 * a + 2.181 * a2) / (1.0 + 2.276 * a + 2.577 * a2)
                }
            }
            MicrofacetType::Ggx => 2.0 / (1.0 + (1.0 + tan_theta_alpha_2).sqrt()),
        }
    }

    /// Samples the slope distribution of visible normals for unit roughness.
    fn sample_visible_11(&self, cos_theta_i: f32, mut u: Vec2) -> Vec2 {
        match self.kind {
            MicrofacetType::Beckmann => {
                let tan_theta_i = (1.0 - cos_theta_i * cos_theta_i).max(0.0).sqrt() / cos_theta_i;
                let cot_theta_i = 1.0 / tan_theta_i;
                let maxval = erf(cot_theta_i);
                u = u.clamp(Vec2::splat(1e-6), Vec2::splat(1.0 - 1e-6));
                let mut x = maxval - (maxval + 1.0) * erf((-u.x.ln()).sqrt());
                let inv_sqrt_pi = 0.564_189_6_f32;
                u.x *=
                    1.0 + maxval + inv_sqrt_pi * tan_theta_i * (-cot_theta_i * cot_theta_i).exp();
                for _ in 0..3 {
                    let slope = erfinv(x);
                    let value = 1.0 + x + inv_sqrt_pi * tan_theta_i * (-slope * slope).exp() - u.x;
                    let derivative = 1.0 - slope * tan_theta_i;
                    x -= value / derivative;
                }
                Vec2::new(erfinv(x), erfinv(2.0 * u.y - 1.0))
            }
            MicrofacetType::Ggx => {
                let mut p = square_to_uniform_disk_concentric(u);
                let s = 0.5 * (1.0 + cos_theta_i);
                let h = (1.0 - p.x * p.x).max(0.0).sqrt();
                p.y = h + (p.y - h) * s;
                let (x, y) = (p.x, p.y);
                let z = (1.0 - p.length_squared()).max(0.0).sqrt();
                let sin_theta_i = (1.0 - cos_theta_i * cos_theta_i).max(0.0).sqrt();
                let norm = 1.0 / (sin_theta_i * y + cos_theta_i * z);
                Vec2::new(cos_theta_i * y - sin_theta_i * z, x) * norm
            }
        }
    }
}

#[inline]
fn sq(x: f32) -> f32 {
    x * x
}

/// (sin phi, cos phi) of a direction, (0, 1) on the pole (as Mitsuba's Frame).
#[inline]
fn sincos_phi(v: Vec3) -> (f32, f32) {
    let sin_theta_2 = 1.0 - v.z * v.z;
    if sin_theta_2.abs() <= 4.0 * 5.960_464_5e-8 {
        return (0.0, 1.0);
    }
    let inv = 1.0 / sin_theta_2.sqrt();
    ((v.y * inv).clamp(-1.0, 1.0), (v.x * inv).clamp(-1.0, 1.0))
}

/// Error function (f64 internally; Chebyshev fit of erfc, rel. error < 1.2e-7).
pub fn erf(x: f32) -> f32 {
    let x = x as f64;
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let ans = t
        * (-z * z - 1.26551223
            + t * (1.00002368
                + t * (0.37409196
                    + t * (0.09678418
                        + t * (-0.18628806
                            + t * (0.27886807
                                + t * (-1.13520398
                                    + t * (1.48851587 + t * (-0.82215223 + t * 0.17087277)))))))))
            .exp();
    let erfc = if x >= 0.0 { ans } else { 2.0 - ans };
    (1.0 - erfc) as f32
}

/// Inverse error function (Giles 2010 single-precision approximation).
#[allow(clippy::excessive_precision)]
pub fn erfinv(x: f32) -> f32 {
    if x <= -1.0 {
        return f32::NEG_INFINITY;
    }
    if x >= 1.0 {
        return f32::INFINITY;
    }
    let mut w = -((1.0 - x) * (1.0 + x)).ln();
    let p;
    if w < 5.0 {
        w -= 2.5;
        let mut q = 2.810_226_4e-8f32;
        q = 3.432_739_4e-7 + q * w;
        q = -3.523_387_7e-6 + q * w;
        q = -4.391_506_5e-6 + q * w;
        q = 0.000_218_580_87 + q * w;
        q = -0.001_253_725 + q * w;
        q = -0.004_177_681_6 + q * w;
        q = 0.246_640_73 + q * w;
        q = 1.501_409_4 + q * w;
        p = q;
    } else {
        w = w.sqrt() - 3.0;
        let mut q = -0.000_200_214_26f32;
        q = 0.000_100_950_56 + q * w;
        q = 0.001_349_343_2 + q * w;
        q = -0.003_673_428_4 + q * w;
        q = 0.005_739_507_7 + q * w;
        q = -0.007_622_461_3 + q * w;
        q = 0.009_438_870_5 + q * w;
        q = 1.001_674_1 + q * w;
        q = 2.832_976_8 + q * w;
        p = q;
    }
    p * x
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erf_and_erfinv_are_inverse_and_match_known_values() {
        assert!((erf(0.5) - 0.520_499_9).abs() < 2e-7);
        assert!((erf(-1.5) + 0.966_105_1).abs() < 2e-7);
        for x in [-0.999f32, -0.7, -0.1, 0.0, 0.3, 0.9, 0.99999] {
            let y = erfinv(x);
            assert!((erf(y) - x).abs() < 2e-6, "{x}: {}", erf(y));
        }
    }

    #[test]
    fn distributions_are_normalised_in_projected_area() {
        // Integral of D(m) cos(theta_m) over the hemisphere is 1.
        for kind in [MicrofacetType::Beckmann, MicrofacetType::Ggx] {
            for (au, av) in [(0.1f32, 0.1f32), (0.5, 0.5), (0.1, 0.4)] {
                let d = Microfacet::new(kind, au, av, true);
                let (nt, np) = (4000, 256);
                let mut sum = 0.0f64;
                for i in 0..nt {
                    // substitute cos(theta) = z, integrate dz dphi
                    let z = (i as f64 + 0.5) / nt as f64;
                    for j in 0..np {
                        let phi = (j as f64 + 0.5) / np as f64 * std::f64::consts::TAU;
                        let s = (1.0 - z * z).sqrt();
                        let m = Vec3::new((s * phi.cos()) as f32, (s * phi.sin()) as f32, z as f32);
                        sum += d.eval(m) as f64 * z;
                    }
                }
                let integral = sum / nt as f64 * std::f64::consts::TAU / np as f64;
                assert!(
                    (integral - 1.0).abs() < 5e-3,
                    "{kind:?} {au} {av}: {integral}"
                );
            }
        }
    }
}
