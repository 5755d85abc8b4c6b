//! Mitsuba's `path` integrator: unidirectional path tracing with next-event
//! estimation, multiple importance sampling (power heuristic) and Russian
//! roulette, with Mitsuba's meaning of `max_depth`, `rr_depth` and
//! `hide_emitters`.
//!
//! The estimator is monomorphised over the scene's features (`ENV`: an
//! environment light exists, `ANALYTIC`: analytic shapes exist) so a scene
//! pays nothing for what it lacks.

use glam::Vec3;

use super::{camera_hit, depth_limit, mitsuba_survival};
use crate::geometry::{spawn_ray, Ray};
use crate::rng::Rng;
use crate::sampling::power_heuristic;
use crate::scene::Scene;

/// Radiance along the camera ray `ray`.
pub fn li<const ENV: bool, const ANALYTIC: bool>(
    scene: &Scene,
    mut ray: Ray,
    rng: &mut Rng,
) -> Vec3 {
    let params = &scene.path;
    if params.max_depth == 0 {
        return Vec3::ZERO;
    }
    let max_depth = depth_limit(params.max_depth);
    let accel = &scene.accel;
    let lights = &scene.lights;

    let mut throughput = Vec3::ONE;
    let mut result = Vec3::ZERO;
    let mut eta = 1.0f32;
    let mut depth = 0u32;
    let mut prev_p = ray.o;
    let mut prev_bsdf_pdf = 1.0f32;
    let mut prev_delta = true;

    let Some(mut hit) = camera_hit::<ANALYTIC>(scene, &mut ray) else {
        return Vec3::ZERO;
    };

    loop {
        let Some(h) = hit else {
            if ENV {
                let le = lights.environment_radiance(ray.d);
                let w = if prev_delta {
                    1.0
                } else {
                    power_heuristic(prev_bsdf_pdf, lights.environment_pdf(ray.d))
                };
                result += throughput * le * w;
            }
            break;
        };
        let si = accel.interaction(&ray, &h);

        // Emission found by BSDF sampling (or directly visible).
        if let Some(light) = scene.shape_light[si.shape as usize] {
            let le = lights.area_radiance(light, si.ns, -ray.d);
            if le != Vec3::ZERO {
                let w = if prev_delta {
                    1.0
                } else {
                    power_heuristic(prev_bsdf_pdf, lights.area_pdf(light, prev_p, si.p, si.ns))
                };
                result += throughput * le * w;
            }
        }

        if depth + 1 >= max_depth {
            break;
        }

        let (bsdf, frame) = scene.bsdf_at(&si, ray.d);
        let wi = frame.to_local(-ray.d);
        let flags = bsdf.flags();

        // Next-event estimation.
        if flags.smooth {
            if let Some(ls) = lights.sample(accel, si.p, rng.next_f32(), rng.next_2d()) {
                let wo = frame.to_local(ls.wi);
                let f = bsdf.eval(wi, wo);
                if f != Vec3::ZERO {
                    let shadow = ls.shadow_ray(si.p, si.ng);
                    if accel.unoccluded::<ANALYTIC>(&shadow) {
                        let w = if ls.delta {
                            1.0
                        } else {
                            power_heuristic(ls.pdf, bsdf.pdf(wi, wo))
                        };
                        result += throughput * f * ls.value * (w / ls.pdf);
                    }
                }
            }
        } else {
            // Keep the random-number stream aligned across materials.
            rng.next_f32();
            rng.next_2d();
        }

        // BSDF sampling.
        let Some(bs) = bsdf.sample(wi, rng.next_f32(), rng.next_2d()) else {
            break;
        };
        throughput *= bs.weight;
        eta *= bs.eta;
        prev_p = si.p;
        prev_bsdf_pdf = bs.pdf;
        prev_delta = bs.lobe.delta;
        depth += 1;

        // Russian roulette, as Mitsuba does it.
        let tp_max = throughput.max_element();
        if depth >= params.rr_depth {
            let q = mitsuba_survival(tp_max, eta);
            if rng.next_f32() >= q {
                break;
            }
            throughput /= q;
        }
        if tp_max <= 0.0 || !tp_max.is_finite() {
            break;
        }

        let wo = frame.to_world(bs.wo);
        ray = spawn_ray(si.p, si.ng, wo);
        hit = accel.intersect::<ANALYTIC>(&ray);
    }
    result
}
