"""Where training runs and how its batches are made.

Cropping and augmenting a batch (gelstereo_train.augment) costs a few milliseconds of CPU per image,
so one process cannot feed a GPU: with ``workers > 0`` the batches are made by that many worker
processes (torch's DataLoader, forked, so the decoded images are shared rather than copied), each
with its own random stream. ``workers == 0`` makes them in the training process from the caller's
generator, exactly as before, so a seeded CPU run stays reproducible.
"""

from __future__ import annotations

import argparse
from typing import Callable, Iterator

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info


def add_device_args(p: argparse.ArgumentParser) -> None:
    """--device and --workers, for the trainers that honour them (Marknet, adaptation)."""
    p.add_argument("--device", default="auto",
                   help="auto (a CUDA GPU when PyTorch sees one, else the CPU), cpu, or cuda[:N]")
    p.add_argument("--workers", type=int, default=0,
                   help="processes that make the augmented batches (0: the training process, reproducible "
                   "from --seed; with a GPU use about one per CPU core)")


def pick_device(name: str) -> torch.device:
    """``auto``: the first CUDA device when there is one, else the CPU; ``cpu`` / ``cuda`` as asked,
    refusing ``cuda`` on a machine without one."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit(f"--device {name}: this PyTorch sees no CUDA device (use --device cpu or auto)")
    return torch.device(name)


def describe(device: torch.device) -> str:
    """The device in words for the log and the checkpoint: ``cpu`` or ``cuda (NVIDIA H200)``."""
    if device.type == "cuda":
        return f"cuda ({torch.cuda.get_device_name(device)})"
    return device.type


class _EndlessBatches(IterableDataset):
    """An endless stream of ``make(rng)`` with a random stream per worker, seeded by (seed, worker)."""

    def __init__(self, make: Callable[[np.random.Generator], tuple], seed: int):
        self.make = make
        self.seed = seed

    def __iter__(self):
        info = get_worker_info()
        worker = 0 if info is None else info.id
        torch.set_num_threads(1)  # the workers are the parallelism; more threads each only contend
        rng = np.random.default_rng([self.seed, worker])
        while True:
            yield self.make(rng)


def _as_is(batch):
    return batch


def batch_stream(make: Callable[[np.random.Generator], tuple], rng: np.random.Generator, workers: int,
                 seed: int, pin_memory: bool = False) -> Iterator[tuple]:
    """Batches ``make(rng)`` forever: in this process from ``rng`` when ``workers`` is 0, else from
    ``workers`` forked processes (a few batches each made ahead)."""
    if workers < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    if workers == 0:
        while True:
            yield make(rng)
    loader = DataLoader(_EndlessBatches(make, seed), batch_size=None, num_workers=workers, collate_fn=_as_is,
                        pin_memory=pin_memory, prefetch_factor=4, persistent_workers=True,
                        multiprocessing_context="fork")
    yield from loader
