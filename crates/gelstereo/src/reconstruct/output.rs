//! The files a reconstruction writes into its output folder: `markers.csv`, `rejected_pairs.csv`,
//! `ply/NNNNNN.ply` and `evaluation.json`. Each frame's rows are written after its point cloud, whole
//! and flushed, so that a run stopped at any point leaves tables that end at a frame boundary.

use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufWriter, Write as _};
use std::path::{Path, PathBuf};

use gelstereo_core::table::MARKER_COLUMNS;
use gelstereo_io::images;
use gelstereo_io::ply::{CoordinateFrame, MarkerPoint, write_marker_cloud};
use gelstereo_matching::FrameReconstruction;

use crate::{Error, Result};

/// The output folder's files, opened afresh: the tables are started and the point clouds and
/// evaluation of an earlier run removed, so that no file of an earlier run looks current.
pub(super) struct OutputFiles {
    markers: Table,
    rejections: Table,
    /// Where the point clouds go; `None`: none are written.
    ply_dir: Option<PathBuf>,
}

/// A CSV table written a frame at a time.
struct Table {
    file: BufWriter<File>,
    pending: String,
}

impl Table {
    fn create(path: &Path, header: &str) -> Result<Self> {
        let file = File::create(path).map_err(io_failed("create", path))?;
        let mut table = Self {
            file: BufWriter::new(file),
            pending: format!("{header}\n"),
        };
        table.flush_frame()?;
        Ok(table)
    }

    /// Appends the pending rows in one write, flushes, and empties them.
    fn flush_frame(&mut self) -> Result<()> {
        self.file
            .write_all(self.pending.as_bytes())
            .and_then(|()| self.file.flush())
            .map_err(|e| Error::Invalid(format!("cannot write the output tables: {e}")))?;
        self.pending.clear();
        Ok(())
    }
}

impl OutputFiles {
    pub fn create(out: &Path, ply: bool) -> Result<Self> {
        create_dir(out)?;
        let evaluation = out.join(EVALUATION_FILE);
        if evaluation.exists() {
            remove(&evaluation)?;
        }
        let ply_dir = out.join("ply");
        if ply_dir.is_dir() {
            for old in images::list_files_named(&ply_dir, is_frame_ply)? {
                remove(&old)?;
            }
        }
        if ply {
            create_dir(&ply_dir)?;
        }
        Ok(Self {
            markers: Table::create(&out.join(MARKERS_FILE), &MARKER_COLUMNS.join(","))?,
            rejections: Table::create(&out.join(REJECTIONS_FILE), "frame,row,col,reason")?,
            ply_dir: ply.then_some(ply_dir),
        })
    }

    /// Writes one frame: its point cloud, then its rows in both tables. Returns the number of pairs
    /// rejected (seen in both views without a 3-D position).
    pub fn write_frame(&mut self, frame: u32, rec: &FrameReconstruction) -> Result<usize> {
        for m in &rec.markers {
            m.record(frame).write_csv(&mut self.markers.pending);
            self.markers.pending.push('\n');
        }
        let rejected = self.add_rejections(frame, rec);
        if let Some(dir) = &self.ply_dir {
            write_cloud(&dir.join(format!("{frame:06}.ply")), frame, rec)?;
        }
        self.markers.flush_frame()?;
        self.rejections.flush_frame()?;
        Ok(rejected)
    }

    /// Adds a row per marker seen in both views without a 3-D position, with why (epipolar check,
    /// triangulation); returns how many.
    fn add_rejections(&mut self, frame: u32, rec: &FrameReconstruction) -> usize {
        let mut rejected = 0;
        for m in &rec.markers {
            if let Some(why) = &m.rejection {
                rejected += 1;
                // One CSV cell: the reason's own commas become semicolons.
                let reason = why.to_string().replace(',', ";");
                let _ = writeln!(
                    self.rejections.pending,
                    "{frame},{},{},{reason}",
                    m.index.row, m.index.col
                );
            }
        }
        rejected
    }

    /// The point clouds' folder, when they are written.
    pub fn ply_dir(&self) -> Option<&Path> {
        self.ply_dir.as_deref()
    }
}

/// The marker table's file name.
pub(super) const MARKERS_FILE: &str = "markers.csv";
/// The rejected pairs' file name.
pub(super) const REJECTIONS_FILE: &str = "rejected_pairs.csv";
/// The evaluation's file name.
pub(super) const EVALUATION_FILE: &str = "evaluation.json";

/// The frame's triangulated markers as a binary PLY point cloud.
fn write_cloud(path: &Path, frame: u32, rec: &FrameReconstruction) -> Result<()> {
    let points: Vec<MarkerPoint> = rec
        .markers
        .iter()
        .filter_map(|m| {
            Some(MarkerPoint {
                index: m.index,
                position_mm: m.position_mm?,
                reprojection_error_px: m.reprojection_error_px?,
            })
        })
        .collect();
    Ok(write_marker_cloud(
        path,
        &points,
        CoordinateFrame::LeftCamera,
        &format!("frame {frame}"),
    )?)
}

/// Whether `name` is a point cloud of this module: six digits and `.ply`.
fn is_frame_ply(name: &str) -> bool {
    name.strip_suffix(".ply")
        .is_some_and(|stem| stem.len() == 6 && stem.bytes().all(|b| b.is_ascii_digit()))
}

fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(io_failed("create", dir))
}

fn remove(path: &Path) -> Result<()> {
    std::fs::remove_file(path).map_err(io_failed("remove", path))
}

/// Writes `text` and a final newline to `path`.
pub(super) fn write_text(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, format!("{text}\n")).map_err(io_failed("write", path))
}

/// The error of a file operation: `cannot VERB PATH: why`.
fn io_failed<'a>(verb: &'a str, path: &'a Path) -> impl FnOnce(std::io::Error) -> Error + 'a {
    move |e| Error::Invalid(format!("cannot {verb} {}: {e}", path.display()))
}
