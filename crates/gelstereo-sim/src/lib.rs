//! The synthetic GelStereo sensor: elastic gel deformation under indenters, stereo rendering through
//! calibrated cameras, and exact ground truth, written as recordings and datasets.
