//! The per-frame tables other tools read (docs/design.md "Interfaces"): `markers.csv`, one row per marker
//! and frame, and `frames.csv`, one row per frame. Empty cells stand for what a mono sensor or a
//! lost marker lacks. Readers look columns up by name, so files may carry extra columns (the
//! simulator adds its ground-truth ones).

use std::fmt::Write as _;
use std::path::Path;

use crate::{Error, GridIndex, MarkerStatus, Point2, Result, SlipState};

/// Columns of `markers.csv`, in order.
pub const MARKER_COLUMNS: [&str; 23] = [
    "frame",
    "row",
    "col",
    "x_left",
    "y_left",
    "x_right",
    "y_right",
    "X_mm",
    "Y_mm",
    "Z_mm",
    "dX_mm",
    "dY_mm",
    "dZ_mm",
    "status",
    "pressure_kPa",
    "in_contact",
    "slipping",
    "X_gel_mm",
    "Y_gel_mm",
    "Z_gel_mm",
    "dX_gel_mm",
    "dY_gel_mm",
    "dZ_gel_mm",
];

/// Columns of `frames.csv`, in order.
pub const FRAME_COLUMNS: [&str; 11] = [
    "frame",
    "contact",
    "contact_area_mm2",
    "max_depth_mm",
    "centroid_X_mm",
    "centroid_Y_mm",
    "slip",
    "force_N",
    "shear_x_N",
    "shear_y_N",
    "torque_Nmm",
];

/// One row of `markers.csv`: one marker in one frame.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MarkerRecord {
    /// Frame number, from 0.
    pub frame: u32,
    /// The marker's grid identity.
    pub index: GridIndex,
    /// Position in the left view (a mono sensor fills this one), px.
    pub left_px: Option<Point2>,
    /// Position in the right view, px.
    pub right_px: Option<Point2>,
    /// 3-D position in the left camera frame, mm.
    pub position_mm: Option<[f64; 3]>,
    /// 3-D displacement against the reference frame, mm.
    pub displacement_mm: Option<[f64; 3]>,
    /// How the position was obtained; empty for ground truth and single-frame reconstructions.
    pub status: Option<MarkerStatus>,
    /// Contact pressure on the marker's cell, kPa; empty where the contact mechanics did not run.
    pub pressure_kpa: Option<f64>,
    /// Whether the marker lies in the contact region.
    pub in_contact: Option<bool>,
    /// Whether the marker slips against the object.
    pub slipping: Option<bool>,
    /// 3-D position in the gel frame (origin at the centre of the reference surface, x along the
    /// lattice's columns, y along its rows, z the surface's normal away from the cameras), mm;
    /// empty where no gel frame is known (ground truth, single-frame reconstructions, mono).
    pub gel_position_mm: Option<[f64; 3]>,
    /// 3-D displacement in the gel frame, mm: `[dx, dy]` the shear, `dz` negative where the gel is
    /// pressed in.
    pub gel_displacement_mm: Option<[f64; 3]>,
}

/// One row of `frames.csv`: the contact summary of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameSummary {
    /// Frame number, from 0.
    pub frame: u32,
    /// Whether anything touches the gel.
    pub contact: bool,
    /// Contact area, mm^2 (0 without contact); `None` when the sensor's scale is unknown (a mono
    /// sensor without its marker pitch), written as an empty cell.
    pub contact_area_mm2: Option<f64>,
    /// Largest indentation depth, mm (0 without contact); `None` when the sensor cannot measure it
    /// (mono sensors), written as an empty cell.
    pub max_depth_mm: Option<f64>,
    /// Contact centroid in the left camera frame, mm; empty without contact.
    pub centroid_mm: Option<[f64; 2]>,
    /// Slip state.
    pub slip: SlipState,
    /// Total normal force on the gel, N; empty where it is unknown (no layer mechanics, a mono
    /// sensor).
    pub force_n: Option<f64>,
    /// Total tangential force on the gel `[x, y]`, N, along the gel frame's axes (the lattice's
    /// columns and rows).
    pub shear_n: Option<[f64; 2]>,
    /// Torque of the tangential tractions about the contact normal through the pressure
    /// centroid, N mm.
    pub torque_nmm: Option<f64>,
    /// Whether the frame was measured. `false` for a frame that could not be read or localized,
    /// or that showed no usable markers: it knows nothing of the contact, and every contact
    /// column is written empty (never as no contact or 0).
    pub measured: bool,
}

/// Appends `,` and a flag as `0` / `1`, or nothing for `None`.
fn push_flag(out: &mut String, v: Option<bool>) {
    out.push(',');
    if let Some(v) = v {
        out.push(if v { '1' } else { '0' });
    }
}

fn push_opt(out: &mut String, v: Option<f64>) {
    out.push(',');
    if let Some(v) = v {
        // Six decimals: 1e-6 px / 1e-6 mm, far below any accuracy we claim.
        let _ = write!(out, "{v:.6}");
    }
}

impl MarkerRecord {
    /// Appends this row's 23 cells (no newline) in [`MARKER_COLUMNS`] order.
    pub fn write_csv(&self, out: &mut String) {
        let _ = write!(out, "{},{},{}", self.frame, self.index.row, self.index.col);
        for p in [self.left_px, self.right_px] {
            push_opt(out, p.map(|p| p.x));
            push_opt(out, p.map(|p| p.y));
        }
        for v in [self.position_mm, self.displacement_mm] {
            for k in 0..3 {
                push_opt(out, v.map(|v| v[k]));
            }
        }
        out.push(',');
        if let Some(s) = self.status {
            out.push_str(s.as_str());
        }
        push_opt(out, self.pressure_kpa);
        push_flag(out, self.in_contact);
        push_flag(out, self.slipping);
        for v in [self.gel_position_mm, self.gel_displacement_mm] {
            for k in 0..3 {
                push_opt(out, v.map(|v| v[k]));
            }
        }
    }

    /// Reads the row `row` of `table`.
    pub fn from_table(table: &CsvTable, row: usize) -> Result<Self> {
        let point = |x: &str, y: &str| -> Result<Option<Point2>> {
            Ok(match (table.opt_f64(row, x)?, table.opt_f64(row, y)?) {
                (Some(x), Some(y)) => Some(Point2::new(x, y)),
                _ => None,
            })
        };
        // The gel-frame columns are newer than the others: tables without them still read.
        let vec3 = |names: [&str; 3]| -> Result<Option<[f64; 3]>> {
            let [a, b, c] = names;
            let cell = |name: &str| match name.contains("_gel_") {
                true => table.opt_f64_if_present(row, name),
                false => table.opt_f64(row, name),
            };
            Ok(match (cell(a)?, cell(b)?, cell(c)?) {
                (Some(a), Some(b), Some(c)) => Some([a, b, c]),
                _ => None,
            })
        };
        Ok(Self {
            frame: table.value(row, "frame", "a frame number")?,
            index: GridIndex {
                row: table.value(row, "row", "a grid row (0-65535)")?,
                col: table.value(row, "col", "a grid column (0-65535)")?,
            },
            left_px: point("x_left", "y_left")?,
            right_px: point("x_right", "y_right")?,
            position_mm: vec3(["X_mm", "Y_mm", "Z_mm"])?,
            displacement_mm: vec3(["dX_mm", "dY_mm", "dZ_mm"])?,
            status: match table.cell(row, "status")? {
                "" => None,
                _ => Some(table.value(row, "status", "tracked, predicted or lost")?),
            },
            pressure_kpa: table.opt_f64_if_present(row, "pressure_kPa")?,
            in_contact: table.opt_flag_if_present(row, "in_contact")?,
            slipping: table.opt_flag_if_present(row, "slipping")?,
            gel_position_mm: vec3(["X_gel_mm", "Y_gel_mm", "Z_gel_mm"])?,
            gel_displacement_mm: vec3(["dX_gel_mm", "dY_gel_mm", "dZ_gel_mm"])?,
        })
    }
}

impl FrameSummary {
    /// Appends this row's 11 cells (no newline) in [`FRAME_COLUMNS`] order.
    pub fn write_csv(&self, out: &mut String) {
        if !self.measured {
            let _ = write!(out, "{}{}", self.frame, ",".repeat(FRAME_COLUMNS.len() - 1));
            return;
        }
        let _ = write!(out, "{},{}", self.frame, u8::from(self.contact));
        push_opt(out, self.contact_area_mm2);
        push_opt(out, self.max_depth_mm);
        push_opt(out, self.centroid_mm.map(|c| c[0]));
        push_opt(out, self.centroid_mm.map(|c| c[1]));
        let _ = write!(out, ",{}", self.slip);
        push_opt(out, self.force_n);
        push_opt(out, self.shear_n.map(|s| s[0]));
        push_opt(out, self.shear_n.map(|s| s[1]));
        push_opt(out, self.torque_nmm);
    }

    /// Reads the row `row` of `table`.
    pub fn from_table(table: &CsvTable, row: usize) -> Result<Self> {
        if table.cell(row, "contact")?.is_empty() {
            return Ok(Self::unmeasured(table.value(row, "frame", "a frame number")?));
        }
        let contact: u8 = table.value(row, "contact", "0 or 1")?;
        Ok(Self {
            frame: table.value(row, "frame", "a frame number")?,
            contact: contact == 1,
            contact_area_mm2: table.opt_f64(row, "contact_area_mm2")?,
            max_depth_mm: table.opt_f64(row, "max_depth_mm")?,
            centroid_mm: match (
                table.opt_f64(row, "centroid_X_mm")?,
                table.opt_f64(row, "centroid_Y_mm")?,
            ) {
                (Some(x), Some(y)) => Some([x, y]),
                _ => None,
            },
            slip: table.value(row, "slip", "no_contact, stick, partial_slip or gross_slip")?,
            force_n: table.opt_f64_if_present(row, "force_N")?,
            shear_n: match (
                table.opt_f64_if_present(row, "shear_x_N")?,
                table.opt_f64_if_present(row, "shear_y_N")?,
            ) {
                (Some(x), Some(y)) => Some([x, y]),
                _ => None,
            },
            torque_nmm: table.opt_f64_if_present(row, "torque_Nmm")?,
            measured: true,
        })
    }

    /// The summary of frame `frame` that was not measured: every contact figure unknown.
    pub fn unmeasured(frame: u32) -> Self {
        Self {
            frame,
            contact: false,
            contact_area_mm2: None,
            max_depth_mm: None,
            centroid_mm: None,
            slip: SlipState::NoContact,
            force_n: None,
            shear_n: None,
            torque_nmm: None,
            measured: false,
        }
    }
}

/// A comma-separated table with a header line, read whole. Cells hold no commas or quotes (all our
/// tables are numbers and single words).
#[derive(Debug, Clone)]
pub struct CsvTable {
    path: String,
    header: Vec<String>,
    rows: Vec<Vec<String>>,
}

impl CsvTable {
    /// Reads `path`, checking that it has a header and that every row has as many cells.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_text(&path.display().to_string(), &text)
    }

    /// Parses `text`; `path` names it in errors.
    pub fn from_text(path: &str, text: &str) -> Result<Self> {
        let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
        let Some((_, head)) = lines.next() else {
            return Err(table_err(path, 1, "(header)", "a header line", ""));
        };
        let header: Vec<String> = head.split(',').map(|s| s.trim().to_owned()).collect();
        let mut rows = Vec::new();
        for (i, line) in lines {
            let cells: Vec<String> = line.split(',').map(|s| s.trim().to_owned()).collect();
            if cells.len() != header.len() {
                return Err(table_err(
                    path,
                    i + 1,
                    "(row)",
                    &format!("{} cells like the header", header.len()),
                    &format!("{} cells", cells.len()),
                ));
            }
            rows.push(cells);
        }
        Ok(Self {
            path: path.to_owned(),
            header,
            rows,
        })
    }

    /// Checks that every column in `columns` is present.
    pub fn require(&self, columns: &[&str]) -> Result<()> {
        for c in columns {
            self.column(c)?;
        }
        Ok(())
    }

    /// Number of data rows.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether the table has no data rows.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// The header's column names.
    pub fn header(&self) -> &[String] {
        &self.header
    }

    fn column(&self, name: &str) -> Result<usize> {
        self.header.iter().position(|h| h == name).ok_or_else(|| {
            table_err(
                &self.path,
                1,
                name,
                "this column in the header",
                &self.header.join(","),
            )
        })
    }

    /// The raw text of `column` in data row `row` (0-based).
    pub fn cell(&self, row: usize, column: &str) -> Result<&str> {
        let c = self.column(column)?;
        Ok(self
            .rows
            .get(row)
            .and_then(|r| r.get(c))
            .map(String::as_str)
            .unwrap_or(""))
    }

    /// Whether the header has `column`.
    pub fn has(&self, column: &str) -> bool {
        self.header.iter().any(|h| h == column)
    }

    /// [`opt_f64`](Self::opt_f64), or `None` where the table has no such column (tables written
    /// before the column existed).
    pub fn opt_f64_if_present(&self, row: usize, column: &str) -> Result<Option<f64>> {
        if self.has(column) {
            self.opt_f64(row, column)
        } else {
            Ok(None)
        }
    }

    /// A `0` / `1` flag, `None` for an empty cell or an absent column.
    pub fn opt_flag_if_present(&self, row: usize, column: &str) -> Result<Option<bool>> {
        if !self.has(column) {
            return Ok(None);
        }
        match self.cell(row, column)? {
            "" => Ok(None),
            "0" => Ok(Some(false)),
            "1" => Ok(Some(true)),
            s => Err(table_err(&self.path, row + 2, column, "0, 1 or an empty cell", s)),
        }
    }

    /// Parses a required cell.
    pub fn value<T: std::str::FromStr>(&self, row: usize, column: &str, expected: &str) -> Result<T> {
        let s = self.cell(row, column)?;
        s.parse()
            .map_err(|_| table_err(&self.path, row + 2, column, expected, s))
    }

    /// Parses an optional number: an empty cell is `None`; NaN and infinities are rejected.
    pub fn opt_f64(&self, row: usize, column: &str) -> Result<Option<f64>> {
        match self.cell(row, column)? {
            "" => Ok(None),
            s => match s.parse::<f64>() {
                Ok(v) if v.is_finite() => Ok(Some(v)),
                _ => Err(table_err(
                    &self.path,
                    row + 2,
                    column,
                    "a finite number or an empty cell",
                    s,
                )),
            },
        }
    }
}

fn table_err(path: &str, line: usize, column: &str, expected: &str, found: &str) -> Error {
    Error::Table {
        path: path.to_owned(),
        line,
        column: column.to_owned(),
        expected: expected.to_owned(),
        found: found.to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marker_rows_round_trip_with_empty_cells() {
        let full = MarkerRecord {
            frame: 7,
            index: GridIndex::new(3, 22),
            left_px: Some(Point2::new(101.25, 33.5)),
            right_px: None,
            position_mm: Some([1.0, -2.5, 30.125]),
            displacement_mm: None,
            status: Some(MarkerStatus::Predicted),
            pressure_kpa: Some(12.25),
            in_contact: Some(true),
            slipping: Some(false),
            gel_position_mm: Some([0.5, -0.25, -0.125]),
            gel_displacement_mm: None,
        };
        let mono = MarkerRecord {
            frame: 8,
            left_px: Some(Point2::new(1.0, 2.0)),
            ..Default::default()
        };
        let mut text = MARKER_COLUMNS.join(",");
        for r in [&full, &mono] {
            text.push('\n');
            r.write_csv(&mut text);
        }
        let table = CsvTable::from_text("mem", &text).unwrap();
        assert_eq!(MarkerRecord::from_table(&table, 0).unwrap(), full);
        assert_eq!(MarkerRecord::from_table(&table, 1).unwrap(), mono);
    }

    #[test]
    fn bad_cells_name_file_line_column_and_expectation() {
        let text = format!(
            "{}\n0,1,2,NaN,,,,,,,,,,tracked,,,,,,,,,",
            MARKER_COLUMNS.join(",")
        );
        let table = CsvTable::from_text("gt/markers.csv", &text).unwrap();
        let err = MarkerRecord::from_table(&table, 0).unwrap_err().to_string();
        assert!(
            err.contains("gt/markers.csv:2") && err.contains("x_left") && err.contains("NaN"),
            "{err}"
        );

        let short = CsvTable::from_text("f.csv", "frame,contact\n1")
            .unwrap_err()
            .to_string();
        assert!(short.contains("f.csv:2") && short.contains("2 cells"), "{short}");
        let missing = FrameSummary::from_table(&CsvTable::from_text("f.csv", "frame\n1").unwrap(), 0);
        assert!(missing.unwrap_err().to_string().contains("'contact'"));
    }

    #[test]
    fn frame_rows_round_trip() {
        let s = FrameSummary {
            frame: 3,
            contact: true,
            contact_area_mm2: Some(12.5),
            max_depth_mm: Some(0.75),
            centroid_mm: Some([0.5, -1.25]),
            slip: SlipState::PartialSlip,
            force_n: Some(1.5),
            shear_n: Some([0.25, -0.125]),
            torque_nmm: Some(0.0625),
            measured: true,
        };
        let mut text = FRAME_COLUMNS.join(",");
        text.push('\n');
        s.write_csv(&mut text);
        let table = CsvTable::from_text("mem", &text).unwrap();
        assert_eq!(FrameSummary::from_table(&table, 0).unwrap(), s);
        // Unknown area and depth (a mono sensor without its scale) are empty cells, not 0.
        let unknown = FrameSummary {
            contact_area_mm2: None,
            max_depth_mm: None,
            force_n: None,
            shear_n: None,
            torque_nmm: None,
            ..s
        };
        let mut row = String::new();
        unknown.write_csv(&mut row);
        assert_eq!(row, "3,1,,,0.500000,-1.250000,partial_slip,,,,");
        // A table written before the force columns existed reads as unknown force.
        let old = "frame,contact,contact_area_mm2,max_depth_mm,centroid_X_mm,centroid_Y_mm,slip\n3,1,,,0.5,-1.25,partial_slip";
        let back = FrameSummary::from_table(&CsvTable::from_text("mem", old).unwrap(), 0).unwrap();
        assert_eq!(back, unknown);
        let table = CsvTable::from_text("mem", &format!("{}\n{row}", FRAME_COLUMNS.join(","))).unwrap();
        assert_eq!(FrameSummary::from_table(&table, 0).unwrap(), unknown);
    }

    mod properties {
        use super::*;
        use proptest::prelude::*;

        /// A cell: a number, a word the tables use, empty, or any short text.
        fn cell() -> impl Strategy<Value = String> {
            prop_oneof![
                Just(String::new()),
                any::<i64>().prop_map(|v| v.to_string()),
                any::<f64>().prop_map(|v| v.to_string()),
                prop_oneof![
                    Just("tracked"),
                    Just("lost"),
                    Just("stick"),
                    Just("no_contact"),
                    Just("1")
                ]
                .prop_map(str::to_owned),
                "[^,\n]{0,8}",
            ]
        }

        fn finite() -> impl Strategy<Value = f64> {
            -1e6f64..1e6
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(256))]

            /// Any text with a table's header: rows parse or give an error naming the file; never
            /// a panic.
            #[test]
            fn any_table_text_parses_or_names_the_file(
                rows in proptest::collection::vec(proptest::collection::vec(cell(), 0..16), 0..4),
                markers in any::<bool>(),
            ) {
                let header = if markers { MARKER_COLUMNS.join(",") } else { FRAME_COLUMNS.join(",") };
                let body: Vec<String> = rows.iter().map(|r| r.join(",")).collect();
                let text = format!("{header}\n{}", body.join("\n"));
                match CsvTable::from_text("p.csv", &text) {
                    Ok(table) => {
                        for r in 0..table.len() {
                            let parsed = if markers {
                                MarkerRecord::from_table(&table, r).map(drop)
                            } else {
                                FrameSummary::from_table(&table, r).map(drop)
                            };
                            if let Err(e) = parsed {
                                prop_assert!(e.to_string().contains("p.csv:"), "{}", e);
                            }
                        }
                    }
                    Err(e) => prop_assert!(e.to_string().contains("p.csv:"), "{}", e),
                }
            }

            /// Whatever frames.csv row is written reads back the same (values at their written
            /// precision).
            #[test]
            fn frame_rows_round_trip_for_any_values(
                frame in any::<u32>(),
                area in proptest::option::of(finite()),
                depth in proptest::option::of(finite()),
                centroid in proptest::option::of((finite(), finite())),
            ) {
                let s = FrameSummary {
                    frame,
                    contact: centroid.is_some(),
                    contact_area_mm2: area,
                    max_depth_mm: depth,
                    centroid_mm: centroid.map(|(x, y)| [x, y]),
                    slip: SlipState::Stick,
                    force_n: area,
                    shear_n: None,
                    torque_nmm: depth,
                    measured: true,
                };
                let mut text = FRAME_COLUMNS.join(",");
                text.push('\n');
                s.write_csv(&mut text);
                let table = CsvTable::from_text("mem", &text).unwrap();
                let back = FrameSummary::from_table(&table, 0).unwrap();
                prop_assert_eq!(back.frame, frame);
                let close = |a: Option<f64>, b: Option<f64>| match (a, b) {
                    (Some(a), Some(b)) => (a - b).abs() <= 1e-6 * b.abs().max(1.0),
                    (a, b) => a.is_none() && b.is_none(),
                };
                prop_assert!(close(back.contact_area_mm2, area));
                prop_assert!(close(back.max_depth_mm, depth));
                prop_assert_eq!(back.centroid_mm.is_some(), centroid.is_some());
            }
        }
    }
}
