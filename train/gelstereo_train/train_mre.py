"""Build the MRE dataset from validation-set predictions and train the MRE.

    python -m gelstereo_train.train_mre --data ROOT --marknet runs/marknet.pt --out runs/mre.pt

As in the paper (section III-A-2): Marknet runs on the validation images; every de-duplicated candidate
with conf_low < c <= conf_keep gets the 11-d feature of docs/model-contract.md and the label 1 when it
is matched one-to-one (nearest pairs first, r = 0.25 x pitch) to a ground-truth marker among all
candidates with c > conf_low, else 0. To see enough uncertain candidates each validation image is also
run with ``--variants`` photometrically augmented copies. The majority class is randomly subsampled to
a 1:1 balance. The MRE (3 fully connected layers) is trained with BCE; 10% is held out to report the
accuracy and the precision of what it accepts at y_e > 0.99.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .augment import AugConfig, photometric
from .data import list_samples
from .evaluate import MarknetRunner
from .metrics import match, radius_for
from .model import MRE
from .postprocess import PostConfig, decode_layout, postprocess, preprocess_layout


def collect(samples, runner: MarknetRunner, post: PostConfig, variants: int, rng, log=print, batch: int = 8):
    """Features (n, 11) and labels (n,) of the uncertain candidates over the samples."""
    feats, labels = [], []
    aug = AugConfig(p_clean=0.0)
    t0 = time.time()
    for i in range(0, len(samples), batch):
        chunk = samples[i : i + batch]
        imgs = [s.load() for s in chunk]
        for s, im in zip(chunk, imgs):
            lay = runner.fitted(im)[1] if runner.fit is not None else runner.layout(im)
            x = preprocess_layout(im, lay)
            for xv in [x] + [photometric(x.clone(), aug, rng) for _ in range(variants)]:
                dec = decode_layout(runner.raw(xv)[0], runner.stride, (im.shape[1], im.shape[0]), lay)
                det = postprocess(dec, post, None)
                if len(det.mre_index) == 0:
                    continue
                pi, _, _ = match(det.candidates[:, :2], s.points_px, radius_for(s.points_px))
                correct = np.zeros(len(det.candidates), bool)
                correct[pi] = True
                feats.append(det.mre_features)
                labels.append(correct[det.mre_index])
        if (i // batch) % 25 == 0:
            n = sum(len(lb) for lb in labels)
            log(f"MRE data: {i + len(chunk)}/{len(samples)} images, {n} candidates ({time.time() - t0:.0f} s)")
    if not feats:
        return np.zeros((0, 11), np.float32), np.zeros(0, bool)
    return np.concatenate(feats), np.concatenate(labels)


def balance(feats, labels, rng):
    """Random 1:1 subsample of the majority class."""
    pos, neg = np.nonzero(labels)[0], np.nonzero(~labels)[0]
    n = min(len(pos), len(neg))
    if n == 0:
        return feats, labels
    sel = np.concatenate([rng.choice(pos, n, replace=False), rng.choice(neg, n, replace=False)])
    rng.shuffle(sel)
    return feats[sel], labels[sel]


def train_mre(feats, labels, epochs: int, seed: int, log=print):
    """Train the MRE; returns (model, report dict)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    n = len(labels)
    perm = rng.permutation(n)
    n_hold = max(1, n // 10) if n >= 20 else 0
    hold, tr = perm[:n_hold], perm[n_hold:]
    x = torch.from_numpy(feats.astype(np.float32))
    y = torch.from_numpy(labels.astype(np.float32))[:, None]
    model = MRE()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    bs = 256
    for ep in range(epochs):
        model.train()
        order = rng.permutation(tr)
        tot = 0.0
        for k in range(0, len(order), bs):
            j = torch.from_numpy(order[k : k + bs])
            loss = F.binary_cross_entropy_with_logits(model(x[j]), y[j])
            opt.zero_grad()
            loss.backward()
            opt.step()
            tot += loss.item() * len(j)
        for g in opt.param_groups:
            g["lr"] = 3e-3 * 0.5 * (1 + np.cos(np.pi * (ep + 1) / epochs))
        if ep % max(1, epochs // 5) == 0 or ep == epochs - 1:
            log(f"MRE epoch {ep + 1}/{epochs} loss {tot / max(1, len(tr)):.4f}")
    model.eval()
    report = {"samples": int(n), "positives": int(labels.sum()), "holdout": int(n_hold)}
    if n_hold:
        with torch.no_grad():
            p = torch.sigmoid(model(x[hold]))[:, 0].numpy()
        yt = labels[hold]
        acc = float(((p > 0.5) == yt).mean())
        accepted = p > 0.99
        report |= {
            "holdout_accuracy": acc,
            "holdout_accepted_share": float(accepted.mean()),
            "holdout_precision_at_0.99": float(yt[accepted].mean()) if accepted.any() else None,
            "holdout_recall_at_0.99": float(accepted[yt].mean()) if yt.any() else None,
        }
    return model, report


def save_mre_checkpoint(path: Path, model: MRE, meta: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": model.state_dict(), "meta": meta}, path)


def load_mre_checkpoint(path: Path | str):
    ck = torch.load(path, map_location="cpu", weights_only=False)
    m = MRE()
    m.load_state_dict(ck["model"])
    return m.eval(), ck["meta"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--marknet", type=Path, required=True, help=".pt checkpoint or .onnx")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--split", default="val")
    p.add_argument("--variants", type=int, default=3, help="augmented copies per validation image")
    p.add_argument("--frame-step", type=int, default=1)
    p.add_argument("--max-images", type=int, default=1200, help="random subset of the split's images")
    p.add_argument("--max-samples", type=int, default=200000, help="cap of the balanced set (paper: 200,000)")
    p.add_argument("--epochs", type=int, default=200)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)

    def log(msg):
        print(f"[{datetime.now().strftime('%H:%M:%S')}] {msg}", flush=True)

    rng = np.random.default_rng(args.seed)
    runner = MarknetRunner(args.marknet, args.threads)
    post = PostConfig()
    samples = list_samples(args.data, args.split, frame_step=args.frame_step)
    if args.max_images is not None and len(samples) > args.max_images:
        samples = [samples[i] for i in np.sort(rng.choice(len(samples), args.max_images, replace=False))]
    t0 = time.time()
    feats, labels = collect(samples, runner, post, args.variants, rng, log)
    raw_counts = {"candidates": int(len(labels)), "correct": int(labels.sum()), "wrong": int((~labels).sum())}
    log(f"MRE raw data {raw_counts}")
    feats, labels = balance(feats, labels, rng)
    if len(labels) > args.max_samples:
        feats, labels = feats[: args.max_samples], labels[: args.max_samples]
    if len(labels) == 0 or labels.all() or (~labels).all():
        log("MRE: not enough uncertain candidates of both classes; training on what there is")
    model, report = train_mre(feats, labels, args.epochs, args.seed, log)
    meta = {
        "dataset": runner.meta.get("dataset", ""),
        "split": args.split,
        "raw_counts": raw_counts,
        "report": report,
        "seconds": round(time.time() - t0, 1),
        "conf_low": post.conf_low,
        "conf_keep": post.conf_keep,
        "dedup_radius_frac": post.dedup_radius_frac,
        "trained": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    save_mre_checkpoint(args.out, model, meta)
    log(json.dumps(meta))
    return 0


if __name__ == "__main__":
    sys.exit(main())
