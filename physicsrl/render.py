"""Pictures of one greedy episode of a physics task, for ``physicsrl-eval``: an animated GIF
of the field after the reset and after each decision (:func:`episode_gif`), and the fields as
a VTX series for ParaView, read back (:func:`record_fields`). Leader only, inside ``with
coordinator``: each frame is one parallel call that gathers or writes the field."""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from matplotlib.tri import Triangulation

from physicsrl.evaluation import episode
from physicsrl.fem.output import Series, read_series


def record_fields(env, policy, seed: int, recorder) -> Series:
    """Play one greedy episode of ``env`` from ``seed``, writing the fields with ``recorder``
    after the reset and after each decision that advanced the simulation time; close the series
    and read it back (leader only, inside ``with coordinator``)."""
    simulator = vars(env)["task"].simulator
    times: list[float] = []

    def write(*_) -> None:
        if not times or simulator.t > times[-1]:
            times.append(simulator.t)
            recorder.write(simulator.t)

    episode(env, policy, seed, callback=write)
    write()  # the rollout stops at the end of the episode before its callback
    recorder.close()
    return read_series(recorder.path)


def episode_gif(env, policy, seed: int, path: Path, fps: float = 1.5) -> dict:
    """Play one greedy episode and write a GIF: the field after the reset and after each
    decision, catheter electrodes (if any), shock moments marked. Leader only, inside
    ``with coordinator`` (one parallel call per frame gathers the field)."""
    task = vars(env)["task"]
    frames = []
    rollout = episode(env, policy, seed, callback=lambda *_: frames.append(task.field()))
    actions = [int(a) for a in rollout["action"].reshape(-1)]
    rewards = rollout["next", "reward"].reshape(-1).tolist()
    points = frames[0][0]
    triangulation = Triangulation(points[:, 0], points[:, 1])
    low = min(float(f[1].min()) for f in frames)
    high = max(float(f[1].max()) for f in frames)
    positions = getattr(task.observation, "positions", None)
    electrodes = positions() if callable(positions) else None
    shock = getattr(task.config, "shock", None)
    images = []
    for i, (_, values, integral) in enumerate(frames):
        figure = Figure(figsize=(4.2, 4.4))
        canvas = FigureCanvasAgg(figure)
        ax = figure.subplots()
        ax.tripcolor(triangulation, values, shading="gouraud", vmin=low, vmax=high, cmap="inferno")
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        if electrodes is not None:
            ax.plot(*np.asarray(electrodes).T, "o", color="cyan", markersize=2.5)
        action = actions[i - 1] if i else None
        marked = action == 1 and shock is not None
        if marked:
            ax.add_patch(Circle(shock.centre, shock.radius, fill=False, color="red", ls="--", lw=2))
        done = sum(rewards[:i])
        title = (
            "reset" if i == 0 else f"decision {i}: action {action}" + (" SHOCK" if marked else "")
        )
        ax.set_title(
            f"{task.name} seed {seed}, {title}\nintegral {integral:.1f}, return so far {done:.2f}",
            fontsize=8,
            color="red" if marked else "black",
        )
        figure.tight_layout()
        canvas.draw()
        images.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    imageio.mimsave(path, images, duration=1000.0 / fps, loop=0)
    return {"actions": actions, "rewards": rewards}
