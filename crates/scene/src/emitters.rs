//! Emitter plugins: `area` (on shapes), `point`, `spot`, `constant`, `envmap`,
//! `directional`.

use std::sync::Arc;

use glam::{DVec3, Vec3};

use crate::context::{Ctx, Reading};
use crate::desc::{AreaEmitterDesc, EmitterDesc};
use crate::error::SceneError;
use crate::imageio::{self, load_checked};
use crate::props::Resolved;
use crate::textures::const_color;
use crate::xml::{invalid, Category};

/// An `area` emitter nested in a shape: `radiance` (default 1).
pub(crate) fn area_emitter(ctx: &Ctx, r: &Resolved) -> Result<AreaEmitterDesc, SceneError> {
    r.expect(Category::Emitter, "an emitter")?;
    let p = ctx.props(&r.node)?;
    if p.plugin() != "area" {
        return Err(invalid(
            p.loc(),
            format!(
                "emitter of type '{}' cannot be attached to a shape (only 'area')",
                p.plugin()
            ),
        ));
    }
    let radiance = const_color(&p, "radiance", Vec3::ONE)?;
    p.finish()?;
    Ok(AreaEmitterDesc { radiance })
}

/// A scene-level emitter.
pub(crate) fn emitter(ctx: &mut Ctx, r: &Resolved) -> Result<EmitterDesc, SceneError> {
    r.expect(Category::Emitter, "an emitter")?;
    let p = ctx.props(&r.node)?;
    let desc = match p.plugin() {
        "area" => {
            return Err(invalid(
                p.loc(),
                "an area emitter must be nested inside a <shape>",
            ))
        }
        "point" => {
            let to_world = p.transform_opt("to_world")?;
            let position = p.point_opt("position")?;
            let position = match (position, to_world) {
                (Some(_), Some(_)) => {
                    return Err(invalid(
                        p.loc(),
                        "point emitter: specify either 'position' or 'to_world', not both",
                    ))
                }
                (Some(pos), None) => pos,
                (None, Some(m)) => m.transform_point3(DVec3::ZERO).as_vec3(),
                (None, None) => Vec3::ZERO,
            };
            EmitterDesc::Point {
                position,
                intensity: const_color(&p, "intensity", Vec3::ONE)?,
            }
        }
        "spot" => {
            let to_world = p.transform("to_world")?.as_mat4();
            let cutoff = p.float("cutoff_angle", 20.0)?;
            let beam = p.float("beam_width", cutoff * 0.75)?;
            if !(cutoff > 0.0 && cutoff <= 90.0) {
                let at = p.get("cutoff_angle").map_or(p.loc(), |c| &c.loc);
                let msg = format!("spot emitter: cutoff_angle {cutoff} is not in (0, 90] degrees");
                return Err(invalid(at, msg));
            }
            if !(beam > 0.0 && beam < cutoff) {
                let at = p.get("beam_width").map_or(p.loc(), |c| &c.loc);
                let msg = format!(
                    "spot emitter: beam_width {beam} is not in (0, cutoff_angle {cutoff}) degrees"
                );
                return Err(invalid(at, msg));
            }
            if !to_world.is_finite() || glam::Mat3::from_mat4(to_world).determinant() == 0.0 {
                return Err(invalid(
                    p.loc(),
                    "spot emitter: to_world must be invertible",
                ));
            }
            EmitterDesc::Spot {
                to_world,
                intensity: const_color(&p, "intensity", Vec3::ONE)?,
                cutoff_angle: cutoff.to_radians(),
                beam_width: beam.to_radians(),
            }
        }
        "constant" => EmitterDesc::Constant {
            radiance: const_color(&p, "radiance", Vec3::ONE)?,
        },
        "directional" => {
            let to_world = p.transform_opt("to_world")?;
            let dir = p.point_opt("direction")?;
            let direction =
                match (dir, to_world) {
                    (Some(_), Some(_)) => return Err(invalid(
                        p.loc(),
                        "directional emitter: specify either 'direction' or 'to_world', not both",
                    )),
                    (Some(d), None) => d.as_dvec3(),
                    (None, Some(m)) => m.transform_vector3(DVec3::Z),
                    (None, None) => DVec3::Z,
                };
            let len = direction.length();
            if !(len > 0.0) || !len.is_finite() {
                return Err(invalid(
                    p.loc(),
                    "directional emitter: direction must be non-zero",
                ));
            }
            EmitterDesc::Directional {
                direction: (direction / len).as_vec3(),
                irradiance: const_color(&p, "irradiance", Vec3::ONE)?,
            }
        }
        "envmap" => {
            let (name, loc) = p
                .string_opt("filename")?
                .ok_or_else(|| invalid(p.loc(), "envmap requires a 'filename' parameter"))?;
            let scale = p.float("scale", 1.0)?;
            let to_world = p.transform("to_world")?.as_mat4();
            let path = ctx.resolve_path(&name, &loc)?;
            let img = load_checked(ctx, &path, false, "envmap file", &loc)?;
            // A scene read without its images has a 1x1 stand-in: the size is the header's
            // (it was read, so it reads again), and a uniform 2x3 map stands in, on which a
            // world can be built.
            let (size, map) = match ctx.reading {
                Reading::Contents => {
                    let size = (img.width, img.height);
                    (size, (size, img.texels.iter().collect()))
                }
                Reading::Names | Reading::Geometry => {
                    let size = imageio::image_size(&path).map_err(|e| {
                        invalid(&loc, format!("envmap file '{}': {e}", path.display()))
                    })?;
                    (size, ((2, 3), vec![Vec3::ONE; 6]))
                }
            };
            if size.0 < 2 || size.1 < 3 {
                return Err(invalid(
                    &loc,
                    format!(
                        "envmap file '{}' is {}x{}: an environment map has at least 2x3 \
                         pixels (as in Mitsuba 3)",
                        path.display(),
                        size.0,
                        size.1
                    ),
                ));
            }
            let ((width, height), texels) = map;
            EmitterDesc::EnvMap {
                width,
                height,
                texels: Arc::new(texels),
                scale,
                to_world,
            }
        }
        _ => {
            let known = "area, point, spot, constant, envmap, directional";
            return Err(p.unsupported("emitter", known));
        }
    };
    p.finish()?;
    Ok(desc)
}
