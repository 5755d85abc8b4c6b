//! A job's iterations on its page: a chart (each iteration's seconds as bars, its image
//! variance as a line on a log scale) and a table, kept current by the live updates.

use maud::{html, Markup};
use pathfarm_proto::v1;

/// The chart's drawing area, in its viewBox units.
const W: f64 = 600.0;
const H: f64 = 120.0;

/// The iterations section's content.
pub(super) fn iterations(j: &v1::JobStatus) -> Markup {
    html! {
        h2 { "Iterations" }
        @if j.iterations.is_empty() {
            p.muted { "The first iteration is under way." }
        } @else {
            (chart(&j.iterations))
            table.iterations {
                thead { tr {
                    th { "#" } th { "kind" } th { "spp" } th { "seconds" } th { "variance" }
                    th { "tree leaves" } th { "rays / sample" }
                } }
                tbody {
                    @for it in &j.iterations {
                        tr {
                            td.num { (it.index) }
                            td { @if it.training { "training" } @else { "final" } }
                            td.num { (it.spp) }
                            td.num { (format!("{:.2}", it.seconds)) }
                            td.num { (format!("{:.3e}", it.variance)) }
                            td.num { (it.tree_leaves) }
                            td.num { (format!("{:.2}", it.rays_per_sample)) }
                        }
                    }
                }
            }
        }
        @if let Some(k) = j.fell_back_after {
            p { "The path fallback gave guiding up after training iteration " (k)
                ": the rest of the budget was path traced." }
        }
    }
}

/// Seconds as bars, variance as a line (log scale), one slot per iteration.
fn chart(its: &[v1::IterationInfo]) -> Markup {
    let slot = W / its.len() as f64;
    let max_s = its
        .iter()
        .map(|i| i.seconds)
        .fold(0.0f64, f64::max)
        .max(1e-9);
    let logs: Vec<f64> = its.iter().map(|i| i.variance.max(1e-30).log10()).collect();
    let (lo, hi) = logs
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let span = (hi - lo).max(1e-9);
    let y_of = |v: f64| 8.0 + (H - 16.0) * (1.0 - (v - lo) / span);
    let points: Vec<String> = (logs.iter().enumerate())
        .map(|(k, &v)| format!("{:.1},{:.1}", (k as f64 + 0.5) * slot, y_of(v)))
        .collect();
    html! {
        svg.chart viewBox={ "0 0 " (W) " " (H) } preserveAspectRatio="none" role="img"
            aria-label="seconds (bars) and image variance (line, log scale) of each iteration" {
            @for (k, it) in its.iter().enumerate() {
                @let h = (H - 4.0) * it.seconds / max_s;
                rect class=(if it.training { "bar" } else { "bar final" })
                    x=(format!("{:.1}", k as f64 * slot + slot * 0.15)) y=(format!("{:.1}", H - h))
                    width=(format!("{:.1}", slot * 0.7)) height=(format!("{:.1}", h)) {}
            }
            polyline.variance points=(points.join(" ")) {}
            @for p in &points {
                @let (x, y) = p.split_once(',').unwrap_or(("0", "0"));
                circle.variance cx=(x) cy=(y) r="3" {}
            }
        }
        p.muted.legend {
            "Bars: seconds (longest " (format!("{max_s:.2}")) " s). Line: image variance, log scale ("
            (format!("{:.1e}", 10f64.powf(lo))) " to " (format!("{:.1e}", 10f64.powf(hi))) ")."
        }
    }
}
