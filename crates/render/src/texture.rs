//! Texture evaluation (Mitsuba `bitmap` and `checkerboard`).

use glam::{Vec2, Vec3};
use pathfarm_scene::{byte_texel, BitmapDesc, TexFilter, TexRef, Texels, TextureDesc, WrapMode};

/// Looks up a colour parameter at surface coordinates `uv`.
#[inline]
pub fn eval(textures: &[TextureDesc], r: TexRef, uv: Vec2) -> Vec3 {
    match r {
        TexRef::Const(c) => c,
        TexRef::Texture(i) => eval_texture_in_register(&textures[i], uv).into(),
    }
}

/// [`eval_texture`] returning a SIMD vector, which comes back in a register: a `Vec3`
/// return goes through memory, and merging it with the constant branch made the compiler
/// store the constant to the stack in pieces and load it back whole, a store-forwarding
/// stall on every constant-colour lookup.
#[inline(never)]
fn eval_texture_in_register(t: &TextureDesc, uv: Vec2) -> glam::Vec3A {
    eval_texture(t, uv).into()
}

/// The linear RGB value of texture `t` at surface coordinates `uv`, after the texture's own uv
/// transform (bitmap lookup with its filter and wrap mode, or checkerboard).
pub fn eval_texture(t: &TextureDesc, uv: Vec2) -> Vec3 {
    match t {
        TextureDesc::Bitmap(b) => eval_bitmap(b, b.to_uv.apply(uv)),
        TextureDesc::Checkerboard {
            color0,
            color1,
            to_uv,
        } => {
            let q = to_uv.apply(uv);
            let mx = q.x - q.x.floor() > 0.5;
            let my = q.y - q.y.floor() > 0.5;
            if mx == my {
                *color0
            } else {
                *color1
            }
        }
    }
}

/// Mitsuba's luminance of a linear sRGB colour (its `eval_1` of an RGB texture).
#[inline]
pub fn luminance(c: Vec3) -> f32 {
    c.dot(Vec3::new(0.212_671, 0.715_160, 0.072_169))
}

/// A scalar parameter (mask opacity): the luminance of the colour `r` at `uv`.
#[inline]
pub fn eval_scalar(textures: &[TextureDesc], r: TexRef, uv: Vec2) -> f32 {
    luminance(eval(textures, r, uv))
}

/// The gradient of the luminance of texture `t` with respect to `(u, v)` at `uv` (Mitsuba's
/// `eval_1_grad`): that of the bilinear interpolation, zero for nearest lookups and
/// checkerboards (flat almost everywhere).
pub fn luminance_gradient(t: &TextureDesc, uv: Vec2) -> Vec2 {
    let TextureDesc::Bitmap(b) = t else {
        return Vec2::ZERO;
    };
    let q = b.to_uv.apply(uv);
    if b.filter != TexFilter::Bilinear || !q.is_finite() {
        return Vec2::ZERO;
    }
    let lum = |x: usize, y: usize| {
        let i = y * b.width as usize + x;
        luminance(match &b.texels {
            Texels::Bytes { rgb, table } => byte_texel(table, rgb[i]),
            Texels::Float(t) => t[i],
        })
    };
    let px = q.x * b.width as f32 - 0.5;
    let py = q.y * b.height as f32 - 0.5;
    let (x0, y0) = (px.floor(), py.floor());
    let (fx, fy) = (px - x0, py - y0);
    let (x0, y0) = (x0 as i64, y0 as i64);
    let (x1, y1) = (
        wrap(x0 + 1, b.width, b.wrap),
        wrap(y0 + 1, b.height, b.wrap),
    );
    let (x0, y0) = (wrap(x0, b.width, b.wrap), wrap(y0, b.height, b.wrap));
    let (f00, f10, f01, f11) = (lum(x0, y0), lum(x1, y0), lum(x0, y1), lum(x1, y1));
    // Partials with respect to the texel coordinates, then to the transformed uv, then
    // (transpose of the uv transform) to the surface's uv.
    let d_pixel = Vec2::new(
        (1.0 - fy) * (f10 - f00) + fy * (f11 - f01),
        (1.0 - fx) * (f01 - f00) + fx * (f11 - f10),
    );
    let d_q = d_pixel * Vec2::new(b.width as f32, b.height as f32);
    b.to_uv.m.transpose() * d_q
}

#[inline]
fn wrap(i: i64, n: u32, mode: WrapMode) -> usize {
    let n = n as i64;
    if (0..n).contains(&i) {
        // Inside the image (nearly every lookup): no integer division.
        return i as usize;
    }
    (match mode {
        WrapMode::Repeat => i.rem_euclid(n),
        WrapMode::Clamp => i.clamp(0, n - 1),
        WrapMode::Mirror => {
            let m = i.rem_euclid(2 * n);
            if m < n {
                m
            } else {
                2 * n - 1 - m
            }
        }
    }) as usize
}

/// Texel lookup with uv (0, 0) at the first stored row (the top of the
/// image file), as Mitsuba's bitmap does; bilinear uses `pos = uv * res - 0.5`.
pub fn eval_bitmap(b: &BitmapDesc, uv: Vec2) -> Vec3 {
    match &b.texels {
        Texels::Bytes { rgb, table } => filter(b, uv, |i| byte_texel(table, rgb[i])),
        Texels::Float(t) => filter(b, uv, |i| t[i]),
    }
}

/// [`eval_bitmap`] with texel `i` (row-major) from `texel`: the storage is matched once
/// per lookup, not per texel.
#[inline(always)]
fn filter(b: &BitmapDesc, uv: Vec2, texel: impl Fn(usize) -> Vec3) -> Vec3 {
    if !uv.is_finite() {
        return Vec3::ZERO;
    }
    // Texel (x, y) from wrapped column x and row y.
    let texel = |x: usize, y: usize| texel(y * b.width as usize + x);
    let (wx, wy) = (
        |x: i64| wrap(x, b.width, b.wrap),
        |y: i64| wrap(y, b.height, b.wrap),
    );
    match b.filter {
        TexFilter::Nearest => texel(
            wx((uv.x * b.width as f32).floor() as i64),
            wy((uv.y * b.height as f32).floor() as i64),
        ),
        TexFilter::Bilinear => {
            let px = uv.x * b.width as f32 - 0.5;
            let py = uv.y * b.height as f32 - 0.5;
            let (x0, y0) = (px.floor(), py.floor());
            let (fx, fy) = (px - x0, py - y0);
            let (x0, y0) = (x0 as i64, y0 as i64);
            let (x1, y1) = (wx(x0 + 1), wy(y0 + 1));
            let (x0, y0) = (wx(x0), wy(y0));
            let top = texel(x0, y0) * (1.0 - fx) + texel(x1, y0) * fx;
            let bottom = texel(x0, y1) * (1.0 - fx) + texel(x1, y1) * fx;
            top * (1.0 - fy) + bottom * fy
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pathfarm_scene::UvTransform;
    use std::sync::Arc;

    fn bitmap(filter: TexFilter, wrap: WrapMode) -> BitmapDesc {
        // 2x2: top row red, green; bottom row blue, white.
        let texels = vec![Vec3::X, Vec3::Y, Vec3::Z, Vec3::ONE];
        BitmapDesc {
            width: 2,
            height: 2,
            texels: Texels::Float(Arc::new(texels)),
            filter,
            wrap,
            to_uv: UvTransform::default(),
        }
    }

    #[test]
    fn bitmap_texel_centres_return_texels_and_midpoints_average() {
        let b = bitmap(TexFilter::Bilinear, WrapMode::Clamp);
        assert_eq!(eval_bitmap(&b, Vec2::new(0.25, 0.25)), Vec3::X);
        assert_eq!(eval_bitmap(&b, Vec2::new(0.75, 0.75)), Vec3::ONE);
        let mid = eval_bitmap(&b, Vec2::new(0.5, 0.5));
        assert!((mid - (Vec3::X + Vec3::Y + Vec3::Z + Vec3::ONE) / 4.0).length() < 1e-6);
        let n = bitmap(TexFilter::Nearest, WrapMode::Repeat);
        assert_eq!(eval_bitmap(&n, Vec2::new(0.9, 0.1)), Vec3::Y);
        assert_eq!(eval_bitmap(&n, Vec2::new(1.9, 1.1)), Vec3::Y);
    }

    #[test]
    fn byte_texels_look_up_the_values_float_texels_would_hold() {
        // A 5x3 8-bit image with every wrap mode and filter: the table-backed storage gives
        // bit for bit what the same image converted to f32 at load gives.
        let table: [f32; 256] =
            std::array::from_fn(|b| pathfarm_scene::srgb_to_linear(b as f32 / 255.0));
        let rgb: Vec<[u8; 4]> = (0..15u32)
            .map(|i| {
                [
                    (i * 37 % 256) as u8,
                    (i * 91 % 256) as u8,
                    (255 - i * 13) as u8,
                    0,
                ]
            })
            .collect();
        let floats: Vec<Vec3> = rgb.iter().map(|&b| byte_texel(&table, b)).collect();
        assert!(floats.windows(2).any(|w| w[0] != w[1]));
        for filter in [TexFilter::Nearest, TexFilter::Bilinear] {
            for wrap in [WrapMode::Repeat, WrapMode::Mirror, WrapMode::Clamp] {
                let mut b = BitmapDesc {
                    width: 5,
                    height: 3,
                    texels: Texels::Float(Arc::new(floats.clone())),
                    filter,
                    wrap,
                    to_uv: UvTransform::default(),
                };
                let f = b.clone();
                b.texels = Texels::Bytes {
                    rgb: Arc::new(rgb.clone()),
                    table: Arc::new(table),
                };
                for k in 0..400 {
                    let uv = Vec2::new(k as f32 * 0.0137 - 1.3, k as f32 * 0.0291 - 2.1);
                    let (a, c) = (eval_bitmap(&b, uv), eval_bitmap(&f, uv));
                    assert_eq!(
                        a.to_array().map(f32::to_bits),
                        c.to_array().map(f32::to_bits)
                    );
                }
            }
        }
    }

    #[test]
    fn wrap_modes_fold_indices() {
        assert_eq!(wrap(-1, 4, WrapMode::Repeat), 3);
        assert_eq!(wrap(-1, 4, WrapMode::Mirror), 0);
        assert_eq!(wrap(4, 4, WrapMode::Mirror), 3);
        assert_eq!(wrap(9, 4, WrapMode::Clamp), 3);
    }

    #[test]
    fn checkerboard_alternates_like_mitsuba() {
        let t = TextureDesc::Checkerboard {
            color0: Vec3::ONE,
            color1: Vec3::ZERO,
            to_uv: UvTransform::default(),
        };
        assert_eq!(eval_texture(&t, Vec2::new(0.25, 0.25)), Vec3::ONE);
        assert_eq!(eval_texture(&t, Vec2::new(0.75, 0.25)), Vec3::ZERO);
        assert_eq!(eval_texture(&t, Vec2::new(0.75, 0.75)), Vec3::ONE);
    }

    #[test]
    fn luminance_gradient_is_the_derivative_of_the_bilinear_lookup() {
        let texels: Vec<Vec3> = (0..35)
            .map(|i| Vec3::new((i * 7 % 11) as f32, (i * 3 % 5) as f32, (i % 4) as f32) * 0.1)
            .collect();
        let mut b = BitmapDesc {
            width: 7,
            height: 5,
            texels: Texels::Float(Arc::new(texels)),
            filter: TexFilter::Bilinear,
            wrap: WrapMode::Repeat,
            to_uv: UvTransform {
                m: glam::Mat2::from_cols_array(&[2.0, 0.5, -0.3, 1.5]),
                t: Vec2::new(0.1, 0.2),
            },
        };
        let t = TextureDesc::Bitmap(b.clone());
        let lum = |uv: Vec2| luminance(eval_texture(&t, uv));
        let h = 1e-3;
        let mut checked = 0;
        for (u, v) in [(0.13, 0.41), (0.57, 0.22), (0.81, 0.93), (0.33, 0.67)] {
            let uv = Vec2::new(u, v);
            let g = luminance_gradient(&t, uv);
            let fd = Vec2::new(
                (lum(uv + Vec2::X * h) - lum(uv - Vec2::X * h)) / (2.0 * h),
                (lum(uv + Vec2::Y * h) - lum(uv - Vec2::Y * h)) / (2.0 * h),
            );
            assert!(
                (g - fd).length() < 2e-2 * (1.0 + fd.length()),
                "{uv}: {g} vs {fd}"
            );
            checked += (g.length() > 0.1) as u32;
        }
        assert!(checked >= 3, "the texture must slope at most points");
        b.filter = TexFilter::Nearest;
        assert_eq!(
            luminance_gradient(&TextureDesc::Bitmap(b), Vec2::new(0.3, 0.3)),
            Vec2::ZERO
        );
    }
}
