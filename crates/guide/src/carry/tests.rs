//! Tests of carry-over: exact deposit into the refined structure, and the carried weight
//! left out of spatial splits.

use crate::config::GuideConfig;
use crate::record::Record;
use crate::sdtree::SdTree;
use crate::test_support::{clustered_records, TestRng};
use glam::Vec3;

/// Sum of a quadtree's leaf-cell sums (what a refinement builds on).
fn leaf_cell_total(t: &crate::DTree) -> u128 {
    t.nodes
        .iter()
        .flat_map(|n| {
            (0..4)
                .filter(|&q| n.children[q] == 0)
                .map(|q| n.sums[q].get())
        })
        .sum()
}

#[test]
fn carry_over_moves_the_built_statistics_into_the_refined_structure_exactly() {
    // Deterministic integer arithmetic (no significance level).
    for (beta, q) in [(1.0, 256u128), (0.5, 128)] {
        let cfg = GuideConfig {
            s_tree_threshold: 1e9, // one spatial leaf
            carry_over: beta,
            ..GuideConfig::default()
        };
        let mut t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg);
        let mut rng = TestRng::new(81);
        for r in clustered_records(&mut rng, 5000) {
            t.record(&r, &mut rng.f32_source());
        }
        let (total, weight) = {
            let b = &t.leaves()[0].building;
            (leaf_cell_total(b), b.weight_fixed())
        };
        assert!(t.leaves()[0].prior.weight_fixed() == 0, "no prior before");
        t.refine(0);
        let l = &t.leaves()[0];
        let (b, p) = (&l.building, &l.prior);
        assert_eq!(leaf_cell_total(b), 0, "the building tree starts empty");
        assert_eq!(b.weight_fixed(), 0);
        assert!(b.node_count() > 1, "the structure was refined");
        assert_eq!(
            p.node_count(),
            b.node_count(),
            "the prior has its structure"
        );
        for (x, y) in p.nodes.iter().zip(&b.nodes) {
            assert_eq!(x.children, y.children);
        }
        // Every old leaf cell's scaled sum lands somewhere; a split cell's sum is shared
        // exactly, so the only loss is each old cell's rounding of the scaling.
        let cells = t.leaves()[0].sampling.tree().leaf_cells().len() as u128;
        let carried = leaf_cell_total(p);
        let exact = total / 256 * q + (total % 256) * q / 256;
        assert!(
            carried <= exact && carried + cells >= exact,
            "{carried} vs {exact}"
        );
        if q == 256 {
            assert_eq!(carried, total);
        }
        assert_eq!(
            p.weight_fixed(),
            weight / 256 * q + (weight % 256) * q / 256
        );
        // With everything carried and nothing new, the next tree learns the same radiance.
        let flux = t.leaves()[0].flux;
        t.refine(1);
        if q == 256 {
            assert_eq!(t.leaves()[0].flux, flux);
            assert_eq!(leaf_cell_total(&t.leaves()[0].prior), total);
        }
    }
}

#[test]
fn carried_weight_does_not_count_towards_spatial_splits() {
    // threshold after iteration k: c sqrt(2^(k+1)) with spp_per_pass 4; c = 1000.
    let cfg = GuideConfig {
        s_tree_threshold: 1000.0,
        carry_over: 1.0,
        ..GuideConfig::default()
    };
    let mut t = SdTree::new(Vec3::ZERO, Vec3::ONE, cfg.clone());
    let rec = |i: usize| {
        let p = Vec3::new(0.2 + 0.0006 * (i % 1000) as f32, 0.5, 0.5);
        Record::radiance_only(p, Vec3::Z, 1.0, 0.5, 1.0)
    };
    for i in 0..1000 {
        t.record(&rec(i), &mut || 0.5);
    }
    t.refine(0); // W 1000 <= 1414: no split
    for i in 0..1200 {
        t.record(&rec(i), &mut || 0.5);
    }
    // W this iteration 1200 <= 2000, but 2200 with the carried 1000.
    t.refine(1);
    assert_eq!(t.leaves().len(), 1, "carried weight split the leaf");
    // Recorded weight alone above the threshold still splits, and the halves share the
    // carried weight.
    for i in 0..3000 {
        t.record(&rec(i), &mut || 0.5);
    }
    t.refine(2); // 3000 > 2828
    assert!(t.leaves().len() > 1);
    let w: u128 = t.leaves().iter().map(|l| l.prior.weight_fixed()).sum();
    assert_eq!(w, (1000 + 1200 + 3000) * crate::stats::FIXED_ONE);
}
