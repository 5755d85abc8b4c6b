//! Library-level correctness tests (doc section 11, items 1-5 and 9-12, and the hemisphere
//! restriction).
//!
//! Statistical tests use fixed seeds and state their significance level; chi-square p-values
//! come from our own regularised incomplete gamma function.

use crate::config::*;
use crate::dtree::{DTree, MAX_DEPTH};
use crate::mapping::{dir_to_uv, uv_to_dir, JACOBIAN};
use crate::record::Record;
use crate::region::{CellMask, CellWeights, Restriction, HEMISPHERE_EPSILON};
use crate::schedule::*;
use crate::sdtree::{LeafHandle, SdTree};
use crate::stats::{to_fixed, FIXED_ONE};
use crate::{IterationStats, WireError};
use glam::{Vec2, Vec3};
use std::sync::atomic::AtomicU64;

// ------------------------------------------------------------------ helpers

/// Small deterministic PRNG (PCG-XSH-RR 64/32).
#[derive(Clone)]
struct Pcg(u64);
impl Pcg {
    fn new(seed: u64) -> Self {
        let mut p = Pcg(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xDA3E_39CB_94B9_5BDB);
        p.next_u32();
        p
    }
    fn next_u32(&mut self) -> u32 {
        let old = self.0;
        self.0 = old
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }
    /// Uniform in [0, 1) with 24 bits.
    fn f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }
    /// Uniform in [0, 1) with 53 bits.
    fn f64(&mut self) -> f64 {
        let a = (self.next_u32() >> 5) as u64;
        let b = (self.next_u32() >> 6) as u64;
        ((a << 26) | b) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }
    fn below(&mut self, n: u32) -> u32 {
        ((self.next_u32() as u64 * n as u64) >> 32) as u32
    }
    fn gauss(&mut self) -> f64 {
        let u1 = 1.0 - self.f64();
        let u2 = self.f64();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
    fn rng(&mut self) -> impl FnMut() -> f32 + '_ {
        move || self.f32()
    }
}

use pathfarm_testkit::{pooled_chi2_pvalue as chi2_test, sidak};

/// Kinds of random quadtrees.
#[derive(Clone, Copy, Debug)]
enum TreeKind {
    /// Several blobs of random width, including zero-energy regions.
    Blobs,
    /// One point mass refined down to depth 20, plus a weak background.
    Peak,
    /// Mass only inside a random rectangle (large zero regions).
    Rect,
}

fn random_uv(rng: &mut Pcg, kind: TreeKind, centres: &[(f64, f64, f64)], rect: [f64; 4]) -> Vec2 {
    match kind {
        TreeKind::Blobs => {
            let (cx, cy, s) = centres[rng.below(centres.len() as u32) as usize];
            let u = (cx + s * rng.gauss()).clamp(0.0, 0.999_999);
            let v = (cy + s * rng.gauss()).rem_euclid(1.0).min(0.999_999);
            Vec2::new(u as f32, v as f32)
        }
        TreeKind::Peak => Vec2::new(centres[0].0 as f32, centres[0].1 as f32),
        TreeKind::Rect => Vec2::new(
            (rect[0] + rng.f64() * (rect[2] - rect[0])) as f32,
            (rect[1] + rng.f64() * (rect[3] - rect[1])) as f32,
        ),
    }
}

/// A random built quadtree: several rounds of deposit / build / reset, then a final deposit
/// and build.
fn random_dtree(seed: u64, kind: TreeKind) -> DTree {
    let mut rng = Pcg::new(seed);
    let ov = AtomicU64::new(0);
    let nc = 1 + rng.below(4) as usize;
    let centres: Vec<(f64, f64, f64)> = (0..nc)
        .map(|_| (rng.f64(), rng.f64(), 10f64.powf(-1.0 - 4.0 * rng.f64())))
        .collect();
    let a = [rng.f64() * 0.5, rng.f64() * 0.5];
    let rect = [
        a[0],
        a[1],
        a[0] + 0.05 + rng.f64() * 0.4,
        a[1] + 0.05 + rng.f64() * 0.4,
    ];
    let mut t = DTree::new();
    let rounds = if matches!(kind, TreeKind::Peak) {
        9
    } else {
        1 + rng.below(6)
    };
    for round in 0..=rounds {
        for _ in 0..2000 {
            let uv = random_uv(&mut rng, kind, &centres, rect);
            let val = 0.1 + rng.f64() * 2.0;
            t.deposit(uv, to_fixed(val).0, &ov);
            t.add_weight(FIXED_ONE, &ov);
        }
        if round == rounds && matches!(kind, TreeKind::Peak) {
            // weak background so that the peak cell is not the only one with mass
            for _ in 0..200 {
                let uv = Vec2::new(rng.f32(), rng.f32());
                t.deposit(uv, to_fixed(0.01).0, &ov);
            }
        }
        t.build();
        if round < rounds {
            t.reset(0.01, MAX_DEPTH);
        }
    }
    t
}

/// Exact probability mass of the tree's distribution inside each cell of a `nu x nv` grid in
/// (u, v), and inside each (theta, phi) bin on the sphere (`nt` equal-angle theta bins over
/// u = (cos theta + 1) / 2, `np` phi bins).
fn bin_masses(t: &DTree, u_edges: &[f64], nv: usize) -> Vec<f64> {
    let nu = u_edges.len() - 1;
    let mut m = vec![0.0; nu * nv];
    for c in t.leaf_cells() {
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

// ------------------------------------------------------------------ 1. chi-square

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
        let t = random_dtree(seed, kind);
        max_depth_seen = max_depth_seen.max(t.depth());
        saw_zero_cell |= t.leaf_cells().iter().any(|c| t.cell_pdf(c) == 0.0);
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
        let mut rng = Pcg::new(seed ^ 0xABCD);
        for _ in 0..n_samples {
            let (uv, pdf) = t.sample_with_pdf(&mut rng.rng());
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
    let t = random_dtree(77, TreeKind::Blobs);
    let other = random_dtree(78, TreeKind::Blobs);
    let nv = 16;
    let u_edges: Vec<f64> = (0..=16).map(|i| i as f64 / 16.0).collect();
    let n = 20_000;
    let exp: Vec<f64> = bin_masses(&other, &u_edges, nv)
        .iter()
        .map(|m| m * n as f64)
        .collect();
    let mut obs = vec![0.0; 16 * nv];
    let mut rng = Pcg::new(5);
    for _ in 0..n {
        let uv = t.sample(&mut rng.rng());
        obs[bin_index(&u_edges, uv.x as f64) * nv + ((uv.y * nv as f32) as usize).min(nv - 1)] +=
            1.0;
    }
    assert!(chi2_test(&obs, &exp) < 1e-6);
}

// ------------------------------------------------------------------ 2. pdf integral, round trip

#[test]
fn quadtree_pdf_integrates_to_one_in_uv_and_on_the_sphere() {
    let kinds = [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect];
    for i in 0..9u64 {
        let t = random_dtree(200 + i, kinds[i as usize % 3]);
        let mut s_uv = 0.0;
        let mut s_sphere = 0.0;
        for c in t.leaf_cells() {
            let p = t.cell_pdf(&c);
            s_uv += p * c.size * c.size;
            s_sphere += (p / JACOBIAN as f64) * (JACOBIAN as f64) * c.size * c.size;
        }
        assert!((s_uv - 1.0).abs() < 1e-5, "uv integral {s_uv}");
        assert!((s_sphere - 1.0).abs() < 1e-5);
    }
    let empty = DTree::new();
    assert_eq!(empty.pdf(Vec2::new(0.3, 0.7)), 1.0);
    let mut rng = Pcg::new(1);
    let (uv, p) = empty.sample_with_pdf(&mut rng.rng());
    assert!(p == 1.0 && uv.x >= 0.0 && uv.x < 1.0 && uv.y >= 0.0 && uv.y < 1.0);
}

#[test]
fn sdtree_sample_returns_unit_directions_whose_pdf_round_trips() {
    let mut tree = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), GuideConfig::default());
    let mut rng = Pcg::new(3);
    assert!(
        tree.sample(Vec3::ZERO, &mut rng.rng()).is_none(),
        "no sampling before refine"
    );
    assert_eq!(tree.pdf(Vec3::ZERO, Vec3::Z), 0.0);
    for _ in 0..5000 {
        let d = uv_to_dir(Vec2::new(0.6 + 0.3 * rng.f32(), 0.2 * rng.f32()));
        tree.record(
            &Record::radiance_only(Vec3::ZERO, d, 1.0, 1.0, 1.0),
            &mut rng.rng(),
        );
    }
    tree.refine(0);
    for _ in 0..2000 {
        let (d, p) = tree
            .sample(Vec3::new(0.1, 0.2, 0.3), &mut rng.rng())
            .unwrap();
        assert!((d.length() - 1.0).abs() < 1e-5);
        let p2 = tree.pdf(Vec3::new(0.1, 0.2, 0.3), d);
        assert!((p - p2).abs() <= 2e-3 * p, "{p} {p2} {d}");
        let uv = dir_to_uv(d);
        assert!((uv_to_dir(uv) - d).length() < 1e-4);
    }
}

// ------------------------------------------------------------------ 3. recorder

#[test]
fn recorder_sums_converge_to_known_radiance_integrals_and_zero_records_only_change_w() {
    use std::f64::consts::PI;
    let cfg = GuideConfig {
        s_tree_threshold: 1e12,
        ..GuideConfig::default()
    };
    let mut tree = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg);
    let mut rng = Pcg::new(11);
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
            &mut rng.rng(),
        );
    }
    // Zero and negative radiance records only add to W; NaN or infinite radiance and invalid
    // weights add nothing, and the non-finite ones are counted.
    let leaf = &tree.leaves()[0];
    let sums_before: Vec<u128> = leaf
        .building
        .nodes()
        .iter()
        .flat_map(|n| n.sums.iter().map(|s| s.get()))
        .collect();
    let w_before = leaf.building.weight_fixed();
    for rad in [0.0f32, -1.0, f32::NAN, f32::INFINITY] {
        tree.record(
            &Record::radiance_only(Vec3::ZERO, Vec3::Z, rad, 1.0, 1.0),
            &mut rng.rng(),
        );
    }
    for w in [0.0f32, -1.0, f32::NAN] {
        tree.record(
            &Record::radiance_only(Vec3::ZERO, Vec3::Z, 1.0, 1.0, w),
            &mut rng.rng(),
        );
    }
    tree.record(
        &Record::radiance_only(Vec3::ZERO, Vec3::Z, 1.0, 0.0, 1.0),
        &mut rng.rng(),
    );
    let leaf = &tree.leaves()[0];
    let sums_after: Vec<u128> = leaf
        .building
        .nodes()
        .iter()
        .flat_map(|n| n.sums.iter().map(|s| s.get()))
        .collect();
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
    let t = &tree.leaves()[0].sampling;
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
    let cfg = GuideConfig {
        s_tree_threshold: 1e12,
        ..GuideConfig::default()
    };
    let mut tree = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg);
    let h = LeafHandle(0);
    assert_eq!(
        tree.incident_radiance_leaf(h, 1.0),
        0.0,
        "unbuilt: no estimate"
    );
    // Uniform directions, L = 2 on the upper hemisphere (z > 0), 0 below: integral 4 pi.
    let mut rng = Pcg::new(77);
    let n = 100_000;
    let p = (1.0 / (4.0 * PI)) as f32;
    for _ in 0..n {
        let d = uv_to_dir(Vec2::new(rng.f64() as f32, rng.f64() as f32));
        let l = if d.z > 0.0 { 2.0 } else { 0.0 };
        tree.record(
            &Record::radiance_only(Vec3::ZERO, d, l, p, 1.0),
            &mut rng.rng(),
        );
    }
    tree.refine(0);
    let leaf = &tree.leaves()[0];
    assert_eq!(
        leaf.flux,
        (leaf.sampling.total() / leaf.sampling.weight()) as f32
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
    let mut split = SdTree::new(
        Vec3::splat(-1.0),
        Vec3::splat(1.0),
        GuideConfig {
            s_tree_threshold: 10.0,
            ..GuideConfig::default()
        },
    );
    for _ in 0..2000 {
        let pos = Vec3::new(rng.f64() as f32, rng.f64() as f32, rng.f64() as f32) * 2.0 - 1.0;
        split.record(
            &Record::radiance_only(pos, Vec3::Z, 3.0, p, 1.0),
            &mut rng.rng(),
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

// ------------------------------------------------------------------ 4. reset invariants

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

// ------------------------------------------------------------------ 5. S-tree

fn clustered_records(rng: &mut Pcg, n: usize) -> Vec<Record> {
    (0..n)
        .map(|_| {
            let p = if rng.below(2) == 0 {
                Vec3::new(
                    -0.8 + 0.3 * rng.f32(),
                    -0.7 + 0.2 * rng.f32(),
                    0.5 + 0.4 * rng.f32(),
                )
            } else {
                Vec3::new(
                    rng.f32() * 2.0 - 1.0,
                    rng.f32() * 2.0 - 1.0,
                    rng.f32() * 2.0 - 1.0,
                )
            };
            let d = uv_to_dir(Vec2::new(rng.f32(), rng.f32()));
            let pb = 0.1 + rng.f32();
            let pg = 0.1 + rng.f32();
            Record {
                position: p,
                direction: d,
                radiance: rng.f32() * 2.0,
                pdf_mix: 0.5 * (pb + pg),
                weight: if rng.below(8) == 0 { 0.5 } else { 1.0 },
                product: rng.f32(),
                pdf_bsdf: pb,
                pdf_guide: pg,
                is_delta: rng.below(20) == 0,
            }
        })
        .collect()
}

fn warmed_tree(cfg: GuideConfig, seed: u64, n: usize, iterations: u32) -> SdTree {
    let mut t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg);
    let mut rng = Pcg::new(seed);
    for k in 0..iterations {
        for r in clustered_records(&mut rng, n) {
            t.record(&r, &mut rng.rng());
        }
        t.step_fractions();
        t.refine(k);
    }
    t
}

#[test]
fn stree_lookup_and_extent_agree_and_faces_stay_inside() {
    let cfg = GuideConfig {
        s_tree_threshold: 100.0,
        ..GuideConfig::default()
    };
    let t = warmed_tree(cfg, 5, 6000, 2);
    assert!(t.stats().leaves > 10);
    let st = t.stree();
    let mut rng = Pcg::new(9);
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
    let cfg = GuideConfig {
        s_tree_threshold: 20.0,
        ..GuideConfig::default()
    };
    let t = warmed_tree(cfg, 7, 20_000, 2);
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
    let mut rng = Pcg::new(11);
    let mut deep = 0;
    for i in 0..50_000 {
        let p = if i % 2 == 0 {
            Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 2.4 - Vec3::splat(1.2)
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

#[test]
fn stree_splits_until_every_leaf_is_at_most_the_threshold() {
    let cfg = GuideConfig {
        s_tree_threshold: 300.0,
        ..GuideConfig::default()
    };
    let mut t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg.clone());
    let mut rng = Pcg::new(21);
    let recs = clustered_records(&mut rng, 20_000);
    for r in &recs {
        t.record(r, &mut rng.rng());
    }
    t.refine(0);
    let thr = cfg.split_threshold(1);
    let st = t.stree();
    // subtree weights (sampling W keeps the W used in the split decisions)
    fn sub_w(t: &SdTree, n: u32) -> f64 {
        let node = &t.stree().nodes()[n as usize];
        if node.is_leaf() {
            t.leaves()[node.leaf as usize].sampling.weight()
        } else {
            sub_w(t, node.children[0]) + sub_w(t, node.children[1])
        }
    }
    let total_w: f64 = recs.iter().map(|r| r.weight as f64).sum();
    assert!((sub_w(&t, 0) - total_w).abs() < 1e-6);
    let mut inner = 0;
    for (i, n) in st.nodes().iter().enumerate() {
        if n.is_leaf() {
            assert!(t.leaves()[n.leaf as usize].sampling.weight() <= thr);
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
        t2.record(r, &mut rng.rng());
    }
    t2.refine(0);
    assert!(t2.stats().spatial_nodes <= 5);
    assert_eq!(t2.stats().leaves, 3);
    // a zero threshold does not split without bound (floor of one record weight)
    let zero = GuideConfig {
        s_tree_threshold: 0.0,
        ..GuideConfig::default()
    };
    let mut t3 = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), zero);
    for r in recs.iter().take(50) {
        t3.record(r, &mut rng.rng());
    }
    t3.refine(0);
    assert!(t3.stats().leaves <= 100, "{}", t3.stats().leaves);
}

#[test]
fn stree_children_inherit_the_whole_payload() {
    let cfg = GuideConfig {
        s_tree_threshold: 1000.0,
        bsdf_sampling_fraction: FractionMode::Learned {
            loss: FractionLoss::Kl,
        },
        ..GuideConfig::default()
    };
    let mut t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg);
    let mut rng = Pcg::new(4);
    for r in clustered_records(&mut rng, 3000) {
        t.record(&r, &mut rng.rng());
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
            l.sampling.nodes(),
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
    let ws: f64 = t.leaves().iter().map(|l| l.sampling.weight()).sum();
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
    let mut rng = Pcg::new(1);
    let s_before = t.sample(Vec3::ZERO, &mut Pcg::new(2).rng());
    for _ in 0..5000 {
        let r = Record::radiance_only(Vec3::ZERO, Vec3::Z, 100.0, 0.1, 1.0);
        t.record(&r, &mut rng.rng());
    }
    let after: Vec<f32> = dirs.iter().map(|&d| t.pdf(Vec3::ZERO, d)).collect();
    assert_eq!(before, after);
    assert_eq!(s_before, t.sample(Vec3::ZERO, &mut Pcg::new(2).rng()));
    let h = t.leaf_index(Vec3::ZERO);
    assert_eq!(t.pdf_leaf(h, dirs[3]), after[3]);
    // and the next refinement does pick the new records up
    t.refine(1);
    let l = t.leaf_index(Vec3::ZERO);
    assert!(t.pdf_leaf(l, Vec3::Z) > after.iter().cloned().fold(0.0, f32::max));
}

// ------------------------------------------------------------------ 9. filters

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
    let mut rng = Pcg::new(32);
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
        t.record(r, &mut rng.rng());
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
        &mut rng.rng(),
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
        let mut rng = Pcg::new(42);
        let rec = Record::radiance_only(p, Vec3::Z, 1.0, 1.0, 1.0);
        for _ in 0..m {
            a.record(&rec, &mut rng.rng());
        }
        b.record(&rec, &mut rng.rng());
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

// ------------------------------------------------------------------ 10. learned fraction

/// Expected gradient of the loss with respect to theta (including L2), by quadrature, for the
/// 1-D toy: p_bsdf = 1, p_guide = 2x, F = 0.3 + 1.4x on [0, 1].
fn toy_expected_grad(theta: f64, p: i32) -> f64 {
    let a = 1.0 / (1.0 + (-theta).exp());
    let n = 20_000;
    let mut g = 0.0;
    for i in 0..n {
        let x = (i as f64 + 0.5) / n as f64;
        let (pb, pg, f) = (1.0, 2.0 * x, 0.3 + 1.4 * x);
        let q = a * pb + (1.0 - a) * pg;
        g += -(f / q).powi(p) * (pb - pg) / n as f64;
    }
    g * a * (1.0 - a) + 0.01 * theta
}

/// The toy's optimal fraction: the root of [`toy_expected_grad`] (bisection over theta).
fn toy_optimum(p: i32) -> f64 {
    let (mut lo, mut hi) = (-5.0f64, 5.0f64);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if toy_expected_grad(mid, p) > 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    1.0 / (1.0 + (-(0.5 * (lo + hi))).exp())
}

#[test]
fn adam_fraction_converges_to_the_analytic_optimum_on_a_1d_toy() {
    for loss in [FractionLoss::Kl, FractionLoss::Var] {
        let p = loss.exponent();
        let alpha_opt = toy_optimum(p);
        // Without the L2 term the optimum is exactly 0.3 (q = F); L2 pulls it towards 0.5.
        assert!(alpha_opt > 0.3 && alpha_opt < 0.45, "optimum {alpha_opt}");
        let unreg =
            toy_expected_grad(-(1.0f64 / 0.3 - 1.0).ln(), p) - 0.01 * -(1.0f64 / 0.3 - 1.0).ln();
        assert!(
            unreg.abs() < 1e-6,
            "unregularised gradient at alpha = 0.3: {unreg}"
        );
        let cfg = GuideConfig {
            s_tree_threshold: 1e15,
            bsdf_sampling_fraction: FractionMode::Learned { loss },
            ..GuideConfig::default()
        };
        let mut t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg);
        let mut rng = Pcg::new(99);
        let steps = 1500;
        let mut tail = 0.0;
        for s in 0..steps {
            let alpha = t.bsdf_sampling_fraction(Vec3::ZERO) as f64;
            for rec in toy_records(&mut rng, alpha, 128) {
                t.record(&rec, &mut rng.rng());
            }
            assert_eq!(t.step_fractions(), 1);
            if s >= steps - 300 {
                tail += t.leaves()[0].fraction.alpha();
            }
        }
        let alpha_end = tail / 300.0;
        assert!(
            (alpha_end - alpha_opt).abs() < 0.02,
            "{loss:?}: learned {alpha_end} vs optimum {alpha_opt}"
        );
    }
}

/// The toy's records (see [`toy_expected_grad`]), sampled with fraction `alpha`.
fn toy_records(rng: &mut Pcg, alpha: f64, n: usize) -> Vec<Record> {
    (0..n)
        .map(|_| {
            let x = if rng.f64() < alpha {
                rng.f64()
            } else {
                rng.f64().sqrt()
            };
            let (pb, pg) = (1.0, 2.0 * x);
            Record {
                position: Vec3::ZERO,
                direction: Vec3::Z,
                radiance: 0.0,
                pdf_mix: (alpha * pb + (1.0 - alpha) * pg) as f32,
                weight: 1.0,
                product: (0.3 + 1.4 * x) as f32,
                pdf_bsdf: pb as f32,
                pdf_guide: pg as f32,
                is_delta: false,
            }
        })
        .collect()
}

#[test]
fn learned_fraction_reaches_its_optimum_in_a_few_passes() {
    // One step_fractions per pass, as the renderer calls it. The first version took one Adam
    // step per call, so 8 passes moved alpha by at most 8 x 0.01 in theta (alpha 0.48-0.52).
    let p = FractionLoss::Kl.exponent();
    let alpha_opt = toy_optimum(p);
    let cfg = GuideConfig {
        s_tree_threshold: 1e15,
        bsdf_sampling_fraction: FractionMode::Learned {
            loss: FractionLoss::Kl,
        },
        fraction_clamp: (0.0, 1.0),
        ..GuideConfig::default()
    };
    for seed in [5, 6, 7] {
        let mut t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg.clone());
        let mut rng = Pcg::new(seed);
        for _ in 0..8 {
            let alpha = t.bsdf_sampling_fraction(Vec3::ZERO) as f64;
            for r in toy_records(&mut rng, alpha, 2000) {
                t.record(&r, &mut rng.rng());
            }
            assert_eq!(t.step_fractions(), 1);
        }
        let alpha = t.leaves()[0].fraction.alpha();
        assert!(
            (alpha - alpha_opt).abs() < 0.03,
            "seed {seed}: alpha {alpha} after 8 passes, optimum {alpha_opt}"
        );
        // one Adam step per record: 256 per call at most
        assert_eq!(
            t.leaves()[0].fraction.t,
            8 * crate::fraction::MAX_STEPS_PER_CALL
        );
    }
}

#[test]
fn fraction_batch_holds_the_exact_gradient_at_every_grid_alpha() {
    use crate::fraction::{dloss_dalpha, interpolate, GRID, GRID_LEN};
    let cfg = GuideConfig {
        s_tree_threshold: 1e15,
        bsdf_sampling_fraction: FractionMode::Learned {
            loss: FractionLoss::Var,
        },
        ..GuideConfig::default()
    };
    let t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg);
    let mut rng = Pcg::new(17);
    // recorded with two different sampling fractions: the batch does not care
    let mut recs = toy_records(&mut rng, 0.3, 500);
    recs.extend(toy_records(&mut rng, 0.8, 500));
    for r in &recs {
        t.record(r, &mut rng.rng());
    }
    let g = &t.leaves()[0].grad;
    assert_eq!(g.weight.get(), 1000 * FIXED_ONE);
    for (k, &a) in GRID.iter().enumerate() {
        let exact: f64 = recs
            .iter()
            .map(|r| {
                dloss_dalpha(
                    a,
                    FractionLoss::Var,
                    r.product,
                    r.pdf_bsdf,
                    r.pdf_guide,
                    r.pdf_mix,
                )
                .unwrap()
            })
            .sum::<f64>()
            / 1000.0;
        let got = g.mean_at_grid(k).unwrap();
        assert!(
            (got - exact).abs() <= 1e-9 * exact.abs().max(1.0),
            "alpha {a}: {got} vs {exact}"
        );
        assert_eq!(g.mean(a), Some(got));
    }
    // interpolation: linear between grid points, constant beyond the ends
    let m: [f64; GRID_LEN] = std::array::from_fn(|k| k as f64 * k as f64);
    assert_eq!(interpolate(&m, 0.0), 0.0);
    assert_eq!(interpolate(&m, 1.0), m[GRID_LEN - 1]);
    let mid = 0.5 * (GRID[2] + GRID[3]);
    assert!((interpolate(&m, mid) - 0.5 * (m[2] + m[3])).abs() < 1e-12);
}

#[test]
fn fixed_fraction_and_clamped_learned_fraction() {
    let t = SdTree::new(Vec3::ZERO, Vec3::ONE, GuideConfig::default());
    assert_eq!(t.bsdf_sampling_fraction(Vec3::ZERO), 0.5);
    let mut l = SdTree::new(Vec3::ZERO, Vec3::ONE, GuideConfig::improvements_2019());
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
    let c = GuideConfig::improvements_2019();
    assert_eq!(c.s_tree_threshold, 4000.0);
    assert_eq!(c.spp_per_pass, 1);
    assert_eq!(c.spatial_filter, SpatialFilter::Stochastic);
    assert_eq!(c.directional_filter, DirectionalFilter::Box);
}

// ------------------------------------------------------------------ 11. schedule

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
    let mut rng = Pcg::new(7);
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
fn image_variance_estimator_is_unbiased_on_synthetic_pixels() {
    let mut rng = Pcg::new(17);
    let (npx, n, sigma) = (5000usize, 16usize, 0.7f64);
    let (mut ws, mut s1, mut s2, mut cnt) = (
        vec![0.0; npx],
        vec![0.0; npx],
        vec![0.0; npx],
        vec![0.0; npx],
    );
    for i in 0..npx {
        for _ in 0..n {
            let x = 3.0 + sigma * rng.gauss();
            ws[i] += 1.0;
            s1[i] += x;
            s2[i] += x * x;
            cnt[i] += 1.0;
        }
    }
    let v = image_variance(&ws, &s1, &s2, &cnt);
    let truth = sigma * sigma / n as f64;
    // the mean of npx unbiased per-pixel estimates has relative sd sqrt(2/(n-1)/npx) ~ 0.5%
    assert!((v / truth - 1.0).abs() < 0.03, "{v} vs {truth}");
}

// ------------------------------------------------------------------ 12. determinism, merge, wire

fn det_records(n: usize, seed: u64) -> Vec<(Record, u64)> {
    let mut rng = Pcg::new(seed);
    clustered_records(&mut rng, n)
        .into_iter()
        .enumerate()
        .map(|(i, r)| (r, seed * 1_000_003 + i as u64))
        .collect()
}

/// Records every record, and beside each a light sample at its position (one in three
/// occluded, value 0) whose value derives from the record's seed.
fn record_all(t: &SdTree, recs: &[(Record, u64)]) {
    for (r, s) in recs {
        t.record(r, &mut Pcg::new(*s).rng());
        let light = if s % 3 == 0 {
            0.0
        } else {
            (s % 997) as f32 * 0.37
        };
        t.record_light_sample(t.leaf_index(r.position), light);
    }
}

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
        let mut rng = Pcg::new(81);
        for r in clustered_records(&mut rng, 5000) {
            t.record(&r, &mut rng.rng());
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
        let cells = t.leaves()[0].sampling.leaf_cells().len() as u128;
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

#[test]
fn recording_from_one_or_two_threads_gives_bit_identical_trees() {
    let cfg = GuideConfig {
        s_tree_threshold: 300.0,
        carry_over: 0.5,
        ..GuideConfig::improvements_2019()
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
    let mut rng = Pcg::new(63);
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

#[test]
fn wire_round_trips_and_detects_corruption() {
    let cfg = GuideConfig {
        carry_over: 0.5,
        ..GuideConfig::improvements_2019()
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

    let mut rng = Pcg::new(73);
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
            let i = rng.below(c.len() as u32) as usize;
            c[i] ^= 1 << rng.below(8);
            assert!(decode(&c).is_err(), "flip at {i} undetected");
        }
        for _ in 0..50 {
            let n = rng.below(buf.len() as u32) as usize;
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

#[test]
fn frozen_sampling_cache_gives_bit_identical_samples_and_pdfs() {
    for i in 0..4u64 {
        let t = random_dtree(500 + i, [TreeKind::Blobs, TreeKind::Peak][i as usize % 2]);
        let mut f = t.clone();
        f.freeze();
        let (mut r1, mut r2) = (Pcg::new(i), Pcg::new(i));
        for _ in 0..2000 {
            let a = t.sample_with_pdf(&mut r1.rng());
            let b = f.sample_with_pdf(&mut r2.rng());
            assert_eq!(
                a.0.to_array().map(f32::to_bits),
                b.0.to_array().map(f32::to_bits)
            );
            assert_eq!(a.1.to_bits(), b.1.to_bits());
            assert_eq!(t.pdf(a.0).to_bits(), f.pdf(a.0).to_bits());
        }
        // Block layout: every block's first node (the root, and each grandchild of a block's
        // first node) has its inner children right after it, in quadrant order, and every
        // node of the tree is in the cache once.
        let kids = |i: usize| f.frozen_children(i).into_iter().filter(|&c| c != 0);
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
fn stats_report_sizes_and_depth_histogram() {
    let t = warmed_tree(
        GuideConfig {
            s_tree_threshold: 200.0,
            ..GuideConfig::default()
        },
        81,
        4000,
        2,
    );
    let s = t.stats();
    assert_eq!(s.leaves, t.leaves().len());
    assert_eq!(s.depth_histogram.iter().sum::<usize>(), s.leaves);
    assert_eq!(s.spatial_nodes, 2 * s.leaves - 1);
    assert!(s.memory_bytes > s.sampling_dtree_nodes * 64);
    assert_eq!(s.overflow_events, 0);
    assert!(s.max_dtree_depth >= 2);
}

#[test]
fn viz_rasterises_the_pdf_with_its_peak_brightest() {
    let ov = AtomicU64::new(0);
    let mut t = DTree::uniform(3); // 8 x 8 cells
    t.deposit(Vec2::new(0.3, 0.8), to_fixed(10.0).0, &ov); // cell (2, 6)
    t.deposit(Vec2::new(0.9, 0.1), to_fixed(1.0).0, &ov); // cell (7, 0)
    t.build();
    let img = crate::viz::rasterize_pdf(&t, 64, 32, false);
    assert_eq!(img.len(), 64 * 32 * 3);
    let px = |x: usize, y: usize| {
        [
            img[(y * 64 + x) * 3],
            img[(y * 64 + x) * 3 + 1],
            img[(y * 64 + x) * 3 + 2],
        ]
    };
    assert_eq!(px(20, 25), [1.0, 1.0, 1.0], "peak cell must be white");
    let dim = px(60, 2);
    assert!(
        dim.iter().sum::<f32>() > 0.0 && dim.iter().sum::<f32>() < 1.0,
        "{dim:?}"
    );
    assert_eq!(px(5, 5), [0.0, 0.0, 0.0], "zero-pdf cell must be black");
    let o = crate::viz::rasterize_pdf(&t, 64, 64, true);
    assert_eq!(
        &o[(8 * 64 + 8) * 3..(8 * 64 + 8) * 3 + 3],
        &[0.0, 1.0, 0.0],
        "cell corner outlined"
    );
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
        let mut r = Pcg::new(i as u64);
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

// ------------------------------------------------------------------ 13. hemisphere restriction

fn random_unit(rng: &mut Pcg) -> Vec3 {
    loop {
        let v = Vec3::new(rng.gauss() as f32, rng.gauss() as f32, rng.gauss() as f32);
        if v.length() > 1e-3 {
            return v.normalize();
        }
    }
}

/// Largest `n . w` over a 65x65 grid of directions covering cell `cell` (edges included).
fn scanned_max(n: Vec3, cell: u32) -> f32 {
    let (iu, iv) = ((cell % 4) as f32, (cell / 4) as f32);
    let mut m = f32::NEG_INFINITY;
    for a in 0..=64 {
        for b in 0..=64 {
            let uv = Vec2::new((iu + a as f32 / 64.0) / 4.0, (iv + b as f32 / 64.0) / 4.0);
            m = m.max(n.dot(uv_to_dir(uv)));
        }
    }
    m
}

#[test]
fn hemisphere_mask_is_exact_for_axis_normals_and_keeps_every_cell_reaching_above() {
    // Deterministic geometry (no significance level).
    for n in [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z] {
        let m = CellMask::hemisphere(n);
        assert_eq!(m.0.count_ones(), 8, "{n}: half the cells");
        for cell in 0..16u32 {
            let (iu, iv) = ((cell % 4) as f32, (cell / 4) as f32);
            let centre = uv_to_dir(Vec2::new((iu + 0.5) / 4.0, (iv + 0.5) / 4.0));
            assert_eq!(
                m.0 & (1 << cell) != 0,
                n.dot(centre) > 0.0,
                "{n} cell {cell}"
            );
        }
    }
    // Any normal: a cell is kept exactly when some direction in it lies above the surface
    // (by more than the epsilon); the scan approaches the cell's maximum from below.
    let mut rng = Pcg::new(41);
    let mut dropped = 0;
    for _ in 0..150 {
        let n = random_unit(&mut rng);
        let m = CellMask::hemisphere(n);
        assert!(m.contains_uv(dir_to_uv(n)), "{n}: its own direction");
        for cell in 0..16u32 {
            let s = scanned_max(n, cell);
            if m.0 & (1 << cell) != 0 {
                assert!(
                    s > HEMISPHERE_EPSILON - 2e-3,
                    "{n} cell {cell}: kept, max {s}"
                );
            } else {
                dropped += 1;
                assert!(
                    s <= HEMISPHERE_EPSILON + 1e-5,
                    "{n} cell {cell}: dropped, max {s}"
                );
            }
        }
    }
    // Half the sphere is below any surface, but the cells straddling the horizon are kept:
    // about 3.4 of the 16 cells are dropped per random normal (8 for axis-aligned ones).
    assert!(dropped >= 150 * 3, "only {dropped} cells dropped");
    assert_eq!(CellMask::hemisphere(Vec3::ZERO), CellMask::ALL);
    assert_eq!(CellMask::hemisphere(Vec3::NAN), CellMask::ALL);
}

/// Mean and minimum of `n . w` over a 64x64 midpoint grid of cell `cell` (the cylindrical
/// mapping preserves area, so the grid's mean is the cell's mean over solid angle).
fn scanned_mean_min(n: Vec3, cell: u32) -> (f64, f32) {
    let (iu, iv) = ((cell % 4) as f32, (cell / 4) as f32);
    let (mut s, mut lo) = (0.0f64, f32::INFINITY);
    for a in 0..64 {
        for b in 0..64 {
            let uv = Vec2::new(
                (iu + (a as f32 + 0.5) / 64.0) / 4.0,
                (iv + (b as f32 + 0.5) / 64.0) / 4.0,
            );
            let c = n.dot(uv_to_dir(uv));
            s += c as f64;
            lo = lo.min(c);
        }
    }
    (s / 4096.0, lo)
}

#[test]
fn vectorised_cell_cosines_equal_the_scalar_form_bit_for_bit() {
    // Deterministic arithmetic (no significance level): the 16-lane form must round exactly
    // as the scalar loop, or images change with the compiler's choice of code.
    let mut rng = Pcg::new(71);
    let mut normals: Vec<Vec3> = (0..20_000).map(|_| random_unit(&mut rng)).collect();
    // Axis-aligned normals and normals a rounding error off them (walls and floors), where
    // the band edges and the azimuth quarters are hit exactly.
    for a in [Vec3::X, Vec3::Y, Vec3::Z, -Vec3::X, -Vec3::Y, -Vec3::Z] {
        normals.push(a);
        for e in [1e-7f32, -1e-7, 1e-4] {
            normals.push((a + Vec3::splat(e)).normalize());
            normals.push((a + Vec3::new(e, -e, 0.5 * e)).normalize());
        }
    }
    normals.push(Vec3::new(0.5, 0.5, 0.5f32.sqrt()).normalize());
    normals.push(Vec3::new(0.0, 0.6, -0.8));
    for n in normals {
        let (v, s) = (
            crate::region::cell_max_cosines(n),
            crate::region::cell_max_cosines_scalar(n),
        );
        assert_eq!(v.map(f32::to_bits), s.map(f32::to_bits), "{n}: maxima");
        let (v, s) = (
            CellWeights::cosine(n),
            crate::region::cosine_weights_scalar(n),
        );
        assert_eq!(v.mask, s.mask, "{n}");
        assert_eq!(
            v.weight.map(f32::to_bits),
            s.weight.map(f32::to_bits),
            "{n}: weights"
        );
    }
}

#[test]
fn cosine_weights_are_the_cells_mean_cosine_and_bounded_at_the_horizon() {
    // Deterministic geometry (no significance level); tolerances cover the 64x64 quadrature.
    // A floor: the bands z in [0, 0.5) and [0.5, 1] have mean cosines 1/4 and 3/4.
    let w = CellWeights::cosine(Vec3::Z);
    assert_eq!(w.mask, CellMask::hemisphere(Vec3::Z));
    for iv in 0..4 {
        assert!((w.weight[2 + 4 * iv] - 0.25).abs() < 1e-6, "{:?}", w.weight);
        assert!((w.weight[3 + 4 * iv] - 0.75).abs() < 1e-6, "{:?}", w.weight);
    }
    let mut rng = Pcg::new(53);
    let (mut inside, mut straddling) = (0, 0);
    for _ in 0..100 {
        let n = random_unit(&mut rng);
        let w = CellWeights::cosine(n);
        assert_eq!(
            w.mask,
            CellMask::hemisphere(n),
            "{n}: the hemisphere's cells"
        );
        for cell in 0..16u32 {
            let wc = w.weight[cell as usize];
            if w.mask.0 & (1 << cell) == 0 {
                assert_eq!(wc, 1.0, "{n} cell {cell}: unused weights stay 1");
                continue;
            }
            let (mean, lo) = scanned_mean_min(n, cell);
            let max = scanned_max(n, cell);
            assert!(
                wc > 0.0 && wc <= max + 1e-5,
                "{n} cell {cell}: {wc} vs max {max}"
            );
            if lo > 0.0 {
                inside += 1;
                assert!(
                    (wc as f64 - mean).abs() < 2e-4,
                    "{n} cell {cell}: {wc} vs mean {mean}"
                );
            } else {
                straddling += 1;
                assert!(
                    wc as f64 >= mean.max(0.25 * max as f64) - 2e-3,
                    "{n} cell {cell}: {wc} vs mean {mean}, max {max}"
                );
            }
        }
    }
    assert!(inside > 200 && straddling > 200, "{inside} {straddling}");
    assert_eq!(CellWeights::cosine(Vec3::NAN), CellWeights::ALL);
    assert_eq!(CellWeights::cosine(Vec3::ZERO), CellWeights::ALL);
}

#[test]
fn cell_of_dir_agrees_with_the_mapping_away_from_quarter_edges() {
    // Deterministic (no significance level): random directions, the axes, and directions a
    // hair off the quarter edges (either cell is right there).
    let mut rng = Pcg::new(59);
    let mut dirs: Vec<Vec3> = (0..100_000).map(|_| random_unit(&mut rng)).collect();
    dirs.extend([Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z]);
    let mut near_edge = 0;
    for d in dirs {
        let want = CellMask::cell_of(dir_to_uv(d));
        let got = CellMask::cell_of_dir(d);
        if d.x.abs().min(d.y.abs()) < 1e-5 {
            near_edge += 1;
            assert_eq!(got % 4, want % 4, "{d}: the band is exact");
        } else {
            assert_eq!(got, want, "{d}");
        }
    }
    assert!(near_edge >= 6, "{near_edge}");
}

#[test]
fn restricted_sampling_matches_the_restricted_pdf_chi_square() {
    // Overall significance 0.01 over all (tree, mask or weighted mask) pairs, Šidák corrected.
    // Bins: the 16x16 grid over (u, v), which nests in the 4x4 cells of a mask.
    let kinds = [TreeKind::Blobs, TreeKind::Peak, TreeKind::Rect];
    let mut rng = Pcg::new(43);
    let mut cases = Vec::new();
    for i in 0..9u64 {
        let t = random_dtree(300 + i, kinds[i as usize % 3]);
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
    cases.push((DTree::new(), CellMask::hemisphere(Vec3::Y).into()));
    cases.push((DTree::new(), CellWeights::cosine(Vec3::Y)));
    let level = sidak(0.01, cases.len());
    let n = 40_000;
    let edges: Vec<f64> = (0..=16).map(|i| i as f64 / 16.0).collect();
    let mut restricted = 0;
    for (k, (mut t, region)) in cases.into_iter().enumerate() {
        if k % 3 == 0 {
            t.freeze(); // both the cached and the computed masses
        }
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
        let mut g = Pcg::new(k as u64);
        for _ in 0..n {
            let (uv, p) = t.sample_restricted(r, &mut g.rng());
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
    let mut rng = Pcg::new(47);
    for i in 0..18u64 {
        let t = random_dtree(400 + i, kinds[i as usize % 3]);
        let n = random_unit(&mut rng);
        let r = if i < 9 {
            t.restrict(CellMask::hemisphere(n))
        } else {
            t.restrict(CellWeights::cosine(n))
        };
        // Leaf cells of depth >= 2 lie in one grid cell; the top levels' leaves are cut by it.
        let mut s = 0.0f64;
        for c in t.leaf_cells() {
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
    let r = t.restrict(CellMask::hemisphere(-Vec3::Z)); // u < 0.5 only: no mass there
    assert_eq!(r, Restriction::NONE);
    assert_eq!(t.restrict(CellMask::hemisphere(Vec3::Z)).mass, 1.0);
    // The empty tree: uniform over the kept cells.
    let e = DTree::new();
    let r = e.restrict(CellMask::hemisphere(Vec3::X));
    assert_eq!(r.mass, 0.5);
    assert_eq!(e.pdf_restricted(r, Vec2::new(0.3, 0.1)), 2.0);
    assert_eq!(e.pdf_restricted(r, Vec2::new(0.3, 0.5)), 0.0);
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
            let a = sn.axis as usize;
            let mut e2 = e;
            e2[a] *= 0.5;
            let mut o2 = o;
            o2[a] += e2[a];
            stack.push((sn.children[1], o2, e2));
            stack.push((sn.children[0], o, e2));
        }
    }
    out
}

#[test]
fn box_overlap_walk_equals_the_walk_from_the_root_bit_for_bit() {
    let cfg = GuideConfig {
        s_tree_threshold: 50.0,
        ..GuideConfig::default()
    };
    let t = warmed_tree(cfg, 11, 8000, 3);
    assert!(t.stats().leaves > 100, "{}", t.stats().leaves);
    let st = t.stree();
    let mut rng = Pcg::new(4);
    let (mut multi, mut got) = (0, Vec::new());
    for i in 0..20_000 {
        // Boxes of a leaf's size around points in it (as the spatial box filter makes them),
        // also across the domain's faces, plus boxes of random sizes up to the whole domain.
        let p = Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 2.4 - Vec3::splat(1.2);
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

/// `split_exact` as first written (quantised weights in a Vec, 128-bit divisions).
fn split_exact_reference(q: u128, weights: &[f64]) -> Vec<u128> {
    let max = weights.iter().cloned().fold(0.0f64, f64::max);
    let mut out = vec![0u128; weights.len()];
    if !(max > 0.0) || !max.is_finite() {
        out[0] = q;
        return out;
    }
    let wi: Vec<u128> = weights
        .iter()
        .map(|&w| {
            if w > 0.0 {
                ((w / max) * 4294967295.0).round() as u128
            } else {
                0
            }
        })
        .collect();
    let t: u128 = wi.iter().sum();
    let imax = (0..wi.len()).fold(0, |m, i| if wi[i] > wi[m] { i } else { m });
    let mut acc = 0u128;
    for i in 0..wi.len() {
        out[i] = (q / t) * wi[i] + ((q % t) * wi[i]) / t;
        acc += out[i];
    }
    out[imax] += q - acc;
    out
}

#[test]
fn split_exact_equals_the_128_bit_reference_bit_for_bit() {
    let mut rng = Pcg::new(8);
    let mut out = Vec::new();
    for n in 1..24 {
        for _ in 0..300 {
            let w: Vec<f64> = (0..n)
                .map(|_| match rng.next_u32() % 4 {
                    0 => 0.0,
                    1 => rng.f32() as f64 * 1e-9,
                    _ => rng.f32() as f64,
                })
                .collect();
            let big = ((rng.next_u32() as u128) << 96) | ((rng.next_u32() as u128) << 40);
            for q in [
                0u128,
                1,
                3,
                (rng.next_u32() as u128) << 20,
                u64::MAX as u128,
                big,
            ] {
                crate::stats::split_exact(q, &w, &mut out);
                assert_eq!(out, split_exact_reference(q, &w), "q {q} weights {w:?}");
            }
        }
    }
}
