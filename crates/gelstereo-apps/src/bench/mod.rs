//! Benchmarks of the pipeline as it runs, timing [`gelstereo::Pipeline`] and [`gelstereo::track::run`]
//! themselves (no copy of their logic):
//! - [`pipeline`]: per-stage medians and p90 in latency mode (one frame at a time, frames decoded
//!   into memory first; the stages timed from their `tracing` spans by a subscriber installed on the
//!   benchmark's thread for that mode only), the whole pipeline per stereo frame with its CPU time, and the throughput
//!   mode (frames localized in parallel on worker threads, feeding the pipeline's tracker in order;
//!   repeated with fresh workers as asked, its medians and range);
//! - [`end_to_end`]: `gelstereo track` from disk with its default outputs, repeated, the median
//!   run's frames/s and CPU time per frame.

pub mod localization;
mod span_clock;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Barrier, mpsc};
use std::time::Instant;

use gelstereo_core::stats::median;
use gelstereo_core::{StereoPair, TieredDetections};
use gelstereo_io::images::{self, StereoRecording};
use gelstereo_markers::{Method, create_localizer};
use opencv::core::{Mat, MatTraitConst};
use serde_json::json;
use span_clock::{Interval, Mark, SpanClock};

use gelstereo::source::FrameSource;
use gelstereo::track::{SinkOptions, TrackOptions};
use gelstereo::{Error, Frame, Images, Pipeline, PipelineConfig, Result};

/// A benchmark's result: the table as text, and the figures as JSON.
#[derive(Debug, Clone)]
pub struct Report {
    /// What `gelstereo bench` prints.
    pub text: String,
    /// The same figures, for `--json`.
    pub json: serde_json::Value,
}

/// What the pipeline benchmark runs on and how.
#[derive(Debug, Clone)]
pub struct PipelineBench {
    /// The stereo recording (folder with left/ and right/).
    pub recording: PathBuf,
    /// The pipeline (calibration, method, models, grid, gel thickness).
    pub config: PipelineConfig,
    /// Distinct frames loaded from frame 0 on (0: all).
    pub frames: usize,
    /// Timed frame-runs per mode.
    pub runs: usize,
    /// Untimed warm-up frame-runs (latency mode).
    pub warmup: usize,
    /// Worker threads of the throughput mode (0: one per core).
    pub workers: usize,
    /// Runs of the throughput mode, each with fresh workers: its figures are their medians (on a
    /// shared machine one run's CPU per frame moves by more than a change worth measuring).
    pub repeats: usize,
}

/// Where a row of the latency table is timed.
#[derive(Clone, Copy)]
enum Timed {
    /// Decoding both views from their bytes, by the benchmark.
    Decode,
    /// From the call of [`Pipeline::process`] to the first tracking span.
    Localization,
    /// The own time of the spans of this name ([`span_clock`]).
    Span(&'static str),
    /// From the first tracking span to the return of [`Pipeline::process`].
    TrackWhole,
}

/// The span that starts the tracking stages of a stereo frame.
const FIRST_TRACKING_SPAN: &str = "track";

/// The rows of the latency table, in pipeline order, and where each is timed (the indented ones:
/// parts of localization, for Marknet only).
const STAGES: [(&str, Timed); 11] = [
    ("decode (both views, from bytes in memory)", Timed::Decode),
    ("localization (both views, one batch)", Timed::Localization),
    (
        "  preprocess (resize, f32 tensor)",
        Timed::Span("marknet.preprocess"),
    ),
    ("  network (ONNX Runtime run)", Timed::Span("marknet.network")),
    (
        "  post-process (decode, select, MRE)",
        Timed::Span("marknet.postprocess"),
    ),
    ("tracking association (2 views)", Timed::Span(FIRST_TRACKING_SPAN)),
    ("triangulation", Timed::Span("triangulate")),
    ("outlier test + fill", Timed::Span("outliers")),
    ("contact geometry", Timed::Span("contact")),
    ("slip", Timed::Span("slip")),
    ("track() whole (stages above + rows)", Timed::TrackWhole),
];

/// CPU time of all threads of this process, ns, from `clock_gettime(CLOCK_PROCESS_CPUTIME_ID)`: exact
/// at the moment of the call (the kernel adds the running threads' pending time), where
/// `/proc/self/task/*/schedstat` lags for a thread that is running; `None` if the clock fails.
#[allow(unsafe_code)]
pub fn process_cpu_clock_ns() -> Option<u64> {
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

/// The cost of one CPU-clock reading, ns: the median over a few empty intervals (subtracted from
/// every CPU interval measured).
pub fn clock_overhead_ns() -> u64 {
    let mut empty: Vec<u64> = (0..31)
        .filter_map(|_| {
            process_cpu_clock_ns()
                .zip(process_cpu_clock_ns())
                .map(|(a, b)| b.saturating_sub(a))
        })
        .collect();
    empty.sort_unstable();
    empty.get(empty.len() / 2).copied().unwrap_or(0)
}

/// Median, 90th percentile and mean of `samples_ms` (zeros when empty).
pub fn stats(samples_ms: &mut [f64]) -> (f64, f64, f64) {
    if samples_ms.is_empty() {
        return (0.0, 0.0, 0.0);
    }
    samples_ms.sort_by(f64::total_cmp);
    let n = samples_ms.len();
    let q = |f: f64| samples_ms[((f * (n - 1) as f64).round() as usize).min(n - 1)];
    (q(0.5), q(0.9), samples_ms.iter().sum::<f64>() / n as f64)
}

/// The load average (1, 5, 15 min) as `/proc/loadavg` gives it.
pub fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .unwrap_or_default()
        .split_whitespace()
        .take(3)
        .collect::<Vec<_>>()
        .join(" ")
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

fn decode(bytes: &[u8], path: &Path) -> Result<Mat> {
    let buf = opencv::core::Vector::<u8>::from_slice(bytes);
    let m = opencv::imgcodecs::imdecode(&buf, opencv::imgcodecs::IMREAD_COLOR)?;
    if m.empty() {
        return Err(Error::Invalid(format!(
            "{}: cannot decode the image (not an image OpenCV reads)",
            path.display()
        )));
    }
    Ok(m)
}

/// The first `n` frames of a recording, as encoded bytes and decoded.
struct Loaded {
    paths: Vec<StereoPair<PathBuf>>,
    encoded: Vec<StereoPair<Vec<u8>>>,
    frames: Vec<Frame>,
}

fn load(rec: &StereoRecording, n: usize) -> Result<Loaded> {
    let mut loaded = Loaded {
        paths: Vec::with_capacity(n),
        encoded: Vec::with_capacity(n),
        frames: Vec::with_capacity(n),
    };
    for k in 0..n {
        let Some(p) = rec.paths(k) else { break };
        let read = |f: &Path| std::fs::read(f).map_err(gelstereo::file_err(f));
        let bytes = StereoPair::new(read(&p.left)?, read(&p.right)?);
        loaded.frames.push(Frame::stereo(
            decode(&bytes.left, &p.left)?,
            decode(&bytes.right, &p.right)?,
        ));
        loaded.encoded.push(bytes);
        loaded.paths.push(p);
    }
    Ok(loaded)
}

fn open_recording(input: &Path) -> Result<StereoRecording> {
    if !images::is_stereo_recording(input) {
        return Err(Error::Invalid(format!(
            "{}: the pipeline benchmark needs a stereo recording (a folder with left/ and right/)",
            input.display()
        )));
    }
    let rec = StereoRecording::open(input)?;
    if rec.is_empty() {
        return Err(Error::Invalid(format!(
            "{}: the recording holds no frames",
            input.display()
        )));
    }
    Ok(rec)
}

/// Per-stage samples of the latency mode.
struct Latency {
    times: Vec<Vec<f64>>,
    cpu: Vec<Vec<f64>>,
    whole: Vec<f64>,
    cpu_whole: Vec<f64>,
    markers: usize,
}

impl Latency {
    fn push(&mut self, row: usize, time: Interval, overhead_ns: u64) {
        self.times[row].push(time.wall_ms());
        self.cpu[row].extend(time.cpu_ms(overhead_ns));
    }
}

/// Latency mode: one frame at a time through [`Pipeline::process`], its stages timed from their
/// `tracing` spans by a [`SpanClock`] on this thread.
fn latency(pipeline: &mut Pipeline, loaded: &Loaded, b: &PipelineBench, overhead_ns: u64) -> Result<Latency> {
    let n = loaded.frames.len();
    let mut l = Latency {
        times: vec![Vec::with_capacity(b.runs); STAGES.len()],
        cpu: vec![Vec::with_capacity(b.runs); STAGES.len()],
        whole: Vec::new(),
        cpu_whole: Vec::new(),
        markers: 0,
    };
    let clock = Arc::new(SpanClock::default());
    let _timing = tracing::subscriber::set_default(Arc::clone(&clock));
    for j in 0..b.warmup + b.runs {
        let k = ping_pong(j, n);
        let m_decode = Mark::now();
        let decoded = decode(&loaded.encoded[k].left, &loaded.paths[k].left)
            .and_then(|l| Ok((l, decode(&loaded.encoded[k].right, &loaded.paths[k].right)?)))?;
        let m_decoded = Mark::now();
        drop(decoded);
        let m0 = Mark::now();
        let out = pipeline.process(&loaded.frames[k])?;
        let m2 = Mark::now();
        if let Some(note) = &out.note {
            return Err(Error::Invalid(format!(
                "{}: {note}",
                loaded.paths[k].left.display()
            )));
        }
        let spans = clock.take_frame();
        if j < b.warmup {
            continue;
        }
        let Some(m1) = spans.get(FIRST_TRACKING_SPAN).map(|t| t.first) else {
            continue;
        };
        for (row, (_, timed)) in STAGES.iter().enumerate() {
            let time = match timed {
                Timed::Decode => Some(Interval::between(&m_decode, &m_decoded)),
                Timed::Localization => Some(Interval::between(&m0, &m1)),
                Timed::Span(name) => spans.get(name).map(|t| t.own),
                Timed::TrackWhole => Some(Interval::between(&m1, &m2)),
            };
            if let Some(time) = time {
                l.push(row, time, overhead_ns);
            }
        }
        let whole = Interval::between(&m0, &m2);
        l.whole.push(whole.wall_ms());
        l.cpu_whole.extend(whole.cpu_ms(overhead_ns));
        l.markers += out.markers.iter().filter(|m| m.left_px.is_some()).count()
            + out.markers.iter().filter(|m| m.right_px.is_some()).count();
    }
    Ok(l)
}

/// Throughput mode: `workers` threads localize frames in parallel (each its own localizer, ONNX
/// Runtime at one intra-op thread), the calling thread feeds them in frame order to `pipeline`.
/// Returns the elapsed time, s, and the CPU time, ns.
fn throughput(
    pipeline: &mut Pipeline,
    frames: &[Frame],
    b: &PipelineBench,
    workers: usize,
) -> Result<(f64, Option<u64>)> {
    let mut loc_config = b.config.localizer.clone();
    loc_config.session.intra_threads = 1;
    let method = b.config.chosen_method();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(workers)
        .build()
        .map_err(|e| Error::Invalid(format!("cannot start the worker threads: {e}")))?;
    let next = AtomicUsize::new(0);
    let stop = AtomicBool::new(false);
    let barrier = Barrier::new(workers + 1);
    let runs = b.runs;
    let (tx, rx) = mpsc::channel::<(usize, Result<StereoPair<TieredDetections>>)>();
    pool.in_place_scope(|s| -> Result<(f64, Option<u64>)> {
        for _ in 0..workers {
            let tx = tx.clone();
            let (loc_config, next, stop, barrier) = (&loc_config, &next, &stop, &barrier);
            s.spawn(move |_| {
                let mut loc = match create_localizer(method, loc_config) {
                    Ok(l) => Some(l),
                    Err(e) => {
                        stop.store(true, Ordering::SeqCst);
                        let _ = tx.send((
                            usize::MAX,
                            Err(Error::from(e)
                                .context(format!("cannot set up method '{method}' for the throughput mode"))),
                        ));
                        None
                    }
                };
                // Warm-up: a few untimed frames per worker.
                if let Some(loc) = loc.as_mut() {
                    for f in frames.iter().cycle().take(3) {
                        if let Images::Stereo(pair) = &f.images {
                            let _ = loc.detect_stereo(pair);
                        }
                    }
                }
                barrier.wait();
                let Some(mut loc) = loc else { return };
                while !stop.load(Ordering::SeqCst) {
                    let j = next.fetch_add(1, Ordering::SeqCst);
                    if j >= runs {
                        break;
                    }
                    let Images::Stereo(pair) = &frames[ping_pong(j, frames.len())].images else {
                        break;
                    };
                    let found = loc.detect_stereo_tiered(pair).map_err(Error::from);
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
        let mut pending = BTreeMap::new();
        let mut expect = 0usize;
        let result = (|| -> Result<()> {
            for (j, found) in &rx {
                pending.insert(j, found?);
                while let Some(d) = pending.remove(&expect) {
                    pipeline.process_detected(&frames[ping_pong(expect, frames.len())], d)?;
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
            return Err(Error::Invalid(format!(
                "throughput mode: {expect} of {runs} frames tracked"
            )));
        }
        Ok((elapsed, c0.zip(c1).map(|(a, b)| b.saturating_sub(a))))
    })
}

/// The medians of the throughput mode's runs: frames/s, and CPU ms per frame where measured.
fn median_run(runs: &[(f64, Option<f64>)]) -> (f64, Option<f64>) {
    let mut fps: Vec<f64> = runs.iter().map(|r| r.0).collect();
    let mut cpu: Vec<f64> = runs.iter().filter_map(|r| r.1).collect();
    (median(&mut fps).unwrap_or(0.0), median(&mut cpu))
}

/// ", the median of N runs (CPU a-b ms per frame, c-d frames/s)" for more than one run, else "".
fn spread_of_runs(runs: &[(f64, Option<f64>)]) -> String {
    if runs.len() < 2 {
        return String::new();
    }
    let range = |v: &mut dyn Iterator<Item = f64>| {
        v.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
            (lo.min(x), hi.max(x))
        })
    };
    let (fps_lo, fps_hi) = range(&mut runs.iter().map(|r| r.0));
    let cpu = match range(&mut runs.iter().filter_map(|r| r.1)) {
        (lo, hi) if lo <= hi => format!("CPU {lo:.2}-{hi:.2} ms per frame, "),
        _ => String::new(),
    };
    format!(
        ", the median of {} runs ({cpu}{fps_lo:.1}-{fps_hi:.1} frames/s)",
        runs.len()
    )
}

/// The recording of the pipeline benchmark, loaded, and the machine it runs on.
struct Setup {
    loaded: Loaded,
    /// Image size, px (width, height).
    size: (i32, i32),
    /// The folder of the models.
    models: String,
    method: Method,
    cores: usize,
    /// Worker threads of the throughput mode.
    workers: usize,
}

impl Setup {
    /// Checks the options and loads the first frames of the recording.
    fn open(b: &PipelineBench) -> Result<Self> {
        if b.runs < 1 {
            return Err(Error::Invalid("--runs must be at least 1".into()));
        }
        if b.repeats < 1 {
            return Err(Error::Invalid("--repeats must be at least 1".into()));
        }
        let rec = open_recording(&b.recording)?;
        let n = if b.frames == 0 {
            rec.len()
        } else {
            b.frames.min(rec.len())
        };
        let loaded = load(&rec, n)?;
        let left = loaded.frames[0].images.left();
        let size = (left.cols(), left.rows());
        let models = b
            .config
            .localizer
            .marknet_path
            .parent()
            .map(|p| p.display().to_string())
            .unwrap_or_default();
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let workers = if b.workers == 0 { cores } else { b.workers };
        let max = gelstereo_core::limits::MAX_THREADS;
        if workers > max {
            return Err(Error::Invalid(format!(
                "workers: at most {max} threads, got {workers}"
            )));
        }
        Ok(Self {
            loaded,
            size,
            models,
            method: b.config.chosen_method(),
            cores,
            workers,
        })
    }

    fn frames(&self) -> usize {
        self.loaded.frames.len()
    }

    /// Whether the method runs a network through ONNX Runtime.
    fn ort(&self) -> bool {
        matches!(self.method, Method::Marknet | Method::MarknetMre | Method::Yolo)
    }
}

/// Processes the reference frame with `pipeline`, then times reference indexing on its own (a
/// fresh pipeline each time): frame 0's markers, and the indexing times, ms.
fn reference_indexing(
    pipeline: &mut Pipeline,
    loaded: &Loaded,
    b: &PipelineBench,
) -> Result<(StereoPair<TieredDetections>, Vec<f64>)> {
    let reference = pipeline.process(&loaded.frames[0])?;
    if let Some(note) = reference.note {
        return Err(Error::Invalid(format!(
            "{}: frame 0 cannot be indexed as the reference lattice: {note}",
            loaded.paths[0].left.display()
        )));
    }
    let Images::Stereo(pair) = &loaded.frames[0].images else {
        return Err(Error::Invalid(
            "the pipeline benchmark needs stereo frames".into(),
        ));
    };
    let dets0 = pipeline.localizer_mut().detect_stereo_tiered(pair)?;
    let mut index_ms = Vec::new();
    for i in 0..(b.runs.min(50) + 2) {
        let mut fresh =
            Pipeline::with_localizer(&b.config, create_localizer(Method::Blob, &b.config.localizer)?)?;
        let t = Instant::now();
        fresh.process_detected(&loaded.frames[0], dets0.clone())?;
        if i >= 2 {
            index_ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    Ok((dets0, index_ms))
}

/// The throughput mode's runs: each run's frames/s and CPU ms per frame, and their medians.
struct ThroughputRuns {
    repeats: Vec<(f64, Option<f64>)>,
    fps: f64,
    cpu_ms: Option<f64>,
    /// With Marknet on a window around the lattice: the same mode on the whole input, right after.
    whole_input: Option<(f64, Option<f64>)>,
}

/// The throughput mode `b.repeats` times (and on the whole input where Marknet runs on a window),
/// each run with a fresh pipeline started from frame 0's markers `dets0`.
fn throughput_runs(
    b: &PipelineBench,
    s: &Setup,
    dets0: &StereoPair<TieredDetections>,
) -> Result<ThroughputRuns> {
    let throughput_of = |bench: &PipelineBench| -> Result<(f64, Option<f64>)> {
        let mut tp_pipeline = Pipeline::with_localizer(
            &bench.config,
            create_localizer(Method::Blob, &bench.config.localizer)?,
        )?;
        tp_pipeline.process_detected(&s.loaded.frames[0], dets0.clone())?;
        let (elapsed_s, cpu_ns) = throughput(&mut tp_pipeline, &s.loaded.frames, bench, s.workers)?;
        let fps = bench.runs as f64 / elapsed_s.max(1e-9);
        Ok((fps, cpu_ns.map(|c| c as f64 * 1e-6 / bench.runs as f64)))
    };
    let repeats: Vec<(f64, Option<f64>)> = (0..b.repeats).map(|_| throughput_of(b)).collect::<Result<_>>()?;
    let (fps, cpu_ms) = median_run(&repeats);
    let windowed =
        matches!(s.method, Method::Marknet | Method::MarknetMre) && b.config.localizer.lattice_window;
    let whole_input = if windowed {
        let mut whole = b.clone();
        whole.config.localizer.lattice_window = false;
        Some(throughput_of(&whole)?)
    } else {
        None
    };
    Ok(ThroughputRuns {
        repeats,
        fps,
        cpu_ms,
        whole_input,
    })
}

/// Median, p90 and mean of a row of the latency table, ms.
#[derive(Clone, Copy)]
struct Spread {
    median: f64,
    p90: f64,
    mean: f64,
}

impl Spread {
    fn of(samples_ms: &mut [f64]) -> Self {
        let (median, p90, mean) = stats(samples_ms);
        Self { median, p90, mean }
    }

    fn json(&self) -> serde_json::Value {
        json!({"median": self.median, "p90": self.p90, "mean": self.mean})
    }
}

/// The latency mode's figures.
struct LatencySummary {
    /// Per stage with samples: its name, wall times and median CPU time.
    stages: Vec<(&'static str, Spread, Option<f64>)>,
    index: Spread,
    whole: Spread,
    cpu_whole: Option<f64>,
    markers_per_view: f64,
}

impl LatencySummary {
    fn new(mut lat: Latency, mut index_ms: Vec<f64>, runs: usize) -> Self {
        let median_of = |s: &mut Vec<f64>| (!s.is_empty()).then(|| stats(s).0);
        let stages = STAGES
            .iter()
            .zip(lat.times.iter_mut())
            .zip(lat.cpu.iter_mut())
            .filter(|((_, samples), _)| !samples.is_empty())
            .map(|(((name, _), samples), cpu)| (*name, Spread::of(samples), median_of(cpu)))
            .collect();
        Self {
            stages,
            index: Spread::of(&mut index_ms),
            whole: Spread::of(&mut lat.whole),
            cpu_whole: median_of(&mut lat.cpu_whole),
            markers_per_view: lat.markers as f64 / (2 * runs) as f64,
        }
    }
}

/// "x.xxx ms", or "/" where not measured.
fn ms_or_slash(v: Option<f64>) -> String {
    v.map_or_else(|| "/".to_owned(), |v| format!("{v:.3} ms"))
}

/// The pipeline benchmark (see the module docs).
pub fn pipeline(b: &PipelineBench) -> Result<Report> {
    let s = Setup::open(b)?;
    let mut pipeline = Pipeline::new(&b.config)?;
    let load_start = load_average();
    eprintln!(
        "pipeline benchmark: {} ({} frames of {}x{}, {}), {} warm-up + {} timed frame-runs per mode; {} cores, load average {load_start}",
        b.recording.display(),
        s.frames(),
        s.size.0,
        s.size.1,
        s.method,
        b.warmup,
        b.runs,
        s.cores
    );
    let (dets0, index_ms) = reference_indexing(&mut pipeline, &s.loaded, b)?;
    let overhead_ns = clock_overhead_ns();
    let lat = latency(&mut pipeline, &s.loaded, b, overhead_ns)?;
    let tp = throughput_runs(b, &s, &dets0)?;
    let loads = [load_start, load_average()];
    let lat = LatencySummary::new(lat, index_ms, b.runs);
    Ok(Report {
        text: pipeline_text(b, &s, &lat, &tp, &loads),
        json: pipeline_json(b, &s, &lat, &tp, loads),
    })
}

/// The pipeline benchmark's table; `loads`: the load average at start and at end.
fn pipeline_text(
    b: &PipelineBench,
    s: &Setup,
    lat: &LatencySummary,
    tp: &ThroughputRuns,
    loads: &[String; 2],
) -> String {
    let mut text = String::new();
    let _ = writeln!(
        text,
        "stereo pipeline, {}: {} frames of {}x{} decoded into memory before timing (disk not timed), walked 0..{} and back; method {} (models {}); calibration {}",
        b.recording.display(),
        s.frames(),
        s.size.0,
        s.size.1,
        s.frames().saturating_sub(1),
        s.method,
        s.models,
        b.config.calibration.clone().unwrap_or_default().display(),
    );
    let intra = b.config.localizer.session.intra_threads;
    let threads = if intra == 0 {
        format!("{} (default: one per core)", s.cores)
    } else {
        intra.to_string()
    };
    let _ = writeln!(
        text,
        "latency mode: one frame at a time through Pipeline::process, the two views' stages in parallel, {} timed frame-runs after {} warm-up{}; CPU = process CPU time, all threads",
        b.runs,
        b.warmup,
        if s.ort() {
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
    let rows = lat
        .stages
        .iter()
        .map(|(name, t, cpu)| (*name, t, ms_or_slash(*cpu)))
        .chain([(
            "reference grid indexing (once per session)",
            &lat.index,
            "/".to_owned(),
        )]);
    for (name, t, cpu) in rows {
        let _ = writeln!(
            text,
            "{name:<44} {:>7.3} ms {:>7.3} ms {:>7.3} ms {cpu:>10}",
            t.median, t.p90, t.mean
        );
    }
    let w = lat.whole;
    let _ = writeln!(
        text,
        "whole pipeline (localization + track(), decoded frames): median {:.2} ms, p90 {:.2} ms per stereo frame ({:.0} frames/s one at a time); CPU {} per frame",
        w.median,
        w.p90,
        1e3 / w.median.max(1e-9),
        ms_or_slash(lat.cpu_whole),
    );
    write_throughput(&mut text, b, s, tp);
    let _ = writeln!(
        text,
        "not timed: exports (markers.csv / frames.csv rows, PLY, overlays, plots; see `gelstereo bench --track`); {:.1} markers per view; stages from their `tracing` spans (own time, nested spans excluded); load average {} at start, {} at end",
        lat.markers_per_view, loads[0], loads[1],
    );
    text
}

/// The throughput mode's lines of the pipeline benchmark's table.
fn write_throughput(text: &mut String, b: &PipelineBench, s: &Setup, tp: &ThroughputRuns) {
    let _ = writeln!(
        text,
        "throughput mode: {:.1} stereo frames/s over {} frames ({} workers localizing frames in parallel{}, sequential tracker); CPU {} per frame{}",
        tp.fps,
        b.runs,
        s.workers,
        if s.ort() {
            ", one ONNX Runtime intra-op thread each"
        } else {
            ""
        },
        ms_or_slash(tp.cpu_ms),
        spread_of_runs(&tp.repeats)
    );
    if let Some((whole_fps, whole_cpu)) = tp.whole_input {
        let _ = writeln!(
            text,
            "throughput mode on the whole input of every frame (--whole-input), right after: {whole_fps:.1} stereo frames/s; CPU {} per frame{}",
            ms_or_slash(whole_cpu),
            tp.cpu_ms
                .zip(whole_cpu)
                .map_or_else(String::new, |(w, f)| format!(
                    " (the window: {:.2}x its CPU)",
                    w / f.max(1e-9)
                ))
        );
    }
}

/// The pipeline benchmark's figures as JSON; `loads`: the load average at start and at end.
fn pipeline_json(
    b: &PipelineBench,
    s: &Setup,
    lat: &LatencySummary,
    tp: &ThroughputRuns,
    loads: [String; 2],
) -> serde_json::Value {
    let [load_start, load_end] = loads;
    let stages: Vec<serde_json::Value> = lat
        .stages
        .iter()
        .map(|(name, t, cpu)| {
            json!({"stage": name, "median_ms": t.median, "p90_ms": t.p90, "mean_ms": t.mean, "cpu_median_ms": cpu})
        })
        .collect();
    let run = |(f, c): (f64, Option<f64>)| json!({"frames_per_s": f, "cpu_ms_per_frame": c});
    json!({
        "recording": b.recording.display().to_string(),
        "calibration": b.config.calibration.clone().unwrap_or_default().display().to_string(),
        "method": s.method.as_str(),
        "models": s.models,
        "frames": s.frames(),
        "image_size": [s.size.0, s.size.1],
        "runs": b.runs,
        "warmup": b.warmup,
        "cores": s.cores,
        "load_average_at_start": load_start,
        "load_average_at_end": load_end,
        "latency": {
            "ort_intra_threads": b.config.localizer.session.intra_threads,
            "stages": stages,
            "reference_indexing_ms": lat.index.json(),
            "whole_ms": lat.whole.json(),
            "cpu_ms_per_frame": lat.cpu_whole,
        },
        "throughput": {
            "workers": s.workers,
            "ort_intra_threads": 1,
            "frames": b.runs,
            "frames_per_s": tp.fps,
            "cpu_ms_per_frame": tp.cpu_ms,
            "repeats": tp.repeats.iter().copied().map(run).collect::<Vec<_>>(),
            "whole_input": tp.whole_input.map(run),
        },
        "tracking_stages_from": "tracing spans (own time)",
        "not_timed": "exports (CSV rows, PLY, overlays, plots)",
    })
}

/// What the end-to-end benchmark runs.
#[derive(Debug, Clone)]
pub struct EndToEndBench {
    /// The recording (any source [`FrameSource::open_path`] takes).
    pub recording: PathBuf,
    /// The pipeline.
    pub config: PipelineConfig,
    /// The outputs, as `gelstereo track` writes them.
    pub sinks: SinkOptions,
    /// Timed runs over the whole recording (after one untimed warm-up run).
    pub runs: usize,
    /// Where the outputs go (emptied of its own files before each run).
    pub out: PathBuf,
    /// Localization threads of the default mode (0: one per core), timed against one frame at a
    /// time.
    pub workers: usize,
}

/// `gelstereo track` end to end, as [`gelstereo::track::run`] runs it: frames read and decoded from disk
/// on the prefetch thread, the pipeline, the default outputs written. Two modes in turn within each
/// run, so machine load hits them alike: frames localized one at a time (`--workers 1`) and ahead of
/// the tracker by `workers` threads (`gelstereo track`'s default); `runs` timed runs of each after a
/// warm-up run, each with a fresh pipeline (models loaded before the clock starts).
pub fn end_to_end(b: &EndToEndBench) -> Result<Report> {
    if b.runs < 1 {
        return Err(Error::Invalid("--runs must be at least 1".into()));
    }
    let ahead_workers = TrackOptions {
        workers: b.workers,
        ..TrackOptions::default()
    }
    .localization_threads();
    let modes = [1, ahead_workers];
    let mut timed: [EndToEndRuns; 2] = Default::default();
    let mut frames = 0;
    let load_start = load_average();
    for run in 0..=b.runs {
        for (mode, &workers) in modes.iter().enumerate() {
            let (n, wall_s, cpu_ms) = end_to_end_run(b, workers)?;
            frames = n;
            if run > 0 {
                timed[mode].push(n, wall_s, cpu_ms);
            }
        }
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut text = String::new();
    let _ = writeln!(
        text,
        "gelstereo track end to end, {}: {frames} frames read and decoded from disk on the prefetch thread, {} ({}), outputs: {}; {} timed runs of each mode after 1 warm-up, in turn; {cores} cores, load average {load_start} at start, {} at end",
        b.recording.display(),
        b.config.chosen_method(),
        if b.config.calibration.is_some() {
            "stereo"
        } else {
            "mono"
        },
        b.sinks.describe(),
        b.runs,
        load_average()
    );
    let [one, ahead] = timed.map(|mut t| t.summary());
    let labels = [
        "one frame at a time (--workers 1)".to_owned(),
        format!("localized ahead by {ahead_workers} threads (default)"),
    ];
    for (label, m) in labels.iter().zip([&one, &ahead]) {
        let _ = writeln!(
            text,
            "{label}: median {:.1} stereo frames/s; {:.2} ms per frame (p90 of runs {:.2} ms); CPU {} per frame (all threads)",
            m.fps,
            m.wall_ms,
            m.wall_p90_ms,
            m.cpu_ms.map_or_else(|| "/".to_owned(), |c| format!("{c:.2} ms"))
        );
    }
    let _ = writeln!(
        text,
        "end to end: median {:.1} stereo frames/s with the default, {:.2}x the frames/s of one frame at a time",
        ahead.fps,
        ahead.fps / one.fps.max(1e-9)
    );
    let mode_json = |m: &EndToEndSummary, workers: usize| {
        json!({
            "workers": workers,
            "frames_per_s_median": m.fps,
            "ms_per_frame": {"median": m.wall_ms, "p90": m.wall_p90_ms},
            "cpu_ms_per_frame_median": m.cpu_ms,
        })
    };
    let json = json!({
        "recording": b.recording.display().to_string(),
        "frames": frames,
        "runs": b.runs,
        "method": b.config.chosen_method().as_str(),
        "outputs": b.sinks.describe(),
        "frames_per_s_median": ahead.fps,
        "one_at_a_time": mode_json(&one, 1),
        "localized_ahead": mode_json(&ahead, ahead_workers),
        "cores": cores,
        "load_average_at_start": load_start,
    });
    Ok(Report { text, json })
}

/// One end-to-end run with `workers` localization threads: frames, wall time (s), CPU time (ms).
fn end_to_end_run(b: &EndToEndBench, workers: usize) -> Result<(usize, f64, Option<f64>)> {
    let mut pipeline = Pipeline::new(&b.config)?;
    let source = FrameSource::open_path(&b.recording, false)?;
    let stereo = source.is_stereo();
    let folder = std::sync::Arc::new(gelstereo::sink::OutputFolder::prepare(&b.out, false)?);
    let mut sinks = gelstereo::track::sinks(&folder, &b.sinks, stereo)?;
    let options = TrackOptions {
        workers,
        ..TrackOptions::default()
    };
    let stop = AtomicBool::new(false);
    let c0 = process_cpu_clock_ns();
    let t0 = Instant::now();
    let summary = gelstereo::track::run(
        &mut pipeline,
        source.prefetch(gelstereo::track::PREFETCH_FRAMES),
        &mut sinks,
        &options,
        &stop,
        &mut |_| {},
    )?;
    let wall_s = t0.elapsed().as_secs_f64();
    let cpu_ms = c0
        .zip(process_cpu_clock_ns())
        .map(|(a, z)| z.saturating_sub(a) as f64 * 1e-6);
    Ok((summary.frames, wall_s, cpu_ms))
}

/// The timed runs of one end-to-end mode, per frame.
#[derive(Default)]
struct EndToEndRuns {
    walls_ms: Vec<f64>,
    fps: Vec<f64>,
    cpus_ms: Vec<f64>,
}

/// Medians of [`EndToEndRuns`].
struct EndToEndSummary {
    fps: f64,
    wall_ms: f64,
    wall_p90_ms: f64,
    cpu_ms: Option<f64>,
}

impl EndToEndRuns {
    fn push(&mut self, frames: usize, wall_s: f64, cpu_ms: Option<f64>) {
        let n = frames.max(1) as f64;
        self.walls_ms.push(wall_s * 1e3 / n);
        self.fps.push(frames as f64 / wall_s.max(1e-9));
        self.cpus_ms.extend(cpu_ms.map(|c| c / n));
    }

    fn summary(&mut self) -> EndToEndSummary {
        let (wall_ms, wall_p90_ms, _) = stats(&mut self.walls_ms);
        let (fps, _, _) = stats(&mut self.fps);
        let cpu_ms = (!self.cpus_ms.is_empty()).then(|| stats(&mut self.cpus_ms).0);
        EndToEndSummary {
            fps,
            wall_ms,
            wall_p90_ms,
            cpu_ms,
        }
    }
}
