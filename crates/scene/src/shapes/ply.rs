//! Stanford PLY loading, ASCII or binary.
//!
//! The header is read and checked here, before anything is allocated: every element's
//! announced count against the [`crate::Limits`] and against what the rest of the file can
//! hold, then the mesh's memory is reserved. The elements are then parsed by `ply-rs-bw`, one
//! at a time (so its per-element maps never pile up), from element definitions built from
//! this header; elements after the vertices and faces are not read.

use std::io::{BufRead, BufReader, Read};

use glam::{Vec2, Vec3};
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{
    Addable, DefaultElement, ElementDef, Property, PropertyDef, PropertyType, ScalarType,
};

use super::mesh::{
    check_limit, shown, vertex_bytes, Budget, LineReader, MeshInput, TRIANGLE_BYTES,
};
use crate::desc::TriangleMesh;
use crate::error::SceneError;
use crate::limits::format_bytes;
use crate::Limits;

/// The longest header line read.
const HEADER_LINE_CAP: usize = 64 << 10;
/// The largest header read.
const HEADER_CAP: u64 = 16 << 20;

/// The longest ASCII element line read: a face of `max_polygon_vertices` indices of up to 32
/// characters.
fn ascii_line_cap(max_polygon_vertices: u64) -> usize {
    max_polygon_vertices
        .saturating_add(64)
        .saturating_mul(32)
        .clamp(1 << 20, 1 << 30) as usize
}

#[derive(Clone, Copy, PartialEq, Debug)]
enum Format {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

/// An `element` of the header, with its `property` lines.
struct Element {
    def: ElementDef,
    count: u64,
    /// The header line of its `element` statement.
    line: u64,
}

impl Element {
    fn has(&self, name: &str) -> bool {
        self.def.properties.contains_key(name)
    }

    /// The fewest bytes one element takes in the file.
    fn min_bytes(&self, format: Format) -> u64 {
        if format == Format::Ascii {
            // At least one number and a line break each ("0\n"); an element without properties
            // is at least a line break.
            return if self.def.properties.is_empty() { 1 } else { 2 };
        }
        self.def
            .properties
            .values()
            .map(|p| match &p.data_type {
                PropertyType::Scalar(t) | PropertyType::List(t, _) => scalar_bytes(t),
            })
            .sum()
    }

    fn has_lists(&self) -> bool {
        self.def
            .properties
            .values()
            .any(|p| matches!(p.data_type, PropertyType::List(..)))
    }
}

fn scalar_bytes(t: &ScalarType) -> u64 {
    match t {
        ScalarType::Char | ScalarType::UChar => 1,
        ScalarType::Short | ScalarType::UShort => 2,
        ScalarType::Int | ScalarType::UInt | ScalarType::Float => 4,
        ScalarType::Double => 8,
    }
}

fn scalar_type(name: &str) -> Option<ScalarType> {
    Some(match name {
        "char" | "int8" => ScalarType::Char,
        "uchar" | "uint8" => ScalarType::UChar,
        "short" | "int16" => ScalarType::Short,
        "ushort" | "uint16" => ScalarType::UShort,
        "int" | "int32" => ScalarType::Int,
        "uint" | "uint32" => ScalarType::UInt,
        "float" | "float32" => ScalarType::Float,
        "double" | "float64" => ScalarType::Double,
        _ => return None,
    })
}

/// Read the header, up to and including its `end_header` line.
fn read_header<R: BufRead>(lines: &mut LineReader<R>) -> Result<(Format, Vec<Element>), String> {
    let eof = || "the PLY header ends before its 'end_header' line".to_string();
    let (_, first) = lines.next_text()?.ok_or_else(eof)?;
    if first.trim_end() != "ply" {
        return Err("not a PLY file (it does not start with a 'ply' line)".into());
    }
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        if lines.consumed > HEADER_CAP {
            return Err(format!(
                "the PLY header is longer than {}",
                format_bytes(HEADER_CAP)
            ));
        }
        let (line, text) = lines.next_text()?.ok_or_else(eof)?;
        let bad = || {
            format!(
                "PLY header line {line}: cannot parse \"{}\"",
                shown(text.trim())
            )
        };
        let words: Vec<&str> = text.split_ascii_whitespace().collect();
        match words.as_slice() {
            [] => {}
            ["comment", ..] | ["obj_info", ..] => {}
            ["end_header"] => break,
            ["format", f, version] => {
                let f = match *f {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::BinaryLittleEndian,
                    "binary_big_endian" => Format::BinaryBigEndian,
                    _ => return Err(bad()),
                };
                let ok_version = version
                    .split_once('.')
                    .is_some_and(|(a, b)| a.parse::<u16>().is_ok() && b.parse::<u8>().is_ok());
                if !ok_version || format.is_some_and(|g| g != f) {
                    return Err(bad());
                }
                format = Some(f);
            }
            ["element", name, count] => {
                if !count.bytes().all(|b| b.is_ascii_digit()) {
                    return Err(bad());
                }
                let count = count.parse::<u64>().map_err(|_| bad())?;
                if elements.iter().any(|e| e.def.name == *name) {
                    return Err(format!(
                        "PLY header line {line}: a second element '{}'",
                        shown(name)
                    ));
                }
                let mut def = ElementDef::new(name.to_string());
                def.count = usize::try_from(count).map_err(|_| bad())?;
                elements.push(Element { def, count, line });
            }
            ["property", rest @ ..] => {
                let (data_type, name) = match rest {
                    [t, name] => (PropertyType::Scalar(scalar_type(t).ok_or_else(bad)?), name),
                    ["list", count_type, t, name] => {
                        let c = scalar_type(count_type).ok_or_else(bad)?;
                        if matches!(c, ScalarType::Float | ScalarType::Double) {
                            return Err(bad());
                        }
                        (PropertyType::List(c, scalar_type(t).ok_or_else(bad)?), name)
                    }
                    _ => return Err(bad()),
                };
                let Some(e) = elements.last_mut() else {
                    return Err(format!(
                        "PLY header line {line}: a property before any element"
                    ));
                };
                if e.def.properties.contains_key(*name) {
                    return Err(format!(
                        "PLY header line {line}: element '{}' has a second property '{}'",
                        shown(&e.def.name),
                        shown(name)
                    ));
                }
                e.def
                    .properties
                    .add(PropertyDef::new(name.to_string(), data_type));
            }
            _ => return Err(bad()),
        }
    }
    let format = format.ok_or("the PLY header has no 'format' line")?;
    Ok((format, elements))
}

/// Check the elements' counts against what the file (`file_bytes` long, `header_bytes` of
/// which are the header) can hold.
fn check_sizes(
    format: Format,
    elements: &[Element],
    file_bytes: u64,
    header_bytes: u64,
) -> Result<(), String> {
    // An ASCII file's last line may lack its line break.
    let slack = u64::from(format == Format::Ascii);
    let mut left = file_bytes.saturating_sub(header_bytes) + slack;
    for (i, e) in elements.iter().enumerate() {
        let min = e.min_bytes(format);
        let need = e.count.saturating_mul(min);
        if need > left {
            let before = if i == 0 {
                ""
            } else {
                " and the elements before it"
            };
            return Err(format!(
                "PLY header line {}: element '{}' announces {} elements of at least {min} \
                 bytes each, {} in all, but the file is only {file_bytes} bytes long, with {} \
                 bytes left after the header{before}",
                e.line,
                shown(&e.def.name),
                e.count,
                format_bytes(need),
                left - slack.min(left)
            ));
        }
        left -= need;
    }
    Ok(())
}

fn scalar(e: &DefaultElement, name: &str) -> Option<f32> {
    e.get(name).and_then(Property::to_f32_lossy)
}

/// Reads the elements after the header, one at a time.
struct Elements<'r, R> {
    lines: LineReader<&'r mut R>,
    format: Format,
    parser: Parser<DefaultElement>,
}

impl<R: BufRead> Elements<'_, R> {
    fn next(&mut self, e: &Element, i: u64) -> Result<DefaultElement, String> {
        let name = shown(&e.def.name);
        match self.format {
            Format::Ascii => {
                let Some((line, text)) = self.lines.next_text()? else {
                    return Err(format!(
                        "the file ends at {name} {i}, but its header announces {} elements '{name}'",
                        e.count
                    ));
                };
                self.parser
                    .read_ascii_element(text, &e.def)
                    .map_err(|err| format!("line {line} ({name} {i}): cannot parse: {err}"))
            }
            Format::BinaryLittleEndian | Format::BinaryBigEndian => {
                let r = self.lines.get_mut();
                let got = if self.format == Format::BinaryLittleEndian {
                    self.parser.read_little_endian_element(r, &e.def)
                } else {
                    self.parser.read_big_endian_element(r, &e.def)
                };
                got.map_err(|err| {
                    if err.kind() == std::io::ErrorKind::UnexpectedEof {
                        format!(
                            "the file ends in {name} {i}, but its header announces {} elements \
                             '{name}'",
                            e.count
                        )
                    } else {
                        format!("{name} {i}: cannot parse: {err}")
                    }
                })
            }
        }
    }

    /// Read past the element `e`.
    fn skip(&mut self, e: &Element) -> Result<(), String> {
        if self.format != Format::Ascii && !e.has_lists() {
            // Fixed-size binary elements: skip their bytes.
            let bytes = e.count.saturating_mul(e.min_bytes(self.format));
            let r = self.lines.get_mut();
            let skipped = std::io::copy(&mut r.take(bytes), &mut std::io::sink())
                .map_err(|err| format!("read error: {err}"))?;
            if skipped < bytes {
                return Err(format!(
                    "the file ends in the elements '{}' its header announces",
                    shown(&e.def.name)
                ));
            }
            return Ok(());
        }
        for i in 0..e.count {
            self.next(e, i)?;
        }
        Ok(())
    }
}

/// The vertex property pairs that hold texture coordinates, the first pair present winning
/// (Mitsuba's names).
const UV_PROPERTIES: [(&str, &str); 4] = [
    ("u", "v"),
    ("s", "t"),
    ("texture_u", "texture_v"),
    ("texture_s", "texture_t"),
];

/// Which attributes a file's vertices carry besides their position.
#[derive(Clone, Copy)]
struct VertexLayout {
    /// `nx ny nz` are all present.
    normals: bool,
    /// The first of [`UV_PROPERTIES`] present.
    uv: Option<(&'static str, &'static str)>,
    /// Store `1 - v` (the shape's `flip_tex_coords`).
    flip_tex_coords: bool,
}

impl VertexLayout {
    /// The layout of vertices that have exactly the properties `has` answers yes for.
    fn new(has: impl Fn(&str) -> bool, flip_tex_coords: bool) -> Self {
        VertexLayout {
            normals: has("nx") && has("ny") && has("nz"),
            uv: UV_PROPERTIES.into_iter().find(|(u, v)| has(u) && has(v)),
            flip_tex_coords,
        }
    }

    /// A mesh with room for `n` vertices and `triangles` triangles, with normal and uv arrays
    /// where the layout has them.
    fn mesh_with_capacity(&self, n: usize, triangles: usize) -> TriangleMesh {
        TriangleMesh {
            positions: Vec::with_capacity(n),
            indices: Vec::with_capacity(triangles),
            normals: self.normals.then(|| Vec::with_capacity(n)),
            uvs: self.uv.map(|_| Vec::with_capacity(n)),
            flip_normals: false,
        }
    }

    /// Appends vertex `e` to `mesh`; the error is the name of a property that is missing or
    /// not a scalar.
    fn push(&self, e: &DefaultElement, mesh: &mut TriangleMesh) -> Result<(), &'static str> {
        let get = |n: &'static str| scalar(e, n).ok_or(n);
        mesh.positions
            .push(Vec3::new(get("x")?, get("y")?, get("z")?));
        if let Some(normals) = &mut mesh.normals {
            normals.push(Vec3::new(get("nx")?, get("ny")?, get("nz")?));
        }
        if let (Some(uvs), Some((un, vn))) = (&mut mesh.uvs, self.uv) {
            let v = get(vn)?;
            uvs.push(Vec2::new(
                get(un)?,
                if self.flip_tex_coords { 1.0 - v } else { v },
            ));
        }
        Ok(())
    }
}

/// Read the `vertex` (x y z, optional nx ny nz, optional u v / s t /
/// texture_u texture_v / texture_s texture_t) and `face` (`vertex_indices`
/// or `vertex_index` lists, fan-triangulated) elements. Mitsuba does not flip
/// PLY texture coordinates by default (`flip_tex_coords` false).
pub(crate) fn load_ply(input: &MeshInput, budget: &mut Budget) -> Result<TriangleMesh, SceneError> {
    let limits = budget.limits().clone();
    let (file, file_bytes) = input.open()?;
    let mut reader = BufReader::new(file);
    let mut lines = LineReader::new(&mut reader, HEADER_LINE_CAP);
    let (format, elements) = read_header(&mut lines).map_err(|m| input.err(m))?;
    let header_bytes = lines.consumed;

    let vertices = elements
        .iter()
        .find(|e| e.def.name == "vertex")
        .ok_or_else(|| input.err("PLY file has no 'vertex' element"))?;
    let faces = elements
        .iter()
        .find(|e| e.def.name == "face")
        .ok_or_else(|| input.err("PLY file has no 'face' element"))?;
    let announces = |e: &Element, what: &str, limit: u64, field: &str| {
        check_limit(e.count, what, limit, field).map_err(|m| {
            input.err(format!(
                "PLY header line {}: element '{}' announces {m}",
                e.line, e.def.name
            ))
        })
    };
    announces(
        vertices,
        "vertices",
        limits.max_mesh_vertices.min(u32::MAX as u64),
        "max_mesh_vertices",
    )?;
    announces(
        faces,
        "faces (each at least one triangle)",
        limits.max_mesh_triangles,
        "max_mesh_triangles",
    )?;
    check_sizes(format, &elements, file_bytes, header_bytes).map_err(|m| input.err(m))?;

    let nv = vertices.count;
    let layout = VertexLayout::new(|n| nv > 0 && vertices.has(n), input.flip_tex_coords);

    // Reserve for the vertices and one triangle per face; polygons reserve more as they come.
    let what = format!("{} ({} vertices, {} faces)", input.source, nv, faces.count);
    budget.reserve(
        nv.saturating_mul(vertex_bytes(layout.uv.is_some()))
            .saturating_add(faces.count.saturating_mul(TRIANGLE_BYTES)),
        &what,
    )?;
    let mut reserved_triangles = faces.count;

    let mut mesh = layout.mesh_with_capacity(nv as usize, faces.count as usize);

    lines.set_cap(ascii_line_cap(limits.max_polygon_vertices));
    let mut reading = Elements {
        lines,
        format,
        parser: Parser::<DefaultElement>::new(),
    };
    let (mut vertices_read, mut faces_read) = (false, false);
    let err = |m: String| input.err(m);
    for element in &elements {
        if vertices_read && faces_read {
            break; // nothing more is needed
        }
        if element.def.name == "vertex" {
            for i in 0..element.count {
                let e = reading.next(element, i).map_err(err)?;
                layout.push(&e, &mut mesh).map_err(|n| {
                    err(format!("vertex {i}: missing or non-scalar property '{n}'"))
                })?;
            }
            vertices_read = true;
        } else if element.def.name == "face" {
            for f in 0..element.count {
                let e = reading.next(element, f).map_err(err)?;
                let idx = face_indices(&e, f, nv, &limits).map_err(err)?;
                let triangles = mesh.indices.len() as u64 + idx.len() as u64 - 2;
                if triangles > limits.max_mesh_triangles {
                    return Err(err(format!(
                        "face {f}: the faces so far make {triangles} triangles, more than the \
                         limit of {} (Limits::max_mesh_triangles)",
                        limits.max_mesh_triangles
                    )));
                }
                if triangles > reserved_triangles {
                    let more = (reserved_triangles / 2)
                        .max(1 << 16)
                        .max(triangles - reserved_triangles);
                    budget.reserve(more.saturating_mul(TRIANGLE_BYTES), &what)?;
                    reserved_triangles += more;
                    mesh.indices.reserve_exact(more as usize);
                }
                super::mesh::triangulate(&idx, &mut mesh.indices);
            }
            faces_read = true;
        } else {
            reading.skip(element).map_err(err)?;
        }
    }
    Ok(mesh)
}

/// Face `f`'s vertex indices: an integer list of at least 3 and at most
/// `max_polygon_vertices` indices, each below `nv`.
fn face_indices(e: &DefaultElement, f: u64, nv: u64, limits: &Limits) -> Result<Vec<u32>, String> {
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
    check_limit(
        idx.len() as u64,
        "vertices",
        limits.max_polygon_vertices,
        "max_polygon_vertices",
    )
    .map_err(|m| format!("face {f} has {m}"))?;
    if let Some(bad) = idx.iter().find(|&&i| i < 0 || i as u64 >= nv) {
        return Err(format!(
            "face {f}: vertex index {bad} out of range ({nv} vertices)"
        ));
    }
    Ok(idx.into_iter().map(|i| i as u32).collect())
}

#[cfg(test)]
mod tests {
    //! Equivalence with the loader this one replaces (the whole file through
    //! `Parser::read_ply`), and the header checks.

    use std::path::{Path, PathBuf};

    use super::*;
    use crate::Limits;

    /// The loader pathfarm had before: the oracle.
    fn load_old(path: &Path, flip_tex_coords: bool) -> Result<TriangleMesh, String> {
        let file = std::fs::File::open(path).map_err(|e| format!("cannot read: {e}"))?;
        let mut reader = std::io::BufReader::new(file);
        let parser = Parser::<DefaultElement>::new();
        let ply = parser
            .read_ply(&mut reader)
            .map_err(|e| format!("cannot parse PLY: {e}"))?;
        let vertices = ply.payload.get("vertex").ok_or("no vertex")?;
        let faces = ply.payload.get("face").ok_or("no face")?;
        let first = vertices.first();
        let layout = VertexLayout::new(
            |n| first.is_some_and(|e| e.contains_key(n)),
            flip_tex_coords,
        );
        let mut mesh = layout.mesh_with_capacity(0, 0);
        for e in vertices {
            layout.push(e, &mut mesh)?;
        }
        for e in faces {
            let list = e
                .get("vertex_indices")
                .or_else(|| e.get("vertex_index"))
                .ok_or("no list")?;
            let idx: Vec<i64> = match list {
                Property::ListUChar(v) => v.iter().map(|&x| x as i64).collect(),
                Property::ListInt(v) => v.iter().map(|&x| x as i64).collect(),
                Property::ListUInt(v) => v.iter().map(|&x| x as i64).collect(),
                _ => return Err("list type".into()),
            };
            for k in 1..idx.len() - 1 {
                mesh.indices
                    .push([idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
            }
        }
        Ok(mesh)
    }

    fn load_new(path: &Path, flip: bool, limits: Limits) -> Result<TriangleMesh, SceneError> {
        crate::shapes::mesh::load_alone(load_ply, path, flip, limits)
    }

    /// A PLY file: a `material` element before the vertices, the vertices (x y z, optionally
    /// normals and `s t`), a `face` element of triangles and quads, and an `edge` element.
    fn ply_file(format: &str, normals: bool, uvs: bool) -> Vec<u8> {
        let n = 6;
        let mut header = format!(
            "ply\r\nformat {format} 1.0\ncomment made by a test\nelement material 2\n\
             property uchar red\nproperty list uchar float weights\n\
             element vertex {n}\nproperty float x\nproperty double y\nproperty float z\n"
        );
        if normals {
            header += "property float nx\nproperty float ny\nproperty float nz\n";
        }
        if uvs {
            header += "property float s\nproperty float t\n";
        }
        header += "element face 3\nproperty list uchar int vertex_indices\n\
                   element edge 1\nproperty int vertex1\nproperty int vertex2\nend_header\n";
        let mut out = header.into_bytes();
        let ascii = format == "ascii";
        let be = format == "binary_big_endian";
        let put = |out: &mut Vec<u8>, bytes_le: &[u8], text: String| {
            if ascii {
                out.extend_from_slice(text.as_bytes());
                out.push(b' ');
            } else if be {
                out.extend(bytes_le.iter().rev());
            } else {
                out.extend_from_slice(bytes_le);
            }
        };
        let end = |out: &mut Vec<u8>| {
            if ascii {
                out.push(b'\n');
            }
        };
        for m in 0..2u8 {
            put(&mut out, &[m], m.to_string());
            put(&mut out, &[2], "2".into());
            for w in [0.25f32, 0.75] {
                put(&mut out, &w.to_le_bytes(), w.to_string());
            }
            end(&mut out);
        }
        for i in 0..n {
            let f = |k: f32| 0.1 * i as f32 + k;
            put(&mut out, &f(0.0).to_le_bytes(), f(0.0).to_string());
            let y = f(1.0) as f64 / 3.0;
            put(&mut out, &y.to_le_bytes(), y.to_string());
            put(&mut out, &f(2.0).to_le_bytes(), f(2.0).to_string());
            if normals {
                for k in [0.0f32, 0.6, 0.8] {
                    put(&mut out, &k.to_le_bytes(), k.to_string());
                }
            }
            if uvs {
                put(&mut out, &f(0.3).to_le_bytes(), f(0.3).to_string());
                put(&mut out, &f(0.7).to_le_bytes(), f(0.7).to_string());
            }
            end(&mut out);
        }
        for face in [&[0i32, 1, 2][..], &[2, 3, 4, 5], &[5, 0, 3]] {
            put(&mut out, &[face.len() as u8], face.len().to_string());
            for &i in face {
                put(&mut out, &i.to_le_bytes(), i.to_string());
            }
            end(&mut out);
        }
        for i in [0i32, 1] {
            put(&mut out, &i.to_le_bytes(), i.to_string());
        }
        end(&mut out);
        out
    }

    /// A temporary file name (the tests remove their files).
    fn temp(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("pathfarm-ply-unit-{}-{name}", std::process::id()))
    }

    #[test]
    fn same_meshes_as_the_whole_file_loader() {
        for format in ["ascii", "binary_little_endian", "binary_big_endian"] {
            for (normals, uvs) in [(false, false), (true, false), (false, true), (true, true)] {
                let p = temp(&format!("{format}-{normals}-{uvs}.ply"));
                std::fs::write(&p, ply_file(format, normals, uvs)).unwrap();
                for flip in [false, true] {
                    let old = load_old(&p, flip).unwrap();
                    let new = load_new(&p, flip, Limits::default()).unwrap();
                    assert_eq!(new, old, "{format} normals {normals} uvs {uvs}");
                    assert_eq!(new.indices.len(), 4);
                    assert_eq!(new.normals.is_some(), normals);
                    assert_eq!(new.uvs.is_some(), uvs);
                }
                std::fs::remove_file(&p).unwrap();
            }
        }
    }

    #[test]
    fn counts_the_file_cannot_hold_are_refused_before_reading() {
        let p = temp("short.ply");
        let bytes = ply_file("binary_little_endian", false, false);
        let end = b"end_header\n";
        let header_end = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
        let header = std::str::from_utf8(&bytes[..header_end]).unwrap();
        let mut out = header
            .replace("element face 3", "element face 300")
            .into_bytes();
        out.extend_from_slice(&bytes[header_end..]);
        std::fs::write(&p, &out).unwrap();
        let e = load_new(&p, false, Limits::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("element 'face' announces 300 elements of at least 1 bytes"),
            "{e}"
        );
        assert!(e.contains("and the elements before it"), "{e}");
        std::fs::remove_file(&p).unwrap();
    }
}
