//! Tests of the spatial filters through recording: box splats conserve mass exactly, and the
//! stochastic filter is the box filter on average.

use crate::config::{DirectionalFilter, GuideConfig, SpatialFilter};
use crate::mapping::uv_to_dir;
use crate::record::Record;
use crate::stats::{to_fixed, FIXED_ONE};
use crate::test_support::{clustered_records, warmed_tree, TestRng};
use glam::{Vec2, Vec3};
use pathfarm_testkit::{pooled_chi2_pvalue as chi2_test, sidak};

#[test]
fn box_splats_conserve_mass_exactly() {
    let base = GuideConfig {
        s_tree_threshold: 200.0,
        spatial_filter: SpatialFilter::Box,
        directional_filter: DirectionalFilter::Box,
        ..GuideConfig::default()
    };
    let t = warmed_tree(base, 31, 4000, 3);
    assert!(t.stats().leaves > 8);
    let mut rng = TestRng::new(32);
    let mut recs = clustered_records(&mut rng, 3000);
    // records at the phi seam, the poles and the domain corners
    for i in 0..200 {
        let v = if i % 2 == 0 { 0.9999 } else { 0.0001 };
        let u = [0.0001f32, 0.5, 0.9999][i % 3];
        let c = if i % 4 == 0 {
            Vec3::splat(1.0)
        } else {
            Vec3::splat(-1.0)
        };
        recs.push(Record::radiance_only(
            c,
            uv_to_dir(Vec2::new(u, v)),
            1.5,
            0.3,
            1.0,
        ));
    }
    let mut expect_sum = 0u128;
    let mut expect_w = 0u128;
    for r in &recs {
        t.record(r, &mut rng.f32_source());
        let v = r.weight as f64 * r.radiance as f64 / r.pdf_mix as f64;
        expect_sum += to_fixed(v).0;
        expect_w += to_fixed(r.weight as f64).0;
    }
    let mut got_sum = 0u128;
    let mut got_w = 0u128;
    let mut touched = 0;
    for l in t.leaves() {
        got_w += l.building.weight_fixed();
        let s: u128 = l.building.nodes().iter().map(|n| n.total()).sum();
        got_sum += s;
        touched += (s > 0) as usize;
    }
    assert_eq!(got_w, expect_w);
    assert_eq!(got_sum, expect_sum);
    assert!(touched > 4);
    // a single splat spreads over several spatial leaves and several cells
    let mut t2 = t.clone();
    let _ = t2.take_stats();
    let p = Vec3::new(-0.62, -0.6, 0.7);
    t2.record(
        &Record::radiance_only(p, uv_to_dir(Vec2::new(0.3, 0.9995)), 1.0, 1.0, 1.0),
        &mut rng.f32_source(),
    );
    let s = t2.take_stats();
    assert!(s.leaves.len() > 1, "box splat hit only one leaf");
    assert!(s.leaves.iter().any(|l| l.nodes.len() > 1
        || l.nodes
            .iter()
            .any(|n| n.1.iter().filter(|&&x| x > 0).count() > 1)));
    let tot: u128 = s
        .leaves
        .iter()
        .flat_map(|l| l.nodes.iter().flat_map(|n| n.1.iter()))
        .sum();
    assert_eq!(tot, FIXED_ONE);
}

#[test]
fn mean_of_stochastic_splats_equals_the_box_splat() {
    // Chi-square at significance 0.01 over the per-leaf counts of M jittered records, against
    // the box filter's per-leaf weights; two record positions (Šidák corrected).
    let mk = |f| GuideConfig {
        s_tree_threshold: 150.0,
        spatial_filter: f,
        ..GuideConfig::default()
    };
    let warm = warmed_tree(mk(SpatialFilter::Nearest), 41, 5000, 2);
    assert!(warm.stats().leaves > 8);
    let level = sidak(0.01, 2);
    for p0 in [Vec3::new(-0.66, -0.61, 0.72), Vec3::new(-0.98, 0.99, -0.5)] {
        // near a corner of its leaf, so that the box overlaps several leaves
        let l = warm.lookup(p0);
        let p = l.min + 0.15 * l.extent;
        let mut a = warm.clone();
        a.config.spatial_filter = SpatialFilter::Stochastic;
        let _ = a.take_stats();
        let mut b = warm.clone();
        b.config.spatial_filter = SpatialFilter::Box;
        let _ = b.take_stats();
        let m = 40_000;
        let mut rng = TestRng::new(42);
        let rec = Record::radiance_only(p, Vec3::Z, 1.0, 1.0, 1.0);
        for _ in 0..m {
            a.record(&rec, &mut rng.f32_source());
        }
        b.record(&rec, &mut rng.f32_source());
        let obs: Vec<f64> = a.leaves().iter().map(|l| l.building.weight()).collect();
        let exp: Vec<f64> = b
            .leaves()
            .iter()
            .map(|l| l.building.weight() * m as f64)
            .collect();
        assert!(
            exp.iter().filter(|&&e| e > 0.0).count() >= 2,
            "box must overlap several leaves: {exp:?} {l:?}"
        );
        let pv = chi2_test(&obs, &exp);
        assert!(pv > level, "p = {pv}");
    }
}
