"""The element-wise mean of Marknet checkpoints of one architecture, written as a checkpoint.

    cd train && ../.venv/bin/python scripts/average_checkpoints.py RUN/a.pt RUN/b.pt --out RUN/soup.pt

Two fine-tunes from one start (say, one on every look and one on the reference look alone) often
land, averaged, between their strengths. The result exports as any checkpoint
(`python -m gelstereo_train.export --marknet RUN/soup.pt ...`); its meta names each source.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelstereo_train.train_marknet import average_checkpoints, save_checkpoint  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoints", nargs="+", type=Path, help="Marknet checkpoints (.pt), one architecture")
    p.add_argument("--out", type=Path, required=True, help="checkpoint to write (.pt)")
    args = p.parse_args(argv)
    model, meta = average_checkpoints(args.checkpoints)
    save_checkpoint(args.out, model, meta)
    print(f"{args.out}: mean of {len(args.checkpoints)} checkpoints")
    return 0


if __name__ == "__main__":
    sys.exit(main())
