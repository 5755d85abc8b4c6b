//! Helpers for writing throw-away scenes under the system temp directory.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use pathfarm_scene::{load_scene, SceneError};

/// A directory the test made, removed with what it holds when this is dropped (at the end
/// of the test, passed or failed).
pub struct TempDir(PathBuf);

impl std::ops::Deref for TempDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for TempDir {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A file in a [`TempDir`] of its own, removed with it.
pub struct TempFile {
    path: PathBuf,
    _dir: TempDir,
}

impl std::ops::Deref for TempFile {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.path
    }
}

impl AsRef<Path> for TempFile {
    fn as_ref(&self) -> &Path {
        &self.path
    }
}

/// A fresh directory unique to this process and `name`.
pub fn temp_dir(name: &str) -> TempDir {
    let d = std::env::temp_dir().join(format!("pathfarm-scene-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    TempDir(d)
}

/// Write `xml` as `scene.xml` in a fresh directory; the scene file, removed with its directory
/// when dropped.
pub fn write_scene(name: &str, xml: &str) -> TempFile {
    let dir = temp_dir(name);
    TempFile {
        path: write_xml_in(&dir, xml),
        _dir: dir,
    }
}

/// Write `xml` as `dir/scene.xml` (creating `dir`); returns its path.
pub fn write_xml_in(dir: &Path, xml: &str) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let p = dir.join("scene.xml");
    std::fs::write(&p, xml).unwrap();
    p
}

/// `scene(body)` written as `dir/scene.xml` (creating `dir`); returns its path and text.
pub fn write_scene_in(dir: &Path, body: &str) -> (PathBuf, String) {
    let xml = scene(body);
    (write_xml_in(dir, &xml), xml)
}

/// A shape of plugin `kind` (obj or ply) loading `file`.
pub fn mesh_shape(kind: &str, file: &str) -> String {
    mesh_shape_with(kind, file, "")
}

/// [`mesh_shape`] with `extra` (e.g. a transform) after the filename.
pub fn mesh_shape_with(kind: &str, file: &str, extra: &str) -> String {
    format!(
        "<shape type=\"{kind}\">\n  <string name=\"filename\" value=\"{file}\"/>{extra}\n</shape>"
    )
}

/// A scene in a fresh directory `name` with one `kind` shape loading `file` (written with
/// `contents`); returns the scene path, its text and the mesh path.
pub fn mesh_scene(
    name: &str,
    kind: &str,
    file: &str,
    contents: &[u8],
) -> (TempFile, String, PathBuf) {
    mesh_scene_with(name, kind, file, contents, "")
}

/// [`mesh_scene`] with `extra` inside the shape after the filename.
pub fn mesh_scene_with(
    name: &str,
    kind: &str,
    file: &str,
    contents: &[u8],
    extra: &str,
) -> (TempFile, String, PathBuf) {
    let xml = scene(&mesh_shape_with(kind, file, extra));
    let p = write_scene(name, &xml);
    let mesh = p.parent().unwrap().join(file);
    std::fs::write(&mesh, contents).unwrap();
    (p, xml, mesh)
}

/// 1-based line of the first line of `text` containing `needle`.
pub fn line_of(text: &str, needle: &str) -> u32 {
    text.lines()
        .position(|l| l.contains(needle))
        .expect("needle in text") as u32
        + 1
}

/// Minimal scene wrapper: a sensor plus `body`.
pub fn scene(body: &str) -> String {
    format!("<scene version=\"3.0.0\">\n<sensor type=\"perspective\"/>\n{body}\n</scene>\n")
}

/// Assert `err` is `Invalid` at `file`:`line` and that its message contains
/// every string in `needles`; the Display form must name file and line.
pub fn assert_invalid_at(err: &SceneError, file: &Path, line: u32, needles: &[&str]) {
    let shown = err.to_string();
    match err {
        SceneError::Invalid {
            file: f,
            line: l,
            message,
        } => {
            assert_eq!(f, file, "wrong file in {shown}");
            assert_eq!(*l, line, "wrong line in {shown}");
            for n in needles {
                assert!(message.contains(n), "message {message:?} lacks {n:?}");
            }
        }
        other => panic!("expected Invalid, got {other:?}"),
    }
    assert!(
        shown.contains(&format!("{}:{line}", file.display())),
        "{shown}"
    );
}

/// Load `p` (whose text is `xml`) expecting an `Invalid` error at the first line of `xml`
/// containing `at` whose message contains every string in `needles` ([`assert_invalid_at`]);
/// returns the error for further checks.
pub fn assert_load_fails_at(p: &Path, xml: &str, at: &str, needles: &[&str]) -> SceneError {
    let err = load_scene(p, &[]).unwrap_err();
    assert_invalid_at(&err, p, line_of(xml, at), needles);
    err
}

/// Run `check` on each case of a table-driven test, `name` naming it. Every case runs even
/// when an earlier one fails (its panic message is printed as it happens, followed by the
/// case's name); the test then fails naming all the cases that failed.
pub fn check_cases<C>(
    cases: impl IntoIterator<Item = C>,
    name: impl Fn(&C) -> String,
    check: impl Fn(C),
) {
    let mut failed = Vec::new();
    for case in cases {
        let case_name = name(&case);
        let run = std::panic::AssertUnwindSafe(|| check(case));
        if std::panic::catch_unwind(run).is_err() {
            eprintln!("(that was case {case_name:?})");
            failed.push(case_name);
        }
    }
    assert!(failed.is_empty(), "failed cases: {failed:?}");
}
