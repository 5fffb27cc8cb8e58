"""Collect the jobs of a sweep into one table.

    python experiments/collect.py multirun/train/<time stamp> [--csv table.csv]

Reads each job directory's ``summary.json`` (written by ``physicsrl-train``) and
``.hydra/overrides.yaml`` (what the job changed), and prints one row per job: the overrides,
the greedy policy's mean return on the held-out seeds, the best baseline's (left empty with
``eval.baselines=false``, as the ATP presets set it), the success rate where the task has one,
and the training time. A job stopped before its first evaluation has no greedy return.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import yaml

IMPLIED = ("mpi.ranks=", "observation=", "reward=", "hydra.")


def row(job: Path) -> dict:
    summary = json.loads((job / "summary.json").read_text())
    overrides = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text()) or []
    policies = {entry["policy"]: entry for entry in summary["table"]}
    greedy = policies.pop("greedy DQN", {})
    best = max(policies.values(), key=lambda entry: entry["return"], default={})
    result = {
        "job": job.name,
        "overrides": " ".join(o for o in overrides if not o.startswith(IMPLIED)),
        "greedy_return": round(greedy["return"], 3) if greedy else "",
        "best_baseline": best.get("policy", ""),
        "best_baseline_return": round(best["return"], 3) if best else "",
        "train_s": round(summary["summary"]["total_s"], 1),
    }
    if "success" in greedy:
        result["greedy_success"] = greedy["success"]
    return result


def job_order(job: Path) -> tuple[bool, int, str]:
    """Hydra's job numbers in numeric order (0, 1, ..., 10), then any other names."""
    return not job.name.isdigit(), int(job.name) if job.name.isdigit() else 0, job.name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", type=Path, help="the sweep directory (hydra.sweep.dir)")
    parser.add_argument("--csv", type=Path, help="also write the table here")
    args = parser.parse_args()
    jobs = sorted((p.parent for p in args.sweep.glob("*/summary.json")), key=job_order)
    if not jobs:
        sys.exit(f"error: no job with a summary.json under {args.sweep}")
    rows = [row(job) for job in jobs]
    columns = list(dict.fromkeys(key for r in rows for key in r))
    writer = csv.DictWriter(sys.stdout, fieldnames=columns, delimiter="\t")
    writer.writeheader()
    writer.writerows(rows)
    if args.csv:
        with open(args.csv, "w", newline="") as stream:
            writer = csv.DictWriter(stream, fieldnames=columns)
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
