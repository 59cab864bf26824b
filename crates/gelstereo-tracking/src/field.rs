//! Dense displacement fields for plots: per-marker values on the lattice, holes filled from their
//! neighbours, then bilinearly interpolated onto a finer grid.

use gelstereo_core::GridShape;

/// A scalar field sampled on a regular grid, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct DenseField {
    /// Samples per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Values, row-major (`width * height`).
    pub values: Vec<f64>,
}

impl DenseField {
    /// Smallest and largest value (0, 0 for an empty field).
    pub fn range(&self) -> (f64, f64) {
        let lo = self.values.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = self.values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if lo.is_finite() && hi.is_finite() {
            (lo, hi)
        } else {
            (0.0, 0.0)
        }
    }
}

/// Interpolates per-marker values (row-major over `shape`, `None` where unknown) onto a grid with
/// `per_cell` samples per lattice step: unknown markers first take the mean of their known
/// 8-neighbours (repeatedly, so holes fill from their rim; still unknown ones take 0), then the
/// lattice is interpolated bilinearly. `None` when `values` does not match `shape` or `per_cell` is 0.
pub fn interpolate(shape: GridShape, values: &[Option<f64>], per_cell: usize) -> Option<DenseField> {
    let (rows, cols) = (usize::from(shape.rows), usize::from(shape.cols));
    if values.len() != rows * cols || per_cell == 0 || rows == 0 || cols == 0 {
        return None;
    }
    let mut v: Vec<Option<f64>> = values.iter().map(|x| x.filter(|x| x.is_finite())).collect();
    for _ in 0..rows.max(cols) {
        let missing: Vec<usize> = (0..v.len()).filter(|&k| v[k].is_none()).collect();
        if missing.is_empty() {
            break;
        }
        let mut filled = Vec::new();
        for k in missing {
            let (r, c) = (k / cols, k % cols);
            let (mut sum, mut n) = (0.0, 0.0);
            for rr in r.saturating_sub(1)..=(r + 1).min(rows - 1) {
                for cc in c.saturating_sub(1)..=(c + 1).min(cols - 1) {
                    if let Some(x) = v[rr * cols + cc] {
                        sum += x;
                        n += 1.0;
                    }
                }
            }
            if n > 0.0 {
                filled.push((k, sum / n));
            }
        }
        if filled.is_empty() {
            break;
        }
        for (k, x) in filled {
            v[k] = Some(x);
        }
    }
    let grid: Vec<f64> = v.iter().map(|x| x.unwrap_or(0.0)).collect();
    let width = (cols - 1) * per_cell + 1;
    let height = (rows - 1) * per_cell + 1;
    let mut out = Vec::with_capacity(width * height);
    let step = 1.0 / per_cell as f64;
    for y in 0..height {
        let fy = y as f64 * step;
        let r0 = (fy.floor() as usize).min(rows.saturating_sub(2));
        let ty = (fy - r0 as f64).clamp(0.0, 1.0);
        for x in 0..width {
            let fx = x as f64 * step;
            let c0 = (fx.floor() as usize).min(cols.saturating_sub(2));
            let tx = (fx - c0 as f64).clamp(0.0, 1.0);
            let at = |r: usize, c: usize| grid[r.min(rows - 1) * cols + c.min(cols - 1)];
            let top = at(r0, c0) * (1.0 - tx) + at(r0, c0 + 1) * tx;
            let bottom = at(r0 + 1, c0) * (1.0 - tx) + at(r0 + 1, c0 + 1) * tx;
            out.push(top * (1.0 - ty) + bottom * ty);
        }
    }
    Some(DenseField {
        width,
        height,
        values: out,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_linear_field_is_reproduced_and_holes_are_filled() {
        let shape = GridShape { rows: 4, cols: 5 };
        let mut v: Vec<Option<f64>> = shape
            .indices()
            .map(|i| Some(f64::from(i.row) + 2.0 * f64::from(i.col)))
            .collect();
        let f = interpolate(shape, &v, 4).unwrap();
        assert_eq!((f.width, f.height), (17, 13));
        for y in 0..f.height {
            for x in 0..f.width {
                let want = y as f64 / 4.0 + 2.0 * x as f64 / 4.0;
                assert!((f.values[y * f.width + x] - want).abs() < 1e-12);
            }
        }
        // A missing interior marker takes its neighbours' mean: exact for a linear field.
        v[7] = None;
        let g = interpolate(shape, &v, 1).unwrap();
        assert!((g.values[7] - (1.0 + 2.0 * 2.0)).abs() < 1e-12);
        assert_eq!(g.range(), (0.0, 3.0 + 8.0));
        assert!(interpolate(shape, &v[..5], 2).is_none());
        assert_eq!(
            interpolate(shape, &vec![None; 20], 2).unwrap().range(),
            (0.0, 0.0)
        );
    }
}
