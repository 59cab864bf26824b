//! Small PNG line plots drawn with OpenCV's imgproc into a `Mat` (no plotting dependency): time
//! series such as contact area, depth or slip state over the frames of a recording.
//!
//! A [`LinePlot`] has axes with "nice" ticks (1, 2, 5 x 10^k), one polyline per [`Series`] (NaN
//! values leave a gap) and a legend. With [`LinePlot::categories`] the y axis is labelled with names
//! instead of numbers and the series are drawn as steps (e.g. `no_contact`, `stick`, `partial_slip`,
//! `gross_slip` at y = 0, 1, 2, 3).

use std::path::Path;

use opencv::core::{CV_8UC3, Mat, Point, Rect, Scalar};
use opencv::imgproc;

use crate::{Error, Result};

/// One curve.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend text.
    pub name: String,
    /// Colour, blue-green-red.
    pub color_bgr: [u8; 3],
    /// (x, y) points in drawing order; a NaN y breaks the line.
    pub points: Vec<(f64, f64)>,
}

/// A line plot.
#[derive(Debug, Clone, PartialEq)]
pub struct LinePlot {
    /// Title above the plot.
    pub title: String,
    /// Label of the x axis (with its unit).
    pub x_label: String,
    /// Label of the y axis (with its unit).
    pub y_label: String,
    /// The curves.
    pub series: Vec<Series>,
    /// Names of the integer y values 0, 1, ... for a categorical (step) plot; empty for numbers.
    pub categories: Vec<String>,
    /// Image width, px.
    pub width: i32,
    /// Image height, px.
    pub height: i32,
}

impl LinePlot {
    /// An empty 800 x 400 plot.
    pub fn new(title: &str, x_label: &str, y_label: &str) -> Self {
        Self {
            title: title.to_owned(),
            x_label: x_label.to_owned(),
            y_label: y_label.to_owned(),
            series: Vec::new(),
            categories: Vec::new(),
            width: 800,
            height: 400,
        }
    }

    /// Adds a curve.
    pub fn with_series(mut self, name: &str, color_bgr: [u8; 3], points: Vec<(f64, f64)>) -> Self {
        self.series.push(Series {
            name: name.to_owned(),
            color_bgr,
            points,
        });
        self
    }
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

fn fmt_tick(v: f64, step: f64) -> String {
    let decimals = if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    };
    format!("{v:.decimals$}")
}

fn color(c: [u8; 3]) -> Scalar {
    Scalar::new(f64::from(c[0]), f64::from(c[1]), f64::from(c[2]), 0.0)
}

/// Draws `plot` into a new BGR image. `name` labels OpenCV errors.
pub fn render(plot: &LinePlot, name: &Path) -> Result<Mat> {
    let cv = |source: opencv::Error| Error::OpenCv {
        path: name.to_path_buf(),
        source,
    };
    let (w, h) = (plot.width.clamp(200, 4000), plot.height.clamp(150, 4000));
    let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC3, Scalar::all(255.0)).map_err(cv)?;
    let (left, right, top, bottom) = (if plot.categories.is_empty() { 70 } else { 110 }, 20, 40, 55);
    let (pw, ph) = (w - left - right, h - top - bottom);
    let finite: Vec<(f64, f64)> = plot
        .series
        .iter()
        .flat_map(|s| s.points.iter().copied())
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect();
    let (mut x0, mut x1) = finite
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.0), b.max(p.0))
        });
    let (mut y0, mut y1) = finite
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.1), b.max(p.1))
        });
    if !plot.categories.is_empty() {
        y0 = -0.5;
        y1 = plot.categories.len() as f64 - 0.5;
    }
    if !(x0.is_finite() && x1.is_finite()) {
        (x0, x1) = (0.0, 1.0);
    }
    if !(y0.is_finite() && y1.is_finite()) {
        (y0, y1) = (0.0, 1.0);
    }
    if plot.categories.is_empty() {
        // Numeric axes start at zero when the data are all positive (areas, depths).
        if y0 > 0.0 {
            y0 = 0.0;
        }
        let pad = 0.05 * (y1 - y0).max(1e-9);
        y1 += pad;
        if y0 < 0.0 {
            y0 -= pad;
        }
    }
    if x1 - x0 < 1e-12 {
        x1 = x0 + 1.0;
    }
    if y1 - y0 < 1e-12 {
        y1 = y0 + 1.0;
    }
    let px = |x: f64| left + ((x - x0) / (x1 - x0) * f64::from(pw)).round() as i32;
    let py = |y: f64| top + ph - ((y - y0) / (y1 - y0) * f64::from(ph)).round() as i32;
    let font = imgproc::FONT_HERSHEY_SIMPLEX;
    let grey = Scalar::all(200.0);
    let black = Scalar::all(0.0);
    let text = |img: &mut Mat, s: &str, at: Point, scale: f64| {
        imgproc::put_text(img, s, at, font, scale, black, 1, imgproc::LINE_AA, false).map_err(cv)
    };
    // Grid and ticks.
    let xs = nice_step(x1 - x0, 8.0);
    let mut t = (x0 / xs).ceil() * xs;
    while t <= x1 + 1e-9 {
        imgproc::line(
            &mut img,
            Point::new(px(t), top),
            Point::new(px(t), top + ph),
            grey,
            1,
            imgproc::LINE_8,
            0,
        )
        .map_err(cv)?;
        text(
            &mut img,
            &fmt_tick(t, xs),
            Point::new(px(t) - 10, top + ph + 18),
            0.4,
        )?;
        t += xs;
    }
    if plot.categories.is_empty() {
        let ys = nice_step(y1 - y0, 6.0);
        let mut t = (y0 / ys).ceil() * ys;
        while t <= y1 + 1e-9 {
            imgproc::line(
                &mut img,
                Point::new(left, py(t)),
                Point::new(left + pw, py(t)),
                grey,
                1,
                imgproc::LINE_8,
                0,
            )
            .map_err(cv)?;
            text(&mut img, &fmt_tick(t, ys), Point::new(5, py(t) + 4), 0.4)?;
            t += ys;
        }
    } else {
        for (k, c) in plot.categories.iter().enumerate() {
            let y = py(k as f64);
            imgproc::line(
                &mut img,
                Point::new(left, y),
                Point::new(left + pw, y),
                grey,
                1,
                imgproc::LINE_8,
                0,
            )
            .map_err(cv)?;
            text(&mut img, c, Point::new(5, y + 4), 0.4)?;
        }
    }
    imgproc::rectangle(
        &mut img,
        Rect::new(left, top, pw, ph),
        black,
        1,
        imgproc::LINE_8,
        0,
    )
    .map_err(cv)?;
    // Curves.
    for s in &plot.series {
        let col = color(s.color_bgr);
        let mut prev: Option<(f64, f64)> = None;
        for &(x, y) in &s.points {
            if !(x.is_finite() && y.is_finite()) {
                prev = None;
                continue;
            }
            if let Some((xp, yp)) = prev {
                if plot.categories.is_empty() {
                    imgproc::line(
                        &mut img,
                        Point::new(px(xp), py(yp)),
                        Point::new(px(x), py(y)),
                        col,
                        2,
                        imgproc::LINE_AA,
                        0,
                    )
                    .map_err(cv)?;
                } else {
                    imgproc::line(
                        &mut img,
                        Point::new(px(xp), py(yp)),
                        Point::new(px(x), py(yp)),
                        col,
                        2,
                        imgproc::LINE_AA,
                        0,
                    )
                    .map_err(cv)?;
                    imgproc::line(
                        &mut img,
                        Point::new(px(x), py(yp)),
                        Point::new(px(x), py(y)),
                        col,
                        2,
                        imgproc::LINE_AA,
                        0,
                    )
                    .map_err(cv)?;
                }
            } else if s.points.len() == 1 || plot.categories.is_empty() {
                imgproc::circle(
                    &mut img,
                    Point::new(px(x), py(y)),
                    2,
                    col,
                    -1,
                    imgproc::LINE_AA,
                    0,
                )
                .map_err(cv)?;
            }
            prev = Some((x, y));
        }
    }
    // Labels and legend.
    text(&mut img, &plot.title, Point::new(left, 25), 0.6)?;
    text(
        &mut img,
        &plot.x_label,
        Point::new(left + pw / 2 - 40, h - 12),
        0.45,
    )?;
    if plot.categories.is_empty() {
        text(&mut img, &plot.y_label, Point::new(5, top - 8), 0.4)?;
    }
    let mut lx = left + pw - 10;
    for s in plot.series.iter().rev() {
        let mut base = 0;
        let size = imgproc::get_text_size(&s.name, font, 0.45, 1, &mut base).map_err(cv)?;
        lx -= size.width + 30;
        imgproc::line(
            &mut img,
            Point::new(lx, 20),
            Point::new(lx + 20, 20),
            color(s.color_bgr),
            3,
            imgproc::LINE_AA,
            0,
        )
        .map_err(cv)?;
        text(&mut img, &s.name, Point::new(lx + 24, 25), 0.45)?;
    }
    Ok(img)
}

/// Renders `plot` and writes it as a PNG to `path`.
pub fn write(path: &Path, plot: &LinePlot) -> Result<()> {
    let img = render(plot, path)?;
    crate::images::write_image(path, &img)
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::prelude::*;

    #[test]
    fn plots_are_written_and_read_back_with_curves_drawn() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("area.png");
        let pts: Vec<(f64, f64)> = (0..50)
            .map(|i| (f64::from(i), if i == 20 { f64::NAN } else { f64::from(i * i) }))
            .collect();
        let plot = LinePlot::new("contact area", "frame", "mm^2").with_series("estimate", [200, 0, 0], pts);
        write(&path, &plot).unwrap();
        let img = crate::images::read_image(&path).unwrap();
        assert_eq!((img.cols(), img.rows()), (800, 400));
        // Some pixels carry the curve's blue.
        let mut blue = 0;
        for y in 0..img.rows() {
            for x in 0..img.cols() {
                let p = img.at_2d::<opencv::core::Vec3b>(y, x).unwrap();
                if p[0] > 150 && p[1] < 100 && p[2] < 100 {
                    blue += 1;
                }
            }
        }
        assert!(blue > 200, "{blue} blue pixels");
        let steps = LinePlot {
            categories: vec!["no_contact".into(), "stick".into()],
            ..LinePlot::new("slip", "frame", "")
        }
        .with_series("slip", [0, 0, 200], vec![(0.0, 0.0), (5.0, 1.0), (9.0, 0.0)]);
        write(&dir.path().join("slip.png"), &steps).unwrap();
        // An empty plot still renders; a bad extension is an error naming the file.
        let err = write(&dir.path().join("x.nope"), &LinePlot::new("t", "x", "y"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("x.nope"), "{err}");
        assert_eq!(nice_step(97.0, 8.0), 20.0);
        assert_eq!(fmt_tick(0.25, 0.05), "0.25");
    }
}
