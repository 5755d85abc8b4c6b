//! The files a scene reads: `SceneDesc::files` lists each once, root first, and with
//! `Limits::confine_files` a scene may read only files inside its own directory (absolute
//! names, `..` and symbolic links leading out are refused with an error naming the file,
//! line and name), while the default still accepts them.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use pathfarm_scene::{
    load_scene, load_scene_with_limits, scene_files, Limits, SceneDesc, SceneError,
};

const TRI_OBJ: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n";
const TRI_PLY: &str =
    "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";

fn confined() -> Limits {
    Limits {
        confine_files: true,
        ..Limits::default()
    }
}

fn write(path: &Path, contents: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, contents).unwrap();
}

fn write_png(path: &Path) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    // 4x3: large enough to be an environment map (Mitsuba 3: at least 2x3)
    image::RgbImage::from_pixel(4, 3, image::Rgb([200, 100, 50]))
        .save(path)
        .unwrap();
}

fn load_confined(p: &Path) -> Result<SceneDesc, SceneError> {
    load_scene_with_limits(p, &[], &confined())
}

/// `scene(body)` written in `dir`: loading it with confinement fails at the line of its
/// `filename` with every string of `needles` in the message. Returns the scene's path.
fn assert_confined_fails(dir: &Path, body: &str, needles: &[&str]) -> PathBuf {
    let (p, xml) = write_scene_in(dir, body);
    let err = load_confined(&p).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "filename"), needles);
    p
}

#[test]
fn files_lists_every_file_read_once_root_first_in_first_read_order() {
    let d = temp_dir("files-list");
    write_png(&d.join("textures/wood.png"));
    write(&d.join("meshes/tri.obj"), TRI_OBJ.as_bytes());
    write(&d.join("tri.ply"), TRI_PLY.as_bytes());
    write_png(&d.join("sky.png"));
    // Each file is referenced twice (the texture by two textures, the OBJ by two shapes).
    let body = format!(
        "<texture type=\"bitmap\" id=\"a\">\n  <string name=\"filename\" value=\"textures/wood.png\"/>\n</texture>\n\
         <texture type=\"bitmap\" id=\"b\">\n  <string name=\"filename\" value=\"./textures/wood.png\"/>\n</texture>\n\
         {}\n{}\n{}\n\
         <emitter type=\"envmap\">\n  <string name=\"filename\" value=\"sky.png\"/>\n</emitter>",
        mesh_shape("obj", "meshes/tri.obj"),
        mesh_shape("ply", "tri.ply"),
        mesh_shape("obj", "meshes/tri.obj"),
    );
    let (p, _) = write_scene_in(&d, &body);
    let expected = vec![
        p.clone(),
        d.join("textures/wood.png"),
        d.join("meshes/tri.obj"),
        d.join("tri.ply"),
        d.join("sky.png"),
    ];
    let s = load_scene(&p, &[]).unwrap();
    assert_eq!(s.files, expected);
    // Learning the names without decoding finds the same files, in the same order.
    assert_eq!(scene_files(&p, &[], &confined()).unwrap(), expected);
    assert_eq!(s.shapes.len(), 3);
    assert_eq!(s.textures.len(), 2);
    // Confinement changes nothing for a self-contained scene.
    let c = load_confined(&p).unwrap();
    assert_eq!(c.files, expected);
    assert_eq!(format!("{:?}", c.shapes), format!("{:?}", s.shapes));
    // A scene of primitives reads only itself.
    let (p2, _) = write_scene_in(&d.join("plain"), "<shape type=\"cube\"/>");
    assert_eq!(load_scene(&p2, &[]).unwrap().files, vec![p2.clone()]);
}

#[test]
fn files_lists_absolute_and_parent_names_as_written_without_confinement() {
    let d = temp_dir("files-abs");
    let outside = d.join("outside/abs.obj");
    write(&outside, TRI_OBJ.as_bytes());
    write(&d.join("up.obj"), TRI_OBJ.as_bytes());
    let body = format!(
        "{}\n{}",
        mesh_shape("obj", outside.to_str().unwrap()),
        mesh_shape("obj", "../up.obj")
    );
    let (p, _) = write_scene_in(&d.join("scene"), &body);
    let s = load_scene(&p, &[]).unwrap();
    assert_eq!(s.files, vec![p.clone(), outside, d.join("scene/../up.obj")]);
}

#[test]
fn confinement_refuses_absolute_paths() {
    let d = temp_dir("confine-abs");
    // A valid mesh outside the scene's directory, named by its absolute path.
    let outside = d.join("outside/abs.obj");
    write(&outside, TRI_OBJ.as_bytes());
    for name in ["/etc/passwd", outside.to_str().unwrap()] {
        assert_confined_fails(
            &d.join("scene"),
            &mesh_shape("obj", name),
            &[name, "absolute", "confine_files"],
        );
    }
    // The default (`pathfarm render`) still reads absolute names.
    let (p, _) = write_scene_in(
        &d.join("scene"),
        &mesh_shape("obj", outside.to_str().unwrap()),
    );
    assert_eq!(load_scene(&p, &[]).unwrap().shapes.len(), 1);
}

#[test]
fn confinement_refuses_parent_components_even_when_they_stay_inside() {
    let d = temp_dir("confine-dotdot");
    write(&d.join("x.obj"), TRI_OBJ.as_bytes());
    write(&d.join("scene/x.obj"), TRI_OBJ.as_bytes());
    write(&d.join("scene/sub/y.obj"), TRI_OBJ.as_bytes());
    for name in ["../x.obj", "sub/../x.obj", "sub/../../x.obj", ".."] {
        assert_confined_fails(
            &d.join("scene"),
            &mesh_shape("obj", name),
            &[&format!("'{name}'"), "'..'", "confine_files"],
        );
    }
    let (p, _) = write_scene_in(&d.join("scene"), &mesh_shape("obj", "../x.obj"));
    assert_eq!(load_scene(&p, &[]).unwrap().shapes.len(), 1);
}

#[test]
fn confinement_refuses_symlinks_that_lead_outside_and_accepts_those_that_stay_inside() {
    use std::os::unix::fs::symlink;
    let d = temp_dir("confine-symlink");
    write(&d.join("outside/x.obj"), TRI_OBJ.as_bytes());
    write_png(&d.join("outside/t.png"));
    write(&d.join("scene/models/real.obj"), TRI_OBJ.as_bytes());
    symlink(d.join("outside/x.obj"), d.join("scene/link.obj")).unwrap();
    symlink("../outside/t.png", d.join("scene/t.png")).unwrap();
    // A symlinked directory: the file name has no '..', its directory leads out.
    symlink(d.join("outside"), d.join("scene/ext")).unwrap();
    symlink("real.obj", d.join("scene/models/alias.obj")).unwrap();
    let texture = "<texture type=\"bitmap\" id=\"t\">\n  <string name=\"filename\" value=\"t.png\"/>\n</texture>";
    for body in [
        mesh_shape("obj", "link.obj"),
        mesh_shape("obj", "ext/x.obj"),
        texture.to_string(),
    ] {
        let outside = std::fs::canonicalize(d.join("outside")).unwrap();
        let p = assert_confined_fails(
            &d.join("scene"),
            &body,
            &[
                "symbolic link",
                &outside.display().to_string(),
                "confine_files",
            ],
        );
        // Not confined, the link is followed.
        load_scene(&p, &[]).unwrap();
    }
    // A link that stays inside the directory is fine; the file is listed by the name used.
    let (p, _) = write_scene_in(&d.join("scene"), &mesh_shape("obj", "models/alias.obj"));
    let s = load_confined(&p).unwrap();
    assert_eq!(s.files, vec![p.clone(), d.join("scene/models/alias.obj")]);
}

#[test]
fn confinement_accepts_subdirectories_and_applies_to_textures_and_envmaps() {
    let d = temp_dir("confine-subdir");
    write(&d.join("scene/models/deep/er/tri.obj"), TRI_OBJ.as_bytes());
    write(&d.join("scene/models/tri.ply"), TRI_PLY.as_bytes());
    write_png(&d.join("scene/textures/a b.png"));
    write_png(&d.join("sky.png"));
    let body = format!(
        "{}\n{}\n<texture type=\"bitmap\" id=\"t\">\n  <string name=\"filename\" value=\"textures/a b.png\"/>\n</texture>",
        mesh_shape("obj", "models/deep/er/tri.obj"),
        mesh_shape("ply", "./models/tri.ply"),
    );
    let (p, _) = write_scene_in(&d.join("scene"), &body);
    let s = load_confined(&p).unwrap();
    assert_eq!(s.files.len(), 4);
    assert_eq!(s.files[1], d.join("scene/models/deep/er/tri.obj"));
    assert!(s.limits.confine_files);

    let sky = d.join("sky.png");
    for (body, name) in [
        (
            "<emitter type=\"envmap\">\n  <string name=\"filename\" value=\"../sky.png\"/>\n</emitter>"
                .to_string(),
            "../sky.png".to_string(),
        ),
        (
            format!(
                "<texture type=\"bitmap\" id=\"t\">\n  <string name=\"filename\" value=\"{}\"/>\n</texture>",
                sky.display()
            ),
            sky.display().to_string(),
        ),
    ] {
        let p = assert_confined_fails(&d.join("scene"), &body, &[&name, "confine_files"]);
        load_scene(&p, &[]).unwrap();
    }
}

#[test]
fn confinement_reports_a_missing_file_by_name_and_line() {
    let d = temp_dir("confine-missing");
    assert_confined_fails(
        &d,
        &mesh_shape("obj", "models/gone.obj"),
        &["models/gone.obj", "No such file"],
    );
}

#[test]
fn confinement_is_off_by_default() {
    assert!(!Limits::default().confine_files);
}

#[test]
fn scene_files_opens_each_file_but_leaves_decoding_to_the_full_load() {
    let d = temp_dir("files-names");
    // A mesh whose contents are broken (only the full load reads them), and an image
    // (only its header is read).
    write(
        &d.join("bad.obj"),
        b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    );
    write_png(&d.join("sky.png"));
    let body = format!(
        "{}\n<emitter type=\"envmap\">\n  <string name=\"filename\" value=\"sky.png\"/>\n</emitter>",
        mesh_shape("obj", "bad.obj")
    );
    let (p, _) = write_scene_in(&d, &body);
    assert!(
        load_confined(&p).is_err(),
        "the full load reads the bad mesh"
    );
    assert_eq!(
        scene_files(&p, &[], &confined()).unwrap(),
        vec![p.clone(), d.join("bad.obj"), d.join("sky.png")]
    );
    // A missing file, the XML's mistakes and confinement are still errors at their line.
    let (p, xml) = write_scene_in(&d.join("missing"), &mesh_shape("ply", "gone.ply"));
    let err = scene_files(&p, &[], &confined()).unwrap_err();
    assert_invalid_at(
        &err,
        &p,
        line_of(&xml, "filename"),
        &["gone.ply", "cannot read"],
    );
    let (p, xml) = write_scene_in(&d.join("outside"), &mesh_shape("obj", "../bad.obj"));
    let err = scene_files(&p, &[], &confined()).unwrap_err();
    assert_invalid_at(&err, &p, line_of(&xml, "filename"), &["'..'"]);
    let (p, _) = write_scene_in(
        &d.join("typo"),
        "<shape type=\"cube\"><float name=\"radius\" value=\"x\"/></shape>",
    );
    assert!(
        scene_files(&p, &[], &confined()).is_err(),
        "a bad value is an error"
    );
}

#[test]
fn confinement_applies_to_includes_and_paths() {
    let d = temp_dir("confine-include");
    write(
        &d.join("scene/parts/ok.xml"),
        b"<scene version=\"3.0.0\"><shape type=\"sphere\"/></scene>",
    );
    write(
        &d.join("outside.xml"),
        b"<scene version=\"3.0.0\"><shape type=\"sphere\"/></scene>",
    );
    let (p, _) = write_scene_in(&d.join("scene"), r#"<include filename="parts/ok.xml"/>"#);
    let s = load_confined(&p).unwrap();
    assert_eq!(s.shapes.len(), 1);
    assert!(
        s.files.contains(&d.join("scene/parts/ok.xml")),
        "{:?}",
        s.files
    );
    let outside = d.join("outside.xml");
    for name in ["../outside.xml".to_string(), outside.display().to_string()] {
        let body = format!("<include filename=\"{name}\"/>");
        let p = assert_confined_fails(&d.join("scene"), &body, &[&name, "confine_files"]);
        load_scene(&p, &[]).unwrap();
    }
    // A <path> directory does not open a way out either.
    write_png(&d.join("tex/wood.png"));
    let body = "<path value=\"../tex\"/>\n<texture type=\"bitmap\" id=\"t\">\n  <string name=\"filename\" value=\"wood.png\"/>\n</texture>";
    let p = assert_confined_fails(&d.join("scene"), body, &["wood.png", "confine_files"]);
    load_scene(&p, &[]).unwrap();
}
