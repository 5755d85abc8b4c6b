//! Rough plastic (Mitsuba `roughplastic`): a rough dielectric coating
//! (Beckmann/GGX, isotropic) over a diffuse substrate. The coating's
//! directional transmittance and its internal hemispherical reflectance are
//! precomputed per (distribution, alpha, eta) in a [`RoughPlasticTable`].

use crate::fresnel::{fresnel_dielectric, reflect_about, refract_about};
use crate::microfacet::{Microfacet, MicrofacetType};
use crate::warp::{square_to_cosine_hemisphere, square_to_cosine_hemisphere_pdf};
use crate::{finite_or_zero, BsdfFlags, BsdfSample};
use glam::{Vec2, Vec3};
use std::f32::consts::FRAC_1_PI;

/// Resolution of the transmittance table in cos(theta) (Mitsuba's
/// `MI_ROUGH_TRANSMITTANCE_RES`).
pub const ROUGH_TRANSMITTANCE_RES: usize = 64;

/// Precomputed coating quantities for one rough plastic material.
#[derive(Clone, Debug, PartialEq)]
pub struct RoughPlasticTable {
    pub distribution: MicrofacetType,
    pub alpha: f32,
    pub eta: f32,
    /// Transmittance into the coating, tabulated at
    /// cos(theta) = max(1e-6, i / (RES - 1)).
    pub external_transmittance: Vec<f32>,
    /// Hemispherical (cosine-weighted) internal reflectance of the coating.
    pub internal_reflectance: f32,
}

impl RoughPlasticTable {
    /// Same quadrature as Mitsuba (Gauss–Legendre 32x32 for eta > 1,
    /// 128x128 otherwise, over visible-normal samples; 64 cos(theta) nodes).
    ///
    /// This is ~1.1 M microfacet samples (for eta > 1), i.e. tens of ms, so
    /// finished tables are memoised process-wide by (distribution, alpha,
    /// eta): building the same table again is a cheap clone.
    pub fn new(distribution: MicrofacetType, alpha: f32, eta: f32) -> Self {
        use std::sync::Mutex;
        static CACHE: Mutex<Vec<RoughPlasticTable>> = Mutex::new(Vec::new());
        let alpha_c = alpha.max(1e-4);
        let hit = |t: &&RoughPlasticTable| {
            t.distribution == distribution
                && t.alpha.to_bits() == alpha_c.to_bits()
                && t.eta.to_bits() == eta.to_bits()
        };
        if let Some(t) = CACHE
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .find(hit)
        {
            return t.clone();
        }
        let t = Self::compute(distribution, alpha, eta);
        let mut cache = CACHE.lock().unwrap_or_else(|e| e.into_inner());
        if cache.len() < 4096 && !cache.iter().any(|c| hit(&c)) {
            cache.push(t.clone());
        }
        t
    }

    /// Builds the table without the cache.
    pub fn compute(distribution: MicrofacetType, alpha: f32, eta: f32) -> Self {
        let distr = Microfacet::new(distribution, alpha, alpha, true);
        let res = ROUGH_TRANSMITTANCE_RES;
        let mus: Vec<f32> = (0..res)
            .map(|i| (i as f32 / (res - 1) as f32).max(1e-6))
            .collect();
        let q_t = GaussLegendre::new(if eta > 1.0 { 32 } else { 128 });
        let inv_eta = 1.0 / eta;
        let q_r = GaussLegendre::new(if inv_eta > 1.0 { 32 } else { 128 });
        // Each cos(theta) row is independent: evaluate rows in parallel
        // (deterministic, the per-row sums are done sequentially).
        let rows: Vec<(f32, f32)> = parallel_map(&mus, |&mu| {
            let wi = Vec3::new((1.0 - mu * mu).sqrt(), 0.0, mu);
            (
                eval_transmittance(&distr, &q_t, wi, eta),
                eval_reflectance(&distr, &q_r, wi, inv_eta) * mu,
            )
        });
        let external_transmittance = rows.iter().map(|r| r.0).collect();
        let internal_reflectance = rows.iter().map(|r| r.1).sum::<f32>() / res as f32 * 2.0;
        Self {
            distribution,
            alpha: distr.alpha_u,
            eta,
            external_transmittance,
            internal_reflectance,
        }
    }

    /// Linear interpolation in the transmittance table (Mitsuba's `lerp_gather`).
    #[inline]
    pub fn transmittance(&self, cos_theta: f32) -> f32 {
        let n = self.external_transmittance.len();
        let x = cos_theta.clamp(0.0, 1.0) * (n - 1) as f32;
        let i = (x as usize).min(n - 2);
        let (v0, v1) = (
            self.external_transmittance[i],
            self.external_transmittance[i + 1],
        );
        v0 + (v1 - v0) * (x - i as f32)
    }
}

fn parallel_map<T: Sync, R: Send + Copy + Default>(
    items: &[T],
    f: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    let threads = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
        .clamp(1, 8);
    let mut out = vec![R::default(); items.len()];
    if threads == 1 {
        for (o, it) in out.iter_mut().zip(items) {
            *o = f(it);
        }
        return out;
    }
    let chunk = items.len().div_ceil(threads);
    std::thread::scope(|s| {
        for (oc, ic) in out.chunks_mut(chunk).zip(items.chunks(chunk)) {
            let f = &f;
            s.spawn(move || {
                for (o, it) in oc.iter_mut().zip(ic) {
                    *o = f(it);
                }
            });
        }
    });
    out
}

/// Gauss–Legendre nodes/weights on [-1, 1].
struct GaussLegendre {
    nodes: Vec<f32>,
    weights: Vec<f32>,
}

impl GaussLegendre {
    fn new(n: usize) -> Self {
        let mut nodes = vec![0.0f32; n];
        let mut weights = vec![0.0f32; n];
        for i in 0..n.div_ceil(2) {
            // Initial guess, then Newton on P_n.
            let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0f64, x);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-16 {
                    break;
                }
            }
            let w = 2.0 / ((1.0 - x * x) * dp * dp);
            nodes[i] = -x as f32;
            nodes[n - 1 - i] = x as f32;
            weights[i] = w as f32;
            weights[n - 1 - i] = w as f32;
        }
        Self { nodes, weights }
    }
}

/// Mitsuba's quadrature over the visible normals `m` of `wi`: the sum of
/// `integrand(m)` at the Gauss–Legendre nodes mapped to [0, 1]^2, each weighted
/// by its node weights / 4 (the Jacobian of that map). Both coating integrals
/// below are this sum; one loop keeps their node order (and so their rounding)
/// the same as Mitsuba's.
#[inline]
fn sum_over_visible_normals(
    distr: &Microfacet,
    q: &GaussLegendre,
    wi: Vec3,
    integrand: impl Fn(Vec3) -> f32,
) -> f32 {
    let mut result = 0.0f32;
    // Mitsuba's meshgrid: x varies fastest.
    for (ny, wy) in q.nodes.iter().zip(&q.weights) {
        for (nx, wx) in q.nodes.iter().zip(&q.weights) {
            let node = Vec2::new(nx * 0.5 + 0.5, ny * 0.5 + 0.5);
            let m = distr.sample_visible_normal(wi, node);
            result += integrand(m) * (wx * wy) * 0.25;
        }
    }
    result
}

/// Mitsuba's `eval_transmittance`: fraction of light refracted into the
/// coating (and not shadowed) for incident direction `wi`.
fn eval_transmittance(distr: &Microfacet, q: &GaussLegendre, wi: Vec3, eta: f32) -> f32 {
    sum_over_visible_normals(distr, q, wi, |m| {
        let (f, cos_theta_t, _eta_it, eta_ti) = fresnel_dielectric(wi.dot(m), eta);
        let wo = refract_about(wi, m, cos_theta_t, eta_ti);
        let smith = distr.smith_g1(wo, m) * (1.0 - f);
        if wo.z * wi.z >= 0.0 || !smith.is_finite() {
            0.0
        } else {
            smith
        }
    })
}

/// Mitsuba's `eval_reflectance`: fraction of light reflected by the coating.
fn eval_reflectance(distr: &Microfacet, q: &GaussLegendre, wi: Vec3, eta: f32) -> f32 {
    sum_over_visible_normals(distr, q, wi, |m| {
        let wo = reflect_about(wi, m);
        let f = fresnel_dielectric(wi.dot(m), eta).0;
        let smith = distr.smith_g1(wo, m) * f;
        if wo.z <= 0.0 || wi.z <= 0.0 || !smith.is_finite() {
            0.0
        } else {
            smith
        }
    })
}

/// Per-hit rough plastic, borrowing its material's table.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RoughPlastic<'a> {
    pub table: &'a RoughPlasticTable,
    pub diffuse_reflectance: Vec3,
    pub specular_reflectance: Vec3,
    pub nonlinear: bool,
    /// See [`crate::plastic::specular_sampling_weight`].
    pub specular_sampling_weight: f32,
    /// Visible-normal sampling of the specular lobe (Mitsuba default true).
    pub sample_visible: bool,
}

impl<'a> RoughPlastic<'a> {
    pub fn new(
        table: &'a RoughPlasticTable,
        diffuse_reflectance: Vec3,
        specular_reflectance: Vec3,
        nonlinear: bool,
        specular_sampling_weight: f32,
        sample_visible: bool,
    ) -> Self {
        Self {
            table,
            diffuse_reflectance,
            specular_reflectance,
            nonlinear,
            specular_sampling_weight,
            sample_visible,
        }
    }

    #[inline]
    fn distr(&self) -> Microfacet {
        Microfacet::new(
            self.table.distribution,
            self.table.alpha,
            self.table.alpha,
            self.sample_visible,
        )
    }

    pub fn flags(&self) -> BsdfFlags {
        BsdfFlags::GLOSSY_REFLECTION
    }

    #[inline]
    fn prob_specular(&self, t_i: f32) -> f32 {
        let ps = (1.0 - t_i) * self.specular_sampling_weight;
        let pd = t_i * (1.0 - self.specular_sampling_weight);
        let p = ps / (ps + pd);
        if p.is_finite() {
            p
        } else {
            0.0
        }
    }

    pub fn sample(&self, wi: Vec3, u_lobe: f32, u: Vec2) -> Option<BsdfSample> {
        if !(wi.z > 0.0) {
            return None;
        }
        let t_i = self.table.transmittance(wi.z);
        let prob_specular = self.prob_specular(t_i);
        let wo = if u_lobe < prob_specular {
            let (m, _) = self.distr().sample(wi, u);
            reflect_about(wi, m)
        } else {
            square_to_cosine_hemisphere(u)
        };
        let pdf = self.pdf(wi, wo);
        if !(pdf > 0.0) || !pdf.is_finite() {
            return None;
        }
        let weight = self.eval(wi, wo) / pdf;
        BsdfSample::glossy_reflection(wo, pdf, weight).if_finite()
    }

    pub fn eval(&self, wi: Vec3, wo: Vec3) -> Vec3 {
        if !(wi.z > 0.0 && wo.z > 0.0) {
            return Vec3::ZERO;
        }
        let distr = self.distr();
        let h = (wo + wi).normalize();
        let d = distr.eval(h);
        let f = fresnel_dielectric(wi.dot(h), self.table.eta).0;
        let g = distr.g(wi, wo, h);
        let spec = self.specular_reflectance * (f * d * g / (4.0 * wi.z));
        let t_i = self.table.transmittance(wi.z);
        let t_o = self.table.transmittance(wo.z);
        let diff = self.diffuse_reflectance;
        let ri = self.table.internal_reflectance;
        let denom = if self.nonlinear {
            Vec3::ONE - diff * ri
        } else {
            Vec3::splat(1.0 - ri)
        };
        let eta = self.table.eta;
        let v = spec + diff / denom * (FRAC_1_PI / (eta * eta) * wo.z * t_i * t_o);
        finite_or_zero(v)
    }

    pub fn pdf(&self, wi: Vec3, wo: Vec3) -> f32 {
        if !(wi.z > 0.0 && wo.z > 0.0) {
            return 0.0;
        }
        let t_i = self.table.transmittance(wi.z);
        let prob_specular = self.prob_specular(t_i);
        let prob_diffuse = 1.0 - prob_specular;
        let h = (wo + wi).normalize();
        let distr = self.distr();
        let spec = if self.sample_visible {
            distr.eval(h) * distr.smith_g1(wi, h) / (4.0 * wi.z)
        } else {
            distr.pdf(wi, h) / (4.0 * wo.dot(h))
        };
        let r = prob_specular * spec + prob_diffuse * square_to_cosine_hemisphere_pdf(wo);
        if r.is_finite() {
            r
        } else {
            0.0
        }
    }
}
