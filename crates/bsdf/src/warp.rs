//! Sample warping functions (same mappings as Mitsuba's `warp.h`).

use glam::{Vec2, Vec3};
use std::f32::consts::{FRAC_1_PI, PI};

/// Shirley–Chiu concentric square-to-disk map (Dave Cline's branch-reduced
/// variant, as Mitsuba's `square_to_uniform_disk_concentric`).
#[inline]
pub fn square_to_uniform_disk_concentric(u: Vec2) -> Vec2 {
    let [x, y] = square_to_uniform_disk_concentric_lane(u.x, u.y);
    Vec2::new(x, y)
}

/// [`square_to_uniform_disk_concentric`] on plain numbers and without branches (selects
/// only), so that a loop over many samples vectorises.
#[inline(always)]
pub fn square_to_uniform_disk_concentric_lane(ux: f32, uy: f32) -> [f32; 2] {
    let x = 2.0 * ux - 1.0;
    let y = 2.0 * uy - 1.0;
    let q13 = x.abs() < y.abs();
    let (r, rp) = if q13 { (y, x) } else { (x, y) };
    // Mitsuba's angle is phi = pi/4 rp/r, or pi/2 - phi in quadrants 1 and
    // 3; sin and cos of pi/2 - phi are cos and sin of phi.
    let (s, c) = sin_cos_quarter(0.25 * PI * rp / r);
    let (px, py) = if q13 { (r * s, r * c) } else { (r * c, r * s) };
    // The centre maps to itself (0/0 above).
    let centre = (x == 0.0) & (y == 0.0);
    [if centre { 0.0 } else { px }, if centre { 0.0 } else { py }]
}

/// `(sin x, cos x)` for |x| <= pi/4 by minimax polynomials (Cephes' `sinf`
/// and `cosf` kernels, error ~1e-7): cheaper than libm's general `sincosf`.
#[inline]
fn sin_cos_quarter(x: f32) -> (f32, f32) {
    let z = x * x;
    let s = x + x * z * (-1.666_665_5e-1 + z * (8.332_161e-3 + z * -1.951_529_6e-4));
    let c = 1.0 - 0.5 * z + z * z * (4.166_664_6e-2 + z * (-1.388_731_6e-3 + z * 2.443_315_7e-5));
    (s, c)
}

/// Cosine-weighted hemisphere sampling via the concentric disk map.
#[inline]
pub fn square_to_cosine_hemisphere(u: Vec2) -> Vec3 {
    Vec3::from_array(square_to_cosine_hemisphere_lane(u.x, u.y))
}

/// [`square_to_cosine_hemisphere`] on plain numbers, branch-free.
#[inline(always)]
pub fn square_to_cosine_hemisphere_lane(ux: f32, uy: f32) -> [f32; 3] {
    let [x, y] = square_to_uniform_disk_concentric_lane(ux, uy);
    let z = (1.0 - (x * x + y * y)).max(0.0).sqrt();
    [x, y, z]
}

/// Density of [`square_to_cosine_hemisphere`] (cos theta / pi; not clamped,
/// as in Mitsuba — callers check the hemisphere).
#[inline]
pub fn square_to_cosine_hemisphere_pdf(v: Vec3) -> f32 {
    FRAC_1_PI * v.z
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn concentric_disk_maps_square_corners_and_center_onto_disk() {
        assert_eq!(
            square_to_uniform_disk_concentric(Vec2::splat(0.5)),
            Vec2::ZERO
        );
        for u in [
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 1.0),
            Vec2::new(1.0, 0.5),
        ] {
            assert!((square_to_uniform_disk_concentric(u).length() - 1.0).abs() < 1e-5);
        }
        let v = square_to_cosine_hemisphere(Vec2::new(0.3, 0.8));
        for i in 0..=1000 {
            let x = (i as f32 / 500.0 - 1.0) * std::f32::consts::FRAC_PI_4;
            let (s, c) = sin_cos_quarter(x);
            assert!(
                (s - x.sin()).abs() < 2e-7 && (c - x.cos()).abs() < 2e-7,
                "{x}"
            );
        }
        assert!((v.length() - 1.0).abs() < 1e-5 && v.z >= 0.0);
    }

    /// Shirley-Chiu: the square's concentric rings map to circles (radius max(|x|, |y|))
    /// and each point keeps its octant's angle, phi = pi/4 y/x where |x| >= |y|.
    #[test]
    fn concentric_map_keeps_rings_and_octant_angles() {
        for i in 0..=40 {
            for j in 0..=40 {
                let u = Vec2::new(i as f32 / 40.0, j as f32 / 40.0);
                let (x, y) = (2.0 * u.x - 1.0, 2.0 * u.y - 1.0);
                let p = square_to_uniform_disk_concentric(u);
                let r = x.abs().max(y.abs());
                assert!((p.length() - r).abs() < 1e-6, "{u}: {p}");
                if r == 0.0 {
                    continue;
                }
                let phi = if x.abs() >= y.abs() {
                    std::f32::consts::FRAC_PI_4 * y / x + if x < 0.0 { PI } else { 0.0 }
                } else {
                    std::f32::consts::FRAC_PI_2 - std::f32::consts::FRAC_PI_4 * x / y
                        + if y < 0.0 { PI } else { 0.0 }
                };
                let expected = Vec2::new(phi.cos(), phi.sin()) * r;
                assert!((p - expected).length() < 1e-5, "{u}: {p} vs {expected}");
            }
        }
    }
}
