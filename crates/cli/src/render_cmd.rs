//! `pathfarm render` and `pathfarm info`.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use pathfarm_render::guided::{self, Budget};
use pathfarm_render::{output, RenderSettings, Scene};
use pathfarm_scene::{load_scene, load_scene_as, Limits};

use crate::cpu_time::process_cpu_time;
use crate::outfile::{self, OutputFile};

#[derive(Args)]
pub struct RenderArgs {
    /// The Mitsuba 3 XML scene.
    pub scene: PathBuf,
    /// Output EXR path (a PNG preview is written beside it; see --preview).
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub budget: BudgetArgs,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Also write per-pixel variance of the mean (variance.R/G/B) and spp channels.
    #[arg(long)]
    pub aovs: bool,
    /// Do not write the PNG preview.
    #[arg(long)]
    pub no_png: bool,
    /// Where to write the PNG preview (default: the output path with .png). Without
    /// this flag, an existing file there is replaced only if pathfarm wrote it.
    #[arg(long, value_name = "PATH", conflicts_with = "no_png")]
    pub preview: Option<PathBuf>,
}

/// What a render computes and with which random numbers: the flags `render`, `submit` and
/// `cluster` share.
#[derive(Args, Clone)]
pub struct BudgetArgs {
    /// Samples per pixel (default: the scene's own budget; for the path tracer, unbounded
    /// with --time). `render` also takes both: the path tracer stops at whichever comes first
    /// and a guided render takes --spp; a farm job takes one of the two.
    #[arg(long)]
    pub spp: Option<u32>,
    /// Wall-clock budget in seconds (the render stops at the end of a pass).
    #[arg(long)]
    pub time: Option<f64>,
    /// Seed of all random numbers (default: the scene sampler's seed).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Override a scene parameter declared with <default>, e.g. -D spp=64.
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    pub defines: Vec<String>,
    /// Replace the scene's integrator by NAME (path, direct, guided_path), keeping its
    /// max_depth, rr_depth and hide_emitters; says on stderr what it replaced and dropped.
    #[arg(long, value_name = "NAME")]
    pub integrator: Option<String>,
}

impl BudgetArgs {
    /// `--spp` and `--time` within `limits` (see [`check_budget_flags`]).
    pub fn check(&self, limits: &Limits) -> Result<()> {
        check_budget_flags(self.spp, self.time, limits)
    }
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

/// `--spp` and `--time` within the limits (`Duration::from_secs_f64` panics past about 1.8e19
/// seconds, so this runs before any conversion).
pub fn check_budget_flags(spp: Option<u32>, time: Option<f64>, limits: &Limits) -> Result<()> {
    if let Some(t) = time {
        if !(t.is_finite() && t > 0.0) {
            bail!("--time must be a positive number of seconds, got {t}");
        }
        if t > limits.max_time_seconds {
            bail!(
                "--time {}: more than the limit of {} seconds (Limits::max_time_seconds)",
                pathfarm_scene::limits::format_number(t),
                limits.max_time_seconds
            );
        }
    }
    if let Some(n) = spp {
        if n == 0 {
            bail!("--spp must be at least 1");
        }
        if n as u64 > limits.max_spp {
            bail!(
                "--spp {n}: more than the limit of {} samples per pixel (Limits::max_spp)",
                limits.max_spp
            );
        }
    }
    Ok(())
}

pub fn info(args: InfoArgs) -> Result<()> {
    let desc = load_scene(&args.scene, &parse_defines(&args.defines)?)?;
    let scene = Scene::build(&desc)?;
    println!("scene: {}", args.scene.display());
    println!(
        "film: {}x{}, {} spp, integrator {:?}",
        scene.width, scene.height, scene.sample_count, desc.integrator
    );
    println!(
        "shapes: {}, triangles: {}, bsdfs: {}, textures: {}, lights: {}",
        desc.shapes.len(),
        scene.world().triangle_count,
        desc.bsdfs.len(),
        desc.textures.len(),
        scene.world().lights.lights.len()
    );
    println!("features: {:?}", desc.features);
    Ok(())
}

/// Opens the PNG preview: `--preview PATH`, which may be replaced whatever it holds, or
/// the output path with .png, which may be replaced only if it is a preview pathfarm wrote
/// (it could be one of the scene's own textures).
fn open_preview(args: &RenderArgs) -> Result<OutputFile> {
    let path = match &args.preview {
        Some(p) => p.clone(),
        None => args.output.with_extension("png"),
    };
    if outfile::same_destination(&path, &args.output) {
        bail!(
            "--preview {}: the same file as the output (-o); give another path",
            path.display()
        );
    }
    if args.preview.is_some() {
        return OutputFile::create(&path);
    }
    OutputFile::create_checked(&path, |p| {
        if output::is_pathfarm_preview(p) {
            return Ok(());
        }
        bail!(
            "{}: exists and is not a preview written by pathfarm, so it is left alone; \
             name another preview file with --preview PATH, or write none with --no-png",
            p.display()
        )
    })
}

pub fn render(args: RenderArgs) -> Result<()> {
    if let Some(n) = args.threads {
        use_threads(n)?;
    }
    let limits = Limits::default();
    args.budget.check(&limits)?;
    let ext_ok = args
        .output
        .extension()
        .map(|e| e.eq_ignore_ascii_case("exr"))
        .unwrap_or(false);
    if !ext_ok {
        bail!("{}: the output must be an .exr file", args.output.display());
    }
    // The outputs are checked and opened before the work, and written together at the end.
    let exr_out = OutputFile::create(&args.output)?;
    let png_out = if args.no_png {
        None
    } else {
        Some(open_preview(&args)?)
    };
    let t_load = Instant::now();
    let defines = parse_defines(&args.budget.defines)?;
    let integrator = args.budget.integrator.as_deref();
    let desc = load_scene_as(&args.scene, &defines, &limits, integrator)?;
    for w in &desc.warnings {
        tracing::warn!("{w}");
    }
    let scene = Scene::build(&desc)?;
    tracing::info!(
        "loaded {} in {:.2} s: {}x{}, {} shapes, {} triangles, {} lights; effects: {}",
        args.scene.display(),
        t_load.elapsed().as_secs_f64(),
        scene.width,
        scene.height,
        desc.shapes.len(),
        scene.world().triangle_count,
        scene.world().lights.lights.len(),
        desc.features
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
    let budget = RenderBudget {
        spp: args.budget.spp,
        time: args.budget.time,
    };
    let seed = args.budget.seed.unwrap_or(scene.seed);
    let rendered = render_scene(&scene, budget, seed, &progress, &on_iteration)?;
    if let Some(gs) = &rendered.guided {
        bar.suspend(|| log_guided(gs));
    }
    let (film, stats) = (rendered.film, rendered.stats);
    let cpu = (process_cpu_time() - cpu0).as_secs_f64();
    bar.finish_and_clear();
    if stats.spp == 0 {
        bail!(
            "--time {}: the budget ended before one sample per pixel was rendered; nothing \
             was written (give more time)",
            args.budget.time.unwrap_or(0.0)
        );
    }
    if stats.invalid_samples > 0 {
        tracing::warn!(
            "{} samples were NaN or infinite and counted as zero",
            stats.invalid_samples
        );
    }
    if stats.nonfinite_records > 0 {
        tracing::warn!(
            "{} guide records were NaN or infinite and left out of the SD-tree",
            stats.nonfinite_records
        );
    }
    let aovs = if args.aovs {
        output::Aovs::Yes
    } else {
        output::Aovs::No
    };
    let exr = output::encode_exr(&film, aovs)
        .with_context(|| format!("writing {}", exr_out.path().display()))?;
    let png = match &png_out {
        Some(out) => Some(
            output::encode_png(&film)
                .with_context(|| format!("writing {}", out.path().display()))?,
        ),
        None => None,
    };
    let mut outputs = vec![(exr_out, exr.as_slice())];
    if let (Some(out), Some(bytes)) = (png_out, &png) {
        outputs.push((out, bytes.as_slice()));
    }
    outfile::commit_all(outputs)?;
    let samples = film.width as f64 * film.height as f64 * stats.spp as f64;
    println!(
        "summary: resolution={}x{} spp={} wall_s={:.3} cpu_s={:.3} samples_per_cpu_s={:.0} \
         nonfinite={}",
        film.width,
        film.height,
        stats.spp,
        stats.wall.as_secs_f64(),
        cpu,
        samples / cpu.max(1e-9),
        stats.nonfinite()
    );
    Ok(())
}

/// Renders with `n` threads (`--threads`).
pub fn use_threads(n: usize) -> Result<()> {
    if n == 0 {
        bail!("--threads must be at least 1");
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(n)
        .build_global()
        .context("configuring the thread pool")
}

/// A render's budget as the command line gives it: `--spp`, `--time`, or neither (the
/// scene's own).
#[derive(Clone, Copy, Debug, Default)]
pub struct RenderBudget {
    pub spp: Option<u32>,
    pub time: Option<f64>,
}

/// What rendering a scene in this process gives.
pub struct Rendered {
    pub film: pathfarm_render::Film,
    pub stats: pathfarm_render::RenderStats,
    /// The guided integrator's statistics (`guided_path` scenes only).
    pub guided: Option<guided::GuidedStats>,
}

/// Renders `scene` with its integrator within `budget` from `seed`: `pathfarm render`'s
/// work, shared with `pathfarm converge`.
pub fn render_scene(
    scene: &Scene,
    budget: RenderBudget,
    seed: u64,
    progress: &(dyn Fn(pathfarm_render::Progress) + Sync),
    on_iteration: &dyn Fn(&guided::GuidedIteration),
) -> Result<Rendered> {
    // Without --spp or --time the path tracer renders the scene's sample count.
    let spp = match budget.time {
        Some(_) => budget.spp,
        None => budget.spp.or(Some(scene.sample_count)),
    };
    let settings = &RenderSettings::new(spp, budget.time.map(Duration::from_secs_f64), seed);
    let Some(params) = &scene.guided else {
        let (film, stats) = pathfarm_render::render(scene, settings, progress);
        return Ok(Rendered {
            film,
            stats,
            guided: None,
        });
    };
    // --spp / --time set the guided budget (training + final) as they set the path
    // tracer's; otherwise the integrator's own budget applies.
    let b = match (budget.spp, budget.time) {
        (Some(s), _) => Budget::Spp(s),
        (None, Some(t)) => Budget::Seconds(t),
        (None, None) => guided::params_budget(params, scene),
    };
    guided::check_budget(params, b).map_err(anyhow::Error::msg)?;
    let options = guided::GuidedOptions {
        progress,
        on_iteration,
        ..Default::default()
    };
    let (film, gs, _tree) = guided::render_guided(scene, params, b, settings, options);
    let stats = pathfarm_render::RenderStats {
        spp: gs.spp,
        wall: gs.wall,
        invalid_samples: gs.invalid_samples,
        nonfinite_records: gs.nonfinite_records,
    };
    Ok(Rendered {
        film,
        stats,
        guided: Some(gs),
    })
}

fn log_guided(gs: &guided::GuidedStats) {
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
    );
}
