"""Write data/models/MODEL_CARD.md from a training run's own records (no hand-copied numbers).

    cd train && ../.venv/bin/python scripts/write_model_card.py RUN_DIR [--models ../data/models] [--notes FILE]

Reads RUN_DIR/{marknet.pt, mre.pt, eval_test.json, real_check.json (optional), machine.txt (optional)}
and MODELS/{marknet.onnx, mre.onnx, export_report.json}.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import onnx
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gelstereo_train.evaluate import format_table  # noqa: E402
from gelstereo_train.model import Marknet, count_flops  # noqa: E402

STEM_WORDS = {
    "s2": "3x3 stride-2 convolution + residual block",
    "s4": "one 5x5 stride-4 convolution + residual block",
    "s4-bare": "one 5x5 stride-4 convolution, no residual block at stride 4",
}


def sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()[:16]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("run", type=Path)
    p.add_argument("--models", type=Path, default=Path(__file__).resolve().parents[2] / "data" / "models")
    p.add_argument("--notes", type=Path, default=None, help="markdown appended as 'Notes'")
    p.add_argument("--title", default="Shipped models: `marknet.onnx`, `mre.onnx`", help="the card's heading")
    args = p.parse_args(argv)
    run, models = args.run, args.models
    ck = torch.load(run / "marknet.pt", map_location="cpu", weights_only=False)
    meta, arch = ck["meta"], ck["arch"]
    net = Marknet(**arch)
    mre_meta = torch.load(run / "mre.pt", map_location="cpu", weights_only=False)["meta"]
    ev = json.loads((run / "eval_test.json").read_text())
    exp = json.loads((models / "export_report.json").read_text())
    props = {e.key: e.value for e in onnx.load(str(models / "marknet.onnx")).metadata_props}
    a = meta["args"]
    L = []
    L.append(f"# {args.title}\n")
    L.append("Marknet + MRE (Liu et al., *Real-Time Marker Localization Learning for GelStereo Tactile Sensing*), "
             "trained in PyTorch by `train/` on simulated data only, exported per `docs/model-contract.md`.\n")
    L.append("## Files\n")
    L.append("| file | bytes | sha256 (16) | contents |\n|---|---|---|---|")
    if props.get("input_size") == "dynamic":
        shapes = (f"input `image` [N,3,H,W] (H, W multiples of {props['input_multiple']}; nominal "
                  f"{props['input_height']}x{props['input_width']}) -> `raw` [N,H/{arch['stride']},W/{arch['stride']},"
                  f"{arch['candidates']},3]; contract `{props['contract']}`")
    else:
        shapes = (f"input `image` [N,3,{props['input_height']},{props['input_width']}] -> `raw` "
                  f"[N,{int(props['input_height']) // arch['stride']},{props['grid']},{arch['candidates']},3]")
    L.append(f"| `marknet.onnx` | {(models / 'marknet.onnx').stat().st_size} | {sha(models / 'marknet.onnx')} | "
             f"{shapes} |")
    L.append(f"| `mre.onnx` | {(models / 'mre.onnx').stat().st_size} | {sha(models / 'mre.onnx')} | "
             "input `features` [N,11] -> `score` [N,1] |\n")
    L.append("## Model\n")
    L.append(f"- Marknet: S = {props['grid']} (stride {arch['stride']}), m = {arch['candidates']}, base width "
             f"{arch['width']}; {sum(q.numel() for q in net.parameters())} parameters, "
             f"{count_flops(net):.3f} GFLOP at 416x416 ({count_flops(net, 320, 416):.3f} at 416x320, the reference "
             f"sensor's auto layout); stem `{arch.get('stem', 's2')}` ("
             + STEM_WORDS.get(arch.get("stem", "s2"), "?")
             + "). Conv + BatchNorm + LeakyReLU, Darknet residual blocks down to stride 32, a top-down path with nearest upsampling and lateral concatenation back to "
             "stride 8, one 1x1 detection head (`train/gelstereo_train/model.py`).")
    L.append("- MRE: 11 -> 32 -> 32 -> 1 fully connected, ReLU, sigmoid inside the exported graph.")
    L.append(f"- Post-processing defaults in metadata_props: conf_keep {props['conf_keep']}, conf_low "
             f"{props['conf_low']}, conf_marknet_only {props['conf_marknet_only']}, dedup_radius_frac "
             f"{props['dedup_radius_frac']}; MRE accept 0.99.")
    L.append(f"- Export: opset 17, `torch.onnx.export(dynamo=False)`; ONNX Runtime vs PyTorch max abs difference "
             f"{exp['marknet_max_abs_diff']:.2g} (Marknet raw logits, 2 random inputs), "
             f"{exp.get('mre_max_abs_diff', float('nan')):.2g} (MRE score).\n")
    L.append("## Data\n")
    L.append(f"- Dataset: `{meta['data_root']}` — metadata `dataset` = \"{meta['dataset']}\".")
    L.append(f"- Marknet: random {a['crop']}x{a['crop']} crops of the training split's images (left and right "
             f"views; {meta['dataset'].split('images=')[-1]} images held in memory), half sampled exactly as at "
             + ("inference under the auto layout (isotropic scale for the image's true marker pitch)"
                if meta.get("aug", {}).get("canonical", "stretch") == "auto"
                else "the first contract's inference (whole image resized to 416x416)")
             + ", half with marker pitch 9-44 px at the input, "
             "anisotropic scale, flips, +-8 deg rotation; photometric augmentation on 70% "
             "(colour gains, contrast, gamma, colour shading, grey, polarity, blur, noise, JPEG)."
             + (f" {a['p_contact']:.0%} of crops centred within a quarter crop of a marker in contact (images "
                "with contact; the others anywhere)." if a.get("p_contact") else ""))
    rc = mre_meta.get("raw_counts", {})
    rep = mre_meta.get("report", {})
    L.append(f"- MRE: {rc.get('candidates')} uncertain candidates (0.1 < c <= 0.4) from the validation split "
             f"(clean + augmented copies): {rc.get('correct')} correct, {rc.get('wrong')} wrong; balanced 1:1 to "
             f"{rep.get('samples')} samples; held-out accuracy {rep.get('holdout_accuracy')}, precision of what it "
             f"accepts at 0.99: {rep.get('holdout_precision_at_0.99')}.\n")
    L.append("## Training\n")
    machine = (run / "machine.txt").read_text().strip() if (run / "machine.txt").exists() else "see notes"
    L.append(f"- Marknet: {meta['steps']} steps of batch {a['batch']} in {meta['train_seconds'] / 60:.1f} min "
             f"wall clock, {a['threads']} threads, AdamW lr {a['lr']} (warm-up, cosine), loss alpha "
             f"{a['alpha']} x BCE + beta {a['beta']} x Euclidean distance; MRE {mre_meta.get('seconds')} s "
             f"(data + training).")
    def from_train(path: str) -> str:  # checkpoints under train/ named as the commands here run (from train/)
        return path.split("/train/", 1)[1] if "/train/" in path else path

    chain, init = [], meta.get("init")
    while init:  # warm starts: the runs whose weights this one continued
        chain.append(init)
        init = init.get("init")
    if chain:
        steps = meta["steps"] + sum(c.get("steps") or 0 for c in chain)
        minutes = (meta["train_seconds"] + sum(c.get("train_seconds") or 0 for c in chain)) / 60
        L.append("- Warm start: continued from " + ", which continued from ".join(
            f"`{from_train(c['path'])}` ({c.get('steps')} steps, {(c.get('train_seconds') or 0) / 60:.1f} min, trained "
            f"{c.get('trained')})" for c in chain) + f"; {steps} steps and {minutes:.1f} min of training in all.")
    L.append(f"- Machine: {machine}\n")
    L.append("Exact commands (from `train/`):\n")
    L.append("```sh")
    canonical = a.get("canonical", meta.get("aug", {}).get("canonical"))
    opts = (f" --stem {a['stem']}" if "stem" in a else "") + (f" --canonical {canonical}" if canonical else "")
    opts += f" --lr {a['lr']}" if a.get("lr") != 3e-3 else ""
    opts += f" --init {from_train(a['init'])}" if a.get("init") else ""
    opts += f" --p-contact {a['p_contact']}" if a.get("p_contact") else ""
    L.append(f"../.venv/bin/python -m gelstereo_train.train_marknet --data {meta['data_root']} --out RUN/marknet.pt "
             f"--minutes {a['minutes']} --threads {a['threads']} --seed {a['seed']}{opts}")
    L.append(f"../.venv/bin/python -m gelstereo_train.train_mre --data {meta['data_root']} --marknet RUN/marknet.pt "
             "--out RUN/mre.pt")
    L.append("../.venv/bin/python -m gelstereo_train.export --marknet RUN/marknet.pt --mre RUN/mre.pt "
             "--out-dir ../data/models")
    L.append(f"../.venv/bin/python -m gelstereo_train.evaluate --data {meta['data_root']} --split test "
             "--marknet ../data/models/marknet.onnx --mre ../data/models/mre.onnx"
             + (f" --max-images {ev['max_images']}" if ev.get("max_images") else ""))
    L.append("```")
    L.append("`train/retrain.sh DATA RUN` runs all of it (and simulates first when DATA is empty).\n")
    L.append("## Test metrics (simulated test split, exported ONNX models)\n")
    rad = ev["marknet"].get("radius_px", {})
    L.append(f"{ev['images']} test images; a prediction is correct when matched one-to-one, nearest first, within "
             f"r = 0.25 x pitch (median r {rad.get('median', float('nan')):.2f} px, {rad.get('min', 0):.2f}-"
             f"{rad.get('max', 0):.2f}); loss = mean squared distance of correct points, original px^2. hard = "
             "markers the tuned blob baseline misses or misplaces (`train/gelstereo_train/blob_params.json`).\n")
    L.append(format_table(ev) + "\n")
    if ev.get("in_range", {}).get("marknet"):
        ir = ev["in_range"]
        L.append(f"The same, restricted to the design range ({ir['rule']}): {ir['images']} of {ev['images']} "
                 "test images.\n")
        L.append(format_table(ir) + "\n")
    if (run / "real_check.json").exists():
        r = json.loads((run / "real_check.json").read_text())
        L.append("## Zero-shot on a real sensor\n")
        L.append(f"`{Path(r['video']).name}` (GelSight Mini, 320x240, 80 markers), frames {r['frame_range']}: "
                 f"all {r['expected']} found (and the same ones as in the first frame) in "
                 f"{r['frames_with_all_found']} of {r['frames']} frames; Marknet + MRE count "
                 f"{r['marknet_mre_count_min']}-{r['marknet_mre_count_max']}, Marknet alone "
                 f"{r['marknet_count_min']}-{r['marknet_count_max']}, blob baseline "
                 f"{r['blob_count_min']}-{r['blob_count_max']} per frame.\n")
    if args.notes and args.notes.exists():
        L.append("## Notes\n")
        L.append(args.notes.read_text().strip() + "\n")
    card = models / "MODEL_CARD.md"
    # Sections other trainers append (the YOLOv3 baseline's) are kept.
    if card.exists():
        old = card.read_text()
        at = old.find("\n## `yolo.onnx`")
        if at >= 0:
            L.append(old[at + 1 :].rstrip() + "\n")
    card.write_text("\n".join(L))
    print(f"wrote {models / 'MODEL_CARD.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
