//! Latitude-longitude environment map with Mitsuba 3's orientation and texel mapping
//! (u = atan2(x, -z) / 2pi, v = acos(y) / pi in the emitter's frame; texel columns at
//! u = (x + 0.5) / width, wrapping around; rows at v = y / (height - 1), the first and last
//! on the poles; bilinear between them), importance sampled over the cells between texels
//! by their largest corner's luminance times their solid angle.

use glam::{Mat4, Vec2, Vec3};
use std::f32::consts::PI;
use std::sync::Arc;

use super::LightSample;
use crate::sampling::Distribution1D;

/// An environment light from a latitude-longitude RGB image, importance sampled by
/// luminance over solid angle.
pub struct EnvMap {
    width: u32,
    height: u32,
    texels: Arc<Vec<Vec3>>,
    scale: f32,
    to_world: Mat4,
    to_local: Mat4,
    /// Marginal over cell rows (between texel rows `j` and `j + 1`).
    rows: Distribution1D,
    /// Conditional over cell columns (between texel columns `i` and `i + 1`), per row.
    cols: Vec<Distribution1D>,
}

fn luminance(c: Vec3) -> f32 {
    0.212671 * c.x + 0.715160 * c.y + 0.072169 * c.z
}

impl EnvMap {
    /// Builds the map from `width x height` linear RGB texels (row-major, row 0 at the top,
    /// i.e. at +y of the emitter's frame; at least 2x3, as Mitsuba requires), scaled by
    /// `scale`, oriented by `to_world`, and precomputes its sampling distributions.
    pub fn new(
        width: u32,
        height: u32,
        texels: Arc<Vec<Vec3>>,
        scale: f32,
        to_world: Mat4,
    ) -> Self {
        assert!(
            width >= 2 && height >= 3,
            "an envmap has at least 2x3 texels"
        );
        let (w, h) = (width as usize, height as usize);
        let lum: Vec<f32> = texels.iter().map(|&c| luminance(c).max(0.0)).collect();
        let mean = lum.iter().map(|&l| l as f64).sum::<f64>() as f32 / lum.len().max(1) as f32;
        let mut cols = Vec::with_capacity(h - 1);
        let mut row_w = Vec::with_capacity(h - 1);
        for j in 0..h - 1 {
            // Every point of a cell is a bilinear mix of its four corners: the largest
            // bounds it, so wherever the map is non-zero the density is too.
            let solid_angle = Self::cell_cos(j, h) - Self::cell_cos(j + 1, h);
            let weights: Vec<f32> = (0..w)
                .map(|i| {
                    let corner = |x: usize, y: usize| lum[y * w + x % w];
                    let m = corner(i, j)
                        .max(corner(i + 1, j))
                        .max(corner(i, j + 1))
                        .max(corner(i + 1, j + 1));
                    (m + 1e-4 * mean) * solid_angle.max(0.0)
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

    /// cos(theta) of texel row `j` of `h` (row 0 at the north pole, row h-1 at the south).
    fn cell_cos(j: usize, h: usize) -> f32 {
        (PI * j as f32 / (h - 1) as f32).cos()
    }

    /// The texel cell `uv` is in, and its place in it: column from the texel centres
    /// (wrapping), row from the poles.
    fn cell(&self, uv: Vec2) -> (usize, usize, f32, f32) {
        let (w, h) = (self.width as f32, self.height as f32);
        let mut x = (uv.x - 0.5 / w) * w;
        x -= (x / w).floor() * w;
        let y = uv.y.clamp(0.0, 1.0) * (h - 1.0);
        let i = (x as usize).min(self.width as usize - 1);
        let j = (y as usize).min(self.height as usize - 2);
        (i, j, x - i as f32, y - j as f32)
    }

    fn lookup(&self, uv: Vec2) -> Vec3 {
        let (i, j, fx, fy) = self.cell(uv);
        let w = self.width as usize;
        let t = |x: usize, y: usize| self.texels[y * w + x % w];
        let a = t(i, j) * (1.0 - fx) + t(i + 1, j) * fx;
        let b = t(i, j + 1) * (1.0 - fx) + t(i + 1, j + 1) * fx;
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

    /// Solid angle of a cell of row `j`.
    fn cell_solid_angle(&self, j: usize) -> f32 {
        let h = self.height as usize;
        2.0 * PI / self.width as f32 * (Self::cell_cos(j, h) - Self::cell_cos(j + 1, h))
    }

    /// Samples a direction towards the map by `u`: a cell by its weight, then a direction
    /// uniform in solid angle within it. The sample's `pdf` is per solid angle and does not
    /// include the light-selection probability. `None` where the density is zero.
    pub fn sample(&self, u: Vec2) -> Option<LightSample> {
        let (j, uy) = self.rows.sample(u.y);
        let (i, ux) = self.cols[j].sample(u.x);
        let h = self.height as usize;
        let (c0, c1) = (Self::cell_cos(j, h), Self::cell_cos(j + 1, h));
        let cos_theta = (c0 + uy * (c1 - c0)).clamp(-1.0, 1.0);
        let sin_theta = (1.0 - cos_theta * cos_theta).max(0.0).sqrt();
        let mut uv_x = (i as f32 + ux + 0.5) / self.width as f32;
        uv_x -= uv_x.floor();
        let phi = uv_x * 2.0 * PI;
        let local = Vec3::new(phi.sin() * sin_theta, cos_theta, -phi.cos() * sin_theta);
        let wi = self.to_world.transform_vector3(local).normalize();
        let p_cell = self.rows.pmf(j) * self.cols[j].pmf(i);
        let pdf = p_cell / self.cell_solid_angle(j);
        if !(pdf > 0.0 && pdf.is_finite()) {
            return None;
        }
        let uv = Vec2::new(uv_x, cos_theta.acos() / PI);
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
        let (i, j, _, _) = self.cell(self.to_uv(d));
        let p_cell = self.rows.pmf(j) * self.cols[j].pmf(i);
        let pdf = p_cell / self.cell_solid_angle(j);
        if pdf.is_finite() {
            pdf
        } else {
            0.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn rows_sit_on_the_poles_and_columns_on_texel_centres_as_in_mitsuba() {
        // Rows of 10, 5 and 1 (3 rows: the poles and the equator), 4 columns.
        let rows = [10.0f32, 5.0, 1.0];
        let texels: Vec<Vec3> = (0..12).map(|k| Vec3::splat(rows[k / 4])).collect();
        let env = EnvMap::new(4, 3, Arc::new(texels), 1.0, Mat4::IDENTITY);
        let at = |theta: f32| env.eval(Vec3::new(theta.sin(), theta.cos(), 0.0)).x;
        assert!((at(0.0) - 10.0).abs() < 1e-5, "the north pole is row 0");
        assert!(
            (at(PI / 4.0) - 7.5).abs() < 1e-4,
            "45 degrees is halfway to row 1"
        );
        assert!((at(PI / 2.0) - 5.0).abs() < 1e-4, "the equator is row 1");
        assert!(
            (at(PI) - 1.0).abs() < 1e-5,
            "the south pole is the last row"
        );
        // Column x is at u = (x + 0.5) / 4; u = atan2(x, -z) / 2pi.
        let cols = [1.0f32, 2.0, 3.0, 4.0];
        let texels: Vec<Vec3> = (0..12).map(|k| Vec3::splat(cols[k % 4])).collect();
        let env = EnvMap::new(4, 3, Arc::new(texels), 1.0, Mat4::IDENTITY);
        let phi = |u: f32| 2.0 * PI * u;
        let dir = |u: f32| Vec3::new(phi(u).sin(), 0.0, -phi(u).cos());
        assert!(
            (env.eval(dir(0.625)).x - 3.0).abs() < 1e-4,
            "the centre of column 2"
        );
        assert!(
            (env.eval(dir(0.75)).x - 3.5).abs() < 1e-4,
            "between columns 2 and 3"
        );
        assert!(
            (env.eval(dir(0.0)).x - 2.5).abs() < 1e-4,
            "between the last and first"
        );
    }

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
        let mut differ = 0;
        for _ in 0..n {
            let s = env.sample(rng.next_2d()).unwrap();
            // The density is constant over a cell: the direction's round trip lands in
            // the sampled cell except within rounding of its border.
            differ += usize::from((env.pdf(s.wi) - s.pdf).abs() > 1e-4 * s.pdf);
            is += (s.value.x / s.pdf) as f64;
            let d = crate::sampling::uniform_sphere(rng.next_2d());
            uni += (env.eval(d).x * 4.0 * PI) as f64;
        }
        assert!(
            differ * 10_000 < n,
            "pdf(sample) differs from the sample's in {differ} of {n}"
        );
        let (is, uni) = (is / n as f64, uni / n as f64);
        assert!(
            (is - uni).abs() < 0.03 * uni,
            "importance {is} vs uniform {uni}"
        );
    }
}
