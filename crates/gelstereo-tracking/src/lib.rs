//! Marker tracking over time, displacement fields, contact geometry and slip detection.
//!
//! - [`tracker`]: ids (grid indices from the reference frame) followed frame to frame in one view,
//!   with motion prediction, gated association on a bucket grid, neighbour-based prediction of
//!   missed markers and re-acquisition.
//! - [`slip`]: per-frame slip state from the 3-D field; [`planar`]: contact and slip of mono sensors.
//! - [`stereo`]: the stereo stages "track" ([`ViewTracking`]) and "triangulate" ([`Triangulation`]).
//! - [`session`]: whole recordings, stereo (the stages track -> triangulate -> contact -> slip) and
//!   mono, producing the `markers.csv` / `frames.csv` rows.
//! - [`field`]: dense interpolation of per-marker fields on the lattice (for plots).
//! - [`contact`]: the marker mesh, indentation depth, contact region, area, centroid, largest depth.
//! - [`stream`]: the per-frame rows and the gel frame as one JSON line per frame (`gelstereo track
//!   --jsonl`), written and read back.
//!
//! # Conventions
//! - Image coordinates in pixels of the original image, (0, 0) = centre of the top-left pixel,
//!   x right, y down.
//! - 3-D positions in mm in the LEFT camera's frame (x right, y down, z forward).
//! - Marker identity = grid index (row, col) on the reference frame of the left view; every list of
//!   markers comes in row-major id order.
//! - Indentation depth is positive when the gel surface is pushed towards the cameras.
//!
//! # Timing
//! [`StereoSession`] runs each stage of a frame in a `tracing` span (level TRACE, no fields): `track`,
//! `triangulate`, `outliers`, `contact`, `slip`. A benchmark times them with a subscriber of its own;
//! without a subscriber a span costs a level check.

pub mod contact;
pub mod error;
pub mod field;
mod fit;
pub mod planar;
pub mod session;
pub mod slip;
pub mod stereo;
pub mod stream;
#[cfg(test)]
mod synthetic;
pub mod tracker;

pub use contact::{ContactConfig, ContactFrame, GelFrame, ReferenceSurface};
pub use error::{Error, Result};
pub use field::{DenseField, interpolate};
pub use gelstereo_mechanics::Layer;
pub use planar::{PlanarConfig, PlanarDetector, PlanarFrame};
pub use session::{MonoFrame, MonoSession, SessionConfig, StereoFrame, StereoSession, flagged_rows};
pub use slip::{SlipConfig, SlipDetector, SlipFrame};
pub use stereo::{Points3, Triangulation, ViewTracking, ViewTracks};
pub use tracker::{TrackFrame, TrackedMarker, Tracker, TrackerConfig};
