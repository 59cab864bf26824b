//! Markers cut by the image border, placed at the centre of their whole dot (`docs/localization.md`,
//! "Borders").
//!
//! The network places a dot cut by the border at the middle of its visible part, pulled inwards by up
//! to the dot's radius, so that neither its position nor whether its centre lies inside the image can
//! be read from it. The image's whole dots say what a dot looks like: their patches, averaged around
//! the reported centres (unbiased for whole dots), make a template. A cut dot is then placed where the
//! template, cut by the same border, fits the pixels the image has (least squares with a gain and an
//! offset, so that the background's shading does not matter), its centre free to lie outside the
//! image. A marker whose fitted centre lies outside the image span goes; one whose centre lies inside
//! stays, at the fitted centre. Markers the fit cannot place (too few whole dots to learn from, a
//! poor fit) are left to the lattice's judgement ([`crate::edge`]).

use gelstereo_core::{Detection, ImageSize, Point2, TieredDetections};
use opencv::core::{Mat, MatTraitConst, MatTraitConstManual, Rect};

use crate::Result;
use crate::edge::{drop_past_the_edge_except, inside_the_image_px, outside_the_image};
use crate::squeezed_blobs::grey_roi;
use crate::{check_image, cv_err};

/// Half the side of the template's square, as a share of the pitch: the dot and a ring of the gel
/// around it, short of the neighbouring dots.
const TEMPLATE_HALF_PITCH: f64 = 0.45;

/// Whole dots needed to make a template, and the most averaged into it.
const TEMPLATE_DOTS: (usize, usize) = (4, 24);

/// Smallest contrast between a template's centre and its rim, in standard deviations of the
/// normalised patches: below it the "dots" are not dots.
const MIN_TEMPLATE_CONTRAST: f32 = 1.0;

/// Smallest correlation between the cut template and the image's pixels for a fit to place a marker.
const MIN_FIT_CORRELATION: f64 = 0.8;

/// The ring of gel around a dot (px) whose pixels its fit compares besides the dot's.
const FIT_RING_PX: f64 = 3.0;

/// How far (px) the fit searches past the reported position along an edge and inwards from it.
const SEARCH_SLACK_PX: f64 = 1.5;

/// Step of the coarse search (px), then the pattern search's finest step.
const COARSE_STEP_PX: f64 = 0.5;
const FINEST_STEP_PX: f64 = 1.0 / 16.0;

/// The image in grey, as `f32`, one value per pixel.
struct Grey {
    values: Vec<f32>,
    width: usize,
    height: usize,
}

impl Grey {
    fn of(image: &Mat, size: ImageSize) -> Result<Self> {
        let rect = Rect::new(0, 0, size.width as i32, size.height as i32);
        let grey = grey_roi(image, rect)?;
        let grey = if grey.is_continuous() {
            grey
        } else {
            grey.try_clone().map_err(cv_err("copy of the grey image"))?
        };
        let bytes = grey.data_bytes().map_err(cv_err("reading the grey image"))?;
        Ok(Self {
            values: bytes.iter().map(|&b| f32::from(b)).collect(),
            width: size.width as usize,
            height: size.height as usize,
        })
    }

    fn at(&self, x: usize, y: usize) -> f32 {
        self.values[y * self.width + x]
    }

    /// Bilinear value at `(x, y)`, which must lie within the outermost pixel centres.
    fn sample(&self, x: f64, y: f64) -> f32 {
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let (x0, y0) = (x0 as usize, y0 as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let top = self.at(x0, y0) * (1.0 - fx) + self.at(x1, y0) * fx;
        let bottom = self.at(x0, y1) * (1.0 - fx) + self.at(x1, y1) * fx;
        top * (1.0 - fy) + bottom * fy
    }
}

/// The average whole dot of an image: normalised patches (zero mean, unit deviation) of `2 half + 1`
/// px a side around the reported centres of its whole dots.
struct DotTemplate {
    half: usize,
    values: Vec<f32>,
    /// Where the radial profile crosses halfway between the centre and the rim, px.
    radius_px: f64,
}

impl DotTemplate {
    /// The template of the dots among `markers` that lie whole inside `grey`, when there are enough
    /// of them and they stand out from the gel.
    fn learn(grey: &Grey, markers: &[Detection], pitch_px: f64) -> Option<Self> {
        let half = (TEMPLATE_HALF_PITCH * pitch_px).round().max(3.0) as usize;
        let reach = half as f64 + 1.0;
        let (w, h) = (grey.width as f64, grey.height as f64);
        let whole: Vec<Point2> = markers
            .iter()
            .map(|d| d.position)
            .filter(|p| p.x >= reach && p.y >= reach && p.x <= w - 1.0 - reach && p.y <= h - 1.0 - reach)
            .collect();
        if whole.len() < TEMPLATE_DOTS.0 {
            return None;
        }
        let side = 2 * half + 1;
        let mut values = vec![0.0f32; side * side];
        let mut patch = vec![0.0f32; side * side];
        let stride = whole.len().div_ceil(TEMPLATE_DOTS.1);
        let mut used = 0usize;
        for p in whole.iter().step_by(stride) {
            for (k, v) in patch.iter_mut().enumerate() {
                let (dx, dy) = ((k % side) as f64 - half as f64, (k / side) as f64 - half as f64);
                *v = grey.sample(p.x + dx, p.y + dy);
            }
            if normalise(&mut patch) {
                values.iter_mut().zip(&patch).for_each(|(t, v)| *t += v);
                used += 1;
            }
        }
        if used < TEMPLATE_DOTS.0 {
            return None;
        }
        values.iter_mut().for_each(|t| *t /= used as f32);
        let mut template = Self {
            half,
            values,
            radius_px: 0.0,
        };
        template.radius_px = template.half_contrast_radius()?;
        Some(template)
    }

    /// Bilinear value at offset `(dx, dy)` from the centre (within `half - 1` of it).
    fn sample(&self, dx: f64, dy: f64) -> f32 {
        let side = 2 * self.half + 1;
        let (x, y) = (dx + self.half as f64, dy + self.half as f64);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let (x0, y0) = (x0 as usize, y0 as usize);
        let at = |x: usize, y: usize| self.values[y.min(side - 1) * side + x.min(side - 1)];
        let top = at(x0, y0) * (1.0 - fx) + at(x0 + 1, y0) * fx;
        let bottom = at(x0, y0 + 1) * (1.0 - fx) + at(x0 + 1, y0 + 1) * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// The mean of the template over the circle of radius `r` (px).
    fn ring_mean(&self, r: f64) -> f32 {
        const ANGLES: usize = 32;
        let sum: f32 = (0..ANGLES)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / ANGLES as f64;
                self.sample(r * a.cos(), r * a.sin())
            })
            .sum();
        sum / ANGLES as f32
    }

    /// The radius where the radial profile first crosses halfway from the centre to the rim; `None`
    /// when the centre does not stand out from the rim.
    fn half_contrast_radius(&self) -> Option<f64> {
        let rim_r = self.half as f64 - 1.5;
        let (centre, rim) = (self.sample(0.0, 0.0), self.ring_mean(rim_r));
        if (centre - rim).abs() < MIN_TEMPLATE_CONTRAST {
            return None;
        }
        let mid = 0.5 * (centre + rim);
        let above = |v: f32| (v - mid) * (centre - mid) > 0.0;
        let step = 0.25;
        let mut r_prev = 0.0;
        let mut v_prev = centre;
        let mut r = step;
        while r <= rim_r {
            let v = self.ring_mean(r);
            if !above(v) {
                let t = f64::from((v_prev - mid) / (v_prev - v));
                return Some(r_prev + t * step);
            }
            (r_prev, v_prev) = (r, v);
            r += step;
        }
        None
    }
}

/// Scales `patch` to zero mean and unit deviation; `false` for a flat patch.
fn normalise(patch: &mut [f32]) -> bool {
    let n = patch.len() as f32;
    let mean = patch.iter().sum::<f32>() / n;
    let var = patch.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
    if var < 1.0 {
        return false;
    }
    let inv = var.sqrt().recip();
    patch.iter_mut().for_each(|v| *v = (*v - mean) * inv);
    true
}

/// How well the template centred at `c` fits the image's pixels within [`FIT_RING_PX`] of its dot
/// (those the image has): their correlation (a gain and an offset fitted), `None` where too few pixels
/// or a negative gain.
fn fit_at(grey: &Grey, template: &DotTemplate, c: Point2) -> Option<f64> {
    let half = template.half as f64;
    let reach = (template.radius_px + FIT_RING_PX).min(half - 1.0);
    let x0 = (c.x - reach).ceil().max(0.0) as usize;
    let y0 = (c.y - reach).ceil().max(0.0) as usize;
    let x1 = (c.x + reach).floor().min(grey.width as f64 - 1.0);
    let y1 = (c.y + reach).floor().min(grey.height as f64 - 1.0);
    if x1 < x0 as f64 || y1 < y0 as f64 {
        return None;
    }
    let (x1, y1) = (x1 as usize, y1 as usize);
    // Pixel (x, y) samples the template at (x - c.x + half, y - c.y + half): one fraction for all.
    let (tx, ty) = (x0 as f64 - c.x + half, y0 as f64 - c.y + half);
    let (kx, ky) = (tx.floor(), ty.floor());
    let (fx, fy) = ((tx - kx) as f32, (ty - ky) as f32);
    let weights = [(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy];
    let side = 2 * template.half + 1;
    let (kx, ky) = (kx as usize, ky as usize);
    let cols = x1 - x0 + 1;
    let (mut st, mut sg, mut stt, mut sgg, mut stg) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for row in 0..=(y1 - y0) {
        let t0 = &template.values[(ky + row) * side + kx..];
        let t1 = &template.values[(ky + row + 1) * side + kx..];
        let g_row = &grey.values[(y0 + row) * grey.width + x0..][..cols];
        for (i, &g) in g_row.iter().enumerate() {
            let t = weights[0] * t0[i] + weights[1] * t0[i + 1] + weights[2] * t1[i] + weights[3] * t1[i + 1];
            let (t, g) = (f64::from(t), f64::from(g));
            st += t;
            sg += g;
            stt += t * t;
            sgg += g * g;
            stg += t * g;
        }
    }
    let n = (cols * (y1 - y0 + 1)) as f64;
    if n < 9.0 {
        return None;
    }
    let cov = stg - st * sg / n;
    let (vt, vg) = (stt - st * st / n, sgg - sg * sg / n);
    (cov > 0.0 && vt > 0.0 && vg > 0.0).then(|| cov / (vt * vg).sqrt())
}

/// The centre (and its fit's correlation) of the dot reported at `p`, cut by the border: searched
/// from the reported position outwards across each edge the dot crosses, up to a radius beyond.
fn fit_cut_dot(grey: &Grey, template: &DotTemplate, p: Point2) -> Option<(Point2, f64)> {
    let r = template.radius_px;
    let (w, h) = (grey.width as f64 - 1.0, grey.height as f64 - 1.0);
    // Across an edge the centre lies up to a radius further out than the visible part's middle;
    // along it the visible part is symmetric about it, and the pattern search below suffices.
    let range = |v: f64, last: f64| {
        let (near_low, near_high) = (v < r + 1.0, v > last - r - 1.0);
        let lo = match (near_low, near_high) {
            (true, _) => v - r - SEARCH_SLACK_PX,
            (false, true) => v - SEARCH_SLACK_PX,
            (false, false) => v,
        };
        let hi = match (near_low, near_high) {
            (_, true) => v + r + SEARCH_SLACK_PX,
            (true, false) => v + SEARCH_SLACK_PX,
            (false, false) => v,
        };
        (lo, hi)
    };
    let ((xlo, xhi), (ylo, yhi)) = (range(p.x, w), range(p.y, h));
    let mut best: Option<(Point2, f64)> = None;
    let consider = |c: Point2, best: &mut Option<(Point2, f64)>| {
        if let Some(s) = fit_at(grey, template, c)
            && best.is_none_or(|(_, b)| s > b)
        {
            *best = Some((c, s));
        }
    };
    let steps = |lo: f64, hi: f64| ((hi - lo) / COARSE_STEP_PX).round() as usize;
    for i in 0..=steps(ylo, yhi) {
        for j in 0..=steps(xlo, xhi) {
            let c = Point2::new(xlo + j as f64 * COARSE_STEP_PX, ylo + i as f64 * COARSE_STEP_PX);
            consider(c, &mut best);
        }
    }
    let mut step = 0.5 * COARSE_STEP_PX;
    while step >= FINEST_STEP_PX {
        let (centre, _) = best?;
        for (dx, dy) in [
            (-1.0, 0.0),
            (1.0, 0.0),
            (0.0, -1.0),
            (0.0, 1.0),
            (-1.0, -1.0),
            (1.0, 1.0),
            (-1.0, 1.0),
            (1.0, -1.0),
        ] {
            consider(Point2::new(centre.x + dx * step, centre.y + dy * step), &mut best);
        }
        if best.is_some_and(|(c, _)| c == centre) {
            step *= 0.5;
        }
    }
    best
}

/// What the fit says of a marker near the border.
enum Verdict {
    /// Not cut by the border (or not placed by the fit): left as it is.
    Unjudged,
    /// Cut, its centre inside the image: placed there.
    Inside(Point2),
    /// Cut, its centre outside the image span: not reported.
    Outside,
}

fn judge(grey: &Grey, template: &DotTemplate, d: &Detection, size: ImageSize) -> Verdict {
    let r = template.radius_px;
    if inside_the_image_px(d.position, size) >= r + 1.0 {
        return Verdict::Unjudged;
    }
    let Some((centre, correlation)) = fit_cut_dot(grey, template, d.position) else {
        return Verdict::Unjudged;
    };
    if correlation < MIN_FIT_CORRELATION {
        return Verdict::Unjudged;
    }
    if outside_the_image(centre, size) {
        return Verdict::Outside;
    }
    // A whole dot the fit confirms keeps the network's position.
    if inside_the_image_px(centre, size) >= r {
        return Verdict::Inside(d.position);
    }
    Verdict::Inside(centre)
}

/// Keeps the markers of `image` (accepted and second tier) whose centre lies inside it, each cut dot
/// placed at its whole dot's centre (module doc); the markers the fit cannot place are judged by the
/// lattice ([`crate::edge`]). Nothing changes without a pitch.
pub fn settle_the_border(found: &mut TieredDetections, image: &Mat, pitch_px: Option<f64>) -> Result<()> {
    let Some(pitch) = pitch_px.filter(|p| p.is_finite() && *p > 0.0) else {
        return Ok(());
    };
    let size = check_image(image)?;
    let near_edge = |d: &Detection| inside_the_image_px(d.position, size) < 0.5 * pitch;
    if !found.accepted.iter().chain(&found.second_tier).any(near_edge) {
        return Ok(());
    }
    let grey = Grey::of(image, size)?;
    let Some(template) = DotTemplate::learn(&grey, &found.accepted, pitch) else {
        drop_past_the_edge_except(found, size, Some(pitch), &[]);
        return Ok(());
    };
    let mut placed = Vec::new();
    for tier in [&mut found.accepted, &mut found.second_tier] {
        tier.retain_mut(|d| match judge(&grey, &template, d, size) {
            Verdict::Unjudged => true,
            Verdict::Outside => false,
            Verdict::Inside(centre) => {
                d.position = centre;
                placed.push(centre);
                true
            }
        });
    }
    drop_past_the_edge_except(found, size, Some(pitch), &placed);
    crate::sort_detections(&mut found.accepted);
    crate::sort_detections(&mut found.second_tier);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_8UC3, Point, Scalar};
    use opencv::imgproc;

    fn det(x: f64, y: f64) -> Detection {
        Detection {
            position: Point2::new(x, y),
            confidence: 1.0,
        }
    }

    /// A 320 x 240 gel of dark dots (radius 5.5 px) at `centres`, drawn at 1/16 px.
    fn gel(centres: &[(f64, f64)]) -> Mat {
        let mut img =
            Mat::new_rows_cols_with_default(240, 320, CV_8UC3, Scalar::new(190.0, 180.0, 170.0, 0.0))
                .unwrap();
        for &(x, y) in centres {
            let at = Point::new((x * 16.0).round() as i32, (y * 16.0).round() as i32);
            imgproc::circle(&mut img, at, 88, Scalar::all(45.0), -1, imgproc::LINE_AA, 4).unwrap();
        }
        img
    }

    /// Dots cut by the left border, reported where the network puts them (the middle of their
    /// visible part): the one centred 1 px inside is placed within 0.2 px of its centre, the one
    /// centred 2 px outside goes; whole dots keep their positions.
    #[test]
    fn cut_dots_are_placed_at_their_centre_or_dropped_when_it_lies_outside() {
        let pitch = 29.0;
        let whole: Vec<(f64, f64)> = (0..6)
            .flat_map(|r| (1..8).map(move |c| (30.0 + pitch * f64::from(c), 30.0 + pitch * f64::from(r))))
            .collect();
        let (inside, outside) = ((1.0, 88.0), (-2.0, 146.0));
        let mut centres = whole.clone();
        centres.extend([inside, outside]);
        let image = gel(&centres);
        let mut found = TieredDetections {
            accepted: whole.iter().map(|&(x, y)| det(x, y)).collect(),
            second_tier: Vec::new(),
        };
        // The middle of the visible part: (x + 5.5) / 2 from the edge at -0.5.
        found.accepted.push(det(0.5 * (inside.0 + 5.5) - 0.25, inside.1));
        found
            .accepted
            .push(det(0.5 * (outside.0 + 5.5) - 0.25, outside.1));
        settle_the_border(&mut found, &image, Some(pitch)).unwrap();
        assert_eq!(found.accepted.len(), whole.len() + 1, "{:?}", found.accepted);
        let placed = found
            .accepted
            .iter()
            .find(|d| d.position.x < 10.0)
            .expect("the dot centred inside");
        assert!(
            (placed.position.x - inside.0).abs() < 0.2 && (placed.position.y - inside.1).abs() < 0.2,
            "{:?}",
            placed.position
        );
        for &(x, y) in &whole {
            assert!(found.accepted.contains(&det(x, y)));
        }
    }
}
