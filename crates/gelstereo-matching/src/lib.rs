//! Grid indexing: gives each detection its (row, col) on the reference lattice; pairs left and right
//! views by index under the epipolar constraint.
//!
//! # Conventions
//! - Image points in pixels of the original image, (0, 0) = centre of the top-left pixel.
//! - Marker identity = grid index (row, col) defined on the reference (first, no-contact) frame of
//!   the LEFT view: row grows with y, col with x, (0, 0) top-left. The marker at (r, c) in the left
//!   view is (r, c) in the right view too.
//! - Everything is deterministic: ties are broken by node and detection number, never by hash-map
//!   order.
//!
//! # Use
//! 1. Index each view's reference frame: [`ReferenceLattice::from_detections`] (a lattice fit with a
//!    known [`GridShape`]), or both views at once with
//!    [`StereoLattice::from_reference`], which also aligns the right view's identities to the left's
//!    with the epipolar geometry.
//! 2. Index every later frame: [`ReferenceLattice::index`] (one view, optionally with the previous
//!    frame's positions as prior) or [`StereoLattice::match_frame`] (both views, the right one gated
//!    by the epipolar constraint, then paired by index and checked).
//! 3. Or do all of it and triangulate with [`StereoReconstructor`], which yields the docs/design.md
//!    per-frame marker rows.
//!
//! See `docs/matching.md` for the method and its measured accuracy.

pub mod eval;
mod grow;
mod lattice;
mod reconstruct;
mod stereo;

pub use lattice::{GridPlacement, IndexedView, IndexingConfig, ReferenceLattice};
pub use reconstruct::{FrameReconstruction, MarkerRejection, ReconstructedMarker, StereoReconstructor};
pub use stereo::{
    EpipolarGeometry, FrameMatch, MatchedPair, PairRejection, StereoConfig, StereoLattice, StereoPlacement,
    StereoPrior, pair_by_index,
};

use gelstereo_core::GridShape;

/// Everything that can go wrong while indexing and pairing markers.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A configuration value is out of range.
    #[error("matching configuration: field '{field}': expected {expected}, found {found}")]
    Config {
        /// The field.
        field: &'static str,
        /// The valid range.
        expected: String,
        /// The value given.
        found: String,
    },
    /// A detection with a NaN or infinite coordinate.
    #[error("detection {detection}: position ({x}, {y}) px: expected finite coordinates")]
    NonFiniteDetection {
        /// Its number in the input.
        detection: usize,
        /// x, px.
        x: f64,
        /// y, px.
        y: f64,
    },
    /// A reference frame without any detection.
    #[error("reference frame: no detections: expected a view of the marker lattice")]
    EmptyView,
    /// No lattice structure could be found (too few detections, or no regular neighbours).
    #[error(
        "reference frame: no marker lattice found among {detections} detections: expected a regular grid \
         with at least 3 of 4 neighbours around a marker near the centre"
    )]
    NoLattice {
        /// Number of detections given.
        detections: usize,
    },
    /// The reference view shows fewer marker rows or columns than the lattice has.
    #[error(
        "reference frame: found {found_rows} rows x {found_cols} columns of markers, expected \
         {} x {}: the whole lattice must be visible in the reference frame so that (0, 0) is the top-left marker",
        expected.rows, expected.cols
    )]
    IncompleteGrid {
        /// The lattice shape asked for.
        expected: GridShape,
        /// Rows with at least one marker.
        found_rows: usize,
        /// Columns with at least one marker.
        found_cols: usize,
    },
    /// A partly visible lattice shows too few rows or columns to be indexed.
    #[error(
        "reference frame: only {found_rows} rows x {found_cols} columns of markers visible: expected at \
         least 3 x 3 to index a partly visible lattice"
    )]
    TooSmallVisible {
        /// Rows seen.
        found_rows: usize,
        /// Columns seen.
        found_cols: usize,
    },
    /// The visible markers do not fit the expected (sensor description's) lattice positions.
    #[error(
        "reference frame: only {agreeing} of {indexed} indexed markers agree on one grid offset with \
         the expected lattice positions (nearest node within half a pitch, {pitch_px:.1} px): expected \
         at least half; check that the sensor description and calibration belong to this recording"
    )]
    Placement {
        /// Markers agreeing with the best offset.
        agreeing: usize,
        /// Markers indexed.
        indexed: usize,
        /// Marker pitch, px.
        pitch_px: f64,
    },
    /// The reference frame shows too small a part of the lattice.
    #[error(
        "reference frame: indexed {found} of {expected} markers, expected at least {:.0}%",
        min_fraction * 100.0
    )]
    TooFewMarkers {
        /// Markers indexed.
        found: usize,
        /// Markers on the lattice.
        expected: usize,
        /// The configured minimum fraction.
        min_fraction: f64,
    },
    /// The indexed reference frame is not a regular lattice (noisy detections or a gel not at
    /// rest slipped the indexing by a row or column somewhere).
    #[error(
        "reference frame: {outliers} of {markers} indexed markers lie more than 0.35 pitch from a smooth \
         fit of the lattice and {broken_steps} of {steps} neighbour steps are broken: expected a regular \
         grid of markers at rest (detections too inaccurate, or contact in the reference frame?)"
    )]
    IrregularLattice {
        /// Markers off the fit.
        outliers: usize,
        /// Markers indexed.
        markers: usize,
        /// Neighbour steps that differ from the fit's by more than 0.7 pitch.
        broken_steps: usize,
        /// Neighbour steps checked.
        steps: usize,
    },
    /// A prior of the wrong length.
    #[error("prior: {found} positions, expected one per lattice node ({expected})")]
    PriorLength {
        /// Nodes on the lattice.
        expected: usize,
        /// Entries given.
        found: usize,
    },
    /// Lattices of different shapes were combined.
    #[error("lattice shapes differ: left {} x {}, right {} x {}", left.rows, left.cols, right.rows, right.cols)]
    ShapeMismatch {
        /// Left view's shape.
        left: GridShape,
        /// Right view's shape.
        right: GridShape,
    },
    /// The right view's lattice could not be aligned with the left's under the epipolar constraint.
    #[error("stereo alignment of the right view: {reason}")]
    StereoAlignment {
        /// What went wrong, with the figures.
        reason: String,
    },
    /// A ground-truth table could not be read (file, line, column and expectation named).
    #[error("ground truth: {0}")]
    Table(#[from] gelstereo_core::Error),
    /// The stereo geometry is unusable (invalid rig, degenerate baseline).
    #[error("stereo geometry: {0}")]
    Geometry(#[from] gelstereo_geometry::Error),
}

/// Result with this crate's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;
