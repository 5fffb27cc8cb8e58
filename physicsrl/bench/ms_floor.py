r"""The floor of the explicit Mitchell-Schaeffer step: a minimal fused structured-grid C loop.

On an (n + 1) x (n + 1) grid of nodes of square Q1 cells of side h (row-major, node (i, j) at
index i (n + 1) + j), lumped mass h^2 in the interior, the explicit step of
:mod:`physicsrl.fem.explicit` is the 9-point stencil

.. math::

    (M_L^{-1} K u)_{ij} = \frac{1}{3 h^2}\Big(8 u_{ij} - \sum_{\text{8 neighbours}} u\Big),

with the homogeneous Neumann condition by mirroring (node -1 reads node 1): the mirrored row
is twice the boundary row of K over twice its lumped mass, so this is the assembled operator.
One pass per step reads u and w, writes u_next and w (32 bytes per node), and the two u
arrays alternate: no index arrays, no matrix values, no ghost update. It is the kernel of the
explicit scheme's structured path (:mod:`physicsrl.fem.explicit`), here called bare on arrays
kept in grid order: no transfers, no per-call checks, and on several ranks no halo exchange
(each rank's strip of rows as a grid of its own, edges mirrored). The benchmark runs it in the
same job as :class:`~physicsrl.fem.MonodomainMitchellSchaeffer` and, on one rank, compares the
fields.
"""

from __future__ import annotations

import numpy as np

from physicsrl.fem.kernels import load, pointer


class StructuredFloor:
    """The floor loop (``ms_stencil`` of :mod:`physicsrl.fem.kernels`) on ``rows`` rows of
    n + 1 nodes of square Q1 cells, c = dt D / (3 h^2), the model's parameters; its edges
    mirrored (a whole grid when rows = n + 1). The state: ``buffers[0]`` (u with a halo row on
    either side, (rows + 2, n + 1)), ``w`` and ``current`` (dt I per node, or None), both of
    shape (rows (n + 1),), in grid order."""

    def __init__(self, rows, n, c, *, dt, tau_in, tau_out, tau_open, tau_close, u_gate):
        module = load()
        self.lib, self.ffi = module.lib, module.ffi
        self.rows, self.n = rows, n
        self.buffers = [np.zeros((rows + 2, n + 1)), np.zeros((rows + 2, n + 1))]
        self.w = np.zeros(rows * (n + 1))
        self.current = None
        self.constants = (
            c,
            dt,
            tau_in,
            tau_out,
            u_gate,
            1.0 - dt / tau_open,
            dt / tau_open,
            1.0 - dt / tau_close,
        )

    def advance(self, steps: int) -> None:
        ffi, n = self.ffi, self.n
        current = ffi.NULL if self.current is None else pointer(ffi, self.current)
        u, other = (pointer(ffi, b) for b in self.buffers)
        self.lib.ms_stencil(
            self.rows, n, steps, 1, 1, u, pointer(ffi, self.w), current, *self.constants, other
        )
        if steps % 2:
            self.buffers.reverse()
