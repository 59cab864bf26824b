//! Still images: reading and writing single files, listing image folders, and stereo recordings
//! (a folder with `left/` and `right/` sub-folders of images with matching file names, taken in sorted
//! order, as docs/design.md defines them).

use std::path::{Path, PathBuf};

use gelstereo_core::StereoPair;
use opencv::core::{Mat, MatTraitConst, Vector};
use opencv::imgcodecs;

use crate::{Error, Result};

/// File extensions (lower case) treated as images when listing folders.
pub const IMAGE_EXTENSIONS: [&str; 9] = ["png", "jpg", "jpeg", "bmp", "tif", "tiff", "pgm", "ppm", "pnm"];

/// Whether `path` has one of the [`IMAGE_EXTENSIONS`] (case-insensitive).
pub fn has_image_extension(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| x.eq_ignore_ascii_case(e)))
}

/// Reads `path` as an 8-bit, 3-channel BGR image (grey and 16-bit files are converted by OpenCV).
///
/// A missing file gives [`Error::Io`]; a file OpenCV cannot decode gives [`Error::Decode`].
pub fn read_image(path: &Path) -> Result<Mat> {
    let meta = std::fs::metadata(path).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if !meta.is_file() {
        return Err(Error::Layout {
            path: path.to_path_buf(),
            what: "expected an image file, found a folder".into(),
        });
    }
    let mat = imgcodecs::imread(path, imgcodecs::IMREAD_COLOR).map_err(|source| Error::OpenCv {
        path: path.to_path_buf(),
        source,
    })?;
    if mat.empty() || mat.cols() == 0 || mat.rows() == 0 {
        return Err(Error::Decode {
            path: path.to_path_buf(),
        });
    }
    Ok(mat)
}

/// Writes `image` to `path`; the format follows the extension (PNG for overlays).
pub fn write_image(path: &Path, image: &Mat) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| Error::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    let ok = imgcodecs::imwrite(path, image, &Vector::new()).map_err(|source| Error::OpenCv {
        path: path.to_path_buf(),
        source,
    })?;
    if ok {
        Ok(())
    } else {
        Err(Error::Layout {
            path: path.to_path_buf(),
            what: "OpenCV could not write this image (unknown extension?)".into(),
        })
    }
}

/// The image files directly inside `dir`, sorted by file name.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|source| Error::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut files = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|source| Error::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let path = entry.path();
        if path.is_file() && has_image_extension(&path) {
            files.push(path);
        }
    }
    files.sort();
    Ok(files)
}

/// Whether `dir` looks like a stereo recording: a folder with `left/` and `right/` sub-folders.
pub fn is_stereo_recording(dir: &Path) -> bool {
    dir.join("left").is_dir() && dir.join("right").is_dir()
}

/// A stereo recording on disk: `dir/left/NAME` and `dir/right/NAME` for each frame, in sorted order.
#[derive(Debug, Clone)]
pub struct StereoRecording {
    /// The recording's folder.
    pub dir: PathBuf,
    /// The frames' file names, sorted; each exists in both `left/` and `right/`.
    pub names: Vec<String>,
}

impl StereoRecording {
    /// Opens `dir`, checking that `left/` and `right/` hold the same image file names.
    pub fn open(dir: &Path) -> Result<Self> {
        let names_in = |side: &str| -> Result<Vec<String>> {
            let sub = dir.join(side);
            if !sub.is_dir() {
                return Err(Error::Layout {
                    path: dir.to_path_buf(),
                    what: format!(
                        "a stereo recording needs the sub-folders left/ and right/; {side}/ is missing"
                    ),
                });
            }
            Ok(list_images(&sub)?
                .iter()
                .filter_map(|p| p.file_name().and_then(|n| n.to_str()).map(str::to_owned))
                .collect())
        };
        let left = names_in("left")?;
        let right = names_in("right")?;
        if let Some(missing) = left.iter().find(|n| !right.contains(n)) {
            return Err(Error::Layout {
                path: dir.to_path_buf(),
                what: format!("left/{missing} has no counterpart right/{missing}"),
            });
        }
        if let Some(missing) = right.iter().find(|n| !left.contains(n)) {
            return Err(Error::Layout {
                path: dir.to_path_buf(),
                what: format!("right/{missing} has no counterpart left/{missing}"),
            });
        }
        if left.is_empty() {
            return Err(Error::Layout {
                path: dir.to_path_buf(),
                what: "left/ and right/ hold no images".into(),
            });
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            names: left,
        })
    }

    /// Number of stereo frames.
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// Whether the recording has no frames (never true for an opened recording).
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// The left and right file of frame `index`, or `None` past the end.
    pub fn paths(&self, index: usize) -> Option<StereoPair<PathBuf>> {
        let name = self.names.get(index)?;
        Some(StereoPair::new(
            self.dir.join("left").join(name),
            self.dir.join("right").join(name),
        ))
    }

    /// Reads frame `index` (both views); `None` past the end.
    pub fn read(&self, index: usize) -> Option<Result<StereoPair<Mat>>> {
        let paths = self.paths(index)?;
        Some(read_image(&paths.left).and_then(|l| Ok(StereoPair::new(l, read_image(&paths.right)?))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corrupt_and_missing_files_are_reported_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join("bad.png");
        std::fs::write(&bad, b"\x89PNG\r\n\x1a\nthis is not a png").unwrap();
        let err = read_image(&bad).unwrap_err().to_string();
        assert!(err.contains("bad.png") && err.contains("cannot decode"), "{err}");
        let err = read_image(&dir.path().join("none.png")).unwrap_err().to_string();
        assert!(err.contains("none.png"), "{err}");
    }

    #[test]
    fn stereo_recordings_need_matching_names() {
        let dir = tempfile::tempdir().unwrap();
        let img =
            Mat::new_rows_cols_with_default(4, 6, opencv::core::CV_8UC3, opencv::core::Scalar::all(9.0))
                .unwrap();
        for (side, name) in [
            ("left", "000001.png"),
            ("right", "000001.png"),
            ("left", "000000.png"),
            ("right", "000000.png"),
        ] {
            write_image(&dir.path().join(side).join(name), &img).unwrap();
        }
        let rec = StereoRecording::open(dir.path()).unwrap();
        assert_eq!(rec.names, ["000000.png", "000001.png"]);
        let pair = rec.read(1).unwrap().unwrap();
        assert_eq!((pair.right.cols(), pair.right.rows()), (6, 4));
        assert!(rec.read(2).is_none());

        write_image(&dir.path().join("left").join("000002.png"), &img).unwrap();
        let err = StereoRecording::open(dir.path()).unwrap_err().to_string();
        assert!(err.contains("left/000002.png has no counterpart"), "{err}");
    }
}
