//! `pathfarm converge`: what accuracy costs in time, on the user's own scene. Every method at
//! every budget, several seeds, against a reference; the error-against-time chart, a noise
//! figure at equal time and a summary of each method's time to reach an error level.
//!
//! Layout: [`method`] (what is compared and swept), [`run`] (one render), [`reference`],
//! [`metrics`] (relMSE), [`summary`] (CSV, tables), [`plot`] (the chart), [`crops`] (the
//! noise figure). This file parses the arguments and drives the runs.

mod crops;
mod method;
mod metrics;
mod plot;
mod reference;
mod run;
mod summary;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

use anyhow::{bail, Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use pathfarm_render::{output, Scene};
use pathfarm_scene::{load_scene_as, IntegratorDesc, Limits};

use crate::render_cmd::{parse_defines, use_threads};
use method::{file_stem, variants, Method, Sweep, Variant};
use metrics::{errors, Image};
use run::{image_path, Budget, RunContext};
use summary::Row;

#[derive(Args)]
pub struct ConvergeArgs {
    /// The Mitsuba 3 XML scene.
    pub scene: PathBuf,
    /// Directory for the results (created if missing; files of earlier runs are replaced).
    #[arg(short, long, value_name = "DIR")]
    pub output: PathBuf,
    /// Reference image (EXR at the scene's resolution or an integer multiple of it, which is
    /// box-downsampled). Default: render one with the guided method and cache it.
    #[arg(long, value_name = "REF.exr")]
    pub reference: Option<PathBuf>,
    /// Wall-clock budgets in seconds, as `pathfarm render --time` (default 5,10,20).
    #[arg(long, value_delimiter = ',', conflicts_with = "spp_budgets")]
    pub budgets: Vec<f64>,
    /// Samples-per-pixel budgets instead of seconds, e.g. 16,64,256.
    #[arg(long, value_delimiter = ',')]
    pub spp_budgets: Vec<u32>,
    /// Methods to compare: path, guided (pathfarm preset), guided-2017, guided-2019,
    /// cluster:N (guided on a local farm of N worker processes sharing the threads).
    #[arg(long, value_delimiter = ',', default_value = "path,guided")]
    pub methods: Vec<String>,
    /// Runs of every method at every budget, with seeds SEED, SEED+1, ...
    #[arg(long, default_value_t = 3)]
    pub repeats: u32,
    /// The first repeat's seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Vary a guide parameter: NAME=V1,V2,... (s_tree_threshold, d_tree_threshold,
    /// spp_per_pass, carry_over, guided_rr_depth); every guided method runs once per value.
    /// May be given several times.
    #[arg(long, value_name = "NAME=V1,V2")]
    pub sweep: Vec<String>,
    /// The crop of the noise figure, X,Y,W,H in pixels (default: where the methods differ
    /// most).
    #[arg(long, value_name = "X,Y,W,H")]
    pub crop: Option<String>,
    /// Override a scene parameter declared with <default>, e.g. -D resx=320.
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    pub defines: Vec<String>,
    /// Replace the scene's integrator by NAME (path, direct, guided_path), keeping its
    /// max_depth, rr_depth and hide_emitters; says on stderr what it replaced and dropped.
    #[arg(long, value_name = "NAME")]
    pub integrator: Option<String>,
    /// Render threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// The reference's budget, each of its two halves (default: 8x the largest budget).
    #[arg(long)]
    pub reference_budget: Option<f64>,
    /// Where rendered references are cached, keyed by the scene's files, the overrides and
    /// the build (default: $XDG_CACHE_HOME/pathfarm/references or
    /// ~/.cache/pathfarm/references).
    #[arg(long, value_name = "DIR")]
    pub cache: Option<PathBuf>,
}

/// The checked arguments.
struct Plan {
    variants: Vec<Variant>,
    budgets: Vec<Budget>,
    unit: &'static str,
    reference_budget: Budget,
}

fn plan(args: &ConvergeArgs) -> Result<Plan> {
    let methods = args
        .methods
        .iter()
        .map(|m| Method::parse(m.trim()))
        .collect::<Result<Vec<_>>>()?;
    let sweeps = args
        .sweep
        .iter()
        .map(|s| Sweep::parse(s))
        .collect::<Result<Vec<_>>>()?;
    if !sweeps.is_empty() && !methods.iter().any(|m| matches!(m, Method::Guided(_))) {
        bail!("--sweep varies the guided methods; --methods names none");
    }
    if args.repeats == 0 || args.repeats > 1000 {
        bail!("--repeats must be 1 to 1000");
    }
    let (budgets, unit) = if !args.spp_budgets.is_empty() {
        if args
            .spp_budgets
            .iter()
            .any(|&b| b == 0 || b as u64 > Limits::default().max_spp)
        {
            bail!(
                "--spp-budgets: each must be 1 to {}",
                Limits::default().max_spp
            );
        }
        (
            args.spp_budgets.iter().map(|&b| Budget::Spp(b)).collect(),
            "spp",
        )
    } else {
        let b = if args.budgets.is_empty() {
            vec![5.0, 10.0, 20.0]
        } else {
            args.budgets.clone()
        };
        if b.iter()
            .any(|&s| !(s > 0.0 && s <= Limits::default().max_time_seconds))
        {
            bail!("--budgets: each must be a positive number of seconds");
        }
        (b.into_iter().map(Budget::Seconds).collect::<Vec<_>>(), "s")
    };
    let largest = budgets.iter().map(|b| run::value(*b)).fold(0.0, f64::max);
    let r = args.reference_budget.unwrap_or(8.0 * largest);
    if !(r > 0.0) {
        bail!("--reference-budget must be positive");
    }
    let reference_budget = match budgets[0] {
        Budget::Spp(_) => Budget::Spp(
            r.round()
                .clamp(1.0, Limits::default().max_spp.min(u32::MAX as u64) as f64)
                as u32,
        ),
        Budget::Seconds(_) => Budget::Seconds(r.min(Limits::default().max_time_seconds)),
    };
    Ok(Plan {
        variants: variants(&methods, &sweeps),
        budgets,
        unit,
        reference_budget,
    })
}

pub fn converge(args: ConvergeArgs) -> Result<()> {
    let plan = plan(&args)?;
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    use_threads(threads)?;
    let defines = parse_defines(&args.defines)?;
    let integrator = args.integrator.as_deref();
    let desc = load_scene_as(&args.scene, &defines, &Limits::default(), integrator)?;
    for w in &desc.warnings {
        tracing::warn!("{w}");
    }
    let mut scene = Scene::build(&desc)?;
    // A farm renders guided jobs only: a cluster run replaces another integrator.
    let guided = matches!(desc.integrator, IntegratorDesc::GuidedPath(_));
    let farm_integrator = (!guided).then_some("guided_path");
    let runs = (plan.budgets.len() * plan.variants.len() * args.repeats as usize) as u64;
    let bar = progress_bar(runs + 2);
    // The bar counts runs (the reference's two halves first) in thousandths.
    let finished = AtomicU64::new(0);
    let set_progress = |done: u64, total: u64| {
        let part = 1000 * done.min(total) / total.max(1);
        bar.set_position(finished.load(Relaxed) * 1000 + part);
    };
    let mut ctx = RunContext {
        scene: &mut scene,
        scene_path: &args.scene,
        defines: &args.defines,
        farm_integrator,
        threads,
        progress: &set_progress,
    };
    let (w, h) = (ctx.scene.width, ctx.scene.height);
    let crop = match &args.crop {
        Some(c) => Some(crops::Crop::parse(c, w, h)?),
        None => None,
    };
    let reference = match &args.reference {
        Some(p) => reference::given(p, w, h)?,
        None => {
            bar.set_message("reference");
            let cache = match &args.cache {
                Some(c) => c.clone(),
                None => reference::default_cache()?,
            };
            let key =
                reference::cache_key(&desc.files, &args.defines, (w, h), plan.reference_budget)?;
            reference::rendered(&mut ctx, &cache, &key, plan.reference_budget)?
        }
    };
    finished.store(2, Relaxed);
    let dir = &args.output;
    std::fs::create_dir_all(dir.join("images"))
        .with_context(|| format!("creating {}", dir.join("images").display()))?;
    reference::save(&reference, &dir.join("reference.exr"))?;
    let rows = run_all(&mut ctx, &plan, &args, &reference.image, &bar, &finished)?;
    let mut reference = reference;
    if reference.floor.is_none() {
        reference.floor = floor_from_runs(&args, &plan, &reference.image)?;
    }
    bar.finish_and_clear();
    write_outputs(&args, &plan, &rows, &reference, Setup { threads, crop })?;
    println!(
        "converge: {} runs, results in {}",
        rows.len(),
        dir.display()
    );
    Ok(())
}

fn progress_bar(runs: u64) -> ProgressBar {
    let bar = ProgressBar::new(runs * 1000);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {percent}% ({eta} left) {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar
}

/// Every variant at every budget, `repeats` times: runs in budget-major order, so an
/// interrupted run has every method's small budgets.
fn run_all(
    ctx: &mut RunContext,
    plan: &Plan,
    args: &ConvergeArgs,
    reference: &Image,
    bar: &ProgressBar,
    finished: &AtomicU64,
) -> Result<Vec<Row>> {
    let total = plan.budgets.len() * plan.variants.len() * args.repeats as usize;
    let mut rows = Vec::with_capacity(total);
    for &budget in &plan.budgets {
        for repeat in 0..args.repeats {
            for v in &plan.variants {
                bar.set_message(format!(
                    "run {}/{total}: {} at {} {} (repeat {repeat})",
                    rows.len() + 1,
                    v.label,
                    run::value(budget),
                    plan.unit
                ));
                let seed = args.seed + repeat as u64;
                let exr = image_path(&args.output, &file_stem(&v.label), budget, repeat);
                let (img, m) = run::run(ctx, v, budget, seed, &exr).with_context(|| {
                    format!("{} at {} {}", v.label, run::value(budget), plan.unit)
                })?;
                let e = errors(&img, reference);
                rows.push(Row {
                    method: v.label.clone(),
                    budget: run::value(budget),
                    repeat,
                    seed,
                    wall_s: m.wall_s,
                    cpu_s: m.cpu_s,
                    spp: m.spp,
                    relmse: e.relmse,
                    mse: e.mse,
                    mean: e.mean,
                    nonfinite: m.nonfinite,
                    training_fraction: m.training_fraction,
                    tree_memory_mb: m.tree_memory_mb,
                });
                finished.fetch_add(1, Relaxed);
            }
        }
    }
    Ok(rows)
}

/// How the runs were made, for the outputs.
struct Setup {
    threads: usize,
    crop: Option<crops::Crop>,
}

fn write_outputs(
    args: &ConvergeArgs,
    plan: &Plan,
    rows: &[Row],
    reference: &reference::Reference,
    setup: Setup,
) -> Result<()> {
    let dir = &args.output;
    let write = |name: &str, bytes: &[u8]| -> Result<()> {
        output::write_file_atomic(&dir.join(name), bytes)?;
        Ok(())
    };
    let mut csv = String::from(summary::CSV_HEADER);
    csv.push('\n');
    rows.iter().for_each(|r| {
        csv.push_str(&r.csv());
        csv.push('\n');
    });
    write("results.csv", csv.as_bytes())?;
    let labels: Vec<String> = plan.variants.iter().map(|v| v.label.clone()).collect();
    let budgets: Vec<f64> = plan.budgets.iter().map(|b| run::value(*b)).collect();
    let curves = summary::curves(rows, &labels, &budgets);
    let scene_name = scene_name(&args.scene);
    let (png, svg) = plot::error_vs_time(&scene_name, &curves, reference.floor)?;
    write("error-vs-time.png", &png)?;
    write("error-vs-time.svg", svg.as_bytes())?;
    let crop = write_crops(args, plan, reference, setup.crop)?;
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let md = summary::markdown(&summary::SummaryInput {
        scene: &scene_name,
        command: &command,
        resolution: (reference.image.width, reference.image.height),
        budget_unit: plan.unit,
        reference_source: &reference.source,
        floor: reference.floor,
        given_reference: args.reference.is_some(),
        cpu: &cpu_name(),
        threads: setup.threads,
        rows,
        curves: &curves,
        budgets: &budgets,
        crop: Some(crop),
    });
    write("summary.md", md.as_bytes())
}

/// A given reference's floor from the first two repeats at the largest budget of every
/// in-process method (the median over methods); None with one repeat.
fn floor_from_runs(args: &ConvergeArgs, plan: &Plan, reference: &Image) -> Result<Option<f64>> {
    if args.repeats < 2 {
        return Ok(None);
    }
    let budget = largest(plan);
    let mut floors = Vec::new();
    for v in plan
        .variants
        .iter()
        .filter(|v| !matches!(v.method, Method::Cluster { .. }))
    {
        let img = |r| run::read_image(&image_path(&args.output, &file_stem(&v.label), budget, r));
        floors.push(metrics::cross_floor(&img(0)?, &img(1)?, reference));
    }
    Ok(Some(summary::median(&floors)).filter(|f| f.is_finite()))
}

fn largest(plan: &Plan) -> Budget {
    *plan
        .budgets
        .iter()
        .max_by(|a, b| run::value(**a).total_cmp(&run::value(**b)))
        .expect("at least one budget")
}

/// `crops.png` from the first repeat at the largest budget; the crop used, as X,Y,W,H.
fn write_crops(
    args: &ConvergeArgs,
    plan: &Plan,
    reference: &reference::Reference,
    crop: Option<crops::Crop>,
) -> Result<String> {
    let budget = largest(plan);
    let images = plan
        .variants
        .iter()
        .map(|v| run::read_image(&image_path(&args.output, &file_stem(&v.label), budget, 0)))
        .collect::<Result<Vec<_>>>()?;
    let crop = crop.unwrap_or_else(|| {
        crops::where_methods_differ(&images.iter().collect::<Vec<_>>(), &reference.image)
    });
    let panels: Vec<crops::Panel> = plan
        .variants
        .iter()
        .zip(&images)
        .map(|(v, image)| crops::Panel {
            label: v.label.clone(),
            image,
        })
        .collect();
    let png = crops::figure(&reference.image, &panels, crop)?;
    output::write_file_atomic(&args.output.join("crops.png"), &png)?;
    Ok(format!("{},{},{},{}", crop.x, crop.y, crop.w, crop.h))
}

/// The scene's directory name (scenes are `NAME/scene.xml`), else its file name.
fn scene_name(path: &Path) -> String {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    match path.parent().and_then(|p| p.file_name()) {
        Some(d) if stem == "scene" => d.to_string_lossy().into_owned(),
        _ => stem,
    }
}

/// The CPU's model name (Linux), for the summary: timings mean little without it.
fn cpu_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "an unknown CPU".into())
}
