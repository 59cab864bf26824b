"""Reads a stereo recording in gelstereo's layout (REC/left/*.png|jpg, REC/right/ the same names)
as OpenCV BGR arrays: the frame source both examples share."""

from pathlib import Path
from typing import Iterator, Tuple

import cv2
import numpy as np

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


def stereo_frames(recording: Path) -> Iterator[Tuple[int, np.ndarray, np.ndarray]]:
    """(frame number, left BGR, right BGR) per stereo pair, in file-name order."""
    lefts = sorted(p for p in (recording / "left").iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not lefts:
        raise SystemExit(f"{recording}: no images in left/ (expected a stereo recording: left/ and right/)")
    for k, left_path in enumerate(lefts):
        right_path = recording / "right" / left_path.name
        left = cv2.imread(str(left_path), cv2.IMREAD_COLOR)
        right = cv2.imread(str(right_path), cv2.IMREAD_COLOR)
        if left is None or right is None:
            raise SystemExit(f"cannot read the pair {left_path} / {right_path}")
        yield k, left, right
