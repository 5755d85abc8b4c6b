//! The error-against-time chart (log-log), drawn with plotters to PNG and SVG.

use std::sync::Once;

use anyhow::{anyhow, Result};
use plotters::coord::Shift;
use plotters::prelude::*;

/// One budget of one method: medians over the repeats, and the spread.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CurvePoint {
    /// Median wall seconds.
    pub wall_s: f64,
    /// Median relMSE, and the smallest and largest over the repeats.
    pub relmse: f64,
    pub lo: f64,
    pub hi: f64,
}

/// One method's line.
#[derive(Clone, Debug, PartialEq)]
pub struct Curve {
    pub label: String,
    pub points: Vec<CurvePoint>,
}

/// The text of both outputs is drawn with the embedded DejaVu Sans (no system fonts).
pub(super) fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            dejavu::sans::regular(),
        );
    });
}

const SIZE: (u32, u32) = (960, 640);

/// Line colours, distinct on white and in print (path first: red).
const COLOURS: [RGBColor; 8] = [
    RGBColor(214, 39, 40),
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(23, 190, 207),
    RGBColor(60, 60, 60),
];

/// The chart as PNG bytes and as SVG text.
pub fn error_vs_time(
    title: &str,
    curves: &[Curve],
    floor: Option<f64>,
) -> Result<(Vec<u8>, String)> {
    register_font();
    let mut rgb = vec![255u8; (SIZE.0 * SIZE.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area();
        draw(&root, title, curves, floor)?;
        root.present()
            .map_err(|e| anyhow!("drawing the chart: {e}"))?;
    }
    let png = pathfarm_render::output::encode_png_rgb8(SIZE.0, SIZE.1, &rgb)?;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        draw(&root, title, curves, floor)?;
        root.present()
            .map_err(|e| anyhow!("drawing the chart: {e}"))?;
    }
    Ok((png, svg))
}

/// The axes' ranges: every point and the floor, with a margin, in decades' fractions.
fn ranges(curves: &[Curve], floor: Option<f64>) -> ((f64, f64), (f64, f64)) {
    let pts = curves.iter().flat_map(|c| &c.points);
    let xs: Vec<f64> = pts.clone().map(|p| p.wall_s).filter(|x| *x > 0.0).collect();
    let ys: Vec<f64> = pts
        .flat_map(|p| [p.lo, p.hi, p.relmse])
        .chain(floor)
        .filter(|y| *y > 0.0 && y.is_finite())
        .collect();
    let span = |v: &[f64], pad: f64| {
        let lo = v.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = v.iter().cloned().fold(0.0, f64::max);
        if lo.is_finite() && hi > 0.0 {
            (lo / pad, hi * pad)
        } else {
            (0.1, 10.0)
        }
    };
    (span(&xs, 1.25), span(&ys, 1.5))
}

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    curves: &[Curve],
    floor: Option<f64>,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| anyhow!("drawing the chart: {e}");
    root.fill(&WHITE).map_err(e)?;
    let ((x0, x1), (y0, y1)) = ranges(curves, floor);
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(80)
        .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc("wall seconds")
        .y_desc("relMSE")
        .y_label_formatter(&|y| format!("{y:.1e}"))
        .x_label_formatter(&|x| format!("{x:.3}"))
        .label_style(("sans-serif", 14))
        .draw()
        .map_err(e)?;
    for (i, c) in curves.iter().enumerate() {
        let color = COLOURS[i % COLOURS.len()].to_rgba();
        let line = c.points.iter().map(|p| (p.wall_s, p.relmse));
        chart
            .draw_series(LineSeries::new(line, color.stroke_width(2)))
            .map_err(e)?
            .label(c.label.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
        let dots = c
            .points
            .iter()
            .map(|p| Circle::new((p.wall_s, p.relmse), 4, color.filled()));
        chart.draw_series(dots).map_err(e)?;
        let bars = c.points.iter().map(|p| {
            PathElement::new(
                vec![(p.wall_s, p.lo), (p.wall_s, p.hi)],
                color.stroke_width(1),
            )
        });
        chart.draw_series(bars).map_err(e)?;
    }
    if let Some(f) = floor.filter(|f| *f > 0.0) {
        let style = BLACK.mix(0.6).stroke_width(1);
        chart
            .draw_series(DashedLineSeries::new([(x0, f), (x1, f)], 8, 6, style))
            .map_err(e)?
            .label("reference's own error")
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerLeft)
        .label_font(("sans-serif", 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(e)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_chart_is_a_png_and_an_svg_with_every_label() {
        let p = |w: f64, r: f64| CurvePoint {
            wall_s: w,
            relmse: r,
            lo: r * 0.9,
            hi: r * 1.1,
        };
        let curves = vec![
            Curve {
                label: "path".into(),
                points: vec![p(1.0, 0.4), p(2.0, 0.2), p(4.0, 0.1)],
            },
            Curve {
                label: "guided".into(),
                points: vec![p(1.1, 0.1), p(2.1, 0.05), p(4.1, 0.025)],
            },
        ];
        let (png, svg) = error_vs_time("test scene", &curves, Some(0.001)).unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), SIZE);
        // Something besides the white background was drawn (lines, text).
        let dark = img
            .pixels()
            .filter(|p| p.0.iter().all(|&c| c < 128))
            .count();
        assert!(dark > 1000, "{dark} dark pixels");
        for label in ["path", "guided", "test scene", "relMSE", "wall seconds"] {
            assert!(svg.contains(label), "{label} missing from the SVG");
        }
    }
}
