//! The farm's two state machines together, without sockets: several guided job sessions
//! driven through the lease scheduler on an injected clock, by simulated workers that join,
//! die, hang (stop heartbeating, so their leases expire) and deliver late (their results are
//! then stale and rejected), in a seeded random schedule, with two units of a job in flight
//! whenever its session overlaps training passes. The workers keep their quadtree records
//! and hand them over once an iteration, as the farm's do (`Records::PerIteration`: only
//! accepted results' records are kept; a job whose holder dies starts again from its last
//! checkpoint under a new records epoch). Every job that is not cancelled must end with the
//! image and tree of the one-process render, bit for bit (deterministic checks, no
//! significance level); the cancelled job must take no more tiles.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::time::Duration;

use pathfarm_farm::scheduler::{
    Event, JobId, LeaseId, Millis, Rejection, Scheduler, SchedulerConfig, WorkerId,
};
use pathfarm_guide::fraction::FractionState;
use pathfarm_guide::IterationStats;
use pathfarm_guide::SdTree;
use pathfarm_render::checkpoint::Checkpoint;
use pathfarm_render::guided::{
    guide_config, render_guided, Budget, FallbackPolicy, GuidedOptions, GuidingVerdict, Next,
    Records, Session, Splatting,
};
use pathfarm_render::pass::{render_unit, PassSpec, TileOutput, UnitInputs};
use pathfarm_render::{Film, Region, RenderSettings, Scene};
use pathfarm_scene::GuidedParams;

use crate::common::*;

/// A unit in flight and the fractions published with it.
struct Flight {
    spec: PassSpec,
    fractions: Vec<FractionState>,
}

/// A job as the driver holds it: its session and the units in flight.
struct SimJob {
    seed: u64,
    spp: u32,
    params: GuidedParams,
    splatting: Splatting,
    policy: FallbackPolicy,
    session: Session,
    flights: Vec<Flight>,
    /// Units issued while another was in flight.
    overlapped: usize,
    /// The tree as published for the unit's tree version: encoded when the version's first
    /// unit is offered (its building statistics empty), as the coordinator publishes it.
    published: (u32, Vec<u8>),
    done: bool,
    cancelled: bool,
    /// The workers whose recording results of the current tree version were accepted.
    holders: BTreeSet<u64>,
    /// The session asked for the iteration's records (`Next::Records`).
    collecting: bool,
    /// The records epoch of the session's results; a roll back starts a new one.
    epoch: u64,
    /// The last checkpoint (state and tree), as the coordinator stores it.
    checkpoint: Option<Vec<u8>>,
    rollbacks: usize,
}

/// Which records a result's are: the job's tree version and records epoch.
type RecordsKey = (u32, u64);

/// A result a worker computed and will deliver at `due`.
struct Pending {
    lease: LeaseId,
    job: JobId,
    unit: u64,
    tile: u32,
    due: Millis,
    out: TileOutput,
    /// The fraction gradients, uploaded with the tile.
    stats: Option<IterationStats>,
    /// The quadtree records, kept by the worker if the result is accepted.
    records: Option<(RecordsKey, IterationStats)>,
}

struct SimWorker {
    /// Per job: the tree copy and the (tree, fraction) version it holds.
    trees: HashMap<u64, ((u32, u32), SdTree)>,
    pending: Vec<Pending>,
    /// A hung worker neither heartbeats nor delivers until it resumes.
    hung_until: Option<Millis>,
    /// Per job, the records of its accepted results, by tree version and epoch.
    held: HashMap<u64, (RecordsKey, IterationStats)>,
}

impl SimWorker {
    /// The worker's copy of `job`'s tree for `unit`: a new tree version is decoded from
    /// the published bytes, new fractions are those published with the unit.
    fn tree(&mut self, job: u64, j: &SimJob, unit: &Flight) -> &mut SdTree {
        let master = j.session.tree();
        let version = (unit.spec.tree_version, unit.spec.fraction_version);
        let e = self
            .trees
            .entry(job)
            .or_insert_with(|| ((u32::MAX, u32::MAX), master.clone()));
        if e.0 .0 != version.0 {
            assert_eq!(j.published.0, version.0, "the published tree is the unit's");
            e.1 = SdTree::decode(&j.published.1).expect("decode");
        }
        if e.0 != version {
            e.1.set_fraction_states(&unit.fractions)
                .expect("same leaves");
        }
        e.0 = version;
        &mut e.1
    }
}

/// Offers the units a job's session issues to the scheduler, or marks the job done.
fn drive(sched: &mut Scheduler, j: &mut SimJob, id: JobId, now: Millis, tiling: &mut TestRng) {
    while drive_once(sched, j, id, now, tiling) {}
}

fn drive_once(
    sched: &mut Scheduler,
    j: &mut SimJob,
    id: JobId,
    now: Millis,
    tiling: &mut TestRng,
) -> bool {
    match j.session.next(now.0 as f64 * 1e-3) {
        Next::Render(spec) => {
            if j.published.0 != spec.tree_version || j.published.1.is_empty() {
                j.published = (spec.tree_version, j.session.tree().encode());
            }
            // every unit cut differently: the tiling must not matter
            let (w, h) = j.session.size();
            let edge = 3 + tiling.below(9) as u32;
            j.session.retile(Region::tiles(w, h, edge)).expect("retile");
            let n = j.session.tiles().len() as u32;
            sched.offer_unit(id, spec.unit, n).expect("offer");
            j.overlapped += usize::from(!j.flights.is_empty());
            let fractions = j.session.tree().fraction_states();
            j.flights.push(Flight { spec, fractions });
            true
        }
        Next::Wait => false,
        Next::Records => {
            j.collecting = true;
            false
        }
        Next::Done => {
            j.done = true;
            false
        }
    }
}

/// The session's records are wanted: once every holder is alive, awake and has no result
/// of the job still to deliver (so every result's fate is known), each hands over what it
/// kept for the job's version and epoch; then the session refines and is checkpointed.
fn try_collect(
    j: &mut SimJob,
    job: u64,
    workers: &mut BTreeMap<u64, SimWorker>,
    now: Millis,
) -> bool {
    let ready = j.holders.iter().all(|h| {
        workers.get(h).is_some_and(|w| {
            w.hung_until.is_none_or(|t| now >= t) && w.pending.iter().all(|p| p.job.0 != job)
        })
    });
    if !ready {
        return false;
    }
    let key = (j.session.tree_version(), j.epoch);
    for h in std::mem::take(&mut j.holders) {
        let w = workers.get_mut(&h).expect("checked");
        let (k, records) = w.held.remove(&job).expect("a holder keeps records");
        assert_eq!(
            k, key,
            "a holder's records are of the version and epoch collected"
        );
        j.session.add_records(&records).expect("records accepted");
    }
    j.session.records_in().expect("collecting");
    j.collecting = false;
    checkpoint(j);
    true
}

/// A worker keeps an accepted result's records: added to those of the same version and
/// epoch, or replacing older ones. The simulation's own copy of the worker's rule
/// (`crates/farm/src/worker/records.rs` `keep`), written apart on purpose: a test that
/// called the product's rule could not catch a mistake in it.
fn keep(
    held: &mut HashMap<u64, (RecordsKey, IterationStats)>,
    job: u64,
    key: RecordsKey,
    r: IterationStats,
) {
    match held.get_mut(&job) {
        Some((k, mine)) if *k == key => mine.merge(&r).expect("one structure"),
        _ => {
            held.insert(job, (key, r));
        }
    }
}

/// Keeps the session's checkpoint, if it can be taken now (between iterations).
fn checkpoint(j: &mut SimJob) {
    if let Some(cp) = j.session.checkpoint() {
        j.checkpoint = Some(cp.to_bytes(&j.session.tree().encode()));
    }
}

/// A holder of job `id`'s records was lost: the job starts again from its last checkpoint
/// (or from the start) under a new records epoch, with new leases.
fn roll_back(sched: &mut Scheduler, j: &mut SimJob, id: JobId, fresh: Session, now: Millis) {
    let session = match &j.checkpoint {
        Some(bytes) => {
            let (cp, tree) = Checkpoint::from_bytes(bytes).expect("read back");
            let (w, h) = j.session.size();
            let tiles = Region::tiles(w, h, 4);
            let mut s = Session::restore(
                &j.params,
                Budget::Spp(j.spp),
                tiles,
                j.splatting,
                j.policy,
                &cp,
                tree,
            )
            .expect("restore");
            s.set_records(Records::PerIteration);
            s
        }
        None => fresh,
    };
    j.session = session;
    j.flights.clear();
    j.holders.clear();
    j.collecting = false;
    j.epoch += 1;
    j.rollbacks += 1;
    j.published = (u32::MAX, Vec::new());
    sched.remove_job(id).expect("remove");
    sched.add_job(id, 0, now).expect("add again");
}

fn one_process(scene: &Scene, spp: u32, seed: u64, policy: FallbackPolicy) -> (Film, SdTree) {
    let params = scene.guided.clone().expect("guided");
    let settings = RenderSettings::new(Some(spp), None, seed);
    let options = GuidedOptions {
        policy,
        ..Default::default()
    };
    let (film, _, tree) = render_guided(scene, &params, Budget::Spp(spp), &settings, options);
    (film, tree)
}

/// Half the jobs keep guiding whatever the fallback check says: at these tiny budgets the
/// rule falls back early, and the kept ones train long enough for passes to overlap.
fn policy_of(job: u64) -> FallbackPolicy {
    match job % 2 {
        0 => FallbackPolicy::Rule,
        _ => FallbackPolicy::Force(GuidingVerdict::Keep),
    }
}

#[test]
fn random_schedule_of_joins_deaths_hangs_and_late_results_gives_one_process_bits() {
    let scene = door_ajar((17, 11));
    let params = scene.guided.clone().expect("guided");
    let config = SchedulerConfig {
        lease_timeout: Duration::from_millis(400),
        heartbeat_timeout: Duration::from_millis(1500),
        max_attempts: 1000,
        leases_per_worker: 3,
        ..SchedulerConfig::default()
    };
    for sim_seed in [1u64, 2, 3] {
        let mut rng = TestRng::new(sim_seed * 0x1234_5678);
        let mut tiling = TestRng::new(sim_seed ^ 0xabcd);
        let mut sched = Scheduler::new(config.clone());
        let mut now = Millis(0);
        let mut jobs: BTreeMap<u64, SimJob> = BTreeMap::new();
        let new_session = |n: u64, seed: u64, spp: u32| {
            let (lo, hi) = scene.accel.bounds();
            let tree = SdTree::new(lo, hi, guide_config(&params, &scene));
            let tiles = Region::tiles(scene.width, scene.height, 4);
            let splatting = Splatting {
                filter: scene.filter,
                seed,
            };
            let size = (scene.width, scene.height);
            let policy = policy_of(n);
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
            s
        };
        for (n, (seed, spp)) in [(3u64, 12u32), (7, 16), (11, 8), (13, 12)]
            .iter()
            .enumerate()
        {
            let session = new_session(n as u64, *seed, *spp);
            let id = JobId(n as u64);
            sched
                .add_job(id, rng.below(3) as i32, now)
                .expect("add job");
            let mut j = SimJob {
                seed: *seed,
                spp: *spp,
                params: params.clone(),
                splatting: Splatting {
                    filter: scene.filter,
                    seed: *seed,
                },
                policy: policy_of(n as u64),
                session,
                flights: Vec::new(),
                overlapped: 0,
                published: (0, Vec::new()),
                done: false,
                cancelled: false,
                holders: BTreeSet::new(),
                collecting: false,
                epoch: 0,
                checkpoint: None,
                rollbacks: 0,
            };
            drive(&mut sched, &mut j, id, now, &mut tiling);
            jobs.insert(n as u64, j);
        }
        let cancel_job = 2u64;
        let cancel_at = 10 + rng.below(20);
        let mut workers: BTreeMap<u64, SimWorker> = BTreeMap::new();
        let mut next_worker = 0u64;
        let (mut deaths, mut stale, mut accepted_after_cancel) = (0, 0, 0);
        for step in 0..200_000u64 {
            if jobs.values().all(|j| j.done || j.cancelled) {
                break;
            }
            assert!(step < 199_999, "seed {sim_seed}: the jobs did not finish");
            now = Millis(now.0 + 1 + rng.below(40));
            // joins and deaths
            if workers.len() < 4 && (workers.is_empty() || rng.chance(0.03)) {
                let id = WorkerId(next_worker);
                next_worker += 1;
                sched.register_worker(id, 1, now).expect("register");
                let w = SimWorker {
                    trees: HashMap::new(),
                    pending: Vec::new(),
                    hung_until: None,
                    held: HashMap::new(),
                };
                workers.insert(id.0, w);
            }
            if workers.len() > 1 && rng.chance(0.04) {
                let ids: Vec<u64> = workers.keys().copied().collect();
                let victim = ids[rng.below(ids.len() as u64) as usize];
                workers.remove(&victim);
                let _ = sched.worker_lost(WorkerId(victim));
                deaths += 1;
                // its kept records died with it
                for (&n, j) in jobs.iter_mut() {
                    if !j.done && !j.cancelled && j.holders.contains(&victim) {
                        let fresh = new_session(n, j.seed, j.spp);
                        roll_back(&mut sched, j, JobId(n), fresh, now);
                        drive(&mut sched, j, JobId(n), now, &mut tiling);
                    }
                }
            }
            // a worker hangs for a while (no heartbeats: its leases expire)
            if rng.chance(0.04) {
                let ids: Vec<u64> = workers.keys().copied().collect();
                let w = ids[rng.below(ids.len() as u64) as usize];
                let until = Millis(now.0 + 200 + rng.below(1000));
                workers.get_mut(&w).unwrap().hung_until = Some(until);
            }
            if step == cancel_at {
                let j = jobs.get_mut(&cancel_job).unwrap();
                if !j.done {
                    sched.cancel_job(JobId(cancel_job)).expect("cancel");
                    j.cancelled = true;
                }
            }
            // each live worker: heartbeat, take leases, deliver what is due
            let ids: Vec<u64> = workers.keys().copied().collect();
            for wid in ids {
                let w = workers.get_mut(&wid).unwrap();
                if w.hung_until.is_some_and(|t| now < t) {
                    continue;
                }
                w.hung_until = None;
                let held: Vec<LeaseId> = w.pending.iter().map(|p| p.lease).collect();
                let _ = sched.heartbeat(WorkerId(wid), &held, now);
                while let Some(lease) = sched.next_lease(WorkerId(wid), now) {
                    let job = lease.key.job;
                    let j = &jobs[&job.0];
                    let unit = j.flights.iter().find(|f| f.spec.unit == lease.key.unit);
                    let unit = unit.expect("a unit in flight");
                    let spec = unit.spec;
                    let tiles = j.session.tiles_of(spec.unit).expect("in flight");
                    let region = tiles[lease.key.tile as usize];
                    let estimate = j.session.estimate().to_vec();
                    let seed = j.seed;
                    let key = (spec.tree_version, j.epoch);
                    let tree = w.tree(job.0, j, unit);
                    let inputs = UnitInputs {
                        scene: &scene,
                        params: &params,
                        tree,
                        estimate: &estimate,
                        seed,
                        tile_size: 4,
                    };
                    let out = render_unit(&inputs, &spec, region, &|_| {});
                    // the gradients go with the tile, the records stay with the worker
                    let (stats, records) = match spec.record() {
                        false => (None, None),
                        true => {
                            let (g, r) = tree.take_stats().split_gradients();
                            (Some(g), Some((key, r)))
                        }
                    };
                    // mostly prompt, sometimes later than the lease lives
                    let delay = if rng.chance(0.15) {
                        500 + rng.below(800)
                    } else {
                        rng.below(60)
                    };
                    w.pending.push(Pending {
                        lease: lease.id,
                        job,
                        unit: lease.key.unit,
                        tile: lease.key.tile,
                        due: Millis(now.0 + delay),
                        out,
                        stats,
                        records,
                    });
                }
                let (due, later): (Vec<Pending>, Vec<Pending>) =
                    w.pending.drain(..).partition(|p| p.due <= now);
                w.pending = later;
                for p in due {
                    match sched.complete(WorkerId(wid), p.lease, now) {
                        Ok(c) => {
                            let j = jobs.get_mut(&p.job.0).unwrap();
                            accepted_after_cancel += j.cancelled as u32;
                            j.session
                                .add_tile(
                                    p.unit,
                                    p.tile as usize,
                                    &p.out,
                                    p.stats.as_ref(),
                                    now.0 as f64 * 1e-3,
                                )
                                .expect("the session takes what the scheduler accepted");
                            if let Some((key, r)) = p.records {
                                keep(&mut w.held, p.job.0, key, r);
                                j.holders.insert(wid);
                            }
                            if c.unit_done {
                                j.flights.retain(|f| f.spec.unit != p.unit);
                                drive(&mut sched, j, p.job, now, &mut tiling);
                            }
                        }
                        Err(
                            Rejection::Expired
                            | Rejection::Superseded
                            | Rejection::UnknownLease
                            | Rejection::JobGone,
                        ) => stale += 1,
                        Err(r) => panic!("seed {sim_seed}: unexpected rejection {r:?}"),
                    }
                }
            }
            for e in sched.tick(now) {
                if let Event::JobFailed { job, reason } = e {
                    panic!("seed {sim_seed}: {job} failed: {reason}");
                }
            }
            for (&n, j) in jobs.iter_mut() {
                if j.collecting && !j.cancelled && try_collect(j, n, &mut workers, now) {
                    drive(&mut sched, j, JobId(n), now, &mut tiling);
                }
            }
        }
        assert!(
            deaths >= 1 && stale >= 1,
            "seed {sim_seed}: the schedule had faults ({deaths} deaths, {stale} stale results)"
        );
        assert_eq!(accepted_after_cancel, 0, "a cancelled job takes no tiles");
        let rollbacks: usize = jobs.values().map(|j| j.rollbacks).sum();
        assert!(
            rollbacks >= 1,
            "seed {sim_seed}: a job rolled back after a holder died"
        );
        let overlapped: usize = jobs.values().map(|j| j.overlapped).sum();
        assert!(
            overlapped >= 2,
            "seed {sim_seed}: units overlapped {overlapped} times"
        );
        for (n, j) in jobs {
            if j.cancelled {
                continue;
            }
            let (film, _, tree) = j.session.finish();
            let (ref_film, ref_tree) = one_process(&scene, j.spp, j.seed, policy_of(n));
            assert!(
                film_bits(&film) == film_bits(&ref_film),
                "seed {sim_seed}, job {n}: the image differs from the one-process render"
            );
            assert!(
                tree.encode() == ref_tree.encode(),
                "seed {sim_seed}, job {n}: the tree differs from the one-process render"
            );
        }
    }
}
