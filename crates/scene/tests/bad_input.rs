//! Bad input: every error names the file and the line at fault.

mod common;

use common::*;
use pathfarm_scene::*;
use std::path::PathBuf;

#[test]
fn malformed_xml_reports_the_line_of_the_syntax_error() {
    let xml = "<scene version=\"3.0.0\">\n<sensor type=\"perspective\">\n<float name=\"fov\" value=\"45\">\n</sensor>\n</scene>\n";
    let p = write_scene("malformed", xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, 4, &["malformed XML"]);
}

#[test]
fn unknown_plugin_type_is_reported_at_its_element() {
    let xml = scene("<shape type=\"rectangle\"/>\n<shape type=\"torus\"/>");
    let p = write_scene("unknown-plugin", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "torus"), &["torus"]);
}

#[test]
fn unknown_integrator_type_is_rejected() {
    let xml = scene("<integrator type=\"bdpt\"/>");
    let p = write_scene("unknown-integrator", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "bdpt"), &["bdpt", "integrator"]);
}

#[test]
fn misspelt_parameter_is_reported_at_its_line() {
    let xml = scene(
        "<bsdf type=\"roughconductor\" id=\"m\">\n  <float name=\"alpha\" value=\"0.2\"/>\n  <float name=\"alpah\" value=\"0.3\"/>\n</bsdf>",
    );
    let p = write_scene("unknown-param", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "alpah"),
        &["alpah", "roughconductor"],
    );
}

#[test]
fn missing_mesh_file_names_the_mesh_and_the_referencing_line() {
    let xml = scene(
        "<shape type=\"obj\">\n  <string name=\"filename\" value=\"nothere.obj\"/>\n</shape>",
    );
    let p = write_scene("missing-mesh", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "nothere.obj"), &["nothere.obj"]);
}

#[test]
fn missing_texture_file_names_the_image_and_the_referencing_line() {
    let xml = scene(
        "<shape type=\"cube\"><bsdf type=\"diffuse\">\n<texture type=\"bitmap\" name=\"reflectance\">\n  <string name=\"filename\" value=\"gone.png\"/>\n</texture></bsdf></shape>",
    );
    let p = write_scene("missing-texture", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "gone.png"), &["gone.png"]);
}

#[test]
fn nan_vertex_in_obj_is_rejected_naming_the_mesh_file() {
    let d = temp_dir("nan-obj");
    std::fs::write(d.join("bad.obj"), "v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    let xml =
        scene("<shape type=\"obj\">\n  <string name=\"filename\" value=\"bad.obj\"/>\n</shape>");
    let p = d.join("scene.xml");
    std::fs::write(&p, &xml).unwrap();
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "bad.obj"),
        &["bad.obj", "non-finite"],
    );
}

#[test]
fn out_of_range_index_in_ply_is_rejected() {
    let d = temp_dir("bad-ply");
    std::fs::write(
        d.join("bad.ply"),
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
    )
    .unwrap();
    let xml =
        scene("<shape type=\"ply\">\n  <string name=\"filename\" value=\"bad.ply\"/>\n</shape>");
    let p = d.join("scene.xml");
    std::fs::write(&p, &xml).unwrap();
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "bad.ply"),
        &["bad.ply", "out of range"],
    );
}

#[test]
fn undefined_ref_id_is_reported_at_the_ref() {
    let xml = scene("<shape type=\"cube\">\n  <ref id=\"NoSuchBSDF\"/>\n</shape>");
    let p = write_scene("undefined-ref", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "NoSuchBSDF"), &["NoSuchBSDF"]);
}

#[test]
fn wrong_property_type_is_reported_at_the_property() {
    let xml = scene("<shape type=\"sphere\">\n  <string name=\"radius\" value=\"1\"/>\n</shape>");
    let p = write_scene("wrong-type", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "radius"),
        &["radius", "string", "float"],
    );
}

#[test]
fn malformed_number_is_reported_at_its_line() {
    let xml = "<scene version=\"3.0.0\">\n<sensor type=\"perspective\">\n  <float name=\"fov\" value=\"4x5\"/>\n</sensor>\n</scene>\n";
    let p = write_scene("bad-number", xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, 3, &["4x5"]);
}

#[test]
fn non_uniform_sphere_transform_is_rejected() {
    let xml = scene("<shape type=\"sphere\">\n<transform name=\"to_world\"><scale x=\"1\" y=\"2\" z=\"1\"/></transform>\n</shape>");
    let p = write_scene("ellipsoid", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "<shape"), &["similarity"]);
}

#[test]
fn textured_roughness_and_spectral_lists_are_unsupported() {
    let xml = scene(
        "<bsdf type=\"roughconductor\">\n<texture type=\"checkerboard\" name=\"alpha\"/>\n</bsdf>",
    );
    let p = write_scene("textured-alpha", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "checkerboard"),
        &["alpha", "not supported"],
    );

    let xml = scene("<bsdf type=\"diffuse\">\n<spectrum name=\"reflectance\" value=\"400:0.1, 700:0.5\"/>\n</bsdf>");
    let p = write_scene("spectral-list", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "spectrum"), &["not supported"]);
}

#[test]
fn scene_without_sensor_is_an_error() {
    let xml = "<scene version=\"3.0.0\">\n<shape type=\"cube\"/>\n</scene>\n";
    let p = write_scene("no-sensor", xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, 1, &["no sensor"]);
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
fn reference_cycle_is_an_error_not_a_stack_overflow() {
    let xml = scene("<bsdf type=\"twosided\" id=\"a\">\n  <ref id=\"a\"/>\n</bsdf>");
    let p = write_scene("cycle", &xml);
    let err = load_scene(&p, &[]).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "<ref"), &["cycle"]);
}

#[test]
fn unknown_element_and_include_are_rejected() {
    let xml = scene("<shape type=\"cube\">\n  <colour name=\"x\" value=\"1\"/>\n</shape>");
    let p = write_scene("unknown-element", &xml);
    assert_invalid_at(
        &load_scene(&p, &[]).unwrap_err(),
        &p,
        line_of(&xml, "colour"),
        &["colour"],
    );
    let xml = scene("<include filename=\"other.xml\"/>");
    let p = write_scene("include", &xml);
    assert_invalid_at(
        &load_scene(&p, &[]).unwrap_err(),
        &p,
        line_of(&xml, "include"),
        &["not supported"],
    );
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
) -> (SceneError, PathBuf, String) {
    let d = temp_dir(tag);
    std::fs::write(d.join(name), mesh).unwrap();
    let xml = scene(&format!(
        "<shape type=\"{kind}\">\n  <string name=\"filename\" value=\"{name}\"/>{shape_body}\n</shape>"
    ));
    let p = d.join("scene.xml");
    std::fs::write(&p, &xml).unwrap();
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
