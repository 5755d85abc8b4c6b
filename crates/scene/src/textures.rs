//! Texture plugins (`bitmap`, `checkerboard`) and colour parameters that
//! may be either constants or textures.

use glam::{DMat4, Mat2, Vec2, Vec3};

use crate::context::Ctx;
use crate::desc::{BitmapDesc, TexFilter, TexRef, TextureDesc, UvTransform, WrapMode};
use crate::error::SceneError;
use crate::imageio::load_checked;
use crate::props::{keywords, Props, Resolved};
use crate::xml::{invalid, Category};

/// A colour parameter `name` of the plugin `p`: `<rgb>`/`<spectrum>`/`<float>`
/// or a nested / referenced `<texture name=...>`. `None` if absent.
pub(crate) fn texref_opt(
    ctx: &mut Ctx,
    p: &Props,
    name: &str,
) -> Result<Option<TexRef>, SceneError> {
    if let Some(c) = p.color_opt(name)? {
        return Ok(Some(TexRef::Const(c)));
    }
    if let Some(child) = p.named_child(name) {
        if child.node.category != Category::Texture {
            return Err(invalid(
                &child.loc,
                format!(
                    "parameter '{name}' of {} must be a texture or colour, got a {} {}",
                    p.what(),
                    child.node.plugin,
                    child.node.category.tag()
                ),
            ));
        }
        return Ok(Some(TexRef::Texture(texture(ctx, &child)?)));
    }
    Ok(None)
}

/// Like [`texref_opt`] with a constant default.
pub(crate) fn texref(
    ctx: &mut Ctx,
    p: &Props,
    name: &str,
    default: f32,
) -> Result<TexRef, SceneError> {
    Ok(texref_opt(ctx, p, name)?.unwrap_or(TexRef::Const(Vec3::splat(default))))
}

/// A colour that must be constant (emitter radiance, conductor eta/k).
pub(crate) fn const_color(p: &Props, name: &str, default: Vec3) -> Result<Vec3, SceneError> {
    if let Some(c) = p.color_opt(name)? {
        return Ok(c);
    }
    refuse_texture(p, name, "<rgb>")?;
    Ok(default)
}

/// As [`const_color`], for three numbers of any sign that are not a colour (a conductor's
/// `eta` and `k`).
pub(crate) fn const_rgb(p: &Props, name: &str, default: Vec3) -> Result<Vec3, SceneError> {
    if let Some(c) = p.rgb_opt(name)? {
        return Ok(c);
    }
    refuse_texture(p, name, "<rgb>")?;
    Ok(default)
}

/// A scalar that must be constant (roughness); textured values are rejected.
pub(crate) fn const_float(p: &Props, name: &str, default: f32) -> Result<f32, SceneError> {
    refuse_texture(p, name, "<float>")?;
    p.float(name, default)
}

/// An error at the nested or referenced texture given as parameter `name`, if there is one:
/// the parameter must be a constant, written as `constant` ("<rgb>").
fn refuse_texture(p: &Props, name: &str, constant: &str) -> Result<(), SceneError> {
    match p.named_child(name) {
        Some(child) => Err(invalid(
            &child.loc,
            format!(
                "parameter '{name}' of {}: a textured value is not supported, use {constant}",
                p.what()
            ),
        )),
        None => Ok(()),
    }
}

/// Mitsuba's conversion of a 4x4 `to_uv` to a 2D affine map: upper-left 2x2
/// and the translation column.
pub(crate) fn uv_transform(m: DMat4) -> UvTransform {
    let m = m.as_mat4();
    UvTransform {
        m: Mat2::from_cols(
            Vec2::new(m.x_axis.x, m.x_axis.y),
            Vec2::new(m.y_axis.x, m.y_axis.y),
        ),
        t: Vec2::new(m.w_axis.x, m.w_axis.y),
    }
}

/// Build (or fetch from cache) the texture `r`, returning its index.
pub(crate) fn texture(ctx: &mut Ctx, r: &Resolved) -> Result<usize, SceneError> {
    let key = std::rc::Rc::as_ptr(&r.node);
    if let Some(&i) = ctx.texture_cache.get(&key) {
        return Ok(i);
    }
    let p = ctx.props(&r.node)?;
    let desc = match p.plugin() {
        "bitmap" => bitmap(ctx, &p)?,
        "checkerboard" => checkerboard(&p)?,
        _ => return Err(p.unsupported("texture", "bitmap, checkerboard")),
    };
    p.finish()?;
    ctx.textures.push(desc);
    let i = ctx.textures.len() - 1;
    ctx.texture_cache.insert(key, i);
    Ok(i)
}

fn checkerboard(p: &Props) -> Result<TextureDesc, SceneError> {
    // Defaults from Mitsuba's checkerboard.cpp: color0 0.4, color1 0.2.
    let color0 = const_color(p, "color0", Vec3::splat(0.4))?;
    let color1 = const_color(p, "color1", Vec3::splat(0.2))?;
    let to_uv = uv_transform(p.transform("to_uv")?);
    Ok(TextureDesc::Checkerboard {
        color0,
        color1,
        to_uv,
    })
}

keywords!(TexFilter, Sensitive: "bilinear" => Self::Bilinear, "nearest" => Self::Nearest);
keywords!(WrapMode, Sensitive:
    "repeat" => Self::Repeat,
    "mirror" => Self::Mirror,
    "clamp" => Self::Clamp,
);

fn bitmap(ctx: &mut Ctx, p: &Props) -> Result<TextureDesc, SceneError> {
    let (name, loc) = p
        .string_opt("filename")?
        .ok_or_else(|| invalid(p.loc(), "bitmap texture requires a 'filename' parameter"))?;
    let filter = p.keyword("filter_type", TexFilter::Bilinear)?;
    let wrap = p.keyword("wrap_mode", WrapMode::Repeat)?;
    let raw = p.bool("raw", false)?;
    let to_uv = uv_transform(p.transform("to_uv")?);
    // `accel` only selects Mitsuba's hardware texture path: no effect here.
    let _ = p.bool("accel", true)?;
    let path = ctx.resolve_path(&name, &loc)?;
    let img = load_checked(ctx, &path, raw, "texture file", &loc)?;
    Ok(TextureDesc::Bitmap(BitmapDesc {
        width: img.width,
        height: img.height,
        texels: img.texels,
        filter,
        wrap,
        to_uv,
    }))
}
