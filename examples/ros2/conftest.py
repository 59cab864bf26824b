"""The `gelstereo` binary of this checkout for the ROS 2 node's tests (built by cargo when missing or
stale, as crates/gelstereo-py/tests does); `GELSTEREO_BIN` names another."""

import json
import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def gelstereo_bin() -> Path:
    if os.environ.get("GELSTEREO_BIN"):
        return Path(os.environ["GELSTEREO_BIN"])
    # Ask cargo where it put the binary: CI builds into a shared CARGO_TARGET_DIR, not ./target.
    built = subprocess.run(
        ["cargo", "build", "--quiet", "--locked", "-p", "gelstereo-cli", "--bin", "gelstereo",
         "--message-format=json"],
        cwd=ROOT, check=True, capture_output=True, text=True,
    )
    for line in built.stdout.splitlines():
        message = json.loads(line)
        if message.get("reason") == "compiler-artifact" and Path(message.get("executable") or "").name == "gelstereo":
            return Path(message["executable"])
    raise RuntimeError("cargo built no gelstereo executable:\n" + built.stdout[-2000:])
