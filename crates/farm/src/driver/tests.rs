//! The driver's protocol on a small scene, one worker rendering in-process.

use std::time::Duration;

use pathfarm_guide::SdTree;
use pathfarm_render::guided::{guide_config, Budget, FallbackPolicy, Records, Splatting};
use pathfarm_render::pass::{render_unit, UnitInputs};
use pathfarm_render::Scene;

use super::*;

const SCENE: &str = include_str!("../coordinator/testdata/lit-floor.xml");

fn scene(test: &str) -> Scene {
    let dir = std::env::temp_dir().join(format!("pathfarm-driver-{}-{test}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("scene.xml");
    std::fs::write(&path, SCENE).unwrap();
    let desc = pathfarm_scene::load_scene(&path, &[]).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    Scene::build(&desc).unwrap()
}

fn driver(scene: &Scene, spp: u32) -> JobDriver {
    let params = scene.guided.clone().unwrap();
    let (lo, hi) = scene.world().accel.bounds();
    let tree = SdTree::new(lo, hi, guide_config(&params, scene));
    let splatting = Splatting {
        filter: scene.filter,
        seed: 1,
    };
    let size = (scene.width, scene.height);
    let tiles = Region::tiles(size.0, size.1, 8);
    let policy = FallbackPolicy::Force(pathfarm_render::guided::GuidingVerdict::Keep);
    let mut s = Session::new(
        &params,
        Budget::Spp(spp),
        tree,
        size,
        splatting,
        tiles,
        policy,
    );
    s.set_records(Records::PerIteration);
    JobDriver::new(s, Tiling::Fixed(8), 7, Millis(0))
}

/// The lease tile `index` of `unit` is rendered under, in these tests.
fn lease_of(unit: u64, index: usize) -> LeaseId {
    LeaseId(unit * 100 + index as u64)
}

/// Renders every tile of `spec` as worker `w` would (a tree from its published form) and
/// hands them in (tile `i` under lease [`lease_of`]); the records stay with the "worker"
/// and are returned.
fn render(
    scene: &Scene,
    d: &mut JobDriver,
    spec: PassSpec,
    w: WorkerId,
) -> (Vec<PassSpec>, Option<IterationStats>) {
    let params = scene.guided.clone().unwrap();
    let mut tree = SdTree::decode(&d.encode_tree()).unwrap();
    let states = codec::decode_fractions(&d.encode_fractions()).unwrap();
    tree.set_fraction_states(&states).unwrap();
    let estimate = d.session().estimate().to_vec();
    let regions = d.session().tiles_of(spec.unit).unwrap().to_vec();
    let inputs = UnitInputs {
        scene,
        params: &params,
        tree: &tree,
        estimate: &estimate,
        seed: 1,
        tile_size: 4,
    };
    let outs: Vec<TileOutput> = (regions.iter())
        .map(|&r| render_unit(&inputs, &spec, r, &|_| {}))
        .collect();
    let (stats, records) = match spec.record() {
        true => {
            let (g, r) = tree.take_stats().split_gradients();
            (Some(g), Some(r))
        }
        false => (None, None),
    };
    let tiles: Vec<TileIn> = (outs.iter().enumerate())
        .map(|(index, out)| TileIn {
            index,
            lease: lease_of(spec.unit, index),
            out,
            render_seconds: 0.01,
        })
        .collect();
    let ended = d
        .tiles_in(w, spec.unit, &tiles, stats.as_ref(), Millis(10))
        .unwrap();
    (ended, records)
}

fn offer(step: Step) -> Offer {
    match step {
        Step::Offer(o) => o,
        other => panic!("expected an offer, got {other:?}"),
    }
}

#[test]
fn inputs_are_published_once_per_version_and_records_are_asked_of_their_holders() {
    let scene = scene("publish");
    let mut d = driver(&scene, 8);
    let w = WorkerId(3);
    let first = offer(d.step(Millis(0), 1).unwrap());
    assert!(first.new_tree && first.new_fractions);
    assert!(!first.new_estimate, "no estimate before an iteration ended");
    assert_eq!(d.published_tree(), Some(first.spec.tree_version));
    assert_eq!(first.tiles, 4, "16x16 in tiles of 8");
    assert!(first.spec.record(), "the first unit trains the guide");
    let mut records: Option<IterationStats> = None;
    let mut leases = Vec::new();
    let mut offers = vec![first];
    let mut asked = Vec::new();
    // Render what is offered until the session wants the iteration's records.
    for _ in 0..64 {
        match d.step(Millis(20), 1).unwrap() {
            Step::Offer(o) => offers.push(o),
            Step::Wait => {
                let spec = *d.flights().first().expect("a unit in flight");
                let (ended, r) = render(&scene, &mut d, spec, w);
                assert_eq!(ended.first().map(|s| s.unit), Some(spec.unit));
                if let Some(r) = r {
                    match &mut records {
                        Some(kept) => kept.merge(&r).unwrap(),
                        None => records = Some(r),
                    }
                    let tiles = d.session().tiles_of(spec.unit).map_or(4, <[_]>::len);
                    leases.extend((0..tiles).map(|i| lease_of(spec.unit, i).0));
                }
                assert!(d.holds(w), "a recording unit's worker holds its records");
            }
            Step::Collect(holders) => {
                asked = holders;
                break;
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!(asked, vec![w], "the holder, once");
    assert!(
        matches!(d.step(Millis(30), 1).unwrap(), Step::Wait),
        "asked only once"
    );
    let version = offers[0].spec.tree_version;
    for o in &offers[1..] {
        assert_eq!(o.spec.tree_version, version);
        assert!(!o.new_tree, "the tree of a version is published once");
    }
    let records = records.expect("records were kept");
    let covered = Coverage::of(leases.iter().copied());
    assert!(matches!(
        d.records_from(WorkerId(4), &records, &covered),
        Err(RecordsRefused::NotAsked(_))
    ));
    assert!(!d.stalled(Millis(30), Duration::from_millis(100)));
    assert!(d.stalled(Millis(200), Duration::from_millis(100)));
    // Records that leave out one accepted upload, or count one too many, are refused and
    // change nothing: the holder is still asked.
    let short = Coverage::of(leases[1..].iter().copied());
    let mut extra = covered;
    extra.add(leases[0]);
    for wrong in [short, extra, Coverage::default()] {
        let e = d.records_from(w, &records, &wrong).unwrap_err();
        assert!(matches!(e, RecordsRefused::Coverage { .. }), "{e}");
        assert!(
            e.to_string()
                .contains(&format!("not the {}", covered.leases())),
            "{e}"
        );
        assert!(d.is_asked(w), "still owed");
    }
    assert_eq!(d.records_from(w, &records, &covered).unwrap(), 0);
    assert!(!d.stalled(Millis(200), Duration::from_millis(100)));
    match d.step(Millis(40), 1).unwrap() {
        Step::IterationEnded { iteration } => assert_eq!(iteration, offers[0].spec.iteration),
        other => panic!("expected the iteration's end, got {other:?}"),
    }
    assert!(!d.holds(w), "the records were handed over");
    let next = offer(d.step(Millis(50), 1).unwrap());
    assert_eq!(next.spec.tree_version, version + 1);
    assert!(
        next.new_tree && next.new_fractions,
        "a refined tree is published"
    );
    // The estimate is published for the passes only if they read it (guided roulette).
    let guided_roulette = scene.guided.as_ref().unwrap().russian_roulette;
    let reads = guided_roulette == pathfarm_scene::GuidedRoulette::Guided;
    assert_eq!(next.new_estimate, reads, "{guided_roulette:?}");
    assert_eq!(d.encode_estimate().is_empty(), !reads);
}

#[test]
fn tiles_the_session_refuses_change_nothing() {
    let scene = scene("refuse");
    let mut d = driver(&scene, 8);
    let o = offer(d.step(Millis(0), 1).unwrap());
    let region = d.session().tiles_of(o.spec.unit).unwrap()[0];
    let params = scene.guided.clone().unwrap();
    let tree = SdTree::decode(&d.encode_tree()).unwrap();
    let inputs = UnitInputs {
        scene: &scene,
        params: &params,
        tree: &tree,
        estimate: &[],
        seed: 1,
        tile_size: 4,
    };
    let out = render_unit(&inputs, &o.spec, region, &|_| {});
    let w = WorkerId(1);
    let wrong_unit = [TileIn {
        index: 0,
        lease: LeaseId(1),
        out: &out,
        render_seconds: 0.0,
    }];
    assert!(d
        .tiles_in(w, o.spec.unit + 5, &wrong_unit, None, Millis(1))
        .is_err());
    let wrong_index = [TileIn {
        index: 1,
        lease: LeaseId(2),
        out: &out,
        render_seconds: 0.0,
    }];
    assert!(d
        .tiles_in(w, o.spec.unit, &wrong_index, None, Millis(1))
        .is_err());
    assert!(!d.holds(w), "a refused tile makes no holder");
    assert_eq!(d.session().tiles_done().0, 0);
    assert_eq!(d.flights().len(), 1);
}
