//! The farm's logic without sockets: the shipped per-job driver
//! ([`pathfarm_farm::driver::JobDriver`]) and lease scheduler, both as the coordinator runs
//! them, on an injected clock, with simulated workers that join, die, hang (stop
//! heartbeating, so their leases expire) and deliver late (their results are then stale and
//! rejected), in a seeded random schedule; and hostile ones: workers that send garbage
//! (non-finite pixel sums, tiles of the wrong region, statistics for a unit that records
//! nothing), hoarders that heartbeat their leases and never upload, and silent workers
//! that take leases and never speak again. Jobs start at different times (slow setup), and
//! one is cancelled.
//!
//! The coordinator's glue is repeated here only where it is transport: inputs travel in the
//! forms workers fetch (encoded by the driver), tiles through the codec's upload form, and a
//! refused upload hands its leases back and is blamed on its sender under the shipped
//! [`Blocklist`] rule. The workers keep their quadtree records and hand them over when
//! asked, as the farm's do; a job whose holder dies, or does not answer in time, starts
//! again from its last checkpoint under a new records epoch.
//!
//! Every job that is not cancelled must end with the image and tree of the one-process
//! render, bit for bit (deterministic checks, no significance level); the cancelled job must
//! take no more tiles, and no honest worker may be blocked.

use std::collections::{BTreeMap, HashMap};
use std::time::Duration;

use pathfarm_farm::codec;
use pathfarm_farm::driver::{
    Blame, Blocklist, Coverage, JobDriver, Standing, Step, TileIn, Tiling,
};
use pathfarm_farm::scheduler::{
    Event, JobId, LeaseId, Millis, Rejection, Scheduler, SchedulerConfig, WorkerId,
};
use pathfarm_farm::tiling::CostMap;
use pathfarm_guide::IterationStats;
use pathfarm_guide::SdTree;
use pathfarm_render::checkpoint::Checkpoint;
use pathfarm_render::guided::{
    guide_config, render_guided, Budget, FallbackPolicy, GuidedOptions, GuidingVerdict, Records,
    Session, Splatting,
};
use pathfarm_render::pass::{render_unit, PassSpec, TileOutput, TilePixels, UnitInputs};
use pathfarm_render::{Film, Region, RenderSettings, Scene};

use crate::common::*;

/// A job as the coordinator holds it: its driver (once set up), and the inputs it
/// published, by version, in the forms workers fetch.
struct SimJob {
    seed: u64,
    spp: u32,
    /// When its (slow) setup ends and its driver starts.
    starts: Millis,
    driver: Option<JobDriver>,
    epoch: u64,
    trees: HashMap<u32, Vec<u8>>,
    fractions: HashMap<(u32, u32), Vec<u8>>,
    estimate: Vec<u8>,
    /// The last checkpoint (state and tree), as the coordinator stores it.
    checkpoint: Option<Vec<u8>>,
    blocklist: Blocklist,
    done: Option<(Film, SdTree)>,
    cancelled: bool,
    overlapped: usize,
    rollbacks: usize,
}

/// Which records a result's are: the job's tree version and records epoch.
type RecordsKey = (u32, u64);

/// What a worker does with what it is given.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Honest,
    /// Every other upload is garbage.
    Garbage,
    /// Heartbeats its leases, never uploads.
    Hoarder,
    /// Takes leases, never heartbeats or uploads.
    Silent,
}

/// A result a worker computed and will deliver at `due`.
struct Pending {
    lease: LeaseId,
    job: u64,
    unit: u64,
    tile: u32,
    due: Millis,
    spec: PassSpec,
    out: TileOutput,
    /// The fraction gradients, uploaded with the tile.
    stats: Option<IterationStats>,
    /// The quadtree records, kept by the worker if the result is accepted.
    records: Option<(RecordsKey, IterationStats)>,
}

struct SimWorker {
    kind: Kind,
    /// Per job: its tree copy and the (epoch, tree, fraction) version it holds.
    trees: HashMap<u64, ((u64, u32, u32), SdTree)>,
    pending: Vec<Pending>,
    /// Leases a hoarder or silent worker sits on.
    kept: Vec<LeaseId>,
    /// A hung worker neither heartbeats nor delivers until it resumes.
    hung_until: Option<Millis>,
    /// Per job, the records of its accepted results, by tree version and epoch.
    held: HashMap<u64, (RecordsKey, IterationStats, Coverage)>,
    uploads: u64,
}

impl SimWorker {
    fn new(kind: Kind) -> Self {
        Self {
            kind,
            trees: HashMap::new(),
            pending: Vec::new(),
            kept: Vec::new(),
            hung_until: None,
            held: HashMap::new(),
            uploads: 0,
        }
    }

    fn identity(id: u64) -> String {
        format!("sim/worker-{id}")
    }

    /// The worker's copy of `job`'s tree for `spec`, fetched as a worker fetches it: a new
    /// tree version decoded from the published bytes, new fractions from theirs.
    fn tree(&mut self, job: u64, j: &SimJob, spec: &PassSpec) -> &mut SdTree {
        let version = (j.epoch, spec.tree_version, spec.fraction_version);
        let tree_bytes = |v: u32| j.trees.get(&v).expect("the unit's tree was published");
        let e = (self.trees.entry(job)).or_insert_with(|| {
            let t = SdTree::decode(tree_bytes(version.1)).expect("decode");
            ((u64::MAX, u32::MAX, u32::MAX), t)
        });
        if (e.0 .0, e.0 .1) != (version.0, version.1) {
            e.1 = SdTree::decode(tree_bytes(version.1)).expect("decode");
        }
        if e.0 != version {
            let key = (spec.tree_version, spec.fraction_version);
            let bytes = j
                .fractions
                .get(&key)
                .expect("the unit's fractions were published");
            let states = codec::decode_fractions(bytes).expect("decode");
            e.1.set_fraction_states(&states).expect("same leaves");
        }
        e.0 = version;
        &mut e.1
    }
}

/// Steps a job's driver until it waits, doing what it says as the coordinator does.
fn drive(sched: &mut Scheduler, j: &mut SimJob, id: u64, now: Millis, slots: usize) {
    while !j.cancelled {
        let Some(d) = j.driver.as_mut() else {
            return;
        };
        match d.step(now, slots).expect("the driver steps") {
            Step::Wait | Step::Collect(_) => return,
            Step::Offer(o) => {
                let v = (o.spec.tree_version, o.spec.fraction_version);
                if o.new_tree {
                    j.trees.insert(v.0, d.encode_tree());
                }
                if o.new_fractions {
                    j.fractions.insert(v, d.encode_fractions());
                }
                if o.new_estimate {
                    j.estimate = d.encode_estimate();
                }
                j.overlapped += usize::from(d.flights().len() > 1);
                sched
                    .offer_unit(JobId(id), o.spec.unit, o.tiles)
                    .expect("offer");
            }
            Step::IterationEnded { .. } => checkpoint(d, &mut j.checkpoint),
            Step::Done => {
                let (film, _, tree) = j.driver.take().unwrap().into_session().finish();
                j.done = Some((film, tree));
                sched.remove_job(JobId(id)).expect("remove");
                return;
            }
        }
    }
}

/// Keeps the session's checkpoint, if it can be taken now (between iterations).
fn checkpoint(d: &JobDriver, into: &mut Option<Vec<u8>>) {
    if let Some(cp) = d.session().checkpoint() {
        *into = Some(cp.to_bytes(&d.encode_tree()));
    }
}

/// A worker keeps an accepted result's records: added to those of the same version and
/// epoch, or replacing older ones. The simulation's own copy of the worker's rule
/// (`crates/farm/src/worker/records.rs` `keep`), written apart on purpose: a test that
/// called the product's rule could not catch a mistake in it.
fn keep(
    held: &mut HashMap<u64, (RecordsKey, IterationStats, Coverage)>,
    (job, lease): (u64, LeaseId),
    key: RecordsKey,
    r: IterationStats,
) {
    match held.get_mut(&job) {
        Some((k, mine, covered)) if *k == key => {
            mine.merge(&r).expect("one structure");
            covered.add(lease.0);
        }
        // (from before a roll back, acknowledged after the new epoch's)
        Some((k, _, _)) if k.1 > key.1 => {}
        _ => {
            held.insert(job, (key, r, Coverage::of([lease.0])));
        }
    }
}

/// The session job `n` starts from (again): its checkpoint's, or a fresh one.
fn session_of(scene: &Scene, n: u64, seed: u64, spp: u32, checkpoint: Option<&[u8]>) -> Session {
    let params = scene.guided.clone().expect("guided");
    let tiles = Region::tiles(scene.width, scene.height, 4);
    let splatting = Splatting {
        filter: scene.filter,
        seed,
    };
    let mut s = match checkpoint {
        Some(bytes) => {
            let (cp, tree) = Checkpoint::from_bytes(bytes).expect("read back");
            let (budget, policy) = (Budget::Spp(spp), policy_of(n));
            Session::restore(&params, budget, tiles, splatting, policy, &cp, tree).expect("restore")
        }
        None => {
            let (lo, hi) = scene.world().accel.bounds();
            let tree = SdTree::new(lo, hi, guide_config(&params, scene));
            let size = (scene.width, scene.height);
            let budget = Budget::Spp(spp);
            Session::new(&params, budget, tree, size, splatting, tiles, policy_of(n))
        }
    };
    s.set_records(Records::PerIteration);
    s
}

/// Odd jobs cut their units by cost, even ones into fixed tiles of a job's own edge.
fn tiling_of(scene: &Scene, n: u64) -> Tiling {
    match n % 2 {
        1 => Tiling::ByCost(CostMap::new(scene.width, scene.height)),
        _ => Tiling::Fixed(3 + n as u32),
    }
}

/// Job `n` (re)starts under a new epoch: a holder of its records was lost or did not
/// answer. Its leases go, and it is scheduled again.
fn roll_back(sched: &mut Scheduler, scene: &Scene, j: &mut SimJob, n: u64, now: Millis) {
    let session = session_of(scene, n, j.seed, j.spp, j.checkpoint.as_deref());
    j.epoch += 1;
    j.driver = Some(JobDriver::new(session, tiling_of(scene, n), j.epoch, now));
    j.trees.clear();
    j.fractions.clear();
    j.rollbacks += 1;
    sched.remove_job(JobId(n)).expect("remove");
    sched.add_job(JobId(n), 0, now).expect("add again");
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

/// Garbage in one of three forms: a non-finite pixel sum, a tile of another region, or
/// statistics for a unit that records nothing (a non-finite sum when it records).
fn spoil(p: &mut Pending, how: u64) {
    let nan = |p: &mut Pending| match &mut p.out.pixels {
        TilePixels::Sums(film) => film.pixels[0].sum_wl[0] = f64::NAN,
        TilePixels::Samples(v) => v[0].x = f32::NAN,
        TilePixels::Prepared(_) => {
            unreachable!("the simulation renders samples, not prepared ones")
        }
    };
    match how % 3 {
        0 => nan(p),
        1 => p.out.region.x0 += 1,
        _ if p.stats.is_none() => {
            p.stats = Some(IterationStats::default());
        }
        _ => nan(p),
    }
}

/// Counters of what the schedule did, for the assertions that it did it.
#[derive(Default, Debug)]
struct Seen {
    deaths: u32,
    stale: u32,
    refused: u32,
    blocked_hostile: u32,
    blocked_honest: u32,
    accepted_after_cancel: u32,
    expired_hoards: u32,
}

/// A simulated farm: the scheduler, the jobs, the workers.
struct Farm<'a> {
    scene: &'a Scene,
    sched: Scheduler,
    jobs: BTreeMap<u64, SimJob>,
    workers: BTreeMap<u64, SimWorker>,
    next_worker: u64,
    rng: TestRng,
    seen: Seen,
    timeout: Duration,
}

impl Farm<'_> {
    fn slots(&self) -> usize {
        self.workers.len().max(1)
    }

    fn join(&mut self, kind: Kind, now: Millis) {
        let id = self.next_worker;
        self.next_worker += 1;
        self.sched
            .register_worker(WorkerId(id), 1, now)
            .expect("register");
        // A blocked identity stays blocked (it cannot be one here: identities are new).
        self.workers.insert(id, SimWorker::new(kind));
    }

    /// Worker `id` is gone: its leases return; jobs whose records it held restart.
    fn lost(&mut self, id: u64, now: Millis) {
        self.workers.remove(&id);
        self.seen.deaths += 1;
        let events = self.sched.worker_lost(WorkerId(id)).unwrap_or_default();
        self.events(events);
        self.holder_gone(WorkerId(id), now);
    }

    fn holder_gone(&mut self, w: WorkerId, now: Millis) {
        let slots = self.slots();
        for (&n, j) in self.jobs.iter_mut() {
            if j.driver.as_ref().is_some_and(|d| d.holds(w)) {
                roll_back(&mut self.sched, self.scene, j, n, now);
                drive(&mut self.sched, j, n, now, slots);
            }
        }
    }

    fn events(&mut self, events: Vec<Event>) {
        for e in events {
            match e {
                Event::JobFailed { job, reason } => panic!("{job} failed: {reason}"),
                Event::LeaseExpired { worker, .. } => {
                    let kind = self.workers.get(&worker.0).map(|w| w.kind);
                    if matches!(kind, Some(Kind::Hoarder | Kind::Silent)) {
                        self.seen.expired_hoards += 1;
                    }
                }
                _ => {}
            }
        }
    }

    /// The shipped refusal rule: the leases go back, the sender is blamed, and blocked past
    /// the limit.
    fn refuse(&mut self, wid: u64, p: &Pending, now: Millis) {
        self.seen.refused += 1;
        let _ = self.sched.hand_back(WorkerId(wid), &[p.lease], now);
        let j = self.jobs.get_mut(&p.job).unwrap();
        let who = SimWorker::identity(wid);
        let was = j.blocklist.is_blocked(&who);
        if j.blocklist.blame(&who, "bad tile", Blame::Bad) == Standing::Blocked && !was {
            let _ = self.sched.block(WorkerId(wid), JobId(p.job));
            match self.workers[&wid].kind {
                Kind::Honest => self.seen.blocked_honest += 1,
                _ => self.seen.blocked_hostile += 1,
            }
        }
    }

    /// Worker `wid` delivers `p`: checked by the scheduler without committing, decoded from
    /// its upload form, taken by the driver, then committed; refused at any step.
    fn deliver(&mut self, wid: u64, p: Pending, now: Millis) {
        match self.sched.check_all(WorkerId(wid), &[p.lease], now) {
            Ok(()) => {}
            Err(Rejection::Expired | Rejection::Superseded | Rejection::UnknownLease)
            | Err(Rejection::JobGone | Rejection::Duplicate) => {
                self.seen.stale += 1;
                return;
            }
            Err(r) => panic!("unexpected rejection {r:?}"),
        }
        let bytes = codec::encode_tile_pixels(&p.out.pixels);
        let region = {
            let d = self.jobs[&p.job]
                .driver
                .as_ref()
                .expect("a lease of a running job");
            d.session().tiles_of(p.unit).expect("in flight")[p.tile as usize]
        };
        let Ok(pixels) = codec::decode_tile_pixels(&bytes, &p.spec, region) else {
            return self.refuse(wid, &p, now);
        };
        let out = TileOutput {
            pixels,
            ..p.out.clone()
        };
        let tile = TileIn {
            index: p.tile as usize,
            lease: p.lease,
            out: &out,
            render_seconds: 1e-3 * (1 + p.tile % 5) as f64,
        };
        let slots = self.slots();
        let j = self.jobs.get_mut(&p.job).unwrap();
        let d = j.driver.as_mut().unwrap();
        let took = d.tiles_in(WorkerId(wid), p.unit, &[tile], p.stats.as_ref(), now);
        let Ok(ended) = took else {
            return self.refuse(wid, &p, now);
        };
        self.sched
            .complete_all(WorkerId(wid), &[p.lease], now)
            .expect("checked");
        self.seen.accepted_after_cancel += j.cancelled as u32;
        if let Some((key, r)) = p.records {
            let held = &mut self.workers.get_mut(&wid).unwrap().held;
            keep(held, (p.job, p.lease), key, r);
        }
        if !ended.is_empty() {
            checkpoint(j.driver.as_ref().unwrap(), &mut j.checkpoint);
            drive(&mut self.sched, j, p.job, now, slots);
        }
    }

    /// Worker `wid` takes the leases it is offered and renders them (a hoarder or a silent
    /// worker only keeps them).
    fn take_leases(&mut self, wid: u64, now: Millis) {
        while let Some(lease) = self.sched.next_lease(WorkerId(wid), now) {
            let w = self.workers.get_mut(&wid).unwrap();
            if matches!(w.kind, Kind::Hoarder | Kind::Silent) {
                w.kept.push(lease.id);
                continue;
            }
            let job = lease.key.job.0;
            let j = &self.jobs[&job];
            let d = j.driver.as_ref().expect("a lease of a running job");
            let spec = *d.flight(lease.key.unit).expect("a unit in flight");
            let region =
                d.session().tiles_of(spec.unit).expect("in flight")[lease.key.tile as usize];
            let estimate = match j.estimate.is_empty() {
                true => Vec::new(),
                false => codec::decode_estimate(&j.estimate).expect("decode"),
            };
            let key = (spec.tree_version, j.epoch);
            let params = self.scene.guided.clone().expect("guided");
            let seed = j.seed;
            let tree = w.tree(job, j, &spec);
            let inputs = UnitInputs {
                scene: self.scene,
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
            let delay = if self.rng.chance(0.15) {
                500 + self.rng.below(800)
            } else {
                self.rng.below(60)
            };
            let mut p = Pending {
                lease: lease.id,
                job,
                unit: lease.key.unit,
                tile: lease.key.tile,
                due: Millis(now.0 + delay),
                spec,
                out,
                stats,
                records,
            };
            w.uploads += 1;
            if w.kind == Kind::Garbage && w.uploads.is_multiple_of(2) {
                spoil(&mut p, w.uploads / 2);
            }
            w.pending.push(p);
        }
    }

    /// Holders asked for records answer (unless hung): each hands what it kept for the
    /// job's version and epoch. A collection that stalls past the timeout restarts the job.
    fn collect(&mut self, now: Millis) {
        let slots = self.slots();
        for (&n, j) in self.jobs.iter_mut() {
            let Some(d) = j.driver.as_mut() else { continue };
            let key = (d.session().tree_version(), d.records_epoch());
            let asked: Vec<u64> = (self.workers.keys().copied())
                .filter(|&w| d.is_asked(WorkerId(w)))
                .collect();
            for wid in asked {
                let w = self.workers.get_mut(&wid).unwrap();
                if w.hung_until.is_some_and(|t| now < t) {
                    continue;
                }
                let (k, records, covered) = w.held.remove(&n).expect("a holder keeps records");
                assert_eq!(
                    k, key,
                    "a holder's records are of the version and epoch asked"
                );
                d.records_from(WorkerId(wid), &records, &covered)
                    .expect("records taken");
            }
            if d.stalled(now, self.timeout) {
                roll_back(&mut self.sched, self.scene, j, n, now);
            }

            drive(&mut self.sched, j, n, now, slots);
        }
    }

    /// One step of every live worker: heartbeat, take leases, deliver what is due.
    fn workers_step(&mut self, now: Millis) {
        let ids: Vec<u64> = self.workers.keys().copied().collect();
        for wid in ids {
            let Some(w) = self.workers.get_mut(&wid) else {
                continue;
            };
            if w.hung_until.is_some_and(|t| now < t) {
                continue;
            }
            w.hung_until = None;
            if w.kind != Kind::Silent {
                let mut held: Vec<LeaseId> = w.pending.iter().map(|p| p.lease).collect();
                held.extend(&w.kept);
                let _ = self.sched.heartbeat(WorkerId(wid), &held, now);
            }
            self.take_leases(wid, now);
            let w = self.workers.get_mut(&wid).unwrap();
            let (due, later): (Vec<Pending>, Vec<Pending>) =
                w.pending.drain(..).partition(|p| p.due <= now);
            w.pending = later;
            for p in due {
                self.deliver(wid, p, now);
            }
        }
    }

    /// Joins (mostly honest workers; an honest one whenever none is left), deaths and hangs.
    fn churn(&mut self, now: Millis) {
        let honest = self
            .workers
            .values()
            .filter(|w| w.kind == Kind::Honest)
            .count();
        if honest == 0 {
            self.join(Kind::Honest, now);
        } else if self.workers.len() < 5 && self.rng.chance(0.03) {
            let kind = match self.rng.below(10) {
                0 => Kind::Garbage,
                1 => Kind::Hoarder,
                2 => Kind::Silent,
                _ => Kind::Honest,
            };
            self.join(kind, now);
        }
        if self.workers.len() > 1 && self.rng.chance(0.03) {
            let ids: Vec<u64> = self.workers.keys().copied().collect();
            let victim = ids[self.rng.below(ids.len() as u64) as usize];
            self.lost(victim, now);
        }
        // a worker hangs for a while (no heartbeats: its leases expire)
        if self.rng.chance(0.04) {
            let ids: Vec<u64> = self.workers.keys().copied().collect();
            let w = ids[self.rng.below(ids.len() as u64) as usize];
            let until = Millis(now.0 + 200 + self.rng.below(1000));
            self.workers.get_mut(&w).unwrap().hung_until = Some(until);
        }
    }

    /// Jobs whose setup ended start.
    fn start_jobs(&mut self, now: Millis) {
        let slots = self.slots();
        for (&n, j) in self.jobs.iter_mut() {
            if j.driver.is_none() && j.done.is_none() && !j.cancelled && now >= j.starts {
                let session = session_of(self.scene, n, j.seed, j.spp, None);
                j.driver = Some(JobDriver::new(session, tiling_of(self.scene, n), 0, now));
                self.sched
                    .add_job(JobId(n), (n % 3) as i32, now)
                    .expect("add job");
                drive(&mut self.sched, j, n, now, slots);
            }
        }
    }

    fn tick(&mut self, now: Millis) {
        let events = self.sched.tick(now);
        // The scheduler declared silent workers lost: they are forgotten, as the
        // coordinator forgets them (a worker that comes back registers anew).
        for e in &events {
            if let Event::WorkerLost { worker, .. } = e {
                if self.workers.remove(&worker.0).is_some() {
                    self.seen.deaths += 1;
                    self.holder_gone(*worker, now);
                }
            }
        }
        self.events(events);
    }
}

#[test]
fn random_schedule_with_faults_and_hostile_workers_gives_one_process_bits() {
    let scene = door_ajar((17, 11));
    let config = SchedulerConfig {
        lease_timeout: Duration::from_millis(400),
        heartbeat_timeout: Duration::from_millis(1500),
        max_lease_lifetime: Duration::from_millis(3000),
        max_attempts: 1000,
        leases_per_worker: 3,
    };
    let mut total = Seen::default();
    for sim_seed in [1u64, 2, 3] {
        let mut rng = TestRng::new(sim_seed * 0x1234_5678);
        let mut jobs = BTreeMap::new();
        for (n, (seed, spp)) in [(3u64, 12u32), (7, 16), (11, 8), (13, 12)]
            .iter()
            .enumerate()
        {
            let n = n as u64;
            let job = SimJob {
                seed: *seed,
                spp: *spp,
                starts: Millis(n * rng.below(400)),
                driver: None,
                epoch: 0,
                trees: HashMap::new(),
                fractions: HashMap::new(),
                estimate: Vec::new(),
                checkpoint: None,
                blocklist: Blocklist::new(3),
                done: None,
                cancelled: false,
                overlapped: 0,
                rollbacks: 0,
            };
            jobs.insert(n, job);
        }
        let mut farm = Farm {
            scene: &scene,
            sched: Scheduler::new(config.clone()),
            jobs,
            workers: BTreeMap::new(),
            next_worker: 0,
            rng: TestRng::new(sim_seed ^ 0xabcd),
            seen: Seen::default(),
            timeout: config.lease_timeout,
        };
        // one worker of each hostile kind from the start
        for kind in [Kind::Honest, Kind::Garbage, Kind::Hoarder, Kind::Silent] {
            farm.join(kind, Millis(0));
        }
        let cancel_job = 2u64;
        let cancel_at = 10 + rng.below(20);
        let mut now = Millis(0);
        for step in 0..200_000u64 {
            let over = |j: &SimJob| j.done.is_some() || j.cancelled;
            if farm.jobs.values().all(over) {
                break;
            }
            assert!(step < 199_999, "seed {sim_seed}: the jobs did not finish");
            now = Millis(now.0 + 1 + rng.below(40));
            farm.start_jobs(now);
            farm.churn(now);
            if step == cancel_at {
                let j = farm.jobs.get_mut(&cancel_job).unwrap();
                if j.done.is_none() {
                    if j.driver.is_some() {
                        farm.sched.cancel_job(JobId(cancel_job)).expect("cancel");
                    }
                    j.cancelled = true;
                }
            }
            farm.workers_step(now);
            farm.tick(now);
            farm.collect(now);
        }
        let seen = &farm.seen;
        println!("seed {sim_seed}: {seen:?}");
        assert!(
            seen.deaths >= 1 && seen.stale >= 1,
            "seed {sim_seed}: faults happened"
        );
        assert_eq!(
            seen.accepted_after_cancel, 0,
            "a cancelled job takes no tiles"
        );
        assert_eq!(
            seen.blocked_honest, 0,
            "seed {sim_seed}: no honest worker is blocked"
        );
        let rollbacks: usize = farm.jobs.values().map(|j| j.rollbacks).sum();
        assert!(rollbacks >= 1, "seed {sim_seed}: a job rolled back");
        let overlapped: usize = farm.jobs.values().map(|j| j.overlapped).sum();
        assert!(
            overlapped >= 2,
            "seed {sim_seed}: units overlapped {overlapped} times"
        );
        for (n, j) in &farm.jobs {
            if j.cancelled {
                continue;
            }
            let (film, tree) = j.done.as_ref().expect("done");
            let (ref_film, ref_tree) = one_process(&scene, j.spp, j.seed, policy_of(*n));
            assert!(
                film_bits(film) == film_bits(&ref_film),
                "seed {sim_seed}, job {n}: the image differs from the one-process render"
            );
            assert!(
                tree.encode() == ref_tree.encode(),
                "seed {sim_seed}, job {n}: the tree differs from the one-process render"
            );
        }
        total.refused += seen.refused;
        total.blocked_hostile += seen.blocked_hostile;
        total.expired_hoards += seen.expired_hoards;
    }
    // Over the seeds, each hostile behaviour happened and was answered.
    assert!(total.refused >= 3, "garbage was refused: {total:?}");
    assert!(
        total.blocked_hostile >= 1,
        "a garbage worker was blocked: {total:?}"
    );
    assert!(
        total.expired_hoards >= 1,
        "hoarded leases expired: {total:?}"
    );
}
