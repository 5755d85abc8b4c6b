//! The guided job session driven tile by tile, as the farm drives it: every tile rendered on
//! its own copy of the tree (decoded from the wire form, fractions set from the master),
//! statistics shipped with `take_stats`, tiles handed in out of order. The image and the
//! trained tree must be bit-identical to the one-process render (deterministic checks, no
//! significance level).

use pathfarm_guide::SdTree;
use pathfarm_render::checkpoint::Checkpoint;
use pathfarm_render::guided::{
    guide_config, render_guided, Budget, FallbackPolicy, GuidedOptions, GuidingVerdict, Next,
    Session,
};
use pathfarm_render::pass::{render_unit, PassKind, UnitInputs};
use pathfarm_render::{Film, Region, RenderSettings, Scene};
use pathfarm_scene::{GuidedCombination, GuidedNee, GuidedParams, GuidedSpatialFilter};

use crate::common::*;

/// A worker's view: the tree of a version, refreshed when the unit names another version.
struct WorkerTree {
    version: Option<(u32, u32)>,
    tree: Option<SdTree>,
}

impl WorkerTree {
    fn get(&mut self, master: &SdTree, version: (u32, u32)) -> &mut SdTree {
        if self.version.map(|v| v.0) != Some(version.0) {
            // a new tree version travels in its wire form
            self.tree = Some(SdTree::decode(&master.encode()).expect("decode"));
        }
        let tree = self.tree.as_mut().unwrap();
        if self.version != Some(version) {
            tree.set_fraction_states(&master.fraction_states())
                .expect("same leaves");
        }
        self.version = Some(version);
        tree
    }
}

/// Whether the tiled driver replaces its session by one restored from a checkpoint
/// whenever one can be taken.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Restarts {
    Never,
    AtEveryCheckpoint,
}

/// The session driven over `tile`-pixel tiles (0: each unit re-tiled with another tile
/// size, as the farm re-tiles units by cost), each unit's tiles handed in in a scrambled
/// order (`order_seed`), each tile rendered on a worker copy of the tree.
fn render_tiled(
    scene: &Scene,
    params: &GuidedParams,
    spp: u32,
    seed: u64,
    tile: u32,
    order_seed: u64,
    policy: FallbackPolicy,
    restarts: Restarts,
) -> (Film, SdTree, Vec<PassKind>) {
    let (w, h) = (scene.width, scene.height);
    let budget = Budget::Spp(spp);
    let (mut session, _) = new_session(scene, params, spp, tile.max(1), policy);
    let mut restored = 0;
    let mut worker = WorkerTree {
        version: None,
        tree: None,
    };
    let mut kinds = Vec::new();
    let mut clock = 0.0;
    while let Next::Render(spec) = session.next(clock) {
        kinds.push(spec.kind);
        if tile == 0 {
            let edge = 3 + (spec.unit % 11) as u32;
            session.retile(Region::tiles(w, h, edge)).expect("retile");
        }
        let tiles = session.tiles().to_vec();
        let mut order: Vec<usize> = (0..tiles.len()).collect();
        TestRng::new(order_seed ^ spec.unit.wrapping_mul(0x9e37_79b9_7f4a_7c15))
            .shuffle(&mut order);
        for index in order {
            let version = (spec.tree_version, spec.fraction_version);
            let estimate = session.estimate().to_vec();
            let wt = worker.get(session.tree(), version);
            let inputs = UnitInputs {
                scene,
                params,
                tree: wt,
                estimate: &estimate,
                seed,
                tile_size: 5,
            };
            let out = render_unit(&inputs, &spec, tiles[index], &|_| {});
            let stats = spec.record().then(|| wt.take_stats());
            clock += 0.001;
            session
                .add_tile(spec.unit, index, &out, stats.as_ref(), clock)
                .expect("tile accepted");
        }
        // A coordinator restarted between iterations continues from the checkpoint alone.
        if let (Restarts::AtEveryCheckpoint, Some(cp)) = (restarts, session.checkpoint()) {
            let bytes = cp.to_bytes(&session.tree().encode());
            let (cp, tree) = Checkpoint::from_bytes(&bytes).expect("read back");
            let tiles = Region::tiles(w, h, tile.max(1));
            session = Session::restore(params, budget, tiles, policy, &cp, tree).expect("restore");
            worker = WorkerTree {
                version: None,
                tree: None,
            };
            restored += 1;
        }
    }
    if restarts == Restarts::AtEveryCheckpoint {
        assert!(
            restored >= 1,
            "the job restarted between iterations ({restored} times)"
        );
    }
    let (film, _, tree) = session.finish();
    (film, tree, kinds)
}

/// A fresh session of `scene` with `params` (an untrained tree of the scene's bounds) over
/// `tile`-pixel tiles, and those tiles.
fn new_session(
    scene: &Scene,
    params: &GuidedParams,
    spp: u32,
    tile: u32,
    policy: FallbackPolicy,
) -> (Session, Vec<Region>) {
    let (lo, hi) = scene.accel.bounds();
    let tree = SdTree::new(lo, hi, guide_config(params, scene));
    let (w, h) = (scene.width, scene.height);
    let tiles = Region::tiles(w, h, tile);
    let session = Session::new(params, Budget::Spp(spp), tree, w, h, tiles.clone(), policy);
    (session, tiles)
}

fn one_process(
    scene: &Scene,
    params: &GuidedParams,
    spp: u32,
    seed: u64,
    policy: FallbackPolicy,
) -> (Film, SdTree) {
    let settings = RenderSettings::new(Some(spp), None, seed);
    let options = GuidedOptions {
        policy,
        ..Default::default()
    };
    let (film, _, tree) = render_guided(scene, params, Budget::Spp(spp), &settings, options);
    (film, tree)
}

fn assert_same(a: &(Film, SdTree), b: &(Film, SdTree), what: &str) {
    assert!(
        film_bits(&a.0) == film_bits(&b.0),
        "{what}: the tiled image differs from the one-process image"
    );
    assert!(
        a.1.encode() == b.1.encode(),
        "{what}: the tiled tree differs from the one-process tree"
    );
}

#[test]
fn tiled_session_with_worker_trees_equals_the_one_process_render() {
    // door-ajar (gaussian filter: tiles need their halo) in the pathfarm preset: learned
    // fractions, guided roulette, splitting, the fallback check, inverse-variance combination.
    let scene = door_ajar((37, 23));
    let params = scene.guided.clone().expect("guided");
    let policy = FallbackPolicy::Rule;
    let single = one_process(&scene, &params, 24, 7, policy);
    let (film, tree, kinds) = render_tiled(&scene, &params, 24, 7, 8, 1, policy, Restarts::Never);
    assert!(kinds.contains(&PassKind::Record) && kinds.contains(&PassKind::Guided));
    assert_same(&(film, tree), &single, "pathfarm preset, 8-pixel tiles");
    // another tiling and another arrival order: the same bits
    let (film, tree, _) = render_tiled(&scene, &params, 24, 7, 13, 99, policy, Restarts::Never);
    assert_same(&(film, tree), &single, "13-pixel tiles");
    // every unit tiled differently
    let (film, tree, _) = render_tiled(&scene, &params, 24, 7, 0, 5, policy, Restarts::Never);
    assert_same(&(film, tree), &single, "a tiling per unit");
    // restarted from a checkpoint after every iteration: the same bits
    let (film, tree, _) = render_tiled(
        &scene,
        &params,
        24,
        7,
        8,
        3,
        policy,
        Restarts::AtEveryCheckpoint,
    );
    assert_same(&(film, tree), &single, "restarted at every checkpoint");
    // the tree learned something (the test would be vacuous on an empty tree)
    assert!(single.1.stats().leaves > 1, "{:?}", single.1.stats());
}

#[test]
fn tiled_session_equals_one_process_through_the_path_fallback() {
    // Forced fallback: probe passes and the plain path-tracing rest are tiled too.
    let scene = door_ajar((29, 17));
    let params = scene.guided.clone().expect("guided");
    let policy = FallbackPolicy::Force(GuidingVerdict::FallBack);
    let single = one_process(&scene, &params, 24, 3, policy);
    let (film, tree, kinds) = render_tiled(
        &scene,
        &params,
        24,
        3,
        6,
        5,
        policy,
        Restarts::AtEveryCheckpoint,
    );
    assert!(kinds.contains(&PassKind::Probe), "{kinds:?}");
    assert!(kinds.contains(&PassKind::Path), "{kinds:?}");
    assert_same(&(film, tree), &single, "forced fallback");
}

#[test]
fn tiled_session_equals_one_process_with_stochastic_filter_kickstart_and_automatic() {
    // The stochastic spatial filter draws random numbers while recording, and kick-start
    // records light samples mid-path: halo samples must draw the same numbers without
    // recording. Automatic combination turns a training iteration into the final one.
    let scene = door_ajar((31, 19));
    let mut params = scene.guided.clone().expect("guided");
    params.spatial_filter = GuidedSpatialFilter::Stochastic;
    params.nee = GuidedNee::Kickstart;
    params.sample_combination = GuidedCombination::Automatic;
    params.path_fallback = false;
    let policy = FallbackPolicy::Rule;
    let single = one_process(&scene, &params, 40, 11, policy);
    let (film, tree, _) = render_tiled(&scene, &params, 40, 11, 7, 2, policy, Restarts::Never);
    assert_same(
        &(film, tree),
        &single,
        "stochastic filter, kickstart, automatic",
    );
}

#[test]
fn damaged_checkpoints_are_refused() {
    let scene = door_ajar((8, 8));
    let params = scene.guided.clone().expect("guided");
    let (s, tiles) = new_session(&scene, &params, 8, 8, FallbackPolicy::Rule);
    let cp = s.checkpoint().expect("a fresh session can be checkpointed");
    let bytes = cp.to_bytes(&s.tree().encode());
    let restore = |b: &[u8]| {
        let (cp, tree) = Checkpoint::from_bytes(b)?;
        Session::restore(
            &params,
            Budget::Spp(8),
            tiles.clone(),
            FallbackPolicy::Rule,
            &cp,
            tree,
        )
    };
    assert!(restore(&bytes).is_ok());
    for cut in [0, 4, 5, 40, bytes.len() / 2, bytes.len() - 1] {
        assert!(restore(&bytes[..cut]).is_err(), "truncated at {cut}");
    }
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(restore(&longer).is_err(), "trailing bytes");
}

#[test]
fn session_rejects_duplicate_foreign_and_misplaced_tiles() {
    let scene = door_ajar((16, 16));
    let params = scene.guided.clone().expect("guided");
    let (mut s, tiles) = new_session(&scene, &params, 8, 8, FallbackPolicy::Rule);
    let Next::Render(spec) = s.next(0.0) else {
        panic!("a first unit")
    };
    assert_eq!(s.next(0.0), Next::Wait, "one unit at a time");
    let inputs = UnitInputs {
        scene: &scene,
        params: &params,
        tree: s.tree(),
        estimate: &[],
        seed: 1,
        tile_size: 4,
    };
    let out0 = render_unit(&inputs, &spec, tiles[0], &|_| {});
    let out1 = render_unit(&inputs, &spec, tiles[1], &|_| {});
    assert!(matches!(
        s.add_tile(spec.unit + 1, 0, &out0, None, 0.0),
        Err(pathfarm_render::session::TileError::WrongUnit { .. })
    ));
    assert!(matches!(
        s.add_tile(spec.unit, 1, &out0, None, 0.0),
        Err(pathfarm_render::session::TileError::WrongRegion { .. })
    ));
    assert!(matches!(
        s.add_tile(spec.unit, 9, &out0, None, 0.0),
        Err(pathfarm_render::session::TileError::NoSuchTile(9))
    ));
    s.add_tile(spec.unit, 0, &out0, None, 0.0).expect("first");
    assert_eq!(
        s.add_tile(spec.unit, 0, &out0, None, 0.0),
        Err(pathfarm_render::session::TileError::Duplicate(0))
    );
    s.add_tile(spec.unit, 1, &out1, None, 0.0).expect("second");
    assert_eq!(s.tiles_done(), (2, 4));
}
