//! Frames of one stream localized ahead of the tracker by worker threads and handed on in frame
//! order. Localization needs nothing but its own frame; tracking needs every earlier frame, so it
//! stays on the calling thread while the workers keep the cores busy with the next frames.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, PoisonError, mpsc};

use gelstereo_core::{StereoPair, TieredDetections};

use crate::source::SourceFrame;
use crate::{FrameLocalizer, Result};

/// A frame's markers as a [`FrameLocalizer`] found them; `None` when the frame could not be read.
pub(crate) type Found = Option<Result<StereoPair<TieredDetections>>>;

/// Pulls `frames` on `workers.len()` threads, each localizing with its own localizer, and calls
/// `consume` with every frame and its markers in the order of `frames`, on the calling thread,
/// until `frames` ends, `consume` returns `Ok(false)` or an error, or `stop` is raised (the frames
/// already pulled are then dropped). At most two frames per worker are held at once.
pub(crate) fn localize_ahead<I>(
    frames: I,
    workers: Vec<FrameLocalizer>,
    stop: &AtomicBool,
    consume: &mut dyn FnMut(SourceFrame, Found) -> Result<bool>,
) -> Result<()>
where
    I: Iterator<Item = SourceFrame> + Send,
{
    let source = Mutex::new((frames, 0usize));
    let halt = AtomicBool::new(false);
    let (tx, rx) = mpsc::sync_channel::<(usize, SourceFrame, Found)>(workers.len());
    std::thread::scope(|scope| {
        for mut worker in workers {
            let (tx, source, halt) = (tx.clone(), &source, &halt);
            scope.spawn(move || {
                while !halt.load(Ordering::SeqCst) && !stop.load(Ordering::SeqCst) {
                    let next = {
                        let mut guard = source.lock().unwrap_or_else(PoisonError::into_inner);
                        let (frames, pulled) = &mut *guard;
                        frames.next().map(|f| {
                            *pulled += 1;
                            (*pulled - 1, f)
                        })
                    };
                    let Some((k, frame)) = next else { break };
                    let found = frame.images.as_ref().ok().map(|im| worker.localize(im));
                    if tx.send((k, frame, found)).is_err() {
                        break;
                    }
                }
            });
        }
        drop(tx);
        let result = in_order(&rx, consume);
        // Workers stop pulling; a worker blocked on a full channel is released by the drop.
        halt.store(true, Ordering::SeqCst);
        drop(rx);
        result
    })
}

/// Hands the received frames to `consume` in pull order.
fn in_order(
    rx: &mpsc::Receiver<(usize, SourceFrame, Found)>,
    consume: &mut dyn FnMut(SourceFrame, Found) -> Result<bool>,
) -> Result<()> {
    let mut pending = BTreeMap::new();
    let mut next = 0usize;
    for (k, frame, found) in rx {
        pending.insert(k, (frame, found));
        while let Some((frame, found)) = pending.remove(&next) {
            next += 1;
            if !consume(frame, found)? {
                return Ok(());
            }
        }
    }
    Ok(())
}
