//! A uniform bucket grid over 2-D points for fixed-radius queries.
//!
//! For the few hundred to few thousand detections of one view, with query radii below one marker
//! pitch, a bucket grid whose cell is about one pitch answers a radius query by looking at 3 x 3
//! cells; it is built in one counting-sort pass and its answers come in a deterministic order
//! (by cell, then by detection number), which keeps marker ids reproducible.

use crate::Point2;

/// The most cells along one side; a wider spread of points gets larger cells.
const MAX_CELLS_PER_SIDE: f64 = 2048.0;

/// The bounding box `[x_min, y_min, x_max, y_max]` of `points`; all zero when there are none.
fn bounds(points: &[Point2]) -> [f64; 4] {
    if points.is_empty() {
        return [0.0; 4];
    }
    points.iter().fold(
        [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY],
        |[x0, y0, x1, y1], p| [x0.min(p.x), y0.min(p.y), x1.max(p.x), y1.max(p.y)],
    )
}

/// `v.floor()` for the cell arithmetic, inlined: without SSE4.1 in the baseline target `f64::floor`
/// is a call into libm, and the radius queries made it a few percent of the post-processing. Exact for
/// |v| < 2^63; beyond that, and for NaN (0 here), the comparisons and casts of the queries treat
/// what it gives as they treat `f64::floor`'s value.
#[inline]
fn floor(v: f64) -> f64 {
    // Truncating cast: saturating, NaN to 0.
    let t = v as i64 as f64;
    if t > v { t - 1.0 } else { t }
}

/// The cells `x.0..=x.1` by `y.0..=y.1` of a grid `nx` cells wide.
struct CellSpan {
    nx: usize,
    x: (usize, usize),
    y: (usize, usize),
}

impl CellSpan {
    /// The first and last cell of each row of the span.
    fn rows(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        (self.y.0..=self.y.1).map(|cy| (cy * self.nx + self.x.0, cy * self.nx + self.x.1))
    }
}

/// Points sorted into square cells.
#[derive(Debug, Clone)]
pub struct Buckets {
    x0: f64,
    y0: f64,
    inv_cell: f64,
    nx: usize,
    ny: usize,
    /// `start[c]..start[c + 1]` are the entries of cell `c` in `items`.
    start: Vec<u32>,
    items: Vec<u32>,
    /// `points[items[k]]` for every `k`: the queries read the points of a run of cells from one
    /// contiguous slice instead of through the index.
    item_points: Vec<Point2>,
    points: Vec<Point2>,
}

impl Buckets {
    /// Sorts `points` (all finite) into cells of about `cell_px` pixels.
    pub fn new(points: &[Point2], cell_px: f64) -> Self {
        let [x0, y0, x1, y1] = bounds(points);
        let span = (x1 - x0).max(y1 - y0).max(1.0);
        let cell = if cell_px.is_finite() && cell_px > 0.0 {
            cell_px
        } else {
            span
        };
        let cell = cell.max(span / MAX_CELLS_PER_SIDE);
        let inv_cell = 1.0 / cell;
        // Truncating casts of finite, non-negative values bounded by MAX_CELLS_PER_SIDE.
        let nx = ((x1 - x0) * inv_cell) as usize + 1;
        let ny = ((y1 - y0) * inv_cell) as usize + 1;
        let cell_of = |p: &Point2| -> usize {
            let cx = (((p.x - x0) * inv_cell) as usize).min(nx - 1);
            let cy = (((p.y - y0) * inv_cell) as usize).min(ny - 1);
            cy * nx + cx
        };
        let mut start = vec![0u32; nx * ny + 1];
        for p in points {
            start[cell_of(p) + 1] += 1;
        }
        for c in 0..nx * ny {
            start[c + 1] += start[c];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; points.len()];
        for (i, p) in points.iter().enumerate() {
            let c = cell_of(p);
            items[fill[c] as usize] = i as u32;
            fill[c] += 1;
        }
        let item_points = items.iter().map(|&i| points[i as usize]).collect();
        Self {
            x0,
            y0,
            inv_cell,
            nx,
            ny,
            start,
            items,
            item_points,
            points: points.to_vec(),
        }
    }

    /// Sorts `points` into cells of about one point each on average (side sqrt(area / n)), the size
    /// for nearest-neighbour queries when no pitch is known.
    pub fn with_one_point_per_cell(points: &[Point2]) -> Self {
        let [x0, y0, x1, y1] = bounds(points);
        let (w, h) = ((x1 - x0).max(1e-6), (y1 - y0).max(1e-6));
        Self::new(points, (w * h / points.len().max(1) as f64).sqrt())
    }

    /// The points, in the order given.
    pub fn points(&self) -> &[Point2] {
        &self.points
    }

    /// Whether some point lies within `radius_px` of `p`. It stops at the first such point: the
    /// lattice's site tests ask this thousands of times per view, mostly of sites a marker holds.
    pub fn any_within(&self, p: Point2, radius_px: f64) -> bool {
        let r2 = radius_px * radius_px;
        let Some(span) = self.cells_within(p, radius_px) else {
            return false;
        };
        span.rows().any(|(first, last)| {
            self.item_points[self.run(first, last)]
                .iter()
                .any(|q| (q.x - p.x).powi(2) + (q.y - p.y).powi(2) <= r2)
        })
    }

    /// Calls `f(index, squared_distance)` for every point within `radius_px` of `p`.
    pub fn for_each_within(&self, p: Point2, radius_px: f64, mut f: impl FnMut(usize, f64)) {
        let r2 = radius_px * radius_px;
        let Some(span) = self.cells_within(p, radius_px) else {
            return;
        };
        // The cells of one row are consecutive in `items`: one loop per row, not per cell (the loop
        // exits of the nearly empty cells were what a query spent its time on).
        for (first, last) in span.rows() {
            let run = self.run(first, last);
            for (&i, q) in self.items[run.clone()].iter().zip(&self.item_points[run]) {
                let d2 = (q.x - p.x).powi(2) + (q.y - p.y).powi(2);
                if d2 <= r2 {
                    f(i as usize, d2);
                }
            }
        }
    }

    /// The cells within `radius_px` of `p`; `None` for a point that is not finite, an empty grid, or
    /// a square around `p` that misses the grid.
    #[inline]
    fn cells_within(&self, p: Point2, radius_px: f64) -> Option<CellSpan> {
        if !(p.x.is_finite() && p.y.is_finite()) || self.points.is_empty() {
            return None;
        }
        let lo_x = floor((p.x - radius_px - self.x0) * self.inv_cell);
        let hi_x = floor((p.x + radius_px - self.x0) * self.inv_cell);
        let lo_y = floor((p.y - radius_px - self.y0) * self.inv_cell);
        let hi_y = floor((p.y + radius_px - self.y0) * self.inv_cell);
        if hi_x < 0.0 || hi_y < 0.0 || lo_x >= self.nx as f64 || lo_y >= self.ny as f64 {
            return None;
        }
        Some(CellSpan {
            nx: self.nx,
            x: (lo_x.max(0.0) as usize, (hi_x as usize).min(self.nx - 1)),
            y: (lo_y.max(0.0) as usize, (hi_y as usize).min(self.ny - 1)),
        })
    }

    /// The entries of cells `first..=last` (of one row) in `items`.
    fn run(&self, first: usize, last: usize) -> std::ops::Range<usize> {
        self.start[first] as usize..self.start[last + 1] as usize
    }

    /// The smallest squared distance from `p` to the points of cells `first..=last` (of one row)
    /// other than point `i`, or `best` if none is closer.
    fn nearest_in_run(&self, p: Point2, i: usize, (first, last): (usize, usize), mut best: f64) -> f64 {
        let run = self.run(first, last);
        for (&j, q) in self.items[run.clone()].iter().zip(&self.item_points[run]) {
            if j as usize != i {
                best = best.min((q.x - p.x) * (q.x - p.x) + (q.y - p.y) * (q.y - p.y));
            }
        }
        best
    }

    /// Distance from `points[i]` to its nearest other point, px (`None` if it is alone or `i` is out of
    /// range). Searches square rings of cells outwards until no closer point can remain: until the
    /// nearest one found is no farther than the edge of the cells searched (a side at the grid's
    /// edge has nothing beyond it).
    pub fn nearest_other_px(&self, i: usize) -> Option<f64> {
        let p = *self.points.get(i)?;
        let cell_px = 1.0 / self.inv_cell;
        let cx = (((p.x - self.x0) * self.inv_cell) as usize).min(self.nx - 1) as isize;
        let cy = (((p.y - self.y0) * self.inv_cell) as usize).min(self.ny - 1) as isize;
        let (nx, ny) = (self.nx as isize, self.ny as isize);
        // Where `p` lies in its cell, and a margin far above the rounding of the cell arithmetic
        // (a point may sit a few ulps outside the cell it was sorted into).
        let fx = p.x - self.x0 - cx as f64 * cell_px;
        let fy = p.y - self.y0 - cy as f64 * cell_px;
        let margin = 1e-9 * (cell_px + self.x0.abs() + self.y0.abs() + p.x.abs() + p.y.abs());
        // Rings 0 and 1 first, as three runs of cells (a nearest point mostly lies in them), then
        // ring by ring outwards.
        let (x0, x1) = ((cx - 1).max(0) as usize, (cx + 1).min(nx - 1) as usize);
        let mut best = f64::INFINITY;
        for gy in (cy - 1).max(0)..=(cy + 1).min(ny - 1) {
            let row = gy as usize * self.nx;
            best = self.nearest_in_run(p, i, (row + x0, row + x1), best);
        }
        for ring in 1..=nx.max(ny) {
            if ring > 1 {
                best = self.nearest_in_ring(p, i, (cx, cy), ring, best);
            }
            let reach =
                clearance(cx, nx, ring, fx, cell_px).min(clearance(cy, ny, ring, fy, cell_px)) - margin;
            if best.is_finite() && reach > 0.0 && best <= reach * reach {
                break;
            }
        }
        best.is_finite().then(|| best.sqrt())
    }

    /// [`nearest_in_run`](Self::nearest_in_run) over the cells `ring` cells away from cell `(cx, cy)`:
    /// the ring's top and bottom rows whole, its other rows at their two ends.
    fn nearest_in_ring(
        &self,
        p: Point2,
        i: usize,
        (cx, cy): (isize, isize),
        ring: isize,
        mut best: f64,
    ) -> f64 {
        let (nx, ny) = (self.nx as isize, self.ny as isize);
        let row = |gy: isize| gy as usize * self.nx;
        let (x0, x1) = ((cx - ring).max(0) as usize, (cx + ring).min(nx - 1) as usize);
        let edge_rows = if ring == 0 { 1 } else { 2 };
        for gy in [cy - ring, cy + ring].into_iter().take(edge_rows) {
            if (0..ny).contains(&gy) {
                best = self.nearest_in_run(p, i, (row(gy) + x0, row(gy) + x1), best);
            }
        }
        for gy in (cy - ring + 1).max(0)..=(cy + ring - 1).min(ny - 1) {
            for gx in [cx - ring, cx + ring] {
                if (0..nx).contains(&gx) {
                    let c = row(gy) + gx as usize;
                    best = self.nearest_in_run(p, i, (c, c), best);
                }
            }
        }
        best
    }
}

/// Along one axis of `n` cells: the distance from a point at `offset` into cell `c` to the cells more
/// than `ring` cells away from `c`, on the nearer side that has any (infinite when neither has).
fn clearance(c: isize, n: isize, ring: isize, offset: f64, cell_px: f64) -> f64 {
    let below = if c - ring > 0 {
        offset + ring as f64 * cell_px
    } else {
        f64::INFINITY
    };
    let above = if c + ring < n - 1 {
        (ring + 1) as f64 * cell_px - offset
    } else {
        f64::INFINITY
    };
    below.min(above)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radius_queries_match_brute_force() {
        // A deterministic scatter (Weyl sequence) with a far outlier that forces large cells.
        let mut pts: Vec<Point2> = (0..300)
            .map(|i| {
                let f = f64::from(i);
                Point2::new((f * 0.618_034).fract() * 400.0, (f * 0.414_214).fract() * 300.0)
            })
            .collect();
        pts.push(Point2::new(1e7, -1e7));
        let b = Buckets::new(&pts, 20.0);
        for (k, q) in [
            Point2::new(10.0, 10.0),
            Point2::new(200.0, 150.0),
            Point2::new(-30.0, 5.0),
        ]
        .iter()
        .enumerate()
        {
            for r in [0.0, 7.5, 25.0, 90.0] {
                let mut got = Vec::new();
                b.for_each_within(*q, r, |i, _| got.push(i));
                got.sort_unstable();
                let want: Vec<usize> = (0..pts.len()).filter(|&i| pts[i].distance(*q) <= r).collect();
                assert_eq!(b.any_within(*q, r), !want.is_empty(), "any: query {k} radius {r}");
                assert_eq!(got, want, "query {k} radius {r}");
            }
        }
    }

    /// The inlined floor agrees with `f64::floor` wherever the cell arithmetic can land.
    #[test]
    fn the_cell_floor_is_the_floor() {
        let values = [-2.5, -1e-12, -0.0, 0.0, 0.5, 2047.75, 1e15 + 0.5, -1e15];
        for v in values {
            assert_eq!(floor(v), v.floor(), "{v}");
        }
        // Out of range: on the same side of every cell index as `f64::floor`'s value.
        assert!(floor(1e300) >= 1e18 && floor(f64::INFINITY) >= 1e18);
        assert!(floor(-1e300) < 0.0 && floor(f64::NEG_INFINITY) < 0.0);
    }

    /// The ring search stops early only where no unsearched point can be closer: its answer is the
    /// brute-force minimum to the last bit, on a jittered lattice (many near-ties at the pitch) and
    /// with cells of every size around it.
    #[test]
    fn nearest_neighbours_are_the_exact_minimum() {
        let pts: Vec<Point2> = (0..400)
            .map(|k| {
                let (r, c) = (f64::from(k / 20), f64::from(k % 20));
                Point2::new(
                    c * 14.3 + (r * 0.37).sin() * 1e-3,
                    r * 14.3 + (c * 0.3).cos() * 1e-3,
                )
            })
            .collect();
        let mut grids = vec![Buckets::with_one_point_per_cell(&pts)];
        grids.extend([3.0, 7.15, 14.3, 14.31, 20.0, 50.0].map(|cell| Buckets::new(&pts, cell)));
        for grid in &grids {
            for (i, p) in pts.iter().enumerate() {
                let brute = (0..pts.len())
                    .filter(|&j| j != i)
                    .map(|j| (pts[j].x - p.x) * (pts[j].x - p.x) + (pts[j].y - p.y) * (pts[j].y - p.y))
                    .fold(f64::INFINITY, f64::min)
                    .sqrt();
                assert_eq!(grid.nearest_other_px(i), Some(brute), "point {i}");
            }
        }
    }

    #[test]
    fn nearest_neighbours_match_brute_force() {
        let mut state = 7u64;
        let mut rnd = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for n in [2usize, 3, 17, 400] {
            let mut pts: Vec<Point2> = (0..n)
                .map(|_| Point2::new(640.0 * rnd(), 30.0 * rnd() * rnd()))
                .collect();
            pts.push(pts[0]);
            pts.push(Point2::new(pts[1].x + 0.01, pts[1].y));
            for cell_px in [0.5, 7.0, 1000.0] {
                let grid = Buckets::new(&pts, cell_px);
                for i in 0..pts.len() {
                    let brute = (0..pts.len())
                        .filter(|&j| j != i)
                        .map(|j| pts[i].distance(pts[j]))
                        .fold(f64::INFINITY, f64::min);
                    let got = grid.nearest_other_px(i).unwrap();
                    assert!(
                        (got - brute).abs() < 1e-12,
                        "n={n} cell={cell_px} i={i}: {got} vs {brute}"
                    );
                }
            }
        }
        assert_eq!(
            Buckets::new(&[Point2::new(1.0, 1.0)], 1.0).nearest_other_px(0),
            None
        );
    }
}
