//! Numerical stability of the guide (issue 27): records carrying NaN, infinities and
//! extreme finite values, quadtrees with zero-energy cells, pdfs near zero, and directions
//! at the poles and on the phi seam of the cylindrical mapping.
//!
//! These are deterministic checks (fixed seeds, exact or rounding-level tolerances): no
//! significance level applies.

use crate::config::*;
use crate::mapping::{dir_to_uv, uv_to_dir, JACOBIAN};
use crate::record::Record;
use crate::sdtree::{LeafHandle, SdTree};
use crate::test_support::{config_2019, seam_and_poles, TestRng};
use glam::{Vec2, Vec3};

/// The configurations under test: the defaults (nearest filters, fixed fraction), the 2019
/// preset (stochastic spatial and box directional filters, learned KL fraction) and box
/// spatial filtering with the learned variance fraction.
fn configs() -> Vec<(&'static str, GuideConfig)> {
    let small = |c: GuideConfig| GuideConfig {
        s_tree_threshold: 400.0,
        ..c
    };
    vec![
        ("default", small(GuideConfig::default())),
        ("2019", small(config_2019())),
        (
            "box-var",
            small(GuideConfig {
                spatial_filter: SpatialFilter::Box,
                directional_filter: DirectionalFilter::Box,
                bsdf_sampling_fraction: FractionMode::Learned {
                    loss: FractionLoss::Var,
                },
                ..GuideConfig::default()
            }),
        ),
    ]
}

/// A valid record: a point in [-1, 1]^3, a direction mostly within a lobe around
/// (u, v) = (0.7, 0.3), radiance in [0, 2), positive pdfs.
fn good_record(rng: &mut TestRng) -> Record {
    let p = Vec3::new(rng.f32(), rng.f32(), rng.f32()) * 2.0 - 1.0;
    let uv = if rng.f32() < 0.8 {
        Vec2::new(0.6 + 0.2 * rng.f32(), 0.2 + 0.2 * rng.f32())
    } else {
        Vec2::new(rng.f32(), rng.f32())
    };
    let (pb, pg) = (0.05 + rng.f32(), 0.05 + rng.f32());
    Record {
        position: p,
        direction: uv_to_dir(uv),
        radiance: 2.0 * rng.f32(),
        pdf_mix: 0.5 * (pb + pg),
        weight: 1.0,
        product: rng.f32(),
        pdf_bsdf: pb,
        pdf_guide: pg,
        is_delta: false,
    }
}

const NON_FINITE: [f32; 3] = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];

/// Variants of `r` that [`SdTree::record`] must skip entirely (its documented validity
/// rules): non-finite or non-positive weight or mixture pdf, non-finite position or
/// direction component.
fn skipped_variants(r: &Record) -> Vec<Record> {
    let mut out = Vec::new();
    for x in NON_FINITE.into_iter().chain([0.0, -1.0]) {
        out.push(Record { weight: x, ..*r });
        out.push(Record { pdf_mix: x, ..*r });
    }
    for x in NON_FINITE {
        out.push(Record { radiance: x, ..*r });
        for axis in 0..3 {
            let mut p = r.position;
            p[axis] = x;
            out.push(Record { position: p, ..*r });
            let mut d = r.direction;
            d[axis] = x;
            out.push(Record { direction: d, ..*r });
        }
    }
    out
}

/// Variants of `r` with a radiance beyond `MAX_RECORD_VALUE` or a non-finite
/// fraction-gradient field, and what each must be equivalent to: such a radiance counts
/// towards W only (as radiance 0); a non-finite product or BSDF/guide pdf gives no fraction
/// gradient (as product 0). (A non-finite radiance skips the record: [`skipped_variants`].)
fn equivalent_variants(r: &Record) -> Vec<(Record, Record)> {
    let mut out = vec![(
        Record {
            radiance: 1e30,
            ..*r
        },
        Record {
            radiance: 0.0,
            ..*r
        },
    )];
    for x in NON_FINITE {
        let no_grad = Record { product: 0.0, ..*r };
        out.push((Record { product: x, ..*r }, no_grad));
        out.push((Record { pdf_bsdf: x, ..*r }, no_grad));
        out.push((Record { pdf_guide: x, ..*r }, no_grad));
    }
    out
}

/// Extreme but finite records: huge radiance over a subnormal pdf (a value of 1e83, beyond
/// the fixed-point range: before `MAX_RECORD_VALUE`, a few of these wrapped the cell sums and
/// the next refinement asked for 5 GiB), subnormal weights and radiance, huge products.
fn extreme_variants(r: &Record) -> Vec<Record> {
    vec![
        Record {
            radiance: f32::MAX,
            pdf_mix: 1e-45,
            ..*r
        },
        Record {
            radiance: 1e-45,
            weight: 1e-45,
            ..*r
        },
        Record {
            product: f32::MAX,
            pdf_bsdf: f32::MAX,
            pdf_guide: 1e-45,
            ..*r
        },
        Record {
            pdf_mix: f32::MAX,
            ..*r
        },
    ]
}

/// Trains `tree` for `iterations` iterations of `n` good records each, feeding every
/// good record through `extra` too (the records it returns are recorded after it).
fn train(
    tree: &mut SdTree,
    seed: u64,
    n: usize,
    iterations: u32,
    extra: impl Fn(&Record) -> Vec<Record>,
) {
    let mut rng = TestRng::new(seed);
    let mut jitter = TestRng::new(seed ^ 0x5555);
    for k in 0..iterations {
        for i in 0..n {
            let r = good_record(&mut rng);
            tree.record(&r, &mut jitter.f32_source());
            for x in extra(&r) {
                tree.record(&x, &mut jitter.f32_source());
            }
            if i % 500 == 499 {
                tree.step_fractions();
            }
        }
        tree.step_fractions();
        tree.refine(k);
    }
}

fn fresh(cfg: &GuideConfig) -> SdTree {
    SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg.clone())
}

/// Every statistic of every spatial leaf is finite, the fraction is a probability, each
/// sampling quadtree's pdf integrates to 1, and sampling returns finite unit directions
/// whose pdf is positive, finite and what [`SdTree::pdf_leaf`] gives for them.
fn assert_guide_sane(tree: &SdTree, what: &str) {
    assert!(tree.is_built(), "{what}");
    let mut rng = TestRng::new(99);
    for (i, leaf) in tree.leaves().iter().enumerate() {
        let h = LeafHandle(i as u32);
        let f = &leaf.fraction;
        assert!(
            leaf.flux.is_finite() && leaf.flux >= 0.0,
            "{what}: leaf {i} flux {}",
            leaf.flux
        );
        assert!(
            f.theta.is_finite() && f.m.is_finite() && f.v.is_finite(),
            "{what}: leaf {i} fraction state {f:?}"
        );
        let (mean, dev) = tree.light_sample_stats_leaf(h);
        assert!(mean.is_finite() && dev.is_finite(), "{what}: leaf {i}");
        let alpha = tree.bsdf_sampling_fraction_leaf(h);
        assert!(
            (0.0..=1.0).contains(&alpha),
            "{what}: leaf {i} alpha {alpha}"
        );
        let integral: f64 = leaf
            .sampling
            .tree()
            .leaf_cells()
            .iter()
            .map(|c| leaf.sampling.cell_pdf(c) * c.size * c.size)
            .sum();
        assert!(
            (integral - 1.0).abs() < 1e-5,
            "{what}: leaf {i} pdf integrates to {integral}"
        );
        for _ in 0..64 {
            let (d, p) = tree
                .sample_leaf(h, &mut rng.f32_source())
                .expect("built tree samples");
            assert!(
                d.is_finite() && (d.length() - 1.0).abs() < 1e-5,
                "{what}: leaf {i} sampled {d}"
            );
            assert!(p > 0.0 && p.is_finite(), "{what}: leaf {i} pdf {p} of {d}");
            let q = tree.pdf_leaf(h, d);
            assert!(
                (q - p).abs() <= 2e-3 * p,
                "{what}: leaf {i}: sampled pdf {p}, pdf of the direction {q} ({d})"
            );
        }
    }
}

#[test]
fn nan_inf_and_extreme_records_leave_every_statistic_finite_and_pdfs_normalised() {
    for (name, cfg) in configs() {
        let mut tree = fresh(&cfg);
        train(&mut tree, 1, 3000, 4, |r| {
            let mut v = skipped_variants(r);
            v.extend(equivalent_variants(r).into_iter().map(|(x, _)| x));
            v.extend(extreme_variants(r));
            v
        });
        assert!(tree.stats().leaves > 1, "{name}: the tree was refined");
        assert_guide_sane(&tree, name);
    }
}

#[test]
fn records_with_non_finite_fields_are_skipped_or_reduced_exactly_as_documented() {
    // Bit-for-bit: a tree fed good records plus the invalid variants equals one fed the
    // good records alone (plus the documented equivalents of the partly valid ones).
    for (name, cfg) in configs() {
        let (mut poisoned, mut clean) = (fresh(&cfg), fresh(&cfg));
        train(&mut poisoned, 2, 2000, 3, |r| {
            let mut v = skipped_variants(r);
            v.extend(equivalent_variants(r).into_iter().map(|(x, _)| x));
            v
        });
        train(&mut clean, 2, 2000, 3, |r| {
            equivalent_variants(r).into_iter().map(|(_, y)| y).collect()
        });
        // The stochastic filter draws three numbers for each record it uses: `train` draws
        // from one jitter stream, so skipped records (which draw none) keep it aligned.
        assert_eq!(
            poisoned.structure_hash(),
            clean.structure_hash(),
            "{name}: structure"
        );
        assert_eq!(poisoned.encode(), clean.encode(), "{name}: tree bytes");
        // Every skipped variant with a NaN or infinity is counted (2000 records x 3
        // iterations, 27 such variants each: weight, pdf and radiance 3 each, position and
        // direction 9 each); the finite skipped ones (weight or pdf 0, -1) are not.
        let counted = poisoned.take_nonfinite_records();
        assert_eq!(counted, 2000 * 3 * 27, "{name}: rejected records counted");
        assert_eq!(clean.take_nonfinite_records(), 0, "{name}");
    }
}

/// A tree over [-1, 1]^3 (one spatial leaf: few records) trained on records in the
/// directions `dirs` yields with radiance `radiance(i)`, `iterations` times.
fn directional_tree(
    cfg: &GuideConfig,
    iterations: u32,
    n: usize,
    dir: impl Fn(usize, &mut TestRng) -> Vec3,
    radiance: impl Fn(usize) -> f32,
) -> SdTree {
    let mut tree = fresh(&GuideConfig {
        s_tree_threshold: 1e12,
        ..cfg.clone()
    });
    let mut rng = TestRng::new(7);
    for k in 0..iterations {
        for i in 0..n {
            let d = dir(i, &mut rng);
            let r = Record::radiance_only(Vec3::ZERO, d, radiance(i), 0.25, 1.0);
            tree.record(&r, &mut || 0.5);
        }
        tree.step_fractions();
        tree.refine(k);
    }
    tree
}

#[test]
fn guide_with_zero_energy_everywhere_samples_uniformly_with_finite_pdfs() {
    // Only zero-radiance records (light never reached the region): the quadtree keeps no
    // energy, sampling falls back to uniform over the sphere, pdf 1 / (4 pi) everywhere.
    for (name, cfg) in configs() {
        let tree = directional_tree(
            &cfg,
            3,
            2000,
            |_, r| uv_to_dir(Vec2::new(r.f32(), r.f32())),
            |_| 0.0,
        );
        assert_guide_sane(&tree, name);
        let h = tree.leaf_index(Vec3::ZERO);
        for d in [Vec3::Z, -Vec3::Z, Vec3::X, Vec3::new(1.0, -0.0, 0.0)] {
            let p = tree.pdf_leaf(h, d);
            assert!((p - 1.0 / JACOBIAN).abs() < 1e-7, "{name}: pdf {p} of {d}");
        }
    }
}

#[test]
fn zero_energy_cells_are_never_sampled_and_near_zero_cells_keep_a_finite_inverse_pdf() {
    // Energy 1 in a narrow lobe, 1e-9 of it (per record) spread over a small patch
    // elsewhere, none anywhere else: refined quadtrees have deep cells, cells with zero
    // energy (pdf exactly 0, never sampled) and cells with pdfs many orders of magnitude
    // below the peak, whose inverse must still be finite (no subnormal pdf).
    let lobe = |r: &mut TestRng| uv_to_dir(Vec2::new(0.7 + 0.01 * r.f32(), 0.3 + 0.01 * r.f32()));
    let faint = |r: &mut TestRng| uv_to_dir(Vec2::new(0.1 + 0.05 * r.f32(), 0.8 + 0.05 * r.f32()));
    for (name, cfg) in configs() {
        let tree = directional_tree(
            &cfg,
            4,
            4000,
            |i, r| if i % 10 == 0 { faint(r) } else { lobe(r) },
            |i| if i % 10 == 0 { 1e-9 } else { 1.0 },
        );
        assert_guide_sane(&tree, name);
        let h = tree.leaf_index(Vec3::ZERO);
        // Cells no record reached (box filters spread energy by up to a cell, so which
        // ones depends on the filter): their pdf is exactly 0.
        let quadtree = &tree.leaf(h).sampling;
        let dark: Vec<_> = quadtree
            .tree()
            .leaf_cells()
            .into_iter()
            .filter(|c| quadtree.cell_pdf(c) == 0.0)
            .collect();
        assert!(!dark.is_empty(), "{name}: zero-energy cells exist");
        for c in &dark {
            let centre = Vec2::new(
                (c.origin[0] + 0.5 * c.size) as f32,
                (c.origin[1] + 0.5 * c.size) as f32,
            );
            assert_eq!(quadtree.pdf(centre), 0.0, "{name}: dark cell {c:?}");
        }
        let mut rng = TestRng::new(3);
        let (mut min_faint, mut peak) = (f32::INFINITY, 0.0f32);
        for _ in 0..200 {
            let p = tree.pdf_leaf(h, faint(&mut rng));
            assert!(p == 0.0 || (1.0 / p).is_finite(), "{name}: faint pdf {p}");
            if p > 0.0 {
                min_faint = min_faint.min(p);
            }
            peak = peak.max(tree.pdf_leaf(h, lobe(&mut rng)));
        }
        assert!(
            min_faint < 1e-4 * peak,
            "{name}: the faint patch is faint: {min_faint} vs {peak}"
        );
        for _ in 0..20_000 {
            let (d, p) = tree.sample_leaf(h, &mut rng.f32_source()).unwrap();
            let uv = dir_to_uv(d);
            let in_lobe = (0.69..=0.72).contains(&uv.x) && (0.29..=0.32).contains(&uv.y);
            let in_faint = (0.09..=0.16).contains(&uv.x) && (0.79..=0.86).contains(&uv.y);
            // Box filters spread energy by up to one cell: allow the cells around the
            // patches, never the dark rest of the sphere.
            assert!(
                in_lobe || in_faint || p > 0.0 && tree.pdf_leaf(h, d) > 0.0,
                "{name}: sampled a zero-energy direction {uv}"
            );
            assert!(p > 0.0 && (1.0 / p).is_finite(), "{name}: pdf {p}");
        }
    }
}

/// Distance from `uv` to the nearest edge of `cell` (0 outside or on it).
fn inside_margin(uv: Vec2, c: &crate::Cell) -> f64 {
    let m = |x: f32, o: f64| (x as f64 - o).min(o + c.size - x as f64);
    m(uv.x, c.origin[0]).min(m(uv.y, c.origin[1])).max(0.0)
}

#[test]
fn energy_at_the_poles_and_on_the_seam_is_sampled_with_consistent_finite_pdfs() {
    // All light arrives exactly from the poles and the seam directions: the quadtree
    // refines deep (cells of side 2^-16 after 5 iterations) in the corners and on the
    // edges of the square. Every such direction gets a positive finite pdf; every sample is a finite
    // unit direction with a positive finite pdf, which the direction's pdf reproduces
    // unless the sample lies within the mapping's f32 resolution of its cell's edge.
    //
    // Found: near the poles `uv_to_dir` computes z = 2u - 1 in f32, so u survives the
    // round trip only to about 3e-8 (2^-25); a sample within that of a cell edge maps back
    // into the neighbour cell, whose pdf can be 0 (a few of 20000 samples here). That is the
    // precision of the mapping, not a sampler fault: the sampled pdf is the density of the
    // (u, v) actually drawn, so guided samples stay unbiased; only MIS weights of
    // directions in those 3e-8-wide slivers use the neighbour's pdf.
    const RESOLUTION: f64 = 6e-8;
    let dirs = seam_and_poles();
    for (name, cfg) in configs() {
        let n = dirs.len();
        let tree = directional_tree(&cfg, 5, 4000, |i, _| dirs[i % n], |_| 1.0);
        assert_guide_sane(&tree, name);
        let h = tree.leaf_index(Vec3::ZERO);
        for &d in &dirs {
            let p = tree.pdf_leaf(h, d);
            assert!(p > 0.0 && p.is_finite(), "{name}: pdf {p} of {d}");
        }
        let quadtree = &tree.leaf(h).sampling;
        assert!(
            quadtree.tree().depth() >= 12,
            "{name}: deep cells ({})",
            quadtree.tree().depth()
        );
        let mut rng = TestRng::new(11);
        let mut on_edges = 0;
        for _ in 0..20_000 {
            let (uv, p) = quadtree.sample_with_pdf(&mut rng.f32_source());
            let d = uv_to_dir(uv);
            assert!(
                d.is_finite() && (d.length() - 1.0).abs() < 1e-5,
                "{name}: {uv} -> {d}"
            );
            assert!(p > 0.0 && p.is_finite(), "{name}: pdf {p} at {uv}");
            let back = dir_to_uv(d);
            let q = quadtree.pdf(back);
            if q != p {
                let margin = inside_margin(back, &quadtree.tree().leaf_cell(uv));
                assert!(
                    margin < RESOLUTION,
                    "{name}: {uv} (pdf {p}) maps back to {back} (pdf {q}), {margin} inside its cell"
                );
                on_edges += 1;
            }
        }
        assert!(
            on_edges < 40,
            "{name}: {on_edges} of 20000 samples on cell edges"
        );
    }
}
