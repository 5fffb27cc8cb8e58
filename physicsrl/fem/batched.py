r"""The Mitchell-Schaeffer time loop on torch for B replicas at once (CPU or CUDA).

DOLFINx builds the operators once, on a mesh of this process alone (``MPI.COMM_SELF``: each rank
owns its replicas on its own copy of the mesh); the time loop is then torch only. The state is
two tensors ``u``, ``w`` of shape (B, n) (n dofs of the Lagrange degree-1 space), the applied
current a tensor (B, c) of cell values (the DG0 dofs of :class:`MonodomainMitchellSchaeffer`'s
``I_app``) or ``None``. Every step is a few matrix products (or a stencil) and elementwise
passes over all B replicas; the schemes are those of :mod:`physicsrl.fem.monodomain`
(``"implicit"``, the report's) and :mod:`physicsrl.fem.explicit` (``"explicit"``), for the same
dt and constants.

Implicit (the report's equations 4-5): gate by forward Euler, then solve

.. math::

    (M + \Delta t D K)\, u^{n+1} = (1 - \Delta t/\tau_\mathrm{out}) M u^n
        + \frac{\Delta t}{\tau_\mathrm{in}} \int_\Omega w^n (u^n)^2 (1 - u^n) \phi_i\, dx
        + \Delta t\, P I,
    \qquad P_{ic} = \int_c \phi_i\, dx,

with M, K the consistent mass and stiffness and P the mixed (P1 test, DG0 trial) mass. The
reaction integral is the exact quadrature of :class:`~physicsrl.fem.quadrature.CellQuadrature`
(degree 5 per direction): gather the cells' dofs, values at the points (one small matrix
product), integrand, cell vectors, ``index_add_`` into the dofs, all replicas at once. This is
the quadrature sum of :class:`~physicsrl.fem.monodomain.MitchellSchaefferRHS` with the linear
terms moved into M and P (exact either way). On a structured grid of Q1 cells (the rectangles
of ``mesh.create_rectangle``, checked by :func:`~physicsrl.fem.grid.grid_of`) the solve is
direct, by fast diagonalisation (:mod:`physicsrl.fem.grid`: four dense products with the
grid's side, all B right-hand sides in each); on any other mesh it is conjugate gradients with
a Jacobi preconditioner on all B right-hand sides together (one sparse product with an (n, B)
block per iteration), warm-started from u^n, until every replica's preconditioned residual is
below ``rtol`` times that of its right-hand side (PETSc's test with ``ksp_rtol``). The PETSc
path stops its CG at the same tolerance, so the two differ within it.

Explicit (lumped mass :math:`m_i = \sum_j M_{ij}`, :func:`~physicsrl.fem.explicit.lumped_mass`):

.. math::

    u^{n+1} = C u^n + \Delta t\big(w^n (u^n)^2 (1 - u^n)/\tau_\mathrm{in} - u^n/\tau_\mathrm{out}
        + M_L^{-1} P I\big), \qquad C = I - \Delta t D M_L^{-1} K,

with the stability limit of :class:`~physicsrl.fem.explicit.ExplicitStep` (refused above it).
On square Q1 cells :math:`C` is the 9-point stencil of :mod:`physicsrl.fem.grid` (checked
against the assembled operator), applied to the replicas as (B, n_y, n_x) grids; elsewhere it
is a sparse product.

With ``compiled=True`` each step runs through ``torch.compile``, which fuses its elementwise
passes, gathers and scatters into a few loops; ``tests/test_fem_batched.py`` checks it against
the eager path.

Precision: float64 by default on the CPU, float32 on CUDA (``dtype`` overrides). The potential
is O(1) and every step adds O(dt) increments, so float32's relative rounding of 6e-8 per step
accumulates far below the schemes' own O(h^2 + dt) errors: the conduction velocity and action
potential duration of a planar wave (explicit, h = 0.1) differ from float64 by 2e-6 and 7e-5
relative (0.11991 mm/ms, 140.4 ms; ``tests/test_fem_batched.py`` asserts < 0.5%). The CG
tolerance is raised to the dtype's reach (``rtol`` is floored at 100 x its machine epsilon).
Compiled, a replica's steps do not depend on the other replicas of its batch, to the bit (the
current enters through :func:`per_replica`); the eager steps size their blocks and sparse
products by the batch and round a replica differently for another batch size. Either way the
rounding follows the CPU's vector instructions (AVX2 and AVX-512 differ).
"""

from __future__ import annotations

import warnings
from contextlib import contextmanager

import numpy as np
import scipy.sparse
import torch
import ufl
from dolfinx import fem, mesh

from physicsrl.fem.errors import InvalidValue, SimulationDiverged
from physicsrl.fem.explicit import lumped_mass, stability_limit
from physicsrl.fem.grid import grid_of
from physicsrl.fem.monodomain import SCHEMES, scheme_substeps
from physicsrl.fem.quadrature import CellQuadrature
from physicsrl.fem.resolution import resolution
from physicsrl.fem.strips import square_stencil
from physicsrl.fem.values import finite, integer, nonnegative, positive

DTYPES = {"float32": torch.float32, "float64": torch.float64}
"""The dtypes of the state, by name."""

CG_RTOL = 1e-10
"""Relative tolerance of the batched CG (that of :data:`~physicsrl.fem.DEFAULT_PETSC_OPTIONS`)."""

CG_MAX_ITERATIONS = 1000


def default_device() -> str:
    """``"cuda"`` when torch sees a GPU, else ``"cpu"``."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def per_replica(matrix: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(B, m): ``matrix`` (m, n, dense or sparse) times each row of ``x`` (B, n), one product
    per replica, so that a replica's result does not depend on its batch: one product with the
    (n, B) block rounds each column differently for other B (MKL's dense and sparse kernels)."""
    if not len(x):
        return x.new_zeros((0, matrix.shape[0]), dtype=matrix.dtype)
    return torch.stack([matrix @ row for row in x.to(matrix.dtype)])


def _sparse(matrix, device, dtype) -> torch.Tensor:
    """A scipy CSR matrix as a torch sparse CSR tensor."""
    matrix = matrix.tocsr()
    matrix.sort_indices()
    with warnings.catch_warnings():  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(
            torch.tensor(matrix.indptr, dtype=torch.int64),
            torch.tensor(matrix.indices, dtype=torch.int64),
            torch.tensor(matrix.data),
            size=matrix.shape,
        ).to(device=device, dtype=dtype)


def _assemble(form) -> object:
    """The scipy CSR matrix of a bilinear form on a COMM_SELF mesh."""
    return fem.assemble_matrix(fem.form(form)).to_scipy()


class BatchedMonodomain:
    """Operators and time loop of the monodomain Mitchell-Schaeffer model for B replicas
    (module docstring).

    Parameters
    ----------
    domain:
        A DOLFINx mesh on ``MPI.COMM_SELF``.
    tau_in, tau_out, tau_open, tau_close, u_gate, D, dt:
        As :class:`~physicsrl.fem.MonodomainMitchellSchaeffer` (the report's values:
        ``physicsrl.envs.atp.MSModel().numerics()``).
    scheme, substeps:
        ``"implicit"`` or ``"explicit"`` with ``substeps`` sub-steps per dt (explicit only).
    device, dtype:
        Where the tensors live (default :func:`default_device`) and their precision (float32
        or float64, a torch dtype or its name; default float64 on the CPU, float32 on CUDA).
    rtol:
        CG tolerance of the implicit scheme (on meshes that are not structured grids).
    compiled:
        Run the step through ``torch.compile``, which fuses its elementwise passes, gathers and
        scatters into a few loops (C++ on the CPU, Triton on CUDA): the right-hand side of the
        implicit scheme is then written out point by point (:meth:`fused_right_hand_side`).
        The first steps of each batch size pay the compilation (seconds; cached on disk).
    threads:
        torch's CPU threads during the time loop (default 1: one rank per core, as MPI codes
        run; torch's default of every core made the planar-wave test 20x slower on the
        2-core machine shared with other processes).

    Attributes
    ----------
    V:
        The degree-1 Lagrange space of u and w; ``V.tabulate_dof_coordinates()`` are the nodes.
    num_dofs, num_cells:
        n and c of the state (B, n) and the current (B, c).
    iterations:
        CG iterations of all implicit steps so far (none on a structured grid: direct solve).
    resolution:
        How well the mesh resolves the front (:func:`physicsrl.fem.resolution.resolution`).
    """

    def __init__(
        self,
        domain: mesh.Mesh,
        *,
        tau_in: float,
        tau_out: float,
        tau_open: float,
        tau_close: float,
        u_gate: float,
        D: float,
        dt: float,
        scheme: str = SCHEMES[0],
        substeps: int = 1,
        device: str | torch.device | None = None,
        dtype: torch.dtype | str | None = None,
        rtol: float = CG_RTOL,
        threads: int = 1,
        compiled: bool = False,
    ):
        if domain.comm.size != 1:
            raise InvalidValue("BatchedMonodomain: the mesh must live on MPI.COMM_SELF")
        substeps = scheme_substeps(scheme, substeps)
        rates = {"tau_in": tau_in, "tau_out": tau_out, "tau_open": tau_open}
        for name, value in {**rates, "tau_close": tau_close, "D": D, "dt": dt}.items():
            positive(name, value)
        positive("rtol", rtol)
        self.u_gate = finite("u_gate", u_gate)
        self.device = torch.device(default_device() if device is None else device)
        dtype = DTYPES.get(dtype, dtype) if isinstance(dtype, str) else dtype
        if dtype not in (None, *DTYPES.values()):
            raise InvalidValue(f"dtype must be float32 or float64, got {dtype!r}")
        self.dtype = dtype or (torch.float32 if self.device.type == "cuda" else torch.float64)
        self.scheme, self.substeps, self.dt = scheme, substeps, float(dt)
        self.iterations = 0
        self.replica_steps = 0  # steps of dt advanced, summed over the replicas
        self.batch_steps = 0  # steps of dt advanced, each of one batch of replicas
        self.threads = integer("threads", threads)
        self.resolution = resolution(domain, D, tau_in, scheme, self.dt)
        V = self.V = fem.functionspace(domain, ("Lagrange", 1))
        Q = fem.functionspace(domain, ("DG", 0))
        self.num_dofs = V.dofmap.index_map.size_local
        self.num_cells = Q.dofmap.index_map.size_local
        u, v, q = ufl.TrialFunction(V), ufl.TestFunction(V), ufl.TrialFunction(Q)
        mass, stiffness = (
            _assemble(u * v * ufl.dx),
            _assemble(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx),
        )
        current = _assemble(q * v * ufl.dx)  # P, (n, c)
        h = self.dt / substeps  # the (sub-)step
        self._gate = (u_gate, 1.0 - h / tau_open, h / tau_open, 1.0 - h / tau_close)
        self._k_in, self._k_out = h / tau_in, h / tau_out
        fuse = torch.compile if compiled else lambda step: step
        if scheme == "explicit":
            m = lumped_mass(V)
            row_sums = np.asarray(abs(stiffness).sum(axis=1)).ravel()
            self.dt_max = stability_limit(row_sums, m, D)
            if h > self.dt_max:
                raise InvalidValue(
                    f"dt / substeps = {h:g} exceeds the explicit scheme's stability limit "
                    f"{self.dt_max:.4g} on {self.num_cells} cells: raise substeps or use "
                    "scheme='implicit'"
                )
            inverse = scipy.sparse.diags(1.0 / m)
            C = scipy.sparse.identity(len(m)) - h * D * inverse @ stiffness
            self._current = _sparse(h * inverse @ current, self.device, self.dtype)
            square = square_stencil(V, C.__matmul__, h * D / 3)
            if square is None:
                self._use_grid(None)
                self._C = _sparse(C, self.device, self.dtype)
                self._step = fuse(self._explicit_step)
            else:
                self._use_grid(grid_of(V))
                self._c = square[1]
                self._step = fuse(self._stencil_step)
            return
        A = mass + self.dt * D * stiffness
        self._use_grid(grid_of(V, mass, stiffness))
        if self._grid is None:
            self._A = _sparse(A, self.device, self.dtype)
            self._inverse_diagonal = self.tensor(1.0 / A.diagonal())[:, None]
        else:
            qx, qy, d = self._grid.fast_diagonalisation(self.dt * D)
            self._qx, self._qy = self.tensor(qx), self.tensor(qy)
            self._qx_t, self._qy_t = self._qx.T.contiguous(), self._qy.T.contiguous()
            self._d = self.tensor(d)[:, :, None]
        self._M = _sparse(mass, self.device, self.dtype)
        self._current = _sparse(self.dt * current, self.device, self.dtype)
        self.rtol = max(float(rtol), 100 * torch.finfo(self.dtype).eps)
        quadrature = CellQuadrature(V, 5)  # exact: w u^3 phi has degree 5 (per direction)
        self._dofs_t = torch.tensor(quadrature.dofs.T, dtype=torch.int64, device=self.device)
        self._phi = torch.as_tensor(quadrature.phi, device=self.device).to(self.dtype)  # (q, d)
        self._phi_t = self._phi.T.contiguous()
        weights = (
            quadrature.cell_det[:, None] * quadrature.point_weights[None, :]
            if quadrature.affine
            else quadrature.point_weights
        )
        self._weights = self.tensor(self._k_in * weights.T)  # (q, cells)
        self._phi_rows = quadrature.phi.tolist()
        # values per block of the reaction: one block on a GPU; ~1 MB work arrays on a CPU
        self.block_values = 2**62 if self.device.type == "cuda" else 2**17
        self._right_hand_side = fuse(
            self.fused_right_hand_side if compiled else self.blocked_right_hand_side
        )

    def _use_grid(self, grid) -> None:
        """Keep ``grid`` (a :class:`~physicsrl.fem.grid.Grid` or None) and its permutations:
        ``_order`` takes dof-ordered rows to grid order, ``_dof_order`` back (both gathers:
        scattering with an index is several times slower on the CPU)."""
        self._grid = grid
        if grid is not None:
            self._order = torch.tensor(grid.order, device=self.device)
            self._dof_order = torch.argsort(self._order)

    # state --------------------------------------------------------------------------------
    def nodal(self, f) -> torch.Tensor:
        """The nodal values (n,) of a number or a callable ``f(x)`` (x of shape (3, n)), as the
        state's tensors hold them."""
        x = self.V.tabulate_dof_coordinates().T
        values = np.broadcast_to(f(x) if callable(f) else float(f), (self.num_dofs,))
        return torch.as_tensor(np.array(values), device=self.device).to(self.dtype)

    def tensor(self, array) -> torch.Tensor:
        """``array`` on the device with the state's dtype."""
        return torch.as_tensor(array, device=self.device).to(self.dtype)

    # stepping -----------------------------------------------------------------------------
    def steps(self, T: float) -> int:
        """The number of steps of dt in T >= 0 (rounded: 50 / 0.03 is not whole)."""
        return round(nonnegative("T", T) / self.dt)

    def advance(self, u: torch.Tensor, w: torch.Tensor, current, steps: int) -> torch.Tensor:
        """Run ``steps`` steps of dt on ``u``, ``w`` (B, n), in place, with the current
        ``current`` ((B, c) cell values or None); return whether each replica's u is still
        finite, (B,) bool (a replica that is not does not stop the others). Inside, the
        replicas are columns ((n, B): sparse products and gathers then move contiguous rows of
        B values), or, for the explicit stencil, (B, n_y, n_x) grids."""
        steps = integer("steps", steps, low=0)
        wanted = ((len(u), self.num_dofs), self.dtype)
        if any((tuple(x.shape), x.dtype) != wanted for x in (u, w)):
            raise InvalidValue(
                f"u and w must be {wanted[1]} tensors of shape (B, {self.num_dofs}), got "
                f"{u.dtype} {tuple(u.shape)} and {w.dtype} {tuple(w.shape)}"
            )
        if current is not None and current.shape != (len(u), self.num_cells):
            raise InvalidValue(
                f"current must have the shape {(len(u), self.num_cells)}, got {current.shape}"
            )
        self.replica_steps += len(u) * steps
        self.batch_steps += steps
        with self._threads():
            forcing = None if current is None else per_replica(self._current, current).T
            stencil = self.scheme == "explicit" and self._grid is not None
            if stencil:
                side = (len(u), len(self._grid.y), len(self._grid.x))
                U, W = (x.index_select(1, self._order).view(side) for x in (u, w))
                if forcing is not None:
                    forcing = forcing.T.index_select(1, self._order).view(side)
            else:
                U, W = u.T.contiguous(), w.T.contiguous()
            if self.scheme == "explicit":
                other = torch.empty_like(U)  # the next u: two buffers, no allocation per step
                for _ in range(steps * self.substeps):
                    self._step(U, W, forcing, other)
                    U, other = other, U
            else:
                for _ in range(steps):
                    b, W = self._right_hand_side(U, W, forcing)
                    self.solve(b, U)
            if stencil:
                for x, grid in ((u, U), (w, W)):
                    x.copy_(grid.view(len(u), -1).index_select(1, self._dof_order))
            else:
                u.copy_(U.T)
                w.copy_(W.T)
            return torch.isfinite(u).all(dim=1)

    @contextmanager
    def _threads(self):
        """torch's CPU threads set to :attr:`threads` for the time loop, then restored."""
        if self.device.type != "cpu":
            yield
            return
        previous = torch.get_num_threads()
        torch.set_num_threads(self.threads)
        try:
            yield
        finally:
            torch.set_num_threads(previous)

    def _gated(self, u: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """w^{n+1}: forward Euler of the gate equation, from u^n and w^n."""
        u_gate, a_open, b_open, a_close = self._gate
        return torch.where(u < u_gate, w * a_open + b_open, w * a_close)

    def _nodal_reaction(self, u: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """The explicit scheme's reaction increment dt (w u^2 (1 - u)/tau_in - u/tau_out)."""
        return u * (self._k_in * w * u * (1.0 - u) - self._k_out)

    def _explicit_step(self, u, w, forcing, out) -> None:
        """u^{n+1} into ``out`` and w^{n+1} into ``w`` (in place) of the explicit scheme,
        replicas as columns (n, B)."""
        new = self._C @ u + self._nodal_reaction(u, w)
        out.copy_(new if forcing is None else new + forcing)
        w.copy_(self._gated(u, w))

    def _stencil_step(self, u, w, forcing, out) -> None:
        """u^{n+1} into ``out`` and w^{n+1} into ``w`` (in place) of the explicit scheme on
        square cells, u, w and out (B, n_y, n_x): the 9-point stencil of
        :mod:`physicsrl.fem.grid`, the Neumann condition a mirror. Writing into buffers matters
        at 1M nodes: a new 8 MB array per step costs more than the step (fresh pages)."""
        padded = torch.nn.functional.pad(u, (1, 1, 1, 1), mode="reflect")
        ny, nx = u.shape[1:]
        ring = sum(
            padded[:, 1 + di : ny + 1 + di, 1 + dj : nx + 1 + dj]
            for di in (-1, 0, 1)
            for dj in (-1, 0, 1)
            if di or dj
        )
        new = u - self._c * (8.0 * u - ring) + self._nodal_reaction(u, w)
        out.copy_(new if forcing is None else new + forcing)
        w.copy_(self._gated(u, w))

    def reaction(self, u: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        r"""(n, B): :math:`\frac{\Delta t}{\tau_\mathrm{in}} \int w u^2 (1 - u) \phi_i dx`
        for the columns of ``u``, ``w`` (n, B), by the exact quadrature, in blocks of cells
        whose (points, block, B) work arrays stay in cache."""
        out = torch.zeros_like(u)
        B, phi, phi_t = u.shape[1], self._phi, self._phi_t
        block = max(1, self.block_values // (B * len(phi)))
        for start in range(0, self.num_cells, block):
            dofs = self._dofs_t[:, start : start + block]  # (d, cells)
            flat = dofs.reshape(-1)
            U = phi @ u.index_select(0, flat).view(len(dofs), -1)  # (q, cells B)
            F = phi @ w.index_select(0, flat).view(len(dofs), -1)
            F *= U
            F *= U
            F *= U.neg_().add_(1.0)
            F.view(len(phi), -1, B).mul_(self._weights[:, start : start + block, None])
            out.index_add_(0, flat, (phi_t @ F).view(-1, B))
        return out

    def blocked_right_hand_side(self, u, w, forcing) -> tuple[torch.Tensor, torch.Tensor]:
        """(b, w^{n+1}) of an implicit step (module docstring) for the columns of ``u``, ``w``
        (n, B): the sparse product with M and :meth:`reaction`."""
        b = self.reaction(u, w)
        b += (1.0 - self._k_out) * (self._M @ u)
        return (b if forcing is None else b + forcing), self._gated(u, w)

    def fused_right_hand_side(self, u, w, forcing) -> tuple[torch.Tensor, torch.Tensor]:
        r""":meth:`blocked_right_hand_side` written for ``torch.compile``: the quadrature point
        by point with the tabulated basis values as constants, and :math:`(1 - \Delta t /
        \tau_\mathrm{out}) M u` as its linear part (exact at this degree), so that gathers,
        integrand and scatter fuse into one pass over the cells."""
        dofs = self._dofs_t  # (d, cells)
        U_cells, W_cells = u[dofs], w[dofs]  # (d, cells, B)
        linear = (1.0 - self._k_out) / self._k_in
        corners = [0.0] * len(dofs)
        for q, row in enumerate(self._phi_rows):
            U = sum(p * U_cells[d] for d, p in enumerate(row))
            W = sum(p * W_cells[d] for d, p in enumerate(row))
            F = self._weights[q][:, None] * (W * U * U * (1.0 - U) + linear * U)
            corners = [corner + p * F for corner, p in zip(corners, row, strict=True)]
        b = torch.zeros_like(u).index_add(0, dofs.reshape(-1), torch.cat(corners))
        return (b if forcing is None else b + forcing), self._gated(u, w)

    def solve(self, b: torch.Tensor, x: torch.Tensor) -> None:
        """(M + dt D K) x = b for the columns of b (n, B), into x: by fast diagonalisation on
        a structured grid, else by CG from x (:meth:`conjugate_gradients`)."""
        if self._grid is None:
            self.conjugate_gradients(b, x)
            return
        ny, nx, B = len(self._grid.y), len(self._grid.x), b.shape[1]
        g = self._qy_t @ b.index_select(0, self._order).view(ny, nx * B)
        g = torch.matmul(self._qx_t, g.view(ny, nx, B)).div_(self._d)
        g = self._qy @ torch.matmul(self._qx, g).view(ny, nx * B)
        x.copy_(g.view(-1, B).index_select(0, self._dof_order))

    def conjugate_gradients(self, b: torch.Tensor, x: torch.Tensor) -> None:
        """(M + dt D K) x = b for the columns of b (n, B) by Jacobi-preconditioned CG, from
        and into x, until every column's preconditioned residual is below rtol x its right-hand
        side's. A column stops changing once it has converged, so that each replica's result
        does not depend on the others in the batch."""
        A, d = self._A, self._inverse_diagonal
        r = b - A @ x
        z = r * d
        limit = self.rtol * torch.linalg.vector_norm(b * d, dim=0)
        p = z.clone()
        rz = (r * z).sum(dim=0)
        zero = torch.zeros_like(rz)
        for _ in range(CG_MAX_ITERATIONS):
            norm = torch.linalg.vector_norm(z, dim=0)
            active = (norm > limit) & torch.isfinite(norm)  # non-finite: diverged, left as is
            if not bool(active.any()):
                return
            self.iterations += 1
            Ap = A @ p
            pAp = (p * Ap).sum(dim=0)
            alpha = torch.where(active & (pAp > 0), rz / pAp, zero)
            x.addcmul_(alpha, p)
            r.addcmul_(alpha, Ap, value=-1.0)
            torch.mul(r, d, out=z)
            rz_new = (r * z).sum(dim=0)
            beta = torch.where(rz > 0, rz_new / rz, zero)
            p.mul_(beta).add_(z)
            rz = rz_new
        raise SimulationDiverged(f"CG did not converge in {CG_MAX_ITERATIONS} iterations")
