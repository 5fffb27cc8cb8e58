r"""The explicit lumped-mass scheme of the monodomain Mitchell-Schaeffer model.

Lumped mass :math:`m_i = \sum_j M_{ij} = \int_\Omega \phi_i\,dx` (the row sums of the
assembled mass matrix, since :math:`\sum_j \phi_j = 1`), stiffness
:math:`K_{ij} = \int_\Omega \nabla\phi_j \cdot \nabla\phi_i\,dx` (assembled once, this rank's
owned rows with local column indices, ghosts included, padded to one row length), nodal
reaction and nodal current. One step of :math:`\Delta t` (a sub-step :math:`\Delta t / k`
with ``substeps=k``):

.. math::

    u_i^{n+1} = u_i^n + \Delta t \Big[-\frac{D}{m_i} (K u^n)_i
      + \frac{w_i^n (u_i^n)^2 (1 - u_i^n)}{\tau_\mathrm{in}} - \frac{u_i^n}{\tau_\mathrm{out}}
      + I_i\Big],
    \qquad I_i = \frac{1}{m_i} \int_\Omega I_\mathrm{app}\, \phi_i\, dx,

and forward Euler for :math:`w_i` as in the implicit scheme. :math:`I_i` is the
lumped-mass-weighted average of the (cell-wise constant) current over the cells around node
:math:`i`. The row operator :math:`C = I - \Delta t D M_L^{-1} K` is stored, so that one C
pass (``ms_explicit`` of :mod:`physicsrl.fem.kernels`) computes the owned :math:`u^{n+1}` and
the gate in place (a new value waits in a ring of ``lag + 1`` values until no later row reads
the old one: DOLFINx's dof order keeps the lag near the grid's side); then one ghost update
(``scatter_forward``).

When the mesh is a structured grid of square Q1 cells (the rectangles of
``mesh.create_rectangle``), :math:`C` is the 9-point stencil
:math:`u_{ij} - \frac{\Delta t D}{3 h^2}\big(8 u_{ij} - \sum_{\text{8 neighbours}} u\big)`,
with the Neumann condition as a mirror (node -1 reads node 1).
:func:`~physicsrl.fem.strips.square_stencil` detects it and checks it against the assembled
rows on a random vector; :meth:`ExplicitStep.advance` then moves the state to strips of node
rows, one per rank, in grid order (:mod:`physicsrl.fem.strips`), runs its steps with the
stencil (``ms_stencil``: no index arrays, no matrix values, 32 bytes per node per step; on
several ranks the two halo rows are exchanged before every step, on one rank all steps run in
one call) and moves the state back, when it has at least :data:`GRID_MIN_STEPS` steps to run
(the transfers cost a few passes).

Stability of the diffusion part: forward Euler needs :math:`\Delta t \le 2 / (D \lambda_\max)`,
:math:`\lambda_\max` the largest eigenvalue of :math:`M_L^{-1} K` (real and non-negative: it is
similar to the symmetric :math:`M_L^{-1/2} K M_L^{-1/2}`). We bound it by Gershgorin's theorem,
:math:`\lambda_\max \le \max_i \sum_j |K_{ij}| / m_i`: a safe limit, computed in one pass and
one reduction. On uniform square Q1 cells of side h the bound is :math:`16 / (3 h^2)` against
the true :math:`4 / h^2`, so the limit it gives, :math:`3 h^2 / (8 D)`, is 3/4 of the true
one (0.032 for h = 1/30, D = 0.013: 3000 cells per side on [-50, 50]^2 run at dt = 0.03).
"""

from __future__ import annotations

import time

import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx.common import IndexMap
from mpi4py import MPI

from physicsrl.fem.errors import InvalidValue
from physicsrl.fem.kernels import pointer
from physicsrl.fem.strips import square_stencil


def lumped_mass(V: fem.FunctionSpace) -> np.ndarray:
    """:math:`m_i = \\int \\phi_i dx` of this rank's owned dofs (shape (owned,))."""
    return _nodal_integrals(fem.form(ufl.TestFunction(V) * ufl.dx), V)


def _nodal_integrals(form: fem.Form, V: fem.FunctionSpace) -> np.ndarray:
    """The owned entries of the assembled vector of a linear form (ghost parts added)."""
    vector = fem.assemble_vector(form)
    vector.scatter_reverse(la.InsertMode.add)
    return vector.array[: V.dofmap.index_map.size_local].copy()


def stiffness_rows(V: fem.FunctionSpace) -> tuple[np.ndarray, np.ndarray, np.ndarray, IndexMap]:
    """(indptr int64, indices int32, values, column map) of the owned rows of the stiffness
    matrix K, with local column indices of the column map: V's owned and ghost dofs, then the
    dofs that K alone couples to an owned row (on a cell of another rank that holds an owned
    dof only at a corner; DOLFINx's sparsity pattern appends them as ghosts)."""
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    K = fem.assemble_matrix(fem.form(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx))
    K.scatter_reverse()
    owned = V.dofmap.index_map.size_local
    indptr = np.ascontiguousarray(K.indptr[: owned + 1], dtype=np.int64)
    indices = np.ascontiguousarray(K.indices[: indptr[-1]], dtype=np.int32)
    return indptr, indices, np.array(K.data[: indptr[-1]], dtype=np.float64), K.index_map(1)


def stability_limit(row_sums: np.ndarray, mass: np.ndarray, D: float, comm=None) -> float:
    r"""The explicit scheme's largest stable (sub-)step, :math:`2 / (D \max_i \sum_j |K_{ij}| /
    m_i)` (Gershgorin, module docstring), from the rows' sums of :math:`|K_{ij}|` and their
    lumped masses; the maximum over ``comm``'s ranks when given (a reduction)."""
    local = float((row_sums / mass).max(initial=0.0))
    return 2.0 / (D * (local if comm is None else comm.allreduce(local, op=MPI.MAX)))


GRID_MIN_STEPS = 8
"""Fewest steps per :meth:`ExplicitStep.advance` for which the structured path is taken."""


class ExplicitStep:
    """Steps of the explicit scheme (module docstring) on ``u`` and ``w`` (``fem.Function``,
    updated in place, ghosts included). Construct on every rank.

    ``dt`` is the sub-step; :meth:`check_stable` raises :class:`InvalidValue` (one line) if it
    exceeds :attr:`dt_max`. :meth:`set_current` takes the DG0 current; :meth:`advance` runs
    steps. ``kernels`` is the compiled module (``None``: numpy). ``timings`` gets the
    seconds of the fused passes (``"explicit"``) and of the ghost updates (``"ghosts"``).
    """

    def __init__(
        self, u, w, *, D, tau_in, tau_out, tau_open, tau_close, u_gate, dt, kernels, timings: dict
    ):
        V = u.function_space
        self.u, self.w, self.dt, self.kernels, self.timings = u, w, float(dt), kernels, timings
        self.owned = V.dofmap.index_map.size_local
        self.comm = V.mesh.comm
        self.mass = lumped_mass(V)
        indptr, indices, values, self.column_map = stiffness_rows(V)
        extended = self.column_map.num_ghosts > V.dofmap.index_map.num_ghosts
        if self.comm.allreduce(extended, op=MPI.LOR):  # (creating a vector is collective)
            self.state = la.vector(self.column_map)  # what the rows read
        else:
            self.state = u.x
        rows = np.repeat(np.arange(self.owned), np.diff(indptr))
        row_sums = np.add.reduceat(np.abs(values), indptr[:-1]) if self.owned else np.zeros(0)
        self.dt_max = stability_limit(row_sums, self.mass, D, self.comm)
        values *= -self.dt * D / self.mass[rows]
        values[indices == rows] += 1.0
        # Rows padded to one width (ELLPACK) with zeros at the diagonal's column.
        lengths = np.diff(indptr)
        self.width = int(lengths.max(initial=1))
        slots = np.arange(indptr[-1]) - np.repeat(indptr[:-1], lengths)
        self.columns = np.repeat(np.arange(self.owned, dtype=np.int32), self.width).reshape(
            self.owned, self.width
        )
        self.values = np.zeros((self.owned, self.width))
        self.columns[rows, slots] = indices
        self.values[rows, slots] = values
        behind = rows - indices
        self.lag = int(behind[indices < self.owned].max(initial=0))
        self.ring = np.empty(self.lag + 1)
        self.grid = square_stencil(V, self._apply, self.dt * D / 3)
        self.constants = (
            self.dt,
            tau_in,
            tau_out,
            u_gate,
            1.0 - self.dt / tau_open,
            self.dt / tau_open,
            1.0 - self.dt / tau_close,
        )
        self._current_form = None
        self.current = np.zeros(self.owned)  # dt I_i
        self.has_current = False
        self._args = None  # the kernel's arguments
        for name in ("explicit", "ghosts"):
            timings.setdefault(name, 0.0)

    def check_stable(self, mesh_description: str) -> None:
        """:class:`InvalidValue` if the (sub-)step exceeds the stability limit."""
        if self.dt > self.dt_max:
            raise InvalidValue(
                f"dt / substeps = {self.dt:g} exceeds the explicit scheme's stability limit "
                f"{self.dt_max:.4g} (Gershgorin bound 2 / (D max_i sum_j |K_ij| / m_i)) on "
                f"{mesh_description}: raise substeps or use scheme='implicit'"
            )

    def set_current(self, I_app: fem.Function) -> None:
        """Take the nodal current I_i = (int I_app phi_i) / m_i from the DG0 ``I_app``."""
        if self._current_form is None:
            V = self.u.function_space
            self._current_form = fem.form(I_app * ufl.TestFunction(V) * ufl.dx)
        np.multiply(
            _nodal_integrals(self._current_form, self.u.function_space),
            self.dt / self.mass,
            out=self.current,
        )
        self.has_current = self.comm.allreduce(bool(self.current.any()), op=MPI.LOR)

    def advance(self, steps: int) -> None:
        """Run ``steps`` steps of u and w in place."""
        if self.grid is not None and self.kernels is not None and steps >= GRID_MIN_STEPS:
            self._advance_grid(steps)
            return
        clock, timings, step, state = time.perf_counter, self.timings, self._step, self.state
        local = len(self.u.x.array)
        if state is not self.u.x:
            state.array[:local] = self.u.x.array
            state.scatter_forward()
        for _ in range(steps):
            start = clock()
            step()
            middle = clock()
            state.scatter_forward()
            timings["explicit"] += middle - start
            timings["ghosts"] += clock() - middle
        if state is not self.u.x:
            self.u.x.array[:] = state.array[:local]

    def _advance_grid(self, steps: int) -> None:
        """``steps`` steps with the stencil on this rank's strip of the grid
        (:mod:`physicsrl.fem.strips`): the state moved there and back, the halo rows refreshed
        before every step on several ranks (on one all steps run in one call)."""
        start = time.perf_counter()
        strips, c = self.grid
        owned, ghosts = self.owned, 0.0
        u, w = self.u.x.array, self.w.x.array
        strip, other = strips.scatter(u[:owned]), np.empty(strips.shape)
        grid_w = strips.scatter(w[:owned])
        current = strips.scatter(self.current)[1:-1] if self.has_current else None
        ffi, kernel = self.kernels.ffi, self.kernels.lib.ms_stencil
        rows, n = strips.shape[0] - 2, strips.width - 1
        arguments = (
            pointer(ffi, grid_w[1:-1]),
            ffi.NULL if current is None else pointer(ffi, current),
            c,
            *self.constants,
        )
        buffers = [pointer(ffi, strip), pointer(ffi, other)]  # swapped with the arrays
        mirror = int(strips.comm.size == 1)  # one strip: its halos are the grid's mirrors
        for count in [steps] if mirror else [1] * steps:
            if not mirror:
                begin = time.perf_counter()
                strips.fill_halos(strip)
                ghosts += time.perf_counter() - begin
            kernel(rows, n, count, mirror, mirror, buffers[0], *arguments, buffers[1])
            if count % 2:
                strip, other = other, strip
                buffers.reverse()
        strips.gather(strip, u[:owned])
        strips.gather(grid_w, w[:owned])
        if not mirror:
            begin = time.perf_counter()
            self.u.x.scatter_forward()
            self.w.x.scatter_forward()
            ghosts += time.perf_counter() - begin
        self.timings["explicit"] += time.perf_counter() - start - ghosts
        self.timings["ghosts"] += ghosts

    def _step(self) -> None:
        current = self.current if self.has_current else None
        if self.kernels is None:
            self._numpy_step(self.state.array, self.w.x.array, current)
            return
        if self._args is None:  # pointers made once: the arrays stay in place
            ffi, u, w = self.kernels.ffi, self.state.array, self.w.x.array
            self._args = (
                (self.owned, w.size, self.width, pointer(ffi, self.columns, "int32_t *")),
                (pointer(ffi, self.values), pointer(ffi, u), pointer(ffi, w)),
                (ffi.NULL, pointer(ffi, self.current)),
                (*self.constants, self.lag, pointer(ffi, self.ring)),
            )
        head, arrays, currents, tail = self._args
        self.kernels.lib.ms_explicit(*head, *arrays, currents[current is not None], *tail)

    def _apply(self, u: np.ndarray) -> np.ndarray:
        """C times the nodal values ``u`` (this rank's dofs, ghosts included): owned rows."""
        vector = la.vector(self.column_map)
        vector.array[: len(u)] = u
        vector.scatter_forward()
        return np.einsum("ij,ij->i", self.values, vector.array[self.columns])

    def _numpy_step(self, u, w, current) -> None:
        dt, tau_in, tau_out, u_gate, a_open, b_open, a_close = self.constants
        n = self.owned
        diffusion = np.einsum("ij,ij->i", self.values, u[self.columns])
        own = u[:n]
        diffusion += own * (dt / tau_in * w[:n] * own * (1.0 - own) - dt / tau_out)
        if current is not None:
            diffusion += current
        w[:] = np.where(u[: len(w)] < u_gate, w * a_open + b_open, w * a_close)
        u[:n] = diffusion
