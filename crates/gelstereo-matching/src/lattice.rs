//! Grid indexing of one view: the reference lattice and per-frame indexing against it.

use gelstereo_core::{Detection, GridIndex, GridShape, Point2};

use crate::grow::{Grower, NONE};
use crate::{Error, Result};
use gelstereo_core::spatial::Buckets;

/// Tuning of the grid indexer. Distances are fractions of the marker pitch in pixels, so one
/// configuration serves any image size.
#[derive(Debug, Clone, PartialEq)]
pub struct IndexingConfig {
    /// A detection is assigned to a node when it lies within `gate_frac x pitch` of the node's
    /// prediction. Default 0.4: half the pitch is where two nodes' gates would touch; 0.4 leaves a
    /// margin for prediction error while staying clear of the neighbours.
    pub gate_frac: f64,
    /// Seeds need a detection within `seed_gate_frac x pitch` of the prior (or reference) position.
    /// Default 0.25 (the docs/design.md correctness radius r), with no second detection within twice
    /// that distance.
    pub seed_gate_frac: f64,
    /// Seeds must agree in displacement with at least [`seed_min_agreeing`](Self::seed_min_agreeing)
    /// neighbouring seeds to within `seed_agreement_frac x pitch`. Default 0.15.
    pub seed_agreement_frac: f64,
    /// Neighbouring seeds (8-neighbourhood) that must agree. Default 2.
    pub seed_min_agreeing: usize,
    /// Radius, in lattice steps, of the neighbourhood a node is predicted from. Default 2 (a 5 x 5
    /// window: enough to bridge one missing marker and to fit a local affine deformation).
    pub fit_radius: usize,
    /// Leave-one-out check: an assignment is dropped when its prediction from at least this many
    /// assigned neighbours misses the gate. Default 4.
    pub prune_min_support: usize,
    /// A reference frame must show at least this fraction of the lattice. Default 0.5.
    pub min_reference_fraction: f64,
}

impl Default for IndexingConfig {
    fn default() -> Self {
        Self {
            gate_frac: 0.4,
            seed_gate_frac: 0.25,
            seed_agreement_frac: 0.15,
            seed_min_agreeing: 2,
            fit_radius: 2,
            prune_min_support: 4,
            min_reference_fraction: 0.5,
        }
    }
}

impl IndexingConfig {
    fn validate(&self) -> Result<()> {
        let checks = [
            ("gate_frac", self.gate_frac, 0.05, 0.5),
            ("seed_gate_frac", self.seed_gate_frac, 0.01, 0.5),
            ("seed_agreement_frac", self.seed_agreement_frac, 0.01, 1.0),
            ("min_reference_fraction", self.min_reference_fraction, 0.0, 1.0),
        ];
        for (name, value, lo, hi) in checks {
            if !(value.is_finite() && (lo..=hi).contains(&value)) {
                return Err(Error::Config {
                    field: name,
                    expected: format!("a number in [{lo}, {hi}]"),
                    found: value.to_string(),
                });
            }
        }
        if self.fit_radius == 0 || self.fit_radius > 5 {
            return Err(Error::Config {
                field: "fit_radius",
                expected: "1 to 5 lattice steps".into(),
                found: self.fit_radius.to_string(),
            });
        }
        Ok(())
    }
}

/// Where a partly visible view's markers sit on the whole grid
/// ([`ReferenceLattice::from_detections_placed`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GridPlacement {
    /// First grid row with an indexed marker.
    pub first_row: u16,
    /// Last grid row with an indexed marker.
    pub last_row: u16,
    /// First grid column with an indexed marker.
    pub first_col: u16,
    /// Last grid column with an indexed marker.
    pub last_col: u16,
    /// Indexed markers whose nearest expected node agrees with the chosen offset.
    pub agreeing: usize,
    /// Markers indexed in the view.
    pub indexed: usize,
}

impl std::fmt::Display for GridPlacement {
    /// `rows 0..=26, columns 0..=12 (325 of 325 markers agree)`, as `gelstereo track` logs it.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "rows {}..={}, columns {}..={} ({} of {} markers agree)",
            self.first_row, self.last_row, self.first_col, self.last_col, self.agreeing, self.indexed
        )
    }
}

/// The detections of one view with the grid index of each.
#[derive(Debug, Clone, PartialEq)]
pub struct IndexedView {
    shape: GridShape,
    positions: Vec<Point2>,
    /// Per node (row-major), the detection assigned to it.
    node_detection: Vec<Option<u32>>,
    /// Per detection, its index.
    detection_index: Vec<Option<GridIndex>>,
}

impl IndexedView {
    pub(crate) fn from_nodes(shape: GridShape, positions: Vec<Point2>, node_det: &[u32]) -> Self {
        let mut detection_index = vec![None; positions.len()];
        let node_detection = node_det
            .iter()
            .zip(shape.indices())
            .map(|(&d, idx)| {
                (d != NONE).then(|| {
                    detection_index[d as usize] = Some(idx);
                    d
                })
            })
            .collect();
        Self {
            shape,
            positions,
            node_detection,
            detection_index,
        }
    }

    /// The lattice shape.
    pub fn shape(&self) -> GridShape {
        self.shape
    }

    /// Number of detections that received an index.
    pub fn indexed_count(&self) -> usize {
        self.node_detection.iter().flatten().count()
    }

    /// Number of detections given (indexed or not).
    pub fn detection_count(&self) -> usize {
        self.positions.len()
    }

    /// The position of detection `detection` (indexed or not), px.
    pub fn detection_position(&self, detection: usize) -> Option<Point2> {
        self.positions.get(detection).copied()
    }

    /// The index of detection `detection` (its position in the slice given to the indexer).
    pub fn index_of(&self, detection: usize) -> Option<GridIndex> {
        self.detection_index.get(detection).copied().flatten()
    }

    /// The detection number assigned to `index`.
    pub fn detection_at(&self, index: GridIndex) -> Option<usize> {
        self.shape
            .linear(index)
            .and_then(|i| self.node_detection[i])
            .map(|d| d as usize)
    }

    /// The position of the marker with `index` in this view, px.
    pub fn position(&self, index: GridIndex) -> Option<Point2> {
        self.detection_at(index).map(|d| self.positions[d])
    }

    /// Indexed markers in row-major order, with their positions.
    pub fn markers(&self) -> impl Iterator<Item = (GridIndex, Point2)> + '_ {
        self.shape
            .indices()
            .zip(&self.node_detection)
            .filter_map(|(idx, d)| d.map(|d| (idx, self.positions[d as usize])))
    }

    /// Position per node, row-major (`None` where no detection was indexed): the `prior` for the
    /// next frame.
    pub fn node_positions(&self) -> Vec<Option<Point2>> {
        self.node_detection
            .iter()
            .map(|d| d.map(|d| self.positions[d as usize]))
            .collect()
    }

    /// Detections that received no index (spurious detections, or markers the indexer could not
    /// place), in input order.
    pub fn unindexed(&self) -> Vec<usize> {
        (0..self.positions.len())
            .filter(|&d| self.detection_index[d].is_none())
            .collect()
    }
}

/// The marker lattice of one view's reference (no-contact) frame: the expected position of every
/// node, the pitch, and the indexing of the reference detections themselves.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceLattice {
    shape: GridShape,
    /// Expected position of every node, row-major: the reference detection, or for nodes missing
    /// from the reference frame, the local-affine prediction from their neighbours.
    nodes: Vec<Point2>,
    observed: Vec<bool>,
    pitch_px: f64,
    config: IndexingConfig,
    reference: IndexedView,
}

/// Checks detections for non-finite positions and returns the positions.
fn positions_of(detections: &[Detection]) -> Result<Vec<Point2>> {
    detections
        .iter()
        .enumerate()
        .map(|(i, d)| {
            let p = d.position;
            if p.x.is_finite() && p.y.is_finite() {
                Ok(p)
            } else {
                Err(Error::NonFiniteDetection {
                    detection: i,
                    x: p.x,
                    y: p.y,
                })
            }
        })
        .collect()
}

/// Median of a non-empty slice (sorts it).
pub(crate) fn median(v: &mut [f64]) -> f64 {
    v.sort_unstable_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Pitch and the two lattice basis vectors (u along columns, closest to +x; v along rows, closest
/// to +y) from nearest-neighbour vectors.
pub(crate) struct GlobalBasis {
    pub(crate) pitch_px: f64,
    pub(crate) u: Point2,
    pub(crate) v: Point2,
}

pub(crate) fn estimate_basis(points: &[Point2]) -> Option<GlobalBasis> {
    let n = points.len();
    if n < 4 {
        return None;
    }
    // The 4 nearest neighbours of every point (brute force: run once per reference frame).
    const K: usize = 4;
    let mut near: Vec<[(f64, usize); K]> = vec![[(f64::INFINITY, usize::MAX); K]; n];
    for i in 0..n {
        for j in 0..n {
            if i == j {
                continue;
            }
            // Squared distances while searching (sqrt taken below).
            let d = (points[i].x - points[j].x).powi(2) + (points[i].y - points[j].y).powi(2);
            let list = &mut near[i];
            if d < list[K - 1].0 {
                let mut k = K - 1;
                while k > 0 && list[k - 1].0 > d {
                    list[k] = list[k - 1];
                    k -= 1;
                }
                list[k] = (d, j);
            }
        }
    }
    for list in &mut near {
        for e in list.iter_mut() {
            e.0 = e.0.sqrt();
        }
    }
    let mut nn: Vec<f64> = near
        .iter()
        .map(|l| l[0].0)
        .filter(|d| d.is_finite() && *d > 0.0)
        .collect();
    if nn.is_empty() {
        return None;
    }
    let pitch = median(&mut nn);
    // Dominant orientation modulo 90 degrees: average of (cos 4t, sin 4t).
    let (mut c4, mut s4) = (0.0, 0.0);
    let mut vecs = Vec::with_capacity(n * K);
    for (i, list) in near.iter().enumerate() {
        for &(d, j) in list {
            if j != usize::MAX && d > 0.7 * pitch && d < 1.35 * pitch {
                let (dx, dy) = (points[j].x - points[i].x, points[j].y - points[i].y);
                let t = dy.atan2(dx);
                c4 += (4.0 * t).cos();
                s4 += (4.0 * t).sin();
                vecs.push((dx, dy));
            }
        }
    }
    if vecs.len() < 4 {
        return None;
    }
    let phi = s4.atan2(c4) / 4.0; // in (-45, 45] degrees: the direction closest to +x
    let dir_u = (phi.cos(), phi.sin());
    let dir_v = (-phi.sin(), phi.cos());
    // Refine each basis vector as the mean of the neighbour vectors within 30 degrees of it
    // (sign-folded), so that it carries the view's own scale and skew.
    let refine = |dir: (f64, f64)| -> Option<Point2> {
        let (mut sx, mut sy, mut k) = (0.0, 0.0, 0usize);
        for &(dx, dy) in &vecs {
            let len = dx.hypot(dy);
            let cos = (dx * dir.0 + dy * dir.1) / len;
            if cos.abs() > 30f64.to_radians().cos() {
                let s = cos.signum();
                sx += s * dx;
                sy += s * dy;
                k += 1;
            }
        }
        (k > 0).then(|| Point2::new(sx / k as f64, sy / k as f64))
    };
    let u = refine(dir_u)?;
    let v = refine(dir_v)?;
    let cross = u.x * v.y - u.y * v.x;
    (pitch.is_finite() && cross.abs() > 0.25 * pitch * pitch).then_some(GlobalBasis {
        pitch_px: pitch,
        u,
        v,
    })
}

/// Result of growing a lattice from scratch on a provisional grid centred on a seed.
pub(crate) struct ScratchLattice {
    /// Provisional grid dimensions.
    pub(crate) rows: usize,
    pub(crate) cols: usize,
    /// Detection per provisional node (NONE where none).
    pub(crate) node_det: Vec<u32>,
    pub(crate) pitch_px: f64,
}

impl ScratchLattice {
    /// Assigned provisional rows / cols: (min row, max row, min col, max col).
    pub(crate) fn extent(&self) -> Option<(usize, usize, usize, usize)> {
        let mut e: Option<(usize, usize, usize, usize)> = None;
        for (n, &d) in self.node_det.iter().enumerate() {
            if d == NONE {
                continue;
            }
            let (r, c) = (n / self.cols, n % self.cols);
            e = Some(match e {
                None => (r, r, c, c),
                Some((r0, r1, c0, c1)) => (r0.min(r), r1.max(r), c0.min(c), c1.max(c)),
            });
        }
        e
    }

    /// The detection at provisional row `r`, column `c`; NONE where none or outside the grid.
    pub(crate) fn det_at(&self, r: i64, c: i64) -> u32 {
        if r < 0 || c < 0 || r >= self.rows as i64 || c >= self.cols as i64 {
            NONE
        } else {
            self.node_det[r as usize * self.cols + c as usize]
        }
    }

    /// Number of assigned nodes per provisional row and per provisional column.
    pub(crate) fn counts(&self) -> (Vec<usize>, Vec<usize>) {
        let mut rows = vec![0; self.rows];
        let mut cols = vec![0; self.cols];
        for (n, &d) in self.node_det.iter().enumerate() {
            if d != NONE {
                rows[n / self.cols] += 1;
                cols[n % self.cols] += 1;
            }
        }
        (rows, cols)
    }
}

/// Grows a lattice over `points` from the detection nearest their median that has lattice
/// neighbours, on a provisional grid big enough for `shape` in any placement.
pub(crate) fn grow_from_scratch(
    points: &[Point2],
    shape: GridShape,
    config: &IndexingConfig,
) -> Result<ScratchLattice> {
    let basis = estimate_basis(points).ok_or(Error::NoLattice {
        detections: points.len(),
    })?;
    let pitch = basis.pitch_px;
    let buckets = Buckets::new(points, pitch);
    let (rows, cols) = (2 * usize::from(shape.rows) + 1, 2 * usize::from(shape.cols) + 1);
    let (rc, cc) = (usize::from(shape.rows), usize::from(shape.cols));
    let gate = config.gate_frac * pitch;

    // Seed candidates: nearest to the median point first; a seed must find at least 3 of its
    // 4 lattice neighbours where the global basis puts them.
    let mut xs: Vec<f64> = points.iter().map(|p| p.x).collect();
    let mut ys: Vec<f64> = points.iter().map(|p| p.y).collect();
    let centre = Point2::new(median(&mut xs), median(&mut ys));
    let mut order: Vec<usize> = (0..points.len()).collect();
    order.sort_by(|&a, &b| {
        points[a]
            .distance(centre)
            .total_cmp(&points[b].distance(centre))
            .then(a.cmp(&b))
    });
    let has_near = |p: Point2| {
        let mut found = false;
        buckets.for_each_within(p, gate, |_, _| found = true);
        found
    };
    let (u, v) = (basis.u, basis.v);
    let seed = order.iter().take(64).copied().find(|&i| {
        let p = points[i];
        [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)]
            .iter()
            .filter(|(a, b)| has_near(Point2::new(p.x + a * u.x + b * v.x, p.y + a * u.y + b * v.y)))
            .count()
            >= 3
    });
    let seed = seed.ok_or(Error::NoLattice {
        detections: points.len(),
    })?;
    let s = points[seed];
    let base: Vec<Point2> = (0..rows * cols)
        .map(|n| {
            let (a, b) = ((n % cols) as f64 - cc as f64, (n / cols) as f64 - rc as f64);
            Point2::new(s.x + a * u.x + b * v.x, s.y + a * u.y + b * v.y)
        })
        .collect();
    let mut g = Grower::new(rows, cols, &base, &buckets, gate, config.fit_radius, |_, _| true);
    g.assign(rc * cols + cc, seed);
    g.grow();
    if g.prune_outliers(config.prune_min_support, false) > 0 {
        g.grow();
    }
    Ok(ScratchLattice {
        rows,
        cols,
        node_det: g.node_det,
        pitch_px: pitch,
    })
}

/// The window start (within `0..len`) of `size` consecutive entries of `counts` with the largest
/// sum; the lowest start among equals.
pub(crate) fn best_window(counts: &[usize], size: usize) -> usize {
    let mut best = (0usize, 0usize);
    for start in 0..=counts.len().saturating_sub(size) {
        let sum: usize = counts[start..(start + size).min(counts.len())].iter().sum();
        if sum > best.1 {
            best = (start, sum);
        }
    }
    best.0
}

/// A partly visible view's detections assigned to the nodes of the whole grid by the expected
/// node positions ([`ReferenceLattice::from_detections_placed`]).
pub(crate) struct PlacedAssignment {
    pub(crate) points: Vec<Point2>,
    /// Detection per node of the whole grid (NONE where none).
    pub(crate) node_det: Vec<u32>,
    pub(crate) pitch_px: f64,
    /// Nodes expected within the detections' extent.
    pub(crate) nodes_in_view: usize,
    pub(crate) placement: GridPlacement,
}

pub(crate) fn placed_assignment(
    detections: &[Detection],
    shape: GridShape,
    expected: &[Option<Point2>],
    config: &IndexingConfig,
) -> Result<PlacedAssignment> {
    config.validate()?;
    if expected.len() != shape.count() {
        return Err(Error::PriorLength {
            expected: shape.count(),
            found: expected.len(),
        });
    }
    let points = positions_of(detections)?;
    if points.is_empty() {
        return Err(Error::EmptyView);
    }
    let scratch = grow_from_scratch(&points, shape, config)?;
    let (h, w) = (usize::from(shape.rows), usize::from(shape.cols));
    let pitch = scratch.pitch_px;
    // Each indexed marker votes for the offset between its provisional node and the nearest
    // expected node (within half a pitch); a few hundred of each, so brute force will do.
    let mut votes: std::collections::BTreeMap<(i64, i64), usize> = std::collections::BTreeMap::new();
    let mut indexed = 0usize;
    for (n, &d) in scratch.node_det.iter().enumerate() {
        if d == NONE {
            continue;
        }
        indexed += 1;
        let p = points[d as usize];
        let nearest = expected
            .iter()
            .enumerate()
            .filter_map(|(k, q)| q.map(|q| (q.distance(p), k)))
            .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        if let Some((_, k)) = nearest.filter(|x| x.0 <= 0.5 * pitch) {
            let (sr, sc) = ((n / scratch.cols) as i64, (n % scratch.cols) as i64);
            *votes
                .entry((sr - (k / w) as i64, sc - (k % w) as i64))
                .or_default() += 1;
        }
    }
    // Most votes first; the lowest offset among equals (deterministic).
    let best = votes
        .iter()
        .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))
        .map(|(&o, &v)| (o, v));
    let Some(((r0, c0), agreeing)) = best.filter(|&(_, v)| 2 * v >= indexed) else {
        return Err(Error::Placement {
            agreeing: best.map_or(0, |b| b.1),
            indexed,
            pitch_px: pitch,
        });
    };
    let node_det: Vec<u32> = (0..h * w)
        .map(|n| scratch.det_at((n / w) as i64 + r0, (n % w) as i64 + c0))
        .collect();
    // Nodes the view can show: expected within the detections' extent (half a pitch beyond).
    let (lo, hi) = points.iter().fold(
        (
            Point2::new(f64::INFINITY, f64::INFINITY),
            Point2::new(f64::NEG_INFINITY, f64::NEG_INFINITY),
        ),
        |(lo, hi), p| {
            (
                Point2::new(lo.x.min(p.x), lo.y.min(p.y)),
                Point2::new(hi.x.max(p.x), hi.y.max(p.y)),
            )
        },
    );
    let m = 0.5 * pitch;
    let in_view = expected
        .iter()
        .flatten()
        .filter(|q| q.x >= lo.x - m && q.x <= hi.x + m && q.y >= lo.y - m && q.y <= hi.y + m)
        .count();
    let placed: Vec<usize> = (0..h * w).filter(|&n| node_det[n] != NONE).collect();
    let placement = GridPlacement {
        first_row: placed.iter().map(|&n| n / w).min().unwrap_or(0) as u16,
        last_row: placed.iter().map(|&n| n / w).max().unwrap_or(0) as u16,
        first_col: placed.iter().map(|&n| n % w).min().unwrap_or(0) as u16,
        last_col: placed.iter().map(|&n| n % w).max().unwrap_or(0) as u16,
        agreeing,
        indexed,
    };
    Ok(PlacedAssignment {
        points,
        node_det,
        pitch_px: pitch,
        nodes_in_view: in_view,
        placement,
    })
}

impl ReferenceLattice {
    /// Indexes a reference (no-contact) frame from scratch: estimates the pitch and the lattice
    /// directions, grows the lattice from a seed near the centre, and places the `shape` window on
    /// the rows and columns that hold the most detections. Row 0 is the top row of markers, col 0
    /// the leftmost column.
    ///
    /// Fails when fewer than [`IndexingConfig::min_reference_fraction`] of the nodes are found, or
    /// when the view shows fewer rows or columns than `shape` (then which row is row 0 is unknown).
    pub fn from_detections(
        detections: &[Detection],
        shape: GridShape,
        config: IndexingConfig,
    ) -> Result<Self> {
        config.validate()?;
        if shape.rows < 2 || shape.cols < 2 {
            return Err(Error::Config {
                field: "shape",
                expected: "at least 2 x 2 markers".into(),
                found: format!("{} x {}", shape.rows, shape.cols),
            });
        }
        let points = positions_of(detections)?;
        if points.is_empty() {
            return Err(Error::EmptyView);
        }
        let scratch = grow_from_scratch(&points, shape, &config)?;
        let (row_counts, col_counts) = scratch.counts();
        let (h, w) = (usize::from(shape.rows), usize::from(shape.cols));
        let r0 = best_window(&row_counts, h);
        let c0 = best_window(&col_counts, w);
        let found_rows = row_counts.iter().filter(|&&c| c > 0).count();
        let found_cols = col_counts.iter().filter(|&&c| c > 0).count();
        if row_counts[r0..r0 + h].contains(&0) || col_counts[c0..c0 + w].contains(&0) {
            return Err(Error::IncompleteGrid {
                expected: shape,
                found_rows,
                found_cols,
            });
        }
        // A whole row or column of markers beyond the window: the lattice asked for is smaller than
        // the one in view (a wrong --grid), which would silently track a part of it.
        let beyond = |counts: &[usize], start: usize, len: usize, half_line: usize| {
            counts
                .iter()
                .enumerate()
                .any(|(k, &c)| !(start..start + len).contains(&k) && c >= half_line.max(2))
        };
        if beyond(&row_counts, r0, h, w / 2) || beyond(&col_counts, c0, w, h / 2) {
            return Err(Error::GridSmallerThanView {
                expected: shape,
                found_rows,
                found_cols,
            });
        }
        let node_det: Vec<u32> = (0..h * w)
            .map(|n| scratch.node_det[(r0 + n / w) * scratch.cols + c0 + n % w])
            .collect();
        Self::from_assignment(points, shape, &node_det, scratch.pitch_px, config)
    }

    /// The rows x columns of a lattice of at most `max` that a reference view shows: the longest
    /// unbroken runs of occupied rows and columns of a lattice grown from scratch. For a sensor whose
    /// grid overfills the camera's view, where [`from_detections`](Self::from_detections) with the
    /// whole shape fails with [`Error::IncompleteGrid`]; indexing the view with the shape returned
    /// makes the visible top-left marker (0, 0). Fails with [`Error::TooSmallVisible`] below 3 x 3.
    pub fn visible_shape(
        detections: &[Detection],
        max: GridShape,
        config: &IndexingConfig,
    ) -> Result<GridShape> {
        config.validate()?;
        let points = positions_of(detections)?;
        if points.is_empty() {
            return Err(Error::EmptyView);
        }
        let scratch = grow_from_scratch(&points, max, config)?;
        let (row_counts, col_counts) = scratch.counts();
        let run = |counts: &[usize], limit: u16| -> u16 {
            let (mut best, mut cur) = (0usize, 0usize);
            for &c in counts {
                cur = if c > 0 { cur + 1 } else { 0 };
                best = best.max(cur);
            }
            u16::try_from(best).unwrap_or(u16::MAX).min(limit)
        };
        let (rows, cols) = (run(&row_counts, max.rows), run(&col_counts, max.cols));
        if rows < 3 || cols < 3 {
            return Err(Error::TooSmallVisible {
                found_rows: usize::from(rows),
                found_cols: usize::from(cols),
            });
        }
        Ok(GridShape { rows, cols })
    }

    /// Indexes a reference frame that may show only part of the `shape` lattice (a sensor whose
    /// grid overfills the camera's view) and places the visible markers on the whole grid by
    /// `expected`: every node's rest position in this view, row-major over `shape` (e.g. the
    /// sensor description's lattice projected through the calibration; `None` where it does not
    /// project). The grid offset is the one most indexed markers agree on (nearest expected node
    /// within half a pitch), so the ids are the sensor's own grid indices.
    ///
    /// Fails with [`Error::Placement`] when fewer than half of the indexed markers agree on one
    /// offset, and with [`Error::TooFewMarkers`] when fewer than `min_reference_fraction` of the
    /// nodes expected within the detections' extent are found.
    pub fn from_detections_placed(
        detections: &[Detection],
        shape: GridShape,
        expected: &[Option<Point2>],
        config: IndexingConfig,
    ) -> Result<(Self, GridPlacement)> {
        let a = placed_assignment(detections, shape, expected, &config)?;
        let lattice =
            Self::from_assignment_of(a.points, shape, &a.node_det, a.pitch_px, config, a.nodes_in_view)?;
        Ok((lattice, a.placement))
    }

    /// Builds the lattice from a complete assignment of reference detections to nodes (`node_det`
    /// row-major over `shape`, NONE where missing); fills the missing nodes by prediction.
    pub(crate) fn from_assignment(
        points: Vec<Point2>,
        shape: GridShape,
        node_det: &[u32],
        pitch_px: f64,
        config: IndexingConfig,
    ) -> Result<Self> {
        Self::from_assignment_of(points, shape, node_det, pitch_px, config, shape.count())
    }

    /// [`from_assignment`](Self::from_assignment) where `nodes_in_view` of the nodes can be seen
    /// (the minimum reference fraction applies to them).
    pub(crate) fn from_assignment_of(
        points: Vec<Point2>,
        shape: GridShape,
        node_det: &[u32],
        pitch_px: f64,
        config: IndexingConfig,
        nodes_in_view: usize,
    ) -> Result<Self> {
        let (h, w) = (usize::from(shape.rows), usize::from(shape.cols));
        let observed: Vec<bool> = node_det.iter().map(|&d| d != NONE).collect();
        let found = observed.iter().filter(|&&o| o).count();
        if (found as f64) < config.min_reference_fraction * nodes_in_view as f64 {
            return Err(Error::TooFewMarkers {
                found,
                expected: nodes_in_view,
                min_fraction: config.min_reference_fraction,
            });
        }
        let regularity = irregular_nodes(&points, node_det, h, w, 0.35 * pitch_px);
        if regularity.refused(found) {
            return Err(Error::IrregularLattice {
                outliers: regularity.outliers,
                markers: found,
                broken_steps: regularity.broken_edges,
                steps: regularity.edges,
            });
        }
        // Fill missing nodes from a regular lattice through the observed ones (basis from their
        // row/column differences), corrected by the local fit of the grower.
        let basis = lattice_basis(&points, node_det, w);
        let anchor = (0..h * w).find(|&n| observed[n]).ok_or(Error::EmptyView)?;
        let (ar, ac) = ((anchor / w) as f64, (anchor % w) as f64);
        let pa = points[node_det[anchor] as usize];
        let base: Vec<Point2> = (0..h * w)
            .map(|n| {
                let (a, b) = ((n % w) as f64 - ac, (n / w) as f64 - ar);
                Point2::new(
                    pa.x + a * basis.0.x + b * basis.1.x,
                    pa.y + a * basis.0.y + b * basis.1.y,
                )
            })
            .collect();
        let buckets = Buckets::new(&points, pitch_px);
        let mut g = Grower::new(
            h,
            w,
            &base,
            &buckets,
            config.gate_frac * pitch_px,
            config.fit_radius,
            |_, _| false,
        );
        for (n, &d) in node_det.iter().enumerate() {
            if d != NONE {
                g.assign(n, d as usize);
            }
        }
        let mut nodes = Vec::with_capacity(h * w);
        for n in 0..h * w {
            nodes.push(if observed[n] {
                points[node_det[n] as usize]
            } else {
                g.predict(n).map_or(base[n], |(p, _)| p)
            });
        }
        let reference = IndexedView::from_nodes(shape, points, node_det);
        Ok(Self {
            shape,
            nodes,
            observed,
            pitch_px,
            config,
            reference,
        })
    }

    /// The lattice shape.
    pub fn shape(&self) -> GridShape {
        self.shape
    }

    /// Median nearest-neighbour distance of the reference markers, px.
    pub fn pitch_px(&self) -> f64 {
        self.pitch_px
    }

    /// The indexing configuration this lattice indexes frames with.
    pub fn config(&self) -> &IndexingConfig {
        &self.config
    }

    /// Expected reference position of the marker `index` (observed, or predicted for markers the
    /// reference frame missed), px.
    pub fn node_position(&self, index: GridIndex) -> Option<Point2> {
        self.shape.linear(index).map(|i| self.nodes[i])
    }

    /// Whether marker `index` was detected in the reference frame.
    pub fn observed(&self, index: GridIndex) -> bool {
        self.shape.linear(index).is_some_and(|i| self.observed[i])
    }

    /// The reference frame's detections with their indices.
    pub fn reference_view(&self) -> &IndexedView {
        &self.reference
    }

    /// Indexes the detections of a (possibly deformed) frame of the same view.
    ///
    /// `prior` (row-major, [`GridShape::count`] entries, e.g. the previous frame's
    /// [`IndexedView::node_positions`]) gives expected positions; nodes without one fall back to
    /// the reference. Seeds are nodes with a unique detection close to their expected position whose
    /// displacement agrees with their neighbours'; only the largest connected group of seeds is
    /// kept, and the lattice grows from it with locally fitted deformation.
    pub fn index(&self, detections: &[Detection], prior: Option<&[Option<Point2>]>) -> Result<IndexedView> {
        self.index_with(detections, prior, |_, _| true)
    }

    /// Like [`index`](Self::index), with a gate `admissible(index, detection)` (`detection` = its
    /// number in `detections`) that may veto detections for a node (the stereo matcher passes the
    /// epipolar constraint).
    pub fn index_with(
        &self,
        detections: &[Detection],
        prior: Option<&[Option<Point2>]>,
        admissible: impl Fn(GridIndex, usize) -> bool,
    ) -> Result<IndexedView> {
        let points = positions_of(detections)?;
        let n_nodes = self.shape.count();
        if let Some(p) = prior
            && p.len() != n_nodes
        {
            return Err(Error::PriorLength {
                expected: n_nodes,
                found: p.len(),
            });
        }
        let (h, w) = (usize::from(self.shape.rows), usize::from(self.shape.cols));
        if points.is_empty() {
            return Ok(IndexedView::from_nodes(self.shape, points, &vec![NONE; n_nodes]));
        }
        let pitch = self.pitch_px;
        let buckets = Buckets::new(&points, pitch);
        let admit = |n: usize, d: usize| admissible(GridIndex::new((n / w) as u16, (n % w) as u16), d);
        let expected = match prior {
            Some(p) => fill_prior(&self.nodes, p, h, w),
            None => self.nodes.clone(),
        };

        let seed_gate = self.config.seed_gate_frac * pitch;
        let mut cand = seed_candidates(&expected, &buckets, seed_gate, pitch, &admit);
        one_node_per_detection(&mut cand, &points, &expected);
        let seeds = Seeds {
            cand: &cand,
            points: &points,
            expected: &expected,
            h,
            w,
            agree: self.config.seed_agreement_frac * pitch,
        };
        let consistent = seeds.consistent(self.config.seed_min_agreeing);
        let (comp, best) = seeds.largest_group(&consistent);
        let mut g = Grower::new(
            h,
            w,
            &expected,
            &buckets,
            self.config.gate_frac * pitch,
            self.config.fit_radius,
            admit,
        );
        if best.0 != usize::MAX {
            for n in 0..n_nodes {
                if comp[n] == best.0 {
                    g.assign(n, cand[n] as usize);
                }
            }
            g.grow();
            // Leave-one-out check. Without a prior the seeds agree with their neighbours by
            // construction and only grown nodes are checked. With a prior every assignment, seeds
            // included, is checked against the REFERENCE lattice geometry: seeds taken from a prior
            // inherit its errors (a node that slid onto its neighbour's detection in an earlier
            // frame agrees with the prior but not with its neighbours).
            let with_prior = prior.is_some();
            if with_prior {
                g.set_base(&self.nodes);
            }
            if g.prune_outliers(self.config.prune_min_support, with_prior) > 0 {
                g.grow();
            }
        }
        Ok(IndexedView::from_nodes(self.shape, points, &g.node_det))
    }
}

/// Seed candidates per node: a unique detection near the expected position (the nearest within
/// `seed_gate`, with the second nearest clearly farther) that `admit` accepts; NONE elsewhere.
fn seed_candidates(
    expected: &[Point2],
    buckets: &Buckets,
    seed_gate: f64,
    pitch: f64,
    admit: &impl Fn(usize, usize) -> bool,
) -> Vec<u32> {
    let mut cand: Vec<u32> = vec![NONE; expected.len()];
    for n in 0..expected.len() {
        let (mut b1, mut b2) = ((f64::INFINITY, NONE), f64::INFINITY);
        buckets.for_each_within(expected[n], 2.0 * seed_gate, |d, d2| {
            if d2 < b1.0 || (d2 == b1.0 && (d as u32) < b1.1) {
                b2 = b1.0;
                b1 = (d2, d as u32);
            } else if d2 < b2 {
                b2 = d2;
            }
        });
        let (d1, d2) = (b1.0.sqrt(), b2.sqrt());
        if b1.1 != NONE && d1 <= seed_gate && d2 > 2.0 * d1.max(0.05 * pitch) && admit(n, b1.1 as usize) {
            cand[n] = b1.1;
        }
    }
    cand
}

/// One node per detection: where two candidates share a detection, the node closer to it keeps
/// it and the other loses its candidate.
fn one_node_per_detection(cand: &mut [u32], points: &[Point2], expected: &[Point2]) {
    let mut owner: Vec<u32> = vec![NONE; points.len()];
    for n in 0..cand.len() {
        let d = cand[n];
        if d == NONE {
            continue;
        }
        let o = owner[d as usize];
        if o == NONE {
            owner[d as usize] = n as u32;
        } else {
            let dist = |m: usize| points[d as usize].distance(expected[m]);
            let (keep, drop) = if dist(n) < dist(o as usize) {
                (n as u32, o)
            } else {
                (o, n as u32)
            };
            owner[d as usize] = keep;
            cand[drop as usize] = NONE;
        }
    }
}

/// The 8-neighbours of node `n` (row-major) inside an `h` x `w` grid.
fn neighbours8(n: usize, h: usize, w: usize) -> impl Iterator<Item = usize> {
    let (r, c) = ((n / w) as i64, (n % w) as i64);
    (-1i64..=1)
        .flat_map(move |dr| (-1i64..=1).map(move |dc| (r + dr, c + dc)))
        .filter(move |&(rr, cc)| (rr, cc) != (r, c) && rr >= 0 && cc >= 0 && rr < h as i64 && cc < w as i64)
        .map(move |(rr, cc)| rr as usize * w + cc as usize)
}

/// Seed candidates with what their agreement is judged by: displacements from the expected
/// positions, compared between neighbours within `agree` pixels.
struct Seeds<'a> {
    cand: &'a [u32],
    points: &'a [Point2],
    expected: &'a [Point2],
    h: usize,
    w: usize,
    agree: f64,
}

impl Seeds<'_> {
    /// Displacement of seed `n` from its expected position.
    fn disp(&self, n: usize) -> (f64, f64) {
        let p = self.points[self.cand[n] as usize];
        (p.x - self.expected[n].x, p.y - self.expected[n].y)
    }

    /// Seeds `n` and `m` are displaced alike.
    fn agree(&self, n: usize, m: usize) -> bool {
        let ((ax, ay), (bx, by)) = (self.disp(n), self.disp(m));
        (ax - bx).powi(2) + (ay - by).powi(2) <= self.agree * self.agree
    }

    /// Seeds whose displacement agrees with at least `min_agreeing` neighbouring seeds.
    fn consistent(&self, min_agreeing: usize) -> Vec<bool> {
        (0..self.cand.len())
            .map(|n| {
                self.cand[n] != NONE
                    && neighbours8(n, self.h, self.w)
                        .filter(|&m| self.cand[m] != NONE && self.agree(n, m))
                        .count()
                        >= min_agreeing
            })
            .collect()
    }

    /// Largest 8-connected component of consistent, mutually agreeing seeds (lowest first node
    /// among equals): the component label per node (usize::MAX where none) and (label, size) of
    /// the largest, with label usize::MAX when there is none.
    fn largest_group(&self, consistent: &[bool]) -> (Vec<usize>, (usize, usize)) {
        let n_nodes = consistent.len();
        let mut comp = vec![usize::MAX; n_nodes];
        let mut best: (usize, usize) = (usize::MAX, 0);
        let mut stack = Vec::new();
        for start in 0..n_nodes {
            if !consistent[start] || comp[start] != usize::MAX {
                continue;
            }
            comp[start] = start;
            stack.push(start);
            let mut size = 0;
            while let Some(n) = stack.pop() {
                size += 1;
                for m in neighbours8(n, self.h, self.w) {
                    // Link only seeds that agree, so that a block displaced by a whole lattice
                    // vector does not join the correctly seeded region.
                    if consistent[m] && comp[m] == usize::MAX && self.agree(n, m) {
                        comp[m] = start;
                        stack.push(m);
                    }
                }
            }
            if size > best.1 {
                best = (start, size);
            }
        }
        (comp, best)
    }
}

/// Mean column step and row step between observed neighbouring nodes.
fn lattice_basis(points: &[Point2], node_det: &[u32], w: usize) -> (Point2, Point2) {
    let (mut su, mut nu, mut sv, mut nv) = ((0.0, 0.0), 0usize, (0.0, 0.0), 0usize);
    for (n, &d) in node_det.iter().enumerate() {
        if d == NONE {
            continue;
        }
        let p = points[d as usize];
        if n % w + 1 < w && node_det[n + 1] != NONE {
            let q = points[node_det[n + 1] as usize];
            su = (su.0 + q.x - p.x, su.1 + q.y - p.y);
            nu += 1;
        }
        if n + w < node_det.len() && node_det[n + w] != NONE {
            let q = points[node_det[n + w] as usize];
            sv = (sv.0 + q.x - p.x, sv.1 + q.y - p.y);
            nv += 1;
        }
    }
    let mean = |s: (f64, f64), k: usize| {
        if k == 0 {
            Point2::default()
        } else {
            Point2::new(s.0 / k as f64, s.1 / k as f64)
        }
    };
    (mean(su, nu), mean(sv, nv))
}

/// Expected positions from a partial prior: nodes with a prior keep it; the others get their
/// reference position moved by the mean displacement (prior - reference) of the nearest nodes that
/// have one (inverse-square lattice-distance weights, growing outwards ring by ring).
fn fill_prior(reference: &[Point2], prior: &[Option<Point2>], h: usize, w: usize) -> Vec<Point2> {
    let mut disp: Vec<Option<(f64, f64)>> = reference
        .iter()
        .zip(prior)
        .map(|(r, p)| {
            p.filter(|p| p.x.is_finite() && p.y.is_finite())
                .map(|p| (p.x - r.x, p.y - r.y))
        })
        .collect();
    if disp.iter().all(Option::is_none) {
        return reference.to_vec();
    }
    while disp.iter().any(Option::is_none) {
        let mut next = disp.clone();
        for n in 0..h * w {
            if disp[n].is_some() {
                continue;
            }
            let (r0, c0) = ((n / w) as i64, (n % w) as i64);
            let (mut sx, mut sy, mut sw) = (0.0, 0.0, 0.0);
            for r in (r0 - 2).max(0)..=(r0 + 2).min(h as i64 - 1) {
                for c in (c0 - 2).max(0)..=(c0 + 2).min(w as i64 - 1) {
                    if let Some((dx, dy)) = disp[r as usize * w + c as usize] {
                        let wt = 1.0 / ((r - r0).pow(2) + (c - c0).pow(2)) as f64;
                        sx += wt * dx;
                        sy += wt * dy;
                        sw += wt;
                    }
                }
            }
            if sw > 0.0 {
                next[n] = Some((sx / sw, sy / sw));
            }
        }
        disp = next;
    }
    reference
        .iter()
        .zip(&disp)
        .map(|(r, d)| {
            let (dx, dy) = d.unwrap_or((0.0, 0.0));
            Point2::new(r.x + dx, r.y + dy)
        })
        .collect()
}

/// How far the indexed reference markers are from a regular lattice.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Regularity {
    /// Markers farther than the limit from the smooth fit.
    outliers: usize,
    /// Neighbour steps (right or down) that differ from the fit's by more than twice the limit.
    broken_edges: usize,
    /// Neighbour steps checked.
    edges: usize,
}

impl Regularity {
    /// Refused: more than 5% of the markers off the fit, or more than 1% (at least 5) of the steps
    /// broken (a slipped block of ids breaks every step along its border).
    fn refused(&self, markers: usize) -> bool {
        self.outliers * 20 > markers || (self.broken_edges >= 5 && self.broken_edges * 100 > self.edges)
    }
}

/// Regularity of the indexed reference markers against a smooth fit of the lattice: a cubic
/// polynomial in (col, row) for each image coordinate, which holds perspective and lens distortion
/// of a gel at rest but not a slip of the indexing (a block of markers one row or column off).
/// Fitted twice, the second time without the first fit's outliers (farther than `limit_px`).
fn irregular_nodes(points: &[Point2], node_det: &[u32], h: usize, w: usize, limit_px: f64) -> Regularity {
    type M10 = nalgebra::SMatrix<f64, 10, 10>;
    type V10 = nalgebra::SVector<f64, 10>;
    let basis = |n: usize| -> V10 {
        let c = (n % w) as f64 / (w.max(2) - 1) as f64 - 0.5;
        let r = (n / w) as f64 / (h.max(2) - 1) as f64 - 0.5;
        V10::from_column_slice(&[
            1.0,
            c,
            r,
            c * c,
            c * r,
            r * r,
            c * c * c,
            c * c * r,
            c * r * r,
            r * r * r,
        ])
    };
    let nodes: Vec<(V10, Point2)> = node_det
        .iter()
        .enumerate()
        .filter(|(_, d)| **d != NONE)
        .map(|(n, &d)| (basis(n), points[d as usize]))
        .collect();
    if nodes.len() < 20 {
        return Regularity::default();
    }
    let fit = |keep: &dyn Fn(usize) -> bool| -> Option<(V10, V10)> {
        let (mut a, mut bx, mut by) = (M10::zeros(), V10::zeros(), V10::zeros());
        for (i, (b, p)) in nodes.iter().enumerate() {
            if keep(i) {
                a += b * b.transpose();
                bx += b * p.x;
                by += b * p.y;
            }
        }
        let lu = a.lu();
        Some((lu.solve(&bx)?, lu.solve(&by)?))
    };
    let residual = |coef: &(V10, V10), i: usize| {
        let (b, p) = &nodes[i];
        (coef.0.dot(b) - p.x).hypot(coef.1.dot(b) - p.y)
    };
    let Some(first) = fit(&|_| true) else {
        return Regularity::default();
    };
    let inlier: Vec<bool> = (0..nodes.len())
        .map(|i| residual(&first, i) <= limit_px)
        .collect();
    let Some(second) = fit(&|i| inlier[i]) else {
        return Regularity::default();
    };
    let outliers = (0..nodes.len())
        .filter(|&i| residual(&second, i) > limit_px)
        .count();
    // Steps between indexed neighbours against the fit's steps: a slipped block breaks the edges
    // along its border even where the smooth fit bends to absorb it.
    let at = |n: usize| -> Point2 {
        let b = basis(n);
        Point2::new(second.0.dot(&b), second.1.dot(&b))
    };
    let (mut edges, mut broken_edges) = (0, 0);
    for n in 0..h * w {
        if node_det[n] == NONE {
            continue;
        }
        for m in [(n % w + 1 < w).then_some(n + 1), (n + w < h * w).then_some(n + w)]
            .into_iter()
            .flatten()
        {
            if node_det[m] == NONE {
                continue;
            }
            let (p, q) = (points[node_det[n] as usize], points[node_det[m] as usize]);
            let (e, f) = (at(n), at(m));
            edges += 1;
            let dev = ((q.x - p.x) - (f.x - e.x)).hypot((q.y - p.y) - (f.y - e.y));
            if dev > 2.0 * limit_px {
                broken_edges += 1;
            }
        }
    }
    Regularity {
        outliers,
        broken_edges,
        edges,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 23 x 23 lattice under perspective and barrel distortion (pitch ~15 px).
    fn distorted_lattice() -> Vec<Point2> {
        (0..23 * 23)
            .map(|n| {
                let (c, r) = ((n % 23) as f64 - 11.0, (n / 23) as f64 - 11.0);
                let (x, y, z) = (c * 0.6, r * 0.6, 25.0 + 0.04 * c * 0.6);
                let (u, v) = (x / z, y / z);
                let k = 1.0 - 0.12 * (u * u + v * v);
                Point2::new(320.0 + 600.0 * u * k, 240.0 + 600.0 * v * k)
            })
            .collect()
    }

    #[test]
    fn a_smooth_lattice_is_regular_and_a_slipped_block_is_not() {
        let pts = distorted_lattice();
        let ident: Vec<u32> = (0..pts.len() as u32).collect();
        let clean = irregular_nodes(&pts, &ident, 23, 23, 0.35 * 14.4);
        assert_eq!(
            (clean.outliers, clean.broken_edges, clean.edges),
            (0, 0, 2 * 22 * 23)
        );
        // Rows 8-13 indexed one column off (each node holds its right neighbour's detection). (A
        // slipped block at the border is partly absorbed by the cubic and caught less well.)
        let block = |n: usize| (8..14).contains(&(n / 23));
        let slipped: Vec<u32> = (0..pts.len())
            .map(|n| match (block(n), n % 23 < 22) {
                (true, true) => (n + 1) as u32,
                (true, false) => NONE,
                (false, _) => n as u32,
            })
            .collect();
        let r = irregular_nodes(&pts, &slipped, 23, 23, 0.35 * 14.4);
        assert!(r.outliers >= 60 && r.refused(523), "{r:?}");
        // At the border the cubic absorbs part of the slip (fewer than 5% off the fit), but the
        // steps along the block's edge break.
        let border: Vec<u32> = (0..pts.len())
            .map(|n| match (n / 23 < 4, n % 23 < 22) {
                (true, true) => (n + 1) as u32,
                (true, false) => NONE,
                (false, _) => n as u32,
            })
            .collect();
        let r = irregular_nodes(&pts, &border, 23, 23, 0.35 * 14.4);
        assert!(
            r.outliers * 20 <= 525 && r.broken_edges >= 20 && r.refused(525),
            "{r:?}"
        );
        let err = ReferenceLattice::from_assignment(
            pts,
            GridShape::REFERENCE,
            &slipped,
            14.4,
            IndexingConfig::default(),
        )
        .unwrap_err();
        assert!(matches!(err, Error::IrregularLattice { .. }), "{err}");
    }
}
