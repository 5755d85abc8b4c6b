//! `pathfarm guide`: train and save an SD-tree, print its statistics, and
//! draw the pictures people expect from path guiding (a quadtree's learned
//! distribution at a point; BSDF-sampled next to guided scatter directions at
//! the first bounce of a pixel).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use glam::{Vec2, Vec3};
use pathfarm_guide::{viz, SamplingDTree, SdTree};
use pathfarm_render::guided::{self, Budget};
use pathfarm_render::integrator::guided_path::{scatter_at, scatter_panels};
use pathfarm_render::{RenderSettings, Scene};
use pathfarm_scene::{load_scene, GuidedParams, IntegratorDesc, Limits};

use crate::outfile::OutputFile;
use crate::render_cmd::parse_defines;

#[derive(Subcommand)]
pub enum GuideCommand {
    /// Train a guide on a scene (the guided integrator's training iterations)
    /// and save the SD-tree.
    Train(TrainArgs),
    /// Print a saved tree's statistics: nodes, leaves, depth histogram, memory.
    Stats(StatsArgs),
    /// Draw the learned directional distribution (the quadtree) at a point.
    Show(ShowArgs),
    /// Draw the directions sampled at the first bounce of a pixel: BSDF
    /// sampling, guided (mixture) sampling, and the learned quadtree.
    Scatter(ScatterArgs),
}

#[derive(Args)]
pub struct TrainArgs {
    pub scene: PathBuf,
    /// Where to write the tree (pathfarm's versioned, checksummed format).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Total samples per pixel (training and final iteration).
    #[arg(long, default_value_t = 64)]
    pub spp: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Guiding configuration when the scene's integrator is not guided_path.
    #[arg(long, default_value = "pathfarm")]
    pub preset: String,
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    pub defines: Vec<String>,
}

#[derive(Args)]
pub struct StatsArgs {
    pub tree: PathBuf,
}

#[derive(Args)]
pub struct ShowArgs {
    pub tree: PathBuf,
    /// World-space point "x,y,z" whose spatial leaf to draw.
    #[arg(long, allow_hyphen_values = true)]
    pub point: String,
    #[arg(short, long)]
    pub output: PathBuf,
    /// Image width (height is half of it: u across, v down).
    #[arg(long, default_value_t = 512)]
    pub width: usize,
}

#[derive(Args)]
pub struct ScatterArgs {
    pub scene: PathBuf,
    /// Pixel "x,y" whose centre ray's first hit is examined.
    #[arg(long)]
    pub pixel: String,
    #[arg(short, long)]
    pub output: PathBuf,
    /// A tree saved by `guide train`; trained now (64 spp, pathfarm preset) if absent.
    #[arg(long)]
    pub tree: Option<PathBuf>,
    /// Directions drawn per strategy.
    #[arg(long, default_value_t = 200_000)]
    pub samples: u32,
    /// Panel width (height is half of it).
    #[arg(long, default_value_t = 256)]
    pub width: usize,
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    pub defines: Vec<String>,
}

pub fn run(cmd: GuideCommand) -> Result<()> {
    match cmd {
        GuideCommand::Train(a) => train(a),
        GuideCommand::Stats(a) => stats(a),
        GuideCommand::Show(a) => show(a),
        GuideCommand::Scatter(a) => scatter(a),
    }
}

fn parse_floats<const N: usize>(s: &str, what: &str) -> Result<[f32; N]> {
    let v: Vec<f32> = s
        .split(',')
        .map(|x| x.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("{what}: expected {N} comma-separated numbers, got '{s}'"))?;
    if v.len() != N || v.iter().any(|x| !x.is_finite()) {
        bail!("{what}: expected {N} comma-separated finite numbers, got '{s}'");
    }
    Ok(std::array::from_fn(|i| v[i]))
}

fn load(scene: &Path, defines: &[String]) -> Result<(Scene, GuidedParams)> {
    let desc = load_scene(scene, &parse_defines(defines)?)?;
    let params = match &desc.integrator {
        IntegratorDesc::GuidedPath(g) => g.clone(),
        IntegratorDesc::Path(p) => GuidedParams {
            path: *p,
            ..GuidedParams::preset_pathfarm()
        },
    };
    Ok((Scene::build(&desc)?, params))
}

fn train_tree(scene: &Scene, params: &GuidedParams, spp: u32, seed: u64) -> SdTree {
    let settings = RenderSettings::new(Some(spp), None, seed);
    let on_iteration = |it: &guided::GuidedIteration| {
        tracing::info!(
            "iteration {}: spp={} nodes={} leaves={} time={:.3}s",
            it.index,
            it.spp,
            it.nodes,
            it.leaves,
            it.seconds
        )
    };
    guided::render_guided(
        scene,
        params,
        Budget::Spp(spp),
        &settings,
        guided::GuidedOptions {
            on_iteration: &on_iteration,
            ..Default::default()
        },
    )
    .2
}

/// Writes `bytes` to the output opened (and checked) before the work.
fn write_atomic(out: OutputFile, bytes: &[u8]) -> Result<()> {
    out.commit(bytes)
}

fn read_tree(path: &Path) -> Result<SdTree> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    SdTree::decode(&bytes)
        .with_context(|| format!("{}: not a valid pathfarm SD-tree", path.display()))
}

fn train(a: TrainArgs) -> Result<()> {
    let out = OutputFile::create(&a.output)?;
    let (scene, mut params) = load(&a.scene, &a.defines)?;
    let preset = match a.preset.as_str() {
        "2017" => GuidedParams::preset_2017(),
        "2019" => GuidedParams::preset_2019(),
        "pathfarm" => GuidedParams::preset_pathfarm(),
        p => bail!("--preset must be 2017, 2019 or pathfarm, got '{p}'"),
    };
    if !matches!(
        load_scene(&a.scene, &parse_defines(&a.defines)?)?.integrator,
        IntegratorDesc::GuidedPath(_)
    ) {
        params = GuidedParams {
            path: params.path,
            ..preset
        };
    }
    crate::render_cmd::check_budget_flags(Some(a.spp), None, &Limits::default())?;
    guided::check_budget(&params, Budget::Spp(a.spp)).map_err(anyhow::Error::msg)?;
    let tree = train_tree(&scene, &params, a.spp, a.seed);
    write_atomic(out, &tree.encode())?;
    print_stats(&tree);
    Ok(())
}

fn print_stats(tree: &SdTree) {
    let s = tree.stats();
    println!("spatial nodes: {}", s.spatial_nodes);
    println!("spatial leaves: {}", s.leaves);
    println!("leaves per depth: {:?}", s.depth_histogram);
    println!(
        "quadtree nodes (sampling / building): {} / {}",
        s.sampling_dtree_nodes, s.building_dtree_nodes
    );
    println!("deepest quadtree: {}", s.max_dtree_depth);
    println!("memory: {:.3} MiB", s.memory_bytes as f64 / 1048576.0);
    println!("fixed-point overflow events: {}", s.overflow_events);
    println!(
        "leaves per BSDF-sampling fraction (0-0.1, ..., 0.9-1): {:?}",
        s.fraction_histogram
    );
}

fn stats(a: StatsArgs) -> Result<()> {
    print_stats(&read_tree(&a.tree)?);
    Ok(())
}

/// Writes an RGB image of display values in [0, 1] as an 8-bit PNG to the output
/// opened (and checked) before the work.
fn write_png(out: OutputFile, width: usize, height: usize, rgb: &[f32]) -> Result<()> {
    let bytes: Vec<u8> = rgb
        .iter()
        .map(|&c| (c.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect();
    let png = pathfarm_render::output::encode_png_rgb8(width as u32, height as u32, &bytes)
        .with_context(|| format!("writing {}", out.path().display()))?;
    out.commit(&png)
}

fn quadtree_image(tree: &SamplingDTree, width: usize) -> Vec<f32> {
    viz::rasterize_pdf(tree, width, width / 2, true)
}

/// A picture of `width` x `height` pixels (from the flag `flag`) within the limits.
fn check_picture(width: usize, height: usize, flag: &str) -> Result<()> {
    let max = Limits::default().max_picture_pixels;
    let pixels = width as u64 * height as u64;
    if pixels > max {
        bail!(
            "{flag}: the picture would be {width}x{height} = {pixels} pixels, more than the \
             limit of {max} (Limits::max_picture_pixels)"
        );
    }
    Ok(())
}

fn show(a: ShowArgs) -> Result<()> {
    let w = a.width.max(16);
    check_picture(w, w / 2, &format!("--width {}", a.width))?;
    let out = OutputFile::create(&a.output)?;
    let tree = read_tree(&a.tree)?;
    let p = Vec3::from(parse_floats::<3>(&a.point, "--point")?);
    let leaf = tree.leaf(tree.leaf_index(p));
    write_png(out, w, w / 2, &quadtree_image(&leaf.sampling, w))?;
    println!("quadtree at {p}: {} nodes; u (across) = (cos theta + 1) / 2 of the world z axis, v (down) = phi / 2pi", leaf.sampling.tree().node_count());
    Ok(())
}

fn scatter(a: ScatterArgs) -> Result<()> {
    let w = a.width.max(16);
    check_picture(3 * w + 8, w / 2, &format!("--width {}", a.width))?;
    let max_samples = Limits::default().max_scatter_samples;
    if a.samples as u64 > max_samples {
        bail!(
            "--samples {}: more than the limit of {max_samples} (Limits::max_scatter_samples)",
            a.samples
        );
    }
    let out = OutputFile::create(&a.output)?;
    let (scene, params) = load(&a.scene, &a.defines)?;
    let [px, py] = parse_floats::<2>(&a.pixel, "--pixel")?;
    if px < 0.0 || py < 0.0 || px >= scene.width as f32 || py >= scene.height as f32 {
        bail!(
            "--pixel {},{} is outside the {}x{} image",
            px,
            py,
            scene.width,
            scene.height
        );
    }
    let tree = match &a.tree {
        Some(t) => read_tree(t)?,
        None => train_tree(&scene, &params, 64, 0),
    };
    let Some(s) = scatter_at(&scene, &params, &tree, Vec2::new(px, py), a.samples) else {
        bail!("the ray through pixel {},{} hits nothing", px, py);
    };
    let h = w / 2;
    let (total_w, img) = scatter_panels(&s, &tree, w, 4);
    write_png(out, total_w, h, &img)?;
    println!(
        "first hit at {} (shape {}), bsdf-sampling fraction {:.3}; panels: BSDF sampling ({} dirs) | guided mixture ({} dirs) | learned quadtree; u across = (cos theta + 1) / 2 of world z, v down = phi / 2pi",
        s.point,
        s.shape,
        s.bsdf_fraction,
        s.from_bsdf.len(),
        s.from_mixture.len()
    );
    Ok(())
}
