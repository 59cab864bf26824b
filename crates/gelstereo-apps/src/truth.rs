//! Ground-truth marker positions of a simulated recording in place of a localizer: measures
//! indexing, tracking, triangulation, contact and slip alone (`gelstereo track --from-ground-truth`).

use std::path::Path;

use gelstereo_core::{Detection, Point2, StereoPair};
use gelstereo_matching::eval::GroundTruth;

use gelstereo::Result;

/// Per frame, the ground-truth positions of the markers visible in each view (with Gaussian noise of
/// `noise_px`, seeded, when > 0), in a shuffled-free but id-free form: sorted by y then x like a
/// localizer's output.
pub fn ground_truth(dir: &Path, noise_px: f64) -> Result<Vec<StereoPair<Vec<Detection>>>> {
    let truth = GroundTruth::read(dir)?;
    let frames = truth.frames.keys().next_back().map_or(0, |f| *f as usize + 1);
    let mut out: Vec<StereoPair<Vec<Detection>>> = vec![StereoPair::default(); frames];
    // xorshift + Box-Muller: reproducible noise without another dependency.
    let mut state: u64 = 0x2545_F491_4F6C_DD1D;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    let mut gauss = move || (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos();
    // Frames, then markers row-major: the order of the simulator's markers.csv, so the noise is drawn
    // in the same sequence for every run.
    for (frame, markers) in &truth.frames {
        let pair = &mut out[*frame as usize];
        for m in markers.values() {
            for (px, list) in [(m.left_px, &mut pair.left), (m.right_px, &mut pair.right)] {
                if let Some(p) = px {
                    list.push(Detection {
                        position: Point2::new(p.x + noise_px * gauss(), p.y + noise_px * gauss()),
                        confidence: 1.0,
                    });
                }
            }
        }
    }
    for pair in &mut out {
        gelstereo_markers::sort_detections(&mut pair.left);
        gelstereo_markers::sort_detections(&mut pair.right);
    }
    Ok(out)
}
