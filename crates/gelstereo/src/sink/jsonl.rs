//! The frame stream, `gelstereo track --jsonl`, in the format of [`gelstereo_tracking::stream`]
//! (one JSON object per frame and line, `docs/schema/frame-v1.json`): [`JsonlSink`] writes a
//! pipeline's [`FrameOutput`]s, [`parse_frame_line`] and [`read_frames`] read them back.

use std::io::{BufRead, Write};

use gelstereo_tracking::GelFrame;
use gelstereo_tracking::stream::{self, StreamFrame};

use crate::{Error, FrameOutput, Result};

/// The line of one frame (no newline), valid against `docs/schema/frame-v1.json`. `gel` is the
/// pipeline's gel frame ([`crate::Pipeline::gel_frame`]); `None` for a mono sensor or before the
/// reference frame.
pub fn frame_line(out: &FrameOutput, gel: Option<&GelFrame>) -> String {
    let note = out.note.as_deref();
    stream::frame_line(out.frame, out.t_s, &out.summary, &out.markers, note, gel)
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
        let mut line = frame_line(frame.output, frame.pipeline.gel_frame().as_ref());
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

/// Reads one line of the stream back into the [`FrameOutput`] it was written from, and the gel
/// frame the line carries ([`stream::parse_frame_line`]); the contact region is the `in_contact`
/// markers. What the stream does not carry comes back empty: the stages' results, the log, the
/// reference positions and earlier frames (each is a line of its own). `name` (the stream and line)
/// starts every error, which names the field and what was expected.
pub fn parse_frame_line(line: &str, name: &str) -> Result<(FrameOutput, Option<GelFrame>)> {
    Ok(output_of(stream::parse_frame_line(line, name)?))
}

/// Reads a whole stream: one [`parse_frame_line`] per non-blank line, named `name:LINE` in errors
/// ([`stream::read_frames`]).
pub fn read_frames<R: BufRead>(
    reader: R,
    name: &str,
) -> impl Iterator<Item = Result<(FrameOutput, Option<GelFrame>)>> + use<R> {
    stream::read_frames(reader, name).map(|frame| Ok(output_of(frame?)))
}

/// The frame as [`crate::Pipeline::process`] returned it, less what the stream does not carry.
fn output_of(read: StreamFrame) -> (FrameOutput, Option<GelFrame>) {
    let contact_region = read
        .markers
        .iter()
        .filter(|m| m.in_contact == Some(true))
        .map(|m| m.index)
        .collect();
    let output = FrameOutput {
        contact_region,
        note: read.note,
        ..FrameOutput::rows(read.frame, read.t_s, read.markers, read.summary)
    };
    (output, read.gel)
}
