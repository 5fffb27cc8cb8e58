"""A cache of induced ATP states, so that a reset need not re-simulate the induction.

Inducing the arrhythmia of an ATP reset simulates ``stimulus_time + rest_time`` (100) time
units, about 3300 steps; restoring a snapshot copies two arrays. The state after a reset is
defined by the potential ``u``, the gate ``w`` (the applied current is off and the time is
``stimulus_time + rest_time``), so a snapshot holds, on each rank, that rank's owned and ghost
dof values of ``u`` and ``w``. Snapshots are keyed by the reset's random draws (exact floats),
filled on demand by resets or ahead of time (:meth:`physicsrl.envs.atp.ATPTask.prefill`); the
oldest are dropped beyond ``capacity``.

On disk (optional): one file per rank, ``atp-<fingerprint>-rank<r>of<n>.npz`` in
``directory``, where the fingerprint hashes the settings that define an induced state (mesh,
model, reset stimulus). A cache written with n ranks is read back only by a job with n ranks
(the same partition: DOLFINx partitions a given mesh deterministically) and only if every rank
finds its file with the expected number of dofs; otherwise it is ignored.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from pathlib import Path

import numpy as np
from mpi4py import MPI


class SnapshotCache:
    """Per-rank snapshots ``key -> (u, w)`` (see the module docstring). The same keys are
    stored on every rank, because only parallel methods store them."""

    def __init__(self, capacity: int, directory: str | None, settings: str, comm: MPI.Comm):
        self.capacity = capacity
        self.comm = comm
        self.fingerprint = hashlib.sha1(settings.encode()).hexdigest()[:12]
        self.path = None
        if directory is not None:
            name = f"atp-{self.fingerprint}-rank{comm.rank}of{comm.size}.npz"
            self.path = Path(directory) / name
        self.states: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()

    def __len__(self) -> int:
        return len(self.states)

    def __contains__(self, key: tuple) -> bool:
        return key in self.states

    def get(self, key: tuple) -> tuple[np.ndarray, np.ndarray]:
        return self.states[key]

    def put(self, key: tuple, u: np.ndarray, w: np.ndarray) -> None:
        if self.capacity <= 0:
            return
        self.states[key] = (u.copy(), w.copy())
        while len(self.states) > self.capacity:
            self.states.popitem(last=False)

    def save(self) -> Path | None:
        """Write this rank's file (collective: every rank writes its own); return its path."""
        if self.path is None:
            return None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        keys = np.array(list(self.states), dtype=float).reshape(len(self.states), -1)
        u = np.array([state[0] for state in self.states.values()])
        w = np.array([state[1] for state in self.states.values()])
        temporary = self.path.with_suffix(".tmp.npz")
        np.savez(temporary, keys=keys, u=u, w=w)
        temporary.replace(self.path)
        return self.path

    def load(self, n_values: int) -> int:
        """Read this rank's file if every rank has a usable one; the number of snapshots
        read (collective)."""
        data = None
        if self.path is not None and self.path.exists():
            with np.load(self.path) as stored:
                data = {name: stored[name] for name in ("keys", "u", "w")}
            if data["u"].ndim != 2 or data["u"].shape[1] != n_values:
                data = None
        if not self.comm.allreduce(data is not None, op=MPI.LAND):
            return 0
        for key, u, w in zip(data["keys"], data["u"], data["w"], strict=True):
            self.put(tuple(float(k) for k in key), u, w)
        return len(data["keys"])
