//! A marker grid that overfills the cameras' view (tests/common's 23 x 23 scene with each view
//! cropped): refused by the whole-lattice indexing, indexed and paired on the sensor's own grid
//! indices when the expected lattice positions place it, indexed from the visible top-left marker
//! without them, and a clear error when too little of it is visible.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::*;
use gelstereo_core::{GridIndex, GridShape, Point2};
use gelstereo_geometry::StereoRig;
use gelstereo_matching::{Error, IndexingConfig, ReferenceLattice, StereoConfig, StereoLattice};

const SOME_MISSING: Imperfections = Imperfections {
    missing: 0.05,
    dust: 0,
    noise_px: 0.3,
};

/// Keeps the detections inside `[x0, x1] x [y0, y1]` (px), as a smaller image would.
fn crop(v: &ViewDetections, x0: f64, x1: f64, y0: f64, y1: f64) -> ViewDetections {
    let keep: Vec<usize> = (0..v.detections.len())
        .filter(|&i| {
            let p = v.detections[i].position;
            p.x >= x0 && p.x <= x1 && p.y >= y0 && p.y <= y1
        })
        .collect();
    ViewDetections {
        detections: keep.iter().map(|&i| v.detections[i]).collect(),
        truth: keep.iter().map(|&i| v.truth[i]).collect(),
    }
}

/// The whole lattice at rest projected into both views (what a sensor description gives).
fn expected(rig: &StereoRig, shift_px: f64) -> (Vec<Option<Point2>>, Vec<Option<Point2>>) {
    markers_mm(&Deformation::NONE)
        .iter()
        .map(|p| {
            let (l, r) = rig.project(p).unwrap();
            let s = |q: Point2| Some(Point2::new(q.x + shift_px, q.y - 0.5 * shift_px));
            (s(l), s(r))
        })
        .unzip()
}

/// Left view cut on the right and at the top, right view cut on the left and at the bottom: 23 x 23
/// lattice (left x 233..550, y 80..400 px) of which each view shows a different part.
fn cropped_scene(rig: &StereoRig, seed: u64) -> (ViewDetections, ViewDetections) {
    let (l, r) = stereo_frame(rig, &Deformation::NONE, SOME_MISSING, seed);
    (
        crop(&l, 0.0, 480.0, 130.0, 479.0),
        crop(&r, 250.0, 639.0, 0.0, 360.0),
    )
}

fn rows_cols(v: &ViewDetections) -> (u16, u16, u16, u16) {
    let t: Vec<GridIndex> = v.truth.iter().flatten().copied().collect();
    (
        t.iter().map(|i| i.row).min().unwrap(),
        t.iter().map(|i| i.row).max().unwrap(),
        t.iter().map(|i| i.col).min().unwrap(),
        t.iter().map(|i| i.col).max().unwrap(),
    )
}

#[test]
fn an_overfilled_grid_is_refused_whole_and_placed_on_the_sensors_indices() {
    for (yaw, roll) in [(0.0, 0.0), (-4.0, 1.5)] {
        let rig = rig(yaw, roll);
        let (l, r) = cropped_scene(&rig, 5);
        assert!(
            rows_cols(&l).0 > 0 && rows_cols(&l).3 < 22,
            "the crop cuts the left view"
        );
        // What failed before: the whole lattice is not visible.
        let e =
            StereoLattice::from_reference(&rig, &l.detections, &r.detections, SHAPE, StereoConfig::default())
                .unwrap_err();
        assert!(matches!(e, Error::IncompleteGrid { .. }), "{e}");

        // Placed by the expected positions (with a 0.2 pitch error in them): every marker gets its
        // own grid index in both views, and every pair is a true pair.
        let (el, er) = expected(&rig, 3.0);
        let (stereo, placement) = StereoLattice::from_reference_placed(
            &rig,
            &l.detections,
            &r.detections,
            SHAPE,
            (&el, &er),
            StereoConfig::default(),
        )
        .unwrap_or_else(|e| panic!("yaw {yaw}: {e}"));
        let sl = score(stereo.left().reference_view(), &l.truth);
        let sr = score(stereo.right().reference_view(), &r.truth);
        assert_eq!((sl.correct, sl.wrong), (sl.markers, 0), "yaw {yaw}: left {sl:?}");
        assert_eq!((sr.correct, sr.wrong), (sr.markers, 0), "yaw {yaw}: right {sr:?}");
        let (r0, r1, c0, c1) = rows_cols(&l);
        assert_eq!((placement.left.first_row, placement.left.last_row), (r0, r1));
        assert_eq!((placement.left.first_col, placement.left.last_col), (c0, c1));
        assert_eq!(placement.within_epipolar, placement.paired);
        let m = stereo.reference_match().unwrap();
        assert!(m.rejected.is_empty());
        let left_ids: std::collections::BTreeSet<GridIndex> = l.truth.iter().flatten().copied().collect();
        let both = r.truth.iter().flatten().filter(|i| left_ids.contains(i)).count();
        assert_eq!(
            m.pairs.len(),
            both,
            "yaw {yaw}: every marker seen in both views is paired"
        );

        // A later frame in contact is indexed and paired on the same ids.
        let (lc, rc) = stereo_frame(
            &rig,
            &Deformation {
                cx_mm: 1.0,
                cy_mm: 0.5,
                sigma_mm: 1.8,
                depth_mm: 0.8,
                shear_mm: PITCH_MM,
            },
            SOME_MISSING,
            77,
        );
        let (lc, rc) = (
            crop(&lc, 0.0, 480.0, 130.0, 479.0),
            crop(&rc, 250.0, 639.0, 0.0, 360.0),
        );
        let f = stereo.match_frame(&lc.detections, &rc.detections, None).unwrap();
        let (sl, sr) = (score(&f.left, &lc.truth), score(&f.right, &rc.truth));
        assert_eq!(sl.wrong + sr.wrong, 0, "yaw {yaw}: contact frame {sl:?} {sr:?}");
        assert!(sl.correct as f64 >= 0.98 * sl.markers as f64, "yaw {yaw}: {sl:?}");
    }
}

#[test]
fn without_expected_positions_the_visible_top_left_marker_is_the_origin() {
    // Rows cut off, every column visible in both views (like a tall grid in a wide image): the
    // epipolar constraint fixes the right view's row offset, the columns' extent the column offset.
    let rig = rig(-4.0, 1.5);
    let (l, r) = stereo_frame(&rig, &Deformation::NONE, SOME_MISSING, 9);
    let (l, r) = (
        crop(&l, 0.0, 639.0, 130.0, 479.0),
        crop(&r, 0.0, 639.0, 0.0, 360.0),
    );
    let visible = ReferenceLattice::visible_shape(&l.detections, SHAPE, &IndexingConfig::default()).unwrap();
    let (r0, r1, c0, c1) = rows_cols(&l);
    assert_eq!(
        visible,
        GridShape {
            rows: r1 - r0 + 1,
            cols: c1 - c0 + 1
        }
    );
    let stereo = visible_reference(&rig, (&l, &r), visible, None).unwrap();
    // Ids = true index minus the visible top-left's, in both views.
    assert_ids_from_the_visible_top_left(&stereo, (&l, &r), (r0, c0), (r1, c1));

    // Columns cut off too: grid rows lie (nearly) along the epipolar lines, so the column offset
    // is open (a few tenths of a pixel apart); a named error, not a guess.
    let (l, r) = cropped_scene(&rig, 9);
    let visible = ReferenceLattice::visible_shape(&l.detections, SHAPE, &IndexingConfig::default()).unwrap();
    let e = visible_reference(&rig, (&l, &r), visible, None).unwrap_err();
    assert!(matches!(e, Error::StereoAlignment { .. }), "{e}");
    // With the marker pitch known, the triangulated spacing settles it: true ids minus the
    // visible top-left's in both views.
    let stereo = visible_reference(&rig, (&l, &r), visible, Some(PITCH_MM)).unwrap();
    let (r0, _, c0, _) = rows_cols(&l);
    let last = (r0 + visible.rows - 1, c0 + visible.cols - 1);
    assert_ids_from_the_visible_top_left(&stereo, (&l, &r), (r0, c0), last);
}

/// `StereoLattice::from_visible_reference` of the whole `SHAPE` on the reference views `views`.
fn visible_reference(
    rig: &StereoRig,
    views: (&ViewDetections, &ViewDetections),
    visible: GridShape,
    pitch_mm: Option<f64>,
) -> Result<StereoLattice, Error> {
    StereoLattice::from_visible_reference(
        rig,
        &views.0.detections,
        &views.1.detections,
        visible,
        SHAPE,
        pitch_mm,
        StereoConfig::default(),
    )
}

/// Every left marker indexed by its true index minus the visible top-left `first` (block
/// `first..=last`), no right marker wrong and at least 90 % of them right.
fn assert_ids_from_the_visible_top_left(
    stereo: &StereoLattice,
    views: (&ViewDetections, &ViewDetections),
    first: (u16, u16),
    last: (u16, u16),
) {
    let sl = score(
        stereo.left().reference_view(),
        &relative_to(&views.0.truth, first, last),
    );
    let sr = score(
        stereo.right().reference_view(),
        &relative_to(&views.1.truth, first, last),
    );
    assert_eq!((sl.correct, sl.wrong), (sl.markers, 0), "left {sl:?}");
    assert_eq!(sr.wrong, 0, "right {sr:?}");
    assert!(sr.correct as f64 >= 0.9 * sr.markers as f64, "right {sr:?}");
}

#[test]
fn too_small_a_visible_part_or_a_foreign_description_is_a_named_error() {
    let rig = rig(0.0, 0.0);
    let (l, _) = stereo_frame(&rig, &Deformation::NONE, CLEAN, 3);
    // Two rows of markers.
    let two = crop(&l, 0.0, 639.0, 0.0, 100.0);
    assert_eq!(rows_cols(&two).1, 1, "the crop leaves rows 0 and 1");
    let e = ReferenceLattice::visible_shape(&two.detections, SHAPE, &IndexingConfig::default()).unwrap_err();
    assert!(
        matches!(
            e,
            Error::TooSmallVisible { found_rows: 2, .. } | Error::NoLattice { .. }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("rows"), "{e}");
    // Expected positions of another sensor (a lattice 40 % larger): no offset fits.
    let (el, _) = expected(&rig, 0.0);
    let centre = Point2::new(391.5, 239.5);
    let foreign: Vec<Option<Point2>> = el
        .iter()
        .map(|p| {
            p.map(|p| {
                Point2::new(
                    centre.x + 1.4 * (p.x - centre.x),
                    centre.y + 1.4 * (p.y - centre.y),
                )
            })
        })
        .collect();
    let e =
        ReferenceLattice::from_detections_placed(&l.detections, SHAPE, &foreign, IndexingConfig::default())
            .unwrap_err();
    assert!(matches!(e, Error::Placement { .. }), "{e}");
    // A wrong number of expected positions.
    let e =
        ReferenceLattice::from_detections_placed(&l.detections, SHAPE, &el[1..], IndexingConfig::default())
            .unwrap_err();
    assert!(matches!(e, Error::PriorLength { .. }), "{e}");
}

/// True indices relative to the visible top-left `first` (ids of a grid indexed from what it shows),
/// `None` outside the visible block `first..=last`.
fn relative_to(truth: &[Option<GridIndex>], first: (u16, u16), last: (u16, u16)) -> Vec<Option<GridIndex>> {
    truth
        .iter()
        .map(|i| {
            i.and_then(|i| {
                (i.row >= first.0 && i.col >= first.1 && i.row <= last.0 && i.col <= last.1)
                    .then(|| GridIndex::new(i.row - first.0, i.col - first.1))
            })
        })
        .collect()
}
