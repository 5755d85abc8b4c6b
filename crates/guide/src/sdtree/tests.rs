//! Tests of the SD-tree facade: sampling and pdf at a point, recording, refinement (spatial
//! splits, quadtree node caps), determinism across threads and size statistics.
//!
//! Statistical tests use fixed seeds and state their significance level.

mod stability;

use super::*;
use crate::config::FractionLoss;
use crate::dtree::MAX_DEPTH;
use crate::mapping::{dir_to_uv, uv_to_dir};
use crate::stats::FIXED_ONE;
use crate::test_support::{
    clustered_records, config_2019, cube_tree, det_records, learned_config, record_all,
    threshold_config, warmed_tree, TestRng,
};
use crate::AdamConfig;
use glam::Vec2;

#[test]
fn sdtree_sample_returns_unit_directions_whose_pdf_round_trips() {
    let mut tree = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), GuideConfig::default());
    let mut rng = TestRng::new(3);
    assert!(
        tree.sample(Vec3::ZERO, &mut rng.f32_source()).is_none(),
        "no sampling before refine"
    );
    assert_eq!(tree.pdf(Vec3::ZERO, Vec3::Z), 0.0);
    for _ in 0..5000 {
        let d = uv_to_dir(Vec2::new(0.6 + 0.3 * rng.f32(), 0.2 * rng.f32()));
        tree.record(
            &Record::radiance_only(Vec3::ZERO, d, 1.0, 1.0, 1.0),
            &mut rng.f32_source(),
        );
    }
    tree.refine(0);
    for _ in 0..2000 {
        let (d, p) = tree
            .sample(Vec3::new(0.1, 0.2, 0.3), &mut rng.f32_source())
            .unwrap();
        assert!((d.length() - 1.0).abs() < 1e-5);
        let p2 = tree.pdf(Vec3::new(0.1, 0.2, 0.3), d);
        assert!((p - p2).abs() <= 2e-3 * p, "{p} {p2} {d}");
        let uv = dir_to_uv(d);
        assert!((uv_to_dir(uv) - d).length() < 1e-4);
    }
}

/// Every node's building sums of `leaf`'s quadtree, in node order: what a record that must
/// add nothing to them is checked against.
fn building_sums(leaf: &Leaf) -> Vec<u128> {
    leaf.building
        .nodes()
        .iter()
        .flat_map(|n| n.sums.iter().map(|s| s.get()))
        .collect()
}

#[test]
fn recorder_sums_converge_to_known_radiance_integrals_and_zero_records_only_change_w() {
    use std::f64::consts::PI;
    let mut tree = cube_tree(threshold_config(1e12));
    let mut rng = TestRng::new(11);
    // L(w) = 3 max(z, 0) + 0.5 [y > 0]; sampled with p_uv(u, v) = u + 0.5.
    let l = |d: Vec3| 3.0 * (d.z as f64).max(0.0) + if d.y > 0.0 { 0.5 } else { 0.0 };
    let n = 200_000;
    let mut vals = Vec::with_capacity(n);
    for _ in 0..n {
        let r = rng.f64();
        let u = (-1.0 + (1.0 + 8.0 * r).sqrt()) * 0.5;
        let v = rng.f64();
        let d = uv_to_dir(Vec2::new(u as f32, v as f32));
        let uv = dir_to_uv(d);
        let p = (uv.x as f64 + 0.5) / (4.0 * PI);
        let rad = l(d);
        vals.push(rad / p);
        tree.record(
            &Record::radiance_only(Vec3::ZERO, d, rad as f32, p as f32, 1.0),
            &mut rng.f32_source(),
        );
    }
    // Zero and negative radiance records only add to W; NaN or infinite radiance and invalid
    // weights add nothing, and the non-finite ones are counted.
    let leaf = &tree.leaves()[0];
    let sums_before = building_sums(leaf);
    let w_before = leaf.building.weight_fixed();
    for rad in [0.0f32, -1.0, f32::NAN, f32::INFINITY] {
        tree.record(
            &Record::radiance_only(Vec3::ZERO, Vec3::Z, rad, 1.0, 1.0),
            &mut rng.f32_source(),
        );
    }
    for w in [0.0f32, -1.0, f32::NAN] {
        tree.record(
            &Record::radiance_only(Vec3::ZERO, Vec3::Z, 1.0, 1.0, w),
            &mut rng.f32_source(),
        );
    }
    tree.record(
        &Record::radiance_only(Vec3::ZERO, Vec3::Z, 1.0, 0.0, 1.0),
        &mut rng.f32_source(),
    );
    let leaf = &tree.leaves()[0];
    let sums_after = building_sums(leaf);
    assert_eq!(
        sums_before, sums_after,
        "zero / invalid radiance must not change sums"
    );
    assert_eq!(leaf.building.weight_fixed(), w_before + 2 * FIXED_ONE);
    assert_eq!(
        tree.take_nonfinite_records(),
        3,
        "NaN and inf radiance, NaN weight"
    );
    assert_eq!(tree.take_nonfinite_records(), 0, "taken");

    tree.refine(0);
    let t = tree.leaves()[0].sampling.tree();
    let w = t.weight();
    assert_eq!(w, (n + 2) as f64);
    let mean: f64 = vals.iter().sum::<f64>() / n as f64;
    let var: f64 = vals.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1) as f64;
    let se = (var / n as f64).sqrt();
    // 5 standard errors: two-sided significance ~6e-7 per check (normal approximation).
    let est = t.total() / n as f64;
    assert!(
        (est - 4.0 * PI).abs() < 5.0 * se,
        "integral {est} vs {}",
        4.0 * PI
    );
    assert!((t.mean() * 4.0 * PI * w / n as f64 - est).abs() < 1e-9);
    // Per root quadrant: q0 (z<0, y>0) = pi/2, q1 (z>0, y>0) = 2 pi, q2 = 0, q3 = 1.5 pi.
    let expect = [0.5 * PI, 2.0 * PI, 0.0, 1.5 * PI];
    for q in 0..4 {
        let s = t.nodes()[0].sums[q].get_f64() / n as f64;
        assert!(
            (s - expect[q]).abs() < 5.0 * se,
            "quadrant {q}: {s} vs {}",
            expect[q]
        );
    }
    assert_eq!(t.nodes()[0].sums[2].get(), 0);
}

#[test]
fn incident_radiance_estimate_is_flux_times_pdf_and_survives_splits_and_the_wire() {
    // Deterministic identities plus one statistical check (5 standard errors, ~6e-7).
    use std::f64::consts::PI;
    let mut tree = cube_tree(threshold_config(1e12));
    let h = LeafHandle(0);
    assert_eq!(
        tree.incident_radiance_leaf(h, 1.0),
        0.0,
        "unbuilt: no estimate"
    );
    // Uniform directions, L = 2 on the upper hemisphere (z > 0), 0 below: integral 4 pi.
    let mut rng = TestRng::new(77);
    let n = 100_000;
    let p = (1.0 / (4.0 * PI)) as f32;
    for _ in 0..n {
        let d = uv_to_dir(Vec2::new(rng.f64() as f32, rng.f64() as f32));
        let l = if d.z > 0.0 { 2.0 } else { 0.0 };
        tree.record(
            &Record::radiance_only(Vec3::ZERO, d, l, p, 1.0),
            &mut rng.f32_source(),
        );
    }
    tree.refine(0);
    let leaf = &tree.leaves()[0];
    assert_eq!(
        leaf.flux,
        (leaf.sampling.tree().total() / leaf.sampling.tree().weight()) as f32
    );
    // per-record value L / p has mean 4 pi and standard deviation 2 pi * sqrt(... ) <= 8 pi
    let se = 8.0 * PI / (n as f64).sqrt();
    assert!(
        ((leaf.flux as f64) - 4.0 * PI).abs() < 5.0 * se,
        "flux {}",
        leaf.flux
    );
    let up = Vec3::new(0.1, 0.2, 0.97).normalize();
    let pdf = tree.pdf_leaf(h, up);
    assert_eq!(tree.incident_radiance_leaf(h, pdf), leaf.flux * pdf);
    let est = tree.incident_radiance_leaf(h, pdf) as f64;
    assert!((est - 2.0).abs() < 0.2, "radiance estimate {est} vs 2");
    assert_eq!(tree.incident_radiance_leaf(h, tree.pdf_leaf(h, -up)), 0.0);
    // Splitting halves the sampling weight but children keep the parent's flux.
    let flux = leaf.flux;
    let mut split = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), threshold_config(10.0));
    for _ in 0..2000 {
        let pos = Vec3::new(rng.f64() as f32, rng.f64() as f32, rng.f64() as f32) * 2.0 - 1.0;
        split.record(
            &Record::radiance_only(pos, Vec3::Z, 3.0, p, 1.0),
            &mut rng.f32_source(),
        );
    }
    split.refine(0);
    assert!(split.leaves().len() > 1);
    let fl: Vec<f32> = split.leaves().iter().map(|l| l.flux).collect();
    assert!(fl.iter().all(|&f| f == fl[0] && f > 0.0), "{fl:?}");
    let back = SdTree::decode(&split.encode()).unwrap();
    assert_eq!(back, split, "flux travels through the wire format");
    assert_eq!(tree.leaves()[0].flux, flux);
}

#[test]
fn quadtree_node_cap_bounds_refinement_and_changes_nothing_when_not_reached() {
    let base = GuideConfig {
        s_tree_threshold: 50.0,
        d_tree_threshold: 1e-5,
        ..GuideConfig::default()
    };
    let free = warmed_tree(base.clone(), 7, 1500, 3);
    assert_eq!(free.raised_d_tree_threshold(), None);
    let used = free.stats().building_dtree_nodes;
    // A cap above what refinement makes changes no bit.
    let roomy = warmed_tree(
        GuideConfig {
            max_dtree_nodes: Some(used),
            ..base.clone()
        },
        7,
        1500,
        3,
    );
    assert_eq!(roomy.raised_d_tree_threshold(), None);
    assert_eq!(roomy.encode(), free.encode());
    // A cap below it is kept, with a raised threshold.
    let cap = used / 4;
    let tight = warmed_tree(
        GuideConfig {
            max_dtree_nodes: Some(cap),
            ..base
        },
        7,
        1500,
        3,
    );
    let raised = tight
        .raised_d_tree_threshold()
        .expect("the cap was reached");
    assert!(raised > 1e-5, "{raised}");
    let n = tight.stats().building_dtree_nodes;
    assert!(n <= cap, "{n} nodes over the cap of {cap}");
    assert!(
        n > cap / 2,
        "{n} nodes: the bisection should come close to the cap of {cap}"
    );
}

#[test]
fn stree_splits_until_every_leaf_is_at_most_the_threshold() {
    let cfg = threshold_config(300.0);
    let mut t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg.clone());
    let mut rng = TestRng::new(21);
    let recs = clustered_records(&mut rng, 20_000);
    for r in &recs {
        t.record(r, &mut rng.f32_source());
    }
    t.refine(0);
    let thr = cfg.split_threshold(1);
    let st = t.stree();
    // subtree weights (sampling W keeps the W used in the split decisions)
    fn sub_w(t: &SdTree, n: u32) -> f64 {
        let node = &t.stree().nodes()[n as usize];
        if node.is_leaf() {
            t.leaves()[node.leaf as usize].sampling.tree().weight()
        } else {
            sub_w(t, node.children[0]) + sub_w(t, node.children[1])
        }
    }
    let total_w: f64 = recs.iter().map(|r| r.weight as f64).sum();
    assert!((sub_w(&t, 0) - total_w).abs() < 1e-6);
    let mut inner = 0;
    for (i, n) in st.nodes().iter().enumerate() {
        if n.is_leaf() {
            assert!(t.leaves()[n.leaf as usize].sampling.tree().weight() <= thr);
        } else {
            assert!(
                sub_w(&t, i as u32) > thr,
                "node {i} split below the threshold"
            );
            inner += 1;
        }
    }
    assert!(inner > 3);
    // Memory cap stops refinement.
    let capped = GuideConfig {
        max_nodes: Some(5),
        ..cfg
    };
    let mut t2 = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), capped);
    for r in &recs {
        t2.record(r, &mut rng.f32_source());
    }
    t2.refine(0);
    assert!(t2.stats().spatial_nodes <= 5);
    assert_eq!(t2.stats().leaves, 3);
    // a zero threshold does not split without bound (floor of one record weight)
    let zero = threshold_config(0.0);
    let mut t3 = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), zero);
    for r in recs.iter().take(50) {
        t3.record(r, &mut rng.f32_source());
    }
    t3.refine(0);
    assert!(t3.stats().leaves <= 100, "{}", t3.stats().leaves);
}

#[test]
fn stree_children_inherit_the_whole_payload() {
    let mut t = cube_tree(learned_config(1000.0, FractionLoss::Kl));
    let mut rng = TestRng::new(4);
    for r in clustered_records(&mut rng, 3000) {
        t.record(&r, &mut rng.f32_source());
    }
    t.leaves[0].fraction.theta = 0.75;
    t.leaves[0].fraction.m = 0.125;
    t.leaves[0].set_theta_cache();
    let mut expected = t.leaves[0].building.clone();
    expected.build();
    let pending = t.leaves[0].grad.clone();
    assert!(pending.pos.iter().any(|a| a.get() > 0) && pending.neg.iter().any(|a| a.get() > 0));
    assert!(pending.weight.get() > 0);
    t.refine(0);
    // the pending fraction batch was measured against the replaced sampling tree: cleared
    for l in t.leaves() {
        assert!(l.grad.is_zero() && l.grad.stepped.get() == 0);
    }
    assert!(t.leaves().len() >= 2);
    for l in t.leaves() {
        assert_eq!(
            l.sampling.tree().nodes(),
            expected.nodes(),
            "sampling tree not inherited"
        );
        assert_eq!(l.fraction.theta, 0.75);
        assert_eq!(l.fraction.m, 0.125);
        let mut reset = expected.clone();
        reset.reset(0.01, MAX_DEPTH);
        assert_eq!(
            l.building, reset,
            "building tree not reset from the inherited tree"
        );
    }
    let ws: f64 = t.leaves().iter().map(|l| l.sampling.tree().weight()).sum();
    assert!((ws - expected.weight()).abs() < 1e-9);
}

#[test]
fn sample_and_pdf_read_only_the_frozen_sampling_tree() {
    let mut t = warmed_tree(GuideConfig::default(), 8, 3000, 1);
    let dirs: Vec<Vec3> = (0..64)
        .map(|i| {
            uv_to_dir(Vec2::new(
                (i % 8) as f32 / 8.0 + 0.01,
                (i / 8) as f32 / 8.0 + 0.01,
            ))
        })
        .collect();
    let before: Vec<f32> = dirs.iter().map(|&d| t.pdf(Vec3::ZERO, d)).collect();
    let mut rng = TestRng::new(1);
    let s_before = t.sample(Vec3::ZERO, &mut TestRng::new(2).f32_source());
    for _ in 0..5000 {
        let r = Record::radiance_only(Vec3::ZERO, Vec3::Z, 100.0, 0.1, 1.0);
        t.record(&r, &mut rng.f32_source());
    }
    let after: Vec<f32> = dirs.iter().map(|&d| t.pdf(Vec3::ZERO, d)).collect();
    assert_eq!(before, after);
    assert_eq!(
        s_before,
        t.sample(Vec3::ZERO, &mut TestRng::new(2).f32_source())
    );
    let h = t.leaf_index(Vec3::ZERO);
    assert_eq!(t.pdf_leaf(h, dirs[3]), after[3]);
    // and the next refinement does pick the new records up
    t.refine(1);
    let l = t.leaf_index(Vec3::ZERO);
    assert!(t.pdf_leaf(l, Vec3::Z) > after.iter().cloned().fold(0.0, f32::max));
}

#[test]
fn fixed_fraction_and_clamped_learned_fraction() {
    let t = SdTree::new(Vec3::ZERO, Vec3::ONE, GuideConfig::default());
    assert_eq!(t.bsdf_sampling_fraction(Vec3::ZERO), 0.5);
    let mut l = SdTree::new(Vec3::ZERO, Vec3::ONE, config_2019());
    assert_eq!(l.bsdf_sampling_fraction(Vec3::ZERO), 0.5);
    l.leaves[0].fraction.theta = 20.0;
    l.leaves[0].set_theta_cache();
    assert_eq!(l.bsdf_sampling_fraction(Vec3::ZERO), 0.95);
    l.leaves[0].fraction.theta = -20.0;
    l.leaves[0].set_theta_cache();
    assert_eq!(l.bsdf_sampling_fraction(Vec3::ZERO), 0.05);
    // theta stays within [-20, 20] under huge gradients
    let mut f = crate::fraction::FractionState {
        theta: 19.999,
        ..Default::default()
    };
    for _ in 0..100 {
        f.adam_step(-1e30, &AdamConfig::default());
    }
    assert!(f.theta <= 20.0);
    let c = config_2019();
    assert_eq!(c.s_tree_threshold, 4000.0);
    assert_eq!(c.spp_per_pass, 1);
    assert_eq!(c.spatial_filter, SpatialFilter::Stochastic);
    assert_eq!(c.directional_filter, DirectionalFilter::Box);
}

#[test]
fn recording_from_one_or_two_threads_gives_bit_identical_trees() {
    let cfg = GuideConfig {
        s_tree_threshold: 300.0,
        carry_over: 0.5,
        ..config_2019()
    };
    let base = warmed_tree(cfg, 51, 4000, 2);
    let recs = det_records(30_000, 52);
    let mut one = base.clone();
    record_all(&one, &recs);
    let mut two = base.clone();
    std::thread::scope(|s| {
        let t = &two;
        let odd: Vec<_> = recs.iter().skip(1).step_by(2).rev().cloned().collect();
        let even: Vec<_> = recs.iter().step_by(2).cloned().collect();
        s.spawn(move || record_all(t, &odd));
        s.spawn(move || record_all(t, &even));
    });
    assert!(one.leaves().iter().any(|l| !l.grad.is_zero()));
    assert_eq!(one.encode(), two.encode());
    one.step_fractions();
    two.step_fractions();
    one.refine(2);
    two.refine(2);
    assert_eq!(one.encode(), two.encode());
    assert!(one == two);
}

#[test]
fn stats_report_sizes_and_depth_histogram() {
    let t = warmed_tree(threshold_config(200.0), 81, 4000, 2);
    let s = t.stats();
    assert_eq!(s.leaves, t.leaves().len());
    assert_eq!(s.depth_histogram.iter().sum::<usize>(), s.leaves);
    assert_eq!(s.spatial_nodes, 2 * s.leaves - 1);
    assert!(s.memory_bytes > s.sampling_dtree_nodes * 64);
    assert_eq!(s.overflow_events, 0);
    assert!(s.max_dtree_depth >= 2);
}
