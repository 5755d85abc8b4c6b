//! Latitude-longitude environment map with Mitsuba's orientation
//! (u = atan2(x, -z) / 2pi, v = acos(y) / pi in the emitter's frame),
//! importance sampled by luminance times sin(theta).

use glam::{Mat4, Vec2, Vec3};
use std::f32::consts::PI;
use std::sync::Arc;

use super::LightSample;
use crate::sampling::Distribution1D;

/// An environment light from a latitude-longitude RGB image, importance sampled by luminance
/// times sin(theta).
pub struct EnvMap {
    width: u32,
    height: u32,
    texels: Arc<Vec<Vec3>>,
    scale: f32,
    to_world: Mat4,
    to_local: Mat4,
    /// Marginal over rows.
    rows: Distribution1D,
    /// Conditional over columns, per row.
    cols: Vec<Distribution1D>,
}

fn luminance(c: Vec3) -> f32 {
    0.212671 * c.x + 0.715160 * c.y + 0.072169 * c.z
}

impl EnvMap {
    /// Builds the map from `width x height` linear RGB texels (row-major, row 0 at the top, i.e. at
    /// +y of the emitter's frame), scaled by `scale`, oriented by `to_world`, and precomputes its
    /// sampling distributions.
    pub fn new(
        width: u32,
        height: u32,
        texels: Arc<Vec<Vec3>>,
        scale: f32,
        to_world: Mat4,
    ) -> Self {
        let (w, h) = (width as usize, height as usize);
        let lum: Vec<f32> = texels.iter().map(|&c| luminance(c).max(0.0)).collect();
        let mean = lum.iter().map(|&l| l as f64).sum::<f64>() as f32 / lum.len().max(1) as f32;
        let mut cols = Vec::with_capacity(h);
        let mut row_w = Vec::with_capacity(h);
        for y in 0..h {
            let sin_theta = (PI * (y as f32 + 0.5) / h as f32).sin();
            // Max over the 3x3 neighbourhood: the bilinear lookup reaches that far,
            // so every texel that can return a non-zero value has non-zero density.
            let weights: Vec<f32> = (0..w)
                .map(|x| {
                    let mut m = 0.0f32;
                    for dy in -1i64..=1 {
                        let yy = (y as i64 + dy).clamp(0, h as i64 - 1) as usize;
                        for dx in -1i64..=1 {
                            let xx = (x as i64 + dx).rem_euclid(w as i64) as usize;
                            m = m.max(lum[yy * w + xx]);
                        }
                    }
                    (m + 1e-4 * mean) * sin_theta
                })
                .collect();
            let d = Distribution1D::new(&weights);
            row_w.push(d.total() as f32);
            cols.push(d);
        }
        Self {
            width,
            height,
            texels,
            scale,
            to_world,
            to_local: to_world.inverse(),
            rows: Distribution1D::new(&row_w),
            cols,
        }
    }

    fn lookup(&self, uv: Vec2) -> Vec3 {
        let (w, h) = (self.width as i64, self.height as i64);
        let px = uv.x * w as f32 - 0.5;
        let py = uv.y * h as f32 - 0.5;
        let (x0, y0) = (px.floor(), py.floor());
        let (fx, fy) = (px - x0, py - y0);
        let t = |x: i64, y: i64| self.texels[(y.clamp(0, h - 1) * w + x.rem_euclid(w)) as usize];
        let (x0, y0) = (x0 as i64, y0 as i64);
        let a = t(x0, y0) * (1.0 - fx) + t(x0 + 1, y0) * fx;
        let b = t(x0, y0 + 1) * (1.0 - fx) + t(x0 + 1, y0 + 1) * fx;
        (a * (1.0 - fy) + b * fy) * self.scale
    }

    fn to_uv(&self, d_world: Vec3) -> Vec2 {
        let d = self.to_local.transform_vector3(d_world).normalize();
        let mut u = d.x.atan2(-d.z) / (2.0 * PI);
        if u < 0.0 {
            u += 1.0;
        }
        Vec2::new(u, d.y.clamp(-1.0, 1.0).acos() / PI)
    }

    /// Radiance arriving from world direction `d`.
    pub fn eval(&self, d: Vec3) -> Vec3 {
        self.lookup(self.to_uv(d))
    }

    /// Samples a direction towards the map by `u`; the sample's `pdf` is per solid angle and does
    /// not include the light-selection probability. `None` at the poles or where the density is
    /// zero.
    pub fn sample(&self, u: Vec2) -> Option<LightSample> {
        let (y, uy) = self.rows.sample(u.y);
        let (x, ux) = self.cols[y].sample(u.x);
        let uv = Vec2::new(
            (x as f32 + ux) / self.width as f32,
            (y as f32 + uy) / self.height as f32,
        );
        let theta = uv.y * PI;
        let phi = uv.x * 2.0 * PI;
        let sin_theta = theta.sin();
        if sin_theta <= 0.0 {
            return None;
        }
        let local = Vec3::new(phi.sin() * sin_theta, theta.cos(), -phi.cos() * sin_theta);
        let wi = self.to_world.transform_vector3(local).normalize();
        let p_texel = self.rows.pmf(y) * self.cols[y].pmf(x);
        let pdf = p_texel * (self.width * self.height) as f32 / (2.0 * PI * PI * sin_theta);
        if !(pdf > 0.0 && pdf.is_finite()) {
            return None;
        }
        Some(LightSample {
            wi,
            point: Vec3::ZERO,
            infinite: true,
            value: self.lookup(uv),
            pdf,
            delta: false,
        })
    }

    /// Solid-angle density with which [`EnvMap::sample`] produces world direction `d` (without the
    /// light-selection probability).
    pub fn pdf(&self, d: Vec3) -> f32 {
        let uv = self.to_uv(d);
        let x = ((uv.x * self.width as f32) as usize).min(self.width as usize - 1);
        let y = ((uv.y * self.height as f32) as usize).min(self.height as usize - 1);
        let sin_theta = (uv.y * PI).sin();
        if sin_theta <= 0.0 {
            return 0.0;
        }
        self.rows.pmf(y) * self.cols[y].pmf(x) * (self.width * self.height) as f32
            / (2.0 * PI * PI * sin_theta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn envmap_sampling_estimates_the_integral_of_its_radiance() {
        // A map with a bright band: estimate the integral of luminance over the
        // sphere by importance sampling and by uniform sampling; they agree.
        let (w, h) = (32u32, 16u32);
        let texels: Vec<Vec3> = (0..w * h)
            .map(|i| {
                if (i / w) == 5 && (i % w) < 8 {
                    Vec3::splat(50.0)
                } else {
                    Vec3::splat(0.5)
                }
            })
            .collect();
        let env = EnvMap::new(w, h, Arc::new(texels), 1.0, Mat4::IDENTITY);
        let mut rng = Rng::new(1, 2);
        let n = 400_000;
        let (mut is, mut uni) = (0.0f64, 0.0f64);
        for _ in 0..n {
            let s = env.sample(rng.next_2d()).unwrap();
            // Near the poles the direction -> theta round trip loses digits
            // (the pdf has a 1/sin(theta) factor), so the tolerance grows there.
            let sin_theta = (1.0 - s.wi.y * s.wi.y).max(0.0).sqrt();
            let tol = 1e-4 / sin_theta.max(1e-3);
            assert!(
                (env.pdf(s.wi) - s.pdf).abs() <= tol.max(1e-3) * s.pdf,
                "{} vs {} at sin(theta) {sin_theta}",
                env.pdf(s.wi),
                s.pdf
            );
            is += (s.value.x / s.pdf) as f64;
            let d = crate::sampling::uniform_sphere(rng.next_2d());
            uni += (env.eval(d).x * 4.0 * PI) as f64;
        }
        let (is, uni) = (is / n as f64, uni / n as f64);
        assert!(
            (is - uni).abs() < 0.03 * uni,
            "importance {is} vs uniform {uni}"
        );
    }
}
