"""Checkpoints that cannot be written or read: a truncated newest checkpoint is skipped on
resume (and a resume without a readable one is one line), a checkpoint directory that cannot
be written is found when the run starts, a full disk during training stops the run cleanly with
its older checkpoints intact and no temporary files, and a resume into another directory writes
only into the resumed run.

The runs train the toy chain of ``tests/mpi_scripts/train_toy_env.py`` for a few iterations.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import zipfile
from functools import partial

import pytest
import torch
from torchrl.checkpoint import Checkpoint

from physicsrl.checkpoint import Checkpoints, damage, read
from physicsrl.config import as_dict, train_config
from physicsrl.envs import load_config
from physicsrl.learner import resume_point
from physicsrl.run_directory import checkpoint_path, find_run, is_checkpoint
from tests.conftest import MPIEXEC, ROOT, together
from tests.test_train import (
    TOY,
    TRAIN,
    checkpoint_name,
    run,
    same,
    start_and_wait_for,
    timeless,
    written,
)

SHORT = [
    f"+env.factory={TOY}:make_env",
    "iterations=6",
    "collector.frames_per_batch=8",
    "optim.learning_starts=16",
    "optim.updates_per_batch=1",
    "eval.every=0",
    "eval.baselines=false",
    "checkpoint.every=2",
    "checkpoint.keep=3",
    "logger.progress=false",
    "logger.tensorboard=false",
]


def truncate(path, fraction: float = 0.5) -> None:
    path.write_bytes(path.read_bytes()[: int(path.stat().st_size * fraction)])


def test_resume_finds_the_run_with_the_newest_checkpoint_or_names_what_has_none(tmp_path):
    """``resume=true``: of the runs beside this one, the one whose newest checkpoint was written
    last (not the newest run, nor the one with the most iterations); a run directory or one of
    its checkpoint files: that run; a directory without checkpoints: one line naming it, and
    its jobs where it holds a sweep's runs (as ``physicsrl-eval run=`` does)."""
    runs = tmp_path / "outputs"
    for age, (name, iteration) in enumerate([("b", 8), ("c", 2), ("a", 4)]):  # a: written last
        checkpoint = runs / name / "checkpoints" / checkpoint_name(iteration)
        checkpoint.parent.mkdir(parents=True)
        checkpoint.write_bytes(b"")
        os.utime(checkpoint, (1_000_000 + age, 1_000_000 + age))
    (runs / "d" / ".hydra").mkdir(parents=True)  # a run that wrote no checkpoint: never chosen
    assert find_run("true", runs) == find_run("True", runs) == runs / "a"
    assert find_run(str(runs / "c"), runs) == runs / "c"
    assert find_run(str(runs / "b" / "checkpoints" / checkpoint_name(8)), runs) == runs / "b"
    with pytest.raises(FileNotFoundError, match=r"resume=.*/d: no checkpoint under .*/d/check"):
        find_run(str(runs / "d"), runs)
    with pytest.raises(FileNotFoundError, match="resume=true: no run with a checkpoint under"):
        find_run("true", runs / "d")
    sweep = re.escape("; a sweep: name one of its jobs (a, b, c)")
    with pytest.raises(
        FileNotFoundError, match=rf"resume=.*/outputs: no checkpoint under .*{sweep}$"
    ):
        find_run(str(runs), tmp_path)
    with pytest.raises(ValueError, match=rf"run=.*/outputs: no checkpoint file there .*{sweep}$"):
        checkpoint_path(str(runs))


def test_a_checkpoint_file_is_told_without_torch_as_torchrl_tells_it(tmp_path):
    """:func:`~physicsrl.run_directory.is_checkpoint` (``physicsrl-eval``'s check on every
    rank, before torch loads) agrees with TorchRL's ``Checkpoint.is_checkpoint`` on an archive,
    the same archive truncated to its first half (its manifest, at the end, is lost), a ZIP
    without a manifest, a ZIP whose manifest names another format, a text file and an empty
    file; ``checkpoint_path`` refuses the others in one line naming ``run``."""
    from torchrl.checkpoint import Checkpoint, JSONCheckpointAdapter

    archive = tmp_path / "ckpt.torchrl"
    Checkpoint().register("extra", {}, adapter=JSONCheckpointAdapter()).save(
        archive, format="archive"
    )
    truncated = tmp_path / "truncated.torchrl"
    truncated.write_bytes(archive.read_bytes()[: archive.stat().st_size // 2])
    others = {"truncated": truncated}
    for name, members in (("bare", {"x.json": "{}"}), ("other", {"manifest.json": '{"a": 1}'})):
        with zipfile.ZipFile(tmp_path / name, "w") as written_zip:
            for member, text in members.items():
                written_zip.writestr(member, text)
        others[name] = tmp_path / name
    others["text"] = tmp_path / "passwd"
    others["text"].write_text("root:x:0:0\n")
    others["empty"] = tmp_path / "empty"
    others["empty"].write_bytes(b"")
    assert is_checkpoint(archive) and Checkpoint.is_checkpoint(archive)
    assert checkpoint_path(str(archive)) == archive
    for name, path in others.items():
        assert is_checkpoint(path) is Checkpoint.is_checkpoint(path) is False, name
        with pytest.raises(ValueError, match=rf"run=.*{path.name} is not a checkpoint file"):
            checkpoint_path(str(path))


def test_resume_skips_a_truncated_checkpoint_and_writes_only_into_the_resumed_run(tmp_path):
    """The newest of 3 checkpoints truncated: one warning naming it, the run resumes from the
    one before in its own directory and reproduces the lost checkpoint bit for bit; the
    resuming command's directory holds only its config, its log and ``resumed.txt``. A resume
    by a job of 2 environments (the run had 1; ``env.factory``'s, known once built): one line
    naming both, no ``resumed.txt``. All three truncated (in a copy of the run): one line
    naming them, exit status 2. The three refused resumes run at the same time."""
    first, second = tmp_path / "first", tmp_path / "second"
    result = run([TRAIN, *SHORT, f"hydra.run.dir={first}"], tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    checkpoints = Checkpoints(first / "checkpoints", keep=3)
    assert [p.name for p in checkpoints.paths()] == [checkpoint_name(i) for i in (2, 4, 6)]
    copy = tmp_path / "copy"
    shutil.copytree(first, copy)
    copied = Checkpoints(copy / "checkpoints", keep=3)
    for path in copied.paths():
        truncate(path, 0.9)
    newest = checkpoints.latest()
    original = read(newest)
    truncate(newest)
    assert damage(newest) is not None

    result = run([TRAIN, *SHORT, f"hydra.run.dir={second}", f"resume={first}"], tmp_path)
    assert result.returncode == 0, result.stdout + result.stderr
    warnings = [line for line in result.stdout.splitlines() if "unreadable checkpoint" in line]
    assert len(warnings) == 1 and str(newest) in warnings[0], result.stdout
    log = (first / "train.log").read_text()
    assert f"resumed from {checkpoints.directory / checkpoint_name(4)} at iteration 4" in log
    repeated = read(newest)
    for name in ("q_network", "loss", "optimizer", "exploration"):
        assert same(repeated[name], original[name]), name
    assert same(written(repeated["replay_buffer"]), written(original["replay_buffer"]))
    assert timeless(repeated["history"]) == timeless(original["history"])
    assert {k: v for k, v in repeated["counters"].items() if k != "time_s"} == {
        k: v for k, v in original["counters"].items() if k != "time_s"
    }
    assert sorted(p.name for p in second.iterdir()) == [".hydra", "resumed.txt", "train.log"]
    assert str(first) in (second / "resumed.txt").read_text()
    with pytest.raises(ValueError, match=f"checkpoints/; this command resumed {first} from"):
        checkpoint_path(str(second))  # physicsrl-eval run=<the resuming command's directory>

    mismatched = [str(MPIEXEC), "-n", "2", TRAIN, *SHORT, "mpi.ranks=2", f"resume={first}"]
    mismatched += [f"hydra.run.dir={tmp_path / 'two'}"]
    # another task: refused before anything is built (it trained the other task on the run's
    # buffer and network, warning about each setting)
    other = [TRAIN, *SHORT, "env=ms", f"resume={first}", f"hydra.run.dir={tmp_path / 'other'}"]
    unreadable = [TRAIN, *SHORT, f"hydra.run.dir={tmp_path / 'third'}", f"resume={copy}"]
    refused = together(
        *(partial(run, arguments, tmp_path) for arguments in (mismatched, other, unreadable))
    )
    assert_refused(
        refused[0],
        "error: the checkpoint's run had 1 environment(s), this job has 2 (mpi.ranks / "
        "mpi.ranks_per_env, times env.replicas): resume with the same number",
    )
    assert not (tmp_path / "two" / "resumed.txt").exists()
    assert_refused(
        refused[1],
        "error: resume: env.name=atp where the checkpoint's run has heat: a resume goes on with "
        "the run's task and Q-network (give its +experiment, or its env, observation, reward and "
        "agent.network)",
    )
    assert_refused(
        refused[2],
        f"error: no readable checkpoint in {copied.directory}: "
        + ", ".join(checkpoint_name(i) for i in (6, 4, 2)),
    )


def assert_refused(result, line: str) -> None:
    """Exit status 2 and this one line, nothing else on stderr and no traceback."""
    assert (result.returncode, result.stderr.splitlines()) == (2, [line]), result.stdout
    assert "Traceback" not in result.stdout


@pytest.mark.parametrize(
    ("task", "replicas", "stored", "refused"),
    [("heat", None, 2, True), ("ms", 3, 3, False), ("ms", 3, 1, True)],
)
def test_a_resume_by_another_number_of_environments_is_refused_before_any_env_is_built(
    tmp_path, task, replicas, stored, refused
):
    """A task's environments are known from the config (groups x ``env.replicas``): a resume
    whose job (1 rank here) has another number than the checkpoint's run had is refused by
    :func:`~physicsrl.learner.resume_point`, before the env is built; the same number resumes."""
    groups = load_config(task, seed=0)
    if replicas:
        groups["env"]["model"]["backend"], groups["env"]["replicas"] = "torch", replicas
    config = train_config({**groups, "resume": str(tmp_path / "run")})
    extra = {"config": as_dict(config), "environments": stored}
    checkpoints = Checkpoints(tmp_path / "run" / "checkpoints", 1)
    checkpoints.save(Checkpoint(format="archive", extra=extra, replay_buffer=[]), 3)
    if refused:
        with pytest.raises(ValueError, match=rf"had {stored} environment\(s\), this job has "):
            resume_point(config, tmp_path / "new")
    else:
        assert resume_point(config, tmp_path / "new").name == checkpoint_name(3)


def test_a_resume_of_another_network_or_of_a_policy_is_refused_before_any_env_is_built(tmp_path):
    """A resume that changes the Q-network's shape (``agent.network.hidden``), or of a stored
    policy (``q_network``, ``counters`` and ``extra`` only, as ``experiments/results/`` keeps
    them), is refused by :func:`~physicsrl.learner.resume_point` in one line naming it."""
    config = train_config({**load_config("heat", seed=0), "resume": str(tmp_path / "run")})
    old = as_dict(config)
    old["agent"]["network"]["hidden"] = [32]
    checkpoints = Checkpoints(tmp_path / "run" / "checkpoints", 1)
    checkpoints.save(Checkpoint(format="archive", extra={"config": old}, replay_buffer=[]), 3)
    with pytest.raises(
        ValueError, match=r"hidden=\[64, 64\] where the checkpoint's run has \[32\]"
    ):
        resume_point(config, tmp_path / "new")
    policy = Checkpoint(format="archive", q_network={}, counters={}, extra={"config": old})
    path = checkpoints.save(policy, 4)
    with pytest.raises(ValueError, match=f"resume: {path} holds a policy, not a training run's"):
        resume_point(config, tmp_path / "new")


def test_a_resume_whose_observation_has_another_size_is_one_line(tmp_path, capsys):
    """The toy's observation made 4 numbers (two frames) where its checkpoint's network reads 2:
    the resume's load ends with status 2 and one line naming the shapes (a 20-line traceback
    before)."""
    sys.path.insert(0, str(TOY.parent))
    from torchrl.envs import CatFrames, TransformedEnv
    from train_toy_env import ToyChainEnv

    from physicsrl.coordinated import Coordinator
    from physicsrl.learner import make_dojo, train_on_leader

    config = train_config({"env": {"factory": f"{TOY}:make_env"}, "resume": True})
    env = ToyChainEnv(Coordinator(), length=3)
    path = make_dojo(config, env, log_dir=tmp_path / "run").save_checkpoint()
    frames = TransformedEnv(env, CatFrames(2, dim=-1, in_keys=["observation"]))
    with pytest.raises(SystemExit) as exit_:
        train_on_leader(config, frames, tmp_path / "new", path)
    assert exit_.value.code == 2
    [line] = capsys.readouterr().err.splitlines()
    assert line.startswith("error: bad config: resume=True: the stored weights do not fit"), line
    assert "torch.Size([64, 2]) from checkpoint" in line and "torch.Size([64, 4])" in line, line


def test_a_checkpoint_directory_that_cannot_be_written_is_one_line_at_the_start(tmp_path):
    """``checkpoints`` taken by a regular file (unwritable even for root): under 2 ranks, one
    line naming it, exit status 2, before any environment is built or iteration run."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "checkpoints").write_text("not a directory")
    command = [str(MPIEXEC), "-n", "2", TRAIN, *SHORT, "mpi.ranks=2", f"hydra.run.dir={run_dir}"]
    result = run(command, tmp_path)
    assert_refused(
        result, f"error: cannot write checkpoints to {run_dir / 'checkpoints'}: File exists"
    )
    assert "environment" not in (run_dir / "train.log").read_text()  # nothing was built


def test_a_full_disk_stops_training_with_the_older_checkpoints_intact(tmp_path):
    """Saves fail from iteration 6 on (a file-size limit of half a checkpoint): the run stops
    there naming the directory, checkpoints 2 and 4 are intact and nothing else is left."""
    script = ROOT / "tests" / "mpi_scripts" / "dojo_full_disk.py"
    result = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "run")],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=script.parent,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    outcome = json.loads(result.stdout.splitlines()[-1])
    directory = tmp_path / "run" / "checkpoints"
    assert outcome["stopped"] == f"cannot write checkpoints to {directory}: File too large"
    assert outcome["iteration"] == 6
    assert outcome["files"] == [checkpoint_name(2), checkpoint_name(4)]  # no temporary files
    assert all(damage(directory / name) is None for name in outcome["files"])
    assert read(directory / checkpoint_name(4), ["counters"])["counters"]["iteration"] == 4


@pytest.mark.skipif(
    os.geteuid() == 0 and not shutil.which("capsh"), reason="root writes anywhere without capsh"
)
def test_a_checkpoint_directory_made_read_only_during_training_stops_the_run(tmp_path):
    """``chmod 555 checkpoints`` once a checkpoint is written (as root, with the capability
    that overrides file permissions dropped): the run stops at its next save, exit status 1,
    one line naming the directory and no traceback; its checkpoints are intact."""
    run_dir = tmp_path / "run"
    arguments = [TRAIN, *SHORT, "iterations=100000", f"hydra.run.dir={run_dir}"]
    if os.geteuid() == 0:
        arguments = ["capsh", "--drop=cap_dac_override", "--", "-c", shlex.join(arguments)]
    directory = run_dir / "checkpoints"
    process = start_and_wait_for(arguments, tmp_path, directory / checkpoint_name(2))
    directory.chmod(0o555)
    try:
        output, _ = process.communicate(timeout=120)
    finally:
        directory.chmod(0o755)
    assert process.returncode == 1, output
    assert "Traceback" not in output
    stops = [line for line in output.splitlines() if "stopped at iteration" in line]
    assert len(stops) == 1, output
    assert stops[0].endswith(f"cannot write checkpoints to {directory}: Permission denied")
    checkpoints = Checkpoints(directory, keep=3).paths()
    assert checkpoints and all(damage(path) is None for path in checkpoints)


def test_read_returns_the_states_the_dojo_saved(tmp_path):
    """``read`` of a saved checkpoint: the Q-network's tensors and the JSON values as saved."""
    sys.path.insert(0, str(TOY.parent))
    from train_toy_env import ToyChainEnv

    from physicsrl.builders import make_q_network
    from physicsrl.config import LoggerConfig, Network, TrainConfig
    from physicsrl.coordinated import Coordinator
    from physicsrl.dojo import Dojo

    env = ToyChainEnv(Coordinator(), length=3)
    config = TrainConfig(logger=LoggerConfig(tensorboard=False, progress=False))
    q_network = make_q_network(env, Network(hidden=[4]))
    dojo = Dojo(q_network, env, config, log_dir=tmp_path, checkpoint_extra={"config": {"seed": 7}})
    path = dojo.save_checkpoint()
    state = read(path)
    assert state["extra"] == {"config": {"seed": 7}} and state["history"] == []
    assert state["counters"]["iteration"] == 0
    for key, value in dojo.q_network.state_dict().items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(state["q_network"][key], value), key
