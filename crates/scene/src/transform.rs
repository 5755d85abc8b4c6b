//! Affine transform helpers with Mitsuba 3's conventions.
//!
//! XML transform operations compose in document order, each new operation
//! applied after the previous ones: `M = op * M`.

use glam::{DMat3, DMat4, DVec3, DVec4};

/// Rotation by `angle_deg` degrees about `axis`, right-handed, as Mitsuba 3's
/// `Transform::rotate`: Rodrigues' formula `c I + s [a]x + (1 - c) a a^T` with the axis as
/// given, not normalised (an axis of length 2 also scales, as in Mitsuba).
pub(crate) fn rotate(axis: DVec3, angle_deg: f64) -> DMat4 {
    let (s, c) = angle_deg.to_radians().sin_cos();
    let a = axis;
    let cross = DMat3::from_cols(
        DVec3::new(0.0, a.z, -a.y),
        DVec3::new(-a.z, 0.0, a.x),
        DVec3::new(a.y, -a.x, 0.0),
    );
    let outer = DMat3::from_cols(a * a.x, a * a.y, a * a.z);
    DMat4::from_mat3(DMat3::IDENTITY * c + cross * s + outer * (1.0 - c))
}

/// Mitsuba's orthonormal basis around unit `n` (Duff et al. 2017, `coordinate_system`): the
/// two tangents, as Mitsuba's `Frame3f(n)` has them.
pub(crate) fn coordinate_system(n: DVec3) -> (DVec3, DVec3) {
    let sign = if n.z >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    let t = DVec3::new(b, sign + n.y * n.y * a, -n.y);
    (coordinate_system_first(n), t)
}

/// Mitsuba's orthonormal basis construction (Duff et al. 2017); returns the
/// first tangent, which Mitsuba uses as `up` when a lookat omits it.
fn coordinate_system_first(n: DVec3) -> DVec3 {
    let sign = if n.z >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    DVec3::new(n.x * n.x * a * sign + 1.0, b * sign, -n.x * sign)
}

/// Mitsuba's `look_at`: camera-to-world with columns `left`, `up'`, `dir`,
/// `origin` (camera looks down +z, +y up, +x left). A zero `up` is replaced
/// as Mitsuba does. `None` if the result is degenerate.
pub(crate) fn look_at(origin: DVec3, target: DVec3, up: DVec3) -> Option<DMat4> {
    let dir = (target - origin).normalize();
    let up = if up == DVec3::ZERO {
        coordinate_system_first(dir)
    } else {
        up
    };
    let left = up.cross(dir).normalize();
    let new_up = dir.cross(left);
    let m = DMat4::from_cols(
        left.extend(0.0),
        new_up.extend(0.0),
        dir.extend(0.0),
        DVec4::new(origin.x, origin.y, origin.z, 1.0),
    );
    m.is_finite().then_some(m)
}

/// Upper-left 3x3 part.
pub(crate) fn linear_part(m: DMat4) -> DMat3 {
    DMat3::from_mat4(m)
}

/// If `m` is a similarity (rotation/reflection times uniform scale plus
/// translation), return the scale factor.
pub(crate) fn similarity_scale(m: DMat4) -> Option<f64> {
    let l = linear_part(m);
    let (a, b, c) = (l.x_axis, l.y_axis, l.z_axis);
    let (la, lb, lc) = (a.length(), b.length(), c.length());
    let s = (la + lb + lc) / 3.0;
    if !(s > 0.0) || !s.is_finite() {
        return None;
    }
    let tol = 1e-4 * s;
    let tol2 = 1e-4 * s * s;
    let last_row_ok = (m.row(3) - DVec4::new(0.0, 0.0, 0.0, 1.0))
        .abs()
        .max_element()
        < 1e-9;
    if (la - s).abs() < tol
        && (lb - s).abs() < tol
        && (lc - s).abs() < tol
        && a.dot(b).abs() < tol2
        && a.dot(c).abs() < tol2
        && b.dot(c).abs() < tol2
        && last_row_ok
    {
        Some(s)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn look_at_maps_plus_z_to_view_direction_and_origin_to_eye() {
        let m = look_at(
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(1.0, 2.0, 10.0),
            DVec3::Y,
        )
        .unwrap();
        assert!((m.transform_point3(DVec3::ZERO) - DVec3::new(1.0, 2.0, 3.0)).length() < 1e-12);
        assert!((m.transform_vector3(DVec3::Z) - DVec3::Z).length() < 1e-12);
        assert!((m.transform_vector3(DVec3::Y) - DVec3::Y).length() < 1e-12);
        // Camera +x is "left": looking down +z with +y up, left is +x in world.
        assert!((m.transform_vector3(DVec3::X) - DVec3::X).length() < 1e-12);
    }

    #[test]
    fn look_at_without_up_still_orthonormal() {
        let m = look_at(DVec3::ZERO, DVec3::new(0.0, 0.0, -1.0), DVec3::ZERO).unwrap();
        let l = linear_part(m);
        assert!((l.determinant().abs() - 1.0).abs() < 1e-9);
        assert!((m.transform_vector3(DVec3::Z) - DVec3::new(0.0, 0.0, -1.0)).length() < 1e-12);
    }

    #[test]
    fn rotate_uses_the_axis_as_given_like_mitsuba() {
        // Mitsuba 3.9.1: ScalarTransform4f().rotate([1, 1, 0], 30).matrix
        let m = rotate(DVec3::new(1.0, 1.0, 0.0), 30.0);
        let expected = [
            [1.0, 0.133975, 0.5],
            [0.133975, 1.0, -0.5],
            [-0.5, 0.5, 0.866025],
        ];
        for (r, row) in expected.iter().enumerate() {
            for (c, &x) in row.iter().enumerate() {
                assert!(
                    (m.col(c)[r] - x).abs() < 1e-6,
                    "[{r}][{c}]: {} vs {x}",
                    m.col(c)[r]
                );
            }
        }
    }

    #[test]
    fn rotate_is_right_handed_in_degrees() {
        let p = rotate(DVec3::new(0.0, 0.0, 1.0), 90.0).transform_point3(DVec3::X);
        assert!((p - DVec3::Y).length() < 1e-12);
    }

    #[test]
    fn similarity_detects_non_uniform_scale() {
        assert_eq!(
            similarity_scale(DMat4::from_scale(DVec3::splat(2.0))),
            Some(2.0)
        );
        assert!(similarity_scale(DMat4::from_scale(DVec3::new(1.0, 2.0, 1.0))).is_none());
        let axis = DVec3::new(1.0, 1.0, 0.0).normalize();
        let r = rotate(axis, 33.0) * DMat4::from_scale(DVec3::splat(3.0));
        assert!((similarity_scale(r).unwrap() - 3.0).abs() < 1e-9);
    }
}
