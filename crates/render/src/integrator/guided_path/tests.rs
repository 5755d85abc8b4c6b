use super::*;
use pathfarm_bsdf::{Conductor, Diffuse, Microfacet, MicrofacetType, RoughConductor};
use pathfarm_guide::GuideConfig;

/// A built tree with a peaked distribution (records from a direction cone around +z, and
/// a weaker one from below, which a surface facing +z cannot reflect).
fn trained_tree() -> SdTree {
    let mut tree = SdTree::new(Vec3::splat(-1.0), Vec3::splat(1.0), GuideConfig::default());
    let mut r = Rng::new(3, 4);
    for k in 0..2 {
        for i in 0..4000 {
            let (axis, l) = if i % 3 == 2 {
                (Vec3::new(-0.2, 0.1, -1.0), 0.5)
            } else {
                (Vec3::new(0.3, 0.2, 1.0), 1.0)
            };
            let d = (axis + 0.3 * (Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) - 0.5))
                .normalize();
            let rec = Record::radiance_only(Vec3::ZERO, d, l + r.next_f32(), 0.5, 1.0);
            tree.record(&rec, &mut || r.next_f32());
        }
        tree.refine(k);
    }
    assert!(tree.is_built());
    tree
}

#[test]
fn split_count_follows_the_upper_window_edge_and_rounds_stochastically() {
    // Deterministic arithmetic (no significance level).
    let i = 0.5f32;
    let edge = SPLIT_WINDOW * i;
    assert_eq!(split_count(edge, i, 0.0), 1, "at the edge: no split");
    assert_eq!(split_count(0.1 * edge, i, 0.0), 1);
    assert_eq!(split_count(2.0 * edge, i, 0.99), 2);
    assert_eq!(
        split_count(2.5 * edge, i, 0.49),
        3,
        "u below the fraction rounds up"
    );
    assert_eq!(split_count(2.5 * edge, i, 0.51), 2);
    assert_eq!(split_count(1e9 * edge, i, 0.0), MAX_SPLIT, "capped");
    assert_eq!(split_count(f32::NAN, i, 0.0), 1);
    assert_eq!(split_count(1.0, 0.0, 0.0), 1, "no pixel estimate: no split");
    assert_eq!(split_count(f32::INFINITY, i, 0.0), 1);
    // Mean copies = the ratio (unbiased rounding), over a uniform grid of u.
    let mean = mean_over_u(|u| split_count(2.3 * edge, i, u));
    assert!((mean - 2.3).abs() < 1e-3, "{mean}");
}

/// Mean of `count(u)` over a uniform grid of 1000 values of u in (0, 1).
fn mean_over_u(count: impl Fn(f32) -> u32) -> f64 {
    let n = 1000;
    (0..n)
        .map(|k| count((k as f32 + 0.5) / n as f32) as f64)
        .sum::<f64>()
        / n as f64
}

#[test]
fn light_sample_count_follows_its_window_and_rounds_stochastically() {
    // Deterministic arithmetic (no significance level).
    let i = 0.5f32;
    let edge = LIGHT_SPLIT_WINDOW * i;
    assert_eq!(
        light_sample_count(edge, i, 0.0),
        1,
        "at the edge: one sample"
    );
    assert_eq!(
        light_sample_count(0.0, i, 0.0),
        1,
        "a certain light sample: one"
    );
    assert_eq!(light_sample_count(3.0 * edge, i, 0.99), 3);
    assert_eq!(
        light_sample_count(2.25 * edge, i, 0.2),
        3,
        "u below the fraction"
    );
    assert_eq!(light_sample_count(2.25 * edge, i, 0.3), 2);
    assert_eq!(
        light_sample_count(1e9 * edge, i, 0.0),
        MAX_LIGHT_SAMPLES,
        "capped"
    );
    assert_eq!(light_sample_count(f32::NAN, i, 0.0), 1);
    assert_eq!(light_sample_count(1.0, 0.0, 0.0), 1, "no pixel estimate");
    // Mean count = the ratio (unbiased rounding), over a uniform grid of u.
    let mean = mean_over_u(|u| light_sample_count(2.7 * edge, i, u));
    assert!((mean - 2.7).abs() < 1e-3, "{mean}");
}

#[test]
fn ppg_survival_is_the_reference_implementations() {
    // Deterministic arithmetic (no significance level).
    assert_eq!(
        ppg_survival(false, true, 1e-6, 1.0),
        1.0,
        "delta/unguided: no RR"
    );
    assert_eq!(ppg_survival(false, false, 1e-6, 1.0), 1.0);
    assert_eq!(
        ppg_survival(true, true, 1e-6, 1.0),
        0.99,
        "built: effectively off"
    );
    assert_eq!(ppg_survival(true, false, 1e-6, 1.0), 0.1);
    assert_eq!(ppg_survival(true, false, 0.5, 1.0), 0.5);
    assert_eq!(ppg_survival(true, false, 0.5, 1.5), 0.99);
    assert_eq!(ppg_survival(true, false, f32::NAN, 1.0), 0.1);
}

#[test]
fn guided_survival_follows_the_weight_window_and_stays_in_bounds() {
    // Deterministic arithmetic (no significance level).
    let i = 2.0f32;
    let window = ROULETTE_WINDOW * i;
    assert_eq!(
        guided_survival(window, i),
        1.0,
        "at the window edge: always kept"
    );
    assert_eq!(guided_survival(10.0 * window, i), 1.0);
    let q = guided_survival(0.5 * window, i);
    assert!((q - 0.5).abs() < 1e-6, "{q}");
    assert_eq!(guided_survival(0.0, i), ROULETTE_MIN_SURVIVAL);
    assert_eq!(guided_survival(1e-9, i), ROULETTE_MIN_SURVIVAL);
    assert_eq!(guided_survival(f32::NAN, i), 1.0);
    assert_eq!(guided_survival(0.0, 0.0), 1.0, "0/0 survives");
    assert_eq!(guided_survival(1.0, 0.0), 1.0);
}

#[test]
fn nee_and_hit_weights_partition_unity_with_the_same_mixture_pdf() {
    // Deterministic identity (no significance level): for directions produced by the
    // mixture sampler, the p_mix it reports equals what NEE computes for that direction,
    // and w_light(n p_light, p_mix) + w_hit(p_mix, n p_light) = 1 for the n light samples
    // of light splitting (each weighted by w_light / (n p_light), so n of them count as
    // one technique of pdf n p_light).
    let tree = trained_tree();
    let frame = Frame::from_normal(Vec3::new(0.1, 0.2, 1.0).normalize());
    let diffuse = Bsdf::Diffuse(Diffuse::new(Vec3::splat(0.8)));
    let rough = Bsdf::RoughConductor(RoughConductor::new(
        Microfacet::new(MicrofacetType::Ggx, 0.3, 0.3, true),
        Conductor::new(Vec3::splat(0.2), Vec3::splat(3.0), Vec3::ONE),
    ));
    let wi = Vec3::new(0.3, -0.2, 0.9).normalize();
    let mut rng = Rng::new(9, 1);
    let mut checked = 0;
    for (bsdf, hemisphere, cosine) in [
        (diffuse, false, false),
        (rough, false, false),
        (diffuse, true, false),
        (rough, true, false),
        (diffuse, true, true),
        (rough, true, true),
    ] {
        let region = guide_region(hemisphere, cosine, bsdf.flags(), &frame, wi);
        for alpha in [0.1f32, 0.5, 0.9] {
            let vg = VertexGuide {
                alpha,
                ..VertexGuide::at(&tree, Vec3::ZERO, region)
            };
            for _ in 0..2000 {
                let Some(ms) =
                    sample_mixture(&tree, &vg, &ShadedBsdf::plain(bsdf), &frame, wi, &mut rng)
                else {
                    continue;
                };
                let (p_nee, p_b, p_g) =
                    vg.pdf(&tree, &ShadedBsdf::plain(bsdf), wi, ms.wo, ms.wo_world);
                assert!(
                    (p_nee - ms.p_mix).abs() <= 1e-5 * ms.p_mix,
                    "{p_nee} vs {}",
                    ms.p_mix
                );
                assert!((p_nee - (alpha * p_b + (1.0 - alpha) * p_g)).abs() <= 1e-6 * p_nee);
                for p_light in [1e-3f32, 0.2, 1.0, 37.0] {
                    for n in [1.0f32, 2.0, MAX_LIGHT_SAMPLES as f32] {
                        let s = mis_weight(n * p_light, p_nee) + mis_weight(p_nee, n * p_light);
                        assert!((s - 1.0).abs() < 1e-5, "{s}");
                    }
                }
                checked += 1;
            }
        }
    }
    assert!(checked > 30_000);
}

#[test]
fn guide_mask_restricts_opaque_bsdfs_to_the_side_of_wi() {
    // Deterministic (no significance level).
    let frame = Frame::from_normal(Vec3::Y);
    let diffuse = Bsdf::Diffuse(Diffuse::new(Vec3::splat(0.5))).flags();
    let glass = Bsdf::Dielectric(pathfarm_bsdf::dielectric::Dielectric::new(
        1.5,
        Vec3::ONE,
        Vec3::ONE,
    ))
    .flags();
    let front = Vec3::new(0.1, 0.2, 0.9).normalize();
    let back = Vec3::new(0.1, 0.2, -0.9).normalize();
    assert_eq!(
        guide_mask(true, diffuse, &frame, front),
        CellMask::hemisphere(Vec3::Y)
    );
    assert_eq!(
        guide_mask(true, diffuse, &frame, back),
        CellMask::hemisphere(-Vec3::Y),
        "seen from behind (two-sided): the other hemisphere"
    );
    assert_eq!(CellMask::hemisphere(Vec3::Y).0.count_ones(), 8);
    assert_eq!(guide_mask(false, diffuse, &frame, front), CellMask::ALL);
    assert_eq!(
        guide_mask(true, glass, &frame, front),
        CellMask::ALL,
        "transmission: the whole sphere"
    );
}

#[test]
fn mixture_sampling_is_unbiased_for_a_diffuse_bsdf() {
    // E[f cos / p_mix] = albedo for any alpha and guide, restricted to the hemisphere
    // (cosine-weighted or not) or not, for an axis-aligned and a tilted normal. 200k samples, tolerance 5 standard
    // errors (two-sided significance ~6e-7 per case).
    let tree = trained_tree();
    let bsdf = Bsdf::Diffuse(Diffuse::new(Vec3::splat(0.7)));
    let wi = Vec3::new(0.2, 0.1, 0.97).normalize();
    let tilted = Vec3::new(0.3, -0.4, 0.8).normalize();
    let cases = [
        (Vec3::Z, false, false, 0.1f32),
        (Vec3::Z, false, false, 0.5),
        (Vec3::Z, true, false, 0.1),
        (Vec3::Z, true, false, 0.5),
        (tilted, true, false, 0.3),
        (Vec3::Z, true, true, 0.1),
        (tilted, true, true, 0.3),
    ];
    for (k, (normal, hemisphere, cosine, alpha)) in cases.into_iter().enumerate() {
        let frame = Frame::from_normal(normal);
        let region = guide_region(hemisphere, cosine, bsdf.flags(), &frame, wi);
        let vg = VertexGuide {
            alpha,
            ..VertexGuide::at(&tree, Vec3::ZERO, region)
        };
        if hemisphere {
            // The cone from below carries about a sixth of the guide's mass.
            assert!(vg.region.mass < 0.95, "case {k}: mass {}", vg.region.mass);
        }
        let mut rng = Rng::new(17, k as u64);
        let n = 200_000;
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for _ in 0..n {
            let w = sample_mixture(&tree, &vg, &ShadedBsdf::plain(bsdf), &frame, wi, &mut rng)
                .map_or(0.0, |m| m.weight.x as f64);
            s += w;
            s2 += w * w;
        }
        let m = s / n as f64;
        let se = ((s2 / n as f64 - m * m) / n as f64).sqrt();
        assert!((m - 0.7).abs() < 5.0 * se, "case {k}: {m} ± {se}");
    }
}

#[test]
fn roulette_reads_the_unrestricted_guide_pdf_back_from_a_restricted_sample() {
    // Deterministic identity (no significance level): guided roulette's radiance estimate
    // needs the guide's own density, which unrestricted_guide_pdf recovers from the
    // restricted p_guide of mixture samples (mask or cosine weights; 0 outside the mask).
    let tree = trained_tree();
    let bsdf = Bsdf::Diffuse(Diffuse::new(Vec3::splat(0.7)));
    let wi = Vec3::new(0.2, 0.1, 0.97).normalize();
    let mut rng = Rng::new(23, 0);
    let mut checked = 0;
    for normal in [Vec3::Z, Vec3::new(0.3, -0.4, 0.8).normalize()] {
        let frame = Frame::from_normal(normal);
        for (hemisphere, cosine) in [(false, false), (true, false), (true, true)] {
            let region = guide_region(hemisphere, cosine, bsdf.flags(), &frame, wi);
            let vg = VertexGuide::at(&tree, Vec3::ZERO, region);
            for _ in 0..2000 {
                let Some(ms) =
                    sample_mixture(&tree, &vg, &ShadedBsdf::plain(bsdf), &frame, wi, &mut rng)
                else {
                    continue;
                };
                let got = unrestricted_guide_pdf(&vg.region, &ms);
                if ms.p_guide == 0.0 {
                    assert_eq!(got, 0.0);
                    continue;
                }
                let want = tree.pdf_leaf(vg.leaf(), ms.wo_world);
                assert!((got - want).abs() <= 1e-5 * want, "{got} vs {want}");
                checked += 1;
            }
        }
    }
    assert!(checked > 5_000, "{checked}");
}

/// One synthetic path event.
#[derive(Clone, Copy)]
struct Ev {
    /// Per-bounce throughput factor b (f cos / p_mix, RGB) and p_mix.
    b: Vec3,
    p_mix: f32,
    /// The vertex is recorded (smooth, non-delta direction).
    recorded: bool,
    /// NEE done at this vertex; its estimate n (radiance, relative to the throughput
    /// arriving at the vertex).
    nee: bool,
    n: Vec3,
    /// Emission found by this vertex's direction (relative to the throughput after the bounce).
    e: Vec3,
}

#[test]
fn forward_loop_recording_matches_the_recursive_reference_on_random_paths() {
    // Deterministic identity up to float rounding (relative 1e-4), on 500 random paths.
    let mut r = Rng::new(5, 5);
    let mut u = || r.next_f32();
    for path in 0..500 {
        let indirect_only = path % 2 == 0;
        let len = 1 + (u() * 12.0) as usize;
        let evs: Vec<Ev> = (0..len)
            .map(|_| Ev {
                b: Vec3::new(0.2 + u(), 0.2 + u(), 0.2 + u()),
                p_mix: 0.5 + u(),
                recorded: u() < 0.8,
                nee: u() < 0.7,
                n: if u() < 0.5 {
                    Vec3::new(u(), u(), u())
                } else {
                    Vec3::ZERO
                },
                e: if u() < 0.5 {
                    Vec3::new(u(), u(), u())
                } else {
                    Vec3::ZERO
                },
            })
            .collect();
        // Forward loop, as li does it: at vertex i, NEE (contribution T_{i-1} n_i),
        // then the bounce (T_i = T_{i-1} b_i, push), then the emission at x_{i+1}
        // (contribution T_i e_i).
        let mut rec = PathRecorder::default();
        let mut t = Vec3::ONE;
        for ev in &evs {
            if ev.nee {
                rec.add(t * ev.n);
            }
            t *= ev.b;
            let v = RecVertex {
                position: Vec3::ZERO,
                direction: Vec3::Z,
                throughput: t,
                p_mix: ev.p_mix,
                weight: 1.0,
                ..Default::default()
            };
            if !(ev.recorded && rec.push(v)) {
                rec.skip();
            }
            rec.add_emission(t * ev.e, indirect_only, ev.nee);
        }
        // Recursive reference: full incident radiance at vertex i along its direction,
        // L_i = e_i + n_{i+1} + b_{i+1} L_{i+1}; a recorded vertex that did NEE learns
        // L_i - e_i when indirect_only.
        let mut full = vec![Vec3::ZERO; len];
        for i in (0..len).rev() {
            let next = if i + 1 < len {
                let nx = &evs[i + 1];
                (if nx.nee { nx.n } else { Vec3::ZERO }) + nx.b * full[i + 1]
            } else {
                Vec3::ZERO
            };
            full[i] = evs[i].e + next;
        }
        let expected: Vec<Vec3> = (0..len)
            .filter(|&i| evs[i].recorded)
            .map(|i| {
                if indirect_only && evs[i].nee {
                    full[i] - evs[i].e
                } else {
                    full[i]
                }
            })
            .collect();
        let got: Vec<Vec3> = rec
            .vertices()
            .iter()
            .map(|v| v.incident_radiance())
            .collect();
        assert_eq!(got.len(), expected.len().min(MAX_RECORDED_VERTICES));
        for (g, e) in got.iter().zip(&expected) {
            assert!(
                (*g - *e).abs().max_element() <= 1e-4 * e.abs().max_element().max(1e-3),
                "path {path}: {g:?} vs {e:?}"
            );
        }
    }
}
