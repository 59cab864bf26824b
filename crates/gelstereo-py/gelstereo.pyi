"""Stereo visuotactile pipeline for GelStereo-type tactile sensors (Rust, through pyo3).

Conventions: pixels with (0, 0) at the centre of the top-left pixel, x right, y down; 3-D in mm in
the left camera's frame (x right, y down, z forward); marker identity = grid (row, col).
"""

import os
from typing import List, Literal, Optional, Tuple, TypedDict, Union

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

    Uses the shipped models (the package's models/) and the tuned blob parameters, as `gelstereo detect`; the
    marker pitch is remembered per image size, and every image runs on the whole network input (the
    images of a loop may come from either camera; `Pipeline` runs a stream's frames on a window
    around its lattice). Raises TypeError / ValueError for an unusable array or method name, GelstereoError when the
    models cannot be loaded or the image is too small. The GIL is released while detecting.
    """

SlipState = Literal["no_contact", "stick", "partial_slip", "gross_slip"]

class Markers(TypedDict):
    """One entry per tracked marker, in id order; NaN where a view or the 3-D stages lack a value."""

    row: npt.NDArray[np.int64]
    col: npt.NDArray[np.int64]
    status: npt.NDArray[np.str_]
    """"tracked", "predicted" or "lost"."""
    x_left: npt.NDArray[np.float64]
    y_left: npt.NDArray[np.float64]
    x_right: npt.NDArray[np.float64]
    y_right: npt.NDArray[np.float64]
    X_mm: npt.NDArray[np.float64]
    Y_mm: npt.NDArray[np.float64]
    Z_mm: npt.NDArray[np.float64]
    dX_mm: npt.NDArray[np.float64]
    dY_mm: npt.NDArray[np.float64]
    dZ_mm: npt.NDArray[np.float64]
    pressure_kPa: npt.NDArray[np.float64]
    """Contact pressure on the marker's cell, kPa (NaN where the contact mechanics did not run)."""
    in_contact: npt.NDArray[np.bool_]
    slipping: npt.NDArray[np.bool_]
    """The marker's traction lies on the friction cone."""
    X_gel_mm: npt.NDArray[np.float64]
    """Position in the gel frame (origin at the centre of the reference surface, z the gel's normal
    away from the cameras), mm; the same for Y_gel_mm, Z_gel_mm."""
    Y_gel_mm: npt.NDArray[np.float64]
    Z_gel_mm: npt.NDArray[np.float64]
    dX_gel_mm: npt.NDArray[np.float64]
    """Displacement in the gel frame, mm (dZ_gel_mm < 0 where the gel is pressed in)."""
    dY_gel_mm: npt.NDArray[np.float64]
    dZ_gel_mm: npt.NDArray[np.float64]

class Contact:
    """The contact of one frame."""

    in_contact: bool
    area_mm2: float
    """Contact area, mm^2 (0 without contact)."""
    max_depth_mm: float
    """Largest indentation depth, mm (0 without contact)."""
    centroid_mm: Optional[Tuple[float, float]]
    """Contact centroid (X, Y) in the left camera frame, mm; None without contact."""
    region: npt.NDArray[np.int64]
    """(K, 2) array of the (row, col) ids of the markers in contact."""
    force_n: float
    """Total normal force on the gel, N (0 without contact; NaN for a mono sensor)."""
    shear_n: Tuple[float, float]
    """Tangential force along the gel frame's x and y, N."""
    torque_nmm: float
    """Torque of the shear about the normal through the pressure centroid, N mm."""

class Frame:
    """One processed frame."""

    frame: int
    """Frame number, from 0 (flagged frames count)."""
    timestamp: float
    """Seconds from the first frame."""
    markers: Markers
    contact: Contact
    slip: Optional[SlipState]
    """None when the frame's contact is unknown (see note)."""
    note: Optional[str]
    """Why the frame is flagged (unreadable, not localized, reference not yet indexed); None if not."""
    log: List[str]
    """Informational lines (how the reference lattice was indexed, re-zeroing)."""
    earlier: List["Frame"]
    """Frames flagged before the reference was indexed, returned again with a lost row per marker."""
    camera_from_gel: Optional[npt.NDArray[np.float64]]
    """(4, 4) transform taking gel-frame points (mm) to the left camera frame (the gel's axes as
    columns, its origin as the translation); None for a mono sensor or before the reference."""

def parse_frame(line: str) -> Frame:
    """One line of a `gelstereo track --jsonl` stream as the Frame `Pipeline.process` returned for it,
    to the stream's precision (camera-frame values through the line's gel frame); `log` and `earlier`
    are not in the stream and come back empty. Raises ValueError naming the field of a bad line."""

class StreamReader:
    """The frames of a stream file, read one at a time."""

    def __iter__(self) -> "StreamReader": ...
    def __next__(self) -> Frame: ...

def read_stream(path: Union[str, os.PathLike[str]]) -> StreamReader:
    """Reads a `gelstereo track --jsonl` file frame by frame (`for frame in read_stream(path)`), each
    as `parse_frame` gives it; blank lines are skipped. Raises GelstereoError when the file cannot be
    opened, ValueError (while iterating) naming the file and line of a bad line."""

class Pipeline:
    """The tracking pipeline: built once (models loaded, calibration read), then fed frame by frame.

    `calibration`: stereo calibration (OpenCV YAML/XML, mrcal folder or "left,right" .cameramodel
    pair), None for a mono sensor; `models`: folder with marknet.onnx and mre.onnx (default: the
    shipped ones); `grid`: "ROWSxCOLS" or (rows, cols) (default 23x23); `sensor`: sensor description
    JSON (its gel's facts, and the indices of a grid that overfills the view). The keywords mirror
    `gelstereo track`'s flags: `gel` (a gel file), `gel_thickness_mm`, `gel_modulus_kpa`, `poisson`,
    `friction`; `method` ("marknet-mre", "marknet", "blob", "yolo"); `pitch_mm` (a mono sensor's
    marker pitch, for its area in mm²); `threads` (0: one per core); `mono` (track the left view
    only); `pad_border` is accepted and ignored (DeprecationWarning), as `--pad-border`. Every
    other setting is `gelstereo track`'s default.
    Raises GelstereoError when the calibration, models, sensor description or a setting cannot be
    used, ValueError for an unknown method or more than 256 threads (also from RAYON_NUM_THREADS or
    OMP_NUM_THREADS).
    """

    def __init__(
        self,
        calibration: Optional[Union[str, os.PathLike[str]]] = None,
        models: Optional[Union[str, os.PathLike[str]]] = None,
        grid: Optional[Union[str, Tuple[int, int]]] = None,
        sensor: Optional[Union[str, os.PathLike[str]]] = None,
        *,
        gel: Optional[Union[str, os.PathLike[str]]] = None,
        gel_thickness_mm: Optional[float] = None,
        gel_modulus_kpa: Optional[float] = None,
        poisson: Optional[float] = None,
        friction: Optional[float] = None,
        method: Optional[str] = None,
        pitch_mm: Optional[float] = None,
        threads: int = 0,
        mono: bool = False,
        pad_border: Optional[Union[str, int]] = None,
    ) -> None: ...
    def process(self, left: Image, right: Optional[Image] = None, timestamp: Optional[float] = None) -> Frame:
        """Processes one frame (stereo when `right` is given); timestamp in s (finite, each later than the last), None: frame number / 30 Hz.

        A frame that cannot be read, localized or indexed comes back flagged (`Frame.note`). The GIL
        is released while processing; threads sharing a pipeline take turns.
        """
    def rezero(self) -> None:
        """Makes the current shape of the gel the reference from the next frame on."""
    @property
    def method(self) -> str: ...
    @property
    def is_stereo(self) -> bool: ...
    @property
    def grid(self) -> Tuple[int, int]: ...

class InputFrame:
    """One frame of a source: its images as numpy uint8 arrays (BGR, as OpenCV reads)."""

    index: int
    """Frame number in the source, from 0."""
    timestamp: float
    """Capture time, s (frame number / frame rate for files)."""
    left: Optional[Image]
    """The left view (a mono sensor's view); None when the frame could not be read."""
    right: Optional[Image]
    """The right view; None for a mono source or an unreadable frame."""
    error: Optional[str]
    """Why the frame could not be read; None for a frame read whole."""

class FrameReader:
    """The frames of a source, in order, read ahead on a thread of their own."""

    is_stereo: bool
    frames: Optional[int]
    """The number of frames when the source declares it (a folder, a video), else None."""
    def __iter__(self) -> "FrameReader": ...
    def __next__(self) -> InputFrame: ...

def open(
    source: Union[str, os.PathLike[str], int, Tuple[int, int]], *, side_by_side: bool = False, mono: bool = False
) -> FrameReader:
    """Opens frames for `Pipeline.process`: a stereo recording folder, a folder of images (mono), a
    video file, a camera index, a (left, right) pair of camera indices, or the same as text ("0",
    "0,1"). `side_by_side`: a video or camera holding both views side by side; `mono`: a stereo
    recording's left view only. Frame files are read in natural order (2 before 10), with a
    UserWarning where names do not settle it (1.png and 01.png) or a video ends before its declared
    length. Raises GelstereoError when the source cannot be opened, TypeError for another type."""
