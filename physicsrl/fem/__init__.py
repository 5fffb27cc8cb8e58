"""Simulators on DOLFINx (report section 4): :class:`TimeProblem`, :class:`HeatEnvironment`,
:class:`MonodomainMitchellSchaeffer`, fused observations and field output.

The only module of physicsrl that imports ``dolfinx_solver``: the wheel's loader makes MPI and
PETSc importable. A cluster's own DOLFINx installation has no such wheel and needs none.
"""

try:
    import dolfinx_solver  # noqa: F401
except ImportError:
    pass
try:
    import dolfinx  # noqa: F401
except ImportError as error:
    raise ImportError(
        "physicsrl's simulators need DOLFINx 0.11 (with petsc4py and mpi4py): pip install "
        "'physicsrl[fem]' for the wheels, or load your site's DOLFINx"
    ) from error

from physicsrl.fem.errors import InvalidValue, SimulationDiverged  # noqa: E402
from physicsrl.fem.heat import HeatEnvironment, default_heat_mesh  # noqa: E402
from physicsrl.fem.integrals import (  # noqa: E402
    WeightedIntegrals,
    form_rows,
    point_rows,
    quadrant_weights,
)
from physicsrl.fem.monodomain import MonodomainMitchellSchaeffer, default_ms_mesh  # noqa: E402
from physicsrl.fem.output import FieldRecorder, read_series, render_series  # noqa: E402
from physicsrl.fem.plot import plot_field  # noqa: E402
from physicsrl.fem.time_problem import DEFAULT_PETSC_OPTIONS, TimeProblem  # noqa: E402

__all__ = [
    "DEFAULT_PETSC_OPTIONS",
    "FieldRecorder",
    "HeatEnvironment",
    "InvalidValue",
    "MonodomainMitchellSchaeffer",
    "SimulationDiverged",
    "TimeProblem",
    "WeightedIntegrals",
    "form_rows",
    "point_rows",
    "default_heat_mesh",
    "default_ms_mesh",
    "plot_field",
    "quadrant_weights",
    "read_series",
    "render_series",
]
