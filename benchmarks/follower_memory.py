"""Peak memory of a rank that only serves its group leader's simulator, beside the same rank
when it builds the whole TorchRL env (the baseline) and beside a floor.

One ``physicsrl-train`` job of 2 ranks forming one environment (``mpi.ranks_per_env=2``, the
heat task, 3 iterations) per case, then one ``physicsrl-eval`` job of the run it trained, laid
out alike (2 held-out seeds); each rank started by this script (MPMD ``mpiexec``) so that it
reads the rank's own peak resident memory (``ru_maxrss`` of its child):

- physicsrl: the built-in task; the follower builds the task alone and imports no torch
  (:func:`physicsrl.envs.factory.make_env_for_rank`);
- baseline: the same env through ``+env.factory`` (:func:`whole_env`, here), which every rank
  builds whole, as every follower did before;
- floor: a process that imports the simulator side (``physicsrl.envs``) and nothing else.

``goal met`` when the follower's peak is at most half the baseline follower's, in training and
in evaluation. Writes
``benchmarks/results/follower_memory.txt`` (command, table).

    python benchmarks/follower_memory.py      # about two minutes
"""

from __future__ import annotations

import resource
import subprocess
import sys
import tempfile
from pathlib import Path

BIN = Path(sys.executable).parent
LAYOUT = "mpi.ranks_per_env=2"
TRAIN = ["iterations=3", "logger.progress=false", "eval.baselines=false", LAYOUT]
EVAL = ["seeds=2", "baselines=false", "gif=false", "curve=false", LAYOUT]
CASES = {"physicsrl": [], "baseline (env.factory)": [f"+env.factory={__file__}:whole_env"]}


def whole_env(cfg, coordinator):
    """The baseline's ``env.factory``: :func:`physicsrl.envs.make_env` on every rank."""
    from physicsrl.checks import plain
    from physicsrl.envs import make_env

    cfg = plain(cfg)
    del cfg["env"]["factory"]
    return make_env(cfg, coordinator)


def child_peak_mb(command: list[str]) -> float:
    """Run ``command``; its peak resident memory in MB (it and its waited-for children). The
    launcher's connection (``PMI_FD``) stays open for it: it is the MPI rank."""
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL, close_fds=False)
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024  # Linux: kB


def job_peaks(command: list[str], directory: Path) -> list[float]:
    """Peak MB of rank 0 (the leader) and rank 1 (its follower) of one job of the physicsrl
    ``command`` (its name in the environment's ``bin`` and its arguments), in ``directory``."""
    command = [str(BIN / command[0]), *command[1:], f"hydra.run.dir={directory}"]
    ranks = []
    for rank in (0, 1):
        out = directory.parent / f"{directory.name}_rank{rank}.txt"
        ranks += [":"] * (rank > 0)
        ranks += ["-n", "1", sys.executable, __file__, "--peak", str(out), *command]
    subprocess.run([str(BIN / "mpiexec"), *ranks], check=True)
    return [float((directory.parent / f"{directory.name}_rank{r}.txt").read_text()) for r in (0, 1)]


def main() -> None:
    if sys.argv[1:2] == ["--peak"]:  # one rank: run its command, write its peak
        Path(sys.argv[2]).write_text(str(child_peak_mb(sys.argv[3:])))
        return
    floor = child_peak_mb([sys.executable, "-c", "import physicsrl.envs"])
    from bench_run import save_summary  # here: whole_env is loaded by physicsrl-train too

    lines = [f"{'command, case':<40s} leader peak (MB)  follower peak (MB)  follower / floor"]
    peaks = {}  # (command, case) -> (leader MB, follower MB)
    with tempfile.TemporaryDirectory() as scratch:
        for number, (case, extra) in enumerate(CASES.items()):
            run = Path(scratch) / f"run{number}"
            peaks["physicsrl-train", case] = job_peaks(["physicsrl-train", *TRAIN, *extra], run)
            evaluation = ["physicsrl-eval", f"run={run}", *EVAL]
            peaks["physicsrl-eval", case] = job_peaks(evaluation, run / "eval")
    for (command, case), (leader, follower) in sorted(peaks.items(), reverse=True):
        name = f"{command}, {case}"
        lines.append(f"{name:<40s} {leader:>16.0f}  {follower:>18.0f}  {follower / floor:>16.2f}")
    lines.append(f"{'floor (import envs)':<40s} {'':>16s}  {floor:>18.0f}  {1:>16.2f}")
    for command in ("physicsrl-train", "physicsrl-eval"):
        ratio = peaks[command, "physicsrl"][1] / peaks[command, "baseline (env.factory)"][1]
        met = "goal met" if ratio <= 0.5 else "goal MISSED"
        lines.append(f"{command}: follower / baseline follower = {ratio:.2f} (goal <= 0.5): {met}")
    save_summary("follower_memory", lines)


if __name__ == "__main__":
    main()
