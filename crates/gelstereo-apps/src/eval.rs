//! The paper's Table I on a dataset written by `gelstereo simulate` (`gelstereo eval`): precision,
//! recall and loss of each localization method on the easy / hard / contact splits (docs/design.md
//! "Metrics"; the definitions live in [`gelstereo_markers::metrics`]).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use gelstereo_core::StereoPair;
use gelstereo_io::images;
use gelstereo_markers::metrics::{self, GroundTruth, SPLITS, SplitTable, ViewSplits};
use gelstereo_markers::{BlobLocalizer, BlobParams, Localizer, LocalizerConfig, Method};
use gelstereo_matching::eval::GroundTruth as RecordingTruth;
use gelstereo_sim::DatasetManifest;
use opencv::core::{Mat, MatTraitConst};
use serde_json::{Value, json};

use gelstereo::{Error, Result};

/// What [`run`] evaluates, and how.
#[derive(Debug, Clone)]
pub struct LocalizationEval {
    /// Dataset folder written by `gelstereo simulate` (`DIR/{train,val,test}/exp_NNNN/...`).
    pub dataset: PathBuf,
    /// Which split to evaluate.
    pub split: String,
    /// The methods, a row each.
    pub methods: Vec<Method>,
    /// Only experiments of this sensor (the `sensor` of `DIR/dataset.json`).
    pub sensor: Option<String>,
    /// SimpleBlobDetector parameters that define the hard split, and their name in the report.
    pub hard_blob: (BlobParams, String),
    /// Model paths, blob parameters (of the blob row) and ONNX Runtime options. Every image is
    /// localized on its own (no pitch remembered across images): datasets mix sensors of one size.
    pub localizer: LocalizerConfig,
    /// Evaluate every N-th frame of each experiment (frames 0, N, 2N, ...; at least 1).
    pub frame_step: usize,
    /// Evaluate at most this many frames per experiment (evenly spaced; 0 = all).
    pub frames_per_experiment: usize,
}

/// Table I: `text` to show, `csv` and `json` to write (`table1.csv`, `table1.json`).
#[derive(Debug, Clone)]
pub struct Table1 {
    /// The table with its caption.
    pub text: String,
    /// A row per split and method.
    pub csv: String,
    /// The rows with what was evaluated and how.
    pub json: Value,
}

/// One stereo frame's images and ground truth: the visible markers of each view.
struct FrameTruth {
    paths: StereoPair<PathBuf>,
    truth: StereoPair<Vec<GroundTruth>>,
}

/// What was scored so far.
struct Tally {
    tables: Vec<SplitTable>,
    radii_px: Vec<f64>,
    frames: usize,
    views: usize,
}

/// Evaluates every method on the split's experiments; `on_experiment` is told each experiment done
/// and its number of frames.
pub fn run(job: &LocalizationEval, on_experiment: &mut dyn FnMut(&Path, usize)) -> Result<Table1> {
    let experiments = experiments(job)?;
    // The hard split is defined by its own blob parameters, whatever the blob row uses.
    let mut hard_blob = BlobLocalizer::new(job.hard_blob.0)?;
    let mut config = job.localizer.clone();
    config.remember_pitch = false;
    let mut localizers: Vec<Box<dyn Localizer + Send>> = job
        .methods
        .iter()
        .map(|m| gelstereo::localizer(*m, &config))
        .collect::<Result<_>>()?;
    let mut tally = Tally {
        tables: vec![SplitTable::default(); job.methods.len()],
        radii_px: Vec::new(),
        frames: 0,
        views: 0,
    };
    for exp in &experiments {
        let frames = chosen_frames(read_experiment(exp)?, job);
        for frame in &frames {
            score_frame(frame, &mut hard_blob, &mut localizers, &mut tally)?;
        }
        on_experiment(exp, frames.len());
    }
    if tally.views == 0 {
        return Err(Error::Invalid(format!(
            "{}: no view with at least two visible ground-truth markers",
            job.dataset.join(&job.split).display()
        )));
    }
    Ok(table(job, experiments.len(), &mut tally))
}

/// The split's `exp_NNNN` folders, sorted, of `job.sensor` when given.
fn experiments(job: &LocalizationEval) -> Result<Vec<PathBuf>> {
    let split_dir = job.dataset.join(&job.split);
    let entries = std::fs::read_dir(&split_dir).map_err(|e| {
        Error::Invalid(format!(
            "{}: not a dataset split folder (expected DIR/{}/exp_NNNN/): {e}",
            split_dir.display(),
            job.split
        ))
    })?;
    let mut experiments: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir() && folder_name(p).starts_with("exp_"))
        .collect();
    experiments.sort();
    // The manifest is checked whenever there is one; a sensor needs it.
    let manifest = match DatasetManifest::read(&job.dataset) {
        Ok(m) => Some(m),
        Err(gelstereo_sim::Error::Io { error, .. })
            if error.kind() == std::io::ErrorKind::NotFound && job.sensor.is_none() =>
        {
            None
        }
        Err(e) => {
            let why = if job.sensor.is_some() {
                "reading the dataset's manifest (needed by --sensor)"
            } else {
                "reading the dataset's manifest"
            };
            return Err(Error::from(e).context(why));
        }
    };
    if let (Some(sensor), Some(manifest)) = (&job.sensor, &manifest) {
        let wanted = experiments_of_sensor(manifest, &job.dataset, sensor)?;
        experiments.retain(|e| wanted.contains(&folder_name(e)));
    }
    if experiments.is_empty() {
        return Err(Error::Invalid(format!(
            "{}: no exp_NNNN folders{}",
            split_dir.display(),
            job.sensor
                .as_ref()
                .map_or(String::new(), |s| format!(" of sensor '{s}'"))
        )));
    }
    Ok(experiments)
}

fn folder_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// The experiment folder names of `sensor` according to the dataset's manifest.
fn experiments_of_sensor(manifest: &DatasetManifest, dataset: &Path, sensor: &str) -> Result<Vec<String>> {
    let names: Vec<String> = manifest
        .experiments
        .iter()
        .filter(|e| e.sensor == sensor)
        .map(|e| e.name.clone())
        .collect();
    if names.is_empty() {
        let mut known: Vec<&str> = manifest.experiments.iter().map(|e| e.sensor.as_str()).collect();
        known.sort_unstable();
        known.dedup();
        return Err(Error::Invalid(format!(
            "{}: no experiment of sensor '{sensor}' (sensors: {})",
            dataset.join("dataset.json").display(),
            known.join(", ")
        )));
    }
    Ok(names)
}

/// Reads one experiment's frames and ground truth (the simulator's markers.csv, read by the
/// matching crate's `eval::GroundTruth`): per view, the visible markers and whether each is in contact.
fn read_experiment(dir: &Path) -> Result<Vec<FrameTruth>> {
    let truth = RecordingTruth::read(dir)?;
    Ok(truth
        .frames
        .into_iter()
        .map(|(f, markers)| {
            let mut views: StereoPair<Vec<GroundTruth>> = StereoPair::default();
            for m in markers.values() {
                for (px, view) in [(m.left_px, &mut views.left), (m.right_px, &mut views.right)] {
                    if let Some(position) = px {
                        view.push(GroundTruth {
                            position,
                            in_contact: m.in_contact,
                        });
                    }
                }
            }
            FrameTruth {
                paths: StereoPair::new(
                    dir.join("left").join(format!("{f:06}.png")),
                    dir.join("right").join(format!("{f:06}.png")),
                ),
                truth: views,
            }
        })
        .collect())
}

/// Every `frame_step`-th frame, then at most `frames_per_experiment` of them, evenly spaced.
fn chosen_frames(frames: Vec<FrameTruth>, job: &LocalizationEval) -> Vec<FrameTruth> {
    let mut frames: Vec<FrameTruth> = frames.into_iter().step_by(job.frame_step.max(1)).collect();
    let k = job.frames_per_experiment;
    if k > 0 && frames.len() > k {
        let n = frames.len();
        let keep: Vec<usize> = (0..k).map(|i| i * (n - 1) / (k - 1).max(1)).collect();
        frames = frames
            .into_iter()
            .enumerate()
            .filter(|(i, _)| keep.contains(i))
            .map(|(_, f)| f)
            .collect();
    }
    frames
}

/// Scores every method on one stereo frame: per view with at least two visible markers, the hard
/// split (what the hard-split blob detector misses) and each method's counts.
fn score_frame(
    frame: &FrameTruth,
    hard_blob: &mut BlobLocalizer,
    localizers: &mut [Box<dyn Localizer + Send>],
    tally: &mut Tally,
) -> Result<()> {
    let pair = StereoPair::new(
        images::read_image(&frame.paths.left)?,
        images::read_image(&frame.paths.right)?,
    );
    let left = view_splits(&pair.left, &frame.truth.left, hard_blob, tally)?;
    let right = view_splits(&pair.right, &frame.truth.right, hard_blob, tally)?;
    for (loc, table) in localizers.iter_mut().zip(tally.tables.iter_mut()) {
        let found = loc.detect_stereo(&pair).map_err(|e| {
            Error::from(e).context(format!("{} on {}", loc.name(), frame.paths.left.display()))
        })?;
        for (dets, gt, split) in [
            (&found.left, &frame.truth.left, &left),
            (&found.right, &frame.truth.right, &right),
        ] {
            if let Some(splits) = split {
                table.add(&metrics::score_view(dets, gt, splits)?);
            }
        }
    }
    tally.frames += 1;
    Ok(())
}

/// A view's hard and border markers and match radius; `None` for a view with fewer than two visible
/// markers.
fn view_splits(
    view: &Mat,
    gt: &[GroundTruth],
    hard_blob: &mut BlobLocalizer,
    tally: &mut Tally,
) -> Result<Option<ViewSplits>> {
    let Some(radius_px) = metrics::radius_from_ground_truth(gt) else {
        return Ok(None);
    };
    let blob = hard_blob.detect(view)?;
    let hard = metrics::hard_markers(&blob, gt, radius_px)?;
    let (width, height) = (view.cols().max(0) as u32, view.rows().max(0) as u32);
    let border = metrics::border_markers(gt, width, height, radius_px);
    tally.radii_px.push(radius_px);
    tally.views += 1;
    Ok(Some(ViewSplits {
        hard,
        border,
        radius_px,
    }))
}

fn pct(v: Option<f64>) -> String {
    v.map_or_else(|| "/".to_owned(), |v| format!("{:.2}%", 100.0 * v))
}

fn num(v: Option<f64>) -> String {
    v.map_or_else(|| "/".to_owned(), |v| format!("{v:.3}"))
}

fn json_num(v: Option<f64>) -> Value {
    v.map_or(Value::Null, |v| json!(v))
}

/// Table I from the tally (at least one view).
fn table(job: &LocalizationEval, experiments: usize, tally: &mut Tally) -> Table1 {
    let radii = &mut tally.radii_px;
    radii.sort_by(f64::total_cmp);
    let r_med = radii[radii.len() / 2];
    let (r_min, r_max) = (radii[0], radii[radii.len() - 1]);
    let mut text = String::new();
    let _ = writeln!(
        text,
        "Table I: marker localization, {} split of {} ({} experiments, {} stereo frames, {} views)",
        job.split,
        job.dataset.display(),
        experiments,
        tally.frames,
        tally.views
    );
    let _ = writeln!(
        text,
        "match radius r = {} x GT pitch: median {r_med:.2} px (range {r_min:.2}-{r_max:.2}); loss in px^2; hard = missed by blob ({}); border = within one pitch of the image border{}",
        metrics::RADIUS_PITCH_FRACTION,
        job.hard_blob.1,
        job.sensor
            .as_ref()
            .map_or(String::new(), |s| format!("; sensor {s}"))
    );
    let _ = writeln!(
        text,
        "{:<8} {:<12} {:>9} {:>9} {:>8} {:>8} {:>8} {:>7}",
        "split", "method", "precision", "recall", "loss", "T", "PT", "PF"
    );
    let mut csv =
        String::from("split,method,precision,recall,loss_px2,markers,correct,wrong,radius_px_median\n");
    let mut rows = Vec::new();
    for split in SPLITS {
        for (m, t) in job.methods.iter().zip(&tally.tables) {
            let Some(c) = t.get(split) else { continue };
            let _ = writeln!(
                text,
                "{split:<8} {:<12} {:>9} {:>9} {:>8} {:>8} {:>8} {:>7}",
                m.as_str(),
                pct(c.precision()),
                pct(c.recall()),
                num(c.loss_px2()),
                c.markers,
                c.correct,
                c.wrong
            );
            let f = |v: Option<f64>| v.map_or_else(String::new, |v| format!("{v:.6}"));
            let _ = writeln!(
                csv,
                "{split},{m},{},{},{},{},{},{},{r_med:.4}",
                f(c.precision()),
                f(c.recall()),
                f(c.loss_px2()),
                c.markers,
                c.correct,
                c.wrong
            );
            rows.push(json!({
                "split": split, "method": m.as_str(), "precision": json_num(c.precision()),
                "recall": json_num(c.recall()), "loss_px2": json_num(c.loss_px2()),
                "markers": c.markers, "correct": c.correct, "wrong": c.wrong,
            }));
        }
    }
    let config = &job.localizer;
    let json = json!({
        "dataset": job.dataset.display().to_string(),
        "split": job.split,
        "experiments": experiments,
        "frames": tally.frames,
        "views": tally.views,
        "radius_px": {"fraction_of_pitch": metrics::RADIUS_PITCH_FRACTION, "median": r_med, "min": r_min, "max": r_max},
        "sensor": job.sensor,
        "hard_blob_params": job.hard_blob.0.to_json(),
        "methods": job.methods.iter().map(|m| m.as_str()).collect::<Vec<_>>(),
        "marknet": config.marknet_path.display().to_string(),
        "mre": config.mre_path.display().to_string(),
        "blob_params": config.blob.to_json(),
        "results": rows,
    });
    Table1 { text, csv, json }
}
