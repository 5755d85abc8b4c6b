//! Bad input gets a clear error naming the file (and line), never a panic,
//! and leaves no output behind.

use crate::common::*;

/// Runs `pathfarm render` on a scene and returns stderr, asserting failure
/// without a panic and without an output file.
fn render_fails(scene: &std::path::Path) -> String {
    let out = scene.with_file_name("out.exr");
    let o = pathfarm(&[
        "render",
        scene.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--spp",
        "1",
    ]);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(
        !o.status.success(),
        "expected failure, got success; stderr: {err}"
    );
    assert!(!err.contains("panicked"), "panic: {err}");
    assert!(!out.exists(), "an output file was written");
    err
}

fn minimal(body: &str) -> String {
    scene_xml(8, 8, 40.0, 4.0, r#"<integrator type="path"/>"#, body)
}

#[test]
fn malformed_xml_names_file_and_line() {
    let p = write_scene(
        "malformed",
        "<scene version=\"3.0.0\">\n  <shape type=\"sphere\">\n</scene>\n",
    );
    let err = render_fails(&p);
    assert!(err.contains("scene.xml:"), "{err}");
}

#[test]
fn unknown_plugin_is_rejected_by_name_and_line() {
    let xml = minimal(r#"<shape type="teapot"/>"#);
    let line = xml.lines().position(|l| l.contains("teapot")).unwrap() + 1;
    let err = render_fails(&write_scene("plugin", &xml));
    assert!(
        err.contains("teapot") && err.contains(&format!("scene.xml:{line}")),
        "{err}"
    );
}

#[test]
fn unknown_parameter_is_rejected_by_name() {
    let xml = minimal(
        r#"<shape type="sphere"><bsdf type="roughconductor"><float name="alpah" value="0.1"/></bsdf></shape>"#,
    );
    let line = xml.lines().position(|l| l.contains("alpah")).unwrap() + 1;
    let err = render_fails(&write_scene("param", &xml));
    assert!(
        err.contains("alpah") && err.contains(&format!(":{line}")),
        "{err}"
    );
}

#[test]
fn missing_mesh_and_texture_name_the_missing_file() {
    let err = render_fails(&write_scene(
        "mesh",
        &minimal(r#"<shape type="obj"><string name="filename" value="nowhere.obj"/></shape>"#),
    ));
    assert!(err.contains("nowhere.obj"), "{err}");
    let tex = r#"<shape type="sphere"><bsdf type="diffuse"><texture name="reflectance" type="bitmap"><string name="filename" value="missing.png"/></texture></bsdf></shape>"#;
    let err = render_fails(&write_scene("tex", &minimal(tex)));
    assert!(err.contains("missing.png"), "{err}");
}

#[test]
fn nan_in_a_mesh_is_rejected_naming_the_mesh() {
    let scene = write_scene(
        "nan",
        &minimal(r#"<shape type="obj"><string name="filename" value="bad.obj"/></shape>"#),
    );
    std::fs::write(
        scene.with_file_name("bad.obj"),
        "v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n",
    )
    .unwrap();
    let err = render_fails(&scene);
    assert!(err.contains("bad.obj"), "{err}");
}

#[test]
fn bad_command_line_values_are_rejected() {
    let scene = shared_scene("cornell-box");
    let dir = temp_dir("cli-bad");
    let out = dir.join("x.exr");
    for args in [
        vec![
            "render",
            scene.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--spp",
            "0",
        ],
        vec![
            "render",
            scene.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--time",
            "-1",
        ],
        vec![
            "render",
            scene.to_str().unwrap(),
            "-o",
            dir.join("x.png").to_str().unwrap(),
        ],
        vec![
            "render",
            scene.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "-D",
            "novalue",
        ],
    ] {
        let o = pathfarm(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && !err.contains("panicked"),
            "{args:?}: {err}"
        );
    }
    assert!(!out.exists());
}
