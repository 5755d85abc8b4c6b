//! The guided training schedule as a state machine (a job session), driven by the one-process
//! render ([`crate::guided::render_guided`]) and by the farm's coordinator alike.
//!
//! The session says what to render next ([`Session::next`]: a [`PassSpec`] over the whole
//! image), takes back what was rendered, tile by tile ([`Session::add_tile`]: pixel sums,
//! guide statistics, counters), and decides iteration ends, refinement, the path fallback and
//! the final combination (doc sections 3 and 5). It owns the master tree, the iteration films,
//! the pixel estimate and the ledger; it renders nothing, does no I/O and reads no clock: the
//! driver passes `now` (seconds since the job started) to every call.
//!
//! Training passes are pipelined: a recording unit samples with the learned fractions stepped
//! on every unit of its iteration but the one just before it, so unit `u` can be issued as
//! soon as unit `u - 2` is in, while `u - 1` still renders (at most two units in flight of
//! one iteration: both recording; or, with an spp budget, the iteration's unrecorded first
//! pass and the recording unit after it, or its last unit and the path fallback's probe
//! that checks it, which samples nothing the iteration learns). A unit's fraction gradients
//! are held apart by unit parity ([`pathfarm_guide::GradTarget::Held`]) until its step is due: when the unit is in and the
//! next one has been issued. The quality cost of the one-pass lag was measured:
//! docs/decisions/fraction-steps-pipelined.md.
//!
//! Invariant (determinism): with an spp budget, the units, their order and every pixel's
//! additions depend only on the job (scene, parameters, seed), never on the tiling, the
//! driver or when results arrive: a unit's tiles cover disjoint pixels, units end in unit
//! order (a unit whose tiles are all in waits for the one before it), a unit's film is merged
//! into its target film when it ends, guide statistics are exact integers, and the fractions
//! step once per recorded unit, on the gradients of the units up to it, before the unit two
//! after it is issued. Time budgets depend on `now` by nature.

use std::sync::Arc;

use pathfarm_guide::schedule::{self, Budget, GuidingVerdict, IterationLength, IterationOutcome};
use pathfarm_guide::{GradTarget, HeldSlot, IterationStats, SdTree, StatsError};
use pathfarm_scene::{GuidedCombination, GuidedParams, GuidedRoulette};

use crate::checkpoint::{self, Checkpoint, CheckpointError, CheckpointParts, In, Out};
use crate::film::Film;
use crate::filter::Filter;
use crate::guided::{
    combine_films, film_relative_variance, film_variance, pixel_estimate, GuidedIteration,
    GuidedStats,
};
use crate::pass::{PassKind, PassSpec, TileOutput, PATH_STREAM};
use crate::render::Region;

mod pixels;
use pixels::{Spares, UnitPixels};

/// How the path fallback decides.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum FallbackPolicy {
    /// [`schedule::guiding_verdict`] on the efficiency costs of the checked guided
    /// iterations, path tracing's, and the per-sample variance ratio of the latest check.
    #[default]
    Rule,
    /// Always this verdict (tests and experiments force either outcome).
    Force(GuidingVerdict),
}

impl FallbackPolicy {
    fn verdict(self, guided_costs: &[f64], path_cost: f64, variance_ratio: f64) -> GuidingVerdict {
        match self {
            Self::Rule => schedule::guiding_verdict(guided_costs, path_cost, variance_ratio),
            Self::Force(v) => v,
        }
    }
}

/// What the driver should do next.
#[derive(Clone, Debug, PartialEq)]
pub enum Next {
    /// Render this unit over every tile and hand the tiles to [`Session::add_tile`].
    Render(PassSpec),
    /// The units in flight must come in first.
    Wait,
    /// The job is done: take the result with [`Session::finish`].
    Done,
    /// The iteration's passes are in and its quadtree records are wanted (only with
    /// [`Records::PerIteration`]): hand them to [`Session::add_records`], then call
    /// [`Session::records_in`]. Until then `next` says this again.
    Records,
}

/// Where a session's quadtree records (the building statistics refinement reads) come
/// from. The fraction gradients come with each unit's tiles either way: every pass end's
/// Adam steps need them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Records {
    /// With each unit's tiles ([`Session::add_tiles`]' statistics, or recorded into
    /// [`Session::tree`] directly): the one-process render.
    #[default]
    WithTiles,
    /// Once an iteration, before refinement: the session says [`Next::Records`] and waits.
    /// A farm whose workers keep an iteration's records ship them once, not with every
    /// unit ([`pathfarm_guide::SdTree::take_gradients`] per unit).
    PerIteration,
}

/// Why records were not accepted.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RecordsError {
    /// The session is not collecting records (it did not say [`Next::Records`]).
    #[error("the session is not collecting an iteration's records")]
    NotCollecting,
    /// The records do not fit the session's tree.
    #[error("records: {0}")]
    Stats(#[from] StatsError),
}

/// Why a tile was not accepted.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TileError {
    /// The tile is for another unit than the one in flight (a late or stray result).
    #[error("unit {got} is not the unit being rendered ({expected:?})")]
    WrongUnit {
        /// The unit the tile says it belongs to.
        got: u64,
        /// The unit in flight; `None` when there is none.
        expected: Option<u64>,
    },
    /// The tile index is out of range of the unit's tiling.
    #[error("tile {0} does not exist")]
    NoSuchTile(usize),
    /// The tile was already accepted (a repeated result).
    #[error("tile {0} was already accepted")]
    Duplicate(usize),
    /// The output's region does not match the tile's region.
    #[error("tile {index}: region {got:?} is not the tile's {expected:?}")]
    WrongRegion {
        /// The tile's index in the unit's tiling.
        index: usize,
        /// The region of the output.
        got: Region,
        /// The region of tile `index`.
        expected: Region,
    },
    /// The output's pixels are not what a tile of the unit has: pixel sums of the tile's
    /// size, or, for a unit of few samples per pixel ([`PassSpec::sample_form`]), its
    /// samples.
    #[error("tile {index}: its pixels are not {expected}")]
    WrongPixels {
        /// The tile's index in the unit's tiling.
        index: usize,
        /// What the unit's tiles hold.
        expected: &'static str,
    },
    /// [`Session::retile`] refused: the message says why.
    #[error("the unit cannot be re-tiled: {0}")]
    NotRetilable(&'static str),
    /// Guide statistics came with a tile of a unit that does not record into the tree.
    #[error("tile {0}: guide statistics for a unit that records nothing")]
    UnexpectedStats(usize),
    /// The tile's guide statistics do not match the session's tree.
    #[error("tile {index}: guide statistics do not fit the tree: {source}")]
    Stats {
        /// The tile's index in the unit's tiling.
        index: usize,
        /// Why [`SdTree::apply_stats`] refused them.
        source: StatsError,
    },
}

/// Bookkeeping of the path fallback (`path_fallback`): while `enabled`, every training
/// iteration that samples from a built tree is checked against an unguided probe.
#[derive(Clone, Debug)]
struct Fallback {
    enabled: bool,
    /// Film of the unguided passes (probes, then the fallback's rendering). Shared with
    /// checkpoints being written (copied on write, [`Arc::make_mut`]).
    path_film: Arc<Film>,
    path_seconds: f64,
    /// Rays of the probe passes.
    path_rays: u64,
    /// Samples per pixel in `path_film`, and how many of them are probes.
    path_spp: u64,
    probe_spp: u64,
    /// Seconds of the current iteration's unrecorded first pass.
    guided_pass_seconds: f64,
    /// Efficiency costs of the checked guided iterations, oldest first.
    guided_costs: Vec<f64>,
    /// The training iteration after which the rest of the budget went to path tracing.
    fell_back_after: Option<u32>,
}

/// The iteration being rendered.
#[derive(Clone, Debug)]
struct Iteration {
    k: u32,
    record: bool,
    until: IterationLength,
    /// Automatic combination stopped training: the rest of the budget goes into this film.
    stopped: bool,
    /// Passes ended, and passes issued (ended or in flight).
    passes: u32,
    issued: u32,
    last_pass: f64,
    /// The iteration's pixels: its first unit's film (`None` until that unit ends), with the
    /// later units' merged in.
    film: Option<Film>,
    t0: f64,
    /// Rays traced by the iteration's units (not by a probe beside them).
    rays: u64,
    spp_before: u64,
    remaining_before: f64,
    nodes: usize,
    leaves: usize,
}

#[derive(Clone, Debug)]
enum Phase {
    /// Plan iteration `k`.
    Plan,
    Iterate(Box<Iteration>),
    /// The probe of the fallback check after the training iteration just ended.
    Probe,
    /// The fallback's rest of the budget, rendered with plain path tracing.
    Rest {
        after: u32,
        t0: f64,
    },
    /// Records are being collected ([`Records::PerIteration`]), then this follows.
    Records(AfterRecords),
    Done,
}

/// What follows a collection of records.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum AfterRecords {
    /// Refinement after training iteration `k`.
    Refine(u32),
    /// The end of the job: the last training iteration's records were not refined (the
    /// path fallback took over, or automatic combination stopped training), and the
    /// trained tree keeps them, as the one-process render's does.
    Finish,
}

/// The unit being rendered and the tiles that are in.
#[derive(Clone, Debug)]
struct Pending {
    spec: PassSpec,
    /// The unit's tiles (the session's default tiling unless the driver re-tiled it).
    tiles: Vec<Region>,
    pixels: UnitPixels,
    done: Vec<bool>,
    left: usize,
    issued_at: f64,
    /// Rays of the tiles that are in.
    rays: u64,
}

impl Iteration {
    /// The iteration's film, once its passes ended ([`Session::end_passes`] makes one if no
    /// unit did).
    fn film(&self) -> &Film {
        self.film
            .as_ref()
            .expect("an ended iteration's film (end_passes)")
    }
}

/// The image so far ([`Session::preview`]): the finished iterations' films, shared with the
/// session, and their weights in the final combination.
#[derive(Clone, Debug)]
pub struct Preview {
    films: Vec<Arc<Film>>,
    weights: Vec<f64>,
}

impl Preview {
    /// The pixel values of the films combined as the final image would combine them (the
    /// last film alone while no film has a weight yet), without making the combined film (a
    /// frame of sums less to allocate at every iteration's end).
    pub fn mean_rgb(&self) -> Vec<[f32; 3]> {
        if self.weights.iter().all(|&w| !(w > 0.0)) {
            return self.films.last().expect("a preview has a film").mean_rgb();
        }
        let refs: Vec<&Film> = self.films.iter().map(|f| &**f).collect();
        crate::guided::combined_means(&refs, &self.weights)
    }

    /// The image's width and height.
    pub fn size(&self) -> (u32, u32) {
        let f = self.films.last().expect("a preview has a film");
        (f.width, f.height)
    }
}

/// What a session needs to splat units whose tiles come back as samples
/// ([`PassSpec::sample_form`]): the scene's reconstruction filter and the job's seed, which
/// give every sample's film position again.
#[derive(Clone, Copy, Debug)]
pub struct Splatting {
    /// The scene's reconstruction filter.
    pub filter: Filter,
    /// The job's seed (the units' [`crate::pass::UnitInputs::seed`]).
    pub seed: u64,
}

/// A guided job's training session. See the module documentation.
pub struct Session {
    params: GuidedParams,
    budget: Budget,
    policy: FallbackPolicy,
    width: u32,
    height: u32,
    splatting: Splatting,
    /// Buffers of ended units, reused by the next ones.
    spares: Spares,
    spp_per_pass: u32,
    tiles: Vec<Region>,
    tree: SdTree,
    tree_version: u32,
    fraction_version: u32,
    phase: Phase,
    /// Where the quadtree records come from.
    records: Records,
    /// Recording units ended since the last collection of records.
    uncollected: bool,
    k: u32,
    next_unit: u64,
    /// Units in flight, oldest first: at most two, both recording units of one iteration.
    pending: Vec<Pending>,
    /// Recording units that ended but whose fraction step waits for the next unit's issue,
    /// oldest first.
    deferred: Vec<u64>,
    /// When the last unit ended (per-pass timing while units overlap).
    last_end: f64,
    spp_done: u64,
    passes_done: u32,
    training_spp: u64,
    prev_secs: Option<f64>,
    iterations: Vec<GuidedIteration>,
    /// The finished iterations' films: never changed once pushed (but for a fallback's
    /// end), so checkpoints and previews share them instead of copying.
    films: Vec<Arc<Film>>,
    history: Vec<IterationOutcome>,
    kept: Option<usize>,
    /// Films of iterations rendered before the tree was built: unguided, so on a fallback
    /// their samples join the path tracer's film.
    unguided: Vec<usize>,
    est_sum: Vec<f64>,
    est_spp: u64,
    estimate: Vec<f32>,
    estimate_version: u32,
    fallback: Fallback,
    rays: u64,
    invalid: u64,
    nonfinite_records: u64,
    splits: u64,
    light_splits: u64,
    finished_at: f64,
}

impl Session {
    /// A session of a `width x height` job training `tree` (fresh, from
    /// [`crate::guided::guide_config`]) within `budget`, whose units the driver renders in
    /// the tiles `tiles` (disjoint, covering the image; e.g. [`Region::tiles`]).
    pub fn new(
        params: &GuidedParams,
        budget: Budget,
        tree: SdTree,
        (width, height): (u32, u32),
        splatting: Splatting,
        tiles: Vec<Region>,
        policy: FallbackPolicy,
    ) -> Self {
        Self {
            params: params.clone(),
            budget,
            policy,
            width,
            height,
            splatting,
            spares: Spares::default(),
            spp_per_pass: params.spp_per_pass.max(1),
            tiles,
            tree,
            tree_version: 0,
            fraction_version: 0,
            phase: Phase::Plan,
            records: Records::WithTiles,
            uncollected: false,
            k: 0,
            next_unit: 0,
            pending: Vec::new(),
            deferred: Vec::new(),
            last_end: 0.0,
            spp_done: 0,
            passes_done: 0,
            training_spp: 0,
            prev_secs: None,
            iterations: Vec::new(),
            films: Vec::new(),
            history: Vec::new(),
            kept: None,
            unguided: Vec::new(),
            est_sum: Vec::new(),
            est_spp: 0,
            estimate: Vec::new(),
            estimate_version: 0,
            fallback: Fallback {
                enabled: params.path_fallback,
                path_film: Arc::new(Film::new(width, height)),
                path_seconds: 0.0,
                path_rays: 0,
                path_spp: 0,
                probe_spp: 0,
                guided_pass_seconds: 0.0,
                guided_costs: Vec::new(),
                fell_back_after: None,
            },
            rays: 0,
            invalid: 0,
            nonfinite_records: 0,
            splits: 0,
            light_splits: 0,
            finished_at: 0.0,
        }
    }

    /// The image's width and height.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The master tree: units sample from it (with the fractions of the current unit).
    pub fn tree(&self) -> &SdTree {
        &self.tree
    }

    /// Refinements so far (the tree version units name).
    pub fn tree_version(&self) -> u32 {
        self.tree_version
    }

    /// Fraction steps since the last refinement.
    pub fn fraction_version(&self) -> u32 {
        self.fraction_version
    }

    /// The pixel estimate guided roulette reads (whole image; empty until an iteration ended).
    pub fn estimate(&self) -> &[f32] {
        &self.estimate
    }

    /// The pixel estimate the passes read: [`Session::estimate`] with guided roulette, empty
    /// otherwise (the path fallback reads the estimate here, in the session; a farm need not
    /// ship a frame-sized array to every worker for it).
    pub fn pass_estimate(&self) -> &[f32] {
        match self.params.russian_roulette {
            GuidedRoulette::Guided => &self.estimate,
            _ => &[],
        }
    }

    /// Changes whenever [`Session::estimate`] does.
    pub fn estimate_version(&self) -> u32 {
        self.estimate_version
    }

    /// The tiles of the unit issued last if it is in flight, or the default tiling units
    /// are issued with.
    pub fn tiles(&self) -> &[Region] {
        match self.pending.last() {
            Some(p) => &p.tiles,
            None => &self.tiles,
        }
    }

    /// The tiles of unit `unit` if it is in flight.
    pub fn tiles_of(&self, unit: u64) -> Option<&[Region]> {
        let p = self.pending.iter().find(|p| p.spec.unit == unit)?;
        Some(&p.tiles)
    }

    /// Re-tiles the unit just issued, before any of its tiles is in: a farm sizes each
    /// unit's tiles to its work. Any tiling gives the same bits (each pixel's additions do
    /// not depend on its tile). `tiles` must be disjoint, non-empty and cover the image.
    pub fn retile(&mut self, tiles: Vec<Region>) -> Result<(), TileError> {
        let Some(p) = self.pending.last_mut() else {
            return Err(TileError::NotRetilable("no unit is in flight"));
        };
        if p.left != p.tiles.len() {
            return Err(TileError::NotRetilable("some of its tiles are in already"));
        }
        if !covers_exactly(&tiles, self.width, self.height) {
            return Err(TileError::NotRetilable(
                "the tiles are not disjoint regions covering the image",
            ));
        }
        p.done = vec![false; tiles.len()];
        p.left = tiles.len();
        p.tiles = tiles;
        Ok(())
    }

    /// The training iteration after which the path fallback gave guiding up for path
    /// tracing, if it did.
    pub fn fell_back_after(&self) -> Option<u32> {
        self.fallback.fell_back_after
    }

    /// Samples per pixel rendered so far (guided and unguided).
    pub fn spp_done(&self) -> u64 {
        self.spp_done + self.fallback.path_spp
    }

    /// Samples and guide records dropped so far for a NaN or infinite value.
    pub fn nonfinite(&self) -> u64 {
        self.invalid + self.nonfinite_records
    }

    /// The training iteration in progress (or the last one).
    pub fn iteration(&self) -> u32 {
        self.k
    }

    /// Tiles accepted / total of the oldest unit in flight.
    pub fn tiles_done(&self) -> (usize, usize) {
        match self.pending.first() {
            Some(p) => (p.tiles.len() - p.left, p.tiles.len()),
            None => (0, self.tiles.len()),
        }
    }

    /// The iterations finished so far.
    pub fn iterations(&self) -> &[GuidedIteration] {
        &self.iterations
    }

    /// Whether the unit in flight (if any) is the final image's: no training is left.
    pub fn in_final_pass(&self) -> bool {
        match &self.phase {
            Phase::Iterate(it) => !it.record || it.stopped,
            Phase::Rest { .. } | Phase::Done => true,
            _ => false,
        }
    }

    /// The next unit to render, or `Wait` while the units in flight must come in first, or
    /// `Done`. A driver that can render two units at once calls it again after a `Render`.
    pub fn next(&mut self, now: f64) -> Next {
        if !self.pending.is_empty() {
            return self.next_overlapping(now);
        }
        loop {
            let phase = std::mem::replace(&mut self.phase, Phase::Done);
            match phase {
                Phase::Plan => self.plan(now),
                Phase::Iterate(it) => {
                    if let Some(spec) = self.iteration_unit(&it, now) {
                        self.phase = Phase::Iterate(it);
                        return self.issue(spec, now);
                    }
                    self.end_passes(it, now);
                }
                Phase::Probe => {
                    self.phase = Phase::Probe;
                    let spec = self.probe_unit();
                    return self.issue(spec, now);
                }
                Phase::Rest { after, t0 } => {
                    self.phase = Phase::Rest { after, t0 };
                    match self.rest_unit(now) {
                        Some(spec) => return self.issue(spec, now),
                        None => self.end_rest(after, t0, now),
                    }
                }
                Phase::Records(then) => {
                    self.phase = Phase::Records(then);
                    return Next::Records;
                }
                Phase::Done if self.uncollected => {
                    self.phase = Phase::Records(AfterRecords::Finish);
                    return Next::Records;
                }
                Phase::Done => {
                    if self.finished_at == 0.0 {
                        self.finished_at = now;
                    }
                    return Next::Done;
                }
            }
        }
    }

    /// How the samples of `unit`, in flight, are splatted: what preparing its tiles apart
    /// needs ([`crate::SplatPlan::prepare`], [`crate::pass::TilePixels::Prepared`]). `None`
    /// for a unit of pixel sums or one not in flight.
    pub fn splat_plan(&self, unit: u64) -> Option<&crate::SplatPlan> {
        let p = self.pending.iter().find(|p| p.spec.unit == unit)?;
        p.pixels.plan()
    }

    /// Accepts the rendered tile `index` of `unit` (`stats`: its guide statistics, from
    /// [`SdTree::take_stats`] on the worker's copy of the tree; `None` when they were
    /// recorded into [`Session::tree`] directly, as the one-process render does). When the
    /// last tile is in, the unit ends. Nothing changes on an error.
    pub fn add_tile(
        &mut self,
        unit: u64,
        index: usize,
        out: &TileOutput,
        stats: Option<&IterationStats>,
        now: f64,
    ) -> Result<(), TileError> {
        self.add_tiles(unit, &[(index, out)], stats, now)
    }

    /// Accepts several rendered tiles of `unit` at once, with the guide statistics of all of
    /// them together (a worker that renders tiles of a unit one after the other into its
    /// tree takes their statistics once: exact sums, the same as each tile's added up). All
    /// or nothing: nothing changes on an error.
    pub fn add_tiles(
        &mut self,
        unit: u64,
        tiles: &[(usize, &TileOutput)],
        stats: Option<&IterationStats>,
        now: f64,
    ) -> Result<(), TileError> {
        let expected = self.pending.first().map(|p| p.spec.unit);
        let Some(p) = self.pending.iter_mut().find(|p| p.spec.unit == unit) else {
            return Err(TileError::WrongUnit {
                got: unit,
                expected,
            });
        };
        for (k, &(index, out)) in tiles.iter().enumerate() {
            check_tile(p, index, out)?;
            if tiles[..k].iter().any(|&(other, _)| other == index) {
                return Err(TileError::Duplicate(index));
            }
        }
        if let Some(s) = stats {
            let first = tiles.first().map_or(0, |&(index, _)| index);
            if !p.spec.record() {
                return Err(TileError::UnexpectedStats(first));
            }
            let target = GradTarget::Held(HeldSlot::of_unit(unit));
            self.tree
                .apply_stats(s, target)
                .map_err(|source| TileError::Stats {
                    index: first,
                    source,
                })?;
        }
        for &(index, out) in tiles {
            p.pixels.put(&out.pixels, p.tiles[index], self.width);
            p.done[index] = true;
            p.left -= 1;
            p.rays += out.rays;
            self.rays += out.rays;
            self.invalid += out.invalid_samples;
            self.nonfinite_records += out.nonfinite_records;
            self.splits += out.split_paths;
            self.light_splits += out.extra_light_samples;
        }
        if let (Some(oldest), Phase::Iterate(it)) = (self.pending.first_mut(), &mut self.phase) {
            // The oldest unit's film is the next its iteration's film takes (end_unit), unless
            // it is the iteration's first, whose film becomes the iteration's.
            if let Some(film) = &mut it.film {
                oldest.pixels.merge_interiors(film);
            }
        }
        while self.pending.first().is_some_and(|p| p.left == 0) {
            let p = self.pending.remove(0);
            self.end_unit(p, now);
            // (the iteration ends before a probe issued beside its last unit does)
            self.settle(now);
        }
        self.catch_up_steps();
        self.settle(now);
        Ok(())
    }

    /// The image as it stands: the finished iterations' films combined as the final image
    /// would combine them (`None` before the first iteration ends). A farm shows it as a
    /// preview while the job runs.
    ///
    /// Cheap: the [`Preview`] shares the films, and [`Preview::mean_rgb`] combines them, which a
    /// driver can do off its critical path.
    pub fn preview(&self) -> Option<Preview> {
        if self.films.is_empty() {
            return None;
        }
        Some(Preview {
            films: self.films.clone(),
            weights: self.weights(),
        })
    }

    /// The final film, the statistics and the trained tree, once [`Session::next`] said
    /// `Done`.
    pub fn finish(mut self) -> (Film, GuidedStats, SdTree) {
        let n = self.films.len();
        let weights = self.weights();
        let film = if n == 0 {
            Film::new(self.width, self.height)
        } else if self.params.sample_combination == GuidedCombination::InverseVar {
            let refs: Vec<&Film> = self.films.iter().map(|f| &**f).collect();
            combine_films(&refs, &weights)
        } else {
            let kept = self.films.swap_remove(self.kept.unwrap_or(n - 1));
            Arc::try_unwrap(kept).unwrap_or_else(|shared| (*shared).clone())
        };
        let spp = self.spp_done;
        let stats = GuidedStats {
            iterations: self.iterations,
            spp: spp as u32,
            training_fraction: if spp > 0 {
                self.training_spp as f64 / spp as f64
            } else {
                0.0
            },
            tree_memory_bytes: self.tree.stats().memory_bytes,
            weights,
            wall: std::time::Duration::from_secs_f64(self.finished_at.max(0.0)),
            invalid_samples: self.invalid,
            nonfinite_records: self.nonfinite_records,
            path_fallback_after: self.fallback.fell_back_after,
            split_paths: self.splits,
            extra_light_samples: self.light_splits,
        };
        (film, stats, self.tree)
    }

    /// Ends the iteration right away when its last unit is in, so that a checkpoint can be
    /// taken before the next [`Session::next`].
    fn settle(&mut self, now: f64) {
        let done = match &self.phase {
            Phase::Iterate(it) => {
                // (a probe in flight is the one issued beside the iteration's last unit)
                let probes = self.pending.iter().all(|p| p.spec.kind == PassKind::Probe);
                probes && self.iteration_unit(it, now).is_none()
            }
            _ => false,
        };
        if done {
            let Phase::Iterate(it) = std::mem::replace(&mut self.phase, Phase::Done) else {
                unreachable!()
            };
            self.end_passes(it, now);
        }
    }

    /// With a unit in flight: the next recording unit of the iteration if it may overlap it
    /// (see the module documentation), else `Wait`.
    fn next_overlapping(&mut self, now: f64) -> Next {
        let Phase::Iterate(it) = &self.phase else {
            return Next::Wait;
        };
        // A recording unit may have the next beside it. So may a training iteration's
        // unrecorded first pass with an spp budget: nothing the next unit samples with
        // depends on it (it takes no fraction step), and only a time budget reads what
        // it costs (`guided_pass_seconds`), which it must then be timed alone for.
        let overlappable = match self.pending.as_slice() {
            [p] => {
                let spp_budget = matches!(self.budget, Budget::Spp(_));
                p.spec.record() || (it.record && !it.stopped && spp_budget)
            }
            _ => false,
        };
        if self.probes_early(it, now) {
            let spec = self.probe_unit();
            return self.issue(spec, now);
        }
        if !overlappable {
            return Next::Wait;
        }
        match self.iteration_unit(it, now) {
            Some(spec) if spec.record() => self.issue(spec, now),
            _ => Next::Wait,
        }
    }

    /// Whether the path fallback's probe may be issued now, beside the iteration's last unit
    /// (`it` is the iteration in progress, one unit in flight): the iteration will be
    /// checked, and nothing the probe samples depends on what is still to come. The probe is
    /// plain path tracing from its own random streams, so it needs nothing of the
    /// iteration; but a time budget times it alone, and automatic combination may yet turn
    /// the iteration into the final one (then there is no check).
    fn probes_early(&self, it: &Iteration, now: f64) -> bool {
        matches!(self.budget, Budget::Spp(_))
            && self.params.sample_combination != GuidedCombination::Automatic
            && it.record
            && !it.stopped
            && self.checks()
            && self.pending.len() == 1
            && self.pending[0].spec.kind != PassKind::Probe
            && self.iteration_unit(it, now).is_none()
    }

    /// Takes the deferred fraction steps that are due: a unit's once the unit after it has
    /// been issued (it sampled with the fractions before that step).
    fn catch_up_steps(&mut self) {
        while let Some(&j) = self.deferred.first() {
            if self.next_unit <= j + 1 {
                break;
            }
            self.step_deferred();
        }
    }

    /// Takes every deferred step: no unit is in flight and the next one is not a recording
    /// unit of the same iteration, or the iteration ended.
    fn flush_steps(&mut self) {
        while !self.deferred.is_empty() {
            self.step_deferred();
        }
    }

    fn step_deferred(&mut self) {
        let j = self.deferred.remove(0);
        self.tree.fold_held(HeldSlot::of_unit(j));
        self.tree.step_fractions();
        self.fraction_version += 1;
    }

    /// Units issued but not ended: their samples are not in `spp_done` yet.
    fn spp_issued(&self) -> u64 {
        self.spp_done + self.pending.iter().map(|p| p.spec.unit_spp()).sum::<u64>()
    }

    /// Issues `spec` as unit `next_unit`, with the fractions its kind samples with: a
    /// recording unit after the steps that are due, any other after every step.
    fn issue(&mut self, mut spec: PassSpec, now: f64) -> Next {
        let early_probe = spec.kind == PassKind::Probe && !self.pending.is_empty();
        if spec.record() {
            self.catch_up_steps();
        } else if !early_probe {
            // (a probe beside the iteration's last unit leaves the steps to the iteration's
            // end, as one after it finds them taken; it samples no fractions)
            self.flush_steps();
        }
        spec.fraction_version = self.fraction_version;
        self.next_unit += 1;
        if let Phase::Iterate(it) = &mut self.phase {
            if !early_probe {
                it.issued += spec.passes;
            }
        }
        if spec.record() {
            // One process records straight into the tree: into the unit's held slot.
            let slot = HeldSlot::of_unit(spec.unit);
            self.tree.set_grad_target(GradTarget::Held(slot));
        }
        self.pending.push(Pending {
            spec,
            tiles: self.tiles.clone(),
            pixels: UnitPixels::new(
                &spec,
                (self.width, self.height),
                &self.splatting,
                &mut self.spares,
            ),
            done: vec![false; self.tiles.len()],
            left: self.tiles.len(),
            issued_at: now,
            rays: 0,
        });
        Next::Render(spec)
    }

    fn spec(&self, kind: PassKind, first_sample: u64, passes: u32, split: bool) -> PassSpec {
        PassSpec {
            unit: self.next_unit,
            iteration: self.k,
            kind,
            first_sample,
            spp: self.spp_per_pass,
            passes,
            spp_before: first_sample,
            split,
            tree_version: self.tree_version,
            fraction_version: self.fraction_version,
        }
    }

    /// Plans iteration `k`, or ends the job when the budget is used up.
    fn plan(&mut self, now: f64) {
        let (k, budget, spp) = (self.k, self.budget, self.spp_per_pass);
        let Some(plan) =
            schedule::plan_iteration(k, budget, spp, self.passes_done, now, self.prev_secs)
        else {
            self.phase = Phase::Done;
            return self.end_job();
        };
        let stats = self.tree.stats();
        self.spares.warm_up((self.width, self.height));
        self.phase = Phase::Iterate(Box::new(Iteration {
            k,
            record: !plan.is_last,
            until: plan.length,
            stopped: false,
            passes: 0,
            issued: 0,
            last_pass: 0.0,
            film: None,
            t0: now,
            rays: 0,
            spp_before: self.spp_done,
            remaining_before: match budget {
                Budget::Spp(s) => (schedule::total_passes(s, spp) - self.passes_done) as f64,
                Budget::Seconds(s) => s - now,
            },
            nodes: stats.spatial_nodes,
            leaves: stats.leaves,
        }));
    }

    /// The iteration's next unit (after the ones issued), or `None` when its passes are
    /// issued. Training passes are one unit each: the learned fractions take their Adam steps
    /// between them, one pass late, so that two can be in flight (stepping once per iteration
    /// instead gave 1.2-2.6 % higher relMSE: docs/decisions/fraction-steps-per-pass.md; the
    /// one-pass lag costs less: docs/decisions/fraction-steps-pipelined.md). The passes of an
    /// iteration that records nothing are one unit with an spp budget, one per pass with a
    /// time budget (so the clock can end it).
    fn iteration_unit(&self, it: &Iteration, now: f64) -> Option<PassSpec> {
        let passes = match it.until {
            IterationLength::Passes(p) if it.issued >= p => return None,
            IterationLength::Passes(p) => p - it.issued,
            IterationLength::UntilSeconds(s) if it.issued > 0 && now + 0.5 * it.last_pass >= s => {
                return None
            }
            IterationLength::UntilSeconds(_) => 1,
        };
        // The first pass of a training iteration checked by the path fallback is not
        // recorded: it times what a final, guided pass costs.
        let probe = it.issued == 0 && it.record && self.checks();
        let rec = it.record && !it.stopped && !probe;
        // Splitting only in passes that sample as the final image does (not in the
        // fallback's timed check pass: there it judged immature trees by split paths and
        // made door-ajar fall back).
        let split = !rec && !probe;
        let kind = if rec {
            PassKind::Record
        } else {
            PassKind::Guided
        };
        let n = if rec || probe { 1 } else { passes };
        Some(self.spec(kind, self.spp_issued(), n, split))
    }

    /// Whether an iteration sampling from the tree is checked by the fallback.
    fn checks(&self) -> bool {
        self.fallback.enabled && self.tree.is_built()
    }

    fn end_unit(&mut self, p: Pending, now: f64) {
        let spec = p.spec;
        let film = p.pixels.film(&p.tiles, &mut self.spares);
        let seconds = now - p.issued_at.max(self.last_end);
        self.last_end = now;
        // (the film to keep for a later unit, if the unit's film is not kept elsewhere)
        let spare = match &mut self.phase {
            Phase::Iterate(it) => {
                let spare = match &mut it.film {
                    Some(f) => {
                        film.merge_into(f);
                        Some(film)
                    }
                    // The iteration's first unit: its film becomes the iteration's. The same
                    // bits as adding it to zeros (a gathered sum starts at +0.0, so it is
                    // never -0.0), without a fresh film's pages (190 MB at 1920x1080)
                    // faulted in here, under a farm coordinator's lock; the units' films get
                    // a new one faulted in on the pool instead (Spares::warm_up).
                    None => {
                        it.film = Some(film.into_film());
                        None
                    }
                };
                it.rays += p.rays;
                if spec.record() {
                    self.deferred.push(spec.unit);
                    self.uncollected = self.records == Records::PerIteration;
                }
                it.last_pass = seconds / spec.passes.max(1) as f64;
                if it.passes == 0 && it.record && !spec.record() && !it.stopped {
                    self.fallback.guided_pass_seconds = it.last_pass;
                }
                it.passes += spec.passes;
                self.spp_done += spec.unit_spp();
                spare
            }
            Phase::Probe => {
                let f = &mut self.fallback;
                film.merge_into(Arc::make_mut(&mut f.path_film));
                f.path_seconds += seconds;
                f.path_rays += p.rays;
                f.path_spp += spec.unit_spp();
                f.probe_spp += spec.unit_spp();
                self.passes_done += spec.passes;
                self.end_probe(now);
                Some(film)
            }
            Phase::Rest { .. } => {
                film.merge_into(Arc::make_mut(&mut self.fallback.path_film));
                self.fallback.path_spp += spec.unit_spp();
                self.fallback.path_seconds += seconds;
                Some(film)
            }
            Phase::Plan | Phase::Records(_) | Phase::Done => {
                unreachable!("a unit completed outside an iteration")
            }
        };
        if let Some(film) = spare {
            self.spares.keep(film);
        }
    }

    /// The iteration's passes are done. Automatic combination may turn a training
    /// iteration into the final one (the rest of the budget goes into its film); otherwise
    /// the iteration ends.
    fn end_passes(&mut self, mut it: Box<Iteration>, now: f64) {
        let (w, h) = (self.width, self.height);
        // (an iteration whose passes ended without a unit has an empty film)
        it.film.get_or_insert_with(|| Film::new(w, h));
        self.flush_steps();
        let automatic = self.params.sample_combination == GuidedCombination::Automatic;
        if it.record && !it.stopped && automatic {
            let cost = match self.budget {
                Budget::Spp(_) => it.passes as f64,
                Budget::Seconds(_) => now - it.t0,
            };
            self.history.push(IterationOutcome {
                variance: film_variance(it.film()),
                cost,
                remaining_before: it.remaining_before,
                spp_before: it.spp_before,
            });
            if schedule::automatic_should_stop(&self.history) {
                it.stopped = true;
                self.training_spp += self.spp_done - it.spp_before;
                it.until = match self.budget {
                    Budget::Spp(s) => IterationLength::Passes(
                        schedule::total_passes(s, self.spp_per_pass) - self.passes_done,
                    ),
                    Budget::Seconds(s) => IterationLength::UntilSeconds(s),
                };
                self.phase = Phase::Iterate(it);
                return;
            }
        }
        self.end_iteration(*it, now);
    }

    fn end_iteration(&mut self, it: Iteration, now: f64) {
        let npix = self.width as u64 * self.height as u64;
        let k = it.k;
        self.passes_done += it.passes;
        let secs = now - it.t0;
        self.prev_secs = Some(secs);
        let training = it.record && !it.stopped;
        let spp = self.spp_done - it.spp_before;
        if training {
            self.training_spp += spp;
        }
        tracing::debug!(
            "guided iteration {k}: {} passes, training {training}",
            it.passes
        );
        self.iterations.push(GuidedIteration {
            index: k,
            spp: spp as u32,
            nodes: it.nodes,
            leaves: it.leaves,
            variance: film_variance(it.film()),
            seconds: secs,
            rays_per_sample: it.rays as f64 / (spp as f64 * npix as f64).max(1.0),
            training,
        });
        if self.params.russian_roulette == GuidedRoulette::Guided || self.fallback.enabled {
            self.update_estimate(it.film(), spp);
        }
        if !self.tree.is_built() {
            // sampled without a guide (iteration 0): plain path tracing
            self.unguided.push(self.films.len());
        }
        let checked = training && self.checks();
        let film = it.film.expect("an ended iteration's film (end_passes)");
        self.films.push(Arc::new(film));
        if !training {
            self.kept = Some(self.films.len() - 1);
            self.phase = Phase::Done;
            return self.end_job();
        }
        if checked {
            // One unguided pass into the probe film, then compare per-sample efficiencies.
            self.phase = Phase::Probe;
            return;
        }
        self.refine(k);
    }

    fn update_estimate(&mut self, film: &Film, spp: u64) {
        let means = film.mean_rgb();
        self.est_sum.resize(means.len(), 0.0);
        for (s, m) in self.est_sum.iter_mut().zip(&means) {
            *s += spp as f64 * (m[0] as f64 + m[1] as f64 + m[2] as f64) / 3.0;
        }
        self.est_spp += spp;
        self.estimate = pixel_estimate(&self.est_sum, self.est_spp, self.width, self.height);
        self.estimate_version += 1;
    }

    fn probe_unit(&self) -> PassSpec {
        let f = &self.fallback;
        let mut spec = self.spec(PassKind::Probe, PATH_STREAM + f.path_spp, 1, false);
        // (issued beside the iteration's last unit, that unit's samples count as done)
        spec.spp_before = self.spp_issued() + f.path_spp;
        spec
    }

    /// The probe is in: compare guided and unguided efficiency, then refine or fall back.
    fn end_probe(&mut self, now: f64) {
        let npix = self.width as u64 * self.height as u64;
        let k = self.k;
        let it = self.iterations.last().unwrap();
        let f = &self.fallback;
        let guided_variance = film_relative_variance(self.films.last().unwrap(), &self.estimate);
        let spp_per_pass = self.spp_per_pass as f64;
        let guided_cost = match self.budget {
            // per-sample variance x seconds per spp of an unrecorded pass
            Budget::Seconds(_) => {
                guided_variance * it.spp as f64 * f.guided_pass_seconds / spp_per_pass
            }
            // deterministic: per-sample variance x rays per spp
            Budget::Spp(_) => guided_variance * it.rays_per_sample * it.spp as f64,
        };
        let path_variance = film_relative_variance(&f.path_film, &self.estimate);
        let path_cost = match self.budget {
            Budget::Seconds(_) => path_variance * f.path_seconds,
            Budget::Spp(_) => path_variance * f.path_rays as f64 / npix.max(1) as f64,
        };
        // per-sample relative variances: film variances of the mean times their spp
        let variance_ratio = guided_variance * it.spp as f64 / (path_variance * f.path_spp as f64);
        self.fallback.guided_costs.push(guided_cost);
        let verdict = self
            .policy
            .verdict(&self.fallback.guided_costs, path_cost, variance_ratio);
        tracing::info!(
            "guiding check after iteration {k}: guided cost {guided_cost:.4e}, path cost \
             {path_cost:.4e} (ratio {:.3}, per-sample variance ratio {variance_ratio:.3}): \
             {verdict:?}",
            guided_cost / path_cost
        );
        match verdict {
            GuidingVerdict::Keep => self.fallback.enabled = false,
            GuidingVerdict::FallBack => {
                self.fallback.fell_back_after = Some(k);
                self.phase = Phase::Rest { after: k, t0: now };
                return;
            }
            GuidingVerdict::Undecided => {}
        }
        self.refine(k);
    }

    /// Refines after training iteration `k`, once its records are in.
    fn refine(&mut self, k: u32) {
        match self.records {
            Records::WithTiles => self.refine_now(k),
            Records::PerIteration => self.phase = Phase::Records(AfterRecords::Refine(k)),
        }
    }

    /// Where the quadtree records come from from now on (the default: with the tiles).
    pub fn set_records(&mut self, records: Records) {
        self.records = records;
    }

    /// Adds quadtree records of the iteration being collected (after [`Next::Records`]):
    /// each worker's, in any order (exact sums). Nothing changes on an error.
    pub fn add_records(&mut self, records: &IterationStats) -> Result<(), RecordsError> {
        if !matches!(self.phase, Phase::Records(_)) {
            return Err(RecordsError::NotCollecting);
        }
        self.tree.apply_stats(records, GradTarget::Batch)?;
        Ok(())
    }

    /// Every worker's records are in: refine, and plan the next iteration.
    pub fn records_in(&mut self) -> Result<(), RecordsError> {
        let Phase::Records(then) = self.phase else {
            return Err(RecordsError::NotCollecting);
        };
        self.uncollected = false;
        match then {
            AfterRecords::Refine(k) => self.refine_now(k),
            AfterRecords::Finish => self.phase = Phase::Done,
        }
        Ok(())
    }

    fn refine_now(&mut self, k: u32) {
        self.tree.refine(k);
        self.tree_version += 1;
        self.fraction_version = 0;
        if let Some(rho) = self.tree.raised_d_tree_threshold() {
            tracing::warn!(
                "iteration {k}: the quadtrees would exceed the guide's memory cap \
                 (max_memory_mb, or Limits::max_guide_memory_bytes): refined with \
                 d_tree_threshold {rho:.3e} instead of {:.3e}",
                self.params.d_tree_threshold
            );
        }
        self.k += 1;
        self.phase = Phase::Plan;
    }

    /// The fallback's next unit of plain path tracing, or `None` when the budget is used.
    /// With an spp budget, one unit for the whole rest (the renderer sizes its passes);
    /// with a time budget, units of about a second.
    fn rest_unit(&self, now: f64) -> Option<PassSpec> {
        let f = &self.fallback;
        let first = PATH_STREAM + f.path_spp;
        let spp = match self.budget {
            Budget::Spp(s) => {
                if f.path_spp > f.probe_spp {
                    return None;
                }
                let total = schedule::total_passes(s, self.spp_per_pass);
                total.saturating_sub(self.passes_done) * self.spp_per_pass
            }
            Budget::Seconds(s) => {
                let per_spp = f.path_seconds / f.path_spp.max(1) as f64;
                let left = s - now;
                if !(left > 0.0) || left < 0.5 * per_spp {
                    return None;
                }
                (left.min(1.0) / per_spp.max(1e-9)).floor().clamp(1.0, 1e6) as u32
            }
        };
        if spp == 0 {
            return None;
        }
        let mut spec = self.spec(PassKind::Path, first, 1, false);
        spec.spp = spp;
        spec.spp_before = self.spp_done + f.path_spp;
        Some(spec)
    }

    /// The fallback's rest is done: the probes' film becomes the final iteration.
    fn end_rest(&mut self, after: u32, t0: f64, now: f64) {
        let npix = self.width as u64 * self.height as u64;
        let (w, h) = (self.width, self.height);
        // The unguided iterations' samples are path tracing's too (the same estimator up to
        // its random streams): they join the film instead of being weighed apart (a 1-spp
        // iteration has no variance estimate, so inverse-variance weighting drops it).
        for &i in &self.unguided {
            Arc::make_mut(&mut self.fallback.path_film).merge(&self.films[i]);
            self.films[i] = Arc::new(Film::new(w, h));
        }
        let f = &self.fallback;
        self.iterations.push(GuidedIteration {
            index: after + 1,
            spp: f.path_spp as u32,
            nodes: 0,
            leaves: 0,
            variance: film_variance(&f.path_film),
            seconds: now - t0,
            // measured on the probe passes (the path integrator does not count rays)
            rays_per_sample: f.path_rays as f64 / (f.probe_spp as f64 * npix as f64).max(1.0),
            training: false,
        });
        let film = std::mem::replace(&mut self.fallback.path_film, Arc::new(Film::new(w, h)));
        self.films.push(film);
        self.kept = Some(self.films.len() - 1);
        self.phase = Phase::Done;
        self.end_job();
    }

    /// Counts the unguided samples into the total (their films were merged, or are probes).
    fn end_job(&mut self) {
        self.spp_done += self.fallback.path_spp;
        self.fallback.path_spp = 0;
    }

    fn weights(&self) -> Vec<f64> {
        let n = self.films.len();
        match self.params.sample_combination {
            // An iteration of one sample per pixel has no usable variance estimate (with a
            // box filter it is exactly 0, which would claim a perfect image): weight 0.
            GuidedCombination::InverseVar if n > 0 => schedule::inverse_variance_weights(
                &self
                    .iterations
                    .iter()
                    .enumerate()
                    .map(|(k, i)| {
                        let merged =
                            self.fallback.fell_back_after.is_some() && self.unguided.contains(&k);
                        if i.spp < 2 || merged {
                            f64::INFINITY
                        } else {
                            i.variance
                        }
                    })
                    .collect::<Vec<_>>(),
            ),
            _ => {
                let mut w = vec![0.0; n];
                if n > 0 {
                    w[self.kept.unwrap_or(n - 1)] = 1.0;
                }
                w
            }
        }
    }
}

/// Copies the `region`-sized `src` into `region` of the whole-image `dst`.
/// Ok if `out` may be accepted as tile `index` of `p`.
fn check_tile(p: &Pending, index: usize, out: &TileOutput) -> Result<(), TileError> {
    let Some(&tile) = p.tiles.get(index) else {
        return Err(TileError::NoSuchTile(index));
    };
    if p.done[index] {
        return Err(TileError::Duplicate(index));
    }
    if out.region != tile {
        return Err(TileError::WrongRegion {
            index,
            got: out.region,
            expected: tile,
        });
    }
    if !out.pixels.fits(&p.spec, tile) || !p.pixels.accepts(&out.pixels) {
        let expected = if p.spec.sample_form() {
            "the samples of its pixels"
        } else {
            "pixel sums of its size"
        };
        return Err(TileError::WrongPixels { index, expected });
    }
    Ok(())
}

impl Session {
    /// Whether no unit is in flight and the next iteration is not planned yet: when
    /// [`Session::checkpoint`] can be taken.
    pub fn between_iterations(&self) -> bool {
        self.pending.is_empty() && matches!(self.phase, Phase::Plan)
    }

    /// The session's state ([`crate::checkpoint`]), between iterations only (when no unit is
    /// in flight and the next iteration is not planned yet): `None` otherwise. The tree is
    /// not in it: keep [`Session::tree`]'s encoding with it (a farm publishes that anyway).
    pub fn checkpoint(&self) -> Option<Checkpoint> {
        self.checkpoint_parts().map(CheckpointParts::encode)
    }

    /// [`Session::checkpoint`] with the films shared, not encoded: cheap, so a driver can
    /// take it on its critical path and encode the films ([`CheckpointParts::encode`], or
    /// one by one, skipping films it stored before: a finished iteration's film is the same
    /// `Arc` in every later checkpoint) off it.
    pub fn checkpoint_parts(&self) -> Option<CheckpointParts> {
        if !self.between_iterations() {
            return None;
        }
        let mut o = Out::default();
        checkpoint::header(&mut o);
        for v in [
            self.width,
            self.height,
            self.tree_version,
            self.fraction_version,
            self.k,
        ] {
            o.u32(v);
        }
        for v in [
            self.next_unit,
            self.spp_done,
            self.passes_done as u64,
            self.training_spp,
        ] {
            o.u64(v);
        }
        o.opt_f64(self.prev_secs);
        o.u64(self.iterations.len() as u64);
        self.iterations.iter().for_each(|i| o.iteration(i));
        o.u64(self.films.len() as u64);
        o.u64(self.history.len() as u64);
        self.history.iter().for_each(|h| o.outcome(h));
        o.opt_u32(self.kept.map(|k| k as u32));
        o.u64(self.unguided.len() as u64);
        self.unguided.iter().for_each(|&u| o.u64(u as u64));
        o.u64(self.est_sum.len() as u64);
        self.est_sum.iter().for_each(|&x| o.f64(x));
        o.u64(self.est_spp);
        o.u64(self.estimate.len() as u64);
        self.estimate.iter().for_each(|&x| o.u32(x.to_bits()));
        o.u32(self.estimate_version);
        self.checkpoint_fallback(&mut o);
        let counters = [
            self.rays,
            self.invalid,
            self.nonfinite_records,
            self.splits,
            self.light_splits,
        ];
        for v in counters {
            o.u64(v);
        }
        let films = self.films.iter().chain([&self.fallback.path_film]);
        Some(CheckpointParts {
            state: o.0,
            films: films.cloned().collect(),
        })
    }

    fn checkpoint_fallback(&self, o: &mut Out) {
        let f = &self.fallback;
        o.u8(f.enabled as u8);
        o.f64(f.path_seconds);
        for v in [f.path_rays, f.path_spp, f.probe_spp] {
            o.u64(v);
        }
        o.f64(f.guided_pass_seconds);
        o.u64(f.guided_costs.len() as u64);
        f.guided_costs.iter().for_each(|&c| o.f64(c));
        o.opt_u32(f.fell_back_after);
    }

    /// A session from a [`Session::checkpoint`] and the tree saved with it, for the same
    /// job (parameters, budget, tiles, policy): it continues exactly as the checkpointed
    /// session would have.
    pub fn restore(
        params: &GuidedParams,
        budget: Budget,
        tiles: Vec<Region>,
        splatting: Splatting,
        policy: FallbackPolicy,
        checkpoint: &Checkpoint,
        tree: SdTree,
    ) -> Result<Session, CheckpointError> {
        let mut i = In(&checkpoint.state);
        checkpoint::check_header(&mut i)?;
        let (width, height) = (i.u32()?, i.u32()?);
        let (tree_version, fraction_version, k) = (i.u32()?, i.u32()?, i.u32()?);
        let dummy = SdTree::new(glam::Vec3::ZERO, glam::Vec3::ONE, Default::default());
        let mut s = Session::new(
            params,
            budget,
            dummy,
            (width, height),
            splatting,
            tiles,
            policy,
        );
        s.tree_version = tree_version;
        s.fraction_version = fraction_version;
        s.k = k;
        s.next_unit = i.u64()?;
        s.spp_done = i.u64()?;
        s.passes_done = i.u64()? as u32;
        s.training_spp = i.u64()?;
        s.prev_secs = i.opt_f64()?;
        s.iterations = (0..i.len(45)?)
            .map(|_| i.iteration())
            .collect::<Result<_, _>>()?;
        let nfilms = i.u64()? as usize;
        if nfilms + 1 != checkpoint.films.len() {
            return Err(CheckpointError(format!(
                "{} films for {nfilms} iterations",
                checkpoint.films.len()
            )));
        }
        let mut films = checkpoint
            .films
            .iter()
            .map(|f| checkpoint::decode_film(f, width, height))
            .collect::<Result<Vec<_>, _>>()?;
        let path_film = films.pop().expect("checked");
        s.films = films.into_iter().map(Arc::new).collect();
        s.history = (0..i.len(32)?)
            .map(|_| i.outcome())
            .collect::<Result<_, _>>()?;
        s.kept = i.opt_u32()?.map(|k| k as usize);
        s.unguided = (0..i.len(8)?)
            .map(|_| Ok(i.u64()? as usize))
            .collect::<Result<_, _>>()?;
        s.est_sum = (0..i.len(8)?).map(|_| i.f64()).collect::<Result<_, _>>()?;
        s.est_spp = i.u64()?;
        let n = i.len(4)?;
        s.estimate = (0..n)
            .map(|_| Ok(f32::from_bits(i.u32()?)))
            .collect::<Result<_, _>>()?;
        s.estimate_version = i.u32()?;
        s.restore_fallback(&mut i)?;
        s.fallback.path_film = Arc::new(path_film);
        for v in [
            &mut s.rays,
            &mut s.invalid,
            &mut s.nonfinite_records,
            &mut s.splits,
            &mut s.light_splits,
        ] {
            *v = i.u64()?;
        }
        s.tree = tree;
        if !i.0.is_empty() {
            return Err(CheckpointError(format!(
                "{} bytes after the end",
                i.0.len()
            )));
        }
        Ok(s)
    }

    fn restore_fallback(&mut self, i: &mut In) -> Result<(), CheckpointError> {
        let f = &mut self.fallback;
        f.enabled = i.bool()?;
        f.path_seconds = i.f64()?;
        f.path_rays = i.u64()?;
        f.path_spp = i.u64()?;
        f.probe_spp = i.u64()?;
        f.guided_pass_seconds = i.f64()?;
        f.guided_costs = (0..i.len(8)?).map(|_| i.f64()).collect::<Result<_, _>>()?;
        f.fell_back_after = i.opt_u32()?;
        Ok(())
    }
}

/// Whether `tiles` are non-empty regions inside the `width x height` image that cover every
/// pixel exactly once.
fn covers_exactly(tiles: &[Region], width: u32, height: u32) -> bool {
    let mut seen = vec![false; width as usize * height as usize];
    let mut covered = 0usize;
    for t in tiles {
        if !t.is_valid_in(width, height) {
            return false;
        }
        for y in t.y0..t.y1 {
            for x in t.x0..t.x1 {
                let i = y as usize * width as usize + x as usize;
                if std::mem::replace(&mut seen[i], true) {
                    return false;
                }
                covered += 1;
            }
        }
    }
    covered == seen.len()
}
