//! Spacing statistics of point sets: each point's nearest-neighbour distance and their median, the
//! marker pitch measure the post-processing, the lattice check, the closer look and the metrics share.

use gelstereo_core::Point2;
use gelstereo_core::spatial::Buckets;
use gelstereo_core::stats::median;

/// Each point's distance to its nearest other point, px (infinite for a point alone).
pub fn nearest_neighbour_distances(points: &[Point2]) -> Vec<f64> {
    if points.len() < 2 {
        return vec![f64::INFINITY; points.len()];
    }
    let grid = Buckets::with_one_point_per_cell(points);
    (0..points.len())
        .map(|i| grid.nearest_other_px(i).unwrap_or(f64::INFINITY))
        .collect()
}

/// The median of the finite `distances`; `None` without any.
pub fn median_finite(distances: &[f64]) -> Option<f64> {
    median(
        &mut distances
            .iter()
            .copied()
            .filter(|d| d.is_finite())
            .collect::<Vec<_>>(),
    )
}

/// Median nearest-neighbour distance between `points`, px; `None` with fewer than two points.
pub fn median_nearest_neighbour_px(points: &[Point2]) -> Option<f64> {
    median_finite(&nearest_neighbour_distances(points))
}
