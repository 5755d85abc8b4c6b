//! Tests of the cell masks and weights: hemisphere masks, cosine weights (vectorised and
//! scalar) and the cell of a direction.

use super::*;
use crate::mapping::{dir_to_uv, uv_to_dir};
use crate::test_support::{random_unit, TestRng};

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
    let mut rng = TestRng::new(41);
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
    let mut rng = TestRng::new(71);
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
    let mut rng = TestRng::new(53);
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
    let mut rng = TestRng::new(59);
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
