"""Cost-normalised learning curves of a training run, with open-loop bars on the same axes.

    python experiments/learning_curve.py RUN_DIR OUT.png [--baselines TABLE.csv ...] [--ranks W]
                                         [--seeds N]

The figure of :func:`physicsrl.learning_curve.plot` (success and return against environment
steps, wall-clock and core-hours); from each ``--baselines`` table (``atp_baselines.py``'s) the
policy of the best mean return is drawn as a line. ``--ranks``: the job's W ranks where the run
has no ``summary.json`` yet. ``--seeds N``: the run evaluated the first N held-out seeds, so
tables per seed (``*_per_seed.csv``) are averaged over those (the bar on the curve's seeds).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from physicsrl.config import held_out_seeds
from physicsrl.learning_curve import best_rows, plot


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a physicsrl-train run directory")
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("--baselines", type=Path, nargs="*", default=[], help="tables")
    parser.add_argument("--ranks", type=int, help="the job's ranks (default: its summary's)")
    parser.add_argument("--seeds", type=int, help="per-seed tables: the first N held-out seeds")
    args = parser.parse_args()
    if args.ranks is not None and args.ranks < 1:
        parser.error(f"--ranks {args.ranks}: a job has at least 1 rank")
    missing = [str(p) for p in (args.run, *args.baselines, args.out.parent) if not p.exists()]
    if missing:
        parser.error(f"{missing[0]}: no such file or directory")
    try:
        seeds = None if args.seeds is None else set(held_out_seeds(args.seeds))
    except ValueError as error:
        parser.error(f"--seeds: {error}")
    if plot(args.run, args.out, best_rows(args.baselines, seeds), args.ranks) is None:
        raise SystemExit(f"{args.run / 'eval.csv'}: no evaluations with wall_s")
    print(args.out)


if __name__ == "__main__":
    main()
