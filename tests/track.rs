//! End-to-end tests of `gelstereo track`: the bundled sample recording (data/sample/press-slide,
//! made by data/sample/make-sample.sh), a damaged copy of it, and the real GelSight Mini video
//! (../shared/real/gelsight-mini-press, skipped with a message when that folder is absent).

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::collections::BTreeMap;
use std::path::Path;

use gelstereo::core::{CsvTable, FrameSummary, GridIndex, MarkerRecord, MarkerStatus, SlipState};
use opencv::prelude::MatTraitConst;

mod common;
use common::{gelstereo_command, repo, sample_copy};

fn track(args: &[&str]) -> (bool, String) {
    let out = gelstereo_command()
        .arg("track")
        .arg("--quiet")
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn frames(path: &Path) -> Vec<FrameSummary> {
    let t = CsvTable::read(path).unwrap();
    (0..t.len())
        .map(|r| FrameSummary::from_table(&t, r).unwrap())
        .collect()
}

fn markers(path: &Path) -> Vec<MarkerRecord> {
    let t = CsvTable::read(path).unwrap();
    (0..t.len())
        .map(|r| MarkerRecord::from_table(&t, r).unwrap())
        .collect()
}

#[test]
fn sample_recording_gives_tables_meshes_overlays_plots_and_the_slip_of_the_truth() {
    let sample = repo().join("data/sample/press-slide");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let (ok, err) = track(&[
        "--method",
        "blob",
        "--out",
        out.to_str().unwrap(),
        sample.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let est = frames(&out.join("frames.csv"));
    let truth = frames(&sample.join("frames.csv"));
    assert_eq!(est.len(), truth.len());
    for f in [
        "ply/cloud_000010.ply",
        "ply/mesh_000010.ply",
        "overlays/000010.png",
        "overlays/depth_000010.png",
        "plots/contact_area.png",
        "plots/max_depth.png",
        "plots/force.png",
        "plots/force.svg",
        "plots/pressure.png",
        "plots/pressure.svg",
        "plots/pressure_map.png",
        "plots/pressure_map.svg",
        "plots/slip.png",
        "plots/slip.svg",
        "plots/max_depth.svg",
        "plots/contact_surface.png",
        "plots/contact_surface.svg",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // Every id in every frame, and every tracked marker within r = 0.25 pitch (4 px, docs/design.md) of
    // its own ground-truth marker: no id swaps.
    let rows = markers(&out.join("markers.csv"));
    assert_eq!(rows.len(), 40 * 529);
    let gt: BTreeMap<(u32, GridIndex), MarkerRecord> = markers(&sample.join("markers.csv"))
        .into_iter()
        .map(|m| ((m.frame, m.index), m))
        .collect();
    for m in rows.iter().filter(|m| m.status == Some(MarkerStatus::Tracked)) {
        let (p, q) = (m.left_px.unwrap(), gt[&(m.frame, m.index)].left_px.unwrap());
        assert!(
            p.distance(q) < 4.0,
            "frame {} marker {}: {p:?} vs {q:?}",
            m.frame,
            m.index
        );
    }
    // Gross slip onset within 2 frames of the truth, nothing but no_contact before contact, depth
    // within 0.05 mm where the press is established.
    let onset = |v: &[FrameSummary]| v.iter().position(|f| f.slip == SlipState::GrossSlip).unwrap();
    assert!(
        onset(&est).abs_diff(onset(&truth)) <= 2,
        "onset {} vs {}",
        onset(&est),
        onset(&truth)
    );
    let first_contact = truth.iter().position(|f| f.contact).unwrap();
    assert!(
        est[..first_contact]
            .iter()
            .all(|f| f.slip == SlipState::NoContact)
    );
    for (e, t) in est.iter().zip(&truth) {
        let (Some(e_depth), Some(t_depth)) = (e.max_depth_mm, t.max_depth_mm) else {
            panic!("frame {}: a stereo run and its truth give every depth", e.frame)
        };
        if t_depth > 0.1 {
            assert!(
                (e_depth - t_depth).abs() < 0.05,
                "frame {}: {e_depth} vs {t_depth}",
                e.frame
            );
        }
    }
}

#[test]
fn unreadable_and_resized_frames_are_flagged_not_fatal_and_missing_ones_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let rec = sample_copy(dir.path(), 8);
    std::fs::write(rec.join("left/000003.jpg"), b"not a jpeg").unwrap();
    // A frame of another size: the left image of frame 5 cropped to 320x240.
    let img = opencv::imgcodecs::imread(
        rec.join("left/000005.jpg").to_str().unwrap(),
        opencv::imgcodecs::IMREAD_COLOR,
    )
    .unwrap();
    let small = opencv::core::Mat::roi(&img, opencv::core::Rect::new(0, 0, 320, 240))
        .unwrap()
        .try_clone()
        .unwrap();
    opencv::imgcodecs::imwrite(
        rec.join("left/000005.jpg").to_str().unwrap(),
        &small,
        &opencv::core::Vector::new(),
    )
    .unwrap();
    // A frame that shows no marker at all (both views black).
    let black = opencv::core::Mat::new_rows_cols_with_default(
        480,
        640,
        opencv::core::CV_8UC3,
        opencv::core::Scalar::all(0.0),
    )
    .unwrap();
    for side in ["left", "right"] {
        let path = rec.join(side).join("000007.jpg");
        opencv::imgcodecs::imwrite(path.to_str().unwrap(), &black, &opencv::core::Vector::new()).unwrap();
    }
    let out = dir.path().join("out");
    let (ok, err) = track(&[
        "--method",
        "blob",
        "--no-ply",
        "--overlay-every",
        "0",
        "--out",
        out.to_str().unwrap(),
        rec.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(err.contains("frame 3") && err.contains("000003.jpg"), "{err}");
    assert!(err.contains("frame 5") && err.contains("320x240"), "{err}");
    let est = frames(&out.join("frames.csv"));
    assert_eq!(
        est.iter().map(|f| f.frame).collect::<Vec<_>>(),
        (0..8).collect::<Vec<_>>(),
        "no gap in frames.csv"
    );
    assert!(
        err.contains("frame 7") && err.contains("no usable markers"),
        "{err}"
    );
    let rows = markers(&out.join("markers.csv"));
    for bad in [3, 5] {
        let lost: Vec<_> = rows.iter().filter(|m| m.frame == bad as u32).collect();
        assert!(
            lost.len() == 529
                && lost
                    .iter()
                    .all(|m| m.status == Some(MarkerStatus::Lost) && m.position_mm.is_none())
        );
    }
    // Frames that know nothing of the contact say so: every contact cell empty, not 0 or
    // no_contact, and the note says why.
    let table = std::fs::read_to_string(out.join("frames.csv")).unwrap();
    for bad in [3, 5, 7] {
        assert!(!est[bad].measured, "frame {bad}: {:?}", est[bad]);
        let line = table.lines().nth(bad + 1).unwrap();
        assert!(line.starts_with(&format!("{bad},,,,,,,,,,,")), "{line}");
        assert!(
            line.split(',').next_back().is_some_and(|note| !note.is_empty()),
            "{line}"
        );
    }
    assert!(
        est[..7]
            .iter()
            .enumerate()
            .all(|(k, f)| f.measured || k == 3 || k == 5)
    );
    // A frame missing from one view is an error that names it.
    std::fs::remove_file(rec.join("right/000006.jpg")).unwrap();
    let (ok, err) = track(&[
        "--method",
        "blob",
        "--out",
        out.to_str().unwrap(),
        rec.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("left/000006.jpg has no counterpart"), "{err}");
    // A folder without markers: a clear error, no panic.
    let blank = dir.path().join("blank");
    std::fs::create_dir_all(&blank).unwrap();
    let grey = opencv::core::Mat::new_rows_cols_with_default(
        240,
        320,
        opencv::core::CV_8UC3,
        opencv::core::Scalar::all(128.0),
    )
    .unwrap();
    for k in 0..3 {
        opencv::imgcodecs::imwrite(
            blank.join(format!("{k}.png")).to_str().unwrap(),
            &grey,
            &opencv::core::Vector::new(),
        )
        .unwrap();
    }
    let (ok, err) = track(&[
        "--method",
        "blob",
        "--out",
        out.to_str().unwrap(),
        blank.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("no frame could be indexed"), "{err}");
}

#[test]
fn real_gelsight_mini_video_keeps_its_ids_and_reports_the_hard_slide() {
    let video = repo().join("../shared/real/gelsight-mini-press/mini_example.avi");
    if !video.is_file() {
        eprintln!(
            "SKIPPED: {} is absent (the real GelSight Mini video lives beside the checkout in ../shared)",
            video.display()
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("mini");
    let (ok, err) = track(&[
        "--grid",
        "8x10",
        "--overlay-every",
        "0",
        "--out",
        out.to_str().unwrap(),
        video.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let rows = markers(&out.join("markers.csv"));
    let est = frames(&out.join("frames.csv"));
    assert_eq!(est.len(), 219);
    let mut by_frame: BTreeMap<u32, BTreeMap<GridIndex, &MarkerRecord>> = BTreeMap::new();
    for m in &rows {
        by_frame.entry(m.frame).or_default().insert(m.index, m);
    }
    // Every marker whose centre lies inside the image tracked in every frame 0-55 (no contact): 74
    // of the 80; the top row's other six dots show a sliver of themselves, their centres above it.
    for f in 0..=55 {
        let tracked = by_frame[&f]
            .values()
            .filter(|m| m.status == Some(MarkerStatus::Tracked))
            .count();
        assert_eq!(tracked, 74, "frame {f}");
    }
    // The same ids throughout: no id ever jumps by more than half a pitch (31 px) between frames.
    for f in 1..219u32 {
        for (id, m) in &by_frame[&f] {
            if let (Some(p), Some(q)) = (m.left_px, by_frame[&(f - 1)][id].left_px) {
                assert!(
                    p.distance(q) < 15.0,
                    "frame {f} marker {id} jumped {:.1} px",
                    p.distance(q)
                );
            }
        }
    }
    // Back within 0.6 px (median) of frame 0 at the last frame.
    let mut back: Vec<f64> = by_frame[&218]
        .iter()
        .filter_map(|(id, m)| Some(m.left_px?.distance(by_frame[&0][id].left_px?)))
        .collect();
    back.sort_by(f64::total_cmp);
    assert!(back[back.len() / 2] < 0.6, "median {}", back[back.len() / 2]);
    // No slip before the press; slip during the hard slide.
    assert!(est[..=55].iter().all(|f| f.slip == SlipState::NoContact));
    let slipping = est[150..=205]
        .iter()
        .filter(|f| matches!(f.slip, SlipState::PartialSlip | SlipState::GrossSlip))
        .count();
    assert!(slipping >= 25, "{slipping} slipping frames in 150-205");
    // Without --pitch-mm the image gives no scale: area and depth are unknown (empty cells), not 0.
    for f in &est {
        assert_eq!(
            (f.contact_area_mm2, f.max_depth_mm),
            (None, None),
            "frame {}",
            f.frame
        );
    }
}

/// Frames localized ahead of the tracker by worker threads (the default) give the tables of one
/// frame at a time on a real mono video: the workers go on with the remembered
/// pitch of the reference frame's localizer, whose auto layout scales this sensor's image.
#[test]
fn real_mono_video_tracks_alike_with_frames_localized_ahead_and_one_at_a_time() {
    let video = repo().join("../shared/real/gelsight-mini-press/mini_example.avi");
    if !video.is_file() {
        eprintln!("SKIPPED: {} is absent", video.display());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let tables = |workers: &str| {
        let out = dir.path().join(workers);
        let (ok, err) = track(&[
            "--workers",
            workers,
            "--grid",
            "8x10",
            "--max-frames",
            "80",
            "--overlay-every",
            "0",
            "--out",
            out.to_str().unwrap(),
            video.to_str().unwrap(),
        ]);
        assert!(ok, "--workers {workers}: {err}");
        ["markers.csv", "frames.csv"].map(|f| std::fs::read_to_string(out.join(f)).unwrap())
    };
    let one = tables("1");
    assert_eq!(frames(&dir.path().join("1/frames.csv")).len(), 80);
    assert_eq!(tables("2"), one);
}

/// A sensor whose 28 x 13 grid overfills the 400 x 300 views (data/fixtures, the sensor variant of
/// `gelstereo simulate --seed 606` train/exp_0006): the whole-lattice indexing refused it; now the
/// recording's sensor description places the visible markers on the sensor's own grid indices, in
/// both views, and the reference frame's ids and pairs are the truth's.
#[test]
fn a_grid_that_overfills_the_view_is_placed_on_the_sensors_own_indices() {
    let dir = tempfile::tempdir().unwrap();
    let rec_root = dir.path().join("sim");
    let sensor = repo().join("data/fixtures/sensor-overfilled-28x13.json");
    let out = gelstereo_command()
        .args([
            "simulate",
            "--quiet",
            "--experiments",
            "1",
            "--frames-per-experiment",
            "30",
        ])
        .args(["--seed", "3", "--randomization", "off", "--sensor"])
        .arg(&sensor)
        .arg("--out")
        .arg(&rec_root)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rec = rec_root.join("train/exp_0000");
    let out_dir = dir.path().join("out");
    let (ok, err) = track(&[
        "--from-ground-truth",
        "--no-ply",
        "--overlay-every",
        "0",
        "--max-frames",
        "2",
        "--out",
        out_dir.to_str().unwrap(),
        rec.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(
        err.contains("overfills the view: placed by the sensor description"),
        "{err}"
    );
    // Reference frame: every marker the truth shows in both views is tracked under its true id,
    // with both of its positions (ground-truth positions in, so exactly).
    let t = CsvTable::read(&rec.join("markers.csv")).unwrap();
    let mut truth = BTreeMap::new();
    for r in 0..t.len() {
        let m = MarkerRecord::from_table(&t, r).unwrap();
        let both = t.cell(r, "visible_left").unwrap() == "1" && t.cell(r, "visible_right").unwrap() == "1";
        if m.frame == 0 && both {
            truth.insert(m.index, m);
        }
    }
    let est: Vec<MarkerRecord> = markers(&out_dir.join("markers.csv"))
        .into_iter()
        .filter(|m| m.frame == 0 && m.status == Some(MarkerStatus::Tracked))
        .collect();
    assert!(truth.len() > 250, "the fixture shows most of the grid");
    assert_eq!(
        est.len(),
        truth.len(),
        "tracked in frame 0 vs visible in both views"
    );
    for m in &est {
        let t = truth
            .get(&m.index)
            .unwrap_or_else(|| panic!("{} is not visible in the truth", m.index));
        for (a, b) in [(m.left_px, t.left_px), (m.right_px, t.right_px)] {
            let (a, b) = (a.unwrap(), b.unwrap());
            assert!(a.distance(b) < 1e-3, "{}: {a:?} vs truth {b:?}", m.index);
        }
    }
}

/// The sample's press-then-slide (`data/sample/make-sample.sh`: seed 3, reference look) simulated
/// in 12 frames instead of 40: the slide moves the contact's markers up to 1.2 pitch from one
/// frame to the next and the released gel springs back 1.4 pitch. Every marker written `tracked`
/// sits on its own marker (no id swap), almost every visible one is tracked, and gross slip is
/// flagged from the frame the truth has it.
#[test]
fn a_fast_press_then_slide_keeps_every_id_and_flags_gross_slip_in_time() {
    let dir = tempfile::tempdir().unwrap();
    let rec_root = dir.path().join("sim");
    let out = gelstereo_command()
        .args(["simulate", "--quiet", "--experiments", "1"])
        .args([
            "--frames-per-experiment",
            "12",
            "--seed",
            "3",
            "--randomization",
            "off",
        ])
        .arg("--out")
        .arg(&rec_root)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rec = rec_root.join("train/exp_0000");
    let out_dir = dir.path().join("out");
    let (ok, err) = track(&[
        "--no-ply",
        "--overlay-every",
        "0",
        "--out",
        out_dir.to_str().unwrap(),
        rec.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let gt: BTreeMap<(u32, GridIndex), MarkerRecord> = markers(&rec.join("markers.csv"))
        .into_iter()
        .map(|m| ((m.frame, m.index), m))
        .collect();
    // r = 0.25 pitch (the pitch is 16.7 px in the left view of the reference frame).
    let r = 0.25 * 16.7;
    let rows = markers(&out_dir.join("markers.csv"));
    let mut tracked = 0;
    for m in rows.iter().filter(|m| m.status == Some(MarkerStatus::Tracked)) {
        tracked += 1;
        let t = &gt[&(m.frame, m.index)];
        for (p, q) in [(m.left_px, t.left_px), (m.right_px, t.right_px)] {
            let (p, q) = (p.unwrap(), q.unwrap());
            assert!(
                p.distance(q) < r,
                "frame {} marker {}: {p:?} vs {q:?}",
                m.frame,
                m.index
            );
        }
    }
    // Slides of more than half a pitch per frame lose markers, or hand them to a neighbour, unless
    // the association follows the contact's motion outward from the still lattice.
    assert!(tracked >= 12 * 529 * 97 / 100, "{tracked} marker-frames tracked");
    let est = frames(&out_dir.join("frames.csv"));
    let truth = frames(&rec.join("frames.csv"));
    let gross = |v: &[FrameSummary]| -> Vec<u32> {
        v.iter()
            .filter(|f| f.slip == SlipState::GrossSlip)
            .map(|f| f.frame)
            .collect()
    };
    let (e, t) = (gross(&est), gross(&truth));
    assert!(
        !t.is_empty() && e.first() == t.first(),
        "gross slip in {e:?}, truth {t:?}"
    );
}
