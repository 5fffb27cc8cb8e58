"""Run one `physicsrl-bench NAME key=value ...` in a scratch directory; return its JSON record."""

from __future__ import annotations

import argparse
import csv
import json
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path


def bench_record(name: str, *overrides: str) -> dict:
    """The record (``command``, ``rows``, ``goals``) that ``physicsrl-bench NAME`` writes."""
    bench = Path(sys.executable).with_name("physicsrl-bench")
    with tempfile.TemporaryDirectory() as directory:
        command = [str(bench), name, *overrides, f"hydra.run.dir={directory}"]
        result = subprocess.run(command, capture_output=True, text=True)
        if result.returncode:  # its one line (a bad setting) or its traceback, and its status
            sys.stderr.write(result.stderr)
            raise SystemExit(result.returncode)
        return json.loads((Path(directory) / f"{name}.json").read_text())


def at_least(low: int):
    """An argparse type: an integer >= ``low`` (argparse names the argument and exits 2)."""

    def integer(text: str) -> int:
        if not text.lstrip("-").isdigit() or int(text) < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {text!r}")
        return int(text)

    return integer


RESULTS = Path(__file__).resolve().parent / "results"


def save_results(name: str, rows: list[dict], figure, lines: list[str]) -> None:
    """Write results/NAME.csv (rows), NAME.png (figure) and NAME.txt (the command, then
    ``lines``), and print the summary."""
    RESULTS.mkdir(exist_ok=True)
    with open(RESULTS / f"{name}.csv", "w", newline="") as stream:
        writer = csv.DictWriter(stream, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
        writer.writeheader()
        writer.writerows(rows)
    figure.tight_layout()
    figure.savefig(RESULTS / f"{name}.png", dpi=120)
    save_summary(name, lines)


def save_summary(name: str, lines: list[str]) -> None:
    """Write results/NAME.txt (the command, then ``lines``) and print it."""
    command = shlex.join(["python", *sys.argv])
    summary = "\n".join([f"command: {command}", *lines])
    (RESULTS / f"{name}.txt").write_text(summary + "\n")
    print(summary)
