//! Integrators: estimate the radiance arriving along a camera ray.

pub mod guided_path;
pub mod path;
pub mod wavefront;

use crate::geometry::{spawn_ray, Hit, Ray};
use crate::scene::Scene;

/// Code monomorphised over the scene's features, so a scene pays nothing for effects it
/// does not contain: `ENV` (an environment light exists) and `ANALYTIC` (analytic shapes
/// exist). [`specialised`] picks the instance for a scene.
pub trait Specialise {
    /// What the specialised code returns.
    type Output;
    /// Runs the code instantiated for these feature flags; [`specialised`] calls the instance that
    /// matches the scene.
    fn call<const ENV: bool, const ANALYTIC: bool>(self) -> Self::Output;
}

/// `f` specialised for `scene`'s features: the one place the features choose an instance.
#[inline]
pub fn specialised<F: Specialise>(scene: &Scene, f: F) -> F::Output {
    match (
        scene.world().features.environment,
        scene.world().features.analytic_shapes,
    ) {
        (false, false) => f.call::<false, false>(),
        (true, false) => f.call::<true, false>(),
        (false, true) => f.call::<false, true>(),
        (true, true) => f.call::<true, true>(),
    }
}

/// The longest path depth from Mitsuba's `max_depth` (-1 = unbounded).
#[inline]
pub fn depth_limit(max_depth: i32) -> u32 {
    if max_depth < 0 {
        u32::MAX
    } else {
        max_depth as u32
    }
}

/// The MIS weight of emission found by a direction sample of pdf `prev_pdf`, against the
/// light technique of the vertex it left: `light_samples` samples of pdf `p_light` each
/// (one technique of pdf `light_samples x p_light`; 0: no light was sampled there). 1 after
/// a delta lobe. Shared by `path` (one light sample) and `guided_path` (light splitting).
#[inline(always)]
pub fn emission_mis(
    prev_pdf: f32,
    prev_delta: bool,
    light_samples: f32,
    p_light: impl FnOnce() -> f32,
) -> f32 {
    if prev_delta || light_samples == 0.0 {
        1.0
    } else {
        crate::sampling::power_heuristic(prev_pdf, light_samples * p_light())
    }
}

/// The MIS weight of a light sample of pdf `p_light`, one of `n` taken at a vertex, against
/// direction sampling there (pdf `p_scatter` of the light's direction). 1 for delta lights.
#[inline(always)]
pub fn light_mis(delta: bool, n: f32, p_light: f32, p_scatter: impl FnOnce() -> f32) -> f32 {
    if delta {
        1.0
    } else {
        crate::sampling::power_heuristic(n * p_light, p_scatter())
    }
}

/// Mitsuba's Russian-roulette survival probability from the throughput's largest channel
/// and the accumulated relative IOR: `min(max(throughput) eta^2, 0.95)`.
#[inline]
pub fn mitsuba_survival(throughput_max: f32, eta: f32) -> f32 {
    (throughput_max * eta * eta).min(0.95)
}

/// The first hit of a camera ray, with Mitsuba's `hide_emitters`: camera rays
/// then pass through area emitters (advancing `ray`), and a camera ray that
/// escapes shows nothing (Mitsuba's `valid_ray`, which hides the environment
/// too). `None` means the sample is black; `Some(None)` a visible miss.
#[inline]
pub fn camera_hit<const ANALYTIC: bool>(scene: &Scene, ray: &mut Ray) -> Option<Option<Hit>> {
    let first = scene.world().accel.intersect::<ANALYTIC>(ray);
    camera_hit_from::<ANALYTIC>(scene, ray, first)
}

/// [`camera_hit`] given the camera ray's first hit `hit`.
///
/// Inlined, with the `hide_emitters` walk out of line: an `Option<Option<Hit>>` returned
/// through memory was written in pieces by the callee and read back whole by the wavefront's
/// camera loop, a store-forwarding stall per camera ray.
#[inline(always)]
pub fn camera_hit_from<const ANALYTIC: bool>(
    scene: &Scene,
    ray: &mut Ray,
    hit: Option<Hit>,
) -> Option<Option<Hit>> {
    if scene.path.hide_emitters {
        hidden_emitters_skipped::<ANALYTIC>(scene, ray, hit)
    } else {
        Some(hit)
    }
}

/// [`camera_hit_from`] with `hide_emitters`: steps through directly visible emitters.
#[inline(never)]
fn hidden_emitters_skipped<const ANALYTIC: bool>(
    scene: &Scene,
    ray: &mut Ray,
    mut hit: Option<Hit>,
) -> Option<Option<Hit>> {
    let accel = &scene.world().accel;
    while let Some(h) = hit {
        if scene.world().shape_light[h.shape as usize].is_none() {
            break;
        }
        let si = accel.interaction(ray, &h);
        *ray = spawn_ray(si.p, si.ng, ray.d, accel.offset_floor());
        hit = accel.intersect::<ANALYTIC>(ray);
    }
    hit?;
    Some(hit)
}
