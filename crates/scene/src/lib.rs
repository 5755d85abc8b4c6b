//! Loading Mitsuba 3 XML scenes into a [`SceneDesc`].
//!
//! The loader resolves `<default>` / `$name` substitution (with command-line
//! overrides taking precedence), `id` / `ref`, nested plugins, `to_world`
//! transforms, loads OBJ / PLY meshes and bitmap / EXR images, and validates
//! everything. Unsupported plugins and unknown parameters are errors that name
//! the file and line: the loader never substitutes silently.
//!
//! Invariant: this crate knows nothing of rays, sampling or rendering.
//!
//! Pipeline: [`xml`] parses the file into a generic plugin tree; [`props`]
//! gives typed, consumed-tracked access to each plugin's parameters; the
//! plugin modules ([`shapes`], [`bsdfs`], [`textures`], [`emitters`],
//! [`sensor`], [`integrator`]) build the description.

// Validity checks are written `!(x > 0.0)` on purpose: they also reject NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod bsdfs;
// The tables keep the digits they were generated with (f64 text of the published values).
#[allow(clippy::excessive_precision)]
mod cie;
mod context;
pub mod desc;
mod emitters;
mod error;
mod imageio;
mod integrator;
mod ior;
pub mod limits;
mod props;
mod sensor;
mod shapes;
mod spectrum;
mod textures;
mod transform;
mod world_source;
mod xml;

pub use desc::*;
pub use error::{shown_bounded, SceneError};
pub use imageio::srgb_to_linear;
pub use limits::Limits;
pub use world_source::world_source;

use std::path::Path;
use std::rc::Rc;

use context::{Ctx, Reading};
use xml::{invalid, Category};

/// Load a Mitsuba 3 XML scene. `overrides` are `-D name=value` pairs; they
/// replace the values of `<default>` declarations and define `$name`s the file
/// references without declaring. An override the file neither declares nor
/// references becomes a parameter of the scene's integrator (so
/// `-D preset=2019` sets `guided_path`'s preset on a file whose integrator
/// block only says `max_depth`); if the integrator has no such parameter, or
/// the file has no `<integrator>`, loading fails with an error naming it.
pub fn load_scene(path: &Path, overrides: &[(String, String)]) -> Result<SceneDesc, SceneError> {
    load_scene_with_limits(path, overrides, &Limits::default())
}

/// [`load_scene`] with the given resource limits: every size the file (or an override) turns
/// into memory or work is checked against `limits` before it is allocated, and with
/// `limits.confine_files` the scene may read only files inside its own directory
/// ([`Limits::confine_files`]). [`SceneDesc::files`] lists the files it read.
pub fn load_scene_with_limits(
    path: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
) -> Result<SceneDesc, SceneError> {
    load(path, overrides, limits, Reading::Contents, None)
}

/// The files the scene `path` reads ([`SceneDesc::files`]: the scene file first), learned
/// without decoding them: the XML is parsed and checked as [`load_scene_with_limits`] checks
/// it, each file it names is resolved (confined with `limits.confine_files`) and opened, and
/// an image's header is read for its size limits; meshes and images are not decoded. A
/// bundler needs only the names, and decoding is most of a load's time
/// (docs/farm-performance.md); what the contents may still get wrong, the full load at the
/// other end finds.
pub fn scene_files(
    path: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
) -> Result<Vec<std::path::PathBuf>, SceneError> {
    Ok(load(path, overrides, limits, Reading::Names, None)?.files)
}

/// [`load_scene_with_limits`] with the scene's integrator replaced by `integrator` (the
/// command line's `--integrator NAME`; `None`: as written). The replacement keeps the
/// parameters every integrator here reads the same way (`max_depth`, `rr_depth`,
/// `hide_emitters`) and drops the others; [`SceneDesc::warnings`] says what it replaced and
/// dropped. A scene without an `<integrator>` gets one.
pub fn load_scene_as(
    path: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
    integrator: Option<&str>,
) -> Result<SceneDesc, SceneError> {
    load(path, overrides, limits, Reading::Contents, integrator)
}

/// [`load_scene_as`] without decoding images (each one's header read and checked against
/// the limits, a stand-in in its place): meshes and everything else as the full load has
/// them, so the scene's bounds and every check but an image's pixels are the full load's.
/// For a scene nothing is rendered from (a farm's validation of a submission: its workers
/// decode the images and fail the job if one is bad).
pub fn load_scene_geometry_as(
    path: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
    integrator: Option<&str>,
) -> Result<SceneDesc, SceneError> {
    load(path, overrides, limits, Reading::Geometry, integrator)
}

/// The scene as [`scene_files_as`] reads it (files named and opened, not decoded): its
/// [`SceneDesc::files`] and [`SceneDesc::warnings`] are those of the full load; its meshes and
/// images are stand-ins.
pub fn scan_scene_as(
    path: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
    integrator: Option<&str>,
) -> Result<SceneDesc, SceneError> {
    load(path, overrides, limits, Reading::Names, integrator)
}

/// [`scene_files`] of the scene with its integrator replaced ([`load_scene_as`]).
pub fn scene_files_as(
    path: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
    integrator: Option<&str>,
) -> Result<Vec<std::path::PathBuf>, SceneError> {
    Ok(load(path, overrides, limits, Reading::Names, integrator)?.files)
}

fn load(
    path: &Path,
    overrides: &[(String, String)],
    limits: &Limits,
    reading: Reading,
    replace: Option<&str>,
) -> Result<SceneDesc, SceneError> {
    let parsed = xml::parse_file(path, overrides, limits)?;
    let mut ctx = Ctx::new(parsed.ids, parsed.base_dir, limits.clone(), reading);
    ctx.warnings = parsed.warnings;
    ctx.search_paths = parsed.search_paths;
    // The scene file first (a bundle's root is its first file), then what it includes.
    ctx.record_file(path);
    for f in &parsed.included {
        ctx.record_file(f);
    }
    let mut integrator_desc = None;
    let mut sensor_desc = None;
    let mut shape_descs = Vec::new();
    let mut emitter_descs = Vec::new();

    let mut unused = parsed.unused_overrides;
    let mut groups = shapes::instance::Groups::default();
    for child in &parsed.objects {
        let mut r = props::resolve(child, &ctx.ids)?;
        match r.node.category {
            Category::Integrator => {
                if let Some(name) = replace {
                    r.node = Rc::new(replaced_integrator(&r.node, name, &mut ctx.warnings));
                }
                if !unused.is_empty() {
                    r.node = Rc::new(with_command_line_params(
                        &r.node,
                        std::mem::take(&mut unused),
                    ));
                }
                if integrator_desc.is_some() {
                    return Err(invalid(
                        &r.loc,
                        "only one integrator can be specified per scene",
                    ));
                }
                integrator_desc = Some(integrator::integrator(&ctx, &r)?);
            }
            Category::Sensor => {
                let s = sensor::sensor(&mut ctx, &r)?;
                if sensor_desc.is_none() {
                    sensor_desc = Some(s);
                } else {
                    ctx.warnings.push(format!(
                        "{}: additional sensor ignored (the first one is used)",
                        r.loc
                    ));
                }
            }
            // A group is built where an instance places it.
            Category::Shape if r.node.plugin == "shapegroup" => {}
            Category::Shape if r.node.plugin == "instance" => {
                shape_descs.extend(shapes::instance::instance(&mut ctx, &r, &mut groups)?)
            }
            Category::Shape => shape_descs.push(shapes::shape(&mut ctx, &r)?),
            Category::Bsdf => {
                // Built now (validated, cached by identity) so refs reuse it.
                bsdfs::bsdf(&mut ctx, &r)?;
            }
            Category::Texture => {
                textures::texture(&mut ctx, &r)?;
            }
            // An area emitter declared at the top with an id that a shape references is
            // the shape's (Mitsuba 3 accepts it so): it is built where the shape names it.
            Category::Emitter if is_shared_area_emitter(&r.node, &parsed.objects) => {}
            Category::Emitter => emitter_descs.push(emitters::emitter(&mut ctx, &r)?),
            Category::Film | Category::RFilter | Category::Sampler => {
                return Err(invalid(
                    &r.loc,
                    format!(
                    "<{}> must be nested inside a sensor (film inside sensor, rfilter inside film)",
                    r.node.category.tag()
                ),
                ))
            }
        }
    }

    if let (Some(name), None) = (replace, &integrator_desc) {
        let node = xml::Node {
            category: Category::Integrator,
            plugin: name.to_string(),
            id: None,
            props: Vec::new(),
            children: Vec::new(),
            loc: xml::root_loc(path),
        };
        let node = with_command_line_params(&node, std::mem::take(&mut unused));
        let child = xml::Child {
            name: None,
            obj: xml::ObjRef::Inline(Rc::new(node)),
        };
        let r = props::resolve(&child, &ctx.ids)?;
        integrator_desc = Some(integrator::integrator(&ctx, &r)?);
    }
    if let Some((name, value)) = unused.first() {
        return Err(invalid(
            &xml::root_loc(path),
            format!(
                "-D {name}={value}: the scene does not use ${name} and has no <integrator> \
                 block to take it as a parameter"
            ),
        ));
    }
    let sensor = sensor_desc.ok_or_else(|| invalid(&xml::root_loc(path), "scene has no sensor"))?;
    let integrator = integrator_desc.unwrap_or(IntegratorDesc::Path(PathParams::default()));
    let features = features(&shape_descs, &ctx.bsdfs, &emitter_descs);
    Ok(SceneDesc {
        source: path.to_path_buf(),
        integrator,
        sensor,
        shapes: shape_descs,
        bsdfs: ctx.bsdfs,
        textures: ctx.textures,
        emitters: emitter_descs,
        features,
        warnings: ctx.warnings,
        limits: ctx.limits,
        files: ctx.files,
    })
}

/// The integrator `node` with the `-D` overrides the file does not use as its parameters: each
/// replaces a property of the same name written in the file (the command line wins, as it
/// does for `<default>`), and one the integrator does not know is an error when it is built.
/// Whether `node` is an `area` emitter with an id that a shape of `objects` references.
fn is_shared_area_emitter(node: &xml::Node, objects: &[xml::Child]) -> bool {
    let Some(id) = node.id.as_deref().filter(|_| node.plugin == "area") else {
        return false;
    };
    let shapes = objects.iter().filter_map(|c| match &c.obj {
        xml::ObjRef::Inline(n) if n.category == Category::Shape => Some(n),
        _ => None,
    });
    shapes
        .flat_map(|n| n.children.iter())
        .any(|c| matches!(&c.obj, xml::ObjRef::Ref { id: r, .. } if r == id))
}

/// The integrator `node` replaced by plugin `name`, keeping the parameters that mean the same
/// in both ([`integrator::shared_params`]); what was replaced and dropped is said in
/// `warnings`. A `moment` wrapper's settings are its single nested
/// integrator's.
fn replaced_integrator(node: &xml::Node, name: &str, warnings: &mut Vec<String>) -> xml::Node {
    let nested = match node.children.as_slice() {
        [xml::Child {
            obj: xml::ObjRef::Inline(inner),
            ..
        }] if node.plugin == "moment" && inner.category == Category::Integrator => Some(inner),
        _ => None,
    };
    let mut n = match nested {
        Some(inner) => xml::Node {
            plugin: format!("moment/{}", inner.plugin),
            ..(**inner).clone()
        },
        None => node.clone(),
    };
    let shared = integrator::shared_params(name);
    let (kept, dropped): (Vec<_>, Vec<_>) =
        (n.props.into_iter()).partition(|p| shared.contains(&p.name.as_str()));
    let mut gone: Vec<String> = dropped.into_iter().map(|p| p.name).collect();
    gone.extend(
        n.children
            .iter()
            .map(|c| c.name.clone().unwrap_or_else(|| "(object)".into())),
    );
    n.props = kept;
    n.children = Vec::new();
    let was = std::mem::replace(&mut n.plugin, name.to_string());
    let dropped = match gone.is_empty() {
        true => "nothing dropped".to_string(),
        false => format!("dropped {}", gone.join(", ")),
    };
    warnings.push(format!(
        "{}: integrator '{was}' replaced by '{name}' (--integrator); kept what it sets of \
         {}; {dropped}",
        node.loc,
        shared.join(", ")
    ));
    n
}

fn with_command_line_params(node: &xml::Node, overrides: Vec<(String, String)>) -> xml::Node {
    let mut n = node.clone();
    for (name, value) in overrides {
        n.props.retain(|p| p.name != name);
        n.props.push(xml::Prop {
            name,
            value: xml::Value::CommandLine(value),
            loc: node.loc.clone(),
        });
    }
    n
}

/// What the scene actually uses: BSDFs reachable from shapes (through
/// `twosided`), their textures, the shapes' emitters and geometry kinds,
/// and the scene-level emitters.
fn features(shapes: &[ShapeDesc], bsdfs: &[BsdfDesc], emitters: &[EmitterDesc]) -> Features {
    let mut f = Features::default();
    let mut seen = vec![false; bsdfs.len()];
    let mut stack: Vec<usize> = shapes.iter().map(|s| s.bsdf).collect();
    let tex = |t: &TexRef| matches!(t, TexRef::Texture(_));
    while let Some(i) = stack.pop() {
        if i >= bsdfs.len() || std::mem::replace(&mut seen[i], true) {
            continue;
        }
        let bsdf = &bsdfs[i];
        // Its colour parameters (any may be a texture), and whether it transmits.
        let (colours, transmits) = match bsdf {
            BsdfDesc::Diffuse { reflectance } => ([Some(reflectance), None], false),
            BsdfDesc::TwoSided { front, back } => {
                stack.extend([*front, *back]);
                continue;
            }
            BsdfDesc::Null => {
                f.pass_through = true;
                continue;
            }
            BsdfDesc::Mask { opacity, nested } => {
                f.pass_through = true;
                f.textures |= tex(opacity);
                stack.push(*nested);
                continue;
            }
            BsdfDesc::BumpMap { nested, .. } | BsdfDesc::NormalMap { nested, .. } => {
                f.perturbed_normals = true;
                f.textures = true;
                stack.push(*nested);
                continue;
            }
            BsdfDesc::Conductor {
                specular_reflectance: r,
                ..
            }
            | BsdfDesc::RoughConductor {
                specular_reflectance: r,
                ..
            } => ([Some(r), None], false),
            BsdfDesc::Dielectric {
                specular_reflectance: r,
                specular_transmittance: t,
                ..
            }
            | BsdfDesc::ThinDielectric {
                specular_reflectance: r,
                specular_transmittance: t,
                ..
            }
            | BsdfDesc::RoughDielectric {
                specular_reflectance: r,
                specular_transmittance: t,
                ..
            } => ([Some(r), Some(t)], true),
            BsdfDesc::Plastic {
                diffuse_reflectance: d,
                specular_reflectance: r,
                ..
            }
            | BsdfDesc::RoughPlastic {
                diffuse_reflectance: d,
                specular_reflectance: r,
                ..
            } => ([Some(d), Some(r)], false),
        };
        f.textures |= colours.into_iter().flatten().any(tex);
        f.transmission |= transmits;
        // The specular lobe: a microfacet one in the rough variants, a delta one otherwise.
        match bsdf {
            BsdfDesc::Diffuse { .. }
            | BsdfDesc::TwoSided { .. }
            | BsdfDesc::Mask { .. }
            | BsdfDesc::Null
            | BsdfDesc::BumpMap { .. }
            | BsdfDesc::NormalMap { .. } => {}
            BsdfDesc::RoughConductor { .. }
            | BsdfDesc::RoughDielectric { .. }
            | BsdfDesc::RoughPlastic { .. } => f.microfacets = true,
            BsdfDesc::Conductor { .. }
            | BsdfDesc::Dielectric { .. }
            | BsdfDesc::ThinDielectric { .. }
            | BsdfDesc::Plastic { .. } => f.delta_bsdfs = true,
        }
    }
    for s in shapes {
        f.area_lights |= s.emitter.is_some();
        f.analytic_shapes |= matches!(
            s.geometry,
            Geometry::Sphere { .. } | Geometry::Disk { .. } | Geometry::Cylinder { .. }
        );
    }
    for e in emitters {
        match e {
            EmitterDesc::Point { .. }
            | EmitterDesc::Spot { .. }
            | EmitterDesc::Directional { .. } => f.delta_lights = true,
            EmitterDesc::Constant { .. } | EmitterDesc::EnvMap { .. } => f.environment = true,
        }
    }
    f
}
