//! Tests of taking, shipping, merging and applying one iteration's statistics.

use super::*;
use crate::config::{DirectionalFilter, FractionLoss, FractionMode, GuideConfig, SpatialFilter};
use crate::record::Record;
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
    applied.apply_stats(&merged).unwrap();
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
        one.apply_stats(&merged),
        Err(crate::StatsError::StructureMismatch)
    ));
}
