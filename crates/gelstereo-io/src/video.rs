//! Video files through OpenCV's `VideoCapture`, frame by frame, and side-by-side stereo frames.

use std::path::{Path, PathBuf};

use gelstereo_core::StereoPair;
use opencv::core::{Mat, MatTraitConst, Rect};
use opencv::prelude::{VideoCaptureTrait, VideoCaptureTraitConst};
use opencv::videoio::{self, VideoCapture};

use crate::{Error, Result};

/// File extensions (lower case) treated as videos.
pub const VIDEO_EXTENSIONS: [&str; 8] = ["avi", "mp4", "mkv", "mov", "webm", "m4v", "mpg", "mpeg"];

/// Whether `path` has one of the [`VIDEO_EXTENSIONS`] (case-insensitive).
pub fn has_video_extension(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| VIDEO_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)))
}

/// The frames of a video file, in order, as 8-bit BGR images.
pub struct VideoFrames {
    path: PathBuf,
    capture: VideoCapture,
    next_index: usize,
}

impl std::fmt::Debug for VideoFrames {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VideoFrames")
            .field("path", &self.path)
            .field("next_index", &self.next_index)
            .finish()
    }
}

impl VideoFrames {
    /// Opens `path`; a missing file or one no OpenCV backend can open is an error naming it.
    pub fn open(path: &Path) -> Result<Self> {
        std::fs::metadata(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        // FFmpeg first (quiet, and what every common container needs); then whatever backend OpenCV has.
        let mut capture = None;
        for backend in [videoio::CAP_FFMPEG, videoio::CAP_ANY] {
            let c = VideoCapture::from_file(path, backend).map_err(|source| Error::OpenCv {
                path: path.to_path_buf(),
                source,
            })?;
            if c.is_opened().map_err(|source| Error::OpenCv {
                path: path.to_path_buf(),
                source,
            })? {
                capture = Some(c);
                break;
            }
        }
        let Some(capture) = capture else {
            return Err(Error::Video {
                path: path.to_path_buf(),
                what: "cannot open as a video (corrupt or unsupported codec)".into(),
            });
        };
        Ok(Self {
            path: path.to_path_buf(),
            capture,
            next_index: 0,
        })
    }

    /// The video file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The frame count the container declares (may be approximate or 0 for some formats).
    pub fn declared_frame_count(&self) -> usize {
        self.capture
            .get(videoio::CAP_PROP_FRAME_COUNT)
            .map(|n| n.max(0.0) as usize)
            .unwrap_or(0)
    }

    /// The frame rate the container declares, Hz (`None` when it declares none).
    pub fn frame_rate_hz(&self) -> Option<f64> {
        self.capture
            .get(videoio::CAP_PROP_FPS)
            .ok()
            .filter(|f| f.is_finite() && *f > 0.0)
    }

    /// Reads the next frame: `Ok(None)` at the end of the video, `Ok(Some((index, image)))` otherwise.
    pub fn next_frame(&mut self) -> Result<Option<(usize, Mat)>> {
        let mut frame = Mat::default();
        let got = self.capture.read(&mut frame).map_err(|source| Error::OpenCv {
            path: self.path.clone(),
            source,
        })?;
        if !got || frame.empty() {
            return Ok(None);
        }
        let index = self.next_index;
        self.next_index += 1;
        Ok(Some((index, frame)))
    }
}

impl Iterator for VideoFrames {
    type Item = Result<(usize, Mat)>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_frame().transpose()
    }
}

/// Splits a side-by-side stereo frame (left half, right half) into its two views (copies).
///
/// `source` names the frame in errors; the width must be even.
pub fn split_side_by_side(frame: &Mat, source: &Path) -> Result<StereoPair<Mat>> {
    let (w, h) = (frame.cols(), frame.rows());
    if w < 2 || w % 2 != 0 {
        return Err(Error::Layout {
            path: source.to_path_buf(),
            what: format!("a side-by-side stereo frame needs an even width, found {w}x{h}"),
        });
    }
    let half = w / 2;
    let left = Mat::roi(frame, Rect::new(0, 0, half, h))
        .and_then(|r| r.try_clone())
        .map_err(|e| Error::OpenCv {
            path: source.to_path_buf(),
            source: e,
        })?;
    let right = Mat::roi(frame, Rect::new(half, 0, half, h))
        .and_then(|r| r.try_clone())
        .map_err(|e| Error::OpenCv {
            path: source.to_path_buf(),
            source: e,
        })?;
    Ok(StereoPair::new(left, right))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn side_by_side_frames_split_into_halves_and_odd_widths_are_rejected() {
        let frame =
            Mat::new_rows_cols_with_default(3, 8, opencv::core::CV_8UC3, opencv::core::Scalar::all(1.0))
                .unwrap();
        let pair = split_side_by_side(&frame, Path::new("v.avi")).unwrap();
        assert_eq!(
            (pair.left.cols(), pair.right.cols(), pair.right.rows()),
            (4, 4, 3)
        );
        let odd =
            Mat::new_rows_cols_with_default(3, 7, opencv::core::CV_8UC3, opencv::core::Scalar::all(1.0))
                .unwrap();
        let err = split_side_by_side(&odd, Path::new("v.avi"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("v.avi") && err.contains("even width"), "{err}");
    }

    #[test]
    fn a_file_that_is_not_a_video_is_reported() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("junk.avi");
        std::fs::write(&p, b"RIFF0000AVI junk").unwrap();
        let err = VideoFrames::open(&p).unwrap_err().to_string();
        assert!(err.contains("junk.avi"), "{err}");
    }
}
