//! A recording's calibration files, written with `gelstereo-geometry`'s writers: `calib.yaml`
//! (OpenCV FileStorage) and `left.cameramodel` / `right.cameramodel` (mrcal).

use std::path::Path;

use gelstereo_geometry::StereoRig;

use crate::error::Result;

/// Writes `calib.yaml`, `left.cameramodel` and `right.cameramodel` of `rig` into `dir`.
pub fn write_calibration(rig: &StereoRig, dir: &Path) -> Result<()> {
    rig.write_opencv_yaml(dir.join("calib.yaml"))?;
    rig.write_mrcal(dir.join("left.cameramodel"), dir.join("right.cameramodel"))?;
    Ok(())
}
