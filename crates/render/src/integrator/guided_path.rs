//! `guided_path`: Mitsuba's path tracer (NEE, power-heuristic MIS, Russian
//! roulette; same `max_depth` / `rr_depth` / `hide_emitters` semantics as
//! [`super::path`]) with directions drawn from a one-sample mixture of the
//! BSDF and an SD-tree guide (Müller et al. 2017, doc sections 2 and 4).
//!
//! * At a vertex with a smooth (non-delta) BSDF component and a built tree the
//!   spatial leaf is looked up once; alpha = its BSDF-sampling fraction. With
//!   probability alpha the BSDF is sampled, else the guide;
//!   `p_mix = alpha p_bsdf + (1 - alpha) p_guide` and the weight is
//!   `f cos / p_mix`. A delta lobe picked by the BSDF has weight
//!   `f / (alpha p_bsdf)` and takes no part in MIS.
//! * NEE is weighted with the power heuristic against the *same* `p_mix`
//!   (same leaf, same alpha), and emitters hit by the sampled direction are
//!   weighted with `p_mix` on the BSDF side ([`mixture_pdf`], [`mis_weight`]).
//! * Russian roulette (`russian_roulette`): Mitsuba's (as `path`: survival
//!   `min(max(throughput) eta^2, 0.95)` from `rr_depth` on); \[G\]'s, which
//!   effectively disables it once the tree is built ([`ppg_survival`]); or guided
//!   (the pathfarm preset): at guided vertices, once pixel estimates exist, from
//!   `guided_rr_depth` on, survival by the path's expected contribution against
//!   the pixel's value ([`guided_survival`]), and Mitsuba's elsewhere. All are
//!   unbiased.
//! * Light splitting (`light_splitting`, the pathfarm preset): in the passes that split
//!   paths, a vertex whose light sample is noisy against the pixel's value (by the leaf's
//!   learned light-sample deviation) takes several, weighed by MIS as one technique of pdf
//!   `n p_light` ([`LIGHT_SPLIT_WINDOW`]). Training passes record every light sample's value
//!   into the leaf's statistics.
//! * Recording (training iterations only) uses the forward-loop suffix-radiance
//!   bookkeeping of [`PathRecorder`]: every contribution added to the pixel is
//!   added to the accumulator of every open vertex; at path end
//!   `L_i = R_i / T_i`. With NEE "always" the emission found by a vertex's own
//!   sampled direction is left out of that vertex (it learns indirect light).
//!
//! All random numbers come from the sample's own [`Rng`]: the image and the
//! recorded statistics are deterministic.
//!
//! Unlike `path`, the estimator runs one path at a time: a batched ("wavefront") form was
//! measured slower, its lanes thinning out at 1 spp a pass
//! (`docs/decisions/guided-one-path-at-a-time.md`).

// `!(x > 0.0)` is used on purpose: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use glam::Vec3;
use pathfarm_bsdf::frame::Frame;
use pathfarm_bsdf::{Bsdf, BsdfFlags};
use pathfarm_guide::{CellMask, CellWeights, LeafHandle, Record, Restriction, SLookup, SdTree};

use super::{camera_hit, depth_limit, emission_mis, light_mis, mitsuba_survival};
use crate::counter::ShardedCounter;
use crate::geometry::{spawn_ray, Ray};
use crate::rng::Rng;
use crate::sampling::power_heuristic;
use crate::scene::Scene;

/// At most this many vertices of a path are recorded (doc section 2).
pub const MAX_RECORDED_VERTICES: usize = 32;

/// What the guided estimator does in the current pass.
#[derive(Clone, Copy, Debug)]
pub struct GuideCtx<'a> {
    /// The SD-tree: sample and pdf read its frozen sampling trees, records go to its
    /// building trees.
    pub tree: &'a SdTree,
    /// Sample from the guide where it applies. false: plain path tracing (the unguided
    /// probe of the path fallback); then `record` must be false too.
    pub guide: bool,
    /// Light sampling (NEE) is done in this pass.
    pub nee: bool,
    /// NEE mode "always": vertices learn indirect light only.
    pub indirect_only: bool,
    /// NEE mode "kickstart" while active: light samples are recorded too and every
    /// record has weight 0.5.
    pub kickstart: bool,
    /// Record training samples (training iterations only).
    pub record: bool,
    /// Guided Russian roulette: each pixel's estimated value (index `y * width + x`), from
    /// the previous iterations. `None`: Mitsuba's throughput-based roulette everywhere.
    pub pixel_estimate: Option<&'a [f32]>,
    /// Depth from which guided roulette (with `pixel_estimate`, at guided vertices) applies
    /// (`guided_rr_depth`); elsewhere roulette starts at `rr_depth`.
    pub guided_rr_depth: u32,
    /// Russian roulette of Müller's reference implementation (`russian_roulette` = `ppg`):
    /// from `rr_depth` on, at vertices with a smooth BSDF whose sampled lobe is not delta,
    /// survival `clamp(max(throughput) eta^2, 0.1, 0.99)` before the tree is built and 0.99
    /// after; no roulette elsewhere. Takes precedence over `pixel_estimate`.
    pub ppg_roulette: bool,
    /// At BSDFs that cannot transmit, sample the guide only in the hemisphere they reflect
    /// into (`guide_hemisphere`, see [`guide_mask`]).
    pub hemisphere: bool,
    /// With `hemisphere`: weight the hemisphere's cells by the clamped cosine
    /// (`guide_cosine`, see [`guide_region`]).
    pub cosine: bool,
    /// Guided splitting (see [`SPLIT_WINDOW`]) in passes that record nothing; needs
    /// `pixel_estimate`.
    pub split: bool,
    /// Light splitting (see [`LIGHT_SPLIT_WINDOW`]) in this pass; needs `pixel_estimate`.
    pub light_split: bool,
    /// Counts the extra paths splitting made (one add per camera sample that split).
    pub splits: Option<&'a ShardedCounter>,
    /// Counts the extra light samples light splitting took (one add per camera sample).
    pub light_splits: Option<&'a ShardedCounter>,
    /// Counts the rays traced (camera, continuation and shadow rays), one add per path.
    pub rays: Option<&'a ShardedCounter>,
}

/// The mixture pdf `alpha p_bsdf + (1 - alpha) p_guide` (just `p_bsdf` when unguided).
#[inline]
pub fn mixture_pdf(guided: bool, alpha: f32, p_bsdf: f32, p_guide: f32) -> f32 {
    if guided {
        alpha * p_bsdf + (1.0 - alpha) * p_guide
    } else {
        p_bsdf
    }
}

/// The shading normal on the side of `wi` (local) at a BSDF that cannot transmit: the
/// hemisphere around it is where alone the BSDF is nonzero. None for transmissive BSDFs.
#[inline]
fn reflecting_normal(flags: BsdfFlags, frame: &Frame, wi: Vec3) -> Option<Vec3> {
    (!flags.transmission).then(|| if wi.z < 0.0 { -frame.n } else { frame.n })
}

/// The cells the guide samples from at a vertex (see [`pathfarm_guide::region`]): with
/// `hemisphere`, at a BSDF that cannot transmit, the hemisphere of the shading normal on the
/// side of `wi` (local), where alone the BSDF is nonzero; else everything.
#[inline]
pub fn guide_mask(hemisphere: bool, flags: BsdfFlags, frame: &Frame, wi: Vec3) -> CellMask {
    match reflecting_normal(flags, frame, wi) {
        Some(n) if hemisphere => CellMask::hemisphere(n),
        _ => CellMask::ALL,
    }
}

/// [`guide_mask`], and with `cosine` the mask's cells weighted by the clamped cosine of the
/// same normal ([`CellWeights::cosine`]): the guide then samples incident radiance x cosine.
#[inline]
pub fn guide_region(
    hemisphere: bool,
    cosine: bool,
    flags: BsdfFlags,
    frame: &Frame,
    wi: Vec3,
) -> CellWeights {
    match reflecting_normal(flags, frame, wi) {
        Some(n) if hemisphere && cosine => CellWeights::cosine(n),
        Some(n) if hemisphere => CellMask::hemisphere(n).into(),
        _ => CellWeights::ALL,
    }
}

/// The unrestricted guide's density in the direction of `ms` (its `p_guide` is the restricted
/// one): what guided roulette's radiance estimate (flux x pdf) needs. 0 where the restriction
/// leaves the direction out. The cell's weight is looked up by [`CellMask::cell_of_dir`] (no
/// arctangent; 1.7 % of a veach-ajar render with `dir_to_uv`), which may pick the neighbouring
/// quarter within rounding of its edge: that only moves a survival probability. (Unweighted
/// cells have weight exactly 1, so a plain mask divides by 1.)
#[inline]
fn unrestricted_guide_pdf(r: &Restriction, ms: &MixtureSample) -> f32 {
    ms.p_guide * r.mass / r.weight[CellMask::cell_of_dir(ms.wo_world) as usize]
}

/// Power-heuristic weight of the strategy with pdf `a` against the one with `b` (light
/// sample: `mis_weight(p_light, p_mix)`; emitter hit: `mis_weight(p_mix, p_light)`).
#[inline]
pub fn mis_weight(a: f32, b: f32) -> f32 {
    power_heuristic(a, b)
}

/// Guide state at one vertex: the leaf, whether guiding applies, and alpha.
#[derive(Clone, Copy, Debug)]
pub struct VertexGuide {
    /// The spatial leaf of the vertex (with its box, which recording reuses).
    pub at: SLookup,
    /// Guiding applies here: the tree is built and the BSDF has a smooth component. False: the
    /// BSDF alone is sampled and `alpha` is 1.
    pub guided: bool,
    /// The leaf's learned BSDF-sampling fraction: the probability of sampling the BSDF rather than
    /// the guide (1 when unguided).
    pub alpha: f32,
    /// The part of the sphere the guide samples from (see [`pathfarm_guide::region`]):
    /// everything, or the hemisphere an opaque surface reflects into.
    pub region: Restriction,
}

impl VertexGuide {
    /// Looks the leaf up once, at a vertex with a smooth BSDF. Guiding applies once the tree
    /// is built.
    #[inline]
    pub fn at(tree: &SdTree, p: Vec3, region: impl Into<CellWeights>) -> Self {
        let mut g = Self::lookup(tree, p);
        g.resolve(tree, region);
        g
    }

    /// The first half of [`VertexGuide::at`]: the leaf, with its payload requested from
    /// memory ([`SdTree::prefetch_leaf`]) but not read. [`VertexGuide::resolve`] must run
    /// before the guide is used (sampling, pdf).
    #[inline]
    pub fn lookup(tree: &SdTree, p: Vec3) -> Self {
        let at = tree.lookup(p);
        let guided = tree.is_built();
        if guided {
            tree.prefetch_leaf(LeafHandle(at.leaf));
        }
        Self {
            at,
            guided,
            alpha: 1.0,
            region: Restriction::NONE,
        }
    }

    /// The second half of [`VertexGuide::at`]: reads the leaf's sampling fraction, restricts
    /// the guide to `region`, a mask or weighted cells ([`CellWeights::ALL`]: no restriction;
    /// see [`guide_region`]), and requests its quadtree's top nodes
    /// ([`SdTree::prefetch_sampling`]).
    #[inline]
    pub fn resolve(&mut self, tree: &SdTree, region: impl Into<CellWeights>) {
        if self.guided {
            tree.prefetch_sampling(self.leaf());
            self.alpha = tree.bsdf_sampling_fraction_leaf(self.leaf());
            self.region = tree.restriction_leaf(self.leaf(), region);
        }
    }

    /// The vertex's spatial leaf.
    #[inline]
    pub fn leaf(&self) -> LeafHandle {
        LeafHandle(self.at.leaf)
    }

    /// No guiding at this vertex (a BSDF without smooth components): the BSDF alone.
    pub fn unguided() -> Self {
        Self {
            at: SLookup::default(),
            guided: false,
            alpha: 1.0,
            region: Restriction::NONE,
        }
    }

    /// `p_mix` of the world direction `wo_world` (local `wo`) and its parts
    /// `(p_mix, p_bsdf, p_guide)`: what NEE weighs against.
    #[inline]
    pub fn pdf(
        &self,
        tree: &SdTree,
        bsdf: &Bsdf,
        wi: Vec3,
        wo: Vec3,
        wo_world: Vec3,
    ) -> (f32, f32, f32) {
        let p_bsdf = bsdf.pdf(wi, wo);
        let p_guide = if self.guided {
            tree.pdf_leaf_restricted(self.leaf(), self.region, wo_world)
        } else {
            0.0
        };
        (
            mixture_pdf(self.guided, self.alpha, p_bsdf, p_guide),
            p_bsdf,
            p_guide,
        )
    }
}

/// A direction drawn from the BSDF/guide mixture.
#[derive(Clone, Copy, Debug, Default)]
pub struct MixtureSample {
    /// Local (shading-frame) direction.
    pub wo: Vec3,
    /// World direction.
    pub wo_world: Vec3,
    /// Throughput factor: `f cos / p_mix`, or `f / (alpha p_bsdf)` for a delta lobe.
    pub weight: Vec3,
    /// `f cos` (zero for delta lobes).
    pub fcos: Vec3,
    /// Mixture pdf (for a delta lobe `alpha` times the lobe probability).
    pub p_mix: f32,
    /// The BSDF's solid-angle pdf of `wo` (for a delta lobe, its lobe probability).
    pub p_bsdf: f32,
    /// The guide's solid-angle pdf of `wo_world` (0 when unguided or for a delta lobe).
    pub p_guide: f32,
    /// The direction came from a delta lobe of the BSDF: it takes no part in MIS and is not
    /// recorded.
    pub delta: bool,
    /// Relative IOR of the crossing (1 for reflection), from the actual direction.
    pub eta: f32,
}

/// Relative IOR of the crossing from local `wi` to `wo` (1 for reflection). Only the rough
/// dielectric has smooth transmission, so only it can get a guide-sampled refraction.
#[inline]
fn crossing_eta(bsdf: &Bsdf, wi: Vec3, wo: Vec3) -> f32 {
    if wi.z * wo.z >= 0.0 {
        return 1.0;
    }
    match bsdf {
        Bsdf::RoughDielectric(b) => {
            if wi.z > 0.0 {
                b.eta
            } else {
                1.0 / b.eta
            }
        }
        _ => 1.0,
    }
}

/// [`Scene::bsdf_at`] kept out of line here. The path integrator inlines it (its shading
/// loop is small and the call's stack round trip stalled it), but inlined into this much
/// larger loop body it cost guided rendering: out of line is 1.3 % faster on veach-ajar
/// (bench/ab.py, 6 reps, 1.006-1.017, images identical).
#[inline(never)]
fn bsdf_at_outlined<'s>(
    scene: &'s Scene,
    si: &crate::geometry::SurfaceInteraction,
    d: Vec3,
) -> (Bsdf<'s>, Frame) {
    scene.bsdf_at(si, d)
}

/// [`sample_mixture`] into `out` (false: absorbed, `out` unchanged). The integrator's form:
/// an `Option<MixtureSample>` returned through memory was written field by field and read
/// back in 32-byte blocks, a store-forwarding stall at every vertex; written into the
/// caller's variable, its fields are read one by one.
#[inline(never)]
fn sample_mixture_into(
    tree: &SdTree,
    g: &VertexGuide,
    bsdf: &Bsdf,
    frame: &Frame,
    wi: Vec3,
    rng: &mut Rng,
    out: &mut MixtureSample,
) -> bool {
    sample_mixture(tree, g, bsdf, frame, wi, rng)
        .map(|ms| *out = ms)
        .is_some()
}

/// Samples the mixture at one vertex. `None` means the path is absorbed.
#[inline]
pub fn sample_mixture(
    tree: &SdTree,
    g: &VertexGuide,
    bsdf: &Bsdf,
    frame: &Frame,
    wi: Vec3,
    rng: &mut Rng,
) -> Option<MixtureSample> {
    let use_bsdf = !g.guided || rng.next_f32() < g.alpha;
    if use_bsdf {
        let bs = bsdf.sample(wi, rng.next_f32(), rng.next_2d())?;
        let wo_world = frame.to_world(bs.wo);
        if bs.lobe.delta {
            return Some(MixtureSample {
                wo: bs.wo,
                wo_world,
                weight: bs.weight / g.alpha,
                fcos: Vec3::ZERO,
                p_mix: g.alpha * bs.pdf,
                p_bsdf: bs.pdf,
                p_guide: 0.0,
                delta: true,
                eta: bs.eta,
            });
        }
        if !g.guided {
            return Some(MixtureSample {
                wo: bs.wo,
                wo_world,
                weight: bs.weight,
                fcos: bs.weight * bs.pdf,
                p_mix: bs.pdf,
                p_bsdf: bs.pdf,
                p_guide: 0.0,
                delta: false,
                eta: bs.eta,
            });
        }
        // A non-delta BSDF sample carries its own pdf and f cos / pdf (the bsdf crate's
        // tests check that they equal `pdf` and `eval / pdf`), so only the guide's pdf is new.
        let fcos = bs.weight * bs.pdf;
        let p_guide = tree.pdf_leaf_restricted(g.leaf(), g.region, wo_world);
        let p_mix = mixture_pdf(true, g.alpha, bs.pdf, p_guide);
        finish(bs.wo, wo_world, fcos, p_mix, bs.pdf, p_guide, bs.eta)
    } else {
        // The guide's sampler returns the same pdf `pdf_leaf` gives for that direction.
        let (wo_world, p_guide) =
            tree.sample_leaf_restricted(g.leaf(), g.region, &mut || rng.next_f32())?;
        let wo = frame.to_local(wo_world);
        let fcos = bsdf.eval(wi, wo);
        let p_bsdf = bsdf.pdf(wi, wo);
        let p_mix = mixture_pdf(true, g.alpha, p_bsdf, p_guide);
        finish(
            wo,
            wo_world,
            fcos,
            p_mix,
            p_bsdf,
            p_guide,
            crossing_eta(bsdf, wi, wo),
        )
    }
}

#[inline]
fn finish(
    wo: Vec3,
    wo_world: Vec3,
    fcos: Vec3,
    p_mix: f32,
    p_bsdf: f32,
    p_guide: f32,
    eta: f32,
) -> Option<MixtureSample> {
    if !(p_mix > 0.0) || !(fcos.max_element() > 0.0) {
        return None;
    }
    let weight = fcos / p_mix;
    if !weight.is_finite() {
        return None;
    }
    Some(MixtureSample {
        wo,
        wo_world,
        weight,
        fcos,
        p_mix,
        p_bsdf,
        p_guide,
        delta: false,
        eta,
    })
}

/// One recorded path vertex (doc section 2).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RecVertex {
    /// The vertex's position, in world space.
    pub position: Vec3,
    /// The guide's spatial leaf at `position` (from the vertex's [`VertexGuide`]).
    pub at: SLookup,
    /// The sampled direction leaving the vertex, in world space (unit).
    pub direction: Vec3,
    /// Throughput including this bounce's `f cos / p_mix` (before Russian roulette).
    pub throughput: Vec3,
    /// `f cos` of the sampled direction (BSDF value times the cosine; not divided by any pdf).
    pub fcos: Vec3,
    /// Mixture pdf (solid angle) the direction was sampled with.
    pub p_mix: f32,
    /// The BSDF's solid-angle pdf of the direction.
    pub p_bsdf: f32,
    /// The guide's solid-angle pdf of the direction.
    pub p_guide: f32,
    /// Statistical weight (1, or 0.5 while NEE kick-start is active).
    pub weight: f32,
    /// Radiance accumulator R_i: the contributions added to the pixel since the vertex.
    pub acc: Vec3,
}

impl RecVertex {
    /// `L_i = R_i / T_i` per channel where `T_i p_mix > 1e-4`, else 0.
    pub fn incident_radiance(&self) -> Vec3 {
        let f = |r: f32, t: f32| if t * self.p_mix > 1e-4 { r / t } else { 0.0 };
        Vec3::new(
            f(self.acc.x, self.throughput.x),
            f(self.acc.y, self.throughput.y),
            f(self.acc.z, self.throughput.z),
        )
    }

    /// The guide record of this vertex (`learn_fraction`: fill the fraction-gradient fields).
    pub fn record(&self, learn_fraction: bool) -> Record {
        let l = self.incident_radiance();
        let mean = |v: Vec3| (v.x + v.y + v.z) / 3.0;
        Record {
            position: self.position,
            direction: self.direction,
            radiance: mean(l),
            pdf_mix: self.p_mix,
            weight: self.weight,
            product: if learn_fraction {
                mean(l * self.fcos)
            } else {
                0.0
            },
            pdf_bsdf: self.p_bsdf,
            pdf_guide: self.p_guide,
            is_delta: false,
        }
    }
}

/// Forward-loop suffix-radiance bookkeeping for one path. Costs nothing until the first
/// [`PathRecorder::push`] (paths that are not recorded never touch it).
#[derive(Clone, Debug, Default)]
pub struct PathRecorder {
    /// The open vertices (at most [`MAX_RECORDED_VERTICES`]).
    v: Vec<RecVertex>,
    /// The last pushed vertex is the path vertex whose sampled direction the next hit
    /// lies along.
    last_is_previous: bool,
}

impl PathRecorder {
    /// The open vertices.
    pub fn vertices(&self) -> &[RecVertex] {
        &self.v
    }

    /// Opens a vertex for the direction just sampled (false when full).
    pub fn push(&mut self, v: RecVertex) -> bool {
        if self.v.len() >= MAX_RECORDED_VERTICES {
            self.last_is_previous = false;
            return false;
        }
        if self.v.capacity() == 0 {
            self.v.reserve_exact(MAX_RECORDED_VERTICES);
        }
        self.v.push(RecVertex {
            acc: Vec3::ZERO,
            ..v
        });
        self.last_is_previous = true;
        true
    }

    /// The path went on from a vertex that was not recorded (delta lobe, full buffer).
    pub fn skip(&mut self) {
        self.last_is_previous = false;
    }

    /// A contribution `c` added to the pixel (NEE, or emission with `indirect_only` false).
    #[inline]
    pub fn add(&mut self, c: Vec3) {
        for v in &mut self.v {
            v.acc += c;
        }
    }

    /// Emission `c` found by the direction sampled at the previous vertex. With
    /// `indirect_only` (NEE always) it is withheld from that vertex when that vertex did NEE
    /// (`prev_nee`): it learns indirect light only.
    #[inline]
    pub fn add_emission(&mut self, c: Vec3, indirect_only: bool, prev_nee: bool) {
        let end = if indirect_only && prev_nee && self.last_is_previous {
            self.v.len() - 1
        } else {
            self.v.len()
        };
        for v in &mut self.v[..end] {
            v.acc += c;
        }
    }

    /// Deposits every vertex into the tree's building statistics.
    pub fn commit(&self, tree: &SdTree, learn_fraction: bool, rng: &mut Rng) {
        for v in self.vertices() {
            tree.record_at(&v.record(learn_fraction), &v.at, &mut || rng.next_f32());
        }
    }
}

/// Guided Russian roulette keeps every path whose expected remaining contribution is at least
/// this fraction of the pixel's estimated value (the weight window's lower edge).
pub const ROULETTE_WINDOW: f32 = 0.25;
/// Lowest survival probability of guided Russian roulette: bounds the weight of survivors where
/// the guide wrongly predicts no light.
pub const ROULETTE_MIN_SURVIVAL: f32 = 0.2;
/// Guided Russian roulette estimates the incident radiance along the sampled direction as
/// `flux * (b p_guide + (1 - b) / 4 pi)` with this `b`: half the guide's directional estimate,
/// half the leaf's mean, so that a young, noisy quadtree cannot predict "no light" outright
/// (white furnace: the standard error of the image mean is 1.5x lower than with b = 1;
/// veach-ajar variance x rays: b = 1: 0.119, 0.5: 0.122, 0 (leaf mean only): 0.126).
pub const ROULETTE_DIRECTIONAL: f32 = 0.5;

/// Survival probability of guided Russian roulette: the path's expected remaining contribution
/// `expected` (throughput x the guide's incident-radiance estimate) relative to
/// [`ROULETTE_WINDOW`] x the pixel's estimated value, clamped to
/// `[ROULETTE_MIN_SURVIVAL, 1]`; NaN survives. (Vorba and Křivánek 2016's weight window,
/// without splitting. Measured on veach-ajar 160x90, final iteration, variance x rays per
/// sample with minimum survival 0.1: window 1: 0.158, 0.5: 0.132, 0.25: 0.122, 0.1: 0.123;
/// window 0.25 with minimum 0.05: 0.133, 0.2: 0.119; Mitsuba's throughput roulette: 0.239.)
#[inline]
pub fn guided_survival(expected: f32, pixel_value: f32) -> f32 {
    let q = expected / (pixel_value * ROULETTE_WINDOW);
    if q >= ROULETTE_MIN_SURVIVAL {
        q.min(1.0)
    } else if q.is_nan() {
        1.0
    } else {
        ROULETTE_MIN_SURVIVAL
    }
}

/// Survival probability of Müller's reference roulette (see [`GuideCtx::ppg_roulette`]):
/// `guided_vertex` = smooth BSDF and a non-delta sampled lobe.
#[inline]
#[allow(clippy::manual_clamp)] // clamp would keep NaN; max/min map it to the lower bound
pub fn ppg_survival(guided_vertex: bool, built: bool, throughput_max: f32, eta: f32) -> f32 {
    if !guided_vertex {
        1.0
    } else if built {
        0.99
    } else {
        // NaN survives with the lower bound (max/min drop NaN operands).
        (throughput_max * eta * eta).max(0.1).min(0.99)
    }
}

/// Guided splitting (the upper edge of the weight window, Vorba and Křivánek 2016): at a
/// guided vertex from `rr_depth - 1` on, in a pass that records nothing, a path whose expected
/// contribution (throughput x the leaf's mean incident radiance) exceeds this multiple of the
/// pixel's estimated value is split into `expected / (SPLIT_WINDOW x value)` copies
/// (stochastically rounded, at most [`MAX_SPLIT`]), each sampling its own direction with
/// `1 / copies` of the throughput. Window 2 measured best (`docs/decisions/splitting.md`).
pub const SPLIT_WINDOW: f32 = 2.0;
/// Most copies one split makes.
pub const MAX_SPLIT: u32 = 4;
/// Most paths one camera sample may grow into by splitting.
pub const MAX_PATHS_PER_SAMPLE: u32 = 16;

/// Light splitting (`light_splitting`): at a guided vertex, in the passes that split paths,
/// the light sample is taken `n` times, `n` = throughput x the standard deviation of one
/// light sample's value learned in the vertex's leaf ([`SdTree::light_sample_stats_leaf`]),
/// over this multiple of the pixel's estimated value (stochastically rounded, at most
/// [`MAX_LIGHT_SAMPLES`]); each sample counts `1 / n`, and MIS weighs them as one technique
/// of pdf `n p_light` (also on the emitter-hit side). The deviation, not the mean, decides:
/// a bright but certain light sample gains nothing from repeats. Window 1 with at most 4
/// samples measured best (`docs/decisions/splitting.md`).
pub const LIGHT_SPLIT_WINDOW: f32 = 1.0;
/// Most light samples light splitting takes at one vertex.
pub const MAX_LIGHT_SAMPLES: u32 = 4;

/// `r` rounded stochastically by `u` in [0, 1), clamped to `[1, max]` (1 for NaN).
#[inline]
fn window_count(r: f32, max: u32, u: f32) -> u32 {
    if !(r > 1.0) || !r.is_finite() {
        return 1;
    }
    let r = r.min(max as f32);
    let n = r.floor();
    (n as u32 + (u < r - n) as u32).clamp(1, max)
}

/// Number of copies a path splits into at a vertex (1: no split); `u` in [0, 1) rounds
/// stochastically. Depends on nothing the copies sample, so splitting stays unbiased.
#[inline]
pub fn split_count(expected: f32, pixel_value: f32, u: f32) -> u32 {
    window_count(expected / (pixel_value * SPLIT_WINDOW), MAX_SPLIT, u)
}

/// Number of light samples at a vertex (see [`LIGHT_SPLIT_WINDOW`]): `deviation` is the
/// throughput times the leaf's light-sample standard deviation. Depends on nothing the light
/// samples draw, so the estimate stays unbiased.
#[inline]
pub fn light_sample_count(deviation: f32, pixel_value: f32, u: f32) -> u32 {
    window_count(
        deviation / (pixel_value * LIGHT_SPLIT_WINDOW),
        MAX_LIGHT_SAMPLES,
        u,
    )
}

/// A path's expected remaining contribution at a guided vertex, the quantity both edges of
/// the weight window compare with the pixel's value: mean throughput x the leaf's incident
/// radiance estimate `flux x pdf` (see [`SdTree::incident_radiance_leaf`]).
#[inline]
fn expected_contribution(tree: &SdTree, vg: &VertexGuide, throughput: Vec3, pdf: f32) -> f32 {
    let l = tree.incident_radiance_leaf(vg.leaf(), pdf);
    (throughput.x + throughput.y + throughput.z) / 3.0 * l
}

/// A path vertex from which directions are sampled: what a split copy resumes from.
#[derive(Clone, Copy)]
struct Vertex<'s> {
    si: crate::geometry::SurfaceInteraction,
    bsdf: Bsdf<'s>,
    frame: Frame,
    wi: Vec3,
    smooth: bool,
    vg: VertexGuide,
    /// NEE was done at this vertex.
    nee: bool,
    /// Light samples taken at this vertex (MIS of an emitter hit by its sampled direction
    /// weighs against `light_samples x p_light`).
    light_samples: f32,
    /// Throughput arriving at the vertex (before its bounce).
    throughput: Vec3,
    eta: f32,
    /// Path depth of the vertex (segments before it).
    depth: u32,
}

/// Radiance along the camera ray `ray` of pixel `pixel` (index `y * width + x`), guided by
/// `g.tree`.
///
/// The loop of [`GuidedPath`]'s steps: arrive at a surface (emission, next-event estimation,
/// splitting), then bounce (mixture sampling, recording, roulette); a path that ends resumes
/// the next split copy waiting at its vertex, until none is left.
pub fn li<const ENV: bool, const ANALYTIC: bool>(
    scene: &Scene,
    g: &GuideCtx,
    mut ray: Ray,
    rng: &mut Rng,
    pixel: usize,
    owned: bool,
) -> Vec3 {
    if scene.path.max_depth == 0 {
        return Vec3::ZERO;
    }
    let mut path = GuidedPath::new(scene, g, pixel, owned, ray.o);
    let Some(mut hit) = camera_hit::<ANALYTIC>(scene, &mut ray) else {
        if let (Some(c), true) = (g.rays, owned) {
            c.add(path.rays);
        }
        return Vec3::ZERO;
    };
    // A split copy waiting to resume at its vertex's direction sampling.
    let mut resume: Option<Vertex> = None;
    // The vertex to bounce from, written in place (a vertex is a few hundred bytes: returned
    // by value it went through memory twice a bounce, measurably slower).
    let mut vertex: Option<Vertex> = None;
    loop {
        let ready = match resume.take() {
            Some(v) => {
                vertex = Some(v);
                true
            }
            None => path.arrive::<ENV, ANALYTIC>(&ray, hit, rng, &mut vertex),
        };
        let goes_on = match (&vertex, ready) {
            (Some(v), true) => path.bounce::<ANALYTIC>(v, rng, &mut ray, &mut hit),
            _ => false,
        };
        if !goes_on {
            // The current path ends: resume the next pending split copy, or stop.
            match path.pending.pop() {
                Some(v) => resume = Some(v),
                None => break,
            }
        }
    }
    path.finish(rng)
}

/// One camera sample's paths in flight (the path and the split copies waiting to resume),
/// what they have found and what they record.
struct GuidedPath<'a> {
    scene: &'a Scene,
    g: &'a GuideCtx<'a>,
    pixel: usize,
    /// The pixel is the sample's tile's own (a halo sample has no side effects).
    owned: bool,
    max_depth: u32,
    rec_weight: f32,
    /// The pixel's estimated value where splitting applies (None: no splitting).
    split_value: Option<f32>,
    /// The pixel's estimated value where light splitting applies.
    light_split_value: Option<f32>,
    extra_light_samples: u64,
    pending: Vec<Vertex<'a>>,
    paths: u32,
    rec: PathRecorder,
    throughput: Vec3,
    result: Vec3,
    eta: f32,
    depth: u32,
    prev_p: Vec3,
    prev_pdf: f32,
    prev_delta: bool,
    prev_nee: bool,
    prev_light_samples: f32,
    rays: u64,
}

impl<'a> GuidedPath<'a> {
    fn new(scene: &'a Scene, g: &'a GuideCtx<'a>, pixel: usize, owned: bool, origin: Vec3) -> Self {
        // Splitting needs the pixel estimate of guided roulette, and is off while recording
        // (a recorded path is one chain of vertices).
        let split_value = match g.pixel_estimate {
            Some(est) if g.split && !g.record => est.get(pixel).copied().filter(|v| *v > 0.0),
            _ => None,
        };
        let light_split_value = match g.pixel_estimate {
            Some(est) if g.light_split => est.get(pixel).copied().filter(|v| *v > 0.0),
            _ => None,
        };
        Self {
            scene,
            g,
            pixel,
            owned,
            max_depth: depth_limit(scene.path.max_depth),
            rec_weight: if g.kickstart { 0.5 } else { 1.0 },
            split_value,
            light_split_value,
            extra_light_samples: 0,
            pending: Vec::new(),
            paths: 1,
            rec: PathRecorder::default(),
            throughput: Vec3::ONE,
            result: Vec3::ZERO,
            eta: 1.0,
            depth: 0,
            prev_p: origin,
            prev_pdf: 1.0,
            prev_delta: true,
            prev_nee: false,
            prev_light_samples: 1.0,
            rays: 1,
        }
    }

    /// Emission `le` found by the last direction sample, MIS-weighted against the light
    /// technique of the vertex it left (pdf `p_light` a sample).
    #[inline(always)]
    fn emitted(&mut self, le: Vec3, p_light: impl FnOnce() -> f32) {
        let light_samples = if self.prev_nee {
            self.prev_light_samples
        } else {
            0.0
        };
        let w = emission_mis(self.prev_pdf, self.prev_delta, light_samples, p_light);
        let c = self.throughput * le * w;
        self.result += c;
        if self.g.record {
            self.rec
                .add_emission(c, self.g.indirect_only, self.prev_nee);
        }
    }

    /// The path arrives along `ray` at `hit`: emission, then (unless it ends here: false) the
    /// vertex to bounce from into `out`, after its light samples and splitting.
    #[inline(always)]
    fn arrive<const ENV: bool, const ANALYTIC: bool>(
        &mut self,
        ray: &Ray,
        hit: Option<crate::geometry::Hit>,
        rng: &mut Rng,
        out: &mut Option<Vertex<'a>>,
    ) -> bool {
        let (scene, lights) = (self.scene, &self.scene.lights);
        let Some(h) = hit else {
            if ENV {
                let le = lights.environment_radiance(ray.d);
                self.emitted(le, || lights.environment_pdf(ray.d));
            }
            return false;
        };
        let si = scene.accel.interaction(ray, &h);
        if let Some(light) = scene.shape_light[si.shape as usize] {
            let le = lights.area_radiance(light, si.ns, -ray.d);
            if le != Vec3::ZERO {
                let prev_p = self.prev_p;
                self.emitted(le, || lights.area_pdf(light, prev_p, si.p, si.ns));
            }
        }
        if self.depth + 1 >= self.max_depth {
            return false;
        }
        let (bsdf, frame) = bsdf_at_outlined(scene, &si, ray.d);
        let wi = frame.to_local(-ray.d);
        let flags = bsdf.flags();
        // The leaf's payload is requested now and read after the light sample, so that its
        // cache misses overlap the light sampling.
        let mut vg = if flags.smooth && self.g.guide {
            VertexGuide::lookup(self.g.tree, si.p)
        } else {
            VertexGuide::unguided()
        };
        let region = if vg.guided {
            guide_region(self.g.hemisphere, self.g.cosine, flags, &frame, wi)
        } else {
            CellWeights::ALL
        };
        let do_nee = self.g.nee && flags.smooth;
        let light_samples = if do_nee {
            self.next_event::<ANALYTIC>(&si, &bsdf, &frame, wi, &mut vg, region, rng)
        } else {
            vg.resolve(self.g.tree, region);
            if self.g.nee {
                rng.next_f32();
                rng.next_2d();
            }
            1
        };
        let v = out.insert(Vertex {
            si,
            bsdf,
            frame,
            wi,
            smooth: flags.smooth,
            vg,
            nee: do_nee,
            light_samples: light_samples as f32,
            throughput: self.throughput,
            eta: self.eta,
            depth: self.depth,
        });
        self.split(v, rng);
        true
    }

    /// Next-event estimation at a smooth vertex, weighted against the mixture pdf: one light
    /// sample, or with light splitting as many as the leaf's light-sample deviation asks
    /// for (one technique of `n p_light`). Resolves `vg` after the first light sample (its
    /// cache misses overlap the sampling). Records the light samples' values in training
    /// passes. Returns the number of light samples taken.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn next_event<const ANALYTIC: bool>(
        &mut self,
        si: &crate::geometry::SurfaceInteraction,
        bsdf: &Bsdf,
        frame: &Frame,
        wi: Vec3,
        vg: &mut VertexGuide,
        region: CellWeights,
        rng: &mut Rng,
    ) -> u32 {
        let (accel, lights, tree, g) = (&self.scene.accel, &self.scene.lights, self.g.tree, self.g);
        let mut ls = lights.sample(accel, si.p, rng.next_f32(), rng.next_2d());
        vg.resolve(tree, region);
        let mut light_samples = 1u32;
        if let Some(value) = self.light_split_value.filter(|_| vg.guided) {
            let (_, std_dev) = tree.light_sample_stats_leaf(vg.leaf());
            let t = self.throughput;
            let deviation = (t.x + t.y + t.z) / 3.0 * std_dev;
            light_samples = light_sample_count(deviation, value, rng.next_f32());
            self.extra_light_samples += u64::from(light_samples - 1);
        }
        let n = light_samples as f32;
        for i in 0..light_samples {
            if i > 0 {
                ls = lights.sample(accel, si.p, rng.next_f32(), rng.next_2d());
            }
            // The light sample's value per unit throughput, for the leaf's statistics.
            let mut value = 0.0f32;
            if let Some(ls) = ls {
                let wo = frame.to_local(ls.wi);
                let f = bsdf.eval(wi, wo);
                let mut w_light = 0.0;
                if f != Vec3::ZERO {
                    let shadow = ls.shadow_ray(si.p, si.ng, accel.offset_floor());
                    self.rays += 1;
                    if accel.unoccluded::<ANALYTIC>(&shadow) {
                        w_light =
                            light_mis(ls.delta, n, ls.pdf, || vg.pdf(tree, bsdf, wi, wo, ls.wi).0);
                        let c = self.throughput * f * ls.value * (w_light / (n * ls.pdf));
                        self.result += c;
                        if g.record {
                            self.rec.add(c);
                            let v = f * ls.value * (w_light / ls.pdf);
                            value = (v.x + v.y + v.z) / 3.0;
                        }
                    }
                }
                if g.record && g.kickstart && !ls.delta {
                    self.kickstart_record(si.p, &ls, w_light, rng);
                }
            }
            if g.record && g.guide && self.owned {
                tree.record_light_sample(vg.leaf(), value);
            }
        }
        light_samples
    }

    /// Kick-start: a light sample is a training record of its own (L = Le w_light, sampled
    /// with p_light, weight 0.5, no fraction gradient).
    #[inline(always)]
    fn kickstart_record(
        &self,
        p: Vec3,
        ls: &crate::light::LightSample,
        w_light: f32,
        rng: &mut Rng,
    ) {
        let l = ls.value * w_light;
        let r = Record::radiance_only(p, ls.wi, (l.x + l.y + l.z) / 3.0, ls.pdf, 0.5);
        if self.owned {
            self.g.tree.record(&r, &mut || rng.next_f32());
        } else {
            self.g.tree.skip_record(&r, &mut || rng.next_f32());
        }
    }

    /// Splitting: decided from the throughput and the leaf's mean radiance, before any
    /// direction is sampled; the copies wait in `pending`. From the depth where roulette
    /// starts (splitting at the first vertices too was worse: `docs/decisions/splitting.md`).
    #[inline(always)]
    fn split(&mut self, v: &mut Vertex<'a>, rng: &mut Rng) {
        let n = match self.split_value {
            Some(value)
                if v.vg.guided
                    && self.depth + 1 >= self.scene.path.rr_depth
                    && self.paths < MAX_PATHS_PER_SAMPLE =>
            {
                // The leaf's mean radiance: no direction is sampled yet.
                let e = expected_contribution(
                    self.g.tree,
                    &v.vg,
                    self.throughput,
                    1.0 / (4.0 * std::f32::consts::PI),
                );
                split_count(e, value, rng.next_f32()).min(MAX_PATHS_PER_SAMPLE - self.paths + 1)
            }
            _ => 1,
        };
        if n <= 1 {
            return;
        }
        v.throughput = self.throughput / n as f32;
        self.pending.extend(std::iter::repeat_n(*v, n as usize - 1));
        self.paths += n - 1;
    }

    /// From vertex `v`: a direction from the BSDF/guide mixture, the vertex recorded,
    /// roulette, and the next ray traced into `ray` and `hit`. False: the path ends.
    #[inline(always)]
    fn bounce<const ANALYTIC: bool>(
        &mut self,
        v: &Vertex<'a>,
        rng: &mut Rng,
        ray: &mut Ray,
        hit: &mut Option<crate::geometry::Hit>,
    ) -> bool {
        self.throughput = v.throughput;
        self.eta = v.eta;
        self.depth = v.depth;
        let (si, vg) = (&v.si, &v.vg);
        let mut ms = MixtureSample::default();
        if !sample_mixture_into(self.g.tree, vg, &v.bsdf, &v.frame, v.wi, rng, &mut ms) {
            return false;
        }
        self.throughput *= ms.weight;
        self.eta *= ms.eta;
        if self.g.record {
            self.record_vertex(v, &ms);
        }
        self.prev_p = si.p;
        self.prev_pdf = ms.p_mix;
        self.prev_delta = ms.delta;
        self.prev_nee = v.nee;
        self.prev_light_samples = v.light_samples;
        self.depth += 1;
        let tp_max = self.throughput.max_element();
        if !self.survives(v, &ms, tp_max, rng) {
            return false;
        }
        if tp_max <= 0.0 || !tp_max.is_finite() {
            return false;
        }
        let accel = &self.scene.accel;
        *ray = spawn_ray(si.p, si.ng, ms.wo_world, accel.offset_floor());
        *hit = accel.intersect::<ANALYTIC>(ray);
        self.rays += 1;
        true
    }

    /// Pushes the vertex `v` left by `ms` on the recorder (smooth, non-delta directions with a
    /// usable pdf), else marks the chain broken there.
    #[inline(always)]
    fn record_vertex(&mut self, v: &Vertex, ms: &MixtureSample) {
        let pushed = v.smooth
            && !ms.delta
            && (1.0 / ms.p_mix).is_finite()
            && self.rec.push(RecVertex {
                position: v.si.p,
                at: v.vg.at,
                direction: ms.wo_world,
                throughput: self.throughput,
                fcos: ms.fcos,
                p_mix: ms.p_mix,
                p_bsdf: ms.p_bsdf,
                p_guide: ms.p_guide,
                weight: self.rec_weight,
                acc: Vec3::ZERO,
            });
        if !pushed {
            self.rec.skip();
        }
    }

    /// Russian roulette: the reference implementation's, guided (weight window, from
    /// `guided_rr_depth`) where the guide applies and pixel estimates exist, else as
    /// Mitsuba does it. False: the path ends (the survivor's throughput is divided by q).
    #[inline(always)]
    fn survives(&mut self, v: &Vertex, ms: &MixtureSample, tp_max: f32, rng: &mut Rng) -> bool {
        let g = self.g;
        let guided_estimate = match g.pixel_estimate {
            Some(est) if !g.ppg_roulette && v.vg.guided && !ms.delta => Some(est),
            _ => None,
        };
        let rr_from = if guided_estimate.is_some() {
            g.guided_rr_depth
        } else {
            self.scene.path.rr_depth
        };
        if self.depth < rr_from {
            return true;
        }
        let q = if g.ppg_roulette {
            ppg_survival(
                v.smooth && !ms.delta,
                self.g.tree.is_built(),
                tp_max,
                self.eta,
            )
        } else if let Some(est) = guided_estimate {
            let e = expected_contribution(
                self.g.tree,
                &v.vg,
                self.throughput,
                // (the unrestricted guide's pdf: the radiance estimate is flux x pdf)
                ROULETTE_DIRECTIONAL * unrestricted_guide_pdf(&v.vg.region, ms)
                    + (1.0 - ROULETTE_DIRECTIONAL) / (4.0 * std::f32::consts::PI),
            );
            guided_survival(e, est.get(self.pixel).copied().unwrap_or(f32::NAN))
        } else {
            mitsuba_survival(tp_max, self.eta)
        };
        if rng.next_f32() >= q {
            return false;
        }
        self.throughput /= q;
        true
    }

    /// The sample's radiance, after its records are committed and its counts added (a halo
    /// sample, not `owned`, has no side effects: its owner's tile records and counts it).
    fn finish(self, rng: &mut Rng) -> Vec3 {
        if !self.owned {
            return self.result;
        }
        let g = self.g;
        if g.record {
            self.rec.commit(self.g.tree, self.g.tree.is_built(), rng);
        }
        if let Some(c) = g.rays {
            c.add(self.rays);
        }
        if let (true, Some(c)) = (self.paths > 1, g.splits) {
            c.add(u64::from(self.paths - 1));
        }
        if let (true, Some(c)) = (self.extra_light_samples > 0, g.light_splits) {
            c.add(self.extra_light_samples);
        }
        self.result
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_bsdf::{Diffuse, MicrofacetType, RoughConductor};
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
            MicrofacetType::Ggx,
            0.3,
            0.3,
            true,
            Vec3::splat(0.2),
            Vec3::splat(3.0),
            Vec3::ONE,
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
                    let Some(ms) = sample_mixture(&tree, &vg, &bsdf, &frame, wi, &mut rng) else {
                        continue;
                    };
                    let (p_nee, p_b, p_g) = vg.pdf(&tree, &bsdf, wi, ms.wo, ms.wo_world);
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
                let w = sample_mixture(&tree, &vg, &bsdf, &frame, wi, &mut rng)
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
                    let Some(ms) = sample_mixture(&tree, &vg, &bsdf, &frame, wi, &mut rng) else {
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
}
