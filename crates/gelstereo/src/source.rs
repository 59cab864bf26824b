//! Frame sources: stereo recordings (`left/` + `right/`), folders of images, video files (mono or
//! side-by-side stereo), one camera (mono or side-by-side) and two cameras paired by capture time.
//! A "camera" may also be a video file, which stands in for a device through the same code.
//! Every frame carries a timestamp: capture time for cameras, frame time for videos, frame number /
//! frame rate otherwise. [`Prefetch`] reads and decodes frames on a thread of its own.

use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;
use std::time::Instant;

use gelstereo_core::StereoPair;
use gelstereo_io::images::{self, StereoRecording};
use gelstereo_io::video::{self, VideoFrames};
use opencv::core::{Mat, MatTraitConst};
use opencv::prelude::{VideoCaptureTrait, VideoCaptureTraitConst};
use opencv::videoio::{self, VideoCapture};

use crate::{Error, Frame, Images, Result};

/// Frame rate assumed for recordings and videos that declare none, Hz.
pub const DEFAULT_FRAME_RATE_HZ: f64 = 30.0;

/// One frame from a source: its number, its time and its images, or why they cannot be read (the
/// error names the file or device).
#[derive(Debug)]
pub struct SourceFrame {
    /// Frame number in the source, from 0.
    pub index: usize,
    /// Capture time, s.
    pub time_s: f64,
    /// The images, or why they cannot be read.
    pub images: Result<Images>,
}

impl SourceFrame {
    /// The frame for [`crate::Pipeline::process`], or the read error.
    pub fn into_frame(self) -> Result<Frame> {
        Ok(Frame {
            images: self.images?,
            time_s: Some(self.time_s),
        })
    }
}

/// A camera device (`/dev/videoN` given as `N`) or a video file standing in for one.
pub struct Camera {
    name: String,
    capture: VideoCapture,
    is_file: bool,
    opened: Instant,
}

impl Camera {
    /// Opens `spec`: a device number (`0`), or the path of a video file.
    pub fn open(spec: &str) -> Result<Self> {
        let (capture, is_file) = match spec.trim().parse::<i32>() {
            Ok(index) => (VideoCapture::new(index, videoio::CAP_ANY)?, false),
            Err(_) => {
                std::fs::metadata(spec).map_err(crate::error::file_err(Path::new(spec)))?;
                (VideoCapture::from_file(spec, videoio::CAP_ANY)?, true)
            }
        };
        if !capture.is_opened().unwrap_or(false) {
            return Err(Error::Invalid(format!(
                "camera {spec} cannot be opened (no such device, it is busy, or not a video)"
            )));
        }
        Ok(Self {
            name: format!("camera {spec}"),
            capture,
            is_file,
            opened: Instant::now(),
        })
    }

    /// The frame rate the device or file declares, Hz.
    pub fn frame_rate_hz(&self) -> f64 {
        self.capture
            .get(videoio::CAP_PROP_FPS)
            .ok()
            .filter(|f| f.is_finite() && *f > 0.0)
            .unwrap_or(DEFAULT_FRAME_RATE_HZ)
    }

    /// Grabs the next frame without decoding it; returns its capture time, s (the video position for
    /// a file, the time since opening for a device), or `None` at the end.
    fn grab(&mut self) -> Result<Option<f64>> {
        if !self.capture.grab()? {
            return Ok(None);
        }
        let t = if self.is_file {
            self.capture.get(videoio::CAP_PROP_POS_MSEC)? * 1e-3
        } else {
            self.opened.elapsed().as_secs_f64()
        };
        Ok(Some(t))
    }

    /// Decodes the frame last grabbed.
    fn retrieve(&mut self) -> Result<Mat> {
        let mut m = Mat::default();
        if !self.capture.retrieve(&mut m, 0)? || m.empty() {
            return Err(Error::Invalid(format!(
                "{}: the frame cannot be decoded",
                self.name
            )));
        }
        Ok(m)
    }
}

/// Where frames come from.
pub enum FrameSource {
    /// A stereo recording, both views (or only the left one with `left_only`).
    Recording {
        /// The recording.
        recording: StereoRecording,
        /// Track the left view only.
        left_only: bool,
        /// The next frame.
        next: usize,
        /// Frame rate for timestamps, Hz.
        frame_rate_hz: f64,
    },
    /// A folder of images (mono).
    Images {
        /// The images, sorted.
        files: Vec<PathBuf>,
        /// The next frame.
        next: usize,
        /// Frame rate for timestamps, Hz.
        frame_rate_hz: f64,
    },
    /// A video file, mono or side-by-side stereo.
    Video {
        /// The video.
        frames: VideoFrames,
        /// Left half, right half.
        side_by_side: bool,
        /// Unreadable frames in a row (five end the stream).
        failures: usize,
        /// The next frame.
        next: usize,
    },
    /// One camera, mono or side-by-side stereo.
    Camera {
        /// The camera.
        camera: Box<Camera>,
        /// Left half, right half.
        side_by_side: bool,
        /// The next frame.
        next: usize,
    },
    /// Two cameras (left, right), frames paired by capture time.
    TwoCameras {
        /// The left and right cameras.
        cameras: Box<StereoPair<Camera>>,
        /// Largest capture-time difference of a pair, s (half a frame period).
        tolerance_s: f64,
        /// The next frame.
        next: usize,
    },
}

impl FrameSource {
    /// Opens a stereo recording folder, a folder of images or a video file (`side_by_side`: a
    /// stereo video, left half and right half).
    pub fn open_path(input: &Path, side_by_side: bool) -> Result<Self> {
        if input.is_dir() {
            if images::is_stereo_recording(input) {
                return Ok(FrameSource::Recording {
                    recording: StereoRecording::open(input)?,
                    left_only: false,
                    next: 0,
                    frame_rate_hz: recording_frame_rate_hz(input)?,
                });
            }
            let files = images::list_images(input)?;
            if files.is_empty() {
                return Err(Error::Invalid(format!(
                    "{}: holds no images (expected left/ and right/, or {} files)",
                    input.display(),
                    images::IMAGE_EXTENSIONS.join("/")
                )));
            }
            return Ok(FrameSource::Images {
                files,
                next: 0,
                frame_rate_hz: recording_frame_rate_hz(input)?,
            });
        }
        if !input.exists() {
            return Err(Error::Invalid(format!(
                "{}: no such file or folder",
                input.display()
            )));
        }
        if video::has_video_extension(input) {
            return Ok(FrameSource::Video {
                frames: VideoFrames::open(input)?,
                side_by_side,
                failures: 0,
                next: 0,
            });
        }
        Err(Error::Invalid(format!(
            "{}: expected a stereo recording folder, a folder of images or a video ({})",
            input.display(),
            video::VIDEO_EXTENSIONS.join("/")
        )))
    }

    /// Opens `spec` as a path ([`Self::open_path`], mono or stereo as the folder says) when it
    /// exists, else as cameras: `N` or `L,R` ([`Self::open_cameras`]).
    pub fn open(spec: &str) -> Result<Self> {
        let path = Path::new(spec);
        if path.exists() {
            return Self::open_path(path, false);
        }
        let cameras: Vec<String> = spec.split(',').map(str::to_owned).collect();
        if cameras.iter().all(|c| c.trim().parse::<i32>().is_ok()) {
            return Self::open_cameras(&cameras, false);
        }
        Err(Error::Invalid(format!(
            "{spec}: no such file or folder, and not a camera number (N or L,R)"
        )))
    }

    /// Like [`Self::open_path`], but a stereo recording gives its left view only (a mono sensor).
    pub fn open_left_view(input: &Path) -> Result<Self> {
        let mut source = Self::open_path(input, false)?;
        if let FrameSource::Recording { left_only, .. } = &mut source {
            *left_only = true;
        }
        Ok(source)
    }

    /// Opens cameras: one spec (`N` or a video path; `side_by_side` for a stereo device) or two
    /// (`[left, right]`, paired by capture time).
    pub fn open_cameras(specs: &[String], side_by_side: bool) -> Result<Self> {
        match specs {
            [one] => Ok(FrameSource::Camera {
                camera: Box::new(Camera::open(one)?),
                side_by_side,
                next: 0,
            }),
            [left, right] => {
                let mut cameras = StereoPair::new(Camera::open(left)?, Camera::open(right)?);
                // One clock for both devices: each counted from its own opening would put the
                // right camera's times behind by however long the left one took to open.
                let epoch = Instant::now();
                cameras.left.opened = epoch;
                cameras.right.opened = epoch;
                let rate = cameras.left.frame_rate_hz().max(cameras.right.frame_rate_hz());
                Ok(FrameSource::TwoCameras {
                    cameras: Box::new(cameras),
                    tolerance_s: 0.5 / rate,
                    next: 0,
                })
            }
            _ => Err(Error::Invalid(format!(
                "--camera: expected one camera (N) or two (L,R), got {}",
                specs.len()
            ))),
        }
    }

    /// Whether the frames are stereo pairs.
    pub fn is_stereo(&self) -> bool {
        match self {
            FrameSource::Recording { left_only, .. } => !left_only,
            FrameSource::Images { .. } => false,
            FrameSource::Video { side_by_side, .. } | FrameSource::Camera { side_by_side, .. } => {
                *side_by_side
            }
            FrameSource::TwoCameras { .. } => true,
        }
    }

    /// The number of frames, when known in advance.
    pub fn len_hint(&self) -> Option<usize> {
        match self {
            FrameSource::Recording { recording, .. } => Some(recording.len()),
            FrameSource::Images { files, .. } => Some(files.len()),
            FrameSource::Video { frames, .. } => Some(frames.declared_frame_count()).filter(|n| *n > 0),
            FrameSource::Camera { .. } | FrameSource::TwoCameras { .. } => None,
        }
    }

    /// The next frame; `None` at the end of the source.
    pub fn next_frame(&mut self) -> Option<SourceFrame> {
        match self {
            FrameSource::Recording {
                recording,
                left_only,
                next,
                frame_rate_hz,
            } => {
                let frame = read_recorded(recording, *left_only, *next, *frame_rate_hz)?;
                *next += 1;
                Some(frame)
            }
            FrameSource::Images {
                files,
                next,
                frame_rate_hz,
            } => {
                let path = files.get(*next)?;
                let frame = SourceFrame {
                    index: *next,
                    time_s: *next as f64 / *frame_rate_hz,
                    images: images::read_image(path).map(Images::Mono).map_err(Error::from),
                };
                *next += 1;
                Some(frame)
            }
            FrameSource::Video {
                frames,
                side_by_side,
                failures,
                next,
            } => read_video(frames, *side_by_side, failures, take_index(next)),
            FrameSource::Camera {
                camera,
                side_by_side,
                next,
            } => read_camera(camera, *side_by_side, take_index(next)),
            FrameSource::TwoCameras {
                cameras,
                tolerance_s,
                next,
            } => read_camera_pair(cameras, *tolerance_s, take_index(next)),
        }
    }

    /// A warning when the frame files' names do not settle their order (the same number written
    /// two ways: [`images::ambiguous_order`]); `None` for a clear order, videos and cameras.
    pub fn order_warning(&self) -> Option<String> {
        match self {
            FrameSource::Recording { recording, .. } => images::ambiguous_order(&recording.names),
            FrameSource::Images { files, .. } => images::ambiguous_order(files),
            _ => None,
        }
    }

    /// After the source has ended: a warning when it ended before its declared length (a video
    /// whose container declares more frames than could be decoded: a truncated or damaged file),
    /// naming the file and both counts; `None` for a source that ended whole or declares nothing.
    pub fn end_warning(&self) -> Option<String> {
        match self {
            FrameSource::Video { frames, .. } => frames.shortfall_warning(),
            _ => None,
        }
    }

    /// Reads and decodes the frames on a thread of its own, at most `depth` ahead of the consumer.
    pub fn prefetch(self, depth: usize) -> Prefetch {
        Prefetch::spawn(self, depth)
    }
}

impl Iterator for FrameSource {
    type Item = SourceFrame;

    fn next(&mut self) -> Option<SourceFrame> {
        self.next_frame()
    }
}

/// The current frame number, and the counter moved on past it.
fn take_index(next: &mut usize) -> usize {
    let index = *next;
    *next += 1;
    index
}

/// Frame `index` of a stereo recording (its left view alone for `left_only`); `None` past its end.
fn read_recorded(
    recording: &StereoRecording,
    left_only: bool,
    index: usize,
    frame_rate_hz: f64,
) -> Option<SourceFrame> {
    let images = if left_only {
        let paths = recording.paths(index)?;
        images::read_image(&paths.left).map(Images::Mono)
    } else {
        recording.read(index)?.map(Images::Stereo)
    };
    Some(SourceFrame {
        index,
        time_s: index as f64 / frame_rate_hz,
        images: images.map_err(Error::from),
    })
}

/// Frame `index` of a video; `None` at its end, or after five unreadable frames in a row (a broken
/// stream), which `failures` counts.
fn read_video(
    frames: &mut VideoFrames,
    side_by_side: bool,
    failures: &mut usize,
    index: usize,
) -> Option<SourceFrame> {
    let rate = frames.frame_rate_hz().unwrap_or(DEFAULT_FRAME_RATE_HZ);
    let images = match frames.next_frame() {
        Ok(None) => return None,
        Ok(Some((_, m))) => {
            *failures = 0;
            split(m, side_by_side, frames.path())
        }
        Err(e) => {
            *failures += 1;
            if *failures > 5 {
                return None;
            }
            Err(e.into())
        }
    };
    Some(SourceFrame {
        index,
        time_s: index as f64 / rate,
        images,
    })
}

/// The next frame of one camera, stamped with its capture time; `None` when the camera ends.
fn read_camera(camera: &mut Camera, side_by_side: bool, index: usize) -> Option<SourceFrame> {
    let time_s = match camera.grab() {
        Ok(Some(t)) => t,
        Ok(None) => return None,
        Err(e) => {
            return Some(SourceFrame {
                index,
                time_s: camera.opened.elapsed().as_secs_f64(),
                images: Err(e.context(camera.name.clone())),
            });
        }
    };
    let images = camera
        .retrieve()
        .and_then(|m| split(m, side_by_side, Path::new(&camera.name)));
    Some(SourceFrame {
        index,
        time_s,
        images,
    })
}

/// The next pair of two cameras ([`grab_pair`]), stamped with the later capture time; `None` when
/// either camera ends.
fn read_camera_pair(cameras: &mut StereoPair<Camera>, tolerance_s: f64, index: usize) -> Option<SourceFrame> {
    match grab_pair(cameras, tolerance_s) {
        Ok(None) => None,
        Ok(Some(time_s)) => {
            let images = cameras
                .left
                .retrieve()
                .and_then(|l| Ok(Images::Stereo(StereoPair::new(l, cameras.right.retrieve()?))));
            Some(SourceFrame {
                index,
                time_s,
                images,
            })
        }
        Err(e) => Some(SourceFrame {
            index,
            time_s: cameras.left.opened.elapsed().as_secs_f64(),
            images: Err(e),
        }),
    }
}

/// Grabs one frame from each camera so that their capture times differ by at most `tolerance_s`:
/// the camera behind grabs again (at most four times, then the pair is taken as it is). Returns the
/// later capture time, or `None` when either camera has ended.
fn grab_pair(cameras: &mut StereoPair<Camera>, tolerance_s: f64) -> Result<Option<f64>> {
    let (Some(mut tl), Some(mut tr)) = (cameras.left.grab()?, cameras.right.grab()?) else {
        return Ok(None);
    };
    for _ in 0..4 {
        if (tl - tr).abs() <= tolerance_s {
            break;
        }
        let behind = if tl < tr {
            &mut cameras.left
        } else {
            &mut cameras.right
        };
        let Some(t) = behind.grab()? else { return Ok(None) };
        if tl < tr { tl = t } else { tr = t }
    }
    Ok(Some(tl.max(tr)))
}

fn split(m: Mat, side_by_side: bool, source: &Path) -> Result<Images> {
    if side_by_side {
        Ok(Images::Stereo(video::split_side_by_side(&m, source)?))
    } else {
        Ok(Images::Mono(m))
    }
}

/// A recording's frame rate: `meta.json` `fps` (or `frame_rate_hz`), else
/// [`DEFAULT_FRAME_RATE_HZ`]; a malformed `meta.json` is an error naming it and the field.
pub fn recording_frame_rate_hz(dir: &Path) -> Result<f64> {
    let meta = gelstereo_sensor::RecordingMeta::read(dir)?;
    Ok(meta
        .and_then(|m| m.frame_rate_hz)
        .unwrap_or(DEFAULT_FRAME_RATE_HZ))
}

/// Frames of a [`FrameSource`] read and decoded on a thread of its own, at most `depth` ahead of the
/// consumer (a bounded channel: memory stays flat however long the source). Dropping it stops the
/// thread after the frame it is reading.
pub struct Prefetch {
    frames: Option<Receiver<SourceFrame>>,
    /// The reading thread; it returns the source's [`FrameSource::end_warning`] when the source
    /// ended (not when the consumer stopped early).
    thread: Option<JoinHandle<Option<String>>>,
    stereo: bool,
    len_hint: Option<usize>,
}

impl Prefetch {
    fn spawn(mut source: FrameSource, depth: usize) -> Self {
        let (stereo, len_hint) = (source.is_stereo(), source.len_hint());
        let (tx, rx): (SyncSender<SourceFrame>, Receiver<SourceFrame>) = sync_channel(depth.max(1));
        let thread = std::thread::Builder::new()
            .name("gelstereo-decode".into())
            .spawn(move || {
                while let Some(f) = source.next_frame() {
                    if tx.send(f).is_err() {
                        return None;
                    }
                }
                source.end_warning()
            })
            .ok();
        Self {
            frames: Some(rx),
            thread,
            stereo,
            len_hint,
        }
    }

    /// Whether the frames are stereo pairs.
    pub fn is_stereo(&self) -> bool {
        self.stereo
    }

    /// The number of frames, when known in advance.
    pub fn len_hint(&self) -> Option<usize> {
        self.len_hint
    }

    /// Stops reading and returns the source's [`FrameSource::end_warning`] if it had ended
    /// (a truncated video); `None` when it ended whole or the consumer stopped first.
    pub fn finish(mut self) -> Option<String> {
        self.frames = None;
        self.thread.take().and_then(|t| t.join().ok().flatten())
    }
}

impl Iterator for Prefetch {
    type Item = SourceFrame;

    fn next(&mut self) -> Option<SourceFrame> {
        self.frames.as_ref()?.recv().ok()
    }
}

impl Drop for Prefetch {
    fn drop(&mut self) {
        // Closing the channel makes the reader's next send fail, so it ends.
        self.frames = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
