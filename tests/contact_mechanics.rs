//! End-to-end tests of the contact mechanics a user relies on: force and area from the bundled
//! sample (made by the bonded-layer simulator, data/sample/make-sample.sh) against its truth,
//! `gelstereo calibrate-gel` finding the gel's modulus from the truth's forces, and the gel's facts
//! refused with a clear message when they are wrong or disagree.

// A test helper may panic: that is how a test reports failure.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use gelstereo::core::{CsvTable, FrameSummary};

mod common;
use common::{gelstereo, sample, text};

fn frames(path: &std::path::Path) -> Vec<FrameSummary> {
    let t = CsvTable::read(path).unwrap();
    (0..t.len())
        .map(|r| FrameSummary::from_table(&t, r).unwrap())
        .collect()
}

#[test]
fn the_sample_gives_the_truths_force_and_area_and_records_the_gel() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let run = gelstereo(&[
        "track",
        "--quiet",
        "--out",
        out.to_str().unwrap(),
        sample().to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", text(&run));
    let est = frames(&out.join("frames.csv"));
    let truth = frames(&sample().join("frames.csv"));
    // Frames whose contact covers at least 4 pitch² (0.8 mm pitch).
    let pairs: Vec<(&FrameSummary, &FrameSummary)> = est
        .iter()
        .zip(&truth)
        .filter(|(_, t)| t.contact && t.contact_area_mm2.unwrap() >= 4.0 * 0.64)
        .collect();
    assert!(pairs.len() >= 25, "{} frames in contact", pairs.len());
    let within = |f: &dyn Fn(&FrameSummary) -> f64, tolerance: f64| {
        pairs
            .iter()
            .filter(|(e, t)| (f(e) / f(t) - 1.0).abs() <= tolerance)
            .count() as f64
            / pairs.len() as f64
    };
    let force = within(&|s| s.force_n.unwrap(), 0.1);
    let area = within(&|s| s.contact_area_mm2.unwrap(), 0.2);
    let area_close = within(&|s| s.contact_area_mm2.unwrap(), 0.1);
    assert!(
        area_close >= 0.8,
        "area within 10 % in {:.0} % of the frames",
        100.0 * area_close
    );
    assert!(
        force >= 0.8,
        "force within 10 % in {:.0} % of the frames",
        100.0 * force
    );
    assert!(
        area >= 0.9,
        "area within 20 % in {:.0} % of the frames",
        100.0 * area
    );
    let gel: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("gel.json")).unwrap()).unwrap();
    assert_eq!(gel["gel"]["modulus_kpa"], 150.0);
    let z = &gel["gel_frame_in_left_camera"]["z_axis"];
    assert!(
        z[2].as_f64().unwrap() > 0.9,
        "the gel's normal points away from the cameras: {z}"
    );
    // The height map of frame 20 (pressed, sliding) in the gel frame: the surface as deep at its
    // lowest as the truth's largest depth; the .npy holds the float heights.
    let scale: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("heightmap/scale.json")).unwrap()).unwrap();
    let (rows, cols) = (
        scale["rows"].as_u64().unwrap() as usize,
        scale["cols"].as_u64().unwrap() as usize,
    );
    assert_eq!((rows, cols), (89, 89));
    let file = std::fs::File::open(out.join("heightmap/000020.png")).unwrap();
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    reader.next_frame(&mut buf).unwrap();
    let lowest = buf
        .chunks_exact(2)
        .map(|b| f64::from(u16::from_be_bytes([b[0], b[1]])) / 1e4 - 3.2768)
        .fold(f64::INFINITY, f64::min);
    let deepest = truth[20].max_depth_mm.unwrap();
    assert!(
        (lowest + deepest).abs() < 0.1,
        "lowest {lowest} mm, truth's depth {deepest} mm"
    );
    // The PLYs are in the gel frame: the reference surface flat at z = 0 around the origin, the
    // pressed surface as deep as the truth.
    let cloud =
        |n: usize| gelstereo::io::ply::read_marker_cloud(&out.join(format!("ply/cloud_{n:06}.ply"))).unwrap();
    let rest = cloud(0);
    let mean = |k: usize| rest.iter().map(|p| p.position_mm[k]).sum::<f64>() / rest.len() as f64;
    assert!(
        mean(0).abs() < 0.05 && mean(1).abs() < 0.05,
        "centre ({}, {})",
        mean(0),
        mean(1)
    );
    // (Within the 3-D noise of the reference frame's markers.)
    assert!(
        rest.iter().all(|p| p.position_mm[2].abs() < 0.1),
        "the reference surface is flat at z = 0"
    );
    let pressed = cloud(20)
        .iter()
        .map(|p| p.position_mm[2])
        .fold(f64::INFINITY, f64::min);
    assert!(
        (pressed + deepest).abs() < 0.1,
        "lowest marker {pressed} mm, truth's depth {deepest} mm"
    );
    // markers.csv carries the gel frame beside the camera frame.
    let table = CsvTable::read(&out.join("markers.csv")).unwrap();
    let dz_gel = (0..table.len())
        .filter(|&r| table.value::<u32>(r, "frame", "").unwrap() == 20)
        .filter_map(|r| table.opt_f64(r, "dZ_gel_mm").unwrap())
        .fold(f64::INFINITY, f64::min);
    assert!(
        (dz_gel + deepest).abs() < 0.1,
        "dZ_gel_mm {dz_gel}, truth's depth {deepest} mm"
    );
    let npy = std::fs::read(out.join("heightmap/000020.npy")).unwrap();
    assert!(npy.starts_with(b"\x93NUMPY") && npy.len() > rows * cols * 4);
}

#[test]
fn calibrate_gel_finds_the_modulus_from_known_forces() {
    let dir = tempfile::tempdir().unwrap();
    let gel = dir.path().join("gel.json");
    let forces = sample().join("frames.csv");
    // Start from a modulus 40 % too low: the fit must land near the simulator's 150 kPa.
    let run = gelstereo(&[
        "calibrate-gel",
        "--forces",
        forces.to_str().unwrap(),
        "--gel-modulus-kpa",
        "90",
        "--out",
        gel.to_str().unwrap(),
        sample().to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", text(&run));
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&gel).unwrap()).unwrap();
    let modulus = v["gel"]["modulus_kpa"].as_f64().unwrap();
    assert!(
        (modulus / 150.0 - 1.0).abs() < 0.1,
        "{modulus} kPa; {}",
        text(&run)
    );
    // The file feeds `track --gel`; a flag that disagrees with it is refused.
    let out = dir.path().join("out");
    let clash = gelstereo(&[
        "track",
        "--gel",
        gel.to_str().unwrap(),
        "--gel-modulus-kpa",
        "300",
        "--out",
        out.to_str().unwrap(),
        sample().to_str().unwrap(),
    ]);
    assert!(!clash.status.success());
    assert!(
        text(&clash).contains("disagrees with") && text(&clash).contains("gel.json"),
        "{}",
        text(&clash)
    );
    // Refuses to replace the file without --force.
    let again = gelstereo(&[
        "calibrate-gel",
        "--force-n",
        "1",
        "--out",
        gel.to_str().unwrap(),
        sample().to_str().unwrap(),
    ]);
    assert!(
        !again.status.success() && text(&again).contains("--force"),
        "{}",
        text(&again)
    );
}

#[test]
fn bad_gel_facts_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    for (flag, value, named) in [
        ("--poisson", "0.5", "poisson"),
        ("--poisson", "NaN", "poisson"),
        ("--gel-modulus-kpa", "-3", "modulus_kpa"),
        ("--gel-thickness-mm", "0", "thickness_mm"),
        ("--friction", "inf", "friction"),
    ] {
        let out = dir.path().join(format!("out-{}", flag.trim_start_matches('-')));
        let run = gelstereo(&[
            "track",
            flag,
            value,
            "--out",
            out.to_str().unwrap(),
            sample().to_str().unwrap(),
        ]);
        assert!(!run.status.success(), "{flag} {value} accepted");
        assert!(text(&run).contains(named), "{flag} {value}: {}", text(&run));
        assert!(!out.exists(), "{flag} {value}: an output folder was made");
    }
}

/// The first frame in gross slip.
fn gross_onset(frames: &[FrameSummary]) -> Option<usize> {
    frames
        .iter()
        .position(|f| f.slip == gelstereo::core::SlipState::GrossSlip)
}

#[test]
fn a_sliding_flat_punch_is_flagged_gross_within_a_frame_of_its_onset() {
    // A flat punch (a singular pressure at its rim, the case a kinematic slip rule flags early or
    // not at all) pressed, sheared through partial slip and slid, simulated by the bonded layer.
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    let made = gelstereo(&[
        "simulate",
        "--quiet",
        "--out",
        sim.to_str().unwrap(),
        "--experiments",
        "1",
        "--frames-per-experiment",
        "30",
        "--seed",
        "2",
        "--randomization",
        "off",
        "--indenter",
        "flat_cylinder",
        "--motion",
        "press-slide",
    ]);
    assert!(made.status.success(), "{}", text(&made));
    let rec = sim.join("train/exp_0000");
    let meta = std::fs::read_to_string(rec.join("meta.json")).unwrap();
    assert!(
        meta.contains("\"flat_cylinder\"") && meta.contains("\"press_slide\""),
        "{meta}"
    );
    let out = dir.path().join("out");
    let run = gelstereo(&[
        "track",
        "--quiet",
        "--out",
        out.to_str().unwrap(),
        rec.to_str().unwrap(),
    ]);
    assert!(run.status.success(), "{}", text(&run));
    let truth = frames(&rec.join("frames.csv"));
    let est = frames(&out.join("frames.csv"));
    let truth_onset = gross_onset(&truth).expect("the simulated slide reaches gross slip");
    assert!(
        truth[..truth_onset]
            .iter()
            .any(|f| f.slip == gelstereo::core::SlipState::PartialSlip),
        "the slide passes through partial slip first"
    );
    let onset = gross_onset(&est).expect("gross slip flagged");
    assert!(
        onset.abs_diff(truth_onset) <= 1,
        "gross slip flagged at frame {onset}, truth {truth_onset}"
    );
    let first_contact = truth.iter().position(|f| f.contact).unwrap();
    assert!(
        est[..first_contact]
            .iter()
            .all(|f| f.slip == gelstereo::core::SlipState::NoContact),
        "slip before contact"
    );
}
