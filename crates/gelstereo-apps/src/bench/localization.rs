//! The localization benchmark: latency of each method per view and per stereo pair, measured side
//! by side in one process (the runs of the methods are interleaved, so machine load hits all alike),
//! with the ratio to the blob baseline. Each method has one localizer per camera (left views go to
//! one, right views to the other, pairs to the left one as a batch), so the views of one recording
//! reach each localizer as a stream would. With Marknet among the methods, Marknet's preprocessing of
//! one view is also timed with each SIMD kernel set the CPU has, side by side. Criterion benches of
//! the same code are in `crates/gelstereo-markers/benches`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use gelstereo_core::StereoPair;
use gelstereo_io::images::{self, StereoRecording};
use gelstereo_markers::{
    InputLayout, Kernels, Localizer, LocalizerConfig, Marknet, Method, ResizeScratch, create_localizer,
    network_input,
};
use opencv::core::{Mat, MatTraitConst};
use serde_json::json;

use super::{Report, stats};
use gelstereo::{Error, Result};

/// What the localization benchmark runs.
pub struct LocalizationBench {
    /// The stereo pairs cycled through.
    pub pairs: Vec<StereoPair<Mat>>,
    /// The methods, the blob baseline first.
    pub methods: Vec<Method>,
    /// Models, blob parameters, ONNX Runtime options.
    pub config: LocalizerConfig,
    /// Timed runs per method and measurement.
    pub runs: usize,
    /// Untimed warm-up runs per method.
    pub warmup: usize,
    /// The blob parameters' name, for the report.
    pub blob_params: String,
    /// Whether the pairs are frames of one recording ([`one_recording`]): a stream, whose views
    /// Marknet runs on a window around the lattice where `config` allows it; pairs of several
    /// recordings (sensors) run on the whole input, as `gelstereo eval` runs datasets.
    pub one_recording: bool,
}

/// Whether [`load_pairs`] of these arguments takes its pairs from one stereo recording.
pub fn one_recording(dataset: Option<&Path>, inputs: &[PathBuf]) -> bool {
    dataset.is_none() && inputs.len() == 1 && images::is_stereo_recording(&inputs[0])
}

/// Up to `count` stereo pairs: frames spread over the recordings of `dataset`'s `split` and the
/// recordings among `inputs`, then consecutive loose images of `inputs` as pairs.
pub fn load_pairs(
    dataset: Option<&Path>,
    split: &str,
    inputs: &[PathBuf],
    count: usize,
) -> Result<Vec<StereoPair<Mat>>> {
    let mut pairs = Vec::new();
    let mut recordings: Vec<PathBuf> = Vec::new();
    let mut loose: Vec<PathBuf> = Vec::new();
    if let Some(ds) = dataset {
        let split_dir = ds.join(split);
        let mut exps: Vec<PathBuf> = std::fs::read_dir(&split_dir)
            .map_err(|e| {
                Error::Invalid(format!(
                    "{}: not a dataset split folder ({e})",
                    split_dir.display()
                ))
            })?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| images::is_stereo_recording(p))
            .collect();
        exps.sort();
        recordings.extend(exps);
    }
    for p in inputs {
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
    while pairs.len() < count && recs.iter().any(|r| k < r.len()) {
        for r in &recs {
            if pairs.len() < count && k < r.len() {
                let step = (r.len() / count.max(1)).max(1);
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
    while pairs.len() < count && !loose_images.is_empty() {
        let left = loose_images.remove(0);
        let right = if loose_images.is_empty() {
            left.try_clone()?
        } else {
            loose_images.remove(0)
        };
        pairs.push(StereoPair::new(left, right));
    }
    if pairs.is_empty() {
        return Err(Error::Invalid(
            "no images to benchmark: give --dataset DIR, stereo recordings or image files".into(),
        ));
    }
    Ok(pairs)
}

/// CPU time used so far by all threads of this process (ONNX Runtime's and OpenCV's pools included),
/// ns, from the scheduler's per-thread accounting (`/proc/self/task/*/schedstat`); `None` where that is
/// unavailable. Unlike wall time it hardly changes with the machine's load.
fn process_cpu_ns() -> Option<u64> {
    let mut total = 0u64;
    for entry in std::fs::read_dir("/proc/self/task").ok()? {
        let path = entry.ok()?.path().join("schedstat");
        let text = std::fs::read_to_string(path).unwrap_or_default();
        total += text
            .split_whitespace()
            .next()
            .and_then(|v| v.parse::<u64>().ok())
            .unwrap_or(0);
    }
    (total > 0).then_some(total)
}

/// Runs `f`, returning its result, wall time and CPU time (ms; CPU `None` without schedstat), the CPU
/// time corrected by `overhead_ns` (the cost of the CPU-time reading itself).
fn timed<T>(overhead_ns: u64, f: impl FnOnce() -> T) -> (T, f64, Option<f64>) {
    let c0 = process_cpu_ns();
    let t = Instant::now();
    let out = f();
    let wall_ms = t.elapsed().as_secs_f64() * 1e3;
    let c1 = process_cpu_ns();
    let cpu_ms = c0
        .zip(c1)
        .map(|(a, b)| b.saturating_sub(a).saturating_sub(overhead_ns) as f64 * 1e-6);
    (out, wall_ms, cpu_ms)
}

/// Runs the benchmark (the first method is the reference of the ratios).
pub fn run(b: &LocalizationBench) -> Result<Report> {
    if b.runs < 1 {
        return Err(Error::Invalid("--runs must be at least 1".into()));
    }
    let (pairs, methods) = (&b.pairs, &b.methods);
    let views: Vec<&Mat> = pairs.iter().flat_map(|p| [&p.left, &p.right]).collect();
    let config = LocalizerConfig {
        lattice_window: b.config.lattice_window && b.one_recording,
        ..b.config.clone()
    };
    let create = |m: &Method| {
        create_localizer(*m, &config)
            .map_err(|e| Error::from(e).context(format!("cannot set up method '{m}'")))
    };
    // Per method: the left camera's localizer (left views and whole pairs), then the right one's.
    let mut locs: Vec<[Box<dyn Localizer + Send>; 2]> = methods
        .iter()
        .map(|m| Ok([create(m)?, create(m)?]))
        .collect::<Result<_>>()?;
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
        b.warmup,
        b.runs,
        load.split_whitespace().take(3).collect::<Vec<_>>().join(" ")
    );
    // The CPU-time reading costs CPU itself: its median over a few empty measurements is subtracted.
    let mut empty: Vec<u64> = (0..31)
        .filter_map(|_| {
            process_cpu_ns()
                .zip(process_cpu_ns())
                .map(|(a, b)| b.saturating_sub(a))
        })
        .collect();
    empty.sort_unstable();
    let overhead_ns = empty.get(empty.len() / 2).copied().unwrap_or(0);
    let n = locs.len();
    let (mut per_view, mut per_pair) = (vec![Vec::new(); n], vec![Vec::new(); n]);
    let (mut cpu_view, mut cpu_pair) = (vec![Vec::new(); n], vec![Vec::new(); n]);
    let mut markers = vec![0usize; n];
    for run in 0..b.warmup + b.runs {
        let counted = run >= b.warmup;
        let (view, side) = (views[run % views.len()], run % views.len() % 2);
        let pair = &pairs[run % pairs.len()];
        for (i, [left, right]) in locs.iter_mut().enumerate() {
            let camera = if side == 0 { &mut *left } else { &mut *right };
            let (found, view_ms, view_cpu) = timed(overhead_ns, || camera.detect(view));
            let found = found.map_err(|e| Error::from(e).context(format!("{} failed", camera.name())))?;
            let (both, pair_ms, pair_cpu) = timed(overhead_ns, || left.detect_stereo(pair));
            let both = both.map_err(|e| Error::from(e).context(format!("{} failed", left.name())))?;
            if counted {
                per_view[i].push(view_ms);
                per_pair[i].push(pair_ms);
                cpu_view[i].extend(view_cpu);
                cpu_pair[i].extend(pair_cpu);
                markers[i] += found.len() + both.left.len() + both.right.len();
            }
        }
    }
    let view_stats: Vec<_> = per_view.iter_mut().map(|s| stats(s)).collect();
    let pair_stats: Vec<_> = per_pair.iter_mut().map(|s| stats(s)).collect();
    let median_of = |s: &mut Vec<f64>| (!s.is_empty()).then(|| stats(s).0);
    let cpu_view_med: Vec<Option<f64>> = cpu_view.iter_mut().map(median_of).collect();
    let cpu_pair_med: Vec<Option<f64>> = cpu_pair.iter_mut().map(median_of).collect();
    let (blob_view, blob_pair) = (view_stats[0].0, pair_stats[0].0);
    let mut text = String::new();
    let _ = writeln!(
        text,
        "{:<12} {:>10} {:>9} {:>9} {:>10} {:>9} {:>9} {:>9} {:>9} {:>10} {:>8}",
        "method",
        "view med",
        "view p90",
        "x blob",
        "pair med",
        "pair p90",
        "x blob",
        "view CPU",
        "pair CPU",
        "CPU x blob",
        "markers"
    );
    let ms = |v: Option<f64>| v.map_or_else(|| "/".to_owned(), |v| format!("{v:.2} ms"));
    let mut rows = Vec::new();
    for (i, m) in methods.iter().enumerate() {
        let (vm, v90, vmean) = view_stats[i];
        let (pm, p90, pmean) = pair_stats[i];
        let per_image = markers[i] as f64 / (3 * b.runs) as f64;
        let cpu_ratio = cpu_view_med[0].zip(cpu_view_med[i]).map(|(b, m)| b / m);
        let _ = writeln!(
            text,
            "{:<12} {:>7.2} ms {:>6.2} ms {:>8.2}x {:>7.2} ms {:>6.2} ms {:>8.2}x {:>9} {:>9} {:>10} {:>8.1}",
            m.as_str(),
            vm,
            v90,
            blob_view / vm,
            pm,
            p90,
            blob_pair / pm,
            ms(cpu_view_med[i]),
            ms(cpu_pair_med[i]),
            cpu_ratio.map_or_else(|| "/".to_owned(), |r| format!("{r:.2}x")),
            per_image
        );
        rows.push(json!({
            "method": m.as_str(),
            "view_ms": {"median": vm, "p90": v90, "mean": vmean},
            "pair_ms": {"median": pm, "p90": p90, "mean": pmean},
            "speedup_vs_blob": {"view": blob_view / vm, "pair": blob_pair / pm},
            "cpu_ms": {"view_median": cpu_view_med[i], "pair_median": cpu_pair_med[i]},
            "markers_per_image": per_image,
        }));
    }
    let _ = writeln!(
        text,
        "x vs blob = blob median / method median (> 1: faster than the blob baseline); CPU = process CPU time \
         of all threads per call (median), which other processes' load hardly changes"
    );
    let preprocessing = if methods
        .iter()
        .any(|m| matches!(m, Method::Marknet | Method::MarknetMre))
    {
        Some(preprocessing_kernels(views[0], &config, b.runs, b.warmup)?)
    } else {
        None
    };
    if let Some((layout, medians)) = &preprocessing {
        let _ = writeln!(text, "{}", preprocessing_line(layout, medians, views[0]));
    }
    let json = json!({
        "pairs": pairs.len(),
        "image_sizes": sizes,
        "preprocessing": preprocessing.map(|(layout, medians)| json!({
            "input": [layout.input_width, layout.input_height],
            "median_ms": medians.iter().map(|(k, ms)| json!({"kernels": k.as_str(), "median": ms})).collect::<Vec<_>>(),
        })),
        "runs": b.runs,
        "warmup": b.warmup,
        "cores": cores,
        "load_average_at_start": load.trim(),
        "ort_intra_threads": b.config.session.intra_threads,
        "blob_params": b.blob_params,
        "results": rows,
    });
    Ok(Report { text, json })
}

/// The layout the model gives `view`'s size after one pass and, per kernel set this CPU has (widest
/// first), the median ms of Marknet's preprocessing of `view` into that whole network input, the
/// kernel sets interleaved run by run on the calling thread.
fn preprocessing_kernels(
    view: &Mat,
    config: &LocalizerConfig,
    runs: usize,
    warmup: usize,
) -> Result<(InputLayout, Vec<(Kernels, f64)>)> {
    let mut marknet = Marknet::load(&config.marknet_path, &config.session)?;
    let size = gelstereo_markers::check_image(view)?;
    marknet.detect(view)?;
    let layout = marknet.next_layout(size);
    let kernels: Vec<Kernels> = [Kernels::Avx512, Kernels::Sse, Kernels::Scalar]
        .into_iter()
        .filter(|k| k.available())
        .collect();
    let mut scratch: Vec<ResizeScratch> = kernels.iter().map(|k| ResizeScratch::with_kernels(*k)).collect();
    let mut times = vec![Vec::with_capacity(runs); kernels.len()];
    let mut plane = Vec::new();
    for run in 0..warmup + runs {
        for (scratch, times) in scratch.iter_mut().zip(&mut times) {
            let t = Instant::now();
            network_input(view, &layout, scratch, &mut plane)?;
            if run >= warmup {
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
    }
    let medians = kernels
        .into_iter()
        .zip(times.iter_mut())
        .map(|(k, t)| (k, stats(t).0))
        .collect();
    Ok((layout, medians))
}

/// The report's line on [`preprocessing_kernels`]: each kernel set's median and its ratio to the
/// narrowest SIMD set's.
fn preprocessing_line(layout: &InputLayout, medians: &[(Kernels, f64)], view: &Mat) -> String {
    let sse = medians.iter().find(|(k, _)| *k == Kernels::Sse).map(|f| f.1);
    let each: Vec<String> = medians
        .iter()
        .map(|(k, ms)| match sse {
            Some(base) if *k != Kernels::Sse => {
                format!("{} {ms:.3} ms ({:.2}x SSE's time)", k.as_str(), ms / base)
            }
            _ => format!("{} {ms:.3} ms", k.as_str()),
        })
        .collect();
    format!(
        "Marknet's preprocessing of one {}x{} view into its whole network input ({}x{}: resize, median-colour margin, planar f32), one thread, kernel sets interleaved, medians: {}",
        view.cols(),
        view.rows(),
        layout.input_width,
        layout.input_height,
        each.join(", ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Only one stereo recording and nothing else is a stream; a dataset, several inputs or loose
    /// images are not.
    #[test]
    fn only_one_recording_is_benchmarked_as_a_stream() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let sample = root.join("data/sample/press-slide");
        assert!(one_recording(None, std::slice::from_ref(&sample)));
        assert!(!one_recording(Some(&root), std::slice::from_ref(&sample)));
        assert!(!one_recording(None, &[sample.clone(), sample.clone()]));
        assert!(!one_recording(None, &[sample.join("left")]));
        assert!(!one_recording(None, &[]));
    }
}
