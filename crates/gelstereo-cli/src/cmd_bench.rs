//! `gelstereo bench`, two benchmarks:
//! - localization (`--dataset DATA`, or recordings / images without `--calib`): latency of each
//!   method per view and per stereo pair, measured side by side in one process (the runs of the
//!   methods are interleaved, so machine load hits all alike), with the ratio to the blob baseline.
//!   Criterion benches of the same code are in `crates/gelstereo-markers/benches`.
//! - the whole stereo pipeline (`--calib FILE RECORDING` or `--pipeline RECORDING`; also
//!   `gelstereo track --bench`): per-stage medians and p90 in latency mode (one frame at a time),
//!   the whole pipeline per stereo frame with its CPU time, and the throughput mode (frames localized
//!   in parallel, sequential tracking); see [`run_pipeline`].

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Barrier, mpsc};
use std::time::Instant;

use anyhow::{Context, bail};
use gelstereo_core::{GridIndex, GridShape, ImageSize, Point2, StereoPair, TieredDetections};
use gelstereo_geometry::{StereoRig, TriangulationConfig, Triangulator};
use gelstereo_io::images::{self, StereoRecording};
use gelstereo_markers::{Localizer, Method, create_localizer};
use gelstereo_matching::{StereoConfig, StereoLattice};
use gelstereo_tracking::{SessionConfig, StereoSession};
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
    /// Timed runs per method and per measurement (after the warm-up); pipeline benchmark: timed
    /// frame-runs per mode.
    #[arg(long, default_value_t = 200)]
    runs: usize,
    /// Untimed warm-up runs per method (pipeline benchmark: frame-runs before the latency mode).
    #[arg(long, default_value_t = 20)]
    warmup: usize,
    /// Also write the figures as JSON here (`--json` is the same option).
    #[arg(long, alias = "json", value_name = "FILE.json")]
    out: Option<PathBuf>,
    /// Pipeline benchmark: the stereo calibration (OpenCV YAML/XML, or a folder / pair of mrcal
    /// .cameramodel files). With it, INPUT is one stereo recording and the whole pipeline is timed.
    #[arg(long, value_name = "FILE")]
    calib: Option<String>,
    /// Pipeline benchmark with the recording's own calib.yaml (as --calib RECORDING/calib.yaml).
    #[arg(long)]
    pipeline: bool,
    /// Pipeline benchmark: the localization method (blob, yolo, marknet or marknet-mre).
    #[arg(long, default_value = "marknet-mre")]
    method: Method,
    /// Pipeline benchmark: distinct frames loaded from frame 0 on, walked forth and back (0: all).
    #[arg(long, default_value_t = 0)]
    frames: usize,
    /// Pipeline benchmark: marker lattice ROWSxCOLS (default: the recording's meta.json, else 23x23).
    #[arg(long, value_name = "ROWSxCOLS")]
    grid: Option<String>,
    /// Pipeline benchmark: worker threads of the throughput mode (0: one per core).
    #[arg(long, default_value_t = 0)]
    workers: usize,
    #[command(flatten)]
    localizer: LocalizerArgs,
    /// Stereo recordings (folders with left/ and right/) or images (consecutive images form pairs);
    /// with --calib or --pipeline: one stereo recording.
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

/// Median, 90th percentile and mean of `samples_ms`.
fn stats(samples_ms: &mut [f64]) -> (f64, f64, f64) {
    samples_ms.sort_by(f64::total_cmp);
    let n = samples_ms.len();
    let q = |f: f64| samples_ms[((f * (n - 1) as f64).round() as usize).min(n - 1)];
    (q(0.5), q(0.9), samples_ms.iter().sum::<f64>() / n as f64)
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    if args.calib.is_some() || args.pipeline {
        let [recording] = args.inputs.as_slice() else {
            bail!(
                "the pipeline benchmark (--calib / --pipeline) takes exactly one stereo RECORDING, got {}",
                args.inputs.len()
            );
        };
        if args.dataset.is_some() {
            bail!("--dataset is for the localization benchmark; the pipeline benchmark takes one RECORDING");
        }
        return run_pipeline(&PipelineBench {
            recording,
            calib: args.calib.as_deref(),
            method: args.method,
            grid: args.grid.as_deref(),
            gel_thickness_mm: None,
            frames: args.frames,
            runs: args.runs,
            warmup: args.warmup,
            workers: args.workers,
            localizer: &args.localizer,
            json: args.out.as_deref(),
        });
    }
    if args.runs < 1 {
        bail!("--runs must be at least 1");
    }
    let mut methods = Method::parse_list(&args.methods)?;
    if !methods.contains(&Method::Blob) {
        methods.insert(0, Method::Blob);
    }
    let pairs = load_pairs(args)?;
    let views: Vec<&Mat> = pairs.iter().flat_map(|p| [&p.left, &p.right]).collect();
    let mut locs: Vec<Box<dyn Localizer + Send>> = methods
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
    for run in 0..args.warmup + args.runs {
        let counted = run >= args.warmup;
        let view = views[run % views.len()];
        let pair = &pairs[run % pairs.len()];
        for (i, loc) in locs.iter_mut().enumerate() {
            let (found, view_ms, view_cpu) = timed(overhead_ns, || loc.detect(view));
            let found = found.with_context(|| format!("{} failed", loc.name()))?;
            let (both, pair_ms, pair_cpu) = timed(overhead_ns, || loc.detect_stereo(pair));
            let both = both.with_context(|| format!("{} failed", loc.name()))?;
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
        let per_image = markers[i] as f64 / (3 * args.runs) as f64;
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

// ---------------------------------------------------------------------------------------------------
// Pipeline benchmark (`gelstereo bench --calib FILE RECORDING`, also `gelstereo track --bench`).
// ---------------------------------------------------------------------------------------------------

/// What the pipeline benchmark runs on and how (`gelstereo bench --calib` and `gelstereo track --bench`
/// fill it from their arguments).
pub struct PipelineBench<'a> {
    /// The stereo recording (folder with left/ and right/).
    pub recording: &'a Path,
    /// Calibration spec; `None`: the recording's calib.yaml.
    pub calib: Option<&'a str>,
    /// Localization method.
    pub method: Method,
    /// Lattice `ROWSxCOLS`; `None`: the recording's meta.json, else 23x23.
    pub grid: Option<&'a str>,
    /// Gel thickness, mm; `None`: the recording's meta.json, else the default.
    pub gel_thickness_mm: Option<f64>,
    /// Distinct frames loaded from frame 0 on (0: all).
    pub frames: usize,
    /// Timed frame-runs per mode.
    pub runs: usize,
    /// Untimed warm-up frame-runs (latency mode).
    pub warmup: usize,
    /// Worker threads of the throughput mode (0: one per core).
    pub workers: usize,
    /// Model paths, blob parameters and ONNX Runtime options (its `threads`: latency mode's intra-op
    /// threads).
    pub localizer: &'a LocalizerArgs,
    /// Also write the figures as JSON here.
    pub json: Option<&'a Path>,
}

/// Stage names of the latency table, in pipeline order (the indented ones: parts of localization,
/// for the learned methods only).
const STAGES: [&str; 11] = [
    "decode (both views, from bytes in memory)",
    "localization (both views, one batch)",
    "  preprocess (resize, f32 tensor)",
    "  network (ONNX Runtime run)",
    "  post-process (decode, select, MRE)",
    "tracking association (2 views)",
    "triangulation",
    "outlier test + fill",
    "contact geometry",
    "slip",
    "track() whole (stages above + rows)",
];

/// CPU time of all threads of this process, ns, from `clock_gettime(CLOCK_PROCESS_CPUTIME_ID)`: exact
/// at the moment of the call (the kernel adds the running threads' pending time), where
/// `/proc/self/task/*/schedstat` lags for a thread that is running; `None` if the clock fails.
#[allow(unsafe_code)]
fn process_cpu_clock_ns() -> Option<u64> {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes one timespec into `ts`, a valid and exclusively borrowed value.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return None;
    }
    Some(u64::try_from(ts.tv_sec).ok()? * 1_000_000_000 + u64::try_from(ts.tv_nsec).ok()?)
}

/// A point in time and the process CPU time then.
#[derive(Clone, Copy)]
struct Mark {
    wall: Instant,
    cpu_ns: Option<u64>,
}

impl Mark {
    fn now() -> Self {
        let cpu_ns = process_cpu_clock_ns();
        Self {
            wall: Instant::now(),
            cpu_ns,
        }
    }

    /// Wall time from `self` to `later`, ms.
    fn wall_ms(&self, later: &Mark) -> f64 {
        (later.wall - self.wall).as_secs_f64() * 1e3
    }

    /// CPU time of the process from `self` to `later`, ms, less `overhead_ns` (one clock reading).
    fn cpu_ms(&self, later: &Mark, overhead_ns: u64) -> Option<f64> {
        self.cpu_ns
            .zip(later.cpu_ns)
            .map(|(a, b)| b.saturating_sub(a).saturating_sub(overhead_ns) as f64 * 1e-6)
    }
}

/// Frame `j` of a ping-pong walk over `n` frames (0, 1, .., n-1, n-2, .., 1, 0, 1, ..): the motion
/// stays continuous however many runs are asked for, so the tracker sees realistic frame-to-frame
/// steps.
fn ping_pong(j: usize, n: usize) -> usize {
    if n <= 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let k = j % period;
    if k < n { k } else { period - k }
}

fn decode_pair(bytes: &StereoPair<Vec<u8>>, paths: &StereoPair<PathBuf>) -> anyhow::Result<StereoPair<Mat>> {
    let one = |b: &Vec<u8>, p: &Path| -> anyhow::Result<Mat> {
        let buf = opencv::core::Vector::<u8>::from_slice(b);
        let m = opencv::imgcodecs::imdecode(&buf, opencv::imgcodecs::IMREAD_COLOR)
            .with_context(|| format!("{}: cannot decode the image", p.display()))?;
        if m.empty() {
            bail!(
                "{}: cannot decode the image (not an image OpenCV reads)",
                p.display()
            );
        }
        Ok(m)
    };
    Ok(StereoPair::new(
        one(&bytes.left, &paths.left)?,
        one(&bytes.right, &paths.right)?,
    ))
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .unwrap_or_default()
        .split_whitespace()
        .take(3)
        .collect::<Vec<_>>()
        .join(" ")
}

/// Makes the calling thread one of the threads of rayon's global pool (a no-op once that pool
/// exists). The two views' parallel stages of one frame then start on this thread and hand one half
/// to the pool's other thread; from outside the pool each stage would wait for a pool thread to
/// wake up first, and gain nothing when none wakes in time.
pub fn join_rayon_pool() {
    // An error means the pool exists already (started by an earlier call): nothing to do.
    let _ = rayon::ThreadPoolBuilder::new()
        .use_current_thread()
        .build_global();
}

/// The pipeline benchmark: per-stage medians and p90 in latency mode (one frame at a time, frames
/// decoded into memory first), the whole pipeline per stereo frame, CPU time per frame, and the
/// throughput mode (localization of frames in parallel on worker threads, one ONNX Runtime session
/// with one intra-op thread each, feeding the sequential tracker).
pub fn run_pipeline(b: &PipelineBench) -> anyhow::Result<()> {
    if b.runs < 1 {
        bail!("--runs must be at least 1");
    }
    let input = b.recording;
    if !images::is_stereo_recording(input) {
        bail!(
            "{}: the pipeline benchmark needs a stereo recording (a folder with left/ and right/)",
            input.display()
        );
    }
    let rec = StereoRecording::open(input)?;
    if rec.is_empty() {
        bail!("{}: the recording holds no frames", input.display());
    }
    let spec = match b.calib {
        Some(c) => c.to_owned(),
        None => input.join("calib.yaml").display().to_string(),
    };
    let rig = StereoRig::load(&spec).with_context(|| format!("cannot load the calibration {spec}"))?;
    let (meta_grid, meta_thickness) = crate::cmd_track::meta(Some(input));
    let shape = match b.grid {
        Some(g) => crate::cmd_track::parse_grid(g)?,
        None => meta_grid.unwrap_or(GridShape::REFERENCE),
    };
    let mut config = SessionConfig::default();
    if let Some(t) = b.gel_thickness_mm.or(meta_thickness) {
        config.contact.gel_thickness_mm = t;
    }
    let n = if b.frames == 0 {
        rec.len()
    } else {
        b.frames.min(rec.len())
    };
    // Every frame read from disk first: encoded bytes (for the decode stage) and decoded images.
    let mut paths = Vec::with_capacity(n);
    let mut encoded = Vec::with_capacity(n);
    for k in 0..n {
        let p = rec
            .paths(k)
            .with_context(|| format!("{}: no frame {k}", input.display()))?;
        let read = |f: &Path| std::fs::read(f).with_context(|| format!("cannot read {}", f.display()));
        encoded.push(StereoPair::new(read(&p.left)?, read(&p.right)?));
        paths.push(p);
    }
    let frames: Vec<StereoPair<Mat>> = encoded
        .iter()
        .zip(&paths)
        .map(|(e, p)| decode_pair(e, p))
        .collect::<anyhow::Result<_>>()?;
    let size = (frames[0].left.cols(), frames[0].left.rows());
    for (k, f) in frames.iter().enumerate() {
        let s = ImageSize {
            width: f.left.cols().max(0) as u32,
            height: f.left.rows().max(0) as u32,
        };
        rig.check_image_sizes(s, s).with_context(|| {
            format!(
                "{}: frame {k} does not match the calibration {spec}",
                paths[k].left.display()
            )
        })?;
        if (f.right.cols(), f.right.rows()) != size || (f.left.cols(), f.left.rows()) != size {
            bail!(
                "{}: frame {k} is {}x{} / {}x{} (left / right), frame 0 {}x{}",
                input.display(),
                f.left.cols(),
                f.left.rows(),
                f.right.cols(),
                f.right.rows(),
                size.0,
                size.1
            );
        }
    }
    let mut loc_config = b.localizer.config()?;
    let models = loc_config
        .marknet_path
        .parent()
        .map(|p| p.display().to_string())
        .unwrap_or_default();
    let mut localizer = b.localizer.localizer(b.method)?;
    localizer.set_cpu_clock(process_cpu_clock_ns);
    // Latency mode: the two views in parallel wherever the stages allow (the throughput mode's
    // localizers and tracker keep to their own thread: the cores are busy with other frames there).
    join_rayon_pool();
    localizer.set_parallel(true);
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let workers = if b.workers == 0 { cores } else { b.workers };
    let load_start = load_average();
    eprintln!(
        "pipeline benchmark: {} ({n} frames of {}x{}, {}), {} warm-up + {} timed frame-runs per mode; {cores} cores, load average {load_start}",
        input.display(),
        size.0,
        size.1,
        b.method,
        b.warmup,
        b.runs
    );
    // The reference frame: indexing, then the session.
    let d0 = localizer.detect_stereo(&frames[0])?;
    let lattice = StereoLattice::from_reference(&rig, &d0.left, &d0.right, shape, StereoConfig::default())
        .with_context(|| {
            format!(
                "{}: frame 0 cannot be indexed as the reference lattice",
                paths[0].left.display()
            )
        })?;
    let l: Vec<(GridIndex, Point2)> = lattice.left().reference_view().markers().collect();
    let r: Vec<(GridIndex, Point2)> = lattice.right().reference_view().markers().collect();
    let triangulator = Triangulator::new(rig.clone(), TriangulationConfig::default())?;
    let make = || -> anyhow::Result<StereoSession> {
        Ok(StereoSession::new(
            shape,
            &l,
            &r,
            triangulator.clone(),
            config.clone(),
        )?)
    };
    // Reference indexing: once per session, timed on its own.
    let mut t_index = Vec::new();
    for i in 0..(b.runs.min(50) + 2) {
        let t = Instant::now();
        let lat = StereoLattice::from_reference(&rig, &d0.left, &d0.right, shape, StereoConfig::default());
        let ms = t.elapsed().as_secs_f64() * 1e3;
        lat?;
        if i >= 2 {
            t_index.push(ms);
        }
    }
    // A clock reading costs CPU itself: its median over a few empty intervals is subtracted.
    let mut empty: Vec<u64> = (0..31)
        .filter_map(|_| {
            process_cpu_clock_ns()
                .zip(process_cpu_clock_ns())
                .map(|(a, b)| b.saturating_sub(a))
        })
        .collect();
    empty.sort_unstable();
    let overhead_ns = empty.get(empty.len() / 2).copied().unwrap_or(0);

    // Latency mode: one frame at a time.
    let mut session = make()?;
    session.record_stage_marks(process_cpu_clock_ns);
    session.set_parallel(true);
    let mut times: Vec<Vec<f64>> = vec![Vec::with_capacity(b.runs); STAGES.len()];
    let mut cpu_times: Vec<Vec<f64>> = vec![Vec::with_capacity(b.runs); STAGES.len()];
    let (mut whole, mut cpu_whole) = (Vec::new(), Vec::new());
    let mut markers = 0usize;
    for j in 0..b.warmup + b.runs {
        let k = ping_pong(j, n);
        let m_decode = Mark::now();
        let decoded = decode_pair(&encoded[k], &paths[k])?;
        let m_decoded = Mark::now();
        drop(decoded);
        let m0 = Mark::now();
        let d = localizer.detect_stereo_tiered(&frames[k])?;
        let m1 = Mark::now();
        session.track_tiered(j as u32, &d.left, &d.right)?;
        let m2 = Mark::now();
        let st: Vec<Mark> = session
            .stage_marks()
            .iter()
            .map(|m| Mark {
                wall: m.wall,
                cpu_ns: m.cpu_ns,
            })
            .collect();
        if j < b.warmup {
            continue;
        }
        let mut push = |i: usize, a: &Mark, b: &Mark| {
            times[i].push(a.wall_ms(b));
            cpu_times[i].extend(a.cpu_ms(b, overhead_ns));
        };
        push(0, &m_decode, &m_decoded);
        push(1, &m0, &m1);
        for (i, w) in st.windows(2).enumerate() {
            push(5 + i, &w[0], &w[1]);
        }
        push(10, &m1, &m2);
        if let Some(parts) = localizer.last_times() {
            times[2].push(parts.preprocess_ms);
            times[3].push(parts.network_ms);
            times[4].push(parts.postprocess_ms);
            if let Some(cpu) = parts.cpu_ms {
                for (i, c) in cpu.iter().enumerate() {
                    cpu_times[2 + i].push((c - overhead_ns as f64 * 1e-6).max(0.0));
                }
            }
        }
        whole.push(m0.wall_ms(&m2));
        cpu_whole.extend(m0.cpu_ms(&m2, overhead_ns));
        markers += d.left.accepted.len() + d.right.accepted.len();
    }

    // Throughput mode: `workers` threads localize frames in parallel (each its own localizer, ONNX
    // Runtime at one intra-op thread), the calling thread tracks them in frame order as they arrive.
    loc_config.session.intra_threads = 1;
    let method = b.method;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(workers)
        .build()
        .context("cannot start the worker threads")?;
    let next = AtomicUsize::new(0);
    let stop = AtomicBool::new(false);
    let barrier = Barrier::new(workers + 1);
    let runs = b.runs;
    let mut throughput_session = make()?;
    let (tx, rx) = mpsc::channel::<(usize, anyhow::Result<StereoPair<TieredDetections>>)>();
    let (elapsed_s, cpu_ns) = pool.in_place_scope(|s| -> anyhow::Result<(f64, Option<u64>)> {
        for _ in 0..workers {
            let tx = tx.clone();
            let (frames, loc_config, next, stop, barrier) = (&frames, &loc_config, &next, &stop, &barrier);
            s.spawn(move |_| {
                let made = create_localizer(method, loc_config)
                    .with_context(|| format!("cannot set up method '{method}' for the throughput mode"));
                let mut loc = match made {
                    Ok(l) => Some(l),
                    Err(e) => {
                        stop.store(true, Ordering::SeqCst);
                        let _ = tx.send((usize::MAX, Err(e)));
                        None
                    }
                };
                // Warm-up: a few untimed frames per worker.
                if let Some(loc) = loc.as_mut() {
                    for k in 0..3 {
                        let _ = loc.detect_stereo(&frames[k % frames.len()]);
                    }
                }
                barrier.wait();
                let Some(mut loc) = loc else { return };
                while !stop.load(Ordering::SeqCst) {
                    let j = next.fetch_add(1, Ordering::SeqCst);
                    if j >= runs {
                        break;
                    }
                    let found = loc
                        .detect_stereo_tiered(&frames[ping_pong(j, frames.len())])
                        .map_err(anyhow::Error::from);
                    if tx.send((j, found)).is_err() {
                        break;
                    }
                }
            });
        }
        drop(tx);
        barrier.wait();
        let c0 = process_cpu_clock_ns();
        let t0 = Instant::now();
        let mut pending = std::collections::BTreeMap::new();
        let mut expect = 0usize;
        let result = (|| -> anyhow::Result<()> {
            for (j, found) in &rx {
                let found = found?;
                pending.insert(j, found);
                while let Some(d) = pending.remove(&expect) {
                    throughput_session.track_tiered(expect as u32, &d.left, &d.right)?;
                    expect += 1;
                }
            }
            Ok(())
        })();
        let elapsed = t0.elapsed().as_secs_f64();
        let c1 = process_cpu_clock_ns();
        if result.is_err() {
            stop.store(true, Ordering::SeqCst);
        }
        drop(rx);
        result?;
        if expect != runs {
            bail!("throughput mode: {expect} of {runs} frames tracked");
        }
        Ok((elapsed, c0.zip(c1).map(|(a, b)| b.saturating_sub(a))))
    })?;
    let fps = runs as f64 / elapsed_s.max(1e-9);
    let cpu_per_frame_tp = cpu_ns.map(|c| c as f64 * 1e-6 / runs as f64);
    let ort = matches!(b.method, Method::Marknet | Method::MarknetMre | Method::Yolo);
    let load_end = load_average();

    // Report.
    let mut text = String::new();
    let _ = writeln!(
        text,
        "stereo pipeline, {}: {n} frames of {}x{} decoded into memory before timing (disk not timed), walked 0..{} and back; method {} (models {models}); calibration {spec}",
        input.display(),
        size.0,
        size.1,
        n.saturating_sub(1),
        b.method
    );
    let threads = if b.localizer.threads == 0 {
        format!("{cores} (default: one per core)")
    } else {
        b.localizer.threads.to_string()
    };
    let _ = writeln!(
        text,
        "latency mode: one frame at a time, the two views' stages in parallel, {} timed frame-runs after {} warm-up{}; CPU = process CPU time, all threads",
        b.runs,
        b.warmup,
        if ort {
            format!(", ONNX Runtime intra-op threads {threads}")
        } else {
            String::new()
        }
    );
    let _ = writeln!(
        text,
        "{:<44} {:>10} {:>10} {:>10} {:>10}",
        "stage", "median", "p90", "mean", "CPU med"
    );
    let median_of = |s: &mut Vec<f64>| (!s.is_empty()).then(|| stats(s).0);
    let ms = |v: Option<f64>| v.map_or_else(|| "/".to_owned(), |v| format!("{v:.3} ms"));
    let mut stage_rows = Vec::new();
    for ((name, samples), cpu) in STAGES.iter().zip(times.iter_mut()).zip(cpu_times.iter_mut()) {
        if samples.is_empty() {
            continue;
        }
        let (med, p90, mean) = stats(samples);
        let cpu_med = median_of(cpu);
        let _ = writeln!(
            text,
            "{name:<44} {med:>7.3} ms {p90:>7.3} ms {mean:>7.3} ms {:>10}",
            ms(cpu_med)
        );
        stage_rows.push(
            json!({"stage": name, "median_ms": med, "p90_ms": p90, "mean_ms": mean, "cpu_median_ms": cpu_med}),
        );
    }
    let (idx_med, idx_p90, idx_mean) = stats(&mut t_index);
    let _ = writeln!(
        text,
        "{:<44} {idx_med:>7.3} ms {idx_p90:>7.3} ms {idx_mean:>7.3} ms {:>10}",
        "reference grid indexing (once per session)", "/"
    );
    let (w_med, w_p90, w_mean) = stats(&mut whole);
    let cpu_whole_med = median_of(&mut cpu_whole);
    let _ = writeln!(
        text,
        "whole pipeline (localization + track(), decoded frames): median {w_med:.2} ms, p90 {w_p90:.2} ms per stereo frame ({:.0} frames/s one at a time); CPU {} per frame",
        1e3 / w_med,
        ms(cpu_whole_med),
    );
    let _ = writeln!(
        text,
        "throughput mode: {fps:.1} stereo frames/s over {runs} frames ({workers} workers localizing frames in parallel{}, sequential tracker); CPU {} per frame",
        if ort {
            ", one ONNX Runtime intra-op thread each"
        } else {
            ""
        },
        ms(cpu_per_frame_tp)
    );
    let _ = writeln!(
        text,
        "not timed: exports (markers.csv / frames.csv rows, PLY, overlays, plots); {:.1} markers per view; tracking stages from StereoSession::track's own stage marks; load average {load_start} at start, {load_end} at end",
        markers as f64 / (2 * b.runs) as f64,
    );
    print!("{text}");
    if let Some(out) = b.json {
        let report = json!({
            "recording": input.display().to_string(),
            "calibration": spec,
            "method": b.method.as_str(),
            "models": models,
            "frames": n,
            "image_size": [size.0, size.1],
            "runs": b.runs,
            "warmup": b.warmup,
            "cores": cores,
            "load_average_at_start": load_start,
            "load_average_at_end": load_end,
            "latency": {
                "ort_intra_threads": b.localizer.threads,
                "stages": stage_rows,
                "reference_indexing_ms": {"median": idx_med, "p90": idx_p90, "mean": idx_mean},
                "whole_ms": {"median": w_med, "p90": w_p90, "mean": w_mean},
                "cpu_ms_per_frame": cpu_whole_med,
            },
            "throughput": {
                "workers": workers,
                "ort_intra_threads": 1,
                "frames": runs,
                "frames_per_s": fps,
                "cpu_ms_per_frame": cpu_per_frame_tp,
            },
            "tracking_stages_from": "StereoSession::track stage marks",
            "not_timed": "exports (CSV rows, PLY, overlays, plots)",
        });
        let pretty = serde_json::to_string_pretty(&report).context("cannot format the JSON report")?;
        std::fs::write(out, pretty + "\n").with_context(|| format!("cannot write {}", out.display()))?;
    }
    Ok(())
}
