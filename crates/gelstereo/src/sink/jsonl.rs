//! The frame stream, `gelstereo track --jsonl`: one JSON object per frame and line, described by
//! the JSON Schema `docs/schema/frame-v1.json` and named in every line's `schema` field.
//!
//! A line holds the `frames.csv` columns, then `markers`: one array per `markers.csv` column
//! (`frame` aside), each in marker order. Column arrays name each column once per frame instead of
//! once per marker, and numbers keep the decimals the measurement supports, so a frame of a
//! 23 x 23 lattice stays a few tens of kB.

use std::io::Write;

use gelstereo_core::MarkerRecord;

use crate::{Error, FrameOutput, Result};

/// The `schema` field of every line: the schema's name and major version. A reader that knows
/// version 1 reads every line that names it; a change that would break such a reader names 2.
pub const FRAME_SCHEMA: &str = "gelstereo-frame/1";

/// Pixels: a hundredth of a pixel, below the frame-to-frame jitter of a tracked marker.
const PX_DECIMALS: usize = 2;
/// A marker's position and displacement, mm: one micrometre, at the stereo noise of a still gel.
const MARKER_MM_DECIMALS: usize = 3;
/// Pressure, kPa.
const KPA_DECIMALS: usize = 2;
/// A frame's depth and centroid, mm (a few numbers per frame: one digit beyond the markers').
const FRAME_MM_DECIMALS: usize = 4;
/// Contact area, mm².
const AREA_DECIMALS: usize = 3;
/// Force, N, and torque, N mm.
const FORCE_DECIMALS: usize = 4;
/// Time, s, as in `frames.csv`.
const TIME_DECIMALS: usize = 6;

/// One JSON value of a line.
enum Cell {
    Int(u32),
    Num(Option<f64>, usize),
    Word(Option<&'static str>),
    Flag(Option<bool>),
}

type MarkerField = (&'static str, fn(&MarkerRecord) -> Cell);

/// `markers.csv`'s columns after `frame`, in its order, and how each is read from a marker.
const MARKER_FIELDS: [MarkerField; 22] = [
    ("row", |m| Cell::Int(u32::from(m.index.row))),
    ("col", |m| Cell::Int(u32::from(m.index.col))),
    ("x_left", |m| px(m.left_px.map(|p| p.x))),
    ("y_left", |m| px(m.left_px.map(|p| p.y))),
    ("x_right", |m| px(m.right_px.map(|p| p.x))),
    ("y_right", |m| px(m.right_px.map(|p| p.y))),
    ("X_mm", |m| mm(m.position_mm, 0)),
    ("Y_mm", |m| mm(m.position_mm, 1)),
    ("Z_mm", |m| mm(m.position_mm, 2)),
    ("dX_mm", |m| mm(m.displacement_mm, 0)),
    ("dY_mm", |m| mm(m.displacement_mm, 1)),
    ("dZ_mm", |m| mm(m.displacement_mm, 2)),
    ("status", |m| Cell::Word(m.status.map(|s| s.as_str()))),
    ("pressure_kPa", |m| Cell::Num(m.pressure_kpa, KPA_DECIMALS)),
    ("in_contact", |m| Cell::Flag(m.in_contact)),
    ("slipping", |m| Cell::Flag(m.slipping)),
    ("X_gel_mm", |m| mm(m.gel_position_mm, 0)),
    ("Y_gel_mm", |m| mm(m.gel_position_mm, 1)),
    ("Z_gel_mm", |m| mm(m.gel_position_mm, 2)),
    ("dX_gel_mm", |m| mm(m.gel_displacement_mm, 0)),
    ("dY_gel_mm", |m| mm(m.gel_displacement_mm, 1)),
    ("dZ_gel_mm", |m| mm(m.gel_displacement_mm, 2)),
];

fn px(v: Option<f64>) -> Cell {
    Cell::Num(v, PX_DECIMALS)
}

fn mm(v: Option<[f64; 3]>, k: usize) -> Cell {
    Cell::Num(v.map(|v| v[k]), MARKER_MM_DECIMALS)
}

/// The line of one frame (no newline), valid against `docs/schema/frame-v1.json`.
pub fn frame_line(out: &FrameOutput) -> String {
    let s = &out.summary;
    // An unmeasured frame's contact is unknown: null, as its empty cells in frames.csv.
    let known = |v: Option<f64>| v.filter(|_| s.measured);
    let n = |v: Option<f64>, decimals| Cell::Num(known(v), decimals);
    let fields = [
        ("frame", Cell::Int(out.frame)),
        ("t_s", Cell::Num(Some(out.t_s), TIME_DECIMALS)),
        ("contact", Cell::Flag(s.measured.then_some(s.contact))),
        ("contact_area_mm2", n(s.contact_area_mm2, AREA_DECIMALS)),
        ("max_depth_mm", n(s.max_depth_mm, FRAME_MM_DECIMALS)),
        ("centroid_X_mm", n(s.centroid_mm.map(|c| c[0]), FRAME_MM_DECIMALS)),
        ("centroid_Y_mm", n(s.centroid_mm.map(|c| c[1]), FRAME_MM_DECIMALS)),
        ("slip", Cell::Word(s.measured.then_some(s.slip.as_str()))),
        ("force_N", n(s.force_n, FORCE_DECIMALS)),
        ("shear_x_N", n(s.shear_n.map(|v| v[0]), FORCE_DECIMALS)),
        ("shear_y_N", n(s.shear_n.map(|v| v[1]), FORCE_DECIMALS)),
        ("torque_Nmm", n(s.torque_nmm, FORCE_DECIMALS)),
    ];
    let mut line = String::with_capacity(64 + out.markers.len() * 128);
    line.push('{');
    push_key(&mut line, "schema");
    push_text(&mut line, Some(FRAME_SCHEMA));
    for (name, cell) in &fields {
        push_key(&mut line, name);
        push_cell(&mut line, cell);
    }
    push_key(&mut line, "note");
    push_text(&mut line, out.note.as_deref());
    push_key(&mut line, "markers");
    line.push('{');
    for (name, field) in MARKER_FIELDS {
        push_key(&mut line, name);
        line.push('[');
        for (k, m) in out.markers.iter().enumerate() {
            if k > 0 {
                line.push(',');
            }
            push_cell(&mut line, &field(m));
        }
        line.push(']');
    }
    line.push_str("}}");
    line
}

/// `"name":`, after a comma unless it opens its object.
fn push_key(line: &mut String, name: &str) {
    if !line.ends_with('{') {
        line.push(',');
    }
    line.push('"');
    line.push_str(name);
    line.push_str("\":");
}

fn push_cell(line: &mut String, cell: &Cell) {
    match *cell {
        Cell::Int(v) => line.push_str(&v.to_string()),
        Cell::Num(v, decimals) => push_number(line, v, decimals),
        Cell::Word(w) => push_text(line, w),
        Cell::Flag(None) => line.push_str("null"),
        Cell::Flag(Some(f)) => line.push_str(if f { "true" } else { "false" }),
    }
}

/// `v` rounded to `decimals`, without trailing zeros (`1.5`, `0`, `-0.012`); `null` for a missing
/// or non-finite value, which JSON cannot hold.
fn push_number(line: &mut String, v: Option<f64>, decimals: usize) {
    let Some(v) = v.filter(|v| v.is_finite()) else {
        line.push_str("null");
        return;
    };
    let text = format!("{v:.decimals$}");
    let text = match text.contains('.') {
        true => text.trim_end_matches('0').trim_end_matches('.'),
        false => &text,
    };
    line.push_str(if text == "-0" { "0" } else { text });
}

/// A JSON string (escaped), or `null`.
fn push_text(line: &mut String, text: Option<&str>) {
    match text {
        Some(t) => line.push_str(&serde_json::Value::from(t).to_string()),
        None => line.push_str("null"),
    }
}

/// Writes [`frame_line`]s to a writer, flushed per frame. A reader that closes the stream (`| head
/// -1`) ends it: the write fails with [`Error::ReaderClosed`], which [`crate::track::run`] takes
/// as the end of the run.
pub struct JsonlSink<W: Write> {
    out: W,
    /// What `out` is, for errors: its path, or `standard output`.
    name: std::path::PathBuf,
}

impl<W: Write> JsonlSink<W> {
    /// Writes to `out` (standard output, a file, a named pipe...), called `name` in errors.
    pub fn new(out: W, name: &std::path::Path) -> Self {
        Self {
            out,
            name: name.to_path_buf(),
        }
    }
}

impl<W: Write> super::Sink for JsonlSink<W> {
    fn frame(&mut self, frame: &super::FrameContext) -> Result<()> {
        let mut line = frame_line(frame.output);
        line.push('\n');
        self.out
            .write_all(line.as_bytes())
            .and_then(|()| self.out.flush())
            .map_err(|source| match source.kind() {
                std::io::ErrorKind::BrokenPipe => Error::ReaderClosed {
                    name: self.name.clone(),
                },
                _ => Error::File {
                    path: self.name.clone(),
                    source,
                },
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use gelstereo_core::table::MARKER_COLUMNS;

    #[test]
    fn marker_arrays_are_the_marker_table_columns_after_frame() {
        let names: Vec<&str> = MARKER_FIELDS.iter().map(|(n, _)| *n).collect();
        assert_eq!(names, MARKER_COLUMNS[1..]);
    }

    #[test]
    fn numbers_are_rounded_without_trailing_zeros() {
        let cases = [
            (Some(1.23456), 3, "1.235"),
            (Some(1.5), 3, "1.5"),
            (Some(2.0), 2, "2"),
            (Some(-0.0001), 3, "0"),
            (Some(-0.0126), 2, "-0.01"),
            (Some(120.0), 0, "120"),
            (Some(f64::NAN), 2, "null"),
            (None, 2, "null"),
        ];
        for (v, decimals, expected) in cases {
            let mut line = String::new();
            push_number(&mut line, v, decimals);
            assert_eq!(line, expected, "{v:?} to {decimals} decimals");
        }
    }

    #[test]
    fn notes_are_escaped() {
        let mut line = String::new();
        push_text(&mut line, Some("cannot read \"a\\b\"\nnext"));
        let back: String = serde_json::from_str(&line).unwrap();
        assert_eq!(back, "cannot read \"a\\b\"\nnext");
    }
}
