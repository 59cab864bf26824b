//! The files a reconstruction writes into its output folder: `markers.csv`, `rejected_pairs.csv`,
//! `ply/NNNNNN.ply` and `evaluation.json`. Each frame's rows are written after its point cloud, whole
//! and flushed, so that a run stopped at any point leaves tables that end at a frame boundary; point
//! clouds and the evaluation are written whole to a temporary name, then renamed.

use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufWriter, Write as _};
use std::path::{Path, PathBuf};

use gelstereo_core::table::MARKER_COLUMNS;
use gelstereo_io::ply::{CoordinateFrame, MarkerPoint, write_marker_cloud};
use gelstereo_matching::FrameReconstruction;

use gelstereo::sink::OutputFolder;
use gelstereo::{Error, Result};

/// The output folder's files: an [`OutputFolder`] (apart from the inputs, locked, the files of an
/// earlier run removed, a folder gelstereo did not write refused without `force`) with the tables
/// started.
pub(super) struct OutputFiles {
    folder: OutputFolder,
    markers: Table,
    rejections: Table,
    /// Whether the point clouds are written (`ply/NNNNNN.ply`).
    ply: bool,
}

/// A CSV table written a frame at a time.
struct Table {
    file: BufWriter<File>,
    path: PathBuf,
    pending: String,
}

impl Table {
    fn create(path: PathBuf, header: &str) -> Result<Self> {
        let file = File::create(&path).map_err(io_failed("create", &path))?;
        let mut table = Self {
            file: BufWriter::new(file),
            path,
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
            .map_err(io_failed("write", &self.path))?;
        self.pending.clear();
        Ok(())
    }
}

impl OutputFiles {
    pub fn create(out: &Path, ply: bool, force: bool, inputs: &[&Path]) -> Result<Self> {
        let folder = OutputFolder::prepare_apart_from(out, force, inputs)?;
        Ok(Self {
            markers: Table::create(folder.claim(MARKERS_FILE)?, &MARKER_COLUMNS.join(","))?,
            rejections: Table::create(folder.claim(REJECTIONS_FILE)?, "frame,row,col,reason")?,
            folder,
            ply,
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
        if self.ply {
            self.folder
                .write_atomic(&format!("ply/{frame:06}.ply"), |p| write_cloud(p, frame, rec))?;
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
    pub fn ply_dir(&self) -> Option<PathBuf> {
        self.ply.then(|| self.folder.dir().join("ply"))
    }

    /// Writes `text` and a final newline to `relative` in the folder, whole or not at all.
    pub fn write_text(&self, relative: &str, text: &str) -> Result<()> {
        self.folder.write_atomic(relative, |p| {
            std::fs::write(p, format!("{text}\n")).map_err(io_failed("write", p))
        })
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

/// The error of a file operation: `cannot VERB PATH: why`.
fn io_failed<'a>(verb: &'a str, path: &'a Path) -> impl FnOnce(std::io::Error) -> Error + 'a {
    move |e| Error::Invalid(format!("cannot {verb} {}: {e}", path.display()))
}
