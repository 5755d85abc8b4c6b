//! Image file loading (PNG, JPEG via `image`; OpenEXR via `exr`) into linear
//! RGB texels, row 0 at the top of the file.

use std::path::Path;
use std::sync::Arc;

use glam::Vec3;

use crate::context::{Ctx, Reading};
use crate::desc::{Location, Texels};
use crate::error::SceneError;
use crate::xml::invalid;

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

/// Load the image `path` for `what` (e.g. "texture file"), after checking its size, read from
/// the file's header, against `Limits::max_texture_pixels` and reserving its memory: a header
/// cannot make the decoder allocate more than the limits allow. Errors are located at `loc`.
pub(crate) fn load_checked(
    ctx: &mut Ctx,
    path: &Path,
    raw: bool,
    what: &str,
    loc: &Location,
) -> Result<LoadedImage, SceneError> {
    let name = format!("{what} '{}'", path.display());
    let fail = |e: String| invalid(loc, format!("{name}: {e}"));
    if path.is_dir() {
        return Err(fail("is a directory, not an image".into()));
    }
    let (w, h) = image_size(path).map_err(fail)?;
    let pixels = w as u64 * h as u64;
    let max = ctx.limits.max_texture_pixels;
    if pixels > max {
        return Err(fail(format!(
            "the image is {w}x{h} ({pixels} pixels), more than the limit of {max} pixels \
             (Limits::max_texture_pixels)"
        )));
    }
    // Decoded bytes plus our texels (up to 16 bytes a pixel for float images).
    ctx.reserve_memory(pixels * 24, &format!("{name} ({w}x{h})"), loc)?;
    if ctx.reading != Reading::Contents {
        // The header read, the pixels not decoded: one black texel stands in.
        return Ok(LoadedImage {
            width: 1,
            height: 1,
            texels: Texels::Float(Arc::new(vec![Vec3::ZERO])),
        });
    }
    // The decoder's own allocations beside the pixels (a PNG's text and colour-profile
    // chunks) are small but not bounded by the pixel count: a 10x9 icon with 6 KB of
    // metadata is a valid texture.
    load_image(path, raw, pixels * 24 + DECODER_ALLOWANCE).map_err(fail)
}

/// What the image decoder may allocate beyond the pixels it decodes.
const DECODER_ALLOWANCE: u64 = 16 << 20;

/// Width and height from the file's header, without decoding it.
pub(crate) fn image_size(path: &Path) -> Result<(u32, u32), String> {
    if is_exr(path) {
        let meta = exr::meta::MetaData::read_from_file(path, false)
            .map_err(|e| format!("cannot read OpenEXR file: {e}"))?;
        let header = meta.headers.first().ok_or("OpenEXR file has no layer")?;
        let size = header.layer_size;
        return Ok((size.width() as u32, size.height() as u32));
    }
    if let Some(d) = renamed_radiance(path)? {
        return Ok(image::ImageDecoder::dimensions(&d));
    }
    image::ImageReader::open(path)
        .map_err(|e| format!("cannot read: {e}"))?
        .with_guessed_format()
        .map_err(|e| format!("cannot read: {e}"))?
        .into_dimensions()
        .map_err(|e| format!("cannot decode image: {e}"))
}

/// The decoder of a Radiance RGBE file whose signature line names another program than
/// RADIANCE (Mitsuba writes `#?RGBE`; the format allows any `#?name`), reading it as
/// `#?RADIANCE`, the only signature the image crate's decoder accepts. `None` for every other
/// file (only its first line is read).
fn renamed_radiance(path: &Path) -> Result<Option<RenamedRadiance>, String> {
    use std::io::{BufRead, Read};
    let file = std::fs::File::open(path).map_err(|e| format!("cannot read: {e}"))?;
    let mut rest = std::io::BufReader::new(file);
    let mut first = Vec::new();
    (&mut rest)
        .take(256)
        .read_until(b'\n', &mut first)
        .map_err(|e| format!("cannot read: {e}"))?;
    let other = first.starts_with(b"#?") && !first.starts_with(b"#?RADIANCE");
    if !other || !first.ends_with(b"\n") {
        return Ok(None);
    }
    let renamed = std::io::Cursor::new(&b"#?RADIANCE\n"[..]).chain(rest);
    image::codecs::hdr::HdrDecoder::new(std::io::BufReader::new(renamed))
        .map(Some)
        .map_err(|e| format!("cannot decode image: {e}"))
}

type RenamedRadiance = image::codecs::hdr::HdrDecoder<
    std::io::BufReader<
        std::io::Chain<std::io::Cursor<&'static [u8]>, std::io::BufReader<std::fs::File>>,
    >,
>;

fn is_exr(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("exr"))
}

/// Load `path`. EXR files are linear already. PNG/JPEG files (8 or 16 bit)
/// are sRGB-encoded and are linearised with the exact sRGB curve unless
/// `raw` (Mitsuba's `raw=true`: use values as stored). Grayscale expands to
/// RGB; alpha is dropped. Errors are messages for the caller to locate.
/// `max_alloc` bounds the decoder's allocations.
fn load_image(path: &Path, raw: bool, max_alloc: u64) -> Result<LoadedImage, String> {
    // Third-party decoders must not take the process down on a bad file.
    let img = std::panic::catch_unwind(|| {
        if is_exr(path) {
            load_exr(path)
        } else {
            load_ldr(path, raw, max_alloc)
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

fn load_ldr(path: &Path, raw: bool, max_alloc: u64) -> Result<LoadedImage, String> {
    // The size was checked against our limits; the decoder's own default (512 MiB) would
    // refuse a valid 16k x 16k texture.
    let mut limits = image::Limits::no_limits();
    limits.max_alloc = Some(max_alloc);
    let decoded = match renamed_radiance(path)? {
        Some(mut d) => image::ImageDecoder::set_limits(&mut d, limits)
            .and_then(|_| image::DynamicImage::from_decoder(d)),
        None => {
            let reader = image::ImageReader::open(path).map_err(|e| format!("cannot read: {e}"))?;
            let mut reader = reader
                .with_guessed_format()
                .map_err(|e| format!("cannot read: {e}"))?;
            reader.limits(limits);
            reader.decode()
        }
    };
    let dynimg = decoded.map_err(|e| format!("cannot decode image: {e}"))?;
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
