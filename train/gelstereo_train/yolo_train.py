"""Train the YOLOv3 baseline on a `gelstereo simulate` dataset (same split, sampler and augmentation as
Marknet: gelstereo_train.augment).

    python -m gelstereo_train.yolo_train --data ROOT --out runs/yolo.pt --minutes 40 --threads 1

Boxes. The simulator labels marker centres only; a YOLO box needs a size. A marker is a printed dot of
diameter ``dot_diameter_mm`` on a lattice of pitch ``pitch_mm`` (the sensor description the simulator
writes into each experiment's meta.json; the random sensor variants differ), so its
apparent diameter is ``diameter_frac = dot_diameter_mm / pitch_mm`` times the LOCAL lattice spacing in
the image, measured per marker and per axis: box width = diameter_frac x the distance to its nearest
horizontal neighbour (|dx| >= |dy|), height = diameter_frac x the distance to its nearest vertical one
(the other axis' value when one is missing). This follows perspective, the anisotropic resize to the
network input and the local compression/stretch of the gel in contact. It is computed on the label
points after the crop's affine map, so crops and jittered scales get consistent boxes.

Anchors: k-means (1 - IoU) on the boxes of the training images as the network sees them at inference
(the whole image resized to the input size), k = heads x anchors per head, rounded to 0.01 px, sorted
by area and given to the heads in ascending stride (YOLOv3's rule).

Targets and loss (YOLOv3): each ground-truth box is assigned to ONE anchor, the one (over all heads) of
best shape IoU, in the cell that contains its centre. The modification for markers: all markers have
nearly the same shape, so two markers in one cell would want the same anchor and YOLOv3 would drop one;
here the second takes the next-best anchor still free in its cell at any head (``fallbacks``); only when
every anchor of every head is taken is a marker left unassigned (``collisions``). Loss = box_scale x [BCE(sigmoid(tx), x - gx) + BCE(., y - gy)
+ (tw - log(w / aw))^2 + (th - log(h / ah))^2] over assigned anchors, + BCE objectness (1 for assigned,
0 for the others except those whose decoded box overlaps a ground-truth box by IoU > ``ignore_iou``,
0.5), with box_scale = 2 - w h / (crop area); everything summed and divided by the number of
assigned anchors (as the Marknet loss).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .augment import AugConfig, photometric, sample_crops
from .data import dataset_tag, list_samples, read_dataset_info
from .model import count_flops
from .train_marknet import add_training_args, load_images, training_main
from .yolo_model import OUTPUTS_PER_ANCHOR, YoloV3, decode_head, kmeans_anchors, mean_best_iou, wh_iou

DEFAULT_DIAMETER_FRAC = 0.5  # calib/reference-sensor.json: dot_diameter_mm 0.4 / pitch_mm 0.8


def _find_grid(obj):
    """The first dict holding both 'dot_diameter_mm' and 'pitch_mm' in a nested JSON value."""
    if isinstance(obj, dict):
        if "dot_diameter_mm" in obj and "pitch_mm" in obj:
            return obj
        for v in obj.values():
            g = _find_grid(v)
            if g is not None:
                return g
    elif isinstance(obj, list):
        for v in obj:
            g = _find_grid(v)
            if g is not None:
                return g
    return None


def _fraction_from(info) -> float | None:
    g = _find_grid(info)
    if g is None:
        return None
    try:
        frac = float(g["dot_diameter_mm"]) / float(g["pitch_mm"])
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return frac if 0.0 < frac < 1.0 else None


def diameter_fraction(exp_dir: Path | str) -> tuple[float, str]:
    """dot diameter / pitch of the sensor an experiment was rendered with, and where it was read
    from: EXP/meta.json (the simulator writes the sensor description there; variants differ), else
    ROOT/dataset.json, else the reference sensor's 0.5."""
    exp_dir = Path(exp_dir)
    meta = exp_dir / "meta.json"
    if meta.exists():
        try:
            frac = _fraction_from(json.loads(meta.read_text()))
        except (OSError, ValueError):
            frac = None
        if frac is not None:
            return frac, str(meta)
    root = exp_dir.parent.parent
    try:
        frac = _fraction_from(read_dataset_info(root))
    except ValueError:
        frac = None
    if frac is not None:
        return frac, str(root / "dataset.json")
    return DEFAULT_DIAMETER_FRAC, "default (reference sensor 0.4 mm / 0.8 mm)"


def marker_boxes(points: np.ndarray, diameter_frac: float, fallback_px: float = float("nan")) -> np.ndarray:
    """Box (w, h) per marker from the local lattice spacing (module docs). (n, 2) points -> (n, 2).
    A marker without any neighbour gets ``diameter_frac * fallback_px`` (NaN when no fallback)."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    n = len(p)
    out = np.full((n, 2), np.nan)
    if n == 0:
        return out
    if n > 1:
        q = p.astype(np.float32)
        adx = np.abs(q[None, :, 0] - q[:, None, 0])
        ady = np.abs(q[None, :, 1] - q[:, None, 1])
        d2 = adx * adx + ady * ady
        np.fill_diagonal(d2, np.inf)
        horiz = adx >= ady
        sx = np.sqrt(np.where(horiz, d2, np.inf).min(1).astype(np.float64))
        sy = np.sqrt(np.where(horiz, np.inf, d2).min(1).astype(np.float64))
        sx = np.where(np.isfinite(sx), sx, sy)
        sy = np.where(np.isfinite(sy), sy, sx)
        out[:, 0], out[:, 1] = sx, sy
    bad = ~np.isfinite(out).all(1)
    out[bad] = fallback_px
    return out * diameter_frac


def canonical_boxes(points_list, image_sizes, input_hw, diameter_frac, max_boxes: int = 200_000,
                    seed: int = 0) -> np.ndarray:
    """Training boxes (w, h) in network input pixels of whole images resized to ``input_hw``;
    ``diameter_frac`` is one value or one per image."""
    rng = np.random.default_rng(seed)
    fracs = np.broadcast_to(np.asarray(diameter_frac, np.float64), (len(points_list),))
    out = []
    for pts, (h_img, w_img), frac in zip(points_list, image_sizes, fracs):
        s = np.array([input_hw[1] / w_img, input_hw[0] / h_img])
        out.append(marker_boxes((np.asarray(pts, np.float64) + 0.5) * s, frac))
    wh = np.concatenate(out) if out else np.zeros((0, 2))
    wh = wh[np.isfinite(wh).all(1)]
    if len(wh) > max_boxes:
        wh = wh[rng.choice(len(wh), max_boxes, replace=False)]
    return wh


@dataclasses.dataclass
class Targets:
    """YOLOv3 targets of a batch, per head: (B, Gy, Gx, A) masks and (B, Gy, Gx, A, 4) (tx, ty, tw, th)
    regression targets, the box scale, and the ground-truth boxes per image (x, y, w, h)."""

    mask: list
    txy: list
    twh: list
    scale: list
    gt: list
    assigned: int
    collisions: int
    fallbacks: int


def build_targets(labels, boxes, shapes, strides, anchors: np.ndarray, crop_area: float) -> Targets:
    """labels: per image (n, 2) centres (input px); boxes: per image (n, 2) sizes; shapes: per head
    (Gy, Gx); anchors (heads, A, 2)."""
    b = len(labels)
    heads, a_per, _ = anchors.shape
    flat_anchors = anchors.reshape(-1, 2)
    mask = [np.zeros((b, gy, gx, a_per), bool) for gy, gx in shapes]
    txy = [np.zeros((b, gy, gx, a_per, 2), np.float32) for gy, gx in shapes]
    twh = [np.zeros((b, gy, gx, a_per, 2), np.float32) for gy, gx in shapes]
    scale = [np.zeros((b, gy, gx, a_per), np.float32) for gy, gx in shapes]
    gts = []
    assigned = collisions = fallbacks = 0
    for i, (pts, wh) in enumerate(zip(labels, boxes)):
        pts = np.asarray(pts, np.float64).reshape(-1, 2)
        wh = np.asarray(wh, np.float64).reshape(-1, 2)
        ok = np.isfinite(wh).all(1) & (wh > 0).all(1)
        pts, wh = pts[ok], wh[ok]
        gts.append(np.concatenate([pts, wh], 1).astype(np.float32))
        if len(pts) == 0:
            continue
        ranked = np.argsort(-wh_iou(wh, flat_anchors), axis=1, kind="stable")
        for k in range(len(pts)):
            for rank, flat in enumerate(ranked[k]):
                h, a = divmod(int(flat), a_per)
                s = strides[h]
                gy_n, gx_n = shapes[h]
                cx = min(int(math.floor(pts[k, 0] / s)), gx_n - 1)
                cy = min(int(math.floor(pts[k, 1] / s)), gy_n - 1)
                if cx >= 0 and cy >= 0 and not mask[h][i, cy, cx, a]:
                    break
            else:
                collisions += 1
                continue
            if rank > 0:
                fallbacks += 1
            mask[h][i, cy, cx, a] = True
            txy[h][i, cy, cx, a] = (pts[k, 0] / s - cx, pts[k, 1] / s - cy)
            twh[h][i, cy, cx, a] = np.log(wh[k] / anchors[h, a])
            scale[h][i, cy, cx, a] = 2.0 - wh[k, 0] * wh[k, 1] / crop_area
            assigned += 1
    t = lambda arrs: [torch.from_numpy(x) for x in arrs]  # noqa: E731
    return Targets(t(mask), t(txy), t(twh), t(scale), gts, assigned, collisions, fallbacks)


def box_iou_xywh(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU of (n, 4) and (k, 4) centre-size boxes -> (n, k)."""
    a1, a2 = a[:, None, :2] - a[:, None, 2:] / 2, a[:, None, :2] + a[:, None, 2:] / 2
    b1, b2 = b[None, :, :2] - b[None, :, 2:] / 2, b[None, :, :2] + b[None, :, 2:] / 2
    inter = (torch.minimum(a2, b2) - torch.maximum(a1, b1)).clamp_min(0).prod(-1)
    area = a[:, None, 2:].prod(-1) + b[None, :, 2:].prod(-1) - inter
    return inter / area.clamp_min(1e-9)


def ignore_mask(dec: torch.Tensor, gt: list, stride: int, ignore_iou: float) -> torch.Tensor:
    """YOLOv3's ignore rule for one head: (B, Gy, Gx, A) True where the decoded box (B, Gy, Gx, A, >=4)
    overlaps some ground-truth box by IoU > ignore_iou. A predicted centre lies inside its own cell,
    so only the 3 x 3 cells around each ground-truth centre are tested (exact for boxes smaller than
    about two strides, i.e. every marker box)."""
    b, gy, gx, a = dec.shape[:4]
    mask = torch.zeros((b, gy, gx, a), dtype=torch.bool)
    rows = [np.c_[np.full(len(g), i), g] for i, g in enumerate(gt) if len(g)]
    if not rows:
        return mask
    g = torch.from_numpy(np.concatenate(rows).astype(np.float32))  # (n, 5): image, x, y, w, h
    img = g[:, 0].long()
    cx = torch.floor(g[:, 1] / stride).long()
    cy = torch.floor(g[:, 2] / stride).long()
    off = torch.tensor([-1, 0, 1])
    nx = (cx[:, None, None] + off[None, None, :]).expand(-1, 3, 3)
    ny = (cy[:, None, None] + off[None, :, None]).expand(-1, 3, 3)
    inside = (nx >= 0) & (nx < gx) & (ny >= 0) & (ny < gy)
    k = inside.nonzero(as_tuple=True)  # (gt index, dy, dx) triples
    gi, ix, iy = k[0], nx[k], ny[k]
    pred = dec[img[gi], iy, ix, :, :4]  # (m, A, 4)
    box = g[gi, 1:5]
    p1, p2 = pred[..., :2] - pred[..., 2:4] / 2, pred[..., :2] + pred[..., 2:4] / 2
    b1, b2 = (box[:, :2] - box[:, 2:] / 2)[:, None], (box[:, :2] + box[:, 2:] / 2)[:, None]
    inter = (torch.minimum(p2, b2) - torch.maximum(p1, b1)).clamp_min(0).prod(-1)
    union = pred[..., 2:4].prod(-1) + box[:, None, 2:].prod(-1) - inter
    hit = inter / union.clamp_min(1e-9) > ignore_iou  # (m, A)
    hits = torch.zeros((b, gy, gx, a), dtype=torch.int32)
    hits.index_put_((img[gi], iy, ix), hit.int(), accumulate=True)
    return hits > 0


def yolo_loss(maps, tg: Targets, strides, anchors: torch.Tensor, ignore_iou: float = 0.5):
    """YOLOv3 loss (module docs). Returns (total, objectness part, box part, mean centre error, input px)."""
    npos = max(tg.assigned, 1)
    obj_sum = maps[0].new_zeros(())
    box_sum = maps[0].new_zeros(())
    centre_err = []
    for h, raw in enumerate(maps):
        s = strides[h]
        m = tg.mask[h]
        with torch.no_grad():
            ignore = ignore_mask(decode_head(raw.detach().float(), s, anchors[h]), tg.gt, s, ignore_iou)
        neg = ~m & ~ignore
        obj_logit = raw[..., 4]
        pos_l, neg_l = obj_logit[m], obj_logit[neg]
        obj_sum = obj_sum + F.binary_cross_entropy_with_logits(pos_l, torch.ones_like(pos_l), reduction="sum")
        obj_sum = obj_sum + F.binary_cross_entropy_with_logits(neg_l, torch.zeros_like(neg_l), reduction="sum")
        if m.any():
            p = raw[m]
            sc = tg.scale[h][m]
            bxy = F.binary_cross_entropy_with_logits(p[:, :2], tg.txy[h][m], reduction="none").sum(1)
            bwh = ((p[:, 2:4] - tg.twh[h][m]) ** 2).sum(1)
            box_sum = box_sum + (sc * (bxy + bwh)).sum()
            with torch.no_grad():
                centre_err.append(((torch.sigmoid(p[:, :2]) - tg.txy[h][m]) * s).norm(dim=1))
    total = (obj_sum + box_sum) / npos
    ce = torch.cat(centre_err).mean() if centre_err else torch.zeros(())
    return total, obj_sum / npos, box_sum / npos, ce


def save_checkpoint(path: Path, model: YoloV3, meta: dict) -> None:
    """Weights + constructor arguments (anchors, strides, width) + metadata."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".part")
    torch.save(
        {
            "model": model.state_dict(),
            "arch": {"anchors": model.anchors.numpy().tolist(), "strides": list(model.strides), "width": model.width},
            "meta": meta,
        },
        tmp,
    )
    tmp.replace(path)


def load_checkpoint(path: Path | str) -> tuple[YoloV3, dict]:
    """Rebuild the detector from a checkpoint; returns (model in eval mode, meta)."""
    ck = torch.load(path, map_location="cpu", weights_only=False)
    model = YoloV3(**ck["arch"])
    model.load_state_dict(ck["model"])
    return model.eval(), ck["meta"]


def fit_anchors(points, images, input_hw, diameter_frac, heads: int, per_head: int, seed: int, log=print):
    """k-means anchors from the canonical training boxes; (heads, per_head, 2) and the fit report."""
    wh = canonical_boxes(points, [im.shape[:2] for im in images], input_hw, diameter_frac, seed=seed)
    anchors = np.round(kmeans_anchors(wh, heads * per_head, seed=seed), 2)  # exact in the metadata text
    fit = mean_best_iou(wh, anchors)
    log(f"k-means anchors (input px, w x h) from {len(wh)} boxes: "
        + ", ".join(f"{w:.2f}x{h:.2f}" for w, h in anchors) + f"; mean best IoU {fit:.3f}; "
        f"box w median {np.median(wh[:, 0]):.2f} h median {np.median(wh[:, 1]):.2f}")
    return anchors.reshape(heads, per_head, 2), {"boxes": int(len(wh)), "mean_best_iou": round(fit, 4)}


def train(args, log=print) -> Path:
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    samples = list_samples(args.data, "train", frame_step=args.frame_step)
    if not samples:
        raise SystemExit(f"{args.data}/train: no images found")
    samples, images, points, pitches = load_images(samples, args.max_images, rng, log, max_gb=args.max_gb)
    log(f"train images {len(images)}, markers {sum(len(p) for p in points)}, "
        f"median pitch {np.nanmedian(pitches):.2f} px")
    cache: dict = {}
    for smp in samples:
        exp_dir = smp.image_path.parent.parent
        if exp_dir not in cache:
            cache[exp_dir] = diameter_fraction(exp_dir)
    fracs = np.array([cache[smp.image_path.parent.parent][0] for smp in samples])
    if args.diameter_frac is not None:
        fracs[:] = args.diameter_frac
    sources = sorted({src for _, src in cache.values()})
    log(f"marker diameter = dot/pitch x local spacing; dot/pitch per experiment: min {fracs.min():.3f} median "
        f"{np.median(fracs):.3f} max {fracs.max():.3f} ({len(cache)} experiments; read from "
        f"{sources[0] if len(sources) == 1 else str(len(sources)) + ' files'})")
    strides = tuple(int(s) for s in args.strides.split(","))
    input_hw = (args.input_size, args.input_size)
    anchors, fit = fit_anchors(points, images, input_hw, fracs, len(strides), args.anchors_per_head, args.seed, log)
    model = YoloV3(anchors, strides=strides, width=args.width)
    log(f"YOLOv3 strides {strides} anchors/head {args.anchors_per_head} width {args.width}: "
        f"{sum(p.numel() for p in model.parameters())} params, {count_flops(model):.3f} GFLOP at 416x416")
    model = model.to(memory_format=torch.channels_last)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    cfg = AugConfig(crop=(args.crop, args.crop), input_size=input_hw)
    budget_s = args.minutes * 60.0 if args.minutes else None
    warm = 200
    anchors_t = model.anchors.detach().clone()
    t0 = time.time()
    step, hist, last_log = 0, [], t0
    model.train()
    while True:
        elapsed = time.time() - t0
        if args.steps is not None:
            frac_done = step / args.steps
            if step >= args.steps:
                break
        else:
            frac_done = elapsed / budget_s
            if frac_done >= 1.0:
                break
        lr = args.lr * min(1.0, (step + 1) / warm) * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(frac_done, 1.0))))
        for g in opt.param_groups:
            g["lr"] = lr
        # augment.make_batch, keeping the image indices (each sensor has its own dot/pitch ratio).
        idx = rng.integers(0, len(images), args.batch)
        x, labels = sample_crops(images, points, pitches, idx, cfg, rng)
        x = photometric(x, cfg, rng)
        boxes = [marker_boxes(lab, fracs[i]) for lab, i in zip(labels, idx)]
        x = x.contiguous(memory_format=torch.channels_last)
        maps = model.head_maps(x)
        tg = build_targets(labels, boxes, [m.shape[1:3] for m in maps], strides, anchors_t.numpy(),
                           float(args.crop * args.crop))
        loss, lo, lb, ce = yolo_loss(maps, tg, strides, anchors_t, args.ignore_iou)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        hist.append((loss.item(), lo.item(), lb.item(), ce.item(), tg.collisions, tg.assigned, tg.fallbacks))
        step += 1
        now = time.time()
        if now - last_log > args.log_every_s or step == 1:
            h = np.asarray(hist[-50:])
            log(f"step {step} t {now - t0:.0f}s lr {lr:.2e} loss {h[:, 0].mean():.4f} obj {h[:, 1].mean():.4f} "
                f"box {h[:, 2].mean():.4f} centre_err {h[:, 3].mean():.3f}px fallbacks {int(h[:, 6].sum())} "
                f"collisions {int(h[:, 4].sum())}/{int(h[:, 4].sum() + h[:, 5].sum())} "
                f"({step * args.batch / (now - t0):.0f} img/s)")
            last_log = now
    train_s = time.time() - t0
    model = model.to(memory_format=torch.contiguous_format)
    meta = {
        "dataset": dataset_tag(args.data, len(images)),
        "data_root": str(args.data),
        "input_height": args.input_size,
        "input_width": args.input_size,
        "trained": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "train_seconds": round(train_s, 1),
        "steps": step,
        "threads": args.threads,
        "diameter_frac": {"min": float(fracs.min()), "median": float(np.median(fracs)), "max": float(fracs.max())},
        "diameter_frac_source": sources,
        "anchor_fit": fit,
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "aug": dataclasses.asdict(cfg),
        "final_loss": float(np.mean([h[0] for h in hist[-100:]])) if hist else None,
    }
    save_checkpoint(Path(args.out), model, meta)
    log(f"saved {args.out} after {step} steps, {train_s:.0f} s")
    return Path(args.out)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_args(p, minutes=40.0, threads=1)
    p.add_argument("--strides", default="8,16", help="head strides, ascending (from 8, 16, 32)")
    p.add_argument("--anchors-per-head", type=int, default=3)
    p.add_argument("--ignore-iou", type=float, default=0.5, help="YOLOv3 ignore threshold for negatives")
    p.add_argument("--diameter-frac", type=float, default=None,
                   help="dot diameter / pitch (default: from the dataset's sensor description)")
    return p


def main(argv=None) -> int:
    return training_main(parser(), train, argv)


if __name__ == "__main__":
    sys.exit(main())
