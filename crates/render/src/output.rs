//! Image output: OpenEXR (linear RGB, optional variance and sample-count
//! channels) and a tonemapped sRGB PNG preview. Files are written to a
//! temporary name and renamed, so a failed write leaves nothing half-written.

use std::path::{Path, PathBuf};

use exr::prelude::{
    read_first_flat_layer_from_file, AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer,
    LayerAttributes, WritableImage,
};

use crate::film::Film;
use crate::RenderError;

fn err(path: &Path, e: impl std::fmt::Display) -> RenderError {
    RenderError::Output {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

fn temp_path(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(format!(".tmp{}", std::process::id()));
    path.with_file_name(name)
}

/// Writes `rgb` (row-major, width x height). With `aovs`, also writes
/// `variance.R/G/B` (variance of each pixel's mean) and `spp`.
pub fn write_exr(path: &Path, film: &Film, aovs: bool) -> Result<(), RenderError> {
    let (w, h) = (film.width as usize, film.height as usize);
    let mean = film.mean_rgb();
    let mut list: Vec<AnyChannel<FlatSamples>> = Vec::new();
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        list.push(AnyChannel::new(
            *name,
            FlatSamples::F32(mean.iter().map(|p| p[c]).collect()),
        ));
    }
    if aovs {
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
    let image = Image::from_layer(layer);
    let tmp = temp_path(path);
    let result = image
        .write()
        .to_file(&tmp)
        .map_err(|e| err(path, e))
        .and_then(|_| std::fs::rename(&tmp, path).map_err(|e| err(path, e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
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

/// Writes an 8-bit sRGB PNG preview (clamped, no exposure change).
pub fn write_png(path: &Path, film: &Film) -> Result<(), RenderError> {
    let mean = film.mean_rgb();
    let mut bytes = Vec::with_capacity(mean.len() * 3);
    for p in &mean {
        for c in p {
            bytes.push((srgb_encode(*c) * 255.0 + 0.5) as u8);
        }
    }
    let tmp = temp_path(path);
    let result = image::save_buffer_with_format(
        &tmp,
        &bytes,
        film.width,
        film.height,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(|e| err(path, e))
    .and_then(|_| std::fs::rename(&tmp, path).map_err(|e| err(path, e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
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
