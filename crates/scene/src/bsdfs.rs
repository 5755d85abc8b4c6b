//! BSDF plugins, with Mitsuba 3's parameter names and defaults.

use std::rc::Rc;

use glam::Vec3;

use crate::context::Ctx;
use crate::desc::{BsdfDesc, MicrofacetDistribution, PerturbOptions, Roughness, TexRef};
use crate::error::SceneError;
use crate::ior::{lookup_conductor, lookup_ior};
use crate::props::{keywords, Props, Resolved};
use crate::textures::{const_float, const_rgb, texref, texref_opt, texture};
use crate::xml::{invalid, Category, Value};

/// Build (or fetch from cache) the BSDF `r`, returning its arena index.
pub(crate) fn bsdf(ctx: &mut Ctx, r: &Resolved) -> Result<usize, SceneError> {
    r.expect(Category::Bsdf, "a bsdf")?;
    let key = Rc::as_ptr(&r.node);
    if let Some(&i) = ctx.bsdf_cache.get(&key) {
        return Ok(i);
    }
    ctx.enter(&r.node, &r.loc)?;
    let result = build(ctx, r);
    ctx.leave(&r.node);
    let desc = result?;
    ctx.bsdfs.push(desc);
    let i = ctx.bsdfs.len() - 1;
    ctx.bsdf_cache.insert(key, i);
    Ok(i)
}

fn build(ctx: &mut Ctx, r: &Resolved) -> Result<BsdfDesc, SceneError> {
    let p = ctx.props(&r.node)?;
    let desc = match p.plugin() {
        "diffuse" => BsdfDesc::Diffuse {
            reflectance: texref(ctx, &p, "reflectance", 0.5)?,
        },
        "twosided" => twosided(ctx, &p)?,
        "mask" => BsdfDesc::Mask {
            opacity: texref(ctx, &p, "opacity", 0.5)?,
            nested: only_nested(ctx, &p)?,
        },
        "null" => BsdfDesc::Null,
        "bumpmap" => BsdfDesc::BumpMap {
            height: nested_texture(ctx, &p)?,
            scale: p.float("scale", 1.0)?,
            nested: only_nested(ctx, &p)?,
            normals: normal_options(&p)?,
        },
        "normalmap" => BsdfDesc::NormalMap {
            normals_texture: match texref_opt(ctx, &p, "normalmap")? {
                Some(TexRef::Texture(t)) => t,
                _ => {
                    return Err(invalid(
                        p.loc(),
                        "normalmap bsdf needs a 'normalmap' texture",
                    ))
                }
            },
            nested: only_nested(ctx, &p)?,
            normals: normal_options(&p)?,
        },
        "conductor" => {
            let (eta, k) = conductor_ior(&p)?;
            BsdfDesc::Conductor {
                eta,
                k,
                specular_reflectance: texref(ctx, &p, "specular_reflectance", 1.0)?,
            }
        }
        "roughconductor" => {
            let roughness = roughness(&p, true)?;
            let (eta, k) = conductor_ior(&p)?;
            BsdfDesc::RoughConductor {
                roughness,
                eta,
                k,
                specular_reflectance: texref(ctx, &p, "specular_reflectance", 1.0)?,
            }
        }
        "dielectric" | "thindielectric" | "roughdielectric" => {
            let int_ior = ior(&p, "int_ior", "bk7")?;
            let ext_ior = ior(&p, "ext_ior", "air")?;
            let specular_reflectance = texref(ctx, &p, "specular_reflectance", 1.0)?;
            let specular_transmittance = texref(ctx, &p, "specular_transmittance", 1.0)?;
            match p.plugin() {
                "dielectric" => BsdfDesc::Dielectric {
                    int_ior,
                    ext_ior,
                    specular_reflectance,
                    specular_transmittance,
                },
                "thindielectric" => BsdfDesc::ThinDielectric {
                    int_ior,
                    ext_ior,
                    specular_reflectance,
                    specular_transmittance,
                },
                _ => BsdfDesc::RoughDielectric {
                    roughness: roughness(&p, true)?,
                    int_ior,
                    ext_ior,
                    specular_reflectance,
                    specular_transmittance,
                },
            }
        }
        "plastic" | "roughplastic" => {
            let int_ior = ior(&p, "int_ior", "polypropylene")?;
            let ext_ior = ior(&p, "ext_ior", "air")?;
            let diffuse_reflectance = texref(ctx, &p, "diffuse_reflectance", 0.5)?;
            let specular_reflectance = texref(ctx, &p, "specular_reflectance", 1.0)?;
            let nonlinear = p.bool("nonlinear", false)?;
            if p.plugin() == "plastic" {
                BsdfDesc::Plastic {
                    int_ior,
                    ext_ior,
                    diffuse_reflectance,
                    specular_reflectance,
                    nonlinear,
                }
            } else {
                BsdfDesc::RoughPlastic {
                    roughness: roughness(&p, false)?,
                    int_ior,
                    ext_ior,
                    diffuse_reflectance,
                    specular_reflectance,
                    nonlinear,
                }
            }
        }
        _ => {
            return Err(p.unsupported(
                "bsdf",
                "diffuse, twosided, mask, null, bumpmap, normalmap, conductor, \
                 roughconductor, dielectric, thindielectric, roughdielectric, plastic, \
                 roughplastic",
            ))
        }
    };
    p.finish()?;
    Ok(desc)
}

fn twosided(ctx: &mut Ctx, p: &Props) -> Result<BsdfDesc, SceneError> {
    let children = p.children_of(Category::Bsdf);
    match children.as_slice() {
        [one] => {
            let i = bsdf(ctx, one)?;
            Ok(BsdfDesc::TwoSided { front: i, back: i })
        }
        [front, back] => {
            let front = bsdf(ctx, front)?;
            let back = bsdf(ctx, back)?;
            Ok(BsdfDesc::TwoSided { front, back })
        }
        _ => Err(invalid(
            p.loc(),
            format!(
                "twosided bsdf needs one or two nested bsdfs, found {}",
                children.len()
            ),
        )),
    }
}

/// The one nested BSDF of a wrapper plugin (`mask`, `bumpmap`, `normalmap`).
fn only_nested(ctx: &mut Ctx, p: &Props) -> Result<usize, SceneError> {
    let children = p.children_of(Category::Bsdf);
    match children.as_slice() {
        [one] => bsdf(ctx, one),
        _ => Err(invalid(
            p.loc(),
            format!(
                "{} needs exactly one nested bsdf, found {}",
                p.what(),
                children.len()
            ),
        )),
    }
}

/// The height texture of a `bumpmap`: its one nested texture, whatever its name (Mitsuba's
/// rule).
fn nested_texture(ctx: &mut Ctx, p: &Props) -> Result<usize, SceneError> {
    let children = p.children_of(Category::Texture);
    match children.as_slice() {
        [one] => texture(ctx, one),
        _ => Err(invalid(
            p.loc(),
            format!(
                "{} needs exactly one nested texture (the height field), found {}",
                p.what(),
                children.len()
            ),
        )),
    }
}

/// The options `bumpmap` and `normalmap` share, with Mitsuba's defaults.
fn normal_options(p: &Props) -> Result<PerturbOptions, SceneError> {
    Ok(PerturbOptions {
        flip_invalid_normals: p.bool("flip_invalid_normals", true)?,
        use_shadowing_function: p.bool("use_shadowing_function", true)?,
    })
}

/// Mitsuba's conductor logic: explicit `eta`/`k` (defaults 0 and 1) when
/// `eta` is given or `material` is "none" (the default), else the named
/// material's tabulated values.
fn conductor_ior(p: &Props) -> Result<(Vec3, Vec3), SceneError> {
    let material = p.string_opt("material")?;
    let is_none = material.as_ref().is_none_or(|(m, _)| m == "none");
    if p.has("eta") || is_none {
        // An index of refraction is not a colour: fitted data may be slightly negative
        // (Bitterli's living-room-2), and the Fresnel terms use only squares.
        let eta = const_rgb(p, "eta", Vec3::ZERO)?;
        let k = const_rgb(p, "k", Vec3::ONE)?;
        Ok((eta, k))
    } else {
        let (m, loc) = material.expect("material present when not none");
        lookup_conductor(&m).map_err(|e| invalid(&loc, e))
    }
}

/// An IOR given as a number or as one of Mitsuba's named IORs.
fn ior(p: &Props, name: &str, default: &str) -> Result<f32, SceneError> {
    let (v, loc) = match p.get(name) {
        None => (
            lookup_ior(default).map_err(|e| invalid(p.loc(), e))?,
            p.loc().clone(),
        ),
        Some(prop) => match &prop.value {
            Value::Float(f) => (*f as f32, prop.loc.clone()),
            Value::Integer(i) => (*i as f32, prop.loc.clone()),
            Value::String(s) => (
                lookup_ior(s).map_err(|e| invalid(&prop.loc, e))?,
                prop.loc.clone(),
            ),
            _ => return Err(p.type_error(prop, "<float> or <string> (a named IOR)")),
        },
    };
    if !(v > 0.0 && v.is_finite()) {
        return Err(invalid(
            &loc,
            format!("'{name}' must be a positive number (got {v})"),
        ));
    }
    Ok(v)
}

// Mitsuba reads the distribution's name in any case.
keywords!(MicrofacetDistribution, Insensitive: "beckmann" => Self::Beckmann, "ggx" => Self::Ggx);

/// `distribution`, `alpha` (or `alpha_u`/`alpha_v` when `anisotropic`),
/// `sample_visible`, with Mitsuba's defaults (beckmann, 0.1, true).
fn roughness(p: &Props, anisotropic: bool) -> Result<Roughness, SceneError> {
    let distribution = p.keyword("distribution", MicrofacetDistribution::Beckmann)?;
    let sample_visible = p.bool("sample_visible", true)?;
    let (alpha_u, alpha_v) = if anisotropic && (p.has("alpha_u") || p.has("alpha_v")) {
        if !(p.has("alpha_u") && p.has("alpha_v")) {
            return Err(invalid(
                p.loc(),
                format!(
                    "{}: both 'alpha_u' and 'alpha_v' must be specified",
                    p.what()
                ),
            ));
        }
        if p.has("alpha") {
            return Err(invalid(
                p.loc(),
                format!(
                    "{}: specify either 'alpha' or 'alpha_u'/'alpha_v', not both",
                    p.what()
                ),
            ));
        }
        (
            const_float(p, "alpha_u", 0.1)?,
            const_float(p, "alpha_v", 0.1)?,
        )
    } else {
        let a = const_float(p, "alpha", 0.1)?;
        (a, a)
    };
    for (n, a) in [("alpha_u", alpha_u), ("alpha_v", alpha_v)] {
        if !(a >= 0.0) {
            return Err(invalid(
                p.loc(),
                format!("{}: roughness {n} must be non-negative (got {a})", p.what()),
            ));
        }
    }
    Ok(Roughness {
        distribution,
        alpha_u,
        alpha_v,
        sample_visible,
    })
}
