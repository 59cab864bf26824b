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

/// Most spurious detections `reconstruct --gt-dust` adds per view (a 23x23 sensor has 529 markers).
pub const MAX_GT_DUST: usize = 100_000;

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
