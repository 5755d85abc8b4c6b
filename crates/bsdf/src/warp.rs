//! Sample warping functions (same mappings as Mitsuba's `warp.h`).

use glam::{Vec2, Vec3};
use std::f32::consts::{FRAC_1_PI, PI};

/// Shirley–Chiu concentric square-to-disk map (Dave Cline's branch-reduced
/// variant, as Mitsuba's `square_to_uniform_disk_concentric`).
#[inline]
pub fn square_to_uniform_disk_concentric(u: Vec2) -> Vec2 {
    let x = 2.0 * u.x - 1.0;
    let y = 2.0 * u.y - 1.0;
    if x == 0.0 && y == 0.0 {
        return Vec2::ZERO;
    }
    let q13 = x.abs() < y.abs();
    let (r, rp) = if q13 { (y, x) } else { (x, y) };
    let mut phi = 0.25 * PI * rp / r;
    if q13 {
        phi = 0.5 * PI - phi;
    }
    let (s, c) = phi.sin_cos();
    Vec2::new(r * c, r * s)
}

/// Cosine-weighted hemisphere sampling via the concentric disk map.
#[inline]
pub fn square_to_cosine_hemisphere(u: Vec2) -> Vec3 {
    let p = square_to_uniform_disk_concentric(u);
    let z = (1.0 - p.length_squared()).max(0.0).sqrt();
    Vec3::new(p.x, p.y, z)
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
        assert!((v.length() - 1.0).abs() < 1e-5 && v.z >= 0.0);
    }
}
