//! Fresnel equations and reflection/refraction helpers (Mitsuba `fresnel.h`).

use glam::Vec3;

/// Unpolarised Fresnel reflectance of a dielectric interface.
///
/// `eta` is the relative IOR (interior / exterior). `cos_theta_i` may be
/// negative (incident from the interior). Returns
/// `(F, cos_theta_t, eta_it, eta_ti)` where `cos_theta_t` carries the sign
/// of the transmitted direction (opposite to `cos_theta_i`), `eta_it` is the
/// relative IOR of the crossing (eta_t / eta_i) and `eta_ti` its inverse.
/// Total internal reflection gives F = 1 and `cos_theta_t = 0`.
#[inline]
pub fn fresnel_dielectric(cos_theta_i: f32, eta: f32) -> (f32, f32, f32, f32) {
    let outside = cos_theta_i >= 0.0;
    let rcp_eta = 1.0 / eta;
    let (eta_it, eta_ti) = if outside {
        (eta, rcp_eta)
    } else {
        (rcp_eta, eta)
    };
    let cos_theta_t_sqr = 1.0 - (1.0 - cos_theta_i * cos_theta_i) * (eta_ti * eta_ti);
    let ci = cos_theta_i.abs();
    let ct = cos_theta_t_sqr.max(0.0).sqrt();
    let index_matched = eta == 1.0;
    let r = if index_matched {
        0.0
    } else if ci == 0.0 {
        1.0
    } else {
        let a_s = (ci - eta_it * ct) / (ci + eta_it * ct);
        let a_p = (ct - eta_it * ci) / (ct + eta_it * ci);
        0.5 * (a_s * a_s + a_p * a_p)
    };
    let cos_theta_t = if cos_theta_i >= 0.0 { -ct } else { ct };
    (r, cos_theta_t, eta_it, eta_ti)
}

/// Unpolarised Fresnel reflectance of a conductor with complex IOR
/// `eta + i k` (k >= 0). `cos_theta_i` must be non-negative.
#[inline]
pub fn fresnel_conductor(cos_theta_i: f32, eta: f32, k: f32) -> f32 {
    let c2 = cos_theta_i * cos_theta_i;
    let s2 = 1.0 - c2;
    let s4 = s2 * s2;
    let temp_1 = eta * eta - k * k - s2;
    let a_2_pb_2 = (temp_1 * temp_1 + 4.0 * k * k * eta * eta).max(0.0).sqrt();
    let a = (0.5 * (a_2_pb_2 + temp_1)).max(0.0).sqrt();
    let term_1 = a_2_pb_2 + c2;
    let term_2 = 2.0 * cos_theta_i * a;
    let r_s = (term_1 - term_2) / (term_1 + term_2);
    let term_3 = a_2_pb_2 * c2 + s4;
    let term_4 = term_2 * s2;
    let r_p = r_s * (term_3 - term_4) / (term_3 + term_4);
    let r = 0.5 * (r_s + r_p);
    if r.is_finite() {
        r
    } else {
        1.0
    }
}

/// [`fresnel_conductor`] per RGB channel.
#[inline]
pub fn fresnel_conductor_rgb(cos_theta_i: f32, eta: Vec3, k: Vec3) -> Vec3 {
    Vec3::new(
        fresnel_conductor(cos_theta_i, eta.x, k.x),
        fresnel_conductor(cos_theta_i, eta.y, k.y),
        fresnel_conductor(cos_theta_i, eta.z, k.z),
    )
}

/// Hemispherical average of the dielectric Fresnel reflectance (fits by Egan &
/// Hilgeman for eta < 1 and d'Eon & Irving otherwise, as Mitsuba).
#[inline]
pub fn fresnel_diffuse_reflectance(eta: f32) -> f32 {
    let inv_eta = 1.0 / eta;
    if eta < 1.0 {
        0.0636 * inv_eta + eta * (eta * -1.4399 + 0.7099) + 0.6681
    } else {
        // Horner in inv_eta of 0.919317 - 3.4793 x + 6.75335 x^2 - 7.80989 x^3 + 4.98554 x^4 - 1.36881 x^5
        let x = inv_eta;
        0.919317 + x * (-3.4793 + x * (6.75335 + x * (-7.80989 + x * (4.98554 + x * -1.36881))))
    }
}

/// Mirror reflection about the local normal (z).
#[inline]
pub fn reflect(wi: Vec3) -> Vec3 {
    Vec3::new(-wi.x, -wi.y, wi.z)
}

/// Mirror reflection of `wi` about the microfacet normal `m`.
#[inline]
pub fn reflect_about(wi: Vec3, m: Vec3) -> Vec3 {
    m * (2.0 * wi.dot(m)) - wi
}

/// Refraction through the macro-surface, given `cos_theta_t` and `eta_ti` from
/// [`fresnel_dielectric`].
#[inline]
pub fn refract(wi: Vec3, cos_theta_t: f32, eta_ti: f32) -> Vec3 {
    Vec3::new(-eta_ti * wi.x, -eta_ti * wi.y, cos_theta_t)
}

/// Refraction through a microfacet with normal `m`.
#[inline]
pub fn refract_about(wi: Vec3, m: Vec3, cos_theta_t: f32, eta_ti: f32) -> Vec3 {
    m * (wi.dot(m) * eta_ti + cos_theta_t) - wi * eta_ti
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dielectric_fresnel_normal_incidence_and_tir() {
        let (r, ct, eit, eti) = fresnel_dielectric(1.0, 1.5);
        assert!(
            (r - 0.04).abs() < 1e-6
                && (ct + 1.0).abs() < 1e-6
                && eit == 1.5
                && (eti - 1.0 / 1.5).abs() < 1e-7
        );
        // From inside at 60 degrees: sin = 0.866 * 1.5 > 1 -> total internal reflection.
        let (r, ct, ..) = fresnel_dielectric(-0.5, 1.5);
        assert_eq!((r, ct), (1.0, 0.0));
        assert_eq!(fresnel_dielectric(0.3, 1.0).0, 0.0);
    }

    #[test]
    fn conductor_fresnel_reduces_to_dielectric_for_zero_k() {
        for c in [1.0f32, 0.7, 0.3, 0.05] {
            let a = fresnel_conductor(c, 1.5, 0.0);
            let b = fresnel_dielectric(c, 1.5).0;
            assert!((a - b).abs() < 1e-5, "{c}: {a} vs {b}");
        }
        assert!((fresnel_conductor(0.0, 0.2, 3.0) - 1.0).abs() < 1e-6);
    }
}
