//! The facade on the sample recording: the pipeline alone, the sources, the outputs' folder.
#![allow(clippy::expect_used, clippy::unwrap_used)]

use std::path::PathBuf;

use gelstereo::source::FrameSource;
use gelstereo::{Frame, FrameOutput, Method, Pipeline, PipelineConfig, SlipState};

fn sample() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../data/sample/press-slide")
}

#[test]
fn pipeline_and_output_move_to_other_threads() {
    fn send<T: Send>() {}
    send::<Pipeline>();
    send::<FrameOutput>();
    send::<Frame>();
    send::<FrameSource>();
}

#[test]
fn sample_recording_tracks_with_3d_markers_slip_and_timestamps() {
    let mut config = PipelineConfig::for_recording(&sample()).unwrap();
    config.method = Some(Method::Blob);
    let mut pipeline = Pipeline::new(&config).unwrap();
    let mut outs = Vec::new();
    for f in FrameSource::open_path(&sample(), false).unwrap() {
        outs.push(pipeline.process(&f.into_frame().unwrap()).unwrap());
    }
    assert_eq!(outs.len(), 40);
    assert!(outs.iter().all(|o| o.note.is_none() && o.markers.len() == 529));
    // Frame number / 30 Hz (the recording declares no rate), from the first frame.
    assert!((outs[3].t_s - 0.1).abs() < 1e-9, "{}", outs[3].t_s);
    assert!(outs[0].markers.iter().filter(|m| m.position_mm.is_some()).count() > 500);
    assert_eq!(outs[0].slip(), SlipState::NoContact);
    assert!(outs.iter().any(|o| o.slip() == SlipState::GrossSlip));
    let pressed = outs
        .iter()
        .max_by(|a, b| {
            a.summary
                .max_depth_mm
                .unwrap_or(0.0)
                .total_cmp(&b.summary.max_depth_mm.unwrap_or(0.0))
        })
        .unwrap();
    assert!(!pressed.contact_region.is_empty() && pressed.summary.max_depth_mm.unwrap_or(0.0) > 0.1);
}

#[test]
fn unreadable_frames_come_back_flagged_and_the_first_good_frame_is_the_reference() {
    let mut config = PipelineConfig::for_recording(&sample()).unwrap();
    config.method = Some(Method::Blob);
    let mut pipeline = Pipeline::new(&config).unwrap();
    let early = pipeline.flag(None, "left/000000.png: cannot decode".into());
    assert!(early.markers.is_empty() && !pipeline.is_started());
    let mut source = FrameSource::open_path(&sample(), false).unwrap();
    let first = pipeline
        .process(&source.next().unwrap().into_frame().unwrap())
        .unwrap();
    assert_eq!(first.frame, 1);
    assert_eq!(first.earlier.len(), 1);
    assert_eq!(first.earlier[0].markers.len(), 529);
    assert!(first.earlier[0].note.as_deref().unwrap().contains("000000.png"));
    let mono = Pipeline::new(&config)
        .unwrap()
        .process(&Frame::mono(opencv::core::Mat::default()));
    assert!(mono.unwrap().note.is_some());
}
