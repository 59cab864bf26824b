//! Marker tracking over time, displacement fields, contact geometry and slip detection.
