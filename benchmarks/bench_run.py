"""Run one `physicsrl-bench NAME key=value ...` in a scratch directory; return its JSON record."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path


def bench_record(name: str, *overrides: str) -> dict:
    """The record (``command``, ``rows``, ``goals``) that ``physicsrl-bench NAME`` writes."""
    bench = Path(sys.executable).with_name("physicsrl-bench")
    with tempfile.TemporaryDirectory() as directory:
        command = [str(bench), name, *overrides, f"hydra.run.dir={directory}"]
        subprocess.run(command, check=True, capture_output=True, text=True)
        return json.loads((Path(directory) / f"{name}.json").read_text())
