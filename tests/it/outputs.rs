//! Outputs: pathfarm replaces only files the user named or that it wrote itself,
//! checks its outputs before the work, and leaves no half-written or temporary
//! file behind, on an error, on Ctrl-C, and even on SIGKILL (where the file
//! system has O_TMPFILE).
//!
//! `PATHFARM_TEST_BIN=/path/to/pathfarm` runs these tests against another
//! binary (e.g. an older one, to see them fail).

use std::fs;
use std::os::unix::process::ExitStatusExt;
use std::path::{Path, PathBuf};

use std::time::{Duration, Instant};

use pathfarm_render::output::{is_pathfarm_preview, read_exr_rgb};

use crate::common::*;

fn run(args: &[&str], timeout: Duration) -> Ended {
    Running::start(args, &[]).wait(timeout)
}

/// [`run`] within [`QUICK`], asserting that it succeeded.
fn run_ok(args: &[&str]) {
    let r = run(args, QUICK);
    assert!(r.status.success(), "{args:?}: {}", r.describe());
}

/// Everything under `dir`: relative paths, sorted, with each file's bytes (None for
/// a directory).
fn snapshot(dir: &Path) -> Vec<(String, Option<Vec<u8>>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(String, Option<Vec<u8>>)>) {
        for e in fs::read_dir(d).expect("read_dir") {
            let p = e.expect("entry").path();
            let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
            if p.is_dir() {
                out.push((rel, None));
                walk(root, &p, out);
            } else {
                out.push((rel, Some(fs::read(&p).expect("read"))));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

fn names(dir: &Path) -> Vec<String> {
    snapshot(dir).into_iter().map(|(n, _)| n).collect()
}

/// A small scene (furnace objects in a constant environment) in a fresh directory: the
/// scene file and the directory.
fn scene_in_dir(tag: &str, size: u32) -> (PathBuf, PathBuf) {
    let xml = scene_xml(
        size,
        size,
        40.0,
        4.0,
        r#"<integrator type="path"/>"#,
        FURNACE_BODY,
    );
    let scene = write_scene(tag, &xml);
    let dir = scene.parent().unwrap().to_path_buf();
    (scene, dir)
}

/// A real PNG that pathfarm did not write (no `Software` = `pathfarm` chunk).
fn foreign_png() -> Vec<u8> {
    let mut bytes = Vec::new();
    image::ImageEncoder::write_image(
        image::codecs::png::PngEncoder::new(&mut bytes),
        &[200u8; 4 * 4 * 3],
        4,
        4,
        image::ExtendedColorType::Rgb8,
    )
    .expect("encode png");
    bytes
}

/// A run that was refused before any work: failed, printed no summary, never loaded
/// the scene (the "loaded" log line), and named `path` in its one-line reason.
fn assert_refused_early(run: &Ended, path: &Path) {
    let what = run.describe();
    assert!(!run.status.success(), "expected a failure: {what}");
    assert!(!run.stdout.contains("summary:"), "it rendered: {what}");
    assert!(
        !run.stderr.contains("loaded ") && !run.stderr.contains("iteration "),
        "it read the scene before refusing: {what}"
    );
    assert!(
        run.stderr.contains(path_str(path)),
        "the message names {path:?}: {what}"
    );
    assert!(
        run.stderr.matches("(os error").count() <= 1,
        "the OS reason is given once: {what}"
    );
    assert!(!run.stderr.contains("panicked"), "{what}");
}

const QUICK: Duration = Duration::from_secs(60);
/// For runs that would render for `--time 20` if the outputs were not checked first.
const LONG: Duration = Duration::from_secs(120);

#[test]
fn preview_never_replaces_a_png_that_pathfarm_did_not_write() {
    let (scene, dir) = scene_in_dir("outputs-foreign", 16);
    // The scene's own texture.png (a real PNG) and a junk.png that is no PNG at all.
    fs::write(dir.join("texture.png"), foreign_png()).unwrap();
    fs::write(dir.join("junk.png"), b"not a png, and not pathfarm's").unwrap();
    for stem in ["texture", "junk"] {
        let before = snapshot(&dir);
        let exr = dir.join(format!("{stem}.exr"));
        let png = dir.join(format!("{stem}.png"));
        let r = run(&render_args(&scene, &exr, &["--time", "20"]), LONG);
        assert_refused_early(&r, &png);
        assert!(
            r.stderr.contains("--preview") && r.stderr.contains("--no-png"),
            "the message says how to proceed: {}",
            r.describe()
        );
        assert_eq!(snapshot(&dir), before, "the directory changed");
    }
    // Named elsewhere, or not written at all, the preview leaves texture.png alone.
    let exr = dir.join("texture.exr");
    let other = dir.join("preview.png");
    run_ok(&render_args(
        &scene,
        &exr,
        &["--spp", "1", "--preview", path_str(&other)],
    ));
    assert!(is_pathfarm_preview(&other));
    assert_eq!(fs::read(dir.join("texture.png")).unwrap(), foreign_png());
    run_ok(&render_args(
        &scene,
        &dir.join("junk.exr"),
        &["--spp", "1", "--no-png"],
    ));
    assert_eq!(
        fs::read(dir.join("junk.png")).unwrap(),
        b"not a png, and not pathfarm's"
    );
    assert_eq!(
        names(&dir),
        [
            "junk.exr",
            "junk.png",
            "preview.png",
            "scene.xml",
            "texture.exr",
            "texture.png"
        ]
    );
}

#[test]
fn preview_written_by_pathfarm_is_replaced_on_rerender() {
    let (scene, dir) = scene_in_dir("outputs-rerender", 16);
    let exr = dir.join("out.exr");
    let png = dir.join("out.png");
    let mut previews = Vec::new();
    for seed in ["1", "2"] {
        run_ok(&render_args(&scene, &exr, &["--spp", "1", "--seed", seed]));
        assert!(
            is_pathfarm_preview(&png),
            "the preview carries pathfarm's mark"
        );
        let (w, h, _) = read_exr_rgb(&exr).expect("the EXR reads back");
        assert_eq!((w, h), (16, 16));
        previews.push(fs::read(&png).unwrap());
    }
    assert_ne!(
        previews[0], previews[1],
        "the second render replaced the preview"
    );
    assert_eq!(names(&dir), ["out.exr", "out.png", "scene.xml"]);
}

#[test]
fn guide_outputs_leave_unrelated_tmp_files_alone() {
    let (scene, dir) = scene_in_dir("outputs-guide", 16);
    let unrelated = [
        ("tree.tmp", b"someone's tree.tmp".as_slice()),
        ("quad.tmp.png", b"someone's quad.tmp.png".as_slice()),
        ("scatter.tmp.png", b"someone's scatter.tmp.png".as_slice()),
    ];
    for (n, b) in unrelated {
        fs::write(dir.join(n), b).unwrap();
    }
    let tree = dir.join("tree.sdt");
    run_ok(&guide_train_args(&scene, &tree, "4"));
    let quad = dir.join("quad.png");
    run_ok(&guide_show_args(&tree, "0,0,0", &quad, "32"));
    let scatter = dir.join("scatter.png");
    run_ok(&guide_scatter_args(
        &scene, &tree, "8,8", &scatter, "32", "1000",
    ));
    for (n, b) in unrelated {
        assert_eq!(
            fs::read(dir.join(n)).ok().as_deref(),
            Some(b),
            "{n} changed"
        );
    }
    assert_eq!(
        names(&dir),
        [
            "quad.png",
            "quad.tmp.png",
            "scatter.png",
            "scatter.tmp.png",
            "scene.xml",
            "tree.sdt",
            "tree.tmp"
        ]
    );
}

#[test]
fn outputs_that_cannot_be_written_are_refused_before_rendering() {
    let (scene, dir) = scene_in_dir("outputs-unwritable", 16);
    fs::create_dir(dir.join("folder.exr")).unwrap();
    fs::write(dir.join("file.txt"), b"a regular file").unwrap();
    fs::create_dir(dir.join("blocked.png")).unwrap();
    let before = snapshot(&dir);
    let folder = dir.join("folder.exr");
    let under_file = dir.join("file.txt/child.exr");
    let blocked = dir.join("blocked.exr");
    let tree_under_file = dir.join("file.txt/tree.sdt");
    let cases: Vec<(Vec<&str>, &Path)> = vec![
        // -o is a directory.
        (render_args(&scene, &folder, &["--time", "20"]), &folder),
        // -o is under a regular file.
        (
            render_args(&scene, &under_file, &["--time", "20"]),
            Path::new("file.txt"),
        ),
        // The preview (blocked.png) is a directory: no EXR may be left either.
        (
            render_args(&scene, &blocked, &["--time", "20"]),
            Path::new("blocked.png"),
        ),
        // guide train -o under a regular file.
        (
            guide_train_args(&scene, &tree_under_file, "100000"),
            Path::new("file.txt"),
        ),
    ];
    for (args, named) in &cases {
        let r = run(args, LONG);
        assert_refused_early(&r, named);
        assert_eq!(snapshot(&dir), before, "{args:?} changed the directory");
    }
}

/// Whether `dir`'s file system has O_TMPFILE (else a kill -9 can leave the named
/// temporary behind, which nothing can prevent).
fn has_o_tmpfile(dir: &Path) -> bool {
    let c = std::ffi::CString::new(path_str(dir)).unwrap();
    // SAFETY: a valid path; the descriptor is closed at once.
    unsafe {
        let fd = libc::open(c.as_ptr(), libc::O_TMPFILE | libc::O_WRONLY, 0o600);
        if fd >= 0 {
            libc::close(fd);
        }
        fd >= 0
    }
}

/// Starts a long render (`--time 30`) writing to `out`, sends `sig` after a second,
/// and returns how it ended.
fn interrupt_render(scene: &Path, out: &Path, sig: libc::c_int, env: &[(&str, &str)]) -> Ended {
    let mut child = Running::start(
        &render_args(scene, out, &["--time", "30", "--threads", "1"]),
        env,
    );
    std::thread::sleep(Duration::from_secs(1));
    assert!(child.poll().is_none(), "the render ended early");
    child.signal(sig);
    child.wait(QUICK)
}

/// Renders a large image (so writing it takes a while), sends `sig` the moment any
/// new entry shows up in the scene's directory, and checks that no temporary or
/// partial file is left: at most the complete outputs. Returns the names left.
fn signal_while_writing(tag: &str, sig: libc::c_int) -> Vec<String> {
    let (scene, dir) = scene_in_dir(tag, 1024);
    let exr = dir.join("out.exr");
    let mut child = Running::start(&render_args(&scene, &exr, &["--spp", "1", "--aovs"]), &[]);
    let t0 = Instant::now();
    loop {
        if child.poll().is_some() {
            break;
        }
        if fs::read_dir(&dir).unwrap().count() > 1 {
            child.signal(sig);
            break;
        }
        assert!(t0.elapsed() < LONG, "the render did not end");
        std::thread::sleep(Duration::from_millis(1));
    }
    let r = child.wait(QUICK);
    let left = names(&dir);
    eprintln!("{tag}: {:?} left {left:?}", r.status);
    for n in &left {
        assert!(
            ["scene.xml", "out.exr", "out.png"].contains(&n.as_str()),
            "{n} was left behind: {left:?}; {}",
            r.describe()
        );
    }
    if left.iter().any(|n| n == "out.exr") {
        let (w, h, _) = read_exr_rgb(&exr).expect("a complete EXR");
        assert_eq!((w, h), (1024, 1024));
    }
    if left.iter().any(|n| n == "out.png") {
        assert!(is_pathfarm_preview(&dir.join("out.png")));
        let img = image::open(dir.join("out.png")).expect("a complete PNG");
        assert_eq!((img.width(), img.height()), (1024, 1024));
    }
    left
}

#[test]
fn interrupting_a_render_leaves_no_temporary_or_partial_file() {
    let (scene, dir) = scene_in_dir("outputs-sigint", 8);
    // With O_TMPFILE and with the named fallback; into directories the output creates;
    // and over outputs of an earlier run, which stay as they were.
    for env in [&[][..], &[("PATHFARM_NO_O_TMPFILE", "1")][..]] {
        for out in ["new/deeper/out.exr", "out.exr"] {
            let before = snapshot(&dir);
            let r = interrupt_render(&scene, &dir.join(out), libc::SIGINT, env);
            assert_eq!(r.status.signal(), Some(libc::SIGINT), "{}", r.describe());
            assert_eq!(snapshot(&dir), before, "{env:?} {out}: {}", r.describe());
        }
        if !dir.join("out.exr").exists() {
            run_ok(&render_args(&scene, &dir.join("out.exr"), &[]));
        }
    }
    // Interrupted while writing, the outputs are written together or not at all.
    let left = signal_while_writing("outputs-sigint-writing", libc::SIGINT);
    assert!(
        left.contains(&"out.exr".to_string()) == left.contains(&"out.png".to_string()),
        "one output without the other: {left:?}"
    );
}

#[test]
fn killing_a_render_leaves_no_temporary_file() {
    let (scene, dir) = scene_in_dir("outputs-sigkill", 8);
    if has_o_tmpfile(&dir) {
        let before = snapshot(&dir);
        let r = interrupt_render(&scene, &dir.join("out.exr"), libc::SIGKILL, &[]);
        assert_eq!(r.status.signal(), Some(libc::SIGKILL), "{}", r.describe());
        assert_eq!(snapshot(&dir), before, "{}", r.describe());
    } else {
        eprintln!(
            "{}: no O_TMPFILE here; a kill -9 during a render may leave a temporary",
            dir.display()
        );
        return;
    }
    signal_while_writing("outputs-sigkill-writing", libc::SIGKILL);
}

/// A log written to a file is plain text (no ANSI colour codes, whether or not NO_COLOR is
/// set), and `render` names the scene's effects in words: the furnace scene's constant
/// environment, its spheres, its glass.
#[test]
fn a_log_to_a_file_is_plain_text_and_names_the_scenes_effects_in_words() {
    let (scene, dir) = scene_in_dir("outputs-plain-log", 8);
    let exr = dir.join("plain.exr");
    for no_color in ["", "1"] {
        let args = render_args(&scene, &exr, &["--spp", "1"]);
        let r = Running::start(&args, &[("NO_COLOR", no_color)]).wait(QUICK);
        assert!(r.status.success(), "{}", r.describe());
        assert!(
            !r.stderr.contains('\x1b'),
            "NO_COLOR={no_color:?}: colour codes in a log to a file:\n{}",
            r.stderr
        );
        let line = (r.stderr.lines())
            .find(|l| l.contains("effects: "))
            .unwrap_or_else(|| panic!("no effects line:\n{}", r.stderr));
        for word in ["environment light", "transmission", "analytic shapes"] {
            assert!(line.contains(word), "{word} missing from {line}");
        }
        assert!(!line.contains("Features {"), "a debug dump: {line}");
    }
}
