r"""The floor of the explicit Mitchell-Schaeffer step: a minimal fused structured-grid C loop.

On an (n + 1) x (n + 1) grid of nodes of square Q1 cells of side h (row-major, node (i, j) at
index i (n + 1) + j), lumped mass h^2 in the interior, the explicit step of
:mod:`physicsrl.fem.explicit` is the 9-point stencil

.. math::

    (M_L^{-1} K u)_{ij} = \frac{1}{3 h^2}\Big(8 u_{ij} - \sum_{\text{8 neighbours}} u\Big),

with the homogeneous Neumann condition by mirroring (node -1 reads node 1): the mirrored row
is twice the boundary row of K over twice its lumped mass, so this is the assembled operator.
One pass per step reads u and w, writes u_next and w (32 bytes per node), and the two u
arrays alternate: no index arrays, no matrix values, no ghost update. The benchmark runs it in
the same job as :class:`~physicsrl.fem.MonodomainMitchellSchaeffer` and compares the fields.
"""

from __future__ import annotations

import time

import numpy as np

from physicsrl.fem.kernels import build, pointer

_CDEF = """
void ms_floor(int64_t n, const double *u, double *w, const double *current, double c,
              double dt, double tau_in, double tau_out, double u_gate, double a_open,
              double b_open, double a_close, double *u_next);
"""

_SOURCE = r"""
#include <stdint.h>
#if defined(__SSE__)
#include <xmmintrin.h>
#endif

/* c = dt D / (3 h^2); nodes 0..n per side; current: dt I per node or NULL. */
void ms_floor(int64_t n, const double *u, double *w, const double *current, double c,
              double dt, double tau_in, double tau_out, double u_gate, double a_open,
              double b_open, double a_close, double *u_next)
{
    const double k_in = dt / tau_in, k_out = dt / tau_out;
    const int64_t s = n + 1;
#if defined(__SSE__)
    const unsigned int csr = _mm_getcsr();
    _mm_setcsr(csr | 0x8040);
#endif
    for (int64_t i = 0; i <= n; ++i) {
        const double *up = u + (i == 0 ? 1 : i - 1) * s, *um = u + i * s;
        const double *dn = u + (i == n ? n - 1 : i + 1) * s;
        for (int64_t j = 0; j <= n; ++j) {
            const int64_t l = j == 0 ? 1 : j - 1, r = j == n ? n - 1 : j + 1;
            const double ui = um[j], wi = w[i * s + j];
            const double ring = up[l] + up[j] + up[r] + um[l] + um[r] + dn[l] + dn[j] + dn[r];
            double v = ui - c * (8.0 * ui - ring) + ui * (k_in * wi * ui * (1.0 - ui) - k_out);
            u_next[i * s + j] = current ? v + current[i * s + j] : v;
            w[i * s + j] = ui < u_gate ? wi * a_open + b_open : wi * a_close;
        }
    }
#if defined(__SSE__)
    _mm_setcsr(csr);
#endif
}
"""


class StructuredFloor:
    """The floor loop on n x n square cells of side h, with the model's parameters; the state
    ``u``, ``w`` (shape ((n + 1)^2,), grid order) and ``current`` (dt I per node, or None)."""

    def __init__(self, n, h, *, D, tau_in, tau_out, tau_open, tau_close, u_gate, dt):
        module = build("_physicsrl_ms_floor_", _CDEF, _SOURCE)
        self.lib, self.ffi = module.lib, module.ffi
        self.n = n
        self.u, self.w = np.zeros((n + 1) ** 2), np.zeros((n + 1) ** 2)
        self.other = np.zeros_like(self.u)
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

    def advance(self, steps: int) -> None:
        ffi = self.ffi
        current = ffi.NULL if self.current is None else pointer(ffi, self.current)
        start = time.perf_counter()
        for _ in range(steps):
            self.lib.ms_floor(
                self.n,
                pointer(ffi, self.u),
                pointer(ffi, self.w),
                current,
                *self.constants,
                pointer(ffi, self.other),
            )
            self.u, self.other = self.other, self.u
        self.seconds += time.perf_counter() - start
