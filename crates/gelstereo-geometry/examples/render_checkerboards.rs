//! Renders stereo checkerboard images through a known calibration, for trying and testing
//! `gelstereo calibrate` (exact projection with the calibration's lens model, 4 x 4 super-sampling).
//!
//! ```text
//! cargo build --release -p gelstereo-geometry --example render_checkerboards
//! target/release/examples/render_checkerboards CALIBRATION OUT_DIR [COLSxROWS] [SQUARE_MM] [POSES]
//! gelstereo calibrate --board 9x6 --square-mm 1.5 --out calib.yaml OUT_DIR/left OUT_DIR/right
//! ```
//! Defaults: a 9x6 inner-corner board of 1.5 mm squares, 15 poses 22-30 mm in front of the left
//! camera, tilted up to ~25 degrees, each fully visible in both views. Deterministic.

use std::path::PathBuf;

use gelstereo_geometry::checkerboard::{RayGrid, render_view};
use gelstereo_geometry::{Board, StereoRig};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use opencv::core::Vector;

/// A small deterministic generator (SplitMix64), so the example needs no RNG crate.
struct SplitMix(u64);

impl SplitMix {
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        #[allow(clippy::cast_precision_loss)]
        let u = (z >> 11) as f64 / (1u64 << 53) as f64;
        lo + (hi - lo) * u
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        return Err("usage: render_checkerboards CALIBRATION OUT_DIR [COLSxROWS] [SQUARE_MM] [POSES]".into());
    }
    let rig = StereoRig::load(&args[1])?;
    let out = PathBuf::from(&args[2]);
    let board = Board::parse(
        args.get(3).map_or("9x6", String::as_str),
        args.get(4).map_or(Ok(1.5), |s| s.parse())?,
    )?;
    let poses: usize = args.get(5).map_or(Ok(15), |s| s.parse())?;
    std::fs::create_dir_all(out.join("left"))?;
    std::fs::create_dir_all(out.join("right"))?;
    let (gl, gr) = (RayGrid::new(&rig.left), RayGrid::new(&rig.right));
    let s = board.square_mm;
    let (w, h) = (
        f64::from(board.inner_cols - 1) * s,
        f64::from(board.inner_rows - 1) * s,
    );
    let mut rng = SplitMix(6);
    let (mut written, mut tries) = (0, 0);
    while written < poses {
        tries += 1;
        if tries > 100_000 {
            return Err(
                "could not place the board in both views: is it larger than the field of view?".into(),
            );
        }
        let rot = UnitQuaternion::from_euler_angles(
            rng.uniform(-0.45, 0.45),
            rng.uniform(-0.45, 0.45),
            rng.uniform(-0.3, 0.3),
        );
        let centre = Vector3::new(
            rng.uniform(-2.0, 2.0),
            rng.uniform(-2.0, 2.0),
            rng.uniform(22.0, 30.0),
        );
        let pose = Isometry3::from_parts(
            Translation3::from(centre - rot * Vector3::new(w / 2.0, h / 2.0, 0.0)),
            rot,
        );
        let corners = [
            (-2.0 * s, -2.0 * s),
            (w + 2.0 * s, -2.0 * s),
            (-2.0 * s, h + 2.0 * s),
            (w + 2.0 * s, h + 2.0 * s),
        ];
        let visible = corners.iter().all(|&(x, y)| {
            rig.project(&(pose * Point3::new(x, y, 0.0)))
                .is_some_and(|(l, r)| rig.left.contains(l) && rig.right.contains(r))
        });
        if !visible {
            continue;
        }
        let l = render_view(&gl, &board, &pose)?;
        let r = render_view(&gr, &board, &(rig.right_from_left * pose))?;
        for (side, img) in [("left", &l), ("right", &r)] {
            let path = out.join(side).join(format!("board_{written:03}.png"));
            if !opencv::imgcodecs::imwrite(&path, img, &Vector::new())? {
                return Err(format!("could not write {}", path.display()).into());
            }
        }
        written += 1;
    }
    println!(
        "wrote {written} stereo pairs to {}/left and {}/right",
        out.display(),
        out.display()
    );
    Ok(())
}
