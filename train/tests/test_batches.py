"""Batches made by worker processes: every worker draws its own crops, and a training run fed by
them ends with a checkpoint that records where it ran."""

from pathlib import Path

import numpy as np
import pytest
import torch

from gelstereo_train import train_marknet
from gelstereo_train.augment import AugConfig, make_batch
from gelstereo_train.batches import batch_stream, pick_device
from gelstereo_train.data import list_samples, median_nn_distance


def _maker(tiny_root):
    s = list_samples(tiny_root, "train")
    imgs = [a.load() for a in s]
    pts = [a.points_px.astype(np.float32) for a in s]
    pitches = np.array([median_nn_distance(p) for p in pts])
    cfg = AugConfig(crop=(64, 64), input_size=(128, 128))
    return lambda rng: make_batch(imgs, pts, pitches, 2, cfg, rng)


def test_in_process_batches_follow_the_callers_generator(tiny_root):
    make = _maker(tiny_root)
    torch.manual_seed(1)  # the sensor noise comes from torch's generator
    a = next(batch_stream(make, np.random.default_rng(5), 0, seed=0))[0]
    torch.manual_seed(1)
    b = make(np.random.default_rng(5))[0]
    assert torch.equal(a, b)


def test_worker_batches_are_well_formed_and_not_repeated(tiny_root):
    stream = batch_stream(_maker(tiny_root), np.random.default_rng(0), 2, seed=3)
    batches = [next(stream) for _ in range(6)]
    for x, labels in batches:
        assert x.shape == (2, 3, 64, 64) and len(labels) == 2
        assert all(isinstance(p, np.ndarray) and p.shape[1] == 2 for p in labels)
    xs = [x for x, _ in batches]
    # two workers seeded (3, 0) and (3, 1): no batch may repeat another
    assert all(not torch.equal(xs[i], xs[j]) for i in range(6) for j in range(i + 1, 6))


def test_a_run_fed_by_workers_writes_a_checkpoint_that_names_its_device(tiny_root, tmp_path):
    ck = tmp_path / "marknet.pt"
    args = train_marknet.parser().parse_args(
        ["--data", str(tiny_root), "--out", str(ck), "--steps", "4", "--batch", "2", "--crop", "64",
         "--input-size", "128", "--width", "4", "--candidates", "3", "--workers", "2", "--device", "cpu"])
    train_marknet.train(args, log=lambda *_: None)
    meta = torch.load(ck, map_location="cpu", weights_only=False)["meta"]
    assert meta["steps"] == 4 and meta["device"] == "cpu" and meta["args"]["workers"] == 2


def test_asking_for_a_missing_gpu_is_refused_by_name(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit, match="--device cuda"):
        pick_device("cuda")
    assert pick_device("auto").type == "cpu"


def test_a_run_with_photometric_augmentation_on_the_device_trains_and_records_it(tiny_root, tmp_path):
    ck = tmp_path / "marknet.pt"
    args = train_marknet.parser().parse_args(
        ["--data", str(tiny_root), "--out", str(ck), "--steps", "3", "--batch", "2", "--crop", "64",
         "--input-size", "128", "--width", "4", "--candidates", "3", "--workers", "1", "--device", "cpu",
         "--augment-on", "device"])
    train_marknet.train(args, log=lambda *_: None)
    meta = torch.load(ck, map_location="cpu", weights_only=False)["meta"]
    assert meta["steps"] == 3 and meta["args"]["augment_on"] == "device"
    assert np.isfinite(meta["final_loss"])
    # where the run's time went: the share spent waiting for the batch makers
    assert 0.0 <= meta["batch_wait_fraction"] <= 1.0


def test_forked_batch_makers_compress_jpeg_after_the_parent_did(tiny_root):
    """The JPEG round trips run on a thread pool; a batch maker forked after the training process
    made one must make its own (a fork inherits the pool without its threads, and would wait on it
    forever). Run in a child process with a time limit, so that a regression fails instead of hanging."""
    import subprocess
    import sys

    script = f"""
import numpy as np, torch
from gelstereo_train.augment import AugConfig, make_batch, photometric
from gelstereo_train.batches import batch_stream
from gelstereo_train.data import list_samples, median_nn_distance
cfg = AugConfig(crop=(64, 64), input_size=(128, 128), p_clean=0.0, p_jpeg=1.0)
photometric(torch.rand(2, 3, 64, 64), cfg, np.random.default_rng(0))
s = list_samples({str(tiny_root)!r}, "train")
imgs = [a.load() for a in s]
pts = [a.points_px.astype(np.float32) for a in s]
pitches = np.array([median_nn_distance(p) for p in pts])
stream = batch_stream(lambda r: make_batch(imgs, pts, pitches, 2, cfg, r), np.random.default_rng(1), 1, seed=2)
x, labels = next(stream)
print("batch", tuple(x.shape))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                          cwd=str(Path(__file__).resolve().parents[1]))
    assert done.returncode == 0, done.stderr
    assert "batch (2, 3, 64, 64)" in done.stdout


def test_a_crop_that_is_no_multiple_of_32_is_refused_before_any_work(tmp_path):
    args = train_marknet.parser().parse_args(
        ["--data", str(tmp_path / "absent"), "--out", str(tmp_path / "m.pt"), "--crop", "100"])
    with pytest.raises(SystemExit, match="--crop 100: expected a positive multiple of 32"):
        train_marknet.train(args, log=lambda *_: None)
