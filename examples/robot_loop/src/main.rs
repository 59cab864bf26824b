//! A robot loop on the gelstereo facade: frames from a recording or cameras, one callback per frame
//! with the 3-D markers and the slip state.
//!
//! `cargo run -p robot-loop -- [RECORDING | N | L,R] [CALIBRATION]` (default: the sample recording).

use gelstereo::{Pipeline, PipelineConfig, source::FrameSource};

fn main() -> gelstereo::Result<()> {
    let mut args = std::env::args().skip(1);
    let input = args.next().unwrap_or_else(|| "data/sample/press-slide".into());
    let mut config = PipelineConfig::for_recording(input.as_ref())?;
    config.calibration = args.next().map(Into::into).or(config.calibration);
    let mut pipeline = Pipeline::new(&config)?;
    pipeline.for_each(FrameSource::open(&input)?.prefetch(4), |out| {
        let in_3d = out.markers.iter().filter(|m| m.position_mm.is_some()).count();
        let depth = out.summary.max_depth_mm.unwrap_or(0.0);
        let (t, slip) = (out.t_s, out.slip());
        println!("{t:.3} s: {in_3d} markers in 3-D, depth {depth:.3} mm, {slip}");
    })?;
    Ok(())
}
