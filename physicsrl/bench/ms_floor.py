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
kept in grid order: no permutation, no per-call checks. The benchmark runs it in the same job
as :class:`~physicsrl.fem.MonodomainMitchellSchaeffer` and compares the fields.
"""

from __future__ import annotations

import time

import numpy as np

from physicsrl.fem.kernels import load, pointer


class StructuredFloor:
    """The floor loop (``ms_stencil`` of :mod:`physicsrl.fem.kernels`) on n x n square cells
    of side h, with the model's parameters; the state ``u``, ``w`` (shape ((n + 1)^2,), grid
    order) and ``current`` (dt I per node, or None)."""

    def __init__(self, n, h, *, D, tau_in, tau_out, tau_open, tau_close, u_gate, dt):
        module = load()
        self.lib, self.ffi = module.lib, module.ffi
        self.n = n
        self.buffers = [np.zeros((n + 3, n + 1)), np.zeros((n + 3, n + 1))]  # halo rows too
        self.w = np.zeros((n + 1) ** 2)
        self.current = None
        self.constants = (
            dt * D / (3 * h * h),
            dt,
            tau_in,
            tau_out,
            u_gate,
            1.0 - dt / tau_open,
            dt / tau_open,
            1.0 - dt / tau_close,
        )
        self.seconds = 0.0

    @property
    def u(self) -> np.ndarray:
        """The node rows of the current u buffer, flat (a view)."""
        return self.buffers[0][1:-1].reshape(-1)

    def advance(self, steps: int) -> None:
        ffi, n = self.ffi, self.n
        current = ffi.NULL if self.current is None else pointer(ffi, self.current)
        u, other = (pointer(ffi, b) for b in self.buffers)
        start = time.perf_counter()
        self.lib.ms_stencil(
            n + 1, n, steps, 1, 1, u, pointer(ffi, self.w), current, *self.constants, other
        )
        self.seconds += time.perf_counter() - start
        if steps % 2:
            self.buffers.reverse()
