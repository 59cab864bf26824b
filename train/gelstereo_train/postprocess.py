"""Inference-side processing for evaluation, the MRE dataset and the fixtures: thin wrappers over the
Rust localizer's own code (``gelstereo.postprocess``, from ``gelstereo-markers``), so that the trainer
measures exactly what ``gelstereo detect`` outputs. docs/model-contract.md describes the steps:
decode, candidates above ``conf_low``, pitch, de-duplication, Marknet's threshold or the MRE, then the
lattice check and (with the image) the steps after it.

Images here are RGB (as ``data.load_rgb`` reads them); they reach Rust as BGR.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from gelstereo import postprocess as _rust

MISSING_DISTANCE = _rust.MISSING_DISTANCE
NEIGHBOURS = _rust.MRE_NEIGHBOURS
AREA_BELOW_SCALE = _rust.AREA_BELOW_SCALE
FILL_SAMPLE_STEP = _rust.FILL_SAMPLE_STEP

_DEFAULT = _rust.default_post()


@dataclass
class PostConfig:
    """Post-processing thresholds (the paper's, as the Rust defaults have them; stored in the model's
    metadata_props). ``lattice``: the lattice check (with its Rust defaults) on or off."""

    conf_keep: float = _DEFAULT["conf_keep"]
    conf_low: float = _DEFAULT["conf_low"]
    conf_marknet_only: float = _DEFAULT["conf_marknet_only"]
    dedup_radius_frac: float = _DEFAULT["dedup_radius_frac"]
    accept: float = _DEFAULT["accept"]
    lattice: bool | None = _DEFAULT["lattice"]


@dataclass(frozen=True)
class FitConfig:
    """The "auto" fit (contract ``gelstereo-marknet/2``) a model is exported with: the image plus one
    marker pitch of margin fitted into ``nominal_hw`` unless that puts the pitch outside
    ``pitch_range_px`` at the input, then scaled to ``pitch_target_px``; sides on multiples of
    ``multiple``. ``prefer_stretch``: the model was trained on whole-image stretches."""

    nominal_hw: tuple[int, int] = (416, 416)
    multiple: int = 32
    pitch_range_px: tuple[float, float] = (9.0, 24.0)
    pitch_target_px: float = 12.0
    prefer_stretch: bool = False


class Layout(NamedTuple):
    """Where an image lies in the network input: resized to (scaled_w, scaled_h) and placed at (ox, oy)
    inside an input of (input_w, input_h)."""

    input_w: int
    input_h: int
    scaled_w: int
    scaled_h: int
    ox: int
    oy: int


@dataclass
class Detections:
    """Result of post-processing one image."""

    candidates: np.ndarray  # (K, 3) kept (de-duplicated) candidates with c > conf_low, desc. c
    pitch_px: float
    marknet: np.ndarray  # (n, 3) Marknet-only output
    marknet_mre: np.ndarray  # (n, 3) Marknet + MRE output (empty without an MRE)
    mre_index: np.ndarray  # indices into candidates that went to the MRE
    mre_features: np.ndarray  # their features (len(mre_index), 11)
    mre_scores: np.ndarray  # their scores (NaN when no MRE given)


def bgr(image: np.ndarray) -> np.ndarray:
    """An RGB (or grey) uint8 image as the Rust code reads it (BGR, contiguous)."""
    a = np.asarray(image, dtype=np.uint8)
    return np.ascontiguousarray(a if a.ndim == 2 else a[:, :, 2::-1])


def fit_layout(w: int, h: int, pitch_px: float | None, fit: FitConfig = FitConfig()) -> Layout:
    """The "auto" layout of a w x h image whose marker pitch is pitch_px (original px; None or NaN:
    unknown, no margin and no pitch check)."""
    return Layout(*_rust.fit_layout(w, h, pitch_px, fit))


def stretch_layout(input_wh: tuple[int, int]) -> Layout:
    """The whole image resized to the input (the first contract's layout)."""
    w, h = input_wh
    return Layout(w, h, w, h, 0, 0)


def fit_config_from_metadata(meta: dict) -> FitConfig:
    """The FitConfig an exported dynamic model declares in its metadata_props."""
    lo, hi = (float(v) for v in meta["pitch_range_px"].split(","))
    return FitConfig(
        nominal_hw=(int(meta["input_height"]), int(meta["input_width"])),
        multiple=int(meta["input_multiple"]),
        pitch_range_px=(lo, hi),
        pitch_target_px=float(meta["pitch_target_px"]),
        prefer_stretch=meta.get("preferred_layout", "isotropic") == "stretch",
    )


def fit_metadata(fit: FitConfig) -> dict:
    """metadata_props entries of the "auto" fit (contract gelstereo-marknet/2)."""
    return {
        "input_size": "dynamic",
        "input_multiple": fit.multiple,
        "pitch_range_px": f"{fit.pitch_range_px[0]:g},{fit.pitch_range_px[1]:g}",
        "pitch_target_px": f"{fit.pitch_target_px:g}",
        "preferred_layout": "stretch" if fit.prefer_stretch else "isotropic",
    }


def input_per_px(image_wh: tuple[int, int], lay: Layout) -> float:
    """Input px per original px under a layout (geometric mean of the two axes)."""
    return _rust.input_per_px(image_wh[0], image_wh[1], tuple(lay))


def preprocess_layout(rgb: np.ndarray, lay: Layout) -> torch.Tensor:
    """uint8 RGB (H, W, 3) or grey -> float (1, 3, input_h, input_w) as Marknet's input in Rust: the
    8-bit image resized (bilinear, half-pixel centres; area averaging first below AREA_BELOW_SCALE),
    /255, the margin filled with the resized image's median colour."""
    return torch.from_numpy(_rust.network_input(bgr(rgb), tuple(lay)))


def preprocess(rgb: np.ndarray, input_hw: tuple[int, int]) -> torch.Tensor:
    """uint8 RGB (H, W, 3) or grey -> float (1, 3, h, w): the whole image resized to the input."""
    return preprocess_layout(rgb, stretch_layout(input_hw[::-1]))


def decode_layout(raw: np.ndarray, stride: int, image_wh: tuple[int, int], lay: Layout) -> np.ndarray:
    """Raw logits (Gy, Gx, m, 3) of one image under a layout -> (n, 3) (x_orig, y_orig, c) in flat order,
    the candidates in the margin removed."""
    raw = np.ascontiguousarray(raw, dtype=np.float32)
    return _rust.decode(raw, stride, image_wh[0], image_wh[1], tuple(lay))


def decode_to_original(raw: np.ndarray, stride: int, image_wh: tuple[int, int], input_wh: tuple[int, int]):
    """Raw logits (Gy, Gx, m, 3) of one image stretched to the input -> (Gy*Gx*m, 3), flat order."""
    return decode_layout(raw, stride, image_wh, stretch_layout(input_wh))


def postprocess(decoded: np.ndarray, cfg: PostConfig, mre_fn=None, input_per_px: float | None = None,
                image_wh: tuple[int, int] | None = None, looked=None, image: np.ndarray | None = None,
                close_look: bool = True) -> Detections:
    """The post-processing of decoded (x_orig, y_orig, c) rows in flat order, for Marknet alone and, with
    ``mre_fn`` ((n, 11) float32 -> (n,) probabilities), Marknet + MRE. With ``cfg.lattice`` and
    ``input_per_px`` (the layout's), both keep their lattice (inside ``looked``, the region a closer look
    re-examined, from a lower confidence); then with the RGB ``image`` the Rust localizer's steps after
    the lattice check, or with ``image_wh`` alone the edge rule."""
    def scores(f):
        return np.asarray(mre_fn(f), dtype=np.float64).reshape(-1).tolist()

    out = _rust.postprocess(
        np.ascontiguousarray(decoded, dtype=np.float64).reshape(-1, 3), cfg,
        mre=None if mre_fn is None else scores, input_per_px=input_per_px,
        size=None if image_wh is None else tuple(image_wh), looked=None if looked is None else tuple(looked),
        image=None if image is None else bgr(image), close_look=close_look)
    return Detections(**out)


def lattice_fit(points: np.ndarray, input_per_px: float, conf: np.ndarray | None = None):
    """(member mask, on-lattice mask, pitch_px or NaN, is_lattice) of ``points`` (n, 2) with confidences
    ``conf`` (None: all sure), by the Rust lattice check."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    c = None if conf is None else np.ascontiguousarray(conf, dtype=np.float64)
    return _rust.lattice_fit(pts, c, input_per_px)


class TorchMRE:
    """Callable wrapper of a trained MRE module (probabilities)."""

    def __init__(self, model):
        self.model = model.eval()

    def __call__(self, feats: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return torch.sigmoid(self.model(torch.from_numpy(np.asarray(feats, np.float32)))).numpy()[:, 0]
