//! Shading data on triangles.

use glam::{Vec2, Vec3};
use pathfarm_scene::TriangleMesh;

/// Barycentric coordinates (b1, b2) of point `p` in triangle (a, b, c).
#[cfg(test)]
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

/// What shading needs of a triangle that does not depend on the hit point.
#[derive(Clone, Copy, Debug)]
pub struct TriShade {
    /// Unit geometric normal (winding order v0, v1, v2; flip applied).
    pub ng: Vec3,
    /// The shading normal when it is the same over the whole triangle (no
    /// vertex normals, or three equal ones as on `rectangle` and `cube`),
    /// flip applied; `None` when the vertex normals must be interpolated.
    pub flat_ns: Option<Vec3>,
}

impl TriShade {
    pub fn new(mesh: &TriangleMesh, tri: usize) -> Self {
        let [i0, i1, i2] = mesh.indices[tri];
        let [a, b, c] = [i0, i1, i2].map(|i| mesh.positions[i as usize]);
        let ng = (b - a).cross(c - a).normalize_or_zero();
        let sign = if mesh.flip_normals { -1.0 } else { 1.0 };
        let flat_ns = match &mesh.normals {
            None => Some(ng),
            Some(n) => {
                let (n0, n1, n2) = (n[i0 as usize], n[i1 as usize], n[i2 as usize]);
                (n0 == n1 && n0 == n2).then(|| {
                    let ns = n0.normalize_or_zero();
                    if ns == Vec3::ZERO {
                        ng
                    } else {
                        ns
                    }
                })
            }
        };
        Self {
            ng: ng * sign,
            flat_ns: flat_ns.map(|n| n * sign),
        }
    }
}

/// Geometric normal, shading normal and uv on triangle `tri` (with its
/// precomputed `TriShade`) at barycentrics `bc` (weights of vertices 1 and 2).
#[inline]
pub fn shade(mesh: &TriangleMesh, tri: usize, bc: Vec2, pre: &TriShade) -> (Vec3, Vec3, Vec2) {
    let bc = bc.clamp(Vec2::ZERO, Vec2::ONE);
    let b0 = 1.0 - bc.x - bc.y;
    let ng = pre.ng;
    let needs_indices = pre.flat_ns.is_none() || mesh.uvs.is_some();
    let [i0, i1, i2] = if needs_indices {
        mesh.indices[tri]
    } else {
        [0; 3]
    };
    let ns = match (pre.flat_ns, &mesh.normals) {
        (Some(ns), _) => ns,
        (None, Some(n)) => {
            let ns = (n[i0 as usize] * b0 + n[i1 as usize] * bc.x + n[i2 as usize] * bc.y)
                .normalize_or_zero();
            if ns == Vec3::ZERO {
                ng
            } else if mesh.flip_normals {
                -ns
            } else {
                ns
            }
        }
        // TriShade always has `flat_ns` for meshes without normals.
        (None, None) => ng,
    };
    let uv = match &mesh.uvs {
        Some(t) => t[i0 as usize] * b0 + t[i1 as usize] * bc.x + t[i2 as usize] * bc.y,
        None => bc,
    };
    (ng, ns, uv)
}

/// `(dp/du, dp/dv)` of triangle `tri` from its vertex uvs (Mitsuba's formula); `None`
/// without uvs or when the uvs are degenerate.
pub fn uv_tangents(mesh: &TriangleMesh, tri: usize) -> Option<(Vec3, Vec3)> {
    let uvs = mesh.uvs.as_ref()?;
    let [i0, i1, i2] = mesh.indices[tri].map(|i| i as usize);
    let (p0, p1, p2) = (mesh.positions[i0], mesh.positions[i1], mesh.positions[i2]);
    let (duv10, duv20) = (uvs[i1] - uvs[i0], uvs[i2] - uvs[i0]);
    let det = duv10.x * duv20.y - duv10.y * duv20.x;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let (dp0, dp1) = (p1 - p0, p2 - p0);
    let inv = 1.0 / det;
    let dp_du = (dp0 * duv20.y - dp1 * duv10.y) * inv;
    let dp_dv = (dp1 * duv10.x - dp0 * duv20.x) * inv;
    (dp_du.is_finite() && dp_dv.is_finite()).then_some((dp_du, dp_dv))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3A;
    use obvhs::ray::Ray;
    use obvhs::rt_triangle::RtTriangle;

    #[test]
    fn obvhs_barycentrics_weight_vertices_one_and_two() {
        let (a, b, c) = (
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(2.0, 0.0, 0.1),
            Vec3::new(0.3, 1.5, -0.2),
        );
        let t = RtTriangle::new(a.into(), b.into(), c.into());
        let p = a * 0.2 + b * 0.5 + c * 0.3;
        let o = Vec3::new(0.1, 0.2, 3.0);
        let d = (p - o).normalize();
        let ray = Ray::new_inf(o.into(), d.into());
        let r = Vec3A::from(d).cross(t.v0 - Vec3A::from(o));
        let inv = 1.0 / t.ng.dot(Vec3A::from(d));
        let bc = Vec2::new(r.dot(t.e2) * inv, r.dot(t.e1) * inv);
        assert!((bc - Vec2::new(0.5, 0.3)).length() < 1e-5, "{bc}");
        assert!((bc - barycentrics(p, a, b, c)).length() < 1e-5);
        assert!(t.intersect(&ray).is_finite());
        // -ng is the winding-order normal.
        assert!(
            Vec3::from(-t.ng)
                .normalize()
                .dot((b - a).cross(c - a).normalize())
                > 0.9999
        );
    }

    #[test]
    fn uv_tangents_map_uv_steps_to_the_triangle_edges() {
        let mesh = TriangleMesh {
            positions: vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(2.0, 0.3, 0.1),
                Vec3::new(-0.4, 1.5, 0.7),
            ],
            uvs: Some(vec![
                Vec2::new(0.1, 0.2),
                Vec2::new(0.6, 0.25),
                Vec2::new(0.2, 0.9),
            ]),
            indices: vec![[0, 1, 2]],
            ..Default::default()
        };
        let (du, dv) = uv_tangents(&mesh, 0).unwrap();
        let uvs = mesh.uvs.as_ref().unwrap();
        for k in [1, 2] {
            let duv = uvs[k] - uvs[0];
            let edge = mesh.positions[k] - mesh.positions[0];
            assert!((du * duv.x + dv * duv.y - edge).length() < 1e-5, "edge {k}");
        }
        let flat = TriangleMesh {
            uvs: Some(vec![Vec2::ZERO; 3]),
            ..mesh.clone()
        };
        assert!(uv_tangents(&flat, 0).is_none(), "degenerate uvs");
        let bare = TriangleMesh { uvs: None, ..mesh };
        assert!(uv_tangents(&bare, 0).is_none(), "no uvs");
    }
}
