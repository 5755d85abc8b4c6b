//! `results.csv` and `summary.md`: every run, and each method's time to reach a set of
//! error levels.

use std::fmt::Write as _;

use super::plot::{Curve, CurvePoint};

/// One row of `results.csv`.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub method: String,
    pub budget: f64,
    pub repeat: u32,
    pub seed: u64,
    pub wall_s: f64,
    pub cpu_s: f64,
    pub spp: u32,
    pub relmse: f64,
    pub mse: f64,
    pub mean: f64,
    pub nonfinite: u64,
    pub training_fraction: f64,
    pub tree_memory_mb: f64,
}

pub const CSV_HEADER: &str = "method,budget,repeat,seed,wall_s,cpu_s,spp,relmse,mse,mean,\
                              nonfinite,training_fraction,tree_memory_mb";

/// `x` for the CSV: empty when not measured (NaN).
fn num(x: f64) -> String {
    if x.is_nan() {
        String::new()
    } else {
        format!("{x}")
    }
}

impl Row {
    pub fn csv(&self) -> String {
        format!(
            "{},{},{},{},{:.4},{:.4},{},{:.6e},{:.6e},{:.6e},{},{},{}",
            self.method,
            self.budget,
            self.repeat,
            self.seed,
            self.wall_s,
            self.cpu_s,
            self.spp,
            self.relmse,
            self.mse,
            self.mean,
            self.nonfinite,
            num(self.training_fraction),
            num(self.tree_memory_mb)
        )
    }
}

/// The median of `v` (NaN if empty).
pub fn median(v: &[f64]) -> f64 {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| !x.is_nan()).collect();
    if s.is_empty() {
        return f64::NAN;
    }
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

/// Each method's curve: per budget (in `budgets` order), medians over the repeats.
pub fn curves(rows: &[Row], labels: &[String], budgets: &[f64]) -> Vec<Curve> {
    labels
        .iter()
        .map(|label| {
            let points = budgets
                .iter()
                .filter_map(|&b| {
                    let runs: Vec<&Row> = rows
                        .iter()
                        .filter(|r| &r.method == label && r.budget == b)
                        .collect();
                    if runs.is_empty() {
                        return None;
                    }
                    let errs: Vec<f64> = runs.iter().map(|r| r.relmse).collect();
                    let walls: Vec<f64> = runs.iter().map(|r| r.wall_s).collect();
                    Some(CurvePoint {
                        wall_s: median(&walls),
                        relmse: median(&errs),
                        lo: errs.iter().cloned().fold(f64::INFINITY, f64::min),
                        hi: errs.iter().cloned().fold(0.0, f64::max),
                    })
                })
                .collect();
            Curve {
                label: label.clone(),
                points,
            }
        })
        .collect()
}

/// The time a curve needs to reach relMSE `level`: interpolated linearly in log-log between
/// the measured points that bracket it, else extrapolated from the nearest end as relMSE
/// proportional to 1 / time (an unbiased estimator's rate) and flagged `true`.
pub fn time_to_reach(c: &Curve, level: f64) -> Option<(f64, bool)> {
    let mut pts: Vec<(f64, f64)> = c
        .points
        .iter()
        .filter(|p| p.wall_s > 0.0 && p.relmse > 0.0)
        .map(|p| (p.wall_s.ln(), p.relmse.ln()))
        .collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let l = level.ln();
    for w in pts.windows(2) {
        let ((x0, y0), (x1, y1)) = (w[0], w[1]);
        if (y0 - l) * (y1 - l) <= 0.0 && y0 != y1 {
            return Some(((x0 + (l - y0) * (x1 - x0) / (y1 - y0)).exp(), false));
        }
    }
    // Beyond the measured range: from the end point nearest in error.
    let (x, y) = *pts
        .iter()
        .min_by(|a, b| (a.1 - l).abs().total_cmp(&(b.1 - l).abs()))?;
    Some(((x + (y - l)).exp(), (y - l).abs() > 1e-12))
}

/// The error levels of the time-to-error table: the `path` curve's medians if there is a
/// path curve, else the first curve's.
pub fn levels(curves: &[Curve]) -> Vec<f64> {
    let c = curves.iter().find(|c| c.label == "path").or(curves.first());
    c.map(|c| c.points.iter().map(|p| p.relmse).collect())
        .unwrap_or_default()
}

/// The text of `summary.md`.
pub struct SummaryInput<'a> {
    pub scene: &'a str,
    pub command: &'a str,
    pub resolution: (u32, u32),
    pub budget_unit: &'a str,
    pub reference_source: &'a str,
    pub floor: Option<f64>,
    /// The reference was given (`--reference`), not rendered.
    pub given_reference: bool,
    pub cpu: &'a str,
    pub threads: usize,
    pub rows: &'a [Row],
    pub curves: &'a [Curve],
    pub budgets: &'a [f64],
    pub crop: Option<String>,
}

pub fn markdown(s: &SummaryInput) -> String {
    let mut o = String::new();
    let _ = writeln!(o, "# Error against time: {}\n", s.scene);
    let _ = writeln!(o, "Made by `{}`", s.command);
    let _ = writeln!(
        o,
        "on {} with {} threads, {}x{} pixels.\n",
        s.cpu, s.threads, s.resolution.0, s.resolution.1
    );
    let _ = writeln!(o, "- Reference: {}.", s.reference_source);
    match (s.floor, s.given_reference) {
        (Some(f), false) => {
            let _ = writeln!(
                o,
                "- The reference's own relMSE, estimated from its two independent halves \
                 (a quarter of their relMSE against each other): {f:.3e}. Errors near it \
                 measure the reference, not the method."
            );
        }
        (Some(f), true) => {
            let _ = writeln!(
                o,
                "- The floor under every curve, estimated as `bench/floor.py` does from two \
                 independent runs a, b of each method at the largest budget, mean((a - ref)(b - \
                 ref) / (ref^2 + 0.01)), median over the methods: {f:.3e}. It is the \
                 reference's own error plus any difference between what pathfarm and the \
                 reference's renderer converge to."
            );
        }
        (None, _) => {
            let _ = writeln!(o, "- The reference's own error is not known (one repeat).");
        }
    }
    let _ = writeln!(
        o,
        "- relMSE: mean over pixels and channels of (value - reference)^2 / (reference^2 + 0.01).\n\
         - Medians over the repeats (seeds); the range is the smallest to largest.\n"
    );
    equal_budget_table(&mut o, s);
    time_to_error_table(&mut o, s.curves);
    if let Some(c) = &s.crop {
        let _ = writeln!(
            o,
            "\n`crops.png`: the crop {c} of each method's first repeat at the largest budget."
        );
    }
    o
}

fn equal_budget_table(o: &mut String, s: &SummaryInput) {
    let _ = writeln!(
        o,
        "## At equal budget\n\n| method | budget ({}) | wall s | spp | relMSE | range | vs path | nonfinite | training | tree MB |\n|---|---|---|---|---|---|---|---|---|---|",
        s.budget_unit
    );
    for c in s.curves {
        for &b in s.budgets {
            let runs: Vec<&Row> = s
                .rows
                .iter()
                .filter(|r| r.method == c.label && r.budget == b)
                .collect();
            if runs.is_empty() {
                continue;
            }
            let med =
                |f: &dyn Fn(&Row) -> f64| median(&runs.iter().map(|r| f(r)).collect::<Vec<_>>());
            let err = med(&|r| r.relmse);
            let path = s
                .rows
                .iter()
                .filter(|r| r.method == "path" && r.budget == b)
                .map(|r| r.relmse)
                .collect::<Vec<_>>();
            let vs = if path.is_empty() {
                "-".into()
            } else {
                format!("{:.2}x", median(&path) / err)
            };
            let (lo, hi) = runs.iter().fold((f64::INFINITY, 0.0f64), |(l, h), r| {
                (l.min(r.relmse), h.max(r.relmse))
            });
            let nonfinite: u64 = runs.iter().map(|r| r.nonfinite).sum();
            let opt = |x: f64, d: usize| {
                if x.is_nan() {
                    "-".to_string()
                } else {
                    format!("{x:.d$}")
                }
            };
            let _ = writeln!(
                o,
                "| {} | {b} | {:.2} | {:.0} | {err:.3e} | {lo:.2e} - {hi:.2e} | {vs} | {nonfinite} | {} | {} |",
                c.label,
                med(&|r| r.wall_s),
                med(&|r| r.spp as f64),
                opt(med(&|r| r.training_fraction), 2),
                opt(med(&|r| r.tree_memory_mb), 1),
            );
        }
    }
    let _ = writeln!(o, "\n`vs path`: path's median relMSE over the method's at the same budget (equal-time efficiency with `--budgets`).\n");
}

fn time_to_error_table(o: &mut String, curves: &[Curve]) {
    let levels = levels(curves);
    if levels.is_empty() {
        return;
    }
    let _ = writeln!(o, "## Time to reach an error level\n");
    let head: Vec<String> = levels.iter().map(|l| format!("relMSE {l:.2e}")).collect();
    let _ = writeln!(o, "| method | {} |", head.join(" | "));
    let _ = writeln!(o, "|---|{}", "---|".repeat(levels.len()));
    let path = curves.iter().find(|c| c.label == "path");
    for c in curves {
        let cells: Vec<String> = levels
            .iter()
            .map(|&l| match time_to_reach(c, l) {
                None => "-".into(),
                Some((t, extrapolated)) => {
                    let mark = if extrapolated { "~" } else { "" };
                    let speedup = path
                        .and_then(|p| time_to_reach(p, l))
                        .map(|(tp, _)| format!(" ({:.2}x)", tp / t))
                        .unwrap_or_default();
                    format!("{mark}{t:.2} s{speedup}")
                }
            })
            .collect();
        let _ = writeln!(o, "| {} | {} |", c.label, cells.join(" | "));
    }
    let _ = writeln!(
        o,
        "\nSeconds to reach each level (path's medians, or the first method's without path), \
         interpolated in log-log between measured points; `~` marks a time extrapolated as \
         relMSE proportional to 1/time beyond the measured range. In brackets: the speed-up \
         over path at that level."
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    fn curve(label: &str, pts: &[(f64, f64)]) -> Curve {
        Curve {
            label: label.into(),
            points: pts
                .iter()
                .map(|&(w, r)| CurvePoint {
                    wall_s: w,
                    relmse: r,
                    lo: r,
                    hi: r,
                })
                .collect(),
        }
    }

    #[test]
    fn time_to_reach_interpolates_in_log_log_and_extrapolates_as_one_over_time() {
        let c = curve("guided", &[(1.0, 0.4), (4.0, 0.1)]);
        let (t, ex) = time_to_reach(&c, 0.2).unwrap();
        assert!((t - 2.0).abs() < 1e-9 && !ex, "{t} {ex}");
        let (t, ex) = time_to_reach(&c, 0.05).unwrap();
        assert!((t - 8.0).abs() < 1e-9 && ex, "{t} {ex}");
        let (t, ex) = time_to_reach(&c, 0.8).unwrap();
        assert!((t - 0.5).abs() < 1e-9 && ex, "{t} {ex}");
        assert_eq!(time_to_reach(&curve("x", &[]), 0.1), None);
    }

    #[test]
    fn medians_and_curves_summarise_the_repeats() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(&[]).is_nan());
        let row = |m: &str, b: f64, w: f64, e: f64| Row {
            method: m.into(),
            budget: b,
            repeat: 0,
            seed: 0,
            wall_s: w,
            cpu_s: w,
            spp: 1,
            relmse: e,
            mse: e,
            mean: 1.0,
            nonfinite: 0,
            training_fraction: f64::NAN,
            tree_memory_mb: f64::NAN,
        };
        let rows = [
            row("path", 1.0, 1.0, 0.3),
            row("path", 1.0, 1.2, 0.5),
            row("path", 1.0, 1.1, 0.4),
        ];
        let c = curves(&rows, &["path".into()], &[1.0, 2.0]);
        assert_eq!(c[0].points.len(), 1, "no runs at budget 2");
        let p = c[0].points[0];
        assert_eq!((p.wall_s, p.relmse, p.lo, p.hi), (1.1, 0.4, 0.3, 0.5));
        assert!(rows[0].csv().ends_with(",0,,"), "{}", rows[0].csv());
        assert_eq!(
            CSV_HEADER.split(',').count(),
            rows[0].csv().split(',').count()
        );
    }
}
