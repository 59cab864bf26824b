"""Fine-tune Marknet on pseudo-labels of a user's own sensor and export a model folder.

    python -m gelstereo_train.adapt --data PSEUDO --out PSEUDO/run/marknet.pt --base ../data/models \
        --out-dir MODELS --minutes 5

`gelstereo adapt` runs this after writing the pseudo-label dataset PSEUDO (images, labels and ignore
masks, see ``crates/gelstereo-apps/src/adapt/labels.rs``); it can be run by hand on such a dataset too. Steps:

1. warm start from the base folder's ``marknet.onnx`` (architecture read from the ONNX graph and its
   metadata; BatchNorm re-inflated, ``onnx_init``);
2. train for ``--minutes`` of wall clock on the ``train`` split with the trainer's augmentations, all
   of which map labels and ignore masks with the image (crops, scale, anisotropy, flips, small
   rotations, photometry), at a low learning rate: the pseudo-labels are the default's own sure finds,
   and the point is to keep them while gaining the markers it was unsure of;
3. export ``marknet.onnx`` (contract ``gelstereo-marknet/2``, checked in ONNX Runtime), copy the base
   ``mre.onnx`` (its features are distances in pitches and the confidence: nothing sensor-specific),
   write ``export_report.json`` and ``MODEL_CARD.md`` (base model, source recording, pseudo-label
   counts, the commands, the time).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import shutil
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import onnx
import torch
from onnx import numpy_helper

from .export import export_marknet, marknet_metadata
from .model import STRIDE_FOR_GRID_416
from .postprocess import FitConfig, PostConfig
from .batches import add_device_args
from .train_marknet import add_training_args, train


def base_architecture(path: Path) -> dict:
    """Stem, width, grid, candidates, input size and layout of an exported Marknet, from its graph and
    metadata_props."""
    try:
        m = onnx.load(str(path))
    except Exception as e:  # noqa: BLE001 - onnx raises several kinds on a bad file
        raise SystemExit(f"{path}: cannot read the base Marknet: {e}") from e
    meta = {p.key: p.value for p in m.metadata_props}
    inits = {t.name: t for t in m.graph.initializer}
    convs = [n for n in m.graph.node if n.op_type == "Conv" and n.input[1] in inits]
    if len(convs) < 2:
        raise SystemExit(f"{path}: fewer than two convolutions with constant weights: not a Marknet")
    w, second = (numpy_helper.to_array(inits[c.input[1]]) for c in convs[:2])
    # s4: one 5x5 stride-4 convolution to 2 x width channels, then a residual block (its 1x1 first);
    # s4-bare: the same convolution, then the 3x3 stride-2 one of stride 8; s2: a 3x3 stride-2 one to
    # width channels.
    if w.shape[2:] == (5, 5):
        stem, width = ("s4" if second.shape[2:] == (1, 1) else "s4-bare"), w.shape[0] // 2
    else:
        stem, width = "s2", w.shape[0]
    try:
        stride = int(meta["stride"])
        candidates = int(meta["candidates"])
        hw = (int(meta["input_height"]), int(meta["input_width"]))
    except (KeyError, ValueError) as e:
        raise SystemExit(f"{path}: metadata_props lacks a number for {e} (docs/model-contract.md)") from e
    grid = {v: k for k, v in STRIDE_FOR_GRID_416.items()}.get(stride)
    if grid is None:
        raise SystemExit(f"{path}: metadata 'stride': expected 8, 16 or 32, found {stride}")
    layout = meta.get("preferred_layout", "stretch")
    # The convolution before the 1x1 head is the last top-down step's second fusing one.
    fuse_kernel = int(numpy_helper.to_array(inits[convs[-2].input[1]]).shape[2])
    return {"stem": stem, "width": width, "grid": grid, "candidates": candidates, "input_hw": hw,
            "canonical": "auto" if layout == "isotropic" else "stretch", "fuse_kernel": fuse_kernel,
            "meta": meta}


def sha16(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_args(p, minutes=5.0, threads=2)
    p.set_defaults(lr=5e-4, batch=16, crop=160, log_every_s=15.0)
    p.add_argument("--base", type=Path, required=True, help="folder with the base marknet.onnx and mre.onnx")
    p.add_argument("--out-dir", type=Path, required=True, help="model folder to write")
    p.add_argument("--command", default=None, help="the command that asked for this run (for the model card)")
    p.add_argument("--name", default=None,
                   help="the folder's final name, for the model card (default: --out-dir; `gelstereo adapt` "
                   "writes into a temporary folder and renames it)")
    p.add_argument("--p-contact", type=float, default=0.0)
    p.add_argument("--p-edge", type=float, default=0.0, help="share of crops laid across an image edge")
    add_device_args(p)
    p.add_argument("--alpha", type=float, default=1.0)
    p.add_argument("--beta", type=float, default=1.0)
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    if args.steps is None and not args.minutes:
        print("give --minutes or --steps", file=sys.stderr)
        return 2
    t_start = time.time()

    def log(msg):
        print(f"[{datetime.now().strftime('%H:%M:%S')}] {msg}", flush=True)

    base_marknet, base_mre = args.base / "marknet.onnx", args.base / "mre.onnx"
    for f in (base_marknet, base_mre):
        if not f.is_file():
            raise SystemExit(f"{f}: base model missing (--base names a folder with marknet.onnx and mre.onnx)")
    info_path = args.data / "dataset.json"
    try:
        info = json.loads(info_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"{info_path}: cannot read the pseudo-label manifest: {e}") from e
    arch = base_architecture(base_marknet)
    log(f"base {base_marknet}: stem {arch['stem']}, width {arch['width']}, S {arch['grid']}, "
        f"m {arch['candidates']}, layout {arch['canonical']}")

    # The trainer's own options, for the base architecture (--out is the checkpoint).
    targs = argparse.Namespace(**vars(args))
    targs.init = base_marknet
    targs.stem, targs.width, targs.fuse_kernel = arch["stem"], arch["width"], arch["fuse_kernel"]
    targs.grid, targs.candidates = arch["grid"], arch["candidates"]
    targs.canonical = arch["canonical"]
    targs.input_size = arch["input_hw"][0]
    targs.exclude_family = []
    targs.save_every_min = 0.0
    torch.set_num_threads(args.threads)
    t_train = time.time()
    train(targs, log)
    train_s = time.time() - t_train

    from .train_marknet import load_checkpoint

    model, meta = load_checkpoint(targs.out)
    hw = arch["input_hw"]
    post = PostConfig()
    fit = FitConfig(nominal_hw=hw, prefer_stretch=arch["canonical"] == "stretch")
    source = info.get("source", "?")
    dataset = f"adapted: {Path(source).name} pseudo-labels ({info.get('generator', '?')}) on {meta['dataset']}"
    args.out_dir.mkdir(parents=True, exist_ok=True)
    mk = args.out_dir / "marknet.onnx"
    md = marknet_metadata(model, hw, dataset, meta["trained"], post, fit=fit)
    diff = export_marknet(model, mk, hw, md)
    log(f"{mk}: onnxruntime vs PyTorch max abs diff (raw logits) {diff:.3g}")
    shutil.copyfile(base_mre, args.out_dir / "mre.onnx")
    (args.out_dir / "export_report.json").write_text(
        json.dumps({"marknet_max_abs_diff": diff, "mre": f"copied from {base_mre}"}, indent=2) + "\n")
    write_card(args, info, meta, arch, base_marknet, train_s, time.time() - t_start, diff)
    log(json.dumps({"done": str(args.out_dir)}))
    return 0


def write_card(args, info: dict, meta: dict, arch: dict, base_marknet: Path, train_s: float, total_s: float,
               diff: float) -> None:
    """MODEL_CARD.md of the adapted folder, from this run's own records."""
    pl = info.get("pseudo_labels", {})
    cfg = info.get("config", {})
    out = args.out_dir
    name = args.name or str(out)
    files = "\n".join(
        f"| `{f}` | {(out / f).stat().st_size} | {sha16(out / f)} |" for f in ("marknet.onnx", "mre.onnx"))
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(pl.get("skipped", {}).items())) or "none"
    init = meta.get("init") or {}
    text = f"""# Adapted models: `marknet.onnx`, `mre.onnx`

Marknet fine-tuned on pseudo-labels of one recording of the user's own sensor by `gelstereo adapt`
(`docs/localization.md`, "Adapting to your sensor"). Use with `--models {name}` (any command that
takes `--models`). The shipped default is unchanged.

## Files

| file | bytes | sha256 (16) |
|---|---|---|
{files}

## Base and source

- Base model: `{base_marknet}` (sha256 {sha16(base_marknet)}; stem `{arch['stem']}`, width {arch['width']},
  S = {arch['grid']}, m = {arch['candidates']}; its dataset: "{arch['meta'].get('dataset', '?')}").
- MRE: the base `mre.onnx`, copied (its features are neighbour distances in pitches and the confidence).
- Source recording: `{info.get('source', '?')}` ({info.get('views', '?')} view(s) per frame).

## Pseudo-labels ({info.get('generator', '?')})

- Frames used: {pl.get('frames_used', '?')}; the default accepted {pl.get('default_accepted', '?')} markers over them.
- Training split: {pl.get('train_views', '?')} views, {pl.get('train_labels', '?')} labels, {pl.get('train_ignored', '?')} ignore discs
  (and everything outside each view's labels' hull grown by half a pitch).
- Held out (not trained on): {pl.get('heldout_views', '?')} views, {pl.get('heldout_labels', '?')} labels; source frames
  {compact(pl.get('heldout_frames', []))}.
- Views left out: {skipped}. Median pitch {fmt(pl.get('pitch_px'))} px.
- Rules: confidence >= {fmt(cfg.get('min_confidence'))}, a lattice member, a detection within
  {fmt(cfg.get('track_radius_frac'))} pitch in each neighbouring frame; ignore discs of {fmt(cfg.get('ignore_radius_frac'))} pitch;
  views with fewer than {fmt(cfg.get('min_frame_fraction'))} x the median labels left out; hold-out blocks of
  {cfg.get('holdout_block', '?')} frames, every {cfg.get('holdout_every', '?')}th.

## Training

- {meta.get('steps', '?')} steps of batch {args.batch} ({args.crop} x {args.crop} crops) in {train_s:.0f} s of wall
  clock (budget {args.minutes} min), {args.threads} thread(s), AdamW lr {args.lr} (warm-up, cosine), seed {args.seed};
  final training loss {fmt(meta.get('final_loss'))}; BatchNorm re-inflated from the base, max
  |torch - onnxruntime| {fmt(init.get('max_abs_diff_vs_onnx'))} before training.
- Export: ONNX Runtime vs PyTorch max abs difference {diff:.2g} (raw logits); whole run {total_s:.0f} s.
- Machine: {platform.platform()}, torch {torch.__version__}; finished {meta.get('trained', '?')}.

## Commands

```sh
{args.command or '(run by hand)'}
python -m gelstereo_train.adapt --data PSEUDO --out PSEUDO/run/marknet.pt --base {args.base} \\
  --out-dir {name} --minutes {args.minutes} --threads {args.threads} --seed {args.seed}
```
"""
    (out / "MODEL_CARD.md").write_text(text)


def fmt(v) -> str:
    return "?" if v is None else f"{v:.3g}" if isinstance(v, float) else str(v)


def compact(frames: list[int]) -> str:
    """`20-29, 70-79` for runs of consecutive frame numbers."""
    if not frames:
        return "none"
    runs, start, prev = [], frames[0], frames[0]
    for f in frames[1:] + [None]:
        if f is not None and f == prev + 1:
            prev = f
            continue
        runs.append(f"{start}-{prev}" if prev != start else f"{start}")
        if f is not None:
            start = prev = f
    return ", ".join(runs)


if __name__ == "__main__":
    sys.exit(main())
