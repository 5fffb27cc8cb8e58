r"""Observations: what the agent sees, as fixed linear functionals of one state variable.

An observation is a small frozen dataclass (its fields are the YAML settings of
``conf/observation/<name>.yaml``) registered in :data:`OBSERVATIONS`. It contributes ``size``
rows to the task's :class:`~physicsrl.fem.integrals.WeightedIntegrals`, so observing costs one
matrix-vector product and one ``Allreduce`` per step, together with the task's own integrals.
The rows weigh the variable ``variable`` names: ``u`` (every task's field: the temperature, the
transmembrane potential), or another that the task simulates (``Task.variables``: the
Mitchell-Schaeffer gate ``w`` of the ATP task, which no electrode can read: a diagnostic of
what the agent would gain from it).
To add one: subclass :class:`Observation`, decorate it with ``@OBSERVATIONS.register("name")``,
implement :meth:`Observation.rows`, and add the YAML.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from dolfinx import fem

from physicsrl.checks import integer, number, positive, vector
from physicsrl.envs.registry import Registry
from physicsrl.fem.integrals import form_rows, point_rows, quadrant_weights

OBSERVATIONS = Registry("observation")


@dataclass(frozen=True)
class Observation:
    """Base class: ``size`` numbers, each :math:`\\int_\\Omega g_k v\\,dx` for fixed g_k, v
    the variable ``variable`` (``u``; checked against the task's ``variables`` by
    :func:`~physicsrl.envs.factory.parts`)."""

    name: ClassVar[str]
    # keyword-only, so that a subclass may declare fields without defaults
    variable: str = field(default="u", kw_only=True)

    @property
    def size(self) -> int:
        raise NotImplementedError

    def rows(self, V: fem.FunctionSpace) -> np.ndarray:
        """Array (size, owned dofs of V): the weights of the owned dofs. Collective."""
        raise NotImplementedError

    def outside(self, extent: float) -> list[tuple[float, float]]:
        """The points this observation reads at that lie outside the square
        [-extent, extent]^2 (checked before a mesh is built); none for integrals over regions."""
        return []


@OBSERVATIONS.register("quadrants")
@dataclass(frozen=True)
class Quadrants(Observation):
    """The integral of u over each quadrant around ``centre`` (4 numbers; units of u x area),
    in the order (x<c_x, y<c_y), (x>c_x, y<c_y), (x<c_x, y>c_y), (x>c_x, y>c_y)."""

    centre: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        object.__setattr__(self, "centre", vector("centre", self.centre, 2))

    @property
    def size(self) -> int:
        return 4

    def rows(self, V: fem.FunctionSpace) -> np.ndarray:
        return form_rows(V, quadrant_weights(V.mesh, self.centre))


@OBSERVATIONS.register("catheter")
@dataclass(frozen=True)
class Catheter(Observation):
    r"""A simulated pentaray catheter (report section 4.3.4, equation 7).

    ``splines`` splines at angles ``first_angle_deg - k 360 / splines`` degrees (k = 0, 1, ...),
    each carrying one electrode at each of ``distances`` from ``centre``; electrode
    :math:`(c_x, c_y)` reads

    .. math:: \int_\Omega e^{-\mu |x - c|}\, u(x)\, dx
              \quad (\text{divided by } 2\pi/\mu^2 \text{ if } \texttt{normalise}),

    in the order spline-major (spline 0's electrodes first, in the order of ``distances``).
    Units: u x area (u itself if normalised).

    Method: the kernel (width :math:`1/\mu` = 0.03 at :math:`\mu` = 33, 55 x narrower than a
    cell of the 60 x 60 grid) is integrated exactly against the finite element basis with a
    product rule in polar coordinates around each electrode: Gauss-Laguerre in
    :math:`\mu r` (``radial_points`` nodes, exact for the radial weight :math:`r e^{-\mu r}`
    times polynomials of degree < 2 ``radial_points`` - 1) times the trapezoidal rule in the
    angle (``angular_points`` nodes), the basis functions tabulated exactly at the nodes
    (:func:`~physicsrl.fem.integrals.point_rows`). Nodes outside the domain are dropped. The
    reading is therefore the kernel applied to the finite element field itself, independent of
    where the nodes are: for u linear it equals :math:`2\pi/\mu^2\, u(c)` to 1e-14 on any mesh,
    and for a smooth field (``1 + sin(x/10) cos(y/13) / 2``) the 60 x 60 and 240 x 240 readings
    agree to 0.2% (both P1 triangles and Q1). The quadrature of the reference's own code (the
    mesh's quadrature points) saw the kernel only where a point happened to fall within ~0.1 of
    an electrode: noise from the node alignment.
    """

    splines: int = 5
    first_angle_deg: float = 90.0
    distances: tuple[float, ...] = (37.5, 32.5, 17.5, 12.5)
    centre: tuple[float, float] = (0.0, 0.0)
    mu: float = 33.0
    normalise: bool = False
    radial_points: int = 16
    angular_points: int = 32

    def __post_init__(self):
        integer("splines", self.splines, 1)
        number("first_angle_deg", self.first_angle_deg)
        distances = vector("distances", self.distances)
        if not distances or min(distances) < 0:
            raise ValueError(
                f"distances must be a non-empty list of numbers >= 0, got {self.distances!r}"
            )
        object.__setattr__(self, "distances", distances)
        object.__setattr__(self, "centre", vector("centre", self.centre, 2))
        positive("mu", self.mu)
        if not isinstance(self.normalise, bool):
            raise ValueError(f"normalise must be true or false, got {self.normalise!r}")
        integer("radial_points", self.radial_points, 1)
        integer("angular_points", self.angular_points, 1)

    @property
    def size(self) -> int:
        return self.splines * len(self.distances)

    def positions(self) -> np.ndarray:
        """Array (size, 2): the electrode coordinates, in reading order."""
        angles = (
            np.deg2rad(self.first_angle_deg) - 2 * np.pi * np.arange(self.splines) / self.splines
        )
        direction = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (splines, 2)
        radius = np.asarray(self.distances)
        return (np.asarray(self.centre) + direction[:, None, :] * radius[None, :, None]).reshape(
            -1, 2
        )

    def outside(self, extent: float) -> list[tuple[float, float]]:
        positions = self.positions()
        return [tuple(p) for p in positions[np.abs(positions).max(axis=1) > extent].tolist()]

    def rows(self, V: fem.FunctionSpace) -> np.ndarray:
        t, w = np.polynomial.laguerre.laggauss(self.radial_points)  # int e^-t f(t) dt
        theta = 2 * np.pi * np.arange(self.angular_points) / self.angular_points
        r = t / self.mu
        offsets = r[:, None, None] * np.stack([np.cos(theta), np.sin(theta)], -1)[None]
        # dx = r dr dtheta, r dr = t dt / mu^2: weight w t / mu^2 x 2 pi / angular_points
        weights = np.repeat(
            w * t / self.mu**2 * (2 * np.pi / self.angular_points), self.angular_points
        )
        if self.normalise:
            weights /= 2 * math.pi / self.mu**2
        positions = self.positions()
        points = positions[:, None, :] + offsets.reshape(1, -1, 2)
        try:
            return point_rows(V, points, np.broadcast_to(weights, points.shape[:2]).copy())
        except ValueError:
            raise ValueError(
                f"observation.distances: the electrodes at {positions.tolist()} are not all "
                "inside the mesh"
            ) from None
