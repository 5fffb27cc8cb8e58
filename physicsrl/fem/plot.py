"""A PNG of a scalar field, gathered from all ranks to the leader.

Each rank sends the coordinates (x, y) and values of its owned dofs; the leader triangulates
the points (Delaunay, so triangles and quadrilaterals alike) and draws them with Gouraud
shading and a colour bar. Only the leader writes the file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from dolfinx import fem


def plot_field(
    function: fem.Function,
    path: str | Path,
    title: str | None = None,
    t: float | None = None,
    limits: tuple[float, float] | None = None,
) -> None:
    """Write ``function`` (scalar, 2D mesh) as a PNG to ``path``. Collective.

    The title is ``title`` (default: the function's name) followed by ``t = ...`` when the
    time ``t`` is given; ``limits`` fixes the colour scale (default: the data range).
    """
    V = function.function_space
    n = V.dofmap.index_map.size_local
    points = V.tabulate_dof_coordinates()[:n, :2]
    local = np.column_stack([points, function.x.array[:n].real])
    comm = V.mesh.comm
    gathered = comm.gather(local, root=0)
    if comm.rank != 0:
        return
    x, y, values = np.concatenate(gathered).T
    plot_points(x, y, values, path, function.name, title, t, limits)


def plot_points(
    x: np.ndarray,
    y: np.ndarray,
    values: np.ndarray,
    path: str | Path,
    name: str,
    title: str | None = None,
    t: float | None = None,
    limits: tuple[float, float] | None = None,
) -> None:
    """Write the values at the points (x, y) (each of shape (n,)) as a PNG; the colour bar is
    labelled ``name``, the title and limits as in :func:`plot_field`. Not collective."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    figure, axes = plt.subplots(figsize=(6, 5))
    vmin, vmax = limits if limits is not None else (values.min(), values.max())
    image = axes.tripcolor(Triangulation(x, y), values, shading="gouraud", vmin=vmin, vmax=vmax)
    figure.colorbar(image, ax=axes, label=name)
    heading = title if title is not None else name
    axes.set_title(heading if t is None else f"{heading}, t = {t:g}")
    axes.set_aspect("equal")
    axes.set_xlabel("x")
    axes.set_ylabel("y")
    figure.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(figure)
