//! `pathfarm render` and `pathfarm info`.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use pathfarm_render::guided::{self, Budget};
use pathfarm_render::{output, RenderSettings, Scene};
use pathfarm_scene::load_scene;

use crate::cpu_time::process_cpu_time;

#[derive(Args)]
pub struct RenderArgs {
    /// The Mitsuba 3 XML scene.
    pub scene: PathBuf,
    /// Output EXR path (a PNG preview is written beside it).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Samples per pixel (default: the scene's sample_count; unbounded with --time).
    #[arg(long)]
    pub spp: Option<u32>,
    /// Wall-clock budget in seconds (the render stops at the end of a pass).
    #[arg(long)]
    pub time: Option<f64>,
    /// Seed of all random numbers (default: the scene sampler's seed).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Override a scene parameter declared with <default>, e.g. -D spp=64.
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    pub defines: Vec<String>,
    /// Also write per-pixel variance of the mean (variance.R/G/B) and spp channels.
    #[arg(long)]
    pub aovs: bool,
    /// Do not write the PNG preview.
    #[arg(long)]
    pub no_png: bool,
}

#[derive(Args)]
pub struct InfoArgs {
    pub scene: PathBuf,
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    pub defines: Vec<String>,
}

pub fn parse_defines(defs: &[String]) -> Result<Vec<(String, String)>> {
    defs.iter()
        .map(|d| match d.split_once('=') {
            Some((k, v)) if !k.is_empty() => Ok((k.to_string(), v.to_string())),
            _ => bail!("-D {d}: expected NAME=VALUE"),
        })
        .collect()
}

pub fn info(args: InfoArgs) -> Result<()> {
    let desc = load_scene(&args.scene, &parse_defines(&args.defines)?)
        .with_context(|| format!("loading {}", args.scene.display()))?;
    let scene = Scene::build(&desc)?;
    println!("scene: {}", args.scene.display());
    println!(
        "film: {}x{}, {} spp, integrator {:?}",
        scene.width, scene.height, scene.sample_count, desc.integrator
    );
    println!(
        "shapes: {}, triangles: {}, bsdfs: {}, textures: {}, lights: {}",
        desc.shapes.len(),
        scene.triangle_count,
        desc.bsdfs.len(),
        desc.textures.len(),
        scene.lights.lights.len()
    );
    println!("features: {:?}", desc.features);
    Ok(())
}

pub fn render(args: RenderArgs) -> Result<()> {
    if let Some(n) = args.threads {
        if n == 0 {
            bail!("--threads must be at least 1");
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .context("configuring the thread pool")?;
    }
    if let Some(t) = args.time {
        if !(t.is_finite() && t > 0.0) {
            bail!("--time must be a positive number of seconds, got {t}");
        }
    }
    if args.spp == Some(0) {
        bail!("--spp must be at least 1");
    }
    let ext_ok = args
        .output
        .extension()
        .map(|e| e.eq_ignore_ascii_case("exr"))
        .unwrap_or(false);
    if !ext_ok {
        bail!("{}: the output must be an .exr file", args.output.display());
    }
    let t_load = Instant::now();
    let desc = load_scene(&args.scene, &parse_defines(&args.defines)?)
        .with_context(|| format!("loading {}", args.scene.display()))?;
    for w in &desc.warnings {
        tracing::warn!("{w}");
    }
    let scene = Scene::build(&desc)?;
    tracing::info!(
        "loaded {} in {:.2} s: {}x{}, {} shapes, {} triangles, {} lights; features {:?}",
        args.scene.display(),
        t_load.elapsed().as_secs_f64(),
        scene.width,
        scene.height,
        desc.shapes.len(),
        scene.triangle_count,
        scene.lights.lights.len(),
        desc.features
    );
    let settings = RenderSettings::new(
        args.spp.or(if args.time.is_some() {
            None
        } else {
            Some(scene.sample_count)
        }),
        args.time.map(Duration::from_secs_f64),
        args.seed.unwrap_or(scene.seed),
    );
    let bar = ProgressBar::new(1);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {percent}% ({eta} left)",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let cpu0 = process_cpu_time();
    let progress = |p: pathfarm_render::Progress| {
        bar.set_length(p.samples_total);
        bar.set_position(p.samples_done);
    };
    let (film, stats) = match &scene.guided {
        None => pathfarm_render::render(&scene, &settings, &progress),
        Some(params) => {
            // --spp / --time set the guided budget (training + final) as they set the
            // path tracer's; otherwise the integrator's own budget applies.
            let budget = match (args.spp, args.time) {
                (Some(s), _) => Budget::Spp(s),
                (None, Some(t)) => Budget::Seconds(t),
                (None, None) => guided::params_budget(params, &scene),
            };
            let on_iteration = |it: &guided::GuidedIteration| {
                bar.suspend(|| {
                    tracing::info!(
                        "iteration {}: spp={} nodes={} leaves={} variance={:.6e} time={:.3}s rays_per_sample={:.3}",
                        it.index,
                        it.spp,
                        it.nodes,
                        it.leaves,
                        it.variance,
                        it.seconds,
                        it.rays_per_sample
                    )
                })
            };
            let (film, gs, _tree) = guided::render_guided_with(
                &scene,
                params,
                budget,
                &settings,
                &progress,
                &on_iteration,
            );
            bar.suspend(|| {
                tracing::info!(
                    "guided: training_fraction={:.3} tree_memory_mb={:.3} weights={:?} \
                     path_fallback={} split_paths={} extra_light_samples={}",
                    gs.training_fraction,
                    gs.tree_memory_bytes as f64 / 1048576.0,
                    gs.weights,
                    gs.path_fallback_after
                        .map_or("no".to_string(), |k| format!("after_iteration_{k}")),
                    gs.split_paths,
                    gs.extra_light_samples
                )
            });
            (
                film,
                pathfarm_render::RenderStats {
                    spp: gs.spp,
                    wall: gs.wall,
                    invalid_samples: gs.invalid_samples,
                },
            )
        }
    };
    let cpu = (process_cpu_time() - cpu0).as_secs_f64();
    bar.finish_and_clear();
    if stats.invalid_samples > 0 {
        tracing::warn!(
            "{} samples were NaN or infinite and counted as zero",
            stats.invalid_samples
        );
    }
    if let Some(dir) = args.output.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    output::write_exr(&args.output, &film, args.aovs)?;
    if !args.no_png {
        output::write_png(&args.output.with_extension("png"), &film)?;
    }
    let samples = film.width as f64 * film.height as f64 * stats.spp as f64;
    println!(
        "summary: resolution={}x{} spp={} wall_s={:.3} cpu_s={:.3} samples_per_cpu_s={:.0}",
        film.width,
        film.height,
        stats.spp,
        stats.wall.as_secs_f64(),
        cpu,
        samples / cpu.max(1e-9)
    );
    Ok(())
}
