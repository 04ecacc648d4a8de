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
fn plotted(chart: &Chart, index: usize, series: &Series) -> (Vec<(f64, f64)>, Vec<(f64, f64, f64)>) {
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
    let pad = if hi > lo { 0.08 * (hi - lo) } else { lo.abs().max(1.0) * 0.05 };
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
    let xs = data.iter().flat_map(|(p, w)| {
        p.iter().map(|q| q.0).chain(w.iter().map(|q| q.0))
    });
    let ys = data
        .iter()
        .flat_map(|(p, w)| p.iter().map(|q| q.1).chain(w.iter().flat_map(|q| [q.1, q.2])))
        .chain(chart.reference.iter().map(|r| r.0));
    let (x0, x1) = match &chart.x_categories {
        Some(c) => (-0.5, c.len().max(1) as f64 - 0.5),
        None => padded(xs).unwrap_or((0.0, 1.0)),
    };
    let (y0, y1) = padded(ys).unwrap_or((0.0, 1.0));
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
        .position(SeriesLabelPosition::LowerRight)
        .draw()?;
    root.present()
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
