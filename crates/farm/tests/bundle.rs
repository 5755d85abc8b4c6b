//! Scene bundles end to end: collect a scene, store its blobs, materialise them into another
//! directory and check the result loads to the same scene; manifests from the network that
//! are refused; errors that name the file at fault.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use pathfarm_farm::bundle::*;
use pathfarm_scene::{Geometry, Limits, SceneDesc};

/// A fresh directory under the system temp directory, removed when dropped (also when the
/// test panics).
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> Self {
        static N: AtomicUsize = AtomicUsize::new(0);
        let d = std::env::temp_dir().join(format!(
            "pathfarm-bundle-test-{}-{}-{name}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        Self(d)
    }

    fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn write(path: &Path, contents: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, contents).unwrap();
}

const TRI_OBJ: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
const QUAD_OBJ: &str = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n";

/// A scene with `body` (and a sensor) written to `dir/scene.xml`.
fn write_scene(dir: &Path, body: &str) -> PathBuf {
    let p = dir.join("scene.xml");
    write(
        &p,
        format!("<scene version=\"3.0.0\">\n<sensor type=\"perspective\"/>\n{body}\n</scene>\n")
            .as_bytes(),
    );
    p
}

fn mesh_shape(file: &str) -> String {
    format!("<shape type=\"obj\">\n  <string name=\"filename\" value=\"{file}\"/>\n</shape>")
}

/// A blob store in `dir`: each local file copied to `dir/<hex digest>`.
fn store_blobs(manifest: &Manifest, locals: &[PathBuf], dir: &Path) {
    std::fs::create_dir_all(dir).unwrap();
    for (e, local) in manifest.files.iter().zip(locals) {
        std::fs::copy(local, dir.join(e.digest.to_hex())).unwrap();
    }
}

/// The scene's contents, leaving out where it was loaded from (`source`, `files`, and the
/// paths inside warnings and locations).
fn assert_same_scene(a: &SceneDesc, b: &SceneDesc) {
    assert_eq!(a.integrator, b.integrator);
    assert_eq!(a.sensor, b.sensor);
    assert_eq!(a.bsdfs, b.bsdfs);
    assert_eq!(a.textures, b.textures);
    assert_eq!(a.emitters, b.emitters);
    assert_eq!(a.features, b.features);
    assert_eq!(a.warnings.len(), b.warnings.len());
    assert_eq!(a.shapes.len(), b.shapes.len());
    for (x, y) in a.shapes.iter().zip(&b.shapes) {
        assert_eq!((&x.id, x.bsdf, x.emitter), (&y.id, y.bsdf, y.emitter));
        assert_eq!(x.location.line, y.location.line);
        match (&x.geometry, &y.geometry) {
            (Geometry::Mesh(m), Geometry::Mesh(n)) => assert!(**m == **n, "meshes differ"),
            (g, h) => assert_eq!(format!("{g:?}"), format!("{h:?}")),
        }
    }
    assert_eq!(a.files.len(), b.files.len());
}

/// Collect `scene`, check the manifest, store its blobs, materialise it elsewhere and check
/// it: the same scene, read from the bundle directory only. Returns the manifest.
fn round_trip(scene: &Path) -> Manifest {
    let limits = Limits::default();
    let original = pathfarm_scene::load_scene_with_limits(scene, &[], &limits).unwrap();
    let (manifest, locals) = collect(scene, &[], None, &limits).unwrap();
    manifest.validate(&BundleLimits::default()).unwrap();
    assert_eq!(manifest.files.len(), locals.len());
    assert_eq!(manifest.root, manifest.files[0].path);
    assert_eq!(
        manifest.root,
        scene.file_name().unwrap().to_str().unwrap(),
        "the root is the scene file's name"
    );
    assert_eq!(locals, original.files, "one entry per file the loader read");
    for (e, local) in manifest.files.iter().zip(&locals) {
        let bytes = std::fs::read(local).unwrap();
        assert_eq!(e.size, bytes.len() as u64, "{}", e.path);
        assert_eq!(e.digest, digest_of(&bytes), "{}", e.path);
        assert_eq!(local, &scene.parent().unwrap().join(&e.path));
    }

    let work = TempDir::new("round-trip");
    let blobs = work.path().join("blobs");
    store_blobs(&manifest, &locals, &blobs);
    let dest = work.path().join("bundle");
    let root = materialize(&manifest, |d| blobs.join(d.to_hex()), &dest).unwrap();
    assert_eq!(root, dest.join(&manifest.root));
    for e in &manifest.files {
        assert_eq!(
            std::fs::read(dest.join(&e.path)).unwrap().len() as u64,
            e.size
        );
    }
    let checked = check(&manifest, &dest, &[], None, &limits, Decode::Everything).unwrap();
    assert_same_scene(&original, &checked);
    assert!(checked.files.iter().all(|f| f.starts_with(&dest)));
    assert_eq!(checked.source, root);
    manifest
}

#[test]
fn digest_hex_round_trips_and_bad_hex_is_refused() {
    // blake3 of the empty input.
    let empty = "af1349b9f5f9a1a6a0404dea36dcc9499bcb25c9adc112b7cc9a93cae41f3262";
    assert_eq!(digest_of(b"").to_hex(), empty);
    assert_eq!(Digest::from_hex(empty).unwrap(), digest_of(b""));
    assert_eq!(
        Digest::from_hex(&empty.to_uppercase()).unwrap(),
        digest_of(b"")
    );
    let d = digest_of(b"pathfarm");
    assert_eq!(Digest::from_hex(&d.to_hex()).unwrap(), d);
    assert_eq!(d.to_string(), d.to_hex());
    assert_ne!(d, digest_of(b"pathfarn"));
    for (bad, needle) in [
        ("", "0 characters"),
        (&empty[..63], "63 characters"),
        (&format!("{empty}0")[..], "65 characters"),
        (&format!("{}g", &empty[..63])[..], "position 63"),
        (&format!("x{}", &empty[1..])[..], "position 0"),
        (&format!("{}é", &empty[..62])[..], "position 62"),
    ] {
        let err = Digest::from_hex(bad).unwrap_err();
        assert!(matches!(err, BundleError::InvalidDigest { .. }), "{err:?}");
        assert!(err.to_string().contains(needle), "{err} lacks {needle:?}");
    }
}

#[test]
fn digest_file_streams_and_matches_digest_of() {
    let t = TempDir::new("digest-file");
    // Larger than the 64 KiB read buffer, not a multiple of it.
    let bytes: Vec<u8> = (0..200_003u32).map(|i| (i * 7 % 251) as u8).collect();
    write(&t.path().join("f"), &bytes);
    assert_eq!(
        digest_file(&t.path().join("f")).unwrap(),
        (digest_of(&bytes), bytes.len() as u64)
    );
    let err = digest_file(&t.path().join("missing")).unwrap_err();
    assert!(err.to_string().contains("missing"), "{err}");
}

fn entry(path: &str, size: u64) -> ManifestEntry {
    ManifestEntry {
        path: path.to_string(),
        digest: digest_of(path.as_bytes()),
        size,
    }
}

fn manifest(root: &str, files: &[(&str, u64)]) -> Manifest {
    Manifest {
        root: root.to_string(),
        files: files.iter().map(|&(p, s)| entry(p, s)).collect(),
    }
}

#[test]
fn validate_accepts_a_normal_manifest() {
    let m = manifest(
        "scene.xml",
        &[
            ("scene.xml", 100),
            ("models/a b.obj", 10),
            ("models/deep/x.ply", 0),
            ("textures/wood.png", 5),
            ("..x/...", 1),
        ],
    );
    m.validate(&BundleLimits::default()).unwrap();
    assert_eq!(m.total_bytes(), 116);
    assert_eq!(m.entry("models/a b.obj").unwrap().size, 10);
    assert!(m.entry("models").is_none());
}

#[test]
fn validate_refuses_bad_paths() {
    for (bad, needle) in [
        ("/etc/passwd", "absolute"),
        ("../x.obj", "'..'"),
        ("models/../../x.obj", "'..'"),
        ("models/..", "'..'"),
        ("./x.obj", "'.'"),
        ("models/./x.obj", "'.'"),
        ("models//x.obj", "empty component"),
        ("models/", "empty component"),
        ("", "is empty"),
        ("models\\x.obj", "backslash"),
        ("..\\x.obj", "backslash"),
        ("x\0.obj", "NUL"),
    ] {
        let m = manifest("scene.xml", &[("scene.xml", 1), (bad, 1)]);
        let err = m.validate(&BundleLimits::default()).unwrap_err();
        assert!(
            matches!(&err, BundleError::InvalidPath { path, .. } if path == bad),
            "{bad:?}: {err:?}"
        );
        assert!(err.to_string().contains(needle), "{err} lacks {needle:?}");
        // An invalid root is refused as a path too.
        let m = manifest(bad, &[(bad, 1)]);
        assert!(matches!(
            m.validate(&BundleLimits::default()).unwrap_err(),
            BundleError::InvalidPath { .. }
        ));
    }
}

#[test]
fn validate_refuses_duplicates_missing_root_and_file_directory_clashes() {
    let limits = BundleLimits::default();
    let m = manifest("scene.xml", &[("scene.xml", 1), ("a.obj", 1), ("a.obj", 2)]);
    let err = m.validate(&limits).unwrap_err();
    assert!(
        matches!(&err, BundleError::DuplicatePath { path } if path == "a.obj"),
        "{err:?}"
    );
    assert!(err.to_string().contains("\"a.obj\""), "{err}");

    let m = manifest("main.xml", &[("scene.xml", 1), ("a.obj", 1)]);
    let err = m.validate(&limits).unwrap_err();
    assert!(
        matches!(&err, BundleError::RootMissing { root } if root == "main.xml"),
        "{err:?}"
    );
    assert!(manifest("scene.xml", &[]).validate(&limits).is_err());

    let m = manifest(
        "scene.xml",
        &[("scene.xml", 1), ("models", 1), ("models/a.obj", 1)],
    );
    let err = m.validate(&limits).unwrap_err();
    assert!(
        matches!(&err, BundleError::FileAndDirectory { path, other } if path == "models" && other == "models/a.obj"),
        "{err:?}"
    );
}

#[test]
fn validate_refuses_what_exceeds_the_limits() {
    let limits = BundleLimits {
        max_files: 3,
        max_total_bytes: 1000,
        max_file_bytes: 600,
    };
    let ok = manifest("scene.xml", &[("scene.xml", 100), ("a", 600), ("b", 300)]);
    ok.validate(&limits).unwrap();

    let m = manifest("scene.xml", &[("scene.xml", 100), ("a", 601)]);
    let err = m.validate(&limits).unwrap_err();
    assert!(
        matches!(&err, BundleError::FileTooLarge { path, size: 601, max: 600 } if path == "a"),
        "{err:?}"
    );
    assert!(err.to_string().contains("max_file_bytes"), "{err}");

    let m = manifest("scene.xml", &[("scene.xml", 500), ("a", 500), ("b", 1)]);
    let err = m.validate(&limits).unwrap_err();
    assert!(
        matches!(err, BundleError::TotalTooLarge { max: 1000, .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("max_total_bytes"), "{err}");

    // Sizes that would overflow a sum.
    let m = manifest(
        "scene.xml",
        &[("scene.xml", 1), ("a", u64::MAX), ("b", u64::MAX)],
    );
    let huge = BundleLimits {
        max_file_bytes: u64::MAX,
        ..limits.clone()
    };
    assert!(matches!(
        m.validate(&huge).unwrap_err(),
        BundleError::TotalTooLarge { .. }
    ));

    let m = manifest(
        "scene.xml",
        &[("scene.xml", 1), ("a", 1), ("b", 1), ("c", 1)],
    );
    let err = m.validate(&limits).unwrap_err();
    assert!(
        matches!(err, BundleError::TooManyFiles { count: 4, max: 3 }),
        "{err:?}"
    );
}

#[test]
fn bundle_limits_defaults() {
    let d = BundleLimits::default();
    assert_eq!(d.max_files, 10_000);
    assert_eq!(d.max_total_bytes, 4 << 30);
    assert!(d.max_file_bytes >= Limits::default().max_scene_file_bytes);
    assert!(d.max_file_bytes <= d.max_total_bytes);
}

#[test]
fn shipped_scenes_round_trip() {
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes");
    let mut n = 0;
    for dir in std::fs::read_dir(&scenes).unwrap() {
        let scene = dir.unwrap().path().join("scene.xml");
        if scene.is_file() {
            let m = round_trip(&scene);
            println!("{}: {} files", scene.display(), m.files.len());
            n += 1;
        }
    }
    assert!(n >= 4, "found {n} shipped scenes");
    // door-ajar has a mesh, materials a texture.
    let m = round_trip(&scenes.join("door-ajar/scene.xml"));
    assert!(m.entry("icosphere.obj").is_some(), "{m:?}");
    let m = round_trip(&scenes.join("materials/scene.xml"));
    assert!(m.entry("texture.png").is_some(), "{m:?}");
}

#[test]
fn shared_cornell_box_round_trips() {
    let m = round_trip(Path::new("/work/shared/scenes/cornell-box/scene.xml"));
    assert_eq!(m.root, "scene.xml");
}

#[test]
fn shared_veach_ajar_round_trips_with_its_meshes_and_textures() {
    let m = round_trip(Path::new("/work/shared/scenes/veach-ajar/scene.xml"));
    let paths: Vec<&str> = m.files.iter().map(|e| e.path.as_str()).collect();
    assert!(paths.contains(&"models/Mesh000.ply"), "{paths:?}");
    assert!(paths.contains(&"models/Mesh016.obj"), "{paths:?}");
    assert!(
        paths.contains(&"textures/Good Textures_005844.jpg"),
        "{paths:?}"
    );
    // The scene file, 17 meshes (Mesh000.ply referenced three times, listed once), 3 textures.
    assert_eq!(m.files.len(), 21, "{paths:?}");
}

#[test]
fn collect_refuses_a_scene_that_refers_outside_its_directory() {
    let t = TempDir::new("collect-outside");
    write(&t.path().join("x.obj"), TRI_OBJ.as_bytes());
    let abs = t.path().join("x.obj");
    for name in ["../x.obj", abs.to_str().unwrap()] {
        let scene = write_scene(&t.path().join("scene"), &mesh_shape(name));
        let err = collect(&scene, &[], None, &Limits::default()).unwrap_err();
        let shown = err.to_string();
        assert!(matches!(err, BundleError::Collect { .. }), "{err:?}");
        for needle in [
            "cannot bundle",
            &scene.display().to_string(),
            name,
            "confined to the scene file's directory",
        ] {
            assert!(shown.contains(needle), "{shown} lacks {needle:?}");
        }
        // The default loader takes it.
        pathfarm_scene::load_scene(&scene, &[]).unwrap();
    }
}

#[test]
fn collect_lists_a_file_once_and_paths_relative_to_the_scene() {
    let t = TempDir::new("collect-dedup");
    write(&t.path().join("s/models/a.obj"), TRI_OBJ.as_bytes());
    let body = format!(
        "{}\n{}",
        mesh_shape("models/a.obj"),
        mesh_shape("./models/a.obj")
    );
    let scene = write_scene(&t.path().join("s"), &body);
    let (m, locals) = collect(&scene, &[], None, &Limits::default()).unwrap();
    let paths: Vec<&str> = m.files.iter().map(|e| e.path.as_str()).collect();
    assert_eq!(paths, ["scene.xml", "models/a.obj"]);
    assert_eq!(locals.len(), 2);
    assert_eq!(m.files[1].digest, digest_of(TRI_OBJ.as_bytes()));
}

/// A two-mesh scene collected, its blobs stored: (temp dir, manifest, blob dir).
fn two_mesh_bundle(name: &str) -> (TempDir, Manifest, PathBuf) {
    let t = TempDir::new(name);
    let src = t.path().join("src");
    write(&src.join("models/a.obj"), TRI_OBJ.as_bytes());
    write(&src.join("models/b.obj"), QUAD_OBJ.as_bytes());
    let scene = write_scene(
        &src,
        &format!(
            "{}\n{}",
            mesh_shape("models/a.obj"),
            mesh_shape("models/b.obj")
        ),
    );
    let (m, locals) = collect(&scene, &[], None, &Limits::default()).unwrap();
    let blobs = t.path().join("blobs");
    store_blobs(&m, &locals, &blobs);
    (t, m, blobs)
}

#[test]
fn check_names_a_referenced_file_missing_from_the_bundle() {
    let (t, mut m, blobs) = two_mesh_bundle("check-missing");
    m.files.retain(|e| e.path != "models/b.obj");
    m.validate(&BundleLimits::default()).unwrap();
    let dest = t.path().join("bundle");
    let root = materialize(&m, |d| blobs.join(d.to_hex()), &dest).unwrap();
    let err = check(&m, &dest, &[], None, &Limits::default(), Decode::Everything).unwrap_err();
    let shown = err.to_string();
    assert!(matches!(err, BundleError::Scene(_)), "{err:?}");
    // The scene file and the line of the filename, and the missing name.
    assert!(shown.contains(&format!("{}:7:", root.display())), "{shown}");
    assert!(shown.contains("models/b.obj"), "{shown}");
}

#[test]
fn check_refuses_a_file_read_that_the_manifest_does_not_list() {
    let (t, m, blobs) = two_mesh_bundle("check-unlisted");
    let dest = t.path().join("bundle");
    materialize(&m, |d| blobs.join(d.to_hex()), &dest).unwrap();
    check(&m, &dest, &[], None, &Limits::default(), Decode::Everything).unwrap();
    // The directory has the file, but the manifest checked against it does not.
    let mut short = m.clone();
    short.files.retain(|e| e.path != "models/a.obj");
    let err = check(
        &short,
        &dest,
        &[],
        None,
        &Limits::default(),
        Decode::Everything,
    )
    .unwrap_err();
    assert!(
        matches!(&err, BundleError::NotInManifest { file } if file == &dest.join("models/a.obj")),
        "{err:?}"
    );
    // A file that changed size after materialising.
    write(
        &dest.join("models/b.obj"),
        format!("{QUAD_OBJ}\n").as_bytes(),
    );
    let err = check(&m, &dest, &[], None, &Limits::default(), Decode::Everything).unwrap_err();
    assert!(
        matches!(&err, BundleError::SizeMismatch { path, .. } if path == "models/b.obj"),
        "{err:?}"
    );
}

#[test]
fn materialize_verifies_blob_sizes() {
    let (t, mut m, blobs) = two_mesh_bundle("materialize-size");
    let e = m
        .files
        .iter_mut()
        .find(|e| e.path == "models/b.obj")
        .unwrap();
    e.size += 1;
    let dest = t.path().join("bundle");
    let err = materialize(&m, |d| blobs.join(d.to_hex()), &dest).unwrap_err();
    assert!(
        matches!(&err, BundleError::SizeMismatch { path, .. } if path == "models/b.obj"),
        "{err:?}"
    );
    assert!(!dest.join("models/b.obj").exists());
    // A missing blob names its path.
    let (t, m, _) = two_mesh_bundle("materialize-missing-blob");
    let empty = t.path().join("no-blobs");
    let err = materialize(&m, |d| empty.join(d.to_hex()), &t.path().join("b")).unwrap_err();
    assert!(
        err.to_string().contains(&m.files[0].digest.to_hex()),
        "{err}"
    );
}

#[test]
fn materialize_copies_when_it_cannot_link() {
    // A blob reached through a symbolic link is copied (linking would link the symlink).
    let (t, m, blobs) = two_mesh_bundle("materialize-copy");
    let links = t.path().join("links");
    std::fs::create_dir_all(&links).unwrap();
    for e in &m.files {
        std::os::unix::fs::symlink(blobs.join(e.digest.to_hex()), links.join(e.digest.to_hex()))
            .unwrap();
    }
    let dest = t.path().join("bundle");
    materialize(&m, |d| links.join(d.to_hex()), &dest).unwrap();
    for e in &m.files {
        let meta = std::fs::symlink_metadata(dest.join(&e.path)).unwrap();
        assert!(meta.file_type().is_file(), "{}", e.path);
        assert_eq!(meta.len(), e.size);
    }
    check(&m, &dest, &[], None, &Limits::default(), Decode::Everything).unwrap();
}

#[test]
fn materialize_never_writes_outside_dest() {
    let (t, m, blobs) = two_mesh_bundle("materialize-outside");
    let outside = t.path().join("outside");
    std::fs::create_dir_all(&outside).unwrap();
    let blob = |d: &Digest| blobs.join(d.to_hex());

    // An invalid path is refused before anything is written, validated or not.
    let mut evil = m.clone();
    evil.files.push(ManifestEntry {
        path: "../outside/x.obj".into(),
        ..m.files[1].clone()
    });
    let dest = t.path().join("bundle1");
    let err = materialize(&evil, blob, &dest).unwrap_err();
    assert!(matches!(err, BundleError::InvalidPath { .. }), "{err:?}");
    let mut abs = m.clone();
    abs.files[1].path = outside.join("x.obj").to_str().unwrap().to_string();
    assert!(matches!(
        materialize(&abs, blob, &dest).unwrap_err(),
        BundleError::InvalidPath { .. }
    ));

    // A symbolic link in the destination where a directory goes.
    let dest = t.path().join("bundle2");
    std::fs::create_dir_all(&dest).unwrap();
    std::os::unix::fs::symlink(&outside, dest.join("models")).unwrap();
    let err = materialize(&m, blob, &dest).unwrap_err();
    assert!(
        matches!(&err, BundleError::Conflict { file, .. } if file == &dest.join("models")),
        "{err:?}"
    );
    assert!(err.to_string().contains("symbolic link"), "{err}");

    // A symbolic link where a file goes is not written through.
    let dest = t.path().join("bundle3");
    std::fs::create_dir_all(&dest).unwrap();
    std::os::unix::fs::symlink(outside.join("scene.xml"), dest.join("scene.xml")).unwrap();
    let err = materialize(&m, blob, &dest).unwrap_err();
    assert!(
        matches!(&err, BundleError::Conflict { file, .. } if file == &dest.join("scene.xml")),
        "{err:?}"
    );
    assert_eq!(std::fs::read_dir(&outside).unwrap().count(), 0);

    // Materialising twice into the same directory does not overwrite.
    let dest = t.path().join("bundle4");
    materialize(&m, blob, &dest).unwrap();
    assert!(matches!(
        materialize(&m, blob, &dest).unwrap_err(),
        BundleError::Conflict { .. }
    ));
}
