//! Tests of the binary forms: CRC-32, round trips and detection of corrupt input.

use super::*;
use crate::test_support::{
    config_2019, det_records, random_dtree, record_all, warmed_tree, TestRng, TreeKind,
};

#[test]
fn crc32_matches_the_standard_check_value() {
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    assert_eq!(crc32(b""), 0);
}

#[test]
fn wire_round_trips_and_detects_corruption() {
    let cfg = GuideConfig {
        carry_over: 0.5,
        ..config_2019()
    };
    let t = warmed_tree(cfg, 71, 3000, 2);
    assert!(t.leaves().iter().any(|l| l.prior.weight_fixed() > 0));
    let mut t2 = t.clone();
    record_all(&t2, &det_records(2000, 72));
    let bytes = t2.encode();
    let back = SdTree::decode(&bytes).unwrap();
    assert!(back == t2);
    assert_eq!(back.encode(), bytes);
    // a tree with a depth-20 quadtree survives the trip
    let mut deep = SdTree::new(Vec3::ZERO, Vec3::ONE, GuideConfig::default());
    deep.leaves[0].building = random_dtree(5, TreeKind::Peak);
    assert!(SdTree::decode(&deep.encode()).unwrap() == deep);

    let stats = t2.take_stats();
    let sbytes = stats.encode();
    assert_eq!(IterationStats::decode(&sbytes).unwrap(), stats);

    let mut rng = TestRng::new(73);
    for (buf, is_tree) in [(&bytes, true), (&sbytes, false)] {
        let decode = |b: &[u8]| -> Result<(), WireError> {
            if is_tree {
                SdTree::decode(b).map(|_| ())
            } else {
                IterationStats::decode(b).map(|_| ())
            }
        };
        for _ in 0..300 {
            let mut c = buf.clone();
            let i = rng.below(c.len() as u64) as usize;
            c[i] ^= 1 << rng.below(8);
            assert!(decode(&c).is_err(), "flip at {i} undetected");
        }
        for _ in 0..50 {
            let n = rng.below(buf.len() as u64) as usize;
            let e = decode(&buf[..n]).unwrap_err();
            assert!(
                matches!(e, WireError::Truncated | WireError::BadMagic(_)),
                "{e:?}"
            );
        }
        let mut c = buf.clone();
        c[0] = b'X';
        assert!(matches!(decode(&c), Err(WireError::BadMagic(_))));
        let mut c = buf.clone();
        c[4] = 9;
        assert!(matches!(decode(&c), Err(WireError::UnsupportedVersion(9))));
        let mut c = buf.clone();
        let mid = c.len() / 2;
        c[mid] ^= 0x10;
        assert!(matches!(
            decode(&c),
            Err(WireError::ChecksumMismatch { .. })
        ));
    }
    assert!(matches!(
        SdTree::decode(&sbytes),
        Err(WireError::BadMagic(_))
    ));
}

/// Compact integers round-trip at every byte length, and only their one canonical form
/// decodes (a high zero byte or a length over 16 is malformed): re-encoding gives the same
/// bytes.
#[test]
fn compact_integers_round_trip_and_have_one_form() {
    let values = [
        0u128,
        1,
        255,
        256,
        1 << 48,
        (1 << 64) - 1,
        1 << 64,
        u128::MAX,
    ];
    for v in values.into_iter().chain((0..128).map(|k| 1u128 << k)) {
        let mut w = W(Vec::new());
        w.cu128(v);
        assert_eq!(
            w.0.len(),
            1 + (128 - v.leading_zeros() as usize).div_ceil(8),
            "{v}"
        );
        let mut r = R { b: &w.0, p: 0 };
        assert_eq!(r.cu128(), Ok(v));
        assert_eq!(r.p, w.0.len());
    }
    let decode = |b: &[u8]| R { b, p: 0 }.cu128();
    assert_eq!(
        decode(&[2, 7, 0]),
        Err(WireError::Malformed(
            "compact integer with a high zero byte"
        ))
    );
    assert_eq!(
        decode(&[17; 18]),
        Err(WireError::Malformed("compact integer length"))
    );
    assert_eq!(decode(&[3, 1, 2]), Err(WireError::Truncated));
}

#[test]
fn a_tree_of_many_leaves_encodes_on_several_threads_to_the_bytes_of_one() {
    let cfg = GuideConfig {
        s_tree_threshold: 4.0,
        ..config_2019()
    };
    let t = warmed_tree(cfg, 81, 40_000, 2);
    assert!(
        t.leaves.len() >= 4 * LEAVES_PER_ENCODER,
        "enough leaves for several encoders: {}",
        t.leaves.len()
    );
    let mut parallel = W(Vec::new());
    put_leaves(&mut parallel, &t.leaves);
    let mut serial = W(Vec::new());
    t.leaves.iter().for_each(|l| put_leaf(&mut serial, l));
    assert!(parallel.0 == serial.0, "the leaves' bytes in order");
    let back = SdTree::decode(&t.encode()).unwrap();
    assert!(back == t);
}

/// Variable-length integers round-trip, and only their shortest form of at most 5 bytes
/// decodes; child distances survive zigzag in both directions.
#[test]
fn varints_round_trip_and_have_one_form() {
    for v in [
        0u64,
        1,
        127,
        128,
        300,
        16_383,
        16_384,
        u64::from(u32::MAX),
        (1 << 35) - 1,
    ] {
        let mut w = W(Vec::new());
        w.varint(v);
        let mut r = R { b: &w.0, p: 0 };
        assert_eq!(r.varint(), Ok(v));
        assert_eq!(r.p, w.0.len());
    }
    let decode = |b: &[u8]| R { b, p: 0 }.varint();
    assert_eq!(
        decode(&[0x81, 0x00]),
        Err(WireError::Malformed("variable-length integer not shortest"))
    );
    assert_eq!(
        decode(&[0xff; 6]),
        Err(WireError::Malformed("variable-length integer too long"))
    );
    assert_eq!(decode(&[0x80]), Err(WireError::Truncated));
    for v in [
        0i64,
        1,
        -1,
        5,
        -5,
        i64::from(u32::MAX),
        -i64::from(u32::MAX),
    ] {
        assert_eq!(unzigzag(zigzag(v)), v);
    }
}

/// A quadtree whose children are not where refinement puts them (a node's children in
/// reverse order, far from their parent) survives the trip; a child index before its
/// parent, past the end or shared is malformed, never a panic.
#[test]
fn quadtrees_of_any_layout_round_trip_and_bad_children_are_malformed() {
    let mut t = DTree::uniform(1);
    for _ in 0..8 {
        t.nodes.push(DNode::default());
    }
    t.nodes[0].children = [8, 0, 3, 1];
    t.nodes[1].children = [0, 2, 0, 0];
    t.nodes[3].children = [7, 6, 5, 4];
    t.nodes[5].sums[2] = Acc128::from_u128(12345);
    let mut w = W(Vec::new());
    put_dtree(&mut w, &t);
    let mut r = R { b: &w.0, p: 0 };
    assert_eq!(get_dtree(&mut r), Ok(t.clone()));
    assert_eq!(r.p, w.0.len());

    let bad = |children: [u32; 4]| {
        let mut u = t.clone();
        u.nodes[1].children = children;
        let mut w = W(Vec::new());
        put_dtree(&mut w, &u);
        let got = get_dtree(&mut R { b: &w.0, p: 0 });
        assert_eq!(got, Err(WireError::Malformed("quadtree child index")));
    };
    bad([0, 2, 4, 0]); // 4 is node 3's child too
    bad([0, 2, 9, 0]); // past the end
    let mut u = t.clone();
    u.nodes[4].children = [0, 0, 0, 2]; // 2 is node 1's child and before 4
    let mut w = W(Vec::new());
    put_dtree(&mut w, &u);
    assert!(get_dtree(&mut R { b: &w.0, p: 0 }).is_err());
}

/// The point of v7: a quadtree's structure costs a byte or two a node, not 17 (four `u32`
/// children and the sums' mask), and a carried prior adds only its sums.
#[test]
fn a_quadtree_without_sums_costs_under_three_bytes_a_node() {
    let t = DTree::uniform(8);
    let mut w = W(Vec::new());
    put_dtree(&mut w, &t);
    let per_node = w.0.len() as f64 / t.nodes.len() as f64;
    assert!(per_node < 3.0, "{per_node} bytes a node");

    let mut prior = t.clone();
    prior.nodes[7].sums[1] = Acc128::from_u128(99);
    let mut w = W(Vec::new());
    put_prior(&mut w, &prior, &t);
    assert_eq!(
        w.0.len(),
        1 + 2 + t.nodes.len() + 1,
        "tag, weight (none), masks, one one-byte sum"
    );
    assert_eq!(get_prior(&mut R { b: &w.0, p: 0 }, &t), Ok(prior));
    let mut w = W(Vec::new());
    put_prior(&mut w, &DTree::new(), &t);
    assert_eq!(w.0, [0]);
    assert_eq!(get_prior(&mut R { b: &w.0, p: 0 }, &t), Ok(DTree::new()));
}
