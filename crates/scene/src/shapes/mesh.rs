//! Turning a loaded object-space triangle mesh into a validated world-space
//! [`TriangleMesh`].

use glam::{DMat3, DMat4, DVec3, Vec3};

use crate::desc::{Location, TriangleMesh};
use crate::error::SceneError;
use crate::xml::invalid;

/// Validate `mesh` (object space, as read from `source`), compute vertex
/// normals when the file has none (unless `face_normals`), and bake
/// `to_world` in: positions by the matrix, normals by its inverse transpose
/// (renormalised). Errors name `source` and the XML line `loc`.
pub(crate) fn finalize(
    mut mesh: TriangleMesh,
    to_world: DMat4,
    face_normals: bool,
    flip_normals: bool,
    source: &str,
    loc: &Location,
) -> Result<TriangleMesh, SceneError> {
    let err = |msg: String| invalid(loc, format!("{source}: {msg}"));
    let n = mesh.positions.len();
    if mesh.indices.is_empty() {
        return Err(err("mesh has no triangles".into()));
    }
    if n > u32::MAX as usize {
        return Err(err("mesh has too many vertices".into()));
    }
    if let Some(i) = mesh.positions.iter().position(|p| !p.is_finite()) {
        return Err(err(format!(
            "vertex {i} has a non-finite position {:?}",
            mesh.positions[i]
        )));
    }
    if let Some(t) = mesh
        .indices
        .iter()
        .position(|t| t.iter().any(|&i| i as usize >= n))
    {
        return Err(err(format!(
            "triangle {t} has an out-of-range vertex index {:?} (mesh has {n} vertices)",
            mesh.indices[t]
        )));
    }
    if let Some(ns) = &mesh.normals {
        if ns.len() != n {
            return Err(err(format!("{} normals for {n} vertices", ns.len())));
        }
        if let Some(i) = ns.iter().position(|v| !v.is_finite()) {
            return Err(err(format!(
                "vertex {i} has a non-finite normal {:?}",
                ns[i]
            )));
        }
    }
    if let Some(uvs) = &mesh.uvs {
        if uvs.len() != n {
            return Err(err(format!(
                "{} texture coordinates for {n} vertices",
                uvs.len()
            )));
        }
        if let Some(i) = uvs.iter().position(|v| !v.is_finite()) {
            return Err(err(format!(
                "vertex {i} has non-finite texture coordinates {:?}",
                uvs[i]
            )));
        }
    }

    let lin = DMat3::from_mat4(to_world);
    let normal_matrix = lin.inverse().transpose();
    if !normal_matrix.is_finite() {
        return Err(invalid(loc, "to_world transform is singular"));
    }
    for p in &mut mesh.positions {
        let w = to_world.transform_point3(p.as_dvec3()).as_vec3();
        if !w.is_finite() {
            return Err(err("a transformed vertex position is not finite".into()));
        }
        *p = w;
    }

    if face_normals {
        mesh.normals = None;
    } else if let Some(ns) = &mut mesh.normals {
        for (i, v) in ns.iter_mut().enumerate() {
            let w = normal_matrix * v.as_dvec3();
            let len = w.length();
            if !(len > 0.0) || !len.is_finite() {
                return Err(err(format!("vertex {i} has a zero-length normal")));
            }
            *v = (w / len).as_vec3();
        }
    } else {
        mesh.normals = Some(vertex_normals(&mesh.positions, &mesh.indices));
    }
    mesh.flip_normals = flip_normals;
    Ok(mesh)
}

/// Angle-weighted smooth vertex normals (world space). Vertices whose
/// incident triangles are all degenerate fall back to +z.
fn vertex_normals(positions: &[Vec3], indices: &[[u32; 3]]) -> Vec<Vec3> {
    let mut acc = vec![DVec3::ZERO; positions.len()];
    for tri in indices {
        let p = tri.map(|i| positions[i as usize].as_dvec3());
        let n = (p[1] - p[0]).cross(p[2] - p[0]);
        let len = n.length();
        if !(len > 0.0) {
            continue;
        }
        let n = n / len;
        for k in 0..3 {
            let e1 = p[(k + 1) % 3] - p[k];
            let e2 = p[(k + 2) % 3] - p[k];
            let angle = e1.angle_between(e2);
            if angle.is_finite() {
                acc[tri[k] as usize] += n * angle;
            }
        }
    }
    acc.into_iter()
        .map(|n| {
            let len = n.length();
            if len > 0.0 && len.is_finite() {
                (n / len).as_vec3()
            } else {
                Vec3::Z
            }
        })
        .collect()
}
