//! Shared state while turning the plugin tree into a [`crate::SceneDesc`]:
//! the BSDF and texture arenas, caches for objects referenced several times,
//! and cycle detection.

use std::collections::{HashMap, HashSet};
use std::path::{Component, Path, PathBuf};
use std::rc::Rc;

use crate::desc::{BsdfDesc, Location, TextureDesc};
use crate::error::SceneError;
use crate::limits::{format_bytes, Limits};
use crate::props::Props;
use crate::xml::{invalid, Node};

/// What a load reads of the files a scene names.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Reading {
    /// Everything: meshes and images decoded (a scene to render).
    Contents,
    /// Only what names and checks them: each file opened, an image's header (its size, for
    /// the limits); meshes and images are not decoded ([`crate::scene_files`]).
    Names,
    /// Meshes decoded, images read as [`Reading::Names`] reads them: what a scene's bounds
    /// and checks need when nothing is rendered from it ([`crate::load_scene_geometry_as`]).
    Geometry,
}

/// Build state. Objects are cached by node identity, so an `id`'d BSDF or
/// texture referenced from many places is built once.
pub(crate) struct Ctx {
    pub ids: HashMap<String, Rc<Node>>,
    pub base_dir: PathBuf,
    /// `<path>` directories, searched first (see [`Ctx::resolve_path`]).
    pub search_paths: Vec<String>,
    pub bsdfs: Vec<BsdfDesc>,
    pub textures: Vec<TextureDesc>,
    pub bsdf_cache: HashMap<*const Node, usize>,
    pub texture_cache: HashMap<*const Node, usize>,
    in_progress: HashSet<*const Node>,
    pub warnings: Vec<String>,
    default_bsdf: Option<usize>,
    black_bsdf: Option<usize>,
    /// Resource limits of this load.
    pub limits: Limits,
    /// What the load reads of the files the scene names.
    pub reading: Reading,
    /// Bytes of mesh and texture data loaded so far (checked against
    /// `limits.max_memory_bytes` before each allocation, see [`Ctx::reserve_memory`]).
    pub memory_bytes: u64,
    /// Every file read so far, as resolved, each once, in first-read order (the root scene
    /// file first): becomes [`crate::SceneDesc::files`].
    pub files: Vec<PathBuf>,
    files_seen: HashSet<PathBuf>,
    /// `base_dir` canonicalized, computed on the first confined [`Ctx::resolve_path`].
    canonical_base: Option<PathBuf>,
}

impl Ctx {
    pub(crate) fn new(
        ids: HashMap<String, Rc<Node>>,
        base_dir: PathBuf,
        limits: Limits,
        reading: Reading,
    ) -> Self {
        Self {
            ids,
            base_dir,
            search_paths: Vec::new(),
            bsdfs: Vec::new(),
            textures: Vec::new(),
            bsdf_cache: HashMap::new(),
            texture_cache: HashMap::new(),
            in_progress: HashSet::new(),
            warnings: Vec::new(),
            default_bsdf: None,
            black_bsdf: None,
            limits,
            reading,
            memory_bytes: 0,
            files: Vec::new(),
            files_seen: HashSet::new(),
            canonical_base: None,
        }
    }

    /// Typed property view of `node` (resolving its nested refs).
    pub(crate) fn props(&self, node: &Rc<Node>) -> Result<Props, SceneError> {
        Props::new(node.clone(), &self.ids)
    }

    /// Record that `path` is read (once; later calls with the same path do nothing).
    pub(crate) fn record_file(&mut self, path: &Path) {
        if self.files_seen.insert(path.to_path_buf()) {
            self.files.push(path.to_path_buf());
        }
    }

    /// Resolve the file name `name` (written at `loc`) relative to the scene file's directory
    /// and record it in [`Ctx::files`]: the caller reads the returned path.
    ///
    /// With `limits.confine_files`, `name` must be relative, without `..` (or root) components,
    /// and resolve, symlinks followed, to a file inside the scene file's directory: anything
    /// else is an error at `loc` naming `name`. Without it, absolute names are used as they
    /// are and `..` is allowed.
    pub(crate) fn resolve_path(
        &mut self,
        name: &str,
        loc: &Location,
    ) -> Result<PathBuf, SceneError> {
        // A relative name is looked up in the `<path>` directories first, as Mitsuba's
        // file resolver does; the name found is the one confinement checks.
        let found = (!Path::new(name).is_absolute())
            .then(|| {
                (self.search_paths.iter())
                    .map(|dir| Path::new(dir).join(name))
                    .find(|rel| self.base_dir.join(rel).exists())
            })
            .flatten();
        let name = match &found {
            Some(rel) => rel.to_str().unwrap_or(name),
            None => name,
        };
        let p = Path::new(name);
        let path = if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.base_dir.join(p)
        };
        if self.limits.confine_files {
            self.check_confined(name, &path, loc)?;
        }
        self.record_file(&path);
        Ok(path)
    }

    /// The checks of `Limits::confine_files` on the file name `name`, resolved to `path`.
    fn check_confined(
        &mut self,
        name: &str,
        path: &Path,
        loc: &Location,
    ) -> Result<(), SceneError> {
        let refuse = |why: &str| {
            invalid(
                loc,
                format!(
                    "file name '{name}' {why}: files are confined to the scene file's \
                     directory (Limits::confine_files)"
                ),
            )
        };
        let p = Path::new(name);
        if p.is_absolute() || p.has_root() {
            return Err(refuse("is an absolute path"));
        }
        let mut normal = 0;
        for c in p.components() {
            match c {
                Component::Normal(_) => normal += 1,
                Component::CurDir => {}
                Component::ParentDir => return Err(refuse("contains a '..' component")),
                Component::RootDir | Component::Prefix(_) => {
                    return Err(refuse("is an absolute path"))
                }
            }
        }
        if normal == 0 {
            return Err(refuse("names no file"));
        }
        let base = match &self.canonical_base {
            Some(b) => b.clone(),
            None => {
                let dir = if self.base_dir.as_os_str().is_empty() {
                    Path::new(".")
                } else {
                    self.base_dir.as_path()
                };
                let b = std::fs::canonicalize(dir).map_err(|e| {
                    invalid(
                        loc,
                        format!(
                            "the scene file's directory '{}': cannot read: {e}",
                            dir.display()
                        ),
                    )
                })?;
                self.canonical_base = Some(b.clone());
                b
            }
        };
        let real = std::fs::canonicalize(path)
            .map_err(|e| invalid(loc, format!("file '{name}': cannot read: {e}")))?;
        if !real.starts_with(&base) {
            return Err(refuse(&format!(
                "resolves (through a symbolic link) to '{}', outside '{}'",
                real.display(),
                base.display()
            )));
        }
        Ok(())
    }

    /// Mark `node` as being built; errors on a reference cycle.
    pub(crate) fn enter(&mut self, node: &Rc<Node>, loc: &Location) -> Result<(), SceneError> {
        if !self.in_progress.insert(Rc::as_ptr(node)) {
            return Err(invalid(
                loc,
                format!(
                    "reference cycle through {} {}",
                    node.plugin,
                    node.category.tag()
                ),
            ));
        }
        Ok(())
    }

    pub(crate) fn leave(&mut self, node: &Rc<Node>) {
        self.in_progress.remove(&Rc::as_ptr(node));
    }

    /// Account for `bytes` more of scene data (`what`, e.g. "mesh file 'x.ply' (12 M
    /// triangles)") before allocating it: an error at `loc` if the scene's data would exceed
    /// `limits.max_memory_bytes`.
    pub(crate) fn reserve_memory(
        &mut self,
        bytes: u64,
        what: &str,
        loc: &Location,
    ) -> Result<(), SceneError> {
        let total = self.memory_bytes.saturating_add(bytes);
        if total > self.limits.max_memory_bytes {
            return Err(invalid(
                loc,
                format!(
                    "{what} needs {}, which with the {} already loaded exceeds the memory limit \
                     of {} (Limits::max_memory_bytes)",
                    format_bytes(bytes),
                    format_bytes(self.memory_bytes),
                    format_bytes(self.limits.max_memory_bytes)
                ),
            ));
        }
        self.memory_bytes = total;
        Ok(())
    }

    /// Index of the BSDF Mitsuba 3 gives an emitting shape that names none (diffuse,
    /// reflectance 0: the emitter reflects nothing), added on first use.
    pub(crate) fn black_bsdf(&mut self) -> usize {
        *self.black_bsdf.get_or_insert_with(|| {
            self.bsdfs.push(BsdfDesc::Diffuse {
                reflectance: crate::desc::TexRef::Const(glam::Vec3::ZERO),
            });
            self.bsdfs.len() - 1
        })
    }

    /// Index of Mitsuba's default BSDF (diffuse, reflectance 0.5), added on
    /// first use.
    pub(crate) fn default_bsdf(&mut self) -> usize {
        *self.default_bsdf.get_or_insert_with(|| {
            self.bsdfs.push(BsdfDesc::Diffuse {
                reflectance: crate::desc::TexRef::Const(glam::Vec3::splat(0.5)),
            });
            self.bsdfs.len() - 1
        })
    }
}
