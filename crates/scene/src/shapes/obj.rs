//! Wavefront OBJ loading (via `tobj`), with Mitsuba's texture-coordinate
//! convention.

use std::path::Path;

use glam::{Vec2, Vec3};

use crate::desc::TriangleMesh;

/// Read an OBJ file into one object-space mesh (all groups merged; polygons
/// fan-triangulated; corners with distinct position/uv/normal tuples become
/// distinct vertices). Like Mitsuba (`flip_tex_coords`, default true for
/// OBJ), v is replaced by 1 - v when `flip_tex_coords`. Materials are ignored.
pub(crate) fn load_obj(path: &Path, flip_tex_coords: bool) -> Result<TriangleMesh, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("cannot read: {e}"))?;
    let mut reader = std::io::BufReader::new(file);
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
    };
    let (models, _materials) =
        tobj::load_obj_buf(&mut reader, &opts, |_| Err(tobj::LoadError::OpenFileFailed))
            .map_err(|e| format!("cannot parse OBJ: {e}"))?;

    let mut mesh = TriangleMesh::default();
    let all_normals = models
        .iter()
        .all(|m| !m.mesh.normals.is_empty() || m.mesh.indices.is_empty());
    let all_uvs = models
        .iter()
        .all(|m| !m.mesh.texcoords.is_empty() || m.mesh.indices.is_empty());
    let mut normals = Vec::new();
    let mut uvs = Vec::new();
    for model in &models {
        let m = &model.mesh;
        if m.indices.is_empty() {
            continue;
        }
        let nv = m.positions.len() / 3;
        if all_normals && m.normals.len() != 3 * nv {
            return Err(format!(
                "object '{}': normal count does not match vertex count",
                model.name
            ));
        }
        if all_uvs && m.texcoords.len() != 2 * nv {
            return Err(format!(
                "object '{}': texture coordinate count does not match vertex count",
                model.name
            ));
        }
        if m.indices.len() % 3 != 0 {
            return Err(format!(
                "object '{}': face is not a triangle after triangulation",
                model.name
            ));
        }
        let base = mesh.positions.len() as u32;
        mesh.positions.extend(
            m.positions
                .chunks_exact(3)
                .map(|c| Vec3::new(c[0], c[1], c[2])),
        );
        if all_normals {
            normals.extend(
                m.normals
                    .chunks_exact(3)
                    .map(|c| Vec3::new(c[0], c[1], c[2])),
            );
        }
        if all_uvs {
            uvs.extend(
                m.texcoords
                    .chunks_exact(2)
                    .map(|c| Vec2::new(c[0], if flip_tex_coords { 1.0 - c[1] } else { c[1] })),
            );
        }
        for t in m.indices.chunks_exact(3) {
            let idx = [t[0], t[1], t[2]];
            if idx.iter().any(|&i| i as usize >= nv) {
                return Err(format!(
                    "object '{}': face index out of range ({:?}, {nv} vertices)",
                    model.name, idx
                ));
            }
            mesh.indices.push(idx.map(|i| i + base));
        }
    }
    if all_normals && !mesh.positions.is_empty() {
        mesh.normals = Some(normals);
    }
    if all_uvs && !mesh.positions.is_empty() {
        mesh.uvs = Some(uvs);
    }
    Ok(mesh)
}
