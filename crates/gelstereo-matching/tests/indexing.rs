//! Grid indexing and stereo pairing on synthetic scenes (tests/common): seeded, with the tolerance of
//! each check stated where it is made.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::*;
use gelstereo_core::{Detection, GridIndex, GridShape, Point2};
use gelstereo_matching::{
    Error, IndexedView, IndexingConfig, ReferenceLattice, StereoConfig, StereoLattice, pair_by_index,
};
use nalgebra::Isometry3;

const HARD: Imperfections = Imperfections {
    missing: 0.2,
    dust: 30,
    noise_px: 0.3,
};

/// The contact of the hard frames: 2 pitches of shear, 1 mm of indentation, about 3 pitches wide.
fn hard_contact(seed: u64) -> Deformation {
    let s = seed as f64;
    Deformation {
        cx_mm: (s * 0.37).sin() * 2.0,
        cy_mm: (s * 0.61).cos() * 2.0,
        sigma_mm: 1.8,
        depth_mm: 1.0,
        shear_mm: 2.0 * PITCH_MM,
    }
}

fn assert_one_to_one(view: &IndexedView) {
    let mut seen = std::collections::BTreeSet::new();
    for d in 0..view.detection_count() {
        if let Some(i) = view.index_of(d) {
            assert!(seen.insert(i), "index {i} given twice");
            assert_eq!(view.detection_at(i), Some(d));
        }
    }
    assert_eq!(seen.len(), view.indexed_count());
}

#[test]
fn reference_frame_is_indexed_exactly_despite_missing_markers_and_dust() {
    let rig = rig(0.0, 0.0);
    for seed in 0..8 {
        let (left, _) = stereo_frame(&rig, &Deformation::NONE, HARD, seed);
        let lattice =
            ReferenceLattice::from_detections(&left.detections, SHAPE, IndexingConfig::default()).unwrap();
        let s = score(lattice.reference_view(), &left.truth);
        assert_one_to_one(lattice.reference_view());
        // Every present marker indexed, and correctly (0 tolerance: the reference must be exact).
        assert_eq!((s.correct, s.wrong), (s.markers, 0), "seed {seed}: {s:?}");
        assert!(
            s.dust_indexed <= 2,
            "seed {seed}: dust placed on the lattice: {s:?}"
        );
        let truth = markers_mm(&Deformation::NONE);
        for (n, idx) in SHAPE.indices().enumerate() {
            let p = rig.left.project(&truth[n]).unwrap();
            let q = lattice.node_position(idx).unwrap();
            // Observed nodes: the detection (noise 0.3 px); missing ones: predicted from their
            // neighbours, within 2 px even at the distorted corners (gates are ~6 px).
            let tol = if lattice.observed(idx) { 1.5 } else { 2.0 };
            assert!(p.distance(q) < tol, "seed {seed} node {idx}: {p:?} vs {q:?}");
        }
        assert!(
            (lattice.pitch_px() - 14.4).abs() < 1.5,
            "pitch {}",
            lattice.pitch_px()
        );
    }
}

#[test]
fn rotated_lattice_keeps_row_along_y_and_col_along_x() {
    // The whole view rotated by 20 degrees about the image centre: (0, 0) is still the marker whose
    // lattice position is top-left after undoing... i.e. rows follow the lattice row closest to +x.
    let rig = rig(0.0, 0.0);
    let (left, _) = stereo_frame(&rig, &Deformation::NONE, CLEAN, 3);
    let a = 20f64.to_radians();
    let rotated: Vec<Detection> = left
        .detections
        .iter()
        .map(|d| {
            let (x, y) = (d.position.x - 320.0, d.position.y - 240.0);
            Detection {
                position: Point2::new(
                    320.0 + a.cos() * x - a.sin() * y,
                    240.0 + a.sin() * x + a.cos() * y,
                ),
                ..*d
            }
        })
        .collect();
    let lattice = ReferenceLattice::from_detections(&rotated, SHAPE, IndexingConfig::default()).unwrap();
    let s = score(lattice.reference_view(), &left.truth);
    assert_eq!((s.correct, s.wrong), (s.markers, 0), "{s:?}");
}

#[test]
fn deformed_frames_are_indexed_without_prior() {
    let rig = rig(0.0, 0.0);
    let (reference, _) = stereo_frame(&rig, &Deformation::NONE, HARD, 100);
    let lattice =
        ReferenceLattice::from_detections(&reference.detections, SHAPE, IndexingConfig::default()).unwrap();
    let (mut total, mut wrong, mut correct) = (0, 0, 0);
    for seed in 0..12 {
        let (left, _) = stereo_frame(&rig, &hard_contact(seed), HARD, 200 + seed);
        let view = lattice.index(&left.detections, None).unwrap();
        assert_one_to_one(&view);
        let s = score(&view, &left.truth);
        total += s.markers;
        wrong += s.wrong;
        correct += s.correct;
    }
    // Done-when figure: indices consistent with the truth for >= 99.5% of markers.
    assert!(
        correct as f64 >= 0.995 * total as f64,
        "correct {correct} of {total}, wrong {wrong}"
    );
    assert!(wrong as f64 <= 0.002 * total as f64, "wrong {wrong} of {total}");
}

#[test]
fn a_pressing_and_sliding_sequence_is_indexed_with_the_previous_frame_as_prior() {
    let rig = rig(0.0, 0.0);
    let (reference, _) = stereo_frame(&rig, &Deformation::NONE, HARD, 7);
    let lattice =
        ReferenceLattice::from_detections(&reference.detections, SHAPE, IndexingConfig::default()).unwrap();
    let mut def = hard_contact(5);
    def.sigma_mm = 2.5;
    let mut prior: Option<Vec<Option<Point2>>> = None;
    let (mut total, mut correct) = (0, 0);
    // Shear grows to 3 pitches (beyond the single-frame 2-pitch budget): the prior carries it.
    for k in 0..=15 {
        let d = Deformation {
            shear_mm: 3.0 * PITCH_MM * f64::from(k) / 15.0,
            depth_mm: 1.2 * f64::from(k.min(5)) / 5.0,
            ..def
        };
        let (left, _) = stereo_frame(&rig, &d, HARD, 1000 + k as u64);
        let view = lattice.index(&left.detections, prior.as_deref()).unwrap();
        let s = score(&view, &left.truth);
        assert_eq!(s.wrong, 0, "frame {k}: {s:?}");
        total += s.markers;
        correct += s.correct;
        prior = Some(view.node_positions());
    }
    assert!(
        correct as f64 >= 0.995 * total as f64,
        "correct {correct} of {total}"
    );
}

#[test]
fn bad_inputs_give_typed_errors() {
    let cfg = IndexingConfig::default;
    assert!(matches!(
        ReferenceLattice::from_detections(&[], SHAPE, cfg()),
        Err(Error::EmptyView)
    ));
    let nan = [Detection {
        position: Point2::new(f64::NAN, 1.0),
        confidence: 1.0,
    }];
    let err = ReferenceLattice::from_detections(&nan, SHAPE, cfg()).unwrap_err();
    assert!(
        matches!(err, Error::NonFiniteDetection { detection: 0, .. }),
        "{err}"
    );
    // A scatter without lattice structure.
    let few: Vec<Detection> = (0..3)
        .map(|i| Detection {
            position: Point2::new(f64::from(i) * 50.0, 7.0),
            confidence: 1.0,
        })
        .collect();
    assert!(matches!(
        ReferenceLattice::from_detections(&few, SHAPE, cfg()),
        Err(Error::NoLattice { detections: 3 })
    ));

    // A cropped reference view: only the columns left of x = 380 px are seen.
    let rig = rig(0.0, 0.0);
    let (left, _) = stereo_frame(&rig, &Deformation::NONE, CLEAN, 1);
    let cropped: Vec<Detection> = left
        .detections
        .iter()
        .copied()
        .filter(|d| d.position.x < 380.0)
        .collect();
    let err = ReferenceLattice::from_detections(&cropped, SHAPE, cfg()).unwrap_err();
    assert!(
        matches!(err, Error::IncompleteGrid { found_rows: 23, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("expected 23 x 23"), "{err}");

    // Too few markers for the configured fraction.
    let sparse = ReferenceLattice::from_detections(
        &left.detections,
        GridShape { rows: 23, cols: 23 },
        IndexingConfig {
            min_reference_fraction: 1.0,
            ..cfg()
        },
    );
    assert!(sparse.is_ok(), "a clean view has every marker");
    let (holey, _) = stereo_frame(
        &rig,
        &Deformation::NONE,
        Imperfections {
            missing: 0.3,
            dust: 0,
            noise_px: 0.0,
        },
        2,
    );
    let err = ReferenceLattice::from_detections(
        &holey.detections,
        SHAPE,
        IndexingConfig {
            min_reference_fraction: 0.9,
            ..cfg()
        },
    )
    .unwrap_err();
    assert!(matches!(err, Error::TooFewMarkers { expected: 529, .. }), "{err}");

    let bad_cfg = IndexingConfig {
        gate_frac: 0.9,
        ..cfg()
    };
    let err = ReferenceLattice::from_detections(&left.detections, SHAPE, bad_cfg).unwrap_err();
    assert!(err.to_string().contains("gate_frac"), "{err}");

    let lattice = ReferenceLattice::from_detections(&left.detections, SHAPE, cfg()).unwrap();
    let err = lattice.index(&left.detections, Some(&[None; 3])).unwrap_err();
    assert!(
        matches!(
            err,
            Error::PriorLength {
                expected: 529,
                found: 3
            }
        ),
        "{err}"
    );
    // An empty later frame is not an error: nothing is indexed.
    let empty = lattice.index(&[], None).unwrap();
    assert_eq!(empty.indexed_count(), 0);
}

#[test]
fn stereo_reference_and_contact_frames_pair_every_marker_correctly() {
    for (yaw, roll) in [(0.0, 0.0), (-4.0, 1.5)] {
        let rig = rig(yaw, roll);
        let (l0, r0) = stereo_frame(&rig, &Deformation::NONE, HARD, 11);
        let stereo = StereoLattice::from_reference(
            &rig,
            &l0.detections,
            &r0.detections,
            SHAPE,
            StereoConfig::default(),
        )
        .unwrap_or_else(|e| panic!("yaw {yaw}: {e}"));
        let s = score(stereo.right().reference_view(), &r0.truth);
        assert_eq!(
            (s.correct, s.wrong),
            (s.markers, 0),
            "yaw {yaw}: right reference {s:?}"
        );
        let reference = stereo.reference_match().unwrap();
        assert!(reference.rejected.is_empty());

        let (mut both_visible, mut paired, mut wrong_pairs) = (0, 0, 0);
        for seed in 0..8 {
            let (l, r) = stereo_frame(&rig, &hard_contact(seed), HARD, 300 + seed);
            let m = stereo.match_frame(&l.detections, &r.detections, None).unwrap();
            assert_one_to_one(&m.right);
            let sr = score(&m.right, &r.truth);
            assert!(
                sr.correct as f64 >= 0.99 * sr.markers as f64,
                "yaw {yaw} seed {seed}: right {sr:?}"
            );
            let left_truth: std::collections::BTreeSet<GridIndex> =
                l.truth.iter().flatten().copied().collect();
            both_visible += r
                .truth
                .iter()
                .flatten()
                .filter(|i| left_truth.contains(i))
                .count();
            for p in &m.pairs {
                paired += 1;
                let ld = m.left.detection_at(p.index).unwrap();
                let rd = m.right.detection_at(p.index).unwrap();
                if l.truth[ld] != Some(p.index) || r.truth[rd] != Some(p.index) {
                    wrong_pairs += 1;
                }
                assert!(p.epipolar_px <= stereo.config().max_epipolar_px);
            }
        }
        // Done-when figures: >= 99% of markers visible in both views paired, <= 0.1% wrong pairs.
        assert!(
            paired as f64 >= 0.99 * both_visible as f64,
            "yaw {yaw}: {paired} of {both_visible}"
        );
        assert!(
            wrong_pairs as f64 <= 0.001 * paired as f64,
            "yaw {yaw}: {wrong_pairs} wrong of {paired}"
        );
    }
}

#[test]
fn pairs_off_their_epipolar_line_are_rejected_and_flagged() {
    let rig = rig(-4.0, 1.5);
    let (l0, r0) = stereo_frame(&rig, &Deformation::NONE, CLEAN, 21);
    let stereo = StereoLattice::from_reference(
        &rig,
        &l0.detections,
        &r0.detections,
        SHAPE,
        StereoConfig::default(),
    )
    .unwrap();
    // Re-index the right view with one marker moved 5 px across its epipolar line (along y here)
    // and no gate, so that the pairing check is what catches it.
    let moved = GridIndex::new(4, 9);
    let d = stereo.right().reference_view().detection_at(moved).unwrap();
    let mut right = r0.detections.clone();
    right[d].position.y += 5.0;
    let view = stereo.right().index(&right, None).unwrap();
    let (pairs, rejected) = pair_by_index(
        stereo.left().reference_view(),
        &view,
        stereo.epipolar(),
        stereo.config().max_epipolar_px,
    )
    .unwrap();
    assert_eq!(rejected.len(), 1, "{rejected:?}");
    assert_eq!(rejected[0].index, moved);
    assert!(rejected[0].epipolar_px.unwrap() > stereo.config().max_epipolar_px);
    assert_eq!(pairs.len(), 528);
    // The gated matcher does not pair it at all.
    let m = stereo.match_frame(&l0.detections, &right, None).unwrap();
    assert_eq!(m.right.detection_at(moved), None);
    assert!(m.rejected.is_empty());
}

#[test]
fn stereo_errors_name_the_problem() {
    let rig = rig(0.0, 0.0);
    let (l0, r0) = stereo_frame(&rig, &Deformation::NONE, CLEAN, 5);
    let err =
        StereoLattice::from_reference(&rig, &l0.detections, &[], SHAPE, StereoConfig::default()).unwrap_err();
    assert!(
        err.to_string()
            .contains("right reference frame has no detections"),
        "{err}"
    );
    // A rig whose baseline is zero is degenerate.
    let mut flat = rig.clone();
    flat.right_from_left = Isometry3::identity();
    let err = StereoLattice::from_reference(
        &flat,
        &l0.detections,
        &r0.detections,
        SHAPE,
        StereoConfig::default(),
    )
    .unwrap_err();
    assert!(matches!(err, Error::Geometry(_)), "{err}");
    // A calibration that does not belong to the views: the right camera tilted by 5 degrees
    // (52 px = 3.6 rows of vertical disparity, so no whole row offset fits either).
    let mut wrong = rig.clone();
    wrong.right_from_left.rotation = nalgebra::UnitQuaternion::from_euler_angles(5f64.to_radians(), 0.0, 0.0)
        * wrong.right_from_left.rotation;
    let err = StereoLattice::from_reference(
        &wrong,
        &l0.detections,
        &r0.detections,
        SHAPE,
        StereoConfig::default(),
    )
    .unwrap_err();
    assert!(matches!(err, Error::StereoAlignment { .. }), "{err}");
}

/// This thread's CPU time, ns (Linux `/proc/thread-self/schedstat`): on a shared, oversubscribed
/// machine wall time mostly measures the other processes.
fn thread_cpu_ns() -> Option<u64> {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// Best-of-5 time of `f` per frame, ms: thread CPU time where the OS reports it, else wall time.
/// Each sample runs `f` 10 times: schedstat is only updated at scheduler events (a few ms apart).
fn time_per_frame(frames: usize, mut f: impl FnMut()) -> f64 {
    const REPS: usize = 10;
    (0..5)
        .map(|_| {
            let (t, c) = (std::time::Instant::now(), thread_cpu_ns());
            for _ in 0..REPS {
                f();
            }
            let ms = match (c, thread_cpu_ns()) {
                (Some(a), Some(b)) => (b - a) as f64 * 1e-6,
                _ => t.elapsed().as_secs_f64() * 1e3,
            };
            ms / (frames * REPS) as f64
        })
        .fold(f64::INFINITY, f64::min)
}

/// Speed and accuracy over 40 hard contact frames; run in release:
/// `cargo test --release -p gelstereo-matching --test indexing -- --ignored --nocapture`.
#[test]
#[ignore = "measurement: run in release with --nocapture"]
fn measure_speed_and_accuracy() {
    let rig = rig(-4.0, 1.5);
    let (l0, r0) = stereo_frame(&rig, &Deformation::NONE, HARD, 100);
    let t = std::time::Instant::now();
    let stereo = StereoLattice::from_reference(
        &rig,
        &l0.detections,
        &r0.detections,
        SHAPE,
        StereoConfig::default(),
    )
    .unwrap();
    println!(
        "reference (both views, from scratch + alignment): {:.2} ms",
        t.elapsed().as_secs_f64() * 1e3
    );
    let frames: Vec<_> = (0..40)
        .map(|seed| stereo_frame(&rig, &hard_contact(seed), HARD, 200 + seed))
        .collect();
    let (mut total, mut correct, mut wrong) = (0, 0, 0);
    for (l, _) in &frames {
        let v = stereo.left().index(&l.detections, None).unwrap();
        let s = score(&v, &l.truth);
        (total, correct, wrong) = (total + s.markers, correct + s.correct, wrong + s.wrong);
    }
    let per = time_per_frame(frames.len(), || {
        for (l, _) in &frames {
            stereo.left().index(&l.detections, None).unwrap();
        }
    });
    println!("left view, no prior: {per:.3} ms/frame; {correct} of {total} correct, {wrong} wrong");
    let per = time_per_frame(frames.len(), || {
        for (_, r) in &frames {
            for d in &r.detections {
                std::hint::black_box(stereo.epipolar().undistort_right(d.position));
            }
        }
    });
    println!("undistorting the right view's points: {per:.3} ms/frame");
    let per = time_per_frame(frames.len(), || {
        for (l, r) in &frames {
            stereo.match_frame(&l.detections, &r.detections, None).unwrap();
        }
    });
    println!("stereo match_frame (index both views + epipolar pairing), no prior: {per:.3} ms/frame");
    let prior = stereo.reference_match().unwrap().to_prior();
    let per = time_per_frame(frames.len(), || {
        for (l, r) in &frames {
            stereo
                .match_frame(&l.detections, &r.detections, Some(&prior))
                .unwrap();
        }
    });
    println!("stereo match_frame with a prior: {per:.3} ms/frame");
}

#[test]
fn reconstruction_recovers_the_exact_3d_lattice_from_exact_projections() {
    use gelstereo_geometry::TriangulationConfig;
    use gelstereo_matching::StereoReconstructor;
    let rig = rig(-4.0, 1.5);
    let (l0, r0) = stereo_frame(&rig, &Deformation::NONE, CLEAN, 1);
    let rec = StereoReconstructor::new(
        &rig,
        &l0.detections,
        &r0.detections,
        SHAPE,
        StereoConfig::default(),
        TriangulationConfig::default(),
    )
    .unwrap();
    let def = hard_contact(2);
    let truth = markers_mm(&def);
    let (l, r) = stereo_frame(&rig, &def, CLEAN, 2);
    let frame = rec.reconstruct(&l.detections, &r.detections, None).unwrap();
    assert_eq!(frame.markers.len(), 529);
    assert_eq!(
        frame.reconstructed_count(),
        529,
        "every marker is seen in both views"
    );
    for (m, t) in frame.markers.iter().zip(&truth) {
        let p = m.position_mm.unwrap();
        // Exact projections: triangulation is exact up to the undistortion tolerance (1e-11 px).
        let err = ((p[0] - t.x).powi(2) + (p[1] - t.y).powi(2) + (p[2] - t.z).powi(2)).sqrt();
        assert!(err < 1e-6, "{}: {err} mm", m.index);
        assert!(m.reprojection_error_px.unwrap() < 1e-6);
        let row = m.record(9);
        assert_eq!(
            (row.frame, row.index, row.displacement_mm, row.status),
            (9, m.index, None, None)
        );
    }
}

#[test]
fn evaluation_counts_coverage_wrong_pairs_and_wrong_ids() {
    use gelstereo_core::StereoPair;
    use gelstereo_geometry::TriangulationConfig;
    use gelstereo_matching::StereoReconstructor;
    use gelstereo_matching::eval::{Evaluation, GroundTruth, TruthMarker};
    let rig = rig(-4.0, 1.5);
    let (l0, r0) = stereo_frame(&rig, &Deformation::NONE, CLEAN, 1);
    let rec = StereoReconstructor::new(
        &rig,
        &l0.detections,
        &r0.detections,
        SHAPE,
        StereoConfig::default(),
        TriangulationConfig::default(),
    )
    .unwrap();
    let def = hard_contact(4);
    let (l, r) = stereo_frame(&rig, &def, CLEAN, 4);
    let pts = markers_mm(&def);
    let mut truth = GroundTruth::default();
    let frame = truth.frames.entry(7).or_default();
    for (n, idx) in SHAPE.indices().enumerate() {
        let (lp, rp) = rig.project(&pts[n]).unwrap();
        frame.insert(
            idx,
            TruthMarker {
                left_px: Some(lp),
                right_px: Some(rp),
                position_mm: Some([pts[n].x, pts[n].y, pts[n].z]),
                in_contact: n == 0,
            },
        );
    }
    truth.contact.insert(7, true);
    let r_px = StereoPair::new(3.5, 3.5);
    let mut good = rec.reconstruct(&l.detections, &r.detections, None).unwrap();
    let mut e = Evaluation::default();
    e.add_frame(&truth, 7, &good, &r_px);
    assert_eq!(
        (e.all.reconstructed, e.all.wrong_pairs, e.all.index_wrong),
        (529, 0, 0)
    );
    assert_eq!(
        (e.all.coverage(), e.all.index_consistency()),
        (Some(1.0), Some(1.0))
    );
    assert!(e.all.rmse_mm().unwrap() < 1e-6);
    assert_eq!(
        (e.contact_frames.reconstructed, e.in_contact_markers.reconstructed),
        (529, 1)
    );

    // Swap two markers' right points: two wrong pairs with large 3-D errors; drop one position:
    // coverage falls by one marker.
    let (a, b) = (good.markers[30].right_px, good.markers[31].right_px);
    good.markers[30].right_px = b;
    good.markers[31].right_px = a;
    good.markers[30].position_mm = Some([0.0, 0.0, 30.0]);
    good.markers[40].position_mm = None;
    let mut e = Evaluation::default();
    e.add_frame(&truth, 7, &good, &r_px);
    assert_eq!((e.all.reconstructed, e.all.wrong_pairs), (528, 2));
    assert_eq!(e.all.reconstructed_of_visible_both, 528);
    assert!(e.all.max_error_mm > 1.0);
    let mut twice = e;
    twice.merge(&e);
    assert_eq!((twice.frames, twice.all.wrong_pairs), (2, 4));
}

#[test]
fn empty_and_one_sided_frames_give_empty_results_not_errors() {
    let rig = rig(-4.0, 1.5);
    let (l0, r0) = stereo_frame(&rig, &Deformation::NONE, HARD, 8);
    let stereo = StereoLattice::from_reference(
        &rig,
        &l0.detections,
        &r0.detections,
        SHAPE,
        StereoConfig::default(),
    )
    .unwrap();
    let prior = stereo.reference_match().unwrap().to_prior();
    for p in [None, Some(&prior)] {
        let m = stereo.match_frame(&[], &[], p).unwrap();
        assert_eq!(
            (m.left.indexed_count(), m.right.indexed_count(), m.pairs.len()),
            (0, 0, 0)
        );
        // Only the left view: its markers are indexed, nothing is paired.
        let m = stereo.match_frame(&l0.detections, &[], p).unwrap();
        assert!(m.left.indexed_count() > 400 && m.pairs.is_empty() && m.rejected.is_empty());
        // An empty frame's prior (all None) falls back to the reference.
        let next = stereo
            .match_frame(&l0.detections, &r0.detections, Some(&m.to_prior()))
            .unwrap();
        assert!(next.pairs.len() > 300, "{}", next.pairs.len());
    }
}
