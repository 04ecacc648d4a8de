//! Line and point charts (sweep results, quality per frame), drawn with plotters into PNG and SVG (same drawing code for both).
//! Text uses the bundled DejaVu Sans through ab_glyph, so nothing depends on system fonts.

use std::path::{Path, PathBuf};

use anyhow::{Result, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;

const WIDTH: u32 = 880;
const HEIGHT: u32 = 560;

/// One line (or point set) of a chart.
#[derive(Clone, Debug, Default)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// Vertical ranges drawn as whiskers: (x, low, high).
    pub whiskers: Vec<(f64, f64, f64)>,
}

/// What a chart shows.
#[derive(Clone, Debug, Default)]
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    /// Plot x on a log10 axis (points with x ≤ 0 are left out).
    pub log_x: bool,
    /// Categorical x: point i of a series sits at x = i (plus its series' offset), labelled so.
    pub x_categories: Option<Vec<String>>,
    /// Join a series' points (sorted by x) with a line.
    pub connect: bool,
    /// A labelled horizontal line, e.g. a collapse floor.
    pub reference: Option<(f64, String)>,
    pub series: Vec<Series>,
}

fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../../assets/fonts/DejaVuSans.ttf"),
        )
        .map_err(|_| ())
        .expect("the bundled font parses");
    });
}

/// Writes `stem.png` and `stem.svg`; returns both paths. A chart without a single finite point
/// is still drawn (empty axes, "no data"), so a report never links a missing file.
pub fn write_chart(chart: &Chart, stem: &Path) -> Result<[PathBuf; 2]> {
    register_font();
    if let Some(dir) = stem.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    draw(
        BitMapBackend::new(&png, (WIDTH, HEIGHT)).into_drawing_area(),
        chart,
    )
    .map_err(|e| anyhow!("drawing {}: {e}", png.display()))?;
    draw(
        SVGBackend::new(&svg, (WIDTH, HEIGHT)).into_drawing_area(),
        chart,
    )
    .map_err(|e| anyhow!("drawing {}: {e}", svg.display()))?;
    Ok([png, svg])
}

/// The plotted coordinates of a series: log x applied, non-finite points dropped, categorical
/// points offset so series sit side by side.
fn plotted(
    chart: &Chart,
    index: usize,
    series: &Series,
) -> (Vec<(f64, f64)>, Vec<(f64, f64, f64)>) {
    let offset = if chart.x_categories.is_some() {
        let n = chart.series.len().max(1) as f64;
        (index as f64 - (n - 1.0) / 2.0) * (0.5 / n)
    } else {
        0.0
    };
    let x_of = |x: f64| -> Option<f64> {
        if chart.log_x {
            (x > 0.0).then(|| x.log10())
        } else {
            Some(x)
        }
        .map(|x| x + offset)
    };
    let mut points: Vec<(f64, f64)> = series
        .points
        .iter()
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .filter_map(|&(x, y)| Some((x_of(x)?, y)))
        .collect();
    points.sort_by(|a, b| a.0.total_cmp(&b.0));
    let whiskers = series
        .whiskers
        .iter()
        .filter(|(x, lo, hi)| x.is_finite() && lo.is_finite() && hi.is_finite())
        .filter_map(|&(x, lo, hi)| Some((x_of(x)?, lo, hi)))
        .collect();
    (points, whiskers)
}

/// Range of values padded by 8 % (or ±1 around a single value).
fn padded(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if !lo.is_finite() {
        return None;
    }
    let pad = if hi > lo {
        0.08 * (hi - lo)
    } else {
        lo.abs().max(1.0) * 0.05
    };
    Some((lo - pad, hi + pad))
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    chart: &Chart,
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    let data: Vec<_> = chart
        .series
        .iter()
        .enumerate()
        .map(|(i, s)| plotted(chart, i, s))
        .collect();
    let xs = data
        .iter()
        .flat_map(|(p, w)| p.iter().map(|q| q.0).chain(w.iter().map(|q| q.0)));
    let ys = data
        .iter()
        .flat_map(|(p, w)| {
            p.iter()
                .map(|q| q.1)
                .chain(w.iter().flat_map(|q| [q.1, q.2]))
        })
        .chain(chart.reference.iter().map(|r| r.0));
    let (x0, x1) = match &chart.x_categories {
        Some(c) => (-0.5, c.len().max(1) as f64 - 0.5),
        None => padded(xs).unwrap_or((0.0, 1.0)),
    };
    let (y0, y1) = padded(ys).unwrap_or((0.0, 1.0));
    let legend_box = legend_size(chart);
    let drawn = drawn_points(chart, &data, (x0, x1));
    let (legend_position, y0) = legend_layout(&drawn, (x0, x1), (y0, y1), legend_box);
    let mut ctx = ChartBuilder::on(&root)
        .caption(&chart.title, ("sans-serif", 22))
        .margin(14)
        .x_label_area_size(48)
        .y_label_area_size(64)
        .build_cartesian_2d(x0..x1, y0..y1)?;
    let log_x = chart.log_x;
    let categories = chart.x_categories.clone();
    let x_format = move |v: &f64| -> String {
        if let Some(c) = &categories {
            let i = v.round();
            return if (v - i).abs() < 1e-6 && i >= 0.0 && (i as usize) < c.len() {
                c[i as usize].clone()
            } else {
                String::new()
            };
        }
        let v = if log_x { 10f64.powf(*v) } else { *v };
        format_number(v)
    };
    let mut mesh = ctx.configure_mesh();
    mesh.x_desc(&chart.x_label)
        .y_desc(&chart.y_label)
        .x_label_formatter(&x_format)
        .y_label_formatter(&|v| format_number(*v))
        .label_style(("sans-serif", 14));
    if let Some(c) = &chart.x_categories {
        mesh.x_labels(c.len() * 2 + 1).disable_x_mesh();
    }
    mesh.draw()?;
    if !data.iter().any(|(p, _)| !p.is_empty()) {
        root.draw(&Text::new(
            "no data",
            (WIDTH as i32 / 2 - 30, HEIGHT as i32 / 2),
            ("sans-serif", 20),
        ))?;
    }
    if let Some((y, label)) = &chart.reference {
        let style = RGBColor(120, 120, 120).stroke_width(2);
        ctx.draw_series(LineSeries::new([(x0, *y), (x1, *y)], style))?
            .label(label.clone())
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], style));
    }
    for (i, (series, (points, whiskers))) in chart.series.iter().zip(&data).enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let line = color.stroke_width(2);
        if chart.connect && points.len() > 1 {
            ctx.draw_series(LineSeries::new(points.clone(), line))?;
        }
        ctx.draw_series(
            whiskers
                .iter()
                .map(|&(x, lo, hi)| PathElement::new([(x, lo), (x, hi)], line)),
        )?;
        ctx.draw_series(
            points
                .iter()
                .map(|&(x, y)| Circle::new((x, y), 5, color.filled())),
        )?
        .label(series.name.clone())
        .legend(move |(x, y)| Circle::new((x + 10, y), 5, color.filled()));
    }
    ctx.configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .position(legend_position)
        .draw()?;
    root.present()
}

/// Approximate pixel size of the plotting area (the chart minus margins, caption and label areas).
const PLOT_AREA: (f64, f64) = (
    WIDTH as f64 - 2.0 * 14.0 - 64.0,
    HEIGHT as f64 - 2.0 * 14.0 - 48.0 - 36.0,
);
const LEGEND_FONT: f64 = 14.0;

/// The legend box as fractions of the plotting area (plotters: text, a 30 px symbol column,
/// 10 px margins, 5 px from the corner), with 8 px to spare for the point markers' radius.
fn legend_size(chart: &Chart) -> (f64, f64) {
    let labels: Vec<&str> = chart
        .reference
        .iter()
        .map(|r| r.1.as_str())
        .chain(chart.series.iter().map(|s| s.name.as_str()))
        .collect();
    // DejaVu Sans averages ~0.6 em per character; plotters' line height is 1.25 em.
    let text_width =
        labels.iter().map(|l| l.chars().count()).max().unwrap_or(0) as f64 * 0.6 * LEGEND_FONT;
    let text_height = labels.len() as f64 * 1.25 * LEGEND_FONT;
    (
        (text_width + 30.0 + 20.0 + 5.0 + 8.0) / PLOT_AREA.0,
        (text_height + 20.0 + 5.0 + 8.0) / PLOT_AREA.1,
    )
}

/// Everything drawn inside the plot, as points in data coordinates: markers, whiskers and lines
/// (sampled densely, so a line crossing a corner counts).
fn drawn_points(
    chart: &Chart,
    data: &[(Vec<(f64, f64)>, Vec<(f64, f64, f64)>)],
    (x0, x1): (f64, f64),
) -> Vec<(f64, f64)> {
    const SAMPLES: usize = 32;
    let segment = |a: (f64, f64), b: (f64, f64)| {
        (0..=SAMPLES).map(move |i| {
            let t = i as f64 / SAMPLES as f64;
            (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1))
        })
    };
    let mut drawn = Vec::new();
    if let Some((y, _)) = &chart.reference {
        drawn.extend(segment((x0, *y), (x1, *y)));
    }
    for (points, whiskers) in data {
        drawn.extend(points.iter().copied());
        if chart.connect {
            for pair in points.windows(2) {
                drawn.extend(segment(pair[0], pair[1]));
            }
        }
        for &(x, lo, hi) in whiskers {
            drawn.extend(segment((x, lo), (x, hi)));
        }
    }
    drawn
}

/// Where the legend goes: the first plot corner (lower right, lower left, upper right, upper
/// left) whose legend box covers nothing drawn; when every corner is taken, the y axis is
/// extended downwards by the box's height so the lower right one is empty. Returns the position
/// and the (possibly lowered) bottom of the y axis.
fn legend_layout(
    drawn: &[(f64, f64)],
    (x0, x1): (f64, f64),
    (y0, y1): (f64, f64),
    (box_w, box_h): (f64, f64),
) -> (SeriesLabelPosition, f64) {
    let normalised: Vec<(f64, f64)> = drawn
        .iter()
        .map(|&(x, y)| ((x - x0) / (x1 - x0), (y - y0) / (y1 - y0)))
        .collect();
    let corners = [
        (
            SeriesLabelPosition::LowerRight,
            (1.0 - box_w, 1.0),
            (0.0, box_h),
        ),
        (SeriesLabelPosition::LowerLeft, (0.0, box_w), (0.0, box_h)),
        (
            SeriesLabelPosition::UpperRight,
            (1.0 - box_w, 1.0),
            (1.0 - box_h, 1.0),
        ),
        (
            SeriesLabelPosition::UpperLeft,
            (0.0, box_w),
            (1.0 - box_h, 1.0),
        ),
    ];
    for (position, (left, right), (bottom, top)) in corners {
        let covers = |&(x, y): &(f64, f64)| x >= left && x <= right && y >= bottom && y <= top;
        if !normalised.iter().any(covers) {
            return (position, y0);
        }
    }
    let box_h = box_h.min(0.5);
    (
        SeriesLabelPosition::LowerRight,
        y0 - box_h * (y1 - y0) / (1.0 - box_h),
    )
}

/// Short tick labels: 3 significant digits, scientific below 1e-2.
pub fn format_number(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if !(1e-2..1e5).contains(&a) {
        return format!("{v:.0e}");
    }
    let digits = (2 - a.log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn covered(
        drawn: &[(f64, f64)],
        position: &SeriesLabelPosition,
        (x0, x1): (f64, f64),
        (y0, y1): (f64, f64),
        (w, h): (f64, f64),
    ) -> usize {
        let (left, right) = match position {
            SeriesLabelPosition::LowerLeft | SeriesLabelPosition::UpperLeft => (0.0, w),
            _ => (1.0 - w, 1.0),
        };
        let (bottom, top) = match position {
            SeriesLabelPosition::LowerLeft | SeriesLabelPosition::LowerRight => (0.0, h),
            _ => (1.0 - h, 1.0),
        };
        drawn
            .iter()
            .map(|&(x, y)| ((x - x0) / (x1 - x0), (y - y0) / (y1 - y0)))
            .filter(|&(x, y)| x >= left && x <= right && y >= bottom && y <= top)
            .count()
    }

    #[test]
    fn the_legend_avoids_the_data_and_makes_room_when_every_corner_is_taken() {
        // A per-frame chart like the default run's: a high flat line, a falling low one whose
        // last points sit in the lower right corner.
        let high: Vec<(f64, f64)> = (0..40).map(|f| (f as f64, 34.0)).collect();
        let low: Vec<(f64, f64)> = (0..40)
            .map(|f| (f as f64, 25.0 - 0.12 * f as f64))
            .collect();
        let chart = Chart {
            connect: true,
            series: vec![
                Series {
                    name: "static pixels".into(),
                    points: high,
                    ..Default::default()
                },
                Series {
                    name: "dynamic pixels".into(),
                    points: low,
                    ..Default::default()
                },
            ],
            ..Default::default()
        };
        let data: Vec<_> = chart
            .series
            .iter()
            .enumerate()
            .map(|(i, s)| plotted(&chart, i, s))
            .collect();
        let xr = (-2.0, 41.0);
        let yr = (20.0, 35.0);
        let drawn = drawn_points(&chart, &data, xr);
        let size = legend_size(&chart);
        assert!(covered(&drawn, &SeriesLabelPosition::LowerRight, xr, yr, size) > 0);
        let (position, bottom) = legend_layout(&drawn, xr, yr, size);
        assert_eq!(bottom, yr.0, "a free corner needs no room");
        assert_eq!(covered(&drawn, &position, xr, yr, size), 0, "{position:?}");

        // Lines through all four corners: the axis is lowered until the lower right box is free.
        let diagonals = Chart {
            connect: true,
            series: vec![
                Series {
                    name: "rising".into(),
                    points: vec![(0.0, 0.0), (1.0, 1.0)],
                    ..Default::default()
                },
                Series {
                    name: "falling".into(),
                    points: vec![(0.0, 1.0), (1.0, 0.0)],
                    ..Default::default()
                },
            ],
            ..Default::default()
        };
        let data: Vec<_> = diagonals
            .series
            .iter()
            .enumerate()
            .map(|(i, s)| plotted(&diagonals, i, s))
            .collect();
        // (Ranges padded by 8 %, as `draw` pads them.)
        let (xr, yr) = ((-0.08, 1.08), (-0.08, 1.08));
        let drawn = drawn_points(&diagonals, &data, xr);
        let size = legend_size(&diagonals);
        let (position, bottom) = legend_layout(&drawn, xr, yr, size);
        assert!(bottom < yr.0);
        assert_eq!(covered(&drawn, &position, xr, (bottom, yr.1), size), 0);
    }
}
