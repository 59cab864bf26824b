//! Scores `gelstereo track` outputs against simulated ground truth (the figures of
//! `docs/tracking.md`, "Accuracy"): id swaps (docs/design.md: ids that ever map to more than one ground-truth marker),
//! the share of visible markers tracked per frame, wrong associations (a marker written `tracked`
//! more than 0.25 pitch from its own true position in either view), contact area / largest depth / centroid errors,
//! gross-slip F1 per frame, onset delay, and slip reported before contact.
//!
//! `cargo run --release -p gelstereo-tracking --example score_track -- REC OUT [REC OUT ...]`
//! (`REC` a simulated recording, `OUT` the folder `gelstereo track` wrote for it). `--swaps` first
//! lists every swapped id: recording, id, and each ground-truth marker it mapped to with its frames.
//!
//! Where `gelstereo track` could not place a grid that overfills the view on the sensor's own
//! indices (visible top-left marker = (0, 0)), the output's ids are shifted by the whole (row, col)
//! offset most of the reference frame's markers agree on before scoring; that is printed.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use gelstereo_core::{CsvTable, FrameSummary, GridIndex, MarkerRecord, MarkerStatus, Point2, SlipState};

struct Truth {
    index: GridIndex,
    left: Option<Point2>,
    right: Option<Point2>,
    visible_both: bool,
}

fn read_markers(path: &Path) -> Result<(Vec<MarkerRecord>, CsvTable), Box<dyn std::error::Error>> {
    let t = CsvTable::read(path)?;
    let rows = (0..t.len())
        .map(|r| MarkerRecord::from_table(&t, r))
        .collect::<Result<Vec<_>, _>>()?;
    Ok((rows, t))
}

fn read_frames(path: &Path) -> Result<Vec<FrameSummary>, Box<dyn std::error::Error>> {
    let t = CsvTable::read(path)?;
    Ok((0..t.len())
        .map(|r| FrameSummary::from_table(&t, r))
        .collect::<Result<Vec<_>, _>>()?)
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(((v.len().max(1) - 1) as f64 * q).round() as usize)
        .copied()
        .unwrap_or(f64::NAN)
}

/// Shifts the estimated ids by the (row, col) offset to the ground truth that most markers of the
/// reference frame agree on (nearest true marker within `r` px in the left view), when it is
/// not zero: ids counted from a visible top-left marker instead of the sensor's grid.
fn align_ids(rec: &Path, est: &mut Vec<MarkerRecord>, truth: &BTreeMap<u32, Vec<Truth>>, r: f64) {
    // The reference frame: the first with positions (frames before it are written as lost).
    let Some(first) = est.iter().filter(|m| m.left_px.is_some()).map(|m| m.frame).min() else {
        return;
    };
    let mut votes: BTreeMap<(i32, i32), usize> = BTreeMap::new();
    for m in est.iter().filter(|m| m.frame == first) {
        let Some(p) = m.left_px else { continue };
        let nearest = truth
            .get(&first)
            .into_iter()
            .flatten()
            .filter_map(|t| t.left.map(|q| (q.distance(p), t.index)))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        if let Some((_, t)) = nearest.filter(|n| n.0 <= r) {
            let d = (
                i32::from(t.row) - i32::from(m.index.row),
                i32::from(t.col) - i32::from(m.index.col),
            );
            *votes.entry(d).or_default() += 1;
        }
    }
    let total: usize = votes.values().sum();
    let Some((&(dr, dc), &n)) = votes.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0))) else {
        return;
    };
    if (dr, dc) == (0, 0) {
        return;
    }
    println!(
        "{}: ids aligned with the ground truth by ({dr:+}, {dc:+}) rows, columns ({n} of {total} reference markers agree)",
        rec.display()
    );
    est.retain_mut(|m| {
        let row = u16::try_from(i32::from(m.index.row) + dr);
        let col = u16::try_from(i32::from(m.index.col) + dc);
        match (row, col) {
            (Ok(row), Ok(col)) => {
                m.index = GridIndex::new(row, col);
                true
            }
            _ => false,
        }
    });
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let list_swaps = args.first().is_some_and(|a| a == "--swaps");
    if list_swaps {
        args.remove(0);
    }
    if args.len() < 2 || !args.len().is_multiple_of(2) {
        return Err("usage: score_track REC OUT [REC OUT ...]".into());
    }
    let (mut swaps, mut ids_total) = (0usize, 0usize);
    let (mut wrong, mut tracked_total) = (0usize, 0usize);
    let mut worst_tracked: f64 = 1.0;
    let mut tracked_fracs = Vec::new();
    let (mut area_err, mut depth_err, mut cent_err) = (Vec::new(), Vec::new(), Vec::new());
    let (mut tp, mut fp, mut fneg) = (0usize, 0usize, 0usize);
    let mut onsets = Vec::new();
    let mut before_contact = 0usize;
    let mut frames_total = 0usize;
    for pair in args.chunks(2) {
        let (rec, out) = (Path::new(&pair[0]), Path::new(&pair[1]));
        let (gt_rows, gt_table) = read_markers(&rec.join("markers.csv"))?;
        let (mut est_rows, _) = read_markers(&out.join("markers.csv"))?;
        let gt_frames = read_frames(&rec.join("frames.csv"))?;
        let est_frames = read_frames(&out.join("frames.csv"))?;
        let mut truth: BTreeMap<u32, Vec<Truth>> = BTreeMap::new();
        for (r, m) in gt_rows.iter().enumerate() {
            let vis = |c: &str| gt_table.cell(r, c).map(|s| s == "1").unwrap_or(false);
            truth.entry(m.frame).or_default().push(Truth {
                index: m.index,
                left: m.left_px.filter(|_| vis("visible_left")),
                right: m.right_px.filter(|_| vis("visible_right")),
                visible_both: vis("visible_left") && vis("visible_right"),
            });
        }
        // Pitch in the left view of the reference frame: median distance to the next column.
        let f0: BTreeMap<GridIndex, Point2> = truth
            .get(&0)
            .map(|v| v.iter().filter_map(|t| t.left.map(|p| (t.index, p))).collect())
            .unwrap_or_default();
        let mut d: Vec<f64> = f0
            .iter()
            .filter_map(|(i, p)| f0.get(&GridIndex::new(i.row, i.col + 1)).map(|q| p.distance(*q)))
            .collect();
        let r = 0.25 * quantile(&mut d, 0.5);
        // Id swaps: output ids that map (nearest visible ground-truth marker within r) to more than
        // one ground-truth marker over the recording.
        align_ids(rec, &mut est_rows, &truth, r);
        let mut maps: BTreeMap<GridIndex, BTreeSet<GridIndex>> = BTreeMap::new();
        // Per output id and ground-truth marker: first frame, last frame, frames.
        let mut spans: BTreeMap<(GridIndex, GridIndex), (u32, u32, u32)> = BTreeMap::new();
        let mut est_by_frame: BTreeMap<u32, Vec<&MarkerRecord>> = BTreeMap::new();
        for m in &est_rows {
            est_by_frame.entry(m.frame).or_default().push(m);
        }
        for (f, rows) in &est_by_frame {
            let Some(gt) = truth.get(f) else { continue };
            let by_id: BTreeMap<GridIndex, &Truth> = gt.iter().map(|t| (t.index, t)).collect();
            let mut tracked = 0usize;
            let mut visible = 0usize;
            for m in rows {
                if let Some(p) = m.left_px.filter(|_| m.status != Some(MarkerStatus::Lost)) {
                    let nearest = gt
                        .iter()
                        .filter_map(|t| t.left.map(|q| (q.distance(p), t.index)))
                        .min_by(|a, b| a.0.total_cmp(&b.0));
                    if let Some((_, id)) = nearest.filter(|n| n.0 <= r) {
                        maps.entry(m.index).or_default().insert(id);
                        let e = spans.entry((m.index, id)).or_insert((*f, *f, 0));
                        e.1 = *f;
                        e.2 += 1;
                    }
                }
                // A tracked marker must sit on its own marker in each view it has a position in.
                if m.status == Some(MarkerStatus::Tracked) {
                    tracked_total += 1;
                    let t = by_id.get(&m.index);
                    let off = |p: Option<Point2>, q: Option<Point2>| match (p, q) {
                        (Some(p), Some(q)) => p.distance(q) > r,
                        (Some(_), None) => true,
                        (None, _) => false,
                    };
                    if t.is_none_or(|t| off(m.left_px, t.left) || off(m.right_px, t.right)) {
                        wrong += 1;
                    }
                }
                if by_id.get(&m.index).is_some_and(|t| t.visible_both) {
                    visible += 1;
                    tracked += usize::from(m.status == Some(MarkerStatus::Tracked));
                }
            }
            if visible > 0 {
                let frac = tracked as f64 / visible as f64;
                worst_tracked = worst_tracked.min(frac);
                tracked_fracs.push(frac);
            }
        }
        if list_swaps {
            for (id, set) in maps.iter().filter(|(_, s)| s.len() > 1) {
                let parts: Vec<String> = set
                    .iter()
                    .map(|g| {
                        let (a, b, c) = spans[&(*id, *g)];
                        format!("{g} in {c} frames {a}-{b}")
                    })
                    .collect();
                println!("swap {} id {id}: {}", rec.display(), parts.join("; "));
            }
        }
        ids_total += maps.len();
        swaps += maps.values().filter(|s| s.len() > 1).count();
        // Contact and slip.
        let (mut gt_onset, mut est_onset) = (None, None);
        let mut touched = false;
        for (g, e) in gt_frames.iter().zip(&est_frames) {
            frames_total += 1;
            touched |= g.contact;
            let slipping = matches!(e.slip, SlipState::PartialSlip | SlipState::GrossSlip);
            before_contact += usize::from(!touched && slipping);
            let (gg, eg) = (g.slip == SlipState::GrossSlip, e.slip == SlipState::GrossSlip);
            tp += usize::from(gg && eg);
            fp += usize::from(!gg && eg);
            fneg += usize::from(gg && !eg);
            if gg && gt_onset.is_none() {
                gt_onset = Some(g.frame);
            }
            if eg && est_onset.is_none() {
                est_onset = Some(e.frame);
            }
            // Unknown values (mono estimates) score as NaN.
            let known = |v: Option<f64>| v.unwrap_or(f64::NAN);
            if known(g.max_depth_mm) >= 0.1 {
                let (ga, ea) = (known(g.contact_area_mm2), known(e.contact_area_mm2));
                area_err.push((ea - ga).abs() / ga);
                depth_err.push((known(e.max_depth_mm) - known(g.max_depth_mm)).abs());
                cent_err.push(match (g.centroid_mm, e.centroid_mm) {
                    (Some(a), Some(b)) => (a[0] - b[0]).hypot(a[1] - b[1]),
                    _ => f64::INFINITY,
                });
            }
        }
        match (gt_onset, est_onset) {
            (Some(a), Some(b)) => onsets.push(i64::from(b) - i64::from(a)),
            (None, None) => {}
            (Some(_), None) => onsets.push(i64::MAX),
            (None, Some(_)) => onsets.push(i64::MIN),
        }
    }
    let within =
        |v: &[f64], t: f64| 100.0 * v.iter().filter(|x| **x <= t).count() as f64 / v.len().max(1) as f64;
    println!("recordings {}, frames {frames_total}", args.len() / 2);
    println!("ids {ids_total}, id swaps {swaps}");
    println!(
        "tracked marker-frames {tracked_total}, wrong associations (> 0.25 pitch off its own truth) {wrong}"
    );
    println!(
        "visible markers tracked per frame: worst {:.2} %, median {:.2} %",
        100.0 * worst_tracked,
        100.0 * quantile(&mut tracked_fracs, 0.5)
    );
    println!(
        "frames with ground-truth depth >= 0.1 mm: {}; area within 10 %: {:.1} % (median error {:.1} %), depth within 0.05 mm: {:.1} % (median {:.3} mm), centroid within 0.2 mm: {:.1} % (median {:.3} mm)",
        area_err.len(),
        within(&area_err, 0.1),
        100.0 * quantile(&mut area_err.clone(), 0.5),
        within(&depth_err, 0.05),
        quantile(&mut depth_err.clone(), 0.5),
        within(&cent_err, 0.2),
        quantile(&mut cent_err.clone(), 0.5)
    );
    let f1 = 2.0 * tp as f64 / (2 * tp + fp + fneg).max(1) as f64;
    // `unsigned_abs`: `i64::MIN` (a false onset) has no `abs` (it wrapped and counted as within).
    let ok = onsets.iter().filter(|o| o.unsigned_abs() <= 2).count();
    let fmt: Vec<String> = onsets
        .iter()
        .map(|o| match *o {
            i64::MAX => "missed".to_owned(),
            i64::MIN => "false".to_owned(),
            o => format!("{o:+}"),
        })
        .collect();
    println!(
        "gross slip per-frame F1 {f1:.3} (tp {tp}, fp {fp}, fn {fneg}); onset within 2 frames in {ok} of {} recordings with gross slip in either ([{}])",
        onsets.len(),
        fmt.join(" ")
    );
    println!("frames with slip reported before the first contact: {before_contact}");
    Ok(())
}
