//! Figures for reports and papers, drawn with [`plotters`]: time series (contact area, depth) with
//! the time axis in seconds when the frames carry timestamps, the slip state over time, heat maps on
//! one fixed colour scale with a colour bar (viridis, a perceptually uniform map), and overlays of
//! both camera views with displacement arrows, a legend and a caption.
//!
//! The format follows the file extension: `.png` (raster) or `.svg` (vector). Overlays draw onto
//! camera images and are PNG only. Values that are unknown (`None`, NaN) are left out of curves and
//! drawn grey in heat maps, never as 0; a series with no known value says so in the plot.
//!
//! Text is rendered through fontconfig / freetype (`plotters`' `ttf` feature): the system needs a
//! sans-serif font (Debian `fonts-dejavu-core`, installed by `scripts/setup.sh`).

use std::path::Path;

use gelstereo_core::{MarkerStatus, Point2, SlipState};
use opencv::core::{CV_8UC3, Mat, MatTraitConst, MatTraitConstManual};
use opencv::imgproc;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;

use crate::{Error, Result};

/// Size of a time-series figure, px (width, height); SVGs use the same units.
pub const PLOT_SIZE: (u32, u32) = (720, 360);
/// Size of a heat map figure (field and colour bar), px.
pub const HEATMAP_SIZE: (u32, u32) = (520, 440);

/// Colour of unknown values in heat maps.
const UNKNOWN_GREY: RGBColor = RGBColor(200, 200, 200);
/// Okabe-Ito colours: distinguishable with the common colour-vision deficiencies.
const BLUE: RGBColor = RGBColor(0, 114, 178);
const ORANGE: RGBColor = RGBColor(230, 159, 0);
const GREEN: RGBColor = RGBColor(0, 158, 115);
const VERMILLION: RGBColor = RGBColor(213, 94, 0);
const SKY: RGBColor = RGBColor(86, 180, 233);
const PURPLE: RGBColor = RGBColor(204, 121, 167);
/// Curve colours in order.
const CURVE_COLOURS: [RGBColor; 4] = [BLUE, VERMILLION, GREEN, PURPLE];
const FONT: &str = "sans-serif";

/// The time axis of a recording: seconds when every frame has a timestamp, else frame numbers.
#[derive(Debug, Clone, PartialEq)]
pub struct Timeline {
    /// Position of each frame on the axis (seconds or frame numbers).
    pub x: Vec<f64>,
    /// Whether `x` is in seconds (else frame numbers).
    pub seconds: bool,
}

impl Timeline {
    /// The axis of `frames`: their timestamps `t_s` (seconds) when given for every frame and finite,
    /// else the frame numbers.
    pub fn new(frames: &[u32], t_s: Option<&[f64]>) -> Self {
        match t_s {
            Some(t) if t.len() == frames.len() && t.iter().all(|v| v.is_finite()) => Self {
                x: t.to_vec(),
                seconds: true,
            },
            _ => Self {
                x: frames.iter().map(|f| f64::from(*f)).collect(),
                seconds: false,
            },
        }
    }

    /// The axis label with its unit.
    pub fn label(&self) -> &'static str {
        if self.seconds { "time (s)" } else { "frame" }
    }

    fn range(&self) -> (f64, f64) {
        let lo = self.x.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = self.x.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if !(lo.is_finite() && hi.is_finite()) {
            return (0.0, 1.0);
        }
        let min_span = if self.seconds { 1e-3 } else { 1.0 };
        (lo, hi.max(lo + min_span))
    }
}

/// One curve of a [`TimeSeries`]: a value per frame of the timeline, `None` where unknown.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    /// Legend text.
    pub name: String,
    /// One value per frame; `None` (or NaN) leaves a gap.
    pub values: Vec<Option<f64>>,
}

/// A plot of quantities over the frames of a recording.
#[derive(Debug, Clone, PartialEq)]
pub struct TimeSeries {
    /// Title above the plot.
    pub title: String,
    /// Label of the y axis, with its unit, e.g. `contact area (mm²)`.
    pub y_label: String,
    /// The x axis.
    pub timeline: Timeline,
    /// The curves.
    pub curves: Vec<Curve>,
    /// The smallest y span shown, in the y unit (the quantity's resolution): keeps noise around 0
    /// from being drawn with ticks such as 0.00000000005.
    pub y_resolution: f64,
    /// Why values are unknown, e.g. why the quantity cannot be measured: shown in the plot when no
    /// value is known, and beside the gaps when some are.
    pub unknown_note: String,
}

/// A dense scalar field over the marker lattice (e.g. indentation depth), for [`heatmap`].
#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    /// Samples per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Values, row-major (`width * height`); NaN where unknown.
    pub values: Vec<f64>,
    /// The x extent the samples cover (first and last column's position), e.g. marker columns.
    pub x_extent: (f64, f64),
    /// The y extent the samples cover (first and last row's position), growing downwards.
    pub y_extent: (f64, f64),
    /// Axis labels (with units), x then y.
    pub axis_labels: (String, String),
}

/// A colour scale shared by the heat maps of a recording, so frames can be compared.
#[derive(Debug, Clone, PartialEq)]
pub struct ColourScale {
    /// Value at the bottom of the scale (darkest).
    pub min: f64,
    /// Value at the top of the scale (brightest); values beyond are clamped.
    pub max: f64,
    /// What the colour shows, with its unit, e.g. `indentation depth (mm)`.
    pub label: String,
}

impl ColourScale {
    /// A scale from 0 (or the smallest value, when negative) to the largest finite value of
    /// `values`, rounded out to a 1, 2 or 5 x 10^k step; at least `resolution` wide.
    pub fn covering(label: &str, values: impl IntoIterator<Item = f64>, resolution: f64) -> Self {
        let (lo, hi) = values
            .into_iter()
            .filter(|v| v.is_finite())
            .fold((0.0f64, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
        let hi = if hi.is_finite() { hi } else { 0.0 };
        let hi = hi.max(lo + resolution.abs().max(1e-12));
        let step = nice_step(hi - lo, 5.0);
        Self {
            min: (lo / step).floor() * step,
            max: (hi / step).ceil() * step,
            label: label.to_owned(),
        }
    }

    fn colour(&self, v: f64) -> RGBColor {
        if !v.is_finite() {
            return UNKNOWN_GREY;
        }
        let span = (self.max - self.min).max(1e-12);
        let t = ((v - self.min) / span).clamp(0.0, 1.0);
        ViridisRGB::get_color_normalized(t, 0.0, 1.0)
    }
}

/// One marker drawn on an overlay.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OverlayMarker {
    /// Where the marker was in the reference frame, px.
    pub reference_px: Point2,
    /// Where it is now, px.
    pub current_px: Point2,
    /// How its position was obtained.
    pub status: MarkerStatus,
    /// Whether it lies in the contact region.
    pub in_contact: bool,
}

/// One camera view of an overlay.
#[derive(Debug)]
pub struct OverlayView<'a> {
    /// Name shown in the view's corner, e.g. `left`.
    pub name: &'a str,
    /// The camera image (8-bit BGR or grey).
    pub image: &'a Mat,
    /// The markers to draw.
    pub markers: Vec<OverlayMarker>,
}

/// Tick step of about `span / target` rounded to 1, 2 or 5 x 10^k.
fn nice_step(span: f64, target: f64) -> f64 {
    let raw = (span / target).max(1e-12);
    let mag = 10f64.powf(raw.log10().floor());
    let f = raw / mag;
    let nice = if f <= 1.0 {
        1.0
    } else if f <= 2.0 {
        2.0
    } else if f <= 5.0 {
        5.0
    } else {
        10.0
    };
    nice * mag
}

/// Tick labels for an axis spanning `lo..hi` with about `ticks` ticks: as many decimals as the
/// tick step needs and no more (0.25, not 0.2500000001), no "-0".
fn tick_label(lo: f64, hi: f64, ticks: f64) -> impl Fn(&f64) -> String {
    let step = nice_step(hi - lo, ticks);
    let decimals = if step >= 1.0 {
        0
    } else {
        ((-step.log10()).ceil().max(0.0) as usize).min(9)
    };
    move |v: &f64| {
        let s = format!("{v:.decimals$}");
        if s.trim_start_matches('-').chars().all(|c| c == '0' || c == '.') {
            "0".to_owned()
        } else {
            s
        }
    }
}

fn figure_error(path: &Path, what: impl std::fmt::Display) -> Error {
    Error::Figure {
        path: path.to_path_buf(),
        what: what.to_string(),
    }
}

/// Something drawn onto any `plotters` backend (PNG through the bitmap backend, or SVG).
trait Figure {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> std::result::Result<(), String>;
}

/// Draws `figure` into a PNG or SVG of `size` at `path`, by extension.
fn render(path: &Path, size: (u32, u32), figure: &impl Figure) -> Result<()> {
    create_parent(path)?;
    match extension(path).as_deref() {
        Some("png") => {
            let mut rgb = vec![255u8; size.0 as usize * size.1 as usize * 3];
            {
                let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
                figure.draw(&root).map_err(|e| figure_error(path, e))?;
                root.present().map_err(|e| figure_error(path, e))?;
            }
            write_rgb_png(path, &rgb, size)
        }
        Some("svg") => {
            let root = SVGBackend::new(path, size).into_drawing_area();
            figure.draw(&root).map_err(|e| figure_error(path, e))?;
            root.present().map_err(|e| figure_error(path, e))
        }
        _ => Err(figure_error(
            path,
            "unknown figure format: expected a .png or .svg file name",
        )),
    }
}

struct SeriesFigure<'a>(&'a TimeSeries);
impl Figure for SeriesFigure<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> std::result::Result<(), String> {
        draw_time_series(root, self.0)
    }
}

struct SlipFigure<'a>(&'a str, &'a Timeline, &'a [SlipState]);
impl Figure for SlipFigure<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> std::result::Result<(), String> {
        draw_slip(root, self.0, self.1, self.2)
    }
}

struct HeatmapFigure<'a>(&'a str, &'a Field, &'a ColourScale);
impl Figure for HeatmapFigure<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> std::result::Result<(), String> {
        draw_heatmap(root, self.0, self.1, self.2)
    }
}

fn extension(path: &Path) -> Option<String> {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
}

fn create_parent(path: &Path) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| Error::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    Ok(())
}

/// Writes an RGB buffer as an 8-bit RGB PNG with the `png` crate's fast compression: about a fifth
/// of OpenCV's fastest PNG setting in CPU time on a stereo overlay, the file ~1 % larger.
fn write_rgb_png(path: &Path, rgb: &[u8], size: (u32, u32)) -> Result<()> {
    let bytes = crate::images::encode_png(rgb, size, 3, png::Compression::Fast, None)
        .map_err(|e| figure_error(path, format!("cannot encode the PNG: {e}")))?;
    std::fs::write(path, bytes).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })
}

fn err<E: std::fmt::Debug>(e: E) -> String {
    format!("{e:?}")
}

/// Writes a time series plot (`.png` or `.svg`, [`PLOT_SIZE`]).
pub fn time_series(path: &Path, plot: &TimeSeries) -> Result<()> {
    render(path, PLOT_SIZE, &SeriesFigure(plot))
}

/// The value axis over the `known` values: from zero (or a margin below the lowest negative
/// value) to a margin above the highest, at least `resolution` tall.
fn value_axis(known: &[f64], resolution: f64) -> (f64, f64) {
    let lo = known.iter().copied().fold(0.0f64, f64::min);
    let hi = known.iter().copied().fold(lo, f64::max);
    let span = (hi - lo).max(resolution.abs().max(1e-12));
    (if lo < 0.0 { lo - 0.05 * span } else { 0.0 }, lo + 1.05 * span)
}

/// A grey note of font `size`, anchored at its `h`, `v` side.
fn note_style(
    size: u32,
    h: plotters::style::text_anchor::HPos,
    v: plotters::style::text_anchor::VPos,
) -> TextStyle<'static> {
    TextStyle::from((FONT, size).into_font())
        .color(&RGBColor(90, 90, 90))
        .pos(plotters::style::text_anchor::Pos::new(h, v))
}

/// Runs of known (finite) values as (x, value) points, so an unknown frame leaves a gap; runs
/// may be empty.
fn known_runs(x: &[f64], values: &[Option<f64>]) -> Vec<Vec<(f64, f64)>> {
    let mut runs: Vec<Vec<(f64, f64)>> = vec![Vec::new()];
    for (x, v) in x.iter().zip(values) {
        match v.filter(|v| v.is_finite()) {
            Some(v) => runs.last_mut().map_or((), |r| r.push((*x, v))),
            None => runs.push(Vec::new()),
        }
    }
    runs
}

fn draw_time_series<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    plot: &TimeSeries,
) -> std::result::Result<(), String> {
    root.fill(&WHITE).map_err(err)?;
    let (x0, x1) = plot.timeline.range();
    let known: Vec<f64> = plot
        .curves
        .iter()
        .flat_map(|c| c.values.iter().flatten().copied())
        .filter(|v| v.is_finite())
        .collect();
    let (y0, y1) = value_axis(&known, plot.y_resolution);
    let (fx, fy) = (tick_label(x0, x1, 8.0), tick_label(y0, y1, 6.0));
    let mut chart = ChartBuilder::on(root)
        .caption(&plot.title, (FONT, 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(64)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(plot.timeline.label())
        .y_desc(plot.y_label.as_str())
        .x_labels(8)
        .y_labels(6)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy)
        .label_style((FONT, 13))
        .axis_desc_style((FONT, 14))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()
        .map_err(err)?;
    if known.is_empty() {
        let at = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
        let style = note_style(
            15,
            plotters::style::text_anchor::HPos::Center,
            plotters::style::text_anchor::VPos::Center,
        );
        chart
            .draw_series(std::iter::once(Text::new(
                format!("unknown: {}", plot.unknown_note),
                at,
                style,
            )))
            .map_err(err)?;
        return Ok(());
    }
    let total: usize = plot.curves.iter().map(|c| c.values.len()).sum();
    if known.len() < total {
        let style = note_style(
            12,
            plotters::style::text_anchor::HPos::Right,
            plotters::style::text_anchor::VPos::Top,
        );
        chart
            .draw_series(std::iter::once(Text::new(
                format!("gaps: unknown ({})", plot.unknown_note),
                (x1, y1),
                style,
            )))
            .map_err(err)?;
    }
    for (k, curve) in plot.curves.iter().enumerate() {
        let colour = CURVE_COLOURS[k % CURVE_COLOURS.len()];
        let runs = known_runs(&plot.timeline.x, &curve.values);
        let style = ShapeStyle::from(&colour).stroke_width(2);
        let mut first = true;
        for run in runs.into_iter().filter(|r| !r.is_empty()) {
            let single = (run.len() == 1).then(|| Circle::new(run[0], 2, style.filled()));
            let series = chart.draw_series(LineSeries::new(run, style)).map_err(err)?;
            if first {
                series
                    .label(curve.name.as_str())
                    .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], style));
                first = false;
            }
            chart.draw_series(single).map_err(err)?;
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font((FONT, 13))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(180, 180, 180))
        .draw()
        .map_err(err)?;
    Ok(())
}

/// Display name and colour of each slip state, in order from no contact to gross slip.
const SLIP_STATES: [(SlipState, &str, RGBColor); 4] = [
    (SlipState::NoContact, "no contact", RGBColor(170, 170, 170)),
    (SlipState::Stick, "stick", GREEN),
    (SlipState::PartialSlip, "partial slip", ORANGE),
    (SlipState::GrossSlip, "gross slip", VERMILLION),
];

fn slip_level(s: SlipState) -> usize {
    SLIP_STATES.iter().position(|(x, _, _)| *x == s).unwrap_or(0)
}

/// Writes the slip state over time (`.png` or `.svg`, [`PLOT_SIZE`]): one bar per frame at its
/// state's row, coloured by state. `states` has one entry per frame of `timeline`.
pub fn slip_timeline(path: &Path, title: &str, timeline: &Timeline, states: &[SlipState]) -> Result<()> {
    render(path, PLOT_SIZE, &SlipFigure(title, timeline, states))
}

fn draw_slip<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    timeline: &Timeline,
    states: &[SlipState],
) -> std::result::Result<(), String> {
    root.fill(&WHITE).map_err(err)?;
    let (x0, x1) = timeline.range();
    // Each frame spans to the next one; the last one as wide as the median step.
    let mut steps: Vec<f64> = timeline
        .x
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|d| *d > 0.0)
        .collect();
    steps.sort_by(f64::total_cmp);
    let step = steps.get(steps.len() / 2).copied().unwrap_or(1.0);
    let fx = tick_label(x0, x1 + step, 8.0);
    let fy = |y: &f64| {
        let k = y.round();
        if (y - k).abs() < 1e-6 && (0.0..4.0).contains(&k) {
            SLIP_STATES[k as usize].1.to_owned()
        } else {
            String::new()
        }
    };
    let mut chart = ChartBuilder::on(root)
        .caption(title, (FONT, 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(96)
        .build_cartesian_2d(x0..x1 + step, -0.5f64..3.5f64)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(timeline.label())
        .x_labels(8)
        .y_labels(5)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy)
        .label_style((FONT, 13))
        .axis_desc_style((FONT, 14))
        .disable_y_mesh()
        .light_line_style(RGBColor(235, 235, 235))
        .draw()
        .map_err(err)?;
    let bars = timeline.x.iter().zip(states).enumerate().map(|(k, (x, s))| {
        let next = timeline
            .x
            .get(k + 1)
            .copied()
            .filter(|n| *n > *x)
            .unwrap_or(x + step);
        let level = slip_level(*s);
        let y = level as f64;
        Rectangle::new([(*x, y - 0.3), (next, y + 0.3)], SLIP_STATES[level].2.filled())
    });
    chart.draw_series(bars).map_err(err)?;
    Ok(())
}

/// Writes a heat map of `field` on `scale` with a colour bar (`.png` or `.svg`, [`HEATMAP_SIZE`]).
/// Use one scale for every heat map of a recording so their colours compare.
pub fn heatmap(path: &Path, title: &str, field: &Field, scale: &ColourScale) -> Result<()> {
    if field.values.len() != field.width * field.height || field.width == 0 || field.height == 0 {
        return Err(figure_error(
            path,
            format!(
                "the field has {} values, expected width x height = {} x {} (both > 0)",
                field.values.len(),
                field.width,
                field.height
            ),
        ));
    }
    render(path, HEATMAP_SIZE, &HeatmapFigure(title, field, scale))
}

fn draw_heatmap<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    field: &Field,
    scale: &ColourScale,
) -> std::result::Result<(), String> {
    root.fill(&WHITE).map_err(err)?;
    let root = root.titled(title, (FONT, 18)).map_err(err)?;
    let (w, _) = root.dim_in_pixel();
    let (map_area, bar_area) = root.split_horizontally(w.saturating_sub(110));
    let (xa, xb) = field.x_extent;
    let (ya, yb) = field.y_extent;
    // Sample k covers half a step either side of its position.
    let dx = if field.width > 1 {
        (xb - xa) / (field.width - 1) as f64
    } else {
        1.0
    };
    let dy = if field.height > 1 {
        (yb - ya) / (field.height - 1) as f64
    } else {
        1.0
    };
    let (x0, x1) = (xa - dx / 2.0, xb + dx / 2.0);
    let (y0, y1) = (ya - dy / 2.0, yb + dy / 2.0);
    let (fx, fy) = (tick_label(x0, x1, 6.0), tick_label(y0, y1, 6.0));
    let mut chart = ChartBuilder::on(&map_area)
        .margin(8)
        .x_label_area_size(40)
        .y_label_area_size(52)
        .build_cartesian_2d(x0..x1, y1..y0)
        .map_err(err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc(field.axis_labels.0.as_str())
        .y_desc(field.axis_labels.1.as_str())
        .x_labels(6)
        .y_labels(6)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy)
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 13))
        .draw()
        .map_err(err)?;
    let cells = field.values.iter().enumerate().map(|(k, v)| {
        let (c, r) = ((k % field.width) as f64, (k / field.width) as f64);
        let (cx, cy) = (xa + c * dx, ya + r * dy);
        Rectangle::new(
            [(cx - dx / 2.0, cy - dy / 2.0), (cx + dx / 2.0, cy + dy / 2.0)],
            scale.colour(*v).filled(),
        )
    });
    chart.draw_series(cells).map_err(err)?;
    colour_bar(&bar_area, scale)
}

fn colour_bar<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    scale: &ColourScale,
) -> std::result::Result<(), String> {
    let (lo, hi) = (scale.min, scale.max.max(scale.min + 1e-12));
    let fy = tick_label(lo, hi, 5.0);
    let mut bar = ChartBuilder::on(area)
        .margin_top(8)
        .margin_bottom(48)
        .margin_right(4)
        .y_label_area_size(0)
        .right_y_label_area_size(62)
        .build_cartesian_2d(0.0f64..1.0f64, lo..hi)
        .map_err(err)?;
    bar.configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .y_labels(6)
        .y_label_formatter(&fy)
        .y_desc(scale.label.as_str())
        .label_style((FONT, 12))
        .axis_desc_style((FONT, 13))
        .draw()
        .map_err(err)?;
    let steps = 128;
    let band = (0..steps).map(|k| {
        let a = lo + (hi - lo) * k as f64 / steps as f64;
        let b = lo + (hi - lo) * (k + 1) as f64 / steps as f64;
        Rectangle::new([(0.0, a), (1.0, b)], scale.colour((a + b) / 2.0).filled())
    });
    bar.draw_series(band).map_err(err)?;
    Ok(())
}

/// The deformed marker surface of one frame, for [`surface`].
#[derive(Debug, Clone, PartialEq)]
pub struct Surface {
    /// Marker rows of the lattice.
    pub rows: usize,
    /// Marker columns of the lattice.
    pub cols: usize,
    /// Marker positions in the left camera frame, mm, row-major; `None` where unknown.
    pub positions_mm: Vec<Option<[f64; 3]>>,
    /// Indentation depth of each marker, mm, row-major; `None` where unknown.
    pub depth_mm: Vec<Option<f64>>,
}

/// Size of a surface figure, px.
pub const SURFACE_SIZE: (u32, u32) = (640, 480);

/// Writes the 3-D contact surface (`.png` or `.svg`, [`SURFACE_SIZE`]): the marker lattice as a mesh
/// over X, Y (mm, left camera frame) with its height the negated indentation depth, each cell
/// coloured by its mean depth on `scale`, with a colour bar.
pub fn surface(path: &Path, title: &str, surface: &Surface, scale: &ColourScale) -> Result<()> {
    let n = surface.rows * surface.cols;
    if surface.positions_mm.len() != n || surface.depth_mm.len() != n || n == 0 {
        return Err(figure_error(
            path,
            format!(
                "the surface has {} positions and {} depths, expected rows x cols = {} x {} (> 0)",
                surface.positions_mm.len(),
                surface.depth_mm.len(),
                surface.rows,
                surface.cols
            ),
        ));
    }
    render(path, SURFACE_SIZE, &SurfaceFigure(title, surface, scale))
}

struct SurfaceFigure<'a>(&'a str, &'a Surface, &'a ColourScale);
impl Figure for SurfaceFigure<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> std::result::Result<(), String> {
        draw_surface(root, self.0, self.1, self.2)
    }
}

/// One lattice cell of a surface: its four corners (x, height, y) and mean depth.
type Quad = ([(f64, f64, f64); 4], f64);

fn surface_quads(s: &Surface) -> Vec<Quad> {
    let at = |r: usize, c: usize| {
        let k = r * s.cols + c;
        match (s.positions_mm[k], s.depth_mm[k]) {
            (Some(p), Some(d)) if d.is_finite() && p.iter().all(|v| v.is_finite()) => {
                Some(((p[0], -d, p[1]), d))
            }
            _ => None,
        }
    };
    let mut quads = Vec::new();
    for r in 0..s.rows.saturating_sub(1) {
        for c in 0..s.cols.saturating_sub(1) {
            if let (Some(a), Some(b), Some(d), Some(e)) =
                (at(r, c), at(r, c + 1), at(r + 1, c + 1), at(r + 1, c))
            {
                quads.push(([a.0, b.0, d.0, e.0], (a.1 + b.1 + d.1 + e.1) / 4.0));
            }
        }
    }
    quads
}

fn draw_surface<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    surface: &Surface,
    scale: &ColourScale,
) -> std::result::Result<(), String> {
    root.fill(&WHITE).map_err(err)?;
    let root = root.titled(title, (FONT, 18)).map_err(err)?;
    let (w, _) = root.dim_in_pixel();
    let (mesh_area, bar_area) = root.split_horizontally(w.saturating_sub(110));
    let mut quads = surface_quads(surface);
    let corners = || quads.iter().flat_map(|q| q.0.iter());
    let range = |f: fn(&(f64, f64, f64)) -> f64| {
        let lo = corners().map(f).fold(f64::INFINITY, f64::min);
        let hi = corners().map(f).fold(f64::NEG_INFINITY, f64::max);
        if lo.is_finite() && hi.is_finite() {
            (lo, hi.max(lo + 1e-3))
        } else {
            (0.0, 1.0)
        }
    };
    let (x, y) = (range(|p| p.0), range(|p| p.2));
    // Height axis from the scale, so frames of a recording compare.
    let (h0, h1) = (-scale.max, -scale.min.min(0.0) + 1e-3);
    let mut chart = ChartBuilder::on(&mesh_area)
        .margin(12)
        .build_cartesian_3d(x.0..x.1, h0..h1, y.0..y.1)
        .map_err(err)?;
    let (yaw, pitch) = (0.6f64, 0.45f64);
    chart.with_projection(|mut p| {
        p.yaw = yaw;
        p.pitch = pitch;
        p.scale = 0.8;
        p.into_matrix()
    });
    let fh = tick_label(h0, h1, 4.0);
    let fxy = tick_label(x.0, x.1, 5.0);
    chart
        .configure_axes()
        .light_grid_style(RGBColor(230, 230, 230))
        .max_light_lines(2)
        .label_style((FONT, 11))
        .x_formatter(&fxy)
        .z_formatter(&fxy)
        .y_formatter(&fh)
        .draw()
        .map_err(err)?;
    // Far cells first (painter's order along the viewing direction).
    let away = |q: &Quad| {
        let (cx, cz) = q.0.iter().fold((0.0, 0.0), |a, p| (a.0 + p.0, a.1 + p.2));
        cx * yaw.sin() - cz * yaw.cos()
    };
    quads.sort_by(|a, b| away(a).total_cmp(&away(b)));
    chart
        .draw_series(
            quads
                .iter()
                .map(|(c, d)| Polygon::new(c.to_vec(), scale.colour(*d).filled())),
        )
        .map_err(err)?;
    let note = TextStyle::from((FONT, 12).into_font()).color(&RGBColor(90, 90, 90));
    mesh_area
        .draw(&Text::new(
            "X, Y: mm in the left camera frame; height: -depth (mm), exaggerated".to_owned(),
            (8, 4),
            note,
        ))
        .map_err(err)?;
    colour_bar(&bar_area, scale)
}

/// Writes an overlay PNG: the views side by side, each with an arrow per marker from its reference
/// position towards its current one (lengthened `arrow_scale` times), a ring around markers in
/// contact, and below them a legend and `caption` (items wrapped to the image width, so small
/// images such as a 320 px GelSight Mini frame keep the whole caption).
pub fn overlay(path: &Path, views: &[OverlayView], arrow_scale: f64, caption: &[String]) -> Result<()> {
    if extension(path).as_deref() != Some("png") {
        return Err(figure_error(
            path,
            "overlays are written as PNG: expected a .png file name",
        ));
    }
    if views.is_empty() {
        return Err(figure_error(path, "no view to draw"));
    }
    let gap = 4u32;
    let sizes: Vec<(u32, u32)> = views
        .iter()
        .map(|v| (v.image.cols().max(0) as u32, v.image.rows().max(0) as u32))
        .collect();
    let images_w = sizes.iter().map(|s| s.0).sum::<u32>() + gap * (views.len() as u32 - 1);
    let images_h = sizes.iter().map(|s| s.1).max().unwrap_or(0);
    if images_w == 0 || images_h == 0 {
        return Err(figure_error(path, "an empty camera image"));
    }
    let font_px = (f64::from(sizes[0].0) / 24.0).clamp(11.0, 16.0);
    let legend = legend_items(arrow_scale);
    let lines = wrap(&legend, caption, images_w, font_px);
    let line_h = (font_px * 1.35).ceil() as u32;
    let size = (images_w, images_h + line_h * lines.len() as u32 + 6);
    let mut rgb = vec![255u8; size.0 as usize * size.1 as usize * 3];
    let mut left = 0u32;
    for (view, (w, _)) in views.iter().zip(&sizes) {
        paste_bgr(&mut rgb, size.0, left, view.image).map_err(|source| Error::OpenCv {
            path: path.to_path_buf(),
            source,
        })?;
        left += w + gap;
    }
    {
        let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
        let mut left = 0i32;
        for (view, (w, _)) in views.iter().zip(&sizes) {
            draw_markers(&root, left, view, arrow_scale, font_px).map_err(|e| figure_error(path, e))?;
            left += *w as i32 + gap as i32;
        }
        draw_text_lines(&root, images_h as i32 + 3, line_h as i32, font_px, &lines)
            .map_err(|e| figure_error(path, e))?;
        root.present().map_err(|e| figure_error(path, e))?;
    }
    create_parent(path)?;
    write_rgb_png(path, &rgb, size)
}

/// A piece of the legend / caption line: text with an optional symbol before it.
#[derive(Debug, Clone)]
enum Item {
    Arrow(RGBColor, String),
    Ring(RGBColor, String),
    Text(String),
}

impl Item {
    fn text(&self) -> &str {
        match self {
            Item::Arrow(_, t) | Item::Ring(_, t) | Item::Text(t) => t,
        }
    }
}

fn status_colour(s: MarkerStatus) -> RGBColor {
    match s {
        MarkerStatus::Tracked => GREEN,
        MarkerStatus::Predicted => ORANGE,
        MarkerStatus::Lost => VERMILLION,
    }
}

fn legend_items(arrow_scale: f64) -> Vec<Item> {
    vec![
        Item::Arrow(GREEN, format!("tracked (x{arrow_scale:.0})")),
        Item::Arrow(ORANGE, "predicted".into()),
        Item::Ring(SKY, "in contact".into()),
    ]
}

/// Width of the symbol drawn before an item's text, in font heights.
const SYMBOL_EM: f64 = 1.6;

/// Lays the legend items, then the caption items, into lines no wider than `width`.
fn wrap(legend: &[Item], caption: &[String], width: u32, font_px: f64) -> Vec<Vec<Item>> {
    // Sans-serif text averages about 0.55 em per character.
    let item_w = |it: &Item| {
        let symbol = if matches!(it, Item::Text(_)) {
            0.0
        } else {
            SYMBOL_EM
        };
        (symbol + 0.55 * it.text().chars().count() as f64 + 1.2) * font_px
    };
    let mut lines: Vec<Vec<Item>> = Vec::new();
    for group in [legend.to_vec(), caption.iter().cloned().map(Item::Text).collect()] {
        let mut line: Vec<Item> = Vec::new();
        let mut used = 0.0;
        for it in group {
            let w = item_w(&it);
            if !line.is_empty() && used + w > f64::from(width) - 8.0 {
                lines.push(std::mem::take(&mut line));
                used = 0.0;
            }
            used += w;
            line.push(it);
        }
        if !line.is_empty() {
            lines.push(line);
        }
    }
    lines
}

/// Copies a BGR or grey image into the RGB canvas at column `left`.
fn paste_bgr(rgb: &mut [u8], canvas_w: u32, left: u32, image: &Mat) -> opencv::Result<()> {
    let mut bgr = Mat::default();
    match image.channels() {
        1 => imgproc::cvt_color(image, &mut bgr, imgproc::COLOR_GRAY2BGR, 0)?,
        4 => imgproc::cvt_color(image, &mut bgr, imgproc::COLOR_BGRA2BGR, 0)?,
        _ => bgr = image.try_clone()?,
    }
    if bgr.typ() != CV_8UC3 {
        return Err(opencv::Error::new(
            opencv::core::StsBadArg,
            "expected an 8-bit image".to_owned(),
        ));
    }
    let bgr = if bgr.is_continuous() {
        bgr
    } else {
        bgr.try_clone()?
    };
    let bytes = bgr.data_bytes()?;
    let (w, h) = (bgr.cols() as usize, bgr.rows() as usize);
    for y in 0..h {
        for x in 0..w {
            let s = (y * w + x) * 3;
            let d = (y * canvas_w as usize + left as usize + x) * 3;
            if let (Some(src), Some(dst)) = (bytes.get(s..s + 3), rgb.get_mut(d..d + 3)) {
                dst.copy_from_slice(&[src[2], src[1], src[0]]);
            }
        }
    }
    Ok(())
}

fn draw_markers<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    left: i32,
    view: &OverlayView,
    arrow_scale: f64,
    font_px: f64,
) -> std::result::Result<(), String> {
    let at = |p: Point2| (left + p.x.round() as i32, p.y.round() as i32);
    let ring_px = (font_px * 0.35).round().max(3.0) as i32;
    for m in &view.markers {
        if m.in_contact {
            root.draw(&Circle::new(at(m.current_px), ring_px, SKY.stroke_width(1)))
                .map_err(err)?;
        }
    }
    for m in &view.markers {
        let r = m.reference_px;
        let tip = Point2::new(
            r.x + arrow_scale * (m.current_px.x - r.x),
            r.y + arrow_scale * (m.current_px.y - r.y),
        );
        arrow(root, at(r), at(tip), status_colour(m.status))?;
    }
    // The view's name on a dark label in its top-left corner.
    let name_w = (0.6 * font_px * view.name.chars().count() as f64 + 8.0) as i32;
    let name_h = (font_px * 1.3) as i32;
    root.draw(&Rectangle::new(
        [(left, 0), (left + name_w, name_h)],
        BLACK.mix(0.6).filled(),
    ))
    .map_err(err)?;
    root.draw(&Text::new(
        view.name.to_owned(),
        (left + 4, 2),
        (FONT, font_px).into_font().color(&WHITE),
    ))
    .map_err(err)?;
    Ok(())
}

/// A line from `a` to `b` with a small head at `b` (none for arrows under 2 px).
fn arrow<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    a: (i32, i32),
    b: (i32, i32),
    colour: RGBColor,
) -> std::result::Result<(), String> {
    let style = colour.stroke_width(1);
    let (dx, dy) = (f64::from(b.0 - a.0), f64::from(b.1 - a.1));
    let len = dx.hypot(dy);
    if len < 2.0 {
        return root.draw(&Circle::new(a, 1, style.filled())).map_err(err);
    }
    root.draw(&PathElement::new([a, b], style)).map_err(err)?;
    let head = (0.3 * len).clamp(2.0, 5.0);
    let (ux, uy) = (dx / len, dy / len);
    for side in [-1.0, 1.0] {
        let (hx, hy) = (
            f64::from(b.0) - head * (ux - side * 0.5 * uy),
            f64::from(b.1) - head * (uy + side * 0.5 * ux),
        );
        root.draw(&PathElement::new(
            [b, (hx.round() as i32, hy.round() as i32)],
            style,
        ))
        .map_err(err)?;
    }
    Ok(())
}

fn draw_text_lines<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    top: i32,
    line_h: i32,
    font_px: f64,
    lines: &[Vec<Item>],
) -> std::result::Result<(), String> {
    let font = (FONT, font_px).into_font().color(&BLACK);
    for (k, line) in lines.iter().enumerate() {
        let y = top + k as i32 * line_h;
        let mid = y + line_h / 2;
        let mut x = 4i32;
        for item in line {
            let symbol_w = (SYMBOL_EM * font_px) as i32;
            match item {
                Item::Arrow(c, _) => {
                    arrow(root, (x, mid), (x + symbol_w - 6, mid), *c)?;
                    x += symbol_w;
                }
                Item::Ring(c, _) => {
                    let r = (font_px * 0.35).round() as i32;
                    root.draw(&Circle::new((x + r + 1, mid), r, c.stroke_width(2)))
                        .map_err(err)?;
                    x += symbol_w;
                }
                Item::Text(_) => {}
            }
            root.draw(&Text::new(item.text().to_owned(), (x, y + 1), font.clone()))
                .map_err(err)?;
            let (w, _) = root.estimate_text_size(item.text(), &font).map_err(err)?;
            x += w as i32 + (font_px * 1.2) as i32;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Scalar, Vec3b};

    fn read(path: &Path) -> Mat {
        crate::images::read_image(path).unwrap()
    }

    fn timeline() -> Timeline {
        let frames: Vec<u32> = (0..40).collect();
        let t: Vec<f64> = frames.iter().map(|f| f64::from(*f) / 30.0).collect();
        Timeline::new(&frames, Some(&t))
    }

    #[test]
    fn time_axis_is_in_seconds_only_when_every_frame_has_a_timestamp() {
        let frames = [0u32, 1, 2];
        assert!(Timeline::new(&frames, Some(&[0.0, 0.5, 1.0])).seconds);
        assert_eq!(Timeline::new(&frames, Some(&[0.0, 0.5, 1.0])).label(), "time (s)");
        let partial = Timeline::new(&frames, Some(&[0.0, f64::NAN, 1.0]));
        assert!(!partial.seconds && partial.x == [0.0, 1.0, 2.0]);
        assert_eq!(Timeline::new(&frames, None).label(), "frame");
    }

    #[test]
    fn tick_labels_carry_the_decimals_of_the_step_only() {
        let f = tick_label(0.0, 1e-9, 6.0);
        assert_eq!(f(&0.0), "0");
        let f = tick_label(0.0, 2.0, 6.0);
        assert_eq!(f(&0.5), "0.5");
        assert_eq!(f(&-0.0), "0");
        assert_eq!(tick_label(0.0, 300.0, 8.0)(&150.0), "150");
        assert_eq!(tick_label(0.0, 0.012, 6.0)(&0.0025), "0.003");
    }

    #[test]
    fn time_series_render_as_png_and_svg_of_the_stated_size() {
        let dir = tempfile::tempdir().unwrap();
        let tl = timeline();
        let values: Vec<Option<f64>> = (0..40)
            .map(|i| (i != 20).then(|| f64::from(i * i) * 0.01))
            .collect();
        let plot = TimeSeries {
            title: "contact area".into(),
            y_label: "area (mm²)".into(),
            timeline: tl,
            curves: vec![Curve {
                name: "estimate".into(),
                values,
            }],
            y_resolution: 0.1,
            unknown_note: "no scale".into(),
        };
        let png = dir.path().join("plots/area.png");
        time_series(&png, &plot).unwrap();
        let img = read(&png);
        assert_eq!((img.cols() as u32, img.rows() as u32), PLOT_SIZE);
        // The curve's blue is drawn.
        let mut blue = 0;
        for y in 0..img.rows() {
            for x in 0..img.cols() {
                let p = img.at_2d::<Vec3b>(y, x).unwrap();
                if p[0] > 150 && p[1] < 140 && p[2] < 60 {
                    blue += 1;
                }
            }
        }
        assert!(blue > 200, "{blue} blue pixels");
        let svg = dir.path().join("area.svg");
        time_series(&svg, &plot).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.contains(r#"width="720" height="360""#), "{}", &text[..200]);
        assert!(text.contains("time (s)") && text.contains("area (mm²)") && text.contains("#0072B2"));
        assert!(
            text.contains("gaps: unknown (no scale)"),
            "the gap at frame 20 is explained"
        );
        // A bad extension is an error naming the file.
        let e = time_series(&dir.path().join("x.jpg"), &plot)
            .unwrap_err()
            .to_string();
        assert!(e.contains("x.jpg") && e.contains(".png or .svg"), "{e}");
    }

    #[test]
    fn a_quantity_without_any_known_value_is_plotted_as_unknown_not_zero() {
        let dir = tempfile::tempdir().unwrap();
        let plot = TimeSeries {
            title: "contact area".into(),
            y_label: "area (mm²)".into(),
            timeline: timeline(),
            curves: vec![Curve {
                name: "estimate".into(),
                values: vec![None; 40],
            }],
            y_resolution: 1.0,
            unknown_note: "the marker pitch is not given (--pitch-mm)".into(),
        };
        let svg = dir.path().join("area.svg");
        time_series(&svg, &plot).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.contains("unknown: the marker pitch is not given (--pitch-mm)"));
        assert!(!text.contains("#0072B2"), "no curve drawn");
    }

    #[test]
    fn slip_timeline_names_the_states_and_colours_each_frame() {
        let dir = tempfile::tempdir().unwrap();
        let states: Vec<SlipState> = (0..40)
            .map(|i| match i {
                0..10 => SlipState::NoContact,
                10..20 => SlipState::Stick,
                20..30 => SlipState::PartialSlip,
                _ => SlipState::GrossSlip,
            })
            .collect();
        let svg = dir.path().join("slip.svg");
        slip_timeline(&svg, "slip state", &timeline(), &states).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        for name in ["no contact", "stick", "partial slip", "gross slip", "time (s)"] {
            assert!(text.contains(name), "{name}");
        }
        let png = dir.path().join("slip.png");
        slip_timeline(&png, "slip state", &timeline(), &states).unwrap();
        let img = read(&png);
        // Vermillion (gross slip) bars are present.
        let p = (0..img.cols())
            .flat_map(|x| (0..img.rows()).map(move |y| (x, y)))
            .filter(|&(x, y)| img.at_2d::<Vec3b>(y, x).unwrap().0 == [0, 94, 213])
            .count();
        assert!(p > 100, "{p} gross-slip pixels");
    }

    fn field(scale_by: f64) -> Field {
        let (w, h) = (23usize, 23usize);
        Field {
            width: w,
            height: h,
            values: (0..w * h)
                .map(|k| {
                    if k == 0 {
                        f64::NAN
                    } else {
                        scale_by * (k % w) as f64 / 22.0
                    }
                })
                .collect(),
            x_extent: (0.0, 22.0),
            y_extent: (0.0, 22.0),
            axis_labels: ("marker column".into(), "marker row".into()),
        }
    }

    #[test]
    fn heat_maps_share_one_fixed_colour_scale_with_a_colour_bar() {
        let dir = tempfile::tempdir().unwrap();
        let (weak, strong) = (field(0.2), field(0.8));
        let scale = ColourScale::covering(
            "indentation depth (mm)",
            weak.values.iter().chain(&strong.values).copied(),
            0.01,
        );
        assert_eq!((scale.min, scale.max), (0.0, 0.8));
        let (a, b) = (dir.path().join("a.png"), dir.path().join("b.png"));
        heatmap(&a, "frame 1", &weak, &scale).unwrap();
        heatmap(&b, "frame 2", &strong, &scale).unwrap();
        let (ia, ib) = (read(&a), read(&b));
        assert_eq!((ia.cols() as u32, ia.rows() as u32), HEATMAP_SIZE);
        // The colour bar is identical in both (same scale), the fields differ: the weak frame's
        // brightest cell is far darker than the strong frame's.
        let bar_x = ia.cols() - 90;
        let column = |m: &Mat| {
            (40..ia.rows() - 60)
                .map(|y| m.at_2d::<Vec3b>(y, bar_x).unwrap().0)
                .collect::<Vec<_>>()
        };
        assert_eq!(column(&ia), column(&ib), "colour bar differs between frames");
        let brightness = |m: &Mat| {
            (0..m.rows())
                .flat_map(|y| (0..m.cols() - 120).map(move |x| (x, y)))
                .map(|(x, y)| m.at_2d::<Vec3b>(y, x).unwrap().0)
                .filter(|p| p[1] > 150 && p[2] > 150 && p[0] < 100) // viridis yellow
                .count()
        };
        assert_eq!(brightness(&ia), 0, "a 0.2 mm field shows no top-of-scale yellow");
        assert!(brightness(&ib) > 100);
        let svg = dir.path().join("a.svg");
        heatmap(&svg, "frame 1", &weak, &scale).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.contains("indentation depth (mm)") && text.contains("marker column"));
        assert!(text.contains("0.8"), "the scale's top is labelled");
        // A field whose size does not match its values is refused by name.
        let bad = Field {
            width: 5,
            ..field(1.0)
        };
        let e = heatmap(&svg, "x", &bad, &scale).unwrap_err().to_string();
        assert!(e.contains("a.svg") && e.contains("529 values"), "{e}");
    }

    #[test]
    fn the_contact_surface_renders_in_3d_with_its_colour_bar() {
        let dir = tempfile::tempdir().unwrap();
        let (rows, cols) = (9usize, 9usize);
        let depth: Vec<Option<f64>> = (0..rows * cols)
            .map(|k| {
                let (r, c) = ((k / cols) as f64 - 4.0, (k % cols) as f64 - 4.0);
                Some(0.6 * (-(r * r + c * c) / 6.0).exp())
            })
            .collect();
        let positions: Vec<Option<[f64; 3]>> = (0..rows * cols)
            .map(|k| Some([0.8 * (k % cols) as f64, 0.8 * (k / cols) as f64, 24.0]))
            .collect();
        let s = Surface {
            rows,
            cols,
            positions_mm: positions,
            depth_mm: depth,
        };
        assert_eq!(surface_quads(&s).len(), 64);
        let scale = ColourScale::covering("indentation depth (mm)", [0.6], 0.01);
        let png = dir.path().join("surface.png");
        surface(&png, "frame 9", &s, &scale).unwrap();
        let img = read(&png);
        assert_eq!((img.cols() as u32, img.rows() as u32), SURFACE_SIZE);
        let svg = dir.path().join("surface.svg");
        surface(&svg, "frame 9", &s, &scale).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.matches("<polygon").count() >= 64, "a polygon per cell");
        assert!(text.contains("indentation depth (mm)"));
        let bad = Surface { rows: 3, ..s };
        assert!(
            surface(&svg, "x", &bad, &scale)
                .unwrap_err()
                .to_string()
                .contains("81 positions")
        );
    }

    #[test]
    fn overlays_show_both_views_side_by_side_with_the_whole_caption_on_small_images() {
        let dir = tempfile::tempdir().unwrap();
        let grey = Mat::new_rows_cols_with_default(240, 320, CV_8UC3, Scalar::all(120.0)).unwrap();
        let markers: Vec<OverlayMarker> = (0..8)
            .map(|k| OverlayMarker {
                reference_px: Point2::new(30.0 + 30.0 * f64::from(k), 120.0),
                current_px: Point2::new(33.0 + 30.0 * f64::from(k), 122.0),
                status: if k == 3 {
                    MarkerStatus::Predicted
                } else {
                    MarkerStatus::Tracked
                },
                in_contact: k > 4,
            })
            .collect();
        let views = [
            OverlayView {
                name: "left",
                image: &grey,
                markers: markers.clone(),
            },
            OverlayView {
                name: "right",
                image: &grey,
                markers,
            },
        ];
        let caption: Vec<String> = ["t 1.23 s", "partial slip", "area unknown", "depth unknown"]
            .map(String::from)
            .to_vec();
        let path = dir.path().join("ov/000001.png");
        overlay(&path, &views, 3.0, &caption).unwrap();
        let img = read(&path);
        assert_eq!(img.cols(), 2 * 320 + 4, "two views side by side");
        assert!(img.rows() > 240, "a band for the legend and caption");
        // One view alone: the caption wraps into more lines instead of being cut.
        let one = dir.path().join("one.png");
        overlay(&one, &views[..1], 3.0, &caption).unwrap();
        let single = read(&one);
        assert_eq!(single.cols(), 320);
        assert!(single.rows() > img.rows(), "{} vs {}", single.rows(), img.rows());
        let lines = wrap(&legend_items(3.0), &caption, 320, 13.0);
        assert!(lines.len() >= 3);
        assert_eq!(
            lines.iter().flatten().count(),
            3 + caption.len(),
            "no item dropped"
        );
        // Green arrows are drawn in both halves.
        let green = |x0: i32, x1: i32| {
            (x0..x1)
                .flat_map(|x| (0..240).map(move |y| (x, y)))
                .filter(|&(x, y)| img.at_2d::<Vec3b>(y, x).unwrap().0 == [115, 158, 0])
                .count()
        };
        assert!(green(0, 320) > 20 && green(324, 644) > 20);
        assert!(overlay(&dir.path().join("o.svg"), &views, 3.0, &caption).is_err());
    }
}
