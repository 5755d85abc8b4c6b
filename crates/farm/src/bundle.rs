//! Scene bundles: a scene file and every file it reads (meshes, textures, environment maps),
//! content-addressed by blake3 [`Digest`].
//!
//! The flow:
//!
//! * the client [`collect`]s a bundle: it loads the scene once with
//!   [`Limits::confine_files`] (so a scene that reads a file outside its own directory is
//!   refused: the bundle must be self-contained) and lists each file the loader read in a
//!   [`Manifest`], by its path relative to the scene's directory, with its digest and size;
//! * the coordinator takes the manifest from the network (untrusted) and
//!   [`Manifest::validate`]s it against its [`BundleLimits`] before it accepts any blob;
//! * a worker (and the coordinator, before it stores a job) [`materialize`]s the bundle from
//!   its blob store into a fresh directory and [`check`]s it: loads the scene from there,
//!   confined to that directory, and verifies that every file the loader read is one of the
//!   manifest's.
//!
//! Manifest paths are relative, `/`-separated and normalised (see [`validate_path`]), so a
//! path joined to the bundle directory always stays inside it.

use std::collections::{HashMap, HashSet};
use std::fmt;
use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Component, Path, PathBuf};

use pathfarm_scene::limits::format_bytes;
use pathfarm_scene::{
    load_scene_as, load_scene_geometry_as, scan_scene_as, scene_files_as, world_source, Limits,
    SceneDesc, SceneError,
};

/// The blake3 digest (32 bytes) of a file's contents: the name of its blob.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Digest(pub [u8; 32]);

impl Digest {
    /// Lower-case hexadecimal, 64 characters.
    pub fn to_hex(&self) -> String {
        const HEX: &[u8; 16] = b"0123456789abcdef";
        let mut s = String::with_capacity(64);
        for b in self.0 {
            s.push(HEX[(b >> 4) as usize] as char);
            s.push(HEX[(b & 15) as usize] as char);
        }
        s
    }

    /// Parse 64 hexadecimal characters (either case); anything else is
    /// [`BundleError::InvalidDigest`].
    pub fn from_hex(text: &str) -> Result<Self, BundleError> {
        let bad = |reason: String| BundleError::InvalidDigest {
            // Untrusted text: quote at most a digest's worth of it.
            text: text.chars().take(80).collect(),
            reason,
        };
        if text.len() != 64 {
            return Err(bad(format!(
                "{} characters, a digest has 64 hexadecimal digits",
                text.len()
            )));
        }
        let digit = |c: u8| match c {
            b'0'..=b'9' => Some(c - b'0'),
            b'a'..=b'f' => Some(c - b'a' + 10),
            b'A'..=b'F' => Some(c - b'A' + 10),
            _ => None,
        };
        let mut out = [0u8; 32];
        for (i, pair) in text.as_bytes().chunks_exact(2).enumerate() {
            match (digit(pair[0]), digit(pair[1])) {
                (Some(hi), Some(lo)) => out[i] = hi << 4 | lo,
                _ => {
                    return Err(bad(format!(
                        "not a hexadecimal digit at position {}",
                        2 * i + usize::from(digit(pair[0]).is_some())
                    )))
                }
            }
        }
        Ok(Self(out))
    }
}

impl fmt::Display for Digest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.to_hex())
    }
}

impl fmt::Debug for Digest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Digest({})", self.to_hex())
    }
}

/// The digest of `bytes`.
pub fn digest_of(bytes: &[u8]) -> Digest {
    Digest(*blake3::hash(bytes).as_bytes())
}

/// The digest and size of the file `path`, read in 64 KiB pieces (a file of any size takes
/// constant memory).
pub fn digest_file(path: &Path) -> Result<(Digest, u64), BundleError> {
    let io_err = |error| BundleError::Io {
        file: path.to_path_buf(),
        action: "cannot read",
        error,
    };
    let mut file = File::open(path).map_err(io_err)?;
    let mut hasher = blake3::Hasher::new();
    let mut buf = vec![0u8; 64 << 10];
    let mut size = 0u64;
    loop {
        let n = match file.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(io_err(e)),
        };
        hasher.update(&buf[..n]);
        size += n as u64;
    }
    Ok((Digest(*hasher.finalize().as_bytes()), size))
}

/// One file of a bundle.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ManifestEntry {
    /// Path relative to the bundle directory, `/`-separated, normalised ([`validate_path`]).
    pub path: String,
    /// blake3 digest of the contents.
    pub digest: Digest,
    /// Size of the contents, in bytes.
    pub size: u64,
}

/// A bundle: the scene file `root` and every file it reads.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Manifest {
    /// The scene XML file: the `path` of one of `files`.
    pub root: String,
    /// The files, each path once. [`collect`] lists the root first, then the files in the
    /// order the loader first read them.
    pub files: Vec<ManifestEntry>,
}

/// What a bundle may hold. The farm takes manifests from the network: the coordinator checks
/// them ([`Manifest::validate`]) before it accepts a single blob.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BundleLimits {
    /// Files in one bundle (default 10 000; the shared veach-ajar scene has 21).
    pub max_files: usize,
    /// Total size of a bundle's files, in bytes (default 4 GiB).
    pub max_total_bytes: u64,
    /// Size of one file, in bytes (default 1 GiB: four times the largest scene XML file the
    /// loader reads, `Limits::max_scene_file_bytes`, 256 MiB, since meshes are larger than
    /// XML; a binary PLY mesh of about 35 M triangles).
    pub max_file_bytes: u64,
}

impl Default for BundleLimits {
    fn default() -> Self {
        Self {
            max_files: 10_000,
            max_total_bytes: 4 << 30,
            max_file_bytes: 1 << 30,
        }
    }
}

/// Everything that can go wrong collecting, validating, materialising or checking a bundle.
/// Every variant names the path, digest or limit at fault.
#[derive(Debug, thiserror::Error)]
pub enum BundleError {
    #[error("invalid digest {text:?}: {reason}")]
    InvalidDigest { text: String, reason: String },
    /// A manifest path that is not relative, '/'-separated and normalised.
    #[error("bundle path {path:?} {reason}")]
    InvalidPath { path: String, reason: &'static str },
    #[error("bundle path {path:?} is listed more than once")]
    DuplicatePath { path: String },
    /// `path` is a file, and `other` puts a file inside it as if it were a directory.
    #[error("bundle path {path:?} is a file, but {other:?} uses it as a directory")]
    FileAndDirectory { path: String, other: String },
    #[error("the bundle's root {root:?} is not one of its files")]
    RootMissing { root: String },
    #[error(
        "the bundle has {count} files, more than the limit of {max} (BundleLimits::max_files)"
    )]
    TooManyFiles { count: usize, max: usize },
    #[error(
        "bundle file {path:?} is {}, more than the limit of {} (BundleLimits::max_file_bytes)",
        format_bytes(*size),
        format_bytes(*max)
    )]
    FileTooLarge { path: String, size: u64, max: u64 },
    /// `total` is the sum up to the first file past the limit (saturating).
    #[error(
        "the bundle's files total more than {} (at least {}; BundleLimits::max_total_bytes)",
        format_bytes(*max),
        format_bytes(*total)
    )]
    TotalTooLarge { total: u64, max: u64 },
    /// The file `file` (a blob, or a file of the bundle directory) for the manifest's `path`
    /// does not have the manifest's size.
    #[error("bundle file {path:?}: {} is {actual} bytes, the manifest says {expected}", file.display())]
    SizeMismatch {
        path: String,
        file: PathBuf,
        expected: u64,
        actual: u64,
    },
    /// Materialising would overwrite something, or write through a symbolic link (which could
    /// lead outside the destination): the destination should be a fresh directory.
    #[error("cannot materialise {}: {reason}", file.display())]
    Conflict { file: PathBuf, reason: &'static str },
    /// An I/O error: `action` is e.g. "cannot read".
    #[error("{}: {action}: {error}", file.display())]
    Io {
        file: PathBuf,
        action: &'static str,
        error: io::Error,
    },
    /// [`collect`] could not load the scene (confined to its directory, so this is also the
    /// error of a scene that refers to a file outside it). As in `SceneError`, the cause is
    /// part of the message, not a `source`.
    #[error("cannot bundle {}: {error}", scene.display())]
    Collect { scene: PathBuf, error: SceneError },
    /// [`check`]: the scene read `file`, which is not one of the manifest's files.
    #[error("the scene read {}, which is not in the bundle's manifest", file.display())]
    NotInManifest { file: PathBuf },
    /// [`check`]: loading the materialised scene failed (a missing file, a bad mesh, ...).
    #[error(transparent)]
    Scene(#[from] SceneError),
}

/// Check that `path` is a manifest path: non-empty, relative (no leading '/'), '/'-separated
/// components that are neither empty nor `.` nor `..`, with no backslash and no NUL.
pub fn validate_path(path: &str) -> Result<(), BundleError> {
    let bad = |reason| {
        Err(BundleError::InvalidPath {
            path: path.chars().take(256).collect(),
            reason,
        })
    };
    if path.is_empty() {
        return bad("is empty");
    }
    if path.starts_with('/') {
        return bad("is absolute (starts with '/')");
    }
    if path.contains('\0') {
        return bad("contains a NUL character");
    }
    if path.contains('\\') {
        return bad("contains a backslash (the separator is '/')");
    }
    for c in path.split('/') {
        match c {
            "" => return bad("has an empty component ('//' or a trailing '/')"),
            "." => return bad("has a '.' component"),
            ".." => return bad("has a '..' component"),
            _ => {}
        }
    }
    Ok(())
}

impl Manifest {
    /// Check the manifest against `limits`: at most `max_files` files, each path valid
    /// ([`validate_path`]) and listed once, no path both a file and a directory of another,
    /// the root one of the files, each size at most `max_file_bytes` and their sum at most
    /// `max_total_bytes`.
    pub fn validate(&self, limits: &BundleLimits) -> Result<(), BundleError> {
        if self.files.len() > limits.max_files {
            return Err(BundleError::TooManyFiles {
                count: self.files.len(),
                max: limits.max_files,
            });
        }
        let mut total = 0u64;
        for e in &self.files {
            if e.size > limits.max_file_bytes {
                return Err(BundleError::FileTooLarge {
                    path: e.path.clone(),
                    size: e.size,
                    max: limits.max_file_bytes,
                });
            }
            total = total.saturating_add(e.size);
            if total > limits.max_total_bytes {
                return Err(BundleError::TotalTooLarge {
                    total,
                    max: limits.max_total_bytes,
                });
            }
        }
        self.entries().map(|_| ())
    }

    /// The sum of the files' sizes (saturating).
    pub fn total_bytes(&self) -> u64 {
        self.files
            .iter()
            .fold(0u64, |t, e| t.saturating_add(e.size))
    }

    /// The entry of `path`, if the manifest lists it.
    pub fn entry(&self, path: &str) -> Option<&ManifestEntry> {
        self.files.iter().find(|e| e.path == path)
    }

    /// The structural part of [`Manifest::validate`] (paths, uniqueness, root), without the
    /// size limits: the entries by path.
    fn entries(&self) -> Result<HashMap<&str, &ManifestEntry>, BundleError> {
        let mut by_path = HashMap::with_capacity(self.files.len());
        for e in &self.files {
            validate_path(&e.path)?;
            if by_path.insert(e.path.as_str(), e).is_some() {
                return Err(BundleError::DuplicatePath {
                    path: e.path.clone(),
                });
            }
        }
        for e in &self.files {
            for (i, _) in e.path.match_indices('/') {
                if by_path.contains_key(&e.path[..i]) {
                    return Err(BundleError::FileAndDirectory {
                        path: e.path[..i].to_string(),
                        other: e.path.clone(),
                    });
                }
            }
        }
        if !by_path.contains_key(self.root.as_str()) {
            return Err(BundleError::RootMissing {
                root: self.root.chars().take(256).collect(),
            });
        }
        Ok(by_path)
    }
}

/// `file`'s path relative to `base` as a manifest path.
fn manifest_path(file: &Path, base: &Path) -> Result<String, BundleError> {
    let shown = || file.display().to_string();
    let rel = file
        .strip_prefix(base)
        .map_err(|_| BundleError::InvalidPath {
            path: shown(),
            reason: "is not inside the scene's directory",
        })?;
    let mut parts = Vec::new();
    for c in rel.components() {
        match c {
            Component::Normal(s) => parts.push(s.to_str().ok_or(BundleError::InvalidPath {
                path: shown(),
                reason: "is not valid UTF-8",
            })?),
            Component::CurDir => {}
            _ => {
                return Err(BundleError::InvalidPath {
                    path: shown(),
                    reason: "is not a plain relative path",
                })
            }
        }
    }
    let path = parts.join("/");
    validate_path(&path)?;
    Ok(path)
}

/// `limits` with [`Limits::confine_files`] on.
fn confined(limits: &Limits) -> Limits {
    Limits {
        confine_files: true,
        ..limits.clone()
    }
}

/// Bundle the scene `scene` (its files learned with `overrides` and `limits`, confined to its
/// directory, by [`scene_files`]: the XML checked, meshes and images not decoded): the
/// manifest of every file the scene reads, paths relative to the scene's directory, the root
/// (the scene file's name) first, and the local file of each entry, in the same order.
/// Digests are computed by streaming each file. A file whose contents are bad is bundled: the
/// coordinator's validation refuses the job if it is a mesh (NaN positions, say), the workers
/// fail it if it is an image's pixels (the validation reads images' headers only), naming the
/// file by its bundle path either way.
///
/// A scene that reads a file outside its directory (an absolute name, `..`, a symbolic link
/// leading out) cannot be bundled: [`BundleError::Collect`] names the file and line.
pub fn collect(
    scene: &Path,
    overrides: &[(String, String)],
    integrator: Option<&str>,
    limits: &Limits,
) -> Result<(Manifest, Vec<PathBuf>), BundleError> {
    let names =
        scene_files_as(scene, overrides, &confined(limits), integrator).map_err(|error| {
            BundleError::Collect {
                scene: scene.to_path_buf(),
                error,
            }
        })?;
    let base = scene.parent().unwrap_or(Path::new(""));
    let mut seen = HashSet::new();
    let mut files = Vec::with_capacity(names.len());
    let mut locals = Vec::with_capacity(names.len());
    for file in names {
        let path = manifest_path(&file, base)?;
        if !seen.insert(path.clone()) {
            continue;
        }
        let (digest, size) = digest_file(&file)?;
        files.push(ManifestEntry { path, digest, size });
        locals.push(file);
    }
    let root = files[0].path.clone();
    Ok((Manifest { root, files }, locals))
}

/// Lay the bundle out under `dest` (created if absent; it should be empty): each file's
/// directories, and the blob `blob_path(digest)` hard-linked into place, or copied where it
/// cannot be linked (another file system). Each file is checked to have the manifest's size.
/// Returns the root scene file's path.
///
/// Nothing is written outside `dest`: the manifest's paths are checked first (as by
/// [`Manifest::validate`], without the size limits), nothing existing is overwritten, and an
/// existing symbolic link (or file) where a directory goes is a [`BundleError::Conflict`].
/// The materialised files share their inode with the blobs when linked: treat them as
/// read-only.
pub fn materialize(
    manifest: &Manifest,
    blob_path: impl Fn(&Digest) -> PathBuf,
    dest: &Path,
) -> Result<PathBuf, BundleError> {
    manifest.entries()?;
    fs::create_dir_all(dest).map_err(|error| BundleError::Io {
        file: dest.to_path_buf(),
        action: "cannot create directory",
        error,
    })?;
    let mut made: HashSet<PathBuf> = HashSet::new();
    for e in &manifest.files {
        let mut dir = dest.to_path_buf();
        let mut parts: Vec<&str> = e.path.split('/').collect();
        let name = parts.pop().expect("split yields one part at least");
        for part in parts {
            dir.push(part);
            if made.contains(&dir) {
                continue;
            }
            match fs::symlink_metadata(&dir) {
                Ok(m) if m.file_type().is_dir() => {}
                Ok(m) if m.file_type().is_symlink() => {
                    return Err(BundleError::Conflict {
                        file: dir,
                        reason: "a symbolic link is where a directory goes (it could lead \
                                 outside the destination)",
                    })
                }
                Ok(_) => {
                    return Err(BundleError::Conflict {
                        file: dir,
                        reason: "a file is where a directory goes",
                    })
                }
                Err(err) if err.kind() == io::ErrorKind::NotFound => {
                    fs::create_dir(&dir).map_err(|error| BundleError::Io {
                        file: dir.clone(),
                        action: "cannot create directory",
                        error,
                    })?
                }
                Err(error) => {
                    return Err(BundleError::Io {
                        file: dir,
                        action: "cannot inspect",
                        error,
                    })
                }
            }
            made.insert(dir.clone());
        }
        place(e, &blob_path(&e.digest), &dir.join(name))?;
    }
    Ok(dest.join(&manifest.root))
}

/// Hard-link (or copy) the blob `blob` of `e` to `target`, which must not exist.
fn place(e: &ManifestEntry, blob: &Path, target: &Path) -> Result<(), BundleError> {
    let mismatch = |file: &Path, actual| BundleError::SizeMismatch {
        path: e.path.clone(),
        file: file.to_path_buf(),
        expected: e.size,
        actual,
    };
    let blob_err = |action, error| BundleError::Io {
        file: blob.to_path_buf(),
        action,
        error,
    };
    let meta = fs::metadata(blob).map_err(|error| blob_err("cannot read blob", error))?;
    if !meta.is_file() {
        return Err(blob_err(
            "cannot read blob",
            io::Error::new(io::ErrorKind::InvalidInput, "not a regular file"),
        ));
    }
    if meta.len() != e.size {
        return Err(mismatch(blob, meta.len()));
    }
    let exists = || BundleError::Conflict {
        file: target.to_path_buf(),
        reason: "it already exists",
    };
    let target_err = |action, error| BundleError::Io {
        file: target.to_path_buf(),
        action,
        error,
    };
    // `link` does not follow a symbolic link: link only a regular blob, copy through others.
    let regular = fs::symlink_metadata(blob).is_ok_and(|m| m.file_type().is_file());
    let linked = if regular {
        fs::hard_link(blob, target)
    } else {
        Err(io::Error::other("not linked"))
    };
    match linked {
        Ok(()) => {
            let len = fs::symlink_metadata(target)
                .map_err(|error| target_err("cannot inspect", error))?
                .len();
            if len != e.size {
                let _ = fs::remove_file(target);
                return Err(mismatch(blob, len));
            }
        }
        Err(err) if err.kind() == io::ErrorKind::AlreadyExists => return Err(exists()),
        Err(_) => {
            let mut src = File::open(blob).map_err(|error| blob_err("cannot read blob", error))?;
            let mut dst = match OpenOptions::new().write(true).create_new(true).open(target) {
                Ok(f) => f,
                Err(err) if err.kind() == io::ErrorKind::AlreadyExists => return Err(exists()),
                Err(error) => return Err(target_err("cannot create", error)),
            };
            let copied = io::copy(&mut (&mut src).take(e.size.saturating_add(1)), &mut dst)
                .and_then(|n| dst.flush().map(|()| n));
            match copied {
                Ok(n) if n == e.size => {}
                Ok(n) => {
                    let _ = fs::remove_file(target);
                    return Err(mismatch(blob, n));
                }
                Err(error) => {
                    let _ = fs::remove_file(target);
                    return Err(target_err("cannot write", error));
                }
            }
        }
    }
    Ok(())
}

/// `e`'s message with the bundle's materialised directory `dir` taken out of its paths, so
/// that it names files by their bundle paths, as the submitter knows them.
pub(crate) fn in_bundle_paths(e: &dyn std::fmt::Display, dir: &Path) -> String {
    e.to_string().replace(&format!("{}/", dir.display()), "")
}

/// How much of a bundle's files [`check`] decodes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Decode {
    /// Meshes and images: a scene to render (a worker's).
    Everything,
    /// Meshes, and of images only their headers (checked against the limits, stand-ins for
    /// their pixels; `pathfarm_scene::load_scene_geometry_as`): the coordinator's validation
    /// of a submission, which needs the scene's bounds and checks but renders nothing. A bad
    /// image is found by the workers, whose leases of the job fail and so the job.
    Geometry,
    /// Neither (files named, opened and checked by size; `pathfarm_scene::scan_scene_as`):
    /// for a scene whose world is built already ([`world_key`],
    /// `pathfarm_render::Scene::with_world`), which reads only its camera and integrator.
    Nothing,
}

/// Load the materialised bundle in `dir` (with `overrides` and `limits`, confined to the root
/// scene file's directory, decoding as `decode` says) and verify that every file the loader
/// read is one of the manifest's, with the manifest's size. Confinement keeps the loader from
/// reading anything outside `dir`, so this also proves that the manifest names all the scene
/// needs; entries the loader did not read are allowed (they cost only storage, within
/// [`BundleLimits`]).
///
/// A file the scene needs and the bundle lacks is a [`BundleError::Scene`] naming it, the
/// scene file and line.
pub fn check(
    manifest: &Manifest,
    dir: &Path,
    overrides: &[(String, String)],
    integrator: Option<&str>,
    limits: &Limits,
    decode: Decode,
) -> Result<SceneDesc, BundleError> {
    let load = match decode {
        Decode::Everything => load_scene_as,
        Decode::Geometry => load_scene_geometry_as,
        Decode::Nothing => scan_scene_as,
    };
    let root = dir.join(&manifest.root);
    let desc = load(&root, overrides, &confined(limits), integrator)?;
    verify_files(manifest, dir, &desc)?;
    Ok(desc)
}

/// Every file the load of `desc` read is one of the manifest's, of the manifest's size.
fn verify_files(manifest: &Manifest, dir: &Path, desc: &SceneDesc) -> Result<(), BundleError> {
    let entries = manifest.entries()?;
    for file in &desc.files {
        let path = manifest_path(file, dir)?;
        let Some(e) = entries.get(path.as_str()) else {
            return Err(BundleError::NotInManifest { file: file.clone() });
        };
        let len = fs::metadata(file)
            .map_err(|error| BundleError::Io {
                file: file.clone(),
                action: "cannot inspect",
                error,
            })?
            .len();
        if len != e.size {
            return Err(BundleError::SizeMismatch {
                path: path.clone(),
                file: file.clone(),
                expected: e.size,
                actual: len,
            });
        }
    }
    Ok(())
}

/// What the world of the bundle's scene (materialised in `dir`) is built from: its
/// [`pathfarm_scene::world_source`] with `overrides`, and the digest of every file in the
/// manifest but the root. Two bundles with one key build the same world (geometry, BVH,
/// lights, materials, textures) whatever their cameras and integrators: the frames of a shot
/// share one. Reads only the scene's text.
pub fn world_key(
    manifest: &Manifest,
    dir: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
) -> Result<Digest, BundleError> {
    let root = dir.join(&manifest.root);
    let source = world_source(&root, overrides, &confined(limits))?;
    let mut h = blake3::Hasher::new();
    h.update(&(source.len() as u64).to_le_bytes());
    h.update(&source);
    let mut files: Vec<&ManifestEntry> = (manifest.files.iter())
        .filter(|e| e.path != manifest.root)
        .collect();
    files.sort_by(|a, b| a.path.cmp(&b.path));
    for e in files {
        h.update(&(e.path.len() as u64).to_le_bytes());
        h.update(e.path.as_bytes());
        h.update(&e.digest.0);
    }
    Ok(Digest(*h.finalize().as_bytes()))
}

/// Why [`build_scene`] failed.
#[derive(Debug)]
pub(crate) enum SceneBuild {
    /// The scene did not load or check against the manifest.
    Load(BundleError),
    /// The resolution asked for is outside the film limits.
    Resolution(String),
    /// The loaded scene could not be built.
    Build(pathfarm_render::RenderError),
}

/// How [`build_scene`] built the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Built {
    /// On the world `held` gave, from a scan of the scene's text.
    OnHeldWorld,
    /// From its files.
    FromFiles,
}

/// What a job asks of its scene beside the bundle: `-D` overrides, an integrator in place of
/// the scene's, a resolution in place of its film's.
pub(crate) struct SceneOptions<'a> {
    pub overrides: &'a [(String, String)],
    pub integrator: Option<&'a str>,
    pub resolution: Option<(u32, u32)>,
}

/// The scene of the bundle materialised in `dir` with `options`, built for `purpose`: on the
/// world `held` gives for its [`world_key`] (a scan of its text against the manifest), else
/// from its files (for [`Purpose::Inspect`](pathfarm_render::Purpose), with stand-ins for
/// its images: [`Decode::Geometry`]). Returns the key with it, under which a caller keeps
/// the world for the next scene.
pub(crate) fn build_scene(
    manifest: &Manifest,
    dir: &Path,
    options: &SceneOptions,
    limits: &Limits,
    purpose: pathfarm_render::Purpose,
    held: impl FnOnce(&Digest) -> Option<std::sync::Arc<pathfarm_render::World>>,
) -> Result<(pathfarm_render::Scene, Digest, Built), SceneBuild> {
    use pathfarm_render::Scene;
    let SceneOptions {
        overrides,
        integrator,
        resolution,
    } = *options;
    let key = world_key(manifest, dir, overrides, limits).map_err(SceneBuild::Load)?;
    // (a world held for inspection is never rendered on)
    let held = held(&key).filter(|w| w.serves(purpose));
    let decode = match (&held, purpose) {
        (Some(_), _) => Decode::Nothing,
        (None, pathfarm_render::Purpose::Inspect) => Decode::Geometry,
        (None, pathfarm_render::Purpose::Render) => Decode::Everything,
    };
    let mut desc =
        check(manifest, dir, overrides, integrator, limits, decode).map_err(SceneBuild::Load)?;
    if let Some((w, h)) = resolution {
        override_resolution(&mut desc, w, h, limits).map_err(SceneBuild::Resolution)?;
    }
    let (scene, built) = match held {
        Some(world) => (Scene::with_world(&desc, world), Built::OnHeldWorld),
        None => (Scene::build_for(&desc, purpose), Built::FromFiles),
    };
    Ok((scene.map_err(SceneBuild::Build)?, key, built))
}

/// Sets the film of `desc` to `width x height` (a job's resolution override), within the
/// film limits the loader applies to a scene's own film.
pub fn override_resolution(
    desc: &mut SceneDesc,
    width: u32,
    height: u32,
    limits: &Limits,
) -> Result<(), String> {
    let side = limits.max_film_side;
    if width == 0 || height == 0 || width > side || height > side {
        return Err(format!(
            "resolution {width}x{height}: each side must be between 1 and {side} \
             (Limits::max_film_side)"
        ));
    }
    if width as u64 * height as u64 > limits.max_film_pixels {
        return Err(format!(
            "resolution {width}x{height}: more than {} pixels (Limits::max_film_pixels)",
            limits.max_film_pixels
        ));
    }
    desc.sensor.film.width = width;
    desc.sensor.film.height = height;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_render::Purpose;

    #[test]
    fn a_world_built_for_inspection_is_never_rendered_on() {
        let dir = std::env::temp_dir().join(format!("pathfarm-held-world-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let scene = dir.join("scene.xml");
        let xml = include_str!("coordinator/testdata/lit-floor.xml");
        std::fs::write(&scene, xml).unwrap();
        let limits = Limits::default();
        let (manifest, _) = collect(&scene, &[], None, &limits).unwrap();
        let options = SceneOptions {
            overrides: &[],
            integrator: None,
            resolution: None,
        };
        let build = |purpose, held: Option<std::sync::Arc<pathfarm_render::World>>| {
            let (s, _, built) =
                build_scene(&manifest, &dir, &options, &limits, purpose, |_| held).unwrap();
            (s.shared_world(), built)
        };
        let (inspected, built) = build(Purpose::Inspect, None);
        assert_eq!(
            (inspected.purpose(), built),
            (Purpose::Inspect, Built::FromFiles)
        );
        let (_, built) = build(Purpose::Inspect, Some(inspected.clone()));
        assert_eq!(built, Built::OnHeldWorld, "an inspection shares it");
        let (rendered, built) = build(Purpose::Render, Some(inspected));
        assert_eq!(built, Built::FromFiles, "a render builds its own");
        assert_eq!(rendered.purpose(), Purpose::Render);
        let (_, built) = build(Purpose::Inspect, Some(rendered.clone()));
        assert_eq!(
            built,
            Built::OnHeldWorld,
            "a render's world serves an inspection"
        );
        let (_, built) = build(Purpose::Render, Some(rendered));
        assert_eq!(built, Built::OnHeldWorld);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
