//! Shared state while turning the plugin tree into a [`crate::SceneDesc`]:
//! the BSDF and texture arenas, caches for objects referenced several times,
//! and cycle detection.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::rc::Rc;

use crate::desc::{BsdfDesc, Location, TextureDesc};
use crate::error::SceneError;
use crate::limits::{format_bytes, Limits};
use crate::props::Props;
use crate::xml::{invalid, Node};

/// Build state. Objects are cached by node identity, so an `id`'d BSDF or
/// texture referenced from many places is built once.
pub(crate) struct Ctx {
    pub ids: HashMap<String, Rc<Node>>,
    pub base_dir: PathBuf,
    pub bsdfs: Vec<BsdfDesc>,
    pub textures: Vec<TextureDesc>,
    pub bsdf_cache: HashMap<*const Node, usize>,
    pub texture_cache: HashMap<*const Node, usize>,
    in_progress: HashSet<*const Node>,
    pub warnings: Vec<String>,
    default_bsdf: Option<usize>,
    /// Resource limits of this load.
    pub limits: Limits,
    /// Bytes of mesh and texture data loaded so far (checked against
    /// `limits.max_memory_bytes` before each allocation, see [`Ctx::reserve_memory`]).
    pub memory_bytes: u64,
}

impl Ctx {
    pub(crate) fn new(ids: HashMap<String, Rc<Node>>, base_dir: PathBuf, limits: Limits) -> Self {
        Self {
            ids,
            base_dir,
            bsdfs: Vec::new(),
            textures: Vec::new(),
            bsdf_cache: HashMap::new(),
            texture_cache: HashMap::new(),
            in_progress: HashSet::new(),
            warnings: Vec::new(),
            default_bsdf: None,
            limits,
            memory_bytes: 0,
        }
    }

    /// Typed property view of `node` (resolving its nested refs).
    pub(crate) fn props(&self, node: &Rc<Node>) -> Result<Props, SceneError> {
        Props::new(node.clone(), &self.ids)
    }

    /// Resolve a file name relative to the scene file's directory.
    pub(crate) fn resolve_path(&self, name: &str) -> PathBuf {
        let p = PathBuf::from(name);
        if p.is_absolute() {
            p
        } else {
            self.base_dir.join(p)
        }
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
