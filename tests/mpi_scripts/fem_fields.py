"""Run the simulators on this job's ranks; the leader saves the fields to argv[1] (npz).

Mitchell-Schaeffer: the benchmark set-up of physicsrl.bench.ms on 24 x 24 cells, 60 steps
(stimulus during the first 30), with the scheme argv[2] (default implicit), 30 steps per call
or, with argv[3] = "stepwise", one (the explicit scheme's general row pass instead of the
strips of its structured path); heat: the default environment with u0 = x + 2y, 0.1 time
units.
Saved: dof coordinates, u and w of the monodomain model (owned dofs of all ranks), whether
the explicit scheme found its strips, the heat quadrant integrals at t = 0 and t = 0.1, and
the heat u with its coordinates, the heat solver's preconditioner (``"bjacobi/icc"``: block
Jacobi with ICC(0) blocks), and the relative errors of the heat resolution report at t = 0.1
and 0.2 (collective, after the leader's calls).
"""

import sys

import numpy as np
from mpi4py import MPI

from physicsrl.bench.ms import DT, no_current, stimulus, w0
from physicsrl.coordinated import Coordinator
from physicsrl.fem import HeatEnvironment, MonodomainMitchellSchaeffer, default_ms_mesh
from physicsrl.fem.heat import resolution


def gather(function):
    """(coordinates, values) of the owned dofs of all ranks, on the leader."""
    n = function.function_space.dofmap.index_map.size_local
    local = np.column_stack(
        [function.function_space.tabulate_dof_coordinates()[:n, :2], function.x.array[:n]]
    )
    parts = MPI.COMM_WORLD.gather(local, root=0)
    return np.concatenate(parts) if parts is not None else None


coordinator = Coordinator()
scheme = sys.argv[2] if len(sys.argv) > 2 else "implicit"
calls = 30 if sys.argv[3:] == ["stepwise"] else 1
ms = MonodomainMitchellSchaeffer(
    coordinator, default_ms_mesh(n=24), w0=w0, I_app=stimulus, scheme=scheme
)
heat = HeatEnvironment(coordinator, u0=lambda x: x[0] + 2 * x[1])
with coordinator:
    if coordinator.is_leader():
        for current in (stimulus, no_current):
            ms.set_I_app(current)
            for _ in range(calls):
                ms.advance_time(30 * DT / calls)
        initial = heat.quadrant_integrals()
        heat.advance_time(0.1)
        quadrants = heat.quadrant_integrals()
u, w, h = gather(ms.u_n()), gather(ms.w_n()), gather(heat.u_n())
heat_resolution = resolution(heat, 2.0, [0.1, 0.2])
if MPI.COMM_WORLD.rank == 0:
    strips = ms._explicit is not None and ms._explicit.grid is not None
    pc = heat.problem._ksp.getPC()
    solver = pc.getType()
    if solver == "bjacobi":
        solver += "/" + pc.getBJacobiSubKSP()[0].getPC().getType()
    np.savez(
        sys.argv[1],
        u=u,
        w=w,
        strips=strips,
        heat=h,
        quadrants=quadrants,
        initial=initial,
        solver=solver,
        heat_resolution=heat_resolution.errors,
    )
