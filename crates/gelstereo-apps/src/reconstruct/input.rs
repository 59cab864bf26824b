//! The frames of a reconstruction and their detections: image pairs localized one by one, the
//! frames of a side-by-side stereo video localized while it is read, or the ground-truth positions
//! of a simulated recording (optionally perturbed).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use gelstereo_core::{Detection, Point2, StereoPair};
use gelstereo_geometry::StereoRig;
use gelstereo_io::{images, video};
use gelstereo_markers::{Localizer, LocalizerConfig, Method};
use gelstereo_matching::eval::GroundTruth;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use gelstereo::image_size;
use gelstereo::{Error, Result};

/// Imperfections added to ground-truth positions, to measure how indexing and pairing hold up
/// under a localizer's noise, misses and false detections. The default adds none.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Perturbation {
    /// Gaussian noise added to each coordinate, px (standard deviation).
    pub noise_px: f64,
    /// Fraction of the markers dropped at random in each view.
    pub missing: f64,
    /// Spurious detections added per view, uniformly over the markers' bounding box.
    pub dust: usize,
    /// Seed of the random draws (each frame draws from `seed ^ (frame << 32)`).
    pub seed: u64,
}

impl Perturbation {
    fn is_none(&self) -> bool {
        self.noise_px == 0.0 && self.missing == 0.0 && self.dust == 0
    }

    /// `dets` with this perturbation applied, drawn from `rng`.
    fn apply(&self, dets: Vec<Detection>, rng: &mut ChaCha8Rng) -> Vec<Detection> {
        if self.is_none() {
            return dets;
        }
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for d in &dets {
            (x0, y0) = (x0.min(d.position.x), y0.min(d.position.y));
            (x1, y1) = (x1.max(d.position.x), y1.max(d.position.y));
        }
        let mut out: Vec<Detection> = Vec::with_capacity(dets.len() + self.dust);
        for d in dets {
            if uniform(rng) < self.missing {
                continue;
            }
            let position = Point2::new(
                d.position.x + self.noise_px * normal(rng),
                d.position.y + self.noise_px * normal(rng),
            );
            out.push(Detection { position, ..d });
        }
        if x1 >= x0 {
            for _ in 0..self.dust {
                let position = Point2::new(x0 + (x1 - x0) * uniform(rng), y0 + (y1 - y0) * uniform(rng));
                out.push(Detection {
                    position,
                    confidence: 1.0,
                });
            }
        }
        out
    }
}

/// Uniform in [0, 1).
fn uniform(rng: &mut ChaCha8Rng) -> f64 {
    rng.random::<f64>()
}

/// Standard normal (Box-Muller).
fn normal(rng: &mut ChaCha8Rng) -> f64 {
    let u1 = uniform(rng).max(1e-300);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * uniform(rng)).cos()
}

/// One stereo frame of the input.
pub(super) struct FrameInput {
    /// Frame number written to the tables.
    pub frame: u32,
    /// Where its detections come from.
    pub markers: Markers,
}

/// Where a frame's detections come from.
pub(super) enum Markers {
    /// Localized from these images when the frame is reconstructed.
    InImages(StereoPair<PathBuf>),
    /// Known beforehand: ground-truth positions, or a video frame localized while it was read.
    Given(StereoPair<Vec<Detection>>),
}

/// The localizer, built on first use (ground-truth input needs none).
pub(super) struct LazyLocalizer<'a> {
    method: Method,
    config: &'a LocalizerConfig,
    built: Option<Box<dyn Localizer + Send>>,
}

impl<'a> LazyLocalizer<'a> {
    pub fn new(method: Method, config: &'a LocalizerConfig) -> Self {
        Self {
            method,
            config,
            built: None,
        }
    }

    fn get(&mut self) -> Result<&mut (dyn Localizer + Send)> {
        let localizer = match self.built.take() {
            Some(l) => l,
            None => gelstereo::localizer(self.method, self.config)?,
        };
        Ok(self.built.insert(localizer).as_mut())
    }
}

/// Per frame, the ground-truth positions of the markers visible in each view, perturbed.
pub(super) fn ground_truth_frames(truth: &GroundTruth, perturbation: &Perturbation) -> Vec<FrameInput> {
    let detection = |p: Option<Point2>| {
        p.map(|position| Detection {
            position,
            confidence: 1.0,
        })
    };
    truth
        .frames
        .iter()
        .map(|(&frame, markers)| {
            let mut rng = ChaCha8Rng::seed_from_u64(perturbation.seed ^ (u64::from(frame) << 32));
            let left: Vec<Detection> = markers.values().filter_map(|m| detection(m.left_px)).collect();
            let right: Vec<Detection> = markers.values().filter_map(|m| detection(m.right_px)).collect();
            FrameInput {
                frame,
                markers: Markers::Given(StereoPair::new(
                    perturbation.apply(left, &mut rng),
                    perturbation.apply(right, &mut rng),
                )),
            }
        })
        .collect()
}

/// The stereo frames of `inputs` given as images: a recording folder, two folders paired by file
/// name, or two images.
pub(super) fn image_frames(inputs: &[PathBuf]) -> Result<Vec<FrameInput>> {
    let pairs = match inputs {
        [dir] => {
            let rec = images::StereoRecording::open(dir)?;
            (0..rec.len()).filter_map(|i| rec.paths(i)).collect()
        }
        [l, r] if l.is_dir() && r.is_dir() => paired_folders(l, r)?,
        [l, r] => vec![StereoPair::new(l.clone(), r.clone())],
        _ => {
            return Err(Error::Invalid(
                "give a stereo RECORDING folder, a side-by-side stereo video, or LEFT RIGHT".into(),
            ));
        }
    };
    pairs
        .into_iter()
        .enumerate()
        .map(|(i, p)| {
            Ok(FrameInput {
                frame: frame_number(i)?,
                markers: Markers::InImages(p),
            })
        })
        .collect()
}

fn frame_number(index: usize) -> Result<u32> {
    u32::try_from(index).map_err(|_| Error::Invalid("too many frames".into()))
}

/// Left and right image lists paired by file name.
fn paired_folders(left: &Path, right: &Path) -> Result<Vec<StereoPair<PathBuf>>> {
    let l = images::list_images(left)?;
    let r = images::list_images(right)?;
    let name = |p: &PathBuf| {
        p.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let right_names: BTreeMap<String, PathBuf> = r.iter().map(|p| (name(p), p.clone())).collect();
    if l.is_empty() {
        return Err(Error::Invalid(format!("{}: no images", left.display())));
    }
    if l.len() != r.len() {
        return Err(Error::Invalid(format!(
            "{} holds {} images but {} holds {}: expected the same file names",
            left.display(),
            l.len(),
            right.display(),
            r.len()
        )));
    }
    l.iter()
        .map(|p| match right_names.get(&name(p)) {
            Some(q) => Ok(StereoPair::new(p.clone(), q.clone())),
            None => Err(Error::Invalid(format!(
                "{} has no counterpart {}",
                p.display(),
                right.join(name(p)).display()
            ))),
        })
        .collect()
}

/// Localizes every frame of a side-by-side stereo video (left half, right half) as it is read;
/// adds the time spent to `localize_ms`. Returns the frames and the warning of a video that ended
/// before the frame count it declares.
pub(super) fn localized_video(
    path: &Path,
    rig: &StereoRig,
    calibration: &Path,
    localizer: &mut LazyLocalizer<'_>,
    localize_ms: &mut f64,
) -> Result<(Vec<FrameInput>, Option<String>)> {
    let localizer = localizer.get()?;
    let mut video = video::VideoFrames::open(path)?;
    let mut frames = Vec::new();
    while let Some((index, frame)) = video.next_frame()? {
        let pair = video::split_side_by_side(&frame, path)?;
        rig.check_image_sizes(image_size(&pair.left), image_size(&pair.right))
            .map_err(|e| {
                Error::from(e).context(format!(
                    "{} frame {index}: the halves do not match the calibration '{}'",
                    path.display(),
                    calibration.display()
                ))
            })?;
        let t = Instant::now();
        let found = localizer
            .detect_stereo(&pair)
            .map_err(|e| Error::from(e).context(format!("localizing {} frame {index}", path.display())))?;
        *localize_ms += t.elapsed().as_secs_f64() * 1e3;
        frames.push(FrameInput {
            frame: frame_number(index)?,
            markers: Markers::Given(found),
        });
    }
    Ok((frames, video.shortfall_warning()))
}

/// The detections of `input` in both views and the time spent localizing them, ms.
pub(super) fn detect(
    input: &FrameInput,
    rig: &StereoRig,
    calibration: &Path,
    localizer: &mut LazyLocalizer<'_>,
) -> Result<(StereoPair<Vec<Detection>>, f64)> {
    let paths = match &input.markers {
        Markers::Given(d) => return Ok((d.clone(), 0.0)),
        Markers::InImages(paths) => paths,
    };
    let localizer = localizer.get()?;
    let read = |p: &PathBuf| {
        images::read_image(p).map_err(|e| Error::from(e).context(format!("frame {}", input.frame)))
    };
    let pair = StereoPair::new(read(&paths.left)?, read(&paths.right)?);
    rig.check_image_sizes(image_size(&pair.left), image_size(&pair.right))
        .map_err(|e| {
            Error::from(e).context(format!(
                "{}: the images do not match the calibration '{}'",
                paths.left.display(),
                calibration.display()
            ))
        })?;
    let t = Instant::now();
    let found = localizer
        .detect_stereo(&pair)
        .map_err(|e| Error::from(e).context(format!("localizing {}", paths.left.display())))?;
    Ok((found, t.elapsed().as_secs_f64() * 1e3))
}
