//! Regenerates `docs/contact-sheet.png`: simulated frames (press, slide, several indenters, hard
//! contact areas, the reference and a GelSight-like look) above frames of the real GelSight Mini
//! recording in `../shared/real/`, so a reader can judge realism.
//!
//! ```text
//! cargo run --release -p gelstereo-sim --example contact_sheet -- [REAL_VIDEO] [OUT.png]
//! ```
//! Defaults: `../shared/real/gelsight-mini-press/mini_example.avi` and `docs/contact-sheet.png`
//! (relative to the repository root). Without the video the real rows are left out.

use std::path::{Path, PathBuf};

use gelstereo_sim::dataset::{Experiment, Simulator, Split};
use gelstereo_sim::motion::{MotionKind, Script};
use gelstereo_sim::render::rgb_to_bgr;
use gelstereo_sim::variant::gelsight_mini_like;
use gelstereo_sim::{Appearance, Indenter, SensorSpec};
use opencv::core::{CV_8UC3, Mat, Point, Rect, Scalar, Size, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc, videoio};
use rand::SeedableRng;

const TILE_W: i32 = 320;
const TILE_H: i32 = 240;

struct Tile {
    label: String,
    /// BGR, any size (resized to the tile).
    image: Mat,
}

#[allow(clippy::too_many_arguments)]
fn sim_tile(
    label: &str,
    sensor: SensorSpec,
    appearance: Appearance,
    indenter: Indenter,
    kind: MotionKind,
    depth: f64,
    slide: [f64; 2],
    twist: f64,
    show: f64,
) -> Result<Tile, Box<dyn std::error::Error>> {
    let frames = 40;
    let script = Script {
        indenter,
        kind,
        centre_mm: [0.0, 0.0],
        angle_deg: 20.0,
        max_depth_mm: depth,
        slide_mm: slide,
        twist_deg: twist,
        frames,
        press_end: 0.35,
        shear_end: 0.9,
        release: false,
    };
    let exp = Experiment {
        index: 0,
        split: Split::Test,
        seed: 7,
        sensor,
        appearance,
        script,
        families: Vec::new(),
    };
    let sim = Simulator::new(exp)?;
    let frame = sim.frame((show * f64::from(frames - 1)).round() as u32)?;
    let [left, _] = frame.images;
    Ok(Tile {
        label: format!("sim: {label}"),
        image: rgb_to_bgr(&left)?,
    })
}

fn real_tiles(video: &Path, frames: &[i32]) -> Result<Vec<Tile>, Box<dyn std::error::Error>> {
    let mut cap = videoio::VideoCapture::from_file(video.to_string_lossy().as_ref(), videoio::CAP_ANY)?;
    if !cap.is_opened()? {
        return Err(format!("{}: cannot open the video", video.display()).into());
    }
    let mut out = Vec::new();
    let mut i = 0;
    let mut img = Mat::default();
    while cap.read(&mut img)? {
        if frames.contains(&i) {
            out.push(Tile {
                label: format!("real GelSight Mini, frame {i}"),
                image: img.try_clone()?,
            });
        }
        i += 1;
    }
    Ok(out)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let args: Vec<String> = std::env::args().skip(1).collect();
    let video = args
        .first()
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join("../shared/real/gelsight-mini-press/mini_example.avi"));
    let out = args
        .get(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join("docs/contact-sheet.png"));

    let reference = SensorSpec::reference;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let mut light_on_dark = Appearance::reference();
    light_on_dark.background = [38.0, 42.0, 60.0];
    light_on_dark.marker_color = [235.0, 232.0, 220.0];
    light_on_dark.gradient_x = [10.0, 20.0, -10.0];
    light_on_dark.contact_tint = [90.0, 110.0, 140.0];
    let mut gs = Appearance::random_gelsight_like(&mut rng);
    gs.jpeg_quality = Some(60);
    let mut gs2 = Appearance::random_gelsight_like(&mut rng);
    gs2.motion_blur = 0.8;
    use MotionKind::*;
    let mut tiles = vec![
        sim_tile(
            "sphere R4, press 1.0 mm",
            reference(),
            Appearance::reference(),
            Indenter::Sphere { radius_mm: 4.0 },
            Press,
            1.0,
            [0.0; 2],
            0.0,
            0.36,
        )?,
        sim_tile(
            "sphere R6, slide 3 mm (gross slip)",
            reference(),
            Appearance::reference(),
            Indenter::Sphere { radius_mm: 6.0 },
            PressSlide,
            1.0,
            [3.0, 0.8],
            0.0,
            0.9,
        )?,
        sim_tile(
            "star, hard press 0.5 mm",
            reference(),
            Appearance::reference(),
            Indenter::Star { radius_mm: 4.5 },
            Press,
            0.5,
            [0.0; 2],
            0.0,
            0.36,
        )?,
        sim_tile(
            "text 'HEL', press",
            reference(),
            Appearance::random(&mut rng),
            Indenter::Text {
                text: "HEL".into(),
                height_mm: 3.5,
            },
            Press,
            0.45,
            [0.0; 2],
            0.0,
            0.36,
        )?,
        sim_tile(
            "cube corner + twist 20 deg",
            reference(),
            Appearance::random(&mut rng),
            Indenter::CubeCorner,
            PressTwist,
            0.8,
            [0.0; 2],
            20.0,
            0.9,
        )?,
        sim_tile(
            "nut, light-on-dark markers",
            reference(),
            light_on_dark,
            Indenter::Nut {
                radius_mm: 4.0,
                hole_mm: 2.0,
            },
            Press,
            0.5,
            [0.0; 2],
            0.0,
            0.36,
        )?,
        sim_tile(
            "GelSight-like, fingertip press",
            gelsight_mini_like(),
            gs.clone(),
            Indenter::Fingertip {
                rx_mm: 6.0,
                ry_mm: 8.5,
            },
            Press,
            1.2,
            [0.0; 2],
            0.0,
            0.36,
        )?,
        sim_tile(
            "GelSight-like, finger slide",
            gelsight_mini_like(),
            gs2,
            Indenter::Fingertip {
                rx_mm: 5.5,
                ry_mm: 8.0,
            },
            PressSlide,
            1.4,
            [2.5, -0.5],
            0.0,
            0.8,
        )?,
    ];
    if video.exists() {
        tiles.extend(real_tiles(&video, &[0, 80, 100, 130, 160, 175, 190, 200])?);
    } else {
        eprintln!(
            "{}: not found, the sheet has simulated frames only",
            video.display()
        );
    }

    let cols = 4;
    let rows = tiles.len().div_ceil(cols) as i32;
    let label_h = 18;
    let mut sheet = Mat::new_rows_cols_with_default(
        rows * (TILE_H + label_h),
        cols as i32 * TILE_W,
        CV_8UC3,
        Scalar::all(255.0),
    )?;
    for (k, t) in tiles.iter().enumerate() {
        let (r, c) = ((k / cols) as i32, (k % cols) as i32);
        let (x, y) = (c * TILE_W, r * (TILE_H + label_h));
        let mut small = Mat::default();
        imgproc::resize(
            &t.image,
            &mut small,
            Size::new(TILE_W, TILE_H),
            0.0,
            0.0,
            imgproc::INTER_AREA,
        )?;
        let mut roi = sheet.roi_mut(Rect::new(x, y + label_h, TILE_W, TILE_H))?;
        small.copy_to(&mut roi)?;
        imgproc::put_text(
            &mut sheet,
            &t.label,
            Point::new(x + 4, y + 13),
            imgproc::FONT_HERSHEY_SIMPLEX,
            0.42,
            Scalar::new(20.0, 20.0, 20.0, 0.0),
            1,
            imgproc::LINE_AA,
            false,
        )?;
    }
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    imgcodecs::imwrite(
        out.to_string_lossy().as_ref(),
        &sheet,
        &Vector::<i32>::from_slice(&[imgcodecs::IMWRITE_PNG_COMPRESSION, 9]),
    )?;
    eprintln!("wrote {}", out.display());
    Ok(())
}
