//! Bad input: every error names the file and the line at fault.

mod common;

use common::*;
use pathfarm_scene::*;

/// Where a case's error must be reported: a line number, or the first line containing a text.
enum At {
    Line(u32),
    First(&'static str),
}

#[test]
fn bad_scenes_are_reported_at_the_line_at_fault() {
    // (case and scene directory name, scene text, where the error is, what its message says)
    let cases: Vec<(&str, String, At, &[&str])> = vec![
        (
            "malformed",
            "<scene version=\"3.0.0\">\n<sensor type=\"perspective\">\n<float name=\"fov\" value=\"45\">\n</sensor>\n</scene>\n".into(),
            At::Line(4),
            &["malformed XML"],
        ),
        (
            "unknown-plugin",
            scene("<shape type=\"rectangle\"/>\n<shape type=\"torus\"/>"),
            At::First("torus"),
            &["torus"],
        ),
        (
            "unknown-integrator",
            scene("<integrator type=\"bdpt\"/>"),
            At::First("bdpt"),
            &["bdpt", "integrator"],
        ),
        (
            "unknown-param",
            scene("<bsdf type=\"roughconductor\" id=\"m\">\n  <float name=\"alpha\" value=\"0.2\"/>\n  <float name=\"alpah\" value=\"0.3\"/>\n</bsdf>"),
            At::First("alpah"),
            &["alpah", "roughconductor"],
        ),
        (
            "missing-mesh",
            scene(&mesh_shape("obj", "nothere.obj")),
            At::First("nothere.obj"),
            &["nothere.obj"],
        ),
        (
            "missing-texture",
            scene("<shape type=\"cube\"><bsdf type=\"diffuse\">\n<texture type=\"bitmap\" name=\"reflectance\">\n  <string name=\"filename\" value=\"gone.png\"/>\n</texture></bsdf></shape>"),
            At::First("gone.png"),
            &["gone.png"],
        ),
        (
            "undefined-ref",
            scene("<shape type=\"cube\">\n  <ref id=\"NoSuchBSDF\"/>\n</shape>"),
            At::First("NoSuchBSDF"),
            &["NoSuchBSDF"],
        ),
        (
            "wrong-type",
            scene("<shape type=\"sphere\">\n  <string name=\"radius\" value=\"1\"/>\n</shape>"),
            At::First("radius"),
            &["radius", "string", "float"],
        ),
        (
            "bad-number",
            "<scene version=\"3.0.0\">\n<sensor type=\"perspective\">\n  <float name=\"fov\" value=\"4x5\"/>\n</sensor>\n</scene>\n".into(),
            At::Line(3),
            &["4x5"],
        ),
        (
            // A sphere's transform must be a similarity.
            "ellipsoid",
            scene("<shape type=\"sphere\">\n<transform name=\"to_world\"><scale x=\"1\" y=\"2\" z=\"1\"/></transform>\n</shape>"),
            At::First("<shape"),
            &["similarity"],
        ),
        (
            "textured-alpha",
            scene("<bsdf type=\"roughconductor\">\n<texture type=\"checkerboard\" name=\"alpha\"/>\n</bsdf>"),
            At::First("checkerboard"),
            &["alpha", "not supported"],
        ),
        (
            "spectral-list-unordered",
            scene("<bsdf type=\"diffuse\">\n<spectrum name=\"reflectance\" value=\"700:0.1, 400:0.5\"/>\n</bsdf>"),
            At::First("spectrum"),
            &["700:0.1, 400:0.5", "wavelengths must increase"],
        ),
        (
            "spectral-list-not-a-pair",
            scene("<bsdf type=\"diffuse\">\n<spectrum name=\"reflectance\" value=\"400:0.1, 0.5\"/>\n</bsdf>"),
            At::First("spectrum"),
            &["\"0.5\" is not a wavelength:value pair"],
        ),
        (
            "no-sensor",
            "<scene version=\"3.0.0\">\n<shape type=\"cube\"/>\n</scene>\n".into(),
            At::Line(1),
            &["no sensor"],
        ),
        (
            // A reference cycle is an error, not a stack overflow.
            "cycle",
            scene("<bsdf type=\"twosided\" id=\"a\">\n  <ref id=\"a\"/>\n</bsdf>"),
            At::First("<ref"),
            &["cycle"],
        ),
        (
            "unknown-element",
            scene("<shape type=\"cube\">\n  <colour name=\"x\" value=\"1\"/>\n</shape>"),
            At::First("colour"),
            &["colour"],
        ),
        (
            "include-missing",
            scene("<include filename=\"other.xml\"/>"),
            At::First("include"),
            &["other.xml", "no such file"],
        ),
        (
            // Keyword parameters name themselves, their plugin and the words they take.
            "unknown-keyword",
            scene("<integrator type=\"guided_path\">\n  <string name=\"nee\" value=\"sometimes\"/>\n</integrator>"),
            At::First("sometimes"),
            &["parameter 'nee' of guided_path integrator must be one of never, always, kickstart (got \"sometimes\")"],
        ),
        (
            // Mitsuba reads a distribution's name in any case but a wrap mode's as written.
            "keyword-case",
            scene("<bsdf type=\"roughconductor\"><string name=\"distribution\" value=\"GGX\"/></bsdf>\n<texture type=\"bitmap\" id=\"t\"><string name=\"filename\" value=\"t.png\"/>\n  <string name=\"wrap_mode\" value=\"Repeat\"/>\n</texture>"),
            At::First("Repeat"),
            &["parameter 'wrap_mode' of bitmap texture must be one of repeat, mirror, clamp (got \"Repeat\")"],
        ),
    ];
    check_cases(
        cases,
        |case| case.0.to_string(),
        |(name, xml, at, needles)| {
            let p = write_scene(name, &xml);
            let line = match at {
                At::Line(l) => l,
                At::First(text) => line_of(&xml, text),
            };
            assert_invalid_at(&load_scene(&p, &[]).unwrap_err(), &p, line, needles);
        },
    );
}

#[test]
fn nan_vertex_in_obj_is_rejected_naming_the_mesh_file() {
    let (p, xml, _) = mesh_scene(
        "nan-obj",
        "obj",
        "bad.obj",
        b"v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n",
    );
    assert_load_fails_at(&p, &xml, "bad.obj", &["bad.obj", "non-finite"]);
}

#[test]
fn out_of_range_index_in_ply_is_rejected() {
    let (p, xml, _) = mesh_scene(
        "bad-ply",
        "ply",
        "bad.ply",
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
    );
    assert_load_fails_at(&p, &xml, "bad.ply", &["bad.ply", "out of range"]);
}

#[test]
fn missing_scene_file_is_an_io_error_naming_it() {
    let p = std::env::temp_dir().join("pathfarm-scene-test-definitely-missing.xml");
    match load_scene(&p, &[]).unwrap_err() {
        SceneError::Io { file, .. } => assert_eq!(file, p),
        e => panic!("{e:?}"),
    }
}

#[test]
fn truncated_or_mangled_scene_files_give_errors_never_panics() {
    let original = std::fs::read_to_string("/work/shared/scenes/cornell-box/scene.xml").unwrap();
    let d = temp_dir("mangled");
    let p = d.join("scene.xml");
    let bytes = original.as_bytes();
    let mut errors = 0;
    for cut in (1..bytes.len()).step_by(23) {
        // Truncate, and separately drop one byte, at `cut`.
        for variant in [
            bytes[..cut].to_vec(),
            [&bytes[..cut], &bytes[cut + 1..]].concat(),
        ] {
            std::fs::write(&p, &variant).unwrap();
            let r = std::panic::catch_unwind(|| load_scene(&p, &[]));
            match r {
                Ok(Ok(_)) => {}
                Ok(Err(SceneError::Invalid { file, line, .. })) => {
                    assert_eq!(file, p);
                    assert!(line >= 1);
                    errors += 1;
                }
                Ok(Err(e)) => panic!("unexpected error kind {e:?}"),
                Err(_) => panic!("loader panicked on input cut at byte {cut}"),
            }
        }
    }
    assert!(errors > 100, "only {errors} errors");
}

/// `mesh` written as `name` beside a scene that loads it with `<shape type="kind">`
/// (extra `shape_body` inside the shape): the load error.
fn mesh_error(
    tag: &str,
    kind: &str,
    name: &str,
    mesh: &[u8],
    shape_body: &str,
) -> (SceneError, TempFile, String) {
    let (p, xml, _) = mesh_scene_with(tag, kind, name, mesh, shape_body);
    let err = load_scene(&p, &[]).expect_err(tag);
    (err, p, xml)
}

/// A binary little-endian PLY triangle with the given vertex coordinates.
fn binary_ply(coords: [[f32; 3]; 3]) -> Vec<u8> {
    let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
    for v in coords.iter().flatten() {
        b.extend(v.to_le_bytes());
    }
    b.push(3);
    for i in 0..3i32 {
        b.extend(i.to_le_bytes());
    }
    b
}

#[test]
fn infinite_and_nan_mesh_data_is_rejected_naming_the_mesh_file() {
    // NaN or Inf anywhere in a mesh's vertex data (positions, normals, texture
    // coordinates; OBJ, ASCII and binary PLY), or a finite position that the shape's
    // transform sends to infinity, must never reach the renderer: the load fails at the
    // shape's line, naming the file and saying what is non-finite.
    let ascii_ply = |v1: &str| {
        format!("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n{v1}\n0 1 0\n3 0 1 2\n")
    };
    let cases: Vec<(&str, &str, &str, Vec<u8>, &str)> = vec![
        (
            "obj-inf",
            "obj",
            "inf.obj",
            b"v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n".to_vec(),
            "",
        ),
        (
            "obj-neg-inf",
            "obj",
            "ninf.obj",
            b"v 0 0 0\nv 1 0 -inf\nv 0 1 0\nf 1 2 3\n".to_vec(),
            "",
        ),
        (
            "obj-overflow",
            "obj",
            "big.obj",
            b"v 0 0 0\nv 1e39 0 0\nv 0 1 0\nf 1 2 3\n".to_vec(),
            "",
        ),
        (
            "obj-nan-normal",
            "obj",
            "nrm.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nvn nan 0 1\nvn 0 0 1\nf 1//1 2//2 3//3\n"
                .to_vec(),
            "",
        ),
        (
            "obj-inf-uv",
            "obj",
            "uv.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt inf 0\nvt 0 1\nf 1/1 2/2 3/3\n".to_vec(),
            "",
        ),
        (
            "ply-ascii-nan",
            "ply",
            "nan.ply",
            ascii_ply("1 nan 0").into_bytes(),
            "",
        ),
        (
            "ply-ascii-inf",
            "ply",
            "inf.ply",
            ascii_ply("1 0 inf").into_bytes(),
            "",
        ),
        (
            "ply-binary-nan",
            "ply",
            "nanb.ply",
            binary_ply([[0.0; 3], [1.0, f32::NAN, 0.0], [0.0, 1.0, 0.0]]),
            "",
        ),
        (
            "ply-binary-inf",
            "ply",
            "infb.ply",
            binary_ply([[0.0; 3], [f32::INFINITY, 0.0, 0.0], [0.0, 1.0, 0.0]]),
            "",
        ),
        (
            "obj-transformed-to-inf",
            "obj",
            "far.obj",
            b"v 0 0 0\nv 3e38 0 0\nv 0 1 0\nf 1 2 3\n".to_vec(),
            "\n  <transform name=\"to_world\"><scale value=\"100\"/></transform>",
        ),
    ];
    for (tag, kind, name, mesh, body) in cases {
        let (err, p, xml) = mesh_error(tag, kind, name, &mesh, body);
        let shown = err.to_string();
        assert!(shown.contains(name), "{tag}: {shown}");
        // (in f64 the transformed vertex is 3e40: beyond the world-coordinate limit; the
        // ASCII PLY reader accepts only digits, so "nan"/"inf" fail to parse at their line)
        let says = match tag {
            "obj-transformed-to-inf" => "world space",
            "ply-ascii-nan" | "ply-ascii-inf" => "line 11",
            _ => "non-finite",
        };
        assert!(shown.contains(says), "{tag}: says what is wrong: {shown}");
        // (the world-space bound is checked per shape: reported at its element)
        let line = if tag == "obj-transformed-to-inf" {
            line_of(&xml, "<shape")
        } else {
            line_of(&xml, name)
        };
        assert!(
            shown.contains(&format!("{}:{line}", p.display())),
            "{tag}: at the shape's line: {shown}"
        );
    }
}
