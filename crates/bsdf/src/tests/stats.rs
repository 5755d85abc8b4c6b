//! Test utilities: the 2D samples of the shared test RNG, the chi-square distribution (regularised
//! incomplete gamma function, no stats crate) and a spherical histogram
//! goodness-of-fit test of `sample` against `pdf`.

use crate::Bsdf;
use glam::{Vec2, Vec3};

pub use pathfarm_testkit::TestRng;

/// Two uniform numbers in [0, 1): the 2D sample a BSDF's `sample` takes.
pub fn vec2(rng: &mut TestRng) -> Vec2 {
    Vec2::new(rng.f32(), rng.f32())
}

pub use pathfarm_testkit::{chi2_quantile, chi2_sf, sidak};

pub const THETA_BINS: usize = 20;
pub const PHI_BINS: usize = 40;

fn dir(z: f64, phi: f64) -> Vec3 {
    let s = (1.0 - z * z).max(0.0).sqrt();
    Vec3::new((s * phi.cos()) as f32, (s * phi.sin()) as f32, z as f32)
}

fn bin_of(wo: Vec3) -> usize {
    let z = wo.z.clamp(-1.0, 1.0) as f64;
    let i = (((z + 1.0) * 0.5 * THETA_BINS as f64) as usize).min(THETA_BINS - 1);
    let mut phi = (wo.y as f64).atan2(wo.x as f64);
    if phi < 0.0 {
        phi += std::f64::consts::TAU;
    }
    let j = ((phi / std::f64::consts::TAU * PHI_BINS as f64) as usize).min(PHI_BINS - 1);
    i * PHI_BINS + j
}

/// 2-D Simpson estimate over a (z, phi) rectangle.
fn simpson(f: &impl Fn(f64, f64) -> f64, z0: f64, z1: f64, p0: f64, p1: f64) -> f64 {
    let (zm, pm) = (0.5 * (z0 + z1), 0.5 * (p0 + p1));
    let w = [1.0, 4.0, 1.0];
    let zs = [z0, zm, z1];
    let ps = [p0, pm, p1];
    let mut s = 0.0;
    for (a, z) in zs.iter().enumerate() {
        for (b, p) in ps.iter().enumerate() {
            s += w[a] * w[b] * f(*z, *p);
        }
    }
    s * (z1 - z0) * (p1 - p0) / 36.0
}

#[allow(clippy::too_many_arguments)]
fn adaptive(
    f: &impl Fn(f64, f64) -> f64,
    z0: f64,
    z1: f64,
    p0: f64,
    p1: f64,
    whole: f64,
    tol: f64,
    depth: u32,
    min_depth: u32,
) -> f64 {
    let (zm, pm) = (0.5 * (z0 + z1), 0.5 * (p0 + p1));
    let quads = [
        (z0, zm, p0, pm),
        (zm, z1, p0, pm),
        (z0, zm, pm, p1),
        (zm, z1, pm, p1),
    ];
    let parts: Vec<f64> = quads
        .iter()
        .map(|q| simpson(f, q.0, q.1, q.2, q.3))
        .collect();
    let sum: f64 = parts.iter().sum();
    if depth == 0 || (min_depth == 0 && (sum - whole).abs() <= 15.0 * tol) {
        return sum + (sum - whole) / 15.0;
    }
    quads
        .iter()
        .zip(parts)
        .map(|(q, w)| {
            adaptive(
                f,
                q.0,
                q.1,
                q.2,
                q.3,
                w,
                tol / 4.0,
                depth - 1,
                min_depth.saturating_sub(1),
            )
        })
        .sum()
}

/// Result of one goodness-of-fit test.
#[derive(Debug)]
pub struct Chi2Result {
    pub stat: f64,
    pub dof: usize,
    pub p_value: f64,
    /// Fraction of trials that were delta lobes or no sample.
    pub leftover: f64,
}

/// Draws `n` samples of `bsdf` at `wi`, bins the non-delta ones on the
/// sphere (equal-area in cos theta x phi) and compares with the integral of
/// `pdf` over each bin. Delta and failed samples go to one extra cell whose
/// expected mass is 1 - integral of pdf. Cells with expected < 5 are pooled.
pub fn chi2_test(bsdf: &Bsdf, wi: Vec3, n: usize, seed: u64) -> Chi2Result {
    chi2_test_refine(bsdf, wi, n, seed, 6.0)
}

/// [`chi2_test`] with the threshold of a bin's chi-square contribution above
/// which its expected count is re-integrated more accurately.
pub fn chi2_test_refine(bsdf: &Bsdf, wi: Vec3, n: usize, seed: u64, refine: f64) -> Chi2Result {
    let nb = THETA_BINS * PHI_BINS;
    let mut obs = vec![0f64; nb];
    let mut leftover_obs = 0f64;
    let mut rng = TestRng::new(seed);
    for _ in 0..n {
        let u_lobe = rng.f32();
        let u = vec2(&mut rng);
        match bsdf.sample(wi, u_lobe, u) {
            Some(s) if !s.lobe.delta => obs[bin_of(s.wo)] += 1.0,
            _ => leftover_obs += 1.0,
        }
    }
    // Expected counts: adaptive Simpson in (theta, phi) over each bin (theta
    // rather than cos(theta) coordinates resolve narrow lobes at the poles).
    let pdf_theta = |theta: f64, phi: f64| bsdf.pdf(wi, dir(theta.cos(), phi)) as f64 * theta.sin();
    let (dz, dp) = (
        2.0 / THETA_BINS as f64,
        std::f64::consts::TAU / PHI_BINS as f64,
    );
    let tol = 0.5 / n as f64;
    let mut exp = vec![0f64; nb];
    for i in 0..THETA_BINS {
        for j in 0..PHI_BINS {
            let (z0, p0) = (-1.0 + i as f64 * dz, j as f64 * dp);
            let (t0, t1) = ((z0 + dz).min(1.0).acos(), z0.max(-1.0).acos());
            let whole = simpson(&pdf_theta, t0, t1, p0, p0 + dp);
            exp[i * PHI_BINS + j] =
                adaptive(&pdf_theta, t0, t1, p0, p0 + dp, whole, tol, 8, 2).max(0.0) * n as f64;
        }
    }
    // Refine the bins with a large deviation: integrate them again with a
    // fine minimum subdivision. This only makes the expected counts more
    // accurate (a wrong sampler still fails).
    for i in 0..THETA_BINS {
        for j in 0..PHI_BINS {
            let k = i * PHI_BINS + j;
            let (o, e) = (obs[k], exp[k]);
            if (o - e) * (o - e) / e.max(1.0) < refine {
                continue;
            }
            let (z0, p0) = (-1.0 + i as f64 * dz, j as f64 * dp);
            let (t0, t1) = ((z0 + dz).min(1.0).acos(), z0.max(-1.0).acos());
            let whole = simpson(&pdf_theta, t0, t1, p0, p0 + dp);
            exp[k] = adaptive(
                &pdf_theta,
                t0,
                t1,
                p0,
                p0 + dp,
                whole,
                0.02 / n as f64,
                14,
                5,
            )
            .max(0.0)
                * n as f64;
        }
    }
    let total: f64 = exp.iter().sum();
    let mut cells: Vec<(f64, f64)> = obs.iter().copied().zip(exp.iter().copied()).collect();
    cells.push((leftover_obs, (n as f64 - total).max(0.0)));
    // Pool the cells with small expected counts.
    let (mut pool_o, mut pool_e) = (0.0, 0.0);
    let mut kept: Vec<(f64, f64)> = Vec::new();
    for (o, e) in cells {
        if e < 5.0 {
            pool_o += o;
            pool_e += e;
        } else {
            kept.push((o, e));
        }
    }
    if pool_e >= 5.0 || kept.is_empty() {
        kept.push((pool_o, pool_e));
    } else if pool_o > 0.0 || pool_e > 0.0 {
        // Merge into the smallest kept cell.
        let k = kept
            .iter()
            .enumerate()
            .min_by(|a, b| a.1 .1.partial_cmp(&b.1 .1).unwrap())
            .unwrap()
            .0;
        kept[k].0 += pool_o;
        kept[k].1 += pool_e;
    }
    let stat: f64 = kept
        .iter()
        .map(|(o, e)| {
            if *e > 0.0 {
                (o - e) * (o - e) / e
            } else if *o > 0.0 {
                f64::INFINITY
            } else {
                0.0
            }
        })
        .sum();
    let dof = kept.len().saturating_sub(1).max(1);
    Chi2Result {
        stat,
        dof,
        p_value: if stat.is_finite() {
            chi2_sf(stat, dof)
        } else {
            0.0
        },
        leftover: leftover_obs / n as f64,
    }
}

/// Direction at polar angle `theta_deg` (measured from +z; > 90 is below
/// the surface) and azimuth `phi_deg`.
pub fn sph(theta_deg: f32, phi_deg: f32) -> Vec3 {
    let (t, p) = (theta_deg.to_radians(), phi_deg.to_radians());
    Vec3::new(t.sin() * p.cos(), t.sin() * p.sin(), t.cos())
}
