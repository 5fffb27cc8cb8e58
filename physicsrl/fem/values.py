"""Setting finite element functions from the kinds of values users pass, with validation.

A *value* is one of

- a number: the constant function;
- a Python callable ``f(x) -> values`` (lambdas included), ``x`` of shape ``(3, n)`` holding
  the interpolation points, returning shape ``(n,)`` or a scalar;
- a :class:`dolfinx.fem.Expression`;
- a :class:`dolfinx.fem.Function` on the same mesh (copied when it lives in the same space,
  interpolated otherwise).

:func:`assign` interpolates the value into a function, updates the ghost entries and checks
collectively that the result is finite, so every rank raises the same :class:`InvalidValue`.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
import ufl
from dolfinx import cpp, fem
from mpi4py import MPI

from physicsrl import checks
from physicsrl.fem.errors import InvalidValue


def _real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def positive(name: str, value) -> float:
    """``value`` as a float; :class:`InvalidValue` naming it unless it is finite and > 0."""
    if not _real(value) or not math.isfinite(value) or value <= 0:
        raise InvalidValue(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def nonnegative(name: str, value) -> float:
    """``value`` as a float; :class:`InvalidValue` naming it unless it is finite and >= 0."""
    if not _real(value) or not math.isfinite(value) or value < 0:
        raise InvalidValue(f"{name} must be a finite number >= 0, got {value!r}")
    return float(value)


def finite(name: str, value) -> float:
    """``value`` as a float; :class:`InvalidValue` naming it unless it is a finite number."""
    if not _real(value) or not math.isfinite(value):
        raise InvalidValue(f"{name} must be a finite number, got {value!r}")
    return float(value)


def integer(name: str, value, low: int = 1) -> int:
    """``value`` as an int; :class:`InvalidValue` naming it unless it is an integer >= ``low``
    (:func:`physicsrl.checks.integer`'s rule: numpy's integers included, ``True`` not)."""
    try:
        return checks.integer(name, value, low)
    except ValueError as error:
        raise InvalidValue(str(error)) from None


def all_finite(function: fem.Function) -> bool:
    """Whether every owned entry of ``function`` is finite on every rank (collective)."""
    n = function.function_space.dofmap.index_map.size_local * function.function_space.dofmap.bs
    ok = bool(np.isfinite(function.x.array[:n]).all())
    return function.function_space.mesh.comm.allreduce(ok, op=MPI.LAND)


def _meshes(expression: ufl.core.expr.Expr) -> set:
    """The meshes of the coefficients and constants in a UFL expression."""
    found = set()
    for term in (
        *ufl.algorithms.extract_coefficients(expression),
        *ufl.algorithms.analysis.extract_constants(expression),
    ):
        found.add(term.ufl_domain())
    return found


def assign(target: fem.Function, value, name: str) -> None:
    """Set ``target`` to ``value`` (see the module docstring) and update its ghost entries.

    Raises :class:`InvalidValue` naming ``name`` for a value of an unknown kind, a callable
    returning the wrong shape, a function or expression on another mesh, or a non-finite result;
    ``target`` is then left unchanged. Collective.
    """
    V = target.function_space
    result = fem.Function(V)
    if isinstance(value, fem.Function):
        if value.function_space.mesh is not V.mesh:
            raise InvalidValue(f"{name}: the function {value.name!r} lives on another mesh")
        if value.function_space == V:
            result.x.array[:] = value.x.array
        else:
            result.interpolate(value)
    elif isinstance(value, fem.Expression):
        if any(domain is not V.mesh.ufl_domain() for domain in _meshes(value.ufl_expression)):
            raise InvalidValue(f"{name}: the expression uses functions on another mesh")
        result.interpolate(value)
    elif isinstance(value, numbers.Real):
        result.x.array[:] = finite(name, value)
    elif callable(value):
        x = cpp.fem.interpolation_coords(V.element._cpp_object, V.mesh.geometry._cpp_object, None)
        values = np.asarray(value(x), dtype=result.x.array.dtype)
        if values.shape == ():
            values = np.full(x.shape[1], values)
        if values.shape != (x.shape[1],):
            raise InvalidValue(
                f"{name}: the callable returned shape {values.shape} for points of shape "
                f"{x.shape}; expected ({x.shape[1]},)"
            )
        result._cpp_object.interpolate_f(values, None)
    else:
        raise InvalidValue(
            f"{name}: expected a number, a callable, a fem.Expression or a fem.Function, got "
            f"{type(value).__name__}"
        )
    result.x.scatter_forward()
    if not all_finite(result):
        raise InvalidValue(f"{name} has non-finite values")
    target.x.array[:] = result.x.array
