//! Best-first lattice growth: the engine behind both reference indexing and per-frame indexing.
//!
//! Every lattice node `n` has a *base* position `base[n]` (the reference frame's position of the
//! marker, or a global affine lattice when indexing a reference from scratch). A node is predicted
//! from the nodes already assigned within `fit_radius` lattice steps by fitting, in weighted least
//! squares, a local affine model of the displacement `detection - base` over lattice coordinates
//! (weights `1 / d⁴`, d in lattice steps, so the nearest neighbours dominate where the deformation
//! bends) and evaluating it at `n`. A small ridge term on the gradient
//! makes the fit well posed with one neighbour or collinear neighbours, where it falls back to
//! copying the neighbours' displacement. This is local lattice growth with locally adapted basis
//! vectors: the fitted gradient is the local deformation of the lattice.
//!
//! Growth pops the node whose prediction lies closest to a free detection (a priority queue with
//! lazy invalidation), assigns it if the detection lies within the gate, and re-predicts the
//! unassigned neighbours. Assignment is one-to-one by construction: a detection leaves the free set
//! when it is assigned, and a node whose best detection was taken meanwhile is re-predicted.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

use gelstereo_core::Point2;
use nalgebra::{Matrix3, Vector3};

use gelstereo_core::spatial::Buckets;

/// Marks "no node" / "no detection" in the dense assignment arrays.
pub(crate) const NONE: u32 = u32::MAX;

/// Ridge weight on the displacement gradient (px per lattice step) of the local fit, relative to the
/// weight 1 of a direct neighbour: small enough not to bias a fit with 3+ neighbours in general
/// position, large enough to keep the normal matrix invertible with one neighbour.
const RIDGE: f64 = 0.02;

/// A node is only assigned when the runner-up detection is at least this many times farther from
/// its prediction than the chosen one: with a prediction error e (in pitches) the true marker is at
/// e and the neighbours at about 1 - e, so this rejects nothing below e = 0.4 (the gate) on a clean
/// lattice, but defers nodes whose prediction falls between two detections.
const AMBIGUITY_RATIO: f64 = 1.5;

/// A candidate assignment in the queue: cost first, then node and detection numbers for a
/// deterministic order among equal costs.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    cost: f64,
    node: u32,
    det: u32,
    version: u32,
}

impl PartialEq for Candidate {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Candidate {}
impl PartialOrd for Candidate {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Candidate {
    fn cmp(&self, other: &Self) -> Ordering {
        // Reversed: BinaryHeap is a max-heap and we want the lowest cost first.
        other
            .cost
            .total_cmp(&self.cost)
            .then(other.node.cmp(&self.node))
            .then(other.det.cmp(&self.det))
            .then(other.version.cmp(&self.version))
    }
}

/// State of one growth run over a `rows x cols` lattice.
pub(crate) struct Grower<'a, F: Fn(usize, usize) -> bool> {
    pub(crate) rows: usize,
    pub(crate) cols: usize,
    base: &'a [Point2],
    buckets: &'a Buckets,
    gate_px: f64,
    fit_radius: i64,
    admissible: F,
    pub(crate) node_det: Vec<u32>,
    pub(crate) det_node: Vec<u32>,
    version: Vec<u32>,
    /// Whether a node was assigned by growth (not given as a seed).
    grown: Vec<bool>,
    /// Fit weight `1 / d⁴` of each offset of the (2 fit_radius + 1)² window, row-major.
    weights: Vec<f64>,
    heap: BinaryHeap<Candidate>,
}

impl<'a, F: Fn(usize, usize) -> bool> Grower<'a, F> {
    /// A run with nothing assigned. `admissible(node, det)` may veto pairs (the epipolar gate).
    pub(crate) fn new(
        rows: usize,
        cols: usize,
        base: &'a [Point2],
        buckets: &'a Buckets,
        gate_px: f64,
        fit_radius: usize,
        admissible: F,
    ) -> Self {
        debug_assert_eq!(base.len(), rows * cols);
        Self {
            rows,
            cols,
            base,
            buckets,
            gate_px,
            fit_radius: fit_radius.max(1) as i64,
            admissible,
            node_det: vec![NONE; rows * cols],
            det_node: vec![NONE; buckets.points().len()],
            version: vec![0; rows * cols],
            grown: vec![false; rows * cols],
            weights: {
                let rad = fit_radius.max(1) as i64;
                (-rad..=rad)
                    .flat_map(|dr| (-rad..=rad).map(move |dc| (dr * dr + dc * dc) as f64))
                    .map(|q| if q == 0.0 { 0.0 } else { 1.0 / (q * q) })
                    .collect()
            },
            heap: BinaryHeap::new(),
        }
    }

    fn det_pos(&self, d: usize) -> Point2 {
        self.buckets.points()[d]
    }

    /// Assigns detection `d` to node `n` (both must be free).
    pub(crate) fn assign(&mut self, n: usize, d: usize) {
        self.node_det[n] = d as u32;
        self.det_node[d] = n as u32;
    }

    /// Removes the assignment of node `n`, if any.
    pub(crate) fn unassign(&mut self, n: usize) {
        let d = self.node_det[n];
        if d != NONE {
            self.det_node[d as usize] = NONE;
            self.node_det[n] = NONE;
            self.grown[n] = false;
        }
    }

    /// Predicted position of node `n` from the assigned nodes around it (excluding `n` itself);
    /// `None` when none is assigned within the fit radius. Also returns how many were used.
    pub(crate) fn predict(&self, n: usize) -> Option<(Point2, usize)> {
        let (r0, c0) = ((n / self.cols) as i64, (n % self.cols) as i64);
        let rad = self.fit_radius;
        // Weighted sums of the normal equations of u(dc, dr) = a + b dc + c dr (symmetric 3x3).
        let (mut s0, mut sc, mut sr, mut scc, mut scr, mut srr) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let (mut bx, mut bxc, mut bxr, mut by, mut byc, mut byr) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        let mut count = 0usize;
        for r in (r0 - rad).max(0)..=(r0 + rad).min(self.rows as i64 - 1) {
            let row = (r as usize) * self.cols;
            for c in (c0 - rad).max(0)..=(c0 + rad).min(self.cols as i64 - 1) {
                let m = row + c as usize;
                let d = self.node_det[m];
                if d == NONE || m == n {
                    continue;
                }
                let (dc, dr) = ((c - c0) as f64, (r - r0) as f64);
                let w = self.weights[((r - r0 + rad) * (2 * rad + 1) + (c - c0 + rad)) as usize];
                let p = self.det_pos(d as usize);
                let (ux, uy) = (w * (p.x - self.base[m].x), w * (p.y - self.base[m].y));
                s0 += w;
                sc += w * dc;
                sr += w * dr;
                scc += w * dc * dc;
                scr += w * dc * dr;
                srr += w * dr * dr;
                bx += ux;
                bxc += ux * dc;
                bxr += ux * dr;
                by += uy;
                byc += uy * dc;
                byr += uy * dr;
                count += 1;
            }
        }
        if count == 0 {
            return None;
        }
        let a = Matrix3::new(s0, sc, sr, sc, scc + RIDGE, scr, sr, scr, srr + RIDGE);
        let inv = a.try_inverse()?;
        let dx = (inv * Vector3::new(bx, bxc, bxr))[0];
        let dy = (inv * Vector3::new(by, byc, byr))[0];
        let p = Point2::new(self.base[n].x + dx, self.base[n].y + dy);
        (p.x.is_finite() && p.y.is_finite()).then_some((p, count))
    }

    /// The nearest free, admissible detection within the gate of `pred`, with its distance; `None`
    /// also when another detection (free or not) lies within [`AMBIGUITY_RATIO`] times that
    /// distance: such a node waits until more of its neighbours are placed.
    fn best_free(&self, n: usize, pred: Point2) -> Option<(usize, f64)> {
        let mut best: Option<(usize, f64)> = None;
        let mut all: [f64; 2] = [f64::INFINITY; 2];
        let reach = self.gate_px * AMBIGUITY_RATIO;
        self.buckets.for_each_within(pred, reach, |d, d2| {
            if d2 < all[0] {
                all = [d2, all[0]];
            } else if d2 < all[1] {
                all[1] = d2;
            }
            if d2 > self.gate_px * self.gate_px || self.det_node[d] != NONE {
                return;
            }
            let better = match best {
                None => true,
                Some((bd, b2)) => d2 < b2 || (d2 == b2 && d < bd),
            };
            if better && (self.admissible)(n, d) {
                best = Some((d, d2));
            }
        });
        let (d, d2) = best?;
        // The runner-up among all detections (the best one is all[0] unless a nearer one is taken
        // or vetoed, in which case that nearer one is the competitor).
        let rival = if d2 <= all[0] { all[1] } else { all[0] };
        let floor = (0.05 * self.gate_px).powi(2);
        (rival > AMBIGUITY_RATIO * AMBIGUITY_RATIO * d2.max(floor)).then(|| (d, d2.sqrt()))
    }

    /// Re-predicts unassigned node `n` and queues its best candidate (invalidating older entries).
    fn evaluate(&mut self, n: usize) {
        if self.node_det[n] != NONE {
            return;
        }
        self.version[n] = self.version[n].wrapping_add(1);
        let Some((pred, _)) = self.predict(n) else { return };
        if let Some((d, dist)) = self.best_free(n, pred) {
            self.heap.push(Candidate {
                cost: dist,
                node: n as u32,
                det: d as u32,
                version: self.version[n],
            });
        }
    }

    fn neighbours(&self, n: usize, radius: i64) -> impl Iterator<Item = usize> + use<F> {
        let (rows, cols) = (self.rows as i64, self.cols as i64);
        let (r0, c0) = ((n as i64) / cols, (n as i64) % cols);
        ((r0 - radius).max(0)..=(r0 + radius).min(rows - 1)).flat_map(move |r| {
            ((c0 - radius).max(0)..=(c0 + radius).min(cols - 1))
                .filter(move |&c| !(r == r0 && c == c0))
                .map(move |c| (r * cols + c) as usize)
        })
    }

    /// Grows from the current assignment until no node can be assigned any more.
    pub(crate) fn grow(&mut self) {
        let nodes = self.rows * self.cols;
        self.heap.clear();
        // Queue every unassigned node that has an assigned node within the fit radius.
        let mut dirty: Vec<bool> = (0..nodes)
            .map(|n| {
                self.node_det[n] == NONE
                    && self
                        .neighbours(n, self.fit_radius)
                        .any(|m| self.node_det[m] != NONE)
            })
            .collect();
        loop {
            let todo: Vec<usize> = (0..nodes).filter(|&n| std::mem::take(&mut dirty[n])).collect();
            for n in todo {
                self.evaluate(n);
            }
            if self.heap.is_empty() {
                return;
            }
            while let Some(c) = self.heap.pop() {
                let (n, d) = (c.node as usize, c.det as usize);
                if self.node_det[n] != NONE || self.version[n] != c.version {
                    continue;
                }
                if self.det_node[d] != NONE {
                    self.evaluate(n);
                    continue;
                }
                self.assign(n, d);
                self.grown[n] = true;
                // Direct neighbours are re-predicted at once; the rest of the fit window is marked
                // for the next sweep (it matters only to bridge missing markers).
                let (r0, c0) = (n / self.cols, n % self.cols);
                for m in self.neighbours(n, self.fit_radius).collect::<Vec<_>>() {
                    if self.node_det[m] != NONE {
                        continue;
                    }
                    let (r, c) = (m / self.cols, m % self.cols);
                    if r.abs_diff(r0) <= 1 && c.abs_diff(c0) <= 1 {
                        self.evaluate(m);
                    } else {
                        dirty[m] = true;
                    }
                }
            }
        }
    }

    /// Replaces the base positions (e.g. a prior by the reference lattice) keeping the assignment.
    pub(crate) fn set_base(&mut self, base: &'a [Point2]) {
        debug_assert_eq!(base.len(), self.rows * self.cols);
        self.base = base;
    }

    /// Leave-one-out check of the nodes placed by growth, and of the seeds too with `seeds`:
    /// unassigns every node whose detection lies farther than the gate from the prediction of at
    /// least `min_support` assigned neighbours. Returns how many were removed.
    pub(crate) fn prune_outliers(&mut self, min_support: usize, seeds: bool) -> usize {
        let mut bad = Vec::new();
        for n in 0..self.rows * self.cols {
            let d = self.node_det[n];
            if d == NONE || !(seeds || self.grown[n]) {
                continue;
            }
            if let Some((pred, count)) = self.predict(n)
                && count >= min_support
                && pred.distance(self.det_pos(d as usize)) > self.gate_px
            {
                bad.push(n);
            }
        }
        for &n in &bad {
            self.unassign(n);
        }
        bad.len()
    }
}
