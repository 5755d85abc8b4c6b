//! Wavefront OBJ loading, with Mitsuba's texture-coordinate convention.
//!
//! Our own parser, linear in the size of the file, reading it twice: a cheap first pass
//! checks the text and counts `v`, `vt`, `vn` lines and face corners, so the counts are checked
//! against the [`crate::Limits`] and the memory is reserved before anything big is allocated;
//! the second pass parses. Every error names the OBJ line.
//!
//! The meshes are those `tobj` (which pathfarm used before) makes with `triangulate`,
//! `single_index`, `ignore_points` and `ignore_lines`, merged as pathfarm merged them:
//!
//! - `o` and `g` start a new object; within an object, each distinct (position, texture
//!   coordinate, normal) index triple of a face corner is one vertex, numbered in order of
//!   first use; the objects' vertices are concatenated;
//! - faces are triangulated by `mesh::triangulate` (fans up to 32 corners, strips beyond); faces of one or two corners are ignored,
//!   as are `l`, `p`, `s`, `usemtl`, `mtllib`, comments and unknown statements;
//! - the mesh has texture coordinates (normals) if every object has a corner with one, and
//!   then every corner must have one; otherwise it has none;
//! - `v x y z w` divides by w; `v x y z r g b` (vertex colours) ignores the colour;
//! - numbers are read by Rust's `str::parse::<f32>`, as tobj reads them, so the bits agree;
//! - a `vt` (`vn`) index in a file without `vt` (`vn`) lines is ignored.
//!
//! Where tobj accepted what is clearly broken, this loader refuses it with a message: an
//! index 0, a corner referring to a vertex defined after it, a face with no corners.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Seek};
use std::str::SplitWhitespace;

use glam::{Vec2, Vec3};

use super::mesh::{
    check_limit, shown, vertex_bytes, Budget, LineReader, MeshInput, TRIANGLE_BYTES,
};
use crate::desc::TriangleMesh;
use crate::error::SceneError;

/// Bytes per vertex of the (position, texture, normal) → vertex map while parsing.
const MAP_BYTES_PER_VERTEX: u64 = 40;

/// The longest line read: a face of `max_polygon_vertices` corners of up to 64 characters.
fn line_cap(max_polygon_vertices: u64) -> usize {
    max_polygon_vertices
        .saturating_mul(64)
        .saturating_add(4096)
        .clamp(1 << 20, 1 << 30) as usize
}

/// What the first pass counts.
#[derive(Default)]
struct Counts {
    positions: u64,
    texcoords: u64,
    normals: u64,
    /// Corners of the faces that make triangles (three or more corners).
    corners: u64,
    triangles: u64,
}

/// Read an OBJ file into one object-space mesh (see the module documentation). Like Mitsuba
/// (`flip_tex_coords`, default true for OBJ), v is replaced by 1 - v when
/// `input.flip_tex_coords`. Materials are ignored.
pub(crate) fn load_obj(input: &MeshInput, budget: &mut Budget) -> Result<TriangleMesh, SceneError> {
    let limits = budget.limits().clone();
    let (file, _) = input.open()?;
    let mut reader = BufReader::new(file);
    let cap = line_cap(limits.max_polygon_vertices);

    skip_byte_order_mark(&mut reader).map_err(|m| input.err(m))?;
    let counts = count(
        &mut LineReader::new(&mut reader, cap),
        limits.max_polygon_vertices,
    )
    .map_err(|m| input.err(m))?;

    check_limit(
        counts.triangles,
        "triangles",
        limits.max_mesh_triangles,
        "max_mesh_triangles",
    )
    .and_then(|()| {
        check_limit(
            counts.positions,
            "vertex positions ('v' lines)",
            limits.max_mesh_vertices,
            "max_mesh_vertices",
        )
    })
    .map_err(|m| input.err(m))?;

    // The vertex count is known only after parsing: reserve for an estimate (a typical mesh
    // has about as many vertices as position, uv or normal lines) and grow while parsing.
    let has_uvs = counts.texcoords > 0;
    let per_vertex = vertex_bytes(has_uvs) + MAP_BYTES_PER_VERTEX;
    let estimated_vertices = counts
        .corners
        .min(counts.positions.max(counts.texcoords).max(counts.normals));
    let what = format!("{} ({} triangles)", input.source, counts.triangles);
    let raw = counts
        .positions
        .saturating_mul(12)
        .saturating_add(counts.texcoords.saturating_mul(8))
        .saturating_add(counts.normals.saturating_mul(12));
    budget.reserve(
        estimated_vertices
            .saturating_mul(per_vertex)
            .saturating_add(counts.triangles.saturating_mul(TRIANGLE_BYTES))
            .saturating_add(raw),
        &what,
    )?;

    reader
        .rewind()
        .map_err(|e| input.err(format!("cannot read: {e}")))?;
    skip_byte_order_mark(&mut reader).map_err(|m| input.err(m))?;
    let mut parser = Parser::new(input, &counts, estimated_vertices, per_vertex, &limits);
    parser.run(&mut LineReader::new(&mut reader, cap), budget, &what)?;
    parser.finish().map_err(|m| input.err(m))
}

/// Refuse UTF-16 (by its byte-order mark) and skip a UTF-8 byte-order mark.
fn skip_byte_order_mark<R: BufRead>(reader: &mut R) -> Result<(), String> {
    let head = reader.fill_buf().map_err(|e| format!("cannot read: {e}"))?;
    if head.starts_with(&[0xFF, 0xFE]) || head.starts_with(&[0xFE, 0xFF]) {
        return Err(
            "the file is UTF-16 text (it starts with a UTF-16 byte-order mark); UTF-16 \
                    is unsupported: convert it to UTF-8 or ASCII"
                .into(),
        );
    }
    if head.starts_with(&[0xEF, 0xBB, 0xBF]) {
        reader.consume(3);
    }
    Ok(())
}

/// The first pass: check that the file is text, count, and check polygon sizes.
fn count<R: BufRead>(lines: &mut LineReader<R>, max_polygon: u64) -> Result<Counts, String> {
    let mut c = Counts::default();
    while let Some((line, text)) = lines.next_obj_text()? {
        let mut words = text.split_whitespace();
        match words.next() {
            Some("v") => c.positions += 1,
            Some("vt") => c.texcoords += 1,
            Some("vn") => c.normals += 1,
            Some("f") => {
                let k = words.count() as u64;
                if k > max_polygon {
                    return Err(polygon_error(line, k, max_polygon));
                }
                if k >= 3 {
                    c.corners += k;
                    c.triangles += k - 2;
                }
            }
            _ => {}
        }
    }
    Ok(c)
}

fn polygon_error(line: u64, k: u64, max_polygon: u64) -> String {
    format!(
        "line {line}: face has {k} vertices, more than the limit of {max_polygon} \
         (Limits::max_polygon_vertices)"
    )
}

const CHANGED: &str = "the file changed while it was being read";

/// A corner's key: its position index, and its texture and normal index as tobj resolves them
/// (0-based; -1 for none).
type Key = (u32, i64, i64);

/// A missing texture or normal index.
const NONE: i64 = -1;

/// The second pass.
struct Parser<'a> {
    input: &'a MeshInput<'a>,
    counts: &'a Counts,
    max_vertices: u64,
    max_polygon: u64,
    /// The file's `v`, `vt`, `vn` lines.
    pos: Vec<Vec3>,
    tex: Vec<Vec2>,
    nrm: Vec<Vec3>,
    /// The mesh being built; `uvs` (`normals`) are filled when the file has `vt` (`vn`)
    /// lines, with zero for corners without.
    positions: Vec<Vec3>,
    uvs: Vec<Vec2>,
    normals: Vec<Vec3>,
    indices: Vec<[u32; 3]>,
    /// Corner key → vertex, for the current object.
    vertex_of: HashMap<Key, u32>,
    /// Vertices memory has been reserved for, and the bytes of each.
    reserved_vertices: u64,
    per_vertex: u64,
    /// Whether the current object has a face (with three or more corners), and a corner with
    /// a texture coordinate / normal.
    object_has_faces: bool,
    object_any_uv: bool,
    object_any_normal: bool,
    /// Whether every object so far with faces had a corner with a texture coordinate / normal.
    all_objects_uv: bool,
    all_objects_normal: bool,
    /// The first corner without a texture coordinate / normal (line, corner).
    first_without_uv: Option<(u64, String)>,
    first_without_normal: Option<(u64, String)>,
    /// The current face's corner keys and vertices.
    keys: Vec<Key>,
    face: Vec<u32>,
}

impl<'a> Parser<'a> {
    fn new(
        input: &'a MeshInput<'a>,
        counts: &'a Counts,
        estimated_vertices: u64,
        per_vertex: u64,
        limits: &crate::Limits,
    ) -> Self {
        let v = estimated_vertices as usize;
        Self {
            input,
            counts,
            max_vertices: limits.max_mesh_vertices.min(u32::MAX as u64),
            max_polygon: limits.max_polygon_vertices,
            pos: Vec::with_capacity(counts.positions as usize),
            tex: Vec::with_capacity(counts.texcoords as usize),
            nrm: Vec::with_capacity(counts.normals as usize),
            positions: Vec::with_capacity(v),
            uvs: Vec::with_capacity(if counts.texcoords > 0 { v } else { 0 }),
            normals: Vec::with_capacity(if counts.normals > 0 { v } else { 0 }),
            indices: Vec::with_capacity(counts.triangles as usize),
            vertex_of: HashMap::new(),
            reserved_vertices: estimated_vertices,
            per_vertex,
            object_has_faces: false,
            object_any_uv: false,
            object_any_normal: false,
            all_objects_uv: true,
            all_objects_normal: true,
            first_without_uv: None,
            first_without_normal: None,
            keys: Vec::new(),
            face: Vec::new(),
        }
    }

    fn run<R: BufRead>(
        &mut self,
        lines: &mut LineReader<R>,
        budget: &mut Budget,
        what: &str,
    ) -> Result<(), SceneError> {
        while let Some((line, text)) = lines.next_obj_text().map_err(|m| self.input.err(m))? {
            self.line(line, text, budget, what)?;
        }
        self.end_object();
        Ok(())
    }

    fn line(
        &mut self,
        line: u64,
        text: &str,
        budget: &mut Budget,
        what: &str,
    ) -> Result<(), SceneError> {
        let input = self.input;
        let err = |m: String| input.err(format!("line {line}: {m}"));
        let mut words = text.split_whitespace();
        match words.next() {
            Some("v") => {
                let mut p = numbers::<3>(&mut words, "vertex coordinate", |i| {
                    format!("vertex has {i} coordinates, expected 3 (x y z)")
                })
                .map_err(err)?;
                let rest: Vec<&str> = words.by_ref().take(4).collect();
                match rest.len() {
                    0 | 3 => {} // x y z, or x y z r g b (the colour is ignored)
                    1 => {
                        let w = number(rest[0], "vertex w coordinate").map_err(err)?;
                        if w == 0.0 {
                            return Err(err("vertex w coordinate is 0".into()));
                        }
                        for c in &mut p {
                            *c /= w;
                        }
                    }
                    n => {
                        let n = if n == 2 { "5" } else { "more than 6" };
                        return Err(err(format!(
                            "vertex has {n} values, expected x y z, x y z w or x y z r g b"
                        )));
                    }
                }
                push_counted(&mut self.pos, self.counts.positions, Vec3::from_array(p))
                    .map_err(err)?;
            }
            Some("vt") => {
                let t = numbers::<2>(&mut words, "texture coordinate", |i| {
                    format!("texture coordinate has {i} values, expected 2 (u v)")
                })
                .map_err(err)?;
                push_counted(&mut self.tex, self.counts.texcoords, Vec2::from_array(t))
                    .map_err(err)?;
            }
            Some("vn") => {
                let n = numbers::<3>(&mut words, "normal component", |i| {
                    format!("normal has {i} components, expected 3 (x y z)")
                })
                .map_err(err)?;
                push_counted(&mut self.nrm, self.counts.normals, Vec3::from_array(n))
                    .map_err(err)?;
            }
            Some("f") => self.face(line, words, budget, what)?,
            Some("o") | Some("g") => self.end_object(),
            _ => {}
        }
        Ok(())
    }

    /// The current object ends (at `o`, `g` or the end of the file).
    fn end_object(&mut self) {
        if self.object_has_faces {
            self.all_objects_uv &= self.object_any_uv;
            self.all_objects_normal &= self.object_any_normal;
        }
        self.object_has_faces = false;
        self.object_any_uv = false;
        self.object_any_normal = false;
        if !self.vertex_of.is_empty() {
            // Dropped, not cleared: clearing costs the table's capacity, every time.
            self.vertex_of = HashMap::new();
        }
    }

    fn face(
        &mut self,
        line: u64,
        words: SplitWhitespace,
        budget: &mut Budget,
        what: &str,
    ) -> Result<(), SceneError> {
        let input = self.input;
        let err = |m: String| input.err(format!("line {line}: {m}"));
        let n = words.clone().count();
        match n as u64 {
            0 => return Err(err("face has no vertices".into())),
            1 | 2 => {
                // A point or a line: ignored (only its syntax is checked, as tobj does).
                for w in words {
                    corner_syntax(w).map_err(err)?;
                }
                return Ok(());
            }
            k if k > self.max_polygon => return Err(err(CHANGED.into())),
            _ => {}
        }
        if self.indices.len() as u64 + (n as u64 - 2) > self.counts.triangles {
            return Err(err(CHANGED.into()));
        }
        // Buffers kept from face to face: no allocation per face.
        let mut keys = std::mem::take(&mut self.keys);
        keys.clear();
        for w in words.clone() {
            keys.push(self.corner(w).map_err(err)?);
        }
        self.object_has_faces = true;
        let has_uvs = self.counts.texcoords > 0;
        let has_normals = self.counts.normals > 0;
        let mut face = std::mem::take(&mut self.face);
        face.clear();
        for (i, &key) in keys.iter().enumerate() {
            let (v, t, nn) = key;
            let corner = || (line, shown(words.clone().nth(i).unwrap_or_default()));
            if has_uvs && t != NONE {
                self.object_any_uv = true;
            } else if self.first_without_uv.is_none() {
                self.first_without_uv = Some(corner());
            }
            if has_normals && nn != NONE {
                self.object_any_normal = true;
            } else if self.first_without_normal.is_none() {
                self.first_without_normal = Some(corner());
            }
            let id = match self.vertex_of.get(&key) {
                Some(&id) => id,
                None => {
                    let id = self.positions.len() as u64;
                    if id >= self.max_vertices {
                        return Err(err(format!(
                            "the mesh has more than {} vertices (distinct position / texture \
                             coordinate / normal combinations), the limit \
                             (Limits::max_mesh_vertices)",
                            self.max_vertices
                        )));
                    }
                    if id >= self.reserved_vertices {
                        self.grow(budget, what).map_err(|e| match e {
                            Some(e) => e,
                            None => err(CHANGED.into()),
                        })?;
                    }
                    self.positions.push(self.pos[v as usize]);
                    if has_uvs {
                        self.uvs.push(if t == NONE {
                            Vec2::ZERO
                        } else {
                            let uv = self.tex[t as usize];
                            let flip = self.input.flip_tex_coords;
                            Vec2::new(uv.x, if flip { 1.0 - uv.y } else { uv.y })
                        });
                    }
                    if has_normals {
                        self.normals.push(if nn == NONE {
                            Vec3::ZERO
                        } else {
                            self.nrm[nn as usize]
                        });
                    }
                    self.vertex_of.insert(key, id as u32);
                    id as u32
                }
            };
            face.push(id);
        }
        super::mesh::triangulate(&face, &mut self.indices);
        self.face = face;
        self.keys = keys;
        Ok(())
    }

    /// Reserve memory for more vertices than estimated (`Err(None)`: more vertices than
    /// corners, the file changed).
    fn grow(&mut self, budget: &mut Budget, what: &str) -> Result<(), Option<SceneError>> {
        let more = (self.reserved_vertices / 2)
            .max(1 << 16)
            .min(self.counts.corners.saturating_sub(self.reserved_vertices));
        if more == 0 {
            return Err(None);
        }
        budget
            .reserve(more.saturating_mul(self.per_vertex), what)
            .map_err(Some)?;
        self.reserved_vertices += more;
        let more = more as usize;
        self.positions.reserve_exact(more);
        if self.counts.texcoords > 0 {
            self.uvs.reserve_exact(more);
        }
        if self.counts.normals > 0 {
            self.normals.reserve_exact(more);
        }
        Ok(())
    }

    /// A face corner `i`, `i/t`, `i//n` or `i/t/n` (indices 1-based, or negative: relative to
    /// the end of the list so far).
    fn corner(&self, w: &str) -> Result<Key, String> {
        let [v, t, n] = corner_parts(w)?;
        let parse = |s: &str| {
            s.parse::<i64>()
                .map_err(|_| format!("could not parse face corner \"{}\"", shown(w)))
        };
        if v.is_empty() {
            return Err(format!("face corner \"{}\" has no vertex index", shown(w)));
        }
        let v = resolve(parse(v)?, self.pos.len(), "face index", "vertices")?;
        // The texture coordinate or normal index `s`, of a list that has `len` items so far
        // and `counted` in the whole file.
        let attribute =
            |s: &str, counted: u64, len: usize, what: &str, items: &str| -> Result<i64, String> {
                if s.is_empty() {
                    Ok(NONE)
                } else if counted == 0 {
                    // No `vt` (`vn`) lines: tobj ignores the index, but it still tells corners
                    // apart.
                    let x = parse(s)?;
                    Ok(if x < 0 { x } else { x - 1 })
                } else {
                    Ok(resolve(parse(s)?, len, what, items)? as i64)
                }
            };
        let t = attribute(
            t,
            self.counts.texcoords,
            self.tex.len(),
            "texture coordinate index",
            "texture coordinates",
        )?;
        let n = attribute(
            n,
            self.counts.normals,
            self.nrm.len(),
            "normal index",
            "normals",
        )?;
        Ok((v, t, n))
    }

    /// The mesh, once the whole file is parsed.
    fn finish(self) -> Result<TriangleMesh, String> {
        let mut mesh = TriangleMesh {
            positions: self.positions,
            indices: self.indices,
            ..Default::default()
        };
        if mesh.positions.is_empty() {
            return Ok(mesh);
        }
        mesh.uvs = kept_attribute(
            self.uvs,
            self.counts.texcoords > 0 && self.all_objects_uv,
            self.first_without_uv,
            "texture coordinate",
        )?;
        mesh.normals = kept_attribute(
            self.normals,
            self.counts.normals > 0 && self.all_objects_normal,
            self.first_without_normal,
            "normal",
        )?;
        Ok(mesh)
    }
}

/// The finished mesh's texture coordinates or normals (`what`): `values` when `kept` (the file
/// has them and every object with faces used them), and then an error if a corner of such an
/// object, `first_without` (line, corner), had none.
fn kept_attribute<T>(
    values: Vec<T>,
    kept: bool,
    first_without: Option<(u64, String)>,
    what: &str,
) -> Result<Option<Vec<T>>, String> {
    if !kept {
        return Ok(None);
    }
    if let Some((line, corner)) = first_without {
        return Err(format!(
            "line {line}: face corner \"{corner}\" has no {what} index, but other faces have \
             {what}s (give every face {what}s, or none)"
        ));
    }
    Ok(Some(values))
}

/// The position, texture and normal index strings of the face corner `w` (empty if absent).
fn corner_parts(w: &str) -> Result<[&str; 3], String> {
    let mut parts = w.split('/');
    let v = parts.next().unwrap_or("");
    let t = parts.next().unwrap_or("");
    let n = parts.next().unwrap_or("");
    if parts.any(|rest| !rest.is_empty()) {
        return Err(format!(
            "face corner \"{}\" has more than three indices",
            shown(w)
        ));
    }
    Ok([v, t, n])
}

/// Check the syntax of the face corner `w` of an ignored face: its indices are integers.
fn corner_syntax(w: &str) -> Result<(), String> {
    for s in corner_parts(w)? {
        if !s.is_empty() && s.parse::<i64>().is_err() {
            return Err(format!("could not parse face corner \"{}\"", shown(w)));
        }
    }
    Ok(())
}

/// A parsed OBJ number.
fn number(w: &str, what: &str) -> Result<f32, String> {
    w.parse::<f32>()
        .map_err(|_| format!("could not parse {what} \"{}\"", shown(w)))
}

/// The next `N` words of a `v`, `vt` or `vn` line as numbers, each a `what` in its parse
/// error; `missing(i)` is the error when the line ends after `i` of them.
fn numbers<const N: usize>(
    words: &mut std::str::SplitWhitespace,
    what: &str,
    missing: impl Fn(usize) -> String,
) -> Result<[f32; N], String> {
    let mut out = [0.0f32; N];
    for (i, c) in out.iter_mut().enumerate() {
        let w = words.next().ok_or_else(|| missing(i))?;
        *c = number(w, what)?;
    }
    Ok(out)
}

/// Append `x` to `list`, of which the counting pass found `counted`: finding more now means
/// the file changed between the two passes (the vectors were sized by the count).
fn push_counted<T>(list: &mut Vec<T>, counted: u64, x: T) -> Result<(), String> {
    if list.len() as u64 >= counted {
        return Err(CHANGED.into());
    }
    list.push(x);
    Ok(())
}

/// The 0-based index of the 1-based or negative (relative) OBJ index `x` into a list of
/// `len` items so far.
fn resolve(x: i64, len: usize, what: &str, items: &str) -> Result<u32, String> {
    let len = len as i64;
    let i = if x < 0 { len + x } else { x - 1 };
    if x == 0 {
        return Err(format!(
            "{what} 0 out of range ({len} {items}; OBJ indices start at 1)"
        ));
    }
    if !(0..len).contains(&i) {
        return Err(format!("{what} {x} out of range ({len} {items})"));
    }
    Ok(i as u32)
}

#[cfg(test)]
mod tests {
    //! Equivalence with the tobj-based loader this one replaces.

    use pathfarm_testkit::TestRng;
    use std::path::{Path, PathBuf};

    use glam::{Vec2, Vec3};

    use super::*;
    use crate::Limits;

    /// The loader pathfarm had before, verbatim but for the error type: the oracle.
    fn load_with_tobj(path: &Path, flip_tex_coords: bool) -> Result<TriangleMesh, String> {
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
                return Err("normal count does not match vertex count".into());
            }
            if all_uvs && m.texcoords.len() != 2 * nv {
                return Err("texture coordinate count does not match vertex count".into());
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
                    return Err("face index out of range".into());
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

    fn load_new(path: &Path, flip: bool, limits: Limits) -> Result<TriangleMesh, SceneError> {
        crate::shapes::mesh::load_alone(load_obj, path, flip, limits)
    }

    fn bits3(v: Vec3) -> [u32; 3] {
        v.to_array().map(f32::to_bits)
    }

    fn bits2(v: Vec2) -> [u32; 2] {
        v.to_array().map(f32::to_bits)
    }

    /// A corner's position, normal and uv, bit for bit.
    type Corner = ([u32; 3], Option<[u32; 3]>, Option<[u32; 2]>);

    /// The triangles' corner attributes, in order.
    fn corners(m: &TriangleMesh) -> Vec<Corner> {
        m.indices
            .iter()
            .flatten()
            .map(|&i| {
                let i = i as usize;
                (
                    bits3(m.positions[i]),
                    m.normals.as_ref().map(|n| bits3(n[i])),
                    m.uvs.as_ref().map(|u| bits2(u[i])),
                )
            })
            .collect()
    }

    /// Both loaders agree on `path`: the same triangles with the same corner attributes, and
    /// the same vertices (sharing matters: smooth normals are computed per vertex).
    fn assert_same(path: &Path) {
        for flip in [true, false] {
            let old = load_with_tobj(path, flip)
                .unwrap_or_else(|e| panic!("tobj fails on {}: {e}", path.display()));
            let new = load_new(path, flip, Limits::default())
                .unwrap_or_else(|e| panic!("new loader fails on {}: {e}", path.display()));
            assert!(!old.indices.is_empty(), "{}", path.display());
            assert_eq!(
                corners(&new),
                corners(&old),
                "corner attributes differ for {}",
                path.display()
            );
            assert_eq!(new.indices, old.indices, "{}", path.display());
            assert_eq!(
                new.positions.iter().copied().map(bits3).collect::<Vec<_>>(),
                old.positions.iter().copied().map(bits3).collect::<Vec<_>>()
            );
            assert_eq!(new.normals.is_some(), old.normals.is_some());
            assert_eq!(new.uvs.is_some(), old.uvs.is_some());
        }
    }

    fn obj_files(dir: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                obj_files(&p, out);
            } else if p.extension().is_some_and(|x| x == "obj") {
                out.push(p);
            }
        }
    }

    #[test]
    fn same_meshes_as_tobj_for_the_example_scenes() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let mut files = vec![root.join("scenes/door-ajar/icosphere.obj")];
        for d in ["veach-ajar", "cornell-box"] {
            let dir = root.join("../shared/scenes").join(d);
            if dir.is_dir() {
                obj_files(&dir, &mut files);
            }
        }
        assert!(files.len() >= 2, "{files:?}");
        for f in &files {
            assert_same(f);
        }
    }

    fn number_text(r: &mut TestRng) -> String {
        let x = (r.below(2_000_001) as f64 - 1_000_000.0) / 1e3 / (1 + r.below(7)) as f64;
        match r.below(7) {
            0 => format!("{x:e}"),
            1 => format!("{:.9}", x),
            2 => format!("{}", x as f32),
            3 => format!("{:.2}", x),
            4 => "-0".into(),
            5 => format!("{}.", r.below(10)),
            _ => format!("{x}"),
        }
    }

    /// A random OBJ file both loaders accept.
    fn random_obj(r: &mut TestRng) -> String {
        let mut s = String::new();
        let nl = if r.chance(0.2) { "\r\n" } else { "\n" };
        let sep = |r: &mut TestRng| {
            if r.chance(0.1) {
                "\t"
            } else if r.chance(0.1) {
                "  "
            } else {
                " "
            }
        };
        let with_t = r.chance(0.6);
        let with_n = r.chance(0.6);
        // Corner forms: 0 `i`, 1 `i/t`, 2 `i//n`, 3 `i/t/n`.
        let form = match (with_t, with_n) {
            (false, false) => 0,
            (true, false) => 1,
            (false, true) => 2,
            (true, true) => 3,
        };
        // tobj refuses files where only some vertices have colours.
        let colours = r.chance(0.15);
        let (mut nv, mut nt, mut nn) = (0u64, 0u64, 0u64);
        s += &format!("# random test file{nl}mtllib x.mtl{nl}");
        for _ in 0..1 + r.below(4) {
            match r.below(3) {
                0 => s += &format!("o obj{}{nl}", r.below(100)),
                1 => s += &format!("g group {}{nl}", r.below(100)),
                _ => {}
            }
            if r.chance(0.3) {
                s += &format!("usemtl m{}{nl}s {}{nl}", r.below(3), r.below(2));
            }
            for _ in 0..3 + r.below(12) {
                let mut line = format!("v{}", sep(r));
                for _ in 0..3 {
                    line += &format!("{}{}", number_text(r), sep(r));
                }
                if colours {
                    line += "0.1 0.2 0.3";
                } else if r.chance(0.1) {
                    line += &format!("{}", 0.5 + r.below(4) as f32);
                }
                s += &line;
                s += nl;
                nv += 1;
                if with_t {
                    s += &format!("vt {} {}{nl}", number_text(r), number_text(r));
                    nt += 1;
                }
                if with_n {
                    s += &format!(
                        "vn {} {} {}{nl}",
                        number_text(r),
                        number_text(r),
                        number_text(r)
                    );
                    nn += 1;
                }
            }
            if r.chance(0.3) {
                s += nl;
                s += &format!("# a comment{nl}l 1 2{nl}p 1{nl}");
            }
            for _ in 0..1 + r.below(10) {
                let k = match r.below(10) {
                    0 => 1 + r.below(2),
                    1..=4 => 3,
                    5..=7 => 4,
                    _ => 5 + r.below(6),
                };
                let mut line = "f".to_string();
                for _ in 0..k {
                    // Reuse a few indices so corners repeat across faces.
                    let pick = |r: &mut TestRng, n: u64| -> String {
                        let i = if r.chance(0.5) {
                            r.below(n.min(4))
                        } else {
                            r.below(n)
                        };
                        if r.chance(0.25) {
                            format!("-{}", n - i)
                        } else {
                            format!("{}", i + 1)
                        }
                    };
                    let v = pick(r, nv);
                    let c = match form {
                        0 => v,
                        1 => format!("{v}/{}", pick(r, nt)),
                        2 => format!("{v}//{}", pick(r, nn)),
                        _ => format!("{v}/{}/{}", pick(r, nt), pick(r, nn)),
                    };
                    line += sep(r);
                    line += &c;
                }
                s += &line;
                s += nl;
            }
        }
        if r.chance(0.5) {
            s += "# no final newline";
        }
        s
    }

    #[test]
    fn same_meshes_as_tobj_for_random_files() {
        let dir = std::env::temp_dir().join(format!("pathfarm-obj-oracle-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut r = TestRng::new(0x9E37_79B9_7F4A_7C15);
        let (mut meshes, mut with_uvs, mut with_normals, mut shared) = (0, 0, 0, 0);
        for i in 0..400 {
            let text = random_obj(&mut r);
            let p = dir.join(format!("r{i}.obj"));
            std::fs::write(&p, &text).unwrap();
            match load_with_tobj(&p, true) {
                Ok(m) if !m.indices.is_empty() => {
                    assert_same(&p);
                    meshes += 1;
                    with_uvs += m.uvs.is_some() as u32;
                    with_normals += m.normals.is_some() as u32;
                    shared += (m.positions.len() < 3 * m.indices.len()) as u32;
                }
                // Only points and lines: no triangles either way.
                Ok(_) => assert!(load_new(&p, true, Limits::default())
                    .unwrap()
                    .indices
                    .is_empty()),
                Err(e) => panic!("generated file tobj refuses ({e}):\n{text}"),
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(
            meshes > 300 && with_uvs > 50 && with_normals > 50 && shared > 100,
            "{meshes} {with_uvs} {with_normals} {shared}"
        );
    }

    #[test]
    fn mixed_texture_coordinates_are_refused_or_dropped_like_tobj() {
        let dir = std::env::temp_dir().join(format!("pathfarm-obj-mixed-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let head = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n";
        // One object, some corners without uv: tobj's counts mismatch, an error.
        let p = dir.join("a.obj");
        std::fs::write(&p, format!("{head}f 1/1 2/2 3/3\nf 1 2 3\n")).unwrap();
        assert!(load_with_tobj(&p, true).is_err());
        let e = load_new(&p, true, Limits::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("line 8: face corner \"1\" has no texture coordinate"),
            "{e}"
        );
        // Two objects, one entirely without uvs: no uvs at all.
        let p = dir.join("b.obj");
        std::fs::write(&p, format!("{head}o a\nf 1/1 2/2 3/3\no b\nf 1 2 3\n")).unwrap();
        assert_same(&p);
        assert!(load_new(&p, true, Limits::default()).unwrap().uvs.is_none());
        // `vt` indices without `vt` lines are ignored, but still distinguish vertices.
        let p = dir.join("c.obj");
        std::fs::write(
            &p,
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/1 2/1 3/1\nf 1/2 2/1 3/1\n",
        )
        .unwrap();
        assert_same(&p);
        assert_eq!(
            load_new(&p, true, Limits::default())
                .unwrap()
                .positions
                .len(),
            4
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
