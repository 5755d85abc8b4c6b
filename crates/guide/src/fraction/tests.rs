//! Tests of the learned BSDF-sampling fraction on a 1-D toy with a known optimum.

use super::*;
use crate::config::GuideConfig;
use crate::record::Record;
use crate::stats::FIXED_ONE;
use crate::test_support::{cube_tree, learned_config, TestRng};
use glam::Vec3;

/// Expected gradient of the loss with respect to theta (including L2), by quadrature, for the
/// 1-D toy: p_bsdf = 1, p_guide = 2x, F = 0.3 + 1.4x on [0, 1].
fn toy_expected_grad(theta: f64, p: i32) -> f64 {
    let a = 1.0 / (1.0 + (-theta).exp());
    let n = 20_000;
    let mut g = 0.0;
    for i in 0..n {
        let x = (i as f64 + 0.5) / n as f64;
        let (pb, pg, f) = (1.0, 2.0 * x, 0.3 + 1.4 * x);
        let q = a * pb + (1.0 - a) * pg;
        g += -(f / q).powi(p) * (pb - pg) / n as f64;
    }
    g * a * (1.0 - a) + 0.01 * theta
}

/// The toy's optimal fraction: the root of [`toy_expected_grad`] (bisection over theta).
fn toy_optimum(p: i32) -> f64 {
    let (mut lo, mut hi) = (-5.0f64, 5.0f64);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if toy_expected_grad(mid, p) > 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    1.0 / (1.0 + (-(0.5 * (lo + hi))).exp())
}

#[test]
fn adam_fraction_converges_to_the_analytic_optimum_on_a_1d_toy() {
    for loss in [FractionLoss::Kl, FractionLoss::Var] {
        let p = loss.exponent();
        let alpha_opt = toy_optimum(p);
        // Without the L2 term the optimum is exactly 0.3 (q = F); L2 pulls it towards 0.5.
        assert!(alpha_opt > 0.3 && alpha_opt < 0.45, "optimum {alpha_opt}");
        let unreg =
            toy_expected_grad(-(1.0f64 / 0.3 - 1.0).ln(), p) - 0.01 * -(1.0f64 / 0.3 - 1.0).ln();
        assert!(
            unreg.abs() < 1e-6,
            "unregularised gradient at alpha = 0.3: {unreg}"
        );
        let mut t = cube_tree(learned_config(1e15, loss));
        let mut rng = TestRng::new(99);
        let steps = 1500;
        let mut tail = 0.0;
        for s in 0..steps {
            let alpha = t.bsdf_sampling_fraction(Vec3::ZERO) as f64;
            for rec in toy_records(&mut rng, alpha, 128) {
                t.record(&rec, &mut rng.f32_source());
            }
            assert_eq!(t.step_fractions(), 1);
            if s >= steps - 300 {
                tail += t.leaves()[0].fraction.alpha();
            }
        }
        let alpha_end = tail / 300.0;
        assert!(
            (alpha_end - alpha_opt).abs() < 0.02,
            "{loss:?}: learned {alpha_end} vs optimum {alpha_opt}"
        );
    }
}

/// The toy's records (see [`toy_expected_grad`]), sampled with fraction `alpha`.
fn toy_records(rng: &mut TestRng, alpha: f64, n: usize) -> Vec<Record> {
    (0..n)
        .map(|_| {
            let x = if rng.f64() < alpha {
                rng.f64()
            } else {
                rng.f64().sqrt()
            };
            let (pb, pg) = (1.0, 2.0 * x);
            Record {
                position: Vec3::ZERO,
                direction: Vec3::Z,
                radiance: 0.0,
                pdf_mix: (alpha * pb + (1.0 - alpha) * pg) as f32,
                weight: 1.0,
                product: (0.3 + 1.4 * x) as f32,
                pdf_bsdf: pb as f32,
                pdf_guide: pg as f32,
                is_delta: false,
            }
        })
        .collect()
}

#[test]
fn learned_fraction_reaches_its_optimum_in_a_few_passes() {
    // One step_fractions per pass, as the renderer calls it. The first version took one Adam
    // step per call, so 8 passes moved alpha by at most 8 x 0.01 in theta (alpha 0.48-0.52).
    let p = FractionLoss::Kl.exponent();
    let alpha_opt = toy_optimum(p);
    let cfg = GuideConfig {
        fraction_clamp: (0.0, 1.0),
        ..learned_config(1e15, FractionLoss::Kl)
    };
    for seed in [5, 6, 7] {
        let mut t = cube_tree(cfg.clone());
        let mut rng = TestRng::new(seed);
        for _ in 0..8 {
            let alpha = t.bsdf_sampling_fraction(Vec3::ZERO) as f64;
            for r in toy_records(&mut rng, alpha, 2000) {
                t.record(&r, &mut rng.f32_source());
            }
            assert_eq!(t.step_fractions(), 1);
        }
        let alpha = t.leaves()[0].fraction.alpha();
        assert!(
            (alpha - alpha_opt).abs() < 0.03,
            "seed {seed}: alpha {alpha} after 8 passes, optimum {alpha_opt}"
        );
        // one Adam step per record: 256 per call at most
        assert_eq!(
            t.leaves()[0].fraction.t,
            8 * crate::fraction::MAX_STEPS_PER_CALL
        );
    }
}

#[test]
fn fraction_batch_holds_the_exact_gradient_at_every_grid_alpha() {
    use crate::fraction::{dloss_dalpha, interpolate, GRID, GRID_LEN};
    let t = cube_tree(learned_config(1e15, FractionLoss::Var));
    let mut rng = TestRng::new(17);
    // recorded with two different sampling fractions: the batch does not care
    let mut recs = toy_records(&mut rng, 0.3, 500);
    recs.extend(toy_records(&mut rng, 0.8, 500));
    for r in &recs {
        t.record(r, &mut rng.f32_source());
    }
    let g = &t.leaves()[0].grad;
    assert_eq!(g.weight.get(), 1000 * FIXED_ONE);
    for (k, &a) in GRID.iter().enumerate() {
        let exact: f64 = recs
            .iter()
            .map(|r| {
                dloss_dalpha(
                    a,
                    FractionLoss::Var,
                    r.product,
                    r.pdf_bsdf,
                    r.pdf_guide,
                    r.pdf_mix,
                )
                .unwrap()
            })
            .sum::<f64>()
            / 1000.0;
        let got = g.mean_at_grid(k).unwrap();
        assert!(
            (got - exact).abs() <= 1e-9 * exact.abs().max(1.0),
            "alpha {a}: {got} vs {exact}"
        );
        assert_eq!(g.mean(a), Some(got));
    }
    // interpolation: linear between grid points, constant beyond the ends
    let m: [f64; GRID_LEN] = std::array::from_fn(|k| k as f64 * k as f64);
    assert_eq!(interpolate(&m, 0.0), 0.0);
    assert_eq!(interpolate(&m, 1.0), m[GRID_LEN - 1]);
    let mid = 0.5 * (GRID[2] + GRID[3]);
    assert!((interpolate(&m, mid) - 0.5 * (m[2] + m[3])).abs() < 1e-12);
}
