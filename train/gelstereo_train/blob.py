"""The paper's baseline: OpenCV SimpleBlobDetector with the tuned parameters of blob_params.json
(used to define the easy/hard split)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

PARAMS_PATH = Path(__file__).with_name("blob_params.json")


def load_params(path: Path | str = PARAMS_PATH) -> dict:
    """The parameter file without its comment keys."""
    d = json.loads(Path(path).read_text())
    return {k: v for k, v in d.items() if not k.startswith("_")}


class BlobDetector:
    """SimpleBlobDetector configured from blob_params.json; detect() returns (n, 2) pixel centres."""

    def __init__(self, params: dict | None = None):
        import cv2

        self._cv2 = cv2
        p = cv2.SimpleBlobDetector_Params()
        for k, v in (params or load_params()).items():
            if not hasattr(p, k):
                raise ValueError(f"{PARAMS_PATH}: unknown SimpleBlobDetector parameter {k!r}")
            setattr(p, k, type(getattr(p, k))(v))
        self.detector = cv2.SimpleBlobDetector_create(p)

    def detect(self, rgb: np.ndarray) -> np.ndarray:
        """Blob centres (n, 2) in original pixels (OpenCV keypoints: pixel-centre convention)."""
        a = np.asarray(rgb)
        grey = a if a.ndim == 2 else self._cv2.cvtColor(np.ascontiguousarray(a[:, :, :3]), self._cv2.COLOR_RGB2GRAY)
        kps = self.detector.detect(grey)
        return np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2)
