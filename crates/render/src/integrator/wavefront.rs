//! The `path` integrator over a batch of camera samples at once ("wavefront"):
//! the steps of [`super::path`] ([`surface`], [`next_event`], [`scatter`]) run
//! as loops over many independent paths, so that each step's loop body is
//! independent from one lane to the next.
//!
//! Why: one path's bounce is a long chain of dependent, latency-bound
//! scalar work (square roots, divisions, table lookups, a traversal whose
//! every step waits on the last). With the paths of a batch side by side,
//! each step's loop body is independent from one lane to the next, so the
//! out-of-order core overlaps lanes, and each step's code and data stay hot.
//!
//! Per bounce: **trace** every path's ray (new camera rays included) as one
//! stream, **shade** every live lane (emission found, the BSDF; all light
//! samples at once, then their MIS weights; diffuse BSDF samples at once, the
//! others one by one; Russian roulette and the next ray), then test every
//! pending **shadow** ray as one stream. A lane's random numbers, arithmetic
//! and order of additions are those of [`super::path::li`], so both give
//! identical bits (tested).

use glam::{Vec2, Vec3};
use pathfarm_bsdf::{diffuse, Bsdf, BsdfSample};

use super::path::{next_event, scatter, surface, Lane, Shading};
use super::{camera_hit_from, depth_limit};
use crate::geometry::{Hit, Ray};
use crate::light::LightSample;
use crate::render::{CameraSample, Estimator};
use crate::rng::Rng;
use crate::scene::Scene;
use crate::shading::ShadedBsdf;

/// Paths in flight per batch: enough lanes to overlap, few enough that their
/// state stays in the first-level cache.
const LANES: usize = 64;

/// `path` over batches of samples, specialised like [`super::path::li`] for
/// an environment light (`ENV`) and analytic shapes (`ANALYTIC`).
pub struct PathWavefront<'a, const ENV: bool, const ANALYTIC: bool> {
    /// The scene the paths are traced in; its features must match `ENV` and `ANALYTIC` (see
    /// [`super::specialised`]).
    pub scene: &'a Scene,
}

/// The buffers of one `estimate` call, reused from bounce to bounce.
struct Scratch<'a> {
    /// The paths still going.
    lanes: Vec<Lane>,
    /// Where each of `lanes` scatters this bounce.
    shading: Vec<Option<Shading<'a>>>,
    /// The lanes of this bounce's light samples, their queries (point, selection
    /// number, 2D number) and the samples.
    nee_lanes: Vec<usize>,
    queries: Vec<(Vec3, f32, Vec2)>,
    light_samples: Vec<Option<LightSample>>,
    /// The diffuse lanes of this bounce, their queries (reflectance, cos of the
    /// incident direction, 2D number) and BSDF samples.
    diffuse_lanes: Vec<usize>,
    diffuse_queries: Vec<(Vec3, f32, Vec2)>,
    bsdf_samples: Vec<Option<BsdfSample>>,
    /// The rays of one stream query, and its answers.
    rays: Vec<Ray>,
    hits: Vec<Option<Hit>>,
    clear: Vec<bool>,
}

impl<const ENV: bool, const ANALYTIC: bool> Estimator for PathWavefront<'_, ENV, ANALYTIC> {
    fn estimate(&self, samples: &[CameraSample], rngs: &mut [Rng], out: &mut [Vec3]) {
        let mut scratch = Scratch {
            lanes: Vec::with_capacity(LANES.min(samples.len())),
            shading: Vec::with_capacity(LANES.min(samples.len())),
            nee_lanes: Vec::new(),
            queries: Vec::new(),
            light_samples: Vec::new(),
            diffuse_lanes: Vec::new(),
            diffuse_queries: Vec::new(),
            bsdf_samples: Vec::new(),
            rays: Vec::new(),
            hits: Vec::new(),
            clear: Vec::new(),
        };
        self.run(samples, rngs, out, &mut scratch);
    }
}

impl<'a, const ENV: bool, const ANALYTIC: bool> PathWavefront<'a, ENV, ANALYTIC> {
    /// All `samples`, up to [`LANES`] paths in flight: a finished path's slot takes the
    /// next camera sample, so the streams stay full until the samples run out.
    fn run(
        &self,
        samples: &[CameraSample],
        rngs: &mut [Rng],
        out: &mut [Vec3],
        scratch: &mut Scratch<'a>,
    ) {
        let Scratch {
            lanes,
            shading,
            nee_lanes,
            queries,
            light_samples,
            diffuse_lanes,
            diffuse_queries,
            bsdf_samples,
            rays,
            hits,
            clear,
        } = scratch;
        let scene = self.scene;
        let params = &scene.path;
        out.fill(Vec3::ZERO);
        if params.max_depth == 0 {
            return;
        }
        let max_depth = depth_limit(params.max_depth);
        let accel = &scene.world().accel;
        let mut next_sample = 0;
        lanes.clear();
        loop {
            // New camera paths in the free slots.
            while lanes.len() < LANES && next_sample < samples.len() {
                lanes.push(Lane::new(next_sample, samples[next_sample].ray));
                next_sample += 1;
            }
            if lanes.is_empty() {
                break;
            }
            // Every path's next ray (a camera ray for the new ones), as one stream.
            rays.clear();
            rays.extend(lanes.iter().map(|l| l.ray));
            hits.clear();
            hits.resize(rays.len(), None);
            accel.intersect_many::<ANALYTIC>(rays, hits);
            for (lane, &hit) in lanes.iter_mut().zip(hits.iter()) {
                if lane.camera {
                    lane.camera = false;
                    match camera_hit_from::<ANALYTIC>(scene, &mut lane.ray, hit) {
                        Some(hit) => lane.hit = hit,
                        // A black sample (hidden emitters, nothing behind).
                        None => lane.alive = false,
                    }
                } else {
                    lane.hit = hit;
                }
            }
            lanes.retain(|lane| lane.alive);

            shading.clear();
            shading.extend(
                lanes
                    .iter_mut()
                    .map(|lane| surface::<ENV>(scene, lane, max_depth, &mut rngs[lane.k])),
            );
            // Next-event estimation: the random numbers, then all light samples at
            // once, then each one's BSDF value and MIS weight.
            nee_lanes.clear();
            queries.clear();
            for (i, (lane, sh)) in lanes.iter().zip(shading.iter()).enumerate() {
                if let Some(sh) = sh {
                    let rng = &mut rngs[lane.k];
                    let (u_select, u) = (rng.next_f32(), rng.next_2d());
                    if sh.bsdf.flags().smooth {
                        nee_lanes.push(i);
                        queries.push((sh.p, u_select, u));
                    }
                }
            }
            light_samples.clear();
            light_samples.resize(queries.len(), None);
            scene
                .world()
                .lights
                .sample_many(accel, queries, light_samples);
            for (&i, ls) in nee_lanes.iter().zip(light_samples.iter()) {
                if let (Some(ls), Some(sh)) = (ls, &shading[i]) {
                    next_event(&mut lanes[i], sh, ls, params.strict_normals);
                }
            }
            // BSDF sampling: the random numbers; diffuse surfaces (the common case)
            // all at once, the others one at a time; then roulette and the next ray.
            diffuse_lanes.clear();
            diffuse_queries.clear();
            for (i, (lane, sh)) in lanes.iter_mut().zip(shading.iter()).enumerate() {
                if let Some(sh) = sh {
                    let rng = &mut rngs[lane.k];
                    let (u_lobe, u) = (rng.next_f32(), rng.next_2d());
                    match sh.bsdf {
                        ShadedBsdf {
                            model: Bsdf::Diffuse(d),
                            bump: None,
                        } => {
                            diffuse_lanes.push(i);
                            diffuse_queries.push((d.reflectance, sh.wi.z, u));
                        }
                        bsdf => scatter(scene, lane, sh, bsdf.sample(sh.wi, u_lobe, u), rng),
                    }
                }
            }
            bsdf_samples.clear();
            bsdf_samples.resize(diffuse_queries.len(), None);
            diffuse::sample_many(diffuse_queries, bsdf_samples);
            for (&i, &bs) in diffuse_lanes.iter().zip(bsdf_samples.iter()) {
                if let Some(sh) = &shading[i] {
                    let lane = &mut lanes[i];
                    scatter(scene, lane, sh, bs, &mut rngs[lane.k]);
                }
            }
            // Shadow rays, all at once.
            rays.clear();
            rays.extend(lanes.iter().filter_map(|l| l.shadow.map(|(r, _)| r)));
            clear.clear();
            clear.resize(rays.len(), false);
            accel.unoccluded_many::<ANALYTIC>(rays, clear);
            let mut next = clear.iter();
            for lane in lanes.iter_mut() {
                if let Some((shadow, contribution)) = lane.shadow.take() {
                    if *next.next().expect("one answer per shadow ray") {
                        lane.result += contribution;
                    } else if scene.world().features.pass_through {
                        let t = scene.transmittance_through::<ANALYTIC>(&shadow);
                        if t > 0.0 {
                            lane.result += contribution * t;
                        }
                    }
                }
            }
            lanes.retain(|lane| {
                if !lane.alive {
                    out[lane.k] = lane.result;
                }
                lane.alive
            });
        }
    }
}
