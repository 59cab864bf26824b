//! Sinks: where [`crate::FrameOutput`]s go. CSV tables ([`TableSink`]), JSON lines ([`JsonlSink`]),
//! PLY clouds and meshes ([`PlySink`]), overlays ([`OverlaySink`]) and plots ([`PlotSink`]), all
//! writing into an [`OutputFolder`] that records what it wrote.
//!
//! Each frame's table rows go out in one write each, markers before frames, and are flushed: an
//! interrupted run loses at most the frame in flight, and never leaves a cut line. Images and PLYs
//! are written to a temporary name and renamed, so none is ever cut either.

mod draw;
mod folder;

use std::fs::File;
use std::io::Write;
use std::sync::Arc;

use gelstereo_core::table::{FRAME_COLUMNS, MARKER_COLUMNS};
use gelstereo_core::{FrameSummary, MarkerRecord};
use gelstereo_io::images;
use gelstereo_tracking::interpolate;

pub use folder::{MANIFEST, OutputFolder};

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

/// The `frames.csv` row of a frame (no newline).
pub fn frames_csv_row(summary: &FrameSummary, t_s: f64, note: Option<&str>, out: &mut String) {
    summary.write_csv(out);
    out.push_str(&format!(",{t_s:.6},"));
    if let Some(n) = note {
        out.push('"');
        out.push_str(&n.replace('"', "\"\"").replace(['\n', '\r'], " "));
        out.push('"');
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

/// One JSON object per frame and line (the columns of both tables, markers nested, plus `t_s`
/// and `note`), flushed per frame: `gelstereo track --jsonl -`.
pub struct JsonlSink<W: Write> {
    out: W,
}

impl<W: Write> JsonlSink<W> {
    /// Writes to `out` (standard output, a file, ...).
    pub fn new(out: W) -> Self {
        Self { out }
    }
}

/// The JSON object of one frame.
pub fn frame_json(out: &FrameOutput) -> serde_json::Value {
    let s = &out.summary;
    let markers: Vec<serde_json::Value> = out.markers.iter().map(marker_json).collect();
    serde_json::json!({
        "frame": out.frame,
        "t_s": out.t_s,
        "contact": s.contact,
        "contact_area_mm2": s.contact_area_mm2,
        "max_depth_mm": s.max_depth_mm,
        "centroid_X_mm": s.centroid_mm.map(|c| c[0]),
        "centroid_Y_mm": s.centroid_mm.map(|c| c[1]),
        "slip": s.slip.as_str(),
        "note": out.note,
        "markers": markers,
    })
}

fn marker_json(m: &MarkerRecord) -> serde_json::Value {
    let xyz = |v: Option<[f64; 3]>, k: usize| v.map(|v| v[k]);
    serde_json::json!({
        "row": m.index.row,
        "col": m.index.col,
        "x_left": m.left_px.map(|p| p.x),
        "y_left": m.left_px.map(|p| p.y),
        "x_right": m.right_px.map(|p| p.x),
        "y_right": m.right_px.map(|p| p.y),
        "X_mm": xyz(m.position_mm, 0),
        "Y_mm": xyz(m.position_mm, 1),
        "Z_mm": xyz(m.position_mm, 2),
        "dX_mm": xyz(m.displacement_mm, 0),
        "dY_mm": xyz(m.displacement_mm, 1),
        "dZ_mm": xyz(m.displacement_mm, 2),
        "status": m.status.map(|s| s.as_str()),
    })
}

impl<W: Write> Sink for JsonlSink<W> {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        let mut line = frame_json(frame.output).to_string();
        line.push('\n');
        let stdout = std::path::Path::new("standard output");
        self.out
            .write_all(line.as_bytes())
            .and_then(|()| self.out.flush())
            .map_err(file_err(stdout))
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
}

impl PlySink {
    /// Writes every `every`th frame (0: none).
    pub fn new(folder: Arc<OutputFolder>, every: usize) -> Self {
        Self { folder, every }
    }
}

impl Sink for PlySink {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        let out = frame.output;
        let Some(Stages::Stereo(st)) = &out.stages else {
            return Ok(());
        };
        if !every(out.frame, self.every) {
            return Ok(());
        }
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
                )
            })
        })
    }
}

/// Overlays of every Nth frame: the left view with displacement arrows and the contact markers
/// (`overlays/NNNNNN.png`), and a colour map of the indentation depth (stereo,
/// `overlays/depth_NNNNNN.png`) or of the displacement (mono, `overlays/displacement_NNNNNN.png`).
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

    fn png(&self, name: &str, image: &opencv::core::Mat) -> Result<()> {
        self.folder
            .write_atomic(name, |path| Ok(images::write_image(path, image)?))
    }
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
        let n = out.frame;
        let shape = frame.pipeline.shape();
        let caption = draw::caption(&out.summary);
        let reference = &out.reference_left_px;
        match stages {
            Stages::Stereo(st) => {
                let lin: Vec<usize> = frame
                    .pipeline
                    .ids()
                    .iter()
                    .map(|i| shape.linear(*i).unwrap_or(0))
                    .collect();
                let in_contact = |k: usize| {
                    lin.get(k)
                        .and_then(|l| st.contact.in_contact.get(*l))
                        .copied()
                        .unwrap_or(false)
                };
                let img = draw::overlay(
                    images.left(),
                    reference,
                    &st.left,
                    &in_contact,
                    self.arrow_scale,
                    &caption,
                )?;
                self.png(&format!("overlays/{n:06}.png"), &img)?;
                if let Some(f) = interpolate(shape, &st.contact.depth_mm, 16) {
                    let title = format!("frame {n} indentation depth 0 .. {:.3} mm", f.range().1.max(0.0));
                    self.png(&format!("overlays/depth_{n:06}.png"), &draw::heatmap(&f, &title)?)?;
                }
            }
            Stages::Mono(m) => {
                let in_contact = |k: usize| m.planar.in_contact.get(k).copied().unwrap_or(false);
                let img = draw::overlay(
                    images.left(),
                    reference,
                    &m.track,
                    &in_contact,
                    self.arrow_scale,
                    &caption,
                )?;
                self.png(&format!("overlays/{n:06}.png"), &img)?;
                // Dense displacement magnitude on the lattice, px.
                let mut mags: Vec<Option<f64>> = vec![None; shape.count()];
                for (k, mk) in m.track.markers.iter().enumerate() {
                    if let (Some(p), Some(l), Some(r)) =
                        (mk.position_px, shape.linear(mk.index), reference.get(k))
                    {
                        mags[l] = Some(p.distance(*r));
                    }
                }
                if let Some(f) = interpolate(shape, &mags, 16) {
                    let title = format!("frame {n} displacement 0 .. {:.1} px", f.range().1);
                    self.png(
                        &format!("overlays/displacement_{n:06}.png"),
                        &draw::heatmap(&f, &title)?,
                    )?;
                }
            }
        }
        Ok(())
    }
}

/// Plots of the run (`plots/contact_area.png`, `plots/max_depth.png` for stereo, `plots/slip.png`),
/// written by [`Sink::finish`] from every frame seen.
pub struct PlotSink {
    folder: Arc<OutputFolder>,
    stereo: bool,
    history: Vec<FrameSummary>,
}

impl PlotSink {
    /// Plots into `folder`; `stereo` adds the depth plot.
    pub fn new(folder: Arc<OutputFolder>, stereo: bool) -> Self {
        Self {
            folder,
            stereo,
            history: Vec::new(),
        }
    }
}

impl Sink for PlotSink {
    fn frame(&mut self, frame: &FrameContext) -> Result<()> {
        self.history.push(frame.output.summary.clone());
        Ok(())
    }

    fn finish(&mut self) -> Result<()> {
        for (name, plot) in draw::run_plots(&self.history, self.stereo) {
            self.folder
                .write_atomic(name, |path| draw::write_plot(path, &plot))?;
        }
        Ok(())
    }
}
