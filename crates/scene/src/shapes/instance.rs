//! Mitsuba's `shapegroup` and `instance`: a group of shapes declared once (with an id, not
//! rendered itself) and placed any number of times by instances, each with its own
//! `to_world`. Each instance becomes copies of the group's shapes in world space (the group
//! built once, in the group's space, then transformed per instance), so the renderer sees
//! plain shapes; each copy's memory is accounted for against `Limits::max_memory_bytes`.
//! As in Mitsuba 3, a group holds no emitters and no nested groups.

use std::collections::HashMap;
use std::sync::Arc;

use glam::DMat4;

use super::mesh;
use crate::context::Ctx;
use crate::desc::{Geometry, ShapeDesc};
use crate::error::SceneError;
use crate::props::Resolved;
use crate::transform::similarity_scale;
use crate::xml::{invalid, Category};

/// The shapes of groups built so far, by the group's id.
#[derive(Default)]
pub(crate) struct Groups(HashMap<String, Arc<Vec<ShapeDesc>>>);

/// The shapes of `shapegroup` node `r`, in the group's space.
fn group(ctx: &mut Ctx, r: &Resolved) -> Result<Vec<ShapeDesc>, SceneError> {
    let p = ctx.props(&r.node)?;
    let children = p.children_of(Category::Shape);
    p.finish()?;
    let mut out = Vec::with_capacity(children.len());
    for c in &children {
        if matches!(c.node.plugin.as_str(), "shapegroup" | "instance") {
            let msg = format!(
                "a shapegroup cannot hold a {} (as in Mitsuba 3)",
                c.node.plugin
            );
            return Err(invalid(&c.loc, msg));
        }
        let s = super::shape(ctx, c)?;
        if s.emitter.is_some() {
            let msg = "a shape in a shapegroup cannot emit light (as in Mitsuba 3)";
            return Err(invalid(&c.loc, msg));
        }
        out.push(s);
    }
    Ok(out)
}

/// The shapes `instance` node `r` places: its group's, transformed by its `to_world`.
pub(crate) fn instance(
    ctx: &mut Ctx,
    r: &Resolved,
    groups: &mut Groups,
) -> Result<Vec<ShapeDesc>, SceneError> {
    let p = ctx.props(&r.node)?;
    let to_world = p.transform("to_world")?;
    let what = p.what();
    let g = p.at_most_one(Category::Shape, &what)?;
    p.finish()?;
    let Some(g) = g.filter(|g| g.node.plugin == "shapegroup") else {
        return Err(invalid(
            &r.loc,
            "an instance needs one shapegroup (a <ref> to its id)",
        ));
    };
    let key = g
        .node
        .id
        .clone()
        .unwrap_or_else(|| format!("{}", g.node.loc));
    let shapes = match groups.0.get(&key) {
        Some(s) => s.clone(),
        None => {
            let built = Arc::new(group(ctx, &g)?);
            groups.0.insert(key, built.clone());
            built
        }
    };
    let mut out = Vec::with_capacity(shapes.len());
    for s in shapes.iter() {
        let geometry = placed(ctx, &s.geometry, to_world, r)?;
        out.push(ShapeDesc {
            geometry,
            location: r.loc.clone(),
            ..s.clone()
        });
    }
    Ok(out)
}

/// `g` (in the group's space) placed by `m`.
fn placed(ctx: &mut Ctx, g: &Geometry, m: DMat4, r: &Resolved) -> Result<Geometry, SceneError> {
    Ok(match g {
        Geometry::Mesh(mesh) => {
            let what = format!("an instance of {} triangles", mesh.indices.len());
            ctx.reserve_memory(mesh.data_bytes(), &what, &r.loc)?;
            let face_normals = mesh.normals.is_none();
            let flip = mesh.flip_normals;
            let copy = (**mesh).clone();
            let m = mesh::finalize(copy, m, face_normals, flip, "instance", &r.loc, &r.loc)?;
            Geometry::Mesh(Arc::new(m))
        }
        Geometry::Sphere {
            center,
            radius,
            flip_normals,
        } => {
            let Some(scale) = similarity_scale(m) else {
                let msg = "an instance of a sphere must be placed by a similarity \
                           (rotation, uniform scale, translation)";
                return Err(invalid(&r.loc, msg));
            };
            // An instance transforms the sphere's normals with its points: a mirroring
            // instance keeps them outward (Mitsuba 3 does), unlike a sphere's own
            // mirroring `to_world`.
            Geometry::Sphere {
                center: m.transform_point3(center.as_dvec3()).as_vec3(),
                radius: (*radius as f64 * scale) as f32,
                flip_normals: *flip_normals,
            }
        }
        Geometry::Disk {
            to_world,
            flip_normals,
        } => Geometry::Disk {
            to_world: (m * to_world.as_dmat4()).as_mat4(),
            flip_normals: *flip_normals,
        },
        Geometry::Cylinder {
            to_world,
            flip_normals,
        } => {
            let t = m * to_world.as_dmat4();
            if similarity_scale(m).is_none() {
                let msg = "an instance of a cylinder must be placed by a similarity";
                return Err(invalid(&r.loc, msg));
            }
            Geometry::Cylinder {
                to_world: t.as_mat4(),
                flip_normals: *flip_normals,
            }
        }
    })
}
