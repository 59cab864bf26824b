//! `gelstereo reconstruct`: localization + grid indexing + left/right pairing + triangulation of a
//! stereo recording (or one stereo pair), written as `OUT/markers.csv` (docs/design.md per-frame marker
//! table, displacement and status empty) and one binary PLY point cloud per frame
//! (`OUT/ply/NNNNNN.ply`). The work is `gelstereo_matching::StereoReconstructor`; this is input
//! handling, output files and, for simulated recordings, the comparison with the ground truth.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use gelstereo_core::table::MARKER_COLUMNS;
use gelstereo_core::{Detection, GridShape, ImageSize, Point2, StereoPair};
use gelstereo_geometry::{StereoRig, TriangulationConfig};
use gelstereo_io::images;
use gelstereo_io::ply::{MarkerPoint, write_marker_cloud};
use gelstereo_markers::{Localizer, Method};
use gelstereo_matching::eval::{Counts, Evaluation, GroundTruth};
use gelstereo_matching::{IndexingConfig, StereoConfig, StereoPrior, StereoReconstructor};
use opencv::prelude::MatTraitConst;

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo reconstruct`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Stereo calibration: OpenCV YAML/XML (K1 D1 K2 D2 R T), or a folder / comma-separated pair of
    /// mrcal .cameramodel files.
    #[arg(long, value_name = "FILE")]
    calib: String,
    /// Output folder: markers.csv, ply/NNNNNN.ply, rejected_pairs.csv (markers seen in both views
    /// but not triangulated, with the reason) and, with --evaluate, evaluation.json.
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
    #[command(flatten)]
    perturb: Perturbation,
    /// Seed of the --gt-* perturbations.
    #[arg(long, default_value_t = 0)]
    seed: u64,
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
    #[arg(long, default_value_t = 3.0)]
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
    /// A stereo recording (folder with left/ and right/), a side-by-side stereo video (left half,
    /// right half), or LEFT RIGHT: two images (one stereo frame) or two folders of images with
    /// matching names.
    #[arg(value_name = "RECORDING | LEFT RIGHT", num_args = 1..=2, required = true)]
    inputs: Vec<PathBuf>,
}

/// Imperfections added to ground-truth positions (with --from-ground-truth), to measure how
/// indexing and pairing hold up under a localizer's noise, misses and false detections.
#[derive(clap::Args, Debug, Clone, Copy)]
struct Perturbation {
    /// Gaussian noise added to each ground-truth coordinate, px (standard deviation).
    #[arg(long, default_value_t = 0.0)]
    gt_noise_px: f64,
    /// Fraction of ground-truth markers dropped at random in each view.
    #[arg(long, default_value_t = 0.0)]
    gt_missing: f64,
    /// Spurious detections added per view, uniformly over the markers' bounding box.
    #[arg(long, default_value_t = 0)]
    gt_dust: usize,
}

/// SplitMix64 (Steele, Lea & Flood 2014): a small seeded generator for the perturbations.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal (Box-Muller).
    fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * self.uniform()).cos()
    }
}

fn perturb(dets: Vec<Detection>, p: &Perturbation, rng: &mut SplitMix64) -> Vec<Detection> {
    if p.gt_noise_px == 0.0 && p.gt_missing == 0.0 && p.gt_dust == 0 {
        return dets;
    }
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for d in &dets {
        (x0, y0) = (x0.min(d.position.x), y0.min(d.position.y));
        (x1, y1) = (x1.max(d.position.x), y1.max(d.position.y));
    }
    let mut out: Vec<Detection> = Vec::with_capacity(dets.len() + p.gt_dust);
    for d in dets {
        if rng.uniform() < p.gt_missing {
            continue;
        }
        let position = Point2::new(
            d.position.x + p.gt_noise_px * rng.normal(),
            d.position.y + p.gt_noise_px * rng.normal(),
        );
        out.push(Detection { position, ..d });
    }
    if x1 >= x0 {
        for _ in 0..p.gt_dust {
            let position = Point2::new(x0 + (x1 - x0) * rng.uniform(), y0 + (y1 - y0) * rng.uniform());
            out.push(Detection {
                position,
                confidence: 1.0,
            });
        }
    }
    out
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
    /// Detections known beforehand: ground-truth 2-D positions, or a video frame localized while
    /// the video was read.
    Given(StereoPair<Vec<Detection>>),
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

/// Localizes every frame of a side-by-side stereo video (left half, right half); adds the time spent
/// to `localize_ms`.
fn localize_video(
    path: &Path,
    rig: &StereoRig,
    args: &Args,
    localize_ms: &mut f64,
) -> anyhow::Result<Vec<FrameInput>> {
    if args.from_ground_truth {
        bail!("--from-ground-truth needs a simulated RECORDING folder, not a video");
    }
    let mut localizer = args.localizer.localizer(args.method)?;
    let mut video = gelstereo_io::video::VideoFrames::open(path)?;
    let mut frames = Vec::new();
    while let Some((index, frame)) = video.next_frame()? {
        let pair = gelstereo_io::video::split_side_by_side(&frame, path)?;
        rig.check_image_sizes(image_size(&pair.left), image_size(&pair.right))
            .with_context(|| {
                format!(
                    "{} frame {index}: the halves do not match the calibration '{}'",
                    path.display(),
                    args.calib
                )
            })?;
        let t = Instant::now();
        let found = localizer
            .detect_stereo(&pair)
            .with_context(|| format!("localizing {} frame {index}", path.display()))?;
        *localize_ms += t.elapsed().as_secs_f64() * 1e3;
        frames.push(FrameInput {
            frame: u32::try_from(index).context("too many frames")?,
            source: FrameSource::Given(found),
        });
    }
    Ok(frames)
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
        (Some(dir), true) => Some(GroundTruth::read(dir).with_context(|| {
            format!(
                "--from-ground-truth / --evaluate need the simulator's ground truth in {}",
                dir.display()
            )
        })?),
        (None, true) => {
            bail!("--from-ground-truth and --evaluate need a simulated RECORDING folder, not LEFT RIGHT")
        }
        _ => None,
    };

    // The frames.
    let mut video_localize_ms = 0.0;
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
                let mut rng = SplitMix64(args.seed ^ (u64::from(frame) << 32));
                let left: Vec<Detection> = markers.values().filter_map(|m| det(m.left_px)).collect();
                let right: Vec<Detection> = markers.values().filter_map(|m| det(m.right_px)).collect();
                FrameInput {
                    frame,
                    source: FrameSource::Given(StereoPair::new(
                        perturb(left, &args.perturb, &mut rng),
                        perturb(right, &args.perturb, &mut rng),
                    )),
                }
            })
            .collect()
    } else if let [video] = args.inputs.as_slice()
        && video.is_file()
        && gelstereo_io::video::has_video_extension(video)
    {
        localize_video(video, &rig, args, &mut video_localize_ms)?
    } else {
        let pairs = match args.inputs.as_slice() {
            [dir] => {
                let rec = images::StereoRecording::open(dir)?;
                (0..rec.len()).filter_map(|i| rec.paths(i)).collect()
            }
            [l, r] if l.is_dir() && r.is_dir() => paired_folders(l, r)?,
            [l, r] => vec![StereoPair::new(l.clone(), r.clone())],
            _ => bail!("give a stereo RECORDING folder, a side-by-side stereo video, or LEFT RIGHT"),
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

    let needs_localizer = frames.iter().any(|f| matches!(f.source, FrameSource::Images(_)));
    let mut localizer: Option<Box<dyn Localizer>> = if !needs_localizer {
        None
    } else {
        Some(args.localizer.localizer(args.method)?)
    };
    let mut detect = |input: &FrameInput| -> anyhow::Result<(StereoPair<Vec<Detection>>, f64)> {
        match (&input.source, localizer.as_mut()) {
            (FrameSource::Given(d), _) => Ok((d.clone(), 0.0)),
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
    let (mut localize_ms, mut match_ms, mut reconstructed, mut paired_rejected) =
        (video_localize_ms, 0.0, 0usize, 0usize);
    // Markers seen in both views without a 3-D position, and why (epipolar check, triangulation).
    let mut rejections = String::from("frame,row,col,reason\n");
    let mut evaluation = Evaluation::default();
    let r_px = StereoPair::new(
        0.25 * reconstructor.lattice().left().pitch_px(),
        0.25 * reconstructor.lattice().right().pitch_px(),
    );
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
        for m in &rec.markers {
            if let Some(why) = &m.rejection {
                paired_rejected += 1;
                // One CSV cell: the reason's own commas become semicolons.
                let reason = why.to_string().replace(',', ";");
                let _ = writeln!(
                    rejections,
                    "{},{},{},{reason}",
                    input.frame, m.index.row, m.index.col
                );
            }
        }
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
        if let Some(truth) = truth.as_ref().filter(|_| args.evaluate) {
            evaluation.add_frame(truth, input.frame, &rec, &r_px);
        }
    }
    let csv_path = args.out.join("markers.csv");
    std::fs::write(&csv_path, csv).with_context(|| format!("cannot write {}", csv_path.display()))?;
    let rej_path = args.out.join("rejected_pairs.csv");
    std::fs::write(&rej_path, rejections).with_context(|| format!("cannot write {}", rej_path.display()))?;
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
        let report = evaluation_json(&evaluation, &r_px, match_ms / n);
        let path = args.out.join("evaluation.json");
        let text = serde_json::to_string_pretty(&report).context("cannot format the evaluation")?;
        std::fs::write(&path, text + "\n").with_context(|| format!("cannot write {}", path.display()))?;
        eprintln!("{}", summary_text(&report));
    }
    Ok(())
}

fn counts_json(c: &Counts) -> serde_json::Value {
    serde_json::json!({
        "markers_visible_left": c.visible_left,
        "markers_detected_left": c.detected_left,
        "index_correct": c.index_correct,
        "index_wrong": c.index_wrong,
        "index_consistency": c.index_consistency(),
        "markers_visible_both": c.visible_both,
        "reconstructed": c.reconstructed,
        "coverage": c.coverage(),
        "markers_detected_both": c.detected_both,
        "matching_coverage": c.matching_coverage(),
        "wrong_pairs": c.wrong_pairs,
        "wrong_pair_rate": c.wrong_pair_rate(),
        "rmse_mm": c.rmse_mm(),
        "max_error_mm": c.max_error_mm,
    })
}

fn evaluation_json(e: &Evaluation, r_px: &StereoPair<f64>, match_ms: f64) -> serde_json::Value {
    serde_json::json!({
        "frames": e.frames,
        "r_px": { "left": r_px.left, "right": r_px.right },
        "matching_ms_per_frame": match_ms,
        "all": counts_json(&e.all),
        "contact_frames": counts_json(&e.contact_frames),
        "in_contact_markers": counts_json(&e.in_contact_markers),
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
            "{key}: 3-D RMSE {} (max {}), coverage {} (of the markers found in both views: {}), wrong pairs {} ({}), index consistency {} ({} wrong of {} detected)",
            mm("rmse_mm"),
            mm("max_error_mm"),
            pct("coverage"),
            pct("matching_coverage"),
            g["wrong_pairs"],
            pct("wrong_pair_rate"),
            pct("index_consistency"),
            g["index_wrong"],
            g["markers_detected_left"],
        );
    }
    s.trim_end().to_owned()
}
