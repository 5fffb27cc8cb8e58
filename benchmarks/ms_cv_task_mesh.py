"""The planar conduction velocity on a task's own 2-D mesh, against the table's 1-D strip.

A planar front started by u = 1 on x < -45 (w = 1) on the n x n Q1 grid of [-50, 50]^2
(default: the report's 60 x 60), dt = 0.03, the default parameters: the speed of the point
where u = 0.5 along y = 0 (linear interpolation), fitted over the later two thirds of the
samples every 2 time units until the front passes x = 40, against the converged speed as
``benchmarks/ms_cv.py`` computes it (its ``speed``: implicit, h = 0.01, dt = 0.002). Writes
benchmarks/results/ms_cv_task_mesh.txt.

    python benchmarks/ms_cv_task_mesh.py [--cells 60] [--scheme implicit]
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

import ms_cv  # benchmarks/ (the script's directory)
import numpy as np
from bench_run import at_least
from dolfinx import mesh
from mpi4py import MPI

from physicsrl.coordinated import Coordinator
from physicsrl.fem.monodomain import SCHEMES, MonodomainMitchellSchaeffer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=at_least(2), default=60, help="an even number")
    parser.add_argument("--scheme", default=SCHEMES[0], choices=SCHEMES)
    args = parser.parse_args()
    if args.cells % 2:
        parser.error(f"--cells={args.cells}: must be even (the front is read on the row y = 0)")
    n = args.cells
    domain = mesh.create_rectangle(
        MPI.COMM_SELF, [[-50, -50], [50, 50]], [n, n], mesh.CellType.quadrilateral
    )
    ms = MonodomainMitchellSchaeffer(
        Coordinator(MPI.COMM_SELF),
        domain,
        u0=lambda x: np.where(x[0] < -45, 1.0, 0.0),
        w0=1.0,
        scheme=args.scheme,
    )
    xy = ms.V.tabulate_dof_coordinates()
    row = np.nonzero(np.isclose(xy[:, 1], 0.0, atol=1e-9))[0]
    row = row[np.argsort(xy[row, 0])]
    x = xy[row, 0]
    times, positions = [], []
    with ms.coordinator:
        while ms.t < 800:
            ms.advance_time(round(2.0 / ms.dt) * ms.dt)
            u = ms.u_n().x.array[row]
            i = np.nonzero(u > 0.5)[0].max()
            if x[i] > 40:
                break
            times.append(ms.t)
            positions.append(x[i] + (u[i] - 0.5) / (u[i] - u[i + 1]) * (x[i + 1] - x[i]))
    converged = ms_cv.speed(0.01, 0.002, "implicit")
    times, positions = np.array(times), np.array(positions)
    later = times >= times[0] + (times[-1] - times[0]) / 3
    speed = np.polyfit(times[later], positions[later], 1)[0]
    line = (
        f"{n} x {n}, {args.scheme}: planar CV {speed:.4f} against the converged {converged:.5f} "
        f"({speed / converged - 1:+.1%})"
    )
    text = f"command: {shlex.join(['python', *sys.argv])}\n{line}\n"
    (Path(__file__).parent / "results" / "ms_cv_task_mesh.txt").write_text(text)
    print(text, end="")


if __name__ == "__main__":
    main()
