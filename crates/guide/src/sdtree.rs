//! The SD-tree facade: spatial binary tree whose leaves hold double-buffered directional
//! quadtrees and the learned BSDF-sampling fraction.

use crate::config::{DirectionalFilter, FractionMode, GuideConfig, SpatialFilter};
use crate::dtree::{prefetch, prefetch_block, DTree, SamplingDTree};
use crate::filter::{spatial_box_overlaps, stochastic_jitter};
use crate::fraction::{FractionState, GradAccum};
use crate::hash::Hasher64;
use crate::iteration_stats::{IterationStats, LeafStats, StatsError};
use crate::light::LightStats;
use crate::mapping::{dir_to_uv, pdf_uv_to_solid_angle, uv_to_dir};
use crate::record::Record;
use crate::region::{CellWeights, Restriction};
use crate::stats::{add_counted, split_exact, to_fixed, Acc128};
use crate::stree::{SLookup, STree};
use glam::Vec3;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::OnceLock;

#[cfg(test)]
mod tests;

/// Deepest S-tree level (root = 0): 20 splits per axis, about the precision of the f32 lookup.
pub const MAX_SPATIAL_DEPTH: u32 = 60;

type BoxScratch = (Vec<(u32, f64)>, Vec<f64>, Vec<u128>, Vec<u128>);
thread_local! {
    static BOX_SCRATCH: std::cell::RefCell<BoxScratch> = std::cell::RefCell::new(Default::default());
}

/// Handle of a spatial leaf (index into [`SdTree::leaves`]), from [`SdTree::leaf_index`].
/// Valid until the next [`SdTree::refine`]: a split leaf keeps its index for its first child
/// and the second child gets a new index, so look handles up again after a refinement.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct LeafHandle(pub u32);

/// Payload of one spatial leaf.
#[derive(Clone, Debug, PartialEq)]
pub struct Leaf {
    /// Quadtree receiving this iteration's records.
    pub building: DTree,
    /// Frozen quadtree of the previous iteration, read by sample and pdf.
    pub sampling: SamplingDTree,
    /// Learned-fraction state (logit and Adam moments).
    pub fraction: FractionState,
    /// The batch the learned fraction steps on: exactly accumulated fraction gradients of
    /// every record since the last refinement (see [`crate::fraction`]).
    pub grad: GradAccum,
    /// Gradients of units whose step is deferred ([`GradTarget::Held`]), by unit parity: they
    /// join `grad` at [`SdTree::fold_held`]. Not part of the wire form (empty whenever a tree
    /// is published: between iterations).
    pub held: [GradAccum; 2],
    /// Integral of the incident radiance over the sphere learned by `sampling`
    /// (`total / W` of the building tree when it was frozen; split children inherit it):
    /// `flux * pdf(direction)` estimates the incident radiance in that direction.
    pub flux: f32,
    /// `sigmoid(fraction.theta)` in f32, cached: it is read at every guided path vertex and
    /// changes only when theta does ([`Leaf::set_theta_cache`]).
    pub(crate) alpha: f32,
    /// Light-sample statistics: this iteration's sums and the mean and deviation frozen at
    /// the last refinement (split children inherit both).
    pub light: LightStats,
    /// Statistics carried over from earlier iterations (`GuideConfig::carry_over`; see
    /// [`crate::carry`]): a quadtree of `building`'s structure whose leaf-cell sums and
    /// weight are added into `building` at the next refinement. Empty without carry-over.
    pub prior: DTree,
}

/// The learned fraction's alpha as vertices read it: f32 sigmoid of the logit.
#[inline]
pub(crate) fn alpha_of(theta: f64) -> f32 {
    let theta = theta as f32;
    1.0 / (1.0 + (-theta).exp())
}

impl Leaf {
    /// Refreshes the cached alpha after `fraction.theta` changed.
    pub(crate) fn set_theta_cache(&mut self) {
        self.alpha = alpha_of(self.fraction.theta);
    }

    fn initial() -> Self {
        Self {
            // The state of a freshly reset empty tree (as [G] resets before iteration 0).
            building: DTree::uniform(4),
            sampling: DTree::new().freeze(),
            fraction: FractionState::default(),
            grad: GradAccum::default(),
            held: Default::default(),
            flux: 0.0,
            alpha: alpha_of(0.0),
            light: LightStats::default(),
            prior: DTree::new(),
        }
    }
}

/// Size and shape statistics of an SD-tree.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct TreeStats {
    /// Number of S-tree nodes.
    pub spatial_nodes: usize,
    /// Number of spatial leaves.
    pub leaves: usize,
    /// Number of spatial leaves per S-tree depth (index = depth, root = 0).
    pub depth_histogram: Vec<usize>,
    /// Total quadtree nodes over all sampling trees.
    pub sampling_dtree_nodes: usize,
    /// Total quadtree nodes over all building trees.
    pub building_dtree_nodes: usize,
    /// Deepest quadtree (root = 1) over all sampling trees.
    pub max_dtree_depth: u32,
    /// Approximate heap memory in bytes.
    pub memory_bytes: usize,
    /// Number of fixed-point overflow events so far (should be 0; see [`crate::stats`]).
    pub overflow_events: u64,
    /// Spatial leaves by the BSDF-sampling fraction they sample with
    /// ([`SdTree::bsdf_sampling_fraction_leaf`]): bin `i` counts fractions in
    /// `[i / 10, (i + 1) / 10)`, the last bin includes 1.
    pub fraction_histogram: [usize; 10],
}

/// The SD-tree guide. Recording takes `&self` and may run on many threads at once; the learned
/// statistics are exact integers, bit-identical for any thread count and record order.
#[derive(Debug)]
pub struct SdTree {
    pub(crate) config: GuideConfig,
    pub(crate) stree: STree,
    pub(crate) leaves: Vec<Leaf>,
    pub(crate) built: bool,
    pub(crate) overflow: AtomicU64,
    /// Records and light samples rejected because a value was NaN or infinite, since the
    /// last [`SdTree::take_nonfinite_records`] (not part of the statistics or the wire form:
    /// renderers report it beside their own non-finite sample count).
    pub(crate) nonfinite: AtomicU64,
    /// Set by `refine` when `max_dtree_nodes` raised the quadtree threshold.
    pub(crate) raised_rho: Option<f64>,
    /// [`SdTree::structure_hash`], computed once per structure (every statistics exchange
    /// checks it, and it walks the whole tree).
    pub(crate) hash: OnceLock<u64>,
    /// Leaves recorded into since the last [`SdTree::take_stats`] or refinement (one bit a
    /// leaf): taking the statistics of a tile visits only those.
    pub(crate) touched: TouchedLeaves,
    /// Where recorded fraction gradients go ([`SdTree::set_grad_target`]).
    pub(crate) grad_target: GradTarget,
}

/// Where fraction gradients go when records are deposited or statistics applied.
///
/// The farm pipelines training passes: a pass samples with the fractions stepped on every
/// pass but the one before it (which is still rendering), so the gradients of a unit are held
/// apart until its step is due, and two units can be in flight at once (one slot each, by
/// unit parity).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum GradTarget {
    /// Straight into the batch the next [`SdTree::step_fractions`] steps on.
    #[default]
    Batch,
    /// Into the held slot of a unit ([`HeldSlot::of_unit`]), until [`SdTree::fold_held`].
    Held(HeldSlot),
}

/// One of the two held gradient slots of every leaf.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HeldSlot {
    /// Units with an even number.
    Even,
    /// Units with an odd number.
    Odd,
}

impl HeldSlot {
    /// The slot of unit `unit`: consecutive units use different slots.
    pub fn of_unit(unit: u64) -> Self {
        if unit.is_multiple_of(2) {
            Self::Even
        } else {
            Self::Odd
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

impl Leaf {
    /// The accumulator `target` names.
    fn grad_of(&self, target: GradTarget) -> &GradAccum {
        match target {
            GradTarget::Batch => &self.grad,
            GradTarget::Held(s) => &self.held[s.index()],
        }
    }
}

/// A set of leaf indices that many recording threads may add to: one bit a leaf.
#[derive(Debug, Default)]
pub(crate) struct TouchedLeaves(Vec<AtomicU64>);

impl TouchedLeaves {
    /// An empty set of `n` leaves.
    pub(crate) fn new(n: usize) -> Self {
        Self((0..n.div_ceil(64)).map(|_| AtomicU64::new(0)).collect())
    }

    /// Adds `leaf` (a load first: after a leaf's first record the word is only read).
    #[inline]
    fn insert(&self, leaf: u32) {
        let (w, bit) = ((leaf / 64) as usize, 1u64 << (leaf % 64));
        if let Some(word) = self.0.get(w) {
            if word.load(Relaxed) & bit == 0 {
                word.fetch_or(bit, Relaxed);
            }
        }
    }

    /// The leaves in the set, ascending, leaving it as it is.
    fn list(&self) -> Vec<u32> {
        let mut out = Vec::new();
        for (w, word) in self.0.iter().enumerate() {
            let mut bits = word.load(Relaxed);
            while bits != 0 {
                out.push(w as u32 * 64 + bits.trailing_zeros());
                bits &= bits - 1;
            }
        }
        out
    }

    /// The leaves in the set, ascending, emptying it.
    fn drain(&self) -> Vec<u32> {
        let mut out = Vec::new();
        for (w, word) in self.0.iter().enumerate() {
            let mut bits = word.swap(0, Relaxed);
            while bits != 0 {
                out.push(w as u32 * 64 + bits.trailing_zeros());
                bits &= bits - 1;
            }
        }
        out
    }
}

impl Clone for TouchedLeaves {
    fn clone(&self) -> Self {
        Self(
            self.0
                .iter()
                .map(|w| AtomicU64::new(w.load(Relaxed)))
                .collect(),
        )
    }
}

impl Clone for SdTree {
    fn clone(&self) -> Self {
        Self {
            config: self.config.clone(),
            stree: self.stree.clone(),
            leaves: self.leaves.clone(),
            built: self.built,
            overflow: AtomicU64::new(self.overflow.load(Relaxed)),
            nonfinite: AtomicU64::new(self.nonfinite.load(Relaxed)),
            raised_rho: self.raised_rho,
            hash: self.hash.clone(),
            touched: self.touched.clone(),
            grad_target: self.grad_target,
        }
    }
}

impl PartialEq for SdTree {
    fn eq(&self, o: &Self) -> bool {
        self.config == o.config
            && self.stree == o.stree
            && self.leaves == o.leaves
            && self.built == o.built
            && self.overflow.load(Relaxed) == o.overflow.load(Relaxed)
    }
}

impl SdTree {
    /// A tree over the cube containing the scene box `[aabb_min, aabb_max]`, with one spatial
    /// leaf whose building quadtree is the uniform depth-4 tree. Not built: [`SdTree::sample`]
    /// returns `None` until the first [`SdTree::refine`].
    pub fn new(aabb_min: Vec3, aabb_max: Vec3, config: GuideConfig) -> Self {
        Self {
            config,
            stree: STree::new(aabb_min, aabb_max),
            leaves: vec![Leaf::initial()],
            built: false,
            overflow: AtomicU64::new(0),
            nonfinite: AtomicU64::new(0),
            raised_rho: None,
            hash: OnceLock::new(),
            touched: TouchedLeaves::new(1),
            grad_target: GradTarget::Batch,
        }
    }

    /// The configuration.
    pub fn config(&self) -> &GuideConfig {
        &self.config
    }

    /// The spatial tree.
    pub fn stree(&self) -> &STree {
        &self.stree
    }

    /// All leaf payloads, indexed by [`LeafHandle`].
    pub fn leaves(&self) -> &[Leaf] {
        &self.leaves
    }

    /// One leaf payload.
    pub fn leaf(&self, h: LeafHandle) -> &Leaf {
        &self.leaves[h.0 as usize]
    }

    /// Whether sampling distributions exist (at least one [`SdTree::refine`] happened).
    pub fn is_built(&self) -> bool {
        self.built
    }

    /// Records and light samples rejected since the last call because a value was NaN or
    /// infinite, leaving zero: a renderer adds it to the non-finite count it reports.
    pub fn take_nonfinite_records(&self) -> u64 {
        self.nonfinite.swap(0, Relaxed)
    }

    /// Number of fixed-point overflow events so far (0 unless sums exceed `2^80` units or one
    /// contribution exceeds `2^80`). Nonzero means the statistics are not trustworthy.
    pub fn overflow_events(&self) -> u64 {
        self.overflow.load(Relaxed)
    }

    /// The leaf containing `p` (points outside the domain are clamped onto it).
    #[inline]
    pub fn leaf_index(&self, p: Vec3) -> LeafHandle {
        LeafHandle(self.stree.lookup(p).leaf)
    }

    /// The leaf containing `p` with its world-space box.
    #[inline]
    pub fn lookup(&self, p: Vec3) -> SLookup {
        self.stree.lookup(p)
    }

    /// Samples a direction from the guide at `p`: `Some((unit direction, solid-angle pdf))`, or
    /// `None` before the first refinement. `rng` returns numbers in `[0, 1)` (2 per level + 2).
    pub fn sample(&self, p: Vec3, rng: &mut impl FnMut() -> f32) -> Option<(Vec3, f32)> {
        self.sample_leaf(self.leaf_index(p), rng)
    }

    /// [`SdTree::sample`] for a leaf handle.
    pub fn sample_leaf(&self, h: LeafHandle, rng: &mut impl FnMut() -> f32) -> Option<(Vec3, f32)> {
        self.sample_leaf_restricted(h, Restriction::NONE, rng)
    }

    /// The guide at leaf `h` restricted to the cells of a mask, optionally weighted (e.g.
    /// [`crate::CellMask::hemisphere`] or [`crate::CellWeights::cosine`] of a surface's
    /// normal; see [`crate::region`]): pass it to
    /// [`SdTree::sample_leaf_restricted`] and [`SdTree::pdf_leaf_restricted`]. No restriction
    /// before the first refinement or when the cells hold no probability.
    #[inline]
    pub fn restriction_leaf(&self, h: LeafHandle, region: impl Into<CellWeights>) -> Restriction {
        if !self.built {
            return Restriction::NONE;
        }
        self.leaves[h.0 as usize].sampling.restrict(region)
    }

    /// [`SdTree::sample_leaf`] from the guide restricted by `r` (from
    /// [`SdTree::restriction_leaf`] for the same leaf). The pdf is the restricted density's.
    #[inline]
    pub fn sample_leaf_restricted(
        &self,
        h: LeafHandle,
        r: Restriction,
        rng: &mut impl FnMut() -> f32,
    ) -> Option<(Vec3, f32)> {
        if !self.built {
            return None;
        }
        let (uv, p) = self.leaves[h.0 as usize].sampling.sample_restricted(r, rng);
        Some((uv_to_dir(uv), pdf_uv_to_solid_angle(p)))
    }

    /// [`SdTree::pdf_leaf`] of the guide restricted by `r` (from
    /// [`SdTree::restriction_leaf`] for the same leaf).
    #[inline]
    pub fn pdf_leaf_restricted(&self, h: LeafHandle, r: Restriction, dir: Vec3) -> f32 {
        if !self.built {
            return 0.0;
        }
        pdf_uv_to_solid_angle(
            self.leaves[h.0 as usize]
                .sampling
                .pdf_restricted(r, dir_to_uv(dir)),
        )
    }

    /// Asks the processor to start loading leaf `h`'s payload (its learned fraction and the
    /// header of its sampling quadtree) into cache, without waiting for it. A hint only: no
    /// effect on any result. A renderer that looks a leaf up well before it samples there
    /// (e.g. before next-event estimation) calls this, then [`SdTree::prefetch_sampling`]
    /// once other work has passed, so the leaf's cache misses overlap that work instead of
    /// stalling the vertex.
    #[inline]
    pub fn prefetch_leaf(&self, h: LeafHandle) {
        if let Some(leaf) = self.leaves.get(h.0 as usize) {
            prefetch((&leaf.alpha as *const f32).cast());
            prefetch((&leaf.sampling.cache as *const Vec<_>).cast());
        }
    }

    /// Asks the processor to start loading the top nodes of leaf `h`'s sampling quadtree (the
    /// root and the line after it). Reads the leaf's header, so call it after
    /// [`SdTree::prefetch_leaf`] has had time to bring that in. A hint only.
    #[inline]
    pub fn prefetch_sampling(&self, h: LeafHandle) {
        if let Some(leaf) = self.leaves.get(h.0 as usize) {
            prefetch_block(&leaf.sampling.cache, 0);
        }
    }

    /// Solid-angle pdf of the guide sampling `dir` (world space, unit) at `p`; 0 before the first
    /// refinement.
    pub fn pdf(&self, p: Vec3, dir: Vec3) -> f32 {
        self.pdf_leaf(self.leaf_index(p), dir)
    }

    /// [`SdTree::pdf`] for a leaf handle.
    pub fn pdf_leaf(&self, h: LeafHandle, dir: Vec3) -> f32 {
        self.pdf_leaf_restricted(h, Restriction::NONE, dir)
    }

    /// Estimated incident radiance (mean over RGB) arriving at leaf `h` from `dir`, given the
    /// guide's solid-angle pdf of `dir` there (`pdf_leaf(h, dir)`): `flux * pdf`. Zero before
    /// the first refinement. A renderer can use it to decide how much a path is worth
    /// continuing (e.g. for Russian roulette) without another tree lookup.
    #[inline]
    pub fn incident_radiance_leaf(&self, h: LeafHandle, pdf: f32) -> f32 {
        if !self.built {
            return 0.0;
        }
        self.leaves[h.0 as usize].flux * pdf
    }

    /// Records one light (next-event) sample taken at a vertex in leaf `h`: its value per unit
    /// path throughput, `f cos Le w / p_light` averaged over colour channels, 0 when occluded
    /// (thread safe, exact; see [`crate::light`]).
    #[inline]
    pub fn record_light_sample(&self, h: LeafHandle, value: f32) {
        if !value.is_finite() {
            self.nonfinite.fetch_add(1, Relaxed);
            return;
        }
        self.touched.insert(h.0);
        self.leaves[h.0 as usize]
            .light
            .record(value, &self.overflow);
    }

    /// Mean and standard deviation of a light sample's value in leaf `h`, as frozen by the last
    /// [`SdTree::refine`] (zeros before any light sample was recorded there).
    #[inline]
    pub fn light_sample_stats_leaf(&self, h: LeafHandle) -> (f32, f32) {
        let l = &self.leaves[h.0 as usize].light;
        (l.mean, l.std_dev)
    }

    /// Probability alpha of sampling the BSDF rather than the guide at `p`.
    pub fn bsdf_sampling_fraction(&self, p: Vec3) -> f32 {
        self.bsdf_sampling_fraction_leaf(self.leaf_index(p))
    }

    /// [`SdTree::bsdf_sampling_fraction`] for a leaf handle: the fixed value, or
    /// `sigmoid(theta)` clamped to `config.fraction_clamp` when learned.
    pub fn bsdf_sampling_fraction_leaf(&self, h: LeafHandle) -> f32 {
        match self.config.bsdf_sampling_fraction {
            FractionMode::Fixed(a) => a,
            FractionMode::Learned { .. } => {
                let (lo, hi) = self.config.fraction_clamp;
                self.leaves[h.0 as usize].alpha.clamp(lo, hi)
            }
        }
    }

    /// Records one training sample into the building statistics (thread safe, `&self`).
    ///
    /// `rng` supplies random numbers in `[0, 1)` for the stochastic spatial filter (three per
    /// record, only with [`SpatialFilter::Stochastic`]), so the renderer keeps determinism.
    /// See [`Record`] for the validity rules and the radiance convention.
    pub fn record(&self, rec: &Record, rng: &mut impl FnMut() -> f32) {
        self.record_at(rec, &self.stree.lookup(rec.position), rng);
    }

    /// [`SdTree::record`] with the spatial leaf of `rec.position` already looked up: `at` must
    /// be what [`SdTree::lookup`] returns for that position (renderers that sampled from the
    /// guide at the vertex have it and save a lookup).
    pub fn record_at(&self, rec: &Record, at: &SLookup, rng: &mut impl FnMut() -> f32) {
        if !record_is_valid(rec) {
            if record_has_nonfinite(rec) {
                self.nonfinite.fetch_add(1, Relaxed);
            }
            return;
        }
        let w = rec.weight as f64;
        let pm = rec.pdf_mix as f64;
        let uv = dir_to_uv(rec.direction);
        let value = w * rec.radiance as f64 / pm;
        let (qv, ov) = if value > 0.0 && value < MAX_RECORD_VALUE {
            to_fixed(value)
        } else {
            (0, false)
        };
        let (qw, ow) = to_fixed(w);
        if ov || ow {
            self.overflow.fetch_add(1, Relaxed);
        }
        match self.config.spatial_filter {
            SpatialFilter::Nearest => self.deposit_leaf(at.leaf, uv, qv, qw, w, rec),
            SpatialFilter::Stochastic => {
                let pj = stochastic_jitter(rec.position, at, rng);
                let leaf = self.stree.lookup(pj).leaf;
                self.deposit_leaf(leaf, uv, qv, qw, w, rec);
            }
            SpatialFilter::Box => {
                let (ov, vols, pv, pw) = BOX_SCRATCH.with(|sc| {
                    let mut sc = sc.borrow_mut();
                    let (ov, vols, pv, pw) = &mut *sc;
                    spatial_box_overlaps(&self.stree, rec.position, at, ov);
                    vols.clear();
                    vols.extend(ov.iter().map(|o| o.1));
                    split_exact(qv, vols, pv);
                    split_exact(qw, vols, pw);
                    (
                        std::mem::take(ov),
                        std::mem::take(vols),
                        std::mem::take(pv),
                        std::mem::take(pw),
                    )
                });
                let total: f64 = vols.iter().sum();
                for (i, &(leaf, vol)) in ov.iter().enumerate() {
                    self.deposit_leaf(leaf, uv, pv[i], pw[i], w * vol / total, rec);
                }
                // hand the buffers back for the next record on this thread
                BOX_SCRATCH.with(|sc| *sc.borrow_mut() = (ov, vols, pv, pw));
            }
        }
    }

    /// Draws from `rng` exactly what [`SdTree::record`] would draw for `rec`, and records
    /// nothing. A renderer that computes a sample twice (a tile's filter halo) records it
    /// once: elsewhere it calls this, so the sample's later random numbers, and so its value,
    /// are the same in both places.
    pub fn skip_record(&self, rec: &Record, rng: &mut impl FnMut() -> f32) {
        if record_is_valid(rec) && self.config.spatial_filter == SpatialFilter::Stochastic {
            for _ in 0..3 {
                rng();
            }
        }
    }

    /// The learned-fraction state of every spatial leaf, in leaf order (what
    /// [`SdTree::step_fractions`] changes between the passes of an iteration).
    pub fn fraction_states(&self) -> Vec<FractionState> {
        self.leaves.iter().map(|l| l.fraction).collect()
    }

    /// Sets every leaf's learned-fraction state (from [`SdTree::fraction_states`] of a tree
    /// with the same spatial structure): a worker holding the iteration's tree follows the
    /// coordinator's fraction steps this way. Fails if the leaf count differs.
    pub fn set_fraction_states(&mut self, states: &[FractionState]) -> Result<(), StatsError> {
        if states.len() != self.leaves.len() {
            return Err(StatsError::IndexOutOfRange);
        }
        for (l, s) in self.leaves.iter_mut().zip(states) {
            l.fraction = *s;
            l.set_theta_cache();
        }
        Ok(())
    }

    fn deposit_leaf(
        &self,
        leaf: u32,
        uv: glam::Vec2,
        qv: u128,
        qw: u128,
        w_share: f64,
        rec: &Record,
    ) {
        let l = &self.leaves[leaf as usize];
        self.touched.insert(leaf);
        l.building.add_weight(qw, &self.overflow);
        if qv != 0 {
            match self.config.directional_filter {
                DirectionalFilter::Nearest => l.building.deposit(uv, qv, &self.overflow),
                DirectionalFilter::Box => {
                    let cell = l.building.leaf_cell(uv);
                    l.building.splat_box(uv, cell.size, qv, &self.overflow);
                }
            }
        }
        if let FractionMode::Learned { loss } = self.config.bsdf_sampling_fraction {
            if !rec.is_delta && w_share > 0.0 {
                l.grad_of(self.grad_target).accumulate(
                    w_share,
                    loss,
                    rec.product,
                    rec.pdf_bsdf,
                    rec.pdf_guide,
                    rec.pdf_mix,
                    self.config.adam.gradient_clamp,
                    &self.overflow,
                );
            }
        }
    }

    /// Adam steps of every leaf's learned fraction: one per `config.adam.min_batch_weight` of
    /// record weight since the leaf's last step ([`FractionState::step`]). Call it at fixed
    /// points of the schedule, e.g. at the end of every pass, so training is deterministic.
    /// No-op in fixed-fraction mode. Returns the number of leaves stepped.
    pub fn step_fractions(&mut self) -> usize {
        if !matches!(
            self.config.bsdf_sampling_fraction,
            FractionMode::Learned { .. }
        ) {
            return 0;
        }
        let adam = self.config.adam;
        let mut n = 0;
        for l in &mut self.leaves {
            if l.fraction.step(&l.grad, &adam) {
                l.set_theta_cache();
                n += 1;
            }
        }
        n
    }

    /// Where recorded fraction gradients go from now on (and what [`SdTree::take_stats`]
    /// takes): the batch by default.
    pub fn set_grad_target(&mut self, target: GradTarget) {
        self.grad_target = target;
    }

    /// Adds the gradients held in `slot` into the batch and empties the slot: the deferred
    /// unit's step is due ([`GradTarget`]).
    pub fn fold_held(&mut self, slot: HeldSlot) {
        let mut of = 0u64;
        for l in &self.leaves {
            let held = &l.held[slot.index()];
            if held.is_zero() {
                continue;
            }
            let (pos, neg) = (held.pos.each_ref(), held.neg.each_ref());
            let pos = pos.map(|a| a.get());
            let neg = neg.map(|a| a.get());
            l.grad.add_from(&pos, &neg, held.weight.get(), &mut of);
            held.clear();
        }
        self.overflow.fetch_add(of, Relaxed);
    }

    /// End of iteration `k` (0-based, the iteration whose records were just taken):
    /// 1. build every building quadtree bottom-up and make it the sampling tree
    ///    (`sampling := building`), and freeze each leaf's light-sample mean and deviation;
    /// 2. refine the S-tree: a leaf splits while its building W exceeds the threshold of the
    ///    iteration about to start, `c * sqrt(2^(k+1) * spp_per_pass / 4)` (as \[G\] refines at the
    ///    start of iteration k+1); both children copy the whole payload with W halved, and are
    ///    re-tested (the fraction-gradient batches are cleared first: they were measured
    ///    against the sampling trees being replaced); `max_nodes` stops splitting, and so does
    ///    depth [`MAX_SPATIAL_DEPTH`]; the threshold is never taken below 1;
    /// 3. reset every building quadtree from its built sums (rho = `d_tree_threshold`), which
    ///    zeroes the statistics, and zero the light-sample sums.
    ///
    /// With `carry_over` > 0 (see [`crate::carry`]), step 1 first adds each leaf's carried
    /// statistics into its building tree, step 2 counts this iteration's weight only (and a
    /// splitting leaf's two halves share the building sums and the carried weight), and step 3
    /// carries that fraction of the built statistics into the new structure.
    pub fn refine(&mut self, k: u32) {
        let carry_q = crate::carry::quantise(self.config.carry_over);
        for l in &mut self.leaves {
            l.grad.clear();
            l.held.iter().for_each(GradAccum::clear);
            if carry_q > 0 {
                crate::carry::add_prior(&l.building, &l.prior, &self.overflow);
            }
            l.building.build();
            let w = l.building.weight();
            l.flux = if w > 0.0 {
                (l.building.total() / w) as f32
            } else {
                0.0
            };
            l.sampling = l.building.clone().freeze();
            l.light.freeze();
        }
        self.built = true;
        // Floor of one record's weight: with a zero or negative threshold every leaf with any
        // weight would split exponentially.
        let threshold = self.config.split_threshold(k.saturating_add(1)).max(1.0);
        let threshold_fixed = to_fixed(threshold).0;
        let mut work: Vec<u32> = (0..self.stree.nodes.len() as u32)
            .filter(|&i| self.stree.nodes[i as usize].is_leaf())
            .collect();
        work.reverse();
        while let Some(node) = work.pop() {
            if let Some(maxn) = self.config.max_nodes {
                if self.stree.nodes.len() + 2 > maxn {
                    break;
                }
            }
            if self.stree.nodes[node as usize].depth >= MAX_SPATIAL_DEPTH {
                continue;
            }
            let li = self.stree.nodes[node as usize].leaf;
            let w = self.leaves[li as usize].building.weight_fixed();
            let carried = self.leaves[li as usize].prior.weight_fixed();
            if w.saturating_sub(carried) <= threshold_fixed {
                continue;
            }
            let (w0, w1) = (w / 2, w - w / 2);
            let new_li = self.leaves.len() as u32;
            let mut child = self.leaves[li as usize].clone();
            {
                let l = &mut self.leaves[li as usize];
                l.building.set_weight_fixed(w0);
                l.sampling
                    .set_weight_fixed(l.sampling.tree().weight_fixed() / 2);
            }
            child.building.set_weight_fixed(w1);
            if carry_q > 0 {
                // The halves share the statistics the next prior is carried from.
                let parent = &mut self.leaves[li as usize];
                crate::carry::halve_sums_into(&parent.building, &child.building);
                parent.prior.set_weight_fixed(carried / 2);
                child.prior.set_weight_fixed(carried - carried / 2);
            }
            let sw = child.sampling.tree().weight_fixed();
            child.sampling.set_weight_fixed(sw - sw / 2);
            self.leaves.push(child);
            let [c0, c1] = self.stree.split(node, li, new_li);
            work.push(c1);
            work.push(c0);
        }
        self.stree.index();
        let md = self.config.max_d_tree_depth;
        let rho = self.capped_d_tree_threshold(md);
        for l in &mut self.leaves {
            let refined = l.building.refined(rho, md);
            if carry_q > 0 {
                l.prior = crate::carry::carry(&l.building, &refined, carry_q);
            }
            l.building = refined;
            l.light.clear();
        }
        self.hash = OnceLock::new();
        self.touched = TouchedLeaves::new(self.leaves.len());
    }

    /// The quadtree refinement threshold of the last refinement, if `max_dtree_nodes` made it
    /// larger than `d_tree_threshold`.
    pub fn raised_d_tree_threshold(&self) -> Option<f64> {
        self.raised_rho
    }

    /// `d_tree_threshold`, or, when refining every building quadtree with it would make more
    /// than `max_dtree_nodes` nodes, the smallest threshold found (by bisection in log space,
    /// a deterministic function of the tree) that stays within the cap. Records it in
    /// `raised_rho`.
    fn capped_d_tree_threshold(&mut self, max_depth: u32) -> f64 {
        let rho = self.config.d_tree_threshold;
        self.raised_rho = None;
        let Some(cap) = self.config.max_dtree_nodes else {
            return rho;
        };
        let fits = |r: f64| {
            let mut left = cap;
            for l in &self.leaves {
                let n = l.building.refined_node_count(r, max_depth, left);
                if n > left {
                    return false;
                }
                left -= n;
            }
            true
        };
        if fits(rho) {
            return rho;
        }
        // fits(hi) should hold at rho = 1 (one node per non-empty leaf); if even that does not
        // fit, 1 is the best there is.
        let (mut lo, mut hi) = (rho.max(1e-12).ln(), 0.0f64);
        for _ in 0..40 {
            let mid = 0.5 * (lo + hi);
            if fits(mid.exp()) {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        let raised = hi.exp();
        self.raised_rho = Some(raised);
        raised
    }

    /// Size statistics.
    pub fn stats(&self) -> TreeStats {
        let mut hist = Vec::new();
        for n in &self.stree.nodes {
            if n.is_leaf() {
                let d = n.depth as usize;
                if hist.len() <= d {
                    hist.resize(d + 1, 0);
                }
                hist[d] += 1;
            }
        }
        let mut s = TreeStats {
            spatial_nodes: self.stree.nodes.len(),
            leaves: self.leaves.len(),
            depth_histogram: hist,
            overflow_events: self.overflow_events(),
            memory_bytes: std::mem::size_of::<Self>()
                + self.stree.memory_bytes()
                + self.leaves.capacity() * std::mem::size_of::<Leaf>(),
            ..Default::default()
        };
        for (i, l) in self.leaves.iter().enumerate() {
            let a = self.bsdf_sampling_fraction_leaf(LeafHandle(i as u32));
            s.fraction_histogram[((a * 10.0) as usize).min(9)] += 1;
            s.sampling_dtree_nodes += l.sampling.tree().node_count();
            s.building_dtree_nodes += l.building.node_count();
            s.max_dtree_depth = s.max_dtree_depth.max(l.sampling.tree().depth());
            s.memory_bytes +=
                l.sampling.memory_bytes() + l.building.memory_bytes() + l.prior.memory_bytes()
                    - std::mem::size_of::<SamplingDTree>()
                    - 2 * std::mem::size_of::<DTree>();
        }
        s
    }

    /// 64-bit fingerprint of everything statistics refer to: the S-tree and the structure of
    /// every building quadtree. Statistics only apply to a tree with the same fingerprint.
    pub fn structure_hash(&self) -> u64 {
        *self.hash.get_or_init(|| self.compute_structure_hash())
    }

    fn compute_structure_hash(&self) -> u64 {
        let mut h = Hasher64::new();
        h.write_u64(self.stree.nodes.len() as u64);
        for n in &self.stree.nodes {
            h.write_u32(n.axis as u32);
            h.write_u32(n.children[0]);
            h.write_u32(n.children[1]);
            h.write_u32(n.leaf);
        }
        h.write_u64(self.leaves.len() as u64);
        for l in &self.leaves {
            l.building.structure_hash(&mut h);
        }
        h.finish()
    }

    /// Moves this iteration's building statistics (quadtree sums, W, pending fraction gradients,
    /// light-sample sums)
    /// out of the tree, leaving zeros: a worker calls this and ships the result (see
    /// [`IterationStats::encode`]). Only touched leaves and nodes are included. The overflow
    /// counter moves into the statistics too. Call it before [`SdTree::refine`] (the building
    /// trees must not have been built or reset since the records were taken).
    pub fn take_stats(&mut self) -> IterationStats {
        self.take_part(StatsPart::All)
    }

    /// Moves only the pending fraction gradients out of the tree (what a pass end's Adam
    /// steps need), leaving the building statistics (quadtree sums, W, light-sample sums)
    /// and the overflow counter for a later [`SdTree::take_stats`]. The two takes together
    /// are exactly one `take_stats`: merged, they are equal to it, bit for bit. A farm
    /// worker ships each pass's gradients and an iteration's quadtree records once.
    pub fn take_gradients(&mut self) -> IterationStats {
        self.take_part(StatsPart::Gradients)
    }

    fn take_part(&mut self, part: StatsPart) -> IterationStats {
        let all = part == StatsPart::All;
        let mut out = IterationStats {
            structure_hash: self.structure_hash(),
            overflow_events: if all {
                self.overflow.swap(0, Relaxed)
            } else {
                0
            },
            leaves: Vec::new(),
        };
        // The touched set stays for the building statistics' take when only the gradients
        // go now.
        let touched = if all {
            self.touched.drain()
        } else {
            self.touched.list()
        };
        // Only leaves recorded into can hold statistics; within them most nodes are zero,
        // so nodes are read first and written only when they hold something.
        for i in touched {
            let Some(l) = self.leaves.get(i as usize) else {
                continue;
            };
            let grad = l.grad_of(self.grad_target);
            let mut ls = LeafStats {
                leaf: i,
                grad_pos: std::array::from_fn(|k| take_nonzero(&grad.pos[k])),
                grad_neg: std::array::from_fn(|k| take_nonzero(&grad.neg[k])),
                grad_weight: take_nonzero(&grad.weight),
                ..LeafStats::default()
            };
            grad.stepped.set(0);
            if all {
                ls.weight = take_nonzero(&l.building.weight);
                ls.light = l.light.take();
                for (ni, n) in l.building.nodes.iter().enumerate() {
                    let s = n.sums.each_ref().map(take_nonzero);
                    if s.iter().any(|&x| x != 0) {
                        ls.nodes.push((ni as u32, s));
                    }
                }
            }
            if ls.weight != 0
                || ls.grad_pos.iter().any(|&x| x != 0)
                || ls.grad_neg.iter().any(|&x| x != 0)
                || ls.grad_weight != 0
                || ls.light.iter().any(|&x| x != 0)
                || !ls.nodes.is_empty()
            {
                out.leaves.push(ls);
            }
        }
        out
    }

    /// Adds statistics (from [`SdTree::take_stats`] on trees with the same structure, possibly
    /// merged) into this tree's building statistics, exactly (integer addition), the fraction
    /// gradients into `target`. Fails without changing anything if the structure fingerprint
    /// or an index does not match.
    pub fn apply_stats(
        &mut self,
        s: &IterationStats,
        target: GradTarget,
    ) -> Result<(), StatsError> {
        if s.structure_hash != self.structure_hash() {
            return Err(StatsError::StructureMismatch);
        }
        for ls in &s.leaves {
            let Some(l) = self.leaves.get(ls.leaf as usize) else {
                return Err(StatsError::IndexOutOfRange);
            };
            if ls
                .nodes
                .iter()
                .any(|&(n, _)| n as usize >= l.building.nodes.len())
            {
                return Err(StatsError::IndexOutOfRange);
            }
        }
        let mut of = 0u64;
        for ls in &s.leaves {
            let l = &self.leaves[ls.leaf as usize];
            l.building
                .weight
                .set(add_counted(l.building.weight.get(), ls.weight, &mut of));
            l.grad_of(target)
                .add_from(&ls.grad_pos, &ls.grad_neg, ls.grad_weight, &mut of);
            let cur = l.light.sums();
            l.light.set_sums(std::array::from_fn(|k| {
                add_counted(cur[k], ls.light[k], &mut of)
            }));
            for &(n, sums) in &ls.nodes {
                let node = &l.building.nodes[n as usize];
                for q in 0..4 {
                    node.sums[q].set(add_counted(node.sums[q].get(), sums[q], &mut of));
                }
            }
        }
        self.overflow.fetch_add(of + s.overflow_events, Relaxed);
        Ok(())
    }
}

/// What [`SdTree::take_part`] moves out of a tree.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum StatsPart {
    /// Everything recorded: [`SdTree::take_stats`].
    All,
    /// The fraction gradients alone: [`SdTree::take_gradients`].
    Gradients,
}

/// The accumulator's value, leaving zero (written only if it was not zero already).
#[inline]
fn take_nonzero(a: &Acc128) -> u128 {
    let v = a.get();
    if v != 0 {
        a.set(0);
    }
    v
}

/// Largest value `weight * radiance / pdf_mix` one record may deposit: 2^48 (2.8e14); a
/// larger (or non-finite) value changes W only, like a non-finite radiance. A quadtree cell
/// sums records in 128-bit fixed point with 48 fractional bits, room for 2^80: 2^32 records
/// of this size still fit. Larger values (no physical estimate comes near them; a subnormal
/// `pdf_mix` can make them) saturated each record and then wrapped the sums, and a wrapped
/// total made refinement split every cell to the maximum depth (4^20 nodes: out of memory).
pub const MAX_RECORD_VALUE: f64 = (1u64 << 48) as f64;

/// Whether [`SdTree::record`] uses `rec` at all: positive finite weight and mixture pdf,
/// finite radiance, position and direction.
fn record_is_valid(rec: &Record) -> bool {
    let w = rec.weight as f64;
    let pm = rec.pdf_mix as f64;
    w > 0.0
        && w.is_finite()
        && pm > 0.0
        && pm.is_finite()
        && rec.radiance.is_finite()
        && rec.position.is_finite()
        && rec.direction.is_finite()
}

/// Whether one of the values [`record_is_valid`] checks is NaN or infinite (a record
/// rejected for that is counted; one of weight 0 is routine and is not).
fn record_has_nonfinite(rec: &Record) -> bool {
    !(rec.weight.is_finite()
        && rec.pdf_mix.is_finite()
        && rec.radiance.is_finite()
        && rec.position.is_finite()
        && rec.direction.is_finite())
}
