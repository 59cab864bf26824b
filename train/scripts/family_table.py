"""Precision / recall per model and family from `gelstereo eval` reports: one markdown table over all
markers and one over the markers in contact (as in docs/experiments/localization-families.md, "Leave one family out").

    python scripts/family_table.py --eval EVAL --models with no_hue --views marker_hue all

Reads EVAL/MODEL/VIEW/table1.json (Marknet-MRE's rows) and prints P / R in %, each view's marker
count in the header.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

SPLITS = ("all", "contact")


def split_row(report: dict, split: str) -> dict:
    for row in report["results"]:
        if row["split"] == split and row["method"] == "marknet-mre":
            return row
    raise SystemExit(f"no marknet-mre row of split '{split}' in the report")


def table(eval_dir: Path, models: list[str], views: list[str], split: str) -> list[str]:
    reports = {(m, v): json.loads((eval_dir / m / v / "table1.json").read_text()) for m in models for v in views}
    counts = [split_row(reports[models[0], v], split)["markers"] for v in views]
    lines = ["| model | " + " | ".join(f"{v} ({n:,})" for v, n in zip(views, counts)) + " |",
             "|---|" + "---|" * len(views)]
    for m in models:
        cells = [split_row(reports[m, v], split) for v in views]
        lines.append(f"| {m} | " + " | ".join(f"{100 * c['precision']:.2f} / {100 * c['recall']:.2f}"
                                             for c in cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--eval", type=Path, required=True, help="folder of EVAL/MODEL/VIEW/table1.json")
    p.add_argument("--models", nargs="+", required=True)
    p.add_argument("--views", nargs="+", required=True)
    args = p.parse_args(argv)
    missing = [f"{m}/{v}" for m in args.models for v in args.views
               if not (args.eval / m / v / "table1.json").is_file()]
    if missing:
        print(f"error: {args.eval}: no table1.json for {', '.join(missing)}", file=sys.stderr)
        return 1
    for split in SPLITS:
        print(f"\n{split} markers, P / R in %:\n")
        print("\n".join(table(args.eval, args.models, args.views, split)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
