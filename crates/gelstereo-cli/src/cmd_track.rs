//! `gelstereo track`: the whole pipeline over a recording: localization in each view, grid indexing
//! of the reference frame, tracking, triangulation, displacement, contact geometry and slip. Writes
//! `OUT/markers.csv` and `OUT/frames.csv` (docs/design.md contracts), per-frame PLY clouds and meshes
//! (`OUT/ply/`), overlay PNGs with displacement arrows (`OUT/overlays/`) and plots (`OUT/plots/`).
//! The work is `gelstereo_tracking::{StereoSession, MonoSession}`; this is input handling and output.
//!
//! Also `gelstereo track --bench`: an alias of the pipeline benchmark `gelstereo bench --calib FILE
//! RECORDING` (`cmd_bench.rs`).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use gelstereo_core::table::{FRAME_COLUMNS, MARKER_COLUMNS};
use gelstereo_core::{
    Detection, FrameSummary, GridIndex, GridShape, ImageSize, MarkerRecord, MarkerStatus, Point2, SlipState,
    StereoPair, TieredDetections,
};
use gelstereo_geometry::{StereoRig, TriangulationConfig, Triangulator};
use gelstereo_io::figures::{self, ColourScale, Curve, OverlayMarker, OverlayView, TimeSeries, Timeline};
use gelstereo_io::images::{self, StereoRecording};
use gelstereo_io::ply::{MarkerPoint, TriangleMesh, VertexProperty, write_marker_cloud, write_mesh};
use gelstereo_io::video::{self, VideoFrames};
use gelstereo_markers::{Localizer, Method};
use gelstereo_matching::eval::GroundTruth;
use gelstereo_matching::{
    Error as MatchError, IndexingConfig, ReferenceLattice, StereoConfig, StereoLattice,
};
use gelstereo_sim::SensorSpec;
use gelstereo_tracking::{
    ContactFrame, MonoSession, SessionConfig, StereoSession, TrackFrame, flagged_rows, interpolate,
};
use indicatif::{ProgressBar, ProgressStyle};
use opencv::core::{Mat, MatTraitConst, Scalar};

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo track`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Stereo calibration (OpenCV YAML/XML, or a folder / pair of mrcal .cameramodel files); default:
    /// the recording's calib.yaml. Needed for stereo input, ignored for mono.
    #[arg(long, value_name = "FILE")]
    calib: Option<String>,
    /// Output folder (created): markers.csv, frames.csv, ply/, overlays/ (PNG), plots/ (PNG and SVG).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Localization method: blob, marknet or marknet-mre (default: marknet-mre when its models are
    /// installed, else blob).
    #[arg(long)]
    method: Option<Method>,
    /// Marker lattice ROWSxCOLS (default: the recording's meta.json, else 23x23).
    #[arg(long, value_name = "ROWSxCOLS")]
    grid: Option<String>,
    /// Read frames live from camera N (OpenCV's device index: 0 is the first camera) instead of a
    /// recording.
    #[arg(long, value_name = "N")]
    camera: Option<i32>,
    /// Treat the video or camera frames as side-by-side stereo (left half, right half).
    #[arg(long)]
    side_by_side: bool,
    /// Track a stereo recording's left view only, as a mono sensor.
    #[arg(long)]
    mono: bool,
    /// Mirror this many pixels around each image border before localizing (mono input), so markers
    /// cut by the border are found (their centres are then biased towards the border).
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pad_border: i32,
    /// Marker pitch, mm: a mono sensor's contact area and centroid in mm; for a stereo grid that
    /// overfills the view without a sensor description, it settles the right view's column offset.
    #[arg(long, value_name = "MM")]
    pitch_mm: Option<f64>,
    /// Gel thickness, mm (width of the layer response used for the contact region); default: the
    /// recording's sensor description (meta.json), else 2.5 (the reference sensor).
    #[arg(long, value_name = "MM")]
    gel_thickness_mm: Option<f64>,
    /// Sensor description (JSON, as `gelstereo simulate --sensor` takes) of a stereo sensor whose
    /// marker grid overfills the cameras' view: its lattice, projected through the calibration,
    /// places the visible markers on the sensor's own grid indices. Default: the recording's
    /// meta.json `sensor`. Without one such a recording is indexed from its visible top-left marker.
    #[arg(long, value_name = "FILE")]
    sensor: Option<PathBuf>,
    /// Frame numbers (from 0, comma separated) at which the current frame becomes the new reference:
    /// drift correction.
    #[arg(long, value_delimiter = ',', value_name = "FRAME")]
    rezero_at: Vec<u32>,
    /// Stop after this many frames.
    #[arg(long, value_name = "N")]
    max_frames: Option<usize>,
    /// Write an overlay PNG (both views, displacement arrows) and a heat map every N frames (0: none).
    #[arg(long, default_value_t = 1, value_name = "N")]
    overlay_every: usize,
    /// Length factor of the displacement arrows in the overlays (1: true length in pixels).
    #[arg(long, default_value_t = 3.0, value_name = "K")]
    arrow_scale: f64,
    /// Do not write PLY files.
    #[arg(long)]
    no_ply: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Use the ground-truth 2-D marker positions of a simulated RECORDING (its markers.csv, markers
    /// visible in each view) instead of a localizer: measures indexing, tracking, triangulation,
    /// contact and slip alone. Ids are not taken from the truth: the positions are indexed and
    /// tracked like detections.
    #[arg(long)]
    from_ground_truth: bool,
    /// With --from-ground-truth: add Gaussian noise of this standard deviation to each coordinate, px.
    #[arg(long, default_value_t = 0.0, value_name = "PX")]
    gt_noise_px: f64,
    /// Benchmark the stereo pipeline on the recording instead of writing outputs (an alias of
    /// `gelstereo bench --calib FILE RECORDING`): per-stage medians, latency and throughput mode.
    #[arg(long)]
    bench: bool,
    /// Frame-runs timed per mode with --bench (after 20 warm-up runs).
    #[arg(long, default_value_t = 200, value_name = "N")]
    bench_frames: usize,
    #[command(flatten)]
    localizer: LocalizerArgs,
    /// A stereo recording (folder with left/ and right/), a folder of images (mono), or a video file.
    #[arg(value_name = "RECORDING|VIDEO")]
    input: Option<PathBuf>,
}

/// One frame of input.
enum Frame {
    Stereo(StereoPair<Mat>),
    Mono(Mat),
}

/// Where frames come from.
enum Source {
    Stereo(StereoRecording),
    Left(StereoRecording),
    Images(Vec<PathBuf>),
    Video {
        frames: VideoFrames,
        side_by_side: bool,
        failures: usize,
    },
    Camera {
        capture: opencv::videoio::VideoCapture,
        side_by_side: bool,
        index: i32,
    },
}

impl Source {
    fn is_stereo(&self) -> bool {
        match self {
            Source::Stereo(_) => true,
            Source::Left(_) | Source::Images(_) => false,
            Source::Video { side_by_side, .. } | Source::Camera { side_by_side, .. } => *side_by_side,
        }
    }

    fn len_hint(&self) -> Option<usize> {
        match self {
            Source::Stereo(r) | Source::Left(r) => Some(r.len()),
            Source::Images(v) => Some(v.len()),
            Source::Video { frames, .. } => Some(frames.declared_frame_count()).filter(|n| *n > 0),
            Source::Camera { .. } => None,
        }
    }

    /// Frame `k`: `None` at the end, `Some(Err)` for a frame that cannot be read (flagged).
    fn next(&mut self, k: usize) -> Option<anyhow::Result<Frame>> {
        match self {
            Source::Stereo(r) => r
                .read(k)
                .map(|p| p.map(Frame::Stereo).map_err(anyhow::Error::from)),
            Source::Left(r) => {
                let paths = r.paths(k)?;
                Some(
                    images::read_image(&paths.left)
                        .map(Frame::Mono)
                        .map_err(anyhow::Error::from),
                )
            }
            Source::Images(v) => {
                let p = v.get(k)?;
                Some(
                    images::read_image(p)
                        .map(Frame::Mono)
                        .map_err(anyhow::Error::from),
                )
            }
            Source::Video {
                frames,
                side_by_side,
                failures,
            } => {
                match frames.next_frame() {
                    Ok(None) => None,
                    Ok(Some((_, m))) => {
                        *failures = 0;
                        Some(if *side_by_side {
                            video::split_side_by_side(&m, frames.path())
                                .map(Frame::Stereo)
                                .map_err(anyhow::Error::from)
                        } else {
                            Ok(Frame::Mono(m))
                        })
                    }
                    Err(e) => {
                        *failures += 1;
                        // Give up after five unreadable frames in a row (a broken stream).
                        if *failures > 5 { None } else { Some(Err(e.into())) }
                    }
                }
            }
            Source::Camera {
                capture,
                side_by_side,
                index,
            } => {
                use opencv::prelude::VideoCaptureTrait;
                let mut m = Mat::default();
                match capture.read(&mut m) {
                    Ok(true) if !m.empty() => Some(if *side_by_side {
                        video::split_side_by_side(&m, Path::new(&format!("camera {index}")))
                            .map(Frame::Stereo)
                            .map_err(anyhow::Error::from)
                    } else {
                        Ok(Frame::Mono(m))
                    }),
                    Ok(_) => None,
                    Err(e) => Some(Err(anyhow::anyhow!("camera {index}: {e}"))),
                }
            }
        }
    }
}

fn open_source(args: &Args) -> anyhow::Result<Source> {
    if let Some(index) = args.camera {
        if args.input.is_some() {
            bail!("give either --camera N or a RECORDING|VIDEO, not both");
        }
        let capture = opencv::videoio::VideoCapture::new(index, opencv::videoio::CAP_ANY)
            .with_context(|| format!("cannot open camera {index}"))?;
        use opencv::prelude::VideoCaptureTraitConst;
        if !capture.is_opened().unwrap_or(false) {
            bail!("camera {index} cannot be opened (no such device, or it is busy)");
        }
        return Ok(Source::Camera {
            capture,
            side_by_side: args.side_by_side,
            index,
        });
    }
    let Some(input) = &args.input else {
        bail!(
            "no input: give a stereo recording (left/ and right/), a folder of images, a video file, or --camera N"
        );
    };
    if input.is_dir() {
        if images::is_stereo_recording(input) {
            let rec = StereoRecording::open(input)?;
            return Ok(if args.mono {
                Source::Left(rec)
            } else {
                Source::Stereo(rec)
            });
        }
        let files = images::list_images(input)?;
        if files.is_empty() {
            bail!(
                "{}: holds no images (expected left/ and right/, or {} files)",
                input.display(),
                images::IMAGE_EXTENSIONS.join("/")
            );
        }
        return Ok(Source::Images(files));
    }
    if !input.exists() {
        bail!("{}: no such file or folder", input.display());
    }
    if video::has_video_extension(input) {
        return Ok(Source::Video {
            frames: VideoFrames::open(input)?,
            side_by_side: args.side_by_side,
            failures: 0,
        });
    }
    bail!(
        "{}: expected a stereo recording folder, a folder of images or a video ({})",
        input.display(),
        video::VIDEO_EXTENSIONS.join("/")
    )
}

/// Parses `--grid ROWSxCOLS`.
pub(crate) fn parse_grid(text: &str) -> anyhow::Result<GridShape> {
    let (r, c) = text
        .split_once(['x', 'X'])
        .with_context(|| format!("--grid '{text}': expected ROWSxCOLS, e.g. 23x23"))?;
    let rows: u16 = r
        .trim()
        .parse()
        .with_context(|| format!("--grid '{text}': rows must be a number"))?;
    let cols: u16 = c
        .trim()
        .parse()
        .with_context(|| format!("--grid '{text}': columns must be a number"))?;
    if rows < 2 || cols < 2 {
        bail!("--grid '{text}': expected at least 2x2 markers");
    }
    Ok(GridShape { rows, cols })
}

/// The recording's sensor description (`meta.json` of a simulated recording): grid and gel thickness.
pub(crate) fn meta(input: Option<&Path>) -> (Option<GridShape>, Option<f64>) {
    let Some(dir) = input.filter(|p| p.is_dir()) else {
        return (None, None);
    };
    let Ok(text) = std::fs::read_to_string(dir.join("meta.json")) else {
        return (None, None);
    };
    let Ok(v) = serde_json::from_str::<serde_json::Value>(&text) else {
        return (None, None);
    };
    let grid = (|| {
        let rows = u16::try_from(v.get("grid")?.get("rows")?.as_u64()?).ok()?;
        let cols = u16::try_from(v.get("grid")?.get("cols")?.as_u64()?).ok()?;
        Some(GridShape { rows, cols })
    })();
    let thickness = v
        .get("sensor")
        .and_then(|s| s.get("gel"))
        .and_then(|g| g.get("thickness_mm"))
        .and_then(|t| t.as_f64());
    (grid, thickness)
}

/// The sensor description: `--sensor FILE`, else the recording's meta.json `sensor` (if any).
fn sensor_spec(args: &Args) -> anyhow::Result<Option<SensorSpec>> {
    if let Some(path) = &args.sensor {
        return Ok(Some(SensorSpec::load(path)?));
    }
    let Some(dir) = args.input.as_deref().filter(|p| p.is_dir()) else {
        return Ok(None);
    };
    let Ok(text) = std::fs::read_to_string(dir.join("meta.json")) else {
        return Ok(None);
    };
    // A recording's description that cannot be read only leaves the grid unplaced (older recordings).
    let spec = serde_json::from_str::<serde_json::Value>(&text)
        .ok()
        .and_then(|v| serde_json::from_value::<SensorSpec>(v.get("sensor")?.clone()).ok())
        .filter(|s| s.validate("meta.json sensor").is_ok());
    let Some(spec) = spec else {
        return Ok(None);
    };
    Ok(Some(spec))
}

fn choose_method(args: &Args) -> Method {
    args.method.unwrap_or_else(|| match args.localizer.config() {
        Ok(c) if c.marknet_path.is_file() && c.mre_path.is_file() => Method::MarknetMre,
        _ => Method::Blob,
    })
}

fn size_of(m: &Mat) -> ImageSize {
    ImageSize {
        width: m.cols().max(0) as u32,
        height: m.rows().max(0) as u32,
    }
}

/// Localizes `image` (with the localizer's second tier), first mirroring `pad` pixels around its
/// border when `pad > 0`.
fn detect_padded(loc: &mut dyn Localizer, image: &Mat, pad: i32) -> anyhow::Result<TieredDetections> {
    if pad <= 0 {
        return Ok(loc.detect_tiered(image)?);
    }
    let mut padded = Mat::default();
    opencv::core::copy_make_border(
        image,
        &mut padded,
        pad,
        pad,
        pad,
        pad,
        opencv::core::BORDER_REFLECT,
        Scalar::all(0.0),
    )
    .context("padding the image border")?;
    let (w, h) = (f64::from(image.cols()), f64::from(image.rows()));
    let p = f64::from(pad);
    let unpad = |found: Vec<Detection>| -> Vec<Detection> {
        found
            .into_iter()
            .map(|mut d| {
                d.position = Point2::new(d.position.x - p, d.position.y - p);
                d
            })
            // Keep markers whose centre lies within half a pad of the image.
            .filter(|d| {
                d.position.x > -0.5 * p
                    && d.position.y > -0.5 * p
                    && d.position.x < w - 1.0 + 0.5 * p
                    && d.position.y < h - 1.0 + 0.5 * p
            })
            .collect()
    };
    let found = loc.detect_tiered(&padded)?;
    Ok(TieredDetections {
        accepted: unpad(found.accepted),
        second_tier: unpad(found.second_tier),
    })
}

/// Warnings printed one by one; the rest are counted.
const MAX_WARNINGS: usize = 10;

/// Output files, written as frames arrive.
struct Outputs {
    dir: PathBuf,
    markers: std::io::BufWriter<std::fs::File>,
    frames: std::io::BufWriter<std::fs::File>,
    history: Vec<FrameSummary>,
    line: String,
    /// Per overlay frame, the heat-map values over the lattice (NaN unknown), drawn when the
    /// recording ends so that every heat map shares one colour scale.
    heat: Vec<(u32, Vec<f32>)>,
    /// The frame of the largest indentation depth so far (stereo) and its marker surface.
    deepest: Option<(u32, f64, figures::Surface)>,
}

impl Outputs {
    fn create(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        let open = |name: &str| -> anyhow::Result<std::io::BufWriter<std::fs::File>> {
            let p = dir.join(name);
            Ok(std::io::BufWriter::new(
                std::fs::File::create(&p).with_context(|| format!("cannot create {}", p.display()))?,
            ))
        };
        let mut out = Self {
            dir: dir.to_path_buf(),
            markers: open("markers.csv")?,
            frames: open("frames.csv")?,
            history: Vec::new(),
            line: String::new(),
            heat: Vec::new(),
            deepest: None,
        };
        writeln!(out.markers, "{}", MARKER_COLUMNS.join(","))?;
        writeln!(out.frames, "{}", FRAME_COLUMNS.join(","))?;
        Ok(out)
    }

    fn rows(&mut self, markers: &[MarkerRecord], summary: &FrameSummary) -> anyhow::Result<()> {
        self.line.clear();
        for m in markers {
            m.write_csv(&mut self.line);
            self.line.push('\n');
        }
        self.markers
            .write_all(self.line.as_bytes())
            .context("cannot write markers.csv")?;
        self.line.clear();
        summary.write_csv(&mut self.line);
        self.line.push('\n');
        self.frames
            .write_all(self.line.as_bytes())
            .context("cannot write frames.csv")?;
        self.history.push(summary.clone());
        Ok(())
    }

    fn finish(mut self, stereo: bool, shape: GridShape) -> anyhow::Result<Vec<FrameSummary>> {
        self.markers.flush().context("cannot write markers.csv")?;
        self.frames.flush().context("cannot write frames.csv")?;
        let h = &self.history;
        let frames: Vec<u32> = h.iter().map(|f| f.frame).collect();
        let timeline = Timeline::new(&frames, None);
        let plots = self.dir.join("plots");
        let area = TimeSeries {
            title: "contact area".into(),
            y_label: "contact area (mm²)".into(),
            timeline: timeline.clone(),
            curves: vec![Curve {
                name: "contact area".into(),
                values: h.iter().map(|f| f.contact_area_mm2).collect(),
            }],
            y_resolution: 0.1,
            unknown_note: "the marker pitch is not given (--pitch-mm)".into(),
        };
        let depth = TimeSeries {
            title: "largest indentation depth".into(),
            y_label: "depth (mm)".into(),
            curves: vec![Curve {
                name: "largest depth".into(),
                values: h.iter().map(|f| f.max_depth_mm).collect(),
            }],
            y_resolution: 0.01,
            unknown_note: "one camera measures no depth".into(),
            ..area.clone()
        };
        let slip: Vec<SlipState> = h.iter().map(|f| f.slip).collect();
        for ext in ["png", "svg"] {
            figures::time_series(&plots.join(format!("contact_area.{ext}")), &area)?;
            if stereo {
                figures::time_series(&plots.join(format!("max_depth.{ext}")), &depth)?;
            }
            figures::slip_timeline(&plots.join(format!("slip.{ext}")), "slip state", &timeline, &slip)?;
        }
        self.write_heat_maps(stereo, shape)?;
        Ok(self.history)
    }

    /// Keeps `contact`'s marker surface when its frame is the deepest so far.
    fn keep_if_deepest(
        &mut self,
        frame: u32,
        depth_mm: Option<f64>,
        shape: GridShape,
        contact: &ContactFrame,
    ) {
        let Some(depth) = depth_mm.filter(|d| d.is_finite()) else {
            return;
        };
        if self.deepest.as_ref().is_some_and(|(_, d, _)| *d >= depth) {
            return;
        }
        let surface = figures::Surface {
            rows: usize::from(shape.rows),
            cols: usize::from(shape.cols),
            positions_mm: contact
                .positions_mm
                .iter()
                .map(|p| p.map(|p| [p.x, p.y, p.z]))
                .collect(),
            depth_mm: contact.depth_mm.clone(),
        };
        self.deepest = Some((frame, depth, surface));
    }

    /// The heat maps of the overlay frames on one colour scale (0 .. the recording's largest value):
    /// indentation depth for stereo, displacement magnitude in the image for mono.
    fn write_heat_maps(&self, stereo: bool, shape: GridShape) -> anyhow::Result<()> {
        let (label, name, resolution) = if stereo {
            ("indentation depth (mm)", "depth", 0.01)
        } else {
            ("displacement (px)", "displacement", 0.5)
        };
        let deepest = self
            .deepest
            .iter()
            .flat_map(|(_, _, s)| s.depth_mm.iter().flatten().copied());
        let scale = ColourScale::covering(
            label,
            self.heat
                .iter()
                .flat_map(|(_, v)| v.iter().map(|x| f64::from(*x)))
                .chain(deepest),
            resolution,
        );
        if let Some((frame, _, surface)) = &self.deepest {
            for ext in ["png", "svg"] {
                let path = self.dir.join("plots").join(format!("contact_surface.{ext}"));
                figures::surface(
                    &path,
                    &format!("contact surface, frame {frame} (deepest)"),
                    surface,
                    &scale,
                )?;
            }
        }
        for (frame, values) in &self.heat {
            let lattice: Vec<Option<f64>> = values
                .iter()
                .map(|v| v.is_finite().then_some(f64::from(*v)))
                .collect();
            let Some(dense) = interpolate(shape, &lattice, 8) else {
                continue;
            };
            let field = figures::Field {
                width: dense.width,
                height: dense.height,
                values: dense.values,
                x_extent: (0.0, f64::from(shape.cols.saturating_sub(1))),
                y_extent: (0.0, f64::from(shape.rows.saturating_sub(1))),
                axis_labels: ("marker column".into(), "marker row".into()),
            };
            let path = self.dir.join("overlays").join(format!("{name}_{frame:06}.png"));
            figures::heatmap(&path, &format!("frame {frame}: {name}"), &field, &scale)?;
        }
        Ok(())
    }
}

/// Writes the marker cloud and the deformed mesh of a stereo frame.
fn write_ply(
    dir: &Path,
    frame: u32,
    session: &StereoSession,
    contact: &ContactFrame,
    reprojection: &[Option<f64>],
) -> anyhow::Result<()> {
    let shape = session.shape();
    let cloud: Vec<MarkerPoint> = shape
        .indices()
        .enumerate()
        .filter_map(|(k, index)| {
            let p = contact.positions_mm[k]?;
            Some(MarkerPoint {
                index,
                position_mm: [p.x, p.y, p.z],
                reprojection_error_px: reprojection[k].unwrap_or(0.0),
            })
        })
        .collect();
    let comment = format!("frame {frame}; reprojection_error 0 for markers predicted from their neighbours");
    write_marker_cloud(&dir.join(format!("cloud_{frame:06}.ply")), &cloud, &comment)?;
    let mut vertex_of = vec![u32::MAX; shape.count()];
    let mut mesh = TriangleMesh::default();
    let names = [
        "depth_mm",
        "displacement_mm",
        "dX_mm",
        "dY_mm",
        "dZ_mm",
        "load_mm",
        "in_contact",
    ];
    let mut props: Vec<Vec<f32>> = vec![Vec::new(); names.len()];
    for (k, p) in contact.positions_mm.iter().enumerate() {
        let Some(p) = p else { continue };
        vertex_of[k] = mesh.vertices_mm.len() as u32;
        mesh.vertices_mm.push([p.x, p.y, p.z]);
        let d = contact.displacement_mm[k].unwrap_or_default();
        let vals = [
            contact.depth_mm[k].unwrap_or(0.0),
            d.norm(),
            d.x,
            d.y,
            d.z,
            contact.load_mm.get(k).copied().unwrap_or(0.0),
            f64::from(u8::from(contact.in_contact[k])),
        ];
        for (v, list) in vals.iter().zip(props.iter_mut()) {
            list.push(*v as f32);
        }
    }
    for t in session.surface().triangles() {
        let f = t.map(|i| vertex_of[i as usize]);
        if f.iter().all(|v| *v != u32::MAX) {
            mesh.faces.push(f);
        }
    }
    mesh.properties = names
        .iter()
        .zip(props)
        .map(|(n, values)| VertexProperty {
            name: (*n).to_owned(),
            values,
        })
        .collect();
    write_mesh(
        &dir.join(format!("mesh_{frame:06}.ply")),
        &mesh,
        &format!("frame {frame}; deformed marker surface"),
    )?;
    Ok(())
}

/// The markers of one view for an overlay: reference position, current position, status, contact.
fn overlay_markers(
    reference: &[Point2],
    track: &TrackFrame,
    in_contact: &dyn Fn(usize) -> bool,
) -> Vec<OverlayMarker> {
    track
        .markers
        .iter()
        .enumerate()
        .filter_map(|(k, m)| {
            Some(OverlayMarker {
                reference_px: *reference.get(k)?,
                current_px: m.position_px?,
                status: m.status,
                in_contact: in_contact(k),
            })
        })
        .collect()
}

enum Session {
    Stereo(Box<StereoSession>),
    Mono(Box<MonoSession>),
}

impl Session {
    fn ids(&self) -> &[GridIndex] {
        match self {
            Session::Stereo(s) => s.ids(),
            Session::Mono(s) => s.tracker().ids(),
        }
    }

    fn shape(&self) -> GridShape {
        match self {
            Session::Stereo(s) => s.shape(),
            Session::Mono(s) => s.tracker().shape(),
        }
    }

    fn stereo(
        rig: &StereoRig,
        lat: &StereoLattice,
        shape: GridShape,
        config: &SessionConfig,
    ) -> anyhow::Result<Self> {
        let l: Vec<(GridIndex, Point2)> = lat.left().reference_view().markers().collect();
        let r: Vec<(GridIndex, Point2)> = lat.right().reference_view().markers().collect();
        let tri = Triangulator::new(rig.clone(), TriangulationConfig::default())?;
        let mut session = StereoSession::new(shape, &l, &r, tri, config.clone())?;
        // The two views' tracker updates and the triangulation on both cores (one frame at a time).
        session.set_parallel(true);
        Ok(Session::Stereo(Box::new(session)))
    }

    fn mono(lat: &ReferenceLattice, shape: GridShape, config: &SessionConfig) -> anyhow::Result<Self> {
        let l: Vec<(GridIndex, Point2)> = lat.reference_view().markers().collect();
        Ok(Session::Mono(Box::new(MonoSession::new(
            shape,
            &l,
            config.clone(),
        )?)))
    }
}

/// The rest positions of a sensor description's markers in both views (row-major; `None` where a
/// marker does not project), with the calibrated rig; and whether every one falls inside the image.
fn expected_lattice(spec: &SensorSpec, rig: &StereoRig) -> anyhow::Result<ExpectedLattice> {
    let sensor = spec.build().context("the sensor description")?;
    let size = rig.left.image_size;
    let inside = |q: &Point2| {
        q.x >= 0.0 && q.y >= 0.0 && q.x <= f64::from(size.width) - 1.0 && q.y <= f64::from(size.height) - 1.0
    };
    let (mut left, mut right) = (Vec::new(), Vec::new());
    for i in spec.grid_shape().indices() {
        let [x, y] = spec.marker_rest_mm(i.row, i.col);
        let p = rig.project(&(sensor.left_from_sensor * nalgebra::Point3::new(x, y, 0.0)));
        left.push(p.map(|p| p.0));
        right.push(p.map(|p| p.1));
    }
    let overfills = left.iter().chain(&right).any(|q| !q.as_ref().is_some_and(inside));
    Ok(ExpectedLattice {
        left,
        right,
        overfills,
    })
}

struct ExpectedLattice {
    left: Vec<Option<Point2>>,
    right: Vec<Option<Point2>>,
    /// Some marker falls outside a view at rest.
    overfills: bool,
}

/// Whether the reference failed because the view does not show the whole lattice.
fn lattice_cut(e: &anyhow::Error) -> bool {
    matches!(
        e.downcast_ref::<MatchError>(),
        Some(MatchError::IncompleteGrid { .. } | MatchError::StereoAlignment { .. })
    )
}

/// Whether the left view's markers come within a pitch of the image border (on a side where the
/// lattice could be cut off) in a direction where fewer rows / columns than `full`'s are visible.
fn touches_border(dets: &[Detection], visible: GridShape, full: GridShape, size: ImageSize) -> bool {
    let pts: Vec<Point2> = dets.iter().map(|d| d.position).collect();
    let mut nn: Vec<f64> = pts
        .iter()
        .enumerate()
        .filter_map(|(i, p)| {
            pts.iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, q)| p.distance(*q))
                .min_by(f64::total_cmp)
        })
        .collect();
    nn.sort_by(f64::total_cmp);
    let Some(&pitch) = nn.get(nn.len() / 2) else {
        return false;
    };
    let (w, h) = (f64::from(size.width) - 1.0, f64::from(size.height) - 1.0);
    let near = |f: &dyn Fn(&Point2) -> bool| pts.iter().any(f);
    (visible.cols < full.cols && near(&|p| p.x < pitch || p.x > w - pitch))
        || (visible.rows < full.rows && near(&|p| p.y < pitch || p.y > h - pitch))
}

/// Starts a session on a reference frame whose view shows only part of the `full` lattice: on the
/// sensor's own grid indices when a sensor description places it, else from the visible top-left
/// marker (with a warning; `pitch_mm`, the marker pitch, can settle the right view's column
/// offset). Returns the session and the lines to log; `None` when the view does not look cut off
/// (no description, and no fewer rows or columns than the grid's near the image border).
fn start_cut(
    dets: &StereoPair<TieredDetections>,
    rig: Option<&StereoRig>,
    full: GridShape,
    expected: Option<&ExpectedLattice>,
    pitch_mm: Option<f64>,
    size: ImageSize,
    config: &SessionConfig,
) -> anyhow::Result<Option<(Session, Vec<String>)>> {
    let (left, right) = (&dets.left.accepted, &dets.right.accepted);
    if let Some(x) = expected {
        let (session, line) = match rig {
            Some(rig) => {
                let (lat, p) = StereoLattice::from_reference_placed(
                    rig,
                    left,
                    right,
                    full,
                    (&x.left, &x.right),
                    StereoConfig::default(),
                )?;
                let line = format!(
                    "the {}x{} grid overfills the view: placed by the sensor description; left view {}, right view {}; \
                     {} of {} markers seen in both views pair within {} px of the epipolar lines",
                    full.rows,
                    full.cols,
                    p.left,
                    p.right,
                    p.within_epipolar,
                    p.paired,
                    StereoConfig::default().max_epipolar_px
                );
                (Session::stereo(rig, &lat, full, config)?, line)
            }
            None => {
                let (lat, p) =
                    ReferenceLattice::from_detections_placed(left, full, &x.left, IndexingConfig::default())?;
                let line = format!(
                    "the {}x{} grid overfills the view: placed by the sensor description on {p}",
                    full.rows, full.cols
                );
                (Session::mono(&lat, full, config)?, line)
            }
        };
        return Ok(Some((session, vec![line])));
    }
    let visible = ReferenceLattice::visible_shape(left, full, &IndexingConfig::default())?;
    if !touches_border(left, visible, full, size) {
        return Ok(None);
    }
    let session = match rig {
        Some(rig) => {
            let lat = StereoLattice::from_visible_reference(
                rig,
                left,
                right,
                visible,
                full,
                pitch_mm,
                StereoConfig::default(),
            )
            .context("give the sensor description (--sensor FILE) to place the grid, or the marker pitch (--pitch-mm)")?;
            Session::stereo(rig, &lat, visible, config)?
        }
        None => Session::mono(
            &ReferenceLattice::from_detections(left, visible, IndexingConfig::default())?,
            visible,
            config,
        )?,
    };
    let line = format!(
        "warning: the {}x{} grid overfills the view and no sensor description places it: indexing the visible \
         {}x{} markers with the visible top-left marker as (0, 0); ids are not the sensor's grid indices",
        full.rows, full.cols, visible.rows, visible.cols
    );
    Ok(Some((session, vec![line])))
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    if args.bench {
        return bench(args);
    }
    let Some(out_dir) = &args.out else {
        bail!("--out DIR is required (where markers.csv, frames.csv, ply/, overlays/ and plots/ go)")
    };
    let mut source = open_source(args)?;
    let stereo = source.is_stereo();
    let (meta_grid, meta_thickness) = meta(args.input.as_deref());
    let mut shape = match &args.grid {
        Some(g) => parse_grid(g)?,
        None => meta_grid.unwrap_or(GridShape::REFERENCE),
    };
    let calib = match (&args.calib, &args.input) {
        (Some(c), _) => Some(c.clone()),
        (None, Some(dir)) if dir.join("calib.yaml").is_file() => {
            Some(dir.join("calib.yaml").display().to_string())
        }
        _ => None,
    };
    let rig = if stereo {
        let Some(spec) = &calib else {
            bail!("stereo input needs --calib FILE (or a calib.yaml in the recording)")
        };
        Some(StereoRig::load(spec).with_context(|| format!("cannot load the calibration {spec}"))?)
    } else {
        None
    };
    // The sensor description's lattice is projected through the calibration (a mono run of a
    // stereo recording uses its left camera); only a grid that overfills the view needs it.
    let expected = match sensor_spec(args)? {
        Some(spec) if spec.grid_shape() == shape => {
            let projection = match &rig {
                Some(r) => Some(r.clone()),
                None => calib.as_deref().and_then(|c| StereoRig::load(c).ok()),
            };
            match projection.map(|r| expected_lattice(&spec, &r)).transpose() {
                Ok(x) => x,
                Err(e) if args.sensor.is_some() => return Err(e),
                // A recording's own description that does not build leaves the grid unplaced.
                Err(_) => None,
            }
        }
        _ => None,
    };
    let mut config = SessionConfig::default();
    if let Some(t) = args.gel_thickness_mm.or(meta_thickness) {
        config.contact.gel_thickness_mm = t;
    }
    config.planar.pitch_mm = args.pitch_mm;
    let method = choose_method(args);
    let mut localizer = args.localizer.localizer(method)?;
    // One frame at a time: the two views' stages in parallel where a core is free (same results).
    crate::cmd_bench::join_rayon_pool();
    localizer.set_parallel(true);
    let truth = if args.from_ground_truth {
        let Some(dir) = args.input.as_deref().filter(|p| p.join("markers.csv").is_file()) else {
            bail!("--from-ground-truth needs a simulated recording with a markers.csv");
        };
        Some(ground_truth(dir, args.gt_noise_px)?)
    } else {
        None
    };
    let outputs = Outputs::create(out_dir)?;
    let ply_dir = out_dir.join("ply");
    let overlay_dir = out_dir.join("overlays");
    if !args.no_ply && stereo {
        std::fs::create_dir_all(&ply_dir).with_context(|| format!("cannot create {}", ply_dir.display()))?;
    }
    let progress = if args.quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(source.len_hint().unwrap_or(0) as u64)
    };
    progress.set_style(
        ProgressStyle::with_template("{spinner} track [{bar:30}] {pos}/{len} frames {per_sec} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut outputs = outputs;
    let mut session: Option<Session> = None;
    let mut reference_size: Option<ImageSize> = None;
    let mut pending_flagged: Vec<(u32, String)> = Vec::new();
    let mut warnings: Vec<String> = Vec::new();
    let mut latest_contact: Option<ContactFrame> = None;
    let started = Instant::now();
    let mut k = 0usize;
    let (mut tracked_total, mut visible_total) = (0usize, 0usize);
    while args.max_frames.is_none_or(|m| k < m) {
        let Some(next) = source.next(k) else { break };
        let frame_no = k as u32;
        k += 1;
        progress.inc(1);
        // Read and localize; any failure flags the frame.
        let detected: anyhow::Result<(Frame, StereoPair<TieredDetections>)> = (|| {
            let frame = next?;
            match &frame {
                Frame::Stereo(pair) => {
                    let size = size_of(&pair.left);
                    if size_of(&pair.right) != size {
                        bail!(
                            "left and right images differ in size ({}x{} vs {}x{})",
                            size.width,
                            size.height,
                            pair.right.cols(),
                            pair.right.rows()
                        );
                    }
                    if let Some(r) = &rig {
                        r.check_image_sizes(size, size)
                            .context("the frame does not match the calibration")?;
                    }
                    check_size(&mut reference_size, size)?;
                    let d = match &truth {
                        Some(t) => t
                            .get(frame_no as usize)
                            .map(|p| StereoPair::new(p.left.clone().into(), p.right.clone().into()))
                            .with_context(|| format!("no ground truth for frame {frame_no}"))?,
                        None => localizer.detect_stereo_tiered(pair)?,
                    };
                    Ok((frame, d))
                }
                Frame::Mono(m) => {
                    check_size(&mut reference_size, size_of(m))?;
                    let d = match &truth {
                        Some(t) => t
                            .get(frame_no as usize)
                            .map(|p| p.left.clone().into())
                            .with_context(|| format!("no ground truth for frame {frame_no}"))?,
                        None => detect_padded(localizer.as_mut(), m, args.pad_border)?,
                    };
                    Ok((frame, StereoPair::new(d, TieredDetections::default())))
                }
            }
        })();
        let (frame, dets) = match detected {
            Ok(x) => x,
            Err(e) => {
                let msg = format!("frame {frame_no}: {e:#}");
                if warnings.len() < MAX_WARNINGS {
                    progress.suspend(|| eprintln!("warning: {msg}; frame written as lost / no contact"));
                }
                match &session {
                    Some(s) => {
                        let (m, f) = flagged_rows(s.ids(), frame_no);
                        outputs.rows(&m, &f)?;
                    }
                    None => pending_flagged.push((frame_no, msg.clone())),
                }
                warnings.push(msg);
                continue;
            }
        };
        if session.is_none() {
            // The first good frame is the reference (no contact): index it.
            let started = match (&frame, &rig) {
                (Frame::Stereo(_), Some(rig)) => StereoLattice::from_reference(
                    rig,
                    &dets.left.accepted,
                    &dets.right.accepted,
                    shape,
                    StereoConfig::default(),
                )
                .map_err(anyhow::Error::from)
                .and_then(|lat| Session::stereo(rig, &lat, shape, &config)),
                _ => ReferenceLattice::from_detections(&dets.left.accepted, shape, IndexingConfig::default())
                    .map_err(anyhow::Error::from)
                    .and_then(|lat| Session::mono(&lat, shape, &config)),
            };
            // A grid that overfills the view: only then the visible part is indexed (a lattice that
            // fits keeps the whole-lattice indexing, and a frame that misses a row the next frame).
            let started = match started {
                Ok(s) => Ok((s, Vec::new())),
                Err(e) if lattice_cut(&e) && expected.as_ref().is_none_or(|x| x.overfills) => {
                    let size = reference_size.unwrap_or(ImageSize { width: 0, height: 0 });
                    let stereo_rig = matches!(frame, Frame::Stereo(_))
                        .then_some(rig.as_ref())
                        .flatten();
                    match start_cut(
                        &dets,
                        stereo_rig,
                        shape,
                        expected.as_ref(),
                        args.pitch_mm,
                        size,
                        &config,
                    ) {
                        Ok(Some(started)) => Ok(started),
                        // Not a cut grid: the whole-lattice error stands (the next frame is tried).
                        Ok(None) => Err(e),
                        Err(cut) => Err(cut.context(format!("{e:#}; indexing the visible part"))),
                    }
                }
                Err(e) => Err(e),
            };
            match started {
                Ok((s, notes)) => {
                    for note in notes {
                        progress.suspend(|| eprintln!("reference frame {frame_no}: {note}"));
                    }
                    shape = s.shape();
                    for (f, _) in pending_flagged.drain(..) {
                        let (m, fs) = flagged_rows(s.ids(), f);
                        outputs.rows(&m, &fs)?;
                    }
                    progress.suspend(|| {
                        eprintln!(
                            "reference frame {frame_no}: {} markers indexed on the {}x{} lattice ({method})",
                            s.ids().len(),
                            shape.rows,
                            shape.cols
                        )
                    });
                    session = Some(s);
                }
                Err(e) => {
                    let msg = format!("frame {frame_no}: cannot index the reference lattice: {e:#}");
                    if warnings.len() < MAX_WARNINGS {
                        progress.suspend(|| eprintln!("warning: {msg}; trying the next frame"));
                    }
                    pending_flagged.push((frame_no, msg.clone()));
                    warnings.push(msg);
                    continue;
                }
            }
        }
        let Some(s) = session.as_mut() else { continue };
        if args.rezero_at.contains(&frame_no) {
            match s {
                Session::Stereo(st) => {
                    if let Some(c) = &latest_contact {
                        st.rezero(c)?;
                    }
                }
                Session::Mono(m) => m.rezero(),
            }
            progress.suspend(|| eprintln!("frame {frame_no}: reference re-zeroed"));
        }
        let write_overlay = args.overlay_every > 0 && (frame_no as usize).is_multiple_of(args.overlay_every);
        match (s, &frame) {
            (Session::Stereo(st), Frame::Stereo(pair)) => {
                let reference: Vec<Point2> = st.left().reference_px().to_vec();
                let reference_right: Vec<Point2> = st.right().reference_px().to_vec();
                let out = st.track_tiered(frame_no, &dets.left, &dets.right)?;
                outputs.rows(&out.markers, &out.summary)?;
                tracked_total += out.left.count(MarkerStatus::Tracked);
                visible_total += out.left.markers.len();
                if !args.no_ply {
                    write_ply(&ply_dir, frame_no, st, &out.contact, &out.reprojection_px)?;
                }
                if write_overlay {
                    let in_contact = |ids: &[GridIndex], k: usize| {
                        ids.get(k)
                            .and_then(|i| shape.linear(*i))
                            .and_then(|l| out.contact.in_contact.get(l).copied())
                            .unwrap_or(false)
                    };
                    let views = [
                        OverlayView {
                            name: "left",
                            image: &pair.left,
                            markers: overlay_markers(&reference, &out.left, &|k| {
                                in_contact(st.left().ids(), k)
                            }),
                        },
                        OverlayView {
                            name: "right",
                            image: &pair.right,
                            markers: overlay_markers(&reference_right, &out.right, &|k| {
                                in_contact(st.right().ids(), k)
                            }),
                        },
                    ];
                    figures::overlay(
                        &overlay_dir.join(format!("{frame_no:06}.png")),
                        &views,
                        args.arrow_scale,
                        &caption(&out.summary),
                    )?;
                    let depth = out
                        .contact
                        .depth_mm
                        .iter()
                        .map(|d| d.map_or(f32::NAN, |d| d as f32));
                    outputs.heat.push((frame_no, depth.collect()));
                }
                outputs.keep_if_deepest(frame_no, out.summary.max_depth_mm, shape, &out.contact);
                latest_contact = Some(out.contact);
            }
            (Session::Mono(m), Frame::Mono(img)) => {
                let reference: Vec<Point2> = m.tracker().reference_px().to_vec();
                let out = m.track_tiered(frame_no, &dets.left)?;
                outputs.rows(&out.markers, &out.summary)?;
                tracked_total += out.track.count(MarkerStatus::Tracked);
                visible_total += out.track.markers.len();
                if write_overlay {
                    let in_contact = |k: usize| out.planar.in_contact.get(k).copied().unwrap_or(false);
                    let view = OverlayView {
                        name: "camera",
                        image: img,
                        markers: overlay_markers(&reference, &out.track, &in_contact),
                    };
                    figures::overlay(
                        &overlay_dir.join(format!("{frame_no:06}.png")),
                        &[view],
                        args.arrow_scale,
                        &caption(&out.summary),
                    )?;
                    // Displacement magnitude on the lattice, px.
                    let mut mags = vec![f32::NAN; shape.count()];
                    for (k, mk) in out.track.markers.iter().enumerate() {
                        if let (Some(p), Some(r), Some(l)) =
                            (mk.position_px, reference.get(k), shape.linear(mk.index))
                        {
                            mags[l] = p.distance(*r) as f32;
                        }
                    }
                    outputs.heat.push((frame_no, mags));
                }
            }
            _ => bail!("frame {frame_no}: a mono frame in a stereo session or the reverse"),
        }
    }
    progress.finish_and_clear();
    if warnings.len() > MAX_WARNINGS {
        eprintln!(
            "warning: {} more warnings of the same kind not shown",
            warnings.len() - MAX_WARNINGS
        );
    }
    if session.is_none() {
        bail!(
            "no frame could be indexed as the reference lattice ({} frames read): {}",
            k,
            warnings.last().map_or("no frames", String::as_str)
        );
    }
    let history = outputs.finish(stereo, shape)?;
    let secs = started.elapsed().as_secs_f64();
    let contact = history.iter().filter(|f| f.contact).count();
    let slip = history
        .iter()
        .filter(|f| matches!(f.slip, SlipState::PartialSlip | SlipState::GrossSlip))
        .count();
    eprintln!(
        "{} frames in {secs:.1} s ({:.1} frames/s): {:.2} % of marker-frames tracked in the left view, {contact} frames in contact, {slip} slipping, {} flagged; outputs in {}",
        history.len(),
        history.len() as f64 / secs.max(1e-9),
        100.0 * tracked_total as f64 / visible_total.max(1) as f64,
        warnings.len(),
        out_dir.display()
    );
    Ok(())
}

/// Per frame, the ground-truth positions of the markers visible in each view (with Gaussian noise of
/// `noise_px`, seeded, when > 0), in a shuffled-free but id-free form: sorted by y then x like a
/// localizer's output.
fn ground_truth(dir: &Path, noise_px: f64) -> anyhow::Result<Vec<StereoPair<Vec<Detection>>>> {
    let truth = GroundTruth::read(dir)?;
    let frames = truth.frames.keys().next_back().map_or(0, |f| *f as usize + 1);
    let mut out: Vec<StereoPair<Vec<Detection>>> = vec![StereoPair::default(); frames];
    // xorshift + Box-Muller: reproducible noise without another dependency.
    let mut state: u64 = 0x2545_F491_4F6C_DD1D;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let mut gauss = move || (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos();
    // Frames, then markers row-major: the order of the simulator's markers.csv, so the noise is drawn
    // in the same sequence for every run.
    for (frame, markers) in &truth.frames {
        let pair = &mut out[*frame as usize];
        for m in markers.values() {
            for (px, list) in [(m.left_px, &mut pair.left), (m.right_px, &mut pair.right)] {
                if let Some(p) = px {
                    list.push(Detection {
                        position: Point2::new(p.x + noise_px * gauss(), p.y + noise_px * gauss()),
                        confidence: 1.0,
                    });
                }
            }
        }
    }
    for pair in &mut out {
        gelstereo_markers::sort_detections(&mut pair.left);
        gelstereo_markers::sort_detections(&mut pair.right);
    }
    Ok(out)
}

/// The overlay caption's items: frame, slip state, contact area and depth ("unknown" where the
/// sensor cannot tell).
fn caption(s: &FrameSummary) -> Vec<String> {
    let known = |v: Option<f64>, decimals: usize, unit: &str| {
        v.map_or_else(|| "unknown".to_owned(), |v| format!("{v:.decimals$} {unit}"))
    };
    vec![
        format!("frame {}", s.frame),
        s.slip.as_str().replace('_', " "),
        format!("area {}", known(s.contact_area_mm2, 1, "mm²")),
        format!("depth {}", known(s.max_depth_mm, 2, "mm")),
    ]
}

fn check_size(reference: &mut Option<ImageSize>, size: ImageSize) -> anyhow::Result<()> {
    match reference {
        Some(r) if *r != size => bail!(
            "image size {}x{} differs from the first frame's {}x{}",
            size.width,
            size.height,
            r.width,
            r.height
        ),
        Some(_) => Ok(()),
        None => {
            *reference = Some(size);
            Ok(())
        }
    }
}

/// `gelstereo track --bench`: an alias of the pipeline benchmark, `gelstereo bench --calib FILE
/// RECORDING` (one implementation, [`crate::cmd_bench::run_pipeline`]).
fn bench(args: &Args) -> anyhow::Result<()> {
    let Some(input) = &args.input else {
        bail!("--bench needs a stereo RECORDING")
    };
    crate::cmd_bench::run_pipeline(&crate::cmd_bench::PipelineBench {
        recording: input,
        calib: args.calib.as_deref(),
        method: choose_method(args),
        grid: args.grid.as_deref(),
        gel_thickness_mm: args.gel_thickness_mm,
        frames: 0,
        runs: args.bench_frames,
        warmup: 20,
        workers: 0,
        localizer: &args.localizer,
        json: None,
    })
}
