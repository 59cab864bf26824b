//! `gelstereo detect`: markers in images, videos and stereo recordings, as `image,x,y,confidence` CSV
//! (docs/design.md "Interfaces"), with optional overlay PNGs. Also the localizer options shared with
//! `gelstereo eval` and `gelstereo bench`.

use std::collections::HashSet;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use gelstereo::core::files::escaped;
use gelstereo::core::{Detection, StereoPair};
use gelstereo::io::AtomicFile;
use gelstereo::io::images::{self, StereoRecording};
use gelstereo::io::video::{self, VideoFrames};
use gelstereo::markers::{BlobParams, InputFit, Localizer, LocalizerConfig, Method, SessionOptions, overlay};
use gelstereo::sink::OutputFolder;
use opencv::core::Mat;

use crate::pad_border::PadBorder;

use crate::project;

/// The help section of the localizer's internal switches: they exist to measure what each step of
/// the localizer adds, and the defaults are what every figure in the docs uses.
const EXPERT: &str = "Expert options (localizer internals; the defaults are measured best)";

/// How to build the localizers: model files, blob parameters, ONNX Runtime options.
#[derive(clap::Args, Debug, Clone)]
pub struct LocalizerArgs {
    /// Folder with marknet.onnx (the localization network) and mre.onnx (the MRE, Marker Rationality
    /// Evaluator, which keeps low-confidence markers that fit the lattice); default: data/models of
    /// the project, else the copy compiled into this binary.
    #[arg(long, value_name = "DIR")]
    pub models: Option<PathBuf>,
    /// Marknet model file (overrides --models).
    #[arg(long, value_name = "FILE")]
    pub marknet: Option<PathBuf>,
    /// MRE (Marker Rationality Evaluator) model file (overrides --models).
    #[arg(long, value_name = "FILE")]
    pub mre: Option<PathBuf>,
    /// SimpleBlobDetector parameters: `tuned` (data/blob_params.json), `default` (OpenCV's), or a JSON file.
    #[arg(long, value_name = "tuned|default|FILE", default_value = "tuned")]
    pub blob_params: String,
    /// ONNX Runtime intra-op threads (0: one per core; at most 256).
    #[arg(long, default_value_t = 0, value_name = "N", value_parser = gelstereo::core::limits::parse_thread_count)]
    pub threads: usize,
    /// Never use the CUDA execution provider, even where ONNX Runtime has it.
    #[arg(long)]
    pub cpu: bool,
    /// How Marknet fits an image to its input: `auto` (the model's: isotropic, scaled so the marker
    /// pitch measured on a first pass lands in the range the network was trained on, a margin of the
    /// median colour; the pitch is remembered per image size), `stretch` (the whole image resized to the nominal
    /// input) or `pad` (isotropic, never enlarged, centred in the nominal input).
    #[arg(long, default_value = "auto", value_name = "auto|stretch|pad", help_heading = EXPERT)]
    pub fit: InputFit,
    /// Run Marknet on the whole input of every frame. By default a stream's later frames run on a
    /// window of the input around the lattice its first frame showed (the whole input again for a
    /// frame whose markers come near the window's edge); the markers are the same to a few
    /// hundredths of a pixel (docs/localization.md, "Window around the lattice").
    #[arg(long, help_heading = EXPERT)]
    pub whole_input: bool,
    /// Do not look again where the lattice is squeezed. By default, where the first pass's
    /// candidates lie closer together than 0.8 pitch (dots pushed into each other at an indenter's
    /// rim), Marknet runs once more on a window around them at 1.5 x the scale and its finds replace
    /// the first pass's there, and dots between squeezed markers that it still misses are found as
    /// blobs (docs/localization.md, "A closer look at squeezed dots", "Blobs between squeezed markers").
    #[arg(long, help_heading = EXPERT)]
    pub no_close_look: bool,
}

impl LocalizerArgs {
    /// The blob parameters `spec` names (`tuned`, `default` or a file).
    pub fn blob(spec: &str) -> anyhow::Result<BlobParams> {
        Ok(match spec {
            "default" => BlobParams::opencv_defaults()?,
            // The shipped file where the project's files are, else the same values compiled in
            // (an installed binary; a test keeps the two equal).
            "tuned" => {
                let path = project::home().join(gelstereo::markers::blob::DEFAULT_PARAMS_FILE);
                if path.is_file() {
                    BlobParams::from_json_file(&path)?
                } else {
                    BlobParams::tuned()
                }
            }
            file => BlobParams::from_json_file(Path::new(file))?,
        })
    }

    /// The library configuration these options describe.
    pub fn config(&self) -> anyhow::Result<LocalizerConfig> {
        let models = self
            .models
            .clone()
            .unwrap_or_else(gelstereo::models::shipped_models);
        Ok(LocalizerConfig {
            marknet_path: self
                .marknet
                .clone()
                .unwrap_or_else(|| models.join("marknet.onnx")),
            mre_path: self.mre.clone().unwrap_or_else(|| models.join("mre.onnx")),
            blob: Self::blob(&self.blob_params)?,
            session: SessionOptions {
                intra_threads: self.threads,
                use_cuda: !self.cpu,
            },
            fit: self.fit,
            remember_pitch: true,
            lattice_window: !self.whole_input,
            close_look: !self.no_close_look,
        })
    }

    /// Builds the localizer of `method`, with the failing method named in the error.
    pub fn localizer(&self, method: Method) -> anyhow::Result<Box<dyn Localizer + Send>> {
        Self::localizer_from(method, &self.config()?)
    }

    /// Builds the localizer of `method` from a configuration, with the failing method named.
    pub fn localizer_from(
        method: Method,
        config: &LocalizerConfig,
    ) -> anyhow::Result<Box<dyn Localizer + Send>> {
        Ok(gelstereo::localizer(method, config)?)
    }
}

/// Arguments of `gelstereo detect`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Localization method: blob (OpenCV's SimpleBlobDetector), yolo, marknet, or marknet-mre (Marknet
    /// with the MRE, Marker Rationality Evaluator).
    #[arg(long, default_value = "marknet-mre")]
    method: Method,
    /// CSV output (`image,x,y,confidence`); standard output when absent.
    #[arg(long, value_name = "FILE.csv")]
    out: Option<PathBuf>,
    /// Write an overlay PNG per image into this folder (circles coloured by confidence, red = 0.1 to
    /// green = 1; a cross marks markers MRE accepted).
    #[arg(long, value_name = "DIR")]
    overlay: Option<PathBuf>,
    /// Write overlays into a non-empty --overlay folder that gelstereo did not write (same-named
    /// files there are replaced). A folder an earlier run wrote is emptied of that run's files
    /// without it.
    #[arg(long)]
    force: bool,
    /// Treat videos as side-by-side stereo (left half, right half).
    #[arg(long)]
    side_by_side: bool,
    /// Kept for old scripts: markers cut by the image border are found by default, placed at their
    /// centre, and none whose centre lies outside the image is reported; a number given is ignored.
    #[arg(long, default_value_t, value_name = "auto|PX")]
    pad_border: PadBorder,
    #[command(flatten)]
    localizer: LocalizerArgs,
    /// Image files, folders of images, stereo recordings (folders with left/ and right/) or video files.
    #[arg(value_name = "INPUT")]
    inputs: Vec<PathBuf>,
}

/// One input, expanded.
enum Source {
    Image(PathBuf),
    Stereo(StereoRecording),
    Video(PathBuf),
}

fn expand(inputs: &[PathBuf]) -> anyhow::Result<Vec<Source>> {
    if inputs.is_empty() {
        bail!(
            "no input images: give image files, folders of images, stereo recordings (left/ and right/) or videos"
        );
    }
    let mut out = Vec::new();
    for p in inputs {
        if p.is_dir() {
            if images::is_stereo_recording(p) {
                out.push(Source::Stereo(StereoRecording::open(p)?));
            } else {
                let files = images::list_images(p)?;
                if files.is_empty() {
                    bail!(
                        "{}: folder holds no images (expected {} files, or left/ and right/)",
                        p.display(),
                        images::IMAGE_EXTENSIONS.join("/")
                    );
                }
                out.extend(files.into_iter().map(Source::Image));
            }
        } else if video::has_video_extension(p) {
            out.push(Source::Video(p.clone()));
        } else {
            out.push(Source::Image(p.clone()));
        }
    }
    Ok(out)
}

/// The CSV destination: a file replaced only on success, or standard output.
enum CsvOut {
    File(AtomicFile),
    Stdout(std::io::BufWriter<std::io::StdoutLock<'static>>),
}

impl Write for CsvOut {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match self {
            Self::File(f) => f.write(buf),
            Self::Stdout(s) => s.write(buf),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match self {
            Self::File(f) => f.flush(),
            Self::Stdout(s) => s.flush(),
        }
    }
}

/// Where the CSV rows and overlays go.
struct Sink {
    csv: CsvOut,
    overlay: Option<OutputFolder>,
    used_names: HashSet<String>,
    mre_band_top: Option<f32>,
    images: usize,
    markers: usize,
}

impl Sink {
    fn emit(
        &mut self,
        name: &str,
        overlay_stem: &str,
        image: &Mat,
        detections: &[Detection],
    ) -> anyhow::Result<()> {
        // Ctrl-C or SIGTERM: stop between images; the CSV's temporary file goes with the error and
        // an existing --out file stays as it was.
        if gelstereo::core::interrupt::requested() {
            bail!(
                "interrupted after {} images; an existing --out file is left as it was",
                self.images
            );
        }
        for d in detections {
            writeln!(
                self.csv,
                "{name},{:.3},{:.3},{:.4}",
                d.position.x, d.position.y, d.confidence
            )
            .context("cannot write the CSV output")?;
        }
        self.images += 1;
        self.markers += detections.len();
        if let Some(folder) = &self.overlay {
            let mut file = format!("{overlay_stem}.png");
            let mut k = 1;
            while !self.used_names.insert(file.clone()) {
                file = format!("{overlay_stem}_{k}.png");
                k += 1;
            }
            let drawn = overlay::draw(image, detections, self.mre_band_top, 6)?;
            folder.write_atomic(&file, |path| Ok(images::write_image(path, &drawn)?))?;
        }
        Ok(())
    }
}

/// An image's name for its overlay file: distinct for names that are not UTF-8.
fn stem(p: &Path) -> String {
    p.file_stem().map(escaped).unwrap_or_else(|| "image".to_owned())
}

/// An image's path for the CSV's `image` column: distinct for names that are not UTF-8.
fn shown(p: &Path) -> String {
    escaped(p.as_os_str())
}

/// The markers of one view.
fn detect_view(localizer: &mut (dyn Localizer + Send), image: &Mat) -> anyhow::Result<Vec<Detection>> {
    Ok(localizer.detect(image)?)
}

/// The markers of both views, as one batch.
fn detect_pair(
    localizer: &mut (dyn Localizer + Send),
    pair: &StereoPair<Mat>,
) -> anyhow::Result<StereoPair<Vec<Detection>>> {
    Ok(localizer.detect_stereo(pair)?)
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    let sources = expand(&args.inputs)?;
    args.pad_border.note_if_given();
    let mut localizer = args.localizer.localizer(args.method)?;
    // An existing --out file is replaced only when every input was read (AtomicFile).
    let csv = match &args.out {
        Some(path) => CsvOut::File(AtomicFile::create(path)?),
        None => CsvOut::Stdout(std::io::BufWriter::new(std::io::stdout().lock())),
    };
    let mut sink = Sink {
        csv,
        overlay: match &args.overlay {
            Some(dir) => {
                let inputs: Vec<&Path> = args.inputs.iter().map(PathBuf::as_path).collect();
                Some(OutputFolder::prepare_apart_from(dir, args.force, &inputs)?)
            }
            None => None,
        },
        used_names: HashSet::new(),
        mre_band_top: localizer.mre_band_top(),
        images: 0,
        markers: 0,
    };
    writeln!(sink.csv, "image,x,y,confidence").context("cannot write the CSV output")?;
    for source in &sources {
        match source {
            Source::Image(path) => {
                let image = images::read_image(path)?;
                let found =
                    detect_view(localizer.as_mut(), &image).with_context(|| format!("{}", path.display()))?;
                sink.emit(&shown(path), &stem(path), &image, &found)?;
            }
            Source::Stereo(rec) => {
                for i in 0..rec.len() {
                    let (Some(paths), Some(pair)) = (rec.paths(i), rec.read(i)) else {
                        break;
                    };
                    let pair = pair?;
                    let found = detect_pair(localizer.as_mut(), &pair)
                        .with_context(|| format!("{} (stereo frame {i})", paths.left.display()))?;
                    for (side, path, image, dets) in [
                        ("left", &paths.left, &pair.left, &found.left),
                        ("right", &paths.right, &pair.right, &found.right),
                    ] {
                        sink.emit(&shown(path), &format!("{side}_{}", stem(path)), image, dets)?;
                    }
                }
            }
            Source::Video(path) => {
                let mut frames = VideoFrames::open(path)?;
                while let Some((index, frame)) = frames.next_frame()? {
                    let name = format!("{}#{index}", shown(path));
                    let context = || format!("{name} (frame {index})");
                    if args.side_by_side {
                        let pair: StereoPair<Mat> = video::split_side_by_side(&frame, path)?;
                        let found = detect_pair(localizer.as_mut(), &pair).with_context(context)?;
                        sink.emit(
                            &format!("{name}:left"),
                            &format!("{}_{index:06}_left", stem(path)),
                            &pair.left,
                            &found.left,
                        )?;
                        sink.emit(
                            &format!("{name}:right"),
                            &format!("{}_{index:06}_right", stem(path)),
                            &pair.right,
                            &found.right,
                        )?;
                    } else {
                        let found = detect_view(localizer.as_mut(), &frame).with_context(context)?;
                        sink.emit(&name, &format!("{}_{index:06}", stem(path)), &frame, &found)?;
                    }
                }
                if let Some(warning) = frames.shortfall_warning() {
                    eprintln!("warning: {warning}");
                }
            }
        }
    }
    sink.csv.flush().context("cannot write the CSV output")?;
    if sink.images == 0 {
        bail!("no images were read from the inputs (empty video?)");
    }
    let (images, markers) = (sink.images, sink.markers);
    if let CsvOut::File(file) = sink.csv {
        file.commit()?;
    }
    let dest = args
        .out
        .as_ref()
        .map_or_else(|| "standard output".to_owned(), |p| p.display().to_string());
    eprintln!(
        "{}: {} markers in {} images ({:.1} per image), written to {dest}",
        localizer.name(),
        markers,
        images,
        markers as f64 / images as f64
    );
    Ok(())
}
