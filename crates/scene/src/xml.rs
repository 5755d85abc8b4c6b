//! Mitsuba 3 XML parsing into a generic plugin tree.
//!
//! This stage knows the XML format (elements, `$name` substitution,
//! `<default>`, typed property elements, transforms, `ref`) but nothing about
//! individual plugins. Every node and property carries its [`Location`] so
//! later stages can report errors at the right line.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::rc::Rc;

use glam::{DMat4, DVec3, Vec3};

use crate::desc::Location;
use crate::error::SceneError;
use crate::transform;

/// Build a [`SceneError::Invalid`] at `loc`.
pub(crate) fn invalid(loc: &Location, message: impl Into<String>) -> SceneError {
    SceneError::Invalid {
        file: loc.file.clone(),
        line: loc.line,
        message: message.into(),
    }
}

/// The object categories Mitsuba's XML knows (the element name of a plugin).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Category {
    Shape,
    Bsdf,
    Texture,
    Emitter,
    Sensor,
    Film,
    RFilter,
    Sampler,
    Integrator,
}

impl Category {
    fn from_tag(tag: &str) -> Option<Self> {
        Some(match tag {
            "shape" => Self::Shape,
            "bsdf" => Self::Bsdf,
            "texture" => Self::Texture,
            "emitter" => Self::Emitter,
            "sensor" => Self::Sensor,
            "film" => Self::Film,
            "rfilter" => Self::RFilter,
            "sampler" => Self::Sampler,
            "integrator" => Self::Integrator,
            _ => return None,
        })
    }

    /// The XML element name.
    pub(crate) fn tag(self) -> &'static str {
        match self {
            Self::Shape => "shape",
            Self::Bsdf => "bsdf",
            Self::Texture => "texture",
            Self::Emitter => "emitter",
            Self::Sensor => "sensor",
            Self::Film => "film",
            Self::RFilter => "rfilter",
            Self::Sampler => "sampler",
            Self::Integrator => "integrator",
        }
    }
}

/// A typed property value, as written in the XML.
#[derive(Clone, Debug)]
pub(crate) enum Value {
    Integer(i64),
    Float(f64),
    Boolean(bool),
    String(String),
    Rgb(Vec3),
    /// A uniform spectrum (the only kind supported).
    Spectrum(Spectrum),
    Point(DVec3),
    Vector(DVec3),
    Transform(DMat4),
    /// A `-D name=value` the scene file does not use, given to the integrator as its parameter
    /// `name`: untyped text, read as whatever type the parameter has.
    CommandLine(String),
}

impl Value {
    /// The XML element name of this kind of value, for error messages.
    pub(crate) fn type_name(&self) -> &'static str {
        match self {
            Value::Integer(_) => "integer",
            Value::Float(_) => "float",
            Value::Boolean(_) => "boolean",
            Value::String(_) => "string",
            Value::Rgb(_) => "rgb",
            Value::Spectrum(_) => "spectrum",
            Value::Point(_) => "point",
            Value::Vector(_) => "vector",
            Value::Transform(_) => "transform",
            Value::CommandLine(_) => "-D",
        }
    }
}

/// A named property of a plugin.
/// A `<spectrum>`: one value for every wavelength, or `wavelength:value` pairs (nm,
/// strictly increasing).
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Spectrum {
    Uniform(f32),
    Pairs(Vec<(f32, f32)>),
}

/// The most `wavelength:value` pairs a `<spectrum>` may list.
const MAX_SPECTRUM_PAIRS: usize = 4096;

#[derive(Clone, Debug)]
pub(crate) struct Prop {
    pub name: String,
    pub value: Value,
    pub loc: Location,
}

/// A nested plugin, either written inline or referenced by `id`.
#[derive(Clone, Debug)]
pub(crate) enum ObjRef {
    Inline(Rc<Node>),
    Ref { id: String, loc: Location },
}

/// A nested object slot: optional `name` attribute plus the object.
#[derive(Clone, Debug)]
pub(crate) struct Child {
    pub name: Option<String>,
    pub obj: ObjRef,
}

/// A plugin instance: `<shape type="obj" id="...">...</shape>`.
#[derive(Clone, Debug)]
pub(crate) struct Node {
    pub category: Category,
    pub plugin: String,
    pub id: Option<String>,
    pub props: Vec<Prop>,
    pub children: Vec<Child>,
    pub loc: Location,
}

/// The parsed scene: top-level objects plus the id table.
#[derive(Debug)]
pub(crate) struct XmlScene {
    pub objects: Vec<Child>,
    pub ids: HashMap<String, Rc<Node>>,
    /// Directory that relative file names are resolved against.
    pub base_dir: PathBuf,
    /// `-D name=value` overrides whose name the file neither declares (`<default>`) nor
    /// references (`$name`), in command-line order: the loader hands them to the integrator.
    pub unused_overrides: Vec<(String, String)>,
    /// What the file does that Mitsuba accepts but is likely a mistake.
    pub warnings: Vec<String>,
    /// Directories of `<path value="..."/>`, relative to `base_dir` (or absolute), the last
    /// declared first: a relative file name is looked up in each before `base_dir`.
    pub search_paths: Vec<String>,
    /// The files `<include>` read, in the order read.
    pub included: Vec<PathBuf>,
}

/// What parsing a scene file and the files it includes shares.
struct Shared {
    params: HashMap<String, String>,
    /// Names declared by `<default>` or referenced by `$name`.
    used: std::cell::RefCell<std::collections::HashSet<String>>,
    ids: HashMap<String, Rc<Node>>,
    /// Bytes `$name` substitution has produced so far, against `max_substituted`.
    substituted: std::cell::Cell<usize>,
    max_substituted: usize,
    warnings: std::cell::RefCell<Vec<String>>,
    limits: crate::Limits,
    /// The directory of the scene file (the root of confinement, and where the files the
    /// scene names are found).
    root_dir: PathBuf,
    /// Bytes of scene text read (the scene and every file it includes), against
    /// `Limits::max_scene_file_bytes`.
    text_bytes: u64,
    included: Vec<PathBuf>,
    objects: Vec<Child>,
    search_paths: Vec<String>,
}

/// One scene file being parsed.
struct Parser<'a, 's> {
    file: PathBuf,
    doc: &'a roxmltree::Document<'a>,
    s: &'s mut Shared,
    /// The file is of Mitsuba 0.x (`version` below 2.0): its plugins' parameters are
    /// upgraded as Mitsuba 3 upgrades them ([`upgrade_from_v1`]).
    legacy: bool,
}

/// Parse `path` with command-line `overrides` (which take precedence over
/// `<default>` values), and the files it includes.
pub(crate) fn parse_file(
    path: &Path,
    overrides: &[(String, String)],
    limits: &crate::Limits,
) -> Result<XmlScene, SceneError> {
    let root_dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let mut shared = Shared {
        params: overrides.iter().cloned().collect(),
        used: Default::default(),
        ids: HashMap::new(),
        substituted: std::cell::Cell::new(0),
        max_substituted: limits.max_substituted_bytes,
        warnings: Default::default(),
        limits: limits.clone(),
        root_dir: root_dir.clone(),
        text_bytes: 0,
        included: Vec::new(),
        objects: Vec::new(),
        search_paths: Vec::new(),
    };
    parse_scene_file(&mut shared, path, 0)?;
    let used = shared.used.into_inner();
    let mut unused_overrides: Vec<(String, String)> = Vec::new();
    for (name, value) in overrides {
        if !used.contains(name) {
            // A repeated -D: the last one wins, as in `params`.
            unused_overrides.retain(|(n, _)| n != name);
            unused_overrides.push((name.clone(), value.clone()));
        }
    }
    Ok(XmlScene {
        objects: shared.objects,
        ids: shared.ids,
        base_dir: root_dir,
        unused_overrides,
        warnings: shared.warnings.into_inner(),
        search_paths: shared.search_paths,
        included: shared.included,
    })
}

/// Parses the scene file `path` (the scene, or a file it includes `depth` deep) into `s`.
fn parse_scene_file(s: &mut Shared, path: &Path, depth: usize) -> Result<(), SceneError> {
    let text = read_scene_text(path, &s.limits, s.text_bytes)?;
    s.text_bytes += text.len() as u64;
    let file_loc = |line: u32| Location {
        file: path.to_path_buf(),
        line,
    };
    let max_depth = s.limits.max_xml_depth;
    check_nesting(&text, max_depth).map_err(|line| {
        invalid(
            &file_loc(line),
            format!("elements nest deeper than {max_depth} levels (Limits::max_xml_depth)"),
        )
    })?;
    let doc = roxmltree::Document::parse(&text).map_err(|e| {
        let pos = e.pos();
        invalid(&file_loc(pos.row), format!("malformed XML: {e}"))
    })?;
    let mut parser = Parser {
        file: path.to_path_buf(),
        doc: &doc,
        s,
        legacy: false,
    };
    let root = doc.root_element();
    if depth > 0 && Category::from_tag(root.tag_name().name()).is_some() {
        // An included file may hold a single object instead of a scene.
        return match parser.parse_element(root)? {
            Element::Object(obj) => {
                parser.s.objects.push(obj);
                Ok(())
            }
            Element::Prop(_) => unreachable!("an object tag"),
        };
    }
    parser.scene(root, depth)
}

impl Parser<'_, '_> {
    /// The `<scene>` element `root` of this file, its children added to the scene.
    fn scene(&mut self, root: roxmltree::Node, depth: usize) -> Result<(), SceneError> {
        let root_loc = self.loc(root);
        if root.tag_name().name() != "scene" {
            return Err(invalid(
                &root_loc,
                format!(
                    "root element must be <scene>, found <{}>",
                    root.tag_name().name()
                ),
            ));
        }
        for attr in root.attributes() {
            if !matches!(attr.name(), "version" | "type" | "id") {
                return Err(invalid(
                    &root_loc,
                    format!("unexpected attribute '{}' on <scene>", attr.name()),
                ));
            }
        }
        match root.attribute("version") {
            None => {
                return Err(invalid(
                    &root_loc,
                    "<scene> is missing the 'version' attribute",
                ))
            }
            Some(v) if !is_version(v) => {
                return Err(invalid(
                    &root_loc,
                    format!(
                        "<scene version=\"{v}\">: the version must be MAJOR.MINOR.PATCH, e.g. \
                         \"3.0.0\""
                    ),
                ))
            }
            Some(v) => {
                let major = v.split('.').next().and_then(|m| m.parse::<u32>().ok());
                self.legacy = major < Some(2);
            }
        }
        for child in root.children().filter(|n| n.is_element()) {
            self.scene_child(child, depth)?;
        }
        Ok(())
    }

    /// One child of `<scene>`: a `<default>`, `<include>`, `<path>` or an object.
    fn scene_child(&mut self, child: roxmltree::Node, depth: usize) -> Result<(), SceneError> {
        let loc = self.loc(child);
        match child.tag_name().name() {
            "default" => {
                self.check_attrs(child, &["name", "value"], &["name", "value"])?;
                let name = child.attribute("name").unwrap_or_default().to_string();
                let value = self.subst(child, child.attribute("value").unwrap_or_default())?;
                if name.is_empty() {
                    return Err(invalid(&loc, "<default>: name must be non-empty"));
                }
                // As in Mitsuba, the first definition wins: command-line
                // overrides, then the earliest <default> of that name.
                self.s.used.borrow_mut().insert(name.clone());
                self.s.params.entry(name).or_insert(value);
            }
            "include" => self.include(child, depth)?,
            "path" => {
                self.check_attrs(child, &["value"], &["value"])?;
                let value = self.subst(child, child.attribute("value").unwrap_or_default())?;
                if !self.s.root_dir.join(&value).is_dir() {
                    let shown = bounded(&value);
                    let msg =
                        format!("<path value=\"{shown}\">: no such directory beside the scene");
                    return Err(invalid(&loc, msg));
                }
                // Mitsuba 3 prepends: the last <path> is searched first.
                self.s.search_paths.insert(0, value);
            }
            _ => match self.parse_element(child)? {
                Element::Object(obj) => self.s.objects.push(obj),
                Element::Prop(p) => {
                    return Err(invalid(
                        &p.loc,
                        format!(
                            "unexpected <{}> property '{}' at scene level",
                            p.value.type_name(),
                            p.name
                        ),
                    ))
                }
            },
        }
        Ok(())
    }

    /// `<include filename="..."/>`: the file's scene (or single object) is added here, as
    /// if written in its place. It is looked for beside the including file, then in the
    /// `<path>` directories, then beside the scene; includes nest at most
    /// `Limits::max_include_depth` deep, at most `Limits::max_include_files` are read, and
    /// their text counts against `Limits::max_scene_file_bytes` with the scene's.
    fn include(&mut self, node: roxmltree::Node, depth: usize) -> Result<(), SceneError> {
        self.check_attrs(node, &["filename", "name"], &["filename"])?;
        let loc = self.loc(node);
        let name = self.req_attr(node, "filename")?;
        let shown = bounded(&name);
        let limits = &self.s.limits;
        if depth + 1 > limits.max_include_depth {
            let max = limits.max_include_depth;
            let msg = format!(
                "<include filename=\"{shown}\">: includes nest deeper than {max} \
                 (Limits::max_include_depth)"
            );
            return Err(invalid(&loc, msg));
        }
        if self.s.included.len() >= limits.max_include_files {
            let max = limits.max_include_files;
            let msg = format!(
                "<include filename=\"{shown}\">: more than {max} files included \
                 (Limits::max_include_files)"
            );
            return Err(invalid(&loc, msg));
        }
        let path = self.find_include(&name, &loc)?;
        self.s.included.push(path.clone());
        parse_scene_file(self.s, &path, depth + 1)
    }

    /// The file an `<include>` names, held to `Limits::confine_files`.
    fn find_include(&self, name: &str, loc: &Location) -> Result<PathBuf, SceneError> {
        let shown = bounded(name);
        let rel = Path::new(name);
        if self.s.limits.confine_files {
            let outside = rel.is_absolute()
                || rel
                    .components()
                    .any(|c| !matches!(c, std::path::Component::Normal(_)));
            if outside {
                let msg = format!(
                    "<include filename=\"{shown}\">: an absolute path or one with '..': files \
                     are confined to the scene file's directory (Limits::confine_files)"
                );
                return Err(invalid(loc, msg));
            }
        }
        let here = self.file.parent().unwrap_or(Path::new(""));
        let searched = (self.s.search_paths.iter()).map(|d| self.s.root_dir.join(d));
        let candidates = std::iter::once(here.to_path_buf())
            .chain(searched)
            .chain(std::iter::once(self.s.root_dir.clone()));
        let Some(path) = candidates.map(|d| d.join(rel)).find(|p| p.is_file()) else {
            let msg = format!("<include filename=\"{shown}\">: no such file");
            return Err(invalid(loc, msg));
        };
        if self.s.limits.confine_files {
            // A symbolic link must not lead out of the scene's directory.
            let root = self.s.root_dir.canonicalize().ok();
            let real = path.canonicalize().ok();
            if !real.zip(root).is_some_and(|(r, root)| r.starts_with(root)) {
                let msg = format!(
                    "<include filename=\"{shown}\">: leads outside the scene file's directory \
                     (Limits::confine_files)"
                );
                return Err(invalid(loc, msg));
            }
        }
        Ok(path)
    }
}

enum Element {
    Object(Child),
    Prop(Prop),
}

/// At most the first 120 characters of `s`, for messages.
fn bounded(s: &str) -> String {
    crate::shown_bounded(s, 120)
}

/// A Mitsuba 0.x parameter name as Mitsuba 3 reads it: camelCase to snake_case, a run of
/// capitals kept together (`intIOR` is `int_ior`, `toWorld` is `to_world`).
pub(crate) fn camel_to_snake(name: &str) -> String {
    let b = name.as_bytes();
    let mut out = String::with_capacity(name.len() + 4);
    let mut i = 0;
    while i < b.len() {
        let c = b[i] as char;
        if i > 0 && b[i - 1].is_ascii_lowercase() && c.is_ascii_uppercase() {
            out.push('_');
            out.push(c.to_ascii_lowercase());
            while i + 1 < b.len() && b[i + 1].is_ascii_uppercase() {
                i += 1;
                out.push(b[i].to_ascii_lowercase() as char);
            }
        } else {
            out.push(c);
        }
        i += 1;
    }
    out
}

/// Mitsuba 3's upgrade of a plugin of a Mitsuba 0.x file: parameter and nested-object names
/// from camelCase to snake_case, a `diffuse` BSDF's `diffuse_reflectance` to `reflectance`,
/// and a texture's `uoffset`, `voffset`, `uscale`, `vscale` to a `to_uv` transform.
fn upgrade_from_v1(
    plugin: &str,
    props: &mut Vec<Prop>,
    children: &mut [Child],
) -> Result<(), SceneError> {
    let rename = |name: &str| match camel_to_snake(name) {
        n if plugin == "diffuse" && n == "diffuse_reflectance" => "reflectance".to_string(),
        n => n,
    };
    for p in props.iter_mut() {
        p.name = rename(&p.name);
    }
    for c in children.iter_mut() {
        c.name = c.name.as_deref().map(rename);
    }
    for (k, p) in props.iter().enumerate() {
        if let Some(prev) = props[..k].iter().find(|q| q.name == p.name) {
            return Err(invalid(
                &p.loc,
                format!(
                    "property '{}' is specified twice once upgraded from Mitsuba 0.x names \
                     (first at line {})",
                    p.name, prev.loc.line
                ),
            ));
        }
    }
    let mut offset = DVec3::ZERO;
    let mut scale = DVec3::ONE;
    let mut loc = None;
    let mut kept = Vec::with_capacity(props.len());
    for p in props.drain(..) {
        let slot = match p.name.as_str() {
            "uoffset" => &mut offset.x,
            "voffset" => &mut offset.y,
            "uscale" => &mut scale.x,
            "vscale" => &mut scale.y,
            _ => {
                kept.push(p);
                continue;
            }
        };
        *slot = match p.value {
            Value::Float(f) => f,
            Value::Integer(i) => i as f64,
            _ => return Err(invalid(&p.loc, format!("'{}' must be a <float>", p.name))),
        };
        loc = Some(p.loc);
    }
    *props = kept;
    if let Some(loc) = loc {
        let value = Value::Transform(DMat4::from_scale(scale) * DMat4::from_translation(offset));
        let name = "to_uv".to_string();
        props.push(Prop { name, value, loc });
    }
    Ok(())
}

/// Split a list of numbers separated by commas and/or whitespace.
pub(crate) fn tokenize(s: &str) -> Vec<&str> {
    s.split(|c: char| c == ',' || c.is_whitespace())
        .filter(|t| !t.is_empty())
        .collect()
}

impl Parser<'_, '_> {
    fn loc(&self, node: roxmltree::Node) -> Location {
        let pos = self.doc.text_pos_at(node.range().start);
        Location {
            file: self.file.clone(),
            line: pos.row,
        }
    }

    /// Check that `node` has all `required` attributes and nothing outside `allowed`.
    fn check_attrs(
        &self,
        node: roxmltree::Node,
        allowed: &[&str],
        required: &[&str],
    ) -> Result<(), SceneError> {
        let tag = node.tag_name().name();
        for attr in node.attributes() {
            if !allowed.contains(&attr.name()) {
                return Err(invalid(
                    &self.loc(node),
                    format!("unexpected attribute '{}' on <{tag}>", attr.name()),
                ));
            }
        }
        for r in required {
            if node.attribute(*r).is_none() {
                return Err(invalid(
                    &self.loc(node),
                    format!("<{tag}> is missing the '{r}' attribute"),
                ));
            }
        }
        Ok(())
    }

    /// Apply `$name` substitution to an attribute value. `\$` escapes a dollar.
    fn subst(&self, node: roxmltree::Node, value: &str) -> Result<String, SceneError> {
        if !value.contains('$') {
            return Ok(value.to_string());
        }
        let mut out = String::with_capacity(value.len());
        let mut chars = value.char_indices().peekable();
        while let Some((i, c)) = chars.next() {
            if c == '\\' && value[i + 1..].starts_with('$') {
                out.push('$');
                chars.next();
                continue;
            }
            if c != '$' {
                out.push(c);
                continue;
            }
            let start = i + 1;
            let mut end = start;
            while let Some(&(j, d)) = chars.peek() {
                if d.is_ascii_alphanumeric() || d == '_' {
                    end = j + d.len_utf8();
                    chars.next();
                } else {
                    break;
                }
            }
            let name = &value[start..end];
            if !self.s.used.borrow().contains(name) {
                self.s.used.borrow_mut().insert(name.to_string());
            }
            match self.s.params.get(name) {
                Some(v) if !name.is_empty() => {
                    let total = self.s.substituted.get().saturating_add(v.len());
                    if total > self.s.max_substituted {
                        return Err(invalid(
                            &self.loc(node),
                            format!(
                                "substituting ${name} would make the scene's substituted text \
                                 longer than {} bytes (Limits::max_substituted_bytes)",
                                self.s.max_substituted
                            ),
                        ));
                    }
                    self.s.substituted.set(total);
                    out.push_str(v)
                }
                _ => {
                    return Err(invalid(
                        &self.loc(node),
                        format!("undefined parameter: ${name} (declare it with <default> or pass -D {name}=...)"),
                    ))
                }
            }
        }
        Ok(out)
    }

    /// Attribute value with substitution applied.
    fn attr(&self, node: roxmltree::Node, name: &str) -> Result<Option<String>, SceneError> {
        node.attribute(name)
            .map(|v| self.subst(node, v))
            .transpose()
    }

    fn req_attr(&self, node: roxmltree::Node, name: &str) -> Result<String, SceneError> {
        self.attr(node, name)?.ok_or_else(|| {
            invalid(
                &self.loc(node),
                format!(
                    "<{}> is missing the '{name}' attribute",
                    node.tag_name().name()
                ),
            )
        })
    }

    /// A finite number (NaN, infinities and overflowing literals such as 1e400 are errors).
    fn parse_f64(&self, node: roxmltree::Node, what: &str, s: &str) -> Result<f64, SceneError> {
        let tag = node.tag_name().name();
        let v = s.trim().parse::<f64>().map_err(|_| {
            invalid(
                &self.loc(node),
                format!("could not parse {what} value \"{s}\" in <{tag}>"),
            )
        })?;
        if !v.is_finite() {
            return Err(invalid(
                &self.loc(node),
                format!("{what} value \"{s}\" in <{tag}> is not a finite number"),
            ));
        }
        Ok(v)
    }

    /// x/y/z attributes (each defaulting to `default`) or a `value` of 1 or 3 numbers.
    fn parse_xyz(&self, node: roxmltree::Node, default: f64) -> Result<DVec3, SceneError> {
        if let Some(v) = self.attr(node, "value")? {
            if node.attribute("x").is_some()
                || node.attribute("y").is_some()
                || node.attribute("z").is_some()
            {
                return Err(invalid(
                    &self.loc(node),
                    "cannot mix \"value\" and \"x\"/\"y\"/\"z\" attributes",
                ));
            }
            return self.parse_vec_str(node, &v, true);
        }
        let mut out = [default; 3];
        for (k, name) in ["x", "y", "z"].iter().enumerate() {
            if let Some(s) = self.attr(node, name)? {
                out[k] = self.parse_f64(node, "numeric", &s)?;
            }
        }
        Ok(DVec3::from_array(out))
    }

    /// "x y z" (or "x, y, z"); with `allow_single`, a single number is replicated.
    fn parse_vec_str(
        &self,
        node: roxmltree::Node,
        s: &str,
        allow_single: bool,
    ) -> Result<DVec3, SceneError> {
        let toks = tokenize(s);
        let nums = toks
            .iter()
            .map(|t| self.parse_f64(node, "numeric", t))
            .collect::<Result<Vec<_>, _>>()?;
        match nums.len() {
            1 if allow_single => Ok(DVec3::splat(nums[0])),
            3 => Ok(DVec3::new(nums[0], nums[1], nums[2])),
            n => Err(invalid(
                &self.loc(node),
                format!(
                    "expected 3 values in <{}>, got {n} (\"{s}\")",
                    node.tag_name().name()
                ),
            )),
        }
    }

    /// A `<spectrum>` value: one number, or `wavelength:value` pairs with strictly
    /// increasing wavelengths (at least two, at most [`MAX_SPECTRUM_PAIRS`]).
    fn parse_spectrum(&self, node: roxmltree::Node, s: &str) -> Result<Spectrum, SceneError> {
        let loc = self.loc(node);
        let toks = tokenize(s);
        if toks.len() == 1 && !toks[0].contains(':') {
            return Ok(Spectrum::Uniform(
                self.parse_f64(node, "spectrum", toks[0])? as f32,
            ));
        }
        let shown = bounded(s);
        if toks.len() < 2 || toks.len() > MAX_SPECTRUM_PAIRS {
            let msg = format!(
                "<spectrum value=\"{shown}\">: one value, or 2 to {MAX_SPECTRUM_PAIRS} \
                 wavelength:value pairs"
            );
            return Err(invalid(&loc, msg));
        }
        let mut pairs: Vec<(f32, f32)> = Vec::with_capacity(toks.len());
        for t in toks {
            let Some((w, v)) = t.split_once(':') else {
                let msg = format!(
                    "<spectrum>: \"{}\" is not a wavelength:value pair",
                    bounded(t)
                );
                return Err(invalid(&loc, msg));
            };
            let w = self.parse_f64(node, "wavelength", w)? as f32;
            let v = self.parse_f64(node, "spectrum value", v)? as f32;
            if !(w.is_finite() && v.is_finite()) {
                let msg = format!("<spectrum>: \"{}\" is not finite", bounded(t));
                return Err(invalid(&loc, msg));
            }
            if pairs.last().is_some_and(|&(prev, _)| w <= prev) {
                let msg = format!("<spectrum value=\"{shown}\">: wavelengths must increase");
                return Err(invalid(&loc, msg));
            }
            pairs.push((w, v));
        }
        Ok(Spectrum::Pairs(pairs))
    }

    fn parse_element(&mut self, node: roxmltree::Node) -> Result<Element, SceneError> {
        let tag = node.tag_name().name();
        let loc = self.loc(node);
        if let Some(category) = Category::from_tag(tag) {
            return Ok(Element::Object(self.parse_object(node, category)?));
        }
        if tag == "ref" {
            self.check_attrs(node, &["id", "name"], &["id"])?;
            let id = self.req_attr(node, "id")?;
            let name = self.attr(node, "name")?;
            return Ok(Element::Object(Child {
                name,
                obj: ObjRef::Ref { id, loc },
            }));
        }
        let name_attr = |p: &Self| p.req_attr(node, "name");
        let value = match tag {
            "float" | "integer" | "boolean" | "string" | "rgb" => {
                self.check_attrs(node, &["name", "value"], &["name", "value"])?;
                let s = self.req_attr(node, "value")?;
                match tag {
                    "float" => Value::Float(self.parse_f64(node, "floating point", &s)?),
                    "integer" => Value::Integer(s.trim().parse::<i64>().map_err(|_| {
                        invalid(&loc, format!("could not parse integer value \"{s}\""))
                    })?),
                    "boolean" => match s.trim().to_ascii_lowercase().as_str() {
                        "true" => Value::Boolean(true),
                        "false" => Value::Boolean(false),
                        _ => {
                            return Err(invalid(
                                &loc,
                                format!("could not parse boolean value \"{s}\" -- must be \"true\" or \"false\""),
                            ))
                        }
                    },
                    "string" => Value::String(s),
                    _ => Value::Rgb(self.parse_vec_str(node, &s, true)?.as_vec3()),
                }
            }
            "spectrum" => {
                self.check_attrs(node, &["name", "value", "filename", "type"], &["name"])?;
                if node.attribute("type").is_some() || node.attribute("filename").is_some() {
                    return Err(invalid(
                        &loc,
                        "<spectrum> is supported as a value or as wavelength:value pairs \
                         (value=\"0.5\", value=\"400:0.1, 700:0.5\"); spectral files and \
                         plugins are not supported",
                    ));
                }
                let s = self.req_attr(node, "value")?;
                Value::Spectrum(self.parse_spectrum(node, &s)?)
            }
            "point" | "vector" => {
                self.check_attrs(node, &["name", "value", "x", "y", "z"], &["name"])?;
                let v = if let Some(s) = self.attr(node, "value")? {
                    if node.attribute("x").is_some()
                        || node.attribute("y").is_some()
                        || node.attribute("z").is_some()
                    {
                        return Err(invalid(
                            &loc,
                            "cannot mix \"value\" and \"x\"/\"y\"/\"z\" attributes",
                        ));
                    }
                    self.parse_vec_str(node, &s, true)?
                } else {
                    for c in ["x", "y", "z"] {
                        if node.attribute(c).is_none() {
                            return Err(invalid(
                                &loc,
                                format!("<{tag}> is missing the '{c}' attribute"),
                            ));
                        }
                    }
                    self.parse_xyz(node, 0.0)?
                };
                if tag == "point" {
                    Value::Point(v)
                } else {
                    Value::Vector(v)
                }
            }
            "transform" => {
                self.check_attrs(node, &["name"], &["name"])?;
                let name = self.req_attr(node, "name")?;
                Value::Transform(self.parse_transform(node).map_err(|e| match e {
                    SceneError::Invalid {
                        file,
                        line,
                        message,
                    } => SceneError::Invalid {
                        file,
                        line,
                        message: format!("<transform name=\"{name}\">: {message}"),
                    },
                    other => other,
                })?)
            }
            "default" | "path" => {
                return Err(invalid(
                    &loc,
                    format!("<{tag}> is only allowed directly inside <scene>"),
                ))
            }
            "include" => {
                return Err(invalid(
                    &loc,
                    "<include> is supported only directly inside <scene>",
                ))
            }
            _ => return Err(invalid(&loc, format!("unsupported XML element <{tag}>"))),
        };
        Ok(Element::Prop(Prop {
            name: name_attr(self)?,
            value,
            loc,
        }))
    }

    fn parse_object(
        &mut self,
        node: roxmltree::Node,
        category: Category,
    ) -> Result<Child, SceneError> {
        self.check_attrs(node, &["type", "id", "name"], &["type"])?;
        let loc = self.loc(node);
        let plugin = self.req_attr(node, "type")?;
        let id = self.attr(node, "id")?;
        let name = self.attr(node, "name")?;
        let mut props: Vec<Prop> = Vec::new();
        let mut children = Vec::new();
        for c in node.children() {
            if c.is_text() && !c.text().unwrap_or_default().trim().is_empty() {
                return Err(invalid(
                    &self.loc(c),
                    format!("unexpected text inside <{}>", category.tag()),
                ));
            }
            if !c.is_element() {
                continue;
            }
            match self.parse_element(c)? {
                Element::Object(child) => children.push(child),
                Element::Prop(p) => {
                    if let Some(prev) = props.iter().find(|q| q.name == p.name) {
                        return Err(invalid(
                            &p.loc,
                            format!(
                                "property '{}' is specified twice (first at line {})",
                                p.name, prev.loc.line
                            ),
                        ));
                    }
                    props.push(p)
                }
            }
        }
        if self.legacy {
            upgrade_from_v1(&plugin, &mut props, &mut children)?;
        }
        let n = Rc::new(Node {
            category,
            plugin,
            id: id.clone(),
            props,
            children,
            loc: loc.clone(),
        });
        if let Some(id) = id {
            if let Some(prev) = self.s.ids.get(&id) {
                return Err(invalid(
                    &loc,
                    format!(
                        "duplicate id '{id}' (first declared at line {})",
                        prev.loc.line
                    ),
                ));
            }
            self.s.ids.insert(id, n.clone());
        }
        Ok(Child {
            name,
            obj: ObjRef::Inline(n),
        })
    }

    fn parse_transform(&self, node: roxmltree::Node) -> Result<DMat4, SceneError> {
        let mut m = DMat4::IDENTITY;
        for c in node.children() {
            if c.is_text() && !c.text().unwrap_or_default().trim().is_empty() {
                return Err(invalid(&self.loc(c), "unexpected text inside <transform>"));
            }
            if !c.is_element() {
                continue;
            }
            let loc = self.loc(c);
            let tag = c.tag_name().name();
            let op = match tag {
                "translate" => {
                    self.check_attrs(c, &["x", "y", "z", "value"], &[])?;
                    DMat4::from_translation(self.parse_xyz(c, 0.0)?)
                }
                "scale" => {
                    self.check_attrs(c, &["x", "y", "z", "value"], &[])?;
                    DMat4::from_scale(self.parse_xyz(c, 1.0)?)
                }
                "rotate" => {
                    self.check_attrs(c, &["x", "y", "z", "value", "angle"], &["angle"])?;
                    let axis = self.parse_xyz(c, 0.0)?;
                    if axis == DVec3::ZERO {
                        return Err(invalid(&loc, "rotation axis cannot be zero"));
                    }
                    let angle = self.parse_f64(c, "angle", &self.req_attr(c, "angle")?)?;
                    if (axis.length() - 1.0).abs() > 1e-6 {
                        self.s.warnings.borrow_mut().push(format!(
                            "{loc}: rotation axis ({}, {}, {}) is not of unit length; like \
                             Mitsuba 3, it is used as given, which also scales",
                            axis.x, axis.y, axis.z
                        ));
                    }
                    transform::rotate(axis, angle)
                }
                // `lookAt`: Mitsuba 0.x files (Mitsuba 0.6 read it; Mitsuba 3 does not).
                "lookat" | "lookAt" if tag == "lookat" || self.legacy => {
                    self.check_attrs(c, &["origin", "target", "up"], &["origin", "target"])?;
                    let origin = self.parse_vec_str(c, &self.req_attr(c, "origin")?, false)?;
                    let target = self.parse_vec_str(c, &self.req_attr(c, "target")?, false)?;
                    let up = match self.attr(c, "up")? {
                        Some(s) => {
                            let up = self.parse_vec_str(c, &s, false)?;
                            if up == DVec3::ZERO {
                                return Err(invalid(
                                    &loc,
                                    "lookat: 'up' is the zero vector (omit it to let the \
                                     camera choose one, or give a direction)",
                                ));
                            }
                            up
                        }
                        None => DVec3::ZERO,
                    };
                    transform::look_at(origin, target, up).ok_or_else(|| {
                        invalid(
                            &loc,
                            "invalid lookat transformation (degenerate origin/target/up)",
                        )
                    })?
                }
                "matrix" => {
                    self.check_attrs(c, &["value"], &["value"])?;
                    let s = self.req_attr(c, "value")?;
                    let toks = tokenize(&s);
                    let n = match toks.len() {
                        16 => 4,
                        9 => 3,
                        k => {
                            return Err(invalid(
                                &loc,
                                format!("matrix must have 9 or 16 values, got {k}"),
                            ))
                        }
                    };
                    let mut rows = DMat4::IDENTITY.to_cols_array_2d(); // used as rows
                    for i in 0..n {
                        for j in 0..n {
                            rows[i][j] = self.parse_f64(c, "matrix", toks[i * n + j])?;
                        }
                    }
                    if rows[3] != [0.0, 0.0, 0.0, 1.0] {
                        return Err(invalid(
                            &loc,
                            format!(
                                "projective matrix (last row {:?}): only affine transforms \
                                 (last row 0 0 0 1) are supported",
                                rows[3]
                            ),
                        ));
                    }
                    // `rows` holds the matrix row-major; glam stores columns.
                    DMat4::from_cols_array_2d(&rows).transpose()
                }
                other => {
                    return Err(invalid(
                        &loc,
                        format!("unexpected <{other}> element inside <transform>"),
                    ))
                }
            };
            m = op * m;
            if !m.is_finite() {
                return Err(invalid(&loc, "transform contains non-finite values"));
            }
        }
        Ok(m)
    }
}

/// Location of the root element (line 1 fallback), for scene-wide errors.
pub(crate) fn root_loc(path: &Path) -> Location {
    let line = std::fs::read_to_string(path)
        .ok()
        .and_then(|t| {
            t.lines()
                .position(|l| l.contains("<scene"))
                .map(|i| i as u32 + 1)
        })
        .unwrap_or(1);
    Location {
        file: path.to_path_buf(),
        line,
    }
}

/// The scene file's text: at most `limits.max_scene_file_bytes`, UTF-8 (UTF-16 and other
/// encodings are refused by name).
/// The text of scene file `path`, `already` bytes of scene text having been read for the
/// scene (an included file counts against the scene's limit).
fn read_scene_text(
    path: &Path,
    limits: &crate::Limits,
    already: u64,
) -> Result<String, SceneError> {
    let max = limits.max_scene_file_bytes.saturating_sub(already);
    let here = |message: String| {
        invalid(
            &Location {
                file: path.to_path_buf(),
                line: 1,
            },
            message,
        )
    };
    let meta = std::fs::metadata(path).map_err(|error| SceneError::Io {
        file: path.to_path_buf(),
        error,
    })?;
    if meta.is_dir() {
        return Err(here("is a directory, not a scene file".into()));
    }
    if meta.len() > max {
        return Err(here(format!(
            "the scene file is {} bytes, more than the {} left of the limit of {} \
             (Limits::max_scene_file_bytes, for the scene and the files it includes)",
            meta.len(),
            max,
            limits.max_scene_file_bytes
        )));
    }
    let bytes = std::fs::read(path).map_err(|error| SceneError::Io {
        file: path.to_path_buf(),
        error,
    })?;
    if bytes.len() as u64 > max {
        return Err(here(format!(
            "the scene file grew past the limit of {} bytes while being read",
            limits.max_scene_file_bytes
        )));
    }
    if bytes.starts_with(&[0xFF, 0xFE]) || bytes.starts_with(&[0xFE, 0xFF]) {
        return Err(here(
            "the file is UTF-16 encoded; only UTF-8 scene files are supported".into(),
        ));
    }
    let bytes = bytes.strip_prefix(&[0xEF, 0xBB, 0xBF]).unwrap_or(&bytes);
    String::from_utf8(bytes.to_vec()).map_err(|e| {
        let at = e.utf8_error().valid_up_to();
        let line = bytes[..at].iter().filter(|&&b| b == b'\n').count() as u32 + 1;
        invalid(
            &Location {
                file: path.to_path_buf(),
                line,
            },
            format!("not valid UTF-8 (byte {at}); only UTF-8 scene files are supported"),
        )
    })
}

/// `MAJOR.MINOR.PATCH` in decimal digits.
fn is_version(v: &str) -> bool {
    let parts: Vec<&str> = v.split('.').collect();
    parts.len() == 3
        && parts
            .iter()
            .all(|p| !p.is_empty() && p.len() <= 9 && p.bytes().all(|b| b.is_ascii_digit()))
}

/// Checks, before the XML parser sees the text (its recursion, and ours over the plugin tree,
/// would exhaust the stack), that elements nest at most `max_depth` deep. Returns the line of
/// the first element past the limit. A conservative scan: it skips comments, CDATA,
/// processing instructions, declarations and quoted attribute values; malformed markup is
/// left for the parser to report.
pub(crate) fn check_nesting(text: &str, max_depth: usize) -> Result<(), u32> {
    let b = text.as_bytes();
    let (mut i, mut depth, mut line) = (0usize, 0usize, 1u32);
    let skip_to = |from: usize, pat: &[u8]| -> usize {
        b[from..]
            .windows(pat.len())
            .position(|w| w == pat)
            .map_or(b.len(), |p| from + p + pat.len())
    };
    while i < b.len() {
        if b[i] == b'\n' {
            line += 1;
        }
        if b[i] != b'<' {
            i += 1;
            continue;
        }
        let rest = &b[i..];
        let end = if rest.starts_with(b"<!--") {
            skip_to(i + 4, b"-->")
        } else if rest.starts_with(b"<![CDATA[") {
            skip_to(i + 9, b"]]>")
        } else if rest.starts_with(b"<?") {
            skip_to(i + 2, b"?>")
        } else if rest.starts_with(b"<!") {
            skip_to(i + 2, b">")
        } else if rest.starts_with(b"</") {
            depth = depth.saturating_sub(1);
            skip_to(i + 2, b">")
        } else {
            let (end, self_closing) = scan_start_tag(b, i + 1);
            if !self_closing {
                depth += 1;
                if depth > max_depth {
                    return Err(line);
                }
            }
            end
        };
        line += b[i + 1..end.min(b.len())]
            .iter()
            .filter(|&&c| c == b'\n')
            .count() as u32;
        i = end;
    }
    Ok(())
}

/// From just after a `<`: the index after the tag's `>`, and whether it ends in `/>`.
fn scan_start_tag(b: &[u8], mut i: usize) -> (usize, bool) {
    let mut quote = None;
    while i < b.len() {
        let c = b[i];
        match quote {
            Some(q) if c == q => quote = None,
            Some(_) => {}
            None if c == b'"' || c == b'\'' => quote = Some(c),
            None if c == b'>' => return (i + 1, i > 0 && b[i - 1] == b'/'),
            None => {}
        }
        i += 1;
    }
    (b.len(), false)
}

#[cfg(test)]
mod tests {
    use super::camel_to_snake;

    #[test]
    fn the_upgrade_turns_camel_case_into_snake_case_as_mitsuba_does() {
        for (old, new) in [
            ("maxDepth", "max_depth"),
            ("intIOR", "int_ior"),
            ("toWorld", "to_world"),
            ("fovAxis", "fov_axis"),
            ("specularReflectance", "specular_reflectance"),
            ("sampleCount", "sample_count"),
            ("radiance", "radiance"),
            ("alphaU", "alpha_u"),
        ] {
            assert_eq!(camel_to_snake(old), new);
        }
    }

    use super::check_nesting;

    #[test]
    fn nesting_check_counts_elements_and_skips_markup_that_does_not_nest() {
        let ok = "<a>\n<!-- <b><b><b> -->\n<b x='<c>' y=\"/>\"/><![CDATA[<d><d>]]><?pi <e>?></a>";
        assert_eq!(check_nesting(ok, 1), Ok(()));
        assert_eq!(check_nesting("<a>\n<b>\n<c/></b></a>", 1), Err(2));
        let deep = "<a>".repeat(101);
        assert_eq!(check_nesting(&deep, 100), Err(1));
        assert_eq!(check_nesting(&deep, 101), Ok(()));
    }
}
