//! One stereo frame to 3-D markers: indexing and pairing ([`StereoLattice`]) followed by
//! triangulation with the geometry crate's [`Triangulator`].

use gelstereo_core::{Detection, GridIndex, GridShape, MarkerRecord, Point2};
use gelstereo_geometry::{Rejection, StereoRig, TriangulationConfig, Triangulator};

use crate::Result;
use crate::stereo::{FrameMatch, StereoConfig, StereoLattice, StereoPrior};

/// Why a marker seen in both views has no 3-D position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MarkerRejection {
    /// The right point is farther than the bound from the left point's epipolar line (`None`: a
    /// point could not be undistorted).
    Epipolar {
        /// Distance, px.
        distance_px: Option<f64>,
    },
    /// The pair passed the epipolar check but triangulation rejected it (chirality, parallel rays,
    /// reprojection bound).
    Triangulation(Rejection),
}

impl std::fmt::Display for MarkerRejection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MarkerRejection::Epipolar { distance_px: Some(d) } => {
                write!(f, "right point {d:.2} px off the epipolar line")
            }
            MarkerRejection::Epipolar { distance_px: None } => write!(f, "a point cannot be undistorted"),
            MarkerRejection::Triangulation(r) => write!(f, "triangulation: {r}"),
        }
    }
}

/// One marker of a reconstructed frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReconstructedMarker {
    /// The marker.
    pub index: GridIndex,
    /// Position in the left view, px (when indexed there).
    pub left_px: Option<Point2>,
    /// Position in the right view, px (when indexed there and not rejected as a pair).
    pub right_px: Option<Point2>,
    /// Triangulated position in the left camera frame, mm.
    pub position_mm: Option<[f64; 3]>,
    /// The larger reprojection error of the two views, px (with `position_mm`).
    pub reprojection_error_px: Option<f64>,
    /// Why a marker indexed in both views was not triangulated.
    pub rejection: Option<MarkerRejection>,
}

impl ReconstructedMarker {
    /// The docs/design.md `markers.csv` row of this marker in `frame` (displacement and status empty).
    pub fn record(&self, frame: u32) -> MarkerRecord {
        MarkerRecord {
            frame,
            index: self.index,
            left_px: self.left_px,
            right_px: self.right_px,
            position_mm: self.position_mm,
            ..Default::default()
        }
    }
}

/// A reconstructed stereo frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameReconstruction {
    /// Indexing and pairing of both views.
    pub matched: FrameMatch,
    /// Every marker of the lattice, row-major (markers seen in neither view have no positions).
    pub markers: Vec<ReconstructedMarker>,
}

impl FrameReconstruction {
    /// Number of markers with a 3-D position.
    pub fn reconstructed_count(&self) -> usize {
        self.markers.iter().filter(|m| m.position_mm.is_some()).count()
    }
}

/// Indexes, pairs and triangulates stereo frames of one sensor against its reference frame.
#[derive(Debug, Clone)]
pub struct StereoReconstructor {
    lattice: StereoLattice,
    triangulator: Triangulator,
}

impl StereoReconstructor {
    /// Builds the reference lattices from the reference (no-contact) frame's detections
    /// ([`StereoLattice::from_reference`]) and the triangulator for `rig`.
    pub fn new(
        rig: &StereoRig,
        reference_left: &[Detection],
        reference_right: &[Detection],
        shape: GridShape,
        config: StereoConfig,
        triangulation: TriangulationConfig,
    ) -> Result<Self> {
        let triangulator = Triangulator::new(rig.clone(), triangulation)?;
        let lattice = StereoLattice::from_reference(rig, reference_left, reference_right, shape, config)?;
        Ok(Self {
            lattice,
            triangulator,
        })
    }

    /// The stereo lattice.
    pub fn lattice(&self) -> &StereoLattice {
        &self.lattice
    }

    /// The triangulator.
    pub fn triangulator(&self) -> &Triangulator {
        &self.triangulator
    }

    /// Reconstructs one frame; `prior` as in [`StereoLattice::match_frame`].
    pub fn reconstruct(
        &self,
        left: &[Detection],
        right: &[Detection],
        prior: Option<&StereoPrior>,
    ) -> Result<FrameReconstruction> {
        let matched = self.lattice.match_frame(left, right, prior)?;
        Ok(self.triangulate(matched))
    }

    /// Triangulates the pairs of an existing match.
    pub fn triangulate(&self, matched: FrameMatch) -> FrameReconstruction {
        let shape = self.lattice.left().shape();
        let mut markers: Vec<ReconstructedMarker> = shape
            .indices()
            .map(|index| ReconstructedMarker {
                index,
                left_px: matched.left.position(index),
                right_px: matched.right.position(index),
                position_mm: None,
                reprojection_error_px: None,
                rejection: None,
            })
            .collect();
        let slot = |index: GridIndex| shape.linear(index);
        for r in &matched.rejected {
            if let Some(i) = slot(r.index) {
                markers[i].right_px = None;
                markers[i].rejection = Some(MarkerRejection::Epipolar {
                    distance_px: r.epipolar_px,
                });
            }
        }
        for p in &matched.pairs {
            let Some(i) = slot(p.index) else { continue };
            match self.triangulator.triangulate(p.left_px, p.right_px) {
                Ok(t) => {
                    let q = t.p_in_left_mm;
                    markers[i].position_mm = Some([q.x, q.y, q.z]);
                    markers[i].reprojection_error_px = Some(t.max_reprojection_error_px());
                }
                Err(e) => markers[i].rejection = Some(MarkerRejection::Triangulation(e)),
            }
        }
        FrameReconstruction { matched, markers }
    }
}
