//! Sinks: where [`crate::FrameOutput`]s go. CSV tables ([`TableSink`]), JSON lines ([`JsonlSink`]),
//! PLY clouds and meshes ([`PlySink`]), overlays ([`OverlaySink`]) and plots ([`PlotSink`]), all
//! writing into an [`OutputFolder`] that records what it wrote.
//!
//! Each frame's table rows go out in one write each, markers before frames, and are flushed: an
//! interrupted run loses at most the frame in flight, and never leaves a cut line. Images and PLYs
//! are written to a temporary name and renamed, so none is ever cut either.

mod draw;
mod folder;
mod jsonl;

use std::fs::File;
use std::io::Write;
use std::sync::Arc;

use gelstereo_core::table::{FRAME_COLUMNS, MARKER_COLUMNS};
use gelstereo_core::{FrameSummary, GridShape};
use gelstereo_io::figures::{self, ColourScale, Curve, OverlayView, TimeSeries, Timeline};
use gelstereo_io::images;
use gelstereo_io::ply::CoordinateFrame;
use gelstereo_tracking::{TrackFrame, interpolate};

pub use folder::{MANIFEST, OutputFolder};
pub use gelstereo_tracking::stream::{FRAME_SCHEMA, MAX_LINE_BYTES};
pub use jsonl::{JsonlSink, frame_line, parse_frame_line, read_frames};

use crate::error::file_err;
use crate::{FrameOutput, Images, Pipeline, Result, Stages};

/// What a sink sees of one frame.
pub struct FrameContext<'a> {
    /// The frame's result.
    pub output: &'a FrameOutput,
    /// The frame's images (`None` for frames that could not be read, and for
    /// [`FrameOutput::earlier`] frames).
    pub images: Option<&'a Images>,
    /// The pipeline after the frame (lattice shape, surface triangles).
    pub pipeline: &'a Pipeline,
}

/// A destination of frame results.
pub trait Sink {
    /// Takes one frame (in frame order).
    fn frame(&mut self, frame: &FrameContext) -> Result<()>;
    /// Completes the outputs after the last frame (also after an interruption).
    fn finish(&mut self) -> Result<()> {
        Ok(())
    }
}

/// `frames.csv`'s columns: the per-frame summary of DESIGN.md, then the time and the flag.
pub fn frames_csv_header() -> String {
    format!("{},t_s,note", FRAME_COLUMNS.join(","))
}

/// The `frames.csv` row of a frame (no newline). The note is kept to one cell that every CSV reader
/// splits alike: commas become semicolons, line breaks and quotes spaces.
pub fn frames_csv_row(summary: &FrameSummary, t_s: f64, note: Option<&str>, out: &mut String) {
    summary.write_csv(out);
    out.push_str(&format!(",{t_s:.6},"));
    if let Some(n) = note {
        out.extend(n.chars().map(|c| match c {
            ',' => ';',
            '\n' | '\r' | '"' => ' ',
            c => c,
        }));
    }
}

/// `markers.csv` and `frames.csv` (DESIGN.md tables; `frames.csv` ends with `t_s` and `note`).
pub struct TableSink {
    markers: File,
    frames: File,
    markers_path: std::path::PathBuf,
    frames_path: std::path::PathBuf,
    line: String,
}

impl TableSink {
    /// Creates both tables in `folder`, headers written.
    pub fn create(folder: &OutputFolder) -> Result<Self> {
        let markers_path = folder.claim("markers.csv")?;
        let frames_path = folder.claim("frames.csv")?;
        let mut sink = Self {
            markers: File::create(&markers_path).map_err(file_err(&markers_path))?,
            frames: File::create(&frames_path).map_err(file_err(&frames_path))?,
            markers_path,
            frames_path,
            line: String::new(),
        };
        let (m, f) = (
            format!("{}\n", MARKER_COLUMNS.join(",")),
            format!("{}\n", frames_csv_header()),
        );
        sink.write(&m, &f)?;
        Ok(sink)
    }

    fn write(&mut self, markers: &str, frames: &str) -> Result<()> {
        self.markers
            .write_all(markers.as_bytes())
            .map_err(file_err(&self.markers_path))?;
        self.frames
            .write_all(frames.as_bytes())
            .map_err(file_err(&self.frames_path))
    }
}

impl Sink for TableSink {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        let out = frame.output;
        let mut markers = std::mem::take(&mut self.line);
        markers.clear();
        for m in &out.markers {
            m.write_csv(&mut markers);
            markers.push('\n');
        }
        let mut row = String::new();
        frames_csv_row(&out.summary, out.t_s, out.note.as_deref(), &mut row);
        row.push('\n');
        let written = self.write(&markers, &row);
        self.line = markers;
        written
    }
}

/// `gel.json`: the gel's facts and friction coefficient the contact mechanics used, and the gel
/// frame (origin and axes in the left camera frame), written once the reference frame sets it.
pub struct GelSink {
    folder: Arc<OutputFolder>,
    written: bool,
}

impl GelSink {
    /// Writes into `folder`.
    pub fn new(folder: Arc<OutputFolder>) -> Self {
        Self {
            folder,
            written: false,
        }
    }
}

impl Sink for GelSink {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        if self.written {
            return Ok(());
        }
        let Some(gel) = frame.pipeline.gel_frame() else {
            return Ok(());
        };
        let (origin, axes) = (gel.origin_mm, gel.axes);
        let c = frame.pipeline.contact_config();
        let v = |v: nalgebra::Vector3<f64>| [v.x, v.y, v.z];
        let json = serde_json::json!({
            "gel": {
                "thickness_mm": c.layer.thickness_mm,
                "modulus_kpa": c.layer.modulus_kpa,
                "poisson": c.layer.poisson,
            },
            "friction": c.friction,
            "gel_frame_in_left_camera": {
                "origin_mm": [origin.x, origin.y, origin.z],
                "x_axis": v(axes[0]),
                "y_axis": v(axes[1]),
                "z_axis": v(axes[2]),
                "convention": "p_gel = [x_axis; y_axis; z_axis] (p_left - origin_mm): x along the lattice's columns, y along its rows, z the reference surface's normal away from the cameras",
            },
        });
        let path = self.folder.claim("gel.json")?;
        let text = serde_json::to_string_pretty(&json).unwrap_or_default() + "\n";
        let mut file = gelstereo_io::atomic::AtomicFile::create(&path)?;
        file.write_all(text.as_bytes()).map_err(file_err(&path))?;
        file.commit()?;
        self.written = true;
        Ok(())
    }
}

/// Samples of a height map per marker pitch.
const HEIGHT_SAMPLES_PER_PITCH: usize = 4;
/// A height map PNG's count per mm and the height of count 0 (unknown): counts of 0.1 µm from
/// −3.2768 mm.
const HEIGHT_COUNTS_PER_MM: f64 = 1e4;
const HEIGHT_PNG_OFFSET_MM: f64 = -3.2768;

/// Dense height maps of the deformed gel surface in the gel frame, every Nth stereo frame:
/// `heightmap/NNNNNN.npy` (float32 mm, NaN unknown) and `heightmap/NNNNNN.png` (16-bit grey,
/// `z_mm = count / 10000 − 3.2768`, 0 unknown), described by `heightmap/scale.json`.
pub struct HeightMapSink {
    folder: Arc<OutputFolder>,
    every: usize,
    described: bool,
}

impl HeightMapSink {
    /// Writes every `every`th frame (0: none).
    pub fn new(folder: Arc<OutputFolder>, every: usize) -> Self {
        Self {
            folder,
            every,
            described: false,
        }
    }
}

impl Sink for HeightMapSink {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        let Some((st, gel)) = due_stereo(frame, self.every) else {
            return Ok(());
        };
        let out = frame.output;
        let map = draw::height_map(
            frame.pipeline.shape(),
            &st.contact,
            &gel,
            HEIGHT_SAMPLES_PER_PITCH,
        );
        if !self.described {
            let json = serde_json::json!({
                "frame": "gel frame (gel.json): z along the reference surface's normal away from the cameras, origin at its centre",
                "rows": map.rows,
                "cols": map.cols,
                "pixel_mm": map.pixel_mm,
                "x0_mm": map.origin_mm[0],
                "y0_mm": map.origin_mm[1],
                "npy": "float32 z_mm of the deformed surface at (x0 + col * pixel, y0 + row * pixel) of the rest surface; NaN unknown",
                "png": {"z_mm": "count / 10000 - 3.2768", "unknown": 0},
            });
            self.folder.write_atomic("heightmap/scale.json", |p| {
                let text = serde_json::to_string_pretty(&json).unwrap_or_default() + "\n";
                std::fs::write(p, text).map_err(file_err(p))
            })?;
            self.described = true;
        }
        let counts: Vec<u16> = map
            .z_mm
            .iter()
            .map(|z| {
                if z.is_finite() {
                    ((f64::from(*z) - HEIGHT_PNG_OFFSET_MM) * HEIGHT_COUNTS_PER_MM)
                        .round()
                        .clamp(1.0, 65535.0) as u16
                } else {
                    0
                }
            })
            .collect();
        let size = (map.cols as u32, map.rows as u32);
        self.folder
            .write_atomic(&format!("heightmap/{:06}.png", out.frame), |p| {
                let bytes = images::encode_png_gray16(&counts, size)
                    .map_err(|e| crate::Error::Invalid(format!("{}: cannot encode: {e}", p.display())))?;
                std::fs::write(p, bytes).map_err(file_err(p))
            })?;
        self.folder
            .write_atomic(&format!("heightmap/{:06}.npy", out.frame), |p| {
                Ok(images::write_npy_f32(p, map.rows, map.cols, map.z_mm.clone())?)
            })
    }
}

/// The stereo stages and the gel frame of `frame` when it is one of every `every_n`; `None` for
/// other frames, mono sensors and frames before the reference.
fn due_stereo<'a>(
    frame: &'a FrameContext,
    every_n: usize,
) -> Option<(&'a gelstereo_tracking::StereoFrame, crate::GelFrame)> {
    if !every(frame.output.frame, every_n) {
        return None;
    }
    match &frame.output.stages {
        Some(Stages::Stereo(st)) => Some((st, frame.pipeline.gel_frame()?)),
        _ => None,
    }
}

/// Whether frame `frame` is one of every `every` (0: none).
fn every(frame: u32, every: usize) -> bool {
    every > 0 && (frame as usize).is_multiple_of(every)
}

/// The marker cloud and the deformed surface mesh of every Nth stereo frame:
/// `ply/cloud_NNNNNN.ply`, `ply/mesh_NNNNNN.ply`.
pub struct PlySink {
    folder: Arc<OutputFolder>,
    every: usize,
    coordinates: CoordinateFrame,
}

impl PlySink {
    /// Writes every `every`th frame (0: none), coordinates in `coordinates`.
    pub fn new(folder: Arc<OutputFolder>, every: usize, coordinates: CoordinateFrame) -> Self {
        Self {
            folder,
            every,
            coordinates,
        }
    }
}

impl Sink for PlySink {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        let Some((st, gel)) = due_stereo(frame, self.every) else {
            return Ok(());
        };
        let out = frame.output;
        let p = frame.pipeline;
        let cloud = format!("ply/cloud_{:06}.ply", out.frame);
        let mesh = format!("ply/mesh_{:06}.ply", out.frame);
        self.folder.write_atomic(&cloud, |cloud_path| {
            self.folder.write_atomic(&mesh, |mesh_path| {
                draw::write_ply(
                    (cloud_path, mesh_path),
                    out.frame,
                    p.shape(),
                    p.surface_triangles(),
                    &st.contact,
                    &st.reprojection_px,
                    &gel,
                    self.coordinates,
                )
            })
        })
    }
}

/// Overlays of every Nth frame: both views (or the one of a mono sensor) with displacement arrows,
/// marker status and contact, a legend and a caption (`overlays/NNNNNN.png`).
pub struct OverlaySink {
    folder: Arc<OutputFolder>,
    every: usize,
    arrow_scale: f64,
}

impl OverlaySink {
    /// Draws every `every`th frame (0: none), arrows `arrow_scale` times the displacement.
    pub fn new(folder: Arc<OutputFolder>, every: usize, arrow_scale: f64) -> Self {
        Self {
            folder,
            every,
            arrow_scale,
        }
    }
}

/// Whether the marker `track.markers[k]` lies in the contact region `in_contact` (over the lattice).
fn marker_in_contact(shape: GridShape, track: &TrackFrame, in_contact: &[bool], k: usize) -> bool {
    track
        .markers
        .get(k)
        .and_then(|m| shape.linear(m.index))
        .and_then(|l| in_contact.get(l).copied())
        .unwrap_or(false)
}

impl Sink for OverlaySink {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        let out = frame.output;
        let (Some(images), Some(stages)) = (frame.images, &out.stages) else {
            return Ok(());
        };
        if !every(out.frame, self.every) {
            return Ok(());
        }
        let shape = frame.pipeline.shape();
        let views = match (stages, images) {
            (Stages::Stereo(st), Images::Stereo(pair)) => {
                let c = &st.contact.in_contact;
                vec![
                    OverlayView {
                        name: "left",
                        image: &pair.left,
                        markers: draw::overlay_markers(&out.reference_left_px, &st.left, &|k| {
                            marker_in_contact(shape, &st.left, c, k)
                        }),
                    },
                    OverlayView {
                        name: "right",
                        image: &pair.right,
                        markers: draw::overlay_markers(&out.reference_right_px, &st.right, &|k| {
                            marker_in_contact(shape, &st.right, c, k)
                        }),
                    },
                ]
            }
            (Stages::Mono(m), Images::Mono(image)) => {
                let c = &m.planar.in_contact;
                vec![OverlayView {
                    name: "camera",
                    image,
                    markers: draw::overlay_markers(&out.reference_left_px, &m.track, &|k| {
                        c.get(k).copied().unwrap_or(false)
                    }),
                }]
            }
            _ => return Ok(()),
        };
        let caption = draw::caption(&out.summary);
        self.folder
            .write_atomic(&format!("overlays/{:06}.png", out.frame), |path| {
                Ok(figures::overlay(path, &views, self.arrow_scale, &caption)?)
            })
    }
}

/// The figures of a run, written by [`Sink::finish`] from every frame seen: contact area, largest
/// depth (stereo) and slip state over time (`plots/*.png` and `.svg`, time axes in seconds); heat
/// maps of every Nth frame on one colour scale for the whole run (indentation depth for stereo,
/// displacement in the image for mono: `overlays/depth_NNNNNN.png` or
/// `overlays/displacement_NNNNNN.png`); the deepest frame's contact surface
/// (`plots/contact_surface.png` and `.svg`); for stereo, the force and the contact pressure over
/// time (`plots/force`, `plots/pressure`) and the pressure over the lattice in the frame of the
/// largest force (`plots/pressure_map`).
pub struct PlotSink {
    folder: Arc<OutputFolder>,
    stereo: bool,
    heat_every: usize,
    history: Vec<FrameSummary>,
    times_s: Vec<f64>,
    /// Per frame, the largest pressure on a marker's cell, kPa (`None` without the mechanics).
    peak_pressure_kpa: Vec<Option<f64>>,
    /// The frame of the largest normal force so far, its force and its pressures (row-major, kPa).
    most_loaded: Option<(u32, f64, Vec<f64>)>,
    shape: Option<GridShape>,
    /// Per heat-map frame, the values over the lattice (NaN unknown).
    heat: Vec<(u32, Vec<f32>)>,
    /// The frame of the largest indentation depth so far and its marker surface.
    deepest: Option<(u32, f64, figures::Surface)>,
}

impl PlotSink {
    /// Plots into `folder`; `stereo` adds the depth plot; a heat map every `heat_every` frames
    /// (0: none).
    pub fn new(folder: Arc<OutputFolder>, stereo: bool, heat_every: usize) -> Self {
        Self {
            folder,
            stereo,
            heat_every,
            history: Vec::new(),
            times_s: Vec::new(),
            peak_pressure_kpa: Vec::new(),
            most_loaded: None,
            shape: None,
            heat: Vec::new(),
            deepest: None,
        }
    }

    /// Keeps the frame's pressures: its peak, and the whole field if it carries the most force.
    fn keep_pressure(&mut self, out: &FrameOutput) {
        let Some(Stages::Stereo(st)) = &out.stages else {
            self.peak_pressure_kpa.push(None);
            return;
        };
        let pressure: Vec<f64> = st.contact.traction_kpa.iter().map(|t| t[2]).collect();
        self.peak_pressure_kpa
            .push(Some(pressure.iter().copied().fold(0.0, f64::max)));
        let force = st.contact.force_n;
        if force > 0.0 && self.most_loaded.as_ref().is_none_or(|(_, f, _)| *f < force) {
            self.most_loaded = Some((out.frame, force, pressure));
        }
    }

    fn keep(&mut self, out: &FrameOutput, shape: GridShape) {
        match &out.stages {
            Some(Stages::Stereo(st)) => {
                if every(out.frame, self.heat_every) {
                    let depth = st
                        .contact
                        .depth_mm
                        .iter()
                        .map(|d| d.map_or(f32::NAN, |d| d as f32));
                    self.heat.push((out.frame, depth.collect()));
                }
                let Some(depth) = out.summary.max_depth_mm.filter(|d| d.is_finite()) else {
                    return;
                };
                if self.deepest.as_ref().is_none_or(|(_, d, _)| *d < depth) {
                    self.deepest = Some((out.frame, depth, draw::surface(shape, &st.contact)));
                }
            }
            Some(Stages::Mono(m)) if every(out.frame, self.heat_every) => {
                // Displacement magnitude on the lattice, px.
                let mut mags = vec![f32::NAN; shape.count()];
                for (k, mk) in m.track.markers.iter().enumerate() {
                    if let (Some(p), Some(r), Some(l)) = (
                        mk.position_px,
                        out.reference_left_px.get(k),
                        shape.linear(mk.index),
                    ) {
                        mags[l] = p.distance(*r) as f32;
                    }
                }
                self.heat.push((out.frame, mags));
            }
            _ => {}
        }
    }

    fn time_series(&self) -> Result<()> {
        let h = &self.history;
        let frames: Vec<u32> = h.iter().map(|f| f.frame).collect();
        let timeline = Timeline::new(&frames, Some(&self.times_s));
        let area = TimeSeries {
            title: "contact area".into(),
            y_label: "contact area (mm²)".into(),
            timeline: timeline.clone(),
            curves: vec![Curve {
                name: "contact area".into(),
                values: h.iter().map(|f| f.contact_area_mm2).collect(),
            }],
            y_resolution: 0.1,
            unknown_note: "the marker pitch is not given (--pitch-mm)".into(),
        };
        let depth = TimeSeries {
            title: "largest indentation depth".into(),
            y_label: "depth (mm)".into(),
            curves: vec![Curve {
                name: "largest depth".into(),
                values: h.iter().map(|f| f.max_depth_mm).collect(),
            }],
            y_resolution: 0.01,
            unknown_note: "one camera measures no depth".into(),
            ..area.clone()
        };
        let force = TimeSeries {
            title: "force on the gel".into(),
            y_label: "force (N)".into(),
            curves: vec![
                Curve {
                    name: "normal".into(),
                    values: h.iter().map(|f| f.force_n).collect(),
                },
                Curve {
                    name: "shear".into(),
                    values: h.iter().map(|f| f.shear_n.map(|[x, y]| x.hypot(y))).collect(),
                },
            ],
            y_resolution: 0.001,
            unknown_note: "one camera gives no force".into(),
            ..area.clone()
        };
        let pressure = TimeSeries {
            title: "contact pressure".into(),
            y_label: "pressure (kPa)".into(),
            curves: vec![
                Curve {
                    name: "peak".into(),
                    values: self.peak_pressure_kpa.clone(),
                },
                Curve {
                    name: "mean (force / area)".into(),
                    values: h.iter().map(mean_pressure_kpa).collect(),
                },
            ],
            y_resolution: 0.1,
            unknown_note: "one camera gives no pressure".into(),
            ..area.clone()
        };
        let slip: Vec<_> = h.iter().map(|f| f.slip).collect();
        let f = &self.folder;
        for ext in ["png", "svg"] {
            f.write_atomic(&format!("plots/contact_area.{ext}"), |p| {
                Ok(figures::time_series(p, &area)?)
            })?;
            if self.stereo {
                f.write_atomic(&format!("plots/max_depth.{ext}"), |p| {
                    Ok(figures::time_series(p, &depth)?)
                })?;
                f.write_atomic(&format!("plots/force.{ext}"), |p| {
                    Ok(figures::time_series(p, &force)?)
                })?;
                f.write_atomic(&format!("plots/pressure.{ext}"), |p| {
                    Ok(figures::time_series(p, &pressure)?)
                })?;
            }
            f.write_atomic(&format!("plots/slip.{ext}"), |p| {
                Ok(figures::slip_timeline(p, "slip state", &timeline, &slip)?)
            })?;
        }
        Ok(())
    }

    /// The pressure over the lattice in the frame of the largest force, one cell per marker.
    fn pressure_map(&self, shape: GridShape) -> Result<()> {
        let Some((frame, force, pressure)) = &self.most_loaded else {
            return Ok(());
        };
        let scale = ColourScale::covering("contact pressure (kPa)", pressure.iter().copied(), 0.1);
        let field = figures::Field {
            width: usize::from(shape.cols),
            height: usize::from(shape.rows),
            values: pressure.clone(),
            x_extent: (0.0, f64::from(shape.cols.saturating_sub(1))),
            y_extent: (0.0, f64::from(shape.rows.saturating_sub(1))),
            axis_labels: ("marker column".into(), "marker row".into()),
        };
        let title = format!("pressure, frame {frame} (largest force, {force:.3} N)");
        for ext in ["png", "svg"] {
            self.folder
                .write_atomic(&format!("plots/pressure_map.{ext}"), |p| {
                    Ok(figures::heatmap(p, &title, &field, &scale)?)
                })?;
        }
        Ok(())
    }

    /// The heat maps and the contact surface on one colour scale (0 .. the run's largest value).
    fn heat_maps(&self, shape: GridShape) -> Result<()> {
        let (label, name, resolution) = if self.stereo {
            ("indentation depth (mm)", "depth", 0.01)
        } else {
            ("displacement (px)", "displacement", 0.5)
        };
        let deepest = self
            .deepest
            .iter()
            .flat_map(|(_, _, s)| s.depth_mm.iter().flatten().copied());
        let heat = self
            .heat
            .iter()
            .flat_map(|(_, v)| v.iter().map(|x| f64::from(*x)));
        let scale = ColourScale::covering(label, heat.chain(deepest), resolution);
        if let Some((frame, _, surface)) = &self.deepest {
            let title = format!("contact surface, frame {frame} (deepest)");
            for ext in ["png", "svg"] {
                self.folder
                    .write_atomic(&format!("plots/contact_surface.{ext}"), |p| {
                        Ok(figures::surface(p, &title, surface, &scale)?)
                    })?;
            }
        }
        for (frame, values) in &self.heat {
            let lattice: Vec<Option<f64>> = values
                .iter()
                .map(|v| v.is_finite().then_some(f64::from(*v)))
                .collect();
            let Some(dense) = interpolate(shape, &lattice, 8) else {
                continue;
            };
            let field = figures::Field {
                width: dense.width,
                height: dense.height,
                values: dense.values,
                x_extent: (0.0, f64::from(shape.cols.saturating_sub(1))),
                y_extent: (0.0, f64::from(shape.rows.saturating_sub(1))),
                axis_labels: ("marker column".into(), "marker row".into()),
            };
            self.folder
                .write_atomic(&format!("overlays/{name}_{frame:06}.png"), |p| {
                    Ok(figures::heatmap(
                        p,
                        &format!("frame {frame}: {name}"),
                        &field,
                        &scale,
                    )?)
                })?;
        }
        Ok(())
    }
}

impl Sink for PlotSink {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        let shape = frame.pipeline.shape();
        self.shape = Some(shape);
        self.keep(frame.output, shape);
        self.keep_pressure(frame.output);
        self.history.push(frame.output.summary.clone());
        self.times_s.push(frame.output.t_s);
        Ok(())
    }

    fn finish(&mut self) -> Result<()> {
        self.time_series()?;
        match self.shape {
            Some(shape) => {
                self.pressure_map(shape)?;
                self.heat_maps(shape)
            }
            None => Ok(()),
        }
    }
}

/// The mean contact pressure of a frame, kPa: its normal force over its contact area (0 without
/// contact, `None` without the contact mechanics).
fn mean_pressure_kpa(summary: &FrameSummary) -> Option<f64> {
    let (force, area) = (summary.force_n?, summary.contact_area_mm2?);
    // N / mm² is MPa.
    Some(if area > 0.0 { 1e3 * force / area } else { 0.0 })
}

/// Saves frames as a stereo recording on disk (`left/NNNNNN.png`, `right/NNNNNN.png`, or the
/// left view alone for mono frames) with their capture times in `times.csv` (`frame,t_s`):
/// `gelstereo capture`, for checkerboard images and for recordings to track later.
pub struct RecordingWriter {
    folder: Arc<OutputFolder>,
    times: File,
    times_path: std::path::PathBuf,
    written: usize,
    first_time_s: Option<f64>,
}

impl RecordingWriter {
    /// Writes into `folder`.
    pub fn create(folder: Arc<OutputFolder>) -> Result<Self> {
        let times_path = folder.claim("times.csv")?;
        let mut times = File::create(&times_path).map_err(file_err(&times_path))?;
        times.write_all(b"frame,t_s\n").map_err(file_err(&times_path))?;
        Ok(Self {
            folder,
            times,
            times_path,
            written: 0,
            first_time_s: None,
        })
    }

    /// Saves one frame captured at `time_s` (any origin); returns its frame number.
    pub fn write(&mut self, images: &Images, time_s: f64) -> Result<usize> {
        let k = self.written;
        let views: Vec<(&str, &opencv::core::Mat)> = match images {
            Images::Stereo(p) => vec![("left", &p.left), ("right", &p.right)],
            Images::Mono(m) => vec![("left", m)],
        };
        for (side, image) in views {
            self.folder.write_atomic(&format!("{side}/{k:06}.png"), |path| {
                Ok(images::write_image(path, image)?)
            })?;
        }
        let first = *self.first_time_s.get_or_insert(time_s);
        self.times
            .write_all(format!("{k},{:.6}\n", time_s - first).as_bytes())
            .map_err(file_err(&self.times_path))?;
        self.written += 1;
        Ok(k)
    }

    /// Frames saved so far.
    pub fn len(&self) -> usize {
        self.written
    }

    /// Whether no frame was saved yet.
    pub fn is_empty(&self) -> bool {
        self.written == 0
    }
}
