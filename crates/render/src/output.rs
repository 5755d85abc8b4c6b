//! Image output: OpenEXR (linear RGB, optional variance and sample-count
//! channels) and a tonemapped sRGB PNG preview.
//!
//! Encoding is separate from writing: [`encode_exr`] and [`encode_png`] build
//! the file's bytes in memory, so a caller can check and open its outputs
//! before the work and write them all at the end (the `pathfarm` command line
//! does, with its own crash-safe writer). [`write_exr`] and [`write_png`] are
//! the simple path for library users: the bytes go to an exclusively created,
//! uniquely named temporary beside the destination, which is synced and
//! renamed into place, and removed on any error.
//!
//! Every PNG pathfarm writes carries a `tEXt` chunk `Software` = `pathfarm`,
//! which [`is_pathfarm_preview`] looks for, so a preview can be told from a
//! file pathfarm did not write.

use std::fs::{File, OpenOptions};
use std::io::{Cursor, Read, Seek, SeekFrom, Write};
use std::path::Path;
use std::sync::atomic::{AtomicU32, Ordering};

use exr::prelude::{
    read_first_flat_layer_from_file, AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer,
    LayerAttributes, WritableImage,
};

use crate::film::Film;
use crate::RenderError;

/// The `tEXt` keyword and text that mark a PNG written by pathfarm.
pub const SOFTWARE_KEY: &str = "Software";
/// The text stored under [`SOFTWARE_KEY`] in the PNGs pathfarm writes.
pub const SOFTWARE_VALUE: &str = "pathfarm";

fn err(path: &Path, e: impl std::fmt::Display) -> RenderError {
    RenderError::Output {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Which channels an EXR carries besides `R`, `G`, `B`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Aovs {
    /// The pixel means only.
    No,
    /// Also `variance.R/G/B` (variance of each pixel's mean) and `spp`.
    Yes,
}

/// The OpenEXR file of `film`: `R`, `G`, `B` (the pixel means) and, with
/// [`Aovs::Yes`], `variance.R/G/B` (variance of each pixel's mean) and `spp`.
pub fn encode_exr(film: &Film, aovs: Aovs) -> Result<Vec<u8>, RenderError> {
    let (w, h) = (film.width as usize, film.height as usize);
    let mean = film.mean_rgb();
    let mut list: Vec<AnyChannel<FlatSamples>> = Vec::new();
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        list.push(AnyChannel::new(
            *name,
            FlatSamples::F32(mean.iter().map(|p| p[c]).collect()),
        ));
    }
    if aovs == Aovs::Yes {
        let var = film.variance_rgb();
        for (c, name) in ["variance.R", "variance.G", "variance.B"]
            .iter()
            .enumerate()
        {
            list.push(AnyChannel::new(
                *name,
                FlatSamples::F32(var.iter().map(|p| p[c]).collect()),
            ));
        }
        list.push(AnyChannel::new(
            "spp",
            FlatSamples::F32(film.pixels.iter().map(|p| p.count as f32).collect()),
        ));
    }
    let channels = AnyChannels::sort(list.into());
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        channels,
    );
    let mut out = Cursor::new(Vec::new());
    Image::from_layer(layer)
        .write()
        .to_buffered(&mut out)
        .map_err(|e| RenderError::Unsupported(format!("encoding the OpenEXR image: {e}")))?;
    Ok(out.into_inner())
}

/// Linear to sRGB-encoded [0, 1].
#[inline]
pub fn srgb_encode(x: f32) -> f32 {
    let x = x.clamp(0.0, 1.0);
    if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

/// The 8-bit sRGB PNG preview of `film` (clamped, no exposure change), marked
/// as pathfarm's.
pub fn encode_png(film: &Film) -> Result<Vec<u8>, RenderError> {
    encode_png_of_means(film.width, film.height, &film.mean_rgb())
}

/// [`encode_png`] of a film whose pixel values ([`Film::mean_rgb`]) are `mean`.
pub fn encode_png_of_means(
    width: u32,
    height: u32,
    mean: &[[f32; 3]],
) -> Result<Vec<u8>, RenderError> {
    let mut bytes = Vec::with_capacity(mean.len() * 3);
    for p in mean {
        for c in p {
            bytes.push((srgb_encode(*c) * 255.0 + 0.5) as u8);
        }
    }
    encode_png_rgb8(width, height, &bytes)
}

/// An 8-bit RGB PNG of `rgb` (row-major, 3 bytes a pixel), marked as pathfarm's
/// with the `tEXt` chunk `Software` = `pathfarm` before the image data.
pub fn encode_png_rgb8(width: u32, height: u32, rgb: &[u8]) -> Result<Vec<u8>, RenderError> {
    let png_err =
        |e: png::EncodingError| RenderError::Unsupported(format!("encoding the PNG: {e}"));
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.add_text_chunk(SOFTWARE_KEY.to_string(), SOFTWARE_VALUE.to_string())
            .map_err(png_err)?;
        let mut writer = enc.write_header().map_err(png_err)?;
        writer.write_image_data(rgb).map_err(png_err)?;
        writer.finish().map_err(png_err)?;
    }
    Ok(out)
}

/// Whether `path` is a PNG that pathfarm wrote: a PNG whose chunks before the
/// image data include the `tEXt` chunk `Software` = `pathfarm`. Reads only the
/// signature and the chunks before the first `IDAT` (skipping their data,
/// except small `tEXt` chunks); anything unreadable or malformed is `false`.
pub fn is_pathfarm_preview(path: &Path) -> bool {
    match File::open(path) {
        Ok(f) => png_has_pathfarm_mark(f).unwrap_or(false),
        Err(_) => false,
    }
}

fn png_has_pathfarm_mark(mut f: impl Read + Seek) -> std::io::Result<bool> {
    const SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', b'\r', b'\n', 0x1a, b'\n'];
    /// Chunks examined before giving up (a real header has a handful).
    const MAX_CHUNKS: usize = 64;
    /// The largest `tEXt` chunk read (the mark is 17 bytes).
    const MAX_TEXT: u32 = 256;
    let mut sig = [0u8; 8];
    f.read_exact(&mut sig)?;
    if sig != SIGNATURE {
        return Ok(false);
    }
    for i in 0..MAX_CHUNKS {
        let mut head = [0u8; 8];
        f.read_exact(&mut head)?;
        let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]);
        let kind = &head[4..8];
        if len > i32::MAX as u32 || (i == 0 && kind != b"IHDR") {
            return Ok(false);
        }
        match kind {
            b"IDAT" | b"IEND" => return Ok(false),
            b"tEXt" if len <= MAX_TEXT => {
                let mut data = vec![0u8; len as usize];
                f.read_exact(&mut data)?;
                let mark = [SOFTWARE_KEY.as_bytes(), &[0], SOFTWARE_VALUE.as_bytes()].concat();
                if data == mark {
                    return Ok(true);
                }
                f.seek(SeekFrom::Current(4))?;
            }
            _ => {
                f.seek(SeekFrom::Current(len as i64 + 4))?;
            }
        }
    }
    Ok(false)
}

/// Writes `bytes` to `path` through a temporary beside it: the temporary is
/// created exclusively under a unique hidden name (so no other file is ever
/// touched), synced, and renamed over `path`; on any error it is removed.
/// Not signal-safe: the command line uses its own writer for that.
pub fn write_file_atomic(path: &Path, bytes: &[u8]) -> Result<(), RenderError> {
    static N: AtomicU32 = AtomicU32::new(0);
    let name = path
        .file_name()
        .ok_or_else(|| err(path, "not a file name"))?
        .to_string_lossy()
        .into_owned();
    let (tmp, mut file) = loop {
        let tmp = path.with_file_name(format!(
            ".{name}.pathfarm-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        match OpenOptions::new().write(true).create_new(true).open(&tmp) {
            Ok(f) => break (tmp, f),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(err(path, e)),
        }
    };
    let result = file
        .write_all(bytes)
        .and_then(|_| file.sync_all())
        .and_then(|_| std::fs::rename(&tmp, path))
        .map_err(|e| err(path, e));
    drop(file);
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Writes the OpenEXR file of `film` (see [`encode_exr`]) to `path`, replacing it.
pub fn write_exr(path: &Path, film: &Film, aovs: Aovs) -> Result<(), RenderError> {
    let bytes = encode_exr(film, aovs).map_err(|e| err(path, e))?;
    write_file_atomic(path, &bytes)
}

/// Writes the PNG preview of `film` (see [`encode_png`]) to `path`, replacing it.
pub fn write_png(path: &Path, film: &Film) -> Result<(), RenderError> {
    let bytes = encode_png(film).map_err(|e| err(path, e))?;
    write_file_atomic(path, &bytes)
}

/// Reads the RGB channels of an EXR file (first layer) as row-major pixels;
/// used by tests and tools.
pub fn read_exr_rgb(path: &Path) -> Result<(u32, u32, Vec<[f32; 3]>), RenderError> {
    let image = read_first_flat_layer_from_file(path).map_err(|e| err(path, e))?;
    let layer = &image.layer_data;
    let (w, h) = (layer.size.0, layer.size.1);
    let find = |name: &str| layer.channel_data.list.iter().find(|c| c.name.eq(name));
    let get = |name: &str| -> Result<Vec<f32>, RenderError> {
        let c = find(name).ok_or_else(|| err(path, format!("no channel {name}")))?;
        Ok(c.sample_data.values_as_f32().collect())
    };
    let (r, g, b) = (get("R")?, get("G")?, get("B")?);
    Ok((
        w as u32,
        h as u32,
        (0..w * h).map(|i| [r[i], g[i], b[i]]).collect(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_pngs_pathfarm_wrote_are_recognised_as_previews() {
        let dir = std::env::temp_dir().join(format!("pathfarm-output-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let ours = dir.join("ours.png");
        let mut film = Film::new(3, 2);
        film.pixels[0].add(1.0, glam::Vec3::ONE);
        write_png(&ours, &film).unwrap();
        assert!(is_pathfarm_preview(&ours));
        let theirs = dir.join("theirs.png");
        image::save_buffer(&theirs, &[7u8; 3 * 2 * 3], 3, 2, image::ColorType::Rgb8).unwrap();
        assert!(!is_pathfarm_preview(&theirs));
        let junk = dir.join("junk.png");
        std::fs::write(&junk, b"\x89PNG\r\n\x1a\n").unwrap();
        assert!(!is_pathfarm_preview(&junk));
        assert!(!is_pathfarm_preview(&dir.join("missing.png")));
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names.len(), 3, "no temporary left: {names:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
