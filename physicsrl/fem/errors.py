"""Errors of the simulators that every rank raises at the same point.

Both derive from :class:`physicsrl.coordinated.CollectiveError`: the condition is decided on
every rank alike (from the replicated arguments of a parallel call, or after a reduction), so
raising it inside a ``@parallel`` method does not abort the job; the leader's caller handles it.
"""

from __future__ import annotations

from physicsrl.coordinated import CollectiveError


class SimulationDiverged(CollectiveError, FloatingPointError):
    """The solution became non-finite (or the linear solver failed) during ``advance_time``."""


class InvalidValue(CollectiveError, ValueError):
    """An argument of a simulator is out of range, non-finite, of the wrong shape, or lives on
    another mesh. The message names the argument."""
