//! Orthonormal shading frames.

use glam::Vec3;

/// An orthonormal basis with `n` as the local z axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    pub s: Vec3,
    pub t: Vec3,
    pub n: Vec3,
}

impl Frame {
    /// Builds a frame around a unit normal (Duff et al. 2017, branchless).
    #[inline]
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let s = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let t = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Self { s, t, n }
    }

    /// Builds a frame around a unit normal whose first axis is the tangent `dp_du` made
    /// orthogonal to it (Mitsuba's shading frame, which normal maps are expressed in); the
    /// normal-only frame if `dp_du` is parallel to the normal.
    pub fn from_normal_tangent(n: Vec3, dp_du: Vec3) -> Self {
        let s = (dp_du - n * n.dot(dp_du)).normalize_or_zero();
        if s == Vec3::ZERO {
            return Self::from_normal(n);
        }
        Self {
            s,
            t: n.cross(s),
            n,
        }
    }

    #[inline]
    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    #[inline]
    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }

    /// The same frame seen from the other side (z negated, still right-handed).
    #[inline]
    pub fn flipped(&self) -> Self {
        Self {
            s: self.t,
            t: self.s,
            n: -self.n,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_is_orthonormal_and_round_trips() {
        for n in [
            Vec3::Z,
            -Vec3::Z,
            Vec3::X,
            Vec3::new(0.3, -0.5, 0.81).normalize(),
            Vec3::new(1e-8, 0.0, -1.0).normalize(),
        ] {
            let f = Frame::from_normal(n);
            assert!((f.s.length() - 1.0).abs() < 1e-5 && (f.t.length() - 1.0).abs() < 1e-5);
            assert!(
                f.s.dot(f.t).abs() < 1e-5 && f.s.dot(f.n).abs() < 1e-5 && f.t.dot(f.n).abs() < 1e-5
            );
            assert!(f.s.cross(f.t).dot(f.n) > 0.99);
            let v = Vec3::new(0.2, 0.7, -0.4);
            assert!((f.to_world(f.to_local(v)) - v).length() < 1e-5);
            let g = f.flipped();
            assert!(g.s.cross(g.t).dot(g.n) > 0.99);
        }
    }
}
