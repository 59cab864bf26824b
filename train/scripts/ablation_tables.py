"""Render Tables II and III (markdown) from the JSON reports of scripts/ablation.sh."""

import json
import sys
from pathlib import Path


def row(label, res):
    out = []
    for split in ("hard", "easy", "contact"):
        m = res["marknet"][split] if "marknet" in res else {"precision": float("nan"), "recall": float("nan"),
                                                               "loss_px2": float("nan")}
        out.append(f"| {split} | {label} | {100 * m['precision']:.2f}% | {100 * m['recall']:.2f}% | {m['loss_px2']:.3f} |")
    return out


def main():
    d = Path(sys.argv[1])
    steps, ntest = sys.argv[2], sys.argv[3]
    head = ["| split | {} | precision | recall | loss (px^2) |", "|---|---|---|---|---|"]
    r = None
    for scope in ("whole", "in_range"):
        for title, key, cfgs in (
            ("Table II: grid S (m = 5)", "S x S", [("S13_m5", "13x13"), ("S26_m5", "26x26"), ("S52_m5", "52x52")]),
            ("Table III: candidates m (S = 52)", "m", [(f"S52_m{m}", str(m)) for m in range(1, 6)]),
        ):
            rows = []
            note = ""
            for name, label in cfgs:
                p = d / f"{name}.json"
                if p.exists():
                    r = json.loads(p.read_text())
                    res = r if scope == "whole" else r["in_range"]
                    note = (f"{r['images']} test images" if scope == "whole"
                            else f"{res['images']} of {r['images']} test images in the design range ({res['rule']})")
                    rows.append(row(label, res))
            print(f"\n{title}; Marknet only (c > 0.2), {steps} steps x batch 32 each; {note}\n")
            print(head[0].format(key))
            print(head[1])
            for split in range(3):
                for rr in rows:
                    print(rr[split])
    if r is not None:
        print(f"\nr = 0.25 x pitch: median {r['marknet']['radius_px']['median']:.2f} px")


if __name__ == "__main__":
    main()
