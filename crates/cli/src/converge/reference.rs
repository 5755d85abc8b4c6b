//! The reference image: given by the user, or rendered once with the most efficient method
//! and cached by the scene's content.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use pathfarm_render::output;

use super::method::{Method, Preset, Variant};
use super::metrics::{reference_floor, Image};
use super::run::{self, read_image, Budget, RunContext};

/// The reference and what is known of its own error.
pub struct Reference {
    pub image: Image,
    /// Its relMSE against the truth: estimated from two independent halves when rendered,
    /// else from pairs of runs once they are done (`None` until then, or with one repeat).
    pub floor: Option<f64>,
    /// Where it came from, for the summary.
    pub source: String,
}

/// Reads `path` and box-downsamples it to `width x height`.
pub fn given(path: &Path, width: u32, height: u32) -> Result<Reference> {
    let image = read_image(path)
        .with_context(|| format!("--reference {}", path.display()))?
        .downsample_to(width, height)
        .with_context(|| format!("--reference {}", path.display()))?;
    Ok(Reference {
        image,
        floor: None,
        source: format!("{} (given)", path.display()),
    })
}

/// The cached reference of key `key` in `cache`, or a new one rendered as two halves of
/// `budget` each with the pathfarm guided preset (seeds 1 000 001 and 1 000 002, apart from
/// the runs' seeds), then cached.
pub fn rendered(
    ctx: &mut RunContext,
    cache: &Path,
    key: &str,
    budget: Budget,
) -> Result<Reference> {
    let halves = [1, 2].map(|i| cache.join(format!("{key}-half{i}.exr")));
    let source = format!(
        "pathfarm guided_path (pathfarm preset), 2 x {} {}, cached as {}",
        run::value(budget),
        match budget {
            Budget::Seconds(_) => "s",
            Budget::Spp(_) => "spp",
        },
        halves[0]
            .with_file_name(format!("{key}-half*.exr"))
            .display()
    );
    if halves.iter().all(|h| h.is_file()) {
        let a = read_image(&halves[0])?;
        let b = read_image(&halves[1])?;
        if a.width == b.width && a.height == b.height {
            return Ok(from_halves(a, b, source));
        }
    }
    std::fs::create_dir_all(cache)
        .with_context(|| format!("creating the reference cache {}", cache.display()))?;
    let variant = Variant {
        method: Method::Guided(Preset::Pathfarm),
        sweep: None,
        label: "reference".into(),
    };
    let mut images = Vec::new();
    for (i, half) in halves.iter().enumerate() {
        let tmp = temp_beside(half);
        let r = run::run(ctx, &variant, budget, 1_000_001 + i as u64, &tmp);
        let r = r.and_then(|(img, _)| {
            std::fs::rename(&tmp, half).with_context(|| format!("writing {}", half.display()))?;
            Ok(img)
        });
        if r.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        images.push(r?);
    }
    let b = images.pop().expect("two");
    let a = images.pop().expect("two");
    Ok(from_halves(a, b, source))
}

fn from_halves(a: Image, b: Image, source: String) -> Reference {
    let floor = reference_floor(&a, &b);
    Reference {
        image: Image::average(&a, &b),
        floor: Some(floor),
        source,
    }
}

/// A unique temporary name beside `path` (renamed over it once complete).
fn temp_beside(path: &Path) -> PathBuf {
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    path.with_file_name(format!(".{name}.{}.exr", std::process::id()))
}

/// The cache key: the build, every file the scene read (name and content), the overrides,
/// the resolution and the reference's budget.
pub fn cache_key(
    files: &[PathBuf],
    defines: &[String],
    size: (u32, u32),
    budget: Budget,
) -> Result<String> {
    let mut h = blake3::Hasher::new();
    h.update(b"pathfarm converge reference v1\0");
    h.update(pathfarm_farm::build::build_id().as_bytes());
    for f in files {
        let bytes = std::fs::read(f).with_context(|| format!("reading {}", f.display()))?;
        h.update(f.file_name().unwrap_or_default().as_encoded_bytes());
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(&bytes);
    }
    for d in defines {
        h.update(d.as_bytes());
        h.update(b"\0");
    }
    h.update(format!("{}x{} {:?}", size.0, size.1, budget).as_bytes());
    Ok(h.finalize().to_hex()[..32].to_string())
}

/// `$XDG_CACHE_HOME/pathfarm/references`, else `$HOME/.cache/pathfarm/references`.
pub fn default_cache() -> Result<PathBuf> {
    let base = match (std::env::var_os("XDG_CACHE_HOME"), std::env::var_os("HOME")) {
        (Some(x), _) if !x.is_empty() => PathBuf::from(x),
        (_, Some(h)) if !h.is_empty() => PathBuf::from(h).join(".cache"),
        _ => bail!("neither XDG_CACHE_HOME nor HOME is set: name a reference cache with --cache"),
    };
    Ok(base.join("pathfarm").join("references"))
}

/// Writes the reference used beside the results (so every figure can be checked).
pub fn save(reference: &Reference, path: &Path) -> Result<()> {
    let mut film = pathfarm_render::Film::new(reference.image.width, reference.image.height);
    for (px, v) in film.pixels.iter_mut().zip(&reference.image.pixels) {
        px.add(1.0, glam::Vec3::from_array(*v));
    }
    output::write_exr(path, &film, output::Aovs::No)?;
    Ok(())
}
