"""Fields for ParaView: time series of a simulator's u (and w) in DOLFINx's VTX format.

:class:`FieldRecorder` writes scalar Functions of one Lagrange space (``sim.u_n()``,
``sim.w_n()``) through ``dolfinx.io.VTXWriter``: an ADIOS2 ``.bp`` directory that every rank
writes its part of, and that ParaView opens as a time series (File > Open, the ``.bp``
directory, reader "ADIOS2VTXReader"). It is a :class:`~physicsrl.coordinated.Coordinated`
object, so an episode runner on the leader calls ``recorder.write(t)`` after each decision.
:func:`read_series` reads a series back with ADIOS2's Python bindings (the ``adios2``
package: the ``fields`` extra), on one process; :func:`render_series` draws one field at one
time of it as a PNG.

Layout of a series (VTX): per step the scalar ``step`` (the time, in the simulator's units, ms
for the monodomain model), and per rank a block of the mesh nodes it holds: ``geometry``
(nodes x 3), the global node numbers ``vtkOriginalPointIds``, ``vtkGhostType`` (1: a copy of a
node another rank owns) and one array per field (the values at the nodes).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from dolfinx import fem, io

from physicsrl.coordinated import Coordinated, Coordinator, parallel


class FieldRecorder(Coordinated):
    """Writes ``functions`` (scalar, one Lagrange space) to ``path`` (a ``.bp`` directory) at
    each :meth:`write`. Construct it on every rank (like a simulator); :meth:`write` and
    :meth:`close` are parallel methods: call them on the leader inside ``with coordinator``."""

    def __init__(self, coordinator: Coordinator, path: str | Path, functions: list[fem.Function]):
        self.register_coordinator(coordinator)
        if not io.has_adios2:
            raise RuntimeError("field output needs DOLFINx built with ADIOS2")
        spaces = {id(f.function_space) for f in functions}
        if not functions or len(spaces) != 1:
            raise ValueError("give one or more Functions of the same function space")
        self.path = Path(path)
        self._writer = io.VTXWriter(
            functions[0].function_space.mesh.comm, self.path, functions, engine="BP5"
        )

    @parallel
    def write(self, t: float) -> None:
        """Append the functions' current values as the step at time ``t``."""
        self._writer.write(t)

    @parallel
    def close(self) -> None:
        """Finish the series (ParaView reads the steps written before this)."""
        self._writer.close()


@dataclass
class Series:
    """A field time series read back: ``times`` (steps,), ``points`` (nodes, 3) in the order
    of the global node numbers, ``values[name]`` (steps, nodes)."""

    times: np.ndarray
    points: np.ndarray
    values: dict[str, np.ndarray]


def read_series(path: str | Path) -> Series:
    """Read a series written by :class:`FieldRecorder` (one process; needs ``adios2``)."""
    import adios2

    layout = {"geometry", "vtkOriginalPointIds", "vtkGhostType", "connectivity", "types"}
    times, steps = [], []
    with adios2.Stream(str(path), "r") as stream:
        for _ in stream.steps():
            names = [
                n
                for n in stream.available_variables()
                if n not in layout and n not in ("step", "NumberOfNodes", "NumberOfEntities")
            ]
            blocks = len(stream.read("NumberOfNodes"))
            owned: dict[str, list[np.ndarray]] = {n: [] for n in ["ids", "points", *names]}
            for block in range(blocks):
                mine = stream.read("vtkGhostType", block_id=block).ravel() == 0
                owned["ids"].append(stream.read("vtkOriginalPointIds", block_id=block)[mine])
                owned["points"].append(stream.read("geometry", block_id=block)[mine])
                for name in names:
                    owned[name].append(stream.read(name, block_id=block).ravel()[mine])
            order = np.argsort(np.concatenate(owned["ids"]).ravel())
            steps.append({n: np.concatenate(parts)[order] for n, parts in owned.items()})
            times.append(float(stream.read("step")))
    if not steps:
        raise ValueError(f"{path}: no steps")
    values = {n: np.stack([s[n] for s in steps]) for n in steps[0] if n not in ("ids", "points")}
    return Series(np.array(times), steps[0]["points"], values)


def render_series(series: Series, name: str, step: int, path: str | Path) -> None:
    """Draw field ``name`` at ``series.times[step]`` as a PNG (one process)."""
    from physicsrl.fem.plot import plot_points

    x, y = series.points[:, 0], series.points[:, 1]
    plot_points(x, y, series.values[name][step], path, name, t=float(series.times[step]))
