//! Helpers shared by the crate's unit tests: the one random number generator, random
//! quadtrees and records, trained trees, and the 2019 configuration.

use crate::config::{DirectionalFilter, FractionLoss, FractionMode, GuideConfig, SpatialFilter};
use crate::dtree::{DTree, MAX_DEPTH};
use crate::mapping::uv_to_dir;
use crate::record::Record;
use crate::sdtree::SdTree;
use crate::stats::{to_fixed, FIXED_ONE};
use glam::{Vec2, Vec3};
use std::sync::atomic::AtomicU64;

/// The 2019 production configuration (Müller 2019): stochastic spatial filter, box
/// directional filter, learned fraction with KL loss, c = 4000, one sample per pixel per pass.
/// Renderers get it from the scene's `preset=2019` (`GuidedParams::preset_2019` in
/// pathfarm-scene); the guide's tests build it here.
pub(crate) fn config_2019() -> GuideConfig {
    GuideConfig {
        s_tree_threshold: 4000.0,
        spp_per_pass: 1,
        spatial_filter: SpatialFilter::Stochastic,
        directional_filter: DirectionalFilter::Box,
        bsdf_sampling_fraction: FractionMode::Learned {
            loss: FractionLoss::Kl,
        },
        ..GuideConfig::default()
    }
}

/// The default configuration with spatial threshold `s_tree_threshold`: how finely the tests'
/// records split space.
pub(crate) fn threshold_config(s_tree_threshold: f64) -> GuideConfig {
    GuideConfig {
        s_tree_threshold,
        ..GuideConfig::default()
    }
}

/// The default configuration with a learned fraction under `loss` and spatial threshold
/// `s_tree_threshold` (1e15: space is never split, one leaf learns from every record).
pub(crate) fn learned_config(s_tree_threshold: f64, loss: FractionLoss) -> GuideConfig {
    GuideConfig {
        s_tree_threshold,
        bsdf_sampling_fraction: FractionMode::Learned { loss },
        ..GuideConfig::default()
    }
}

/// An empty tree over the cube [-1, 1]^3, the domain of every test's records.
pub(crate) fn cube_tree(cfg: GuideConfig) -> SdTree {
    SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg)
}

/// The random numbers of every test in the crate.
pub(crate) use pathfarm_testkit::TestRng;

/// Kinds of random quadtrees.
#[derive(Clone, Copy, Debug)]
pub(crate) enum TreeKind {
    /// Several blobs of random width, including zero-energy regions.
    Blobs,
    /// One point mass refined down to depth 20, plus a weak background.
    Peak,
    /// Mass only inside a random rectangle (large zero regions).
    Rect,
}

fn random_uv(
    rng: &mut TestRng,
    kind: TreeKind,
    centres: &[(f64, f64, f64)],
    rect: [f64; 4],
) -> Vec2 {
    match kind {
        TreeKind::Blobs => {
            let (cx, cy, s) = centres[rng.below(centres.len() as u64) as usize];
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
pub(crate) fn random_dtree(seed: u64, kind: TreeKind) -> DTree {
    let mut rng = TestRng::new(seed);
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

pub(crate) fn clustered_records(rng: &mut TestRng, n: usize) -> Vec<Record> {
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

pub(crate) fn warmed_tree(cfg: GuideConfig, seed: u64, n: usize, iterations: u32) -> SdTree {
    let mut t = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), cfg);
    let mut rng = TestRng::new(seed);
    for k in 0..iterations {
        for r in clustered_records(&mut rng, n) {
            t.record(&r, &mut rng.f32_source());
        }
        t.step_fractions();
        t.refine(k);
    }
    t
}

pub(crate) fn det_records(n: usize, seed: u64) -> Vec<(Record, u64)> {
    let mut rng = TestRng::new(seed);
    clustered_records(&mut rng, n)
        .into_iter()
        .enumerate()
        .map(|(i, r)| (r, seed * 1_000_003 + i as u64))
        .collect()
}

/// Records every record, and beside each a light sample at its position (one in three
/// occluded, value 0) whose value derives from the record's seed.
pub(crate) fn record_all(t: &SdTree, recs: &[(Record, u64)]) {
    for (r, s) in recs {
        t.record(r, &mut TestRng::new(*s).f32_source());
        let light = if s % 3 == 0 {
            0.0
        } else {
            (s % 997) as f32 * 0.37
        };
        t.record_light_sample(t.leaf_index(r.position), light);
    }
}

pub(crate) fn random_unit(rng: &mut TestRng) -> Vec3 {
    loop {
        let v = Vec3::new(rng.gauss() as f32, rng.gauss() as f32, rng.gauss() as f32);
        if v.length() > 1e-3 {
            return v.normalize();
        }
    }
}

/// Directions on the seam of the mapping (phi = 0 = 2 pi: y = +-0 with x > 0, and
/// the two f32 neighbours of the seam) and at the poles (+-z).
pub(crate) fn seam_and_poles() -> Vec<Vec3> {
    let tiny = f32::EPSILON;
    vec![
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(1.0, -0.0, 0.0),
        Vec3::new(1.0, tiny, 0.0).normalize(),
        Vec3::new(1.0, -tiny, 0.0).normalize(),
        Vec3::new(1.0, -1e-30, 0.3).normalize(),
        uv_to_dir(Vec2::new(0.5, 1.0 - f32::EPSILON / 2.0)),
        Vec3::Z,
        -Vec3::Z,
        Vec3::new(1e-30, 0.0, 1.0),
        Vec3::new(0.0, 0.0, -1.0 + f32::EPSILON),
    ]
}
