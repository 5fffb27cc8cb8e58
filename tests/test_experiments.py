"""Experiment presets, local sweeps and their collection, and the Slurm launcher config."""

import csv
import subprocess
import sys
from pathlib import Path

from physicsrl.checkpoint import checkpoint_file, read
from tests.conftest import ROOT

TRAIN = str(Path(sys.executable).with_name("physicsrl-train"))
TINY = [
    "iterations=3",
    "collector.frames_per_batch=10",
    "optim.learning_starts=10",
    "eval.every=3",
    "eval.seeds=[1000000000,1000000001]",
    "logger.progress=false",
    "env.mesh.cells=8",
]


def compose(*overrides: str, section: str = "job") -> str:
    command = [TRAIN, "--cfg", section, *overrides]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_atp_presets_compose_with_the_report_figures():
    job = compose("+experiment=atp")
    assert "name: atp" in job and "name: catheter" in job and "iterations: 120" in job
    assert "inputs:\n    - observation\n    - step" in job and "n_steps: 8" in job
    wide = compose("+experiment=atp_wide")
    assert "- -20.0\n    - 20.0" in wide  # the wider placement of the reset stimulus
    assert "iterations: 120" in wide and "n_steps: 8" in wide  # the rest from the atp preset


def test_slurm_launcher_config_composes_one_mpi_job_per_sweep_job():
    hydra = compose("+cluster=slurm", section="hydra")
    assert "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher" in hydra
    assert "tasks_per_node: 8" in hydra
    assert "export SLURM_MPI_TYPE=pmix" in hydra


def test_local_sweep_runs_two_jobs_and_collects_one_table(tmp_path):
    """The issue's sweep form (agent.lr, here 2 jobs): own run dirs, Adam at each job's lr."""
    sweep = tmp_path / "sweep"
    result = subprocess.run(
        [TRAIN, "-m", "agent.lr=1e-3,3e-4", *TINY, f"hydra.sweep.dir={sweep}"],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1"]
    for job, lr in (("0", 1e-3), ("1", 3e-4)):
        optimizer = read(checkpoint_file(sweep / job), ["optimizer"])["optimizer"]
        assert optimizer["param_groups"][0]["lr"] == lr
    table = tmp_path / "table.csv"
    subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "collect.py"), str(sweep), "--csv", str(table)],
        check=True,
        capture_output=True,
        timeout=60,
    )
    rows = list(csv.DictReader(table.open()))
    assert [row["overrides"].split()[0] for row in rows] == ["agent.lr=0.001", "agent.lr=0.0003"]
    assert all(float(row["train_s"]) > 0 for row in rows)


def test_atp_baselines_script_tables_each_policy(tmp_path):
    """The baseline script on a small ATP preset: one row per policy, shocks as scheduled."""
    script = ROOT / "experiments" / "atp_baselines.py"
    small = ["env.mesh.cells=20", "env.max_decisions=4", "env.extra_waits=2"]
    command = [sys.executable, str(script), "--seeds", "2", "--select-seeds", "1"]
    command += ["--policies", "never,always,single", "--out", str(tmp_path), *small]
    subprocess.run(command, check=True, capture_output=True, timeout=300, cwd=tmp_path)
    rows = {r["policy"]: r for r in csv.DictReader((tmp_path / "atp_baselines.csv").open())}
    assert list(rows)[:2] == ["never shock", "always shock"] and len(rows) == 3
    assert float(rows["never shock"]["shocks"]) == 0 and float(rows["always shock"]["shocks"]) == 4
    single = next(r for name, r in rows.items() if name.startswith("best single shock"))
    assert float(single["shocks"]) <= 1
    assert "commit" in (tmp_path / "atp_baselines.txt").read_text()


def test_stored_atp_agent_reproduces_its_row_of_the_results_table(tmp_path):
    """The stored ATP policy (experiments/results/atp_agent.torchrl) on the first held-out seed, on
    2 MPI ranks: the return, success and shocks of that seed's row in atp_agent_eval.csv (made
    on 1 rank), so the table is reproducible and does not depend on the number of ranks."""
    from tests.conftest import MPIEXEC

    results = ROOT / "experiments" / "results"
    out = tmp_path / "eval"
    command = [str(MPIEXEC), "-n", "2", str(Path(sys.executable).with_name("physicsrl-eval"))]
    command += [f"run={results / 'atp_agent.torchrl'}", "seeds=1", "baselines=false", "gif=false"]
    command += ["curve=false", f"hydra.run.dir={out}"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    (row,) = csv.DictReader((out / "eval.csv").open())
    stored = next(csv.DictReader((results / "atp_agent_eval.csv").open()))
    assert row["seed"] == stored["seed"]
    for key in ("return", "success", "shocks"):
        assert float(row[key]) == float(stored[key]), key
