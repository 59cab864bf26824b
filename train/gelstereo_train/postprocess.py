"""Inference-side processing shared by evaluation, the MRE dataset and the Rust fixtures; this is the
reference implementation of docs/model-contract.md.

Order of operations for one image (all positions in ORIGINAL pixels, pixel-centre convention):
1. decode every cell/slot: ``x_in = (sigmoid(tx) + gx) * stride``, ``x_orig = x_in * W / input_width - 0.5``
   (likewise y), ``c = sigmoid(tc)``;
2. candidates = those with ``c > conf_low``;
3. ``pitch_px`` = median nearest-neighbour distance between the candidates with ``c > conf_keep``
   (fallback: all candidates; undefined with fewer than 2);
4. de-duplication: candidates visited in descending c (ties: lower flat index first, flat index =
   (gy * Gx + gx) * m + k); one closer than ``dedup_radius_frac * pitch_px`` to an already kept one
   is dropped;
5. Marknet only: the kept candidates with ``c > conf_marknet_only``;
6. Marknet + MRE: the kept candidates with ``c > conf_keep``, plus those with c <= conf_keep whose MRE
   score is > ``accept``. MRE feature: the 10 smallest distances from the candidate to the OTHER kept
   candidates, ascending, divided by pitch_px, missing ones = 4.0 (all = 4.0 when pitch is undefined),
   then c.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .data import nearest_neighbour_distances

MISSING_DISTANCE = 4.0
NEIGHBOURS = 10


@dataclass(frozen=True)
class LatticeCheck:
    """Which candidates sit on a marker lattice (``lattice_members``; the Rust twin is
    ``gelstereo_markers::lattice``). A point is a member when it lies on equally spaced lines of three
    points (it and two neighbours, spacing within ``tolerance_frac``) in at least two directions
    ``min_angle_deg`` apart, and such points joined by those lines form a patch of at least
    ``min_patch`` whose spacing is within ``patch_pitch_ratio`` of the largest patch's (texture lines up
    by chance at its own, finer spacing). Neighbours are searched within ``reach_frac`` x max(own
    nearest-neighbour distance, median of them)."""

    tolerance_frac: float = 0.2
    reach_frac: float = 1.6
    min_angle_deg: float = 30.0
    min_patch: int = 6
    patch_pitch_ratio: float = 1.3  # a patch's spacing against the largest patch's, at most
    max_neighbours: int = 12
    min_support: int = 8  # members needed for a lattice (and for its pitch to steer the layout)
    min_input_pitch_px: float = 8.0  # smallest lattice spacing at the network input
    adjacent_members: int = 3  # members within reach_frac x pitch that put a non-member on the lattice
    adjacent_min_confidence: float = 0.9  # confidence such a non-member needs to be kept
    looked_min_confidence: float = 0.4  # the same inside the region a closer look re-examined
    line_end_min_confidence: float = 0.7  # a candidate this sure may join on one line, end or middle (Rust: the same)


@dataclass
class PostConfig:
    """Post-processing thresholds (paper values; stored in the model's metadata_props)."""

    conf_keep: float = 0.4  # paper: c > 0.4 passes directly
    conf_low: float = 0.1  # paper: 0.1 < c <= 0.4 goes to the MRE
    conf_marknet_only: float = 0.2  # paper: Marknet alone outputs c > 0.2
    dedup_radius_frac: float = 0.3  # of pitch_px; below half the smallest compressed pitch seen in sim
    accept: float = 0.99  # paper: MRE accepts when y_e > 0.99
    # The lattice check of the output and of the layout's pitch (None: the contract's steps alone)
    lattice: LatticeCheck | None = LatticeCheck()


@dataclass(frozen=True)
class FitConfig:
    """How an image is fitted to a dynamic-size network input (contract ``gelstereo-marknet/2``, "auto" fit).

    The scale is isotropic: the image plus one marker pitch of margin is fitted into the nominal input
    (``nominal_hw``); if that puts the marker pitch outside ``pitch_range_px`` at the input, the image is
    scaled to ``pitch_target_px`` instead. The input is the scaled image centred in the smallest multiple
    of ``multiple`` px around it, the rest filled with the image's median colour (``preprocess_layout``)."""

    nominal_hw: tuple[int, int] = (416, 416)
    multiple: int = 32
    pitch_range_px: tuple[float, float] = (9.0, 24.0)
    pitch_target_px: float = 12.0
    max_side: int = 2048
    # The layout the network was trained on (its canonical crops): False = isotropic, as above; True = the
    # whole-image stretch to the nominal input, kept whenever it puts the pitch in range along both axes.
    prefer_stretch: bool = False


@dataclass(frozen=True)
class Layout:
    """Where an image lies in the network input: resized to (scaled_w, scaled_h) and placed at (ox, oy)
    inside an input of (input_w, input_h)."""

    input_w: int
    input_h: int
    scaled_w: int
    scaled_h: int
    ox: int
    oy: int


def _ceil_to(v: float, m: int) -> int:
    return max(m, int(math.ceil(v / m - 1e-9)) * m)


def fit_layout(w: int, h: int, pitch_px: float | None, fit: FitConfig = FitConfig()) -> Layout:
    """The "auto" layout of a w x h image whose marker pitch is pitch_px (original px; None or NaN:
    unknown, no margin and no pitch check). Mirrors ``fit_layout`` in gelstereo-markers."""
    p = pitch_px if pitch_px is not None and math.isfinite(pitch_px) and pitch_px > 0 else 0.0
    nh, nw = fit.nominal_hw
    lo, hi = fit.pitch_range_px
    if fit.prefer_stretch and (p == 0 or (lo <= p * nw / w <= hi and lo <= p * nh / h <= hi)):
        return Layout(nw, nh, nw, nh, 0, 0)
    s = min(nw / (w + p), nh / (h + p))
    if p > 0 and not lo <= p * s <= hi:
        s = fit.pitch_target_px / p
    return layout_at_scale(w, h, p, s, fit)


def layout_at_scale(w: int, h: int, p: float, s: float, fit: FitConfig) -> Layout:
    """The layout of a w x h image at scale s with a margin of p px, capped at fit.max_side."""
    s = min(s, fit.max_side / (w + p), fit.max_side / (h + p))
    iw = _ceil_to(s * (w + p), fit.multiple)
    ih = _ceil_to(s * (h + p), fit.multiple)
    sw = min(iw, max(1, int(math.floor(s * w + 0.5))))  # half away from zero, as Rust's f64::round
    sh = min(ih, max(1, int(math.floor(s * h + 0.5))))
    return Layout(iw, ih, sw, sh, (iw - sw) // 2, (ih - sh) // 2)


RELAYOUT_SCALE_CHANGE = 0.1  # a second pass when the measured pitch moves the scale by more than this
AREA_BELOW_SCALE = 0.34  # below this scale the image is reduced by area averaging first (Rust: AREA_BELOW_SCALE)
MAX_RELAYOUTS = 3  # passes at the layout of a measured pitch, at most (Rust: MAX_RELAYOUTS)
MIN_PITCH_SUPPORT = 8  # confident candidates (c > conf_keep) needed to trust a measured pitch


PROBE_SCALE = 2.0  # a first pass without a pitch is run again at this x the scale (see MarknetRunner.fitted)
FINE_PROBE_SCALE = 4.0  # where neither the first pass nor the probe finds a lattice: probed once more at this x
COARSE_PROBE_SCALE = 0.25  # where no pass so far finds a lattice: probed at this x too (markers too coarse)
PROBE_MIN_GAIN = 2.0  # times the first pass's confident candidates the probe must find
PROBE_MIN_COVER = 0.5  # share of the first pass's covered area (confident x pitch^2) the probe must cover


# A closer look where the lattice is squeezed (Rust: ``gelstereo_markers::close_look``).
SQUEEZED_NN_PITCH = 0.8  # a candidate whose nearest other candidate is closer than this x pitch is squeezed
SQUEEZED_MAX_CONFIDENCE = 0.9  # ... when the network is less sure of it than this (a sure pair is resolved)
CLOSE_LOOK_ZOOM = 1.5  # scale of the close look relative to the first pass's
CLOSE_LOOK_MAX_INPUT_PITCH_PX = 20.0  # ... capped so that the pitch at the input stays below this
CLOSE_LOOK_MIN_ZOOM = 1.2  # a smaller zoom is not worth a pass
CLOSE_LOOK_MAX_SHARE = 0.5  # a larger region of squeezed candidates is an irregular lattice, not a squeeze
CLOSE_LOOK_MARGIN_PITCH = 1.5  # margin around the squeezed candidates, pitches


def squeezed_region(kept: np.ndarray, pitch: float, image_wh: tuple[int, int]):
    """(x0, y0, x1, y1) around the squeezed rows of ``kept`` (de-duplicated candidates x, y, c; squeezed: a
    neighbour closer than SQUEEZED_NN_PITCH x pitch, c < SQUEEZED_MAX_CONFIDENCE) with the
    margin, clipped to the image; None without a pitch, a squeezed candidate, or where the region is
    larger than CLOSE_LOOK_MAX_SHARE of the image (Rust: ``close_look::squeezed_region``)."""
    if not np.isfinite(pitch) or pitch <= 0 or len(kept) < 2:
        return None
    squeezed = kept[(nearest_neighbour_distances(kept[:, :2]) < SQUEEZED_NN_PITCH * pitch)
                    & (kept[:, 2] < SQUEEZED_MAX_CONFIDENCE), :2]
    return region_around(squeezed, pitch, image_wh)


def region_around(points: np.ndarray, pitch: float, image_wh: tuple[int, int]):
    """(x0, y0, x1, y1): the box around ``points`` grown by CLOSE_LOOK_MARGIN_PITCH x pitch, clipped to the
    image span; None without points or where it covers more than CLOSE_LOOK_MAX_SHARE of the image
    (Rust: ``close_look::region_around``)."""
    if not len(points):
        return None
    w, h = image_wh
    m = CLOSE_LOOK_MARGIN_PITCH * pitch
    (x0, y0), (x1, y1) = points.min(0) - m, points.max(0) + m
    x0, y0, x1, y1 = max(x0, -0.5), max(y0, -0.5), min(x1, w - 0.5), min(y1, h - 0.5)
    if max(x1 - x0, 0) * max(y1 - y0, 0) > CLOSE_LOOK_MAX_SHARE * w * h:
        return None
    return x0, y0, x1, y1


def close_look_zoom(pitch_at_input: float) -> float | None:
    """The close look's zoom for a first pass whose pitch at the input is ``pitch_at_input`` px (Rust:
    ``close_look::close_look_zoom``)."""
    zoom = min(CLOSE_LOOK_ZOOM, CLOSE_LOOK_MAX_INPUT_PITCH_PX / pitch_at_input)
    return zoom if zoom >= CLOSE_LOOK_MIN_ZOOM else None


def in_region(rows: np.ndarray, region) -> np.ndarray:
    """Which rows (x, y, ...) lie inside ``region`` (x0, y0, x1, y1), edges included (Rust:
    ``Region::contains``)."""
    x0, y0, x1, y1 = region
    x, y = rows[:, 0], rows[:, 1]
    return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)


def merge_close_look(first: np.ndarray, closer: np.ndarray, region) -> np.ndarray:
    """The first pass's decoded rows outside ``region``, then the close look's inside it (Rust:
    ``close_look::merge``)."""
    return np.concatenate([first[~in_region(first, region)], closer[in_region(closer, region)]])


def probe_layout(w: int, h: int, fit: FitConfig, scale: float = PROBE_SCALE) -> Layout:
    """The probe of the "auto" fit: isotropic, PROBE_SCALE x the nominal fit's scale, no margin (capped at
    fit.max_side). A sensor whose pitch falls below the network's range at the nominal fit shows only a
    scattered few markers there, whose nearest-neighbour distances overstate the pitch, so the measured
    pitch alone never asks for the larger scale. ``scale``: FINE_PROBE_SCALE for the fine probe, COARSE_PROBE_SCALE for the coarse one.
    Mirrors ``probe_layout`` / ``probe_layout_at`` in gelstereo-markers."""
    nh, nw = fit.nominal_hw
    return layout_at_scale(w, h, 0.0, scale * min(nw / w, nh / h), fit)


def relayout_needed(used: Layout, wanted: Layout) -> bool:
    """Whether a pass under ``used`` should be redone under ``wanted`` (scale off by > 10 % along x or y)."""
    return (abs(wanted.scaled_w / used.scaled_w - 1.0) > RELAYOUT_SCALE_CHANGE
            or abs(wanted.scaled_h / used.scaled_h - 1.0) > RELAYOUT_SCALE_CHANGE)


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


FILL_SAMPLE_STEP = 4  # the margin's colour: median of every 4th pixel of every 4th row (Rust: resize.rs)


def preprocess_layout(rgb: np.ndarray, lay: Layout) -> torch.Tensor:
    """uint8 RGB (H, W, 3) or grey -> float (1, 3, input_h, input_w): rgb/255, bilinear resize to the
    layout's scaled size (half-pixel centres, no antialiasing; below AREA_BELOW_SCALE along either axis the
    8-bit image is first reduced to that size by area averaging, cv2.INTER_AREA), the margin filled with
    the resized image's median colour per channel (lower median of the sampled pixels). A mirrored margin would
    complete a dot cut by the border into a phantom marker on the edge and pull whole dots near the
    edge towards their reflections."""
    a = np.asarray(rgb)
    if lay.scaled_w < AREA_BELOW_SCALE * a.shape[1] or lay.scaled_h < AREA_BELOW_SCALE * a.shape[0]:
        import cv2  # the trainer's requirements; only large reductions need it

        a = cv2.resize(np.ascontiguousarray(a), (lay.scaled_w, lay.scaled_h), interpolation=cv2.INTER_AREA)
    x = preprocess(a, (lay.scaled_h, lay.scaled_w))
    if (lay.scaled_w, lay.scaled_h) == (lay.input_w, lay.input_h):
        return x
    step = FILL_SAMPLE_STEP
    fill = x[0, :, ::step, ::step].reshape(3, -1).median(dim=1).values
    out = fill.view(1, 3, 1, 1).expand(1, 3, lay.input_h, lay.input_w).clone()
    out[:, :, lay.oy:lay.oy + lay.scaled_h, lay.ox:lay.ox + lay.scaled_w] = x
    return out


def decode_layout(raw: np.ndarray, stride: int, image_wh: tuple[int, int], lay: Layout) -> np.ndarray:
    """Raw logits (Gy, Gx, m, 3) of one image under a layout -> (n, 3) (x_orig, y_orig, c) in flat order,
    the candidates in the margin removed (a marker whose centre lies outside the image is not reported)."""
    raw = np.asarray(raw, dtype=np.float64)
    gy, gx, m, _ = raw.shape
    sig = 1.0 / (1.0 + np.exp(-raw))
    xs = np.arange(gx).reshape(1, gx, 1)
    ys = np.arange(gy).reshape(gy, 1, 1)
    x_in = (sig[..., 0] + xs) * stride - lay.ox
    y_in = (sig[..., 1] + ys) * stride - lay.oy
    sx = image_wh[0] / lay.scaled_w
    sy = image_wh[1] / lay.scaled_h
    out = np.stack([x_in * sx - 0.5, y_in * sy - 0.5, sig[..., 2]], axis=-1).reshape(-1, 3)
    w, h = image_wh
    inside = (out[:, 0] >= -0.5) & (out[:, 0] <= w - 0.5) & (out[:, 1] >= -0.5) & (out[:, 1] <= h - 0.5)
    return out[inside]


def preprocess(rgb: np.ndarray, input_hw: tuple[int, int]) -> torch.Tensor:
    """uint8 RGB (H, W, 3) (or grey (H, W)) -> float (1, 3, h, w) in [0, 1]: rgb/255, then a bilinear
    resize with half-pixel centres and no antialiasing (OpenCV INTER_LINEAR geometry)."""
    a = np.asarray(rgb)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    x = torch.from_numpy(np.ascontiguousarray(a[:, :, :3])).permute(2, 0, 1).float()[None] / 255.0
    if tuple(x.shape[2:]) != tuple(input_hw):
        x = F.interpolate(x, size=tuple(input_hw), mode="bilinear", align_corners=False, antialias=False)
    return x


def decode_to_original(raw: np.ndarray, stride: int, image_wh: tuple[int, int], input_wh: tuple[int, int]):
    """Raw logits (Gy, Gx, m, 3) of one image -> (Gy*Gx*m, 3) array (x_orig, y_orig, c), flat order."""
    raw = np.asarray(raw, dtype=np.float64)
    gy, gx, m, _ = raw.shape
    sig = 1.0 / (1.0 + np.exp(-raw))
    xs = np.arange(gx).reshape(1, gx, 1)
    ys = np.arange(gy).reshape(gy, 1, 1)
    x_in = (sig[..., 0] + xs) * stride
    y_in = (sig[..., 1] + ys) * stride
    sx = image_wh[0] / input_wh[0]
    sy = image_wh[1] / input_wh[1]
    out = np.stack([x_in * sx - 0.5, y_in * sy - 0.5, sig[..., 2]], axis=-1)
    return out.reshape(-1, 3)


def _pairwise(p: np.ndarray) -> np.ndarray:
    d = np.sqrt(((p[:, None, :] - p[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    return d


def pitch_px(cands: np.ndarray, conf_keep: float) -> float:
    """Median nearest-neighbour distance of the confident candidates (NaN when undefined)."""
    sel = cands[cands[:, 2] > conf_keep]
    if len(sel) < 2:
        sel = cands
    if len(sel) < 2:
        return float("nan")
    return float(np.median(nearest_neighbour_distances(sel[:, :2])))


def dedup(cands: np.ndarray, radius_px: float) -> np.ndarray:
    """Indices (into cands) kept by the greedy de-duplication, in descending confidence."""
    order = np.argsort(-cands[:, 2], kind="stable")
    if not np.isfinite(radius_px) or radius_px <= 0 or len(cands) < 2:
        return order
    p = cands[order, :2]
    d = _pairwise(p)
    kept = np.zeros(len(p), dtype=bool)
    for i in range(len(p)):
        if not (kept & (d[i] < radius_px)).any():
            kept[i] = True
    return order[kept]


def mre_features(kept: np.ndarray, pitch: float, which: np.ndarray) -> np.ndarray:
    """(len(which), 11) float32 features of kept[which] against all other kept candidates."""
    feats = np.full((len(which), NEIGHBOURS + 1), MISSING_DISTANCE, dtype=np.float64)
    if len(which) == 0:
        return feats.astype(np.float32)
    feats[:, NEIGHBOURS] = kept[which, 2]
    if np.isfinite(pitch) and pitch > 0 and len(kept) > 1:
        d = np.sqrt(((kept[which, None, :2] - kept[None, :, :2]) ** 2).sum(-1))
        d[np.arange(len(which)), which] = np.inf
        d.sort(axis=1)
        k = min(NEIGHBOURS, len(kept) - 1)
        feats[:, :k] = d[:, :k] / pitch
    return feats.astype(np.float32)


@dataclass
class Detections:
    """Result of post-processing one image."""

    candidates: np.ndarray  # (K, 3) kept (de-duplicated) candidates with c > conf_low, desc. c
    pitch_px: float
    marknet: np.ndarray  # (n, 3) Marknet-only output
    marknet_mre: np.ndarray  # (n, 3) Marknet + MRE output
    mre_index: np.ndarray  # indices into candidates that went to the MRE
    mre_features: np.ndarray  # their features (len(mre_index), 11)
    mre_scores: np.ndarray  # their scores (NaN when no MRE given)


# A marker reported closer than this share of the pitch to the image's outermost pixel centres is not
# reported: its visible part is less than half a dot, its centre outside the image (Rust:
# `postprocess::EDGE_MARGIN_PITCH`).
EDGE_MARGIN_PITCH = 0.02  # without a lattice line inwards, a marker reported nearer the edge goes (Rust: edge.rs)
IMAGE_SPAN_PX = 0.5  # the image reaches this far beyond its outermost pixel centres (Rust: IMAGE_SPAN_PX)
NEAR_EDGE_PITCH = 0.5  # markers reported within this of an edge are checked against it
EDGE_STEP_PITCH = (0.6, 1.5)  # the first step of a line inwards, in pitches
EDGE_LINE_TOLERANCE = 0.3  # the second step's distance from equal spacing, in first steps
MIN_INWARD_COSINE = 0.5  # a line's first step against the edge's inward normal


def _extrapolated_inside(p: np.ndarray, normal: np.ndarray, offset: float, lattice: np.ndarray,
                         pitch: float) -> float | None:
    """How far inside the side (normal, offset) the line inwards from ``p`` most nearly along the normal
    puts its centre: ``2 p1 - p2`` for lattice points one and two steps away (Rust: ``extrapolated_inside_px``)."""
    v = lattice - p
    step = np.hypot(v[:, 0], v[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = (v @ normal) / step
    ok = (step >= EDGE_STEP_PITCH[0] * pitch) & (step <= EDGE_STEP_PITCH[1] * pitch) & (cosine >= MIN_INWARD_COSINE)
    best = None
    for j in np.nonzero(ok)[0][np.argsort(-cosine[ok], kind="stable")]:
        want = 2 * lattice[j] - p
        e = np.hypot(*(lattice - want).T)
        k = int(e.argmin())
        if e[k] <= EDGE_LINE_TOLERANCE * step[j]:
            best = float((2 * lattice[j] - lattice[k]) @ normal - offset)
            break
    return best


def inside_the_edge(markers: np.ndarray, image_wh: tuple[int, int], pitch: float) -> np.ndarray:
    """The rows (x, y, ...) of ``markers`` whose centre lies inside an image of ``image_wh``: near an edge,
    the line of the markers inwards puts it no further than ``IMAGE_SPAN_PX``
    beyond the outermost pixel centres, or without such a line the marker is reported at least
    ``EDGE_MARGIN_PITCH`` x ``pitch`` inside them; all of them without a pitch
    (Rust: ``gelstereo_markers::edge::drop_past_the_edge``)."""
    if not np.isfinite(pitch) or pitch <= 0 or not len(markers):
        return markers
    w, h = image_wh
    sides = [(np.array([1.0, 0.0]), 0.0), (np.array([-1.0, 0.0]), -(w - 1.0)),
             (np.array([0.0, 1.0]), 0.0), (np.array([0.0, -1.0]), -(h - 1.0))]
    pts = markers[:, :2].astype(np.float64)
    keep = np.ones(len(markers), bool)
    for i, p in enumerate(pts):
        for normal, offset in sides:
            inside = float(p @ normal - offset)
            if inside >= NEAR_EDGE_PITCH * pitch:
                continue
            centre = _extrapolated_inside(p, normal, offset, pts, pitch)
            if (inside < EDGE_MARGIN_PITCH * pitch) if centre is None else (centre < -IMAGE_SPAN_PX):
                keep[i] = False
                break
    return markers[keep]


BLOB_LEVELS = (0.3, 0.5, 0.7)  # grey levels between the dots' median and the gel's (Rust: squeezed_blobs::LEVELS)
BLOB_MIN_CONTRAST = 12.0  # grey levels between dots and gel below which no blob is trusted
BLOB_AREA_PITCH2 = (0.02, 0.6)  # a blob's area in pitches squared
BLOB_MIN_INERTIA_RATIO = 0.1  # a dash squeezed to 0.35 of its width passes
BLOB_MIN_CONVEXITY = 0.85  # two merged dashes do not
BLOB_AWAY_PITCH = 0.3  # from every marker
BLOB_INSIDE_MARKERS = 3  # markers within BLOB_INSIDE_REACH_PITCH, around it with no gap over SURROUNDED_GAP_DEG
BLOB_INSIDE_REACH_PITCH = 1.6
BLOB_SQUEEZED_AMONG = 4  # one of its this many nearest markers is squeezed
BLOB_EDGE_PITCH = 0.5  # from the outermost pixel centres
BLOB_CONFIDENCE = 0.5
BLOB_SEARCH_PITCH = 1.5  # radius of the neighbourhood of a squeezed marker searched


def _blob_detector(dot: float, gel: float, pitch: float):
    """OpenCV's SimpleBlobDetector for dots of median grey ``dot`` on a gel of ``gel``, ``pitch`` px apart, at
    BLOB_LEVELS between them; None below BLOB_MIN_CONTRAST (Rust: ``squeezed_blobs::detector_for``)."""
    import cv2

    lo, hi = min(dot, gel), max(dot, gel)
    span = hi - lo
    if span < BLOB_MIN_CONTRAST:
        return None
    p = cv2.SimpleBlobDetector_Params()
    p.thresholdStep = (BLOB_LEVELS[1] - BLOB_LEVELS[0]) * span
    p.minThreshold, p.maxThreshold = lo + BLOB_LEVELS[0] * span, lo + BLOB_LEVELS[2] * span + 0.5
    p.minRepeatability, p.minDistBetweenBlobs = 2, 0.25 * pitch
    p.filterByColor, p.blobColor = True, 0 if dot < gel else 255
    p.filterByArea, p.minArea, p.maxArea = True, BLOB_AREA_PITCH2[0] * pitch ** 2, BLOB_AREA_PITCH2[1] * pitch ** 2
    p.filterByCircularity = False
    p.filterByInertia, p.minInertiaRatio = True, BLOB_MIN_INERTIA_RATIO
    p.filterByConvexity, p.minConvexity = True, BLOB_MIN_CONVEXITY
    return cv2.SimpleBlobDetector_create(p)


def squeezed_blobs(image: np.ndarray, markers: np.ndarray, pitch: float) -> np.ndarray:
    """(k, 3) markers (x, y, BLOB_CONFIDENCE) the network missed between the squeezed rows of ``markers``
    (x, y, ...; squeezed: a neighbour closer than SQUEEZED_NN_PITCH x pitch), found as blobs of the RGB
    or grey ``image`` by OpenCV's SimpleBlobDetector at BLOB_LEVELS, away from every marker, surrounded by
    them, beside a squeezed one and away from the border (Rust: ``gelstereo_markers::squeezed_blobs``)."""
    import cv2

    none = np.zeros((0, 3))
    if not np.isfinite(pitch) or pitch <= 0 or len(markers) < 2:
        return none
    pts = markers[:, :2].astype(np.float64)
    squeezed = nearest_neighbour_distances(pts) < SQUEEZED_NN_PITCH * pitch
    if not squeezed.any():
        return none
    h, w = image.shape[:2]
    region = region_around(pts[squeezed], pitch, (w, h))
    if region is None:
        return none
    x0, y0, x1, y1 = region
    ix0, iy0 = int(math.floor(max(x0, 0.0))), int(math.floor(max(y0, 0.0)))
    ix1, iy1 = min(int(math.ceil(x1)), w - 1), min(int(math.ceil(y1)), h - 1)
    if ix1 <= ix0 or iy1 <= iy0:
        return none
    roi = image[iy0:iy1 + 1, ix0:ix1 + 1]
    grey = roi.copy() if roi.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(roi), cv2.COLOR_RGB2GRAY)
    inside = pts[(pts[:, 0] >= x0) & (pts[:, 0] <= x1) & (pts[:, 1] >= y0) & (pts[:, 1] <= y1)]
    ix = np.clip(np.floor(inside + 0.5).astype(int) - [ix0, iy0], 0, [grey.shape[1] - 1, grey.shape[0] - 1])
    dot, gel = float(np.median(grey[ix[:, 1], ix[:, 0]])) if len(ix) else 0.0, float(np.median(grey))
    # Only the squeezed markers' neighbourhoods are searched: the rest is painted the gel's grey.
    searched = np.zeros(grey.shape, np.uint8)
    # Rounding half away from zero, as Rust's f64::round.
    for q in np.floor(pts[squeezed] + 0.5).astype(int) - [ix0, iy0]:
        cv2.circle(searched, (int(q[0]), int(q[1])), int(math.floor(BLOB_SEARCH_PITCH * pitch + 0.5)), 255, -1)
    grey[searched == 0] = int(math.floor(gel + 0.5))
    detector = _blob_detector(dot, gel, pitch)
    if detector is None:
        return none
    kps = detector.detect(grey)
    found = []
    for k in kps:
        b = np.array([k.pt[0] + ix0, k.pt[1] + iy0])
        if inside_the_image_px(b, (w, h)) < BLOB_EDGE_PITCH * pitch:
            continue
        d = np.hypot(*(pts - b).T)
        near = np.nonzero(d < BLOB_INSIDE_REACH_PITCH * pitch)[0]
        near = near[np.argsort(d[near], kind="stable")]
        if not len(near) or d[near[0]] <= BLOB_AWAY_PITCH * pitch or len(near) < BLOB_INSIDE_MARKERS:
            continue
        angles = np.sort(np.arctan2(pts[near, 1] - b[1], pts[near, 0] - b[0]))
        gap = max(np.diff(angles).max(initial=0.0), 2 * math.pi - (angles[-1] - angles[0]))
        if gap <= math.radians(SURROUNDED_GAP_DEG) and squeezed[near[:BLOB_SQUEEZED_AMONG]].any():
            found.append((b[0], b[1], BLOB_CONFIDENCE))
    return np.array(found).reshape(-1, 3)


SITE_STEP = (0.75, 1.33)  # spacing of the lines that place an empty site, in pitches (Rust: SITE_STEP)
SITE_LINE_TOLERANCE = 0.2  # a line's third point within this share of its spacing (Rust: LINE_TOLERANCE)
SITE_EMPTY_PITCH = 0.5  # no marker this close: the site is empty (Rust: EMPTY_PITCH)
SITE_INSIDE_PITCH = 0.15  # sites searched this far inside the outermost pixel centres (Rust: INSIDE_PITCH)
SITE_REACH_PITCH = 0.3  # a blob within this of its site and as far from every marker (Rust: SITE_REACH_PITCH)
SITE_SEARCH_HALF_PITCH = 0.7  # half the side of the square searched (Rust: SEARCH_HALF_PITCH)
SITE_DOT_SAMPLES = 6  # neighbouring markers whose grey gives the dots' grey (Rust: DOT_SAMPLES)


def _empty_sites(pts: np.ndarray, pitch: float, image_wh: tuple[int, int]) -> np.ndarray:
    """The sites ``s = 2 b - a`` that lines of three markers ``c, a, b`` predict with no marker within
    SITE_EMPTY_PITCH, at a hole (a marker on the line past ``s``) or where the image's border cuts the
    lattice (the next site past ``s`` outside the image); one per site (Rust: ``site_blobs::empty_sites``)."""
    sites: list[np.ndarray] = []

    def near(q: np.ndarray, radius: float) -> bool:
        return bool((np.hypot(pts[:, 0] - q[0], pts[:, 1] - q[1]) <= radius).any())

    for a in pts:
        d_all = np.hypot(pts[:, 0] - a[0], pts[:, 1] - a[1])
        for j in np.nonzero((d_all >= SITE_STEP[0] * pitch) & (d_all <= SITE_STEP[1] * pitch))[0]:
            b, d = pts[j], d_all[j]
            s = 2 * b - a
            if (inside_the_image_px(s, image_wh) < SITE_INSIDE_PITCH * pitch
                    or not near(2 * a - b, SITE_LINE_TOLERANCE * d) or near(s, SITE_EMPTY_PITCH * pitch)):
                continue
            beyond = 2 * s - b
            if (near(beyond, SITE_LINE_TOLERANCE * d) or outside_the_image(beyond, image_wh)) and all(
                    math.hypot(*(t - s)) > SITE_REACH_PITCH * pitch for t in sites):
                sites.append(s)
    return np.array(sites).reshape(-1, 2)


def site_blobs(image: np.ndarray, markers: np.ndarray, pitch: float) -> np.ndarray:
    """(k, 3) markers (x, y, BLOB_CONFIDENCE) the network missed at the lattice's empty sites
    (``_empty_sites``), found as the blob nearest each site by OpenCV's SimpleBlobDetector in the
    RGB or grey ``image`` around it, at levels between its neighbours' grey and the gel's (Rust:
    ``gelstereo_markers::site_blobs``)."""
    import cv2

    if not np.isfinite(pitch) or pitch <= 0 or len(markers) < 3:
        return np.zeros((0, 3))
    pts = markers[:, :2].astype(np.float64)
    grey = image if image.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    h, w = grey.shape
    found = []
    for s in _empty_sites(pts, pitch, (w, h)):
        half = SITE_SEARCH_HALF_PITCH * pitch
        x0, y0 = max(int(math.floor(s[0] - half)), 0), max(int(math.floor(s[1] - half)), 0)
        x1, y1 = min(int(math.ceil(s[0] + half)), w - 1), min(int(math.ceil(s[1] + half)), h - 1)
        if x1 - x0 < 4 or y1 - y0 < 4:
            continue
        roi = np.ascontiguousarray(grey[y0:y1 + 1, x0:x1 + 1])
        d = np.hypot(pts[:, 0] - s[0], pts[:, 1] - s[1])
        order = np.argsort(d, kind="stable")
        nearest = pts[order[:SITE_DOT_SAMPLES]][d[order[:SITE_DOT_SAMPLES]] <= 2.0 * pitch]
        q = np.floor(nearest + 0.5).astype(int)
        q = q[(q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < w) & (q[:, 1] < h)]
        dot = float(np.median(grey[q[:, 1], q[:, 0]])) if len(q) else 0.0
        detector = _blob_detector(dot, float(np.median(roi)), pitch)
        if detector is None:
            continue
        best = None
        for k in detector.detect(roi):
            b = np.array([k.pt[0] + x0, k.pt[1] + y0])
            e = math.hypot(*(b - s))
            far = np.hypot(pts[:, 0] - b[0], pts[:, 1] - b[1]).min() > SITE_REACH_PITCH * pitch
            if e <= SITE_REACH_PITCH * pitch and far and (best is None or e < best[0]):
                best = (e, b)
        if best is not None:
            found.append((best[1][0], best[1][1], BLOB_CONFIDENCE))
    return np.array(found).reshape(-1, 3)


def postprocess(decoded: np.ndarray, cfg: PostConfig, mre_fn=None, input_per_px: float | None = None,
                image_wh: tuple[int, int] | None = None, looked=None) -> Detections:
    """Steps 2-6 of the module doc on decoded (x_orig, y_orig, c) rows in flat order.
    ``mre_fn`` maps an (n, 11) float32 array to (n,) probabilities; None = Marknet only.
    With ``cfg.lattice`` and ``input_per_px`` (the layout's input px per original px), both outputs
    keep only their lattice members (``keep_the_lattice``), as ``gelstereo-markers`` does, and with
    ``image_wh`` too only the markers inside the edge margin (``inside_the_edge``). ``looked``: the region
    (x0, y0, x1, y1) a closer look re-examined (``MarknetRunner.looked``), where the lattice check keeps
    markers on the lattice from ``looked_min_confidence``."""
    cands = decoded[decoded[:, 2] > cfg.conf_low]
    pitch = pitch_px(cands, cfg.conf_keep)
    kept = cands[dedup(cands, cfg.dedup_radius_frac * pitch)]
    marknet = kept[kept[:, 2] > cfg.conf_marknet_only]
    low = np.nonzero(kept[:, 2] <= cfg.conf_keep)[0]
    feats = mre_features(kept, pitch, low)
    if mre_fn is not None and len(low):
        scores = np.asarray(mre_fn(feats), dtype=np.float64).reshape(-1)
    else:
        scores = np.full(len(low), np.nan)
    accept = np.zeros(len(kept), dtype=bool)
    accept[kept[:, 2] > cfg.conf_keep] = True
    if mre_fn is not None:
        accept[low[scores > cfg.accept]] = True
    marknet_mre = kept[accept]
    if cfg.lattice is not None and input_per_px is not None:
        marknet = keep_the_lattice(marknet, cfg.lattice, input_per_px,
                                   unsure=kept[kept[:, 2] <= cfg.conf_marknet_only], looked=looked,
                                   image_wh=image_wh)
        marknet_mre = keep_the_lattice(marknet_mre, cfg.lattice, input_per_px, unsure=kept[~accept],
                                       looked=looked, image_wh=image_wh)
        if image_wh is not None:
            marknet = inside_the_edge(marknet, image_wh, pitch)
            marknet_mre = inside_the_edge(marknet_mre, image_wh, pitch)
    return Detections(kept, pitch, marknet, marknet_mre, low, feats, scores)


class TorchMRE:
    """Callable wrapper of a trained MRE module (probabilities)."""

    def __init__(self, model):
        self.model = model.eval()

    def __call__(self, feats: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return torch.sigmoid(self.model(torch.from_numpy(np.asarray(feats, np.float32)))).numpy()[:, 0]


def run_marknet(model, rgb_images: list[np.ndarray], input_hw: tuple[int, int], batch: int = 8):
    """Decoded candidates (flat, original px) for each image, running the PyTorch model."""
    model.eval()
    out = []
    with torch.no_grad():
        for i in range(0, len(rgb_images), batch):
            chunk = rgb_images[i : i + batch]
            x = torch.cat([preprocess(im, input_hw) for im in chunk])
            raw = model(x).numpy()
            for im, r in zip(chunk, raw):
                out.append(decode_to_original(r, model.stride, (im.shape[1], im.shape[0]), input_hw[::-1]))
    return out


class _Patches:
    """A union-find forest whose roots are the smallest index of their set (Rust: ``lattice::Patches``)."""

    def __init__(self, n: int):
        self.parent = list(range(n))

    def root(self, x: int) -> int:
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def join(self, a: int, b: int) -> None:
        ra, rb = self.root(a), self.root(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def lattice_members(points: np.ndarray, check: LatticeCheck = LatticeCheck()) -> np.ndarray:
    """Boolean mask of the points (n, 2) that sit on a locally consistent lattice (see LatticeCheck)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(p)
    member = np.zeros(n, dtype=bool)
    if n < 3:
        return member
    nn = nearest_neighbour_distances(p)
    median_nn = float(np.median(nn))
    angles: list[list[float]] = [[] for _ in range(n)]
    bonds = []
    for s in range(0, n, 512):
        d = np.sqrt(((p[s:s + 512, None, :] - p[None, :, :]) ** 2).sum(-1))
        for r in range(d.shape[0]):
            i = s + r
            reach = check.reach_frac * max(nn[i], median_nn)
            cand = np.nonzero((d[r] <= reach) & (np.arange(n) != i))[0]
            # the nearest max_neighbours, ties by index (stable sort of the index-ordered candidates)
            cand = cand[np.argsort(d[r, cand], kind="stable")][: check.max_neighbours]
            for a in range(len(cand)):
                j = cand[a]
                v = p[j] - p[i]
                length = math.hypot(v[0], v[1])
                for b in range(a + 1, len(cand)):
                    k = cand[b]
                    miss = p[k] - (p[i] - v)
                    if math.hypot(miss[0], miss[1]) <= check.tolerance_frac * length:
                        ang = math.atan2(v[1], v[0]) % math.pi
                        for q in (i, j, k):
                            angles[q].append(ang)
                        bonds.append((i, j))
                        bonds.append((i, k))
    min_angle = math.radians(check.min_angle_deg)
    two_lines = np.zeros(n, dtype=bool)
    for i in range(n):
        a = np.array(angles[i])
        d = np.abs(a[:, None] - a[None, :])
        # two lines: some pair of directions differs by at least min_angle (modulo pi)
        two_lines[i] = len(a) >= 2 and bool((np.minimum(d, math.pi - d) >= min_angle).any())
    patches = _Patches(n)

    for i, j in bonds:
        if two_lines[i] and two_lines[j]:
            patches.join(i, j)
    roots = np.array([patches.root(i) for i in range(n)])
    sizes = np.bincount(roots[two_lines], minlength=n)
    member = two_lines & (sizes[roots] >= check.min_patch)
    if member.any():
        # the largest patch (ties: the smallest root) sets the pitch the other patches must share
        patch_ids = np.unique(roots[member])
        counts = np.array([(member & (roots == r)).sum() for r in patch_ids])
        pitch = {r: float(np.median(nn[member & (roots == r)])) for r in patch_ids}
        reference = pitch[patch_ids[int(np.argmax(counts))]]
        ok = {r: pitch[r] <= reference * check.patch_pitch_ratio and pitch[r] * check.patch_pitch_ratio >= reference
              for r in patch_ids}
        member &= np.array([ok.get(r, False) for r in roots])
    return member


SPACING_LEFT_OUT = 0.2  # share of the sure points the lines leave out before spacing is asked (Rust: SPACING_LEFT_OUT)
SPACED_NN = (0.6, 1.6)  # nearest-neighbour range of a member by spacing, in medians (Rust: SPACED_NN)
SPACED_REACH = 2.0  # neighbours by spacing are searched within this many medians (Rust: SPACED_REACH)
SURROUNDED_GAP_DEG = 120.0  # largest gap between an inner point's neighbours (Rust: SURROUNDED_GAP_DEG)


def spaced_members(points: np.ndarray, sure: np.ndarray, check: LatticeCheck = LatticeCheck(),
                   nn: np.ndarray | None = None) -> np.ndarray:
    """Boolean mask of the members by spacing (Rust: ``lattice::spaced_members``): points whose nearest
    neighbour is within SPACED_NN of the median, in patches of at least ``min_patch``, at least half of them
    ``sure``, held together by inner points (three such neighbours within SPACED_REACH medians around them,
    no gap above SURROUNDED_GAP_DEG); a sure spaced point with an inner one within reach joins its patch.
    ``nn``: the points' nearest-neighbour distances, when the caller has them."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(p)
    nn = nearest_neighbour_distances(p) if nn is None else nn
    if n < 3 or not np.isfinite(nn).any():
        return np.zeros(n, dtype=bool)
    median_nn = float(np.median(nn[np.isfinite(nn)]))
    spaced = (nn >= SPACED_NN[0] * median_nn) & (nn <= SPACED_NN[1] * median_nn)
    d = np.sqrt(((p[:, None, :] - p[None, :, :]) ** 2).sum(-1))
    near = (d <= SPACED_REACH * median_nn) & ~np.eye(n, dtype=bool)
    inner = np.zeros(n, dtype=bool)
    for i in np.nonzero(spaced)[0]:
        j = np.nonzero(near[i] & spaced)[0]
        if len(j) >= 3:
            a = np.sort(np.arctan2(p[j, 1] - p[i, 1], p[j, 0] - p[i, 0]))
            gap = max(float(np.diff(a).max(initial=0.0)), 2 * math.pi - (a[-1] - a[0]))
            inner[i] = gap <= math.radians(SURROUNDED_GAP_DEG)
    patches = _Patches(n)

    for i in np.nonzero(spaced)[0]:
        for j in np.nonzero(near[i] & inner)[0]:
            patches.join(i, j)
    member = inner | (spaced & sure & ((near & inner[None, :]).sum(1) >= 1))
    roots = np.array([patches.root(i) for i in range(n)])
    sizes = np.bincount(roots[member], minlength=n)
    sure_sizes = np.bincount(roots[member & sure], minlength=n)
    return member & (sizes[roots] >= check.min_patch) & (2 * sure_sizes[roots] >= sizes[roots])


def _finish_fit(p: np.ndarray, nn: np.ndarray, member: np.ndarray, check: LatticeCheck, input_per_px: float):
    """The fit of the ``member`` points among ``p`` (nearest-neighbour distances ``nn``; Rust: ``finish_fit``)."""
    pitch = float(np.median(nn[member])) if member.sum() >= 2 else float("nan")
    ok = bool(member.sum() >= check.min_support and np.isfinite(pitch)
              and pitch * input_per_px >= check.min_input_pitch_px)
    on = member.copy()
    if np.isfinite(pitch):
        for i in np.nonzero(~member)[0]:
            d = np.hypot(p[member, 0] - p[i, 0], p[member, 1] - p[i, 1])
            on[i] = int((d <= check.reach_frac * pitch).sum()) >= check.adjacent_members
    return member, on, pitch, ok


def lattice_fit(points: np.ndarray, check: LatticeCheck, input_per_px: float, conf: np.ndarray | None = None):
    """(member mask, on-lattice mask, pitch_px or NaN, is_lattice) of ``points`` with confidences ``conf``
    (None: all sure) (Rust: ``lattice::fit_lattice``): a lattice needs ``min_support`` members whose median
    nearest-neighbour distance is at least ``min_input_pitch_px`` at the network input; a non-member with
    ``adjacent_members`` members within ``reach_frac`` x that pitch is on the lattice too (a marker pushed
    off its lines in a pile-up). The members are those of the lines and, where those leave more than one
    in 5 of the sure points (confidence >= ``adjacent_min_confidence``) out, those of ``spaced_members``:
    both lattices at one pitch are one (their union), else the larger is."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    nn = nearest_neighbour_distances(p)
    lined_member = lattice_members(p, check)
    sure = np.ones(len(p), dtype=bool) if conf is None else np.asarray(conf) >= check.adjacent_min_confidence
    left_out = int((sure & ~lined_member).sum())
    if left_out < 3 or left_out <= SPACING_LEFT_OUT * int(sure.sum()):
        return _finish_fit(p, nn, lined_member, check, input_per_px)
    spaced_member = spaced_members(p, sure, check, nn)
    lined = _finish_fit(p, nn, lined_member, check, input_per_px)
    spaced = _finish_fit(p, nn, spaced_member, check, input_per_px)
    if not spaced[3]:
        return lined
    if not lined[3]:
        return spaced
    a, b = lined[2], spaced[2]
    if a <= b * check.patch_pitch_ratio and b <= a * check.patch_pitch_ratio:
        return _finish_fit(p, nn, lined_member | spaced_member, check, input_per_px)
    return spaced if spaced_member.sum() > lined_member.sum() else lined


SITE_REACH = 2.2  # members searched around an empty site, in pitches (Rust: SITE_REACH)


def inside_the_image_px(p: np.ndarray, image_wh: tuple[int, int]) -> float:
    """How far ``p`` lies inside the outermost pixel centres of an image of ``image_wh``, px (negative
    outside; Rust: ``edge::inside_the_image_px``)."""
    w, h = image_wh
    return float(min(p[0], p[1], w - 1.0 - p[0], h - 1.0 - p[1]))


def outside_the_image(p: np.ndarray, image_wh: tuple[int, int]) -> bool:
    """Whether ``p`` lies more than ``IMAGE_SPAN_PX`` beyond the outermost pixel centres of an image of
    ``image_wh`` (Rust: ``edge::outside_the_image``)."""
    return inside_the_image_px(p, image_wh) < -IMAGE_SPAN_PX


LINE_END_INSIDE_PITCH = 0.5  # a candidate joining on one line lies this far inside (Rust: the same)


def _at_an_empty_site(p: np.ndarray, confidence: float, members: np.ndarray, taken: np.ndarray, pitch: float,
                      check: LatticeCheck, image_wh: tuple[int, int] | None) -> bool:
    """Rust: ``lattice::at_an_empty_site``: no taken site within half a pitch, and on equally spaced
    lines of three with members in two directions, the middle of at least one, or, in an image of
    ``image_wh``, the end of one whose next site beyond ``p`` lies outside the image; a candidate of
    ``confidence`` >= ``line_end_min_confidence`` at least ``LINE_END_INSIDE_PITCH`` inside an image of
    ``image_wh`` needs only to lie on one such line (its end or its middle)."""
    if len(taken) and np.hypot(taken[:, 0] - p[0], taken[:, 1] - p[1]).min() <= 0.5 * pitch:
        return False
    near = members[np.hypot(members[:, 0] - p[0], members[:, 1] - p[1]) <= SITE_REACH * pitch]
    tol2 = check.tolerance_frac ** 2
    any_angles, middle_angles = [], []
    cut = False

    def beyond(near_pt: np.ndarray) -> bool:
        """The site one step beyond ``p`` from its neighbour ``near_pt`` lies outside the image."""
        return image_wh is not None and outside_the_image(2 * p - near_pt, image_wh)

    for a in range(len(near)):
        q = near[a]
        for r in near[a + 1:]:
            pq2, pr2 = ((p - q) ** 2).sum(), ((p - r) ** 2).sum()
            if not SITE_STEP[0] <= math.sqrt(min(pq2, pr2)) / pitch <= SITE_STEP[1]:
                continue
            is_middle = ((2 * p - q - r) ** 2).sum() <= tol2 * pq2
            end_beside_q = ((2 * q - p - r) ** 2).sum() <= tol2 * pq2
            end_beside_r = ((2 * r - p - q) ** 2).sum() <= tol2 * pr2
            cut = cut or (end_beside_q and beyond(q)) or (end_beside_r and beyond(r))
            is_end = end_beside_q or end_beside_r
            if is_middle or is_end:
                angle = math.atan2(r[1] - q[1], r[0] - q[0]) % math.pi
                any_angles.append(angle)
                if is_middle:
                    middle_angles.append(angle)
    a = np.array(any_angles)
    d = np.abs(a[:, None] - a[None, :])
    two = len(a) >= 2 and bool((np.minimum(d, math.pi - d) >= math.radians(check.min_angle_deg)).any())
    line_end = (confidence >= check.line_end_min_confidence and image_wh is not None
                and inside_the_image_px(p, image_wh) >= LINE_END_INSIDE_PITCH * pitch)
    return ((bool(middle_angles) or cut) and two) or (line_end and len(a) > 0)


def keep_the_lattice(markers: np.ndarray, check: LatticeCheck | None, input_per_px: float,
                     unsure: np.ndarray | None = None, looked=None,
                     image_wh: tuple[int, int] | None = None) -> np.ndarray:
    """The rows (x, y, c) of ``markers`` that are lattice members, or on the lattice with a confidence of at
    least ``adjacent_min_confidence`` (none without a lattice), plus the rows of ``unsure`` (the second
    tier) and the refused ``markers`` that sit at an empty lattice site, most confident first; all of
    ``markers`` when ``check`` is None; with ``image_wh``, a site the image's border cuts the lattice at
    counts as empty too (``_at_an_empty_site``); inside ``looked`` (x0, y0, x1, y1) the bound is
    ``looked_min_confidence`` (Rust: ``lattice::keep_fitted_lattice``)."""
    if check is None:
        return markers
    member, on, pitch, ok = lattice_fit(markers[:, :2], check, input_per_px, markers[:, 2])
    bound = np.full(len(markers), check.adjacent_min_confidence)
    if looked is not None:
        bound[in_region(markers, looked)] = check.looked_min_confidence
    keep = member | (on & (markers[:, 2] >= bound))
    if not ok:
        return markers[:0]
    kept = markers[keep]
    pool = markers[~keep] if unsure is None else np.concatenate([markers[~keep], unsure.reshape(-1, 3)])
    if len(pool) and np.isfinite(pitch):
        members = markers[member, :2]
        taken = kept[:, :2]
        moved = []
        for row in pool[np.argsort(-pool[:, 2], kind="stable")]:
            if _at_an_empty_site(row[:2], float(row[2]), members, taken, pitch, check, image_wh):
                moved.append(row)
                taken = np.vstack([taken, row[None, :2]])
        if moved:
            kept = np.vstack([kept, np.array(moved)])
    return kept


def input_per_px(image_wh: tuple[int, int], lay: Layout) -> float:
    """Input px per original px under a layout (geometric mean of the two axes; Rust: ``input_per_px``)."""
    return math.sqrt(lay.scaled_w / image_wh[0] * lay.scaled_h / image_wh[1])
