"""Stereo visuotactile pipeline for GelStereo-type tactile sensors (Rust, through pyo3).

Conventions: pixels with (0, 0) at the centre of the top-left pixel, x right, y down; 3-D in mm in
the left camera's frame (x right, y down, z forward); marker identity = grid (row, col).
"""

from typing import Literal, Optional, Tuple, TypedDict

import numpy as np
import numpy.typing as npt

__version__: str

Image = npt.NDArray[np.uint8]
"""HxW grey or HxWx3 BGR (as OpenCV reads) uint8; HxWx4 BGRA is accepted too."""

class GelstereoError(RuntimeError):
    """An error of the gelstereo libraries, carrying the Rust message with its causes."""

def detect(
    image: Image, method: Literal["marknet-mre", "marknet", "blob", "yolo"] = "marknet-mre"
) -> npt.NDArray[np.float64]:
    """Marker centres in one image: an (N, 3) array of x, y (px) and confidence, sorted by y, then x.

    Uses the shipped models (data/models) and the tuned blob parameters, as `gelstereo detect`.
    Raises TypeError / ValueError for an unusable array or method name, GelstereoError when the
    models cannot be loaded or the image is too small. The GIL is released while detecting.
    """
