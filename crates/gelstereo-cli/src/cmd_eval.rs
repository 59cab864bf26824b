//! `gelstereo eval`: the paper's Table I on a dataset written by `gelstereo simulate` — precision,
//! recall and loss of each localization method on the easy / hard / contact splits (DESIGN.md
//! "Metrics"; the definitions live in `gelstereo_markers::metrics`).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use gelstereo_core::StereoPair;
use gelstereo_io::images;
use gelstereo_markers::metrics::{self, GroundTruth, SPLITS, SplitTable};
use gelstereo_markers::{BlobLocalizer, Localizer, Method};
use gelstereo_matching::eval::GroundTruth as RecordingTruth;
use serde_json::json;

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo eval`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Dataset folder written by `gelstereo simulate` (DIR/{train,val,test}/exp_NNNN/...).
    #[arg(long, value_name = "DIR")]
    dataset: PathBuf,
    /// Which split to evaluate.
    #[arg(long, default_value = "test")]
    split: String,
    /// Comma-separated methods (blob, marknet, marknet-mre).
    #[arg(long, default_value = "blob,marknet,marknet-mre")]
    methods: String,
    /// Folder for table1.csv and table1.json (default: eval-<split> in the current folder).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Only experiments of this sensor (the `sensor` of DIR/dataset.json, e.g. `gelstereo-reference`).
    #[arg(long, value_name = "NAME")]
    sensor: Option<String>,
    /// SimpleBlobDetector parameters that define the hard split (`tuned`, `default` or a JSON file).
    #[arg(long, value_name = "tuned|default|FILE", default_value = "tuned")]
    hard_blob_params: String,
    /// Evaluate every N-th frame of each experiment (frames 0, N, 2N, ...; the trainer's --frame-step).
    #[arg(long, default_value_t = 1, value_name = "N")]
    frame_step: usize,
    /// Evaluate at most this many frames per experiment (evenly spaced; 0 = all).
    #[arg(long, default_value_t = 0)]
    frames_per_experiment: usize,
    #[command(flatten)]
    localizer: LocalizerArgs,
}

/// One stereo frame's ground truth: the visible markers of each view.
struct FrameTruth {
    paths: StereoPair<PathBuf>,
    truth: StereoPair<Vec<GroundTruth>>,
}

/// Reads one experiment's frames and ground truth (the simulator's markers.csv, read by the
/// matching crate's `eval::GroundTruth`): per view, the visible markers and whether each is in contact.
fn read_experiment(dir: &Path) -> anyhow::Result<Vec<FrameTruth>> {
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

/// The experiment folder names of `sensor` according to DIR/dataset.json.
fn experiments_of_sensor(dataset: &Path, sensor: &str) -> anyhow::Result<Vec<String>> {
    let path = dataset.join("dataset.json");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("cannot read {} (needed by --sensor)", path.display()))?;
    let json: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let Some(list) = json["experiments"].as_array() else {
        bail!("{}: 'experiments': expected a list", path.display());
    };
    let names: Vec<String> = list
        .iter()
        .filter(|e| e["sensor"].as_str() == Some(sensor))
        .filter_map(|e| e["name"].as_str().map(str::to_owned))
        .collect();
    if names.is_empty() {
        let mut known: Vec<&str> = list.iter().filter_map(|e| e["sensor"].as_str()).collect();
        known.sort_unstable();
        known.dedup();
        bail!(
            "{}: no experiment of sensor '{sensor}' (sensors: {})",
            path.display(),
            known.join(", ")
        );
    }
    Ok(names)
}

fn pct(v: Option<f64>) -> String {
    v.map_or_else(|| "/".to_owned(), |v| format!("{:.2}%", 100.0 * v))
}

fn num(v: Option<f64>) -> String {
    v.map_or_else(|| "/".to_owned(), |v| format!("{v:.3}"))
}

fn json_num(v: Option<f64>) -> serde_json::Value {
    v.map_or(serde_json::Value::Null, |v| json!(v))
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    let methods = Method::parse_list(&args.methods)?;
    let split_dir = args.dataset.join(&args.split);
    let mut experiments: Vec<PathBuf> = std::fs::read_dir(&split_dir)
        .with_context(|| {
            format!(
                "{}: not a dataset split folder (expected DIR/{}/exp_NNNN/)",
                split_dir.display(),
                args.split
            )
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_dir()
                && p.file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with("exp_"))
        })
        .collect();
    experiments.sort();
    if let Some(sensor) = &args.sensor {
        let wanted = experiments_of_sensor(&args.dataset, sensor)?;
        experiments.retain(|e| {
            e.file_name()
                .is_some_and(|n| wanted.iter().any(|w| w == &n.to_string_lossy()))
        });
    }
    if experiments.is_empty() {
        bail!(
            "{}: no exp_NNNN folders{}",
            split_dir.display(),
            args.sensor
                .as_ref()
                .map_or(String::new(), |s| format!(" of sensor '{s}'"))
        );
    }

    // The hard split is defined by the TUNED blob baseline, whatever --blob-params says for the blob row.
    let mut tuned_blob = BlobLocalizer::new(LocalizerArgs::blob(&args.hard_blob_params)?)?;
    // Every image on its own (no pitch remembered across images): datasets mix sensors of one size.
    let mut config = args.localizer.config()?;
    config.remember_pitch = false;
    let mut localizers: Vec<Box<dyn Localizer + Send>> = methods
        .iter()
        .map(|m| LocalizerArgs::localizer_from(*m, &config))
        .collect::<anyhow::Result<_>>()?;
    let mut tables = vec![SplitTable::default(); methods.len()];
    let mut radii: Vec<f64> = Vec::new();
    let (mut n_frames, mut n_views) = (0usize, 0usize);
    let started = Instant::now();
    for exp in &experiments {
        let mut frames = read_experiment(exp)?;
        if args.frame_step > 1 {
            frames = frames.into_iter().step_by(args.frame_step).collect();
        }
        if args.frames_per_experiment > 0 && frames.len() > args.frames_per_experiment {
            let n = frames.len();
            let k = args.frames_per_experiment;
            let keep: Vec<usize> = (0..k).map(|i| i * (n - 1) / (k - 1).max(1)).collect();
            frames = frames
                .into_iter()
                .enumerate()
                .filter(|(i, _)| keep.contains(i))
                .map(|(_, f)| f)
                .collect();
        }
        for fr in &frames {
            let pair = StereoPair::new(
                images::read_image(&fr.paths.left)?,
                images::read_image(&fr.paths.right)?,
            );
            let mut hard = StereoPair::new(Vec::new(), Vec::new());
            let mut radius = StereoPair::new(None, None);
            for (view, gt, hard_out, r_out) in [
                (&pair.left, &fr.truth.left, &mut hard.left, &mut radius.left),
                (&pair.right, &fr.truth.right, &mut hard.right, &mut radius.right),
            ] {
                let Some(r) = metrics::radius_from_ground_truth(gt) else {
                    continue;
                };
                let blob = tuned_blob.detect(view)?;
                *hard_out = metrics::hard_markers(&blob, gt, r)?;
                *r_out = Some(r);
                radii.push(r);
                n_views += 1;
            }
            for (loc, table) in localizers.iter_mut().zip(tables.iter_mut()) {
                let found = loc
                    .detect_stereo(&pair)
                    .with_context(|| format!("{} on {}", loc.name(), fr.paths.left.display()))?;
                for (dets, gt, hard, r) in [
                    (&found.left, &fr.truth.left, &hard.left, radius.left),
                    (&found.right, &fr.truth.right, &hard.right, radius.right),
                ] {
                    if let Some(r) = r {
                        table.add(&metrics::score_view(dets, gt, hard, r)?);
                    }
                }
            }
            n_frames += 1;
        }
        eprintln!(
            "{}: {} frames ({:.0} s so far)",
            exp.display(),
            frames.len(),
            started.elapsed().as_secs_f64()
        );
    }
    if n_views == 0 {
        bail!(
            "{}: no view with at least two visible ground-truth markers",
            split_dir.display()
        );
    }
    radii.sort_by(f64::total_cmp);
    let r_med = radii[radii.len() / 2];
    let (r_min, r_max) = (radii[0], radii[radii.len() - 1]);

    let mut text = String::new();
    let _ = writeln!(
        text,
        "Table I: marker localization, {} split of {} ({} experiments, {} stereo frames, {} views)",
        args.split,
        args.dataset.display(),
        experiments.len(),
        n_frames,
        n_views
    );
    let _ = writeln!(
        text,
        "match radius r = {} x GT pitch: median {r_med:.2} px (range {r_min:.2}-{r_max:.2}); loss in px^2; hard = missed by blob ({}){}",
        metrics::RADIUS_PITCH_FRACTION,
        args.hard_blob_params,
        args.sensor
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
        for (m, t) in methods.iter().zip(&tables) {
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
    print!("{text}");
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(format!("eval-{}", args.split)));
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    let config = args.localizer.config()?;
    let report = json!({
        "dataset": args.dataset.display().to_string(),
        "split": args.split,
        "experiments": experiments.len(),
        "frames": n_frames,
        "views": n_views,
        "radius_px": {"fraction_of_pitch": metrics::RADIUS_PITCH_FRACTION, "median": r_med, "min": r_min, "max": r_max},
        "sensor": args.sensor,
        "hard_blob_params": LocalizerArgs::blob(&args.hard_blob_params)?.to_json(),
        "methods": methods.iter().map(|m| m.as_str()).collect::<Vec<_>>(),
        "marknet": config.marknet_path.display().to_string(),
        "mre": config.mre_path.display().to_string(),
        "blob_params": config.blob.to_json(),
        "results": rows,
    });
    let csv_path = out.join("table1.csv");
    std::fs::write(&csv_path, csv).with_context(|| format!("cannot write {}", csv_path.display()))?;
    let json_path = out.join("table1.json");
    let pretty = serde_json::to_string_pretty(&report).context("cannot format the JSON report")?;
    std::fs::write(&json_path, pretty + "\n")
        .with_context(|| format!("cannot write {}", json_path.display()))?;
    eprintln!("written {} and {}", csv_path.display(), json_path.display());
    Ok(())
}
