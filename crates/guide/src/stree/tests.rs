//! Tests of the spatial tree: lookups, the jump table and the box-overlap walk.

use super::*;
use crate::test_support::{threshold_config, warmed_tree, TestRng};

/// A uniform point in the domain [-1, 1]^3 grown by 0.2 on every side, so that lookups and
/// boxes also cross the domain's faces.
fn point_around_domain(rng: &mut TestRng) -> Vec3 {
    Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 2.4 - Vec3::splat(1.2)
}

#[test]
fn stree_lookup_and_extent_agree_and_faces_stay_inside() {
    let t = warmed_tree(threshold_config(100.0), 5, 6000, 2);
    assert!(t.stats().leaves > 10);
    let st = t.stree();
    let mut rng = TestRng::new(9);
    for i in 0..20_000 {
        let p = if i < 8 {
            // corners of the domain, including the max faces
            let m = st.domain_min();
            let s = st.domain_size();
            m + Vec3::new((i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32) * s
        } else if i < 2000 {
            // near the lower faces: coordinates with few leading digits
            let m = st.domain_min();
            let s = st.domain_size();
            let tiny = |u: f32| s * u * 2f32.powi(-(u * 40.0) as i32);
            m + Vec3::new(tiny(rng.f32()), tiny(rng.f32()), tiny(rng.f32()))
        } else {
            Vec3::new(
                rng.f32() * 2.4 - 1.2,
                rng.f32() * 2.4 - 1.2,
                rng.f32() * 2.4 - 1.2,
            )
        };
        let l = st.lookup(p);
        let x = st.normalise(p);
        let (o, e) = st.node_box_normalised(l.node);
        for a in 0..3 {
            assert!(
                x[a] >= o[a] && (x[a] < o[a] + e[a] || (x[a] == 1.0 && o[a] + e[a] == 1.0)),
                "point {p} box {o:?} {e:?}"
            );
            // Exactly the box of a float walk halving and adding extents.
            assert_eq!(l.extent[a], e[a] * st.domain_size(), "point {p}");
            assert_eq!(
                l.min[a],
                st.domain_min()[a] + o[a] * st.domain_size(),
                "point {p}"
            );
        }
        assert!(st.nodes()[l.node as usize].is_leaf());
        assert_eq!(st.nodes()[l.node as usize].leaf, l.leaf);
    }
    // Points exactly on split planes belong to the upper child: every leaf's lower corner
    // (and its centre) looks up that leaf.
    for (i, n) in st.nodes().iter().enumerate() {
        if n.is_leaf() {
            let (o, e) = st.node_box_normalised(i as u32);
            let o3 = Vec3::from_array(o);
            assert_eq!(
                st.lookup_normalised(o3).node,
                i as u32,
                "lower corner of leaf {i}"
            );
            let c = o3 + Vec3::from_array(e) * 0.5;
            assert_eq!(st.lookup_normalised(c).node, i as u32);
        }
    }
}

#[test]
fn stree_jump_table_finds_the_leaves_the_plain_descent_finds() {
    // Leaves above and below the jump table's depth (12 levels), points everywhere
    // (deterministic sweep, no significance level).
    let t = warmed_tree(threshold_config(20.0), 7, 20_000, 2);
    let st = t.stree();
    let plain = st.without_index();
    let depths: Vec<u32> = st
        .nodes()
        .iter()
        .filter(|n| n.is_leaf())
        .map(|n| n.depth)
        .collect();
    assert!(
        depths.iter().any(|&d| d < 12) && depths.iter().any(|&d| d > 12),
        "{depths:?}"
    );
    let mut rng = TestRng::new(11);
    let mut deep = 0;
    for i in 0..50_000 {
        let p = if i % 2 == 0 {
            point_around_domain(&mut rng)
        } else {
            // nodes' lower corners: points on split planes
            let node = (rng.f32() * st.nodes().len() as f32) as u32 % st.nodes().len() as u32;
            let (o, _) = st.node_box_normalised(node);
            st.domain_min() + Vec3::from_array(o) * st.domain_size()
        };
        let (a, b) = (st.lookup(p), plain.lookup(p));
        assert_eq!(a, b, "point {p}");
        deep += (st.nodes()[a.node as usize].depth > 12) as u32;
    }
    assert!(deep > 0);
}

/// The overlap walk as first written (from the root, a heap stack, all three overlaps at every
/// node): the reference [`crate::stree::STree::for_each_overlap`] must match bit for bit.
fn overlaps_reference(st: &crate::STree, lo: [f32; 3], hi: [f32; 3]) -> Vec<(u32, f64)> {
    let mut out = Vec::new();
    let mut stack = vec![(0u32, [0.0f64; 3], [1.0f64; 3])];
    while let Some((n, o, e)) = stack.pop() {
        let mut vol = 1.0f64;
        for a in 0..3 {
            let l = if o[a] <= 0.0 { f64::NEG_INFINITY } else { o[a] };
            let h = if o[a] + e[a] >= 1.0 {
                f64::INFINITY
            } else {
                o[a] + e[a]
            };
            vol *= ((hi[a] as f64).min(h) - (lo[a] as f64).max(l)).max(0.0);
        }
        if !(vol > 0.0) {
            continue;
        }
        let sn = &st.nodes()[n as usize];
        if sn.is_leaf() {
            out.push((sn.leaf, vol));
        } else {
            let (o2, e2) = upper_half(o, e, sn.axis as usize);
            stack.push((sn.children[1], o2, e2));
            stack.push((sn.children[0], o, e2));
        }
    }
    out
}

#[test]
fn box_overlap_walk_equals_the_walk_from_the_root_bit_for_bit() {
    let t = warmed_tree(threshold_config(50.0), 11, 8000, 3);
    assert!(t.stats().leaves > 100, "{}", t.stats().leaves);
    let st = t.stree();
    let mut rng = TestRng::new(4);
    let (mut multi, mut got) = (0, Vec::new());
    for i in 0..20_000 {
        // Boxes of a leaf's size around points in it (as the spatial box filter makes them),
        // also across the domain's faces, plus boxes of random sizes up to the whole domain.
        let p = point_around_domain(&mut rng);
        let c = st.normalise(p);
        let e = if i % 4 == 0 {
            Vec3::splat(rng.f32() * rng.f32())
        } else {
            st.lookup(p).extent / st.domain_size() * 0.5
        };
        let (lo, hi) = ((c - e).to_array(), (c + e).to_array());
        got.clear();
        st.for_each_overlap(lo, hi, |l, v| got.push((l, v)));
        let want = overlaps_reference(st, lo, hi);
        assert_eq!(got, want, "box {lo:?} {hi:?}");
        multi += (want.len() > 1) as usize;
    }
    assert!(multi > 2000, "too few boxes over several leaves: {multi}");
}
