//! The farm's throughput over the last minutes on the workers page: samples a second in
//! each bucket of the coordinator's series, as bars.

use maud::{html, Markup};

use super::super::throughput::{Bucket, BUCKET, SPAN};

/// The chart's drawing area, in its viewBox units.
const W: f64 = 600.0;
const H: f64 = 90.0;

/// The throughput section: a bar a bucket (oldest left; the last one still filling), with
/// the rate of the last full bucket and the peak in words.
pub(super) fn chart(series: &[Bucket]) -> Markup {
    let secs = BUCKET.as_secs_f64();
    let rates: Vec<f64> = series.iter().map(|b| b.samples as f64 / secs).collect();
    let peak = rates.iter().copied().fold(0.0f64, f64::max);
    let last_full = rates.len().checked_sub(2).map_or(0.0, |i| rates[i]);
    let tiles: u64 = series.iter().map(|b| b.tiles).sum();
    let slot = W / rates.len().max(1) as f64;
    html! {
        section.throughput {
            h2 { "Throughput, last " (SPAN.as_secs() / 60) " minutes" }
            @if peak == 0.0 {
                p.muted { "No tiles accepted in the last " (SPAN.as_secs() / 60) " minutes." }
            } @else {
                svg.chart viewBox={ "0 0 " (W) " " (H) } preserveAspectRatio="none" role="img"
                    aria-label="samples a second accepted, per bucket" {
                    @for (k, r) in rates.iter().enumerate() {
                        @let h = (H - 4.0) * r / peak;
                        rect.bar x=(format!("{:.1}", k as f64 * slot + slot * 0.1))
                            y=(format!("{:.1}", H - h)) width=(format!("{:.1}", slot * 0.8))
                            height=(format!("{:.1}", h)) {}
                    }
                }
                p.muted.legend {
                    "Samples a second accepted, per " (BUCKET.as_secs()) " s, from "
                    (SPAN.as_secs() / 60) " minutes ago (left) to now (right): "
                    (rate(last_full)) " in the last full bucket, peak " (rate(peak)) "; "
                    (tiles) " tiles."
                }
            }
        }
    }
}

/// A rate in words: `12.3 M/s`.
fn rate(r: f64) -> String {
    match r {
        r if r >= 1e9 => format!("{:.1} G/s", r / 1e9),
        r if r >= 1e6 => format!("{:.1} M/s", r / 1e6),
        r if r >= 1e3 => format!("{:.1} k/s", r / 1e3),
        r => format!("{r:.0}/s"),
    }
}
