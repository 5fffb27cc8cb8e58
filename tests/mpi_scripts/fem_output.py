"""Record u and w of a small Mitchell-Schaeffer run with FieldRecorder into argv[1] (a .bp
directory); the leader reads the series back and compares it with the values and times it
gathered from all ranks while writing, then renders w at the last step to argv[2] (PNG)."""

import sys

import numpy as np
from mpi4py import MPI

from physicsrl.bench.ms import DT, w0
from physicsrl.coordinated import Coordinated, Coordinator, parallel
from physicsrl.fem import (  # as the README imports them
    FieldRecorder,
    MonodomainMitchellSchaeffer,
    default_ms_mesh,
    read_series,
    render_series,
)

series_path, png_path = sys.argv[1], sys.argv[2]


def bump(x):
    return np.exp(-(x[0] ** 2 + x[1] ** 2) / 400.0)


class Snapshot(Coordinated):
    """Gathers (x, y, u, w) of the owned dofs of every rank, sorted by (x, y), to the leader."""

    def __init__(self, coordinator, ms):
        self.register_coordinator(coordinator)
        self.ms = ms

    @parallel
    def take(self):
        u, w = self.ms.u_n(), self.ms.w_n()
        n = u.function_space.dofmap.index_map.size_local
        points = u.function_space.tabulate_dof_coordinates()[:n, :2]
        local = np.column_stack([points, u.x.array[:n], w.x.array[:n]])
        parts = MPI.COMM_WORLD.gather(local, root=0)
        if parts is None:
            return None
        rows = np.concatenate(parts)
        return rows[np.lexsort((rows[:, 1].round(9), rows[:, 0].round(9)))]


coordinator = Coordinator()
ms = MonodomainMitchellSchaeffer(coordinator, default_ms_mesh(n=8), u0=bump, w0=w0)
recorder = FieldRecorder(coordinator, series_path, [ms.u_n(), ms.w_n()])
snapshot = Snapshot(coordinator, ms)
with coordinator:
    if coordinator.is_leader():
        times, expected = [], []
        for _ in range(3):
            ms.advance_time(4 * DT)
            recorder.write(ms.t)
            times.append(ms.t)
            expected.append(snapshot.take())
        recorder.close()
if MPI.COMM_WORLD.rank == 0:
    series = read_series(series_path)
    assert np.array_equal(series.times, times), (series.times, times)
    order = np.lexsort((series.points[:, 1].round(9), series.points[:, 0].round(9)))
    for step, rows in enumerate(expected):
        assert np.allclose(series.points[order, :2], rows[:, :2], atol=1e-12)
        assert np.array_equal(series.values["u"][step][order], rows[:, 2]), step
        assert np.array_equal(series.values["w"][step][order], rows[:, 3]), step
    assert np.abs(series.values["u"][-1] - series.values["u"][0]).max() > 1e-3  # it moved
    render_series(series, "w", -1, png_path)
    print(f"ok: {len(times)} steps of {len(order)} nodes", file=sys.stderr)
