//! eval/pdf/sample consistency, energy conservation, reciprocity and
//! numerical hygiene.

use super::stats::{sph, vec2, TestRng};
use super::{rough_conductor, rough_dielectric};
use crate::*;
use glam::{Vec2, Vec3};

fn uniform_sphere(rng: &mut TestRng) -> Vec3 {
    let z = 1.0 - 2.0 * rng.f32();
    let phi = std::f32::consts::TAU * rng.f32();
    let s = (1.0 - z * z).max(0.0).sqrt();
    Vec3::new(s * phi.cos(), s * phi.sin(), z)
}

const AU: Vec3 = Vec3::new(0.143, 0.374, 1.442);
const AU_K: Vec3 = Vec3::new(3.983, 2.385, 1.603);

/// Smooth (non-delta-only) models, with the tables they borrow.
fn smooth_models(tables: &[RoughPlasticTable]) -> Vec<(String, Bsdf<'_>)> {
    let mut v: Vec<(String, Bsdf)> = vec![
        (
            "diffuse".into(),
            Bsdf::Diffuse(Diffuse::new(Vec3::new(0.7, 0.5, 0.2))),
        ),
        (
            "plastic".into(),
            Bsdf::Plastic(Plastic::new(
                1.5,
                Vec3::new(0.8, 0.3, 0.1),
                Vec3::ONE,
                false,
                specular_sampling_weight(0.4, 1.0),
            )),
        ),
        (
            "plastic nonlinear".into(),
            Bsdf::Plastic(Plastic::new(
                1.33,
                Vec3::new(0.9, 0.3, 0.1),
                Vec3::splat(0.8),
                true,
                0.5,
            )),
        ),
    ];
    for kind in [MicrofacetType::Ggx, MicrofacetType::Beckmann] {
        for (au, av) in [(0.05f32, 0.05f32), (0.3, 0.3), (0.1, 0.4)] {
            for vis in [true, false] {
                v.push((
                    format!("roughconductor {kind:?} {au}/{av} vis {vis}"),
                    rough_conductor(kind, (au, av), vis, AU, AU_K),
                ));
                for eta in [1.5f32, 1.0 / 1.33] {
                    v.push((
                        format!("roughdielectric {kind:?} {au}/{av} vis {vis} eta {eta}"),
                        rough_dielectric(
                            kind,
                            (au, av),
                            vis,
                            eta,
                            Vec3::splat(0.9),
                            Vec3::splat(0.8),
                        ),
                    ));
                }
            }
        }
    }
    for t in tables {
        for vis in [true, false] {
            v.push((
                format!("roughplastic {:?} {} vis {vis}", t.distribution, t.alpha),
                Bsdf::RoughPlastic(RoughPlastic::new(
                    t,
                    Vec3::new(0.8, 0.3, 0.1),
                    Vec3::ONE,
                    vis,
                    specular_sampling_weight(0.4, 1.0),
                    vis,
                )),
            ));
        }
    }
    v
}

fn tables() -> Vec<RoughPlasticTable> {
    vec![
        RoughPlasticTable::new(MicrofacetType::Ggx, 0.3, 1.5),
        RoughPlasticTable::new(MicrofacetType::Beckmann, 0.1, 1.33),
    ]
}

fn rel_close(a: f32, b: f32, tol: f32) -> bool {
    (a - b).abs() <= tol * a.abs().max(b.abs()) + 1e-6
}

#[test]
fn sampled_weight_and_pdf_agree_with_eval_and_pdf() {
    let tables = tables();
    let mut rng = TestRng::new(7);
    for (name, b) in smooth_models(&tables) {
        let mut checked = 0;
        for _ in 0..20_000 {
            let mut wi = uniform_sphere(&mut rng);
            if wi.z.abs() < 0.1 {
                continue; // avoid the last few degrees of grazing, where f32 cancellation dominates
            }
            if !b.flags().transmission && wi.z < 0.0 {
                wi.z = -wi.z;
            }
            let Some(s) = b.sample(wi, rng.f32(), vec2(&mut rng)) else {
                continue;
            };
            if s.lobe.delta {
                continue;
            }
            let pdf = b.pdf(wi, s.wo);
            let f = b.eval(wi, s.wo);
            assert!(
                rel_close(s.pdf, pdf, 1e-3),
                "{name}: wi {wi} wo {}: sample pdf {} vs pdf {pdf}",
                s.wo,
                s.pdf
            );
            for c in 0..3 {
                assert!(
                    rel_close(s.weight[c], f[c] / pdf, 1e-3),
                    "{name}: wi {wi} wo {}: weight {} vs eval/pdf {}",
                    s.wo,
                    s.weight,
                    f / pdf
                );
            }
            assert_eq!(s.lobe.transmission, s.wo.z * wi.z < 0.0, "{name}");
            checked += 1;
        }
        assert!(checked > 1000, "{name}: only {checked} samples");
    }
}

fn albedo(b: &Bsdf, wi: Vec3, n: usize, radiance_scaling: bool) -> Vec3 {
    let mut rng = TestRng::new(11);
    let mut sum = Vec3::ZERO;
    for _ in 0..n {
        if let Some(s) = b.sample(wi, rng.f32(), vec2(&mut rng)) {
            sum += if radiance_scaling {
                s.weight
            } else {
                s.weight * (s.eta * s.eta)
            };
        }
    }
    sum / n as f32
}

#[test]
fn diffuse_with_unit_reflectance_has_albedo_exactly_one() {
    let b = Bsdf::Diffuse(Diffuse::new(Vec3::ONE));
    let mut rng = TestRng::new(3);
    for _ in 0..10_000 {
        let wi = sph(80.0 * rng.f32(), 360.0 * rng.f32());
        let s = b
            .sample(wi, rng.f32(), vec2(&mut rng))
            .expect("diffuse always samples");
        assert_eq!(s.weight, Vec3::ONE);
    }
}

#[test]
fn white_models_do_not_create_energy() {
    let tables = tables();
    // A perfectly reflecting conductor: eta = 0, k = 1 gives F = 1 exactly.
    let (w_eta, w_k) = (Vec3::ZERO, Vec3::ONE);
    let mut models: Vec<(String, Bsdf)> = vec![
        (
            "conductor".into(),
            Bsdf::Conductor(Conductor::new(w_eta, w_k, Vec3::ONE)),
        ),
        (
            "dielectric".into(),
            Bsdf::Dielectric(Dielectric::new(1.5, Vec3::ONE, Vec3::ONE)),
        ),
        (
            "thindielectric".into(),
            Bsdf::ThinDielectric(ThinDielectric::new(1.5, Vec3::ONE, Vec3::ONE)),
        ),
        (
            "plastic".into(),
            Bsdf::Plastic(Plastic::new(1.5, Vec3::ONE, Vec3::ONE, false, 0.5)),
        ),
    ];
    for kind in [MicrofacetType::Ggx, MicrofacetType::Beckmann] {
        for a in [0.05f32, 0.3, 1.0] {
            models.push((
                format!("roughconductor {kind:?} {a}"),
                rough_conductor(kind, (a, a), true, w_eta, w_k),
            ));
            models.push((
                format!("roughdielectric {kind:?} {a}"),
                rough_dielectric(kind, (a, a), true, 1.5, Vec3::ONE, Vec3::ONE),
            ));
        }
    }
    for t in &tables {
        models.push((
            "roughplastic".into(),
            Bsdf::RoughPlastic(RoughPlastic::new(t, Vec3::ONE, Vec3::ONE, false, 0.5, true)),
        ));
    }
    for (name, b) in &models {
        for theta in [0.0f32, 30.0, 60.0, 85.0, 100.0, 150.0] {
            if theta > 90.0 && !b.flags().transmission {
                continue;
            }
            let wi = sph(theta, 20.0);
            // Without the radiance-mode eta^2 factor of refraction: <= 1.
            let a = albedo(b, wi, 200_000, false);
            assert!(
                a.max_element() <= 1.0 + 5e-3,
                "{name} theta {theta}: albedo {a}"
            );
            // With it, from outside (entering the denser medium): still <= 1.
            if theta < 90.0 {
                let a = albedo(b, wi, 200_000, true);
                assert!(
                    a.max_element() <= 1.0 + 5e-3,
                    "{name} theta {theta}: radiance albedo {a}"
                );
            }
        }
    }
    // Smooth white dielectric: every sample carries exactly eta_ti^2.
    let b = Bsdf::Dielectric(Dielectric::new(1.5, Vec3::ONE, Vec3::ONE));
    assert!(
        (albedo(&b, sph(40.0, 0.0), 10_000, false) - Vec3::ONE)
            .abs()
            .max_element()
            < 1e-5
    );
}

#[test]
fn smooth_white_rough_conductor_reflects_almost_everything() {
    for kind in [MicrofacetType::Ggx, MicrofacetType::Beckmann] {
        let b = rough_conductor(kind, (0.02, 0.02), true, Vec3::ZERO, Vec3::ONE);
        for theta in [0.0f32, 45.0, 70.0] {
            let a = albedo(&b, sph(theta, 10.0), 100_000, true);
            assert!(
                a.min_element() > 0.98 && a.max_element() <= 1.0 + 1e-4,
                "{kind:?} theta {theta}: {a}"
            );
        }
    }
}

#[test]
fn diffuse_and_rough_reflection_are_reciprocal() {
    let mut rng = TestRng::new(5);
    let models = [
        Bsdf::Diffuse(Diffuse::new(Vec3::new(0.3, 0.6, 0.9))),
        rough_conductor(MicrofacetType::Ggx, (0.3, 0.3), true, AU, AU_K),
        rough_conductor(MicrofacetType::Beckmann, (0.1, 0.4), true, AU, AU_K),
        rough_dielectric(
            MicrofacetType::Ggx,
            (0.3, 0.3),
            true,
            1.5,
            Vec3::ONE,
            Vec3::ONE,
        ),
    ];
    for b in &models {
        for _ in 0..2000 {
            let (mut wi, mut wo) = (uniform_sphere(&mut rng), uniform_sphere(&mut rng));
            wi.z = wi.z.abs().max(0.05);
            wo.z = wo.z.abs().max(0.05);
            let (wi, wo) = (wi.normalize(), wo.normalize());
            let f1 = b.eval(wi, wo) / wo.z;
            let f2 = b.eval(wo, wi) / wi.z;
            assert!(
                (f1 - f2).abs().max_element() <= 1e-3 * f1.max_element().max(1e-3),
                "{b:?}: {f1} vs {f2}"
            );
        }
    }
}

#[test]
fn no_model_produces_nan_or_infinity_anywhere() {
    let mut tables = Vec::new();
    for kind in [MicrofacetType::Ggx, MicrofacetType::Beckmann] {
        for a in [0.0f32, 1e-4, 1.0] {
            for eta in [1.0f32, 1.5, 1.0 / 1.5] {
                tables.push(RoughPlasticTable::new(kind, a, eta));
            }
        }
    }
    let mut models: Vec<Bsdf> = vec![
        Bsdf::Diffuse(Diffuse::new(Vec3::ONE)),
        Bsdf::Conductor(Conductor::new(AU, AU_K, Vec3::ONE)),
        Bsdf::Conductor(Conductor::new(Vec3::ZERO, Vec3::ZERO, Vec3::ONE)),
    ];
    for eta in [1.0f32, 1.5, 1.0 / 1.5] {
        models.push(Bsdf::Dielectric(Dielectric::new(eta, Vec3::ONE, Vec3::ONE)));
        models.push(Bsdf::ThinDielectric(ThinDielectric::new(
            eta,
            Vec3::ONE,
            Vec3::ONE,
        )));
        models.push(Bsdf::Plastic(Plastic::new(
            eta,
            Vec3::ONE,
            Vec3::ONE,
            true,
            0.5,
        )));
        models.push(Bsdf::Plastic(Plastic::new(
            eta,
            Vec3::ZERO,
            Vec3::ZERO,
            false,
            0.0,
        )));
        for kind in [MicrofacetType::Ggx, MicrofacetType::Beckmann] {
            for (au, av) in [(0.0f32, 0.0f32), (1e-4, 1e-4), (1.0, 1.0), (1e-4, 1.0)] {
                for vis in [true, false] {
                    models.push(rough_conductor(kind, (au, av), vis, AU, AU_K));
                    models.push(rough_dielectric(
                        kind,
                        (au, av),
                        vis,
                        eta,
                        Vec3::ONE,
                        Vec3::ONE,
                    ));
                }
            }
        }
    }
    for t in &tables {
        models.push(Bsdf::RoughPlastic(RoughPlastic::new(
            t,
            Vec3::ONE,
            Vec3::ONE,
            true,
            0.5,
            true,
        )));
        models.push(Bsdf::RoughPlastic(RoughPlastic::new(
            t,
            Vec3::ONE,
            Vec3::ONE,
            false,
            1.0,
            false,
        )));
    }
    let mut dirs = vec![
        Vec3::Z,
        -Vec3::Z,
        Vec3::X,
        -Vec3::Y,
        Vec3::new(0.6, 0.8, 0.0),
        Vec3::new(1.0, 0.0, 1e-7).normalize(),
        Vec3::new(1.0, 0.0, -1e-7).normalize(),
    ];
    let mut rng = TestRng::new(9);
    for _ in 0..40 {
        dirs.push(uniform_sphere(&mut rng));
    }
    let us = [0.0f32, 1e-7, 0.5, 0.9999999];
    for b in &models {
        for &wi in &dirs {
            for &wo in &dirs {
                let f = b.eval(wi, wo);
                let p = b.pdf(wi, wo);
                assert!(
                    f.is_finite() && f.min_element() >= 0.0 && p.is_finite() && p >= 0.0,
                    "{b:?} {wi} {wo}: {f} {p}"
                );
            }
            for &a in &us {
                for &x in &us {
                    for &y in &us {
                        if let Some(s) = b.sample(wi, a, Vec2::new(x, y)) {
                            assert!(
                                s.weight.is_finite()
                                    && s.weight.max_element() > 0.0
                                    && s.pdf > 0.0
                                    && s.pdf.is_finite()
                                    && s.wo.is_finite()
                                    && s.eta.is_finite(),
                                "{b:?} {wi}: {s:?}"
                            );
                            assert!((s.wo.length() - 1.0).abs() < 1e-3, "{b:?} {wi}: {s:?}");
                        }
                    }
                }
            }
            for _ in 0..50 {
                if let Some(s) = b.sample(wi, rng.f32(), vec2(&mut rng)) {
                    assert!(
                        s.weight.is_finite() && s.pdf.is_finite() && s.pdf > 0.0,
                        "{b:?} {wi}: {s:?}"
                    );
                }
            }
        }
    }
}

#[test]
fn all_finite_rejects_nan_and_infinities() {
    assert!(crate::all_finite([
        0.0,
        -1.0,
        f32::MAX,
        f32::MIN_POSITIVE,
        -0.0
    ]));
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        assert!(!crate::all_finite([1.0, bad, 2.0]));
        assert!(!crate::all_finite([bad]));
    }
}

#[test]
fn index_matched_rough_dielectric_passes_light_straight_through() {
    // eta = 1 (equal IORs): no interface, whatever the roughness. Walter's model is
    // degenerate there (half vector 0); before the fix every sample was rejected and the
    // object rendered black. Now: a delta transmission wo = -wi of weight
    // `specular_transmittance`, no continuous part.
    let mut rng = TestRng::new(9);
    for kind in [MicrofacetType::Ggx, MicrofacetType::Beckmann] {
        for alpha in [1e-4f32, 0.3, 1.0] {
            let b = rough_dielectric(kind, (alpha, alpha), true, 1.0, Vec3::ONE, Vec3::splat(0.8));
            let flags = b.flags();
            assert!(flags.delta && !flags.smooth, "{kind:?} {alpha}: {flags:?}");
            for _ in 0..100 {
                let wi = uniform_sphere(&mut rng);
                let (ul, u) = (rng.f32(), Vec2::new(rng.f32(), rng.f32()));
                let s = b.sample(wi, ul, u).expect("never absorbed");
                assert_eq!(s.wo, -wi);
                assert_eq!(s.weight, Vec3::splat(0.8));
                assert!(s.lobe.delta && s.lobe.transmission && s.eta == 1.0);
                let wo = uniform_sphere(&mut rng);
                assert_eq!(b.eval(wi, wo), Vec3::ZERO);
                assert_eq!(b.pdf(wi, wo), 0.0);
            }
        }
    }
}
