//! Tests of the iteration schedule, the automatic stop, inverse-variance weights and the path
//! fallback's rule.

use super::*;
use crate::test_support::TestRng;

#[test]
fn schedule_doubles_passes_and_last_iteration_absorbs_the_remainder() {
    assert_eq!(plan_spp(1024, 4), vec![1, 2, 4, 8, 16, 32, 64, 129]);
    assert_eq!(plan_spp(12, 4), vec![1, 2]);
    assert_eq!(plan_spp(4, 4), vec![1]);
    assert_eq!(plan_spp(0, 4), Vec::<u32>::new());
    assert_eq!(total_passes(10, 4), 3);
    for spp in [1u32, 7, 64, 100, 1000, 4096, 5000] {
        for ppp in [1u32, 4] {
            let plan = plan_spp(spp, ppp);
            let total: u32 = plan.iter().sum();
            assert_eq!(total, total_passes(spp, ppp));
            let last = *plan.last().unwrap();
            assert!(2 * last + 2 >= total, "last {last} of {total}");
            for (k, &p) in plan.iter().enumerate().take(plan.len() - 1) {
                assert_eq!(p, 1 << k);
            }
        }
    }
    assert_eq!(iteration_passes(3, 100), (8, false));
    assert_eq!(iteration_passes(3, 20), (20, true));
    assert_eq!(
        plan_iteration(7, Budget::Spp(1024), 4, 127, 0.0, None),
        Some(IterationPlan {
            length: IterationLength::Passes(129),
            is_last: true
        })
    );
    assert_eq!(
        plan_iteration(8, Budget::Spp(1024), 4, 256, 0.0, None),
        None
    );
    assert_eq!(
        plan_iteration(3, Budget::Seconds(100.0), 1, 7, 10.0, Some(5.0)),
        Some(IterationPlan {
            length: IterationLength::Passes(8),
            is_last: false
        })
    );
    assert_eq!(
        plan_iteration(4, Budget::Seconds(100.0), 1, 15, 60.0, Some(10.0)),
        Some(IterationPlan {
            length: IterationLength::UntilSeconds(100.0),
            is_last: true
        })
    );
    assert_eq!(
        plan_iteration(4, Budget::Seconds(100.0), 1, 15, 100.0, Some(10.0)),
        None
    );
    assert!(time_iteration_is_last(100.0, 40.0));
    assert!(!time_iteration_is_last(100.0, 30.0));
}

#[test]
fn automatic_combination_stops_when_extrapolated_variance_worsens_after_256_spp() {
    // Mocked iterations with an spp budget of 1024 passes at 1 spp.
    let mk = |vars: &[f64]| {
        let mut remaining = 1024.0;
        let mut spp = 0u64;
        let mut h = Vec::new();
        for (k, &v) in vars.iter().enumerate() {
            let cost = (1u64 << k) as f64;
            h.push(IterationOutcome {
                variance: v,
                cost,
                remaining_before: remaining,
                spp_before: spp,
            });
            remaining -= cost;
            spp += cost as u64;
        }
        h
    };
    // variance halves (extrapolation improves) until iteration 9, then stalls
    let mut vars: Vec<f64> = (0..9)
        .map(|k| 1.0 / (1u64 << k) as f64 / (1.0 + k as f64))
        .collect();
    vars.push(vars[8] * 0.9); // k = 9: 512 passes; worse extrapolation? check below
    let h = mk(&vars);
    let e8 = extrapolated_final_variance(h[8].variance, h[8].cost, h[8].remaining_before);
    let e9 = extrapolated_final_variance(h[9].variance, h[9].cost, h[9].remaining_before);
    assert!(e9 > e8);
    assert_eq!(automatic_stop_index(&h), Some(9));
    // the same worsening before 256 spp is not trusted
    let mut early: Vec<f64> = vec![1.0, 0.4, 0.9];
    early.extend((3..8).map(|k| 0.5f64.powi(k) / 8.0));
    let he = mk(&early);
    assert_eq!(automatic_stop_index(&he[..3]), None);
    // a budget that cannot afford the next iteration stops
    let tight = vec![IterationOutcome {
        variance: 1.0,
        cost: 64.0,
        remaining_before: 100.0,
        spp_before: 63,
    }];
    assert!(automatic_should_stop(&tight));
    assert!((extrapolated_final_variance(2.0, 4.0, 16.0) - 0.5).abs() < 1e-12);
}

/// Inverse-variance combination of images (equal-length slices), weighted per entry in f64
/// as a renderer combines its iteration images with [`inverse_variance_weights`].
fn combine_inverse_variance(images: &[&[f32]], variances: &[f64]) -> Vec<f32> {
    let weights = inverse_variance_weights(variances);
    let mut out = vec![0.0f64; images[0].len()];
    for (img, &w) in images.iter().zip(&weights) {
        for (o, &x) in out.iter_mut().zip(img.iter()) {
            *o += w * x as f64;
        }
    }
    out.into_iter().map(|x| x as f32).collect()
}

#[test]
fn inverse_variance_weights_combine_synthetic_images_optimally() {
    let w = inverse_variance_weights(&[1.0, 1.0, 4.0, 2.0, 1.0, 0.5]);
    assert_eq!(&w[..2], &[0.0, 0.0]);
    let inv = [0.25, 0.5, 1.0, 2.0];
    let s: f64 = inv.iter().sum();
    for i in 0..4 {
        assert!((w[2 + i] - inv[i] / s).abs() < 1e-12);
    }
    assert_eq!(
        inverse_variance_weights(&[3.0, 0.0, 2.0]),
        vec![0.0, 1.0, 0.0]
    );
    assert_eq!(inverse_variance_weights(&[f64::NAN]), vec![1.0]);
    // synthetic noisy images of a known truth
    let mut rng = TestRng::new(7);
    let npx = 20_000;
    let truth: Vec<f32> = (0..npx).map(|i| (i % 17) as f32 * 0.1).collect();
    let sig = [2.0f64, 1.5, 1.0, 0.8, 0.6, 0.5];
    let imgs: Vec<Vec<f32>> = sig
        .iter()
        .map(|&s| {
            truth
                .iter()
                .map(|&t| (t as f64 + s * rng.gauss()) as f32)
                .collect()
        })
        .collect();
    let vars: Vec<f64> = sig.iter().map(|s| s * s).collect();
    let refs: Vec<&[f32]> = imgs.iter().map(|v| v.as_slice()).collect();
    let comb = combine_inverse_variance(&refs, &vars);
    let mse: f64 = comb
        .iter()
        .zip(&truth)
        .map(|(&c, &t)| ((c - t) as f64).powi(2))
        .sum::<f64>()
        / npx as f64;
    let ideal = 1.0 / vars[2..].iter().map(|v| 1.0 / v).sum::<f64>();
    // relative sd of the MSE estimate is sqrt(2/npx) = 1%; 5% is ~5 sigma
    assert!((mse / ideal - 1.0).abs() < 0.05, "mse {mse} ideal {ideal}");
    assert!(mse < vars[5] * 0.8);
}

#[test]
fn guiding_verdict_keeps_clear_wins_and_falls_back_after_two_clear_losses_or_one_far_loss() {
    // Deterministic rule (no significance level). `v(costs, path)`: per-sample variance ratio 1.
    use crate::schedule::{guiding_verdict, GuidingVerdict::*};
    let v = |costs: &[f64], path: f64| guiding_verdict(costs, path, 1.0);
    assert_eq!(v(&[], 1.0), Undecided);
    assert_eq!(v(&[0.5], 1.0), Keep, "clearly better at the first check");
    assert_eq!(v(&[2.3], 1.0), Undecided, "one clear loss is not enough");
    assert_eq!(v(&[2.4], 1.0), FallBack, "a far loss at the first check is");
    assert_eq!(v(&[240.0], 100.0), FallBack);
    assert_eq!(
        v(&[1.9, 1.2], 1.0),
        Undecided,
        "the second loss must be clear too"
    );
    assert_eq!(v(&[3.0, 1.3], 1.0), FallBack, "two clear losses in a row");
    assert_eq!(v(&[3.0, 1.1], 1.0), Undecided, "a marginal loss waits");
    assert_eq!(v(&[1.1, 3.0], 1.0), Undecided);
    assert_eq!(v(&[1.1, 1.1, 1.1], 1.0), Undecided);
    assert_eq!(
        v(&[1.1, 1.1, 1.1, 1.2], 1.0),
        Keep,
        "last check: marginal keeps"
    );
    assert_eq!(
        v(&[1.1, 1.1, 1.1, 1.3], 1.0),
        FallBack,
        "last check: clear loss"
    );
    assert_eq!(v(&[3.0, 0.79], 1.0), Keep);
    // scale invariance: only the ratio to the path cost counts
    assert_eq!(v(&[300.0, 130.0], 100.0), FallBack);
    // no usable comparison: guiding stays (after the last check), never a fallback
    assert_eq!(v(&[3.0, 3.0], 0.0), Undecided);
    assert_eq!(v(&[3.0, 3.0, 3.0, 3.0], f64::NAN), Keep);
    assert_eq!(v(&[f64::NAN, 3.0], 1.0), Undecided);
}

#[test]
fn guiding_verdict_falls_back_at_the_first_check_when_guided_samples_are_noisier_and_dearer() {
    // Deterministic rule (no significance level).
    use crate::schedule::{guiding_verdict as v, GuidingVerdict::*};
    // cornell-box-like: noisier per sample and clearly less efficient
    assert_eq!(v(&[2.0], 1.0, 1.8), FallBack);
    assert_eq!(
        v(&[1.25], 1.0, 1.2),
        FallBack,
        "both thresholds are inclusive"
    );
    // door-ajar-like: dearer in cost but less noisy per sample: the tree gets its chance
    assert_eq!(v(&[2.0], 1.0, 0.77), Undecided);
    assert_eq!(v(&[2.0], 1.0, 1.19), Undecided);
    // noisier but not clearly less efficient (cheap guided samples): not yet
    assert_eq!(v(&[1.2], 1.0, 1.8), Undecided);
    // only the first check uses it; later ones need two clear losses in a row
    assert_eq!(v(&[1.1, 2.0], 1.0, 1.8), Undecided);
    assert_eq!(v(&[2.0, 2.0], 1.0, 0.5), FallBack);
    // a clear win keeps guiding whatever the variance ratio says
    assert_eq!(v(&[0.5], 1.0, 1.8), Keep);
    // a NaN variance ratio is no evidence
    assert_eq!(v(&[2.0], 1.0, f64::NAN), Undecided);
}
