//! Weighted least-squares maps between two sets of corresponding points, evaluated at one point:
//! where a marker lands, judged by the markers around it.

use gelstereo_core::Point2;
use nalgebra::{SMatrix, SVector};

/// The weighted least-squares affine map of `(from, to, weight)` pairs, evaluated at `at`: where a
/// point of the `from` plane lands in the `to` plane, judged by the points around it. `None` with
/// fewer than 4 pairs or when their `from` points do not span two directions (the spread's
/// determinant below 1 % of `scale`^4; `scale` is the spacing of the points, e.g. the local pitch).
pub(crate) fn affine_at(
    pairs: impl IntoIterator<Item = ([f64; 2], [f64; 2], f64)>,
    at: Point2,
    scale: f64,
) -> Option<Point2> {
    let (mut s, mut sx, mut sy, mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut su, mut sv, mut sxu, mut syu, mut sxv, mut syv) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let mut count = 0;
    for ([fx, fy], [u, v], w) in pairs {
        // Centred on `at`: the sums stay small and the map's offset is the answer.
        let (x, y) = (fx - at.x, fy - at.y);
        count += 1;
        s += w;
        sx += w * x;
        sy += w * y;
        sxx += w * x * x;
        sxy += w * x * y;
        syy += w * y * y;
        su += w * u;
        sv += w * v;
        sxu += w * x * u;
        syu += w * y * u;
        sxv += w * x * v;
        syv += w * y * v;
    }
    if count < 4 {
        return None;
    }
    let (mx, my, mu, mv) = (sx / s, sy / s, su / s, sv / s);
    let (cxx, cxy, cyy) = (sxx / s - mx * mx, sxy / s - mx * my, syy / s - my * my);
    let (cxu, cyu, cxv, cyv) = (
        sxu / s - mx * mu,
        syu / s - my * mu,
        sxv / s - mx * mv,
        syv / s - my * mv,
    );
    // Points along one line (or nearly) leave the map across it undetermined.
    let det = cxx * cyy - cxy * cxy;
    let s2 = scale * scale;
    if det.is_nan() || det < 0.01 * s2 * s2 {
        return None;
    }
    let (bu, cu) = ((cyy * cxu - cxy * cyu) / det, (cxx * cyu - cxy * cxu) / det);
    let (bv, cv) = ((cyy * cxv - cxy * cyv) / det, (cxx * cyv - cxy * cxv) / det);
    Some(Point2::new(mu - bu * mx - cu * my, mv - bv * mx - cv * my))
}

/// The weighted least-squares quadratic map of `(from, to, weight)` pairs (each output coordinate
/// a polynomial of degree 2 in the input), evaluated at `at`; the [`affine_at`] map where the
/// quadratic is undetermined (fewer than 12 pairs, a singular system) or bends more than half of
/// `scale` away from the affine one at `at` (extrapolating, not interpolating). It follows a
/// curved surface: between the two views of a stereo pair the affine map of a marker's neighbours
/// misses the deepest marker of a contact by several times what the quadratic one does.
pub(crate) fn quadratic_at(pairs: &[([f64; 2], [f64; 2], f64)], at: Point2, scale: f64) -> Option<Point2> {
    let affine = affine_at(pairs.iter().copied(), at, scale)?;
    if pairs.len() < 12 {
        return Some(affine);
    }
    let mut normal = SMatrix::<f64, 6, 6>::zeros();
    let (mut bu, mut bv) = (SVector::<f64, 6>::zeros(), SVector::<f64, 6>::zeros());
    for &([fx, fy], [u, v], w) in pairs {
        // Centred on `at` and in units of `scale`: a well-conditioned system.
        let (x, y) = ((fx - at.x) / scale, (fy - at.y) / scale);
        let row = SVector::<f64, 6>::from([1.0, x, y, x * x, x * y, y * y]);
        normal += w * row * row.transpose();
        bu += (w * u) * row;
        bv += (w * v) * row;
    }
    let Some(chol) = normal.cholesky() else {
        return Some(affine);
    };
    let p = Point2::new(chol.solve(&bu)[0], chol.solve(&bv)[0]);
    Some(
        if p.x.is_finite() && p.y.is_finite() && p.distance(affine) <= 0.5 * scale {
            p
        } else {
            affine
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pairs on a 5 x 5 lattice (pitch 10) around the origin, mapped by `map`, weights 1/d^2.
    fn lattice(map: impl Fn(f64, f64) -> [f64; 2]) -> Vec<([f64; 2], [f64; 2], f64)> {
        let mut v = Vec::new();
        for i in -2i32..=2 {
            for j in -2i32..=2 {
                if (i, j) != (0, 0) {
                    let (x, y) = (10.0 * f64::from(i), 10.0 * f64::from(j));
                    v.push(([x, y], map(x, y), 1.0 / f64::from(i * i + j * j)));
                }
            }
        }
        v
    }

    #[test]
    fn affine_and_quadratic_maps_reproduce_what_they_can_represent() {
        let at = Point2::new(0.0, 0.0);
        let affine = |x: f64, y: f64| [3.0 + 1.1 * x - 0.2 * y, -4.0 + 0.1 * x + 0.9 * y];
        let pairs = lattice(affine);
        let p = affine_at(pairs.iter().copied(), at, 10.0).unwrap();
        assert!(p.distance(Point2::new(3.0, -4.0)) < 1e-9, "{p:?}");
        let q = quadratic_at(&pairs, at, 10.0).unwrap();
        assert!(q.distance(Point2::new(3.0, -4.0)) < 1e-9, "{q:?}");
        // A cap (the deepest marker of a contact): the affine map misses its top, the quadratic
        // does not.
        let cap = |x: f64, y: f64| [x + 2.0 - 0.004 * (x * x + y * y), y];
        let pairs = lattice(cap);
        let p = affine_at(pairs.iter().copied(), at, 10.0).unwrap();
        assert!(p.distance(Point2::new(2.0, 0.0)) > 0.5, "{p:?}");
        let q = quadratic_at(&pairs, at, 10.0).unwrap();
        assert!(q.distance(Point2::new(2.0, 0.0)) < 1e-9, "{q:?}");
    }

    #[test]
    fn too_few_or_collinear_pairs_give_no_map() {
        let at = Point2::new(0.0, 0.0);
        let line: Vec<_> = (1..6)
            .map(|i| ([f64::from(i), 0.0], [f64::from(i), 1.0], 1.0))
            .collect();
        assert_eq!(affine_at(line.iter().copied(), at, 1.0), None);
        assert_eq!(quadratic_at(&line, at, 1.0), None);
        assert_eq!(affine_at(line[..3].iter().copied(), at, 0.1), None);
        // Few pairs: the affine map.
        let four = [
            ([1.0, 0.0], [2.0, 0.0], 1.0),
            ([0.0, 1.0], [1.0, 1.0], 1.0),
            ([-1.0, 0.0], [0.0, 0.0], 1.0),
            ([0.0, -1.0], [1.0, -1.0], 1.0),
        ];
        assert_eq!(quadratic_at(&four, at, 1.0), Some(Point2::new(1.0, 0.0)));
    }
}
