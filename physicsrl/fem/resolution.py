r"""How well a mesh resolves the Mitchell-Schaeffer front, and what that costs in accuracy.

The excitation front of the monodomain model is about :math:`\sqrt{D \tau_\mathrm{in}}` wide
(0.062 mm for the report's D = 0.013 mm^2/ms, :math:`\tau_\mathrm{in}` = 0.3 ms). The planar
conduction velocity (CV) a scheme computes depends on h against that width;
``benchmarks/ms_cv.py`` measures its relative error against the converged CV for both schemes
at dt = 0.03 and writes the table :data:`TABLE` (``cv_error.csv`` beside this module, the one
place the numbers live). :func:`resolution` interpolates it, linearly in
:math:`\log(h / \text{width})`, clamped to the table's ends.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

TABLE = Path(__file__).with_name("cv_error.csv")
"""Columns ``scheme``, ``h_over_width``, ``cv_error`` (relative, signed: -1 when no wave
propagates), written by ``benchmarks/ms_cv.py``."""


@dataclass(frozen=True)
class Resolution:
    """A mesh against the front: largest cell diameter ``h``, front width
    :math:`\\sqrt{D \\tau_\\mathrm{in}}`, and the expected relative planar CV error of
    ``scheme`` from :data:`TABLE`."""

    scheme: str
    cells: int
    h: float
    front_width: float
    cv_error: float

    @property
    def ratio(self) -> float:
        return self.h / self.front_width

    @property
    def mesh(self) -> str:
        return f"{self.cells} cells, h = {self.h:.4g}"

    def __str__(self) -> str:
        return (
            f"resolution: h = {self.h:.3g}, front width sqrt(D tau_in) = {self.front_width:.3g},"
            f" h/width = {self.ratio:.3g}: expected planar CV error {self.cv_error:+.1%}"
            f" ({self.scheme} scheme, {self.cells} cells)"
        )


def cv_table(scheme: str) -> tuple[np.ndarray, np.ndarray]:
    """(h / width ascending, CV error) of ``scheme`` from :data:`TABLE`."""
    with TABLE.open() as table:
        rows = [row for row in csv.DictReader(table) if row["scheme"] == scheme]
    rows.sort(key=lambda row: float(row["h_over_width"]))
    return (
        np.array([float(row["h_over_width"]) for row in rows]),
        np.array([float(row["cv_error"]) for row in rows]),
    )


def expected_cv_error(scheme: str, ratio: float) -> float:
    """The table's CV error of ``scheme`` at h / width = ``ratio`` (interpolated)."""
    ratios, errors = cv_table(scheme)
    return float(np.interp(math.log(ratio), np.log(ratios), errors))


def largest_cell_diameter(domain) -> float:
    """The largest distance between two nodes of a cell, over all ranks (collective)."""
    x = domain.geometry.x
    dofmap = domain.geometry.dofmaps[0][: domain.topology.index_map(domain.topology.dim).size_local]
    nodes = x[dofmap]  # (cells, nodes per cell, 3)
    h = 0.0
    for a in range(nodes.shape[1]):
        for b in range(a + 1, nodes.shape[1]):
            h = max(h, float(np.linalg.norm(nodes[:, a] - nodes[:, b], axis=1).max(initial=0)))
    return domain.comm.allreduce(h, op=MPI.MAX)


def resolution(domain, D: float, tau_in: float, scheme: str) -> Resolution:
    """The :class:`Resolution` of ``domain`` for the model's D and tau_in (collective)."""
    h = largest_cell_diameter(domain)
    width = math.sqrt(D * tau_in)
    cells = domain.topology.index_map(domain.topology.dim).size_global
    return Resolution(scheme, cells, h, width, expected_cv_error(scheme, h / width))
