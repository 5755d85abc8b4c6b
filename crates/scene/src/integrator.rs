//! Integrator plugins. Each integrator type is one function from its
//! properties to an [`IntegratorDesc`]; add a new one by adding a match arm
//! in [`integrator`] and its function.

use crate::context::Ctx;
use crate::desc::{
    GuidedBudgetType, GuidedCombination, GuidedDirectionalFilter, GuidedFractionLoss, GuidedNee,
    GuidedParams, GuidedRoulette, GuidedSpatialFilter, IntegratorDesc, PathParams,
};
use crate::error::SceneError;
use crate::limits::{format_number, Limits};
use crate::props::{keywords, Props, Resolved};
use crate::xml::{invalid, Category};

/// Build the integrator `r`.
pub(crate) fn integrator(ctx: &Ctx, r: &Resolved) -> Result<IntegratorDesc, SceneError> {
    let p = ctx.props(&r.node)?;
    let desc = match p.plugin() {
        "path" => IntegratorDesc::Path(path_params(&p)?),
        "guided_path" => IntegratorDesc::GuidedPath(guided_params(&p, &ctx.limits)?),
        "direct" => IntegratorDesc::Path(direct_params(&p)?),
        "moment" => return moment(ctx, &p),
        _ => return Err(p.unsupported("integrator", "path, direct, guided_path, moment")),
    };
    p.finish()?;
    Ok(desc)
}

/// The parameters `plugin` reads the same way as every other integrator here: what
/// `--integrator` keeps of the scene's own (`direct` has no depth of its own).
pub(crate) fn shared_params(plugin: &str) -> &'static [&'static str] {
    match plugin {
        "direct" => &["hide_emitters", "strict_normals"],
        _ => &["max_depth", "rr_depth", "hide_emitters", "strict_normals"],
    }
}

/// Mitsuba's `path`: `max_depth` (-1 = unbounded), `rr_depth` (5, must be
/// > 0), `hide_emitters` (false).
fn path_params(p: &Props) -> Result<PathParams, SceneError> {
    let d = PathParams::default();
    Ok(PathParams {
        max_depth: p.int_in("max_depth", d.max_depth as i64, -1, i32::MAX as i64)? as i32,
        rr_depth: p.int_in("rr_depth", d.rr_depth as i64, 1, u32::MAX as i64)? as u32,
        hide_emitters: p.bool("hide_emitters", d.hide_emitters)?,
        strict_normals: p.bool("strict_normals", d.strict_normals)?,
    })
}

/// Mitsuba's `moment`: the image of its nested integrator, beside that image's second
/// moment (an AOV pathfarm does not write). The image is the nested integrator's, so that is
/// what renders; Mitsuba's test scenes wrap `path` in it.
fn moment(ctx: &Ctx, p: &Props) -> Result<IntegratorDesc, SceneError> {
    let nested = p.children_of(Category::Integrator);
    p.finish()?;
    match nested.as_slice() {
        [one] => integrator(ctx, one),
        _ => Err(invalid(
            p.loc(),
            format!(
                "moment integrator: {} nested integrators; pathfarm renders the image of \
                 exactly one",
                nested.len()
            ),
        )),
    }
}

/// Mitsuba's `direct` (emitted light and direct illumination, light and BSDF samples
/// combined by MIS) is what `path` computes with `max_depth` 2: the same estimator of the
/// same value. Its sample counts (`emitter_samples`, `bsdf_samples`, `shading_samples`)
/// are accepted and render as one light and one BSDF sample a pixel sample: they change the
/// noise per sample, not the image.
fn direct_params(p: &Props) -> Result<PathParams, SceneError> {
    for name in ["emitter_samples", "bsdf_samples", "shading_samples"] {
        p.int_in(name, 1, 0, u32::MAX as i64)?;
    }
    Ok(PathParams {
        max_depth: 2,
        hide_emitters: p.bool("hide_emitters", false)?,
        strict_normals: p.bool("strict_normals", false)?,
        ..PathParams::default()
    })
}

/// `guided_path`'s named parameter sets.
#[derive(Clone, Copy)]
enum Preset {
    /// Müller et al. 2017.
    Ppg2017,
    /// Müller 2019's production improvements.
    Ppg2019,
    /// pathfarm's default.
    Pathfarm,
}

impl Preset {
    fn params(self) -> GuidedParams {
        match self {
            Preset::Ppg2017 => GuidedParams::preset_2017(),
            Preset::Ppg2019 => GuidedParams::preset_2019(),
            Preset::Pathfarm => GuidedParams::preset_pathfarm(),
        }
    }
}

// The words of `guided_path`'s keyword parameters, read in any case.
keywords!(Preset, Insensitive: "2017" => Preset::Ppg2017, "2019" => Preset::Ppg2019, "pathfarm" => Preset::Pathfarm);
keywords!(GuidedRoulette, Insensitive: "throughput" => Self::Throughput, "ppg" => Self::Ppg, "guided" => Self::Guided);
keywords!(GuidedNee, Insensitive: "never" => Self::Never, "always" => Self::Always, "kickstart" => Self::Kickstart);
keywords!(GuidedCombination, Insensitive:
    "discard" => Self::Discard,
    "automatic" => Self::Automatic,
    "inversevar" => Self::InverseVar,
);
keywords!(GuidedSpatialFilter, Insensitive:
    "nearest" => Self::Nearest,
    "stochastic" => Self::Stochastic,
    "box" => Self::Box,
);
keywords!(GuidedDirectionalFilter, Insensitive: "nearest" => Self::Nearest, "box" => Self::Box);
keywords!(GuidedFractionLoss, Insensitive: "none" => Self::None, "kl" => Self::Kl, "var" => Self::Var);
keywords!(GuidedBudgetType, Insensitive: "spp" => Self::Spp, "seconds" => Self::Seconds);

/// A float parameter that must be finite and within `[min, max]` (checked before rounding).
fn float_in(p: &Props, name: &str, default: f64, min: f64, max: f64) -> Result<f64, SceneError> {
    let v = p.in_range(name, p.f64_opt(name)?, min, max, format_number)?;
    // Read as a 32-bit float, as every float parameter is (the images depend on it).
    Ok(v.map_or(default, |v| v as f32 as f64))
}

/// The smallest `d_tree_threshold` (the papers use 0.01): about 2 million nodes per quadtree.
const MIN_D_TREE_THRESHOLD: f64 = 1e-5;

/// `guided_path`: the `path` parameters plus the SD-tree guide's (see [`GuidedParams`]).
fn guided_params(p: &Props, limits: &Limits) -> Result<GuidedParams, SceneError> {
    let d = p.keyword("preset", Preset::Pathfarm)?.params();
    let path = path_params(p)?;
    let (budget_type, budget) = guided_budget(p, limits, d.budget_type)?;
    let (max_memory_mb, max_nodes) = guided_caps(p)?;
    Ok(GuidedParams {
        path,
        budget,
        budget_type,
        spp_per_pass: p.int_in("spp_per_pass", d.spp_per_pass as i64, 1, 1 << 20)? as u32,
        s_tree_threshold: float_in(p, "s_tree_threshold", d.s_tree_threshold, 1e-6, 1e12)?,
        // Below rho a quadrant is not refined: a quadtree has at most about 20 / rho nodes,
        // so rho = 0 would refine every cell to depth 20 (4^20 nodes per leaf).
        d_tree_threshold: float_in(
            p,
            "d_tree_threshold",
            d.d_tree_threshold,
            MIN_D_TREE_THRESHOLD,
            1.0,
        )?,
        carry_over: float_in(p, "carry_over", d.carry_over, 0.0, 1.0)?,
        russian_roulette: p.keyword("russian_roulette", d.russian_roulette)?,
        guided_rr_depth: p.int_in(
            "guided_rr_depth",
            d.guided_rr_depth as i64,
            1,
            u32::MAX as i64,
        )? as u32,
        splitting: p.bool("splitting", d.splitting)?,
        light_splitting: p.bool("light_splitting", d.light_splitting)?,
        path_fallback: p.bool("path_fallback", d.path_fallback)?,
        guide_hemisphere: p.bool("guide_hemisphere", d.guide_hemisphere)?,
        guide_cosine: p.bool("guide_cosine", d.guide_cosine)?,
        nee: p.keyword("nee", d.nee)?,
        sample_combination: p.keyword("sample_combination", d.sample_combination)?,
        spatial_filter: p.keyword("spatial_filter", d.spatial_filter)?,
        directional_filter: p.keyword("directional_filter", d.directional_filter)?,
        bsdf_sampling_fraction: float_in(
            p,
            "bsdf_sampling_fraction",
            d.bsdf_sampling_fraction as f64,
            0.0,
            1.0,
        )? as f32,
        bsdf_sampling_fraction_loss: p
            .keyword("bsdf_sampling_fraction_loss", d.bsdf_sampling_fraction_loss)?,
        max_memory_mb,
        max_nodes,
    })
}

/// `budget_type` and `budget`, the budget within the limits of its unit.
fn guided_budget(
    p: &Props,
    limits: &Limits,
    default_type: GuidedBudgetType,
) -> Result<(GuidedBudgetType, Option<f64>), SceneError> {
    let budget_type = p.keyword("budget_type", default_type)?;
    let (max_budget, unit, limit) = match budget_type {
        GuidedBudgetType::Spp => (limits.max_spp as f64, "spp", "Limits::max_spp"),
        GuidedBudgetType::Seconds => (
            limits.max_time_seconds,
            "seconds",
            "Limits::max_time_seconds",
        ),
    };
    let budget = match p.f64_opt("budget")? {
        None => None,
        Some((b, loc)) if !(b > 0.0) => {
            return Err(invalid(
                &loc,
                format!(
                    "parameter 'budget' of {} must be positive (got {})",
                    p.what(),
                    format_number(b)
                ),
            ))
        }
        Some((b, loc)) if b > max_budget => {
            return Err(invalid(
                &loc,
                format!(
                    "parameter 'budget' of {} is {} {unit}, more than the limit of {} \
                     ({limit})",
                    p.what(),
                    format_number(b),
                    max_budget
                ),
            ))
        }
        Some((b, _)) => Some(b as f32 as f64),
    };
    Ok((budget_type, budget))
}

/// The memory caps of the spatial tree: `max_memory_mb` and `max_nodes`.
fn guided_caps(p: &Props) -> Result<(Option<f64>, Option<u64>), SceneError> {
    let max_memory_mb = match p.float_opt("max_memory_mb")? {
        None => None,
        Some(m) if !(m > 0.0) => {
            return Err(invalid(
                p.loc(),
                format!(
                    "parameter 'max_memory_mb' of {} must be positive (got {m})",
                    p.what()
                ),
            ))
        }
        Some(m) => Some(m as f64),
    };
    let max_nodes = p.int_opt("max_nodes")?;
    let max_nodes = match max_nodes {
        None => None,
        Some((n, loc)) if n < 1 => {
            return Err(invalid(
                &loc,
                format!(
                    "parameter 'max_nodes' of {} must be at least 1 (got {n})",
                    p.what()
                ),
            ))
        }
        Some((n, _)) => Some(n as u64),
    };
    Ok((max_memory_mb, max_nodes))
}
