//! One job's progress through its [`Session`], as a pure state machine: the clock is passed
//! in, nothing is sent or stored, and every step returns what the caller must do. The
//! coordinator runs it for each job it renders, and the socket-less simulation
//! (`tests/it/farm_sim.rs`) runs the same code, so what the simulation shows of the farm's
//! logic is true of the shipped coordinator.
//!
//! What the driver owns, for its job: the units in flight, how each unit is cut into tiles
//! ([`Tiling`]), which inputs (tree, fractions, pixel estimate) have been published to the
//! workers, which workers hold quadtree records of the iteration and which of them still
//! owe them, and the records epoch. What it does not own: leases and workers (the
//! [`Scheduler`](crate::scheduler::Scheduler)), blobs, the job's record and its
//! persistence (the coordinator), and a worker's standing with the job ([`Blocklist`]).
//!
//! The protocol, each call followed by [`JobDriver::step`] until it says
//! [`Step::Wait`]:
//! * [`Step::Offer`]: store the unit's new inputs where workers fetch them, then offer its
//!   tiles to the scheduler.
//! * tiles come in: [`JobDriver::tiles_in`] (after the scheduler checked the leases, before
//!   it commits them: a tile the session refuses changes nothing).
//! * [`Step::Collect`]: ask those workers for their records; each answer goes to
//!   [`JobDriver::records_from`], with the leases they say they cover ([`Coverage`]), which
//!   must be those the driver took from that worker. A holder that is lost ([`JobDriver::holds`]) or a
//!   collection that stalls ([`JobDriver::stalled`]) means the job must restart from its
//!   checkpoint, under a new epoch: a new driver.
//! * [`Step::IterationEnded`]: the tree was refined; the session can be checkpointed.
//! * [`Step::Done`]: take the results ([`JobDriver::into_session`], then
//!   [`Session::finish`]).

mod blocklist;
mod coverage;

use std::collections::{BTreeMap, BTreeSet};

pub use blocklist::{Blame, Blocklist, Standing};
pub use coverage::{Coverage, CoverageDigestLength, COVERAGE_DIGEST_BYTES};

use pathfarm_guide::IterationStats;
use pathfarm_render::guided::{Next, RecordsError, Session};
use pathfarm_render::pass::{PassSpec, TileOutput};
use pathfarm_render::session::TileError;
use pathfarm_render::Region;

use crate::codec;
use crate::scheduler::{LeaseId, Millis, WorkerId};
use crate::tiling::CostMap;

/// How a job's units are cut into tiles.
#[derive(Clone, Debug)]
pub enum Tiling {
    /// Square tiles of this edge (the job set one).
    Fixed(u32),
    /// A few tiles per worker thread, of equal cost as measured in the job's earlier units.
    ByCost(CostMap),
}

/// A unit to offer, and which of its inputs no earlier unit published (the caller stores
/// those where workers fetch them, in the forms [`JobDriver::encode_tree`],
/// [`JobDriver::encode_fractions`] and [`JobDriver::encode_estimate`] give).
#[derive(Clone, Copy, Debug)]
pub struct Offer {
    pub spec: PassSpec,
    /// Tiles of the unit (their regions: [`Session::tiles_of`]).
    pub tiles: u32,
    /// A new tree version.
    pub new_tree: bool,
    /// New selection probabilities (a new tree or fraction version).
    pub new_fractions: bool,
    /// A new pixel estimate.
    pub new_estimate: bool,
}

/// What the caller must do next.
#[derive(Debug)]
pub enum Step {
    /// Publish the unit's new inputs, then offer its tiles.
    Offer(Offer),
    /// Ask these workers for the quadtree records they hold of the current tree version
    /// and epoch ([`JobDriver::records_epoch`]).
    Collect(Vec<WorkerId>),
    /// Training iteration `iteration` ended and the tree was refined (or, after the last,
    /// the job is ready to finish): a checkpoint can be taken now.
    IterationEnded { iteration: u32 },
    /// Everything is rendered.
    Done,
    /// Nothing until tiles or records come in.
    Wait,
}

/// Why a step could not be taken: the job cannot go on.
#[derive(Debug, thiserror::Error)]
pub enum DriverError {
    #[error("tiling unit {unit}: {source}")]
    Tiling { unit: u64, source: TileError },
    #[error("records: {0}")]
    Records(#[from] RecordsError),
}

/// Why a holder's records were refused.
#[derive(Debug, thiserror::Error)]
pub enum RecordsRefused {
    #[error("records not asked of worker {0}")]
    NotAsked(WorkerId),
    #[error("records refused by the session: {0}")]
    Session(#[from] RecordsError),
    #[error("records of worker {worker} cover {stated}, not the {taken} accepted from it")]
    Coverage {
        worker: WorkerId,
        stated: Coverage,
        taken: Coverage,
    },
}

/// A rendered tile handed to [`JobDriver::tiles_in`].
pub struct TileIn<'a> {
    /// Its index in the unit's tiling.
    pub index: usize,
    /// The lease it was rendered under (what the holder's records say they cover).
    pub lease: LeaseId,
    pub out: &'a TileOutput,
    /// What the worker says it spent rendering it (for the next units' tiling).
    pub render_seconds: f64,
}

/// Versions of the inputs the workers were last given.
#[derive(Clone, Copy, Debug, Default)]
struct Published {
    tree: Option<u32>,
    fractions: Option<(u32, u32)>,
    estimate: Option<u32>,
}

/// The holders still owing records, and since when.
#[derive(Clone, Debug)]
struct Collecting {
    left: BTreeSet<WorkerId>,
    since: Millis,
}

/// One job's progress: see the module docs.
pub struct JobDriver {
    session: Session,
    /// The units whose tiles are not all in, oldest first.
    flights: Vec<PassSpec>,
    tiling: Tiling,
    records_epoch: u64,
    /// Workers whose tiles of the current tree version's recording units were accepted,
    /// and those tiles' leases: the workers keep those tiles' records until asked.
    holders: BTreeMap<WorkerId, Coverage>,
    collecting: Option<Collecting>,
    published: Published,
    /// When the driver started: the session's clock is seconds since then.
    started: Millis,
}

impl JobDriver {
    /// Drives `session` (which must keep its records per iteration) from `now`; its
    /// results carry `records_epoch`, which no earlier driver of the job used.
    pub fn new(session: Session, tiling: Tiling, records_epoch: u64, now: Millis) -> Self {
        Self {
            session,
            flights: Vec::new(),
            tiling,
            records_epoch,
            holders: BTreeMap::new(),
            collecting: None,
            published: Published::default(),
            started: now,
        }
    }

    pub fn session(&self) -> &Session {
        &self.session
    }

    /// The session, to finish it once [`Step::Done`] was returned.
    pub fn into_session(self) -> Session {
        self.session
    }

    pub fn records_epoch(&self) -> u64 {
        self.records_epoch
    }

    /// The units in flight, oldest first.
    pub fn flights(&self) -> &[PassSpec] {
        &self.flights
    }

    /// The unit in flight numbered `unit`.
    pub fn flight(&self, unit: u64) -> Option<&PassSpec> {
        self.flights.iter().find(|f| f.unit == unit)
    }

    /// The tree version the workers were last given.
    pub fn published_tree(&self) -> Option<u32> {
        self.published.tree
    }

    /// Seconds on the session's clock at `now`.
    pub fn seconds(&self, now: Millis) -> f64 {
        now.0.saturating_sub(self.started.0) as f64 * 1e-3
    }

    /// The next thing to do; `slots` is the worker threads a unit's tiles are shared among.
    pub fn step(&mut self, now: Millis, slots: usize) -> Result<Step, DriverError> {
        match self.session.next(self.seconds(now)) {
            Next::Wait => Ok(Step::Wait),
            Next::Done => Ok(Step::Done),
            Next::Records => self.records_wanted(now),
            Next::Render(spec) => self.issue(spec, slots),
        }
    }

    /// The session wants the iteration's records: ask every holder once, or, if none holds
    /// any (or all have answered), refine now.
    fn records_wanted(&mut self, now: Millis) -> Result<Step, DriverError> {
        match &self.collecting {
            Some(c) if !c.left.is_empty() => return Ok(Step::Wait),
            Some(_) => {}
            None if !self.holders.is_empty() => {
                let left: BTreeSet<WorkerId> = self.holders.keys().copied().collect();
                let ask = left.iter().copied().collect();
                self.collecting = Some(Collecting { left, since: now });
                return Ok(Step::Collect(ask));
            }
            None => {}
        }
        self.collecting = None;
        self.holders.clear();
        let iteration = self.session.iteration();
        self.session.records_in()?;
        Ok(Step::IterationEnded { iteration })
    }

    /// Cuts the unit the session issued into tiles and says what to publish for it.
    fn issue(&mut self, spec: PassSpec, slots: usize) -> Result<Step, DriverError> {
        let tiles = match &self.tiling {
            Tiling::Fixed(edge) => {
                let (w, h) = self.session.size();
                Region::tiles(w, h, *edge)
            }
            Tiling::ByCost(cost) => cost.tiles(slots, spec.unit_spp()),
        };
        let unit = spec.unit;
        (self.session.retile(tiles)).map_err(|source| DriverError::Tiling { unit, source })?;
        let fractions = Some((spec.tree_version, spec.fraction_version));
        let uses_estimate = !self.session.pass_estimate().is_empty();
        let estimate = uses_estimate.then(|| self.session.estimate_version());
        let offer = Offer {
            spec,
            tiles: self.session.tiles().len() as u32,
            new_tree: self.published.tree != Some(spec.tree_version),
            new_fractions: self.published.fractions != fractions,
            new_estimate: self.published.estimate != estimate,
        };
        self.published = Published {
            tree: Some(spec.tree_version),
            fractions,
            estimate,
        };
        self.flights.push(spec);
        Ok(Step::Offer(offer))
    }

    /// The session's tree, as workers fetch it.
    pub fn encode_tree(&self) -> Vec<u8> {
        self.session.tree().encode()
    }

    /// The tree's selection probabilities, as workers fetch them.
    pub fn encode_fractions(&self) -> Vec<u8> {
        codec::encode_fractions(&self.session.tree().fraction_states())
    }

    /// The pixel estimate, as workers fetch it; empty if the session has none.
    pub fn encode_estimate(&self) -> Vec<u8> {
        let estimate = self.session.pass_estimate();
        match estimate.is_empty() {
            true => Vec::new(),
            false => codec::encode_estimate(estimate),
        }
    }

    /// Takes tiles of `unit` rendered by `worker`, all or none (nothing changes on an
    /// error). Returns the units that ended, oldest first (a unit ends once its tiles and
    /// those of every unit before it are in).
    pub fn tiles_in(
        &mut self,
        worker: WorkerId,
        unit: u64,
        tiles: &[TileIn],
        stats: Option<&IterationStats>,
        now: Millis,
    ) -> Result<Vec<PassSpec>, TileError> {
        let outs: Vec<(usize, &TileOutput)> = tiles.iter().map(|t| (t.index, t.out)).collect();
        let secs = self.seconds(now);
        self.session.add_tiles(unit, &outs, stats, secs)?;
        let spec = *self
            .flight(unit)
            .expect("the session took tiles of a unit in flight");
        if spec.record() {
            let covered = self.holders.entry(worker).or_default();
            tiles.iter().for_each(|t| covered.add(t.lease.0));
        }
        if let Tiling::ByCost(cost) = &mut self.tiling {
            for t in tiles {
                let samples = t.out.region.pixels() as u64 * spec.unit_spp();
                cost.record(t.out.region, t.render_seconds / samples.max(1) as f64);
            }
        }
        let session = &self.session;
        let (ended, open) = (self.flights.iter()).partition(|f| session.tiles_of(f.unit).is_none());
        self.flights = open;
        Ok(ended)
    }

    /// Whether `worker` was asked for records and has not answered.
    pub fn is_asked(&self, worker: WorkerId) -> bool {
        (self.collecting.as_ref()).is_some_and(|c| c.left.contains(&worker))
    }

    /// Adds the records `worker` was asked for, which it says are those of the leases
    /// `covered`. Returns how many holders still owe theirs. Nothing changes on an error.
    pub fn records_from(
        &mut self,
        worker: WorkerId,
        records: &IterationStats,
        covered: &Coverage,
    ) -> Result<usize, RecordsRefused> {
        if !self.is_asked(worker) {
            return Err(RecordsRefused::NotAsked(worker));
        }
        let taken = self.holders.get(&worker).copied().unwrap_or_default();
        if *covered != taken {
            return Err(RecordsRefused::Coverage {
                worker,
                stated: *covered,
                taken,
            });
        }
        self.session.add_records(records)?;
        let c = self.collecting.as_mut().expect("asked");
        c.left.remove(&worker);
        Ok(c.left.len())
    }

    /// Whether `worker` holds records of the iteration in progress: if it is lost, or
    /// loses them, the job must restart from its checkpoint.
    pub fn holds(&self, worker: WorkerId) -> bool {
        self.holders.contains_key(&worker)
    }

    /// Whether the holders were asked more than `timeout` ago and some have not answered
    /// (a wedged holder must not stall the job: it restarts from its checkpoint).
    pub fn stalled(&self, now: Millis, timeout: std::time::Duration) -> bool {
        (self.collecting.as_ref()).is_some_and(|c| {
            !c.left.is_empty() && now.0.saturating_sub(c.since.0) > timeout.as_millis() as u64
        })
    }
}

#[cfg(test)]
mod tests;
