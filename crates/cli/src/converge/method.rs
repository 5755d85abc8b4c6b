//! The methods `pathfarm converge` compares, and the guide parameters it sweeps.

use anyhow::{bail, Context, Result};
use pathfarm_scene::GuidedParams;

/// How one run renders.
#[derive(Clone, Debug, PartialEq)]
pub enum Method {
    /// The path tracer (`path`, the scene's path parameters).
    Path,
    /// `guided_path` with a preset (and the scene's path parameters).
    Guided(Preset),
    /// `guided_path` (pathfarm preset) on a local farm of this many worker processes
    /// (`pathfarm cluster`), the threads shared among them.
    Cluster { workers: u32 },
}

/// A `guided_path` preset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preset {
    /// pathfarm's defaults (the 2019 improvements and this project's own).
    Pathfarm,
    /// Müller et al. 2017 as published.
    Y2017,
    /// Müller 2019 ("Practical path guiding in production").
    Y2019,
}

impl Preset {
    /// The preset's parameters, keeping `path`'s (depth, roulette start, hidden emitters).
    pub fn params(self, path: pathfarm_scene::PathParams) -> GuidedParams {
        let mut p = match self {
            Preset::Pathfarm => GuidedParams::preset_pathfarm(),
            Preset::Y2017 => GuidedParams::preset_2017(),
            Preset::Y2019 => GuidedParams::preset_2019(),
        };
        p.path = path;
        p
    }
}

/// The guide parameters `--sweep` can vary (all of `guided_path`'s numeric parameters that
/// trade accuracy for time).
pub const SWEEPABLE: &[&str] = &[
    "s_tree_threshold",
    "d_tree_threshold",
    "spp_per_pass",
    "carry_over",
    "guided_rr_depth",
];

/// One method with, optionally, one swept parameter set to one value.
#[derive(Clone, Debug, PartialEq)]
pub struct Variant {
    pub method: Method,
    /// The parameter and its value (guided methods only).
    pub sweep: Option<(String, f64)>,
    /// The name in tables, file names and legends, e.g. `guided-2019` or
    /// `guided[s_tree_threshold=1000]`.
    pub label: String,
}

impl Method {
    /// Parses a `--methods` entry.
    pub fn parse(s: &str) -> Result<Method> {
        Ok(match s {
            "path" => Method::Path,
            "guided" => Method::Guided(Preset::Pathfarm),
            "guided-2017" => Method::Guided(Preset::Y2017),
            "guided-2019" => Method::Guided(Preset::Y2019),
            _ => match s.strip_prefix("cluster:") {
                Some(n) => {
                    let workers: u32 = n
                        .parse()
                        .ok()
                        .filter(|&w| (1..=64).contains(&w))
                        .with_context(|| format!("--methods {s}: workers must be 1 to 64"))?;
                    Method::Cluster { workers }
                }
                None => bail!(
                    "--methods: unknown method {s:?} (known: path, guided, guided-2017, \
                     guided-2019, cluster:N)"
                ),
            },
        })
    }

    /// The name it was given on the command line.
    pub fn name(&self) -> String {
        match self {
            Method::Path => "path".into(),
            Method::Guided(Preset::Pathfarm) => "guided".into(),
            Method::Guided(Preset::Y2017) => "guided-2017".into(),
            Method::Guided(Preset::Y2019) => "guided-2019".into(),
            Method::Cluster { workers } => format!("cluster:{workers}"),
        }
    }
}

/// A `--sweep NAME=V1,V2,...` flag.
#[derive(Clone, Debug, PartialEq)]
pub struct Sweep {
    pub name: String,
    pub values: Vec<f64>,
}

impl Sweep {
    pub fn parse(s: &str) -> Result<Sweep> {
        let (name, values) = s
            .split_once('=')
            .with_context(|| format!("--sweep {s}: expected NAME=V1,V2,..."))?;
        if !SWEEPABLE.contains(&name) {
            bail!(
                "--sweep {s}: {name:?} cannot be swept (one of: {})",
                SWEEPABLE.join(", ")
            );
        }
        let values = values
            .split(',')
            .map(|v| {
                v.trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite() && *x >= 0.0)
                    .with_context(|| format!("--sweep {s}: {v:?} is not a non-negative number"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Sweep {
            name: name.to_string(),
            values,
        })
    }
}

/// Sets the swept parameter `name` of `p` to `v` (names from [`SWEEPABLE`]), checking the
/// value as the scene loader checks it.
pub fn apply_sweep(p: &mut GuidedParams, name: &str, v: f64) -> Result<()> {
    let whole = |what: &str, lo: f64| -> Result<u32> {
        if v.fract() != 0.0 || v < lo || v > u32::MAX as f64 {
            bail!("--sweep {name}={v}: {what}");
        }
        Ok(v as u32)
    };
    match name {
        "s_tree_threshold" if v > 0.0 => p.s_tree_threshold = v,
        "d_tree_threshold" if (1e-5..=1.0).contains(&v) => p.d_tree_threshold = v,
        "spp_per_pass" => p.spp_per_pass = whole("a whole number of at least 1", 1.0)?,
        "carry_over" if v <= 1.0 => p.carry_over = v,
        "guided_rr_depth" => p.guided_rr_depth = whole("a whole number of at least 1", 1.0)?,
        _ => bail!("--sweep {name}={v}: out of the parameter's range"),
    }
    Ok(())
}

/// The runs' variants: every method, then every guided method (not on a cluster) once per
/// swept value.
pub fn variants(methods: &[Method], sweeps: &[Sweep]) -> Vec<Variant> {
    let mut out: Vec<Variant> = methods
        .iter()
        .map(|m| Variant {
            method: m.clone(),
            sweep: None,
            label: m.name(),
        })
        .collect();
    for s in sweeps {
        for m in methods.iter().filter(|m| matches!(m, Method::Guided(_))) {
            for &v in &s.values {
                out.push(Variant {
                    method: m.clone(),
                    sweep: Some((s.name.clone(), v)),
                    label: format!("{}[{}={}]", m.name(), s.name, v),
                });
            }
        }
    }
    out
}

/// `label` made safe as a file name: letters, digits, `-` and `.`; anything else becomes `_`.
pub fn file_stem(label: &str) -> String {
    label
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn methods_parse_and_name_themselves_back() {
        for s in ["path", "guided", "guided-2017", "guided-2019", "cluster:3"] {
            assert_eq!(Method::parse(s).unwrap().name(), s);
        }
        for bad in ["mlt", "cluster:0", "cluster:x", "cluster:65", ""] {
            assert!(Method::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn sweeps_make_one_variant_per_guided_method_and_value() {
        let methods = [Method::Path, Method::Guided(Preset::Y2019)];
        let sweep = Sweep::parse("s_tree_threshold=1000,4000").unwrap();
        let v = variants(&methods, &[sweep]);
        let labels: Vec<&str> = v.iter().map(|v| v.label.as_str()).collect();
        assert_eq!(
            labels,
            [
                "path",
                "guided-2019",
                "guided-2019[s_tree_threshold=1000]",
                "guided-2019[s_tree_threshold=4000]"
            ]
        );
        assert_eq!(file_stem(labels[2]), "guided-2019_s_tree_threshold_1000_");
        assert!(Sweep::parse("max_depth=3").is_err());
        assert!(Sweep::parse("s_tree_threshold=1,x").is_err());
    }

    #[test]
    fn swept_values_are_checked_like_the_scene_parameters() {
        let mut p = Preset::Pathfarm.params(Default::default());
        apply_sweep(&mut p, "s_tree_threshold", 1000.0).unwrap();
        assert_eq!(p.s_tree_threshold, 1000.0);
        apply_sweep(&mut p, "spp_per_pass", 2.0).unwrap();
        assert_eq!(p.spp_per_pass, 2);
        assert!(apply_sweep(&mut p, "spp_per_pass", 1.5).is_err());
        assert!(apply_sweep(&mut p, "d_tree_threshold", 2.0).is_err());
        assert!(apply_sweep(&mut p, "s_tree_threshold", 0.0).is_err());
    }
}
