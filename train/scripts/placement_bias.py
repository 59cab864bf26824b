"""Where the default localizer places the markers it finds, per appearance family of the widened
simulator: the bias (mean) and spread (sd) of the position error, detection minus truth, in x and in y.

    python scripts/placement_bias.py --gelstereo ../target/release/gelstereo --work ../BIAS

With no dataset in WORK/data it first writes the held-out set (`gelstereo simulate --out WORK/data
--experiments 500 --frames-per-experiment 8 --seed 333 --randomization wide --split test`: 100
experiments of a seed no shipped model was trained on), then runs `gelstereo detect` (every default,
Marknet-MRE) on each experiment's two views into WORK/detections (kept: delete it to detect anew, e.g.
with another build), matches every image's detections one-to-one to its visible true markers within
r = 0.25 x pitch (the metrics of `gelstereo eval`) and prints one markdown row per family.

Families are those of each experiment's `meta.json`, plus `gradient:strong`: looks whose LED gradient
or vignetting (any channel of `gradient_x`, `gradient_y`, `gradient_radial`) spans at least 60 grey
levels. `n` counts matched markers. The standard error is that of a mean over experiments (the
markers of one experiment share its look, so they are not independent draws): the sd of the
per-experiment means over the square root of the number of experiments. `|mean| > 0.3` counts the
experiments whose own bias exceeds 0.3 px on either axis (at least 20 matched markers).
WORK/errors.csv holds every matched marker's error. `--replace outline` (or `membership`,
`membership-filled`) re-places each detection from the pixels first: placements tried and not
shipped (`placement_refine.py`).

A glint's direction (`appearance.glint.offset`) and a band's phase are fixed for a recording, so
their pull can cancel in a family's mean while every marker of one sensor moves the same way. The
second table therefore projects each error onto the direction the texture could pull it: from the
dot's centre towards its glint, and across the bands towards the brighter side for markers on a
band's slope (banding of period >= 8 px, where the band's slope is at least half its steepest).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelstereo_train.metrics import match, radius_for  # noqa: E402
from placement_refine import PLACEMENTS  # noqa: E402

SEED = 333
STRONG_GRADIENT = 60.0
BOUND_PX = 0.3
MIN_MARKERS_PER_EXPERIMENT = 20
VIEWS = ("left", "right")


def simulate(gelstereo: str, data: Path) -> None:
    subprocess.run([gelstereo, "simulate", "--out", str(data), "--experiments", "500",
                    "--frames-per-experiment", "8", "--seed", str(SEED), "--randomization", "wide",
                    "--split", "test", "--quiet"], check=True)


def detect(gelstereo: str, experiment: Path, out: Path, extra: list[str]) -> None:
    subprocess.run([gelstereo, "detect", "--threads", "1", "--out", str(out), *extra, str(experiment)],
                   check=True, stderr=subprocess.DEVNULL)


def families_of(meta: dict) -> list[str]:
    fams = [f for f in meta["families"] if not f.startswith("res:")]
    a = meta["appearance"]
    span = max(abs(v) for k in ("gradient_x", "gradient_y", "gradient_radial") for v in a[k])
    if span >= STRONG_GRADIENT:
        fams.append("gradient:strong")
    return ["all", *fams]


def read_detections(path: Path) -> dict[tuple[str, int], np.ndarray]:
    out: dict[tuple[str, int], list] = defaultdict(list)
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            image = Path(r["image"])
            out[image.parent.name, int(image.stem)].append((float(r["x"]), float(r["y"])))
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def read_truth(path: Path) -> dict[tuple[str, int], tuple[np.ndarray, np.ndarray]]:
    rows: dict[tuple[str, int], list] = defaultdict(list)
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            for view in VIEWS:
                if r[f"visible_{view}"] == "1":
                    rows[view, int(r["frame"])].append(
                        (float(r[f"x_{view}"]), float(r[f"y_{view}"]), r["in_contact"] == "1"))
    return {k: (np.asarray([v[:2] for v in vs]), np.asarray([v[2] for v in vs])) for k, vs in rows.items()}


def experiment_errors(experiment: Path, detections: Path, frame_step: int, replace: str | None) -> list[tuple]:
    """(view, frame, x, y, dx, dy, in_contact) of every matched true marker."""
    dets = read_detections(detections)
    rows = []
    for (view, frame), (gt, contact) in sorted(read_truth(experiment / "markers.csv").items()):
        if len(gt) < 2 or frame % frame_step:
            continue
        det = dets.get((view, frame), np.zeros((0, 2)))
        if replace and len(det):
            image = cv2.imread(str(experiment / view / f"{frame:06d}.png"), cv2.IMREAD_COLOR)
            det = PLACEMENTS[replace](image, det)
        pi, gi, _ = match(det, gt, radius_for(gt))
        for p, g in zip(pi, gi):
            dx, dy = det[p] - gt[g]
            rows.append((view, frame, gt[g][0], gt[g][1], dx, dy, bool(contact[g])))
    return rows


def stats(per_experiment: list[np.ndarray]) -> dict:
    """Pooled mean / sd over markers; standard error of the mean over experiments."""
    e = np.concatenate(per_experiment)
    means = np.array([p.mean(0) for p in per_experiment])
    se = means.std(0, ddof=1) / np.sqrt(len(means)) if len(means) > 1 else np.full(2, np.nan)
    big = [p for p in per_experiment if len(p) >= MIN_MARKERS_PER_EXPERIMENT]
    over = sum(bool((np.abs(p.mean(0)) > BOUND_PX).any()) for p in big)
    return {"n": len(e), "experiments": len(per_experiment), "mean": e.mean(0), "sd": e.std(0, ddof=1),
            "se": se, "over": over, "counted": len(big)}


def directed(meta: dict, x: float, y: float, dx: float, dy: float) -> list[tuple[str, float]]:
    """(statistic, signed error px) of one marker: along its glint and towards the brighter band."""
    a = meta["appearance"]
    polarity = "dark" if "marker:dark" in meta["families"] else "light or hue"
    out = []
    if a.get("glint"):
        o = np.asarray(a["glint"]["offset"], np.float64)
        pull = float(np.dot((dx, dy), o / np.linalg.norm(o)))
        out.append((f"glint, {polarity} markers: towards the glint", pull))
    for t in a.get("textures", []):
        if t["kind"] != "bands" or t["period_px"] < 8.0:
            continue
        n = np.array([np.cos(t["angle"]), np.sin(t["angle"])])
        slope = np.cos(2 * np.pi * (x * n[0] + y * n[1]) / t["period_px"] + t["phase"])
        if abs(slope) >= 0.5:
            pull = float(np.sign(slope) * np.dot((dx, dy), n))
            out.append((f"banding, {polarity} markers: towards the brighter band", pull))
    return out


def directed_table(pulls: dict[str, list[np.ndarray]]) -> list[str]:
    lines = ["| texture, statistic | experiments / markers | mean ± se / sd, px | "
             f"experiments with \\|mean\\| > {BOUND_PX} |", "|---|---|---|---|"]
    for name in sorted(pulls):
        s = stats([np.stack([p, p], 1) for p in pulls[name]])
        lines.append(f"| {name} | {s['experiments']} / {s['n']:,} | {s['mean'][0]:+.3f} ± {s['se'][0]:.3f} / "
                     f"{s['sd'][0]:.2f} | {s['over']} of {s['counted']} |")
    return lines


def table(errors: dict[str, list[np.ndarray]]) -> list[str]:
    lines = ["| family | experiments / markers | x: mean ± se / sd, px | y: mean ± se / sd, px | "
             f"experiments with \\|mean\\| > {BOUND_PX} |",
             "|---|---|---|---|---|"]
    order = ["all"] + sorted(f for f in errors if f != "all")
    for fam in order:
        s = stats(errors[fam])
        cells = [f"{s['mean'][a]:+.3f} ± {s['se'][a]:.3f} / {s['sd'][a]:.2f}" for a in (0, 1)]
        lines.append(f"| `{fam}` | {s['experiments']} / {s['n']:,} | {cells[0]} | {cells[1]} | "
                     f"{s['over']} of {s['counted']} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gelstereo", default="gelstereo", help="the gelstereo binary")
    p.add_argument("--work", type=Path, required=True, help="folder for data/, detections/, errors.csv")
    p.add_argument("--detect-arg", action="append", default=[], help="passed on to gelstereo detect")
    p.add_argument("--contact", action="store_true", help="only the markers in contact")
    p.add_argument("--frame-step", type=int, default=1, help="only frames 0, N, 2N, ...")
    p.add_argument("--replace", choices=sorted(PLACEMENTS),
                   help="re-place each detection from the pixels (tried, not shipped; placement_refine.py)")
    args = p.parse_args(argv)
    data = args.work / "data"
    if not (data / "test").is_dir():
        simulate(args.gelstereo, data)
    experiments = sorted(m.parent for m in (data / "test").glob("*/meta.json"))
    if not experiments:
        print(f"error: {data / 'test'} holds no experiment with a meta.json", file=sys.stderr)
        return 1
    (args.work / "detections").mkdir(parents=True, exist_ok=True)
    errors: dict[str, list[np.ndarray]] = defaultdict(list)
    pulls: dict[str, list[np.ndarray]] = defaultdict(list)
    with open(args.work / "errors.csv", "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["experiment", "view", "frame", "x", "y", "dx", "dy", "in_contact", "families"])
        for exp in experiments:
            dets = args.work / "detections" / f"{exp.name}.csv"
            if not dets.is_file():
                detect(args.gelstereo, exp, dets, args.detect_arg)
            rows = experiment_errors(exp, dets, args.frame_step, args.replace)
            meta = json.loads((exp / "meta.json").read_text())
            fams = families_of(meta)
            mine: dict[str, list[float]] = defaultdict(list)
            for r in rows:
                out.writerow([exp.name, r[0], r[1], f"{r[2]:.3f}", f"{r[3]:.3f}", f"{r[4]:.4f}", f"{r[5]:.4f}",
                              int(r[6]), " ".join(fams)])
                if r[6] or not args.contact:
                    for name, v in directed(meta, *r[2:6]):
                        mine[name].append(v)
            for name, v in mine.items():
                pulls[name].append(np.asarray(v))
            d = np.array([(r[4], r[5]) for r in rows if r[6] or not args.contact]).reshape(-1, 2)
            if len(d):
                for fam in fams:
                    errors[fam].append(d)
    print("\n".join(table(errors)))
    print()
    print("\n".join(directed_table(pulls)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
