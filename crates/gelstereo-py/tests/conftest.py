"""Shared fixtures of the gelstereo Python package tests: the checkout, the sample recording, the
`gelstereo` binary of this checkout (built by cargo when missing or stale)."""

import json
import os
import subprocess
from pathlib import Path

import cv2
import pytest

ROOT = Path(__file__).resolve().parents[3]
SAMPLE = ROOT / "data" / "sample" / "press-slide"


@pytest.fixture(scope="session")
def sample() -> Path:
    return SAMPLE


@pytest.fixture(scope="session")
def left_bgr():
    """The sample recording's first left view as OpenCV reads it (HxWx3 uint8 BGR)."""
    image = cv2.imread(str(SAMPLE / "left" / "000000.jpg"), cv2.IMREAD_COLOR)
    assert image is not None
    return image


@pytest.fixture(scope="session")
def gelstereo_bin() -> Path:
    """The `gelstereo` binary built from this checkout (debug profile, as `cargo test` builds it);
    `GELSTEREO_BIN` names another."""
    if os.environ.get("GELSTEREO_BIN"):
        return Path(os.environ["GELSTEREO_BIN"])
    # Ask cargo where it put the binary: CI builds into a shared CARGO_TARGET_DIR, not ./target.
    built = subprocess.run(
        ["cargo", "build", "--quiet", "--locked", "-p", "gelstereo-cli", "--bin", "gelstereo",
         "--message-format=json"],
        cwd=ROOT,
        check=True,
        capture_output=True,
        text=True,
    )
    for line in built.stdout.splitlines():
        message = json.loads(line)
        if message.get("reason") == "compiler-artifact" and message.get("executable"):
            if Path(message["executable"]).name == "gelstereo":
                return Path(message["executable"])
    raise RuntimeError("cargo built no gelstereo executable:\n" + built.stdout[-2000:])
