//! Bad input gets a clear error naming the file (and line), never a panic,
//! and leaves no output behind.

use crate::common::*;

/// Runs `pathfarm render` on a scene and returns stderr, asserting failure
/// without a panic and without an output file.
fn render_fails(scene: &std::path::Path) -> String {
    let out = scene.with_file_name("out.exr");
    let err = assert_clean_failure(&pathfarm_render(scene, &out, &["--spp", "1"]), "render");
    assert!(!out.exists(), "an output file was written");
    err
}

fn minimal(body: &str) -> String {
    scene_xml(8, 8, 40.0, 4.0, r#"<integrator type="path"/>"#, body)
}

/// [`render_fails`] on a [`minimal`] scene with `body`: its stderr, and the line of the
/// scene file holding `needle`.
fn minimal_fails(tag: &str, body: &str, needle: &str) -> (String, usize) {
    let xml = minimal(body);
    (render_fails(&write_scene(tag, &xml)), line_of(&xml, needle))
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
    let (err, line) = minimal_fails("plugin", r#"<shape type="teapot"/>"#, "teapot");
    assert!(
        err.contains("teapot") && err.contains(&format!("scene.xml:{line}")),
        "{err}"
    );
}

#[test]
fn unknown_parameter_is_rejected_by_name() {
    let body = r#"<shape type="sphere"><bsdf type="roughconductor"><float name="alpah" value="0.1"/></bsdf></shape>"#;
    let (err, line) = minimal_fails("param", body, "alpah");
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
    let png = dir.join("x.png");
    for (out, extra) in [
        (&out, &["--spp", "0"][..]),
        (&out, &["--time", "-1"]),
        (&png, &[]),
        (&out, &["-D", "novalue"]),
    ] {
        let o = pathfarm_render(&scene, out, extra);
        assert_clean_failure(&o, &format!("-o {} {extra:?}", out.display()));
    }
    assert!(!out.exists());
}
