//! Cylindrical (equal-area) mapping between world-space unit directions and the unit square.
//!
//! `u = (clamp(d.z, -1, 1) + 1) / 2`, `v = atan2(d.y, d.x) / (2 pi)` wrapped into `[0, 1)`.
//! The mapping is area preserving up to the constant Jacobian `d(omega) = 4 pi du dv`, so a
//! density over the square converts to solid angle as `p_omega = p_uv / (4 pi)`.

use glam::{Vec2, Vec3};

/// Jacobian of the cylindrical mapping: solid angle per unit area of `(u, v)`, i.e. `4 pi`.
pub const JACOBIAN: f32 = 4.0 * std::f32::consts::PI;

/// Maps a world-space direction to `(u, v)` in `[0, 1]^2` (`v` in `[0, 1)`).
///
/// The direction need not be normalised for `v`, but `u` reads `d.z` directly, so pass unit
/// vectors. A direction with a non-finite component maps to `(0, 0)`. `phi` comes from
/// [`atan2_f32`] (error about 1e-7 rad, the size of f32 rounding), which is several times
/// cheaper than libm's f64 `atan2` on the renderer's hot path.
#[inline]
pub fn dir_to_uv(d: Vec3) -> Vec2 {
    if !d.is_finite() {
        return Vec2::ZERO;
    }
    let u = ((d.z.clamp(-1.0, 1.0) + 1.0) * 0.5).clamp(0.0, 1.0);
    let mut phi = atan2_f32(d.y, d.x);
    if phi < 0.0 {
        phi += std::f32::consts::TAU;
    }
    let v = phi * (1.0 / std::f32::consts::TAU);
    Vec2::new(u, if (0.0..1.0).contains(&v) { v } else { 0.0 })
}

/// `atan2(y, x)` in f32 for finite arguments, in `[-pi, pi]`: a degree-15 odd minimax-fitted
/// polynomial for `atan` on `[0, 1]` (max error 1.2e-7 rad evaluated in f32) with the usual
/// octant reduction (overall within 4e-7 rad, under 2 f32 ulps at pi). `atan2_f32(0, 0) = 0`.
#[inline]
pub fn atan2_f32(y: f32, x: f32) -> f32 {
    let (ax, ay) = (x.abs(), y.abs());
    let (mn, mx) = if ax < ay { (ax, ay) } else { (ay, ax) };
    let a = if mx > 0.0 { mn / mx } else { 0.0 };
    let s = a * a;
    let mut r = -0.004_055_998_6_f32;
    r = r * s + 0.021_868_008;
    r = r * s - 0.055_919_44;
    r = r * s + 0.096_427_07;
    r = r * s - 0.139_088_26;
    r = r * s + 0.199_466_05;
    r = r * s - 0.333_298_64;
    r = r * s + 0.999_999_34;
    r *= a;
    if ay > ax {
        r = std::f32::consts::FRAC_PI_2 - r;
    }
    if x < 0.0 {
        r = std::f32::consts::PI - r;
    }
    if y < 0.0 {
        -r
    } else {
        r
    }
}

/// Maps `(u, v)` (expected in `[0, 1]^2`, clamped) to a unit world-space direction.
///
/// In f32: `sin(theta) = 2 sqrt(u (1 - u))` (no cancellation near the poles) and
/// [`sincos_turns`] for `phi = 2 pi v`, which is several times cheaper than libm's f64 sincos
/// on the renderer's hot path and within a few f32 ulps of it.
#[inline]
pub fn uv_to_dir(uv: Vec2) -> Vec3 {
    let u = uv.x.clamp(0.0, 1.0);
    let cos_t = 2.0 * u - 1.0;
    let sin_t = 2.0 * (u * (1.0 - u)).max(0.0).sqrt();
    let (sin_p, cos_p) = sincos_turns(uv.y);
    Vec3::new(sin_t * cos_p, sin_t * sin_p, cos_t)
}

/// `(sin, cos)` of the angle `2 pi v` (`v` in turns, any finite value; `[0, 1)` is the
/// intended range), in f32: quarter-turn reduction (exact: `4 v - round(4 v)`), then Cephes'
/// single-precision minimax polynomials on `[-pi/4, pi/4]`. Error under 2e-7 absolute.
#[inline]
pub fn sincos_turns(v: f32) -> (f32, f32) {
    let t = v * 4.0;
    let q = t.round();
    // |r| <= 0.5; exact (t and q are within one of each other, Sterbenz).
    let r = t - q;
    let a = r * std::f32::consts::FRAC_PI_2;
    let a2 = a * a;
    let s = a + a * a2 * (-1.666_665_5e-1 + a2 * (8.332_161e-3 + a2 * -1.951_529_6e-4));
    let c =
        1.0 - 0.5 * a2 + a2 * a2 * (4.166_664_6e-2 + a2 * (-1.388_731_6e-3 + a2 * 2.443_315_7e-5));
    // The quadrant: q mod 4 (q is an integer-valued float; `as i64` is exact for finite v).
    match (q as i64) & 3 {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// Converts a density over `(u, v)` to a density over solid angle (divides by `4 pi`).
#[inline]
pub fn pdf_uv_to_solid_angle(p_uv: f32) -> f32 {
    p_uv / JACOBIAN
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::seam_and_poles;

    #[test]
    fn atan2_f32_matches_libm_within_about_one_f32_ulp_of_pi() {
        // Deterministic sweep (no significance level): angles all around the circle, radii
        // over many magnitudes, the axes, and signed zeros.
        let mut worst = 0.0f64;
        for i in 0..200_000 {
            let t =
                -std::f64::consts::PI + 2.0 * std::f64::consts::PI * (i as f64 + 0.5) / 200_000.0;
            for r in [1e-20f64, 1e-3, 1.0, 7.5, 1e20] {
                let (y, x) = ((r * t.sin()) as f32, (r * t.cos()) as f32);
                let e = (atan2_f32(y, x) as f64 - (y as f64).atan2(x as f64)).abs();
                worst = worst.max(e);
            }
        }
        // 4e-7 = 1.7 ulp of f32 at pi (the octant reduction subtracts from pi in f32).
        assert!(worst < 4e-7, "max error {worst}");
        for (y, x) in [
            (0.0f32, 1.0f32),
            (1.0, 0.0),
            (0.0, -1.0),
            (-1.0, 0.0),
            (1.0, 1.0),
            (0.0, 0.0),
        ] {
            let e = (atan2_f32(y, x) as f64 - (y as f64).atan2(x as f64)).abs();
            assert!(e < 4e-7, "({y}, {x}): {e}");
        }
        assert!((atan2_f32(-0.0, -1.0).abs() - std::f32::consts::PI).abs() < 1e-6);
    }

    #[test]
    fn sincos_turns_matches_libm_all_around_the_circle() {
        // Deterministic sweep (no significance level), including the quadrant boundaries.
        let mut worst = 0.0f64;
        let n = 400_000;
        for i in 0..=n {
            let v = i as f32 / n as f32;
            let (s, c) = sincos_turns(v);
            let phi = 2.0 * std::f64::consts::PI * v as f64;
            worst = worst
                .max((s as f64 - phi.sin()).abs())
                .max((c as f64 - phi.cos()).abs());
        }
        assert!(worst < 2e-7, "max error {worst}");
        assert_eq!(sincos_turns(0.0), (0.0, 1.0));
        assert_eq!(sincos_turns(0.25).0, 1.0);
        assert_eq!(sincos_turns(0.5).1, -1.0);
        assert_eq!(sincos_turns(0.75).0, -1.0);
    }

    #[test]
    fn round_trip_direction_uv_direction() {
        let mut s = 12345u64;
        for _ in 0..10000 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let a = ((s >> 40) as f32) / (1u64 << 24) as f32;
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let b = ((s >> 40) as f32) / (1u64 << 24) as f32;
            let uv = Vec2::new(a, b);
            let d = uv_to_dir(uv);
            assert!((d.length() - 1.0).abs() < 1e-5);
            let uv2 = dir_to_uv(d);
            let dv = (uv2.y - uv.y).abs();
            let dv = dv.min(1.0 - dv);
            assert!((uv2.x - uv.x).abs() < 1e-5, "{uv} {uv2}");
            // phi is ill-conditioned only at the poles
            if a > 1e-3 && a < 1.0 - 1e-3 {
                assert!(dv < 1e-4, "{uv} {uv2}");
            }
            let d2 = uv_to_dir(uv2);
            assert!((d2 - d).length() < 1e-4);
        }
    }

    #[test]
    fn axes_map_to_documented_coordinates_and_nan_to_origin() {
        assert_eq!(dir_to_uv(Vec3::Z).x, 1.0);
        assert_eq!(dir_to_uv(-Vec3::Z).x, 0.0);
        let x = dir_to_uv(Vec3::X);
        assert!((x.x - 0.5).abs() < 1e-7 && x.y == 0.0);
        let y = dir_to_uv(Vec3::Y);
        assert!((y.y - 0.25).abs() < 1e-7);
        let my = dir_to_uv(-Vec3::Y);
        assert!((my.y - 0.75).abs() < 1e-7);
        assert_eq!(dir_to_uv(Vec3::new(f32::NAN, 0.0, 1.0)), Vec2::ZERO);
        assert_eq!(dir_to_uv(Vec3::new(f32::INFINITY, 0.0, 0.0)), Vec2::ZERO);
        assert!((JACOBIAN - 12.566371).abs() < 1e-5);
    }

    #[test]
    fn mapping_is_finite_and_inverse_at_the_poles_and_on_the_seam() {
        for d in seam_and_poles() {
            let uv = dir_to_uv(d);
            assert!(
                (0.0..=1.0).contains(&uv.x) && (0.0..1.0).contains(&uv.y),
                "{d} maps to {uv}"
            );
            let back = uv_to_dir(uv);
            assert!(
                back.is_finite() && (back - d.normalize()).length() < 1e-3,
                "{d} -> {uv} -> {back}"
            );
        }
        // The corners of the square: the poles for any v, the seam's two edges.
        for (u, v) in [
            (0.0, 0.0),
            (1.0, 0.0),
            (0.0, 1.0),
            (1.0, 1.0),
            (0.5, 0.0),
            (0.5, 1.0),
        ] {
            let d = uv_to_dir(Vec2::new(u, v));
            assert!((d.length() - 1.0).abs() < 1e-6, "({u}, {v}) -> {d}");
        }
        assert_eq!(
            uv_to_dir(Vec2::new(1.0, 0.37)),
            Vec3::Z,
            "the pole has no phi"
        );
    }
}
