//! `gelstereo track`: the whole pipeline over a recording: localization in each view, grid indexing
//! of the reference frame, tracking, triangulation, displacement, contact geometry and slip. Writes
//! `OUT/markers.csv` and `OUT/frames.csv` (DESIGN.md contracts), per-frame PLY clouds and meshes
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
use gelstereo_io::images::{self, StereoRecording};
use gelstereo_io::plot::{self, LinePlot};
use gelstereo_io::ply::{MarkerPoint, TriangleMesh, VertexProperty, write_marker_cloud, write_mesh};
use gelstereo_io::video::{self, VideoFrames};
use gelstereo_markers::{Localizer, Method};
use gelstereo_matching::eval::GroundTruth;
use gelstereo_matching::{
    Error as MatchError, IndexingConfig, ReferenceLattice, StereoConfig, StereoLattice,
};
use gelstereo_sim::SensorSpec;
use gelstereo_tracking::{
    ContactFrame, DenseField, MonoSession, SessionConfig, StereoSession, TrackFrame, flagged_rows,
    interpolate,
};
use indicatif::{ProgressBar, ProgressStyle};
use opencv::core::{Mat, MatTraitConst, Point, Scalar};
use opencv::imgproc;

use crate::cmd_detect::LocalizerArgs;

/// Arguments of `gelstereo track`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Stereo calibration (OpenCV YAML/XML, or a folder / pair of mrcal .cameramodel files); default:
    /// the recording's calib.yaml. Needed for stereo input, ignored for mono.
    #[arg(long, value_name = "FILE")]
    calib: Option<String>,
    /// Output folder (created): markers.csv, frames.csv, ply/, overlays/, plots/.
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Localization method: blob, marknet or marknet-mre (default: marknet-mre when its models are
    /// installed, else blob).
    #[arg(long)]
    method: Option<Method>,
    /// Marker lattice ROWSxCOLS (default: the recording's meta.json, else 23x23).
    #[arg(long, value_name = "ROWSxCOLS")]
    grid: Option<String>,
    /// Read frames from camera N (live) instead of a recording.
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
    /// Re-zero the reference at these frames (comma separated): drift correction.
    #[arg(long, value_delimiter = ',', value_name = "FRAME")]
    rezero_at: Vec<u32>,
    /// Stop after this many frames.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Write an overlay PNG every N frames (0: none).
    #[arg(long, default_value_t = 1, value_name = "N")]
    overlay_every: usize,
    /// Length factor of the displacement arrows in the overlays.
    #[arg(long, default_value_t = 3.0)]
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
    #[arg(long, default_value_t = 200)]
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

    fn finish(mut self, stereo: bool) -> anyhow::Result<Vec<FrameSummary>> {
        self.markers.flush().context("cannot write markers.csv")?;
        self.frames.flush().context("cannot write frames.csv")?;
        let h = &self.history;
        let x = |f: &FrameSummary| f64::from(f.frame);
        let area: Vec<(f64, f64)> = h.iter().map(|f| (x(f), f.contact_area_mm2)).collect();
        plot::write(
            &self.dir.join("plots/contact_area.png"),
            &LinePlot::new("contact area", "frame", "mm^2").with_series("contact area", [200, 80, 0], area),
        )?;
        if stereo {
            let depth: Vec<(f64, f64)> = h.iter().map(|f| (x(f), f.max_depth_mm)).collect();
            plot::write(
                &self.dir.join("plots/max_depth.png"),
                &LinePlot::new("largest indentation depth", "frame", "mm").with_series(
                    "max depth",
                    [0, 120, 220],
                    depth,
                ),
            )?;
        }
        let slip: Vec<(f64, f64)> = h.iter().map(|f| (x(f), f64::from(slip_level(f.slip)))).collect();
        let cats = [
            SlipState::NoContact,
            SlipState::Stick,
            SlipState::PartialSlip,
            SlipState::GrossSlip,
        ]
        .map(|s| s.as_str().to_owned())
        .to_vec();
        plot::write(
            &self.dir.join("plots/slip.png"),
            &LinePlot {
                categories: cats,
                ..LinePlot::new("slip state", "frame", "")
            }
            .with_series("slip", [40, 40, 200], slip),
        )?;
        Ok(self.history)
    }
}

fn slip_level(s: SlipState) -> u8 {
    match s {
        SlipState::NoContact => 0,
        SlipState::Stick => 1,
        SlipState::PartialSlip => 2,
        SlipState::GrossSlip => 3,
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

/// Draws displacement arrows (reference -> current, scaled) and the contact markers onto `image`.
fn overlay(
    image: &Mat,
    reference: &[Point2],
    track: &TrackFrame,
    in_contact: &dyn Fn(usize) -> bool,
    scale: f64,
    caption: &str,
) -> anyhow::Result<Mat> {
    let mut out = Mat::default();
    if image.channels() == 1 {
        imgproc::cvt_color(image, &mut out, imgproc::COLOR_GRAY2BGR, 0)?;
    } else {
        out = image.try_clone()?;
    }
    let pt = |p: Point2| Point::new(p.x.round() as i32, p.y.round() as i32);
    for (k, m) in track.markers.iter().enumerate() {
        let Some(p) = m.position_px else { continue };
        let r = reference[k];
        let tip = Point2::new(r.x + scale * (p.x - r.x), r.y + scale * (p.y - r.y));
        let color = match m.status {
            MarkerStatus::Tracked => Scalar::new(0.0, 200.0, 0.0, 0.0),
            MarkerStatus::Predicted => Scalar::new(0.0, 160.0, 255.0, 0.0),
            MarkerStatus::Lost => Scalar::new(0.0, 0.0, 255.0, 0.0),
        };
        if in_contact(k) {
            imgproc::circle(
                &mut out,
                pt(p),
                5,
                Scalar::new(0.0, 0.0, 255.0, 0.0),
                1,
                imgproc::LINE_AA,
                0,
            )?;
        }
        imgproc::arrowed_line(&mut out, pt(r), pt(tip), color, 1, imgproc::LINE_AA, 0, 0.25)?;
    }
    imgproc::put_text(
        &mut out,
        caption,
        Point::new(6, 16),
        imgproc::FONT_HERSHEY_SIMPLEX,
        0.45,
        Scalar::new(0.0, 0.0, 0.0, 0.0),
        3,
        imgproc::LINE_AA,
        false,
    )?;
    imgproc::put_text(
        &mut out,
        caption,
        Point::new(6, 16),
        imgproc::FONT_HERSHEY_SIMPLEX,
        0.45,
        Scalar::new(255.0, 255.0, 255.0, 0.0),
        1,
        imgproc::LINE_AA,
        false,
    )?;
    Ok(out)
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
                let out = st.track_tiered(frame_no, &dets.left, &dets.right)?;
                outputs.rows(&out.markers, &out.summary)?;
                tracked_total += out.left.count(MarkerStatus::Tracked);
                visible_total += out.left.markers.len();
                if !args.no_ply {
                    write_ply(&ply_dir, frame_no, st, &out.contact, &out.reprojection_px)?;
                }
                if write_overlay {
                    let lin: Vec<usize> = st
                        .left()
                        .ids()
                        .iter()
                        .map(|i| shape.linear(*i).unwrap_or(0))
                        .collect();
                    let caption = caption(&out.summary);
                    let img = overlay(
                        &pair.left,
                        &reference,
                        &out.left,
                        &|k| out.contact.in_contact[lin[k]],
                        args.arrow_scale,
                        &caption,
                    )?;
                    images::write_image(&overlay_dir.join(format!("{frame_no:06}.png")), &img)?;
                    let field = interpolate(shape, &out.contact.depth_mm, 16);
                    if let Some(f) = field {
                        let map = heatmap(
                            &f,
                            &format!(
                                "frame {frame_no} indentation depth 0 .. {:.3} mm",
                                f.range().1.max(0.0)
                            ),
                        )?;
                        images::write_image(&overlay_dir.join(format!("depth_{frame_no:06}.png")), &map)?;
                    }
                }
                latest_contact = Some(out.contact);
            }
            (Session::Mono(m), Frame::Mono(img)) => {
                let reference: Vec<Point2> = m.tracker().reference_px().to_vec();
                let out = m.track_tiered(frame_no, &dets.left)?;
                outputs.rows(&out.markers, &out.summary)?;
                tracked_total += out.track.count(MarkerStatus::Tracked);
                visible_total += out.track.markers.len();
                if write_overlay {
                    let in_contact = out.planar.in_contact.clone();
                    let caption = caption(&out.summary);
                    let drawn = overlay(
                        img,
                        &reference,
                        &out.track,
                        &|k| in_contact.get(k).copied().unwrap_or(false),
                        args.arrow_scale,
                        &caption,
                    )?;
                    images::write_image(&overlay_dir.join(format!("{frame_no:06}.png")), &drawn)?;
                    // Dense displacement magnitude on the lattice, px.
                    let mut mags: Vec<Option<f64>> = vec![None; shape.count()];
                    for (k, mk) in out.track.markers.iter().enumerate() {
                        if let (Some(p), Some(l)) = (mk.position_px, shape.linear(mk.index)) {
                            mags[l] = Some(p.distance(reference[k]));
                        }
                    }
                    if let Some(f) = interpolate(shape, &mags, 16) {
                        let map = heatmap(
                            &f,
                            &format!("frame {frame_no} displacement 0 .. {:.1} px", f.range().1),
                        )?;
                        images::write_image(
                            &overlay_dir.join(format!("displacement_{frame_no:06}.png")),
                            &map,
                        )?;
                    }
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
    let history = outputs.finish(stereo)?;
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

/// A colour map (jet, 0 .. the field's maximum) of a dense field, with a caption.
fn heatmap(field: &DenseField, caption: &str) -> anyhow::Result<Mat> {
    let (_, hi) = field.range();
    let scale = if hi > 0.0 { 255.0 / hi } else { 0.0 };
    let bytes: Vec<u8> = field
        .values
        .iter()
        .map(|v| (v.max(0.0) * scale).round().clamp(0.0, 255.0) as u8)
        .collect();
    let grey = Mat::new_rows_cols_with_data(field.height as i32, field.width as i32, &bytes)?.try_clone()?;
    let mut colour = Mat::default();
    imgproc::apply_color_map(&grey, &mut colour, imgproc::COLORMAP_JET)?;
    let mut out = Mat::default();
    let (w, h) = (colour.cols().max(1), colour.rows().max(1));
    let k = (480.0 / f64::from(h)).max(1.0);
    imgproc::resize(
        &colour,
        &mut out,
        opencv::core::Size::new((f64::from(w) * k) as i32, (f64::from(h) * k) as i32),
        0.0,
        0.0,
        imgproc::INTER_LINEAR,
    )?;
    imgproc::put_text(
        &mut out,
        caption,
        Point::new(6, 18),
        imgproc::FONT_HERSHEY_SIMPLEX,
        0.5,
        Scalar::all(255.0),
        1,
        imgproc::LINE_AA,
        false,
    )?;
    Ok(out)
}

fn caption(s: &FrameSummary) -> String {
    format!(
        "frame {} {} area {:.2} mm2 depth {:.3} mm",
        s.frame,
        s.slip.as_str(),
        s.contact_area_mm2,
        s.max_depth_mm
    )
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
