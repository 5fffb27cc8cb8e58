"""Peak memory per cell of the Mitchell-Schaeffer simulator, beside the estimate by which
``physicsrl-train`` refuses a mesh too large (:data:`physicsrl.config.MESH_BYTES_PER_CELL`).

For each scheme and grid (cells x cells quadrilaterals of [-50, 50]^2, one rank), a fresh
process builds the simulator and advances it 10 steps of dt = 0.03 (or the explicit scheme's
stability limit on that grid, if smaller); its peak resident memory less the peak after the
imports, per cell, is set beside the estimate, with ``goal met`` when the estimate covers
every peak measured. Writes ``benchmarks/results/ms_memory.txt`` (command, table).

    python benchmarks/ms_memory.py                       # 500 and 1000 cells: ~20 s
    python benchmarks/ms_memory.py --cells 1000 2000     # 2000: ~4 GB, a minute
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys

from bench_run import save_summary  # benchmarks/ (the script's directory)

SCHEMES = ("implicit", "explicit")


def peak_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: kB


def measure(cells: int, scheme: str) -> float:
    """In this process: the simulator's peak bytes per cell (module docstring)."""
    import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

    # isort: split

    from physicsrl.coordinated import Coordinator
    from physicsrl.envs.atp import MSModel
    from physicsrl.envs.task import SquareMesh
    from physicsrl.fem import MonodomainMitchellSchaeffer

    imported = peak_bytes()
    coordinator = Coordinator()
    grid = SquareMesh(cells, 50.0, "quadrilateral")
    domain = grid.create()
    dt = min(0.03, 0.99 * grid.explicit_limit(MSModel.D))
    simulator = MonodomainMitchellSchaeffer(coordinator, domain, scheme=scheme, dt=dt)
    with coordinator:
        simulator.advance_time(10 * dt)
    return (peak_bytes() - imported) / cells**2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, nargs="+", default=[500, 1000])
    parser.add_argument("--one", nargs=2, metavar=("CELLS", "SCHEME"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:  # a child: one measurement, printed
        print(measure(int(args.one[0]), args.one[1]))
        return
    from physicsrl.config import MESH_BYTES_PER_CELL

    lines = ["cells per side  scheme    peak bytes per cell  estimate  measured / estimate"]
    ratios = []
    for cells in args.cells:
        for scheme in SCHEMES:
            child = [sys.executable, __file__, "--one", str(cells), scheme]
            result = subprocess.run(child, check=True, capture_output=True, text=True)
            per_cell = float(result.stdout)
            ratios.append(per_cell / MESH_BYTES_PER_CELL)
            lines.append(
                f"{cells:<15d} {scheme:<9s} {per_cell:>19.0f}  {MESH_BYTES_PER_CELL:>8d}  "
                f"{ratios[-1]:>19.2f}"
            )
    met = "goal met" if max(ratios) <= 1 else "goal MISSED"
    lines.append(f"the estimate covers every peak (measured / estimate <= 1): {met}")
    save_summary("ms_memory", lines)


if __name__ == "__main__":
    main()
