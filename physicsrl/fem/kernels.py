r"""C kernels of the monodomain model, compiled once with cffi and cached on disk.

Four loops that numpy can only express as many passes over large temporaries:

``ms_rhs``
    The right-hand side of the Mitchell-Schaeffer step (see
    :class:`physicsrl.fem.monodomain.MitchellSchaefferRHS`): for every owned cell :math:`c`,
    gather the dof values :math:`u_k, w_k` (k < nd), evaluate
    :math:`U_q = \sum_k \Phi_{qk} u_k` and :math:`W_q` at the nq quadrature points, the
    integrand :math:`f_q = U_q + \Delta t\,(W_q U_q^2 (1 - U_q) / \tau_\mathrm{in}
    - U_q / \tau_\mathrm{out} + I_c)` and add
    :math:`|\det J_c|\,\sum_q \hat w_q f_q \Phi_{qk}` to :math:`b` at the cell's dofs
    (with :math:`|\det J_c(\hat x_q)|` per point on non-affine cells). The points are
    processed four at a time (GCC/Clang vector extensions: AVX with ``-march=native``); about
    20 ns per Q1 cell on the AMD EPYC (znver3) this was measured on, 40-45 ns without.
``ms_gate``
    The forward-Euler gate update :math:`w^{n+1}_i = a_\mathrm{open} w_i + b_\mathrm{open}` if
    :math:`u_i < u_\mathrm{gate}`, else :math:`a_\mathrm{close} w_i`, into a separate array.
``ms_explicit``
    One step of the explicit scheme (:mod:`physicsrl.fem.explicit`): a row product with the
    operator's owned rows padded to one width (ELLPACK, so that the row loop has a constant
    length and unrolls), the nodal reaction and current, for the owned rows, in place (a new
    value is held back in a small ring until no later row reads the old one), and the gate
    update of every local entry in place.
``ms_stencil``
    Steps of the same scheme on a strip of node rows of a structured grid of square Q1 cells,
    the state in grid order with a halo row on either side (:mod:`physicsrl.fem.strips`): the
    operator is the 9-point stencil, the Neumann condition a mirror; one pass per step reads u
    and w and writes the other u buffer and w (32 bytes per node), with no index arrays and no
    matrix values.
``cell_det``
    :math:`|\det J|` at the quadrature points of every cell from the coordinate element's
    derivative table (gdim = tdim = 1, 2, 3), as per-cell values plus the largest relative
    spread within a cell (0 on affine cells), or as the full (cells, points) table.

Arrays are passed as raw pointers (``ffi.cast`` of numpy's data address): C-contiguous,
float64 values, int32 indices (DOLFINx's local index type). The dimensions nd and nq of the
common cells (Q1, P1 and Q1 hexahedra with the exact rules) get their own inlined copies of
the loop so that the compiler unrolls them.

Compilation: :func:`load` builds a CPython extension module with ``cffi`` (API mode, the
mechanism FFCx uses for the forms' kernels) into ``$PHYSICSRL_CACHE_DIR`` (default
``~/.cache/physicsrl``), named by a hash of the source, the compiler flags, the Python version
and the CPU (``-march=native``), so a changed source is rebuilt and an unchanged one is loaded
from disk (milliseconds). Rank 0 of the given communicator builds first while the others wait
at a barrier; any rank that then still finds no module (another node, a private disk) builds
its own. Every build happens in a private temporary directory and is moved into place with an
atomic rename, so concurrent builds never expose a partial file. Without a working C compiler
:func:`load` warns once and returns ``None``, and the callers use their numpy versions.
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import os
import platform
import sys
import tempfile
import warnings
from pathlib import Path

_CDEF = """
void ms_rhs(int64_t num_cells, int nd, int nq, const int32_t *dofs, const double *phi,
            const double *point_weights, int64_t weight_stride, const double *cell_det,
            const double *u, const double *w, const double *current,
            const int32_t *current_dofs, double dt, double tau_in, double tau_out,
            double *b, int64_t b_size);
void ms_gate(int64_t n, const double *u, const double *w, double *out, double u_gate,
             double a_open, double b_open, double a_close);
double cell_det(int64_t num_cells, int gdim, int nq, int nx, const int32_t *x_dofs,
                const double *x, const double *dphi, double *det, int per_point);
void ms_explicit(int64_t owned, int64_t local, int width, const int32_t *columns,
                 const double *values, double *u, double *w, const double *current,
                 double dt, double tau_in, double tau_out, double u_gate, double a_open,
                 double b_open, double a_close, int64_t lag, double *ring);
void ms_stencil(int64_t rows, int64_t n, int64_t steps, int mirror_first, int mirror_last,
                double *u, double *w, const double *current, double c, double dt,
                double tau_in, double tau_out, double u_gate, double a_open, double b_open,
                double a_close, double *other);
"""

_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <string.h>
#if defined(__SSE__)
#include <xmmintrin.h>
#endif

/* Four doubles, one AVX register (two SSE registers without AVX): the quadrature points of a
   cell, padded with zero weights to a multiple of 4, are processed four at a time. */
typedef double v4d __attribute__((vector_size(32)));

/* b[dofs of cell c] += sum_q s_cq f(U_cq, W_cq, I_c) phi[q][k] for every cell c, with
   s_cq = point_weights[c * weight_stride + q] * (cell_det ? cell_det[c] : 1). Inlined with
   constant nd, nq for the common elements, so that the arrays have fixed sizes and the loops
   unroll. The padded points have zero basis values and weights: they add exact zeros. */
static inline __attribute__((always_inline)) void
rhs_cells(int64_t num_cells, const int nd, const int nq, const int32_t *dofs, const double *phi,
          const double *point_weights, int64_t weight_stride, const double *cell_det,
          const double *u, const double *w, const double *current, const int32_t *current_dofs,
          double dt, double inv_in, double inv_out, double *b)
{
    const int nv = (nq + 3) / 4;
    v4d pt[nd][nv], sw[nv]; /* phi[q][k] as pt[k][q / 4][q % 4]; the weights likewise */
    for (int k = 0; k < nd; ++k)
        for (int q = 0; q < 4 * nv; ++q)
            pt[k][q / 4][q % 4] = q < nq ? phi[q * nd + k] : 0.0;
    for (int q = 0; q < 4 * nv; ++q)
        sw[q / 4][q % 4] = q < nq ? point_weights[q] : 0.0;
    for (int64_t c = 0; c < num_cells; ++c) {
        const int32_t *cd = dofs + c * nd;
        v4d U[nv], W[nv], f[nv];
        for (int v = 0; v < nv; ++v)
            U[v] = W[v] = (v4d){0.0, 0.0, 0.0, 0.0};
        for (int k = 0; k < nd; ++k) {
            const double uk = u[cd[k]], wk = w[cd[k]];
            for (int v = 0; v < nv; ++v) {
                U[v] += pt[k][v] * uk;
                W[v] += pt[k][v] * wk;
            }
        }
        if (weight_stride) /* non-affine cells: w_q |det J_c(x_q)| */
            for (int q = 0; q < nq; ++q)
                sw[q / 4][q % 4] = point_weights[c * weight_stride + q];
        const double I = current[current_dofs[c]];
        for (int v = 0; v < nv; ++v)
            f[v] = sw[v] * (U[v] + dt * (W[v] * U[v] * U[v] * (1.0 - U[v]) * inv_in
                                         - U[v] * inv_out + I));
        const double scale = cell_det ? cell_det[c] : 1.0;
        for (int k = 0; k < nd; ++k) {
            v4d s = f[0] * pt[k][0];
            for (int v = 1; v < nv; ++v)
                s += f[v] * pt[k][v];
            b[cd[k]] += scale * ((s[0] + s[1]) + (s[2] + s[3]));
        }
    }
}

void ms_rhs(int64_t num_cells, int nd, int nq, const int32_t *dofs, const double *phi,
            const double *point_weights, int64_t weight_stride, const double *cell_det,
            const double *u, const double *w, const double *current,
            const int32_t *current_dofs, double dt, double tau_in, double tau_out,
            double *b, int64_t b_size)
{
    const double inv_in = 1.0 / tau_in, inv_out = 1.0 / tau_out;
#if defined(__SSE__)
    /* Flush subnormal results and operands to zero inside this loop (restored at the end):
       u decays exponentially ahead of a wave, and u^2 w of u ~ 1e-160 is subnormal, which
       costs ~100 cycles per operation. The change is below 1e-308 absolute. */
    const unsigned int csr = _mm_getcsr();
    _mm_setcsr(csr | 0x8040);
#endif
    memset(b, 0, sizeof(double) * b_size);
#define RHS(ND, NQ) rhs_cells(num_cells, ND, NQ, dofs, phi, point_weights, weight_stride, \
                              cell_det, u, w, current, current_dofs, dt, inv_in, inv_out, b)
    if (nd == 4 && nq == 9)
        RHS(4, 9); /* Q1, 3 x 3 Gauss */
    else if (nd == 3 && nq == 7)
        RHS(3, 7); /* P1 triangle, degree 5 */
    else if (nd == 8 && nq == 27)
        RHS(8, 27); /* Q1 hexahedron */
    else
        RHS(nd, nq);
#undef RHS
#if defined(__SSE__)
    _mm_setcsr(csr);
#endif
}

void ms_gate(int64_t n, const double *u, const double *w, double *out, double u_gate,
             double a_open, double b_open, double a_close)
{
    for (int64_t i = 0; i < n; ++i)
        out[i] = u[i] < u_gate ? w[i] * a_open + b_open : w[i] * a_close;
}

/* One explicit step (physicsrl.fem.explicit), in place: for the owned rows i,
   u[i] <- sum_k C[i][k] u[columns[i][k]] (k < width: the row of C = I - dt D M_L^-1 K,
           padded with zeros)
           + dt (w u^2 (1 - u) / tau_in - u / tau_out) + current[i] (dt I_i; NULL: none),
   all from the old u; and the gate of every local entry (owned and ghost) in place, from u
   and the old w. Row i reads no column below i - lag (lag >= 0), so its new value waits in a
   ring of lag + 1 values and is written when row i + lag + 1 starts.
   Inlined with constant widths for the common elements, so that the row loop unrolls. */
static inline __attribute__((always_inline)) void
explicit_rows(int64_t owned, int64_t local, const int width, const int32_t *columns,
              const double *values, double *u, double *w, const double *current,
              double k_in, double k_out, double u_gate, double a_open, double b_open,
              double a_close, int64_t lag, double *ring)
{
    const int64_t r = lag + 1;
    for (int64_t i = 0, slot = 0; i < owned; ++i, slot = slot + 1 == r ? 0 : slot + 1) {
        if (i >= r)
            u[i - r] = ring[slot];
        const int32_t *col = columns + i * width;
        const double *val = values + i * width;
        double s = 0.0;
        for (int k = 0; k < width; ++k)
            s += val[k] * u[col[k]];
        const double ui = u[i], wi = w[i];
        s += ui * (k_in * wi * ui * (1.0 - ui) - k_out);
        ring[slot] = current ? s + current[i] : s;
        w[i] = ui < u_gate ? wi * a_open + b_open : wi * a_close;
    }
    for (int64_t i = owned > r ? owned - r : 0; i < owned; ++i)
        u[i] = ring[i % r];
    for (int64_t i = owned; i < local; ++i)
        w[i] = u[i] < u_gate ? w[i] * a_open + b_open : w[i] * a_close;
}

void ms_explicit(int64_t owned, int64_t local, int width, const int32_t *columns,
                 const double *values, double *u, double *w, const double *current,
                 double dt, double tau_in, double tau_out, double u_gate, double a_open,
                 double b_open, double a_close, int64_t lag, double *ring)
{
#if defined(__SSE__)
    const unsigned int csr = _mm_getcsr(); /* subnormals to zero, as in ms_rhs */
    _mm_setcsr(csr | 0x8040);
#endif
#define ROWS(WIDTH) explicit_rows(owned, local, WIDTH, columns, values, u, w, current, \
                                  dt / tau_in, dt / tau_out, u_gate, a_open, b_open, a_close, \
                                  lag, ring)
    if (width == 9)
        ROWS(9); /* Q1 quadrilaterals */
    else if (width == 27)
        ROWS(27); /* Q1 hexahedra */
    else
        ROWS(width);
#undef ROWS
#if defined(__SSE__)
    _mm_setcsr(csr);
#endif
}

/* `steps` steps on `rows` rows of the n + 1 nodes per row of square Q1 cells of side h,
   row-major, c = dt D / (3 h^2): (M_L^-1 K u)_ij = (8 u_ij - the 8 neighbours) / (3 h^2); at
   an edge of the grid node -1 is mirrored to node 1 (the Neumann condition: the mirrored row
   is twice the boundary row of K over twice its lumped mass). current: dt I per node, or NULL.
   u and `other` hold rows + 2 rows: the halo row above (row -1), the node rows, the halo row
   below (row `rows`); w and current hold the node rows only. Row -1 is read from the halo, or
   from node row 1 with mirror_first; likewise row `rows` with mirror_last; the columns always
   mirror. Each step writes the other u buffer (halos untouched) and w in place: the result is
   in u after an even number of steps, in `other` after an odd one. Halos that are not
   mirrors must be refreshed between steps (steps = 1). */
void ms_stencil(int64_t rows, int64_t n, int64_t steps, int mirror_first, int mirror_last,
                double *u, double *w, const double *current, double c, double dt,
                double tau_in, double tau_out, double u_gate, double a_open, double b_open,
                double a_close, double *other)
{
    const double k_in = dt / tau_in, k_out = dt / tau_out;
    const int64_t s = n + 1;
#if defined(__SSE__)
    const unsigned int csr = _mm_getcsr(); /* subnormals to zero, as in ms_rhs */
    _mm_setcsr(csr | 0x8040);
#endif
    double *from = u + s, *to = other + s; /* node row 0 */
    for (int64_t step = 0; step < steps; ++step) {
        for (int64_t i = 0; i < rows; ++i) {
            const double *up = from + (i == 0 && mirror_first ? 1 : i - 1) * s;
            const double *um = from + i * s;
            const double *dn = from + (i == rows - 1 && mirror_last ? rows - 2 : i + 1) * s;
            double *wi_row = w + i * s, *out = to + i * s;
            const double *cur = current ? current + i * s : 0;
            for (int64_t j = 0; j <= n; ++j) {
                const int64_t l = j == 0 ? 1 : j - 1, r = j == n ? n - 1 : j + 1;
                const double ui = um[j], wi = wi_row[j];
                const double ring = up[l] + up[j] + up[r] + um[l] + um[r] + dn[l] + dn[j] + dn[r];
                const double v = ui - c * (8.0 * ui - ring)
                                 + ui * (k_in * wi * ui * (1.0 - ui) - k_out);
                out[j] = cur ? v + cur[j] : v;
                wi_row[j] = ui < u_gate ? wi * a_open + b_open : wi * a_close;
            }
        }
        double *swap = from;
        from = to;
        to = swap;
    }
#if defined(__SSE__)
    _mm_setcsr(csr);
#endif
}

/* |det J| at the nq points of every cell; J_ij = sum_a x[x_dofs[a]][i] dphi[j][q][a].
   per_point: det[c * nq + q]; else det[c] (point 0). Returns max_c max_q
   |det_cq - det_c0| / max_c |det_c0|, zero iff every cell is affine (to round-off). */
double cell_det(int64_t num_cells, int gdim, int nq, int nx, const int32_t *x_dofs,
                const double *x, const double *dphi, double *det, int per_point)
{
    double spread = 0.0, largest = 0.0;
    for (int64_t c = 0; c < num_cells; ++c) {
        const int32_t *cd = x_dofs + c * nx;
        double first = 0.0;
        for (int q = 0; q < nq; ++q) {
            double J[3][3] = {{0.0}};
            for (int j = 0; j < gdim; ++j) {
                const double *d = dphi + ((int64_t)j * nq + q) * nx;
                for (int a = 0; a < nx; ++a) {
                    const double *xa = x + 3 * (int64_t)cd[a];
                    for (int i = 0; i < gdim; ++i)
                        J[i][j] += xa[i] * d[a];
                }
            }
            double value;
            if (gdim == 1)
                value = J[0][0];
            else if (gdim == 2)
                value = J[0][0] * J[1][1] - J[0][1] * J[1][0];
            else
                value = J[0][0] * (J[1][1] * J[2][2] - J[1][2] * J[2][1])
                        - J[0][1] * (J[1][0] * J[2][2] - J[1][2] * J[2][0])
                        + J[0][2] * (J[1][0] * J[2][1] - J[1][1] * J[2][0]);
            value = fabs(value);
            if (q == 0)
                first = value;
            else if (fabs(value - first) > spread)
                spread = fabs(value - first);
            if (per_point)
                det[c * nq + q] = value;
        }
        if (!per_point)
            det[c] = first;
        if (first > largest)
            largest = first;
    }
    return largest > 0.0 ? spread / largest : 0.0;
}
"""

_FLAGS = ["-O3", "-march=native"]
"""Compiler flags; ``-march=native`` (AVX2 and FMA where the CPU has them) makes the module
specific to the CPU, whose description is therefore part of the cache key."""
_module = None
_loaded = False


def cache_dir() -> Path:
    """Where compiled kernels are kept: ``$PHYSICSRL_CACHE_DIR`` or ``~/.cache/physicsrl``."""
    return Path(os.environ.get("PHYSICSRL_CACHE_DIR", Path.home() / ".cache" / "physicsrl"))


def _module_name(prefix: str, cdef: str, source: str) -> str:
    key = "\0".join([cdef, source, " ".join(_FLAGS), sys.version, sys.platform, _cpu()])
    return prefix + hashlib.sha256(key.encode()).hexdigest()[:16]


def _cpu() -> str:
    """The CPU's model and feature flags (Linux), else the machine type."""
    try:
        with open("/proc/cpuinfo") as info:
            lines = [line for line in info if line.startswith(("model name", "flags"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.machine()


def _build(name: str, target: Path, cdef: str, source: str) -> None:
    """Compile the module in a private directory and rename it to ``target`` (atomic)."""
    import cffi

    ffi = cffi.FFI()
    ffi.cdef(cdef)
    ffi.set_source(name, source, extra_compile_args=_FLAGS)
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as build:
        built = ffi.compile(tmpdir=build)
        os.replace(built, target)


def _import(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def build(prefix: str, cdef: str, source: str, comm=None):
    """The cffi module (attributes ``ffi`` and ``lib``) of C ``source`` declaring ``cdef``,
    built or loaded from the cache as described in the module docstring and named ``prefix``
    plus a hash; raises if it cannot be built. Collective over ``comm`` (``None``: this
    process alone)."""
    name = _module_name(prefix, cdef, source)
    target = cache_dir() / (name + importlib.machinery.EXTENSION_SUFFIXES[0])
    error = None
    try:
        if comm is not None and comm.rank == 0 and not target.exists():
            _build(name, target, cdef, source)
    except Exception as exc:  # reported by every rank below, after the barrier
        error = exc
    if comm is not None and comm.size > 1:
        comm.Barrier()
    if error is not None:
        raise error
    if not target.exists():
        _build(name, target, cdef, source)
    return _import(name, target)


def load(comm=None):
    """This module's kernels (attributes ``ffi`` and ``lib``), or ``None`` with a warning if
    they cannot be built. Collective over ``comm`` (an ``MPI.Comm``, or ``None`` for this
    process alone) on the first call; later calls return the loaded module at once."""
    global _module, _loaded
    if _loaded:
        return _module
    try:
        _module = build("_physicsrl_kernels_", _CDEF, _SOURCE, comm)
    except Exception as exc:  # no compiler, no headers, unwritable cache: use numpy
        warnings.warn(
            f"physicsrl: C kernels unavailable ({type(exc).__name__}: {exc}); "
            "using the numpy versions",
            RuntimeWarning,
            stacklevel=2,
        )
        _module = None
    _loaded = True
    return _module


def pointer(ffi, array, ctype: str = "double *"):
    """A C pointer to the data of a C-contiguous numpy array (which must outlive its use)."""
    if not array.flags.c_contiguous:
        raise ValueError("kernels.pointer: the array must be C-contiguous")
    return ffi.cast(ctype, array.ctypes.data)
