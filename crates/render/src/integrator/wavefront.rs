//! The `path` integrator over a batch of camera samples at once ("wavefront"):
//! the same estimator as [`super::path::li`], bit for bit, restructured so
//! that each step of a bounce runs as a loop over many independent paths.
//!
//! Why: one path's bounce is a long chain of dependent, latency-bound
//! scalar work (square roots, divisions, table lookups, a traversal whose
//! every step waits on the last). With the paths of a batch side by side,
//! each step's loop body is independent from one lane to the next, so the
//! out-of-order core overlaps lanes, and each step's code and data stay hot.
//!
//! Per bounce: **shade** every live lane (emission found, the BSDF, the light
//! sample with its MIS weight, the BSDF sample, Russian roulette, the next
//! ray), then test every pending **shadow** ray, then **trace** every
//! continuing ray. A lane's random numbers, arithmetic and order of additions
//! are those of the one-path estimator, so both give identical bits (tested).

use glam::{Vec2, Vec3};
use pathfarm_bsdf::{diffuse, Bsdf, BsdfSample, Frame};

use super::{camera_hit_from, depth_limit, mitsuba_survival};
use crate::geometry::{spawn_ray, Hit, Ray};
use crate::light::LightSample;
use crate::render::{CameraSample, Estimator};
use crate::rng::Rng;
use crate::sampling::power_heuristic;
use crate::scene::Scene;

/// Paths in flight per batch: enough lanes to overlap, few enough that their
/// state stays in the first-level cache.
const LANES: usize = 64;

/// Lanes per group of the vectorised BSDF sampling.
const GROUP: usize = 16;

/// `path` over batches of samples, specialised like [`super::path::li`] for
/// an environment light (`ENV`) and analytic shapes (`ANALYTIC`).
pub struct PathWavefront<'a, const ENV: bool, const ANALYTIC: bool> {
    pub scene: &'a Scene,
}

/// The buffers of a batch, reused from one batch to the next.
struct Scratch<'a> {
    /// The paths still going.
    lanes: Vec<Lane>,
    /// Where each of `lanes` scatters this bounce.
    shading: Vec<Option<Shading<'a>>>,
    /// Diffuse lanes to sample this bounce: (lane, cos of the incident direction, 2D
    /// number, reflectance).
    diffuse: Vec<(usize, f32, Vec2, Vec3)>,
    /// Next-event queries (point, selection number, 2D number) and their light samples.
    queries: Vec<(Vec3, f32, Vec2)>,
    light_samples: Vec<Option<LightSample>>,
    /// The rays of one stream query, and its answers.
    rays: Vec<Ray>,
    hits: Vec<Option<Hit>>,
    clear: Vec<bool>,
}

/// Where a lane scatters this bounce.
#[derive(Clone, Copy)]
struct Shading<'a> {
    p: Vec3,
    ng: Vec3,
    bsdf: Bsdf<'a>,
    frame: Frame,
    /// Direction towards the previous vertex, in the shading frame.
    wi: Vec3,
}

/// One path in flight.
#[derive(Clone, Copy)]
struct Lane {
    /// Index of the sample in the batch.
    k: usize,
    ray: Ray,
    hit: Option<Hit>,
    throughput: Vec3,
    result: Vec3,
    eta: f32,
    depth: u32,
    prev_p: Vec3,
    prev_bsdf_pdf: f32,
    prev_delta: bool,
    /// A next-event shadow ray is pending, with the contribution it adds
    /// if unoccluded.
    shadow: Option<(Ray, Vec3)>,
    /// The path goes on (its next ray is to be traced).
    alive: bool,
    /// `ray` is the camera ray (Mitsuba's `hide_emitters` applies to its hits).
    camera: bool,
}

impl<const ENV: bool, const ANALYTIC: bool> Estimator for PathWavefront<'_, ENV, ANALYTIC> {
    fn estimate(&self, samples: &[CameraSample], rngs: &mut [Rng], out: &mut [Vec3]) {
        let mut scratch = Scratch {
            lanes: Vec::with_capacity(LANES.min(samples.len())),
            shading: Vec::with_capacity(LANES.min(samples.len())),
            diffuse: Vec::new(),
            queries: Vec::new(),
            light_samples: Vec::new(),
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
            diffuse,
            queries,
            light_samples,
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
        let accel = &scene.accel;
        let mut next_sample = 0;
        lanes.clear();
        loop {
            // New camera paths in the free slots.
            while lanes.len() < LANES && next_sample < samples.len() {
                let ray = samples[next_sample].ray;
                lanes.push(Lane {
                    k: next_sample,
                    ray,
                    hit: None,
                    throughput: Vec3::ONE,
                    result: Vec3::ZERO,
                    eta: 1.0,
                    depth: 0,
                    prev_p: ray.o,
                    prev_bsdf_pdf: 1.0,
                    prev_delta: true,
                    shadow: None,
                    alive: true,
                    camera: true,
                });
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
            shading.extend(lanes.iter_mut().map(|lane| self.surface(lane, max_depth)));
            // Next-event estimation: the random numbers, then all light samples at
            // once, then each one's BSDF value and MIS weight.
            queries.clear();
            for (lane, sh) in lanes.iter().zip(shading.iter()) {
                if let Some(sh) = sh {
                    let rng = &mut rngs[lane.k];
                    let (u_select, u) = (rng.next_f32(), rng.next_2d());
                    if sh.bsdf.flags().smooth {
                        queries.push((sh.p, u_select, u));
                    }
                }
            }
            light_samples.clear();
            light_samples.resize(queries.len(), None);
            scene.lights.sample_many(accel, queries, light_samples);
            let mut next = light_samples.iter();
            for (lane, sh) in lanes.iter_mut().zip(shading.iter()) {
                if let Some(sh) = sh {
                    if sh.bsdf.flags().smooth {
                        if let Some(ls) = next.next().expect("one light sample per query") {
                            Self::next_event(lane, sh, ls);
                        }
                    }
                }
            }
            // BSDF sampling: the random numbers; diffuse surfaces (the common case)
            // side by side, the others one at a time; then roulette and the next ray.
            diffuse.clear();
            for (i, (lane, sh)) in lanes.iter_mut().zip(shading.iter()).enumerate() {
                if let Some(sh) = sh {
                    let rng = &mut rngs[lane.k];
                    let (u_lobe, u) = (rng.next_f32(), rng.next_2d());
                    match sh.bsdf {
                        Bsdf::Diffuse(d) => diffuse.push((i, sh.wi.z, u, d.reflectance)),
                        bsdf => self.scatter(lane, sh, bsdf.sample(sh.wi, u_lobe, u), rng),
                    }
                }
            }
            for group in diffuse.chunks(GROUP) {
                // Structure of arrays, so that this loop vectorises.
                let (mut wi_z, mut ux, mut uy) =
                    ([1.0f32; GROUP], [0.5f32; GROUP], [0.5f32; GROUP]);
                let mut r = [[1.0f32; GROUP]; 3];
                for (j, &(_, z, u, refl)) in group.iter().enumerate() {
                    (wi_z[j], ux[j], uy[j]) = (z, u.x, u.y);
                    (r[0][j], r[1][j], r[2][j]) = (refl.x, refl.y, refl.z);
                }
                let (mut valid, mut pdf, mut wo) =
                    ([false; GROUP], [0.0f32; GROUP], [[0.0f32; GROUP]; 3]);
                for j in 0..GROUP {
                    let s =
                        diffuse::sample_lane([r[0][j], r[1][j], r[2][j]], wi_z[j], ux[j], uy[j]);
                    (valid[j], pdf[j]) = (s.valid, s.pdf);
                    (wo[0][j], wo[1][j], wo[2][j]) = (s.wo[0], s.wo[1], s.wo[2]);
                }
                for (j, &(i, _, _, refl)) in group.iter().enumerate() {
                    let bs = valid[j].then(|| {
                        let wo = Vec3::new(wo[0][j], wo[1][j], wo[2][j]);
                        BsdfSample::glossy_reflection(wo, pdf[j], refl)
                    });
                    let lane = &mut lanes[i];
                    let sh = shading[i].as_ref().expect("a diffuse lane scatters");
                    self.scatter(lane, sh, bs, &mut rngs[lane.k]);
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
                if let Some((_, contribution)) = lane.shadow.take() {
                    if *next.next().expect("one answer per shadow ray") {
                        lane.result += contribution;
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

    /// The surface a lane's ray found: emission (MIS-weighted against the
    /// previous BSDF sample), then the BSDF to scatter with, unless the path
    /// ends here (escaped, or at the depth limit).
    #[inline(always)]
    fn surface(&self, lane: &mut Lane, max_depth: u32) -> Option<Shading<'a>> {
        let scene = self.scene;
        let lights = &scene.lights;
        lane.alive = false;
        let ray = lane.ray;
        let Some(h) = lane.hit else {
            if ENV {
                let le = lights.environment_radiance(ray.d);
                let w = if lane.prev_delta {
                    1.0
                } else {
                    power_heuristic(lane.prev_bsdf_pdf, lights.environment_pdf(ray.d))
                };
                lane.result += lane.throughput * le * w;
            }
            return None;
        };
        let si = scene.accel.interaction(&ray, &h);

        if let Some(light) = scene.shape_light[si.shape as usize] {
            let le = lights.area_radiance(light, si.ns, -ray.d);
            if le != Vec3::ZERO {
                let w = if lane.prev_delta {
                    1.0
                } else {
                    power_heuristic(
                        lane.prev_bsdf_pdf,
                        lights.area_pdf(light, lane.prev_p, si.p, si.ns),
                    )
                };
                lane.result += lane.throughput * le * w;
            }
        }

        if lane.depth + 1 >= max_depth {
            return None;
        }
        let (bsdf, frame) = scene.bsdf_at(&si, ray.d);
        let wi = frame.to_local(-ray.d);
        Some(Shading {
            p: si.p,
            ng: si.ng,
            bsdf,
            frame,
            wi,
        })
    }

    /// Next-event estimation with light sample `ls`: its MIS-weighted contribution
    /// and the shadow ray that decides it (tested later, with the batch's).
    #[inline(always)]
    fn next_event(lane: &mut Lane, sh: &Shading<'a>, ls: &LightSample) {
        let wo = sh.frame.to_local(ls.wi);
        let f = sh.bsdf.eval(sh.wi, wo);
        if f != Vec3::ZERO {
            let w = if ls.delta {
                1.0
            } else {
                power_heuristic(ls.pdf, sh.bsdf.pdf(sh.wi, wo))
            };
            lane.shadow = Some((
                ls.shadow_ray(sh.p, sh.ng),
                lane.throughput * f * ls.value * (w / ls.pdf),
            ));
        }
    }

    /// After BSDF sample `bs` (`None`: absorbed): the path's throughput, Russian
    /// roulette as Mitsuba does it, and the next ray.
    #[inline(always)]
    fn scatter(&self, lane: &mut Lane, sh: &Shading<'a>, bs: Option<BsdfSample>, rng: &mut Rng) {
        let Some(bs) = bs else {
            return;
        };
        lane.throughput *= bs.weight;
        lane.eta *= bs.eta;
        lane.prev_p = sh.p;
        lane.prev_bsdf_pdf = bs.pdf;
        lane.prev_delta = bs.lobe.delta;
        lane.depth += 1;

        let tp_max = lane.throughput.max_element();
        if lane.depth >= self.scene.path.rr_depth {
            let q = mitsuba_survival(tp_max, lane.eta);
            if rng.next_f32() >= q {
                return;
            }
            lane.throughput /= q;
        }
        if tp_max <= 0.0 || !tp_max.is_finite() {
            return;
        }
        lane.ray = spawn_ray(sh.p, sh.ng, sh.frame.to_world(bs.wo));
        lane.alive = true;
    }
}
