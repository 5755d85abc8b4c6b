//! Helpers for writing throw-away scenes under the system temp directory.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use pathfarm_scene::SceneError;

/// A fresh directory unique to this process and `name`.
pub fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("pathfarm-scene-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Write `xml` as `scene.xml` in a fresh directory; returns its path.
pub fn write_scene(name: &str, xml: &str) -> PathBuf {
    let d = temp_dir(name);
    let p = d.join("scene.xml");
    std::fs::write(&p, xml).unwrap();
    p
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
