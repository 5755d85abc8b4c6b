//! Mitsuba's `path` integrator: unidirectional path tracing with next-event
//! estimation, multiple importance sampling (power heuristic) and Russian
//! roulette, with Mitsuba's meaning of `max_depth`, `rr_depth` and
//! `hide_emitters`.
//!
//! The estimator is written as the steps of one bounce of one path ([`Lane`]:
//! [`surface`], [`next_event`], [`scatter`]); [`li`] runs them for one path at a
//! time, [`super::wavefront`] for many paths side by side. Both are
//! monomorphised over the scene's features (`ENV`: an environment light exists,
//! `ANALYTIC`: analytic shapes exist) so a scene pays nothing for what it lacks.

use glam::Vec3;
use pathfarm_bsdf::{BsdfSample, Frame};

use super::{camera_hit, depth_limit, emission_mis, light_mis, mitsuba_survival};
use crate::geometry::{spawn_ray, Hit, Ray, SurfaceInteraction};
use crate::light::LightSample;
use crate::rng::Rng;
use crate::scene::{Scene, MAX_PASSES};
use crate::shading::ShadedBsdf;

/// Radiance along the camera ray `ray`, one path at a time: each bounce's light
/// sample is tested and added at once.
pub fn li<const ENV: bool, const ANALYTIC: bool>(scene: &Scene, ray: Ray, rng: &mut Rng) -> Vec3 {
    if scene.path.max_depth == 0 {
        return Vec3::ZERO;
    }
    let max_depth = depth_limit(scene.path.max_depth);
    let (accel, lights) = (&scene.world().accel, &scene.world().lights);
    let mut lane = Lane::new(0, ray);
    let Some(hit) = camera_hit::<ANALYTIC>(scene, &mut lane.ray) else {
        return Vec3::ZERO;
    };
    lane.hit = hit;
    loop {
        let Some(sh) = surface::<ENV>(scene, &mut lane, max_depth, rng) else {
            if !lane.alive {
                break;
            }
            // Stepped through a mask or null surface: the same segment goes on.
            lane.hit = accel.intersect::<ANALYTIC>(&lane.ray);
            continue;
        };
        let (u_select, u) = (rng.next_f32(), rng.next_2d());
        if sh.bsdf.flags().smooth {
            if let Some(ls) = lights.sample(accel, sh.p, u_select, u) {
                next_event(&mut lane, &sh, &ls, scene.path.strict_normals);
            }
        }
        if let Some((shadow, contribution)) = lane.shadow.take() {
            let t = scene.transmittance::<ANALYTIC>(&shadow);
            if t > 0.0 {
                lane.result += contribution * t;
            }
        }
        let (u_lobe, u) = (rng.next_f32(), rng.next_2d());
        scatter(scene, &mut lane, &sh, sh.bsdf.sample(sh.wi, u_lobe, u), rng);
        if !lane.alive {
            break;
        }
        lane.hit = accel.intersect::<ANALYTIC>(&lane.ray);
    }
    lane.result
}

/// One path in flight: what the estimator carries from bounce to bounce.
#[derive(Clone, Copy)]
pub(super) struct Lane {
    /// Index of the path's camera sample (in a batch).
    pub k: usize,
    pub ray: Ray,
    /// What `ray` hit.
    pub hit: Option<Hit>,
    pub throughput: Vec3,
    pub result: Vec3,
    pub eta: f32,
    pub depth: u32,
    pub prev_p: Vec3,
    pub prev_bsdf_pdf: f32,
    pub prev_delta: bool,
    /// A next-event shadow ray is pending, with the contribution it adds
    /// if unoccluded.
    pub shadow: Option<(Ray, Vec3)>,
    /// The path goes on (its next ray is to be traced).
    pub alive: bool,
    /// `ray` is the camera ray (Mitsuba's `hide_emitters` applies to its hits).
    pub camera: bool,
    /// Surfaces this segment has passed straight through (see [`crate::scene::MAX_PASSES`]).
    pub passes: u32,
}

impl Lane {
    /// The path of camera sample `k` along camera ray `ray`, before its first hit.
    pub fn new(k: usize, ray: Ray) -> Self {
        Self {
            k,
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
            passes: 0,
        }
    }
}

/// Where a path scatters this bounce.
#[derive(Clone, Copy)]
pub(super) struct Shading<'a> {
    pub p: Vec3,
    pub ng: Vec3,
    pub bsdf: ShadedBsdf<'a>,
    pub frame: Frame,
    /// Direction towards the previous vertex, in the shading frame.
    pub wi: Vec3,
    /// The scene's [`crate::geometry::Accel::offset_floor`], for the rays leaving `p`.
    pub offset_floor: f32,
}

/// The surface the lane's ray found: emission (MIS-weighted against the previous
/// BSDF sample), then the BSDF to scatter with, unless the path ends here (escaped,
/// or at the depth limit) or steps straight through a `mask` or `null` surface (`None`
/// with `lane.alive` set and `lane.ray` the continued segment: not a bounce, so the depth
/// and the previous vertex, which the next emission's MIS weight refers to, stay). Clears
/// `lane.alive`; [`scatter`] sets it again.
#[inline(always)]
pub(super) fn surface<'a, const ENV: bool>(
    scene: &'a Scene,
    lane: &mut Lane,
    max_depth: u32,
    rng: &mut Rng,
) -> Option<Shading<'a>> {
    let lights = &scene.world().lights;
    lane.alive = false;
    let ray = lane.ray;
    let Some(h) = lane.hit else {
        if ENV {
            let le = lights.environment_radiance(ray.d);
            let w = emission_mis(lane.prev_bsdf_pdf, lane.prev_delta, 1.0, || {
                lights.environment_pdf(ray.d)
            });
            lane.result += lane.throughput * le * w;
        }
        return None;
    };
    let si = scene.world().accel.interaction(&ray, &h);

    // Emission found by BSDF sampling (or directly visible).
    if let Some(light) = scene.world().shape_light[si.shape as usize] {
        let le = lights.area_radiance(light, si.ns, -ray.d);
        if le != Vec3::ZERO {
            let w = emission_mis(lane.prev_bsdf_pdf, lane.prev_delta, 1.0, || {
                lights.area_pdf(light, lane.prev_p, si.p, si.ns)
            });
            lane.result += lane.throughput * le * w;
        }
    }

    if scene.world().features.pass_through && stepped_through(scene, lane, si, rng) {
        return None;
    }
    if lane.depth + 1 >= max_depth {
        return None;
    }
    let (bsdf, frame) = scene.bsdf_at(&si, h.prim, ray.d);
    let wi = frame.to_local(-ray.d);
    // With strict normals, `ng` is turned to the side of the frame (the flipped one of a
    // two-sided back): the light and scattered directions are then checked against the frame.
    // Ray offsets do not depend on its sign.
    let ng = if scene.path.strict_normals {
        strict_side_normal(si.ng, si.ns, frame.n, ray.d)?
    } else {
        si.ng
    };
    Some(Shading {
        p: si.p,
        ng,
        bsdf,
        frame,
        wi,
        offset_floor: scene.world().accel.offset_floor(),
    })
}

/// In a scene with `mask` or `null` surfaces: whether the lane steps through the surface at
/// `si` (its ray then continues beyond it, unless it has passed [`MAX_PASSES`] surfaces in
/// this segment, which ends the path). Out of line: scenes without such surfaces never call it.
/// `si` by value: a reference escaping into an out-of-line call would keep the interaction in
/// memory on every hit.
#[inline(never)]
fn stepped_through(scene: &Scene, lane: &mut Lane, si: SurfaceInteraction, rng: &mut Rng) -> bool {
    if !passes_through(scene.pass_probability(&si), rng) {
        lane.passes = 0;
        return false;
    }
    lane.passes += 1;
    if lane.passes <= MAX_PASSES {
        lane.ray = spawn_ray(si.p, si.ng, lane.ray.d, scene.world().accel.offset_floor());
        lane.alive = true;
    }
    true
}

/// Mitsuba 0.x's `strictNormals` test: the geometric normal `ng` and the shading normal `ns`
/// put the direction `w` on the same side.
#[inline(always)]
pub(super) fn same_side(ng: glam::Vec3, ns: glam::Vec3, w: glam::Vec3) -> bool {
    ng.dot(w) * ns.dot(w) > 0.0
}

/// With strict normals: `None` if the ray along `ray_d` arrives on different sides of `ng`
/// and `ns`, else [`side_normal`]. Out of line: other scenes never call it.
#[inline(never)]
fn strict_side_normal(
    ng: glam::Vec3,
    ns: glam::Vec3,
    frame_n: glam::Vec3,
    ray_d: glam::Vec3,
) -> Option<glam::Vec3> {
    same_side(ng, ns, -ray_d).then(|| side_normal(ng, ns, frame_n))
}

/// `ng` turned to the side of a frame whose normal `frame_n` is the shading normal `ns` or
/// (seen from a two-sided back) its opposite: [`in_frame_side`] is then [`same_side`] for any frame.
#[inline(always)]
pub(super) fn side_normal(ng: glam::Vec3, ns: glam::Vec3, frame_n: glam::Vec3) -> glam::Vec3 {
    if frame_n.dot(ns) < 0.0 {
        -ng
    } else {
        ng
    }
}

/// [`same_side`] for the direction `world`, given in the frame as `local`, with `ng` from
/// [`side_normal`].
#[inline(always)]
pub(super) fn in_frame_side(ng: glam::Vec3, world: glam::Vec3, local: glam::Vec3) -> bool {
    ng.dot(world) * local.z > 0.0
}

/// Whether a path meeting a surface that it passes through with probability `pass` does so
/// (a random number is drawn only for a partly opaque surface).
#[inline(always)]
pub(super) fn passes_through(pass: f32, rng: &mut Rng) -> bool {
    pass > 0.0 && (pass >= 1.0 || rng.next_f32() < pass)
}

/// Next-event estimation with light sample `ls`: its MIS-weighted contribution and
/// the shadow ray that decides it (`lane.shadow`, for the caller to test).
#[inline(always)]
pub(super) fn next_event(lane: &mut Lane, sh: &Shading<'_>, ls: &LightSample, strict: bool) {
    let wo = sh.frame.to_local(ls.wi);
    if strict && !in_frame_side(sh.ng, ls.wi, wo) {
        return;
    }
    let f = sh.bsdf.eval(sh.wi, wo);
    if f != Vec3::ZERO {
        let w = light_mis(ls.delta, 1.0, ls.pdf, || sh.bsdf.pdf(sh.wi, wo));
        lane.shadow = Some((
            ls.shadow_ray(sh.p, sh.ng, sh.offset_floor),
            lane.throughput * f * ls.value * (w / ls.pdf),
        ));
    }
}

/// After BSDF sample `bs` (`None`: absorbed): the path's throughput, Russian
/// roulette as Mitsuba does it, and the next ray (`lane.alive` if there is one).
#[inline(always)]
pub(super) fn scatter(
    scene: &Scene,
    lane: &mut Lane,
    sh: &Shading<'_>,
    bs: Option<BsdfSample>,
    rng: &mut Rng,
) {
    let Some(bs) = bs else {
        return;
    };
    if scene.path.strict_normals && !in_frame_side(sh.ng, sh.frame.to_world(bs.wo), bs.wo) {
        return;
    }
    lane.throughput *= bs.weight;
    lane.eta *= bs.eta;
    lane.prev_p = sh.p;
    lane.prev_bsdf_pdf = bs.pdf;
    lane.prev_delta = bs.lobe.delta;
    lane.depth += 1;

    let tp_max = lane.throughput.max_element();
    if lane.depth >= scene.path.rr_depth {
        let q = mitsuba_survival(tp_max, lane.eta);
        if rng.next_f32() >= q {
            return;
        }
        lane.throughput /= q;
    }
    if tp_max <= 0.0 || !tp_max.is_finite() {
        return;
    }
    lane.ray = spawn_ray(sh.p, sh.ng, sh.frame.to_world(bs.wo), sh.offset_floor);
    lane.alive = true;
}
