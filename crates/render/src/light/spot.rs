//! Mitsuba's `spot` emitter: a point light shining along the +z axis of its frame, at full
//! intensity within `beam_width` of the axis and falling off linearly in angle to zero at
//! `cutoff_angle`.

use glam::{Mat3, Mat4, Vec3};

use super::LightSample;

/// A spot light in world space.
pub struct Spot {
    position: Vec3,
    /// World to the light's frame (directions only).
    to_local: Mat3,
    intensity: Vec3,
    cutoff: f32,
    cos_cutoff: f32,
    cos_beam: f32,
    inv_transition: f32,
}

impl Spot {
    /// The spot at `to_world`'s origin shining along its +z, of `intensity` (W/sr) on its
    /// axis; angles in radians, `0 < beam_width < cutoff_angle`.
    pub fn new(to_world: Mat4, intensity: Vec3, cutoff_angle: f32, beam_width: f32) -> Self {
        Self {
            position: to_world.transform_point3(Vec3::ZERO),
            to_local: Mat3::from_mat4(to_world).inverse(),
            intensity,
            cutoff: cutoff_angle,
            cos_cutoff: cutoff_angle.cos(),
            cos_beam: beam_width.cos(),
            inv_transition: 1.0 / (cutoff_angle - beam_width),
        }
    }

    /// The fraction of the intensity sent along world direction `d` (from the light).
    pub fn falloff(&self, d: Vec3) -> f32 {
        let cos_theta = (self.to_local * d).normalize().z;
        if !(cos_theta > self.cos_cutoff) {
            0.0
        } else if cos_theta >= self.cos_beam {
            1.0
        } else {
            (self.cutoff - cos_theta.clamp(-1.0, 1.0).acos()) * self.inv_transition
        }
    }

    /// Next-event estimation from `p`: `None` outside the cone.
    pub fn sample(&self, p: Vec3) -> Option<LightSample> {
        let v = self.position - p;
        let d2 = v.length_squared();
        if d2 == 0.0 {
            return None;
        }
        let wi = v / d2.sqrt();
        let f = self.falloff(-wi);
        if f <= 0.0 {
            return None;
        }
        Some(LightSample {
            wi,
            point: self.position,
            infinite: false,
            value: self.intensity * (f / d2),
            pdf: 1.0,
            delta: true,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_beam_is_full_inside_its_width_and_falls_off_linearly_in_angle_to_the_cutoff() {
        let (cutoff, beam) = (20f32.to_radians(), 15f32.to_radians());
        // Looking down -y from (0, 2, 0): to_world maps +z to -y.
        let to_world = Mat4::from_translation(Vec3::new(0.0, 2.0, 0.0))
            * Mat4::from_rotation_x(90f32.to_radians());
        let s = Spot::new(to_world, Vec3::splat(3.0), cutoff, beam);
        let at = |deg: f32| {
            let a = deg.to_radians();
            s.falloff(Vec3::new(a.sin(), -a.cos(), 0.0))
        };
        assert_eq!(at(0.0), 1.0);
        assert_eq!(at(14.9), 1.0);
        assert!((at(17.5) - 0.5).abs() < 1e-3, "{}", at(17.5));
        assert_eq!(at(20.5), 0.0);
        let below = s.sample(Vec3::ZERO).unwrap();
        assert!(
            (below.value - Vec3::splat(0.75)).abs().max_element() < 1e-6,
            "3 / 2^2"
        );
        assert!(
            s.sample(Vec3::new(5.0, 0.0, 0.0)).is_none(),
            "outside the cone"
        );
    }
}
