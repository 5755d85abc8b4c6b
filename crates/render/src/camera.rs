//! Mitsuba's `perspective` pinhole camera.

use glam::{Mat4, Vec2, Vec3};
use pathfarm_scene::{FovAxis, SensorDesc};

use crate::geometry::Ray;

/// Generates primary rays. Film coordinates: x right, y down, in pixels.
#[derive(Clone, Debug)]
pub struct Camera {
    to_world: Mat4,
    origin: Vec3,
    width: f32,
    height: f32,
    tan_half_x: f32,
    tan_half_y: f32,
    near_clip: f32,
    far_clip: f32,
}

/// Converts a field of view along `axis` into the horizontal one, as
/// Mitsuba's `parse_fov` does.
pub fn x_fov_degrees(fov: f32, axis: FovAxis, aspect: f32) -> f32 {
    let t = (fov.to_radians() * 0.5).tan();
    let from_y = || 2.0 * (t * aspect).atan();
    let rad = match axis {
        FovAxis::X => return fov,
        FovAxis::Y => from_y(),
        FovAxis::Diagonal => 2.0 * (t / (1.0 + 1.0 / (aspect * aspect)).sqrt()).atan(),
        FovAxis::Smaller => {
            if aspect > 1.0 {
                from_y()
            } else {
                return fov;
            }
        }
        FovAxis::Larger => {
            if aspect > 1.0 {
                return fov;
            } else {
                from_y()
            }
        }
    };
    rad.to_degrees()
}

impl Camera {
    /// The camera of `desc`: its `to_world` placement, its field of view converted to the
    /// horizontal one, its film's aspect ratio and its near and far clip distances.
    pub fn new(desc: &SensorDesc) -> Self {
        let (w, h) = (desc.film.width as f32, desc.film.height as f32);
        let aspect = w / h;
        let xfov = x_fov_degrees(desc.fov, desc.fov_axis, aspect);
        let tan_half_x = (xfov.to_radians() * 0.5).tan();
        Self {
            to_world: desc.to_world,
            origin: desc.to_world.transform_point3(Vec3::ZERO),
            width: w,
            height: h,
            tan_half_x,
            tan_half_y: tan_half_x / aspect,
            near_clip: desc.near_clip,
            far_clip: desc.far_clip,
        }
    }

    /// The ray through film position `p` (in pixels, continuous).
    #[inline]
    pub fn ray(&self, p: Vec2) -> Ray {
        let sx = p.x / self.width;
        let sy = p.y / self.height;
        // Camera space: +z forward, +x left, +y up (Mitsuba's convention).
        let local = Vec3::new(
            (1.0 - 2.0 * sx) * self.tan_half_x,
            (1.0 - 2.0 * sy) * self.tan_half_y,
            1.0,
        );
        let inv_len = local.length_recip();
        let d = self.to_world.transform_vector3(local * inv_len).normalize();
        // Mitsuba clips at near/far along the ray: t in [near/cos, far/cos].
        let cos = inv_len; // local.z == 1
        Ray {
            o: self.origin,
            d,
            tmin: self.near_clip / cos,
            tmax: self.far_clip / cos,
        }
    }
}
