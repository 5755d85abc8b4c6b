use crate::*;
use std::time::Instant;

#[test]
fn rough_plastic_table_is_deterministic_and_cached() {
    for kind in [MicrofacetType::Ggx, MicrofacetType::Beckmann] {
        for (alpha, eta) in [(0.1f32, 1.5f32), (0.6, 1.33), (1e-4, 1.5), (1.0, 1.0 / 1.5)] {
            let t0 = Instant::now();
            let a = RoughPlasticTable::compute(kind, alpha, eta);
            let dt = t0.elapsed();
            let b = RoughPlasticTable::new(kind, alpha, eta);
            eprintln!(
                "{kind:?} alpha {alpha} eta {eta}: {:.2} ms, Ri {}",
                dt.as_secs_f64() * 1e3,
                a.internal_reflectance
            );
            assert_eq!(a, b);
            let t1 = Instant::now();
            let c = RoughPlasticTable::new(kind, alpha, eta);
            assert_eq!(a, c);
            assert!(
                t1.elapsed().as_secs_f64() < 5e-3,
                "a cached table must be cheap"
            );
            assert!(a
                .external_transmittance
                .iter()
                .all(|t| t.is_finite() && (0.0..=1.0).contains(t)));
            assert!(
                a.internal_reflectance.is_finite() && (0.0..1.0).contains(&a.internal_reflectance)
            );
        }
    }
}
