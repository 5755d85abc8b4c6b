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

use super::path::same_side;
use super::{camera_hit, depth_limit, emission_mis, light_mis, mitsuba_survival};
use crate::counter::ShardedCounter;
use crate::geometry::{spawn_ray, Ray};
use crate::rng::Rng;
use crate::sampling::power_heuristic;
use crate::scene::{Scene, MAX_PASSES};
use crate::shading::ShadedBsdf;

mod mixture;
mod recorder;
mod roulette;
mod scatter;
#[cfg(test)]
mod tests;

pub use mixture::*;
#[allow(unused_imports)]
use mixture::*;
pub use recorder::*;
pub use roulette::*;
#[allow(unused_imports)]
use roulette::*;
pub use scatter::{scatter_at, scatter_panels, Scatter};

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

/// A path vertex from which directions are sampled: what a split copy resumes from.
#[derive(Clone, Copy)]
struct Vertex<'s> {
    si: crate::geometry::SurfaceInteraction,
    bsdf: ShadedBsdf<'s>,
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
        let (scene, lights) = (self.scene, &self.scene.world().lights);
        let (mut ray, mut hit) = (*ray, hit);
        let mut passes = 0;
        let (si, prim) = loop {
            let Some(h) = hit else {
                if ENV {
                    let le = lights.environment_radiance(ray.d);
                    self.emitted(le, || lights.environment_pdf(ray.d));
                }
                return false;
            };
            let si = scene.world().accel.interaction(&ray, &h);
            if let Some(light) = scene.world().shape_light[si.shape as usize] {
                let le = lights.area_radiance(light, si.ns, -ray.d);
                if le != Vec3::ZERO {
                    let prev_p = self.prev_p;
                    self.emitted(le, || lights.area_pdf(light, prev_p, si.p, si.ns));
                }
            }
            // A mask or null surface the path steps through is not a vertex: the segment
            // goes on, and the previous vertex stays what emission MIS and recording see.
            if !super::path::passes_through(scene.pass_probability(&si), rng) {
                break (si, h.prim);
            }
            passes += 1;
            if passes > MAX_PASSES {
                return false;
            }
            ray = spawn_ray(si.p, si.ng, ray.d, scene.world().accel.offset_floor());
            hit = scene.world().accel.intersect::<ANALYTIC>(&ray);
            self.rays += 1;
        };
        let ray = &ray;
        if self.depth + 1 >= self.max_depth {
            return false;
        }
        let (bsdf, frame) = bsdf_at_outlined(scene, &si, prim, ray.d);
        let wi = frame.to_local(-ray.d);
        if scene.path.strict_normals && !same_side(si.ng, si.ns, -ray.d) {
            return false;
        }
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
        bsdf: &ShadedBsdf,
        frame: &Frame,
        wi: Vec3,
        vg: &mut VertexGuide,
        region: CellWeights,
        rng: &mut Rng,
    ) -> u32 {
        let (accel, lights, tree, g) = (
            &self.scene.world().accel,
            &self.scene.world().lights,
            self.g.tree,
            self.g,
        );
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
                let strict = self.scene.path.strict_normals;
                let f = if strict && !same_side(si.ng, si.ns, ls.wi) {
                    Vec3::ZERO
                } else {
                    bsdf.eval(wi, wo)
                };
                let mut w_light = 0.0;
                if f != Vec3::ZERO {
                    let shadow = ls.shadow_ray(si.p, si.ng, accel.offset_floor());
                    self.rays += 1;
                    let transmitted = self.scene.transmittance::<ANALYTIC>(&shadow);
                    if transmitted > 0.0 {
                        // The light's MIS weight, times what reaches it through mask and null
                        // surfaces (exactly 1 without them).
                        w_light =
                            light_mis(ls.delta, n, ls.pdf, || vg.pdf(tree, bsdf, wi, wo, ls.wi).0)
                                * transmitted;
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
        if self.scene.path.strict_normals && !same_side(si.ng, si.ns, ms.wo_world) {
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
        let accel = &self.scene.world().accel;
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
