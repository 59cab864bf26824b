//! `gelstereo eval`: the paper's Table I on a dataset written by `gelstereo simulate` — precision,
//! recall and loss of each localization method on the easy / hard / contact splits. The work is
//! [`gelstereo_apps::eval::run`]; this is argument parsing, progress and the output files.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use gelstereo::markers::Method;
use gelstereo_apps::eval::LocalizationEval;

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
    #[arg(long, default_value_t = 1, value_name = "N",
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    frame_step: usize,
    /// Evaluate at most this many frames per experiment (evenly spaced; 0 = all).
    #[arg(long, default_value_t = 0, value_name = "N")]
    frames_per_experiment: usize,
    #[command(flatten)]
    localizer: LocalizerArgs,
}

/// Runs `gelstereo eval`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let job = LocalizationEval {
        dataset: args.dataset.clone(),
        split: args.split.clone(),
        methods: Method::parse_list(&args.methods)?,
        sensor: args.sensor.clone(),
        hard_blob: (
            LocalizerArgs::blob(&args.hard_blob_params)?,
            args.hard_blob_params.clone(),
        ),
        localizer: args.localizer.config()?,
        frame_step: args.frame_step,
        frames_per_experiment: args.frames_per_experiment,
    };
    let started = Instant::now();
    let table = gelstereo_apps::eval::run(&job, &mut |exp, frames| {
        eprintln!(
            "{}: {frames} frames ({:.0} s so far)",
            exp.display(),
            started.elapsed().as_secs_f64()
        );
    })?;
    print!("{}", table.text);
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(format!("eval-{}", args.split)));
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    let csv_path = out.join("table1.csv");
    std::fs::write(&csv_path, &table.csv).with_context(|| format!("cannot write {}", csv_path.display()))?;
    let json_path = out.join("table1.json");
    let pretty = serde_json::to_string_pretty(&table.json).context("cannot format the JSON report")?;
    std::fs::write(&json_path, pretty + "\n")
        .with_context(|| format!("cannot write {}", json_path.display()))?;
    eprintln!("written {} and {}", csv_path.display(), json_path.display());
    Ok(())
}
