"""Dataset views per family: for every family a split's experiments carry (their `meta.json`
`families`, written by `gelstereo simulate --randomization wide`), a folder holding the dataset's
`dataset.json` and links to that family's experiments, which `gelstereo eval --dataset VIEW` scores
alone. A view named `all` holds every experiment of the split.

    python scripts/family_views.py --data WIDE --out VIEWS [--split test]
    gelstereo eval --dataset VIEWS/marker_hue --methods marknet-mre --frame-step 4

Folder names replace `:` by `_`, `<` by `lt` and `>` by `gt` (`pitch:<16` -> `pitch_lt16`). Prints
each family with its number of experiments.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from collections import defaultdict
from pathlib import Path


def folder_name(family: str) -> str:
    return family.replace(":", "_").replace("<", "lt").replace(">", "gt")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="dataset written by gelstereo simulate")
    p.add_argument("--out", type=Path, required=True, help="folder for the views (created)")
    p.add_argument("--split", default="test")
    args = p.parse_args(argv)
    experiments = sorted((args.data / args.split).glob("*/meta.json"))
    if not experiments:
        print(f"error: {args.data / args.split} holds no experiment with a meta.json", file=sys.stderr)
        return 1
    families: dict[str, list[Path]] = defaultdict(list)
    for meta in experiments:
        exp = meta.parent.resolve()
        families["all"].append(exp)
        for family in json.loads(meta.read_text()).get("families", []):
            families[family].append(exp)
    for family, exps in sorted(families.items()):
        view = args.out / folder_name(family)
        (view / args.split).mkdir(parents=True, exist_ok=True)
        shutil.copy(args.data / "dataset.json", view / "dataset.json")
        for exp in exps:
            link = view / args.split / exp.name
            if not link.exists():
                link.symlink_to(exp)
        print(f"{family} {len(exps)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
