//! The `perspective` sensor with its nested `hdrfilm` (and reconstruction
//! filter) and sampler.

use crate::context::Ctx;
use crate::desc::{FilmDesc, FovAxis, RFilter, SensorDesc};
use crate::error::SceneError;
use crate::props::{Props, Resolved};
use crate::xml::{invalid, Category};

/// Build the sensor `r`, appending any warnings to `ctx.warnings`.
pub(crate) fn sensor(ctx: &mut Ctx, r: &Resolved) -> Result<SensorDesc, SceneError> {
    let p = ctx.props(&r.node)?;
    if p.plugin() != "perspective" {
        return Err(p.unsupported("sensor", "perspective"));
    }
    let (fov, fov_axis) = fov(&p)?;
    let to_world_d = p.transform("to_world")?;
    let to_world = to_world_d.as_mat4();
    let det = glam::DMat3::from_mat4(to_world_d).determinant();
    if !(det.abs() > 1e-30) || !to_world.is_finite() {
        return Err(invalid(
            p.loc(),
            format!(
                "perspective sensor: to_world must be invertible (its 3x3 part has determinant \
                 {det:e})"
            ),
        ));
    }
    let near_clip = p.float("near_clip", 1e-2)?;
    let far_clip = p.float("far_clip", 1e4)?;
    if !(near_clip > 0.0 && near_clip < far_clip) {
        return Err(invalid(
            p.loc(),
            format!("need 0 < near_clip < far_clip (got {near_clip}, {far_clip})"),
        ));
    }
    // A pinhole camera has no focal plane: `focus_distance` changes nothing.
    let _ = p.float("focus_distance", far_clip)?;
    for name in ["principal_point_offset_x", "principal_point_offset_y"] {
        if p.float(name, 0.0)? != 0.0 {
            return Err(invalid(
                p.loc(),
                format!("'{name}' other than 0 is not supported"),
            ));
        }
    }

    let film = match p.at_most_one(Category::Film, "sensor")? {
        None => FilmDesc {
            width: 768,
            height: 576,
            rfilter: RFilter::Gaussian { stddev: 0.5 },
        },
        Some(f) => film(ctx, &f)?,
    };
    let (sample_count, seed) = match p.at_most_one(Category::Sampler, "sensor")? {
        None => (4, 0),
        Some(s) => sampler(ctx, &s)?,
    };
    p.finish()?;
    Ok(SensorDesc {
        to_world,
        fov,
        fov_axis,
        near_clip,
        far_clip,
        film,
        sample_count,
        seed,
    })
}

/// `fov` + `fov_axis`, or Mitsuba's `focal_length` ("50mm", 35mm-film
/// equivalent) converted to a diagonal field of view.
fn fov(p: &Props) -> Result<(f32, FovAxis), SceneError> {
    if p.has("fov") && p.has("focal_length") {
        return Err(invalid(
            p.loc(),
            "specify either a focal length ('focal_length') or a field of view ('fov'), not both",
        ));
    }
    let (fov, axis) = if let Some(f) = p.float_opt("fov")? {
        let axis = match p.string_opt("fov_axis")? {
            None => FovAxis::X,
            Some((s, loc)) => match s.to_ascii_lowercase().as_str() {
                "x" => FovAxis::X,
                "y" => FovAxis::Y,
                "diagonal" => FovAxis::Diagonal,
                "smaller" => FovAxis::Smaller,
                "larger" => FovAxis::Larger,
                _ => {
                    return Err(invalid(
                        &loc,
                        format!(
                        "fov_axis \"{s}\" must be one of 'smaller', 'larger', 'diagonal', 'x', 'y'"
                    ),
                    ))
                }
            },
        };
        (f, axis)
    } else {
        let (s, loc) = p
            .string_opt("focal_length")?
            .unwrap_or_else(|| ("50mm".into(), p.loc().clone()));
        let num = s.trim().strip_suffix("mm").unwrap_or(s.trim());
        let f: f64 = num
            .trim()
            .parse()
            .ok()
            .filter(|f: &f64| *f > 0.0 && f.is_finite())
            .ok_or_else(|| {
                invalid(
                    &loc,
                    format!("could not parse focal_length \"{s}\" (expected e.g. \"50mm\")"),
                )
            })?;
        let fov = 2.0
            * ((36.0f64 * 36.0 + 24.0 * 24.0).sqrt() / (2.0 * f))
                .atan()
                .to_degrees();
        (fov as f32, FovAxis::Diagonal)
    };
    if !(fov > 0.0 && fov < 180.0) {
        return Err(invalid(
            p.loc(),
            format!("fov must be in (0, 180) degrees (got {fov})"),
        ));
    }
    Ok((fov, axis))
}

fn film(ctx: &Ctx, r: &Resolved) -> Result<FilmDesc, SceneError> {
    let p = ctx.props(&r.node)?;
    if p.plugin() != "hdrfilm" {
        return Err(p.unsupported("film", "hdrfilm"));
    }
    let limits = &ctx.limits;
    let side = limits.max_film_side as i64;
    let width = p.int_limited("width", 768, 1, side, "Limits::max_film_side")? as u32;
    let height = p.int_limited("height", 576, 1, side, "Limits::max_film_side")? as u32;
    let pixels = width as u64 * height as u64;
    if pixels > limits.max_film_pixels {
        return Err(invalid(
            p.loc(),
            format!(
                "film of {width}x{height} = {pixels} pixels exceeds the limit of {} pixels \
                 (Limits::max_film_pixels)",
                limits.max_film_pixels
            ),
        ));
    }
    // Output-format options that do not change the image we compute.
    for name in ["file_format", "pixel_format", "component_format"] {
        let _ = p.string_opt(name)?;
    }
    let _ = p.bool("banner", true)?;
    let _ = p.bool("high_quality_edges", false)?;
    let rfilter = match p.at_most_one(Category::RFilter, "film")? {
        None => RFilter::Gaussian { stddev: 0.5 },
        Some(f) => rfilter(ctx, &f)?,
    };
    p.finish()?;
    Ok(FilmDesc {
        width,
        height,
        rfilter,
    })
}

fn rfilter(ctx: &Ctx, r: &Resolved) -> Result<RFilter, SceneError> {
    let p = ctx.props(&r.node)?;
    let max_radius = ctx.limits.max_filter_radius;
    // `reach` is the filter's radius per unit of the parameter (a gaussian reaches 4 stddev).
    let checked = |v: f32, name: &str, reach: f64| {
        if !(v > 0.0) {
            Err(invalid(
                p.loc(),
                format!("rfilter '{name}' must be positive (got {v})"),
            ))
        } else if v as f64 * reach > max_radius {
            Err(invalid(
                p.loc(),
                format!(
                    "rfilter '{name}' {v} reaches {} pixels, more than the limit of \
                     {max_radius} pixels (Limits::max_filter_radius)",
                    v as f64 * reach
                ),
            ))
        } else {
            Ok(v)
        }
    };
    let f = match p.plugin() {
        "box" => RFilter::Box { radius: 0.5 },
        "tent" => RFilter::Tent {
            radius: checked(p.float("radius", 1.0)?, "radius", 1.0)?,
        },
        "gaussian" => RFilter::Gaussian {
            stddev: checked(p.float("stddev", 0.5)?, "stddev", 4.0)?,
        },
        _ => return Err(p.unsupported("rfilter", "box, tent, gaussian")),
    };
    p.finish()?;
    Ok(f)
}

/// `independent` sampler; `stratified`, `multijitter`, `ldsampler` and
/// `orthogonal` are accepted but treated as independent (with a warning).
fn sampler(ctx: &mut Ctx, r: &Resolved) -> Result<(u32, u64), SceneError> {
    let p = ctx.props(&r.node)?;
    match p.plugin() {
        "independent" => {}
        "stratified" | "multijitter" | "ldsampler" | "orthogonal" => {
            if matches!(p.plugin(), "stratified" | "multijitter" | "orthogonal") {
                let _ = p.bool("jitter", true)?;
            }
            if p.plugin() == "orthogonal" {
                let _ = p.int_opt("strength")?;
            }
            ctx.warnings.push(format!(
                "{}: sampler '{}' is treated as 'independent' (same sample count, different sample pattern)",
                p.loc(),
                p.plugin()
            ));
        }
        _ => return Err(p.unsupported(
            "sampler",
            "independent; stratified, multijitter, ldsampler, orthogonal treated as independent",
        )),
    }
    let max_spp = ctx.limits.max_spp.min(u32::MAX as u64) as i64;
    let sample_count = p.int_limited("sample_count", 4, 1, max_spp, "Limits::max_spp")? as u32;
    let seed = p.int_in("seed", 0, 0, i64::MAX)? as u64;
    p.finish()?;
    Ok((sample_count, seed))
}
