//! `gelstereo bench`: localization latency of each method per view and per stereo pair, measured side
//! by side in one process (the runs of the methods are interleaved, so machine load hits all alike),
//! with the ratio to the blob baseline. Criterion benches of the same code are in
//! `crates/gelstereo-markers/benches`.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use gelstereo_core::StereoPair;
use gelstereo_io::images::{self, StereoRecording};
use gelstereo_markers::{Localizer, Method};
use opencv::core::{Mat, MatTraitConst};
use serde_json::json;

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo bench`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Take stereo pairs from this dataset (written by `gelstereo simulate`): its --split's experiments.
    #[arg(long, value_name = "DIR")]
    dataset: Option<PathBuf>,
    /// Dataset split to take pairs from.
    #[arg(long, default_value = "test")]
    split: String,
    /// Number of distinct stereo pairs to cycle through.
    #[arg(long, default_value_t = 8)]
    pairs: usize,
    /// Comma-separated methods; `blob` is always measured too (it is the reference).
    #[arg(long, default_value = "blob,marknet,marknet-mre")]
    methods: String,
    /// Timed runs per method and per measurement (after the warm-up).
    #[arg(long, default_value_t = 200)]
    runs: usize,
    /// Untimed warm-up runs per method.
    #[arg(long, default_value_t = 20)]
    warmup: usize,
    /// Also write the figures as JSON here.
    #[arg(long, value_name = "FILE.json")]
    out: Option<PathBuf>,
    #[command(flatten)]
    localizer: LocalizerArgs,
    /// Stereo recordings (folders with left/ and right/) or images (consecutive images form pairs).
    #[arg(value_name = "INPUT")]
    inputs: Vec<PathBuf>,
}

fn load_pairs(args: &Args) -> anyhow::Result<Vec<StereoPair<Mat>>> {
    let mut pairs = Vec::new();
    let mut recordings: Vec<PathBuf> = Vec::new();
    let mut loose: Vec<PathBuf> = Vec::new();
    if let Some(ds) = &args.dataset {
        let split = ds.join(&args.split);
        let mut exps: Vec<PathBuf> = std::fs::read_dir(&split)
            .with_context(|| format!("{}: not a dataset split folder", split.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| images::is_stereo_recording(p))
            .collect();
        exps.sort();
        recordings.extend(exps);
    }
    for p in &args.inputs {
        if p.is_dir() && images::is_stereo_recording(p) {
            recordings.push(p.clone());
        } else if p.is_dir() {
            loose.extend(images::list_images(p)?);
        } else {
            loose.push(p.clone());
        }
    }
    // Spread the pairs over the recordings: frame k of each in turn.
    let recs: Vec<StereoRecording> = recordings
        .iter()
        .map(|r| StereoRecording::open(r))
        .collect::<Result<_, _>>()?;
    let mut k = 0;
    while pairs.len() < args.pairs && recs.iter().any(|r| k < r.len()) {
        for r in &recs {
            if pairs.len() < args.pairs && k < r.len() {
                let step = (r.len() / args.pairs.max(1)).max(1);
                if let Some(p) = r.read((k * step).min(r.len() - 1)) {
                    pairs.push(p?);
                }
            }
        }
        k += 1;
    }
    let mut loose_images = loose
        .iter()
        .map(|p| images::read_image(p))
        .collect::<Result<Vec<_>, _>>()?;
    while pairs.len() < args.pairs && !loose_images.is_empty() {
        let left = loose_images.remove(0);
        let right = if loose_images.is_empty() {
            left.try_clone()?
        } else {
            loose_images.remove(0)
        };
        pairs.push(StereoPair::new(left, right));
    }
    if pairs.is_empty() {
        bail!("no images to benchmark: give --dataset DIR, stereo recordings or image files");
    }
    Ok(pairs)
}

/// Median, 90th percentile and mean of `samples_ms`.
fn stats(samples_ms: &mut [f64]) -> (f64, f64, f64) {
    samples_ms.sort_by(f64::total_cmp);
    let n = samples_ms.len();
    let q = |f: f64| samples_ms[((f * (n - 1) as f64).round() as usize).min(n - 1)];
    (q(0.5), q(0.9), samples_ms.iter().sum::<f64>() / n as f64)
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    if args.runs < 1 {
        bail!("--runs must be at least 1");
    }
    let mut methods = Method::parse_list(&args.methods)?;
    if !methods.contains(&Method::Blob) {
        methods.insert(0, Method::Blob);
    }
    let pairs = load_pairs(args)?;
    let views: Vec<&Mat> = pairs.iter().flat_map(|p| [&p.left, &p.right]).collect();
    let mut locs: Vec<Box<dyn Localizer>> = methods
        .iter()
        .map(|m| args.localizer.localizer(*m))
        .collect::<anyhow::Result<_>>()?;
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let sizes: std::collections::BTreeSet<String> = views
        .iter()
        .map(|v| format!("{}x{}", v.cols(), v.rows()))
        .collect();
    eprintln!(
        "benchmarking {} on {} stereo pairs ({}), {} warm-up + {} timed runs each; {cores} cores, load average {}",
        methods.iter().map(|m| m.as_str()).collect::<Vec<_>>().join(", "),
        pairs.len(),
        sizes.iter().cloned().collect::<Vec<_>>().join(", "),
        args.warmup,
        args.runs,
        load.split_whitespace().take(3).collect::<Vec<_>>().join(" ")
    );
    let mut per_view = vec![Vec::with_capacity(args.runs); locs.len()];
    let mut per_pair = vec![Vec::with_capacity(args.runs); locs.len()];
    let mut markers = vec![0usize; locs.len()];
    for run in 0..args.warmup + args.runs {
        let timed = run >= args.warmup;
        let view = views[run % views.len()];
        let pair = &pairs[run % pairs.len()];
        for (i, loc) in locs.iter_mut().enumerate() {
            let t = Instant::now();
            let found = loc
                .detect(view)
                .with_context(|| format!("{} failed", loc.name()))?;
            let view_ms = t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            let both = loc
                .detect_stereo(pair)
                .with_context(|| format!("{} failed", loc.name()))?;
            let pair_ms = t.elapsed().as_secs_f64() * 1e3;
            if timed {
                per_view[i].push(view_ms);
                per_pair[i].push(pair_ms);
                markers[i] += found.len() + both.left.len() + both.right.len();
            }
        }
    }
    let view_stats: Vec<_> = per_view.iter_mut().map(|s| stats(s)).collect();
    let pair_stats: Vec<_> = per_pair.iter_mut().map(|s| stats(s)).collect();
    let (blob_view, blob_pair) = (view_stats[0].0, pair_stats[0].0);
    let mut text = String::new();
    let _ = writeln!(
        text,
        "{:<12} {:>10} {:>9} {:>10} {:>10} {:>9} {:>10} {:>9}",
        "method", "view med", "view p90", "x vs blob", "pair med", "pair p90", "x vs blob", "markers"
    );
    let mut rows = Vec::new();
    for (i, m) in methods.iter().enumerate() {
        let (vm, v90, vmean) = view_stats[i];
        let (pm, p90, pmean) = pair_stats[i];
        let per_image = markers[i] as f64 / (3 * args.runs) as f64;
        let _ = writeln!(
            text,
            "{:<12} {:>7.2} ms {:>6.2} ms {:>9.2}x {:>7.2} ms {:>6.2} ms {:>9.2}x {:>9.1}",
            m.as_str(),
            vm,
            v90,
            blob_view / vm,
            pm,
            p90,
            blob_pair / pm,
            per_image
        );
        rows.push(json!({
            "method": m.as_str(),
            "view_ms": {"median": vm, "p90": v90, "mean": vmean},
            "pair_ms": {"median": pm, "p90": p90, "mean": pmean},
            "speedup_vs_blob": {"view": blob_view / vm, "pair": blob_pair / pm},
            "markers_per_image": per_image,
        }));
    }
    let _ = writeln!(
        text,
        "x vs blob = blob median / method median (> 1: faster than the blob baseline)"
    );
    print!("{text}");
    if let Some(out) = &args.out {
        let report = json!({
            "pairs": pairs.len(),
            "image_sizes": sizes,
            "runs": args.runs,
            "warmup": args.warmup,
            "cores": cores,
            "load_average_at_start": load.trim(),
            "ort_intra_threads": args.localizer.threads,
            "blob_params": args.localizer.blob_params,
            "results": rows,
        });
        let pretty = serde_json::to_string_pretty(&report).context("cannot format the JSON report")?;
        std::fs::write(out, pretty + "\n").with_context(|| format!("cannot write {}", out.display()))?;
    }
    Ok(())
}
