"""Generate the tiny ONNX fixtures for the Rust tests of gelstereo-markers.

    cd train && ../.venv/bin/python scripts/make_onnx_fixtures.py [--out ../data/fixtures/onnx]

Writes (all small, deterministic from the seeds below):
- ``marknet_tiny.onnx``: a Marknet with random weights (stride 8, m = 2, width 2, input 64 x 64, so the
  grid is 8 x 8), exported exactly like the shipped model (names, opset 17, dynamic batch,
  metadata_props of docs/model-contract.md). BatchNorm statistics are randomised and the head bias is
  shifted so that the confidences straddle the thresholds 0.1 / 0.2 / 0.4.
- ``mre_tiny.onnx``: an MRE with random weights whose output bias puts scores around the 0.99 cut.
- ``dots_64x64.png`` (no resize needed: checks the network itself) and ``dots_80x60.png`` (resized to
  64 x 64: checks the preprocessing too), rendered dots.
- ``marknet_tiny_auto.onnx``, ``dots_160x120.png``, ``expected_auto.json``: the same network with a dynamic
  input (contract gelstereo-marknet/2) and the expected "auto" fit (layouts and two-pass results).
- ``expected.json``: for each image the raw output (flat, [Gy, Gx, m, 3] row-major), the decoded
  candidates in original pixels (flat order), and the full post-processing result (pitch, kept
  candidates, Marknet-only output, MRE features and scores, Marknet + MRE output); plus MRE scores
  for a few hand-written feature rows. Tolerances are stated in the file.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gelstereo_train.export import export_marknet, export_mre, marknet_metadata, mre_metadata  # noqa: E402
from gelstereo_train.model import MRE, Marknet  # noqa: E402
from gelstereo_train.evaluate import MarknetRunner  # noqa: E402
from gelstereo_train.postprocess import (  # noqa: E402
    FitConfig,
    Layout,
    PostConfig,
    decode_to_original,
    fit_layout,
    postprocess,
    preprocess,
)
from gelstereo.postprocess import probe_layout  # noqa: E402
from gelstereo_train.tinydata import grid_points, render_dots  # noqa: E402

INPUT_HW = (64, 64)
# The contract's defaults, except a larger de-duplication radius so that the random net's candidates
# exercise it (the value is stored in the fixture's metadata_props like any model's).
# The contract's steps alone: a random network's candidates form no marker lattice.
FIXTURE_POST = PostConfig(dedup_radius_frac=0.6, lattice=None)


def build_models():
    torch.manual_seed(1234)
    net = Marknet(stride=8, candidates=2, width=2)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 1.5)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.2, 0.2)
        net.head.weight.normal_(0.0, 1.5)
        b = net.head.bias.view(2, 3)
        b[:, :2] = 0.0
        b[:, 2] = -1.5
    net.eval()
    # Calibrate the confidence logits on a rendered image: spread ~1.5, centred at logit(0.2), so the
    # thresholds 0.1 / 0.2 / 0.4 all cut through the candidates.
    pts, _, _ = grid_points(64, 64, 11.0, 5, 5)
    x = preprocess(render_dots(64, 64, pts, 3.3, np.random.default_rng(0)), INPUT_HW)
    with torch.no_grad():
        tc = net(x)[..., 2]
        w = net.head.weight.view(2, 3, -1)
        b = net.head.bias.view(2, 3)
        raw0 = net(x)
        for k in range(2):
            for j in range(2):  # positions: spread the sigmoid over the cell
                sj = 1.5 / float(raw0[..., k, j].std())
                w[k, j] *= sj
                b[k, j] = b[k, j] * sj - float(raw0[..., k, j].mean()) * sj
            scale = 1.5 / float(tc[..., k].std())
            w[k, 2] *= scale
            b[k, 2] = b[k, 2] * scale - float(tc[..., k].mean()) * scale + float(np.log(0.2 / 0.8))
    torch.manual_seed(99)
    mre = MRE().eval()
    # Centre the scores of this image's MRE features at the 0.99 cut, spread ~2 logits.
    with torch.no_grad():
        raw = net(x).numpy()[0]
    det = postprocess(decode_to_original(raw, 8, (64, 64), (64, 64)), FIXTURE_POST, None)
    with torch.no_grad():
        f = torch.from_numpy(det.mre_features)
        z = mre(f)[:, 0]
        mre.net[-1].weight.mul_(2.0 / float(z.std()))
        z = mre(f)[:, 0]
        print(f"MRE calibration on {len(f)} features: logit std {float(z.std()):.2f}")
        mre.net[-1].bias.add_(float(np.log(0.99 / 0.01)) - float(z.quantile(0.3)))
    return net, mre


def write_auto_fixture(net, out: Path, post: PostConfig, mre_fn, rng) -> None:
    """The "auto" fit (contract gelstereo-marknet/2): the same network exported with a dynamic input as
    ``marknet_tiny_auto.onnx``; ``expected_auto.json`` holds fit_layout for a table of sizes and pitches,
    probe_layout for a table of sizes and, per image, the first-pass layout, the final layout and the
    post-processed output of the multi-pass fit (no pitch remembered), as the Rust localizer's passes compute them (MarknetRunner)."""
    fit = FitConfig(nominal_hw=INPUT_HW)
    md = marknet_metadata(net, INPUT_HW, "fixture: random weights (train/scripts/make_onnx_fixtures.py)",
                          "2026-11-22T00:00:00Z", post, fit=fit)
    path = out / "marknet_tiny_auto.onnx"
    diff = export_marknet(net, path, INPUT_HW, md)
    pts, _, _ = grid_points(120, 160, 26.0, 4, 6)
    img = render_dots(120, 160, pts + rng.uniform(-1, 1, pts.shape), 26.0 * 0.3, rng)
    Image.fromarray(img).save(out / "dots_160x120.png")
    runner = MarknetRunner(path, threads=1, post=post)
    lay_dict = lambda lay: Layout(*lay)._asdict()  # noqa: E731
    cases = []
    for w, h in ((640, 480), (320, 240), (800, 600), (64, 64), (1280, 720), (5000, 40)):
        for pitch in (None, 5.0, 10.0, 16.0, 31.0, 200.0):
            cases.append({"width": w, "height": h, "pitch_px": pitch,
                          "layout": lay_dict(fit_layout(w, h, pitch, FitConfig()))})
    stretch_cases = []
    for w, h in ((640, 480), (320, 240), (800, 600), (416, 416), (1280, 720)):
        for pitch in (None, 5.0, 10.0, 16.0, 31.0):
            stretch_cases.append({"width": w, "height": h, "pitch_px": pitch,
                                  "layout": lay_dict(fit_layout(w, h, pitch, FitConfig(prefer_stretch=True)))})
    probe_cases = []
    for w, h in ((640, 480), (320, 240), (800, 600), (64, 64), (1280, 720), (2000, 1500), (5000, 40), (40, 5000)):
        probe_cases.append({"width": w, "height": h, "layout": lay_dict(probe_layout(w, h, FitConfig()))})
    auto = {
        "generator": "train/scripts/make_onnx_fixtures.py",
        "tolerance": "positions 0.05 px, conf 0.01 (resize implementations differ by rounding)",
        "export_max_abs_diff": diff,
        "fit_layout_nominal_416": cases,
        "fit_layout_nominal_416_prefer_stretch": stretch_cases,
        "probe_layout_nominal_416": probe_cases,
        "images": {},
    }
    for name in ("dots_80x60.png", "dots_160x120.png"):
        im = np.asarray(Image.open(out / name).convert("RGB"))
        first = runner.layout(im)
        dec, final = runner.fitted(im)
        det = postprocess(dec, post, mre_fn)
        auto["images"][name] = {
            "first_layout": lay_dict(first),
            "final_layout": lay_dict(final),
            "pitch_px": det.pitch_px,
            "marknet": _round(det.marknet),
            "marknet_mre": _round(det.marknet_mre),
        }
        print(f"{name}: auto fit {first} -> {final}, marknet {len(det.marknet)}")
    (out / "expected_auto.json").write_text(json.dumps(auto, indent=1) + "\n")


def _round(a, nd=6):
    return np.round(np.asarray(a, dtype=np.float64), nd).tolist()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[2] / "data" / "fixtures" / "onnx")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    net, mre = build_models()
    post = FIXTURE_POST
    md = marknet_metadata(net, INPUT_HW, "fixture: random weights (train/scripts/make_onnx_fixtures.py)",
                          "2026-11-22T00:00:00Z", post, dynamic=False)
    d_mk = export_marknet(net, out / "marknet_tiny.onnx", INPUT_HW, md, dynamic=False)
    d_mre = export_mre(mre, out / "mre_tiny.onnx", mre_metadata("fixture: random weights", post))

    rng = np.random.default_rng(7)
    images = {}
    for name, (h, w), pitch in (("dots_64x64.png", (64, 64), 11.0), ("dots_80x60.png", (60, 80), 13.0)):
        pts, _, _ = grid_points(h, w, pitch, int(h // pitch), int(w // pitch))
        img = render_dots(h, w, pts + rng.uniform(-1, 1, pts.shape), pitch * 0.3, rng)
        Image.fromarray(img).save(out / name)
        images[name] = np.asarray(Image.open(out / name).convert("RGB"))

    mre_fn = lambda f: torch.sigmoid(mre(torch.from_numpy(f))).detach().numpy()[:, 0]  # noqa: E731
    expected = {
        "generator": "train/scripts/make_onnx_fixtures.py",
        "tolerance": {
            "raw_64x64": "1e-4 abs (same input; float32 kernels differ)",
            "raw_80x60": "0.05 abs on logits, positions 0.05 px, conf 0.01 (resize implementations differ by "
            "rounding: bilinear half-pixel, no antialiasing)",
            "mre_score": "1e-5 abs",
        },
        "export_max_abs_diff": {"marknet": d_mk, "mre": d_mre},
        "marknet_metadata": {k: str(v) for k, v in md.items()},
        "post": {
            "conf_keep": post.conf_keep,
            "conf_low": post.conf_low,
            "conf_marknet_only": post.conf_marknet_only,
            "dedup_radius_frac": post.dedup_radius_frac,
            "accept": post.accept,
        },
        "images": {},
    }
    for name, img in images.items():
        x = preprocess(img, INPUT_HW)
        with torch.no_grad():
            raw = net(x).numpy()[0]
        dec = decode_to_original(raw, net.stride, (img.shape[1], img.shape[0]), INPUT_HW[::-1])
        det = postprocess(dec, post, mre_fn)
        expected["images"][name] = {
            "width": img.shape[1],
            "height": img.shape[0],
            "raw_shape": list(raw.shape),
            "raw": _round(raw.reshape(-1)),
            "decoded": _round(dec),
            "pitch_px": det.pitch_px,
            "kept": _round(det.candidates),
            "marknet": _round(det.marknet),
            "mre_features": _round(det.mre_features),
            "mre_scores": _round(det.mre_scores, 8),
            "marknet_mre": _round(det.marknet_mre),
        }
        c = dec[:, 2]
        print(f"{name}: c>0.1 {int((c > 0.1).sum())}, c>0.2 {int((c > 0.2).sum())}, c>0.4 {int((c > 0.4).sum())}, "
              f"kept {len(det.candidates)}, marknet {len(det.marknet)}, mre in {len(det.mre_index)}, "
              f"removed by dedup {int((c > 0.1).sum()) - len(det.candidates)}, "
              f"accepted {int((det.mre_scores > post.accept).sum())}, final {len(det.marknet_mre)}")
    feats = np.array(
        [[1.0] * 4 + [1.4] * 4 + [2.0, 2.2, 0.3], [0.1] + [1.0] * 9 + [0.15], [4.0] * 10 + [0.35]], np.float32
    )
    expected["mre_rows"] = {"features": _round(feats), "scores": _round(mre_fn(feats), 8)}
    (out / "expected.json").write_text(json.dumps(expected, indent=1) + "\n")
    write_auto_fixture(net, out, post, mre_fn, rng)
    total = sum(f.stat().st_size for f in out.iterdir())
    print(f"wrote {out} ({total / 1024:.0f} KB); export diffs marknet {d_mk:.2g} mre {d_mre:.2g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
