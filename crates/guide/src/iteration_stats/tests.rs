//! Tests of taking, shipping, merging and applying one iteration's statistics.

use super::*;
use crate::config::{DirectionalFilter, FractionLoss, FractionMode, GuideConfig, SpatialFilter};
use crate::record::Record;
use crate::sdtree::{GradTarget, HeldSlot};
use crate::test_support::{det_records, record_all, warmed_tree, TestRng};

#[test]
fn merged_statistics_of_a_three_way_split_equal_one_place_recording() {
    let cfg = GuideConfig {
        s_tree_threshold: 300.0,
        spatial_filter: SpatialFilter::Box,
        directional_filter: DirectionalFilter::Box,
        bsdf_sampling_fraction: FractionMode::Learned {
            loss: FractionLoss::Var,
        },
        carry_over: 0.5,
        ..GuideConfig::default()
    };
    let base = warmed_tree(cfg, 61, 4000, 2);
    assert!(
        base.leaves().iter().any(|l| l.prior.weight_fixed() > 0),
        "the base tree carries statistics"
    );
    let recs = det_records(20_000, 62);
    let mut rng = TestRng::new(63);
    let mut parts: [Vec<(Record, u64)>; 3] = Default::default();
    for r in &recs {
        parts[rng.below(3) as usize].push(*r);
    }
    let mut one = base.clone();
    record_all(&one, &recs);
    let mut shipped = Vec::new();
    for p in &parts {
        let mut w = base.clone();
        record_all(&w, p);
        let st = w.take_stats();
        let bytes = st.encode();
        let back = IterationStats::decode(&bytes).unwrap();
        assert_eq!(back, st);
        shipped.push(back);
    }
    let merged = IterationStats::merge_all(shipped.iter().rev()).unwrap();
    assert!(merged
        .leaves
        .iter()
        .any(|l| l.light[2] != 0 && l.light[0] != 0));
    let mut applied = base.clone();
    applied.apply_stats(&merged, GradTarget::Batch).unwrap();
    assert_eq!(applied.encode(), one.encode());
    assert_eq!(one.clone().take_stats(), merged);
    one.step_fractions();
    applied.step_fractions();
    one.refine(2);
    applied.refine(2);
    assert_eq!(applied.encode(), one.encode());
    assert!(one.leaves().iter().any(|l| l.light.std_dev > 0.0));
    // statistics of another structure are refused
    assert!(matches!(
        one.apply_stats(&merged, GradTarget::Batch),
        Err(crate::StatsError::StructureMismatch)
    ));
}

#[test]
fn gradients_held_by_unit_and_folded_equal_gradients_recorded_into_the_batch() {
    let cfg = GuideConfig {
        bsdf_sampling_fraction: FractionMode::Learned {
            loss: FractionLoss::Var,
        },
        ..GuideConfig::default()
    };
    let base = warmed_tree(cfg, 71, 4000, 2);
    let (even, odd) = (det_records(6_000, 72), det_records(6_000, 73));
    let mut one = base.clone();
    record_all(&one, &even);
    record_all(&one, &odd);
    // one process: records go to the unit's slot directly
    let mut held = base.clone();
    held.set_grad_target(GradTarget::Held(HeldSlot::of_unit(4)));
    record_all(&held, &even);
    held.set_grad_target(GradTarget::Held(HeldSlot::of_unit(5)));
    record_all(&held, &odd);
    assert_eq!(
        held.step_fractions(),
        0,
        "nothing is in the batch before a fold"
    );
    // a farm: a worker's statistics applied into the unit's slot
    let mut shipped = base.clone();
    for (unit, recs) in [(5, &odd), (4, &even)] {
        let w = base.clone();
        record_all(&w, recs);
        let mut w = w;
        let target = GradTarget::Held(HeldSlot::of_unit(unit));
        shipped.apply_stats(&w.take_stats(), target).unwrap();
    }
    for t in [&mut held, &mut shipped] {
        t.fold_held(HeldSlot::Even);
        t.fold_held(HeldSlot::Odd);
        assert!(t
            .leaves()
            .iter()
            .all(|l| l.held.iter().all(|h| h.is_zero())));
    }
    assert!(one.step_fractions() > 0);
    assert!(held.step_fractions() > 0);
    assert!(shipped.step_fractions() > 0);
    assert_eq!(held.encode(), one.encode());
    assert_eq!(shipped.encode(), one.encode());
}

#[test]
fn gradients_taken_per_pass_and_records_taken_once_merge_to_one_take() {
    let cfg = GuideConfig {
        bsdf_sampling_fraction: FractionMode::Learned {
            loss: FractionLoss::Var,
        },
        carry_over: 0.5,
        ..GuideConfig::default()
    };
    let base = warmed_tree(cfg, 81, 4000, 2);
    let passes = [det_records(5_000, 82), det_records(5_000, 83)];
    let mut whole = base.clone();
    passes.iter().for_each(|p| record_all(&whole, p));
    let whole = whole.take_stats();
    // a worker: each pass's gradients shipped at its end, the records once at the end
    let mut split = base.clone();
    let mut shipped = Vec::new();
    for p in &passes {
        record_all(&split, p);
        let g = split.take_gradients();
        assert!(!g.leaves.is_empty(), "the pass recorded gradients");
        assert!(g
            .leaves
            .iter()
            .all(|l| l.weight == 0 && l.nodes.is_empty() && l.light == [0; 3]));
        assert_eq!(g.overflow_events, 0);
        shipped.push(g);
    }
    let records = split.take_stats();
    assert!(records
        .leaves
        .iter()
        .all(|l| l.grad_weight == 0 && l.grad_pos == [0; 8] && l.grad_neg == [0; 8]));
    assert!(records.leaves.iter().any(|l| !l.nodes.is_empty()));
    shipped.push(records);
    assert_eq!(IterationStats::merge_all(shipped.iter()).unwrap(), whole);
    assert!(split.take_stats().leaves.is_empty(), "nothing is left");
    // the same split of statistics already taken: the gradients part is the passes' sum
    let (grads, rest) = whole.clone().split_gradients();
    let pass_grads = IterationStats::merge_all(shipped[..2].iter()).unwrap();
    assert_eq!(grads, pass_grads);
    assert_eq!(rest, shipped[2]);
    assert_eq!(IterationStats::merge_all([&grads, &rest]).unwrap(), whole);
}
