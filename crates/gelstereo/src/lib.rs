//! gelstereo: the stereo visuotactile pipeline as one library, the crate a robot program depends on.
//!
//! - [`Pipeline`]: built once from a [`PipelineConfig`] (calibration, models, sensor), then
//!   [`Pipeline::process`] per [`Frame`] gives a [`FrameOutput`]: per marker its grid id, status,
//!   position in each view, 3-D position and displacement; contact area, depth, centroid and region;
//!   the slip state; the timestamp. It carries every fallback of `gelstereo track`: the reference
//!   frame is the first that can be indexed, a grid that overfills the view is indexed on its visible
//!   part, unreadable frames come back flagged, [`Pipeline::rezero`] corrects drift.
//! - [`source`]: frames from recordings, image folders, videos, side-by-side or two cameras, with
//!   timestamps, optionally decoded ahead on a thread of their own ([`source::Prefetch`]).
//! - [`sink`]: CSV tables, JSON lines, PLY clouds and meshes, overlays and plots, into an output
//!   folder that records what it wrote ([`sink::OutputFolder`]).
//! - [`track`]: source -> pipeline -> sinks, what `gelstereo track` runs.
//! - [`gel`]: the gel's facts (thickness, modulus, Poisson ratio) from a gel file or the sensor.
//! - [`models`]: where the shipped models are, in a checkout, an installed package or binary.
//!
//! The applications over the pipeline (benchmarks, adaptation, calibration, `doctor`, evaluation,
//! reconstruction jobs) are the crate `gelstereo-apps`.
//!
//! ```no_run
//! use gelstereo::{Pipeline, PipelineConfig, source::FrameSource};
//! let dir = std::path::Path::new("data/sample/press-slide");
//! let mut pipeline = Pipeline::new(&PipelineConfig::for_recording(dir)?)?;
//! for frame in FrameSource::open_path(dir, false)? {
//!     let out = pipeline.process(&frame.into_frame()?)?;
//!     println!("{:.3} s: {} markers, {}", out.t_s, out.markers.len(), out.slip().as_str());
//! }
//! # Ok::<(), gelstereo::Error>(())
//! ```
//!
//! # Conventions
//! Pixels of the original image, (0, 0) the centre of the top-left pixel, x right, y down; 3-D in mm
//! in the left camera's frame (x right, y down, z forward); marker id = grid (row, col) on the left
//! view's reference frame; times in s.

mod config;
mod error;
pub mod gel;
pub mod models;
mod pipeline;
pub mod sink;
pub mod source;
mod start;
pub mod track;

pub use config::{GelFacts, PipelineConfig, localizer, parse_grid, project_home};
pub use error::{Error, Result, file_err};
pub use gelstereo_sensor::RecordingMeta;
pub use gelstereo_tracking::GelFrame;
pub use pipeline::{
    Frame, FrameLocalizer, FrameOutput, Images, Pipeline, Stages, image_size, join_rayon_pool,
};

pub use gelstereo_core as core;
pub use gelstereo_geometry as geometry;
pub use gelstereo_io as io;
pub use gelstereo_markers as markers;
pub use gelstereo_matching as matching;
pub use gelstereo_sensor as sensor;
pub use gelstereo_sim as sim;
pub use gelstereo_tracking as tracking;

pub use gelstereo_core::{FrameSummary, GridIndex, GridShape, MarkerRecord, MarkerStatus, SlipState};
pub use gelstereo_markers::{LocalizerConfig, Method};

#[cfg(test)]
mod tests {
    /// The reference sensor's file (`calib/reference-sensor.json`) describes the gel the pipeline
    /// assumes by default.
    #[test]
    fn the_simulated_and_the_assumed_reference_gel_agree() {
        let gel = gelstereo_sensor::SensorSpec::reference().gel;
        assert_eq!(gel.layer(), gelstereo_tracking::ContactConfig::default().layer);
    }
}
