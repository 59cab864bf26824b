"""Shared fixtures: a tiny dataset in the exact `gelstereo simulate` layout (rendered dots), and the
scripts of `train/scripts/` loaded as modules."""

import importlib.util
from pathlib import Path

import pytest
import torch

from gelstereo_train.tinydata import write_tiny_dataset

torch.set_num_threads(2)


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("tiny"), size_hw=(120, 160), pitch_px=14.0, frames=2)


@pytest.fixture(scope="session")
def script():
    """Loads `train/scripts/NAME.py` as a module (the scripts are no package)."""

    def load(name: str):
        path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
