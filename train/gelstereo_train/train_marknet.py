"""Train Marknet on a `gelstereo simulate` dataset.

    python -m gelstereo_train.train_marknet --data ROOT --out runs/marknet.pt --minutes 45

Training runs on random crops (default 208 x 208 network pixels) of the training images, sampled and
augmented by gelstereo_train.augment; Adam with a warm-up and cosine decay over the budget (minutes or
steps). The checkpoint holds the weights and every setting needed to rebuild and export the model.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from .augment import AugConfig, make_batch, make_batch_with_ignore, make_crops, make_crops_with_ignore, photometric
from .batches import add_device_args, batch_stream, describe, pick_device
from .data import dataset_tag, experiment_families, list_samples, median_nn_distance
from .loss import build_targets, distillation_loss, ignore_cells, marknet_loss
from .model import FUSE_KERNELS, STEMS, STRIDE_FOR_GRID_416, Marknet, count_flops
from .onnx_init import load_onnx_weights
from .qat import ActivationRounding


def decoded(samples, threads: int):
    """(sample, image) in the samples' order, decoded by `threads` threads (OpenCV's decoders release
    the GIL) a few chunks ahead of the consumer, so stopping early decodes little more."""
    chunk = 4 * max(threads, 1)
    with ThreadPoolExecutor(max_workers=max(threads, 1)) as pool:
        for start in range(0, len(samples), chunk):
            part = samples[start:start + chunk]
            yield from zip(part, pool.map(lambda s: s.load(), part))


def load_images(samples, max_images: int | None, rng: np.random.Generator, log=print, max_gb: float | None = None,
                threads: int = 1):
    """Decode a random subset of the samples into memory (at most max_images, at most max_gb of
    uint8 pixels): images, label points, per-image pitch."""
    order = rng.permutation(len(samples))
    if max_images is not None:
        order = order[:max_images]
    budget = None if max_gb is None else max_gb * 1e9
    kept, images, points, pitches = [], [], [], []
    total = 0
    t0 = time.time()
    for s, img in decoded([samples[k] for k in np.sort(order)], threads):
        if budget is not None and total + img.nbytes > budget:
            log(f"memory budget {max_gb} GB reached after {len(images)} images")
            break
        total += img.nbytes
        kept.append(s)
        if s.ignore_path is not None:
            s.ignore = s.load_ignore()
            if s.ignore.shape != img.shape[:2]:
                raise SystemExit(f"{s.ignore_path}: ignore mask is {s.ignore.shape[1]}x{s.ignore.shape[0]} px, "
                                 f"its image {s.image_path} is {img.shape[1]}x{img.shape[0]}")
        images.append(img)
        points.append(s.points_px.astype(np.float32))
        pitches.append(median_nn_distance(s.points_px))
        if len(images) % 500 == 0:
            log(f"loaded {len(images)}/{len(order)} images ({time.time() - t0:.0f} s, {total / 1e9:.2f} GB)")
    return kept, images, points, np.asarray(pitches, np.float64)


def save_checkpoint(path: Path, model: Marknet, meta: dict) -> None:
    """Weights + constructor arguments + metadata (dataset, input size, training record)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".part")
    torch.save(
        {
            "model": {k: v.cpu() for k, v in model.state_dict().items()},
            "arch": model.arch(),
            "meta": meta,
        },
        tmp,
    )
    tmp.replace(path)


def load_checkpoint(path: Path | str) -> tuple[Marknet, dict]:
    """Rebuild a Marknet from a checkpoint; returns (model in eval mode, meta)."""
    ck = torch.load(path, map_location="cpu", weights_only=False)
    model = Marknet(**ck["arch"])
    model.load_state_dict(ck["model"])
    return model.eval(), ck["meta"]


def average_checkpoints(paths: list[Path]) -> tuple[Marknet, dict]:
    """The element-wise mean of the weights of checkpoints of one architecture (a "soup": two
    fine-tunes from one start often land between their strengths). Integer buffers (BatchNorm's step
    counts) are the first checkpoint's. The meta names each source with its training record."""
    if len(paths) < 2:
        raise SystemExit("average_checkpoints: give at least two checkpoints")
    cks = []
    for path in paths:
        if not Path(path).is_file():
            raise SystemExit(f"{path}: no such checkpoint file")
        ck = torch.load(path, map_location="cpu", weights_only=False)
        if not (isinstance(ck, dict) and {"arch", "model", "meta"} <= ck.keys()):
            raise SystemExit(f"{path}: not a Marknet checkpoint of train_marknet (expected its arch, model "
                             "and meta)")
        cks.append(ck)
    arch = cks[0]["arch"]
    for path, ck in zip(paths[1:], cks[1:]):
        if ck["arch"] != arch:
            raise SystemExit(f"{path}: architecture {ck['arch']} differs from {paths[0]}'s {arch}; "
                             "only checkpoints of one architecture can be averaged")
    first = cks[0]["model"]
    mean = {k: (torch.stack([ck["model"][k] for ck in cks]).mean(dim=0) if v.is_floating_point() else v)
            for k, v in first.items()}
    model = Marknet(**arch)
    model.load_state_dict(mean)
    sources = [training_record(ck["meta"], p) for p, ck in zip(paths, cks)]
    # What export reads (input size, the crops' layout) is the first checkpoint's: same architecture.
    meta = {k: cks[0]["meta"][k] for k in ("input_height", "input_width", "aug") if k in cks[0]["meta"]}
    datasets = dict.fromkeys(str(ck["meta"].get("dataset")) for ck in cks)
    return model.eval(), meta | {"dataset": " + ".join(datasets), "average_of": sources,
                                 "trained": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}


def load_init(model: Marknet, path: Path) -> dict:
    """Copies a checkpoint's weights into `model`. The architecture must be the one asked for, or one
    that holds every weight of it with the same name and shape (an "s4" checkpoint warm-starts an
    "s4-bare" model: the residual block it lacks is left out). Returns the checkpoint's training record
    (steps, seconds, its own warm start, the weights left out) for this run's metadata."""
    if not path.is_file():
        raise SystemExit(f"--init {path}: no such checkpoint file")
    ck = torch.load(path, map_location="cpu", weights_only=False)
    want = model.arch()
    have = ck.get("arch") if isinstance(ck, dict) else None
    mine = model.state_dict()
    theirs = narrowed_kernels(ck.get("model", {}) if isinstance(ck, dict) else {}, mine)
    if have != want and any(k not in theirs or theirs[k].shape != v.shape for k, v in mine.items()):
        raise SystemExit(f"--init {path}: checkpoint architecture {have} differs from the one asked for {want} "
                         "and lacks some of its weights (give the same --grid, --candidates, --width, --stem and "
                         "--fuse-kernel)")
    left_out = sorted(k for k in theirs if k not in mine)
    model.load_state_dict({k: theirs[k] for k in mine})
    record = training_record(ck.get("meta", {}), path)
    return record | ({"left_out": left_out} if left_out else {})


def training_record(meta: dict, path: Path | str) -> dict:
    """What a checkpoint built on another records of it: when, how long and from what it was trained,
    and where it was read from."""
    return {k: meta.get(k) for k in ("trained", "steps", "train_seconds", "init")} | {"path": str(path)}


def narrowed_kernels(theirs: dict, mine: dict) -> dict:
    """`theirs` with each square convolution kernel that `mine` holds narrower (a 3x3 fusing
    convolution where the model has a 1x1) summed over its taps: the narrow kernel then answers a
    locally constant input as the wide one did, a warm start training refines."""
    out = dict(theirs)
    for k, v in theirs.items():
        m = mine.get(k)
        if (m is not None and v.dim() == 4 and m.dim() == 4 and v.shape[:2] == m.shape[:2]
                and m.shape[2:] == (1, 1) and v.shape[2] == v.shape[3] > 1):
            out[k] = v.sum(dim=(2, 3), keepdim=True)
    return out


def load_teacher(path: Path | None, student: Marknet, log=print) -> Marknet | None:
    """The Marknet checkpoint whose outputs the student learns besides the labels (`--teacher`), frozen
    in eval mode; it must share the student's head (stride, candidates)."""
    if path is None:
        return None
    if not Path(path).is_file():
        raise SystemExit(f"--teacher {path}: no such checkpoint file")
    teacher, _ = load_checkpoint(path)
    if (teacher.stride, teacher.candidates) != (student.stride, student.candidates):
        raise SystemExit(f"--teacher {path}: its head has stride {teacher.stride} and {teacher.candidates} candidates "
                         f"per cell, the student's {student.stride} and {student.candidates}")
    for p in teacher.parameters():
        p.requires_grad_(False)
    log(f"distilling from {path} ({sum(p.numel() for p in teacher.parameters())} params)")
    return teacher


def train(args, log=print) -> Path:
    if args.crop < 32 or args.crop % 32:
        # the batch makers lay out the targets for an output grid of crop / stride cells
        raise SystemExit(f"--crop {args.crop}: expected a positive multiple of 32 (network px)")
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    samples = list_samples(args.data, "train", frame_step=args.frame_step)
    if not samples:
        raise SystemExit(f"{args.data}/train: no images found")
    exclude = list(getattr(args, "exclude_family", None) or [])
    if exclude:
        before = len(samples)
        samples = [s for s in samples
                   if not set(exclude) & set(experiment_families(args.data, s.split, s.experiment))]
        log(f"held out families {exclude}: {before - len(samples)} of {before} images left out")
        if not samples:
            raise SystemExit(f"{args.data}/train: every image belongs to a held-out family {exclude}")
    samples, images, points, pitches = load_images(samples, args.max_images, rng, log, args.max_gb,
                                                   threads=max(args.threads, args.workers))
    n_markers = sum(len(p) for p in points)
    # Pseudo-labelled data (`gelstereo adapt`) marks uncertain regions: no negatives there.
    ignore = [getattr(s, "ignore", None) for s in samples]
    if all(m is None for m in ignore):
        ignore = None
    else:
        log(f"{sum(m is not None for m in ignore)} images carry ignore masks "
            f"({np.mean([m.mean() for m in ignore if m is not None]):.1%} of their pixels ignored)")
    log(f"train images {len(images)}, markers {n_markers}, median pitch {np.nanmedian(pitches):.2f} px")

    stride = STRIDE_FOR_GRID_416[args.grid]  # S is defined at 416x416; the stride is what the net has
    model = Marknet(stride=stride, candidates=args.candidates, width=args.width, stem=args.stem,
                    fuse_kernel=args.fuse_kernel)
    init, init_record = getattr(args, "init", None), None
    cfg = AugConfig(crop=(args.crop, args.crop), input_size=(args.input_size, args.input_size),
                    canonical=args.canonical, p_contact=args.p_contact,
                    p_edge=args.p_edge)
    contact = [s.points_px[s.in_contact] for s in samples]
    if init is not None and Path(init).suffix == ".onnx":
        calib = [make_batch(images, points, pitches, args.batch, cfg, rng, contact)[0] for _ in range(8)]
        init_record = load_onnx_weights(model, Path(init), calib)
        log(f"initialised from exported {init}; BatchNorm re-inflated on {len(calib)} batches, "
            f"max |torch - onnxruntime| {init_record['max_abs_diff_vs_onnx']:.2e}")
    elif init is not None:
        init_record = load_init(model, Path(init))
        log(f"initialised from {init} (warm start: fine-tunes those weights under this run's schedule)")
    log(f"Marknet stride {stride} m {args.candidates} width {args.width}: "
        f"{sum(p.numel() for p in model.parameters())} params, {count_flops(model):.3f} GFLOP at 416x416")
    device = pick_device(args.device)
    teacher = load_teacher(getattr(args, "teacher", None), model, log)
    torch.backends.cudnn.benchmark = device.type == "cuda"  # fixed crop shapes: pick the fastest kernels once
    log(f"training on {describe(device)}, batches made by "
        f"{f'{args.workers} worker processes' if args.workers else 'the training process'}")
    model = model.to(device, memory_format=torch.channels_last)
    if teacher is not None:
        teacher = teacher.to(device, memory_format=torch.channels_last)
    if getattr(args, "qat", False):
        rounding = ActivationRounding(model).to(device)
        log(f"quantization-aware: {len(rounding)} activations rounded to uint8 as the int8 build rounds them")
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    if cfg.p_contact > 0:
        log(f"{sum(len(c) > 0 for c in contact)} of {len(samples)} images show contact markers; "
            f"{cfg.p_contact:.0%} of crops are centred near one of them there")
    budget_s = args.minutes * 60.0 if args.minutes else None
    warm = 200
    t0 = time.time()
    step = 0
    hist, drops = [], []
    last_log = t0
    # Time spent waiting for the batch makers, in all and since the last log line: near 100 % the
    # batches are the limit, near 0 the training device (or this process's own work) is.
    waited, waited_at_log, step_at_log = 0.0, 0.0, 0
    last_save = t0
    on_device = getattr(args, "augment_on", "workers") == "device"
    if on_device:
        log(f"photometric augmentation on {describe(device)}, crops made by the batch makers")
    grid = (args.crop // stride, args.crop // stride)

    def make(r):
        # The targets are made with the crops, by the batch makers: the training process only feeds the device.
        if ignore is None:
            x, labels = (make_crops if on_device else make_batch)(images, points, pitches, args.batch, cfg, r, contact)
            rest = ()
        else:
            x, labels, masks = (make_crops_with_ignore if on_device else make_batch_with_ignore)(
                images, points, pitches, args.batch, cfg, r, contact, ignore)
            rest = (masks,)
        return (x, *build_targets(labels, *grid, stride, args.candidates), *rest)

    batches = batch_stream(make, rng, args.workers, args.seed, pin_memory=device.type == "cuda")
    model.train()
    while True:
        elapsed = time.time() - t0
        if args.steps is not None:
            frac = step / args.steps
            if step >= args.steps:
                break
        else:
            frac = elapsed / budget_s
            if frac >= 1.0:
                break
        lr = args.lr * min(1.0, (step + 1) / warm) * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0))))
        for g in opt.param_groups:
            g["lr"] = lr
        asked = time.time()
        x, tgt, mask, dropped, *crop_ignore = next(batches)
        waited += time.time() - asked
        cells = ignore_cells(crop_ignore[0].to(device), stride) if crop_ignore else None
        x = x.to(device, non_blocking=True)
        if on_device:  # uint8 crops: the photometric half here, from this process's stream
            x = photometric(x.float() / 255.0, cfg, rng)
        x = x.contiguous(memory_format=torch.channels_last)
        raw = model(x)
        tgt, mask = tgt.to(device, non_blocking=True), mask.to(device, non_blocking=True)
        loss, lc, lp, md = marknet_loss(raw, tgt, mask, stride, args.alpha, args.beta, cells)
        if teacher is not None:
            with torch.no_grad():
                teacher_raw = teacher(x)
            loss = loss + args.distill_weight * distillation_loss(raw, teacher_raw, stride)[0]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        # Kept on the device, read at each log: a read per step would make the host wait for every step.
        hist.append(torch.stack([loss.detach(), lc.detach(), lp.detach(), md.detach()]))
        drops.append(dropped)
        step += 1
        now = time.time()
        if now - last_log > args.log_every_s or step == 1:
            h = torch.stack(hist[-50:]).cpu().numpy()
            log(f"step {step} t {now - t0:.0f}s lr {lr:.2e} loss {h[:, 0].mean():.4f} "
                f"conf {h[:, 1].mean():.4f} dist {h[:, 2].mean():.4f} mean_d {h[:, 3].mean():.3f}px "
                f"dropped {sum(drops[-50:])} ({step * args.batch / (now - t0):.0f} img/s; since the last line "
                f"{(step - step_at_log) * args.batch / max(now - last_log, 1e-9):.0f} img/s, "
                f"{100 * (waited - waited_at_log) / max(now - last_log, 1e-9):.0f} % waiting for batches)")
            last_log, waited_at_log, step_at_log = now, waited, step
        if args.save_every_min and now - last_save > 60.0 * args.save_every_min:
            save_checkpoint(Path(args.out), model.to(memory_format=torch.contiguous_format),
                            run_meta(args, cfg, images, hist, step, now - t0, init_record, partial=True,
                                     device=describe(device), batch_wait_s=waited))
            model = model.to(memory_format=torch.channels_last)
            model.train()
            log(f"checkpoint {args.out} at step {step}")
            last_save = now
    train_s = time.time() - t0
    model = model.to(memory_format=torch.contiguous_format)
    save_checkpoint(Path(args.out), model, run_meta(args, cfg, images, hist, step, train_s, init_record,
                                                     device=describe(device), batch_wait_s=waited))
    log(f"saved {args.out} after {step} steps, {train_s:.0f} s")
    return Path(args.out)


def run_meta(args, cfg, images, hist, step: int, train_s: float, init_record, partial: bool = False,
             device: str = "cpu", batch_wait_s: float | None = None) -> dict:
    """The checkpoint's metadata: dataset, input size, training record (`partial` while running)."""
    return {
        "dataset": dataset_tag(args.data, len(images)),
        "data_root": str(args.data),
        "input_height": args.input_size,
        "input_width": args.input_size,
        "trained": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "train_seconds": round(train_s, 1),
        "steps": step,
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "aug": dataclasses.asdict(cfg),
        "final_loss": float(torch.stack(hist[-100:])[:, 0].mean()) if hist else None,
        "init": init_record,
        "device": device,
        "partial": partial,
        # the share of the training time spent waiting for the batch makers
        "batch_wait_fraction": None if batch_wait_s is None else round(batch_wait_s / max(train_s, 1e-9), 3),
    }


def add_training_args(p: argparse.ArgumentParser, minutes: float, threads: int) -> None:
    """The options every trainer here shares (Marknet, YOLOv3): data, output, budget, crops, optimiser,
    memory, threads, seed, logging."""
    p.add_argument("--data", type=Path, required=True, help="dataset root (has train/ val/ test/)")
    p.add_argument("--out", type=Path, required=True, help="checkpoint file to write (.pt)")
    p.add_argument("--minutes", type=float, default=minutes, help="wall-clock training budget")
    p.add_argument("--steps", type=int, default=None, help="train this many steps instead of --minutes")
    p.add_argument("--width", type=int, default=8, help="base channel width")
    p.add_argument("--input-size", type=int, default=416)
    p.add_argument("--crop", type=int, default=224, help="training crop size, network pixels (multiple of 32)")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--lr", type=float, default=3e-3)
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--max-images", type=int, default=4000, help="images kept in memory (random subset)")
    p.add_argument("--max-gb", type=float, default=3.0, help="memory budget for the decoded images")
    p.add_argument("--frame-step", type=int, default=1, help="use every k-th frame of each experiment")
    p.add_argument("--threads", type=int, default=threads)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--log-every-s", type=float, default=30.0)


def training_main(p: argparse.ArgumentParser, train_fn, argv=None) -> int:
    """Parses the arguments and runs `train_fn(args, log)` with timestamped logging; exit status 2
    without a budget."""
    args = p.parse_args(argv)
    if args.steps is None and not args.minutes:
        print("give --minutes or --steps", file=sys.stderr)
        return 2

    def log(msg):
        print(f"[{datetime.now().strftime('%H:%M:%S')}] {msg}", flush=True)

    train_fn(args, log)
    log(json.dumps({"done": str(args.out)}))
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_args(p, minutes=45.0, threads=2)
    p.add_argument("--grid", type=int, default=52, choices=(13, 26, 52), help="S at 416x416")
    p.add_argument("--candidates", type=int, default=5, help="m, candidates per cell (1..5)")
    p.add_argument("--stem", default="s2", choices=STEMS,
                   help="s2: stride-2 stage; s4: one 5x5 stride-4 convolution and a residual block (~2x faster); "
                   "s4-bare: the same convolution alone (~1.4x faster than s4; see model.py)")
    p.add_argument("--canonical", choices=("auto", "stretch"), default="stretch",
                   help="scale of the crops sampled as at inference: stretch (whole image to the input, how the "
                   "shipped model was trained) or auto (the auto layout)")
    p.add_argument("--fuse-kernel", type=int, default=3, choices=FUSE_KERNELS,
                   help="kernel of the top-down path's second fusing convolution (1: cheaper; a 3x3 "
                        "checkpoint warm-starts it with each kernel summed over its taps)")
    p.add_argument("--init", type=Path, default=None,
                   help="start from this Marknet checkpoint's weights (same architecture) instead of random ones; "
                   "an exported .onnx works too (e.g. data/models/marknet.onnx)")
    p.add_argument("--exclude-family", action="append", default=[], metavar="FAMILY",
                   help="leave out the training experiments of this family (meta.json `families`, e.g. "
                   "marker:hue, lattice:hexagonal, res:1920x1080, texture:banding); repeatable")
    p.add_argument("--save-every-min", type=float, default=5.0,
                   help="write the checkpoint every this many minutes while training (0: only at the end)")
    p.add_argument("--p-contact", type=float, default=0.0,
                   help="share of crops centred near a marker in contact (images with contact only; the shipped "
                   "models: 0, i.e. anywhere)")
    p.add_argument("--p-edge", type=float, default=0.0,
                   help="share of crops laid across an image edge, the outside filled with the image's median "
                   "colour as the auto layout's margin at inference (dots cut by the border; shipped models: 0)")
    add_device_args(p)
    p.add_argument("--augment-on", choices=("workers", "device"), default="workers",
                   help="where the photometric augmentation runs: in the batch makers with the crops (a seeded "
                   "CPU run's batches), or on the training device, the batch makers making uint8 crops only "
                   "(a third to a half of a crop's CPU time in the batch makers)")
    p.add_argument("--teacher", type=Path, default=None,
                   help="Marknet checkpoint whose outputs the student learns too (distillation; e.g. "
                   "checkpoints/default/marknet.pt for a cheaper --stem warm-started with --init from it)")
    p.add_argument("--distill-weight", type=float, default=1.0, help="weight of the distillation loss")
    p.add_argument("--alpha", type=float, default=1.0, help="weight of the confidence BCE")
    p.add_argument("--beta", type=float, default=1.0, help="weight of the Euclidean distance")
    p.add_argument("--qat", action="store_true",
                   help="quantization-aware: train with the activations rounded to uint8 as the int8 build "
                   "(gelstereo_train.quantize) rounds them; the checkpoint stays a float network")
    return p


def main(argv=None) -> int:
    return training_main(parser(), train, argv)


if __name__ == "__main__":
    sys.exit(main())
