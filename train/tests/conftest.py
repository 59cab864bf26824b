"""Shared fixtures: a tiny dataset in the exact `gelstereo simulate` layout (rendered dots)."""

import pytest
import torch

from gelstereo_train.tinydata import write_tiny_dataset

torch.set_num_threads(2)


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("tiny"), size_hw=(120, 160), pitch_px=14.0, frames=2)
