"""Inducing ahead (``env.model.induce_ahead=true``) beside inducing each new draw when its
replica's episode ends (the baseline, ``false``), in one run: two ``physicsrl-train`` jobs of
the radius-35 timing task with the same seed, each on one process (side by side on a CPU, one
after the other on a GPU).

A GPU pays for the inductions' batch-steps (steps of dt, each advancing one batch whatever its
size: a step of a few replicas costs about what a full batch's does there); their work is the
replica-steps. ``goal met`` when inducing ahead takes fewer induction batch-steps for the same
replica-steps and the two runs stored the same transitions, to the bit (their replay buffers).
The seconds of each phase are printed for the device the jobs ran on. Writes
``benchmarks/results/induce_ahead.txt`` (command, table).

    python benchmarks/induce_ahead.py                                  # CPU, 32 replicas: ~6 min
    python benchmarks/induce_ahead.py --device cuda --replicas 1024
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import torch
from bench_run import at_least, save_summary

from physicsrl.checkpoint import read
from physicsrl.run_directory import checkpoint_path

CASES = {"baseline (induce_ahead=false)": "false", "physicsrl (induce_ahead=true)": "true"}


def command(run: Path, ahead: str, device: str, replicas: int, iterations: int) -> list[str]:
    train = str(Path(sys.executable).with_name("physicsrl-train"))
    return [
        *(train, "+experiment=atp_timing_r35", f"env.model.device={device}"),
        *(f"env.replicas={replicas}", f"iterations={iterations}", "eval.every=0"),
        *("eval.seeds=${held_out:2}", "logger.progress=false", f"env.model.induce_ahead={ahead}"),
        f"hydra.run.dir={run}",
    ]


def transitions(run: Path) -> dict[str, torch.Tensor]:
    """The written rows of each key of the run's replay buffer, from its last checkpoint."""
    buffer = read(checkpoint_path(str(run)), {"replay_buffer": True})["replay_buffer"]
    written = buffer["_storage"]["_len"]
    return {key: value[:written] for key, value in buffer["_storage"]["_storage"].items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()))
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--replicas", type=at_least(1), default=32)
    parser.add_argument("--iterations", type=at_least(1), default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        runs = {case: Path(scratch) / ahead for case, ahead in CASES.items()}
        jobs = [
            command(runs[case], ahead, args.device, args.replicas, args.iterations)
            for case, ahead in CASES.items()
        ]
        if args.device == "cpu":  # one core each, side by side
            processes = [subprocess.Popen(job, stdout=subprocess.DEVNULL) for job in jobs]
            if any(process.wait() for process in processes):
                raise SystemExit("a training job failed")
        else:  # one GPU: one at a time
            for job in jobs:
                subprocess.run(job, stdout=subprocess.DEVNULL, check=True)
        summary = {
            case: json.loads((run / "summary.json").read_text())["summary"]
            for case, run in runs.items()
        }
        stored = [transitions(run) for run in runs.values()]

    lines = [
        f"{args.replicas} replicas on {args.device}, {args.iterations} iterations of "
        "+experiment=atp_timing_r35 (seed 0), per phase: seconds, replica-steps, batch-steps",
        f"{'case':<30s} {'induction':>30s} {'decisions':>30s} {'waits':>30s}",
    ]
    for case, record in summary.items():
        phases = [record["simulated"][p] for p in ("induction", "decisions", "waits")]
        cells = [f"{s:8.1f}s {r:>10,d} {b:>9,d}" for s, r, b in phases]
        lines.append(f"{case:<30s} " + " ".join(f"{c:>30s}" for c in cells))
    (_, work, steps), (_, ahead_work, ahead_steps) = (
        summary[case]["simulated"]["induction"] for case in CASES
    )
    same = stored[0].keys() == stored[1].keys() and all(
        torch.equal(stored[0][key], stored[1][key]) for key in stored[0]
    )
    met = ahead_steps < steps and ahead_work == work and same
    lines.append(
        f"induction batch-steps: {ahead_steps / steps:.2f} of the baseline's; replica-steps "
        f"{'the same' if ahead_work == work else f'{ahead_work / work:.2f}x'}; transitions "
        f"{'the same to the bit' if same else 'DIFFER'} "
        f"(goal: fewer batch-steps, the same work and transitions): "
        f"{'goal met' if met else 'goal MISSED'}"
    )
    save_summary("induce_ahead", lines)


if __name__ == "__main__":
    main()
