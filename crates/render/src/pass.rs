//! One unit of a guided job's work, rendered over one region of the image: what a
//! [`crate::session::Session`] asks for ([`PassSpec`]) and what rendering it gives back
//! ([`TileOutput`]). The one-process render and the farm's workers both render units with
//! [`render_unit`], so a tile rendered on any machine has the bits the same pixels get in a
//! whole-image render.

use pathfarm_guide::SdTree;
use pathfarm_scene::{GuidedNee, GuidedParams, GuidedRoulette};

use crate::counter::ShardedCounter;
use crate::film::Film;
use crate::integrator::guided_path::{self, GuideCtx};
use crate::render::{
    path_estimator, render_region_into, sample_region, CameraSample, Estimator, Progress, Region,
    RenderSettings,
};
use crate::rng::Rng;
use crate::scene::Scene;

/// NEE "kickstart" does light sampling while fewer than this many spp have been rendered.
pub const KICKSTART_SPP: u64 = 128;

/// Random streams of the path fallback's unguided passes start at this sample index, apart
/// from the guided passes' (which count up from 0).
pub const PATH_STREAM: u64 = 1 << 40;

/// What a unit renders.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PassKind {
    /// A training pass: guided, recorded into the tree's building statistics.
    Record,
    /// Guided passes that record nothing (the final image, or the path fallback's timed
    /// check pass).
    Guided,
    /// The path fallback's unguided probe pass (the guided integrator without the guide).
    Probe,
    /// The path fallback's rest of the budget: the plain `path` integrator.
    Path,
}

/// One unit of work: `passes` passes of `spp` samples per pixel over the whole image, one
/// after the other, each pass accumulating into the unit's film. A session hands units out
/// one at a time; the farm splits each into tiles.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PassSpec {
    /// Sequence number of the unit within its job (0, 1, ...).
    pub unit: u64,
    /// The training iteration it belongs to.
    pub iteration: u32,
    /// What the unit renders: training, guided final, the fallback's probe, or plain path tracing.
    pub kind: PassKind,
    /// Random stream of the unit's first sample: sample `s` of pass `p` of every pixel uses
    /// stream `first_sample + p * spp + s`.
    pub first_sample: u64,
    /// Samples per pixel of each pass.
    pub spp: u32,
    /// Passes in the unit.
    pub passes: u32,
    /// Guided spp rendered before the unit (NEE "kickstart" applies below [`KICKSTART_SPP`]).
    pub spp_before: u64,
    /// Guided splitting and light splitting (when the parameters enable them).
    pub split: bool,
    /// The tree version to sample from: the number of refinements it has had.
    pub tree_version: u32,
    /// The learned fractions' version within the iteration: fraction steps taken since the
    /// last refinement.
    pub fraction_version: u32,
}

impl PassSpec {
    /// Whether the unit samples from the guide.
    pub fn guide(&self) -> bool {
        matches!(self.kind, PassKind::Record | PassKind::Guided)
    }

    /// Whether the unit records into the guide.
    pub fn record(&self) -> bool {
        self.kind == PassKind::Record
    }

    /// Samples per pixel of the whole unit.
    pub fn unit_spp(&self) -> u64 {
        self.spp as u64 * self.passes as u64
    }

    /// Whether the unit's tiles come back as samples ([`TilePixels::Samples`]) rather than
    /// pixel sums: for units of at most [`SAMPLES_MAX_SPP`] samples per pixel.
    pub fn sample_form(&self) -> bool {
        self.unit_spp() <= SAMPLES_MAX_SPP
    }

    /// The pixels whose samples a unit's render of `region` (of a `size` image whose
    /// reconstruction filter is `filter`) draws, so whose pixel estimate it may read: the
    /// region alone for a unit of samples, the region and its filter halo for one of sums
    /// ([`crate::render_region_into`]).
    pub fn sampled_pixels(
        &self,
        region: Region,
        filter: &crate::filter::Filter,
        size: (u32, u32),
    ) -> Region {
        match self.sample_form() {
            true => region,
            false => region.grown(filter.reach() as u32, size.0, size.1),
        }
    }

    /// The unit's render calls: how many, and the samples per pixel of each. Each is
    /// rendered and splatted on its own, the `p`-th from random stream `first_sample + p x
    /// spp`: the plain path tracer renders the whole unit in one call, the guided integrator
    /// one call a pass.
    pub fn render_calls(&self) -> (u32, u32) {
        match self.kind {
            PassKind::Path => (1, self.spp * self.passes),
            _ => (self.passes, self.spp),
        }
    }
}

/// Units of at most this many samples per pixel travel as samples: 12 bytes a sample (its
/// radiance; its film position is drawn again from its random stream) against 92 bytes a
/// pixel of sums, and a tile of samples needs no filter halo.
pub const SAMPLES_MAX_SPP: u64 = 7;

/// A tile's pixels as rendering gives them back.
#[derive(Clone, Debug, PartialEq)]
pub enum TilePixels {
    /// The region's pixel sums (a `region`-sized film): its own samples and its filter
    /// halo's, splatted.
    Sums(Film),
    /// The radiance of the region's own samples, for a unit whose [`PassSpec::sample_form`]
    /// holds: for each of the unit's render calls ([`PassSpec::render_calls`]), every pixel of
    /// the region row-major, its samples in index order. The session splats the whole
    /// image once every tile is in ([`crate::splat_samples`]), which gives the bits a
    /// whole-image render gives.
    Samples(Vec<glam::Vec3>),
    /// [`TilePixels::Samples`] prepared by the unit's splat plan ([`crate::SplatPlan::prepare`]:
    /// film positions drawn, the region's interior gathered), as a farm coordinator does off
    /// its lock before it hands a tile to the session.
    Prepared(Box<crate::splat::RegionSplat>),
}

impl TilePixels {
    /// Whether this is the form a tile of `region` of `spec` has (the right film size, or the
    /// right number of samples).
    pub fn fits(&self, spec: &PassSpec, region: Region) -> bool {
        match self {
            TilePixels::Sums(f) => {
                !spec.sample_form() && (f.width, f.height) == (region.width(), region.height())
            }
            TilePixels::Samples(v) => {
                spec.sample_form() && v.len() as u64 == region.pixels() as u64 * spec.unit_spp()
            }
            TilePixels::Prepared(r) => {
                spec.sample_form()
                    && r.region() == region
                    && r.plan().samples(region) as u64 == region.pixels() as u64 * spec.unit_spp()
            }
        }
    }
}

/// What rendering a unit over a region gives: the region's pixels (sums or samples) and
/// counters of its own samples. (The guide statistics of a [`PassKind::Record`] unit went
/// into the tree it was rendered with; a worker takes them out with
/// [`SdTree::take_stats`].)
#[derive(Clone, Debug, PartialEq)]
pub struct TileOutput {
    /// The region of the image the tile covers, in whole-image pixel coordinates.
    pub region: Region,
    /// The region's pixels, in the form [`PassSpec::sample_form`] says.
    pub pixels: TilePixels,
    /// Rays traced (camera, continuation and shadow rays) by guided-integrator samples.
    pub rays: u64,
    /// Camera samples with a non-finite value (counted as zero).
    pub invalid_samples: u64,
    /// Guide records and light samples the tree rejected for a non-finite value.
    pub nonfinite_records: u64,
    /// Extra paths made by splitting.
    pub split_paths: u64,
    /// Extra light samples taken by light splitting.
    pub extra_light_samples: u64,
}

/// Everything a unit is rendered with besides its [`PassSpec`].
pub struct UnitInputs<'a> {
    /// The scene being rendered.
    pub scene: &'a Scene,
    /// The job's `guided_path` parameters.
    pub params: &'a GuidedParams,
    /// The tree of `spec.tree_version` with the fractions of `spec.fraction_version`;
    /// records of a [`PassKind::Record`] unit go into its building statistics.
    pub tree: &'a SdTree,
    /// Per-pixel value estimate of the whole image for guided roulette (empty: none).
    pub estimate: &'a [f32],
    /// The job's seed: the same for every unit and tile of the job, so that every pixel's random
    /// streams do not depend on who renders it.
    pub seed: u64,
    /// Pixels per parallel work item (does not change the image).
    pub tile_size: u32,
}

/// Renders `spec` over `region`. `progress` gets the samples done of this call.
pub fn render_unit(
    inputs: &UnitInputs,
    spec: &PassSpec,
    region: Region,
    progress: &(dyn Fn(Progress) + Sync),
) -> TileOutput {
    let counters = Counters::default();
    let mut out = RegionOut::new(spec, region);
    if spec.kind == PassKind::Path {
        let settings = settings(inputs, spec.spp * spec.passes);
        let est = path_estimator(inputs.scene);
        out.render(inputs.scene, &settings, progress, spec.first_sample, &est);
    } else {
        let settings = settings(inputs, spec.spp);
        let npix = region.pixels() as u64;
        for p in 0..spec.passes {
            let done = p as u64 * spec.spp as u64;
            let ctx = guide_ctx(inputs, spec, spec.spp_before + done, &counters);
            let est = GuidedEstimator {
                scene: inputs.scene,
                ctx,
            };
            let base = done * npix;
            let pass_progress = |q: Progress| {
                progress(Progress {
                    samples_done: base + q.samples_done,
                    samples_total: spec.unit_spp() * npix,
                })
            };
            let first = spec.first_sample + done;
            out.render(inputs.scene, &settings, &pass_progress, first, &est);
        }
    }
    let invalid = out.invalid;
    TileOutput {
        region,
        pixels: out.pixels,
        rays: counters.rays.total(),
        invalid_samples: invalid,
        nonfinite_records: inputs.tree.take_nonfinite_records(),
        split_paths: counters.splits.total(),
        extra_light_samples: counters.light_splits.total(),
    }
}

/// A tile's pixels as its render calls fill them in.
struct RegionOut {
    region: Region,
    pixels: TilePixels,
    invalid: u64,
}

impl RegionOut {
    fn new(spec: &PassSpec, region: Region) -> Self {
        let pixels = if spec.sample_form() {
            TilePixels::Samples(Vec::with_capacity(
                region.pixels() * spec.unit_spp() as usize,
            ))
        } else {
            TilePixels::Sums(Film::new(region.width(), region.height()))
        };
        Self {
            region,
            pixels,
            invalid: 0,
        }
    }

    /// One render call of the unit: splatted into the sums, or its samples appended.
    fn render<E: Estimator + ?Sized>(
        &mut self,
        scene: &Scene,
        settings: &RenderSettings,
        progress: &(dyn Fn(Progress) + Sync),
        first_sample: u64,
        est: &E,
    ) {
        let region = self.region;
        let st = match &mut self.pixels {
            TilePixels::Sums(film) => {
                render_region_into(scene, settings, progress, first_sample, region, film, est)
            }
            TilePixels::Samples(values) => {
                let (v, st) = sample_region(scene, settings, progress, first_sample, region, est);
                values.extend_from_slice(&v);
                st
            }
            TilePixels::Prepared(_) => unreachable!("a region renders into sums or samples"),
        };
        self.invalid += st.invalid_samples;
    }
}

fn settings(inputs: &UnitInputs, spp: u32) -> RenderSettings {
    RenderSettings {
        spp: Some(spp),
        time_limit: None,
        seed: inputs.seed,
        tile_size: inputs.tile_size,
        pass_spp: None,
    }
}

#[derive(Default)]
struct Counters {
    rays: ShardedCounter,
    splits: ShardedCounter,
    light_splits: ShardedCounter,
}

/// The guided integrator's context for one pass of `spec` after `spp_done` guided spp.
fn guide_ctx<'a>(
    inputs: &UnitInputs<'a>,
    spec: &PassSpec,
    spp_done: u64,
    counters: &'a Counters,
) -> GuideCtx<'a> {
    let params = inputs.params;
    let guide = spec.guide();
    let nee = match params.nee {
        GuidedNee::Never => false,
        GuidedNee::Always => true,
        GuidedNee::Kickstart => spp_done < KICKSTART_SPP,
    };
    let roulette = params.russian_roulette == GuidedRoulette::Guided;
    let tree = inputs.tree;
    GuideCtx {
        tree,
        guide,
        nee,
        indirect_only: params.nee == GuidedNee::Always,
        kickstart: params.nee == GuidedNee::Kickstart && nee,
        record: spec.record(),
        ppg_roulette: guide && params.russian_roulette == GuidedRoulette::Ppg,
        guided_rr_depth: params.guided_rr_depth,
        hemisphere: params.guide_hemisphere,
        cosine: params.guide_cosine,
        split: params.splitting && spec.split,
        light_split: params.light_splitting && spec.split,
        splits: Some(&counters.splits),
        light_splits: Some(&counters.light_splits),
        rays: Some(&counters.rays),
        pixel_estimate: if guide && roulette && tree.is_built() && !inputs.estimate.is_empty() {
            Some(inputs.estimate)
        } else {
            None
        },
    }
}

/// [`guided_path::li`] for a scene's features.
struct GuidedLi;

type GuidedLiFn = fn(&Scene, &GuideCtx, crate::geometry::Ray, &mut Rng, usize, bool) -> glam::Vec3;

impl crate::integrator::Specialise for GuidedLi {
    type Output = GuidedLiFn;
    fn call<const ENV: bool, const ANALYTIC: bool>(self) -> GuidedLiFn {
        guided_path::li::<ENV, ANALYTIC>
    }
}

/// The guided integrator as an [`Estimator`], specialised for the scene's effects.
struct GuidedEstimator<'a> {
    scene: &'a Scene,
    ctx: GuideCtx<'a>,
}

impl Estimator for GuidedEstimator<'_> {
    fn estimate(&self, samples: &[CameraSample], rngs: &mut [Rng], out: &mut [glam::Vec3]) {
        let (scene, ctx) = (self.scene, &self.ctx);
        let li = crate::integrator::specialised(scene, GuidedLi);
        for ((s, rng), o) in samples.iter().zip(rngs.iter_mut()).zip(out.iter_mut()) {
            *o = li(scene, ctx, s.ray, rng, s.pixel, s.owned);
        }
    }
}
