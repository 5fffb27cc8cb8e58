"""Planar conduction-velocity error of both Mitchell-Schaeffer schemes against the cell size.

For each cell type, scheme (implicit: the report's; explicit: lumped mass) and cell side h,
the speed of a planar front (:func:`physicsrl.fem.resolution.planar_front_speed`: a strip of
the cells of a grid of squares of side h, the model's default parameters, each time step of
:data:`~physicsrl.fem.resolution.TABLE_DTS`: 0.03, the tasks', and its halves) against
the converged speed (the implicit scheme on quadrilaterals at h = 0.01, dt = 0.002; the
explicit one there is printed as a check). On quadrilaterals the front runs along the cells'
edges; on triangles along their edges and along their hypotenuses, and the table keeps the
larger error in magnitude (a spiral's front runs every way). The ratio h / width uses the
cells' diameter sqrt(2) h, as :func:`~physicsrl.fem.resolution.resolution` does, and
width = sqrt(D tau_in). Writes the library's table ``physicsrl/fem/cv_error.csv`` and
``benchmarks/results/ms_cv.txt`` (command, table). Serial, about a minute.

    python benchmarks/ms_cv.py
    python benchmarks/ms_cv.py --at 2000:0.03 4000:0.015   # seconds

``--at CELLS:DT``: instead, the explicit scheme's error on quadrilaterals at those grids of
[-50, 50]^2 (h = 100 / CELLS) and time steps, the table left as it is, into
``benchmarks/results/ms_cv_at.txt``.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

from physicsrl.fem.errors import InvalidValue
from physicsrl.fem.resolution import TABLE, TABLE_DTS, planar_front_speed

D, TAU_IN = 0.013, 0.3
SIDES = [100 / 60, 1.0, 0.5, 100 / 300, 0.25, 0.2, 100 / 750, 0.1, 0.05, 100 / 3000]
"""Cell sides: the report's 60 x 60 grid on [-50, 50]^2 (1.67) down to 3000 x 3000 (0.033)."""


def diameter_over_width(h: float) -> float:
    """The cells' diameter sqrt(2) h over the front width sqrt(D tau_in)."""
    return math.sqrt(2) * h / math.sqrt(D * TAU_IN)


DIRECTIONS = {"quadrilateral": ("edges",), "triangle": ("edges", "hypotenuses")}
"""The directions of the front measured on each cell type (``front_strip``'s ``along``)."""


def speed(h: float, dt: float, scheme: str, cell_type="quadrilateral", along="edges") -> float:
    length = max(4.0, 40 * h)
    T = 6.0 + 0.7 * length / 0.12
    return planar_front_speed(
        h, dt, length=length, T=T, t_fit=None, cell_type=cell_type, along=along, scheme=scheme
    )


def grid_step(text: str) -> tuple[int, float]:
    """``"CELLS:DT"`` -> (cells per side, dt), both > 0."""
    cells, _, dt = text.partition(":")
    try:
        pair = int(cells), float(dt)
    except ValueError:
        pair = (0, 0.0)
    if pair[0] < 1 or not pair[1] > 0:
        raise argparse.ArgumentTypeError(f"{text!r}: expected CELLS:DT, e.g. 2000:0.03")
    return pair


def errors_at(grids: list[tuple[int, float]], reference: float) -> list[tuple[float, float]]:
    """(h / width, explicit CV error) at each (cells per side of [-50, 50]^2, dt)."""
    return [
        (diameter_over_width(100 / cells), speed(100 / cells, dt, "explicit") / reference - 1)
        for cells, dt in grids
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--at", nargs="+", type=grid_step, metavar="CELLS:DT")
    at = parser.parse_args().at
    reference = speed(0.01, 0.002, "implicit")
    if at:
        lines = [
            f"command: python {' '.join(sys.argv)}",
            "| cells per side of [-50, 50]^2 | diameter / width | dt | explicit CV error |",
            "| --- | --- | --- | --- |",
        ]
        for (cells, dt), (ratio, error) in zip(at, errors_at(at, reference), strict=True):
            lines.append(f"| {cells} | {ratio:.3g} | {dt:g} | {error:+.2%} |")
        (Path(__file__).parent / "results" / "ms_cv_at.txt").write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
        return
    check = speed(0.01, 0.002, "explicit")
    rows = {}  # (cell type, scheme, dt) -> {h: (ratio, error, direction)}
    for cell_type, directions in DIRECTIONS.items():
        for scheme in ("implicit", "explicit"):
            for dt in TABLE_DTS:
                for h in SIDES:
                    try:
                        errors = {
                            a: speed(h, dt, scheme, cell_type, a) / reference - 1
                            for a in directions
                        }
                    except InvalidValue as refused:  # dt above the explicit scheme's limit
                        print(f"{cell_type} {scheme} dt = {dt:g} h = {h:.4f}: {refused}")
                        continue
                    along = max(errors, key=lambda a: abs(errors[a]))
                    rows.setdefault((cell_type, scheme, dt), {})[h] = (
                        diameter_over_width(h),
                        errors[along],
                        along,
                    )
                    shown = ", ".join(f"along {a} {e:+.2%}" for a, e in errors.items())
                    print(f"{cell_type} {scheme} dt = {dt:g} h = {h:.4f}: {shown}", flush=True)
    with TABLE.open("w", newline="") as table:
        writer = csv.writer(table)
        writer.writerow(["scheme", "cell_type", "dt", "h_over_width", "cv_error"])
        for (cell_type, scheme, dt), measured in rows.items():
            writer.writerows(
                (scheme, cell_type, dt, f"{r:.5g}", f"{e:.5g}") for r, e, _ in measured.values()
            )
    steps = " | ".join(f"dt {dt:g}" for dt in reversed(TABLE_DTS))
    lines = [
        f"command: python {' '.join(sys.argv)}",
        f"converged CV (implicit, quadrilaterals, h = 0.01, dt = 0.002): {reference:.5f}; "
        f"explicit there: {check:.5f} ({check / reference - 1:+.3%})",
        "",
        "CV error of each scheme at each time step (the direction of the larger in brackets):",
        "",
        f"| cells | cell side h | cells per side of [-50, 50]^2 | diameter / width |"
        f" implicit, {steps} | explicit, {steps} |",
        "| --- | --- | --- | --- |" + " --- |" * 2 * len(TABLE_DTS),
    ]
    for cell_type in DIRECTIONS:
        for h in SIDES:
            cells = []
            for scheme in ("implicit", "explicit"):
                for dt in reversed(TABLE_DTS):
                    measured = rows.get((cell_type, scheme, dt), {}).get(h)
                    cells.append(f"{measured[1]:+.1%} ({measured[2]})" if measured else "refused")
            lines.append(
                f"| {cell_type} | {h:.4g} | {100 / h:.0f} | {diameter_over_width(h):.3g} | "
                + " | ".join(cells)
                + " |"
            )
    lines.append("\nrefused: dt above the explicit scheme's limit on those cells.")
    out = Path(__file__).parent / "results" / "ms_cv.txt"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
