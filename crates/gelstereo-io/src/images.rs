//! Still images: reading and writing single files, listing image folders, and stereo recordings
//! (a folder with `left/` and `right/` sub-folders of images with matching file names, taken in sorted
//! order, as docs/design.md defines them).

use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use gelstereo_core::StereoPair;
use opencv::core::{Mat, MatTraitConst, Vector};
use opencv::imgcodecs;
use opencv::prelude::MatTraitManual;

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
/// A missing file gives [`Error::Io`]; a file OpenCV cannot decode gives [`Error::Decode`]; a PNG or
/// JPEG cut short gives [`Error::Truncated`]; an image larger than the limits of
/// [`gelstereo_core::limits`] gives [`Error::TooLarge`] before any pixel is decoded.
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
    let format = checked_format(path)?;
    if format == Format::Png
        && let Some(mat) = decode_png(path)
    {
        return Ok(mat);
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

/// Decodes an 8-bit RGB or grey PNG with the `png` crate into the BGR image `imread` gives (the
/// same pixels: `tests` compares them), in less CPU time than OpenCV's libpng path on the
/// fast-compressed PNGs of simulated recordings (`fdeflate` inflates them fast). `None` for
/// every other layout (palette, alpha or transparency, 16-bit, under 8-bit, animated) and for
/// anything the crate refuses, checksums included: OpenCV then decodes the file, so conversions and
/// errors stay OpenCV's.
fn decode_png(path: &Path) -> Option<Mat> {
    let bytes = std::fs::read(path).ok()?;
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.ignore_checksums(false);
    let mut reader = decoder.read_info().ok()?;
    let info = reader.info();
    let grey = match (info.color_type, info.bit_depth) {
        (png::ColorType::Rgb, png::BitDepth::Eight) => false,
        (png::ColorType::Grayscale, png::BitDepth::Eight) => true,
        _ => return None,
    };
    if info.trns.is_some() || info.is_animated() {
        return None;
    }
    let (width, height) = (i32::try_from(info.width).ok()?, i32::try_from(info.height).ok()?);
    let mut mat = Mat::new_rows_cols_with_default(
        height,
        width,
        opencv::core::CV_8UC3,
        opencv::core::Scalar::all(0.0),
    )
    .ok()?;
    let bgr = mat.data_bytes_mut().ok()?;
    if grey {
        let mut pixels = vec![0u8; reader.output_buffer_size()?];
        reader.next_frame(&mut pixels).ok()?;
        for (d, &v) in bgr.chunks_exact_mut(3).zip(&pixels) {
            d.fill(v);
        }
    } else {
        // Decoded straight into the image, then R and B swapped in place: no second buffer.
        if reader.output_buffer_size()? != bgr.len() {
            return None;
        }
        reader.next_frame(bgr).ok()?;
        for px in bgr.chunks_exact_mut(3) {
            px.swap(0, 2);
        }
    }
    reader.finish().ok()?;
    Some(mat)
}

/// Encodes 8-bit pixels, row by row, as a PNG in memory: grey (`channels` 1) or RGB (3), with
/// `compression` and, when given, one `filter` for every row (else the crate's adaptive choice).
pub fn encode_png(
    pixels: &[u8],
    (width, height): (u32, u32),
    channels: u8,
    compression: png::Compression,
    filter: Option<png::Filter>,
) -> std::result::Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::with_capacity(pixels.len() * 2 / 3);
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(if channels == 1 {
        png::ColorType::Grayscale
    } else {
        png::ColorType::Rgb
    });
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(compression);
    if let Some(filter) = filter {
        encoder.set_filter(filter);
    }
    let mut writer = encoder.write_header()?;
    writer.write_image_data(pixels)?;
    writer.finish()?;
    Ok(out)
}

/// Encodes 16-bit grey pixels, row by row, as a PNG in memory (a height map's counts).
pub fn encode_png_gray16(
    pixels: &[u16],
    (width, height): (u32, u32),
) -> std::result::Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::with_capacity(pixels.len());
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Sixteen);
    let bytes: Vec<u8> = pixels.iter().flat_map(|v| v.to_be_bytes()).collect();
    let mut writer = encoder.write_header()?;
    writer.write_image_data(&bytes)?;
    writer.finish()?;
    Ok(out)
}

/// Writes `values` (`rows x cols`, row-major) as a NumPy `.npy` array of float32.
pub fn write_npy_f32(path: &Path, rows: usize, cols: usize, values: Vec<f32>) -> Result<()> {
    let io = |e: std::io::Error| crate::Error::Io {
        path: path.to_path_buf(),
        source: e,
    };
    let array = ndarray::Array2::from_shape_vec((rows, cols), values).map_err(|e| {
        io(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            e.to_string(),
        ))
    })?;
    let file = std::fs::File::create(path).map_err(io)?;
    ndarray_npy::WriteNpyExt::write_npy(&array, std::io::BufWriter::new(file))
        .map_err(|e| io(std::io::Error::other(e.to_string())))
}

/// How many bytes at the end of a file are searched for its format's end marker.
const END_MARKER_WINDOW_BYTES: u64 = 4096;

/// Checks what can be checked before decoding: the dimensions in the header against
/// [`gelstereo_core::limits::check_image_dimensions`], and that a PNG ends with its `IEND` chunk and a
/// JPEG with its EOI marker (libjpeg decodes a truncated JPEG partly, with a warning that names no
/// file). Formats this does not recognise are left to the decoder.
pub fn check_image_file(path: &Path) -> Result<()> {
    checked_format(path).map(|_| ())
}

/// The container format told by a file's first bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Format {
    Png,
    Jpeg,
    Other,
}

/// [`check_image_file`], returning the format it read from the header (so the decoder is chosen
/// without reading the file again).
fn checked_format(path: &Path) -> Result<Format> {
    let io = |source| Error::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let mut head = [0u8; 8];
    let head_len = read_up_to(&mut file, &mut head).map_err(io)?;
    let (format, end_marker): (Format, &[u8]) = match &head[..head_len] {
        [0x89, b'P', b'N', b'G', ..] => (Format::Png, b"IEND"),
        [0xFF, 0xD8, 0xFF, ..] => (Format::Jpeg, &[0xFF, 0xD9]),
        _ => return check_dimensions(path).map(|()| Format::Other),
    };
    let len = file.metadata().map_err(io)?.len();
    let start = len.saturating_sub(END_MARKER_WINDOW_BYTES);
    file.seek(SeekFrom::Start(start)).map_err(io)?;
    let mut tail = Vec::new();
    file.read_to_end(&mut tail).map_err(io)?;
    if !tail.windows(end_marker.len()).any(|w| w == end_marker) {
        return Err(Error::Truncated {
            path: path.to_path_buf(),
        });
    }
    check_dimensions(path).map(|()| format)
}

/// The header's dimensions against the limits (formats the header reader does not know pass).
fn check_dimensions(path: &Path) -> Result<()> {
    if let Ok(size) = imagesize::size(path) {
        gelstereo_core::limits::check_image_dimensions(size.width as u64, size.height as u64).map_err(
            |what| Error::TooLarge {
                path: path.to_path_buf(),
                what,
            },
        )?;
    }
    Ok(())
}

/// Reads as much of `buf` as the file holds.
fn read_up_to(file: &mut std::fs::File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut filled = 0;
    while filled < buf.len() {
        match file.read(&mut buf[filled..])? {
            0 => break,
            n => filled += n,
        }
    }
    Ok(filled)
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

/// The image files directly inside `dir`, in the natural order of their names ([`sort_naturally`]). An entry with an image extension that
/// cannot be followed (a symbolic link in a loop or to a missing file) is an error naming it.
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
        if !has_image_extension(&path) {
            continue;
        }
        match std::fs::metadata(&path) {
            Ok(meta) if meta.is_file() => files.push(path),
            Ok(_) => {}
            // A link that cannot be followed (a loop, or a missing target) is reported, not skipped.
            Err(source) => return Err(Error::Io { path, source }),
        }
    }
    sort_naturally(&mut files);
    Ok(files)
}

/// Sorts paths by name in natural order: runs of digits compare as numbers, so `frame_2.png` comes
/// before `frame_10.png` (byte order would put it after); of names equal as numbers, fewer leading
/// zeros come first (`1.png`, then `01.png`). The order is the same on every machine.
pub fn sort_naturally(files: &mut [PathBuf]) {
    files.sort_by(|a, b| alphanumeric_sort::compare_path(a, b).then_with(|| a.cmp(b)));
}

/// For names sorted by [`sort_naturally`]: a warning when two of them carry the same number
/// written differently (`1.png` and `01.png`), whose order the names alone do not settle; `None`
/// when the order is clear.
pub fn ambiguous_order<P: AsRef<Path>>(sorted: &[P]) -> Option<String> {
    let name = |p: &P| {
        p.as_ref()
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned())
    };
    let mut by_number: std::collections::BTreeMap<String, Vec<String>> = Default::default();
    for p in sorted {
        by_number
            .entry(without_leading_zeros(&name(p)))
            .or_default()
            .push(name(p));
    }
    let ties: Vec<String> = by_number
        .values()
        .filter(|names| names.len() > 1)
        .map(|names| names.join(" and "))
        .collect();
    let first = ties.first()?;
    let more = match ties.len() {
        1 => String::new(),
        n => format!(" (and {} more pairs)", n - 1),
    };
    Some(format!(
        "frame files {first}{more} carry the same number written differently and are read in that order (rename them to settle it)"
    ))
}

/// `name` with the leading zeros of each of its numbers dropped (`f007.png` -> `f7.png`).
fn without_leading_zeros(name: &str) -> String {
    let mut out = String::with_capacity(name.len());
    let mut in_number = false;
    let chars: Vec<char> = name.chars().collect();
    for (k, c) in chars.iter().enumerate() {
        let digit_follows = chars.get(k + 1).is_some_and(char::is_ascii_digit);
        if *c == '0' && !in_number && digit_follows {
            continue;
        }
        in_number = c.is_ascii_digit();
        out.push(*c);
    }
    out
}

/// The regular files directly inside `dir` whose names `keep` accepts, sorted naturally.
pub fn list_files_named(dir: &Path, keep: impl Fn(&str) -> bool) -> Result<Vec<PathBuf>> {
    let io = |source| Error::Io {
        path: dir.to_path_buf(),
        source,
    };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let entry = entry.map_err(io)?;
        let name = entry.file_name();
        if name.to_str().is_some_and(&keep) && entry.file_type().map_err(io)?.is_file() {
            files.push(entry.path());
        }
    }
    sort_naturally(&mut files);
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
    fn the_same_number_written_two_ways_is_an_ambiguous_order() {
        let mut names: Vec<PathBuf> = ["10.png", "2.png", "01.png", "1.png"]
            .iter()
            .map(PathBuf::from)
            .collect();
        sort_naturally(&mut names);
        assert_eq!(names[3], PathBuf::from("10.png"));
        let warning = ambiguous_order(&names).unwrap();
        assert!(warning.contains("1.png and 01.png"), "{warning}");
        names.retain(|n| n != Path::new("01.png"));
        assert_eq!(ambiguous_order(&names), None);
    }

    #[test]
    fn frame_files_come_in_natural_order() {
        let mut files: Vec<PathBuf> = [
            "sample_10.jpg",
            "sample_2.jpg",
            "sample_1.jpg",
            "01.png",
            "1.png",
            "b.png",
        ]
        .iter()
        .map(PathBuf::from)
        .collect();
        sort_naturally(&mut files);
        let names: Vec<&str> = files.iter().map(|p| p.to_str().unwrap()).collect();
        assert_eq!(
            names,
            [
                "1.png",
                "01.png",
                "b.png",
                "sample_1.jpg",
                "sample_2.jpg",
                "sample_10.jpg"
            ]
        );
    }
    use opencv::prelude::MatTraitConstManual;

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

    /// A PNG of `channels` (1 grey, 3 RGB, 4 RGBA) 8-bit samples, pseudo-random (xorshift) with
    /// smooth runs so that every filter type is worth choosing.
    fn png_bytes(width: u32, height: u32, channels: usize, compression: png::Compression) -> Vec<u8> {
        let mut state: u32 = 0x9E37_79B9;
        let samples: Vec<u8> = (0..width as usize * height as usize * channels)
            .map(|i| {
                state ^= state << 13;
                state ^= state >> 17;
                state ^= state << 5;
                if (i / 97) % 2 == 0 {
                    (i % 251) as u8
                } else {
                    state as u8
                }
            })
            .collect();
        let mut out = Vec::new();
        let mut enc = png::Encoder::new(&mut out, width, height);
        enc.set_color(match channels {
            1 => png::ColorType::Grayscale,
            3 => png::ColorType::Rgb,
            _ => png::ColorType::Rgba,
        });
        enc.set_depth(png::BitDepth::Eight);
        enc.set_compression(compression);
        let mut writer = enc.write_header().unwrap();
        writer.write_image_data(&samples).unwrap();
        writer.finish().unwrap();
        out
    }

    /// The `png` crate path gives the pixels of OpenCV's `imread(IMREAD_COLOR)`, byte for byte, for
    /// the layouts it takes (grey and RGB, the simulator's fast compression and the default one) and
    /// for those it leaves to OpenCV (RGBA); a checksum error is OpenCV's decode error.
    #[test]
    fn png_frames_decode_to_the_pixels_of_opencv() {
        let dir = tempfile::tempdir().unwrap();
        for (channels, compression, fast) in [
            (3, png::Compression::Fastest, true),
            (3, png::Compression::Balanced, true),
            (1, png::Compression::Fastest, true),
            (4, png::Compression::Fastest, false),
        ] {
            let path = dir.path().join(format!("{channels}-{compression:?}.png"));
            std::fs::write(&path, png_bytes(161, 53, channels, compression)).unwrap();
            assert_eq!(decode_png(&path).is_some(), fast, "{}", path.display());
            let ours = read_image(&path).unwrap();
            let opencv = imgcodecs::imread(&path, imgcodecs::IMREAD_COLOR).unwrap();
            assert_eq!(
                (ours.rows(), ours.cols(), ours.typ()),
                (53, 161, opencv::core::CV_8UC3)
            );
            assert_eq!(
                ours.data_bytes().unwrap(),
                opencv.data_bytes().unwrap(),
                "{}",
                path.display()
            );
        }
        // One flipped byte inside the image data: the crate refuses it and so does OpenCV.
        let mut bytes = png_bytes(161, 53, 3, png::Compression::Fastest);
        let at = bytes.len() / 2;
        bytes[at] ^= 0x40;
        let broken = dir.path().join("broken.png");
        std::fs::write(&broken, bytes).unwrap();
        assert!(decode_png(&broken).is_none());
        let err = read_image(&broken).unwrap_err().to_string();
        assert!(err.contains("broken.png"), "{err}");
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
