//! Contact geometry and slip on the simulator's exact 3-D marker positions (its `markers.csv`,
//! no images, no detector), against its per-frame ground truth (`frames.csv`): the development loop
//! of `docs/tracking.md`, used to choose the defaults of `ContactConfig` and `SlipConfig`.
//!
//! `cargo run --release -p gelstereo-tracking --example truth_eval -- [--noise MM] REC...`
//! (a recording folder per experiment; `VERBOSE=1` prints every contact frame, `PER_RECORDING=1`
//! each recording's geometry medians and gross-slip errors). `--tracked REC OUT ...` replays contact and slip on
//! the 3-D positions a `gelstereo track` run wrote to `OUT/markers.csv` instead (from images, with
//! no localization: a fast loop for slip rules; `score_track` gives the figures of record).

use std::path::Path;

use gelstereo_core::{CsvTable, FrameSummary, GridShape, MarkerRecord, SlipState};
use gelstereo_tracking::{ContactConfig, ReferenceSurface, SlipConfig, SlipDetector};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mut noise = 0.0;
    if args.first().is_some_and(|a| a == "--noise") && args.len() > 1 {
        noise = args[1].parse()?;
        args.drain(..2);
    }
    let tracked = args.first().is_some_and(|a| a == "--tracked");
    if tracked {
        args.remove(0);
        if !args.len().is_multiple_of(2) {
            return Err("--tracked takes pairs REC OUT".into());
        }
    }
    let verbose = std::env::var("VERBOSE").is_ok();
    // PER_RECORDING=1: one line per recording with gross-slip errors.
    let per_recording = std::env::var("PER_RECORDING").is_ok();
    // Tuning overrides: MIN_DEPTH, CONTACT_NOISE, CORE_DEPTH, SLIP_DRIFT,
    // MIN_SHEAR, STICK_SHEAR_PER_DEPTH, SHEAR_NOISE, SHEAR_PER_DEPTH, DRIFT_NOISE, TWIST_GROSS, TURN_RATIO.
    let mut contact_cfg = ContactConfig::default();
    override_from_env("MIN_DEPTH", &mut contact_cfg.min_depth_mm);
    override_from_env("CONTACT_NOISE", &mut contact_cfg.contact_noise_factor);
    let mut slip_cfg = SlipConfig::default();
    override_from_env("SLIP_DRIFT", &mut slip_cfg.drift_mm_per_frame);
    override_from_env("SHEAR_PER_DEPTH", &mut slip_cfg.min_shear_per_depth);
    override_from_env("MIN_SHEAR", &mut slip_cfg.min_shear_mm);
    override_from_env("DRIFT_NOISE", &mut slip_cfg.drift_noise_factor);
    override_from_env("STICK_SHEAR_PER_DEPTH", &mut slip_cfg.stick_shear_per_depth);
    override_from_env("SHEAR_NOISE", &mut slip_cfg.shear_noise_factor);
    override_from_env("CORE_DEPTH", &mut slip_cfg.core_depth_fraction);
    override_from_env("TURN_RATIO", &mut slip_cfg.twist_turn_ratio);
    override_from_env("TWIST_GROSS", &mut slip_cfg.twist_gross_fraction);
    override_from_env("CONE_LOAD", &mut slip_cfg.cone_load_fraction);
    let (mut area_ok, mut depth_ok, mut cent_ok, mut cmp) = (0usize, 0usize, 0usize, 0usize);
    let mut conf = [[0usize; 4]; 4];
    let (mut tp, mut fp, mut fneg) = (0usize, 0usize, 0usize);
    let mut slip_before_contact = 0;
    let mut onset_err = Vec::new();
    let mut ratios = Vec::new();
    let mut cerrs = Vec::new();
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let pairs: Vec<(&String, &String)> = if tracked {
        args.chunks(2).map(|p| (&p[0], &p[1])).collect()
    } else {
        args.iter().map(|a| (a, a)).collect()
    };
    for (rec, positions) in pairs {
        let rec = Path::new(rec);
        let markers = CsvTable::read(&Path::new(positions).join("markers.csv"))?;
        let frames = CsvTable::read(&rec.join("frames.csv"))?;
        let rows: Vec<MarkerRecord> = (0..markers.len())
            .map(|r| MarkerRecord::from_table(&markers, r))
            .collect::<Result<_, _>>()?;
        let truth: Vec<FrameSummary> = (0..frames.len())
            .map(|r| FrameSummary::from_table(&frames, r))
            .collect::<Result<_, _>>()?;
        let shape = GridShape {
            rows: rows.iter().map(|m| m.index.row).max().unwrap_or(0) + 1,
            cols: rows.iter().map(|m| m.index.col).max().unwrap_or(0) + 1,
        };
        let mut per_frame: Vec<Vec<Option<[f64; 3]>>> = vec![vec![None; shape.count()]; truth.len()];
        for m in &rows {
            if let (Some(lin), Some(p)) = (shape.linear(m.index), m.position_mm)
                && let Some(slot) = per_frame.get_mut(m.frame as usize)
            {
                slot[lin] = Some(p.map(|v| v + noise * (2.0 * uniform() - 1.0) * 3f64.sqrt()));
            }
        }
        // The gel thickness of the recording's sensor (as `gelstereo track` reads it from meta.json).
        let mut contact_cfg = contact_cfg.clone();
        if let Some(t) = meta_thickness_mm(&rec.join("meta.json")) {
            contact_cfg.layer.thickness_mm = t;
        }
        let mut surface = match ReferenceSurface::new(shape, &per_frame[0], contact_cfg) {
            Ok(s) => s,
            // A track run that found no reference lattice reports no contact in every frame (as
            // `score_track` scores it).
            Err(e) if tracked => {
                eprintln!("{}: {e}; scored as no contact", rec.display());
                let gt_gross = truth.iter().filter(|g| g.slip == SlipState::GrossSlip).count();
                fneg += gt_gross;
                for gt in &truth {
                    conf[gt.slip as usize][SlipState::NoContact as usize] += 1;
                }
                if gt_gross > 0 {
                    onset_err.push(999);
                }
                continue;
            }
            Err(e) => return Err(e.into()),
        };
        let mut det = SlipDetector::new(slip_cfg.clone())?;
        let (mut gt_onset, mut est_onset) = (None, None);
        let (tp0, fp0, fn0) = (tp, fp, fneg);
        let (r0, c0) = (ratios.len(), cerrs.len());
        let mut derrs = Vec::new();
        let mut touched = false;
        let session_cfg = gelstereo_tracking::SessionConfig::default();
        let reference = per_frame[0].clone();
        for (f, gt) in truth.iter().enumerate() {
            // A track run's written positions again through its outlier test and fill (markers it
            // dropped within the noise floor were written as measured), as the session analyses them.
            if tracked {
                gelstereo_tracking::stereo::reject_outliers(
                    shape,
                    &reference,
                    &mut per_frame[f],
                    session_cfg.outlier_threshold,
                    session_cfg.outlier_noise_mm,
                );
                per_frame[f] =
                    gelstereo_tracking::stereo::fill_from_neighbours(shape, &reference, &per_frame[f]);
            }
            let c = surface.analyze(&per_frame[f])?;
            let sl = det.update(&surface, &c);
            touched |= gt.contact;
            if !touched && sl.state != SlipState::NoContact && sl.state != SlipState::Stick {
                slip_before_contact += 1;
            }
            conf[gt.slip as usize][sl.state as usize] += 1;
            let (g, p) = (gt.slip == SlipState::GrossSlip, sl.state == SlipState::GrossSlip);
            tp += usize::from(g && p);
            fp += usize::from(!g && p);
            fneg += usize::from(g && !p);
            if g && gt_onset.is_none() {
                gt_onset = Some(f);
            }
            if p && est_onset.is_none() {
                est_onset = Some(f);
            }
            let ce = match (gt.centroid_mm, c.centroid_mm) {
                (Some(a), Some(b)) => (a[0] - b.x).hypot(a[1] - b.y),
                _ => f64::INFINITY,
            };
            let (gt_area, gt_depth) = (
                gt.contact_area_mm2.unwrap_or(f64::NAN),
                gt.max_depth_mm.unwrap_or(f64::NAN),
            );
            let ae = (c.contact_area_mm2 - gt_area) / gt_area.max(1e-9);
            let de = c.max_depth_mm - gt_depth;
            // Geometry is scored where the contact is established (ground-truth depth >= 0.1 mm).
            if gt_depth >= 0.1 {
                cmp += 1;
                area_ok += usize::from(ae.abs() <= 0.1);
                ratios.push(1.0 + ae);
                cerrs.push(ce);
                depth_ok += usize::from(de.abs() <= 0.05);
                derrs.push(de);
                cent_ok += usize::from(ce <= 0.2);
            }
            if verbose && (gt.contact || c.contact) {
                // The share of the load on the friction cone, and the shear per unit normal force.
                let (mut slipping, mut load) = (0.0, 0.0);
                for (k, t) in c
                    .traction_kpa
                    .iter()
                    .enumerate()
                    .filter(|(k, _)| c.in_contact[*k])
                {
                    load += t[2];
                    slipping += if c.slipping[k] { t[2] } else { 0.0 };
                }
                println!(
                    "{} f {f:3} area {:6.2}/{:6.2} ({:+.2}) force {:.3}/{:.3} cone {:.2} ratio {:.3}/{:.3} depth {:.3}/{:.3} cent {:.3} slip {:>12}/{:<12} sf {:.2} drift {:+.4} shear {:.3} rot {:+.4} turned {:+.4} noise {:.4}",
                    rec.display(),
                    c.contact_area_mm2,
                    gt_area,
                    ae,
                    c.force_n,
                    gt.force_n.unwrap_or(f64::NAN),
                    slipping / load.max(f64::MIN_POSITIVE),
                    c.shear_n[0].hypot(c.shear_n[1]) / c.force_n.max(f64::MIN_POSITIVE),
                    gt.shear_n.map_or(f64::NAN, |s| s[0].hypot(s[1])) / gt.force_n.unwrap_or(f64::NAN),
                    c.max_depth_mm,
                    gt_depth,
                    ce,
                    sl.state.as_str(),
                    gt.slip.as_str(),
                    sl.stick_fraction,
                    sl.drift_mm,
                    sl.shear_mm.norm(),
                    sl.rotation_rad,
                    sl.turned_rad,
                    c.depth_noise_mm
                );
            }
        }
        let onset = match (gt_onset, est_onset) {
            (Some(a), Some(b)) => Some(b as i64 - a as i64),
            (None, None) => None,
            _ => Some(999),
        };
        onset_err.extend(onset);
        if per_recording && cerrs.len() > c0 {
            // The recording's geometry: median area ratio, signed depth error and centroid error.
            let median = |v: &[f64]| {
                let mut v = v.to_vec();
                v.sort_by(f64::total_cmp);
                v[v.len() / 2]
            };
            println!(
                "{}: geometry {} frames, area ratio {:.2}, depth error {:+.3} mm, centroid error {:.3} mm ({} within 0.2 mm)",
                rec.display(),
                cerrs.len() - c0,
                median(&ratios[r0..]),
                median(&derrs),
                median(&cerrs[c0..]),
                cerrs[c0..].iter().filter(|e| **e <= 0.2).count()
            );
        }
        if per_recording && (fp > fp0 || fneg > fn0 || onset.is_some_and(|o| o.abs() > 2)) {
            println!(
                "{}: gross tp {} fp {} fn {}, onset {:?} (truth {:?})",
                rec.display(),
                tp - tp0,
                fp - fp0,
                fneg - fn0,
                onset,
                gt_onset
            );
        }
    }
    let pct = |a: usize| 100.0 * a as f64 / cmp.max(1) as f64;
    println!(
        "frames with depth >= 0.1 mm: {cmp}; area within 10%: {:.1}%, depth within 0.05 mm: {:.1}%, centroid within 0.2 mm: {:.1}%",
        pct(area_ok),
        pct(depth_ok),
        pct(cent_ok)
    );
    ratios.sort_by(f64::total_cmp);
    cerrs.sort_by(f64::total_cmp);
    let q = |v: &[f64], f: f64| {
        v.get(((v.len().max(1) - 1) as f64 * f) as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    println!(
        "area ratio quartiles {:.2} {:.2} {:.2}; centroid error median {:.3} mm, 90th {:.3} mm",
        q(&ratios, 0.25),
        q(&ratios, 0.5),
        q(&ratios, 0.75),
        q(&cerrs, 0.5),
        q(&cerrs, 0.9)
    );
    let f1 = 2.0 * tp as f64 / (2 * tp + fp + fneg).max(1) as f64;
    println!(
        "gross slip F1 {f1:.3} (tp {tp} fp {fp} fn {fneg}); slip before contact {slip_before_contact}; onset errors {onset_err:?}"
    );
    println!("confusion (rows truth, cols estimate; no_contact stick partial gross): {conf:?}");
    Ok(())
}

/// `sensor.gel.thickness_mm` of a simulated recording's `meta.json` (a plain text search: the
/// example has no JSON dependency), `None` when absent.
fn meta_thickness_mm(path: &Path) -> Option<f64> {
    let text = std::fs::read_to_string(path).ok()?;
    let at = text.find("\"thickness_mm\"")?;
    let rest = text[at..].split_once(':')?.1.trim_start();
    let end = rest.find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-' || c == 'e'))?;
    rest[..end].parse().ok()
}

/// Sets `field` from the environment variable `name` when it is set and parses (a tuning override).
fn override_from_env<T: std::str::FromStr>(name: &str, field: &mut T) {
    if let Some(v) = std::env::var(name).ok().and_then(|v| v.parse().ok()) {
        *field = v;
    }
}
