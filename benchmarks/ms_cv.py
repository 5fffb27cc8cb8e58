"""Planar conduction-velocity error of both Mitchell-Schaeffer schemes against the cell size.

For each scheme (implicit: the report's; explicit: lumped mass) and cell side h, the speed of
a planar front (:func:`physicsrl.fem.resolution.planar_front_speed`: a strip of 1 x n square
cells of side h, the model's default parameters, dt = 0.03) against the converged speed (the
implicit scheme at h = 0.01, dt = 0.002; the explicit one there is printed as a check). The
ratio h / width uses the cells' diameter sqrt(2) h, as :func:`~physicsrl.fem.resolution.resolution`
does, and width = sqrt(D tau_in). Writes the library's table ``physicsrl/fem/cv_error.csv``
and ``benchmarks/results/ms_cv.txt`` (command, table). Serial, seconds.

    python benchmarks/ms_cv.py
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

from physicsrl.fem.resolution import TABLE, TABLE_DT, planar_front_speed

D, TAU_IN = 0.013, 0.3
SIDES = [100 / 60, 1.0, 0.5, 100 / 300, 0.25, 0.2, 100 / 750, 0.1, 0.05, 100 / 3000]
"""Cell sides: the report's 60 x 60 grid on [-50, 50]^2 (1.67) down to 3000 x 3000 (0.033)."""


def speed(h: float, dt: float, scheme: str) -> float:
    length = max(4.0, 40 * h)
    T = 6.0 + 0.7 * length / 0.12
    return planar_front_speed(h, dt, length=length, T=T, t_fit=None, scheme=scheme)


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()  # --help; no options
    reference = speed(0.01, 0.002, "implicit")
    check = speed(0.01, 0.002, "explicit")
    width = math.sqrt(D * TAU_IN)
    rows = []
    for scheme in ("implicit", "explicit"):
        for h in SIDES:
            c = speed(h, TABLE_DT, scheme)
            rows.append((scheme, h, math.sqrt(2) * h / width, c, c / reference - 1))
            print(f"{scheme:8s} h = {h:.4f}: CV {c:.5f} ({c / reference - 1:+.2%})", flush=True)
    with TABLE.open("w", newline="") as table:
        writer = csv.writer(table)
        writer.writerow(["scheme", "h_over_width", "cv_error"])
        writer.writerows((s, f"{r:.5g}", f"{e:.5g}") for s, _, r, _, e in rows)
    lines = [
        f"command: python {' '.join(sys.argv)}",
        f"converged CV (implicit, h = 0.01, dt = 0.002): {reference:.5f}; "
        f"explicit there: {check:.5f} ({check / reference - 1:+.3%})",
        "",
        "| cell side h | cells per side of [-50, 50]^2 | diameter / width | implicit CV error |"
        " explicit CV error |",
        "| --- | --- | --- | --- | --- |",
    ]
    by_scheme = {s: [r for r in rows if r[0] == s] for s in ("implicit", "explicit")}
    for implicit, explicit in zip(by_scheme["implicit"], by_scheme["explicit"], strict=True):
        _, h, ratio, _, error = implicit
        lines.append(
            f"| {h:.4g} | {100 / h:.0f} | {ratio:.3g} | {error:+.1%} | {explicit[4]:+.1%} |"
        )
    out = Path(__file__).parent / "results" / "ms_cv.txt"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
