//! Tests of the quadtree in both states: recording, building and refining a [`DTree`], and
//! sampling and evaluating the density of a [`SamplingDTree`] (also restricted to cells).
//!
//! Statistical tests use fixed seeds and state their significance level.

use super::*;
use crate::mapping::{uv_to_dir, JACOBIAN};
use crate::region::{CellMask, CellWeights, Restriction};
use crate::stats::to_fixed;
use crate::test_support::{random_dtree, random_unit, TestRng, TreeKind};
use glam::Vec3;
use pathfarm_testkit::{pooled_chi2_pvalue as chi2_test, sidak};

/// Exact probability mass of the tree's distribution inside each cell of a `nu x nv` grid in
/// (u, v), and inside each (theta, phi) bin on the sphere (`nt` equal-angle theta bins over
/// u = (cos theta + 1) / 2, `np` phi bins).
fn bin_masses(t: &SamplingDTree, u_edges: &[f64], nv: usize) -> Vec<f64> {
    let nu = u_edges.len() - 1;
    let mut m = vec![0.0; nu * nv];
    for c in t.tree().leaf_cells() {
        let p = t.cell_pdf(&c);
        if p == 0.0 {
            continue;
        }
        let (u0, u1) = (c.origin[0], c.origin[0] + c.size);
        let (v0, v1) = (c.origin[1], c.origin[1] + c.size);
        for i in 0..nu {
            let ou = (u1.min(u_edges[i + 1]) - u0.max(u_edges[i])).max(0.0);
            if ou == 0.0 {
                continue;
            }
            let j0 = ((v0 * nv as f64).floor() as usize).min(nv - 1);
            let j1 = ((v1 * nv as f64).ceil() as usize).min(nv);
            for j in j0..j1 {
                let (b0, b1) = (j as f64 / nv as f64, (j + 1) as f64 / nv as f64);
                let ovv = (v1.min(b1) - v0.max(b0)).max(0.0);
                m[i * nv + j] += p * ou * ovv;
            }
        }
    }
    m
}

fn bin_index(edges: &[f64], x: f64) -> usize {
    let n = edges.len() - 1;
    let mut i = edges.partition_point(|&e| e <= x);
    i = i.saturating_sub(1);
    i.min(n - 1)
}

#[test]
fn quadtree_sampling_matches_pdf_chi_square_on_random_trees() {
    // Overall significance 0.01 over all (tree, binning) pairs, Šidák corrected.
    let kinds = [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect];
    let trees: Vec<(u64, TreeKind)> = (0..12u64)
        .map(|i| (1000 + i, kinds[i as usize % 3]))
        .collect();
    let m = trees.len() * 2;
    let level = sidak(0.01, m);
    let n_samples = 60_000;
    let mut max_depth_seen = 0;
    let mut saw_zero_cell = false;
    for &(seed, kind) in &trees {
        let t = random_dtree(seed, kind).freeze();
        max_depth_seen = max_depth_seen.max(t.tree().depth());
        saw_zero_cell |= t.tree().leaf_cells().iter().any(|c| t.cell_pdf(c) == 0.0);
        // (u, v) grid
        let nu = 24;
        let nv = 24;
        let u_edges: Vec<f64> = (0..=nu).map(|i| i as f64 / nu as f64).collect();
        // sphere grid: equal-angle theta bins, theta measured from +z
        let nt = 12;
        let t_edges: Vec<f64> = (0..=nt)
            .map(|i| {
                let th = std::f64::consts::PI * (nt - i) as f64 / nt as f64;
                ((th.cos() + 1.0) * 0.5).clamp(0.0, 1.0)
            })
            .collect();
        let exp_uv: Vec<f64> = bin_masses(&t, &u_edges, nv)
            .iter()
            .map(|m| m * n_samples as f64)
            .collect();
        let exp_sp: Vec<f64> = bin_masses(&t, &t_edges, nv)
            .iter()
            .map(|m| m * n_samples as f64)
            .collect();
        let total: f64 = exp_uv.iter().sum();
        assert!(
            (total - n_samples as f64).abs() < 1e-6 * n_samples as f64,
            "mass {total}"
        );
        let mut obs_uv = vec![0.0; nu * nv];
        let mut obs_sp = vec![0.0; nt * nv];
        let mut rng = TestRng::new(seed ^ 0xABCD);
        for _ in 0..n_samples {
            let (uv, pdf) = t.sample_with_pdf(&mut rng.f32_source());
            assert!(pdf > 0.0, "sampled a zero-pdf point");
            let p2 = t.pdf(uv);
            assert!(
                (pdf - p2).abs() <= 1e-4 * pdf,
                "sample pdf {pdf} vs pdf {p2}"
            );
            let iu = bin_index(&u_edges, uv.x as f64);
            let iv = ((uv.y as f64 * nv as f64) as usize).min(nv - 1);
            obs_uv[iu * nv + iv] += 1.0;
            // sphere binning from the world direction
            let d = uv_to_dir(uv);
            let theta = (d.z as f64).clamp(-1.0, 1.0).acos();
            let it = ((theta / std::f64::consts::PI * nt as f64) as usize).min(nt - 1);
            let mut phi = (d.y as f64).atan2(d.x as f64);
            if phi < 0.0 {
                phi += 2.0 * std::f64::consts::PI;
            }
            let ip = ((phi / (2.0 * std::f64::consts::PI) * nv as f64) as usize).min(nv - 1);
            // sphere bins are indexed from u = 0 (theta = pi) upwards
            obs_sp[(nt - 1 - it) * nv + ip] += 1.0;
        }
        let p_uv = chi2_test(&obs_uv, &exp_uv);
        assert!(
            p_uv > level,
            "tree {seed} {kind:?}: uv chi2 p = {p_uv:e} (level {level:e})"
        );
        // For directions exactly on a theta-bin border, float rounding may move the bin; the
        // expected masses treat bins as half-open in u, which is measure-zero different.
        let p_sp = chi2_test(&obs_sp, &exp_sp);
        assert!(
            p_sp > level,
            "tree {seed} {kind:?}: sphere chi2 p = {p_sp:e} (level {level:e})"
        );
    }
    assert_eq!(
        max_depth_seen, MAX_DEPTH,
        "random trees must reach depth 20"
    );
    assert!(saw_zero_cell, "random trees must contain zero-energy cells");
}

#[test]
fn chi_square_detects_a_wrong_sampler() {
    // Power check of the harness: sampling a tree but binning against a different tree's pdf
    // must be rejected.
    let t = random_dtree(77, TreeKind::Blobs).freeze();
    let other = random_dtree(78, TreeKind::Blobs).freeze();
    let nv = 16;
    let u_edges: Vec<f64> = (0..=16).map(|i| i as f64 / 16.0).collect();
    let n = 20_000;
    let exp: Vec<f64> = bin_masses(&other, &u_edges, nv)
        .iter()
        .map(|m| m * n as f64)
        .collect();
    let mut obs = vec![0.0; 16 * nv];
    let mut rng = TestRng::new(5);
    for _ in 0..n {
        let uv = t.sample(&mut rng.f32_source());
        obs[bin_index(&u_edges, uv.x as f64) * nv + ((uv.y * nv as f32) as usize).min(nv - 1)] +=
            1.0;
    }
    assert!(chi2_test(&obs, &exp) < 1e-6);
}

#[test]
fn quadtree_pdf_integrates_to_one_in_uv_and_on_the_sphere() {
    let kinds = [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect];
    for i in 0..9u64 {
        let t = random_dtree(200 + i, kinds[i as usize % 3]).freeze();
        let mut s_uv = 0.0;
        let mut s_sphere = 0.0;
        for c in t.tree().leaf_cells() {
            let p = t.cell_pdf(&c);
            s_uv += p * c.size * c.size;
            s_sphere += (p / JACOBIAN as f64) * (JACOBIAN as f64) * c.size * c.size;
        }
        assert!((s_uv - 1.0).abs() < 1e-5, "uv integral {s_uv}");
        assert!((s_sphere - 1.0).abs() < 1e-5);
    }
    let empty = DTree::new().freeze();
    assert_eq!(empty.pdf(Vec2::new(0.3, 0.7)), 1.0);
    let mut rng = TestRng::new(1);
    let (uv, p) = empty.sample_with_pdf(&mut rng.f32_source());
    assert!(p == 1.0 && uv.x >= 0.0 && uv.x < 1.0 && uv.y >= 0.0 && uv.y < 1.0);
}

/// Mass of the old tree inside the cell (origin, size), assuming uniform density in old leaves.
fn old_mass(t: &DTree, origin: [f64; 2], size: f64) -> f64 {
    let mut node = 0usize;
    let mut o = [0.0f64; 2];
    let mut s = 1.0f64;
    loop {
        let h = s * 0.5;
        let q = ((origin[0] >= o[0] + h) as usize) | (((origin[1] >= o[1] + h) as usize) << 1);
        let qo = [
            o[0] + if q & 1 != 0 { h } else { 0.0 },
            o[1] + if q & 2 != 0 { h } else { 0.0 },
        ];
        let c = t.nodes()[node].children[q];
        let sum = t.nodes()[node].sums[q].get_f64();
        if size >= h || c == 0 {
            return sum * (size / h) * (size / h);
        }
        node = c as usize;
        o = qo;
        s = h;
    }
}

#[test]
fn reset_refines_exactly_where_energy_fraction_exceeds_rho() {
    let kinds = [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect];
    for i in 0..9u64 {
        let old = random_dtree(300 + i, kinds[i as usize % 3]);
        let total = old.total();
        for rho in [0.01, 0.05] {
            let mut t = old.clone();
            t.reset(rho, MAX_DEPTH);
            assert!(t.depth() <= MAX_DEPTH);
            assert_eq!(t.weight_fixed(), 0);
            let mut stack = vec![(0usize, [0.0f64; 2], 1.0f64, 1u32)];
            let mut checked = 0;
            while let Some((n, o, s, d)) = stack.pop() {
                for q in 0..4 {
                    let h = s * 0.5;
                    let qo = [
                        o[0] + if q & 1 != 0 { h } else { 0.0 },
                        o[1] + if q & 2 != 0 { h } else { 0.0 },
                    ];
                    let f = old_mass(&old, qo, h) / total;
                    let c = t.nodes()[n].children[q];
                    assert_eq!(
                        c != 0,
                        f > rho && d < MAX_DEPTH,
                        "cell {qo:?} size {h} f {f} depth {d}"
                    );
                    assert_eq!(t.nodes()[n].sums[q].get(), 0);
                    checked += 1;
                    if c != 0 {
                        stack.push((c as usize, qo, h, d + 1));
                    }
                }
            }
            assert!(checked > 4);
        }
    }
    // An empty tree resets to the uniform depth-4 tree.
    let mut e = random_dtree(1, TreeKind::Blobs);
    e.clear_stats();
    e.reset(0.01, MAX_DEPTH);
    assert_eq!(e.leaf_count(), 256);
    assert_eq!(e.node_count(), 85);
    assert_eq!(e.depth(), 4);
}

#[test]
fn refined_node_count_equals_the_refined_trees_node_count_and_stops_at_its_limit() {
    let kinds = [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect];
    for i in 0..9u64 {
        let t = random_dtree(400 + i, kinds[i as usize % 3]);
        for rho in [0.2, 0.01, 1e-3, 1e-5] {
            let n = t.refined(rho, MAX_DEPTH).node_count();
            assert_eq!(
                t.refined_node_count(rho, MAX_DEPTH, usize::MAX),
                n,
                "rho {rho}"
            );
            assert_eq!(t.refined_node_count(rho, MAX_DEPTH, n), n);
            assert_eq!(t.refined_node_count(rho, MAX_DEPTH, n - 1), n);
            assert_eq!(t.refined_node_count(rho, MAX_DEPTH, n - 2), n - 1);
        }
        // rho = 0 would refine every seeded cell to depth 20 (4^19 nodes): the count stops.
        assert_eq!(t.refined_node_count(0.0, MAX_DEPTH, 100_000), 100_001);
    }
}

#[test]
fn build_makes_every_parent_sum_equal_the_sum_of_its_children() {
    for i in 0..6u64 {
        let t = random_dtree(400 + i, [TreeKind::Blobs, TreeKind::Peak][i as usize % 2]);
        let mut inner = 0;
        for n in t.nodes() {
            for q in 0..4 {
                let c = n.children[q];
                if c != 0 {
                    assert_eq!(n.sums[q].get(), t.nodes()[c as usize].total());
                    inner += 1;
                }
            }
        }
        assert!(inner > 0);
        let leaf_total: u128 = t
            .leaf_cells()
            .iter()
            .map(|c| t.nodes()[c.node as usize].sums[c.quadrant as usize].get())
            .sum();
        assert_eq!(leaf_total, t.total_fixed());
    }
}

#[test]
fn directional_box_splat_wraps_across_the_phi_seam() {
    let ov = AtomicU64::new(0);
    let t = DTree::uniform(4);
    // cell size 1/16 centred on v = 0.001: most of the square lies beyond the seam
    t.splat_box(Vec2::new(0.5, 0.001), 1.0 / 16.0, 1_000_000, &ov);
    let mut low = 0u128;
    let mut high = 0u128;
    for c in t.leaf_cells() {
        let s = t.nodes()[c.node as usize].sums[c.quadrant as usize].get();
        if c.origin[1] < 0.5 {
            low += s;
        } else {
            high += s;
        }
    }
    assert_eq!(low + high, 1_000_000);
    let frac = high as f64 / 1e6;
    assert!((frac - (0.03125 - 0.001) / 0.0625).abs() < 1e-4, "{frac}");
}

#[test]
fn frozen_sampling_cache_gives_bit_identical_samples_and_pdfs() {
    for i in 0..4u64 {
        let t = random_dtree(500 + i, [TreeKind::Blobs, TreeKind::Peak][i as usize % 2]);
        // The factors in node order, each node's computed from its sums: the frozen tree's
        // block layout must sample and evaluate exactly as they do.
        let plain = SamplingDTree::in_node_order(t.clone());
        let f = t.clone().freeze();
        assert_eq!(
            plain.cell_masses().map(f32::to_bits),
            f.cell_masses().map(f32::to_bits)
        );
        let (mut r1, mut r2) = (TestRng::new(i), TestRng::new(i));
        for _ in 0..2000 {
            let a = plain.sample_with_pdf(&mut r1.f32_source());
            let b = f.sample_with_pdf(&mut r2.f32_source());
            assert_eq!(
                a.0.to_array().map(f32::to_bits),
                b.0.to_array().map(f32::to_bits)
            );
            assert_eq!(a.1.to_bits(), b.1.to_bits());
            assert_eq!(plain.pdf(a.0).to_bits(), f.pdf(a.0).to_bits());
        }
        // Block layout: every block's first node (the root, and each grandchild of a block's
        // first node) has its inner children right after it, in quadrant order, and every
        // node of the tree is in the cache once.
        let kids = |i: usize| f.cache_children(i).into_iter().filter(|&c| c != 0);
        let (mut roots, mut seen) = (vec![0usize], vec![false; t.node_count()]);
        seen[0] = true;
        let mut blocks = 0;
        while let Some(r) = roots.pop() {
            blocks += 1;
            for (j, c) in kids(r).enumerate() {
                assert_eq!(c as usize, r + 1 + j, "child {j} of block root {r}");
                assert!(!std::mem::replace(&mut seen[c as usize], true));
                for g in kids(c as usize) {
                    assert!(!std::mem::replace(&mut seen[g as usize], true));
                    roots.push(g as usize);
                }
            }
        }
        assert!(seen.iter().all(|&s| s), "the cache holds every node");
        assert!(blocks >= 3, "the tree spans several blocks ({blocks})");
    }
}

#[test]
fn leaf_slot_finds_the_same_cell_as_leaf_cell() {
    // Deterministic identity (no significance level): the cell recording deposits into and the
    // cell with its geometry agree on every point, including cell borders and the square's
    // edges.
    for (i, kind) in [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect]
        .into_iter()
        .enumerate()
    {
        let t = random_dtree(900 + i as u64, kind);
        let mut r = TestRng::new(i as u64);
        let mut points: Vec<Vec2> = (0..5000).map(|_| Vec2::new(r.f32(), r.f32())).collect();
        for c in t.leaf_cells() {
            let (o, s) = (c.origin, c.size);
            points.push(Vec2::new(o[0] as f32, o[1] as f32));
            points.push(Vec2::new((o[0] + s) as f32, (o[1] + 0.5 * s) as f32));
        }
        points.extend([
            Vec2::ZERO,
            Vec2::ONE,
            Vec2::new(1.0, 0.0),
            Vec2::new(-0.5, 2.0),
        ]);
        for uv in points {
            let c = t.leaf_cell(uv);
            assert_eq!(t.leaf_slot(uv), (c.node, c.quadrant as usize), "{uv:?}");
        }
    }
}

#[test]
fn restricted_sampling_matches_the_restricted_pdf_chi_square() {
    // Overall significance 0.01 over all (tree, mask or weighted mask) pairs, Šidák corrected.
    // Bins: the 16x16 grid over (u, v), which nests in the 4x4 cells of a mask.
    let kinds = [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect];
    let mut rng = TestRng::new(43);
    let mut cases = Vec::new();
    for i in 0..9u64 {
        let t = random_dtree(300 + i, kinds[i as usize % 3]).freeze();
        cases.push((
            t.clone(),
            CellMask::hemisphere(random_unit(&mut rng)).into(),
        ));
        cases.push((t.clone(), CellMask(rng.next_u32() as u16 | 1).into()));
        cases.push((t.clone(), CellWeights::cosine(random_unit(&mut rng))));
        // any mask with any positive weights (spanning three decades)
        let mut weight = [1.0f32; 16];
        for w in &mut weight {
            *w = 10f32.powf(3.0 * rng.f32() - 2.0);
        }
        let mask = CellMask(rng.next_u32() as u16 | 1);
        cases.push((t, CellWeights { mask, weight }));
    }
    cases.push((DTree::new().freeze(), CellMask::hemisphere(Vec3::Y).into()));
    cases.push((DTree::new().freeze(), CellWeights::cosine(Vec3::Y)));
    let level = sidak(0.01, cases.len());
    let n = 40_000;
    let edges: Vec<f64> = (0..=16).map(|i| i as f64 / 16.0).collect();
    let mut restricted = 0;
    for (k, (t, region)) in cases.into_iter().enumerate() {
        let r = t.restrict(region);
        let mut exp = bin_masses(&t, &edges, 16);
        for (b, e) in exp.iter_mut().enumerate() {
            let uv = Vec2::new((b / 16) as f32 / 16.0 + 0.01, (b % 16) as f32 / 16.0 + 0.01);
            if r.mask.contains_uv(uv) {
                *e *= r.weight[CellMask::cell_of(uv) as usize] as f64;
            } else {
                *e = 0.0;
            }
        }
        let mass: f64 = exp.iter().sum();
        assert!(
            (r.mass as f64 - mass).abs() <= 1e-5 * mass.max(1.0),
            "case {k}: mass {} vs exact {mass}",
            r.mass
        );
        restricted += (r.mask != CellMask::ALL) as u32;
        let mut obs = vec![0.0; 256];
        let mut g = TestRng::new(k as u64);
        for _ in 0..n {
            let (uv, p) = t.sample_restricted(r, &mut g.f32_source());
            assert!(p > 0.0 && r.mask.contains_uv(uv), "case {k}: {uv} pdf {p}");
            assert_eq!(
                p.to_bits(),
                t.pdf_restricted(r, uv).to_bits(),
                "case {k}: sampled pdf vs pdf"
            );
            obs[bin_index(&edges, uv.x as f64) * 16 + ((uv.y * 16.0) as usize).min(15)] += 1.0;
        }
        let exp: Vec<f64> = exp.iter().map(|e| e / mass * n as f64).collect();
        let p = chi2_test(&obs, &exp);
        assert!(p > level, "case {k}: chi2 p = {p:e} (level {level:e})");
    }
    assert!(restricted >= 30, "most cases must restrict ({restricted})");
}

#[test]
fn restricted_pdf_integrates_to_one_and_vanishes_outside_the_mask() {
    // Deterministic quadrature (exact for piecewise-constant densities; no significance level).
    // Plain and cosine-weighted hemispheres.
    let kinds = [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect];
    let mut rng = TestRng::new(47);
    for i in 0..18u64 {
        let t = random_dtree(400 + i, kinds[i as usize % 3]).freeze();
        let n = random_unit(&mut rng);
        let r = if i < 9 {
            t.restrict(CellMask::hemisphere(n))
        } else {
            t.restrict(CellWeights::cosine(n))
        };
        // Leaf cells of depth >= 2 lie in one grid cell; the top levels' leaves are cut by it.
        let mut s = 0.0f64;
        for c in t.tree().leaf_cells() {
            for cell in 0..16u32 {
                let (g0, g1) = ((cell % 4) as f64 * 0.25, (cell / 4) as f64 * 0.25);
                let ou = (c.origin[0] + c.size).min(g0 + 0.25) - c.origin[0].max(g0);
                let ov = (c.origin[1] + c.size).min(g1 + 0.25) - c.origin[1].max(g1);
                if ou <= 0.0 || ov <= 0.0 {
                    continue;
                }
                let centre = Vec2::new(
                    (c.origin[0].max(g0) + ou * 0.5) as f32,
                    (c.origin[1].max(g1) + ov * 0.5) as f32,
                );
                let p = t.pdf_restricted(r, centre);
                if r.mask.0 & (1 << cell) == 0 {
                    assert_eq!(p, 0.0, "tree {i}: density outside the mask");
                }
                s += p as f64 * ou * ov;
            }
        }
        assert!((s - 1.0).abs() < 1e-4, "tree {i}: integral {s}");
    }
    // Cells without probability cannot be sampled: no restriction then.
    let ov = AtomicU64::new(0);
    let mut t = DTree::new();
    t.deposit(Vec2::new(0.9, 0.1), to_fixed(1.0).0, &ov);
    t.build();
    let t = t.freeze();
    let r = t.restrict(CellMask::hemisphere(-Vec3::Z)); // u < 0.5 only: no mass there
    assert_eq!(r, Restriction::NONE);
    assert_eq!(t.restrict(CellMask::hemisphere(Vec3::Z)).mass, 1.0);
    // The empty tree: uniform over the kept cells.
    let e = DTree::new().freeze();
    let r = e.restrict(CellMask::hemisphere(Vec3::X));
    assert_eq!(r.mass, 0.5);
    assert_eq!(e.pdf_restricted(r, Vec2::new(0.3, 0.1)), 2.0);
    assert_eq!(e.pdf_restricted(r, Vec2::new(0.3, 0.5)), 0.0);
}
