//! What the mesh loaders share: the mesh file being read ([`MeshInput`]), opening it, the
//! memory [`Budget`] of a load and its line reader, and turning a loaded object-space triangle
//! mesh into a validated world-space [`TriangleMesh`] ([`finalize`]).

use std::fmt::Display;
use std::fs::File;
use std::io::{BufRead, Read};
use std::path::Path;

use glam::{DMat3, DMat4, DVec3, Vec3};

use crate::context::Ctx;
use crate::desc::{Location, TriangleMesh};
use crate::error::SceneError;
use crate::limits::Limits;
use crate::xml::invalid;

/// The largest world-space |coordinate| a shape may reach. The renderer squares coordinates
/// (and distances) in 32-bit floats, which overflow to infinity beyond about 1.8e19, and the
/// geometry then silently vanishes; 1e18 leaves some room for sums of squares.
pub(crate) const MAX_WORLD_COORDINATE: f64 = 1e18;

/// Bytes per vertex of a finished mesh: position and shading normal (the file's, or computed
/// ones), plus texture coordinates when it has them.
pub(crate) fn vertex_bytes(has_uvs: bool) -> u64 {
    12 + 12 + if has_uvs { 8 } else { 0 }
}

/// Bytes per triangle of a finished mesh (three 32-bit indices).
pub(crate) const TRIANGLE_BYTES: u64 = 12;

/// The mesh file a shape refers to.
pub(crate) struct MeshInput<'a> {
    pub path: &'a Path,
    /// "mesh file '/abs/x.obj'", the start of every message about it.
    pub source: String,
    /// The scene file line of the `<string name="filename">`.
    pub loc: Location,
    /// Mitsuba's `flip_tex_coords`: v is replaced by 1 - v.
    pub flip_tex_coords: bool,
}

impl MeshInput<'_> {
    /// An error about the mesh file: "scene.xml:12: mesh file '…': {msg}".
    pub(crate) fn err(&self, msg: impl Display) -> SceneError {
        invalid(&self.loc, format!("{}: {msg}", self.source))
    }

    /// Open the file, refusing what is not a regular file (a directory, a FIFO, a device)
    /// with a message that says so; returns the file and its size in bytes.
    pub(crate) fn open(&self) -> Result<(File, u64), SceneError> {
        let cannot_read = |e: std::io::Error| self.err(format!("cannot read: {e}"));
        let meta = std::fs::metadata(self.path).map_err(cannot_read)?;
        if meta.is_dir() {
            return Err(self.err("is a directory, not a mesh file"));
        }
        if !meta.is_file() {
            return Err(self.err("is not a regular file"));
        }
        let file = File::open(self.path).map_err(cannot_read)?;
        Ok((file, meta.len()))
    }
}

/// The memory a mesh load accounts for in [`Ctx::reserve_memory`]: reserved before the
/// vectors are allocated (an estimate, grown in steps while loading when the estimate proves
/// short), then settled to the finished mesh's actual size ([`Budget::settle`]).
pub(crate) struct Budget<'c> {
    ctx: &'c mut Ctx,
    loc: Location,
    held: u64,
}

impl<'c> Budget<'c> {
    pub(crate) fn new(ctx: &'c mut Ctx, loc: &Location) -> Self {
        Self {
            ctx,
            loc: loc.clone(),
            held: 0,
        }
    }

    pub(crate) fn limits(&self) -> &Limits {
        &self.ctx.limits
    }

    /// Reserve `bytes` more for `what` ("mesh file '…' (12 triangles)"); an error at the
    /// filename's line when the scene's data would exceed `Limits::max_memory_bytes`.
    pub(crate) fn reserve(&mut self, bytes: u64, what: &str) -> Result<(), SceneError> {
        self.ctx.reserve_memory(bytes, what, &self.loc)?;
        self.held = self.held.saturating_add(bytes);
        Ok(())
    }

    /// Replace what this load reserved by `actual`, the finished mesh's size (the temporary
    /// arrays of the parse are freed by then).
    pub(crate) fn settle(mut self, actual: u64, what: &str) -> Result<(), SceneError> {
        if actual > self.held {
            self.reserve(actual - self.held, what)
        } else {
            self.ctx.memory_bytes = self.ctx.memory_bytes.saturating_sub(self.held - actual);
            Ok(())
        }
    }
}

/// Reads a text file line by line (lines end at '\n'), keeping only one line in memory, at
/// most `cap` bytes long.
pub(crate) struct LineReader<R> {
    reader: R,
    buf: Vec<u8>,
    /// 1-based number of the line last returned.
    pub line: u64,
    /// Bytes read so far.
    pub consumed: u64,
    cap: usize,
}

impl<R: BufRead> LineReader<R> {
    pub(crate) fn new(reader: R, cap: usize) -> Self {
        Self {
            reader,
            buf: Vec::new(),
            line: 0,
            consumed: 0,
            cap,
        }
    }

    pub(crate) fn get_mut(&mut self) -> &mut R {
        &mut self.reader
    }

    /// Read lines of up to `cap` bytes from now on.
    pub(crate) fn set_cap(&mut self, cap: usize) {
        self.cap = cap;
    }

    /// The next line's number (1-based) and bytes, without its "\n" or "\r\n" (`None` at
    /// the end of the file).
    pub(crate) fn next_bytes(&mut self) -> Result<Option<(u64, &[u8])>, String> {
        self.buf.clear();
        let limit = self.cap as u64 + 2;
        let n = (&mut self.reader)
            .take(limit)
            .read_until(b'\n', &mut self.buf)
            .map_err(|e| format!("line {}: read error: {e}", self.line + 1))?;
        if n == 0 {
            return Ok(None);
        }
        self.consumed += n as u64;
        self.line += 1;
        if self.buf.last() == Some(&b'\n') {
            self.buf.pop();
            if self.buf.last() == Some(&b'\r') {
                self.buf.pop();
            }
        }
        if self.buf.len() > self.cap {
            return Err(format!(
                "line {} is longer than {} bytes, the longest line this loader reads",
                self.line, self.cap
            ));
        }
        Ok(Some((self.line, &self.buf)))
    }

    /// The next line as text: a NUL byte or invalid UTF-8 is an error naming the line.
    pub(crate) fn next_text(&mut self) -> Result<Option<(u64, &str)>, String> {
        let Some((line, bytes)) = self.next_bytes()? else {
            return Ok(None);
        };
        text_of(line, bytes).map(|t| Some((line, t)))
    }

    /// The next line of an OBJ file as text ([`obj_text_of`]).
    pub(crate) fn next_obj_text(&mut self) -> Result<Option<(u64, &str)>, String> {
        let Some((line, bytes)) = self.next_bytes()? else {
            return Ok(None);
        };
        obj_text_of(line, bytes).map(|t| Some((line, t)))
    }
}

/// An OBJ line as text. Only keywords and numbers need be ASCII: a line that is not UTF-8
/// (a 3ds Max export writes names and comments in its code page) is read as the part before
/// its comment if that is text, else as its keyword alone if the keyword only names
/// something (`o`, `g`, `usemtl`, `mtllib`, `s`, or a comment); a data line (`v`, `f`, ...)
/// that is not text is still an error.
pub(crate) fn obj_text_of(line: u64, bytes: &[u8]) -> Result<&str, String> {
    let error = match text_of(line, bytes) {
        Ok(text) => return Ok(text),
        Err(e) if bytes.contains(&0) => return Err(e),
        Err(e) => e,
    };
    if let Some(hash) = bytes.iter().position(|&b| b == b'#') {
        if let Ok(text) = std::str::from_utf8(&bytes[..hash]) {
            return Ok(text);
        }
    }
    let keyword = (bytes.split(u8::is_ascii_whitespace))
        .find(|w| !w.is_empty())
        .unwrap_or_default();
    match keyword {
        b"o" | b"g" | b"usemtl" | b"mtllib" | b"s" => {
            Ok(std::str::from_utf8(keyword).expect("ASCII"))
        }
        _ => Err(error),
    }
}

/// `bytes` (line `line` of a text file) as text: a NUL byte or invalid UTF-8 is an error.
pub(crate) fn text_of(line: u64, bytes: &[u8]) -> Result<&str, String> {
    if bytes.contains(&0) {
        return Err(format!(
            "line {line} contains a NUL byte: this is binary data (or UTF-16 text, which is \
             unsupported), not a text file"
        ));
    }
    std::str::from_utf8(bytes).map_err(|e| {
        format!(
            "line {line} is not valid UTF-8 text (invalid byte at column {}); mesh files must \
             be ASCII or UTF-8",
            e.valid_up_to() + 1
        )
    })
}

/// At most the first 40 characters of `token`, for messages.
pub(crate) fn shown(token: &str) -> String {
    crate::shown_bounded(token, 40)
}

/// "1234 vertices, more than the limit of 1000 (Limits::max_mesh_vertices)" when
/// `count > limit`.
pub(crate) fn check_limit(count: u64, what: &str, limit: u64, field: &str) -> Result<(), String> {
    if count > limit {
        Err(format!(
            "{count} {what}, more than the limit of {limit} (Limits::{field})"
        ))
    } else {
        Ok(())
    }
}

/// Validate `mesh` (object space, as read from `source`), compute vertex
/// normals when the file has none (unless `face_normals`), and bake
/// `to_world` in: positions by the matrix, normals by its inverse transpose
/// (renormalised). Errors name `source` and the XML line `loc` (for a mesh
/// file, the line of its `filename`); world-space positions beyond
/// [`MAX_WORLD_COORDINATE`] are an error at the shape's line `shape_loc`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn finalize(
    mut mesh: TriangleMesh,
    to_world: DMat4,
    face_normals: bool,
    flip_normals: bool,
    source: &str,
    loc: &Location,
    shape_loc: &Location,
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
    for (i, p) in mesh.positions.iter_mut().enumerate() {
        let w = to_world.transform_point3(p.as_dvec3());
        if !w.is_finite() {
            return Err(err("a transformed vertex position is not finite".into()));
        }
        if !(w.abs().max_element() <= MAX_WORLD_COORDINATE) {
            return Err(invalid(
                shape_loc,
                format!(
                    "{source}: vertex {i} lies at ({:?}, {:?}, {:?}) in world space, {}",
                    w.x,
                    w.y,
                    w.z,
                    beyond_bound_message()
                ),
            ));
        }
        *p = w.as_vec3();
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

/// Why a world-space coordinate beyond [`MAX_WORLD_COORDINATE`] is refused.
pub(crate) fn beyond_bound_message() -> String {
    format!(
        "beyond the bound of {MAX_WORLD_COORDINATE:e} on |x|, |y| and |z| (the renderer squares \
         coordinates in 32-bit floats, which become infinite beyond about 1.8e19)"
    )
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

/// Polygons with at most this many corners are fan-triangulated, as Mitsuba and tobj do
/// (corners 0, k, k + 1), so ordinary meshes keep their exact triangles.
pub(crate) const MAX_FAN_CORNERS: usize = 32;

/// Triangulates the polygon `corners` (n >= 3) into `out`, keeping its winding. Larger
/// polygons are split recursively at the middle corner of each range (triangle
/// (first, middle, last), then both halves): a fan's triangles all share corner 0, so their
/// boxes all overlap there and the BVH build took seconds for one face of 30,000 corners;
/// the split's triangles are mostly small and local, like the polygon's own edges.
pub(crate) fn triangulate(corners: &[u32], out: &mut Vec<[u32; 3]>) {
    let n = corners.len();
    if n <= MAX_FAN_CORNERS {
        out.extend((1..n.saturating_sub(1)).map(|k| [corners[0], corners[k], corners[k + 1]]));
        return;
    }
    // Ranges [a, b] of corners still to triangulate, on an explicit stack (depth log2 n).
    let mut stack = vec![(0usize, n - 1)];
    while let Some((a, b)) = stack.pop() {
        if b - a < 2 {
            continue;
        }
        let m = a + (b - a) / 2;
        // Corners in polygon order: the polygon's winding.
        out.push([corners[a], corners[m], corners[b]]);
        stack.push((m, b));
        stack.push((a, m));
    }
}

/// A mesh loader ([`super::obj::load_obj`], [`super::ply::load_ply`]) run on `path` as a
/// scene's shape would run it, in a context of its own under `limits`: for the loaders' unit
/// tests, which call it without a scene.
#[cfg(test)]
pub(crate) fn load_alone(
    load: fn(&MeshInput, &mut Budget) -> Result<TriangleMesh, SceneError>,
    path: &Path,
    flip_tex_coords: bool,
    limits: Limits,
) -> Result<TriangleMesh, SceneError> {
    let mut ctx = Ctx::new(
        std::collections::HashMap::new(),
        std::path::PathBuf::new(),
        limits,
        crate::context::Reading::Contents,
    );
    // (a made-up scene file line for the errors to name)
    let loc = Location {
        file: std::path::PathBuf::from("scene.xml"),
        line: 1,
    };
    let input = MeshInput {
        path,
        source: format!("mesh file '{}'", path.display()),
        loc: loc.clone(),
        flip_tex_coords,
    };
    let mut budget = Budget::new(&mut ctx, &loc);
    load(&input, &mut budget)
}

#[cfg(test)]
mod triangulate_tests {
    use super::*;

    #[test]
    fn small_polygons_are_fans_and_large_ones_strips_covering_every_edge_once() {
        let mut out = Vec::new();
        triangulate(&[0, 1, 2, 3], &mut out);
        assert_eq!(out, vec![[0, 1, 2], [0, 2, 3]]);
        for n in [MAX_FAN_CORNERS + 1, 100, 1001] {
            let corners: Vec<u32> = (0..n as u32).collect();
            out.clear();
            triangulate(&corners, &mut out);
            assert_eq!(out.len(), n - 2);
            // Every polygon edge appears once in the same direction (the winding is kept),
            // every inner edge twice in opposite directions (a watertight triangulation).
            let mut edges = std::collections::HashMap::new();
            for t in &out {
                assert!(t[0] < t[1] && t[1] < t[2], "{t:?} changes the winding");
                for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                    *edges.entry((a, b)).or_insert(0) += 1;
                }
            }
            for k in 0..n as u32 {
                let (a, b) = (k, (k + 1) % n as u32);
                assert_eq!(edges.get(&(a, b)), Some(&1), "polygon edge {a}-{b}");
                assert_eq!(edges.get(&(b, a)), None);
            }
            for (&(a, b), &c) in &edges {
                let boundary = (a + 1) % n as u32 == b;
                assert!(
                    boundary || (c == 1 && edges.get(&(b, a)) == Some(&1)),
                    "edge {a}-{b}"
                );
            }
        }
    }
}
