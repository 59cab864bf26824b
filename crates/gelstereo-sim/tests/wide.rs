//! The widened randomisation (`--randomization wide`): its sensors and looks keep the ground truth
//! exact (markers outside a membrane are not printed and never visible; a marker whose centre is
//! outside the image is not visible; lattices have the promised geometry), each experiment names
//! its families, and the same seed gives the same bytes.
#![allow(clippy::unwrap_used)]

use gelstereo_sim::dataset::{DatasetConfig, Randomization, plan};
use gelstereo_sim::sensor::{Lattice, Membrane};
use gelstereo_sim::{SensorSpec, Simulator};

fn wide_plan(experiments: u32, frames: u32, seed: u64) -> Vec<gelstereo_sim::Experiment> {
    let mut cfg = DatasetConfig::new(experiments, frames, seed);
    cfg.randomization = Randomization::Wide;
    plan(&cfg).unwrap()
}

#[test]
fn wide_plans_cover_the_families_and_tag_them() {
    let exps = wide_plan(120, 2, 9);
    let all: std::collections::BTreeSet<&str> = exps
        .iter()
        .flat_map(|e| e.families.iter().map(String::as_str))
        .collect();
    for fam in [
        "marker:dark",
        "marker:light",
        "marker:hue",
        "lattice:square",
        "lattice:hexagonal",
        "lattice:irregular",
        "membrane:none",
        "membrane:circle",
        "membrane:trapezoid",
        "res:1920x1080",
        "pitch:<16",
        "pitch:>40",
        "texture:scanlines",
        "texture:banding",
        "texture:moire",
        "texture:fingerprint",
        "texture:newton_rings",
        "texture:glint",
    ] {
        assert!(all.contains(fam), "no experiment of family {fam} in 120: {all:?}");
    }
    for e in &exps {
        let s = e.sensor.build().unwrap();
        let pitch = s.pitch_px();
        assert!(
            (7.0..=115.0).contains(&pitch),
            "{}: pitch {pitch} px",
            e.sensor.name
        );
        assert!(e.sensor.cameras.image_width <= 1920 && e.sensor.cameras.image_height <= 1080);
    }
    // The `full` randomisation tags nothing (its datasets stay as they were).
    let full = plan(&DatasetConfig::new(10, 2, 9)).unwrap();
    assert!(full.iter().all(|e| e.families.is_empty()));
}

#[test]
fn hexagonal_and_irregular_lattices_have_their_geometry() {
    let mut spec = SensorSpec::reference();
    spec.grid.lattice = Lattice::Hexagonal;
    let p = spec.grid.pitch_mm;
    let pts: Vec<[f64; 2]> = spec
        .grid_shape()
        .indices()
        .map(|i| spec.marker_rest_mm(i.row, i.col))
        .collect();
    // An inner marker has six neighbours at one pitch, none closer.
    let centre = spec.marker_rest_mm(11, 11);
    let d: Vec<f64> = pts
        .iter()
        .map(|q| (q[0] - centre[0]).hypot(q[1] - centre[1]))
        .filter(|&d| d > 1e-9)
        .collect();
    let six = d.iter().filter(|&&x| (x - p).abs() < 1e-9).count();
    assert_eq!(six, 6);
    assert!(d.iter().all(|&x| x > p - 1e-9));
    spec.build().unwrap();

    let mut spec = SensorSpec::reference();
    spec.grid.lattice = Lattice::Irregular {
        jitter_frac: 0.2,
        seed: 5,
    };
    let a = spec.marker_rest_mm(3, 4);
    assert_eq!(a, spec.marker_rest_mm(3, 4), "reproducible");
    let square = SensorSpec::reference().marker_rest_mm(3, 4);
    let moved = (a[0] - square[0]).abs().max((a[1] - square[1]).abs());
    assert!(moved > 0.0 && moved <= 0.2 * p + 1e-12, "moved {moved} mm");
    spec.grid.lattice = Lattice::Irregular {
        jitter_frac: 0.5,
        seed: 5,
    };
    let e = spec.validate("s.json").unwrap_err().to_string();
    assert!(e.contains("grid.lattice.jitter_frac"), "{e}");
}

#[test]
fn membranes_hold_whole_dots_and_name_bad_fields() {
    let m = Membrane::Circle { radius_mm: 5.0 };
    assert!(m.holds(0.0, 4.7, 0.2) && !m.holds(0.0, 4.9, 0.2));
    let t = Membrane::Trapezoid {
        top_half_width_mm: 2.0,
        bottom_half_width_mm: 4.0,
        half_height_mm: 3.0,
    };
    // Half-width 3 at y = 0: inside at x = 2.5, outside at 3.5; above the top edge is outside.
    assert!(t.holds(2.5, 0.0, 0.1) && !t.holds(3.5, 0.0, 0.0) && !t.holds(0.0, -3.2, 0.0));
    let mut spec = SensorSpec::reference();
    spec.membrane = Some(Membrane::Circle { radius_mm: -1.0 });
    let e = spec.validate("s.json").unwrap_err().to_string();
    assert!(e.contains("membrane.radius_mm"), "{e}");
}

/// Every wide experiment's frames: visibility is exactly "printed and centre inside the image"
/// in both views, unprinted markers exist only with a membrane, and frames are reproducible.
#[test]
fn wide_ground_truth_is_consistent_and_reproducible() {
    let exps = wide_plan(60, 3, 21);
    // Up to four each of: lattices overfilling the images, membranes, the rest (small images only).
    let kind = |e: &gelstereo_sim::Experiment| {
        let overfill = e.sensor.build().unwrap().visible_fraction_at_rest(0.0) < 0.95;
        usize::from(e.sensor.membrane.is_some()) + 2 * usize::from(overfill && e.sensor.membrane.is_none())
    };
    let small: Vec<_> = exps
        .iter()
        .filter(|e| e.sensor.cameras.image_width <= 640)
        .collect();
    let picked = (0..3).flat_map(|k| small.iter().filter(move |e| kind(e) == k).take(4));
    let mut with_membrane = 0;
    let mut cut_by_border = 0;
    for e in picked {
        let sim = Simulator::new((*e).clone()).unwrap();
        let f = sim.frame(2).unwrap();
        let cams = [&sim.sensor.rig.left, &sim.sensor.rig.right];
        let mut rows = String::new();
        sim.marker_rows(2, &f.markers, &mut rows);
        for (m, line) in f.markers.iter().zip(rows.lines()) {
            let cols: Vec<&str> = line.split(',').collect();
            let vis = &cols[cols.len() - 2..];
            for v in 0..2 {
                let inside = m.px[v].is_some_and(|q| cams[v].contains(q));
                let want = if m.printed && inside { "1" } else { "0" };
                assert_eq!(vis[v], want, "{}: marker {:?} view {v}", e.name(), m.index);
                if m.printed && !inside && m.px[v].is_some() {
                    cut_by_border += 1;
                }
            }
            assert!(m.printed || e.sensor.membrane.is_some());
        }
        with_membrane += usize::from(e.sensor.membrane.is_some());
        // Same experiment, same frame: same pixels.
        let again = Simulator::new((*e).clone()).unwrap().frame(2).unwrap();
        for v in 0..2 {
            use opencv::core::MatTraitConstManual;
            assert_eq!(
                f.images[v].data_bytes().unwrap(),
                again.images[v].data_bytes().unwrap(),
                "{} view {v}",
                e.name()
            );
        }
    }
    assert!(
        with_membrane > 0 && cut_by_border > 0,
        "{with_membrane} {cut_by_border}"
    );
}

/// `--split test` writes only the test experiments, byte for byte as the whole dataset holds them.
#[test]
fn one_split_is_the_same_files_as_in_the_whole_dataset() {
    use gelstereo_sim::dataset::{Split, write_dataset};
    let tmp = tempfile::tempdir().unwrap();
    let cfg = DatasetConfig::new(5, 2, 8);
    write_dataset(&tmp.path().join("all"), &cfg, false, &|| {}).unwrap();
    let mut only = cfg.clone();
    only.only_split = Some(Split::Test);
    write_dataset(&tmp.path().join("test"), &only, false, &|| {}).unwrap();
    let names = |d: &std::path::Path| {
        let mut v: Vec<_> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        v.sort();
        v
    };
    let test_exps = names(&tmp.path().join("all/test"));
    assert!(!test_exps.is_empty());
    assert_eq!(
        names(&tmp.path().join("test")),
        ["dataset.json", "test"].map(std::ffi::OsString::from)
    );
    assert_eq!(names(&tmp.path().join("test/test")), test_exps);
    for e in &test_exps {
        for f in ["markers.csv", "meta.json", "left/000001.png", "right/000001.png"] {
            let a = std::fs::read(tmp.path().join("all/test").join(e).join(f)).unwrap();
            let b = std::fs::read(tmp.path().join("test/test").join(e).join(f)).unwrap();
            assert!(a == b, "{}/{f} differs", e.to_string_lossy());
        }
    }
    assert_eq!("test".parse::<Split>().unwrap(), Split::Test);
    assert!(
        "tset"
            .parse::<Split>()
            .unwrap_err()
            .to_string()
            .contains("train, val or test")
    );
}

/// `--randomization rims`: flat-faced indenters only, on gels that spread more, whose rims squeeze
/// neighbouring dots below 0.6 pitch apart (the pile-ups real flat contacts make) without ever
/// folding the gel over itself (material points stay apart).
#[test]
fn rims_squeeze_the_lattice_without_folding_it() {
    use gelstereo_core::spatial::Buckets;
    use gelstereo_sim::indenter::Indenter;
    let mut cfg = DatasetConfig::new(24, 8, 71);
    cfg.randomization = Randomization::Rims;
    let exps = plan(&cfg).unwrap();
    for e in &exps {
        assert!(
            matches!(
                e.script.indenter,
                Indenter::FlatCylinder { .. } | Indenter::Hexagon { .. } | Indenter::Prism { .. }
            ),
            "{}: {:?}",
            e.name(),
            e.script.indenter
        );
        assert!(
            gelstereo_sim::dataset::RIM_POISSON.contains(&e.sensor.gel.poisson),
            "{}",
            e.sensor.gel.poisson
        );
        assert!(!e.families.is_empty());
    }
    let (mut closest, mut squeezed) = (f64::INFINITY, 0usize);
    for e in exps
        .iter()
        .filter(|e| e.sensor.cameras.image_width <= 640)
        .take(6)
    {
        let sim = Simulator::new(e.clone()).unwrap();
        let pitch = sim.sensor.pitch_px();
        let pressed = (e.script.press_end * f64::from(e.script.frames)).ceil() as u32;
        let f = sim.frame(pressed.min(7)).unwrap();
        let pts: Vec<_> = f.markers.iter().filter_map(|m| m.px[0]).collect();
        let buckets = Buckets::with_one_point_per_cell(&pts);
        for nn in (0..pts.len()).filter_map(|i| buckets.nearest_other_px(i)) {
            closest = closest.min(nn / pitch);
            squeezed += usize::from(nn < 0.6 * pitch);
        }
    }
    assert!(squeezed > 0, "no marker squeezed below 0.6 pitch");
    assert!(
        closest > 0.2,
        "markers {closest} pitch apart: the gel folded over itself"
    );
}

#[test]
fn a_chosen_indenter_and_motion_are_used_by_every_experiment_and_unknown_names_are_refused() {
    use gelstereo_sim::MotionKind;
    use gelstereo_sim::dataset::{DatasetConfig, plan};
    let mut config = DatasetConfig::new(12, 10, 5);
    let drawn = plan(&config).unwrap();
    config.indenter = Some("flat_cylinder".into());
    config.motion = Some("press-slide".parse().unwrap());
    let chosen = plan(&config).unwrap();
    assert!(chosen.iter().all(|e| e.script.indenter.name() == "flat_cylinder"));
    assert!(chosen.iter().all(|e| e.script.kind == MotionKind::PressSlide));
    // The other draws of the seed are those of the unconstrained plan.
    assert!(
        drawn
            .iter()
            .zip(&chosen)
            .all(|(a, b)| a.appearance == b.appearance && a.split == b.split)
    );
    config.indenter = Some("teapot".into());
    let err = plan(&config).unwrap_err().to_string();
    assert!(
        err.contains("indenter") && err.contains("teapot") && err.contains("flat_cylinder"),
        "{err}"
    );
    assert!(
        "slide-press"
            .parse::<MotionKind>()
            .unwrap_err()
            .to_string()
            .contains("press_slide")
    );
}
