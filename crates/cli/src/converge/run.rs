//! One run of one method at one budget: in this process, or on a local farm.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use pathfarm_render::{output, Scene};

use super::method::{apply_sweep, Method, Variant};
use super::metrics::Image;
use crate::cpu_time::{children_cpu_time, process_cpu_time};
use crate::render_cmd::{render_scene, RenderBudget};

/// A run's budget: wall seconds (as `pathfarm render --time`) or samples per pixel.
pub use pathfarm_render::guided::Budget;

/// A budget as a number (the `budget` column).
pub fn value(b: Budget) -> f64 {
    match b {
        Budget::Seconds(s) => s,
        Budget::Spp(n) => n as f64,
    }
}

/// A budget as `pathfarm render`'s flags take it.
fn render_budget(b: Budget) -> RenderBudget {
    match b {
        Budget::Seconds(s) => RenderBudget {
            spp: None,
            time: Some(s),
        },
        Budget::Spp(n) => RenderBudget {
            spp: Some(n),
            time: None,
        },
    }
}

/// What one run measured (besides its image).
#[derive(Clone, Debug, PartialEq)]
pub struct Measured {
    pub wall_s: f64,
    pub cpu_s: f64,
    pub spp: u32,
    pub nonfinite: u64,
    pub training_fraction: f64,
    pub tree_memory_mb: f64,
}

/// Everything a run needs besides its variant, budget and seed.
pub struct RunContext<'a> {
    /// The scene, built once; its integrator is set per run.
    pub scene: &'a mut Scene,
    /// The scene file and the `-D` overrides (a cluster run loads the scene itself).
    pub scene_path: &'a Path,
    pub defines: &'a [String],
    /// The integrator a cluster run renders the scene with when the scene's own is not
    /// `guided_path` (`--integrator` of `cluster`; a farm renders guided jobs only).
    pub farm_integrator: Option<&'a str>,
    /// Threads of in-process runs; a cluster's workers share them.
    pub threads: usize,
    /// Samples done / total of the current run, for the progress bar.
    pub progress: &'a (dyn Fn(u64, u64) + Sync),
}

/// Renders `variant` within `budget` from `seed`; the image is also written to `exr`.
pub fn run(
    ctx: &mut RunContext,
    variant: &Variant,
    budget: Budget,
    seed: u64,
    exr: &Path,
) -> Result<(Image, Measured)> {
    if let Method::Cluster { workers } = variant.method {
        return run_cluster(ctx, workers, budget, seed, exr);
    }
    let path = ctx.scene.path;
    ctx.scene.guided = match &variant.method {
        Method::Guided(preset) => {
            let mut p = preset.params(path);
            if let Some((name, v)) = &variant.sweep {
                apply_sweep(&mut p, name, *v)?;
            }
            Some(p)
        }
        _ => None,
    };
    let progress = |p: pathfarm_render::Progress| (ctx.progress)(p.samples_done, p.samples_total);
    let (cpu0, t0) = (process_cpu_time(), Instant::now());
    let r = render_scene(ctx.scene, render_budget(budget), seed, &progress, &|_| {})?;
    let wall_s = t0.elapsed().as_secs_f64();
    let cpu_s = (process_cpu_time() - cpu0).as_secs_f64();
    if r.stats.spp == 0 {
        bail!(
            "{}: the budget ended before one sample per pixel",
            variant.label
        );
    }
    output::write_exr(exr, &r.film, output::Aovs::No)?;
    let measured = Measured {
        wall_s,
        cpu_s,
        spp: r.stats.spp,
        nonfinite: r.stats.nonfinite(),
        training_fraction: r.guided.as_ref().map_or(0.0, |g| g.training_fraction),
        tree_memory_mb: r
            .guided
            .as_ref()
            .map_or(0.0, |g| g.tree_memory_bytes as f64 / 1048576.0),
    };
    let image = Image {
        width: r.film.width,
        height: r.film.height,
        pixels: r.film.mean_rgb(),
    };
    Ok((image, measured))
}

/// `pathfarm cluster` as a child process: its whole wall time (processes, uploads and all)
/// is the run's, and the CPU time of the cluster and everything it started.
fn run_cluster(
    ctx: &RunContext,
    workers: u32,
    budget: Budget,
    seed: u64,
    exr: &Path,
) -> Result<(Image, Measured)> {
    let exe = std::env::current_exe().context("finding the pathfarm executable")?;
    let mut cmd = Command::new(exe);
    cmd.arg("cluster")
        .arg("--workers")
        .arg(workers.to_string())
        .arg("--threads-per-worker")
        .arg((ctx.threads / workers as usize).max(1).to_string())
        .arg(ctx.scene_path)
        .arg("-o")
        .arg(exr)
        .arg("--seed")
        .arg(seed.to_string());
    match budget {
        Budget::Seconds(s) => cmd.arg("--time").arg(s.to_string()),
        Budget::Spp(n) => cmd.arg("--spp").arg(n.to_string()),
    };
    for d in ctx.defines {
        cmd.arg("-D").arg(d);
    }
    if let Some(name) = ctx.farm_integrator {
        cmd.arg("--integrator").arg(name);
    }
    let (cpu0, t0) = (children_cpu_time(), Instant::now());
    let out = cmd
        .stdin(Stdio::null())
        .env("RUST_LOG", "warn")
        .output()
        .context("running pathfarm cluster")?;
    let wall_s = t0.elapsed().as_secs_f64();
    let cpu_s = (children_cpu_time() - cpu0).as_secs_f64();
    let stdout = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        bail!(
            "pathfarm cluster --workers {workers} failed ({}): {}",
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    let field = |key: &str| -> Result<u64> {
        summary_field(&stdout, key)
            .with_context(|| format!("pathfarm cluster printed no {key}= in: {stdout}"))
    };
    let image = read_image(exr)?;
    let measured = Measured {
        wall_s,
        cpu_s,
        spp: field("spp")? as u32,
        nonfinite: field("nonfinite")?,
        training_fraction: f64::NAN,
        tree_memory_mb: f64::NAN,
    };
    Ok((image, measured))
}

/// The integer after `key=` on the `summary:` line of `stdout`.
fn summary_field(stdout: &str, key: &str) -> Option<u64> {
    let line = stdout.lines().find(|l| l.starts_with("summary:"))?;
    line.split_whitespace()
        .find_map(|w| w.strip_prefix(key)?.strip_prefix('='))?
        .parse()
        .ok()
}

/// An EXR's RGB channels.
pub fn read_image(path: &Path) -> Result<Image> {
    let (width, height, pixels) = output::read_exr_rgb(path)?;
    Ok(Image {
        width,
        height,
        pixels,
    })
}

/// `DIR/images/STEM-BUDGET-REPEAT.exr`.
pub fn image_path(dir: &Path, stem: &str, budget: Budget, repeat: u32) -> PathBuf {
    dir.join("images")
        .join(format!("{stem}-{}-{repeat}.exr", value(budget)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summary_fields_are_read_from_the_summary_line_only() {
        let out = "job-1\nsummary: job=job-1 spp=64 wall_s=3.2 nonfinite=0\n";
        assert_eq!(summary_field(out, "spp"), Some(64));
        assert_eq!(summary_field(out, "nonfinite"), Some(0));
        assert_eq!(summary_field(out, "rays"), None);
        assert_eq!(summary_field("spp=3\n", "spp"), None);
    }
}
