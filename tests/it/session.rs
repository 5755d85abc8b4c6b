//! The guided job session driven tile by tile, as the farm drives it: every tile rendered on
//! its own copy of the tree (decoded from the wire form, fractions set from those published
//! with the unit), statistics shipped with `take_stats`, two units in flight whenever the
//! session allows, tiles of both handed in interleaved and out of order. The image and the
//! trained tree must be bit-identical to the one-process render (deterministic checks, no
//! significance level).

use pathfarm_guide::fraction::FractionState;
use pathfarm_guide::SdTree;
use pathfarm_render::checkpoint::Checkpoint;
use pathfarm_render::guided::{
    guide_config, render_guided, Budget, FallbackPolicy, GuidedOptions, GuidingVerdict, Next,
    Records, RecordsError, Session, Splatting,
};
use pathfarm_render::pass::{render_unit, PassKind, PassSpec, TilePixels, UnitInputs};
use pathfarm_render::{Film, Region, RenderSettings, Scene};
use pathfarm_scene::{GuidedCombination, GuidedNee, GuidedParams, GuidedSpatialFilter};

use crate::common::*;

/// A worker's view: the tree of a version, refreshed when the unit names another version.
struct WorkerTree {
    version: Option<(u32, u32)>,
    tree: Option<SdTree>,
}

impl WorkerTree {
    /// The tree for `unit`, whose fractions were published when it was issued.
    fn get(&mut self, master: &SdTree, unit: &Flight) -> &mut SdTree {
        let version = (unit.spec.tree_version, unit.spec.fraction_version);
        if self.version.map(|v| v.0) != Some(version.0) {
            // a new tree version travels in its wire form
            self.tree = Some(SdTree::decode(&master.encode()).expect("decode"));
        }
        let tree = self.tree.as_mut().unwrap();
        if self.version != Some(version) {
            tree.set_fraction_states(&unit.fractions)
                .expect("same leaves");
        }
        self.version = Some(version);
        tree
    }
}

/// A unit in flight: what was published with it, and its tiles not handed in yet.
struct Flight {
    spec: PassSpec,
    tiles: Vec<Region>,
    fractions: Vec<FractionState>,
    estimate: Vec<f32>,
    order: Vec<usize>,
}

/// Whether the tiled driver replaces its session by one restored from a checkpoint
/// whenever one can be taken.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Restarts {
    Never,
    AtEveryCheckpoint,
}

/// Where the tiled driver's workers send their quadtree records.
#[derive(Clone, Copy, PartialEq, Eq)]
enum RecordsAt {
    /// With every tile (`take_stats`).
    Tiles,
    /// Once an iteration ([`Records::PerIteration`]): each tile's gradients with it
    /// (`take_gradients`), the records when the session asks, from each of this many
    /// workers, whose trees each get a random share of the tiles.
    Iteration { workers: usize },
}

/// How [`render_tiled`] drives a session: the job (`spp`, `seed`, `policy`) and the ways
/// the farm may split it (tile size, hand-in order, restarts, where records go).
#[derive(Clone, Copy)]
struct Drive {
    spp: u32,
    seed: u64,
    /// Tile size in pixels; 0: each unit re-tiled with another size.
    tile: u32,
    /// Scrambles the order tiles are handed in.
    order_seed: u64,
    policy: FallbackPolicy,
    restarts: Restarts,
    records: RecordsAt,
}

/// What a tiled drive gave: the image, the tree, the kinds of the units in issue order, and
/// how many units were issued while another was in flight.
struct Driven {
    film: Film,
    tree: SdTree,
    kinds: Vec<PassKind>,
    overlapped: usize,
    /// Path-fallback probes issued while a unit of the iteration they check was in flight.
    probes_beside: usize,
    /// The iterations' accounts (the fallback's rule reads their rays a sample).
    iterations: Vec<pathfarm_render::guided::GuidedIteration>,
}

impl Driven {
    /// Training passes overlapped at least `n` times (a test of the pipelined steps would be
    /// vacuous otherwise).
    fn assert_overlapped(&self, n: usize) {
        let (got, kinds) = (self.overlapped, &self.kinds);
        assert!(got >= n, "{got} units overlapped: {kinds:?}");
    }
}

/// The session driven over `tile`-pixel tiles (0: each unit re-tiled with another tile
/// size, as the farm re-tiles units by cost), with every unit the session issues taken at
/// once (two when training passes overlap), the tiles of the units in flight handed in
/// interleaved in a scrambled order (`order_seed`: the later unit's tiles may all be in
/// first), each tile rendered on a worker copy of the tree.
fn render_tiled(scene: &Scene, params: &GuidedParams, drive: Drive) -> Driven {
    let Drive {
        spp,
        seed,
        tile,
        order_seed,
        policy,
        restarts,
        records,
    } = drive;
    let (w, h) = (scene.width, scene.height);
    let budget = Budget::Spp(spp);
    let (mut session, _) = new_session(scene, params, (spp, seed), tile.max(1), policy);
    let (nworkers, per_iteration) = match records {
        RecordsAt::Tiles => (1, false),
        RecordsAt::Iteration { workers } => (workers, true),
    };
    let records_mode = |s: &mut Session| {
        if per_iteration {
            s.set_records(Records::PerIteration);
        }
    };
    records_mode(&mut session);
    let fresh = || -> Vec<WorkerTree> {
        (0..nworkers)
            .map(|_| WorkerTree {
                version: None,
                tree: None,
            })
            .collect()
    };
    // A coordinator restarted between iterations continues from the checkpoint alone.
    let restart = |session: &mut Session| -> bool {
        let Some(cp) = session.checkpoint() else {
            return false;
        };
        let bytes = cp.to_bytes(&session.tree().encode());
        let (cp, tree) = Checkpoint::from_bytes(&bytes).expect("read back");
        let tiles = Region::tiles(w, h, tile.max(1));
        let splatting = splatting(scene, seed);
        *session =
            Session::restore(params, budget, tiles, splatting, policy, &cp, tree).expect("restore");
        records_mode(session);
        true
    };
    let mut restored = 0;
    let mut collected = 0;
    let mut workers = fresh();
    let mut kinds = Vec::new();
    let mut overlapped = 0;
    let mut probes_beside = 0;
    let mut flights: Vec<Flight> = Vec::new();
    let mut pick = TestRng::new(order_seed);
    let mut clock = 0.0;
    loop {
        loop {
            let spec = match session.next(clock) {
                Next::Render(spec) => spec,
                Next::Records => {
                    collect_records(&mut session, &mut workers, &mut pick);
                    collected += 1;
                    if restarts == Restarts::AtEveryCheckpoint && restart(&mut session) {
                        workers = fresh();
                        restored += 1;
                    }
                    continue;
                }
                Next::Wait | Next::Done => break,
            };
            kinds.push(spec.kind);
            overlapped += usize::from(!flights.is_empty());
            probes_beside += usize::from(!flights.is_empty() && spec.kind == PassKind::Probe);
            if tile == 0 {
                let edge = 3 + (spec.unit % 11) as u32;
                session.retile(Region::tiles(w, h, edge)).expect("retile");
            }
            let tiles = session.tiles().to_vec();
            let mut order: Vec<usize> = (0..tiles.len()).collect();
            TestRng::new(order_seed ^ spec.unit.wrapping_mul(0x9e37_79b9_7f4a_7c15))
                .shuffle(&mut order);
            flights.push(Flight {
                spec,
                tiles,
                fractions: session.tree().fraction_states(),
                estimate: session.estimate().to_vec(),
                order,
            });
        }
        if flights.is_empty() {
            break;
        }
        let f = pick.index(flights.len());
        let flight = &mut flights[f];
        let index = flight.order.pop().expect("a flight has tiles left");
        let spec = flight.spec;
        let wt = workers[pick.index(nworkers)].get(session.tree(), flight);
        let inputs = UnitInputs {
            scene,
            params,
            tree: wt,
            estimate: &flight.estimate,
            seed,
            tile_size: 5,
        };
        let mut out = render_unit(&inputs, &spec, flight.tiles[index], &|_| {});
        if let (TilePixels::Samples(v), Some(plan), true) = (
            &out.pixels,
            session.splat_plan(spec.unit),
            index.is_multiple_of(2),
        ) {
            // every other tile prepared apart, as a farm coordinator prepares them
            let prepared = plan.prepare(flight.tiles[index], v);
            out.pixels = TilePixels::Prepared(Box::new(prepared));
        }
        let stats = match per_iteration {
            false => spec.record().then(|| wt.take_stats()),
            true => spec.record().then(|| wt.take_gradients()),
        };
        if flight.order.is_empty() {
            flights.remove(f);
        }
        clock += 0.001;
        session
            .add_tile(spec.unit, index, &out, stats.as_ref(), clock)
            .expect("tile accepted");
        if restarts == Restarts::AtEveryCheckpoint && restart(&mut session) {
            workers = fresh();
            restored += 1;
        }
    }
    if per_iteration {
        // one collection before every refinement, and one at the end when the last
        // training iteration was not refined (restarts aside: a restored session starts
        // counting again from its checkpoint's version)
        let refined = session.tree_version() as usize;
        assert!(collected >= 1, "records were collected");
        if restarts == Restarts::Never {
            let expected = refined..=refined + 1;
            assert!(expected.contains(&collected), "{collected} for {refined}");
        }
    }
    if restarts == Restarts::AtEveryCheckpoint {
        assert!(
            restored >= 1,
            "the job restarted between iterations ({restored} times)"
        );
    }
    let (film, stats, tree) = session.finish();
    Driven {
        film,
        tree,
        kinds,
        overlapped,
        probes_beside,
        iterations: stats.iterations,
    }
}

/// Hands the session every worker's records of the iteration (those whose tree is the
/// session's version: a worker that took no tile of the iteration has none), in a random
/// order, then says they are in.
fn collect_records(session: &mut Session, workers: &mut [WorkerTree], pick: &mut TestRng) {
    let mut order: Vec<usize> = (0..workers.len()).collect();
    pick.shuffle(&mut order);
    let version = session.tree_version();
    for i in order {
        let w = &mut workers[i];
        if w.version.map(|v| v.0) != Some(version) {
            continue;
        }
        let records = w
            .tree
            .as_mut()
            .expect("a versioned worker has a tree")
            .take_stats();
        session.add_records(&records).expect("records accepted");
    }
    session.records_in().expect("collecting");
    assert!(
        session.add_records(&Default::default()) == Err(RecordsError::NotCollecting),
        "records outside a collection are refused"
    );
}

/// What a session of `scene` splats sample-form units with, for a job of `seed`.
fn splatting(scene: &Scene, seed: u64) -> Splatting {
    Splatting {
        filter: scene.filter,
        seed,
    }
}

/// A fresh session of `scene` with `params` (an untrained tree of the scene's bounds) for
/// `spp` samples per pixel with `seed`, over `tile`-pixel tiles, and those tiles.
fn new_session(
    scene: &Scene,
    params: &GuidedParams,
    (spp, seed): (u32, u64),
    tile: u32,
    policy: FallbackPolicy,
) -> (Session, Vec<Region>) {
    let (lo, hi) = scene.world().accel.bounds();
    let tree = SdTree::new(lo, hi, guide_config(params, scene));
    let (w, h) = (scene.width, scene.height);
    let tiles = Region::tiles(w, h, tile);
    let budget = Budget::Spp(spp);
    let splat = splatting(scene, seed);
    let session = Session::new(params, budget, tree, (w, h), splat, tiles.clone(), policy);
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
    let base = Drive {
        spp: 24,
        seed: 7,
        tile: 8,
        order_seed: 1,
        policy,
        restarts: Restarts::Never,
        records: RecordsAt::Tiles,
    };
    let d = render_tiled(&scene, &params, base);
    assert!(d.kinds.contains(&PassKind::Record) && d.kinds.contains(&PassKind::Guided));
    assert_same(&(d.film, d.tree), &single, "pathfarm preset, 8-pixel tiles");
    // another tiling and another arrival order: the same bits
    let d = render_tiled(
        &scene,
        &params,
        Drive {
            tile: 13,
            order_seed: 99,
            ..base
        },
    );
    assert_same(&(d.film, d.tree), &single, "13-pixel tiles");
    // every unit tiled differently
    let d = render_tiled(
        &scene,
        &params,
        Drive {
            tile: 0,
            order_seed: 5,
            ..base
        },
    );
    assert_same(&(d.film, d.tree), &single, "a tiling per unit");
    // restarted from a checkpoint after every iteration: the same bits
    let restarted = Drive {
        order_seed: 3,
        restarts: Restarts::AtEveryCheckpoint,
        ..base
    };
    let d = render_tiled(&scene, &params, restarted);
    assert_same(&(d.film, d.tree), &single, "restarted at every checkpoint");
    // the tree learned something (the test would be vacuous on an empty tree)
    assert!(single.1.stats().leaves > 1, "{:?}", single.1.stats());
    overlapping_passes_keep_the_bits(&scene, &params, base, "guiding kept, overlapping");
}

/// Guiding kept (no fallback at `base`'s budget): the training passes overlap, and the
/// tiled drive still gives the one-process bits.
fn overlapping_passes_keep_the_bits(scene: &Scene, params: &GuidedParams, base: Drive, what: &str) {
    let keep = FallbackPolicy::Force(GuidingVerdict::Keep);
    let single = one_process(scene, params, base.spp, base.seed, keep);
    let overlapping = Drive {
        order_seed: 4,
        policy: keep,
        ..base
    };
    let d = render_tiled(scene, params, overlapping);
    d.assert_overlapped(2);
    assert_same(&(d.film, d.tree), &single, what);
}

#[test]
fn records_collected_once_an_iteration_from_several_workers_give_one_process_bits() {
    // Workers ship each tile's fraction gradients with it and their quadtree records once
    // an iteration, when the session asks (Records::PerIteration), in any order.
    let scene = door_ajar((37, 23));
    let params = scene.guided.clone().expect("guided");
    let policy = FallbackPolicy::Rule;
    let three = RecordsAt::Iteration { workers: 3 };
    let single = one_process(&scene, &params, 24, 7, policy);
    let base = Drive {
        spp: 24,
        seed: 7,
        tile: 8,
        order_seed: 1,
        policy,
        restarts: Restarts::Never,
        records: three,
    };
    let d = render_tiled(&scene, &params, base);
    assert_same(&(d.film, d.tree), &single, "records per iteration");
    let restarted = Drive {
        tile: 0,
        order_seed: 6,
        restarts: Restarts::AtEveryCheckpoint,
        ..base
    };
    let d = render_tiled(&scene, &params, restarted);
    assert_same(
        &(d.film, d.tree),
        &single,
        "records per iteration, restarted",
    );
    let what = "records per iteration, overlapping";
    overlapping_passes_keep_the_bits(&scene, &params, base, what);
    let fall = FallbackPolicy::Force(GuidingVerdict::FallBack);
    let single = one_process(&scene, &params, 24, 3, fall);
    let two = RecordsAt::Iteration { workers: 2 };
    let fallen = Drive {
        seed: 3,
        tile: 6,
        order_seed: 5,
        policy: fall,
        records: two,
        ..base
    };
    let d = render_tiled(&scene, &params, fallen);
    assert!(d.kinds.contains(&PassKind::Probe), "{:?}", d.kinds);
    assert_same(
        &(d.film, d.tree),
        &single,
        "records per iteration, fallback",
    );
}

#[test]
fn tiled_session_equals_one_process_through_the_path_fallback() {
    // Forced fallback: probe passes and the plain path-tracing rest are tiled too.
    let scene = door_ajar((29, 17));
    let params = scene.guided.clone().expect("guided");
    let policy = FallbackPolicy::Force(GuidingVerdict::FallBack);
    let single = one_process(&scene, &params, 24, 3, policy);
    let d = render_tiled(
        &scene,
        &params,
        Drive {
            spp: 24,
            seed: 3,
            tile: 6,
            order_seed: 5,
            policy,
            restarts: Restarts::AtEveryCheckpoint,
            records: RecordsAt::Tiles,
        },
    );
    assert!(d.kinds.contains(&PassKind::Probe), "{:?}", d.kinds);
    assert!(d.kinds.contains(&PassKind::Path), "{:?}", d.kinds);
    assert_same(&(d.film, d.tree), &single, "forced fallback");
}

#[test]
fn a_probe_beside_its_iterations_last_unit_gives_the_fallback_rule_one_process_numbers() {
    // The path fallback's own rule, and probes issued while the iteration they check still
    // renders, their tiles handed in among its last unit's: every iteration's accounts
    // (rays a sample, which the rule weighs), the image and the tree must be one process's.
    let scene = door_ajar((29, 17));
    let params = scene.guided.clone().expect("guided");
    assert!(params.path_fallback, "the preset checks its iterations");
    let (spp, seed) = (24, 3);
    let settings = RenderSettings::new(Some(spp), None, seed);
    let options = GuidedOptions::default();
    let (film, stats, tree) = render_guided(&scene, &params, Budget::Spp(spp), &settings, options);
    let mut beside = 0;
    for order_seed in [5, 6, 7] {
        let d = render_tiled(
            &scene,
            &params,
            Drive {
                spp,
                seed,
                tile: 6,
                order_seed,
                policy: FallbackPolicy::Rule,
                restarts: Restarts::Never,
                records: RecordsAt::Tiles,
            },
        );
        beside += d.probes_beside;
        let rays = |its: &[pathfarm_render::guided::GuidedIteration]| -> Vec<u64> {
            its.iter().map(|i| i.rays_per_sample.to_bits()).collect()
        };
        assert_eq!(
            rays(&d.iterations),
            rays(&stats.iterations),
            "order {order_seed}"
        );
        let what = format!("probes beside, order {order_seed}");
        assert_same(&(d.film, d.tree), &(film.clone(), tree.clone()), &what);
    }
    assert!(
        beside >= 1,
        "no probe was issued beside its iteration's last unit"
    );
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
    let d = render_tiled(
        &scene,
        &params,
        Drive {
            spp: 40,
            seed: 11,
            tile: 7,
            order_seed: 2,
            policy,
            restarts: Restarts::Never,
            records: RecordsAt::Tiles,
        },
    );
    d.assert_overlapped(4);
    assert_same(
        &(d.film, d.tree),
        &single,
        "stochastic filter, kickstart, automatic",
    );
}

#[test]
fn damaged_checkpoints_are_refused() {
    let scene = door_ajar((8, 8));
    let params = scene.guided.clone().expect("guided");
    let (s, tiles) = new_session(&scene, &params, (8, 1), 8, FallbackPolicy::Rule);
    let cp = s.checkpoint().expect("a fresh session can be checkpointed");
    let bytes = cp.to_bytes(&s.tree().encode());
    let restore = |b: &[u8]| {
        let (cp, tree) = Checkpoint::from_bytes(b)?;
        Session::restore(
            &params,
            Budget::Spp(8),
            tiles.clone(),
            splatting(&scene, 1),
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
    let (mut s, tiles) = new_session(&scene, &params, (8, 1), 8, FallbackPolicy::Rule);
    let Next::Render(spec) = s.next(0.0) else {
        panic!("a first unit")
    };
    assert_eq!(
        s.next(0.0),
        Next::Wait,
        "iteration 0 is one pass: nothing overlaps it"
    );
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
    // iteration 0 renders 1 spp: its tiles are samples, not sums
    assert!(spec.sample_form());
    let sums = pathfarm_render::pass::TileOutput {
        pixels: TilePixels::Sums(Film::new(tiles[0].width(), tiles[0].height())),
        ..out0.clone()
    };
    assert!(matches!(
        s.add_tile(spec.unit, 0, &sums, None, 0.0),
        Err(pathfarm_render::session::TileError::WrongPixels { index: 0, .. })
    ));
    let TilePixels::Samples(mut short) = out0.pixels.clone() else {
        panic!("samples")
    };
    short.pop();
    let short = pathfarm_render::pass::TileOutput {
        pixels: TilePixels::Samples(short),
        ..out0.clone()
    };
    assert!(matches!(
        s.add_tile(spec.unit, 0, &short, None, 0.0),
        Err(pathfarm_render::session::TileError::WrongPixels { index: 0, .. })
    ));
    s.add_tile(spec.unit, 0, &out0, None, 0.0).expect("first");
    assert_eq!(
        s.add_tile(spec.unit, 0, &out0, None, 0.0),
        Err(pathfarm_render::session::TileError::Duplicate(0))
    );
    s.add_tile(spec.unit, 1, &out1, None, 0.0).expect("second");
    assert_eq!(s.tiles_done(), (2, 4));
}

#[test]
fn a_unit_whose_tiles_are_all_in_first_waits_for_the_unit_before_it() {
    let scene = door_ajar((12, 8));
    let mut params = scene.guided.clone().expect("guided");
    params.path_fallback = false;
    let (mut s, tiles) = new_session(&scene, &params, (16, 1), 4, FallbackPolicy::Rule);
    let mut worker = WorkerTree {
        version: None,
        tree: None,
    };
    // renders every tile of `unit` on the worker copy and hands them in
    let hand_in = |s: &mut Session, unit: &Flight, worker: &mut WorkerTree| {
        for (i, &tile) in unit.tiles.iter().enumerate() {
            let wt = worker.get(s.tree(), unit);
            let inputs = UnitInputs {
                scene: &scene,
                params: &params,
                tree: wt,
                estimate: &unit.estimate,
                seed: 5,
                tile_size: 4,
            };
            let out = render_unit(&inputs, &unit.spec, tile, &|_| {});
            let stats = unit.spec.record().then(|| wt.take_stats());
            s.add_tile(unit.spec.unit, i, &out, stats.as_ref(), 0.0)
                .expect("accepted");
        }
    };
    let flight = |s: &Session, spec: PassSpec| Flight {
        spec,
        tiles: tiles.clone(),
        fractions: s.tree().fraction_states(),
        estimate: s.estimate().to_vec(),
        order: Vec::new(),
    };
    // units one at a time until the session issues a second one beside the first
    let (first, second) = loop {
        let Next::Render(spec) = s.next(0.0) else {
            panic!("the job ended without overlapping passes")
        };
        let unit = flight(&s, spec);
        if let Next::Render(next) = s.next(0.0) {
            break (unit, flight(&s, next));
        }
        hand_in(&mut s, &unit, &mut worker);
    };
    assert_eq!(second.spec.unit, first.spec.unit + 1);
    assert_eq!(
        second.spec.fraction_version, first.spec.fraction_version,
        "the second unit samples without the first unit's step"
    );
    assert_eq!(s.next(0.0), Next::Wait, "two units in flight at most");
    let spp = s.spp_done();
    hand_in(&mut s, &second, &mut worker);
    assert_eq!(
        s.spp_done(),
        spp,
        "the later unit does not end before the earlier one"
    );
    assert_eq!(s.next(0.0), Next::Wait);
    hand_in(&mut s, &first, &mut worker);
    assert_eq!(s.spp_done(), spp + 2, "both units ended");
    assert_eq!(s.tiles_done(), (0, tiles.len()));
}
