//! The sensor, described once: the marker lattice (shape, pitch, arrangement), the gel's facts
//! (thickness, Young's modulus, Poisson ratio), the two cameras and the membrane's outline
//! ([`SensorSpec`], the JSON file `calib/reference-sensor.json` shows); its built pose
//! ([`Sensor`]: the calibrated rig and each camera's frame from the sensor frame); and what a
//! recording's `meta.json` states ([`RecordingMeta`]). The pipeline, the simulator and the CLI read
//! sensor facts from here.
//!
//! # Frames
//! The *sensor frame* has its origin at the centre of the gel's marker surface, x along the grid's
//! columns, y along its rows (so row grows with y, col with x, as in the left view), and z pointing
//! from the cameras out through the gel towards the object. `docs/sim.md` documents every field.

pub mod error;
pub mod recording;
pub mod spec;

pub use error::{Error, Result};
pub use recording::{MAX_FRAME_RATE_HZ, RecordingMeta};
pub use spec::{
    CameraSpec, CamerasSpec, GelSpec, GridSpec, Lattice, Membrane, REFERENCE_MODULUS_KPA, REFERENCE_POISSON,
    Sensor, SensorSpec, splitmix64,
};
