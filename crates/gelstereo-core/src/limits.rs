//! Resource limits: every number a user or a file gives that sizes threads, memory or recursion is
//! checked against one of these before work starts (docs/reliability.md lists them with the reasons).

/// Most worker or intra-op threads any command starts (`--threads`, `--workers`). More threads than
/// cores only add memory (each ONNX Runtime session and worker holds its own buffers) and contention.
pub const MAX_THREADS: usize = 256;

/// Longest side of an image read from a file, px: headers are read before decoding, so a huge image
/// is refused before its pixels are allocated.
pub const MAX_IMAGE_SIDE_PX: u64 = 16_384;

/// Most pixels of an image read from a file (64 megapixels: 192 MB as 8-bit BGR, about ten times
/// that through a localizer).
pub const MAX_IMAGE_PIXELS: u64 = 64 * 1024 * 1024;

/// Deepest nesting of sequences, maps or XML elements in a calibration file: tree parsers recurse
/// (or build and drop trees) once per level and overflow the stack on deep files, so the depth is
/// checked before the file is parsed. A stereo calibration needs 3 levels.
pub const MAX_CALIBRATION_DEPTH: usize = 32;

/// Largest calibration file read, bytes (a stereo calibration is a few kB).
pub const MAX_CALIBRATION_BYTES: u64 = 4 * 1024 * 1024;

/// Most inner corners along either side of a checkerboard (`--board`, `--checkerboard`): OpenCV's
/// detectors need several pixels per square, so even a 4K image holds boards far smaller; the
/// simulator allocates per corner and per pose.
pub const MAX_BOARD_CORNERS_PER_SIDE: u32 = 200;

/// Most markers along either side of a lattice (`--grid`, a recording's `meta.json`): every
/// tracking table is sized rows x cols, and a sensor with 8 px between markers in a 1920 px image
/// has 240.
pub const MAX_GRID_SIDE: u16 = 1000;

/// Largest JSON description read (a sensor file, a recording's `meta.json`, a dataset's
/// `dataset.json`): a sensor description is a few kB, a manifest of ten thousand experiments about
/// a megabyte.
pub const MAX_DESCRIPTION_BYTES: u64 = 16 * 1024 * 1024;

/// Most spurious detections `reconstruct --gt-dust` adds per view (a 23x23 sensor has 529 markers).
pub const MAX_GT_DUST: usize = 100_000;

/// Reads the text file `path`, refusing it (an `InvalidData` error) once it is past `max_bytes`,
/// before more is read, or when it is not UTF-8.
pub fn read_text_at_most(path: &std::path::Path, max_bytes: u64) -> std::io::Result<String> {
    use std::io::Read;
    let mut bytes = Vec::new();
    std::fs::File::open(path)?
        .take(max_bytes + 1)
        .read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max_bytes {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("larger than {max_bytes} bytes, more than such a file holds"),
        ));
    }
    String::from_utf8(bytes).map_err(|e| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "not UTF-8 text (an invalid byte at offset {})",
                e.utf8_error().valid_up_to()
            ),
        )
    })
}

/// Parses a thread or worker count for a command-line option: `0` (one per core) to [`MAX_THREADS`].
/// Usable directly as a clap `value_parser`.
pub fn parse_thread_count(text: &str) -> Result<usize, String> {
    let n: usize = text
        .trim()
        .parse()
        .map_err(|_| format!("'{text}': expected a whole number of threads, 0 to {MAX_THREADS}"))?;
    check_thread_count(n).map(|()| n)
}

/// Parses a whole number from 0 to `max` for a command-line option that sizes an allocation.
pub fn parse_count_at_most(text: &str, max: usize) -> Result<usize, String> {
    match text.trim().parse::<usize>() {
        Ok(n) if n <= max => Ok(n),
        _ => Err(format!("'{text}': expected a whole number from 0 to {max}")),
    }
}

/// Environment variables that size thread pools gelstereo starts or that its libraries read: rayon's
/// global pool, and OpenMP (OpenCV, ONNX Runtime, PyTorch in `adapt`).
pub const THREAD_ENV_VARS: [&str; 2] = ["RAYON_NUM_THREADS", "OMP_NUM_THREADS"];

/// Checks the thread counts of [`THREAD_ENV_VARS`] against [`MAX_THREADS`] before any pool reads
/// them: a huge count starts thousands of threads that load the machine and ignore signals. An
/// empty variable is ignored (as rayon does); OpenMP's nested form `4,2` is checked item by item.
pub fn check_thread_env() -> Result<(), String> {
    for name in THREAD_ENV_VARS {
        let Some(value) = std::env::var_os(name) else {
            continue;
        };
        let text = value.to_string_lossy();
        if text.trim().is_empty() {
            continue;
        }
        for item in text.split(',') {
            parse_thread_count(item).map_err(|e| {
                format!(
                    "environment variable {name}='{}': {e}; unset it or set a smaller count",
                    shorten(&text, ECHO_CHARS)
                )
            })?;
        }
    }
    Ok(())
}

/// Most characters of a user's text repeated in an error message; the rest is cut (a file or a
/// variable may hold megabytes in one string).
pub const ECHO_CHARS: usize = 80;

/// `text` cut to its first `max_chars` characters, with "..." and the full length when cut.
pub fn shorten(text: &str, max_chars: usize) -> std::borrow::Cow<'_, str> {
    match text.char_indices().nth(max_chars) {
        None => std::borrow::Cow::Borrowed(text),
        Some((end, _)) => std::borrow::Cow::Owned(format!(
            "{}... ({} characters in all)",
            &text[..end],
            text.chars().count()
        )),
    }
}

/// Parses a finite number from `lo` to `hi` for a command-line option (NaN and infinities are
/// refused: they pass every comparison-free path silently).
pub fn parse_number_in(text: &str, lo: f64, hi: f64) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && (lo..=hi).contains(&v) => Ok(v),
        _ => Err(format!(
            "'{}': expected a number from {lo} to {hi}",
            shorten(text, ECHO_CHARS)
        )),
    }
}

/// Checks a thread or worker count (0 means one per core) against [`MAX_THREADS`].
pub fn check_thread_count(n: usize) -> Result<(), String> {
    if n > MAX_THREADS {
        return Err(format!("{n} threads: expected 0 (one per core) to {MAX_THREADS}"));
    }
    Ok(())
}

/// Checks an image's dimensions against [`MAX_IMAGE_SIDE_PX`] and [`MAX_IMAGE_PIXELS`]; the error
/// says what was found and what is allowed.
pub fn check_image_dimensions(width: u64, height: u64) -> Result<(), String> {
    if width > MAX_IMAGE_SIDE_PX || height > MAX_IMAGE_SIDE_PX || width * height > MAX_IMAGE_PIXELS {
        return Err(format!(
            "{width}x{height} px: larger than gelstereo reads (at most {MAX_IMAGE_SIDE_PX} px a side \
             and {} megapixels)",
            MAX_IMAGE_PIXELS / (1024 * 1024)
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thread_counts_are_bounded_and_named() {
        assert_eq!(parse_thread_count("0"), Ok(0));
        assert_eq!(parse_thread_count("256"), Ok(256));
        let err = parse_thread_count("100000").unwrap_err();
        assert!(err.contains("100000") && err.contains("256"), "{err}");
        assert!(parse_thread_count("-1").is_err());
        assert!(parse_thread_count("lots").is_err());
        assert_eq!(parse_count_at_most("7", 7), Ok(7));
        let err = parse_count_at_most("1e10", MAX_GT_DUST).unwrap_err();
        assert!(err.contains("1e10") && err.contains("100000"), "{err}");
    }

    #[test]
    fn numbers_are_finite_and_in_range() {
        assert_eq!(parse_number_in("0.5", 0.0, 1.0), Ok(0.5));
        assert_eq!(parse_number_in("1", 0.0, 1.0), Ok(1.0));
        for bad in ["2", "-0.1", "NaN", "nan", "inf", "x", ""] {
            let err = parse_number_in(bad, 0.0, 1.0).unwrap_err();
            assert!(err.contains("from 0 to 1"), "{bad}: {err}");
        }
    }

    #[test]
    fn long_text_is_cut_short() {
        assert_eq!(shorten("abc", 3), "abc");
        assert_eq!(shorten("abcd", 3), "abc... (4 characters in all)");
        let long = "é".repeat(1_000_000);
        let cut = shorten(&long, ECHO_CHARS);
        assert!(cut.len() < 200 && cut.contains("1000000 characters"), "{cut}");
    }

    #[test]
    fn image_dimensions_are_bounded() {
        assert!(check_image_dimensions(640, 480).is_ok());
        assert!(check_image_dimensions(8192, 8192).is_ok());
        let err = check_image_dimensions(20_000, 20_000).unwrap_err();
        assert!(err.contains("20000x20000"), "{err}");
        assert!(check_image_dimensions(16_384, 4_096).is_ok());
        assert!(check_image_dimensions(16_384, 4_097).is_err());
        assert!(check_image_dimensions(16_385, 1).is_err());
    }
}
