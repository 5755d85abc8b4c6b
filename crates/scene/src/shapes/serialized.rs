//! Mitsuba's `serialized` meshes, file format versions 3 and 4 (what Mitsuba 0.5 and 0.6 and
//! their exporters write; Mitsuba 3 reads them too). Little endian: per shape a header
//! (`0x041C`, the version) and a zlib stream holding a flag word, the shape's name (version
//! 4: NUL-terminated), the vertex and triangle counts (u64), positions, then normals,
//! texture coordinates and colours if the flags say so (f32, or f64 with the double
//! precision flag), then three u32 vertex indices per triangle. Several shapes are
//! concatenated; the file ends with each shape's offset (u64 in version 4, u32 in version 3)
//! and their count (u32), which `shape_index` picks from.
//!
//! Untrusted input: the counts are checked against the limits and the memory budget before
//! anything is allocated, every index against the vertex count, and a stream that ends early
//! or a name longer than [`MAX_NAME_BYTES`] is an error naming the file.

use std::io::{BufReader, Read, Seek, SeekFrom};

use glam::{Vec2, Vec3};

use super::mesh::{check_limit, vertex_bytes, Budget, MeshInput, TRIANGLE_BYTES};
use crate::desc::TriangleMesh;
use crate::error::SceneError;

const MAGIC: u16 = 0x041C;
const HAS_NORMALS: u32 = 0x0001;
const HAS_TEXCOORDS: u32 = 0x0002;
const HAS_COLORS: u32 = 0x0008;
const DOUBLE_PRECISION: u32 = 0x2000;

/// The longest shape name read (Mitsuba's exporters write object names).
const MAX_NAME_BYTES: usize = 4096;

/// Loads shape `shape_index` of the serialized file `input` in object space.
pub(crate) fn load_serialized(
    input: &MeshInput,
    shape_index: u32,
    budget: &mut Budget,
) -> Result<TriangleMesh, SceneError> {
    let (mut file, size) = input.open()?;
    let err = |m: String| input.err(m);
    let version = header(&mut file).map_err(err)?;
    if shape_index > 0 {
        let offset = shape_offset(&mut file, size, version, shape_index).map_err(err)?;
        file.seek(SeekFrom::Start(offset))
            .map_err(|e| err(format!("cannot read: {e}")))?;
        let again = header(&mut file).map_err(err)?;
        if again != version {
            return Err(err(format!(
                "shape {shape_index} is of another format version"
            )));
        }
    }
    let mut z = flate2::read::ZlibDecoder::new(BufReader::new(file));
    let flags = u32::from_le_bytes(read_array(&mut z).map_err(err)?);
    if version == 4 {
        skip_name(&mut z).map_err(err)?;
    }
    let vertices = u64::from_le_bytes(read_array(&mut z).map_err(err)?);
    let triangles = u64::from_le_bytes(read_array(&mut z).map_err(err)?);
    let limits = budget.limits().clone();
    let max_vertices = limits.max_mesh_vertices.min(u32::MAX as u64);
    check_limit(vertices, "vertices", max_vertices, "max_mesh_vertices").map_err(err)?;
    check_limit(
        triangles,
        "triangles",
        limits.max_mesh_triangles,
        "max_mesh_triangles",
    )
    .map_err(err)?;
    let has_uvs = flags & HAS_TEXCOORDS != 0;
    let what = format!(
        "{} ({vertices} vertices, {triangles} triangles)",
        input.source
    );
    let bytes = vertices.saturating_mul(vertex_bytes(has_uvs));
    budget.reserve(
        bytes.saturating_add(triangles.saturating_mul(TRIANGLE_BYTES)),
        &what,
    )?;
    let (nv, nt) = (vertices as usize, triangles as usize);
    let double = flags & DOUBLE_PRECISION != 0;
    let mut mesh = TriangleMesh {
        positions: read_vec3s(&mut z, nv, double).map_err(err)?,
        normals: None,
        uvs: None,
        indices: Vec::new(),
        flip_normals: false,
    };
    if flags & HAS_NORMALS != 0 {
        mesh.normals = Some(read_vec3s(&mut z, nv, double).map_err(err)?);
    }
    if has_uvs {
        let mut uvs = Vec::with_capacity(nv);
        read_scalars(&mut z, nv * 2, double, |i, x| match i % 2 {
            0 => uvs.push(Vec2::new(x, 0.0)),
            _ => uvs.last_mut().expect("pushed").y = x,
        })
        .map_err(err)?;
        mesh.uvs = Some(uvs);
    }
    if flags & HAS_COLORS != 0 {
        read_scalars(&mut z, nv * 3, double, |_, _| {}).map_err(err)?;
    }
    mesh.indices = read_triangles(&mut z, nt, vertices).map_err(err)?;
    Ok(mesh)
}

/// The format version after checking the magic number.
fn header(r: &mut impl Read) -> Result<u16, String> {
    let h: [u8; 4] = read_array(r)?;
    let magic = u16::from_le_bytes([h[0], h[1]]);
    let version = u16::from_le_bytes([h[2], h[3]]);
    if magic != MAGIC {
        return Err(format!(
            "not a serialized mesh (it starts with 0x{magic:04X}, not 0x{MAGIC:04X})"
        ));
    }
    if !(3..=4).contains(&version) {
        return Err(format!(
            "serialized format version {version} is not supported (versions 3 and 4 are)"
        ));
    }
    Ok(version)
}

/// Where shape `index` starts, from the dictionary at the end of the file.
fn shape_offset(
    f: &mut (impl Read + Seek),
    size: u64,
    version: u16,
    index: u32,
) -> Result<u64, String> {
    let short = || "the file is too short for its dictionary of shapes".to_string();
    let io = |e: std::io::Error| format!("cannot read: {e}");
    f.seek(SeekFrom::Start(size.checked_sub(4).ok_or_else(short)?))
        .map_err(io)?;
    let count = u32::from_le_bytes(read_array(f)?);
    if index >= count {
        return Err(format!(
            "shape_index {index} is out of range: the file holds {count} shapes"
        ));
    }
    let left = (count - index) as u64;
    let offset = if version == 4 {
        let at = size.checked_sub(4 + 8 * left).ok_or_else(short)?;
        f.seek(SeekFrom::Start(at)).map_err(io)?;
        u64::from_le_bytes(read_array(f)?)
    } else {
        let at = size.checked_sub(4 * (left + 1)).ok_or_else(short)?;
        f.seek(SeekFrom::Start(at)).map_err(io)?;
        u32::from_le_bytes(read_array(f)?) as u64
    };
    if offset.saturating_add(4) > size {
        return Err(format!(
            "shape {index} starts at {offset}, past the end of the file"
        ));
    }
    Ok(offset)
}

fn read_array<const N: usize>(r: &mut impl Read) -> Result<[u8; N], String> {
    let mut b = [0u8; N];
    r.read_exact(&mut b).map_err(ended)?;
    Ok(b)
}

fn ended(e: std::io::Error) -> String {
    match e.kind() {
        std::io::ErrorKind::UnexpectedEof => "the mesh data ends early (truncated file)".into(),
        _ => format!("cannot read the compressed mesh data: {e}"),
    }
}

/// Skips a NUL-terminated name of at most [`MAX_NAME_BYTES`].
fn skip_name(r: &mut impl Read) -> Result<(), String> {
    for _ in 0..=MAX_NAME_BYTES {
        if read_array::<1>(r)?[0] == 0 {
            return Ok(());
        }
    }
    Err(format!(
        "the shape's name is longer than {MAX_NAME_BYTES} bytes"
    ))
}

/// Reads `n` scalars (f32, or f64 if `double`), handing each to `f` with its index, a block
/// at a time.
fn read_scalars(
    r: &mut impl Read,
    n: usize,
    double: bool,
    mut f: impl FnMut(usize, f32),
) -> Result<(), String> {
    let width = if double { 8 } else { 4 };
    let mut buf = vec![0u8; 1 << 16];
    let mut i = 0;
    while i < n {
        let take = (n - i).min(buf.len() / width);
        let block = &mut buf[..take * width];
        r.read_exact(block).map_err(ended)?;
        for c in block.chunks_exact(width) {
            let x = match double {
                true => f64::from_le_bytes(c.try_into().expect("8 bytes")) as f32,
                false => f32::from_le_bytes(c.try_into().expect("4 bytes")),
            };
            f(i, x);
            i += 1;
        }
    }
    Ok(())
}

fn read_vec3s(r: &mut impl Read, n: usize, double: bool) -> Result<Vec<Vec3>, String> {
    let mut out = Vec::with_capacity(n);
    read_scalars(r, n * 3, double, |i, x| match i % 3 {
        0 => out.push(Vec3::new(x, 0.0, 0.0)),
        1 => out.last_mut().expect("pushed").y = x,
        _ => out.last_mut().expect("pushed").z = x,
    })?;
    Ok(out)
}

/// Reads `n` triangles of three u32 indices, each below `vertices`.
fn read_triangles(r: &mut impl Read, n: usize, vertices: u64) -> Result<Vec<[u32; 3]>, String> {
    let mut out = Vec::with_capacity(n);
    let mut buf = vec![0u8; 12 << 12];
    let mut t = 0;
    while t < n {
        let take = (n - t).min(buf.len() / 12);
        let block = &mut buf[..take * 12];
        r.read_exact(block).map_err(ended)?;
        for c in block.chunks_exact(12) {
            let v = |k: usize| u32::from_le_bytes(c[4 * k..4 * k + 4].try_into().expect("4"));
            let tri = [v(0), v(1), v(2)];
            if let Some(&bad) = tri.iter().find(|&&i| i as u64 >= vertices) {
                return Err(format!(
                    "triangle {t}: vertex index {bad} out of range ({vertices} vertices)"
                ));
            }
            out.push(tri);
            t += 1;
        }
    }
    Ok(out)
}
