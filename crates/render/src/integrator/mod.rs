//! Integrators: estimate the radiance arriving along a camera ray.

pub mod guided_path;
pub mod path;
pub mod wavefront;

use crate::geometry::{spawn_ray, Hit, Ray};
use crate::scene::Scene;

/// The longest path depth from Mitsuba's `max_depth` (-1 = unbounded).
#[inline]
pub fn depth_limit(max_depth: i32) -> u32 {
    if max_depth < 0 {
        u32::MAX
    } else {
        max_depth as u32
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
    let first = scene.accel.intersect::<ANALYTIC>(ray);
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
    let accel = &scene.accel;
    while let Some(h) = hit {
        if scene.shape_light[h.shape as usize].is_none() {
            break;
        }
        let si = accel.interaction(ray, &h);
        *ray = spawn_ray(si.p, si.ng, ray.d, accel.offset_floor());
        hit = accel.intersect::<ANALYTIC>(ray);
    }
    hit?;
    Some(hit)
}
