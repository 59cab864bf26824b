//! What is checked in a calibration file before it is parsed: its size ([`MAX_CALIBRATION_BYTES`])
//! and the nesting depth of its sequences, maps and XML elements ([`MAX_CALIBRATION_DEPTH`]). Tree
//! parsers recurse (or build and drop trees) once per level, so a file nested tens of thousands deep
//! would overflow the stack (an abort no error handling can catch).
//!
//! The depth is counted conservatively: YAML flow brackets (`[`, `{`) outside quotes and comments,
//! plus the block levels opened by deeper indentation or `- ` sequence entries; XML elements that are
//! opened and not yet closed.

use std::io::Read;
use std::path::Path;

use gelstereo_core::limits::{MAX_CALIBRATION_BYTES, MAX_CALIBRATION_DEPTH};

use crate::error::{Error, Result};

/// A calibration file's text, read and checked by [`read_calibration_file`].
pub(crate) struct CheckedText {
    /// The text (invalid UTF-8 replaced, so a parser reports it where it is).
    pub text: String,
    /// XML (extension `.xml` or text starting with `<`), YAML otherwise.
    pub xml: bool,
}

/// Reads `path` (at most [`MAX_CALIBRATION_BYTES`]) and checks its nesting depth.
pub(crate) fn read_calibration_file(path: &Path) -> Result<CheckedText> {
    let bytes = read_at_most(path)?;
    if let Some(at) = bytes.iter().position(|&b| b == 0) {
        let line = 1 + bytes[..at].iter().filter(|&&b| b == b'\n').count();
        return Err(syntax(
            path,
            line,
            format!("binary data (a NUL byte at offset {at}): expected a text file, OpenCV YAML or XML"),
        ));
    }
    let text = String::from_utf8_lossy(&bytes).into_owned();
    let is_xml =
        path.extension().is_some_and(|e| e.eq_ignore_ascii_case("xml")) || text.trim_start().starts_with('<');
    let deepest = if is_xml {
        xml_depth(&text)
    } else {
        yaml_depth(&text)
    };
    match deepest {
        Some((depth, line)) if depth > MAX_CALIBRATION_DEPTH => Err(syntax(
            path,
            line,
            format!(
                "nested {depth} levels deep or more: expected at most {MAX_CALIBRATION_DEPTH} \
                 (a stereo calibration needs 3)"
            ),
        )),
        _ => Ok(CheckedText { text, xml: is_xml }),
    }
}

/// The bytes of the calibration file `path` (an OpenCV file or a mrcal `.cameramodel`), refused
/// past [`MAX_CALIBRATION_BYTES`] before more is read.
pub(crate) fn read_at_most(path: &Path) -> Result<Vec<u8>> {
    let io = |source| Error::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let mut bytes = Vec::new();
    file.take(MAX_CALIBRATION_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() as u64 > MAX_CALIBRATION_BYTES {
        return Err(syntax(
            path,
            0,
            format!("larger than {MAX_CALIBRATION_BYTES} bytes: not a calibration file"),
        ));
    }
    Ok(bytes)
}

/// A syntax error of the calibration file `path` at 1-based `line` (0 when unknown).
pub(crate) fn syntax(path: &Path, line: usize, message: impl Into<String>) -> Error {
    Error::Syntax {
        path: path.to_path_buf(),
        line,
        message: message.into(),
    }
}

/// The deepest YAML nesting and its 1-based line, stopping once past the limit.
pub(crate) fn yaml_depth(text: &str) -> Option<(usize, usize)> {
    let mut deepest: Option<(usize, usize)> = None;
    let mut indents: Vec<usize> = Vec::new();
    let mut flow = 0usize;
    for (k, line) in text.lines().enumerate() {
        let line_no = k + 1;
        let content = line.trim_start_matches([' ', '\t']);
        if content.is_empty() || content.starts_with('#') {
            continue;
        }
        let mut column = line.len() - content.len();
        let mut rest = content;
        if flow == 0 {
            while indents.last().is_some_and(|&top| top >= column) {
                indents.pop();
            }
            indents.push(column);
            // Block sequence entries on one line (`- - - x`) each open a level.
            while let Some(after) = rest
                .strip_prefix('-')
                .filter(|a| a.is_empty() || a.starts_with([' ', '\t']))
            {
                let trimmed = after.trim_start_matches([' ', '\t']);
                column += rest.len() - trimmed.len();
                indents.push(column);
                rest = trimmed;
            }
        }
        let mut quote: Option<char> = None;
        let mut previous = ' ';
        for c in rest.chars() {
            match (quote, c) {
                (Some(q), c) if c == q => quote = None,
                (Some(_), _) => {}
                (None, '\'' | '"') => quote = Some(c),
                (None, '#') if previous == ' ' || previous == '\t' => break,
                (None, '[' | '{') => {
                    flow += 1;
                    note(&mut deepest, indents.len() + flow, line_no);
                }
                (None, ']' | '}') => flow = flow.saturating_sub(1),
                _ => {}
            }
            previous = c;
        }
        note(&mut deepest, indents.len() + flow, line_no);
        if deepest.is_some_and(|(d, _)| d > MAX_CALIBRATION_DEPTH) {
            break;
        }
    }
    deepest
}

/// The deepest XML element nesting and its 1-based line, stopping once past the limit.
pub(crate) fn xml_depth(text: &str) -> Option<(usize, usize)> {
    let bytes = text.as_bytes();
    let mut deepest: Option<(usize, usize)> = None;
    let mut depth = 0usize;
    let mut line = 1usize;
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'\n' => line += 1,
            b'<' => {
                let rest = &bytes[i + 1..];
                let close = |pattern: &[u8]| {
                    rest.windows(pattern.len())
                        .position(|w| w == pattern)
                        .map_or(bytes.len(), |p| i + 1 + p + pattern.len())
                };
                let end = if rest.starts_with(b"!--") {
                    close(b"-->")
                } else {
                    close(b">")
                };
                let tag = &bytes[i..end.min(bytes.len())];
                line += tag.iter().filter(|&&b| b == b'\n').count();
                if rest.starts_with(b"/") {
                    depth = depth.saturating_sub(1);
                } else if !(rest.starts_with(b"?") || rest.starts_with(b"!") || tag.ends_with(b"/>")) {
                    depth += 1;
                    note(&mut deepest, depth, line);
                    if depth > MAX_CALIBRATION_DEPTH {
                        break;
                    }
                }
                i = end;
                continue;
            }
            _ => {}
        }
        i += 1;
    }
    deepest
}

fn note(deepest: &mut Option<(usize, usize)>, depth: usize, line: usize) {
    if deepest.is_none_or(|(d, _)| depth > d) {
        *deepest = Some((depth, line));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_of_ordinary_calibrations_is_small() {
        let yaml = "%YAML:1.0\n---\nK1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 2.,\n       0., 1., 3., 0., 0., 1. ]\nimage_width: 640\n";
        let (d, _) = yaml_depth(yaml).unwrap();
        assert!(d <= 3, "{d}");
        let xml = "<?xml version=\"1.0\"?>\n<opencv_storage>\n<K1 type_id=\"opencv-matrix\">\n  <rows>3</rows>\n  <data>1 0 2 0 1 3 0 0 1</data></K1>\n<empty/>\n<!-- a <comment> -->\n</opencv_storage>\n";
        assert_eq!(xml_depth(xml), Some((3, 4)));
    }

    #[test]
    fn deep_nesting_is_measured_in_every_syntax() {
        let flow = format!("K1: {}{}\n", "[".repeat(50_000), "]".repeat(50_000));
        assert!(yaml_depth(&flow).unwrap().0 > MAX_CALIBRATION_DEPTH);
        let dashes = format!("K1: \n{}1\n", "- ".repeat(1_000));
        assert!(yaml_depth(&dashes).unwrap().0 > MAX_CALIBRATION_DEPTH);
        let indented: String = (0..100).map(|k| format!("{}a{k}:\n", " ".repeat(k))).collect();
        assert!(yaml_depth(&indented).unwrap().0 > MAX_CALIBRATION_DEPTH);
        let xml = format!(
            "<opencv_storage>{}{}</opencv_storage>",
            "<a>".repeat(50_000),
            "</a>".repeat(50_000)
        );
        assert!(xml_depth(&xml).unwrap().0 > MAX_CALIBRATION_DEPTH);
        // Quoted and commented brackets do not count.
        assert!(
            yaml_depth(&format!("name: \"{}\" # {}\n", "[".repeat(100), "{".repeat(100)))
                .unwrap()
                .0
                <= 2
        );
    }
}
