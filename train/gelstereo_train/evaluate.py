"""Evaluate Marknet, Marknet + MRE and the blob baseline on a split with the paper's metrics.

    python -m gelstereo_train.evaluate --data ROOT --split test --marknet runs/marknet.pt \
        --mre runs/mre.pt --out runs/eval_test.json

Models are given as PyTorch checkpoints (.pt) or exported ONNX files (.onnx, run in onnxruntime).
See gelstereo_train.metrics for the definitions (r = 0.25 x pitch, splits easy / hard / contact).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from .blob import BlobDetector
from .data import experiment_families, list_samples, median_nn_distance
from .metrics import Evaluator, hard_mask, radius_for
from .runtime import ort_session
from .postprocess import (
    FitConfig,
    Layout,
    PostConfig,
    TorchMRE,
    bgr,
    decode_layout,
    fit_config_from_metadata,
    fit_layout,
    input_per_px,
    postprocess,
    preprocess_layout,
    stretch_layout,
)
from gelstereo import postprocess as rust_post


class MarknetRunner:
    """Runs a Marknet checkpoint or ONNX file on RGB images; returns decoded candidates per image.

    The passes are the Rust localizer's (``gelstereo.postprocess.Marknet``, each image on its own as
    ``gelstereo eval`` runs them): models with a dynamic input (contract ``gelstereo-marknet/2``, every
    checkpoint) get the "auto" fit of docs/model-contract.md (probes, relayouts to the measured pitch and,
    with the lattice check, a closer look where candidates lie squeezed; ``close_look=False``: none, as
    ``gelstereo eval --no-close-look``); fixed-size models (``gelstereo-marknet/1``) and ``fit="stretch"``
    the whole-image stretch. A checkpoint is exported to ONNX for them first. ``raw`` runs the network
    itself (PyTorch or ONNX Runtime) on a prepared input (the MRE dataset's augmented copies)."""

    def __init__(self, path: Path | str, threads: int = 2, post: PostConfig | None = None, fit: str = "auto",
                 close_look: bool = True):
        if fit not in ("auto", "stretch"):
            raise ValueError(f"fit must be 'auto' or 'stretch', got {fit!r}")
        path = Path(path)
        self.path = path
        self.post = post or PostConfig()
        self.close_look = close_look
        self.looked: list = []  # per image of the latest call, the region its closer look re-examined or None
        if path.suffix == ".onnx":
            self.sess = ort_session(path, threads)
            meta = self.sess.get_modelmeta().custom_metadata_map
            self.model = None
            self.net = rust_post.Marknet(str(path), threads, fit, self.post, close_look)
            dynamic = meta.get("input_size") == "dynamic" and fit == "auto"
            self.fit = fit_config_from_metadata(meta) if dynamic else None
        else:
            from .train_marknet import load_checkpoint

            self.model, meta = load_checkpoint(path)
            self.sess = None
            hw = (int(meta["input_height"]), int(meta["input_width"]))
            stretch = meta.get("aug", {}).get("canonical", "stretch") == "stretch"
            fit_cfg = FitConfig(nominal_hw=hw, prefer_stretch=stretch)
            self.net = self._exported(threads, fit, fit_cfg, close_look)
            self.fit = fit_cfg if fit == "auto" else None
        self.input_hw = (self.net.input_height, self.net.input_width)
        self.stride = self.net.stride
        self.meta = meta

    def _exported(self, threads: int, fit: str, fit_cfg: FitConfig, close_look: bool):
        """The Rust runner of the checkpoint's model, exported to a temporary ONNX file."""
        from .export import export_marknet, marknet_metadata

        with tempfile.TemporaryDirectory() as tmp:
            onnx_path = Path(tmp) / "marknet.onnx"
            meta = marknet_metadata(self.model, fit_cfg.nominal_hw, "checkpoint", "checkpoint", self.post, fit_cfg)
            export_marknet(self.model, onnx_path, fit_cfg.nominal_hw, meta)
            return rust_post.Marknet(str(onnx_path), threads, fit, self.post, close_look)

    def raw(self, x: torch.Tensor) -> np.ndarray:
        if self.sess is not None:
            return self.sess.run(["raw"], {"image": x.numpy()})[0]
        with torch.no_grad():
            return self.model(x).numpy()

    def layout(self, img: np.ndarray, pitch_px: float | None = None) -> Layout:
        """The input layout of an image: "auto" fit for dynamic models, else the stretch."""
        h, w = img.shape[:2]
        if self.fit is None:
            return stretch_layout(self.input_hw[::-1])
        return fit_layout(w, h, pitch_px, self.fit)

    def run_layout(self, img: np.ndarray, lay: Layout) -> np.ndarray:
        """Decoded candidates (flat, original px) of one image under one layout, run by ``raw``."""
        raw = self.raw(preprocess_layout(img, lay))[0]
        return decode_layout(raw, self.stride, (img.shape[1], img.shape[0]), lay)

    def fitted(self, img: np.ndarray) -> tuple[np.ndarray, Layout]:
        """Decoded candidates (c > conf_low) of one image after the Rust passes and the layout they came
        from; ``looked_region``: the region its closer look re-examined, or None."""
        dec, lay, self.looked_region = self.net.fitted([bgr(img)])[0]
        return dec, Layout(*lay)

    def __call__(self, images: list[np.ndarray], batch: int = 8) -> list[np.ndarray]:
        fitted = [self.fitted(im) + (self.looked_region,) for im in images]
        self.layouts = [lay for _, lay, _ in fitted]
        self.looked = [looked for _, _, looked in fitted]
        return [dec for dec, _, _ in fitted]


def load_mre(path: Path | str | None, threads: int = 2):
    """A callable (n, 11) -> (n,) probabilities from an MRE checkpoint (.pt) or ONNX file."""
    if path is None:
        return None
    path = Path(path)
    if path.suffix == ".onnx":
        sess = ort_session(path, threads)
        return lambda f: sess.run(["score"], {"features": np.asarray(f, np.float32)})[0][:, 0]
    from .train_mre import load_mre_checkpoint

    return TorchMRE(load_mre_checkpoint(path)[0])


MIN_PITCH_IN_PX = 9.0  # lower end of the training scale jitter (pitch at the network input)


def pitch_at_input_px(gt: np.ndarray, image_wh, input_wh) -> float:
    """Marker pitch of the ground truth at the network input, the smaller of the x and y scalings."""
    return median_nn_distance(gt) * min(input_wh[0] / image_wh[0], input_wh[1] / image_wh[1])


def evaluate(samples, runner: MarknetRunner, mre_fn, post: PostConfig, blob: BlobDetector | None = None,
             log=print, batch: int = 8, min_pitch_in_px: float = MIN_PITCH_IN_PX) -> dict:
    """Metrics of Marknet, Marknet+MRE and the blob baseline over samples; also over the images whose
    marker pitch at the network input is >= min_pitch_in_px (the design range), under "in_range"."""
    ev = {"marknet": Evaluator(), "marknet_mre": Evaluator(), "blob": Evaluator()}
    ev_in = {"marknet": Evaluator(), "marknet_mre": Evaluator(), "blob": Evaluator()}
    n_out = 0
    blob = blob or BlobDetector()
    t0 = time.time()
    t_net = 0.0
    for i in range(0, len(samples), batch):
        chunk = samples[i : i + batch]
        imgs = [s.load() for s in chunk]
        t = time.time()
        decoded = runner(imgs, batch=batch)
        t_net += time.time() - t
        for s, img, dec, used, looked in zip(chunk, imgs, decoded, runner.layouts, runner.looked):
            gt = s.points_px
            r = radius_for(gt)
            bl = blob.detect(img)
            hard = hard_mask(bl, gt, r)
            size = (img.shape[1], img.shape[0])
            det = postprocess(dec, post, mre_fn, input_per_px(size, used), size, looked, img, runner.close_look)
            lay = runner.layout(img, median_nn_distance(gt))
            in_range = pitch_at_input_px(gt, size, (lay.scaled_w, lay.scaled_h)) >= min_pitch_in_px
            n_out += not in_range
            for e in (ev, ev_in) if in_range else (ev,):
                e["marknet"].add_image(det.marknet, gt, hard, s.in_contact, r, size)
                if mre_fn is not None:
                    e["marknet_mre"].add_image(det.marknet_mre, gt, hard, s.in_contact, r, size)
                e["blob"].add_image(bl, gt, hard, s.in_contact, r, size)
        if (i // batch) % 25 == 0:
            log(f"evaluated {i + len(chunk)}/{len(samples)} images ({time.time() - t0:.0f} s)")
    out = {k: v.summary() for k, v in ev.items() if v.radii}
    out["images"] = len(samples)
    out["in_range"] = {k: v.summary() for k, v in ev_in.items() if v.radii}
    out["in_range"]["images"] = len(samples) - n_out
    out["in_range"]["rule"] = f"marker pitch at the network input >= {min_pitch_in_px} px"
    out["torch_or_ort_seconds_per_image"] = t_net / max(1, len(samples))
    return out


def format_table(res: dict) -> str:
    """Markdown table: method x split with precision, recall, loss."""
    lines = ["| method | split | precision | recall | loss (px^2) | T | PT | PF |", "|---|---|---|---|---|---|---|---|"]
    for method in ("blob", "marknet", "marknet_mre"):
        if method not in res:
            continue
        for split in ("easy", "hard", "contact", "all"):
            m = res[method][split]
            lines.append(
                f"| {method} | {split} | {100 * m['precision']:.2f}% | {100 * m['recall']:.2f}% | "
                f"{m['loss_px2']:.3f} | {m['T']} | {m['PT']} | {m['PF']} |"
            )
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--marknet", type=Path, required=True, help=".pt checkpoint or .onnx")
    p.add_argument("--mre", type=Path, default=None, help=".pt checkpoint or .onnx")
    p.add_argument("--out", type=Path, default=None, help="JSON file for the results")
    p.add_argument("--frame-step", type=int, default=1)
    p.add_argument("--max-experiments", type=int, default=None)
    p.add_argument("--max-images", type=int, default=None, help="random subset (seed 0) of the split's images")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--fit", choices=("auto", "stretch"), default="auto",
                   help="auto: the model's layout (two passes, docs/model-contract.md); stretch: whole image "
                   "resized to the nominal input (the first contract)")
    p.add_argument("--dedup-radius-frac", type=float, default=None)
    p.add_argument("--family", action="append", default=[], metavar="FAMILY",
                   help="only the experiments of this family (meta.json `families`, datasets of "
                   "`gelstereo simulate --randomization wide`); repeated: of all of them")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    post = PostConfig()
    if args.dedup_radius_frac is not None:
        post.dedup_radius_frac = args.dedup_radius_frac
    runner = MarknetRunner(args.marknet, args.threads, post, fit=args.fit)
    samples = list_samples(args.data, args.split, frame_step=args.frame_step, max_experiments=args.max_experiments)
    if args.family:
        samples = [s for s in samples
                   if set(args.family) <= set(experiment_families(args.data, s.split, s.experiment))]
        if not samples:
            raise SystemExit(f"{args.data}/{args.split}: no experiment of the families {args.family}")
    if args.max_images is not None and len(samples) > args.max_images:
        keep = np.sort(np.random.default_rng(0).choice(len(samples), args.max_images, replace=False))
        samples = [samples[i] for i in keep]
    res = evaluate(samples, runner, load_mre(args.mre, args.threads), post)
    res["split"] = args.split
    res["families"] = args.family
    res["max_images"] = args.max_images
    res["marknet_file"] = str(args.marknet)
    res["mre_file"] = str(args.mre) if args.mre else None
    print(format_table(res))
    if res["in_range"].get("marknet"):
        print(f"\nIn the design range ({res['in_range']['rule']}): {res['in_range']['images']} of {res['images']} images")
        print(format_table(res["in_range"]))
    print(json.dumps({k: res[k] for k in ("images", "split")} | {"radius_px": res["marknet"].get("radius_px")}))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
