//! Left/right identities and pairs: the right view's lattice aligned to the left's by the epipolar
//! constraint, per-frame indexing of the right view gated by it, and pairing by index.
//!
//! The epipolar constraint is used rectification-free: both points are undistorted to normalised
//! coordinates with the calibrated distortion model, and the distance of the right point to the
//! epipolar line `E x_left` (`E = [t]x R` from `right_from_left`) is measured in pixels of the
//! undistorted right image.

use gelstereo_core::{Detection, GridIndex, GridShape, Point2};
use gelstereo_geometry::{StereoRig, TriangulationConfig, Triangulator};
use nalgebra::{Matrix3, Vector2, Vector3};

use crate::grow::NONE;
use crate::lattice::{
    GridPlacement, IndexedView, IndexingConfig, ReferenceLattice, ScratchLattice, best_window,
    grow_from_scratch, median, placed_assignment,
};
use crate::{Error, Result};

/// The epipolar geometry of a calibrated rig, for distances of right points to left points'
/// epipolar lines.
#[derive(Debug, Clone)]
pub struct EpipolarGeometry {
    rig: StereoRig,
    essential: Matrix3<f64>,
}

impl EpipolarGeometry {
    /// The epipolar geometry of `rig` (checked: finite intrinsics and extrinsics, non-zero baseline).
    pub fn new(rig: &StereoRig) -> Result<Self> {
        rig.validate()?;
        let t = rig.right_from_left.translation.vector;
        let r = rig.right_from_left.rotation.to_rotation_matrix().into_inner();
        let essential = t.cross_matrix() * r;
        Ok(Self {
            rig: rig.clone(),
            essential,
        })
    }

    /// The rig.
    pub fn rig(&self) -> &StereoRig {
        &self.rig
    }

    /// The epipolar line of left pixel `left_px` in the right view's normalised coordinates
    /// (`l . (x, y, 1) = 0`); `None` when the point cannot be undistorted.
    pub fn line_of_left(&self, left_px: Point2) -> Option<Vector3<f64>> {
        let x = self.rig.left.undistort(left_px)?;
        let l = self.essential * Vector3::new(x.x, x.y, 1.0);
        (l.x.is_finite() && l.y.is_finite() && l.z.is_finite() && (l.x != 0.0 || l.y != 0.0)).then_some(l)
    }

    /// Normalised coordinates of right pixel `right_px`.
    pub fn undistort_right(&self, right_px: Point2) -> Option<Vector2<f64>> {
        self.rig.right.undistort(right_px)
    }

    /// Distance, in px of the undistorted right image, of normalised right point `x` to `line`.
    pub fn line_distance_px(&self, line: &Vector3<f64>, x: &Vector2<f64>) -> f64 {
        let num = (line.x * x.x + line.y * x.y + line.z).abs();
        let (a, b) = (line.x / self.rig.right.fx, line.y / self.rig.right.fy);
        num / (a * a + b * b).sqrt()
    }

    /// Distance, px, of `right_px` to the epipolar line of `left_px`; `None` when either point
    /// cannot be undistorted.
    pub fn distance_px(&self, left_px: Point2, right_px: Point2) -> Option<f64> {
        let l = self.line_of_left(left_px)?;
        let x = self.undistort_right(right_px)?;
        Some(self.line_distance_px(&l, &x))
    }
}

/// Tuning of the stereo matcher.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoConfig {
    /// A pair is accepted when the right point lies within this distance of the left point's
    /// epipolar line, px. Default 3.0: in line with the triangulator's default bound of 2 px of
    /// reprojection error per view (which allows up to ~4 px of epipolar distance), so correct but
    /// noisy detections (1-2.5 px off, as a pilot Marknet at the image edges or blobs under contact)
    /// are kept, and far below the offset of a neighbouring row's marker (about a pitch, 14-30 px).
    /// A tighter bound drops correct pairs without removing wrong ones (docs/matching.md).
    pub max_epipolar_px: f64,
    /// Indexing of each view.
    pub indexing: IndexingConfig,
}

impl StereoConfig {
    /// `max_epipolar_px` must be a distance > 0 px.
    fn check_epipolar(&self) -> Result<()> {
        if self.max_epipolar_px.is_finite() && self.max_epipolar_px > 0.0 {
            return Ok(());
        }
        Err(Error::Config {
            field: "max_epipolar_px",
            expected: "a distance > 0 px".into(),
            found: self.max_epipolar_px.to_string(),
        })
    }
}

impl Default for StereoConfig {
    fn default() -> Self {
        Self {
            max_epipolar_px: 3.0,
            indexing: IndexingConfig::default(),
        }
    }
}

/// Expected positions per node of both views (row-major), e.g. the previous frame's.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct StereoPrior {
    /// Left view.
    pub left: Vec<Option<Point2>>,
    /// Right view.
    pub right: Vec<Option<Point2>>,
}

/// A left/right pair of one marker that passed the epipolar check.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatchedPair {
    /// The marker.
    pub index: GridIndex,
    /// Left view position, px.
    pub left_px: Point2,
    /// Right view position, px.
    pub right_px: Point2,
    /// Distance of the right point to the left point's epipolar line, px.
    pub epipolar_px: f64,
}

/// A marker indexed in both views whose pair failed the epipolar check.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairRejection {
    /// The marker.
    pub index: GridIndex,
    /// Left view position, px.
    pub left_px: Point2,
    /// Right view position, px.
    pub right_px: Point2,
    /// Epipolar distance, px; `None` when a point could not be undistorted.
    pub epipolar_px: Option<f64>,
}

/// Both views of one frame indexed and paired.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMatch {
    /// The left view's indexing.
    pub left: IndexedView,
    /// The right view's indexing (same identities as the left).
    pub right: IndexedView,
    /// Accepted pairs, row-major.
    pub pairs: Vec<MatchedPair>,
    /// Markers indexed in both views whose pair failed the epipolar check, row-major.
    pub rejected: Vec<PairRejection>,
}

impl FrameMatch {
    /// Positions of this frame as the prior of the next.
    pub fn to_prior(&self) -> StereoPrior {
        StereoPrior {
            left: self.left.node_positions(),
            right: self.right.node_positions(),
        }
    }
}

/// Pairs two indexed views by index and checks each pair against the epipolar constraint
/// (`max_epipolar_px`). Pairs come out row-major.
pub fn pair_by_index(
    left: &IndexedView,
    right: &IndexedView,
    epipolar: &EpipolarGeometry,
    max_epipolar_px: f64,
) -> Result<(Vec<MatchedPair>, Vec<PairRejection>)> {
    if left.shape() != right.shape() {
        return Err(Error::ShapeMismatch {
            left: left.shape(),
            right: right.shape(),
        });
    }
    let mut pairs = Vec::new();
    let mut rejected = Vec::new();
    for (index, left_px) in left.markers() {
        let Some(right_px) = right.position(index) else {
            continue;
        };
        match epipolar.distance_px(left_px, right_px) {
            Some(e) if e <= max_epipolar_px => pairs.push(MatchedPair {
                index,
                left_px,
                right_px,
                epipolar_px: e,
            }),
            e => rejected.push(PairRejection {
                index,
                left_px,
                right_px,
                epipolar_px: e,
            }),
        }
    }
    Ok((pairs, rejected))
}

/// Where both views' markers sit on the whole grid ([`StereoLattice::from_reference_placed`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StereoPlacement {
    /// The left view's placement (defines the ids).
    pub left: GridPlacement,
    /// The right view's.
    pub right: GridPlacement,
    /// Markers placed in both views.
    pub paired: usize,
    /// Of those, pairs within `max_epipolar_px` (the others are dropped from the right view).
    pub within_epipolar: usize,
}

/// The reference lattices of both views with aligned identities, and the stereo geometry.
#[derive(Debug, Clone)]
pub struct StereoLattice {
    left: ReferenceLattice,
    right: ReferenceLattice,
    epipolar: EpipolarGeometry,
    config: StereoConfig,
}

impl StereoLattice {
    /// Indexes the reference (no-contact) frame of both views. The left view defines the
    /// identities ([`ReferenceLattice::from_detections`]); the right view's lattice is grown from
    /// scratch and then shifted by the whole number of rows and columns that puts the most right
    /// markers within `max_epipolar_px` of the epipolar lines of their left namesakes. When the
    /// epipolar lines run along the grid rows, column shifts are not told apart by the constraint;
    /// then the right lattice's own extent decides if the right view shows the whole lattice, and
    /// the alignment fails otherwise.
    pub fn from_reference(
        rig: &StereoRig,
        left: &[Detection],
        right: &[Detection],
        shape: GridShape,
        config: StereoConfig,
    ) -> Result<Self> {
        Self::from_reference_with(rig, left, right, shape, config, (true, true), None)
    }

    /// [`from_reference`](Self::from_reference) for a view that shows only the visible part of a
    /// larger grid, `shape` = [`ReferenceLattice::visible_shape`] of the left view, of the sensor's
    /// `full` grid: the visible top-left marker is (0, 0). The right view's own extent only decides
    /// a column (row) offset that the epipolar constraint leaves open where both views can show
    /// every column (row) of the sensor (`shape` has all of `full`'s). Otherwise, with the marker
    /// pitch `pitch_mm` known, the offset whose triangulated reference lattice has the median
    /// neighbour spacing nearest the pitch decides (a wrong column offset changes the disparity by
    /// a pitch and so the depth and the spacing), when it is within 5 % of the pitch and every
    /// other offset at least 5 % farther; else the alignment fails with a named error.
    pub fn from_visible_reference(
        rig: &StereoRig,
        left: &[Detection],
        right: &[Detection],
        shape: GridShape,
        full: GridShape,
        pitch_mm: Option<f64>,
        config: StereoConfig,
    ) -> Result<Self> {
        Self::from_reference_with(
            rig,
            left,
            right,
            shape,
            config,
            (shape.rows >= full.rows, shape.cols >= full.cols),
            pitch_mm,
        )
    }

    /// Indexes the reference frame of both views on the whole `shape` grid where a view may show
    /// only part of it: each view's markers are placed by `expected` (every node's rest position
    /// per view, row-major, e.g. the sensor description's lattice projected through the
    /// calibration: [`ReferenceLattice::from_detections_placed`]), so ids are the sensor's grid
    /// indices and the left/right offset follows. Right markers off their left namesakes' epipolar
    /// lines are dropped; the alignment fails when fewer than half of the markers indexed in both
    /// views pair within `max_epipolar_px` (a description of another sensor).
    pub fn from_reference_placed(
        rig: &StereoRig,
        left: &[Detection],
        right: &[Detection],
        shape: GridShape,
        expected: (&[Option<Point2>], &[Option<Point2>]),
        config: StereoConfig,
    ) -> Result<(Self, StereoPlacement)> {
        config.check_epipolar()?;
        let epipolar = EpipolarGeometry::new(rig)?;
        let (left_lattice, left_place) =
            ReferenceLattice::from_detections_placed(left, shape, expected.0, config.indexing.clone())?;
        require_right_detections(right)?;
        let mut a = placed_assignment(right, shape, expected.1, &config.indexing)?;
        let (mut paired, mut within) = (0usize, 0usize);
        for (n, idx) in shape.indices().enumerate() {
            let d = a.node_det[n];
            if d == NONE || !left_lattice.observed(idx) {
                continue;
            }
            paired += 1;
            let e = left_lattice
                .node_position(idx)
                .and_then(|l| epipolar.distance_px(l, a.points[d as usize]));
            if e.is_some_and(|e| e <= config.max_epipolar_px) {
                within += 1;
            } else {
                a.node_det[n] = NONE;
            }
        }
        if within * 2 < paired || paired == 0 {
            return Err(Error::StereoAlignment {
                reason: format!(
                    "{within} of {paired} markers placed on the grid in both views lie within {} px of their \
                     left namesakes' epipolar lines: expected at least half; check that the sensor description \
                     and the calibration belong to this recording",
                    config.max_epipolar_px
                ),
            });
        }
        let right_lattice = ReferenceLattice::from_assignment_of(
            a.points,
            shape,
            &a.node_det,
            a.pitch_px,
            config.indexing.clone(),
            a.nodes_in_view,
        )?;
        let placement = StereoPlacement {
            left: left_place,
            right: a.placement,
            paired,
            within_epipolar: within,
        };
        Ok((
            Self {
                left: left_lattice,
                right: right_lattice,
                epipolar,
                config,
            },
            placement,
        ))
    }

    fn from_reference_with(
        rig: &StereoRig,
        left: &[Detection],
        right: &[Detection],
        shape: GridShape,
        config: StereoConfig,
        extent_decides: (bool, bool),
        pitch_mm: Option<f64>,
    ) -> Result<Self> {
        config.check_epipolar()?;
        let epipolar = EpipolarGeometry::new(rig)?;
        let left_lattice = ReferenceLattice::from_detections(left, shape, config.indexing.clone())?;
        require_right_detections(right)?;
        let points = finite_right_points(right)?;
        let scratch = grow_from_scratch(&points, shape, &config.indexing)?;
        let Some(extent) = scratch.extent() else {
            return Err(Error::StereoAlignment {
                reason: "no lattice found in the right view".into(),
            });
        };
        let search = OffsetSearch::new(
            &epipolar,
            &left_lattice,
            &points,
            &scratch,
            shape,
            config.max_epipolar_px,
            extent_decides != (true, true),
        );
        let scored = search.scored_offsets(extent);
        let best = scored[0];
        search.require_half_within(best)?;
        let rivals: Vec<(i64, i64)> = scored
            .iter()
            .filter(|s| s.0 * 10 >= best.0 * 9)
            .map(|s| (s.1, s.2))
            .collect();
        let (r0, c0) = if rivals.len() == 1 {
            (best.1, best.2)
        } else {
            search.settle_rivals(rig, &rivals, best, extent, extent_decides, pitch_mm)?
        };
        let node_det = search.node_assignment(r0, c0);
        let in_window = search.nodes_in_window(r0, c0);
        let right_lattice = ReferenceLattice::from_assignment_of(
            points,
            shape,
            &node_det,
            scratch.pitch_px,
            config.indexing.clone(),
            in_window,
        )?;
        Ok(Self {
            left: left_lattice,
            right: right_lattice,
            epipolar,
            config,
        })
    }

    /// The left view's reference lattice (defines the identities).
    pub fn left(&self) -> &ReferenceLattice {
        &self.left
    }

    /// The right view's reference lattice, aligned to the left's identities.
    pub fn right(&self) -> &ReferenceLattice {
        &self.right
    }

    /// The epipolar geometry.
    pub fn epipolar(&self) -> &EpipolarGeometry {
        &self.epipolar
    }

    /// The configuration.
    pub fn config(&self) -> &StereoConfig {
        &self.config
    }

    /// The reference frame's own match (its indexed views, paired and checked).
    pub fn reference_match(&self) -> Result<FrameMatch> {
        let (left, right) = (
            self.left.reference_view().clone(),
            self.right.reference_view().clone(),
        );
        let (pairs, rejected) = pair_by_index(&left, &right, &self.epipolar, self.config.max_epipolar_px)?;
        Ok(FrameMatch {
            left,
            right,
            pairs,
            rejected,
        })
    }

    /// Indexes and pairs one stereo frame. The left view is indexed against the left reference
    /// lattice; the right view against the right one, where a detection is only admitted for a
    /// marker indexed in the left view if it lies within `max_epipolar_px` of that marker's
    /// epipolar line. Every pair is then checked again ([`pair_by_index`]).
    pub fn match_frame(
        &self,
        left: &[Detection],
        right: &[Detection],
        prior: Option<&StereoPrior>,
    ) -> Result<FrameMatch> {
        let left_view = self.left.index(left, prior.map(|p| p.left.as_slice()))?;
        let w = usize::from(self.left.shape().cols);
        let lines: Vec<Option<Vector3<f64>>> = left_view
            .node_positions()
            .iter()
            .map(|p| p.and_then(|p| self.epipolar.line_of_left(p)))
            .collect();
        let right_norm: Vec<Option<Vector2<f64>>> = right
            .iter()
            .map(|d| self.epipolar.undistort_right(d.position))
            .collect();
        let tol = self.config.max_epipolar_px;
        let right_view = self
            .right
            .index_with(right, prior.map(|p| p.right.as_slice()), |idx, d| {
                let n = usize::from(idx.row) * w + usize::from(idx.col);
                match (&lines[n], &right_norm[d]) {
                    (Some(l), Some(x)) => self.epipolar.line_distance_px(l, x) <= tol,
                    (Some(_), None) => false,
                    (None, _) => true,
                }
            })?;
        // Pair by index, reusing the lines and undistorted points computed above.
        let (pairs, rejected) = {
            let mut pairs = Vec::new();
            let mut rejected = Vec::new();
            for (index, left_px) in left_view.markers() {
                let Some(rd) = right_view.detection_at(index) else {
                    continue;
                };
                let right_px = right[rd].position;
                let n = usize::from(index.row) * w + usize::from(index.col);
                let e = match (&lines[n], &right_norm[rd]) {
                    (Some(l), Some(x)) => Some(self.epipolar.line_distance_px(l, x)),
                    _ => None,
                };
                match e {
                    Some(e) if e <= tol => pairs.push(MatchedPair {
                        index,
                        left_px,
                        right_px,
                        epipolar_px: e,
                    }),
                    e => rejected.push(PairRejection {
                        index,
                        left_px,
                        right_px,
                        epipolar_px: e,
                    }),
                }
            }
            (pairs, rejected)
        };
        Ok(FrameMatch {
            left: left_view,
            right: right_view,
            pairs,
            rejected,
        })
    }
}

/// The right view's reference frame must show markers to be aligned with the left's (both
/// reference constructors start with this check).
fn require_right_detections(right: &[Detection]) -> Result<()> {
    if right.is_empty() {
        return Err(Error::StereoAlignment {
            reason: "the right reference frame has no detections".into(),
        });
    }
    Ok(())
}

/// The right reference frame's marker positions, refused when one is not finite (a non-finite
/// position would poison every distance the alignment measures).
fn finite_right_points(right: &[Detection]) -> Result<Vec<Point2>> {
    let points: Vec<Point2> = right.iter().map(|d| d.position).collect();
    if let Some(i) = points.iter().position(|p| !(p.x.is_finite() && p.y.is_finite())) {
        return Err(Error::NonFiniteDetection {
            detection: i,
            x: points[i].x,
            y: points[i].y,
        });
    }
    Ok(points)
}

/// The search for the row/column offset that places the right view's scratch lattice on the
/// left reference lattice: everything each candidate offset is scored against, computed once.
struct OffsetSearch<'a> {
    epipolar: &'a EpipolarGeometry,
    left: &'a ReferenceLattice,
    points: &'a [Point2],
    scratch: &'a ScratchLattice,
    /// Reference grid rows and columns.
    h: usize,
    w: usize,
    max_epipolar_px: f64,
    /// Epipolar line per reference node where the left view observed its marker.
    lines: Vec<Option<Vector3<f64>>>,
    /// Undistorted right points (None where undistortion failed).
    right_norm: Vec<Option<Vector2<f64>>>,
    /// (provisional row, provisional column, detection) of every assigned scratch node.
    assigned: Vec<(i64, i64, usize)>,
    /// The grid is cut off by the view in some direction (see [`OffsetSearch::score`]).
    cut: bool,
    /// Least overlap a cut grid's offset needs to be scored at all.
    min_overlap: usize,
}

impl<'a> OffsetSearch<'a> {
    /// Epipolar lines of the observed left reference markers, undistorted right points and the
    /// assigned scratch nodes.
    fn new(
        epipolar: &'a EpipolarGeometry,
        left: &'a ReferenceLattice,
        points: &'a [Point2],
        scratch: &'a ScratchLattice,
        shape: GridShape,
        max_epipolar_px: f64,
        cut: bool,
    ) -> Self {
        let lines: Vec<Option<Vector3<f64>>> = shape
            .indices()
            .map(|idx| {
                left.observed(idx)
                    .then(|| left.node_position(idx))
                    .flatten()
                    .and_then(|p| epipolar.line_of_left(p))
            })
            .collect();
        let right_norm: Vec<Option<Vector2<f64>>> =
            points.iter().map(|&p| epipolar.undistort_right(p)).collect();
        let assigned: Vec<(i64, i64, usize)> = scratch
            .node_det
            .iter()
            .enumerate()
            .filter(|(_, d)| **d != NONE)
            .map(|(n, &d)| ((n / scratch.cols) as i64, (n % scratch.cols) as i64, d as usize))
            .collect();
        let min_overlap = (assigned.len().min(lines.iter().flatten().count()) / 4).max(6);
        Self {
            epipolar,
            left,
            points,
            scratch,
            h: usize::from(shape.rows),
            w: usize::from(shape.cols),
            max_epipolar_px,
            lines,
            right_norm,
            assigned,
            cut,
            min_overlap,
        }
    }

    /// The reference node (row-major) a provisional node lands on under offset `(r0, c0)`, if
    /// inside the grid.
    fn node_under(&self, r: i64, c: i64, r0: i64, c0: i64) -> Option<(i64, i64)> {
        let (gr, gc) = (r - r0, c - c0);
        let outside = gr < 0 || gc < 0 || gr >= self.h as i64 || gc >= self.w as i64;
        (!outside).then_some((gr, gc))
    }

    /// Per offset: right markers on an observed left node, and of those the ones within the
    /// epipolar bound.
    fn fit(&self, r0: i64, c0: i64) -> (usize, usize) {
        let (mut overlap, mut within) = (0usize, 0usize);
        for &(r, c, d) in &self.assigned {
            let Some((gr, gc)) = self.node_under(r, c, r0, c0) else {
                continue;
            };
            if let Some(l) = &self.lines[gr as usize * self.w + gc as usize] {
                overlap += 1;
                if self.right_norm[d]
                    .is_some_and(|x| self.epipolar.line_distance_px(l, &x) <= self.max_epipolar_px)
                {
                    within += 1;
                }
            }
        }
        (overlap, within)
    }

    /// A grid cut off by the view: the views overlap more under some wrong column offsets than
    /// under the true one, so an offset scores the share of its overlap that fits (in 1/1000,
    /// over at least a quarter of the markers), not the count.
    fn score(&self, r0: i64, c0: i64) -> usize {
        let (overlap, within) = self.fit(r0, c0);
        match self.cut {
            false => within,
            true if overlap >= self.min_overlap => within * 1000 / overlap,
            true => 0,
        }
    }

    /// Every offset that keeps the scratch extent overlapping the grid, as (score, row offset,
    /// column offset): highest score first, lowest offsets among equals (deterministic).
    fn scored_offsets(&self, extent: (usize, usize, usize, usize)) -> Vec<(usize, i64, i64)> {
        let (rmin, rmax, cmin, cmax) = extent;
        let (h, w) = (self.h, self.w);
        let mut scored = Vec::new();
        for r0 in rmin as i64 - h as i64 + 1..=rmax as i64 {
            for c0 in cmin as i64 - w as i64 + 1..=cmax as i64 {
                scored.push((self.score(r0, c0), r0, c0));
            }
        }
        scored.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        scored
    }

    /// Refuses the alignment when even the best offset fits fewer than half the markers it
    /// could: the calibration most likely belongs to another sensor.
    fn require_half_within(&self, best: (usize, i64, i64)) -> Result<()> {
        let possible = if self.cut {
            1000
        } else {
            self.assigned.len().min(self.lines.iter().flatten().count())
        };
        if best.0 * 2 < possible {
            let (_, within) = self.fit(best.1, best.2);
            return Err(Error::StereoAlignment {
                reason: format!(
                    "at best {} of {} right markers lie within {} px of their left namesakes' epipolar \
                     lines: expected at least half; check that the calibration belongs to this sensor",
                    within,
                    self.assigned.len(),
                    self.max_epipolar_px
                ),
            });
        }
        Ok(())
    }

    /// Chooses among offsets that fit about equally well. The window of the right lattice's own
    /// rows and columns that holds the most markers (a stray row of dust beside the lattice does
    /// not move it) decides when every one of its rows and columns is occupied. Per direction: an
    /// offset all rivals share stands; else the window decides where allowed (`extent_decides`:
    /// not for a direction in which the sensor's grid overfills the view, where the windows say
    /// nothing). Failing that, the triangulated spacing against the known pitch decides.
    fn settle_rivals(
        &self,
        rig: &StereoRig,
        rivals: &[(i64, i64)],
        best: (usize, i64, i64),
        extent: (usize, usize, usize, usize),
        extent_decides: (bool, bool),
        pitch_mm: Option<f64>,
    ) -> Result<(i64, i64)> {
        let (h, w) = (self.h, self.w);
        let (row_counts, col_counts) = self.scratch.counts();
        let (wr, wc) = (best_window(&row_counts, h), best_window(&col_counts, w));
        let rows_full = extent_decides.0 && !row_counts[wr..wr + h].contains(&0);
        let cols_full = extent_decides.1 && !col_counts[wc..wc + w].contains(&0);
        let shared = |of: fn(&(i64, i64)) -> i64| {
            let v = of(&rivals[0]);
            rivals.iter().all(|r| of(r) == v).then_some(v)
        };
        let r = shared(|r| r.0).or(rows_full.then_some(wr as i64));
        let c = shared(|r| r.1).or(cols_full.then_some(wc as i64));
        let spacing_errors: Vec<((i64, i64), f64)> = match pitch_mm {
            Some(p) if r.zip(c).filter(|rc| rivals.contains(rc)).is_none() => {
                let tri = Triangulator::new(rig.clone(), TriangulationConfig::default())?;
                rivals
                    .iter()
                    .map(|&(r0, c0)| ((r0, c0), self.spacing_error(&tri, r0, c0, p)))
                    .collect()
            }
            _ => Vec::new(),
        };
        let by_pitch = spacing_errors
            .iter()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .filter(|best| {
                best.1 <= 0.05
                    && spacing_errors
                        .iter()
                        .all(|o| o.0 == best.0 || o.1 >= best.1 + 0.05)
            })
            .map(|best| best.0);
        if let Some(by_extent) = r.zip(c).filter(|rc| rivals.contains(rc)) {
            Ok(by_extent)
        } else if let Some(by_pitch) = by_pitch {
            Ok(by_pitch)
        } else {
            Err(self.ambiguity_error(rivals, best, extent, pitch_mm, &spacing_errors))
        }
    }

    /// The metric cue: relative error of the triangulated median neighbour spacing against the
    /// known pitch `p` under offset `(r0, c0)` (infinite where no neighbours triangulate).
    fn spacing_error(&self, tri: &Triangulator, r0: i64, c0: i64, p: f64) -> f64 {
        let (h, w) = (self.h, self.w);
        let mut at: Vec<Option<nalgebra::Point3<f64>>> = vec![None; h * w];
        for &(r, c, d) in &self.assigned {
            let Some((gr, gc)) = self.node_under(r, c, r0, c0) else {
                continue;
            };
            let idx = GridIndex::new(gr as u16, gc as u16);
            if let Some(l) = self
                .left
                .observed(idx)
                .then(|| self.left.node_position(idx))
                .flatten()
            {
                at[gr as usize * w + gc as usize] =
                    tri.triangulate(l, self.points[d]).ok().map(|t| t.p_in_left_mm);
            }
        }
        let mut steps: Vec<f64> = Vec::new();
        for n in 0..h * w {
            let Some(a) = at[n] else { continue };
            let right_n = (n % w + 1 < w).then_some(n + 1);
            let below = (n / w + 1 < h).then_some(n + w);
            for m in [right_n, below].into_iter().flatten() {
                if let Some(b) = at[m] {
                    steps.push((b - a).norm());
                }
            }
        }
        if steps.is_empty() {
            f64::INFINITY
        } else {
            (median(&mut steps) / p - 1.0).abs()
        }
    }

    /// The error for rivals neither the extent nor the pitch could settle, naming the offsets
    /// and, where measured, their spacing errors.
    fn ambiguity_error(
        &self,
        rivals: &[(i64, i64)],
        best: (usize, i64, i64),
        extent: (usize, usize, usize, usize),
        pitch_mm: Option<f64>,
        spacing_errors: &[((i64, i64), f64)],
    ) -> Error {
        let (rmin, rmax, cmin, cmax) = extent;
        let cue = if spacing_errors.is_empty() {
            String::new()
        } else {
            let v: Vec<String> = spacing_errors
                .iter()
                .map(|((r0, c0), e)| format!("({r0}, {c0}): {:.0} %", 100.0 * e))
                .collect();
            format!(
                "; triangulated neighbour spacing off the {:.3} mm pitch by offset: {} (expected one \
                 within 5 % and the others 5 % farther)",
                pitch_mm.unwrap_or(f64::NAN),
                v.join(", ")
            )
        };
        Error::StereoAlignment {
            reason: format!(
                "{} row/column offsets of the right lattice fit the epipolar constraint about equally \
                 well (best {} markers) and the right view does not show the whole {} x {} lattice \
                 (rows {}..={}, columns {}..={} of its own grid){cue}",
                rivals.len(),
                self.fit(best.1, best.2).1,
                self.h,
                self.w,
                rmin,
                rmax,
                cmin,
                cmax
            ),
        }
    }

    /// The detection per reference node under offset `(r0, c0)`, dropping right markers that
    /// contradict the constraint (where the left one was seen).
    fn node_assignment(&self, r0: i64, c0: i64) -> Vec<u32> {
        let w = self.w;
        (0..self.h * w)
            .map(|n| {
                let d = self.scratch.det_at((n / w) as i64 + r0, (n % w) as i64 + c0);
                let ok = d != NONE
                    && match (&self.lines[n], &self.right_norm[d as usize]) {
                        (Some(l), Some(x)) => self.epipolar.line_distance_px(l, x) <= self.max_epipolar_px,
                        (Some(_), None) => false,
                        (None, _) => true,
                    };
                if ok { d } else { NONE }
            })
            .collect()
    }

    /// Reference nodes the right view can show: a cut grid shows only its part of the window, so
    /// the minimum reference fraction counts the right markers that fall in the window.
    fn nodes_in_window(&self, r0: i64, c0: i64) -> usize {
        let w = self.w;
        if self.cut {
            (0..self.h * w)
                .filter(|n| self.scratch.det_at((n / w) as i64 + r0, (n % w) as i64 + c0) != NONE)
                .count()
        } else {
            self.h * w
        }
    }
}
