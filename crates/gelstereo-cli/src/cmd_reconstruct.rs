//! `gelstereo reconstruct`: localization + grid indexing + left/right pairing + triangulation of a
//! stereo recording (or one stereo pair), written as `OUT/markers.csv` (DESIGN.md per-frame marker
//! table, displacement and status empty) and one binary PLY point cloud per frame
//! (`OUT/ply/NNNNNN.ply`). The work is `gelstereo_matching::StereoReconstructor`; this is input
//! handling, output files and, for simulated recordings, the comparison with the ground truth.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use gelstereo_core::table::MARKER_COLUMNS;
use gelstereo_core::{
    CsvTable, Detection, GridIndex, GridShape, ImageSize, MarkerRecord, Point2, StereoPair,
};
use gelstereo_geometry::{StereoRig, TriangulationConfig};
use gelstereo_io::images;
use gelstereo_io::ply::{MarkerPoint, write_marker_cloud};
use gelstereo_markers::{Localizer, Method};
use gelstereo_matching::{
    FrameReconstruction, IndexingConfig, StereoConfig, StereoPrior, StereoReconstructor,
};
use opencv::prelude::MatTraitConst;

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo reconstruct`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Stereo calibration: OpenCV YAML/XML (K1 D1 K2 D2 R T), or a folder / comma-separated pair of
    /// mrcal .cameramodel files.
    #[arg(long, value_name = "FILE")]
    calib: String,
    /// Output folder (markers.csv, ply/, and evaluation.json with --evaluate).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Localization method: blob, marknet or marknet-mre.
    #[arg(long, default_value = "marknet-mre")]
    method: Method,
    /// Use the ground-truth 2-D marker positions of a simulated RECORDING (its markers.csv, markers
    /// visible in each view) instead of a localizer: measures indexing, pairing and triangulation
    /// alone. The positions go through the same indexing as detections do (their ids are not used).
    #[arg(long)]
    from_ground_truth: bool,
    /// Marker lattice ROWSxCOLS (default: the recording's meta.json, else 23x23).
    #[arg(long, value_name = "ROWSxCOLS")]
    grid: Option<String>,
    /// The no-contact reference frame (number in sorted order) that defines the marker ids.
    #[arg(long, default_value_t = 0)]
    reference: usize,
    /// Index every frame against the reference alone, not seeded by the previous frame.
    #[arg(long)]
    no_prior: bool,
    /// Pairs farther than this from their epipolar line are rejected, px.
    #[arg(long, default_value_t = 2.0)]
    max_epipolar_px: f64,
    /// Triangulated points with a larger reprojection error in either view are rejected, px.
    #[arg(long, default_value_t = 2.0)]
    max_reprojection_px: f64,
    /// Do not write the per-frame PLY point clouds.
    #[arg(long)]
    no_ply: bool,
    /// Compare with the ground truth of a simulated RECORDING (markers.csv, frames.csv): 3-D RMSE,
    /// coverage, wrong pairs and grid-index consistency, printed and written to OUT/evaluation.json.
    #[arg(long)]
    evaluate: bool,
    #[command(flatten)]
    localizer: LocalizerArgs,
    /// A stereo recording (folder with left/ and right/), or LEFT RIGHT: two images (one stereo
    /// frame) or two folders of images with matching names.
    #[arg(value_name = "RECORDING | LEFT RIGHT", num_args = 1..=2, required = true)]
    inputs: Vec<PathBuf>,
}

/// One stereo frame of the input.
struct FrameInput {
    /// Frame number written to markers.csv.
    frame: u32,
    /// Where its detections come from.
    source: FrameSource,
}

enum FrameSource {
    Images(StereoPair<PathBuf>),
    /// Ground-truth 2-D positions (left, right).
    Truth(StereoPair<Vec<Detection>>),
}

/// Ground truth of one marker in one frame of a simulated recording.
#[derive(Debug, Clone, Copy)]
struct TruthMarker {
    left_px: Option<Point2>,
    right_px: Option<Point2>,
    position_mm: Option<[f64; 3]>,
    in_contact: bool,
}

/// A simulated recording's ground truth: per frame, per index.
struct Truth {
    frames: BTreeMap<u32, BTreeMap<GridIndex, TruthMarker>>,
    contact_frames: BTreeMap<u32, bool>,
}

fn read_truth(dir: &Path) -> anyhow::Result<Truth> {
    let path = dir.join("markers.csv");
    let table = CsvTable::read(&path).with_context(|| {
        format!(
            "--from-ground-truth / --evaluate need the simulator's {}",
            path.display()
        )
    })?;
    table
        .require(&["visible_left", "visible_right", "in_contact"])
        .with_context(|| {
            format!(
                "{}: not a simulated recording's ground truth (visible_left/visible_right/in_contact)",
                path.display()
            )
        })?;
    let mut frames: BTreeMap<u32, BTreeMap<GridIndex, TruthMarker>> = BTreeMap::new();
    for row in 0..table.len() {
        let rec = MarkerRecord::from_table(&table, row)?;
        let flag = |c: &str| -> anyhow::Result<bool> { Ok(table.value::<u8>(row, c, "0 or 1")? == 1) };
        let (vis_left, vis_right) = (flag("visible_left")?, flag("visible_right")?);
        let m = TruthMarker {
            left_px: rec.left_px.filter(|_| vis_left),
            right_px: rec.right_px.filter(|_| vis_right),
            position_mm: rec.position_mm,
            in_contact: flag("in_contact")?,
        };
        frames.entry(rec.frame).or_default().insert(rec.index, m);
    }
    let mut contact_frames = BTreeMap::new();
    let fpath = dir.join("frames.csv");
    if fpath.exists() {
        let ft = CsvTable::read(&fpath)?;
        for row in 0..ft.len() {
            let frame: u32 = ft.value(row, "frame", "a frame number")?;
            let contact: u8 = ft.value(row, "contact", "0 or 1")?;
            contact_frames.insert(frame, contact == 1);
        }
    }
    Ok(Truth {
        frames,
        contact_frames,
    })
}

fn parse_grid(text: &str) -> anyhow::Result<GridShape> {
    let parsed = text
        .split_once(['x', 'X'])
        .and_then(|(r, c)| Some((r.trim().parse().ok()?, c.trim().parse().ok()?)));
    match parsed {
        Some((rows, cols)) if rows >= 2 && cols >= 2 => Ok(GridShape { rows, cols }),
        _ => bail!("--grid '{text}': expected ROWSxCOLS with at least 2 of each, e.g. 23x23"),
    }
}

/// The grid shape and image size a simulated recording's meta.json states, if any.
fn read_meta(dir: &Path) -> anyhow::Result<(Option<GridShape>, Option<ImageSize>)> {
    let path = dir.join("meta.json");
    if !path.exists() {
        return Ok((None, None));
    }
    let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not valid JSON", path.display()))?;
    let u = |a: &str, b: Option<&str>| {
        let x = v.get(a)?;
        let x = match b {
            Some(b) => x.get(b)?,
            None => x,
        };
        x.as_u64()
    };
    let grid = match (u("grid", Some("rows")), u("grid", Some("cols"))) {
        (Some(r), Some(c)) => Some(GridShape {
            rows: u16::try_from(r).with_context(|| format!("{}: grid.rows {r} too large", path.display()))?,
            cols: u16::try_from(c).with_context(|| format!("{}: grid.cols {c} too large", path.display()))?,
        }),
        _ => None,
    };
    let size = match (u("image_width", None), u("image_height", None)) {
        (Some(w), Some(h)) => Some(ImageSize {
            width: u32::try_from(w)?,
            height: u32::try_from(h)?,
        }),
        _ => None,
    };
    Ok((grid, size))
}

/// Left and right image lists paired by file name.
fn paired_folders(left: &Path, right: &Path) -> anyhow::Result<Vec<StereoPair<PathBuf>>> {
    let l = images::list_images(left)?;
    let r = images::list_images(right)?;
    let name = |p: &PathBuf| {
        p.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let right_names: BTreeMap<String, PathBuf> = r.iter().map(|p| (name(p), p.clone())).collect();
    if l.is_empty() {
        bail!("{}: no images", left.display());
    }
    if l.len() != r.len() {
        bail!(
            "{} holds {} images but {} holds {}: expected the same file names",
            left.display(),
            l.len(),
            right.display(),
            r.len()
        );
    }
    l.iter()
        .map(|p| match right_names.get(&name(p)) {
            Some(q) => Ok(StereoPair::new(p.clone(), q.clone())),
            None => bail!(
                "{} has no counterpart {}",
                p.display(),
                right.join(name(p)).display()
            ),
        })
        .collect()
}

fn image_size(m: &opencv::core::Mat) -> ImageSize {
    ImageSize {
        width: u32::try_from(m.cols()).unwrap_or(0),
        height: u32::try_from(m.rows()).unwrap_or(0),
    }
}

/// Runs `gelstereo reconstruct`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let rig = StereoRig::load(&args.calib)
        .with_context(|| format!("cannot load the calibration '{}'", args.calib))?;
    let recording = (args.inputs.len() == 1).then(|| args.inputs[0].clone());
    let (meta_grid, meta_size) = match &recording {
        Some(dir) => read_meta(dir)?,
        None => (None, None),
    };
    let shape = match &args.grid {
        Some(text) => parse_grid(text)?,
        None => meta_grid.unwrap_or(GridShape::REFERENCE),
    };
    if let Some(size) = meta_size {
        rig.check_image_sizes(size, size)
            .context("the recording's meta.json image size does not match the calibration")?;
    }
    let truth = match (&recording, args.from_ground_truth || args.evaluate) {
        (Some(dir), true) => Some(read_truth(dir)?),
        (None, true) => {
            bail!("--from-ground-truth and --evaluate need a simulated RECORDING folder, not LEFT RIGHT")
        }
        _ => None,
    };

    // The frames.
    let frames: Vec<FrameInput> = if args.from_ground_truth {
        let Some(truth) = &truth else {
            bail!("--from-ground-truth needs a simulated RECORDING")
        };
        truth
            .frames
            .iter()
            .map(|(&frame, markers)| {
                let det = |p: Option<Point2>| {
                    p.map(|position| Detection {
                        position,
                        confidence: 1.0,
                    })
                };
                FrameInput {
                    frame,
                    source: FrameSource::Truth(StereoPair::new(
                        markers.values().filter_map(|m| det(m.left_px)).collect(),
                        markers.values().filter_map(|m| det(m.right_px)).collect(),
                    )),
                }
            })
            .collect()
    } else {
        let pairs = match args.inputs.as_slice() {
            [dir] => {
                let rec = images::StereoRecording::open(dir)?;
                (0..rec.len()).filter_map(|i| rec.paths(i)).collect()
            }
            [l, r] if l.is_dir() && r.is_dir() => paired_folders(l, r)?,
            [l, r] => vec![StereoPair::new(l.clone(), r.clone())],
            _ => bail!("give a stereo RECORDING folder, or LEFT RIGHT"),
        };
        pairs
            .into_iter()
            .enumerate()
            .map(|(i, p)| -> anyhow::Result<FrameInput> {
                Ok(FrameInput {
                    frame: u32::try_from(i).context("too many frames")?,
                    source: FrameSource::Images(p),
                })
            })
            .collect::<anyhow::Result<_>>()?
    };
    if frames.is_empty() {
        bail!("the input holds no stereo frames");
    }
    let Some(reference) = frames.get(args.reference) else {
        bail!(
            "--reference {}: the input has only {} frames",
            args.reference,
            frames.len()
        );
    };

    let mut localizer: Option<Box<dyn Localizer>> = if args.from_ground_truth {
        None
    } else {
        Some(args.localizer.localizer(args.method)?)
    };
    let mut detect = |input: &FrameInput| -> anyhow::Result<(StereoPair<Vec<Detection>>, f64)> {
        match (&input.source, localizer.as_mut()) {
            (FrameSource::Truth(d), _) => Ok((d.clone(), 0.0)),
            (FrameSource::Images(paths), Some(loc)) => {
                let read =
                    |p: &PathBuf| images::read_image(p).with_context(|| format!("frame {}", input.frame));
                let pair = StereoPair::new(read(&paths.left)?, read(&paths.right)?);
                rig.check_image_sizes(image_size(&pair.left), image_size(&pair.right))
                    .with_context(|| {
                        format!(
                            "{}: the images do not match the calibration '{}'",
                            paths.left.display(),
                            args.calib
                        )
                    })?;
                let t = Instant::now();
                let found = loc
                    .detect_stereo(&pair)
                    .with_context(|| format!("localizing {}", paths.left.display()))?;
                Ok((found, t.elapsed().as_secs_f64() * 1e3))
            }
            (FrameSource::Images(_), None) => bail!("no localizer"),
        }
    };

    let config = StereoConfig {
        max_epipolar_px: args.max_epipolar_px,
        indexing: IndexingConfig::default(),
    };
    let triangulation = TriangulationConfig {
        max_reprojection_error_px: args.max_reprojection_px,
        ..Default::default()
    };
    let (ref_dets, _) = detect(reference)?;
    let reconstructor = StereoReconstructor::new(
        &rig,
        &ref_dets.left,
        &ref_dets.right,
        shape,
        config,
        triangulation,
    )
    .with_context(|| {
        format!(
            "indexing the reference frame {} ({} left / {} right markers) as a {}x{} lattice",
            reference.frame,
            ref_dets.left.len(),
            ref_dets.right.len(),
            shape.rows,
            shape.cols
        )
    })?;

    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    let ply_dir = args.out.join("ply");
    if !args.no_ply {
        std::fs::create_dir_all(&ply_dir).with_context(|| format!("cannot create {}", ply_dir.display()))?;
    }
    let mut csv = MARKER_COLUMNS.join(",");
    csv.push('\n');
    let mut prior: Option<StereoPrior> = None;
    let (mut localize_ms, mut match_ms, mut reconstructed, mut paired_rejected) = (0.0, 0.0, 0usize, 0usize);
    let mut results: Vec<(u32, FrameReconstruction)> = Vec::with_capacity(frames.len());
    for input in &frames {
        let (dets, loc_ms) = detect(input)?;
        localize_ms += loc_ms;
        let t = Instant::now();
        let rec = reconstructor
            .reconstruct(
                &dets.left,
                &dets.right,
                if args.no_prior { None } else { prior.as_ref() },
            )
            .with_context(|| format!("frame {}", input.frame))?;
        match_ms += t.elapsed().as_secs_f64() * 1e3;
        if !args.no_prior {
            prior = Some(rec.matched.to_prior());
        }
        for m in &rec.markers {
            m.record(input.frame).write_csv(&mut csv);
            csv.push('\n');
        }
        reconstructed += rec.reconstructed_count();
        paired_rejected += rec.markers.iter().filter(|m| m.rejection.is_some()).count();
        if !args.no_ply {
            let points: Vec<MarkerPoint> = rec
                .markers
                .iter()
                .filter_map(|m| {
                    Some(MarkerPoint {
                        index: m.index,
                        position_mm: m.position_mm?,
                        reprojection_error_px: m.reprojection_error_px?,
                    })
                })
                .collect();
            let path = ply_dir.join(format!("{:06}.ply", input.frame));
            write_marker_cloud(&path, &points, &format!("frame {}", input.frame))?;
        }
        results.push((input.frame, rec));
    }
    let csv_path = args.out.join("markers.csv");
    std::fs::write(&csv_path, csv).with_context(|| format!("cannot write {}", csv_path.display()))?;
    let n = frames.len() as f64;
    eprintln!(
        "{} frames, {}x{} lattice: {:.1} markers reconstructed per frame ({} pairs rejected in all); \
         localization {:.2} ms/frame, indexing+pairing+triangulation {:.3} ms/frame; wrote {}{}",
        frames.len(),
        shape.rows,
        shape.cols,
        reconstructed as f64 / n,
        paired_rejected,
        localize_ms / n,
        match_ms / n,
        csv_path.display(),
        if args.no_ply {
            String::new()
        } else {
            format!(" and {}/", ply_dir.display())
        }
    );
    if args.evaluate {
        let Some(truth) = &truth else {
            bail!("--evaluate needs a simulated RECORDING")
        };
        let pitch = StereoPair::new(
            reconstructor.lattice().left().pitch_px(),
            reconstructor.lattice().right().pitch_px(),
        );
        let report = evaluate(truth, &results, pitch, match_ms / n);
        let path = args.out.join("evaluation.json");
        let text = serde_json::to_string_pretty(&report).context("cannot format the evaluation")?;
        std::fs::write(&path, text + "\n").with_context(|| format!("cannot write {}", path.display()))?;
        eprintln!("{}", summary_text(&report));
    }
    Ok(())
}

/// Counts behind one row of the evaluation.
#[derive(Default, Clone, Copy)]
struct Counts {
    visible_left: usize,
    detected_left: usize,
    index_correct: usize,
    index_wrong: usize,
    visible_both: usize,
    reconstructed: usize,
    reconstructed_of_visible_both: usize,
    wrong_pairs: usize,
    sq_error_mm2: f64,
    max_error_mm: f64,
}

impl Counts {
    fn json(&self) -> serde_json::Value {
        let frac = |a: usize, b: usize| {
            if b == 0 {
                serde_json::Value::Null
            } else {
                (a as f64 / b as f64).into()
            }
        };
        let rmse = if self.reconstructed == 0 {
            serde_json::Value::Null
        } else {
            (self.sq_error_mm2 / self.reconstructed as f64).sqrt().into()
        };
        serde_json::json!({
            "markers_visible_left": self.visible_left,
            "markers_detected_left": self.detected_left,
            "index_correct": self.index_correct,
            "index_wrong": self.index_wrong,
            "index_consistency": frac(self.index_correct, self.detected_left),
            "markers_visible_both": self.visible_both,
            "reconstructed": self.reconstructed,
            "coverage": frac(self.reconstructed_of_visible_both, self.visible_both),
            "wrong_pairs": self.wrong_pairs,
            "wrong_pair_rate": frac(self.wrong_pairs, self.reconstructed),
            "rmse_mm": rmse,
            "max_error_mm": self.max_error_mm,
        })
    }
}

/// The true index of every left detection: the nearest visible ground-truth marker within `r_px`,
/// matched one-to-one nearest pairs first (DESIGN.md "Metrics"); `None` for spurious detections.
fn true_indices(
    view: &gelstereo_matching::IndexedView,
    gt: &BTreeMap<GridIndex, TruthMarker>,
    r_px: f64,
) -> Vec<Option<GridIndex>> {
    let mut cand: Vec<(f64, usize, GridIndex)> = Vec::new();
    for d in 0..view.detection_count() {
        let Some(p) = view.detection_position(d) else {
            continue;
        };
        for (idx, t) in gt {
            if let Some(q) = t.left_px {
                let dist = p.distance(q);
                if dist <= r_px {
                    cand.push((dist, d, *idx));
                }
            }
        }
    }
    cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut out = vec![None; view.detection_count()];
    let mut used = std::collections::BTreeSet::new();
    for (_, d, idx) in cand {
        if out[d].is_none() && used.insert(idx) {
            out[d] = Some(idx);
        }
    }
    out
}

/// DESIGN.md metrics against the simulator's ground truth, with r = 0.25 x pitch (px) per view:
/// grid-index consistency (of the left detections that are true markers, the fraction given their
/// true id; `index_wrong` also counts spurious detections that received an id), coverage
/// (reconstructed / visible in both views), wrong pairs (left or right point farther than r from
/// the marker's own), 3-D RMSE over the reconstructed markers.
fn evaluate(
    truth: &Truth,
    results: &[(u32, FrameReconstruction)],
    pitch_px: StereoPair<f64>,
    match_ms: f64,
) -> serde_json::Value {
    let r = StereoPair::new(0.25 * pitch_px.left, 0.25 * pitch_px.right);
    // [all, contact frames, in-contact markers]
    let mut c = [Counts::default(); 3];
    let empty = BTreeMap::new();
    for (frame, rec) in results {
        let gt = truth.frames.get(frame).unwrap_or(&empty);
        let contact_frame = truth.contact_frames.get(frame).copied().unwrap_or(false);
        let mut add = |in_contact: bool, f: &dyn Fn(&mut Counts)| {
            f(&mut c[0]);
            if contact_frame {
                f(&mut c[1]);
            }
            if in_contact {
                f(&mut c[2]);
            }
        };
        let left = &rec.matched.left;
        for (d, t) in true_indices(left, gt, r.left).into_iter().enumerate() {
            let given = left.index_of(d);
            let in_contact = t.and_then(|t| gt.get(&t)).is_some_and(|m| m.in_contact);
            match (t, given) {
                (Some(t), Some(g)) if t == g => add(in_contact, &|c| {
                    c.detected_left += 1;
                    c.index_correct += 1;
                }),
                (Some(_), Some(_)) => add(in_contact, &|c| {
                    c.detected_left += 1;
                    c.index_wrong += 1;
                }),
                (Some(_), None) => add(in_contact, &|c| c.detected_left += 1),
                (None, Some(_)) => add(false, &|c| c.index_wrong += 1),
                (None, None) => {}
            }
        }
        for m in &rec.markers {
            let t = gt.get(&m.index);
            let in_contact = t.is_some_and(|t| t.in_contact);
            let t_left = t.and_then(|t| t.left_px);
            let t_right = t.and_then(|t| t.right_px);
            if t_left.is_some() {
                add(in_contact, &|c| c.visible_left += 1);
            }
            if t_left.is_some() && t_right.is_some() {
                add(in_contact, &|c| c.visible_both += 1);
            }
            if let (Some(pos), Some(right)) = (m.position_mm, m.right_px) {
                let right_ok = t_right.is_some_and(|q| right.distance(q) <= r.right);
                let left_ok = t_left
                    .zip(m.left_px)
                    .is_some_and(|(q, p)| p.distance(q) <= r.left);
                let err = t.and_then(|t| t.position_mm).map(|g| {
                    ((pos[0] - g[0]).powi(2) + (pos[1] - g[1]).powi(2) + (pos[2] - g[2]).powi(2)).sqrt()
                });
                add(in_contact, &|c| {
                    c.reconstructed += 1;
                    if t_left.is_some() && t_right.is_some() {
                        c.reconstructed_of_visible_both += 1;
                    }
                    if !(right_ok && left_ok) {
                        c.wrong_pairs += 1;
                    }
                    if let Some(e) = err {
                        c.sq_error_mm2 += e * e;
                        c.max_error_mm = c.max_error_mm.max(e);
                    }
                });
            }
        }
    }
    serde_json::json!({
        "frames": results.len(),
        "r_px": { "left": r.left, "right": r.right },
        "matching_ms_per_frame": match_ms,
        "all": c[0].json(),
        "contact_frames": c[1].json(),
        "in_contact_markers": c[2].json(),
    })
}

fn summary_text(v: &serde_json::Value) -> String {
    let mut s = String::new();
    for key in ["all", "contact_frames", "in_contact_markers"] {
        let g = &v[key];
        let pct = |k: &str| {
            g[k].as_f64()
                .map_or("-".to_owned(), |x| format!("{:.3}%", 100.0 * x))
        };
        let mm = |k: &str| g[k].as_f64().map_or("-".to_owned(), |x| format!("{x:.2e} mm"));
        let _ = writeln!(
            s,
            "{key}: 3-D RMSE {} (max {}), coverage {}, wrong pairs {} ({}), index consistency {} ({} wrong of {} detected)",
            mm("rmse_mm"),
            mm("max_error_mm"),
            pct("coverage"),
            g["wrong_pairs"],
            pct("wrong_pair_rate"),
            pct("index_consistency"),
            g["index_wrong"],
            g["markers_detected_left"],
        );
    }
    s.trim_end().to_owned()
}
