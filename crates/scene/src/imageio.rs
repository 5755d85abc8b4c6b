//! Image file loading (PNG, JPEG via `image`; OpenEXR via `exr`) into linear
//! RGB texels, row 0 at the top of the file.

use std::path::Path;
use std::sync::Arc;

use glam::Vec3;

use crate::desc::Texels;

/// A decoded image: linear (or raw) RGB, row-major, row 0 = top.
pub(crate) struct LoadedImage {
    pub width: u32,
    pub height: u32,
    pub texels: Texels,
}

/// The exact sRGB electro-optical transfer function (encoded -> linear).
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Load `path`. EXR files are linear already. PNG/JPEG files (8 or 16 bit)
/// are sRGB-encoded and are linearised with the exact sRGB curve unless
/// `raw` (Mitsuba's `raw=true`: use values as stored). Grayscale expands to
/// RGB; alpha is dropped. Errors are messages for the caller to locate.
pub(crate) fn load_image(path: &Path, raw: bool) -> Result<LoadedImage, String> {
    let is_exr = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"));
    // Third-party decoders must not take the process down on a bad file.
    let img = std::panic::catch_unwind(|| {
        if is_exr {
            load_exr(path)
        } else {
            load_ldr(path, raw)
        }
    })
    .unwrap_or_else(|_| Err("the image decoder failed (panicked) on this file".into()))?;
    if img.width == 0 || img.height == 0 {
        return Err("image has zero size".into());
    }
    if let Some(i) = img.texels.iter().position(|t| !t.is_finite()) {
        return Err(format!(
            "texel {} (x={}, y={}) is not finite",
            i,
            i as u32 % img.width,
            i as u32 / img.width
        ));
    }
    Ok(img)
}

fn load_ldr(path: &Path, raw: bool) -> Result<LoadedImage, String> {
    let reader = image::ImageReader::open(path).map_err(|e| format!("cannot read: {e}"))?;
    let reader = reader
        .with_guessed_format()
        .map_err(|e| format!("cannot read: {e}"))?;
    let dynimg = reader
        .decode()
        .map_err(|e| format!("cannot decode image: {e}"))?;
    let (width, height) = (dynimg.width(), dynimg.height());
    let conv = |v: f32| if raw { v } else { srgb_to_linear(v) };
    let texels = match &dynimg {
        image::DynamicImage::ImageLuma8(_)
        | image::DynamicImage::ImageLumaA8(_)
        | image::DynamicImage::ImageRgb8(_)
        | image::DynamicImage::ImageRgba8(_) => {
            // The bytes and a 256-entry table: the exact curve per byte.
            let table: [f32; 256] = std::array::from_fn(|b| conv(b as f32 / 255.0));
            let rgb = dynimg.to_rgb8();
            Texels::Bytes {
                rgb: Arc::new(rgb.pixels().map(|p| [p[0], p[1], p[2], 0]).collect()),
                table: Arc::new(table),
            }
        }
        image::DynamicImage::ImageRgb32F(_) | image::DynamicImage::ImageRgba32F(_) => {
            // Float formats (e.g. HDR decoders) are linear.
            Texels::Float(Arc::new(
                dynimg
                    .to_rgb32f()
                    .pixels()
                    .map(|p| Vec3::new(p[0], p[1], p[2]))
                    .collect(),
            ))
        }
        _ => {
            // 16-bit PNGs: still sRGB-encoded (Mitsuba linearises them too).
            let rgb = dynimg.to_rgb16();
            Texels::Float(Arc::new(
                rgb.pixels()
                    .map(|p| {
                        Vec3::new(
                            conv(p[0] as f32 / 65535.0),
                            conv(p[1] as f32 / 65535.0),
                            conv(p[2] as f32 / 65535.0),
                        )
                    })
                    .collect(),
            ))
        }
    };
    Ok(LoadedImage {
        width,
        height,
        texels,
    })
}

fn load_exr(path: &Path) -> Result<LoadedImage, String> {
    use exr::prelude::*;
    let image = read_first_rgba_layer_from_file(
        path,
        |res, _| (res.width(), vec![Vec3::ZERO; res.width() * res.height()]),
        |(w, px): &mut (usize, Vec<Vec3>), pos, (r, g, b, _a): (f32, f32, f32, f32)| {
            px[pos.y() * *w + pos.x()] = Vec3::new(r, g, b);
        },
    )
    .map_err(|e| format!("cannot read OpenEXR file: {e}"))?;
    let size = image.layer_data.size;
    let (_, texels) = image.layer_data.channel_data.pixels;
    Ok(LoadedImage {
        width: size.width() as u32,
        height: size.height() as u32,
        texels: Texels::Float(Arc::new(texels)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_byte_128_linearises_to_known_value() {
        // (128/255 + 0.055) / 1.055 ^ 2.4 = 0.2158605...
        assert!((srgb_to_linear(128.0 / 255.0) - 0.215_860_5).abs() < 1e-6);
        assert!((srgb_to_linear(10.0 / 255.0) - 10.0 / 255.0 / 12.92).abs() < 1e-9);
        assert_eq!(srgb_to_linear(1.0), 1.0);
    }
}
