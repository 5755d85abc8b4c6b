//! Shape plugins: `obj`, `ply`, `serialized`, `rectangle`, `cube`, `sphere`, `disk`,
//! `cylinder`.

pub(crate) mod instance;
mod mesh;
mod obj;
mod ply;
pub(crate) mod primitives;
mod serialized;

use std::sync::Arc;

use glam::{DMat4, DVec3, Vec3};

use crate::bsdfs::bsdf;
use crate::context::{Ctx, Reading};
use crate::desc::{Geometry, ShapeDesc};
use crate::emitters::area_emitter;
use crate::error::SceneError;
use crate::props::{Props, Resolved};
use crate::transform::similarity_scale;
use crate::xml::{invalid, Category};

/// Build the shape `r`: geometry in world space, its BSDF (if none, Mitsuba's default:
/// diffuse 0.5, or black on an emitter) and optional area emitter.
pub(crate) fn shape(ctx: &mut Ctx, r: &Resolved) -> Result<ShapeDesc, SceneError> {
    let p = ctx.props(&r.node)?;
    let geometry = geometry(ctx, &p)?;

    let bsdf_node = p.at_most_one(Category::Bsdf, &p.what())?;
    let emitter = match p.at_most_one(Category::Emitter, &p.what())? {
        None => None,
        Some(e) => Some(area_emitter(ctx, &e)?),
    };
    // Mitsuba 3: a shape without a BSDF gets a diffuse one, black if the shape emits.
    let bsdf_index = match (bsdf_node, &emitter) {
        (Some(b), _) => bsdf(ctx, &b)?,
        (None, Some(_)) => ctx.black_bsdf(),
        (None, None) => ctx.default_bsdf(),
    };
    p.finish()?;
    Ok(ShapeDesc {
        id: r.node.id.clone(),
        geometry,
        bsdf: bsdf_index,
        emitter,
        location: r.node.loc.clone(),
    })
}

fn geometry(ctx: &mut Ctx, p: &Props) -> Result<Geometry, SceneError> {
    let to_world = p.transform("to_world")?;
    let flip_normals = p.bool("flip_normals", false)?;
    let loc = p.loc().clone();
    match p.plugin() {
        "obj" | "ply" | "serialized" => {
            let is_obj = p.plugin() == "obj";
            let is_serialized = p.plugin() == "serialized";
            let (name, name_loc) = p.string_opt("filename")?.ok_or_else(|| {
                invalid(
                    &loc,
                    format!("{} requires a 'filename' parameter", p.what()),
                )
            })?;
            let face_normals = p.bool("face_normals", false)?;
            // Mitsuba: OBJ flips v by default, PLY does not; a serialized file has no flag.
            let flip_tex_coords = !is_serialized && p.bool("flip_tex_coords", is_obj)?;
            let shape_index = match is_serialized {
                true => p.int_in("shape_index", 0, 0, u32::MAX as i64)? as u32,
                false => 0,
            };
            let path = ctx.resolve_path(&name, &name_loc)?;
            let input = mesh::MeshInput {
                path: &path,
                source: format!("mesh file '{}'", path.display()),
                loc: name_loc.clone(),
                flip_tex_coords,
            };
            if ctx.reading == Reading::Names {
                // Opened, not decoded: a stand-in that no renderer sees.
                input.open()?;
                let stand_in = primitives::rectangle();
                let m = mesh::finalize(stand_in, DMat4::IDENTITY, false, false, "", &loc, &loc)?;
                return Ok(Geometry::Mesh(Arc::new(m)));
            }
            let mut budget = mesh::Budget::new(ctx, &name_loc);
            // A parser (ply-rs's in particular) must not take the process down on a bad file.
            let local = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                if is_obj {
                    obj::load_obj(&input, &mut budget)
                } else if is_serialized {
                    serialized::load_serialized(&input, shape_index, &mut budget)
                } else {
                    ply::load_ply(&input, &mut budget)
                }
            }))
            .unwrap_or_else(|_| Err(input.err("the mesh parser failed (panicked) on this file")))?;
            let m = mesh::finalize(
                local,
                to_world,
                face_normals,
                flip_normals,
                &input.source,
                &name_loc,
                &loc,
            )?;
            let what = format!("{} ({} triangles)", input.source, m.indices.len());
            budget.settle(m.data_bytes(), &what)?;
            Ok(Geometry::Mesh(Arc::new(m)))
        }
        "rectangle" | "cube" => {
            let face_normals = p.bool("face_normals", false)?;
            let local = if p.plugin() == "rectangle" {
                primitives::rectangle()
            } else {
                primitives::cube()
            };
            let m = mesh::finalize(
                local,
                to_world,
                face_normals,
                flip_normals,
                p.plugin(),
                &loc,
                &loc,
            )?;
            Ok(Geometry::Mesh(Arc::new(m)))
        }
        "sphere" => {
            let center = p.point_opt("center")?.unwrap_or(Vec3::ZERO).as_dvec3();
            let radius32 = p.float("radius", 1.0)?;
            if !(radius32 > 0.0) {
                let at = p.get("radius").map_or(&loc, |r| &r.loc);
                return Err(invalid(
                    at,
                    format!("sphere: radius must be positive, got {radius32}"),
                ));
            }
            let radius = radius32 as f64;
            // Mitsuba: to_world * translate(center) * scale(radius).
            let m = to_world
                * glam::DMat4::from_translation(center)
                * glam::DMat4::from_scale(DVec3::splat(radius));
            let Some(_) = similarity_scale(m) else {
                return Err(invalid(
                    &loc,
                    "sphere: to_world must be a similarity (rotation, uniform scale, translation); \
                     non-uniform scale or shear would make an ellipsoid",
                ));
            };
            let world_radius = m.transform_vector3(DVec3::X).length();
            let world_center = m.transform_point3(DVec3::ZERO);
            if !(world_radius > 0.0) || !world_center.is_finite() || !world_radius.is_finite() {
                return Err(invalid(&loc, "sphere: radius must be positive and finite"));
            }
            let extent = world_center.abs() + DVec3::splat(world_radius);
            if !(extent.max_element() <= mesh::MAX_WORLD_COORDINATE) {
                return Err(invalid(
                    &loc,
                    format!(
                        "sphere: center ({:?}, {:?}, {:?}) and radius {world_radius:?} in world \
                         space reach {}",
                        world_center.x,
                        world_center.y,
                        world_center.z,
                        mesh::beyond_bound_message()
                    ),
                ));
            }
            // A mirroring transform turns the sphere inside out.
            let mirrored = glam::DMat3::from_mat4(m).determinant() < 0.0;
            Ok(Geometry::Sphere {
                center: world_center.as_vec3(),
                radius: world_radius as f32,
                flip_normals: flip_normals != mirrored,
            })
        }
        "disk" => {
            let m = to_world.as_mat4();
            if !m.is_finite() || glam::DMat3::from_mat4(to_world).determinant() == 0.0 {
                return Err(invalid(
                    &loc,
                    "disk: to_world must be finite and invertible",
                ));
            }
            // The unit disk's points are t + a x + b y with a^2 + b^2 <= 1.
            let extent = to_world.w_axis.truncate().abs()
                + to_world.x_axis.truncate().abs()
                + to_world.y_axis.truncate().abs();
            if !(extent.max_element() <= mesh::MAX_WORLD_COORDINATE) {
                return Err(invalid(
                    &loc,
                    format!(
                        "disk: in world space it reaches {}",
                        mesh::beyond_bound_message()
                    ),
                ));
            }
            Ok(Geometry::Disk {
                to_world: m,
                flip_normals,
            })
        }
        "cylinder" => cylinder(p, to_world, flip_normals),
        _ => {
            let known = "obj, ply, serialized, rectangle, cube, sphere, disk, cylinder";
            Err(p.unsupported("shape", known))
        }
    }
}

/// Mitsuba's `cylinder`: open, from `p0` (default the origin) to `p1` (default +z), of
/// `radius` (1), then `to_world`. Folded into one transform of the unit cylinder; the result
/// must stay circular (the cross-section's axes equal and perpendicular to each other and to
/// the axis), which an area light's uniform sampling relies on.
fn cylinder(p: &Props, to_world: DMat4, flip_normals: bool) -> Result<Geometry, SceneError> {
    let loc = p.loc().clone();
    let p0 = p.point_opt("p0")?.unwrap_or(Vec3::ZERO).as_dvec3();
    let p1 = p.point_opt("p1")?.unwrap_or(Vec3::Z).as_dvec3();
    let radius = p.float("radius", 1.0)? as f64;
    let axis = p1 - p0;
    let length = axis.length();
    if !(radius > 0.0 && radius.is_finite() && length > 0.0 && length.is_finite()) {
        let msg = "cylinder: radius and the distance from p0 to p1 must be positive and finite";
        return Err(invalid(&loc, msg));
    }
    let w = axis / length;
    // Mitsuba's frame around the axis: the same angle origin, so the same uv.
    let (u, v) = crate::transform::coordinate_system(w);
    let frame = DMat4::from_cols(
        (u * radius).extend(0.0),
        (v * radius).extend(0.0),
        (w * length).extend(0.0),
        p0.extend(1.0),
    );
    let m = to_world * frame;
    let (x, y, z) = (
        m.x_axis.truncate(),
        m.y_axis.truncate(),
        m.z_axis.truncate(),
    );
    let circular = (x.length() - y.length()).abs() <= 1e-6 * x.length()
        && x.dot(y).abs() <= 1e-6 * x.length_squared()
        && x.dot(z).abs() <= 1e-6 * x.length() * z.length()
        && y.dot(z).abs() <= 1e-6 * y.length() * z.length();
    if !circular || !m.is_finite() {
        return Err(invalid(
            &loc,
            "cylinder: to_world must keep it circular (no non-uniform scale across its axis, \
             no shear)",
        ));
    }
    let extent = m.w_axis.truncate().abs() + x.abs() + y.abs() + z.abs();
    if !(extent.max_element() <= mesh::MAX_WORLD_COORDINATE) {
        let msg = format!(
            "cylinder: in world space it reaches {}",
            mesh::beyond_bound_message()
        );
        return Err(invalid(&loc, msg));
    }
    Ok(Geometry::Cylinder {
        to_world: m.as_mat4(),
        flip_normals,
    })
}
