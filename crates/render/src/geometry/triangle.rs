//! Shading data on triangles.

use glam::{Vec2, Vec3};
use pathfarm_scene::TriangleMesh;

/// Barycentric coordinates (b1, b2) of point `p` in triangle (a, b, c),
/// computed from the (already found) hit point.
#[inline]
pub fn barycentrics(p: Vec3, a: Vec3, b: Vec3, c: Vec3) -> Vec2 {
    let e1 = b - a;
    let e2 = c - a;
    let ep = p - a;
    let d11 = e1.dot(e1);
    let d12 = e1.dot(e2);
    let d22 = e2.dot(e2);
    let dp1 = ep.dot(e1);
    let dp2 = ep.dot(e2);
    let den = d11 * d22 - d12 * d12;
    if den.abs() < f32::MIN_POSITIVE {
        return Vec2::ZERO;
    }
    let b1 = (d22 * dp1 - d12 * dp2) / den;
    let b2 = (d11 * dp2 - d12 * dp1) / den;
    Vec2::new(b1.clamp(0.0, 1.0), b2.clamp(0.0, 1.0))
}

/// Geometric normal, shading normal and uv at point `p` on triangle `tri`.
#[inline]
pub fn shade(mesh: &TriangleMesh, tri: usize, p: Vec3) -> (Vec3, Vec3, Vec2) {
    let [i0, i1, i2] = mesh.indices[tri];
    let (a, b, c) = (mesh.positions[i0 as usize], mesh.positions[i1 as usize], mesh.positions[i2 as usize]);
    let mut ng = (b - a).cross(c - a).normalize_or_zero();
    let bc = barycentrics(p, a, b, c);
    let b0 = 1.0 - bc.x - bc.y;
    let mut ns = match &mesh.normals {
        Some(n) => (n[i0 as usize] * b0 + n[i1 as usize] * bc.x + n[i2 as usize] * bc.y).normalize_or_zero(),
        None => ng,
    };
    if ns == Vec3::ZERO {
        ns = ng;
    }
    if mesh.flip_normals {
        ng = -ng;
        ns = -ns;
    }
    let uv = match &mesh.uvs {
        Some(t) => t[i0 as usize] * b0 + t[i1 as usize] * bc.x + t[i2 as usize] * bc.y,
        None => bc,
    };
    (ng, ns, uv)
}
