"""A cache of induced ATP states, so that a reset need not re-simulate the induction.

Inducing the arrhythmia of an ATP reset simulates about 100 time units (3300 steps);
restoring a snapshot copies two arrays. The state after a reset is defined by the potential
``u`` and the gate ``w`` (the applied current is off, the time follows from the draws), so a
snapshot holds, on each rank, that rank's owned and ghost dof values of ``u`` and ``w``.
Snapshots are keyed by the reset's random draws (exact floats), filled on demand by resets or
ahead of time (:meth:`physicsrl.envs.atp.ATPTask.prefill`); beyond ``capacity`` the oldest are
dropped from memory.

On disk (optional, a library shared by the jobs that use the same settings, e.g. a training run
and its evaluation): every snapshot is written when it is stored (under a temporary name of
its own, then renamed: jobs may write the same one at once), one file per rank,
``<directory>/atp-<fingerprint>/<key>-rank<r>of<n>.npz``, where the fingerprint hashes the
settings that define an induced state (mesh, model, induction) and ``<key>`` the draws. A
snapshot missing from memory is read from disk if every rank finds its file: a library written
with n ranks serves only jobs with n ranks (the same partition: DOLFINx partitions a given mesh
deterministically). The disk library is never pruned.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections import OrderedDict
from pathlib import Path

import numpy as np
from mpi4py import MPI


def _digest(text: str) -> str:
    return hashlib.sha1(text.encode()).hexdigest()[:12]


class SnapshotCache:
    """Per-rank snapshots ``key -> (u, w)`` (see the module docstring). The same keys are
    stored on every rank, because only parallel methods store them; membership tests are
    collective when there is a directory."""

    def __init__(self, capacity: int, directory: str | None, settings: str, comm: MPI.Comm):
        self.capacity = capacity
        self.comm = comm
        self.fingerprint = _digest(settings)
        self.directory = None
        if directory is not None:
            self.directory = Path(directory).expanduser() / f"atp-{self.fingerprint}"
        self.states: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()

    def __len__(self) -> int:
        return len(self.states)

    def _path(self, key: tuple) -> Path | None:
        if self.directory is None:
            return None
        name = f"{_digest(repr(tuple(map(float, key))))}-rank{self.comm.rank}of{self.comm.size}"
        return self.directory / f"{name}.npz"

    def __contains__(self, key: tuple) -> bool:
        if key in self.states:
            return True
        path = self._path(key)
        return path is not None and self.comm.allreduce(path.exists(), op=MPI.LAND)

    def get(self, key: tuple) -> tuple[np.ndarray, np.ndarray]:
        if key in self.states:
            return self.states[key]
        with np.load(self._path(key)) as stored:
            u, w = stored["u"], stored["w"]
        self._remember(key, u, w)
        return u, w

    def put(self, key: tuple, u: np.ndarray, w: np.ndarray) -> None:
        """Store a copy of (u, w) in memory (if ``capacity`` > 0) and on disk (if a
        directory was given)."""
        path = self._path(key)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            # a name of its own: jobs sharing the library (and groups of one job, whose ranks
            # have the same names) may write the same snapshot at once
            with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".npz", delete=False) as f:
                np.savez(f, u=u, w=w)
            os.replace(f.name, path)
        self._remember(key, u, w)

    def _remember(self, key: tuple, u: np.ndarray, w: np.ndarray) -> None:
        if self.capacity <= 0:
            return
        self.states[key] = (u.copy(), w.copy())
        while len(self.states) > self.capacity:
            self.states.popitem(last=False)
