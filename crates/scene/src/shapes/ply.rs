//! Stanford PLY loading (via `ply-rs-bw`), ASCII or binary.

use std::path::Path;

use glam::{Vec2, Vec3};
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{DefaultElement, Property};

use crate::desc::TriangleMesh;

fn scalar(e: &DefaultElement, name: &str) -> Option<f32> {
    e.get(name).and_then(Property::to_f32_lossy)
}

/// Read the `vertex` (x y z, optional nx ny nz, optional u v / s t /
/// texture_u texture_v / texture_s texture_t) and `face` (`vertex_indices`
/// or `vertex_index` lists, fan-triangulated) elements. Mitsuba does not flip
/// PLY texture coordinates by default (`flip_tex_coords` false).
pub(crate) fn load_ply(path: &Path, flip_tex_coords: bool) -> Result<TriangleMesh, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("cannot read: {e}"))?;
    let mut reader = std::io::BufReader::new(file);
    let parser = Parser::<DefaultElement>::new();
    let ply = parser
        .read_ply(&mut reader)
        .map_err(|e| format!("cannot parse PLY: {e}"))?;
    let vertices = ply
        .payload
        .get("vertex")
        .ok_or("PLY file has no 'vertex' element")?;
    let faces = ply
        .payload
        .get("face")
        .ok_or("PLY file has no 'face' element")?;

    let mut mesh = TriangleMesh::default();
    let first = vertices.first();
    let has = |n: &str| first.is_some_and(|e| e.contains_key(n));
    let has_normals = has("nx") && has("ny") && has("nz");
    let uv_names = [
        ("u", "v"),
        ("s", "t"),
        ("texture_u", "texture_v"),
        ("texture_s", "texture_t"),
    ]
    .into_iter()
    .find(|(a, b)| has(a) && has(b));
    let mut normals = Vec::new();
    let mut uvs = Vec::new();
    for (i, e) in vertices.iter().enumerate() {
        let get = |n: &str| {
            scalar(e, n).ok_or_else(|| format!("vertex {i}: missing or non-scalar property '{n}'"))
        };
        mesh.positions
            .push(Vec3::new(get("x")?, get("y")?, get("z")?));
        if has_normals {
            normals.push(Vec3::new(get("nx")?, get("ny")?, get("nz")?));
        }
        if let Some((un, vn)) = uv_names {
            let v = get(vn)?;
            uvs.push(Vec2::new(
                get(un)?,
                if flip_tex_coords { 1.0 - v } else { v },
            ));
        }
    }
    for (f, e) in faces.iter().enumerate() {
        let list = e
            .get("vertex_indices")
            .or_else(|| e.get("vertex_index"))
            .ok_or_else(|| format!("face {f}: no 'vertex_indices' list"))?;
        let idx: Vec<i64> = match list {
            Property::ListChar(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUChar(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListShort(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUShort(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListInt(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUInt(v) => v.iter().map(|&x| x as i64).collect(),
            _ => return Err(format!("face {f}: vertex indices are not an integer list")),
        };
        if idx.len() < 3 {
            return Err(format!("face {f} has fewer than 3 vertices"));
        }
        if let Some(bad) = idx
            .iter()
            .find(|&&i| i < 0 || i as usize >= mesh.positions.len())
        {
            return Err(format!(
                "face {f}: vertex index {bad} out of range ({} vertices)",
                mesh.positions.len()
            ));
        }
        for k in 1..idx.len() - 1 {
            mesh.indices
                .push([idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
        }
    }
    if has_normals {
        mesh.normals = Some(normals);
    }
    if uv_names.is_some() {
        mesh.uvs = Some(uvs);
    }
    Ok(mesh)
}
