"""Training batches: geometric sampling of crops with exact label mapping, and photometric
augmentation for sim-to-real transfer. Everything is done batch-wise in PyTorch on the CPU.

Geometry (per sample): either the *canonical* view (the image scaled as the "auto" fit does at inference,
``postprocess.fit_layout`` with its true marker pitch, then a random crop) or a *jittered* view (marker pitch at the input drawn log-uniformly in
``pitch_in_px``, independent x/y scale for anisotropic resizes, flips, a small rotation). Sampling is
bilinear with half-pixel centres (OpenCV INTER_LINEAR / torch ``align_corners=False``), i.e. the same
geometry as the inference resize. Where a crop reduces the image below ``AREA_BELOW_SCALE`` along
either axis, the source window is first reduced to the crop's scale by area averaging (OpenCV
INTER_AREA), as the inference preprocessing reduces such images: bilinear sampling alone would alias
fine texture (scan lines) into patterns the network never meets at inference. Labels are mapped with
the same affine transform in continuous coordinates (pixel i covers [i, i+1)); markers whose centre
falls outside the crop are dropped.

Photometry (per sample, a fraction of samples stays clean): colour gains, brightness/contrast, gamma,
low-frequency colour shading (the illumination of GelSight-type sensors), greyscale, polarity
inversion (light markers on a dark background), Gaussian blur, Gaussian noise, JPEG compression.
"""

from __future__ import annotations

import io
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from .postprocess import AREA_BELOW_SCALE, FILL_SAMPLE_STEP, FitConfig, fit_layout


@dataclass
class AugConfig:
    """Augmentation parameters (defaults used for the shipped model)."""

    crop: tuple[int, int] = (224, 224)  # (height, width) of a training crop, network input pixels
    input_size: tuple[int, int] = (416, 416)  # (height, width) of the canonical network input
    p_canonical: float = 0.5  # share of crops sampled exactly as at inference
    # Share of crops centred near a marker in contact (where the image has one; else anywhere): contact
    # markers are a small share of the training markers, and the tracker's contact and slip figures
    # rest on them.
    p_contact: float = 0.0
    # Share of crops laid across an image edge (one or both axes), overhanging it by up to half a pitch
    # plus one input multiple (32 px), the outside filled with the image's median colour: what the auto
    # layout's margin shows the network at inference, where markers cut by the border sit. At 0 the
    # crops stay inside the image and the outside of an image smaller than a crop repeats its border.
    p_edge: float = 0.0
    # How the canonical crops are scaled: "auto" (the auto layout, isotropic) or "stretch" (whole image to
    # input_size, the first contract's preprocessing, which the shipped model was trained with)
    canonical: str = "auto"
    pitch_in_px: tuple[float, float] = (9.0, 44.0)  # jittered marker pitch (x) at the input
    aspect: tuple[float, float] = (0.7, 1.5)  # y scale / x scale in jittered crops
    rotate_deg: float = 8.0
    flip: bool = True
    p_clean: float = 0.3  # share of samples without photometric augmentation
    p_gain: float = 0.6
    p_contrast: float = 0.7
    p_gamma: float = 0.5
    p_shading: float = 0.5
    p_grey: float = 0.15
    p_invert: float = 0.15
    p_blur: float = 0.4
    blur_sigma: tuple[float, float] = (0.3, 1.6)
    p_noise: float = 0.5
    noise_std: tuple[float, float] = (0.003, 0.04)
    p_jpeg: float = 0.2
    jpeg_quality: tuple[int, int] = (30, 95)


def _window_transform(cfg, h_img, w_img, pitch_px, rng, focus=None):
    """Affine map from crop continuous coords u to source continuous coords: p = c + A (u - crop/2).
    ``focus``: (n, 2) source points (e.g. markers in contact); with probability ``cfg.p_contact`` the
    crop is centred within a quarter crop of one of them (kept inside the image) instead of anywhere."""
    ch, cw = cfg.crop
    if rng.random() < cfg.p_canonical or not math.isfinite(pitch_px):
        if cfg.canonical == "stretch":
            sx = cfg.input_size[1] / w_img
            sy = cfg.input_size[0] / h_img
        else:  # as at inference ("auto" fit): isotropic, the scale fit_layout picks for this image and pitch
            lay = fit_layout(w_img, h_img, pitch_px, FitConfig(nominal_hw=cfg.input_size))
            sx = lay.scaled_w / w_img
            sy = lay.scaled_h / h_img
        rot = 0.0
        fx = fy = 1.0
    else:
        lo, hi = np.log(cfg.pitch_in_px[0]), np.log(cfg.pitch_in_px[1])
        sx = float(np.exp(rng.uniform(lo, hi))) / pitch_px
        sy = sx * float(np.exp(rng.uniform(np.log(cfg.aspect[0]), np.log(cfg.aspect[1]))))
        rot = math.radians(rng.uniform(-cfg.rotate_deg, cfg.rotate_deg))
        fx = -1.0 if (cfg.flip and rng.random() < 0.5) else 1.0
        fy = -1.0 if (cfg.flip and rng.random() < 0.5) else 1.0
    c, s = math.cos(rot), math.sin(rot)
    a = np.array([[c, -s], [s, c]]) @ np.diag([fx / sx, fy / sy])
    # Half extent of the window in source pixels (bounding box of the rotated crop).
    half = np.abs(a) @ np.array([cw / 2.0, ch / 2.0])
    cen = np.empty(2)
    near = None
    # No draw at p_contact = 0: the shipped recipes keep their random stream.
    if cfg.p_contact > 0 and focus is not None and len(focus) and rng.random() < cfg.p_contact:
        near = np.asarray(focus[rng.integers(len(focus))], np.float64) + 0.5  # continuous coords
        near = near + rng.uniform(-0.25, 0.25, 2) * 2.0 * half
    for k, size in enumerate((w_img, h_img)):
        lo, hi = half[k], size - half[k]
        if hi <= lo:
            cen[k] = size / 2.0
        elif near is not None:
            cen[k] = min(max(near[k], lo), hi)
        else:
            cen[k] = rng.uniform(lo, hi)
    # No draw at p_edge = 0, as for p_contact.
    if cfg.p_edge > 0 and near is None and rng.random() < cfg.p_edge:
        _lay_across_edge(cen, half, (w_img, h_img), pitch_px, (cw, ch), rng)
    return a, cen


EDGE_MULTIPLE_PX = 32  # the auto layout rounds its input up to this multiple: the most margin beyond half a pitch


def _lay_across_edge(cen, half, size, pitch_px, crop, rng):
    """Moves the crop centre ``cen`` (in place) so that the crop overhangs one edge of the image along
    one axis or both: by up to half a pitch plus ``EDGE_MULTIPLE_PX`` input px (the auto layout's
    margin), drawn uniformly; an axis where the crop spans the image stays centred."""
    axes = [k for k in (0, 1) if size[k] > 2 * half[k]]
    if not axes:
        return
    chosen = [k for k in axes if rng.random() < 0.5] or [axes[rng.integers(len(axes))]]
    pitch = pitch_px if math.isfinite(pitch_px) else 0.0
    for k in chosen:
        src_per_crop_px = 2.0 * half[k] / crop[k]
        overhang = rng.uniform(0.0, 0.5 * pitch + EDGE_MULTIPLE_PX * src_per_crop_px)
        cen[k] = half[k] - overhang if rng.random() < 0.5 else size[k] - half[k] + overhang


def _area_reduced(sub: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The source window ``sub`` (H, W, C uint8) reduced by area averaging to the scale of the crop
    whose affine map (crop to source) is ``a``, where that scale lies below ``AREA_BELOW_SCALE`` along
    either axis; else ``sub`` itself. The reduced window spans the same extent, so the normalised
    coordinates that ``grid_sample`` reads it by, and with them the labels, are unchanged."""
    scale = 1.0 / np.maximum(np.hypot(a[:, 0], a[:, 1]), 1e-12)  # crop px per source px, along x and y
    if scale.min() >= AREA_BELOW_SCALE:
        return sub
    hs, ws = sub.shape[:2]
    size = (max(1, min(ws, round(ws * scale[0]))), max(1, min(hs, round(hs * scale[1]))))
    out = cv2.resize(np.ascontiguousarray(sub), size, interpolation=cv2.INTER_AREA)
    return out.reshape(size[1], size[0], -1)


def sample_crops(images, points, pitches, idx, cfg: AugConfig, rng: np.random.Generator, focus=None,
                 ignore=None, ignore_out: list | None = None):
    """Cut one crop per index. Returns a float tensor (B, 3, ch, cw) in [0, 1] and a list of (n, 2)
    float32 label arrays in crop continuous coordinates. ``focus``: per image, the (n, 2) points a
    ``cfg.p_contact`` share of crops is centred near (None: none). ``ignore``: per image, a bool
    (H, W) mask of regions neither marker nor background (or None); each crop's mask, warped with the
    crop's own transform (nearest pixel), is appended to ``ignore_out`` as a bool (ch, cw) tensor.
    The masks draw no random numbers: the crops are the same with and without them."""
    ch, cw = cfg.crop
    out = torch.empty(len(idx), 3, ch, cw)
    labels = []
    for b, i in enumerate(idx):
        img = images[i]
        h_img, w_img = img.shape[:2]
        a, cen = _window_transform(cfg, h_img, w_img, pitches[i], rng, None if focus is None else focus[i])
        half = np.abs(a) @ np.array([cw / 2.0, ch / 2.0])
        # Sub-window of the source that covers the crop (+2 px margin for bilinear taps).
        x0 = int(max(0, math.floor(cen[0] - half[0]) - 2))
        y0 = int(max(0, math.floor(cen[1] - half[1]) - 2))
        x1 = int(min(w_img, math.ceil(cen[0] + half[0]) + 2))
        y1 = int(min(h_img, math.ceil(cen[1] + half[1]) + 2))
        hs, ws = y1 - y0, x1 - x0
        window = _area_reduced(img[y0:y1, x0:x1], a)
        sub = torch.from_numpy(np.array(window)).permute(2, 0, 1).float() / 255.0
        # Normalised coords of the sub-window: xn = 2 * (p - x0) / ws - 1, u_n in [-1, 1] over the crop.
        theta = torch.tensor(
            [
                [2.0 / ws * a[0, 0] * cw / 2, 2.0 / ws * a[0, 1] * ch / 2, 2.0 * (cen[0] - x0) / ws - 1.0],
                [2.0 / hs * a[1, 0] * cw / 2, 2.0 / hs * a[1, 1] * ch / 2, 2.0 * (cen[1] - y0) / hs - 1.0],
            ],
            dtype=torch.float32,
        )
        grid = F.affine_grid(theta[None], [1, 3, ch, cw], align_corners=False)
        out[b] = F.grid_sample(sub[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
        # Only a crop whose bounding box leaves the image can have an outside.
        if cfg.p_edge > 0 and (np.any(cen - half < 0) or np.any(cen + half > (w_img, h_img))):
            _fill_outside(out[b], grid[0], (x0, y0, ws, hs), (w_img, h_img), img)
        if ignore_out is not None:
            mask = None if ignore is None else ignore[i]
            if mask is None:
                ignore_out.append(torch.zeros(ch, cw, dtype=torch.bool))
            else:
                msub = torch.from_numpy(np.ascontiguousarray(mask[y0:y1, x0:x1])).float()[None, None]
                warped = F.grid_sample(msub, grid, mode="nearest", padding_mode="border", align_corners=False)
                ignore_out.append(warped[0, 0] > 0.5)
        pts = np.asarray(points[i], dtype=np.float64).reshape(-1, 2) + 0.5  # continuous source coords
        u = (pts - cen) @ np.linalg.inv(a).T + np.array([cw / 2.0, ch / 2.0])
        keep = (u[:, 0] >= 0) & (u[:, 0] < cw) & (u[:, 1] >= 0) & (u[:, 1] < ch)
        labels.append(u[keep].astype(np.float32))
    return out, labels


def _fill_outside(crop: torch.Tensor, grid: torch.Tensor, sub: tuple, size: tuple, img: np.ndarray) -> None:
    """Sets the pixels of ``crop`` (3, ch, cw) whose source point (``grid``, normalised coordinates of the
    sub-window ``sub`` = (x0, y0, width, height)) lies outside the ``size`` = (w, h) image to the image's
    median colour, sampled as the inference margin's (every 4th pixel of every 4th row, lower median)."""
    x0, y0, ws, hs = sub
    sx = x0 + (grid[..., 0] + 1.0) * (ws / 2.0)
    sy = y0 + (grid[..., 1] + 1.0) * (hs / 2.0)
    outside = (sx < 0) | (sx > size[0]) | (sy < 0) | (sy > size[1])
    if not bool(outside.any()):
        return
    sample = torch.from_numpy(np.ascontiguousarray(img[::FILL_SAMPLE_STEP, ::FILL_SAMPLE_STEP])).reshape(-1, img.shape[2])
    fill = sample.float().median(dim=0).values / 255.0
    crop[:, outside] = fill[:, None]


def _gaussian_blur(x: torch.Tensor, sigmas: np.ndarray) -> torch.Tensor:
    """Per-sample separable Gaussian blur (grouped convolution)."""
    b, c, h, w = x.shape
    r = int(math.ceil(2.5 * max(float(sigmas.max()), 0.4)))
    t = torch.arange(-r, r + 1, dtype=torch.float32, device=x.device)
    s = torch.from_numpy(np.maximum(sigmas, 1e-3)).float().to(x.device).view(b, 1)
    k = torch.exp(-0.5 * (t[None] / s) ** 2)
    k = k / k.sum(1, keepdim=True)
    k = k.repeat_interleave(c, dim=0)  # (b*c, 2r+1)
    y = x.reshape(1, b * c, h, w)
    y = F.pad(y, (r, r, r, r), mode="replicate")
    y = F.conv2d(y, k.view(b * c, 1, 1, -1), groups=b * c)
    y = F.conv2d(y, k.view(b * c, 1, -1, 1), groups=b * c)
    return y.view(b, c, h, w)


def _jpeg(img: torch.Tensor, quality: int) -> torch.Tensor:
    """A JPEG round trip of one (3, H, W) crop in [0, 1] through libjpeg (PIL), on the crop's device."""
    arr = (img.clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    with Image.open(buf) as im:
        back = np.asarray(im.convert("RGB"))
    return torch.from_numpy(back.copy()).permute(2, 0, 1).to(img.device).float() / 255.0


_JPEG_POOL: tuple[int, ThreadPoolExecutor] | None = None


def _jpeg_pool() -> ThreadPoolExecutor:
    """This process's JPEG threads. A forked batch maker inherits its parent's pool without the
    threads, so the pool is keyed by the process id."""
    global _JPEG_POOL
    if _JPEG_POOL is None or _JPEG_POOL[0] != os.getpid():
        _JPEG_POOL = (os.getpid(), ThreadPoolExecutor(max_workers=4, thread_name_prefix="jpeg"))
    return _JPEG_POOL[1]


def photometric(x: torch.Tensor, cfg: AugConfig, rng: np.random.Generator) -> torch.Tensor:
    """Apply the photometric augmentations to a (B, 3, H, W) batch in [0, 1] (each op only on the
    samples drawn for it), on the batch's device: the parameters come from ``rng`` wherever it runs."""
    b, _, h, w = x.shape
    dev = x.device
    aug = rng.random(b) >= cfg.p_clean

    def pick(p):
        return torch.from_numpy(np.nonzero(aug & (rng.random(b) < p))[0]).to(dev)

    def u(lo, hi, n, c=1):
        return torch.from_numpy(rng.uniform(lo, hi, (n, c, 1, 1))).float().to(dev)

    i = pick(cfg.p_gain)
    if len(i):
        x[i] = x[i] * u(0.6, 1.4, len(i), 3)
    i = pick(cfg.p_contrast)
    if len(i):
        xi = x[i]
        mean = xi.mean(dim=(1, 2, 3), keepdim=True)
        x[i] = (xi - mean) * u(0.5, 1.5, len(i)) + mean + u(-0.2, 0.2, len(i))
    i = pick(cfg.p_shading)
    if len(i):
        field = torch.from_numpy(rng.normal(0.0, 1.0, (len(i), 3, 3, 3))).float().to(dev)
        field = F.interpolate(field, size=(h, w), mode="bilinear", align_corners=True)
        x[i] = x[i] + u(0.03, 0.25, len(i)) * field
    x.clamp_(0, 1)
    i = pick(cfg.p_gamma)
    if len(i):
        gam = torch.from_numpy(np.exp(rng.uniform(np.log(0.6), np.log(1.6), (len(i), 1, 1, 1)))).float().to(dev)
        x[i] = x[i].clamp_min(1e-4) ** gam
    i = pick(cfg.p_grey)
    if len(i):
        x[i] = x[i].mean(1, keepdim=True).expand(-1, 3, -1, -1)
    i = pick(cfg.p_invert)
    if len(i):
        x[i] = 1.0 - x[i]
    i = pick(cfg.p_blur)
    if len(i):
        x[i] = _gaussian_blur(x[i], rng.uniform(*cfg.blur_sigma, len(i)))
    i = pick(cfg.p_noise)
    if len(i):
        x[i] = x[i] + torch.randn(len(i), 3, h, w, device=dev) * u(*cfg.noise_std, len(i))
    x.clamp_(0, 1)
    chosen = pick(cfg.p_jpeg).tolist()
    qualities = [rng.integers(cfg.jpeg_quality[0], cfg.jpeg_quality[1] + 1) for _ in chosen]
    if chosen:
        # libjpeg releases the GIL: a few threads keep a trainer augmenting on its GPU from waiting here.
        x[chosen] = torch.stack(list(_jpeg_pool().map(_jpeg, x[chosen].cpu(), qualities))).to(dev)
    # Real images are 8-bit: quantise like the inference input.
    return torch.round(x * 255.0) / 255.0


def make_batch(images, points, pitches, batch: int, cfg: AugConfig, rng: np.random.Generator, focus=None):
    """A training batch: (B, 3, ch, cw) float tensor and per-sample label arrays (input pixels);
    ``focus`` as in ``sample_crops``."""
    idx = rng.integers(0, len(images), batch)
    x, labels = sample_crops(images, points, pitches, idx, cfg, rng, focus)
    return photometric(x, cfg, rng), labels


def make_crops(images, points, pitches, batch: int, cfg: AugConfig, rng: np.random.Generator, focus=None):
    """The geometric half of ``make_batch``: (B, 3, ch, cw) uint8 crops, quantised as an 8-bit resize
    at inference is, and their labels. A trainer whose batch workers are the bottleneck makes these
    there and applies ``photometric`` on its GPU (``--augment-on device``): the photometric half is
    one half to two thirds of a crop's CPU time."""
    idx = rng.integers(0, len(images), batch)
    x, labels = sample_crops(images, points, pitches, idx, cfg, rng, focus)
    return torch.round(x * 255.0).to(torch.uint8), labels


def make_crops_with_ignore(images, points, pitches, batch: int, cfg: AugConfig, rng: np.random.Generator,
                           focus=None, ignore=None):
    """``make_crops`` plus each crop's ignore mask, as ``make_batch_with_ignore``."""
    idx = rng.integers(0, len(images), batch)
    masks: list = []
    x, labels = sample_crops(images, points, pitches, idx, cfg, rng, focus, ignore, masks)
    return torch.round(x * 255.0).to(torch.uint8), labels, torch.stack(masks)


def make_batch_with_ignore(images, points, pitches, batch: int, cfg: AugConfig, rng: np.random.Generator,
                           focus=None, ignore=None):
    """``make_batch`` plus each crop's ignore mask, a bool (B, ch, cw) tensor (see ``sample_crops``);
    the same crops and augmentations as ``make_batch`` with the same random stream."""
    idx = rng.integers(0, len(images), batch)
    masks: list = []
    x, labels = sample_crops(images, points, pitches, idx, cfg, rng, focus, ignore, masks)
    return photometric(x, cfg, rng), labels, torch.stack(masks)
