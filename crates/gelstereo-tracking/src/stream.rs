//! The frame stream, `gelstereo track --jsonl`: one JSON object per frame and line, described by
//! the JSON Schema `docs/schema/frame-v1.json` and named in every line's `schema` field: the
//! per-frame rows of a session ([`MarkerRecord`]s, [`FrameSummary`]) and the gel frame, written by
//! [`frame_line`] and read back by [`parse_frame_line`] into a [`StreamFrame`].
//!
//! A line holds the `frames.csv` columns, the gel frame (`gel`: its origin and axes in the left
//! camera frame), then `markers`:
//! - one array per per-marker number, in marker order (row-major lattice ids): `row`, `col`, the
//!   pixel positions, the 3-D positions and displacements in the gel frame in integer micrometres
//!   (`X_gel_um` ...), and `pressure_kPa`;
//! - the few markers that differ from the rest as lists of their indices into those arrays:
//!   `predicted` and `lost` (every other marker is tracked), `in_contact` and `slipping` (`null`
//!   when the frame's contact is unknown).
//!
//! The camera-frame positions of `markers.csv` are not repeated: they are the gel-frame ones
//! through `gel`, which the reader applies. Each number keeps the decimals its measurement
//! supports and no more, so a frame of a 23 x 23 lattice stays under 40 kB.

use std::io::{BufRead, Read};

use gelstereo_core::{FrameSummary, GridIndex, MarkerRecord, MarkerStatus, Point2, SlipState};
use nalgebra::{Point3, Vector3};
use serde_json::Value;

use crate::{Error, GelFrame, Result};

/// The `schema` field of every line: the schema's name and major version. A reader that knows
/// version 1 reads every line that names it; a change that would break such a reader names 2.
pub const FRAME_SCHEMA: &str = "gelstereo-frame/1";

/// Pixels: a hundredth of a pixel, below the frame-to-frame jitter of a tracked marker.
const PX_DECIMALS: usize = 2;
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
/// The gel frame's origin, mm: a tenth of a micrometre, below the markers' micrometre.
const ORIGIN_DECIMALS: usize = 4;
/// The gel frame's axes (unit vectors): a turn of 1e-7 rad moves a point 30 mm away by 3 nm.
const AXIS_DECIMALS: usize = 7;

/// The longest line [`read_frames`] reads (a 23 x 23 frame is a few tens of kB; this allows a
/// lattice of a hundred times as many markers).
pub const MAX_LINE_BYTES: u64 = 16 * 1024 * 1024;

/// One frame as a line of the stream holds it.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamFrame {
    /// Frame number, from 0.
    pub frame: u32,
    /// Seconds from the first frame.
    pub t_s: f64,
    /// The `frames.csv` row.
    pub summary: FrameSummary,
    /// The `markers.csv` rows, in id order (row-major).
    pub markers: Vec<MarkerRecord>,
    /// Why the frame is flagged; `None` for a frame processed normally.
    pub note: Option<String>,
    /// The gel frame; `None` for a mono sensor or before the reference frame.
    pub gel: Option<GelFrame>,
}

/// One JSON value of a line.
enum Cell {
    Int(u32),
    Num(Option<f64>, usize),
    Word(Option<&'static str>),
    Flag(Option<bool>),
}

type MarkerField = (&'static str, fn(&MarkerRecord) -> Cell);

/// The per-marker number arrays, in their order in a line.
const MARKER_ARRAYS: [MarkerField; 13] = [
    ("row", |m| Cell::Int(u32::from(m.index.row))),
    ("col", |m| Cell::Int(u32::from(m.index.col))),
    ("x_left", |m| px(m.left_px.map(|p| p.x))),
    ("y_left", |m| px(m.left_px.map(|p| p.y))),
    ("x_right", |m| px(m.right_px.map(|p| p.x))),
    ("y_right", |m| px(m.right_px.map(|p| p.y))),
    ("X_gel_um", |m| um(m.gel_position_mm, 0)),
    ("Y_gel_um", |m| um(m.gel_position_mm, 1)),
    ("Z_gel_um", |m| um(m.gel_position_mm, 2)),
    ("dX_gel_um", |m| um(m.gel_displacement_mm, 0)),
    ("dY_gel_um", |m| um(m.gel_displacement_mm, 1)),
    ("dZ_gel_um", |m| um(m.gel_displacement_mm, 2)),
    ("pressure_kPa", |m| Cell::Num(m.pressure_kpa, KPA_DECIMALS)),
];

type MarkerSet = (&'static str, fn(&MarkerRecord) -> Option<bool>);

/// The per-marker index lists: the markers for which the test holds. `in_contact` and
/// `slipping` are `null` when no marker's value is known (a flagged frame, a mono sensor).
const MARKER_SETS: [MarkerSet; 4] = [
    ("predicted", |m| Some(m.status == Some(MarkerStatus::Predicted))),
    ("lost", |m| Some(m.status == Some(MarkerStatus::Lost))),
    ("in_contact", |m| m.in_contact),
    ("slipping", |m| m.slipping),
];

fn px(v: Option<f64>) -> Cell {
    Cell::Num(v, PX_DECIMALS)
}

/// A gel-frame coordinate, mm, as integer micrometres: the stereo noise of a still gel.
fn um(v: Option<[f64; 3]>, k: usize) -> Cell {
    Cell::Num(v.map(|v| 1000.0 * v[k]), 0)
}

/// The line of one frame (no newline), valid against `docs/schema/frame-v1.json`: its number, time,
/// summary, marker rows and note, and the gel frame (`None` for a mono sensor or before the
/// reference frame).
pub fn frame_line(
    frame: u32,
    t_s: f64,
    summary: &FrameSummary,
    markers: &[MarkerRecord],
    note: Option<&str>,
    gel: Option<&GelFrame>,
) -> String {
    let s = summary;
    // An unmeasured frame's contact is unknown: null, as its empty cells in frames.csv.
    let known = |v: Option<f64>| v.filter(|_| s.measured);
    let n = |v: Option<f64>, decimals| Cell::Num(known(v), decimals);
    let fields = [
        ("frame", Cell::Int(frame)),
        ("t_s", Cell::Num(Some(t_s), TIME_DECIMALS)),
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
    let mut line = String::with_capacity(256 + markers.len() * 72);
    line.push('{');
    push_key(&mut line, "schema");
    push_text(&mut line, Some(FRAME_SCHEMA));
    for (name, cell) in &fields {
        push_key(&mut line, name);
        push_cell(&mut line, cell);
    }
    push_key(&mut line, "note");
    push_text(&mut line, note);
    push_key(&mut line, "gel");
    push_gel(&mut line, gel);
    push_key(&mut line, "markers");
    line.push('{');
    for (name, field) in MARKER_ARRAYS {
        push_key(&mut line, name);
        push_list(&mut line, markers.iter().map(field));
    }
    for (name, test) in MARKER_SETS {
        push_key(&mut line, name);
        if markers.iter().all(|m| test(m).is_none()) {
            line.push_str("null");
        } else {
            let members = markers.iter().enumerate();
            let indices = members.filter(|(_, m)| test(m) == Some(true));
            push_list(&mut line, indices.map(|(k, _)| Cell::Int(k as u32)));
        }
    }
    line.push_str("}}");
    line
}

/// `{"origin_mm":[x,y,z],"axes":[[..],[..],[..]]}`, or `null`.
fn push_gel(line: &mut String, gel: Option<&GelFrame>) {
    let Some(gel) = gel else {
        line.push_str("null");
        return;
    };
    line.push('{');
    push_key(line, "origin_mm");
    push_list(
        line,
        gel.origin_mm.iter().map(|v| Cell::Num(Some(*v), ORIGIN_DECIMALS)),
    );
    push_key(line, "axes");
    line.push('[');
    for (k, axis) in gel.axes.iter().enumerate() {
        if k > 0 {
            line.push(',');
        }
        push_list(line, axis.iter().map(|v| Cell::Num(Some(*v), AXIS_DECIMALS)));
    }
    line.push_str("]}");
}

fn push_list(line: &mut String, cells: impl Iterator<Item = Cell>) {
    line.push('[');
    for (k, cell) in cells.enumerate() {
        if k > 0 {
            line.push(',');
        }
        push_cell(line, &cell);
    }
    line.push(']');
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

/// Reads one line of the stream back into the frame it was written from. The camera-frame
/// positions and displacements are the gel-frame ones through the line's gel frame (so they agree
/// with `markers.csv` to about a micrometre); the read gel frame's marker pitch, which the stream
/// does not carry, is NaN. `name` (the stream and line) starts every error, which names the field
/// and what was expected.
pub fn parse_frame_line(line: &str, name: &str) -> Result<StreamFrame> {
    let v: Value = serde_json::from_str(line)
        .map_err(|e| Error::Stream(format!("{name}: expected a JSON object: {e}")))?;
    let fields = Fields { v: &v, name };
    let schema = fields.get("schema")?;
    if schema.as_str() != Some(FRAME_SCHEMA) {
        return Err(fields.bad("schema", &format!("\"{FRAME_SCHEMA}\""), schema));
    }
    let gel = fields.gel()?;
    let frame = fields.integer(&v, "frame", u32::MAX.into())? as u32;
    let summary = fields.summary(frame)?;
    let markers = fields.markers(frame, gel.as_ref())?;
    let note = match fields.get("note")? {
        Value::Null => None,
        Value::String(t) => Some(t.clone()),
        other => return Err(fields.bad("note", "a string or null", other)),
    };
    let t_s = fields
        .number(&v, "t_s")?
        .ok_or_else(|| fields.bad("t_s", "a number", &Value::Null))?;
    Ok(StreamFrame {
        frame,
        t_s,
        summary,
        markers,
        note,
        gel,
    })
}

/// Reads a whole stream: one [`parse_frame_line`] per non-blank line, named `name:LINE` in errors.
/// A line longer than [`MAX_LINE_BYTES`] is an error before it is held in memory whole.
pub fn read_frames<R: BufRead>(reader: R, name: &str) -> impl Iterator<Item = Result<StreamFrame>> + use<R> {
    let name = name.to_owned();
    let mut reader = reader;
    let mut number = 0usize;
    std::iter::from_fn(move || {
        loop {
            number += 1;
            let mut line = String::new();
            let read = reader.by_ref().take(MAX_LINE_BYTES + 1).read_line(&mut line);
            let at = format!("{name}:{number}");
            match read {
                Err(e) => return Some(Err(Error::Stream(format!("{at}: cannot read: {e}")))),
                Ok(0) => return None,
                Ok(n) if n as u64 > MAX_LINE_BYTES => {
                    return Some(Err(Error::Stream(format!(
                        "{at}: expected a line of at most {MAX_LINE_BYTES} bytes"
                    ))));
                }
                Ok(_) if line.trim().is_empty() => continue,
                Ok(_) => return Some(parse_frame_line(line.trim_end(), &at)),
            }
        }
    })
}

/// The fields of one parsed line, with errors that name the line and the field.
struct Fields<'a> {
    v: &'a Value,
    name: &'a str,
}

impl Fields<'_> {
    fn bad(&self, field: &str, expected: &str, found: &Value) -> Error {
        let found = found.to_string();
        let found = gelstereo_core::limits::shorten(&found, gelstereo_core::limits::ECHO_CHARS);
        Error::Stream(format!(
            "{}: {field}: expected {expected}, found {found}",
            self.name
        ))
    }

    fn get(&self, field: &str) -> Result<&Value> {
        self.v
            .get(field)
            .ok_or_else(|| Error::Stream(format!("{}: {field}: missing", self.name)))
    }

    /// `object[field]`: a finite number or null.
    fn number(&self, object: &Value, field: &str) -> Result<Option<f64>> {
        match object.get(field) {
            None => Err(Error::Stream(format!("{}: {field}: missing", self.name))),
            Some(Value::Null) => Ok(None),
            Some(n) => match n.as_f64().filter(|x| x.is_finite()) {
                Some(x) => Ok(Some(x)),
                None => Err(self.bad(field, "a number or null", n)),
            },
        }
    }

    /// `object[field]`: an integer from 0 to `max`.
    fn integer(&self, object: &Value, field: &str, max: u64) -> Result<u64> {
        let n = object
            .get(field)
            .ok_or_else(|| Error::Stream(format!("{}: {field}: missing", self.name)))?;
        n.as_u64()
            .filter(|x| *x <= max)
            .ok_or_else(|| self.bad(field, &format!("an integer from 0 to {max}"), n))
    }

    fn summary(&self, frame: u32) -> Result<FrameSummary> {
        let v = self.v;
        let contact = match self.get("contact")? {
            Value::Null => None,
            Value::Bool(b) => Some(*b),
            other => return Err(self.bad("contact", "true, false or null", other)),
        };
        let pair = |a: &str, b: &str| -> Result<Option<[f64; 2]>> {
            Ok(match (self.number(v, a)?, self.number(v, b)?) {
                (Some(x), Some(y)) => Some([x, y]),
                _ => None,
            })
        };
        let slip = match self.get("slip")? {
            Value::Null => SlipState::NoContact,
            Value::String(word) => word.parse().map_err(|_| {
                self.bad(
                    "slip",
                    "a slip state (no_contact, stick, partial_slip, gross_slip)",
                    &v["slip"],
                )
            })?,
            other => return Err(self.bad("slip", "a string or null", other)),
        };
        Ok(FrameSummary {
            frame,
            contact: contact.unwrap_or(false),
            contact_area_mm2: self.number(v, "contact_area_mm2")?,
            max_depth_mm: self.number(v, "max_depth_mm")?,
            centroid_mm: pair("centroid_X_mm", "centroid_Y_mm")?,
            slip,
            force_n: self.number(v, "force_N")?,
            shear_n: pair("shear_x_N", "shear_y_N")?,
            torque_nmm: self.number(v, "torque_Nmm")?,
            measured: contact.is_some(),
        })
    }

    fn gel(&self) -> Result<Option<GelFrame>> {
        let gel = self.get("gel")?;
        if gel.is_null() {
            return Ok(None);
        }
        let triple = |v: Option<&Value>, what: &str| -> Result<Vector3<f64>> {
            let found = v.unwrap_or(&Value::Null);
            let numbers: Option<Vec<f64>> = found
                .as_array()
                .filter(|a| a.len() == 3)
                .and_then(|a| a.iter().map(|x| x.as_f64().filter(|x| x.is_finite())).collect());
            numbers
                .map(|n| Vector3::new(n[0], n[1], n[2]))
                .ok_or_else(|| self.bad(what, "3 numbers", found))
        };
        let origin = triple(gel.get("origin_mm"), "gel.origin_mm")?;
        let axes = gel.get("axes").and_then(Value::as_array).filter(|a| a.len() == 3);
        let axes = axes.ok_or_else(|| self.bad("gel.axes", "3 axes of 3 numbers", gel))?;
        let axes = [
            triple(axes.first(), "gel.axes")?,
            triple(axes.get(1), "gel.axes")?,
            triple(axes.get(2), "gel.axes")?,
        ];
        for axis in &axes {
            if (axis.norm() - 1.0).abs() > 1e-4 {
                return Err(self.bad("gel.axes", "unit vectors", &gel["axes"]));
            }
        }
        Ok(Some(GelFrame {
            origin_mm: Point3::from(origin),
            axes,
            pitch_mm: f64::NAN,
        }))
    }

    fn markers(&self, frame: u32, gel: Option<&GelFrame>) -> Result<Vec<MarkerRecord>> {
        let markers = self.get("markers")?;
        let count = markers.get("row").and_then(Value::as_array).map_or(0, Vec::len);
        let mut arrays = Vec::with_capacity(MARKER_ARRAYS.len());
        for (field, _) in MARKER_ARRAYS {
            let found = markers.get(field).unwrap_or(&Value::Null);
            match found.as_array() {
                Some(a) if a.len() == count => arrays.push(a),
                _ => {
                    let expected = format!("an array of {count} values (one per marker)");
                    return Err(self.bad(&format!("markers.{field}"), &expected, found));
                }
            }
        }
        let mut sets = Vec::with_capacity(MARKER_SETS.len());
        for (field, _) in MARKER_SETS {
            sets.push(self.index_set(markers, field, count)?);
        }
        let number = |k: usize, m: usize| -> Result<Option<f64>> {
            let (field, _) = MARKER_ARRAYS[k];
            match &arrays[k][m] {
                Value::Null => Ok(None),
                n => n
                    .as_f64()
                    .filter(|x| x.is_finite())
                    .map(Some)
                    .ok_or_else(|| self.bad(&format!("markers.{field}[{m}]"), "a number or null", n)),
            }
        };
        let id = |k: usize, m: usize| -> Result<u16> {
            let (field, _) = MARKER_ARRAYS[k];
            let n = &arrays[k][m];
            n.as_u64()
                .and_then(|x| u16::try_from(x).ok())
                .ok_or_else(|| self.bad(&format!("markers.{field}[{m}]"), "a lattice index", n))
        };
        let point = |kx: usize, m: usize| -> Result<Option<Point2>> {
            Ok(match (number(kx, m)?, number(kx + 1, m)?) {
                (Some(x), Some(y)) => Some(Point2::new(x, y)),
                _ => None,
            })
        };
        let vector = |k0: usize, m: usize| -> Result<Option<[f64; 3]>> {
            Ok(match (number(k0, m)?, number(k0 + 1, m)?, number(k0 + 2, m)?) {
                (Some(x), Some(y), Some(z)) => Some([x / 1000.0, y / 1000.0, z / 1000.0]),
                _ => None,
            })
        };
        let member = |set: &Option<Vec<bool>>, m: usize| set.as_ref().map(|s| s[m]);
        let mut rows = Vec::with_capacity(count);
        for m in 0..count {
            let gel_position_mm = vector(6, m)?;
            let gel_displacement_mm = vector(9, m)?;
            let status = match (member(&sets[0], m), member(&sets[1], m)) {
                (_, Some(true)) => MarkerStatus::Lost,
                (Some(true), _) => MarkerStatus::Predicted,
                _ => MarkerStatus::Tracked,
            };
            rows.push(MarkerRecord {
                frame,
                index: GridIndex::new(id(0, m)?, id(1, m)?),
                left_px: point(2, m)?,
                right_px: point(4, m)?,
                position_mm: gel.zip(gel_position_mm).map(|(g, p)| g.to_camera(p)),
                displacement_mm: gel.zip(gel_displacement_mm).map(|(g, d)| g.vector_to_camera(d)),
                status: Some(status),
                pressure_kpa: number(12, m)?,
                in_contact: member(&sets[2], m),
                slipping: member(&sets[3], m),
                gel_position_mm,
                gel_displacement_mm,
            });
        }
        Ok(rows)
    }

    /// An index list as one flag per marker; `None` for `null`.
    fn index_set(&self, markers: &Value, field: &str, count: usize) -> Result<Option<Vec<bool>>> {
        let found = markers.get(field).unwrap_or(&Value::Null);
        if found.is_null() {
            return Ok(None);
        }
        let expected = format!("an array of marker indices below {count}");
        let indices = found
            .as_array()
            .ok_or_else(|| self.bad(&format!("markers.{field}"), &expected, found))?;
        let mut flags = vec![false; count];
        for index in indices {
            let k = index
                .as_u64()
                .and_then(|k| usize::try_from(k).ok())
                .filter(|k| *k < count)
                .ok_or_else(|| self.bad(&format!("markers.{field}"), &expected, index))?;
            flags[k] = true;
        }
        Ok(Some(flags))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A frame of `n` markers with values from `seed` values, some missing, and a tilted gel frame.
    fn frame_of(values: &[(f64, f64, f64, u8)], measured: bool) -> StreamFrame {
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let gel = GelFrame {
            origin_mm: Point3::new(0.5, -0.25, 24.0),
            axes: [
                Vector3::new(c, 0.0, s),
                Vector3::new(0.0, 1.0, 0.0),
                Vector3::new(-s, 0.0, c),
            ],
            pitch_mm: 0.8,
        };
        let markers = values
            .iter()
            .enumerate()
            .map(|(k, &(a, b, z, kind))| {
                let gel_position_mm = (kind % 5 != 0).then_some([a, b, z]);
                let gel_displacement_mm = gel_position_mm.map(|_| [b / 100.0, a / 100.0, -z / 50.0]);
                let status = [MarkerStatus::Tracked, MarkerStatus::Predicted, MarkerStatus::Lost]
                    [usize::from(kind % 3)];
                MarkerRecord {
                    frame: 7,
                    index: GridIndex::new((k / 23) as u16, (k % 23) as u16),
                    left_px: Some(Point2::new(a * 10.0, b * 10.0)),
                    right_px: (kind % 2 == 0).then(|| Point2::new(b, a)),
                    position_mm: gel_position_mm.map(|p| gel.to_camera(p)),
                    displacement_mm: gel_displacement_mm.map(|d| gel.vector_to_camera(d)),
                    status: Some(status),
                    pressure_kpa: measured.then_some(z.abs()),
                    in_contact: measured.then_some(kind % 4 == 1),
                    slipping: measured.then_some(kind % 7 == 3),
                    gel_position_mm,
                    gel_displacement_mm,
                }
            })
            .collect();
        let mut summary = FrameSummary::unmeasured(7);
        if measured {
            summary = FrameSummary {
                contact: true,
                contact_area_mm2: Some(3.5),
                max_depth_mm: Some(0.25),
                centroid_mm: Some([1.0, -2.0]),
                slip: SlipState::PartialSlip,
                force_n: Some(1.25),
                shear_n: Some([0.1, -0.2]),
                torque_nmm: Some(0.05),
                measured: true,
                frame: 7,
            };
        }
        StreamFrame {
            frame: 7,
            t_s: 0.25,
            markers,
            summary,
            note: (!measured).then(|| "cannot read \"x\"".to_owned()),
            gel: Some(gel),
        }
    }

    fn line_of(frame: &StreamFrame) -> String {
        let note = frame.note.as_deref();
        frame_line(
            frame.frame,
            frame.t_s,
            &frame.summary,
            &frame.markers,
            note,
            frame.gel.as_ref(),
        )
    }

    fn within<const N: usize>(a: Option<[f64; N]>, b: Option<[f64; N]>, tolerance: f64) -> bool {
        match (a, b) {
            (None, None) => true,
            (Some(a), Some(b)) => a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= tolerance),
            _ => false,
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// A written line reads back as the frame, to the stream's precision.
        #[test]
        fn lines_read_back_as_the_frame_they_were_written_from(
            values in proptest::collection::vec((-20.0f64..20.0, -20.0f64..20.0, -2.0f64..2.0, any::<u8>()), 0..60),
            measured in any::<bool>(),
        ) {
            let frame = frame_of(&values, measured);
            let back = parse_frame_line(&line_of(&frame), "s.jsonl:1").unwrap();
            prop_assert!(back.gel.is_some());
            prop_assert_eq!(&back.summary, &frame.summary);
            prop_assert_eq!(back.note, frame.note);
            prop_assert_eq!(back.markers.len(), frame.markers.len());
            for (m, truth) in back.markers.iter().zip(&frame.markers) {
                prop_assert_eq!((m.index, m.status, m.in_contact, m.slipping), (truth.index, truth.status, truth.in_contact, truth.slipping));
                prop_assert!(within(m.gel_position_mm, truth.gel_position_mm, 5e-4 + 1e-9));
                prop_assert!(within(m.gel_displacement_mm, truth.gel_displacement_mm, 5e-4 + 1e-9));
                prop_assert!(within(m.position_mm, truth.position_mm, 1e-3));
                prop_assert!(within(m.left_px.map(|p| [p.x, p.y]), truth.left_px.map(|p| [p.x, p.y]), 0.005 + 1e-9));
            }
        }

        /// A line with bytes replaced, inserted or cut: a frame or an error naming the stream and
        /// line, never a panic.
        #[test]
        fn mutated_lines_read_or_name_the_line(
            values in proptest::collection::vec((-20.0f64..20.0, -20.0f64..20.0, -2.0f64..2.0, any::<u8>()), 1..8),
            edits in proptest::collection::vec((any::<usize>(), any::<u8>(), 0u8..3), 1..6),
        ) {
            let mut bytes = line_of(&frame_of(&values, true)).into_bytes();
            gelstereo_core::testing::mutate(&mut bytes, &edits);
            let text = String::from_utf8_lossy(&bytes);
            for result in read_frames(text.as_bytes(), "s.jsonl") {
                if let Err(e) = result {
                    let message = e.to_string();
                    prop_assert!(message.starts_with("s.jsonl:"), "{}", message);
                    prop_assert!(message.len() < 600, "{}", message);
                }
            }
        }
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
