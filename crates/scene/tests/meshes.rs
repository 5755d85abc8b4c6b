//! Mesh files as untrusted input: big polygons in linear time, errors that name the mesh
//! file's line, counts checked against the limits before anything is allocated, and
//! world-space bounds.

mod common;

use std::fmt::Write as _;

use common::*;
use pathfarm_scene::{load_scene, load_scene_with_limits, Geometry, Limits, SceneDesc, SceneError};

fn triangles(s: &SceneDesc) -> usize {
    match &s.shapes[0].geometry {
        Geometry::Mesh(m) => m.indices.len(),
        g => panic!("not a mesh: {g:?}"),
    }
}

/// An OBJ file of `n` vertices on a circle and one face through all of them.
fn polygon_obj(n: usize, negative: bool) -> String {
    let mut s = String::with_capacity(n * 40);
    for i in 0..n {
        let a = i as f64 / n as f64 * std::f64::consts::TAU;
        writeln!(s, "v {} {} 0", a.cos(), a.sin()).unwrap();
    }
    s.push('f');
    for i in 0..n {
        if negative {
            write!(s, " -{}", n - i).unwrap();
        } else {
            write!(s, " {}", i + 1).unwrap();
        }
    }
    s.push('\n');
    s
}

/// The scene of one [`polygon_obj`]`(n, negative)`, loaded from a fresh directory `name`
/// (removed again).
fn load_polygon(name: &str, n: usize, negative: bool) -> SceneDesc {
    let obj = polygon_obj(n, negative);
    let (p, _, _) = mesh_scene(name, "obj", "poly.obj", obj.as_bytes());

    load_scene(&p, &[]).unwrap()
}

#[test]
fn obj_polygon_of_30000_vertices_loads_as_29998_triangles() {
    let s = load_polygon("poly30k", 30_000, false);
    assert_eq!(triangles(&s), 29_998);
}

#[test]
fn obj_polygon_of_600000_indices_loads() {
    // Relative indices, for good measure.
    let s = load_polygon("poly600k", 600_000, true);
    assert_eq!(triangles(&s), 599_998);
    match &s.shapes[0].geometry {
        Geometry::Mesh(m) => {
            assert_eq!(m.positions.len(), 600_000);
            // Split at the middle corner first (not a fan: see `mesh::triangulate`), every
            // triangle in polygon order (the winding is kept).
            assert_eq!(m.indices[0], [0, 299_999, 599_999]);
            assert!(m.indices.iter().all(|t| t[0] < t[1] && t[1] < t[2]));
        }
        _ => unreachable!(),
    }
}

/// The error loading `contents` as an OBJ: at the filename's scene line, naming the file and
/// containing `needle`.
fn obj_error(name: &str, contents: &[u8], needle: &str) -> String {
    let (p, xml, mesh) = mesh_scene(name, "obj", "x.obj", contents);
    let prefix = format!("mesh file '{}': ", mesh.display());
    let err = assert_load_fails_at(&p, &xml, "x.obj", &[&prefix, needle]);
    err.to_string()
}

#[test]
fn obj_errors_name_the_obj_line() {
    let ten = "v 0 0 0\n".repeat(10);
    obj_error(
        "obj-range",
        format!("{ten}# a comment\nf 1 2 40\n").as_bytes(),
        "line 12: face index 40 out of range (10 vertices)",
    );
    obj_error(
        "obj-float",
        b"v 0 0 0\nv 1 0 0\nv 1.0e 1 0\nf 1 2 3\n",
        "line 3: could not parse vertex coordinate \"1.0e\"",
    );
    obj_error(
        "obj-negative",
        format!("{ten}f -1 -2 -11\n").as_bytes(),
        "line 11: face index -11 out of range (10 vertices)",
    );
    obj_error(
        "obj-zero",
        format!("{ten}f 0 1 2\n").as_bytes(),
        "line 11: face index 0 out of range (10 vertices; OBJ indices start at 1)",
    );
    obj_error(
        "obj-forward",
        b"v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n",
        "line 3: face index 3 out of range (2 vertices)",
    );
    obj_error(
        "obj-uv-range",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\n\nf 1/1 2/1 3/2\n",
        "line 6: texture coordinate index 2 out of range (1 texture coordinates)",
    );
    obj_error(
        "obj-normal-range",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//9\n",
        "line 5: normal index 9 out of range (1 normals)",
    );
    obj_error(
        "obj-corner",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3/x\n",
        "line 4: could not parse face corner \"3/x\"",
    );
    obj_error(
        "obj-corner4",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3/1/1/1\n",
        "line 4: face corner \"3/1/1/1\" has more than three indices",
    );
    obj_error(
        "obj-w",
        b"v 0 0 0\nv 1 0 0 0\nv 0 1 0\nf 1 2 3\n",
        "line 2: vertex w coordinate is 0",
    );
    obj_error(
        "obj-short-v",
        b"v 0 0 0\nv 1 0\n",
        "line 2: vertex has 2 coordinates, expected 3 (x y z)",
    );
    obj_error(
        "obj-vt",
        b"v 0 0 0\nvt 0.5 zero\n",
        "line 2: could not parse texture coordinate \"zero\"",
    );
    obj_error(
        "obj-mixed-normals",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\nf 3 2 1\n",
        "line 6: face corner \"3\" has no normal index, but other faces have normals",
    );
}

#[test]
fn obj_names_and_comments_may_be_in_any_code_page() {
    // A 3ds Max export: Latin-1 in comments, object and material names.
    let obj = b"# Cr\xe9\xe9 par 3ds Max\nmtllib caf\xe9.mtl\no Th\xe9i\xe8re\ng gr\xfcn\n\
                v 0 0 0\nv 1 0 0 # \xb0\nv 0 1 0\nusemtl m\xe9tal\ns 1\nf 1 2 3\n";
    let (p, _, _) = mesh_scene("obj-latin1-names", "obj", "x.obj", obj);
    assert_eq!(triangles(&load_scene(&p, &[]).unwrap()), 1);
}

#[test]
fn obj_files_that_are_not_text_are_refused() {
    obj_error(
        "obj-latin1-data",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 \xe93\n",
        "line 4 is not valid UTF-8 text",
    );
    obj_error(
        "obj-nul",
        b"v 0 0 0\nv 1 0 0\nv 0\x001 0\nf 1 2 3\n",
        "line 3 contains a NUL byte",
    );
    let utf16: Vec<u8> = std::iter::once(0xFEFFu16)
        .chain("v 0 0 0\n".encode_utf16())
        .flat_map(u16::to_le_bytes)
        .collect();
    let e = obj_error("obj-utf16", &utf16, "UTF-16");
    assert!(e.contains("unsupported"), "{e}");
    // A UTF-8 byte-order mark is skipped: the first vertex is not lost.
    let (p, _, _) = mesh_scene(
        "obj-utf8-bom",
        "obj",
        "x.obj",
        b"\xEF\xBB\xBFv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    );
    assert_eq!(triangles(&load_scene(&p, &[]).unwrap()), 1);
}

/// A binary little-endian PLY header announcing `vertices` vertices (x y z floats) and
/// `faces` faces, followed by `payload`.
fn ply_bytes(format: &str, vertices: u64, faces: u64, payload: &[u8]) -> Vec<u8> {
    let mut b = format!(
        "ply\nformat {format} 1.0\nelement vertex {vertices}\nproperty float x\n\
         property float y\nproperty float z\nelement face {faces}\n\
         property list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    b.extend_from_slice(payload);
    b
}

/// One binary little-endian triangle: three vertices and a face.
fn binary_triangle() -> Vec<u8> {
    let mut b = Vec::new();
    for v in [[0f32, 0., 0.], [1., 0., 0.], [0., 1., 0.]] {
        for c in v {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    b.push(3);
    for i in [0i32, 1, 2] {
        b.extend_from_slice(&i.to_le_bytes());
    }
    b
}

#[test]
fn ply_header_announcing_2_pow_31_vertices_in_a_tiny_file_is_refused() {
    let n = 1u64 << 31;
    let bytes = ply_bytes("binary_little_endian", n, 1, &binary_triangle());
    let (p, xml, _) = mesh_scene("ply-huge-bin", "ply", "x.ply", &bytes);
    assert_load_fails_at(
        &p,
        &xml,
        "x.ply",
        &[
            "x.ply",
            "PLY header line 3: element 'vertex' announces 2147483648 elements of at least \
             12 bytes each",
            &format!("the file is only {} bytes long", bytes.len()),
        ],
    );

    let bytes = ply_bytes("ascii", n, 1, b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n");
    let (p, xml, _) = mesh_scene("ply-huge-ascii", "ply", "x.ply", &bytes);
    assert_load_fails_at(
        &p,
        &xml,
        "x.ply",
        &["element 'vertex' announces 2147483648 elements of at least 2 bytes each"],
    );
}

fn limited(limits: Limits, name: &str, kind: &str, contents: &[u8], needles: &[&str]) {
    let file = format!("x.{kind}");
    let (p, xml, _) = mesh_scene(name, kind, &file, contents);
    assert!(
        load_scene(&p, &[]).is_ok(),
        "{name} must load under the default limits"
    );
    let err = load_scene_with_limits(&p, &[], &limits).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, &file), needles);
}

#[test]
fn mesh_counts_above_the_limits_are_refused() {
    let small = |f: fn(&mut Limits)| {
        let mut l = Limits::default();
        f(&mut l);
        l
    };
    let quads = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\nf 1 2 3 4\nf 4 3 2 1\n";
    limited(
        small(|l| l.max_mesh_triangles = 5),
        "lim-obj-tris",
        "obj",
        quads.as_bytes(),
        &["6 triangles, more than the limit of 5 (Limits::max_mesh_triangles)"],
    );
    limited(
        small(|l| l.max_mesh_vertices = 3),
        "lim-obj-verts",
        "obj",
        quads.as_bytes(),
        &["4 vertex positions ('v' lines), more than the limit of 3 (Limits::max_mesh_vertices)"],
    );
    limited(
        small(|l| l.max_mesh_vertices = 5),
        "lim-obj-split-verts",
        "obj",
        b"v 0 0 0\nv 1 0 0\nv 1 1 0\nvt 0 0\nvt 1 1\nf 1/1 2/1 3/1\nf 1/2 2/2 3/2\n",
        &[
            "line 7: the mesh has more than 5 vertices",
            "(Limits::max_mesh_vertices)",
        ],
    );
    limited(
        small(|l| l.max_polygon_vertices = 3),
        "lim-obj-poly",
        "obj",
        quads.as_bytes(),
        &["line 5: face has 4 vertices, more than the limit of 3 (Limits::max_polygon_vertices)"],
    );
    limited(
        small(|l| l.max_memory_bytes = 100),
        "lim-obj-memory",
        "obj",
        quads.as_bytes(),
        &["(6 triangles) needs", "(Limits::max_memory_bytes)"],
    );

    let tri = ply_bytes("binary_little_endian", 3, 1, &binary_triangle());
    limited(
        small(|l| l.max_mesh_vertices = 2),
        "lim-ply-verts",
        "ply",
        &tri,
        &[
            "element 'vertex' announces 3 vertices, more than the limit of 2 \
           (Limits::max_mesh_vertices)",
        ],
    );
    limited(
        small(|l| l.max_mesh_triangles = 0),
        "lim-ply-faces",
        "ply",
        &tri,
        &[
            "element 'face' announces 1 faces (each at least one triangle), more than the limit \
           of 0 (Limits::max_mesh_triangles)",
        ],
    );
    let quad = ply_bytes(
        "ascii",
        4,
        2,
        b"0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n4 3 2 1 0\n",
    );
    limited(
        small(|l| l.max_polygon_vertices = 3),
        "lim-ply-poly",
        "ply",
        &quad,
        &["face 0 has 4 vertices, more than the limit of 3 (Limits::max_polygon_vertices)"],
    );
    limited(
        small(|l| l.max_mesh_triangles = 3),
        "lim-ply-tris",
        "ply",
        &quad,
        &[
            "face 1: the faces so far make 4 triangles, more than the limit of 3 \
           (Limits::max_mesh_triangles)",
        ],
    );
    limited(
        small(|l| l.max_memory_bytes = 50),
        "lim-ply-memory",
        "ply",
        &quad,
        &["(4 vertices, 2 faces) needs", "(Limits::max_memory_bytes)"],
    );
}

#[test]
fn a_directory_given_as_a_mesh_is_reported_as_a_directory() {
    for kind in ["obj", "ply"] {
        let xml = scene(&mesh_shape(kind, "meshes"));
        let p = write_scene(&format!("dir-mesh-{kind}"), &xml);
        std::fs::create_dir(p.parent().unwrap().join("meshes")).unwrap();
        let err = assert_load_fails_at(
            &p,
            &xml,
            "meshes",
            &["meshes': is a directory, not a mesh file"],
        );
        assert!(!err.to_string().contains("read error"), "{err}");
    }
}

/// `err` as anyhow's `{:#}` prints it: each error of the source chain, joined by ": ".
fn chain(err: &SceneError) -> String {
    let mut s = err.to_string();
    let mut source = std::error::Error::source(err);
    while let Some(e) = source {
        s += &format!(": {e}");
        source = e.source();
    }
    s
}

#[test]
fn a_missing_mesh_file_prints_its_os_error_once() {
    for kind in ["obj", "ply"] {
        let xml = scene(&mesh_shape(kind, &format!("gone.{kind}")));
        let p = write_scene(&format!("gone-{kind}"), &xml);
        let err = assert_load_fails_at(&p, &xml, "gone.", &["cannot read: "]);
        let shown = chain(&err);
        assert_eq!(shown.matches("os error 2").count(), 1, "{shown}");
    }
}

#[test]
fn world_coordinates_beyond_1e18_are_refused_at_the_shape() {
    let d = temp_dir("far");
    std::fs::write(d.join("tri.obj"), "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    let shape = |kind: &str, inner: &str, scale: &str| {
        format!(
            "<shape type=\"{kind}\">\n{inner}\n<transform name=\"to_world\">\n\
             <scale value=\"{scale}\"/>\n</transform>\n</shape>"
        )
    };
    let obj = "<string name=\"filename\" value=\"tri.obj\"/>";
    for (kind, inner) in [
        ("obj", obj),
        ("rectangle", ""),
        ("cube", ""),
        ("sphere", ""),
        ("disk", ""),
    ] {
        // 1e17 is fine.
        let (ok, _) = write_scene_in(&d, &shape(kind, inner, "1e17"));
        load_scene(&ok, &[]).unwrap_or_else(|e| panic!("{kind}: {e}"));

        let (p, xml) = write_scene_in(&d, &shape(kind, inner, "1e20"));
        assert_load_fails_at(
            &p,
            &xml,
            "<shape",
            &[kind, "beyond the bound of 1e18", "32-bit floats"],
        );
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn sphere_radius_must_be_positive() {
    for (r, shown) in [("0", "got 0"), ("-1", "got -1"), ("-0.5", "got -0.5")] {
        let xml = scene(&format!(
            "<shape type=\"sphere\">\n<float name=\"radius\" value=\"{r}\"/>\n</shape>"
        ));
        let p = write_scene(&format!("radius{r}"), &xml);
        let err = assert_load_fails_at(
            &p,
            &xml,
            "radius",
            &[&format!("sphere: radius must be positive, {shown}")],
        );
        assert!(!err.to_string().contains("similarity"), "{err}");
    }
    // A real shear still says why it is refused.
    let xml = scene(
        "<shape type=\"sphere\">\n<transform name=\"to_world\">\n\
         <matrix value=\"1 0.5 0 0  0 1 0 0  0 0 1 0  0 0 0 1\"/>\n</transform>\n</shape>",
    );
    let p = write_scene("sheared-sphere", &xml);
    assert_load_fails_at(&p, &xml, "<shape", &["similarity"]);
}

/// One shape of a Mitsuba serialized file (format `version` 3 or 4): the header and the
/// zlib stream of its flags, name, counts, positions, normals, texture coordinates and
/// indices (f64 with `double`).
fn serialized_shape(
    version: u16,
    double: bool,
    positions: &[[f32; 3]],
    normals: Option<&[[f32; 3]]>,
    uvs: Option<&[[f32; 2]]>,
    triangles: &[[u32; 3]],
) -> Vec<u8> {
    use std::io::Write;
    let mut body = Vec::new();
    let flags = u32::from(normals.is_some())
        | if uvs.is_some() { 2 } else { 0 }
        | if double { 0x2000 } else { 0x1000 };
    body.extend(flags.to_le_bytes());
    if version == 4 {
        body.extend(b"shape name\0");
    }
    body.extend((positions.len() as u64).to_le_bytes());
    body.extend((triangles.len() as u64).to_le_bytes());
    let mut put = |x: f32| match double {
        true => body.extend((x as f64).to_le_bytes()),
        false => body.extend(x.to_le_bytes()),
    };
    positions.iter().flatten().for_each(|&x| put(x));
    normals
        .into_iter()
        .flatten()
        .flatten()
        .for_each(|&x| put(x));
    uvs.into_iter().flatten().flatten().for_each(|&x| put(x));
    for t in triangles.iter().flatten() {
        body.extend(t.to_le_bytes());
    }
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
    z.write_all(&body).unwrap();
    let mut out = vec![0x1C, 0x04];
    out.extend(version.to_le_bytes());
    out.extend(z.finish().unwrap());
    out
}

/// Shapes concatenated, with the dictionary of their offsets at the end.
fn serialized_file(version: u16, shapes: &[Vec<u8>]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut offsets = Vec::new();
    for s in shapes {
        offsets.push(out.len() as u64);
        out.extend(s);
    }
    for o in offsets {
        match version {
            4 => out.extend(o.to_le_bytes()),
            _ => out.extend((o as u32).to_le_bytes()),
        }
    }
    out.extend((shapes.len() as u32).to_le_bytes());
    out
}

const QUAD: [[f32; 3]; 4] = [
    [0.0, 0.0, 0.0],
    [1.0, 0.0, 0.0],
    [1.0, 1.0, 0.0],
    [0.0, 1.0, 0.0],
];

#[test]
fn serialized_meshes_load_by_shape_index_in_both_versions_and_precisions() {
    let tri = serialized_shape(4, false, &QUAD[..3], None, None, &[[0, 1, 2]]);
    let uvs = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
    let normals = [[0.0, 0.0, 1.0]; 4];
    let quad = serialized_shape(
        4,
        false,
        &QUAD,
        Some(&normals),
        Some(&uvs),
        &[[0, 1, 2], [0, 2, 3]],
    );
    let file = serialized_file(4, &[tri, quad]);
    for (index, triangles, has_uvs) in [(0, 1, false), (1, 2, true)] {
        let extra = format!("\n  <integer name=\"shape_index\" value=\"{index}\"/>");
        let name = format!("serialized-v4-{index}");
        let (p, _, _) = mesh_scene_with(&name, "serialized", "m.serialized", &file, &extra);
        let s = load_scene(&p, &[]).unwrap();
        let Geometry::Mesh(m) = &s.shapes[0].geometry else {
            panic!("a mesh")
        };
        assert_eq!(m.indices.len(), triangles);
        assert_eq!(m.uvs.is_some(), has_uvs);
        assert_eq!(m.positions[2], glam::Vec3::new(1.0, 1.0, 0.0));
        if has_uvs {
            // as stored: a serialized file's v is not flipped
            assert_eq!(m.uvs.as_ref().unwrap()[3], glam::Vec2::new(0.0, 1.0));
        }
    }
    let v3 = serialized_file(
        3,
        &[serialized_shape(3, true, &QUAD, None, None, &[[3, 2, 1]])],
    );
    let (p, _, _) = mesh_scene("serialized-v3", "serialized", "m.serialized", &v3);
    let s = load_scene(&p, &[]).unwrap();
    let Geometry::Mesh(m) = &s.shapes[0].geometry else {
        panic!("a mesh")
    };
    assert_eq!(
        (m.indices[0], m.positions[3]),
        ([3, 2, 1], glam::Vec3::new(0.0, 1.0, 0.0))
    );
}

#[test]
fn bad_serialized_files_are_refused_naming_the_file() {
    let good = serialized_shape(4, false, &QUAD[..3], None, None, &[[0, 1, 2]]);
    let file = serialized_file(4, std::slice::from_ref(&good));
    let err = |name: &str, bytes: &[u8], extra: &str, needle: &str| {
        let (p, xml, mesh) = mesh_scene_with(name, "serialized", "m.serialized", bytes, extra);
        let prefix = format!("mesh file '{}': ", mesh.display());
        assert_load_fails_at(&p, &xml, "m.serialized", &[&prefix, needle]);
    };
    let index = "\n  <integer name=\"shape_index\" value=\"1\"/>";
    err(
        "ser-index",
        &file,
        index,
        "shape_index 1 is out of range: the file holds 1 shapes",
    );
    err(
        "ser-magic",
        b"PK\x03\x04 not a mesh",
        "",
        "not a serialized mesh",
    );
    let mut v5 = file.clone();
    v5[2] = 5;
    err("ser-version", &v5, "", "format version 5 is not supported");
    err("ser-truncated", &good[..good.len() - 6], "", "ends early");
    let oob = serialized_shape(4, false, &QUAD[..3], None, None, &[[0, 1, 7]]);
    err(
        "ser-oob",
        &serialized_file(4, &[oob]),
        "",
        "triangle 0: vertex index 7 out of range",
    );
}
