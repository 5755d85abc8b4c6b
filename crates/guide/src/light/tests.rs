//! Tests of the light-sample statistics through the SD-tree.

use crate::config::GuideConfig;
use crate::record::Record;
use crate::sdtree::SdTree;
use glam::Vec3;

#[test]
fn light_sample_statistics_freeze_their_mean_and_deviation_at_refinement() {
    // Deterministic (no significance level): exact sums of dyadic values.
    let cfg = GuideConfig {
        s_tree_threshold: 10.0,
        ..GuideConfig::default()
    };
    let mut t = SdTree::new(Vec3::ZERO, Vec3::ONE, cfg);
    let h = t.leaf_index(Vec3::splat(0.5));
    for v in [0.0, 1.0, 2.0, 3.0, -1.0, f32::NAN, f32::INFINITY] {
        t.record_light_sample(h, v); // the last three are ignored
    }
    assert_eq!(t.take_nonfinite_records(), 2, "NaN and inf are counted");
    assert_eq!(
        t.light_sample_stats_leaf(h),
        (0.0, 0.0),
        "frozen only at refine"
    );
    assert_eq!(t.leaves()[0].light.sums()[2], 4 * crate::stats::FIXED_ONE);
    // enough records for the leaf to split
    for i in 0..400 {
        let p = Vec3::new(0.3 + 0.001 * i as f32, 0.5, 0.5);
        t.record(
            &Record::radiance_only(p, Vec3::Z, 1.0, 0.5, 1.0),
            &mut || 0.5,
        );
    }
    t.refine(0);
    assert!(t.leaves().len() > 1, "the leaf split");
    let expect = (1.5f32, 1.25f64.sqrt() as f32); // mean of 0..3, sqrt(3.5 - 1.5^2)
    for (i, l) in t.leaves().iter().enumerate() {
        assert_eq!((l.light.mean, l.light.std_dev), expect, "leaf {i} inherits");
        assert_eq!(l.light.sums(), [0; 3], "sums zeroed for the next iteration");
    }
    // An iteration without light samples keeps what was learned.
    t.refine(1);
    assert_eq!(
        t.light_sample_stats_leaf(t.leaf_index(Vec3::splat(0.5))),
        expect
    );
    // A certain light sample has no deviation.
    let h = t.leaf_index(Vec3::splat(0.5));
    for _ in 0..5 {
        t.record_light_sample(h, 0.75);
    }
    t.refine(2);
    let h = t.leaf_index(Vec3::splat(0.5));
    assert_eq!(t.light_sample_stats_leaf(h), (0.75, 0.0));
}
