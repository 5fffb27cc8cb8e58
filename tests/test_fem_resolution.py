"""The resolution guard: h against the front width, the expected CV error, the warning."""

from __future__ import annotations

import physicsrl.fem  # noqa: F401  (first: loads the MPI library that dolfinx links to)

# isort: split

import math
import runpy
import warnings

import dolfinx.mesh
import numpy as np
import pytest
from dolfinx.mesh import CellType
from mpi4py import MPI

from physicsrl.coordinated import Coordinator
from physicsrl.envs import load_config, make_env
from physicsrl.fem import resolution as guard
from physicsrl.fem.resolution import ResolutionWarning, cv_table
from tests.conftest import ROOT


@pytest.mark.parametrize("scheme", ["implicit", "explicit"])
def test_the_report_grid_reads_its_row_of_the_table(scheme):
    """60 x 60 cells of side 100/60: h is the cell diagonal, the width sqrt(0.013 * 0.3), and
    the expected CV error is the table's entry for that ratio (a row of the table)."""
    mesh = physicsrl.fem.default_ms_mesh(n=60)
    r = guard.resolution(mesh, 0.013, 0.3, scheme, 0.03)
    assert r.h == pytest.approx(math.sqrt(2) * 100 / 60, rel=1e-12)
    assert r.front_width == pytest.approx(math.sqrt(0.0039), rel=1e-12)
    ratios, errors = cv_table(scheme)
    row = np.argmin(abs(np.log(ratios / r.ratio)))
    assert ratios[row] == pytest.approx(r.ratio, rel=1e-4)
    assert r.cv_error == pytest.approx(errors[row], abs=1e-4)
    assert str(r).count("\n") == 0 and f"{r.cv_error:+.1%}" in str(r)
    assert not r.uncovered and "not in the table" not in str(r)


def test_what_the_table_does_not_cover_is_named_and_warned():
    """A dt longer than the table's longest, a mesh coarser than its coarsest row and a cell
    type it has no rows for (tetrahedra) are named in the report and warned about: the table's
    number is then a lower bound (coarser) or unmeasured (dt, cell type), even where it is
    below 5 % (h = 0.2: +4.9 %). A shorter dt is covered: its error is interpolated linearly
    in dt between the table's steps. Triangles have rows of their own: at h = 0.2 a front
    along their hypotenuses is +12 % off, and the report says so and warns."""
    fine = 100 / 500  # cell side of 500 x 500 on [-50, 50]^2: h/width 4.53
    for cells, cell_type, dt, reason in [
        (40, "quadrilateral", 0.5, "dt = 0.5, its longest is 0.03"),
        (1, "quadrilateral", 0.03, "h/width above its coarsest 37.7"),
    ]:
        side = fine * 40 if cells == 40 else 5.0  # the one-cell mesh: h/width 114
        mesh = dolfinx.mesh.create_rectangle(
            MPI.COMM_WORLD, [[0, 0], [side, side]], [cells, cells], getattr(CellType, cell_type)
        )
        r = guard.resolution(mesh, 0.013, 0.3, "implicit", dt)
        assert r.uncovered == (reason,)
        assert reason in str(r) and reason in r.warning and "\n" not in r.warning
    coarsest = f"{cv_table('implicit')[1][-1]:+.1%} or worse"
    assert coarsest in str(r) and coarsest in r.warning
    cube = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 1, 1]], [4, 4, 4])
    r = guard.resolution(cube, 0.013, 0.3, "implicit", 0.03)
    assert "tetrahedron cells, it has quadrilaterals and triangles" in r.uncovered
    quads, triangles = (
        dolfinx.mesh.create_rectangle(MPI.COMM_WORLD, [[0, 0], [8, 8]], [n, n], cells)
        for n, cells in ((60, CellType.quadrilateral), (40, CellType.triangle))
    )
    r = guard.resolution(quads, 0.013, 0.3, "implicit", 0.01)  # h/width 3.02: a row
    rows = [cv_table("implicit", dt=dt)[1][3] for dt in (0.0075, 0.015)]
    assert r.warning is None and r.cv_error == pytest.approx(
        np.interp(0.01, [0.0075, 0.015], rows), abs=1e-4
    )
    r = guard.resolution(triangles, 0.013, 0.3, "implicit", 0.03)
    assert not r.uncovered
    assert r.cv_error == pytest.approx(cv_table("implicit", "triangle")[1][4], abs=1e-4)
    assert 0.11 < r.cv_error < 0.13 and "+12.1%" in r.warning


def build(capsys, *overrides_per_env):
    """The ResolutionWarnings and output of building one ATP env per list of overrides, in
    one process under Python's default warning filter."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for overrides in overrides_per_env:
            make_env(load_config("ms", overrides=overrides), Coordinator())
    return [w for w in caught if issubclass(w.category, ResolutionWarning)], capsys.readouterr()


def test_the_report_preset_warns_once_and_a_resolved_mesh_not(capsys):
    """Building the report's 60 x 60 ATP env prints its resolution and warns (one line),
    under Python's default filter not again for a second such env but again for another
    mesh; a resolved mesh (h = 0.1, explicit: -2 % expected) prints and does not warn, nor
    does the 60 x 60 env with env.model.warn_resolution=false."""
    quiet = ["env.model.warn_resolution=false"]
    resolved = [
        "env.mesh.cells=20",
        "env.mesh.extent=1.0",
        "env.model.scheme=explicit",
        "observation.distances=[0.75,0.65,0.35,0.25]",
    ]
    caught, out = build(capsys, resolved)
    assert not caught and "expected planar CV error -2.2%" in out.out
    caught, _ = build(capsys, quiet)
    assert not caught
    caught, out = build(capsys, [], [], ["env.mesh.cells=50"])
    assert len(caught) == 2 and "\n" not in str(caught[0].message)
    assert "h/width = 37.7" in str(caught[0].message)
    assert "h/width = 45.3" in str(caught[1].message)
    assert out.out.count("resolution: h = 2.36") == 2


def test_a_front_speed_with_a_step_longer_than_its_sampling_interval_ends():
    """``planar_front_speed`` samples every 0.5 time units, or every dt when dt is longer: with
    dt = 1.5 it returns (it used to advance by 0 forever); the front, stepped that coarsely,
    dies."""
    assert guard.planar_front_speed(0.25, 1.5, length=4.0, T=20.0) == 0.0


def test_the_error_at_a_grid_and_step_is_the_tables_row_at_that_step():
    """``benchmarks/ms_cv.py --at``: at 2000 cells per side the explicit scheme's CV error at
    dt = 0.03 and at dt = 0.015 is the table's row of that step (h / width 1.13, written by the
    full benchmark), and smaller in magnitude at the shorter step."""
    module = runpy.run_path(str(ROOT / "benchmarks" / "ms_cv.py"))
    reference = module["speed"](0.01, 0.002, "implicit")
    measured = module["errors_at"]([(2000, 0.03), (2000, 0.015)], reference)
    for (ratio, error), dt in zip(measured, (0.03, 0.015), strict=True):
        ratios, errors = cv_table("explicit", dt=dt)
        (row,) = np.nonzero(np.isclose(ratios, ratio, rtol=1e-4))[0]
        assert error == pytest.approx(errors[row], abs=1e-5)
    assert measured[0][1] < measured[1][1] < 0
