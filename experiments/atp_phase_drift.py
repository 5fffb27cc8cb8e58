"""How far a grid's reentry drifts in time from a finer grid's: the catheter's readings of one
never-shock episode of the resolved timing task at each grid, and the time shift between them.

    python experiments/atp_phase_drift.py record --cells 1000 --draw 10 --out <dir>   # minutes
    python experiments/atp_phase_drift.py record --cells 2000 --draw 10 --out <dir>   # ~15 min
    mpiexec -n 2 python experiments/atp_phase_drift.py record --cells 4000 --draw 10 --every 5.01 \\
        --out <dir> env.model.dt=0.015   # ~1 h on 2 ranks sharing the mesh, ~11 GB
    python experiments/atp_phase_drift.py compare --out <dir>

``record``: ``+experiment=atp_resolved_timing`` on held-out draw ``--draw`` (seed 1000000000 +
draw), never shocking, read every ``--every`` time units (``env.decision_interval``, rounded to
whole steps of dt) over the episode's span (its 15 decisions of 50, no extra waits):
``<out>/readings_<cells>.npz`` with the times since the takeover (T,) and the readings
(T, electrodes).

``compare`` (the grids' readings at the same times: 5.01 is 167 steps of dt = 0.03 and 334 of
0.015): for each grid against the next finer one, in windows of ``--window`` time units,
the shift s that minimises the mean squared difference between the coarse readings at t and
the fine ones at t - s (linear interpolation; each electrode scaled by its fine readings'
deviation): s > 0 means the coarse grid's reentry runs late. A slower front (the coarse grid's
conduction-velocity error) makes s grow with time; an outcome decided by where the refractory
tails lie when the shock fires (experiments/results/README.md) moves with it.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
import torch
from mpi4py import MPI

from physicsrl import builders
from physicsrl.cli.train import train_config
from physicsrl.config import held_out_seeds
from physicsrl.coordinated import abort_on_error
from physicsrl.envs.baselines import Constant
from physicsrl.envs.layout import environments
from physicsrl.evaluation import episode
from physicsrl.tables import provenance

SPAN = 750.0  # time units the task's episode spans after the takeover: 15 decisions of 50
SHIFTS = np.arange(-100.0, 100.25, 0.25)  # candidate shifts, time units: within half a period


def record(cells: int, draw: int, every: float, out: Path, overrides: list[str]) -> None:
    """The readings of draw ``draw``'s never-shock episode on ``cells`` x ``cells``."""
    settings = [
        "+experiment=atp_resolved_timing",
        f"env.mesh.cells={cells}",
        "env.model.scheme=explicit",
        f"env.decision_interval={every}",
        f"env.max_decisions={round(SPAN / every)}",
        "env.extra_waits=0",
        f"env.shock.duration={every}",  # checked against the interval; no shock fires
        *overrides,
    ]
    cfg = train_config(settings)
    ranks = MPI.COMM_WORLD.size  # one environment, its mesh shared by every rank
    with abort_on_error(), environments(lambda c: builders.make_env(cfg, c), ranks) as env:
        if env is None:  # another rank: it served the leader's episode
            return
        rollout = episode(env, Constant(0), held_out_seeds(draw + 1)[draw])
        readings = torch.cat([rollout["observation"], rollout["next", "observation"][-1:]])
        out.mkdir(parents=True, exist_ok=True)
        interval = round(every / cfg.env.model.dt) * cfg.env.model.dt  # whole steps of dt
        np.savez(
            out / f"readings_{cells}.npz",
            times=interval * np.arange(len(readings)),
            readings=readings.double().numpy(),
            command=shlex.join(["python", *sys.argv]) + f"  # {provenance()}",
        )
        print(f"{cells} cells: {len(readings)} readings, every {every} time units", flush=True)


def shifts(times, coarse, fine, window: float) -> list[tuple[float, float, float]]:
    """(window start, window end, s) per window of ``window`` time units: the shift s of
    :data:`SHIFTS` minimising the scaled squared difference between ``coarse`` (T, electrodes)
    at t and ``fine`` (T, electrodes) at t - s, both read at ``times`` (T,)."""
    scale = fine.std(0) + 1e-12
    rows = []
    for start in np.arange(times[0], times[-1] - window / 2, window):
        inside = (times >= start) & (times < start + window)
        t = times[inside]
        errors = []
        for s in SHIFTS:
            late = np.stack([np.interp(t - s, times, f) for f in fine.T], -1)
            usable = (t - s >= times[0]) & (t - s <= times[-1])  # no extrapolation
            errors.append(np.mean(((coarse[inside] - late) / scale)[usable] ** 2))
        rows.append((float(start), float(t[-1]), float(SHIFTS[int(np.argmin(errors))])))
    return rows


def compare(out: Path, window: float) -> None:
    runs = {int(p.stem.split("_")[1]): np.load(p) for p in out.glob("readings_*.npz")}
    lines = [shlex.join(["python", *sys.argv]) + f"  # {provenance()}"]
    lines += [f"readings_{cells}: {str(run['command'])}" for cells, run in sorted(runs.items())]
    grids = sorted(runs)
    for coarse, fine in zip(grids, grids[1:], strict=False):
        a, b = runs[coarse], runs[fine]
        n = min(len(a["times"]), len(b["times"]))  # an episode that ended by itself is shorter
        lines.append(f"{coarse} against {fine} cells (s > 0: {coarse} runs late):")
        for start, end, s in shifts(a["times"][:n], a["readings"][:n], b["readings"][:n], window):
            lines.append(f"  {start:6.1f}-{end:6.1f} time units after the takeover: s = {s:+.2f}")
    text = "\n".join(lines) + "\n"
    (out / "atp_phase_drift.txt").write_text(text)
    print(text, end="")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=("record", "compare"))
    parser.add_argument("--cells", type=int, help="cells per side (record)")
    parser.add_argument("--draw", type=int, default=10, help="held-out draw (record)")
    parser.add_argument("--every", type=float, default=5.0, help="time units between readings")
    parser.add_argument("--window", type=float, default=150.0, help="time units (compare)")
    parser.add_argument("--out", type=Path, default=Path("experiments/results/atp_phase_drift"))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides (record)")
    args = parser.parse_intermixed_args()
    if args.stage == "record":
        if args.cells is None or args.draw < 0 or args.every <= 0:
            parser.error(
                f"record needs --cells, a --draw >= 0 and --every > 0, got {args.cells}, "
                f"{args.draw}, {args.every}"
            )
        record(args.cells, args.draw, args.every, args.out, args.overrides)
    elif len(list(args.out.glob("readings_*.npz"))) < 2 or args.window <= 0:
        parser.error(f"compare needs two grids' readings in {args.out} and a --window > 0")
    else:
        compare(args.out, args.window)


if __name__ == "__main__":
    main()
